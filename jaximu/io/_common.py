"""What the readers and writers share: units, plausibility limits, the error type and how
rows are named in messages."""

from __future__ import annotations

import math

import numpy as np

from jaximu.errors import InputError

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
QUATERNION_NORM_TOLERANCE = 1e-2
"""How far from 1 a stored quaternion's norm may be (files round it: EuRoC's ground truth is
off by up to 1.5e-4); beyond it the numbers are not a unit quaternion (a wrong column, a
scaled q), refused rather than normalised."""


def in_gap(t_ref, t, max_gap=None):
    """Which times ``t`` (within ``[t_ref[0], t_ref[-1]]``) fall strictly inside an interval
    of the sorted reference times ``t_ref`` longer than ``max_gap`` (default
    :data:`GAP_FACTOR` × the median interval): a dropout, which interpolation must not
    bridge (the one rule of :meth:`GroundTruth.interpolate`, the calibration's windows and
    the command's comparisons). Returns ``(inside, k, limit)``: ``(n,)`` booleans, the index
    ``k`` of the interval ``[t_ref[k], t_ref[k + 1]]`` holding each time, and the limit [s]."""
    d = np.diff(t_ref)
    limit = max_gap if max_gap is not None else GAP_FACTOR * float(np.median(d))
    k = np.clip(np.searchsorted(t_ref, t, side="right") - 1, 0, len(t_ref) - 2)
    return (d[k] > limit) & (t > t_ref[k]) & (t < t_ref[k + 1]), k, limit


CLOCK_TOLERANCE = 1e-5  # [s] stamps this close count as the same instant


class DataError(InputError):
    """A recording that cannot be used as it is; the message names the rows, and
    :attr:`fixes` holds the options that repair it (:class:`jaximu.errors.InputError`)."""


def _seconds(name, x, *, positive=False, allow_inf=False) -> float:
    """A time option [s] as a ``float``: a real number (not text, not a bool), not NaN,
    finite unless ``allow_inf``, and ``> 0`` if ``positive``; else a ``ValueError`` naming
    ``name``."""
    if isinstance(x, (bool, np.bool_, str, bytes)) or np.ndim(x) != 0:
        raise ValueError(f"{name} must be a number of seconds, got {type(x).__name__} {x!r}")
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(
            f"{name} must be a number of seconds, got {type(x).__name__} {x!r}"
        ) from None
    if math.isnan(v) or (math.isinf(v) and not allow_inf) or (positive and not v > 0):
        kind = "a positive" if positive else "a finite"
        raise ValueError(f"{name} must be {kind} number of seconds, got {x!r}")
    return v


def _max_gap(x):
    """``max_gap``: ``None`` (the default threshold) or seconds ``> 0`` (``inf``: no limit)."""
    return None if x is None else _seconds("max_gap", x, positive=True, allow_inf=True)


def _rows(labels, idx, limit=5) -> str:
    idx = np.asarray(idx).ravel()
    shown = ", ".join(str(labels[i]) for i in idx[:limit])
    more = f", … ({len(idx)} in all)" if len(idx) > limit else ""
    return shown + more


def _labels(n, lines=None):
    if lines is None:
        return [f"row {i}" for i in range(n)]
    return [f"line {int(k)}" for k in lines]


REPAIR_DOC = """sort, drop_duplicates, drop_nonfinite, max_gap, allow_gaps, check_units:
            see :func:`jaximu.io.validate_imu` (the default raises :class:`DataError`)."""


def with_repair_doc(f):
    """Put :data:`REPAIR_DOC` into ``f``'s docstring (its ``{repair}``)."""
    f.__doc__ = f.__doc__.replace("{repair}", REPAIR_DOC)
    return f
