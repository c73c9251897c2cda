"""`jaximu preintegrate`, `montecarlo`, `calibrate` and `allan` end to end in a subprocess
(a file of their own so that pytest-xdist runs it beside tests/app/test_cli.py). The subprocesses
keep their compilations in the suite's temporary folder (conftest.py: JAXIMU_CACHE_DIR)."""

import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

SEG = str(pathlib.Path(__file__).resolve().parents[1] / "data" / "euroc_v1_02_medium")


def run(*args):
    return subprocess.run(
        [sys.executable, "-m", "jaximu", *args], capture_output=True, text=True, timeout=300
    )


def test_preintegrate_windows_against_ground_truth(tmp_path):
    res = run(
        "preintegrate",
        SEG,
        "--window",
        "0.5",
        "--bias-from-groundtruth",
        "--out",
        str(tmp_path / "pim.npz"),
    )
    assert res.returncode == 0, res.stderr
    assert "10 windows of 100 samples" in res.stdout
    med = res.stdout.split("residuals against the ground truth")[1]
    # 0.5 s windows from the dataset's own biases: a tenth of a degree (SOURCE.md: 0.07° at 1 s)
    assert float(med.split("rotation ")[1].split("°")[0]) < 0.3
    with np.load(tmp_path / "pim.npz") as z:
        assert z["delta_p"].shape == (10, 3) and z["cov"].shape == (10, 9, 9)
        np.testing.assert_allclose(z["delta_t"], 0.5, atol=1e-4)


def test_montecarlo_command():
    res = run(
        "montecarlo", "--runs", "64", "--seconds", "0.5", "--rate", "100", "--trajectory", "circle"
    )
    assert res.returncode == 0, res.stderr
    assert "average NEES" in res.stdout and "predicted" in res.stdout


def test_calibrate_command(tmp_path):
    # the default optimiser, Levenberg-Marquardt (L-BFGS and Adam: tests/calibration/test_calibration.py)
    res = run("calibrate", SEG, "--estimate", "b_g", "--out", str(tmp_path / "cal.json"))
    assert res.returncode == 0, res.stderr
    assert "compiling the residuals and their Jacobian" in res.stdout
    assert "converged" in res.stdout and "not converged" not in res.stdout
    fit = json.loads((tmp_path / "cal.json").read_text())["fields"]["b_g"]
    # 5 s of data: within 5 mrad/s of the dataset's own estimate (-0.0022, 0.0207, 0.0758)
    np.testing.assert_allclose(fit["value"], [-0.0022, 0.0207, 0.0758], atol=5e-3)


def test_allan_command_warns_on_motion():
    res = run("allan", SEG)
    assert res.returncode == 0, res.stderr
    assert "gyroscope_noise_density" in res.stdout and "does not look static" in res.stdout


def test_preintegrate_when_the_ground_truth_starts_later(tmp_path):
    """Real sequences record IMU before and after the ground truth: only the windows inside
    it are compared (here 1.0–3.995 s: five 0.5 s windows), and the output is written."""
    src = pathlib.Path(SEG) / "mav0"
    mav0 = tmp_path / "seq" / "mav0"
    (mav0 / "imu0").mkdir(parents=True)
    (mav0 / "state_groundtruth_estimate0").mkdir()
    (mav0 / "imu0" / "data.csv").write_text((src / "imu0" / "data.csv").read_text())
    gt = (src / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines(True)
    (mav0 / "state_groundtruth_estimate0" / "data.csv").write_text(gt[0] + "".join(gt[201:801]))
    res = run(
        "preintegrate",
        str(tmp_path / "seq"),
        "--bias-from-groundtruth",
        "--out",
        str(tmp_path / "pim.npz"),
    )
    assert res.returncode == 0, res.stderr
    assert "median over the 5 windows inside it" in res.stdout
    assert (tmp_path / "pim.npz").exists()


def test_calibrate_command_fits_noise_densities_and_writes_an_imu_yaml(tmp_path):
    """``--estimate b_g,b_a,noise`` on 5 s of data (the likelihood over 100 windows of the
    shortest length, the longer ones in the model check): the JSON holds each density and the reference's σ with its standard
    error (strict JSON: ``null`` where undetermined), and the Kalibr imu.yaml it writes
    reads back through ``jaximu.kalibr`` to the JSON's values."""
    from jaximu import kalibr

    out, yaml = tmp_path / "cal.json", tmp_path / "imu.yaml"
    res = run(
        "calibrate",
        SEG,
        "--estimate",
        "b_g,b_a,noise",
        "--window-lengths",
        "0.05,0.1,0.2,0.5",
        "--out",
        str(out),
        "--imu-yaml",
        str(yaml),
    )
    assert res.returncode == 0, res.stderr
    assert "noise densities by likelihood" in res.stdout and "Kalibr imu.yaml written" in res.stdout
    noise = json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"{c} in JSON"))
    noise = noise["noise"]
    assert noise["window_lengths"] == pytest.approx([0.05, 0.1, 0.2, 0.5], rel=1e-3)
    back = kalibr.read_sensor_yaml(yaml).noise
    for name in (
        "gyroscope_noise_density",
        "accelerometer_noise_density",
        "gyroscope_random_walk",
        "accelerometer_random_walk",
    ):
        value, std = noise[name]["value"], noise[name]["std"]
        assert value > 0 and (std is None or std > 0), (name, value, std)
        assert float(getattr(back, name)) == pytest.approx(value, rel=1e-15)
    assert len(noise["reference_sigma"]["value"]) == 3
