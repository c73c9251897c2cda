"""Allan deviation of a static IMU recording, and the fit of its noise densities.

For a rate signal ``y`` sampled every ``dt`` (gyro [rad/s] or accelerometer [m/s²]) and the
cluster time ``τ = m·dt``, the overlapping Allan variance is (IEEE Std 952, with
``θ = cumsum(y)·dt`` the integrated signal):

    σ²(τ) = Σ_k (θ_{k+2m} - 2 θ_{k+m} + θ_k)² / (2 τ² (N - 2m)).

White noise of density ``σ_w`` gives ``σ(τ) = σ_w / √τ`` (slope -1/2: ``σ_w = σ(1 s)``); a bias
random walk of density ``σ_rw`` gives ``σ(τ) = σ_rw √(τ/3)`` (slope +1/2: ``σ_rw = σ(3 s)``).
:func:`fit_noise` fits ``σ²(τ) = σ_w²/τ + σ_rw² τ/3`` by weighted least squares, which returns
exactly the Kalibr parameters of :class:`jaximu.ImuNoise` (``*_noise_density``,
``*_random_walk``).

Both need a static recording: :func:`motion_ratio` says whether a signal looks static (its
spread does not survive averaging), and :func:`static_intervals` finds the stretches of a
recording that do.
"""

from __future__ import annotations

import itertools
import numbers
from typing import NamedTuple

import numpy as np

from jaximu.errors import Fix, InputError
from jaximu.geometry import _checks as val

__all__ = [
    "GYRO_WHITE_MAX",
    "STATIC_MOTION_RATIO",
    "VISIBLE",
    "NoiseFit",
    "allan_deviation",
    "check_units",
    "fit_noise",
    "motion_ratio",
    "static_intervals",
]

VISIBLE = 0.1
"""The share of the fitted ``σ²(τ)`` that a term must reach at some τ of the fit to count as
determined by :func:`fit_noise` (below it, the term is returned as 0: not determined)."""

GYRO_WHITE_MAX = 2e-3
"""Largest plausible gyro white-noise density [rad/s/√Hz] (0.11 °/s/√Hz: four times the
noisiest consumer MEMS gyro's datasheet figure, 0.03 °/s/√Hz)."""


