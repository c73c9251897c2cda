"""What the subcommands share: the input and output options, reading the recording named on
the command line, and the checks of options that come before the work.

Parsing only: the readers and the sensor files are the library's (:mod:`jaximu.io`,
:mod:`jaximu.kalibr`).
"""

from __future__ import annotations

import pathlib
import sys

import numpy as np

__all__ = [
    "UsageError",
    "add_input_options",
    "add_output_options",
    "add_repair_options",
    "add_sensor_options",
    "add_unit_options",
    "bias_option",
    "check_earth_rate",
    "check_outputs",
    "compute_dtype",
    "detect_format",
    "load_recording",
    "reader_options",
    "sensor_and_world",
    "start_at_groundtruth",
]


class UsageError(ValueError):
    """A mistake in the command line."""


def compute_dtype(args):
    """``--float64``: float64 (x64 switched on, as the user asked), else JAX's default float."""
    import jax
    import jax.numpy as jnp

    if getattr(args, "float64", False):
        if not jax.config.jax_enable_x64:
            jax.config.update("jax_enable_x64", True)  # the user asked for it on the command line
        return jnp.float64
    return jnp.result_type(float)


def sensor_and_world(args, rate_hz=None):
    """``--body-P-sensor`` and ``--earth-rate``: ``(body_P_sensor, omega_coriolis, noise)``
    (``noise``: the YAML's densities, which replace ``--noise``, or ``None``)."""
    from jaximu.calibration import kalibr
    from jaximu.schemes.world import earth_rate

    pose = noise = omega = None
    if getattr(args, "body_P_sensor", None):
        cfg = kalibr.parse_body_P_sensor(args.body_P_sensor)
        pose, noise = cfg.body_P_sensor, cfg.noise
        if pose is not None:
            print(
                f"IMU pose on the body from {cfg.source}: q_BS = "
                f"{np.array2string(np.asarray(pose.q), precision=6)}, p_BS = "
                f"{np.array2string(np.asarray(pose.p), precision=4)} m"
            )
        if noise is not None:
            print(f"noise densities from {cfg.source} (they replace --noise)")
        if cfg.rate_hz and rate_hz and abs(cfg.rate_hz - rate_hz) > 0.05 * rate_hz:
            print(
                f"note: the YAML's rate {cfg.rate_hz:g} Hz differs from the recording's "
                f"{rate_hz:.1f} Hz"
            )
    if getattr(args, "earth_rate", None) is not None:
        omega = np.asarray(earth_rate(args.earth_rate), np.float64)
        print(
            f"rotating world: Earth's rate at latitude {args.earth_rate:g}° (east-north-up) "
            f"{np.array2string(omega, precision=4)} rad/s"
        )
    return pose, omega, noise


def check_earth_rate(args):
    """``--earth-rate``: a latitude in [-90, 90] degrees, checked before the work (reading
    the data) and named by its flag."""
    lat = getattr(args, "earth_rate", None)
    if lat is not None and not (np.isfinite(lat) and abs(lat) <= 90):
        raise UsageError(f"--earth-rate is a latitude in degrees, in [-90, 90]; got {lat:g}")


def add_sensor_options(p):
    g = p.add_argument_group("sensor pose and rotating world")
    g.add_argument(
        "--body-P-sensor",
        metavar="QW,QX,QY,QZ,PX,PY,PZ|YAML",
        help="the IMU's pose in the body frame: q_BS (Hamilton) and the lever arm "
        "p_BS [m]; or an EuRoC sensor.yaml (T_BS) or Kalibr camchain (cam0 "
        "T_cam_imu: the camera is the body) / imu.yaml, whose noise densities "
        "replace --noise",
    )
    g.add_argument(
        "--earth-rate",
        type=float,
        metavar="LAT",
        help="latitude [°] of the local east-north-up world: Earth's rotation "
        "(Coriolis and centrifugal, exact transition) at it",
    )


def detect_format(path: pathlib.Path) -> str:
    """``--format auto``: the input format of ``path``, from its layout or suffix."""
    if path.is_dir():
        if (path / "metadata.yaml").is_file():
            return "rosbag"
        mav0 = path / "mav0" if (path / "mav0").is_dir() else path
        if (mav0 / "mocap0").is_dir() and not (mav0 / "state_groundtruth_estimate0").is_dir():
            return "tumvi"
        return "euroc"
    suffix = path.suffix.lower()
    if suffix in (".bag", ".mcap", ".db3"):
        return "rosbag"
    if suffix == ".npz":
        return "npz"
    if path.name == "data.csv" and path.parent.name == "imu0":
        return "euroc"
    return "csv"


