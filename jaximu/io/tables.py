"""Generic recordings: delimited text with a column mapping (:func:`read_csv`), NumPy arrays
(:func:`from_arrays`) and ``.npz`` files (:func:`read_npz`)."""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

from jaximu.errors import Fix
from jaximu.geometry import _checks as val
from jaximu.io._common import (
    _ACCEL_UNITS,
    _GYRO_UNITS,
    _TIME_UNITS,
    DataError,
    _labels,
    _rows,
    with_repair_doc,
)
from jaximu.io._text import _check_unit, _column, _header_time_unit, _parse, _read_table
from jaximu.io.containers import GroundTruth, ImuData
from jaximu.io.validation import make


@with_repair_doc
def read_csv(
    path,
    *,
    time=0,
    gyro=(1, 2, 3),
    accel=(4, 5, 6),
    time_unit: str | None = None,
    gyro_unit: str = "rad/s",
    accel_unit: str = "m/s^2",
    delimiter: str | None = None,
    comment: str = "#",
    **options,
) -> ImuData:
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
        raise DataError(
            f"{path}: the header states the time column in [{stated}] "
            f"({header[cols[0]].strip()!r}) but time_unit={time_unit!r} was given",
            [Fix("time_unit", stated)],
            api_note=" (or leave it out)",
        )
    stamps, values = _parse(rows, lines, cols[0], cols[1:], time_unit, path, True)
    return make(
        stamps,
        values[:, 0:3] * w_scale,
        values[:, 3:6] * a_scale,
        lines=lines,
        source=str(path),
        **options,
    )


@with_repair_doc
def from_arrays(
    t,
    gyro,
    accel,
    *,
    time_unit: str = "s",
    gyro_unit: str = "rad/s",
    accel_unit: str = "m/s^2",
    ground_truth: GroundTruth | None = None,
    source: str = "arrays",
    **options,
) -> ImuData:
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
    t = val.as_numbers("t", t, None)  # as_numbers refuses complex arrays too
    gyro, accel = val.as_numbers("gyro", gyro), val.as_numbers("accel", accel)
    if t.dtype.kind not in "iuf":
        raise ValueError(
            f"t must be an array of real numbers (times in {time_unit}), got {t.dtype.name}"
        )
    if t.ndim != 1:
        raise DataError(f"t must have shape (N,), got {t.shape}")
    if gyro.shape != (len(t), 3) or accel.shape != (len(t), 3):
        raise DataError(
            f"gyro and accel must have shape (N, 3) with N = {len(t)}, got "
            f"{gyro.shape} and {accel.shape}"
        )
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
        raise DataError(
            f"times beyond ±{limit:.3g} {time_unit} (int64 nanoseconds) at "
            f"{_rows(labels, np.flatnonzero(bad))}; check time_unit"
        )
    if np.issubdtype(t.dtype, np.integer):
        stamps = t.astype(np.int64) * unit_ns
    else:
        stamps = np.round(t.astype(np.float64) * unit_ns).astype(np.int64)
    data = make(stamps, gyro * w_scale, accel * a_scale, source=source, **options)
    if ground_truth is not None:
        shift = (int(stamps[0]) - data.t0_ns) * 1e-9
        data = dataclasses.replace(
            data, ground_truth=dataclasses.replace(ground_truth, t=ground_truth.t + shift)
        )
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
        # numpy's own text advises allow_pickle / pickle.load(): unsafe, and not the fix
        raise DataError(
            f"{path} is not a NumPy .npz file (an archive of arrays written by "
            "np.savez); check the file, or its format"
        ) from None
    return from_arrays(*arrays, source=str(path), **kwargs)
