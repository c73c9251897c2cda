"""Fast XLA-CPU preintegration (analytic Jacobians, final i→j): Euler (Forster / GTSAM
Manifold) and VINS-Mono's midpoint.

Same numbers as the generic recursion of :mod:`jaximu.preintegration` (to float rounding),
with the layout rules of :mod:`jaximu.kernels.fast` (structure of arrays, ``(3, 3, B)`` batch-minor
blocks, polynomial half angle, materialised stages, batch blocks, time chunks) and three
algebraic simplifications:

* **Rotated error.** The recursion runs on ``θ' = ΔR_ik δθ`` (the rotation error in frame
  ``B_i`` instead of ``B_k``): ``T_k = blockdiag(ΔR_ik, I, I, I, I)``,
  ``Φ'_k = T_k Φ_k``, ``Q'_k = T_k Q_k T_kᵀ``. The one-step transition becomes

      F' = T_{k+1} F T_kᵀ = [[I, 0, 0, B', 0], [-h²/2 [u]x, I, h I, 0, -h²/2 R],
                             [-h [u]x, 0, I, 0, -h R], [0, 0, 0, I, 0], [0, 0, 0, 0, I]]

  with ``R = ΔR_ik``, ``u = R f``, ``B' = -h R Jl(ω h)`` (``= ΔR_ik+1 · (-h Jr)``): the θ
  block is the identity, so ``Φ P Φᵀ`` needs far fewer 3×3 products. At the end the θ rows
  (and columns) are rotated back with ``ΔR_ijᵀ``.
* **Closed forms.** In these coordinates the accumulated ``Φ'_θθ = I``, ``Φ_vθ = -[Δv]x``
  and ``Φ_pθ = -[Δp]x`` (the same sums as Δv, Δp); only ``B', D_p, D_v, E_p, E_v`` are carried.
* **Known zeros.** The 15×15 covariance starts at zero; its ``(b_g, b_a)`` block stays zero
  and its bias diagonal blocks stay diagonal (``Σ h σ_b²``), so they are carried as vectors.

Long sequences (``method="parallel"`` with a small batch) are cut into ``C`` chunks that run
side by side as extra lanes (Euler: each in its own start frame), and the chunk summaries
are composed by two short sequential folds over a ``C1 × C2`` grid (dense 15×15 algebra: few
summaries; the frame change of :func:`jaximu.preintegration.compose`).

The midpoint scheme (VINS-Mono's first-order ``F``, non-unit quaternion) runs in the original
coordinates with the same layout; only its p rows = h/2 × v rows structure is used.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaximu.geometry import so3
from jaximu.kernels.preint_euler import _zero_carry, step
from jaximu.kernels.preint_midpoint import _zero_carry_mid, mid_step
from jaximu.kernels.preint_summaries import _finish, _reduce_chunks, _to_summary, summary
from jaximu.kernels.soa import _components, _time_chunks, block_lanes, run_blocked, whole_chunks
from jaximu.schemes._blocks import Blocks

MIN_CHUNK = 16  # shortest time chunk per lane


def _as_chunks(C, gyro, accel, dt, per_sequence, edge=None):
    """Each of the B sequences as ``C`` time chunks of ``L`` steps side by side as lanes
    (the parallel method; ``L``: ``ceil(T / C)`` rounded up to whole kernel time chunks,
    :func:`jaximu.kernels.soa.whole_chunks`): gyro, accel ``(B, T, k)`` -> ``(B C, L, k)``, dt
    ``(B, T)`` -> ``(B C, L)``, zero-padded at the end (``h = 0`` steps: the kernels'
    ``guard`` makes them identities); ``edge`` ``(B, T, m)``: per-step values appended to
    ``accel``, padded with their last one; ``per_sequence``: ``(B, ·)`` arrays repeated per
    chunk (a ``(·,)`` one shared by all, or ``None``, passes). Returns
    ``((gyro, accel, dt, per_sequence), guard)``, ``guard``: some steps are padding."""
    B, T = dt.shape
    L = whole_chunks(-(-T // C))
    pad = C * L - T
    if pad:
        padw = lambda x, **kw: jnp.pad(  # noqa: E731
            x, ((0, 0), (0, pad)) + ((0, 0),) * (x.ndim - 2), **kw
        )
        gyro, accel, dt = padw(gyro), padw(accel), padw(dt)
        edge = None if edge is None else padw(edge, mode="edge")
    if edge is not None:
        accel = jnp.concatenate([accel, edge], -1)
    lanes = lambda x: x.reshape((B * C, L) + x.shape[2:])  # noqa: E731
    rep = [x if x is None or x.ndim == 1 else jnp.repeat(x, C, axis=0) for x in per_sequence]
    return (lanes(gyro), lanes(accel), lanes(dt), tuple(rep)), bool(pad)


def preintegrate_midpoint(
    gyro, accel, dt, b_g, b_a, var, C=1, lever=None, jacobians="analytic", isotropic_accel=False
):
    """As :func:`preintegrate_euler` for VINS-Mono's midpoint; gyro, accel ``(B, T, 6)``:
    samples k and k+1 side by side. Returns the generic code's outputs. ``isotropic_accel``
    is not used: the end sample's rotation comes from VINS-Mono's unnormalised quaternion,
    so ``R_1 D R_1ᵀ`` is not ``σ² I`` (the accelerometer blocks stay products).

    With ``C > 1`` chunks (the parallel method): as the generic code, the rotations ``ΔR_ik``
    come first from an associative scan of the normalised increments; each chunk then runs in
    frame ``B_i`` with its rotations given, and the chunk summaries compose without a frame
    change (VINS-Mono's unnormalised rotation makes a change of frame inexact).
    ``jacobians``: :func:`mid_step`."""
    B, T, _ = gyro.shape
    dtype = gyro.dtype
    guard = False
    if C > 1:
        omega = 0.5 * (gyro[..., 0:3] + gyro[..., 3:6]) - (b_g if b_g.ndim == 1 else b_g[:, None])
        hT = jnp.broadcast_to(dt, (B, T))
        incr = jnp.concatenate([jnp.ones_like(hT)[..., None], 0.5 * hT[..., None] * omega], -1)
        incl = so3.quat_normalize(
            jax.lax.associative_scan(so3.quat_mul, so3.quat_normalize(incr), axis=1)
        )
        q_last = incl[:, -1]
        dR = jnp.concatenate(
            [jnp.broadcast_to(so3.quat_identity((), dtype), (B, 1, 4)), incl[:, :-1]], 1
        )
        # the rotation rides along with the specific force (B, T, 10); padded steps sit at
        # a unit rotation (autodiff normalises through it)
        (gyro, accel, dt, (b_g, b_a, var, lever)), guard = _as_chunks(
            C, gyro, accel, hT, (b_g, b_a, var, lever), edge=dR
        )

    def block(gyro, accel, dt, b_g, b_a, var, lever):
        Bc = gyro.shape[0]
        bg, ba, s = _components(b_g), _components(b_a), _components(var)
        r = None if lever is None else _components(lever)

        def st(c, w, a, h, consts):
            w0 = tuple(w[i] - bg[i] for i in range(3))
            w1 = tuple(w[3 + i] - bg[i] for i in range(3))
            a0 = tuple(a[i] - ba[i] for i in range(3))
            a1 = tuple(a[3 + i] - ba[i] for i in range(3))
            return mid_step(
                c, w0, a0, w1, a1, h, s, a[6:10] if C > 1 else None, guard, r, jacobians
            )

        q, dv, dp, t, Phi, P, d3, d4, S = _time_chunks(
            st, _zero_carry_mid(Bc, dtype), gyro, accel, dt, None, None
        )[0]
        bm = lambda X: jnp.moveaxis(X, -1, 0)  # noqa: E731
        A, Bg, Cp, Cv, Dp, Dv, Ep, Ev = (bm(X) for X in Phi)
        phi = Blocks(A=A, B=Bg, Cp=Cp, Cv=Cv, Dp=Dp, Dv=Dv, Ep=Ep, Ev=Ev, dt=t)
        return summary(q, dv, dp, t, phi, P, d3, d4, S)

    out = _run_blocked(block, gyro, accel, dt, b_g, b_a, var, lever)
    if C > 1:
        out = jax.tree_util.tree_map(lambda x: x.reshape((B, C) + x.shape[1:]), out)
        out = _reduce_chunks(out, C, rotate=False)
        out["q"] = q_last
    return (
        out["t"],
        so3.quat_normalize(out["q"]),
        out["dv"],
        out["dp"],
        out["Phi"],
        out["Q15"],
        out["Q9"],
    )


# ----------------------------------------------------------------------------- driver


def _run_blocked(block, gyro, accel, dt, b_g, b_a, var, lever):
    """:func:`jaximu.kernels.soa.run_blocked` of ``block(gyro, accel, dt, b_g, b_a, var, lever)``
    over the lanes: a ``dt`` ``(T,)``, biases ``(3,)``, variances ``(12,)`` or a lever arm
    ``(3,)`` (or ``None``) shared by all lanes are read whole by every block."""
    shared = (dt.ndim == 1,) + tuple(x is None or x.ndim == 1 for x in (b_g, b_a, var, lever))
    return run_blocked(
        block,
        gyro.shape[0],
        block_lanes(gyro.dtype),
        gyro,
        accel,
        dt,
        b_g,
        b_a,
        var,
        lever,
        whole=(False, False) + shared,
    )


def num_chunks(B, T, method, dtype):
    """Time chunks per sequence: 1 for ``"sequential"``; for ``"parallel"`` enough to fill
    about one batch block of lanes, each chunk at least :data:`MIN_CHUNK` samples long (a
    divisor of T within 1/16 of that is preferred: less padding). A block's step costs
    nearly as much with fewer lanes: the padded steps of a full block cost less than
    lanes left empty (one window of 10^5 float64 samples, measured before chunks were
    padded to whole kernel time chunks: 64 chunks with 32 padded steps 9.9 M samples/s,
    50 chunks of 2000 9.1 M)."""
    lanes = block_lanes(dtype)
    if method != "parallel" or B >= lanes or T < 2 * MIN_CHUNK:
        return 1
    C = int(max(1, min(-(-lanes // B), T // MIN_CHUNK)))
    for c in range(C, C - C // 16 - 1, -1):
        if T % c == 0:
            return c
    return C


def preintegrate_euler(
    gyro, accel, dt, b_g, b_a, var, C, lever=None, jacobians="analytic", isotropic_accel=False
):
    """Flat batch: gyro, accel ``(B, T, 3)``; dt ``(T,)`` or ``(B, T)``; b_g, b_a ``(3,)`` or
    ``(B, 3)``; var ``(12,)`` or ``(B, 12)`` (σ² per axis); ``C`` time chunks per sequence;
    ``lever``: ``None``, ``(3,)`` or ``(B, 3)``, the lever arm of samples moved from a sensor;
    ``jacobians``: ``"analytic"`` or ``"autodiff"`` (:func:`step`); ``isotropic_accel``: the
    accelerometer's white-noise variances (``var[..., 3:6]``) are equal on every axis
    (:func:`step`).

    Returns ``(t, q, dv, dp, Φ, Q15, Q9)`` with leading axis B, as the generic code."""
    B, T, _ = gyro.shape
    dtype = gyro.dtype
    guard = False
    if C > 1:
        (gyro, accel, dt, (b_g, b_a, var, lever)), guard = _as_chunks(
            C, gyro, accel, jnp.broadcast_to(dt, (B, T)), (b_g, b_a, var, lever)
        )

    def block(gyro, accel, dt, b_g, b_a, var, lever):
        Bc = gyro.shape[0]
        bg, ba, s = _components(b_g), _components(b_a), _components(var)
        r = None if lever is None else _components(lever)

        def st(c, w, a, h, consts):
            omega = tuple(w[i] - bg[i] for i in range(3))
            f = tuple(a[i] - ba[i] for i in range(3))
            return step(c, omega, f, h, s, guard, r, jacobians, isotropic_accel)

        carry, _ = _time_chunks(st, _zero_carry(Bc, dtype), gyro, accel, dt, None, None)
        return _to_summary(carry)

    summ = _run_blocked(block, gyro, accel, dt, b_g, b_a, var, lever)
    if C > 1:
        summ = jax.tree_util.tree_map(lambda x: x.reshape((B, C) + x.shape[1:]), summ)
        summ = _reduce_chunks(summ, C)
    return _finish(summ)


KERNELS = {"euler": preintegrate_euler, "midpoint": preintegrate_midpoint}
"""The structure-of-arrays kernel of each scheme's preintegration step
(:data:`jaximu.schemes._preintegration_steps.PREINTEGRATION_STEPS`, by the same name)."""
