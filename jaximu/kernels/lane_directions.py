"""The lane layout's directions of the Jacobian blocks by ``jax.jvp``
(:func:`jaximu.schemes._jvp_blocks.blocks_by_jvp`, the propagation kernels' and the
preintegration kernels'): three directions at a time, direction axis major, lanes minor.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaximu.geometry._vec import V3
from jaximu.kernels.lane_math import _E3
from jaximu.schemes._jvp_blocks import (
    Directions,
    jvp_directions,
    lane_directions,
    rotation_rows,
    rotation_tangents,
)

__all__ = [
    "LANE_DIRECTIONS",
    "direction_block",
    "jvp_directions",
    "lane_directions",
    "rotation_rows",
    "rotation_tangents",
]


def direction_block(rows, dtype):
    """3 output components, each ``(3 directions, *lanes)``, as the ``(3, 3, *lanes)`` block
    ``[row i, direction j]`` (one-hot broadcasting, not ``jnp.stack``: a concatenate is a
    scalar loop on XLA:CPU)."""
    E3 = jnp.asarray(_E3, dtype)
    return sum(E3[:, i, None, None] * r[None] for i, r in enumerate(rows))


LANE_DIRECTIONS = Directions(
    along=lambda cols, like: V3(*lane_directions(cols, like[0].dtype, like[0].shape)),
    block=lambda rows: direction_block(rows, rows[0].dtype),
)
