"""Structure-of-arrays (SoA) building blocks of the fast kernels: one home for each.

Why this layout (measured on this project's 2-core AVX2 x86 CPU, JAX 0.10.2; the figures
and the reasoning are in docs/DESIGN.md, "Kernel layout"):

* **Structure of arrays.** Inside the scan every per-sample quantity is a tuple of ``(B,)``
  arrays (one per component; :class:`~jaximu.geometry._vec.V3` for vectors) and every 3×3 covariance
  block is a ``(3, 3, B)`` array (batch minor). Each XLA loop fusion is then a plain loop
  over the batch that LLVM vectorises. With the ``(B, 3)`` layout the fusions read several
  components of one buffer through the scan's dynamic-slice index, which LLVM cannot
  vectorise (scalar code).
* **No concatenates in the loop** (``jnp.stack`` becomes a scalar select loop on XLA CPU);
  vectors and blocks are assembled by broadcasting against constant one-hot tensors.
* **Polynomial sin/cos.** ``jnp.sin``/``jnp.cos`` are scalar libm calls on XLA CPU. The half
  angle of the exponential uses even polynomials in θ² (exact to rounding for θ ≤ π/2, no
  sqrt/division, NaN-free gradient at 0); a Cody-Waite range-reduced path handles larger
  angles and runs only when some element needs it (``lax.cond``).
* **Stage boundaries.** XLA CPU has no multi-output fusion: a value read by several fusions is
  recomputed in each (and a transposed read recomputes it again). Costly intermediate values
  are materialised by computing them inside ``lax.cond`` with identical branches
  (:func:`_stage`).
* **Blocking.** Batches are processed in blocks of lanes (state in L1/L2), and time in chunks
  of ``K`` samples whose inputs are transposed to time-major per chunk (:func:`_time_chunks`).
"""

from __future__ import annotations

import math
import os

import jax
import jax.numpy as jnp
from jax.experimental.xla_metadata import set_xla_metadata

from jaximu.kernels import device
from jaximu.kernels.lane_math import _materialise

_CHUNK = (64, 16)  # preferred largest / smallest time chunk


HALO = 2
"""Samples before a time chunk that :func:`_time_chunks` gives its ``samples`` function
(two: the held last sample of a next-sample scheme takes the derivative of the one before
it)."""


# ----------------------------------------------------------------------------- drivers


def _components(x):
    return tuple(x[..., i] for i in range(x.shape[-1]))


