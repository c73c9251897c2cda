"""The input contract of ``propagate`` and ``propagate_final``: gravity's sign, half precision,
the sensor pose (``body_P_sensor``), the rotating world (``earth_rate``,
``omega_coriolis``) and batches that do not fit, each refused naming the argument (or, for
a valid input, against a closed form). Errors come before any compilation; the valid calls
use tiny inputs.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu import NavState, SensorPose

W1 = np.zeros((1, 3))
A1 = np.array([[0.0, 0.0, 9.81]])
X0 = NavState(jnp.array([1.0, 0, 0, 0]), jnp.zeros(3), jnp.zeros(3), jnp.zeros(3), jnp.zeros(3))
T = 4
GYRO = jnp.zeros((T, 3))
ACCEL = jnp.tile(jnp.array([0.0, 0.0, 9.81]), (T, 1))
DT = 0.01
POSE = SensorPose(jnp.array([1.0, 0, 0, 0]), jnp.array([0.1, 0.0, 0.0]))


# --------------------------------------------------------------------------- gravity and precision


def test_gravity_magnitude_must_not_be_negative():
    s = NavState.identity((), jnp.float64)
    msg = r"gravity = -9\.81 is a magnitude.*pass gravity=9\.81"
    with pytest.raises(ValueError, match=msg):
        jaximu.propagate(s, W1, A1, 0.01, gravity=-9.81)
    pim = jaximu.preintegrate(W1, A1, 0.01)
    with pytest.raises(ValueError, match=msg):
        jaximu.predict(s, pim, gravity=-9.81)
    # a vector is a direction: any sign is allowed
    out = jaximu.propagate_final(s, W1, A1, 0.01, gravity=np.array([0.0, 0.0, 9.81]))
    np.testing.assert_allclose(np.asarray(out.v), [0, 0, 2 * 9.81 * 0.01])


@pytest.mark.parametrize("half", [np.float16, jnp.bfloat16], ids=["float16", "bfloat16"])
def test_half_precision_is_computed_in_float32_not_float16(half):
    """float16 samples (a ROS driver's packed output) and bfloat16 ones (a network's) are
    integrated in float32: a still IMU with excess accel climbs by the closed form ½ a t²
    (half precision loses the increments). The user's arrays are not changed. (numpy files
    bfloat16 under the kind of raw bytes, which the checks once took for text.)"""
    n = 400
    gyro = np.zeros((n, 3), half)
    accel = np.tile(np.asarray([0, 0, 9.81], half), (n, 1))
    a_excess = float(accel[0, 2]) - 9.81
    before = accel.copy()
    out = jaximu.propagate_final(NavState.identity((), half), gyro, accel, np.asarray(0.01, half))
    assert out.p.dtype == jnp.float32
    dt = float(np.asarray(0.01, half))
    T = n * dt
    np.testing.assert_allclose(float(out.p[2]), 0.5 * a_excess * T * T, rtol=1e-2)
    np.testing.assert_array_equal(accel, before)


# --------------------------------------------------------------------------- body_P_sensor


@pytest.mark.parametrize(
    "call",
    [
        lambda pose: jaximu.propagate(
            X0,
            jnp.broadcast_to(GYRO, (2, T, 3)),
            jnp.broadcast_to(ACCEL, (2, T, 3)),
            DT,
            body_P_sensor=pose,
        ),
        lambda pose: jaximu.preintegrate(
            jnp.broadcast_to(GYRO, (2, T, 3)),
            jnp.broadcast_to(ACCEL, (2, T, 3)),
            DT,
            body_P_sensor=pose,
        ),
    ],
)
def test_a_sensor_pose_whose_batch_does_not_fit_is_named(call):
    # before: JAX's "mul got incompatible shapes" / einsum's label error
    pose = SensorPose(jnp.tile(jnp.array([1.0, 0, 0, 0]), (3, 1)), jnp.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"do not broadcast: body_P_sensor\.q \(3,\)"):
        call(pose)


def test_a_sensor_pose_of_none_or_text_names_the_field():
    with pytest.raises(ValueError, match=r"body_P_sensor\.q must be an array of numbers"):
        jaximu.propagate(X0, GYRO, ACCEL, DT, body_P_sensor=SensorPose(None, [0.1, 0, 0]))
    with pytest.raises(ValueError, match=r"R_BS must be an array of numbers"):
        SensorPose.from_rotation("eye", [0, 0, 0])


def test_from_rotation_refuses_a_non_finite_lever_arm():
    # before: a SensorPose holding NaN
    with pytest.raises(ValueError, match=r"lever arm p_BS contains non-finite"):
        SensorPose.from_rotation(np.eye(3), [np.nan, 0, 0])


# --------------------------------------------------------------------------- rotating world


def test_earth_rate_names_the_bad_latitude_and_refuses_text_and_non_float_dtypes():
    with pytest.raises(ValueError, match=r"latitude_deg\[1\] = 95"):
        jaximu.earth_rate([10, 95])
    for bad in ("45", None):  # before: "45" ran, None said "got None" from a numpy error
        with pytest.raises(ValueError, match=r"latitude_deg must be an array of numbers"):
            jaximu.earth_rate(bad)
    for dtype in (np.int32, "banana"):  # before: an int computation / numpy's TypeError
        with pytest.raises(ValueError, match=r"dtype must be a floating dtype"):
            jaximu.earth_rate(45.0, dtype=dtype)


def test_earth_rate_is_the_closed_form():
    lat = np.array([-90.0, -30.0, 0.0, 48.1, 90.0])
    phi = np.deg2rad(lat)
    want = 7.292115e-5 * np.stack([0 * phi, np.cos(phi), np.sin(phi)], -1)
    np.testing.assert_allclose(
        np.asarray(jaximu.earth_rate(lat)), want, rtol=1e-6, atol=1e-6 * 7.3e-5
    )


def test_omega_coriolis_whose_batch_does_not_fit_is_named():
    with pytest.raises(ValueError, match=r"do not broadcast: .*omega_coriolis \(3,\)"):
        jaximu.propagate(
            X0,
            jnp.zeros((2, T, 3)),
            jnp.broadcast_to(ACCEL, (2, T, 3)),
            DT,
            omega_coriolis=jnp.zeros((3, 3)),
        )


def test_mismatched_batches_name_the_arguments():
    with pytest.raises(ValueError, match=r"gyro \(2,\), accel \(3,\)"):
        jaximu.propagate(X0, jnp.zeros((2, T, 3)), jnp.zeros((3, T, 3)), DT)
