"""Gradient-based IMU calibration against a reference trajectory.

The sensor model (the one :func:`jaximu.simulate.add_noise` draws from)::

    w_m = (I + S_g) ω + b_g + n_g,      a_m = (I + S_a) f + b_a + n_a,

with ``S = diag(scale) + L(misalignment)``: scale-factor errors on the diagonal and the
three misalignment terms ``[S_10, S_20, S_21]`` strictly below it (the lower-triangular
form of Kalibr's ``scale-misalignment`` model). The reference (motion capture or a
dataset's ground truth) is time-stamped on its own clock: IMU time ``t`` is reference time
``t + time_offset``.

The reference tracks its own body frame B; the IMU frame S may be rotated from it by
``q_BS`` and sit at the lever arm ``p_BS`` (the extrinsics, :class:`jaximu.SensorPose`;
``body_P_sensor`` in :func:`jaximu.preintegrate`). With ``extrinsics=True`` in
:func:`calibration_problem` they join the model (and may be estimated: ``estimate=(...,
"q_BS", "p_BS")``); the frame check then initialises ``q_BS`` in closed form instead of
refusing a rotated IMU: the rotation vectors of the windows satisfy ``φ_B = R_BS φ_S``
exactly, a least-squares rotation fit (Wahba's problem, with a constant for the bias).

The loss compares the corrected IMU with the reference between keyframes a fixed number of
samples apart: the 9-dim preintegration residual ``[r_θ, r_p, r_v]`` of
:func:`jaximu.residual` (``model="preintegration"``), or the same quantities from
:func:`jaximu.propagate_final` started at the reference state (``model="propagation"``;
equal for ``"euler"``), whitened by the residual covariance (preintegration noise plus the
reference's own noise), ``loss = ½ Σ_k |L_k⁻¹ r_k|²``. The whitening is computed once at the
start (it depends on the samples, not on the parameters). Where the reference has no
velocities, the keyframe velocities are estimated with the parameters (nuisance).

The reference is not interpolated across its dropouts (motion capture loses the body for
tenths of a second): a window with a keyframe inside a reference gap longer than
``GAP_FACTOR`` × the reference's median interval (:meth:`jaximu.io.GroundTruth.interpolate`'s
rule) is left out of the fit (weight 0: nothing of it reaches the loss or its gradient), and
:attr:`CalibrationProblem.skip_note` says how many and which gaps.

Windows are evaluated in groups under :func:`jax.checkpoint`, so reverse-mode memory is
that of one group plus one scalar per group: gradients through 10⁶ samples fit in a laptop's
memory (``benchmarks/calibration.py`` measures it).

Parameters are optimised in normalised coordinates ``z = (θ - θ₀) / scale`` (the
:data:`SCALES`: 0.01 rad/s for ``b_g``, 0.1 m/s² for ``b_a``, ...), so one learning rate
suits every field. The uncertainty is the Gauss-Newton / Laplace approximation
``cov = (JᵀJ)⁻¹`` of the whitened residuals at the optimum; it is right when the noise
model is (check ``reduced_chi2`` ≈ 1).

The fit (:func:`calibrate`) is Levenberg–Marquardt on the whitened residuals by default:
one compiled function returns the residuals and their Jacobian (``jacfwd`` over the free
coordinates; 6 tangents per window for nuisance velocities) and serves every iteration and
the covariance. optax L-BFGS and Adam on the loss are there too.

The noise densities (and the reference's σ) are fitted by maximum likelihood, the exact joint
likelihood of consecutive windows' residuals (a Kalman filter's prediction-error
decomposition, :mod:`jaximu.calibration._noise_filter`): :func:`calibration_problem` with
``window_lengths`` returns a
:class:`jaximu.calibration._noise_problem.NoiseProblem`, and ``estimate=`` may then name
:data:`NOISE_FIELDS` (isotropic densities) or :data:`PER_AXIS_FIELDS` (per axis) beside the
fields; the model, its covariance and the fit are in
:mod:`jaximu.calibration._noise_fit` (docs/guide/noise-densities.md).

Adding an estimable field (an IMU–body extrinsic, say): a pytree field of
:class:`ImuCalibration` with its default in :meth:`ImuCalibration.default`; its name in
:data:`FIELDS`, its size in ``_SIZES``, its typical magnitude in :data:`SCALES` (the unit of
its normalised coordinate); and its use in ``_group_residuals``, the one place the model
meets the data. The optimisers, the Jacobian, the Laplace covariance and ``estimate=`` follow.
Coordinates are additive (``θ = θ₀ + scale · z``), so a rotation is best estimated as a
rotation vector ``δ`` applied as ``R₀ Exp(δ)`` inside the model (``δ₀ = 0``).
"""

