"""The structure-of-arrays fast path (jaximu/kernels/fast.py: Euler, exact quaternion exponential,
batched mean; analytic final covariance) against the generic kernels it replaces."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _shared import dispatch_as
from _shared import random_inputs as inputs

import jaximu
from jaximu.engine import _dispatch
from jaximu.engine.errorstate import _propagate_covariance
from jaximu.engine.propagate import _propagate
from jaximu.kernels import lane_math
from jaximu.kernels import soa as _soa

G_W = jnp.array([0.0, 0.0, -9.81])


@functools.partial(jax.jit, static_argnames=("save_all", "fast", "scheme"))
def mean(state, gyro, accel, dt, g, *, save_all, fast, scheme="euler"):
    return _propagate(
        state,
        gyro,
        accel,
        dt,
        g,
        scheme=scheme,
        attitude="quaternion",
        save_all=save_all,
        fast=fast,
    )[0]


@pytest.mark.parametrize(
    "B,T,big,per_lane_dt,scheme",
    [
        (64, 97, False, False, "euler"),
        (40, 50, True, True, "euler"),
        (2100, 40, False, False, "euler"),
        (40, 50, True, True, "midpoint"),
        (64, 97, False, False, "rk4"),
        (40, 50, True, True, "rk4"),
    ],
)
@pytest.mark.parametrize("save_all", [False, True])
def test_mean_fast_path_equals_generic(B, T, big, per_lane_dt, scheme, save_all):
    assert B >= _dispatch.TABLE[0].min_lanes
    state, gyro, accel = inputs(B, T, big_angles=big)
    rng = np.random.default_rng(1)
    dt = jnp.asarray(rng.uniform(0.002, 0.02, size=(B, T) if per_lane_dt else (T,)))
    g = jnp.asarray(np.tile(G_W, (B, 1)) + 0.01 * rng.normal(size=(B, 3))) if big else G_W
    fast = mean(state, gyro, accel, dt, g, save_all=save_all, fast=True, scheme=scheme)
    ref = mean(state, gyro, accel, dt, g, save_all=save_all, fast=False, scheme=scheme)
    for a, b in zip(jax.tree_util.tree_leaves(fast), jax.tree_util.tree_leaves(ref)):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(1.0, np.abs(b).max()))


def test_mean_fast_path_float32_and_batch_shapes():
    state, gyro, accel = inputs(48, 30, dtype=np.float32)
    state = jax.tree_util.tree_map(lambda x: x.reshape((6, 8) + x.shape[1:]), state)
    gyro, accel = gyro.reshape(6, 8, 30, 3), accel.reshape(6, 8, 30, 3)
    dt = jnp.full(30, 0.01, jnp.float32)
    fast = mean(state, gyro, accel, dt, G_W.astype(jnp.float32), save_all=True, fast=True)
    ref = mean(state, gyro, accel, dt, G_W.astype(jnp.float32), save_all=True, fast=False)
    assert fast.p.shape == (6, 8, 30, 3) and fast.p.dtype == jnp.float32
    np.testing.assert_allclose(fast.p, ref.p, rtol=0, atol=2e-5)
    np.testing.assert_allclose(fast.q, ref.q, rtol=0, atol=2e-6)


@functools.partial(jax.jit, static_argnames=("fast",))
def cov(state, P0, gyro, accel, dt, g, noise, *, fast):
    states, P, _ = _propagate_covariance(
        state,
        P0,
        gyro,
        accel,
        dt,
        g,
        noise,
        scheme="euler",
        attitude="quaternion",
        jacobians="analytic",
        save_all=False,
        fast=fast,
    )
    return states, P


@pytest.mark.parametrize(
    "B,T,big,batched_noise", [(1, 60, False, False), (33, 41, True, True), (5, 200, False, True)]
)
def test_covariance_fast_path_equals_generic(B, T, big, batched_noise):
    state, gyro, accel = inputs(B, T, seed=3, big_angles=big)
    rng = np.random.default_rng(4)
    A = rng.normal(size=(B, 15, 15)) * 0.02
    P0 = jnp.asarray(A @ np.swapaxes(A, -1, -2) + 1e-6 * np.eye(15))
    dt = jnp.asarray(rng.uniform(0.002, 0.02, size=(B, T)))
    noise = jaximu.ImuNoise.euroc()
    if batched_noise:
        noise = jaximu.ImuNoise(
            jnp.asarray(rng.uniform(1e-4, 1e-3, size=(B, 3))),
            2e-3,
            jnp.asarray(rng.uniform(1e-5, 1e-4, size=(B, 1)) * np.ones(3)),
            3e-3,
        )
    s1, P1 = cov(state, P0, gyro, accel, dt, G_W, noise, fast=True)
    s2, P2 = cov(state, P0, gyro, accel, dt, G_W, noise, fast=False)
    np.testing.assert_allclose(P1, P2, rtol=0, atol=1e-12 * np.abs(P2).max())
    np.testing.assert_allclose(s1.p, s2.p, rtol=0, atol=1e-11 * max(1, np.abs(s2.p).max()))


def test_fast_path_gradients_equal_generic_ones_at_zero_rate():
    state, _, accel = inputs(32, 20, seed=5)
    gyro = jnp.zeros_like(accel)
    dt = jnp.full(20, 0.01)

    def loss(gyro, accel, b_g, fast):
        s = mean(state.replace(b_g=b_g), gyro, accel, dt, G_W, save_all=False, fast=fast)
        return jnp.sum(s.p**2) + jnp.sum(s.q[..., 1:] * 3.0)

    grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2)), static_argnums=3)  # one program each
    g_fast = grad(gyro, accel, state.b_g * 0, True)
    g_ref = grad(gyro, accel, state.b_g * 0, False)
    for a, b in zip(g_fast, g_ref):
        assert np.all(np.isfinite(np.asarray(a)))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-10 * max(1, np.abs(b).max()))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_half_angle_kernels_match_trig(dtype):
    """The polynomial / range-reduced half-angle pair equals cos(θ/2), sin(θ/2)/θ from numpy,
    from 0 to 200 rad (rounding-level: 4 ulp-scaled)."""
    theta = np.r_[0.0, 1e-8, 1e-3, np.linspace(0.01, 3.2, 400), np.linspace(3.2, 200.0, 400)]
    t2 = jnp.asarray(theta**2, dtype)
    theta = np.sqrt(np.asarray(t2, np.float64))  # the angle the kernel actually sees
    c, k = jax.jit(lane_math._half_any)(t2)
    safe = np.where(theta > 0, theta, 1.0)
    k_ref = np.where(theta > 0, np.sin(theta / 2) / safe, 0.5)
    eps = np.finfo(dtype).eps
    # cos(θ/2) is only as good as θ/2 itself for large angles: tolerance 8 eps max(1, θ).
    assert np.all(
        np.abs(np.asarray(c, np.float64) - np.cos(theta / 2)) <= 8 * eps * np.maximum(1, theta)
    )
    np.testing.assert_allclose(k, k_ref, rtol=0, atol=8 * eps)
    small = theta**2 < lane_math._THR
    cs, ks = jax.jit(lane_math._half_small)(t2[small])
    np.testing.assert_allclose(cs, np.cos(theta[small] / 2), rtol=0, atol=4 * eps)
    np.testing.assert_allclose(ks, k_ref[small], rtol=0, atol=4 * eps)


@pytest.mark.parametrize(
    "B,T,scheme,save_all,intervals,backend",
    [
        # the accelerator's time chunks: the final state's deltas reduced as a tree, every state
        # from a prefix scan of them; 2049 steps as 64 chunks of 33 (63 padding steps, dt = 0)
        (1, 2080, "midpoint", False, False, "accelerator"),
        (1, 2051, "euler", True, False, "accelerator"),
        (2, 2050, "rk4", True, True, "accelerator"),
        (2, 2050, "rk4", False, True, "accelerator"),
        # 132 chunks of 33 steps: the last three all padding
        (1, 4229, "rk4", True, True, "accelerator"),
        # the CPU: the one-block kernel over the long sequence (no chunks on the CPU)
        (1, 2051, "euler", False, False, "cpu"),
        (1, 2051, "euler", True, False, "cpu"),
        (2, 2050, "rk4", True, True, "cpu"),
    ],
)
def test_long_sequences_equal_the_plain_scan(B, T, scheme, save_all, intervals, backend):
    """A few long float64 sequences on an accelerator run as time chunks side by side
    (deltas from the identity, composed as a tree; every state stored runs the chunks again
    from the starts a parallel prefix scan of their deltas gives); on the CPU on the
    one-block kernel. Each: the plain generic scan's states to rounding, for every scheme,
    with per-sample dt and with dt of length T-1 (samples at the ends of the intervals).
    The accelerator's dispatch runs here on the CPU (tests/_shared.dispatch_as)."""
    state, gyro, accel = inputs(B, T, seed=8)
    rng = np.random.default_rng(9)
    dt = jnp.asarray(rng.uniform(0.002, 0.008, size=(T - 1,) if intervals else (T,)))
    steps = dt.shape[-1]
    with dispatch_as(backend):
        assert _dispatch.kernel(
            "mean",
            scheme,
            attitude="quaternion",
            save_all=save_all,
            lanes=B,
            steps=steps,
            on=backend,
        ) == ("soa_mean_chunked" if backend == _dispatch.ACCELERATOR else "soa_mean")
        fast = mean(state, gyro, accel, dt, G_W, save_all=save_all, fast=True, scheme=scheme)
    ref = mean(state, gyro, accel, dt, G_W, save_all=save_all, fast=False, scheme=scheme)
    for a, b in zip(jax.tree_util.tree_leaves(fast), jax.tree_util.tree_leaves(ref)):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(1.0, np.abs(b).max()))


