"""``jaximu preintegrate``: preintegrate a recording between keyframes and check the windows
against its ground truth (the work is :func:`jaximu.preintegrate`'s and
:mod:`jaximu.keyframes`')."""

from __future__ import annotations

import time

import numpy as np

from jaximu.app.common import (
    UsageError,
    add_input_options,
    add_sensor_options,
    bias_option,
    check_outputs,
    compute_dtype,
    load_recording,
    sensor_and_world,
)
from jaximu.studies.recording import NOISE_PRESETS
from jaximu.studies.recording import noise_preset as _noise


def cmd_preintegrate(args):
    import jax.numpy as jnp

    from jaximu.engine.preintegration import preintegrate
    from jaximu.geometry.state import ImuBias
    from jaximu.studies import keyframes

    check_outputs(out=args.out)
    if not args.window > 0:
        raise UsageError("--window must be positive")
    data = load_recording(args)
    dtype = compute_dtype(args)
    n = round(args.window * data.rate_hz)
    if n < 2:
        raise UsageError(f"--window {args.window} s holds fewer than 2 samples")
    if len(data.dt) < n:
        raise UsageError(f"the recording ({data.duration:.2f} s) is shorter than one window")
    windows = keyframes.keyframe_windows(data.t, n)
    K = len(windows.t_i)
    gt = data.ground_truth
    bias = bias_option(args.bias)
    how = "given" if bias is not None else "zero"
    if bias is None and args.bias_from_groundtruth:
        if gt is None or gt.b_g is None:
            raise UsageError("--bias-from-groundtruth: the ground truth has no biases")
        k = np.clip(np.searchsorted(gt.t, data.t[0]), 0, len(gt.t) - 1)
        bias, how = np.r_[gt.b_g[k], gt.b_a[k]], "from the ground truth"
    bias = np.zeros(6) if bias is None else bias
    gyro = jnp.asarray(data.gyro[windows.sample_index], dtype)
    accel = jnp.asarray(data.accel[windows.sample_index], dtype)
    dt = jnp.asarray(windows.dt, dtype)
    b = ImuBias(jnp.asarray(bias[:3], dtype), jnp.asarray(bias[3:], dtype))
    print(f"{K} windows of {n} samples ({args.window:g} s), scheme {args.scheme}, biases {how}")
    pose, omega, yaml_noise = sensor_and_world(args, data.rate_hz)
    tic = time.perf_counter()
    pim = preintegrate(
        gyro,
        accel,
        dt,
        b,
        yaml_noise or _noise(args.noise),
        args.scheme,
        method=args.method,
        body_P_sensor=pose,
    )
    pim.delta_p.block_until_ready()
    print(f"preintegrated in {time.perf_counter() - tic:.2f} s including compilation")
    angle = np.rad2deg(2 * np.arccos(np.clip(np.abs(np.asarray(pim.delta_q)[:, 0]), 0, 1)))
    sig = np.sqrt(np.diagonal(np.asarray(pim.cov, np.float64), axis1=1, axis2=2))
    print(
        f"\n{'window':>6}{'t0 [s]':>9}{'|ΔR| [°]':>10}{'|Δv| [m/s]':>12}{'|Δp| [m]':>10}"
        f"{'σθ [°]':>9}{'σp [m]':>9}{'σv [m/s]':>10}"
    )
    for k in list(range(min(K, 5))) + ([K - 1] if K > 5 else []):
        print(
            f"{k:>6}{windows.t_i[k]:>9.3f}{angle[k]:>10.3f}"
            f"{np.linalg.norm(np.asarray(pim.delta_v)[k]):>12.4f}"
            f"{np.linalg.norm(np.asarray(pim.delta_p)[k]):>10.4f}"
            f"{np.rad2deg(sig[k, 0]):>9.4f}{sig[k, 3]:>9.5f}{sig[k, 6]:>10.5f}"
        )
    if args.out:
        np.savez(
            args.out,
            stamp_i_ns=data.stamps_ns[windows.sample_index[:, 0]],
            stamp_j_ns=data.stamps_ns[windows.sample_index[:, -1]],
            **{
                name: np.asarray(getattr(pim, name))
                for name in (
                    "delta_t",
                    "delta_q",
                    "delta_v",
                    "delta_p",
                    "cov",
                    "cov15",
                    "dR_dbg",
                    "dv_dbg",
                    "dv_dba",
                    "dp_dbg",
                    "dp_dba",
                )
            },
            bias=bias,
        )
        print(f"preintegrated measurements written to {args.out}")
    if gt is None or gt.v is None:
        return 0
    # windows with an end in a ground-truth gap (a mocap dropout) are left out: the ground
    # truth there would be interpolated across the gap
    cover = keyframes.groundtruth_coverage(gt, windows.t_i, windows.t_j)
    if not cover.inside.any():
        return 0
    skipped = (
        f"; {int(cover.in_gap.sum())} window(s) with an end in a ground-truth gap left out"
        if cover.in_gap.any()
        else ""
    )
    if not cover.checked.any():
        print(
            f"\nno comparison with the ground truth: each of the {int(cover.inside.sum())} "
            "windows inside it has an end in one of its gaps"
        )
        return 0
    r = keyframes.groundtruth_residuals(pim, gt, windows.t_i, windows.t_j, b, omega_coriolis=omega)[
        cover.checked
    ]
    print(
        f"\nresiduals against the ground truth (median over the {int(cover.checked.sum())} "
        f"windows inside it{skipped}): rotation "
        f"{np.rad2deg(np.median(np.linalg.norm(r[:, 0:3], axis=1))):.3f}°, position "
        f"{np.median(np.linalg.norm(r[:, 3:6], axis=1)):.4f} m, velocity "
        f"{np.median(np.linalg.norm(r[:, 6:9], axis=1)):.4f} m/s"
    )
    return 0


def add_parser(sub):
    """Register ``jaximu preintegrate`` on the command's subparsers."""
    p = sub.add_parser(
        "preintegrate",
        help="preintegrate a recording between keyframes",
        description="Cut the recording into windows and preintegrate each "
        "(deltas, 9×9 and 15×15 covariances, bias Jacobians); compare with the "
        "ground truth when it has velocities.",
    )
    add_input_options(p)
    p.add_argument(
        "--window", type=float, default=0.5, help="seconds per window (> 0, at least 2 samples)"
    )
    p.add_argument("--scheme", default="euler", choices=["euler", "midpoint"])
    p.add_argument(
        "--method",
        default="auto",
        choices=["auto", "sequential", "parallel"],
        help="auto (default): the fastest for the windows; all give the same numbers",
    )
    p.add_argument("--bias", metavar="'BGX BGY BGZ BAX BAY BAZ'", help="biases [rad/s, m/s²]")
    p.add_argument(
        "--bias-from-groundtruth", action="store_true", help="use the ground truth's bias estimate"
    )
    p.add_argument("--noise", default="euroc", choices=NOISE_PRESETS)
    p.add_argument("--out", metavar="NPZ", help="write the preintegrated measurements")
    p.add_argument("--float64", action="store_true", help="compute in float64")
    add_sensor_options(p)
    p.set_defaults(func=cmd_preintegrate)
    return p
