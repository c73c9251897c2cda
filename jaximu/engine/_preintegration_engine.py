"""The preintegration engine behind :func:`jaximu.preintegrate`: the measurement
(:class:`Preintegrated`), the associative accumulation of the steps, the sequential and
parallel recursions and the structure-of-arrays kernels' entry (:func:`_preintegrate`)."""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.engine import _dispatch as dispatch
from jaximu.geometry import _checks as val
from jaximu.geometry import so3
from jaximu.geometry.state import ImuBias
from jaximu.kernels import fast_preint as _fast_preint
from jaximu.schemes import _blocks as blk
from jaximu.schemes._blocks import Blocks
from jaximu.schemes._preintegration_steps import _UPPER9, _step, _step_autodiff, preintegration_step


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Preintegrated:
    """Preintegrated IMU measurement between keyframes i and j (frame ``B_i``, no gravity).

    Fields may carry leading batch axes (and, for prefixes, a time axis before the last
    one(s)).

    Attributes:
        delta_t: ``(...,)`` Δt_ij [s].
        delta_q: ``(..., 4)`` ΔR_ij as a unit quaternion ``[w, x, y, z]``.
        delta_v: ``(..., 3)`` Δv_ij [m/s].
        delta_p: ``(..., 3)`` Δp_ij [m].
        transition: ``(..., 15, 15)`` Φ_ij of the error ``[δθ, δp, δv, δb_g, δb_a]``.
        cov15: ``(..., 15, 15)`` covariance with the bias random walk.
        cov: ``(..., 9, 9)`` covariance of ``[δθ, δp, δv]`` from the white noise.
        bias_hat: the linearisation bias.
    """

    delta_t: jax.Array
    delta_q: jax.Array
    delta_v: jax.Array
    delta_p: jax.Array
    transition: jax.Array
    cov15: jax.Array
    cov: jax.Array
    bias_hat: ImuBias

    @property
    def delta_R(self):
        """``(..., 3, 3)`` ΔR_ij."""
        return so3.quat_to_matrix(self.delta_q)

    @property
    def dR_dbg(self):
        """``∂ΔR/∂b_g`` (``ΔR(b) ≈ ΔR Exp(dR_dbg δb_g)``), ``(..., 3, 3)``."""
        return self.transition[..., 0:3, 9:12]

    @property
    def dp_dbg(self):
        return self.transition[..., 3:6, 9:12]

    @property
    def dp_dba(self):
        return self.transition[..., 3:6, 12:15]

    @property
    def dv_dbg(self):
        return self.transition[..., 6:9, 9:12]

    @property
    def dv_dba(self):
        return self.transition[..., 6:9, 12:15]

    def covariance(self, chart: str = "additive", combined: bool = False):
        """The covariance in a chart: ``"additive"`` (ours, VINS-Mono) or ``"gtsam"``.

        GTSAM's ``preintMeasCov`` has δp, δv in the frame at j: ``T P Tᵀ`` with
        ``T = blockdiag(I, ΔRᵀ, ΔRᵀ)``. For ``combined`` (15×15) GTSAM orders the biases
        ``[b_a, b_g]`` and differentiates with respect to the measurements (``-∂/∂b``), so
        its bias blocks are reordered and their cross terms change sign:
        ``T = blockdiag(I, ΔRᵀ, ΔRᵀ, [[0, -I], [-I, 0]])``.
        """
        P = self.cov15 if val.check_bool("combined", combined) else self.cov
        if chart == "additive":
            return P
        if chart != "gtsam":
            raise ValueError(f"unknown chart {chart!r}; choose 'additive' or 'gtsam'")
        Rt = jnp.swapaxes(self.delta_R, -1, -2)
        n = P.shape[-1]
        eye = jnp.eye(3, dtype=P.dtype)
        T = jnp.zeros(Rt.shape[:-2] + (n, n), P.dtype)
        T = T.at[..., 0:3, 0:3].set(eye).at[..., 3:6, 3:6].set(Rt).at[..., 6:9, 6:9].set(Rt)
        if n == 15:
            T = T.at[..., 9:12, 12:15].set(-eye).at[..., 12:15, 9:12].set(-eye)
        return T @ P @ jnp.swapaxes(T, -1, -2)


# --------------------------------------------------------------------------- accumulation


class _Acc(NamedTuple):
    """What composes associatively: the transition and the two noise covariances."""

    Phi: Blocks
    Q15: dict
    Q9: dict


