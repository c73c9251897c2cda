"""The ``jaximu`` command: IMU recordings in, trajectories, uncertainty and plots out.

  jaximu demo                      dead reckoning on bundled real EuRoC data, with a plot
  jaximu propagate FILE            propagate a recording (EuRoC/TUM-VI folder, CSV, NPZ, ROS bag)
  jaximu preintegrate FILE         preintegrate it between keyframes
  jaximu montecarlo                Monte Carlo covariance study on a simulated trajectory
  jaximu calibrate FILE            fit IMU biases (scale, misalignment, …) against ground truth
  jaximu allan FILE                Allan deviation and Kalibr noise densities of a static recording
  jaximu learn train|evaluate      train and evaluate a learned gyro denoiser (jaximu[learning])

User mistakes (a missing file, a malformed CSV, bad options) end with one line on stderr and
exit code 2; ``jaximu COMMAND --help`` describes each command.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import time
import warnings

import numpy as np

# the library code the command runs (re-exported: jaximu.cli.run_demo and
# jaximu.cli.propagate_recording stay importable)
from jaximu.recording import DEMO_SCHEMES, DEMO_SECONDS, NOISE_PRESETS  # noqa: F401
from jaximu.recording import default_P0 as _default_P0
from jaximu.recording import noise_preset as _noise
from jaximu.recording import propagate_recording, run_demo  # noqa: F401
from jaximu.recording import save_plot as _plot_or_say

REPORT_AT = (1, 2, 5, 10, 20, 30, 60, 120, 300, 600)


class UsageError(ValueError):
    """A mistake in the command line."""


# --------------------------------------------------------------------------- helpers


def _dtype(args):
    import jax
    import jax.numpy as jnp

    if getattr(args, "float64", False):
        if not jax.config.jax_enable_x64:
            jax.config.update("jax_enable_x64", True)  # the user asked for it on the command line
        return jnp.float64
    return jnp.result_type(float)


def _sensor_and_world(args, rate_hz=None):
    """``--body-P-sensor`` and ``--earth-rate``: ``(body_P_sensor, omega_coriolis, noise)``
    (``noise``: the YAML's densities, which replace ``--noise``, or ``None``)."""
    import jaximu
    from jaximu import kalibr

    pose = noise = omega = None
    if getattr(args, "body_P_sensor", None):
        cfg = kalibr.parse_body_P_sensor(args.body_P_sensor)
        pose, noise = cfg.body_P_sensor, cfg.noise
        if pose is not None:
            print(f"IMU pose on the body from {cfg.source}: q_BS = "
                  f"{np.array2string(np.asarray(pose.q), precision=6)}, p_BS = "
                  f"{np.array2string(np.asarray(pose.p), precision=4)} m")
        if noise is not None:
            print(f"noise densities from {cfg.source} (they replace --noise)")
        if cfg.rate_hz and rate_hz and abs(cfg.rate_hz - rate_hz) > 0.05 * rate_hz:
            print(f"note: the YAML's rate {cfg.rate_hz:g} Hz differs from the recording's "
                  f"{rate_hz:.1f} Hz")
    if getattr(args, "earth_rate", None) is not None:
        omega = np.asarray(jaximu.earth_rate(args.earth_rate), np.float64)
        print(f"rotating world: Earth's rate at latitude {args.earth_rate:g}° (east-north-up) "
              f"{np.array2string(omega, precision=4)} rad/s")
    return pose, omega, noise


def _check_earth_rate(args):
    """``--earth-rate``: a latitude in [-90, 90] degrees, checked before the work (reading
    the data) and named by its flag."""
    lat = getattr(args, "earth_rate", None)
    if lat is not None and not (np.isfinite(lat) and abs(lat) <= 90):
        raise UsageError(f"--earth-rate is a latitude in degrees, in [-90, 90]; got {lat:g}")


def _add_sensor_options(p):
    g = p.add_argument_group("sensor pose and rotating world")
    g.add_argument("--body-P-sensor", metavar="QW,QX,QY,QZ,PX,PY,PZ|YAML",
                   help="the IMU's pose in the body frame: q_BS (Hamilton) and the lever arm "
                   "p_BS [m]; or an EuRoC sensor.yaml (T_BS) or Kalibr camchain (cam0 "
                   "T_cam_imu: the camera is the body) / imu.yaml, whose noise densities "
                   "replace --noise")
    g.add_argument("--earth-rate", type=float, metavar="LAT",
                   help="latitude [°] of the local east-north-up world: Earth's rotation "
                   "(Coriolis and centrifugal, exact transition) at it")


def _detect_format(path: pathlib.Path) -> str:
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


def _load(args):
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
    fmt = args.format if args.format != "auto" else _detect_format(path)
    repair = dict(sort=args.sort, drop_duplicates=args.drop_duplicates,
                  drop_nonfinite=args.drop_nonfinite, allow_gaps=args.allow_gaps,
                  max_gap=args.max_gap, check_units=not args.no_unit_check)
    units = dict(gyro_unit=args.gyro_unit, accel_unit=args.accel_unit)
    if args.topic is not None and fmt != "rosbag":
        raise UsageError(f"--topic names a ROS bag's topic; {path} is read as {fmt}: drop "
                         "--topic (or pass --format rosbag for a bag)")
    if args.time_unit is not None and fmt not in ("csv", "npz"):
        raise UsageError(f"--time-unit applies to CSV and NPZ input, not {fmt} (stamps in ns)")
    if fmt in ("euroc", "tumvi"):  # SI by definition; the units flags for other ASL folders
        data = (io.read_euroc if fmt == "euroc" else io.read_tumvi)(path, **units, **repair)
    elif fmt == "csv":
        cols = [c.strip() for c in args.columns.split(",")]
        if len(cols) != 7:
            raise UsageError("--columns needs 7 comma-separated columns: t,wx,wy,wz,ax,ay,az")
        cols = [int(c) if c.lstrip("-").isdigit() else c for c in cols]
        data = io.read_csv(path, time=cols[0], gyro=cols[1:4], accel=cols[4:7],
                           time_unit=args.time_unit, **units, **repair)
    elif fmt == "npz":
        data = io.read_npz(path, time_unit=args.time_unit or "s", **units, **repair)
    else:
        data = io.read_rosbag(path, args.topic, **units, **repair)
    print(f"read {len(data)} samples over {data.duration:.3f} s at {data.rate_hz:.1f} Hz from "
          f"{data.source} ({fmt})" + ("; with ground truth" if data.ground_truth else ""))
    for note in data.repairs:
        print(f"repair: {note}", file=sys.stderr)
    if args.start or args.duration is not None:
        data = data.window(args.start, args.duration)
    return data


def _add_input_options(p, formats=("auto", "euroc", "tumvi", "csv", "npz", "rosbag")):
    p.add_argument("file", help="EuRoC/TUM-VI sequence folder (mav0/...), imu0/data.csv, a CSV, "
                   "an NPZ, or a ROS 1/2 bag")
    g = p.add_argument_group("input")
    g.add_argument("--format", default="auto", choices=formats,
                   help="input format (default: from the path)")
    g.add_argument("--columns", default="0,1,2,3,4,5,6", metavar="T,WX,WY,WZ,AX,AY,AZ",
                   help="CSV columns, indices or header names (default: EuRoC order)")
    g.add_argument("--time-unit", default=None, choices=["s", "ms", "us", "ns"],
                   help="CSV/NPZ time unit (default: the unit the CSV header states, such as "
                   "EuRoC's '#timestamp [ns]', else s)")
    g.add_argument("--gyro-unit", default="rad/s", choices=["rad/s", "deg/s"])
    g.add_argument("--accel-unit", default="m/s^2", choices=["m/s^2", "g"])
    g.add_argument("--topic", help="ROS bag: the sensor_msgs/Imu topic (default: the only one)")
    g.add_argument("--start", type=float, default=0.0, help="skip this many seconds (≥ 0)")
    g.add_argument("--duration", type=float, default=None, help="use this many seconds (> 0)")
    r = p.add_argument_group("repairs (off by default: problems are errors)")
    r.add_argument("--sort", action="store_true", help="sort samples by time")
    r.add_argument("--drop-duplicates", action="store_true",
                   help="keep the first of samples with equal stamps")
    r.add_argument("--drop-nonfinite", action="store_true", help="drop rows with NaN/inf")
    r.add_argument("--allow-gaps", action="store_true", help="keep gaps longer than --max-gap")
    r.add_argument("--max-gap", type=float, default=None,
                   help="longest interval [s] (default: 5 × the median)")
    r.add_argument("--no-unit-check", action="store_true",
                   help="skip the rate and magnitude plausibility checks")


def _add_output_options(p, plot_default=None):
    p.add_argument("--plot", default=plot_default, metavar="PNG",
                   help="write a plot" + (" (default: %(default)s)" if plot_default else ""))
    p.add_argument("--float64", action="store_true", help="compute in float64")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _check_outputs(**paths):
    """Fail before the work, not after it: the output folders exist, the suffixes are known."""
    suffixes = {"states": (".csv", ".npz"), "plot": (".png", ".pdf", ".svg", ".jpg"),
                "save": (".npz",), "imu-yaml": (".yaml", ".yml")}
    for name, path in paths.items():
        if not path:
            continue
        p = pathlib.Path(path)
        if p.is_dir():
            raise UsageError(f"--{name} {path} is a folder: name a file in it, e.g. "
                             f"--{name} {p / ('out' + suffixes.get(name, ('.json',))[0])}")
        if not p.parent.is_dir():
            raise UsageError(f"--{name} {path}: the folder {p.parent} does not exist")
        if name in suffixes and p.suffix.lower() not in suffixes[name]:
            raise UsageError(f"--{name} {path}: use one of {', '.join(suffixes[name])}")


def _bias(text):
    if text is None:
        return None
    vals = [float(x) for x in text.replace(",", " ").split()]
    if len(vals) != 6:
        raise UsageError("--bias needs 6 numbers: b_g (rad/s) x y z, b_a (m/s²) x y z")
    return np.asarray(vals)


# --------------------------------------------------------------------------- propagation


def _check_gravity(g, dtype):
    """``--gravity``: a finite magnitude ≥ 0, checked before the work (the propagation runs
    under ``jit``, where the library's own check cannot run), in the computation ``dtype``
    (float64 without x64 would be truncated, with a JAX warning)."""
    from jaximu import _validation as val

    if not np.isfinite(g):
        raise UsageError(f"--gravity must be a finite magnitude ≥ 0 [m/s²], got {g}")
    val.gravity_vector(g, dtype)  # a negative magnitude: an error whose fix is a flag


def _start_at_groundtruth(data, gt, flag=None):
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
        raise UsageError(f"the ground truth starts at {gt.t[0]:.3f} s, after the samples used "
                         f"({span}) end: pass --start ≥ {gt.t[0]:.3f} or a longer --duration"
                         f"{drop}")
    if data.t[0] > gt.t[-1]:
        raise UsageError(f"the ground truth ends at {gt.t[-1]:.3f} s, before the samples used "
                         f"({span}) start: pass --start < {gt.t[-1]:.3f}{drop}")
    raise UsageError(f"the ground truth ([{gt.t[0]:.3f}, {gt.t[-1]:.3f}] s) and the samples "
                     f"used ({span}) share fewer than 2 samples; pass a longer --duration{drop}")


def _report_drift(err, t_start, out=None):
    """Print the error against ground truth at 1, 2, 5, … s after ``t_start`` (the start of
    the propagation) and the drift per second, where the ground truth covers those times."""
    out = out if out is not None else sys.stdout
    lo, hi = float(err.t[0] - t_start), float(err.t[-1] - t_start)
    marks = [s for s in REPORT_AT if lo - 0.01 <= s <= hi + 1e-6]
    if not marks:
        print(f"(the ground truth covers {lo:.2f}–{hi:.2f} s after the start: no table)",
              file=out)
        return marks
    has_v = err.velocity is not None
    print(f"\n{'t [s]':>8}{'position [m]':>15}{'velocity [m/s]':>16}{'attitude [°]':>14}"
          f"{'drift [m/s]':>13}", file=out)
    for s in marks:
        pos, vel, att = err.at(s, t_start)
        vel_text = f"{vel:.3f}" if has_v else "–"
        print(f"{s:>8g}{pos:>15.3f}{vel_text:>16}{att:>14.3f}{pos / s:>13.3f}", file=out)
    return marks


def cmd_propagate(args):
    import jax

    from jaximu import io

    dtype = _dtype(args)
    _check_gravity(args.gravity, dtype)
    if not args.still > 0:
        raise UsageError(f"--still must be positive (seconds of still samples), got {args.still}")
    _check_outputs(out=args.out, states=args.states, plot=args.plot)
    data = _load(args)
    if args.init_from_groundtruth:
        gt = data.ground_truth
        if gt is None:
            raise UsageError(f"{args.file} has no ground truth: drop --init-from-groundtruth")
        data = _start_at_groundtruth(data, gt, "--init-from-groundtruth")
    state0, how = io.initial_state(data, from_groundtruth=args.init_from_groundtruth,
                                   still_seconds=args.still, bias=_bias(args.bias))
    print(how)
    noise = _noise(args.noise)
    pose, omega, yaml_noise = _sensor_and_world(args, data.rate_hz)
    noise = yaml_noise or noise
    P0 = _default_P0(args.init_from_groundtruth)
    tic = time.perf_counter()
    t, states, cov = propagate_recording(data, state0, P0, noise, args.scheme, dtype,
                                         gravity=args.gravity, progress=not args.no_progress,
                                         body_P_sensor=pose, omega_coriolis=omega)
    elapsed = time.perf_counter() - tic
    print(f"propagated {len(data.dt)} steps ({args.scheme}, {np.dtype(dtype).name}, "
          f"{jax.default_backend()}) in {elapsed:.2f} s including compilation")
    s_end = np.sqrt(np.diag(cov[-1]))
    print(f"final position {np.array2string(states.p[-1], precision=3)} m, 1σ "
          f"{np.array2string(s_end[3:6], precision=3)} m; attitude 1σ "
          f"{np.array2string(np.rad2deg(s_end[0:3]), precision=2)}°")
    if data.ground_truth is not None:
        try:
            err = io.trajectory_errors(t, states, data.ground_truth, cov)
        except io.DataError as e:  # no overlap: the trajectory is still written
            print(f"no comparison with the ground truth: {e}")
        else:
            kind = "from the ground-truth state" if args.init_from_groundtruth else \
                "(not initialised from it: expect an offset; use --init-from-groundtruth)"
            print(f"against ground truth {kind}:")
            _report_drift(err, float(t[0]))
    if args.out:
        io.write_tum(args.out, t, states, t0_ns=data.t0_ns)
        print(f"trajectory written to {args.out} (TUM format: t tx ty tz qx qy qz qw)")
    if args.states:
        io.write_states(args.states, t, states, cov, t0_ns=data.t0_ns)
        print(f"states and covariances written to {args.states}")

    def make():
        from jaximu.plots import plot_trajectory

        return plot_trajectory(t, states, data.ground_truth, cov, label=f"jaximu {args.scheme}",
                               title=f"jaximu propagate: {pathlib.Path(args.file).name}")
    _plot_or_say(make, args.plot)
    return 0


# --------------------------------------------------------------------------- demo


def cmd_demo(args):
    if not args.seconds > 0:
        raise UsageError("--seconds must be positive")
    if not args.seconds <= DEMO_SECONDS:
        raise UsageError(f"--seconds {args.seconds:g}: the bundled excerpt holds {DEMO_SECONDS:g} s "
                         f"of ground truth; pass --seconds ≤ {DEMO_SECONDS:g}")
    if not args.no_plot:
        _check_outputs(plot=args.plot)
    run_demo(args.seconds, args.scheme, None if args.no_plot else args.plot,
             progress=not args.no_progress)
    return 0


# --------------------------------------------------------------------------- preintegration


def _in_groundtruth_gap(gt, t):
    """Which of the times ``t`` (inside the ground truth) fall in one of its gaps, by the
    rule :meth:`jaximu.io.GroundTruth.interpolate` refuses them with (default ``max_gap``)."""
    from jaximu.io._common import in_gap

    return in_gap(gt.t, np.clip(t, gt.t[0], gt.t[-1]))[0]


def cmd_preintegrate(args):
    import jax
    import jax.numpy as jnp

    import jaximu
    from jaximu import io

    _check_outputs(out=args.out)
    if not args.window > 0:
        raise UsageError("--window must be positive")
    data = _load(args)
    dtype = _dtype(args)
    n = int(round(args.window * data.rate_hz))
    if n < 2:
        raise UsageError(f"--window {args.window} s holds fewer than 2 samples")
    K = len(data.dt) // n
    if K < 1:
        raise UsageError(f"the recording ({data.duration:.2f} s) is shorter than one window")
    gt = data.ground_truth
    bias = _bias(args.bias)
    how = "given" if bias is not None else "zero"
    if bias is None and args.bias_from_groundtruth:
        if gt is None or gt.b_g is None:
            raise UsageError("--bias-from-groundtruth: the ground truth has no biases")
        k = np.clip(np.searchsorted(gt.t, data.t[0]), 0, len(gt.t) - 1)
        bias, how = np.r_[gt.b_g[k], gt.b_a[k]], "from the ground truth"
    bias = np.zeros(6) if bias is None else bias
    # n + 1 samples per window, the last shared with the next window: the midpoint scheme
    # then averages the boundary samples as propagate does (interval form of dt)
    idx = np.arange(K)[:, None] * n + np.arange(n + 1)
    gyro = jnp.asarray(data.gyro[idx], dtype)
    accel = jnp.asarray(data.accel[idx], dtype)
    dt = jnp.asarray(data.dt[: K * n].reshape(K, n), dtype)
    b = jaximu.ImuBias(jnp.asarray(bias[:3], dtype), jnp.asarray(bias[3:], dtype))
    print(f"{K} windows of {n} samples ({args.window:g} s), scheme {args.scheme}, biases {how}")
    pose, omega, yaml_noise = _sensor_and_world(args, data.rate_hz)
    tic = time.perf_counter()
    pim = jaximu.preintegrate(gyro, accel, dt, b, yaml_noise or _noise(args.noise), args.scheme,
                              method=args.method, body_P_sensor=pose)
    pim.delta_p.block_until_ready()
    print(f"preintegrated in {time.perf_counter() - tic:.2f} s including compilation")
    angle = np.rad2deg(2 * np.arccos(np.clip(np.abs(np.asarray(pim.delta_q)[:, 0]), 0, 1)))
    sig = np.sqrt(np.diagonal(np.asarray(pim.cov, np.float64), axis1=1, axis2=2))
    print(f"\n{'window':>6}{'t0 [s]':>9}{'|ΔR| [°]':>10}{'|Δv| [m/s]':>12}{'|Δp| [m]':>10}"
          f"{'σθ [°]':>9}{'σp [m]':>9}{'σv [m/s]':>10}")
    for k in list(range(min(K, 5))) + ([K - 1] if K > 5 else []):
        print(f"{k:>6}{data.t[k * n]:>9.3f}{angle[k]:>10.3f}"
              f"{np.linalg.norm(np.asarray(pim.delta_v)[k]):>12.4f}"
              f"{np.linalg.norm(np.asarray(pim.delta_p)[k]):>10.4f}"
              f"{np.rad2deg(sig[k, 0]):>9.4f}{sig[k, 3]:>9.5f}{sig[k, 6]:>10.5f}")
    if args.out:
        np.savez(args.out, stamp_i_ns=data.stamps_ns[0:K * n:n],
                 stamp_j_ns=data.stamps_ns[n:K * n + 1:n],
                 **{name: np.asarray(getattr(pim, name)) for name in
                    ("delta_t", "delta_q", "delta_v", "delta_p", "cov", "cov15", "dR_dbg",
                     "dv_dbg", "dv_dba", "dp_dbg", "dp_dba")},
                 bias=bias)
        print(f"preintegrated measurements written to {args.out}")
    ti, tj = data.t[0:K * n:n], data.t[n:K * n + 1:n]
    inside = np.ones(K, bool) if gt is None else (
        (ti >= gt.t[0] - io.CLOCK_TOLERANCE) & (tj <= gt.t[-1] + io.CLOCK_TOLERANCE))
    if gt is not None and gt.v is not None and inside.any():
        # windows with an end in a ground-truth gap (a mocap dropout) are left out: the
        # ground truth there would be interpolated across the gap
        in_gap = inside & (_in_groundtruth_gap(gt, ti) | _in_groundtruth_gap(gt, tj))
        use = inside & ~in_gap
        skipped = (f"; {int(in_gap.sum())} window(s) with an end in a ground-truth gap left "
                   "out" if in_gap.any() else "")
        if not use.any():
            print(f"\nno comparison with the ground truth: each of the {int(inside.sum())} "
                  "windows inside it has an end in one of its gaps")
            return 0
        ti, tj = ti[use], tj[use]
        states = []
        for tt in (ti, tj):
            q, p, v = gt.interpolate(tt)
            states.append(jaximu.NavState(*(jnp.asarray(x, dtype) for x in (q, p, v)),
                                          b.b_g, b.b_a))
        sel = jax.tree_util.tree_map(lambda x: x[np.flatnonzero(use)], pim)
        r = np.asarray(jaximu.residual(states[0], states[1], sel, omega_coriolis=omega),
                       np.float64)
        print(f"\nresiduals against the ground truth (median over the {int(use.sum())} "
              f"windows inside it{skipped}): rotation "
              f"{np.rad2deg(np.median(np.linalg.norm(r[:, 0:3], axis=1))):.3f}°, position "
              f"{np.median(np.linalg.norm(r[:, 3:6], axis=1)):.4f} m, velocity "
              f"{np.median(np.linalg.norm(r[:, 6:9], axis=1)):.4f} m/s")
    return 0


# --------------------------------------------------------------------------- Monte Carlo


FIX_SIGMA = 0.05
"""``--fix-sigma``'s default [m]."""


def cmd_montecarlo(args):
    import jax
    import jax.numpy as jnp

    from jaximu import montecarlo, simulate

    if args.runs < 2:
        raise UsageError(f"--runs must be ≥ 2, got {args.runs}")
    for flag, x in (("--seconds", args.seconds), ("--rate", args.rate)):
        if not 0 < x < 1e6:
            raise UsageError(f"{flag} must be positive and finite (below 1e6), got {x:g}")
    if args.seconds * args.rate < 1:
        raise UsageError(f"--seconds {args.seconds:g} at --rate {args.rate:g} Hz holds no sample "
                         f"interval; pass --seconds ≥ {1 / args.rate:g} or a higher --rate")
    _check_outputs(plot=args.plot, save=args.save)
    dtype = _dtype(args)
    traj = {"circle": simulate.circle, "figure-eight": simulate.figure_eight,
            "lissajous": simulate.lissajous, "helix": simulate.helix}[args.trajectory]()
    n = int(round(args.seconds * args.rate))
    times = jnp.arange(n + 1, dtype=dtype) / args.rate
    sig = np.r_[[np.deg2rad(0.1)] * 3, [0.01] * 3, [0.01] * 3, [1e-4] * 3, [1e-3] * 3]
    P0 = jnp.asarray(np.diag(sig**2), dtype)
    if args.filter is not None and args.filter < 1:
        raise UsageError(f"--filter must be a number of samples ≥ 1, got {args.filter}")
    if args.filter is not None and args.filter > n:
        raise UsageError(f"--filter {args.filter} is more than the {n} samples of --seconds "
                         f"{args.seconds:g} at --rate {args.rate:g} Hz: no fix would happen; "
                         f"pass at most --filter {n}")
    if args.fix_sigma is not None and args.filter is None:
        raise UsageError("--fix-sigma is the position fix of the filter study; pass --filter N "
                         "too (a fix every N samples), or drop --fix-sigma")
    fix_sigma = FIX_SIGMA if args.fix_sigma is None else args.fix_sigma
    if not (fix_sigma > 0 and np.isfinite(fix_sigma)):
        raise UsageError(f"--fix-sigma must be positive and finite, got {fix_sigma:g}")
    say = print if jax.process_index() == 0 else (lambda *a, **k: None)  # one report
    say(f"Monte Carlo: {args.runs} runs of {args.seconds:g} s of {args.trajectory} at "
        f"{args.rate:g} Hz, noise {args.noise}, scheme {args.scheme} "
        f"({np.dtype(dtype).name}, {jax.local_device_count()} {jax.default_backend()} device(s)"
        f"{f' × {jax.process_count()} processes' if jax.process_count() > 1 else ''})"
        + (f"; filter: position fix (σ {fix_sigma:g} m) every {args.filter} samples"
           if args.filter else ""))
    tic = time.perf_counter()
    res = montecarlo.monte_carlo(traj, times, P0, _noise(args.noise), args.runs,
                                 jax.random.PRNGKey(args.seed), scheme=args.scheme,
                                 record_every=max(1, n // 50), update_every=args.filter,
                                 measurement=montecarlo.PositionFix(fix_sigma)
                                 if args.filter else None,
                                 progress=not args.no_progress and jax.process_index() == 0,
                                 dtype=dtype)
    say(f"done in {time.perf_counter() - tic:.2f} s including compilation")
    lo, hi = res.nees_bounds
    inside = float(np.mean(res.consistent))
    say(f"average NEES at the end {res.nees_mean[-1]:.2f} (expected 15, "
        f"{100 * res.confidence:.0f}% interval [{lo:.2f}, {hi:.2f}]); inside the interval at "
        f"{100 * inside:.0f}% of the recorded times")
    if res.nis_mean is not None:
        ok = np.isfinite(res.nis_mean)
        nlo, nhi = res.nis_bounds
        say(f"average NIS at the last update {res.nis_mean[ok][-1]:.2f} (expected 3, "
            f"interval [{nlo:.2f}, {nhi:.2f}]); inside at "
            f"{100 * np.mean((res.nis_mean[ok] >= nlo) & (res.nis_mean[ok] <= nhi)):.0f}% of "
            "the updates")
    names = ("attitude [°]", "position [m]", "velocity [m/s]")
    what = "filter" if args.filter else "predicted"
    for name, i0, scale in zip(names, (0, 3, 6), (np.rad2deg(1.0), 1.0, 1.0)):
        pred = np.sqrt(np.diag(res.predicted_cov[-1])[i0:i0 + 3]) * scale
        emp = np.sqrt(np.diag(res.error_cov[-1])[i0:i0 + 3]) * scale
        say(f"final 1σ {name:<15} {what} {np.array2string(pred, precision=4)}"
            f"  Monte Carlo {np.array2string(emp, precision=4)}")
    if args.save and jax.process_index() == 0:
        res.save(args.save)
        say(f"wrote {args.save}")

    def make():
        from jaximu.plots import plot_monte_carlo

        return plot_monte_carlo(res)
    _plot_or_say(make, args.plot)
    return 0


# --------------------------------------------------------------------------- calibration


class _warnings_as_lines:
    """The library's warnings (a χ²/dof above its limit, a rotation the motion does not
    determine) as one ``warning:`` line each on stderr, without Python's file and source
    lines."""

    def __enter__(self):
        self._ctx = warnings.catch_warnings(record=True)
        self._caught = self._ctx.__enter__()
        for category in (RuntimeWarning, UserWarning):  # shown once each, as a line
            warnings.simplefilter("always", category)
        return self

    def __exit__(self, *exc):
        self._ctx.__exit__(*exc)
        for w in self._caught:
            print(f"warning: {w.message}", file=sys.stderr)
        return False


# --------------------------------------------------------------------------- Allan deviation


def _motion_ratio(y, dt, window=1.0):
    """The spread of the ``window``-second means over the spread of the samples (largest over
    the axes): ≈ ``1/√(window/dt)`` for white noise, ≈ 1 for motion."""
    m = max(1, int(round(window / dt)))
    n = len(y) // m
    if n < 2:
        return 0.0  # too short to judge
    means = y[:n * m].reshape(n, m, -1).mean(1)
    return float(np.max(means.std(0) / np.maximum(y.std(0), 1e-300)))


def cmd_allan(args):
    from jaximu import allan

    _check_outputs(plot=args.plot)
    data = _load(args)
    dt = float(np.median(data.dt))
    jitter = float(np.max(np.abs(data.dt - dt)) / dt)
    if jitter > 0.05:
        print(f"note: sample intervals vary by up to {100 * jitter:.0f}% of the median; the "
              "Allan deviation assumes a constant rate")
    # Static means the gyro is white noise about its bias: 1 s means vary √(rate) times less
    # than the samples (≈ 0.07 at 200 Hz); motion varies slowly and survives the averaging.
    # (The spread of the samples cannot tell: a still gyro in deg/s spreads 57× more.)
    moving = _motion_ratio(data.gyro, dt)
    static = moving < 0.3
    if not static:
        print(f"note: the gyro's 1 s means vary by {100 * moving:.0f}% of its sample spread: the "
              "recording does not look static, so the densities below include motion")
    print(f"Allan deviation of {len(data)} samples ({data.duration:.1f} s at {1 / dt:.1f} Hz)")
    for name, y in (("gyro", data.gyro), ("accelerometer", data.accel)):
        flat = np.flatnonzero(np.ptp(y, axis=0) == 0)
        if len(flat):
            raise UsageError(f"the {name}'s {'xyz'[flat[0]]} axis is constant in {args.file} "
                             f"({y[0, flat[0]]:g} in every sample): the Allan deviation measures "
                             "noise, and this signal has none (a simulated or quantised file?)")
    results = {}
    for name, y, unit in (("gyroscope", data.gyro, "rad/s"), ("accelerometer", data.accel, "m/s²")):
        taus, adev = allan.allan_deviation(y, dt)
        fit = allan.fit_noise(taus, adev)
        results[name] = (taus, adev, fit, unit)
    if static and not args.no_unit_check:  # motion would inflate the densities
        allan.check_units(results["gyroscope"][2], results["accelerometer"][2])
    def shown(values, determined):  # a density the fit could not determine is no 0
        pairs = zip(np.atleast_1d(values), np.atleast_1d(determined))
        return "[" + " ".join(f"{v:.4g}" if ok else "not-determined" for v, ok in pairs) + "]"

    for name, (taus, adev, fit, unit) in results.items():
        print(f"{name}_noise_density: {shown(fit.white, fit.white_determined)}"
              f"   # {unit}/√Hz (x, y, z)")
        print(f"{name}_random_walk:   {shown(fit.random_walk, fit.random_walk_determined)}"
              f"   # {unit}·√Hz")
    if not all(np.all(f.white_determined) and np.all(f.random_walk_determined)
               for _, _, f, _ in results.values()):
        print("note: not-determined: the Allan deviation does not show that term on that axis "
              "(motion, or too short a recording); no density is given for it")
    if data.duration < 600:
        print("note: random walks need a long static recording (hours); this one is "
              f"{data.duration:.0f} s, so they are rough")

    def make():
        import matplotlib.pyplot as plt

        from jaximu.plots import plot_allan

        fig, axes = plt.subplots(1, 2, figsize=(13, 5))
        for ax, (name, (taus, adev, fit, unit)) in zip(axes, results.items()):
            plot_allan(taus, adev, fit, ax=ax, unit=unit, title=f"{name}")
        fig.tight_layout()
        return fig
    _plot_or_say(make, args.plot)
    return 0


# --------------------------------------------------------------------------- parser


def build_parser():
    parser = argparse.ArgumentParser(
        prog="jaximu", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1])
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("demo", help="dead reckoning on bundled real EuRoC data, with a plot",
                       description="Propagate the bundled 20 s EuRoC MAV V1_02_medium excerpt "
                       "from the ground-truth state with the ground-truth biases, with every "
                       "scheme; print the drift against ground truth; write a plot.")
    p.add_argument("--seconds", type=float, default=20.0,
                   help="length to propagate, 0 < s ≤ 20 (the excerpt's ground truth)")
    p.add_argument("--scheme", default="midpoint", choices=DEMO_SCHEMES)
    p.add_argument("--plot", default="jaximu_demo.png", help="output PNG (default: %(default)s)")
    p.add_argument("--no-plot", action="store_true", help="do not write a plot")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("propagate", help="propagate a recording: trajectory, covariance, plot",
                       description="Propagate state and 15×15 covariance through a recording. "
                       "Without --init-from-groundtruth the attitude comes from gravity "
                       "alignment of the first still samples (yaw 0), position and velocity "
                       "are zero, and biases zero unless --bias is given.")
    _add_input_options(p)
    p.add_argument("--scheme", default="midpoint", choices=DEMO_SCHEMES)
    p.add_argument("--init-from-groundtruth", action="store_true",
                   help="start from the ground-truth pose, velocity and biases")
    p.add_argument("--bias", metavar="'BGX BGY BGZ BAX BAY BAZ'",
                   help="biases [rad/s, m/s²] (overrides the ground truth's)")
    p.add_argument("--still", type=float, default=1.0,  # > 0
                   help="seconds of still samples for gravity alignment (default: %(default)s)")
    p.add_argument("--noise", default="euroc", choices=NOISE_PRESETS,
                   help="noise densities for the covariance (default: %(default)s)")
    p.add_argument("--gravity", type=float, default=9.81, help="gravity magnitude g ≥ 0 [m/s²] (g_W = [0, 0, -g]; default: "
                   "%(default)s)")
    p.add_argument("--out", metavar="TUM", help="write the trajectory in TUM format (for evo)")
    p.add_argument("--states", metavar="CSV|NPZ", help="write states and covariances")
    _add_sensor_options(p)
    _add_output_options(p)
    p.set_defaults(func=cmd_propagate)

    p = sub.add_parser("preintegrate", help="preintegrate a recording between keyframes",
                       description="Cut the recording into windows and preintegrate each "
                       "(deltas, 9×9 and 15×15 covariances, bias Jacobians); compare with the "
                       "ground truth when it has velocities.")
    _add_input_options(p)
    p.add_argument("--window", type=float, default=0.5, help="seconds per window (> 0, at least 2 samples)")
    p.add_argument("--scheme", default="euler", choices=["euler", "midpoint"])
    p.add_argument("--method", default="auto", choices=["auto", "sequential", "parallel"],
                   help="auto (default): the fastest for the windows; all give the same numbers")
    p.add_argument("--bias", metavar="'BGX BGY BGZ BAX BAY BAZ'", help="biases [rad/s, m/s²]")
    p.add_argument("--bias-from-groundtruth", action="store_true",
                   help="use the ground truth's bias estimate")
    p.add_argument("--noise", default="euroc", choices=NOISE_PRESETS)
    p.add_argument("--out", metavar="NPZ", help="write the preintegrated measurements")
    p.add_argument("--float64", action="store_true", help="compute in float64")
    _add_sensor_options(p)
    p.set_defaults(func=cmd_preintegrate)

    p = sub.add_parser("montecarlo", help="Monte Carlo covariance study on a simulated trajectory",
                       description="Draw noisy IMU copies of a simulated trajectory, propagate "
                       "them, and compare the sample error covariance with the linearised one "
                       "(NEES with its χ² interval).")
    p.add_argument("--trajectory", default="figure-eight",
                   choices=["circle", "figure-eight", "lissajous", "helix"])
    p.add_argument("--runs", type=int, default=1000, help="Monte Carlo runs (≥ 2)")
    p.add_argument("--seconds", type=float, default=10.0,
                   help="trajectory length (> 0, at least one sample interval)")
    p.add_argument("--rate", type=float, default=200.0, help="IMU rate [Hz] (> 0)")
    p.add_argument("--noise", default="euroc", choices=NOISE_PRESETS)
    p.add_argument("--scheme", default="euler", choices=DEMO_SCHEMES)
    p.add_argument("--seed", type=int, default=0, help="PRNG seed (any integer)")
    p.add_argument("--filter", type=int, metavar="N", default=None,
                   help="filter study: every run propagates its own covariance and takes a "
                   "position fix every N samples (error-state EKF, Joseph form); NEES and NIS")
    p.add_argument("--fix-sigma", type=float, default=None,
                   help=f"position fix standard deviation [m] (> 0; default {FIX_SIGMA}); "
                   "only with --filter")
    p.add_argument("--save", metavar="NPZ",
                   help="write the result with its settings (jaximu.montecarlo.load_result)")
    _add_output_options(p)
    p.set_defaults(func=cmd_montecarlo)

    from jaximu import cli_calibrate

    cli_calibrate.add_parser(sub)

    p = sub.add_parser("allan", help="Allan deviation and noise densities of a static recording",
                       description="Overlapping Allan deviation of the gyro and accelerometer, "
                       "and the fitted white-noise and random-walk densities (Kalibr units).")
    _add_input_options(p)
    p.add_argument("--plot", metavar="PNG", help="write a plot")
    p.set_defaults(func=cmd_allan)
    from jaximu import cli_learn

    cli_learn.add_parser(sub)
    return parser


def options_table() -> str:
    """Markdown of every command's options (flag, accepts, default, help), generated from
    the parser: the "what each function accepts" document embeds it, and a test keeps the
    two equal."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    lines = []
    commands = []
    for name, p in sub.choices.items():  # `jaximu learn train`: a subcommand's actions too
        nested = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        commands += ([(f"{name} {n}", q) for a in nested for n, q in a.choices.items()]
                     if nested else [(name, p)])
    for name, p in commands:
        lines += [f"### `jaximu {name}`", "", "| option | accepts | default | meaning |",
                  "|---|---|---|---|"]
        for a in p._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            flag = ", ".join(a.option_strings) or a.dest
            if a.choices:
                accepts = " ".join(f"`{c}`" for c in a.choices)
            elif a.nargs == 0:
                accepts = "flag"
            else:
                accepts = {float: "number", int: "integer"}.get(a.type, "text")
            default = "" if a.default is None or a.nargs == 0 else f"`{a.default}`"
            text = (a.help or "").replace("%(default)s", str(a.default)).replace("|", "/")
            lines.append(f"| `{flag}` | {accepts} | {default} | {text} |")
        lines.append("")
    return "\n".join(lines)


# The library's errors carry their repairs as data (jaximu.errors.Fix: option and value); on
# the command line they are flags.
FLAGS = {"gyro_unit": "--gyro-unit", "accel_unit": "--accel-unit", "time_unit": "--time-unit",
         "sort": "--sort", "drop_duplicates": "--drop-duplicates",
         "drop_nonfinite": "--drop-nonfinite", "allow_gaps": "--allow-gaps",
         "max_gap": "--max-gap", "gravity": "--gravity",
         "keyframe_interval": "--keyframe-interval", "seconds": "--seconds",
         "update_every": "--filter"}
INVERTED_FLAGS = {("check_units", False): "--no-unit-check"}
API_ONLY_OPTIONS = frozenset({"measurement", "path"})
"""Options the library's fixes may name that have no flag (rendered as keywords):
``monte_carlo``'s ``measurement`` (the command builds it from ``--fix-sigma``) and
``MonteCarloResult.save``'s ``path`` (``--save`` is checked by the command first)."""


def flag_of(fix) -> str:
    """A :class:`jaximu.errors.Fix` as the command's flag: ``--gyro-unit deg/s``, ``--sort``."""
    from jaximu.errors import ANY

    inverted = INVERTED_FLAGS.get((fix.option, fix.value))
    if inverted:
        return inverted
    flag = FLAGS.get(fix.option)
    if flag is None:
        return fix.as_keyword()
    if fix.value is ANY:
        return fix.describe(flag)
    if fix.value is True:
        return flag
    return f"{flag} {fix.value:g}" if isinstance(fix.value, float) else f"{flag} {fix.value}"


def _message(e) -> str:
    from jaximu.errors import InputError

    return e.render(flag_of) if isinstance(e, InputError) else str(e)


def cache_folder(environ=None) -> pathlib.Path | None:
    """Where the command keeps XLA's compilations between runs: ``$JAXIMU_CACHE_DIR``, else
    ``$XDG_CACHE_HOME/jaximu/xla``, else ``~/.cache/jaximu/xla``; ``None`` when
    ``JAXIMU_CACHE_DIR`` is ``off`` (or empty)."""
    env = os.environ if environ is None else environ
    if "JAXIMU_CACHE_DIR" in env:
        value = env["JAXIMU_CACHE_DIR"].strip()
        return None if value.lower() in ("", "off", "0", "none") else pathlib.Path(value)
    base = env.get("XDG_CACHE_HOME") or str(pathlib.Path.home() / ".cache")
    return pathlib.Path(base) / "jaximu" / "xla"


def enable_compilation_cache() -> pathlib.Path | None:
    """Persist compilations in :func:`cache_folder`, so that a second run
    of a command skips them: ``jaximu calibrate``'s L-BFGS step compiles for ~40 s on 2 CPU
    cores. A folder the user already gave JAX (``JAX_COMPILATION_CACHE_DIR``) is kept.
    Returns the folder in use, or None."""
    import jax

    if jax.config.jax_compilation_cache_dir:
        return pathlib.Path(jax.config.jax_compilation_cache_dir)
    folder = cache_folder()
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # a read-only home: run without the cache
    jax.config.update("jax_compilation_cache_dir", str(folder))
    # every compilation, not only those over 1 s: a command runs ~150 small eager ones
    # (0.05 s each, ~7 s in all for calibrate), which load from the cache in a fraction
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return folder


def main(argv=None, *, cache: bool | None = None) -> int:
    """The command. ``cache``: keep compilations in :func:`cache_folder` (default: when run
    as the command, ``argv is None``; not when called from Python with ``argv``)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    from jaximu.io import DataError

    args.cache_dir = None
    try:
        _check_earth_rate(args)
        if cache if cache is not None else argv is None:
            args.cache_dir = enable_compilation_cache()
        return args.func(args)
    except (UsageError, DataError, ValueError, ImportError, OSError, OverflowError) as e:
        # user mistakes (and unwritable outputs, full disks): one line, no traceback
        print(f"jaximu {args.command}: error: {_message(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaximu: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
