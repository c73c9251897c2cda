"""jaximu.io: readers (real segments under tests/data and files the tests write), validation
with row numbers, each repair option, exports read back (plain parser and evo)."""

import dataclasses
import pathlib

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

import jaximu
from jaximu import io
from jaximu.state import NavState

DATA = pathlib.Path(__file__).resolve().parents[1] / "data"
EUROC = DATA / "euroc_v1_02_medium"
TUMVI = DATA / "tumvi_room4"


def plain_rows(path):
    """The file's data rows with a plain parser: int stamps and float values."""
    rows = [ln.split(",") for ln in path.read_text().splitlines() if ln and not ln.startswith("#")]
    return np.array([int(r[0]) for r in rows]), np.array([[float(x) for x in r[1:]] for r in rows])


# --------------------------------------------------------------------------- real segments


def test_euroc_segment_keeps_nanoseconds_and_ground_truth():
    data = io.read_euroc(EUROC)
    stamps, values = plain_rows(EUROC / "mav0/imu0/data.csv")
    assert data.stamps_ns.dtype == np.int64
    np.testing.assert_array_equal(data.stamps_ns, stamps)  # every nanosecond, exactly
    assert data.t0_ns == 1403715526907142912
    np.testing.assert_array_equal(np.round(data.t * 1e9).astype(np.int64) + data.t0_ns, stamps)
    np.testing.assert_array_equal(data.gyro, values[:, :3])
    np.testing.assert_array_equal(data.accel, values[:, 3:])
    g_stamps, g_values = plain_rows(EUROC / "mav0/state_groundtruth_estimate0/data.csv")
    gt = data.ground_truth
    assert abs(gt.t[0] - 256e-9) < 1e-15  # 256 ns after the first IMU stamp
    np.testing.assert_array_equal(gt.p, g_values[:, 0:3])
    np.testing.assert_array_equal(gt.q, g_values[:, 3:7])  # as stored, not normalised
    np.testing.assert_array_equal(gt.v, g_values[:, 7:10])
    np.testing.assert_array_equal(gt.b_a, g_values[:, 13:16])
    assert data.repairs == () and abs(data.rate_hz - 200) < 0.01
    # the imu0/data.csv path and the mav0 folder give the same
    assert len(io.read_euroc(EUROC / "mav0/imu0/data.csv")) == len(data)
    # the bundled flat excerpt (imu.csv + groundtruth.csv)
    assert (
        len(io.read_euroc(pathlib.Path(jaximu.__file__).parent / "data/euroc_v1_02_medium")) == 4002
    )


def test_tumvi_segment_pose_only_ground_truth_with_dropouts():
    data = io.read_tumvi(TUMVI)
    stamps, values = plain_rows(TUMVI / "mav0/imu0/data.csv")
    np.testing.assert_array_equal(data.stamps_ns, stamps)
    assert np.ptp(data.dt) > 1e-5  # TUM-VI's intervals vary (here 5.004–5.025 ms)
    gt = data.ground_truth
    assert gt.v is None and gt.b_g is None and len(gt) == 747
    # interpolation at the stamps returns the stored (normalised) poses
    q, p, v = gt.interpolate(gt.t[100:110])
    np.testing.assert_allclose(p, gt.p[100:110], atol=1e-12)
    qn = gt.q[100:110] / np.linalg.norm(gt.q[100:110], axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.sum(q * qn, 1)), 1, atol=1e-12)
    # between stamps: scipy's Slerp
    tq = 0.5 * (gt.t[200:210] + gt.t[201:211])
    ref = Slerp(gt.t[195:215], Rotation.from_quat(gt.q[195:215][:, [1, 2, 3, 0]]))(tq)
    q, _, _ = gt.interpolate(tq)
    np.testing.assert_allclose(
        (Rotation.from_quat(q[:, [1, 2, 3, 0]]) * ref.inv()).magnitude(), 0, atol=1e-12
    )
    # the 0.483 s mocap dropout is not bridged
    k = int(np.argmax(np.diff(gt.t)))
    assert abs(gt.t[k + 1] - gt.t[k] - 0.483) < 1e-3
    with pytest.raises(io.DataError, match="gap"):
        gt.interpolate([gt.t[k] + 0.2])
    # velocity from differences of the positions where there is none
    assert gt.velocity(gt.t[10:12]).shape == (2, 3)


def test_differenced_velocity_matches_euroc_velocity():
    gt = io.read_euroc(EUROC).ground_truth
    pose_only = dataclasses.replace(gt, v=None)
    t = gt.t[100:900:50]
    err = pose_only.velocity(t) - gt.interpolate(t)[2]
    assert np.abs(err).max() < 0.05  # EuRoC's 6-decimal positions over 2 × 5 ms