def _combine(earlier: _Acc, later: _Acc) -> _Acc:
    Q15 = blk.symmetrize_diagonal(blk.add_blocks(blk.phi_p_phit(earlier.Q15, later.Phi), later.Q15))
    Q9 = blk.symmetrize_diagonal(blk.add_blocks(blk.phi_p_phit(earlier.Q9, later.Phi), later.Q9))
    Q9 = {k: Q9[k] for k in earlier.Q9}  # the bias blocks of Q9 stay zero
    return _Acc(blk.phi_compose(later.Phi, earlier.Phi), Q15, Q9)


def _identity_acc(batch, dtype) -> _Acc:
    eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), tuple(batch) + (3, 3))
    z = jnp.zeros(tuple(batch) + (3, 3), dtype)
    Phi = Blocks(eye, z, z, z, z, z, z, z, jnp.zeros(tuple(batch), dtype))
    return _Acc(Phi, {k: z for k in blk.UPPER}, {k: z for k in _UPPER9})


def _finish(delta_t, dq, dv, dp, acc: _Acc, bias: ImuBias) -> Preintegrated:
    Q9 = {k: acc.Q9.get(k) for k in blk.UPPER}
    cov9 = blk.blocks_to_dense(Q9)[..., :9, :9]
    batch = dq.shape[:-1]
    return Preintegrated(
        delta_t=delta_t,
        delta_q=so3.quat_normalize(dq),
        delta_v=dv,
        delta_p=dp,
        transition=blk.phi_to_dense(acc.Phi),
        cov15=blk.blocks_to_dense(acc.Q15),
        cov=cov9,
        bias_hat=ImuBias(
            jnp.broadcast_to(bias.b_g, batch + (3,)), jnp.broadcast_to(bias.b_a, batch + (3,))
        ),
    )


def _pairs(gyro, accel, dt, scheme):
    """Time-major samples k and k+1 and steps; ``dt`` of length T (hold the last sample) or
    T-1 (samples are the ends of the intervals)."""
    T = gyro.shape[-2]
    n = dt.shape[-1] if dt.ndim else T
    w = jnp.moveaxis(gyro, -2, 0)
    a = jnp.moveaxis(accel, -2, 0)
    h = jnp.moveaxis(dt, -1, 0) if dt.ndim else jnp.broadcast_to(dt, (n,))
    if n == T:
        w1 = jnp.concatenate([w[1:], w[-1:]], 0)
        a1 = jnp.concatenate([a[1:], a[-1:]], 0)
    else:
        w1, a1 = w[1:], a[1:]
    return w[:n], a[:n], w1, a1, h


def _chunk_scan(
    scheme, step_fn, b_g, b_a, noise, xs, batch, dtype, prefixes, blocks=True, lever=None
):
    """``lax.scan`` of the preintegration recursion over the leading (time) axis of ``xs``.

    ``xs = (dR, w0, a0, w1, a1, h, mask)``: with ``dR`` None the rotation is carried (the
    sequential recursion); otherwise it is given per step (already known in frame ``B_i``).
    Steps whose ``mask`` is False (padding) are identities. With ``blocks=False`` only the
    mean is carried (the accumulated blocks are ``None``): a graph that is differentiated
    then never traces the Jacobian and covariance blocks at all.
    """
    dR_given, w0, a0, w1, a1, h, mask = xs
    q_id = so3.quat_identity(batch, dtype)
    ident = _identity_acc(batch, dtype) if blocks else None

    def body(carry, x):
        dq, dv, dp, t, acc = carry
        dR, w0k, a0k, w1k, a1k, hk, mk = x
        if mk is not None:
            hk_safe = jnp.where(mk, hk, jnp.ones_like(hk))
        else:
            hk_safe = hk
        s = step_fn(
            scheme, dq if dR is None else dR, w0k, a0k, w1k, a1k, hk_safe, b_g, b_a, noise, lever
        )
        step = _Acc(s.F, s.Q15, s.Q9) if blocks else None
        a_k = s.acc
        if mk is not None:
            step = jax.tree_util.tree_map(
                lambda x_, i_: jnp.where(mk.reshape(mk.shape + (1,) * (x_.ndim - mk.ndim)), x_, i_),
                step,
                ident if blocks else None,
            )
            a_k = jnp.where(mk[..., None], a_k, 0.0)
            hk = jnp.where(mk, hk, 0.0)
        hv = hk[..., None]
        dp = dp + dv * hv + 0.5 * a_k * hv * hv
        dv = dv + a_k * hv
        if dR is None:
            dq = so3.quat_normalize(so3.quat_mul(dq, s.dq))
        acc = _combine(acc, step) if blocks else None
        carry = (dq, dv, dp, t + hk, acc)
        return carry, (carry if prefixes else None)

    z = jnp.zeros(tuple(batch) + (3,), dtype)
    carry0 = (q_id, z, z, jnp.zeros(tuple(batch), dtype), ident)
    return jax.lax.scan(body, carry0, (dR_given, w0, a0, w1, a1, h, mask))


