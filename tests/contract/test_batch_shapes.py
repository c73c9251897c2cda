"""Every entry's batch check names the arguments whose batches do not broadcast, the noise
densities included (the message is checked, not only the error type: it says which input
to fix).
"""

from __future__ import annotations

import jax.numpy as jnp
import pytest

import jaximu


def samples(B=3, T=20):
    gyro = jnp.zeros((B, T, 3))
    return gyro, gyro.at[..., 2].set(9.81)


def _states(n):
    return jaximu.NavState(jnp.tile(jnp.asarray([1.0, 0, 0, 0]), (n, 1)), *(jnp.zeros((n, 3)),) * 4)


@pytest.mark.parametrize(
    "case,named",
    [
        ("covariance P0", r"state and samples \(3,\), P0 \(4,\)"),
        ("covariance noise", r"noise\.accelerometer_noise_density \(4,\)"),
        ("needs_reintegration", r"bias\.b_g \(4,\), bias\.b_a \(\), pim \(3,\)"),
        ("predict", r"state_i \(4,\), pim \(3,\)"),
        ("residual", r"state_i \(3,\), state_j \(4,\), pim \(3,\)"),
    ],
)
def test_batch_mismatch_names_the_arguments(case, named):
    """Every entry's batch check names the arguments whose batches do not broadcast (the
    message is checked, not only the error type: it says which input to fix)."""
    gyro, accel = samples()
    calls = {
        "covariance P0": lambda: jaximu.propagate_covariance_final(
            _states(3),
            jnp.tile(jnp.eye(15) * 1e-4, (4, 1, 1)),
            gyro,
            accel,
            0.005,
            jaximu.ImuNoise(1e-3, 1e-2),
        ),
        "covariance noise": lambda: jaximu.propagate_covariance_final(
            _states(3),
            jnp.eye(15) * 1e-4,
            gyro,
            accel,
            0.005,
            jaximu.ImuNoise(1e-3, jnp.full((4, 3), 1e-2)),
        ),
        "needs_reintegration": lambda: jaximu.needs_reintegration(
            jaximu.preintegrate(gyro, accel, 0.005), jaximu.ImuBias(jnp.zeros((4, 3)), jnp.zeros(3))
        ),
        "predict": lambda: jaximu.predict(_states(4), jaximu.preintegrate(gyro, accel, 0.005)),
        "residual": lambda: jaximu.residual(
            _states(3), _states(4), jaximu.preintegrate(gyro, accel, 0.005)
        ),
    }
    with pytest.raises(ValueError, match="do not broadcast: .*" + named):
        calls[case]()
