"""One propagation step for each scheme and attitude form.

Continuous model (docs/DESIGN.md): ``Ṙ = R [ω]x``, ``v̇ = R f + g_W``, ``ṗ = v``, with the
bias-corrected rate ``ω = w_m - b_g`` and specific force ``f = a_m - b_a``; the biases are
constant in the mean (their random walk has zero mean).

Sample ``k`` is held over ``[t_k, t_k + dt_k)``. Each scheme is written as a few *stages*:
rotation vectors ``φ_s`` at which the attitude is evaluated, the specific force ``f_s``
there, and weights so that

    R⁺ = R ⊞ φ_end,   v⁺ = v + Σ_s wv_s a_s,   p⁺ = p + v dt + Σ_s wp_s a_s,
    a_s = (R ⊞ φ_s) f_s + g_W.

=========  ===============================================  ==========================
scheme     stages                                           order (inputs linear in t)
=========  ===============================================  ==========================
euler      zero-order hold on sample k (OpenVINS discrete,  1
           GTSAM's Forster recursion): φ = ω_k dt
midpoint   VINS-Mono: φ = ½(ω_k + ω_k+1) dt, accelerations  2
           at both ends averaged
rk4        ω, f linear between samples k and k+1; φ(τ) is   4
           the two-term Magnus expansion (exact Ω₁, Ω₂ for
           a linear rate, "coning" term τ³/(12dt) ω_k×ω_k+1);
           Simpson/RK4 weights on the accelerations
=========  ===============================================  ==========================

The attitude form decides what ``R ⊞ φ`` means:

* ``"quaternion"``: exact exponential ``q ⊗ Exp(φ)`` (the Θ(Δt) of docs/DESIGN.md), renormalised
  so that rounding cannot let ``|q|`` drift;
* ``"quaternion_first_order"``: ``normalize(q ⊗ [1, φ/2])``; an angle error θ³/12 per
  step, so attitude is at most second order whatever the scheme;
* ``"matrix"``: ``R Exp(φ)`` on a rotation matrix carried through the scan (no
  re-orthonormalisation, so its drift from SO(3) can be studied);
* ``"euler_angles"``: ZYX angles, ``χ ← χ + E(χ) φ`` (with ``"rk4"``, classical RK4 on
  ``χ̇ = E(χ) ω(t)``). Singular at pitch ±90°.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import jax

from jaximu.geometry import sensor, so3
from jaximu.geometry._vec import V3, matvec, matvec_v3
from jaximu.geometry.state import NavState
from jaximu.schemes import _blocks as blk
from jaximu.schemes._blocks import Blocks, add

__all__ = [
    "SCHEMES",
    "ATTITUDES",
    "ORDER",
    "Attitude",
    "Scheme",
    "get_attitude",
    "get_scheme",
    "step",
    "nav_step",
]

SCHEMES = ("euler", "midpoint", "rk4")
ATTITUDES = ("quaternion", "quaternion_first_order", "matrix", "euler_angles")
ORDER = {"euler": 1, "midpoint": 2, "rk4": 4}
"""Convergence order of each scheme when the inputs are linear between samples."""

# cos(pitch) below which the Euler-angle form is declared singular (0.08° from ±90°).
GIMBAL_LOCK_COS = 1e-3


@dataclasses.dataclass(frozen=True)
class Attitude:
    """How the orientation is carried through a scan, and how it is advanced."""

    name: str
    from_quat: Callable
    to_quat: Callable
    to_matrix: Callable
    rotate: Callable
    advance: Callable
    exact_exponential: bool


_ATTITUDE_FORMS = {
    "quaternion": Attitude(
        "quaternion",
        from_quat=lambda q: q,
        to_quat=lambda q: q,
        to_matrix=so3.quat_to_matrix,
        rotate=so3.quat_rotate,
        # Renormalised: without it rounding lets |q| drift (1 + 5e-4 after 1e5 float32
        # steps), and a non-unit q scales every rotated specific force.
        advance=lambda q, phi: so3.quat_normalize(so3.quat_mul(q, so3.exp(phi))),
        exact_exponential=True,
    ),
    "quaternion_first_order": Attitude(
        "quaternion_first_order",
        from_quat=lambda q: q,
        to_quat=lambda q: q,
        to_matrix=so3.quat_to_matrix,
        rotate=so3.quat_rotate,
        advance=so3.quat_first_order_update,
        exact_exponential=False,
    ),
    "matrix": Attitude(
        "matrix",
        from_quat=so3.quat_to_matrix,
        to_quat=so3.matrix_to_quat,
        to_matrix=lambda R: R,
        rotate=matvec,
        advance=lambda R, phi: R @ so3.exp_matrix(phi),
        exact_exponential=True,
    ),
    "euler_angles": Attitude(
        "euler_angles",
        from_quat=so3.quat_to_euler_zyx,
        to_quat=so3.euler_zyx_to_quat,
        to_matrix=so3.euler_zyx_to_matrix,
        rotate=lambda chi, v: matvec(so3.euler_zyx_to_matrix(chi), v),
        advance=lambda chi, phi: chi + matvec(so3.euler_rate_matrix(chi), phi),
        exact_exponential=False,
    ),
}


def get_attitude(name: str) -> Attitude:
    """The attitude form called ``name`` (one of :data:`ATTITUDES`)."""
    try:
        return _ATTITUDE_FORMS[name]
    except KeyError:
        raise ValueError(f"unknown attitude form {name!r}; choose one of {ATTITUDES}") from None


def check_scheme(scheme: str) -> str:
    if scheme not in SCHEMES:
        raise ValueError(f"unknown scheme {scheme!r}; choose one of {SCHEMES}")
    return scheme


END = "end"
"""A stage's ``phi`` that means the attitude at the end of the step (computed once)."""


