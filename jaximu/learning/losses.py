"""Losses on orientation (and velocity) increments, computed by jaximu's own integration.

For a horizon of ``H`` samples the corrected samples are cut into windows and each window is
preintegrated (:func:`jaximu.preintegrate`, batched over all windows, differentiated end to
end); the residual of a window is ``r = Log(ΔR_gtᵀ ΔR̂)`` (the true increment from the
ground truth's attitudes at the window's ends). Longer horizons compose neighbouring
windows (``ΔR_ac = ΔR_ab ΔR_bc``), as Brossard's loss does.

The uncertainty of ``r`` is propagated with the model's per-sample noise density by the
engine's per-step Jacobians (:func:`jaximu.step_jacobians`, :func:`jaximu.discrete_process_noise`)
over the state ``[δθ, δb_g]``, with the model's residual gyro bias ``σ_b`` as the bias's
prior and the ground truth's own attitude noise ``σ_ref`` at both ends:
``S = P_θθ + 2 σ_ref² I``. The negative log-likelihood ``½ rᵀ S⁻¹ r + ½ log det S`` trains
the noise outputs; the residual enters it without gradient, so the corrections are trained
by the published Huber loss alone and the uncertainty cannot trade accuracy for variance.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaximu.engine.errorstate import (
    accumulate_covariance,
    compose_transitions,
    small_matmul,
    transition_products,
)
from jaximu.engine.preintegration import preintegrate
from jaximu.geometry import so3
from jaximu.geometry._checks import check_finite, check_int, check_sign, to_dtype
from jaximu.geometry._tolerances import check_unit_norm
from jaximu.geometry.noise import ImuNoise
from jaximu.schemes.integrators import blocks_analytic

__all__ = [
    "Windows",
    "windows",
    "huber",
    "increment_loss",
    "rotation_covariance",
    "gaussian_nll",
    "velocity_residuals",
]


class Windows(NamedTuple):
    """Orientation increments of consecutive windows (leading axes ``(..., W)``).

    Attributes:
        delta_q: ``(..., W, 4)`` ΔR̂ of each window (unit quaternion).
        delta_v: ``(..., W, 3)`` Δv̂ of each window in its first body frame [m/s].
        Phi, Q: ``(..., W, 6, 6)`` the window's transition and noise of ``[δθ, δb_g]``
            (``None`` when no density is given).
    """

    delta_q: jax.Array
    delta_v: jax.Array
    Phi: jax.Array | None
    Q: jax.Array | None


def _cut(x, H):
    """``(..., T, c)`` → ``(..., T // H, H, c)`` (a tail shorter than ``H`` is dropped)."""
    W = x.shape[-2] // H
    return x[..., : W * H, :].reshape(x.shape[:-2] + (W, H, x.shape[-1]))


def rotation_step_blocks(gyro, density, dt, random_walk):
    """Per-step ``(Φ, Q)`` of ``[δθ, δb_g]`` (``(..., 6, 6)``) from the engine's Euler blocks
    (:func:`jaximu.errorstate.blocks_analytic`: ``Φ_θθ = Exp(ω dt)ᵀ``, ``Φ_θbg = -Jr dt``,
    which is also the gyro noise's column of ``G``) and the noise model's ``σ²/dt``
    (:meth:`jaximu.ImuNoise.discrete_variances`): ``Q = G Q_c Gᵀ`` on these rows.

    Only the rotation and gyro-bias rows are formed: they are exact on their own (the
    rotation error depends on itself and the gyro bias alone), and the 15×15 product cost
    more than the network's forward pass in training."""
    batch = gyro.shape[:-1]
    dtype = gyro.dtype
    h = jnp.broadcast_to(jnp.asarray(dt, dtype), batch)
    eye = jnp.eye(3, dtype=dtype)
    zero = jnp.zeros(batch + (3,), dtype)
    b = blocks_analytic("euler", jnp.broadcast_to(eye, batch + (3, 3)), gyro, zero, gyro, zero, h)
    noise = ImuNoise(
        density, jnp.zeros((), dtype), jnp.asarray(random_walk, dtype), jnp.zeros((), dtype)
    )
    var = noise.discrete_variances(h, dtype)  # [σ_g², σ_a², σ_bg², σ_ba²] / dt, (..., 12)
    Z = jnp.zeros(batch + (3, 3), dtype)
    Phi = jnp.concatenate(
        [jnp.concatenate([b.A, b.B], -1), jnp.concatenate([Z, jnp.broadcast_to(eye, Z.shape)], -1)],
        -2,
    )
    Q_tt = small_matmul(b.B * var[..., None, 0:3], jnp.swapaxes(b.B, -1, -2))
    walk = (h * h)[..., None, None] * var[..., None, 6:9] * eye  # G_bb = dt I
    Q = jnp.concatenate([jnp.concatenate([Q_tt, Z], -1), jnp.concatenate([Z, walk], -1)], -2)
    return Phi, Q


def windows(gyro, accel, dt, H: int, density=None, random_walk=0.0) -> Windows:
    """Preintegrate windows of ``H`` samples.

    Args:
        gyro, accel: ``(..., T, 3)`` corrected samples; dt: sample interval [s] (scalar).
        H: samples per window; density: ``(..., T, 3)`` gyro noise density [rad/s/√Hz], or
            ``None`` for the mean only; random_walk: gyro bias random walk [rad/s²/√Hz].
    """
    g, a = _cut(gyro, H), _cut(accel, H)
    dtype = gyro.dtype
    pim = preintegrate(g, a, jnp.asarray(dt, dtype))
    Phi = Q = None
    if density is not None:
        # the Jacobians at the corrected rates, without their gradient: the likelihood
        # trains the noise, not the corrections
        F, Qs = rotation_step_blocks(
            jax.lax.stop_gradient(g), _cut(density, H), jnp.asarray(dt, dtype), random_walk
        )
        # the window's transition (the product of its steps') and noise (accumulated from 0)
        Phi = transition_products(F)[..., -1, :, :]
        Q = accumulate_covariance(F, Qs)
    return Windows(pim.delta_q, pim.delta_v, Phi, Q)


def _pick(x, tail: int, start: int, W: int):
    """Every other window from ``start`` (the window axis is the one before ``tail`` axes)."""
    return x[(Ellipsis, slice(start, 2 * W, 2)) + (slice(None),) * tail]


def compose_pairs(w: Windows) -> Windows:
    """Windows of twice the horizon: each even window followed by the next odd one
    (``ΔR_ac = ΔR_ab ΔR_bc``, ``Δv_ac = Δv_ab + ΔR_ab Δv_bc``, ``Φ_ac = Φ_bc Φ_ab``,
    ``Q_ac = Φ_bc Q_ab Φ_bcᵀ + Q_bc``)."""
    W = w.delta_q.shape[-2] // 2
    q1, q2 = _pick(w.delta_q, 1, 0, W), _pick(w.delta_q, 1, 1, W)
    v1, v2 = _pick(w.delta_v, 1, 0, W), _pick(w.delta_v, 1, 1, W)
    dq = so3.quat_normalize(so3.quat_mul(q1, q2))
    dv = v1 + so3.quat_rotate(q1, v2)
    Phi = Q = None
    if w.Phi is not None:
        F1, F2 = _pick(w.Phi, 2, 0, W), _pick(w.Phi, 2, 1, W)
        Q1, Q2 = _pick(w.Q, 2, 0, W), _pick(w.Q, 2, 1, W)
        Phi, Q = compose_transitions((F1, Q1), (F2, Q2))
    return Windows(dq, dv, Phi, Q)


def window_references(reference, H: int):
    """``(..., W)`` whether each window of ``H`` samples has a reference at both ends, from
    ``reference`` ``(..., T + 1)`` (per sample, as ``q_true``; a window's true increment reads
    the ground truth at its two ends only)."""
    n = (reference.shape[-1] - 1) // H
    ends = reference[..., 0 : n * H + 1 : H]
    return ends[..., :-1] & ends[..., 1:]


def true_increments(q, H: int, start: int = 0):
    """``(..., W, 4)`` true ``ΔR`` of consecutive windows of ``H`` samples from ``start``,
    from the attitudes ``q`` ``(..., T, 4)``: ``q_{k}⁻¹ q_{k+H}``."""
    n = (q.shape[-2] - 1 - start) // H
    ends = q[..., start : start + n * H + 1 : H, :]
    return so3.quat_mul(so3.quat_conj(ends[..., :-1, :]), ends[..., 1:, :])


def rotation_residual(dq_true, dq_hat):
    """``Log(ΔR_trueᵀ ΔR̂)`` ``(..., 3)`` [rad]."""
    return so3.log(so3.quat_mul(so3.quat_conj(dq_true), dq_hat))


def _mean(x, weights):
    """The mean of ``x`` ``(..., W)`` over everything, or weighted by ``weights`` (same shape:
    1 for a window with a reference at both ends, 0 for one without)."""
    if weights is None:
        return jnp.mean(x)
    w = jnp.broadcast_to(weights.astype(x.dtype), x.shape)
    return jnp.sum(w * x) / jnp.maximum(jnp.sum(w), 1.0)


def huber(r, delta: float, weights=None):
    """Brossard's loss on residuals ``r``: ``δ²·SmoothL1(r/δ)`` per component, averaged
    (over the windows of ``weights`` ``(..., W)`` when given)."""
    x = jnp.abs(r) / delta
    per = jnp.mean(jnp.where(x < 1.0, 0.5 * x * x, x - 0.5), -1)
    return delta * delta * _mean(per, weights)


def rotation_covariance(Phi, Q, bias_sigma, reference_sigma):
    """``S = P_θθ + 2 σ_ref² I``: the covariance of the rotation residual of windows with
    transition ``Phi`` and noise ``Q`` (``(..., 6, 6)``), from ``P0 = diag(0, σ_b² I)``."""
    B = Phi[..., 0:3, 3:6]  # ∂δθ_end/∂δb_g
    P = Q[..., 0:3, 0:3] + bias_sigma**2 * small_matmul(B, jnp.swapaxes(B, -1, -2))
    eye = jnp.eye(3, dtype=P.dtype)
    return P + 2.0 * reference_sigma**2 * eye


def gaussian_nll(r, S, weights=None):
    """``½ rᵀ S⁻¹ r + ½ log det S`` averaged over the windows (3-dim residuals; over those
    of ``weights`` ``(..., W)`` when given)."""
    L = jnp.linalg.cholesky(S)
    z = jax.scipy.linalg.solve_triangular(L, r[..., None], lower=True)[..., 0]
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1)), -1)
    return _mean(0.5 * jnp.sum(z * z, -1) + 0.5 * logdet, weights)


