"""A starting state for a recording, and an estimate's errors against ground truth."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from jaximu.geometry import _checks as val
from jaximu.geometry import _tolerances
from jaximu.geometry.state import NavState  # noqa: PLC0415
from jaximu.io._common import CLOCK_TOLERANCE, QUATERNION_NORM_TOLERANCE, DataError, _seconds
from jaximu.io.containers import GroundTruth, ImuData, _qmul
from jaximu.io.writers import _check_cov, _check_times, _pose_arrays, _sigma


def gravity_alignment(accel_mean) -> np.ndarray:
    """The attitude ``[w, x, y, z]`` of a still IMU from its mean specific force ``(3,)``.

    Roll and pitch put the measured specific force along world +z (still and level reads
    ``[0, 0, +g]``); yaw is not observable from gravity and is set to 0 (ZYX convention,
    ``R = Rz(0) Ry(pitch) Rx(roll)``). ``accel_mean``: ``(3,)`` m/s², finite, non-zero.
    """
    f = np.asarray(accel_mean, np.float64)
    if f.shape != (3,) or not np.all(np.isfinite(f)) or not np.any(f):
        raise ValueError(
            f"accel_mean must be a finite, non-zero (3,) specific force [m/s²], got "
            f"{np.array2string(f, precision=4)}"
        )
    roll = math.atan2(f[1], f[2])
    pitch = math.atan2(-f[0], math.hypot(f[1], f[2]))
    cr, sr, cp, sp = (
        math.cos(roll / 2),
        math.sin(roll / 2),
        math.cos(pitch / 2),
        math.sin(pitch / 2),
    )
    return np.array([cp * cr, cp * sr, sp * cr, -sp * sr])


def initial_state(
    data: ImuData, *, from_groundtruth: bool = False, still_seconds: float = 1.0, bias=None
):
    """A starting :class:`jaximu.NavState` (numpy float64) for a recording, and how it was made.

    Args:
        data: the recording; the state is at ``data.t[0]``.
        from_groundtruth: take q (normalised), p, v and, if ``bias`` is None, the biases from
            the ground truth at ``t[0]`` (v from differences of p when the ground truth has
            none; biases zero when it has none).
        still_seconds: otherwise the attitude comes from gravity alignment of the mean
            specific force over the first ``still_seconds`` (``> 0``; yaw 0), with p = v = 0.
        bias: ``(6,)`` ``[b_g, b_a]`` [rad/s, m/s²] to use (default zero without ground truth).

    Returns:
        ``(state, description)``: the state and one sentence saying where each part came from.
    """
    from_groundtruth = val.check_bool("from_groundtruth", from_groundtruth)
    still_seconds = _seconds("still_seconds", still_seconds, positive=True)
    b = np.zeros(6) if bias is None else val.as_numbers("bias", bias)
    if b.shape != (6,) or not np.all(np.isfinite(b)):
        raise ValueError(
            f"bias must be six finite numbers [b_g (rad/s), b_a (m/s²)], got "
            f"shape {b.shape}" + ("" if b.shape != (6,) else " with NaN or inf")
        )
    t0 = data.t[:1]
    if from_groundtruth:
        gt = data.ground_truth
        if gt is None:
            raise DataError(f"{data.source}: no ground truth to initialise from")
        q, p, _ = gt.interpolate(t0)
        v = gt.velocity(t0)
        how = "initial state from the ground truth"
        if bias is None and gt.b_g is not None and gt.b_a is not None:
            k = int(np.argmin(np.abs(gt.t - t0[0])))
            b = np.r_[gt.b_g[k], gt.b_a[k]]
            how += " (pose, velocity, biases)"
        else:
            how += (
                " (pose, velocity"
                + (")" if gt.v is not None else " from differentiated positions)")
                + (f"; biases {'given' if bias is not None else 'zero'}")
            )
        return NavState(q[0], p[0], v[0], b[:3], b[3:]), how
    still = data.t <= data.t[0] + still_seconds
    if still.sum() < 2:
        raise DataError(f"fewer than 2 samples in the first {still_seconds} s")
    f = data.accel[still].mean(0) - b[3:]
    spread = float(np.linalg.norm(data.gyro[still] - data.gyro[still].mean(0), axis=1).max())
    span = f"{still_seconds:g} s"
    if data.t[-1] < data.t[0] + still_seconds:
        span = (
            f"{data.duration:.3g} s (the whole recording: it is shorter than "
            f"still_seconds = {still_seconds:g} s)"
        )
    how = (
        f"initial attitude from gravity alignment of the first {span} "
        f"(|f| = {np.linalg.norm(f):.3f} m/s², yaw set to 0); position and velocity zero; "
        f"biases {'given' if bias is not None else 'zero'}"
    )
    if spread > 0.1:
        how += (
            f". WARNING: the gyro varies by up to {spread:.2f} rad/s in that interval: the "
            "IMU does not look still, so the alignment may be off"
        )
    q = gravity_alignment(f)
    return NavState(q, np.zeros(3), np.zeros(3), b[:3], b[3:]), how


@dataclasses.dataclass(frozen=True)
class TrajectoryErrors:
    """Estimate against ground truth at the ground-truth times inside the estimate's span.

    Attributes:
        t: ``(K,)`` [s]; position: ``(K, 3)`` ``p̂ - p`` [m]; rotation: ``(K, 3)``
            ``Log(Rᵀ R̂)`` [rad] (body frame, the error state's convention);
        velocity: ``(K, 3)`` ``v̂ - v`` [m/s] or ``None``; sigma: ``(K, 15)`` standard
            deviations of the estimate (interpolated), or ``None``.
    """

    t: np.ndarray
    position: np.ndarray
    rotation: np.ndarray
    velocity: np.ndarray | None
    sigma: np.ndarray | None

    def at(self, seconds, t_start: float | None = None):
        """``(|position|, |velocity| or nan, |rotation| in degrees)`` at the ground-truth stamp
        nearest ``t_start + seconds`` (``t_start``: the estimate's start; default ``t[0]``)."""
        ref = self.t[0] if t_start is None else t_start
        i = int(np.argmin(np.abs(self.t - ref - seconds)))
        vel = float(np.linalg.norm(self.velocity[i])) if self.velocity is not None else math.nan
        return (
            float(np.linalg.norm(self.position[i])),
            vel,
            math.degrees(float(np.linalg.norm(self.rotation[i]))),
        )


def trajectory_errors(t, states, ground_truth: GroundTruth, cov=None) -> TrajectoryErrors:
    """Compare estimated states with ground truth (the estimate is interpolated to the
    ground-truth stamps, so ground-truth dropouts are simply skipped).

    Args:
        t: ``(T,)`` times of the states [s, the ground truth's clock]; states: a
            :class:`jaximu.NavState` with ``(T, ·)`` fields (``q`` unit quaternions, as the
            propagation returns them); cov: ``(T, 15, 15)`` or ``None`` (finite, no negative
            variance).

    Raises:
        ValueError: shapes that do not match, non-finite values, ``t`` not increasing, a
            non-unit ``states.q`` or a negative variance in ``cov``.
    """
    q, p = _pose_arrays(states)
    T = len(q)
    t = _check_times(t, T)
    if T < 2:
        raise ValueError(f"states hold {T} state(s); at least 2 are needed to compare a trajectory")
    back = np.flatnonzero(np.diff(t) <= 0)
    if len(back):
        i = int(back[0])
        raise ValueError(
            f"t must be increasing: t[{i + 1}] = {t[i + 1]:.9g} s follows "
            f"t[{i}] = {t[i]:.9g} s; pass the states in time order"
        )
    # the readers' tolerance: rounding passes, a scaled q does not
    _tolerances.check_unit_norm(
        "states.q",
        q,
        np.float64,
        tol=QUATERNION_NORM_TOLERANCE,
        where=lambda i: f" at row {i[0]}",
        fix="trajectory_errors does not normalise it for you; pass unit "
        "quaternions (q / |q|) if the norm is only rounding, else check "
        "where states.q came from",
    )
    v = val.as_numbers("states.v", states.v)
    if v.shape != (T, 3):
        raise ValueError(f"states.v must have shape ({T}, 3), got {v.shape}")
    val.check_finite("states.v", v)
    if cov is not None:
        cov = _check_cov(cov, T)
    est = GroundTruth(t=t, q=q, p=p, v=v)
    gt = ground_truth
    inside = (gt.t >= t[0] - CLOCK_TOLERANCE) & (gt.t <= t[-1] + CLOCK_TOLERANCE)
    if inside.sum() < 1:
        raise DataError("the ground truth does not overlap the estimate")
    tk = gt.t[inside]
    q_hat, p_hat, v_hat = est.interpolate(tk, max_gap=np.inf)
    q_gt = gt.q[inside] / np.linalg.norm(gt.q[inside], axis=1, keepdims=True)
    d = _qmul(q_gt * np.array([1, -1, -1, -1]), q_hat)
    d *= np.where(d[:, :1] < 0, -1.0, 1.0)
    s = np.linalg.norm(d[:, 1:], axis=1, keepdims=True)
    angle = 2 * np.arctan2(s, d[:, :1])
    rot = np.where(s > 1e-12, angle / np.where(s > 1e-12, s, 1.0), 2.0) * d[:, 1:]
    vel = None if gt.v is None else v_hat - gt.v[inside]
    sigma = None
    if cov is not None:
        var = np.diagonal(cov, axis1=1, axis2=2)
        sigma = _sigma(np.stack([np.interp(tk, t, var[:, j]) for j in range(15)], 1))
    return TrajectoryErrors(
        t=tk, position=p_hat - gt.p[inside], rotation=rot, velocity=vel, sigma=sigma
    )
