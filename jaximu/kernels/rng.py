"""Counter-based normal numbers for Monte Carlo studies: Threefry-2x32 and Box–Muller.

A counter-based generator is a keyed hash of a counter: the number drawn for
``(key, stream, run, step)`` is a pure function of those four integers, so any run can be
regenerated alone, and the numbers do not depend on how the runs are cut into chunks,
spread over devices or over processes. Choice and statistical evidence: docs/DESIGN.md,
"Monte Carlo random numbers".

* **Block function**: Threefry-2x32 (Salmon, Moraes, Dror, Shaw, "Parallel random numbers:
  as easy as 1, 2, 3", SC 2011): additions, rotations and xors of ``uint32`` words, which
  XLA:CPU vectorises over the lanes. With 20 rounds it is bit-identical to the block
  function of ``jax.random`` (``jax.extend.random.threefry_2x32``; tested). The key is
  ``(key words of the stream)``, the counter ``(run, step)``.
* **Normals**: Box–Muller on two 24-bit uniforms, ``r = sqrt(-2 ln u1)``, ``(r cos 2πu2,
  r sin 2πu2)``; ``u1 ∈ (0, 1)`` (no log of 0: the largest radius is 5.9σ), and ``cos``/``sin``
  by a quadrant reduction of ``4 u2`` (exact in floating point) and short polynomials
  (``jnp.sin``/``jnp.cos`` are scalar calls on XLA:CPU).

All functions are pure ``jax.numpy`` and broadcast over the counter arrays.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

ROTATIONS = (13, 15, 26, 6, 17, 29, 16, 24)  # Threefry-2x32 (Random123)
PARITY = 0x1BD11BDA


def _rotl(x, r):
    return (x << jnp.uint32(r)) | (x >> jnp.uint32(32 - r))


def threefry2x32(k0, k1, c0, c1, rounds: int = 20, loop: bool = True):
    """The Threefry-2x32 block function: ``(k0, k1)`` key words, ``(c0, c1)`` counter words
    (``uint32`` arrays that broadcast), ``rounds`` a multiple of 4 (Random123's key injection
    after every 4 rounds). Returns two ``uint32`` arrays of the broadcast shape.

    ``loop=True`` (the CPU's route): the rounds run in a ``fori_loop`` of two rounds per
    iteration: the loop carry is in memory, so XLA:CPU, which has no multi-output fusion and
    would otherwise fuse (and recompute) the whole chain of integer operations into each
    consumer of either output word, computes each round once. ``loop=False`` (an
    accelerator's, :data:`jaximu.engine._dispatch.MONTE_CARLO`): the rounds are written out,
    one elementwise fusion; on a GPU each iteration of a loop is a launch and a copy of its
    predicate to the host, and inside a Monte Carlo step the rounds' loops were 15 of them
    a step. The words are the same either way (integer arithmetic; tested).
    """
    if rounds % 4:
        raise ValueError(f"rounds must be a multiple of 4, got {rounds}")
    k0, k1, c0, c1 = (jnp.asarray(x, jnp.uint32) for x in (k0, k1, c0, c1))
    shape = jnp.broadcast_shapes(k0.shape, k1.shape, c0.shape, c1.shape)
    k2 = k0 ^ k1 ^ jnp.uint32(PARITY)
    x0 = jnp.broadcast_to(c0 + k0, shape)
    x1 = jnp.broadcast_to(c1 + k1, shape)
    if not loop:
        kt = (k0, k1, k2)  # the key words as they are: no stacked array to index
        for r in range(rounds):
            x0 = x0 + x1
            x1 = _rotl(x1, ROTATIONS[r % 8]) ^ x0
            if r % 4 == 3:
                s = r // 4 + 1
                x0, x1 = x0 + kt[s % 3], x1 + kt[(s + 1) % 3] + jnp.uint32(s)
        return x0, x1
    ks = jnp.stack(jnp.broadcast_arrays(k0, k1, k2))
    rot = jnp.asarray(ROTATIONS, jnp.uint32)

    def two_rounds(i, x):
        x0, x1 = x
        for u in range(2):
            r = rot[(2 * i + u) % 8]
            x0 = x0 + x1
            x1 = ((x1 << r) | (x1 >> (jnp.uint32(32) - r))) ^ x0
        return x0, x1

    def group(s, x):  # four rounds, then the key injection s + 1
        x0, x1 = jax.lax.fori_loop(2 * s, 2 * s + 2, two_rounds, x)
        s1 = s + 1
        return x0 + ks[s1 % 3], x1 + ks[(s1 + 1) % 3] + s1.astype(jnp.uint32)

    return jax.lax.fori_loop(0, rounds // 4, group, (x0, x1))


_INV24 = 1.0 / (1 << 24)


def _sin_cos_quarter(r, dtype):
    """``sin r, cos r`` for ``|r| ≤ π/4`` (Taylor polynomials, below rounding there)."""
    n = 9 if jnp.dtype(dtype) == jnp.float64 else 5
    r2 = r * r
    s = c = 0.0
    for i in reversed(range(n)):
        s = s * r2 + (-1) ** i / math.factorial(2 * i + 1)
        c = c * r2 + (-1) ** i / math.factorial(2 * i)
    return r * s, c


def box_muller(b0, b1, dtype):
    """Two independent standard normals from two ``uint32`` words (arrays that broadcast)."""
    u1 = ((b0 >> jnp.uint32(8)).astype(dtype) + 0.5) * _INV24  # (0, 1)
    m = (b1 >> jnp.uint32(8)).astype(dtype) * (4.0 * _INV24)  # 4 u2 in [0, 4), exact
    k = jnp.floor(m + 0.5)  # quadrant 0..4 (4 is 0)
    s, c = _sin_cos_quarter((m - k) * (0.5 * math.pi), dtype)
    quad = k - 4.0 * jnp.floor(0.25 * k)
    odd = (quad == 1.0) | (quad == 3.0)
    sa, ca = jnp.where(odd, c, s), jnp.where(odd, s, c)
    sin = jnp.where(quad >= 2.0, -sa, sa)
    cos = jnp.where((quad == 1.0) | (quad == 2.0), -ca, ca)
    rad = jnp.sqrt(-2.0 * jnp.log(u1))
    return rad * cos, rad * sin


def stream_keys(key, n_streams: int):
    """``(n_streams, 2)`` ``uint32`` key words for streams ``0..n-1`` of a ``jax.random`` key
    (new-style or raw ``uint32[2]``): ``threefry(key, (0x4A4D4331, j))`` ("JMC1", stream j)."""
    data = key
    try:
        if jnp.issubdtype(
            jnp.asarray(key).dtype if not hasattr(key, "dtype") else key.dtype, jax.dtypes.prng_key
        ):
            data = jax.random.key_data(key)
        data = jnp.asarray(data, jnp.uint32).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(
            "key must be a threefry jax.random key (e.g. jax.random.key(0)), got "
            f"{type(key).__name__} {key!r:.40}"
        ) from None
    if data.shape != (2,):
        raise ValueError(
            "key must be a threefry jax.random key (two uint32 words), got key "
            f"data of shape {data.shape}"
        )
    return _stream_words(data, int(n_streams))


@functools.partial(jax.jit, static_argnums=1)
def _stream_words(data, n_streams):
    # compiled once: run op by op, the block function's loops are traced again at every call
    # (0.3 s of each Monte Carlo study; benchmarks/montecarlo.py)
    j = jnp.arange(n_streams, dtype=jnp.uint32)
    a, b = threefry2x32(data[0], data[1], jnp.uint32(0x4A4D4331), j)
    return jnp.stack([a, b], -1)


def normals(keys, run, step, n_pairs: int, dtype, rounds: int = 20, loop: bool = True):
    """``2 n_pairs`` standard normals for every ``(run, step)``: pair ``j`` comes from stream
    ``j`` (``keys[j]``, from :func:`stream_keys`) at counter ``(run, step)``.

    Args:
        keys: ``(≥ n_pairs, 2)`` uint32 stream keys.
        run, step: ``uint32`` arrays (broadcast; shape ``S``).

        loop: :func:`threefry2x32`'s.

    Returns:
        a list of ``2 n_pairs`` arrays of shape ``S``: pair j's two normals at ``2j, 2j+1``.
    """
    return normals_at(keys, run, [step] * n_pairs, dtype, rounds, loop=loop)


def normals_at(keys, run, steps, dtype, rounds: int = 20, stage=None, loop: bool = True):
    """Like :func:`normals` with one counter per pair: pair ``j`` from stream ``keys[j]`` at
    ``(run, steps[j])``. All pairs are hashed together, in one loop. ``stage``: applied to
    the two ``(n_pairs,) + S`` arrays of first and second normals before they are split
    (e.g. to materialise them). ``loop``: :func:`threefry2x32`'s."""
    run = jnp.asarray(run, jnp.uint32)
    steps = [jnp.asarray(s, jnp.uint32) for s in steps]
    n_pairs = len(steps)
    S = jnp.broadcast_shapes(run.shape, *(s.shape for s in steps))
    c1 = jnp.stack([jnp.broadcast_to(s, S) for s in steps])  # (n_pairs,) + S
    k = keys[:n_pairs].reshape((n_pairs, 2) + (1,) * len(S))
    b0, b1 = threefry2x32(k[:, 0], k[:, 1], run, c1, rounds, loop)
    z0, z1 = box_muller(b0, b1, dtype)
    if stage is not None:
        z0, z1 = stage((z0, z1))
    return [z[j] for j in range(n_pairs) for z in (z0, z1)]


def np_threefry2x32(k0, k1, c0, c1, rounds=20):
    """Plain-numpy transcription (for tests): uint64 arithmetic masked to 32 bits."""
    M = 0xFFFFFFFF
    k0, k1, c0, c1 = (np.asarray(x, np.uint64) for x in (k0, k1, c0, c1))
    ks = (k0, k1, (k0 ^ k1 ^ np.uint64(PARITY)) & M)
    x0, x1 = (c0 + ks[0]) & M, (c1 + ks[1]) & M
    for r in range(rounds):
        rot = ROTATIONS[r % 8]
        x0 = (x0 + x1) & M
        x1 = (((x1 << np.uint64(rot)) & M) | (x1 >> np.uint64(32 - rot))) ^ x0
        if r % 4 == 3:
            s = r // 4 + 1
            x0 = (x0 + ks[s % 3]) & M
            x1 = (x1 + ks[(s + 1) % 3] + np.uint64(s)) & M
    return x0.astype(np.uint32), x1.astype(np.uint32)
