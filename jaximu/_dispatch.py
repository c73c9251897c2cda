"""Which kernel runs: one table for every engine entry (docs/DESIGN.md, "Dispatch").

The engine has two families of kernels:

* ``generic``: readable ``lax.scan`` kernels on ``(..., 3)`` arrays, for every scheme,
  attitude form and Jacobian option. They are the reference the fast kernels are tested
  against (``fast=False`` forces them).
* structure-of-arrays kernels (:mod:`jaximu._soa`, :mod:`jaximu._fast`,
  :mod:`jaximu._fast_preint`): the same mathematics laid out for XLA:CPU's vectoriser.

A ``jax.vmap`` of an entry reaches this table with the whole batch (:mod:`jaximu._batching`),
so the same row decides for leading axes and for ``vmap``. The table is read top to bottom;
the first row whose conditions hold names the kernel.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp


class Row(NamedTuple):
    entry: str  # "mean", "covariance", "preintegrate"
    schemes: tuple  # schemes the kernel implements
    attitudes: tuple | None  # attitude forms (None: not applicable)
    jacobians: tuple | None  # Jacobian options (None: not applicable)
    save_all: tuple  # (False,) final only, (False, True) both
    min_lanes: int  # below this many batch elements the generic kernel is as fast
    kernel: str


TABLE = (
    # mean of every scheme with the exact quaternion exponential; below 32 lanes XLA's
    # generic scan (one fused kernel per step) is as fast
    Row("mean", ("euler", "midpoint", "rk4"), ("quaternion",), None, (False, True), 32,
        "soa_mean"),
    # final covariance, Euler, closed-form Jacobians
    Row("covariance", ("euler",), ("quaternion",), ("analytic",), (False,), 1, "soa_cov"),
    # preintegration, closed-form Jacobians, final i→j (min_lanes: see preintegrate_kernel)
    Row("preintegrate", ("euler",), None, ("analytic",), (False,), 1, "soa_preint_euler"),
    Row("preintegrate", ("midpoint",), None, ("analytic",), (False,), 1,
        "soa_preint_midpoint"),
)

GENERIC = "generic"

PREINT_MIN_LANES_SEQUENTIAL = 8
"""Sequential preintegration of fewer windows than this runs the generic scan (as fast)."""


def kernel(entry, scheme, *, attitude=None, jacobians=None, save_all=False, lanes=1,
           fast=True) -> str:
    """The kernel that runs ``entry`` for these static options and ``lanes`` batch elements."""
    if not fast:
        return GENERIC
    for row in TABLE:
        if (row.entry == entry and scheme in row.schemes
                and (row.attitudes is None or attitude in row.attitudes)
                and (row.jacobians is None or jacobians in row.jacobians)
                and save_all in row.save_all and lanes >= row.min_lanes):
            return row.kernel
    return GENERIC


# --------------------------------------------------------------------------- preintegration

PREINT_METHODS = ("auto", "sequential", "parallel")


def preint_method(method, lanes, steps, dtype) -> str:
    """``method="auto"``: the fastest correct method for the shape.

    Both methods give the same numbers to rounding. ``"parallel"`` cuts each window into
    time chunks that run side by side as extra lanes; it pays when the batch alone does not
    fill a block of lanes (few, long windows). With enough windows the sequential method
    has all the lanes it needs and does less work.
    """
    if method != "auto":
        return method
    from jaximu._fast_preint import MIN_CHUNK, block_lanes

    if lanes < block_lanes(jnp.dtype(dtype)) // 2 and steps >= 4 * MIN_CHUNK:
        return "parallel"
    return "sequential"


def preintegrate_kernel(scheme, *, jacobians, prefixes, method, lanes, fast=True) -> str:
    if prefixes:
        return GENERIC
    if method == "sequential" and lanes < PREINT_MIN_LANES_SEQUENTIAL:
        return GENERIC
    return kernel("preintegrate", scheme, jacobians=jacobians, lanes=lanes, fast=fast)
