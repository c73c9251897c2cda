"""``jaximu montecarlo``: a Monte Carlo covariance (or filter) study on a simulated
trajectory (the work is :func:`jaximu.montecarlo.monte_carlo`'s)."""

from __future__ import annotations

import time

import numpy as np

from jaximu.app.common import UsageError, add_output_options, check_outputs, compute_dtype
from jaximu.studies.recording import DEMO_SCHEMES, NOISE_PRESETS
from jaximu.studies.recording import noise_preset as _noise
from jaximu.studies.recording import save_plot as _plot_or_say

FIX_SIGMA = 0.05
"""``--fix-sigma``'s default [m]."""


def cmd_montecarlo(args):
    import jax
    import jax.numpy as jnp

    from jaximu.studies import montecarlo, simulate

    if args.runs < 2:
        raise UsageError(f"--runs must be ≥ 2, got {args.runs}")
    for flag, x in (("--seconds", args.seconds), ("--rate", args.rate)):
        if not 0 < x < 1e6:
            raise UsageError(f"{flag} must be positive and finite (below 1e6), got {x:g}")
    if args.seconds * args.rate < 1:
        raise UsageError(
            f"--seconds {args.seconds:g} at --rate {args.rate:g} Hz holds no sample "
            f"interval; pass --seconds ≥ {1 / args.rate:g} or a higher --rate"
        )
    check_outputs(plot=args.plot, save=args.save)
    dtype = compute_dtype(args)
    traj = {
        "circle": simulate.circle,
        "figure-eight": simulate.figure_eight,
        "lissajous": simulate.lissajous,
        "helix": simulate.helix,
    }[args.trajectory]()
    n = round(args.seconds * args.rate)
    times = jnp.arange(n + 1, dtype=dtype) / args.rate
    sig = np.r_[[np.deg2rad(0.1)] * 3, [0.01] * 3, [0.01] * 3, [1e-4] * 3, [1e-3] * 3]
    P0 = jnp.asarray(np.diag(sig**2), dtype)
    if args.filter is not None and args.filter < 1:
        raise UsageError(f"--filter must be a number of samples ≥ 1, got {args.filter}")
    if args.filter is not None and args.filter > n:
        raise UsageError(
            f"--filter {args.filter} is more than the {n} samples of --seconds "
            f"{args.seconds:g} at --rate {args.rate:g} Hz: no fix would happen; "
            f"pass at most --filter {n}"
        )
    if args.fix_sigma is not None and args.filter is None:
        raise UsageError(
            "--fix-sigma is the position fix of the filter study; pass --filter N "
            "too (a fix every N samples), or drop --fix-sigma"
        )
    fix_sigma = FIX_SIGMA if args.fix_sigma is None else args.fix_sigma
    if not (fix_sigma > 0 and np.isfinite(fix_sigma)):
        raise UsageError(f"--fix-sigma must be positive and finite, got {fix_sigma:g}")
    say = print if jax.process_index() == 0 else (lambda *a, **k: None)  # one report
    say(
        f"Monte Carlo: {args.runs} runs of {args.seconds:g} s of {args.trajectory} at "
        f"{args.rate:g} Hz, noise {args.noise}, scheme {args.scheme} "
        f"({np.dtype(dtype).name}, {jax.local_device_count()} {jax.default_backend()} device(s)"
        f"{f' × {jax.process_count()} processes' if jax.process_count() > 1 else ''})"
        + (
            f"; filter: position fix (σ {fix_sigma:g} m) every {args.filter} samples"
            if args.filter
            else ""
        )
    )
    tic = time.perf_counter()
    res = montecarlo.monte_carlo(
        traj,
        times,
        P0,
        _noise(args.noise),
        args.runs,
        jax.random.PRNGKey(args.seed),
        scheme=args.scheme,
        record_every=max(1, n // 50),
        update_every=args.filter,
        measurement=montecarlo.PositionFix(fix_sigma) if args.filter else None,
        progress=not args.no_progress and jax.process_index() == 0,
        dtype=dtype,
    )
    say(f"done in {time.perf_counter() - tic:.2f} s including compilation")
    lo, hi = res.nees_bounds
    inside = float(np.mean(res.consistent))
    say(
        f"average NEES at the end {res.nees_mean[-1]:.2f} (expected 15, "
        f"{100 * res.confidence:.0f}% interval [{lo:.2f}, {hi:.2f}]); inside the interval at "
        f"{100 * inside:.0f}% of the recorded times"
    )
    if res.nis_mean is not None:
        ok = np.isfinite(res.nis_mean)
        nlo, nhi = res.nis_bounds
        say(
            f"average NIS at the last update {res.nis_mean[ok][-1]:.2f} (expected 3, "
            f"interval [{nlo:.2f}, {nhi:.2f}]); inside at "
            f"{100 * np.mean((res.nis_mean[ok] >= nlo) & (res.nis_mean[ok] <= nhi)):.0f}% of "
            "the updates"
        )
    names = ("attitude [°]", "position [m]", "velocity [m/s]")
    what = "filter" if args.filter else "predicted"
    for name, i0, scale in zip(names, (0, 3, 6), (np.rad2deg(1.0), 1.0, 1.0)):
        pred = np.sqrt(np.diag(res.predicted_cov[-1])[i0 : i0 + 3]) * scale
        emp = np.sqrt(np.diag(res.error_cov[-1])[i0 : i0 + 3]) * scale
        say(
            f"final 1σ {name:<15} {what} {np.array2string(pred, precision=4)}"
            f"  Monte Carlo {np.array2string(emp, precision=4)}"
        )
    if args.save and jax.process_index() == 0:
        res.save(args.save)
        say(f"wrote {args.save}")

    def make():
        from jaximu.studies.plots import plot_monte_carlo

        return plot_monte_carlo(res)

    _plot_or_say(make, args.plot)
    return 0


def add_parser(sub):
    """Register ``jaximu montecarlo`` on the command's subparsers."""
    p = sub.add_parser(
        "montecarlo",
        help="Monte Carlo covariance study on a simulated trajectory",
        description="Draw noisy IMU copies of a simulated trajectory, propagate "
        "them, and compare the sample error covariance with the linearised one "
        "(NEES with its χ² interval).",
    )
    p.add_argument(
        "--trajectory",
        default="figure-eight",
        choices=["circle", "figure-eight", "lissajous", "helix"],
    )
    p.add_argument("--runs", type=int, default=1000, help="Monte Carlo runs (≥ 2)")
    p.add_argument(
        "--seconds",
        type=float,
        default=10.0,
        help="trajectory length (> 0, at least one sample interval)",
    )
    p.add_argument("--rate", type=float, default=200.0, help="IMU rate [Hz] (> 0)")
    p.add_argument("--noise", default="euroc", choices=NOISE_PRESETS)
    p.add_argument("--scheme", default="euler", choices=DEMO_SCHEMES)
    p.add_argument("--seed", type=int, default=0, help="PRNG seed (any integer)")
    p.add_argument(
        "--filter",
        type=int,
        metavar="N",
        default=None,
        help="filter study: every run propagates its own covariance and takes a "
        "position fix every N samples (error-state EKF, Joseph form); NEES and NIS",
    )
    p.add_argument(
        "--fix-sigma",
        type=float,
        default=None,
        help=f"position fix standard deviation [m] (> 0; default {FIX_SIGMA}); only with --filter",
    )
    p.add_argument(
        "--save",
        metavar="NPZ",
        help="write the result with its settings (jaximu.montecarlo.load_result)",
    )
    add_output_options(p)
    p.set_defaults(func=cmd_montecarlo)
    return p
