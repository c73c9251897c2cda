"""Sensor configuration files as the field writes them: EuRoC / ASL ``sensor.yaml`` and
Kalibr's ``camchain-imucam.yaml`` and ``imu.yaml``.

* EuRoC ``mav0/imu0/sensor.yaml`` (ASL format): ``T_BS`` (``rows: 4``, ``cols: 4``, ``data``:
  16 numbers, row-major), ``rate_hz`` and the four Kalibr noise densities at the top level.
* Kalibr ``camchain-imucam.yaml``: ``cam0: T_cam_imu`` (a 4×4 nested list): the IMU's pose
  in the camera frame, ``T_CS``; with the camera as the body it is ``T_BS``.
* Kalibr ``imu.yaml``: ``imu0:`` with ``update_rate`` and the densities (no pose);
  :func:`write_imu_yaml` writes one (Kalibr's input layout: the keys at the top level).

:func:`read_sensor_yaml` returns a :class:`SensorConfig`; :func:`parse_body_P_sensor` reads
the command's ``--body-P-sensor`` (seven numbers or such a file). Reading YAML needs PyYAML
(``pip install jaximu[kalibr]``).
"""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

from jaximu.geometry import _tolerances
from jaximu.geometry.noise import ImuNoise
from jaximu.geometry.sensor import SensorPose

__all__ = ["SensorConfig", "read_sensor_yaml", "parse_body_P_sensor", "write_imu_yaml"]

DENSITIES = (
    "gyroscope_noise_density",
    "accelerometer_noise_density",
    "gyroscope_random_walk",
    "accelerometer_random_walk",
)


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    """What a sensor file says.

    Attributes:
        body_P_sensor: the IMU's pose in the body frame (``None`` if the file has none).
        rate_hz: the IMU rate [Hz] (``rate_hz`` / ``update_rate``), or ``None``.
        noise: the four densities as :class:`jaximu.ImuNoise`, or ``None`` if it has none.
        source: the file and the key the pose came from.
    """

    body_P_sensor: SensorPose | None
    rate_hz: float | None
    noise: ImuNoise | None
    source: str


def _load_yaml(path):
    try:
        import yaml
    except ImportError:
        raise ImportError(
            "reading a sensor YAML file needs PyYAML: pip install pyyaml (or jaximu[kalibr])"
        ) from None
    p = pathlib.Path(path)
    if p.is_dir():
        raise ValueError(
            f"{path}: is a folder; name the sensor YAML file in it (EuRoC "
            "mav0/imu0/sensor.yaml, Kalibr camchain-imucam.yaml or imu.yaml)"
        )
    if not p.is_file():
        raise FileNotFoundError(f"{path}: no such file (a sensor YAML file)")
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise ValueError(
            f"{path}: not a text (YAML) file; expected an EuRoC sensor.yaml or a "
            "Kalibr camchain/imu file"
        ) from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ValueError(f"{path}: not valid YAML ({e})") from None
    if not isinstance(doc, dict):
        raise ValueError(
            f"{path}: expected a YAML mapping (EuRoC sensor.yaml or a Kalibr "
            "camchain/imu file), got " + type(doc).__name__
        )
    return doc


def _number(path, key, x, positive=False):
    try:
        if isinstance(x, bool):  # YAML's yes/no; text such as 1e-3 (YAML 1.1 reads it as a
            raise TypeError  # string) is a number
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: {key} must be a number, got {x!r}") from None
    if not np.isfinite(v) or v < 0 or (positive and v == 0):
        raise ValueError(
            f"{path}: {key} must be finite and {'> 0' if positive else '≥ 0'}, got {x!r}"
        )
    return v