class Point(NamedTuple):
    """One evaluation point of a scheme inside the step, on :class:`~jaximu.geometry._vec.V3`s.

    ``phi`` is ``None`` at the start of the step (no rotation), :data:`END` at its end,
    or the rotation vector of an intermediate attitude; ``tau`` the fraction of the step at
    which it is taken (for the bias derivative of ``phi``). ``wv``, ``wp``: the weights of
    the acceleration ``(R ⊞ φ) f + g_W`` in ``v⁺`` and ``p⁺`` (module docstring).
    """

    phi: object
    tau: float
    f: V3
    wv: jax.Array
    wp: jax.Array


class Scheme:
    """A one-step scheme: its stages, written once on :class:`~jaximu.geometry._vec.V3` components so
    that the generic kernels (``(..., 3)`` arrays split into components) and the
    structure-of-arrays kernels (``(B,)`` lanes, :mod:`jaximu.kernels.soa`) run the same formulas.

    ``points(ω_k, f_k, ω_k+1, f_k+1, h) -> (list[Point], φ_end)`` with bias-corrected inputs
    and ``h`` broadcasting against the components; ``dphi_db(ω_k, ω_k+1, h, τ) -> (a, c)``
    the derivative of the stage rotation vector at ``τ`` with respect to a common gyro bias,
    ``a I + [c]x`` (``c`` is ``None`` when zero); :meth:`blocks` the closed-form blocks of
    the step's ``Φ`` from them, in any block layout.
    """

    name: str
    order: int
    uses_next_sample: bool

    def points(self, omega0, f0, omega1, f1, h):
        raise NotImplementedError

    def dphi_db(self, omega0, omega1, h, tau):
        return -h, None

    def p_over_v(self, h):
        """``s`` when every stage's ``wp = s wv`` (then ``Φ``'s p rows are ``s`` times its v
        rows beyond ``dt I``, and so are ``G``'s: :func:`jaximu.schemes._blocks.structured_update`
        forms them from the v rows), else ``None``. Euler and midpoint: ``h/2``."""
        return 0.5 * h

    def blocks(self, R0, omega0, f0, omega1, f1, h, ops, end=None, lever=None):
        """Closed-form blocks of ``Φ`` (exact-exponential attitude forms) in the layout
        ``ops`` (:data:`jaximu.schemes._blocks.ARRAYS` or :data:`jaximu.kernels.lane_math.SOA`). With the stages
        ``R_s = R̂ Exp(φ_s)``, ``u_s = R_s f_s`` (OpenVINS / Solà; docs/DESIGN.md):

            Φ_θθ = Exp(φ_end)ᵀ            Φ_θbg = Jr(φ_end) ∂φ_end/∂b_g
            Φ_vθ = -[Σ wv_s u_s]x R̂       Φ_pθ = -[Σ wp_s u_s]x R̂      Φ_pv = dt I
            Φ_vbg = -Σ wv_s R_s [f_s]x Jr(φ_s) ∂φ_s/∂b_g      (zero for Euler)
            Φ_vba = -Σ wv_s R_s            (p rows: the same with wp_s)

        Args:
            R0: the attitude ``R̂`` at the start of the step, a block of ``ops``.
            omega0, f0, omega1, f1: bias-corrected samples k and k+1 (:class:`V3`).
            h: step [s], per element.
            end: ``(Exp(φ_end), Jr(φ_end))`` when the caller has them (the mean step shares
                the end rotation's half angle).
            lever: the lever arm ``r`` (:class:`V3`, body frame [m]) when the samples are a
                sensor's moved to the body (:mod:`jaximu.sensor`): ``f_s`` then carries
                ``-ω×(ω×r)`` of the samples it interpolates, and the b_g column gains
                ``Σ w_s R_s K_s`` with ``K_s = (1-τ_s) K(ω_k) + τ_s K(ω_k+1)``
                (:func:`jaximu.sensor.centripetal_jacobian`), exact for every scheme.

        Returns:
            :class:`jaximu.schemes._blocks.Blocks`.
        """
        pts, phi_end = self.points(omega0, f0, omega1, f1, h)
        # ops.barrier: values read by several products are computed once (SoA: XLA:CPU would
        # recompute them inside every consumer; docs/DESIGN.md "Kernel layout")
        R0, E_end, J_end = ops.barrier((R0, *(ops.exp_jr(phi_end) if end is None else end)))

        def times_dphi(X, tau):  # X ∂φ(τ)/∂b_g = a X + X [c]x
            a, c = self.dphi_db(omega0, omega1, h, tau)
            out = ops.scale(a, X)
            return out if c is None else out + ops.matmul(X, ops.skew(c))

        if lever is not None:
            K0 = sensor.centripetal_jacobian(omega0, lever, ops)
            K1 = sensor.centripetal_jacobian(omega1, lever, ops) if self.uses_next_sample else K0
            K0, K1 = ops.barrier((K0, K1))

        uv, up, Dv, Dp, Ev, Ep = [], [], [], [], [], []
        for pt in pts:
            if pt.phi is None:
                R_s, J_s = R0, None
            elif pt.phi is END:
                R_s, J_s = ops.barrier(ops.matmul(R0, E_end)), J_end
            else:
                E_s, J_s = ops.barrier(ops.exp_jr(pt.phi))
                R_s = ops.barrier(ops.matmul(R0, E_s))
            u = ops.matvec(R_s, pt.f)
            uv.append(u * pt.wv)
            up.append(u * pt.wp)
            Ev.append(ops.scale(-pt.wv, R_s))
            Ep.append(ops.scale(-pt.wp, R_s))
            D = None
            if J_s is not None:
                D = -ops.matmul(ops.matmul(R_s, ops.skew(pt.f)), times_dphi(J_s, pt.tau))
            if lever is not None:  # f_s moves by +K_s δb_g (the rate falls by δb_g)
                K_s = (
                    K0
                    if pt.tau == 0.0
                    else K1
                    if pt.tau == 1.0
                    else (1.0 - pt.tau) * K0 + pt.tau * K1
                )
                D = add(D, ops.matmul(R_s, K_s))
            if D is not None:
                Dv.append(ops.scale(pt.wv, D))
                Dp.append(ops.scale(pt.wp, D))
        sum_v = functools.reduce(lambda a, b: a + b, uv)
        sum_p = functools.reduce(lambda a, b: a + b, up)
        return Blocks(
            A=ops.transpose(E_end),
            B=times_dphi(J_end, 1.0),
            Cp=-ops.matmul(ops.skew(sum_p), R0),
            Cv=-ops.matmul(ops.skew(sum_v), R0),
            Dp=add(*Dp),
            Dv=add(*Dv),
            Ep=add(*Ep),
            Ev=add(*Ev),
            dt=h,
        )


