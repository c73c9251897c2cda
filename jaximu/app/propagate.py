"""``jaximu propagate``: state and 15×15 covariance through a recording, the drift against
its ground truth, the trajectory written for evo.

The work is :func:`jaximu.recording.propagate_recording`'s and :mod:`jaximu.io`'s
(:func:`~jaximu.io.initial_state`, :func:`~jaximu.io.trajectory_errors`, the writers).
"""

from __future__ import annotations

import pathlib
import sys
import time

import numpy as np

from jaximu.app.common import (
    UsageError,
    add_input_options,
    add_output_options,
    add_sensor_options,
    bias_option,
    check_outputs,
    compute_dtype,
    load_recording,
    sensor_and_world,
    start_at_groundtruth,
)
from jaximu.studies.recording import DEMO_SCHEMES, NOISE_PRESETS, propagate_recording
from jaximu.studies.recording import default_P0 as _default_P0
from jaximu.studies.recording import noise_preset as _noise
from jaximu.studies.recording import save_plot as _plot_or_say

REPORT_AT = (1, 2, 5, 10, 20, 30, 60, 120, 300, 600)
"""The seconds after the start at which the drift table reports the error."""


def _check_gravity(g, dtype):
    """``--gravity``: a finite magnitude ≥ 0, checked before the work (the propagation runs
    under ``jit``, where the library's own check cannot run), in the computation ``dtype``
    (float64 without x64 would be truncated, with a JAX warning)."""
    from jaximu.geometry import _checks as val

    if not np.isfinite(g):
        raise UsageError(f"--gravity must be a finite magnitude ≥ 0 [m/s²], got {g}")
    val.gravity_vector(g, dtype)  # a negative magnitude: an error whose fix is a flag


def _report_drift(err, t_start, out=None):
    """Print the error against ground truth at 1, 2, 5, … s after ``t_start`` (the start of
    the propagation) and the drift per second, where the ground truth covers those times."""
    out = out if out is not None else sys.stdout
    lo, hi = float(err.t[0] - t_start), float(err.t[-1] - t_start)
    marks = [s for s in REPORT_AT if lo - 0.01 <= s <= hi + 1e-6]
    if not marks:
        print(f"(the ground truth covers {lo:.2f}–{hi:.2f} s after the start: no table)", file=out)
        return marks
    has_v = err.velocity is not None
    print(
        f"\n{'t [s]':>8}{'position [m]':>15}{'velocity [m/s]':>16}{'attitude [°]':>14}"
        f"{'drift [m/s]':>13}",
        file=out,
    )
    for s in marks:
        pos, vel, att = err.at(s, t_start)
        vel_text = f"{vel:.3f}" if has_v else "–"
        print(f"{s:>8g}{pos:>15.3f}{vel_text:>16}{att:>14.3f}{pos / s:>13.3f}", file=out)
    return marks


def cmd_propagate(args):
    import jax

    from jaximu import io

    dtype = compute_dtype(args)
    _check_gravity(args.gravity, dtype)
    if not args.still > 0:
        raise UsageError(f"--still must be positive (seconds of still samples), got {args.still}")
    check_outputs(out=args.out, states=args.states, plot=args.plot)
    data = load_recording(args)
    if args.init_from_groundtruth:
        gt = data.ground_truth
        if gt is None:
            raise UsageError(f"{args.file} has no ground truth: drop --init-from-groundtruth")
        data = start_at_groundtruth(data, gt, "--init-from-groundtruth")
    state0, how = io.initial_state(
        data,
        from_groundtruth=args.init_from_groundtruth,
        still_seconds=args.still,
        bias=bias_option(args.bias),
    )
    print(how)
    noise = _noise(args.noise)
    pose, omega, yaml_noise = sensor_and_world(args, data.rate_hz)
    noise = yaml_noise or noise
    P0 = _default_P0(args.init_from_groundtruth)
    tic = time.perf_counter()
    t, states, cov = propagate_recording(
        data,
        state0,
        P0,
        noise,
        args.scheme,
        dtype,
        gravity=args.gravity,
        progress=not args.no_progress,
        body_P_sensor=pose,
        omega_coriolis=omega,
    )
    elapsed = time.perf_counter() - tic
    print(
        f"propagated {len(data.dt)} steps ({args.scheme}, {np.dtype(dtype).name}, "
        f"{jax.default_backend()}) in {elapsed:.2f} s including compilation"
    )
    s_end = np.sqrt(np.diag(cov[-1]))
    print(
        f"final position {np.array2string(states.p[-1], precision=3)} m, 1σ "
        f"{np.array2string(s_end[3:6], precision=3)} m; attitude 1σ "
        f"{np.array2string(np.rad2deg(s_end[0:3]), precision=2)}°"
    )
    if data.ground_truth is not None:
        try:
            err = io.trajectory_errors(t, states, data.ground_truth, cov)
        except io.DataError as e:  # no overlap: the trajectory is still written
            print(f"no comparison with the ground truth: {e}")
        else:
            kind = (
                "from the ground-truth state"
                if args.init_from_groundtruth
                else "(not initialised from it: expect an offset; use --init-from-groundtruth)"
            )
            print(f"against ground truth {kind}:")
            _report_drift(err, float(t[0]))
    if args.out:
        io.write_tum(args.out, t, states, t0_ns=data.t0_ns)
        print(f"trajectory written to {args.out} (TUM format: t tx ty tz qx qy qz qw)")
    if args.states:
        io.write_states(args.states, t, states, cov, t0_ns=data.t0_ns)
        print(f"states and covariances written to {args.states}")

    def make():
        from jaximu.studies.plots import plot_trajectory

        return plot_trajectory(
            t,
            states,
            data.ground_truth,
            cov,
            label=f"jaximu {args.scheme}",
            title=f"jaximu propagate: {pathlib.Path(args.file).name}",
        )

    _plot_or_say(make, args.plot)
    return 0


def add_parser(sub):
    """Register ``jaximu propagate`` on the command's subparsers."""
    p = sub.add_parser(
        "propagate",
        help="propagate a recording: trajectory, covariance, plot",
        description="Propagate state and 15×15 covariance through a recording. "
        "Without --init-from-groundtruth the attitude comes from gravity "
        "alignment of the first still samples (yaw 0), position and velocity "
        "are zero, and biases zero unless --bias is given.",
    )
    add_input_options(p)
    p.add_argument("--scheme", default="midpoint", choices=DEMO_SCHEMES)
    p.add_argument(
        "--init-from-groundtruth",
        action="store_true",
        help="start from the ground-truth pose, velocity and biases",
    )
    p.add_argument(
        "--bias",
        metavar="'BGX BGY BGZ BAX BAY BAZ'",
        help="biases [rad/s, m/s²] (overrides the ground truth's)",
    )
    p.add_argument(
        "--still",
        type=float,
        default=1.0,  # > 0
        help="seconds of still samples for gravity alignment (default: %(default)s)",
    )
    p.add_argument(
        "--noise",
        default="euroc",
        choices=NOISE_PRESETS,
        help="noise densities for the covariance (default: %(default)s)",
    )
    p.add_argument(
        "--gravity",
        type=float,
        default=9.81,
        help="gravity magnitude g ≥ 0 [m/s²] (g_W = [0, 0, -g]; default: %(default)s)",
    )
    p.add_argument("--out", metavar="TUM", help="write the trajectory in TUM format (for evo)")
    p.add_argument("--states", metavar="CSV|NPZ", help="write states and covariances")
    add_sensor_options(p)
    add_output_options(p)
    p.set_defaults(func=cmd_propagate)
    return p
