"""Bad input on the less-trodden entries (probe s17): each case raised JAX's or numpy's own
error deep in the stack (naming no argument), altered the user's data silently, or returned
a wrong result, before its fix. Tiny shapes: the suite is compile-bound."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu.errorstate import position_jacobian


def state(batch=(), dtype=jnp.float64):
    z = jnp.zeros(batch + (3,), dtype)
    return jaximu.NavState(jnp.broadcast_to(jnp.asarray([1.0, 0, 0, 0], dtype), batch + (4,)),
                           z, z, z, z)


# --------------------------------------------------------------------------- error state


@pytest.mark.parametrize("kw, named", [
    (dict(gyro=jnp.zeros((3, 3))), r"state \(2,\), gyro \(3,\)"),
    (dict(dt=jnp.full(3, 0.01)), r"dt \(3,\)"),
    (dict(gyro_next=jnp.zeros((3, 3)), scheme="midpoint"), r"gyro_next \(3,\)"),
    (dict(gravity=jnp.zeros((3, 3))), r"gravity \(3,\)"),
])
def test_step_jacobians_names_the_batch_that_does_not_fit(kw, named):
    args = dict(gyro=jnp.zeros((2, 3)), accel=jnp.zeros((2, 3)), dt=0.01) | kw
    with pytest.raises(ValueError, match=r"do not broadcast: .*" + named):
        jaximu.step_jacobians(state((2,)), **args)


def test_discrete_process_noise_names_the_batch_that_does_not_fit():
    G = jnp.zeros((3, 15, 12))
    with pytest.raises(ValueError, match=r"do not broadcast: G \(3,\), dt \(2,\)"):
        jaximu.discrete_process_noise(G, jaximu.ImuNoise.euroc(), jnp.full(2, 0.01))
    noise = jaximu.ImuNoise(jnp.full((2, 3), 1e-3), 1e-2, 1e-5, 1e-4)
    with pytest.raises(ValueError, match=r"G \(3,\), dt \(\), "
                                         r"noise\.gyroscope_noise_density \(2,\)"):
        jaximu.discrete_process_noise(G, noise, 0.01)


def test_discrete_process_noise_keeps_a_float64_dt():
    """A float64 ``dt`` beside a float32 ``G`` was rounded to float32 (only ``G`` counted)."""
    G = jnp.zeros((15, 12), jnp.float32)
    assert jaximu.discrete_process_noise(G, jaximu.ImuNoise.euroc(),
                                         np.float64(0.001)).dtype == jnp.float64
    assert jaximu.discrete_process_noise(G, jaximu.ImuNoise.euroc(), 0.001).dtype == jnp.float32


def test_ekf_update_does_not_round_a_float64_state_field_to_float32():
    """Only ``state.q`` decided the dtype: a float64 position beside float32 ``q`` and
    covariances came back float32, its 1e-9 m gone."""
    s32 = state(dtype=jnp.float32)
    s = s32.replace(p=jnp.asarray([1.0, 2.0, 3.0]) + 1e-9)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    out, _, _ = jaximu.ekf_update(s, f32(1e-2 * np.eye(15)), jnp.zeros(3, jnp.float32),
                                  position_jacobian(jnp.float32), f32(1e-2 * np.eye(3)))
    assert out.p.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(out.p), np.asarray(s.p))  # a zero residual


def test_correct_names_the_batches_that_do_not_broadcast():
    gyro = jnp.zeros((2, 4, 3))
    pim = jaximu.preintegrate(gyro, gyro.at[..., 2].set(9.81), 0.01)
    with pytest.raises(ValueError, match=r"bias\.b_g \(3,\), bias\.b_a \(\), pim \(2,\)"):
        jaximu.correct(pim, jaximu.ImuBias(jnp.zeros((3, 3)), jnp.zeros(3)))


# --------------------------------------------------------------------------- Monte Carlo

MC = dict(n_runs=2, n_keep=0, chunk_size=2)


def mc_study(**kw):
    import jax

    from jaximu import montecarlo, simulate
    args = dict(trajectory=simulate.circle(), times=np.arange(5) * 0.01,
                P0=1e-6 * np.eye(15), noise=jaximu.ImuNoise.euroc(), key=jax.random.key(0))
    return montecarlo.monte_carlo(**(args | MC | kw))


def test_monte_carlo_names_a_batched_density_before_the_work():
    """A (2, 3) density reached numpy's IndexError after the reference propagation."""
    noise = jaximu.ImuNoise(1.6e-4, np.full((2, 3), 2.8e-3), 2.2e-5, 8.6e-4)
    with pytest.raises(ValueError, match=r"noise\.accelerometer_noise_density must be a scalar "
                                         r"or \(3,\) for a Monte Carlo study.*\(2, 3\)"):
        mc_study(noise=noise)


