"""Keyframe windows over a recording, and their check against its ground truth (what
``jaximu preintegrate`` computes).

* :func:`keyframe_windows`: consecutive windows of a whole number of sample intervals from
  the first sample, each holding its two keyframes (the last sample of a window is the
  first of the next, so the midpoint scheme averages the boundary samples as
  :func:`jaximu.propagate` does).
* :func:`groundtruth_coverage`: which windows a ground truth can check: both keyframes
  inside it, and neither in one of its gaps (a dropout, which interpolation must not
  bridge: the rule of :meth:`jaximu.io.GroundTruth.interpolate`).
* :func:`groundtruth_residuals`: the residual of each window's preintegrated measurement
  (:func:`jaximu.residual`) between the ground-truth states at its keyframes.

Times are in seconds on the recording's clock; the work is on the host (numpy), except the
residual, which runs :func:`jaximu.residual`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from jaximu.engine.preintegration import Preintegrated, residual
from jaximu.geometry import _checks as val
from jaximu.geometry.state import ImuBias, NavState
from jaximu.io import CLOCK_TOLERANCE, GroundTruth
from jaximu.io._common import in_gap

__all__ = [
    "GroundTruthCoverage",
    "KeyframeWindows",
    "groundtruth_coverage",
    "groundtruth_residuals",
    "keyframe_windows",
]


class KeyframeWindows(NamedTuple):
    """``K`` consecutive windows of ``n`` sample intervals (:func:`keyframe_windows`).

    Attributes:
        sample_index: ``(K, n + 1)`` sample indices of each window, from keyframe i
            (column 0) to keyframe j (column ``n``, the next window's column 0):
            ``gyro[sample_index]`` is the ``(K, n + 1, 3)`` input of
            :func:`jaximu.preintegrate`.
        dt: ``(K, n)`` sample intervals [s] of each window (``t[k + 1] - t[k]``).
        t_i: ``(K,)`` time of each window's first keyframe [s].
        t_j: ``(K,)`` time of each window's last keyframe [s].
    """

    sample_index: np.ndarray
    dt: np.ndarray
    t_i: np.ndarray
    t_j: np.ndarray


class GroundTruthCoverage(NamedTuple):
    """Which windows a ground truth can check (:func:`groundtruth_coverage`).

    Attributes:
        inside: ``(K,)`` both keyframes within the ground truth's span (to
            :data:`jaximu.io.CLOCK_TOLERANCE`).
        in_gap: ``(K,)`` inside, with a keyframe in one of the ground truth's gaps.
    """

    inside: np.ndarray
    in_gap: np.ndarray

    @property
    def checked(self) -> np.ndarray:
        """``(K,)`` the windows the ground truth checks: inside it and in none of its gaps."""
        return self.inside & ~self.in_gap


def keyframe_windows(t, samples: int) -> KeyframeWindows:
    """Cut a recording into consecutive windows of ``samples`` intervals from its first sample.

    Window ``k`` holds samples ``k·samples … (k + 1)·samples``; its last sample is the next
    window's first. The samples after the last whole window are left out (``K = (N - 1) //
    samples`` windows).

    Args:
        t: ``(N,)`` sample times [s], finite and strictly increasing.
        samples: sample intervals per window, an integer ``≥ 1`` (``round(seconds · rate)``
            for windows of ``seconds``).

    Returns:
        :class:`KeyframeWindows`.

    Raises:
        ValueError: naming ``t`` (not 1-D, not finite, not strictly increasing) or
            ``samples`` (not a positive integer, or more intervals than ``t`` holds).
    """
    t = val.as_numbers("t", t)
    if t.ndim != 1 or len(t) < 2:
        raise ValueError(f"t must be an (N,) array of at least 2 sample times, got shape {t.shape}")
    val.check_finite("t", t)
    down = np.flatnonzero(np.diff(t) <= 0)
    if down.size:
        i = int(down[0])
        raise ValueError(
            f"t must be strictly increasing, but t[{i}] = {t[i]:.17g} and "
            f"t[{i + 1}] = {t[i + 1]:.17g}"
        )
    n = val.check_int("samples", samples, 1)
    K = (len(t) - 1) // n
    if K < 1:
        raise ValueError(
            f"samples = {n} intervals is more than the {len(t) - 1} intervals of "
            f"t: pass samples ≤ {len(t) - 1}"
        )
    index = np.arange(K)[:, None] * n + np.arange(n + 1)
    return KeyframeWindows(index, np.diff(t)[index[:, :-1]], t[index[:, 0]], t[index[:, -1]])


def groundtruth_coverage(ground_truth, t_i, t_j) -> GroundTruthCoverage:
    """Which windows ``[t_i, t_j]`` the ground truth can check.

    A window is *inside* when ``t_i ≥`` the ground truth's first time and ``t_j ≤`` its last
    (each to :data:`jaximu.io.CLOCK_TOLERANCE`); it is *in a gap* when it is inside and a
    keyframe falls strictly inside an interval of the ground truth longer than
    :data:`jaximu.io.GAP_FACTOR` × its median interval (a mocap dropout:
    :meth:`jaximu.io.GroundTruth.interpolate` refuses such times).

    Args:
        ground_truth: :class:`jaximu.io.GroundTruth` on the recording's clock.
        t_i: ``(K,)`` first keyframe times [s], finite.
        t_j: ``(K,)`` last keyframe times [s], finite (as :class:`KeyframeWindows`).

    Returns:
        :class:`GroundTruthCoverage`.
    """
    gt = _ground_truth(ground_truth)
    t_i, t_j = _times("t_i", t_i), _times("t_j", t_j)
    if t_i.shape != t_j.shape:
        raise ValueError(
            f"t_i and t_j must have the same shape (one entry per window), got "
            f"{t_i.shape} and {t_j.shape}"
        )
    inside = (t_i >= gt.t[0] - CLOCK_TOLERANCE) & (t_j <= gt.t[-1] + CLOCK_TOLERANCE)
    gap = inside & (_in_gap(gt, t_i) | _in_gap(gt, t_j))
    return GroundTruthCoverage(inside, gap)


def groundtruth_residuals(
    pim, ground_truth, t_i, t_j, bias, gravity=9.81, *, omega_coriolis=None
) -> np.ndarray:
    """The residual of each window's measurement between the ground-truth states at its
    keyframes.

    The states at ``t_i`` and ``t_j`` are the ground truth's pose and velocity interpolated
    there (:meth:`jaximu.io.GroundTruth.interpolate`) with the biases ``bias``; the residual
    is :func:`jaximu.residual`'s, in ``pim``'s dtype.

    Args:
        pim: :class:`jaximu.Preintegrated` of ``K`` windows (leading axis ``K``).
        ground_truth: :class:`jaximu.io.GroundTruth` with velocities.
        t_i: ``(K,)`` first keyframe times [s].
        t_j: ``(K,)`` last keyframe times [s].
        bias: :class:`jaximu.ImuBias` of the states (``b_g`` [rad/s], ``b_a`` [m/s²]).
        gravity: as :func:`jaximu.residual`.
        omega_coriolis: as :func:`jaximu.residual`.

    Returns:
        ``(K, 15)`` float64 residuals ``[r_θ, r_p, r_v, r_bg, r_ba]``; the rows of the windows
        the ground truth does not check (:attr:`GroundTruthCoverage.checked` false) are NaN.

    Raises:
        ValueError: a ground truth without velocities, or ``pim`` not of ``K`` windows.
    """
    import jax
    import jax.numpy as jnp

    gt = _ground_truth(ground_truth)
    if gt.v is None:
        raise ValueError(
            "ground_truth has no velocities: the residual compares them "
            "(a pose-only ground truth cannot check a preintegrated measurement)"
        )
    checked = groundtruth_coverage(gt, t_i, t_j).checked
    K = len(checked)
    if not isinstance(pim, Preintegrated) or np.shape(pim.delta_t) != (K,):
        raise ValueError(
            f"pim must be a Preintegrated of {K} windows (one per t_i), got "
            f"{type(pim).__name__} of shape {np.shape(getattr(pim, 'delta_t', ()))}"
        )
    if not isinstance(bias, ImuBias):
        raise ValueError(f"bias must be an ImuBias, got {type(bias).__name__}")
    out = np.full((K, 15), np.nan)
    if not checked.any():
        return out
    rows = np.flatnonzero(checked)
    dtype = pim.delta_p.dtype
    states = []
    for tt in (_times("t_i", t_i)[rows], _times("t_j", t_j)[rows]):
        q, p, v = gt.interpolate(tt)
        states.append(
            NavState(
                jnp.asarray(q, dtype),
                jnp.asarray(p, dtype),
                jnp.asarray(v, dtype),
                bias.b_g,
                bias.b_a,
            )
        )
    sel = jax.tree_util.tree_map(lambda x: x[rows], pim)
    out[rows] = np.asarray(
        residual(states[0], states[1], sel, gravity, omega_coriolis=omega_coriolis), np.float64
    )
    return out


def _ground_truth(gt) -> GroundTruth:
    if not isinstance(gt, GroundTruth):
        raise ValueError(f"ground_truth must be a jaximu.io.GroundTruth, got {type(gt).__name__}")
    return gt


def _times(name, t) -> np.ndarray:
    t = val.as_numbers(name, t)
    if t.ndim != 1:
        raise ValueError(f"{name} must be a (K,) array of keyframe times, got shape {t.shape}")
    val.check_finite(name, t)
    return t


def _in_gap(gt, t):
    """Which of the times ``t`` fall in one of the ground truth's gaps (clamped to its span:
    the rule of :meth:`jaximu.io.GroundTruth.interpolate`, default ``max_gap``)."""
    return in_gap(gt.t, np.clip(t, gt.t[0], gt.t[-1]))[0]
