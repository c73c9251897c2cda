"""The IMU's pose on the body (body_P_sensor): against exact simulated signals (autodiff of
the sensor's own trajectory), closed forms, GTSAM's body_P_sensor, numpy's gradient and
finite differences; bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _shared import SEG, central_difference_phi, euroc_window
from scipy.spatial.transform import Rotation

import jaximu
from jaximu import simulate as sim
from jaximu.sensor import SensorPose

try:
    import gtsam
except ImportError:
    gtsam = None
needs_gtsam = pytest.mark.skipif(gtsam is None, reason="gtsam is not installed")

NOISE = jaximu.ImuNoise.euroc()
R_BS = Rotation.from_rotvec([0.3, -0.5, 0.4])  # 40°
P_BS = np.array([0.3, -0.2, 0.15])  # |r| = 0.39 m
POSE = SensorPose.from_rotation(R_BS.as_matrix(), P_BS)


def fast_rotation():
    """Rates up to ~5 rad/s about every axis, changing (α up to ~25 rad/s²)."""
    return sim.lissajous(
        amplitude=(1.0, 0.8, 0.4),
        frequency=(0.3, 0.4, 0.5),
        attitude_amplitude=(0.8, 0.6, 1.5),
        attitude_frequency=(0.7, 0.9, 0.5),
    )


def test_ideal_imu_of_an_offset_sensor_on_a_circle_is_the_closed_form():
    """Level circle at yaw rate Ω: a sensor at r = (0.5, 0.2, 0) (R_BS = I) adds the
    centripetal -Ω² r to the body's (0, vΩ, g); rotated by R_BS its axes turn with it."""
    t = jnp.linspace(0.0, 10.0, 21)
    traj = sim.circle(radius=5.0, speed=2.0)
    Om = 0.4
    r = np.array([0.5, 0.2, 0.0])
    gyro, accel = sim.ideal_imu(traj, t, body_P_sensor=SensorPose.from_rotation(np.eye(3), r))
    np.testing.assert_allclose(gyro, np.tile([0, 0, Om], (21, 1)), rtol=0, atol=1e-12)
    expect = np.array([0, 2.0 * Om, 9.81]) - Om**2 * r
    np.testing.assert_allclose(accel, np.tile(expect, (21, 1)), rtol=0, atol=1e-12)
    R = Rotation.from_euler("z", 90, degrees=True)
    gyro, accel = sim.ideal_imu(traj, t, body_P_sensor=SensorPose.from_rotation(R.as_matrix(), r))
    np.testing.assert_allclose(accel, np.tile(R.inv().apply(expect), (21, 1)), atol=1e-12)
    np.testing.assert_allclose(gyro, np.tile(R.inv().apply([0, 0, Om]), (21, 1)), atol=1e-12)


def test_to_body_recovers_the_body_signals_of_a_fast_rotating_body():
    """The transformation of exact sensor signals gives the body's signals to the accuracy
    of α from central differences (second order: the error falls 4x when dt halves)."""
    traj = fast_rotation()
    errs = []
    for dt in (0.004, 0.002):
        t = jnp.arange(0.0, 0.4, dt)
        w_b, f_b = sim.ideal_imu(traj, t)
        w_s, f_s = sim.ideal_imu(traj, t, body_P_sensor=POSE)
        gb, ab = jaximu.sensor.to_body(POSE, w_s, f_s, dt, jnp.zeros(3))
        np.testing.assert_allclose(gb, w_b, rtol=0, atol=1e-12)
        errs.append(np.abs(np.asarray(ab - f_b))[2:-2].max())  # interior samples
    assert errs[0] / errs[1] == pytest.approx(4.0, rel=0.1), errs


def test_angular_acceleration_is_numpys_second_order_gradient_on_an_uneven_grid():
    rng = np.random.default_rng(3)
    dt = rng.uniform(0.004, 0.006, 40)
    t = np.concatenate([[0.0], np.cumsum(dt[:-1])])
    w = rng.normal(size=(40, 3))
    ref = np.gradient(w, t, axis=0, edge_order=1)
    np.testing.assert_allclose(
        jaximu.sensor.angular_acceleration(jnp.asarray(w), dt), ref, rtol=1e-12, atol=1e-12
    )
    # dt of T-1 intervals: the same grid
    np.testing.assert_allclose(
        jaximu.sensor.angular_acceleration(jnp.asarray(w), dt[:-1]), ref, rtol=1e-12, atol=1e-12
    )


