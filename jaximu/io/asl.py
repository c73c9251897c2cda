"""EuRoC MAV and TUM-VI: the ASL folder layout (``mav0/imu0/data.csv`` and a ground-truth
folder), and the flat excerpts bundled in ``jaximu/data``."""

from __future__ import annotations

import pathlib

from jaximu.io._common import _ACCEL_UNITS, _GYRO_UNITS, DataError, with_repair_doc
from jaximu.io._text import _check_unit, _parse, _read_table
from jaximu.io.containers import ImuData
from jaximu.io.validation import make


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


def _read_asl(path, groundtruth, prefer, options, gyro_unit="rad/s", accel_unit="m/s^2"):
    w_scale = _check_unit("gyro_unit", gyro_unit, _GYRO_UNITS)
    a_scale = _check_unit("accel_unit", accel_unit, _ACCEL_UNITS)
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
        gt = (g_stamps, g_values, g_lines, cols, f"ground truth {gt_path}")
    source = str(imu_path) + (f" + {gt_path}" if gt_path else "")
    return make(stamps, values[:, 0:3] * w_scale, values[:, 3:6] * a_scale, lines=lines,
                ground_truth=gt, source=source, **options)


@with_repair_doc
def read_euroc(path, *, groundtruth=True, gyro_unit: str = "rad/s", accel_unit: str = "m/s^2",
               **options) -> ImuData:
    """Read a EuRoC MAV sequence (ASL layout).

    Args:
        path: the sequence folder (holding ``mav0``), ``mav0`` itself, its
            ``imu0/data.csv``, or a flat folder with ``imu.csv`` and ``groundtruth.csv``
            (the excerpts bundled in ``jaximu/data``).
        groundtruth: ``True`` to load ``state_groundtruth_estimate0/data.csv`` when present
            (p, q ``[w, x, y, z]`` of ``R_WB``, v, b_g, b_a), a path, or ``False``.
        gyro_unit, accel_unit: ``"rad/s"`` or ``"deg/s"``; ``"m/s^2"`` or ``"g"``
            (converted to SI). EuRoC's and TUM-VI's own files are SI (the default); these
            are for other recordings stored in the ASL layout.
        options: {repair}

    Returns:
        :class:`ImuData` with int64 stamps exactly as in the file.
    """
    return _read_asl(path, groundtruth, "euroc", options, gyro_unit, accel_unit)


def read_tumvi(path, *, groundtruth=True, gyro_unit: str = "rad/s", accel_unit: str = "m/s^2",
               **options) -> ImuData:
    """Read a TUM-VI sequence (ASL layout: ``mav0/imu0/data.csv``, motion capture in
    ``mav0/mocap0/data.csv``: pose only, 120 Hz with dropouts; the IMU's intervals vary).

    Args as :func:`read_euroc`.
    """
    return _read_asl(path, groundtruth, "tumvi", options, gyro_unit, accel_unit)
