"""The batch checks name their arguments, the noise densities included.

A noise density with batch axes that do not broadcast with the samples' batch used to reach
the engine and fail there with JAX's raw "Incompatible shapes for broadcasting: shapes=[...]",
naming no argument (every other mismatch names its arguments)."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaximu


def samples(B=3, T=20):
    gyro = jnp.zeros((B, T, 3))
    return gyro, gyro.at[..., 2].set(9.81)


@pytest.mark.parametrize("pose", [None, jaximu.SensorPose(jnp.asarray([1.0, 0, 0, 0]),
                                                          jnp.asarray([0.1, 0, 0]))])
def test_noise_batch_mismatch_names_the_density(pose):
    gyro, accel = samples()
    noise = jaximu.ImuNoise(1e-3, jnp.full((4, 3), 1e-2))
    with pytest.raises(ValueError, match=r"do not broadcast: gyro \(3,\).*"
                                         r"noise\.accelerometer_noise_density \(4,\)"):
        jaximu.preintegrate(gyro, accel, 0.005, None, noise, body_P_sensor=pose)


def test_broadcasting_noise_batch_still_accepted():
    """A per-window density (3, 3) beside windows (3,) and an unbatched one (4, 3) beside a
    single window: the first equals three single-window calls."""
    gyro, accel = samples()
    gyro = gyro + jnp.asarray(np.random.default_rng(0).normal(size=gyro.shape)) * 0.3
    dens = jnp.asarray([[1e-2] * 3, [2e-2] * 3, [3e-2] * 3])
    pim = jaximu.preintegrate(gyro, accel, 0.005, None, jaximu.ImuNoise(1e-3, dens))
    for i in range(3):
        one = jaximu.preintegrate(gyro[i], accel[i], 0.005, None,
                                  jaximu.ImuNoise(1e-3, float(dens[i, 0])))
        np.testing.assert_allclose(pim.cov[i], one.cov, rtol=1e-12,
                                   atol=1e-12 * float(np.abs(one.cov).max()))
    out = jaximu.preintegrate(gyro[0], accel[0], 0.005, None,
                              jaximu.ImuNoise(1e-3, jnp.full((4, 3), 1e-2)))
    assert out.cov.shape == (4, 9, 9)


def _states(n):
    return jaximu.NavState(jnp.tile(jnp.asarray([1.0, 0, 0, 0]), (n, 1)),
                           *(jnp.zeros((n, 3)),) * 4)


@pytest.mark.parametrize("case,named", [
    ("covariance P0", r"state and samples \(3,\), P0 \(4,\)"),
    ("covariance noise", r"noise\.accelerometer_noise_density \(4,\)"),
    ("needs_reintegration", r"bias\.b_g \(4,\), bias\.b_a \(\), pim \(3,\)"),
    ("predict", r"state_i \(4,\), pim \(3,\)"),
    ("residual", r"state_i \(3,\), state_j \(4,\), pim \(3,\)"),
])
def test_batch_mismatch_names_the_arguments(case, named):
    """Every entry's batch check names the arguments whose batches do not broadcast (the
    message is checked, not only the error type: it says which input to fix)."""
    gyro, accel = samples()
    calls = {
        "covariance P0": lambda: jaximu.propagate_covariance_final(
            _states(3), jnp.tile(jnp.eye(15) * 1e-4, (4, 1, 1)), gyro, accel, 0.005,
            jaximu.ImuNoise(1e-3, 1e-2)),
        "covariance noise": lambda: jaximu.propagate_covariance_final(
            _states(3), jnp.eye(15) * 1e-4, gyro, accel, 0.005,
            jaximu.ImuNoise(1e-3, jnp.full((4, 3), 1e-2))),
        "needs_reintegration": lambda: jaximu.needs_reintegration(
            jaximu.preintegrate(gyro, accel, 0.005),
            jaximu.ImuBias(jnp.zeros((4, 3)), jnp.zeros(3))),
        "predict": lambda: jaximu.predict(_states(4), jaximu.preintegrate(gyro, accel, 0.005)),
        "residual": lambda: jaximu.residual(_states(3), _states(4),
                                            jaximu.preintegrate(gyro, accel, 0.005)),
    }
    with pytest.raises(ValueError, match="do not broadcast: .*" + named):
        calls[case]()
