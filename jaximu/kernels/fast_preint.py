"""Fast XLA-CPU preintegration (analytic Jacobians, final i→j): Euler (Forster / GTSAM
Manifold) and VINS-Mono's midpoint.

Same numbers as the generic recursion of :mod:`jaximu.preintegration` (to float rounding),
with the layout rules of :mod:`jaximu.kernels.fast` (structure of arrays, ``(3, 3, B)`` batch-minor
blocks, polynomial half angle, materialised stages, batch blocks, time chunks) and three
algebraic simplifications:

* **Rotated error.** The recursion runs on ``θ' = ΔR_ik δθ`` (the rotation error in frame
  ``B_i`` instead of ``B_k``): ``T_k = blockdiag(ΔR_ik, I, I, I, I)``,
  ``Φ'_k = T_k Φ_k``, ``Q'_k = T_k Q_k T_kᵀ``. The one-step transition becomes

      F' = T_{k+1} F T_kᵀ = [[I, 0, 0, B', 0], [-h²/2 [u]x, I, h I, 0, -h²/2 R],
                             [-h [u]x, 0, I, 0, -h R], [0, 0, 0, I, 0], [0, 0, 0, 0, I]]

  with ``R = ΔR_ik``, ``u = R f``, ``B' = -h R Jl(ω h)`` (``= ΔR_ik+1 · (-h Jr)``): the θ
  block is the identity, so ``Φ P Φᵀ`` needs far fewer 3×3 products. At the end the θ rows
  (and columns) are rotated back with ``ΔR_ijᵀ``.
* **Closed forms.** In these coordinates the accumulated ``Φ'_θθ = I``, ``Φ_vθ = -[Δv]x``
  and ``Φ_pθ = -[Δp]x`` (the same sums as Δv, Δp); only ``B', D_p, D_v, E_p, E_v`` are carried.
* **Known zeros.** The 15×15 covariance starts at zero; its ``(b_g, b_a)`` block stays zero
  and its bias diagonal blocks stay diagonal (``Σ h σ_b²``), so they are carried as vectors.

Long sequences (``method="parallel"`` with a small batch) are cut into ``C`` chunks that run
side by side as extra lanes (Euler: each in its own start frame), and the chunk summaries
are composed by two short sequential folds over a ``C1 × C2`` grid (dense 15×15 algebra: few
summaries; the frame change of :func:`jaximu.preintegration.compose`).

The midpoint scheme (VINS-Mono's first-order ``F``, non-unit quaternion) runs in the original
coordinates with the same layout; only its p rows = h/2 × v rows structure is used.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.geometry import sensor, so3
from jaximu.geometry._vec import V3
from jaximu.geometry.so3 import quat_normalize, quat_to_matrix
from jaximu.kernels.fast import blocks_autodiff
from jaximu.kernels.lane_directions import (
    direction_block,
    jvp_directions,
    lane_directions,
    rotation_rows,
    rotation_tangents,
)
from jaximu.kernels.lane_math import (
    _E3,
    _THR,
    SOA,
    _any_big,
    _bmm,
    _bsym,
    _bt,
    _cond,
    _diag_row,
    _half_any,
    _half_small,
    _jr_b_small,
    _lane,
    _outer,
    _quat_mul,
    _quat_normalize,
    _quat_renormalize,
    _quat_rotate,
    _rows,
    _skew3,
    _stage,
    quat_matrix,
)
from jaximu.kernels.soa import _components, _time_chunks, block_lanes, run_blocked, whole_chunks
from jaximu.schemes.integrators import compose_deltas, get_scheme

MIN_CHUNK = 16  # shortest time chunk per lane


# ----------------------------------------------------------------------------- one step


def _lane_scalars(big):
    """Stage 1 (per lane): the mean update and the scalars of the step."""
    def f(q, dv, dp, t, omega, fsp, h):
        u = _quat_rotate(q, fsp)
        phi = tuple(h * w for w in omega)
        t2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
        if big:
            c, k = _half_any(t2)
            sm = t2 < _THR
            b = jnp.where(sm, _jr_b_small(jnp.where(sm, t2, 0.0)),
                          (1.0 - 2.0 * k * c) / jnp.where(sm, 1.0, t2))
        else:
            c, k = _half_small(t2)
            b = _jr_b_small(t2)
        q1 = _quat_renormalize(_quat_mul(q, (c, k * phi[0], k * phi[1], k * phi[2])))
        dp1 = tuple((dp[i] + dv[i] * h) + 0.5 * u[i] * h * h for i in range(3))
        dv1 = tuple(dv[i] + u[i] * h for i in range(3))
        return (q1, dv1, dp1, t + h), (u, phi, t2, k, b)

    return f


def _rot_jl(q, phi, t2, k, b):
    """Stage 2a: ``R = R(q)`` and ``Jl(φ)`` as ``(3, 3, B)``."""
    dtype = q[0].dtype
    I3 = jnp.asarray(_E3, dtype)[:, :, None]
    phi3 = _rows(phi, dtype)
    Jl = (I3 + _lane(2.0 * (k * k)) * _skew3(phi, dtype)
          + _lane(b) * (_outer(phi3, phi3) - _lane(t2) * I3))
    return quat_matrix(q, dtype), Jl


def _step_blocks(R, Jl, h, u):
    """Stage 2b: ``Ev = -h R``, ``B' = -h R Jl(φ)``, ``Cv = -h [u]x``."""
    mh = _lane(-h)
    Ev = mh * R
    return Ev, _bmm(Ev, Jl), mh * _skew3(u, R.dtype)


def _autodiff_blocks(q, dv, dp, omega, fsp, h, lever):
    """Stage 2 by autodiff (``jacobians="autodiff"``): ``Ev``, ``B'``, ``Cv`` (and with a
    lever arm ``Dk``) as the propagation kernel's :func:`jaximu.kernels.fast.blocks_autodiff` makes
    them, ``jax.jvp`` of the Euler step (:func:`jaximu.kernels.lane_forms.mean_step`, zero gravity, from
    ``(ΔR_ik, Δp, Δv)``) with the rotation error in the start frame ``B_i``
    (``world_error``): the rotated coordinates of this kernel, where ``Φ'_θθ = I``. The
    other blocks follow from these in an Euler step (``Cp = h/2 Cv``, ``Ep = h/2 Ev``,
    ``Dp = h/2 Dk``), as in the closed forms; the exact Euler step makes the two equal to
    rounding."""
    w, f, zero = V3(*omega), V3(*fsp), V3(0.0, 0.0, 0.0)
    _, b = blocks_autodiff(get_scheme("euler"), q, V3(*dp), V3(*dv), w, f, w, f, h, zero,
                           None if lever is None else V3(*lever), world_error=True)
    return b.Ev, b.B, b.Cv, (None if lever is None else b.Dv)