class Euler(Scheme):
    """Zero-order hold on sample k (OpenVINS discrete, GTSAM's Forster recursion)."""

    name, order, uses_next_sample = "euler", 1, False

    def points(self, omega0, f0, omega1, f1, h):
        return [Point(None, 0.0, f0, h, 0.5 * h * h)], h * omega0


class Midpoint(Scheme):
    """VINS-Mono: rate averaged over the step, accelerations at both ends averaged."""

    name, order, uses_next_sample = "midpoint", 2, True

    def points(self, omega0, f0, omega1, f1, h):
        phi = (0.5 * h) * (omega0 + omega1)
        hh = 0.25 * h * h
        return [Point(None, 0.0, f0, 0.5 * h, hh), Point(END, 1.0, f1, 0.5 * h, hh)], phi


class RK4(Scheme):
    """ω, f linear between samples; two-term Magnus rotation; Simpson/RK4 weights."""

    name, order, uses_next_sample = "rk4", 4, True

    @staticmethod
    def magnus(omega0, omega1, alpha, h):
        """``Ω(τ) = τ ω0 + τ²/(2h)(ω1 - ω0) + τ³/(12h) ω0 × ω1`` at ``τ = alpha h`` (exact
        Ω₁ + Ω₂ for a rate linear from ω0 to ω1 over ``h``), written without dividing by
        ``h`` so that a zero step is an exact identity with finite derivatives."""
        return (
            (alpha * h) * omega0
            + (alpha * alpha * 0.5 * h) * (omega1 - omega0)
            + (alpha**3 / 12 * h * h) * omega0.cross(omega1)
        )

    def points(self, omega0, f0, omega1, f1, h):
        phi_half = self.magnus(omega0, omega1, 0.5, h)
        phi_end = self.magnus(omega0, omega1, 1.0, h)
        return [
            Point(None, 0.0, f0, h / 6, h * h / 6),
            Point(phi_half, 0.5, 0.5 * (f0 + f1), 4 * h / 6, 2 * h * h / 6),
            Point(END, 1.0, f1, h / 6, 0.0 * h),
        ], phi_end

    def p_over_v(self, h):
        return None  # Simpson weights: wp/wv is h, h/2 and 0 along the stages

    def dphi_db(self, omega0, omega1, h, tau):
        """``-τ I + τ³/(12h) [ω1 - ω0]x`` with ``τ = tau · h``."""
        return -(tau * h), (omega1 - omega0) * (tau**3 / 12 * h * h)


