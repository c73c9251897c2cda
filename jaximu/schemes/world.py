"""The rotating world: Earth's rate, the exact rotating-frame transition and GTSAM's
classic Coriolis terms (the one home of both).

A world frame W fixed to the Earth (east-north-up, z up) turns at ``ω_W`` relative to
inertial space. A gyroscope measures the body's rate relative to inertial space,
``ω_IB = ω_WB + R_WBᵀ ω_W``, and in W

    Ṙ = R [ω_IB]x - [ω_W]x R,    v̇ = R f + g_W - 2 ω_W × v - ω_W × (ω_W × p),    ṗ = v

(Coriolis and centrifugal accelerations; ``g_W`` the gravity the user passes, constant in
W). GTSAM calls ``ω_W`` ``omegaCoriolis``; jaximu uses its name and meaning
(``omega_coriolis=``, ``(3,)`` [rad/s] in W; :func:`earth_rate` gives Earth's).

**Exact transition** (the default, ``coriolis_exact=True``; GTSAM ≥ 4.3, after Brossard,
Barrau & Bonnabel). In the inertial frame I that coincides with W at the start of an
interval, ``x_I(t) = Exp(ω t) x_W(t)``: the body obeys the still-world equations with the
transported velocity ``v̄ = v + ω × p`` and a gravity that turns, ``Exp(ω t) g_W``. So a
step (or a preintegrated window) of length ``T`` is

    v̄ = v + ω×p                                  (:func:`to_inertial`)
    (R', p', v̄') = the still-world step from (R, p, v̄) with the constant g_W
    v̄' += T (J_l(ωT) - I) g_W,  p' += T² (Γ₂(ωT) - ½ I) g_W      (the turning gravity)
    R⁺ = Exp(-ωT) R',  p⁺ = Exp(-ωT) p',  v⁺ = Exp(-ωT) v̄' - ω×p⁺   (:func:`leave_inertial`)

with ``J_l(φ) = Σ [φ]xⁿ/(n+1)!`` (SO(3)'s left Jacobian) and ``Γ₂(φ) = Σ [φ]xⁿ/(n+2)!``
(:func:`gamma2`). Exact for a constant ``ω_W``: the rotating world adds no error to a
scheme, whose order it keeps. Coriolis and centrifugal are both in it
(``coriolis_second_order`` is inert, as in GTSAM ≥ 4.3).

**Classic additive terms** (``coriolis_exact=False``; GTSAM ≤ 4.2's ``NavState::coriolis``
in ``correctPIM``): :func:`coriolis_increments` over ``Δt`` from ``(p, v)``: rotation
``-ω Δt``, position ``-ω×v Δt²``, velocity ``-2 ω×v Δt``, plus ``-½ Δt² ω×(ω×p)`` and
``-Δt ω×(ω×p)`` with ``coriolis_second_order``. :func:`jaximu.predict` adds them to the
preintegrated tangent as ``correctPIM`` does; :func:`jaximu.propagate` applies them after
each scheme step at its end state (``R ← Exp(-ωΔt) R``), a first-order splitting.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaximu.geometry import _checks as val
from jaximu.geometry import so3
from jaximu.geometry._vec import V3, matmul, matvec, matvec_v3
from jaximu.schemes import _blocks as blk

__all__ = [
    "EARTH_RATE",
    "earth_rate",
    "coriolis_increments",
    "check_omega",
    "gamma2",
    "to_inertial",
    "leave_inertial",
    "enter_inertial",
    "gravity_excess",
]

EARTH_RATE = 7.292115e-5
"""Earth's sidereal rotation rate [rad/s] (WGS-84)."""