def test_whole_chunks_are_cut_without_a_remainder():
    """A chunk length from ``soa.whole_chunks`` is the shortest at least as long that the
    kernel's time chunks divide (no second loop body to compile)."""
    for L in range(1, 3000):
        W = _soa.whole_chunks(L)
        assert W >= L and W % _soa._chunk_size(W) == 0
        assert all(x % _soa._chunk_size(x) for x in range(L, W))


@pytest.mark.parametrize("save_all", [False, True])
def test_long_sequence_gradient_equals_generic(save_all):
    """The gradient through the chunked path (an accelerator's, run here on the CPU) equals
    the generic scan's, for a loss on the states of one float64 sequence of 2100 steps: the
    final state (the chunk deltas reduced as a tree) and every state (two kernel passes and
    the parallel prefix of the chunk deltas)."""
    state, gyro, accel = inputs(1, 2100, seed=13)
    dt = jnp.full((2100,), 0.005)
    w = jnp.asarray(np.random.default_rng(14).normal(size=(2100, 3)))

    def loss(scale, fast):
        s = mean(
            state, gyro * scale, accel, dt, G_W, save_all=save_all, fast=fast, scheme="midpoint"
        )
        if not save_all:
            return jnp.sum(s.p[0] * w[0]) + jnp.sum(s.q[0] * w[1, :1])
        return jnp.sum(s.p[0] * w) * 1e-3 + jnp.sum(s.q[0] * w[:, :1])

    # traced under the dispatch it is called in: one program for each
    grad = jax.jit(jax.grad(loss), static_argnums=1)
    with dispatch_as("accelerator"):
        assert (
            _dispatch.kernel(
                "mean", "midpoint", attitude="quaternion", save_all=save_all, lanes=1, steps=2100
            )
            == "soa_mean_chunked"
        )
        fast = grad(1.1, True)
    np.testing.assert_allclose(fast, grad(1.1, False), rtol=1e-10)