T_END = 0.6
DTS = (0.004, 0.002)


@pytest.fixture(scope="module")
def sensor_signals():
    """Exact sensor samples of :func:`fast_rotation` at two rates, and the true end state."""
    traj = fast_rotation()
    truth = sim.true_states(traj, jnp.array([0.0, T_END]))
    x0 = jaximu.NavState(truth.q[0], truth.p[0], truth.v[0], jnp.zeros(3), jnp.zeros(3))
    out = {}
    for dt in DTS:
        n = int(round(T_END / dt))
        gyro, accel = sim.ideal_imu(traj, jnp.asarray(dt * np.arange(n + 1)), body_P_sensor=POSE)
        out[dt] = (gyro, accel, jnp.full(n, dt))  # n intervals between n + 1 samples
    return x0, np.asarray(truth.p[1]), out


def _errors(sig, scheme, pose, **kw):
    x0, p_end, data = sig
    return [
        float(
            np.linalg.norm(
                np.asarray(
                    jaximu.propagate_final(x0, *data[dt], scheme, body_P_sensor=pose, **kw).p
                )
                - p_end
            )
        )
        for dt in DTS
    ]


@pytest.mark.parametrize("scheme,order", [("euler", 1), ("midpoint", 2), ("rk4", 2)])
def test_lever_arm_correction_converges_at_the_schemes_order(scheme, order, sensor_signals):
    """Sensor 0.39 m from the body origin, rotated 40°, on a body turning at up to 5 rad/s:
    with the correction the position error against the exact trajectory falls at the
    scheme's order (2^order when dt halves); rotating the samples alone (no lever arm), or
    dropping α×r (GTSAM's model), leaves an error that does not fall."""
    good = _errors(sensor_signals, scheme, POSE)
    assert abs(np.log2(good[0] / good[1]) - order) < 0.3, good
    bad = _errors(sensor_signals, scheme, SensorPose(POSE.q, jnp.zeros(3)))
    assert bad[1] > 0.8 * bad[0] and bad[1] > 100 * good[1], (bad, good)
    radial = _errors(sensor_signals, scheme, POSE, tangential=False)
    assert radial[1] > 0.8 * radial[0] and radial[1] > 10 * good[1], (radial, good)


# --------------------------------------------------------------------------- GTSAM

window = euroc_window


def gtsam_pim(gyro, accel, dt, bias, pose=None):
    p = gtsam.PreintegrationParams.MakeSharedU(9.81)
    p.setGyroscopeCovariance(np.eye(3) * NOISE.gyroscope_noise_density**2)
    p.setAccelerometerCovariance(np.eye(3) * NOISE.accelerometer_noise_density**2)
    p.setIntegrationCovariance(np.zeros((3, 3)))
    if pose is not None:
        p.setBodyPSensor(gtsam.Pose3(gtsam.Rot3(np.asarray(pose.R)), np.asarray(pose.p)))
    b = gtsam.imuBias.ConstantBias(np.asarray(bias.b_a), np.asarray(bias.b_g))
    pim = gtsam.PreintegratedImuMeasurementsManifold(p, b)
    for k in range(len(dt)):
        pim.integrateMeasurement(accel[k], gyro[k], dt[k])
    return pim


