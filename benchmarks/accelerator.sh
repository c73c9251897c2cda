#!/usr/bin/env bash
# The benchmark tables on an accelerator, as one run of at most 9.2 minutes (an NVIDIA H100
# is lent for 15 minutes in all, its start-up included, and one command may run 10): a
# smoke check first (the run stops there if jaximu cannot run on the device), the time
# chunks' crossover (about 2 minutes), propagation (4), preintegration (about 1.7) and
# Monte Carlo (quick: 2000 runs, 1). Each step has its own time limit, so a slow one cannot
# take the others' time; propagation stops starting cases in time to write its JSON (on the
# H100 its 71 cases take about 6.5 minutes, compile-bound: finish the table in a second
# call on the warm machine with `python3 benchmarks/propagation.py --first N --out ...`,
# N the first case not run, as the log says).
#
#   bash benchmarks/accelerator.sh          # from the repository root
#   bash benchmarks/accelerator.sh studies  # the studies' and the training's tables instead
#   DATA="d1 d2 ..." bash benchmarks/accelerator.sh studies   # with the training recordings
#
# `studies` (one call of at most 9 minutes): the smoke check, then
# benchmarks/studies_device.py (Monte Carlo at 10^4/10^5/10^6 runs, the filter study, the
# Monte Carlo route's chunk × unroll sweep, `jaximu calibrate` on the bundled excerpt; each
# row beside the committed CPU figures), then, when DATA names the training recordings'
# folders (carried to the device: they are not in the repository), benchmarks/learning.py
# with the whole `jaximu learn train` (its step against PyTorch where torch is installed).
#
# Writes benchmarks/results/{propagation,preintegration,montecarlo,chunk-crossover}-<machine>.json
# (each script names its file after the device) and, when $OUT is set (the device machine's
# folder that comes back), copies them and the printed tables there.
set -u
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}  # the device image's Python is python3 (no plain python there)
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
RES=benchmarks/results
LOG=${OUT:-$RES}/accelerator-run.txt
mkdir -p "$RES" "$(dirname "$LOG")"
MARK=$(mktemp)  # the results written after it are this run's
run() {  # run LIMIT_S COMMAND...: one step, its output in the log
  local limit=$1; shift
  echo "=== $* (limit ${limit} s)" | tee -a "$LOG"
  timeout "$limit" "$@" 2>&1 | tee -a "$LOG"
  local rc=${PIPESTATUS[0]}
  echo "=== exit $rc" | tee -a "$LOG"
  return "$rc"
}
# smoke: jaximu imports and runs one covariance on the device, or nothing else is worth the time
run 60 "$PY" -c "
import jax, jax.numpy as jnp, jaximu
print(jax.devices(), jax.__version__, jax.default_backend())
T = 4096
out = jaximu.propagate_covariance_final(
    jaximu.NavState.identity(), jnp.eye(15) * 1e-4, jnp.full((T, 3), 0.1), jnp.tile(jnp.array([0., 0., 9.8]), (T, 1)),
    0.005, jaximu.ImuNoise.euroc())
print('ok', jax.tree_util.tree_map(lambda x: x.shape, out))
" || { echo "smoke failed: stopping" | tee -a "$LOG"; exit 1; }
if [ "${1:-tables}" = studies ]; then
  CPU_REF=$(ls "$RES"/studies-device-*cpu.json 2>/dev/null | head -n 1)
  run 300 "$PY" benchmarks/studies_device.py --sweep --deadline 240 \
    --calibrate tests/data/euroc_v1_02_medium ${CPU_REF:+--cpu "$CPU_REF"}
  if [ -n "${DATA:-}" ]; then
    # shellcheck disable=SC2086  # DATA is a list of folders
    run 170 "$PY" benchmarks/learning.py --data $DATA --quick --torch-compile --full-training --train-minutes 2
  fi
  if [ -n "${OUT:-}" ]; then
    find "$RES" -newer "$MARK" -name '*.json' -exec cp -v {} "$OUT"/ \;
  fi
  rm -f "$MARK"
  exit 0
fi
# where the time chunks beat sequential launches, by length and batch (the dispatch table's
# MEAN_CHUNK_STEPS, MEAN_CHUNK_LANES, COV_CHUNK_STEPS, COV_CHUNK_LANES), first: the figures
# the table still lacks; its budget stops starting cases, a case's compile may overrun it
run 110 env BUDGET=80 "$PY" benchmarks/chunk_crossover.py
# every row of the table, the one-recording rows (time chunks) among them; no case over 15 s
run 240 "$PY" benchmarks/propagation.py --max-case-s 15 --deadline 195
run 110 "$PY" benchmarks/preintegration.py
run 60 "$PY" benchmarks/montecarlo.py --quick
if [ -n "${OUT:-}" ]; then
  find "$RES" -newer "$MARK" -name '*.json' -exec cp -v {} "$OUT"/ \;
fi
rm -f "$MARK"