# --------------------------------------------------------------------------- CSV, arrays, NPZ


def write_csv(path, lines):
    path.write_text("\n".join(lines) + "\n")
    return path


def test_generic_csv_round_trip_with_names_and_units(tmp_path):
    rng = np.random.default_rng(0)
    n = 50
    ns = 1_600_000_000_123_456_789 + 5_000_000 * np.arange(n, dtype=np.int64)
    w = rng.normal(0, 0.5, (n, 3))
    a = rng.normal(0, 1, (n, 3)) + [0, 0, 9.81]
    lines = ["time_ms;ax_g;ay_g;az_g;gx_dps;gy_dps;gz_dps;temp"]
    for k in range(n):
        ms = f"{ns[k] // 10**6}.{ns[k] % 10**6:06d}"
        vals = np.r_[a[k] / io.STANDARD_GRAVITY, np.rad2deg(w[k])]
        lines.append(ms + ";" + ";".join(repr(float(x)) for x in vals) + ";25.0")
    path = write_csv(tmp_path / "imu.txt", lines)
    data = io.read_csv(
        path,
        time="time_ms",
        gyro=("gx_dps", "gy_dps", "gz_dps"),
        accel=("ax_g", "ay_g", "az_g"),
        time_unit="ms",
        gyro_unit="deg/s",
        accel_unit="g",
    )
    np.testing.assert_array_equal(data.stamps_ns, ns)  # exact from the decimal text
    np.testing.assert_allclose(data.gyro, w, rtol=1e-14)
    np.testing.assert_allclose(data.accel, a, rtol=1e-14)
    # by index, whitespace separated, seconds
    lines = [
        f"{ns[k] // 10**9}.{ns[k] % 10**9:09d} "
        + " ".join(repr(float(x)) for x in np.r_[w[k], a[k]])
        for k in range(n)
    ]
    data2 = io.read_csv(write_csv(tmp_path / "imu2.txt", lines))
    np.testing.assert_array_equal(data2.stamps_ns, ns)
    np.testing.assert_array_equal(data2.gyro, w)


def test_from_arrays_and_npz(tmp_path):
    rng = np.random.default_rng(1)
    ns = 1403715524907142912 + 5_000_000 * np.arange(20, dtype=np.int64)
    w, a = rng.normal(0, 0.1, (20, 3)), rng.normal(0, 0.1, (20, 3)) + [0, 0, 9.8]
    w_in, a_in, ns_in = w.copy(), a.copy(), ns.copy()
    data = io.from_arrays(ns, w, a, time_unit="ns")
    np.testing.assert_array_equal(data.stamps_ns, ns)
    data.gyro[0] = 99.0  # the container holds copies
    np.testing.assert_array_equal(w, w_in)
    np.testing.assert_array_equal(a, a_in)
    np.testing.assert_array_equal(ns, ns_in)
    np.savez(tmp_path / "rec.npz", t=ns, gyro=w, accel=a)
    back = io.read_npz(tmp_path / "rec.npz", time_unit="ns")
    np.testing.assert_array_equal(back.stamps_ns, ns)
    np.testing.assert_array_equal(back.accel, a)
    with pytest.raises(io.DataError, match="no array"):
        io.read_npz(tmp_path / "rec.npz", gyro="w")


# --------------------------------------------------------------------------- validation


def samples(n=40, rate=200.0, seed=2):
    rng = np.random.default_rng(seed)
    ns = (1_000_000_000 + np.arange(n) * (1e9 / rate)).astype(np.int64)
    return ns, rng.normal(0, 0.1, (n, 3)), rng.normal(0, 0.2, (n, 3)) + [0, 0, 9.81]


def euroc_csv(path, ns, w, a, raw=None):
    rows = [f"{s}," + ",".join(repr(float(x)) for x in np.r_[w[k], a[k]]) for k, s in enumerate(ns)]
    if raw:
        for k, text in raw.items():
            rows[k] = text
    return write_csv(path, ["#timestamp [ns],wx,wy,wz,ax,ay,az"] + rows)


def test_nonfinite_rows_named_and_dropped(tmp_path):
    ns, w, a = samples()
    w[7, 1] = np.nan
    a[20, 2] = np.inf
    path = euroc_csv(tmp_path / "data.csv", ns, w, a)
    with pytest.raises(io.DataError, match=r"NaN or inf values at line 9, line 22") as e:
        io.read_csv(path, time_unit="ns")
    assert "drop_nonfinite=True" in str(e.value)
    data = io.read_csv(path, time_unit="ns", drop_nonfinite=True)
    np.testing.assert_array_equal(data.stamps_ns, np.delete(ns, [7, 20]))
    assert data.repairs == ("dropped 2 sample(s) with NaN/inf values: line 9, line 22",)
    # arrays: row indices
    with pytest.raises(io.DataError, match=r"at row 7, row 20"):
        io.from_arrays(ns, w, a, time_unit="ns")