SCHEME_OBJECTS = {s.name: s for s in (Euler(), Midpoint(), RK4())}


def get_scheme(name: str) -> Scheme:
    """The scheme called ``name`` (one of :data:`SCHEMES`)."""
    try:
        return SCHEME_OBJECTS[check_scheme(name)]
    except KeyError:  # pragma: no cover - check_scheme raised already
        raise


def rk4_euler_angles(deriv, chi: V3, p: V3, v: V3, omega0: V3, f0: V3, omega1: V3, f1: V3, h):
    """Classical RK4 on ``(χ, p, v)`` with ω, f linear inside the step (the ``"euler_angles"``
    form's RK4), written once on :class:`V3` components for both layouts: the generic
    kernels' (:func:`_rk4_euler_angles`) and the lanes' (``jaximu.kernels.lane_forms``).

    ``deriv(χ, ω, f) -> (χ̇, a)``: the layout's angle rates ``E(χ) ω`` and acceleration
    ``R(χ) f + g``. ``h``: the step [s], per element (a scalar or the components' shape).
    """
    # a V3 on the left of each product: h may be an array of lanes
    omega_m, f_m = (omega0 + omega1) * 0.5, (f0 + f1) * 0.5
    k1, a1 = deriv(chi, omega0, f0)
    k2, a2 = deriv(chi + k1 * (0.5 * h), omega_m, f_m)
    k3, a3 = deriv(chi + k2 * (0.5 * h), omega_m, f_m)
    k4, a4 = deriv(chi + k3 * h, omega1, f1)
    chi1 = chi + (k1 + k2 * 2 + k3 * 2 + k4) * (h / 6)
    v1 = v + (a1 + a2 * 2 + a3 * 2 + a4) * (h / 6)
    p1 = p + v * h + (a1 + a2 + a3) * (h * h / 6)
    return chi1, p1, v1


