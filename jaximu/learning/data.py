"""Sequences for learning: raw IMU samples with the ground truth at the IMU times.

:func:`load_sequence` reads a sequence folder in any layout :func:`jaximu.io.read_euroc`
reads (EuRoC's ASL ``mav0/``, or the flat ``imu.csv`` with ``groundtruth.csv`` full state or
``groundtruth_pose.txt`` pose only), keeps the IMU samples the ground truth covers, and
interpolates the ground truth at them (slerp for the attitude). Motion capture drops frames:
a sample inside a ground-truth gap longer than ``max_gap`` keeps its IMU sample (the
integration runs through it) but has no reference (:attr:`Sequence.reference` is False there:
training leaves its windows out), and the ground truth's own rows are kept beside
(:attr:`Sequence.gt_t`, :attr:`Sequence.gt_q`): the evaluation compares at those stamps, so no
error is ever computed across a dropout. Everything here is numpy, float64, outside ``jit``.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib

import numpy as np

from jaximu.geometry._checks import TIMES_FIX, as_numbers, check_positive, check_times
from jaximu.io import DataError, read_euroc
from jaximu.io._common import _max_gap, in_gap

__all__ = ["Sequence", "load_sequence", "split", "RATE_TOLERANCE"]

RATE_TOLERANCE = 0.02
"""Relative difference of sampling rates accepted as the same rate (EuRoC: 200 Hz ± 0.01%)."""


@dataclasses.dataclass(frozen=True)
class Sequence:
    """One recording with the ground truth on the IMU's samples (numpy, float64).

    Attributes:
        name: the folder's name.
        t: ``(N,)`` sample times [s] (from the first kept sample).
        gyro, accel: ``(N, 3)`` raw samples [rad/s], [m/s²], IMU frame.
        q: ``(N, 4)`` true attitude ``R_WB`` (Hamilton ``[w, x, y, z]``, unit, sign-continuous).
        p, v: ``(N, 3)`` true position [m] and velocity [m/s] in W (velocity differentiated
            from positions when the ground truth has none).
        b_g, b_a: ``(N, 3)`` ground-truth biases, or ``None`` (pose-only ground truth).
        repairs: what the reader repaired at the caller's request (``sort``,
            ``drop_duplicates``, …), in words; empty when nothing was.
        reference: ``(N,)`` booleans: whether the ground truth at the sample is interpolated
            between rows at most ``max_gap`` apart (False inside a motion-capture dropout:
            ``q``, ``p``, ``v`` there are slerped across it and not to be compared with);
            ``None``: every sample has one.
        gt_t, gt_q: ``(M,)`` the ground truth's own stamps [s] on ``t``'s clock (inside
            ``[t[0], t[-1]]``) and ``(M, 4)`` its attitudes there, where the evaluation
            compares; ``None``: the samples' ``t`` and ``q``.
    """

    name: str
    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    q: np.ndarray
    p: np.ndarray
    v: np.ndarray
    b_g: np.ndarray | None = None
    b_a: np.ndarray | None = None
    repairs: tuple[str, ...] = ()
    reference: np.ndarray | None = None
    gt_t: np.ndarray | None = None
    gt_q: np.ndarray | None = None

    def __post_init__(self):
        t = check_times("Sequence.t", self.t, 2, TIMES_FIX)
        N = len(t)
        for name, width in (
            ("gyro", 3),
            ("accel", 3),
            ("q", 4),
            ("p", 3),
            ("v", 3),
            ("b_g", 3),
            ("b_a", 3),
        ):
            x = getattr(self, name)
            if x is None and name in ("b_g", "b_a"):
                continue
            x = as_numbers(f"Sequence.{name}", x)
            if x.shape != (N, width):
                raise ValueError(
                    f"Sequence.{name} must have shape ({N}, {width}) (one row per "
                    f"time in t), got {x.shape}"
                )
            bad = np.flatnonzero(~np.isfinite(x).all(1))
            if len(bad):
                raise ValueError(f"Sequence.{name} has NaN or inf at rows {bad[:5].tolist()}")
            object.__setattr__(self, name, x)
        qn = np.linalg.norm(self.q, axis=1)
        if np.any(np.abs(qn - 1) > 1e-6):
            raise ValueError(
                f"Sequence.q must hold unit quaternions [w, x, y, z]; |q| = "
                f"{qn[np.argmax(np.abs(qn - 1))]:.6g}: normalise them"
            )
        object.__setattr__(self, "t", t)
        if self.reference is not None:
            ref = np.asarray(self.reference)
            if ref.shape != (N,) or ref.dtype != np.bool_:
                raise ValueError(
                    f"Sequence.reference must be ({N},) booleans (one per time in t), got "
                    f"{ref.dtype} {ref.shape}"
                )
            object.__setattr__(self, "reference", ref)
        if (self.gt_t is None) != (self.gt_q is None):
            raise ValueError("Sequence.gt_t and Sequence.gt_q are given together or not at all")
        if self.gt_t is not None:
            # the stamps as any recording's: 1-D, finite, strictly increasing
            gt_t = check_times("Sequence.gt_t", self.gt_t, 1, TIMES_FIX)
            gt_q = np.asarray(self.gt_q, np.float64)
            M = len(gt_t)
            if gt_q.shape != (M, 4):
                raise ValueError(
                    f"Sequence.gt_t must be (M,) and gt_q (M, 4) with M ≥ 1, got {gt_t.shape} "
                    f"and {gt_q.shape}"
                )
            if not np.isfinite(gt_q).all():
                raise ValueError("Sequence.gt_t and gt_q must be finite")
            if gt_t[0] < t[0] or gt_t[-1] > t[-1]:
                raise ValueError(
                    f"Sequence.gt_t must lie inside [t[0], t[-1]] = "
                    f"[{t[0]:.6f}, {t[-1]:.6f}] s, got [{gt_t[0]:.6f}, {gt_t[-1]:.6f}] s"
                )
            qn = np.linalg.norm(gt_q, axis=1)
            if np.any(np.abs(qn - 1) > 1e-6):
                raise ValueError(
                    f"Sequence.gt_q must hold unit quaternions [w, x, y, z]; |q| = "
                    f"{qn[np.argmax(np.abs(qn - 1))]:.6g}: normalise them"
                )
            object.__setattr__(self, "gt_t", gt_t)
            object.__setattr__(self, "gt_q", gt_q)

    def __len__(self):
        return len(self.t)

    @property
    def dt(self) -> np.ndarray:
        """``(N-1,)`` sample intervals [s]: step k goes from sample k to k+1."""
        return np.diff(self.t)

    @property
    def rate_hz(self) -> float:
        return float(1.0 / np.median(np.diff(self.t)))

    @property
    def seconds(self) -> float:
        return float(self.t[-1] - self.t[0])

    @property
    def has_reference(self) -> np.ndarray:
        """``(N,)`` booleans: :attr:`reference`, all True when it is ``None``."""
        return np.ones(len(self), bool) if self.reference is None else self.reference

    def stamps(self) -> tuple[np.ndarray, np.ndarray]:
        """``(τ, q)``: where the evaluation compares: the ground truth's own stamps and
        attitudes (:attr:`gt_t`, :attr:`gt_q`), or the samples' when it has none."""
        if self.gt_t is None or self.gt_q is None:
            return self.t, self.q
        return self.gt_t, self.gt_q

    def slice(self, start: int, stop: int | None = None, suffix: str = "") -> Sequence:
        """Samples ``start:stop`` as a new sequence (times kept)."""
        s = slice(start, stop)
        opt = lambda x: None if x is None else x[s]  # noqa: E731
        t = self.t[s]
        gt = {}
        if self.gt_t is not None and self.gt_q is not None:
            inside = (self.gt_t >= t[0]) & (self.gt_t <= t[-1])
            gt = dict(gt_t=self.gt_t[inside], gt_q=self.gt_q[inside])
            if not inside.any():  # no row of its own inside: the samples' references
                gt = {}
        return Sequence(
            self.name + suffix,
            self.t[s],
            self.gyro[s],
            self.accel[s],
            self.q[s],
            self.p[s],
            self.v[s],
            opt(self.b_g),
            opt(self.b_a),
            self.repairs,
            opt(self.reference),
            **gt,
        )