def _noise_blocks(Bk, Ev, sg, sa):
    """Stage 2c: ``Qθ = B' diag(σ_g²/h) B'ᵀ``, ``Qv = Ev diag(σ_a²/h) Evᵀ``; with ``Ev =
    None`` (an isotropic accelerometer, :func:`step`) only ``Qθ``."""
    dtype = Bk.dtype
    Qth = _bmm(Bk * _diag_row(sg, dtype), _bt(Bk))
    return Qth if Ev is None else (Qth, _bmm(Ev * _diag_row(sa, dtype), _bt(Ev)))


# blocks of the 15×15 covariance that are carried (the others: (3,3), (4,4) diagonal; (3,4)
# and (0,4) zero: Cov(δθ, δb_a) starts at zero and stays there, as neither the rotation
# rows of F nor the gyro noise reach b_a, and neither the bias rows nor their noise reach θ)
P15_KEYS = ((0, 0), (0, 1), (0, 2), (0, 3), (1, 1), (1, 2), (1, 3), (1, 4), (2, 2), (2, 3),
            (2, 4))
P9_KEYS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _cov15_a(P, d3, d4, Bk, Cv, Ev):
    """``M = F' P`` rows θ and the v-row increments ``N_j = Cv P_0j + Ev P_4j``
    (``P_04 = 0``)."""
    P = dict(zip(P15_KEYS, P))
    M00 = P[0, 0] + _bmm(Bk, _bt(P[0, 3]))
    M01 = P[0, 1] + _bmm(Bk, _bt(P[1, 3]))
    M02 = P[0, 2] + _bmm(Bk, _bt(P[2, 3]))
    M03 = P[0, 3] + Bk * d3[None]
    N0 = _bmm(Cv, P[0, 0])
    N1 = _bmm(Cv, P[0, 1]) + _bmm(Ev, _bt(P[1, 4]))
    N2 = _bmm(Cv, P[0, 2]) + _bmm(Ev, _bt(P[2, 4]))
    N3 = _bmm(Cv, P[0, 3])
    N4 = Ev * d4[None]
    return (M00, M01, M02, M03), (N0, N1, N2, N3, N4)


def _cov15_b(M10, M14, M20, M24, M00, Cv, Ev):
    """``K_i = M_i0 Cvᵀ + M_i4 Evᵀ`` for the rows θ, p, v (``M_04 = P_04 = 0``)."""
    Cvt, Evt = _bt(Cv), _bt(Ev)
    return (_bmm(M00, Cvt), _bmm(M10, Cvt) + _bmm(M14, Evt),
            _bmm(M20, Cvt) + _bmm(M24, Evt))


def _cov9_a(S, Cv):
    S = dict(zip(P9_KEYS, S))
    return tuple(_bmm(Cv, S[0, j]) for j in range(3))


def _cov9_b(M10, M20, S00, Cv):
    Cvt = _bt(Cv)
    return _bmm(S00, Cvt), _bmm(M10, Cvt), _bmm(M20, Cvt)


def _lever_rk(R, omega, lever):
    """``R K(ω)`` (``(3, 3, B)``) for samples moved from a sensor at the lever arm ``lever``
    (a 3-tuple): a gyro bias error ``δb_g`` moves the specific force by ``K δb_g``, a noise
    the same way (:func:`jaximu.sensor.centripetal_jacobian`)."""
    return _bmm(R, sensor.centripetal_jacobian(V3(*omega), V3(*lever), SOA))


