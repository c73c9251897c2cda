"""Issue 12: the bad-input contract in the places the first property tests did not reach.

One block per defect class of the issue (5: shapes the ``so3`` kernels documented but did not
check; 2: ``P0`` tolerances that ignored scale; 3: physical parameters outside their domain;
6: NaN in, NaN out from public helpers; 4: errors that named the library's internals), each a
plain test of the reported example plus, where the input space is wide, a hypothesis
property. Every expectation is independent of the code under test: an error message that
names the user's argument, scipy / numpy numbers, or a closed form.

Compile cost: every error here is raised before any compilation; the few valid calls use
tiny inputs and share their shapes.
"""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import jaximu
from jaximu import ImuBias, ImuNoise, NavState, allan, montecarlo, simulate, so3
from jaximu import calibration as cal


def fast_settings(n):
    return settings(max_examples=n, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow])


# --------------------------------------------------------------------------- class 5: so3 shapes

# every so3 kernel: (function, [(argument name, last-axis shape), ...])
SO3_SIGNATURES = {
    "skew": [("v", (3,))],
    "quat_mul": [("p", (4,)), ("q", (4,))],
    "quat_conj": [("q", (4,))],
    "quat_normalize": [("q", (4,))],
    "quat_rotate": [("q", (4,)), ("v", (3,))],
    "quat_to_matrix": [("q", (4,))],
    "matrix_to_quat": [("R", (3, 3))],
    "exp": [("phi", (3,))],
    "log": [("q", (4,))],
    "exp_matrix": [("phi", (3,))],
    "log_matrix": [("R", (3, 3))],
    "right_jacobian": [("phi", (3,))],
    "right_jacobian_inv": [("phi", (3,))],
    "left_jacobian": [("phi", (3,))],
    "quat_first_order_update": [("q", (4,)), ("phi", (3,))],
    "xyzw_to_wxyz": [("q", (4,))],
    "wxyz_to_xyzw": [("q", (4,))],
    "jpl_to_hamilton": [("q_jpl", (4,))],
    "hamilton_to_jpl": [("q_wb", (4,))],
    "euler_zyx_to_quat": [("chi", (3,))],
    "euler_zyx_to_matrix": [("chi", (3,))],
    "quat_to_euler_zyx": [("q", (4,))],
    "euler_rate_matrix": [("chi", (3,))],
}


def test_every_so3_kernel_is_in_the_signature_table():
    assert set(SO3_SIGNATURES) == set(so3.__all__) - {"quat_identity"}


def test_so3_reported_examples_raise_naming_the_argument():
    with pytest.raises(ValueError, match=r"so3\.exp: phi must have shape \(\.\.\., 3\), got \(4,\)"):
        so3.exp(np.zeros(4))
    with pytest.raises(ValueError, match=r"so3\.quat_to_matrix: q must have shape \(\.\.\., 4\), "
                                         r"got \(3,\)"):
        so3.quat_to_matrix(np.zeros(3))
    with pytest.raises(ValueError, match=r"so3\.log_matrix: R must have shape \(\.\.\., 3, 3\)"):
        so3.log_matrix(np.eye(4))


def test_so3_batches_that_do_not_broadcast_are_named():
    with pytest.raises(ValueError, match=r"so3\.quat_rotate: the batch shapes of q \(2, 4\) "
                                         r"and v \(3, 3\) do not broadcast"):
        so3.quat_rotate(np.ones((2, 4)), np.ones((3, 3)))
    with pytest.raises(ValueError, match=r"so3\.quat_mul: the batch shapes of p"):
        so3.quat_mul(np.ones((2, 4)), np.ones((5, 4)))


def test_so3_accepts_python_lists_like_arrays():
    """A ROS quaternion as a list: the same numbers as scipy's."""
    q_xyzw = [0.1, -0.2, 0.3, 0.9273618495495704]  # unit
    q = so3.xyzw_to_wxyz(q_xyzw)
    np.testing.assert_allclose(np.asarray(q), np.r_[q_xyzw[3], q_xyzw[:3]], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(so3.quat_to_matrix(list(np.asarray(q)))),
                               Rotation.from_quat(q_xyzw).as_matrix(), atol=1e-6)
    np.testing.assert_allclose(np.asarray(so3.exp([0.0, 0.0, np.pi / 2])),
                               [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], atol=1e-6)
    np.testing.assert_allclose(np.asarray(so3.quat_rotate([1, 0, 0, 0], [1, 2, 3])), [1, 2, 3])


