"""jaximu.io.read_euroc reads each layout a EuRoC sequence comes in (the ASL folders, a flat
folder with the full-state groundtruth.csv, a flat folder with the pose-only
groundtruth_pose.txt), checked against a plain NumPy parse of the same text; a folder that is
no sequence and broken pose files are refused with the file and line named."""

import pathlib
import shutil

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from jaximu import io

MH03 = (
    pathlib.Path(__file__).resolve().parents[1] / "data" / "euroc_mh_03_medium"
)  # imu.csv + pose .txt
POSE = "groundtruth_pose.txt"


def plain_imu(path):
    """IMU stamps (int64 ns) and ``(N, 6)`` values with np.loadtxt."""
    stamps = np.loadtxt(path, delimiter=",", skiprows=1, usecols=0, dtype=np.int64)
    values = np.loadtxt(path, delimiter=",", skiprows=1, usecols=range(1, 7))
    return stamps, values


def plain_pose(path):
    """The pose file with np.loadtxt: exact ns stamps from the decimal text (integer
    arithmetic on the digits) and the ``(M, 7)`` values ``tx ty tz qx qy qz qw`` as stored."""
    text = np.loadtxt(path, skiprows=1, usecols=0, dtype=str)
    whole, frac = zip(*(s.split(".") for s in text))
    stamps = np.array([int(w) * 10**9 + int(f.ljust(9, "0")) for w, f in zip(whole, frac)])
    return stamps, np.loadtxt(path, skiprows=1, usecols=range(1, 8))


def lines_of(path):
    return path.read_text().splitlines()


def write_lines(path, lines):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


# --------------------------------------------------------------------------- the pose layout


def test_flat_pose_layout_against_a_plain_parse():
    data = io.read_euroc(MH03)
    stamps, values = plain_imu(MH03 / "imu.csv")
    np.testing.assert_array_equal(data.stamps_ns, stamps)
    np.testing.assert_array_equal(data.gyro, values[:, :3])
    np.testing.assert_array_equal(data.accel, values[:, 3:])
    gt_ns, pose = plain_pose(MH03 / POSE)
    gt = data.ground_truth
    assert len(gt) == 300 and gt.v is None and gt.b_g is None and gt.b_a is None
    np.testing.assert_array_equal(gt.p, pose[:, 0:3])
    np.testing.assert_array_equal(gt.q, pose[:, [6, 3, 4, 5]])  # x y z w → [w, x, y, z]
    # stamps exactly: seconds with 5 decimals, 10 µs resolution, off the IMU's ns grid
    assert gt_ns[0] == 1403637132888320000
    assert gt_ns[0] - stamps[50] == 1024  # the IMU sample before it is 1.024 µs earlier
    np.testing.assert_array_equal(gt.t, (gt_ns - stamps[0]) * 1e-9)
    assert str(MH03 / POSE) in data.source


def test_pose_quaternion_is_body_to_world():
    """On the ground before take-off the accelerometer reads R_WBᵀ [0, 0, g] (on average,
    within its bias and the rotors' vibration); the file's order read as [w, x, y, z], or the
    inverse rotation, miss it by more than g."""
    data = io.read_euroc(MH03)
    gt = data.ground_truth
    inside = np.flatnonzero((data.t >= gt.t[0]) & (data.t <= gt.t[-1]))[:100]
    q, _, _ = gt.interpolate(data.t[inside])
    expected = Rotation.from_quat(q[:, [1, 2, 3, 0]]).inv().apply([0.0, 0.0, 9.81])
    assert np.linalg.norm((data.accel[inside] - expected).mean(0)) < 0.5


