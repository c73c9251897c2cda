"""read_rosbag on small ROS 1 / ROS 2 bags that the tests write with the rosbags writers.

No JAX: everything here is NumPy and rosbags, tiny bags in tmp_path.
"""

import re

import numpy as np
import pytest

rosbags = pytest.importorskip("rosbags")

from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from jaximu.io import DataError, read_rosbag

IMU = "sensor_msgs/msg/Imu"
STRING = "std_msgs/msg/String"
T0_NS = 1403715524 * 10**9 + 907142912  # a non-round epoch (EuRoC-like)
DT_NS = 5_000_000  # 200 Hz
N = 50

# ROS 1 (.bag file), ROS 2 sqlite3 and (where this rosbags writes it) ROS 2 mcap folders.
FORMATS = ["ros1", "sqlite3"] + (["mcap"] if hasattr(StoragePlugin, "MCAP") else [])

_STORES = {}


def _typestore(fmt):
    key = Stores.ROS1_NOETIC if fmt == "ros1" else Stores.ROS2_HUMBLE
    if key not in _STORES:
        _STORES[key] = get_typestore(key)
    return _STORES[key]


def _imu_msg(ts, fmt, stamp_ns, gyro, accel, seq=0):
    T = ts.types
    sec, nanosec = divmod(int(stamp_ns), 10**9)
    stamp = T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    if fmt == "ros1":
        header = T["std_msgs/msg/Header"](seq=seq, stamp=stamp, frame_id="imu")
    else:
        header = T["std_msgs/msg/Header"](stamp=stamp, frame_id="imu")
    vec = T["geometry_msgs/msg/Vector3"]
    return T[IMU](
        header=header,
        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.full(9, -1.0),  # "no orientation", as REP 145 says
        angular_velocity=vec(x=float(gyro[0]), y=float(gyro[1]), z=float(gyro[2])),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=vec(x=float(accel[0]), y=float(accel[1]), z=float(accel[2])),
        linear_acceleration_covariance=np.zeros(9),
    )


def write_bag(tmp_path, fmt, topics, name="rec"):
    """Write a bag; ``topics``: ``{topic: (msgtype, [(log_ns, payload), ...])}`` where the
    payload is ``(stamp_ns, gyro, accel)`` for Imu, a str for String, or raw ``bytes`` (written
    as they are). Messages go in in log-time order. Returns the path to read (the ``.bag``
    file, or the ROS 2 bag folder)."""
    ts = _typestore(fmt)
    ros1 = fmt == "ros1"
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    if ros1:
        path = tmp_path / f"{name}.bag"
        writer = Writer1(path)
    else:
        path = tmp_path / name
        plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=Writer2.VERSION_LATEST, storage_plugin=plugin)
    with writer:
        entries = []
        for topic, (msgtype, msgs) in topics.items():
            conn = writer.add_connection(topic, msgtype, typestore=ts)
            for seq, (log_ns, payload) in enumerate(msgs):
                if isinstance(payload, bytes):
                    data = payload
                elif msgtype == IMU:
                    data = ser(_imu_msg(ts, fmt, *payload, seq=seq), IMU)
                else:
                    data = ser(ts.types[STRING](data=payload), STRING)
                entries.append((int(log_ns), conn, data))
        for log_ns, conn, data in sorted(entries, key=lambda e: e[0]):
            writer.write(conn, log_ns, data)
    return path


def make_series(seed, n=N, t0_ns=T0_NS, gyro_scale=0.3):
    """``(stamps_ns, log_ns, gyro, accel)``: header stamps on a jittered 200 Hz grid, receive
    times 1.7–2.2 ms later, gyro [rad/s] and accel [m/s²] of realistic size."""
    rng = np.random.default_rng(seed)
    stamps = t0_ns + np.arange(n, dtype=np.int64) * DT_NS + rng.integers(-20_000, 20_000, n)
    log = stamps + 1_700_123 + rng.integers(0, 500_000, n)
    gyro = rng.normal(0.0, gyro_scale, (n, 3))
    accel = np.array([0.3, -0.2, 9.81]) + rng.normal(0.0, 0.5, (n, 3))
    return stamps, log, gyro, accel