def _rk4_euler_angles(chi, p, v, omega0, f0, omega1, f1, h, g):
    """:func:`rk4_euler_angles` on ``(..., 3)`` arrays, the angles' rates and rotation from
    :mod:`jaximu.so3`."""
    g = V3.of(g)

    def deriv(c, w, f):
        cs = c.stack()
        return (
            matvec_v3(so3.euler_rate_matrix(cs), w),
            matvec_v3(so3.euler_zyx_to_matrix(cs), f) + g,
        )

    out = rk4_euler_angles(deriv, *(V3.of(x) for x in (chi, p, v, omega0, f0, omega1, f1)), h)
    return tuple(x.stack() for x in out)


def step(scheme, attitude: Attitude, x, p, v, omega0, f0, omega1, f1, h, g):
    """Advance ``(x, p, v)`` over one sample.

    Args:
        scheme: one of :data:`SCHEMES` (static).
        attitude: the attitude form (static); ``x`` is in its representation.
        x: attitude in the form's representation (``(..., 4)``, ``(..., 3, 3)`` or ``(..., 3)``).
        p, v: ``(..., 3)`` position and velocity in W.
        omega0, f0: ``(..., 3)`` bias-corrected body rate [rad/s] and specific force [m/s²]
            of sample k.
        omega1, f1: the same for sample k+1 (ignored by ``"euler"``).
        h: ``(...,)`` step length [s].
        g: ``(..., 3)`` gravity in W [m/s²].

    Returns:
        ``(x⁺, p⁺, v⁺)``.
    """
    if scheme == "rk4" and attitude.name == "euler_angles":
        return _rk4_euler_angles(x, p, v, omega0, f0, omega1, f1, h, g)
    pts, phi_end = get_scheme(scheme).points(V3.of(omega0), V3.of(f0), V3.of(omega1), V3.of(f1), h)
    x_end = attitude.advance(x, phi_end.stack())
    p1, v1 = stage_sum(
        pts,
        x,
        x_end,
        lambda x, phi: attitude.advance(x, phi.stack()),
        lambda x, f: V3.of(attitude.rotate(x, f.stack())),
        V3.of(p),
        V3.of(v),
        h,
        V3.of(g),
    )
    return x_end, p1.stack(), v1.stack()


def stage_sum(points, x, x_end, advance, rotate, p: V3, v: V3, h, g: V3):
    """``p⁺``, ``v⁺`` of a step from its stages, in any layout (the one home of the sum):

        v⁺ = v + Σ_s wv_s a_s,   p⁺ = p + v h + Σ_s wp_s a_s,   a_s = (R ⊞ φ_s) f_s + g_W,

    with ``x`` the attitude at the start, ``x_end`` at the end, ``advance(x, φ)`` and
    ``rotate(x, f)`` the layout's ``R ⊞ φ`` and ``R f`` (:class:`~jaximu.geometry._vec.V3` vectors)."""
    v1, p1 = v, p + v * h
    for pt in points:
        if pt.phi is None:
            xs = x
        elif pt.phi is END:
            xs = x_end
        else:
            xs = advance(x, pt.phi)
        a = rotate(xs, pt.f) + g
        v1 = v1 + a * pt.wv
        p1 = p1 + a * pt.wp
    return p1, v1


