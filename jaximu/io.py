"""Reading IMU recordings and writing trajectories.

Readers return one container, :class:`ImuData`: exact int64 nanosecond stamps, times in
seconds (float64) since the first stamp, raw gyro [rad/s] and accelerometer [m/s²] samples
in the IMU frame, and optional :class:`GroundTruth`.

* :func:`read_euroc` / :func:`read_tumvi`: the ASL layout of EuRoC MAV and TUM-VI
  (``mav0/imu0/data.csv``; ground truth from ``state_groundtruth_estimate0`` (EuRoC: pose,
  velocity, biases) or ``mocap0`` (TUM-VI: pose only)).
* :func:`read_csv`: any delimited text file, with a column mapping and unit options.
* :func:`from_arrays`, :func:`read_npz`: NumPy arrays.
* :func:`read_rosbag`: ``sensor_msgs/Imu`` from ROS 1 bags and ROS 2 bags (sqlite3 or
  mcap), through the `rosbags <https://gitlab.com/ternaris/rosbags>`_ library
  (``pip install "jaximu[rosbag]"``).

Every reader validates what it loads (:func:`validate_imu`): non-finite rows, timestamps
that go backwards or repeat, gaps, an implausible sampling rate and units that look wrong (a
gyro in deg/s, an accelerometer in g) raise :class:`DataError`, naming the rows (file
lines for files). Explicit options repair (``sort``, ``drop_duplicates``, ``drop_nonfinite``,
``allow_gaps``; :meth:`ImuData.split_at_gaps`), and each repair is described in
:attr:`ImuData.repairs`. Nothing is dropped or converted silently.

Writers: :func:`write_tum` (``t tx ty tz qx qy qz qw``, the format ``evo`` reads),
:func:`write_states` (CSV or NPZ of states with their covariances) and the matching readers
:func:`read_tum`, :func:`read_states`.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
from decimal import Decimal, InvalidOperation

import numpy as np

from jaximu.errors import Fix, InputError

__all__ = [
    "DataError", "GroundTruth", "ImuData", "validate_imu", "read_euroc", "read_tumvi",
    "read_csv", "from_arrays", "read_npz", "read_rosbag", "write_tum", "read_tum",
    "write_states", "read_states", "STANDARD_GRAVITY", "gravity_alignment", "initial_state",
    "TrajectoryErrors", "trajectory_errors",
]

#: Standard gravity [m/s²], used to convert accelerometers that report in g.
STANDARD_GRAVITY = 9.80665
_TIME_UNITS = {"s": 10**9, "ms": 10**6, "us": 10**3, "ns": 1}
_GYRO_UNITS = {"rad/s": 1.0, "deg/s": math.pi / 180.0}
_ACCEL_UNITS = {"m/s^2": 1.0, "m/s2": 1.0, "m/s²": 1.0, "g": STANDARD_GRAVITY}
# Plausibility limits: the widest common MEMS gyro range is ±2000 °/s (34.9 rad/s), and no
# recording turns at > 10 rad/s (1.6 rev/s) on median; a still or moving accelerometer reads
# ~9.81 m/s² on median, ~1 if it reports in g.
_GYRO_MAX = 35.0
_GYRO_MEDIAN_MAX = 10.0
_ACCEL_MEDIAN_RANGE = (3.0, 60.0)
_DT_RANGE = (1e-5, 1.0)  # 1 Hz … 100 kHz
GAP_FACTOR = 5.0  # default gap threshold: this many median intervals
CLOCK_TOLERANCE = 1e-5  # [s] stamps this close count as the same instant


class DataError(InputError):
    """A recording that cannot be used as it is; the message names the rows, and
    :attr:`fixes` holds the options that repair it (:class:`jaximu.errors.InputError`)."""


def _rows(labels, idx, limit=5) -> str:
    idx = np.asarray(idx).ravel()
    shown = ", ".join(str(labels[i]) for i in idx[:limit])
    more = f", … ({len(idx)} in all)" if len(idx) > limit else ""
    return shown + more


def _labels(n, lines=None):
    if lines is None:
        return [f"row {i}" for i in range(n)]
    return [f"line {int(k)}" for k in lines]


# --------------------------------------------------------------------------- containers


def _qmul(a, b):
    aw, av, bw, bv = a[..., :1], a[..., 1:], b[..., :1], b[..., 1:]
    return np.concatenate([aw * bw - np.sum(av * bv, -1, keepdims=True),
                           aw * bv + bw * av + np.cross(av, bv)], -1)


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
        """
        t = np.atleast_1d(np.asarray(t, np.float64))
        if t.min() < self.t[0] - CLOCK_TOLERANCE or t.max() > self.t[-1] + CLOCK_TOLERANCE:
            raise DataError(
                f"ground truth covers [{self.t[0]:.6f}, {self.t[-1]:.6f}] s, asked for "
                f"[{t.min():.6f}, {t.max():.6f}] s")
        t = np.clip(t, self.t[0], self.t[-1])
        gaps = np.diff(self.t)
        limit = max_gap if max_gap is not None else GAP_FACTOR * np.median(gaps)
        k = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 2)
        across = (gaps[k] > limit) & (t > self.t[k]) & (t < self.t[k + 1])
        if across.any():
            i = int(np.argmax(across))
            raise DataError(
                f"ground truth has a {gaps[k[i]]:.3f} s gap at t = {self.t[k[i]]:.3f} s; "
                f"t = {t[i]:.3f} s falls inside it (max_gap = {limit:.4f} s)")
        q = _slerp(self.q[k], self.q[k + 1], (t - self.t[k]) / gaps[k])
        p = np.stack([np.interp(t, self.t, self.p[:, j]) for j in range(3)], axis=1)
        v = None
        if self.v is not None:
            v = np.stack([np.interp(t, self.t, self.v[:, j]) for j in range(3)], axis=1)
        return q, p, v

    def velocity(self, t):
        """Velocity at ``t``: the stored one, or central differences of the positions."""
        if self.v is not None:
            return self.interpolate(t)[2]
        t = np.atleast_1d(np.asarray(t, np.float64))
        h = float(np.median(np.diff(self.t)))
        lo, hi = np.maximum(t - h, self.t[0]), np.minimum(t + h, self.t[-1])
        return (self.interpolate(hi)[1] - self.interpolate(lo)[1]) / (hi - lo)[:, None]


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
        """The samples at ``index`` (a slice or indices); times stay relative to ``t0_ns``."""
        return dataclasses.replace(self, stamps_ns=self.stamps_ns[index], t=self.t[index],
                                   gyro=self.gyro[index], accel=self.accel[index])

    def window(self, start: float = 0.0, duration: float | None = None) -> ImuData:
        """Samples with ``start ≤ t ≤ start + duration`` [s since ``t0_ns``]."""
        end = np.inf if duration is None else start + duration
        keep = (self.t >= start - 1e-12) & (self.t <= end + 1e-12)
        if keep.sum() < 2:
            raise DataError(f"the window [{start}, {end}] s holds fewer than 2 samples "
                            f"(the recording spans [{self.t[0]:.3f}, {self.t[-1]:.3f}] s)")
        return self.select(np.flatnonzero(keep))

    def gaps(self, max_gap: float | None = None) -> np.ndarray:
        """Indices ``i`` with ``t[i+1] - t[i] > max_gap`` (default ``GAP_FACTOR`` × median)."""
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
            note = (f"split at {len(cuts)} gap(s): this piece is rows {lo}–{hi - 1} "
                    f"(t = {self.t[lo]:.3f}–{self.t[hi - 1]:.3f} s)")
            if dropped:
                note += f"; pieces shorter than {min_samples} samples dropped: rows {dropped}"
            pieces.append(dataclasses.replace(self.select(slice(lo, hi)),
                                              repairs=self.repairs + (note,)))
        return pieces


