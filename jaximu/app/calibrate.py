"""``jaximu calibrate``: IMU calibration against a ground-truth trajectory (the work is
:mod:`jaximu.calibration`'s).

``cmd_calibrate`` and the parser section in :func:`add_parser` call the shared helpers of
:mod:`jaximu.app.common` by private names (``_load``, ``_dtype``, …), imported under them.
"""

from __future__ import annotations

import json
import pathlib
import sys
import time
import warnings

import numpy as np

from jaximu.app.common import UsageError
from jaximu.app.common import add_input_options as _add_input_options
from jaximu.app.common import add_sensor_options as _add_sensor_options
from jaximu.app.common import check_outputs as _check_outputs
from jaximu.app.common import compute_dtype as _dtype
from jaximu.app.common import load_recording as _load
from jaximu.app.common import sensor_and_world as _sensor_and_world
from jaximu.app.common import start_at_groundtruth as _start_at_groundtruth
from jaximu.recording import NOISE_PRESETS
from jaximu.recording import noise_preset as _noise


class _warnings_as_lines:
    """The library's warnings (a χ²/dof above its limit, a rotation the motion does not
    determine) as one ``warning:`` line each on stderr, without Python's file and source
    lines."""

    def __enter__(self):
        self._ctx = warnings.catch_warnings(record=True)
        self._caught = self._ctx.__enter__()
        for category in (RuntimeWarning, UserWarning):  # shown once each, as a line
            warnings.simplefilter("always", category)
        return self

    def __exit__(self, *exc):
        self._ctx.__exit__(*exc)
        for w in self._caught:
            print(f"warning: {w.message}", file=sys.stderr)
        return False


def cmd_calibrate(args):
    import jax.numpy as jnp

    from jaximu import calibration as cal

    if not args.keyframe_interval > 0:
        raise UsageError("--keyframe-interval must be positive")
    if args.steps is not None and args.steps < 1:
        raise UsageError(f"--steps must be at least 1, got {args.steps}")
    estimate = tuple(s.strip() for s in args.estimate.split(",") if s.strip())
    unknown = [s for s in estimate if s not in cal.FIELDS]
    if unknown or not estimate:
        raise UsageError(f"{f'unknown field(s) {unknown} in' if unknown else 'no field in'} "
                         f"--estimate; fields: {', '.join(cal.FIELDS)}")
    _check_outputs(out=args.out)
    data = _load(args)
    gt = data.ground_truth
    if gt is None:
        raise UsageError(f"{args.file} has no ground truth: calibration needs a reference "
                         "trajectory (EuRoC state_groundtruth_estimate0 or TUM-VI mocap0)")
    dtype = _dtype(args)
    ref = cal.Reference(gt.t, gt.q, gt.p, gt.v)
    _start_at_groundtruth(data, gt)  # a window outside the ground truth: say where it is
    inside = (data.t >= gt.t[0]) & (data.t <= gt.t[-1])
    d = data.select(np.flatnonzero(inside))
    pose, omega, yaml_noise = _sensor_and_world(args, data.rate_hz)
    extrinsics = pose is not None or bool({"q_BS", "p_BS"} & set(estimate))
    initial = None
    if pose is not None:
        initial = cal.ImuCalibration.default(dtype=dtype, q_BS=np.asarray(pose.q),
                                             p_BS=np.asarray(pose.p))
    with _warnings_as_lines():
        problem = cal.calibration_problem(jnp.asarray(d.t, dtype), jnp.asarray(d.gyro, dtype),
                                          jnp.asarray(d.accel, dtype), ref,
                                          yaml_noise or _noise(args.noise),
                                          keyframe_interval=args.keyframe_interval,
                                          scheme=args.scheme, extrinsics=extrinsics,
                                          omega_coriolis=omega)
    if "q_BS0" in problem.diagnostics:
        angle = float(np.degrees(np.asarray(problem.diagnostics["q_BS0_angle"])))
        print(f"IMU-to-reference rotation from the gyro and the reference's rotations (closed "
              f"form): {angle:.2f}°, q_BS0 = "
              f"{np.array2string(np.asarray(problem.diagnostics['q_BS0']), precision=5)}")
    if problem.n_skipped:  # keyframes inside a dropout of the reference: left out of the fit
        print(f"note: {problem.skip_note}")
    print(f"calibrating {', '.join(estimate)} on {d.duration:.1f} s "
          f"(keyframes every {args.keyframe_interval:g} s, {args.scheme})")
    cached = getattr(args, "cache_dir", None)
    what = {"lm": "residuals and their Jacobian", "lbfgs": "L-BFGS step",
            "adam": "Adam step"}[args.optimizer]
    print(f"compiling the {what}, then fitting (a first run compiles for about "
          f"{ {'lm': 5, 'lbfgs': 40, 'adam': 15}[args.optimizer]} s on 2 CPU cores"
          + (f"; the compilation is kept in {cached} for the next runs" if cached else "")
          + ")…", flush=True)
    tic = time.perf_counter()
    with _warnings_as_lines():
        res = cal.calibrate(problem, initial, estimate=estimate, optimizer=args.optimizer,
                            steps=args.steps)
    print(f"done in {time.perf_counter() - tic:.2f} s ({len(res.loss_history) - 1} steps, "
          f"{'converged' if res.converged else 'not converged'}); χ²/dof = {res.reduced_chi2:.3g}")
    out = {}
    for name in estimate:
        value = np.asarray(getattr(res.calibration, name), np.float64)
        std = np.asarray(getattr(res.std, name), np.float64)
        out[name] = {"value": value.tolist(), "std": std.tolist()}
        line = f"{name:>14} = {np.array2string(value, precision=5)} ± " \
               f"{np.array2string(std, precision=5)}"
        truth = {"b_g": gt.b_g, "b_a": gt.b_a}.get(name)
        if truth is not None:
            line += f"   (ground truth {np.array2string(truth.mean(0), precision=5)})"
        print(line)
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(
            {"fields": out, "reduced_chi2": res.reduced_chi2, "source": data.source}, indent=2))
        print(f"calibration written to {args.out}")
    return 0


