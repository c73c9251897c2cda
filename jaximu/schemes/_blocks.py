"""Block algebra for the 15-dim error state ``[θ, p, v, b_g, b_a]`` (five 3-blocks).

Every one-step transition ``Φ`` of this library (propagation, preintegration, both schemes,
closed form or VINS-Mono's) has the same sparsity, and products of such matrices keep it:

    Φ = [[A,  0, 0,    B,  0 ],
         [Cp, I, dt I, Dp, Ep],
         [Cv, 0, I,    Dv, Ev],
         [0,  0, 0,    I,  0 ],
         [0,  0, 0,    0,  I ]]

so a ``Φ`` is stored as eight 3×3 blocks and the scalar ``dt``, and a symmetric ``P`` as its
15 upper 3×3 blocks ``{(i, j): P_ij, i ≤ j}``. A block may be ``None`` (zero) and is then
skipped: this is what makes ``Φ P Φᵀ`` cost a few dozen 3×3 products instead of dense
15×15 ones.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg

from jaximu.geometry import so3
from jaximu.geometry._vec import V3


class Layout(NamedTuple):
    """How 3×3 blocks are stored: the products, transposes and rotation functions every
    block formula uses (here, and the closed-form Jacobians of
    :meth:`jaximu.integrators.Scheme.blocks`).

    :data:`ARRAYS`: ``(..., 3, 3)`` arrays (the generic kernels); :data:`jaximu.kernels.lane_math.SOA`:
    ``(3, 3, B)`` batch-minor blocks (the structure-of-arrays kernels). One copy of the
    block algebra serves both. Vectors are :class:`~jaximu.geometry._vec.V3` of per-element scalars.
    """

    matmul: Callable[..., Any]  # X @ Y
    transpose: Callable[..., Any]  # Xᵀ
    scale: Callable[..., Any]  # s X for a per-element scalar s
    scale_cols: Callable[..., Any]  # X diag(s) for a per-element 3-vector s
    diag: Callable[..., Any]  # diag(s) for a per-element 3-vector s
    # materialise a pytree of blocks (see kernels/soa.py)
    barrier: Callable[..., Any] = lambda tree: tree
    skew: Any = None  # [v]x of a V3
    matvec: Any = None  # X v -> V3
    exp_jr: Any = None  # (Exp(φ), Jr(φ)) of a rotation vector φ (V3)
    from_arrays: Any = None  # a (3, 3) or (..., 3, 3) array as a block of this layout
    cholesky: Any = None  # factor of a symmetric positive definite (m, m) block
    tri_solve: Any = None  # (factor, X, trans=False) -> L⁻¹ X (trans: L⁻ᵀ X)


ARRAYS = Layout(
    matmul=jnp.matmul,
    transpose=lambda x: jnp.swapaxes(x, -1, -2),
    scale=lambda s, X: jnp.asarray(s)[..., None, None] * X,
    scale_cols=lambda X, s: X * s[..., None, :],
    diag=lambda s: s[..., :, None] * jnp.eye(3, dtype=s.dtype),
    skew=lambda v: so3.skew(v.stack()),
    matvec=lambda X, v: V3.of(jnp.einsum("...ij,...j->...i", X, v.stack())),
    exp_jr=lambda phi: (so3.exp_matrix(phi.stack()), so3.right_jacobian(phi.stack())),
    from_arrays=lambda X: X,
    cholesky=lambda S: jnp.linalg.cholesky(S),
    tri_solve=lambda L, X, trans=False: jax.scipy.linalg.solve_triangular(
        L, X, lower=True, trans=1 if trans else 0
    ),
)


class Blocks(NamedTuple):
    """Non-trivial 3×3 blocks of ``Φ`` (``(..., 3, 3)``; ``None`` where zero) and ``dt``."""

    A: Any  # θθ: an array, or the string "I" where the lane kernels know it is the identity
    B: jax.Array | None  # θ b_g
    Cp: jax.Array | None  # p θ (None where the p rows follow from the v rows)
    Cv: jax.Array  # v θ
    Dp: jax.Array | None  # p b_g
    Dv: jax.Array | None  # v b_g
    Ep: jax.Array | None  # p b_a
    Ev: jax.Array | None  # v b_a
    dt: jax.Array  # (...,) the p-v block is dt·I


UPPER = [(i, j) for i in range(5) for j in range(i, 5)]


def t(x, ops: Layout = ARRAYS):
    return None if x is None else ops.transpose(x)


def mm(X, Y, ops: Layout = ARRAYS):
    """3×3 (batched) product; ``None`` (a zero block) if either factor is ``None``."""
    if X is None or Y is None:
        return None
    return ops.matmul(X, Y)


def add(*terms):
    """Sum of the blocks that are not ``None`` (``None`` if all are)."""
    terms = [x for x in terms if x is not None]
    if not terms:
        return None
    out = terms[0]
    for x in terms[1:]:
        out = out + x
    return out


def scale(s, X, ops: Layout = ARRAYS):
    return None if X is None else ops.scale(s, X)


def sym(x, ops: Layout = ARRAYS):
    return 0.5 * (x + t(x, ops))


def dense_to_blocks(P):
    """The 15 upper 3×3 blocks ``{(i, j): P_ij}`` of a ``(..., 15, 15)`` matrix."""
    return {(i, j): P[..., 3 * i : 3 * i + 3, 3 * j : 3 * j + 3] for i, j in UPPER}


def blocks_to_dense(Pb, batch=None, dtype=None, n: int = 5):
    """Symmetric ``(..., 3n, 3n)`` from upper blocks (``None`` or missing blocks are zero);
    ``n = 5``: the 15×15 error-state matrix."""
    present = [x for x in Pb.values() if x is not None]
    batch = present[0].shape[:-2] if batch is None else batch
    dtype = present[0].dtype if dtype is None else dtype
    zero = jnp.zeros(tuple(batch) + (3, 3), dtype)

    def get(i, j):
        x = block(Pb, i, j)
        return zero if x is None else jnp.broadcast_to(x, tuple(batch) + (3, 3))

    return jnp.concatenate(
        [jnp.concatenate([get(i, j) for j in range(n)], -1) for i in range(n)], -2
    )


def phi_to_dense(b: Blocks):
    """Dense ``(..., 15, 15)`` ``Φ`` from its blocks."""
    batch = jnp.broadcast_shapes(*(x.shape[:-2] for x in b[:-1] if x is not None), b.dt.shape)
    dtype = b.A.dtype
    Z = jnp.zeros(batch + (3, 3), dtype)
    eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), batch + (3, 3))

    def f(x):
        return Z if x is None else jnp.broadcast_to(x, batch + (3, 3))

    rows = [
        [b.A, Z, Z, b.B, Z],
        [b.Cp, eye, scale(b.dt, eye), b.Dp, b.Ep],
        [b.Cv, Z, eye, b.Dv, b.Ev],
        [Z, Z, Z, eye, Z],
        [Z, Z, Z, Z, eye],
    ]
    return jnp.concatenate([jnp.concatenate([f(x) for x in r], -1) for r in rows], -2)


def phi_from_dense(Phi):
    """Blocks of a dense ``Φ`` that has the structure of the module docstring."""

    def blk(i, j):
        return Phi[..., 3 * i : 3 * i + 3, 3 * j : 3 * j + 3]

    return Blocks(
        blk(0, 0),
        blk(0, 3),
        blk(1, 0),
        blk(2, 0),
        blk(1, 3),
        blk(2, 3),
        blk(1, 4),
        blk(2, 4),
        Phi[..., 3, 6],
    )


def phi_compose(F: Blocks, P: Blocks, ops: Layout = ARRAYS) -> Blocks:
    """``F Φ`` for two structured transitions (``F`` applied after ``P``): the product of
    their block rows (:func:`rows_product` of :func:`transition_rows`, 6 products), as
    :class:`Blocks`."""
    return rows_to_blocks(rows_product(transition_rows(F, ops), transition_rows(P, ops), ops))


def block(Pb, i, j, ops: Layout = ARRAYS):
    """``P_ij`` of a symmetric ``P`` stored as upper blocks: ``P_jiᵀ`` below the diagonal,
    ``None`` where zero."""
    return Pb.get((i, j)) if i <= j else t(Pb.get((j, i)), ops)


def phi_p_phit(Pb, b: Blocks, ops: Layout = ARRAYS, p_over_v=None):
    """``Φ P Φᵀ`` on upper blocks (``None``/missing blocks of ``P`` are zero).

    ``p_over_v``: a per-element scalar ``s`` when the p rows of ``Φ`` beyond the structural
    ``dt I`` are ``s`` times its v rows (``Cp = s Cv``, ``Dp = s Dv``, ``Ep = s Ev``; Euler
    and midpoint, ``s = dt/2``: :attr:`jaximu.integrators.Scheme.p_over_v`). The p rows'
    products are then those of the v rows, scaled: ``b.Cp``, ``b.Dp``, ``b.Ep`` are not read.
    ``b.A`` may be the string ``"I"`` (an identity block: no product; the rotation error in
    the world frame, :func:`jaximu.kernels.fast.cov_step_blocks`).
    """

    def P(i, j):
        return block(Pb, i, j, ops)

    def mm(X, Y):
        return globals()["mm"](X, Y, ops)

    def scale(s, X):
        return globals()["scale"](s, X, ops)

    def t(x, ops=ops):
        return globals()["t"](x, ops)

    hh = b.dt
    Bt, Cvt, Dvt, Evt = t(b.B), t(b.Cv), t(b.Dv), t(b.Ev)
    # M = Φ P, rows θ (0), p (1), v (2); rows b_g (3), b_a (4) are those of P.
    M = {3: {j: P(3, j) for j in range(5)}, 4: {j: P(4, j) for j in range(5)}}
    M[0] = {j: add(_times(b.A, P(0, j), ops), mm(b.B, P(3, j))) for j in range(5)}
    if p_over_v is None:
        M[1] = {
            j: add(
                P(1, j), scale(hh, P(2, j)), mm(b.Cp, P(0, j)), mm(b.Dp, P(3, j)), mm(b.Ep, P(4, j))
            )
            for j in range(5)
        }
        M[2] = {
            j: add(P(2, j), mm(b.Cv, P(0, j)), mm(b.Dv, P(3, j)), mm(b.Ev, P(4, j)))
            for j in range(5)
        }
        M[0], M[1], M[2] = ops.barrier((M[0], M[1], M[2]))  # each is read by several products
        Cpt, Dpt, Ept = t(b.Cp), t(b.Dp), t(b.Ep)

        def K(Mi):  # the p and v columns' products of row block i
            return (
                add(mm(Mi[0], Cpt), mm(Mi[3], Dpt), mm(Mi[4], Ept)),
                add(mm(Mi[0], Cvt), mm(Mi[3], Dvt), mm(Mi[4], Evt)),
            )
    else:
        N = {j: add(mm(b.Cv, P(0, j)), mm(b.Dv, P(3, j)), mm(b.Ev, P(4, j))) for j in range(5)}
        M[0], N = ops.barrier((M[0], N))  # each is read by several products
        M[2] = {j: add(P(2, j), N[j]) for j in range(5)}
        M[1] = {j: add(P(1, j), scale(hh, P(2, j)), scale(p_over_v, N[j])) for j in range(5)}
        M[1], M[2] = ops.barrier((M[1], M[2]))
        Kv = ops.barrier(
            [add(mm(M[i][0], Cvt), mm(M[i][3], Dvt), mm(M[i][4], Evt)) for i in range(3)]
        )

        def K(i):
            return scale(p_over_v, Kv[i]), Kv[i]

    out: dict = {}
    for i in range(3):
        Mi = M[i]
        out[(i, 3)] = Mi[3]
        out[(i, 4)] = Mi[4]
        kp, kv = K(i if p_over_v is not None else Mi)
        cols = {
            0: lambda: add(_times_t(Mi[0], b.A, ops), mm(Mi[3], Bt)),
            1: lambda: add(Mi[1], scale(hh, Mi[2]), kp),
            2: lambda: add(Mi[2], kv),
        }
        for j in range(i, 3):
            out[(i, j)] = cols[j]()
    out[(3, 3)], out[(3, 4)], out[(4, 4)] = P(3, 3), P(3, 4), P(4, 4)
    return out


class ScaledIdentity(NamedTuple):
    """The block ``s I`` (``s`` a per-element scalar): the p-v block ``Δt I`` of a
    transition, kept as its scalar so that products with it are scalings."""

    s: jax.Array


def _eye(ndim, dtype, ops):
    """The identity block of ``ndim`` dimensions in the layout ``ops`` (lanes minor: as
    many trailing unit axes as the block has lane axes)."""
    eye = jnp.eye(3, dtype=dtype)
    return eye if ops is ARRAYS else eye.reshape((3, 3) + (1,) * (ndim - 2))


def entry_t(X, ops: Layout = ARRAYS):
    """The transpose of a block entry (``None``, ``"I"``, :class:`ScaledIdentity` or a block)."""
    return X if X is None or isinstance(X, (str, ScaledIdentity)) else ops.transpose(X)


def entry_mul(X, Y, ops: Layout = ARRAYS):
    """``X Y`` of two block entries (``None`` zero, ``"I"``, :class:`ScaledIdentity`, a
    block): only two blocks cost a product."""
    if X is None or Y is None:
        return None
    if isinstance(X, str):
        return Y
    if isinstance(Y, str):
        return X
    if isinstance(X, ScaledIdentity):
        return ScaledIdentity(X.s * Y.s) if isinstance(Y, ScaledIdentity) else ops.scale(X.s, Y)
    if isinstance(Y, ScaledIdentity):
        return ops.scale(Y.s, X)
    return ops.matmul(X, Y)


def entry_add(*terms, ops: Layout = ARRAYS):
    """The sum of block entries (``None`` if all are ``None``): multiples of the identity
    stay a :class:`ScaledIdentity` (``"I"`` alone stays ``"I"``), a block absorbs them."""
    kept = [x for x in terms if x is not None]
    if len(kept) <= 1:
        return kept[0] if kept else None
    scalars = [
        1.0 if isinstance(x, str) else x.s for x in kept if isinstance(x, (str, ScaledIdentity))
    ]
    blocks = [x for x in kept if not isinstance(x, (str, ScaledIdentity))]
    s: Any = None
    for x in scalars:
        s = x if s is None else s + x
    if not blocks:
        return ScaledIdentity(s)
    out = add(*blocks)
    return out if s is None else out + ops.scale(s, _eye(out.ndim, out.dtype, ops))


def transition_rows(b: Blocks, ops: Layout = ARRAYS, p_over_v=None):
    """A transition's block rows θ, p, v (rows b_g, b_a are identity rows) from its
    :class:`Blocks`: ``{i: {j: entry}}`` for :func:`rows_product` and :func:`congruence`.
    ``p_over_v``: as :func:`phi_p_phit` (the p rows are ``s`` times the v rows)."""
    Cp, Dp, Ep = b.Cp, b.Dp, b.Ep
    if p_over_v is not None:
        Cp, Dp, Ep = (scale(p_over_v, X, ops) for X in (b.Cv, b.Dv, b.Ev))
    return {
        0: {0: b.A, 3: b.B},
        1: {0: Cp, 1: "I", 2: ScaledIdentity(b.dt), 3: Dp, 4: Ep},
        2: {0: b.Cv, 2: "I", 3: b.Dv, 4: b.Ev},
    }


# the block columns of a transition's rows θ, p, v that may be non-zero (module docstring)
_TRANSITION_COLUMNS = {0: (0, 3), 1: (0, 1, 2, 3, 4), 2: (0, 2, 3, 4)}


def rows_to_blocks(rows) -> Blocks:
    """The inverse of :func:`transition_rows`: the :class:`Blocks` of a transition given by
    its block rows θ, p, v (missing entries zero; ``p_over_v`` not applied, the p row as
    given)."""
    extra = [(i, j) for i, row in rows.items() for j in row if j not in _TRANSITION_COLUMNS[i]]
    if extra:
        raise ValueError(f"blocks {extra} are outside a transition's structure")
    if not (isinstance(rows[1].get(1), str) and isinstance(rows[2].get(2), str)):
        raise ValueError("blocks (1, 1) and (2, 2) of a transition are the identity")
    if not isinstance(rows[1].get(2), ScaledIdentity):
        raise ValueError("block (1, 2) of a transition is dt I")
    return Blocks(
        A=rows[0].get(0),
        B=rows[0].get(3),
        Cp=rows[1].get(0),
        Cv=rows[2].get(0),
        Dp=rows[1].get(3),
        Dv=rows[2].get(3),
        Ep=rows[1].get(4),
        Ev=rows[2].get(4),
        dt=rows[1][2].s,
    )


def rows_product(F, G, ops: Layout = ARRAYS, columns=range(5), p_over_v=None):
    """``F G`` of two matrices that are the identity but for their block rows ``{i: {j:
    entry}}`` (:func:`transition_rows`, :func:`jaximu.world.error_map_rows`); the product
    in the same form (its rows: those of ``F`` and of ``G``). ``columns``: only these block
    columns of the product, for a ``G`` given by those columns alone (``(F G)[:, J] = F
    G[:, J]``: a product of transitions accumulated column by column).

    ``p_over_v``: ``s`` when ``F``'s p row is ``s`` times its v row but for its p and v
    columns (``I`` and ``dt I``; :func:`phi_p_phit`); its products are then not formed:
    ``(F G)_pj = G_pj + s (F G)_vj + (dt − s) G_vj``."""

    def g(k, j):
        return G[k].get(j) if k in G else ("I" if k == j else None)

    out = {i: dict(G[i]) for i in G if i not in F}
    for i, Fi in F.items():
        if i == 1 and p_over_v is not None:
            continue
        row = {
            j: entry_add(*(entry_mul(Fik, g(k, j), ops) for k, Fik in Fi.items()), ops=ops)
            for j in columns
        }
        out[i] = {j: x for j, x in row.items() if x is not None}
    if p_over_v is not None and 1 in F:
        s, rest = ScaledIdentity(p_over_v), ScaledIdentity(F[1][2].s - p_over_v)
        row = {
            j: entry_add(
                g(1, j),
                entry_mul(s, out[2].get(j), ops),
                entry_mul(rest, g(2, j), ops),
                ops=ops,
            )
            for j in columns
        }
        out[1] = {j: x for j, x in row.items() if x is not None}
    return out


def rotate_rows(rows, R, rotated, ops: Layout = ARRAYS):
    """``T M Tᵀ`` for ``M`` given by its block rows and ``T`` block diagonal, ``R`` on the
    blocks in ``rotated`` and the identity elsewhere: each entry becomes ``T_i M_ij T_jᵀ``
    (a multiple of the identity between two rotated blocks stays one)."""

    def side(i):
        return R if i in rotated else "I"

    out: dict = {}
    for i, row in rows.items():
        out[i] = {}
        for j, X in row.items():
            if isinstance(X, (str, ScaledIdentity)) and (i in rotated) == (j in rotated):
                out[i][j] = X
            else:
                out[i][j] = entry_mul(entry_mul(side(i), X, ops), entry_t(side(j), ops), ops)
    return out


def conform_rows(rows, pattern, block_shape, scalar_shape, dtype, ops: Layout = ARRAYS):
    """``rows`` in the fixed form ``pattern`` (``{i: {j: kind}}``, kind ``"I"``, ``"s"`` (a
    :class:`ScaledIdentity`) or ``"X"`` (a block); missing: zero), blocks broadcast to
    ``block_shape`` and scalars to ``scalar_shape``: the carry of a scan over transitions,
    whose structure must not change from one step to the next."""

    def value(i, j):
        if i not in rows:
            return "I" if i == j else None
        return rows[i].get(j)

    out: dict = {}
    for i, prow in pattern.items():
        extra = [j for j in rows.get(i, {}) if j not in prow and rows[i][j] is not None]
        if extra:
            raise ValueError(f"row {i} has blocks {extra} outside the pattern")
        out[i] = {}
        for j, kind in prow.items():
            x = value(i, j)
            if kind == "I":
                if x != "I":
                    raise ValueError(f"block ({i}, {j}) is not the identity the pattern says")
                out[i][j] = "I"
                continue
            if isinstance(x, (str, ScaledIdentity)) or x is None:
                s = 0.0 if x is None else (1.0 if isinstance(x, str) else x.s)
                if kind == "s":
                    out[i][j] = ScaledIdentity(
                        jnp.broadcast_to(jnp.asarray(s, dtype), scalar_shape)
                    )
                    continue
                x = ops.scale(s, _eye(len(block_shape), dtype, ops))
            elif kind == "s":
                raise ValueError(
                    f"block ({i}, {j}) is a full block, the pattern a multiple of the identity"
                )
            out[i][j] = jnp.broadcast_to(jnp.asarray(x, dtype), block_shape)
    return out


def rows_pattern(rows):
    """The form of block rows (:func:`conform_rows`' ``pattern``)."""

    def kind(x):
        return "I" if isinstance(x, str) else ("s" if isinstance(x, ScaledIdentity) else "X")

    return {i: {j: kind(x) for j, x in row.items() if x is not None} for i, row in rows.items()}


def rows_leaves(rows, pattern):
    """The arrays of block rows in the form ``pattern`` (:func:`conform_rows`), in a fixed
    order: a block's, or a :class:`ScaledIdentity`'s scalar."""
    return [
        rows[i][j].s if kind == "s" else rows[i][j]
        for i, prow in sorted(pattern.items())
        for j, kind in sorted(prow.items())
        if kind != "I"
    ]


def rows_from_leaves(leaves, pattern):
    """The inverse of :func:`rows_leaves`."""
    it = iter(leaves)
    return {
        i: {
            j: "I" if kind == "I" else (ScaledIdentity(next(it)) if kind == "s" else next(it))
            for j, kind in sorted(prow.items())
        }
        for i, prow in sorted(pattern.items())
    }


def compose_transitions(first, then, ops: Layout = ARRAYS):
    """``(Φ₂Φ₁, Φ₂ Q₁ Φ₂ᵀ + Q₂)``: the interval ``first = (Φ₁, Q₁)`` followed by ``then =
    (Φ₂, Q₂)`` (``Φ`` as block rows, ``Q`` as upper blocks), so that ``P ↦ Φ₂(Φ₁ P Φ₁ᵀ +
    Q₁)Φ₂ᵀ + Q₂`` is one step ``P ↦ Φ P Φᵀ + Q``. Associative: chunks of a long sequence
    compose in sequence or as a parallel prefix scan."""
    (F1, Q1), (F2, Q2) = first, then
    return rows_product(F2, F1, ops), add_blocks(congruence(Q1, F2, ops), Q2)


def congruence(Pb, rows, ops: Layout = ARRAYS):
    """``M P Mᵀ`` on upper blocks, for an ``M`` that is the identity but for the block rows
    in ``rows``: ``{i: {k: M_ik}}`` (missing blocks zero, the string ``"I"`` an identity
    block, a :class:`ScaledIdentity` a multiple of it), as :func:`jaximu.world.error_map_rows`
    and :func:`transition_rows` give them. Rows of ``M`` that are identity rows cost
    nothing."""

    def P(i, j):
        return block(Pb, i, j, ops)

    def times(Mik, X):  # M_ik X
        return entry_mul(Mik, X, ops)

    def times_t(X, Mjl):  # X M_jlᵀ
        return entry_mul(X, entry_t(Mjl, ops), ops)

    # N = M P (all columns of the changed rows), then N Mᵀ (the changed columns)
    N = {
        i: {j: add(*(times(Mik, P(k, j)) for k, Mik in rows[i].items())) for j in range(5)}
        for i in rows
    }
    N = ops.barrier(N)  # each block is read by several products

    def Nrow(i, j):
        return N[i][j] if i in N else P(i, j)

    out: dict = {}
    for i, j in UPPER:
        if j in rows:
            out[(i, j)] = add(*(times_t(Nrow(i, l), Mjl) for l, Mjl in rows[j].items()))
        else:
            out[(i, j)] = Nrow(i, j)
    return out


def add_blocks(Pb, Qb):
    """Blockwise ``P + Q`` (``None``/missing blocks are zero)."""
    keys = set(Pb) | set(Qb)
    return {k: add(Pb.get(k), Qb.get(k)) for k in keys}


def symmetrize_diagonal(Pb, ops: Layout = ARRAYS):
    return {k: (sym(v, ops) if (v is not None and k[0] == k[1]) else v) for k, v in Pb.items()}


def noise_blocks(columns, variances, ops: Layout = ARRAYS):
    """Upper blocks of ``Σ_n V_n diag(s_n) V_nᵀ`` for noise inputs ``n``.

    Args:
        columns: list over noise inputs of ``{row_block: V_rn}`` (``(..., 3, 3)``; a missing
            row block is zero).
        variances: list over noise inputs of per-axis variances ``s_n`` (``(..., 3)``, or
            as ``ops`` stores 3-vectors).
    """
    out: dict = {}
    for V, s in zip(columns, variances):
        V = {k: v for k, v in V.items() if v is not None}
        rows = sorted(V)
        for a_i, i in enumerate(rows):
            Vs = ops.scale_cols(V[i], s)
            for j in rows[a_i:]:
                out[(i, j)] = add(out.get((i, j)), mm(Vs, t(V[j], ops), ops))
    return out


def structured_update(Pb, b: Blocks, qc, ops: Layout = ARRAYS, p_over_v=None, qc_scale=None):
    """``Φ P Φᵀ + G Q_c Gᵀ`` on the upper blocks of ``P``, using the structure of ``Φ``.

    Args:
        Pb: upper blocks of ``P`` (see :func:`dense_to_blocks`).
        b: blocks of ``Φ``; ``G`` follows from them (module docstring).
        qc: the diagonal of ``Q_c`` as four per-axis 3-vectors ``[σ_g², σ_a², σ_bg², σ_ba²]/dt``
            (``(..., 3)`` each, or as ``ops`` stores 3-vectors); a ``(..., 12)`` array is split.
        ops: the block layout (:data:`ARRAYS` or :data:`jaximu.kernels.lane_math.SOA`).
        p_over_v: ``s`` with ``Cp = s Cv``, ``Dp = s Dv``, ``Ep = s Ev`` when the scheme has
            that structure (:func:`phi_p_phit`), or ``None``.
        qc_scale: a per-element factor of every variance in ``qc`` (``1/dt`` of shared
            ``σ²`` when the steps differ by element), applied once to each noise block;
            ``None``: none.
    """
    if not isinstance(qc, (tuple, list)):
        qc = (qc[..., 0:3], qc[..., 3:6], qc[..., 6:9], qc[..., 9:12])
    if p_over_v is not None:  # the p rows follow from the v rows: not formed at all
        b = b._replace(Cp=None, Dp=None, Ep=None)
    b = ops.barrier(b)  # every block is read by several products
    h = b.dt
    if p_over_v is None:
        Q = noise_blocks([{0: b.B, 1: b.Dp, 2: b.Dv}, {1: b.Ep, 2: b.Ev}], [qc[0], qc[1]], ops)
    else:  # G's p rows are s times its v rows too
        Q = noise_blocks([{0: b.B, 2: b.Dv}, {2: b.Ev}], [qc[0], qc[1]], ops)
    if qc_scale is not None:
        Q = {k: scale(qc_scale, X, ops) for k, X in Q.items()}
    if p_over_v is not None:
        Q[(0, 1)] = scale(p_over_v, Q.get((0, 2)), ops)
        Q[(1, 2)] = scale(p_over_v, Q.get((2, 2)), ops)
        Q[(1, 1)] = scale(p_over_v * p_over_v, Q.get((2, 2)), ops)
    hh = h * h if qc_scale is None else h * h * qc_scale
    Q[(3, 3)] = ops.scale(hh, ops.diag(qc[2]))
    Q[(4, 4)] = ops.scale(hh, ops.diag(qc[3]))
    return symmetrize_diagonal(add_blocks(phi_p_phit(Pb, b, ops, p_over_v), Q), ops)


def _times(Hk, X, ops):
    """``H_k X`` for a measurement column block ``H_k`` (``"I"``: the identity)."""
    return X if isinstance(Hk, str) else mm(Hk, X, ops)


def _times_t(X, Hk, ops):
    """``X H_kᵀ``."""
    return X if isinstance(Hk, str) else mm(X, t(Hk, ops), ops)


class KalmanUpdate(NamedTuple):
    """The result of :func:`kalman_update` (blocks of its layout)."""

    dx: list  # the 5 blocks (3 × 1) of δx = K ν
    P: dict  # upper blocks of P⁺
    nis: jax.Array  # (1 × 1) νᵀ S⁻¹ ν


def kalman_update(Pb, H, R, nu, ops: Layout = ARRAYS, check=None):
    """Kalman update of the error state, Joseph form, on upper blocks: the mathematics of
    :func:`jaximu.errorstate.ekf_update` (its one home; the Monte Carlo filter study runs
    it on SoA lanes).

    With ``U = P Hᵀ``, ``S = H U + R`` (factored by Cholesky, ``ops.cholesky``) and
    ``K = U S⁻¹``::

        δx = K ν,   P⁺ = (I - K H) P (I - K H)ᵀ + K R Kᵀ = M + (K R - M Hᵀ) Kᵀ,
        M = (I - K H) P = P - K Uᵀ,   NIS = νᵀ S⁻¹ ν.

    Args:
        Pb: upper blocks of ``P`` (:func:`dense_to_blocks`).
        H: the 5 column blocks ``H_k`` (``m × 3``) of the ``(m, 15)`` Jacobian; ``None``
            where zero, the string ``"I"`` for an identity block (``m = 3``): a position fix
            is ``(None, "I", None, None, None)``, which costs no product.
        R: ``m × m`` measurement noise covariance; nu: ``m × 1`` residual ``ν = z - h(x̂)``.
        ops: the layout (:data:`ARRAYS`, or :data:`jaximu.kernels.lane_math.SOA`: ``(m, n, B)`` lanes).
        check: ``check(S)`` called before ``S`` is factored (e.g. a definiteness check).
    """

    def P(i, j):
        return block(Pb, i, j, ops)

    cols = [k for k in range(5) if H[k] is not None]
    U = [add(*(_times_t(P(i, k), H[k], ops) for k in cols)) for i in range(5)]  # P Hᵀ rows
    S = add(*(_times(H[k], U[k], ops) for k in cols), R)
    S = sym(S, ops)
    if check is not None:
        check(S)
    F = ops.cholesky(S)
    Kt = [
        None if u is None else ops.tri_solve(F, ops.tri_solve(F, t(u, ops)), trans=True) for u in U
    ]  # Kᵢᵀ = S⁻¹ Uᵢᵀ
    K = [t(x, ops) for x in Kt]
    white = ops.tri_solve(F, nu)
    nis = mm(t(white, ops), white, ops)
    dx = [mm(k, nu, ops) for k in K]
    K, Kt, dx = ops.barrier((K, Kt, dx))  # each is read by several products

    def M(i, j):  # ((I - K H) P)_ij
        ku = mm(K[i], t(U[j], ops), ops)
        return add(P(i, j), None if ku is None else -ku)

    Z = [
        add(mm(K[i], R, ops), *(-_times_t(M(i, k), H[k], ops) for k in cols)) for i in range(5)
    ]  # K R - M Hᵀ
    new = {(i, j): add(M(i, j), mm(Z[i], Kt[j], ops)) for i, j in UPPER}
    return KalmanUpdate(dx, symmetrize_diagonal(new, ops), nis)


def whiten(Pb, e, ops: Layout = ARRAYS):
    """``L⁻¹ e`` for ``P = L Lᵀ`` (block Cholesky on the upper blocks ``Pb``; ``e``: the 5
    blocks ``3 × 1`` of an error): ``|L⁻¹ e|² = eᵀ P⁻¹ e``, the NEES. Returns the 5 blocks
    of ``L⁻¹ e``."""

    def P(i, j):
        return block(Pb, i, j, ops)

    F: list = [None] * 5
    y: list = [None] * 5
    Lo: dict = {}  # Lo[(i, j)] = L_ijᵀ (i > j)
    for j in range(5):
        F[j] = ops.cholesky(
            add(P(j, j), *(-mm(t(Lo[(j, k)], ops), Lo[(j, k)], ops) for k in range(j)))
        )
        col = {}
        for i in range(j + 1, 5):  # L_ij = (P_ij - Σ L_ik L_jkᵀ) L_jj⁻ᵀ
            X = add(P(j, i), *(-mm(t(Lo[(j, k)], ops), Lo[(i, k)], ops) for k in range(j)))
            col[(i, j)] = ops.tri_solve(F[j], X)
        yj = ops.tri_solve(F[j], add(e[j], *(-mm(t(Lo[(j, k)], ops), y[k], ops) for k in range(j))))
        col, y[j] = ops.barrier((col, yj))  # each is read by the later columns
        Lo.update(col)
    return y
