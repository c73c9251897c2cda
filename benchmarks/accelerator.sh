#!/usr/bin/env bash
# The benchmark tables on an accelerator, as one run of at most 10.5 minutes (an NVIDIA
# H100 is lent for 15 minutes in all, its start-up included): propagation ~4 (5 at most),
# preintegration and Monte Carlo (quick: 2000 runs) under 1.5 each, the time chunks'
# crossover 2.5. Each step has its own time limit, so a slow one cannot take the others'
# time (a step cut by its limit writes no JSON but the crossover's, written as it goes; the
# printed lines are in the log).
#
#   bash benchmarks/accelerator.sh          # from the repository root
#
# Writes benchmarks/results/{propagation,preintegration,montecarlo,chunk-crossover}-<machine>.json
# (each script names its file after the device) and, when $OUT is set (the device machine's
# folder that comes back), copies them and the printed tables there.
set -u
cd "$(dirname "$0")/.."
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
RES=benchmarks/results
LOG=${OUT:-$RES}/accelerator-run.txt
mkdir -p "$RES" "$(dirname "$LOG")"
MARK=$(mktemp)  # the results written after it are this run's
run() {  # run LIMIT_S COMMAND...: one step, its output in the log
  local limit=$1; shift
  echo "=== $* (limit ${limit} s)" | tee -a "$LOG"
  timeout "$limit" "$@" 2>&1 | tee -a "$LOG"
  echo "=== exit ${PIPESTATUS[0]}" | tee -a "$LOG"
}
python -c "import jax; print(jax.devices(), jax.__version__)" 2>&1 | tee -a "$LOG"
# where the time chunks beat sequential launches, by length and batch (the dispatch table's
# MEAN_CHUNK_STEPS, MEAN_CHUNK_LANES, COV_CHUNK_STEPS, COV_CHUNK_LANES), first: the figures
# the table still lacks; its budget stops starting cases, a case's compile may overrun it
run 150 env BUDGET=115 python benchmarks/chunk_crossover.py
# every row of the table, the one-recording rows (time chunks) among them; no case over 20 s
run 300 python benchmarks/propagation.py --max-case-s 20
run 90 python benchmarks/preintegration.py
run 80 python benchmarks/montecarlo.py --quick
if [ -n "${OUT:-}" ]; then
  find "$RES" -newer "$MARK" -name '*.json' -exec cp -v {} "$OUT"/ \;
fi
rm -f "$MARK"