# --------------------------------------------------------------------------- validation


def validate_imu(stamps_ns, gyro, accel, *, lines=None, sort: bool = False,
                 drop_duplicates: bool = False, drop_nonfinite: bool = False,
                 max_gap: float | None = None, allow_gaps: bool = False,
                 check_units: bool = True):
    """Check a recording and apply the requested repairs.

    Args:
        stamps_ns: ``(N,)`` int64 stamps [ns]; gyro, accel: ``(N, 3)`` in rad/s, m/s².
        lines: ``(N,)`` file line numbers for the messages (else row indices are named).
        sort: sort samples by time (stable) instead of raising on timestamps that go back.
        drop_duplicates: keep the first of samples with the same stamp instead of raising.
        drop_nonfinite: drop rows with NaN/inf instead of raising.
        max_gap: longest allowed interval [s] (default ``GAP_FACTOR`` × the median).
        allow_gaps: keep longer intervals (said in the repairs) instead of raising; cut them
            with :meth:`ImuData.split_at_gaps`.
        check_units: check the sampling interval and the magnitudes are plausible.

    Returns:
        ``(index, repairs)``: the rows to keep, in order, and what was changed.

    Raises:
        DataError: naming the rows and the option that repairs the problem.
    """
    stamps_ns = np.asarray(stamps_ns)
    gyro = np.asarray(gyro, np.float64)
    accel = np.asarray(accel, np.float64)
    n = len(stamps_ns)
    if gyro.shape != (n, 3) or accel.shape != (n, 3):
        raise DataError(f"gyro and accel must have shape (N, 3) with N = {n} stamps; got "
                        f"{gyro.shape} and {accel.shape}")
    labels = _labels(n, lines)
    repairs: list[str] = []
    idx = np.arange(n)

    bad = ~(np.isfinite(gyro).all(1) & np.isfinite(accel).all(1))
    if bad.any():
        rows = np.flatnonzero(bad)
        if not drop_nonfinite:
            raise DataError(f"{len(rows)} sample(s) with NaN or inf values at "
                            f"{_rows(labels, rows)}", [Fix("drop_nonfinite", True)],
                            api_note=" to drop them")
        repairs.append(f"dropped {len(rows)} sample(s) with NaN/inf values: {_rows(labels, rows, 20)}")
        idx = idx[~bad]

    back = np.flatnonzero(np.diff(stamps_ns[idx]) < 0) + 1
    if len(back):
        if not sort:
            i = idx[back]
            raise DataError(f"timestamps go backwards at {len(back)} place(s): "
                            f"{_rows(labels, i)} (earlier than the row before)",
                            [Fix("sort", True)], api_note=" to sort by time")
        order = np.argsort(stamps_ns[idx], kind="stable")
        moved = int(np.sum(order != np.arange(len(order))))
        repairs.append(f"sorted by time: {moved} sample(s) moved (first out of order at "
                       f"{labels[idx[back[0]]]})")
        idx = idx[order]

    dup = np.flatnonzero(np.diff(stamps_ns[idx]) == 0) + 1
    if len(dup):
        if not drop_duplicates:
            raise DataError(f"{len(dup)} duplicate timestamp(s) at {_rows(labels, idx[dup])} "
                            "(same stamp as the row before)", [Fix("drop_duplicates", True)],
                            api_note=" to keep the first of each")
        same = np.all(gyro[idx[dup]] == gyro[idx[dup - 1]], axis=1) & np.all(
            accel[idx[dup]] == accel[idx[dup - 1]], axis=1)
        repairs.append(f"dropped {len(dup)} sample(s) with a duplicate timestamp "
                       f"({int(same.sum())} identical to the kept one): "
                       f"{_rows(labels, idx[dup], 20)}")
        idx = np.delete(idx, dup)

    if len(idx) < 2:
        raise DataError(f"fewer than 2 usable samples ({len(idx)} of {n})")
    dt = np.diff(stamps_ns[idx]) * 1e-9
    med = float(np.median(dt))
    if check_units and not _DT_RANGE[0] <= med <= _DT_RANGE[1]:
        raise DataError(f"median sampling interval {med:.3g} s ({1 / med:.3g} Hz) is implausible "
                        "for an IMU", [Fix("time_unit", phrase="check the time unit ({})")],
                        lead="")
    limit = max_gap if max_gap is not None else GAP_FACTOR * med
    gaps = np.flatnonzero(dt > limit)
    if len(gaps):
        where = ", ".join(f"{dt[g]:.4g} s after {labels[idx[g]]}" for g in gaps[:5])
        more = f", … ({len(gaps)} in all)" if len(gaps) > 5 else ""
        if not allow_gaps:
            raise DataError(f"{len(gaps)} gap(s) longer than {limit:.4g} s: {where}{more}",
                            [Fix("allow_gaps", True), Fix("max_gap", phrase="a larger")],
                            api_note=" (allow_gaps keeps them: then split_at_gaps())")
        repairs.append(f"kept {len(gaps)} gap(s) longer than {limit:.4g} s: {where}{more}")

    if check_units:
        g, a = gyro[idx], accel[idx]
        with np.errstate(over="ignore"):  # magnitudes near the float64 limit: inf, reported below
            wn, an = np.linalg.norm(g, axis=1), np.linalg.norm(a, axis=1)
        if wn.max() > _GYRO_MAX or np.median(wn) > _GYRO_MEDIAN_MAX:
            i = int(np.argmax(wn))
            raise DataError(
                f"gyro magnitudes up to {wn.max():.4g} (median {np.median(wn):.3g}) at "
                f"{labels[idx[i]]} are implausible in rad/s (±2000 °/s = 34.9 rad/s): is the "
                "gyro in deg/s?", [Fix("gyro_unit", "deg/s"), Fix("check_units", False)],
                sep=" ")
        am = float(np.median(an))
        if not _ACCEL_MEDIAN_RANGE[0] <= am <= _ACCEL_MEDIAN_RANGE[1]:
            in_g = am < _ACCEL_MEDIAN_RANGE[0]
            hint = "is the accelerometer in g?" if in_g else "check the accelerometer unit;"
            raise DataError(f"median accelerometer magnitude {am:.4g} is implausible in m/s² "
                            f"(gravity alone reads 9.81): {hint}",
                            ([Fix("accel_unit", "g")] if in_g else []) + [Fix("check_units", False)],
                            sep=" ")
    return idx, tuple(repairs)


