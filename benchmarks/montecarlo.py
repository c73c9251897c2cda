"""Monte Carlo covariance throughput: jaximu against GTSAM's ScenarioRunner.estimateCovariance.

    python benchmarks/montecarlo.py            # N = 10^4 runs × 1000 samples (≈ 1-2 min)
    python benchmarks/montecarlo.py --quick    # N = 2000

Scenario: GTSAM's constant twist (a level circle, ω = 0.4 rad/s, v = 2 m/s), 1000 samples at
200 Hz, EuRoC ADIS16448 noise, float32 (as the issue's target) and float64. Reported as
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
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaximu  # noqa: E402
from jaximu import simulate as sim  # noqa: E402
from jaximu.montecarlo import monte_carlo  # noqa: E402
from propagation import machine_info, machine_slug  # noqa: E402  (same folder)

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


def bench_jaximu(n_runs, dtype):
    traj = sim.circle(RADIUS, SPEED)
    times = np.arange(T + 1) * DT
    P0 = np.eye(15) * 1e-8
    noise = jaximu.ImuNoise.euroc()

    def run():
        return monte_carlo(traj, times, P0, noise, n_runs, jax.random.key(0), dtype=dtype,
                           record_every=T, chunk_size=min(n_runs, 4096))

    secs, comp = timed(run)
    res = run()
    return secs, comp, res


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
        w, a, _ = sim.add_noise(key, gyro, accel, jnp.full(T + 1, DT, dtype), noise,
                                batch_shape=(chunk,))
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

    scenario = gtsam.ConstantTwistScenario(np.array([0, 0, SPEED / RADIUS]), np.array([SPEED, 0, 0]))
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
    args = ap.parse_args(argv)
    n_runs = 2000 if args.quick else 10_000
    samples = n_runs * T
    info = machine_info()
    print(f"# Monte Carlo benchmark on {info['cpu_model']} ({info['cpu_count']} CPUs), "
          f"N = {n_runs} × {T} samples", flush=True)
    rows = []
    g_rate = None
    try:
        secs, _ = bench_gtsam(n_runs)
        g_rate = samples / secs
        rows.append(dict(case="gtsam ScenarioRunner.estimateCovariance", dtype="float64",
                         run_s=secs, compile_s=0.0, rate=g_rate))
        print(f"gtsam: {secs:.2f} s", flush=True)
    except ImportError:
        print("gtsam is not installed: baseline skipped", flush=True)
    for dtype in (jnp.float32, jnp.float64):
        name = jnp.dtype(dtype).name
        secs, comp, res = bench_jaximu(n_runs, dtype)
        rows.append(dict(case="jaximu monte_carlo (mean per run, covariance once)", dtype=name,
                         run_s=secs, compile_s=comp, rate=samples / secs,
                         nees=float(res.nees_mean[-1]), nees_bounds=res.nees_bounds.tolist()))
        print(f"jaximu {name}: {secs:.2f} s, NEES {res.nees_mean[-1]:.2f} in "
              f"[{res.nees_bounds[0]:.2f}, {res.nees_bounds[1]:.2f}]", flush=True)
        secs, comp = bench_per_run_covariance(n_runs, dtype)
        rows.append(dict(case="jaximu per-run covariance (filter per run)", dtype=name,
                         run_s=secs, compile_s=comp, rate=samples / secs))
        print(f"jaximu per-run covariance {name}: {secs:.2f} s", flush=True)
    print("\n| case | dtype | run s | samples/s | compile s | × GTSAM |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        ratio = f"{r['rate'] / g_rate:.1f}" if g_rate else "-"
        print(f"| {r['case']} | {r['dtype']} | {r['run_s']:.2f} | {r['rate'] / 1e6:.2f} M | "
              f"{r['compile_s']:.1f} | {ratio} |")
    best = max((r for r in rows if r["dtype"] == "float32" and r["case"].startswith("jaximu")),
               key=lambda r: r["rate"])
    verdict = "met" if best["run_s"] < 1.0 else f"missed ({best['run_s']:.2f} s)"
    print(f"\nTarget (float32): {n_runs} × {T} in under 1 s: {verdict}"
          + (f"; {best['rate'] / g_rate:.1f}× GTSAM (target 10×)" if g_rate else ""))
    out = args.out or os.path.join(os.path.dirname(__file__), "results",
                                   f"montecarlo-{machine_slug(info)}{'-quick' if args.quick else ''}.json")
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as f:
        json.dump(dict(machine=info, n_runs=n_runs, samples=T, rows=rows), f, indent=1)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
