"""Monte Carlo studies and calibration on the machine's default device, beside a CPU's figures.

    python benchmarks/studies_device.py                     # studies at 10^4 / 10^5 / 10^6 runs
    python benchmarks/studies_device.py --sweep             # also the route's chunk × unroll grid
    python benchmarks/studies_device.py --cpu benchmarks/results/studies-device-intel-xeon-2cpu.json
    python benchmarks/studies_device.py --max-runs 100000 --calibrate DIR   # a CPU's quick table

Workloads (float32, the scenario of ``benchmarks/montecarlo.py``: GTSAM's level circle, 1000
samples at 200 Hz, EuRoC ADIS16448 noise):

* **open-loop study** (:func:`jaximu.montecarlo.monte_carlo`, ``record_every=100``) at 10^4,
  10^5 and 10^6 runs: the first call (compile included) and the best of the calls after it,
  with the device's peak memory (``memory_stats``) or the process's peak RSS on a CPU;
* **filter study**: a position fix every 10 samples (``update_every=10``, ``PositionFix``),
  every run propagating its own covariance, at 10^4 and 10^5 runs;
* **sweep** (``--sweep``): the study at 10^5 runs with each chunk size and unroll of the
  dispatch table's route (:data:`jaximu.engine._dispatch.MONTE_CARLO`) replaced, so that a
  device's figures can set its row (the results do not depend on them);
* **calibration** (``--calibrate DIR``): ``jaximu calibrate DIR`` (biases) and
  ``--estimate noise`` as commands, wall time of each (compile included: what a user waits).

With ``--cpu FILE`` (this script's JSON from a CPU) every row prints the CPU's figure beside
it and the ratio. Writes ``benchmarks/results/studies-device-<machine>.json``.
The training's figures (the whole ``jaximu learn train`` and its step against PyTorch) are
``benchmarks/learning.py``'s (``--full-training``).
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from propagation import machine_info, machine_slug  # noqa: E402  (same folder)

jax.config.update("jax_enable_x64", False)  # propagation.py turns it on: float32 here

import jaximu  # noqa: E402
from jaximu import simulate as sim  # noqa: E402
from jaximu.engine import _dispatch  # noqa: E402
from jaximu.montecarlo import PositionFix, monte_carlo  # noqa: E402

T, DT = 1000, 0.005


def peak_memory_mb():
    """Peak memory so far: the default device's (``memory_stats``) or, on a CPU, the
    process's high-water mark."""
    stats = jax.local_devices()[0].memory_stats() or {}
    if "peak_bytes_in_use" in stats:
        return stats["peak_bytes_in_use"] / 2**20
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 1024
    except (OSError, StopIteration):
        return float("nan")


def study(n_runs, reps, **kw):
    """(first call s, best later call s, result) of the benchmark's study."""
    args = (sim.circle(5.0, 2.0), np.arange(T + 1) * DT, np.eye(15) * 1e-8)
    noise = jaximu.ImuNoise.euroc()

    def call(seed):
        return monte_carlo(*args, noise, n_runs, jax.random.key(seed), n_keep=0, **kw)

    t0 = time.perf_counter()
    res = call(0)
    first = time.perf_counter() - t0
    best = float("inf")
    for r in range(reps):
        t0 = time.perf_counter()
        call(r + 1)
        best = min(best, time.perf_counter() - t0)
    return first, best, res


def row(case, n_runs, first, best, res, **extra):
    out = dict(
        case=case,
        runs=n_runs,
        samples=n_runs * T,
        first_s=first,
        run_s=best,
        rate=n_runs * T / best,
        nees=float(res.nees_mean[-1]),
        nees_bounds=[float(x) for x in res.nees_bounds],
        peak_mb=peak_memory_mb(),
        **extra,
    )
    if res.nis_mean is not None:
        out["nis"] = float(res.nis_mean[-1])
    return out


def sweep(n_runs, deadline, say):
    """The open-loop and filter studies at ``n_runs`` with each route setting."""
    on = _dispatch.backend()
    saved = _dispatch.MONTE_CARLO[on]
    rows = []
    grid = [(c, u, 1) for c in (1 << 15, 1 << 16, 1 << 17, 1 << 18) for u in (1, 2, 4, 8)]
    grid += [(saved.chunk_runs, saved.unroll, f) for f in (2, 4)]
    try:
        for chunk, unroll, funroll in grid:
            if time.perf_counter() > deadline:
                say(f"sweep: deadline reached before chunk {chunk} unroll {unroll}")
                break
            _dispatch.MONTE_CARLO[on] = saved._replace(
                chunk_runs=chunk, unroll=unroll, filter_unroll=funroll
            )
            kw = dict(record_every=100) if funroll == 1 else dict(update_every=10)
            first, best, res = study(n_runs, 1, dtype=jnp.float32, **kw)
            case = "open loop" if funroll == 1 else "filter"
            steps = unroll if funroll == 1 else funroll  # steps a loop iteration of this study
            rows.append(row(f"sweep {case}", n_runs, first, best, res, chunk=chunk, unroll=steps))
            say(
                f"sweep {case:>9}: chunk {chunk:>6} unroll {steps}: first {first:6.2f} s, "
                f"run {best:6.3f} s = {n_runs * T / best / 1e6:9.1f} M samples/s"
            )
    finally:
        _dispatch.MONTE_CARLO[on] = saved
    return rows


