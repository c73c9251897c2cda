"""Fast XLA-CPU formulations of the two hot loops (Euler scheme, exact quaternion exponential).

Why this module exists (measured on a 2-core AVX2 x86 box, JAX 0.10.2; see the perf report):

* **Structure of arrays.** Inside the scan every per-sample quantity is a tuple of ``(B,)``
  arrays (one per component) and every 3×3 covariance block is a ``(3, 3, B)`` array (batch
  minor). Each XLA loop fusion is then a plain loop over the batch that LLVM vectorises.
  With the ``(B, 3)`` layout the fusions read several components of one buffer through the
  scan's dynamic-slice index, which LLVM cannot vectorise (scalar code).
* **No concatenates in the loop** (``jnp.stack`` becomes a scalar select loop on XLA CPU);
  vectors and blocks are assembled by broadcasting against constant one-hot tensors.
* **Polynomial sin/cos.** ``jnp.sin``/``jnp.cos`` are scalar libm calls on XLA CPU. The half
  angle of the exponential uses even polynomials in θ² (exact to rounding for θ ≤ π/2, no
  sqrt/division, NaN-free gradient at 0); a Cody-Waite range-reduced path handles larger
  angles and runs only when some element needs it (``lax.cond``).
* **Stage boundaries.** XLA CPU has no multi-output fusion: a value read by several fusions is
  recomputed in each (and a transposed read recomputes it again). The covariance update is
  split into stages whose outputs are materialised by running them inside ``lax.cond`` with
  identical branches.
* **Blocking.** Batches are processed in blocks of at most ``_BLOCK`` lanes (state in L1/L2),
  and time in chunks of ``K`` samples whose inputs are transposed to time-major per chunk.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

_BLOCK = 1024  # lanes per batch block
MEAN_MIN_BATCH = 32  # below this the generic mean loop is as fast (XLA compiles it to one kernel)
_CHUNK = (64, 16)  # preferred largest / smallest time chunk

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
    n = jnp.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return tuple(x / n for x in q)


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _quat_rotate(q, v):
    """``R(q) v = v + 2w (u×v) + 2 u×(u×v)`` (as :func:`jaximu.so3.quat_rotate`)."""
    w, u = q[0], q[1:]
    t = tuple(2.0 * x for x in _cross(u, v))
    c = _cross(u, t)
    return tuple(v[i] + w * t[i] + c[i] for i in range(3))


def _mean_update(q, p, v, uq, phi, c, k, h, g):
    """Euler step with the exact exponential, renormalised (integrators.step)."""
    dq = (c, k * phi[0], k * phi[1], k * phi[2])
    q1 = _quat_normalize(_quat_mul(q, dq))
    a = tuple(uq[i] + g[i] for i in range(3))
    hh = 0.5 * h * h
    p1 = tuple((p[i] + h * v[i]) + hh * a[i] for i in range(3))
    v1 = tuple(v[i] + h * a[i] for i in range(3))
    return q1, p1, v1


def mean_step(carry, omega, f, h, g):
    """One mean step on SoA tuples: ``carry = (q, p, v)``."""
    q, p, v = carry
    uq = _quat_rotate(q, f)
    phi = tuple(h * w for w in omega)
    t2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    c, k = jax.lax.cond(_any_big(t2), _half_any, _half_small, t2)
    return _mean_update(q, p, v, uq, phi, c, k, h, g)


# ----------------------------------------------------------------------------- 3x3 blocks

_E3 = np.eye(3)
_S3 = np.stack([np.stack([np.cross(_E3[i], _E3[c]) for c in range(3)], axis=1) for i in range(3)])


def _bmm(X, Y):
    """Blockwise ``X @ Y`` of ``(3, 3, B)`` arrays (batch minor): one vectorised loop."""
    return X[:, 0:1] * Y[0:1, :] + X[:, 1:2] * Y[1:2, :] + X[:, 2:3] * Y[2:3, :]


def _bt(X):
    return jnp.swapaxes(X, 0, 1)


def _bsym(X):
    return 0.5 * (X + _bt(X))


def _vec3(t, dtype):
    """3-tuple of ``(B,)`` -> ``(3, B)`` by broadcasting (no concatenate)."""
    E = jnp.asarray(_E3, dtype)
    return E[:, 0:1] * t[0][None] + E[:, 1:2] * t[1][None] + E[:, 2:3] * t[2][None]


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
        return _vec3(s3, dtype)[None]
    return jnp.stack([jnp.asarray(x, dtype) for x in s3])[None, :, None]


def _stage(pred, fn, *args):
    """Run ``fn`` inside a ``lax.cond`` with two identical branches: XLA materialises a
    conditional's outputs, so a value read by several fusions is computed once (XLA CPU has
    no multi-output fusion and otherwise recomputes it inside every consumer fusion, and twice
    for a transposed read). ``pred`` must be a runtime value (any): with a constant one XLA
    inlines the conditional and the boundary disappears."""
    return jax.lax.cond(pred, fn, fn, *args)


def _lane_scalars(big):
    """Stage 1 (per lane): the mean update and the scalars of the Φ blocks."""

    def f(q, p, v, omega, fsp, h, g):
        uq = _quat_rotate(q, fsp)
        phi = tuple(h * w for w in omega)
        t2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
        if big:
            c, k = _half_any(t2)
            sm = t2 < _THR
            b = jnp.where(sm, _jr_b_small(jnp.where(sm, t2, 0.0)),
                          (1.0 - 2.0 * k * c) / jnp.where(sm, 1.0, t2))
        else:
            c, k = _half_small(t2)
            b = _jr_b_small(t2)
        mean = _mean_update(q, p, v, uq, phi, c, k, h, g)
        return mean, (uq, phi, t2, c, k, b)

    return f


def _phi_blocks(q, h, uq, phi, t2, c, k, b):
    """Φ blocks (Euler, exact exp; errorstate.blocks_analytic) as ``(3, 3, B)`` arrays:
    A = Exp(φ)ᵀ, Bm = -h Jr(φ), Cv = -h [R f]x R, Ev = -h R."""
    dtype = q[0].dtype
    I3 = jnp.asarray(_E3, dtype)[:, :, None]
    w0, qv = q[0], q[1:]
    qv3 = _vec3(qv, dtype)
    R = (_lane(w0 * w0 - (qv[0] * qv[0] + qv[1] * qv[1] + qv[2] * qv[2])) * I3
         + 2.0 * _outer(qv3, qv3) + _lane(2.0 * w0) * _skew3(qv, dtype))
    mh = _lane(-h) if jnp.ndim(h) else -h
    Ev = mh * R
    Cv = _bmm(_skew3(uq, dtype), Ev)
    phi3 = _vec3(phi, dtype)
    ppT = _outer(phi3, phi3)
    K = _skew3(phi, dtype)
    kk = k * k
    A = _lane(c * c - kk * t2) * I3 + _lane(2.0 * kk) * ppT - _lane(2.0 * c * k) * K
    Bm = mh * (I3 - _lane(2.0 * kk) * K + _lane(b) * (ppT - _lane(t2) * I3))
    return A, Bm, Cv, Ev


def cov_step(carry, omega, f, h, g, qc):
    """Mean + covariance step. ``carry = (q, p, v, Pb)`` with ``Pb`` the tuple of the 15
    upper 3×3 blocks of P in :data:`UPPER` order, each ``(3, 3, B)``. ``qc``: 12-tuple of
    the diagonal of ``Q_c`` (scalars or ``(B,)``)."""
    q, p, v, Pb = carry
    dtype = q[0].dtype
    t2 = sum((h * w) * (h * w) for w in omega)
    (q1, p1, v1), lane = jax.lax.cond(_any_big(t2), _lane_scalars(True), _lane_scalars(False),
                                      q, p, v, omega, f, h, g)
    ok = jnp.all(jnp.isfinite(h))  # any runtime predicate (both branches are the same)
    # Materialised copies of h and qc: a dynamic-slice of the scan input inside the 3-D block
    # fusions (its index reloaded in the loop) stops LLVM from vectorising them.
    h, qc = _stage(ok, lambda h, qc: (h * 1, tuple(x * 1 for x in qc)), h, qc)
    A, Bm, Cv, Ev = _stage(ok, _phi_blocks, q, h, *lane)
    Pd = dict(zip(UPPER, Pb))
    hb = _lane(h) if jnp.ndim(h) else h

    def P(i, j):
        return Pd[(i, j)] if i <= j else _bt(Pd[(j, i)])

    def stage_a(Pb, A, Bm, Cv, Ev):
        Pd = dict(zip(UPPER, Pb))

        def P(i, j):
            return Pd[(i, j)] if i <= j else _bt(Pd[(j, i)])

        # M = Φ P, θ rows; N_j = Cv P0j + Ev P4j gives the v rows (P2j + N_j) and, for Euler,
        # the p rows (P1j + h P2j + h/2 N_j) since Cp = h/2 Cv and Ep = h/2 Ev.
        M0 = tuple(_bmm(A, P(0, j)) + _bmm(Bm, P(3, j)) for j in range(5))
        N = tuple(_bmm(Cv, P(0, j)) + _bmm(Ev, P(4, j)) for j in range(5))
        return M0, N

    M0, N = _stage(ok, stage_a, Pb, A, Bm, Cv, Ev)
    M1 = [P(1, j) + hb * P(2, j) + (0.5 * hb) * N[j] for j in range(5)]
    M2 = [P(2, j) + N[j] for j in range(5)]

    def stage_b(M0, M1, M2, Bm, Cv, Ev, qc):
        Cvt, Evt, Bt = _bt(Cv), _bt(Ev), _bt(Bm)
        Kv = tuple(_bmm(M[0], Cvt) + _bmm(M[4], Evt) for M in (M0, M1, M2))  # (M Φᵀ)_v - M_v
        Qth = _bmm(Bm * _diag_row(qc[0:3], dtype), Bt)
        Qv = _bmm(Ev * _diag_row(qc[3:6], dtype), Evt)
        return Kv, Qth, Qv

    (K0, K1, K2), Qth, Qv = _stage(ok, stage_b, M0, M1, M2, Bm, Cv, Ev, qc)
    I3 = jnp.asarray(_E3, dtype)[:, :, None]
    new = {
        (0, 0): _bsym(_bmm(M0[0], _bt(A)) + _bmm(M0[3], _bt(Bm)) + Qth),
        (0, 1): M0[1] + hb * M0[2] + (0.5 * hb) * K0,
        (0, 2): M0[2] + K0,
        (0, 3): M0[3],
        (0, 4): M0[4],
        (1, 1): _bsym(M1[1] + hb * M1[2] + (0.5 * hb) * K1 + (0.25 * hb * hb) * Qv),
        (1, 2): M1[2] + K1 + (0.5 * hb) * Qv,
        (1, 3): M1[3],
        (1, 4): M1[4],
        (2, 2): _bsym(M2[2] + K2 + Qv),
        (2, 3): M2[3],
        (2, 4): M2[4],
        (3, 3): _bsym(Pd[(3, 3)] + (hb * hb) * (I3 * _diag_row(qc[6:9], dtype))),
        (3, 4): Pd[(3, 4)],
        (4, 4): _bsym(Pd[(4, 4)] + (hb * hb) * (I3 * _diag_row(qc[9:12], dtype))),
    }
    return q1, p1, v1, tuple(new[ij] for ij in UPPER)


UPPER = tuple((i, j) for i in range(5) for j in range(i, 5))


# ----------------------------------------------------------------------------- drivers


def _components(x):
    return tuple(x[..., i] for i in range(x.shape[-1]))


def _block_size(B):
    if B <= _BLOCK:
        return B
    for nb in range(-(-B // _BLOCK), B // 256 + 1):
        if B % nb == 0:
            return B // nb
    return B


def _chunk_size(T):
    hi, lo = _CHUNK
    if T <= hi:
        return T
    for K in range(hi, lo - 1, -1):
        if T % K == 0:
            return K
    return 32  # remainder handled by a second (shorter) segment


def _time_chunks(step, carry, gyro, accel, dt, consts, save):
    """Scan ``step(carry, w, a, h, consts) -> carry`` over time for one batch block.

    gyro, accel: ``(Bc, T, 3)``; dt: ``(T,)`` or ``(Bc, T)``. Inputs are transposed to
    time-major ``(K, Bc)`` components one chunk of K samples at a time (cache-resident).
    ``save(carry) -> tuple of (Bc, n)`` arrays written at every sample into ``(Bc, T, n)``
    buffers (or ``None``).
    """
    Bc, T, _ = gyro.shape
    K = _chunk_size(T)
    nC, rem = divmod(T, K)

    def comps(x, t0, L):
        c = jax.lax.dynamic_slice_in_dim(x, t0, L, axis=1)  # (Bc, L, 3)
        ct = jnp.transpose(c, (2, 1, 0))  # (3, L, Bc)
        return tuple(ct[i] for i in range(ct.shape[0]))

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

        xs = (t0 + jnp.arange(L), comps(gyro, t0, L), comps(accel, t0, L), hs(t0, L))
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


def run_blocked(block_fn, B, *args):
    """``block_fn(*block_args)`` over batch blocks; every leaf of ``args`` has leading axis B."""
    Bc = _block_size(B)
    if Bc == B:
        return block_fn(*args)
    nb = B // Bc
    split = lambda x: x.reshape((nb, Bc) + x.shape[1:])  # noqa: E731
    out = jax.lax.map(lambda a: block_fn(*a), jax.tree_util.tree_map(split, args))
    return jax.tree_util.tree_map(lambda x: x.reshape((B,) + x.shape[2:]), out)


def _stack_last(t):
    return jnp.stack(t, axis=-1)


def propagate_mean(q, p, v, b_g, b_a, gyro, accel, dt, g, save_all):
    """Flat batch: q ``(B, 4)``, p/v/b_g/b_a ``(B, 3)``, gyro/accel ``(B, T, 3)``,
    dt ``(T,)`` or ``(B, T)``, g ``(3,)`` or ``(B, 3)``. Returns final ``(q, p, v)`` (B, ·)
    or, with save_all, the ``(B, T, ·)`` trajectories."""
    B = gyro.shape[0]
    shared_dt = dt.ndim == 1
    shared_g = g.ndim == 1

    def block(q, p, v, b_g, b_a, gyro, accel, dt_b, g_b):
        consts = (_components(b_g), _components(b_a), _components(g_b if not shared_g else g))
        carry = (_components(q), _components(p), _components(v))

        def step(c, w, a, h, consts):
            bg, ba, gv = consts
            omega = tuple(w[i] - bg[i] for i in range(3))
            f = tuple(a[i] - ba[i] for i in range(3))
            return mean_step(c, omega, f, h, gv)

        save = (lambda c: tuple(_stack_last(x) for x in c)) if save_all else None
        carry, bufs = _time_chunks(step, carry, gyro, accel, dt if shared_dt else dt_b, consts, save)
        if save_all:
            return bufs
        return tuple(_stack_last(x) for x in carry)

    dt_arg = jnp.zeros((B, 1), gyro.dtype) if shared_dt else dt
    g_arg = jnp.zeros((B, 1), gyro.dtype) if shared_g else g
    return run_blocked(block, B, q, p, v, b_g, b_a, gyro, accel, dt_arg, g_arg)


def dense_to_blocks(P):
    """``(B, 15, 15)`` -> tuple of the 15 upper blocks as ``(3, 3, B)``."""
    return tuple(jnp.moveaxis(P[:, 3 * i:3 * i + 3, 3 * j:3 * j + 3], 0, -1) for i, j in UPPER)


def blocks_to_dense(Pb):
    d = dict(zip(UPPER, Pb))

    def get(i, j):
        return d[(i, j)] if i <= j else _bt(d[(j, i)])

    D = jnp.concatenate([jnp.concatenate([get(i, j) for j in range(5)], 1) for i in range(5)], 0)
    return jnp.moveaxis(D, -1, 0)


def propagate_cov_final(q, p, v, b_g, b_a, P0, gyro, accel, dt, g, qc_fn, qc_per_lane):
    """Final mean and covariance. ``qc_fn(h, lane_params) -> (…, 12)`` discrete variances;
    ``qc_per_lane``: ``(B, m)`` per-lane noise parameters (or None for shared noise)."""
    B = gyro.shape[0]
    shared_dt = dt.ndim == 1
    shared_g = g.ndim == 1

    def block(q, p, v, b_g, b_a, P0, gyro, accel, dt_b, g_b, lane_noise):
        consts = (_components(b_g), _components(b_a), _components(g if shared_g else g_b),
                  None if qc_per_lane is None else lane_noise)
        carry = (_components(q), _components(p), _components(v), dense_to_blocks(P0))

        def step(c, w, a, h, consts):
            bg, ba, gv, ln = consts
            omega = tuple(w[i] - bg[i] for i in range(3))
            f = tuple(a[i] - ba[i] for i in range(3))
            qc = qc_fn(h, ln)  # (12,) or (Bc, 12)
            qc = tuple(qc[..., i] for i in range(12))
            return cov_step(c, omega, f, h, gv, qc)

        (q, p, v, Pb), _ = _time_chunks(step, carry, gyro, accel, dt if shared_dt else dt_b,
                                        consts, None)
        return _stack_last(q), _stack_last(p), _stack_last(v), blocks_to_dense(Pb)

    z = jnp.zeros((B, 1), gyro.dtype)
    return run_blocked(block, B, q, p, v, b_g, b_a, P0, gyro, accel,
                       z if shared_dt else dt, z if shared_g else g,
                       z if qc_per_lane is None else qc_per_lane)
