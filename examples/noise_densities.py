"""Recover an IMU's noise densities from a simulated flight with known ones.

A 60 s Lissajous flight at 200 Hz of a consumer-grade IMU (densities below), a motion-capture
reference at 100 Hz with its own noise (σ_θ = 1 mrad, σ_p = 1 mm, σ_v = 1 cm/s), windows of
0.25, 1, 2.5 and 7.5 s; the fit starts from densities 2.5× too large and prints the table of
fitted values ± 1σ beside the truth (passed as the "Allan" column) and the starting values.

    python examples/noise_densities.py [--seed S]
"""

import argparse

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaximu  # noqa: E402
from jaximu import calibration as cal  # noqa: E402
from jaximu import simulate as sim  # noqa: E402
from jaximu import so3  # noqa: E402

TRUE = jaximu.ImuNoise(2e-3, 2e-2, 2e-4, 2e-2)
REF_SIGMA = np.array([1e-3, 1e-3, 1e-2])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seconds", type=float, default=60.0)
    args = ap.parse_args()
    rate = 200.0
    t = np.arange(int(args.seconds * rate) + 1) / rate
    traj = sim.lissajous(attitude_amplitude=(0.8, 0.6, 1.5), attitude_frequency=(0.31, 0.23, 0.13))
    gyro, accel = sim.ideal_imu(traj, jnp.asarray(t))
    gm, am, _ = sim.add_noise(
        jax.random.key(args.seed),
        gyro,
        accel,
        1 / rate,
        TRUE,
        b_g0=np.array([0.003, -0.002, 0.004]),
        b_a0=np.array([0.05, -0.08, 0.1]),
    )
    t_ref = np.arange(0.0, args.seconds + 1e-9, 0.01)
    truth = sim.true_states(traj, jnp.asarray(t_ref))
    rng = np.random.default_rng(args.seed)
    q = so3.quat_mul(truth.q, so3.exp(jnp.asarray(rng.normal(0, REF_SIGMA[0], (len(t_ref), 3)))))
    p = np.asarray(truth.p) + rng.normal(0, REF_SIGMA[1], p_shape := (len(t_ref), 3))
    v = np.asarray(truth.v) + rng.normal(0, REF_SIGMA[2], p_shape)
    reference = cal.Reference(t_ref, np.asarray(q), p, v)
    start = jaximu.ImuNoise(5e-3, 5e-2, 5e-4, 5e-2)
    problem = cal.calibration_problem(
        t,
        np.asarray(gm),
        np.asarray(am),
        reference,
        start,
        window_lengths=(0.25, 1, 2.5, 7.5),
        scheme="midpoint",
        reference_sigma=2 * REF_SIGMA,
    )
    result = cal.calibrate(problem, estimate=("b_g", "b_a") + cal.NOISE_FIELDS)
    print(result.noise_table(allan=TRUE))
    print(
        "(the 'Allan' column holds the simulated truth; reference truth:", REF_SIGMA.tolist(), ")"
    )


if __name__ == "__main__":
    main()