def test_host_side_inputs_under_jit_name_the_argument():
    """monte_carlo under jit: "P0 must be an array of numbers, got DynamicJaxprTracer"."""
    import jax
    with pytest.raises(ValueError, match=r"P0 must be concrete numbers, got a traced value.*"
                                         r"outside jax\.jit"):
        jax.jit(lambda P: mc_study(P0=P).nees_mean)(jnp.eye(15) * 1e-6)


# --------------------------------------------------------------------------- simulate

T5 = np.arange(5) * 0.01


def test_ideal_imu_refuses_a_batched_pose_gravity_or_world_rate():
    """A batched sensor pose gave (T, B, 3) outputs, the batch after time (read as B samples
    of T trajectories); a batched gravity or world rate raised JAX's broadcasting error."""
    from jaximu import simulate as sim
    poses = jaximu.SensorPose(jnp.tile(jnp.asarray([1.0, 0, 0, 0]), (2, 1)), jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"body_P_sensor\.q must be one \(4,\) quaternion.*"
                                         r"\(2, 4\); jax\.vmap over ideal_imu"):
        sim.ideal_imu(sim.circle(), T5, body_P_sensor=poses)
    with pytest.raises(ValueError, match=r"omega_coriolis must be one \(3,\) world rate"):
        sim.ideal_imu(sim.circle(), T5, omega_coriolis=np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"gravity must be one magnitude or \(3,\) vector"):
        sim.ideal_imu(sim.circle(), T5, gravity=np.zeros((2, 3)))


def test_a_trajectory_whose_pose_is_not_unit_or_not_finite_is_named():
    """ω = 2 vec(q* ⊗ q̇) of a non-unit q is a wrong rate, returned silently (and NaN too)."""
    from jaximu import simulate as sim
    scaled = sim.Trajectory(lambda s: (jnp.asarray([2.0, 0, 0, 0]) * (1 + s), jnp.zeros(3)),
                            "scaled")
    with pytest.raises(ValueError, match=r"traj\.pose \(scaled\) gave a non-unit quaternion at "
                                         r"t\[0\] = 0"):
        sim.ideal_imu(scaled, T5)
    with pytest.raises(ValueError, match=r"non-unit quaternion"):
        sim.true_states(scaled, T5)
    nan = sim.Trajectory(lambda s: (jnp.asarray([1.0, 0, 0, 0]), jnp.sqrt(s - 0.02) * jnp.ones(3)))
    with pytest.raises(ValueError, match=r"traj\.pose \(trajectory\) gave non-finite values at "
                                         r"t\[0\]"):
        sim.ideal_imu(nan, T5)


@pytest.mark.parametrize("kw, message", [
    (dict(times=["a", "b"]), r"times must be an array of numbers, got list"),
    (dict(times=[0.0, [1.0]]), r"times must be an array of numbers"),
    (dict(times=[False, True]), r"times must be numbers, got booleans"),
    (dict(positions=np.zeros((2, 3)) + 1j), r"positions must be real"),
    (dict(positions=None), r"positions must be an array of numbers, got NoneType"),
    (dict(quaternions=[[1.0, 0, 0, 0], [np.nan, 0, 0, 0]]), r"quaternions contains non-finite"),
])
def test_waypoints_name_what_is_not_numbers(kw, message):
    """numpy's "could not convert string to float" (no name), a complex position's imaginary
    part dropped with a warning, booleans and NaN quaternions accepted."""
    from jaximu import simulate as sim
    args = dict(times=[0.0, 1.0], positions=np.zeros((2, 3)), quaternions=None) | kw
    with pytest.raises(ValueError, match=message):
        sim.waypoints(**args)


