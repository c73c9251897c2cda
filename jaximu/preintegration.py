"""Preintegration of IMU samples between two keyframes (Forster et al.; GTSAM; VINS-Mono).

Between keyframes i and j the samples are integrated once, in the body frame ``B_i`` of the
first keyframe and without gravity, at a linearisation bias ``b̂``:

    ΔR_ij = Π Exp(ω_k dt_k),   Δv_ij = Σ ΔR_ik f_k dt_k,   Δp_ij = Σ (Δv_ik dt_k + ½ ΔR_ik f_k dt_k²)

(``"euler"``, Forster's on-manifold scheme = GTSAM's ``ManifoldPreintegration``), or with
VINS-Mono's midpoint rule (``"midpoint"``, its ``IntegrationBase::midPointIntegration``
reproduced exactly: first-order quaternion update, its linearisation ``F`` and its 18-dim
noise model ``V``). When an optimiser moves the bias, the deltas are corrected to first
order with the bias Jacobians instead of re-integrating (:func:`correct`).

The error of a :class:`Preintegrated` is ``[δθ, δp, δv, δb_g, δb_a]`` (our error-state
order): ``ΔR = ΔR̂ Exp(δθ)`` and additive ``δp``, ``δv`` in frame ``B_i`` (VINS-Mono's
convention). ``transition`` is the accumulated ``Φ_ij`` of that error (VINS-Mono's
``jacobian``); its bias columns are the bias Jacobians. ``cov15`` includes the bias random
walk (GTSAM's combined factor, VINS-Mono's covariance); ``cov`` is the 9×9 covariance of
``[δθ, δp, δv]`` from the white noise alone (GTSAM's ``preintMeasCov``).

GTSAM expresses ``δp``, ``δv`` in the frame at j (its NavState chart ``p ⊞ ξ = p + R ξ``):
``Preintegrated.covariance(chart="gtsam")`` returns ``T cov Tᵀ`` with
``T = blockdiag(I, ΔRᵀ, ΔRᵀ)``.

Time is parallel too: a one-step transition ``(Φ_k, Q_k)`` composes associatively,
``(Φ, Q)_ac = (Φ_bc Φ_ab, Φ_bc Q_ab Φ_bcᵀ + Q_bc)``, and once the rotations ``ΔR_ik`` are
known (an associative scan of quaternion products) every increment is expressed in frame
``B_i`` and sums are prefix sums. ``method="parallel"`` therefore uses
``lax.associative_scan`` (O(log T) depth) and equals ``method="sequential"`` to rounding,
for both schemes, and can return every prefix ``i→k``.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu import _blocks as blk
from jaximu import _dispatch as dispatch
from jaximu import _fast_preint
from jaximu import _validation as val
from jaximu import sensor
from jaximu import so3
from jaximu import world
from jaximu._batching import ArgSpec, leading_axes
from jaximu._blocks import Blocks, mm
from jaximu._vec import V3
from jaximu.errorstate import blocks_analytic
from jaximu.integrators import compose_deltas, get_scheme
from jaximu.noise import ImuNoise
from jaximu.state import ImuBias, NavState

__all__ = [
    "Preintegrated",
    "preintegrate",
    "correct",
    "compose",
    "predict",
    "residual",
    "whitened_residual",
    "needs_reintegration",
    "bias_jacobians_autodiff",
    "REINTEGRATION_THRESHOLD",
    "SCHEMES",
]

SCHEMES = ("euler", "midpoint")
METHODS = ("auto", "sequential", "parallel")
REINTEGRATION_THRESHOLD = {"gyro": 0.01, "accel": 0.10}
"""Bias changes [rad/s, m/s²] past which VINS-Mono re-integrates instead of correcting."""

@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Preintegrated:
    """Preintegrated IMU measurement between keyframes i and j (frame ``B_i``, no gravity).

    Fields may carry leading batch axes (and, for prefixes, a time axis before the last
    one(s)).

    Attributes:
        delta_t: ``(...,)`` Δt_ij [s].
        delta_q: ``(..., 4)`` ΔR_ij as a unit quaternion ``[w, x, y, z]``.
        delta_v: ``(..., 3)`` Δv_ij [m/s].
        delta_p: ``(..., 3)`` Δp_ij [m].
        transition: ``(..., 15, 15)`` Φ_ij of the error ``[δθ, δp, δv, δb_g, δb_a]``.
        cov15: ``(..., 15, 15)`` covariance with the bias random walk.
        cov: ``(..., 9, 9)`` covariance of ``[δθ, δp, δv]`` from the white noise.
        bias_hat: the linearisation bias.
    """

    delta_t: jax.Array
    delta_q: jax.Array
    delta_v: jax.Array
    delta_p: jax.Array
    transition: jax.Array
    cov15: jax.Array
    cov: jax.Array
    bias_hat: ImuBias

    @property
    def delta_R(self):
        """``(..., 3, 3)`` ΔR_ij."""
        return so3.quat_to_matrix(self.delta_q)

    @property
    def dR_dbg(self):
        """``∂ΔR/∂b_g`` (``ΔR(b) ≈ ΔR Exp(dR_dbg δb_g)``), ``(..., 3, 3)``."""
        return self.transition[..., 0:3, 9:12]

    @property
    def dp_dbg(self):
        return self.transition[..., 3:6, 9:12]

    @property
    def dp_dba(self):
        return self.transition[..., 3:6, 12:15]

    @property
    def dv_dbg(self):
        return self.transition[..., 6:9, 9:12]

    @property
    def dv_dba(self):
        return self.transition[..., 6:9, 12:15]

    def covariance(self, chart: str = "additive", combined: bool = False):
        """The covariance in a chart: ``"additive"`` (ours, VINS-Mono) or ``"gtsam"``.

        GTSAM's ``preintMeasCov`` has δp, δv in the frame at j: ``T P Tᵀ`` with
        ``T = blockdiag(I, ΔRᵀ, ΔRᵀ)``. For ``combined`` (15×15) GTSAM orders the biases
        ``[b_a, b_g]`` and differentiates with respect to the measurements (``-∂/∂b``), so
        its bias blocks are reordered and their cross terms change sign:
        ``T = blockdiag(I, ΔRᵀ, ΔRᵀ, [[0, -I], [-I, 0]])``.
        """
        P = self.cov15 if val.check_bool("combined", combined) else self.cov
        if chart == "additive":
            return P
        if chart != "gtsam":
            raise ValueError(f"unknown chart {chart!r}; choose 'additive' or 'gtsam'")
        Rt = jnp.swapaxes(self.delta_R, -1, -2)
        n = P.shape[-1]
        eye = jnp.eye(3, dtype=P.dtype)
        T = jnp.zeros(Rt.shape[:-2] + (n, n), P.dtype)
        T = T.at[..., 0:3, 0:3].set(eye).at[..., 3:6, 3:6].set(Rt).at[..., 6:9, 6:9].set(Rt)
        if n == 15:
            T = T.at[..., 9:12, 12:15].set(-eye).at[..., 12:15, 9:12].set(-eye)
        return T @ P @ jnp.swapaxes(T, -1, -2)


# --------------------------------------------------------------------------- one step


class _Step(NamedTuple):
    dq: jax.Array  # (..., 4) rotation increment (unnormalised for VINS's midpoint)
    acc: jax.Array  # (..., 3) acceleration in frame B_i used for this step
    F: Blocks
    Q15: dict
    Q9: dict


_UPPER9 = [(i, j) for i in range(3) for j in range(i, 3)]


def _fill(Q, keys, like):
    """All ``keys`` present (zero blocks where missing), so scans see one structure."""
    z = jnp.zeros(like.shape[:-1] + (3, 3), like.dtype)
    return {k: z if Q.get(k) is None else jnp.broadcast_to(Q[k], z.shape) for k in keys}


def _zeros_like_blocks(b: Blocks):
    z = jnp.zeros_like(b.A)
    return Blocks(*(z if x is None else x for x in b[:-1]), b.dt)


def _euler_step(dR, w0, a0, h, b_g, b_a, var, lever=None):
    """Forster / GTSAM Manifold: zero-order hold on sample k. The gyro noise enters as the
    gyro bias does (``F``'s b_g column: with a ``lever`` arm it reaches p and v too, as in
    GTSAM's ``D_correctedAcc_measuredOmega``)."""
    omega, f = w0 - b_g, a0 - b_a
    R0 = so3.quat_to_matrix(dR)
    F = blocks_analytic("euler", R0, omega, f, omega, f, h, lever)
    sg, sa, sbg, sba = var
    Q9 = blk.noise_blocks([{0: F.B, 1: F.Dp, 2: F.Dv}, {1: F.Ep, 2: F.Ev}], [sg, sa])
    return so3.exp(h[..., None] * omega), so3.quat_rotate(dR, f), F, Q9, (sbg, sba)


def _vins_midpoint_step(dR, w0, a0, w1, a1, h, b_g, b_a, var, lever=None):
    """VINS-Mono's ``midPointIntegration``, rearranged to our error order [θ, p, v, b_g, b_a].

    Like VINS-Mono, the second acceleration and ``F`` use the *unnormalised* product
    ``ΔR_k ⊗ [1, ω̄dt/2]`` (through Eigen's rotation formula, identical to
    :func:`so3.quat_rotate`), and ``F`` is VINS-Mono's first-order linearisation.
    Its noise is 18-dim ``[n_a0, n_g0, n_a1, n_g1, n_ba, n_bg]`` with variances
    ``acc_n² = 2σ_a²/dt``, ``gyr_n² = 2σ_g²/dt``, ``acc_w² = σ_ba²/dt``, ``gyr_w² = σ_bg²/dt``:
    the mapping that gives the continuous densities their meaning (``σ_g² dt`` on δθ per
    step, etc.). With a ``lever`` arm (samples moved from a sensor, :mod:`jaximu.sensor`)
    ``f_i`` carries ``-ω_i×(ω_i×r)``: the gyro bias and noise of sample i also move it, by
    ``K_i`` (:func:`jaximu.sensor.centripetal_jacobian`).
    """
    omega = 0.5 * (w0 + w1) - b_g
    f0, f1 = a0 - b_a, a1 - b_a
    hv = h[..., None]
    dq = jnp.concatenate([jnp.ones_like(h)[..., None], 0.5 * hv * omega], axis=-1)
    q1 = so3.quat_mul(dR, dq)
    R0, R1 = so3.quat_to_matrix(dR), so3.quat_to_matrix(q1)
    acc = 0.5 * (so3.quat_rotate(dR, f0) + so3.quat_rotate(q1, f1))
    eye = jnp.eye(3, dtype=omega.dtype)
    h1, h2, h3 = h[..., None, None], (h * h)[..., None, None], (h * h * h)[..., None, None]
    A = eye - so3.skew(omega) * h1
    R0a0, R1a1 = mm(R0, so3.skew(f0)), mm(R1, so3.skew(f1))
    R1a1A = mm(R1a1, A)
    F = Blocks(
        A=A,
        B=-eye * h1,
        Cp=-0.25 * R0a0 * h2 - 0.25 * R1a1A * h2,
        Cv=-0.5 * R0a0 * h1 - 0.5 * R1a1A * h1,
        Dp=0.25 * R1a1 * h3,
        Dv=0.5 * R1a1 * h2,
        Ep=-0.25 * (R0 + R1) * h2,
        Ev=-0.5 * (R0 + R1) * h1,
        dt=h,
    )
    sg, sa, sbg, sba = var
    Vg = {0: 0.5 * eye * h1, 1: -0.125 * R1a1 * h3, 2: -0.25 * R1a1 * h2}
    Va0 = {1: 0.25 * R0 * h2, 2: 0.5 * R0 * h1}  # ∂(p, v)/∂f0; f1's: R1 for R0
    Va1 = {1: 0.25 * R1 * h2, 2: 0.5 * R1 * h1}
    Vg0 = Vg1 = Vg
    if lever is not None:
        r = V3.of(lever)
        RK0 = mm(R0, sensor.centripetal_jacobian(V3.of(w0 - b_g), r, blk.ARRAYS))
        RK1 = mm(R1, sensor.centripetal_jacobian(V3.of(w1 - b_g), r, blk.ARRAYS))
        F = F._replace(Dp=F.Dp + 0.25 * (RK0 + RK1) * h2, Dv=F.Dv + 0.5 * (RK0 + RK1) * h1)
        Vg0 = {0: Vg[0], 1: Vg[1] - 0.25 * RK0 * h2, 2: Vg[2] - 0.5 * RK0 * h1}
        Vg1 = {0: Vg[0], 1: Vg[1] - 0.25 * RK1 * h2, 2: Vg[2] - 0.5 * RK1 * h1}
    Q9 = blk.noise_blocks([Va0, Vg0, Va1, Vg1], [2 * sa, 2 * sg, 2 * sa, 2 * sg])
    return dq, acc, F, Q9, (sbg, sba)


def _euler_noise(n, w0, a0, w1, a1):
    """Step noise ``[n_g, n_a, n_wg, n_wa]`` (12) as it enters the Euler step."""
    return w0 + n[..., 0:3], a0 + n[..., 3:6], w1, a1, n[..., 6:9], n[..., 9:12]


def _vins_noise(n, w0, a0, w1, a1):
    """VINS-Mono's ``[n_a0, n_g0, n_a1, n_g1, n_ba, n_bg]`` (18)."""
    return (w0 + n[..., 3:6], a0 + n[..., 0:3], w1 + n[..., 9:12], a1 + n[..., 6:9],
            n[..., 15:18], n[..., 12:15])


def _vins_variances(v):
    """Discrete variances ``[σ_g², σ_a², σ_bg², σ_ba²]/dt`` → VINS-Mono's 18 (see
    :func:`_vins_midpoint_step`)."""
    sg, sa, sbg, sba = jnp.split(v, 4, axis=-1)
    return jnp.concatenate([2 * sa, 2 * sg, 2 * sa, 2 * sg, sba, sbg], -1)


@dataclasses.dataclass(frozen=True)
class PreintegrationStep:
    """What a scheme brings to preintegration (:attr:`jaximu.integrators.Scheme.preintegration`):

    * ``step(dR, w0, a0, w1, a1, h, b_g, b_a, var, lever) -> (dq, acc, F, Q9, (σ_bg², σ_ba²))``:
      the generic step on ``(..., 3)`` arrays, with closed-form ``F`` and white-noise blocks
      (``lever``: ``None``, or the lever arm of samples moved from a sensor,
      :mod:`jaximu.sensor`);
    * ``noise_dim``, ``perturb(n, w0, a0, w1, a1)`` and ``variances(σ²/dt)``: how its step
      noise enters, for the autodiff Jacobians (:func:`_step_autodiff`);
    * ``kernel``: its structure-of-arrays kernel (:mod:`jaximu._fast_preint`).
    """

    name: str
    uses_next_sample: bool
    step: object
    noise_dim: int
    perturb: object
    variances: object
    kernel: object


PREINTEGRATION_STEPS = {
    # Forster / GTSAM Manifold: the propagation Euler step from the identity, without gravity
    "euler": PreintegrationStep("euler", False,
                                lambda dR, w0, a0, w1, a1, h, *r: _euler_step(dR, w0, a0, h, *r),
                                12, _euler_noise, lambda v: v, _fast_preint.preintegrate_euler),
    # VINS-Mono's midpoint (first-order quaternion, its F and 18-dim noise), kept exactly so
    # that results agree with VINS-Mono; the propagation midpoint uses the exact exponential
    "midpoint": PreintegrationStep("midpoint", True, _vins_midpoint_step, 18, _vins_noise,
                                   _vins_variances, _fast_preint.preintegrate_midpoint),
}


def _step(scheme, dR, w0, a0, w1, a1, h, b_g, b_a, noise, lever=None) -> _Step:
    """One step of ``scheme`` at the preintegrated rotation ``dR`` (``(..., 4)``, unit)."""
    dtype = w0.dtype
    if noise is None:
        var = [jnp.zeros(h.shape + (3,), dtype)] * 4
    else:
        var = jnp.split(noise.discrete_variances(h, dtype), 4, axis=-1)  # σ²/dt each
    dq, acc, F, Q9, (sbg, sba) = get_scheme(scheme).preintegration.step(
        dR, w0, a0, w1, a1, h, b_g, b_a, var, lever)
    eye = jnp.eye(3, dtype=dtype)
    h2 = (h * h)[..., None, None]
    Q15 = dict(Q9)
    Q15[(3, 3)] = h2 * (sbg[..., :, None] * eye)
    Q15[(4, 4)] = h2 * (sba[..., :, None] * eye)
    return _Step(dq, acc, _zeros_like_blocks(F), _fill(Q15, blk.UPPER, dq), _fill(Q9, _UPPER9, dq))


def _step_autodiff(scheme, dR, w0, a0, w1, a1, h, b_g, b_a, noise, lever=None) -> _Step:
    """``F`` and the noise Jacobians by ``jax.jacfwd`` of the step's mean (exact derivatives).
    With a ``lever`` arm the specific force carries ``-ω×(ω×r)`` of the perturbed rate
    (:mod:`jaximu.sensor`), so gyro bias and noise reach it."""
    dtype = w0.dtype
    pre = get_scheme(scheme).preintegration
    nominal = _step(scheme, dR, w0, a0, w1, a1, h, b_g, b_a, None)

    def mean(delta, n):
        """Next (ΔR, Δp, Δv, b) from the perturbed current ones, relative to Δp = Δv = 0."""
        dRp = so3.quat_mul(dR, so3.exp(delta[..., 0:3]))
        bg, ba = b_g + delta[..., 9:12], b_a + delta[..., 12:15]
        w0n, a0n, w1n, a1n, nbg, nba = pre.perturb(n, w0, a0, w1, a1)
        if lever is not None:  # the samples' -ω×(ω×r), moved with the perturbed rate
            a0n = sensor.moved_specific_force(a0n, w0 - b_g, w0n - bg, lever)
            a1n = sensor.moved_specific_force(a1n, w1 - b_g, w1n - bg, lever)
        s = _step(scheme, dRp, w0n, a0n, w1n, a1n, h, bg, ba, None)
        dq_next = so3.quat_normalize(so3.quat_mul(dRp, s.dq))
        hv = h[..., None]
        dtheta = so3.log(so3.quat_mul(so3.quat_conj(
            so3.quat_normalize(so3.quat_mul(dR, nominal.dq))), dq_next))
        p = delta[..., 3:6] + delta[..., 6:9] * hv + 0.5 * s.acc * hv * hv
        v = delta[..., 6:9] + s.acc * hv
        return jnp.concatenate([dtheta, p - 0.5 * nominal.acc * hv * hv, v - nominal.acc * hv,
                                delta[..., 9:15] + jnp.concatenate([nbg, nba], -1) * hv], -1)

    n_noise = pre.noise_dim
    zero15, zero_n = jnp.zeros(15, dtype), jnp.zeros(n_noise, dtype)
    Phi = jax.jacfwd(lambda d: mean(d, zero_n))(zero15)
    G = jax.jacfwd(lambda n: mean(zero15, n))(zero_n)
    if noise is None:
        s = jnp.zeros(h.shape + (n_noise,), dtype)
    else:
        s = pre.variances(noise.discrete_variances(h, dtype))  # from [σ_g², σ_a², σ_bg², σ_ba²]/dt
    walk = n_noise - 6
    Q15 = blk.dense_to_blocks((G * s[..., None, :]) @ jnp.swapaxes(G, -1, -2))
    G9 = G[..., :9, :walk]
    Q9d = (G9 * s[..., None, :walk]) @ jnp.swapaxes(G9, -1, -2)
    Q9 = {(i, j): Q9d[..., 3 * i:3 * i + 3, 3 * j:3 * j + 3] for i, j in _UPPER9}
    return _Step(nominal.dq, nominal.acc, blk.phi_from_dense(Phi), Q15=Q15, Q9=Q9)


# --------------------------------------------------------------------------- accumulation


class _Acc(NamedTuple):
    """What composes associatively: the transition and the two noise covariances."""

    Phi: Blocks
    Q15: dict
    Q9: dict


def _combine(earlier: _Acc, later: _Acc) -> _Acc:
    Q15 = blk.symmetrize_diagonal(blk.add_blocks(blk.phi_p_phit(earlier.Q15, later.Phi),
                                                 later.Q15))
    Q9 = blk.symmetrize_diagonal(blk.add_blocks(blk.phi_p_phit(earlier.Q9, later.Phi), later.Q9))
    Q9 = {k: Q9[k] for k in earlier.Q9}  # the bias blocks of Q9 stay zero
    return _Acc(blk.phi_compose(later.Phi, earlier.Phi), Q15, Q9)


def _identity_acc(batch, dtype) -> _Acc:
    eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), tuple(batch) + (3, 3))
    z = jnp.zeros(tuple(batch) + (3, 3), dtype)
    Phi = Blocks(eye, z, z, z, z, z, z, z, jnp.zeros(tuple(batch), dtype))
    return _Acc(Phi, {k: z for k in blk.UPPER}, {k: z for k in _UPPER9})