def _validate_groundtruth(stamps_ns, values, lines, label):
    """Ground truth must be finite and strictly increasing (it is never repaired)."""
    labels = _labels(len(stamps_ns), lines)
    bad = ~np.isfinite(values).all(1)
    if bad.any():
        raise DataError(f"{label}: NaN or inf at {_rows(labels, np.flatnonzero(bad))}")
    nonincr = np.flatnonzero(np.diff(stamps_ns) <= 0) + 1
    if len(nonincr):
        raise DataError(f"{label}: timestamps not increasing at {_rows(labels, nonincr)}")
    qn = np.linalg.norm(values[:, 3:7], axis=1)
    off = np.flatnonzero(np.abs(qn - 1) > 1e-2)
    if len(off):
        raise DataError(f"{label}: quaternion norm {qn[off[0]]:.4g} at {_rows(labels, off)}: "
                        "not [w, x, y, z] unit quaternions")


def _make(stamps_ns, gyro, accel, *, lines=None, ground_truth=None, source="", **options):
    stamps_ns = np.asarray(stamps_ns, np.int64)
    idx, repairs = validate_imu(stamps_ns, gyro, accel, lines=lines, **options)
    stamps = stamps_ns[idx]
    t0 = int(stamps[0])
    gt = None
    if ground_truth is not None:
        gt_ns, gt_values, gt_lines, cols = ground_truth
        _validate_groundtruth(gt_ns, gt_values, gt_lines, "ground truth")
        t_gt = (gt_ns - t0) * 1e-9
        get = lambda i: gt_values[:, i:i + 3].copy() if gt_values.shape[1] >= i + 3 else None  # noqa: E731
        gt = GroundTruth(t=t_gt, p=gt_values[:, 0:3].copy(), q=gt_values[:, 3:7].copy(),
                         v=get(7) if cols >= 10 else None, b_g=get(10) if cols >= 13 else None,
                         b_a=get(13) if cols >= 16 else None)
    t = (stamps - t0) * 1e-9
    close = np.flatnonzero(np.diff(t) <= 0)
    if len(close):  # only past ~10^8 s: float64 seconds then resolve ~15 ns
        raise DataError(f"stamps {stamps[close[0]]} and "
                        f"{stamps[close[0] + 1]} ns are distinct but equal in float64 seconds "
                        f"since the first stamp (the recording spans {t[-1]:.3g} s); check the "
                        "time unit")
    return ImuData(stamps_ns=stamps, t=t,
                   gyro=np.array(gyro, np.float64)[idx], accel=np.array(accel, np.float64)[idx],
                   t0_ns=t0, ground_truth=gt, source=source, repairs=repairs)


# --------------------------------------------------------------------------- text parsing


def _sniff_delimiter(line):
    for d in (",", "\t", ";"):
        if d in line:
            return d
    return None  # whitespace


def _split(line, delimiter):
    parts = line.split(delimiter) if delimiter else line.split()
    return [p.strip() for p in parts]


def _is_number(s):
    try:
        float(s)
        return True
    except ValueError:
        return False


