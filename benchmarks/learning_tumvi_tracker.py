"""The gravity-aided gyro-bias tracker alone on whole recordings, for a grid of its settings.

    python benchmarks/learning_tumvi_tracker.py --data DIR... [--set K=V[,V...] ...] [--json FILE]

The tracker (:mod:`jaximu.learning.tracking`) has no learned weights: its settings are the
model's (:class:`jaximu.learning.ModelConfig`) and its priors come from the training
recordings (zero bias and the floor's spread for a pose-only ground truth; with
``--leave-one-out`` each recording's from the others only, as a recording never trained on). Each recording
is integrated whole from its first true attitude with the tracked bias removed (the
"tracker" row of ``jaximu learn evaluate``) and the mean AOE at the ground truth's stamps is
printed beside the raw gyro's, for every combination of the ``--set`` values
(``--set velocity_sigma=1,3,10 --set standstill=true,false``).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json

import jax
import jax.numpy as jnp
import numpy as np

from jaximu import learning
from jaximu.learning._batches import fitted_config
from jaximu.learning.evaluation import _plain_run, _tracked_gyro, stamp_steps


def _mean_aoe(gyro, seq) -> float:
    """Mean AOE [deg] of ``gyro`` ``(T, 3)`` integrated whole from the first true attitude,
    at the ground truth's stamps (as :func:`jaximu.learning.evaluate_sequence`)."""
    k, h = stamp_steps(seq)
    _, q_ref = seq.stamps()
    f = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    aoe, _ = _plain_run(f(gyro), f(seq.q[0]), f(seq.dt), jnp.asarray(k), f(h), f(q_ref))
    return float(np.degrees(np.asarray(aoe)).mean())


def _values(default, text: str):
    if isinstance(default, bool):
        return [v.lower() in ("1", "true", "yes") for v in text.split(",")]
    if isinstance(default, tuple):  # one number for all three axes
        return [(float(v),) * 3 for v in text.split(",")]
    return [type(default)(v) for v in text.split(",")]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", nargs="+", required=True, help="sequence folders")
    ap.add_argument("--set", nargs="*", default=[], help="ModelConfig KEY=V1,V2,...")
    ap.add_argument("--json", help="append the rows here (JSON lines)")
    ap.add_argument(
        "--leave-one-out",
        action="store_true",
        help="each recording's priors (constant bias, spreads) from the others alone",
    )
    a = ap.parse_args(argv)
    seqs = [learning.load_sequence(p) for p in a.data]
    base = fitted_config(learning.ModelConfig(), seqs, seqs[0].rate_hz)

    def priors(i):  # the configuration the recording i is tracked with
        others = [s for j, s in enumerate(seqs) if j != i] if a.leave_one_out else seqs
        return fitted_config(learning.ModelConfig(), others, seqs[0].rate_hz)

    grid = {}
    for s in a.set:
        key, _, text = s.partition("=")
        grid[key] = _values(getattr(base, key), text)
    for combo in itertools.product(*grid.values()) if grid else [()]:
        kw = dict(zip(grid, combo))
        row = {"settings": kw, "raw": {}, "tracker": {}, "leave_one_out": a.leave_one_out}
        for i, s in enumerate(seqs):
            model = learning.Denoiser(dataclasses.replace(priors(i), **kw), jax.random.key(0))
            g, acc = jnp.asarray(s.gyro, jnp.float32), jnp.asarray(s.accel, jnp.float32)
            row["raw"][s.name] = round(_mean_aoe(g, s), 3)
            row["tracker"][s.name] = round(_mean_aoe(_tracked_gyro(model, g, acc), s), 3)
        mean = sum(row["tracker"].values()) / len(seqs)
        row["tracker_mean"] = round(mean, 3)
        print(json.dumps(row), flush=True)
        if a.json:
            with open(a.json, "a") as f:
                f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