class _Dense(NamedTuple):
    """A chunk summary in frame ``B_i``, dense, for the associative scan across chunks."""

    t: jax.Array
    dv: jax.Array
    dp: jax.Array
    Phi: jax.Array
    Q15: jax.Array
    Q9: jax.Array


def _to_dense(t, dv, dp, acc: _Acc) -> _Dense:
    Q9 = {k: acc.Q9.get(k) for k in blk.UPPER}
    return _Dense(
        t,
        dv,
        dp,
        blk.phi_to_dense(acc.Phi),
        blk.blocks_to_dense(acc.Q15),
        blk.blocks_to_dense(Q9)[..., :9, :9],
    )


def _combine_dense(e1: _Dense, e2: _Dense) -> _Dense:
    """``e2`` after ``e1``; all quantities in the same frame ``B_i``, so no rotation."""

    def sandwich(F, Q):
        return F @ Q @ jnp.swapaxes(F, -1, -2)

    return _Dense(
        e1.t + e2.t,
        e1.dv + e2.dv,
        e1.dp + e2.dp + e1.dv * e2.t[..., None],
        e2.Phi @ e1.Phi,
        blk.sym(sandwich(e2.Phi, e1.Q15) + e2.Q15),
        blk.sym(sandwich(e2.Phi[..., :9, :9], e1.Q9) + e2.Q9),
    )


