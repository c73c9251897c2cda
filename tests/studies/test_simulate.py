"""Trajectories, IMU synthesis by autodiff, noise processes, Monte Carlo, Allan deviation."""

import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats
from scipy.spatial.transform import Rotation

import jaximu
from jaximu import allan
from jaximu import simulate as sim
from jaximu.montecarlo import chi2_interval, monte_carlo

G = 9.81


def test_circle_imu_equals_hand_derived_signals():
    """Level circle of radius r at speed v: gyro (0, 0, v/r), accel (0, v²/r, g) exactly."""
    t = jnp.linspace(0.0, 20.0, 101)
    gyro, accel = sim.ideal_imu(sim.circle(radius=5.0, speed=2.0), t)
    np.testing.assert_allclose(gyro, np.tile([0, 0, 0.4], (101, 1)), rtol=0, atol=1e-12)
    np.testing.assert_allclose(accel, np.tile([0, 0.8, G], (101, 1)), rtol=0, atol=1e-12)


def test_true_states_are_consistent_with_the_pose():
    """v is dp/dt (central differences), |q| = 1, and the specific force of a general motion
    equals Rᵀ(p̈ - g) with p̈ from central differences of p (independent of jacfwd)."""
    traj = sim.lissajous()
    t = jnp.array([0.3, 1.7, 4.2])
    s = sim.true_states(traj, t)
    h = 1e-4
    p = lambda x: np.asarray(jax.vmap(traj.pose)(jnp.asarray(x))[1])  # noqa: E731
    np.testing.assert_allclose(s.v, (p(t + h) - p(t - h)) / (2 * h), atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(s.q, axis=-1), 1.0, atol=1e-14)
    acc_fd = (p(t + h) - 2 * p(t) + p(t - h)) / h**2
    _, f = sim.ideal_imu(traj, t)
    R = Rotation.from_quat(np.asarray(s.q), scalar_first=True)
    np.testing.assert_allclose(f, R.inv().apply(acc_fd - [0, 0, -G]), atol=1e-5)


def test_waypoint_spline_passes_through_waypoints_and_is_smooth():
    times = np.array([0.0, 1.0, 2.5, 4.0])
    pos = np.array([[0.0, 0, 0], [1, 0, 0.5], [1, 2, 1], [0, 3, 1]])
    quats = Rotation.from_euler(
        "ZYX", [[0, 0, 0], [1.0, 0.1, 0], [2.5, 0, 0.2], [3.5, -0.1, 0]]
    ).as_quat(scalar_first=True)
    traj = sim.waypoints(times, pos, quats)
    q, p = jax.vmap(traj.pose)(jnp.asarray(times))
    np.testing.assert_allclose(p, pos, atol=1e-12)
    ang = (
        Rotation.from_quat(np.asarray(q), scalar_first=True).inv()
        * Rotation.from_quat(quats, scalar_first=True)
    ).magnitude()
    assert ang.max() < 1e-12
    # C2: the IMU signals are continuous across a knot
    g1, a1 = sim.ideal_imu(traj, jnp.array([1.0 - 1e-7, 1.0 + 1e-7]))
    np.testing.assert_allclose(g1[0], g1[1], atol=1e-5)
    np.testing.assert_allclose(a1[0], a1[1], atol=1e-5)
    with pytest.raises(ValueError, match="strictly increasing"):
        sim.waypoints([0.0, 0.0], pos[:2])


@pytest.mark.parametrize("scheme,order", [("euler", 1), ("midpoint", 2), ("rk4", 2)])
def test_schemes_converge_at_their_order_on_simulated_motion(scheme, order):
    """A helix with wobbling attitude sampled at 100-1600 Hz: the error at 2 s falls at the
    scheme's order (RK4 is limited to 2 by the linear interpolation of the samples).
    Position errors at 200 Hz (measured): Euler 2.5e-3 m, midpoint 1.1e-6 m, RK4 1.1e-6 m."""
    traj = sim.helix()
    errors, steps = [], []
    for rate in (100, 200, 400, 800, 1600):
        t = jnp.arange(0, 2 * rate + 1) / rate
        w, f = sim.ideal_imu(traj, t)
        truth = sim.true_states(traj, t)
        end = jaximu.propagate_final(truth[0], w, f, jnp.full(2 * rate, 1.0 / rate), scheme)
        errors.append(float(jnp.linalg.norm(end.p - truth.p[-1])))
        steps.append(1.0 / rate)
    slope = np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert abs(slope - order) < 0.2, (slope, errors)
    limit = {"euler": 3e-3, "midpoint": 1.5e-6, "rk4": 1.5e-6}[scheme]
    assert errors[1] < limit


