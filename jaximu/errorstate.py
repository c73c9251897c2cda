"""Error-state transition ``Φ``, noise Jacobian ``G``, process noise ``Q_d``, covariance propagation.

Error state ``δ = [dθ, dp, dv, db_g, db_a]`` (15), rotation error on the right
(``R = R̂ Exp(dθ)``); step noise ``n = [n_g, n_a, n_wg, n_wa]`` (12, see :mod:`jaximu.noise`).
For one step ``x⁺ = f(x, n)``:

    Φ = ∂ (f(x̂ ⊞ δ, 0) ⊟ f(x̂, 0)) / ∂δ,    G = ∂ (f(x̂, n) ⊟ f(x̂, 0)) / ∂n,
    P⁺ = Φ P Φᵀ + G Q_c Gᵀ,                  Q_c = diag(σ_g², σ_a², σ_bg², σ_ba²) / dt.

Two ways to get ``Φ`` and ``G``, tested equal:

* ``"autodiff"``: ``jax.jacfwd`` through ``boxplus``/``boxminus`` of the step function; any
  scheme and attitude form. The reference.
* ``"analytic"``: closed forms (OpenVINS / Solà) for the exact-exponential forms
  (``"quaternion"``, ``"matrix"``). With the stages of :mod:`jaximu.integrators`
  (``R_s = R̂ Exp(φ_s)``, ``u_s = R_s f_s``):

      Φ_θθ = Exp(φ_end)ᵀ            Φ_θbg = Jr(φ_end) ∂φ_end/∂b_g
      Φ_vθ = -[Σ wv_s u_s]x R̂       Φ_pθ = -[Σ wp_s u_s]x R̂      Φ_pv = dt I
      Φ_vbg = -Σ wv_s R_s [f_s]x Jr(φ_s) ∂φ_s/∂b_g      (zero for Euler)
      Φ_vba = -Σ wv_s R_s            (p rows: the same with wp_s)
      G = [[Φ_θbg, 0, 0, 0], [Φ_pbg, Φ_pba, 0, 0], [Φ_vbg, Φ_vba, 0, 0], [0, 0, dt I, 0], [0, 0, 0, dt I]]

  For Euler this is OpenVINS's discrete model (``Φ_θbg = -Jr(ω dt) dt``,
  ``Φ_vθ = -R̂ [f]x dt``, ``Φ_pθ = -½ R̂ [f]x dt²``, ``Φ_vba = -R̂ dt``, ``Φ_pba = -½ R̂ dt²``).

The analytic covariance update uses the block structure of ``Φ`` (identity and zero blocks,
a handful of 3×3 products on the upper blocks of the symmetric ``P``) instead of dense
15×15 products.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu import _validation as val
from jaximu import so3
from jaximu.integrators import Attitude, check_scheme, get_attitude, nav_step, stages, step
from jaximu.noise import ImuNoise
from jaximu.propagate import broadcast_state, mean_body, prepare, time_major
from jaximu.state import NavState, boxminus, boxplus

__all__ = [
    "step_jacobians",
    "discrete_process_noise",
    "propagate_covariance",
    "propagate_covariance_final",
    "JACOBIANS",
]

JACOBIANS = ("auto", "analytic", "autodiff")


# --------------------------------------------------------------------------- Jacobians


def jacobians_autodiff(scheme, att: Attitude, state: NavState, w0, a0, w1, a1, h, g):
    """``(Φ, G)`` of one step by ``jax.jacfwd`` through boxplus/boxminus; ``(..., 15, 15/12)``.

    The perturbation is shared by every batch element, so one forward pass with 27
    tangents gives the per-element Jacobians.
    """
    nominal = nav_step(scheme, att, state, w0, a0, w1, a1, h, g)
    dtype = state.q.dtype

    def f_delta(delta):
        return boxminus(nav_step(scheme, att, boxplus(state, delta), w0, a0, w1, a1, h, g), nominal)

    def f_noise(n):
        return boxminus(nav_step(scheme, att, state, w0, a0, w1, a1, h, g, noise=n), nominal)

    Phi = jax.jacfwd(f_delta)(jnp.zeros(15, dtype))
    G = jax.jacfwd(f_noise)(jnp.zeros(12, dtype))
    return Phi, G


class Blocks(NamedTuple):
    """Non-trivial 3×3 blocks of ``Φ`` (``(..., 3, 3)``; ``None`` where zero)."""

    A: jax.Array  # θθ
    B: jax.Array  # θ b_g
    Cp: jax.Array  # p θ
    Cv: jax.Array  # v θ
    Dp: jax.Array | None  # p b_g
    Dv: jax.Array | None  # v b_g
    Ep: jax.Array  # p b_a
    Ev: jax.Array  # v b_a


def mm(X, Y):
    """(Batched) 3×3 product."""
    return jnp.matmul(X, Y)


def _wsum(terms):
    terms = [t for t in terms if t is not None]
    out = terms[0]
    for t in terms[1:]:
        out = out + t
    return out


def blocks_analytic(scheme, R0, omega0, f0, omega1, f1, h) -> Blocks:
    """Closed-form blocks of ``Φ`` for the exact-exponential forms (module docstring).

    Args:
        R0: ``(..., 3, 3)`` attitude ``R̂`` at the start of the step.
        omega0, f0, omega1, f1: bias-corrected samples k and k+1, ``(..., 3)``.
        h: ``(...,)`` step [s].
    """
    stage_list, phi_end, dphi_end = stages(scheme, omega0, f0, omega1, f1, h)
    A = jnp.swapaxes(so3.exp_matrix(phi_end), -1, -2)
    B = mm(so3.right_jacobian(phi_end), dphi_end)
    uv, up, Dv, Dp, Ev, Ep = [], [], [], [], [], []
    for s in stage_list:
        R_s = R0 if s.phi is None else mm(R0, so3.exp_matrix(s.phi))
        u = jnp.einsum("...ij,...j->...i", R_s, s.f)
        wv, wp = s.wv[..., None, None], s.wp[..., None, None]
        uv.append(s.wv[..., None] * u)
        up.append(s.wp[..., None] * u)
        Ev.append(-wv * R_s)
        Ep.append(-wp * R_s)
        if s.phi is not None:
            D = -mm(mm(R_s, so3.skew(s.f)), mm(so3.right_jacobian(s.phi), s.dphi_dbg))
            Dv.append(wv * D)
            Dp.append(wp * D)
    Cv = -mm(so3.skew(_wsum(uv)), R0)
    Cp = -mm(so3.skew(_wsum(up)), R0)
    return Blocks(A, B, Cp, Cv, _wsum(Dp) if Dp else None, _wsum(Dv) if Dv else None,
                  _wsum(Ep), _wsum(Ev))


def dense_from_blocks(b: Blocks, h):
    """Assemble ``Φ`` ``(..., 15, 15)`` and ``G`` ``(..., 15, 12)`` from the blocks."""
    batch = jnp.broadcast_shapes(b.A.shape[:-2], b.Cv.shape[:-2], b.Ev.shape[:-2], h.shape)
    dtype = b.A.dtype
    Z = jnp.zeros(batch + (3, 3), dtype)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), batch + (3, 3))
    hI = h[..., None, None] * eye
    Dp = Z if b.Dp is None else b.Dp
    Dv = Z if b.Dv is None else b.Dv

    def bc(x):
        return jnp.broadcast_to(x, batch + (3, 3))

    rows = [
        [b.A, Z, Z, b.B, Z],
        [b.Cp, eye, hI, Dp, b.Ep],
        [b.Cv, Z, eye, Dv, b.Ev],
        [Z, Z, Z, eye, Z],
        [Z, Z, Z, Z, eye],
    ]
    Phi = jnp.concatenate([jnp.concatenate([bc(x) for x in r], -1) for r in rows], -2)
    grows = [
        [b.B, Z, Z, Z],
        [Dp, b.Ep, Z, Z],
        [Dv, b.Ev, Z, Z],
        [Z, Z, hI, Z],
        [Z, Z, Z, hI],
    ]
    G = jnp.concatenate([jnp.concatenate([bc(x) for x in r], -1) for r in grows], -2)
    return Phi, G


def step_jacobians(state: NavState, gyro, accel, dt, *, gyro_next=None, accel_next=None,
                   scheme: str = "euler", attitude: str = "quaternion", gravity=9.81,
                   method: str = "autodiff"):
    """``Φ`` and ``G`` of one propagation step at ``state``.

    Args:
        state: linearisation point (fields ``(..., 4)``/``(..., 3)``).
        gyro, accel: ``(..., 3)`` raw sample k; ``gyro_next``, ``accel_next``: sample k+1
            (midpoint, RK4; default: sample k held).
        dt: ``(...,)`` step [s].
        method: ``"autodiff"`` or ``"analytic"`` (exact-exponential attitude forms only).

    Returns:
        ``(Φ, G)``: ``(..., 15, 15)`` and ``(..., 15, 12)``.
    """
    check_scheme(scheme)
    att = get_attitude(attitude)
    val.require_navstate(state)
    dtype = val.float_dtype(state.q, gyro, accel)
    state = val.check_state(state, dtype)
    w0, a0 = jnp.asarray(gyro, dtype), jnp.asarray(accel, dtype)
    w1 = w0 if gyro_next is None else jnp.asarray(gyro_next, dtype)
    a1 = a0 if accel_next is None else jnp.asarray(accel_next, dtype)
    for name, x in (("gyro", w0), ("accel", a0), ("gyro_next", w1), ("accel_next", a1)):
        val.check_vector(name, x, time_axis=False)
        val.check_finite(name, x)
    h = jnp.asarray(dt, dtype)
    if val.is_concrete(h) and not np.all(np.asarray(h) > 0):
        raise ValueError(f"dt must be positive and finite, got {np.asarray(h)}")
    g = val.gravity_vector(gravity, dtype)
    if method == "autodiff":
        return jacobians_autodiff(scheme, att, state, w0, a0, w1, a1, h, g)
    if method == "analytic":
        _require_analytic(att)
        b = blocks_analytic(scheme, state.R, w0 - state.b_g, a0 - state.b_a, w1 - state.b_g,
                            a1 - state.b_a, h)
        return dense_from_blocks(b, h)
    raise ValueError(f"unknown Jacobian method {method!r}; choose 'autodiff' or 'analytic'")


def _require_analytic(att: Attitude):
    if not att.exact_exponential:
        raise ValueError(
            f"analytic Jacobians are derived for the exact-exponential attitude forms "
            f"('quaternion', 'matrix'), not {att.name!r}; use jacobians='autodiff'"
        )


def discrete_process_noise(G, noise: ImuNoise, dt):
    """``Q_d = G Q_c Gᵀ`` with ``Q_c = noise.discrete_covariance(dt)``. ``(..., 15, 15)``."""
    qc = noise.discrete_variances(dt, G.dtype)
    return (G * qc[..., None, :]) @ jnp.swapaxes(G, -1, -2)


# --------------------------------------------------------------------------- covariance


def _t(x):
    return jnp.swapaxes(x, -1, -2)


def _sym(x):
    return 0.5 * (x + _t(x))


_UPPER = [(i, j) for i in range(5) for j in range(i, 5)]


def dense_to_blocks(P):
    """The 15 upper 3×3 blocks ``{(i, j): P_ij}`` (i ≤ j, order θ, p, v, b_g, b_a)."""
    return {(i, j): P[..., 3 * i:3 * i + 3, 3 * j:3 * j + 3] for i, j in _UPPER}


def blocks_to_dense(Pb):
    def get(i, j):
        return Pb[(i, j)] if i <= j else _t(Pb[(j, i)])

    return jnp.concatenate(
        [jnp.concatenate([get(i, j) for j in range(5)], -1) for i in range(5)], -2
    )


def structured_update(Pb, b: Blocks, h, qc):
    """``Φ P Φᵀ + G Q_c Gᵀ`` on the upper blocks of ``P``, using the structure of ``Φ``.

    Args:
        Pb: upper blocks of ``P`` (see :func:`dense_to_blocks`).
        b: blocks of ``Φ``; h: ``(...,)`` step; qc: ``(..., 12)`` diagonal of ``Q_c``.
    """

    def P(i, j):
        return Pb[(i, j)] if i <= j else _t(Pb[(j, i)])

    def add(*terms):
        return _wsum(terms)

    def mmo(X, Y):
        return None if (X is None or Y is None) else mm(X, Y)

    hh = h[..., None, None]
    # M = Φ P, rows θ (0), p (1), v (2); rows b_g, b_a of M are those of P.
    M0 = {j: add(mm(b.A, P(0, j)), mm(b.B, P(3, j))) for j in range(5)}
    M1 = {j: add(P(1, j), hh * P(2, j), mm(b.Cp, P(0, j)), mmo(b.Dp, P(3, j)), mm(b.Ep, P(4, j)))
          for j in range(5)}
    M2 = {j: add(P(2, j), mm(b.Cv, P(0, j)), mmo(b.Dv, P(3, j)), mm(b.Ev, P(4, j))) for j in (0, 2, 3, 4)}
    Dpt = None if b.Dp is None else _t(b.Dp)
    Dvt = None if b.Dv is None else _t(b.Dv)
    At, Bt, Cpt, Cvt, Ept, Evt = _t(b.A), _t(b.B), _t(b.Cp), _t(b.Cv), _t(b.Ep), _t(b.Ev)

    def col_p(M):  # (M Φᵀ)_{·p}
        return add(M[1], hh * M[2], mm(M[0], Cpt), mmo(M[3], Dpt),
                   mm(M[4], Ept))

    def col_v(M):  # (M Φᵀ)_{·v}
        return add(M[2], mm(M[0], Cvt), mmo(M[3], Dvt), mm(M[4], Evt))

    sg, sa = qc[..., 0:3], qc[..., 3:6]
    sbg, sba = qc[..., 6:9], qc[..., 9:12]

    def xsy(X, s, Y):  # X diag(s) Yᵀ
        return None if (X is None or Y is None) else mm(X * s[..., None, :], _t(Y))

    new = {
        (0, 0): add(mm(M0[0], At), mm(M0[3], Bt), xsy(b.B, sg, b.B)),
        (0, 1): add(col_p(M0), xsy(b.B, sg, b.Dp)),
        (0, 2): add(col_v(M0), xsy(b.B, sg, b.Dv)),
        (0, 3): M0[3],
        (0, 4): M0[4],
        (1, 1): add(col_p(M1), xsy(b.Dp, sg, b.Dp), xsy(b.Ep, sa, b.Ep)),
        (1, 2): add(col_v(M1), xsy(b.Dp, sg, b.Dv), xsy(b.Ep, sa, b.Ev)),
        (1, 3): M1[3],
        (1, 4): M1[4],
        (2, 2): add(col_v(M2), xsy(b.Dv, sg, b.Dv), xsy(b.Ev, sa, b.Ev)),
        (2, 3): M2[3],
        (2, 4): M2[4],
        (3, 3): Pb[(3, 3)] + (hh * hh) * (sbg[..., :, None] * jnp.eye(3, dtype=sbg.dtype)),
        (3, 4): Pb[(3, 4)],
        (4, 4): Pb[(4, 4)] + (hh * hh) * (sba[..., :, None] * jnp.eye(3, dtype=sba.dtype)),
    }
    for i in range(5):
        new[(i, i)] = _sym(new[(i, i)])
    return new


def _check_cov(P0, dtype):
    P0 = jnp.asarray(P0, dtype)
    if P0.ndim < 2 or P0.shape[-2:] != (15, 15):
        raise ValueError(f"P0 must have shape (..., 15, 15), got {tuple(P0.shape)}")
    val.check_finite("P0", P0)
    if val.is_concrete(P0):
        arr = np.asarray(P0, np.float64)
        scale = max(1.0, float(np.abs(arr).max()))
        asym = np.abs(arr - np.swapaxes(arr, -1, -2)).max()
        if asym > 1e-6 * scale:
            raise ValueError(f"P0 is not symmetric (max |P - Pᵀ| = {asym:.3g})")
        min_eig = np.linalg.eigvalsh(0.5 * (arr + np.swapaxes(arr, -1, -2))).min()
        if min_eig < -1e-9 * scale:
            raise ValueError(f"P0 is not positive semi-definite (smallest eigenvalue {min_eig:.3g})")
    return P0


def _check_noise(noise, dtype):
    if not isinstance(noise, ImuNoise):
        raise ValueError(f"noise must be a jaximu.ImuNoise, got {type(noise).__name__}")
    fields = {}
    for name in ("gyroscope_noise_density", "accelerometer_noise_density",
                 "gyroscope_random_walk", "accelerometer_random_walk"):
        x = jnp.asarray(getattr(noise, name), dtype)
        if x.ndim > 0 and x.shape[-1] != 3:
            raise ValueError(f"noise.{name} must be a scalar or have shape (..., 3), got {tuple(x.shape)}")
        val.check_finite(f"noise.{name}", x)
        if val.is_concrete(x) and np.any(np.asarray(x) < 0):
            raise ValueError(f"noise.{name} must be non-negative, got {np.asarray(x)}")
        fields[name] = x
    return ImuNoise(**fields)


def _resolve_jacobians(jacobians, att):
    if jacobians not in JACOBIANS:
        raise ValueError(f"unknown jacobians {jacobians!r}; choose one of {JACOBIANS}")
    if jacobians == "auto":
        return "analytic" if att.exact_exponential else "autodiff"
    if jacobians == "analytic":
        _require_analytic(att)
    return jacobians


@functools.partial(jax.jit, static_argnames=("scheme", "attitude", "jacobians", "save_all", "unroll"))
def _propagate_covariance(state, P0, gyro, accel, dt, g, noise, *, scheme, attitude, jacobians,
                          save_all, unroll=1):
    att = get_attitude(attitude)
    nb = lambda x: x.shape[:-1] if x.ndim else ()  # noqa: E731
    batch = jnp.broadcast_shapes(
        state.batch_shape, P0.shape[:-2], gyro.shape[:-2], accel.shape[:-2], dt.shape[:-1],
        g.shape[:-1], *(nb(jnp.asarray(x)) for x in jax.tree_util.tree_leaves(noise)))
    state = broadcast_state(state, batch)
    P0 = jnp.broadcast_to(P0, tuple(batch) + (15, 15))
    xs = time_major(gyro, accel, dt, scheme)
    b_g, b_a = state.b_g, state.b_a
    mean = mean_body(scheme, att, b_g, b_a, g)

    def body(carry, xs):
        x, p, v, locked, Pc = carry
        w0, a0, w1, a1, h = xs
        qc = noise.discrete_variances(h, x.dtype)
        if jacobians == "analytic":
            b = blocks_analytic(scheme, att.to_matrix(x), w0 - b_g, a0 - b_a, w1 - b_g, a1 - b_a, h)
            Pn = structured_update(Pc, b, h, qc)
        else:
            lin = NavState(att.to_quat(x), p, v, b_g, b_a)
            Phi, G = jacobians_autodiff(scheme, att, lin, w0, a0, w1, a1, h, g)
            Pn = _sym(Phi @ Pc @ _t(Phi) + (G * qc[..., None, :]) @ _t(G))
        (x, p, v, locked), _ = mean((x, p, v, locked), xs)
        out = None
        if save_all:
            out = (att.to_quat(x), p, v, blocks_to_dense(Pn) if jacobians == "analytic" else Pn)
        return (x, p, v, locked, Pn), out

    P_init = dense_to_blocks(P0) if jacobians == "analytic" else P0
    carry0 = (att.from_quat(state.q), state.p, state.v, jnp.zeros(batch, bool), P_init)
    (x, p, v, locked, Pc), out = jax.lax.scan(body, carry0, xs, unroll=unroll)
    if save_all:
        T = gyro.shape[-2]
        q_t, p_t, v_t, P_t = out
        q_t, p_t, v_t = (jnp.moveaxis(y, 0, -2) for y in (q_t, p_t, v_t))
        P_t = jnp.moveaxis(P_t, 0, -3)
        bshape = tuple(batch) + (T, 3)
        states = NavState(q_t, p_t, v_t, jnp.broadcast_to(b_g[..., None, :], bshape),
                          jnp.broadcast_to(b_a[..., None, :], bshape))
        return states, P_t, locked
    P_final = blocks_to_dense(Pc) if jacobians == "analytic" else Pc
    return NavState(att.to_quat(x), p, v, b_g, b_a), P_final, locked


def _covariance_entry(state, P0, gyro, accel, dt, noise, scheme, attitude, gravity, jacobians,
                      save_all):
    from jaximu.propagate import _report_gimbal_lock

    state, gyro, accel, dt, g, _ = prepare(state, gyro, accel, dt, gravity, scheme, attitude)
    dtype = state.q.dtype
    P0 = _check_cov(P0, dtype)
    noise = _check_noise(noise, dtype)
    jac = _resolve_jacobians(jacobians, get_attitude(attitude))
    states, P, locked = _propagate_covariance(
        state, P0, gyro, accel, dt, g, noise, scheme=scheme, attitude=attitude, jacobians=jac,
        save_all=save_all)
    _report_gimbal_lock(locked, attitude)
    return states, P


def propagate_covariance(state: NavState, P0, gyro, accel, dt, noise: ImuNoise,
                         scheme: str = "euler", *, attitude: str = "quaternion", gravity=9.81,
                         jacobians: str = "auto"):
    """Propagate the state and its 15×15 error-state covariance through IMU samples.

    ``P⁺ = Φ P Φᵀ + G Q_c Gᵀ`` at every sample, linearised at the state before the step.

    Args:
        state, gyro, accel, dt, scheme, attitude, gravity: as :func:`jaximu.propagate`.
        P0: ``(..., 15, 15)`` symmetric PSD covariance of ``[dθ, dp, dv, db_g, db_a]`` at t_0.
        noise: :class:`ImuNoise` densities (fields may be batched ``(..., 3)``).
        jacobians: ``"analytic"`` (closed forms + block-structured update; exact-exponential
            forms), ``"autodiff"`` (``jax.jacfwd``; any form; dense update) or ``"auto"``
            (analytic where available).

    Returns:
        ``(states, covariances)``: a :class:`NavState` with fields ``batch + (T, ·)`` as
        :func:`jaximu.propagate`, and ``batch + (T, 15, 15)`` covariances (entry k after
        sample k), symmetric and positive semi-definite.
    """
    return _covariance_entry(state, P0, gyro, accel, dt, noise, scheme, attitude, gravity,
                             jacobians, save_all=True)


def propagate_covariance_final(state: NavState, P0, gyro, accel, dt, noise: ImuNoise,
                               scheme: str = "euler", *, attitude: str = "quaternion",
                               gravity=9.81, jacobians: str = "auto"):
    """Like :func:`propagate_covariance`, returning only the final state and ``(..., 15, 15)`` covariance."""
    return _covariance_entry(state, P0, gyro, accel, dt, noise, scheme, attitude, gravity,
                             jacobians, save_all=False)