from __future__ import annotations

import warnings

import jax.numpy as jnp
import numpy as np

# The model, the checks and the fit live in their own modules; the calibration's public
# names (and the internals the tests call) are importable from here as before.
from jaximu.calibration._checks import (
    QUICK_COMPILE_SAMPLES,
    _apply,
    _check_consistency,
    _compiled,
    _device,
    _initial_rotation,
    _keyframe_rotations,
    _once,
    _preintegrate_sequential,
    _rotation_vectors,
)
from jaximu.calibration._fit import (
    _residuals_jacobian_compiled,  # noqa: F401  (tests)
)
from jaximu.calibration._model import (
    _SIZES,
    FIELDS,
    MODELS,
    SCALES,
    CalibrationError,
    CalibrationProblem,
    ImuCalibration,
    Reference,
    _gap_list,
    _interp,
    calibration_loss,
    calibration_residuals,
    sensor_matrix,  # noqa: F401  (calibration.sensor_matrix)
)
from jaximu.calibration._noise_problem import (
    NOISE_FIELDS,
    PER_AXIS_FIELDS,
    NoiseProblem,
    noise_problem,
)
from jaximu.calibration._noise_table import noise_table
from jaximu.errors import Fix, InputError
from jaximu.geometry import _checks as val
from jaximu.geometry import _tolerances, so3
from jaximu.geometry.noise import ImuNoise, check_noise
from jaximu.geometry.state import ImuBias
from jaximu.io._common import GAP_FACTOR, in_gap
from jaximu.schemes import world

__all__ = [
    "ImuCalibration",
    "Reference",
    "CalibrationProblem",
    "CalibrationError",
    "calibration_problem",
    "calibration_loss",
    "calibration_residuals",
    "FIELDS",
    "NOISE_FIELDS",
    "PER_AXIS_FIELDS",
    "SCALES",
    "noise_table",
]


def _check_initial(initial):
    """``initial``: ``None`` or an :class:`ImuCalibration` of single (unbatched) fields of
    their documented shapes, finite, with a unit ``q_BS`` (relative 1e-3, as
    :class:`Reference`'s quaternions) and ``gravity ≥ 0`` (a magnitude)."""
    if initial is None:
        return
    if not isinstance(initial, ImuCalibration):
        raise ValueError(f"initial must be an ImuCalibration or None, got {type(initial).__name__}")
    for name in FIELDS:
        x = np.asarray(getattr(initial, name), np.float64)
        shape = (_SIZES[name],) if _SIZES[name] > 1 else ()
        if x.shape != shape:
            raise ValueError(f"initial.{name} must have shape {shape}, got {x.shape}")
        val.check_finite(f"initial.{name}", x)
    _tolerances.check_unit_norm(
        "initial.q_BS",
        np.asarray(initial.q_BS, np.float64),
        np.float64,
        tol=_tolerances.ROUNDED_QUATERNION,
        fix="normalise it: q / |q|",
        what="must be a unit quaternion [w, x, y, z]",
    )
    if float(np.asarray(initial.gravity)) < 0:
        raise ValueError(
            f"initial.gravity is a magnitude [m/s²] and must be ≥ 0, got "
            f"{float(np.asarray(initial.gravity)):g} (g_W = [0, 0, -g])"
        )