def _block_size(n, lanes):
    """Lanes per batch block: ``n`` itself when at most ``lanes``, otherwise a divisor of
    ``n`` between ``lanes/4`` and ``lanes`` (no padding), or ``n`` when none exists."""
    if n <= lanes:
        return n
    for nb in range(-(-n // lanes), n // (lanes // 4) + 1):
        if n % nb == 0:
            return n // nb
    return n


def _chunk_size(T):
    hi, lo = _CHUNK
    if T <= hi:
        return T
    for K in range(hi, lo - 1, -1):
        if T % K == 0:
            return K
    return 32  # remainder handled by a second (shorter) segment


def whole_chunks(L):
    """The shortest length ``≥ L`` that :func:`_time_chunks` cuts into equal chunks (at most
    :data:`_CHUNK` ``[0]`` steps, or one with a divisor between the two bounds): a
    remainder chunk is a second loop body in the kernel, which LLVM compiles again (the
    final state of 1 × 10^5 float64 samples as 64 chunks of 1563 steps compiled in 1.3 s,
    of 1568 in 0.8 s). Callers that cut a sequence into chunks of their own pad to it."""
    while L % _chunk_size(L):
        L += 1
    return L


def _time_chunks(step, carry, gyro, accel, dt, consts, save, next_sample=False, samples=None):
    """Scan ``step(carry, w, a, h, consts) -> carry`` over time for one batch block.

    gyro, accel: ``(Bc, T, 3)`` (or more samples); dt: ``(T,)`` or ``(Bc, T)``, the T steps.
    Inputs are transposed to
    time-major ``(K, Bc)`` components one chunk of K samples at a time (cache-resident).
    With ``next_sample`` the inputs hold ``T + 1`` samples and ``w``, ``a`` are 6-tuples:
    samples k and k+1, both read from the same chunk (no paired copy of the inputs).
    ``save(carry) -> tuple of (Bc, n)`` arrays written at every sample into ``(Bc, T, n)``
    buffers (or ``None``).

    ``samples(w, a, hw, k) -> (w, a)``: the chunk's samples changed before the steps read
    them (a sensor's into the body's, :func:`jaximu.sensor.chunk_to_body`), on the chunk in
    cache rather than as a pass over the whole input. ``w``, ``a`` are 3-tuples of
    ``(n + 3, Bc)`` components: the chunk's ``n`` samples (``L``, or ``L + 1`` with
    ``next_sample``) with :data:`HALO` neighbours before and one after (at the sequence's
    ends they repeat the end sample); ``hw`` the ``n + 2`` spacings between them
    (``dt`` of the interval starting at each, the index clamped into ``dt``), ``(n + 2,)``
    or ``(n + 2, Bc)``; ``k`` the chunk samples' indices ``(n,)``. It returns the ``n``
    chunk samples.
    """
    # steps: dt's length (the samples may hold one more that only ``samples`` reads)
    Bc, T = gyro.shape[0], dt.shape[-1]
    K = _chunk_size(T)
    nC, rem = divmod(T, K)

    def window(x, t0, n, axis, after):
        """``n`` entries of ``x`` from ``t0`` along ``axis``; with ``samples``, with
        :data:`HALO` before and ``after`` after (indices clamped into ``x``)."""
        main = jax.lax.dynamic_slice_in_dim(x, t0, n, axis=axis)
        if samples is None:
            return main
        size = x.shape[axis]
        at = lambda i: jax.lax.dynamic_slice_in_dim(  # noqa: E731
            x, jnp.clip(i, 0, size - 1), 1, axis=axis
        )
        return jnp.concatenate(
            [at(t0 - HALO + j) for j in range(HALO)]
            + [main]
            + [at(t0 + n + j) for j in range(after)],
            axis=axis,
        )

    def comps(x, t0, L):
        c = window(x, t0, L + int(next_sample), 1, 1)
        ct = _materialise(jnp.transpose(c, (2, 1, 0)))  # (3, ·, Bc), transposed once
        return tuple(ct[i] for i in range(ct.shape[0]))

    def both(t0, L):
        w, a = comps(gyro, t0, L), comps(accel, t0, L)
        if samples is not None:  # changed once per chunk, in cache
            n = L + int(next_sample)
            hw = window(dt, t0, L, dt.ndim - 1, int(next_sample))  # n + HALO spacings
            hw = hw if dt.ndim == 1 else jnp.transpose(hw)  # (n + 2, Bc)
            w, a = _materialise(tuple(tuple(x) for x in samples(w, a, hw, t0 + jnp.arange(n))))
        if next_sample:
            return (
                tuple(c[:L] for c in w) + tuple(c[1:] for c in w),
                tuple(c[:L] for c in a) + tuple(c[1:] for c in a),
            )
        return w, a

    def hs(t0, L):
        if dt.ndim == 1:
            return jax.lax.dynamic_slice_in_dim(dt, t0, L, axis=0)
        return jnp.transpose(jax.lax.dynamic_slice_in_dim(dt, t0, L, axis=1))  # (L, Bc)

    def segment(state, t0, L):
        carry, bufs = state

        def body(st, xs):
            c, bufs = st
            t, w, a, h = xs
            c = step(c, w, a, h, consts)
            if save is not None:
                bufs = tuple(
                    jax.lax.dynamic_update_index_in_dim(b, y, t, 1) for b, y in zip(bufs, save(c))
                )
            return (c, bufs), None

        xs = (t0 + jnp.arange(L),) + both(t0, L) + (hs(t0, L),)
        return jax.lax.scan(body, (carry, bufs), xs)[0]

    bufs = ()
    if save is not None:
        bufs = tuple(jnp.zeros((Bc, T) + y.shape[1:], y.dtype) for y in save(carry))
    state = (carry, bufs)
    if nC:
        state = jax.lax.scan(lambda s, i: (segment(s, i * K, K), None), state, jnp.arange(nC))[0]
    if rem:
        state = segment(state, nC * K, rem)
    return state


def _mesh_axes(args):
    """``(mesh, axes)``: the current mesh (``jax.set_mesh``) or, without one, that of the
    arguments' types (arrays sharded on a mesh carry it), and its axes not already manual
    (inside a ``shard_map``) — or ``(None, ())``."""
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty:
        typed = (
            getattr(jax.typeof(x).sharding, "mesh", None) for x in jax.tree_util.tree_leaves(args)
        )
        mesh = next((m for m in typed if m is not None and not m.empty), mesh)
    if mesh.empty:
        return None, ()
    axes = tuple(
        a
        for a, kind in zip(mesh.axis_names, mesh.axis_types)
        if kind != jax.sharding.AxisType.Manual
    )
    return mesh, axes


ONE_KERNEL = {"xla_cpu_small_call": "true", "inlineable": "false"}
"""XLA frontend attributes that make XLA:CPU compile a call as one kernel (docs/DESIGN.md,
"One kernel per block")."""


ONE_KERNEL_ENABLED = os.environ.get("JAXIMU_ONE_KERNEL", "1") != "0"
"""``JAXIMU_ONE_KERNEL=0`` in the environment (read at import) turns the tag off: every block
then runs through XLA's thunk executor, as before (slower; for an XLA that mishandles it)."""


BLOCK_BYTES = 512
"""Bytes of one ``(B,)`` row of a batch block: 64 lanes in float64, 128 in float32. Inside
one kernel (:func:`one_kernel`) a block's state then stays in L1/L2 (docs/DESIGN.md)."""


def block_lanes(dtype):
    """Lanes per batch block for ``dtype``: :data:`BLOCK_BYTES` of them on the CPU, a
    whole GPU's worth on an accelerator (:data:`jaximu.kernels.device.ACCELERATOR_LANES`)."""
    if device.backend() != device.CPU:
        return device.ACCELERATOR_LANES
    return BLOCK_BYTES // jnp.dtype(dtype).itemsize


# Primitives XLA:CPU's whole-computation emitter compiles. It does not take the library
# fusions XLA makes of dots (XNNPACK/YNNPACK), nor custom calls (LAPACK), scatters, sorts or
# collectives: a block that uses anything outside this list runs as a plain call.
_ONE_KERNEL_PRIMITIVES = frozenset(
    """
    abs acos acosh add add_any and asin asinh atan atan2 atanh bitcast_convert_type
    broadcast_in_dim cbrt ceil clamp closed_call concatenate cond convert_element_type copy
    copy_p cos cosh custom_jvp_call custom_vjp_call custom_vjp_call_jaxpr div
    dynamic_slice dynamic_update_slice eq erf erf_inv erfc exp exp2 expand_dims expm1
    floor ge gt imag integer_pow iota is_finite jit le log log1p logistic lt max min mul
    ne neg nextafter not optimization_barrier or pad pjit population_count pow real
    reduce_and reduce_max reduce_min reduce_or reduce_prod reduce_sum reduce_xor rem
    reshape round rsqrt scan select_n shift_left shift_right_arithmetic
    shift_right_logical sign sin sinh slice sqrt square squeeze stack stop_gradient sub
    tan tanh threefry2x32 transpose while xor
""".split()
)


def _kernel_safe(jaxpr) -> bool:
    for eqn in jaxpr.eqns:
        if eqn.primitive.name not in _ONE_KERNEL_PRIMITIVES:
            return False
        for v in eqn.params.values():
            for x in v if isinstance(v, (tuple, list)) else (v,):
                sub = getattr(x, "jaxpr", x)  # a ClosedJaxpr's jaxpr, or a Jaxpr
                if hasattr(sub, "eqns") and not _kernel_safe(sub):
                    return False
    return True


def one_kernel(fn, *args):
    """``fn(*args)``, compiled by XLA:CPU as one kernel.

    The call is tagged so that XLA keeps it (``inlineable="false"``) and emits it whole
    (``xla_cpu_small_call``, the tag XLA's own small-while-loop pass gives the loops it
    hoists): the time loop inside runs as straight code instead of one thunk per fusion
    (docs/DESIGN.md, "One kernel per block"). Only the call carries the tag, and only its
    primal: derivatives run through the plain call (:func:`_plain_derivatives`). A block that
    uses an operation that emitter lacks (:data:`_ONE_KERNEL_PRIMITIVES`), and every
    backend but the CPU, get the plain call."""
    call = jax.jit(fn)
    if (
        not ONE_KERNEL_ENABLED
        or jax.default_backend() != "cpu"
        or not _kernel_safe(call.trace(*args).jaxpr.jaxpr)
    ):
        return call(*args)
    # The arguments pass a barrier: an argument XLA can fold to a constant (samples a user
    # closed over, say) would otherwise be sunk into the loop inside the kernel as a large
    # constant, which the whole-computation emitter cannot address (XLA aborts).
    args = jax.lax.optimization_barrier(args)

    def tagged(*args):
        return set_xla_metadata(call(*args), **ONE_KERNEL)

    return _plain_derivatives(tagged, call)(*args)


def _plain_derivatives(fn, plain):
    """``fn`` whose derivatives are those of ``plain`` (the same function untagged). A
    tagged derivative keeps neither guard of the primal: the arguments' barrier (a
    ``jax.linearize`` of ``propagate_final`` on closed-over samples aborted the process in
    XLA's emitter) nor a sane compile time (its forward pass saving every step's residuals
    in one LLVM function: an eager ``jax.grad`` of a 64 × 500 preintegration compiled for
    150 s, against 10 s)."""
    fn = jax.custom_jvp(fn)
    fn.defjvp(lambda primals, tangents: jax.jvp(plain, primals, tangents))
    return fn


def run_blocked(block_fn, B, lanes, *args, whole=()):
    """``block_fn(*args)`` over batch blocks of at most ``lanes`` lanes (a ``lax.map``).
    ``whole``: a flag per argument, ``True`` for one every block reads whole (a gravity,
    noise variances, a ``dt`` common to all lanes, ``None``); every leaf of the others has
    leading axis B and each block gets its own lanes of it.

    Under a mesh (:func:`_mesh_axes`) whose free axes divide ``B`` the lanes are first split
    over its devices with a ``shard_map``: lanes are independent, so each device runs its
    own part with no communication (docs/DESIGN.md, "Several devices"). ``block_fn`` closes
    over no traced value (JAX cannot transpose a ``shard_map`` whose body does): what all
    lanes share is an argument read whole, passed replicated. Under a mesh that does not
    divide ``B`` (an odd batch, one sequence) the kernel runs whole on replicated inputs:
    an input the partitioner left sharded (a sequence whose time axis a user split) would
    otherwise get collectives inside the one-kernel call, which XLA:CPU's kernel emitter
    cannot link; the gather happens before the call, once."""
    whole = tuple(whole) or (False,) * len(args)
    lane_args = tuple(a for a, w in zip(args, whole, strict=True) if not w)
    shared = tuple(a for a, w in zip(args, whole) if w)
    mesh, axes = _mesh_axes(lane_args)
    n = math.prod(mesh.shape[a] for a in axes) if axes else 1
    if n == 1:
        return _run_blocks(block_fn, B, lanes, lane_args, shared, whole)
    P = jax.sharding.PartitionSpec
    # Sharding in types (an Explicit mesh): the layout is written into the arguments' types
    # with reshard, and the results are gathered back to replicated ones, the types the code
    # around the kernels is written for (one copy of the results between the devices).
    explicit = any(
        mesh.axis_types[mesh.axis_names.index(a)] == jax.sharding.AxisType.Explicit for a in axes
    )

    def put(tree, spec):
        if explicit:
            return jax.tree_util.tree_map(lambda x: jax.sharding.reshard(x, spec), tree)
        return jax.tree_util.tree_map(lambda x: jax.lax.with_sharding_constraint(x, spec), tree)

    with jax.sharding.use_abstract_mesh(mesh):  # the kernels' own arrays on it too
        if B % n:  # not split: the kernel runs whole, on replicated inputs
            lane_args, shared = put((lane_args, shared), P())
            return _run_blocks(block_fn, B, lanes, lane_args, shared, whole)
        local = jax.shard_map(
            lambda a, s: _run_blocks(block_fn, B // n, lanes, a, s, whole),
            in_specs=(P(axes), P()),
            out_specs=P(axes),
            axis_names=set(axes),
            check_vma=False,
        )
        if not explicit:
            return local(lane_args, shared)
        out = local(put(lane_args, P(axes)), put(shared, P()))
        return put(out, P())


def replicated(tree):
    """``tree`` replicated on the current mesh (:func:`_mesh_axes`), or as it is without
    one: the inputs of a kernel that runs whole on every device (:func:`run_blocked`'s
    undivided batch; the time chunks' composition), so that no collective lands inside the
    one-kernel call (XLA:CPU's kernel emitter cannot link it)."""
    mesh, axes = _mesh_axes(tree)
    if not axes:
        return tree
    spec = jax.sharding.PartitionSpec()
    explicit = any(
        mesh.axis_types[mesh.axis_names.index(a)] == jax.sharding.AxisType.Explicit for a in axes
    )
    with jax.sharding.use_abstract_mesh(mesh):
        if explicit:
            return jax.tree_util.tree_map(lambda x: jax.sharding.reshard(x, spec), tree)
        return jax.tree_util.tree_map(lambda x: jax.lax.with_sharding_constraint(x, spec), tree)


def _run_blocks(block_fn, B, lanes, lane_args, shared, whole):
    def ordered(block_args, shared):  # the arguments back in their order
        lane, common = iter(block_args), iter(shared)
        return block_fn(*(next(common) if w else next(lane) for w in whole))

    def call(block_args):
        return one_kernel(ordered, block_args, shared)

    Bc = _block_size(B, lanes)
    if Bc == B:
        return call(lane_args)
    nb = B // Bc
    split = lambda x: x.reshape((nb, Bc) + x.shape[1:])  # noqa: E731
    out = jax.lax.map(call, jax.tree_util.tree_map(split, lane_args))
    return jax.tree_util.tree_map(lambda x: x.reshape((B,) + x.shape[2:]), out)


def _stack_last(t):
    return jnp.stack(t, axis=-1)