def earth_rate(latitude_deg, dtype=None):
    """Earth's rotation rate in the local east-north-up world (z up) at ``latitude_deg``.

    ``ω_W = Ω [0, cos φ, sin φ]`` with ``Ω =`` :data:`EARTH_RATE`; ``latitude_deg`` in
    degrees, ``[-90, 90]``, finite (scalar or ``(...,)``; checked on eager calls, not inside
    a caller's ``jit``). ``dtype``: float32, float64 (needs ``jax_enable_x64``) or ``None``
    (JAX's default float). Returns ``(..., 3)`` [rad/s], for ``omega_coriolis=``.
    """
    dtype = jnp.result_type(float) if dtype is None else val.compute_dtype("dtype", dtype)
    lat_in = latitude_deg
    latitude_deg = val.to_dtype("latitude_deg", latitude_deg, dtype)
    if val.is_concrete(lat_in):
        lat = np.asarray(lat_in, np.float64)
        bad = ~np.isfinite(lat) | (np.abs(lat) > 90)
        if bad.any():
            where = val._first_bad(bad) if lat.ndim else ""
            raise ValueError(
                f"latitude_deg must be in [-90, 90] degrees and finite, got "
                f"latitude_deg{where} = {lat[tuple(np.argwhere(bad)[0])]:g}"
            )
    phi = jnp.deg2rad(latitude_deg)
    return EARTH_RATE * jnp.stack([jnp.zeros_like(phi), jnp.cos(phi), jnp.sin(phi)], -1)


def check_omega(omega, dtype, name="omega_coriolis"):
    """``omega_coriolis`` as a finite ``(..., 3)`` ``dtype`` array (``ValueError`` naming it)."""
    w = val.to_dtype(name, omega, dtype)
    if w.ndim < 1 or w.shape[-1] != 3:
        raise ValueError(
            f"{name} must be the world's rotation rate, a (3,) vector in rad/s "
            f"(e.g. jaximu.earth_rate(latitude_deg)), got shape {tuple(w.shape)}"
        )
    val.check_finite(name, w)
    return w


# --------------------------------------------------------------------------- exact


def gamma2(phi):
    """``Γ₂(φ) = Σ_n [φ]xⁿ / (n+2)! = ½ I + b [φ]x + e [φ]x²`` with ``b = (θ - sin θ)/θ³``,
    ``e = (θ²/2 + cos θ - 1)/θ⁴`` (Taylor series near 0). ``(..., 3) -> (..., 3, 3)``.
    ``∫₀ᵀ∫₀ˢ Exp(ω u) du ds = T² Γ₂(ωT)``."""
    theta_sq = jnp.sum(phi * phi, axis=-1)
    a, b, _ = so3._jacobian_coeffs(phi)  # a = (1 - cos θ)/θ²
    small = theta_sq < 1e-2
    safe = jnp.where(small, jnp.ones_like(theta_sq), theta_sq)
    t2 = theta_sq
    e = jnp.where(small, 1 / 24 - t2 / 720 + t2 * t2 / 40320 - t2**3 / 3628800, (0.5 - a) / safe)
    K = so3.skew(phi)
    eye = jnp.eye(3, dtype=phi.dtype)
    return 0.5 * eye + b[..., None, None] * K + e[..., None, None] * so3._skew_sq(phi)


# The per-element formulas below are written once on V3 (components: ``(...,)`` arrays or the
# ``(B,)`` lanes of the structure-of-arrays kernels, docs/DESIGN.md "kernel layout"); the
# public functions take and return ``(..., 3)`` arrays and call them.


def to_inertial_v3(omega: V3, p: V3, v: V3) -> V3:
    """:func:`to_inertial` on components."""
    return v + omega.cross(p)


def to_inertial(omega, p, v):
    """The transported velocity ``v̄ = v + ω × p`` (velocity in the inertial frame that
    coincides with W now)."""
    return to_inertial_v3(V3.of(omega), V3.of(p), V3.of(v)).stack()


def gravity_excess(omega, dt, g):
    """What the turning gravity adds over ``dt`` beyond a constant ``g``, in the inertial
    frame of the start: ``(dp, dv) = (T²(Γ₂(ωT) - ½I) g, T (J_l(ωT) - I) g)``."""
    T = jnp.asarray(dt)[..., None]
    phi = omega * T
    eye = jnp.eye(3, dtype=phi.dtype)
    dv = T * matvec(so3.left_jacobian(phi) - eye, g)
    dp = T * T * matvec(gamma2(phi) - 0.5 * eye, g)
    return dp, dv


