"""The residual gyro bias ``σ_b`` of the learned uncertainty, set on held-out data.

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

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaximu.learning.evaluation import attitude_terms, integrate_attitude, orientation_errors

__all__ = [
    "NeesTerms",
    "nees_terms",
    "average_nees",
    "fit_bias_sigma",
    "leave_one_out",
    "with_bias_sigma",
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
    samples before it as context)."""
    cast = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    return _terms(model, cast(seq.gyro), cast(seq.accel), cast(seq.q), cast(seq.dt), start)


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


def with_bias_sigma(model, bias_sigma: float):
    """``model`` with its residual gyro bias set to ``bias_sigma`` [rad/s]."""
    return eqx.tree_at(
        lambda m: m.log_bias_sigma,
        model,
        jnp.asarray(np.log(bias_sigma), model.log_bias_sigma.dtype),
    )
