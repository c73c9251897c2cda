"""In-process A/B of the dispatch table's kernel choices on the current backend.

Each case (the public entries, wrapped in ``jax.jit``) runs under three tables:

* ``new``: the dispatch table as it is (``jaximu.engine._dispatch.TABLE``);
* ``generic``: an empty table, so every entry runs the generic ``lax.scan`` kernels;
* ``soa``: the CPU's structure-of-arrays rows on every backend (the table before the
  accelerator rows, less the CPU's float64-only chunked row), the covariance sequential;
* ``sequential``: the table as it is less the covariance's time chunks
  (``soa_cov_chunked``): with ``new``, where the chunks pay for one trajectory
  (``ONLY="cov analytic euler final 1x"``: 256 to 10^5 steps).

and prints, per case, samples/s, compile s and the largest difference of the outputs
from the first table's relative to their largest value (rounding: the tables pick
different kernels). Written for the first GPU lent to the project (docs/DESIGN.md, "On a
GPU"); on the CPU it shows the same choices from the other side. JAX's caches are cleared
between tables (a traced entry does not key on the table).

Usage::

    python benchmarks/dispatch_ab.py                    # every case, every table
    ONLY="cov analytic" python benchmarks/dispatch_ab.py  # cases whose name contains it
    VARIANTS=new,generic BUDGET=300 python benchmarks/dispatch_ab.py

Writes ``$OUT/dispatch_ab.json`` (``OUT`` defaults to ``benchmarks/results``, the file then
named ``dispatch-ab-<machine>.json``).
"""

import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # propagation.py beside it
import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
import propagation as P  # noqa: E402

import jaximu  # noqa: E402
import jaximu.engine._dispatch as dsp  # noqa: E402

TABLE0 = dsp.TABLE
SOA_TABLE = tuple(
    r._replace(
        backends=("cpu", "accelerator"), min_lanes=min(r.min_lanes, 32) if r.entry == "mean" else 1
    )
    for r in TABLE0
    if not (r.kernel == "soa_mean_chunked" and "cpu" in r.backends)
    and not (r.entry == "covariance" and r.backends == ("accelerator",))
    and r.kernel != "soa_cov_chunked"
)
# the accelerator's chunked row first among the mean rows after the 32-lane one
VARIANTS = {
    "new": dict(table=TABLE0),
    "generic": dict(table=()),
    "soa": dict(table=SOA_TABLE),
    "sequential": {"table": tuple(r for r in TABLE0 if r.kernel != "soa_cov_chunked")},
}


def apply(v):
    dsp.TABLE = v["table"]
    jax.clear_caches()


def case(kind, scheme, save, B, T, dtype, jac=None, vmap=False, attitude="quaternion"):
    name = (
        f"{kind} {jac + ' ' if jac else ''}{scheme} {save}"
        + ("" if attitude == "quaternion" else " " + attitude)
        + (" vmap" if vmap else "")
    )
    return dict(
        section=kind,
        name=name,
        kind=kind,
        scheme=scheme,
        jac=jac,
        save=save,
        B=B,
        T=T,
        dtype=dtype,
        vmap=vmap,
        rotating=False,
        lever=False,
        attitude=attitude,
    )


def preint_fn(B, T, dtype, method="auto"):
    rng = np.random.default_rng(0)
    g = jnp.asarray(rng.standard_normal((B, T, 3)) * 0.3, dtype)
    a = jnp.asarray(rng.standard_normal((B, T, 3)) + np.array([0, 0, 9.81]), dtype)
    d = jnp.full((B, T), 0.005, dtype)
    b = jaximu.ImuBias(jnp.zeros(3, dtype), jnp.zeros(3, dtype))
    noise = jaximu.ImuNoise.euroc()
    if B == 1:
        g, a, d = g[0], a[0], d[0]
    fn = lambda g, a, d: jaximu.preintegrate(g, a, d, b, noise, "euler", method)  # noqa: E731
    return fn, (g, a, d)


