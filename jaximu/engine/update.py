"""The filter update on the error state: the EKF update with the rotation error on the right
(:func:`ekf_update`) and the position measurement's Jacobian.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaximu.engine.errorstate import _check_cov
from jaximu.geometry import _checks as val
from jaximu.geometry import _tolerances
from jaximu.geometry.state import NavState, boxplus, check_state, require_navstate
from jaximu.schemes import _blocks as blk

__all__ = ["ekf_update", "position_jacobian"]


# --------------------------------------------------------------------------- EKF update


def position_jacobian(dtype=None):
    """``H = [0, I, 0, 0, 0]``, ``(3, 15)``: a position fix ``z = p + ν`` in the error state
    (the residual is ``z - p̂``). ``dtype``: float32, float64 (needs ``jax_enable_x64``) or
    ``None`` (JAX's default float)."""
    dtype = jnp.result_type(float) if dtype is None else val.compute_dtype("dtype", dtype)
    H = np.zeros((3, 15))
    H[:, 3:6] = np.eye(3)
    return jnp.asarray(H, dtype)


def _check_innovation(S, dtype):
    """``S = H P Hᵀ + R`` must be positive definite to the dtype's precision (its Cholesky
    factor is the update's; :func:`jaximu.geometry._tolerances.check_definite`), on eager calls."""
    _tolerances.check_definite(
        "the innovation covariance S = H P Hᵀ + R",
        S,
        dtype,
        what="the gain K = P Hᵀ S⁻¹",
        fix="R must be positive definite (a measurement noise variance σ² > 0 on every row), "
        "or P positive in the measured directions",
    )


def ekf_update(state: NavState, P, residual, H, R):
    """Error-state EKF update, Joseph form (batched over leading axes, differentiable).

    With the innovation covariance ``S = H P Hᵀ + R`` and gain ``K = P Hᵀ S⁻¹``::

        δx = K ν,   x⁺ = x ⊞ δx,   P⁺ = (I - K H) P (I - K H)ᵀ + K R Kᵀ,   NIS = νᵀ S⁻¹ ν.

    The Joseph form keeps ``P⁺`` symmetric positive semi-definite under rounding and for any
    gain. ``S`` is factored by Cholesky (no explicit inverse). The error state is not reset
    through ``∂(x ⊞ δx)``'s rotation Jacobian (first order, as OpenVINS).

    Args:
        state: the estimate :class:`NavState` (fields ``batch + (·)``; ``q`` unit, never
            normalised for you; finite).
        P: ``batch + (15, 15)`` its error covariance ``[dθ, dp, dv, db_g, db_a]``, symmetric
            positive semi-definite (judged per axis, as
            :func:`propagate_covariance`'s ``P0``), finite.
        residual: ``batch + (m,)`` ``ν = z - h(x̂)`` (e.g. ``z - p̂`` for a position fix),
            finite.
        H: ``(m, 15)`` or ``batch + (m, 15)`` measurement Jacobian ``∂h/∂δ``
            (:func:`position_jacobian`), finite.
        R: ``(m, m)`` or ``batch + (m, m)`` measurement noise covariance, symmetric
            positive semi-definite (as ``P``), finite; with ``P``, ``S = H P Hᵀ + R`` must
            be positive definite to the dtype's precision (the smallest eigenvalue of its
            correlation matrix above 60 ε: :func:`jaximu.geometry._tolerances.definiteness`), or the
            update refuses it naming ``S``, ``R`` and ``P``.

    The computation dtype is the promotion of the inputs' (at least float32: integer and
    half-precision inputs are computed in float32). Shapes and batch shapes are checked
    always; values (finiteness, symmetry, definiteness, unit ``q``) on eager calls only,
    not inside a caller's ``jit``/``vmap``/``grad``, where a singular ``S`` gives NaN.

    Returns:
        ``(state⁺, P⁺, nis)`` with ``nis`` of shape ``batch``.

    Raises:
        ValueError: naming the argument, for any of them outside the domain above.
    """
    require_navstate(state)
    dtype = val.float_dtype(state, P, residual, H, R)  # every field of the state counts
    state = check_state(state, dtype)
    P = _check_cov(P, dtype, "P")
    residual, H, R = (
        val.to_dtype(n, x, dtype) for n, x in (("residual", residual), ("H", H), ("R", R))
    )
    if H.ndim < 2 or H.shape[-1] != 15:
        raise ValueError(f"H must have shape (..., m, 15), got {tuple(H.shape)}")
    m = H.shape[-2]
    if m < 1:
        raise ValueError("H has no rows (m = 0): a measurement needs at least one")
    if residual.ndim < 1 or residual.shape[-1:] != (m,):
        raise ValueError(
            f"residual must have shape (..., {m}) to match H {tuple(H.shape)}, got "
            f"{tuple(residual.shape)}"
        )
    R = _check_cov(R, dtype, "R", m)
    val.check_finite("residual", residual)
    val.check_finite("H", H)
    val.batch_shape(
        state.batch_shape,
        P.shape[:-2],
        residual.shape[:-1],
        H.shape[:-2],
        R.shape[:-2],
        names=("state", "P", "residual", "H", "R"),
    )
    out = _ekf_update(state, P, residual, H, R)
    return val.check_output("ekf_update", out, "the inputs are too large")


def _ekf_update(state, P, residual, H, R):
    """The update on dense arrays: :func:`jaximu.schemes._blocks.kalman_update` (the one home of
    the Joseph form) on ``P``'s blocks and ``H``'s column blocks. Only ``P``'s upper blocks
    are read: :func:`ekf_update` has checked it symmetric to rounding."""
    batch = jnp.broadcast_shapes(P.shape[:-2], residual.shape[:-1], H.shape[:-2], R.shape[:-2])
    out = blk.kalman_update(
        blk.dense_to_blocks(P),
        [H[..., :, 3 * k : 3 * k + 3] for k in range(5)],
        R,
        residual[..., None],
        blk.ARRAYS,
        check=lambda S: _check_innovation(S, S.dtype),
    )
    dx = jnp.concatenate([jnp.broadcast_to(d, batch + (3, 1)) for d in out.dx], -2)[..., 0]
    P_new = blk.blocks_to_dense(out.P, batch=batch)
    return boxplus(state, dx), P_new, jnp.broadcast_to(out.nis[..., 0, 0], batch)
