"""Gradients at points a user can reach that earlier tests missed (float64, against central
differences): each test failed before its fix."""

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
    noise = jaximu.ImuNoise(jnp.array([1.7e-4, 0.0, 2e-4]), jnp.array([2e-3, 2e-3, 3e-3]),
                            jnp.zeros(3), jnp.zeros(3))

    @jax.jit
    def loss(theta):
        pose = jaximu.SensorPose(so3.exp(theta), jnp.array([0.05, 0.0, 0.1]))
        pim = jaximu.preintegrate(gyro, accel, 0.005, noise=noise, body_P_sensor=pose)
        return 1e6 * jnp.sum(pim.cov * jnp.arange(81.0).reshape(9, 9)) + jnp.sum(pim.delta_p)

    for theta in (np.zeros(3), np.array([0.1, -0.2, 0.3])):
        g = np.asarray(jax.grad(loss)(jnp.asarray(theta)))
        assert np.all(np.isfinite(g)), g
        ref = _central(loss, theta, 1e-5)
        np.testing.assert_allclose(g, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
