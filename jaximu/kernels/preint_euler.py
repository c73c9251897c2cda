"""One Euler (Forster / GTSAM) preintegration step on lanes, in the rotated error coordinates of
:mod:`jaximu.kernels.fast_preint` (where the algebra is explained): the step's blocks, analytic
or by autodiff, its noise, and the covariance products that the block structure leaves.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaximu.geometry import sensor
from jaximu.geometry._vec import V3
from jaximu.geometry.so3 import quat_mul_components
from jaximu.kernels.fast import blocks_autodiff
from jaximu.kernels.lane_math import (
    _E3,
    _THR,
    SOA,
    _any_big,
    _bmm,
    _bt,
    _cond,
    _diag_row,
    _half_any,
    _half_small,
    _jr_b_small,
    _lane,
    _outer,
    _quat_renormalize,
    _quat_rotate,
    _rows,
    _skew3,
    _stage,
    quat_matrix,
)
from jaximu.schemes._blocks import sym
from jaximu.schemes.integrators import get_scheme


def _sym(X):
    """``(X + Xᵀ)/2`` of a ``(3, 3, B)`` block: :func:`jaximu.schemes._blocks.sym` on lanes."""
    return sym(X, SOA)


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
            b = jnp.where(
                sm,
                _jr_b_small(jnp.where(sm, t2, 0.0)),
                (1.0 - 2.0 * k * c) / jnp.where(sm, 1.0, t2),
            )
        else:
            c, k = _half_small(t2)
            b = _jr_b_small(t2)
        q1 = _quat_renormalize(quat_mul_components(q, (c, k * phi[0], k * phi[1], k * phi[2])))
        dp1 = tuple((dp[i] + dv[i] * h) + 0.5 * u[i] * h * h for i in range(3))
        dv1 = tuple(dv[i] + u[i] * h for i in range(3))
        return (q1, dv1, dp1, t + h), (u, phi, t2, k, b)

    return f


def _rot_jl(q, phi, t2, k, b):
    """Stage 2a: ``R = R(q)`` and ``Jl(φ)`` as ``(3, 3, B)``."""
    dtype = q[0].dtype
    I3 = jnp.asarray(_E3, dtype)[:, :, None]
    phi3 = _rows(phi, dtype)
    Jl = (
        I3
        + _lane(2.0 * (k * k)) * _skew3(phi, dtype)
        + _lane(b) * (_outer(phi3, phi3) - _lane(t2) * I3)
    )
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
    _, b = blocks_autodiff(
        get_scheme("euler"),
        q,
        V3(*dp),
        V3(*dv),
        w,
        f,
        w,
        f,
        h,
        zero,
        None if lever is None else V3(*lever),
        world_error=True,
    )
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
P15_KEYS = ((0, 0), (0, 1), (0, 2), (0, 3), (1, 1), (1, 2), (1, 3), (1, 4), (2, 2), (2, 3), (2, 4))


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
    return (_bmm(M00, Cvt), _bmm(M10, Cvt) + _bmm(M14, Evt), _bmm(M20, Cvt) + _bmm(M24, Evt))


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


def step(carry, omega, fsp, h, s, guard, lever=None, jacobians="analytic", isotropic_accel=False):
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
        _any_big(t2), _lane_scalars(True), _lane_scalars(False), q, dv, dp, t, omega, fsp, h
    )
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
        Ev, Bk, Cv, Dk = _stage(
            ok, lambda *a: _autodiff_blocks(*a, lever), q, dv, dp, omega, fsp, h
        )
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
    Phi1 = (
        Bacc + Bk,
        (Dp + hb * Dv) + half * X,
        Dv + X,
        (Ep + hb * Ev_acc) + half * Ev,
        Ev_acc + Ev,
    )

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
    M10, M11, M12, M13, M14 = _stage(
        ok, lambda *a: tuple(x * 1 for x in a), M10, M11, M12, M13, M14
    )
    K0, K1, K2 = _stage(ok, _cov15_b, M10, M14, M20, M24, M00, Cv, Ev)
    if Dk is not None:  # and the v columns M_i3 Dkᵀ
        Dkt = _bt(Dk)
        K0, K1, K2 = K0 + _bmm(M03, Dkt), K1 + _bmm(M13, Dkt), K2 + _bmm(M23, Dkt)
    new = {
        (0, 0): _sym((M00 + _bmm(M03, _bt(Bk))) + Qth),
        (0, 1): (M01 + hb * M02) + half * K0,
        (0, 2): M02 + K0,
        (0, 3): M03,
        (1, 1): _sym(((M11 + hb * M12) + half * K1) + (half * half) * Qv),
        (1, 2): (M12 + K1) + half * Qv,
        (1, 3): M13,
        (1, 4): M14,
        (2, 2): _sym((M22 + K2) + Qv),
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
        _sym(Sd[0, 0] + Qth),
        (Sd[0, 1] + hb * Sd[0, 2]) + half * K90,
        Sd[0, 2] + K90,
        _sym(((L11 + hb * L12) + half * K91) + (half * half) * Qv),
        (L12 + K91) + half * Qv,
        _sym((L22 + K92) + Qv),
    )
    if Qtv is not None:
        S1 = (S1[0], S1[1] + half * Qtv, S1[2] + Qtv) + S1[3:]
    return (q1, dv1, dp1, t1, Phi1, tuple(new[k] for k in P15_KEYS), d3n, d4n, S1)


def _zero_carry(Bc, dtype):
    z = jnp.zeros((Bc,), dtype)
    Z = jnp.zeros((3, 3, Bc), dtype)
    z3 = jnp.zeros((3, Bc), dtype)
    q = (jnp.ones((Bc,), dtype), z, z, z)
    return (q, (z, z, z), (z, z, z), z, (Z,) * 5, (Z,) * len(P15_KEYS), z3, z3, (Z,) * len(P9_KEYS))
