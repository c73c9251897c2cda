"""The training's arrays: the parts' constant biases, the tracker's priors and the input
normalisation from them, the parts stacked for the step, each sequence's tracked gyro bias,
and the validation parts padded to one batch (:func:`jaximu.learning.train`)."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jaximu.io import DataError
from jaximu.learning.data import padded_length, to_length


def constant_biases(parts):
    """The mean of the ground-truth biases over the parts that have them (the constant
    baseline), ``(b_g, b_a)`` as 3-tuples; zeros where no part has biases."""
    out = []
    for key in ("b_g", "b_a"):
        means = [getattr(s, key).mean(0) for s in parts if getattr(s, key) is not None]
        out.append(tuple(float(x) for x in (np.mean(means, 0) if means else np.zeros(3))))
    return tuple(out)


def bias_spreads(parts, factors=(3.0, 1.0), floors=(5e-4, 0.02)):
    """The tracker's prior standard deviations ``(σ_bg, σ_ba)`` (3-tuples): ``factors`` times
    the spread of the parts' ground-truth biases about their mean, at least ``floors``
    ([rad/s], [m/s²]). A new recording's gyro bias may lie further out than the few training
    recordings' do, and too tight a prior keeps it from the tracker; a loose accelerometer
    prior lets the tracker explain tilt by accelerometer bias instead. Chosen on the five
    EuRoC training recordings each left out in turn, the tracker alone (mean AOE): 2.48° with
    these; gyro spread doubled 2.60°, taken once 2.90° (accelerometer floor 0.015-0.03);
    accelerometer floor 0.03 2.55°, its spread tripled 2.69°."""
    out = []
    for key, factor, floor in zip(("b_g", "b_a"), factors, floors):
        means = [getattr(s, key).mean(0) for s in parts if getattr(s, key) is not None]
        spread = np.std(means, 0) if len(means) > 1 else np.zeros(3)
        out.append(tuple(float(x) for x in np.maximum(factor * spread, floor)))
    return tuple(out)


def normalisation(parts):
    """Per-channel mean and standard deviation of ``[ω_m, a_m]`` over all samples."""
    x = np.concatenate([np.concatenate([s.gyro, s.accel], 1) for s in parts], 0)
    return tuple(float(v) for v in x.mean(0)), tuple(float(v) for v in x.std(0) + 1e-9)


def pieces(parts, horizon: int, offset: int, window: int | None):
    """The training pieces' length ``L`` (a multiple of ``horizon``), each part's random
    start bound (starts ``0 … bound-1``; ``(S,)`` int32) and the stacked length: with
    ``window`` [samples] ``None``, pieces of the shortest part at starts ``0 … offset-1``;
    otherwise pieces of ``window`` samples (at most the shortest part's) anywhere in each
    part, which are stacked padded to the longest."""
    shortest = min(len(s) for s in parts)
    if window is None:
        L = (shortest - offset - 1) // horizon * horizon
        bounds = [offset] * len(parts)
        length = shortest
    else:
        L = (min(window, shortest - 1)) // horizon * horizon
        bounds = [len(s) - L for s in parts]
        length = max(len(s) for s in parts)
    return L, jnp.asarray(bounds, jnp.int32), length


def fitted_config(base, parts, rate: float):
    """``base`` (a :class:`jaximu.learning.ModelConfig`) with what the training parts
    ``parts`` set: the rate [Hz], the input normalisation, the constant biases and the
    tracker's bias priors."""
    g_bias, a_bias = constant_biases(parts)
    g_sigma, a_sigma = bias_spreads(parts)
    mean, std = normalisation(parts)
    return dataclasses.replace(
        base,
        rate_hz=round(rate, 3),
        input_mean=mean,
        input_std=std,
        gyro_bias=g_bias,
        accel_bias=a_bias,
        gyro_bias_sigma=g_sigma,
        accel_bias_sigma=a_sigma,
    )


def _stack(parts, biases, length):
    """The parts' arrays ``(S, length, ·)``: cut to ``length``, or padded to it by repeating
    each part's last sample (never inside a piece: :func:`pieces` bounds the starts)."""
    fit = lambda x: to_length(x, length)  # noqa: E731
    g = np.stack([fit(s.gyro) for s in parts])
    a = np.stack([fit(s.accel) for s in parts])
    q = np.stack([fit(s.q) for s in parts])
    v = np.stack([fit(s.v) for s in parts])
    b = np.stack([fit(x) for x in biases])
    ref = np.stack([fit(s.has_reference) for s in parts])
    f = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    return f(g), f(a), f(q), f(v), f(b), jnp.asarray(ref)


def _tracked_biases(model, sequences):
    """Each whole sequence's tracked gyro bias ``(N_i, 3)`` and its standard deviation
    (numpy, [rad/s]). The tracker is fixed, not learned: it runs once, on all sequences
    padded to one length in one program (it is causal: the padding changes nothing before
    it), of a length that recordings of about one length share (:func:`padded_length`)."""
    N = padded_length(max(len(s) for s in sequences))
    g = jnp.asarray(np.stack([to_length(s.gyro, N) for s in sequences]), jnp.float32)
    a = jnp.asarray(np.stack([to_length(s.accel, N) for s in sequences]), jnp.float32)
    b, sigma = (np.asarray(x) for x in model.track(g, a))
    return [b[i, : len(s)] for i, s in enumerate(sequences)], [
        sigma[i, : len(s)] for i, s in enumerate(sequences)
    ]


class ValidationBatch(NamedTuple):
    """The validation parts, each with ``context`` samples before it (the network's
    receptive field), padded to one length ``N`` (:func:`padded_length` of the longest) by
    repeating each part's last sample, in one batch ``(S, N, ·)`` float32: one program
    validates them all, whatever their lengths.

    Attributes:
        gyro, accel: raw samples [rad/s], [m/s²]; q: true attitudes ``[w, x, y, z]``;
        p, v: true positions [m] and velocities [m/s] (world);
        dt: the interval [s] from each sample to the next (the last one repeated);
        bias, bias_sigma: the tracked gyro bias of the whole sequence and its standard
            deviation [rad/s];
        run: True on the samples integrated, from the first validation sample with a
            reference on (to the part's end);
        compare: True on the validation samples with a reference (not in a dropout);
        start: ``(S,)`` int32, the index of each part's first validation sample;
        length: ``(S,)`` int32, each row's samples before the padding.
    """

    gyro: jnp.ndarray
    accel: jnp.ndarray
    q: jnp.ndarray
    p: jnp.ndarray
    v: jnp.ndarray
    dt: jnp.ndarray
    bias: jnp.ndarray
    bias_sigma: jnp.ndarray
    run: jnp.ndarray
    compare: jnp.ndarray
    start: jnp.ndarray
    length: jnp.ndarray


def _validation_arrays(seqs, vals, tracked, context) -> ValidationBatch:
    """The :class:`ValidationBatch` of the validation parts ``vals`` of ``seqs``;
    ``tracked``: each whole sequence's ``(bias, sigma)`` lists (:func:`_tracked_biases`)."""
    biases, sigmas = tracked
    pieces = []
    for s, v, b, sb in zip(seqs, vals, biases, sigmas):
        k = len(s) - len(v)
        lo = max(0, k - context)
        pieces.append((s.slice(lo), b[lo:], sb[lo:], k - lo))
    # a length that batches of about one length share (each leave-one-out fold's recording)
    S, N = len(pieces), padded_length(max(len(p) for p, _, _, _ in pieces))
    widths = dict(gyro=3, accel=3, q=4, p=3, v=3, dt=1, bias=3, bias_sigma=3)
    out = {name: np.zeros((S, N, c)) for name, c in widths.items()}
    run, compare = np.zeros((S, N), bool), np.zeros((S, N), bool)
    start, length = np.zeros(S, np.int32), np.zeros(S, np.int32)
    for i, (p, b, sb, c0) in enumerate(pieces):
        n = len(p)
        dt = np.append(p.dt, p.dt[-1:])[:, None]
        rows = dict(gyro=p.gyro, accel=p.accel, q=p.q, p=p.p, v=p.v, dt=dt, bias=b, bias_sigma=sb)
        for name, x in rows.items():
            out[name][i] = to_length(x, N)
        ref = p.has_reference[c0:]
        if not ref.any():
            raise DataError(
                f"sequence {p.name!r}: its validation part has no sample with ground truth "
                "(all inside dropouts): give a longer recording or another train_seconds"
            )
        run[i, c0 + int(np.argmax(ref)) : n] = True
        compare[i, c0:n] = ref
        start[i], length[i] = c0, n
    f = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    out["dt"] = out["dt"][..., 0]
    return ValidationBatch(
        **{name: f(x) for name, x in out.items()},
        run=jnp.asarray(run),
        compare=jnp.asarray(compare),
        start=jnp.asarray(start),
        length=jnp.asarray(length),
    )
