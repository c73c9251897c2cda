"""Issue 12, class 7 and the repair-as-data design: the command's defects, each with the
user's flag in the one-line error; and errors that carry their repair (option and value) as
data, which the command renders as its flag.

The command runs in-process (``jaximu.cli.main``), so the errors, which are all raised
before any computation, cost no JAX start-up; the expected texts are the flags a user types.
"""

from __future__ import annotations

import pathlib
import re
import shutil

import numpy as np
import pytest

from jaximu import allan, cli, io
from jaximu.errors import Fix, InputError

DATA = pathlib.Path(__file__).parent / "data"
EUROC_IMU = DATA / "euroc_v1_02_medium" / "mav0" / "imu0" / "data.csv"


def main(capsys, *argv):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_line_error(capsys, *argv):
    """Run the command; it must fail with exit 2 and one ``error:`` line; return that line
    and stdout."""
    code, out, err = main(capsys, *argv)
    assert code == 2, (out, err)
    assert "Traceback" not in err
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    return lines[0], out


# --------------------------------------------------------------------------- demo


def test_demo_shorter_than_the_first_mark_still_reports(capsys):
    """``--seconds 0.5`` used to end in an IndexError traceback."""
    code, out, err = main(capsys, "demo", "--seconds", "0.5", "--no-plot", "--no-progress")
    assert code == 0, err
    assert "Traceback" not in err
    assert re.search(r"position drift \d+\.\d+ m after 0\.5 s", out), out


def test_demo_longer_than_the_excerpt_is_refused(capsys):
    line, out = one_line_error(capsys, "demo", "--seconds", "100", "--no-plot")
    assert "--seconds 100" in line and "≤ 20" in line, line
    assert out == ""  # nothing ran


def test_demo_plot_into_a_missing_folder_fails_before_the_work(capsys, tmp_path):
    line, out = one_line_error(capsys, "demo", "--seconds", "1",
                               "--plot", tmp_path / "missing" / "demo.png")
    assert "--plot" in line and "does not exist" in line, line
    assert out == ""


def test_outputs_naming_a_folder_fail_before_the_work(capsys, tmp_path):
    line, out = one_line_error(capsys, "propagate", DATA / "tumvi_room4", "--out", tmp_path)
    assert f"--out {tmp_path}" in line and "is a folder" in line, line
    assert "read" not in out
    line, out = one_line_error(capsys, "demo", "--plot", tmp_path)
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
    line, _ = one_line_error(capsys, "allan", path)
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


# --------------------------------------------------------------------------- montecarlo, gravity


def test_montecarlo_too_short_names_the_flags(capsys):
    line, _ = one_line_error(capsys, "montecarlo", "--seconds", "0.001", "--runs", "4")
    assert "--seconds 0.001" in line and "--rate" in line, line
    assert "times" not in line


@pytest.mark.parametrize("value,fragment", [("nan", "--gravity must be"),
                                            ("-9.81", "--gravity 9.81")])
def test_propagate_gravity_is_checked_before_the_work(capsys, value, fragment):
    line, out = one_line_error(capsys, "propagate", DATA / "tumvi_room4", f"--gravity={value}")
    assert fragment in line, line
    assert "overflow" not in line and "gravity=" not in line, line


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
    parser_flags = set(re.findall(r"add_argument\(\s*\"(--[\w-]+)\"",
                                  pathlib.Path(cli.__file__).read_text()))
    for option in options - cli.API_ONLY_OPTIONS:
        flags = [cli.FLAGS.get(option)] + [f for (o, _), f in cli.INVERTED_FLAGS.items()
                                           if o == option]
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
    res = subprocess.run([sys.executable, "-m", "jaximu", "montecarlo", "--runs", "4",
                          "--seconds", "0.5", "--rate", "100", "--no-progress"],
                         capture_output=True, text=True, timeout=300, env=env)
    assert res.returncode == 0, res.stderr
    assert any((tmp_path / "xla").iterdir()), "nothing was cached"


def test_library_fixes_render_as_flags_in_calibrate(capsys):
    """A keyframe interval below one sample: the library's fix (keyframe_interval ≥ 0.005)
    is shown as the command's flag."""
    line, _ = one_line_error(capsys, "calibrate", DATA / "euroc_v1_02_medium",
                             "--keyframe-interval", "0.001")
    assert "--keyframe-interval ≥ 0.005" in line, line