def _read_table(path, delimiter=None, comment="#"):
    """``(header, rows, lines)``: the header fields (or None), the text fields of each data
    row and its 1-based line number.

    The header is a first line none of whose fields is a number, or else the last comment
    line before the data with as many fields as the data (ASL files: ``#timestamp [ns],…``).
    Every other non-comment line is data: a text field there is reported when its column is
    used, never dropped as a header.
    """
    path = pathlib.Path(path)
    if path.is_dir():
        raise DataError(f"{path} is a directory, not a file")
    if not path.is_file():
        raise DataError(f"no such file: {path}")
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark is not data
    except UnicodeDecodeError:
        raise DataError(f"{path} is not a text file") from None
    numbered = [(k, ln.strip()) for k, ln in enumerate(text.splitlines(), start=1) if ln.strip()]
    if delimiter is None:  # sniffed from the first data line (a comment may hold anything)
        first = next((ln for _, ln in numbered if not ln.startswith(comment)), "")
        delimiter = _sniff_delimiter(first)
    header, comments, rows, lines = None, [], [], []
    for k, line in numbered:
        if line.startswith(comment):
            if not rows:
                comments.append(_split(line.lstrip(comment), delimiter))
            continue
        fields = _split(line, delimiter)
        if not rows and header is None and not any(_is_number(f) for f in fields if f):
            header = fields
            continue
        rows.append(fields)
        lines.append(k)
    if not rows:
        raise DataError(f"{path}: no data rows")
    if header is None:
        header = next((c for c in reversed(comments) if len(c) == len(rows[0])), None)
    return header, rows, np.asarray(lines)


def _column(header, spec, path):
    if isinstance(spec, (int, np.integer)):
        return int(spec)
    if header is None:
        raise DataError(f"{path} has no header line: give columns by index, not {spec!r}")
    norm = lambda s: s.split("[")[0].strip().lower()  # noqa: E731  "w_RS_S_x [rad s^-1]"
    for i, h in enumerate(header):
        if h.strip().lower() == spec.lower() or norm(h) == norm(spec):
            return i
    raise DataError(f"{path}: no column named {spec!r}; the header has {header}")


def _to_ns(text, unit_ns, label):
    """Exact integer nanoseconds from a decimal string (no float rounding)."""
    try:
        exact = Decimal(text) * unit_ns
        ns = int(exact.to_integral_value())
    except (InvalidOperation, ValueError, OverflowError):  # text, NaN, inf
        raise DataError(f"{label}: timestamp {text!r} is not a finite number") from None
    if unit_ns == 1 and exact != ns:
        raise DataError(f"{label}: timestamp {text!r} is not a whole number of nanoseconds",
                        [Fix("time_unit", phrase="check the time unit ({})")], lead="")
    if abs(ns) > np.iinfo(np.int64).max:
        raise DataError(f"{label}: timestamp {text!r} is beyond int64 nanoseconds",
                        [Fix("time_unit", phrase="check the time unit ({})")], lead="")
    return ns


def _parse(rows, lines, time_col, value_cols, time_unit, path):
    width = max([time_col, *value_cols]) + 1
    unit_ns = _TIME_UNITS[time_unit]
    stamps = np.empty(len(rows), np.int64)
    values = np.empty((len(rows), len(value_cols)), np.float64)
    for r, (fields, k) in enumerate(zip(rows, lines)):
        if len(fields) < width:
            raise DataError(f"{path}, line {k}: expected at least {width} columns, "
                            f"got {len(fields)}")
        stamps[r] = _to_ns(fields[time_col], unit_ns, f"{path}, line {k}")
        try:
            values[r] = [float(fields[c]) for c in value_cols]
        except ValueError:
            bad = next(fields[c] for c in value_cols if not _is_number(fields[c]))
            raise DataError(f"{path}, line {k}: {bad!r} is not a number") from None
    return stamps, values


def _check_unit(kind, unit, table):
    if unit not in table:
        raise ValueError(f"unknown {kind} {unit!r}; choose one of {sorted(table)}")
    return table[unit]


# --------------------------------------------------------------------------- readers

_REPAIR_DOC = """sort, drop_duplicates, drop_nonfinite, max_gap, allow_gaps, check_units:
            see :func:`validate_imu` (the default raises :class:`DataError`)."""

_GT_DIRS = {"euroc": ("state_groundtruth_estimate0", "mocap0", "vicon0", "leica0"),
            "tumvi": ("mocap0", "state_groundtruth_estimate0")}


def _asl_paths(path, groundtruth, prefer):
    path = pathlib.Path(path)
    if path.is_dir():
        if (path / "mav0").is_dir():
            path = path / "mav0"
        if (path / "imu0" / "data.csv").is_file():
            imu = path / "imu0" / "data.csv"
            candidates = [path / d / "data.csv" for d in _GT_DIRS[prefer]]
        elif (path / "imu.csv").is_file():  # a flat excerpt, as jaximu/data ships
            imu = path / "imu.csv"
            candidates = [path / "groundtruth.csv"]
        else:
            raise DataError(f"{path}: neither mav0/imu0/data.csv nor imu.csv found")
    elif path.is_file():
        imu = path
        mav0 = path.parent.parent
        candidates = [mav0 / d / "data.csv" for d in _GT_DIRS[prefer]]
    else:
        raise DataError(f"no such file or directory: {path}")
    if groundtruth is True:
        gt = next((c for c in candidates if c.is_file()), None)
    elif groundtruth:
        gt = pathlib.Path(groundtruth)
        if not gt.is_file():
            raise DataError(f"no such ground-truth file: {gt}")
    else:
        gt = None
    return imu, gt


def _read_asl(path, groundtruth, prefer, options):
    imu_path, gt_path = _asl_paths(path, groundtruth, prefer)
    _, rows, lines = _read_table(imu_path, ",")
    stamps, values = _parse(rows, lines, 0, range(1, 7), "ns", imu_path)
    gt = None
    if gt_path is not None:
        _, g_rows, g_lines = _read_table(gt_path, ",")
        cols = len(g_rows[0]) - 1
        if cols < 7:
            raise DataError(f"{gt_path}, line {g_lines[0]}: expected p (3) and q (4) after the "
                            f"stamp, got {cols} values")
        g_stamps, g_values = _parse(g_rows, g_lines, 0, range(1, cols + 1), "ns", gt_path)
        gt = (g_stamps, g_values, g_lines, cols)
    source = str(imu_path) + (f" + {gt_path}" if gt_path else "")
    return _make(stamps, values[:, 0:3], values[:, 3:6], lines=lines, ground_truth=gt,
                 source=source, **options)


