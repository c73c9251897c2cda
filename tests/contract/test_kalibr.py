"""The Kalibr readers refuse what they would misread: a zero rate, ``yes`` for a number, a
binary or a folder for a sensor YAML, and a ``--body-P-sensor`` that is not text.
"""

from __future__ import annotations

import pytest

from jaximu import kalibr

SENSOR = (
    "T_BS:\n  cols: 4\n  rows: 4\n  data: [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]\n"
    "rate_hz: 200\ngyroscope_noise_density: 1.7e-04\ngyroscope_random_walk: 1.9e-05\n"
    "accelerometer_noise_density: 2.0e-3\naccelerometer_random_walk: 3.0e-3\n"
)


def test_sensor_yaml_refuses_a_zero_rate_a_yes_and_files_that_are_not_yaml(tmp_path):
    (tmp_path / "r0.yaml").write_text(SENSOR.replace("rate_hz: 200", "rate_hz: 0"))
    with pytest.raises(ValueError, match=r"r0\.yaml: rate_hz must be finite and > 0"):
        kalibr.read_sensor_yaml(tmp_path / "r0.yaml")  # before: rate_hz = 0.0 returned
    (tmp_path / "yes.yaml").write_text(SENSOR.replace("1.7e-04", "yes"))
    with pytest.raises(ValueError, match=r"gyroscope_noise_density must be a number, got True"):
        kalibr.read_sensor_yaml(tmp_path / "yes.yaml")  # before: a density of 1.0
    (tmp_path / "bin.yaml").write_bytes(b"PK\x03\x04\xff\xfe\xa4")
    with pytest.raises(ValueError, match=r"bin\.yaml: not a text \(YAML\) file"):
        kalibr.read_sensor_yaml(tmp_path / "bin.yaml")  # before: UnicodeDecodeError
    with pytest.raises(ValueError, match=r"is a folder; name the sensor YAML file"):
        kalibr.read_sensor_yaml(tmp_path)  # before: IsADirectoryError
    with pytest.raises(ValueError, match=r"--body-P-sensor .*: is a folder"):
        kalibr.parse_body_P_sensor(str(tmp_path))
    with pytest.raises(ValueError, match=r"--body-P-sensor must be text"):
        kalibr.parse_body_P_sensor(None)
