"""The ``jaximu`` command.

``jaximu demo`` propagates the bundled EuRoC MAV excerpt (real ADIS16448 data, 200 Hz) from
the ground-truth initial state with the ground-truth biases, prints the drift against ground
truth, and writes a plot (if matplotlib is installed: ``pip install "jaximu[examples]"``).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def _nearest(t_query, t):
    idx = np.searchsorted(t, t_query)
    idx = np.clip(idx, 1, len(t) - 1)
    return np.where(np.abs(t[idx - 1] - t_query) <= np.abs(t[idx] - t_query), idx - 1, idx)


def run_demo(seconds: float = 20.0, scheme: str = "midpoint", plot: str | None = "jaximu_demo.png",
             out=sys.stdout) -> dict:
    """Run the demo; returns the drift table ``{scheme: {t: (pos_m, vel_mps, att_deg)}}``."""
    import jax
    import jax.numpy as jnp

    import jaximu
    from jaximu import so3
    from jaximu.datasets import euroc_v1_02_segment

    seg = euroc_v1_02_segment()
    k0 = int(_nearest(np.array([seg.t_gt[0]]), seg.t)[0])
    t_end = min(seg.t_gt[-1], seg.t_gt[0] + seconds)
    k1 = int(_nearest(np.array([t_end]), seg.t)[0])
    t = seg.t[k0:k1 + 1]
    gyro, accel = seg.gyro[k0:k1], seg.accel[k0:k1]
    dt = np.diff(t)
    # Ground truth at every IMU time (the EuRoC GT lies on the IMU grid within 3 µs).
    g_idx = _nearest(t, seg.t_gt)
    q_gt = seg.q_gt[g_idx] / np.linalg.norm(seg.q_gt[g_idx], axis=1, keepdims=True)
    p_gt, v_gt = seg.p_gt[g_idx], seg.v_gt[g_idx]
    dtype = jnp.result_type(float)  # float32 unless the user enabled x64
    # The file's quaternions have |q| - 1 up to 1.5e-4: normalised here, explicitly.
    state0 = jaximu.NavState(
        q=jnp.asarray(q_gt[0], dtype), p=jnp.asarray(p_gt[0], dtype),
        v=jnp.asarray(v_gt[0], dtype), b_g=jnp.asarray(seg.b_g_gt[g_idx[0]], dtype),
        b_a=jnp.asarray(seg.b_a_gt[g_idx[0]], dtype))
    noise = jaximu.ImuNoise.euroc()
    # Initial uncertainty: the ground truth's own (~1 mm, ~0.1°, ~1 cm/s), and the biases'
    # run-to-run spread.
    P0 = np.diag(np.r_[[np.deg2rad(0.1) ** 2] * 3, [1e-6] * 3, [1e-4] * 3,
                       [1e-4 ** 2] * 3, [1e-3 ** 2] * 3])
    print(f"jaximu demo: EuRoC MAV V1_02_medium, {len(dt)} samples over {t[-1] - t[0]:.2f} s "
          f"at 200 Hz ({jnp.dtype(dtype).name}, {jax.default_backend()})", file=out)
    print("propagating from the ground-truth state with the ground-truth biases; "
          "no corrections (pure dead reckoning)", file=out)
    report_at = [s for s in (1, 2, 5, 10, 20, 30, 60) if s <= t[-1] - t[0] + 1e-9]
    table = {}
    results = {}
    for sch in jaximu.SCHEMES:
        tic = time.perf_counter()
        states, covs = jaximu.propagate_covariance(state0, P0, gyro, accel, dt, noise, sch)
        jax.block_until_ready(covs)
        elapsed = time.perf_counter() - tic
        q, p, v = (np.asarray(x, np.float64) for x in (states.q, states.p, states.v))
        dq = so3.quat_mul(so3.quat_conj(jnp.asarray(q_gt[1:])), jnp.asarray(q))
        att = np.rad2deg(np.linalg.norm(np.asarray(so3.log(dq)), axis=1))
        pos = np.linalg.norm(p - p_gt[1:], axis=1)
        vel = np.linalg.norm(v - v_gt[1:], axis=1)
        rows = {}
        for s in report_at:
            i = int(np.argmin(np.abs((t[1:] - t[0]) - s)))
            rows[s] = (pos[i], vel[i], att[i])
        table[sch] = rows
        results[sch] = dict(p=p, err=p - p_gt[1:], att=att, cov=np.asarray(covs, np.float64),
                            seconds=elapsed)
    print(f"\n{'scheme':<10}" + "".join(f"{f'{s} s':>22}" for s in report_at), file=out)
    print(f"{'':<10}" + "".join(f"{'pos m / vel m/s / °':>22}" for _ in report_at), file=out)
    for sch, rows in table.items():
        cells = "".join(f"{f'{a:.3f} / {b:.3f} / {c:.2f}':>22}" for a, b, c in rows.values())
        print(f"{sch:<10}{cells}", file=out)
    horizon = report_at[-1]
    per_s = table[scheme][horizon][0] / horizon
    print(f"\n{scheme}: position drift {table[scheme][horizon][0]:.2f} m after {horizon} s "
          f"({per_s:.3f} m per second on average); propagation with covariance took "
          f"{results[scheme]['seconds']:.2f} s including compilation", file=out)
    if plot:
        try:
            _plot(plot, t[1:] - t[0], p_gt[1:], results, scheme)
            print(f"plot written to {plot}", file=out)
        except ImportError:
            print("matplotlib is not installed: no plot (pip install \"jaximu[examples]\")",
                  file=out)
    return table


def _plot(path, t, p_gt, results, scheme):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = results[scheme]
    fig, ax = plt.subplots(2, 2, figsize=(12, 8.5))
    ax[0, 0].plot(p_gt[:, 0], p_gt[:, 1], "k-", lw=2, label="ground truth")
    for name, res in results.items():
        ax[0, 0].plot(res["p"][:, 0], res["p"][:, 1], lw=1, label=f"jaximu {name}")
    ax[0, 0].set(title="Top view (world frame)", xlabel="x [m]", ylabel="y [m]", aspect="equal")
    ax[0, 0].legend(fontsize=8)
    ax[0, 1].plot(t, p_gt[:, 2], "k-", lw=2, label="ground truth")
    ax[0, 1].plot(t, r["p"][:, 2], lw=1, label=f"jaximu {scheme}")
    ax[0, 1].set(title="Height", xlabel="t [s]", ylabel="z [m]")
    ax[0, 1].legend(fontsize=8)
    sigma = np.sqrt(np.stack([r["cov"][:, 3 + i, 3 + i] for i in range(3)], axis=1))
    for i, c in enumerate("xyz"):
        line, = ax[1, 0].plot(t, r["err"][:, i], lw=1, label=f"error {c}")
        ax[1, 0].fill_between(t, -3 * sigma[:, i], 3 * sigma[:, i], color=line.get_color(),
                              alpha=0.12)
    ax[1, 0].set(title=f"Position error with 3σ envelope ({scheme})", xlabel="t [s]", ylabel="[m]")
    ax[1, 0].legend(fontsize=8)
    for name, res in results.items():
        ax[1, 1].plot(t, res["att"], lw=1, label=name)
    ax[1, 1].set(title="Attitude error", xlabel="t [s]", ylabel="[deg]")
    ax[1, 1].legend(fontsize=8)
    fig.suptitle("jaximu: IMU dead reckoning on EuRoC MAV V1_02_medium (real ADIS16448 data)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="jaximu", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="dead reckoning on bundled real EuRoC data, with a plot")
    demo.add_argument("--seconds", type=float, default=20.0, help="length to propagate (≤ 20 s)")
    demo.add_argument("--scheme", default="midpoint", choices=["euler", "midpoint", "rk4"])
    demo.add_argument("--plot", default="jaximu_demo.png", help="output PNG (default: %(default)s)")
    demo.add_argument("--no-plot", action="store_true", help="do not write a plot")
    args = parser.parse_args(argv)
    try:
        if args.command == "demo":
            if not 0 < args.seconds:
                parser.error("--seconds must be positive")
            run_demo(args.seconds, args.scheme, None if args.no_plot else args.plot)
    except ValueError as e:  # user mistakes: one line, no traceback
        print(f"jaximu: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
