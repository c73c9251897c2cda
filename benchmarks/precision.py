"""float32 against float64 over one hour of 200 Hz IMU data, per integration scheme.

A simulated trajectory (``jaximu.simulate``) gives exact IMU samples and the true states, all
computed in float64. The same samples are propagated with ``jaximu.propagate`` from the true
initial state in float64, and cast to float32 and propagated in float32. At 1 s, 1 min,
10 min and 1 h the script reports

* the float32 − float64 difference: position [m] and rotation angle of ``q32⁻¹ ⊗ q64`` [rad];
* the float64 error against the truth: the scheme's own discretisation error, for context.

float32 is enough while its difference from float64 stays below the scheme's discretisation
error: beyond that, the rounding, not the scheme, limits the accuracy.

    python benchmarks/precision.py                # 1 h at 200 Hz (720,000 samples)
    python benchmarks/precision.py --quick        # 10 min
    python benchmarks/precision.py --trajectory helix

Prints a Markdown table and a verdict per scheme; writes
``benchmarks/results/precision-<machine>.json``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import re
import sys
import time
from pathlib import Path

import jax

# The library never enables float64 itself; the caller does, before any array is made.
jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaximu  # noqa: E402
from jaximu import simulate as sim  # noqa: E402
from jaximu import so3  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from propagation import machine_info, machine_slug  # noqa: E402  (same folder)

RESULTS_DIR = Path(__file__).resolve().parent / "results"
DT = 0.005  # 200 Hz
RATE = 200  # samples per second: records are taken every RATE steps (1 s)
SCHEMES = ("euler", "midpoint", "rk4")
HORIZONS = (1, 60, 600, 3600)  # s
TRAJECTORIES = {"lissajous": sim.lissajous, "helix": sim.helix}


def angle(qa, qb):
    """Rotation angle [rad] of ``qa⁻¹ ⊗ qb``, in float64 (both normalised first)."""
    qa, qb = (so3.quat_normalize(jnp.asarray(q, jnp.float64)) for q in (qa, qb))
    return jnp.linalg.norm(so3.log(so3.quat_mul(so3.quat_conj(qa), qb)), axis=-1)


def propagate_recorded(scheme: str, x0, gyro, accel, dt):
    """Every state from ``jaximu.propagate``, kept once per second (state after steps RATE-1, …).

    T + 1 samples and T steps: ``dt`` has one entry fewer than the samples, so step k uses
    samples k and k+1 (midpoint, RK4) and no step holds a sample past its interval.
    """

    @jax.jit
    def run(x0, gyro, accel, dt):
        states = jaximu.propagate(x0, gyro, accel, dt, scheme)
        return jax.tree_util.tree_map(lambda a: a[RATE - 1 :: RATE], states)

    t0 = time.perf_counter()
    out = jax.block_until_ready(run(x0, gyro, accel, dt))
    return out, time.perf_counter() - t0


def cast_state(s, dtype):
    return jax.tree_util.tree_map(lambda a: a.astype(dtype), s)


def fmt(x: float) -> str:
    return f"{x:.2e}"


def horizon_label(s: int) -> str:
    return {1: "1 s", 60: "1 min", 600: "10 min", 3600: "1 h"}.get(s, f"{s} s")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="10 min of data instead of 1 h")
    ap.add_argument("--trajectory", choices=sorted(TRAJECTORIES), default="lissajous")
    ap.add_argument("--out", type=Path, help="JSON path")
    args = ap.parse_args(argv)

    duration = 600 if args.quick else 3600
    horizons = [h for h in HORIZONS if h <= duration]
    T = duration * RATE
    info = machine_info()
    traj = TRAJECTORIES[args.trajectory]()
    t_start = time.perf_counter()
    print(
        f"jaximu precision benchmark: {args.trajectory}, {T:,} samples ({duration} s at "
        f"{RATE} Hz), schemes {', '.join(SCHEMES)}",
        file=sys.stderr,
    )

    # Simulation times in float64: the propagation only ever sees dt, never absolute time.
    t = jnp.arange(T + 1, dtype=jnp.float64) * DT
    gyro64, accel64 = sim.ideal_imu(traj, t)
    truth = sim.true_states(traj, t)
    truth_rec = jax.tree_util.tree_map(lambda a: a[RATE::RATE], truth)  # at 1 s, 2 s, …
    x0_64 = truth[0]
    dt64 = jnp.full((T,), DT, jnp.float64)
    # float32 sees the rounded samples, state and step: part of what float32 costs.
    gyro32, accel32 = gyro64.astype(jnp.float32), accel64.astype(jnp.float32)
    x0_32 = cast_state(x0_64, jnp.float32)
    x0_32 = x0_32.replace(q=so3.quat_normalize(x0_32.q))
    dt32 = jnp.full((T,), DT, jnp.float32)
    dt_rel = float(np.float32(DT)) / DT - 1
    print(f"  simulated in {time.perf_counter() - t_start:.1f} s", file=sys.stderr)

    results, rows = {}, []
    for scheme in SCHEMES:
        s64, run64 = propagate_recorded(scheme, x0_64, gyro64, accel64, dt64)
        s32, run32 = propagate_recorded(scheme, x0_32, gyro32, accel32, dt32)
        p32, v32 = (np.asarray(a, np.float64) for a in (s32.p, s32.v))
        rec = dict(
            dp32=np.linalg.norm(p32 - np.asarray(s64.p), axis=-1),
            dth32=np.asarray(angle(s32.q, s64.q)),
            dv32=np.linalg.norm(v32 - np.asarray(s64.v), axis=-1),
            err64_p=np.linalg.norm(np.asarray(s64.p - truth_rec.p), axis=-1),
            err64_th=np.asarray(angle(s64.q, truth_rec.q)),
            err64_v=np.linalg.norm(np.asarray(s64.v - truth_rec.v), axis=-1),
            err32_p=np.linalg.norm(p32 - np.asarray(truth_rec.p), axis=-1),
            err32_th=np.asarray(angle(s32.q, truth_rec.q)),
        )
        # Both errors oscillate with the motion (a periodic attitude error passes through zero),
        # so compare the largest value so far of each rather than values at one instant.
        env = {k: np.maximum.accumulate(v) for k, v in rec.items()}
        over = (env["dp32"] > env["err64_p"]) | (env["dth32"] > env["err64_th"])
        first = int(np.argmax(over)) + 1 if over.any() else None
        at = {h: {k: float(v[h - 1]) for k, v in rec.items()} for h in horizons}
        max_so_far = {h: {k: float(v[h - 1]) for k, v in env.items()} for h in horizons}
        enough = [h for h in horizons if not over[h - 1]]
        last = max_so_far[horizons[-1]]
        ratios = (
            f"at {horizon_label(horizons[-1])} the largest float32 difference so far is "
            f"{last['dp32'] / last['err64_p']:.2g}× the largest discretisation error in "
            f"position ({fmt(last['dp32'])} vs {fmt(last['err64_p'])} m) and "
            f"{last['dth32'] / last['err64_th']:.2g}× in rotation "
            f"({fmt(last['dth32'])} vs {fmt(last['err64_th'])} rad)"
        )
        if first is None:
            verdict = f"float32 is enough over the whole {horizon_label(duration)}: {ratios}"
        else:
            start = (
                "float32 is not enough even at 1 s"
                if first == 1
                else f"float32 is enough for the first {first - 1} s"
            )
            checkpoints = ", ".join(horizon_label(h) for h in enough) or "no checkpoint"
            verdict = (
                f"{start}; it exceeds the discretisation error in {over.mean():.0%} of the "
                f"seconds (enough at: {checkpoints}); {ratios}"
            )
        results[scheme] = dict(
            at=at,
            max_so_far=max_so_far,
            first_exceeds_s=first,
            share_exceeds=float(over.mean()),
            verdict=verdict,
            run64_s=run64,
            run32_s=run32,
            every_10s={k: [float(f"{x:.4g}") for x in v[9::10]] for k, v in rec.items()},
        )
        for h in horizons:
            a, m = at[h], max_so_far[h]
            cells = [f"{fmt(a[k])} ({fmt(m[k])})" for k in ("dp32", "dth32", "err64_p", "err64_th")]
            rows.append(
                f"| {scheme} | {horizon_label(h)} | {' | '.join(cells)} | "
                f"{'yes' if h in enough else 'no'} |"
            )
        print(
            f"  {scheme}: float64 {run64:.1f} s, float32 {run32:.1f} s (compile included)",
            file=sys.stderr,
        )

    print()
    print(
        f"{args.trajectory}, {T:,} samples at {RATE} Hz, exact IMU samples, from the true "
        "initial state:"
    )
    print()
    print(
        "| scheme | time | float32−float64 position [m] | float32−float64 rotation [rad] | "
        "float64 error position [m] | float64 error rotation [rad] | float32 enough |"
    )
    print("|---|---|--:|--:|--:|--:|---|")
    print("\n".join(rows))
    print()
    print(
        "Each cell: the value at that time (the largest value up to that time). float32 enough: "
        "the largest float32−float64 difference up to that time is below the largest float64 "
        "error against the truth (the scheme's discretisation error) up to that time, in "
        "position and rotation."
    )
    print(
        f"Note: float32 rounds dt = {DT} by {dt_rel:+.1e} (relative), so float32 integrates "
        f"{-dt_rel * duration:.1e} s less time over {horizon_label(duration)}; it also rounds "
        "every sample and the initial state. All three are part of the difference above."
    )
    print()
    for scheme in SCHEMES:
        print(f"- {scheme}: {results[scheme]['verdict']}.")
    elapsed = time.perf_counter() - t_start
    print(f"\nTotal {elapsed:.0f} s.")

    out = args.out or RESULTS_DIR / (
        f"precision-{machine_slug(info)}{'-quick' if args.quick else ''}.json"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = dict(
        benchmark="jaximu float32 vs float64 precision",
        date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        machine=info,
        settings=dict(
            quick=args.quick,
            trajectory=args.trajectory,
            samples=T,
            dt=DT,
            duration_s=duration,
            horizons_s=horizons,
            attitude="quaternion",
            float32_dt=float(np.float32(DT)),
            argv=sys.argv[1:],
        ),
        definitions=dict(
            dp32="|p32 - p64| [m]",
            dth32="rotation angle of q32^-1 q64 [rad]",
            dv32="|v32 - v64| [m/s]",
            err64_p="|p64 - p_true| [m]: discretisation error",
            err64_th="rotation angle of q64^-1 q_true [rad]",
            err64_v="|v64 - v_true| [m/s]",
            err32_p="|p32 - p_true| [m]",
            err32_th="rotation angle of q32^-1 q_true [rad]",
            at="each quantity at the horizon",
            max_so_far="its largest value up to the horizon",
            every_10s="each quantity at 10 s, 20 s, ... (index k: time 10(k+1) s)",
            first_exceeds_s="first second at which the largest dp32 so far exceeds the largest "
            "err64_p so far, or the same for rotation",
            share_exceeds="share of the seconds at which that holds",
            run_s="jit compile + run of jaximu.propagate over all samples",
        ),
        total_s=elapsed,
        schemes=results,
    )
    # One line per list of numbers keeps the series readable and the file small.
    text = re.sub(
        r"\[\s+([^\[\]{}]*?)\s+\]",
        lambda m: "[" + " ".join(m.group(1).split()) + "]",
        json.dumps(doc, indent=1),
    )
    out.write_text(text + "\n")
    print(f"Wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
