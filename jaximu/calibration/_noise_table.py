"""The noise fit of :func:`jaximu.calibration.calibrate` in words: the fitted densities beside
the given and Allan values, with their discrete-time standard deviations."""

from __future__ import annotations

import numpy as np

from jaximu.calibration._noise_problem import DENSITIES, PER_AXIS_FIELDS, _isotropic
from jaximu.geometry.noise import ImuNoise

_UNITS = {
    "gyroscope_noise_density": ("rad/s/√Hz", "rad/s"),
    "accelerometer_noise_density": ("m/s²/√Hz", "m/s²"),
    "gyroscope_random_walk": ("rad/s²/√Hz", "rad/s"),
    "accelerometer_random_walk": ("m/s³/√Hz", "m/s²"),
}


def _allan_values(allan, per_axis=False):
    """``allan``: ``None``, an :class:`ImuNoise` or ``(gyro, accel)``
    :class:`jaximu.allan.NoiseFit` → four scalars (RMS over axes; NaN where not determined),
    or (``per_axis``) four ``(3,)`` arrays (a scalar repeated)."""
    if per_axis:
        if allan is None:
            return [np.full(3, np.nan)] * 4
        if isinstance(allan, ImuNoise):
            vals = [getattr(allan, n) for n in DENSITIES]
        else:
            _allan_values(allan)  # the same refusal of anything else
            gyro, accel = allan
            vals = [gyro.white, accel.white, gyro.random_walk, accel.random_walk]
        out = [np.broadcast_to(np.asarray(v, np.float64), (3,)) for v in vals]
        if isinstance(allan, ImuNoise):
            return out
        return [np.where(v > 0, v, np.nan) for v in out]  # 0: not determined
    if allan is None:
        return [np.nan] * 4
    if isinstance(allan, ImuNoise):
        return list(_isotropic(allan))
    try:
        gyro, accel = allan
        vals = [gyro.white, accel.white, gyro.random_walk, accel.random_walk]
    except (TypeError, ValueError, AttributeError):
        raise ValueError(
            "allan must be None, an ImuNoise or (gyro, accel) NoiseFit of "
            f"jaximu.allan.fit_noise, got {type(allan).__name__}"
        ) from None
    out = []
    for v in vals:
        v = np.asarray(v, np.float64)
        out.append(float(np.sqrt(np.mean(v**2))) if np.all(v > 0) else np.nan)
    return out


def noise_table(result, allan=None) -> str:
    """The noise fit of ``result`` (a :class:`CalibrationResult` of a problem built with
    ``window_lengths``) as a table: each density fitted ± 1σ in Kalibr's continuous-time
    units, beside the value given to the problem, beside ``allan`` (Allan-deviation values
    of a static recording: an :class:`ImuNoise` or the ``(gyro, accel)``
    :class:`jaximu.allan.NoiseFit`, optional), and the discrete-time standard deviation of
    the fitted density at the recording's rate (white: ``σ/√dt`` per sample; random walk:
    ``σ·√dt`` per bias step; :meth:`ImuNoise.sample_std`); then the reference's σ. A density
    fitted per axis (:data:`PER_AXIS_FIELDS`) has a row per axis (``name[x]``, …), beside
    the given and Allan values of that axis."""
    if getattr(result, "noise", None) is None:
        raise ValueError(
            "result holds no noise fit: calibrate a problem built with "
            "calibration_problem(..., window_lengths=...) and estimate densities"
        )
    dt = 1.0 / result.rate_hz
    fitted, std = _isotropic(result.noise), _isotropic(result.noise_std)
    given, al = _isotropic(result.noise_given), _allan_values(allan)
    discrete = [
        float(np.sqrt(np.mean(np.asarray(x, np.float64) ** 2)))
        for x in ImuNoise(*fitted).sample_std(dt, np.float32)
    ]
    fmt = lambda x: "—" if not np.isfinite(x) else f"{x:.4g}"  # noqa: E731
    by_length = ", ".join(
        f"{x:g} s: {c:.3f}" for x, c in zip(result.window_lengths, result.chi2_by_length)
    )
    lines = [
        f"noise densities by likelihood: {result.n_windows} consecutive windows of "
        f"{result.window_lengths[0]:g} s; χ²/dof = {result.reduced_chi2:.3f} at the "
        "estimate (whitened innovations)",
        f"each window alone, mean squared whitened residual per length: {by_length}",
        f"{'':28s} {'unit (Kalibr)':13s} {'fitted ± 1σ':>22s} {'given':>10s} "
        f"{'Allan':>10s}   discrete std at {result.rate_hz:.4g} Hz",
    ]
    for i, name in enumerate(DENSITIES):
        unit, dunit = _UNITS[name]
        per = " per sample" if i < 2 else " per bias step"
        if PER_AXIS_FIELDS[i] in result.free:
            lines += _axis_rows(result, i, allan, dt, fmt)
            continue
        est = (
            f"{fitted[i]:.4g} ± {std[i]:.2g}" if name in result.free else f"{fitted[i]:.4g} (fixed)"
        )
        lines.append(
            f"{name:28s} {unit:13s} {est:>22s} {fmt(given[i]):>10s} {fmt(al[i]):>10s}"
            f"   {discrete[i]:.4g} {dunit}" + per
        )
    for j, (name, unit) in enumerate(
        (("reference σ_θ", "rad"), ("reference σ_p", "m"), ("reference σ_v", "m/s"))
    ):
        s, e = result.reference_sigma[j], result.reference_sigma_std[j]
        est = f"{s:.4g} ± {e:.2g}" if "reference_sigma" in result.free else f"{s:.4g} (fixed)"
        lines.append(
            f"{name:28s} {unit:13s} {est:>22s} {fmt(result.reference_sigma_given[j]):>10s}"
        )
    return "\n".join(lines)


def _axis_rows(result, i, allan, dt, fmt):
    """The rows of density ``i`` fitted per axis: one per axis, each with its own given and
    Allan value and discrete-time standard deviation."""
    name = DENSITIES[i]
    unit, dunit = _UNITS[name]
    axes = lambda x: np.broadcast_to(np.asarray(x, np.float64), (3,))  # noqa: E731
    fitted, std = axes(getattr(result.noise, name)), axes(getattr(result.noise_std, name))
    given, al = axes(getattr(result.noise_given, name)), _allan_values(allan, True)[i]
    discrete = np.asarray(result.noise.sample_std(dt, np.float32)[i], np.float64)
    rows = []
    for a in range(3):
        label = f"{name}[{'xyz'[a]}]"
        rows.append(
            f"{label:28s} {unit:13s} {f'{fitted[a]:.4g} ± {std[a]:.2g}':>22s} "
            f"{fmt(given[a]):>10s} {fmt(al[a]):>10s}   {discrete[a]:.4g} {dunit}"
            + (" per sample" if i < 2 else " per bias step")
        )
    return rows