def test_backwards_stamps_named_and_sorted():
    ns, w, a = samples()
    order = np.arange(40)
    order[[10, 11]] = [11, 10]
    with pytest.raises(io.DataError, match=r"backwards at 1 place\(s\): row 11") as e:
        io.from_arrays(ns[order], w[order], a[order], time_unit="ns")
    assert "sort=True" in str(e.value)
    data = io.from_arrays(ns[order], w[order], a[order], time_unit="ns", sort=True)
    np.testing.assert_array_equal(data.stamps_ns, ns)
    np.testing.assert_array_equal(data.gyro, w)  # values travel with their stamps
    assert data.repairs == ("sorted by time: 2 sample(s) moved (first out of order at row 11)",)


def test_duplicates_named_and_dropped():
    ns, w, a = samples()
    ns2 = np.insert(ns, 16, ns[15])
    w2, a2 = np.insert(w, 16, w[15] + 1e-3, axis=0), np.insert(a, 16, a[15], axis=0)
    with pytest.raises(io.DataError, match=r"1 duplicate timestamp\(s\) at row 16"):
        io.from_arrays(ns2, w2, a2, time_unit="ns")
    data = io.from_arrays(ns2, w2, a2, time_unit="ns", drop_duplicates=True)
    np.testing.assert_array_equal(data.stamps_ns, ns)
    np.testing.assert_array_equal(data.gyro, w)  # the first of the two is kept
    assert data.repairs == (
        "dropped 1 sample(s) with a duplicate timestamp (0 identical to the kept one): row 16",
    )


def test_gaps_named_kept_and_split():
    ns, w, a = samples(60)
    ns = ns.copy()
    ns[30:] += 200_000_000  # a 0.205 s gap after row 29
    with pytest.raises(io.DataError, match=r"1 gap\(s\) longer than 0.025 s: 0.205 s after row 29"):
        io.from_arrays(ns, w, a, time_unit="ns")
    data = io.from_arrays(ns, w, a, time_unit="ns", allow_gaps=True)
    assert len(data) == 60 and "kept 1 gap(s)" in data.repairs[0]
    pieces = data.split_at_gaps()
    assert [len(p) for p in pieces] == [30, 30]
    np.testing.assert_array_equal(pieces[1].stamps_ns, ns[30:])
    assert "rows 30–59" in pieces[1].repairs[-1]
    # a larger max_gap accepts it
    assert len(io.from_arrays(ns, w, a, time_unit="ns", max_gap=0.3)) == 60


def test_units_that_look_wrong():
    ns, w, a = samples()
    with pytest.raises(io.DataError, match="deg/s"):
        io.from_arrays(ns, np.rad2deg(w) * 20, a, time_unit="ns")
    with pytest.raises(io.DataError, match="accel_unit='g'"):
        io.from_arrays(ns, w, a / io.STANDARD_GRAVITY, time_unit="ns")
    with pytest.raises(io.DataError, match="time unit"):  # ns stamps read as seconds
        io.from_arrays(ns.astype(float), w, a, time_unit="s")
    data = io.from_arrays(ns, w, a / io.STANDARD_GRAVITY, time_unit="ns", accel_unit="g")
    np.testing.assert_allclose(data.accel, a, rtol=1e-15)
    with pytest.raises(ValueError, match="unknown gyro_unit"):
        io.from_arrays(ns, w, a, gyro_unit="rpm")


def test_malformed_files(tmp_path):
    ns, w, a = samples()
    path = euroc_csv(tmp_path / "short.csv", ns, w, a, raw={5: "1000025000000,0.1,0.2"})
    with pytest.raises(io.DataError, match=r"line 7: expected at least 7 columns, got 3"):
        io.read_csv(path, time_unit="ns")
    path = euroc_csv(tmp_path / "text.csv", ns, w, a, raw={3: "1000015000000,0.1,abc,0,0,0,9.8"})
    with pytest.raises(io.DataError, match=r"line 5: 'abc' is not a number"):
        io.read_csv(path, time_unit="ns")
    with pytest.raises(io.DataError, match="no such file"):
        io.read_csv(tmp_path / "missing.csv")
    with pytest.raises(io.DataError, match="no column named 'gyro_x'"):
        io.read_csv(path, time_unit="ns", gyro=("gyro_x", "wy", "wz"))


