"""A Monte Carlo covariance study and an Allan-deviation noise fit, with plots.

    python examples/monte_carlo.py [--runs 2000] [--out .]

Writes ``mc_envelopes.png`` (3σ envelopes of the linearised covariance over the error cloud),
``mc_nees.png`` (average NEES with its 95% interval) and ``allan.png`` (Allan deviation of a
simulated 3-hour static recording with the fitted noise lines), and prints the numbers.
"""

import argparse
import os
import time

import jax
import numpy as np

import jaximu
from jaximu import allan, plots
from jaximu import simulate as sim
from jaximu.montecarlo import monte_carlo


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=2000)
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--out", default=".")
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")

    noise = jaximu.ImuNoise.euroc()
    traj = sim.figure_eight()
    times = np.arange(0, args.seconds + 1e-9, 0.005)  # 200 Hz
    P0 = np.diag([np.deg2rad(0.1) ** 2] * 3 + [1e-4] * 3 + [1e-4] * 3 + [1e-8] * 3 + [1e-6] * 3)
    tic = time.perf_counter()
    res = monte_carlo(
        traj, times, P0, noise, args.runs, jax.random.key(0), scheme="midpoint", record_every=20
    )
    print(
        f"{args.runs} runs × {len(times) - 1} samples of {traj.name} in "
        f"{time.perf_counter() - tic:.1f} s (compilation included)"
    )
    print(
        f"average NEES at the end: {res.nees_mean[-1]:.2f}, 95% interval "
        f"[{res.nees_bounds[0]:.2f}, {res.nees_bounds[1]:.2f}]; consistent at "
        f"{100 * res.consistent.mean():.0f}% of the recorded times"
    )
    wrong = monte_carlo(
        traj,
        times,
        P0,
        (
            noise,
            jaximu.ImuNoise(
                *(0.5 * np.asarray(x) for x in (1.6968e-04, 2.0e-3, 1.9393e-05, 3.0e-3))
            ),
        ),
        args.runs,
        jax.random.key(0),
        scheme="midpoint",
        record_every=100,
    )
    print(
        f"with a filter that assumes half the noise: average NEES {wrong.nees_mean[-1]:.1f} "
        "(detected)"
    )
    plots.plot_monte_carlo(res).savefig(os.path.join(args.out, "mc_envelopes.png"), dpi=100)
    plots.plot_nees(res).savefig(os.path.join(args.out, "mc_nees.png"), dpi=100)

    # Allan deviation of a simulated static gyro: 3 hours at 100 Hz
    dt, n = 0.01, 3 * 3600 * 100
    w, _, _ = sim.add_noise(
        jax.random.key(1), np.zeros((n, 3), np.float32), np.zeros((n, 3), np.float32), dt, noise
    )
    taus, adev = allan.allan_deviation(np.asarray(w, np.float64), dt)
    fit = allan.fit_noise(taus, adev)
    print("gyro noise density    true 1.697e-04, fitted", " ".join(f"{x:.3e}" for x in fit.white))
    print(
        "gyro random walk      true 1.939e-05, fitted",
        " ".join(f"{x:.3e}" for x in fit.random_walk),
    )
    plots.plot_allan(taus, adev, fit).savefig(os.path.join(args.out, "allan.png"), dpi=100)
    print(f"plots written to {os.path.abspath(args.out)}: mc_envelopes.png, mc_nees.png, allan.png")


if __name__ == "__main__":
    main()