def test_add_noise_refuses_a_batch_beyond_batch_shape():
    """gyro (2, T, 3) with batch_shape=() gave both elements the same noise draw, silently;
    mismatched batches came back as outputs of different shapes."""
    import jax

    from jaximu import simulate as sim
    key, noise = jax.random.key(0), jaximu.ImuNoise.euroc()
    g = jnp.zeros((2, 5, 3))
    with pytest.raises(ValueError, match=r"gyro has batch axes \(2,\) beyond batch_shape = \(\): "
                                         r"every element would get the same noise draw; pass "
                                         r"batch_shape=\(2,\)"):
        sim.add_noise(key, g, g, 0.01, noise)
    with pytest.raises(ValueError, match=r"do not broadcast: batch_shape \(\), gyro \(2,\), "
                                         r"accel \(3,\)"):
        sim.add_noise(key, g, jnp.zeros((3, 5, 3)), 0.01, noise)
    with pytest.raises(ValueError, match=r"batch_shape \(2,\), gyro \(\), accel \(\), "
                                         r"b_g0 \(3,\)"):
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
    with pytest.raises(ValueError, match=r"do not broadcast: dt \(5,\), "
                                         r"noise\.gyroscope_noise_density \(2,\)"):
        sim.add_noise(jax.random.key(0), g, g, 0.01,
                      jaximu.ImuNoise(np.full((2, 3), 1e-3), 1e-2, 1e-5, 1e-4))
    _, _, err = sim.add_noise(jax.random.key(0), g, g, 0.01, noise, b_g0=np.full(3, 1e-3))
    assert err.b_g.dtype == jnp.float64  # the float64 turn-on bias was rounded to float32


# --------------------------------------------------------------------------- calibration


@pytest.fixture(scope="module")
def cal_inputs():
    from jaximu import calibration as cal
    from jaximu import simulate as sim
    traj, t = sim.circle(), np.arange(60) * 0.01
    gyro, accel = sim.ideal_imu(traj, t)
    s = sim.true_states(traj, t)
    ref = cal.Reference(t, np.asarray(s.q), np.asarray(s.p), np.asarray(s.v))
    return t, gyro, accel, ref


def test_calibrate_refuses_estimate_given_as_a_string():
    """tuple("b_g") is ('b', '_', 'g'): "unknown calibration fields ['b', '_', 'g']"; None
    gave Python's "'NoneType' object is not iterable"."""
    from jaximu import calibration as cal
    with pytest.raises(ValueError, match=r"estimate must be a tuple of field names, got the "
                                         r"string 'b_g,b_a'; pass estimate=\('b_g', 'b_a'\)"):
        cal.calibrate(cal.CalibrationProblem(*[None] * 13), estimate="b_g,b_a")
    with pytest.raises(ValueError, match=r"estimate must be a tuple of field names .*NoneType"):
        cal.calibrate(None, estimate=None)


def test_calibration_loss_names_its_arguments(cal_inputs):
    """AttributeError "'NoneType' object has no attribute 'velocities'"."""
    from jaximu import calibration as cal
    t, gyro, accel, ref = cal_inputs
    problem = cal.calibration_problem(t, gyro, accel, ref, jaximu.ImuNoise.euroc(),
                                      keyframe_interval=0.2, check=False)
    with pytest.raises(ValueError, match=r"problem must be a CalibrationProblem"):
        cal.calibration_loss(None, cal.ImuCalibration.default())
    with pytest.raises(ValueError, match=r"calib must be an ImuCalibration"):
        cal.calibration_residuals(problem, None)
    with pytest.raises(ValueError, match=r"velocities must have the shape \(3, 3\) of "
                                         r"problem\.velocities"):
        cal.calibration_loss(problem, cal.ImuCalibration.default(), jnp.zeros((2, 3)))


def test_imu_calibration_default_names_its_arguments():
    from jaximu import calibration as cal
    with pytest.raises(ValueError, match=r"dtype must be a floating dtype .*'foo'"):
        cal.ImuCalibration.default(dtype="foo")
    with pytest.raises(ValueError, match=r"gravity must be an array of numbers, got str"):
        cal.ImuCalibration.default(gravity="9.81")
    with pytest.raises(ValueError, match=r"b_g must be an array of numbers, got str"):
        cal.ImuCalibration.default(b_g="abc")


