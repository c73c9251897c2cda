"""Leave-one-recording-out model selection (:func:`jaximu.learning.train` with
``TrainConfig(selection="leave_one_out" | "leave_one_out_worst")``): each recording is left
out in turn, a model trained on the others, the left-out recording integrated whole at every
validation; the step chosen on these folds is the one kept of the model trained on all. No
recording ever judges a model trained on it."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import numpy as np

from jaximu.learning import _validation

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


def accel_ratio(rows) -> float:
    """The accelerometer correction's score from validation windows ``rows`` (a list, one
    per validation part, of :func:`jaximu.learning._validation.window_errors`' dicts): the
    mean, over the parts, the window lengths and the two errors (``|δv|`` [m/s], ``|δp|``
    [m]), of ``learned / learned_gyro``, the dead reckoning with the corrected
    accelerometer over that with the same gyro and the constant accelerometer bias: 1
    without a correction, below 1 where it helps."""
    r = [x[w]["learned"][i] / x[w]["learned_gyro"][i] for x in rows for w in x for i in (0, 1)]
    if not r:
        raise ValueError("accel_ratio needs the windows of one validation part or more")
    return float(np.mean(r))


def with_accel(model, source):
    """``model`` with the accelerometer's own layers and correction taken from ``source``
    (both :class:`jaximu.learning.Denoiser` with ``ModelConfig.accel_network``)."""
    return eqx.tree_at(
        lambda m: (m.accel_layers, m.accel_out), model, (source.accel_layers, source.accel_out)
    )


class AccelChoice:
    """The accelerometer's own layers (``ModelConfig.accel_network``) kept from their own
    step: the one with the lowest :func:`accel_ratio` on the 1-s and 5-s windows of the
    validation parts ``parts`` (indices into the validation batch: those with true
    velocities and 5 s or more), step 0 (no correction, ratio 1) a candidate. The gyro's
    layers are kept by the attitude; with layers of their own the two never share a
    weight, so each part is kept as it was at its step."""

    def __init__(self, model, parts: list[int], dt: float):
        self.best = (1.0, model, 0)
        self.parts, self.dt = parts, dt

    def judge(self, ema, vdata, step: int) -> float | None:
        """The ratio of the model ``ema`` at ``step`` (None without validation windows)."""
        if not self.parts:
            return None
        rows = _validation.window_errors(ema, vdata, self.dt, (1.0, 5.0))
        ratio = accel_ratio([rows[i] for i in self.parts])
        if ratio < self.best[0]:
            self.best = (ratio, ema, step)
        return ratio

    def apply(self, model, record: dict, say):
        """``model`` with the kept accelerometer layers; their step and ratio recorded."""
        ratio, source, step = self.best
        record.update(accel_step=step, validation_accel_ratio=ratio)
        if not self.parts:
            say(
                "no validation part with true velocities of 5 s or more: the accelerometer's "
                "correction is kept untrained (zero)"
            )
        else:
            say(
                f"accelerometer layers: step {step} (validation dead reckoning {ratio:.3f} × "
                "the constant accelerometer bias's, 1-s and 5-s windows)"
            )
        return with_accel(model, source)
