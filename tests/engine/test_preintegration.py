"""Preintegration against GTSAM (Manifold classes), a numpy transcription of VINS-Mono's
midPointIntegration, GTSAM's unit-test anchors, finite differences and propagation."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _shared import SEG, euroc_window
from scipy.spatial.transform import Rotation

import jaximu
from jaximu import so3

try:
    import gtsam
except ImportError:  # the test extra installs it; without it only the GTSAM comparisons skip
    gtsam = None
needs_gtsam = pytest.mark.skipif(gtsam is None, reason="gtsam is not installed")

NOISE = jaximu.ImuNoise.euroc()


def window(start_s, length_s):
    """Raw EuRoC samples of a window (flight part of the bundled excerpt) and GT biases."""
    return euroc_window(start_s, length_s)[1:]


def gtsam_params(combined=False, g=9.81):
    cls = gtsam.PreintegrationCombinedParams if combined else gtsam.PreintegrationParams
    p = cls.MakeSharedU(g)
    p.setGyroscopeCovariance(np.eye(3) * NOISE.gyroscope_noise_density**2)
    p.setAccelerometerCovariance(np.eye(3) * NOISE.accelerometer_noise_density**2)
    p.setIntegrationCovariance(np.zeros((3, 3)))
    if combined:
        p.setBiasAccCovariance(np.eye(3) * NOISE.accelerometer_random_walk**2)
        p.setBiasOmegaCovariance(np.eye(3) * NOISE.gyroscope_random_walk**2)
    return p


def gtsam_pim(gyro, accel, dt, bias, combined=False):
    b = gtsam.imuBias.ConstantBias(np.asarray(bias.b_a), np.asarray(bias.b_g))
    cls = (
        gtsam.PreintegratedCombinedMeasurementsManifold
        if combined
        else gtsam.PreintegratedImuMeasurementsManifold
    )
    pim = cls(gtsam_params(combined), b)
    for k in range(len(dt)):
        pim.integrateMeasurement(accel[k], gyro[k], dt[k])
    return pim


WINDOWS = [(5.0, 0.05), (6.3, 0.2), (8.0, 0.5), (10.0, 1.0), (12.5, 2.0)]


@needs_gtsam
@pytest.mark.parametrize("start,length", WINDOWS)
def test_euler_equals_gtsam_manifold_on_euroc(start, length):
    """Deltas to 1e-9, Δt exactly, preintMeasCov to 1e-8 relative (in GTSAM's chart), predict
    to 1e-9, for windows of 0.05-2 s of real EuRoC data at the ground-truth biases."""
    gyro, accel, dt, bias = window(start, length)
    ref = gtsam_pim(gyro, accel, dt, bias)
    pim = jaximu.preintegrate(gyro, accel, dt, bias, NOISE, "euler")
    np.testing.assert_allclose(pim.delta_R, ref.deltaRij().matrix(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(pim.delta_v, ref.deltaVij(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(pim.delta_p, ref.deltaPij(), rtol=0, atol=1e-9)
    assert float(pim.delta_t) == pytest.approx(ref.deltaTij(), abs=1e-12)
    C = ref.preintMeasCov()
    np.testing.assert_allclose(pim.covariance("gtsam"), C, rtol=0, atol=1e-8 * np.abs(C).max())
    # prediction from the ground-truth state at the window start (a different bias than the
    # linearisation point, so the first-order correction is exercised too)
    k0 = int(round(start / 0.005))
    q0 = SEG.q_gt[k0] / np.linalg.norm(SEG.q_gt[k0])
    b_g, b_a = np.asarray(bias.b_g) + 1e-3, np.asarray(bias.b_a) - 2e-2
    state = jaximu.NavState(*(jnp.asarray(x) for x in (q0, SEG.p_gt[k0], SEG.v_gt[k0], b_g, b_a)))
    nav = gtsam.NavState(gtsam.Rot3.Quaternion(*q0), SEG.p_gt[k0], SEG.v_gt[k0])
    pred = ref.predict(nav, gtsam.imuBias.ConstantBias(b_a, b_g))
    ours = jaximu.predict(state, pim)
    np.testing.assert_allclose(ours.R, pred.attitude().matrix(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours.p, pred.position(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours.v, pred.velocity(), rtol=0, atol=1e-9)


@needs_gtsam
@pytest.mark.parametrize("start,length", WINDOWS[1:4])
def test_combined_covariance_equals_gtsam_combined_manifold(start, length):
    """cov15 in GTSAM's chart (δp, δv in frame j; biases [b_a, b_g], signs of -∂/∂b) equals
    PreintegratedCombinedMeasurementsManifold's preintMeasCov to 1e-8 relative."""
    gyro, accel, dt, bias = window(start, length)
    ref = gtsam_pim(gyro, accel, dt, bias, combined=True).preintMeasCov()
    pim = jaximu.preintegrate(gyro, accel, dt, bias, NOISE, "euler")
    np.testing.assert_allclose(
        pim.covariance("gtsam", combined=True), ref, rtol=0, atol=1e-8 * np.abs(ref).max()
    )


# --------------------------------------------------------------------------- GTSAM anchors


def test_gtsam_preintegrated_measurements_anchor():
    """testImuFactor PreintegratedMeasurements: acc (0.1,0,0), ω (π/100,0,0), dt 0.5, twice."""
    one = jaximu.preintegrate([[np.pi / 100, 0, 0]], [[0.1, 0, 0]], [0.5])
    np.testing.assert_allclose(
        one.delta_R, Rotation.from_rotvec([np.pi / 200, 0, 0]).as_matrix(), atol=1e-12
    )
    np.testing.assert_allclose(one.delta_p, [0.0125, 0, 0], atol=1e-12)
    np.testing.assert_allclose(one.delta_v, [0.05, 0, 0], atol=1e-12)
    two = jaximu.preintegrate([[np.pi / 100, 0, 0]] * 2, [[0.1, 0, 0]] * 2, [0.5, 0.5])
    np.testing.assert_allclose(
        two.delta_R, Rotation.from_rotvec([np.pi / 100, 0, 0]).as_matrix(), atol=1e-12
    )
    np.testing.assert_allclose(two.delta_p, [0.05, 0, 0], atol=1e-12)
    np.testing.assert_allclose(two.delta_v, [0.1, 0, 0], atol=1e-12)
    assert float(two.delta_t) == 1.0


def test_gtsam_check_covariance_anchor():
    """testImuFactor CheckCovariance: kGyroSigma = 0.5°/60, kAccelSigma = 0.1/60 (densities);
    GTSAM's position entry 5.00868e-05 includes its integrationCovariance 1e-4·dt = 5e-5."""
    noise = jaximu.ImuNoise(np.deg2rad(0.5) / 60, 0.1 / 60)
    pim = jaximu.preintegrate([[np.pi / 100, 0, 0]], [[0.1, 0, 0]], [0.5], noise=noise)
    C = np.asarray(pim.covariance("gtsam"))
    np.testing.assert_allclose(np.diag(C)[0:3], 1.0577e-08, rtol=1e-4)
    np.testing.assert_allclose(np.diag(C)[3:6], 5.00868e-05 - 5e-5, rtol=2e-3)
    np.testing.assert_allclose(np.diag(C)[6:9], 1.38889e-06, rtol=1e-5)
    np.testing.assert_allclose(np.diag(C[3:6, 6:9]), 3.47222e-07, rtol=1e-5)


def test_gtsam_predict_position_and_velocity_anchor():
    """z-down g = 10, ω 0, acc (0,1,-10), 1000 × 1 ms, linearised at b_a = (0.2,0,0), predicted
    with zero bias from identity: R = I, p = (0, 0.5, 0), v = (0, 1, 0) (1e-9)."""
    pim = jaximu.preintegrate(
        np.zeros((1000, 3)),
        np.tile([0.0, 1, -10], (1000, 1)),
        0.001,
        jaximu.ImuBias(jnp.zeros(3), jnp.array([0.2, 0, 0])),
    )
    s = jaximu.predict(jaximu.NavState.identity(dtype=jnp.float64), pim, gravity=[0, 0, 10.0])
    np.testing.assert_allclose(s.R, np.eye(3), atol=1e-9)
    np.testing.assert_allclose(s.p, [0, 0.5, 0], atol=1e-9)
    np.testing.assert_allclose(s.v, [0, 1, 0], atol=1e-9)


def test_gtsam_predict_arbitrary_anchor():
    """testImuFactor PredictArbitrary: ω = (π/10)(1,1,1), acc (0.1, 0.2, -10) held for
    1000 × 1 ms, z-down g = 10, linearised at b_a = (0.2,0,0), predicted with zero bias: GTSAM's
    regression values (1e-7)."""
    w = np.tile([np.pi / 10] * 3, (1000, 1))
    a = np.tile([0.1, 0.2, -10.0], (1000, 1))
    pim = jaximu.preintegrate(w, a, 0.001, jaximu.ImuBias(jnp.zeros(3), jnp.array([0.2, 0, 0])))
    s = jaximu.predict(jaximu.NavState.identity(dtype=jnp.float64), pim, gravity=[0, 0, 10.0])
    R = [
        [0.903715275, -0.250741668, 0.347026393],
        [0.347026393, 0.903715275, -0.250741668],
        [-0.250741668, 0.347026393, 0.903715275],
    ]
    np.testing.assert_allclose(s.R, R, atol=1e-7)
    np.testing.assert_allclose(s.p, [-0.516077031, 0.57842919, 0.0876478403], atol=1e-7)
    np.testing.assert_allclose(s.v, [-1.62337767, 1.57954409, 0.343833571], atol=1e-7)


def test_gtsam_compare_with_preintegrated_rotation_anchor():
    """ω_true (0.1,0,0) + bias (1,2,3), dt 0.5: ΔR = Roll(0.05); corrected to gyro bias
    (1.05, 2, 3): Roll(0.025) (first order is exact about a fixed axis); J = -Jr(ω dt) dt."""
    bias = jaximu.ImuBias(jnp.array([1.0, 2, 3]), jnp.zeros(3))
    pim = jaximu.preintegrate([[1.1, 2, 3]], [[0.0, 0, 0]], [0.5], bias)
    np.testing.assert_allclose(
        pim.delta_R, Rotation.from_rotvec([0.05, 0, 0]).as_matrix(), atol=1e-12
    )
    np.testing.assert_allclose(
        pim.dR_dbg, -so3.right_jacobian(jnp.array([0.05, 0, 0])) * 0.5, atol=1e-15
    )
    c = jaximu.correct(pim, jaximu.ImuBias(jnp.array([1.05, 2, 3]), jnp.zeros(3)))
    np.testing.assert_allclose(
        c.delta_R, Rotation.from_rotvec([0.025, 0, 0]).as_matrix(), atol=1e-9
    )


# --------------------------------------------------------------------------- VINS-Mono


def _eigen_qmul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def _eigen_rotate(q, v):
    """Eigen's ``Quaterniond * Vector3d`` (also applied to non-unit quaternions)."""
    u = q[1:]
    uv = 2 * np.cross(u, v)
    return v + q[0] * uv + np.cross(u, uv)


def _eigen_matrix(q):
    """Eigen's ``toRotationMatrix`` (no normalisation)."""
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _sk(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def vins_mono_integration(gyro, accel, dt, ba, bg, ACC_N, GYR_N, ACC_W, GYR_W):
    """IntegrationBase::push_back / midPointIntegration of VINS-Mono (vins_estimator/src/
    factor/integration_base.h), transcribed in numpy, in its own order [p, θ, v, b_a, b_g]."""
    noise = np.zeros((18, 18))
    for i, s in enumerate([ACC_N, GYR_N, ACC_N, GYR_N, ACC_W, GYR_W]):
        noise[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = s * s * np.eye(3)
    dp, dv, dq = np.zeros(3), np.zeros(3), np.array([1.0, 0, 0, 0])
    jac, cov = np.eye(15), np.zeros((15, 15))
    acc_0, gyr_0 = accel[0], gyro[0]
    I3 = np.eye(3)
    for k in range(len(dt)):
        _dt, acc_1, gyr_1 = dt[k], accel[k + 1], gyro[k + 1]
        un_acc_0 = _eigen_rotate(dq, acc_0 - ba)
        un_gyr = 0.5 * (gyr_0 + gyr_1) - bg
        rq = _eigen_qmul(dq, np.r_[1.0, un_gyr * _dt / 2])
        un_acc_1 = _eigen_rotate(rq, acc_1 - ba)
        un_acc = 0.5 * (un_acc_0 + un_acc_1)
        rp = dp + dv * _dt + 0.5 * un_acc * _dt * _dt
        rv = dv + un_acc * _dt
        R0, R1 = _eigen_matrix(dq), _eigen_matrix(rq)
        Rw, Ra0, Ra1 = _sk(un_gyr), _sk(acc_0 - ba), _sk(acc_1 - ba)
        F = np.zeros((15, 15))
        F[0:3, 0:3] = I3
        F[0:3, 3:6] = -0.25 * R0 @ Ra0 * _dt**2 - 0.25 * R1 @ Ra1 @ (I3 - Rw * _dt) * _dt**2
        F[0:3, 6:9] = I3 * _dt
        F[0:3, 9:12] = -0.25 * (R0 + R1) * _dt**2
        F[0:3, 12:15] = -0.25 * R1 @ Ra1 * _dt**2 * -_dt
        F[3:6, 3:6] = I3 - Rw * _dt
        F[3:6, 12:15] = -I3 * _dt
        F[6:9, 3:6] = -0.5 * R0 @ Ra0 * _dt - 0.5 * R1 @ Ra1 @ (I3 - Rw * _dt) * _dt
        F[6:9, 6:9] = I3
        F[6:9, 9:12] = -0.5 * (R0 + R1) * _dt
        F[6:9, 12:15] = -0.5 * R1 @ Ra1 * _dt * -_dt
        F[9:12, 9:12] = I3
        F[12:15, 12:15] = I3
        V = np.zeros((15, 18))
        V[0:3, 0:3] = 0.25 * R0 * _dt**2
        V[0:3, 3:6] = 0.25 * -R1 @ Ra1 * _dt**2 * 0.5 * _dt
        V[0:3, 6:9] = 0.25 * R1 * _dt**2
        V[0:3, 9:12] = V[0:3, 3:6]
        V[3:6, 3:6] = 0.5 * I3 * _dt
        V[3:6, 9:12] = 0.5 * I3 * _dt
        V[6:9, 0:3] = 0.5 * R0 * _dt
        V[6:9, 3:6] = 0.5 * -R1 @ Ra1 * _dt * 0.5 * _dt
        V[6:9, 6:9] = 0.5 * R1 * _dt
        V[6:9, 9:12] = V[6:9, 3:6]
        V[9:12, 12:15] = I3 * _dt
        V[12:15, 15:18] = I3 * _dt
        jac = F @ jac
        cov = F @ cov @ F.T + V @ noise @ V.T
        dp, dv, dq = rp, rv, rq / np.linalg.norm(rq)
        acc_0, gyr_0 = acc_1, gyr_1
    return dp, dq, dv, jac, cov


# VINS-Mono order [p, θ, v, b_a, b_g] -> ours [θ, p, v, b_g, b_a]
VINS_TO_OURS = np.r_[3:6, 0:3, 6:9, 12:15, 9:12]


@pytest.mark.parametrize("method", ["sequential", "parallel"])
def test_midpoint_equals_vins_mono_transcription(method):
    """Mean, jacobian (bias Jacobians) and 15×15 covariance equal VINS-Mono's (1e-10 rel), with
    acc_n = σ_a √(2/dt), gyr_n = σ_g √(2/dt), acc_w = σ_ba/√dt, gyr_w = σ_bg/√dt."""
    k0, n = 1600, 300  # 1.5 s of flight
    gyro, accel = SEG.gyro[k0 : k0 + n + 1], SEG.accel[k0 : k0 + n + 1]
    h = 0.005
    dt = np.full(n, h)  # n intervals between n + 1 samples: VINS-Mono's push_back
    ba, bg = SEG.b_a_gt[k0], SEG.b_g_gt[k0]
    dp, dq, dv, jac, cov = vins_mono_integration(
        gyro,
        accel,
        dt,
        ba,
        bg,
        NOISE.accelerometer_noise_density * np.sqrt(2 / h),
        NOISE.gyroscope_noise_density * np.sqrt(2 / h),
        NOISE.accelerometer_random_walk / np.sqrt(h),
        NOISE.gyroscope_random_walk / np.sqrt(h),
    )
    pim = jaximu.preintegrate(
        gyro, accel, dt, jaximu.ImuBias(jnp.asarray(bg), jnp.asarray(ba)), NOISE, "midpoint", method
    )
    np.testing.assert_allclose(pim.delta_p, dp, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(pim.delta_v, dv, rtol=1e-10, atol=1e-14)
    assert abs(abs(np.dot(np.asarray(pim.delta_q), dq)) - 1) < 1e-15
    J = jac[np.ix_(VINS_TO_OURS, VINS_TO_OURS)]
    np.testing.assert_allclose(pim.transition, J, rtol=0, atol=1e-10 * np.abs(J).max())
    C = cov[np.ix_(VINS_TO_OURS, VINS_TO_OURS)]
    np.testing.assert_allclose(pim.cov15, C, rtol=0, atol=1e-10 * np.abs(C).max())


# --------------------------------------------------------------------------- properties


@pytest.fixture(scope="module")
def flight():
    return window(9.0, 1.0)


@pytest.mark.parametrize("scheme", jaximu.preintegration.SCHEMES)
def test_parallel_equals_sequential_and_prefixes(scheme, flight):
    gyro, accel, dt, bias = flight
    seq = jaximu.preintegrate(gyro, accel, dt, bias, NOISE, scheme, "sequential", prefixes=True)
    par = jaximu.preintegrate(gyro, accel, dt, bias, NOISE, scheme, "parallel", prefixes=True)
    for a, b in zip(jax.tree_util.tree_leaves(seq), jax.tree_util.tree_leaves(par)):
        a, b = np.asarray(a), np.asarray(b)
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-10 * max(np.abs(a).max(), 1e-300))
    # prefix k equals preintegrating the first k + 1 samples alone
    k = 57
    short = jaximu.preintegrate(gyro[: k + 1], accel[: k + 1], dt[: k + 1], bias, NOISE, scheme)
    prefix = jax.tree_util.tree_map(lambda x: x[k], seq)
    if scheme == "midpoint":  # the short window holds its last sample instead of using k + 1
        short = jaximu.preintegrate(gyro[: k + 2], accel[: k + 2], dt[: k + 1], bias, NOISE, scheme)
    for a, b in zip(jax.tree_util.tree_leaves(short), jax.tree_util.tree_leaves(prefix)):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-15)


def test_bias_jacobians_analytic_equal_jacfwd_of_the_mean(flight):
    """Euler: the analytic recursion equals jax.jacfwd of the mean deltas over the window
    (1e-10). Midpoint: jacobians='autodiff' equals it too; VINS-Mono's own linearisation
    (jacobians='analytic') differs at first order in dt (measured 2e-4 relative at 200 Hz)."""
    gyro, accel, dt, bias = flight
    names = ("dR_dbg", "dp_dbg", "dp_dba", "dv_dbg", "dv_dba")
    for scheme, jac, tol in [
        ("euler", "analytic", 1e-10),
        ("midpoint", "autodiff", 1e-10),
        ("midpoint", "analytic", 1e-3),
    ]:
        ref = jaximu.bias_jacobians_autodiff(gyro, accel, dt, bias, scheme)
        pim = jaximu.preintegrate(gyro, accel, dt, bias, scheme=scheme, jacobians=jac)
        for name, J in zip(names, ref):
            scale = np.abs(np.asarray(J)).max()
            np.testing.assert_allclose(
                getattr(pim, name), J, rtol=0, atol=tol * scale, err_msg=f"{scheme} {jac} {name}"
            )


def test_euler_autodiff_and_analytic_covariances_agree(flight):
    gyro, accel, dt, bias = flight
    a = jaximu.preintegrate(gyro, accel, dt, bias, NOISE, "euler", jacobians="analytic")
    b = jaximu.preintegrate(gyro, accel, dt, bias, NOISE, "euler", jacobians="autodiff")
    for f in ("transition", "cov15", "cov"):
        x, y = np.asarray(getattr(a, f)), np.asarray(getattr(b, f))
        np.testing.assert_allclose(y, x, rtol=0, atol=1e-10 * np.abs(x).max())


@pytest.mark.parametrize("scheme", jaximu.preintegration.SCHEMES)
def test_correct_is_second_order(scheme, flight):
    """First-order correction vs re-integration: halving δb divides the error by ~4."""
    gyro, accel, dt, bias = flight
    pim = jaximu.preintegrate(gyro, accel, dt, bias, scheme=scheme, jacobians="autodiff")
    direction = np.array([0.02, -0.015, 0.01, 0.2, -0.1, 0.15])
    errors = []
    for s in (1.0, 0.5, 0.25):
        db = s * direction
        new = jaximu.ImuBias(bias.b_g + db[:3], bias.b_a + db[3:])
        exact = jaximu.preintegrate(gyro, accel, dt, new, scheme=scheme)
        approx = jaximu.correct(pim, new)
        errors.append(
            np.linalg.norm(np.asarray(approx.delta_p - exact.delta_p))
            + np.linalg.norm(np.asarray(approx.delta_v - exact.delta_v))
            + np.linalg.norm(
                np.asarray(so3.log(so3.quat_mul(so3.quat_conj(exact.delta_q), approx.delta_q)))
            )
        )
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert np.all((3.6 < ratios) & (ratios < 4.4)), (errors, ratios)


def test_needs_reintegration_thresholds():
    pim = jaximu.preintegrate(np.zeros((3, 3)), np.zeros((3, 3)), 0.01)
    z = jnp.zeros(3)
    assert not bool(jaximu.needs_reintegration(pim, jaximu.ImuBias(z + 0.005, z + 0.05)))
    assert bool(jaximu.needs_reintegration(pim, jaximu.ImuBias(jnp.array([0.011, 0, 0]), z)))
    assert bool(jaximu.needs_reintegration(pim, jaximu.ImuBias(z, jnp.array([0, 0.11, 0]))))


def _propagated_states(flight, scheme):
    gyro, accel, dt, bias = flight
    k0 = int(round(9.0 / 0.005))
    q0 = SEG.q_gt[k0] / np.linalg.norm(SEG.q_gt[k0])
    s0 = jaximu.NavState(
        jnp.asarray(q0), jnp.asarray(SEG.p_gt[k0]), jnp.asarray(SEG.v_gt[k0]), bias.b_g, bias.b_a
    )
    # Propagation with gravity is an independent route to the same end state.
    s1 = jaximu.propagate_final(
        s0,
        gyro,
        accel,
        dt,
        scheme,
        attitude="quaternion" if scheme == "euler" else "quaternion_first_order",
    )
    return s0, s1


def test_predict_and_residual_agree_with_propagation(flight):
    """Euler preintegration + gravity = Euler propagation: predict() equals propagate_final()
    and the residual between the two propagated states is zero (1e-10)."""
    gyro, accel, dt, bias = flight
    pim = jaximu.preintegrate(gyro, accel, dt, bias, NOISE, "euler")
    s0, s1 = _propagated_states(flight, "euler")
    pred = jaximu.predict(s0, pim)
    np.testing.assert_allclose(pred.p, s1.p, atol=1e-10)
    np.testing.assert_allclose(pred.v, s1.v, atol=1e-10)
    np.testing.assert_allclose(jaximu.residual(s0, s1, pim), np.zeros(15), atol=1e-10)


def test_residual_zero_on_gtsam_accelerating_scenario():
    """GTSAM's Accelerating scenario (exact for the zero-order hold): the residual between the
    analytic states at 0 and 3 s is zero; a velocity offset shows up as -R_iᵀ offset."""
    nRb = np.array([[0.0, 1, 0], [1, 0, 0], [0, 0, -1]]).T
    p0, v0, a_n = np.array([10.0, 20, 0]), np.array([50.0, 0, 0]), np.array([0.0, 0.2, 0])
    omega, dt, n = np.array([0.1, 0.2, 0.3]), 0.3, 10
    t = dt * np.arange(n + 1)
    R_t = Rotation.from_matrix(nRb) * Rotation.from_rotvec(t[:, None] * omega)
    f = R_t.inv().apply(a_n - np.array([0.0, 0, -9.81]))
    pim = jaximu.preintegrate(np.tile(omega, (n, 1)), f[:n], dt, noise=NOISE)
    z = jnp.zeros(3)

    def state(k, dv=0.0):
        return jaximu.NavState(
            jnp.asarray(R_t[k].as_quat(scalar_first=True)),
            jnp.asarray(p0 + v0 * t[k] + 0.5 * a_n * t[k] ** 2),
            jnp.asarray(v0 + a_n * t[k] + dv),
            z,
            z,
        )

    np.testing.assert_allclose(jaximu.residual(state(0), state(n), pim), np.zeros(15), atol=1e-9)
    offset = np.array([0.1, 0.1, 0.1])
    r = np.asarray(jaximu.residual(state(0, offset), state(n), pim))
    np.testing.assert_allclose(r[6:9], -R_t[0].inv().apply(offset), atol=1e-9)


def test_residual_jacobians_by_autodiff_equal_finite_differences(flight):
    gyro, accel, dt, bias = flight
    pim = jaximu.preintegrate(gyro, accel, dt, bias, NOISE, "euler")
    s0, s1 = _propagated_states(flight, "euler")
    s1 = jaximu.boxplus(s1, jnp.asarray(np.random.default_rng(0).normal(size=15) * 1e-2))

    @jax.jit
    def r(d_i, d_j):
        return jaximu.residual(jaximu.boxplus(s0, d_i), jaximu.boxplus(s1, d_j), pim)

    z = jnp.zeros(15)
    Ji, Jj = jax.jacfwd(r, argnums=(0, 1))(z, z)
    eps = 1e-6
    for J, arg in ((Ji, 0), (Jj, 1)):
        fd = np.zeros((15, 15))
        for c in range(15):
            e = np.zeros(15)
            e[c] = eps
            args_p = [z, z]
            args_m = [z, z]
            args_p[arg], args_m[arg] = jnp.asarray(e), jnp.asarray(-e)
            fd[:, c] = (np.asarray(r(*args_p)) - np.asarray(r(*args_m))) / (2 * eps)
        np.testing.assert_allclose(J, fd, rtol=0, atol=1e-7 * np.abs(fd).max())


def test_whitened_residual_gives_the_mahalanobis_norm(flight):
    gyro, accel, dt, bias = flight
    pim = jaximu.preintegrate(gyro, accel, dt, bias, NOISE, "midpoint")
    s0, s1 = _propagated_states(flight, "euler")
    s1 = jaximu.boxplus(s1, jnp.asarray(np.random.default_rng(1).normal(size=15) * 1e-3))
    r = np.asarray(jaximu.residual(s0, s1, pim))
    w = np.asarray(jaximu.whitened_residual(s0, s1, pim))
    np.testing.assert_allclose(w @ w, r @ np.linalg.solve(np.asarray(pim.cov15), r), rtol=1e-8)


def test_whitened_residual_batches_broadcast_and_empty(flight):
    """A batch of states against one measurement (the block Cholesky on lanes) equals numpy's
    factor and solve per element; an empty batch gives an empty result."""
    gyro, accel, dt, bias = flight
    pim = jaximu.preintegrate(gyro, accel, dt, bias, NOISE)
    s0, s1 = _propagated_states(flight, "euler")
    d = jnp.asarray(np.random.default_rng(2).normal(size=(70, 15)) * 1e-3)  # > one block
    s1b = jax.vmap(lambda x: jaximu.boxplus(s1, x))(d)
    s0b = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (70,) + x.shape), s0)
    w = np.asarray(jaximu.whitened_residual(s0b, s1b, pim))
    L = np.linalg.cholesky(np.asarray(pim.cov15))
    want = np.linalg.solve(L, np.asarray(jaximu.residual(s0b, s1b, pim)).T).T
    np.testing.assert_allclose(w, want, rtol=0, atol=1e-12 * np.abs(want).max())
    empty = jax.tree_util.tree_map(lambda x: x[:0], s0b)
    assert jaximu.whitened_residual(empty, empty, pim).shape == (0, 15)