def _finish(delta_t, dq, dv, dp, acc: _Acc, bias: ImuBias) -> Preintegrated:
    Q9 = {k: acc.Q9.get(k) for k in blk.UPPER}
    cov9 = blk.blocks_to_dense(Q9)[..., :9, :9]
    batch = dq.shape[:-1]
    return Preintegrated(
        delta_t=delta_t, delta_q=so3.quat_normalize(dq), delta_v=dv, delta_p=dp,
        transition=blk.phi_to_dense(acc.Phi), cov15=blk.blocks_to_dense(acc.Q15), cov=cov9,
        bias_hat=ImuBias(jnp.broadcast_to(bias.b_g, batch + (3,)),
                         jnp.broadcast_to(bias.b_a, batch + (3,))))


def _pairs(gyro, accel, dt, scheme):
    """Time-major samples k and k+1 and steps; ``dt`` of length T (hold the last sample) or
    T-1 (samples are the ends of the intervals)."""
    T = gyro.shape[-2]
    n = dt.shape[-1] if dt.ndim else T
    w = jnp.moveaxis(gyro, -2, 0)
    a = jnp.moveaxis(accel, -2, 0)
    h = jnp.moveaxis(dt, -1, 0) if dt.ndim else jnp.broadcast_to(dt, (n,))
    if n == T:
        w1 = jnp.concatenate([w[1:], w[-1:]], 0)
        a1 = jnp.concatenate([a[1:], a[-1:]], 0)
    else:
        w1, a1 = w[1:], a[1:]
    return w[:n], a[:n], w1, a1, h