def test_interpolation_at_imu_times_against_scipy():
    data = io.read_euroc(MH03)
    gt = data.ground_truth
    gt_ns, pose = plain_pose(MH03 / POSE)
    t_gt = (gt_ns - data.stamps_ns[0]) * 1e-9
    inside = (data.t >= t_gt[0]) & (data.t <= t_gt[-1])
    assert inside.sum() == 299  # the IMU samples on lines 481–779 of the full file
    t = data.t[inside]
    q, p, v = gt.interpolate(t)
    assert v is None
    ref = Slerp(t_gt, Rotation.from_quat(pose[:, 3:7]))(t)  # scipy reads x y z w as stored
    np.testing.assert_allclose(
        (Rotation.from_quat(q[:, [1, 2, 3, 0]]) * ref.inv()).magnitude(), 0, atol=1e-12
    )
    p_ref = np.stack([np.interp(t, t_gt, pose[:, j]) for j in range(3)], axis=1)
    np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-12)
    # no velocity in the file: central differences of the positions
    k = np.arange(1, 299)
    v_ref = (pose[k + 1, 0:3] - pose[k - 1, 0:3]) / (t_gt[k + 1] - t_gt[k - 1])[:, None]
    np.testing.assert_allclose(gt.velocity(t_gt[k]), v_ref, rtol=0, atol=1e-8)


def test_pose_file_in_asl_folder_explicit_path_and_imu_file(tmp_path):
    flat = io.read_euroc(MH03)
    mav0 = tmp_path / "MH_03_medium" / "mav0"
    (mav0 / "imu0").mkdir(parents=True)
    shutil.copy(MH03 / "imu.csv", mav0 / "imu0" / "data.csv")
    shutil.copy(MH03 / POSE, mav0 / POSE)
    for path in (
        tmp_path / "MH_03_medium",
        mav0,
        mav0 / "imu0" / "data.csv",  # ASL
        MH03 / "imu.csv",
    ):  # a flat folder's imu.csv: its ground truth beside it
        data = io.read_euroc(path)
        np.testing.assert_array_equal(data.stamps_ns, flat.stamps_ns)
        np.testing.assert_array_equal(data.ground_truth.q, flat.ground_truth.q)
        np.testing.assert_array_equal(data.ground_truth.t, flat.ground_truth.t)
    imu_only = tmp_path / "imu_only"
    imu_only.mkdir()
    shutil.copy(MH03 / "imu.csv", imu_only / "imu.csv")
    assert io.read_euroc(imu_only).ground_truth is None  # none there: not an error
    explicit = io.read_euroc(imu_only, groundtruth=MH03 / POSE)
    np.testing.assert_array_equal(explicit.ground_truth.p, flat.ground_truth.p)
    tabs = write_lines(
        tmp_path / "poses.tum",
        [ln.replace(" ", "\t") if i else ln for i, ln in enumerate(lines_of(MH03 / POSE))],
    )
    explicit = io.read_euroc(imu_only, groundtruth=tabs)  # tab separated: a TUM pose too
    np.testing.assert_array_equal(explicit.ground_truth.q, flat.ground_truth.q)
    assert io.read_euroc(MH03, groundtruth=False).ground_truth is None


def test_full_state_csv_of_the_same_poses_reads_the_same_and_comes_first(tmp_path):
    """The same poses written as EuRoC's CSV (ns stamps, [w, x, y, z]) give the same
    GroundTruth; in a folder with both files the full-state CSV is the one read."""
    shutil.copy(MH03 / "imu.csv", tmp_path / "imu.csv")
    shutil.copy(MH03 / POSE, tmp_path / POSE)
    gt_ns, pose = plain_pose(MH03 / POSE)
    rows = [
        f"{s}," + ",".join(repr(float(x)) for x in r[[0, 1, 2, 6, 3, 4, 5]])
        for s, r in zip(gt_ns, pose)
    ]
    write_lines(tmp_path / "groundtruth.csv", ["#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z", *rows])
    data = io.read_euroc(tmp_path)
    assert data.source.endswith("groundtruth.csv")
    flat = io.read_euroc(MH03).ground_truth
    for name in ("t", "p", "q"):
        np.testing.assert_array_equal(getattr(data.ground_truth, name), getattr(flat, name))


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "reader, gt_dir", [(io.read_euroc, "state_groundtruth_estimate0"), (io.read_tumvi, "mocap0")]
)
def test_a_folder_that_is_no_sequence(tmp_path, reader, gt_dir):
    (tmp_path / "notes.txt").write_text("not a sequence\n")
    (tmp_path / "nested" / "mav0").mkdir(parents=True)  # mav0 without imu0
    for path in (tmp_path, tmp_path / "nested"):
        with pytest.raises(io.DataError) as e:
            reader(path)
        msg = str(e.value)
        assert "\n" not in msg and msg.startswith(f"{path} is not a ")
        for expected in (
            "mav0/imu0/data.csv",
            f"mav0/{gt_dir}/data.csv",
            "imu.csv",
            "groundtruth.csv",
            POSE,
        ):
            assert expected in msg


