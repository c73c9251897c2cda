"""What :func:`jaximu.calibration.calibration_problem` runs once per problem: its compiled
helpers (at the quick compile level for small problems), the unit and frame checks of the
windows' rotations and velocity changes against the reference, and the closed-form initial
IMU-to-body rotation."""

from __future__ import annotations

import functools

import jax
import numpy as np

from jaximu.calibration._model import CalibrationError
from jaximu.engine._preintegration_engine import _preintegrate
from jaximu.geometry import so3

QUICK_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
"""XLA options for graphs that run once or a few times on little data: about half the
compile time, several times the run time (benchmarks/calibration.py --command: a cold
`jaximu calibrate` on 30 s at 200 Hz is mostly compilation)."""
QUICK_COMPILE_SAMPLES = 30_000
"""Problems of at most this many samples (150 s at 200 Hz) compile their fit with
:data:`QUICK_COMPILE`: one evaluation of the residuals and their Jacobian then takes about
0.1 s per 6,000 samples instead of 0.015 s, less than the compile time it saves over the
ten-odd evaluations of a Levenberg–Marquardt fit."""


@functools.cache
def _compiled(fn, quick: bool, static_argnames=()):
    """``jax.jit(fn)``, with :data:`QUICK_COMPILE` when ``quick``."""
    return jax.jit(
        fn, static_argnames=static_argnames, compiler_options=QUICK_COMPILE if quick else None
    )


def _once(fn):
    """``fn`` jitted with :data:`QUICK_COMPILE`, for the one-shot computations of
    :func:`calibration_problem` and its checks: run op by op, JAX would compile every
    primitive apart (about 0.1 s each on 2 cores, 12 s of a cold `jaximu calibrate`)."""
    return _compiled(fn, True)


def _device(x, dtype=None):
    """The host array ``x`` on the device (in ``dtype``, cast by numpy): a transfer, where
    ``jnp.asarray`` compiles a small program for every new shape and dtype (JAX stages it),
    a few dozen per :func:`calibration_problem` of a new size."""
    return jax.device_put(np.asarray(x, dtype))


def _keyframe_rotations(q):
    """``R_i`` ``(K, 3, 3)`` of keyframes ``0..K-1`` and the rotation vectors ``(K, 3)`` of
    ``q_i⁻¹ q_{i+1}``, from ``(K + 1, 4)`` keyframe attitudes."""
    return (so3.quat_to_matrix(q[:-1]), so3.log(so3.quat_mul(so3.quat_conj(q[:-1]), q[1:])))


def _apply(calib, gyro, accel):
    return calib.apply(gyro, accel)


def _preintegrate_sequential(gyro, accel, dt, bias, noise, *, scheme, fast):
    return _preintegrate(
        gyro,
        accel,
        dt,
        bias,
        noise,
        scheme=scheme,
        method="sequential",
        jacobians="analytic",
        prefixes=False,
        fast=fast,
    )


def _rotation_vectors(dq):
    return np.asarray(_once(so3.log)(dq), np.float64)


GYRO_BIAS_MAX = 0.5
"""Largest gyro bias [rad/s] the checks put down to the sensor (29 °/s: beyond the turn-on
bias of any MEMS gyro); a larger steady disagreement with the reference is a unit mistake."""
FRAME_ANGLE_TOL = 0.3
"""Smallest rotation [rad] (17°) between the IMU's axes and the reference's body frame that the
frame check reports, when the data determine it."""
FRAME_SIGNIFICANCE = 21.1
"""χ²(3) at 1 - 1e-4: how far beyond its own uncertainty a fitted rotation must be."""


def _rotation_fit(x, y, floor):
    """Wahba's problem ``y ≈ R x + c`` over rows (the constant absorbs a bias: ``b Δt`` per
    window): the best rotation's vector ``θ`` and the likelihood-ratio statistic of ``R``
    against ``I``, ``(RSS(I) - RSS(R)) / σ²``, ``χ²(3)`` if the frames agree. ``σ²`` is the
    residual variance per component, at least ``floor²`` (the reference's own noise), so
    rows that barely vary (a still segment) cannot make a rotation significant: the check
    judges only what the data can show."""
    x, y = x - x.mean(0), y - y.mean(0)
    U, _, Vt = np.linalg.svd(x.T @ y)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    theta = np.asarray(_once(so3.log_matrix)(_device(R)), np.float64)
    rss_r = float(np.sum((y - x @ R.T) ** 2))
    rss_i = float(np.sum((y - x) ** 2))
    dof = max(3 * len(x) - 6, 1)
    sigma2 = max(rss_r / dof, floor**2, 1e-300)
    return theta, (rss_i - rss_r) / sigma2


def _check_frame(name, x_imu, x_ref, floor, diag):
    label = "gyroscope" if name == "gyro" else "accelerometer"
    what = "rotation" if name == "gyro" else "velocity change"
    if len(x_imu) < 3:
        return
    theta, stat = _rotation_fit(x_imu, x_ref, floor)
    angle = float(np.linalg.norm(theta))
    diag[f"{name}_frame_error"] = angle
    if angle > FRAME_ANGLE_TOL and stat > FRAME_SIGNIFICANCE:
        raise CalibrationError(
            f"the {label}'s axes do not match the reference's body frame: the {what} per "
            f"window fits ref ≈ R imu best with R a rotation of {np.degrees(angle):.0f}° about "
            f"{np.array2string(theta / angle, precision=2)} (likelihood ratio {stat:.3g} against "
            "R = I). Is the reference the pose of the IMU frame, and its quaternion "
            "[w, x, y, z] of R_WB? If the IMU is mounted rotated on the reference's body, pass "
            "extrinsics=True (jaximu calibrate: --estimate ...,q_BS): the rotation then "
            "starts from this fit and is estimated (q_BS)"
        )


