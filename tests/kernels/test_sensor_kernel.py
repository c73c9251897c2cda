"""A sensor at a pose (``body_P_sensor``) in the mean's structure-of-arrays kernel: its samples
move into the body frame inside the kernel's time chunks (jaximu.sensor.chunk_to_body, with a
halo of neighbouring samples for the derivative α). Checked against the samples moved first
by the whole-array transform (jaximu.sensor.to_body, whose α is numpy's gradient in
tests/geometry/test_sensor.py) and run through the generic kernel (``fast=False``): values and
gradients, at the chunks' seams and the sequence's ends."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu.engine import _dispatch
from jaximu.engine._inputs import sensor_engine_inputs
from jaximu.engine.errorstate import _propagate_covariance
from jaximu.engine.propagate import _propagate, _sensor_options
from jaximu.sensor import SensorPose

G_W = jnp.array([0.0, 0.0, -9.81])


def _sensor_inputs(state, gyro, accel, dt, body_P_sensor, tangential, omega_coriolis):
    """The samples moved into the body frame first, by the whole-array transform (the generic
    kernel's inputs), the state with body-frame biases, and ``ω_W``."""
    tangential, omega, pose = _sensor_options(
        state, gyro, accel, body_P_sensor, tangential, omega_coriolis
    )
    state, gyro, accel = sensor_engine_inputs(False, pose, state, gyro, accel, dt, tangential)
    return state, gyro, accel, omega


def unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def case_inputs(batch, T, n, per_lane_dt, per_lane_pose, dtype, seed=0):
    """Samples of a body turning at up to ~6 rad/s with a rate that changes every sample
    (so α is large and a wrong neighbour shows), ``n`` steps (``T`` or ``T - 1``)."""
    rng = np.random.default_rng(seed)
    gyro = rng.normal(size=batch + (T, 3)) * 3.0
    accel = rng.normal(size=batch + (T, 3)) + [0.0, 0.0, 9.8]
    dt = rng.uniform(0.003, 0.008, size=(batch if per_lane_dt else ()) + (n,))
    state = jaximu.NavState(
        unit(rng.normal(size=batch + (4,))),
        rng.normal(size=batch + (3,)),
        rng.normal(size=batch + (3,)),
        0.01 * rng.normal(size=batch + (3,)),
        0.1 * rng.normal(size=batch + (3,)),
    )
    pb = batch if per_lane_pose else ()
    pose = SensorPose(
        unit(rng.normal(size=pb + (4,)) + [2.0, 0, 0, 0]), rng.uniform(-0.4, 0.4, size=pb + (3,))
    )
    cast = lambda t: jax.tree_util.tree_map(lambda x: jnp.asarray(x, dtype), t)  # noqa: E731
    return cast(state), cast(gyro), cast(accel), cast(dt), cast(pose)


@functools.partial(jax.jit, static_argnames=("scheme", "save_all", "tangential", "attitude"))
def in_kernel(state, gyro, accel, dt, pose, omega, *, scheme, save_all, tangential, attitude):
    """The engine as the entries call it: raw sensor samples, the pose, sensor-frame biases."""
    return _propagate(
        state,
        gyro,
        accel,
        dt,
        G_W.astype(gyro.dtype),
        omega,
        pose,
        scheme=scheme,
        attitude=attitude,
        save_all=save_all,
        tangential=tangential,
    )[0]


@functools.partial(jax.jit, static_argnames=("scheme", "save_all", "tangential", "attitude"))
def moved_first(state, gyro, accel, dt, pose, omega, *, scheme, save_all, tangential, attitude):
    """The reference: the whole-array transform, then the generic kernel."""
    inner, gyro, accel, _ = _sensor_inputs(state, gyro, accel, dt, pose, tangential, None)
    return _propagate(
        inner,
        gyro,
        accel,
        dt,
        G_W.astype(gyro.dtype),
        omega,
        scheme=scheme,
        attitude=attitude,
        save_all=save_all,
        fast=False,
    )[0]


def assert_close(got, want, rtol):
    for a, b in zip((got.q, got.p, got.v), (want.q, want.p, want.v)):
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_allclose(a, b, rtol=0, atol=rtol * max(1.0, float(np.abs(b).max())))


# (scheme, batch, T samples, intervals (n = T - 1), dt per lane, pose per lane, save_all,
#  tangential, attitude, rotating, dtype)
CASES = [
    # chunks of 32 and a remainder of 13 (77 steps), a pose per lane, every state
    ("euler", (2, 3), 78, True, False, True, True, True, "quaternion", False, np.float64),
    # the held last sample of a next-sample scheme (n = T), dt per lane, float32
    ("midpoint", (5,), 150, False, True, False, False, True, "quaternion", False, np.float32),
    # one sequence, RK4, three samples: first, last and held samples in one chunk
    ("rk4", (), 3, False, False, False, True, True, "quaternion", False, np.float64),
    # no tangential term; Euler angles in a turning world
    ("midpoint", (4,), 40, True, True, True, False, False, "euler_angles", True, np.float64),
]


@pytest.mark.parametrize(
    "scheme,batch,T,intervals,lane_dt,lane_pose,save_all,tangential,attitude,rotating,dtype", CASES
)
def test_samples_moved_in_the_kernel_equal_the_samples_moved_first(
    scheme, batch, T, intervals, lane_dt, lane_pose, save_all, tangential, attitude, rotating, dtype
):
    state, gyro, accel, dt, pose = case_inputs(
        batch, T, T - 1 if intervals else T, lane_dt, lane_pose, dtype
    )
    lanes = int(np.prod(batch))
    assert (
        _dispatch.kernel(
            "mean",
            scheme,
            attitude=attitude,
            save_all=save_all,
            lanes=lanes,
            steps=dt.shape[-1],
            dtype=dtype,
            rotating=rotating,
        )
        == "soa_mean"
    )
    omega = jnp.asarray(jaximu.earth_rate(48.0), dtype) if rotating else None
    kw = dict(scheme=scheme, save_all=save_all, tangential=tangential, attitude=attitude)
    got = in_kernel(state, gyro, accel, dt, pose, omega, **kw)
    want = moved_first(state, gyro, accel, dt, pose, omega, **kw)
    assert_close(got, want, 1e-12 if dtype == np.float64 else 2e-5)
    # the pose matters here: without its lever arm the result moves far beyond that
    still = SensorPose(pose.q, jnp.zeros_like(pose.p))
    off = in_kernel(state, gyro, accel, dt, still, omega, **kw)
    assert float(jnp.max(jnp.abs(off.v - want.v))) > 1e-3 * float(jnp.max(jnp.abs(want.v)))


def test_gradients_through_the_pose_and_samples_equal_the_reference():
    """``grad`` with respect to the lever arm, the rotation q_BS and the gyro samples (every
    sample, so the halo's derivatives reach the right neighbours), midpoint, float64."""
    state, gyro, accel, dt, pose = case_inputs((3,), 40, 40, False, True, np.float64, seed=1)
    kw = dict(scheme="midpoint", save_all=False, tangential=True, attitude="quaternion")

    def loss(fn, p, q, w):
        out = fn(state, w, accel, dt, SensorPose(q, p), None, **kw)
        return jnp.sum(out.p**2) + jnp.sum(jnp.sin(out.q))

    got = jax.grad(functools.partial(loss, in_kernel), argnums=(0, 1, 2))(pose.p, pose.q, gyro)
    want = jax.grad(functools.partial(loss, moved_first), argnums=(0, 1, 2))(pose.p, pose.q, gyro)
    for a, b in zip(got, want):
        assert np.all(np.isfinite(np.asarray(a)))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-10 * float(np.abs(b).max()))