@needs_gtsam
@pytest.mark.parametrize("start,length", [(6.3, 0.2), (10.0, 1.0)])
def test_preintegrate_with_body_P_sensor_equals_gtsam(start, length):
    """GTSAM's PreintegratedImuMeasurementsManifold with body_P_sensor (rotation and lever
    arm) on real EuRoC samples: deltas to 1e-9 with tangential=False (GTSAM's model), and
    predict (at the linearisation bias) to 1e-9."""
    k0, gyro, accel, dt, bias = window(start, length)
    ref = gtsam_pim(gyro, accel, dt, bias, POSE)
    pim = jaximu.preintegrate(gyro, accel, dt, bias, NOISE, body_P_sensor=POSE, tangential=False)
    np.testing.assert_allclose(pim.delta_R, ref.deltaRij().matrix(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(pim.delta_v, ref.deltaVij(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(pim.delta_p, ref.deltaPij(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(pim.bias_hat.b_g, bias.b_g, rtol=0, atol=0)
    q0 = SEG.q_gt[k0] / np.linalg.norm(SEG.q_gt[k0])
    state = jaximu.NavState(
        *(jnp.asarray(x) for x in (q0, SEG.p_gt[k0], SEG.v_gt[k0], bias.b_g, bias.b_a))
    )
    nav = gtsam.NavState(gtsam.Rot3.Quaternion(*q0), SEG.p_gt[k0], SEG.v_gt[k0])
    pred = ref.predict(nav, gtsam.imuBias.ConstantBias(np.asarray(bias.b_a), np.asarray(bias.b_g)))
    ours = jaximu.predict(state, pim)
    np.testing.assert_allclose(ours.R, pred.attitude().matrix(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours.p, pred.position(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours.v, pred.velocity(), rtol=0, atol=1e-9)


@needs_gtsam
def test_tangential_term_is_gtsams_model_plus_alpha_cross_r_from_numpy_gradient():
    """GTSAM omits α×r. Feeding GTSAM samples from which α×r (α from numpy's gradient of the
    body rate) was removed gives ours with tangential=True, to 1e-9; and the term matters on
    real flight data (Δv differs by far more than that)."""
    k0, gyro, accel, dt, bias = window(8.0, 0.5)
    R = np.asarray(POSE.R)
    t = np.concatenate([[0.0], np.cumsum(dt[:-1])])
    alpha = np.gradient(gyro @ R.T, t, axis=0, edge_order=1)
    accel_ref = accel - np.cross(alpha, P_BS) @ R  # R_BSᵀ (α × r), in S
    ref = gtsam_pim(gyro, accel_ref, dt, bias, POSE)
    pim = jaximu.preintegrate(gyro, accel, dt, bias, NOISE, body_P_sensor=POSE)
    np.testing.assert_allclose(pim.delta_v, ref.deltaVij(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(pim.delta_p, ref.deltaPij(), rtol=0, atol=1e-9)
    without = jaximu.preintegrate(
        gyro, accel, dt, bias, NOISE, body_P_sensor=POSE, tangential=False
    )
    assert np.abs(np.asarray(without.delta_v - pim.delta_v)).max() > 1e-4


@needs_gtsam
@pytest.mark.parametrize(
    "lever,jacobians,method",
    [
        (False, "analytic", "sequential"),
        (True, "analytic", "sequential"),
        (True, "autodiff", "parallel"),
    ],
)
def test_covariance_of_a_sensor_at_a_pose_equals_gtsam(lever, jacobians, method):
    """preintMeasCov in GTSAM's chart to 1e-8 relative (isotropic densities, GTSAM's model:
    tangential=False). With a lever arm the gyro noise also moves the body's specific force
    through ω×(ω×r) (GTSAM's D_correctedAcc_measuredOmega), a visible part of the result."""
    _, gyro, accel, dt, bias = window(10.0, 1.0)
    pose = POSE if lever else SensorPose(POSE.q, jnp.zeros(3))
    ref = gtsam_pim(gyro, accel, dt, bias, pose).preintMeasCov()
    pim = jaximu.preintegrate(
        gyro,
        accel,
        dt,
        bias,
        NOISE,
        body_P_sensor=pose,
        tangential=False,
        jacobians=jacobians,
        method=method,
    )
    np.testing.assert_allclose(pim.covariance("gtsam"), ref, rtol=0, atol=1e-8 * np.abs(ref).max())
    if lever:  # the lever arm's part is far above the tolerance
        no_lever = gtsam_pim(gyro, accel, dt, bias, SensorPose(POSE.q, jnp.zeros(3)))
        assert np.abs(no_lever.preintMeasCov() - ref).max() > 1e-4 * np.abs(ref).max()


@pytest.mark.parametrize("scheme,jacobians", [("euler", "analytic"), ("midpoint", "autodiff")])
def test_bias_jacobians_of_a_sensor_at_a_pose_are_sensor_frame_derivatives(scheme, jacobians):
    """∂Δ/∂b with the bias in the sensor frame: central finite differences of re-integration
    at b ± ε e_i, rotation and lever arm (a gyro bias also moves ω×(ω×r))."""
    _, gyro, accel, dt, bias = window(6.3, 0.2)
    pim = jaximu.preintegrate(
        gyro, accel, dt, bias, scheme=scheme, jacobians=jacobians, body_P_sensor=POSE
    )
    eps = 1e-6
    for i in range(3):
        e = np.eye(3)[i] * eps
        out = []
        for s in (1, -1):
            b = jaximu.ImuBias(bias.b_g + s * e, bias.b_a + s * e)
            out.append(jaximu.preintegrate(gyro, accel, dt, b, scheme=scheme, body_P_sensor=POSE))
        dv = (out[0].delta_v - out[1].delta_v) / (2 * eps)
        np.testing.assert_allclose(dv, pim.dv_dbg[:, i] + pim.dv_dba[:, i], rtol=0, atol=1e-6)
        dp = (out[0].delta_p - out[1].delta_p) / (2 * eps)
        np.testing.assert_allclose(dp, pim.dp_dbg[:, i] + pim.dp_dba[:, i], rtol=0, atol=1e-6)


# --------------------------------------------------------------------------- covariance


def _offset_sensor_on_a_fast_body(n=60, dt=0.005):
    traj = fast_rotation()
    t = jnp.asarray(dt * np.arange(n))
    gyro, accel = sim.ideal_imu(traj, t, body_P_sensor=POSE)
    x0 = sim.true_states(traj, t[:1])
    x0 = jaximu.NavState(
        x0.q[0], x0.p[0], x0.v[0], jnp.array([0.01, -0.02, 0.005]), jnp.array([0.1, 0.0, -0.05])
    )
    return x0, gyro, accel, dt


@pytest.mark.parametrize(
    "scheme,jacobians", [("euler", "analytic"), ("midpoint", "autodiff"), ("rk4", "analytic")]
)
def test_propagate_covariance_of_a_sensor_at_a_pose_is_phi_phit(scheme, jacobians):
    """Zero noise, P0 = I: the covariance is Φ Φᵀ with Φ by central finite differences of
    propagate_final in the 15 error directions (bias errors in S), sensor rotated and at a
    lever arm on a fast-turning body (a gyro bias moves ω×(ω×r) too). The batched kernel
    (final state) and the generic one (every state) agree to 1e-12."""
    x0, gyro, accel, dt = _offset_sensor_on_a_fast_body()
    zero = jaximu.ImuNoise(0.0, 0.0, 0.0, 0.0)
    _, P = jaximu.propagate_covariance_final(
        x0, jnp.eye(15), gyro, accel, dt, zero, scheme, body_P_sensor=POSE, jacobians=jacobians
    )
    run = jax.jit(lambda x: jaximu.propagate_final(x, gyro, accel, dt, scheme, body_P_sensor=POSE))
    Phi = central_difference_phi(run, x0)
    ref = Phi @ Phi.T
    np.testing.assert_allclose(P, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    _, P_all = jaximu.propagate_covariance(
        x0, jnp.eye(15), gyro, accel, dt, zero, scheme, body_P_sensor=POSE, jacobians=jacobians
    )
    np.testing.assert_allclose(P_all[-1], P, rtol=0, atol=1e-12 * np.abs(P).max())


def test_gyro_noise_of_a_sensor_at_a_lever_arm_reaches_the_velocity():
    """Euler, white noise only, GTSAM's model (tangential=False): the covariance is
    Σ_k J_k diag(σ²/dt) J_kᵀ with J_k the derivative of the final error state with respect
    to raw sample k (jax.jacfwd through the sensor-to-body transformation of the mean, not
    the covariance kernels), to 1e-12, for both Jacobian options; the gyro noise moving
    ω×(ω×r) is a visible part of it."""
    x0, gyro, accel, dt = _offset_sensor_on_a_fast_body(40)
    noise = jaximu.ImuNoise(2e-2, 2e-3, 0.0, 0.0)
    sg2, sa2 = noise.gyroscope_noise_density**2 / dt, noise.accelerometer_noise_density**2 / dt
    nominal = jaximu.propagate_final(x0, gyro, accel, dt, body_P_sensor=POSE, tangential=False)

    def error(g, a, pose=POSE):
        out = jaximu.propagate_final(x0, g, a, dt, body_P_sensor=pose, tangential=False)
        return jaximu.boxminus(out, nominal)

    Jg, Ja = (J.reshape(15, -1) for J in jax.jit(jax.jacfwd(error, argnums=(0, 1)))(gyro, accel))
    ref = sg2 * Jg @ Jg.T + sa2 * Ja @ Ja.T
    for jacobians in ("analytic", "autodiff"):
        _, P = jaximu.propagate_covariance_final(
            x0,
            jnp.zeros((15, 15)),
            gyro,
            accel,
            dt,
            noise,
            body_P_sensor=POSE,
            jacobians=jacobians,
            tangential=False,
        )
        np.testing.assert_allclose(
            P, ref, rtol=0, atol=1e-12 * np.abs(ref).max(), err_msg=jacobians
        )
    # the same samples already in the body frame, the rate not moving the specific force:
    # what the covariance was without the coupling
    gyro_b, accel_b = jaximu.sensor.to_body(POSE, gyro, accel, dt, x0.b_g, tangential=False)
    x0_b = jaximu.NavState(x0.q, x0.p, x0.v, POSE.R @ x0.b_g, POSE.R @ x0.b_a)
    nominal_b = jaximu.propagate_final(x0_b, gyro_b, accel_b, dt)
    Jg_b = jax.jit(
        jax.jacfwd(
            lambda g: jaximu.boxminus(jaximu.propagate_final(x0_b, g, accel_b, dt), nominal_b)
        )
    )(gyro_b).reshape(15, -1)
    uncoupled = sg2 * Jg_b @ Jg_b.T + sa2 * Ja @ Ja.T
    assert np.abs(uncoupled - ref)[:9, :9].max() > 1e-3 * np.abs(ref).max()


def test_vins_midpoint_covariance_of_a_sensor_at_a_lever_arm_is_near_the_exact_one():
    """VINS-Mono's first-order midpoint (jacobians='analytic') with the lever arm's coupling
    against the exact derivatives (jacobians='autodiff'): within VINS's own linearisation
    error (2e-4 relative on this window without a lever arm), while the coupling moves the
    covariance by ~2e-2 (a large gyro density makes it dominant)."""
    _, gyro, accel, dt, bias = window(10.0, 1.0)
    noise = jaximu.ImuNoise(2e-2, 2e-3, 0.0, 0.0)
    a, b = (
        jaximu.preintegrate(
            gyro, accel, dt, bias, noise, "midpoint", jacobians=j, body_P_sensor=POSE
        )
        for j in ("analytic", "autodiff")
    )
    for f in ("transition", "cov15"):
        x, y = np.asarray(getattr(a, f)), np.asarray(getattr(b, f))
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-3 * np.abs(y).max(), err_msg=f)
    rotated = jaximu.preintegrate(
        gyro,
        accel,
        dt,
        bias,
        noise,
        "midpoint",
        jacobians="autodiff",
        body_P_sensor=SensorPose(POSE.q, jnp.zeros(3)),
    )
    assert np.abs(np.asarray(rotated.cov15 - b.cov15)).max() > 1e-2 * np.abs(b.cov15).max()


# --------------------------------------------------------------------------- transforms


def test_grad_through_the_lever_arm_and_vmap_and_float32():
    """Differentiable in p_BS (gradient equals central differences); a vmap over sensor
    poses equals the loop; float32 inputs run in float32."""
    traj = fast_rotation()
    t = jnp.asarray(0.005 * np.arange(20))
    gyro, accel = sim.ideal_imu(traj, t, body_P_sensor=POSE)
    x0 = jaximu.NavState.identity(dtype=jnp.float64)

    @jax.jit
    def f(p):
        return jaximu.propagate_final(
            x0, gyro, accel, 0.005, body_P_sensor=SensorPose(POSE.q, p)
        ).p[0]

    g = jax.grad(f)(jnp.asarray(P_BS))
    eps = 1e-6
    fd = [(f(P_BS + eps * e) - f(P_BS - eps * e)) / (2 * eps) for e in np.eye(3)]
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-9)
    ps = jnp.asarray(np.stack([P_BS, 2 * P_BS, -P_BS]))
    batched = jax.vmap(
        lambda p: (
            jaximu.propagate_final(x0, gyro, accel, 0.005, body_P_sensor=SensorPose(POSE.q, p)).p
        )
    )(ps)
    for k in range(3):
        one = jaximu.propagate_final(
            x0, gyro, accel, 0.005, body_P_sensor=SensorPose(POSE.q, ps[k])
        ).p
        np.testing.assert_allclose(batched[k], one, rtol=0, atol=1e-12)
    pose32 = SensorPose(POSE.q.astype(jnp.float32), POSE.p.astype(jnp.float32))
    out = jaximu.propagate_final(
        jaximu.NavState.identity(),
        gyro.astype(jnp.float32),
        accel.astype(jnp.float32),
        0.005,
        body_P_sensor=pose32,
    )
    assert out.p.dtype == jnp.float32
    ref = jaximu.propagate_final(x0, gyro, accel, 0.005, body_P_sensor=POSE)
    np.testing.assert_allclose(out.p, ref.p, rtol=0, atol=1e-4)


def test_sensor_biases_come_back_in_the_sensor_frame():
    _, gyro, accel, dt, bias = window(6.3, 0.2)
    x0 = jaximu.NavState(jnp.array([1.0, 0, 0, 0]), jnp.zeros(3), jnp.zeros(3), bias.b_g, bias.b_a)
    out = jaximu.propagate(x0, gyro, accel, dt, body_P_sensor=POSE)
    np.testing.assert_array_equal(out.b_g, np.tile(bias.b_g, (len(dt), 1)))
    np.testing.assert_array_equal(out.b_a, np.tile(bias.b_a, (len(dt), 1)))


# --------------------------------------------------------------------------- bad input


def test_bad_sensor_poses_are_refused_with_the_argument_named():
    x0 = jaximu.NavState.identity(dtype=jnp.float64)
    w = np.zeros((5, 3))
    a = np.tile([0, 0, 9.81], (5, 1))
    with pytest.raises(ValueError, match=r"body_P_sensor: R_BS is not a rotation matrix"):
        SensorPose.from_rotation(np.diag([1.0, 1.0, 1.1]), np.zeros(3))
    with pytest.raises(ValueError, match=r"body_P_sensor: R_BS is not a rotation matrix"):
        SensorPose.from_rotation(np.diag([1.0, 1.0, -1.0]), np.zeros(3))  # a reflection
    with pytest.raises(ValueError, match=r"lever arm p_BS must have shape \(3,\)"):
        SensorPose.from_rotation(np.eye(3), np.zeros(2))
    with pytest.raises(ValueError, match=r"body_P_sensor.q is not a unit quaternion"):
        jaximu.propagate(
            x0, w, a, 0.01, body_P_sensor=SensorPose(jnp.array([1.0, 0.1, 0, 0]), jnp.zeros(3))
        )
    with pytest.raises(ValueError, match=r"body_P_sensor.p must be the lever arm p_BS of shape"):
        jaximu.preintegrate(
            w, a, 0.01, body_P_sensor=SensorPose(jnp.array([1.0, 0, 0, 0]), jnp.zeros(2))
        )
    with pytest.raises(ValueError, match=r"body_P_sensor must be a jaximu.SensorPose"):
        jaximu.propagate(x0, w, a, 0.01, body_P_sensor=np.eye(4))
    with pytest.raises(ValueError, match=r"last row must be \[0, 0, 0, 1\]"):
        SensorPose.from_matrix(np.eye(4) * 2)
