"""Calibration against a reference with dropouts, and windows that are not in the fit.

A window that is not in the fit (padding of the last group; a keyframe inside a reference
gap) adds nothing to the loss, the residuals or their gradient. References: the loss as the
sum of the squared residuals, a problem without padding, and a problem built on the whole
reference from which the same windows are removed before any tracing.
"""

import jax
import jax.numpy as jnp
import numpy as np

import jaximu
from jaximu import calibration as cal
from jaximu import simulate as sim

RATE = 200.0
SECONDS = 10.0
NOISE = jaximu.ImuNoise.euroc()
WHITE = jaximu.ImuNoise(NOISE.gyroscope_noise_density, NOISE.accelerometer_noise_density, 0.0, 0.0)
TRAJ = sim.lissajous(attitude_amplitude=(0.8, 0.6, 1.5), attitude_frequency=(0.31, 0.23, 0.13))
B_G, B_A = np.array([0.003, -0.002, 0.004]), np.array([0.05, -0.08, 0.1])


def simulate_data(seed=0):
    """IMU at 200 Hz; reference at 100 Hz (pose and velocity), 0.5 s beyond either end."""
    t = np.arange(int(SECONDS * RATE) + 1) / RATE
    gyro, accel = sim.ideal_imu(TRAJ, jnp.asarray(t))
    gm, am, _ = sim.add_noise(jax.random.key(seed), gyro, accel, 1 / RATE, WHITE, b_g0=B_G,
                              b_a0=B_A)
    t_ref = np.arange(-0.5, SECONDS + 0.5, 0.01)
    truth = sim.true_states(TRAJ, jnp.asarray(t_ref))
    ref = cal.Reference(t_ref, np.asarray(truth.q), np.asarray(truth.p), np.asarray(truth.v))
    return t, np.asarray(gm), np.asarray(am), ref


def problem_for(t, gm, am, ref, **kw):
    kw = dict(dict(scheme="midpoint", reference_sigma=(0, 0, 0)), **kw)
    return cal.calibration_problem(t, gm, am, ref, NOISE, **kw)


def test_padding_windows_add_nothing_to_the_loss_or_its_gradient():
    """20 windows in groups of 8: 4 padding windows (copies of window 0) must weigh 0; the
    loss equals ½ Σ r² of the residuals and the loss and gradient of one group of 20."""
    data = simulate_data()
    padded = problem_for(*data, windows_per_group=8)
    whole = problem_for(*data, windows_per_group=20)
    assert padded.weight.shape == (3, 8) and whole.weight.shape == (1, 20)
    c = cal.ImuCalibration.default(dtype=jnp.float64, b_g=0.5 * B_G, b_a=-B_A)
    r = cal.calibration_residuals(padded, c)
    loss = float(cal.calibration_loss(padded, c))
    np.testing.assert_allclose(loss, 0.5 * float(jnp.sum(r * r)), rtol=1e-12)
    np.testing.assert_allclose(loss, float(cal.calibration_loss(whole, c)), rtol=1e-12)
    grad = jax.grad(lambda x: cal.calibration_loss(padded, x))(c)
    want = jax.grad(lambda x: cal.calibration_loss(whole, x))(c)
    for name in ("b_g", "b_a"):
        np.testing.assert_allclose(getattr(grad, name), getattr(want, name), rtol=1e-10)
