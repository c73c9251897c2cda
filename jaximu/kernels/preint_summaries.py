"""Summaries of preintegrated chunks on lanes and their composition: the chunks of a long
sequence (``method="parallel"``) composed by two short sequential folds, with dense 15×15
algebra (few summaries; the frame change of :func:`jaximu.preintegration.compose`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.geometry.so3 import quat_normalize, quat_to_matrix, skew
from jaximu.kernels.preint_euler import P9_KEYS, P15_KEYS
from jaximu.schemes import _blocks as blk
from jaximu.schemes._blocks import Blocks
from jaximu.schemes.integrators import compose_deltas

# ----------------------------------------------------------------------------- summaries
#
# A summary (batch-major, in its start frame, θ' coordinates) is a dict: q (n, 4), dv, dp
# (n, 3), t (n,), Phi (n, 15, 15), Q15 (n, 15, 15), Q9 (n, 9, 9). Few of them are composed
# (chunks of one sequence), so dense 15×15 algebra is cheap there and quick to compile.


def summary(q, dv, dp, t, phi: Blocks, P, d3, d4, S):
    """A chunk's summary (batch-major) from a kernel's final lanes: ``q``, ``dv``, ``dp``
    component tuples of ``(B,)``, ``t`` ``(B,)``, ``phi`` the transition's blocks (batch-major,
    :func:`jaximu.schemes._blocks.phi_to_dense` forms it), ``P`` the 15×15 noise's upper
    blocks (:data:`P15_KEYS`, ``(3, 3, B)``) with the bias blocks' diagonals ``d3``, ``d4``,
    ``S`` the 9×9's (:data:`P9_KEYS`)."""
    last = lambda x: jnp.stack(x, -1)  # noqa: E731
    bm = lambda X: jnp.moveaxis(X, -1, 0)  # noqa: E731
    eye = jnp.eye(3, dtype=t.dtype)
    P15 = {k: bm(X) for k, X in zip(P15_KEYS, P)}
    P15[3, 3] = bm(d3)[:, None, :] * eye
    P15[4, 4] = bm(d4)[:, None, :] * eye
    P9 = {k: bm(X) for k, X in zip(P9_KEYS, S)}
    return dict(
        q=last(q),
        dv=last(dv),
        dp=last(dp),
        t=t,
        Phi=blk.phi_to_dense(phi),
        Q15=blk.blocks_to_dense(P15),
        Q9=blk.blocks_to_dense(P9, n=3),
    )


def _to_summary(c):
    """:func:`summary` of the Euler kernel's carry, in the rotated error coordinates
    (``Φ_θθ = I``, ``Φ_vθ = -[Δv]x``, ``Φ_pθ = -[Δp]x``: :mod:`jaximu.kernels.fast_preint`)."""
    q, dv, dp, t, (Bg, Dp, Dv, Ep, Ev), P, d3, d4, S = c
    bm = lambda X: jnp.moveaxis(X, -1, 0)  # noqa: E731
    I = jnp.broadcast_to(jnp.eye(3, dtype=t.dtype), t.shape + (3, 3))
    phi = Blocks(
        A=I,
        B=bm(Bg),
        Cp=-skew(jnp.stack(dp, -1)),
        Cv=-skew(jnp.stack(dv, -1)),
        Dp=bm(Dp),
        Dv=bm(Dv),
        Ep=bm(Ep),
        Ev=bm(Ev),
        dt=t,
    )
    return summary(q, dv, dp, t, phi, P, d3, d4, S)


def _frame(R, n, k):
    """``blockdiag(R × k, I)`` of size n (``R`` on the first k 3-blocks)."""
    eye = jnp.broadcast_to(jnp.eye(n, dtype=R.dtype), R.shape[:-2] + (n, n))
    for i in range(k):
        eye = eye.at[..., 3 * i : 3 * i + 3, 3 * i : 3 * i + 3].set(R)
    return eye


