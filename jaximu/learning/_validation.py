"""The training's judgements of the validation parts, each one program for all of them
(:class:`jaximu.learning._batches.ValidationBatch`): the mean AOE that chooses the kept
step, the terms of the orientation NEES that set the residual bias ``σ_b``, and the
dead-reckoning errors over windows.

One program for the batch, not one per sequence: a program is compiled per shape, and the
validation parts all differ in length. Compiled one sequence at a time (the tracker, the
network op by op, the covariance and the windows of each), the programs after the last step
took 180 s of a 300-s training of two recordings on 2 CPU cores (``jax_log_compiles``), the
steps 14 s; on a GPU each such compile takes longer still. The mathematics is that of the
per-sequence functions (:func:`jaximu.learning.uncertainty.nees_terms`,
:func:`jaximu.learning.evaluation.window_errors`), which the tests compare these with.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaximu.learning._batches import ValidationBatch
from jaximu.learning.evaluation import (
    _window_run,
    attitude_terms,
    integrate_attitude,
    orientation_errors,
)
from jaximu.learning.uncertainty import NeesTerms


def _first_run_sample(v: ValidationBatch):
    """``(S,)`` each row's first integrated sample (its first validation sample with a
    reference)."""
    return jnp.argmax(v.run, 1)


def _shifted(x, offsets):
    """Each row of ``x`` ``(S, N, ·)`` from its own ``offsets[i]`` on, ``N`` samples, the
    last sample repeated past the row's end."""
    N = x.shape[1]
    tail = jnp.repeat(x[:, -1:], N, axis=1)
    return jax.vmap(lambda r, o: jax.lax.dynamic_slice_in_dim(r, o, N))(
        jnp.concatenate([x, tail], 1), offsets
    )


@eqx.filter_jit
def validate(model, v: ValidationBatch, *, dt: float):
    """Mean AOE [rad] of each validation part, integrated from its first true attitude:
    the rates before it (the network's context) are zeroed, so the attitude stays at
    that true attitude until the validation part starts."""
    c = model(v.gyro, v.accel, gyro_bias=v.bias)
    first = _first_run_sample(v)
    q0 = jnp.take_along_axis(v.q, first[:, None, None], 1)[:, 0]
    gyro = jnp.where(v.run[..., None], c.gyro, 0.0)
    steps = jnp.full(v.run.shape[:1] + (v.run.shape[1] - 1,), dt, jnp.float32)
    _, aoe, _ = orientation_errors(integrate_attitude(q0, gyro, steps), v.q)
    return jnp.sum(jnp.where(v.compare, aoe, 0.0), 1) / jnp.sum(v.compare, 1)


@eqx.filter_jit
def _nees_arrays(model, v: ValidationBatch):
    c = model(v.gyro, v.accel, gyro_bias=v.bias)
    first = _first_run_sample(v)
    g, d, s, q, h = (
        _shifted(x, first) for x in (c.gyro, c.gyro_density, v.bias_sigma, v.q, v.dt[..., None])
    )
    inside = jnp.arange(g.shape[1])[None, :] < (v.length - first)[:, None]
    compare = _shifted(v.compare[..., None], first)[..., 0] & inside
    h = h[:, :-1, 0]
    r, _, _ = orientation_errors(integrate_attitude(q[:, 0], g, h), q)
    rw, markov = model.config.gyro_random_walk, model.config.bias_markov
    W, B = jax.vmap(lambda gi, di, hi, si: attitude_terms(gi, di, hi, rw, si, markov))(g, d, h, s)
    return r, W, B, compare, model.reference_sigma.astype(jnp.float32)


def nees_terms(model, v: ValidationBatch) -> list[NeesTerms]:
    """Each validation part's :class:`jaximu.learning.uncertainty.NeesTerms`, integrated
    from its first sample with a reference, at its samples with one (those of
    :func:`jaximu.learning.uncertainty.nees_terms` from that sample)."""
    r, W, B, compare, ref = (np.asarray(x) for x in _nees_arrays(model, v))
    out = []
    for i in range(r.shape[0]):
        k = np.flatnonzero(compare[i])
        out.append(NeesTerms(r[i, k], W[i, k], B[i, k], jnp.asarray(ref)))
    return out


@eqx.filter_jit
def _window_arrays(model, v: ValidationBatch, *, windows: tuple):
    c = model(v.gyro, v.accel, gyro_bias=v.bias)
    cfg = model.config
    shift = lambda x: _shifted(x, v.start)  # noqa: E731
    # each series from its validation start, once for every window length and variant
    g0 = shift(v.gyro - jnp.asarray(cfg.gyro_bias, jnp.float32))
    a0 = shift(v.accel - jnp.asarray(cfg.accel_bias, jnp.float32))
    g, a = shift(c.gyro), shift(c.accel)
    q, p, vel = shift(v.q), shift(v.p), shift(v.v)
    steps = shift(v.dt[..., None])[..., 0]
    last = v.length - v.start - 1  # each row's steps from its validation start
    variants = (("constant_bias", (g0, a0)), ("learned_gyro", (g, a0)), ("learned", (g, a)))
    out = {}
    for n in windows:
        j = jnp.arange((v.gyro.shape[1] - 1) // n)
        valid = (j[None, :] + 1) * n <= last[:, None]  # the windows inside the row
        mean = lambda e: jnp.sum(jnp.where(valid, e, 0.0), 1) / jnp.sum(valid, 1)  # noqa: E731
        rows = {}
        for name, (gi, ai) in variants:
            dv, dp = jax.vmap(lambda *x: _window_run(*x, n=n))(gi, ai, q, p, vel, steps)
            rows[name] = (mean(dv), mean(dp))
        out[n] = rows
    return out


def window_errors(model, v: ValidationBatch, dt: float, seconds: tuple) -> list[dict]:
    """Each validation part's dead-reckoning errors over windows of each of ``seconds``
    from its first validation sample, as :func:`jaximu.learning.evaluation.window_errors`
    gives them: ``[{"1s": {variant: (mean |δv| [m/s], mean |δp| [m])}, ...}]``."""
    ns = tuple(int(round(w / dt)) for w in seconds)
    arrays = _window_arrays(model, v, windows=ns)
    S = int(v.gyro.shape[0])
    return [
        {
            f"{w:g}s": {name: (float(dv[i]), float(dp[i])) for name, (dv, dp) in arrays[n].items()}
            for w, n in zip(seconds, ns)
        }
        for i in range(S)
    ]