def test_long_float32_sequence_in_time_chunks_on_an_accelerator():
    """On an accelerator a long float32 sequence runs as time chunks too (there a sequential
    step costs a launch): its states, every one stored, are the float64 scan's to float32
    rounding over 2051 steps (2e-4 of the largest value; the plain float32 scan is off by
    ~1e-5 here)."""
    save_all = True
    state, gyro, accel = inputs(1, 2051, seed=12)
    dt = jnp.full((2051,), 0.005)

    def f32(x):
        return jax.tree_util.tree_map(lambda y: jnp.asarray(y, jnp.float32), x)

    assert (
        _dispatch.kernel(
            "mean",
            "midpoint",
            attitude="quaternion",
            save_all=save_all,
            lanes=1,
            steps=2051,
            dtype="float32",
            on=_dispatch.ACCELERATOR,
        )
        == "soa_mean_chunked"
    )
    with dispatch_as(_dispatch.ACCELERATOR):
        fast = mean(
            *f32((state, gyro, accel, dt, G_W)), save_all=save_all, fast=True, scheme="midpoint"
        )
    ref = mean(state, gyro, accel, dt, G_W, save_all=save_all, fast=False, scheme="midpoint")
    for a, b in zip(jax.tree_util.tree_leaves(fast), jax.tree_util.tree_leaves(ref)):
        assert a.dtype == jnp.float32 and a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=2e-4 * max(1.0, np.abs(b).max()))


