"""The covariance of a few long sequences in time chunks (jaximu/engine/_chunked.py) against the
sequential structure-of-arrays scan over the same samples (itself tested against the generic
kernels and finite differences elsewhere): every scheme, both Jacobian options, a sensor at a
lever arm in a still and in a turning world, float64 and float32, the final covariance and
every one stored; chunk boundaries anywhere; gradients; the dispatch."""

import contextlib
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _shared import dispatch_as, random_inputs

import jaximu
from jaximu.engine import _dispatch

NOISE = jaximu.ImuNoise.euroc()
P0 = jnp.diag(jnp.asarray(np.r_[[3e-4] * 3, [1e-2] * 3, [1e-2] * 3, [1e-6] * 3, [1e-4] * 3]))
POSE = jaximu.SensorPose.from_rotation(
    np.asarray(jaximu.so3.exp_matrix(jnp.asarray([0.3, -0.5, 0.4]))), np.array([0.3, -0.2, 0.15])
)
OMEGA = np.asarray(jaximu.earth_rate(48.0)) * 100  # a fast turn, that the maps matter


@contextlib.contextmanager
def table(chunked_from=None, chunks=None):
    """The dispatch with the chunked rows from ``chunked_from`` steps (``None``: without
    them, the sequential kernels), ``chunks`` time chunks per sequence when given."""
    saved, saved_chunks = _dispatch.TABLE, _dispatch.covariance_chunks
    rows = []
    for r in saved:
        if r.kernel == "soa_cov_chunked":
            if chunked_from is None:
                continue
            r = r._replace(min_steps=chunked_from)
        rows.append(r)
    _dispatch.TABLE = tuple(rows)
    if chunks is not None:
        _dispatch.covariance_chunks = lambda lanes, steps, dtype: chunks(steps)
    jax.clear_caches()
    try:
        yield
    finally:
        _dispatch.TABLE, _dispatch.covariance_chunks = saved, saved_chunks
        jax.clear_caches()


def sequence(T, seed=3, dtype=np.float64, rate=1.0):
    state, gyro, accel = random_inputs(1, T, seed=seed)
    state = jax.tree_util.tree_map(lambda x: jnp.asarray(x[0], dtype), state)
    dt = np.random.default_rng(seed + 1).uniform(0.003, 0.007, T)
    return (
        state,
        jnp.asarray(gyro[0] * rate, dtype),
        jnp.asarray(accel[0], dtype),
        jnp.asarray(dt, dtype),
    )


def covariances(scheme, jacobians, attitude="quaternion", rotating=False, outputs="final+stored"):
    """Final and/or stored covariance (one jitted function) of one sequence (or, under
    ``jax.vmap``, a few), from a sensor at a lever arm, in a still or a turning world."""
    kw = {
        "jacobians": jacobians,
        "attitude": attitude,
        "body_P_sensor": POSE,
        "omega_coriolis": OMEGA if rotating else None,
    }

    def run(state, gyro, accel, dt):
        P = jnp.asarray(P0, gyro.dtype)
        fns = {"final": jaximu.propagate_covariance_final, "stored": jaximu.propagate_covariance}
        return [fns[o](state, P, gyro, accel, dt, NOISE, scheme, **kw) for o in outputs.split("+")]

    return jax.jit(run)


def assert_close(a, b, rtol):
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        assert x.shape == y.shape
        np.testing.assert_allclose(x, y, rtol=0, atol=rtol * np.abs(y).max())


# every scheme with both Jacobian options, each from a sensor at a lever arm; a still world
# (the chunks from the identity, turned into their start's frame: the world-frame rotation
# error of the quaternion forms' final covariance, the body frame otherwise) and a turning
# one (the chunks from the mean's own states, as Euler angles always); the final covariance
# and every one stored; the chunks cut anywhere: 100 steps as 7 chunks of 15 (5 padding
# steps), as one chunk, as chunks of one step (each reading the next chunk's first sample).
# The world's maps and the second pass of the stored covariances are the same code for every
# scheme, so not every scheme runs every world and output (the compile time of the suite).
CASES = [
    ("euler", "analytic", "quaternion", False, 7, "final+stored"),
    ("midpoint", "analytic", "matrix", True, 100, "stored"),
    ("rk4", "analytic", "quaternion", False, 1, "final"),
    ("euler", "autodiff", "euler_angles", True, 4, "final"),
    ("midpoint", "autodiff", "quaternion_first_order", False, 7, "stored"),
    ("rk4", "autodiff", "quaternion", False, 3, "final"),
]


@functools.lru_cache
def sequential(case, dtype=np.float64):
    """The sequential scan's results for a case of :data:`CASES`."""
    scheme, jacobians, attitude, rotating, _, outputs = case
    with table():
        return covariances(scheme, jacobians, attitude, rotating, outputs)(
            *case_inputs(case, dtype)
        )


def case_inputs(case, dtype=np.float64):
    return sequence(
        100, seed=len(case[2]), dtype=dtype, rate=0.3 if case[2] == "euler_angles" else 1.0
    )


@pytest.mark.parametrize("case", CASES, ids=lambda c: "-".join(map(str, c)))
def test_chunks_equal_the_sequential_scan(case):
    """Final state and covariance, and every one stored, of 100 float64 steps (per-sample
    dt) from a sensor at a lever arm, in time chunks: the sequential scan's to 1e-12 of each
    output's largest value."""
    scheme, jacobians, attitude, rotating, chunks, outputs = case
    with table(chunked_from=1, chunks=lambda n: chunks):
        assert (
            _dispatch.kernel(
                "covariance",
                scheme,
                attitude=attitude,
                jacobians=jacobians,
                lanes=1,
                steps=100,
                rotating=rotating,
                lever=True,
            )
            == "soa_cov_chunked"
        )
        chunked = covariances(scheme, jacobians, attitude, rotating, outputs)(*case_inputs(case))
    assert_close(chunked, sequential(case), 1e-12)