def test_covariance_with_samples_moved_in_the_kernel_equals_the_samples_moved_first():
    """The covariance kernels read the moved samples too (their Jacobians take the lever arm
    as before): a pose per lane, 77 steps (chunks and a remainder), n = T, midpoint, every
    covariance stored. (The closed-form Euler covariance with the moved samples is checked
    as Φ Φᵀ, Φ by finite differences, in tests/geometry/test_sensor.py.)"""
    scheme, jacobians, save_all = "midpoint", "autodiff", True
    state, gyro, accel, dt, pose = case_inputs((3,), 77, 77, False, True, np.float64, seed=2)
    P0 = jnp.asarray(np.diag(np.linspace(1e-4, 1e-2, 15)))
    noise = jaximu.ImuNoise.euroc()
    assert _dispatch.kernel(
        "covariance",
        scheme,
        attitude="quaternion",
        jacobians=jacobians,
        save_all=save_all,
        lanes=3,
        lever=True,
    ).startswith("soa_cov")
    kw = dict(scheme=scheme, attitude="quaternion", jacobians=jacobians, save_all=save_all)
    got = _propagate_covariance(state, P0, gyro, accel, dt, G_W, noise, None, pose.p, pose, **kw)
    inner, g_b, a_b, _ = _sensor_inputs(state, gyro, accel, dt, pose, True, None)
    want = _propagate_covariance(
        inner, P0, g_b, a_b, dt, G_W, noise, None, pose.p, fast=False, **kw
    )
    assert_close(got[0], want[0], 1e-12)
    np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-12 * float(np.abs(want[1]).max()))


@pytest.mark.parametrize("dtype,per_lane", [(np.float64, "p"), (np.float32, "q")])
def test_a_pose_half_shared_over_several_blocks(dtype, per_lane):
    """130 lanes (several blocks of the kernel), the lever arm per lane and the rotation
    shared (what a vmap over lever arms makes), or the other way round."""
    B = 130
    state, gyro, accel, dt, pose = case_inputs((B,), 20, 20, False, True, dtype, seed=3)
    pose = SensorPose(pose.q[0], pose.p) if per_lane == "p" else SensorPose(pose.q, pose.p[0])
    kw = dict(scheme="euler", save_all=False, tangential=True, attitude="quaternion")
    got = in_kernel(state, gyro, accel, dt, pose, None, **kw)
    want = moved_first(state, gyro, accel, dt, pose, None, **kw)
    assert_close(got, want, 1e-12 if dtype == np.float64 else 2e-5)