def add_parser(sub):
    """Register ``jaximu calibrate`` on the command's subparsers."""
    p = sub.add_parser("calibrate", help="fit IMU biases (or scale, misalignment, …) to ground truth",
                       description="Fit IMU calibration parameters (Levenberg-Marquardt, or "
                       "optax L-BFGS/Adam) on preintegration residuals between ground-truth keyframes; "
                       "print them with their Laplace 1σ.")
    _add_input_options(p)
    p.add_argument("--estimate", default="b_g,b_a",
                   help="comma-separated fields (default: %(default)s); any of b_g, b_a, "
                   "gyro_scale, gyro_misalignment, accel_scale, accel_misalignment, gravity, "
                   "time_offset, q_BS (the IMU's rotation in the reference's body frame, "
                   "initialised in closed form), p_BS (its lever arm)")
    p.add_argument("--keyframe-interval", type=float, default=0.5,
                   help="seconds between keyframes (> 0, at least one sample interval)")
    p.add_argument("--scheme", default="midpoint", choices=["euler", "midpoint"])
    p.add_argument("--optimizer", default="lm", choices=["lm", "lbfgs", "adam"],
                   help="Levenberg-Marquardt on the residuals (default: compiles least, fewest "
                   "steps), optax L-BFGS or Adam")
    p.add_argument("--steps", type=int, default=None,
                   help="optimiser steps (≥ 1; default: 50 LM, 100 L-BFGS, 1000 Adam)")
    p.add_argument("--noise", default="euroc", choices=NOISE_PRESETS)
    p.add_argument("--out", metavar="JSON", help="write the fitted values")
    p.add_argument("--float64", action="store_true", help="compute in float64")
    _add_sensor_options(p)
    p.set_defaults(func=cmd_calibrate)
    return p
