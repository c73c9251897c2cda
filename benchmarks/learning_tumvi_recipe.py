"""A training recipe judged by leave-one-recording-out folds inside :func:`jaximu.learning.train`.

    python benchmarks/learning_tumvi_recipe.py --data DIR... [--set K=V ...] [--model K=V ...]
        [--seed S] [--out MODEL] [--json FILE]

Runs ``train(..., TrainConfig(selection="leave_one_out", ...))``: each recording is left out
in turn, a model trained on the others, the left-out recording integrated whole from its
first true attitude at every validated step (step 0: the untrained network, the tracked or
constant bias alone); the step with the lowest mean over the folds is kept of the model
trained on all. ``--set`` changes :class:`jaximu.learning.TrainConfig` settings
(``--set learning_rate=3e-4 validate_every=10``), ``--model`` :class:`jaximu.learning.ModelConfig`
ones (``--model velocity_sigma=3``). The folds' figures (mean AOE of each left-out recording
by step) and the chosen step are printed and appended as one JSON line; ``--out`` saves the
kept model. No recording the folds are given is a test recording: pass training ones only.
"""

from __future__ import annotations

import argparse
import json
import time

from _settings import replaced

from jaximu import learning
from jaximu.learning.alignment import shifted_reference


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", nargs="+", required=True, help="training sequence folders (≥ 2)")
    ap.add_argument("--set", nargs="*", default=[], help="TrainConfig settings KEY=VALUE")
    ap.add_argument("--model", nargs="*", default=[], help="ModelConfig settings KEY=VALUE")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", help="save the kept model to this folder")
    ap.add_argument("--json", help="append the result here (JSON lines)")
    ap.add_argument(
        "--reference-shift",
        type=float,
        default=0.0,
        help="train on the ground truth read at t + this [s] (its clock's offset)",
    )
    a = ap.parse_args(argv)
    cfg, train_kw = replaced(learning.TrainConfig(selection="leave_one_out"), a.set)
    mcfg, model_kw = replaced(learning.ModelConfig(), a.model)
    seqs = [learning.load_sequence(p) for p in a.data]
    if a.reference_shift:
        seqs = [shifted_reference(s, a.reference_shift) for s in seqs]
    t0 = time.perf_counter()
    r = learning.train(seqs, cfg, mcfg, seed=a.seed, log=print)
    loo = r.record["leave_one_out"]
    row = {
        "train_settings": train_kw,
        "model_settings": model_kw,
        "seed": a.seed,
        "reference_shift_s": a.reference_shift,
        "steps": loo["steps"],
        "folds": {f["left_out"]: [round(x, 3) for x in f["aoe_mean_deg"]] for f in loo["folds"]},
        "mean_aoe_deg": [round(x, 3) for x in loo["mean_aoe_deg"]],
        "chosen_step": loo["chosen_step"],
        "validation_history": {
            h["step"]: [round(x, 3) for x in h["validation_aoe_mean_deg"]]
            for h in r.record["history"]
        },
        "wall_seconds": round(time.perf_counter() - t0),
    }
    print(json.dumps(row))
    if a.json:
        with open(a.json, "a") as f:
            f.write(json.dumps(row) + "\n")
    if a.out:
        learning.save(a.out, r.model, r.record)


if __name__ == "__main__":
    main()