def load_recording(args):
    """Read the recording named on the command line, with the repair options given."""
    from jaximu import io

    path = pathlib.Path(args.file)
    if args.duration is not None and not args.duration > 0:
        raise UsageError("--duration must be positive")
    if args.max_gap is not None and not args.max_gap > 0:
        raise UsageError("--max-gap must be positive")
    if not args.start >= 0:
        raise UsageError("--start must be ≥ 0")
    if not path.exists():
        raise UsageError(f"no such file or directory: {path}")
    fmt = args.format if args.format != "auto" else detect_format(path)
    options = reader_options(args)
    if args.topic is not None and fmt != "rosbag":
        raise UsageError(
            f"--topic names a ROS bag's topic; {path} is read as {fmt}: drop "
            "--topic (or pass --format rosbag for a bag)"
        )
    if args.time_unit is not None and fmt not in ("csv", "npz"):
        raise UsageError(f"--time-unit applies to CSV and NPZ input, not {fmt} (stamps in ns)")
    if fmt in ("euroc", "tumvi"):  # SI by definition; the units flags for other ASL folders
        data = (io.read_euroc if fmt == "euroc" else io.read_tumvi)(path, **options)
    elif fmt == "csv":
        cols = [c.strip() for c in args.columns.split(",")]
        if len(cols) != 7:
            raise UsageError("--columns needs 7 comma-separated columns: t,wx,wy,wz,ax,ay,az")
        cols = [int(c) if c.lstrip("-").isdigit() else c for c in cols]
        data = io.read_csv(
            path,
            time=cols[0],
            gyro=cols[1:4],
            accel=cols[4:7],
            time_unit=args.time_unit,
            **options,
        )
    elif fmt == "npz":
        data = io.read_npz(path, time_unit=args.time_unit or "s", **options)
    else:
        data = io.read_rosbag(path, args.topic, **options)
    print(
        f"read {len(data)} samples over {data.duration:.3f} s at {data.rate_hz:.1f} Hz from "
        f"{data.source} ({fmt})" + ("; with ground truth" if data.ground_truth else "")
    )
    for note in data.repairs:
        print(f"repair: {note}", file=sys.stderr)
    if args.start or args.duration is not None:
        data = data.window(args.start, args.duration)
    return data


def add_input_options(p, formats=("auto", "euroc", "tumvi", "csv", "npz", "rosbag")):
    p.add_argument(
        "file",
        help="EuRoC/TUM-VI sequence folder (mav0/...), imu0/data.csv, a CSV, "
        "an NPZ, or a ROS 1/2 bag",
    )
    g = p.add_argument_group("input")
    g.add_argument(
        "--format", default="auto", choices=formats, help="input format (default: from the path)"
    )
    g.add_argument(
        "--columns",
        default="0,1,2,3,4,5,6",
        metavar="T,WX,WY,WZ,AX,AY,AZ",
        help="CSV columns, indices or header names (default: EuRoC order)",
    )
    g.add_argument(
        "--time-unit",
        default=None,
        choices=["s", "ms", "us", "ns"],
        help="CSV/NPZ time unit (default: the unit the CSV header states, such as "
        "EuRoC's '#timestamp [ns]', else s)",
    )
    add_unit_options(g)
    g.add_argument("--topic", help="ROS bag: the sensor_msgs/Imu topic (default: the only one)")
    g.add_argument("--start", type=float, default=0.0, help="skip this many seconds (≥ 0)")
    g.add_argument("--duration", type=float, default=None, help="use this many seconds (> 0)")
    add_repair_options(p)


def add_unit_options(g):
    """``--gyro-unit`` and ``--accel-unit`` on the argument group ``g``."""
    g.add_argument("--gyro-unit", default="rad/s", choices=["rad/s", "deg/s"])
    g.add_argument("--accel-unit", default="m/s^2", choices=["m/s^2", "g"])