def nees(r, S):
    """``rᵀ S⁻¹ r`` per window (3 on average when consistent)."""
    L = jnp.linalg.cholesky(S)
    z = jax.scipy.linalg.solve_triangular(L, r[..., None], lower=True)[..., 0]
    return jnp.sum(z * z, -1)


def check_horizons(name: str, horizons) -> tuple:
    """``horizons`` (named ``name`` in the error) as a tuple of whole numbers of samples,
    each twice the one before: the windows of one horizon are the pairs of the one before's
    (:func:`compose_pairs`)."""
    try:
        h = tuple(horizons)
    except TypeError:
        raise ValueError(f"{name} must be window lengths in samples, got {horizons!r}") from None
    h = tuple(check_int(f"{name}[{i}]", x, 1) for i, x in enumerate(h))
    if not h or any(b != 2 * a for a, b in zip(h, h[1:])):
        raise ValueError(f"{name} must each be twice the one before, got {h}")
    return h


def _check_truth(name: str, x, T: int, width: int, dtype):
    """``x``: the ground truth ``(..., T + 1, width)`` at the ``T`` samples and after the
    last step, finite (unit quaternions for ``width`` 4), as ``dtype``."""
    x = to_dtype(name, x, dtype)
    if x.ndim < 2 or x.shape[-2:] != (T + 1, width):
        raise ValueError(
            f"{name} must have shape (..., T + 1, {width}) = (..., {T + 1}, {width}): the "
            f"truth at the T = {T} samples and after the last step, got {tuple(x.shape)}"
        )
    check_finite(name, x, "pass finite ground truth")
    if width == 4:
        check_unit_norm(name, x, dtype)
    return x


