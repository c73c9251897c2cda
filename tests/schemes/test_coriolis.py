"""The rotating world (omega_coriolis): Earth's rate in closed form, predict against GTSAM's
omegaCoriolis (first and second order), propagation against exact rotating-frame
simulation, the covariance against finite differences, the dispatch row."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _shared import central_difference_phi

import jaximu
from jaximu import simulate as sim
from jaximu.datasets import euroc_v1_02_segment
from jaximu.engine import _dispatch

try:
    import gtsam
except ImportError:
    gtsam = None
needs_gtsam = pytest.mark.skipif(gtsam is None, reason="gtsam is not installed")

NOISE = jaximu.ImuNoise.euroc()
SEG = euroc_v1_02_segment()
OMEGA_E = 7.292115e-5


def test_earth_rate_in_east_north_up():
    np.testing.assert_allclose(jaximu.earth_rate(0.0), [0, OMEGA_E, 0], rtol=0, atol=1e-20)
    np.testing.assert_allclose(jaximu.earth_rate(90.0), [0, 0, OMEGA_E], rtol=0, atol=1e-20)
    lat = np.deg2rad(47.3769)  # Zürich
    np.testing.assert_allclose(
        jaximu.earth_rate(47.3769), [0, OMEGA_E * np.cos(lat), OMEGA_E * np.sin(lat)], rtol=1e-14
    )
    with pytest.raises(ValueError, match=r"latitude_deg must be in \[-90, 90\]"):
        jaximu.earth_rate(100.0)


def _gtsam_params(omega, second_order):
    p = gtsam.PreintegrationParams.MakeSharedU(9.81)
    p.setGyroscopeCovariance(np.eye(3) * NOISE.gyroscope_noise_density**2)
    p.setAccelerometerCovariance(np.eye(3) * NOISE.accelerometer_noise_density**2)
    p.setIntegrationCovariance(np.zeros((3, 3)))
    p.setOmegaCoriolis(np.asarray(omega, float))
    if second_order:
        # GTSAM's Python wrapper has no setter for use2ndOrderCoriolis: set the flag in its
        # serialised form (the bool right before n_gravity) and read it back
        toks = p.serialize().split(" ")
        assert toks[-5] == "0" and float(toks[-2]) == -9.81, toks[-6:]
        toks[-5] = "1"
        p.deserialize(" ".join(toks))
    return p


def _window():
    k0, n = 2000, 200
    gyro, accel = SEG.gyro[k0 : k0 + n], SEG.accel[k0 : k0 + n]
    dt = np.diff(SEG.t[k0 : k0 + n + 1])
    b_g, b_a = SEG.b_g_gt[k0], SEG.b_a_gt[k0]
    q0 = SEG.q_gt[k0] / np.linalg.norm(SEG.q_gt[k0])
    p0 = SEG.p_gt[k0] + np.array([30.0, -20.0, 5.0])  # far from the origin: centrifugal
    state = jaximu.NavState(
        *(jnp.asarray(x) for x in (q0, p0, SEG.v_gt[k0], b_g + 1e-3, b_a - 2e-2))
    )
    return gyro, accel, dt, jaximu.ImuBias(b_g, b_a), state


@needs_gtsam
@pytest.mark.parametrize("second_order", [False, True])
@pytest.mark.parametrize("omega", [(0.02, -0.03, 0.05), "earth"])
def test_exact_predict_with_omega_coriolis_equals_gtsam(omega, second_order):
    """GTSAM 4.3's PreintegratedImuMeasurementsManifold.predict with omegaCoriolis is the
    exact rotating-frame transition (use2ndOrderCoriolis inert, both ways tested): on 1 s
    of real EuRoC samples, from the ground-truth state (moved 37 m from the origin) with a
    bias away from the linearisation point, attitude, position, velocity to 1e-9."""
    omega = np.asarray(jaximu.earth_rate(47.4) if omega == "earth" else omega)
    gyro, accel, dt, bias, state = _window()
    b = gtsam.imuBias.ConstantBias(np.asarray(bias.b_a), np.asarray(bias.b_g))
    ref = gtsam.PreintegratedImuMeasurementsManifold(_gtsam_params(omega, second_order), b)
    for k in range(len(dt)):
        ref.integrateMeasurement(accel[k], gyro[k], dt[k])
    pred = ref.predict(
        gtsam.NavState(
            gtsam.Rot3.Quaternion(*np.asarray(state.q)), np.asarray(state.p), np.asarray(state.v)
        ),
        gtsam.imuBias.ConstantBias(np.asarray(state.b_a), np.asarray(state.b_g)),
    )
    pim = jaximu.preintegrate(gyro, accel, dt, bias, NOISE)
    ours = jaximu.predict(state, pim, omega_coriolis=omega, coriolis_second_order=second_order)
    np.testing.assert_allclose(ours.R, pred.attitude().matrix(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours.p, pred.position(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours.v, pred.velocity(), rtol=0, atol=1e-9)
    still = jaximu.predict(state, pim)
    assert np.abs(np.asarray(still.v - ours.v)).max() > 1e-6  # the terms are exercised


def _classic_predict_numpy(state, pim, omega, second_order, g=9.81):
    """GTSAM ≤ 4.2's predict with omegaCoriolis, transcribed in numpy from its
    NavState::correctPIM / coriolis / retract (gtsam/navigation/NavState.cpp):
    ξ = [Log ΔR, Δp + Rᵀv Δt + ½Rᵀg Δt², Δv + Rᵀg Δt] + Rᵀ·[-ωΔt, -Δt²ω×v, -2Δt ω×v]
    (second order: dP -= ½Δt² ω×(ω×p), dV -= Δt ω×(ω×p)); retract
    R Exp(ξ_R), p + R ξ_p, v + R ξ_v."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(np.asarray(state.q), scalar_first=True).as_matrix()
    p, v = np.asarray(state.p), np.asarray(state.v)
    dq, dv_, dp_ = (np.asarray(x) for x in jaximu.preintegration._corrected_deltas(pim, state.bias))
    T = float(pim.delta_t)
    gv = np.array([0, 0, -g])
    wxv = np.cross(omega, v)
    n_dR, n_dP, n_dV = -T * omega, -T * T * wxv, -2 * T * wxv
    if second_order:
        wwp = np.cross(omega, np.cross(omega, p))
        n_dP, n_dV = n_dP - 0.5 * T * T * wwp, n_dV - T * wwp
    xi_R = Rotation.from_quat(dq, scalar_first=True).as_rotvec() + R.T @ n_dR
    xi_P = dp_ + R.T @ v * T + 0.5 * R.T @ gv * T * T + R.T @ n_dP
    xi_V = dv_ + R.T @ gv * T + R.T @ n_dV
    return R @ Rotation.from_rotvec(xi_R).as_matrix(), p + R @ xi_P, v + R @ xi_V


