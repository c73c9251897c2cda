"""The recording and ground-truth containers (:class:`ImuData`, :class:`GroundTruth`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from jaximu.geometry import _checks as val
from jaximu.io._common import CLOCK_TOLERANCE, GAP_FACTOR, DataError, _max_gap, _seconds, in_gap


def _qmul(a, b):
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return np.concatenate(
        [aw * bw - np.sum(av * bv, -1, keepdims=True), aw * bv + bw * av + np.cross(av, bv)], -1
    )


def _slerp(q0, q1, alpha):
    """``q0 ⊗ Exp(α Log(q0* ⊗ q1))`` on normalised float64 quaternions (shortest arc)."""
    q0 = q0 / np.linalg.norm(q0, axis=-1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=-1, keepdims=True)
    d = _qmul(q0 * np.array([1, -1, -1, -1]), q1)
    d *= np.where(d[..., :1] < 0, -1.0, 1.0)
    s = np.linalg.norm(d[..., 1:], axis=-1, keepdims=True)
    half = np.arctan2(s, d[..., :1])  # half the relative angle, in [0, π/2]
    a = np.asarray(alpha, np.float64)[..., None]
    # sin(α·half)/s, with its limit α as s → 0
    ratio = np.where(s > 1e-12, np.sin(a * half) / np.where(s > 1e-12, s, 1.0), a)
    step = np.concatenate([np.cos(a * half), ratio * d[..., 1:]], -1)
    return _qmul(q0, step)


@dataclasses.dataclass(frozen=True)
class GroundTruth:
    """Reference trajectory on the IMU clock (numpy, float64).

    Attributes:
        t: ``(M,)`` times [s] since the recording's ``t0_ns``.
        q: ``(M, 4)`` Hamilton ``[w, x, y, z]`` of ``R_WB`` as stored (not normalised; the
            EuRoC files deviate from unit norm by up to 1.5e-4).
        p: ``(M, 3)`` position of the IMU in W [m].
        v: ``(M, 3)`` velocity in W [m/s], or ``None`` (TUM-VI's mocap has none).
        b_g, b_a: ``(M, 3)`` bias estimates [rad/s], [m/s²], or ``None``.
    """

    t: np.ndarray
    q: np.ndarray
    p: np.ndarray
    v: np.ndarray | None = None
    b_g: np.ndarray | None = None
    b_a: np.ndarray | None = None

    def __post_init__(self):
        M = np.shape(self.t)[0] if np.ndim(self.t) == 1 else None
        if M is None:
            raise ValueError(f"GroundTruth.t must have shape (M,), got {np.shape(self.t)}")
        for name, width in (("q", 4), ("p", 3), ("v", 3), ("b_g", 3), ("b_a", 3)):
            x = getattr(self, name)
            if x is not None and np.shape(x) != (M, width):
                raise ValueError(
                    f"GroundTruth.{name} must have shape ({M}, {width}) (one row "
                    f"per time in t), got {np.shape(x)}"
                )
        if M < 2:
            raise DataError(
                f"the ground truth has {M} row(s); at least 2 are needed to interpolate it"
            )

    def __len__(self):
        return len(self.t)

    def interpolate(self, t, max_gap: float | None = None):
        """Pose (and velocity) at times ``t`` [s]: slerp of the normalised quaternions,
        linear in p and v.

        Args:
            t: ``(K,)`` query times inside ``[t[0], t[-1]]`` (up to ``CLOCK_TOLERANCE``
                outside is clamped: EuRoC's ground truth lies on the IMU grid within 3 µs).
            max_gap: refuse to interpolate across ground-truth gaps longer than this [s]
                (default: ``GAP_FACTOR`` × the median interval; mocap has dropouts).

        Returns:
            ``(q, p, v)``: ``(K, 4)`` unit quaternions, ``(K, 3)``, ``(K, 3)`` or ``None``.

        Raises:
            ValueError: ``t`` not finite numbers; ``max_gap`` not a positive number.
            DataError: ``t`` outside the ground truth, or inside a gap.
        """
        max_gap = _max_gap(max_gap)
        t = np.atleast_1d(val.as_numbers("t", t))
        val.check_finite("t", t)
        if t.min() < self.t[0] - CLOCK_TOLERANCE or t.max() > self.t[-1] + CLOCK_TOLERANCE:
            raise DataError(
                f"ground truth covers [{self.t[0]:.6f}, {self.t[-1]:.6f}] s, asked for "
                f"[{t.min():.6f}, {t.max():.6f}] s"
            )
        t = np.clip(t, self.t[0], self.t[-1])
        gaps = np.diff(self.t)
        across, k, limit = in_gap(self.t, t, max_gap)
        if across.any():
            i = int(np.argmax(across))
            raise DataError(
                f"ground truth has a {gaps[k[i]]:.3f} s gap at t = {self.t[k[i]]:.3f} s; "
                f"t = {t[i]:.3f} s falls inside it (max_gap = {limit:.4f} s)"
            )
        q = _slerp(self.q[k], self.q[k + 1], (t - self.t[k]) / gaps[k])
        p = np.stack([np.interp(t, self.t, self.p[:, j]) for j in range(3)], axis=1)
        v = None
        if self.v is not None:
            v = np.stack([np.interp(t, self.t, self.v[:, j]) for j in range(3)], axis=1)
        return q, p, v

    def velocity(self, t, max_gap: float | None = None):
        """Velocity at ``t``: the stored one, or central differences of the positions
        (``max_gap``: as in :meth:`interpolate`)."""
        if self.v is not None:
            return self.interpolate(t, max_gap)[2]
        t = np.atleast_1d(np.asarray(t, np.float64))
        h = float(np.median(np.diff(self.t)))
        lo, hi = np.maximum(t - h, self.t[0]), np.minimum(t + h, self.t[-1])
        p_hi, p_lo = self.interpolate(hi, max_gap)[1], self.interpolate(lo, max_gap)[1]
        return (p_hi - p_lo) / (hi - lo)[:, None]


@dataclasses.dataclass(frozen=True)
class ImuData:
    """An IMU recording (numpy; times float64).

    Attributes:
        stamps_ns: ``(N,)`` int64 stamps [ns] as read (exact: EuRoC's nanoseconds survive).
        t: ``(N,)`` float64 seconds since ``t0_ns`` (``stamps_ns - t0_ns``, exact to 1e-16
            relative; absolute epoch seconds in float64 would round to ~0.2 µs).
        gyro: ``(N, 3)`` raw angular rate in the IMU frame [rad/s].
        accel: ``(N, 3)`` raw specific force in the IMU frame [m/s²].
        t0_ns: the stamp of ``t = 0`` [ns].
        ground_truth: :class:`GroundTruth` on the same clock, or ``None``.
        source: where it came from.
        repairs: what the repair options changed, one sentence each (empty if nothing).
    """

    stamps_ns: np.ndarray
    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    t0_ns: int
    ground_truth: GroundTruth | None = None
    source: str = ""
    repairs: tuple[str, ...] = ()

    def __len__(self):
        return len(self.t)

    @property
    def dt(self) -> np.ndarray:
        """``(N-1,)`` intervals [s] between consecutive samples (the ``dt`` that
        :func:`jaximu.propagate` takes with the interval convention)."""
        return np.diff(self.t)

    @property
    def rate_hz(self) -> float:
        return 1.0 / float(np.median(self.dt))

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    def select(self, index) -> ImuData:
        """The samples at ``index`` (a slice, integer indices or an ``(N,)`` boolean mask);
        times stay relative to ``t0_ns``."""
        if not isinstance(index, slice):
            idx = np.asarray(index)
            n = len(self)
            if idx.dtype == bool:
                if idx.shape != (n,):
                    raise ValueError(
                        f"index: a boolean mask must have shape ({n},) (one entry "
                        f"per sample), got {idx.shape}"
                    )
            elif idx.dtype.kind not in "iu" and idx.size:
                raise ValueError(
                    f"index must be a slice, integer indices or a boolean mask, "
                    f"got {idx.dtype.name} {index!r}"[:200]
                )
            elif idx.size and (idx.min() < -n or idx.max() >= n):
                raise ValueError(
                    f"index holds {int(idx.min() if idx.min() < -n else idx.max())}"
                    f", outside the {n} samples"
                )
            else:
                index = idx.astype(np.intp)
        return dataclasses.replace(
            self,
            stamps_ns=self.stamps_ns[index],
            t=self.t[index],
            gyro=self.gyro[index],
            accel=self.accel[index],
        )

    def window(self, start: float = 0.0, duration: float | None = None) -> ImuData:
        """Samples with ``start ≤ t ≤ start + duration`` [s since ``t0_ns``]
        (``duration``: ``> 0``; ``None``: to the end)."""
        start = _seconds("start", start)
        end = np.inf if duration is None else start + _seconds("duration", duration, positive=True)
        keep = (self.t >= start - 1e-12) & (self.t <= end + 1e-12)
        if keep.sum() < 2:
            shown = "the end" if end == np.inf else f"{end:.6g} s"
            raise DataError(
                f"the window [{start:.6g} s, {shown}] holds fewer than 2 samples "
                f"(the recording spans [{self.t[0]:.3f}, {self.t[-1]:.3f}] s)"
            )
        return self.select(np.flatnonzero(keep))

    def gaps(self, max_gap: float | None = None) -> np.ndarray:
        """Indices ``i`` with ``t[i+1] - t[i] > max_gap`` (default ``GAP_FACTOR`` × median)."""
        max_gap = _max_gap(max_gap)
        d = self.dt
        limit = max_gap if max_gap is not None else GAP_FACTOR * float(np.median(d))
        return np.flatnonzero(d > limit)

    def split_at_gaps(self, max_gap: float | None = None, min_samples: int = 2) -> list[ImuData]:
        """Pieces between gaps longer than ``max_gap``; each piece's :attr:`repairs` says
        where it was cut. Pieces with fewer than ``min_samples`` samples are dropped, and
        that is said too."""
        cuts = self.gaps(max_gap)
        bounds = np.r_[0, cuts + 1, len(self)]
        pieces, dropped = [], []
        for lo, hi in zip(bounds[:-1], bounds[1:]):
            if hi - lo < min_samples:
                dropped.append((int(lo), int(hi)))
                continue
            note = (
                f"split at {len(cuts)} gap(s): this piece is rows {lo}–{hi - 1} "
                f"(t = {self.t[lo]:.3f}–{self.t[hi - 1]:.3f} s)"
            )
            if dropped:
                note += f"; pieces shorter than {min_samples} samples dropped: rows {dropped}"
            pieces.append(
                dataclasses.replace(self.select(slice(lo, hi)), repairs=self.repairs + (note,))
            )
        return pieces