def _chunk_length(T: int) -> int:
    """Samples per chunk for the parallel method: at most ~512 chunks side by side."""
    return max(16, -(-T // 512)) if T > 16 else T


def _pim_from_dense(dq, d: _Dense, bias):
    batch = dq.shape[:-1]
    return Preintegrated(
        delta_t=d.t,
        delta_q=so3.quat_normalize(dq),
        delta_v=d.dv,
        delta_p=d.dp,
        transition=d.Phi,
        cov15=d.Q15,
        cov=d.Q9,
        bias_hat=ImuBias(
            jnp.broadcast_to(bias.b_g, batch + (3,)), jnp.broadcast_to(bias.b_a, batch + (3,))
        ),
    )


def _time_major_batch(x, batch, tail):
    """``(T,) + own_batch + tail`` -> ``(T,) + batch + tail`` (batch axes right-aligned)."""
    own = x.ndim - 1 - len(tail)
    x = x.reshape(x.shape[:1] + (1,) * (len(batch) - own) + x.shape[1:])
    return jnp.broadcast_to(x, x.shape[:1] + tuple(batch) + tuple(tail))


def _preintegrate_fast(
    gyro, accel, dt, bias, noise, batch, method, scheme, lever=None, jacobians="analytic"
):
    T = gyro.shape[-2]
    n = dt.shape[-1] if dt.ndim else T  # dt of length T-1: Euler leaves the last sample unused
    dtype = gyro.dtype
    B = int(np.prod(batch, dtype=np.int64))
    flat = lambda x, tail: jnp.broadcast_to(x, tuple(batch) + tail).reshape((B,) + tail)  # noqa: E731
    pre = preintegration_step(scheme)
    if pre.uses_next_sample:  # samples k and k+1 side by side (as _pairs)

        def pair(x):
            x1 = x[..., 1:, :] if n < T else jnp.concatenate([x[..., 1:, :], x[..., -1:, :]], -2)
            return jnp.concatenate([x[..., :n, :], x1], -1)

        gyro, accel = pair(gyro), pair(accel)
    k = gyro.shape[-1]
    gyro_f = flat(gyro[..., :n, :], (n, k))
    accel_f = flat(accel[..., :n, :], (n, k))
    dt_f = jnp.broadcast_to(dt, (n,)) if dt.ndim <= 1 else flat(dt, (n,))
    b_g = bias.b_g if bias.b_g.ndim == 1 else flat(bias.b_g, (3,))
    b_a = bias.b_a if bias.b_a.ndim == 1 else flat(bias.b_a, (3,))
    if noise is None:
        var = jnp.zeros(12, dtype)
    else:
        var = noise.variances(dtype)
        var = var if var.ndim == 1 else flat(var, (12,))
    if lever is not None and lever.ndim > 1:
        lever = flat(lever, (3,))
    C = _fast_preint.num_chunks(B, n, method, dtype)
    # a scalar accelerometer density: the same noise on every axis (the kernel's R D Rᵀ = σ² I)
    iso = noise is None or jnp.ndim(noise.accelerometer_noise_density) == 0
    kernel = _fast_preint.KERNELS[pre.name]
    t, q, dv, dp, Phi, Q15, Q9 = kernel(
        gyro_f, accel_f, dt_f, b_g, b_a, var, C, lever, jacobians, iso
    )
    unflat = lambda x: x.reshape(tuple(batch) + x.shape[1:])  # noqa: E731
    return Preintegrated(
        delta_t=unflat(t),
        delta_q=unflat(q),
        delta_v=unflat(dv),
        delta_p=unflat(dp),
        transition=unflat(Phi),
        cov15=unflat(Q15),
        cov=unflat(Q9),
        bias_hat=ImuBias(
            jnp.broadcast_to(bias.b_g, tuple(batch) + (3,)),
            jnp.broadcast_to(bias.b_a, tuple(batch) + (3,)),
        ),
    )


@functools.partial(jax.jit, static_argnames=("scheme", "method", "jacobians", "prefixes", "fast"))
def _preintegrate(
    gyro, accel, dt, bias, noise, lever=None, *, scheme, method, jacobians, prefixes, fast=True
):
    nb = lambda x: x.shape[:-1] if x.ndim else ()  # noqa: E731
    batch = tuple(
        jnp.broadcast_shapes(
            gyro.shape[:-2],
            accel.shape[:-2],
            dt.shape[:-1],
            bias.b_g.shape[:-1],
            bias.b_a.shape[:-1],
            *(nb(jnp.asarray(x)) for x in jax.tree_util.tree_leaves(noise)),
            *(() if lever is None else (lever.shape[:-1],)),
        )
    )
    lanes = int(np.prod(batch, dtype=np.int64))
    method = dispatch.preint_method(method, lanes, gyro.shape[-2], gyro.dtype)
    run = dispatch.preintegrate_implementation(
        scheme,
        jacobians=jacobians,
        prefixes=prefixes,
        method=method,
        lanes=lanes,
        fast=fast,
        lever=lever is not None,
    )
    return run(
        PreintegrationInputs(
            gyro, accel, dt, bias, noise, batch, method, scheme, lever, jacobians, prefixes
        )
    )


class PreintegrationInputs(NamedTuple):
    """The preintegration engine's inputs once checked and dispatched, in the order every
    implementation reads them: the samples and ``dt``, the linearisation ``bias``, ``noise``
    (``None``: none), the broadcast ``batch`` shape, the resolved ``method``, then the
    static options and the optional lever arm (``None`` when not given)."""

    gyro: Any
    accel: Any
    dt: Any
    bias: ImuBias
    noise: Any
    batch: tuple
    method: str
    scheme: str
    lever: Any
    jacobians: str
    prefixes: bool


# Preintegration's implementations, one per kernel of the table's "preintegrate" rows, each
# taking the engine's PreintegrationInputs.


@dispatch.implements("preintegrate", "soa_preint_euler", "soa_preint_midpoint")
def _preintegrate_soa(inputs: PreintegrationInputs):
    a = inputs
    return _preintegrate_fast(
        a.gyro, a.accel, a.dt, a.bias, a.noise, a.batch, a.method, a.scheme, a.lever, a.jacobians
    )


@dispatch.implements("preintegrate", dispatch.GENERIC)
def _preintegrate_generic(inputs: PreintegrationInputs):
    gyro, accel, dt, bias, noise, batch, method, scheme, lever, jacobians, prefixes = inputs
    step_fn = _step if jacobians == "analytic" else _step_autodiff
    w0, a0, w1, a1, h = _pairs(gyro, accel, dt, scheme)
    dtype = w0.dtype
    b_g, b_a = bias.b_g, bias.b_a
    T = h.shape[0]
    h = _time_major_batch(h, batch, ())
    w0, a0, w1, a1 = (_time_major_batch(x, batch, (3,)) for x in (w0, a0, w1, a1))
    if method == "sequential":
        final, out = _chunk_scan(
            scheme,
            step_fn,
            b_g,
            b_a,
            noise,
            (None, w0, a0, w1, a1, h, None),
            batch,
            dtype,
            prefixes,
            lever=lever,
        )
        dq, dv, dp, t, acc = out if prefixes else final
        pim = _finish(t, dq, dv, dp, acc, ImuBias(b_g, b_a))
    else:
        # 1. rotations ΔR_ik: an associative scan of the (normalised) increments
        q_id = so3.quat_identity(batch, dtype)
        incr = step_fn(
            scheme, jnp.broadcast_to(q_id, (T,) + batch + (4,)), w0, a0, w1, a1, h, b_g, b_a, None
        ).dq
        incl = so3.quat_normalize(
            jax.lax.associative_scan(so3.quat_mul, so3.quat_normalize(incr), axis=0)
        )
        dR = jnp.concatenate([q_id[None], incl[:-1]], axis=0)
        # 2. chunks of L steps side by side, each step already in frame B_i
        L = _chunk_length(T)
        C = -(-T // L)
        pad = C * L - T

        def chunked(x, fill=0):  # (T, ...) -> (L, C, ...), time k = c L + l
            if pad:
                x = jnp.concatenate([x, jnp.full((pad,) + x.shape[1:], fill, x.dtype)], 0)
            return jnp.swapaxes(x.reshape((C, L) + x.shape[1:]), 0, 1)

        mask = chunked(jnp.ones((T,) + batch, bool)) if pad else None
        # padded steps are masked out, but their rotations are unit quaternions: the
        # autodiff step normalises dR ⊗ dq, and a zero dR's NaN reached the reverse-mode
        # gradient through the mask's where
        xs = (chunked(dR, q_id),) + tuple(chunked(x) for x in (w0, a0, w1, a1, h)) + (mask,)
        final, out = _chunk_scan(
            scheme, step_fn, b_g, b_a, noise, xs, (C,) + batch, dtype, prefixes, lever=lever
        )
        # 3. an associative scan across the chunk summaries (dense: few, cheap to compile)
        _, dv, dp, t, acc = final
        chunk_prefix = jax.lax.associative_scan(_combine_dense, _to_dense(t, dv, dp, acc), axis=0)
        if prefixes:
            first = _to_dense(
                jnp.zeros_like(t[:1]),
                jnp.zeros_like(dv[:1]),
                jnp.zeros_like(dp[:1]),
                _identity_acc((1,) + batch, dtype),
            )
            excl = jax.tree_util.tree_map(
                lambda a_, b_: jnp.concatenate([a_, b_[:-1]], 0), first, chunk_prefix
            )
            _, dv_l, dp_l, t_l, acc_l = out  # (L, C, ...)
            inner = _to_dense(t_l, dv_l, dp_l, acc_l)
            whole = _combine_dense(jax.tree_util.tree_map(lambda x: x[None], excl), inner)
            whole = jax.tree_util.tree_map(
                lambda x: jnp.swapaxes(x, 0, 1).reshape((C * L,) + x.shape[2:])[:T], whole
            )
            pim = _pim_from_dense(incl, whole, ImuBias(b_g, b_a))
        else:
            last = jax.tree_util.tree_map(lambda x: x[-1], chunk_prefix)
            pim = _pim_from_dense(incl[-1], last, ImuBias(b_g, b_a))
    if prefixes:  # time first inside the scan -> time before the last axes
        pim = Preintegrated(
            delta_t=jnp.moveaxis(pim.delta_t, 0, -1),
            delta_q=jnp.moveaxis(pim.delta_q, 0, -2),
            delta_v=jnp.moveaxis(pim.delta_v, 0, -2),
            delta_p=jnp.moveaxis(pim.delta_p, 0, -2),
            transition=jnp.moveaxis(pim.transition, 0, -3),
            cov15=jnp.moveaxis(pim.cov15, 0, -3),
            cov=jnp.moveaxis(pim.cov, 0, -3),
            bias_hat=jax.tree_util.tree_map(lambda x: jnp.moveaxis(x, 0, -2), pim.bias_hat),
        )
    return pim