@fast_settings(60)
@given(st.data())
def test_so3_kernels_refuse_wrong_shapes_naming_the_argument(data):
    """Any kernel, any of its arguments given a wrong trailing shape (or a scalar): a
    ``ValueError`` naming the function, the argument and the shape wanted."""
    name = data.draw(st.sampled_from(sorted(SO3_SIGNATURES)), label="kernel")
    sig = SO3_SIGNATURES[name]
    bad = data.draw(st.integers(0, len(sig) - 1), label="argument")
    batch = data.draw(st.sampled_from(((), (2,))), label="batch")
    args = []
    for i, (arg, shape) in enumerate(sig):
        if i == bad:
            # wrong: not ending in the shape wanted ((2, 4) is a batch of quaternions)
            shape = data.draw(st.sampled_from([s for s in ((), (2,), (3,), (4,), (5,), (3, 3),
                                                           (4, 4), (3, 4), (4, 3))
                                               if s[len(s) - len(shape):] != shape]),
                              label="wrong shape")
            args.append(np.ones(batch + shape if shape else ()))
        else:
            args.append(np.ones(batch + shape))
    want = ", ".join(str(s) for s in sig[bad][1])
    with pytest.raises(ValueError) as err:
        getattr(so3, name)(*args)
    assert re.search(rf"so3\.{name}: {sig[bad][0]} must have shape \(\.\.\., {want}\)",
                     str(err.value)), str(err.value)


# --------------------------------------------------------------------------- class 2: P0 scale

S64 = NavState.identity((), jnp.float64)
W1 = np.zeros((1, 3))
A1 = np.array([[0.0, 0.0, 9.81]])


def cov_final(P0, dtype=np.float64):
    s = NavState.identity((), dtype)
    return jaximu.propagate_covariance_final(s, P0, W1.astype(dtype), A1.astype(dtype), 0.01,
                                             ImuNoise.euroc())


def test_p0_symmetry_is_judged_relative_to_its_scale():
    P0 = np.eye(15) * 1e-6
    P0[0, 1] = 1e-7  # one-sided: 10% of the matrix's scale
    with pytest.raises(ValueError, match="P0 is not symmetric"):
        cov_final(P0)


def test_p0_definiteness_is_judged_relative_to_its_scale():
    P0 = np.eye(15) * 1e-6
    P0[4, 4] = -1e-10  # a negative variance, 1e-4 of the scale
    with pytest.raises(ValueError, match="P0 is not positive semi-definite"):
        cov_final(P0)


def test_p0_from_rounding_at_any_scale_is_accepted():
    """A covariance ``A Aᵀ`` computed in the dtype (rounding-level asymmetry, a singular
    direction) is valid at 1e-12 and at 1e6; the output variances are non-negative."""
    rng = np.random.default_rng(1)
    A = rng.normal(size=(15, 14))
    for scale in (1e-12, 1e6):
        for dtype in (np.float64, np.float32):
            Ad = (A * np.sqrt(scale)).astype(dtype)
            P0 = Ad @ Ad.T
            _, P = cov_final(P0, dtype)
            assert np.all(np.diag(np.asarray(P, np.float64)) >= 0)


# --------------------------------------------------------------------------- class 3: domains


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


TRAJ = simulate.circle()
TIMES = np.arange(11) * 0.01
P0_MC = np.eye(15) * 1e-6


def mc(**kw):
    args = dict(trajectory=TRAJ, times=TIMES, P0=P0_MC, noise=ImuNoise.euroc(), n_runs=4,
                key=jax.random.PRNGKey(0))
    args.update(kw)
    return montecarlo.monte_carlo(**args)


@pytest.mark.parametrize("kw,message", [
    ({"confidence": 95}, r"confidence must be in \(0, 1\).*got 95.*0\.95"),
    ({"confidence": 0.0}, r"confidence must be in \(0, 1\)"),
    ({"record_every": 0}, r"record_every must be a positive integer, got 0"),
    ({"record_every": 1.5}, r"record_every must be a positive integer, got 1\.5"),
    ({"n_runs": 1}, r"n_runs must be an integer ≥ 2, got 1"),
    ({"n_runs": 10.5}, r"n_runs must be an integer ≥ 2, got 10\.5"),
    ({"chunk_size": 0}, r"chunk_size must be a positive integer, got 0"),
    ({"n_keep": -1}, r"n_keep must be a non-negative integer, got -1"),
    ({"gravity": -9.81}, r"gravity = -9\.81 is a magnitude"),
    ({"scheme": "heun"}, r"unknown scheme 'heun'"),
    ({"dtype": np.int32}, r"dtype must be a floating dtype"),
])
def test_monte_carlo_parameters_outside_their_domain(kw, message):
    with pytest.raises(ValueError, match=message):
        mc(**kw)