def _chunk_scan(scheme, step_fn, b_g, b_a, noise, xs, batch, dtype, prefixes, blocks=True,
                lever=None):
    """``lax.scan`` of the preintegration recursion over the leading (time) axis of ``xs``.

    ``xs = (dR, w0, a0, w1, a1, h, mask)``: with ``dR`` None the rotation is carried (the
    sequential recursion); otherwise it is given per step (already known in frame ``B_i``).
    Steps whose ``mask`` is False (padding) are identities. With ``blocks=False`` only the
    mean is carried (the accumulated blocks are ``None``): a graph that is differentiated
    then never traces the Jacobian and covariance blocks at all.
    """
    dR_given, w0, a0, w1, a1, h, mask = xs
    q_id = so3.quat_identity(batch, dtype)
    ident = _identity_acc(batch, dtype) if blocks else None

    def body(carry, x):
        dq, dv, dp, t, acc = carry
        dR, w0k, a0k, w1k, a1k, hk, mk = x
        if mk is not None:
            hk_safe = jnp.where(mk, hk, jnp.ones_like(hk))
        else:
            hk_safe = hk
        s = step_fn(scheme, dq if dR is None else dR, w0k, a0k, w1k, a1k, hk_safe, b_g, b_a,
                    noise, lever)
        step = _Acc(s.F, s.Q15, s.Q9) if blocks else None
        a_k = s.acc
        if mk is not None:
            step = jax.tree_util.tree_map(
                lambda x_, i_: jnp.where(mk.reshape(mk.shape + (1,) * (x_.ndim - mk.ndim)), x_, i_),
                step, ident if blocks else None)
            a_k = jnp.where(mk[..., None], a_k, 0.0)
            hk = jnp.where(mk, hk, 0.0)
        hv = hk[..., None]
        dp = dp + dv * hv + 0.5 * a_k * hv * hv
        dv = dv + a_k * hv
        if dR is None:
            dq = so3.quat_normalize(so3.quat_mul(dq, s.dq))
        acc = _combine(acc, step) if blocks else None
        carry = (dq, dv, dp, t + hk, acc)
        return carry, (carry if prefixes else None)

    z = jnp.zeros(tuple(batch) + (3,), dtype)
    carry0 = (q_id, z, z, jnp.zeros(tuple(batch), dtype), ident)
    return jax.lax.scan(body, carry0, (dR_given, w0, a0, w1, a1, h, mask))