def step(carry, omega, fsp, h, s, guard, lever=None, jacobians="analytic",
         isotropic_accel=False):
    """One Euler step in the rotated coordinates. ``s``: 12-tuple of ``σ²`` per axis
    (scalars or ``(B,)``); ``guard``: padded steps (``h = 0``) are exact identities.
    ``lever`` (a 3-tuple, or ``None``): samples moved from a sensor at that lever arm; the
    gyro bias and noise then reach v (and p) through ``Dk = h R K`` (:func:`_lever_rk`),
    F''s b_g column and the gyro noise's (they enter alike). ``jacobians``: the step's
    blocks in closed form (``"analytic"``) or by autodiff (:func:`_autodiff_blocks`); the
    covariance update after them is the same. ``isotropic_accel``: the accelerometer's white
    noise is the same on every axis (a scalar density), so its block
    ``Ev diag(σ_a²/h) Evᵀ = h σ_a² R Rᵀ`` is ``h σ_a² I`` (R a rotation: to rounding),
    one product fewer a step."""
    q, dv, dp, t, (Bacc, Dp, Dv, Ep, Ev_acc), P, d3, d4, S = carry
    t2 = sum((h * w) * (h * w) for w in omega)
    (q1, dv1, dp1, t1), lane = _cond(
        _any_big(t2), _lane_scalars(True), _lane_scalars(False),
        q, dv, dp, t, omega, fsp, h)
    u, phi, t2, k, b = lane
    ok = jnp.all(jnp.isfinite(h))  # a runtime predicate for the stage conds
    hd = jnp.where(h > 0, h, jnp.ones_like(h)) if guard else h
    ih = 1.0 / hd  # one division a step (σ²/dt: noise.discrete_variances)
    var = tuple(x * ih for x in s)
    h, var = _stage(ok, lambda h, v: (h * 1, tuple(x * 1 for x in v)), h, var)
    Dk = Qtv = None
    if jacobians == "analytic":
        R, Jl = _stage(ok, _rot_jl, q, phi, t2, k, b)
        Ev, Bk, Cv = _stage(ok, _step_blocks, R, Jl, h, u)
        if lever is not None:
            Dk = _stage(ok, lambda R, h: _lever_rk(R, omega, lever) * _lane(h), R, h)
    else:
        Ev, Bk, Cv, Dk = _stage(ok, lambda *a: _autodiff_blocks(*a, lever), q, dv, dp, omega,
                                fsp, h)
    if isotropic_accel:  # var[3] = σ_a²/h: Qv = h² var[3] I
        Qth = _stage(ok, _noise_blocks, Bk, None, var[0:3], None)
        Qv = jnp.asarray(_E3, Bk.dtype)[:, :, None] * _lane(h * h * var[3])
    else:
        Qth, Qv = _stage(ok, _noise_blocks, Bk, Ev, var[0:3], var[3:6])
    hb = _lane(h)
    half = 0.5 * hb
    if lever is not None:  # F'_vbg = Dk; the gyro noise column is [Bk, h/2 Dk, Dk]
        sg = _diag_row(var[0:3], q[0].dtype)
        Qv = Qv + _bmm(Dk * sg, _bt(Dk))
        Qtv = _bmm(Bk * sg, _bt(Dk))

    # transition (Φ' = F' Φ'): Cv Φ'_θbg is the only product
    X = _bmm(Cv, Bacc) if Dk is None else _bmm(Cv, Bacc) + Dk
    Phi1 = (Bacc + Bk, (Dp + hb * Dv) + half * X, Dv + X, (Ep + hb * Ev_acc) + half * Ev,
            Ev_acc + Ev)

    # 15×15 covariance
    Pd = dict(zip(P15_KEYS, P))
    (M00, M01, M02, M03), (N0, N1, N2, N3, N4) = _stage(ok, _cov15_a, P, d3, d4, Bk, Cv, Ev)
    if Dk is not None:  # the v-row increments gain Dk P_3j
        N0, N1, N2 = (N + _bmm(Dk, _bt(Pd[j, 3])) for N, j in ((N0, 0), (N1, 1), (N2, 2)))
        N3 = N3 + Dk * d3[None]
    M10 = (_bt(Pd[0, 1]) + hb * _bt(Pd[0, 2])) + half * N0
    M11 = (Pd[1, 1] + hb * _bt(Pd[1, 2])) + half * N1
    M12 = (Pd[1, 2] + hb * Pd[2, 2]) + half * N2
    M13 = (Pd[1, 3] + hb * Pd[2, 3]) + half * N3
    M14 = (Pd[1, 4] + hb * Pd[2, 4]) + half * N4
    M20 = _bt(Pd[0, 2]) + N0
    M22 = Pd[2, 2] + N2
    M23 = Pd[2, 3] + N3
    M24 = Pd[2, 4] + N4
    M10, M11, M12, M13, M14 = _stage(ok, lambda *a: tuple(x * 1 for x in a),
                                     M10, M11, M12, M13, M14)
    K0, K1, K2 = _stage(ok, _cov15_b, M10, M14, M20, M24, M00, Cv, Ev)
    if Dk is not None:  # and the v columns M_i3 Dkᵀ
        Dkt = _bt(Dk)
        K0, K1, K2 = K0 + _bmm(M03, Dkt), K1 + _bmm(M13, Dkt), K2 + _bmm(M23, Dkt)
    new = {
        (0, 0): _bsym((M00 + _bmm(M03, _bt(Bk))) + Qth),
        (0, 1): (M01 + hb * M02) + half * K0,
        (0, 2): M02 + K0,
        (0, 3): M03,
        (1, 1): _bsym(((M11 + hb * M12) + half * K1) + (half * half) * Qv),
        (1, 2): (M12 + K1) + half * Qv,
        (1, 3): M13,
        (1, 4): M14,
        (2, 2): _bsym((M22 + K2) + Qv),
        (2, 3): M23,
        (2, 4): M24,
    }
    if Qtv is not None:
        new[0, 1] = new[0, 1] + half * Qtv
        new[0, 2] = new[0, 2] + Qtv
    h2 = h * h
    d3n = d3 + _diag_row(tuple(h2 * x for x in var[6:9]), q[0].dtype)[0]
    d4n = d4 + _diag_row(tuple(h2 * x for x in var[9:12]), q[0].dtype)[0]

    # 9×9 white-noise covariance (no bias columns: F'_9 = [[I,0,0],[Cp,I,hI],[Cv,0,I]])
    Sd = dict(zip(P9_KEYS, S))
    N90, N91, N92 = _stage(ok, _cov9_a, S, Cv)
    L10 = (_bt(Sd[0, 1]) + hb * _bt(Sd[0, 2])) + half * N90
    L11 = (Sd[1, 1] + hb * _bt(Sd[1, 2])) + half * N91
    L12 = (Sd[1, 2] + hb * Sd[2, 2]) + half * N92
    L20 = _bt(Sd[0, 2]) + N90
    L22 = Sd[2, 2] + N92
    L11, L12, L22 = _stage(ok, lambda *a: tuple(x * 1 for x in a), L11, L12, L22)
    K90, K91, K92 = _stage(ok, _cov9_b, L10, L20, Sd[0, 0], Cv)
    S1 = (
        _bsym(Sd[0, 0] + Qth),
        (Sd[0, 1] + hb * Sd[0, 2]) + half * K90,
        Sd[0, 2] + K90,
        _bsym(((L11 + hb * L12) + half * K91) + (half * half) * Qv),
        (L12 + K91) + half * Qv,
        _bsym((L22 + K92) + Qv),
    )
    if Qtv is not None:
        S1 = (S1[0], S1[1] + half * Qtv, S1[2] + Qtv) + S1[3:]
    return (q1, dv1, dp1, t1, Phi1, tuple(new[k] for k in P15_KEYS), d3n, d4n, S1)


def _zero_carry(Bc, dtype):
    z = jnp.zeros((Bc,), dtype)
    Z = jnp.zeros((3, 3, Bc), dtype)
    z3 = jnp.zeros((3, Bc), dtype)
    q = (jnp.ones((Bc,), dtype), z, z, z)
    return (q, (z, z, z), (z, z, z), z, (Z,) * 5, (Z,) * len(P15_KEYS), z3, z3,
            (Z,) * len(P9_KEYS))


# ----------------------------------------------------------------------------- VINS midpoint
#
# VINS-Mono's midPointIntegration in the original error coordinates (its first-order F is not
# a rotation, so the rotated coordinates do not simplify it). Its p rows are h/2 × its v rows
# (Cp = h/2 Cv, Dp = h/2 Dv, Ep = h/2 Ev, and the same for the noise), which halves the work.
# The carried transition has all eight blocks.


def _mid_lane(q, dv, dp, t, omega, f0, f1, h):
    """Stage 1 (per lane): the mean update, VINS-Mono's unnormalised ``q ⊗ [1, ω̄h/2]``."""
    dq = (jnp.ones_like(h) if jnp.ndim(h) else jnp.ones_like(q[0]),) + tuple(0.5 * h * w
                                                                           for w in omega)
    q1u = _quat_mul(q, dq)
    u0, u1 = _quat_rotate(q, f0), _quat_rotate(q1u, f1)
    acc = tuple(0.5 * (u0[i] + u1[i]) for i in range(3))
    dp1 = tuple((dp[i] + dv[i] * h) + 0.5 * acc[i] * h * h for i in range(3))
    dv1 = tuple(dv[i] + acc[i] * h for i in range(3))
    return (_quat_normalize(q1u), dv1, dp1, t + h), q1u


