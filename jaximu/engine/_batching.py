"""``jax.vmap`` lands on the batched kernels.

Every engine entry (``_propagate``, ``_propagate_covariance``, ``_preintegrate``) already
broadcasts over leading batch axes and chooses its kernel from the *whole* batch it sees
(see :mod:`jaximu.engine._dispatch`). Under a plain ``jax.vmap`` it would see one trajectory: the
dispatcher would pick the small-batch kernel and JAX would then batch that kernel's scan
generically (batch-major carries, conds turned into selects), several times slower than
the same work passed as leading axes (docs/DESIGN.md, "vmap").

:func:`leading_axes` binds an entry as one JAX primitive so that a ``vmap`` of it is
answered by one call of the entry with the mapped axis moved in front of the batch axes: the
arguments' own batch axes stay where they are, unmapped arguments broadcast as they always
do, and the result's batch is ``(mapped,) + batch``. The batching rule binds the primitive
again, so it nests (an outer ``vmap`` routes once more) and works under ``jit``; the JVP rule
is ``jax.jvp`` of the entry, ordinary operations, so ``grad``, ``jacfwd``, ``hessian`` and
``grad`` of a ``vmap`` (which differentiates the batched call) need no further rules.

A ``vmap`` *of a derivative* (per-example gradients) differentiates the per-element call,
which JAX then batches generically: correct, at the speed of the generic kernels.
``jax.custom_batching.custom_vmap`` was tried first: it is not linearisable (``grad`` of it
fails in JAX 0.10), and under a ``custom_jvp`` the batched JVP rule (a ``vmap`` of the
per-element derivative) failed to transpose through the SoA kernel's conds
(docs/DESIGN.md, section 4).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.extend.core import ClosedJaxpr, Primitive, jaxpr_as_fun, new_jaxpr_eqn
from jax.interpreters import ad, batching, mlir
from jax.interpreters import partial_eval as pe

__all__ = ["leading_axes", "ArgSpec"]


class ArgSpec(NamedTuple):
    """How one positional argument's leaves look for a single batch element.

    Attributes:
        core: number of trailing (non-batch) axes of each leaf, e.g. 2 for ``(..., T, 3)``.
        scalar: for a leaf that may be a 0-d scalar standing for a whole core (``dt`` for
            every step, an isotropic noise density), ``scalar(args, in_batched)`` gives the
            core length it stands for; ``None`` if the leaf is never a scalar.
    """

    core: int
    scalar: Callable | None = None


def _to_leading(axis_size, in_batched, args, specs: Sequence[ArgSpec]):
    """Batched leaves ``(V, *own_batch, *core)`` -> ``(V, 1.., *own_batch, *core)`` so that,
    right-aligned against the unmapped leaves, the mapped axis is the leading batch axis."""
    flat = []  # per argument: (leaves with their flags, treedef)
    for arg, batched, spec in zip(args, in_batched, specs):
        leaves, tree = jax.tree_util.tree_flatten(arg)
        flags = jax.tree_util.tree_leaves(batched)
        pairs = []
        for x, b in zip(leaves, flags):
            if b and x.ndim == 1 and spec.core and spec.scalar is not None:
                # one scalar per element standing for a whole core of n values
                x = jnp.broadcast_to(x[:, None], (axis_size, spec.scalar(args, in_batched)))
            pairs.append((x, b))
        flat.append((pairs, tree))
    rank = max(
        [x.ndim - int(b) - spec.core for (pairs, _), spec in zip(flat, specs) for x, b in pairs]
        + [0]
    )
    out = []
    for (pairs, tree), spec in zip(flat, specs):
        leaves = []
        for x, b in pairs:
            if b:
                own = x.ndim - 1 - spec.core
                x = x.reshape((axis_size,) + (1,) * (rank - own) + x.shape[1:])
            leaves.append(x)
        out.append(jax.tree_util.tree_unflatten(tree, leaves))
    return tuple(out)


@functools.cache
def leading_axes(fn: Callable, specs: tuple, statics: tuple = ()) -> Callable:
    """``fn(*args, **dict(statics))`` whose ``vmap`` runs as one call over leading axes.

    Args:
        fn: an engine entry broadcasting over leading batch axes; its outputs carry the full
            broadcast batch in front.
        specs: one :class:`ArgSpec` per positional argument.
        statics: ``(name, value)`` pairs of static keyword arguments (hashable).

    The call is one primitive: its batching rule moves the mapped axis in front
    (:func:`_to_leading`) and binds it again, so nested ``vmap`` and ``vmap`` under any other
    transform route to the batched kernels; its JVP rule is ``jax.jvp`` of ``fn`` itself
    (ordinary operations, so ``linearize``, ``grad`` and ``jacfwd`` need no more rules).
    Under a trace ``fn`` is traced once per bind (the primitive carries the jaxpr, which its
    abstract evaluation, lowering and JVP read); a call on concrete arrays runs ``fn``.
    """
    plain = functools.partial(fn, **dict(statics))

    def bind(leaves, in_tree):
        """``(output leaves, output tree)`` of ``fn`` on these arguments. Under a trace,
        ``fn`` is traced once and the primitive bound with its jaxpr: the abstract
        evaluation reads the jaxpr's output types and the lowering evaluates the jaxpr, so
        the entry's Python runs once per call site (tracing is a large part of the compile
        time of the small kernels). On concrete arrays (an eager call, or the batching rule
        of an eager ``vmap``) there is nothing to route: ``fn`` runs directly."""
        out_tree = []

        def traced(*leaves):
            out = plain(*jax.tree_util.tree_unflatten(in_tree, leaves))
            out_leaves, tree = jax.tree_util.tree_flatten(out)
            out_tree.append(tree)
            return out_leaves

        if not any(isinstance(x, jax.core.Tracer) for x in leaves):
            return traced(*leaves), out_tree[0]
        jaxpr = jax.make_jaxpr(traced)(*leaves)
        return prim.bind(*leaves, in_tree=in_tree, jaxpr=jaxpr, kept=None), out_tree[0]

    prim = Primitive(f"jaximu_{fn.__name__.lstrip('_')}")
    prim.multiple_results = True

    def evaluate(*leaves, in_tree, jaxpr, kept):
        return jaxpr_as_fun(jaxpr)(*leaves)

    prim.def_impl(evaluate)
    prim.def_abstract_eval(lambda *avals, in_tree, jaxpr, kept: jaxpr.out_avals)
    mlir.register_lowering(prim, mlir.lower_fun(evaluate, multiple_results=True))

    def _jvp(primals, tangents, *, in_tree, jaxpr, kept):
        tangents = tuple(ad.instantiate_zeros(t) for t in tangents)
        return jax.jvp(jaxpr_as_fun(jaxpr), tuple(primals), tangents)

    ad.primitive_jvps[prim] = _jvp

    def _dce(used_outputs, eqn):
        """Dead-code elimination: outputs the program never reads are not computed. The
        carried jaxpr is pruned (through the kernels' maps, calls, conds and scans, whose
        own rules drop a carry nothing used reads: a preintegration whose ``cov15`` is
        unused skips the 15×15 recursion); ``kept`` records which of the entry's outputs
        remain, for the batching rule, which binds the whole entry again."""
        if not any(used_outputs) and not eqn.effects:
            return [False] * len(eqn.invars), None
        if all(used_outputs) or eqn.effects:
            return [True] * len(eqn.invars), eqn
        jaxpr = eqn.params["jaxpr"]
        pruned, _ = pe.dce_jaxpr(jaxpr.jaxpr, list(used_outputs), instantiate=True)
        kept = eqn.params["kept"] or tuple(range(len(used_outputs)))
        params = dict(
            eqn.params,
            jaxpr=ClosedJaxpr(pruned, jaxpr.consts),
            kept=tuple(k for k, u in zip(kept, used_outputs) if u),
        )
        outvars = [v for v, u in zip(eqn.outvars, used_outputs) if u]
        return [True] * len(eqn.invars), new_jaxpr_eqn(
            list(eqn.invars), outvars, prim, params, eqn.effects, eqn.source_info, eqn.ctx
        )

    pe.dce_rules[prim] = _dce

    def _batch(args, dims, *, in_tree, jaxpr, kept):
        size = next(x.shape[d] for x, d in zip(args, dims) if d is not None)
        leaves = [x if d is None else jnp.moveaxis(x, d, 0) for x, d in zip(args, dims)]
        flags = [d is not None for d in dims]
        tree_args = jax.tree_util.tree_unflatten(in_tree, leaves)
        tree_flags = jax.tree_util.tree_unflatten(in_tree, flags)
        moved = _to_leading(size, tree_flags, tree_args, specs)
        new_leaves, new_tree = jax.tree_util.tree_flatten(moved)
        out, _ = bind(new_leaves, new_tree)
        if kept is not None:  # a pruned call (_dce): its remaining outputs
            out = [out[k] for k in kept]
        return out, [0] * len(out)

    batching.primitive_batchers[prim] = _batch

    def routed(*args):
        out, out_tree = bind(*jax.tree_util.tree_flatten(args))
        return jax.tree_util.tree_unflatten(out_tree, out)

    return routed