ROW = "1403637132.90832 4.631110 -1.786677 0.577097 {} -0.776262 -0.072298 0.606412"  # line 6
GOOD = ROW.format("-0.156384")


def broken(tmp_path, text):
    """A flat folder whose pose file has line 6 replaced by ``text``."""
    shutil.copy(MH03 / "imu.csv", tmp_path / "imu.csv")
    lines = lines_of(MH03 / POSE)
    assert lines[5] == GOOD
    lines[5] = text
    return write_lines(tmp_path / POSE, lines)


@pytest.mark.parametrize(
    "text, message",
    [
        pytest.param(
            GOOD.rsplit(" ", 1)[0],
            r"groundtruth_pose.txt, line 6: a TUM pose has 8 "
            r"values .* got 7",
            id="7 columns",
        ),
        pytest.param(GOOD + " 0.1", r"groundtruth_pose.txt, line 6: .* got 9", id="9 columns"),
        pytest.param(
            GOOD.replace(" ", ","), r"groundtruth_pose.txt, line 6: .* got 1", id="commas"
        ),
        pytest.param(
            ROW.format("nan"),
            r"ground truth .*groundtruth_pose.txt: NaN or inf at "
            r"line 6",
            id="NaN value",
        ),
        pytest.param(
            GOOD.replace("1403637132.90832", "nan"),
            r"groundtruth_pose.txt, line 6: "
            r"timestamp 'nan' is not a finite number",
            id="NaN stamp",
        ),
        pytest.param(
            GOOD.replace(".90832", ".90332"),
            r"groundtruth_pose.txt: timestamps not "
            r"increasing at line 6",
            id="repeated stamp",
        ),  # = line 5's
        pytest.param(
            GOOD.replace(".90832", ".89832"),
            r"groundtruth_pose.txt: timestamps not "
            r"increasing at line 6",
            id="stamp going back",
        ),  # before line 5's
        pytest.param(
            GOOD.replace("1403637132.90832", "1403637132908320000"),
            r"groundtruth_pose.txt, line 6: timestamp '1403637132908320000' is beyond int64 "
            r"nanoseconds; this file's format stamps in s",
            id="stamp in ns",
        ),
        pytest.param(
            ROW.format("-1.156384"),
            r"groundtruth_pose.txt: the quaternion is not a "
            r"\[w, x, y, z\] unit quaternion at line 6: its norm is 1\.5\d*",
            id="non-unit quaternion",
        ),
    ],
)
def test_broken_pose_files_name_file_and_line(tmp_path, text, message):
    path = broken(tmp_path, text)
    with pytest.raises(io.DataError, match=message) as e:
        io.read_euroc(tmp_path)
    assert "\n" not in str(e.value)
    with pytest.raises(io.DataError, match=message):  # the same, named explicitly
        io.read_euroc(MH03, groundtruth=path)


def test_imu_stamps_in_seconds_name_the_layouts_unit_not_an_option_it_lacks(tmp_path):
    """An ``imu.csv`` stamped in seconds: the ASL layout's stamps are nanoseconds, and
    read_euroc has no ``time_unit`` (read_csv has): the message says so and offers no fix."""
    lines = lines_of(MH03 / "imu.csv")[:40]
    t, rest = lines[1].split(",", 1)
    lines[1] = f"{int(t) * 1e-9:.9f},{rest}"
    write_lines(tmp_path / "imu.csv", lines)
    with pytest.raises(io.DataError) as e:
        io.read_euroc(tmp_path, groundtruth=False)
    assert str(e.value).startswith(f"{tmp_path / 'imu.csv'}, line 2: timestamp '{lines[1][:20]}")
    assert "format stamps in ns" in str(e.value) and "read_csv" in str(e.value)
    assert e.value.fixes == ()
