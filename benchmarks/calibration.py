"""Calibration loss: time per gradient step, compile time and memory, at 10^5 and 10^6 samples.

    python benchmarks/calibration.py            # 1e5 and 1e6 samples, float32 and float64
    python benchmarks/calibration.py --quick    # 1e5 only
    python benchmarks/calibration.py --command  # `jaximu calibrate` on 30 s at 200 Hz: cold, warm
    python benchmarks/calibration.py --command --noise  # the same with the noise densities

``--command`` times what a user waits for: ``jaximu calibrate`` run as a command (a fresh
process: importing JAX, reading, checking, compiling, fitting, the Laplace covariance) on a
simulated 30 s EuRoC-layout recording at 200 Hz (biases, white noise, ground truth with
velocities), once with an empty compilation cache (cold) and once more with the cache the
first run filled (warm). The targets on the 2-core VM: < 25 s cold, < 15 s warm.
``--noise`` simulates all four densities and a noisy reference (``write_euroc_layout``)
and adds the four noise densities and the reference's σ to the fit (``--estimate
b_g,b_a,noise --window-lengths 0.25,1,3``: windows of 0.25, 1 and 3 s); target < 30 s cold.

Workload: a simulated Lissajous flight at 200 Hz with biases, scale and misalignment, the
reference at 20 Hz; keyframes every 0.5 s (100 samples); the loss of
:func:`jaximu.calibration.calibration_loss` (``model="propagation"``, midpoint) and its
gradient with respect to every field of :class:`ImuCalibration` (``jax.value_and_grad``).

Memory: ``temp`` is XLA's compiled temporary-buffer size for the value-and-gradient (the
reverse-mode tape), from ``compiled.memory_analysis()``; the inputs (samples and whitening)
are listed apart. Windows are evaluated in checkpointed groups (``windows_per_group``, 64 by
default): the tape holds one group; ``--per-group`` changes it, and the 10^5 case is also run
with one group holding every window (no checkpointing benefit) for comparison.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from propagation import machine_info, machine_slug  # noqa: E402  (same folder)

import jaximu  # noqa: E402
from jaximu import calibration as cal  # noqa: E402
from jaximu import simulate as sim  # noqa: E402
from jaximu import so3  # noqa: E402

RATE = 200.0


def make_problem(n_samples, dtype, per_group):
    t = np.arange(n_samples + 1) / RATE
    traj = sim.lissajous(attitude_amplitude=(0.8, 0.6, 1.5), attitude_frequency=(0.31, 0.23, 0.13))
    gyro, accel = sim.ideal_imu(traj, jnp.asarray(t))
    noise = jaximu.ImuNoise.euroc()
    white = jaximu.ImuNoise(noise.gyroscope_noise_density, noise.accelerometer_noise_density, 0, 0)
    gm, am, _ = sim.add_noise(
        jax.random.key(0),
        gyro,
        accel,
        1 / RATE,
        white,
        b_g0=jnp.array([0.003, -0.002, 0.004]),
        b_a0=jnp.array([0.05, -0.08, 0.1]),
    )
    t_ref = t[::10]
    truth = sim.true_states(traj, jnp.asarray(t_ref))
    ref = cal.Reference(t_ref, np.asarray(truth.q), np.asarray(truth.p), np.asarray(truth.v))
    return cal.calibration_problem(
        t,
        np.asarray(gm, dtype),
        np.asarray(am, dtype),
        ref,
        noise,
        scheme="midpoint",
        model="propagation",
        reference_sigma=(0, 0, 0),
        windows_per_group=per_group,
    )


def bench(n_samples, dtype, per_group, reps=3):
    prob = make_problem(n_samples, dtype, per_group)
    calib = cal.ImuCalibration.default(dtype=dtype)
    f = jax.jit(jax.value_and_grad(cal.calibration_loss, argnums=1))
    t0 = time.perf_counter()
    compiled = f.lower(prob, calib).compile()
    t_compile = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    jax.block_until_ready(compiled(prob, calib))
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(prob, calib))
        times.append(time.perf_counter() - t0)
    inputs = sum(x.nbytes for x in jax.tree_util.tree_leaves(prob))
    return dict(
        samples=prob.n_samples,
        windows=prob.n_windows,
        dtype=jnp.dtype(dtype).name,
        windows_per_group=per_group,
        step_s=min(times),
        compile_s=t_compile,
        samples_per_s=prob.n_samples / min(times),
        temp_mb=mem.temp_size_in_bytes / 2**20,
        inputs_mb=inputs / 2**20,
        max_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    )


REFERENCE_SIGMA = np.array([1e-3, 1e-3, 1e-2])
"""A motion-capture reference's noise, σ_θ [rad], σ_p [m], σ_v [m/s] (``--noise``)."""


