"""XLA:CPU's 512-bit vectors against its default 256, the same kernels in one process.

    python benchmarks/vector_width.py           # ~4 min on a 2-core CPU
    python benchmarks/vector_width.py --quick   # three cases, < 1 min

XLA:CPU asks LLVM for 256-bit vectors by default, also on CPUs with AVX-512. A user changes
that with ``XLA_FLAGS=--xla_cpu_prefer_vector_width=512`` before JAX starts (the whole
process), or for one top-level ``jax.jit`` with
``compiler_options={"xla_cpu_prefer_vector_width": 512}`` (JAX refuses it on a nested
``jit``, which is why jaximu cannot choose it for its own kernels). This script compiles each
case both ways in one process — the second way as that ``compiler_options`` — and times them
alternately, round after round, so that the ratio is free of this host's drift (its speed
moves ±25% within minutes, more than the effect between two separate runs); a ratio is the
median over rounds of the per-round ratio. It also checks that both give the same numbers
(the kernels' arithmetic is elementwise over lanes: the vector width changes no rounding).

Cases: the propagation benchmark's (``benchmarks/propagation.py``, 1024 × 1000 unless said)
and the preintegration benchmark's float64 workloads (``benchmarks/preintegration.py``).
Writes ``benchmarks/results/vector-width-<machine>.json`` and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import datetime
import json
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import preintegration as PB  # noqa: E402
import propagation as P  # noqa: E402

import jaximu  # noqa: E402

WIDE = {"xla_cpu_prefer_vector_width": 512}


def propagation_case(kind, scheme, dtype, save="final", B=1024, T=1000, jac="analytic"):
    case = dict(kind=kind, scheme=scheme, save=save, B=B, T=T, dtype=dtype, jac=jac)
    fn, args = P.build(case)
    what = "mean" if kind == "mean" else f"covariance ({jac})"
    name = f"{what}, {scheme}, {'final' if save == 'final' else 'every step stored'}"
    return name, dtype, f"{B} × {T}", fn, args, B * T


def preintegration_case(workload, scheme="euler"):
    long, windows, bias = PB.make_inputs(100_000, 4096, 200)
    data = long if workload == "long" else windows
    args = tuple(jnp.asarray(x, jnp.float64) for x in data)
    b = jaximu.ImuBias(jnp.asarray(bias[0]), jnp.asarray(bias[1]))
    noise = jaximu.ImuNoise.euroc()

    def fn(g, a, d):
        return jaximu.preintegrate(g, a, d, b, noise, scheme)

    size = "1 × 100000" if workload == "long" else "4096 × 200"
    n = int(np.prod(args[0].shape[:-1]))
    return f"preintegrate, {scheme}, default method", "float64", size, fn, args, n


def cases(quick):
    if quick:
        yield propagation_case("mean", "euler", "float32", B=256, T=200)
        yield propagation_case("cov", "euler", "float32", B=256, T=200)
        yield propagation_case("cov", "euler", "float64", B=256, T=200)
        return
    for dtype in ("float32", "float64"):
        yield propagation_case("mean", "euler", dtype)
    yield propagation_case("mean", "midpoint", "float32")
    yield propagation_case("mean", "rk4", "float32")
    yield propagation_case("mean", "euler", "float32", save="all")
    for dtype in ("float32", "float64"):
        yield propagation_case("cov", "euler", dtype)
    yield propagation_case("cov", "euler", "float32", jac="autodiff")
    yield propagation_case("cov", "midpoint", "float32")
    yield propagation_case("cov", "rk4", "float32")
    yield propagation_case("cov", "euler", "float32", save="all", T=200)
    yield preintegration_case("windows")
    yield preintegration_case("long")
    yield preintegration_case("windows", "midpoint")


def measure(fn, args, n, rounds, reps):
    fns = {"256": jax.jit(fn), "512": jax.jit(fn, compiler_options=WIDE)}
    compile_s, outs = {}, {}
    for k, f in fns.items():
        t0 = time.perf_counter()
        f.lower(*args).compile()
        compile_s[k] = time.perf_counter() - t0
        outs[k] = [
            np.asarray(x, np.float64)
            for x in jax.tree_util.tree_leaves(jax.block_until_ready(f(*args)))
        ]
    # the largest difference relative to the largest value of each output
    rel = max(
        float(
            np.max(np.abs(x - y), initial=0.0)
            / max(np.max(np.abs(x), initial=0.0), np.finfo(np.float64).tiny)
        )
        for x, y in zip(outs["256"], outs["512"])
    )
    rates = {k: [] for k in fns}
    for _ in range(rounds):
        for k, f in fns.items():
            best = np.inf
            for _ in range(reps):
                t0 = time.perf_counter()
                jax.block_until_ready(f(*args))
                best = min(best, time.perf_counter() - t0)
            rates[k].append(n / best)
    ratio = np.asarray(rates["512"]) / np.asarray(rates["256"])
    return dict(
        rate_256=float(np.median(rates["256"])),
        rate_512=float(np.median(rates["512"])),
        ratio_median=float(np.median(ratio)),
        ratio_min=float(ratio.min()),
        ratio_max=float(ratio.max()),
        compile_256_s=compile_s["256"],
        compile_512_s=compile_s["512"],
        max_rel_difference=rel,
    )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="three small cases (smoke test)")
    ap.add_argument("--rounds", type=int, default=6, help="alternating rounds (default 6)")
    ap.add_argument("--reps", type=int, default=3, help="runs per variant and round, best kept")
    ap.add_argument("--out", type=Path, help="JSON output path (default benchmarks/results/...)")
    args = ap.parse_args(argv)
    info = P.machine_info()
    print(
        f"# XLA:CPU vector width 512 against 256 on {info['cpu_model']} "
        f"({info['cpu_count']} CPUs), jax {jax.__version__}",
        flush=True,
    )
    rows = []
    t_start = time.perf_counter()
    for name, dtype, size, fn, fargs, n in cases(args.quick):
        r = measure(fn, fargs, n, args.rounds, args.reps)
        rows.append(dict(case=name, dtype=dtype, size=size, **r))
        print(
            f"- {name}, {dtype}, {size}: {r['rate_256'] / 1e6:.2f} → {r['rate_512'] / 1e6:.2f} "
            f"M samples/s, {r['ratio_median']:.2f}× [{r['ratio_min']:.2f}, "
            f"{r['ratio_max']:.2f}], compile {r['compile_256_s']:.2f} / "
            f"{r['compile_512_s']:.2f} s, largest relative difference "
            f"{r['max_rel_difference']:.1e}",
            flush=True,
        )
    print(
        "\n| case | dtype | B × T | 256-bit, samples/s | 512-bit | ratio (median of rounds, "
        "range) | compile s, 256 / 512 | results differ by |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['case']} | {r['dtype']} | {r['size']} | {r['rate_256'] / 1e6:.2f} M | "
            f"{r['rate_512'] / 1e6:.2f} M | {r['ratio_median']:.2f}× ({r['ratio_min']:.2f}–"
            f"{r['ratio_max']:.2f}) | {r['compile_256_s']:.2f} / {r['compile_512_s']:.2f} | "
            f"{r['max_rel_difference']:.0e} |"
        )
    out = args.out or (
        P.RESULTS_DIR / f"vector-width-{P.machine_slug(info)}{'-quick' if args.quick else ''}.json"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = dict(
        benchmark="XLA:CPU prefer_vector_width 512 vs 256",
        date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        machine=info,
        settings=dict(rounds=args.rounds, reps=args.reps, quick=args.quick),
        total_s=time.perf_counter() - t_start,
        rows=rows,
    )
    out.write_text(json.dumps(doc, indent=1))
    print(f"\nwrote {out}")


if __name__ == "__main__":
    main()
