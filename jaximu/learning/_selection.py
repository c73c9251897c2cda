"""Leave-one-recording-out model selection (:func:`jaximu.learning.train` with
``TrainConfig(selection="leave_one_out" | "leave_one_out_worst")``): each recording is left
out in turn, a model trained on the others, the left-out recording integrated whole at every
validation; the step chosen on these folds is the one kept of the model trained on all. No
recording ever judges a model trained on it."""

from __future__ import annotations

import dataclasses

import numpy as np

CRITERIA = ("leave_one_out", "leave_one_out_worst")


def choose_step(aoe, criterion: str) -> int:
    """The index of the kept step from the folds' errors ``aoe`` ``(folds, steps)`` [deg],
    column 0 the untrained network (the tracker or constant bias alone): ``"leave_one_out"``,
    the lowest mean over the folds; ``"leave_one_out_worst"``, the lowest worst ratio
    ``aoe[f, j] / aoe[f, 0]`` over the folds, so a step is kept only if it is below the
    untrained network on every left-out recording (column 0, ratio 1, otherwise; the first
    of equal ones)."""
    aoe = np.asarray(aoe, np.float64)
    if criterion == "leave_one_out":
        return int(np.argmin(aoe.mean(0)))
    if criterion == "leave_one_out_worst":
        return int(np.argmin((aoe / aoe[:, :1]).max(0)))
    raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")


def leave_one_out(fit, sequences, cfg, model_config, seed, minutes, say):
    """The folds and the model trained on all at the chosen step (``fit``: the training's
    ``_fit``, whose ``held_out`` validates a fold on the recording left out and whose
    ``keep_step`` keeps the chosen step, chosen without any recording's own seconds)."""
    fold_cfg = dataclasses.replace(cfg, selection="validation", calibrate_uncertainty=False)
    folds = []
    for i, s in enumerate(sequences):
        others = sequences[:i] + sequences[i + 1 :]
        say(f"fold {i + 1}/{len(sequences)}: {s.name} left out")
        r = fit(others, fold_cfg, model_config, seed, minutes, lambda x: None, held_out=s)
        rec = r.record
        aoe = [rec["validation_untrained_deg"][0]]
        aoe += [h["validation_aoe_mean_deg"][0] for h in rec["history"]]
        steps = [0] + [h["step"] for h in rec["history"]]
        folds.append({"left_out": s.name, "trained_on": rec["sequences"], "steps": steps})
        folds[-1]["aoe_mean_deg"] = aoe
        say(f"  {s.name}: " + " ".join(f"{k}: {x:.2f}°" for k, x in zip(steps, aoe)))
    steps = min((f["steps"] for f in folds), key=len)  # (a fold cut short by minutes)
    table = [f["aoe_mean_deg"][: len(steps)] for f in folds]
    mean = [float(x) for x in np.mean(table, 0)]
    j = choose_step(table, cfg.selection)
    say(
        "leave-one-out: mean AOE of the left-out recordings by step "
        + " ".join(f"{k}: {x:.2f}°" for k, x in zip(steps, mean))
        + f"; keeping step {steps[j]} of the model trained on all ({cfg.selection})"
    )
    result = fit(sequences, cfg, model_config, seed, minutes, say, keep_step=(steps[j], mean[j]))
    result.record["leave_one_out"] = {
        "folds": folds,
        "steps": steps,
        "mean_aoe_deg": mean,
        "criterion": cfg.selection,
        "chosen_step": steps[j],
    }
    return result
