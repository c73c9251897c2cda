"""The `jaximu` command end to end, in a subprocess, on the bundled real EuRoC excerpt."""

import subprocess
import sys

import numpy as np
import pytest

from jaximu.datasets import euroc_v1_02_segment


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "jaximu", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


def test_bundled_segment_is_intact():
    """The excerpt keeps EuRoC's exact int64 nanosecond stamps and 200 Hz grid."""
    seg = euroc_v1_02_segment()
    assert seg.t0_ns == 1403715524907142912
    assert seg.gyro.shape == (4002, 3) and seg.q_gt.shape == (4001, 4)
    np.testing.assert_allclose(np.diff(seg.t), 0.005, atol=2e-6)
    assert abs(seg.t_gt[0] - 256e-9) < 1e-12  # GT stamp 256 ns after the first IMU stamp
    # Still at the start: the accelerometer reads ~g.
    assert abs(np.linalg.norm(seg.accel[:200].mean(axis=0)) - 9.81) < 0.05


def test_demo_runs_and_reports_drift(tmp_path):
    pytest.importorskip("matplotlib")
    out = tmp_path / "demo.png"
    res = run("demo", "--seconds", "2", "--plot", str(out))
    assert res.returncode == 0, res.stderr
    assert "EuRoC MAV V1_02_medium" in res.stdout and "position drift" in res.stdout
    lines = [ln for ln in res.stdout.splitlines()
             if ln.split()[:1] in (["euler"], ["midpoint"], ["rk4"])]
    assert len(lines) == 3
    # Dead reckoning over 2 s from the ground-truth state: centimetres, not metres (a wrong
    # gravity sign or quaternion order gives tens of metres).
    drift_2s = float(lines[1].split()[-5])
    assert drift_2s < 0.3
    assert out.exists() and out.stat().st_size > 10_000


def test_demo_without_plot():
    res = run("demo", "--seconds", "1", "--no-plot")
    assert res.returncode == 0, res.stderr
    assert "plot written" not in res.stdout


def test_user_mistakes_exit_non_zero_without_traceback():
    res = run("demo", "--seconds", "-1", "--no-plot")
    assert res.returncode != 0 and "Traceback" not in res.stderr
    assert "--seconds must be positive" in res.stderr
    res = run("frobnicate")
    assert res.returncode != 0 and "Traceback" not in res.stderr


def test_quickstart_example_runs():
    import pathlib

    example = pathlib.Path(__file__).resolve().parents[1] / "examples" / "quickstart.py"
    if not example.exists():  # an installed package without the source tree
        pytest.skip("examples/ not present")
    res = subprocess.run([sys.executable, str(example)], capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert [ln[:2] for ln in lines] == ["1.", "2.", "3.", "4.", "5."]
    # 1 s of dead reckoning from the ground truth: a few centimetres (SOURCE.md: 2.5 cm median)
    assert float(lines[0].split("error ")[1].split(" m")[0]) < 0.1


def test_monte_carlo_example_writes_its_plots(tmp_path):
    import pathlib

    pytest.importorskip("matplotlib")
    example = pathlib.Path(__file__).resolve().parents[1] / "examples" / "monte_carlo.py"
    if not example.exists():
        pytest.skip("examples/ not present")
    res = subprocess.run([sys.executable, str(example), "--runs", "200", "--seconds", "1",
                          "--out", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    for name in ("mc_envelopes.png", "mc_nees.png", "allan.png"):
        assert (tmp_path / name).stat().st_size > 10_000
    assert "average NEES" in res.stdout and "(detected)" in res.stdout


def test_learned_correction_example_runs(tmp_path):
    """A few training steps of examples/learned_correction.py (the full run is ~25 s)."""
    import pathlib

    example = pathlib.Path(__file__).resolve().parents[1] / "examples" / "learned_correction.py"
    if not example.exists():
        pytest.skip("examples/ not present")
    out = tmp_path / "lc.png"
    res = subprocess.run([sys.executable, str(example), "--steps", "3", "--out", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "held-out sequence (EuRoC V2_01)" in res.stdout and out.stat().st_size > 10_000