def read_euroc(path, *, groundtruth=True, **options) -> ImuData:
    """Read a EuRoC MAV sequence (ASL layout).

    Args:
        path: the sequence folder (holding ``mav0``), ``mav0`` itself, its
            ``imu0/data.csv``, or a flat folder with ``imu.csv`` and ``groundtruth.csv``
            (the excerpts bundled in ``jaximu/data``).
        groundtruth: ``True`` to load ``state_groundtruth_estimate0/data.csv`` when present
            (p, q ``[w, x, y, z]`` of ``R_WB``, v, b_g, b_a), a path, or ``False``.
        options: {repair}

    Returns:
        :class:`ImuData` with int64 stamps exactly as in the file.
    """
    return _read_asl(path, groundtruth, "euroc", options)


def read_tumvi(path, *, groundtruth=True, **options) -> ImuData:
    """Read a TUM-VI sequence (ASL layout: ``mav0/imu0/data.csv``, motion capture in
    ``mav0/mocap0/data.csv``: pose only, 120 Hz with dropouts; the IMU's intervals vary).

    Args as :func:`read_euroc`.
    """
    return _read_asl(path, groundtruth, "tumvi", options)


def _header_time_unit(header, col):
    """The unit a header states for the time column (``#timestamp [ns]``), or None."""
    if header is None or col >= len(header):
        return None
    import re

    m = re.search(r"\[\s*(ns|us|µs|ms|s)\s*\]", str(header[col]))
    return None if m is None else {"µs": "us"}.get(m.group(1), m.group(1))


def read_csv(path, *, time=0, gyro=(1, 2, 3), accel=(4, 5, 6), time_unit: str | None = None,
             gyro_unit: str = "rad/s", accel_unit: str = "m/s^2", delimiter: str | None = None,
             comment: str = "#", **options) -> ImuData:
    """Read IMU samples from a delimited text file.

    Args:
        path: the file; comma, tab, semicolon or whitespace separated (sniffed unless
            ``delimiter`` is given); lines starting with ``comment`` are skipped; a first
            line that is not all numbers is the header.
        time, gyro, accel: columns: indices, or header names (matched case-insensitively,
            ignoring a trailing ``[unit]``). Default: EuRoC's order ``t, wx, wy, wz, ax, ay, az``.
        time_unit: ``"s"``, ``"ms"``, ``"us"`` or ``"ns"``; stamps are converted to
            integer nanoseconds exactly from their decimal text. Default ``None``: the unit
            the time column's header states (``#timestamp [ns]``, as in EuRoC's files), else
            seconds. A unit given that contradicts the header is a :class:`DataError`.
        gyro_unit: ``"rad/s"`` or ``"deg/s"`` (converted to rad/s).
        accel_unit: ``"m/s^2"`` or ``"g"`` (× 9.80665, converted to m/s²).
        options: {repair}
    """
    if time_unit is not None:
        _check_unit("time_unit", time_unit, _TIME_UNITS)
    w_scale = _check_unit("gyro_unit", gyro_unit, _GYRO_UNITS)
    a_scale = _check_unit("accel_unit", accel_unit, _ACCEL_UNITS)
    header, rows, lines = _read_table(path, delimiter, comment)
    cols = [_column(header, c, path) for c in (time, *gyro, *accel)]
    if len(cols) != 7:
        raise ValueError("gyro and accel each need 3 columns")
    stated = _header_time_unit(header, cols[0])
    if time_unit is None:
        time_unit = stated or "s"
    elif stated is not None and stated != time_unit:
        raise DataError(f"{path}: the header states the time column in [{stated}] "
                        f"({header[cols[0]].strip()!r}) but time_unit={time_unit!r} was given",
                        [Fix("time_unit", stated)], api_note=" (or leave it out)")
    stamps, values = _parse(rows, lines, cols[0], cols[1:], time_unit, path)
    return _make(stamps, values[:, 0:3] * w_scale, values[:, 3:6] * a_scale, lines=lines,
                 source=str(path), **options)


def from_arrays(t, gyro, accel, *, time_unit: str = "s", gyro_unit: str = "rad/s",
                accel_unit: str = "m/s^2", ground_truth: GroundTruth | None = None,
                source: str = "arrays", **options) -> ImuData:
    """An :class:`ImuData` from NumPy arrays (copied; the caller's arrays are not changed).

    Args:
        t: ``(N,)`` times in ``time_unit``; integers with ``time_unit="ns"`` are exact.
        gyro, accel: ``(N, 3)`` in ``gyro_unit``, ``accel_unit`` (converted to SI).
        ground_truth: on the clock of ``t`` *after* conversion, seconds since ``t[0]``.
        options: {repair} Messages name rows by index.
    """
    unit_ns = _check_unit("time_unit", time_unit, _TIME_UNITS)
    w_scale = _check_unit("gyro_unit", gyro_unit, _GYRO_UNITS)
    a_scale = _check_unit("accel_unit", accel_unit, _ACCEL_UNITS)
    t = np.asarray(t)
    gyro, accel = np.asarray(gyro), np.asarray(accel)
    if t.ndim != 1:
        raise DataError(f"t must have shape (N,), got {t.shape}")
    if gyro.shape != (len(t), 3) or accel.shape != (len(t), 3):
        raise DataError(f"gyro and accel must have shape (N, 3) with N = {len(t)}, got "
                        f"{gyro.shape} and {accel.shape}")
    limit = np.iinfo(np.int64).max // unit_ns  # int64 nanoseconds reach ±292 years
    labels = _labels(len(t))
    if np.issubdtype(t.dtype, np.integer):
        bad = np.abs(t.astype(np.float64)) > limit
    else:
        bad = ~np.isfinite(t.astype(np.float64))
        if bad.any():
            raise DataError(f"non-finite times at {_rows(labels, np.flatnonzero(bad))}")
        bad = np.abs(t.astype(np.float64)) > limit
    if bad.any():
        raise DataError(f"times beyond ±{limit:.3g} {time_unit} (int64 nanoseconds) at "
                        f"{_rows(labels, np.flatnonzero(bad))}; check time_unit")
    if np.issubdtype(t.dtype, np.integer):
        stamps = t.astype(np.int64) * unit_ns
    else:
        stamps = np.round(t.astype(np.float64) * unit_ns).astype(np.int64)
    data = _make(stamps, gyro * w_scale, accel * a_scale, source=source, **options)
    if ground_truth is not None:
        shift = (int(stamps[0]) - data.t0_ns) * 1e-9
        data = dataclasses.replace(
            data, ground_truth=dataclasses.replace(ground_truth, t=ground_truth.t + shift))
    return data