def write_euroc_layout(folder, seconds=30.0, seed=0, noise_fit=False):
    """A simulated recording in EuRoC's ASL layout: ``mav0/imu0/data.csv`` (200 Hz, biases
    and white noise) and ``mav0/state_groundtruth_estimate0/data.csv`` (p, q, v, biases).

    ``noise_fit``: the recording a noise-density fit is for — the IMU with all four of the
    EuRoC densities (random walks too) and a ground truth with :data:`REFERENCE_SIGMA` drawn
    into its attitudes, positions and velocities. (With white noise alone and an exact
    reference, five of the fitted σ have their maximum likelihood at zero, where the fit in
    log σ never settles.)"""
    import pathlib

    n = int(round(seconds * RATE))
    t = np.arange(n + 1) / RATE
    traj = sim.lissajous(attitude_amplitude=(0.8, 0.6, 1.5), attitude_frequency=(0.31, 0.23, 0.13))
    gyro, accel = sim.ideal_imu(traj, jnp.asarray(t))
    noise = jaximu.ImuNoise.euroc()
    white = jaximu.ImuNoise(noise.gyroscope_noise_density, noise.accelerometer_noise_density, 0, 0)
    b_g, b_a = np.array([0.003, -0.002, 0.004]), np.array([0.05, -0.08, 0.1])
    gm, am, _ = sim.add_noise(
        jax.random.key(seed),
        gyro,
        accel,
        1 / RATE,
        noise if noise_fit else white,
        b_g0=jnp.asarray(b_g),
        b_a0=jnp.asarray(b_a),
    )
    truth = sim.true_states(traj, jnp.asarray(t))
    if noise_fit:
        rng = np.random.default_rng(seed)
        shape = (n + 1, 3)
        truth = truth.replace(
            q=so3.quat_mul(truth.q, so3.exp(jnp.asarray(rng.normal(0, REFERENCE_SIGMA[0], shape)))),
            p=np.asarray(truth.p) + rng.normal(0, REFERENCE_SIGMA[1], shape),
            v=np.asarray(truth.v) + rng.normal(0, REFERENCE_SIGMA[2], shape),
        )
    ns = 1_403_715_273_262_142_976 + np.arange(n + 1) * 5_000_000
    mav0 = pathlib.Path(folder) / "mav0"
    (mav0 / "imu0").mkdir(parents=True, exist_ok=True)
    (mav0 / "state_groundtruth_estimate0").mkdir(exist_ok=True)
    imu = np.column_stack([np.asarray(gm), np.asarray(am)])
    with open(mav0 / "imu0" / "data.csv", "w") as f:
        f.write(
            "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
            "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n"
        )
        f.writelines(f"{s}," + ",".join(f"{x:.17g}" for x in row) + "\n" for s, row in zip(ns, imu))
    gt = np.column_stack(
        [
            np.asarray(truth.p),
            np.asarray(truth.q),
            np.asarray(truth.v),
            np.tile(b_g, (n + 1, 1)),
            np.tile(b_a, (n + 1, 1)),
        ]
    )
    with open(mav0 / "state_groundtruth_estimate0" / "data.csv", "w") as f:
        f.write(
            "#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z,v_x,v_y,v_z,bw_x,bw_y,bw_z,ba_x,ba_y,ba_z\n"
        )
        f.writelines(f"{s}," + ",".join(f"{x:.17g}" for x in row) + "\n" for s, row in zip(ns, gt))
    return b_g, b_a


