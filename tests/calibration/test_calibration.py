"""Calibration: recovery within the predicted uncertainty, exact gradients,
one compilation for the fit, loud failures on wrong units and frames.

References: the simulated truth (biases, scale, misalignment, gravity and time offset drawn
into the samples by ``simulate.add_noise``), central finite differences, and two independent
code paths for the residual (preintegration and propagation).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu import calibration as cal
from jaximu import simulate as sim

RATE = 200.0
SECONDS = 20.0
NOISE = jaximu.ImuNoise.euroc()
WHITE = jaximu.ImuNoise(NOISE.gyroscope_noise_density, NOISE.accelerometer_noise_density, 0.0, 0.0)
TRAJ = sim.lissajous(attitude_amplitude=(0.8, 0.6, 1.5), attitude_frequency=(0.31, 0.23, 0.13))
S_G = np.array([[0.01, 0, 0], [0.003, -0.005, 0], [-0.002, 0.004, 0.008]])
S_A = np.array([[-0.006, 0, 0], [0.002, 0.01, 0], [0.003, -0.004, 0.004]])


def simulate_data(seed, b_g, b_a, S_g=None, S_a=None, time_offset=0.0, gravity=9.81):
    """IMU stamps on the IMU clock; reference (100 Hz, pose and velocity) on its own clock."""
    t_imu = np.arange(int(SECONDS * RATE) + 1) / RATE
    t_true = t_imu + time_offset  # the instant each IMU sample was taken, reference clock
    gyro, accel = sim.ideal_imu(TRAJ, jnp.asarray(t_true), gravity=gravity)
    gm, am, _ = sim.add_noise(
        jax.random.key(seed),
        gyro,
        accel,
        1 / RATE,
        WHITE,
        b_g0=b_g,
        b_a0=b_a,
        gyro_misalignment=S_g,
        accel_misalignment=S_a,
    )
    t_ref = np.arange(-0.5, SECONDS + 0.5, 0.01)
    truth = sim.true_states(TRAJ, jnp.asarray(t_ref))
    ref = cal.Reference(t_ref, np.asarray(truth.q), np.asarray(truth.p), np.asarray(truth.v))
    return t_imu, np.asarray(gm), np.asarray(am), ref


def problem_for(t, gm, am, ref, **kw):
    kw = dict(dict(scheme="midpoint", model="propagation", reference_sigma=(0, 0, 0)), **kw)
    return cal.calibration_problem(t, gm, am, ref, NOISE, **kw)


def within(res, truth, n_sigma=3.0):
    for name, want in truth.items():
        est = np.asarray(getattr(res.calibration, name))
        std = np.asarray(getattr(res.std, name))
        assert np.all(std > 0), name
        assert np.all(np.abs(est - want) < n_sigma * std), (name, est, want, std)


def test_recovers_biases_within_predicted_uncertainty_and_compiles_once():
    """Three seeds; 6 components each within 3σ of the Laplace covariance (each check
    fails by chance with probability 0.27% when the covariance is right). The reduced χ²
    at the estimate lies in its 99.9% interval, and the residuals-and-Jacobian function of the
    default optimiser (Levenberg–Marquardt) compiles once."""
    rng = np.random.default_rng(0)
    sizes = []
    for seed in range(3):
        b_g = rng.normal(0, 0.005, 3)
        b_a = rng.normal(0, 0.1, 3)
        prob = problem_for(*simulate_data(seed, b_g, b_a))
        res = cal.calibrate(prob)
        sizes.append(cal._residuals_jacobian_compiled(prob)._cache_size())
        assert res.converged
        within(res, {"b_g": b_g, "b_a": b_a})
        assert np.asarray(res.std.b_g).max() < 1e-4 and np.asarray(res.std.b_a).max() < 1e-3
        lo, hi = jaximu.montecarlo.chi2_interval(res.dof, 0.999)
        assert lo < res.chi2 < hi, (res.chi2, res.dof)
        assert np.all(np.asarray(res.std.gyro_scale) == 0)  # not estimated
    assert sizes[0] == sizes[1] == sizes[2], sizes  # no retracing for new data of one shape


def test_recovers_all_intrinsics_time_offset_and_gravity():
    b_g, b_a = np.array([0.003, -0.002, 0.004]), np.array([0.05, -0.08, 0.1])
    data = simulate_data(11, b_g, b_a, S_G, S_A, time_offset=0.004, gravity=9.805)
    res = cal.calibrate(problem_for(*data), estimate=cal.FIELDS, steps=300)
    within(
        res,
        {
            "b_g": b_g,
            "b_a": b_a,
            "gyro_scale": np.diag(S_G),
            "accel_scale": np.diag(S_A),
            "gyro_misalignment": S_G[[1, 2, 2], [0, 0, 1]],
            "accel_misalignment": S_A[[1, 2, 2], [0, 0, 1]],
            "gravity": 9.805,
            "time_offset": 0.004,
        },
    )
    # Informative, not a trivially wide covariance.
    assert float(res.std.time_offset) < 1e-4 and float(res.std.gravity) < 0.01
    assert np.asarray(res.std.gyro_scale).max() < 2e-4
    assert 0.7 < res.reduced_chi2 < 1.4


def test_reference_without_velocities_estimates_them_as_nuisance():
    """Poses only (motion capture): keyframe velocities join the unknowns; the biases are
    still recovered within their (now marginal) 3σ, and the velocities near the truth."""
    b_g, b_a = np.array([0.004, 0.002, -0.003]), np.array([0.06, -0.04, 0.09])
    t, gm, am, ref = simulate_data(8, b_g, b_a)
    poses = cal.Reference(ref.t, ref.q, ref.p)
    prob = problem_for(t, gm, am, poses)
    res = cal.calibrate(prob)
    within(res, {"b_g": b_g, "b_a": b_a})
    t_key = t[0] + np.arange(prob.n_windows + 1) * 0.5
    v_true = np.asarray(sim.true_states(TRAJ, jnp.asarray(t_key)).v)
    assert np.abs(res.velocities - v_true).max() < 0.01
    # The velocity columns of the Jacobian (6 tangents per window, scattered to its two
    # keyframes) against central differences of the residuals in three keyframe velocities.
    layout = cal._Layout(("b_g", "b_a"), prob.velocities.size)
    init_vec = cal._flatten(cal.ImuCalibration.default(dtype=jnp.float64))
    z = jnp.asarray(np.random.default_rng(1).normal(0, 0.3, 6 + layout.n_velocity))
    _, J = cal._residuals_jacobian(z, prob, init_vec, layout=layout)
    res_of = jax.jit(
        lambda z_: cal.calibration_residuals(
            prob, *cal._unpack(z_, init_vec, prob.velocities, layout)
        ).reshape(-1)
    )
    for col in (6 + 0, 6 + 3 * 7 + 2, 6 + layout.n_velocity - 1):  # first, inner, last
        e = np.zeros(len(z))
        e[col] = 1e-4
        fd = (np.asarray(res_of(z + e)) - np.asarray(res_of(z - e))) / 2e-4
        np.testing.assert_allclose(
            np.asarray(J)[:, col], fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max()
        )
        assert np.count_nonzero(np.asarray(J)[:, col]) <= 18  # only the windows it bounds
    with_v = cal.calibrate(problem_for(t, gm, am, ref))
    assert np.all(np.asarray(res.std.b_a) > np.asarray(with_v.std.b_a))  # less information


def test_adam_and_levenberg_marquardt_reach_the_lbfgs_optimum():
    b_g, b_a = np.array([0.002, 0.001, -0.003]), np.array([-0.05, 0.03, 0.07])
    prob = problem_for(*simulate_data(5, b_g, b_a))
    a = cal.calibrate(prob, optimizer="lbfgs")
    lm = cal.calibrate(prob)  # the default
    assert lm.converged and len(lm.loss_history) < 10
    for name in ("b_g", "b_a"):
        np.testing.assert_allclose(
            np.asarray(getattr(lm.calibration, name)),
            np.asarray(getattr(a.calibration, name)),
            atol=0.01 * float(np.asarray(getattr(a.std, name)).min()),
        )
        np.testing.assert_allclose(
            np.asarray(getattr(lm.std, name)), np.asarray(getattr(a.std, name)), rtol=1e-3
        )
    assert lm.chi2 <= a.chi2 * (1 + 1e-9)
    b = cal.calibrate(prob, optimizer="adam", learning_rate=0.05, steps=2000, tol=1e-12)
    np.testing.assert_allclose(
        np.asarray(b.calibration.b_g),
        np.asarray(a.calibration.b_g),
        atol=0.05 * float(np.asarray(a.std.b_g).min()),
    )
    np.testing.assert_allclose(
        np.asarray(b.calibration.b_a),
        np.asarray(a.calibration.b_a),
        atol=0.05 * float(np.asarray(a.std.b_a).min()),
    )
    assert b.loss_history[-1] <= a.loss_history[-1] * (1 + 1e-6)


@pytest.fixture(scope="module")
def full_problem():
    b_g, b_a = np.array([0.003, -0.002, 0.004]), np.array([0.05, -0.08, 0.1])
    return problem_for(*simulate_data(2, b_g, b_a, S_G, S_A, time_offset=0.0013))


def test_loss_gradient_matches_finite_differences(full_problem):
    calib = cal.ImuCalibration.default(
        dtype=jnp.float64,
        b_g=[0.002, -0.001, 0.003],
        b_a=[0.04, -0.05, 0.08],
        gyro_scale=[0.005, -0.002, 0.004],
        gyro_misalignment=[0.001, -0.002, 0.003],
        accel_scale=[-0.003, 0.006, 0.002],
        accel_misalignment=[0.001, 0.002, -0.002],
        gravity=9.80,
        time_offset=0.0021,
    )  # off the reference's 10 ms grid (a kink there)
    loss = jax.jit(cal.calibration_loss)
    grad = jax.jit(jax.grad(cal.calibration_loss, argnums=1))(full_problem, calib)
    for name in cal.FIELDS:
        g = np.atleast_1d(np.asarray(getattr(grad, name)))
        x0 = np.atleast_1d(np.asarray(getattr(calib, name), np.float64))
        h = 1e-4 * cal.SCALES[name]
        for i in range(len(x0)):
            xp, xm = x0.copy(), x0.copy()
            xp[i] += h
            xm[i] -= h
            shape = np.shape(getattr(calib, name))
            fp = loss(full_problem, dataclasses.replace(calib, **{name: xp.reshape(shape)}))
            fm = loss(full_problem, dataclasses.replace(calib, **{name: xm.reshape(shape)}))
            fd = (float(fp) - float(fm)) / (2 * h)
            np.testing.assert_allclose(
                g[i], fd, rtol=2e-5, atol=1e-6 * abs(fd) + 1e-3, err_msg=f"{name}[{i}]"
            )


def test_preintegration_and_propagation_residuals_agree():
    """The same residual by two code paths: preintegrate + residual, and propagate_final
    from the reference state (equal for Euler; the two midpoint rules differ at O(dt²):
    VINS-Mono's first-order quaternion against the exact exponential)."""
    b_g, b_a = np.array([0.003, -0.002, 0.004]), np.array([0.05, -0.08, 0.1])
    data = simulate_data(4, b_g, b_a, S_G, S_A)
    prop = problem_for(*data, scheme="euler")
    pre = dataclasses.replace(prop, model="preintegration")
    calib = cal.ImuCalibration.default(
        dtype=jnp.float64, b_g=b_g, b_a=b_a, gyro_scale=np.diag(S_G), time_offset=0.0013
    )
    r_prop = np.asarray(jax.jit(cal.calibration_residuals)(prop, calib))
    r_pre = np.asarray(jax.jit(cal.calibration_residuals)(pre, calib))
    assert r_prop.shape == (prop.n_windows, 9)
    np.testing.assert_allclose(r_pre, r_prop, rtol=1e-9, atol=1e-9 * np.abs(r_prop).max())


def test_checkpointed_groups_bound_gradient_memory(full_problem):
    """Groups of windows under jax.checkpoint: the gradient's temporary memory is that of
    one group (compiled memory analysis), and the gradient is the same."""
    t, gm, am, ref = simulate_data(2, np.zeros(3), np.zeros(3))
    calib = cal.ImuCalibration.default(dtype=jnp.float64)
    out = {}
    for per_group in (4, 40):
        prob = problem_for(t, gm, am, ref, windows_per_group=per_group)
        f = jax.jit(jax.grad(cal.calibration_loss, argnums=1))
        comp = f.lower(prob, calib).compile()
        out[per_group] = (comp.memory_analysis().temp_size_in_bytes, comp(prob, calib))
    assert out[4][0] < 0.5 * out[40][0], (out[4][0], out[40][0])
    np.testing.assert_allclose(np.asarray(out[4][1].b_g), np.asarray(out[40][1].b_g), rtol=1e-9)


@pytest.mark.parametrize(
    "mistake, message",
    [
        ("gyro_degrees", "deg/s"),
        ("accel_in_g", "in g"),
        ("imu_rotated", "axes do not match"),
        ("quaternion_xyzw", "axes do not match"),
    ],
)
def test_wrong_units_and_frames_fail_loudly(mistake, message):
    t, gm, am, ref = simulate_data(3, np.array([0.003, 0, 0]), np.array([0.05, 0, 0]))
    if mistake == "gyro_degrees":
        gm = np.degrees(gm)
    elif mistake == "accel_in_g":
        am = am / 9.81
    elif mistake == "imu_rotated":  # IMU mounted 90° about z from the reference's body
        Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
        gm, am = gm @ Rz.T, am @ Rz.T
    else:
        ref = cal.Reference(ref.t, ref.q[:, [1, 2, 3, 0]], ref.p, ref.v)
    with pytest.raises(cal.CalibrationError, match=message):
        problem_for(t, gm, am, ref)


def test_bad_arguments_are_named():
    t, gm, am, ref = simulate_data(3, np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="strictly"):
        problem_for(t[::-1], gm, am, ref)
    with pytest.raises(ValueError, match="unknown model"):
        problem_for(t, gm, am, ref, model="ekf")
    with pytest.raises(ValueError, match="not unit"):
        problem_for(t, gm, am, cal.Reference(ref.t, 2 * ref.q, ref.p, ref.v))
    prob = problem_for(t, gm, am, ref)
    with pytest.raises(ValueError, match="unknown calibration fields"):
        cal.calibrate(prob, estimate=("bias",))
    with pytest.raises(ValueError, match="unknown optimizer"):
        cal.calibrate(prob, optimizer="sgd")