def imu_topic(stamps, log, gyro, accel):
    return (IMU, [(lg, (s, g, a)) for s, lg, g, a in zip(stamps, log, gyro, accel)])


# --------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("fmt", FORMATS)
def test_round_trip(tmp_path, fmt):
    stamps, log, gyro, accel = make_series(1)
    path = write_bag(tmp_path, fmt, {"/imu0": imu_topic(stamps, log, gyro, accel)})
    data = read_rosbag(path)
    assert data.stamps_ns.dtype == np.int64
    np.testing.assert_array_equal(data.stamps_ns, stamps)  # exact integer nanoseconds
    assert data.t0_ns == int(stamps[0]) == T0_NS + int(stamps[0] - T0_NS)
    assert data.t.dtype == np.float64
    np.testing.assert_array_equal(data.t, (stamps - stamps[0]) * 1e-9)
    assert data.gyro.dtype == data.accel.dtype == np.float64
    np.testing.assert_array_equal(data.gyro, gyro)  # float64 survives bit for bit
    np.testing.assert_array_equal(data.accel, accel)
    assert data.repairs == ()
    assert data.ground_truth is None
    assert "/imu0" in data.source
    assert abs(data.rate_hz - 200.0) < 1.0
    # a str path and the topic named explicitly read the same
    again = read_rosbag(str(path), "/imu0")
    np.testing.assert_array_equal(again.stamps_ns, stamps)
    np.testing.assert_array_equal(again.gyro, gyro)


@pytest.mark.parametrize("fmt", [f for f in FORMATS if f != "ros1"])
def test_ros2_storage_file(tmp_path, fmt):
    """A ROS 2 storage file (``.db3`` / ``.mcap``) given directly, without its folder."""
    stamps, log, gyro, accel = make_series(2)
    folder = write_bag(tmp_path, fmt, {"/imu0": imu_topic(stamps, log, gyro, accel)})
    (file,) = folder.glob("*.db3" if fmt == "sqlite3" else "*.mcap")
    data = read_rosbag(file)
    np.testing.assert_array_equal(data.stamps_ns, stamps)
    np.testing.assert_array_equal(data.gyro, gyro)
    np.testing.assert_array_equal(data.accel, accel)


# --------------------------------------------------------------------------- stamps


@pytest.mark.parametrize("fmt", FORMATS)
def test_log_stamps(tmp_path, fmt):
    stamps, log, gyro, accel = make_series(3)
    assert not np.any(stamps == log)
    path = write_bag(tmp_path, fmt, {"/imu0": imu_topic(stamps, log, gyro, accel)})
    by_log = read_rosbag(path, stamp="log")
    np.testing.assert_array_equal(by_log.stamps_ns, log)
    assert by_log.t0_ns == int(log[0])
    np.testing.assert_array_equal(by_log.t, (log - log[0]) * 1e-9)
    np.testing.assert_array_equal(by_log.gyro, gyro)
    np.testing.assert_array_equal(by_log.accel, accel)
    by_header = read_rosbag(path, stamp="header")
    np.testing.assert_array_equal(by_header.stamps_ns, stamps)


def test_unknown_stamp_option(tmp_path):
    stamps, log, gyro, accel = make_series(4)
    path = write_bag(tmp_path, "ros1", {"/imu0": imu_topic(stamps, log, gyro, accel)})
    with pytest.raises(ValueError, match="stamp"):
        read_rosbag(path, stamp="receive")


# --------------------------------------------------------------------------- topics


