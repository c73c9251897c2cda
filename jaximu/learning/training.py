"""Training the denoiser on sequences with ground truth (Brossard's recipe, with the
likelihood of the learned noise).

Each step takes, from every training part, a piece starting at a random offset of
``0 … offset-1`` samples, adds Gaussian noise to the raw samples (white, and a constant bias
per piece), and takes one AdamW step on the increment loss
(:func:`jaximu.learning.losses.increment_loss`) plus the NLL. Every ``validate_every`` steps
each validation part is integrated whole from its first true attitude and the model with
the lowest mean AOE (averaged over the sequences) is kept. Deterministic for a seed on one
machine (unless ``minutes`` cuts the run short).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaximu.geometry._checks import check_positive
from jaximu.io import DataError
from jaximu.learning import _validation, uncertainty
from jaximu.learning._batches import (
    _stack,
    _tracked_biases,
    _validation_arrays,
    bias_spreads,
    constant_biases,
    fitted_config,
    normalisation,
    pieces,
)
from jaximu.learning._selection import CRITERIA, AccelChoice, leave_one_out
from jaximu.learning.alignment import reference_offset, shifted_reference
from jaximu.learning.data import Sequence, check_rate, check_sequence, split
from jaximu.learning.losses import huber, increment_loss, velocity_residuals
from jaximu.learning.model import Denoiser, ModelConfig
from jaximu.learning.recipe import TrainConfig, _optimizer, _step_settings

__all__ = [
    "TrainResult",
    "train",
    "constant_biases",
    "bias_spreads",
    "normalisation",
]


class TrainResult(NamedTuple):
    """The best model and what happened (``record``: JSON-serialisable)."""

    model: Denoiser
    record: dict


OFFSET_UNIT = 1e-3
"""[rad/s] per unit of the per-recording offsets (Adam's steps are of the learning rate's size
in the parameters: bias-sized steps need bias-sized units)."""


def _loss(params, g, a, b, q, v, ref, k_drop, has_v, n_v, cfg: TrainConfig, dt: float):
    """The training loss of one step and its ``(rotation, nll)`` parts (``has_v``: 1 for the
    parts whose ground truth has velocities, ``n_v`` their number, at least 1; ``b`` the
    tracked gyro bias; ``ref`` where the ground truth has a reference; ``params``: the model
    and the training recordings' offsets)."""
    model, offsets = params
    mcfg = model.config
    if cfg.recording_offsets:  # each recording's own constant, apart from the network
        b = b + OFFSET_UNIT * (offsets - jnp.mean(offsets, 0))[:, None, :]
    c = model(g, a, key=k_drop, gyro_bias=b)
    rot, nll = increment_loss(
        c,
        q,
        dt,
        cfg.horizons,
        bias_sigma=model.bias_sigma,
        reference_sigma=model.reference_sigma,
        random_walk=mcfg.gyro_random_walk,
        skip=cfg.skip,
        reference=ref,
    )
    total = rot + cfg.nll_weight * nll
    if mcfg.accel_head:  # velocity increments: the gyro enters without its gradient
        r = velocity_residuals(
            jax.lax.stop_gradient(c.gyro), c.accel, q, v, dt, cfg.velocity_horizon
        )
        per_seq = jax.vmap(lambda x: huber(x, cfg.velocity_delta))(r)
        total = total + cfg.velocity_weight * jnp.sum(per_seq * has_v) / n_v
    return total, (rot, nll)


# The step and the validation are compiled once per configuration, model structure and data
# shape (the static arguments and the model's static structure are their cache keys; the
# settings fitted to the data are arrays, Denoiser.fitted), not once per call of train: a
# second run with the same settings (another seed, a rerun, another fold) starts at once.
@eqx.filter_jit
def _step(
    params,
    ema,
    opt_state,
    key,
    G,
    A,
    Q,
    V,
    B,
    R,
    bounds,
    noise,
    bias_noise,
    has_v,
    n_v,
    *,
    cfg: TrainConfig,
    dt: float,
    L: int,
):
    """One AdamW step on pieces of ``L`` samples of the training parts ``(S, N, ·)`` at random
    starts ``0 … bounds-1`` (``(S,)``), with noise added; ``params``: ``(model, offsets)``, ``ema``: the exponential
    average of the model's weights."""
    S = G.shape[0]
    k_off, k_w, k_b, k_drop = jax.random.split(key, 4)
    offs = jax.random.randint(k_off, (S,), 0, bounds)
    cut = lambda x, n: jax.vmap(lambda xi, o: jax.lax.dynamic_slice_in_dim(xi, o, n))(x, offs)  # noqa: E731
    x = jnp.concatenate([cut(G, L), cut(A, L)], -1)
    # a constant per piece shifts the samples and, as the tracker would follow it, the bias
    shift = bias_noise * jax.random.normal(k_b, (S, 1, 6))
    x = x + noise * jax.random.normal(k_w, x.shape) + shift
    b = cut(B, L) + shift[..., :3] if cfg.bias_noise_shown else cut(B, L)
    # the weights and the offsets are trained; the model's fitted settings (inputs of the
    # program, not constants of it) are not
    params, frozen = eqx.partition(params, _trainable(params))
    loss_of = lambda p, *a: _loss(eqx.combine(p, frozen), *a)  # noqa: E731
    (loss, parts), grads = eqx.filter_value_and_grad(loss_of, has_aux=True)(
        params,
        x[..., :3],
        x[..., 3:],
        b,
        cut(Q, L + 1),
        cut(V, L + 1),
        cut(R, L + 1),
        k_drop,
        has_v,
        n_v,
        cfg,
        dt,
    )
    updates, opt_state = _optimizer(cfg, params).update(grads, opt_state, params)
    params = eqx.apply_updates(params, updates)
    # the validated and kept model is the exponential average of the weights: the
    # whole-sequence error hangs on the learned bias, which single steps jitter
    ema = jax.tree_util.tree_map(
        lambda e, m: e + (1.0 - cfg.ema) * (m - e), eqx.filter(ema, _trainable(ema)), params[0]
    )
    return params, ema, opt_state, loss, parts


def _trainable(tree):
    """The filter of ``tree``'s (a model, or ``(model, offsets)``) trained leaves: its
    floating arrays but the model's fitted settings (``Denoiser.fitted``)."""
    spec = jax.tree_util.tree_map(eqx.is_inexact_array, tree)
    model = tree[0] if isinstance(tree, tuple) else tree
    where = (lambda t: t[0].fitted) if isinstance(tree, tuple) else (lambda t: t.fitted)
    return eqx.tree_at(where, spec, jax.tree_util.tree_map(lambda _: False, model.fitted))


def train(
    sequences: list[Sequence],
    config: TrainConfig | None = None,
    model_config: ModelConfig | None = None,
    *,
    seed: int = 0,
    minutes: float | None = None,
    log: Callable[[str], None] | None = print,
) -> TrainResult:
    """Train a :class:`Denoiser` on ``sequences`` (each split into training and validation).

    Args:
        sequences: :class:`Sequence` with ground truth, all at one rate.
        config: :class:`TrainConfig`; model_config: :class:`ModelConfig` (its normalisation,
            constant biases and rate are filled in from the training parts).
        seed: the random seed (initialisation, offsets, noise, dropout).
        minutes: stop after this wall time (the best model so far is kept).
        log: progress lines (``None``: silent).

    Returns:
        :class:`TrainResult`.
    """
    cfg = config or TrainConfig()
    say = log or (lambda s: None)
    if isinstance(sequences, Sequence) or not sequences:
        raise DataError(
            "sequences must be a non-empty list of jaximu.learning.Sequence "
            "(load_sequence(folder) for each folder)"
        )
    for i, s in enumerate(sequences):
        check_sequence(f"sequences[{i}]", s)
    names = [s.name for s in sequences]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:  # the record and the leave-one-out figures are by name; one recording twice
        # would also be weighted twice
        raise DataError(
            f"sequences must have distinct names; {', '.join(map(repr, twice))} is given "
            "more than once: give each recording once (load_sequence(folder, name=...) "
            "names two recordings whose folders share a name)"
        )
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    if minutes is not None:
        check_positive("minutes", minutes)
    if not isinstance(cfg, TrainConfig):
        raise ValueError(f"config must be a TrainConfig, got {type(cfg).__name__}")
    if model_config is not None and not isinstance(model_config, ModelConfig):
        raise ValueError(f"model_config must be a ModelConfig, got {type(model_config).__name__}")
    for s in sequences:
        check_rate(s, sequences[0].rate_hz, f"sequence {sequences[0].name!r}")
    if cfg.whole_recordings and cfg.selection not in CRITERIA:
        raise ValueError(
            "TrainConfig(whole_recordings=True) keeps no seconds for validation: use it with "
            "selection='leave_one_out' (the recordings left out judge the steps)"
        )
    if cfg.selection in CRITERIA:
        if model_config is not None and model_config.accel_network:
            raise ValueError(
                f"TrainConfig(selection={cfg.selection!r}) judges the attitude alone, and "
                "ModelConfig(accel_network=True) keeps the accelerometer's layers by the "
                "validation parts' windows: use selection='validation' with it, or "
                "accel_network=False"
            )
        if len(sequences) < 2:
            raise DataError(
                "TrainConfig(selection='leave_one_out') needs two recordings or more (each "
                f"is validated by models trained on the others); got {len(sequences)}: give "
                "more recordings or selection='validation'"
            )
    # one rate for every fold and the final model (the first recording's), so that the folds,
    # which differ in their first recording, share the step's program (dt is in its key)
    fit = functools.partial(_fit, rate=sequences[0].rate_hz)
    if cfg.selection in CRITERIA:
        return leave_one_out(fit, list(sequences), cfg, model_config, seed, minutes, say)
    return fit(list(sequences), cfg, model_config, seed, minutes, say)


def _fit(
    sequences, cfg, model_config, seed, minutes, say, held_out=None, keep_step=None, *, rate
) -> TrainResult:
    """:func:`train` once its arguments are checked. ``held_out``: a recording validated
    whole instead of the validation parts (a fold of :func:`jaximu.learning._selection.leave_one_out`); ``keep_step``:
    ``(step, score)``, keep the weights of that step (0: untrained) and stop there, with no
    choice by validation; ``rate`` [Hz]: the model's sample rate."""
    trains, vals = zip(*(split(s, cfg.train_seconds) for s in sequences))
    if cfg.whole_recordings:  # (vals: the record's figures and the uncertainty's only)
        trains = tuple(sequences)
    clock = {}
    if cfg.align_reference:  # the training parts' ground truth on the IMU's clock
        clock = {t.name: reference_offset(t) for t in trains}
        trains = tuple(shifted_reference(t, clock[t.name]) for t in trains)
    mcfg = fitted_config(model_config or ModelConfig(), trains, rate)
    dt = 1.0 / rate
    Hmax = cfg.horizons[-1]
    shortest = min(len(s) for s in trains)
    window = round(cfg.train_seconds * rate) if cfg.whole_recordings else None
    L, bounds, length = pieces(trains, Hmax, cfg.offset, window)
    if L < Hmax:
        raise DataError(
            f"the shortest training part ({shortest} samples) is shorter than the "
            f"longest horizon ({Hmax} samples) plus the offsets ({cfg.offset}): give "
            "longer sequences or TrainConfig(horizons=...) with shorter ones"
        )
    key = jax.random.key(seed)
    key, k_init = jax.random.split(key)
    model = Denoiser(mcfg, k_init)
    t_tracker = time.perf_counter()
    # every sequence's bias in one program (and the recording left out, if one is)
    tracked = _tracked_biases(model, sequences + ([held_out] if held_out is not None else []))
    biases = tracked[0][: len(sequences)]
    # The network learns what the bias leaves; it is shown each training part's bias as the
    # tracker ends it (its most informed estimate before the validation part, constant over
    # the part), not the tracker's first seconds, whose transient is each recording's own:
    # learned, it biases every other recording (validation mean AOE 0.59-0.63° against the
    # tracker's own 0.52°).
    settled = [np.broadcast_to(b[len(t) - 1], b.shape) for b, t in zip(biases, trains)]
    G, A, Q, V, B, R = _stack(trains, settled, length)
    # velocities of ground truth that has them (a pose-only one's are differenced
    # positions: too noisy for velocity increments)
    has_v = jnp.asarray([s.b_g is not None for s in trains], jnp.float32)
    n_v = jnp.maximum(jnp.sum(has_v), 1.0)
    if held_out is not None:  # validated whole, from its first true attitude
        vals = (held_out,)
        vdata = _validation_arrays(
            vals, vals, ([tracked[0][-1]], [tracked[1][-1]]), mcfg.receptive_field
        )
    else:
        vdata = _validation_arrays(sequences, vals, tracked, mcfg.receptive_field)
    # each stage's own time, for a device where one of them could dominate (the steps' time
    # is theirs: they are waited for before a validation is timed)
    seconds = dict(tracker_and_data=time.perf_counter() - t_tracker, steps=0.0, validation=0.0)
    say(
        f"training on {len(trains)} sequences at {rate:.1f} Hz: "
        + (
            f"{L} samples anywhere in "
            if cfg.whole_recordings
            else f"the first {cfg.train_seconds:g} s of "
        )
        + f"each ({sum(len(s) for s in trains)} samples); validating on "
        + ("the recording left out " if held_out is not None else "the rest ")
        + f"({sum(len(v) for v in vals)} samples: "
        + ", ".join(f"{v.name} {v.seconds:.1f} s" for v in vals)
        + ")"
    )

    params = (model, jnp.zeros((len(trains), 3), jnp.float32))
    trained = eqx.filter(params, _trainable(params))
    opt_state = _optimizer(_step_settings(cfg), trained).init(trained)
    fitted = eqx.filter(model, _trainable(model), inverse=True)  # not trained: kept here
    noise = jnp.asarray([cfg.gyro_noise] * 3 + [cfg.accel_noise] * 3, jnp.float32)
    bias_noise = jnp.asarray([cfg.gyro_bias_noise] * 3 + [cfg.accel_bias_noise] * 3, jnp.float32)
    jitted = functools.partial(_step, cfg=_step_settings(cfg), dt=dt, L=L)

    def step(params, ema, opt_state, key, *data):  # the trained leaves back in the model
        params, ema, opt_state, loss, parts = jitted(params, ema, opt_state, key, *data)
        return (
            (eqx.combine(params[0], fitted), params[1]),
            eqx.combine(ema, fitted),
            opt_state,
            loss,
            parts,
        )

    validate = functools.partial(_validation.validate, dt=dt)

    record: dict[str, Any] = {
        "seed": seed,
        "train": cfg.to_json(),
        "sequences": [s.name for s in sequences],
        "split": {
            s.name: {"train_samples": len(t), "validation_samples": len(v)}
            for s, t, v in zip(sequences, trains, vals)
        },
        "history": [],
    }
    if clock:
        record["reference_offsets_s"] = clock
        say(
            "the training parts' ground truth realigned to the integrated gyro: "
            + " ".join(f"{k} {1e3 * v:+.2f} ms" for k, v in clock.items())
        )
    t_start = time.perf_counter()
    key, k = jax.random.split(key)
    t0 = time.perf_counter()
    # arguments, not constants folded into the program
    data = (G, A, Q, V, B, R, bounds, noise, bias_noise, has_v, n_v)
    params, ema, opt_state, loss, parts = step(params, model, opt_state, k, *data)
    jax.block_until_ready(loss)
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    untrained = np.degrees(np.asarray(validate(model, vdata)))  # the tracked bias alone
    t_val_first = time.perf_counter() - t0
    vB_constant = jnp.broadcast_to(jnp.asarray(mcfg.gyro_bias, jnp.float32), vdata.bias.shape)
    baseline = np.degrees(np.asarray(validate(model, vdata._replace(bias=vB_constant))))
    record["validation_constant_bias_deg"] = [float(x) for x in baseline]
    record["validation_untrained_deg"] = [float(x) for x in untrained]
    say(
        "constant-bias baseline: validation mean AOE "
        + " ".join(f"{v.name} {x:.2f}°" for v, x in zip(vals, baseline))
    )
    if mcfg.bias_tracking:
        say(
            "the tracked bias alone (the untrained network): "
            + " ".join(f"{v.name} {x:.2f}°" for v, x in zip(vals, untrained))
        )
    # the untrained network is a candidate: a network that only hurts on validation is not kept
    best = (float(untrained.mean()), model, 0)
    if keep_step is not None:  # chosen without these recordings' validation parts
        best = (keep_step[1], model, 0)
    accel = AccelChoice(model, _window_parts(sequences, vals), dt) if mcfg.accel_network else None
    compile_time = t_first + t_val_first
    i = 1
    cut_short = False
    while True:
        if keep_step is not None and i >= keep_step[0]:
            if i == keep_step[0]:  # (step 0, the untrained network, is kept already)
                best = (keep_step[1], ema, i)
            break
        if keep_step is None and (i % cfg.validate_every == 0 or i == cfg.steps):
            t0 = time.perf_counter()
            jax.block_until_ready(loss)
            t1 = time.perf_counter()
            aoe = np.degrees(np.asarray(validate(ema, vdata)))
            seconds["steps"] += t1 - t0
            seconds["validation"] += time.perf_counter() - t1
            mean_aoe = float(aoe.mean())
            record["history"].append(
                {
                    "step": i,
                    "loss": float(loss),
                    "huber": float(parts[0]),
                    "nll": float(parts[1]),
                    "validation_aoe_mean_deg": [float(x) for x in aoe],
                }
            )
            ratio = None if accel is None else accel.judge(ema, vdata, i)  # its own layers
            if ratio is not None:
                record["history"][-1]["validation_accel_ratio"] = ratio
            mark = ""
            if mean_aoe < best[0]:
                best, mark = (mean_aoe, ema, i), " *"
            say(
                f"step {i:5d}/{cfg.steps}  loss {float(parts[0]):.4g}  nll {float(parts[1]):8.3f}"
                f"  validation mean AOE {mean_aoe:6.2f}° ("
                + " ".join(f"{x:.2f}" for x in aoe)
                + f"){mark}"
                + ("" if ratio is None else f"  accelerometer windows × {ratio:.3f}")
                + f"  {time.perf_counter() - t_start:6.0f} s"
            )
        if i >= cfg.steps:
            break
        if minutes is not None and time.perf_counter() - t_start > 60 * minutes:
            cut_short = True
            say(
                f"stopped after {minutes:g} minutes at step {i} (--minutes); the run is not "
                "reproducible step for step"
            )
            break
        key, k = jax.random.split(key)
        t0 = time.perf_counter()
        params, ema, opt_state, loss, parts = step(params, ema, opt_state, k, *data)
        if i % 10 == 0:
            jax.block_until_ready(loss)
        seconds["steps"] += time.perf_counter() - t0
        i += 1
    model = best[1] if accel is None else accel.apply(best[1], record, say)
    t_after = time.perf_counter()
    if cfg.calibrate_uncertainty:
        t0 = time.perf_counter()
        learned_ref = float(model.reference_sigma)
        ref, short_sb = uncertainty.fit_reference_sigma(
            model,
            G[:, :-1],
            A[:, :-1],
            Q,
            dt,
            cfg.horizons,
            gyro_bias=B[:, :-1],
            skip=cfg.skip,
            reference=R,
        )
        model = uncertainty.with_reference_sigma(model, ref)
        say(
            f"ground truth's attitude noise σ_ref = {ref:.3g} rad, by the likelihood of the "
            f"training windows with the kept network (was {learned_ref:.3g}; "
            f"{time.perf_counter() - t0:.1f} s)"
        )
        terms = _validation.nees_terms(model, vdata)
        model = uncertainty.set_bias_sigma(model, terms, [v.name for v in vals], record, say)
        if cfg.bias_markov:  # asked for (TrainConfig.bias_markov): not the default recipe
            model = uncertainty.set_bias_markov(model, sequences, vals, record, say)
        record["uncertainty"].update(
            learned_reference_sigma=learned_ref, short_horizon_bias_sigma=short_sb
        )
    if held_out is None:
        _record_windows(model, sequences, vals, vdata, dt, record, say)
    seconds["uncertainty_and_windows"] = time.perf_counter() - t_after
    seconds.update(first_step=t_first, first_validation=t_val_first)
    wall = time.perf_counter() - t_start
    record["recording_offsets_rad_s"] = {
        s.name: [float(x) for x in OFFSET_UNIT * (o - params[1].mean(0))]
        for s, o in zip(trains, np.asarray(params[1]))
    }
    record.update(
        {
            "best_step": best[2],
            "validation_aoe_mean_deg": best[0],
            "steps_run": i,
            "cut_short": cut_short,
            "wall_seconds": wall,
            "compile_seconds": compile_time,
            "first_step_seconds": t_first,
            "samples_per_step": int(G.shape[0] * L),
            "piece_start_bounds": [int(x) for x in np.asarray(bounds)],
            "stage_seconds": seconds,
        }
    )
    say(
        f"best model: step {best[2]} (validation mean AOE {best[0]:.2f}°); wall {wall:.0f} s, of "
        f"which compile ≈ {compile_time:.1f} s; the steps {seconds['steps']:.1f} s, the "
        f"validations {seconds['validation']:.1f} s, the tracker and data "
        f"{seconds['tracker_and_data']:.1f} s (before the wall's start)"
    )
    return TrainResult(model, record)


def _record_windows(model, sequences, vals, vdata, dt, record, say):
    """Dead-reckoning errors over 1-s and 5-s windows of the validation parts with ground
    truth velocities (``vdata``: their batch): what the accelerometer correction is judged
    by."""
    kept = _window_parts(sequences, vals)
    rows = _validation.window_errors(model, vdata, dt, (1.0, 5.0)) if kept else []
    out = {vals[i].name: rows[i] for i in kept}
    record["validation_windows"] = out
    for w in ("1s", "5s"):
        rows = [x[w] for x in out.values()]
        if rows:
            mean = {k: np.mean([r[k] for r in rows], 0) for k in rows[0]}
            say(
                f"validation dead reckoning over {w} windows from the true state, mean |δv| "
                f"[m/s] / |δp| [m]: "
                + ", ".join(f"{k} {a:.3f} / {b:.3f}" for k, (a, b) in mean.items())
            )


def _window_parts(sequences, vals) -> list[int]:
    """The indices of the validation parts judged by dead-reckoning windows: those of 5 s
    or more whose ground truth has velocities (pose only: differenced velocities)."""
    return [
        i for i, (s, v) in enumerate(zip(sequences, vals)) if s.b_g is not None and v.seconds >= 5.0
    ]
