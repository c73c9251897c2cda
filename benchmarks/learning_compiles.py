"""The programs one `learning.train` (or one `jaximu learn evaluate`) compiles, and where
its wall time goes.

Every program XLA compiles is logged (``jax_log_compiles``) and counted by name; the
training's own record gives its stages' times (``stage_seconds``). On a device whose
compiles are slow (a GPU's take seconds each), a training that compiles a program per
sequence, or runs a network op by op, spends its time there, not in its steps.

    python benchmarks/learning_compiles.py DATA/euroc_v1_02_medium DATA/euroc_v2_01_easy \
        [--steps 20] [--train-seconds 40] [--selection leave_one_out] [--json out.json]
    python benchmarks/learning_compiles.py DATA/... --evaluate euroc [--json out.json]

With ``--evaluate MODEL`` it runs the command ``jaximu learn evaluate MODEL DATA...`` instead
(every recording's whole-run rows, dead-reckoning windows and windowed NEES).
"""

from __future__ import annotations

import argparse
import collections
import json
import logging
import re
import time

import jax


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="+", help="recording folders (imu.csv + ground truth)")
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--train-seconds", type=float, default=40.0)
    ap.add_argument(
        "--selection",
        default="validation",
        help="TrainConfig.selection: validation, or leave_one_out (a fold per recording)",
    )
    ap.add_argument("--evaluate", metavar="MODEL", help="time `jaximu learn evaluate MODEL`")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()

    jax.config.update("jax_log_compiles", True)
    compiles: list[tuple[str, float]] = []

    class Count(logging.Handler):
        def emit(self, r):
            m = re.search(r"Finished XLA compilation of (.*?) in ([0-9.e-]+) sec", r.getMessage())
            if m:
                compiles.append((m.group(1), float(m.group(2))))

    logger = logging.getLogger("jax")
    logger.addHandler(Count())
    logger.setLevel(logging.WARNING)
    logger.propagate = False  # counted, not printed

    if args.evaluate:
        _evaluate(args, compiles)
        return
    from jaximu import learning

    seqs = [learning.load_sequence(p) for p in args.data]
    cfg = learning.TrainConfig(
        steps=args.steps,
        validate_every=max(1, args.steps // 2),
        train_seconds=args.train_seconds,
        selection=args.selection,
    )
    t0 = time.perf_counter()
    r = learning.train(seqs, cfg, log=None)
    total = time.perf_counter() - t0
    print(
        f"train: {total:.1f} s from the call to its return ({len(seqs)} recordings, {args.steps} steps)"
    )
    print("stages [s]: " + ", ".join(f"{k} {v:.1f}" for k, v in r.record["stage_seconds"].items()))
    rows = _table(compiles)
    if args.json:
        out = {
            "command": "python benchmarks/learning_compiles.py "
            + " ".join(args.data)
            + f" --steps {args.steps} --train-seconds {args.train_seconds:g}"
            + f" --selection {args.selection}",
            "train_seconds_call": total,
            "stage_seconds": r.record["stage_seconds"],
            "programs_compiled": len(compiles),
            "compile_seconds": sum(s for _, s in compiles),
            "by_program": {n: {"count": len(ss), "seconds": sum(ss)} for n, ss in rows},
        }
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


def _table(compiles):
    """Print the compiles by program, most seconds first; return ``[(name, [seconds])]``."""
    by_name: dict[str, list[float]] = collections.defaultdict(list)
    for name, s in compiles:
        by_name[name].append(s)
    rows = sorted(by_name.items(), key=lambda x: -sum(x[1]))
    print(f"programs compiled: {len(compiles)}, {sum(s for _, s in compiles):.1f} s of compile")
    for name, ss in rows[:15]:
        print(f"  {len(ss):4d} × {name:40s} {sum(ss):7.2f} s")
    return rows


def _evaluate(args, compiles):
    from jaximu.cli import main as cli

    t0 = time.perf_counter()
    cli(["learn", "evaluate", args.evaluate, *args.data])
    total = time.perf_counter() - t0
    print(f"evaluate: {total:.1f} s from the call to its return ({len(args.data)} recordings)")
    rows = _table(compiles)
    if args.json:
        out = {
            "command": "python benchmarks/learning_compiles.py "
            + " ".join(args.data)
            + f" --evaluate {args.evaluate}",
            "evaluate_seconds_call": total,
            "programs_compiled": len(compiles),
            "compile_seconds": sum(s for _, s in compiles),
            "by_program": {n: {"count": len(ss), "seconds": sum(ss)} for n, ss in rows},
        }
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