def test_chi2_interval_confidence_domain():
    with pytest.raises(ValueError, match=r"confidence must be in \(0, 1\)"):
        montecarlo.chi2_interval(15, 95)
    with pytest.raises(ValueError, match=r"dof must be positive"):
        montecarlo.chi2_interval(0)
    from scipy.stats import chi2
    lo, hi = montecarlo.chi2_interval(1500, 0.95)
    np.testing.assert_allclose([lo, hi], chi2.interval(0.95, 1500), rtol=1e-4)


def a_reference(n=401, rate=200.0):
    t = np.arange(n) / rate
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    return t, cal.Reference(t, q, np.zeros((n, 3)), np.zeros((n, 3)))


@pytest.mark.parametrize("value,message", [
    (-0.5, r"keyframe_interval must be positive and finite, got -0\.5"),
    (np.nan, r"keyframe_interval must be positive and finite, got nan"),
    (0.001, r"keyframe_interval = 0\.001 s is shorter than one sample interval \(0\.005 s\)"),
])
def test_keyframe_interval_domain(value, message):
    t, ref = a_reference()
    gyro = np.zeros((len(t), 3))
    accel = np.tile([0, 0, 9.81], (len(t), 1))
    with pytest.raises(ValueError, match=message):
        cal.calibration_problem(t, gyro, accel, ref, ImuNoise.euroc(), keyframe_interval=value)


def test_half_precision_is_computed_in_float32_not_float16():
    """float16 samples (a ROS driver's packed output) are integrated in float32: a still IMU
    with 0.01 m/s² of excess accel climbs by the closed form ½ a t² (float16 loses the
    increments). The user's arrays are not changed."""
    n = 400
    gyro = np.zeros((n, 3), np.float16)
    accel = np.tile(np.float16([0, 0, 9.81]), (n, 1))
    a_excess = float(accel[0, 2]) - 9.81
    before = accel.copy()
    out = jaximu.propagate_final(NavState.identity((), jnp.float16), gyro, accel,
                                 np.float16(0.01))
    assert out.p.dtype == jnp.float32
    dt = float(np.float16(0.01))
    T = n * dt
    np.testing.assert_allclose(float(out.p[2]), 0.5 * a_excess * T * T, rtol=1e-2)
    np.testing.assert_array_equal(accel, before)


# --------------------------------------------------------------------------- class 6: NaN out

PIM = jaximu.preintegrate(np.zeros((3, 3)), np.tile([0, 0, 9.81], (3, 1)), 0.01)
PIM_NOISY = jaximu.preintegrate(np.zeros((3, 3)), np.tile([0, 0, 9.81], (3, 1)), 0.01,
                                noise=ImuNoise.euroc())


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


def test_discrete_process_noise_checks_dt():
    G = np.zeros((15, 12))
    G[np.arange(12) + 3, np.arange(12)] = 1.0
    for dt in (0.0, -0.01, np.nan):
        with pytest.raises(ValueError, match=r"dt must be positive and finite"):
            jaximu.discrete_process_noise(G, ImuNoise.euroc(), dt)
    for bad, message in ((G.T, r"G must have shape \(\.\.\., 15, 12\) .*got \(12, 15\)"),
                         (G[:12], r"G must have shape \(\.\.\., 15, 12\)"),
                         (np.zeros(12), r"G must have shape \(\.\.\., 15, 12\)"),
                         (np.where(G > 0, np.nan, 0.0), r"G contains non-finite")):
        with pytest.raises(ValueError, match=message):
            jaximu.discrete_process_noise(bad, ImuNoise.euroc(), 0.01)
    with pytest.raises(ValueError, match=r"noise must be a jaximu\.ImuNoise, got tuple"):
        jaximu.discrete_process_noise(G, (1e-3, 1e-2, 1e-5, 1e-4), 0.01)
    n = ImuNoise.euroc()
    Q = np.asarray(jaximu.discrete_process_noise(G, n, 0.01))
    want = np.r_[[n.gyroscope_noise_density**2] * 3, [n.accelerometer_noise_density**2] * 3,
                 [n.gyroscope_random_walk**2] * 3, [n.accelerometer_random_walk**2] * 3] / 0.01
    np.testing.assert_allclose(np.diag(Q)[3:], want, rtol=1e-6)


