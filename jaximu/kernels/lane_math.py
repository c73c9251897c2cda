"""Lane algebra of the structure-of-arrays kernels (:mod:`jaximu.kernels.soa`, where the layout is
explained): the half angle's polynomials, quaternions and 3-vectors as tuples of ``(B,)`` lanes,
3×3 blocks as ``(3, 3, B)`` arrays (:data:`SOA`, the block layout of
:mod:`jaximu.schemes._blocks` on lanes), and the stage boundaries that materialise a value once.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.geometry import so3
from jaximu.geometry._vec import V3
from jaximu.kernels import device
from jaximu.schemes._blocks import Layout

# ----------------------------------------------------------------------------- half angle

_HALF_PI = 0.5 * math.pi


_THR = _HALF_PI**2  # θ² below which θ/2 ≤ π/4 and the polynomials apply directly


def _horner(x, coeffs):
    out = coeffs[-1]
    for c in reversed(coeffs[:-1]):
        out = out * x + c
    return out


def _is64(dtype):
    return jnp.dtype(dtype) == jnp.float64


def _sinc_cos_coeffs(dtype):
    n = 9 if _is64(dtype) else 6
    sinc = [(-1) ** i / math.factorial(2 * i + 1) for i in range(n)]  # sin(r)/r in r²
    cos = [(-1) ** i / math.factorial(2 * i) for i in range(n)]  # cos(r) in r²
    return sinc, cos


def _jr_b_small(t2):
    """``(θ - sin θ)/θ³`` as a polynomial in ``θ²`` (θ ≤ π/2)."""
    n = 10 if _is64(t2.dtype) else 6
    return _horner(t2, [(-1) ** i / math.factorial(2 * i + 3) for i in range(n)])


def _half_small(t2):
    """``(cos(θ/2), sin(θ/2)/θ)`` for θ ≤ π/2: polynomials in θ² (no sqrt, no division)."""
    sinc, cos = _sinc_cos_coeffs(t2.dtype)
    r2 = 0.25 * t2
    return _horner(r2, cos), 0.5 * _horner(r2, sinc)


def _half_any(t2):
    """Same for any θ: Cody-Waite reduction of θ/2 by π/2 and the same polynomials.

    Elements with θ ≤ π/2 get exactly the values of :func:`_half_small`; the others see a
    safe argument (double where), so values and gradients stay finite everywhere.
    """
    sinc, cos = _sinc_cos_coeffs(t2.dtype)
    small = t2 < _THR
    theta = jnp.sqrt(jnp.where(small, _THR, t2))
    x = 0.5 * theta
    k = jnp.round(x * (2.0 / math.pi))
    if _is64(t2.dtype):
        c1, c2, c3 = 1.5707963267341256, 6.077100506506192e-11, 2.0222568e-21
    else:
        c1, c2, c3 = 1.5703125, 4.837512969970703125e-4, 7.549789948768648e-8
    r = ((x - k * c1) - k * c2) - k * c3
    r2 = jnp.where(small, 0.25 * t2, r * r)
    S, C = _horner(r2, sinc), _horner(r2, cos)
    s = r * S
    n = k - 4.0 * jnp.floor(0.25 * k)  # quadrant
    odd = (n == 1) | (n == 3)
    sa, ca = jnp.where(odd, C, s), jnp.where(odd, s, C)
    sin_x = jnp.where(n >= 2, -sa, sa)
    cos_x = jnp.where((n == 1) | (n == 2), -ca, ca)
    return jnp.where(small, C, cos_x), jnp.where(small, 0.5 * S, sin_x / theta)


def _any_big(t2):
    return jnp.any(t2 >= _THR)


# ----------------------------------------------------------------------------- SoA algebra


def _quat_normalize(q):
    """``q / |q|`` as ``q · rsqrt(|q|²)``: one square root and one division per lane
    instead of four divisions (faster: docs/DESIGN.md section 3, "One square root a
    normalisation"; the result differs from the division in the last bit)."""
    r = jax.lax.rsqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return tuple(x * r for x in q)


def _quat_renormalize(q):
    """``q / |q|`` for a ``q`` whose norm is 1 to rounding: a unit quaternion times a unit
    increment. With ``ε = |q|² - 1``, ``1/|q| = 1 - ε/2 + 3ε²/8 - …``, so
    ``r = (3 - |q|²)/2`` is the division's to ``3ε²/8``, below rounding while ``|ε|`` is
    (then ``|q r|`` is 1 within ``3ε²/8`` and each step squares the deviation; the
    direction is the division's exactly). The engines start from a normalised ``q``
    (:func:`jaximu.engine._inputs.unit_start`), so every step's input is such a product. The
    square root and the division sat on a step's loop-carried path (each step's rotation
    waits for the last one's): one float64 trajectory 1.3x faster without them
    (docs/DESIGN.md, "Renormalisation"). Over many lanes ``r`` is stored once
    (:func:`_materialise`) for the four components to read; XLA would otherwise recompute
    it in each. Increments that are not unit (first order, VINS-Mono's midpoint) use
    :func:`_quat_normalize`."""
    r = 1.5 - 0.5 * (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if jnp.size(r) > 1:
        (r,) = _materialise([r])
    return tuple(x * r for x in q)


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _quat_rotate(q, v):
    """``R(q) v = v + 2w (u×v) + 2 u×(u×v)`` (as :func:`jaximu.so3.quat_rotate`)."""
    w, u = q[0], q[1:]
    t = tuple(2.0 * x for x in _cross(u, v))
    c = _cross(u, t)
    return tuple(v[i] + w * t[i] + c[i] for i in range(3))


def half_angle(t2):
    """``(cos(θ/2), sin(θ/2)/θ)`` for per-lane ``θ² = t2``: the range-reduced path only when
    some lane needs it."""
    return _cond(_any_big(t2), _half_any, _half_small, t2)


def quat_matrix(q, dtype):
    """:func:`jaximu.so3.quat_to_matrix` (also for a non-unit ``q``) as ``(3, 3, B)``:
    ``I + 2(u uᵀ - |u|² I) + 2 w [u]x``."""
    I3 = jnp.asarray(_E3, dtype)[:, :, None]
    w, u = q[0], q[1:]
    u3 = _rows(u, dtype)
    return (
        I3
        + 2.0 * (_outer(u3, u3) - _lane(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]) * I3)
        + _lane(2.0 * w) * _skew3(u, dtype)
    )


# ----------------------------------------------------------------------------- 3x3 blocks

_E3 = np.eye(3)


_S3 = so3.SKEW_GENERATORS


def _bmm(X, Y):
    """Blockwise ``X @ Y`` of ``(n, k, B)`` and ``(k, m, B)`` arrays (batch minor; 3×3
    blocks, or the ``m``-row blocks of a measurement): one vectorised loop."""
    out = X[:, 0:1] * Y[0:1, :]
    for i in range(1, X.shape[1]):
        out = out + X[:, i : i + 1] * Y[i : i + 1, :]
    return out


def _rows(rows, dtype):
    """``m`` rows, each ``(B,)`` or ``(n, B)``, -> ``(m, B)`` or ``(m, n, B)`` by broadcasting
    against one-hot columns (no concatenate)."""
    E = np.eye(len(rows))
    terms = [
        jnp.asarray(E[:, i], dtype).reshape((-1,) + (1,) * r.ndim) * r[None]
        for i, r in enumerate(rows)
    ]
    out = terms[0]
    for x in terms[1:]:
        out = out + x
    return out


def _cholesky(S):
    """Lower Cholesky factor ``L`` of a symmetric positive definite ``(m, m, B)`` on lanes
    (:data:`SOA`'s ``cholesky``), unrolled (``m`` is small: a measurement's rows, a 3×3
    block): nested lists of ``(B,)`` entries, ``F[i][j] = L_ij`` below the diagonal and
    ``F[i][i] = 1 / L_ii`` (what :func:`_tri_solve` multiplies by)."""
    m = S.shape[0]
    L = [[None] * m for _ in range(m)]
    for j in range(m):
        d = S[j, j]
        for k in range(j):
            d = d - L[j][k] * L[j][k]
        inv = 1.0 / jnp.sqrt(d)
        L[j][j] = inv
        for i in range(j + 1, m):
            x = S[i, j]
            for k in range(j):
                x = x - L[i][k] * L[j][k]
            L[i][j] = x * inv
    return _materialise(L)


def _tri_solve(L, X, trans=False):
    """``L⁻¹ X`` (``trans``: ``L⁻ᵀ X``) for a factor of :func:`_cholesky` and ``X`` of shape
    ``(m, n, B)``: substitution row by row."""
    m = len(L)
    Y = [None] * m
    order = range(m - 1, -1, -1) if trans else range(m)
    for i in order:
        y = X[i]
        for k in range(i + 1, m) if trans else range(i):
            y = y - (L[k][i] if trans else L[i][k])[None] * Y[k]
        Y[i] = y * L[i][i][None]
    return _rows(Y, X.dtype)


def _bt(X):
    return jnp.swapaxes(X, 0, 1)


def _skew3(t, dtype):
    """3-tuple of ``(B,)`` -> ``[v]x`` as ``(3, 3, B)`` (:func:`jaximu.geometry.so3.skew_of`)."""
    return so3.skew_of(tuple(jnp.asarray(x, dtype) for x in t), lanes_last=True)


def _outer(u, v):
    return u[:, None, :] * v[None, :, :]


def _lane(s):
    """A per-lane scalar ``(B,)`` (or a Python/0-d scalar) broadcast against ``(3, 3, B)``."""
    return s[None, None] if jnp.ndim(s) else s


def _diag_row(s3, dtype):
    if jnp.ndim(s3[0]):
        return _rows(s3, dtype)[None]
    return jnp.stack([jnp.asarray(x, dtype) for x in s3])[None, :, None]


def _materialise(tree):
    """:func:`_stage` of the identity on a pytree: its array leaves are computed once, in
    memory; other leaves (the identity block marker ``"I"`` of :mod:`jaximu.schemes._blocks`) pass
    as they are."""
    if device.backend() != device.CPU:  # a stage is the plain call there (_stage)
        return tree
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    marks = [isinstance(x, str) for x in leaves]
    arrays = [x for x, m in zip(leaves, marks) if not m]
    big = [x for x in arrays if jnp.ndim(x)]
    pred = big[0].ravel()[0] == big[0].ravel()[0]  # any runtime value: branches agree
    staged = iter(_stage(pred, lambda a: [x * 1 for x in a], arrays))
    return jax.tree_util.tree_unflatten(
        treedef, [x if m else next(staged) for x, m in zip(leaves, marks)]
    )


def _diag3(s3, dtype):
    return jnp.asarray(_E3, dtype)[:, :, None] * _diag_row(s3, dtype)


def _dtype_of(v):
    return jnp.result_type(*v)


def half_angle_jr(t2):
    """``(cos(θ/2), sin(θ/2)/θ, (θ - sin θ)/θ³)`` for per-lane ``θ² = t2``: polynomials in
    θ² (the range-reduced half angle only when some lane needs it); finite values and
    derivatives at θ = 0 (double ``where``)."""

    def small(t2):
        c, k = _half_small(t2)
        return c, k, _jr_b_small(t2)

    def big(t2):
        c, k = _half_any(t2)
        sm = t2 < _THR
        # sin θ / θ = 2 k c, so (θ - sin θ)/θ³ = (1 - 2kc)/θ²
        b = jnp.where(
            sm, _jr_b_small(jnp.where(sm, t2, 0.0)), (1.0 - 2.0 * k * c) / jnp.where(sm, 1.0, t2)
        )
        return c, k, b

    return _cond(_any_big(t2), big, small, t2)


def exp_jr(phi: V3, half=None):
    """``(Exp(φ), Jr(φ))`` as ``(3, 3, B)`` from the half-angle scalars (``half``: those of
    :func:`half_angle_jr` when the caller has them):

        Exp(φ) = (c² - k²θ²) I + 2k² φφᵀ + 2kc [φ]x,   Jr(φ) = I - 2k² [φ]x + b [φ]x²,

    with ``c = cos(θ/2)``, ``k = sin(θ/2)/θ``, ``b = (θ - sin θ)/θ³``, ``[φ]x² = φφᵀ - θ² I``."""
    dtype = _dtype_of(phi)
    t2 = phi.dot(phi)
    c, k, b = half_angle_jr(t2) if half is None else half
    I3 = jnp.asarray(_E3, dtype)[:, :, None]
    p3 = _rows(phi, dtype)
    ppT = _outer(p3, p3)
    K = _skew3(phi, dtype)
    kk = k * k
    E = _lane(c * c - kk * t2) * I3 + _lane(2.0 * kk) * ppT + _lane(2.0 * k * c) * K
    J = I3 - _lane(2.0 * kk) * K + _lane(b) * (ppT - _lane(t2) * I3)
    return E, J


SOA = Layout(
    matmul=lambda X, Y: _bmm(X, Y),
    transpose=lambda X: _bt(X),
    scale=lambda s, X: _lane(s) * X,
    scale_cols=lambda X, s: X * _diag_row(s, X.dtype),
    diag=lambda s: _diag3(s, jnp.result_type(*s)),
    barrier=lambda tree: _materialise(tree),
    skew=lambda v: _skew3(v, _dtype_of(v)),
    matvec=lambda X, v: V3(*(X[i, 0] * v.x + X[i, 1] * v.y + X[i, 2] * v.z for i in range(3))),
    exp_jr=exp_jr,
    # a shared (3, 3) block broadcasts over the lanes; a per-lane (B, 3, 3) one moves its
    # batch axis last
    from_arrays=lambda X: X[..., None] if X.ndim == 2 else jnp.moveaxis(X, 0, -1),
    cholesky=_cholesky,
    tri_solve=_tri_solve,
)
"""The block algebra of :mod:`jaximu.schemes._blocks` on ``(3, 3, B)`` batch-minor blocks; 3-vectors
per lane are 3-tuples of ``(B,)`` arrays (or scalars)."""


def _stage(pred, fn, *args):
    """Run ``fn`` inside a ``lax.cond`` with two identical branches: XLA materialises a
    conditional's outputs, so a value read by several fusions is computed once (XLA CPU has
    no multi-output fusion and otherwise recomputes it inside every consumer fusion, and twice
    for a transposed read). ``pred`` must be a runtime value (any): with a constant one XLA
    inlines the conditional and the boundary disappears. On an accelerator the plain call:
    XLA:GPU fuses with several outputs, and a conditional there waits for its predicate on
    the host at every step."""
    return _cond(pred, fn, fn, *args)


def _cond(pred, true_fn, false_fn, *args):
    """``lax.cond`` on the CPU; ``true_fn(*args)`` on an accelerator, where a conditional
    copies its predicate to the host and waits for it (each step of a scan then costs a
    round trip). Only for conds whose ``true_fn`` is right for every input (the range-reduced
    branch, a stage's identical branches)."""
    if device.backend() != device.CPU:
        return true_fn(*args)
    return jax.lax.cond(pred, true_fn, false_fn, *args)
