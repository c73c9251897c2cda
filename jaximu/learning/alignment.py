"""The ground truth's timing against the integrated gyro's, fitted from the gyro itself.

The integrated gyro and the ground truth may disagree in time by a few milliseconds: a
motion capture stamped on its own clock reads each attitude early or late, and the
integration itself holds each sample over the interval that follows it, so its attitude
lags the true one by about half an interval (2.5 ms at 200 Hz) when each sample is the
rate at its stamp. Over a window of ``H`` samples the increments then differ by about
``ω δ`` at each end (3 mrad at 1 rad/s and 3 ms): on TUM-VI's handheld rooms (``δ`` fitted
3.3–3.4 ms; on EuRoC's five shared recordings 0.6–2.8 ms) more than the rest of the mocap's
noise, and a signal the increment loss rewards a causal network for predicting, which no
correction of the gyro can do well from past samples.
:func:`reference_offset` finds the shift ``δ`` [s] at which the raw gyro's increments over
windows of ``horizon`` samples agree best with the ground truth's (read at ``t + δ``);
:func:`shifted_reference` reads the attitude at the samples there. Training may realign its
parts with them (``TrainConfig(align_reference=True)``); the evaluation compares with the
ground truth as recorded.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaximu.geometry import so3
from jaximu.geometry._checks import check_int, check_number, check_positive
from jaximu.io import DataError
from jaximu.io.containers import GroundTruth
from jaximu.learning.data import Sequence, check_sequence, sign_continuous
from jaximu.learning.evaluation import integrate_attitude

__all__ = ["reference_offset", "shifted_reference"]


def _stamps(seq: Sequence):
    """The ground truth's own stamps [s] and unit attitudes ``(M, 4)``."""
    tau, q = seq.stamps()
    return np.asarray(tau, np.float64), np.asarray(q, np.float64)


def _attitude_at(seq: Sequence, t):
    """``(K, 4)`` the ground truth's attitude slerped at ``t`` [s] (held at its ends)."""
    tau, q = _stamps(seq)
    gt = GroundTruth(tau, q, np.zeros((len(tau), 3)))
    q_t, _, _ = gt.interpolate(np.clip(t, tau[0], tau[-1]), max_gap=np.inf)
    return q_t


def shifted_reference(seq: Sequence, shift: float) -> Sequence:
    """``seq`` with its attitude at each sample ``k`` read from the ground truth at
    ``t_k + shift`` (``shift`` [s], finite; slerped between the ground truth's own stamps
    and held at its ends): a ground truth whose clock runs ``shift`` behind the IMU's,
    realigned. Its other fields (positions, references, stamps) are kept."""
    check_sequence("seq", seq)
    shift = check_number("shift", shift)
    if not np.isfinite(shift):
        raise ValueError(f"shift must be a finite number of seconds, got {shift!r}")
    return dataclasses.replace(seq, q=sign_continuous(_attitude_at(seq, seq.t + shift)))


def _increments(q, H: int):
    """``(W, 4)``: ``q_kᵀ q_{k+H}`` of consecutive windows of ``H`` samples."""
    n = (len(q) - 1) // H
    ends = q[0 : n * H + 1 : H]
    return np.asarray(so3.quat_mul(so3.quat_conj(ends[:-1]), ends[1:]))


def _misfit(seq: Sequence, dq_gyro, keep, shift: float, H: int) -> float:
    """The mean squared increment residual [rad²] at ``shift``, about its mean (a constant
    gyro bias moves every window alike and is no misalignment)."""
    dq_true = _increments(_attitude_at(seq, seq.t + shift), H)
    r = np.asarray(so3.log(so3.quat_mul(so3.quat_conj(dq_true), dq_gyro)))[keep]
    return float(np.mean(np.sum((r - r.mean(0)) ** 2, -1)))


def reference_offset(
    seq: Sequence, horizon: int = 64, search: float = 0.02, resolution: float = 1e-3
) -> float:
    """The shift ``δ`` [s] of the ground truth's clock that best explains the raw gyro.

    The raw gyro (less the ground truth's mean bias, when it has one) is integrated over
    consecutive windows of ``horizon`` samples and compared with the ground truth's
    increments read at ``t + δ``, over the windows with a reference at both ends; ``δ`` is
    the minimum of their mean squared residual (about its mean) on a grid of ``resolution``
    over ``[-search, search]``, refined by the parabola through it and its neighbours.

    Args:
        seq: a :class:`Sequence` with its ground truth's own stamps.
        horizon: the windows' length [samples], at least 2 (64: a third of a second at
            200 Hz, where TUM-VI's residual is the misalignment's rather than the noise's).
        search, resolution: the range and grid of shifts [s], positive, ``resolution`` at
            most ``search``.

    Returns:
        ``δ`` [s]: train on :func:`shifted_reference` ``(seq, δ)``. A minimum at the
        search's edge is returned as the edge.

    Raises:
        DataError: fewer than 3 windows with a reference at both ends.
    """
    check_sequence("seq", seq)
    H = check_int("horizon", horizon, 2)
    search = check_positive("search", search, hint=" [s]")
    resolution = check_positive("resolution", resolution, hint=" [s]")
    if resolution > search:
        raise ValueError(
            f"resolution ({resolution:g} s) must be at most search ({search:g} s): pass a "
            f"finer grid, e.g. resolution={search / 10:g}"
        )
    gyro = seq.gyro - (0.0 if seq.b_g is None else seq.b_g.mean(0))
    # the gyro's attitude, each sample held over its own interval
    q = np.asarray(integrate_attitude(seq.q[0], gyro, np.diff(seq.t)), np.float64)
    dq_gyro = _increments(q, H)
    ref = seq.has_reference
    n = len(dq_gyro)
    keep = ref[0 : n * H : H] & ref[H : n * H + 1 : H]
    if keep.sum() < 3:
        raise DataError(
            f"sequence {seq.name!r}: {int(keep.sum())} windows of {H} samples with a "
            "reference at both ends; at least 3 are needed to fit the ground truth's clock "
            "offset (give a longer recording or a shorter horizon)"
        )
    grid = np.arange(-round(search / resolution), round(search / resolution) + 1) * resolution
    cost = np.array([_misfit(seq, dq_gyro, keep, d, H) for d in grid])
    i = int(np.argmin(cost))
    if i == 0 or i == len(grid) - 1:
        return float(grid[i])
    a, b, c = cost[i - 1 : i + 2]
    curvature = a - 2 * b + c
    step = 0.5 * (a - c) / curvature if curvature > 0 else 0.0
    return float(grid[i] + np.clip(step, -1.0, 1.0) * resolution)