class _Dense(NamedTuple):
    """A chunk summary in frame ``B_i``, dense, for the associative scan across chunks."""

    t: jax.Array
    dv: jax.Array
    dp: jax.Array
    Phi: jax.Array
    Q15: jax.Array
    Q9: jax.Array


def _to_dense(t, dv, dp, acc: _Acc) -> _Dense:
    Q9 = {k: acc.Q9.get(k) for k in blk.UPPER}
    return _Dense(t, dv, dp, blk.phi_to_dense(acc.Phi), blk.blocks_to_dense(acc.Q15),
                  blk.blocks_to_dense(Q9)[..., :9, :9])


def _combine_dense(e1: _Dense, e2: _Dense) -> _Dense:
    """``e2`` after ``e1``; all quantities in the same frame ``B_i``, so no rotation."""
    def sandwich(F, Q):
        return F @ Q @ jnp.swapaxes(F, -1, -2)

    return _Dense(e1.t + e2.t, e1.dv + e2.dv, e1.dp + e2.dp + e1.dv * e2.t[..., None],
                  e2.Phi @ e1.Phi, blk.sym(sandwich(e2.Phi, e1.Q15) + e2.Q15),
                  blk.sym(sandwich(e2.Phi[..., :9, :9], e1.Q9) + e2.Q9))