def run(fn, args, B, T, reps=5, min_time=0.5):
    t0 = time.perf_counter()
    comp = jax.jit(fn).lower(*args).compile()
    c = time.perf_counter() - t0
    out = jax.block_until_ready(comp(*args))
    runs = []
    while len(runs) < reps or (sum(runs) < min_time and len(runs) < 40):
        t = time.perf_counter()
        jax.block_until_ready(comp(*args))
        runs.append(time.perf_counter() - t)
    r = float(np.median(runs))
    return dict(compile_s=c, run_s=r, rate=B * T / r), out


def reldiff(a, b):
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    m = 0.0
    for x, y in zip(la, lb):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        m = max(m, float(np.max(np.abs(x - y)) / (np.max(np.abs(y)) + 1e-300)))
    return m


CASES = []
for dt in ("float32", "float64"):
    CASES += [
        case("mean", "euler", "final", 1024, 1000, dt),
        case("mean", "euler", "final", 16384, 200, dt),
        case("mean", "midpoint", "final", 1024, 1000, dt),
        case("cov", "euler", "final", 1024, 1000, dt, jac="analytic"),
        case("cov", "euler", "final", 4096, 250, dt, jac="analytic"),
        case("cov", "euler", "final", 16384, 200, dt, jac="analytic"),
        case("cov", "euler", "final", 4096, 250, dt, jac="autodiff"),
        case("cov", "euler", "final", 16384, 200, dt, jac="autodiff"),
        case("cov", "midpoint", "final", 4096, 250, dt, jac="analytic"),
        case("mean", "euler", "final", 1, 100_000, dt),
        case("mean", "euler", "all", 1, 100_000, dt),
        case("mean", "midpoint", "all", 1, 100_000, dt),
    ]
    # one trajectory's covariance: sequential or in time chunks, by length (the crossover)
    CASES += [
        case("cov", "euler", "final", 1, T, dt, jac="analytic")
        for T in (256, 512, 1024, 2048, 4096, 100_000)
    ]
PRE = [
    ("preint 4096x200", 4096, 200, "float64"),
    ("preint 1x100000", 1, 100_000, "float64"),
    ("preint 1024x200", 1024, 200, "float64"),
]

only = os.environ.get("ONLY")
names = os.environ.get("VARIANTS", ",".join(VARIANTS)).split(",")
results = []
budget = float(os.environ.get("BUDGET", "420"))
t_start = time.perf_counter()
print(jax.devices(), jax.__version__, flush=True)
jobs = [("prop", c) for c in CASES] + [("pre", p) for p in PRE]
for kind, c in jobs:
    label = c["name"] + f" {c['B']}x{c['T']} {c['dtype']}" if kind == "prop" else f"{c[0]} {c[3]}"
    if only and only not in label:
        continue
    ref = None
    for vn in names:
        if time.perf_counter() - t_start > budget:
            print("budget out", flush=True)
            break
        apply(VARIANTS[vn])
        try:
            if kind == "prop":
                fn, args = P.build(c)
                B, T = c["B"], c["T"]
            else:
                fn, args = preint_fn(c[1], c[2], c[3])
                B, T = c[1], c[2]
            res, out = run(fn, args, B, T)
            res["diff"] = 0.0 if ref is None else reldiff(out, ref)
            ref = out if ref is None else ref
        except Exception as e:  # noqa: BLE001
            res = dict(error=repr(e)[:300])
        res.update(case=label, variant=vn)
        results.append(res)
        print(json.dumps(res), flush=True)
        out = None
out_dir = os.environ.get("OUT")
info = P.machine_info()
path = (
    os.path.join(out_dir, "dispatch_ab.json")
    if out_dir
    else os.path.join(
        os.path.dirname(os.path.abspath(__file__)),
        "results",
        f"dispatch-ab-{P.machine_slug(info)}.json",
    )
)
with open(path, "w") as fh:
    json.dump(dict(machine=info, results=results), fh, indent=1)
print("\n| case | " + " | ".join(names) + " |")
by = {}
for r in results:
    by.setdefault(r["case"], {})[r["variant"]] = r
for cname, d in by.items():
    cells = []
    for vn in names:
        r = d.get(vn)
        cells.append(
            ""
            if r is None
            else (
                "ERR"
                if "error" in r
                else f"{r['rate'] / 1e6:.1f}M c{r['compile_s']:.1f} d{r['diff']:.0e}"
            )
        )
    print(f"| {cname} | " + " | ".join(cells) + " |")