def leave_inertial_terms(omega, dt, g):
    """What :func:`leave_inertial` needs of ``(ω, dt, g)`` alone (per step, not per state):
    ``(dθ, Q, dp, dv)`` with ``dθ = -ω dt`` ``(..., 3)``, ``Q = Exp(dθ)`` ``(..., 3, 3)`` and
    the turning gravity's ``(dp, dv)`` (:func:`gravity_excess`)."""
    dp, dv = gravity_excess(omega, dt, g)
    dth = -jnp.asarray(dt)[..., None] * omega
    return dth, so3.exp_matrix(dth), dp, dv


def leave_inertial_v3(omega: V3, Q, dp: V3, dv: V3, p: V3, v: V3):
    """:func:`leave_inertial` on components, from :func:`leave_inertial_terms`:
    ``p⁺ = Q (p' + dp)``, ``v⁺ = Q (v̄' + dv) - ω × p⁺``."""
    p1 = matvec_v3(Q, p + dp)
    return p1, matvec_v3(Q, v + dv) - omega.cross(p1)


def leave_inertial(omega, dt, g, p, v):
    """From the inertial frame of the start back to W after ``dt``, the turning gravity
    added: returns ``(dθ, p⁺, v⁺)`` with ``R⁺ = Exp(dθ) R'``, ``dθ = -ω dt``."""
    dth, Q, dp, dv = leave_inertial_terms(omega, dt, g)
    p1, v1 = leave_inertial_v3(V3.of(omega), Q, V3.of(dp), V3.of(dv), V3.of(p), V3.of(v))
    return dth, p1.stack(), v1.stack()


def enter_inertial(omega, dt, g, p, v):
    """The inverse of :func:`leave_inertial` (same returns: ``R' = Exp(-dθ) R⁺``)."""
    dp, dv = gravity_excess(omega, dt, g)
    dth = -jnp.asarray(dt)[..., None] * omega
    Qt = jnp.swapaxes(so3.exp_matrix(dth), -1, -2)
    return dth, matvec(Qt, p) - dp, matvec(Qt, v + jnp.cross(omega, p)) - dv


def error_map_rows(omega, dt, coriolis):
    """The error-state maps of a step in the turning world, as the 3×3 blocks of the rows
    that differ from the identity (order ``[θ, p, v, b_g, b_a]``, blocks 0–4): ``{row:
    {column: (..., 3, 3)}}``, the string ``"I"`` for an identity block, for
    :func:`jaximu.schemes._blocks.congruence`. Returns ``(Pre, Post)``, the maps before and after the
    still-world step's ``Φ`` (``Pre`` ``None`` when there is none).

    * ``coriolis="exact"``: ``Pre`` of :func:`to_inertial`, ``δv̄ = δv + [ω]x δp``; ``Post``
      of :func:`leave_inertial`, ``δp⁺ = Q δp'``, ``δv⁺ = Q δv̄' - [ω]x Q δp'`` with
      ``Q = Exp(-ω dt)``.
    * ``"first_order"`` / ``"second_order"``: ``Post`` is ``∂(p⁺, v⁺)/∂(p, v)`` of
      ``(p + dp, v + dv)`` with :func:`coriolis_increments` (linear in ``p``, ``v``).

    The rotation error is on the right, so the rotations on the left (``Exp(-ω dt) R``)
    leave its rows alone.
    """
    W = so3.skew(omega)
    h = jnp.asarray(dt)[..., None, None]
    if coriolis == "exact":
        Q = so3.exp_matrix(-jnp.asarray(dt)[..., None] * omega)
        return {2: {1: W, 2: "I"}}, {1: {1: Q}, 2: {1: -matmul(W, Q), 2: Q}}
    eye = jnp.eye(3, dtype=W.dtype)
    cross = -(h * h) * W
    if coriolis == "second_order":
        W2 = so3._skew_sq(omega)
        return None, {
            1: {1: eye - 0.5 * h * h * W2, 2: cross},
            2: {1: -h * W2, 2: eye - 2.0 * h * W},
        }
    return None, {1: {1: "I", 2: cross}, 2: {2: eye - 2.0 * h * W}}


