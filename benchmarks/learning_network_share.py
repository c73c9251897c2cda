"""The network's own share on recordings left out of training: each fold's left-out AOE by
step, and what the network outputs there.

    python benchmarks/learning_network_share.py --data DIR... --label NAME [--folds NAME ...]
        [--steps N] [--set K=V ...] [--model-set K=V ...] [--no-bias-tracking] [--json FILE]

For each fold (one recording left out, the same recipe as ``jaximu learn train
--leave-one-out``'s folds: ``_fit`` with ``held_out``), the kept exponential average of the
weights is captured at every validation and, on the left-out recording, measured:

* ``aoe``: the whole-run mean AOE (the fold's judge; step 0 = the tracker alone);
* ``heldout_huber``: Brossard's increment loss (the training loss's rotation part, no noise,
  no dropout) on the left-out recording: does what the training lowers transfer?
* ``corr_mean``: the mean of the network's correction ``ω̂ − (ω_m − b̂)`` [rad/s] against
  ``resid_mean``, the mean of what the tracker leaves, ``ω_true − (ω_m − b̂)`` (``ω_true``
  differenced from the true attitude; the correction that would be right);
* ``corr_hf_rms``: the RMS of the correction minus its 1-s block means [rad/s] (its
  high-frequency part), ``corr_lf_rms`` the RMS of the 1-s block means;
* ``aoe_lf_only`` / ``aoe_hf_only`` / ``aoe_mean_only``: the AOE with only the correction's
  1-s block means, only what is left of it, or only its mean over the recording; and
  ``aoe_matrix_only`` / ``aoe_network_only``: with only the learned matrix's part ``C ω_m``
  or only the convolution's: which part of the correction helps or hurts.

``--ceilings`` trains nothing: for each left-out recording, what a correction after the
tracker could do at best (:func:`ceilings`).

The training's own loss at each validation (``train_huber``, the step's, with noise and
dropout) is recorded beside. Results are appended to ``--json`` (a list of experiments).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
from _settings import replaced

from jaximu import learning
from jaximu.learning import _validation, training
from jaximu.learning._batches import fitted_config
from jaximu.learning.data import split
from jaximu.learning.evaluation import integrate_attitude, orientation_errors
from jaximu.learning.losses import increment_loss


def _true_rates(q, dt):
    """Body rates differenced from unit quaternions ``(N, 4)`` [w, x, y, z]: ``(N-1, 3)``."""
    w0, v0 = q[:-1, :1], q[:-1, 1:]
    w1, v1 = q[1:, :1], q[1:, 1:]
    # conj(q0) * q1
    w = w0 * w1 + np.sum(v0 * v1, 1, keepdims=True)
    v = w0 * v1 - w1 * v0 - np.cross(v0, v1)
    v = np.where(w < 0, -v, v)
    w = np.abs(w)
    ang = 2 * np.arctan2(np.linalg.norm(v, axis=1, keepdims=True), w)
    axis = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-15)
    return axis * ang / dt[:, None]


def _blocks(x, n):
    """1-s block means of ``x (N, 3)`` repeated back to ``(N, 3)`` (the tail's own block)."""
    out = np.empty_like(x)
    for k in range(0, len(x), n):
        out[k : k + n] = x[k : k + n].mean(0)
    return out


def _aoe(gyro, seq, dt):
    """Mean AOE [deg] of ``gyro (N, 3)`` integrated from the first true attitude, at the
    samples with a reference."""
    steps = jnp.full((len(gyro) - 1,), dt, jnp.float32)
    q = integrate_attitude(
        jnp.asarray(seq.q[0], jnp.float32), jnp.asarray(gyro, jnp.float32), steps
    )
    _, aoe, _ = orientation_errors(q, jnp.asarray(seq.q, jnp.float32))
    ref = seq.has_reference
    return float(np.degrees(np.asarray(aoe)[ref].mean()))


def diagnose(model, seq, bias, cfg):
    """The left-out recording's figures for one captured model (see the module's doc)."""
    dt = 1.0 / seq.rate_hz
    g = jnp.asarray(seq.gyro, jnp.float32)[None]
    a = jnp.asarray(seq.accel, jnp.float32)[None]
    b = jnp.asarray(bias, jnp.float32)[None]
    c = model(g, a, gyro_bias=b)
    base = np.asarray(g[0] - b[0], np.float64)
    w_hat = np.asarray(c.gyro[0], np.float64)
    corr = w_hat - base
    rates = _true_rates(seq.q, np.diff(seq.t))
    ok = seq.has_reference[:-1] & seq.has_reference[1:]
    resid = rates - base[:-1]
    n = int(round(seq.rate_hz))
    lf = _blocks(corr, n)
    rot, _ = increment_loss(
        type(c)(*(x[:, :-1] for x in c)),  # T samples, T + 1 attitudes
        jnp.asarray(seq.q, jnp.float32)[None],
        dt,
        cfg.horizons,
        skip=cfg.skip,
        reference=jnp.asarray(seq.has_reference)[None],
    )
    corr_c = np.asarray(seq.gyro @ np.asarray(model.gyro_matrix, np.float64).T)
    return {
        "aoe": _aoe(w_hat, seq, dt),
        "aoe_matrix_only": _aoe(base + corr_c, seq, dt),
        "aoe_network_only": _aoe(base + corr - corr_c, seq, dt),
        "matrix_corr_mean": corr_c.mean(0).tolist(),
        "heldout_huber": float(rot),
        "corr_mean": corr.mean(0).tolist(),
        "resid_mean": resid[ok].mean(0).tolist(),
        "corr_lf_rms": float(np.sqrt(np.mean(lf**2))),
        "corr_hf_rms": float(np.sqrt(np.mean((corr - lf) ** 2))),
        "aoe_lf_only": _aoe(base + lf, seq, dt),
        "aoe_hf_only": _aoe(base + corr - lf, seq, dt),
        "aoe_mean_only": _aoe(base + corr.mean(0), seq, dt),
    }


def _fold_model(others, train_seconds, mcfg):
    """The untrained model of a fold (its priors and normalisation from ``others``' first
    ``train_seconds``, as ``_fit`` sets them): the tracker alone."""
    trains = [split(s, train_seconds)[0] for s in others]
    mcfg = fitted_config(mcfg, trains, others[0].rate_hz)
    return learning.Denoiser(mcfg, jax.random.key(0))


def _residual_blocks(seq, bias, n):
    """1-s block means of ``ω_m − b̂`` and of what the tracker leaves, ``ω_true − (ω_m − b̂)``,
    over the blocks with a reference throughout: ``(K, 3)`` each; and ``ω_m − b̂ (N, 3)``,
    the residual ``(N, 3)`` (zero where no reference)."""
    u = seq.gyro - bias
    ok = np.r_[seq.has_reference[:-1] & seq.has_reference[1:], False]
    r = np.zeros_like(u)
    r[:-1] = _true_rates(seq.q, np.diff(seq.t)) - u[:-1]
    r[~ok] = 0.0
    X = [u[k : k + n].mean(0) for k in range(0, len(u) - n, n) if ok[k : k + n].all()]
    Y = [r[k : k + n].mean(0) for k in range(0, len(u) - n, n) if ok[k : k + n].all()]
    return np.array(X), np.array(Y), u, r, ok


def ceilings(seqs, held, cfg, mcfg):
    """What a correction added after the tracker could do on ``held`` at best: the AOE [deg]
    of the tracker alone, with what it leaves removed exactly as one constant, as 10-s or
    1-s block means (oracles: the left-out recording's own truth), with the best linear
    scale/misalignment ``C (ω_m − b̂)`` fitted by least squares on 1-s blocks of the left-out
    recording itself (oracle) or of the others (as training could; their tracked bias), and
    with the ground truth's own bias where it has one."""
    others = [s for s in seqs if s is not held]
    model = _fold_model(others, cfg.train_seconds, mcfg)
    biases = training._tracked_biases(model, [held, *others])[0]  # (biases, their σ)
    dt = 1.0 / held.rate_hz
    n = int(round(held.rate_hz))
    X, Y, u, r, ok = _residual_blocks(held, biases[0], n)
    fits = [_residual_blocks(s, b, n)[:2] for s, b in zip(others, biases[1:])]
    C_own = np.linalg.lstsq(X, Y, rcond=None)[0].T
    Xo, Yo = (np.concatenate([f[i] for f in fits]) for i in (0, 1))
    C_others = np.linalg.lstsq(Xo, Yo, rcond=None)[0].T
    out = {
        "tracker_alone": _aoe(u, held, dt),
        "oracle_constant": _aoe(u + r[ok].mean(0), held, dt),
        "oracle_10s_blocks": _aoe(u + _blocks(r, 10 * n), held, dt),
        "oracle_1s_blocks": _aoe(u + _blocks(r, n), held, dt),
        "matrix_fitted_on_itself": _aoe(u + u @ C_own.T, held, dt),
        "matrix_fitted_on_others": _aoe(u + u @ C_others.T, held, dt),
        "residual_10s_means_1e-4_rad_s": [
            np.round(r[k : k + 10 * n][ok[k : k + 10 * n]].mean(0) * 1e4, 1).tolist()
            for k in range(0, len(r), 10 * n)
            if ok[k : k + 10 * n].any()
        ],
    }
    if held.b_g is not None:
        out["true_bias"] = _aoe(held.gyro - held.b_g, held, dt)
    return out


def run_fold(seqs, held, cfg, mcfg, seed, say):
    captured = []
    original = _validation.validate  # (training reads it from that module at each _fit)

    def capture(model, *args, **kw):
        captured.append(model)
        return original(model, *args, **kw)

    _validation.validate = capture
    try:
        others = [s for s in seqs if s is not held]
        r = training._fit(  # at the rate train() gives every fold: the first recording's
            others, cfg, mcfg, seed, None, lambda x: None, held_out=held, rate=seqs[0].rate_hz
        )
    finally:
        _validation.validate = original
    rec = r.record
    # captured: the untrained model, the constant-bias baseline (same model), then one per
    # validation
    models = [captured[0]] + captured[2:]
    steps = [0] + [h["step"] for h in rec["history"]]
    train_huber = [None] + [h["huber"] for h in rec["history"]]
    tracked = training._tracked_biases(models[0], [held])[0][0]
    rows = []
    for k, m, th in zip(steps, models, train_huber):
        d = diagnose(m, held, tracked, cfg)
        d.update(step=k, train_huber=th)
        rows.append(d)
        say(
            f"  {held.name} step {k:4d}: AOE {d['aoe']:.3f}° (lf only {d['aoe_lf_only']:.3f}, "
            f"hf only {d['aoe_hf_only']:.3f}, mean only {d['aoe_mean_only']:.3f}, C only "
            f"{d['aoe_matrix_only']:.3f}, net only {d['aoe_network_only']:.3f})  held-out "
            f"huber {d['heldout_huber']:.4g}  train huber {th if th is None else round(th, 4)}"
            f"  corr mean {np.round(np.array(d['corr_mean']) * 1e4, 2)} resid mean "
            f"{np.round(np.array(d['resid_mean']) * 1e4, 2)} [1e-4 rad/s]  hf rms "
            f"{d['corr_hf_rms']:.2e} lf rms {d['corr_lf_rms']:.2e}"
        )
    return {"left_out": held.name, "by_step": rows, "wall_seconds": rec["wall_seconds"]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", nargs="+", required=True)
    ap.add_argument("--label", required=True)
    ap.add_argument("--folds", nargs="*", help="left-out recordings' names (default: all)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--set", nargs="*", default=[], help="TrainConfig KEY=VALUE")
    ap.add_argument("--model-set", nargs="*", default=[], help="ModelConfig KEY=VALUE")
    ap.add_argument("--no-bias-tracking", action="store_true")
    ap.add_argument("--json", help="append the experiment to this JSON file's list")
    ap.add_argument(
        "--ceilings", action="store_true", help="only the ceilings (no training; see ceilings)"
    )
    a = ap.parse_args(argv)
    cfg, _ = replaced(learning.TrainConfig(), a.set)
    cfg = dataclasses.replace(
        cfg, steps=a.steps, selection="validation", calibrate_uncertainty=False
    )
    mcfg, _ = replaced(learning.ModelConfig(), a.model_set)
    if a.no_bias_tracking:
        mcfg = dataclasses.replace(mcfg, bias_tracking=False)
    seqs = [learning.load_sequence(p) for p in a.data]
    held = [s for s in seqs if not a.folds or s.name in a.folds]
    print(f"{a.label}: {a.set} {a.model_set} no_bias_tracking={a.no_bias_tracking}", flush=True)
    if a.ceilings:
        rows = {h.name: ceilings(seqs, h, cfg, mcfg) for h in held}
        for k, v in rows.items():
            print(k, {x: (round(y, 3) if isinstance(y, float) else y) for x, y in v.items()})
        if a.json:
            p = pathlib.Path(a.json)
            doc = json.loads(p.read_text()) if p.exists() else {"experiments": []}
            doc["ceilings"] = rows
            p.write_text(json.dumps(doc, indent=1) + "\n")
        return
    t0 = time.perf_counter()
    folds = []
    for h in held:
        folds.append(run_fold(seqs, h, cfg, mcfg, a.seed, lambda s: print(s, flush=True)))
    steps = [r["step"] for r in folds[0]["by_step"]]
    mean = [float(np.mean([f["by_step"][j]["aoe"] for f in folds])) for j in range(len(steps))]
    ratio = [m / mean[0] for m in mean]
    print(
        "mean AOE by step: "
        + " ".join(f"{k}: {m:.3f}° ({r:.3f})" for k, m, r in zip(steps, mean, ratio)),
        flush=True,
    )
    out = {
        "label": a.label,
        "command": "python benchmarks/learning_network_share.py "
        + " ".join(
            ["--label", a.label, "--steps", str(a.steps)]
            + (["--folds", *a.folds] if a.folds else [])
            + (["--set", *a.set] if a.set else [])
            + (["--model-set", *a.model_set] if a.model_set else [])
            + (["--no-bias-tracking"] if a.no_bias_tracking else [])
        ),
        "seed": a.seed,
        "folds": folds,
        "steps": steps,
        "mean_aoe_deg_by_step": mean,
        "ratio_to_step0_by_step": ratio,
        "wall_seconds": time.perf_counter() - t0,
    }
    if a.json:
        p = pathlib.Path(a.json)
        doc = json.loads(p.read_text()) if p.exists() else {"experiments": []}
        doc["experiments"].append(out)
        p.write_text(json.dumps(doc, indent=1) + "\n")


if __name__ == "__main__":
    jax.config.update("jax_enable_x64", False)
    main()