def _combine(a, b, rotate=True):
    """Summary ``a`` then ``b`` (``b`` in the end frame of ``a``), as
    :func:`jaximu.preintegration.compose`: ``b`` is moved to ``a``'s frame by
    ``T = blockdiag(R, R, R, I, I)`` (``θ'``, p, v all rotate) and composed. With
    ``rotate=False`` both are already in the same frame (plain composition)."""
    deltas = lambda s: (s["q"], s["dp"], s["dv"], s["t"])  # noqa: E731
    if rotate:
        R = quat_to_matrix(a["q"])
        T = _frame(R, 15, 3)
        T9 = T[..., :9, :9]
        Fb = T @ b["Phi"] @ blk.t(T)
        Qb15, Qb9 = T @ b["Q15"] @ blk.t(T), T9 @ b["Q9"] @ blk.t(T9)
        q, dp, dv, t = compose_deltas(
            deltas(a), deltas(b), lambda x: jnp.einsum("...ij,...j->...i", R, x)
        )
    else:  # the same frame: the sums of compose_deltas without a rotation
        Fb, Qb15, Qb9, q = b["Phi"], b["Q15"], b["Q9"], a["q"]
        dv, dp, t = (
            a["dv"] + b["dv"],
            (a["dp"] + a["dv"] * b["t"][..., None]) + b["dp"],
            a["t"] + b["t"],
        )
    F9 = Fb[..., :9, :9]
    return dict(
        q=q,
        dv=dv,
        dp=dp,
        t=t,
        Phi=Fb @ a["Phi"],
        Q15=blk.sym(Fb @ a["Q15"] @ blk.t(Fb) + Qb15),
        Q9=blk.sym(F9 @ a["Q9"] @ blk.t(F9) + Qb9),
    )


def _identity_summary(like):
    out = jax.tree_util.tree_map(jnp.zeros_like, like)
    out["q"] = out["q"].at[..., 0].set(1)
    out["Phi"] = jnp.broadcast_to(jnp.eye(15, dtype=out["Phi"].dtype), out["Phi"].shape)
    return out


def _fold(s, axis, rotate=True):
    """Sequential composition along ``axis`` (a ``lax.scan``; the other axes are lanes)."""
    first = jax.tree_util.tree_map(lambda x: jnp.take(x, 0, axis=axis), s)
    rest = jax.tree_util.tree_map(
        lambda x: jnp.moveaxis(jax.lax.slice_in_dim(x, 1, x.shape[axis], axis=axis), axis, 0), s
    )
    return jax.lax.scan(lambda c, x: (_combine(c, x, rotate), None), first, rest)[0]


def _reduce_chunks(s, C, rotate=True):
    """Compose the ``C`` chunk summaries along axis 1 (``(B, C, ...)``): two sequential folds
    over a ``C1 × C2`` grid (``C2 ≈ √C``), i.e. ~2√C dependent steps, each over many lanes."""
    C2 = int(np.ceil(np.sqrt(C)))
    C1 = -(-C // C2)
    if C1 * C2 > C:
        ident = _identity_summary(jax.tree_util.tree_map(lambda x: x[:, : C1 * C2 - C], s))
        s = jax.tree_util.tree_map(lambda x, y: jnp.concatenate([x, y], 1), s, ident)
    s = jax.tree_util.tree_map(lambda x: x.reshape(x.shape[:1] + (C1, C2) + x.shape[2:]), s)
    s = _fold(s, 2, rotate) if C2 > 1 else jax.tree_util.tree_map(lambda x: x[:, :, 0], s)
    return _fold(s, 1, rotate) if C1 > 1 else jax.tree_util.tree_map(lambda x: x[:, 0], s)


def _finish(s):
    """Summary in θ' coordinates -> ``(t, q, dv, dp, Φ, Q15, Q9)`` of the generic code: the
    θ rows (and columns) are rotated back with ``ΔR_ijᵀ``."""
    Rt = blk.t(quat_to_matrix(s["q"]))
    T = _frame(Rt, 15, 1)
    T9 = T[..., :9, :9]
    return (
        s["t"],
        quat_normalize(s["q"]),
        s["dv"],
        s["dp"],
        T @ s["Phi"],
        blk.sym(T @ s["Q15"] @ blk.t(T)),
        blk.sym(T9 @ s["Q9"] @ blk.t(T9)),
    )