def test_float32_chunks_are_as_close_to_float64_as_the_sequential_scan():
    """float32 (the first case of :data:`CASES`): the chunked results differ from the
    float64 scan's by no more than 3× what the float32 sequential scan's do (or 10 ε of the
    largest value): the composition adds no error of its own beyond rounding."""
    case = CASES[0]
    scheme, jacobians, attitude, rotating, chunks, outputs = case
    args = case_inputs(case, np.float32)
    with table(chunked_from=1, chunks=lambda n: chunks):
        chunked = covariances(scheme, jacobians, attitude, rotating, outputs)(*args)
    for c, s, r in zip(
        *(
            jax.tree_util.tree_leaves(x)
            for x in (chunked, sequential(case, np.float32), sequential(case))
        )
    ):
        assert c.dtype == jnp.float32
        c, s, r = (np.asarray(x, np.float64) for x in (c, s, r))
        scale = np.abs(r).max()
        err_c, err_s = np.abs(c - r).max() / scale, np.abs(s - r).max() / scale
        assert err_c <= max(3 * err_s, 10 * np.finfo(np.float32).eps), (err_c, err_s)


def test_gradient_through_the_chunks_equals_the_sequential_scan():
    """``jax.grad`` of a loss on the final state and covariance (closed-form blocks, a still
    world, 64 steps as 4 chunks: the chunks' kernel, their deltas and the composition) with
    respect to the gyro's scale and the noise density: the sequential scan's to 1e-9."""
    state, gyro, accel, dt = sequence(64, seed=11)
    w = jnp.asarray(np.random.default_rng(12).normal(size=(15, 15)))

    def loss(scale, sigma):
        noise = dataclasses.replace(NOISE, gyroscope_noise_density=sigma)
        s, P = jaximu.propagate_covariance_final(state, P0, gyro * scale, accel, dt, noise)
        return jnp.sum(P * w) * 1e3 + jnp.sum(s.p * w[0, :3]) + jnp.sum(s.q * w[1, :4])

    x = (1.1, 2e-3)
    with table(chunked_from=1, chunks=lambda n: 4):
        chunked = jax.jit(jax.grad(loss, argnums=(0, 1)))(*x)
    with table():
        ref = jax.jit(jax.grad(loss, argnums=(0, 1)))(*x)
    np.testing.assert_allclose(chunked, ref, rtol=1e-9)


def test_dispatch_picks_the_chunks_for_a_few_long_sequences():
    """The table's chunked rows take one long sequence (and a few) on both backends, not a
    short one nor a batch that fills the lanes itself. ``jax.vmap`` of two sequences reaches
    the chunks (as a batch of two: 3 chunks each), on both backends. On an accelerator (run
    here on the CPU: tests/_shared.dispatch_as) the table's own threshold, a short sequence,
    runs as the chunks its lanes take (8 of 32 steps), composed by a parallel prefix scan,
    the final covariance and every one stored. Both: the sequential scan's results to 1e-12."""

    def kernel(on, lanes, steps, jac="analytic", attitude="quaternion"):
        return _dispatch.kernel(
            "covariance", "euler", attitude=attitude, jacobians=jac, lanes=lanes, steps=steps, on=on
        )

    for on in (_dispatch.CPU, _dispatch.ACCELERATOR):
        long, most = _dispatch.COV_CHUNK_STEPS[on], _dispatch.COV_CHUNK_LANES[on]
        assert kernel(on, 1, long) == "soa_cov_chunked"
        assert kernel(on, most, long, "autodiff", "euler_angles") == "soa_cov_chunked"
        assert kernel(on, 1, long - 1) == "soa_cov_analytic"
        assert kernel(on, most + 1, long) == "soa_cov_analytic"

    def run(state, gyro, accel, dt):
        return jax.vmap(
            lambda s, g, a, d: jaximu.propagate_covariance_final(s, P0, g, a, d, NOISE)
        )(state, gyro, accel, dt)

    pair = [sequence(100, seed=s) for s in (21, 22)]
    args = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *pair)
    with table(chunked_from=1):
        assert _dispatch.covariance_chunks(2, 100, "float64") == 3
        chunked = jax.jit(run)(*args)
    with table():
        ref = jax.jit(run)(*args)
    assert_close(chunked, ref, 1e-12)
    # the same pair on an accelerator, whose chunks the batch leaves room for
    with dispatch_as(_dispatch.ACCELERATOR), table(chunked_from=1):
        assert _dispatch.covariance_chunks(2, 100, "float64") == 3
        chunked = jax.jit(run)(*args)
    assert_close(chunked, ref, 1e-12)

    scheme, jacobians, attitude, rotating, _, outputs = CASES[0]
    n = _dispatch.COV_CHUNK_STEPS[_dispatch.ACCELERATOR]
    args = sequence(n, seed=23)
    with dispatch_as(_dispatch.ACCELERATOR):
        assert (
            _dispatch.kernel(
                "covariance",
                scheme,
                attitude=attitude,
                jacobians=jacobians,
                lanes=1,
                steps=n,
                lever=True,
            )
            == "soa_cov_chunked"
        )
        assert _dispatch.covariance_chunks(1, n, "float64") == n // _dispatch.MIN_CHUNK_STEPS
        chunked = covariances(scheme, jacobians, attitude, rotating, outputs)(*args)
    with table():
        ref = covariances(scheme, jacobians, attitude, rotating, outputs)(*args)
    assert_close(chunked, ref, 1e-12)
