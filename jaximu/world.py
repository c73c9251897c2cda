"""The rotating world: Earth's rate and the Coriolis / centrifugal terms (one home).

A world frame W fixed to the Earth (east-north-up, z up) turns with the Earth's rate
``ω_W`` relative to inertial space. A gyroscope measures the body's rate relative to
inertial space, ``ω_IB = ω_WB + R_WBᵀ ω_W``, and in W the velocity obeys

    v̇ = R f + g_W - 2 ω_W × v - ω_W × (ω_W × p),   Ṙ = R [ω_IB]x - [ω_W]x R

(Coriolis and centrifugal accelerations; ``g_W`` is the gravity the user passes). GTSAM calls
``ω_W`` ``omegaCoriolis`` and keeps only the Coriolis term unless ``use2ndOrderCoriolis``;
jaximu uses its name and meaning: ``omega_coriolis=`` ``(3,)`` [rad/s] in W, with
``coriolis_second_order=False`` by default (centrifugal term off: a user whose ``g_W`` is
the local apparent gravity, which already holds it, keeps it off).

:func:`coriolis_increments` is the one home of the discretised terms over a step ``Δt`` from
a state ``(p, v)``: the world-frame rotation ``-ω_W Δt``, position ``-ω_W×v Δt²`` and velocity
``-2 ω_W×v Δt`` (plus ``-½ Δt² ω×(ω×p)`` and ``-Δt ω×(ω×p)`` at second order). These are
GTSAM's ``NavState::coriolis`` (its ``dP`` drops a factor 2 against an INS text: it is the
exact ``½ a Δt²`` of the Coriolis acceleration ``a = -2ω×v``). :func:`jaximu.predict` adds
them to the preintegrated tangent as GTSAM's ``correctPIM`` does; :func:`jaximu.propagate`
applies them after each scheme step (``R ← Exp(-ω_W Δt) R``, ``p``, ``v`` incremented at the
step's end state), a first-order splitting whose error per unit time is
``O(|ω_W| |f| Δt)`` (about 1e-6 m/s² at Earth's rate and 200 Hz).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaximu import _validation as val
from jaximu import so3

__all__ = ["EARTH_RATE", "earth_rate", "coriolis_increments", "check_omega"]

EARTH_RATE = 7.292115e-5
"""Earth's sidereal rotation rate [rad/s] (WGS-84)."""


def earth_rate(latitude_deg, dtype=None):
    """Earth's rotation rate in the local east-north-up world (z up) at ``latitude_deg``.

    ``ω_W = Ω [0, cos φ, sin φ]`` with ``Ω =`` :data:`EARTH_RATE`; ``latitude_deg`` in
    ``[-90, 90]`` (scalar or ``(...,)``). Returns ``(..., 3)`` [rad/s], for ``omega_coriolis=``.
    """
    lat = np.asarray(latitude_deg, float) if val.is_concrete(latitude_deg) else None
    if lat is not None and (not np.all(np.isfinite(lat)) or np.any(np.abs(lat) > 90)):
        raise ValueError(f"latitude_deg must be in [-90, 90] degrees, got {latitude_deg!r}")
    phi = jnp.deg2rad(jnp.asarray(latitude_deg, dtype))
    return EARTH_RATE * jnp.stack([jnp.zeros_like(phi), jnp.cos(phi), jnp.sin(phi)], -1)


def check_omega(omega, dtype, name="omega_coriolis"):
    """``omega_coriolis`` as a finite ``(..., 3)`` ``dtype`` array (``ValueError`` naming it)."""
    w = val.to_dtype(name, omega, dtype)
    if w.ndim < 1 or w.shape[-1] != 3:
        raise ValueError(f"{name} must be the world's rotation rate, a (3,) vector in rad/s "
                         f"(e.g. jaximu.earth_rate(latitude_deg)), got shape {tuple(w.shape)}")
    val.check_finite(name, w)
    return w


def coriolis_increments(omega, p, v, dt, second_order: bool = False):
    """World-frame increments of the rotating world over a step (GTSAM's ``coriolis``).

    Args:
        omega: ``(..., 3)`` world rotation rate ``ω_W`` [rad/s] in W.
        p, v: ``(..., 3)`` position [m] and velocity [m/s] in W.
        dt: ``(...,)`` step [s].
        second_order: include the centrifugal terms.

    Returns:
        ``(dθ, dp, dv)`` in W, each ``(..., 3)``: ``dθ = -ω Δt`` (the attitude becomes
        ``Exp(dθ) R``), ``dp = -Δt² ω×v [- ½Δt² ω×(ω×p)]``, ``dv = -2Δt ω×v [- Δt ω×(ω×p)]``.
    """
    h = jnp.asarray(dt)[..., None]
    wxv = jnp.cross(omega, v)
    dth = -h * omega
    dp = -(h * h) * wxv
    dv = -2.0 * h * wxv
    if second_order:
        wwp = jnp.cross(omega, jnp.cross(omega, p))
        dp = dp - 0.5 * h * h * wwp
        dv = dv - h * wwp
    dth = jnp.broadcast_to(dth, jnp.broadcast_shapes(dth.shape, dp.shape))
    return dth, dp, dv


def coriolis_transition(omega, dt, second_order: bool = False):
    """``∂(p⁺, v⁺)/∂(p, v)`` of ``(p + dp, v + dv)`` with :func:`coriolis_increments`:
    ``(..., 6, 6)``, rows and columns ``[p, v]`` (the increments are linear in ``p``, ``v``)."""
    h = jnp.asarray(dt)[..., None, None]
    W = so3.skew(omega)
    eye = jnp.eye(3, dtype=W.dtype)
    s = 1.0 if second_order else 0.0
    W2 = W @ W
    top = jnp.concatenate(jnp.broadcast_arrays(eye - 0.5 * s * h * h * W2, -(h * h) * W), -1)
    bot = jnp.concatenate(jnp.broadcast_arrays(-s * h * W2, eye - 2.0 * h * W), -1)
    return jnp.concatenate([top, bot], -2)