def _matrix(path, key, node):
    """A 4×4 from ASL's ``{rows, cols, data}`` or Kalibr's nested list."""
    if isinstance(node, dict):
        missing = [k for k in ("rows", "cols", "data") if k not in node]
        if missing:
            raise ValueError(
                f"{path}: {key} lacks the field(s) {', '.join(missing)} (ASL "
                "format: rows: 4, cols: 4, data: [16 numbers, row-major])"
            )
        if (node["rows"], node["cols"]) != (4, 4):
            raise ValueError(
                f"{path}: {key} must be 4×4, got rows: {node['rows']}, cols: {node['cols']}"
            )
        data = node["data"]
    else:
        data = node
    try:
        T = np.asarray(data, float).reshape(4, 4)
    except (TypeError, ValueError):
        raise ValueError(
            f"{path}: {key} must hold 16 numbers (a 4×4 homogeneous transform), got {data!r}"
        ) from None
    try:
        return SensorPose.from_matrix(T)
    except ValueError as e:
        raise ValueError(f"{path}: {key}: {e}") from None


def read_sensor_yaml(path, camera: str = "cam0") -> SensorConfig:
    """Read an EuRoC ``sensor.yaml``, a Kalibr ``camchain-imucam.yaml`` (the pose of
    ``camera``'s ``T_cam_imu``: the camera is then the body) or a Kalibr ``imu.yaml``.

    Raises ``ValueError`` naming the file and the field on a missing or malformed field
    (``T_BS`` without ``data``, a non-rotation, three of the four densities, …); a file
    with neither a pose nor densities is refused.
    """
    doc = _load_yaml(path)
    pose, where = None, None
    if "T_BS" in doc:
        pose, where = _matrix(path, "T_BS", doc["T_BS"]), "T_BS"
    elif isinstance(doc.get(camera), dict) and "T_cam_imu" in doc[camera]:
        pose, where = (
            _matrix(path, f"{camera}.T_cam_imu", doc[camera]["T_cam_imu"]),
            f"{camera}.T_cam_imu",
        )
    elif any(isinstance(v, dict) and "T_cam_imu" in v for v in doc.values()):
        cams = [k for k, v in doc.items() if isinstance(v, dict) and "T_cam_imu" in v]
        raise ValueError(f"{path}: no {camera!r} with T_cam_imu; the file has {cams}")
    imu = doc["imu0"] if isinstance(doc.get("imu0"), dict) else doc
    present = [k for k in DENSITIES if k in imu]
    if present and len(present) < 4:
        missing = [k for k in DENSITIES if k not in imu]
        raise ValueError(
            f"{path}: the noise densities are incomplete: {', '.join(missing)} "
            "missing (Kalibr names, continuous-time densities)"
        )
    noise = ImuNoise(*(_number(path, k, imu[k]) for k in DENSITIES)) if present else None
    rate_key = "rate_hz" if "rate_hz" in imu else ("update_rate" if "update_rate" in imu else None)
    rate = _number(path, rate_key, imu[rate_key], positive=True) if rate_key else None
    if pose is None and noise is None:
        raise ValueError(
            f"{path}: neither a pose (T_BS, or cam0.T_cam_imu) nor noise densities "
            "found; expected an EuRoC sensor.yaml or a Kalibr camchain/imu file"
        )
    return SensorConfig(pose, rate, noise, f"{path}" + (f" ({where})" if where else ""))


