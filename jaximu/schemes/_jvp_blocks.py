"""The blocks of ``Φ`` by ``jax.jvp`` of a step in its 9 non-structural directions, for both
block layouts: :func:`blocks_by_jvp` (the choice of the directions, their three groups and
the assembly of :class:`~jaximu.schemes._blocks.Blocks` from the tangents), the quaternion's
tangents and rows (:func:`rotation_tangents`, :func:`rotation_rows`) and the array layout's
directions (:data:`ARRAY_DIRECTIONS`; the lanes': :data:`jaximu.kernels.lane_directions.LANE_DIRECTIONS`).

Directions are stacked on a leading axis and run as one ``vmap`` of ``jax.jvp`` per group.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.geometry.so3 import quat_mul_components
from jaximu.schemes._blocks import Blocks


def lane_directions(cols, dtype, lanes):
    """``cols`` (3 directions × 3 components, a numpy array) as a 3-tuple of ``(3, *lanes)``
    components: direction j's component i is ``cols[j, i]`` on every lane (``lanes``: any
    shape, ``()`` included)."""
    index = (slice(None),) + (None,) * len(lanes)  # (3,) -> (3, 1, …): one per lane axis
    return tuple(
        jnp.broadcast_to(jnp.asarray(cols[:, i], dtype)[index], (3,) + lanes) for i in range(3)
    )


def rotation_tangents(q, world=False):
    """The tangents of ``q ⊗ Exp(δθ)`` (``world``: ``Exp(δθ) ⊗ q``) in the 3 directions of
    ``δθ``: ``q ⊗ [0, ½ e_j]`` (``[0, ½ e_j] ⊗ q``), a 4-tuple of ``(3, *lanes)`` (``q``: a
    4-tuple of components of shape ``lanes``)."""
    dtype, lanes = q[0].dtype, q[0].shape
    E = np.eye(3)
    # Python floats (weakly typed): the tangents keep the lanes' dtype
    half = [
        quat_mul_components(tuple(0.5 * float(x) for x in (0.0, *E[j])), q)
        if world
        else quat_mul_components(q, tuple(0.5 * float(x) for x in (0.0, *E[j])))
        for j in range(3)
    ]
    onehot = lane_directions(E, dtype, lanes)  # onehot[j][d] = δ_jd on every lane
    return tuple(sum(onehot[j] * half[j][c][None] for j in range(3)) for c in range(4))


def rotation_rows(tq1, q1, world=False):
    """The rotation error's rows from a tangent ``δq⁺`` of ``q⁺``: ``2 vec(q⁺* ⊗ δq⁺)``
    (``world``: ``2 vec(δq⁺ ⊗ q⁺*)``), the tangent of ``Log(q̂⁺* q⁺)``; components as
    :func:`rotation_tangents`'."""
    conj = tuple(x[None] for x in (q1[0], -q1[1], -q1[2], -q1[3]))
    rel = quat_mul_components(tq1, conj) if world else quat_mul_components(conj, tq1)
    return tuple(2.0 * rel[1 + i] for i in range(3))


def jvp_directions(fn, primals, tangents):
    """``jax.jvp`` of ``fn`` in several directions at once (a ``vmap`` over the leading axis
    of ``tangents``); returns the output tangents, direction axis first."""
    return jax.vmap(lambda t: jax.jvp(fn, primals, t)[1])(tangents)


class Directions(NamedTuple):
    """How a layout writes the directions of :func:`blocks_by_jvp` and reads its tangents
    (direction axis first in both)."""

    along: Callable[..., Any]  # (cols, like) -> the 3 directions cols[j] on an input like `like`
    block: Callable[..., Any]  # a tangent of a 3-vector output -> its block [component, direction]


def _stacked_components(x):
    return tuple(x[..., i] for i in range(x.shape[-1]))


def _array_along(cols, like):
    return jnp.stack(lane_directions(cols, like.dtype, like.shape[:-1]), -1)


ARRAY_DIRECTIONS = Directions(
    along=_array_along,
    block=lambda tangent: jnp.moveaxis(tangent, 0, -1),  # (3, ..., 3) -> (..., 3, 3)
)


