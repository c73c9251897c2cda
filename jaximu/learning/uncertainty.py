"""The scalars of the learned uncertainty, set after training: the ground truth's attitude
noise ``σ_ref`` by the likelihood of the training windows, and the residual gyro bias
``σ_b`` on held-out data.

The network and its noise head are trained with the likelihood, but the kept weights are
those of the best validation step, which may come early (the shipped model's: step 25 of an
exponential average), before the scalars have moved from their initial values.
:func:`fit_reference_sigma` therefore fits ``σ_ref`` (with a short-horizon ``σ_b``, a
nuisance parameter there) to the kept network by maximum likelihood of the training
windows' increments, the same negative log-likelihood as the training loss's.

Over a whole sequence the attitude error of an open-loop run is dominated by the gyro bias
the correction misses, whose spread shows only across recordings: on the training parts the
network has seen, it is smaller than on a new one, so the likelihood of the training windows
cannot set it. It is set instead on the validation parts, by moment matching: the one
``σ_b`` whose average orientation NEES, averaged over the sequences, is 3
(:func:`fit_bias_sigma`; the NEES falls monotonically as ``σ_b`` grows, so a bisection in
``log σ_b`` finds it). :func:`leave_one_out` reports each sequence's NEES with ``σ_b`` set
on the others, so the figure reported for a sequence never saw it.

The whole run's NEES is one draw of that bias; the NEES over many windows of seconds, each
started from the true attitude (:func:`window_nees`, the error at each window's end), reads
the covariance over seconds instead. Where the gyro's error varies within a recording (the
Vicon room recordings of EuRoC), neither ``σ_b`` (set for the whole run) nor a random walk
(unbounded over it) explains those windows; a first-order Gauss–Markov bias does
(``ModelConfig.bias_markov_sigma``, ``bias_markov_time``), fitted by the likelihood of the
held-out windows through the engine's covariance (:func:`fit_bias_markov`,
:func:`set_bias_markov`).
"""

from __future__ import annotations

import dataclasses
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaximu.geometry._checks import check_int, check_output, check_positive, compute_dtype
from jaximu.io import DataError
from jaximu.learning.data import check_sequence, padded_length, to_length
from jaximu.learning.evaluation import (
    attitude_terms,
    integrate_attitude,
    markov_attitude,
    orientation_errors,
    window_samples,
)
from jaximu.learning.losses import (
    check_horizons,
    gaussian_nll,
    increment_terms,
    rotation_covariance,
    rotation_step_blocks,
)
from jaximu.learning.model import Denoiser, check_model

__all__ = [
    "NeesTerms",
    "nees_terms",
    "average_nees",
    "fit_bias_sigma",
    "fit_reference_sigma",
    "leave_one_out",
    "window_nees_terms",
    "window_nees",
    "fit_bias_markov",
    "with_bias_markov",
    "set_bias_markov",
    "with_bias_sigma",
    "with_reference_sigma",
    "set_bias_sigma",
]


class NeesTerms(eqx.Module):
    """What the NEES of one run needs, for any ``σ_b``: the errors ``r`` ``(T, 3)``, the
    covariance terms ``W``, ``B`` ``(T, 3, 3)`` (:func:`attitude_terms`) and ``σ_ref``."""

    r: jax.Array
    W: jax.Array
    B: jax.Array
    reference_sigma: jax.Array


@eqx.filter_jit
def _terms(model, gyro, accel, q_true, dt, start):
    c = model(gyro, accel)
    g, d, q = c.gyro[start:], c.gyro_density[start:], q_true[start:]
    qs = integrate_attitude(q[0], g, dt[start:])
    r, _, _ = orientation_errors(qs, q)
    cfg = model.config
    W, B = attitude_terms(
        g, d, dt[start:], cfg.gyro_random_walk, c.gyro_bias_sigma[start:], cfg.bias_markov
    )
    return NeesTerms(r, W, B, model.reference_sigma.astype(g.dtype))


