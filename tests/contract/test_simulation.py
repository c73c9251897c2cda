"""The input contract of ``jaximu.simulate``: trajectories' parameters, ``ideal_imu`` and
``true_states`` (times, batched poses, gravity, world rate, a pose function that does not
return unit quaternions), ``waypoints`` and ``add_noise`` (batches, keys, densities, text
and complex inputs), each refused naming the argument; half precision computes in float32.
Errors come before any compilation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu import ImuNoise, simulate
from jaximu import simulate as sim

N = ImuNoise.euroc()
KEY = jax.random.PRNGKey(0)
G = np.zeros((20, 3))
A = G + [0.0, 0.0, 9.81]
T20 = np.arange(20) * 0.01
TRAJ = sim.circle()
T5 = np.arange(5) * 0.01


# --------------------------------------------------------------------------- parameters and domains


@pytest.mark.parametrize(
    "call,message",
    [
        (lambda: simulate.circle(radius=0.0), r"radius must be positive and finite, got 0\.0"),
        (lambda: simulate.circle(speed=np.nan), r"speed must be finite"),
        (lambda: simulate.figure_eight(period=-1.0), r"period must be positive and finite"),
        (lambda: simulate.lissajous(amplitude=(1.0, 2.0)), r"amplitude must have shape \(3,\)"),
        (lambda: simulate.helix(radius=-3.0), r"radius must be positive"),
        (
            lambda: simulate.waypoints([0.0, np.nan, 2.0], np.zeros((3, 3))),
            r"times contains non-finite",
        ),
        (
            lambda: simulate.ideal_imu(lambda t: t, np.zeros(3)),
            r"traj must be a jaximu\.simulate\.Trajectory",
        ),
        (lambda: simulate.ideal_imu(TRAJ, np.zeros((3, 2))), r"t must be a 1-D array"),
        (lambda: simulate.true_states(TRAJ, np.array([0.0, np.inf])), r"t contains non-finite"),
        (
            lambda: simulate.ideal_imu(TRAJ, np.zeros(3), gravity=-9.81),
            r"gravity = -9\.81 is a magnitude",
        ),
        (
            lambda: simulate.add_noise(
                jax.random.PRNGKey(0), np.zeros((3, 2)), np.zeros((3, 3)), 0.01, ImuNoise.euroc()
            ),
            r"gyro must have shape \(\.\.\., T, 3\)",
        ),
        (
            lambda: simulate.add_noise(
                jax.random.PRNGKey(0), np.zeros((3, 3)), np.zeros((3, 3)), 0.0, ImuNoise.euroc()
            ),
            r"dt must be positive and finite",
        ),
        (
            lambda: simulate.add_noise(
                jax.random.PRNGKey(0),
                np.zeros((3, 3)),
                np.zeros((3, 3)),
                0.01,
                ImuNoise.euroc(),
                gyro_misalignment=np.zeros(3),
            ),
            r"gyro_misalignment must have shape \(3, 3\)",
        ),
    ],
)
def test_simulate_parameters_outside_their_domain(call, message):
    with pytest.raises(ValueError, match=message):
        call()


@pytest.mark.parametrize(
    "call,message",
    [
        (
            lambda: jaximu.io.gravity_alignment(np.zeros(3)),
            r"accel_mean must be a finite, non-zero",
        ),
        (lambda: jaximu.io.gravity_alignment([0.0, np.nan, 9.8]), r"accel_mean must be a finite"),
        (
            lambda: simulate.add_noise(
                jax.random.PRNGKey(0),
                np.zeros((3, 3)),
                np.zeros((3, 3)),
                0.01,
                ImuNoise.euroc(),
                b_g0=np.zeros(2),
            ),
            r"b_g0 must be a scalar or have shape \(\.\.\., 3\)",
        ),
    ],
)
def test_io_and_simulate_helpers_name_their_arguments(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_half_precision_times_are_computed_in_float32():
    """A float16 t gives float32 signals and states (as docs/guide/errors.md promises), not
    float16."""
    t = T20[:5].astype(np.float16)
    gyro, accel = sim.ideal_imu(TRAJ, t)
    assert gyro.dtype == accel.dtype == jnp.float32
    assert sim.true_states(TRAJ, t).p.dtype == jnp.float32


@pytest.mark.parametrize(
    "call,message",
    [
        (lambda: sim.add_noise(KEY, G + 0j, A, 0.01, N), r"gyro must be real, got a complex"),
        (lambda: sim.add_noise(KEY, G, A + 1j, 0.01, N), r"accel must be real, got a complex"),
        (lambda: sim.add_noise(KEY, G, A, 0.01, N, b_g0=np.zeros(3) + 1j), r"b_g0 must be real"),
        (
            lambda: sim.add_noise(KEY, G, A, 0.01, N, accel_misalignment=np.eye(3) * 1j),
            r"accel_misalignment must be real",
        ),
        (lambda: sim.ideal_imu(TRAJ, T20 + 0j), r"t must be real, got a complex"),
        (lambda: sim.true_states(TRAJ, T20 + 0j), r"t must be real, got a complex"),
        (lambda: sim.ideal_imu(TRAJ, T20, gravity=9.81 + 0j), r"gravity must be real"),
        (lambda: sim.helix(wobble=0.2j), r"wobble must be real"),
    ],
)
def test_complex_inputs_are_refused(call, message):
    """Complex inputs are refused naming them (their imaginary part would be dropped with
    only a warning)."""
    with pytest.raises(ValueError, match=message):
        call()


@pytest.mark.parametrize(
    "call,message",
    [
        (
            lambda: sim.add_noise(KEY, G, A, 0.01, N, gyro_misalignment=np.full((3, 3), np.nan)),
            r"gyro_misalignment contains non-finite values",
        ),
        (
            lambda: sim.add_noise(KEY, G, A, np.full(19, 0.01), N),
            r"dt must be a scalar or have shape \(T,\) = \(20,\) .* got \(19,\)",
        ),
        (lambda: sim.add_noise(KEY, G[:0], A[:0], 0.01, N), r"hold no samples \(T = 0\)"),
        (
            lambda: sim.add_noise(KEY, G, A, 0.01, N, batch_shape=(-1,)),
            r"batch_shape must be a tuple of non-negative ints, got \(-1,\)",
        ),
        (
            lambda: sim.add_noise(KEY, G, A, 0.01, N, batch_shape=(2.5,)),
            r"batch_shape must be a tuple of non-negative ints",
        ),
        (
            lambda: sim.add_noise(KEY, G, A, 0.01, N, b_g0="0.1"),
            r"b_g0 must be an array of numbers",
        ),
        (
            lambda: sim.add_noise(KEY, G, A, 0.01, N, gyro_misalignment=[["a"] * 3] * 3),
            r"gyro_misalignment must be an array of numbers",
        ),
        (
            lambda: sim.add_noise(KEY, G.astype(str), A, 0.01, N),
            r"gyro must be an array of numbers",
        ),
        (lambda: sim.add_noise(KEY, G, A, "0.01", N), r"dt must be an array of numbers"),
        (
            lambda: sim.add_noise(KEY, G, A, True, N),
            r"dt must be sample periods in seconds, got a bool",
        ),
        (lambda: sim.ideal_imu(TRAJ, "0.1"), r"t must be an array of numbers, got str"),
        (lambda: sim.true_states(TRAJ, [0.0, "0.1"]), r"t must be an array of numbers"),
        (lambda: sim.circle(speed="2"), r"speed must be a number, got str"),
        (lambda: sim.circle(radius=True), r"radius must be a number, got bool"),
        (lambda: sim.lissajous(amplitude=(1.0, 2.0, "3")), r"amplitude must be numbers of shape"),
    ],
)
def test_simulate_names_the_bad_argument(call, message):
    """Each bad argument is named: a NaN misalignment (it gave NaN samples), and shapes,
    text and bools that raised JAX's or numpy's errors naming no argument."""
    with pytest.raises(ValueError, match=message):
        call()


def test_batch_shape_int_gets_the_fix():
    with pytest.raises(
        ValueError,
        match=r"batch_shape must be a tuple of ints, got the int 3; "
        r"pass batch_shape=\(3,\)",
    ):
        sim.add_noise(KEY, G, A, 0.01, N, batch_shape=3)


# ---------------------------------------------------------------- ideal_imu, true_states, waypoints


def test_ideal_imu_refuses_a_batched_pose_gravity_or_world_rate():
    """A batched sensor pose gave (T, B, 3) outputs, the batch after time (read as B samples
    of T trajectories); a batched gravity or world rate raised JAX's broadcasting error."""
    from jaximu import simulate as sim

    poses = jaximu.SensorPose(jnp.tile(jnp.asarray([1.0, 0, 0, 0]), (2, 1)), jnp.zeros((2, 3)))
    with pytest.raises(
        ValueError,
        match=r"body_P_sensor\.q must be one \(4,\) quaternion.*"
        r"\(2, 4\); jax\.vmap over ideal_imu",
    ):
        sim.ideal_imu(sim.circle(), T5, body_P_sensor=poses)
    with pytest.raises(ValueError, match=r"omega_coriolis must be one \(3,\) world rate"):
        sim.ideal_imu(sim.circle(), T5, omega_coriolis=np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"gravity must be one magnitude or \(3,\) vector"):
        sim.ideal_imu(sim.circle(), T5, gravity=np.zeros((2, 3)))


