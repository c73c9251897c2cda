"""Jacobian blocks of a step by ``jax.jvp`` on lanes (the propagation kernels' and the
preintegration kernels'): three directions at a time, direction axis major, lanes minor.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.geometry.so3 import quat_mul_components
from jaximu.kernels.lane_math import _E3

# ----------------------------------------------------------------------------- autodiff blocks
#
# Jacobian blocks of a step by jax.jvp on lanes (the propagation kernels' and the
# preintegration kernels'): three directions at a time, direction axis major, lanes minor.


def lane_directions(cols, dtype, lanes):
    """``cols`` (3 directions × 3 components, a numpy array) as a 3-tuple of ``(3, *lanes)``
    components: direction j's component i is ``cols[j, i]`` on every lane."""
    return tuple(
        jnp.broadcast_to(jnp.asarray(cols[:, i], dtype)[:, None], (3,) + lanes) for i in range(3)
    )


def rotation_tangents(q, world=False):
    """The tangents of ``q ⊗ Exp(δθ)`` (``world``: ``Exp(δθ) ⊗ q``) in the 3 directions of
    ``δθ``: ``q ⊗ [0, ½ e_j]`` (``[0, ½ e_j] ⊗ q``), a 4-tuple of ``(3, *lanes)``."""
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


def jvp_directions(fn, primals, tangents):
    """``jax.jvp`` of ``fn`` in several directions at once (a ``vmap`` over the leading axis
    of ``tangents``); returns the output tangents, direction axis first."""
    return jax.vmap(lambda t: jax.jvp(fn, primals, t)[1])(tangents)


def direction_block(rows, dtype):
    """3 output components, each ``(3 directions, *lanes)``, as the ``(3, 3, *lanes)`` block
    ``[row i, direction j]`` (one-hot broadcasting, not ``jnp.stack``: a concatenate is a
    scalar loop on XLA:CPU)."""
    E3 = jnp.asarray(_E3, dtype)
    return sum(E3[:, i, None, None] * r[None] for i, r in enumerate(rows))


def rotation_rows(tq1, q1, world=False):
    """The rotation error's rows from a tangent ``δq⁺`` of ``q⁺``: ``2 vec(q⁺* ⊗ δq⁺)``
    (``world``: ``2 vec(δq⁺ ⊗ q⁺*)``), the tangent of ``Log(q̂⁺* q⁺)``."""
    conj = tuple(x[None] for x in (q1[0], -q1[1], -q1[2], -q1[3]))
    rel = quat_mul_components(tq1, conj) if world else quat_mul_components(conj, tq1)
    return tuple(2.0 * rel[1 + i] for i in range(3))
