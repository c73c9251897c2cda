"""Where time chunks beat sequential launches: the crossover the dispatch table's chunked
rows need on an accelerator (``jaximu.engine._dispatch``: ``MEAN_CHUNK_STEPS``,
``MEAN_CHUNK_LANES``, ``COV_CHUNK_STEPS``, ``COV_CHUNK_LANES``; docs/DESIGN.md, "Dispatch").

Each case (a public entry under ``jax.jit``, Euler, closed-form blocks) runs under two tables:

* ``sequential``: the table less its time chunks (``soa_mean_chunked``, ``soa_cov_chunked``);
* ``chunked``: the chunked rows for every length and batch (their ``min_steps`` 1,
  ``max_lanes`` none), the chunks as many as the dispatch cuts (``mean_chunks``,
  ``covariance_chunks``: none shorter than ``MIN_CHUNK_STEPS``);

and prints run times, compile times, the winner and the relative difference of the results;
then, per sweep, the suggested threshold: the shortest length from which the chunks win at
every longer length measured (a length sweep), or the largest batch up to which they win at
every smaller one (a batch sweep). Sweeps run in order of what the table needs most, each
case only while the budget lasts (``BUDGET`` s, default 140); a sequential run predicted
over ``SEQ_MAX_S`` (default 3 s) is extrapolated from the sweep's longest measured one
(its cost per step is constant: one launch a step). The results' relative difference
is printed beside each (rounding: the two paths sum in different orders).

Usage (on the accelerator; the CPU runs it too, with the CPU's table)::

    python benchmarks/chunk_crossover.py
    BUDGET=60 ONLY="cov" python benchmarks/chunk_crossover.py
    AS_BACKEND=accelerator BUDGET=30 python benchmarks/chunk_crossover.py  # a smoke test of
        # the accelerator's dispatch on the CPU (as tests/_shared.dispatch_as)

Writes ``benchmarks/results/chunk-crossover-<machine>.json`` (``$OUT/chunk_crossover.json``
when ``OUT`` is set).
"""

import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # propagation.py beside it
import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
import propagation as P  # noqa: E402

import jaximu.engine._dispatch as dsp  # noqa: E402

if os.environ.get("AS_BACKEND"):
    dsp.backend = lambda: os.environ["AS_BACKEND"]
TABLE0 = dsp.TABLE
CHUNKED = ("soa_mean_chunked", "soa_cov_chunked")
TABLES = {
    "sequential": tuple(r for r in TABLE0 if r.kernel not in CHUNKED),
    "chunked": tuple(
        r._replace(min_steps=1, max_lanes=None) if r.kernel in CHUNKED else r for r in TABLE0
    ),
}

# (name, kind, save, dtype, [(B, T), ...], sweep over "T" or "B"), in the order the table
# needs them: a coarse pass over every sweep first, then finer points of the same sweeps (a
# chunked covariance compiles for seconds, and the budget may end the run early)
SWEEPS = [
    ("cov final 1 trajectory", "cov", "final", "float64", [(1, T) for T in (128, 256, 512)], "T"),
    ("mean final 1 trajectory", "mean", "final", "float32", [(1, T) for T in (64, 128, 256)], "T"),
    (
        "mean final batch x 200",
        "mean",
        "final",
        "float32",
        [(B, 200) for B in (1024, 16384, 32768)],
        "B",
    ),
    (
        "cov final batch x 256",
        "cov",
        "final",
        "float64",
        [(B, 256) for B in (1024, 4096, 16384)],
        "B",
    ),
    ("cov all 1 trajectory", "cov", "all", "float64", [(1, T) for T in (256, 512)], "T"),
    ("mean all 1 trajectory", "mean", "all", "float32", [(1, T) for T in (128, 256)], "T"),
    (
        "cov final 1 trajectory",
        "cov",
        "final",
        "float64",
        [(1, T) for T in (64, 1024, 4096, 100_000)],
        "T",
    ),
    (
        "mean final 1 trajectory",
        "mean",
        "final",
        "float32",
        [(1, T) for T in (512, 1024, 4096)],
        "T",
    ),
    ("cov all 1 trajectory", "cov", "all", "float64", [(1, T) for T in (128, 1024)], "T"),
    ("cov final batch x 256", "cov", "final", "float64", [(B, 256) for B in (64, 8192)], "B"),
    ("mean final batch x 200", "mean", "final", "float32", [(B, 200) for B in (8192, 65536)], "B"),
]


def case(kind, save, B, T, dtype):
    return dict(
        section=kind,
        name=f"{kind} {'analytic ' if kind == 'cov' else ''}euler {save}",
        kind=kind,
        scheme="euler",
        jac="analytic" if kind == "cov" else None,
        save=save,
        B=B,
        T=T,
        dtype=dtype,
        vmap=False,
        rotating=False,
        lever=False,
        attitude="quaternion",
    )


def timed(fn, args, reps=3, min_time=0.2):
    """``(compile s, best run s, output)`` of ``jax.jit(fn)``."""
    t0 = time.perf_counter()
    comp = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    out = jax.block_until_ready(comp(*args))
    runs = []
    while len(runs) < reps or (sum(runs) < min_time and len(runs) < 30):
        t = time.perf_counter()
        jax.block_until_ready(comp(*args))
        runs.append(time.perf_counter() - t)
    return compile_s, min(runs), out


def reldiff(a, b):
    m = 0.0
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        m = max(m, float(np.max(np.abs(x - y)) / (np.max(np.abs(y)) + 1e-300)))
    return m