def test_compose_is_associative_and_equals_one_window(flight):
    """compose(compose(a, b), c) = compose(a, compose(b, c)) = preintegrate(a+b+c) for Euler."""
    gyro, accel, dt, bias = flight
    cuts = [0, 70, 130, 200]
    parts = [
        jaximu.preintegrate(gyro[i:j], accel[i:j], dt[i:j], bias, NOISE, "euler")
        for i, j in zip(cuts[:-1], cuts[1:])
    ]
    left = jaximu.compose(jaximu.compose(parts[0], parts[1]), parts[2])
    right = jaximu.compose(parts[0], jaximu.compose(parts[1], parts[2]))
    whole = jaximu.preintegrate(gyro, accel, dt, bias, NOISE, "euler")
    for f in ("delta_q", "delta_v", "delta_p", "delta_t", "transition", "cov15", "cov"):
        w = np.asarray(getattr(whole, f))
        for got in (left, right):
            np.testing.assert_allclose(
                getattr(got, f), w, rtol=0, atol=1e-10 * np.abs(w).max(), err_msg=f
            )


def test_compose_corrects_to_the_first_bias(flight):
    gyro, accel, dt, bias = flight
    other = jaximu.ImuBias(bias.b_g + 1e-3, bias.b_a - 1e-2)
    a = jaximu.preintegrate(gyro[:100], accel[:100], dt[:100], bias, scheme="euler")
    b = jaximu.preintegrate(gyro[100:], accel[100:], dt[100:], other, scheme="euler")
    whole = jaximu.preintegrate(gyro, accel, dt, bias, scheme="euler")
    ab = jaximu.compose(a, b)
    np.testing.assert_allclose(ab.bias_hat.b_g, bias.b_g)
    np.testing.assert_allclose(ab.delta_v, whole.delta_v, atol=1e-6)  # first-order correction


