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
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaximu.geometry._checks import check_int, check_output, check_positive, compute_dtype
from jaximu.io import DataError
from jaximu.learning.data import check_sequence
from jaximu.learning.evaluation import (
    attitude_terms,
    integrate_attitude,
    orientation_errors,
    window_samples,
)
from jaximu.learning.losses import (
    check_horizons,
    gaussian_nll,
    increment_terms,
    rotation_covariance,
)
from jaximu.learning.model import check_model

__all__ = [
    "NeesTerms",
    "nees_terms",
    "average_nees",
    "fit_bias_sigma",
    "fit_reference_sigma",
    "leave_one_out",
    "window_nees_terms",
    "window_nees",
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
    W, B = attitude_terms(
        g, d, dt[start:], model.config.gyro_random_walk, c.gyro_bias_sigma[start:]
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


@partial(jax.jit, static_argnames=("n",))
def _window_nees_run(model, gyro, accel, q_true, dt, i0, n):
    """The NEES terms at the ends of the windows of ``n`` steps from the samples ``i0``
    ``(W,)``, each integrated from its true attitude (the network sees the whole run)."""
    c = model(gyro, accel)
    idx = i0[:, None] + jnp.arange(n + 1)  # (W, n + 1): each window's samples, both ends in
    g = c.gyro[idx]
    h = dt[idx[:, :-1]]
    q_end = jax.vmap(lambda q0, g, h: integrate_attitude(q0, g, h)[-1])(q_true[i0], g, h)
    r, _, _ = orientation_errors(q_end, q_true[i0 + n])
    rw = model.config.gyro_random_walk
    W, B = jax.vmap(lambda g, d, h, s: attitude_terms(g, d, h, rw, s))(
        g, c.gyro_density[idx], h, c.gyro_bias_sigma[idx]
    )
    return NeesTerms(r, W[:, -1], B[:, -1], model.reference_sigma.astype(g.dtype))


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
    n, start = window_samples(model, seq, seconds, start)
    dtype = compute_dtype("dtype", dtype)
    i0 = start + n * np.arange((len(seq) - 1 - start) // n)
    ref = seq.has_reference
    i0 = i0[ref[i0] & ref[i0 + n]]
    if not len(i0):
        raise DataError(
            f"sequence {seq.name!r}: none of its windows of {seconds!r} s from sample "
            f"{start} on has a ground-truth reference at both ends (motion-capture "
            "dropouts): pass shorter seconds"
        )
    cast = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    return check_output(
        "window_nees_terms",
        _window_nees_run(
            model, cast(seq.gyro), cast(seq.accel), cast(seq.q), cast(seq.dt), jnp.asarray(i0), n
        ),
        f"the model's corrections or covariance of sequence {seq.name!r} overflow {dtype.name}",
    )


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


@partial(jax.jit, static_argnums=2)
def _lbfgs(p, terms, steps):
    """L-BFGS on :func:`_window_nll` from ``p`` (optax's, its zoom line search), one
    compiled loop: until the gradient's largest entry is under 1e-6 or ``steps`` iterations."""
    f = lambda q: _window_nll(q, terms)  # noqa: E731
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
    p = _lbfgs(p0, terms, check_int("steps", steps, 1))
    sb, sr = np.exp(np.asarray(p, np.float64))
    return float(sr), float(sb)


def with_reference_sigma(model, reference_sigma: float):
    """``model`` with the ground truth's attitude noise set to ``reference_sigma`` [rad]."""
    return _with_log(model, lambda m: m.log_reference_sigma, reference_sigma, "reference_sigma")


def set_bias_sigma(model, sequences, vals, record, say):
    """``model`` with ``σ_b`` set on the validation parts ``vals`` of ``sequences``
    (:func:`fit_bias_sigma`, after training); writes ``record["uncertainty"]`` with each
    sequence's NEES with ``σ_b`` set on the other sequences, and says so."""
    terms = [nees_terms(model, s, len(s) - len(v)) for s, v in zip(sequences, vals)]
    sigma = fit_bias_sigma(terms)
    loo = leave_one_out(terms)
    record["uncertainty"] = {
        "bias_sigma": sigma,
        "learned_bias_sigma": float(model.bias_sigma),
        "reference_sigma": float(model.reference_sigma),
        "validation_nees_leave_one_out": {v.name: n for v, (_, n) in zip(vals, loo)},
    }
    achieved = float(np.mean([average_nees(t, sigma) for t in terms]))
    say(
        f"residual gyro bias σ_b = {sigma:.3g} rad/s, set on the validation parts (average "
        f"NEES {achieved:.2f}"
        + ("" if achieved > 2.9 else ": below 3 with no residual bias at all")
        + "); "
        + (
            "each sequence's NEES with σ_b set on the others: "
            + " ".join(f"{v.name} {n:.2f}" for v, (_, n) in zip(vals, loo))
            if len(vals) > 1
            else "one sequence: no leave-one-out NEES"
        )
    )
    return with_bias_sigma(model, sigma)