def test_white_noise_and_bias_walk_statistics():
    """Per-sample std σ/√dt and bias-walk variance σ_rw² t, each inside its 99.9% chi-square
    interval, over 400 independent streams of 500 samples."""
    noise = jaximu.ImuNoise(2e-3, 3e-2, 4e-4, 5e-3)
    n, T, dt = 400, 500, 0.01
    keys = jax.random.split(jax.random.key(3), n)
    zeros = jnp.zeros((T, 3))
    w, a, err = jax.vmap(lambda k: sim.add_noise(k, zeros, zeros, dt, noise))(keys)
    white_g = np.asarray(w - err.b_g).reshape(-1)
    white_a = np.asarray(a - err.b_a).reshape(-1)
    for x, sigma in ((white_g, 2e-3 / np.sqrt(dt)), (white_a, 3e-2 / np.sqrt(dt))):
        lo, hi = stats.chi2.ppf([0.0005, 0.9995], x.size - 1) / (x.size - 1)
        assert lo < x.var(ddof=1) / sigma**2 < hi
    for end, srw in (
        (np.asarray(err.b_g_end).reshape(-1), 4e-4),
        (np.asarray(err.b_a_end).reshape(-1), 5e-3),
    ):
        k = end.size
        lo, hi = stats.chi2.ppf([0.0005, 0.9995], k) / k
        assert lo < np.mean(end**2) / (srw**2 * T * dt) < hi


def test_turn_on_bias_scale_and_misalignment():
    S = np.array([[0.01, 0.002, 0.0], [-0.001, -0.02, 0.003], [0.0, 0.001, 0.005]])
    f = jnp.tile(jnp.array([0.5, -1.0, G]), (10, 1))
    zero = jaximu.ImuNoise(0.0, 0.0)
    _, a, err = sim.add_noise(
        jax.random.key(0),
        jnp.zeros((10, 3)),
        f,
        0.01,
        zero,
        b_a0=jnp.array([0.1, 0.2, 0.3]),
        accel_misalignment=S,
    )
    np.testing.assert_allclose(a, np.asarray(f) @ (np.eye(3) + S).T + [0.1, 0.2, 0.3], atol=1e-12)
    np.testing.assert_allclose(err.b_a, np.tile([0.1, 0.2, 0.3], (10, 1)))


def test_chi2_interval_matches_scipy():
    """Wilson-Hilferty against scipy, at the tolerances the docstring states."""
    for dof, tol in ((15, 1.3e-2), (150, 2e-4), (1500, 5e-6), (30000, 6e-8)):
        np.testing.assert_allclose(
            chi2_interval(dof, 0.99), stats.chi2.ppf([0.005, 0.995], dof), rtol=tol
        )


@pytest.fixture(scope="module")
def mc_setup():
    traj = sim.helix()
    times = np.arange(0, 1.0 + 1e-9, 0.005)  # 200 steps
    P0 = np.diag([1e-6] * 3 + [1e-6] * 3 + [1e-6] * 3 + [1e-8] * 3 + [1e-6] * 3)
    noise = jaximu.ImuNoise(2e-3, 2e-2, 1e-4, 2e-3)
    return traj, times, P0, noise


