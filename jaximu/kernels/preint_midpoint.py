"""One VINS-Mono midpoint preintegration step on lanes (its first-order ``F`` and non-unit
quaternion, in the original error coordinates; :mod:`jaximu.kernels.fast_preint`), with the
p rows = h/2 × v rows structure of its blocks.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaximu.geometry.so3 import quat_mul_components
from jaximu.kernels.lane_directions import (
    direction_block,
    jvp_directions,
    lane_directions,
    rotation_rows,
    rotation_tangents,
)
from jaximu.kernels.lane_math import (
    _E3,
    SOA,
    _bmm,
    _bt,
    _diag_row,
    _lane,
    _quat_normalize,
    _quat_rotate,
    _skew3,
    _stage,
    quat_matrix,
)
from jaximu.kernels.preint_euler import P9_KEYS, P15_KEYS, _lever_rk, _zero_carry
from jaximu.schemes._blocks import sym


def _sym(X):
    """``(X + Xᵀ)/2`` of a ``(3, 3, B)`` block: :func:`jaximu.schemes._blocks.sym` on lanes."""
    return sym(X, SOA)


# ----------------------------------------------------------------------------- VINS midpoint
#
# VINS-Mono's midPointIntegration in the original error coordinates (its first-order F is not
# a rotation, so the rotated coordinates do not simplify it). Its p rows are h/2 × its v rows
# (Cp = h/2 Cv, Dp = h/2 Dv, Ep = h/2 Ev, and the same for the noise), which halves the work.
# The carried transition has all eight blocks.


def _mid_lane(q, dv, dp, t, omega, f0, f1, h):
    """Stage 1 (per lane): the mean update, VINS-Mono's unnormalised ``q ⊗ [1, ω̄h/2]``."""
    dq = (jnp.ones_like(h) if jnp.ndim(h) else jnp.ones_like(q[0]),) + tuple(
        0.5 * h * w for w in omega
    )
    q1u = quat_mul_components(q, dq)
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
    tq_w, tv_w = jvp_directions(
        lambda w: mean(q, w), (omega,), (lane_directions(np.eye(3), dtype, lanes),)
    )

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
    M0 = (
        _bmm(A, P[0, 0]) + _b_times(B, _bt(P[0, 3]), h),
        _bmm(A, P[0, 1]) + _b_times(B, _bt(P[1, 3]), h),
        _bmm(A, P[0, 2]) + _b_times(B, _bt(P[2, 3]), h),
        _bmm(A, P[0, 3]) + _b_times(B, I3 * d3[None], h),
    )
    N = (
        _bmm(Cv, P[0, 0]) + _bmm(Dv, _bt(P[0, 3])),
        _bmm(Cv, P[0, 1]) + _bmm(Dv, _bt(P[1, 3])) + _bmm(Ev, _bt(P[1, 4])),
        _bmm(Cv, P[0, 2]) + _bmm(Dv, _bt(P[2, 3])) + _bmm(Ev, _bt(P[2, 4])),
        _bmm(Cv, P[0, 3]) + Dv * d3[None],
        Ev * d4[None],
    )
    return M0, N


def _mid_cov_b(M0, M1, M2, A, B, Cv, Dv, Ev, h):
    Cvt, Dvt, Evt = _bt(Cv), _bt(Dv), _bt(Ev)
    K = (_bmm(M0[0], Cvt) + _bmm(M0[3], Dvt),) + tuple(
        _bmm(M[0], Cvt) + _bmm(M[3], Dvt) + _bmm(M[4], Evt) for M in (M1, M2)
    )
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


def mid_step(
    carry, w0, a0, w1, a1, h, s, q_given=None, guard=False, lever=None, jacobians="analytic"
):
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
        RK = _stage(ok, lambda R0, R1: (_lever_rk(R0, w0, lever), _lever_rk(R1, w1, lever)), R0, R1)
    Dv, Ev, Qtt, Qv, Qtv = _stage(ok, _mid_blocks2, A, B, Cv, Dr, R0, R1, h, var[0:3], var[3:6], RK)
    dtype = q[0].dtype
    hb = _lane(h)
    half = 0.5 * hb

    # transition Φ ← F Φ (F.Cp = h/2 F.Cv, F.Dp = h/2 F.Dv, F.Ep = h/2 F.Ev)
    XA, XB, AA, AB = _stage(
        ok,
        lambda A, Cv, Ac, Bc: (_bmm(Cv, Ac), _bmm(Cv, Bc), _bmm(A, Ac), _bmm(A, Bc)),
        A,
        Cv,
        Ac,
        Bc,
    )
    I3 = jnp.asarray(_E3, dtype)[:, :, None]
    Phi1 = (
        AA,
        AB + (-hb * I3 if B is None else B),
        (half * XA + Cpc) + hb * Cvc,
        XA + Cvc,
        ((half * XB + Dpc) + hb * Dvc) + half * Dv,
        (XB + Dvc) + Dv,
        (Epc + hb * Evc) + half * Ev,
        Evc + Ev,
    )

    # 15×15 covariance
    Pd = dict(zip(P15_KEYS, P))
    M0, N = _stage(ok, _mid_cov_a, P, d3, d4, A, B, Cv, Dv, Ev, h)
    M1 = tuple(
        (Pd[1, j] if j >= 1 else _bt(Pd[0, 1]))
        + hb * (Pd[2, j] if j >= 2 else _bt(Pd[j, 2]))
        + half * N[j]
        for j in range(5)
    )
    M2 = tuple((Pd[2, j] if j >= 2 else _bt(Pd[j, 2])) + N[j] for j in range(5))
    M1, M2 = _stage(ok, lambda a, b: (tuple(x * 1 for x in a), tuple(x * 1 for x in b)), M1, M2)
    (K0, K1, K2), C00 = _stage(ok, _mid_cov_b, M0, M1, M2, A, B, Cv, Dv, Ev, h)
    new = {
        (0, 0): _sym(C00 + Qtt),
        (0, 1): ((M0[1] + hb * M0[2]) + half * K0) + half * Qtv,
        (0, 2): (M0[2] + K0) + Qtv,
        (0, 3): M0[3],
        (1, 1): _sym(((M1[1] + hb * M1[2]) + half * K1) + (half * half) * Qv),
        (1, 2): (M1[2] + K1) + half * Qv,
        (1, 3): M1[3],
        (1, 4): M1[4],
        (2, 2): _sym((M2[2] + K2) + Qv),
        (2, 3): M2[3],
        (2, 4): M2[4],
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
        _sym(C900 + Qtt),
        ((L0[1] + hb * L0[2]) + half * K90) + half * Qtv,
        (L0[2] + K90) + Qtv,
        _sym(((L11 + hb * L12) + half * K91) + (half * half) * Qv),
        (L12 + K91) + half * Qv,
        _sym((L22 + K92) + Qv),
    )
    return (q1, dv1, dp1, t1, Phi1, tuple(new[k] for k in P15_KEYS), d3n, d4n, S1)


def _zero_carry_mid(Bc, dtype):
    q, dv, dp, t, _, P, d3, d4, S = _zero_carry(Bc, dtype)
    Z = jnp.zeros((3, 3, Bc), dtype)
    I = jnp.broadcast_to(jnp.asarray(_E3, dtype)[:, :, None], (3, 3, Bc))
    return (q, dv, dp, t, (I,) + (Z,) * 7, P, d3, d4, S)
