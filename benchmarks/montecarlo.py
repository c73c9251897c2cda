"""Monte Carlo covariance throughput: jaximu against GTSAM's ScenarioRunner.estimateCovariance.

    python benchmarks/montecarlo.py            # N = 10^4 runs × 1000 samples (≈ 2-3 min)
    python benchmarks/montecarlo.py --quick    # N = 2000
    python benchmarks/montecarlo.py --big 1000000   # also 10^6 runs: peak memory (minutes)

The CPU is split into one XLA device per core (``--xla_force_host_platform_device_count``,
set below before JAX starts) so that ``monte_carlo`` runs one chunk per core. The noise is
drawn inside the scan (counter-based Threefry, :mod:`jaximu.kernels.rng`), so "noise generation
included" is the only way it runs. Peak memory of a study is measured in a fresh
subprocess (``resource.getrusage(RUSAGE_SELF).ru_maxrss``, the whole process: Python, JAX,
the compiled code). The filter study (position fix every 20 samples, every run propagating
its own covariance) and two ``jax.distributed`` processes are measured too.

Scenario: GTSAM's constant twist (a level circle, ω = 0.4 rad/s, v = 2 m/s), 1000 samples at
200 Hz, EuRoC ADIS16448 noise, float32 (as the target) and float64. Reported as
trajectory-samples/s end to end (noise generation included), compile time apart:

* ``jaximu monte_carlo``: N noisy runs propagated (mean), errors against the clean
  propagation, the linearised covariance once, NEES per run (:func:`jaximu.montecarlo.monte_carlo`);
* ``jaximu per-run covariance``: the same noisy runs, each also propagating its own 15×15
  covariance (a filter per run: ``propagate_covariance_final`` on the batch);
* ``gtsam ScenarioRunner.estimateCovariance(T, N)``: its C++ loop (noisy preintegration per
  run, 9×9 sample covariance).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

os.environ.setdefault("XLA_FLAGS", f"--xla_force_host_platform_device_count={os.cpu_count()}")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from propagation import machine_info, machine_slug  # noqa: E402  (same folder)

import jaximu  # noqa: E402
from jaximu import simulate as sim  # noqa: E402
from jaximu.montecarlo import PositionFix, monte_carlo  # noqa: E402

T, DT = 1000, 0.005
RADIUS, SPEED = 5.0, 2.0


def timed(fn, reps=2):
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
    runs = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - t0)
    return min(runs), max(first - min(runs), 0.0)


def bench_jaximu(n_runs, dtype, **kw):
    traj = sim.circle(RADIUS, SPEED)
    times = np.arange(T + 1) * DT
    P0 = np.eye(15) * 1e-8
    noise = jaximu.ImuNoise.euroc()
    kw.setdefault("record_every", T)

    def run():
        return monte_carlo(
            traj,
            times,
            P0,
            noise,
            n_runs,
            jax.random.key(0),
            dtype=dtype,
            n_keep=0,
            **kw,
        )

    secs, comp = timed(run)
    res = run()
    return secs, comp, res


_CHILD = """
import os, resource, sys, time, json
import jax
import numpy as np, jaximu
from jaximu import simulate as sim
from jaximu.montecarlo import monte_carlo
n_runs, T, DT, dist = int(sys.argv[1]), int(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
if dist != "-":
    pid, port = (int(x) for x in dist.split(":"))
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2,
                               process_id=pid)
times = np.arange(T + 1) * DT
args = (sim.circle(5.0, 2.0), times, np.eye(15) * 1e-8, jaximu.ImuNoise.euroc())
# compile: the same study once (monte_carlo evens its chunks out over the chunks in flight,
# so the chunk shape depends on n_runs)
monte_carlo(*args, n_runs, jax.random.key(1), record_every=T, n_keep=0)
t0 = time.perf_counter()
r = monte_carlo(*args, n_runs, jax.random.key(0), record_every=T, n_keep=0)
secs = time.perf_counter() - t0
# peak RSS of this process's own memory: VmHWM (ru_maxrss would keep the high-water mark of
# the forked parent's pages across exec: the benchmark's own 1.4 GB)
try:
    with open("/proc/self/status") as f:
        rss = next(int(l.split()[1]) for l in f if l.startswith("VmHWM:")) / 1024
