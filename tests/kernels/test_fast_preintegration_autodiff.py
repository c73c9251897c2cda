"""``jacobians="autodiff"`` on the structure-of-arrays preintegration kernels
(jaximu/kernels/fast_preint.py: the step's blocks by ``jax.jvp`` of the kernel's own step, then the
same covariance update as the closed forms) against the generic recursion's autodiff step
(``jax.jacfwd`` of the step's mean and noise, dense). A file of its own so that the test
runner's workers balance (its tests compile long)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_fast_preintegration import assert_same, inputs, pre, uses_fast_path

import jaximu


@pytest.mark.parametrize(
    "scheme,batch,T,method,kw,lever",
    [
        (
            "euler",
            (3, 2),
            100,
            "sequential",
            {"per_lane_dt": True, "batched_bias": True, "batched_noise": True},
            False,
        ),
        ("euler", (), 301, "parallel", {"big": True}, False),  # padded last chunk, big angles
        ("euler", (2,), 150, "parallel", {"per_lane_dt": True}, True),
        ("midpoint", (9,), 60, "sequential", {"batched_bias": True, "batched_noise": True}, True),
        ("midpoint", (), 301, "parallel", {"big": True, "per_lane_dt": True}, False),
    ],
)
def test_autodiff_fast_path_equals_generic_autodiff(scheme, batch, T, method, kw, lever):
    """``jacobians="autodiff"`` on the SoA kernels (their blocks by ``jax.jvp`` of the SoA
    step: preint_euler._autodiff_blocks, preint_midpoint._mid_autodiff) against the generic recursion's
    autodiff step (``jax.jacfwd`` of the step's mean and noise, dense): the same numbers to
    rounding, with a lever arm too (its gyro bias and noise then move the specific force).
    For the midpoint these are the exact derivatives, not VINS-Mono's linearisation (the
    last assertion)."""
    args = inputs(batch, T, seed=11, **kw)
    r = jnp.asarray(np.random.default_rng(12).normal(size=batch + (3,)) * 0.3) if lever else None
    assert uses_fast_path(scheme, "autodiff", False, method, int(np.prod(batch)), lever=lever)
    fast = pre(*args, r, method=method, fast=True, jacobians="autodiff", scheme=scheme)
    assert_same(
        fast,
        pre(*args, r, method="sequential", fast=False, jacobians="autodiff", scheme=scheme),
        1e-12,
    )
    # The reference is the generic autodiff recursion, the same code in every case: that
    # it is not VINS-Mono's linearisation is seen once, on the sequential case (the
    # parallel one would compile the analytic parallel kernel for it: 1.3 s of CPU).
    if scheme == "midpoint" and method == "sequential":
        vins = pre(*args, r, method=method, fast=True, scheme=scheme)
        diff = np.abs(np.asarray(fast.transition - vins.transition)).max()
        assert diff > 1e-6 * np.abs(np.asarray(vins.transition)).max()


def test_autodiff_fast_path_gradients_equal_generic():
    """Gradients through the autodiff blocks (second derivatives of the step) equal the
    generic autodiff recursion's. The midpoint only (each such gradient takes ~35 s to
    compile): its blocks and Euler's are made by the same helpers (_soa.rotation_tangents,
    jvp_directions, rotation_rows), and Euler's values are checked above."""
    scheme = "midpoint"
    g, a, dt, bias, _ = inputs((3,), 24, seed=13)

    def loss(g, bg, sigma, fast):
        pim = pre(
            g,
            a,
            dt,
            jaximu.ImuBias(bg, bias.b_a),
            jaximu.ImuNoise(sigma, 2e-3, 2e-5, 3e-3),
            method="sequential",
            fast=fast,
            jacobians="autodiff",
            scheme=scheme,
        )
        return (
            jnp.sum(pim.delta_p)
            + 1e6 * jnp.sum(jnp.trace(pim.cov, axis1=-2, axis2=-1))
            + 1e3 * jnp.sum(pim.cov15[..., 9:15, 0:9])
            + jnp.sum(pim.transition[..., 0:9, 9:15] ** 2)
        )

    # The fast path's gradient by reverse mode (what a user's jax.grad runs); the generic
    # one, the reference, by forward mode: the same vector (seen: to 3e-16 of its largest
    # entry) from a program cheaper to trace and compile than the reverse-mode one (9 s of
    # CPU against 13 s), whose 220 directions run in under a second at this size.
    grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2)), static_argnums=3)
    reference = jax.jit(jax.jacfwd(loss, argnums=(0, 1, 2)), static_argnums=3)
    args = (g, bias.b_g, jnp.asarray(1.7e-4))
    for x, y in zip(grad(*args, True), reference(*args, False)):
        assert np.all(np.isfinite(np.asarray(x)))
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-10 * max(np.abs(y).max(), 1e-300))
