"""The C++/Eigen reference of the preintegration benchmark computes jaximu's mathematics.

Skipped where g++ or Eigen is missing. Agreement only; nothing here is timed.
"""

import os
import sys

import jax.numpy as jnp
import numpy as np
import pytest

import jaximu

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
import cpp_reference  # noqa: E402

pytestmark = pytest.mark.skipif(cpp_reference.find_toolchain()[0] is None,
                                reason="no C++ compiler or Eigen")

FIELDS = ("delta_q", "delta_v", "delta_p", "cov") + cpp_reference.JACOBIANS


def _inputs(shape, seed=0):
    rng = np.random.default_rng(seed)
    # fast rotations too, so both branches of the exponential (θ² above and below 1e-4) run
    gyro = rng.normal(0.0, 3.0, shape + (3,))
    accel = np.array([0.3, -0.2, 9.81]) + rng.normal(0.0, 2.0, shape + (3,))
    dt = rng.uniform(0.002, 0.01, shape)
    b_g, b_a = np.array([0.01, -0.02, 0.005]), np.array([0.1, 0.05, -0.08])
    noise = jaximu.ImuNoise(np.array([1.7e-4, 2e-4, 1.5e-4]), np.array([2e-3, 3e-3, 2.5e-3]),
                            1.9e-5, 3e-3)
    return gyro, accel, dt, b_g, b_a, noise


@pytest.mark.parametrize("shape", [(150,), (3, 60)])
def test_matches_jaximu_euler(shape):
    gyro, accel, dt, b_g, b_a, noise = _inputs(shape)
    ref = cpp_reference.run_cpp_reference(gyro, accel, dt, b_g, b_a, noise, min_time=0.0,
                                          verbose=False)
    assert ref is not None
    pim = jaximu.preintegrate(jnp.asarray(gyro), jnp.asarray(accel), jnp.asarray(dt),
                              jaximu.ImuBias(jnp.asarray(b_g), jnp.asarray(b_a)), noise, "euler")
    big = np.sum(np.square(np.linalg.norm(gyro - b_g, axis=-1) * dt) >= 1e-4)
    assert 0 < big < gyro[..., 0].size
    for kernel in ("blocked", "dense"):
        res = ref["kernels"][kernel]["result"]
        np.testing.assert_allclose(res["delta_t"], np.sum(dt, axis=-1), rtol=1e-14)
        for name, (diff, scale) in cpp_reference.agreement(res, pim).items():
            assert diff <= 1e-12 * scale, (kernel, name, diff, scale)
        assert res["cov"].shape == np.shape(pim.cov)
        np.testing.assert_allclose(res["cov"], np.swapaxes(res["cov"], -1, -2), rtol=0,
                                   atol=1e-15 * np.abs(res["cov"]).max())