def _mid_blocks(q, q1u, omega, f0, f1, h):
    """Stage 2: A, Cv, Dv, Ev of F and the noise factor W = -h²/4 R1[f1]x."""
    dtype = q[0].dtype
    I3 = jnp.asarray(_E3, dtype)[:, :, None]
    hb = _lane(h)
    R0, R1 = quat_matrix(q, dtype), quat_matrix(q1u, dtype)
    A = I3 - _skew3(omega, dtype) * hb
    R0a0 = _bmm(R0, _skew3(f0, dtype))
    R1a1 = _bmm(R1, _skew3(f1, dtype))
    return A, R0, R1, R0a0, R1a1


def _mid_analytic(q, q1u, omega, f0, f1, h):
    """VINS-Mono's closed-form blocks: ``A = I - [ω̄]x h``, ``B = -h I`` (``None``: not
    formed), ``Cv`` and ``Dr = -∂v/∂ω̄ = ½ R1 [f1]x h²`` (``Dv`` without a lever arm)."""
    A, R0, R1, R0a0, R1a1 = _mid_blocks(q, q1u, omega, f0, f1, h)
    hb = _lane(h)
    Cv = -0.5 * (R0a0 + _bmm(R1a1, A)) * hb
    return A, None, Cv, 0.5 * R1a1 * (hb * hb), R0, R1


def _mid_autodiff(q, omega, f0, f1, h):
    """The same blocks by autodiff (``jacobians="autodiff"``): ``jax.jvp`` of VINS-Mono's
    mean (:func:`_mid_lane`) in the directions ``δθ`` (the tangent ``q ⊗ [0, ½ e_j]``) and
    ``δω̄``, each a ``vmap`` over its 3 directions; rotation rows ``2 vec(q⁺* ⊗ δq⁺)`` (as
    :func:`jaximu.kernels.fast.blocks_autodiff`). ``∂v/∂f_i = ½ h R_i`` is exact in both."""
    dtype = q[0].dtype
    lanes = q[0].shape
    zero = jnp.zeros(lanes, dtype)
    z3 = (zero, zero, zero)

    def mean(q, omega):
        (q1, dv1, _, _), _ = _mid_lane(q, z3, z3, zero, omega, f0, f1, h)
        return q1, dv1

    (q1, _, _, _), q1u = _mid_lane(q, z3, z3, zero, omega, f0, f1, h)
    tq_t, tv_t = jvp_directions(lambda q: mean(q, omega), (q,), (rotation_tangents(q),))
    tq_w, tv_w = jvp_directions(lambda w: mean(q, w), (omega,),
                                (lane_directions(np.eye(3), dtype, lanes),))

    def block(rows):
        return direction_block(rows, dtype)

    def rot(tq1):
        return rotation_rows(tq1, q1)

    R0, R1 = quat_matrix(q, dtype), quat_matrix(q1u, dtype)
    return block(rot(tq_t)), -block(rot(tq_w)), block(tv_t), -block(tv_w), R0, R1


def _mid_blocks2(A, B, Cv, Dr, R0, R1, h, sg, sa, RK=None):
    """Dv, Ev of F and the white-noise blocks Qθθ, Qv, Qθv from the step's blocks (closed
    form or autodiff): the gyro noise of either sample moves ω̄ by half of it, so its rows
    are ``-½ B`` (θ) and ``-½ Dr`` (v; ``Dr = -∂v/∂ω̄``); the accelerometer noise's v rows
    are ``½ h R_i``; the p rows are h/2 of the v rows. ``B = None``: VINS-Mono's ``-h I``.
    ``RK = (R0 K0, R1 K1)`` for samples moved from a sensor at a lever arm
    (:func:`_lever_rk`): f_i moves with the gyro bias and noise of sample i, ``K_i δω_i``."""
    dtype = A.dtype
    hb = _lane(h)
    Ev = -0.5 * (R0 + R1) * hb
    W = -0.5 * Dr  # v row of either gyro noise (p row: h/2 of it)
    sa2 = _diag_row(tuple(2.0 * x for x in sa), dtype)
    sg2 = _diag_row(tuple(2.0 * x for x in sg), dtype)
    G = 0.25 * (hb * hb)
    Qa = G * (_bmm(R0 * sa2, _bt(R0)) + _bmm(R1 * sa2, _bt(R1)))
    if B is None:  # θ row of either gyro noise: ½ h I
        Qtt = jnp.asarray(_E3, dtype)[:, :, None] * (sg2 * (2.0 * G))
        Gt = None
    else:
        Gt = -0.5 * B
        Qtt = 2.0 * _bmm(Gt * sg2, _bt(Gt))
    W0 = W1 = W
    Dv = Dr
    if RK is not None:
        RK0, RK1 = RK
        Dv = Dr + 0.5 * (RK0 + RK1) * hb
        W0, W1 = W - 0.5 * RK0 * hb, W - 0.5 * RK1 * hb
    Qv = Qa + _bmm(W0 * sg2, _bt(W0)) + _bmm(W1 * sg2, _bt(W1))
    if Gt is None:
        Qtv = _bt(0.5 * hb * (W0 + W1) * sg2)  # (h/2 I) diag(2σ_g²/h) (W0 + W1)ᵀ
    else:
        Qtv = _bmm(Gt * sg2, _bt(W0 + W1))
    return Dv, Ev, Qtt, Qv, Qtv


def _b_times(B, X, h):
    """``B X`` for the θ row's b_g block ``B`` (``None``: VINS-Mono's ``-h I``)."""
    return -_lane(h) * X if B is None else _bmm(B, X)


