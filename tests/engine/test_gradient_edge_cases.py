"""Gradients at edge points a user can reach, finite and equal to central differences
(float64): a per-axis noise density with a zero entry under a sensor pose, and the padded
last time chunk of the parallel preintegration with prefixes."""

import jax
import jax.numpy as jnp
import numpy as np

import jaximu
from jaximu import so3


def _central(f, x, h):
    x = np.asarray(x, np.float64)
    out = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        out.append((float(f(jnp.asarray(x + e))) - float(f(jnp.asarray(x - e)))) / (2 * h))
    return np.array(out)


def test_sensor_pose_gradient_with_a_zero_per_axis_density():
    """Per-axis densities with zero entries (zero random walks given as (3,) arrays, or one
    quiet axis) under a sensor pose: the body-frame densities ``sqrt((R∘R) σ²)`` are zero on
    some axis, where jnp.sqrt's derivative is inf; the gradient with respect to the pose
    was NaN (jaximu.sensor.noise_to_body). Now finite and equal to central differences."""
    rng = np.random.default_rng(0)
    T = 8
    gyro = jnp.asarray(rng.normal(size=(T, 3)))
    accel = jnp.asarray(rng.normal(size=(T, 3)) + [0.0, 0.0, 9.81])
    noise = jaximu.ImuNoise(
        jnp.array([1.7e-4, 0.0, 2e-4]), jnp.array([2e-3, 2e-3, 3e-3]), jnp.zeros(3), jnp.zeros(3)
    )

    def loss(theta):
        pose = jaximu.SensorPose(so3.exp(theta), jnp.array([0.05, 0.0, 0.1]))
        pim = jaximu.preintegrate(gyro, accel, 0.005, noise=noise, body_P_sensor=pose)
        return 1e6 * jnp.sum(pim.cov * jnp.arange(81.0).reshape(9, 9)) + jnp.sum(pim.delta_p)

    value_and_grad = jax.jit(jax.value_and_grad(loss))  # the differences' values too
    for theta in (np.zeros(3), np.array([0.1, -0.2, 0.3])):
        g = np.asarray(value_and_grad(jnp.asarray(theta))[1])
        assert np.all(np.isfinite(g)), g
        ref = _central(lambda x: value_and_grad(x)[0], theta, 1e-5)
        np.testing.assert_allclose(g, ref, rtol=0, atol=1e-6 * np.abs(ref).max())


def test_parallel_prefixes_autodiff_gradient_with_padded_chunks():
    """``prefixes=True`` runs the generic recursion; ``method="parallel"`` (also what
    ``"auto"`` picks for one window of 64 samples or more) pads the last time chunk. The
    padded steps' rotations were zero quaternions, which the autodiff step normalises: the
    NaN was masked out of the values but not out of the reverse-mode gradient with respect
    to the bias and the noise densities (any rates; 20 samples: two chunks of 16)."""
    rng = np.random.default_rng(1)
    T = 20
    gyro = jnp.asarray(rng.normal(size=(T, 3)))
    accel = jnp.asarray(rng.normal(size=(T, 3)) + [0.0, 0.0, 9.81])
    b_a = jnp.asarray(0.1 * rng.normal(size=3))

    def loss(x):
        pim = jaximu.preintegrate(
            gyro,
            accel,
            0.005,
            jaximu.ImuBias(x[:3], b_a),
            jaximu.ImuNoise(x[3], 2e-3, 1.9e-5, 3e-3),
            "euler",
            "parallel",
            prefixes=True,
            jacobians="autodiff",
        )
        return (
            jnp.sum(pim.delta_p[-1])
            + jnp.sum(pim.transition[-1, 3:9, 9:12])
            + 1e6 * jnp.sum(pim.cov[-1])
        )

    x0 = np.array([0.01, -0.02, 0.005, 1.7e-4])
    value_and_grad = jax.jit(jax.value_and_grad(loss))  # the differences' values too
    g = np.asarray(value_and_grad(jnp.asarray(x0))[1])
    assert np.all(np.isfinite(g)), g
    ref = _central(lambda x: value_and_grad(x)[0], x0, 1e-7)
    np.testing.assert_allclose(g, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
