"""The input contract of the preintegration helpers: ``whitened_residual`` (no noise is an
error, not NaN), ``needs_reintegration``, ``bias_jacobians_autodiff``, ``compose`` and
``correct`` (batches named), and noise densities with batch axes (named when they do not
broadcast, equal to single-window calls when they do).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu import ImuBias, ImuNoise, NavState

S64 = NavState.identity((), jnp.float64)
PIM = jaximu.preintegrate(np.zeros((3, 3)), np.tile([0, 0, 9.81], (3, 1)), 0.01)
PIM_NOISY = jaximu.preintegrate(
    np.zeros((3, 3)), np.tile([0, 0, 9.81], (3, 1)), 0.01, noise=ImuNoise.euroc()
)
W1 = np.zeros((1, 3))
A1 = np.array([[0.0, 0.0, 9.81]])


def test_whitened_residual_without_noise_is_an_error_not_nan():
    with pytest.raises(ValueError, match=r"pim\.cov15 is singular.*noise="):
        jaximu.whitened_residual(S64, S64, PIM)
    r = jaximu.whitened_residual(S64, S64, PIM_NOISY)  # with noise: finite
    assert np.isfinite(np.asarray(r)).all()


def test_needs_reintegration_checks_its_inputs():
    bias = ImuBias(np.array([np.nan, 0, 0]), np.zeros(3))
    with pytest.raises(ValueError, match=r"bias\.b_g contains non-finite"):
        jaximu.needs_reintegration(PIM, bias)
    with pytest.raises(ValueError, match=r"gyro_threshold must be non-negative and finite"):
        jaximu.needs_reintegration(PIM, ImuBias.zeros(), gyro_threshold=np.nan)
    with pytest.raises(ValueError, match=r"pim must be a jaximu\.Preintegrated"):
        jaximu.needs_reintegration((PIM.delta_q,), ImuBias.zeros())
    assert bool(jaximu.needs_reintegration(PIM, ImuBias(np.array([0.02, 0, 0]), np.zeros(3))))
    assert not bool(jaximu.needs_reintegration(PIM, ImuBias.zeros()))


def test_bias_jacobians_autodiff_unknown_scheme():
    with pytest.raises(ValueError, match=r"unknown preintegration scheme 'rk4'"):
        jaximu.bias_jacobians_autodiff(W1, A1, 0.01, scheme="rk4")


def test_compose_of_mismatched_batches_names_them():
    gyro = np.zeros((2, 3, 3))
    accel = np.tile([0, 0, 9.81], (2, 3, 1))
    ab = jaximu.preintegrate(gyro, accel, 0.01)
    bc = jaximu.preintegrate(
        np.concatenate([gyro, gyro[:1]]), np.concatenate([accel, accel[:1]]), 0.01
    )
    with pytest.raises(
        ValueError,
        match=r"pim_ab and pim_bc have batch shapes \(2,\) and "
        r"\(3,\), which do not broadcast",
    ):
        jaximu.compose(ab, bc)
    with pytest.raises(ValueError, match=r"pim_bc must be a jaximu\.Preintegrated"):
        jaximu.compose(ab, (bc.delta_q,))


def test_correct_names_the_batches_that_do_not_broadcast():
    gyro = jnp.zeros((2, 4, 3))
    pim = jaximu.preintegrate(gyro, gyro.at[..., 2].set(9.81), 0.01)
    with pytest.raises(ValueError, match=r"bias\.b_g \(3,\), bias\.b_a \(\), pim \(2,\)"):
        jaximu.correct(pim, jaximu.ImuBias(jnp.zeros((3, 3)), jnp.zeros(3)))


# ------------------------------------------------------------------ noise densities with batch axes


def samples(B=3, T=20):
    gyro = jnp.zeros((B, T, 3))
    return gyro, gyro.at[..., 2].set(9.81)


@pytest.mark.parametrize(
    "pose", [None, jaximu.SensorPose(jnp.asarray([1.0, 0, 0, 0]), jnp.asarray([0.1, 0, 0]))]
)
def test_noise_batch_mismatch_names_the_density(pose):
    gyro, accel = samples()
    noise = jaximu.ImuNoise(1e-3, jnp.full((4, 3), 1e-2))
    with pytest.raises(
        ValueError,
        match=r"do not broadcast: gyro \(3,\).*"
        r"noise\.accelerometer_noise_density \(4,\)",
    ):
        jaximu.preintegrate(gyro, accel, 0.005, None, noise, body_P_sensor=pose)


def test_broadcasting_noise_batch_still_accepted():
    """A per-window density (3, 3) beside windows (3,) and an unbatched one (4, 3) beside a
    single window: the first equals three single-window calls."""
    gyro, accel = samples()
    gyro = gyro + jnp.asarray(np.random.default_rng(0).normal(size=gyro.shape)) * 0.3
    dens = jnp.asarray([[1e-2] * 3, [2e-2] * 3, [3e-2] * 3])
    pim = jaximu.preintegrate(gyro, accel, 0.005, None, jaximu.ImuNoise(1e-3, dens))
    for i in range(3):
        one = jaximu.preintegrate(
            gyro[i], accel[i], 0.005, None, jaximu.ImuNoise(1e-3, float(dens[i, 0]))
        )
        np.testing.assert_allclose(
            pim.cov[i], one.cov, rtol=1e-12, atol=1e-12 * float(np.abs(one.cov).max())
        )
    out = jaximu.preintegrate(
        gyro[0], accel[0], 0.005, None, jaximu.ImuNoise(1e-3, jnp.full((4, 3), 1e-2))
    )
    assert out.cov.shape == (4, 9, 9)
