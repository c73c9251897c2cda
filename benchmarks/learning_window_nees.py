"""The orientation NEES over windows of 1 s and 5 s each started from the true attitude
(:func:`jaximu.learning.window_nees`), beside the whole run's, on recordings a model never
trained on; optionally with the Gauss–Markov gyro bias fitted first, the network fixed, on
the validation parts of the model's own training recordings
(:func:`jaximu.learning.fit_bias_markov`, what ``jaximu learn train`` now does after setting
``σ_b``).

    python benchmarks/learning_window_nees.py MODEL --test DIR... [--fit-on DIR...] [--json FILE]

``MODEL``: a model folder or a shipped name; ``--test``: the recordings left out of its
training (each integrated whole, and in windows from its start); ``--fit-on``: its training
recordings, whose parts after the first 80 s (:func:`jaximu.learning.split`) the bias is
fitted on. A model trained on four of the five EuRoC recordings, evaluated on the fifth:

    jaximu learn train euroc_mh_03_medium euroc_mh_05_difficult euroc_v1_02_medium \\
        euroc_v2_03_difficult --out without_v2_01 --seed 0 --steps 100
    python benchmarks/learning_window_nees.py without_v2_01 --test euroc_v2_01_easy \\
        --fit-on euroc_mh_03_medium euroc_mh_05_difficult euroc_v1_02_medium euroc_v2_03_difficult
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

from jaximu import learning
from jaximu.learning import uncertainty


def figures(model, seq) -> dict:
    rep = learning.evaluate_sequence(model, seq)
    out = {"whole_run": rep.nees_orientation, "aoe_mean_deg": rep.metrics["learned"].aoe_mean}
    for w in (1.0, 5.0):
        t = uncertainty.window_nees_terms(model, seq, w)
        out[f"{w:g}s"] = uncertainty.average_nees(t, float(model.bias_sigma))
        out[f"{w:g}s_windows"] = int(len(t.r))
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model")
    p.add_argument("--test", nargs="+", required=True, metavar="DIR")
    p.add_argument("--fit-on", nargs="*", default=[], metavar="DIR")
    p.add_argument("--json", metavar="FILE")
    args = p.parse_args()
    model = learning.load(args.model)
    doc: dict = {"model": args.model, "bias_sigma": float(model.bias_sigma), "test": {}}
    tests = [learning.load_sequence(d) for d in args.test]
    models = {"constant_bias_model": model}
    if args.fit_on:
        seqs = [learning.load_sequence(d) for d in args.fit_on]
        starts = [len(s) - len(learning.split(s)[1]) for s in seqs]
        t0 = time.perf_counter()
        sm, tau = learning.fit_bias_markov(model, seqs, starts)
        doc["fit_on"] = [s.name for s in seqs]
        doc["bias_markov"] = {"sigma": sm, "time": tau, "seconds": time.perf_counter() - t0}
        print(f"Gauss–Markov bias fitted on {doc['fit_on']}: σ_m {sm:.3g} rad/s, τ {tau:.3g} s")
        models["with_gauss_markov_bias"] = uncertainty.with_bias_markov(model, sm, tau)
    for s in tests:
        doc["test"][s.name] = {k: figures(m, s) for k, m in models.items()}
        for k, row in doc["test"][s.name].items():
            print(
                f"{s.name} {k}: whole run {row['whole_run']:.3f}, 1 s {row['1s']:.2f}, "
                f"5 s {row['5s']:.2f}"
            )
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    main()