@pytest.mark.parametrize("fmt", FORMATS)
def test_topic_selection(tmp_path, fmt):
    s0, l0, g0, a0 = make_series(5)
    s1, l1, g1, a1 = make_series(6, n=40, t0_ns=T0_NS + 1_234_567)
    path = write_bag(
        tmp_path,
        fmt,
        {
            "/imu0": imu_topic(s0, l0, g0, a0),
            "/imu1": imu_topic(s1, l1, g1, a1),
            "/status": (STRING, [(l0[0] + 1, "ok"), (l0[10] + 1, "still ok")]),
        },
    )
    with pytest.raises(DataError) as err:
        read_rosbag(path)
    assert "/imu0" in str(err.value) and "/imu1" in str(err.value)
    assert "topic=" in str(err.value)

    one = read_rosbag(path, topic="/imu1")
    np.testing.assert_array_equal(one.stamps_ns, s1)
    np.testing.assert_array_equal(one.gyro, g1)
    np.testing.assert_array_equal(one.accel, a1)
    assert "/imu1" in one.source
    zero = read_rosbag(path, "/imu0")
    np.testing.assert_array_equal(zero.stamps_ns, s0)
    np.testing.assert_array_equal(zero.gyro, g0)

    with pytest.raises(DataError, match="/nope"):
        read_rosbag(path, topic="/nope")
    with pytest.raises(DataError, match=re.escape(STRING)):
        read_rosbag(path, topic="/status")


@pytest.mark.parametrize("fmt", ["ros1", "sqlite3"])
def test_no_imu_topic(tmp_path, fmt):
    path = write_bag(tmp_path, fmt, {"/status": (STRING, [(T0_NS, "hello")])})
    with pytest.raises(DataError, match="0 sensor_msgs/msg/Imu topics"):
        read_rosbag(path)


@pytest.mark.parametrize("fmt", ["ros1", "sqlite3"])
def test_empty_imu_topic(tmp_path, fmt):
    path = write_bag(tmp_path, fmt, {"/imu0": (IMU, []), "/status": (STRING, [(T0_NS, "x")])})
    with pytest.raises(DataError, match="no messages"):
        read_rosbag(path)


# --------------------------------------------------------------------------- validation


@pytest.mark.parametrize("fmt", FORMATS)
def test_duplicate_stamps(tmp_path, fmt):
    stamps, log, gyro, accel = make_series(7)
    stamps[17] = stamps[16]  # the sensor repeated a stamp; the receive times still increase
    path = write_bag(tmp_path, fmt, {"/imu0": imu_topic(stamps, log, gyro, accel)})
    with pytest.raises(DataError, match="duplicate") as err:
        read_rosbag(path)
    assert re.search(r"\brow 17\b", str(err.value)), str(err.value)
    assert "drop_duplicates=True" in str(err.value)

    data = read_rosbag(path, drop_duplicates=True)
    keep = np.delete(np.arange(N), 17)
    assert len(data) == N - 1
    np.testing.assert_array_equal(data.stamps_ns, stamps[keep])
    np.testing.assert_array_equal(data.gyro, gyro[keep])
    np.testing.assert_array_equal(data.accel, accel[keep])
    assert len(data.repairs) == 1
    assert "duplicate" in data.repairs[0] and re.search(r"\brow 17\b", data.repairs[0])
    # the receive times have no duplicate
    assert len(read_rosbag(path, stamp="log")) == N


@pytest.mark.parametrize("fmt", FORMATS)
def test_gyro_in_degrees(tmp_path, fmt):
    # a driver that publishes deg/s: ~100 °/s per axis
    stamps, log, gyro_deg, accel = make_series(8, gyro_scale=100.0)
    path = write_bag(tmp_path, fmt, {"/imu0": imu_topic(stamps, log, gyro_deg, accel)})
    with pytest.raises(DataError, match="deg/s"):
        read_rosbag(path)
    raw = read_rosbag(path, check_units=False)
    np.testing.assert_array_equal(raw.gyro, gyro_deg)


