"""Fit IMU biases by gradient descent (optax) through jaximu's preintegration.

1. Simulated: a Lissajous flight with known gyro and accelerometer biases, the reference
   pose and velocity at 20 Hz. The fit must land within its own predicted 3σ.
2. Real: the bundled 20 s of EuRoC MAV V1_02 against its ground truth (Vicon poses and the
   dataset's velocity). The fitted constant biases are printed beside the dataset's own
   bias estimates (its ``b_w``, ``b_a`` columns), with the dead-reckoning drift from the
   true initial state before and after calibration.

    python examples/calibrate_biases.py [--optimizer lbfgs|adam] [--quick]
"""

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaximu  # noqa: E402
from jaximu import calibration as cal  # noqa: E402
from jaximu import datasets  # noqa: E402
from jaximu import simulate as sim  # noqa: E402


def show(name, est, std, truth, unit):
    for i, axis in enumerate("xyz"):
        z = (est[i] - truth[i]) / std[i]
        print(
            f"  {name}_{axis}: fitted {est[i]:+.5f} ± {std[i]:.5f}   true {truth[i]:+.5f}"
            f"   ({z:+.2f} σ) {unit}"
        )


def simulated(args):
    print("== simulated: Lissajous flight, 200 Hz, reference at 20 Hz ==")
    rate, seconds = 200.0, 10.0 if args.quick else 30.0
    t = np.arange(int(seconds * rate) + 1) / rate
    traj = sim.lissajous()
    gyro, accel = sim.ideal_imu(traj, jnp.asarray(t))
    noise = jaximu.ImuNoise.euroc()
    white = jaximu.ImuNoise(
        noise.gyroscope_noise_density, noise.accelerometer_noise_density, 0.0, 0.0
    )  # constant biases: what the fit assumes
    b_g, b_a = np.array([0.004, -0.003, 0.006]), np.array([0.08, -0.05, 0.12])
    gm, am, _ = sim.add_noise(jax.random.key(7), gyro, accel, 1 / rate, white, b_g0=b_g, b_a0=b_a)
    truth = sim.true_states(traj, jnp.asarray(t))
    ref = cal.Reference(
        t[::10], np.asarray(truth.q)[::10], np.asarray(truth.p)[::10], np.asarray(truth.v)[::10]
    )
    problem = cal.calibration_problem(
        t, gm, am, ref, noise, scheme="midpoint", model="propagation", reference_sigma=(0, 0, 0)
    )
    t0 = time.perf_counter()
    res = cal.calibrate(problem, optimizer=args.optimizer)
    print(
        f"  {len(res.loss_history) - 1} {args.optimizer} steps in "
        f"{time.perf_counter() - t0:.1f} s (with compilation); χ²/dof = {res.reduced_chi2:.3f}"
    )
    show("b_g", np.asarray(res.calibration.b_g), np.asarray(res.std.b_g), b_g, "rad/s")
    show("b_a", np.asarray(res.calibration.b_a), np.asarray(res.std.b_a), b_a, "m/s²")
    return res


def drift(seg, b_g, b_a, seconds):
    """Position error after ``seconds`` of dead reckoning from the true initial state."""
    n = int(round(seconds / 0.005))
    q0 = seg.q_gt[0] / np.linalg.norm(seg.q_gt[0])
    x0 = jaximu.NavState(
        jnp.asarray(q0),
        jnp.asarray(seg.p_gt[0]),
        jnp.asarray(seg.v_gt[0]),
        jnp.asarray(b_g, jnp.float64),
        jnp.asarray(b_a, jnp.float64),
    )
    i0 = int(np.searchsorted(seg.t, seg.t_gt[0]))
    end = jaximu.propagate_final(
        x0, seg.gyro[i0 : i0 + n], seg.accel[i0 : i0 + n], np.diff(seg.t)[i0 : i0 + n], "midpoint"
    )
    j = int(np.argmin(np.abs(seg.t_gt - seg.t[i0 + n])))
    return float(np.linalg.norm(np.asarray(end.p) - seg.p_gt[j]))


def real(args):
    print("== real: EuRoC MAV V1_02 (20 s bundled excerpt) against its ground truth ==")
    seg = datasets.euroc_v1_02_segment()
    ref = cal.Reference(seg.t_gt, seg.q_gt, seg.p_gt, seg.v_gt)
    problem = cal.calibration_problem(
        seg.t,
        seg.gyro,
        seg.accel,
        ref,
        jaximu.ImuNoise.euroc(),
        scheme="midpoint",
        model="propagation",
        reference_sigma=(1e-3, 1e-3, 1e-2),
    )
    res = cal.calibrate(problem, optimizer=args.optimizer)
    print(f"  {problem.n_windows} windows of 0.5 s; χ²/dof = {res.reduced_chi2:.3f}")
    gt_g, gt_a = seg.b_g_gt.mean(0), seg.b_a_gt.mean(0)
    show("b_g", np.asarray(res.calibration.b_g), np.asarray(res.std.b_g), gt_g, "rad/s")
    show("b_a", np.asarray(res.calibration.b_a), np.asarray(res.std.b_a), gt_a, "m/s²")
    print("  ('true' here is the dataset's own estimate, itself uncertain)")
    z = np.zeros(3)
    for s in (1.0, 5.0, 10.0):
        print(
            f"  drift after {s:4.1f} s: zero bias {100 * drift(seg, z, z, s):8.2f} cm, "
            f"fitted {100 * drift(seg, res.calibration.b_g, res.calibration.b_a, s):8.2f} cm,"
            f" dataset's biases {100 * drift(seg, gt_g, gt_a, s):8.2f} cm"
        )
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--optimizer", choices=("lbfgs", "adam"), default="lbfgs")
    ap.add_argument("--quick", action="store_true", help="shorter simulation (for tests)")
    args = ap.parse_args(argv)
    simulated(args)
    real(args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