def parse_body_P_sensor(text: str, camera: str = "cam0") -> SensorConfig:
    """``--body-P-sensor``: ``"qw,qx,qy,qz,px,py,pz"`` (``q_BS`` Hamilton, ``p_BS`` [m]) or
    the path of a YAML file (:func:`read_sensor_yaml`). A quaternion typed with a few digits
    (``|q|`` within 1e-3 of 1) is normalised and said so in ``source``; beyond that it is an
    error."""
    if not isinstance(text, str):
        raise ValueError(
            f"--body-P-sensor must be text (seven numbers or a YAML file), got "
            f"{type(text).__name__}"
        )
    p = pathlib.Path(text)
    if p.is_dir():
        raise ValueError(
            f"--body-P-sensor {text}: is a folder; name the sensor YAML file in "
            "it (EuRoC mav0/imu0/sensor.yaml, Kalibr camchain-imucam.yaml)"
        )
    if p.suffix.lower() in (".yaml", ".yml") or p.is_file():
        if not p.is_file():
            raise ValueError(f"--body-P-sensor {text}: no such file")
        return read_sensor_yaml(p, camera)
    parts = [s for s in text.replace(" ", ",").split(",") if s]
    try:
        vals = np.array([float(s) for s in parts])
    except ValueError:
        vals = np.array([])
    if vals.shape != (7,) or not np.all(np.isfinite(vals)):
        raise ValueError(
            f"--body-P-sensor {text!r}: expected seven numbers qw,qx,qy,qz,px,py,pz "
            "(q_BS Hamilton, p_BS in metres) or a sensor YAML file"
        )
    q = vals[:4]
    norm = float(np.linalg.norm(q))
    _tolerances.check_unit_norm(
        f"--body-P-sensor: q_BS = {q.tolist()}",
        q,
        np.float64,
        tol=_tolerances.ROUNDED_QUATERNION,
        fix="give a unit quaternion [w, x, y, z]",
    )
    note = "" if abs(norm - 1) < 1e-12 else f" (q normalised from |q| = {norm:.6g})"
    pose = SensorPose(np.asarray(q / norm), np.asarray(vals[4:]))
    return SensorConfig(pose, None, None, f"--body-P-sensor{note}")


_UNIT_COMMENTS = {
    "gyroscope_noise_density": "rad/s/sqrt(Hz) (gyro white noise)",
    "gyroscope_random_walk": "rad/s^2/sqrt(Hz) (gyro bias diffusion)",
    "accelerometer_noise_density": "m/s^2/sqrt(Hz) (accel white noise)",
    "accelerometer_random_walk": "m/s^3/sqrt(Hz) (accel bias diffusion)",
}


def write_imu_yaml(
    path, noise: ImuNoise, rate_hz: float, rostopic: str = "/imu0", comment: str = ""
) -> pathlib.Path:
    """Write a Kalibr ``imu.yaml`` (its input layout: the four continuous-time densities,
    ``rostopic`` and ``update_rate`` at the top level; no PyYAML needed): what
    :func:`read_sensor_yaml` reads back. Kalibr's densities are scalars, so each field of
    ``noise`` must be one finite number ``≥ 0`` (a per-axis value is refused: pass its
    axes' root mean square if that is what you mean); ``rate_hz > 0``; ``comment``: a line
    or more written as YAML comments at the top. Every number is written with 17
    significant digits (it reads back exactly). Returns the path."""
    if not isinstance(noise, ImuNoise):
        raise ValueError(f"noise must be an ImuNoise, got {type(noise).__name__}")
    values = {}
    for key in DENSITIES:
        x = np.asarray(getattr(noise, key), np.float64)
        if x.ndim != 0:
            raise ValueError(
                f"noise.{key} has shape {x.shape}: Kalibr's imu.yaml holds one "
                "number per density; pass a scalar (e.g. the axes' root mean square)"
            )
        if not np.isfinite(x) or x < 0:
            raise ValueError(f"noise.{key} must be finite and ≥ 0, got {float(x)}")
        values[key] = float(x)
    rate = _number("rate_hz", "rate_hz", rate_hz, positive=True)
    if not isinstance(rostopic, str) or not rostopic or any(c in rostopic for c in "\n:#'\""):
        raise ValueError(f"rostopic must be a topic name such as '/imu0', got {rostopic!r}")
    lines = [f"# {line}" for line in str(comment).splitlines()]
    lines += [f"{key}: {values[key]:.17g}  # {_UNIT_COMMENTS[key]}" for key in DENSITIES]
    lines += [f"rostopic: {rostopic}", f"update_rate: {rate:.17g}  # Hz"]
    p = pathlib.Path(path)
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return p
