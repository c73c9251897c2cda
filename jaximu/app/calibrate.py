"""``jaximu calibrate``: fit IMU calibration fields (biases, scale, misalignment, …) and the
noise densities against a recording's ground truth.

  jaximu calibrate FILE [--estimate b_g,b_a] [--keyframe-interval S] [--out JSON]
  jaximu calibrate FILE --estimate b_g,b_a,noise [--window-lengths 0.25,1,4]
                        [--reference-sigma 1e-3,1e-3,1e-2] [--imu-yaml imu.yaml]

``noise`` in ``--estimate`` stands for the four densities and the reference's σ
(:data:`jaximu.calibration.NOISE_FIELDS`), ``noise_per_axis`` for the four densities per axis
and the reference's σ (:data:`jaximu.calibration.PER_AXIS_FIELDS`); any of those names may be
given alone. Parsing and printing only: the work is :mod:`jaximu.calibration`'s.

The shared helpers of :mod:`jaximu.app.common` are imported under the private names
(``_load``, ``_dtype``, …) this module has always called them by.
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
from jaximu.studies.recording import NOISE_PRESETS
from jaximu.studies.recording import noise_preset as _noise


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


WINDOW_LENGTHS = "0.25,1,4"


def _numbers(flag, text, count=None):
    try:
        vals = tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise UsageError(f"{flag} must be comma-separated numbers, got {text!r}") from None
    if count is not None and len(vals) != count:
        raise UsageError(f"{flag} must hold {count} numbers, got {text!r}")
    if not vals or not all(np.isfinite(vals)) or min(vals) <= 0:
        raise UsageError(f"{flag} must be positive numbers, got {text!r}")
    return vals


def _estimate(text, cal):
    names = []
    aliases = {
        "noise": cal.NOISE_FIELDS,
        "noise_per_axis": cal.PER_AXIS_FIELDS + ("reference_sigma",),
    }
    given = [s.strip() for s in text.split(",") if s.strip()]
    twice = sorted({s for s in given if given.count(s) > 1})
    if twice:
        raise UsageError(
            f"--estimate names {', '.join(twice)} more than once, got {text!r}; name each "
            f"field once: --estimate {','.join(dict.fromkeys(given))}"
        )
    for s in given:
        if s in aliases:
            names += [n for n in aliases[s] if n not in names]
        elif s and s not in names:
            names.append(s)
    known = cal.FIELDS + cal.NOISE_FIELDS + cal.PER_AXIS_FIELDS
    unknown = [s for s in names if s not in known]
    if unknown or not names:
        raise UsageError(
            f"{f'unknown field(s) {unknown} in' if unknown else 'no field in'} "
            f"--estimate; fields: {', '.join(cal.FIELDS)}, and the noise's "
            f"{', '.join(cal.NOISE_FIELDS)} (or noise for all of them), per axis "
            f"{', '.join(cal.PER_AXIS_FIELDS)} (or noise_per_axis)"
        )
    both = [n for n in cal.NOISE_FIELDS[:4] if n in names and f"{n}_per_axis" in names]
    if both:
        raise UsageError(
            f"--estimate names {both[0]} both isotropically and per axis: give one "
            "(noise and noise_per_axis together name every density both ways)"
        )
    return tuple(names)


def cmd_calibrate(args):
    import jax.numpy as jnp

    from jaximu import calibration as cal

    estimate = _estimate(args.estimate, cal)
    noise_fit = any(n in cal.NOISE_FIELDS + cal.PER_AXIS_FIELDS for n in estimate)
    if args.keyframe_interval is not None and not args.keyframe_interval > 0:
        raise UsageError("--keyframe-interval must be positive")
    if noise_fit and args.keyframe_interval is not None:
        raise UsageError(
            "--keyframe-interval with noise densities in --estimate: their windows "
            "are --window-lengths (the shortest are the keyframes)"
        )
    if args.steps is not None and args.steps < 1:
        raise UsageError(f"--steps must be at least 1, got {args.steps}")
    lengths = _numbers("--window-lengths", args.window_lengths) if noise_fit else None
    if args.window_lengths != WINDOW_LENGTHS and not noise_fit:
        raise UsageError("--window-lengths is for fitting noise densities: add noise to --estimate")
    if args.imu_yaml and not noise_fit:
        raise UsageError("--imu-yaml writes fitted noise densities: add noise to --estimate")
    ref_sigma = _numbers("--reference-sigma", args.reference_sigma, 3)
    if noise_fit and args.optimizer != "lm":
        raise UsageError("--optimizer: the noise densities are fitted by damped Newton (lm)")
    _check_outputs(**{"out": args.out, "imu-yaml": args.imu_yaml})
    data = _load(args)
    gt = data.ground_truth
    if gt is None:
        raise UsageError(
            f"{args.file} has no ground truth: calibration needs a reference "
            "trajectory (EuRoC state_groundtruth_estimate0 or TUM-VI mocap0)"
        )
    dtype = _dtype(args)
    ref = cal.Reference(gt.t, gt.q, gt.p, gt.v)
    _start_at_groundtruth(data, gt)  # a window outside the ground truth: say where it is
    inside = (data.t >= gt.t[0]) & (data.t <= gt.t[-1])
    d = data.select(np.flatnonzero(inside))
    pose, omega, yaml_noise = _sensor_and_world(args, data.rate_hz)
    extrinsics = pose is not None or bool({"q_BS", "p_BS"} & set(estimate))
    if noise_fit and extrinsics:
        raise UsageError(
            "noise densities with extrinsics (--body-P-sensor, q_BS, p_BS): fit "
            "the extrinsics first, then the noise on the rotated samples"
        )
    initial = None
    if pose is not None:
        initial = cal.ImuCalibration.default(
            dtype=dtype, q_BS=np.asarray(pose.q), p_BS=np.asarray(pose.p)
        )
    if noise_fit:  # too few windows: said before any work, from the windows d can hold
        from jaximu.calibration._noise_fit import check_window_count
        from jaximu.calibration._noise_problem import check_window_span

        shortest = float(np.min(lengths))
        check_window_span(float(np.max(lengths)), d.duration, shortest)
        fits = int(np.floor(d.duration / shortest * (1 + 1e-9))) if shortest > 0 else 0
        check_window_count(estimate, fits, shortest, d.duration)
    noise = yaml_noise or _noise(args.noise)
    kw = (
        {"window_lengths": lengths}
        if noise_fit
        else {"keyframe_interval": args.keyframe_interval or 0.5, "extrinsics": extrinsics}
    )
    with _warnings_as_lines():
        problem = cal.calibration_problem(
            jnp.asarray(d.t, dtype),
            jnp.asarray(d.gyro, dtype),
            jnp.asarray(d.accel, dtype),
            ref,
            noise,
            scheme=args.scheme,
            omega_coriolis=omega,
            reference_sigma=ref_sigma,
            **kw,
        )
    base = problem.base if noise_fit else problem
    if "q_BS0" in base.diagnostics:
        angle = float(np.degrees(np.asarray(base.diagnostics["q_BS0_angle"])))
        print(
            f"IMU-to-reference rotation from the gyro and the reference's rotations (closed "
            f"form): {angle:.2f}°, q_BS0 = "
            f"{np.array2string(np.asarray(base.diagnostics['q_BS0']), precision=5)}"
        )
    if base.n_skipped:  # keyframes inside a dropout of the reference: left out of the fit
        print(f"note: {base.skip_note}")
    windows = (
        f"windows of {', '.join(f'{x:g}' for x in problem.window_lengths)} s"
        if noise_fit
        else f"keyframes every {args.keyframe_interval or 0.5:g} s"
    )
    print(f"calibrating {', '.join(estimate)} on {d.duration:.1f} s ({windows}, {args.scheme})")
    cached = getattr(args, "cache_dir", None)
    what = {"lm": "residuals and their Jacobian", "lbfgs": "L-BFGS step", "adam": "Adam step"}[
        args.optimizer
    ]
    print(
        f"compiling the {what}, then fitting (a first run compiles for about "
        f"{ {'lm': 5, 'lbfgs': 40, 'adam': 15}[args.optimizer] } s on 2 CPU cores"
        + (f"; the compilation is kept in {cached} for the next runs" if cached else "")
        + ")…",
        flush=True,
    )
    tic = time.perf_counter()
    with _warnings_as_lines():
        res = cal.calibrate(
            problem, initial, estimate=estimate, optimizer=args.optimizer, steps=args.steps
        )
    print(
        f"done in {time.perf_counter() - tic:.2f} s ({len(res.loss_history) - 1} steps, "
        f"{'converged' if res.converged else 'not converged'}); χ²/dof = {res.reduced_chi2:.3g}"
    )
    out = {}
    for name in (n for n in estimate if n in cal.FIELDS):
        value = np.asarray(getattr(res.calibration, name), np.float64)
        std = np.asarray(getattr(res.std, name), np.float64)
        out[name] = {"value": value.tolist(), "std": std.tolist()}
        line = (
            f"{name:>14} = {np.array2string(value, precision=5)} ± "
            f"{np.array2string(std, precision=5)}"
        )
        truth = {"b_g": gt.b_g, "b_a": gt.b_a}.get(name)
        if truth is not None:
            line += f"   (ground truth {np.array2string(truth.mean(0), precision=5)})"
        print(line)
    doc = {"fields": out, "reduced_chi2": res.reduced_chi2, "source": data.source}
    if noise_fit:
        print(res.noise_table())
        doc["noise"] = _noise_json(res, cal)
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(doc, indent=2))
        print(f"calibration written to {args.out}")
    if args.imu_yaml:
        from jaximu.calibration import kalibr

        iso, note = _kalibr_noise(res.noise)
        kalibr.write_imu_yaml(
            args.imu_yaml,
            iso,
            res.rate_hz,
            comment=(
                f"jaximu calibrate {args.file}: densities by likelihood over windows of "
                f"{', '.join(f'{x:g}' for x in res.window_lengths)} s; χ²/dof = "
                f"{res.reduced_chi2:.3f}" + (f"\n{note}" if note else "")
            ),
        )
        print(f"Kalibr imu.yaml written to {args.imu_yaml}" + (f" ({note})" if note else ""))
    return 0


def _kalibr_noise(noise):
    """``(ImuNoise of scalars, note)``: Kalibr's imu.yaml holds one number per density, so a
    density fitted per axis is written as its axes' root mean square, which ``note`` says
    with the per-axis values (``""`` when every density is one number)."""
    from jaximu import calibration as cal
    from jaximu.calibration import kalibr

    values = {n: np.asarray(getattr(noise, n), np.float64) for n in kalibr.DENSITIES}
    per_axis = [f"{n} {np.array2string(x, precision=4)}" for n, x in values.items() if x.ndim]
    iso = cal.ImuNoise(**{n: float(np.sqrt(np.mean(x**2))) for n, x in values.items()})
    if not per_axis:
        return iso, ""
    return iso, (
        "per-axis densities written as their axes' root mean square (Kalibr's imu.yaml "
        f"holds one number per density): {'; '.join(per_axis)}"
    )


def _json_numbers(x):
    """An array as JSON numbers: a value the fit did not determine (NaN) is ``null``, which
    every JSON reader takes (``NaN`` is no JSON)."""
    a = np.asarray(x, np.float64)
    if a.ndim == 0:
        return float(a) if np.isfinite(a) else None
    return [_json_numbers(v) for v in a]


def _noise_json(res, cal):
    """The densities (Kalibr units) and the reference's σ, each ``{value, std}`` (``std``
    ``null`` where the likelihood does not determine the value); per window length the
    check of :attr:`CalibrationResult.chi2_by_length`."""
    out = {}
    for name in cal.NOISE_FIELDS[:4]:
        out[name] = {
            "value": _json_numbers(getattr(res.noise, name)),
            "std": _json_numbers(getattr(res.noise_std, name)),
        }
    out["reference_sigma"] = {
        "value": _json_numbers(res.reference_sigma),
        "std": _json_numbers(res.reference_sigma_std),
    }
    out["rate_hz"] = res.rate_hz
    out["window_lengths"] = list(res.window_lengths)
    out["chi2_by_length"] = _json_numbers(np.asarray(res.chi2_by_length, np.float64))
    return out


def add_parser(sub):
    p = sub.add_parser(
        "calibrate",
        help="fit IMU biases (or scale, misalignment, …, the noise densities) to ground truth",
        description="Fit IMU calibration parameters (Levenberg-Marquardt, or "
        "optax L-BFGS/Adam) on preintegration residuals between ground-truth "
        "keyframes, and the noise densities by likelihood over windows of several "
        "lengths; print them with their Laplace 1σ.",
    )
    _add_input_options(p)
    p.add_argument(
        "--estimate",
        default="b_g,b_a",
        help="comma-separated fields (default: %(default)s); any of b_g, b_a, "
        "gyro_scale, gyro_misalignment, accel_scale, accel_misalignment, gravity, "
        "time_offset, q_BS (the IMU's rotation in the reference's body frame, "
        "initialised in closed form), p_BS (its lever arm); the noise densities "
        "gyroscope_noise_density, accelerometer_noise_density, "
        "gyroscope_random_walk, accelerometer_random_walk and reference_sigma, or "
        "noise for all five; a density per axis: its name with _per_axis (e.g. "
        "gyroscope_noise_density_per_axis), or noise_per_axis for the four and "
        "reference_sigma",
    )
    p.add_argument(
        "--keyframe-interval",
        type=float,
        default=None,
        help="seconds between keyframes (> 0, at least one sample interval; "
        "default 0.5); not with noise densities",
    )
    p.add_argument(
        "--window-lengths",
        default=WINDOW_LENGTHS,
        help="noise densities: comma-separated window lengths [s], each a whole "
        "multiple of the shortest; the shortest are fitted (≥ 16 in the recording), "
        "the longer ones check the fit (default: %(default)s)",
    )
    p.add_argument(
        "--reference-sigma",
        default="1e-3,1e-3,1e-2",
        help="the reference's own noise σ_θ [rad], σ_p [m], σ_v [m/s] (positive; "
        "the starting values when reference_sigma is estimated; default: %(default)s)",
    )
    p.add_argument("--scheme", default="midpoint", choices=["euler", "midpoint"])
    p.add_argument(
        "--optimizer",
        default="lm",
        choices=["lm", "lbfgs", "adam"],
        help="Levenberg-Marquardt on the residuals (default: compiles least, fewest "
        "steps), optax L-BFGS or Adam",
    )
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help="optimiser steps (≥ 1; default: 50 LM, 100 L-BFGS, 1000 Adam)",
    )
    p.add_argument(
        "--noise",
        default="euroc",
        choices=NOISE_PRESETS,
        help="the densities to whiten with (and to start a noise fit from)",
    )
    p.add_argument("--out", metavar="JSON", help="write the fitted values")
    p.add_argument(
        "--imu-yaml",
        metavar="YAML",
        help="write the fitted densities as a Kalibr imu.yaml (with noise in --estimate; "
        "a density fitted per axis as its axes' root mean square, said in the file)",
    )
    p.add_argument("--float64", action="store_true", help="compute in float64")
    _add_sensor_options(p)
    p.set_defaults(func=cmd_calibrate)