# --------------------------------------------------------------------------- exports


def trajectory(n=30, seed=3):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return NavState(
        q=q,
        p=rng.normal(0, 5, (n, 3)),
        v=rng.normal(size=(n, 3)),
        b_g=rng.normal(0, 1e-3, (n, 3)),
        b_a=rng.normal(0, 1e-2, (n, 3)),
    )


def test_tum_export_read_back(tmp_path):
    states = trajectory()
    t = 0.005 * np.arange(30)
    t0 = 1403715524907142912
    io.write_tum(tmp_path / "traj.tum", t, states, t0_ns=t0)
    stamps, p, q = io.read_tum(tmp_path / "traj.tum")
    np.testing.assert_array_equal(stamps, t0 + 5_000_000 * np.arange(30))  # exact epoch ns
    np.testing.assert_allclose(p, states.p, atol=1e-9)
    np.testing.assert_allclose(q, states.q, atol=1e-9)
    first = (tmp_path / "traj.tum").read_text().splitlines()[1].split()
    assert first[0] == "1403715524.907142912" and len(first) == 8
    assert float(first[7]) == pytest.approx(states.q[0, 0], abs=1e-9)  # qw last in the file


def test_tum_export_read_by_evo(tmp_path):
    file_interface = pytest.importorskip("evo.tools.file_interface")
    states = trajectory()
    t = 0.01 * np.arange(30)
    io.write_tum(tmp_path / "traj.tum", t, states, t0_ns=1_520_531_164_173_162_567)
    traj = file_interface.read_tum_trajectory_file(str(tmp_path / "traj.tum"))
    np.testing.assert_allclose(traj.positions_xyz, states.p, atol=1e-9)
    np.testing.assert_allclose(traj.orientations_quat_wxyz, states.q, atol=1e-9)  # evo: wxyz
    np.testing.assert_allclose(traj.timestamps, 1_520_531_164.173162567 + t, rtol=0, atol=1e-6)


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_states_with_covariances_round_trip(tmp_path, suffix):
    states = trajectory(12)
    rng = np.random.default_rng(4)
    L = rng.normal(size=(12, 15, 15))
    cov = L @ np.swapaxes(L, 1, 2)
    path = tmp_path / f"states{suffix}"
    io.write_states(path, 0.01 * np.arange(12), states, cov, t0_ns=77)
    stamps, back, cov_back = io.read_states(path)
    np.testing.assert_array_equal(stamps, 77 + 10_000_000 * np.arange(12))
    for name in ("q", "p", "v", "b_g", "b_a"):
        np.testing.assert_array_equal(getattr(back, name), getattr(states, name))
    np.testing.assert_array_equal(cov_back, cov)
    if suffix == ".csv":
        header = path.read_text().splitlines()[0].split(",")
        assert header[:4] == ["stamp_ns", "t", "q_w", "q_x"] and "sigma_theta_x" in header


# --------------------------------------------------------------------------- initial state, errors


def test_gravity_alignment_against_scipy():
    rng = np.random.default_rng(5)
    for _ in range(20):
        f = rng.normal(size=3)
        f[2] = abs(f[2]) + 0.2  # not upside down
        q = io.gravity_alignment(9.81 * f / np.linalg.norm(f))
        R = Rotation.from_quat(q[[1, 2, 3, 0]])
        np.testing.assert_allclose(R.apply(f / np.linalg.norm(f)), [0, 0, 1], atol=1e-12)
        assert abs(R.as_euler("ZYX")[0]) < 1e-12  # yaw 0


def test_initial_state_and_errors_against_known_perturbations():
    data = io.read_euroc(EUROC)
    gt = data.ground_truth
    state, how = io.initial_state(data, from_groundtruth=True)
    assert "biases" in how
    np.testing.assert_allclose(state.b_g, gt.b_g[0])
    still, how = io.initial_state(data, still_seconds=1.0, bias=np.r_[[0.0] * 3, gt.b_a[0]])
    assert "gravity alignment" in how and "biases given" in how
    np.testing.assert_array_equal(still.p, 0)
    # the aligned tilt agrees with the ground truth's to the accuracy of a still average
    tilt = lambda q: Rotation.from_quat(q[[1, 2, 3, 0]]).inv().apply([0, 0, 1])  # noqa: E731
    assert np.degrees(np.arccos(np.clip(tilt(still.q) @ tilt(state.q), -1, 1))) < 1.0
    # errors: the truth itself, shifted by 1 cm and rotated by a known body-frame rotation
    dtheta = np.array([0.01, -0.02, 0.005])
    R_hat = Rotation.from_quat(gt.q[:, [1, 2, 3, 0]]) * Rotation.from_rotvec(dtheta)
    est = NavState(
        q=R_hat.as_quat()[:, [3, 0, 1, 2]], p=gt.p + [0.01, 0, 0], v=gt.v, b_g=gt.b_g, b_a=gt.b_a
    )
    err = io.trajectory_errors(gt.t, est, gt)
    np.testing.assert_allclose(err.position, np.tile([0.01, 0, 0], (len(gt), 1)), atol=1e-12)
    np.testing.assert_allclose(err.rotation, np.tile(dtheta, (len(gt), 1)), atol=1e-6)
    np.testing.assert_allclose(err.velocity, 0, atol=1e-12)
    pos, vel, att = err.at(1.0)
    assert pos == pytest.approx(0.01) and att == pytest.approx(
        np.degrees(np.linalg.norm(dtheta)), rel=1e-4
    )