@pytest.mark.parametrize(
    "scheme,B,intervals,jac,save_all,backend",
    [
        ("euler", 3, False, "autodiff", True, "cpu"),
        ("midpoint", 2, True, "autodiff", True, "cpu"),
        ("rk4", 2, False, "autodiff", False, "cpu"),
        ("midpoint", 3, False, "analytic", False, "cpu"),
        ("rk4", 2, True, "analytic", True, "cpu"),
        ("midpoint", 2, True, "autodiff", False, "accelerator"),
        ("rk4", 3, False, "analytic", True, "accelerator"),
    ],
)
def test_soa_covariance_kernels_equal_generic_closed_forms(
    scheme, B, intervals, jac, save_all, backend
):
    """soa_cov_autodiff (blocks by jax.linearize of the SoA step, 9 directions) and
    soa_cov_analytic (Scheme.blocks on the SoA layout) against the generic kernel with the
    closed-form blocks on arrays: same mean and covariance to rounding, final or after every
    step (``save_all``); as the accelerator runs them too (one block, no stage conditionals,
    the range-reduced half angle on every lane: tests/_shared.dispatch_as)."""
    T = 25
    state, gyro, accel = inputs(B, T, seed=10, big_angles=True)
    rng = np.random.default_rng(11)
    A = rng.normal(size=(15, 15)) * 0.02
    P0 = jnp.asarray(A @ A.T + 1e-6 * np.eye(15))
    dt = jnp.asarray(rng.uniform(0.002, 0.02, size=(B, T - 1 if intervals else T)))
    noise = jaximu.ImuNoise(jnp.asarray([1e-3, 2e-3, 3e-3]), 2e-3, 1e-4, 3e-3)

    def run(jac, fast):
        return jax.jit(
            lambda s, P, w, a, h: _propagate_covariance(
                s,
                P,
                w,
                a,
                h,
                G_W,
                noise,
                scheme=scheme,
                attitude="quaternion",
                jacobians=jac,
                save_all=save_all,
                fast=fast,
            )[:2]
        )(state, P0, gyro, accel, dt)

    assert (
        _dispatch.kernel(
            "covariance",
            scheme,
            attitude="quaternion",
            jacobians=jac,
            save_all=save_all,
            lanes=B,
            on=backend,
        )
        == f"soa_cov_{jac}"
    )
    with dispatch_as(backend):
        s1, P1 = run(jac, True)
    s2, P2 = run("analytic", False)
    assert P1.shape == P2.shape == (B,) + (dt.shape[-1:] if save_all else ()) + (15, 15)
    np.testing.assert_allclose(P1, P2, rtol=0, atol=1e-12 * np.abs(P2).max())
    if scheme == "euler":  # float32 in, float32 out, close to float64
        f32 = lambda x: jax.tree_util.tree_map(lambda y: jnp.asarray(y, jnp.float32), x)  # noqa: E731
        s3, P3 = jax.jit(
            lambda s, P, w, a, h: _propagate_covariance(
                s,
                P,
                w,
                a,
                h,
                G_W.astype(jnp.float32),
                f32(noise),
                scheme=scheme,
                attitude="quaternion",
                jacobians="autodiff",
                save_all=save_all,
                fast=True,
            )[:2]
        )(*f32((state, P0, gyro, accel, dt)))
        assert P3.dtype == jnp.float32 and s3.q.dtype == jnp.float32
        np.testing.assert_allclose(P3, P2, rtol=0, atol=1e-4 * np.abs(P2).max())
    for a, b in zip(jax.tree_util.tree_leaves(s1), jax.tree_util.tree_leaves(s2)):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(1, np.abs(b).max()))