def error_maps(omega, h, coriolis, ops=blk.ARRAYS):
    """:func:`error_map_rows` with the blocks in the layout ``ops`` (made as arrays from
    ``omega`` ``(..., 3)`` and ``h``, then converted: ``ops.from_arrays``)."""
    pre, post = error_map_rows(omega, h, coriolis)
    if ops is not blk.ARRAYS:
        pre, post = (
            None
            if m is None
            else {
                i: {k: (x if isinstance(x, str) else ops.from_arrays(x)) for k, x in r.items()}
                for i, r in m.items()
            }
            for m in (pre, post)
        )
    return pre, post


def covariance_step(
    Pb, b, qc, omega, h, coriolis, ops=blk.ARRAYS, p_over_v=None, maps=None, qc_scale=None
):
    """The covariance step in a turning world (:mod:`jaximu.world`), on block-structured
    ``Pb``: ``Post (Φ (Pre P Preᵀ) Φᵀ + G Q Gᵀ) Postᵀ`` with the still-world step's ``Φ``
    between the error maps of :func:`error_map_rows` (exact transition: into
    and out of the step's inertial frame; classic terms: no ``Pre``, ``Post`` the increments'
    ``[p, v]`` Jacobian), each applied as a block congruence (:func:`jaximu.schemes._blocks.congruence`).
    ``ops``: the block layout (the maps' blocks are made as arrays from ``omega``
    ``(..., 3)`` and ``h``, then converted: ``ops.from_arrays``); ``p_over_v``: as
    :func:`jaximu.schemes._blocks.structured_update`, as is ``qc_scale``; ``maps``:
    :func:`error_maps`' result when the caller has it."""
    pre, post = error_maps(omega, h, coriolis, ops) if maps is None else maps
    if pre is not None:
        Pb = blk.congruence(Pb, pre, ops)
    return blk.congruence(blk.structured_update(Pb, b, qc, ops, p_over_v, qc_scale), post, ops)


# --------------------------------------------------------------------------- classic


def coriolis_increments(omega, p, v, dt, second_order: bool = False):
    """World-frame increments of GTSAM ≤ 4.2's classic model over a step (``coriolis``).

    Args:
        omega: ``(..., 3)`` world rotation rate ``ω_W`` [rad/s] in W.
        p, v: ``(..., 3)`` position [m] and velocity [m/s] in W.
        dt: ``(...,)`` step [s].
        second_order: include the centrifugal terms.

    Returns:
        ``(dθ, dp, dv)`` in W, each ``(..., 3)``: ``dθ = -ω Δt`` (the attitude becomes
        ``Exp(dθ) R``), ``dp = -Δt² ω×v [- ½Δt² ω×(ω×p)]``, ``dv = -2Δt ω×v [- Δt ω×(ω×p)]``.
    """
    dth, dp, dv = coriolis_increments_v3(
        V3.of(omega), V3.of(p), V3.of(v), jnp.asarray(dt), second_order
    )
    dp, dv = dp.stack(), dv.stack()
    dth = dth.stack()
    return jnp.broadcast_to(dth, jnp.broadcast_shapes(dth.shape, dp.shape)), dp, dv


def coriolis_increments_v3(omega: V3, p: V3, v: V3, h, second_order: bool = False):
    """:func:`coriolis_increments` on components; ``h`` the step, ``(...,)`` or a scalar."""
    wxv = omega.cross(v)
    dth = omega * (-h)
    dp = wxv * (-(h * h))
    dv = wxv * (-2.0 * h)
    if second_order:
        wwp = omega.cross(omega.cross(p))
        dp = dp - wwp * (0.5 * h * h)
        dv = dv - wwp * h
    return dth, dp, dv