def sign_continuous(q):
    """``q`` ``(N, 4)`` normalised, its signs flipped so consecutive quaternions are in the
    same hemisphere (as a sequence's attitudes are loaded and realigned)."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    flips = np.cumsum(np.sum(q[1:] * q[:-1], -1) < 0) % 2
    q[1:] *= np.where(flips[:, None] == 1, -1.0, 1.0)
    return q


def load_sequence(
    path, *, name: str | None = None, max_gap: float | None = None, **reader_options
) -> Sequence:
    """Read a sequence folder and put its ground truth on the IMU samples it covers.

    Args:
        path: a sequence folder: EuRoC's ASL layout (holding ``mav0/``), or a flat folder
            with ``imu.csv`` and ``groundtruth.csv`` (full state) or ``groundtruth_pose.txt``
            (pose only: seconds, ``x y z qx qy qz qw``).
        name: the sequence's name (default: the folder's name).
        max_gap: the longest ground-truth gap [s] across which the reference at the IMU
            samples is interpolated (slerp). Default: 5 × the ground truth's median interval.
            Motion capture drops frames: a sample inside a longer gap has no reference
            (:attr:`Sequence.reference`), and the sequence starts and ends at samples that
            have one.
        reader_options: :func:`jaximu.io.read_euroc`'s options for the IMU samples: units
            (``gyro_unit``, ``accel_unit``) and repairs (``sort``, ``drop_duplicates``,
            ``drop_nonfinite``, ``allow_gaps``, ``check_units``), all off by default. The
            IMU's longest interval is the reader's default (``max_gap`` here is the ground
            truth's).

    Raises:
        DataError: not a sequence folder, no ground truth, ground truth that does not
            overlap the IMU, what the reader
            refuses (duplicate or unsorted stamps, non-finite samples, gaps; naming the
            folder, the rows and the option that repairs them).
    """
    path = pathlib.Path(path)
    max_gap = _max_gap(max_gap)
    try:
        data = read_euroc(path, **reader_options)
    except DataError as e:
        # The reader names rows and its repairs; name the folder (several are read at once)
        # and leave out its max_gap, which is the IMU's there and the ground truth's here.
        named = e.problem.startswith(f"{path}:") or f"{path}{os.sep}" in e.problem
        problem = e.problem if named else f"{path}: {e.problem}"
        fixes = [f for f in e.fixes if f.option != "max_gap"]
        raise DataError(problem, fixes, lead=e.lead, sep=e.sep, api_note=e.api_note) from None
    gt = data.ground_truth
    if gt is None:
        raise DataError(
            f"{path}: no ground truth found (expected mav0/state_groundtruth_"
            "estimate0/data.csv, groundtruth.csv or groundtruth_pose.txt beside "
            "the IMU samples); learning and evaluation need it"
        )
    inside = np.flatnonzero((data.t >= gt.t[0]) & (data.t <= gt.t[-1]))
    if len(inside) < 2:
        raise DataError(
            f"{path}: the ground truth ({gt.t[0]:.3f} to {gt.t[-1]:.3f} s) does "
            f"not cover the IMU samples ({data.t[0]:.3f} to {data.t[-1]:.3f} s); "
            "check that both files are of the same recording"
        )
    if np.any(np.diff(inside) != 1):  # cannot happen for a sorted t, kept as a guard
        raise DataError(f"{path}: IMU samples inside the ground truth are not contiguous")
    # a sample inside a dropout (a gap longer than max_gap) has no reference; the
    # sequence starts and ends at samples that have one (the start is the first true attitude)
    across, _, _ = in_gap(gt.t, data.t[inside], max_gap)
    kept = inside[~across]
    if len(kept) < 2:
        raise DataError(f"{path}: no two IMU samples fall outside the ground truth's gaps")
    lo, hi = kept[0], kept[-1] + 1
    t = data.t[lo:hi]
    reference = ~across[lo - inside[0] : hi - inside[0]]
    q, p, v = gt.interpolate(t, max_gap=np.inf)
    if v is None:
        v = gt.velocity(t, max_gap=np.inf)
    b = {}
    for k in ("b_g", "b_a"):
        x = getattr(gt, k)
        b[k] = None if x is None else np.stack([np.interp(t, gt.t, x[:, j]) for j in range(3)], 1)
    rows = (gt.t >= t[0]) & (gt.t <= t[-1])
    return Sequence(
        name or path.name,
        t - t[0],
        data.gyro[lo:hi].copy(),
        data.accel[lo:hi].copy(),
        sign_continuous(q),
        p,
        v,
        **b,
        repairs=tuple(data.repairs),
        reference=None if reference.all() else reference,
        gt_t=gt.t[rows] - t[0],
        gt_q=gt.q[rows] / np.linalg.norm(gt.q[rows], axis=1, keepdims=True),  # files round
    )


def split(seq: Sequence, train_seconds: float = 80.0) -> tuple[Sequence, Sequence]:
    """The first ``train_seconds`` for training and the rest for validation (Brossard's
    split of each training sequence)."""
    check_sequence("seq", seq)
    check_positive("train_seconds", train_seconds)
    k = int(np.searchsorted(seq.t, seq.t[0] + train_seconds))
    if k < 2 or len(seq) - k < 2:
        raise DataError(
            f"sequence {seq.name!r} ({seq.seconds:.1f} s) is too short to keep "
            f"{train_seconds:g} s for training and some for validation"
        )
    return seq.slice(0, k, ""), seq.slice(k, None, "")


def check_sequence(name: str, seq) -> Sequence:
    """``seq`` must be a :class:`Sequence` (named ``name`` in the message)."""
    if not isinstance(seq, Sequence):
        raise ValueError(
            f"{name} must be a jaximu.learning.Sequence (from load_sequence), got "
            f"{type(seq).__name__}"
        )
    return seq


def check_rate(seq: Sequence, rate_hz: float, what: str = "the model") -> None:
    """Refuse a sequence sampled at another rate than ``rate_hz``."""
    r = seq.rate_hz
    if abs(r - rate_hz) > RATE_TOLERANCE * rate_hz:
        raise DataError(
            f"sequence {seq.name!r} is sampled at {r:.1f} Hz, {what} at "
            f"{rate_hz:g} Hz: resample the recording to {rate_hz:g} Hz or train "
            "a model at its rate"
        )


def padded_length(n: int) -> int:
    """The length that arrays of ``n`` samples are padded to (:func:`to_length`) before a
    compiled program over a whole recording: the first of ``12, 16, 24, 32, …`` (``2ᵏ`` and
    ``3·2ᵏ⁻¹``) at or above ``n``, so that recordings of about one length (within a factor
    of 1.5) share one program. A program over a recording takes seconds to compile and
    less to run; at most half as many samples more are run."""
    p = 16
    while p < n:
        p *= 2
    return p * 3 // 4 if p * 3 // 4 >= n else p


def to_length(x, n: int) -> np.ndarray:
    """``x`` ``(T, ·)`` cut to ``n`` samples, or padded to them by repeating its last (a
    causal computation's outputs before the padding are unchanged by it)."""
    x = np.asarray(x)[:n]
    return np.concatenate([x, np.repeat(x[-1:], n - len(x), 0)])