def test_a_trajectory_whose_pose_is_not_unit_or_not_finite_is_named():
    """ω = 2 vec(q* ⊗ q̇) of a non-unit q is a wrong rate, returned silently (and NaN too)."""
    from jaximu import simulate as sim

    scaled = sim.Trajectory(
        lambda s: (jnp.asarray([2.0, 0, 0, 0]) * (1 + s), jnp.zeros(3)), "scaled"
    )
    with pytest.raises(
        ValueError,
        match=r"traj\.pose \(scaled\) gave a non-unit quaternion at "
        r"t\[0\] = 0",
    ):
        sim.ideal_imu(scaled, T5)
    with pytest.raises(ValueError, match=r"non-unit quaternion"):
        sim.true_states(scaled, T5)
    nan = sim.Trajectory(lambda s: (jnp.asarray([1.0, 0, 0, 0]), jnp.sqrt(s - 0.02) * jnp.ones(3)))
    with pytest.raises(
        ValueError,
        match=r"traj\.pose \(trajectory\) gave non-finite values at "
        r"t\[0\]",
    ):
        sim.ideal_imu(nan, T5)


@pytest.mark.parametrize(
    "kw, message",
    [
        (dict(times=["a", "b"]), r"times must be an array of numbers, got list"),
        (dict(times=[0.0, [1.0]]), r"times must be an array of numbers"),
        (dict(times=[False, True]), r"times must be numbers, got booleans"),
        (dict(positions=np.zeros((2, 3)) + 1j), r"positions must be real"),
        (dict(positions=None), r"positions must be an array of numbers, got NoneType"),
        (dict(quaternions=[[1.0, 0, 0, 0], [np.nan, 0, 0, 0]]), r"quaternions contains non-finite"),
    ],
)
def test_waypoints_name_what_is_not_numbers(kw, message):
    """numpy's "could not convert string to float" (no name), a complex position's imaginary
    part dropped with a warning, booleans and NaN quaternions accepted."""
    from jaximu import simulate as sim

    args = dict(times=[0.0, 1.0], positions=np.zeros((2, 3)), quaternions=None) | kw
    with pytest.raises(ValueError, match=message):
        sim.waypoints(**args)


