"""Φ, G, Q_d and covariance propagation against finite differences, a numpy transcription of
OpenVINS's discrete model, GTSAM's one-step covariance, and Monte Carlo statistics."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

import jaximu
from jaximu.errorstate import blocks_autodiff, dense_from_blocks, jacobians_autodiff
from jaximu.integrators import get_attitude, nav_step
from jaximu.sensor import moved_specific_force
from jaximu.state import boxminus, boxplus

G = 9.81


def random_state(seed, batch=()):
    rng = np.random.default_rng(seed)
    n = int(np.prod(batch, dtype=int))
    q = Rotation.random(n, random_state=seed).as_quat(scalar_first=True).reshape(batch + (4,))
    return jaximu.NavState(
        jnp.asarray(q),
        *(jnp.asarray(rng.normal(size=batch + (3,)) * s) for s in (1.0, 1.0, 0.02, 0.2)),
    )


def random_samples(seed, batch=()):
    rng = np.random.default_rng(seed)
    w0, w1 = rng.normal(size=(2,) + batch + (3,)) * 1.5
    a0, a1 = rng.normal(size=(2,) + batch + (3,)) * 3 + [0, 0, G]
    return w0, a0, w1, a1


G_W = jnp.array([0.0, 0.0, -G])


@functools.partial(jax.jit, static_argnames=("scheme", "attitude"))
def _step_error(delta, noise, state, w0, a0, w1, a1, h, *, scheme, attitude):
    att = get_attitude(attitude)
    nominal = nav_step(scheme, att, state, w0, a0, w1, a1, h, G_W)
    moved = nav_step(scheme, att, boxplus(state, delta), w0, a0, w1, a1, h, G_W, noise=noise)
    return boxminus(moved, nominal)


def central_differences(fn, n, eps=1e-6):
    cols = []
    for i in range(n):
        e = np.zeros(n)
        e[i] = eps
        cols.append((np.asarray(fn(jnp.asarray(e))) - np.asarray(fn(jnp.asarray(-e)))) / (2 * eps))
    return np.stack(cols, axis=-1)


@pytest.mark.parametrize("attitude", jaximu.ATTITUDES)
@pytest.mark.parametrize("scheme", jaximu.SCHEMES)
def test_autodiff_jacobians_equal_central_differences(scheme, attitude):
    """Φ and G by jacfwd through boxplus/boxminus equal central differences (float64, 1e-6
    rel), and so do the blockwise ones (9 directions)."""
    state = random_state(1)
    if attitude == "euler_angles":  # keep away from gimbal lock
        state = state.replace(
            q=jnp.asarray(Rotation.from_euler("ZYX", [0.5, 0.3, -0.2]).as_quat(scalar_first=True))
        )
    w0, a0, w1, a1 = random_samples(2)
    h = jnp.asarray(0.02)
    Phi, G_ = jacobians_autodiff(scheme, get_attitude(attitude), state, w0, a0, w1, a1, h, G_W)
    kw = dict(state=state, w0=w0, a0=a0, w1=w1, a1=a1, h=h, scheme=scheme, attitude=attitude)
    fd_phi = central_differences(lambda d: _step_error(d, jnp.zeros(12), **kw), 15)
    fd_g = central_differences(lambda n: _step_error(jnp.zeros(15), n, **kw), 12)
    scale_phi, scale_g = np.abs(fd_phi).max(), np.abs(fd_g).max()
    np.testing.assert_allclose(Phi, fd_phi, rtol=0, atol=1e-6 * scale_phi)
    np.testing.assert_allclose(G_, fd_g, rtol=0, atol=1e-6 * scale_g)
    # The 9-direction blockwise Jacobians the covariance propagation uses, assembled with
    # the structural blocks, equal the dense 15+12-direction ones.
    b = blocks_autodiff(scheme, get_attitude(attitude), state, w0, a0, w1, a1, h, G_W)
    Phi_b, G_b = dense_from_blocks(b)
    np.testing.assert_allclose(Phi_b, Phi, rtol=0, atol=1e-13 * np.abs(Phi).max())
    np.testing.assert_allclose(G_b, G_, rtol=0, atol=1e-13 * np.abs(G_).max())


def test_blockwise_autodiff_broadcasts_batches_and_moves_the_specific_force_with_a_lever():
    """The 9-direction blocks of one state and ``(2, 3)`` batched samples moved from a
    sensor at a lever arm equal central differences of the step whose specific force is
    corrected at the perturbed rate (:func:`jaximu.sensor.moved_specific_force`), per element."""
    att = get_attitude("quaternion")
    state = random_state(5)
    w0, a0, w1, a1 = (jnp.asarray(x) for x in random_samples(6, (2, 3)))
    h, r = jnp.asarray(0.01), jnp.asarray([0.1, -0.2, 0.05])
    b = blocks_autodiff("midpoint", att, state, w0, a0, w1, a1, h, G_W, lever=r)
    Phi_b, _ = dense_from_blocks(b)
    assert Phi_b.shape == (2, 3, 15, 15)
    nominal = nav_step("midpoint", att, state, w0, a0, w1, a1, h, G_W)

    @jax.jit
    def error(delta):
        at = boxplus(state, delta)
        a0_ = moved_specific_force(a0, w0 - state.b_g, w0 - at.b_g, r)
        a1_ = moved_specific_force(a1, w1 - state.b_g, w1 - at.b_g, r)
        return boxminus(nav_step("midpoint", att, at, w0, a0_, w1, a1_, h, G_W), nominal)

    fd = central_differences(error, 15)
    np.testing.assert_allclose(Phi_b, fd, rtol=0, atol=1e-6 * np.abs(fd).max())


@pytest.mark.parametrize("attitude", ["quaternion", "matrix"])
@pytest.mark.parametrize("scheme", jaximu.SCHEMES)
def test_analytic_jacobians_equal_autodiff(scheme, attitude):
    state = random_state(3, (4,))
    w0, a0, w1, a1 = random_samples(4, (4,))
    h = jnp.asarray([0.005, 0.01, 0.1, 0.3])  # up to large steps, where the forms would differ
    kw = dict(gyro_next=w1, accel_next=a1, scheme=scheme, attitude=attitude)
    Phi_ad, G_ad = jaximu.step_jacobians(state, w0, a0, h, method="autodiff", **kw)
    Phi_an, G_an = jaximu.step_jacobians(state, w0, a0, h, method="analytic", **kw)
    np.testing.assert_allclose(Phi_an, Phi_ad, rtol=0, atol=1e-10)
    np.testing.assert_allclose(G_an, G_ad, rtol=0, atol=1e-10)


def test_analytic_jacobians_at_zero_rate():
    state = random_state(5)
    zeros = jnp.zeros(3)
    for scheme in jaximu.SCHEMES:
        Phi_ad, G_ad = jaximu.step_jacobians(
            state, zeros, jnp.array([0, 0, G]), 0.01, scheme=scheme, method="autodiff"
        )
        Phi_an, G_an = jaximu.step_jacobians(
            state, zeros, jnp.array([0, 0, G]), 0.01, scheme=scheme, method="analytic"
        )
        assert np.all(np.isfinite(Phi_ad)) and np.all(np.isfinite(G_ad))
        np.testing.assert_allclose(Phi_an, Phi_ad, rtol=0, atol=1e-12)
        np.testing.assert_allclose(G_an, G_ad, rtol=0, atol=1e-12)


def openvins_discrete_F_G(R_wb, omega, f, dt):
    """OpenVINS's discrete Φ and G (docs/propagation-discrete, Propagator.cpp), transcribed in
    numpy and moved to our conventions: OpenVINS's R_k is R_GtoI = R_WBᵀ, its gravity is
    subtracted (+g up), its JPL left error equals our right error on R_WB. Noise order
    [n_g, n_a, n_wg, n_wa], error order [θ, p, v, b_g, b_a]."""

    def sk(v):
        return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])

    R_GtoI = R_wb.T
    dR = Rotation.from_rotvec(-omega * dt).as_matrix()  # R_GtoI,k+1 R_GtoI,kᵀ = Exp(-ω dt)
    th = -omega * dt  # Jr is evaluated at Log(ΔR) = -ω dt
    n = np.linalg.norm(th)
    K = sk(th / n)
    Jr = np.eye(3) - (1 - np.cos(n)) / n * K + (n - np.sin(n)) / n * K @ K
    F = np.eye(15)
    F[0:3, 0:3] = dR
    F[0:3, 9:12] = -dR @ Jr * dt
    F[3:6, 0:3] = -0.5 * R_GtoI.T @ sk(f * dt**2)
    F[3:6, 6:9] = np.eye(3) * dt
    F[3:6, 12:15] = -0.5 * R_GtoI.T * dt**2
    F[6:9, 0:3] = -R_GtoI.T @ sk(f * dt)
    F[6:9, 12:15] = -R_GtoI.T * dt
    Gm = np.zeros((15, 12))
    Gm[0:3, 0:3] = -dR @ Jr * dt
    Gm[3:6, 3:6] = -0.5 * R_GtoI.T * dt**2
    Gm[6:9, 3:6] = -R_GtoI.T * dt
    Gm[9:12, 6:9] = np.eye(3) * dt
    Gm[12:15, 9:12] = np.eye(3) * dt
    return F, Gm


def test_euler_jacobians_equal_openvins_discrete_model():
    state = random_state(6)
    w, a = np.array([0.4, -1.1, 0.7]), np.array([0.3, 1.2, 9.5])
    dt = 0.01
    omega = w - np.asarray(state.b_g)
    f = a - np.asarray(state.b_a)
    F, Gm = openvins_discrete_F_G(np.asarray(state.R), omega, f, dt)
    for method in ("autodiff", "analytic"):
        Phi, G_ = jaximu.step_jacobians(state, w, a, dt, method=method)
        np.testing.assert_allclose(Phi, F, rtol=0, atol=1e-13)
        np.testing.assert_allclose(G_, Gm, rtol=0, atol=1e-13)


# --------------------------------------------------------------------------- covariance


def test_one_step_covariance_matches_gtsam_check_covariance():
    """GTSAM testImuFactor CheckCovariance: one step acc (0.1,0,0), ω (π/100,0,0), dt 0.5 with
    σ_g = 0.5°/60 /√Hz... (kGyroSigma) and σ_a = 0.1/60: rot 1.0577e-08, vel 1.38889e-06, pos-vel
    3.47222e-07, pos σ_a² dt³/4 = 8.68e-08 (GTSAM adds integrationCovariance 1e-4·dt on top:
    5.00868e-05 - 5e-05)."""
    noise = jaximu.ImuNoise(np.deg2rad(0.5) / 60, 0.1 / 60)
    s0 = jaximu.NavState.identity(dtype=jnp.float64)
    _, P = jaximu.propagate_covariance_final(
        s0, jnp.zeros((15, 15)), [[np.pi / 100, 0, 0]], [[0.1, 0, 0]], [0.5], noise
    )
    np.testing.assert_allclose(np.diag(P)[0:3], 1.0577e-08, rtol=1e-4)
    np.testing.assert_allclose(np.diag(P)[3:6], 5.00868e-05 - 5e-5, rtol=2e-3)
    np.testing.assert_allclose(np.diag(P)[6:9], 1.38889e-06, rtol=1e-5)
    np.testing.assert_allclose(np.diag(P[3:6, 6:9]), 3.47222e-07, rtol=1e-5)
    off = P.at[jnp.diag_indices(15)].set(0).at[3:6, 6:9].set(0).at[6:9, 3:6].set(0)
    assert np.abs(off[:9, :9]).max() < 1e-12


def _trajectory(seed, T, batch=()):
    rng = np.random.default_rng(seed)
    gyro = rng.normal(size=batch + (T, 3)) * 0.8
    accel = rng.normal(size=batch + (T, 3)) * 2 + [0, 0, G]
    return gyro, accel


def _random_P0(seed):
    A = np.random.default_rng(seed).normal(size=(15, 15)) * 0.03
    return A @ A.T + 1e-6 * np.eye(15)


@pytest.mark.parametrize("scheme", jaximu.SCHEMES)
def test_structured_analytic_covariance_equals_dense_autodiff(scheme):
    gyro, accel = _trajectory(7, 60, (2,))
    state = random_state(8, (2,))
    noise = jaximu.ImuNoise(
        jnp.array([1e-3, 2e-3, 3e-3]), 2e-2, 1e-4, jnp.array([1e-3, 2e-3, 5e-4])
    )
    P0 = _random_P0(9)
    dt = np.random.default_rng(10).uniform(0.002, 0.02, size=60)
    s1, P1 = jaximu.propagate_covariance(
        state, P0, gyro, accel, dt, noise, scheme, jacobians="analytic"
    )
    s2, P2 = jaximu.propagate_covariance(
        state, P0, gyro, accel, dt, noise, scheme, jacobians="autodiff"
    )
    np.testing.assert_allclose(P1, P2, rtol=0, atol=1e-10 * np.abs(P2).max())
    np.testing.assert_allclose(s1.p, s2.p, rtol=0, atol=1e-14)
    s3 = jaximu.propagate(state, gyro, accel, dt, scheme)
    np.testing.assert_allclose(s1.p, s3.p, rtol=0, atol=1e-14)


def test_covariance_is_symmetric_psd_and_final_matches():
    gyro, accel = _trajectory(11, 400)
    state = random_state(12)
    noise = jaximu.ImuNoise.euroc()
    P0 = _random_P0(13)
    _, P = jaximu.propagate_covariance(state, P0, gyro, accel, 0.005, noise, "rk4")
    P = np.asarray(P)
    np.testing.assert_array_equal(P, np.swapaxes(P, -1, -2))
    eig = np.linalg.eigvalsh(P)
    assert eig.min() > -1e-12 * eig.max()
    _, P_final = jaximu.propagate_covariance_final(state, P0, gyro, accel, 0.005, noise, "rk4")
    # the final covariance runs on the SoA kernel (soa_cov_analytic), every covariance on the
    # generic one: the same formulas in another order, equal to rounding (400 steps)
    np.testing.assert_allclose(P_final, P[-1], rtol=0, atol=1e-13 * np.abs(P).max())


def test_covariance_growth_of_still_imu_matches_closed_form():
    """Still, level IMU, white noise only, P0 = 0, Euler: P_θθ = σ_g² t, P_vv ≈ σ_a² t + the
    tilt-coupling g² σ_g² t³/3 on x, y (closed form of the continuous model; the discrete
    sums equal it to O(dt))."""
    sg, sa = 1e-3, 2e-2
    n, dt = 2000, 0.005
    t = n * dt
    _, P = jaximu.propagate_covariance_final(
        jaximu.NavState.identity(dtype=jnp.float64),
        np.zeros((15, 15)),
        np.zeros((n, 3)),
        np.tile([0, 0, G], (n, 1)),
        dt,
        jaximu.ImuNoise(sg, sa),
    )
    np.testing.assert_allclose(np.diag(P)[0:3], sg**2 * t, rtol=1e-12)
    expected_vv = sa**2 * t + G**2 * sg**2 * t**3 / 3
    np.testing.assert_allclose(np.diag(P)[6:8], expected_vv, rtol=2e-3)
    np.testing.assert_allclose(P[8, 8], sa**2 * t, rtol=1e-12)


@pytest.fixture(scope="module")
def monte_carlo_runs():
    """N = 2000 noisy copies of one IMU stream (per-sample white noise σ/√dt, bias random walk
    σ_rw·√dt per sample, initial errors drawn from P0), propagated with every scheme."""
    N, T, dt = 2000, 100, 0.01
    rng = np.random.default_rng(14)
    noise = jaximu.ImuNoise(2e-2, 5e-2, 1e-2, 5e-2)
    gyro, accel = _trajectory(15, T + 1)
    state = random_state(16)
    # Initial errors of ~0.4° and ~1 cm: small enough for the linearisation to hold (with
    # 10x the variance the second-order terms push the average NEES to 15.56 > 15.32).
    P0 = _random_P0(17) * 0.01
    L = np.linalg.cholesky(P0)
    d0 = (L @ rng.normal(size=(N, 15, 1)))[..., 0]
    starts = boxplus(
        jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (N,) + x.shape), state),
        jnp.asarray(d0),
    )
    sg, sa, sbg, sba = noise.sample_std(dt)
    # The estimator sees the clean samples and keeps its biases constant. The truth starts at
    # x ⊞ δ0 and its bias walks, b(k) = b_start + W(k) with W(k) the sum of the steps before
    # sample k; its rate is ω = w_m - b(k) - n_k, i.e. the truth propagates the samples
    # w_m - W(k) - n_k with the constant b_start (likewise for the accelerometer).
    bg_walk = np.cumsum(rng.normal(size=(N, T + 1, 3)) * np.asarray(sbg), axis=1)
    ba_walk = np.cumsum(rng.normal(size=(N, T + 1, 3)) * np.asarray(sba), axis=1)
    bg_walk = np.concatenate([np.zeros((N, 1, 3)), bg_walk[:, :-1]], axis=1)
    ba_walk = np.concatenate([np.zeros((N, 1, 3)), ba_walk[:, :-1]], axis=1)
    noisy_gyro = gyro - bg_walk - rng.normal(size=(N, T + 1, 3)) * np.asarray(sg)
    noisy_accel = accel - ba_walk - rng.normal(size=(N, T + 1, 3)) * np.asarray(sa)
    return dict(
        N=N,
        T=T,
        dt=dt,
        noise=noise,
        gyro=gyro,
        accel=accel,
        state=state,
        P0=P0,
        starts=starts,
        noisy_gyro=noisy_gyro,
        noisy_accel=noisy_accel,
        bg_walk=bg_walk,
        ba_walk=ba_walk,
    )


@pytest.mark.parametrize("scheme", ["euler"])
def test_monte_carlo_nees_is_consistent(scheme, monte_carlo_runs):
    """The linearised covariance matches the spread of N = 2000 noisy runs: the average NEES
    of the 15-dim error at the end lies in its two-sided 99% chi-square interval
    (χ²(15N)/N), and a covariance from a 4× wrong noise model is rejected.

    Truth: runs with the noisy samples started from x ⊞ δ0 (δ0 ~ N(0, P0)), with the bias
    state carried along the true bias walk; estimate: the noise-free propagation from x.
    Euler is used because its per-step noise model (white noise held over the step) is the
    one the samples were drawn from.
    """
    c = monte_carlo_runs
    T, N = c["T"], c["N"]
    truth = jaximu.propagate(
        c["starts"], c["noisy_gyro"][:, :T], c["noisy_accel"][:, :T], c["dt"], scheme
    )
    final_truth = truth[:, -1].replace(
        b_g=truth.b_g[:, -1] + c["bg_walk"][:, T], b_a=truth.b_a[:, -1] + c["ba_walk"][:, T]
    )
    est, P = jaximu.propagate_covariance_final(
        c["state"], c["P0"], c["gyro"][:T], c["accel"][:T], c["dt"], c["noise"], scheme
    )
    err = np.asarray(boxminus(final_truth, est))
    nees = np.einsum("ni,ij,nj->n", err, np.linalg.inv(np.asarray(P)), err)
    lo, hi = stats.chi2.ppf([0.005, 0.995], 15 * N) / N
    assert lo < nees.mean() < hi, (nees.mean(), lo, hi)
    wrong = jaximu.ImuNoise(*(4 * np.asarray(x) for x in (2e-2, 5e-2, 1e-2, 5e-2)))
    _, P_wrong = jaximu.propagate_covariance_final(
        c["state"], c["P0"], c["gyro"][:T], c["accel"][:T], c["dt"], wrong, scheme
    )
    nees_wrong = np.einsum("ni,ij,nj->n", err, np.linalg.inv(np.asarray(P_wrong)), err)
    assert not lo < nees_wrong.mean() < hi


def test_gradient_of_covariance_wrt_noise_parameters_matches_finite_differences():
    gyro, accel = _trajectory(18, 30)
    state = random_state(19)
    P0 = _random_P0(20)

    def loss(params):
        noise = jaximu.ImuNoise(*params)
        _, P = jaximu.propagate_covariance_final(state, P0, gyro, accel, 0.01, noise)
        return jnp.trace(P[:9, :9]) + 3.0 * P[4, 7]

    # The gradient and the differences' values from one program.
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    params = jnp.array([1e-2, 3e-2, 2e-3, 4e-2])
    grad = value_and_grad(params)[1]
    # P is linear in the variances, so the loss is quadratic in the densities and central
    # differences are exact up to rounding for any step: a large step keeps rounding small.
    fd = central_differences(lambda e: value_and_grad(params + e)[0], 4, eps=1e-4)
    assert np.all(np.isfinite(grad))
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


def test_discrete_process_noise_is_g_qc_gt():
    state = random_state(21)
    _, G_ = jaximu.step_jacobians(state, [0.1, 0.2, 0.3], [0.0, 0.5, 9.8], 0.01)
    noise = jaximu.ImuNoise(1e-3, 2e-2, 3e-4, 4e-3)
    Qc = np.diag(np.repeat(np.array([1e-3, 2e-2, 3e-4, 4e-3]) ** 2 / 0.01, 3))
    np.testing.assert_allclose(
        jaximu.discrete_process_noise(G_, noise, 0.01),
        np.asarray(G_) @ Qc @ np.asarray(G_).T,
        rtol=1e-13,
        atol=1e-30,
    )


def test_float32_covariance_stays_finite_and_close():
    gyro, accel = _trajectory(22, 2000)
    out = {}
    for dtype in (jnp.float32, jnp.float64):
        state = jaximu.NavState.identity(dtype=dtype)
        _, P = jaximu.propagate_covariance_final(
            state,
            np.eye(15, dtype=dtype) * 1e-4,
            gyro.astype(dtype),
            accel.astype(dtype),
            np.asarray(0.005, dtype),
            jaximu.ImuNoise.euroc(),
        )
        out[dtype] = np.asarray(P, np.float64)
    assert np.all(np.isfinite(out[jnp.float32]))
    np.testing.assert_allclose(
        out[jnp.float32], out[jnp.float64], rtol=0, atol=1e-4 * np.abs(out[jnp.float64]).max()
    )


@pytest.mark.parametrize(
    "kwargs,message",
    [
        (dict(P0=np.eye(14)), r"P0 must have shape \(\.\.\., 15, 15\)"),
        (dict(P0=np.eye(15) + np.triu(np.ones((15, 15)), 1)), "P0 is not symmetric"),
        (dict(P0=-np.eye(15)), "P0 is not positive semi-definite"),
        (dict(P0=np.full((15, 15), np.nan)), "P0 contains non-finite"),
        (dict(noise=jaximu.ImuNoise(-1e-3, 1e-2)), "must be non-negative"),
        (dict(noise=jaximu.ImuNoise(np.ones(2), 1e-2)), "must be a scalar or have shape"),
        (dict(noise=(1e-3, 1e-2, 0, 0)), "noise must be a jaximu.ImuNoise"),
        (dict(jacobians="numeric"), "unknown jacobians 'numeric'"),
        (dict(jacobians="analytic", attitude="euler_angles"), "analytic Jacobians are derived"),
    ],
)
def test_covariance_bad_input(kwargs, message):
    args = dict(P0=np.eye(15) * 1e-4, noise=jaximu.ImuNoise.euroc())
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        jaximu.propagate_covariance(
            jaximu.NavState.identity(dtype=jnp.float64),
            args.pop("P0"),
            np.zeros((5, 3)),
            np.zeros((5, 3)),
            0.01,
            args.pop("noise"),
            **args,
        )


def test_step_jacobians_bad_method():
    with pytest.raises(ValueError, match="unknown Jacobian method"):
        jaximu.step_jacobians(
            jaximu.NavState.identity(), np.zeros(3), np.zeros(3), 0.01, method="fd"
        )
