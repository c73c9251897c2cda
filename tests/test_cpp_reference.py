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

pytestmark = pytest.mark.skipif(
    cpp_reference.find_toolchain()[0] is None, reason="no C++ compiler or Eigen"
)

FIELDS = ("delta_q", "delta_v", "delta_p", "cov") + cpp_reference.JACOBIANS


def _inputs(shape, seed=0):
    rng = np.random.default_rng(seed)
    # fast rotations too, so both branches of the exponential (θ² above and below 1e-4) run
    gyro = rng.normal(0.0, 3.0, shape + (3,))
    accel = np.array([0.3, -0.2, 9.81]) + rng.normal(0.0, 2.0, shape + (3,))
    dt = rng.uniform(0.002, 0.01, shape)
    b_g, b_a = np.array([0.01, -0.02, 0.005]), np.array([0.1, 0.05, -0.08])
    noise = jaximu.ImuNoise(
        np.array([1.7e-4, 2e-4, 1.5e-4]), np.array([2e-3, 3e-3, 2.5e-3]), 1.9e-5, 3e-3
    )
    return gyro, accel, dt, b_g, b_a, noise


@pytest.mark.parametrize("shape", [(150,), (3, 60)])
def test_matches_jaximu_euler(shape):
    gyro, accel, dt, b_g, b_a, noise = _inputs(shape)
    ref = cpp_reference.run_cpp_reference(
        gyro, accel, dt, b_g, b_a, noise, min_time=0.0, verbose=False
    )
    assert ref is not None
    pim = jaximu.preintegrate(
        jnp.asarray(gyro),
        jnp.asarray(accel),
        jnp.asarray(dt),
        jaximu.ImuBias(jnp.asarray(b_g), jnp.asarray(b_a)),
        noise,
        "euler",
    )
    big = np.sum(np.square(np.linalg.norm(gyro - b_g, axis=-1) * dt) >= 1e-4)
    assert 0 < big < gyro[..., 0].size
    for kernel in ("blocked", "dense"):
        res = ref["kernels"][kernel]["result"]
        np.testing.assert_allclose(res["delta_t"], np.sum(dt, axis=-1), rtol=1e-14)
        for name, (diff, scale) in cpp_reference.agreement(res, pim).items():
            assert diff <= 1e-12 * scale, (kernel, name, diff, scale)
        assert res["cov"].shape == np.shape(pim.cov)
        np.testing.assert_allclose(
            res["cov"],
            np.swapaxes(res["cov"], -1, -2),
            rtol=0,
            atol=1e-15 * np.abs(res["cov"]).max(),
        )


def _basalt_means(gyro, accel, dt, b_g, b_a):
    """Basalt's ``propagateState`` transcribed in numpy with scipy's rotations: the step's
    specific force rotated by the half-step rotation ``ΔR Exp(φ/2)``."""
    from scipy.spatial.transform import Rotation

    R, v, p = Rotation.identity(), np.zeros(3), np.zeros(3)
    for w, f, h in zip(gyro - b_g, accel - b_a, dt):
        a = (R * Rotation.from_rotvec(0.5 * h * w)).apply(f)
        p = p + v * h + 0.5 * a * h * h
        v = v + a * h
        R = R * Rotation.from_rotvec(h * w)
    return v, p


@pytest.mark.skipif(
    cpp_reference.find_basalt()[0] is None, reason="Basalt's headers not given (BASALT_HEADERS_DIR)"
)
def test_basalt_kernel():
    """The ``"basalt"`` kernel (Basalt's own class) in this program's layout: its rotation
    and gyro-bias Jacobian of the rotation are Euler's (the same exponential), its Δv, Δp
    those of its half-step scheme."""
    gyro, accel, dt, b_g, b_a, noise = _inputs((2, 60))
    dt = np.round(dt * 1e9) * 1e-9  # Basalt's timestamps are integer nanoseconds
    ref = cpp_reference.run_cpp_reference(
        gyro, accel, dt, b_g, b_a, noise, min_time=0.0, kernels=("basalt",), verbose=False
    )
    res = ref["kernels"]["basalt"]["result"]
    pim = jaximu.preintegrate(
        jnp.asarray(gyro),
        jnp.asarray(accel),
        jnp.asarray(dt),
        jaximu.ImuBias(jnp.asarray(b_g), jnp.asarray(b_a)),
        noise,
        "euler",
    )
    agree = cpp_reference.agreement(res, pim)
    for name in ("delta_q", "dR_dbg"):
        assert agree[name][0] <= 1e-12 * agree[name][1], (name, agree[name])
    cov = np.asarray(pim.cov)[:, :3, :3]
    np.testing.assert_allclose(res["cov"][:, :3, :3], cov, rtol=0, atol=1e-12 * np.abs(cov).max())
    for i in range(2):
        v, p = _basalt_means(gyro[i], accel[i], dt[i], b_g, b_a)
        np.testing.assert_allclose(res["delta_v"][i], v, rtol=0, atol=1e-12 * np.abs(v).max())
        np.testing.assert_allclose(res["delta_p"][i], p, rtol=0, atol=1e-12 * np.abs(p).max())