def _sqrt_information(cov, dtype) -> np.ndarray:
    """``L⁻¹`` for the residuals' covariances ``cov = L Lᵀ`` (``(..., 9, 9)``, one per window),
    which whiten the residuals; a covariance singular to the precision of ``dtype``
    (:func:`jaximu.geometry._tolerances.check_definite`) is refused, naming the window and its axes:
    its whitened residual would be the rounding divided by zero."""
    _tolerances.check_definite(
        "the residuals' covariance",
        cov,
        dtype,
        axes=_tolerances.ERROR_AXES[:9],
        what="the residuals are whitened by its inverse Cholesky factor",
        fix="noise (its white-noise densities) and reference_sigma leave some residual "
        "without variance; give noise positive densities (its datasheet's or an Allan "
        "fit's) or reference_sigma positive values",
    )
    return np.linalg.inv(np.linalg.cholesky(cov))


def _velocities_from_positions(p, t, good):
    """Keyframe velocities by differences of the keyframe positions ``p`` at times ``t``
    (``np.gradient``: central inside, one-sided at the ends) using only keyframes where
    ``good``; a keyframe with no good neighbour gets 0 (its windows are left out)."""
    v = np.gradient(p, t, axis=0)
    if good.all():
        return v
    n = len(t)
    for k in range(n):
        lo_ok = k > 0 and good[k - 1]
        hi_ok = k < n - 1 and good[k + 1]
        if not good[k]:
            v[k] = 0.0
        elif not (lo_ok and hi_ok):
            lo, hi = (k - 1 if lo_ok else k), (k + 1 if hi_ok else k)
            v[k] = (p[hi] - p[lo]) / (t[hi] - t[lo]) if hi > lo else 0.0
    return v


