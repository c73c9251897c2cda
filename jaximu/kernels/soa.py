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
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental.xla_metadata import set_xla_metadata

from jaximu.geometry import so3
from jaximu.geometry._vec import V3
from jaximu.kernels import device
from jaximu.schemes._blocks import Layout
from jaximu.schemes.integrators import get_attitude, stage_sum

_CHUNK = (64, 16)  # preferred largest / smallest time chunk
HALO = 2
"""Samples before a time chunk that :func:`_time_chunks` gives its ``samples`` function
(two: the held last sample of a next-sample scheme takes the derivative of the one before
it)."""

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


def _quat_mul(p, q):
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw)


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
    (:func:`jaximu.propagate.unit_start`), so every step's input is such a product. The
    square root and the division sat on a step's loop-carried path (each step's rotation
    waits for the last one's): one float64 trajectory 1.3x faster without them
    (docs/DESIGN.md, "Renormalisation"). Over many lanes ``r`` is stored once
    (:func:`_materialise`) for the four components to read; XLA would otherwise recompute
    it in each. Increments that are not unit (first order, VINS-Mono's midpoint) use
    :func:`_quat_normalize`."""
    r = 1.5 - 0.5 * (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if jnp.size(r) > 1:
        r, = _materialise([r])
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
    return (I3 + 2.0 * (_outer(u3, u3) - _lane(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]) * I3)
            + _lane(2.0 * w) * _skew3(u, dtype))


# ----------------------------------------------------------------------------- 3x3 blocks

_E3 = np.eye(3)
_S3 = np.stack([np.stack([np.cross(_E3[i], _E3[c]) for c in range(3)], axis=1) for i in range(3)])


def _bmm(X, Y):
    """Blockwise ``X @ Y`` of ``(n, k, B)`` and ``(k, m, B)`` arrays (batch minor; 3×3
    blocks, or the ``m``-row blocks of a measurement): one vectorised loop."""
    out = X[:, 0:1] * Y[0:1, :]
    for i in range(1, X.shape[1]):
        out = out + X[:, i:i + 1] * Y[i:i + 1, :]
    return out


def _rows(rows, dtype):
    """``m`` rows, each ``(B,)`` or ``(n, B)``, -> ``(m, B)`` or ``(m, n, B)`` by broadcasting
    against one-hot columns (no concatenate)."""
    E = np.eye(len(rows))
    terms = [jnp.asarray(E[:, i], dtype).reshape((-1,) + (1,) * r.ndim) * r[None]
             for i, r in enumerate(rows)]
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
        for k in (range(i + 1, m) if trans else range(i)):
            y = y - (L[k][i] if trans else L[i][k])[None] * Y[k]
        Y[i] = y * L[i][i][None]
    return _rows(Y, X.dtype)


def _bt(X):
    return jnp.swapaxes(X, 0, 1)


def _bsym(X):
    return 0.5 * (X + _bt(X))


def _skew3(t, dtype):
    """3-tuple of ``(B,)`` -> ``[v]x`` as ``(3, 3, B)``."""
    S = jnp.asarray(_S3, dtype)
    return sum(S[i][:, :, None] * t[i][None, None] for i in range(3))


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
    return jax.tree_util.tree_unflatten(treedef, [x if m else next(staged)
                                                  for x, m in zip(leaves, marks)])


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
        b = jnp.where(sm, _jr_b_small(jnp.where(sm, t2, 0.0)),
                      (1.0 - 2.0 * k * c) / jnp.where(sm, 1.0, t2))
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


# ----------------------------------------------------------------------------- autodiff blocks
#
# Jacobian blocks of a step by jax.jvp on lanes (the propagation kernels' and the
# preintegration kernels'): three directions at a time, direction axis major, lanes minor.


def lane_directions(cols, dtype, lanes):
    """``cols`` (3 directions × 3 components, a numpy array) as a 3-tuple of ``(3, *lanes)``
    components: direction j's component i is ``cols[j, i]`` on every lane."""
    return tuple(jnp.broadcast_to(jnp.asarray(cols[:, i], dtype)[:, None], (3,) + lanes)
                 for i in range(3))


def rotation_tangents(q, world=False):
    """The tangents of ``q ⊗ Exp(δθ)`` (``world``: ``Exp(δθ) ⊗ q``) in the 3 directions of
    ``δθ``: ``q ⊗ [0, ½ e_j]`` (``[0, ½ e_j] ⊗ q``), a 4-tuple of ``(3, *lanes)``."""
    dtype, lanes = q[0].dtype, q[0].shape
    E = np.eye(3)
    # Python floats (weakly typed): the tangents keep the lanes' dtype
    half = [_quat_mul(tuple(0.5 * float(x) for x in (0.0, *E[j])), q) if world
            else _quat_mul(q, tuple(0.5 * float(x) for x in (0.0, *E[j]))) for j in range(3)]
    onehot = lane_directions(E, dtype, lanes)  # onehot[j][d] = δ_jd on every lane
    return tuple(sum(onehot[j] * half[j][c][None] for j in range(3)) for c in range(4))


def jvp_directions(fn, primals, tangents):
    """``jax.jvp`` of ``fn`` in several directions at once (a ``vmap`` over the leading axis
    of ``tangents``); returns the output tangents, direction axis first."""
    return jax.vmap(lambda t: jax.jvp(fn, primals, t)[1])(tangents)


def direction_block(rows, dtype):
    """3 output components, each ``(3 directions, *lanes)``, as the ``(3, 3, *lanes)`` block
    ``[row i, direction j]`` (one-hot broadcasting, not ``jnp.stack``: a concatenate is a
    scalar loop on XLA:CPU)."""
    E3 = jnp.asarray(_E3, dtype)
    return sum(E3[:, i, None, None] * r[None] for i, r in enumerate(rows))


def rotation_rows(tq1, q1, world=False):
    """The rotation error's rows from a tangent ``δq⁺`` of ``q⁺``: ``2 vec(q⁺* ⊗ δq⁺)``
    (``world``: ``2 vec(δq⁺ ⊗ q⁺*)``), the tangent of ``Log(q̂⁺* q⁺)``."""
    conj = tuple(x[None] for x in (q1[0], -q1[1], -q1[2], -q1[3]))
    rel = _quat_mul(tq1, conj) if world else _quat_mul(conj, tq1)
    return tuple(2.0 * rel[1 + i] for i in range(3))


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
            x, jnp.clip(i, 0, size - 1), 1, axis=axis)
        return jnp.concatenate([at(t0 - HALO + j) for j in range(HALO)] + [main]
                               + [at(t0 + n + j) for j in range(after)], axis=axis)

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
            return (tuple(c[:L] for c in w) + tuple(c[1:] for c in w),
                    tuple(c[:L] for c in a) + tuple(c[1:] for c in a))
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
                bufs = tuple(jax.lax.dynamic_update_index_in_dim(b, y, t, 1)
                             for b, y in zip(bufs, save(c)))
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
        typed = (getattr(jax.typeof(x).sharding, "mesh", None)
                 for x in jax.tree_util.tree_leaves(args))
        mesh = next((m for m in typed if m is not None and not m.empty), mesh)
    if mesh.empty:
        return None, ()
    axes = tuple(a for a, kind in zip(mesh.axis_names, mesh.axis_types)
                 if kind != jax.sharding.AxisType.Manual)
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
_ONE_KERNEL_PRIMITIVES = frozenset("""
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
""".split())


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
    if not ONE_KERNEL_ENABLED or jax.default_backend() != "cpu" or not _kernel_safe(
            call.trace(*args).jaxpr.jaxpr):
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
    explicit = any(mesh.axis_types[mesh.axis_names.index(a)] == jax.sharding.AxisType.Explicit
                   for a in axes)

    def put(tree, spec):
        if explicit:
            return jax.tree_util.tree_map(lambda x: jax.sharding.reshard(x, spec), tree)
        return jax.tree_util.tree_map(lambda x: jax.lax.with_sharding_constraint(x, spec),
                                      tree)

    with jax.sharding.use_abstract_mesh(mesh):  # the kernels' own arrays on it too
        if B % n:  # not split: the kernel runs whole, on replicated inputs
            lane_args, shared = put((lane_args, shared), P())
            return _run_blocks(block_fn, B, lanes, lane_args, shared, whole)
        local = jax.shard_map(lambda a, s: _run_blocks(block_fn, B // n, lanes, a, s, whole),
                              in_specs=(P(axes), P()), out_specs=P(axes),
                              axis_names=set(axes), check_vma=False)
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
    explicit = any(mesh.axis_types[mesh.axis_names.index(a)] == jax.sharding.AxisType.Explicit
                   for a in axes)
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


# ----------------------------------------------------------------------------- attitude forms
#
# The attitude forms of jaximu.integrators (``Attitude``) on lanes: a form's state is a tuple
# of lanes (4 for the quaternions, 9 for a matrix, row-major). Each form advances, rotates,
# gives its matrix, its tangents in the rotation error's 3 directions and the error's rows
# from a tangent of the result (autodiff blocks), and turns left (a rotating world).


def _quat_advance(q, phi: V3, half=None):
    """``normalize(q ⊗ Exp(φ))``: the exact exponential, renormalised so that rounding
    cannot let ``|q|`` drift; ``half``: ``(cos(θ/2), sin(θ/2)/θ)`` when the caller has them."""
    c, k = half_angle(phi.dot(phi)) if half is None else half
    return _quat_renormalize(_quat_mul(q, (c, k * phi.x, k * phi.y, k * phi.z)))


def _quat_first_order(q, phi: V3, half=None):
    """``normalize(q ⊗ [1, φ/2])`` (:func:`jaximu.so3.quat_first_order_update`)."""
    return _quat_normalize(_quat_mul(q, (1.0, 0.5 * phi.x, 0.5 * phi.y, 0.5 * phi.z)))


def _quat_rotate_left(q, dth):
    """``normalize(Exp(dθ) ⊗ q)`` for a rotation vector ``dθ`` ``(..., 3)``."""
    e = so3.exp(dth)
    return _quat_normalize(_quat_mul(tuple(e[..., i] for i in range(4)), q))


def _lanes_matrix(x, dtype):
    """A matrix's 9 lanes (row-major) as ``(3, 3, B)`` (one-hot broadcasting)."""
    E = np.eye(9).reshape(9, 3, 3)
    return sum(jnp.asarray(E[n], dtype)[:, :, None] * x[n][None, None] for n in range(9))


def _mat_mul_lanes(X, Y):
    """``X Y`` of two matrices given as 9 lanes each (or ``(3, 3, …)`` blocks), 9 lanes."""
    return tuple(sum(X[3 * i + m] * Y[3 * m + j] for m in range(3))
                 for i in range(3) for j in range(3))


def _matrix_advance(R, phi: V3, half=None):
    """``R Exp(φ)`` (:func:`jaximu.so3.exp_matrix`, from the same half angle)."""
    c, k = half_angle(phi.dot(phi)) if half is None else half
    E = quat_matrix((c, k * phi.x, k * phi.y, k * phi.z), _dtype_of(phi))
    return _mat_mul_lanes(R, tuple(E[n // 3, n % 3] for n in range(9)))


def _matrix_rotate(R, f):
    return tuple(R[3 * i] * f[0] + R[3 * i + 1] * f[1] + R[3 * i + 2] * f[2]
                 for i in range(3))


def _matrix_rotate_left(R, dth):
    """``Exp(dθ) R`` (:func:`jaximu.so3.exp_matrix`) for ``dθ`` ``(..., 3)``."""
    E = so3.exp_matrix(dth)
    return _mat_mul_lanes(tuple(E[..., n // 3, n % 3] for n in range(9)), R)


def _matrix_tangents(R, world=False):
    """The tangents of ``R Exp(δθ)`` (``world``: ``Exp(δθ) R``) in the 3 directions of
    ``δθ``: ``R [e_j]x`` (``[e_j]x R``), 9 lanes of ``(3, *lanes)``."""
    dtype, lanes = R[0].dtype, R[0].shape
    # [e_j]x (_S3[j]) as 9 lanes of (3 directions, *lanes)
    S = tuple(jnp.broadcast_to(jnp.asarray(_S3[:, n // 3, n % 3], dtype).reshape(
        (3,) + (1,) * len(lanes)), (3,) + lanes) for n in range(9))
    Rd = tuple(x[None] for x in R)
    return _mat_mul_lanes(S, Rd) if world else _mat_mul_lanes(Rd, S)


def _matrix_rows(tR1, R1, world=False):
    """The rotation error's rows from a tangent ``δR⁺`` of ``R⁺``: ``vee(R⁺ᵀ δR⁺)``
    (``world``: ``vee(δR⁺ R⁺ᵀ)``), the tangent of ``Log(R̂⁺ᵀ R⁺)`` (its skew part: the
    exact derivative for an orthonormal ``R⁺``)."""
    R1t = tuple(R1[3 * (n % 3) + n // 3][None] for n in range(9))
    M = _mat_mul_lanes(tR1, R1t) if world else _mat_mul_lanes(R1t, tR1)
    return (0.5 * (M[7] - M[5]), 0.5 * (M[2] - M[6]), 0.5 * (M[3] - M[1]))


def _sincos(a):
    """``(sin a, cos a)`` per lane from the range-reduced half angle of ``θ = 2|a|``
    (:func:`_half_any`: ``cos a`` and ``sin|a| / 2|a|``): vectorised arithmetic, where
    ``jnp.sin``/``cos`` are scalar library calls on XLA:CPU."""
    c, k = _half_any(4.0 * (a * a))
    return 2.0 * a * k, c


def _euler_trig(chi):
    """``(sin, cos)`` of roll, pitch and yaw."""
    return tuple(_sincos(x) for x in chi)


def _euler_matrix(chi, trig=None):
    """``R(χ)`` of ZYX angles ``χ = (roll, pitch, yaw)`` as 9 lanes
    (:func:`jaximu.so3.euler_zyx_to_matrix`)."""
    (sr, cr), (sp, cp), (sy, cy) = _euler_trig(chi) if trig is None else trig
    return (cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr,
            sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr,
            -sp, cp * sr, cp * cr)


def _euler_rate(chi, w, trig=None):
    """``E(χ) ω``: the angles' rate for a body rate ``ω`` (:func:`jaximu.so3.euler_rate_matrix`;
    singular at pitch ±π/2, which the kernels report)."""
    (sr, cr), (sp, cp) = (_euler_trig(chi) if trig is None else trig)[:2]
    tp = sp / cp
    return V3(w[0] + (sr * tp) * w[1] + (cr * tp) * w[2], cr * w[1] + (-sr) * w[2],
              (sr / cp) * w[1] + (cr / cp) * w[2])


def _euler_advance(chi, phi: V3, half=None):
    """``χ + E(χ) φ`` (the ``"euler_angles"`` form's update)."""
    return tuple(V3(*chi) + _euler_rate(chi, phi))


def _euler_rotate_left(chi, dth):
    """The angles of ``Exp(dθ) R(χ)`` (as the generic kernels: through quaternions)."""
    q = so3.euler_zyx_to_quat(jnp.stack(jnp.broadcast_arrays(*chi), -1))
    chi1 = so3.quat_to_euler_zyx(so3.quat_normalize(so3.quat_mul(so3.exp(dth), q)))
    return tuple(chi1[..., i] for i in range(3))


def _euler_rates_to_body(trig, d):
    """``W(χ) δχ = E(χ)⁻¹ δχ``: the body-frame rotation of an angle change ``δχ`` (the
    inverse of :func:`_euler_rate`: ``[[1, 0, -sp], [0, cr, sr cp], [0, -sr, cr cp]]``;
    ``trig`` the angles' :func:`_euler_trig`, ``d`` components broadcasting against it)."""
    (sr, cr), (sp, cp) = trig[:2]
    return (d[0] - sp * d[2], cr * d[1] + (sr * cp) * d[2], (-sr) * d[1] + (cr * cp) * d[2])


def _euler_tangents(chi, world=False):
    """The tangents of the angles of ``R(χ) Exp(δθ)`` in the 3 directions of ``δθ``:
    ``E(χ) e_j``, 3 lanes of ``(3, *lanes)`` — the derivative the generic kernels take
    through ``quat_to_euler_zyx`` (periodic in roll and yaw, so the same for angles carried
    past ±π). Body frame only: the angles' step is no right multiplication of ``R``, so the
    world-frame error's ``Φ_θθ`` is not the identity the kernels' world frame assumes
    (:func:`jaximu.kernels.fast.blocks_autodiff`)."""
    if world:
        raise NotImplementedError("Euler angles keep the body-frame rotation error")
    dtype, lanes = chi[0].dtype, chi[0].shape
    trig = _euler_trig(chi)
    cols = [_euler_rate(chi, tuple(float(x) for x in np.eye(3)[j]), trig) for j in range(3)]
    onehot = lane_directions(np.eye(3), dtype, lanes)
    return tuple(sum(onehot[j] * cols[j][i][None] for j in range(3)) for i in range(3))


def _euler_rows(tchi1, chi1, world=False):
    """The rotation error's rows from a tangent ``δχ⁺`` of the angles ``χ⁺``: ``W(χ⁺) δχ⁺``,
    the tangent of ``Log(R̂⁺ᵀ R⁺)`` (body frame only, as :func:`_euler_tangents`)."""
    if world:
        raise NotImplementedError("Euler angles keep the body-frame rotation error")
    trig = tuple((s[None], c[None]) for s, c in _euler_trig(chi1))
    return _euler_rates_to_body(trig, tchi1)


def rk4_euler_angles(chi, p: V3, v: V3, omega0, f0, omega1, f1, h, g: V3):
    """Classical RK4 on ``(χ, p, v)`` with ω, f linear inside the step, on lanes
    (:func:`jaximu.integrators._rk4_euler_angles`, the ``"euler_angles"`` form's RK4)."""
    def deriv(c, w, f):
        trig = _euler_trig(c)
        return _euler_rate(c, w, trig), V3(*_matrix_rotate(_euler_matrix(c, trig), f)) + g

    # a V3 on the left of each product: h may be an array of lanes
    omega_m, f_m = (omega0 + omega1) * 0.5, (f0 + f1) * 0.5
    chi = V3(*chi)
    k1, a1 = deriv(chi, omega0, f0)
    k2, a2 = deriv(chi + k1 * (0.5 * h), omega_m, f_m)
    k3, a3 = deriv(chi + k2 * (0.5 * h), omega_m, f_m)
    k4, a4 = deriv(chi + k3 * h, omega1, f1)
    chi1 = chi + (k1 + k2 * 2 + k3 * 2 + k4) * (h / 6)
    v1 = v + (a1 + a2 * 2 + a3 * 2 + a4) * (h / 6)
    p1 = p + v * h + (a1 + a2 + a3) * (h * h / 6)
    return tuple(chi1), tuple(p1), tuple(v1)


class LaneForm(NamedTuple):
    """An attitude form (:class:`jaximu.integrators.Attitude`) on SoA lanes."""
    name: str
    size: int  # lanes of its state
    advance: Callable  # (x, φ: V3, half=None) -> x ⊞ φ
    rotate: Callable  # (x, f) -> R(x) f, 3 lanes
    matrix: Callable  # (x, dtype) -> R(x) as (3, 3, B)
    tangents: Callable  # (x, world) -> tangents of x ⊞ δθ in 3 directions
    rows: Callable  # (tx⁺, x⁺, world) -> the rotation error's 3 rows
    rotate_left: Callable  # (x, dθ (…, 3)) -> Exp(dθ) R(x), the form's state


_QUAT: dict[str, Any] = dict(size=4, rotate=_quat_rotate, matrix=quat_matrix,
                             tangents=rotation_tangents, rows=rotation_rows,
                             rotate_left=_quat_rotate_left)
LANE_FORMS = {
    "quaternion": LaneForm("quaternion", advance=_quat_advance, **_QUAT),
    "quaternion_first_order": LaneForm("quaternion_first_order", advance=_quat_first_order,
                                       **_QUAT),
    "matrix": LaneForm("matrix", 9, _matrix_advance, _matrix_rotate, _lanes_matrix,
                       _matrix_tangents, _matrix_rows, _matrix_rotate_left),
    # no closed-form Jacobian (autodiff blocks only), the pitch singularity reported by the
    # kernels (jaximu.kernels.fast.propagate_mean, propagate_cov)
    "euler_angles": LaneForm(
        "euler_angles", 3, _euler_advance,
        lambda chi, f: _matrix_rotate(_euler_matrix(chi), f),
        lambda chi, dtype: _lanes_matrix(_euler_matrix(chi), dtype), _euler_tangents,
        _euler_rows, _euler_rotate_left),
}
"""The attitude forms the structure-of-arrays kernels run, each as its own lanes."""


def lane_form(name) -> LaneForm:
    return LANE_FORMS[name]


def from_quat(form: LaneForm, q):
    """The form's state ``(B, size)`` from quaternions ``(B, 4)``: the generic kernels'
    ``Attitude.from_quat``, a matrix flattened row-major."""
    return get_attitude(form.name).from_quat(q).reshape(q.shape[:-1] + (form.size,))


def to_quat(form: LaneForm, x):
    """Quaternions ``(…, 4)`` from the form's states ``(…, size)`` (``Attitude.to_quat``)."""
    shape = (3, 3) if form.size == 9 else (form.size,)
    return get_attitude(form.name).to_quat(x.reshape(x.shape[:-1] + shape))


# ----------------------------------------------------------------------------- mean step


def _rotate_stage(form, x, f):
    """``R f`` of one stage, computed once into memory: the position and velocity rows
    that read it are separate loops, and each would otherwise recompute the rotation (mean
    kernels 1.07-1.25x faster; docs/DESIGN.md, "Stage boundaries")."""
    return V3(*_materialise(form.rotate(x, f)))


def mean_step(scheme, q, p, v, omega0, f0, omega1, f1, h, g, end_half=None,
              form: LaneForm = LANE_FORMS["quaternion"]):
    """One step of ``scheme`` (a :class:`jaximu.integrators.Scheme`) on SoA lanes in the
    attitude form ``form`` (:data:`LANE_FORMS`; default the exact quaternion exponential):
    :func:`jaximu.integrators.step` in this layout.

    Args:
        q: the form's state (4-tuple of ``(B,)`` for a quaternion); p, v, omega*, f*, g:
        :class:`V3` of ``(B,)`` (or scalars); h: ``(B,)`` or scalar step [s].
        end_half: ``(cos(θ/2), sin(θ/2)/θ)`` of the end rotation when the caller has them.

    Returns:
        ``(q⁺, p⁺, v⁺)``.
    """
    if form.name == "euler_angles" and scheme.name == "rk4":
        return rk4_euler_angles(q, p, v, omega0, f0, omega1, f1, h, g)
    pts, phi_end = scheme.points(omega0, f0, omega1, f1, h)
    q_end = form.advance(q, phi_end, end_half)
    p1, v1 = stage_sum(pts, q, q_end, form.advance,
                       lambda x, f: _rotate_stage(form, x, f), p, v, h, g)
    return q_end, tuple(p1), tuple(v1)