def _mid_cov_a(P, d3, d4, A, B, Cv, Dv, Ev, h):
    """``M = F P`` rows θ and the v-row increments ``N_j = Cv P_0j + Dv P_3j + Ev P_4j``
    (``P_04 = 0``: ``M`` has no block 4 in row θ)."""
    P = dict(zip(P15_KEYS, P))
    I3 = jnp.asarray(_E3, A.dtype)[:, :, None]
    M0 = (_bmm(A, P[0, 0]) + _b_times(B, _bt(P[0, 3]), h),
          _bmm(A, P[0, 1]) + _b_times(B, _bt(P[1, 3]), h),
          _bmm(A, P[0, 2]) + _b_times(B, _bt(P[2, 3]), h),
          _bmm(A, P[0, 3]) + _b_times(B, I3 * d3[None], h))
    N = (_bmm(Cv, P[0, 0]) + _bmm(Dv, _bt(P[0, 3])),
         _bmm(Cv, P[0, 1]) + _bmm(Dv, _bt(P[1, 3])) + _bmm(Ev, _bt(P[1, 4])),
         _bmm(Cv, P[0, 2]) + _bmm(Dv, _bt(P[2, 3])) + _bmm(Ev, _bt(P[2, 4])),
         _bmm(Cv, P[0, 3]) + Dv * d3[None],
         Ev * d4[None])
    return M0, N


def _mid_cov_b(M0, M1, M2, A, B, Cv, Dv, Ev, h):
    Cvt, Dvt, Evt = _bt(Cv), _bt(Dv), _bt(Ev)
    K = ((_bmm(M0[0], Cvt) + _bmm(M0[3], Dvt),)
         + tuple(_bmm(M[0], Cvt) + _bmm(M[3], Dvt) + _bmm(M[4], Evt) for M in (M1, M2)))
    return K, _bmm(M0[0], _bt(A)) + _bt(_b_times(B, _bt(M0[3]), h))


def _mid_cov9(S, A, Cv, h):
    S = dict(zip(P9_KEYS, S))
    hb = _lane(h)
    M0 = tuple(_bmm(A, S[0, j]) for j in range(3))
    N = tuple(_bmm(Cv, S[0, j]) for j in range(3))
    M10 = (_bt(S[0, 1]) + hb * _bt(S[0, 2])) + 0.5 * hb * N[0]
    M20 = _bt(S[0, 2]) + N[0]
    Cvt = _bt(Cv)
    K = (_bmm(M0[0], Cvt), _bmm(M10, Cvt), _bmm(M20, Cvt))
    return M0, N, K, _bmm(M0[0], _bt(A))


def mid_step(carry, w0, a0, w1, a1, h, s, q_given=None, guard=False, lever=None,
             jacobians="analytic"):
    """One VINS-Mono midpoint step; with ``q_given`` the rotation at the step is an input (the
    parallel method's chunks, frame ``B_i``) instead of the carried one. ``lever``: as
    :func:`step`. ``jacobians``: VINS-Mono's linearisation (``"analytic"``,
    :func:`_mid_analytic`) or the exact derivatives of its mean (``"autodiff"``,
    :func:`_mid_autodiff`); the covariance update after them is the same."""
    q, dv, dp, t, (Ac, Bc, Cpc, Cvc, Dpc, Dvc, Epc, Evc), P, d3, d4, S = carry
    omega = tuple(0.5 * (w0[i] + w1[i]) for i in range(3))  # bias removed by the caller
    ok = jnp.all(jnp.isfinite(h))
    if q_given is not None:
        q = q_given
    (q1, dv1, dp1, t1), q1u = _stage(ok, _mid_lane, q, dv, dp, t, omega, a0, a1, h)
    hd = jnp.where(h > 0, h, jnp.ones_like(h)) if guard else h
    ih = 1.0 / hd  # one division a step
    var = tuple(x * ih for x in s)
    h, var = _stage(ok, lambda h, v: (h * 1, tuple(x * 1 for x in v)), h, var)
    if jacobians == "analytic":
        A, B, Cv, Dr, R0, R1 = _stage(ok, _mid_analytic, q, q1u, omega, a0, a1, h)
    else:
        A, B, Cv, Dr, R0, R1 = _stage(ok, _mid_autodiff, q, omega, a0, a1, h)
    RK = None
    if lever is not None:
        RK = _stage(ok, lambda R0, R1: (_lever_rk(R0, w0, lever), _lever_rk(R1, w1, lever)),
                    R0, R1)
    Dv, Ev, Qtt, Qv, Qtv = _stage(ok, _mid_blocks2, A, B, Cv, Dr, R0, R1, h, var[0:3],
                                  var[3:6], RK)
    dtype = q[0].dtype
    hb = _lane(h)
    half = 0.5 * hb

    # transition Φ ← F Φ (F.Cp = h/2 F.Cv, F.Dp = h/2 F.Dv, F.Ep = h/2 F.Ev)
    XA, XB, AA, AB = _stage(ok, lambda A, Cv, Ac, Bc: (_bmm(Cv, Ac), _bmm(Cv, Bc), _bmm(A, Ac),
                                                        _bmm(A, Bc)), A, Cv, Ac, Bc)
    I3 = jnp.asarray(_E3, dtype)[:, :, None]
    Phi1 = (AA, AB + (-hb * I3 if B is None else B), (half * XA + Cpc) + hb * Cvc, XA + Cvc,
            ((half * XB + Dpc) + hb * Dvc) + half * Dv, (XB + Dvc) + Dv,
            (Epc + hb * Evc) + half * Ev, Evc + Ev)

    # 15×15 covariance
    Pd = dict(zip(P15_KEYS, P))
    M0, N = _stage(ok, _mid_cov_a, P, d3, d4, A, B, Cv, Dv, Ev, h)
    M1 = tuple((Pd[1, j] if j >= 1 else _bt(Pd[0, 1])) + hb * (
        Pd[2, j] if j >= 2 else _bt(Pd[j, 2])) + half * N[j] for j in range(5))
    M2 = tuple((Pd[2, j] if j >= 2 else _bt(Pd[j, 2])) + N[j] for j in range(5))
    M1, M2 = _stage(ok, lambda a, b: (tuple(x * 1 for x in a), tuple(x * 1 for x in b)),
                    M1, M2)
    (K0, K1, K2), C00 = _stage(ok, _mid_cov_b, M0, M1, M2, A, B, Cv, Dv, Ev, h)
    new = {
        (0, 0): _bsym(C00 + Qtt),
        (0, 1): ((M0[1] + hb * M0[2]) + half * K0) + half * Qtv,
        (0, 2): (M0[2] + K0) + Qtv,
        (0, 3): M0[3],
        (1, 1): _bsym(((M1[1] + hb * M1[2]) + half * K1) + (half * half) * Qv),
        (1, 2): (M1[2] + K1) + half * Qv,
        (1, 3): M1[3], (1, 4): M1[4],
        (2, 2): _bsym((M2[2] + K2) + Qv),
        (2, 3): M2[3], (2, 4): M2[4],
    }
    h2 = h * h
    d3n = d3 + _diag_row(tuple(h2 * x for x in var[6:9]), dtype)[0]
    d4n = d4 + _diag_row(tuple(h2 * x for x in var[9:12]), dtype)[0]

    # 9×9 white-noise covariance
    Sd = dict(zip(P9_KEYS, S))
    L0, L, (K90, K91, K92), C900 = _stage(ok, _mid_cov9, S, A, Cv, h)
    L11 = (Sd[1, 1] + hb * _bt(Sd[1, 2])) + half * L[1]
    L12 = (Sd[1, 2] + hb * Sd[2, 2]) + half * L[2]
    L22 = Sd[2, 2] + L[2]
    S1 = (
        _bsym(C900 + Qtt),
        ((L0[1] + hb * L0[2]) + half * K90) + half * Qtv,
        (L0[2] + K90) + Qtv,
        _bsym(((L11 + hb * L12) + half * K91) + (half * half) * Qv),
        (L12 + K91) + half * Qv,
        _bsym((L22 + K92) + Qv),
    )
    return (q1, dv1, dp1, t1, Phi1, tuple(new[k] for k in P15_KEYS), d3n, d4n, S1)


