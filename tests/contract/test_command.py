"""The command's contract: bad input gets a one-line error that names the user's flag and
says the fix, before the work; the errors that carry their repair as data render as the
command's flags; nothing the user gave is altered or written wrong without a word.

The command runs in-process (``jaximu.cli.main``), so the errors, which are all raised
before any computation, cost no JAX start-up; the expected texts are the flags a user
types.
"""

from __future__ import annotations

import os
import pathlib
import re
import shutil
import subprocess
import sys
import warnings

import numpy as np
import pytest
from _shared import DATA, REPO

from jaximu import allan, cli, io
from jaximu.errors import Fix, InputError

EUROC_IMU = DATA / "euroc_v1_02_medium" / "mav0" / "imu0" / "data.csv"


def main(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def error_line(capsys, *argv):
    """Run the command; it must fail with exit 2 and one ``error:`` line; return that line
    and stdout."""
    code, out, err = main(capsys, *argv)
    assert code == 2, (out, err)
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    return lines[0], out


EUROC = DATA / "euroc_v1_02_medium"
N = 400
T = np.arange(N) * 0.005
G = np.zeros((N, 3))
A = G + [0.0, 0.0, 9.81]


def run(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_line_error(capsys, *argv):
    code, out, err = run(capsys, *argv)
    assert code == 2, (out, err)
    assert "Traceback" not in err and "Warning" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "error:" in lines[0], err
    return lines[0], out


def euroc_copy(tmp_path, gt_rows=None, scale_gyro=1.0, scale_accel=1.0):
    scale_gyro, scale_accel = float(scale_gyro), float(scale_accel)
    """The bundled EuRoC excerpt (5 s, ground truth on the IMU clock), with the ground-truth
    data rows ``gt_rows`` kept (a slice or index array) and the IMU columns scaled."""
    d = tmp_path / "eu"
    shutil.copytree(EUROC, d)
    if gt_rows is not None:
        gt = d / "mav0" / "state_groundtruth_estimate0" / "data.csv"
        lines = gt.read_text().splitlines()
        rows = np.asarray(lines[1:], object)[gt_rows]
        gt.write_text("\n".join([lines[0], *rows]) + "\n")
    if scale_gyro != 1.0 or scale_accel != 1.0:
        imu = d / "mav0" / "imu0" / "data.csv"
        lines = imu.read_text().splitlines()
        out = [lines[0]]
        for ln in lines[1:]:
            f = ln.split(",")
            out.append(
                ",".join(
                    [f[0]]
                    + [repr(float(x) * scale_gyro) for x in f[1:4]]
                    + [repr(float(x) * scale_accel) for x in f[4:7]]
                )
            )
        imu.write_text("\n".join(out) + "\n")
    return d


# --------------------------------------------------------------------------- demo


def test_demo_shorter_than_the_first_mark_still_reports(capsys):
    """``--seconds 0.5`` used to end in an IndexError traceback."""
    code, out, err = main(capsys, "demo", "--seconds", "0.5", "--no-plot", "--no-progress")
    assert code == 0, err
    assert "Traceback" not in err
    assert re.search(r"position drift \d+\.\d+ m after 0\.5 s", out), out


def test_demo_longer_than_the_excerpt_is_refused(capsys):
    line, out = error_line(capsys, "demo", "--seconds", "100", "--no-plot")
    assert "--seconds 100" in line and "≤ 20" in line, line
    assert out == ""  # nothing ran


def test_demo_plot_into_a_missing_folder_fails_before_the_work(capsys, tmp_path):
    line, out = error_line(
        capsys, "demo", "--seconds", "1", "--plot", tmp_path / "missing" / "demo.png"
    )
    assert "--plot" in line and "does not exist" in line, line
    assert out == ""


def test_outputs_naming_a_folder_fail_before_the_work(capsys, tmp_path):
    line, out = error_line(capsys, "propagate", DATA / "tumvi_room4", "--out", tmp_path)
    assert f"--out {tmp_path}" in line and "is a folder" in line, line
    assert "read" not in out
    line, out = error_line(capsys, "demo", "--plot", tmp_path)
    assert "--plot" in line and "is a folder" in line, line


# --------------------------------------------------------------------------- readers


def test_csv_with_a_nanosecond_header_is_read_in_nanoseconds(tmp_path):
    """A bare EuRoC ``imu0/data.csv`` under another name: its header says ``#timestamp [ns]``."""
    copy = tmp_path / "recording.csv"
    shutil.copy(EUROC_IMU, copy)
    data = io.read_csv(copy)
    ref = io.read_euroc(DATA / "euroc_v1_02_medium")
    assert len(data) == len(ref)
    np.testing.assert_array_equal(data.stamps_ns, ref.stamps_ns)
    # a unit given that contradicts the header is an error naming both, not a guess
    with pytest.raises(io.DataError, match=r"header .*\[ns\].*time_unit='s'") as e:
        io.read_csv(copy, time_unit="s")
    assert Fix("time_unit", "ns") in e.value.fixes


def test_cli_reads_the_nanosecond_header(capsys, tmp_path):
    copy = tmp_path / "recording.csv"
    shutil.copy(EUROC_IMU, copy)
    code, out, err = main(capsys, "allan", copy, "--no-unit-check")
    assert code == 0, err
    assert "at 200.0 Hz" in out, out


def static_recording(path, gyro_scale=1.0, seconds=60.0, rate=200.0, seed=0):
    """A still IMU with white noise of EuRoC's densities (gyro 1.7e-4 rad/s/√Hz, accel 2e-3
    m/s²/√Hz), gyro written in rad/s × ``gyro_scale``."""
    rng = np.random.default_rng(seed)
    n = int(seconds * rate)
    t = np.arange(n) / rate
    gyro = rng.normal(0, 1.7e-4 * np.sqrt(rate), (n, 3)) + 2e-3
    accel = rng.normal(0, 2e-3 * np.sqrt(rate), (n, 3)) + [0.0, 0.0, 9.81]
    np.savetxt(path, np.column_stack([t, gyro * gyro_scale, accel]), delimiter=",", fmt="%.9g")
    return path


def test_allan_of_a_static_gyro_in_deg_per_s_is_refused(capsys, tmp_path):
    path = static_recording(tmp_path / "still_deg.csv", gyro_scale=np.rad2deg(1.0))
    line, _ = error_line(capsys, "allan", path)
    assert "--gyro-unit deg/s" in line, line
    code, out, err = main(capsys, "allan", path, "--gyro-unit", "deg/s")
    assert code == 0, err
    white = float(re.search(r"gyroscope_noise_density: \[([\d.e-]+)", out).group(1))
    assert abs(white / 1.7e-4 - 1) < 0.2, out


def test_allan_of_a_static_gyro_in_rad_per_s_is_accepted(capsys, tmp_path):
    code, out, err = main(capsys, "allan", static_recording(tmp_path / "still.csv"))
    assert code == 0, err
    white = float(re.search(r"gyroscope_noise_density: \[([\d.e-]+)", out).group(1))
    assert abs(white / 1.7e-4 - 1) < 0.2, out


def test_cli_one_row_ground_truth_is_one_line(capsys, tmp_path):
    """Was a traceback (IndexError in interpolate) with exit 1."""
    d = euroc_copy(tmp_path, gt_rows=slice(400, 401))
    line, _ = one_line_error(capsys, "propagate", d, "--init-from-groundtruth", "--no-progress")
    assert "1 row(s); at least 2" in line and "state_groundtruth_estimate0" in line, line


def test_cli_window_before_the_ground_truth_says_where_it_starts(capsys, tmp_path):
    """Said 'the window [0.9949900640000001, inf] s holds fewer than 2 samples'."""
    d = euroc_copy(tmp_path, gt_rows=slice(200, None))
    line, _ = one_line_error(
        capsys, "propagate", d, "--init-from-groundtruth", "--duration", "0.5", "--no-progress"
    )
    assert "the ground truth starts at 1.000 s" in line and "--start ≥ 1.000" in line, line
    assert "inf" not in line
    line, _ = one_line_error(capsys, "calibrate", d, "--duration", "0.5")
    assert "the ground truth starts at 1.000 s" in line, line


def test_cli_unit_advice_on_an_asl_folder_can_be_followed(capsys, tmp_path):
    """The advice '--gyro-unit deg/s' was then refused for EuRoC folders."""
    d = euroc_copy(tmp_path, scale_gyro=np.rad2deg(1.0) * 40, scale_accel=1 / 9.80665)
    line, _ = one_line_error(capsys, "preintegrate", d, "--window", "1000")
    assert "--gyro-unit deg/s" in line, line
    line, out = one_line_error(
        capsys, "preintegrate", d, "--gyro-unit", "deg/s", "--accel-unit", "g", "--window", "1000"
    )
    assert out.startswith("read 1002 samples") and "shorter than one window" in line, (out, line)
    data = io.read_euroc(d, gyro_unit="deg/s", accel_unit="g")
    ref = io.read_euroc(EUROC)
    np.testing.assert_allclose(data.gyro, ref.gyro * 40, rtol=1e-12)
    np.testing.assert_allclose(data.accel, ref.accel, rtol=1e-12)


def test_cli_preintegrate_leaves_windows_in_a_ground_truth_gap_out(capsys, tmp_path):
    """Wrote its output, then exited 2 with 'ground truth has a 1.005 s gap'."""
    keep = np.r_[0:400, 600:1001]
    d = euroc_copy(tmp_path, gt_rows=keep)
    out_file = tmp_path / "p.npz"
    code, out, err = run(capsys, "preintegrate", d, "--window", "0.5", "--out", out_file)
    assert code == 0, err
    assert "Traceback" not in err and "error" not in err, err
    assert out_file.is_file()
    assert "window(s) with an end in a ground-truth gap left out" in out, out


def test_not_an_npz_file_gives_no_pickle_advice(capsys, tmp_path):
    """numpy's text advised allow_pickle= / pickle.load() (unsafe, and not the fix)."""
    path = tmp_path / "x.npz"
    path.write_text("t,a\n1,2\n")
    line, _ = one_line_error(capsys, "propagate", path)
    assert "is not a NumPy .npz file" in line and "pickle" not in line, line


def test_allan_of_a_constant_signal_names_the_file(capsys, tmp_path):
    """Said 'adev must be positive ... at index [0, 0]' (an internal, not the file)."""
    path = tmp_path / "c.npz"
    np.savez(
        path,
        t=np.arange(2000) * 0.005,
        gyro=np.zeros((2000, 3)),
        accel=np.zeros((2000, 3)) + [0, 0, 9.81],
    )
    line, _ = one_line_error(capsys, "allan", path)
    assert f"gyro's x axis is constant in {path}" in line, line


def test_topic_for_a_file_that_is_not_a_bag_is_refused(capsys, tmp_path):
    """--topic was ignored for a CSV without a word."""
    path = tmp_path / "c.npz"
    np.savez(path, t=T, gyro=G, accel=A)
    line, _ = one_line_error(capsys, "allan", path, "--topic", "/imu0")
    assert "--topic names a ROS bag's topic" in line, line


# -------------------------------------------------------------------- flags checked before the work


def test_montecarlo_too_short_names_the_flags(capsys):
    line, _ = error_line(capsys, "montecarlo", "--seconds", "0.001", "--runs", "4")
    assert "--seconds 0.001" in line and "--rate" in line, line
    assert "times" not in line


@pytest.mark.parametrize(
    "value,fragment", [("nan", "--gravity must be"), ("-9.81", "--gravity 9.81")]
)
def test_propagate_gravity_is_checked_before_the_work(capsys, value, fragment):
    line, out = error_line(capsys, "propagate", DATA / "tumvi_room4", f"--gravity={value}")
    assert fragment in line, line
    assert "overflow" not in line and "gravity=" not in line, line


@pytest.mark.parametrize(
    "argv, msg",
    [
        (
            ["montecarlo", "--seconds", "0.05", "--rate", "100", "--fix-sigma", "0.1"],
            r"--fix-sigma is the position fix of the filter study; pass --filter N",
        ),
        (
            ["montecarlo", "--seconds", "0.05", "--rate", "100", "--filter", "100"],
            r"--filter 100 is more than the 5 samples .* pass at most --filter 5",
        ),
        (["montecarlo", "--rate", "0"], r"--rate must be positive"),
        (
            ["propagate", "no_such_folder", "--earth-rate", "100"],
            r"--earth-rate is a latitude in degrees, in \[-90, 90\]; got 100",
        ),
    ],
)
def test_the_command_names_the_flag_before_the_work(argv, msg, capsys):
    # before: --fix-sigma ignored without --filter, an IndexError traceback for --filter >
    # samples, "latitude_deg" (not the flag) after reading the data
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert __import__("re").search(msg, err), err


@pytest.mark.parametrize(
    "estimate, fragment",
    [
        ("", "no field in --estimate"),
        ("foo", "unknown field(s) ['foo'] in --estimate"),
        ("b_g,b_a,b_g", "--estimate names b_g more than once, got 'b_g,b_a,b_g'; name each "),
    ],
)
def test_calibrate_estimate_is_checked_before_the_recording_is_read(capsys, estimate, fragment):
    """An empty --estimate reached the library after the recording was read and the problem
    built ("estimate names no field", no flag); an unknown one was named after reading."""

    from jaximu import cli

    folder = DATA / "euroc_v1_02_medium"
    code = cli.main(["calibrate", str(folder), "--estimate", estimate])
    out, err = capsys.readouterr()
    assert code == 2 and fragment in err, err
    assert "read " not in out, out  # refused before the work


# --------------------------------------------------------------------------- repair as data


def test_reader_errors_carry_their_repair_as_data():
    ns = np.arange(100, dtype=np.int64) * 5_000_000
    w = np.zeros((100, 3))
    w[:, 0] = 100.0  # 100 "rad/s": deg/s
    a = np.tile([0.0, 0.0, 9.81], (100, 1))
    with pytest.raises(io.DataError) as e:
        io.from_arrays(ns, w, a, time_unit="ns")
    assert isinstance(e.value, InputError)
    assert Fix("gyro_unit", "deg/s") in e.value.fixes
    assert Fix("check_units", False) in e.value.fixes
    assert "gyro_unit='deg/s'" in str(e.value)
    flags = e.value.render(cli.flag_of)
    assert "--gyro-unit deg/s" in flags and "--no-unit-check" in flags
    assert "gyro_unit" not in flags and "check_units" not in flags


def test_the_command_renders_every_fix_the_library_can_raise():
    """Every ``Fix(option, …)`` in the library's source has a flag (the command's parser
    knows it), or is declared as having none; ``_as_flags``' string rewriting is gone."""
    src = "\n".join(p.read_text() for p in pathlib.Path(cli.__file__).parent.rglob("*.py"))
    options = set(re.findall(r"\bFix\(\s*\"(\w+)\"", src))
    assert {"gyro_unit", "accel_unit", "sort", "check_units"} <= options
    app = pathlib.Path(cli.__file__).parent / "app"  # the command: one module per subcommand
    parser_flags = set(
        re.findall(
            r"add_argument\(\s*\"(--[\w-]+)\"", "\n".join(p.read_text() for p in app.glob("*.py"))
        )
    )
    for option in options - cli.API_ONLY_OPTIONS:
        flags = [cli.FLAGS.get(option)] + [
            f for (o, _), f in cli.INVERTED_FLAGS.items() if o == option
        ]
        flags = [f for f in flags if f]
        assert flags and all(f in parser_flags for f in flags), (option, flags)
    assert not hasattr(cli, "_as_flags")


def test_allan_unit_check_is_a_library_function_with_fixes():
    taus = np.logspace(-2, 1, 10)
    gyro = allan.fit_noise(taus, np.sqrt((1e-2) ** 2 / taus)[:, None] * np.ones(3))
    accel = allan.fit_noise(taus, np.sqrt((2e-3) ** 2 / taus)[:, None] * np.ones(3))
    with pytest.raises(InputError) as e:
        allan.check_units(gyro, accel)
    assert Fix("gyro_unit", "deg/s") in e.value.fixes
    allan.check_units(allan.fit_noise(taus, np.sqrt((1.7e-4) ** 2 / taus)), accel)


def test_allan_on_a_moving_recording_notes_motion_and_skips_the_unit_check(capsys):
    """Motion inflates the densities: the command says so and does not call it deg/s."""
    code, out, err = main(capsys, "allan", DATA / "euroc_v1_02_medium")
    assert code == 0, err
    assert "does not look static" in out


def test_library_fixes_render_as_flags_in_calibrate(capsys):
    """A keyframe interval below one sample: the library's fix (keyframe_interval ≥ 0.005)
    is shown as the command's flag."""
    line, _ = error_line(
        capsys, "calibrate", DATA / "euroc_v1_02_medium", "--keyframe-interval", "0.001"
    )
    assert "--keyframe-interval ≥ 0.005" in line, line


@pytest.mark.parametrize(
    "argv, fragments",
    [
        (  # 0.3 s against the default 0.25, 1, 4 s windows: too short, not a gap
            ("--duration", "0.3"),
            ("the longest window length, 4 s, is longer than the 0.295 s", "in --window-lengths"),
        ),
        (  # 6 s of windows of 2 s: 16 are needed
            ("--window-lengths", "2"),
            ("holds 2 windows of 2 s", "at least 16", "≤ 0.3", "s in --window-lengths"),
        ),
    ],
)
def test_calibrate_noise_windows_the_recording_cannot_hold_are_refused_before_the_work(
    capsys, argv, fragments
):
    line, out = error_line(capsys, "calibrate", EUROC, "--estimate", "noise", *argv)
    for fragment in fragments:
        assert fragment in line, line
    assert "window_lengths" not in line and "compiling" not in out and "calibrating" not in out


def test_the_library_fix_for_update_every_renders_as_the_filter_flag():
    e = InputError("update_every too large", [Fix("update_every", 5)], lead="pass at most")
    assert e.render(cli.flag_of).endswith("pass at most --filter 5")


# --------------------------------------------------------------------------- warnings and output


def test_calibrate_warnings_are_one_line_each(capsys):
    with cli._warnings_as_lines():
        warnings.warn(
            "calibration residual χ²/dof = 322 > 100: check", RuntimeWarning, stacklevel=1
        )
    err = capsys.readouterr().err
    assert err == "warning: calibration residual χ²/dof = 322 > 100: check\n", err


def test_cli_propagate_prints_no_jax_warning_in_float32(tmp_path):
    """Every float32 propagate run printed JAX's 'float64 ... not available' UserWarning
    (the suite runs in float64, so the command runs in a child without x64)."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env["PYTHONPATH"] = str(REPO)
    r = subprocess.run(
        [sys.executable, "-m", "jaximu", "propagate", str(tmp_path / "no.csv")],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert r.returncode == 2
    assert r.stderr.splitlines() == [
        f"jaximu propagate: error: no such file or directory: {tmp_path / 'no.csv'}"
    ], r.stderr


# --------------------------------------------------------------------------- compilation cache


def test_cache_folder_follows_the_environment(tmp_path):
    assert cli.cache_folder({"JAXIMU_CACHE_DIR": str(tmp_path)}) == tmp_path
    assert cli.cache_folder({"JAXIMU_CACHE_DIR": "off"}) is None
    assert cli.cache_folder({"XDG_CACHE_HOME": str(tmp_path)}) == tmp_path / "jaximu" / "xla"
    assert cli.cache_folder({}) == pathlib.Path.home() / ".cache" / "jaximu" / "xla"


def test_the_command_keeps_its_compilations(tmp_path):
    """Run as the command (a subprocess): the Monte Carlo chunk's compilation lands in the
    cache folder, for the next run to reuse."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, JAXIMU_CACHE_DIR=str(tmp_path / "xla"))
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "jaximu",
            "montecarlo",
            "--runs",
            "4",
            "--seconds",
            "0.5",
            "--rate",
            "100",
            "--no-progress",
        ],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert res.returncode == 0, res.stderr
    assert any((tmp_path / "xla").iterdir()), "nothing was cached"
