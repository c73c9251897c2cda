"""EuRoC MAV and TUM-VI: the ASL folder layout (``mav0/imu0/data.csv`` and a ground-truth
folder), and flat folders (``imu.csv`` with ``groundtruth.csv`` or ``groundtruth_pose.txt``:
the excerpts bundled in ``jaximu/data`` and the learning split's sequences)."""

from __future__ import annotations

import pathlib

from jaximu.io._common import _ACCEL_UNITS, _GYRO_UNITS, DataError, with_repair_doc
from jaximu.io._text import _check_unit, _parse, _parse_tum, _read_delimited, _read_table
from jaximu.io.containers import ImuData
from jaximu.io.validation import make

_GT_DIRS = {
    "euroc": ("state_groundtruth_estimate0", "mocap0", "vicon0", "leica0"),
    "tumvi": ("mocap0", "state_groundtruth_estimate0"),
}
_FLAT_GT = ("groundtruth.csv", "groundtruth_pose.txt")  # full state first, then pose only
_NAMES = {"euroc": "EuRoC", "tumvi": "TUM-VI"}


def _asl_candidates(mav0, prefer):
    """The ground-truth files of an ASL ``mav0`` folder, in the order they are preferred."""
    return [mav0 / d / "data.csv" for d in _GT_DIRS[prefer]] + [mav0 / _FLAT_GT[1]]


def _not_a_sequence(path, prefer):
    gt = f"mav0/{_GT_DIRS[prefer][0]}/data.csv"
    return DataError(
        f"{path} is not a {_NAMES[prefer]} sequence folder: expected mav0/imu0/data.csv "
        f"(ASL layout, ground truth in {gt}), or imu.csv with groundtruth.csv (flat, full "
        f"state) or with groundtruth_pose.txt (flat, pose only); found none of them"
    )


def _asl_paths(path, groundtruth, prefer):
    """``(imu, groundtruth)`` file paths (the latter ``None`` when none is found or asked)."""
    path = pathlib.Path(path)
    if path.is_dir():
        root = path / "mav0" if (path / "mav0").is_dir() else path
        if (root / "imu0" / "data.csv").is_file():
            imu = root / "imu0" / "data.csv"
            candidates = _asl_candidates(root, prefer)
        elif (root / "imu.csv").is_file():  # flat: jaximu/data, the learning split
            imu = root / "imu.csv"
            candidates = [root / name for name in _FLAT_GT]
        else:
            raise _not_a_sequence(path, prefer)
    elif path.is_file():
        imu = path
        if path.parent.name == "imu0":  # mav0/imu0/data.csv
            candidates = _asl_candidates(path.parent.parent, prefer)
        else:  # a flat folder's imu.csv
            candidates = [path.parent / name for name in _FLAT_GT]
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


def _read_groundtruth(path):
    """Ground truth in either format, decided by the file's content: comma separated is the
    ASL CSV (stamp [ns], p, q ``[w, x, y, z]``, then optionally v, b_g, b_a); whitespace
    separated (spaces or tabs) is a TUM pose (t [s], p, q ``[x, y, z, w]``). Returns what
    :func:`make` takes: ``(stamps_ns, values, lines, cols, label)`` with values
    ``[p, q (w, x, y, z), ...]``."""
    _, rows, lines, delimiter = _read_delimited(path)
    label = f"ground truth {path}"
    if delimiter in (None, "\t"):
        stamps, values = _parse_tum(rows, lines, path)
        return stamps, values, lines, 7, label
    cols = len(rows[0]) - 1
    if cols < 7:
        raise DataError(
            f"{path}, line {lines[0]}: expected p (3) and q (4) after the stamp, got {cols} values"
        )
    stamps, values = _parse(rows, lines, 0, range(1, cols + 1), "ns", path)
    return stamps, values, lines, cols, label


