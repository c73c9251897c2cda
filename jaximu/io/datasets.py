"""Real IMU data bundled with the package (for the demo, examples and tests).

``euroc_v1_02_segment()`` reads the 20 s excerpt of EuRoC MAV V1_02_medium shipped in
``jaximu/data/euroc_v1_02_medium``, ``euroc_v2_01_segment()`` a 20 s excerpt of V2_01_easy
(another room, another day) in ``jaximu/data/euroc_v2_01_easy`` (see their ``SOURCE.md``
for origin and licence).
"""

from __future__ import annotations

import dataclasses
from importlib import resources

import numpy as np

__all__ = ["EurocSegment", "euroc_v1_02_segment", "euroc_v2_01_segment"]


@dataclasses.dataclass(frozen=True)
class EurocSegment:
    """IMU samples and full-state ground truth of a EuRoC MAV excerpt (numpy, float64).

    Times are seconds since ``t0_ns`` (the first IMU stamp, int64 nanoseconds, kept exact).
    Ground-truth quaternions are ``[w, x, y, z]`` of ``R_WB`` as stored (|q| may differ
    from 1 by ~1e-4 in the file; they are *not* normalised here).

    Attributes:
        t0_ns: first IMU stamp [ns].
        t: ``(N,)`` IMU times [s]; gyro, accel: ``(N, 3)`` raw samples [rad/s], [m/s²].
        t_gt: ``(M,)`` ground-truth times [s]; q_gt ``(M, 4)``, p_gt, v_gt ``(M, 3)`` in W;
        b_g_gt, b_a_gt: ``(M, 3)`` bias estimates of the dataset [rad/s], [m/s²].
    """

    t0_ns: int
    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    t_gt: np.ndarray
    q_gt: np.ndarray
    p_gt: np.ndarray
    v_gt: np.ndarray
    b_g_gt: np.ndarray
    b_a_gt: np.ndarray


def _read_csv(path):
    """Rows of a EuRoC CSV: int64 nanosecond stamps (exact) and float64 values."""
    with open(path) as f:
        rows = [line.split(",") for line in f if line.strip() and not line.startswith("#")]
    stamps = np.array([int(r[0]) for r in rows], dtype=np.int64)
    values = np.array([[float(x) for x in r[1:]] for r in rows], dtype=np.float64)
    return stamps, values


def euroc_v1_02_segment() -> EurocSegment:
    """The bundled 20 s excerpt of EuRoC MAV V1_02_medium (200 Hz ADIS16448 + ground truth)."""
    return _euroc_segment("euroc_v1_02_medium")


def euroc_v2_01_segment() -> EurocSegment:
    """The bundled 20 s excerpt of EuRoC MAV V2_01_easy (flight from 10 s to 30 s)."""
    return _euroc_segment("euroc_v2_01_easy")


def _euroc_segment(folder) -> EurocSegment:
    base = resources.files("jaximu") / "data" / folder
    with resources.as_file(base / "imu.csv") as p:
        ts_imu, imu = _read_csv(p)
    with resources.as_file(base / "groundtruth.csv") as p:
        ts_gt, gt = _read_csv(p)
    t0 = int(ts_imu[0])
    return EurocSegment(
        t0_ns=t0,
        t=(ts_imu - t0) * 1e-9,
        gyro=imu[:, 0:3],
        accel=imu[:, 3:6],
        t_gt=(ts_gt - t0) * 1e-9,
        p_gt=gt[:, 0:3],
        q_gt=gt[:, 3:7],
        v_gt=gt[:, 7:10],
        b_g_gt=gt[:, 10:13],
        b_a_gt=gt[:, 13:16],
    )