def array_rotation_tangents(q):
    """:func:`rotation_tangents` of a ``(..., 4)`` quaternion array: ``(3, ..., 4)``."""
    return jnp.stack(rotation_tangents(_stacked_components(q)), -1)


def array_rotation_rows(tq1, q1):
    """:func:`rotation_rows` on arrays: ``tq1`` ``(3, ..., 4)``, ``q1`` ``(..., 4)`` ->
    ``(3, ..., 3)``."""
    return jnp.stack(rotation_rows(_stacked_components(tq1), _stacked_components(q1)), -1)


def blocks_by_jvp(
    step,
    q,
    omega0,
    omega1,
    f0,
    f1,
    h,
    tq,
    rows,
    directions: Directions,
    lever_columns=None,
    identity_A=False,
):
    """One step and the blocks of its ``Φ`` by ``jax.jvp`` in the 9 directions that are not
    structural, in both layouts: ``dθ``, ``db_g``, ``db_a``.

    The rest of ``Φ`` is known for every step of this library: ``p⁺``, ``v⁺`` depend on
    ``p``, ``v`` through ``I`` and ``dt I`` only, ``θ⁺`` not at all, the biases are carried.
    The directions run in three groups that each perturb only their own inputs, so that
    JAX's symbolic zeros skip what a direction cannot reach (a ``db_a`` tangent never enters
    the half angle): ``dθ`` (the tangents ``tq`` of the attitude ``q ⊞ δθ``), ``db_g`` and
    ``db_a`` (``-e_j`` on both samples' rate or specific force, as ``ω = w - b_g``,
    ``f = a - b_a``).

    Args:
        step: ``(q, ω₀, ω₁, f₀, f₁) -> (q⁺, p⁺, v⁺)``, the step from the attitude and the
            samples (start position, velocity, gravity and ``h`` fixed in it).
        q, omega0, omega1, f0, f1: the step's inputs there (the samples of one shape).
        h: the step [s] (the ``dt`` of the blocks).
        tq: the tangents of ``q ⊞ δθ`` in the 3 directions of ``δθ`` (direction axis
            first).
        rows: ``(δq⁺, q⁺) ->`` the rotation error's rows (the tangent of ``q⁺ ⊟ q̂⁺``).
        directions: the layout's :class:`Directions`.
        lever_columns: ``None``, or the step's rate input ``->`` the columns ``K e_j`` as
            directions on a specific force (:func:`jaximu.sensor.centripetal_jacobian` at
            the bias-corrected rate): samples moved from a
            sensor at a lever arm, whose specific force moves by ``K δb_g``; the ``db_g``
            tangents then perturb the specific force too.
        identity_A: the rotation error's ``Φ_θθ`` is the identity (the world-frame error):
            ``A`` is returned as ``"I"``, not formed.

    Returns:
        ``((q⁺, p⁺, v⁺), Blocks)`` in the layout of ``directions``.
    """
    minus_e = directions.along(-np.eye(3), omega0)
    q1, p1, v1 = step(q, omega0, omega1, f0, f1)
    d_theta = jvp_directions(lambda q: step(q, omega0, omega1, f0, f1), (q,), (tq,))
    if lever_columns is None:
        d_bg = jvp_directions(
            lambda w0, w1: step(q, w0, w1, f0, f1), (omega0, omega1), (minus_e, minus_e)
        )
    else:
        d_bg = jvp_directions(
            lambda w0, w1, a0, a1: step(q, w0, w1, a0, a1),
            (omega0, omega1, f0, f1),
            (minus_e, minus_e, lever_columns(omega0), lever_columns(omega1)),
        )
    d_ba = jvp_directions(
        lambda a0, a1: step(q, omega0, omega1, a0, a1), (f0, f1), (minus_e, minus_e)
    )
    block = directions.block
    (tq_t, tp_t, tv_t), (tq_g, tp_g, tv_g), (_, tp_a, tv_a) = d_theta, d_bg, d_ba
    b = Blocks(
        A="I" if identity_A else block(rows(tq_t, q1)),
        B=block(rows(tq_g, q1)),
        Cp=block(tp_t),
        Cv=block(tv_t),
        Dp=block(tp_g),
        Dv=block(tv_g),
        Ep=block(tp_a),
        Ev=block(tv_a),
        dt=h,
    )
    return (q1, p1, v1), b