def nees_terms(model, seq, start: int = 0, dtype=jnp.float32) -> NeesTerms:
    """The NEES terms of ``seq`` integrated from its sample ``start`` (the network sees the
    samples before it as context), at the samples with a reference
    (:attr:`jaximu.learning.Sequence.reference`)."""
    check_model("model", model)
    check_sequence("seq", seq)
    start = check_int("start", start, 0)
    if start > len(seq) - 2:
        raise ValueError(f"start = {start} leaves no step of the {len(seq)} samples of seq")
    cast = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    t = _terms(model, cast(seq.gyro), cast(seq.accel), cast(seq.q), cast(seq.dt), start)
    if seq.reference is None:
        return t
    keep = np.flatnonzero(seq.has_reference[start:])  # no error inside a mocap dropout
    return NeesTerms(t.r[keep], t.W[keep], t.B[keep], t.reference_sigma)


def average_nees(t: NeesTerms, bias_sigma: float) -> float:
    """The average over the samples of ``rᵀ S⁻¹ r``, ``S = W + σ_b² B Bᵀ + 2 σ_ref² I``."""
    r, W, B = (np.asarray(x, np.float64) for x in (t.r, t.W, t.B))
    S = (
        W
        + bias_sigma**2 * B @ np.swapaxes(B, -1, -2)
        + 2.0 * float(t.reference_sigma) ** 2 * np.eye(3)
    )
    return float(np.mean(np.einsum("ki,ki->k", r, np.linalg.solve(S, r[..., None])[..., 0])))


def fit_bias_sigma(terms: list[NeesTerms], target: float = 3.0) -> float:
    """The ``σ_b`` [rad/s] whose NEES, averaged per sequence and then over ``terms``, is
    ``target`` (bisection on ``log σ_b`` in ``[1e-8, 1]``)."""
    f = lambda s: np.mean([average_nees(t, s) for t in terms]) - target  # noqa: E731
    lo, hi = np.log(1e-8), np.log(1.0)
    if f(np.exp(lo)) < 0:  # consistent without any residual bias
        return float(np.exp(lo))
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(np.exp(mid)) > 0 else (lo, mid)
    return float(np.exp(0.5 * (lo + hi)))


def leave_one_out(terms: list[NeesTerms]) -> list[tuple[float, float]]:
    """For each sequence, ``(σ_b fitted on the others, its average NEES with it)``."""
    out = []
    for i, t in enumerate(terms):
        others = terms[:i] + terms[i + 1 :]
        s = fit_bias_sigma(others) if others else float("nan")
        out.append((s, average_nees(t, s)))
    return out


@partial(jax.jit, static_argnames=("n", "steps"))
def _window_nees_run(model, gyro, accel, q_true, dt, i0, n, steps=False):
    """For recordings ``(S, N, ·)`` (padded to one length by repeating their last sample:
    the network and the tracker are causal, so the padding changes no window before it),
    the NEES terms at the ends of the windows of ``n`` steps from the samples ``i0``
    ``(S, W)``, each integrated from its true attitude (the network sees the whole run),
    each ``(S, W, ·)``. With ``steps``: and the windows' step transitions ``(S, W, n, 6, 6)``
    and intervals ``(S, W, n)`` for :func:`fit_bias_markov`. One program for all the
    recordings: compiled per recording, the windows of a training's validation parts were
    one compile each."""
    c = model(gyro, accel)
    rw, markov = model.config.gyro_random_walk, model.config.bias_markov
    ref = model.reference_sigma.astype(c.gyro.dtype)

    def one(g_all, d_all, s_all, q, dt, i0):
        idx = i0[:, None] + jnp.arange(n + 1)  # (W, n + 1): each window's samples, both ends
        g, d = g_all[idx], d_all[idx]
        h = dt[idx[:, :-1]]
        q_end = jax.vmap(lambda q0, g, h: integrate_attitude(q0, g, h)[-1])(q[i0], g, h)
        r, _, _ = orientation_errors(q_end, q[i0 + n])
        W, B = jax.vmap(lambda g, d, h, s: attitude_terms(g, d, h, rw, s, markov))(
            g, d, h, s_all[idx]
        )
        if not steps:
            return r, W[:, -1], B[:, -1]
        F, _ = rotation_step_blocks(g[:, :-1], d[:, :-1], h, 0.0)
        return r, W[:, -1], B[:, -1], F, h

    out = jax.vmap(one)(c.gyro, c.gyro_density, c.gyro_bias_sigma, q_true, dt, i0)
    terms = NeesTerms(out[0], out[1], out[2], ref)
    return (terms, out[3:]) if steps else terms