def compose_deltas(a, b, rotate=None):
    """Interval ``a`` then interval ``b``, each as its deltas ``(Δq, Δp, Δv, Δt)`` in its own
    start frame (quaternion ``(..., 4)``, vectors ``(..., 3)``, ``Δt`` ``(...)``), gravity
    free: ``(Δq_a ⊗ Δq_b, Δp_a + Δv_a Δt_b + ΔR_a Δp_b, Δv_a + ΔR_a Δv_b, Δt_a + Δt_b)``, the
    product normalised. The composition of preintegrated intervals (Forster et al. 2017), and
    of the time chunks of a long sequence; associative, so it reduces as a tree or a
    parallel prefix scan. ``rotate``: ``x -> ΔR_a x`` when the caller holds ``ΔR_a`` as a
    matrix anyway (default: the rotation by ``Δq_a``)."""
    qa, pa, va, ta = a
    qb, pb, vb, tb = b
    rot = rotate or (lambda x: so3.quat_rotate(qa, x))
    return (
        so3.quat_normalize(so3.quat_mul(qa, qb)),
        pa + va * tb[..., None] + rot(pb),
        va + rot(vb),
        ta + tb,
    )


def apply_deltas(q, p, v, g, deltas):
    """The state ``(q, p, v)`` moved by an interval's gravity-free deltas ``(Δq, Δp, Δv, Δt)``
    (:func:`compose_deltas`) under gravity ``g``: ``(q ⊗ Δq, p + v Δt + ½ g Δt² + R Δp,
    v + g Δt + R Δv)`` (Forster et al. 2017; the quaternion product not renormalised).
    Quaternions ``(..., 4)``, vectors ``(..., 3)``, ``Δt`` ``(...)``."""
    dq, dp, dv, t = deltas
    t = t[..., None]
    return (
        so3.quat_mul(q, dq),
        p + v * t + 0.5 * g * t * t + so3.quat_rotate(q, dp),
        v + g * t + so3.quat_rotate(q, dv),
    )


def nav_step(scheme, attitude: Attitude, state: NavState, w0, a0, w1, a1, h, g, noise=None):
    """One step on a :class:`NavState` (quaternion in, quaternion out), with optional noise.

    Args:
        w0, a0, w1, a1: ``(..., 3)`` raw gyro/accel samples k and k+1.
        h: ``(...,)`` step [s]; g: ``(..., 3)`` gravity in W.
        noise: optional ``(..., 12)`` step noise ``[n_g, n_a, n_wg, n_wa]`` held over the step
            (see :mod:`jaximu.noise`): ``ω = w - b_g - n_g``, ``f = a - b_a - n_a``,
            ``b⁺ = b + n_w h``.

    This is the function whose Jacobians (through ``boxplus``/``boxminus``) are ``Φ`` and ``G``.
    """
    b_g, b_a = state.b_g, state.b_a
    n_g = n_a = 0.0
    if noise is not None:
        n_g, n_a = noise[..., 0:3], noise[..., 3:6]
    omega0, omega1 = w0 - b_g - n_g, w1 - b_g - n_g
    f0, f1 = a0 - b_a - n_a, a1 - b_a - n_a
    x, p, v = step(
        scheme,
        attitude,
        attitude.from_quat(state.q),
        state.p,
        state.v,
        omega0,
        f0,
        omega1,
        f1,
        h,
        g,
    )
    if noise is not None:
        b_g = b_g + h[..., None] * noise[..., 6:9]
        b_a = b_a + h[..., None] * noise[..., 9:12]
    return NavState(attitude.to_quat(x), p, v, b_g, b_a)


def blocks_analytic(scheme, R0, omega0, f0, omega1, f1, h, lever=None) -> Blocks:
    """Closed-form blocks of ``Φ`` for the exact-exponential forms on ``(..., 3, 3)`` arrays
    (:meth:`Scheme.blocks`, the one home of the formulas, in the array layout).

    Args:
        R0: ``(..., 3, 3)`` attitude ``R̂`` at the start of the step.
        omega0, f0, omega1, f1: bias-corrected samples k and k+1, ``(..., 3)``.
        h: ``(...,)`` step [s].
        lever: optional ``(..., 3)`` lever arm of samples moved to the body
            (:meth:`jaximu.integrators.Scheme.blocks`).
    """
    return get_scheme(scheme).blocks(
        R0,
        V3.of(omega0),
        V3.of(f0),
        V3.of(omega1),
        V3.of(f1),
        h,
        blk.ARRAYS,
        lever=None if lever is None else V3.of(lever),
    )