def _check_consistency(phi_imu, phi_ref, dv_imu, dv_ref, Dt, reference_sigma=(1e-3, 1e-3, 1e-2)):
    """Catch unit and frame mistakes before fitting (see :func:`calibration_problem`),
    judging only what the data can show and blaming the sensor that is wrong.

    1. Gyro units, where the reference turns (> 0.2 rad/s in at least 3 windows): the
       median ratio of the rotations must be within a factor 3 of 1 (deg/s gives 57).
       Where it does not turn, the gyro's mean rate must not exceed the reference's by more
       than a bias can (:data:`GYRO_BIAS_MAX`): a still deg/s gyro reads its bias × 57.
    2. Accelerometer units: the median ratio of the velocity changes (gravity included,
       always excited) within a factor 3 of 1 (g gives 0.10).
    3. Frames: the best rotation between the IMU's and the reference's rotations (with a
       bias constant) and velocity changes must be below :data:`FRAME_ANGLE_TOL` or not
       significant (:func:`_rotation_fit`; the reference's ``σ_θ``, ``σ_v`` bound the noise
       from below).
    """
    diag = dict.fromkeys(
        ("gyro_ratio", "gyro_frame_error", "accel_ratio", "accel_frame_error"), np.nan
    )
    rate_ref = np.linalg.norm(phi_ref, axis=-1) / Dt
    rate_imu = np.linalg.norm(phi_imu, axis=-1) / Dt
    moving = rate_ref > 0.2  # rad/s; below, a bias could dominate the gyro's magnitude
    if moving.sum() >= 3:
        ratio = float(np.median(rate_imu[moving] / rate_ref[moving]))
        diag["gyro_ratio"] = ratio
        if not 1 / 3 < ratio < 3:
            raise CalibrationError(
                f"the gyroscope's rotation is {ratio:.3g} times the reference's (expected ≈ 1): "
                "a gyro in deg/s read as rad/s gives ≈ 57; convert to rad/s"
            )
    excess = float(np.median(rate_imu - rate_ref))
    if excess > GYRO_BIAS_MAX:
        raise CalibrationError(
            f"the gyroscope reads {float(np.median(rate_imu)):.3g} rad/s (median over the windows) "
            f"where the reference turns at {float(np.median(rate_ref)):.3g} rad/s: more than a "
            f"bias can explain ({GYRO_BIAS_MAX:g} rad/s); is the gyro in deg/s? convert to rad/s"
        )
    ratio = float(
        np.median(
            np.linalg.norm(dv_imu, axis=-1) / np.maximum(np.linalg.norm(dv_ref, axis=-1), 1e-300)
        )
    )
    diag["accel_ratio"] = ratio
    if not 1 / 3 < ratio < 3:
        raise CalibrationError(
            f"the accelerometer's velocity change is {ratio:.3g} times the reference's (expected"
            " ≈ 1): an accelerometer in g read as m/s² gives ≈ 0.10; convert to m/s²"
        )
    s_th, _, s_v = (max(float(x), 0.0) for x in reference_sigma)
    _check_frame("gyro", phi_imu, phi_ref, np.sqrt(2) * s_th, diag)
    _check_frame("accel", dv_imu, dv_ref, np.sqrt(2) * s_v, diag)
    return diag


def _initial_rotation(phi_imu, phi_ref, dv_imu, dv_ref, reference_sigma):
    """The closed-form ``R_BS``: the least-squares rotation (:func:`_rotation_fit`) of the
    windows' rotation vectors (``φ_B = R_BS φ_S``), or, where the rotations do not
    determine it, of their velocity changes (gravity always excites them); the identity
    where neither does. Returns ``(θ, statistic, source)`` with ``R_BS = Exp(θ)``.

    Determined: the second singular value of the centred inputs exceeds 10× the fit's
    residual noise (two independent directions of motion)."""
    s_th, _, s_v = (max(float(x), 0.0) for x in reference_sigma)
    for source, x, y, floor in (
        ("gyro", phi_imu, phi_ref, np.sqrt(2) * s_th),
        ("accel", dv_imu, dv_ref, np.sqrt(2) * s_v),
    ):
        if len(x) < 3:
            continue
        theta, stat = _rotation_fit(x, y, floor)
        xc, yc = x - x.mean(0), y - y.mean(0)
        R = np.asarray(_once(so3.exp_matrix)(_device(theta)), np.float64)
        sigma = np.sqrt(
            max(float(np.sum((yc - xc @ R.T) ** 2)) / max(3 * len(x) - 6, 1), floor**2, 1e-300)
        )
        if np.linalg.svd(xc, compute_uv=False)[1] > 10 * sigma:
            return theta, stat, source
    return np.zeros(3), np.nan, "none"