def calibrate(folder, say):
    """Wall time of ``jaximu calibrate`` (biases, then the noise fit) on ``folder``."""
    rows = []
    for case, extra in (("calibrate biases", []), ("calibrate noise", ["--estimate", "noise"])):
        cmd = [sys.executable, "-m", "jaximu", "calibrate", str(folder), *extra]
        t0 = time.perf_counter()
        out = subprocess.run(cmd, capture_output=True, text=True)
        secs = time.perf_counter() - t0
        ok = out.returncode == 0
        rows.append(dict(case=case, wall_s=secs, ok=ok, command=" ".join(cmd[1:])))
        say(f"{case}: {secs:.1f} s wall (compile included){'' if ok else ' FAILED'}")
        if not ok:
            say(out.stderr[-2000:])
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--max-runs", type=int, default=1_000_000, help="largest open-loop study")
    ap.add_argument("--sweep", action="store_true", help="the route's chunk × unroll grid")
    ap.add_argument("--calibrate", default=None, help="a sequence folder for jaximu calibrate")
    ap.add_argument("--cpu", default=None, help="this script's JSON from a CPU, printed beside")
    ap.add_argument("--deadline", type=float, default=420.0, help="seconds: start no case after")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    deadline = time.perf_counter() + args.deadline
    info = machine_info()
    route = _dispatch.monte_carlo_route()
    say = lambda *a: print(*a, flush=True)  # noqa: E731
    say(
        f"# {info['cpu_model'] if jax.default_backend() == 'cpu' else info.get('device_kind')}"
        f" ({jax.default_backend()}), load average {os.getloadavg()[0]:.1f}, "
        f"jax {jax.__version__}; Monte Carlo route {route}"
    )
    rows = []
    for n in (10_000, 100_000, 1_000_000):
        if n > args.max_runs or time.perf_counter() > deadline:
            continue
        first, best, res = study(n, 2 if n < 1_000_000 else 1, dtype=jnp.float32, record_every=100)
        rows.append(row("open loop", n, first, best, res))
        say(
            f"open loop {n:>8} runs: first {first:6.2f} s, run {best:7.3f} s = "
            f"{n * T / best / 1e6:9.1f} M samples/s, NEES {res.nees_mean[-1]:.2f} in "
            f"[{res.nees_bounds[0]:.2f}, {res.nees_bounds[1]:.2f}], peak {rows[-1]['peak_mb']:.0f} MB"
        )
    for n in (10_000, 100_000):
        if n > args.max_runs or time.perf_counter() > deadline:
            continue
        first, best, res = study(
            n, 1, dtype=jnp.float32, update_every=10, measurement=PositionFix(0.05)
        )
        rows.append(row("filter, fix every 10", n, first, best, res))
        say(
            f"filter    {n:>8} runs: first {first:6.2f} s, run {best:7.3f} s = "
            f"{n * T / best / 1e6:9.1f} M samples/s, NEES {res.nees_mean[-1]:.2f}, "
            f"NIS {res.nis_mean[-1]:.2f}"
        )
    if args.sweep:
        rows += sweep(min(100_000, args.max_runs), deadline, say)
    if args.calibrate:
        rows += calibrate(pathlib.Path(args.calibrate), say)

    cpu = {}
    if args.cpu:
        ref = json.loads(pathlib.Path(args.cpu).read_text())
        cpu = {(r["case"], r.get("runs")): r for r in ref["rows"]}
        say(f"\n| case | runs | here | {ref['machine']} | × |")
        say("|---|--:|--:|--:|--:|")
        for r in rows:
            c = cpu.get((r["case"], r.get("runs")))
            key = "run_s" if "run_s" in r else "wall_s"
            if c is None:
                continue
            say(
                f"| {r['case']} | {r.get('runs', '')} | {r[key]:.3f} s | {c[key]:.3f} s | "
                f"{c[key] / r[key]:.1f} |"
            )
    out = args.out or f"benchmarks/results/studies-device-{machine_slug(info)}.json"
    payload = dict(
        benchmark="studies_device",
        machine=machine_slug(info),
        host=info,
        jax=jax.__version__,
        route=route._asdict(),
        load_average_1min=[os.getloadavg()[0]],
        rows=rows,
    )
    pathlib.Path(out).write_text(json.dumps(payload, indent=1) + "\n")
    say(f"wrote {out}")


if __name__ == "__main__":
    os.chdir(pathlib.Path(__file__).resolve().parent.parent)
    sys.exit(main())