def allan_deviation(y, dt: float, taus=None, points_per_decade: int = 10):
    """Overlapping Allan deviation of rate samples.

    Args:
        y: ``(N,)`` or ``(N, d)`` real samples (e.g. the three gyro axes), constant rate
            ``1/dt``.
        dt: sample period [s].
        taus: cluster times [s], strictly increasing (an unsorted or repeated list is
            refused: the output follows their order). Each is rounded to a whole number of
            samples, at least one, and the returned ``taus`` are those used (one per given
            τ, in order; compare them with yours: a τ below ``dt`` comes back as ``dt``).
            Default: log-spaced from ``dt`` to ``N·dt/10`` (at least ~10 independent
            clusters at the longest τ).
        points_per_decade: density of the default τ grid.

    Returns:
        ``(taus, adev)``: ``(M,)`` and ``(M,)`` or ``(M, d)``, finite.

    Raises:
        ValueError: on a wrong shape, fewer than 10 samples, non-finite, complex or text
            samples, a ``dt`` or ``τ`` that is not positive and finite, ``taus`` not strictly
            increasing, a ``τ`` of half the recording or more, or a result that overflows
            float64 (samples near the float64 limit).
    """
    y = _real_array("y", y)
    if y.ndim not in (1, 2):
        raise ValueError(f"y must have shape (N,) or (N, d), got {y.shape}")
    squeeze = y.ndim == 1
    y = y[:, None] if squeeze else y
    n = y.shape[0]
    if n < 10:
        raise ValueError(f"need at least 10 samples, got {n}")
    if np.ndim(dt) != 0:
        raise ValueError(f"dt must be a scalar sample period, got shape {np.shape(dt)}")
    if isinstance(dt, (str, bytes, bool, np.bool_)) or np.iscomplexobj(dt):
        raise ValueError(f"dt must be a real number of seconds, got {type(dt).__name__} {dt!r}")
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be positive and finite, got {dt}")
    if not np.all(np.isfinite(y)):
        bad = np.argwhere(~np.isfinite(y))[0]
        raise ValueError(
            f"y contains non-finite values (NaN or inf), first at sample {bad[0]}"
            + ("" if squeeze else f", column {bad[1]}")
        )
    if taus is None:
        if not isinstance(points_per_decade, numbers.Real) or isinstance(points_per_decade, bool):
            raise ValueError(
                f"points_per_decade must be a positive number, got {points_per_decade!r}"
            )
        if not points_per_decade > 0:
            raise ValueError(f"points_per_decade must be positive, got {points_per_decade}")
        m_max = max(1, n // 10)
        ms = np.unique(
            np.round(
                np.logspace(0, np.log10(m_max), int(np.log10(m_max) * points_per_decade) + 1)
            ).astype(int)
        )
    else:
        taus = _real_array("taus", taus)
        if taus.ndim > 1:
            raise ValueError(f"taus must be a 1-D list of cluster times, got shape {taus.shape}")
        taus = np.atleast_1d(taus)
        if not np.all(np.isfinite(taus) & (taus > 0)):
            raise ValueError(f"every τ must be positive and finite, got {taus}")
        down = np.flatnonzero(np.diff(taus) <= 0)
        if down.size:
            i = int(down[0])
            raise ValueError(
                f"taus must be strictly increasing (the output follows their "
                f"order), but taus[{i}] = {taus[i]:g} and taus[{i + 1}] = "
                f"{taus[i + 1]:g}; pass np.unique(taus)"
            )
        with np.errstate(over="ignore"):
            ms = np.maximum(1, np.round(taus / dt))
        if np.any(2 * ms >= n):
            i = int(np.argmax(2 * ms >= n))
            longest = (n - 1) // 2 * dt
            raise ValueError(
                f"every τ must be shorter than half the recording: taus[{i}] = {taus[i]:g} s, "
                f"and the {n} samples of {dt:g} s hold clusters of at most {longest:g} s; "
                f"pass taus up to {longest:g} s (or a longer recording)"
            )
        ms = ms.astype(int)
    # Overflow (|y| or dt near the float64 limits) is reported below, not warned about.
    with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
        theta = np.concatenate([np.zeros((1, y.shape[1])), np.cumsum(y, axis=0) * dt])
        adev = np.empty((len(ms), y.shape[1]))
        for i, m in enumerate(ms):
            d = theta[2 * m :] - 2 * theta[m:-m] + theta[: -2 * m]
            tau = m * dt
            adev[i] = np.sqrt(np.sum(d * d, axis=0) / (2 * tau * tau * (n + 1 - 2 * m)))
    if not np.all(np.isfinite(adev)):
        i, j = np.argwhere(~np.isfinite(adev))[0]
        raise ValueError(
            f"the Allan deviation overflowed float64 at τ = {ms[i] * dt:g}"
            + ("" if squeeze else f", column {j}")
            + ": y or dt is too large (or dt too small); rescale the samples"
        )
    taus = ms * dt
    return taus, (adev[:, 0] if squeeze else adev)


STATIC_MOTION_RATIO = 0.3
"""The :func:`motion_ratio` below which a signal looks static. White noise about a constant
(a still gyro about its bias) has ``1/√m`` for ``m`` samples per window (0.07 for 1 s at
200 Hz); motion varies slowly, survives the averaging and keeps the ratio near 1."""


def motion_ratio(y, dt: float, window: float = 1.0) -> float:
    """How much of a signal's spread survives averaging over ``window`` seconds.

    The standard deviation of the means of consecutive ``window``-second stretches over the
    standard deviation of the samples, the largest over the axes (:data:`STATIC_MOTION_RATIO`
    tells static from moving). White noise about a constant gives ``≈ 1/√m`` (``m``
    samples per window); a signal constant over each window (slow motion) gives ≈ 1. The
    ratio does not depend on the unit: a still gyro in deg/s spreads 57× more than in rad/s,
    and its ratio is the same.

    Args:
        y: ``(N,)`` or ``(N, d)`` real samples at a constant rate ``1/dt`` (e.g. the gyro
            [rad/s]), finite.
        dt: sample period [s], positive and finite.
        window: averaging time [s], positive and finite; rounded to a whole number ``m`` of
            samples, at least one. The samples after the last whole window count in the
            samples' spread only.

    Returns:
        The ratio (a float ≥ 0; an axis whose samples are all equal counts 0), or NaN when
        ``y`` holds fewer than two whole windows (too short to judge).

    Raises:
        ValueError: naming ``y``, ``dt`` or ``window`` outside that domain.
    """
    y = _real_array("y", y)
    if y.ndim not in (1, 2) or len(y) < 1:
        raise ValueError(f"y must have shape (N,) or (N, d), got {y.shape}")
    if not np.all(np.isfinite(y)):
        raise ValueError(
            f"y contains non-finite values (NaN or inf), first at sample "
            f"{int(np.argwhere(~np.isfinite(y))[0][0])}"
        )
    dt, window = val.check_positive("dt", dt), val.check_positive("window", window)
    m = max(1, round(window / dt))
    n = len(y) // m
    if n < 2:
        return float("nan")
    means = y[: n * m].reshape(n, m, -1).mean(1)
    return float(np.max(means.std(0) / np.maximum(y.std(0), 1e-300)))


def static_intervals(y, dt: float, segment: float = 10.0, window: float = 1.0) -> np.ndarray:
    """The stretches of a recording that look static (for :func:`allan_deviation`).

    The recording is cut into consecutive ``segment``-second pieces (the samples after the
    last whole piece join it); a piece whose :func:`motion_ratio` over ``window`` is below
    :data:`STATIC_MOTION_RATIO` is static, and neighbouring static pieces are merged. A piece
    too short to judge (fewer than two windows: a recording shorter than ``2·window``) is
    not static.

    Args:
        y: ``(N,)`` or ``(N, d)`` real samples at a constant rate ``1/dt`` (the gyro, which
            tells motion best), finite.
        dt: sample period [s], positive and finite.
        segment: length [s] of the pieces judged, at least ``2·window``.
        window: averaging time [s] of :func:`motion_ratio`, positive and finite.

    Returns:
        ``(M, 2)`` integer sample ranges ``[start, stop)`` of the static stretches, in order
        (``(0, 2)`` when none is static): ``y[start:stop]``.

    Raises:
        ValueError: naming ``y``, ``dt``, ``segment`` or ``window`` outside that domain.
    """
    y = _real_array("y", y)
    dt, window = val.check_positive("dt", dt), val.check_positive("window", window)
    segment = val.check_positive("segment", segment)
    if segment < 2 * window:
        raise ValueError(
            f"segment = {segment:g} s must hold at least two windows of "
            f"{window:g} s (motion_ratio compares their means): pass segment ≥ "
            f"{2 * window:g}"
        )
    m = max(1, round(segment / dt))
    bounds = np.r_[np.arange(0, max(len(y) // m, 1)) * m, len(y)]
    still = [
        motion_ratio(y[a:b], dt, window) < STATIC_MOTION_RATIO  # NaN: not static
        for a, b in itertools.pairwise(bounds)
    ]
    out: list[list[int]] = []
    for k, s in enumerate(still):
        if s and out and out[-1][1] == bounds[k]:
            out[-1][1] = bounds[k + 1]
        elif s:
            out.append([bounds[k], bounds[k + 1]])
    return np.array(out, dtype=np.int64).reshape(-1, 2)


def _real_array(name, x) -> np.ndarray:
    """``x`` as a float64 array; complex (its imaginary part would be dropped), bool, text
    (never parsed for you) or ragged input raises a ``ValueError`` naming ``name``."""
    val.check_real(name, x)
    if val.kind_of(x) not in "fiu":
        shown = repr(x)
        shown = shown if len(shown) <= 60 else shown[:57] + "..."
        raise ValueError(f"{name} must be an array of numbers, got {type(x).__name__} {shown}")
    return val.as_numbers(name, x)  # a JAX tracer: named too (this runs on the host)


class NoiseFit(NamedTuple):
    """White-noise density and random-walk density fitted to an Allan deviation.

    A density of exactly 0 means **not determined**, not "no noise": the data did not show
    a term of that slope (its least-squares coefficient came out negative, or the term
    stayed below :data:`VISIBLE` of the fitted ``σ²`` at every τ: motion in the recording,
    or one too short for the random walk to show), so the fit dropped it.
    :attr:`white_determined` and :attr:`random_walk_determined` flag those entries; do not
    use them as densities (an :class:`jaximu.ImuNoise` with a 0 density claims a perfect
    sensor).

    Attributes:
        white: ``σ_w`` [unit/√Hz] (``gyroscope_noise_density`` or ``accelerometer_noise_density``).
        random_walk: ``σ_rw`` [unit·√Hz] (``gyroscope_random_walk``, ``accelerometer_random_walk``).
    """

    white: np.ndarray
    random_walk: np.ndarray

    @property
    def white_determined(self) -> np.ndarray:
        """``False`` where the fit could not determine :attr:`white` (returned as 0)."""
        return np.asarray(self.white) > 0

    @property
    def random_walk_determined(self) -> np.ndarray:
        """``False`` where the fit could not determine :attr:`random_walk` (returned as 0)."""
        return np.asarray(self.random_walk) > 0

    def model(self, taus):
        """The fitted ``σ(τ)``."""
        taus = np.asarray(taus, float)[:, None] if np.ndim(self.white) else np.asarray(taus, float)
        return np.sqrt(self.white**2 / taus + self.random_walk**2 * taus / 3)


def fit_noise(taus, adev) -> NoiseFit:
    """Fit ``σ²(τ) = σ_w²/τ + σ_rw² τ/3`` to an Allan deviation (per column).

    Weighted least squares on the relative error of ``σ²``, weighted by ``τ^(-1/2)``: the
    relative uncertainty of an overlapping Allan variance grows like ``√(τ/T)`` (fewer
    independent clusters), so long τ count less. Both coefficients are kept non-negative:
    a term whose coefficient comes out negative, or that stays below :data:`VISIBLE` of the
    fitted ``σ²(τ)`` at every τ, is dropped (the other refitted alone) and returned as
    exactly 0, which means *not determined* (see :class:`NoiseFit`, whose
    ``white_determined`` and ``random_walk_determined`` flag it).

    Args:
        taus: ``(n,)`` cluster times [s], positive and finite, at least 2.
        adev: ``(n,)`` or ``(n, d)`` Allan deviations at ``taus``, positive and finite (as
            :func:`allan_deviation` returns them).

    Raises:
        ValueError: naming ``taus`` or ``adev`` when they are outside that domain.
    """
    taus = _real_array("taus", taus)
    adev = _real_array("adev", adev)
    if taus.ndim != 1 or len(taus) < 2:
        raise ValueError(
            f"taus must be a 1-D array of at least 2 cluster times, got shape {taus.shape}"
        )
    if adev.ndim not in (1, 2):
        raise ValueError(f"adev must have shape (n,) or (n, d), got {adev.shape}")
    if adev.shape[0] != len(taus):
        raise ValueError(f"taus and adev have different lengths: {len(taus)} and {adev.shape[0]}")
    if not np.all(np.isfinite(taus) & (taus > 0)):
        raise ValueError(
            f"taus must be positive and finite, got {taus[~(np.isfinite(taus) & (taus > 0))][0]} "
            f"at index {int(np.argmax(~(np.isfinite(taus) & (taus > 0))))}"
        )
    bad = ~np.isfinite(adev)
    if bad.any():
        i = tuple(int(k) for k in np.argwhere(bad)[0])
        raise ValueError(f"adev contains non-finite values (NaN or inf), first at index {list(i)}")
    if np.any(adev <= 0):
        i = tuple(int(k) for k in np.argwhere(adev <= 0)[0])
        raise ValueError(
            f"adev must be positive (a constant signal has no noise to fit), got "
            f"{adev[i]} at index {list(i)}"
        )
    squeeze = adev.ndim == 1
    adev = adev[:, None] if squeeze else adev
    white, walk = [], []
    A = np.stack([1 / taus, taus / 3], axis=1)
    for col in adev.T:
        w = 1 / (col**2 * np.sqrt(taus))

        def alone(j):  # the fit with term j only (the other absent), and its cost
            c = np.zeros(2)
            c[j] = max(np.sum(A[:, j] * col**2 * w * w) / np.sum((A[:, j] * w) ** 2), 0.0)
            return np.sum(((A @ c) * w - col**2 * w) ** 2), c

        coef, *_ = np.linalg.lstsq(A * w[:, None], col**2 * w, rcond=None)
        if coef[0] < 0 or coef[1] < 0:  # one term absent: fit the other alone
            coef = min((alone(0), alone(1)), key=lambda x: x[0])[1]
        share = (A * coef) / np.maximum(A @ coef, np.finfo(float).tiny)[:, None]
        hidden = np.flatnonzero(share.max(axis=0) < VISIBLE)
        if hidden.size == 1:  # a term never visible in the curve: not determined
            coef = alone(1 - int(hidden[0]))[1]
        white.append(np.sqrt(max(coef[0], 0.0)))
        walk.append(np.sqrt(max(coef[1], 0.0)))
    w, r = np.array(white), np.array(walk)
    return NoiseFit(w[0], r[0]) if squeeze else NoiseFit(w, r)


def check_units(gyro: NoiseFit, accel: NoiseFit | None = None):
    """Refuse gyro densities that are implausible in rad/s: a static recording whose gyro is
    in deg/s gives densities 57× too large (EuRoC's ADIS16448, 1.7e-4 rad/s/√Hz, reads
    9.7e-3), which nothing downstream would notice.

    Raises :class:`jaximu.errors.InputError` (a ``ValueError``) whose fixes are
    ``gyro_unit='deg/s'`` (the readers' option) or ``check_units=False``, when the median
    white-noise density over the axes exceeds :data:`GYRO_WHITE_MAX` (over the axes whose
    density was determined; with none determined there is nothing to judge). A gyro in deg/s
    that is quieter than 3.5e-5 rad/s/√Hz (tactical grade) is not caught; motion in a recording
    that is not static inflates the densities and can trip the check.
    """
    del accel  # the accelerometer's unit is judged by the readers (gravity's magnitude)
    if not isinstance(gyro, NoiseFit):
        raise ValueError(
            f"gyro must be the NoiseFit of the gyro (from allan.fit_noise), got "
            f"{type(gyro).__name__}"
        )
    white = np.atleast_1d(np.asarray(gyro.white, float))
    white = white[white > 0]  # the axes whose density was determined
    if white.size == 0:
        return
    median = float(np.median(white))
    if median > GYRO_WHITE_MAX:
        raise InputError(
            f"the gyro white-noise density {median:.3g} rad/s/√Hz is implausible for an IMU in "
            f"rad/s (the noisiest MEMS gyros stay below {GYRO_WHITE_MAX:g}; read as deg/s it is "
            f"{np.deg2rad(median):.3g} rad/s/√Hz): is the gyro in deg/s, or the recording not "
            "static?",
            [Fix("gyro_unit", "deg/s"), Fix("check_units", False)],
            sep=" ",
        )