def calibration_problem(
    t,
    gyro,
    accel,
    reference: Reference,
    noise: ImuNoise,
    *,
    keyframe_interval: float | None = None,
    scheme: str = "euler",
    model: str = "preintegration",
    reference_sigma=(1e-3, 1e-3, 1e-2),
    initial: ImuCalibration | None = None,
    windows_per_group: int = 64,
    check: bool = True,
    extrinsics: bool = False,
    omega_coriolis=None,
    window_lengths=None,
) -> CalibrationProblem | NoiseProblem:
    """Cut the IMU stream into keyframe windows and pair them with the reference.

    Args:
        t: ``(N,)`` IMU times [s] (IMU clock); gyro, accel: ``(N, 3)`` raw samples [rad/s],
            [m/s²]. Their dtype is the computation's.
        reference: the :class:`Reference` (reference clock). Keyframes lie where both exist.
            It is not interpolated across its gaps (dropouts): intervals longer than
            ``GAP_FACTOR`` × its median interval, the rule of
            :meth:`jaximu.io.GroundTruth.interpolate`. A window with a keyframe strictly
            inside one is left out of the fit (weight 0; :attr:`CalibrationProblem.skip_note`
            says how many and where); a gap between two keyframes of a window does not
            matter (the residual reads the reference at the keyframes only). A
            :class:`CalibrationError` names the gaps when they leave no window.
        noise: :class:`ImuNoise` of the IMU (whitening of the residuals).
        keyframe_interval: seconds between keyframes, positive, at least one sample interval
            (rounded to whole samples); default 0.5. Not with ``window_lengths``.
        scheme: ``"euler"`` or ``"midpoint"``; model: ``"preintegration"`` or ``"propagation"``.
        reference_sigma: ``(σ_θ [rad], σ_p [m], σ_v [m/s])``, each ``≥ 0``, of the
            reference's own errors,
            added to each residual's covariance as ``diag(2σ_θ², 2σ_p² + σ_v²Δt², 2σ_v²)``
            (ends assumed independent).
        initial: the calibration at which the consistency checks integrate (default zero).
        windows_per_group: windows per checkpointed group (memory of a gradient), ≥ 1.
        check: run the unit and frame checks, raising :class:`CalibrationError`: the
            rotation (velocity change) of each window from the raw gyro (accel) is compared
            with the reference's (a gyro in deg/s reads 57× too much, an accelerometer in g
            0.10×; an IMU frame rotated from the reference's body frame or a quaternion in
            ``[x, y, z, w]`` order gives a rotation between them). The checks judge only
            what the data can show: a rotation is reported when it exceeds
            :data:`FRAME_ANGLE_TOL` *and* the windows' motion determines it (a likelihood
            ratio beyond :data:`FRAME_SIGNIFICANCE`, noise bounded below by
            ``reference_sigma``); a near-still segment passes the frame check, and a
            deg/s gyro is caught there by its mean rate (:data:`GYRO_BIAS_MAX`). Every 3 s
            excerpt of the bundled recordings passes (``tests/calibration/test_calibration_checks.py``).
        extrinsics: the IMU frame may be rotated from the reference's body frame and sit at
            a lever arm (``q_BS``, ``p_BS`` of :class:`ImuCalibration` join the model). The
            frame check then becomes the initialiser: the least-squares rotation between the
            windows' gyro and reference rotations (or velocity changes, where the rotations
            do not determine it; :func:`_initial_rotation`) is ``q_BS0``, reported in
            ``diagnostics``, and the other checks run on the rotated samples. A
            ``RuntimeWarning`` says when the motion determines no rotation (``q_BS0`` is
            then the identity).
        omega_coriolis: optional ``(3,)`` rotation rate of the reference's world [rad/s] in W
            (:func:`jaximu.earth_rate`): the residuals then use the exact rotating-world
            prediction (:func:`jaximu.residual`).

        window_lengths: window lengths [s] for fitting the noise densities
            (``estimate=(..., "gyroscope_noise_density", …, "reference_sigma")`` in
            :func:`calibrate`, or per axis ``"gyroscope_noise_density_per_axis"``, …), e.g. ``(0.25, 1, 4)``: the shortest are the keyframe
            windows, whose residuals' exact joint likelihood is fitted (white noise, random
            walk and the reference's noise separate through their correlation in time:
            :mod:`jaximu.calibration._noise_filter`); each longer one, a whole multiple of the shortest
            composed of consecutive shortest windows, serves as a check of the fitted model
            at that time scale (:attr:`CalibrationResult.chi2_by_length`). At least 16
            shortest windows must lie in the fit. The model is ``"preintegration"``, without
            ``extrinsics``; a reference without velocities gets its positions' central
            differences (their error is part of ``σ_v``).

    Returns:
        :class:`CalibrationProblem`, or with ``window_lengths`` a
        :class:`jaximu.calibration._noise_problem.NoiseProblem` (the shortest windows' problem as
        its ``base``).
    """
    if window_lengths is not None:
        if keyframe_interval is not None:
            raise InputError(
                "keyframe_interval and window_lengths both given: with "
                "window_lengths the keyframes are the shortest length's",
                [Fix("keyframe_interval", "leave keyframe_interval out")],
            )
        return noise_problem(
            calibration_problem,
            t,
            gyro,
            accel,
            reference,
            noise,
            window_lengths=window_lengths,
            scheme=scheme,
            model=model,
            reference_sigma=reference_sigma,
            initial=initial,
            windows_per_group=windows_per_group,
            check=check,
            extrinsics=extrinsics,
            omega_coriolis=omega_coriolis,
        )
    keyframe_interval = 0.5 if keyframe_interval is None else keyframe_interval
    if scheme not in ("euler", "midpoint"):
        raise ValueError(f"unknown scheme {scheme!r}; choose 'euler' or 'midpoint'")
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}; choose one of {MODELS}")
    keyframe_interval = val.check_positive("keyframe_interval", keyframe_interval)
    windows_per_group = val.check_int("windows_per_group", windows_per_group, 1)
    sig = np.asarray(reference_sigma, np.float64) if np.ndim(reference_sigma) == 1 else None
    if sig is None or sig.shape != (3,) or not np.all(np.isfinite(sig) & (sig >= 0)):
        raise ValueError(
            "reference_sigma must be three non-negative numbers (σ_θ [rad], σ_p [m], "
            f"σ_v [m/s]), got {reference_sigma!r}"
        )
    if not isinstance(reference, Reference):
        raise ValueError(
            f"reference must be a jaximu.calibration.Reference, got {type(reference).__name__}"
        )
    check = val.check_bool("check", check)
    extrinsics = val.check_bool("extrinsics", extrinsics)
    _check_initial(initial)
    dtype = val.float_dtype(gyro, accel)
    t = val.as_numbers("t", t)
    gyro_np, accel_np = val.as_numbers("gyro", gyro, None), val.as_numbers("accel", accel, None)
    if t.ndim != 1 or gyro_np.shape != (len(t), 3) or accel_np.shape != (len(t), 3):
        raise ValueError(
            f"t, gyro, accel must have shapes (N,), (N, 3), (N, 3); got "
            f"{t.shape}, {gyro_np.shape}, {accel_np.shape}"
        )
    if len(t) < 3:
        raise ValueError(
            f"t, gyro, accel hold {len(t)} samples; a calibration needs at least "
            "two keyframe windows of samples"
        )
    val.check_times("t", t, 3, val.TIMES_FIX)
    val.check_finite("gyro", gyro_np)
    val.check_finite("accel", accel_np)
    noise = check_noise(noise, dtype)
    val.check_unbatched_noise(noise, "a calibration problem")
    if omega_coriolis is not None:
        omega_coriolis = world.check_omega(omega_coriolis, dtype)
        if omega_coriolis.ndim != 1:
            raise ValueError(
                f"omega_coriolis must be one (3,) world rate for a calibration "
                f"problem (one recording), got shape {omega_coriolis.shape}"
            )
    rt, rq, rp = (val.as_numbers(f"reference.{n}", getattr(reference, n)) for n in "tqp")
    M = len(rt) if rt.ndim else 0
    if rt.ndim != 1 or rq.shape != (M, 4) or rp.shape != (M, 3) or M < 2:
        raise ValueError("reference t, q, p must have shapes (M,), (M, 4), (M, 3) with M ≥ 2")
    val.check_times("reference.t", rt, 2, val.TIMES_FIX)  # a NaN time would pass an order test
    for name, x in (("reference.q", rq), ("reference.p", rp)):
        val.check_finite(name, x)
    _tolerances.check_unit_norm(
        "reference.q",
        rq,
        np.float64,
        tol=_tolerances.ROUNDED_QUATERNION,
        what="is not unit ([w, x, y, z] quaternions)",
        where=lambda i: f" at row {i[0]}",
        fix="pass unit quaternions (a normalised copy is used within this tolerance)",
    )
    rq = rq / np.linalg.norm(rq, axis=-1, keepdims=True)
    has_v = reference.v is not None
    rv = val.as_numbers("reference.v", reference.v) if has_v else np.zeros_like(rp)
    if rv.shape != (M, 3):
        raise ValueError(f"reference.v must have shape (M, 3), got {rv.shape}")
    val.check_finite("reference.v", rv)

    init = initial if initial is not None else ImuCalibration.default(dtype=dtype)
    td0 = float(np.asarray(init.time_offset))
    period = float(np.median(np.diff(t)))
    W = int(round(keyframe_interval / period))
    if W < 1:
        raise InputError(
            f"keyframe_interval = {keyframe_interval:g} s is shorter than one sample "
            f"interval ({period:.3g} s): keyframes are whole samples apart "
            "(typically 0.1–1 s)",
            [Fix("keyframe_interval", phrase=f"{{}} ≥ {period:.3g}")],
        )
    inside = np.nonzero((t + td0 >= rt[0]) & (t + td0 <= rt[-1]))[0]
    if len(inside) < W + 2:
        raise ValueError("the IMU and the reference overlap by less than one keyframe interval")
    first, last = inside[0], inside[-1]
    K = (last - first) // W
    if K < 1:
        raise ValueError("the IMU and the reference overlap by less than one keyframe interval")
    idx = first + W * np.arange(K + 1)
    # Keyframes inside a reference dropout: their windows are left out (weight 0), never
    # fitted to a pose interpolated across the gap.
    inside, gap_of, max_gap = in_gap(rt, t[idx] + td0)  # the keyframes on the reference clock
    kept = ~(inside[:-1] | inside[1:])
    gap_windows: dict[int, int] = {}  # gap index -> windows with a keyframe inside it
    for k in np.flatnonzero(~kept):
        for end in (k, k + 1):
            if inside[end]:
                gap_windows[gap_of[end]] = gap_windows.get(gap_of[end], 0) + 1
    skipped = tuple(
        (float(rt[i]), float(rt[i + 1] - rt[i]), n) for i, n in sorted(gap_windows.items())
    )
    if not kept.any():
        raise CalibrationError(
            f"every one of the {K} keyframe windows has a keyframe inside a reference gap "
            f"(an interval longer than {max_gap:.4g} s, {GAP_FACTOR:g} × the reference's median "
            f"interval), and the reference is not interpolated across gaps: "
            f"{_gap_list(skipped)}. Calibrate on a stretch the reference covers"
        )
    # Each window holds the W + 1 samples from keyframe to keyframe and the W intervals
    # between them (the midpoint rule uses both ends; Euler leaves the last one unused).
    sl = idx[:-1, None] + np.arange(W + 1)  # (K, W + 1)
    dt_all = np.diff(t)
    win_gyro, win_accel, win_dt = gyro_np[sl], accel_np[sl], dt_all[sl[:, :-1]]

    # Keyframe velocities where the reference has none: central differences of positions.
    t0 = t[idx[0]]  # common time origin: keeps float32 times (and absolute stamps) precise
    qk, pk, vk = (
        np.asarray(x, np.float64)
        for x in _once(_interp)(
            _device(t[idx] - t0 + td0),
            _device(rt - t0),
            _device(rq),
            _device(rp),
            _device(rv),
        )
    )
    if not has_v:
        vk = _velocities_from_positions(pk, t[idx], ~inside)

    # Raw preintegration (for the whitening and the checks) at the initial calibration.
    g_c, a_c = _once(_apply)(init, _device(win_gyro, dtype), _device(win_accel, dtype))
    # Run once per problem, so its compile time is what the user waits for: the plain scan
    # (it compiles in a fraction of the time of the side-by-side chunks "auto" picks for a few
    # dozen windows; the inputs are checked above). Small problems compile it at the quick
    # level and on the generic kernel, which compiles faster than the structure-of-arrays
    # one there.
    zero3 = jnp.zeros(3, dtype)
    quick = K * W <= QUICK_COMPILE_SAMPLES
    pim = _compiled(_preintegrate_sequential, quick, ("scheme", "fast"))(
        g_c,
        a_c,
        _device(win_dt, dtype),
        ImuBias(zero3, zero3),
        noise,
        scheme=scheme,
        fast=not quick,
    )
    cov = np.asarray(pim.cov, np.float64)
    Dt = win_dt.sum(-1)
    s_th, s_p, s_v = (float(x) for x in reference_sigma)
    extra = np.zeros((K, 9))
    extra[:, 0:3] = 2 * s_th**2
    extra[:, 3:6] = (2 * s_p**2 + (s_v * Dt) ** 2)[:, None] if has_v else 2 * s_p**2
    extra[:, 6:9] = 2 * s_v**2 if has_v else 0.0
    cov = cov + extra[:, :, None] * np.eye(9)

    diagnostics = dict.fromkeys(
        ("gyro_ratio", "gyro_frame_error", "accel_ratio", "accel_frame_error"), np.nan
    )
    q_BS0 = None
    if check or extrinsics:
        g = float(np.asarray(init.gravity))
        gW = np.array([0.0, 0.0, -g])
        R_i, phi_ref = (np.asarray(x, np.float64) for x in _once(_keyframe_rotations)(_device(qk)))
        phi_imu = _rotation_vectors(_device(pim.delta_q, np.float64))
        dv_imu = np.asarray(pim.delta_v, np.float64)
        dv_ref = np.einsum("kji,kj->ki", R_i, vk[1:] - vk[:-1] - gW * Dt[:, None])
        # the checks judge the windows of the fit only
        phi_imu, phi_ref, dv_imu, dv_ref = (x[kept] for x in (phi_imu, phi_ref, dv_imu, dv_ref))
        found = {}
        if extrinsics:
            theta, stat, source = _initial_rotation(
                phi_imu, phi_ref, dv_imu, dv_ref, reference_sigma
            )
            if source == "none":
                warnings.warn(
                    "the motion determines no rotation between the IMU and the "
                    "reference's body frame (no two independent directions of "
                    "rotation or of velocity change): q_BS starts at the identity",
                    RuntimeWarning,
                    stacklevel=2,
                )
            R0 = np.asarray(_once(so3.exp_matrix)(_device(theta)), np.float64)
            q_BS0 = np.asarray(_once(so3.exp)(_device(theta)), np.float64)
            found = {
                "q_BS0": q_BS0,
                "q_BS0_angle": float(np.linalg.norm(theta)),
                "q_BS0_statistic": stat,
            }
            phi_imu, dv_imu = phi_imu @ R0.T, dv_imu @ R0.T  # the checks on the body's axes
        if check:
            diagnostics = _check_consistency(
                phi_imu, phi_ref, dv_imu, dv_ref, Dt[kept], reference_sigma
            )
        diagnostics.update(found)
    # after the unit and frame checks, which name a wrong unit or frame (a gyro in deg/s turns
    # windows by whole turns, where the rotation's covariance is singular) more usefully
    sqrt_info = _sqrt_information(cov, dtype)

    C = max(1, min(int(windows_per_group), K))
    G = -(-K // C)
    pad = G * C - K

    def grp(x):
        x = np.concatenate([x, np.repeat(x[:1], pad, axis=0)]) if pad else x
        return x.reshape((G, C) + x.shape[1:])

    as_d = lambda x: _device(x, dtype)  # noqa: E731
    return CalibrationProblem(
        gyro=as_d(grp(win_gyro)),
        accel=as_d(grp(win_accel)),
        dt=as_d(grp(win_dt)),
        t_start=as_d(grp(t[idx[:-1]] - t0)),
        t_end=as_d(grp(t[idx[1:]] - t0)),
        window=_device(grp(np.arange(K))),
        weight=as_d(np.concatenate([kept, np.zeros(pad)]).reshape(G, C)),  # padding: 0
        sqrt_info=as_d(grp(sqrt_info)),
        ref_t=as_d(rt - t0),
        ref_q=as_d(rq),
        ref_p=as_d(rp),
        ref_v=as_d(rv),
        velocities=as_d(vk),
        scheme=scheme,
        model=model,
        has_velocity=has_v,
        diagnostics={k: as_d(v) for k, v in diagnostics.items()},
        n_windows=int(K),
        q_BS0=None if q_BS0 is None else as_d(q_BS0),
        extrinsics=bool(extrinsics),
        sample_density2=as_d(
            np.stack(
                [
                    np.broadcast_to(
                        np.asarray(getattr(noise, f"{s}_noise_density"), np.float64) ** 2, (3,)
                    )
                    for s in ("gyroscope", "accelerometer")
                ]
            )
        ),
        reference_var=as_d(grp(extra)),
        omega_coriolis=omega_coriolis,
        max_gap=float(max_gap),
        skipped=skipped,
    )