def _chunk_length(T: int) -> int:
    """Samples per chunk for the parallel method: at most ~512 chunks side by side."""
    return max(16, -(-T // 512)) if T > 16 else T


def _pim_from_dense(dq, d: _Dense, bias):
    batch = dq.shape[:-1]
    return Preintegrated(
        delta_t=d.t, delta_q=so3.quat_normalize(dq), delta_v=d.dv, delta_p=d.dp,
        transition=d.Phi, cov15=d.Q15, cov=d.Q9,
        bias_hat=ImuBias(jnp.broadcast_to(bias.b_g, batch + (3,)),
                         jnp.broadcast_to(bias.b_a, batch + (3,))))


def _time_major_batch(x, batch, tail):
    """``(T,) + own_batch + tail`` -> ``(T,) + batch + tail`` (batch axes right-aligned)."""
    own = x.ndim - 1 - len(tail)
    x = x.reshape(x.shape[:1] + (1,) * (len(batch) - own) + x.shape[1:])
    return jnp.broadcast_to(x, x.shape[:1] + tuple(batch) + tuple(tail))


def _preintegrate_fast(gyro, accel, dt, bias, noise, batch, method, scheme, lever=None,
                       jacobians="analytic"):
    T = gyro.shape[-2]
    n = dt.shape[-1] if dt.ndim else T  # dt of length T-1: Euler leaves the last sample unused
    dtype = gyro.dtype
    B = int(np.prod(batch, dtype=np.int64))
    flat = lambda x, tail: jnp.broadcast_to(x, tuple(batch) + tail).reshape((B,) + tail)  # noqa: E731
    pre = get_scheme(scheme).preintegration
    if pre.uses_next_sample:  # samples k and k+1 side by side (as _pairs)
        def pair(x):
            x1 = x[..., 1:, :] if n < T else jnp.concatenate([x[..., 1:, :], x[..., -1:, :]], -2)
            return jnp.concatenate([x[..., :n, :], x1], -1)

        gyro, accel = pair(gyro), pair(accel)
    k = gyro.shape[-1]
    gyro_f = flat(gyro[..., :n, :], (n, k))
    accel_f = flat(accel[..., :n, :], (n, k))
    dt_f = jnp.broadcast_to(dt, (n,)) if dt.ndim <= 1 else flat(dt, (n,))
    b_g = bias.b_g if bias.b_g.ndim == 1 else flat(bias.b_g, (3,))
    b_a = bias.b_a if bias.b_a.ndim == 1 else flat(bias.b_a, (3,))
    if noise is None:
        var = jnp.zeros(12, dtype)
    else:
        var = noise.variances(dtype)
        var = var if var.ndim == 1 else flat(var, (12,))
    if lever is not None and lever.ndim > 1:
        lever = flat(lever, (3,))
    C = _fast_preint.num_chunks(B, n, method, dtype)
    # a scalar accelerometer density: the same noise on every axis (the kernel's R D Rᵀ = σ² I)
    iso = noise is None or jnp.ndim(noise.accelerometer_noise_density) == 0
    t, q, dv, dp, Phi, Q15, Q9 = pre.kernel(gyro_f, accel_f, dt_f, b_g, b_a, var, C, lever,
                                            jacobians, iso)
    unflat = lambda x: x.reshape(tuple(batch) + x.shape[1:])  # noqa: E731
    return Preintegrated(
        delta_t=unflat(t), delta_q=unflat(q), delta_v=unflat(dv), delta_p=unflat(dp),
        transition=unflat(Phi), cov15=unflat(Q15), cov=unflat(Q9),
        bias_hat=ImuBias(jnp.broadcast_to(bias.b_g, tuple(batch) + (3,)),
                         jnp.broadcast_to(bias.b_a, tuple(batch) + (3,))))


@functools.partial(jax.jit, static_argnames=("scheme", "method", "jacobians", "prefixes", "fast"))
def _preintegrate(gyro, accel, dt, bias, noise, lever=None, *, scheme, method, jacobians,
                  prefixes, fast=True):
    step_fn = _step if jacobians == "analytic" else _step_autodiff
    nb = lambda x: x.shape[:-1] if x.ndim else ()  # noqa: E731
    batch = tuple(jnp.broadcast_shapes(
        gyro.shape[:-2], accel.shape[:-2], dt.shape[:-1], bias.b_g.shape[:-1],
        bias.b_a.shape[:-1],
        *(nb(jnp.asarray(x)) for x in jax.tree_util.tree_leaves(noise)),
        *(() if lever is None else (lever.shape[:-1],))))
    lanes = int(np.prod(batch, dtype=np.int64))
    method = dispatch.preint_method(method, lanes, gyro.shape[-2], gyro.dtype)
    if dispatch.preintegrate_kernel(scheme, jacobians=jacobians, prefixes=prefixes,
                                    method=method, lanes=lanes, fast=fast,
                                    lever=lever is not None) != dispatch.GENERIC:
        return _preintegrate_fast(gyro, accel, dt, bias, noise, batch, method, scheme, lever,
                                  jacobians)
    w0, a0, w1, a1, h = _pairs(gyro, accel, dt, scheme)
    dtype = w0.dtype
    b_g, b_a = bias.b_g, bias.b_a
    T = h.shape[0]
    h = _time_major_batch(h, batch, ())
    w0, a0, w1, a1 = (_time_major_batch(x, batch, (3,)) for x in (w0, a0, w1, a1))
    if method == "sequential":
        final, out = _chunk_scan(scheme, step_fn, b_g, b_a, noise, (None, w0, a0, w1, a1, h, None),
                                 batch, dtype, prefixes, lever=lever)
        dq, dv, dp, t, acc = out if prefixes else final
        pim = _finish(t, dq, dv, dp, acc, ImuBias(b_g, b_a))
    else:
        # 1. rotations ΔR_ik: an associative scan of the (normalised) increments
        q_id = so3.quat_identity(batch, dtype)
        incr = step_fn(scheme, jnp.broadcast_to(q_id, (T,) + batch + (4,)), w0, a0, w1, a1, h,
                       b_g, b_a, None).dq
        incl = so3.quat_normalize(jax.lax.associative_scan(so3.quat_mul,
                                                           so3.quat_normalize(incr), axis=0))
        dR = jnp.concatenate([q_id[None], incl[:-1]], axis=0)
        # 2. chunks of L steps side by side, each step already in frame B_i
        L = _chunk_length(T)
        C = -(-T // L)
        pad = C * L - T

        def chunked(x, fill=0):  # (T, ...) -> (L, C, ...), time k = c L + l
            if pad:
                x = jnp.concatenate([x, jnp.full((pad,) + x.shape[1:], fill, x.dtype)], 0)
            return jnp.swapaxes(x.reshape((C, L) + x.shape[1:]), 0, 1)

        mask = chunked(jnp.ones((T,) + batch, bool)) if pad else None
        # padded steps are masked out, but their rotations are unit quaternions: the
        # autodiff step normalises dR ⊗ dq, and a zero dR's NaN reached the reverse-mode
        # gradient through the mask's where
        xs = (chunked(dR, q_id),) + tuple(chunked(x) for x in (w0, a0, w1, a1, h)) + (mask,)
        final, out = _chunk_scan(scheme, step_fn, b_g, b_a, noise, xs, (C,) + batch, dtype,
                                 prefixes, lever=lever)
        # 3. an associative scan across the chunk summaries (dense: few, cheap to compile)
        _, dv, dp, t, acc = final
        chunk_prefix = jax.lax.associative_scan(_combine_dense, _to_dense(t, dv, dp, acc), axis=0)
        if prefixes:
            first = _to_dense(jnp.zeros_like(t[:1]), jnp.zeros_like(dv[:1]),
                              jnp.zeros_like(dp[:1]), _identity_acc((1,) + batch, dtype))
            excl = jax.tree_util.tree_map(lambda a_, b_: jnp.concatenate([a_, b_[:-1]], 0),
                                          first, chunk_prefix)
            _, dv_l, dp_l, t_l, acc_l = out  # (L, C, ...)
            inner = _to_dense(t_l, dv_l, dp_l, acc_l)
            whole = _combine_dense(jax.tree_util.tree_map(lambda x: x[None], excl), inner)
            whole = jax.tree_util.tree_map(
                lambda x: jnp.swapaxes(x, 0, 1).reshape((C * L,) + x.shape[2:])[:T], whole)
            pim = _pim_from_dense(incl, whole, ImuBias(b_g, b_a))
        else:
            last = jax.tree_util.tree_map(lambda x: x[-1], chunk_prefix)
            pim = _pim_from_dense(incl[-1], last, ImuBias(b_g, b_a))
    if prefixes:  # time first inside the scan -> time before the last axes
        pim = Preintegrated(
            delta_t=jnp.moveaxis(pim.delta_t, 0, -1),
            delta_q=jnp.moveaxis(pim.delta_q, 0, -2), delta_v=jnp.moveaxis(pim.delta_v, 0, -2),
            delta_p=jnp.moveaxis(pim.delta_p, 0, -2),
            transition=jnp.moveaxis(pim.transition, 0, -3), cov15=jnp.moveaxis(pim.cov15, 0, -3),
            cov=jnp.moveaxis(pim.cov, 0, -3),
            bias_hat=jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, 0, -2), pim.bias_hat))
    return pim


def _steps_of(args, batched):
    return args[0].shape[-2]  # gyro is argument 0


_SAMPLES = ArgSpec(2)
_VEC = ArgSpec(1, lambda args, batched: 3)  # bias fields (..., 3); densities scalar or (..., 3)


def routed_preintegrate(scheme, method, jacobians, prefixes):
    """:func:`_preintegrate` whose ``jax.vmap`` lands on the batched kernels; arguments
    ``(gyro, accel, dt, bias, noise, lever)`` (``noise`` and ``lever`` may be ``None``)."""
    return leading_axes(_preintegrate,
                        (_SAMPLES, _SAMPLES, ArgSpec(1, _steps_of), _VEC, _VEC, _VEC),
                        (("jacobians", jacobians), ("method", method), ("prefixes", prefixes),
                         ("scheme", scheme)))


def _check_bias(bias, dtype):
    if bias is None:
        return ImuBias(jnp.zeros(3, dtype), jnp.zeros(3, dtype))
    if not isinstance(bias, ImuBias):
        raise ValueError(f"bias must be a jaximu.ImuBias, got {type(bias).__name__}")
    out = []
    for name in ("b_g", "b_a"):
        x = val.to_dtype(f"bias.{name}", getattr(bias, name), dtype)
        if x.ndim < 1 or x.shape[-1] != 3:
            raise ValueError(f"bias.{name} must have shape (..., 3), got {tuple(x.shape)}")
        val.check_finite(f"bias.{name}", x)
        out.append(x)
    return ImuBias(*out)


def preintegrate(gyro, accel, dt, bias: ImuBias | None = None, noise: ImuNoise | None = None,
                 scheme: str = "euler", method: str = "auto", *, prefixes: bool = False,
                 jacobians: str = "analytic", body_P_sensor=None,
                 tangential: bool = True) -> Preintegrated:
    """Preintegrate IMU samples between two keyframes.

    Args:
        gyro, accel: ``(..., T, 3)`` raw samples [rad/s], [m/s²] from keyframe i on.
        dt: ``(..., T)`` steps (sample k held over ``dt[k]``; for ``"midpoint"`` the last
            step then holds sample T-1), or ``(..., T-1)`` when the samples are the ends of
            the intervals (VINS-Mono's ``push_back``: step k uses samples k and k+1; Euler
            then leaves the last sample unused); or a scalar (``(T,)`` steps).
        bias: linearisation bias :class:`ImuBias` (default zero).
        noise: :class:`ImuNoise` densities (default none: zero covariances).
        scheme: ``"euler"`` (Forster / GTSAM Manifold) or ``"midpoint"`` (VINS-Mono).
        method: ``"auto"`` (default: the fastest for the shape, chosen by
            :func:`jaximu._dispatch.preint_method`: ``"parallel"`` for few long windows,
            ``"sequential"`` otherwise), ``"sequential"`` (``lax.scan``) or ``"parallel"``
            (time chunks side by side composed associatively, O(log T) depth on the generic
            path); all give the same numbers to rounding.
        prefixes: return every prefix ``i→k`` (fields gain a time axis before their last
            axes) instead of only ``i→j``.
        jacobians: ``"analytic"`` (closed forms; VINS-Mono's own linearisation for the
            midpoint) or ``"autodiff"`` (``jax.jacfwd`` of each step's mean: exact
            derivatives, also for the midpoint).
        body_P_sensor: optional :class:`jaximu.SensorPose`: the IMU's pose in the body frame
            (GTSAM's ``PreintegrationParams.body_P_sensor``). The deltas are then the body's
            (frame ``B_i``); ``bias``, ``bias_hat`` and the bias rows and columns of
            ``transition`` and ``cov15`` are the sensor's, in S (:mod:`jaximu.sensor`; what
            is approximated in the covariance is said there).
        tangential: with ``body_P_sensor``, correct the tangential acceleration ``α×r``
            too; ``False`` reproduces GTSAM (centripetal ``ω×(ω×r)`` only).

    Returns:
        :class:`Preintegrated`.

    Raises:
        ValueError: on bad shapes, values or options (as :func:`jaximu.propagate`), and on
            an eager call whose result is not finite (``dt`` or samples too large, or ``dt``
            so small that the noise ``σ²/dt`` overflows the dtype).
    """
    if scheme not in SCHEMES:
        raise ValueError(f"unknown preintegration scheme {scheme!r}; choose one of {SCHEMES}")
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {METHODS}")
    if jacobians not in ("analytic", "autodiff"):
        raise ValueError(f"unknown jacobians {jacobians!r}; choose 'analytic' or 'autodiff'")
    prefixes = val.check_bool("prefixes", prefixes)
    tangential = val.check_bool("tangential", tangential)
    # the data's dtype; the noise densities and a sensor pose (constants) take it
    dtype = val.float_dtype(gyro, accel, dt, bias)
    gyro, accel, dt, _ = val.check_imu(gyro, accel, dt, dtype, allow_intervals=True)
    bias = _check_bias(bias, dtype)
    if noise is not None:
        noise = val.check_noise(noise, dtype)
    val.batch_shape(gyro.shape[:-2], accel.shape[:-2], dt.shape[:-1], bias.b_g.shape[:-1],
                    bias.b_a.shape[:-1], names=("gyro", "accel", "dt", "bias.b_g", "bias.b_a"),
                    noise=noise)  # the densities' batch axes too, each named
    if body_P_sensor is not None:
        return _preintegrate_sensor(gyro, accel, dt, bias, noise, scheme, method, prefixes,
                                    jacobians, body_P_sensor, tangential)
    pim = routed_preintegrate(scheme, method, jacobians, prefixes)(gyro, accel, dt, bias, noise)
    return val.check_output("preintegrate", pim, "dt or the IMU samples are too large, or dt so "
                            "small that the noise σ²/dt overflows,")


def _preintegrate_sensor(gyro, accel, dt, bias, noise, scheme, method, prefixes, jacobians,
                         body_P_sensor, tangential):
    """:func:`preintegrate` of a sensor at ``body_P_sensor``: the body's samples
    (:func:`jaximu.sensor.to_body`) with body-frame biases, and the result's bias
    quantities back in the sensor frame (``Φ_S = Tᵀ Φ_B T``, ``C_S = Tᵀ C_B T``)."""
    tangential = val.check_bool("tangential", tangential)
    pose = sensor.check_pose(body_P_sensor, gyro.dtype,
                             batch=jnp.broadcast_shapes(gyro.shape[:-2], bias.b_g.shape[:-1]),
                             batch_name="samples and bias")
    gyro_b, accel_b = sensor.to_body(pose, gyro, accel, dt, bias.b_g, tangential=tangential)
    bias_b = ImuBias(sensor.bias_to_body(pose, bias.b_g), sensor.bias_to_body(pose, bias.b_a))
    noise_b = None if noise is None else sensor.noise_to_body(pose, noise)
    pim = routed_preintegrate(scheme, method, jacobians, prefixes)(gyro_b, accel_b, dt, bias_b,
                                                                   noise_b, sensor.lever_of(pose))
    T = sensor.bias_transform(pose)
    if prefixes:
        T = T[..., None, :, :]
    pim = dataclasses.replace(
        pim, transition=sensor.congruence(T, pim.transition, inverse=True),
        cov15=sensor.congruence(T, pim.cov15, inverse=True),
        bias_hat=ImuBias(*(jnp.broadcast_to(b if b.ndim == h.ndim else b[..., None, :], h.shape)
                           for b, h in
                           ((bias.b_g, pim.bias_hat.b_g), (bias.b_a, pim.bias_hat.b_a)))))
    return val.check_output("preintegrate", pim, "dt or the IMU samples are too large, or dt "
                            "so small that the noise σ²/dt overflows,")


# --------------------------------------------------------------------------- use


def _check_pim(pim):
    """Type and finiteness of a :class:`Preintegrated` given to :func:`correct` & co.;
    returns its batch shape."""
    if not isinstance(pim, Preintegrated):
        raise ValueError(f"pim must be a jaximu.Preintegrated, got {type(pim).__name__}")
    for path, x in jax.tree_util.tree_leaves_with_path(pim):
        val.check_finite("pim" + jax.tree_util.keystr(path), x)
    return pim.delta_q.shape[:-1]


def _check_state_arg(name, state):
    """Shapes, finiteness and unit ``q`` of a state given to :func:`predict`/:func:`residual`
    (validation only: the state is used as given)."""
    if not isinstance(state, NavState):
        raise ValueError(f"{name} must be a jaximu.NavState, got {type(state).__name__}")
    try:
        val.check_state(state, val.float_dtype(*jax.tree_util.tree_leaves(state)))
    except ValueError as e:
        raise ValueError(str(e).replace("state", name, 1)) from None
    return state.batch_shape


def _output(fn_name, out):
    return val.check_output(fn_name, out, "the states or the preintegrated deltas are too large")


def _corrected_deltas(pim: Preintegrated, bias: ImuBias):
    """``(ΔR, Δv, Δp)`` corrected to first order from ``pim.bias_hat`` to ``bias``."""
    dbg = bias.b_g - pim.bias_hat.b_g
    dba = bias.b_a - pim.bias_hat.b_a

    def mv(M, x):
        return jnp.einsum("...ij,...j->...i", M, x)

    return (so3.quat_mul(pim.delta_q, so3.exp(mv(pim.dR_dbg, dbg))),
            pim.delta_v + mv(pim.dv_dbg, dbg) + mv(pim.dv_dba, dba),
            pim.delta_p + mv(pim.dp_dbg, dbg) + mv(pim.dp_dba, dba))


def _correct(pim: Preintegrated, bias: ImuBias) -> Preintegrated:
    dq, dv, dp = _corrected_deltas(pim, bias)
    return dataclasses.replace(
        pim, delta_q=dq, delta_v=dv, delta_p=dp,
        bias_hat=ImuBias(jnp.broadcast_to(bias.b_g, pim.bias_hat.b_g.shape),
                         jnp.broadcast_to(bias.b_a, pim.bias_hat.b_a.shape)),
    )


def correct(pim: Preintegrated, bias: ImuBias) -> Preintegrated:
    """First-order bias update of the deltas (no re-integration).

    ``ΔR ← ΔR Exp(J_R δb_g)``, ``Δv ← Δv + J_vg δb_g + J_va δb_a``, ``Δp`` likewise, with
    ``δb = bias - pim.bias_hat``. The result has ``bias_hat = bias`` and keeps the Jacobians
    and covariances (a first-order re-linearisation). Past
    :data:`REINTEGRATION_THRESHOLD` re-integrating is advised (:func:`needs_reintegration`).
    ``bias`` may be shared or batched like ``pim`` (its batch must broadcast to ``pim``'s).
    """
    batch = _check_pim(pim)
    if not isinstance(bias, ImuBias):
        raise ValueError(f"bias must be a jaximu.ImuBias, got {type(bias).__name__}")
    bias = _check_bias(bias, val.float_dtype(bias.b_g, bias.b_a))
    if tuple(val.batch_shape(bias.b_g.shape[:-1], bias.b_a.shape[:-1], batch,
                             names=("bias.b_g", "bias.b_a", "pim"))) != tuple(batch):
        raise ValueError(f"bias has batch shape {bias.b_g.shape[:-1]} / {bias.b_a.shape[:-1]}, "
                         f"which does not broadcast to the preintegrated batch shape {batch}")
    return _output("correct", _correct(pim, bias))


def needs_reintegration(pim: Preintegrated, bias: ImuBias, gyro_threshold: float = 0.01,
                        accel_threshold: float = 0.10):
    """Whether ``bias`` is far enough from ``pim.bias_hat`` that re-integration is advised
    (VINS-Mono: ``|δb_a| > 0.10`` m/s² or ``|δb_g| > 0.01`` rad/s). ``(...,)`` bool.

    ``pim``: a :class:`Preintegrated`; ``bias``: an :class:`ImuBias` whose batch broadcasts
    to ``pim``'s; thresholds ``≥ 0`` and finite [rad/s], [m/s²]. Bad values (a NaN bias,
    which would answer False) raise ``ValueError`` on eager calls.
    """
    batch = _check_pim(pim)
    if not isinstance(bias, ImuBias):
        raise ValueError(f"bias must be a jaximu.ImuBias, got {type(bias).__name__}")
    bias = _check_bias(bias, val.float_dtype(bias.b_g, bias.b_a))
    val.batch_shape(bias.b_g.shape[:-1], bias.b_a.shape[:-1], batch,
                    names=("bias.b_g", "bias.b_a", "pim"))
    for name, x in (("gyro_threshold", gyro_threshold), ("accel_threshold", accel_threshold)):
        if val.is_concrete(x):
            val.check_positive(name, x, allow_zero=True)
    dbg = jnp.linalg.norm(bias.b_g - pim.bias_hat.b_g, axis=-1)
    dba = jnp.linalg.norm(bias.b_a - pim.bias_hat.b_a, axis=-1)
    return (dbg > gyro_threshold) | (dba > accel_threshold)


def compose(pim_ab: Preintegrated, pim_bc: Preintegrated) -> Preintegrated:
    """``pim_ac`` from two consecutive intervals, each preintegrated in its own start frame.

    ``pim_bc`` is first corrected to ``pim_ab``'s linearisation bias (:func:`correct`). Its
    transition and noise are moved to frame ``B_a`` by ``T = blockdiag(I, ΔR_ab, ΔR_ab, I, I)``
    and composed: ``Φ_ac = (T Φ_bc T⁻¹) Φ_ab``, ``Q_ac = (T Φ_bc T⁻¹) Q_ab (·)ᵀ + T Q_bc Tᵀ``.
    Exact (to rounding) for ``"euler"``; for VINS-Mono's midpoint the conjugation is exact
    only to O((ω dt)²), because VINS-Mono rotates with an unnormalised quaternion.

    Both are :class:`Preintegrated` with finite values and batch shapes that broadcast
    (``ValueError`` naming ``pim_ab`` / ``pim_bc`` otherwise).
    """
    batches = []
    for name, p in (("pim_ab", pim_ab), ("pim_bc", pim_bc)):
        try:
            batches.append(_check_pim(p))
        except ValueError as e:
            raise ValueError(str(e).replace("pim", name, 1)) from None
    try:
        batch = jnp.broadcast_shapes(*batches)
    except ValueError:
        raise ValueError(f"pim_ab and pim_bc have batch shapes {tuple(batches[0])} and "
                         f"{tuple(batches[1])}, which do not broadcast") from None

    def widen(p, own):  # a shared measurement against a batch: broadcast it first
        n = len(own)
        return p if tuple(own) == tuple(batch) else jax.tree_util.tree_map(
            lambda x: jnp.broadcast_to(x, tuple(batch) + x.shape[n:]), p)

    pim_ab, pim_bc = widen(pim_ab, batches[0]), widen(pim_bc, batches[1])
    bc = _correct(pim_bc, pim_ab.bias_hat)
    R = pim_ab.delta_R

    def mv(M, x):
        return jnp.einsum("...ij,...j->...i", M, x)

    F = blk.phi_from_dense(bc.transition)
    F = F._replace(Cp=mm(R, F.Cp), Cv=mm(R, F.Cv), Dp=mm(R, F.Dp), Dv=mm(R, F.Dv),
                   Ep=mm(R, F.Ep), Ev=mm(R, F.Ev))
    Phi_ab = blk.phi_from_dense(pim_ab.transition)
    Rb = {0: None, 1: R, 2: R, 3: None, 4: None}

    def ab_blocks(Qd, n):
        if n == 15:
            return blk.dense_to_blocks(Qd)
        return {(i, j): Qd[..., 3 * i:3 * i + 3, 3 * j:3 * j + 3] for i, j in _UPPER9}

    def conj(Qd, n):
        Qb = ab_blocks(Qd, n)
        out = {}
        for (i, j), X in Qb.items():
            X = X if Rb[i] is None else mm(Rb[i], X)
            out[(i, j)] = X if Rb[j] is None else mm(X, blk.t(Rb[j]))
        return out

    acc = _combine(_Acc(Phi_ab, ab_blocks(pim_ab.cov15, 15), ab_blocks(pim_ab.cov, 9)),
                   _Acc(F, conj(bc.cov15, 15), conj(bc.cov, 9)))
    dq, dp, dv, dt = compose_deltas(
        (pim_ab.delta_q, pim_ab.delta_p, pim_ab.delta_v, pim_ab.delta_t),
        (bc.delta_q, bc.delta_p, bc.delta_v, bc.delta_t), lambda x: mv(R, x))
    return _finish(dt, dq, dv, dp, acc, pim_ab.bias_hat)


def _gravity(gravity, dtype):
    return val.gravity_vector(gravity, dtype)


def _world(omega_coriolis, dtype, batch, coriolis_exact, coriolis_second_order):
    """``omega_coriolis`` checked (and its batch against ``batch``), and the two bools."""
    val.check_bool("coriolis_exact", coriolis_exact)
    val.check_bool("coriolis_second_order", coriolis_second_order)
    if omega_coriolis is None:
        return None
    omega = world.check_omega(omega_coriolis, dtype)
    val.batch_shape(batch, omega.shape[:-1], names=("states and pim", "omega_coriolis"))
    return omega


def _coriolis_terms(state_i, pim, omega, second_order):
    """GTSAM ≤ 4.2's ``correctPIM`` increments from the state at i (:mod:`jaximu.world`):
    the world-frame ``(dθ, dp, dv)`` over ``Δt_ij``."""
    return world.coriolis_increments(omega, state_i.p, state_i.v, pim.delta_t, second_order)


def _delta_rotation(state_i, delta_q, dth):
    """GTSAM's classic ``Exp(Log ΔR + R_iᵀ dθ_W)``."""
    return so3.exp(so3.log(delta_q) + so3.quat_rotate(so3.quat_conj(state_i.q), dth))


CORIOLIS_DOC = """
    ``omega_coriolis``: optional ``(3,)`` world rotation rate [rad/s] in W (GTSAM's
    ``omegaCoriolis``, e.g. :func:`jaximu.earth_rate`), with ``coriolis_exact=True``
    (default) the exact rotating-world transition over ``Δt_ij`` (GTSAM ≥ 4.3's prediction,
    Coriolis and centrifugal both; :mod:`jaximu.world`), or with ``coriolis_exact=False``
    GTSAM ≤ 4.2's classic ``correctPIM`` terms, ``R_j = R_i Exp(Log ΔR - Δt R_iᵀ ω)``,
    ``v_j += -2Δt ω×v_i``, ``p_j += -Δt² ω×v_i``, and with ``coriolis_second_order`` the
    centrifugal ``-Δt ω×(ω×p_i)``, ``-½Δt² ω×(ω×p_i)``.
"""


def predict(state_i: NavState, pim: Preintegrated, gravity=9.81, *, omega_coriolis=None,
            coriolis_exact: bool = True, coriolis_second_order: bool = False) -> NavState:
    """The state at keyframe j from the state at i and the preintegrated measurement.

    The deltas are first corrected to ``state_i``'s biases; then ``R_j = R_i ΔR``,
    ``v_j = v_i + g_W Δt + R_i Δv``, ``p_j = p_i + v_i Δt + ½ g_W Δt² + R_i Δp``; the
    biases are carried over.
    {coriolis}"""
    batch = (_check_state_arg("state_i", state_i), _check_pim(pim))
    g = _gravity(gravity, pim.delta_v.dtype)
    batch = val.batch_shape(*batch, g.shape[:-1], names=("state_i", "pim", "gravity"))
    omega = _world(omega_coriolis, pim.delta_v.dtype, batch, coriolis_exact,
                   coriolis_second_order)
    delta_q, delta_v, delta_p = _corrected_deltas(pim, state_i.bias)
    dt = pim.delta_t[..., None]
    v_i = state_i.v
    if omega is not None and coriolis_exact:
        v_i = world.to_inertial(omega, state_i.p, v_i)
    p = state_i.p + v_i * dt + 0.5 * g * dt * dt + so3.quat_rotate(state_i.q, delta_p)
    v = v_i + g * dt + so3.quat_rotate(state_i.q, delta_v)
    q = so3.quat_mul(state_i.q, delta_q)
    if omega is not None and coriolis_exact:
        dth, p, v = world.leave_inertial(omega, pim.delta_t, g, p, v)
        q = so3.quat_mul(so3.exp(dth), q)
    elif omega is not None:
        dth, dp, dv = _coriolis_terms(state_i, pim, omega, coriolis_second_order)
        p, v = p + dp, v + dv
        q = so3.quat_mul(state_i.q, _delta_rotation(state_i, delta_q, dth))
    return _output("predict", NavState(q=q, p=p, v=v, b_g=state_i.b_g, b_a=state_i.b_a))


def residual(state_i: NavState, state_j: NavState, pim: Preintegrated, gravity=9.81, *,
             omega_coriolis=None, coriolis_exact: bool = True,
             coriolis_second_order: bool = False):
    """The 15-dim residual ``[r_θ, r_p, r_v, r_bg, r_ba]`` (VINS-Mono's ``evaluate``, our order).

    ``r_θ = Log(ΔR̃ᵀ R_iᵀ R_j)``, ``r_p = R_iᵀ(p_j - p_i - v_i Δt - ½ g_W Δt²) - Δp̃``,
    ``r_v = R_iᵀ(v_j - v_i - g_W Δt) - Δṽ``, ``r_b = b_j - b_i``, with ``~`` the deltas
    corrected to ``state_i``'s biases. Zero for states that agree with the measurement.
    {coriolis}
    The residual then measures ``state_j`` against that prediction: with the exact
    transition in the inertial frame of ``t_i`` (``state_j`` mapped there, the transported
    velocities ``v + ω×p`` and the turning gravity); with the classic terms ``ΔR̃`` becomes
    ``Exp(Log ΔR̃ + R_iᵀ dθ_W)`` and ``dp``, ``dv`` join the gravity terms. Zero for
    ``state_j = predict(state_i, ...)`` with the same options.
    """
    batch = (_check_state_arg("state_i", state_i), _check_state_arg("state_j", state_j),
             _check_pim(pim))
    g = _gravity(gravity, pim.delta_v.dtype)
    batch = val.batch_shape(*batch, g.shape[:-1], names=("state_i", "state_j", "pim", "gravity"))
    omega = _world(omega_coriolis, pim.delta_v.dtype, batch, coriolis_exact,
                   coriolis_second_order)
    delta_q, delta_v, delta_p = _corrected_deltas(pim, state_i.bias)
    dt = pim.delta_t[..., None]
    qi_inv = so3.quat_conj(state_i.q)
    p_i, v_i, p_j, v_j, q_j, rot = state_i.p, state_i.v, state_j.p, state_j.v, state_j.q, delta_q
    if omega is not None and coriolis_exact:
        v_i = world.to_inertial(omega, p_i, v_i)
        dth, p_j, v_j = world.enter_inertial(omega, pim.delta_t, g, p_j, v_j)
        q_j = so3.quat_mul(so3.exp(-dth), q_j)
    dp_w = p_j - p_i - v_i * dt - 0.5 * g * dt * dt
    dv_w = v_j - v_i - g * dt
    if omega is not None and not coriolis_exact:
        dth, dp, dv = _coriolis_terms(state_i, pim, omega, coriolis_second_order)
        dp_w, dv_w = dp_w - dp, dv_w - dv
        rot = _delta_rotation(state_i, delta_q, dth)
    r_theta = so3.log(so3.quat_mul(so3.quat_conj(rot), so3.quat_mul(qi_inv, q_j)))
    r_p = so3.quat_rotate(qi_inv, dp_w)
    r_v = so3.quat_rotate(qi_inv, dv_w)
    parts = [r_theta, r_p - delta_p, r_v - delta_v, state_j.b_g - state_i.b_g,
             state_j.b_a - state_i.b_a]
    shape = jnp.broadcast_shapes(*(x.shape for x in parts))
    return _output("residual",
                   jnp.concatenate([jnp.broadcast_to(x, shape) for x in parts], axis=-1))


predict.__doc__ = predict.__doc__.replace("{coriolis}", CORIOLIS_DOC)
residual.__doc__ = residual.__doc__.replace("{coriolis}", CORIOLIS_DOC)


def whitened_residual(state_i: NavState, state_j: NavState, pim: Preintegrated, gravity=9.81,
                      *, omega_coriolis=None, coriolis_exact: bool = True,
                      coriolis_second_order: bool = False):
    """``L⁻¹ r`` with ``cov15 = L Lᵀ`` (Cholesky): ``|L⁻¹ r|² = rᵀ cov15⁻¹ r``.

    ``cov15`` must be positive definite to the precision of its dtype (the smallest
    eigenvalue of its correlation matrix above 60 ε:
    :func:`jaximu._validation.definiteness`): preintegrate with ``noise=`` whose densities
    and random walks are all non-zero, over at least two samples (one sample's position and
    velocity noise are the same accelerometer noise, fully correlated). On an eager call a
    ``cov15`` that is not (a measurement preintegrated without noise) raises ``ValueError``
    naming the window and the dependent axes (the check runs on the host: about 10 µs a
    window); inside a caller's ``jit`` nothing is checked and the result is then not finite
    (NaN or inf) or meaningless (rounding divided by a near-zero pivot).

    The factorisation is a block Cholesky on lanes (:func:`_whiten`): 65536 windows in
    0.03 s, against 0.13 s for LAPACK's, one matrix at a time (float64, 2-core CPU, 1 device).
    """
    r = residual(state_i, state_j, pim, gravity, omega_coriolis=omega_coriolis,
                 coriolis_exact=coriolis_exact, coriolis_second_order=coriolis_second_order)
    val.check_definite(
        "pim.cov15", pim.cov15, pim.cov15.dtype, axes=val.ERROR_AXES,
        what="the residual is whitened by its Cholesky factor",
        fix="preintegrate with noise=jaximu.ImuNoise(...) whose four densities are > 0, over "
            "at least two samples")
    return _output("whitened_residual", _whiten(pim.cov15, r))


@jax.jit
def _whiten(cov15, r):
    """``L⁻¹ r`` for ``cov15 = L Lᵀ``, ``(..., 15, 15)`` and ``(..., 15)`` broadcast together:
    the block Cholesky of :func:`jaximu._blocks.whiten` (the Monte Carlo NEES's) on lanes,
    3×3 blocks ``(3, 3, N)`` (a batch of 15×15 factorisations as LAPACK calls ran one
    matrix at a time: 2 µs per window). Not positive definite: NaN or inf."""
    from jaximu._fast import dense_to_blocks
    from jaximu._soa import SOA, block_lanes, run_blocked

    batch = jnp.broadcast_shapes(cov15.shape[:-2], r.shape[:-1])
    P = jnp.broadcast_to(cov15, batch + (15, 15)).reshape(-1, 15, 15)
    e = jnp.broadcast_to(r, batch + (15,)).reshape(-1, 15)
    if e.shape[0] == 0:  # an empty batch: no lanes to run
        return e.reshape(batch + (15,))

    def block(P, e):  # (Bc, 15, 15), (Bc, 15): one kernel per block of lanes
        Pb = dict(zip(blk.UPPER, dense_to_blocks(P)))
        eT = e.T
        y = blk.whiten(Pb, [eT[3 * i:3 * i + 3, None] for i in range(5)], SOA)
        return jnp.concatenate([b[:, 0] for b in y], 0).T

    return run_blocked(block, e.shape[0], block_lanes(e.dtype), P, e).reshape(batch + (15,))


def bias_jacobians_autodiff(gyro, accel, dt, bias: ImuBias | None = None,
                            scheme: str = "euler"):
    """The bias Jacobians by ``jax.jacfwd`` of the mean deltas over the whole window.

    Returns ``(dR_dbg, dp_dbg, dp_dba, dv_dbg, dv_dba)``, each ``(..., 3, 3)``, with the
    rotation one defined as in :class:`Preintegrated` (``Log(ΔR̂ᵀ ΔR(b̂ + δ))``).
    ``gyro``, ``accel``, ``dt``, ``bias`` as :func:`preintegrate`; ``scheme`` ``"euler"`` or
    ``"midpoint"``.
    """
    if scheme not in SCHEMES:
        raise ValueError(f"unknown preintegration scheme {scheme!r}; choose one of {SCHEMES}")
    dtype = val.float_dtype(gyro, accel, dt, bias)
    gyro, accel, dt, _ = val.check_imu(gyro, accel, dt, dtype, allow_intervals=True)
    bias = _check_bias(bias, dtype)
    return _bias_jacobians_autodiff(gyro, accel, dt, bias, scheme=scheme)


@functools.partial(jax.jit, static_argnames=("scheme",))
def _bias_jacobians_autodiff(gyro, accel, dt, bias, *, scheme):
    def deltas(delta_b):
        b = ImuBias(bias.b_g + delta_b[..., 0:3], bias.b_a + delta_b[..., 3:6])
        pim = _preintegrate(gyro, accel, dt, b, None, scheme=scheme, method="sequential",
                            jacobians="analytic", prefixes=False)
        return pim.delta_q, pim.delta_p, pim.delta_v

    q0, _, _ = deltas(jnp.zeros(6, gyro.dtype))

    def errors(delta_b):
        q, p, v = deltas(delta_b)
        return so3.log(so3.quat_mul(so3.quat_conj(q0), q)), p, v

    Jq, Jp, Jv = jax.jacfwd(errors)(jnp.zeros(6, gyro.dtype))
    return Jq[..., 0:3], Jp[..., 0:3], Jp[..., 3:6], Jv[..., 0:3], Jv[..., 3:6]

