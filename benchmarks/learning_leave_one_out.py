"""Leave one recording out: how the training recipe does on a recording it never saw.

    python benchmarks/learning_leave_one_out.py --data DIR... [--seed S] [--set K=V ...]
        [--only NAME ...] [--json FILE]

The validation parts that :func:`jaximu.learning.train` selects its model on are the later
seconds of the training recordings themselves: the same flight, the same day, the same bias.
A test recording shares none of that, so the validation figures flatter any recipe that
learns each recording's own bias. Here each folder in turn is held out: a model is trained
on the others (their usual training and validation parts, the same settings and seed as
``jaximu learn train``) and the held-out recording is evaluated whole, integrated open loop
from its first true attitude, as ``jaximu learn evaluate`` does for the test split: raw
gyro, the constant bias of the training recordings, the learned model. ``--set`` changes a
:class:`jaximu.learning.TrainConfig` setting (``--set horizons=16,32``,
``--set gyro_bias_noise=3e-3``) to compare recipes on the same folds.

Each fold trains one model (about 4 minutes on 2 cores for the five EuRoC training
recordings), so the whole run takes about as long as five ``jaximu learn train``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

from _settings import replaced

from jaximu import learning


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", nargs="+", required=True, help="sequence folders (≥ 3)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", nargs="*", default=[], help="TrainConfig settings KEY=VALUE")
    ap.add_argument("--only", nargs="*", help="hold out only these folders' names")
    ap.add_argument("--json", help="append each fold's result here (JSON lines)")
    a = ap.parse_args(argv)
    config, _ = replaced(learning.TrainConfig(), a.set)
    seqs = [learning.load_sequence(p) for p in a.data]
    if len(seqs) < 3:
        raise SystemExit("--data: give at least three sequence folders (two train, one held out)")
    held = [s for s in seqs if not a.only or s.name in a.only]
    print(f"settings: {a.set or 'defaults'}, seed {a.seed}")
    print(f"{'held out':<24} {'raw':>7} {'const':>7} {'learned':>8} {'AYE c/l':>11} {'NEES':>6}")
    rows = []
    for h in held:
        t0 = time.perf_counter()
        result = learning.train([s for s in seqs if s is not h], config, seed=a.seed, log=None)
        report = learning.evaluate_sequence(result.model, h).to_json()
        m, y = report["aoe_mean_deg"], report["aye_mean_deg"]
        nees = report["nees_orientation"]
        print(
            f"{h.name:<24} {m['raw']:7.2f} {m['constant_bias']:7.2f} {m['learned']:8.2f} "
            f"{y['constant_bias']:5.2f}/{y['learned']:<5.2f} {nees:6.2f}"
            f"   ({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
        row = {"settings": a.set, "seed": a.seed, "held_out": h.name, **report}
        rows.append(row)
        if a.json:
            with pathlib.Path(a.json).open("a") as f:
                f.write(json.dumps(row) + "\n")
    if len(rows) > 1:
        mean = lambda k: sum(r["aoe_mean_deg"][k] for r in rows) / len(rows)  # noqa: E731
        worse = [
            r["held_out"]
            for r in rows
            if r["aoe_mean_deg"]["learned"] >= r["aoe_mean_deg"]["constant_bias"]
        ]
        print(
            f"{'mean':<24} {mean('raw'):7.2f} {mean('constant_bias'):7.2f} {mean('learned'):8.2f}"
            f"   learned not below the constant bias on: {', '.join(worse) or 'none'}"
        )


if __name__ == "__main__":
    main()
