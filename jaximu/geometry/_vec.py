"""Three-vectors as named components, so one formula serves every layout.

A scheme's stages (:mod:`jaximu.integrators`) are written once on :class:`V3`. The
generic kernels split ``(..., 3)`` arrays into components (:meth:`V3.of`); the
structure-of-arrays kernels (:mod:`jaximu.kernels.soa`) keep ``(B,)`` lanes as components, the
layout XLA:CPU vectorises (docs/DESIGN.md, "kernel layout"). Scalars multiplying a
``V3`` broadcast against its components (``(...,)`` arrays, or Python/0-d scalars).
The small matrix products on ``(..., n, m)`` arrays (:func:`matvec`, :func:`matmul`) and
on a :class:`V3` (:func:`matvec_v3`) live here too: one home for each.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


class V3(NamedTuple):
    x: jax.Array
    y: jax.Array
    z: jax.Array

    @staticmethod
    def of(a) -> V3:
        """Components of a ``(..., 3)`` array."""
        return V3(a[..., 0], a[..., 1], a[..., 2])

    def stack(self):
        """The ``(..., 3)`` array."""
        return jnp.stack(jnp.broadcast_arrays(*self), axis=-1)

    # tuple's + and * concatenate and repeat: a V3 adds and scales instead
    def __add__(self, o):
        return V3(self.x + o.x, self.y + o.y, self.z + o.z)

    def __sub__(self, o):
        return V3(self.x - o.x, self.y - o.y, self.z - o.z)

    def __neg__(self):
        return V3(-self.x, -self.y, -self.z)

    def __mul__(self, s):
        return V3(self.x * s, self.y * s, self.z * s)

    def __rmul__(self, s):
        return V3(s * self.x, s * self.y, s * self.z)

    def dot(self, o):
        return self.x * o.x + self.y * o.y + self.z * o.z

    def cross(self, o):
        return V3(
            self.y * o.z - self.z * o.y, self.z * o.x - self.x * o.z, self.x * o.y - self.y * o.x
        )


def matvec(M, x):
    """``M x`` for ``(..., n, m)`` matrices and ``(..., m)`` vectors, broadcasting.

    A broadcast product and sum, not a ``dot``: it fuses with its neighbours and stays
    inside one compiled kernel on XLA:CPU (docs/DESIGN.md, "One kernel per block")."""
    return jnp.sum(M * x[..., None, :], axis=-1)


def matmul(A, B):
    """``A B`` for ``(..., n, k)`` and ``(..., k, m)``, broadcasting (as :func:`matvec`)."""
    return jnp.sum(A[..., :, :, None] * B[..., None, :, :], axis=-2)


def matvec_v3(M, x: V3) -> V3:
    """``M x`` for ``(..., 3, 3)`` ``M`` (or ``(3, 3)``, shared) and a :class:`V3`."""
    return V3(*(M[..., i, 0] * x.x + M[..., i, 1] * x.y + M[..., i, 2] * x.z for i in range(3)))