def test_batched_windows_and_vmap(flight):
    gyro, accel, dt, bias = flight
    G = gyro[:180].reshape(4, 45, 3)
    A = accel[:180].reshape(4, 45, 3)
    D = dt[:180].reshape(4, 45)
    batched = jaximu.preintegrate(G, A, D, bias, NOISE, "euler", "parallel")
    mapped = jax.vmap(lambda g, a, d: jaximu.preintegrate(g, a, d, bias, NOISE, "euler"))(G, A, D)
    assert batched.delta_p.shape == (4, 3) and batched.cov15.shape == (4, 15, 15)
    for i in range(4):
        one = jaximu.preintegrate(G[i], A[i], D[i], bias, NOISE, "euler")
        np.testing.assert_allclose(batched.delta_p[i], one.delta_p, atol=1e-14)
        np.testing.assert_allclose(batched.cov15[i], one.cov15, atol=1e-20)
        np.testing.assert_allclose(mapped.cov15[i], one.cov15, atol=1e-20)


def test_gradients_wrt_measurements_bias_and_noise(flight):
    gyro, accel, dt, bias = flight
    gyro, accel, dt = gyro[:40], accel[:40], dt[:40]

    @functools.partial(jax.jit, static_argnames="scheme")
    def loss(g, a, bg, sigma, scheme):
        pim = jaximu.preintegrate(
            g, a, dt, jaximu.ImuBias(bg, bias.b_a), jaximu.ImuNoise(sigma, 2e-3, 2e-5, 3e-3), scheme
        )
        return (
            jnp.sum(pim.delta_p * jnp.array([1.0, -2, 0.5]))
            + jnp.sum(so3.log(pim.delta_q))
            + 1e6 * jnp.trace(pim.cov)
        )

    # one program per scheme for the gradient and the differences' values (an eager grad of
    # the jitted loss compiles its linearised and transposed parts apart, and the loss again)
    value_and_grad = jax.jit(
        jax.value_and_grad(loss, argnums=(0, 1, 2, 3)), static_argnames="scheme"
    )
    for scheme in jaximu.preintegration.SCHEMES:
        args = (jnp.asarray(gyro), jnp.asarray(accel), bias.b_g, jnp.asarray(1.7e-4, float))
        grads = value_and_grad(*args, scheme=scheme)[1]
        for i, g in enumerate(grads):
            assert np.all(np.isfinite(np.asarray(g)))
            x = np.asarray(args[i], dtype=float)
            idx = (3, 1) if x.ndim == 2 else ((2,) if x.ndim == 1 else ())
            e = np.zeros_like(x)
            e[idx] = 1e-6
            a_p, a_m = list(args), list(args)
            a_p[i], a_m[i] = jnp.asarray(x + e), jnp.asarray(x - e)
            fd = (
                value_and_grad(*a_p, scheme=scheme)[0] - value_and_grad(*a_m, scheme=scheme)[0]
            ) / 2e-6
            np.testing.assert_allclose(np.asarray(g)[idx], fd, rtol=1e-5, atol=1e-9)