@pytest.mark.parametrize("second_order", [False, True])
def test_classic_predict_equals_gtsam_42_correct_pim_transcription(second_order):
    """coriolis_exact=False: GTSAM ≤ 4.2's additive Coriolis model, first and second order,
    equals a numpy transcription of its formulas to 1e-12; the residual against it is 0."""
    omega = np.array([0.02, -0.03, 0.05])
    gyro, accel, dt, bias, state = _window()
    pim = jaximu.preintegrate(gyro, accel, dt, bias, NOISE)
    kw = dict(omega_coriolis=omega, coriolis_exact=False, coriolis_second_order=second_order)
    ours = jaximu.predict(state, pim, **kw)
    R, p, v = _classic_predict_numpy(state, pim, omega, second_order)
    np.testing.assert_allclose(ours.R, R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(ours.p, p, rtol=0, atol=1e-12 * np.abs(p).max())
    np.testing.assert_allclose(ours.v, v, rtol=0, atol=1e-12 * np.abs(v).max())
    np.testing.assert_allclose(jaximu.residual(state, ours, pim, **kw), 0.0, rtol=0, atol=1e-10)


@pytest.mark.parametrize("exact", [True, False])
def test_residual_is_zero_at_the_prediction_and_not_at_the_still_worlds(exact):
    omega = np.array([0.02, -0.03, 0.05])
    gyro, accel, dt, bias, state = _window()
    pim = jaximu.preintegrate(gyro, accel, dt, bias, NOISE)
    kw = dict(omega_coriolis=omega, coriolis_exact=exact, coriolis_second_order=True)
    pred = jaximu.predict(state, pim, **kw)
    np.testing.assert_allclose(jaximu.residual(state, pred, pim, **kw), 0.0, rtol=0, atol=1e-10)
    assert np.abs(np.asarray(jaximu.residual(state, pred, pim))).max() > 1e-4


W_FAST = np.array([0.05, -0.1, 0.2])  # |ω| = 0.23 rad/s: the terms are large


@pytest.fixture(scope="module")
def rotating_signals():
    """Exact IMU samples of a helix given in a world turning at W_FAST, at two rates."""
    traj = sim.helix(radius=3.0, turn_rate=0.8, climb_rate=0.5)
    t_end = 2.0
    truth = sim.true_states(traj, jnp.array([0.0, t_end]))
    x0 = jaximu.NavState(
        truth.q[0], truth.p[0] + jnp.array([4.0, 0.0, 0.0]), truth.v[0], jnp.zeros(3), jnp.zeros(3)
    )
    moved = sim.Trajectory(lambda s: (traj.pose(s)[0], traj.pose(s)[1] + jnp.array([4.0, 0, 0])))
    out = {}
    for dt in (0.01, 0.005):
        n = int(round(t_end / dt))
        gyro, accel = sim.ideal_imu(
            moved, jnp.asarray(dt * np.arange(n + 1)), omega_coriolis=W_FAST
        )
        out[dt] = (gyro, accel, jnp.full(n, dt))
    return x0, np.asarray(truth.p[1]) + [4.0, 0, 0], np.asarray(truth.q[1]), out


def _errors(sig, scheme="midpoint", **kw):
    x0, p_end, _, data = sig
    return [
        float(
            np.linalg.norm(
                np.asarray(jaximu.propagate_final(x0, *data[dt], scheme, **kw).p) - p_end
            )
        )
        for dt in (0.01, 0.005)
    ]


@pytest.mark.parametrize("scheme,order", [("euler", 1), ("midpoint", 2)])
def test_rotating_world_propagation_converges_to_the_exact_rotating_frame_motion(
    scheme, order, rotating_signals
):
    """Samples of a motion given in a world turning at 0.23 rad/s (Coriolis and centrifugal,
    by autodiff): the exact transition keeps the scheme's order (the error falls 2^order
    when dt halves); the classic second-order terms converge at first order; the
    first-order terms (centrifugal missing) and a still world do not converge."""
    exact = _errors(rotating_signals, scheme, omega_coriolis=W_FAST)
    assert abs(np.log2(exact[0] / exact[1]) - order) < 0.3, exact
    classic = _errors(
        rotating_signals,
        scheme,
        omega_coriolis=W_FAST,
        coriolis_exact=False,
        coriolis_second_order=True,
    )
    assert classic[0] / classic[1] > 1.7, classic
    still = _errors(rotating_signals, scheme)
    first = _errors(rotating_signals, scheme, omega_coriolis=W_FAST, coriolis_exact=False)
    for bad in (still, first):
        assert bad[1] > 0.9 * bad[0] and bad[1] > 10 * exact[1], (bad, exact)


@pytest.mark.parametrize("exact", [True, False])
def test_covariance_in_a_rotating_world_is_phi_phi_t_by_finite_differences(exact, rotating_signals):
    """Zero noise, P0 = I: P = Φ Φᵀ, Φ by central finite differences of propagate_final
    with omega_coriolis (the generic kernels with the increments' [p, v] Jacobian)."""
    x0, _, _, data = rotating_signals
    gyro, accel, dt = (x[:41] if x.ndim > 1 else x[:40] for x in data[0.01])
    kw = dict(omega_coriolis=W_FAST, coriolis_exact=exact, coriolis_second_order=True)
    zero = jaximu.ImuNoise(0.0, 0.0, 0.0, 0.0)
    _, P = jaximu.propagate_covariance_final(x0, jnp.eye(15), gyro, accel, dt, zero, **kw)
    run = jax.jit(lambda x: jaximu.propagate_final(x, gyro, accel, dt, **kw))
    Phi = central_difference_phi(run, x0)
    ref = Phi @ Phi.T
    np.testing.assert_allclose(P, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    # and the world's terms are in it: without them Φ differs
    _, P_still = jaximu.propagate_covariance_final(x0, jnp.eye(15), gyro, accel, dt, zero)
    assert np.abs(np.asarray(P_still) - ref).max() > 1e-4 * np.abs(ref).max()


def _rotating_inputs(rng, B, T, lane_dt, lane_omega):
    """Random states far from the origin (large centrifugal terms), samples, steps and a
    world rate, shared by all lanes or one per lane."""
    gyro = jnp.asarray(rng.normal(0, 0.5, (B, T, 3)))
    accel = jnp.asarray(rng.normal(0, 1, (B, T, 3)) + [0, 0, 9.81])
    dt = jnp.asarray(rng.uniform(0.005, 0.02, (B, T)) if lane_dt else np.full(T, 0.01))
    omega = jnp.asarray(rng.normal(0, 0.2, (B, 3)) if lane_omega else W_FAST)
    q0 = rng.normal(size=(B, 4))
    x0 = jaximu.NavState(
        jnp.asarray(q0 / np.linalg.norm(q0, axis=-1, keepdims=True)),
        jnp.asarray(rng.normal(0, 50, (B, 3))),
        jnp.asarray(rng.normal(0, 3, (B, 3))),
        jnp.zeros((B, 3)),
        jnp.zeros((B, 3)),
    )
    return x0, gyro, accel, dt, omega, jnp.array([0.0, 0.0, -9.81])


# Each case pairs a scheme with a Coriolis model and a batching of dt and ω, so that every
# scheme, every model and both layouts (shared and per-lane) of dt and ω are covered once.
ROTATING_SOA_CASES = [
    ("euler", "exact", False, False),
    ("midpoint", "first_order", True, False),
    ("rk4", "second_order", False, True),
    ("midpoint", "exact", True, True),
]


@pytest.mark.parametrize("scheme,coriolis,lane_dt,lane_omega", ROTATING_SOA_CASES)
def test_rotating_world_mean_on_the_soa_kernel_equals_the_generic_kernel(
    scheme, coriolis, lane_dt, lane_omega
):
    """The dispatch table's column: the mean in a rotating world takes the structure-of-arrays
    row, and equals the generic scan of
    jaximu.propagate.rotating_step at every state (float64, relative 1e-12)."""
    from jaximu.engine.propagate import _propagate

    assert (
        _dispatch.kernel(
            "mean", scheme, attitude="quaternion", lanes=64, rotating=True, on=_dispatch.CPU
        )
        == "soa_mean"
    )
    rng = np.random.default_rng(1)
    # 32 lanes: the SoA row's minimum
    x0, gyro, accel, dt, omega, g = _rotating_inputs(rng, 32, 25, lane_dt, lane_omega)
    fast, generic = (
        _propagate(
            x0,
            gyro,
            accel,
            dt,
            g,
            omega,
            scheme=scheme,
            attitude="quaternion",
            save_all=True,
            fast=f,
            coriolis=coriolis,
        )[0]
        for f in (True, False)
    )
    for a, b in ((fast.q, generic.q), (fast.p, generic.p), (fast.v, generic.v)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(np.asarray(b)).max())
    # and the world's terms are in it: the still world's states differ
    still = _propagate(
        x0,
        gyro,
        accel,
        dt,
        g,
        None,
        scheme=scheme,
        attitude="quaternion",
        save_all=False,
        fast=True,
    )[0]
    assert np.abs(np.asarray(still.p) - np.asarray(fast.p[:, -1])).max() > 1e-3


@pytest.mark.parametrize(
    "scheme,coriolis,jacobians,lane_dt,lane_omega",
    [
        ("midpoint", "exact", "analytic", True, False),
        ("rk4", "second_order", "autodiff", False, True),
        ("euler", "first_order", "analytic", False, False),
    ],
)
def test_rotating_world_covariance_on_the_soa_kernel_equals_the_generic_kernel(
    scheme, coriolis, jacobians, lane_dt, lane_omega
):
    """The covariance in a rotating world takes the structure-of-arrays rows (the world's
    error maps as block congruences, jaximu.world.covariance_step, on either layout) and
    equals the generic kernel (float64, relative 1e-12), whose covariance the
    finite-difference test above checks; the cases cover every scheme and model once and
    both Jacobian options."""
    from jaximu.engine.errorstate import _propagate_covariance

    row = "soa_cov_" + jacobians
    assert (
        _dispatch.kernel(
            "covariance",
            scheme,
            attitude="quaternion",
            jacobians=jacobians,
            lanes=4,
            rotating=True,
            on=_dispatch.CPU,
        )
        == row
    )
    rng = np.random.default_rng(2)
    x0, gyro, accel, dt, omega, g = _rotating_inputs(rng, 4, 15, lane_dt, lane_omega)
    A = rng.normal(size=(4, 15, 15))
    P0 = jnp.asarray(A @ np.swapaxes(A, -1, -2) * 1e-3)
    (s_f, P_f, _), (s_g, P_g, _) = (
        _propagate_covariance(
            x0,
            P0,
            gyro,
            accel,
            dt,
            g,
            NOISE,
            omega,
            scheme=scheme,
            attitude="quaternion",
            jacobians=jacobians,
            save_all=False,
            fast=f,
            coriolis=coriolis,
        )
        for f in (True, False)
    )
    np.testing.assert_allclose(P_f, P_g, rtol=0, atol=1e-12 * np.abs(np.asarray(P_g)).max())
    np.testing.assert_allclose(s_f.p, s_g.p, rtol=0, atol=1e-12 * np.abs(np.asarray(s_g.p)).max())
    P_still = _propagate_covariance(
        x0,
        P0,
        gyro,
        accel,
        dt,
        g,
        NOISE,
        None,
        scheme=scheme,
        attitude="quaternion",
        jacobians=jacobians,
        save_all=False,
        fast=True,
    )[1]
    assert (
        np.abs(np.asarray(P_still) - np.asarray(P_g)).max() > 1e-6 * np.abs(np.asarray(P_g)).max()
    )


def test_bad_omega_coriolis_is_refused():
    x0 = jaximu.NavState.identity(dtype=jnp.float64)
    with pytest.raises(ValueError, match=r"omega_coriolis must be the world's rotation rate"):
        jaximu.propagate(x0, np.zeros((4, 3)), np.zeros((4, 3)), 0.01, omega_coriolis=7e-5)
    with pytest.raises(ValueError, match=r"omega_coriolis contains non-finite"):
        jaximu.propagate(
            x0, np.zeros((4, 3)), np.zeros((4, 3)), 0.01, omega_coriolis=[0, np.nan, 0]
        )
