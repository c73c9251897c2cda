"""How jaximu's propagation cost scales with the trajectory length T and the batch size N.

Two sweeps, each for mean-only ``propagate_final(..., "euler")`` and for
``propagate_covariance_final(..., ImuNoise.euroc(), "euler")`` (final 15×15 covariance only):

* T in 1e2 … 1e6 samples, one trajectory (B = 1);
* N in 1 … 1e5 trajectories of T = 200 samples.

Per point: compile time (``jax.jit(f).lower(*args).compile()``, timed on its own) and the best
of ≥ 3 runs of the compiled function (``jax.block_until_ready``); samples/s = B·T / run time.
Then two checks: run time linear in T, compile time flat in T (the scan must not unroll).

    python benchmarks/scaling.py            # float32, full sweeps (a few minutes on 2 cores)
    python benchmarks/scaling.py --quick    # T ≤ 1e4, N ≤ 1e3 (< 1 min)
    python benchmarks/scaling.py --f64      # float64 instead; --both for both dtypes

Prints a Markdown table and the checks; writes ``benchmarks/results/scaling-<machine>.json``
and ``scaling-<machine>.png``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

import jax

# The library never enables float64 itself; the caller does, before any array is made.
jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaximu  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from propagation import CpuMeter, machine_info, machine_slug  # noqa: E402  (same folder)

RESULTS_DIR = Path(__file__).resolve().parent / "results"

T_SWEEP = (100, 1_000, 10_000, 100_000, 1_000_000)
N_SWEEP = (1, 10, 100, 1_000, 10_000, 100_000)
T_FOR_N = 200
DT = 0.005  # 200 Hz
GYRO_STD, ACCEL_STD = 0.5, 0.5  # rad/s; m/s² around [0, 0, 9.81]
NOISE = jaximu.ImuNoise.euroc()
WORKLOADS = ("mean", "cov")
# Per-sample time at T = 1e2 this much above T = 1e3's: the fixed per-call cost dominates.
OVERHEAD_RATIO = 1.5
BUSY_WARN = 0.10  # flag a point when other processes used more of the CPUs than this


def make_inputs(B: int, T: int, dtype: str, seed: int = 0):
    rng = np.random.default_rng(seed)
    npd = np.dtype(dtype)
    gyro = rng.standard_normal((B, T, 3), dtype=npd) * npd.type(GYRO_STD)
    accel = rng.standard_normal((B, T, 3), dtype=npd) * npd.type(ACCEL_STD)
    accel += np.array([0.0, 0.0, 9.81], npd)
    return dict(
        state=jaximu.NavState.identity((B,), jnp.dtype(dtype)),
        gyro=jnp.asarray(gyro),
        accel=jnp.asarray(accel),
        dt=jnp.full((T,), DT, jnp.dtype(dtype)),
        # Shared by the batch: the library broadcasts it to (B, 15, 15).
        P0=1e-6 * jnp.eye(15, dtype=jnp.dtype(dtype)),
    )


def build(workload: str, x: dict):
    if workload == "mean":

        def fn(s, g, a, h):
            return jaximu.propagate_final(s, g, a, h, "euler")

        return fn, (x["state"], x["gyro"], x["accel"], x["dt"])

    def fn(s, P, g, a, h):
        return jaximu.propagate_covariance_final(s, P, g, a, h, NOISE, "euler")

    return fn, (x["state"], x["P0"], x["gyro"], x["accel"], x["dt"])


def measure(fn, args, reps: int, min_time: float, max_reps: int = 50) -> dict:
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    runs = []
    # Tiny cases run in microseconds: time more of them so the best one is not just noise.
    while len(runs) < reps or (sum(runs) < min_time and len(runs) < max_reps):
        t = time.perf_counter()
        out = compiled(*args)
        jax.block_until_ready(out)
        runs.append(time.perf_counter() - t)
        finite = all(
            bool(np.isfinite(np.asarray(leaf)).all()) for leaf in jax.tree_util.tree_leaves(out)
        )
        del out
    return dict(status="ok", compile_s=compile_s, run_s=min(runs), runs_s=runs, finite=finite)


def plan(quick: bool, dtypes: list[str]) -> list[dict]:
    ts = [t for t in T_SWEEP if not quick or t <= 10_000]
    ns = [n for n in N_SWEEP if not quick or n <= 1_000]
    points = []
    for dtype in dtypes:
        for workload in WORKLOADS:
            points += [dict(dtype=dtype, workload=workload, sweep="T", B=1, T=t) for t in ts]
            points += [dict(dtype=dtype, workload=workload, sweep="N", B=n, T=T_FOR_N) for n in ns]
    return points


def predict(point: dict, done: list[dict], reps: int):
    """Seconds predicted for ``point`` from the previous point of its sweep (None if first).

    Per-sample time is taken as constant, which over-predicts when the previous point was
    dominated by fixed per-call costs: cautious, never optimistic.
    """
    same = [r for r in done if all(r[k] == point[k] for k in ("dtype", "workload", "sweep"))]
    if not same:
        return None, None
    prev = same[-1]
    if prev["status"] != "ok":
        return float("inf"), (
            f"skipped: larger than a point already skipped ({prev['B']}×{prev['T']})"
        )
    run = prev["run_s"] * (point["B"] * point["T"]) / (prev["B"] * prev["T"])
    return prev["compile_s"] + reps * run, (
        f"{reps} runs × {run:.2g} s + {prev['compile_s']:.2g} s compile, "
        f"extrapolated from {prev['B']}×{prev['T']}"
    )


# --------------------------------------------------------------------------- the two checks


def checks(results: list[dict]) -> list[dict]:
    out = []
    for dtype in dict.fromkeys(r["dtype"] for r in results):
        for workload in WORKLOADS:
            pts = [
                r
                for r in results
                if r["dtype"] == dtype
                and r["workload"] == workload
                and r["sweep"] == "T"
                and r["status"] == "ok"
            ]
            if len(pts) < 2:
                continue
            per = {r["T"]: r["run_s"] / r["T"] for r in pts}
            ts = sorted(per)
            # run = a + b·T, fitted on relative error: a is the fixed per-call cost.
            T_arr = np.array(ts, float)
            run = np.array([per[t] * t for t in ts])
            a, b = np.linalg.lstsq(
                np.c_[np.ones_like(T_arr), T_arr] / run[:, None], np.ones_like(run), rcond=None
            )[0]
            resid = float(np.max(np.abs((a + b * T_arr) / run - 1)))
            # T = 1e2 is left out of the ratio when the fixed cost is most of its run time.
            overhead = len(ts) > 2 and ts[0] == 100 and a > 0.5 * per[100] * 100
            lo = ts[1] if overhead else ts[0]
            # Where the fixed cost is under 10 % of the run, per-sample time should be constant.
            steady = [t for t in ts if a < 0.1 * per[t] * t] if a > 0 else ts
            spread = (
                max(per[t] for t in steady) / min(per[t] for t in steady)
                if len(steady) >= 2
                else None
            )
            comp = [r["compile_s"] for r in pts]
            out.append(
                dict(
                    dtype=dtype,
                    workload=workload,
                    T_min=lo,
                    T_max=ts[-1],
                    per_sample_ratio=per[ts[-1]] / per[lo],
                    per_sample_ratio_incl_T100=per[ts[-1]] / per[ts[0]],
                    T100_overhead_dominated=bool(overhead),
                    fit_overhead_s=float(a),
                    fit_per_sample_s=float(b),
                    fit_max_rel_resid=resid,
                    steady_T=steady,
                    steady_spread=spread,
                    linear=bool(spread is not None and spread <= 1.25),
                    compile_min_s=min(comp),
                    compile_max_s=max(comp),
                    compile_ratio=max(comp) / min(comp),
                    compile_flat=max(comp) / min(comp) <= 2.0,
                )
            )
    return out


def exp10(x: int) -> str:
    k = int(round(np.log10(x)))
    return f"1e{k}" if 10**k == x else f"{x:,}"


def ns(seconds: float) -> str:
    x = seconds * 1e9
    return f"{x:.0f}" if x >= 100 else f"{x:.3g}"


def check_lines(cks: list[dict]) -> list[str]:
    lines = []
    for c in cks:
        r = c["per_sample_ratio"]
        excl = (
            f" (T=1e2 left out: the fixed per-call cost is most of its run; with it the "
            f"ratio is {c['per_sample_ratio_incl_T100']:.2f})"
            if c["T100_overhead_dominated"]
            else ""
        )
        if c["steady_spread"] is None:
            steady = "too few T with a negligible fixed cost to judge linearity"
        else:
            steady = (
                f"where the fixed cost is under 10% of the run (T ≥ "
                f"{exp10(min(c['steady_T']))}), per-sample time varies by "
                f"{c['steady_spread']:.2f}× "
                f"({'linear' if c['linear'] else 'NOT linear'}: limit 1.25×)"
            )
        lines.append(
            f"- {c['workload']} {c['dtype']}: per-sample time at T={exp10(c['T_max'])} / at "
            f"T={exp10(c['T_min'])} = {r:.2f}{excl}; fit run = "
            f"{c['fit_overhead_s'] * 1e6:.0f} µs + {ns(c['fit_per_sample_s'])} ns·T (within "
            f"{c['fit_max_rel_resid']:.0%} at every T); {steady}. "
            f"Compile time over T: {c['compile_min_s']:.2f}–{c['compile_max_s']:.2f} s, "
            f"max/min {c['compile_ratio']:.2f} ({'flat' if c['compile_flat'] else 'NOT flat'}: "
            f"limit 2×)."
        )
    return lines


# --------------------------------------------------------------------------- output


def fmt_rate(x: float) -> str:
    return f"{x / 1e6:.2f} M" if x >= 1e6 else f"{x / 1e3:.1f} k"


def table(results: list[dict]) -> str:
    lines = [
        "| workload | dtype | sweep | B | T | compile s | run ms | samples/s | ns/sample | note |",
        "|---|---|---|--:|--:|--:|--:|--:|--:|---|",
    ]
    for r in results:
        head = f"| {r['workload']} | {r['dtype']} | {r['sweep']} | {r['B']:,} | {r['T']:,} |"
        if r["status"] != "ok":
            lines.append(f"{head} | | skipped | | {r['reason']} |")
            continue
        note = []
        if r.get("other_cpu_share") is not None and r["other_cpu_share"] > BUSY_WARN:
            note.append(f"other processes used {r['other_cpu_share']:.0%} of the CPUs")
        if not r["finite"]:
            note.append("NON-FINITE OUTPUT")
        lines.append(
            f"{head} {r['compile_s']:.2f} | {r['run_s'] * 1e3:.3g} | "
            f"{fmt_rate(r['samples_per_s'])} | {ns(r['run_s'] / (r['B'] * r['T']))} | "
            f"{'; '.join(note)} |"
        )
    return "\n".join(lines)


def plot(results: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    colors = {
        ("mean", "float32"): "C0",
        ("cov", "float32"): "C1",
        ("mean", "float64"): "C2",
        ("cov", "float64"): "C3",
    }
    for ax, sweep, xkey, xlabel in (
        (axes[0], "T", "T", "T (samples, B = 1)"),
        (axes[1], "N", "B", f"N (trajectories, T = {T_FOR_N})"),
    ):
        ax2 = ax.twinx()
        for (workload, dtype), c in colors.items():
            pts = [
                r
                for r in results
                if r["sweep"] == sweep
                and r["workload"] == workload
                and r["dtype"] == dtype
                and r["status"] == "ok"
            ]
            if not pts:
                continue
            x = [r[xkey] for r in pts]
            ax.plot(
                x,
                [r["samples_per_s"] for r in pts],
                "o-",
                color=c,
                label=f"{workload} {dtype}: samples/s",
            )
            ax2.plot(
                x,
                [r["compile_s"] for r in pts],
                "s--",
                color=c,
                alpha=0.6,
                label=f"{workload} {dtype}: compile s",
            )
        for a in (ax, ax2):
            a.set_xscale("log")
            a.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("samples/s (solid)")
        ax2.set_ylabel("compile time [s] (dashed)")
        ax.grid(True, which="both", alpha=0.3)
        h1, l1 = ax.get_legend_handles_labels()
        h2, l2 = ax2.get_legend_handles_labels()
        ax.legend(h1 + h2, l1 + l2, fontsize=7, loc="best")
        ax.set_title(f"against {sweep}")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# --------------------------------------------------------------------------- main


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="T ≤ 1e4 and N ≤ 1e3 (< 1 min)")
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--f64", action="store_true", help="float64 instead of float32")
    g.add_argument("--both", action="store_true", help="float32 and float64")
    ap.add_argument(
        "--reps", type=int, default=3, help="timed runs per point, at least (default 3)"
    )
    ap.add_argument(
        "--min-time",
        type=float,
        default=0.2,
        help="time a fast point until its runs add up to this many s (default 0.2)",
    )
    ap.add_argument(
        "--max-case-s",
        type=float,
        default=30.0,
        help="skip a point predicted to take longer (compile + runs; default 30)",
    )
    ap.add_argument("--out", type=Path, help="JSON path (the PNG goes next to it)")
    args = ap.parse_args(argv)

    dtypes = ["float64"] if args.f64 else ["float32", "float64"] if args.both else ["float32"]
    info = machine_info()
    points = plan(args.quick, dtypes)
    print(
        f"jaximu scaling benchmark: {info['cpu_model']}, "
        f"{info['cpus_usable'] or info['cpu_count']} CPUs, jax {info['jax']} "
        f"({info['backend']}); {len(points)} points",
        file=sys.stderr,
    )
    t_start, run_meter = time.perf_counter(), CpuMeter()
    results = []
    for i, p in enumerate(points):
        print(
            f"[{i + 1}/{len(points)}] {p['workload']} {p['dtype']} B={p['B']} T={p['T']} ...",
            end="",
            file=sys.stderr,
            flush=True,
        )
        guess, why = predict(p, results, args.reps)
        meter = CpuMeter()
        if guess is not None and guess > args.max_case_s:
            res = dict(
                status="skipped",
                reason=why
                if why.startswith("skipped")
                else f"skipped: predicted {guess:.3g} s ({why}) > {args.max_case_s:.3g} s budget",
            )
        else:
            fn, fargs = build(p["workload"], make_inputs(p["B"], p["T"], p["dtype"]))
            res = measure(fn, fargs, args.reps, args.min_time)
            del fargs
            res["samples_per_s"] = p["B"] * p["T"] / res["run_s"]
        res = {**p, **res, "predicted_s": guess, "other_cpu_share": meter.other_share()}
        results.append(res)
        print(
            f" {fmt_rate(res['samples_per_s'])}samples/s, run {res['run_s'] * 1e3:.3g} ms, "
            f"compile {res['compile_s']:.2f} s"
            if res["status"] == "ok"
            else f" {res['reason']}",
            file=sys.stderr,
            flush=True,
        )

    elapsed, other = time.perf_counter() - t_start, run_meter.other_share()
    cks = checks(results)
    print()
    print(table(results))
    print()
    print(
        "Run time: best of ≥ 3 runs of the AOT-compiled function (more for points under "
        f"{args.min_time} s in all), compilation excluded; compile s: trace + lower + XLA "
        "compile."
    )
    print()
    print("Checks:")
    for line in check_lines(cks):
        print(line)
    skipped = [r for r in results if r["status"] != "ok"]
    if skipped:
        print()
        print("Skipped:")
        for r in skipped:
            print(f"- {r['workload']} {r['dtype']} {r['B']}×{r['T']}: {r['reason']}")
    print()
    print(
        f"Total {elapsed:.0f} s"
        + ("." if other is None else f"; other processes used {other:.0%} of the CPUs.")
    )
    if other is not None and other > BUSY_WARN:
        print("Warning: the machine was not idle; timings are inflated (see the note column).")

    out = args.out
    if out is None:
        # One file per machine whatever the dtypes (the JSON lists them); quick runs apart.
        out = RESULTS_DIR / f"scaling-{machine_slug(info)}{'-quick' if args.quick else ''}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = dict(
        benchmark="jaximu scaling in T and N",
        date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        machine=info,
        settings=dict(
            quick=args.quick,
            dtypes=dtypes,
            reps=args.reps,
            min_time_s=args.min_time,
            max_case_s=args.max_case_s,
            dt=DT,
            gyro_std=GYRO_STD,
            accel_std=ACCEL_STD,
            P0="1e-6 I",
            noise="ImuNoise.euroc()",
            scheme="euler",
            jacobians="auto (analytic)",
            argv=sys.argv[1:],
        ),
        definitions=dict(
            samples_per_s="B*T / run_s",
            run_s="best of >= reps runs of the AOT-compiled jax.jit function (block_until_ready)",
            compile_s="jax.jit(f).lower(*args).compile() wall time",
            per_sample_ratio="(run_s/T at T_max) / (run_s/T at T_min); T_min skips T=100 when "
            "the fitted fixed cost fit_overhead_s is over half its run time",
            fit="run_s = fit_overhead_s + fit_per_sample_s * T, least squares on relative error; "
            "fit_max_rel_resid its largest relative misfit over the T sweep",
            steady_spread="max / min per-sample time over steady_T, the T where fit_overhead_s "
            "is under 10% of the run; linear: steady_spread <= 1.25",
            compile_ratio="max / min compile_s over the T sweep",
        ),
        checks=cks,
        total_s=elapsed,
        other_cpu_share=other,
        points=results,
    )
    out.write_text(json.dumps(doc, indent=2) + "\n")
    png = out.with_suffix(".png")
    plot(
        results,
        png,
        f"jaximu scaling, Euler, {info['cpu_model']} "
        f"({info['cpus_usable'] or info['cpu_count']} CPUs), jax {info['jax']}",
    )
    print(f"Wrote {out} and {png}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
