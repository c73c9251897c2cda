"""Sensor files as the field writes them (EuRoC sensor.yaml, Kalibr camchain and imu.yaml),
--body-P-sensor text, and their bad input."""

import pathlib

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaximu
from jaximu import kalibr

pytest.importorskip("yaml")

# EuRoC MAV mav0/imu0/sensor.yaml, verbatim (ASL format)
EUROC_IMU = """\
# Default imu sensor yaml file
sensor_type: imu
comment: VI-Sensor IMU (ADIS16448)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0,
         0.0, 1.0, 0.0, 0.0,
         0.0, 0.0, 1.0, 0.0,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 200

# inertial sensor noise model parameters (static)
gyroscope_noise_density: 1.6968e-04     # [ rad / s / sqrt(Hz) ]   ( gyro "white noise" )
gyroscope_random_walk: 1.9393e-05       # [ rad / s^2 / sqrt(Hz) ] ( gyro bias diffusion )
accelerometer_noise_density: 2.0000e-3  # [ m / s^2 / sqrt(Hz) ]   ( accel "white noise" )
accelerometer_random_walk: 3.0000e-3    # [ m / s^3 / sqrt(Hz) ].  ( accel bias diffusion )
"""

# EuRoC MAV mav0/cam0/sensor.yaml's T_BS (the camera in the IMU/body frame)
EUROC_T_B_CAM0 = np.array(
    [
        [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
        [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
        [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def write(tmp_path, name, text):
    path = pathlib.Path(tmp_path) / name
    path.write_text(text)
    return path


def test_euroc_imu_sensor_yaml(tmp_path):
    cfg = kalibr.read_sensor_yaml(write(tmp_path, "sensor.yaml", EUROC_IMU))
    np.testing.assert_array_equal(cfg.body_P_sensor.q, [1, 0, 0, 0])
    np.testing.assert_array_equal(cfg.body_P_sensor.p, [0, 0, 0])
    assert cfg.rate_hz == 200.0
    assert (
        cfg.noise.gyroscope_noise_density,
        cfg.noise.gyroscope_random_walk,
        cfg.noise.accelerometer_noise_density,
        cfg.noise.accelerometer_random_walk,
    ) == (1.6968e-04, 1.9393e-05, 2.0e-3, 3.0e-3)


def test_asl_t_bs_with_a_rotation_and_lever_arm(tmp_path):
    """A camera's ASL T_BS (EuRoC cam0): the rotation against scipy, the translation as is."""
    data = ", ".join(repr(float(x)) for x in EUROC_T_B_CAM0.reshape(-1))
    text = f"sensor_type: camera\nT_BS:\n  rows: 4\n  cols: 4\n  data: [{data}]\nrate_hz: 20\n"
    cfg = kalibr.read_sensor_yaml(write(tmp_path, "cam0.yaml", text))
    R = Rotation.from_quat(np.asarray(cfg.body_P_sensor.q), scalar_first=True).as_matrix()
    np.testing.assert_allclose(R, EUROC_T_B_CAM0[:3, :3], atol=1e-9)
    np.testing.assert_allclose(cfg.body_P_sensor.p, EUROC_T_B_CAM0[:3, 3], atol=0)
    assert cfg.noise is None and cfg.rate_hz == 20.0


def test_kalibr_camchain_t_cam_imu_is_the_imu_pose_in_the_camera(tmp_path):
    T_cam_imu = np.linalg.inv(EUROC_T_B_CAM0)
    rows = "\n".join(f"  - [{', '.join(repr(float(x)) for x in r)}]" for r in T_cam_imu)
    text = f"cam0:\n  T_cam_imu:\n{rows}\n  camera_model: pinhole\n  timeshift_cam_imu: 0.0\n"
    cfg = kalibr.read_sensor_yaml(write(tmp_path, "camchain-imucam.yaml", text))
    R = Rotation.from_quat(np.asarray(cfg.body_P_sensor.q), scalar_first=True).as_matrix()
    np.testing.assert_allclose(R, T_cam_imu[:3, :3], atol=1e-9)
    np.testing.assert_allclose(cfg.body_P_sensor.p, T_cam_imu[:3, 3], atol=1e-12)
    assert "cam0.T_cam_imu" in cfg.source


def test_kalibr_imu_yaml(tmp_path):
    text = (
        "imu0:\n  accelerometer_noise_density: 0.002\n  accelerometer_random_walk: 0.003\n"
        "  gyroscope_noise_density: 0.00017\n  gyroscope_random_walk: 0.00002\n"
        "  rostopic: /imu0\n  update_rate: 200.0\n"
    )
    cfg = kalibr.read_sensor_yaml(write(tmp_path, "imu.yaml", text))
    assert cfg.body_P_sensor is None and cfg.rate_hz == 200.0
    assert cfg.noise.accelerometer_random_walk == 0.003


def test_body_P_sensor_text():
    cfg = kalibr.parse_body_P_sensor("0.7071068,0,0,0.7071068,0.1,-0.2,0.05")
    np.testing.assert_allclose(np.linalg.norm(cfg.body_P_sensor.q), 1.0, atol=1e-15)
    assert "normalised" in cfg.source
    np.testing.assert_array_equal(cfg.body_P_sensor.p, [0.1, -0.2, 0.05])


@pytest.mark.parametrize(
    "text,match",
    [
        ("T_BS:\n  rows: 4\n  cols: 4\nrate_hz: 200\n", r"T_BS lacks the field\(s\) data"),
        ("T_BS:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n", r"T_BS must be 4×4"),
        (
            "T_BS:\n  rows: 4\n  cols: 4\n  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1.2, 0, 0, 0, 0, 1]\n",
            r"T_BS: body_P_sensor: R_BS is not a rotation matrix",
        ),
        ("T_BS:\n  rows: 4\n  cols: 4\n  data: [1, 0, 0]\n", r"T_BS must hold 16 numbers"),
        (
            EUROC_IMU.replace("gyroscope_random_walk: 1.9393e-05", ""),
            r"noise densities are incomplete: gyroscope_random_walk missing",
        ),
        ("sensor_type: imu\nrate_hz: 200\n", r"neither a pose .* nor noise densities"),
        (
            "cam1:\n  T_cam_imu: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n",
            r"no 'cam0' with T_cam_imu; the file has \['cam1'\]",
        ),
    ],
)
def test_bad_sensor_files_name_the_field(tmp_path, text, match):
    with pytest.raises(ValueError, match=match):
        kalibr.read_sensor_yaml(write(tmp_path, "bad.yaml", text))


@pytest.mark.parametrize(
    "text,match",
    [
        ("1,0,0,0,0.1,0.2", r"expected seven numbers"),
        ("0.9,0,0,0,0,0,0", r"is not a unit quaternion"),
        ("missing.yaml", r"no such file"),
    ],
)
def test_bad_body_P_sensor_text(text, match):
    with pytest.raises(ValueError, match=match):
        kalibr.parse_body_P_sensor(text)


def test_cli_reports_a_bad_body_P_sensor_in_one_line(capsys):
    folder = pathlib.Path(jaximu.__file__).parent / "data" / "euroc_v1_02_medium"
    from jaximu import cli

    rc = cli.main(
        [
            "propagate",
            str(folder),
            "--init-from-groundtruth",
            "--no-progress",
            "--body-P-sensor",
            "1,0,0",
        ],
        cache=False,
    )
    assert rc == 2
    err = capsys.readouterr().err
    assert "expected seven numbers qw,qx,qy,qz,px,py,pz" in err and "Traceback" not in err
