"""Navigation state, IMU bias, and the 15-dim error state.

Conventions (docs/DESIGN.md): ``q`` is the Hamilton quaternion ``[w, x, y, z]`` of ``R_WB``
(body to world); ``p``, ``v`` are in the world frame W (z up); ``b_g``, ``b_a`` are in the
body frame B. The error state is ordered ``[dθ, dp, dv, db_g, db_a]``; the rotation error
is on the right (body frame), ``R = R̂ Exp(dθ)``, and the rest is additive. This equals
OpenVINS's left JPL error and GTSAM's ``retract`` on the rotation.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.geometry import so3
from jaximu.geometry._checks import check_batch_shape, check_finite, to_dtype
from jaximu.geometry._tolerances import check_unit_norm

__all__ = [
    "NavState",
    "ImuBias",
    "boxplus",
    "boxminus",
    "ERROR_STATE_DIM",
    "THETA",
    "POS",
    "VEL",
    "BG",
    "BA",
]

ERROR_STATE_DIM = 15
THETA = slice(0, 3)
"""Rotation error (rad, body frame) in the 15-dim error state."""
POS = slice(3, 6)
"""Position error (m, world frame)."""
VEL = slice(6, 9)
"""Velocity error (m/s, world frame)."""
BG = slice(9, 12)
"""Gyroscope bias error (rad/s, body frame)."""
BA = slice(12, 15)
"""Accelerometer bias error (m/s², body frame)."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class NavState:
    """Inertial navigation state; every field may carry leading batch (and time) axes.

    Attributes:
        q: ``(..., 4)`` unit quaternion ``[w, x, y, z]`` of ``R_WB``.
        p: ``(..., 3)`` position of the IMU in W [m].
        v: ``(..., 3)`` velocity of the IMU in W [m/s].
        b_g: ``(..., 3)`` gyroscope bias in B [rad/s] (``w_m = w_B + b_g + n_g``).
        b_a: ``(..., 3)`` accelerometer bias in B [m/s²] (``a_m = R_WBᵀ(a_W - g_W) + b_a + n_a``).
    """

    q: jax.Array | np.ndarray
    p: jax.Array | np.ndarray
    v: jax.Array | np.ndarray
    b_g: jax.Array | np.ndarray
    b_a: jax.Array | np.ndarray

    @classmethod
    def identity(cls, batch_shape=(), dtype=jnp.float32) -> NavState:
        """Identity attitude, zero position, velocity and biases."""
        batch_shape = check_batch_shape(batch_shape)
        z = jnp.zeros(batch_shape + (3,), dtype)
        return cls(so3.quat_identity(batch_shape, dtype), z, z, z, z)

    @property
    def R(self) -> jax.Array:
        """``(..., 3, 3)`` rotation matrix ``R_WB``."""
        return so3.quat_to_matrix(self.q)

    @property
    def bias(self) -> ImuBias:
        """The biases as an :class:`ImuBias`."""
        return ImuBias(self.b_g, self.b_a)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Broadcast shape of the leading axes of all fields."""
        return jnp.broadcast_shapes(
            self.q.shape[:-1],
            self.p.shape[:-1],
            self.v.shape[:-1],
            self.b_g.shape[:-1],
            self.b_a.shape[:-1],
        )

    def replace(self, **changes) -> NavState:
        """A copy with some fields replaced."""
        return dataclasses.replace(self, **changes)

    def __getitem__(self, index) -> NavState:
        """Index the leading axes of every field (e.g. ``states[-1]``, ``states[:, 10]``)."""
        return jax.tree_util.tree_map(lambda x: x[index], self)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ImuBias:
    """IMU biases in the body frame; fields may carry leading batch axes.

    Attributes:
        b_g: ``(..., 3)`` gyroscope bias [rad/s].
        b_a: ``(..., 3)`` accelerometer bias [m/s²].
    """

    b_g: jax.Array | np.ndarray
    b_a: jax.Array | np.ndarray

    @classmethod
    def zeros(cls, batch_shape=(), dtype=jnp.float32) -> ImuBias:
        """Zero gyro and accelerometer biases ``batch_shape + (3,)``."""
        z = jnp.zeros(check_batch_shape(batch_shape) + (3,), dtype)
        return cls(z, z)


def _require_state(name, state):
    """Type and field shapes (static: free inside ``jit``); returns the fields' batch shapes."""
    if not isinstance(state, NavState):
        raise ValueError(f"{name} must be a jaximu.NavState, got {type(state).__name__}")
    for field, dim in (("q", 4), ("p", 3), ("v", 3), ("b_g", 3), ("b_a", 3)):
        shape = jnp.shape(getattr(state, field))
        if len(shape) < 1 or shape[-1] != dim:
            raise ValueError(f"{name}.{field} must have shape (..., {dim}), got {tuple(shape)}")
    return [jnp.shape(x)[:-1] for x in (state.q, state.p, state.v, state.b_g, state.b_a)]