def test_monte_carlo_nees_is_consistent_and_a_wrong_model_is_detected(mc_setup):
    """N = 2000 runs: the average NEES lies in its 99% chi-square interval at every recorded
    time; with a filter that assumes twice the noise it falls far below."""
    traj, times, P0, noise = mc_setup
    # 4 recorded times at 99%: a false alarm for ~3% of keys (the times are correlated). With
    # the counter-based generator key 0 draws an average NEES 2.9σ low at t = 0.25 s; over
    # 12 keys the z-scores of the 4 times have mean -0.28 (SE 0.29) and sd 1.13: no bias.
    res = monte_carlo(
        traj, times, P0, noise, 2000, jax.random.key(1), record_every=50, confidence=0.99
    )
    assert res.nees is None and res.times[-1] == pytest.approx(1.0)
    assert np.all(res.consistent), (res.nees_mean, res.nees_bounds)
    # The empirical covariance agrees with the predicted one: relative Frobenius error of the
    # θ, p, v block below 12% (GTSAM's testImuFactorCovariance criterion).
    C, P = res.error_cov[-1][:9, :9], res.predicted_cov[-1][:9, :9]
    assert np.linalg.norm(C - P) / np.linalg.norm(P) < 0.12
    twice = jaximu.ImuNoise(*(2 * np.array([2e-3, 2e-2, 1e-4, 2e-3])))
    # (the same record times as above: the study's compiled chunk serves this one too)
    wrong = monte_carlo(
        traj, times, P0, (noise, twice), 2000, jax.random.key(0), record_every=50, confidence=0.99
    )
    assert wrong.nees_mean[-1] < 0.6 * wrong.nees_bounds[0]
    assert np.abs(res.discretization_error[-1][3:6]).max() < 1e-2


def test_sharded_and_single_device_runs_agree(tmp_path):
    """Four (forced host) devices vs one, same key: the same statistics."""
    script = textwrap.dedent("""
        import json, sys
        import jax
        jax.config.update("jax_enable_x64", True)
        import numpy as np, jaximu
        from jaximu import simulate as sim
        from jaximu.montecarlo import monte_carlo
        assert len(jax.devices()) == 4
        times = np.arange(0, 0.2 + 1e-9, 0.005)
        P0 = np.eye(15) * 1e-6
        out = {}
        for shard in (True, False):
            r = monte_carlo(sim.circle(), times, P0, jaximu.ImuNoise.euroc(), 64,
                            jax.random.key(7), chunk_size=16, record_every=40, shard=shard,
                            keep_nees=True)
            out[str(shard)] = [r.nees.tolist(), r.error_cov.tolist()]
        print(json.dumps(out))
    """)
    # four host devices, on top of the parent's XLA flags (conftest.py: the fast-compile
    # options; without them the child's two compilations take ~1.6x longer)
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4"
    env = dict(os.environ, XLA_FLAGS=flags.strip())
    res = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300
    )
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    np.testing.assert_allclose(out["True"][0], out["False"][0], rtol=1e-10)
    np.testing.assert_allclose(out["True"][1], out["False"][1], rtol=1e-10, atol=1e-20)


def test_allan_deviation_recovers_the_noise_densities():
    """3 hours of a simulated static gyro at 100 Hz (EuRoC ADIS16448 densities): the fit
    recovers the white-noise density within 10% and the random walk within 25%."""
    dt, n = 0.01, 3 * 3600 * 100
    sw, srw = 1.6968e-04, 1.9393e-05
    rng = np.random.default_rng(5)
    y = rng.normal(size=(n, 3)) * sw / np.sqrt(dt) + np.cumsum(
        rng.normal(size=(n, 3)) * srw * np.sqrt(dt), axis=0
    )
    taus, adev = allan.allan_deviation(y, dt)
    fit = allan.fit_noise(taus, adev)
    np.testing.assert_allclose(fit.white, sw, rtol=0.10)
    np.testing.assert_allclose(fit.random_walk, srw, rtol=0.25)
    # the pure white-noise slope: σ(τ) √τ is constant at short τ
    short = taus < 1.0
    np.testing.assert_allclose(adev[short, 0] * np.sqrt(taus[short]), sw, rtol=0.1)


def test_allan_deviation_of_white_noise_matches_the_closed_form():
    """For white noise the overlapping Allan variance at τ = m dt is σ²/(m dt²)·dt... i.e.
    σ_w²/τ; checked at τ = dt against the plain variance of pairwise differences."""
    rng = np.random.default_rng(0)
    y = rng.normal(size=200_000)
    taus, adev = allan.allan_deviation(y, 1.0, taus=[1.0])
    expected = np.sqrt(0.5 * np.mean(np.diff(y) ** 2))
    np.testing.assert_allclose(adev[0], expected, rtol=1e-12)
    with pytest.raises(ValueError, match="at least 10 samples"):
        allan.allan_deviation(np.zeros(5), 1.0)