except (OSError, StopIteration):
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(dict(secs=secs, maxrss_mb=rss,
                      nees=float(r.nees_mean[-1]), cov=r.error_cov[-1].ravel().tolist())))
"""


def bench_subprocess(n_runs, devices=None, dist=None):
    """A study in a fresh process (float32): run time after compilation and peak RSS."""
    env = dict(os.environ)
    if devices is not None:
        env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    cmd = [sys.executable, "-c", _CHILD, str(n_runs), str(T), str(DT)]
    if dist is None:
        out = subprocess.run(cmd + ["-"], capture_output=True, text=True, env=env, check=True)
        return json.loads(out.stdout.strip().splitlines()[-1])
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    procs = [
        subprocess.Popen(cmd + [f"{i}:{port}"], stdout=subprocess.PIPE, text=True, env=env)
        for i in range(2)
    ]
    return [json.loads(p.communicate()[0].strip().splitlines()[-1]) for p in procs]


def bench_per_run_covariance(n_runs, dtype):
    traj = sim.circle(RADIUS, SPEED)
    t = jnp.asarray(np.arange(T + 1) * DT, dtype)
    gyro, accel = sim.ideal_imu(traj, t)
    x0 = sim.true_states(traj, t)[0]
    noise = jaximu.ImuNoise.euroc()
    P0 = jnp.eye(15, dtype=dtype) * 1e-8
    dt = jnp.full(T, DT, dtype)
    chunk = min(n_runs, 2048)

    @jax.jit
    def one_chunk(key):
        w, a, _ = sim.add_noise(
            key, gyro, accel, jnp.full(T + 1, DT, dtype), noise, batch_shape=(chunk,)
        )
        x = jax.tree_util.tree_map(lambda v: jnp.broadcast_to(v, (chunk,) + v.shape), x0)
        return jaximu.propagate_covariance_final(x, P0, w[:, :T], a[:, :T], dt, noise)

    def run():
        out = None
        for c in range(0, n_runs, chunk):
            out = one_chunk(jax.random.fold_in(jax.random.key(1), c))
        jax.block_until_ready(out)

    return timed(run)


def bench_gtsam(n_runs):
    import gtsam

    scenario = gtsam.ConstantTwistScenario(
        np.array([0, 0, SPEED / RADIUS]), np.array([SPEED, 0, 0])
    )
    params = gtsam.PreintegrationParams.MakeSharedU(9.81)
    n = jaximu.ImuNoise.euroc()
    params.setGyroscopeCovariance(np.eye(3) * n.gyroscope_noise_density**2)
    params.setAccelerometerCovariance(np.eye(3) * n.accelerometer_noise_density**2)
    params.setIntegrationCovariance(np.eye(3) * 1e-12)
    runner = gtsam.ScenarioRunner(scenario, params, DT, gtsam.imuBias.ConstantBias())
    t0 = time.perf_counter()
    cov = runner.estimateCovariance(T * DT, n_runs)
    return time.perf_counter() - t0, cov


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=None)
    ap.add_argument("--big", type=int, default=0, help="also run this many runs (peak memory)")
    args = ap.parse_args(argv)
    n_runs = 2000 if args.quick else 10_000
    samples = n_runs * T
    info = machine_info()
    print(
        f"# Monte Carlo benchmark on {info['cpu_model']} ({info['cpu_count']} CPUs), "
        f"N = {n_runs} × {T} samples",
        flush=True,
    )
    rows = []
    g_rate = None
    try:
        secs, _ = bench_gtsam(n_runs)
        g_rate = samples / secs
        rows.append(
            dict(
                case="gtsam ScenarioRunner.estimateCovariance",
                dtype="float64",
                run_s=secs,
                compile_s=0.0,
                rate=g_rate,
            )
        )
        print(f"gtsam: {secs:.2f} s", flush=True)
    except ImportError:
        print("gtsam is not installed: baseline skipped", flush=True)
    for dtype in (jnp.float32, jnp.float64):
        name = jnp.dtype(dtype).name
        secs, comp, res = bench_jaximu(n_runs, dtype)
        rows.append(
            dict(
                case="jaximu monte_carlo (noise in the scan, covariance once)",
                dtype=name,
                run_s=secs,
                compile_s=comp,
                rate=samples / secs,
                nees=float(res.nees_mean[-1]),
                nees_bounds=res.nees_bounds.tolist(),
            )
        )
        print(
            f"jaximu {name}: {secs:.2f} s, NEES {res.nees_mean[-1]:.2f} in "
            f"[{res.nees_bounds[0]:.2f}, {res.nees_bounds[1]:.2f}]",
            flush=True,
        )
        secs, comp, res = bench_jaximu(
            n_runs, dtype, update_every=20, measurement=PositionFix(0.05)
        )
        rows.append(
            dict(
                case="jaximu filter study (own covariance, position fix / 20 samples)",
                dtype=name,
                run_s=secs,
                compile_s=comp,
                rate=samples / secs,
                nees=float(res.nees_mean[-1]),
                nis=float(res.nis_mean[-1]),
            )
        )
        print(
            f"jaximu filter {name}: {secs:.2f} s, NEES {res.nees_mean[-1]:.2f} "
            f"NIS {res.nis_mean[-1]:.2f}",
            flush=True,
        )
        if dtype == jnp.float64 or args.quick:
            continue
        secs, comp = bench_per_run_covariance(n_runs, dtype)
        rows.append(
            dict(
                case="jaximu per-run covariance (filter per run)",
                dtype=name,
                run_s=secs,
                compile_s=comp,
                rate=samples / secs,
            )
        )
        print(f"jaximu per-run covariance {name}: {secs:.2f} s", flush=True)
    # processes: one process on every core vs two processes of one core each (jax.distributed)
    one = bench_subprocess(n_runs)
    two = bench_subprocess(n_runs, devices=1, dist=True)
    rel = np.abs(np.asarray(two[0]["cov"]) - one["cov"]).max() / np.abs(one["cov"]).max()
    secs2 = max(t["secs"] for t in two)
    rows.append(
        dict(
            case=f"2 jax.distributed processes (1 core each; cov rel. diff {rel:.1e})",
            dtype="float32",
            run_s=secs2,
            compile_s=float("nan"),
            rate=samples / secs2,
            maxrss_mb=max(t["maxrss_mb"] for t in two),
        )
    )
    rows.append(
        dict(
            case=f"1 process, {os.cpu_count()} devices (peak RSS {one['maxrss_mb']:.0f} MB)",
            dtype="float32",
            run_s=one["secs"],
            compile_s=float("nan"),
            rate=samples / one["secs"],
            maxrss_mb=one["maxrss_mb"],
        )
    )
    print(
        f"2 processes: {secs2:.2f} s (stats rel. diff {rel:.1e}); 1 process: {one['secs']:.2f} s",
        flush=True,
    )
    if args.big:
        big = bench_subprocess(args.big)
        rows.append(
            dict(
                case=f"{args.big} runs (peak RSS {big['maxrss_mb']:.0f} MB)",
                dtype="float32",
                run_s=big["secs"],
                compile_s=float("nan"),
                rate=args.big * T / big["secs"],
                maxrss_mb=big["maxrss_mb"],
            )
        )
        print(
            f"{args.big} runs: {big['secs']:.1f} s, peak RSS {big['maxrss_mb']:.0f} MB", flush=True
        )
    print("\n| case | dtype | run s | samples/s | compile s | × GTSAM |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        ratio = f"{r['rate'] / g_rate:.1f}" if g_rate else "-"
        print(
            f"| {r['case']} | {r['dtype']} | {r['run_s']:.2f} | {r['rate'] / 1e6:.2f} M | "
            f"{r['compile_s']:.1f} | {ratio} |"
        )
    best = max(
        (r for r in rows if r["dtype"] == "float32" and r["case"].startswith("jaximu")),
        key=lambda r: r["rate"],
    )
    verdict = "met" if best["run_s"] < 1.0 else f"missed ({best['run_s']:.2f} s)"
    print(
        f"\nTarget (float32): {n_runs} × {T} in under 1 s: {verdict}"
        + (f"; {best['rate'] / g_rate:.1f}× GTSAM (target 12×)" if g_rate else "")
    )
    print(f"load average during the run: {os.getloadavg()} on {os.cpu_count()} cores")
    out = args.out or os.path.join(
        os.path.dirname(__file__),
        "results",
        f"montecarlo-{machine_slug(info)}{'-quick' if args.quick else ''}.json",
    )
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as f:
        json.dump(dict(machine=info, n_runs=n_runs, samples=T, rows=rows), f, indent=1)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