def time_command(seconds=30.0, extra=(), noise_fit=False):
    """Wall time of ``jaximu calibrate`` in a fresh process: cold cache, then warm."""
    import subprocess
    import sys
    import tempfile

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        b_g, b_a = write_euroc_layout(tmp + "/rec", seconds, noise_fit=noise_fit)
        env = dict(os.environ, JAXIMU_CACHE_DIR=tmp + "/cache")
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
        for label in ("cold", "warm"):
            t0 = time.perf_counter()
            ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            out = subprocess.run(
                [sys.executable, "-m", "jaximu", "calibrate", tmp + "/rec", *extra],
                env=env,
                capture_output=True,
                text=True,
            )
            if out.returncode:
                raise SystemExit(out.stdout + out.stderr)
            wall = time.perf_counter() - t0
            ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            # CPU time beside wall time: on a shared VM the wall time varies with the host's
            # load (steal), the CPU time much less.
            cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
            fit = next((ln for ln in out.stdout.splitlines() if ln.startswith("done in")), "")
            rows.append(dict(cache=label, wall_s=wall, cpu_s=cpu, fit_line=fit))
            print(
                f"jaximu calibrate, {seconds:g} s at {RATE:g} Hz, {label} cache: {wall:6.1f} s "
                f"wall, {cpu:6.1f} s CPU (process start to result); {fit}"
            )
        print(out.stdout.strip().splitlines()[-2])
        print(out.stdout.strip().splitlines()[-1])
        print(f"         truth: b_g = {b_g}, b_a = {b_a}")
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument(
        "--command",
        action="store_true",
        help="only time `jaximu calibrate` on 30 s at 200 Hz, cold and warm",
    )
    ap.add_argument("--seconds", type=float, default=30.0, help="with --command")
    ap.add_argument(
        "--noise",
        action="store_true",
        help="with --command: fit the noise densities too (windows 0.25, 1, 3 s)",
    )
    ap.add_argument("--per-group", type=int, default=64)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    info = machine_info()
    if args.command:
        print(
            f"machine: {info['cpu_model']} ({info['cpus_usable']} usable CPUs), jax {info['jax']}"
        )
        noise = ("--estimate", "b_g,b_a,noise", "--window-lengths", "0.25,1,3")
        time_command(args.seconds, noise if args.noise else (), noise_fit=args.noise)
        return
    sizes = [100_000] if args.quick else [100_000, 1_000_000]
    rows = []
    print(f"machine: {info['cpu_model']} ({info['cpus_usable']} usable CPUs), jax {info['jax']}")
    print(
        f"{'samples':>9} {'dtype':>7} {'group':>6} {'step':>9} {'Msamples/s':>10} "
        f"{'compile':>8} {'temp MB':>8} {'inputs MB':>9} {'max RSS MB':>10}"
    )
    cases = [(n, d, args.per_group) for n in sizes for d in (jnp.float32, jnp.float64)]
    cases.append((100_000, jnp.float64, 100_000))  # every window in one group
    for n, d, g in cases:
        r = bench(n, d, g)
        rows.append(r)
        print(
            f"{r['samples']:>9} {r['dtype']:>7} {min(g, r['windows']):>6} {r['step_s']:>8.3f}s "
            f"{r['samples_per_s'] / 1e6:>10.2f} {r['compile_s']:>7.1f}s {r['temp_mb']:>8.1f} "
            f"{r['inputs_mb']:>9.1f} {r['max_rss_mb']:>10.0f}"
        )
    out = args.out or os.path.join(
        os.path.dirname(__file__), "results", f"calibration-{machine_slug(info)}.json"
    )
    with open(out, "w") as fh:
        json.dump(dict(machine=info, results=rows), fh, indent=1)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