def test_fit_noise_refuses_nan_silently(capfd):
    taus = np.logspace(-2, 1, 10)
    with pytest.raises(ValueError, match=r"adev contains non-finite"):
        allan.fit_noise(taus, np.full(10, np.nan))
    with pytest.raises(ValueError, match=r"taus must be positive and finite"):
        allan.fit_noise(-taus, np.ones(10))
    with pytest.raises(ValueError, match=r"taus and adev have different lengths"):
        allan.fit_noise(taus, np.ones(9))
    with pytest.raises(ValueError, match=r"adev must be positive"):
        allan.fit_noise(taus, np.zeros(10))
    assert capfd.readouterr().out == ""  # LAPACK printed to stdout
    fit = allan.fit_noise(taus, np.sqrt(0.01**2 / taus))  # pure white noise
    np.testing.assert_allclose(fit.white, 0.01, rtol=1e-6)


def test_bias_jacobians_autodiff_unknown_scheme():
    with pytest.raises(ValueError, match=r"unknown preintegration scheme 'rk4'"):
        jaximu.bias_jacobians_autodiff(W1, A1, 0.01, scheme="rk4")


# --------------------------------------------------------------------------- class 4: names


def test_monte_carlo_times_nan_is_named_as_times():
    times = TIMES.copy()
    times[3] = np.nan
    with pytest.raises(ValueError, match=r"times contains non-finite values .*\[3\]") as err:
        mc(times=times)
    assert "gyro" not in str(err.value)


def test_monte_carlo_bias_shape_is_named():
    with pytest.raises(ValueError, match=r"b_g0 must have shape \(3,\), got \(2,\)"):
        mc(b_g0=np.zeros(2))
    with pytest.raises(ValueError, match=r"b_a0 contains non-finite"):
        mc(b_a0=np.array([0, np.nan, 0]))
    with pytest.raises(ValueError, match=r"trajectory must be a jaximu\.simulate\.Trajectory"):
        mc(trajectory=lambda t: t)


def test_compose_of_mismatched_batches_names_them():
    gyro = np.zeros((2, 3, 3))
    accel = np.tile([0, 0, 9.81], (2, 3, 1))
    ab = jaximu.preintegrate(gyro, accel, 0.01)
    bc = jaximu.preintegrate(np.concatenate([gyro, gyro[:1]]),
                             np.concatenate([accel, accel[:1]]), 0.01)
    with pytest.raises(ValueError, match=r"pim_ab and pim_bc have batch shapes \(2,\) and "
                                         r"\(3,\), which do not broadcast"):
        jaximu.compose(ab, bc)
    with pytest.raises(ValueError, match=r"pim_bc must be a jaximu\.Preintegrated"):
        jaximu.compose(ab, (bc.delta_q,))


# --------------------------------------------------------------------------- simulate domains


@pytest.mark.parametrize("call,message", [
    (lambda: simulate.circle(radius=0.0), r"radius must be positive and finite, got 0\.0"),
    (lambda: simulate.circle(speed=np.nan), r"speed must be finite"),
    (lambda: simulate.figure_eight(period=-1.0), r"period must be positive and finite"),
    (lambda: simulate.lissajous(amplitude=(1.0, 2.0)), r"amplitude must have shape \(3,\)"),
    (lambda: simulate.helix(radius=-3.0), r"radius must be positive"),
    (lambda: simulate.waypoints([0.0, np.nan, 2.0], np.zeros((3, 3))), r"times contains non-finite"),
    (lambda: simulate.ideal_imu(lambda t: t, np.zeros(3)), r"traj must be a jaximu\.simulate\.Trajectory"),
    (lambda: simulate.ideal_imu(TRAJ, np.zeros((3, 2))), r"t must be a 1-D array"),
    (lambda: simulate.true_states(TRAJ, np.array([0.0, np.inf])), r"t contains non-finite"),
    (lambda: simulate.ideal_imu(TRAJ, np.zeros(3), gravity=-9.81), r"gravity = -9\.81 is a magnitude"),
    (lambda: simulate.add_noise(jax.random.PRNGKey(0), np.zeros((3, 2)), np.zeros((3, 3)), 0.01,
                                ImuNoise.euroc()), r"gyro must have shape \(\.\.\., T, 3\)"),
    (lambda: simulate.add_noise(jax.random.PRNGKey(0), np.zeros((3, 3)), np.zeros((3, 3)), 0.0,
                                ImuNoise.euroc()), r"dt must be positive and finite"),
    (lambda: simulate.add_noise(jax.random.PRNGKey(0), np.zeros((3, 3)), np.zeros((3, 3)), 0.01,
                                ImuNoise.euroc(), gyro_misalignment=np.zeros(3)),
     r"gyro_misalignment must have shape \(3, 3\)"),
])
def test_simulate_parameters_outside_their_domain(call, message):
    with pytest.raises(ValueError, match=message):
        call()