@pytest.mark.parametrize("kind", ["gyro", "accel"])
def test_unit_advice_works(tmp_path, kind):
    """The unit error's advice must be something read_rosbag accepts: the message says to
    pass ``gyro_unit='deg/s'`` / ``accel_unit='g'``, so read_rosbag must take that option and
    convert to SI (like read_csv and from_arrays do)."""
    if kind == "gyro":  # a driver publishing deg/s: ~100 °/s per axis
        stamps, log, gyro, accel = make_series(9, gyro_scale=100.0)
        option, pattern = {"gyro_unit": "deg/s"}, "deg/s"
    else:  # a driver publishing g
        stamps, log, gyro, accel = make_series(9)
        accel = accel / 9.80665
        option, pattern = {"accel_unit": "g"}, "in g"
    path = write_bag(tmp_path, "ros1", {"/imu0": imu_topic(stamps, log, gyro, accel)})
    with pytest.raises(DataError, match=pattern) as err:
        read_rosbag(path)
    ((name, value),) = option.items()
    assert f"{name}='{value}'" in str(err.value)  # the advice the user is given ...
    data = read_rosbag(path, **option)  # ... works
    np.testing.assert_array_equal(data.stamps_ns, stamps)
    if kind == "gyro":
        np.testing.assert_allclose(data.gyro, np.deg2rad(gyro), rtol=1e-15, atol=0)
        np.testing.assert_array_equal(data.accel, accel)
    else:
        np.testing.assert_array_equal(data.gyro, gyro)
        np.testing.assert_allclose(data.accel, accel * 9.80665, rtol=1e-15, atol=0)


@pytest.mark.parametrize("fmt", ["ros1", "sqlite3"])
def test_backwards_stamps_sort(tmp_path, fmt):
    stamps, log, gyro, accel = make_series(10)
    stamps[[20, 21]] = stamps[[21, 20]]  # header stamps out of order, receive order intact
    path = write_bag(tmp_path, fmt, {"/imu0": imu_topic(stamps, log, gyro, accel)})
    with pytest.raises(DataError, match=r"backwards.*\brow 21\b"):
        read_rosbag(path)
    data = read_rosbag(path, sort=True)
    order = np.argsort(stamps, kind="stable")
    np.testing.assert_array_equal(data.stamps_ns, stamps[order])
    np.testing.assert_array_equal(data.gyro, gyro[order])
    assert len(data.repairs) == 1 and "sorted" in data.repairs[0]


# --------------------------------------------------------------------------- not bags


def test_missing_path(tmp_path):
    for missing in (tmp_path / "nothing.bag", tmp_path / "nothing"):
        with pytest.raises(DataError, match="no such file"):
            read_rosbag(missing)


@pytest.mark.parametrize(
    "name, content",
    [
        ("notes.txt", b"timestamp,wx,wy,wz,ax,ay,az\n1,0,0,0,0,0,9.81\n"),
        ("garbage.bag", bytes(range(256)) * 8),
        ("garbage.db3", b"not sqlite at all" * 10),
        ("garbage.mcap", b"\x89MCAP0\r\n" + b"\x00" * 50),
    ],
)
def test_not_a_bag_file(tmp_path, name, content):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(DataError, match="not a readable ROS bag"):
        read_rosbag(path)


def test_folder_without_metadata(tmp_path):
    folder = tmp_path / "empty"
    folder.mkdir()
    with pytest.raises(DataError, match="not a readable ROS bag"):
        read_rosbag(folder)


@pytest.mark.parametrize("fmt", ["ros1", "sqlite3"])
def test_corrupt_message(tmp_path, fmt):
    """A truncated Imu message is a DataError naming the bag, not rosbags' own exception."""
    stamps, log, gyro, accel = make_series(11, n=10)
    name, msgs = imu_topic(stamps, log, gyro, accel)
    msgs[4] = (msgs[4][0], b"\x00\x01\x00\x00\x07")  # 5 bytes: far too short for an Imu
    path = write_bag(tmp_path, fmt, {"/imu0": (name, msgs)})
    with pytest.raises(DataError) as err:
        read_rosbag(path)
    assert path.name in str(err.value)