def _check_corrected(corrected) -> None:
    if not hasattr(corrected, "gyro_density"):
        raise ValueError(
            "corrected must be the model's output (jaximu.learning.Corrected), got "
            f"{type(corrected).__name__}"
        )


def _check_step(dt, dtype):
    """``dt``: the sampling interval, one positive finite number (traced values pass)."""
    d = check_sign("dt", dt, dtype, strict=True, unit="s", fix="pass the sampling interval")
    if d.ndim:
        raise ValueError(f"dt must be one sampling interval [s], got shape {tuple(d.shape)}")
    return d


def _check_horizons(horizons, T: int, skip: int) -> tuple:
    """:func:`check_horizons`, and the longest with at least one window in ``T`` samples
    after ``skip``."""
    h = check_horizons("horizons", horizons)
    skip = check_int("skip", skip, 0)
    H, s = h[-1], -(-skip // 2 ** (len(h) - 1))
    if T // H - s < 1:
        raise ValueError(
            f"horizons: no window of {H} samples fits in {T} samples (after skipping {skip} "
            f"of {h[0]}); give shorter horizons or more samples"
        )
    return h


def increment_terms(
    corrected,
    q_true,
    dt,
    horizons=(16, 32),
    *,
    with_noise=True,
    random_walk=0.0,
    skip: int = 0,
    reference=None,
):
    """For each of ``horizons`` in turn (a generator): ``(r, Phi, Q, m)``, the rotation
    residuals ``(..., W, 3)`` of the windows of that many samples, with ``with_noise`` their
    transitions and noise ``(..., W, 6, 6)`` (None otherwise), and ``m`` ``(..., W)`` whether
    each window has a reference at both ends (None without ``reference``): what
    :func:`increment_loss` and the uncertainty's fit
    (:func:`jaximu.learning.uncertainty.fit_reference_sigma`) read. Arguments as
    :func:`increment_loss`'s."""
    _check_corrected(corrected)
    T = corrected.gyro.shape[-2]
    horizons = _check_horizons(horizons, T, skip)
    q_true = _check_truth("q_true", q_true, T, 4, corrected.gyro.dtype)
    dt = _check_step(dt, corrected.gyro.dtype)
    w = windows(
        corrected.gyro,
        corrected.accel,
        dt,
        horizons[0],
        corrected.gyro_density if with_noise else None,
        random_walk,
    )
    for i, H in enumerate(horizons):
        if i:
            w = compose_pairs(w)
        dq_true = true_increments(q_true, H)
        W = min(dq_true.shape[-2], w.delta_q.shape[-2])
        s = -(-skip // (2**i))  # first windows left out
        r = rotation_residual(dq_true[..., s:W, :], w.delta_q[..., s:W, :])
        m = None if reference is None else window_references(reference, H)[..., s:W]
        if with_noise:
            assert w.Phi is not None and w.Q is not None  # formed when a density is given
            yield r, w.Phi[..., s:W, :, :], w.Q[..., s:W, :, :], m
        else:
            yield r, None, None, m


def increment_loss(
    corrected,
    q_true,
    dt,
    horizons=(16, 32),
    *,
    huber_delta=0.005,
    weight=1e6,
    bias_sigma=None,
    reference_sigma=None,
    random_walk=0.0,
    skip: int = 0,
    reference=None,
):
    """Brossard's loss over ``horizons`` (each twice the previous) plus the NLL.

    Args:
        corrected: :class:`jaximu.learning.model.Corrected` ``(..., T, 3)``.
        q_true: ``(..., T + 1, 4)`` true attitude at the samples and after the last step.
        horizons: window lengths [samples], each twice the one before (``(16, 32)``).
        skip: windows of the first horizon to leave out at the start (the network's warm-up).
        reference: ``(..., T + 1)`` booleans, whether the ground truth has a reference at
            each sample (:attr:`jaximu.learning.Sequence.reference`), or None (everywhere):
            a window without one at both ends is left out of both terms.

    Returns:
        ``(loss, nll)``: the Huber loss (horizon ``h`` weighted ``1/2^i``) and the
        likelihood term (``0`` when ``bias_sigma`` is ``None``).
    """
    _check_corrected(corrected)
    with_noise = bias_sigma is not None
    loss = jnp.zeros((), corrected.gyro.dtype)
    nll = jnp.zeros((), corrected.gyro.dtype)
    terms = increment_terms(
        corrected,
        q_true,
        dt,
        horizons,
        with_noise=with_noise,
        random_walk=random_walk,
        skip=skip,
        reference=reference,
    )
    for i, (r, Phi, Q, m) in enumerate(terms):
        loss = loss + weight * huber(r, huber_delta, m) / 2**i
        if with_noise:
            S = rotation_covariance(Phi, Q, bias_sigma, reference_sigma)
            nll = nll + gaussian_nll(jax.lax.stop_gradient(r), S, m)
    return loss, nll


def velocity_residuals(gyro, accel, q_true, v_true, dt, H: int, gravity=9.81):
    """``(..., W, 3)`` velocity-increment errors [m/s] of windows of ``H`` samples, in W:
    ``R_i Δv̂_ij + g_W Δt − (v_j − v_i)`` with the true ``R_i`` and velocities (AirIMU's
    setting), the increments preintegrated by :func:`jaximu.preintegrate`.

    Args:
        gyro, accel: ``(..., T, 3)`` corrected samples; q_true, v_true: ``(..., T + 1, ·)``
            true attitude and velocity at the samples and after the last step.
    """
    H = check_int("H", H, 1)
    T = jnp.shape(gyro)[-2]
    dtype = jnp.result_type(gyro)
    q_true = _check_truth("q_true", q_true, T, 4, dtype)
    v_true = _check_truth("v_true", v_true, T, 3, dtype)
    dt = _check_step(dt, dtype)
    if H > T:
        raise ValueError(f"H = {H}: no window of {H} samples fits in the {T} samples; pass H ≤ {T}")
    w = windows(gyro, accel, dt, H)
    W = w.delta_v.shape[-2]
    q0 = q_true[..., 0 : W * H : H, :]
    v = v_true[..., 0 : W * H + 1 : H, :]
    g = jnp.asarray([0.0, 0.0, -gravity], gyro.dtype)
    return so3.quat_rotate(q0, w.delta_v) + g * (H * dt) - (v[..., 1:, :] - v[..., :-1, :])
