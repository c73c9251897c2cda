"""Reading IMU recordings and writing trajectories.

Readers return one container, :class:`ImuData`: exact int64 nanosecond stamps, times in
seconds (float64) since the first stamp, raw gyro [rad/s] and accelerometer [m/s²] samples
in the IMU frame, and optional :class:`GroundTruth`.

* :func:`read_euroc` / :func:`read_tumvi`: EuRoC MAV and TUM-VI sequences in three
  layouts: the datasets' own ASL layout (``mav0/imu0/data.csv``; ground truth from
  ``state_groundtruth_estimate0`` (EuRoC: pose, velocity, biases) or ``mocap0`` (TUM-VI:
  pose only)); a flat folder with ``imu.csv`` and the full-state ``groundtruth.csv``; a flat
  folder with ``imu.csv`` and ``groundtruth_pose.txt`` (pose only, TUM format
  ``t tx ty tz qx qy qz qw`` in seconds, read exactly to the nanosecond).
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

The package is split along its seams; every name above is importable from ``jaximu.io``:

* :mod:`jaximu.io.containers`: :class:`ImuData`, :class:`GroundTruth`.
* :mod:`jaximu.io.validation`: :func:`validate_imu` and the container built from what passes.
* :mod:`jaximu.io.asl` (EuRoC, TUM-VI), :mod:`jaximu.io.tables` (CSV, arrays, NPZ),
  :mod:`jaximu.io.rosbag` (ROS bags): the readers.
* :mod:`jaximu.io.writers`: TUM and states files.
* :mod:`jaximu.io.evaluation`: :func:`initial_state`, :func:`trajectory_errors`.
"""

from jaximu.io._common import CLOCK_TOLERANCE, GAP_FACTOR, STANDARD_GRAVITY, DataError
from jaximu.io.asl import read_euroc, read_tumvi
from jaximu.io.containers import GroundTruth, ImuData
from jaximu.io.evaluation import (
    TrajectoryErrors,
    gravity_alignment,
    initial_state,
    trajectory_errors,
)
from jaximu.io.rosbag import read_rosbag
from jaximu.io.tables import from_arrays, read_csv, read_npz
from jaximu.io.validation import validate_imu
from jaximu.io.writers import read_states, read_tum, write_states, write_tum

__all__ = [
    "DataError",
    "GroundTruth",
    "ImuData",
    "validate_imu",
    "read_euroc",
    "read_tumvi",
    "read_csv",
    "from_arrays",
    "read_npz",
    "read_rosbag",
    "write_tum",
    "read_tum",
    "write_states",
    "read_states",
    "STANDARD_GRAVITY",
    "gravity_alignment",
    "initial_state",
    "TrajectoryErrors",
    "trajectory_errors",
    "CLOCK_TOLERANCE",
    "GAP_FACTOR",
]
