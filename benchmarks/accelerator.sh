#!/usr/bin/env bash
# The benchmark tables on an accelerator, as one run of about 12 minutes (an NVIDIA H100:
# propagation ~5, preintegration ~2, Monte Carlo ~2, the chunk crossover ~2 minutes; each
# step has its own time limit, so a slow one cannot take the others' time).
#
#   bash benchmarks/accelerator.sh          # from the repository root
#
# Writes benchmarks/results/{propagation,preintegration,montecarlo,dispatch-ab}-<machine>.json
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
# every row of the table, the one-recording rows (time chunks) among them; no case over 20 s
run 330 python benchmarks/propagation.py --max-case-s 20
run 150 python benchmarks/preintegration.py
run 120 python benchmarks/montecarlo.py
# where the covariance's time chunks pay for one trajectory (256 to 10^5 steps), and the
# mean's long sequences, against the sequential kernels
run 150 env VARIANTS=new,sequential ONLY="cov analytic euler final 1x" BUDGET=130 python benchmarks/dispatch_ab.py
if [ -n "${OUT:-}" ]; then
  find "$RES" -newer "$MARK" -name '*.json' -exec cp -v {} "$OUT"/ \;
fi
rm -f "$MARK"
