"""ROS 1 and ROS 2 bags of ``sensor_msgs/Imu``, through the ``rosbags`` library."""

from __future__ import annotations

import pathlib
from typing import Any

import numpy as np

from jaximu.io._common import _ACCEL_UNITS, _GYRO_UNITS, DataError, with_repair_doc
from jaximu.io._text import _check_unit
from jaximu.io.containers import ImuData
from jaximu.io.validation import make


@with_repair_doc
def read_rosbag(
    path,
    topic: str | None = None,
    *,
    stamp: str = "header",
    gyro_unit: str = "rad/s",
    accel_unit: str = "m/s^2",
    **options,
) -> ImuData:
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
        raise ImportError('reading ROS bags needs rosbags: pip install "jaximu[rosbag]"') from None
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
                raise DataError(
                    f"{path}: {len(imu_topics)} {imu_type} topics {imu_topics}; "
                    "name one with topic="
                )
            topic = imu_topics[0]
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            raise DataError(f"{path}: no topic {topic!r}; IMU topics: {imu_topics}")
        if conns[0].msgtype != imu_type:
            raise DataError(f"{path}: topic {topic!r} has type {conns[0].msgtype}, not {imu_type}")
        stamps, gyro, accel = [], [], []
        try:
            for conn, log_ns, raw in reader.messages(connections=conns):
                msg: Any = reader.deserialize(raw, conn.msgtype)  # a sensor_msgs/Imu
                w, a = msg.angular_velocity, msg.linear_acceleration
                if stamp == "header":
                    s = msg.header.stamp
                    stamps.append(int(s.sec) * 10**9 + int(s.nanosec))
                else:
                    stamps.append(int(log_ns))
                gyro.append((w.x, w.y, w.z))
                accel.append((a.x, a.y, a.z))
        except Exception as e:  # a corrupt message or chunk: rosbags' own error types
            raise DataError(
                f"{path}: message row {len(stamps)} on {topic!r} could not be read "
                f"({type(e).__name__}: {e})"
            ) from None
    finally:
        reader.close()
    if not stamps:
        raise DataError(f"{path}: topic {topic!r} holds no messages")
    return make(
        np.asarray(stamps, np.int64),
        np.asarray(gyro, np.float64) * w_scale,
        np.asarray(accel, np.float64) * a_scale,
        source=f"{path}:{topic}",
        **options,
    )
