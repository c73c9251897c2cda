"""Checks of a loaded recording, the repairs the options ask for, and the container built
from what passes (every reader ends in :func:`make`)."""

from __future__ import annotations

import numpy as np

from jaximu.errors import Fix
from jaximu.geometry import _checks as val
from jaximu.geometry import _tolerances
from jaximu.io._common import (
    _ACCEL_MEDIAN_RANGE,
    _DT_RANGE,
    _GYRO_MAX,
    _GYRO_MEDIAN_MAX,
    GAP_FACTOR,
    QUATERNION_NORM_TOLERANCE,
    DataError,
    _labels,
    _max_gap,
    _rows,
)
from jaximu.io.containers import GroundTruth, ImuData


def validate_imu(
    stamps_ns,
    gyro,
    accel,
    *,
    lines=None,
    sort: bool = False,
    drop_duplicates: bool = False,
    drop_nonfinite: bool = False,
    max_gap: float | None = None,
    allow_gaps: bool = False,
    check_units: bool = True,
):
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
        ValueError: an option of the wrong kind (``sort="no"``: the options are bools).
    """
    sort = val.check_bool("sort", sort)
    drop_duplicates = val.check_bool("drop_duplicates", drop_duplicates)
    drop_nonfinite = val.check_bool("drop_nonfinite", drop_nonfinite)
    allow_gaps = val.check_bool("allow_gaps", allow_gaps)
    check_units = val.check_bool("check_units", check_units)
    max_gap = _max_gap(max_gap)
    stamps_ns = val.as_numbers("stamps_ns", stamps_ns, None)
    gyro = val.as_numbers("gyro", gyro)
    accel = val.as_numbers("accel", accel)
    n = len(stamps_ns)
    if gyro.shape != (n, 3) or accel.shape != (n, 3):
        raise DataError(
            f"gyro and accel must have shape (N, 3) with N = {n} stamps; got "
            f"{gyro.shape} and {accel.shape}"
        )
    labels = _labels(n, lines)
    repairs: list[str] = []
    idx = np.arange(n)

    bad = ~(np.isfinite(gyro).all(1) & np.isfinite(accel).all(1))
    if bad.any():
        rows = np.flatnonzero(bad)
        if not drop_nonfinite:
            raise DataError(
                f"{len(rows)} sample(s) with NaN or inf values at {_rows(labels, rows)}",
                [Fix("drop_nonfinite", True)],
                api_note=" to drop them",
            )
        repairs.append(
            f"dropped {len(rows)} sample(s) with NaN/inf values: {_rows(labels, rows, 20)}"
        )
        idx = idx[~bad]

    back = np.flatnonzero(np.diff(stamps_ns[idx]) < 0) + 1
    if len(back):
        if not sort:
            i = idx[back]
            raise DataError(
                f"timestamps go backwards at {len(back)} place(s): "
                f"{_rows(labels, i)} (earlier than the row before)",
                [Fix("sort", True)],
                api_note=" to sort by time",
            )
        order = np.argsort(stamps_ns[idx], kind="stable")
        moved = int(np.sum(order != np.arange(len(order))))
        repairs.append(
            f"sorted by time: {moved} sample(s) moved (first out of order at "
            f"{labels[idx[back[0]]]})"
        )
        idx = idx[order]

    dup = np.flatnonzero(np.diff(stamps_ns[idx]) == 0) + 1
    if len(dup):
        if not drop_duplicates:
            raise DataError(
                f"{len(dup)} duplicate timestamp(s) at {_rows(labels, idx[dup])} "
                "(same stamp as the row before)",
                [Fix("drop_duplicates", True)],
                api_note=" to keep the first of each",
            )
        same = np.all(gyro[idx[dup]] == gyro[idx[dup - 1]], axis=1) & np.all(
            accel[idx[dup]] == accel[idx[dup - 1]], axis=1
        )
        repairs.append(
            f"dropped {len(dup)} sample(s) with a duplicate timestamp "
            f"({int(same.sum())} identical to the kept one): "
            f"{_rows(labels, idx[dup], 20)}"
        )
        idx = np.delete(idx, dup)

    if len(idx) < 2:
        raise DataError(f"fewer than 2 usable samples ({len(idx)} of {n})")
    dt = np.diff(stamps_ns[idx]) * 1e-9
    med = float(np.median(dt))
    if check_units and not _DT_RANGE[0] <= med <= _DT_RANGE[1]:
        raise DataError(
            f"median sampling interval {med:.3g} s ({1 / med:.3g} Hz) is implausible for an IMU",
            [Fix("time_unit", phrase="check the time unit ({})")],
            lead="",
        )
    limit = max_gap if max_gap is not None else GAP_FACTOR * med
    gaps = np.flatnonzero(dt > limit)
    if len(gaps):
        where = ", ".join(f"{dt[g]:.4g} s after {labels[idx[g]]}" for g in gaps[:5])
        more = f", … ({len(gaps)} in all)" if len(gaps) > 5 else ""
        if not allow_gaps:
            raise DataError(
                f"{len(gaps)} gap(s) longer than {limit:.4g} s: {where}{more}",
                [Fix("allow_gaps", True), Fix("max_gap", phrase="a larger")],
                api_note=" (allow_gaps keeps them: then split_at_gaps())",
            )
        repairs.append(f"kept {len(gaps)} gap(s) longer than {limit:.4g} s: {where}{more}")

    if check_units:
        g, a = gyro[idx], accel[idx]
        with np.errstate(over="ignore"):  # magnitudes near the float64 limit: inf, reported below
            wn, an = np.linalg.norm(g, axis=1), np.linalg.norm(a, axis=1)
        if wn.max() > _GYRO_MAX or np.median(wn) > _GYRO_MEDIAN_MAX:
            worst = int(np.argmax(wn))
            raise DataError(
                f"gyro magnitudes up to {wn.max():.4g} (median {np.median(wn):.3g}) at "
                f"{labels[idx[worst]]} are implausible in rad/s (±2000 °/s = 34.9 rad/s): is the "
                "gyro in deg/s?",
                [Fix("gyro_unit", "deg/s"), Fix("check_units", False)],
                sep=" ",
            )
        am = float(np.median(an))
        if not _ACCEL_MEDIAN_RANGE[0] <= am <= _ACCEL_MEDIAN_RANGE[1]:
            in_g = am < _ACCEL_MEDIAN_RANGE[0]
            hint = "is the accelerometer in g?" if in_g else "check the accelerometer unit;"
            raise DataError(
                f"median accelerometer magnitude {am:.4g} is implausible in m/s² "
                f"(gravity alone reads 9.81): {hint}",
                ([Fix("accel_unit", "g")] if in_g else []) + [Fix("check_units", False)],
                sep=" ",
            )
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
    qn = np.abs(np.linalg.norm(values[:, 3:7], axis=1) - 1)
    off = np.flatnonzero(~(qn <= QUATERNION_NORM_TOLERANCE))
    _tolerances.check_unit_norm(
        f"{label}: the quaternion",
        values[:, 3:7],
        np.float64,
        tol=QUATERNION_NORM_TOLERANCE,
        error=DataError,
        what="is not a [w, x, y, z] unit quaternion",
        where=lambda i: f" at {_rows(labels, off)}",
        fix="check the column order (p, then q as w, x, y, z)",
    )


def make(stamps_ns, gyro, accel, *, lines=None, ground_truth=None, source="", **options):
    stamps_ns = val.as_numbers("stamps_ns", stamps_ns, np.int64)
    idx, repairs = validate_imu(stamps_ns, gyro, accel, lines=lines, **options)
    stamps = stamps_ns[idx]
    t0 = int(stamps[0])
    gt = None
    if ground_truth is not None:
        gt_ns, gt_values, gt_lines, cols = ground_truth[:4]
        label = ground_truth[4] if len(ground_truth) > 4 else "ground truth"
        if len(gt_ns) < 2:
            raise DataError(
                f"{label}: the ground truth has {len(gt_ns)} row(s); at least 2 "
                "are needed to interpolate it"
            )
        _validate_groundtruth(gt_ns, gt_values, gt_lines, label)
        t_gt = (gt_ns - t0) * 1e-9
        get = lambda i: gt_values[:, i : i + 3].copy() if gt_values.shape[1] >= i + 3 else None  # noqa: E731
        gt = GroundTruth(
            t=t_gt,
            p=gt_values[:, 0:3].copy(),
            q=gt_values[:, 3:7].copy(),
            v=get(7) if cols >= 10 else None,
            b_g=get(10) if cols >= 13 else None,
            b_a=get(13) if cols >= 16 else None,
        )
    t = (stamps - t0) * 1e-9
    close = np.flatnonzero(np.diff(t) <= 0)
    if len(close):  # only past ~10^8 s: float64 seconds then resolve ~15 ns
        raise DataError(
            f"stamps {stamps[close[0]]} and "
            f"{stamps[close[0] + 1]} ns are distinct but equal in float64 seconds "
            f"since the first stamp (the recording spans {t[-1]:.3g} s); check the "
            "time unit"
        )
    return ImuData(
        stamps_ns=stamps,
        t=t,
        gyro=np.array(gyro, np.float64)[idx],
        accel=np.array(accel, np.float64)[idx],
        t0_ns=t0,
        ground_truth=gt,
        source=source,
        repairs=repairs,
    )