def _window_starts(model, seq, seconds, start):
    """``(n, i0)``: the samples per window of ``seconds`` and the first samples of the
    consecutive windows from ``start`` on with a reference at both ends
    (:func:`window_nees_terms`); DataError when none has."""
    n, start = window_samples(model, seq, seconds, start)
    i0 = start + n * np.arange((len(seq) - 1 - start) // n)
    ref = seq.has_reference
    i0 = i0[ref[i0] & ref[i0 + n]]
    if not len(i0):
        raise DataError(
            f"sequence {seq.name!r}: none of its windows of {seconds!r} s from sample "
            f"{start} on has a ground-truth reference at both ends (motion-capture "
            "dropouts): pass shorter seconds"
        )
    return n, i0


def _windows(model, seqs, n, i0s, dtype, steps=False):
    """:func:`window_nees_terms` of the windows of ``n`` samples from ``i0s[i]`` of each of
    ``seqs`` (with ``steps``: and the windows' steps, see :func:`_window_nees_run`), in one
    program: a list with one entry per sequence."""
    dtype = compute_dtype("dtype", dtype)
    # to lengths that recordings of about one length share (padded_length): one program
    N = padded_length(max(len(s) for s in seqs))
    Wn = (N - 1) // n  # as many windows as N samples hold: a function of N and n alone

    def stack(x):  # each sequence's samples, its last repeated to N
        return jnp.asarray(np.stack([to_length(a, N) for a in x]), dtype)

    # each sequence's window starts, its last repeated to Wn (those rows are cut off)
    starts = np.stack([to_length(i, Wn) for i in i0s])
    dts = [np.asarray(s.dt)[:, None] for s in seqs]
    out = check_output(
        "window_nees_terms",
        _window_nees_run(
            model,
            stack([s.gyro for s in seqs]),
            stack([s.accel for s in seqs]),
            stack([s.q for s in seqs]),
            stack(dts)[..., 0],
            jnp.asarray(starts),
            n,
            steps,
        ),
        "the model's corrections or covariance of sequences "
        f"{[s.name for s in seqs]} overflow {dtype.name}",
    )
    t, extra = (out[0], out[1]) if steps else (out, ())
    r, W, B = np.asarray(t.r), np.asarray(t.W), np.asarray(t.B)  # (cut on the host: no
    # slicing program per recording's number of windows)
    rows = []
    for k, i in enumerate(i0s):
        m = len(i)
        terms = NeesTerms(r[k, :m], W[k, :m], B[k, :m], t.reference_sigma)
        rows.append((terms, tuple(x[k, :m] for x in extra)) if steps else terms)
    return rows


def window_nees_terms(model, seq, seconds: float, start: int = 0, dtype=jnp.float32) -> NeesTerms:
    """The NEES terms of the orientation error at the end of each of the consecutive
    windows of ``seconds`` from sample ``start`` on, each integrated open loop from its own
    true attitude with ``model``'s corrected gyro (the network sees the whole recording, the
    samples before ``start`` as context): ``r = Log(R_trueᵀ R̂)`` ``(W, 3)`` [rad] at each
    window's last sample, and the covariance terms over that window alone
    (:func:`jaximu.learning.evaluation.attitude_terms`: the learned density, the bias random
    walk ``ModelConfig.gyro_random_walk`` and the tracked bias's ``σ``; ``B`` for the
    residual bias ``σ_b``, which :func:`average_nees` adds with ``2 σ_ref² I``, the ground
    truth's noise at the window's two ends).

    The error is taken at the window's end only, so the windows' NEES are independent draws
    up to the bias they share; a window is kept when the ground truth has a reference
    (:attr:`jaximu.learning.Sequence.has_reference`) at both its ends, so a motion-capture
    dropout inside it does not matter. A tail shorter than a window is left out.

    Raises:
        ValueError / InputError: ``model`` or ``seq`` not what they should be, ``seconds``
            not positive or outside one sample interval … the recording's length from
            ``start`` on, ``start`` past the last step (:func:`window_samples`); DataError:
            no window with a reference at both ends.
    """
    n, i0 = _window_starts(model, seq, seconds, start)
    return _windows(model, [seq], n, [i0], dtype)[0]


def window_nees(
    model, seq, seconds: float, start: int = 0, dtype=jnp.float32, bias_sigma=None
) -> float:
    """The average orientation NEES over the consecutive windows of ``seconds`` of ``seq``
    from sample ``start`` on, each window started from the true attitude and the error
    taken at its end (:func:`window_nees_terms`), with the model's covariance over the
    window: 3 when the model is consistent at that horizon. ``bias_sigma`` [rad/s]: the
    residual gyro bias, the model's ``σ_b`` when None. The whole run's NEES is
    :attr:`jaximu.learning.SequenceReport.nees_orientation`."""
    t = window_nees_terms(model, seq, seconds, start, dtype)
    sigma = (
        float(model.bias_sigma)
        if bias_sigma is None
        else check_positive("bias_sigma", bias_sigma, allow_zero=True)
    )
    return average_nees(t, sigma)


@jax.jit
def _markov_nll(p, data):
    """The negative log-likelihood of the windows' orientation errors, each horizon's mean
    summed (as :func:`_window_nll`'s), with a Gauss–Markov bias of ``σ_m = exp(p₀)``,
    ``τ = τ₀ + exp(p₁)`` added to each window's covariance; ``data``: ``(τ₀, per horizon
    (terms, F, h, σ_b))``."""
    tau0, data = data
    sm, tau = jnp.exp(p[0]), tau0 + jnp.exp(p[1])
    out = 0.0
    for t, F, h, sb in data:
        S = (
            t.W
            + sb**2 * t.B @ jnp.swapaxes(t.B, -1, -2)
            + sm**2 * markov_attitude(F, h, tau, save_all=False)
            + 2.0 * t.reference_sigma**2 * jnp.eye(3, dtype=t.W.dtype)
        )
        out = out + gaussian_nll(t.r, S)
    return out


def fit_bias_markov(
    model,
    sequences,
    starts=None,
    seconds=(1.0, 5.0),
    *,
    bias_sigma=None,
    steps: int = 100,
    dtype=jnp.float32,
) -> tuple[float, float]:
    """``(σ_m [rad/s], τ [s])`` of a first-order Gauss–Markov gyro bias (stationary
    standard deviation, correlation time) maximising the likelihood of the orientation
    errors at the ends of the windows of ``seconds`` of ``sequences``, each window started
    from the true attitude (:func:`window_nees_terms`), with the covariance the model
    predicts over the window plus the Gauss–Markov bias's
    (:func:`jaximu.learning.evaluation.markov_attitude`, through the engine's
    :func:`jaximu.accumulate_covariance`): the term a slowly varying bias error needs,
    which neither the constant ``σ_b`` (too small over a few seconds once set for the whole
    run) nor a random walk (unbounded over the whole run) can give. The network is fixed;
    L-BFGS in ``(log σ_m, log(τ - τ₀))`` from ``τ₀ + 10 s`` and the ``σ_m`` that alone
    would explain the shortest windows' errors, the model's own
    Gauss–Markov bias left out of the covariance. ``τ₀`` is the shortest window: the bias
    is the slowly varying error, and an error that varies faster than the shortest window
    is white noise over the windows, the learned density's to explain (unbounded, the
    likelihood of windows whose errors grow slower than ``√t``, the ground truth's own
    error over seconds, takes ``τ`` to zero: a white noise of ``σ_m √dt``, which depends on
    the sampling interval and is not the bias the term is for).

    Args:
        sequences: :class:`jaximu.learning.Sequence` s (held-out data: the validation parts).
        starts: per sequence, the sample the windows start from (the samples before are the
            network's context), or None (0 each).
        seconds: the windows' lengths [s]; a sequence shorter than one of them from its start
            has no window of it.
        bias_sigma: the constant residual bias ``σ_b`` [rad/s] (None: the model's).
        steps: L-BFGS iterations at most.

    Raises:
        ValueError / InputError: bad arguments, named; DataError: no window at all.
    """
    check_model("model", model)
    if not isinstance(sequences, (list, tuple)) or not sequences:
        raise ValueError(
            "sequences must be a non-empty list of jaximu.learning.Sequence, got "
            f"{type(sequences).__name__}"
        )
    for i, s in enumerate(sequences):
        check_sequence(f"sequences[{i}]", s)
    starts = [0] * len(sequences) if starts is None else list(starts)
    if len(starts) != len(sequences):
        raise ValueError(
            f"starts must give one sample per sequence ({len(sequences)}), got {len(starts)}"
        )
    starts = [check_int(f"starts[{i}]", x, 0) for i, x in enumerate(starts)]
    try:
        seconds = tuple(seconds)
    except TypeError:
        raise ValueError(
            f"seconds must be window lengths [s], e.g. (1.0, 5.0), got {seconds!r}"
        ) from None
    if not seconds:
        raise ValueError("seconds must name at least one window length [s], e.g. (1.0, 5.0)")
    seconds = tuple(
        check_positive(f"seconds[{i}]", x, hint=": pass window lengths [s], e.g. (1.0, 5.0)")
        for i, x in enumerate(seconds)
    )
    steps = check_int("steps", steps, 1)
    sb = (
        float(model.bias_sigma)
        if bias_sigma is None
        else check_positive("bias_sigma", bias_sigma, allow_zero=True)
    )
    parts = _markov_parts(model, sequences, starts, seconds, dtype)
    return _fit_markov(parts, sb, min(seconds), steps)


def _markov_parts(model, sequences, starts, seconds, dtype=jnp.float32) -> dict:
    """``{seconds: [(i, terms, F, h)]}``: for each window length, each sequence ``i`` that
    holds a window of it with a reference at both ends from ``starts[i]`` on, its
    :func:`window_nees_terms` without the model's Gauss–Markov bias, and its windows' step
    transitions and intervals (what :func:`markov_attitude` needs)."""
    base = with_bias_markov(model, 0.0)
    out: dict = {}
    for w in seconds:
        rows = []  # the sequences that hold a window of w with a reference at both ends
        for i, (s, k) in enumerate(zip(sequences, starts)):
            if (len(s) - 1 - k) / s.rate_hz < w:
                continue
            try:
                rows.append((i, *_window_starts(base, s, w, k)))
            except DataError:
                continue
        found = {}
        for n in sorted({r[1] for r in rows}):  # one program per window's samples
            group = [r for r in rows if r[1] == n]
            got = _windows(
                base, [sequences[i] for i, _, _ in group], n, [r[2] for r in group], dtype, True
            )
            found.update({i: (i, t, F, h) for (i, _, _), (t, (F, h)) in zip(group, got)})
        out[w] = [found[i] for i in sorted(found)]
    return out


def _fit_markov(parts: dict, bias_sigma: float, tau0: float, steps: int = 100):
    """:func:`fit_bias_markov` on :func:`_markov_parts`' windows."""
    cat = lambda xs: jnp.concatenate(list(xs), 0)  # noqa: E731
    data = []
    for w in sorted(parts):  # the shortest first
        rows = parts[w]
        if not rows:
            continue
        t = NeesTerms(
            cat(r[1].r for r in rows),
            cat(r[1].W for r in rows),
            cat(r[1].B for r in rows),
            rows[0][1].reference_sigma,
        )
        F, h = cat(r[2] for r in rows), cat(r[3] for r in rows)
        data.append((t, F, h, jnp.asarray(bias_sigma, t.W.dtype)))
    if not data:
        raise DataError(
            f"no sequence holds a window of {min(parts):g} s with a ground-truth reference "
            "at both ends from its start: give longer sequences or shorter seconds"
        )
    # from the bias that alone would explain the shortest windows' errors (where the
    # likelihood's gradient is not lost under the other terms)
    t = data[0][0]
    start = np.sqrt(np.mean(np.sum(np.asarray(t.r, np.float64) ** 2, -1)) / 3.0) / tau0
    p0 = jnp.asarray([np.log(max(start, 1e-9)), np.log(10.0)], data[0][1].dtype)
    p = np.asarray(_lbfgs(_markov_nll, p0, (jnp.asarray(tau0, p0.dtype), data), steps))
    return float(np.exp(p[0])), float(tau0 + np.exp(p[1]))


def _with_markov_terms(t: NeesTerms, F, h, markov) -> NeesTerms:
    """``t`` with a Gauss–Markov bias ``markov = (σ_m, τ)`` added to its ``W``."""
    sm, tau = markov
    return NeesTerms(t.r, t.W + sm**2 * markov_attitude(F, h, tau, False), t.B, t.reference_sigma)


def set_bias_markov(model, sequences, vals, record, say, fit: bool = True):
    """After :func:`set_bias_sigma`: the windowed NEES (1 s and 5 s,
    :func:`window_nees`) of each validation part ``vals`` of ``sequences``, recorded in
    ``record["uncertainty"]``; with ``fit``, ``model`` with a Gauss–Markov bias fitted on
    those windows (:func:`fit_bias_markov`) and the NEES with it recorded beside."""
    starts = [len(s) - len(v) for s, v in zip(sequences, vals)]
    parts = _markov_parts(model, sequences, starts, (1.0, 5.0))
    sb = float(model.bias_sigma)

    def table(markov):
        out: dict = {v.name: {} for v in vals}
        for w, rows in parts.items():
            for i, t, F, h in rows:
                t = t if markov is None else _with_markov_terms(t, F, h, markov)
                out[vals[i].name][f"{w:g}s"] = average_nees(t, sb)
        return out

    def line(nees):
        return " ".join(
            f"{n} " + "/".join(f"{x:.2f}" for x in row.values()) for n, row in nees.items() if row
        )

    u = record.setdefault("uncertainty", {})
    u["validation_window_nees"] = before = table(model.config.bias_markov)
    say(f"validation windowed NEES (1 s / 5 s from the true attitude): {line(before)}")
    if not fit or not any(parts.values()):
        return model
    markov = _fit_markov(parts, sb, 1.0)
    u["bias_markov_sigma"], u["bias_markov_time"] = markov
    u["validation_window_nees_markov"] = after = table(markov)
    say(
        f"Gauss–Markov gyro bias σ_m = {markov[0]:.3g} rad/s, τ = {markov[1]:.3g} s, by the "
        f"likelihood of those windows; their NEES with it: {line(after)}"
    )
    return with_bias_markov(model, *markov)


def with_bias_markov(model, sigma: float, time: float | None = None):
    """``model`` with its Gauss–Markov bias set to ``sigma`` [rad/s] (0: none) and
    correlation time ``time`` [s] (None: the model's), in its settings
    (``ModelConfig.bias_markov_sigma``, ``bias_markov_time``: saved with it)."""
    check_model("model", model)
    cfg = model.config
    time = cfg.bias_markov_time if time is None else time
    new = dataclasses.replace(cfg, bias_markov_sigma=sigma, bias_markov_time=time)
    skeleton = Denoiser(new, jax.random.key(0))  # the same structure; the weights are model's
    return jax.tree_util.tree_unflatten(
        jax.tree_util.tree_structure(skeleton), jax.tree_util.tree_leaves(model)
    )


def _with_log(model, where, value: float, name: str):
    """``model`` with the log-parameter ``where(model)`` set to ``log(value)``, in its dtype
    (``value`` a positive number, named ``name`` if not)."""
    check_model("model", model)
    value = check_positive(name, value)
    return eqx.tree_at(where, model, jnp.asarray(np.log(value), where(model).dtype))


def with_bias_sigma(model, bias_sigma: float):
    """``model`` with its residual gyro bias set to ``bias_sigma`` [rad/s]."""
    return _with_log(model, lambda m: m.log_bias_sigma, bias_sigma, "bias_sigma")


@eqx.filter_jit
def _window_terms(model, gyro, accel, gyro_bias, q_true, dt, horizons, skip, reference):
    c = model(gyro, accel, gyro_bias=gyro_bias)
    rw = model.config.gyro_random_walk
    terms = increment_terms(c, q_true, dt, horizons, random_walk=rw, skip=skip, reference=reference)
    return list(terms)


@jax.jit
def _window_nll(log_sigmas, terms):
    """The training loss's negative log-likelihood of the windows ``terms`` (per horizon
    ``(r, Phi, Q, m)``) with ``(σ_b, σ_ref) = exp(log_sigmas)``."""
    sb, sr = jnp.exp(log_sigmas[0]), jnp.exp(log_sigmas[1])
    return sum(gaussian_nll(r, rotation_covariance(Phi, Q, sb, sr), m) for r, Phi, Q, m in terms)


@partial(jax.jit, static_argnums=(0, 3))
def _lbfgs(nll, p, terms, steps):
    """L-BFGS on ``nll(p, terms)`` from ``p`` (optax's, its zoom line search), one
    compiled loop: until the gradient's largest entry is under 1e-6 or ``steps`` iterations."""
    f = lambda q: nll(q, terms)  # noqa: E731
    opt = optax.lbfgs()
    value_and_grad = optax.value_and_grad_from_state(f)

    def body(carry):
        p, state, i = carry
        value, grad = value_and_grad(p, state=state)
        updates, state = opt.update(grad, state, p, value=value, grad=grad, value_fn=f)
        return optax.apply_updates(p, updates), state, i + 1

    def more(carry):
        _, state, i = carry
        grad = optax.tree.get(state, "grad")
        return (i == 0) | ((i < steps) & (jnp.max(jnp.abs(grad)) > 1e-6))

    return jax.lax.while_loop(more, body, (p, opt.init(p), 0))[0]


def fit_reference_sigma(
    model,
    gyro,
    accel,
    q_true,
    dt,
    horizons,
    *,
    gyro_bias=None,
    skip: int = 0,
    steps: int = 100,
    reference=None,
) -> tuple[float, float]:
    """``(σ_ref [rad], σ_b [rad/s])`` maximising the likelihood of the increments of
    ``model``'s corrected gyro against the ground truth (the negative log-likelihood of
    :func:`jaximu.learning.losses.increment_loss` at ``horizons``, the network fixed).
    ``σ_b`` is the residual bias over those short horizons, fitted alongside as a nuisance
    parameter (the whole-run ``σ_b`` is :func:`fit_bias_sigma`'s).

    Args:
        gyro, accel: ``(S, T, 3)`` raw samples; q_true: ``(S, T + 1, 4)`` true attitudes.
        dt: the sample interval [s]; gyro_bias: ``(S, T, 3)`` the tracked bias, or None (the
            model tracks it).
        steps: L-BFGS iterations at most, in ``log σ`` (it stops when the gradient vanishes).
        reference: ``(S, T + 1)`` booleans, where the ground truth has a reference (None:
            everywhere); windows without one at both ends are left out.
    """
    check_model("model", model)
    horizons, skip = check_horizons("horizons", horizons), check_int("skip", skip, 0)
    terms = _window_terms(model, gyro, accel, gyro_bias, q_true, dt, horizons, skip, reference)
    p0 = jnp.stack([model.log_bias_sigma, model.log_reference_sigma]).astype(gyro.dtype)
    p = _lbfgs(_window_nll, p0, terms, check_int("steps", steps, 1))
    sb, sr = np.exp(np.asarray(p, np.float64))
    return float(sr), float(sb)


def with_reference_sigma(model, reference_sigma: float):
    """``model`` with the ground truth's attitude noise set to ``reference_sigma`` [rad]."""
    return _with_log(model, lambda m: m.log_reference_sigma, reference_sigma, "reference_sigma")


def set_bias_sigma(model, terms: list[NeesTerms], names: list[str], record, say):
    """``model`` with ``σ_b`` set on the validation parts' NEES ``terms`` (named ``names``;
    :func:`fit_bias_sigma`, after training); writes ``record["uncertainty"]`` with each
    part's NEES with ``σ_b`` set on the other parts, and says so."""
    sigma = fit_bias_sigma(terms)
    loo = leave_one_out(terms)
    record["uncertainty"] = {
        "bias_sigma": sigma,
        "learned_bias_sigma": float(model.bias_sigma),
        "reference_sigma": float(model.reference_sigma),
        "validation_nees_leave_one_out": {v: n for v, (_, n) in zip(names, loo)},
    }
    achieved = float(np.mean([average_nees(t, sigma) for t in terms]))
    say(
        f"residual gyro bias σ_b = {sigma:.3g} rad/s, set on the validation parts (average "
        f"NEES {achieved:.2f}"
        + ("" if achieved > 2.9 else ": below 3 with no residual bias at all")
        + "); "
        + (
            "each sequence's NEES with σ_b set on the others: "
            + " ".join(f"{v} {n:.2f}" for v, (_, n) in zip(names, loo))
            if len(names) > 1
            else "one sequence: no leave-one-out NEES"
        )
    )
    return with_bias_sigma(model, sigma)
