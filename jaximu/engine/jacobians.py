"""The error-state Jacobians of one step: ``Φ`` and ``G`` by autodiff or in closed form
(:func:`step_jacobians`, the definitions in :mod:`jaximu.engine.errorstate`'s docstring), their
blocks, and the discrete process noise ``Q_d``.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.geometry import _checks as val
from jaximu.geometry import sensor
from jaximu.geometry._vec import V3
from jaximu.geometry.noise import ImuNoise, check_noise
from jaximu.geometry.state import NavState, boxminus, boxplus, check_state, require_navstate
from jaximu.schemes import _blocks as blk
from jaximu.schemes._blocks import Blocks
from jaximu.schemes._jvp_blocks import (
    ARRAY_DIRECTIONS,
    array_rotation_rows,
    array_rotation_tangents,
    blocks_by_jvp,
)
from jaximu.schemes.integrators import (
    Attitude,
    blocks_analytic,
    check_scheme,
    get_attitude,
    nav_step,
)

__all__ = ["JACOBIANS", "step_jacobians", "discrete_process_noise"]


JACOBIANS = ("auto", "analytic", "autodiff")


# --------------------------------------------------------------------------- Jacobians


def jacobians_autodiff(scheme, att: Attitude, state: NavState, w0, a0, w1, a1, h, g):
    """``(Φ, G)`` of one step by ``jax.jacfwd`` through boxplus/boxminus; ``(..., 15, 15/12)``.

    The perturbation is shared by every batch element, so one forward pass with 27
    tangents gives the per-element Jacobians.
    """
    nominal = nav_step(scheme, att, state, w0, a0, w1, a1, h, g)
    dtype = state.q.dtype

    def f_delta(delta):
        return boxminus(nav_step(scheme, att, boxplus(state, delta), w0, a0, w1, a1, h, g), nominal)

    def f_noise(n):
        return boxminus(nav_step(scheme, att, state, w0, a0, w1, a1, h, g, noise=n), nominal)

    Phi = jax.jacfwd(f_delta)(jnp.zeros(15, dtype))
    G = jax.jacfwd(f_noise)(jnp.zeros(12, dtype))
    return Phi, G


def blocks_autodiff(
    scheme, att: Attitude, state: NavState, w0, a0, w1, a1, h, g, lever=None
) -> Blocks:
    """The blocks of ``Φ`` by ``jax.jvp`` of the step in the 9 directions that are not
    structural, ``dθ``, ``db_g``, ``db_a`` (any scheme and attitude form):
    :func:`jaximu.schemes._jvp_blocks.blocks_by_jvp` in the array layout, the function
    that makes the structure-of-arrays kernels' blocks too
    (:func:`jaximu.kernels.fast.blocks_autodiff`).

    The step is :func:`nav_step` from the quaternion ``state.q`` (its form's own
    coordinates inside); the directions are those of :func:`boxplus` and the rows those of
    :func:`boxminus` (``q ⊗ [0, ½ e_j]``, ``2 vec(q⁺* ⊗ δq⁺)``; the biases as ``-e_j`` on
    the samples). ``G`` is known from ``Φ`` (the white noises enter exactly as the biases
    do, ``ω = w - b_g - n_g``, ``f = a - b_a - n_a``; the walks as ``dt I``), so
    :func:`structured_update` serves both Jacobian options. 9 tangents instead of 27, and no
    dense 15×15 products; tested equal to :func:`jacobians_autodiff` (dense) and to the
    closed forms.

    ``lever``: the lever arm ``r`` (``(..., 3)`` [m]) of samples moved from a sensor to the
    body (:mod:`jaximu.sensor`): their specific force carries ``-ω×(ω×r)``, so it moves with
    the gyro bias by ``K δb_g`` (:func:`jaximu.sensor.centripetal_jacobian`).
    """
    batch = jnp.broadcast_shapes(
        state.q.shape[:-1],
        state.b_g.shape[:-1],
        state.b_a.shape[:-1],
        *(x.shape[:-1] for x in (w0, a0, w1, a1)),
        *(() if lever is None else (jnp.shape(lever)[:-1],)),
    )
    q, w0, a0, w1, a1 = (
        jnp.broadcast_to(x, batch + x.shape[-1:]) for x in (state.q, w0, a0, w1, a1)
    )

    def step(q, w0, w1, a0, a1):
        s = nav_step(
            scheme, att, NavState(q, state.p, state.v, state.b_g, state.b_a), w0, a0, w1, a1, h, g
        )
        return s.q, s.p, s.v

    def k_cols(w):  # direction j moves f by the column K e_j
        K = sensor.centripetal_jacobian(V3.of(w - state.b_g), V3.of(lever), blk.ARRAYS)
        return jnp.moveaxis(jnp.broadcast_to(K, batch + (3, 3)), -1, 0)

    _, b = blocks_by_jvp(
        step,
        q,
        w0,
        w1,
        a0,
        a1,
        h,
        array_rotation_tangents(q),
        array_rotation_rows,
        ARRAY_DIRECTIONS,
        None if lever is None else k_cols,
    )
    return b


def dense_from_blocks(b: Blocks):
    """Assemble ``Φ`` ``(..., 15, 15)`` and ``G`` ``(..., 15, 12)`` from the blocks."""
    Phi = blk.phi_to_dense(b)
    batch = Phi.shape[:-2]
    Z = jnp.zeros(batch + (3, 3), Phi.dtype)
    hI = jnp.broadcast_to(b.dt[..., None, None] * jnp.eye(3, dtype=Phi.dtype), batch + (3, 3))

    def f(x):
        return Z if x is None else jnp.broadcast_to(x, batch + (3, 3))

    rows: list[list[Any]] = [
        [b.B, Z, Z, Z],
        [b.Dp, b.Ep, Z, Z],
        [b.Dv, b.Ev, Z, Z],
        [Z, Z, hI, Z],
        [Z, Z, Z, hI],
    ]
    G = jnp.concatenate([jnp.concatenate([f(x) for x in r], -1) for r in rows], -2)
    return Phi, G


def step_jacobians(
    state: NavState,
    gyro,
    accel,
    dt,
    *,
    gyro_next=None,
    accel_next=None,
    scheme: str = "euler",
    attitude: str = "quaternion",
    gravity=9.81,
    method: str = "autodiff",
):
    """``Φ`` and ``G`` of one propagation step at ``state``.

    Args:
        state: linearisation point (fields ``(..., 4)``/``(..., 3)``).
        gyro, accel: ``(..., 3)`` raw sample k; ``gyro_next``, ``accel_next``: sample k+1
            (midpoint, RK4; default: sample k held).
        dt: ``(...,)`` step [s].
        method: ``"autodiff"`` or ``"analytic"`` (exact-exponential attitude forms only).

    Returns:
        ``(Φ, G)``: ``(..., 15, 15)`` and ``(..., 15, 12)``.
    """
    check_scheme(scheme)
    att = get_attitude(attitude)
    require_navstate(state)
    dtype = val.float_dtype(state, gyro, accel, dt, gyro_next, accel_next)
    state = check_state(state, dtype)
    w0, a0 = val.to_dtype("gyro", gyro, dtype), val.to_dtype("accel", accel, dtype)
    w1 = w0 if gyro_next is None else val.to_dtype("gyro_next", gyro_next, dtype)
    a1 = a0 if accel_next is None else val.to_dtype("accel_next", accel_next, dtype)
    for name, x in (("gyro", w0), ("accel", a0), ("gyro_next", w1), ("accel_next", a1)):
        val.check_vector(name, x, time_axis=False)
        val.check_finite(name, x)
    h = val.to_dtype("dt", dt, dtype)
    if val.is_concrete(h) and not np.all(np.isfinite(np.asarray(h)) & (np.asarray(h) > 0)):
        raise ValueError(f"dt must be positive and finite, got {np.asarray(h)}")
    g = val.gravity_vector(gravity, dtype)
    val.batch_shape(
        state.batch_shape,
        w0.shape[:-1],
        a0.shape[:-1],
        w1.shape[:-1],
        a1.shape[:-1],
        h.shape,
        g.shape[:-1],
        names=("state", "gyro", "accel", "gyro_next", "accel_next", "dt", "gravity"),
    )
    if method == "analytic":
        _require_analytic(att)
    elif method != "autodiff":
        raise ValueError(f"unknown Jacobian method {method!r}; choose 'autodiff' or 'analytic'")
    return _checked_step_jacobians(
        state, w0, a0, w1, a1, h, g, scheme=scheme, attitude=att.name, method=method
    )


@functools.partial(jax.jit, static_argnames=("scheme", "attitude", "method"))
def _checked_step_jacobians(state, w0, a0, w1, a1, h, g, *, scheme, attitude, method):
    """The arithmetic of :func:`step_jacobians` on its checked inputs, as one program per
    scheme, form and method (called eagerly, its few hundred operations would each be
    compiled on their own)."""
    att = get_attitude(attitude)
    if method == "autodiff":  # 9 tangents, the rest structural (equal to the dense 27)
        return dense_from_blocks(blocks_autodiff(scheme, att, state, w0, a0, w1, a1, h, g))
    b = blocks_analytic(
        scheme, state.R, w0 - state.b_g, a0 - state.b_a, w1 - state.b_g, a1 - state.b_a, h
    )
    return dense_from_blocks(b)


def _require_analytic(att: Attitude):
    if not att.exact_exponential:
        raise ValueError(
            f"analytic Jacobians are derived for the exact-exponential attitude forms "
            f"('quaternion', 'matrix'), not {att.name!r}; use jacobians='autodiff'"
        )


def discrete_process_noise(G, noise: ImuNoise, dt):
    """``Q_d = G Q_c Gᵀ`` with ``Q_c = noise.discrete_covariance(dt)``.

    Args:
        G: ``(..., 15, 12)`` noise Jacobian (error state ``[dθ, dp, dv, db_g, db_a]`` by
            noise ``[n_g, n_a, n_wg, n_wa]``, as :func:`step_jacobians` returns), finite.
        noise: :class:`jaximu.ImuNoise` (continuous densities, ``≥ 0``, finite).
        dt: scalar or ``(...,)`` step [s], ``> 0`` and finite.

    Returns:
        ``(..., 15, 15)`` in the promoted dtype of ``G`` and ``dt`` (a float64 ``dt`` beside
        a float32 ``G`` is not rounded to float32; a Python scalar is weak; float32 for
        integer or half-precision data). Shapes, types and batch shapes (``G``'s, ``dt``'s
        and the densities') are checked always, values on eager calls.
    """
    dtype = val.float_dtype(G, dt)
    G = val.to_dtype("G", G, dtype)
    if G.ndim < 2 or G.shape[-2:] != (15, 12):
        raise ValueError(
            f"G must have shape (..., 15, 12) (error state by noise), got {tuple(G.shape)}"
        )
    val.check_finite("G", G)
    noise = check_noise(noise, dtype)
    try:
        dt_batch = jnp.shape(dt)
    except (TypeError, ValueError):  # not numbers: discrete_variances names dt
        dt_batch = ()
    val.batch_shape(G.shape[:-2], dt_batch, names=("G", "dt"), noise=noise)
    qc = noise.discrete_variances(dt, dtype)
    return (G * qc[..., None, :]) @ jnp.swapaxes(G, -1, -2)


def _resolve_jacobians(jacobians, att):
    if jacobians not in JACOBIANS:
        raise ValueError(f"unknown jacobians {jacobians!r}; choose one of {JACOBIANS}")
    if jacobians == "auto":
        return "analytic" if att.exact_exponential else "autodiff"
    if jacobians == "analytic":
        _require_analytic(att)
    return jacobians