def add_repair_options(p, max_gap: bool = True):
    """The readers' repairs as flags (:func:`reader_options` reads them back); ``max_gap``:
    with ``--max-gap``, the IMU's longest interval (``jaximu learn`` has its own, the ground
    truth's)."""
    r = p.add_argument_group("repairs (off by default: problems are errors)")
    r.add_argument("--sort", action="store_true", help="sort samples by time")
    r.add_argument(
        "--drop-duplicates", action="store_true", help="keep the first of samples with equal stamps"
    )
    r.add_argument("--drop-nonfinite", action="store_true", help="drop rows with NaN/inf")
    gap = "--max-gap" if max_gap else "5 × the median interval"
    r.add_argument("--allow-gaps", action="store_true", help=f"keep gaps longer than {gap}")
    if max_gap:
        r.add_argument(
            "--max-gap",
            type=float,
            default=None,
            help="longest interval [s] (default: 5 × the median)",
        )
    r.add_argument(
        "--no-unit-check",
        action="store_true",
        help="skip the rate and magnitude plausibility checks",
    )


def reader_options(args, max_gap: bool = True) -> dict:
    """The readers' keyword options (units and repairs) from the flags of
    :func:`add_unit_options` and :func:`add_repair_options`."""
    options = {
        "gyro_unit": args.gyro_unit,
        "accel_unit": args.accel_unit,
        "sort": args.sort,
        "drop_duplicates": args.drop_duplicates,
        "drop_nonfinite": args.drop_nonfinite,
        "allow_gaps": args.allow_gaps,
        "check_units": not args.no_unit_check,
    }
    if max_gap:
        options["max_gap"] = args.max_gap
    return options


def add_output_options(p, plot_default=None):
    p.add_argument(
        "--plot",
        default=plot_default,
        metavar="PNG",
        help="write a plot" + (" (default: %(default)s)" if plot_default else ""),
    )
    p.add_argument("--float64", action="store_true", help="compute in float64")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def check_outputs(**paths):
    """Fail before the work, not after it: the output folders exist, the suffixes are known."""
    suffixes = {
        "states": (".csv", ".npz"),
        "plot": (".png", ".pdf", ".svg", ".jpg"),
        "save": (".npz",),
    }
    for name, path in paths.items():
        if not path:
            continue
        p = pathlib.Path(path)
        if p.is_dir():
            raise UsageError(
                f"--{name} {path} is a folder: name a file in it, e.g. "
                f"--{name} {p / ('out' + suffixes.get(name, ('.json',))[0])}"
            )
        if not p.parent.is_dir():
            raise UsageError(f"--{name} {path}: the folder {p.parent} does not exist")
        if name in suffixes and p.suffix.lower() not in suffixes[name]:
            raise UsageError(f"--{name} {path}: use one of {', '.join(suffixes[name])}")


def bias_option(text):
    """``--bias 'BGX BGY BGZ BAX BAY BAZ'``: ``(6,)`` [rad/s, m/s²], or ``None`` when not given."""
    if text is None:
        return None
    vals = [float(x) for x in text.replace(",", " ").split()]
    if len(vals) != 6:
        raise UsageError("--bias needs 6 numbers: b_g (rad/s) x y z, b_a (m/s²) x y z")
    return np.asarray(vals)


def start_at_groundtruth(data, gt, flag=None):
    """The samples from where the ground truth begins; a window that ends before it, or
    starts after it ends, is an error that says so (``flag``: the option that needs the
    ground truth, if one does)."""
    from jaximu import io

    tol = io.CLOCK_TOLERANCE
    drop = f", or drop {flag}" if flag else ""
    inside = (data.t >= gt.t[0] - tol) & (data.t <= gt.t[-1] + tol)
    if inside.sum() >= 2:
        return data if data.t[0] >= gt.t[0] - tol else data.window(gt.t[0] - tol)
    span = f"[{data.t[0]:.3f}, {data.t[-1]:.3f}] s"
    if data.t[-1] < gt.t[0]:
        raise UsageError(
            f"the ground truth starts at {gt.t[0]:.3f} s, after the samples used "
            f"({span}) end: pass --start ≥ {gt.t[0]:.3f} or a longer --duration"
            f"{drop}"
        )
    if data.t[0] > gt.t[-1]:
        raise UsageError(
            f"the ground truth ends at {gt.t[-1]:.3f} s, before the samples used "
            f"({span}) start: pass --start < {gt.t[-1]:.3f}{drop}"
        )
    raise UsageError(
        f"the ground truth ([{gt.t[0]:.3f}, {gt.t[-1]:.3f}] s) and the samples "
        f"used ({span}) share fewer than 2 samples; pass a longer --duration{drop}"
    )