def _broadcast(*shapes):
    try:
        return jnp.broadcast_shapes(*shapes)
    except ValueError:
        raise ValueError(
            "batch shapes do not broadcast: " + ", ".join(str(tuple(s)) for s in shapes)
        ) from None


def boxplus(state: NavState, delta: jax.Array) -> NavState:
    """``state ⊞ δ``: ``(q ⊗ Exp(dθ), p + dp, v + dv, b_g + db_g, b_a + db_a)``.

    A pure array function like :mod:`jaximu.so3`'s (no value checks, so it is cheap inside
    ``jit``); shapes are checked (``ValueError``).

    Args:
        state: the linearisation point.
        delta: ``(..., 15)`` error state ``[dθ, dp, dv, db_g, db_a]``.
    """
    batch = _require_state("state", state)
    delta = jnp.asarray(delta)
    if delta.ndim < 1 or delta.shape[-1] != ERROR_STATE_DIM:
        raise ValueError(f"delta must have shape (..., {ERROR_STATE_DIM}), got {delta.shape}")
    _broadcast(*batch, delta.shape[:-1])
    return NavState(
        q=so3.quat_mul(state.q, so3.exp(delta[..., THETA])),
        p=state.p + delta[..., POS],
        v=state.v + delta[..., VEL],
        b_g=state.b_g + delta[..., BG],
        b_a=state.b_a + delta[..., BA],
    )


def boxminus(state: NavState, reference: NavState) -> jax.Array:
    """``state ⊟ reference``: the ``(..., 15)`` error ``δ`` with ``reference ⊞ δ = state``.

    The rotation part is ``Log(R_refᵀ R)`` (body frame of the reference), angle in ``[0, π]``.
    A pure array function, like :func:`boxplus`.
    """
    _broadcast(*_require_state("state", state), *_require_state("reference", reference))
    parts = [
        so3.log(so3.quat_mul(so3.quat_conj(reference.q), state.q)),
        state.p - reference.p,
        state.v - reference.v,
        state.b_g - reference.b_g,
        state.b_a - reference.b_a,
    ]
    shape = jnp.broadcast_shapes(*(x.shape for x in parts))
    return jnp.concatenate([jnp.broadcast_to(x, shape) for x in parts], axis=-1)


def require_navstate(state):
    if not isinstance(state, NavState):
        raise ValueError(f"state must be a jaximu.NavState, got {type(state).__name__}")


def check_state(state: NavState, dtype) -> NavState:
    """Shapes, finiteness and unit norm of ``state.q`` (never normalised for the caller)."""
    require_navstate(state)
    fields = {"q": 4, "p": 3, "v": 3, "b_g": 3, "b_a": 3}
    out = {}
    for name, dim in fields.items():
        x = to_dtype(f"state.{name}", getattr(state, name), dtype)
        if x.ndim < 1 or x.shape[-1] != dim:
            raise ValueError(f"state.{name} must have shape (..., {dim}), got {tuple(x.shape)}")
        check_finite(f"state.{name}", x)
        out[name] = x
    try:
        jnp.broadcast_shapes(*(x.shape[:-1] for x in out.values()))
    except ValueError:
        raise ValueError(
            "state fields have incompatible batch shapes: "
            + ", ".join(f"{k}{tuple(v.shape)}" for k, v in out.items())
        ) from None
    check_unit_norm("state.q", out["q"], dtype)
    return NavState(**out)