def _as_chunks(C, gyro, accel, dt, per_sequence, edge=None):
    """Each of the B sequences as ``C`` time chunks of ``L`` steps side by side as lanes
    (the parallel method; ``L``: ``ceil(T / C)`` rounded up to whole kernel time chunks,
    :func:`jaximu.kernels.soa.whole_chunks`): gyro, accel ``(B, T, k)`` -> ``(B C, L, k)``, dt
    ``(B, T)`` -> ``(B C, L)``, zero-padded at the end (``h = 0`` steps: the kernels'
    ``guard`` makes them identities); ``edge`` ``(B, T, m)``: per-step values appended to
    ``accel``, padded with their last one; ``per_sequence``: ``(B, ·)`` arrays repeated per
    chunk (a ``(·,)`` one shared by all, or ``None``, passes). Returns
    ``((gyro, accel, dt, per_sequence), guard)``, ``guard``: some steps are padding."""
    B, T = dt.shape
    L = whole_chunks(-(-T // C))
    pad = C * L - T
    if pad:
        padw = lambda x, **kw: jnp.pad(  # noqa: E731
            x, ((0, 0), (0, pad)) + ((0, 0),) * (x.ndim - 2), **kw)
        gyro, accel, dt = padw(gyro), padw(accel), padw(dt)
        edge = None if edge is None else padw(edge, mode="edge")
    if edge is not None:
        accel = jnp.concatenate([accel, edge], -1)
    lanes = lambda x: x.reshape((B * C, L) + x.shape[2:])  # noqa: E731
    rep = [x if x is None or x.ndim == 1 else jnp.repeat(x, C, axis=0) for x in per_sequence]
    return (lanes(gyro), lanes(accel), lanes(dt), tuple(rep)), bool(pad)


def preintegrate_midpoint(gyro, accel, dt, b_g, b_a, var, C=1, lever=None,
                          jacobians="analytic", isotropic_accel=False):
    """As :func:`preintegrate_euler` for VINS-Mono's midpoint; gyro, accel ``(B, T, 6)``:
    samples k and k+1 side by side. Returns the generic code's outputs. ``isotropic_accel``
    is not used: the end sample's rotation comes from VINS-Mono's unnormalised quaternion,
    so ``R_1 D R_1ᵀ`` is not ``σ² I`` (the accelerometer blocks stay products).

    With ``C > 1`` chunks (the parallel method): as the generic code, the rotations ``ΔR_ik``
    come first from an associative scan of the normalised increments; each chunk then runs in
    frame ``B_i`` with its rotations given, and the chunk summaries compose without a frame
    change (VINS-Mono's unnormalised rotation makes a change of frame inexact).
    ``jacobians``: :func:`mid_step`."""
    B, T, _ = gyro.shape
    dtype = gyro.dtype
    guard = False
    if C > 1:
        omega = 0.5 * (gyro[..., 0:3] + gyro[..., 3:6]) - (b_g if b_g.ndim == 1 else b_g[:, None])
        hT = jnp.broadcast_to(dt, (B, T))
        incr = jnp.concatenate([jnp.ones_like(hT)[..., None], 0.5 * hT[..., None] * omega], -1)
        incl = so3.quat_normalize(jax.lax.associative_scan(
            so3.quat_mul, so3.quat_normalize(incr), axis=1))
        q_last = incl[:, -1]
        dR = jnp.concatenate([jnp.broadcast_to(so3.quat_identity((), dtype), (B, 1, 4)),
                              incl[:, :-1]], 1)
        # the rotation rides along with the specific force (B, T, 10); padded steps sit at
        # a unit rotation (autodiff normalises through it)
        (gyro, accel, dt, (b_g, b_a, var, lever)), guard = _as_chunks(
            C, gyro, accel, hT, (b_g, b_a, var, lever), edge=dR)

    def block(gyro, accel, dt, b_g, b_a, var, lever):
        Bc = gyro.shape[0]
        bg, ba, s = _components(b_g), _components(b_a), _components(var)
        r = None if lever is None else _components(lever)

        def st(c, w, a, h, consts):
            w0 = tuple(w[i] - bg[i] for i in range(3))
            w1 = tuple(w[3 + i] - bg[i] for i in range(3))
            a0 = tuple(a[i] - ba[i] for i in range(3))
            a1 = tuple(a[3 + i] - ba[i] for i in range(3))
            return mid_step(c, w0, a0, w1, a1, h, s, a[6:10] if C > 1 else None, guard, r,
                            jacobians)

        q, dv, dp, t, Phi, P, d3, d4, S = _time_chunks(
            st, _zero_carry_mid(Bc, dtype), gyro, accel, dt, None, None)[0]
        last = lambda x: jnp.stack(x, -1)  # noqa: E731
        bm = lambda X: jnp.moveaxis(X, -1, 0)  # noqa: E731
        A, Bg, Cp, Cv, Dp, Dv, Ep, Ev = (bm(X) for X in Phi)
        eye = jnp.eye(3, dtype=dtype)
        I = jnp.broadcast_to(eye, t.shape + (3, 3))
        Z = jnp.zeros_like(I)
        rows = [[A, Z, Z, Bg, Z], [Cp, I, t[:, None, None] * eye, Dp, Ep], [Cv, Z, I, Dv, Ev],
                [Z, Z, Z, I, Z], [Z, Z, Z, Z, I]]
        Phi = jnp.concatenate([jnp.concatenate(r, -1) for r in rows], -2)
        P15 = {k: bm(X) for k, X in zip(P15_KEYS, P)}
        P15[3, 3] = bm(d3)[:, None, :] * eye
        P15[4, 4] = bm(d4)[:, None, :] * eye
        P9 = {k: bm(X) for k, X in zip(P9_KEYS, S)}
        return dict(q=last(q), dv=last(dv), dp=last(dp), t=t, Phi=Phi, Q15=_dense(P15, 5),
                    Q9=_dense(P9, 3))

    out = _run_blocked(block, gyro, accel, dt, b_g, b_a, var, lever)
    if C > 1:
        out = jax.tree_util.tree_map(lambda x: x.reshape((B, C) + x.shape[1:]), out)
        out = _reduce_chunks(out, C, rotate=False)
        out["q"] = q_last
    return (out["t"], so3.quat_normalize(out["q"]), out["dv"], out["dp"], out["Phi"], out["Q15"],
            out["Q9"])


def _zero_carry_mid(Bc, dtype):
    q, dv, dp, t, _, P, d3, d4, S = _zero_carry(Bc, dtype)
    Z = jnp.zeros((3, 3, Bc), dtype)
    I = jnp.broadcast_to(jnp.asarray(_E3, dtype)[:, :, None], (3, 3, Bc))
    return (q, dv, dp, t, (I,) + (Z,) * 7, P, d3, d4, S)


# ----------------------------------------------------------------------------- summaries
#
# A summary (batch-major, in its start frame, θ' coordinates) is a dict: q (n, 4), dv, dp
# (n, 3), t (n,), Phi (n, 15, 15), Q15 (n, 15, 15), Q9 (n, 9, 9). Few of them are composed
# (chunks of one sequence), so dense 15×15 algebra is cheap there and quick to compile.


def _t(X):
    return jnp.swapaxes(X, -1, -2)


def _sym(X):
    return 0.5 * (X + _t(X))


def _skew(v):
    z = jnp.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return jnp.stack([jnp.stack([z, -w, y], -1), jnp.stack([w, z, -x], -1),
                      jnp.stack([-y, x, z], -1)], -2)


def _dense(blocks, n):
    """Symmetric ``(…, 3n, 3n)`` from upper blocks ``{(i, j): (…, 3, 3)}`` (others zero)."""
    some = next(iter(blocks.values()))
    Z = jnp.zeros_like(some)

    def get(i, j):
        if i <= j:
            return blocks.get((i, j), Z)
        return _t(blocks[(j, i)]) if (j, i) in blocks else Z

    return jnp.concatenate([jnp.concatenate([get(i, j) for j in range(n)], -1)
                            for i in range(n)], -2)


def _to_summary(c):
    q, dv, dp, t, (Bg, Dp, Dv, Ep, Ev), P, d3, d4, S = c
    last = lambda x: jnp.stack(x, -1)  # noqa: E731
    bm = lambda X: jnp.moveaxis(X, -1, 0)  # noqa: E731
    dv, dp = last(dv), last(dp)
    eye = jnp.eye(3, dtype=t.dtype)
    I = jnp.broadcast_to(eye, t.shape + (3, 3))
    Z = jnp.zeros_like(I)
    rows = [[I, Z, Z, bm(Bg), Z], [-_skew(dp), I, t[:, None, None] * eye, bm(Dp), bm(Ep)],
            [-_skew(dv), Z, I, bm(Dv), bm(Ev)], [Z, Z, Z, I, Z], [Z, Z, Z, Z, I]]
    Phi = jnp.concatenate([jnp.concatenate(r, -1) for r in rows], -2)
    P15 = {k: bm(X) for k, X in zip(P15_KEYS, P)}
    P15[3, 3] = bm(d3)[:, None, :] * eye
    P15[4, 4] = bm(d4)[:, None, :] * eye
    P9 = {k: bm(X) for k, X in zip(P9_KEYS, S)}
    return dict(q=last(q), dv=dv, dp=dp, t=t, Phi=Phi, Q15=_dense(P15, 5), Q9=_dense(P9, 3))


def _frame(R, n, k):
    """``blockdiag(R × k, I)`` of size n (``R`` on the first k 3-blocks)."""
    eye = jnp.broadcast_to(jnp.eye(n, dtype=R.dtype), R.shape[:-2] + (n, n))
    for i in range(k):
        eye = eye.at[..., 3 * i:3 * i + 3, 3 * i:3 * i + 3].set(R)
    return eye


def _combine(a, b, rotate=True):
    """Summary ``a`` then ``b`` (``b`` in the end frame of ``a``), as
    :func:`jaximu.preintegration.compose`: ``b`` is moved to ``a``'s frame by
    ``T = blockdiag(R, R, R, I, I)`` (``θ'``, p, v all rotate) and composed. With
    ``rotate=False`` both are already in the same frame (plain composition)."""
    deltas = lambda s: (s["q"], s["dp"], s["dv"], s["t"])  # noqa: E731
    if rotate:
        R = quat_to_matrix(a["q"])
        T = _frame(R, 15, 3)
        T9 = T[..., :9, :9]
        Fb = T @ b["Phi"] @ _t(T)
        Qb15, Qb9 = T @ b["Q15"] @ _t(T), T9 @ b["Q9"] @ _t(T9)
        q, dp, dv, t = compose_deltas(deltas(a), deltas(b),
                                      lambda x: jnp.einsum("...ij,...j->...i", R, x))
    else:  # the same frame: the sums of compose_deltas without a rotation
        Fb, Qb15, Qb9, q = b["Phi"], b["Q15"], b["Q9"], a["q"]
        dv, dp, t = (a["dv"] + b["dv"], (a["dp"] + a["dv"] * b["t"][..., None]) + b["dp"],
                     a["t"] + b["t"])
    F9 = Fb[..., :9, :9]
    return dict(q=q, dv=dv, dp=dp, t=t, Phi=Fb @ a["Phi"],
                Q15=_sym(Fb @ a["Q15"] @ _t(Fb) + Qb15), Q9=_sym(F9 @ a["Q9"] @ _t(F9) + Qb9))


def _identity_summary(like):
    out = jax.tree_util.tree_map(jnp.zeros_like, like)
    out["q"] = out["q"].at[..., 0].set(1)
    out["Phi"] = jnp.broadcast_to(jnp.eye(15, dtype=out["Phi"].dtype), out["Phi"].shape)
    return out


def _fold(s, axis, rotate=True):
    """Sequential composition along ``axis`` (a ``lax.scan``; the other axes are lanes)."""
    first = jax.tree_util.tree_map(lambda x: jnp.take(x, 0, axis=axis), s)
    rest = jax.tree_util.tree_map(
        lambda x: jnp.moveaxis(jax.lax.slice_in_dim(x, 1, x.shape[axis], axis=axis), axis, 0), s)
    return jax.lax.scan(lambda c, x: (_combine(c, x, rotate), None), first, rest)[0]


def _reduce_chunks(s, C, rotate=True):
    """Compose the ``C`` chunk summaries along axis 1 (``(B, C, ...)``): two sequential folds
    over a ``C1 × C2`` grid (``C2 ≈ √C``), i.e. ~2√C dependent steps, each over many lanes."""
    C2 = int(np.ceil(np.sqrt(C)))
    C1 = -(-C // C2)
    if C1 * C2 > C:
        ident = _identity_summary(jax.tree_util.tree_map(lambda x: x[:, :C1 * C2 - C], s))
        s = jax.tree_util.tree_map(lambda x, y: jnp.concatenate([x, y], 1), s, ident)
    s = jax.tree_util.tree_map(lambda x: x.reshape(x.shape[:1] + (C1, C2) + x.shape[2:]), s)
    s = _fold(s, 2, rotate) if C2 > 1 else jax.tree_util.tree_map(lambda x: x[:, :, 0], s)
    return _fold(s, 1, rotate) if C1 > 1 else jax.tree_util.tree_map(lambda x: x[:, 0], s)


def _finish(s):
    """Summary in θ' coordinates -> ``(t, q, dv, dp, Φ, Q15, Q9)`` of the generic code: the
    θ rows (and columns) are rotated back with ``ΔR_ijᵀ``."""
    Rt = _t(quat_to_matrix(s["q"]))
    T = _frame(Rt, 15, 1)
    T9 = T[..., :9, :9]
    return (s["t"], quat_normalize(s["q"]), s["dv"], s["dp"], T @ s["Phi"],
            _sym(T @ s["Q15"] @ _t(T)), _sym(T9 @ s["Q9"] @ _t(T9)))


# ----------------------------------------------------------------------------- driver


def _run_blocked(block, gyro, accel, dt, b_g, b_a, var, lever):
    """:func:`jaximu.kernels.soa.run_blocked` of ``block(gyro, accel, dt, b_g, b_a, var, lever)``
    over the lanes: a ``dt`` ``(T,)``, biases ``(3,)``, variances ``(12,)`` or a lever arm
    ``(3,)`` (or ``None``) shared by all lanes are read whole by every block."""
    shared = (dt.ndim == 1,) + tuple(x is None or x.ndim == 1 for x in (b_g, b_a, var, lever))
    return run_blocked(block, gyro.shape[0], block_lanes(gyro.dtype), gyro, accel, dt, b_g, b_a,
                       var, lever, whole=(False, False) + shared)


def num_chunks(B, T, method, dtype):
    """Time chunks per sequence: 1 for ``"sequential"``; for ``"parallel"`` enough to fill
    about one batch block of lanes, each chunk at least :data:`MIN_CHUNK` samples long (a
    divisor of T within 1/16 of that is preferred: less padding). A block's step costs
    nearly as much with fewer lanes: the padded steps of a full block cost less than
    lanes left empty (one window of 10^5 float64 samples, measured before chunks were
    padded to whole kernel time chunks: 64 chunks with 32 padded steps 9.9 M samples/s,
    50 chunks of 2000 9.1 M)."""
    lanes = block_lanes(dtype)
    if method != "parallel" or B >= lanes or T < 2 * MIN_CHUNK:
        return 1
    C = int(max(1, min(-(-lanes // B), T // MIN_CHUNK)))
    for c in range(C, C - C // 16 - 1, -1):
        if T % c == 0:
            return c
    return C


def preintegrate_euler(gyro, accel, dt, b_g, b_a, var, C, lever=None, jacobians="analytic",
                       isotropic_accel=False):
    """Flat batch: gyro, accel ``(B, T, 3)``; dt ``(T,)`` or ``(B, T)``; b_g, b_a ``(3,)`` or
    ``(B, 3)``; var ``(12,)`` or ``(B, 12)`` (σ² per axis); ``C`` time chunks per sequence;
    ``lever``: ``None``, ``(3,)`` or ``(B, 3)``, the lever arm of samples moved from a sensor;
    ``jacobians``: ``"analytic"`` or ``"autodiff"`` (:func:`step`); ``isotropic_accel``: the
    accelerometer's white-noise variances (``var[..., 3:6]``) are equal on every axis
    (:func:`step`).

    Returns ``(t, q, dv, dp, Φ, Q15, Q9)`` with leading axis B, as the generic code."""
    B, T, _ = gyro.shape
    dtype = gyro.dtype
    guard = False
    if C > 1:
        (gyro, accel, dt, (b_g, b_a, var, lever)), guard = _as_chunks(
            C, gyro, accel, jnp.broadcast_to(dt, (B, T)), (b_g, b_a, var, lever))

    def block(gyro, accel, dt, b_g, b_a, var, lever):
        Bc = gyro.shape[0]
        bg, ba, s = _components(b_g), _components(b_a), _components(var)
        r = None if lever is None else _components(lever)

        def st(c, w, a, h, consts):
            omega = tuple(w[i] - bg[i] for i in range(3))
            f = tuple(a[i] - ba[i] for i in range(3))
            return step(c, omega, f, h, s, guard, r, jacobians, isotropic_accel)

        carry, _ = _time_chunks(st, _zero_carry(Bc, dtype), gyro, accel, dt, None, None)
        return _to_summary(carry)

    summ = _run_blocked(block, gyro, accel, dt, b_g, b_a, var, lever)
    if C > 1:
        summ = jax.tree_util.tree_map(lambda x: x.reshape((B, C) + x.shape[1:]), summ)
        summ = _reduce_chunks(summ, C)
    return _finish(summ)



KERNELS = {"euler": preintegrate_euler, "midpoint": preintegrate_midpoint}
"""The structure-of-arrays kernel of each scheme's preintegration step
(:data:`jaximu.schemes._preintegration_steps.PREINTEGRATION_STEPS`, by the same name)."""