def read_npz(path, *, t="t", gyro="gyro", accel="accel", **kwargs) -> ImuData:
    """Read arrays named ``t``, ``gyro``, ``accel`` (or the given keys) from an ``.npz``
    file; the rest as :func:`from_arrays`."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise DataError(f"no such file: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in (t, gyro, accel) if k not in z.files]
            if missing:
                raise DataError(f"{path}: no array(s) {missing}; it has {z.files}")
            arrays = z[t], z[gyro], z[accel]
    except (OSError, ValueError) as e:
        if isinstance(e, DataError):
            raise
        raise DataError(f"{path} is not a NumPy .npz file ({e})") from None
    return from_arrays(*arrays, source=str(path), **kwargs)


def read_rosbag(path, topic: str | None = None, *, stamp: str = "header",
                gyro_unit: str = "rad/s", accel_unit: str = "m/s^2", **options) -> ImuData:
    """Read ``sensor_msgs/Imu`` messages from a ROS 1 bag or a ROS 2 bag folder/file.

    Needs ``rosbags`` (``pip install "jaximu[rosbag]"``). No ROS installation is needed.

    Args:
        path: a ``.bag`` file (ROS 1), or a ROS 2 bag folder (``metadata.yaml`` with sqlite3
            or mcap storage).
        topic: the IMU topic; default: the only ``sensor_msgs/msg/Imu`` topic in the bag.
        stamp: ``"header"`` (``header.stamp``, the sensor's time) or ``"log"`` (when the
            recorder received it).
        gyro_unit: ``"rad/s"`` (what ``sensor_msgs/Imu`` specifies) or ``"deg/s"`` for
            drivers that publish degrees (converted to rad/s).
        accel_unit: ``"m/s^2"`` or ``"g"`` (× 9.80665, converted to m/s²).
        options: {repair} Messages name messages by their index in the topic.
    """
    try:
        from rosbags.highlevel import AnyReader  # noqa: PLC0415
    except ImportError:
        raise ImportError("reading ROS bags needs rosbags: pip install \"jaximu[rosbag]\"") from None
    if stamp not in ("header", "log"):
        raise ValueError(f"unknown stamp {stamp!r}; choose 'header' or 'log'")
    w_scale = _check_unit("gyro_unit", gyro_unit, _GYRO_UNITS)
    a_scale = _check_unit("accel_unit", accel_unit, _ACCEL_UNITS)
    path = pathlib.Path(path)
    if not path.exists():
        raise DataError(f"no such file or directory: {path}")
    imu_type = "sensor_msgs/msg/Imu"
    try:
        reader = AnyReader([path])
        reader.open()
    except Exception as e:  # rosbags raises its own types for unreadable bags
        raise DataError(f"{path} is not a readable ROS bag ({type(e).__name__}: {e})") from None
    try:
        imu_topics = sorted({c.topic for c in reader.connections if c.msgtype == imu_type})
        if topic is None:
            if len(imu_topics) != 1:
                raise DataError(f"{path}: {len(imu_topics)} {imu_type} topics {imu_topics}; "
                                "name one with topic=")
            topic = imu_topics[0]
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            raise DataError(f"{path}: no topic {topic!r}; IMU topics: {imu_topics}")
        if conns[0].msgtype != imu_type:
            raise DataError(f"{path}: topic {topic!r} has type {conns[0].msgtype}, not {imu_type}")
        stamps, gyro, accel = [], [], []
        try:
            for conn, log_ns, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                w, a = msg.angular_velocity, msg.linear_acceleration
                if stamp == "header":
                    s = msg.header.stamp
                    stamps.append(int(s.sec) * 10**9 + int(s.nanosec))
                else:
                    stamps.append(int(log_ns))
                gyro.append((w.x, w.y, w.z))
                accel.append((a.x, a.y, a.z))
        except Exception as e:  # a corrupt message or chunk: rosbags' own error types
            raise DataError(f"{path}: message row {len(stamps)} on {topic!r} could not be read "
                            f"({type(e).__name__}: {e})") from None
    finally:
        reader.close()
    if not stamps:
        raise DataError(f"{path}: topic {topic!r} holds no messages")
    return _make(np.asarray(stamps, np.int64), np.asarray(gyro, np.float64) * w_scale,
                 np.asarray(accel, np.float64) * a_scale, source=f"{path}:{topic}", **options)


for _f in (read_euroc, read_csv, from_arrays, read_rosbag):
    _f.__doc__ = _f.__doc__.replace("{repair}", _REPAIR_DOC)


# --------------------------------------------------------------------------- writers


def _stamps(t, t0_ns):
    """Absolute int64 ns stamps from seconds since ``t0_ns`` (exact for ns-grid times)."""
    return int(t0_ns) + np.round(np.asarray(t, np.float64) * 1e9).astype(np.int64)


def _seconds_text(ns):
    ns = int(ns)
    sign = "-" if ns < 0 else ""
    return f"{sign}{abs(ns) // 10**9}.{abs(ns) % 10**9:09d}"


def _pose_arrays(states):
    q = np.asarray(states.q, np.float64)
    p = np.asarray(states.p, np.float64)
    if q.ndim != 2 or p.ndim != 2:
        raise ValueError(f"states must hold one trajectory: q (T, 4), p (T, 3); got "
                         f"{q.shape}, {p.shape}")
    return q, p


def write_tum(path, t, states, *, t0_ns: int = 0) -> None:
    """Write poses in the TUM trajectory format, one ``t tx ty tz qx qy qz qw`` per line.

    This is what ``evo`` (``evo_ape tum gt.txt est.txt``) and the TUM RGB-D tools read.

    Args:
        path: output file.
        t: ``(T,)`` times [s] since ``t0_ns``; written as absolute seconds with all nine
            decimals, from integer nanoseconds (no float rounding of the epoch).
        states: a :class:`jaximu.NavState` (or anything with ``q`` ``(T, 4)`` Hamilton
            ``[w, x, y, z]`` of ``R_WB`` and ``p`` ``(T, 3)``); the file has ``[x, y, z, w]``.
        t0_ns: the epoch of ``t = 0`` [ns] (:attr:`ImuData.t0_ns`).
    """
    q, p = _pose_arrays(states)
    if len(t) != len(q):
        raise ValueError(f"t has {len(t)} entries, states {len(q)}")
    stamps = _stamps(t, t0_ns)
    with open(path, "w") as f:
        f.write("# timestamp tx ty tz qx qy qz qw (jaximu: W z-up, q of R_WB)\n")
        for s, pk, qk in zip(stamps, p, q):
            f.write(f"{_seconds_text(s)} {pk[0]:.9f} {pk[1]:.9f} {pk[2]:.9f} "
                    f"{qk[1]:.9f} {qk[2]:.9f} {qk[3]:.9f} {qk[0]:.9f}\n")


def read_tum(path):
    """Read a TUM trajectory file.

    Returns:
        ``(stamps_ns, p, q)``: ``(T,)`` int64 ns (exact from the decimal text), ``(T, 3)``,
        ``(T, 4)`` Hamilton ``[w, x, y, z]`` (converted from the file's ``[x, y, z, w]``).
    """
    _, rows, lines = _read_table(path, None)
    for fields, k in zip(rows, lines):
        if len(fields) != 8:
            raise DataError(f"{path}, line {k}: a TUM pose has 8 values, got {len(fields)}")
    stamps, values = _parse(rows, lines, 0, range(1, 8), "s", path)
    return stamps, values[:, 0:3], values[:, [6, 3, 4, 5]]


_STATE_FIELDS = (("q", ("w", "x", "y", "z")), ("p", "xyz"), ("v", "xyz"), ("b_g", "xyz"),
                 ("b_a", "xyz"))
_ERROR_NAMES = [f"{b}_{c}" for b in ("theta", "p", "v", "b_g", "b_a") for c in "xyz"]


def write_states(path, t, states, cov=None, *, t0_ns: int = 0, full_covariance: bool = True):
    """Write states (and covariances) to CSV or NPZ, by the file's suffix.

    CSV: a header line, then per state ``stamp_ns, t, q_w … q_z, p_x …, v_x …, b_g_x …,
    b_a_x …``, then the standard deviations ``sigma_theta_x … sigma_b_a_z`` (error state
    ``[dθ, dp, dv, db_g, db_a]``, rotation error on the right) and, with
    ``full_covariance``, the upper triangle of ``P`` as ``P_i_j``. NPZ: arrays
    ``stamps_ns, t, q, p, v, b_g, b_a`` and ``cov`` ``(T, 15, 15)``.

    Args:
        t: ``(T,)`` [s] since ``t0_ns``; states: a :class:`jaximu.NavState` with ``(T, ·)``
        fields; cov: ``(T, 15, 15)`` or ``None``.
    """
    path = pathlib.Path(path)
    arrays = {name: np.asarray(getattr(states, name), np.float64) for name, _ in _STATE_FIELDS}
    T = len(arrays["q"])
    if np.ndim(t) != 1 or len(t) != T or any(a.ndim != 2 or len(a) != T for a in arrays.values()):
        raise ValueError(f"t (T,) and states with (T, ·) fields expected; got t {np.shape(t)}, "
                         + ", ".join(f"{k} {a.shape}" for k, a in arrays.items()))
    if cov is not None:
        cov = np.asarray(cov, np.float64)
        if cov.shape != (T, 15, 15):
            raise ValueError(f"cov must have shape ({T}, 15, 15), got {cov.shape}")
    stamps = _stamps(t, t0_ns)
    if path.suffix == ".npz":
        extra = {} if cov is None else {"cov": cov}
        np.savez(path, stamps_ns=stamps, t=np.asarray(t, np.float64), t0_ns=np.int64(t0_ns),
                 **arrays, **extra)
        return
    if path.suffix != ".csv":
        raise ValueError(f"write_states writes .csv or .npz, not {path.suffix!r}")
    cols = ["stamp_ns", "t"] + [f"{n}_{c}" for n, comps in _STATE_FIELDS for c in comps]
    block = [np.asarray(t, np.float64)[:, None]] + [arrays[n] for n, _ in _STATE_FIELDS]
    if cov is not None:
        cols += [f"sigma_{n}" for n in _ERROR_NAMES]
        block.append(np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0, None)))
        if full_covariance:
            iu = np.triu_indices(15)
            cols += [f"P_{i}_{j}" for i, j in zip(*iu)]
            block.append(cov[:, iu[0], iu[1]])
    values = np.concatenate(block, axis=1)
    with open(path, "w") as f:
        f.write(",".join(cols) + "\n")
        for s, row in zip(stamps, values):
            f.write(f"{s}," + ",".join(repr(float(x)) for x in row) + "\n")


def read_states(path):
    """Read what :func:`write_states` wrote.

    Returns:
        ``(stamps_ns, states, cov)``: int64 ``(T,)``, a :class:`jaximu.NavState` of numpy
        float64 arrays, and ``(T, 15, 15)`` (``None`` if not written; from a CSV without the
        full covariance, diagonal from the standard deviations).
    """
    from jaximu.state import NavState  # noqa: PLC0415

    path = pathlib.Path(path)
    if path.suffix == ".npz":
        with np.load(path, allow_pickle=False) as z:
            states = NavState(*(z[n] for n, _ in _STATE_FIELDS))
            return z["stamps_ns"], states, (z["cov"] if "cov" in z.files else None)
    header, rows, lines = _read_table(path, ",")
    if header is None or header[0] != "stamp_ns":
        raise DataError(f"{path}: not a jaximu states CSV (no 'stamp_ns' header)")
    stamps, values = _parse(rows, lines, 0, range(1, len(header)), "ns", path)
    col = {name: i - 1 for i, name in enumerate(header)}
    take = lambda names: values[:, [col[n] for n in names]]  # noqa: E731
    states = NavState(*(take([f"{n}_{c}" for c in comps]) for n, comps in _STATE_FIELDS))
    cov = None
    if "P_0_0" in col:
        cov = np.zeros((len(stamps), 15, 15))
        for i, j in zip(*np.triu_indices(15)):
            cov[:, i, j] = cov[:, j, i] = values[:, col[f"P_{i}_{j}"]]
    elif "sigma_theta_x" in col:
        sig = take([f"sigma_{n}" for n in _ERROR_NAMES])
        cov = sig[:, :, None] ** 2 * np.eye(15)
    return stamps, states, cov


# --------------------------------------------------------------------------- initial state and errors


def gravity_alignment(accel_mean) -> np.ndarray:
    """The attitude ``[w, x, y, z]`` of a still IMU from its mean specific force ``(3,)``.

    Roll and pitch put the measured specific force along world +z (still and level reads
    ``[0, 0, +g]``); yaw is not observable from gravity and is set to 0 (ZYX convention,
    ``R = Rz(0) Ry(pitch) Rx(roll)``). ``accel_mean``: ``(3,)`` m/s², finite, non-zero.
    """
    f = np.asarray(accel_mean, np.float64)
    if f.shape != (3,) or not np.all(np.isfinite(f)) or not np.any(f):
        raise ValueError(f"accel_mean must be a finite, non-zero (3,) specific force [m/s²], got "
                         f"{np.array2string(f, precision=4)}")
    roll = math.atan2(f[1], f[2])
    pitch = math.atan2(-f[0], math.hypot(f[1], f[2]))
    cr, sr, cp, sp = math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    return np.array([cp * cr, cp * sr, sp * cr, -sp * sr])


def initial_state(data: ImuData, *, from_groundtruth: bool = False, still_seconds: float = 1.0,
                  bias=None):
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
    from jaximu.state import NavState  # noqa: PLC0415

    if not (np.isfinite(still_seconds) and still_seconds > 0):
        raise ValueError(f"still_seconds must be positive and finite, got {still_seconds}")
    if bias is not None and (np.shape(bias) != (6,) or not np.all(np.isfinite(bias))):
        raise ValueError(f"bias must be six finite numbers [b_g (rad/s), b_a (m/s²)], got "
                         f"shape {np.shape(bias)}")
    b = np.zeros(6) if bias is None else np.asarray(bias, np.float64).reshape(6)
    t0 = data.t[:1]
    if from_groundtruth:
        gt = data.ground_truth
        if gt is None:
            raise DataError(f"{data.source}: no ground truth to initialise from")
        q, p, _ = gt.interpolate(t0)
        v = gt.velocity(t0)
        how = "initial state from the ground truth"
        if bias is None and gt.b_g is not None:
            k = int(np.argmin(np.abs(gt.t - t0[0])))
            b = np.r_[gt.b_g[k], gt.b_a[k]]
            how += " (pose, velocity, biases)"
        else:
            how += (" (pose, velocity" + (")" if gt.v is not None else " from differentiated "
                    "positions)") + (f"; biases {'given' if bias is not None else 'zero'}"))
        return NavState(q[0], p[0], v[0], b[:3], b[3:]), how
    still = data.t <= data.t[0] + still_seconds
    if still.sum() < 2:
        raise DataError(f"fewer than 2 samples in the first {still_seconds} s")
    f = data.accel[still].mean(0) - b[3:]
    spread = float(np.linalg.norm(data.gyro[still] - data.gyro[still].mean(0), axis=1).max())
    how = (f"initial attitude from gravity alignment of the first {still_seconds:g} s "
           f"(|f| = {np.linalg.norm(f):.3f} m/s², yaw set to 0); position and velocity zero; "
           f"biases {'given' if bias is not None else 'zero'}")
    if spread > 0.1:
        how += (f". WARNING: the gyro varies by up to {spread:.2f} rad/s in that interval: the "
                "IMU does not look still, so the alignment may be off")
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
        return (float(np.linalg.norm(self.position[i])), vel,
                math.degrees(float(np.linalg.norm(self.rotation[i]))))


def trajectory_errors(t, states, ground_truth: GroundTruth, cov=None) -> TrajectoryErrors:
    """Compare estimated states with ground truth (the estimate is interpolated to the
    ground-truth stamps, so ground-truth dropouts are simply skipped).

    Args:
        t: ``(T,)`` times of the states [s, the ground truth's clock]; states: a
            :class:`jaximu.NavState` with ``(T, ·)`` fields; cov: ``(T, 15, 15)`` or ``None``.
    """
    q, p = _pose_arrays(states)
    t = np.asarray(t, np.float64)
    v = np.asarray(states.v, np.float64)
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
        var = np.diagonal(np.asarray(cov, np.float64), axis1=1, axis2=2)
        sigma = np.sqrt(np.clip(np.stack([np.interp(tk, t, var[:, j]) for j in range(15)], 1),
                                0, None))
    return TrajectoryErrors(t=tk, position=p_hat - gt.p[inside], rotation=rot, velocity=vel,
                            sigma=sigma)
