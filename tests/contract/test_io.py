"""The input contract of ``jaximu.io`` (numpy only): the writers and ``trajectory_errors``
refuse what they would write or compare wrong (times given as stamps, NaN, a ``t0_ns`` that
is not an integer, negative variances, a non-unit ``q``), ground truth of one row, readers'
options that are not bools, text and complex arrays, and the readers' helpers name their
arguments.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from _shared import DATA

from jaximu import NavState, io
from jaximu.errors import InputError

EUROC = DATA / "euroc_v1_02_medium"
N = 400
T = np.arange(N) * 0.005
G = np.zeros((N, 3))
A = G + [0.0, 0.0, 9.81]


def states(n=40, scale=1.0):
    q = np.tile([scale, 0.0, 0.0, 0.0], (n, 1))
    z = np.zeros((n, 3))
    return NavState(q, z, z, z, z)


def gt50():
    return io.GroundTruth(
        t=np.arange(50) * 0.01, q=np.tile([1.0, 0, 0, 0], (50, 1)), p=np.zeros((50, 3))
    )


T40 = np.arange(40) * 0.01
EYE = np.broadcast_to(np.eye(15), (40, 15, 15))


# --------------------------------------------------------------------------- writers


@pytest.mark.parametrize("writer", ["tum", "csv", "npz"])
def test_writers_refuse_stamps_given_as_t(tmp_path, writer):
    """``data.stamps_ns`` passed as ``t`` wrote -9223372036.854775808 for every line."""
    t = np.array([1_400_000_000_000_000_000, 1_400_000_000_005_000_000])
    path = tmp_path / f"x.{writer}"
    with pytest.raises(
        ValueError,
        match=r"t\[0\] = 1\.4e\+18 s is beyond int64 nanoseconds.*"
        r"pass data\.t, not stamps_ns",
    ):
        if writer == "tum":
            io.write_tum(path, t, states(2))
        else:
            io.write_states(path, t, states(2))
    assert not path.exists()


def test_writers_refuse_nan_times_and_states(tmp_path):
    with pytest.raises(ValueError, match=r"^t contains non-finite"):
        io.write_tum(
            tmp_path / "x.tum", np.array([0.0, np.nan]), states(2), t0_ns=1_400_000_000_000_000_000
        )
    s = states(2)
    with pytest.raises(ValueError, match=r"^states\.p contains non-finite"):
        io.write_states(
            tmp_path / "x.csv", np.array([0.0, 1.0]), NavState(s.q, s.p + np.nan, s.v, s.b_g, s.b_a)
        )
    with pytest.raises(ValueError, match=r"^states\.q contains non-finite"):
        io.write_tum(
            tmp_path / "x.tum", np.array([0.0, 1.0]), NavState(s.q * np.nan, s.p, s.v, s.b_g, s.b_a)
        )


@pytest.mark.parametrize("t0", ["123", 1.5, 1.7e18 + 0.5, True, None])
def test_writers_refuse_a_t0_ns_that_is_not_an_integer(tmp_path, t0):
    """``"123"`` was parsed, ``1.5`` truncated to 1 ns."""
    with pytest.raises(ValueError, match="t0_ns must be an integer number of nanoseconds"):
        io.write_tum(tmp_path / "x.tum", np.array([0.0, 1.0]), states(2), t0_ns=t0)
    io.write_tum(tmp_path / "x.tum", np.array([0.0, 1.0]), states(2), t0_ns=np.int64(7))
    assert io.read_tum(tmp_path / "x.tum")[0].tolist() == [7, 1_000_000_007]
    # a 0-d integer array (np.load(...)["t0_ns"]) is an integer too
    io.write_tum(tmp_path / "x.tum", np.array([0.0, 1.0]), states(2), t0_ns=np.array(9))
    assert io.read_tum(tmp_path / "x.tum")[0].tolist() == [9, 1_000_000_009]


def test_write_tum_refuses_a_column_of_times(tmp_path):
    with pytest.raises(ValueError, match=r"t must have shape \(40,\)"):
        io.write_tum(tmp_path / "x.tum", T40[:, None], states())


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_write_states_refuses_negative_or_nonfinite_covariances(tmp_path, suffix):
    """Negative variances were written as σ = 0; NaN covariances were written."""
    with pytest.raises(ValueError, match=r"cov\[0, 0, 0\] = -1 is a negative variance"):
        io.write_states(tmp_path / f"s{suffix}", T40, states(), cov=-EYE)
    with pytest.raises(ValueError, match=r"^cov contains non-finite"):
        io.write_states(tmp_path / f"s{suffix}", T40, states(), cov=np.full((40, 15, 15), np.nan))
    # rounding below zero, relative to the matrix's scale, passes (σ 0)
    cov = EYE * 1e-6
    cov = cov.copy()
    cov[:, 5, 5] = -1e-14
    io.write_states(tmp_path / f"s{suffix}", T40, states(), cov=cov)


def test_write_states_full_covariance_is_a_bool(tmp_path):
    """``full_covariance="no"`` wrote the full P."""
    with pytest.raises(InputError, match="full_covariance=False"):
        io.write_states(tmp_path / "s.csv", T40, states(), cov=EYE, full_covariance="no")


# --------------------------------------------------------------------------- trajectory_errors


def test_trajectory_errors_refuses_negative_or_nonfinite_cov():
    with pytest.raises(ValueError, match="negative variance"):
        io.trajectory_errors(T40, states(), gt50(), cov=-np.ones((40, 15, 15)))
    with pytest.raises(ValueError, match="^cov contains non-finite"):
        io.trajectory_errors(T40, states(), gt50(), cov=np.full((40, 15, 15), np.nan))
    with pytest.raises(ValueError, match=r"cov must have shape \(40, 15, 15\)"):
        io.trajectory_errors(T40, states(), gt50(), cov=np.zeros((40, 9, 9)))


def test_trajectory_errors_does_not_normalise_q():
    """q = 2·identity gave rotation error 0."""
    with pytest.raises(
        ValueError,
        match=r"states\.q is not a unit quaternion at row 0: its "
        r"norm is 2 .*does not normalise",
    ):
        io.trajectory_errors(T40, states(scale=2.0), gt50())
    io.trajectory_errors(T40, states(scale=1 + 1.5e-4), gt50())  # rounding, as in EuRoC


def test_trajectory_errors_names_t():
    with pytest.raises(ValueError, match=r"t must have shape \(40,\).*got \(30,\)"):
        io.trajectory_errors(T40[:30], states(), gt50())
    with pytest.raises(ValueError, match="t must be increasing"):
        io.trajectory_errors(T40[::-1].copy(), states(), gt50())
    with pytest.raises(ValueError, match="^t contains non-finite"):
        io.trajectory_errors(np.r_[T40[:-1], np.nan], states(), gt50())


# --------------------------------------------------------------------------- ground truth


def test_ground_truth_with_one_row_is_refused():
    with pytest.raises(io.DataError, match="1 row.*at least 2"):
        io.GroundTruth(t=np.zeros(1), q=np.array([[1.0, 0, 0, 0]]), p=np.zeros((1, 3)))
    with pytest.raises(ValueError, match=r"GroundTruth\.q must have shape \(50, 4\)"):
        io.GroundTruth(
            t=np.arange(50) * 0.01, q=np.tile([1.0, 0, 0, 0], (10, 1)), p=np.zeros((50, 3))
        )


def one_row_euroc(tmp_path):
    """The bundled EuRoC excerpt (flat layout) with one ground-truth row."""
    d = tmp_path / "eu"
    shutil.copytree(EUROC, d)
    gt = d / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = gt.read_text().splitlines()
    gt.write_text("\n".join(lines[:1] + lines[400:401]) + "\n")
    return d, gt


def test_reader_refuses_a_one_row_ground_truth_naming_the_file(tmp_path):
    d, gt = one_row_euroc(tmp_path)
    with pytest.raises(io.DataError, match=f"{gt}.*1 row.*at least 2"):
        io.read_euroc(d)


def test_interpolate_refuses_nan_times_and_bad_max_gap():
    gt = gt50()
    with pytest.raises(ValueError, match="^t contains non-finite"):
        gt.interpolate([np.nan])
    for bad in (np.nan, -1.0, "0.1", True):
        with pytest.raises(ValueError, match="^max_gap must be a"):
            gt.interpolate([0.005], max_gap=bad)
    gt.interpolate([0.005], max_gap=np.inf)  # no limit


@pytest.mark.parametrize("bad", [np.nan, -1.0, "0.1"])
def test_max_gap_of_the_readers_and_gaps(bad):
    with pytest.raises(ValueError, match="^max_gap must be a"):
        io.from_arrays(T, G, A, max_gap=bad)
    with pytest.raises(ValueError, match="^max_gap must be a"):
        io.from_arrays(T, G, A).gaps(max_gap=bad)


# --------------------------------------------------------------------------- bool options


@pytest.mark.parametrize(
    "option", ["sort", "drop_duplicates", "drop_nonfinite", "allow_gaps", "check_units"]
)
@pytest.mark.parametrize("value", ["no", 1, None])
def test_reader_options_are_bools(option, value):
    """``sort="no"`` sorted the samples."""
    with pytest.raises(ValueError, match=f"^{option} must be True or False"):
        io.from_arrays(T[::-1].copy(), G, A, **{option: value})


def test_initial_state_from_groundtruth_is_a_bool():
    with pytest.raises(InputError, match="from_groundtruth=False"):
        io.initial_state(io.from_arrays(T, G, A), from_groundtruth="no")


def test_initial_state_says_when_the_recording_is_shorter_than_still_seconds():
    _, how = io.initial_state(io.from_arrays(T, G, A), still_seconds=1e9)
    assert "the whole recording" in how and "1e+09" in how, how


# -------------------------------------------------------------------------- text and complex arrays


def test_from_arrays_refuses_text():
    """Text arrays were parsed (``t``) or raised a UFuncTypeError (gyro)."""
    with pytest.raises(ValueError, match="^t must be an array of numbers"):
        io.from_arrays(T.astype(str), G, A)
    with pytest.raises(ValueError, match="^gyro must be an array of numbers"):
        io.from_arrays(T, G.astype(str), A)


def test_read_npz_refuses_a_text_time_array(tmp_path):
    np.savez(tmp_path / "x.npz", t=T.astype(str), gyro=G, accel=A)
    with pytest.raises(ValueError, match="^t must be an array of numbers"):
        io.read_npz(tmp_path / "x.npz")


def test_window_and_select_name_their_arguments():
    data = io.from_arrays(T, G, A)
    with pytest.raises(ValueError, match="^start must be a number of seconds"):
        data.window(start="0.5")
    with pytest.raises(ValueError, match="^duration must be a positive"):
        data.window(0.0, -1.0)
    with pytest.raises(ValueError, match=r"boolean mask must have shape \(400,\)"):
        data.select(np.ones(3, bool))
    with pytest.raises(ValueError, match="^index must be a slice, integer indices"):
        data.select([0.5, 1.5])
    with pytest.raises(ValueError, match="outside the 400 samples"):
        data.select([0, 1000])
    assert len(data.select(np.arange(N) < 10)) == 10
    with pytest.raises(io.DataError, match=r"the window \[5 s, the end\]"):
        data.window(5.0)


def test_csv_reader_refuses_digit_separators_and_negative_columns(tmp_path):
    rows = [f"{k * 5_000_000},0,0,0,0,0,9.81" for k in range(50)]
    path = tmp_path / "x.csv"
    path.write_text("\n".join(rows[:10] + ["50000000,1_0,0,0,0,0,9.81"] + rows[11:]) + "\n")
    with pytest.raises(io.DataError, match="line 11: '1_0' is not a number"):
        io.read_csv(path, time_unit="ns")
    path.write_text("\n".join(rows[:10] + ["5_0000000,0,0,0,0,0,9.81"] + rows[11:]) + "\n")
    with pytest.raises(io.DataError, match="line 11: timestamp '5_0000000' is not a finite"):
        io.read_csv(path, time_unit="ns")
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(ValueError, match="column indices count from 0.*got -1"):
        io.read_csv(path, time_unit="ns", accel=(4, 5, -1))


@pytest.mark.parametrize("which", ["t", "gyro", "accel"])
def test_from_arrays_refuses_complex(which):
    """The imaginary part was dropped with only a ComplexWarning."""
    arrays = {"t": T, "gyro": G, "accel": A}
    arrays[which] = arrays[which] + 0j
    with pytest.raises(ValueError, match=f"^{which} must be real, got a complex value"):
        io.from_arrays(**arrays)