@pytest.mark.parametrize("call,message", [
    (lambda: jaximu.io.gravity_alignment(np.zeros(3)), r"accel_mean must be a finite, non-zero"),
    (lambda: jaximu.io.gravity_alignment([0.0, np.nan, 9.8]), r"accel_mean must be a finite"),
    (lambda: simulate.add_noise(jax.random.PRNGKey(0), np.zeros((3, 3)), np.zeros((3, 3)), 0.01,
                                ImuNoise.euroc(), b_g0=np.zeros(2)),
     r"b_g0 must be a scalar or have shape \(\.\.\., 3\)"),
])
def test_io_and_simulate_helpers_name_their_arguments(call, message):
    with pytest.raises(ValueError, match=message):
        call()


# --------------------------------------------------------------------------- jaximu.recording


def _recording_args(**kw):
    data = jaximu.io.from_arrays(np.arange(5) * 0.01, np.zeros((5, 3)),
                                 np.tile([0.0, 0.0, 9.81], (5, 1)))
    args = dict(data=data, state0=NavState.identity(), P0=np.eye(15) * 1e-4,
                noise=ImuNoise.euroc(), scheme="midpoint", dtype=jnp.float32)
    args.update(kw)
    return args


@pytest.mark.parametrize("kw,message", [
    ({"scheme": "rk5"}, r"unknown scheme 'rk5'"),
    ({"chunk": 0}, r"chunk must be a positive integer, got 0"),
    ({"dtype": np.float16}, r"dtype must be a floating dtype \(float32 or float64\)"),
    ({"gravity": -9.81}, r"gravity = -9\.81 is a magnitude"),
    ({"P0": -np.eye(15)}, r"P0"),
])
def test_propagate_recording_names_its_arguments(kw, message):
    from jaximu.recording import propagate_recording

    with pytest.raises(ValueError, match=message):
        propagate_recording(**_recording_args(**kw))


def test_run_demo_checks_before_the_work(tmp_path):
    from jaximu.errors import Fix, InputError
    from jaximu.recording import run_demo

    with pytest.raises(InputError, match=r"seconds=100: the bundled excerpt holds 20 s") as err:
        run_demo(100.0, plot=None)
    assert err.value.fixes == (Fix("seconds", 20.0),)
    for bad in (0.0, -1.0, np.nan):
        with pytest.raises(ValueError, match=r"seconds must be positive and finite"):
            run_demo(bad, plot=None)
    with pytest.raises(ValueError, match=r"unknown scheme 'rk5'"):
        run_demo(1.0, scheme="rk5", plot=None)
    with pytest.raises(ValueError, match=r"the folder .*missing does not exist"):
        run_demo(1.0, plot=str(tmp_path / "missing" / "demo.png"))
    with pytest.raises(ValueError, match=r"is a folder"):
        run_demo(1.0, plot=str(tmp_path))


def test_so3_of_integer_lists_is_computed_in_floats():
    """A ROS-style quaternion typed as integers is a rotation, not integer arithmetic."""
    q = so3.quat_mul([1, 0, 0, 0], [0, 1, 0, 0])
    assert jnp.issubdtype(q.dtype, jnp.floating)
    np.testing.assert_allclose(q, [0, 1, 0, 0])
    R = so3.quat_to_matrix([0, 0, 0, 1])  # 180° about z
    np.testing.assert_allclose(R, Rotation.from_quat([0, 0, 1, 0]).as_matrix(), atol=1e-6)
    np.testing.assert_allclose(so3.exp([0, 0, 0]), [1, 0, 0, 0])