def suggest(rows, axis):
    """The threshold a sweep suggests (module docstring), or a sentence why none."""
    done = [r for r in rows if r.get("winner")]
    if not done:
        return None
    if axis == "T":
        wins = [
            r["T"] for i, r in enumerate(done) if all(s["winner"] == "chunked" for s in done[i:])
        ]
        return min(wins) if wins else "sequential at every length measured"
    wins = [
        r["B"] for i, r in enumerate(done) if all(s["winner"] == "chunked" for s in done[: i + 1])
    ]
    return max(wins) if wins else "sequential at every batch measured"


def main():
    budget = float(os.environ.get("BUDGET", "140"))
    seq_max = float(os.environ.get("SEQ_MAX_S", "3"))
    only = os.environ.get("ONLY")
    t_start = time.perf_counter()
    info = P.machine_info()
    print(jax.devices(), jax.__version__, f"budget {budget:.0f} s", flush=True)
    sweeps = {}
    for name, kind, save, dtype, sizes, axis in SWEEPS:
        if only and only not in name:
            continue
        sweep = sweeps.setdefault(
            name, dict(name=name, kind=kind, save=save, dtype=dtype, axis=axis, rows=[])
        )
        rows = sweep["rows"]
        for B, T in sizes:
            if time.perf_counter() - t_start > budget:
                print(f"budget out before {name} {B}x{T}", flush=True)
                break
            # one launch a step: the sweep's longest sequential run so far gives its cost
            seq = [
                r
                for r in rows
                if axis == "T" and "sequential_run_s" in r and not r.get("sequential_extrapolated")
            ]
            longest = max(seq, key=lambda r: r["T"]) if seq else None
            per_step = longest["sequential_run_s"] / longest["T"] if longest else None
            c = case(kind, save, B, T, dtype)
            fn, args = P.build(c)
            row = dict(B=B, T=T)
            outs = {}
            for variant in ("chunked", "sequential"):
                dsp.TABLE = TABLES[variant]
                jax.clear_caches()
                if variant == "sequential" and per_step and per_step * T * 3 > seq_max:
                    row["sequential_run_s"] = per_step * T
                    row["sequential_extrapolated"] = True
                    continue
                try:
                    comp_s, run_s, outs[variant] = timed(fn, args)
                except Exception as e:  # noqa: BLE001 (an out-of-memory shape is a result)
                    row[f"{variant}_error"] = repr(e)[:200]
                    continue
                row[f"{variant}_run_s"], row[f"{variant}_compile_s"] = run_s, comp_s
            dsp.TABLE = TABLE0
            if len(outs) == 2:
                row["diff"] = reldiff(outs["chunked"], outs["sequential"])
            outs = None
            if "chunked_run_s" in row and "sequential_run_s" in row:
                ratio = row["sequential_run_s"] / row["chunked_run_s"]
                row["speedup"] = ratio
                row["winner"] = "chunked" if ratio > 1 else "sequential"
            rows.append(row)
            fmt = lambda k: f"{row[k] * 1e3:9.3f} ms" if k in row else "      —   "  # noqa: E731
            print(
                f"{name:26s} {dtype} {B:6d}x{T:<7d} chunked {fmt('chunked_run_s')} "
                f"(c {row.get('chunked_compile_s', 0):.1f} s)  sequential "
                f"{fmt('sequential_run_s')}{'*' if row.get('sequential_extrapolated') else ' '}"
                f" -> {row.get('winner', '?'):10s} x{row.get('speedup', 0):.2f}"
                f"  diff {row.get('diff', float('nan')):.1e}",
                flush=True,
            )
            write(list(sweeps.values()), info, budget, t_start)
    sweeps = list(sweeps.values())
    for s in sweeps:
        s["rows"].sort(key=lambda r: r[s["axis"]])
        s["suggested"] = suggest(s["rows"], s["axis"])
    on = dsp.backend()
    print(
        "\n* sequential extrapolated from the sweep's longest measured run (one launch a "
        f"step)\nSuggested thresholds (the table now, {on}: mean from "
        f"{dsp.MEAN_CHUNK_STEPS} steps up to {dsp.MEAN_CHUNK_LANES} sequences, the "
        f"accelerator's only; covariance from {dsp.COV_CHUNK_STEPS[on]} steps up to "
        f"{dsp.COV_CHUNK_LANES[on]} sequences):"
    )
    for s in sweeps:
        what = "chunks from length" if s["axis"] == "T" else "chunks up to batch"
        print(f"  {s['name']:32s} {s['dtype']}: {what} {s['suggested']}")
    print(f"Wrote {write(sweeps, info, budget, t_start)}", flush=True)


def write(sweeps, info, budget, t_start):
    """The JSON of the sweeps so far (after every case: a run cut by its time limit keeps
    what it measured)."""
    out_dir = os.environ.get("OUT")
    path = (
        os.path.join(out_dir, "chunk_crossover.json")
        if out_dir
        else os.path.join(
            os.path.dirname(os.path.abspath(__file__)),
            "results",
            f"chunk-crossover-{P.machine_slug(info)}.json",
        )
    )
    with open(path, "w") as fh:
        json.dump(
            dict(
                machine=info,
                budget_s=budget,
                total_s=time.perf_counter() - t_start,
                table=dict(
                    mean_chunk_steps=dsp.MEAN_CHUNK_STEPS,
                    mean_chunk_lanes=dsp.MEAN_CHUNK_LANES,
                    cov_chunk_steps=dsp.COV_CHUNK_STEPS,
                    cov_chunk_lanes=dsp.COV_CHUNK_LANES,
                ),
                sweeps=sweeps,
            ),
            fh,
            indent=1,
        )
    return path


if __name__ == "__main__":
    main()