# --------------------------------------------------------------------------- add_noise


def test_add_noise_refuses_a_batch_beyond_batch_shape():
    """gyro (2, T, 3) with batch_shape=() gave both elements the same noise draw, silently;
    mismatched batches came back as outputs of different shapes."""
    import jax

    from jaximu import simulate as sim

    key, noise = jax.random.key(0), jaximu.ImuNoise.euroc()
    g = jnp.zeros((2, 5, 3))
    with pytest.raises(
        ValueError,
        match=r"gyro has batch axes \(2,\) beyond batch_shape = \(\): "
        r"every element would get the same noise draw; pass "
        r"batch_shape=\(2,\)",
    ):
        sim.add_noise(key, g, g, 0.01, noise)
    with pytest.raises(
        ValueError,
        match=r"do not broadcast: batch_shape \(\), gyro \(2,\), "
        r"accel \(3,\)",
    ):
        sim.add_noise(key, g, jnp.zeros((3, 5, 3)), 0.01, noise)
    with pytest.raises(
        ValueError,
        match=r"batch_shape \(2,\), gyro \(\), accel \(\), "
        r"b_g0 \(3,\)",
    ):
        sim.add_noise(key, g[0], g[0], 0.01, noise, b_g0=np.zeros((3, 3)), batch_shape=(2,))
    gm, _, err = sim.add_noise(key, g, g, 0.01, noise, batch_shape=(2,))
    assert gm.shape == (2, 5, 3) and not np.allclose(gm[0], gm[1])


def test_add_noise_names_key_and_density_and_keeps_float64_data():
    import jax

    from jaximu import simulate as sim

    g = jnp.zeros((5, 3), jnp.float32)
    noise = jaximu.ImuNoise.euroc()
    with pytest.raises(ValueError, match=r"key must be a jax\.random key .*got int 0"):
        sim.add_noise(0, g, g, 0.01, noise)
    with pytest.raises(
        ValueError,
        match=r"do not broadcast: dt \(5,\), "
        r"noise\.gyroscope_noise_density \(2,\)",
    ):
        sim.add_noise(
            jax.random.key(0), g, g, 0.01, jaximu.ImuNoise(np.full((2, 3), 1e-3), 1e-2, 1e-5, 1e-4)
        )
    _, _, err = sim.add_noise(jax.random.key(0), g, g, 0.01, noise, b_g0=np.full(3, 1e-3))
    assert err.b_g.dtype == jnp.float64  # the float64 turn-on bias was rounded to float32
