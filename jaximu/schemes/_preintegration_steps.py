"""One preintegration step of each scheme (:class:`PreintegrationStep`: the generic step, how its
noise enters, its structure-of-arrays kernel) and the step by automatic differentiation, for
:func:`jaximu.preintegrate` (docs/DESIGN.md section 2)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaximu.geometry import sensor, so3
from jaximu.geometry._vec import V3
from jaximu.schemes import _blocks as blk
from jaximu.schemes._blocks import Blocks, mm
from jaximu.schemes.integrators import blocks_analytic, get_scheme

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
    return Blocks._make([z if x is None else x for x in b[:-1]] + [b.dt])


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
    return (
        w0 + n[..., 3:6],
        a0 + n[..., 0:3],
        w1 + n[..., 9:12],
        a1 + n[..., 6:9],
        n[..., 15:18],
        n[..., 12:15],
    )


def _vins_variances(v):
    """Discrete variances ``[σ_g², σ_a², σ_bg², σ_ba²]/dt`` → VINS-Mono's 18 (see
    :func:`_vins_midpoint_step`)."""
    sg, sa, sbg, sba = jnp.split(v, 4, axis=-1)
    return jnp.concatenate([2 * sa, 2 * sg, 2 * sa, 2 * sg, sba, sbg], -1)


@dataclasses.dataclass(frozen=True)
class PreintegrationStep:
    """What a scheme brings to preintegration (:func:`preintegration_step`):

    * ``step(dR, w0, a0, w1, a1, h, b_g, b_a, var, lever) -> (dq, acc, F, Q9, (σ_bg², σ_ba²))``:
      the generic step on ``(..., 3)`` arrays, with closed-form ``F`` and white-noise blocks
      (``lever``: ``None``, or the lever arm of samples moved from a sensor,
      :mod:`jaximu.sensor`);
    * ``noise_dim``, ``perturb(n, w0, a0, w1, a1)`` and ``variances(σ²/dt)``: how its step
      noise enters, for the autodiff Jacobians (:func:`_step_autodiff`).

    Its structure-of-arrays kernel is :data:`jaximu.kernels.fast_preint.KERNELS`'s entry of
    the same name (the kernels sit above the schemes).
    """

    name: str
    uses_next_sample: bool
    step: Callable[..., Any]
    noise_dim: int
    perturb: Callable[..., Any]
    variances: Callable[..., Any]


PREINTEGRATION_STEPS = {
    # Forster / GTSAM Manifold: the propagation Euler step from the identity, without gravity
    "euler": PreintegrationStep(
        "euler",
        False,
        lambda dR, w0, a0, w1, a1, h, *r: _euler_step(dR, w0, a0, h, *r),
        12,
        _euler_noise,
        lambda v: v,
    ),
    # VINS-Mono's midpoint (first-order quaternion, its F and 18-dim noise), kept exactly so
    # that results agree with VINS-Mono; the propagation midpoint uses the exact exponential
    "midpoint": PreintegrationStep(
        "midpoint", True, _vins_midpoint_step, 18, _vins_noise, _vins_variances
    ),
}


def preintegration_step(scheme) -> PreintegrationStep | None:
    """The :class:`PreintegrationStep` of ``scheme`` (a name or a
    :class:`jaximu.integrators.Scheme`), or ``None`` where :func:`jaximu.preintegrate` has no
    such scheme (RK4)."""
    return PREINTEGRATION_STEPS.get(get_scheme(scheme).name)


def _required(scheme) -> PreintegrationStep:
    """:func:`preintegration_step` of a scheme that has one (the entries checked it)."""
    step = preintegration_step(scheme)
    if step is None:
        raise ValueError(
            f"scheme {scheme!r} has no preintegration step; use one of "
            f"{tuple(PREINTEGRATION_STEPS)}"
        )
    return step


def _step(scheme, dR, w0, a0, w1, a1, h, b_g, b_a, noise, lever=None) -> _Step:
    """One step of ``scheme`` at the preintegrated rotation ``dR`` (``(..., 4)``, unit)."""
    dtype = w0.dtype
    if noise is None:
        var = [jnp.zeros(h.shape + (3,), dtype)] * 4
    else:
        var = jnp.split(noise.discrete_variances(h, dtype), 4, axis=-1)  # σ²/dt each
    dq, acc, F, Q9, (sbg, sba) = _required(scheme).step(dR, w0, a0, w1, a1, h, b_g, b_a, var, lever)
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
    pre = _required(scheme)
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
        dtheta = so3.log(
            so3.quat_mul(so3.quat_conj(so3.quat_normalize(so3.quat_mul(dR, nominal.dq))), dq_next)
        )
        p = delta[..., 3:6] + delta[..., 6:9] * hv + 0.5 * s.acc * hv * hv
        v = delta[..., 6:9] + s.acc * hv
        return jnp.concatenate(
            [
                dtheta,
                p - 0.5 * nominal.acc * hv * hv,
                v - nominal.acc * hv,
                delta[..., 9:15] + jnp.concatenate([nbg, nba], -1) * hv,
            ],
            -1,
        )

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
    Q9 = {(i, j): Q9d[..., 3 * i : 3 * i + 3, 3 * j : 3 * j + 3] for i, j in _UPPER9}
    return _Step(nominal.dq, nominal.acc, blk.phi_from_dense(Phi), Q15=Q15, Q9=Q9)