@pytest.mark.parametrize("change, message", [
    (dict(extrinsics="no"), r"extrinsics must be True or False, got the string 'no'; "
                            r"pass extrinsics=False"),
    (dict(check="no"), r"check must be True or False"),
    (dict(omega_coriolis=np.zeros((2, 3))), r"omega_coriolis must be one \(3,\) world rate"),
    (dict(noise=jaximu.ImuNoise(np.full((2, 3), 1e-3), 1e-2)),
     r"noise\.gyroscope_noise_density must be a scalar or \(3,\) for a calibration problem"),
    (dict(noise=jaximu.ImuNoise(0.0, 0.0), reference_sigma=(0, 0, 0)),
     r"the residuals' covariance is singular.*give noise positive densities"),
    (dict(t="abc"), r"t must be an array of numbers, got str"),
    (dict(reference_t="abc"), r"reference\.t must be an array of numbers, got str"),
    (dict(reference_t=np.nan), r"reference\.t contains non-finite values .* \[5\]"),
])
def test_calibration_problem_names_what_it_took_silently_or_raised_deep(cal_inputs, change,
                                                                         message):
    """extrinsics="no" and check="no" counted as True; a (2, 3) world rate was kept; a batched
    density and text reached JAX's/numpy's own errors; zero densities numpy's LinAlgError; a
    NaN reference time passed the order test."""
    from jaximu import calibration as cal
    t, gyro, accel, ref = cal_inputs
    kw = dict(noise=jaximu.ImuNoise.euroc(), keyframe_interval=0.2, check=False) | change
    rt = kw.pop("reference_t", ref.t)
    if isinstance(rt, float):
        rt = np.where(np.arange(len(ref.t)) == 5, rt, ref.t)
    ref = cal.Reference(rt, ref.q, ref.p, ref.v)
    with pytest.raises(ValueError, match=message):
        cal.calibration_problem(kw.pop("t", t), gyro, accel, ref, **kw)


# --------------------------------------------------------------------------- allan


def test_allan_names_a_traced_input_and_a_wrong_fit():
    """allan_deviation under jit raised JAX's TracerArrayConversionError; check_units(None)
    an AttributeError."""
    import jax

    from jaximu import allan
    with pytest.raises(ValueError, match=r"y must be concrete numbers, got a traced value"):
        jax.jit(lambda y: allan.allan_deviation(y, 0.01)[1])(jnp.zeros((20, 3)))
    with pytest.raises(ValueError, match=r"gyro must be the NoiseFit of the gyro"):
        allan.check_units(None)


# --------------------------------------------------------------------------- command


@pytest.mark.parametrize("estimate, fragment", [("", "no field in --estimate"),
                                                ("foo", "unknown field(s) ['foo'] in --estimate")])
def test_calibrate_estimate_is_checked_before_the_recording_is_read(capsys, estimate, fragment):
    """An empty --estimate reached the library after the recording was read and the problem
    built ("estimate names no field", no flag); an unknown one was named after reading."""
    import pathlib

    from jaximu import cli
    folder = pathlib.Path(__file__).parent / "data" / "euroc_v1_02_medium"
    code = cli.main(["calibrate", str(folder), "--estimate", estimate])
    out, err = capsys.readouterr()
    assert code == 2 and fragment in err, err
    assert "read " not in out, out  # refused before the work


# --------------------------------------------------------------------------- constructors


@pytest.mark.parametrize("make", [jaximu.NavState.identity, jaximu.ImuBias.zeros])
def test_constructors_name_a_bad_batch_shape(make):
    """An int batch_shape raised Python's "'int' object is not iterable"; a negative or
    non-int dimension JAX's shape error. Both are named, with the fix for the int."""
    with pytest.raises(ValueError, match=r"batch_shape must be a tuple of ints, got the int 3; "
                                         r"pass batch_shape=\(3,\)"):
        make(3)
    with pytest.raises(ValueError, match=r"batch_shape must be a tuple of non-negative ints"):
        make((2, -1))
    assert make((2,)).b_g.shape == (2, 3)
