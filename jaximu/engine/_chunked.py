"""Long sequences in time chunks that run side by side as lanes: the mean's and the
covariance's (docs/DESIGN.md, "Dispatch" and "On a GPU").

A sequence of ``n`` steps is cut into ``C`` chunks of ``L`` steps (the last padded with
steps of ``dt = 0``: exact identities of every scheme, with no noise), lane ``b·C + c``
holding chunk ``c`` of sequence ``b``. Every chunk runs on the structure-of-arrays kernels
(:mod:`jaximu.kernels.fast`) at once; what each chunk leaves is then composed along the sequence,
in order or as an associative (parallel prefix) scan:

* the mean: a chunk run from the identity without gravity gives its exact deltas
  ``(ΔR, Δp, Δv, Δt)`` (:func:`jaximu.integrators.compose_deltas`);
* the covariance: a chunk run with ``P = 0`` gives its noise ``Q_c`` and, multiplying the
  steps' transitions, its ``Φ_c`` (run from the identity, only their bias columns: the
  others follow from the chunk's deltas, :func:`local_transition`);
  ``P ↦ Φ_c P Φ_cᵀ + Q_c`` composes associatively
  (:func:`jaximu.schemes._blocks.compose_transitions`). In a still world the chunks need no
  mean first: ``Φ`` does not depend on ``p``, ``v`` or gravity, and a chunk run from the identity
  has the transition and noise of the chunk run from its true start ``R_c`` in coordinates
  turned by ``R_c`` (``T = blockdiag(R_c, R_c, R_c, I, I)`` for the world-frame rotation
  error, ``blockdiag(I, R_c, R_c, I, I)`` for the body-frame one), so one pass gives the
  deltas, ``Φ_c`` and ``Q_c``. A turning world (whose maps hold ``ω`` in W) and Euler angles
  (whose step depends on the angles themselves) run the chunks from their true starts,
  which the mean's own pass gives. Every covariance stored: the chunks run a second time,
  from their start states and covariances, storing every step.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaximu.engine import _dispatch as dispatch
from jaximu.geometry import so3
from jaximu.kernels import fast as _fast
from jaximu.kernels import lane_forms, lane_math
from jaximu.kernels import soa as _soa
from jaximu.kernels.lane_math import SOA
from jaximu.schemes import _blocks as blk
from jaximu.schemes import integrators
from jaximu.schemes._blocks import UPPER
from jaximu.schemes.integrators import compose_deltas

# --------------------------------------------------------------------------- layout


def chunk_length(steps, chunks) -> int:
    """Steps of one chunk: ``steps / chunks`` rounded up to a length the kernel's own time
    chunks divide (:func:`jaximu.kernels.soa.whole_chunks`: a remainder is a second loop body that
    LLVM compiles again)."""
    return _soa.whole_chunks(-(-steps // chunks))


def chunk_lanes(gyro, accel, dt, C, L, extra):
    """Samples ``(B, n + extra, k)`` and steps ``dt`` ``(B, n)`` as ``B·C`` lanes of ``L``
    steps (and ``L + extra`` samples: a scheme that uses sample k+1 reads the next chunk's
    first), lane ``b·C + c`` chunk ``c`` of sequence ``b``; the steps past ``n`` have
    ``dt = 0`` (exact identities) and repeat the last sample."""
    B, n = dt.shape
    pad = C * L - n
    if pad:
        dt = jnp.pad(dt, ((0, 0), (0, pad)))
        gyro, accel = (jnp.pad(x, ((0, 0), (0, pad), (0, 0)), mode="edge") for x in (gyro, accel))
    # computed in the program: as a numpy constant (C·(L+1) indices) it is compiled into
    # it, and the compile grew with the sequence (2^25 steps: 3.8 against 1.1 s)
    idx = (
        jnp.arange(C, dtype=jnp.int32)[:, None] * L
        + jnp.arange(L + extra, dtype=jnp.int32)[None, :]
    )
    lanes = lambda x: x[:, idx].reshape((B * C,) + idx.shape[1:] + x.shape[2:])
    return lanes(gyro), lanes(accel), dt.reshape(B * C, L)


def repeat_lanes(x, C):
    """A per-sequence value ``(B, ·)`` for each of its ``C`` chunks' lanes ``(B·C, ·)``; a
    shared one (``None``, or no lane axis: ``ndim < 2``) as it is."""
    return x if x is None or x.ndim < 2 else jnp.repeat(x, C, axis=0)


def by_chunk(x, B, C):
    """Lanes ``(B·C, ·)`` as ``(C, B, ·)``: chunk first."""
    return jnp.moveaxis(x.reshape((B, C) + x.shape[1:]), 1, 0)


def by_lane(x):
    """``(C, B, ·)`` as lanes ``(B·C, ·)``."""
    return jnp.moveaxis(x, 0, 1).reshape((-1,) + x.shape[2:])


# --------------------------------------------------------------------------- the mean's deltas


def identity_deltas(B, dtype):
    """The deltas of a chunk of no steps, ``(1, B, ·)``."""
    return (
        jnp.zeros((1, B, 4), dtype).at[..., 0].set(1),
        jnp.zeros((1, B, 3), dtype),
        jnp.zeros((1, B, 3), dtype),
        jnp.zeros((1, B), dtype),
    )


def total_deltas(deltas):
    """The product of chunk deltas ``(C, B, ·)`` in order, reduced pairwise as a tree
    (``log2 C`` levels): ``(B, ·)``."""
    B, dtype = deltas[3].shape[1], deltas[3].dtype
    while deltas[0].shape[0] > 1:
        if deltas[0].shape[0] % 2:  # an identity chunk pads to an even count
            deltas = tuple(
                jnp.concatenate([d, e]) for d, e in zip(deltas, identity_deltas(B, dtype))
            )
        deltas = compose_deltas(tuple(d[0::2] for d in deltas), tuple(d[1::2] for d in deltas))
    return tuple(d[0] for d in deltas)


def deltas_before(deltas):
    """The deltas from the sequence's start to each chunk's start (an exclusive parallel
    prefix scan of ``(C, B, ·)`` chunk deltas): ``(C, B, ·)``."""
    B, dtype = deltas[3].shape[1], deltas[3].dtype
    ident = identity_deltas(B, dtype)
    if deltas[0].shape[0] == 1:
        return ident
    prefix = jax.lax.associative_scan(compose_deltas, tuple(d[:-1] for d in deltas))
    return tuple(jnp.concatenate([e, d]) for e, d in zip(ident, prefix))


def prefix_scan(combine, elems, identity):
    """The inclusive prefix of ``elems`` (leaves ``(N, ·)``) under the associative
    ``combine(earlier, later)``, in ``⌈log2 N⌉`` levels: at level ``d`` every element ``i``
    becomes ``combine(x[i - 2^d], x[i])``, ``identity`` (leaves ``(1, ·)``, with
    ``combine(identity, x) = x``) standing in before the first (Hillis–Steele). The levels are
    one loop whose body is one ``combine`` over all ``N`` elements: traced and compiled once,
    where ``jax.lax.associative_scan`` (about ``N`` combines in all, not ``N log2 N``) unrolls
    about ``2 log2 N`` of them into the program (the accelerator's covariance of 256 steps, 8
    chunks, final and every one stored, took 14–15 s of compile on the CPU that way, 5–6 s as a
    loop)."""
    N = jax.tree_util.tree_leaves(elems)[0].shape[0]
    levels = (N - 1).bit_length()

    def level(d, x):
        before = jax.tree_util.tree_map(
            lambda e, y: jax.lax.dynamic_slice_in_dim(
                jnp.concatenate([jnp.broadcast_to(e, y.shape), y]), N - (1 << d), N
            ),
            identity,
            x,
        )
        return combine(before, x)

    if levels < 2:  # one level: no loop
        return level(0, elems) if levels else elems
    return jax.lax.fori_loop(0, levels, level, elems)


def apply_deltas(q, p, v, g, d):
    """The state ``(q, p, v)`` moved by deltas ``d`` under gravity ``g``
    (:func:`jaximu.integrators.apply_deltas`), the quaternion renormalised."""
    q1, p1, v1 = integrators.apply_deltas(q, p, v, g, d)
    return so3.quat_normalize(q1), p1, v1


# --------------------------------------------------------------------------- the covariance


def runs_from_identity(omega, attitude) -> bool:
    """Whether the covariance's chunks run from the identity (one pass for the deltas and
    the summaries: a still world, an attitude form whose step is a right multiplication of
    ``R``), or from their true starts (a turning world, Euler angles): module docstring."""
    return omega is None and attitude != "euler_angles"


def _rotation_maps(R, rotated):
    """``blockdiag`` of ``R`` on the blocks ``rotated``: :func:`jaximu.schemes._blocks.congruence`'s
    rows."""
    return {i: {i: R} for i in rotated}


def _in_start_frame(F, Q, R, rotated, pattern):
    """A chunk's ``(Φ, Q)`` from its run from the identity in the coordinates of its true
    start ``R`` (``T Φ Tᵀ``, ``T Q Tᵀ``; module docstring)."""
    if not rotated:
        return F, Q
    F = blk.rotate_rows(F, R, rotated, SOA)
    like = jax.tree_util.tree_leaves(Q)[0]
    F = blk.conform_rows(F, pattern, like.shape, like.shape[2:], like.dtype, SOA)
    return F, blk.congruence(Q, _rotation_maps(R, rotated), SOA)


def _frame(q):
    """``R(q)`` of quaternions ``(…, B, 4)`` as blocks ``(3, 3, …, B)``."""
    return jnp.moveaxis(so3.quat_to_matrix(q), (-2, -1), (0, 1))


def compose_covariance(P0, F, Q, pattern, rotated, save_all, on, start=None, deltas=None, g=None):
    """``P_{c+1} = Φ_c P_c Φ_cᵀ + Q_c`` along the chunks: in order (the CPU: one compiled
    kernel, :func:`jaximu.kernels.soa.one_kernel`) or as an associative scan of the pairs (an
    accelerator: ``log2 C`` levels of launches, not ``C``).

    ``P0``: upper blocks ``(3, 3, B)``; ``F``: the chunks' transition leaves
    (:func:`jaximu.schemes._blocks.rows_leaves` of ``pattern``) and ``Q`` the 15 upper blocks of
    their noise, ``(C, 3, 3, B)`` (scalars ``(C, B)``). Chunks run from the identity
    (``rotated``: the blocks their start's rotation turns, :func:`_in_start_frame`) move the
    state ``start = (q, p, v)`` ``(B, ·)`` by their ``deltas`` ``(C, B, ·)`` under gravity
    ``g`` ``(B, 3)``, which gives each chunk's start. Returns ``(P, end, starts)``: the final
    upper blocks, the final state (``None`` without deltas) and, with ``save_all``, each
    chunk's start ``((q, p, v) (C, B, ·), P blocks (C, 3, 3, B))`` (else ``None``)."""
    moving = deltas is not None
    if on == dispatch.CPU:

        def body(carry, xs, g):
            x, P = carry
            leaves, Qc, d = xs
            Fc, Qc = _in_start_frame(
                blk.rows_from_leaves(leaves, pattern),
                dict(zip(UPPER, Qc)),
                _frame(x[0]) if moving else None,
                rotated,
                pattern,
            )
            new = blk.symmetrize_diagonal(
                blk.add_blocks(blk.congruence(dict(zip(UPPER, P)), Fc, SOA), Qc), SOA
            )
            x1 = apply_deltas(*x, g, d) if moving else x
            return (x1, tuple(new[k] for k in UPPER)), ((x, P) if save_all else None)

        def run(x, P0, F, Q, deltas, g):  # closes over no traced value (one_kernel)
            return jax.lax.scan(lambda c, xs: body(c, xs, g), (x, P0), (F, Q, deltas))

        # one chunk: no loop (XLA:CPU's kernel emitter aborts on the call whose loop of one
        # trip it removes, its outputs then its parameters)
        call = run if F[0].shape[0] == 1 else lambda *a: _soa.one_kernel(run, *a)
        (end, P), starts = _soa.replicated(
            call(
                *_soa.replicated(
                    (
                        start if moving else None,
                        tuple(P0[k] for k in UPPER),
                        tuple(F),
                        tuple(Q),
                        deltas,
                        g,
                    )
                )
            )
        )
        if starts is not None:
            starts = (starts[0], dict(zip(UPPER, starts[1])))
        return dict(zip(UPPER, P)), end, starts
    # an accelerator: the chunks' starts by a parallel prefix of their deltas, the pairs
    # (Φ_c, Q_c) in the sequence's coordinates, (I, P0) first, and their parallel prefix
    before = apply_deltas(*(x[None] for x in start), g, deltas_before(deltas)) if moving else None
    # the scan's axis leads every leaf; the block algebra runs with it last, as a lane axis
    last = lambda x: jnp.moveaxis(x, 0, -1)
    first = lambda x: jnp.moveaxis(x, -1, 0)
    Fr, Qr = _in_start_frame(
        blk.rows_from_leaves([last(x) for x in F], pattern),
        dict(zip(UPPER, (last(x) for x in Q))),
        jnp.swapaxes(_frame(before[0]), -1, -2) if moving else None,
        rotated,
        pattern,
    )
    like = Qr[(0, 0)]
    ident = blk.conform_rows(
        {}, pattern, like.shape[:-1] + (1,), like.shape[2:-1] + (1,), like.dtype, SOA
    )
    elems = (
        tuple(first(x) for x in blk.rows_leaves(_join(ident, Fr, pattern), pattern)),
        tuple(
            first(
                jnp.concatenate(
                    [jnp.broadcast_to(P0[k][..., None], like.shape[:-1] + (1,)), Qr[k]], -1
                )
            )
            for k in UPPER
        ),
    )

    def combine(a, b):
        Fa, Fb = (blk.rows_from_leaves([last(y) for y in x[0]], pattern) for x in (a, b))
        Fn, Qn = blk.compose_transitions(
            (Fa, {k: last(y) for k, y in zip(UPPER, a[1])}),
            (Fb, {k: last(y) for k, y in zip(UPPER, b[1])}),
            SOA,
        )
        sh = Qn[(0, 0)].shape
        Fn = blk.conform_rows(Fn, pattern, sh, sh[2:], like.dtype, SOA)
        return (
            tuple(first(x) for x in blk.rows_leaves(Fn, pattern)),
            tuple(first(blk.sym(Qn[k], SOA) if k[0] == k[1] else Qn[k]) for k in UPPER),
        )

    # P_0 (= P0) ... P_C, (C + 1, ...); (I, 0) before the first
    zero = tuple(jnp.zeros_like(x[:1]) for x in elems[1])
    _, P_all = prefix_scan(combine, elems, (tuple(x[:1] for x in elems[0]), zero))
    P = {k: x[-1] for k, x in zip(UPPER, P_all)}
    end = apply_deltas(*start, g, total_deltas(deltas)) if moving else None
    starts = None
    if save_all:
        starts = (before, {k: x[:-1] for k, x in zip(UPPER, P_all)})
    return P, end, starts


def _join(ident, F, pattern):
    """The identity's rows then the chunks' along the last axis (the associative scan's
    first element)."""
    out = {}
    for i, row in pattern.items():
        out[i] = {}
        for j, kind in row.items():
            if kind == "I":
                out[i][j] = "I"
            elif kind == "s":
                out[i][j] = blk.ScaledIdentity(jnp.concatenate([ident[i][j].s, F[i][j].s], -1))
            else:
                out[i][j] = jnp.concatenate([ident[i][j], F[i][j]], -1)
    return out


BIAS_COLUMNS = {0: {3: "X"}, 1: {3: "X", 4: "X"}, 2: {3: "X", 4: "X"}}
"""The block columns of a chunk's transition that its kernel multiplies when the chunk runs
from the identity in a still world (:func:`local_transition`): those of the biases."""


def local_transition(bias_leaves, deltas, world_error, pattern):
    """The leaves of a chunk's transition ``Φ_c`` in the form ``pattern``
    (:func:`jaximu.schemes._blocks.rows_leaves`, each ``(C, 3, 3, B)`` or ``(C, B)``), the
    chunk run from the identity without gravity in a still world, from its bias columns
    ``bias_leaves`` (:data:`BIAS_COLUMNS`) and its deltas ``(ΔR, Δp, Δv, Δt)``
    ``(C, B, ·)``. The other columns are exact in closed form, for every scheme: every
    step is a rotation ``R`` times the step's body-frame terms, so a rotation error at the
    start (``R₀ = I``) turns the whole run, ``δp = −[Δp]× δθ`` and ``δv = −[Δv]× δθ``, and
    ends as ``δθ`` (the world-frame error, ``world_error``) or ``ΔRᵀ δθ`` (the body-frame
    one); the position and velocity errors at the start move as ``δp + Δt δv`` and ``δv``."""
    blocks = lambda X: jnp.moveaxis(X, (-2, -1), (1, 2))  # (C, B, 3, 3) -> (C, 3, 3, B)
    dR, dp, dv, dT = deltas
    rows = blk.rows_from_leaves(bias_leaves, BIAS_COLUMNS)
    rows[0][0] = "I" if world_error else blocks(jnp.swapaxes(so3.quat_to_matrix(dR), -1, -2))
    rows[1].update({0: blocks(so3.skew(-dp)), 1: "I", 2: blk.ScaledIdentity(dT)})
    rows[2].update({0: blocks(so3.skew(-dv)), 2: "I"})
    return tuple(blk.rows_leaves(rows, pattern))


def _start_indices(C, L, n):
    """Each chunk's start as an index into the states after every step (``-1``: the
    initial state), clamped to the last state: chunks past the end are all padding."""
    return jnp.minimum(jnp.arange(C) * L, n) - 1


def covariance(
    sch,
    form,
    q,
    p,
    v,
    b_g,
    b_a,
    P0,
    gyro,
    accel,
    dt,
    g,
    var,
    jacobians,
    omega=None,
    coriolis="exact",
    lever=None,
    save_all=False,
):
    """Mean and covariance of ``B`` sequences in time chunks (module docstring): the final
    ``(q, p, v, P)`` ``(B, ·)`` or, with ``save_all``, those after every step ``(B, n, ·)``
    (``q`` in the attitude form ``form``), and Euler angles' locked flags ``(B,)`` (or
    ``None``). The inputs as :func:`jaximu.kernels.fast.propagate_cov`'s (flat lanes; the samples
    already the body's, ``lever`` the sensor's lever arm for the Jacobians; ``dt`` ``(n,)``
    or ``(B, n)``; ``var`` the noise's ``σ²`` ``(12,)`` or ``(B, 12)``), ``q`` in the form,
    normalised."""
    B, n = gyro.shape[0], dt.shape[-1]
    dtype = gyro.dtype
    on = dispatch.backend()
    C = dispatch.covariance_chunks(B, n, dtype)
    L = chunk_length(n, C)
    extra = int(sch.uses_next_sample)
    gyro_c, accel_c, dt_c = chunk_lanes(gyro, accel, jnp.broadcast_to(dt, (B, n)), C, L, extra)
    rep = lambda x: repeat_lanes(x, C)
    omega_c, lever_c, var_c = rep(omega), rep(lever), rep(var)
    g_b = jnp.broadcast_to(g, (B, 3))
    local = runs_from_identity(omega, form.name)
    world_error = _fast.world_error_frame(omega, False, form)
    pattern = _fast.transition_pattern(omega is not None, world_error)
    locked = None
    if local:  # from the identity, without gravity: the deltas, Φ_c and Q_c in one pass
        q_id = jnp.zeros((B * C, 4), dtype).at[:, 0].set(1)
        x_s = lane_forms.from_quat(form, q_id)
        p_s = v_s = jnp.zeros((B * C, 3), dtype)
        g_s = jnp.zeros(3, dtype)
    else:  # from the true starts: the mean's own pass first
        mean = _fast.propagate_mean(
            sch, q, p, v, b_g, b_a, gyro, accel, dt, g, True, omega, coriolis, form
        )
        idx = _start_indices(C, L, n)

        def starts(x, x0):  # (B, n, ·) -> the chunks' starts, lanes (B·C, ·)
            at = jnp.take(x, jnp.maximum(idx, 0), axis=1)
            return jnp.where((idx < 0)[None, :, None], x0[:, None], at).reshape(B * C, -1)

        x_s, p_s, v_s = (starts(x, x0) for x, x0 in zip(mean[:3], (q, p, v)))
        g_s = rep(g_b)
        if len(mean) > 3:
            locked = mean[3][:, -1, 0]
    zeros = jnp.zeros((B * C, 15, 15), dtype)
    # from the identity the kernel multiplies only the transitions' bias columns: the
    # others follow from the chunk's deltas (local_transition)
    accumulated = BIAS_COLUMNS if local else pattern
    out = _fast.propagate_cov(
        x_s,
        p_s,
        v_s,
        rep(b_g),
        rep(b_a),
        zeros,
        gyro_c,
        accel_c,
        dt_c,
        g_s,
        var_c,
        sch,
        jacobians,
        omega_c,
        coriolis,
        lever_c,
        False,
        form,
        transition=accumulated,
        padded=True,
    )
    soa = lambda x: jnp.moveaxis(x.reshape((B, C) + x.shape[1:]), (0, 1), (-1, 0))
    Q = tuple(soa(x) for x in out[3])  # (C, 3, 3, B)
    F = tuple(soa(x) for x in out[4])
    deltas = start = None
    rotated = ()
    if local:  # the chunks' deltas move the state from one chunk's start to the next
        deltas = (lane_forms.to_quat(form, out[0]), out[1], out[2], jnp.sum(dt_c, axis=-1))
        deltas = tuple(by_chunk(x, B, C) for x in deltas)  # (C, B, ·)
        F = local_transition(F, deltas, world_error, pattern)
        start = (so3.quat_normalize(lane_forms.to_quat(form, q)), p, v)
        rotated = (0, 1, 2) if world_error else (1, 2)
    Pb = dict(zip(UPPER, _fast.dense_to_lanes(P0)))
    if world_error:  # the user's body-frame rotation error into the world frame
        Pb = blk.congruence(Pb, {0: {0: _frame(start[0])}}, SOA)
    P, end, starts = compose_covariance(
        Pb, F, Q, pattern, rotated, save_all, on, start, deltas, g_b
    )
    if not save_all:
        if local:
            xf, pf, vf = lane_forms.from_quat(form, end[0]), end[1], end[2]
        else:
            xf, pf, vf = (x[:, -1] for x in mean[:3])
        if world_error:
            P = blk.congruence(P, {0: {0: lane_math._bt(_frame(end[0]))}}, SOA)
        return xf, pf, vf, _fast.lanes_to_dense(tuple(P[k] for k in UPPER)), locked
    # every covariance: the chunks again, from their starts, storing every step
    if local:
        x_s = lane_forms.from_quat(form, by_lane(starts[0][0]))
        p_s, v_s = by_lane(starts[0][1]), by_lane(starts[0][2])
    # (C, 3, 3, B) -> (3, 3, B·C), lane b·C + c
    lanes = lambda x: jnp.moveaxis(x, 0, -1).reshape(x.shape[1:3] + (B * C,))
    P_starts = {k: lanes(x) for k, x in starts[1].items()}
    if world_error:  # the starts' covariances in the body frame, as the kernel keeps them
        P_starts = blk.congruence(
            P_starts, {0: {0: lane_math._bt(_frame(by_lane(starts[0][0])))}}, SOA
        )
    P_s = _fast.lanes_to_dense(tuple(P_starts[k] for k in UPPER))
    x_t, p_t, v_t, P_t, *_ = _fast.propagate_cov(
        x_s,
        p_s,
        v_s,
        rep(b_g),
        rep(b_a),
        P_s,
        gyro_c,
        accel_c,
        dt_c,
        rep(g_b),
        var_c,
        sch,
        jacobians,
        omega_c,
        coriolis,
        lever_c,
        True,
        form,
        padded=True,
    )
    seq = lambda x: x.reshape((B, C * L) + x.shape[2:])[:, :n]
    return seq(x_t), seq(p_t), seq(v_t), seq(P_t), locked