def _read_asl(path, groundtruth, prefer, options, gyro_unit="rad/s", accel_unit="m/s^2"):
    w_scale = _check_unit("gyro_unit", gyro_unit, _GYRO_UNITS)
    a_scale = _check_unit("accel_unit", accel_unit, _ACCEL_UNITS)
    imu_path, gt_path = _asl_paths(path, groundtruth, prefer)
    _, rows, lines = _read_table(imu_path, ",")
    stamps, values = _parse(rows, lines, 0, range(1, 7), "ns", imu_path)
    gt = None if gt_path is None else _read_groundtruth(gt_path)
    source = str(imu_path) + (f" + {gt_path}" if gt_path else "")
    return make(
        stamps,
        values[:, 0:3] * w_scale,
        values[:, 3:6] * a_scale,
        lines=lines,
        ground_truth=gt,
        source=source,
        **options,
    )


@with_repair_doc
def read_euroc(
    path, *, groundtruth=True, gyro_unit: str = "rad/s", accel_unit: str = "m/s^2", **options
) -> ImuData:
    """Read a EuRoC MAV sequence, in any of three layouts:

    * ASL (the dataset's own): ``mav0/imu0/data.csv``, ground truth in
      ``mav0/state_groundtruth_estimate0/data.csv`` (or ``mocap0``, ``vicon0``, ``leica0``,
      or a pose-only ``mav0/groundtruth_pose.txt``);
    * flat, full state: a folder with ``imu.csv`` (as ``imu0/data.csv``) and
      ``groundtruth.csv`` (as ``state_groundtruth_estimate0/data.csv``);
    * flat, pose only: a folder with ``imu.csv`` and ``groundtruth_pose.txt``.

    The ground-truth files come in two formats, told apart by their content: the ASL CSV
    (comma separated: stamp [ns], p [m], q Hamilton ``[w, x, y, z]`` of ``R_WB``, then
    v [m/s], b_g [rad/s], b_a [m/s²] if present), and a TUM pose file (spaces or tabs,
    8 values a row: ``t tx ty tz qx qy qz qw``, t in seconds, read exactly to the
    nanosecond; q ``[x, y, z, w]``, reordered to ``[w, x, y, z]``; v, b_g, b_a ``None``:
    :meth:`GroundTruth.velocity` differentiates the positions).

    Args:
        path: the sequence folder (holding ``mav0``), ``mav0`` itself, its
            ``imu0/data.csv``, a flat folder, or its ``imu.csv``.
        groundtruth: ``True`` to load the layout's ground truth when present (the full
            state before a pose-only file; ``None`` when there is none), a path to a file
            in either format, or ``False``.
        gyro_unit, accel_unit: ``"rad/s"`` or ``"deg/s"``; ``"m/s^2"`` or ``"g"``
            (converted to SI). EuRoC's and TUM-VI's own files are SI (the default); these
            are for other recordings stored in the ASL layout.
        options: {repair}

    Returns:
        :class:`ImuData` with int64 stamps exactly as in the file, and its
        :class:`GroundTruth` on the same clock (or ``None``).

    Raises:
        DataError: a folder holding neither ``mav0/imu0/data.csv`` nor ``imu.csv`` (the
            message lists the layouts); a ground-truth file with a row of the wrong width,
            NaN or inf values, times that do not increase, or quaternions that are not unit
            (naming the file and line); what :func:`validate_imu` refuses.
    """
    return _read_asl(path, groundtruth, "euroc", options, gyro_unit, accel_unit)


def read_tumvi(
    path, *, groundtruth=True, gyro_unit: str = "rad/s", accel_unit: str = "m/s^2", **options
) -> ImuData:
    """Read a TUM-VI sequence (ASL layout: ``mav0/imu0/data.csv``, motion capture in
    ``mav0/mocap0/data.csv``: pose only, 120 Hz with dropouts; the IMU's intervals vary; or
    a flat folder as :func:`read_euroc` reads).

    Args as :func:`read_euroc`.
    """
    return _read_asl(path, groundtruth, "tumvi", options, gyro_unit, accel_unit)
