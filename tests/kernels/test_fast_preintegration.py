"""The structure-of-arrays preintegration fast path (jaximu/kernels/fast_preint.py: Euler and
VINS-Mono's midpoint, analytic Jacobians, final i→j only) against the generic recursion it
replaces."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu.engine import _dispatch
from jaximu.engine.preintegration import _preintegrate
from jaximu.kernels import fast_preint as _fast_preint
from jaximu.kernels.soa import block_lanes


def uses_fast_path(
    scheme, jacobians, prefixes, method="sequential", lanes=1024, fast=True, lever=False
):
    return (
        _dispatch.preintegrate_kernel(
            scheme,
            jacobians=jacobians,
            prefixes=prefixes,
            method=method,
            lanes=lanes,
            fast=fast,
            lever=lever,
        )
        != "generic"
    )


FIELDS = ("delta_t", "delta_q", "delta_v", "delta_p", "transition", "cov15", "cov")


def inputs(
    batch,
    T,
    seed=0,
    per_lane_dt=False,
    big=False,
    batched_bias=False,
    batched_noise=False,
    intervals=False,
    dtype=np.float64,
):
    rng = np.random.default_rng(seed)
    g = rng.normal(size=batch + (T, 3)) * 0.8
    if big:  # some steps turn by more than π/2: the range-reduced half angle
        g[..., ::7, :] *= 300.0
    a = rng.normal(size=batch + (T, 3)) * 2 + [0, 0, 9.81]
    n = T - 1 if intervals else T
    dt = rng.uniform(0.002, 0.02, size=batch + (n,) if per_lane_dt else (n,))
    bias = jaximu.ImuBias(
        jnp.asarray(rng.normal(size=batch + (3,) if batched_bias else (3,)) * 0.01, dtype),
        jnp.asarray(rng.normal(size=(3,)) * 0.1, dtype),
    )
    sg = jnp.asarray(rng.uniform(1e-4, 3e-4, size=batch + (3,) if batched_noise else (3,)), dtype)
    noise = jaximu.ImuNoise(sg, 2e-3, 2e-5, jnp.asarray([3e-3, 2e-3, 1e-3], dtype))
    return (jnp.asarray(g, dtype), jnp.asarray(a, dtype), jnp.asarray(dt, dtype), bias, noise)


def pre(
    gyro, accel, dt, bias, noise, lever=None, *, method, fast, scheme="euler", jacobians="analytic"
):
    """The engine's preintegration, every argument passed the same way whichever way a test
    spells it (a static argument given by keyword and the same one left at its default are
    two keys of the jit cache: the one program would be compiled twice)."""
    return _pre(
        gyro,
        accel,
        dt,
        bias,
        noise,
        lever,
        method=method,
        fast=fast,
        scheme=scheme,
        jacobians=jacobians,
    )


@functools.partial(jax.jit, static_argnames=("method", "fast", "scheme", "jacobians"))
def _pre(gyro, accel, dt, bias, noise, lever, *, method, fast, scheme, jacobians):
    return _preintegrate(
        gyro,
        accel,
        dt,
        bias,
        noise,
        lever,
        scheme=scheme,
        method=method,
        jacobians=jacobians,
        prefixes=False,
        fast=fast,
    )


def assert_same(fast, ref, rel):
    for name in FIELDS:
        a, b = np.asarray(getattr(fast, name)), np.asarray(getattr(ref, name))
        assert a.shape == b.shape and a.dtype == b.dtype, name
        assert np.all(np.isfinite(a)), name
        np.testing.assert_allclose(
            a, b, rtol=0, atol=rel * max(np.abs(b).max(), 1e-300), err_msg=name
        )


def test_dispatch():
    f64 = jnp.float64
    assert uses_fast_path("euler", "analytic", False, "sequential", 8)
    assert uses_fast_path("euler", "analytic", False, "parallel", 1)
    assert uses_fast_path("euler", "analytic", False, "sequential", 1)
    assert not uses_fast_path("euler", "analytic", True)
    assert uses_fast_path("euler", "autodiff", False)
    assert uses_fast_path("euler", "autodiff", False, "parallel", 1, lever=True)
    assert not uses_fast_path("euler", "analytic", False, fast=False)
    assert uses_fast_path("midpoint", "analytic", False, "sequential", 8)
    assert uses_fast_path("midpoint", "analytic", False, "parallel", 1, f64)
    assert uses_fast_path("midpoint", "autodiff", False, "parallel", 4096, f64)
    f64 = jnp.float64
    assert _fast_preint.num_chunks(4096, 200, "parallel", f64) == 1
    assert _fast_preint.num_chunks(1, 100000, "sequential", f64) == 1
    C = _fast_preint.num_chunks(1, 100000, "parallel", f64)
    lanes = block_lanes(f64)  # one batch block of chunks: a divisor of T close to it, or all
    assert C == lanes or (lanes - lanes // 16 <= C < lanes and 100000 % C == 0)


@pytest.mark.parametrize(
    "batch,T,method,kw",
    [
        ((5,), 60, "sequential", {}),
        ((5,), 60, "parallel", {}),
        ((), 300, "parallel", {}),
        ((), 301, "parallel", {"big": True}),  # padded last chunk, big angles
        (
            (3, 2),
            100,
            "sequential",
            {"per_lane_dt": True, "batched_bias": True, "batched_noise": True},
        ),
        (
            (2,),
            400,
            "parallel",
            {"per_lane_dt": True, "batched_bias": True, "batched_noise": True, "intervals": True},
        ),
        # 64 chunks of 67 steps padded to 68 (whole kernel time chunks): the last one all padding
        ((), 4229, "parallel", {"per_lane_dt": True}),
        ((1100,), 40, "sequential", {"big": True}),  # several batch blocks
        ((4,), 80, "sequential", {}),  # a few windows: one block of 4 lanes
    ],
)
def test_fast_path_equals_generic(batch, T, method, kw):
    """The reference is the generic sequential scan (quick to compile; the generic parallel
    method equals it to rounding, tests/engine/test_preintegration.py), once the generic parallel."""
    args = inputs(batch, T, **kw)
    ref_method = "parallel" if (batch, T) == ((), 300) else "sequential"
    assert_same(
        pre(*args, method=method, fast=True), pre(*args, method=ref_method, fast=False), 1e-12
    )


@pytest.mark.parametrize(
    "scheme,batch,T,method,per_lane",
    [("midpoint", (8,), 60, "sequential", True), ("euler", (2,), 150, "parallel", True)],
)
def test_fast_path_with_a_lever_arm_equals_generic(scheme, batch, T, method, per_lane):
    """Samples of a sensor at a lever arm (its specific force moves with the gyro bias and
    noise: jaximu/geometry/sensor.py): the SoA kernels' extra terms equal the generic recursion's
    (Scheme.blocks / VINS-Mono's step with the lever arm), one lever arm per window or one
    for all, on fast-turning samples (|ω| ~ 1.4 rad/s) where the coupling is large."""
    g, a, dt, bias, _ = inputs(batch, T, seed=5)
    noise = jaximu.ImuNoise(2e-2, 2e-3, 2e-5, 3e-3)
    rng = np.random.default_rng(6)
    lever = jnp.asarray(rng.normal(size=batch + (3,) if per_lane else (3,)) * 0.3)
    assert uses_fast_path(scheme, "analytic", False, method, int(np.prod(batch)), lever=True)
    fast = pre(g, a, dt, bias, noise, lever, method=method, fast=True, scheme=scheme)
    assert_same(
        fast,
        pre(g, a, dt, bias, noise, lever, method="sequential", fast=False, scheme=scheme),
        1e-12,
    )
    plain = pre(g, a, dt, bias, noise, None, method="sequential", fast=False, scheme=scheme)
    assert np.abs(np.asarray(fast.cov - plain.cov)).max() > 1e-3 * np.abs(plain.cov).max()


@pytest.mark.parametrize("method", ["sequential", "parallel"])
def test_fast_path_float32(method):
    args = inputs((), 1000, seed=2, dtype=np.float32)
    assert_same(
        pre(*args, method=method, fast=True), pre(*args, method="sequential", fast=False), 3e-5
    )


def test_fast_path_without_noise_and_scalar_dt():
    g, a, _, bias, _ = inputs((4,), 50, seed=3)
    dt = jnp.asarray(0.005)
    for method in ("sequential", "parallel"):
        assert_same(
            pre(g, a, dt, bias, None, method=method, fast=True),
            pre(g, a, dt, bias, None, method="sequential", fast=False),
            1e-12,
        )


@pytest.mark.parametrize("scheme", ["euler", "midpoint"])
def test_fast_path_gradients_equal_generic(scheme):
    g, a, dt, bias, _ = inputs((8,), 64, seed=4)

    def loss(g, a, bg, sigma, fast, method):
        pim = pre(
            g,
            a,
            dt,
            jaximu.ImuBias(bg, bias.b_a),
            jaximu.ImuNoise(sigma, 2e-3, 2e-5, 3e-3),
            method=method,
            fast=fast,
            scheme=scheme,
        )
        return (
            jnp.sum(pim.delta_p * jnp.array([1.0, -2, 0.5]))
            + jnp.sum(pim.delta_q)
            + 1e6 * jnp.sum(jnp.trace(pim.cov, axis1=-2, axis2=-1))
            + 1e3 * jnp.sum(pim.cov15[..., 9:15, 0:9])
            + jnp.sum(pim.transition[..., 0:9, 9:15])
        )

    args = (g, a, bias.b_g, jnp.asarray(1.7e-4))
    # One compiled gradient per path (far cheaper than op-by-op reverse mode here); each
    # fast-path gradient takes ~30-40 s to trace and compile, so one fast method per scheme.
    # Euler: the parallel method, whose chunks run the sequential method's per-lane
    # recursion (preintegrate_euler's `block`, on B·C lanes of T/C steps instead of B lanes
    # of T) and then compose the chunk summaries: its gradient covers both. Midpoint: the
    # sequential method (its parallel one is checked for values above).
    method = "parallel" if scheme == "euler" else "sequential"
    if method == "parallel":
        assert _fast_preint.num_chunks(8, 64, "parallel", jnp.float64) > 1
    grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)), static_argnums=(4, 5))
    gr = grad(*args, False, "sequential")
    gf = grad(*args, True, method)
    for x, y in zip(gf, gr):
        assert np.all(np.isfinite(np.asarray(x)))
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-10 * max(np.abs(y).max(), 1e-300))


def test_shared_dt_with_batched_windows():
    """``dt`` ``(T,)`` shared by a batch of windows (both paths; the shapes of
    test_fast_path_equals_generic's first cases, whose reference program is compiled once)."""
    g, a, dt, bias, noise = inputs((5,), 60, seed=5)
    fast = jaximu.preintegrate(g, a, dt, bias, noise)
    ref = pre(g, a, dt, bias, noise, method="sequential", fast=False)
    assert_same(fast, ref, 1e-12)
    for i in range(5):
        one = jaximu.preintegrate(g[i], a[i], dt, bias, noise)
        np.testing.assert_allclose(
            fast.cov15[i], one.cov15, rtol=0, atol=1e-13 * np.abs(one.cov15).max()
        )


@pytest.mark.parametrize(
    "batch,T,method,kw",
    [
        ((9,), 60, "sequential", {"batched_bias": True, "batched_noise": True}),
        ((3, 3), 61, "sequential", {"per_lane_dt": True, "intervals": True}),
        ((300,), 30, "parallel", {"big": True}),  # parallel from a full block of windows
    ],
)
def test_midpoint_fast_path_equals_generic(batch, T, method, kw):
    args = inputs(batch, T, seed=7, **kw)
    assert uses_fast_path("midpoint", "analytic", False, method, int(np.prod(batch)))
    assert_same(
        pre(*args, method=method, fast=True, scheme="midpoint"),
        pre(*args, method="sequential", fast=False, scheme="midpoint"),
        1e-12,
    )


@pytest.mark.parametrize("T,big", [(301, True), (4229, False)])
def test_midpoint_parallel_long_sequence(T, big):
    """One sequence in chunks (rotations first, then chunks in frame B_i). 4229: 64 chunks of
    67 steps padded to 68 (whole kernel time chunks), the samples padded with the last one
    (without the big angles, whose first-order transition VINS-Mono's midpoint grows by ~5
    a step: over 600 of them it overflows on every path)."""
    args = inputs((), T, seed=9, per_lane_dt=True, big=big)
    assert _fast_preint.num_chunks(1, T, "parallel", jnp.float64) > 1
    assert_same(
        pre(*args, method="parallel", fast=True, scheme="midpoint"),
        pre(*args, method="sequential", fast=False, scheme="midpoint"),
        1e-12,
    )


def test_midpoint_fast_path_float32():
    args = inputs((9,), 300, seed=8, dtype=np.float32)
    assert_same(
        pre(*args, method="sequential", fast=True, scheme="midpoint"),
        pre(*args, method="sequential", fast=False, scheme="midpoint"),
        3e-5,
    )


@pytest.mark.parametrize("jacobians", ["analytic", "autodiff"])
def test_fast_path_per_axis_accelerometer_noise(jacobians):
    """A scalar accelerometer density lets the Euler kernel write its noise block as
    ``h σ_a² I`` (``R D Rᵀ`` of a rotation); a density per axis keeps the product
    ``Ev D Evᵀ``: both equal the generic recursion, and the per-axis one differs from the
    scalar one by as much as the densities differ. The shapes and the scalar noise are those
    of test_fast_path_equals_generic's first cases (their programs are compiled once)."""
    g, a, dt, bias, scalar = inputs((5,), 60, seed=11)
    per_axis = dataclasses.replace(
        scalar, accelerometer_noise_density=jnp.asarray([1e-3, 4e-3, 2e-3])
    )
    # The noise block is the kernel's step (preint_euler.step, its isotropic_accel form),
    # the same function in both methods; here the parallel method's 3 chunks of 20 steps
    # need no padding, so its steps are the sequential ones. Both methods for the analytic
    # blocks; the autodiff ones (the same noise block after them) on the sequential method:
    # the parallel method's two autodiff programs would add 4 s of CPU and no new step.
    methods = ("sequential", "parallel") if jacobians == "analytic" else ("sequential",)
    for method in methods:
        for noise in (per_axis, scalar):
            assert_same(
                pre(g, a, dt, bias, noise, method=method, fast=True, jacobians=jacobians),
                pre(g, a, dt, bias, noise, method="sequential", fast=False),
                1e-12,
            )
    d = (
        pre(g, a, dt, bias, per_axis, method="sequential", fast=True).cov
        - pre(g, a, dt, bias, scalar, method="sequential", fast=True).cov
    )
    assert (
        np.abs(np.asarray(d)).max()
        > 0.1
        * np.abs(np.asarray(pre(g, a, dt, bias, scalar, method="sequential", fast=True).cov)).max()
    )
