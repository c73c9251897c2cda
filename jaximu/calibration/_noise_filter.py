"""The exact joint likelihood of consecutive windows' residuals (the noise fit's model): a
linear-Gaussian state space whose prediction-error decomposition a Kalman filter evaluates.

Model. Keyframes ``0..K`` a window apart; window ``k`` runs from keyframe ``k`` to ``k+1``.
With the preintegration error ``[δθ, δp, δv, δb_g, δb_a]`` of :mod:`jaximu.preintegration`
(true minus estimate, ``δb = b_true - b̂``) and the reference's error ``ε_k = [δθ, δp, δv]``
at keyframe ``k`` (``q ⊗ Exp(δθ)``, ``p + δp``, ``v + δv``; white, ``diag(σ_θ², σ_p², σ_v²)``
per axis), the residual of :func:`jaximu.residual` is, to first order,

    r_k = F_k δb_k + n_k + A_k ε_k + B_k ε_{k+1},      δb_{k+1} = δb_k + w_k,

``F_k`` the window's bias Jacobian (``transition[:9, 9:]``), ``(n_k, w_k)`` the window's
preintegration noise with covariance ``cov15`` (white noise and the bias random walk inside
the window, their correlation included; linear in the four squared densities), ``A_k``,
``B_k`` the residual's derivatives in the reference's errors at the window's ends (a tilt
error also turns gravity), ``δb_0 = 0`` (the fit's constant bias is the bias at the first
keyframe). The state ``x_k = [δb_k, ε_k]`` (15) carries the bias deviation and the
reference's error shared by windows ``k-1`` and ``k`` (a moving-average term). One step
maps ``x_k`` and the step's noise ``ν_k = [n_k, w_k, ε_{k+1}]`` to ``[r_k; x_{k+1}]``:

    [r_k; x_{k+1}] = G_k x_k + Γ_k ν_k,   G_k = [[F_k, A_k], [I, 0], [0, 0]],
    Γ_k = [[I, 0, B_k], [0, I, 0], [0, 0, I]],   Cov ν_k = blockdiag(cov15_k, R),

so ``Q_k = Γ_k Cov(ν_k) Γ_kᵀ`` (24×24) is linear in the squared σ (the four densities, or
their twelve per-axis values, and ``σ_θ, σ_p, σ_v``): ``Q_k = Σ_b σ_b² Q_kb``.

Likelihood. From ``x_k | r_{<k} ~ N(m, P)``: ``[r_k; x_{k+1}]`` has mean ``G m`` and
covariance ``G P Gᵀ + Q_k``; the innovation ``e_k = r_k - (G m)_r`` has covariance ``S_k``
(the ``r`` block), and conditioning on it gives ``x_{k+1} | r_{≤k}``. Then

    NLL = ½ Σ_k (e_kᵀ S_k⁻¹ e_k + log det S_k)   (+ const)

is the exact negative log-likelihood of all residuals jointly (correlations across windows
through the bias drift and the shared keyframes included). A longer window's residual is a
function of the shorter ones', so windows of one length carry all the information; white
noise, random walk and the reference's noise separate through how the residuals correlate
in time. Windows in a reference gap are predicted through (no update).

Scaling (float32): residual rows are divided by the initial model's marginal standard
deviations ``d_k``; the state by ``σ_rw0 √T`` (bias, ``T`` the span) and ``σ_ref0``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np


def state_space(cov15_basis, bias_jacobian, reference_jacobian, ref_sigma0):
    """The filter's matrices in float64 numpy, scaled.

    Args:
        cov15_basis: ``(K, D, 15, 15)`` each window's ``cov15`` with one density alone at its
            initial value: ``D = 4`` isotropic densities, or ``D = 12`` per axis (density
            ``i``'s axis ``a`` at ``3 i + a``; the order of :data:`DENSITIES`).
        bias_jacobian: ``(K, 9, 6)`` ``F_k``.
        reference_jacobian: ``(K, 9, 2, 9)`` ``[A_k, B_k]`` (residual in the reference's
            errors at the window's start, end).
        ref_sigma0: ``(3,)`` initial ``(σ_θ, σ_p, σ_v)`` (positive).

    Returns:
        ``(H, Qb, P0b, d)``: ``H`` ``(K, 24, 15)`` the scaled ``G_k``; ``Qb`` ``(K, D + 3,
        24, 24)`` the scaled ``Q_kb`` at the initial σ (the densities', then ``σ_θ, σ_p,
        σ_v``); ``P0b`` ``(D + 3, 15, 15)`` the initial state's covariance (``ε_0``); ``d``
        ``(K, 9)`` the residual scale (divide ``r``)."""
    # a window in a reference gap may hold non-finite Jacobians; the filter only predicts
    # through it, and a NaN there would still reach the gradient through jnp.where
    cov = np.nan_to_num(np.asarray(cov15_basis, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    F = np.nan_to_num(np.asarray(bias_jacobian, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    Jr = np.nan_to_num(np.asarray(reference_jacobian, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    K, D = cov.shape[:2]
    n_sigma = D + 3
    per = D // 4  # bases per density: 1 isotropic, 3 per axis
    A, B = Jr[:, :, 0, :], Jr[:, :, 1, :]
    s_ref = np.repeat(np.asarray(ref_sigma0, np.float64), 3)  # (9,)
    # a window's bias variance per density (its axes' bases together); K windows: σ_rw0² T,
    # the bias state's scale
    rw_g, rw_a = slice(2 * per, 3 * per), slice(3 * per, 4 * per)
    var_win = (
        np.stack(
            [
                cov[:, rw_g, 9:12, 9:12].trace(axis1=2, axis2=3).sum(1),
                cov[:, rw_a, 12:15, 12:15].trace(axis1=2, axis2=3).sum(1),
            ],
            1,
        ).mean(0)
        / 3
    )
    s_b = np.repeat(np.sqrt(var_win * K), 3)
    s_b = np.where(s_b > 0, s_b, 1.0)
    # the physical noise bases: Cov ν per σ, mapped by Γ_k
    Qb = np.zeros((K, n_sigma, 24, 24))
    for i in range(D):
        Qb[:, i, :15, :15] = cov[:, i]  # [n; w] → [r; δb_{k+1}] with Γ = I there
    for j in range(3):
        Rj = np.zeros((9, 9))
        Rj[3 * j : 3 * j + 3, 3 * j : 3 * j + 3] = np.eye(3) * ref_sigma0[j] ** 2
        BR = B @ Rj  # (K, 9, 9)
        Qb[:, D + j, :9, :9] = BR @ np.swapaxes(B, 1, 2)
        Qb[:, D + j, :9, 15:] = BR
        Qb[:, D + j, 15:, :9] = np.swapaxes(BR, 1, 2)
        Qb[:, D + j, 15:, 15:] = Rj
    G = np.zeros((K, 24, 15))
    G[:, :9, :6], G[:, :9, 6:] = F, A
    G[:, 9:15, :6] = np.eye(6)
    P0b = np.zeros((n_sigma, 15, 15))
    for j in range(3):
        P0b[D + j, 6 + 3 * j : 9 + 3 * j, 6 + 3 * j : 9 + 3 * j] = np.eye(3) * ref_sigma0[j] ** 2
    # scaling: residual rows by the marginal σ of the initial model, state by s_x
    marg = Qb.sum(1)[:, :9, :9] + A @ P0b.sum(0)[6:, 6:] @ np.swapaxes(A, 1, 2)
    d = np.sqrt(np.maximum(np.diagonal(marg, axis1=1, axis2=2), 0))
    d = np.where(d > 0, d, 1.0)
    s_x = np.concatenate([s_b, s_ref])
    out = np.concatenate([d, np.broadcast_to(s_x, (K, 15))], 1)  # (K, 24)
    H = G / out[:, :, None] * s_x[None, None, :]
    Qb = Qb / (out[:, None, :, None] * out[:, None, None, :])
    P0b = P0b / (s_x[:, None] * s_x[None, :])
    return H, Qb, P0b, d


def _step(carry, inputs, c):
    """One window: predict ``[r_k; x_{k+1}]``, the innovation's NLL term, condition."""
    m, P = carry
    e_r, H, Qb, kept = inputs
    Q = jnp.einsum("b,bij->ij", c, Qb)
    M = H @ m
    C = H @ P @ H.T + Q
    C = 0.5 * (C + C.T)
    S = jnp.where(kept, C[:9, :9], jnp.eye(9, dtype=C.dtype))
    e = jnp.where(kept, e_r - M[:9], 0)
    L = jnp.linalg.cholesky(S)
    w = jax.scipy.linalg.solve_triangular(L, e, lower=True)
    X = jax.scipy.linalg.solve_triangular(L, C[:9, 9:], lower=True)  # L⁻¹ C_rx
    gain_e = X.T @ w  # C_xr S⁻¹ e
    m_new = M[9:] + jnp.where(kept, gain_e, 0)
    P_new = C[9:, 9:] - jnp.where(kept, X.T @ X, 0)
    P_new = 0.5 * (P_new + P_new.T)
    term = jnp.where(kept, 0.5 * (w @ w) + jnp.sum(jnp.log(jnp.diagonal(L))), 0)
    return (m_new, P_new), (term, w)


def filter_pass(u, r, H, Qb, P0b, kept):
    """``(NLL, w)``: the negative log-likelihood (scaled residuals; add ``Σ log d`` for the
    physical one) and the whitened innovations ``(K, 9)`` (zero where not ``kept``), at log
    σ offsets ``u`` ``(D + 3,)`` (``σ = σ_0 e^u``, the order of ``Qb``); ``r`` ``(K, 9)``
    scaled residuals."""
    c = jnp.exp(2 * u)
    P0 = jnp.einsum("b,bij->ij", c, P0b)
    m0 = jnp.zeros(15, r.dtype)
    _, (terms, w) = jax.lax.scan(lambda carry, x: _step(carry, x, c), (m0, P0), (r, H, Qb, kept))
    return jnp.sum(terms), w


def nll(p, r, J, H, Qb, P0b, kept, u0, free_idx, n_c, tie=None):
    """The NLL at ``p = [δ, u_free]``: residuals ``r + J δ`` (``J`` ``(K, 9, n_c)``, the
    calibration's fields linearised), log σ ``u0`` with ``u0[free_idx] = u_free[tie]``
    (``tie``: which free coordinate sets each of ``free_idx``, so that an isotropic density
    among per-axis bases sets its three axes' σ; ``None``: one each, in order)."""
    u = u0.at[free_idx].set(p[n_c:] if tie is None else p[n_c:][tie])
    e = r + jnp.einsum("kin,n->ki", J, p[:n_c])
    return filter_pass(u, e, H, Qb, P0b, kept)[0]


def nll_derivatives(p, r, J, H, Qb, P0b, kept, u0, free_idx, tie=None):
    """``(NLL, gradient, Hessian)`` in ``p`` (autodiff through the filter; ``n_c`` from
    ``J``'s last axis). The Hessian's columns one at a time (``lax.map`` of forward over
    reverse): ``jax.hessian`` batches the tangents through the filter's small Cholesky
    factors, several times slower on CPU."""
    n_c = J.shape[-1]
    f = lambda q: nll(q, r, J, H, Qb, P0b, kept, u0, free_idx, n_c, tie)  # noqa: E731
    value, grad = jax.value_and_grad(f)(p)
    column = lambda v: jax.jvp(jax.grad(f), (p,), (v,))[1]  # noqa: E731
    hess = jax.lax.map(column, jnp.eye(p.shape[0], dtype=p.dtype))
    return value, grad, 0.5 * (hess + hess.T)


DERIVATIVES_COMPILE = {"xla_backend_optimization_level": 1}
"""XLA options for :func:`nll_derivatives` of a small problem. Not the calibration's
``QUICK_COMPILE`` (level 0): the filter's scans of small matrices, forward over reverse once
per coordinate, run about twice as long there (0.21 s against 0.11 s per evaluation of 80
windows and 13 coordinates on 2 CPU cores), which over a fit's ten to thirty evaluations
costs more than the 1 to 1.5 s of compile time level 0 saves; level 1 compiles faster than
XLA's default and runs as fast."""


@functools.cache
def compiled_derivatives(quick: bool):
    """:func:`nll_derivatives` jitted, with :data:`DERIVATIVES_COMPILE` when ``quick`` (a small
    problem, whose compile time weighs)."""

    return jax.jit(nll_derivatives, compiler_options=DERIVATIVES_COMPILE if quick else None)


@jax.jit
def whitened_innovations(u, r, H, Qb, P0b, kept):
    """``(K, 9)`` ``L_k⁻¹ e_k`` (``S_k = L_k L_kᵀ``): white with unit variance under the model."""
    return filter_pass(u, r, H, Qb, P0b, kept)[1]