def test_float32_preintegration_close_to_float64(flight):
    gyro, accel, dt, bias = flight
    out = {}
    for dtype in (jnp.float32, jnp.float64):
        b = jaximu.ImuBias(bias.b_g.astype(dtype), bias.b_a.astype(dtype))
        out[dtype] = jaximu.preintegrate(
            gyro.astype(dtype), accel.astype(dtype), dt.astype(dtype), b, NOISE, "euler", "parallel"
        )
    assert out[jnp.float32].delta_p.dtype == jnp.float32
    np.testing.assert_allclose(
        np.asarray(out[jnp.float32].delta_p, float), out[jnp.float64].delta_p, atol=1e-5
    )
    c64 = np.asarray(out[jnp.float64].cov)
    np.testing.assert_allclose(
        np.asarray(out[jnp.float32].cov, float), c64, rtol=0, atol=1e-4 * np.abs(c64).max()
    )


@pytest.mark.parametrize(
    "args,message",
    [
        (dict(gyro=np.zeros((0, 3)), accel=np.zeros((0, 3)), dt=np.zeros(0)), "no samples"),
        (dict(dt=np.r_[0.01, 0.0, 0.01, 0.01, 0.01]), r"dt must be positive and finite; dt\[1\]"),
        (dict(accel=np.zeros((4, 3))), "different numbers of samples"),
        (dict(dt=np.full(3, 0.01)), r"dt must be a scalar or have shape \(\.\.\., T\) or"),
        (dict(gyro=np.r_[np.zeros((4, 3)), [[np.nan, 0, 0]]]), "gyro contains non-finite"),
        (dict(scheme="rk4"), "unknown preintegration scheme 'rk4'"),
        (dict(method="tree"), "unknown method 'tree'"),
        (dict(bias=(0, 0)), "bias must be a jaximu.ImuBias"),
    ],
)
def test_bad_input(args, message):
    kw = dict(gyro=np.zeros((5, 3)), accel=np.zeros((5, 3)), dt=np.full(5, 0.01))
    kw.update(args)
    with pytest.raises(ValueError, match=message):
        jaximu.preintegrate(kw.pop("gyro"), kw.pop("accel"), kw.pop("dt"), **kw)