# --------------------------------------------------------------------------- properties

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

_values = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64), st.floats(-20, 20))


@settings(
    max_examples=300,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow],
)
@given(
    n=st.integers(0, 12),
    data=st.data(),
    t_dtype=st.sampled_from([np.float64, np.float32, np.int64]),
    repair=st.booleans(),
)
def test_from_arrays_returns_clean_data_or_a_data_error(n, data, t_dtype, repair):
    """Random lengths (0 included), NaN/inf anywhere, unsorted and repeated times, huge
    steps: either a DataError/ValueError, or an ImuData with strictly increasing stamps,
    finite samples and at least two of them."""
    t = data.draw(
        hnp.arrays(
            t_dtype,
            n,
            elements=(
                st.integers(0, 10**6) if t_dtype == np.int64 else st.floats(-1e30, 1e30, width=64)
            ),
        )
    )
    gyro = data.draw(hnp.arrays(np.float64, (n, 3), elements=_values))
    accel = data.draw(hnp.arrays(np.float64, (n, 3), elements=_values))
    kw = (
        dict(
            sort=True, drop_duplicates=True, drop_nonfinite=True, allow_gaps=True, check_units=False
        )
        if repair
        else {}
    )
    try:
        out = io.from_arrays(t, gyro, accel, time_unit="ms", **kw)
    except ValueError as e:  # DataError is a ValueError
        assert str(e)
        return
    assert len(out) >= 2 and np.all(np.diff(out.stamps_ns) > 0)
    assert np.isfinite(out.gyro).all() and np.isfinite(out.accel).all()
    assert np.all(np.diff(out.t) > 0) and out.t[0] == 0


def test_stamps_float64_seconds_cannot_separate_are_an_error():
    """Found by the property test: ns stamps 4 years apart at both ends of 10 ns."""
    t = np.array([0.0, -1e-5, -1.35286059e11])  # ms
    zeros = np.zeros((3, 3))
    with pytest.raises(io.DataError, match="equal in float64 seconds"):
        io.from_arrays(
            t, zeros, zeros, time_unit="ms", sort=True, allow_gaps=True, check_units=False
        )


def test_header_detection_never_drops_data(tmp_path):
    ns, w, a = samples(10)
    body = [f"{s}," + ",".join(repr(float(x)) for x in np.r_[w[k], a[k]]) for k, s in enumerate(ns)]
    # headerless, with a text status column: the first row is data, not a header
    path = write_csv(tmp_path / "status.csv", [r + ",ok" for r in body])
    data = io.read_csv(path, time_unit="ns")
    np.testing.assert_array_equal(data.stamps_ns, ns)
    with pytest.raises(io.DataError, match=r"line 1: 'ok' is not a number"):
        io.read_csv(path, time_unit="ns", gyro=(7, 2, 3))
    # a byte-order mark and a free-text comment above the ASL-style header
    text = "\ufeff# recorded by foo, units SI\n#t,wx,wy,wz,ax,ay,az\n" + "\n".join(body) + "\n"
    (tmp_path / "bom.csv").write_text(text, encoding="utf-8")
    data = io.read_csv(
        tmp_path / "bom.csv",
        time="t",
        gyro=("wx", "wy", "wz"),
        accel=("ax", "ay", "az"),
        time_unit="ns",
    )
    np.testing.assert_array_equal(data.gyro, w)
    # fractional nanoseconds in an ASL file: the file is in another unit
    with pytest.raises(io.DataError, match="not a whole number of nanoseconds"):
        io.read_csv(write_csv(tmp_path / "s.csv", ["1.5,0,0,0,0,0,9.8"] * 2), time_unit="ns")
