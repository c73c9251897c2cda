"""Monte Carlo studies at scale: the counter-based generator, regeneration of single runs,
chunk and process independence, streaming statistics, the EKF update and the filter study.

Every check is against something independent of the code under test: ``jax.random``'s own
Threefry block function and a plain-numpy transcription, the moments of the normal
distribution with stated confidence, scipy's Kolmogorov-Smirnov test, ``jaximu.propagate``
of the regenerated samples, a plain-numpy Joseph-form update with scipy rotations, finite
differences, and χ² intervals.
"""

import json
import os
import socket
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
from jaximu import simulate as sim
from jaximu.engine import _dispatch
from jaximu.errorstate import ekf_update, position_jacobian
from jaximu.kernels import rng as _rng
from jaximu.state import NavState, boxminus
from jaximu.studies.montecarlo import PositionFix, _chunk_runs, load_result, monte_carlo, sample_run

# A statistic outside ±Z standard errors fails: two-sided false-alarm rate 5.7e-7 per check.
Z = 5.0


# --------------------------------------------------------------------------- generator


def test_threefry_is_jax_random_block_function_and_the_numpy_transcription():
    from jax.extend.random import threefry_2x32

    rng = np.random.default_rng(0)
    k = rng.integers(0, 2**32, 2, dtype=np.uint32)
    c = rng.integers(0, 2**32, 2000, dtype=np.uint32)
    ref = np.asarray(threefry_2x32(jnp.asarray(k), jnp.asarray(c)))
    a, b = _rng.threefry2x32(k[0], k[1], c[:1000], c[1000:])
    np.testing.assert_array_equal(np.r_[a, b], ref)
    na, nb = _rng.np_threefry2x32(k[0], k[1], c[:1000], c[1000:])
    np.testing.assert_array_equal(np.r_[na, nb], ref)


def test_threefry_rounds_written_out_give_the_loops_words():
    """The accelerator's hash (rounds written out, no loop) gives jax.random's words, as the
    CPU's loop does: the route changes no number."""
    from jax.extend.random import threefry_2x32

    rng = np.random.default_rng(1)
    k = rng.integers(0, 2**32, 2, dtype=np.uint32)
    c = rng.integers(0, 2**32, 2000, dtype=np.uint32)
    ref = np.asarray(threefry_2x32(jnp.asarray(k), jnp.asarray(c)))
    a, b = jax.jit(lambda c0, c1: _rng.threefry2x32(k[0], k[1], c0, c1, loop=False))(
        c[:1000], c[1000:]
    )
    np.testing.assert_array_equal(np.r_[a, b], ref)


@pytest.fixture(scope="module")
def draws():
    """16 streams × 256 runs × 256 steps of normals, float64 (2^20 numbers)."""
    keys = _rng.stream_keys(jax.random.key(3), 8)
    run = jnp.arange(256, dtype=jnp.uint32)[:, None]
    step = jnp.arange(256, dtype=jnp.uint32)[None, :]
    z = jax.jit(lambda k: jnp.stack(_rng.normals(k, run, step, 8, jnp.float64)))(keys)
    return np.asarray(z)  # (16, runs, steps)


def test_generator_moments_to_fourth_order(draws):
    """Mean 0, variance 1, skewness 0, E z⁴ = 3, each within Z standard errors of its sample
    estimate (SEs 1, √2, √6, √96 over √n), per stream and pooled."""
    for z in list(draws.reshape(16, -1)) + [draws.ravel()]:
        n = z.size
        for stat, expected, se in (
            (z.mean(), 0.0, 1.0),
            ((z**2).mean(), 1.0, 2**0.5),
            ((z**3).mean(), 0.0, 6**0.5),
            ((z**4).mean(), 3.0, 96**0.5),
        ):
            assert abs(stat - expected) < Z * se / n**0.5, (stat, expected)


def test_generator_kolmogorov_smirnov(draws):
    """KS against the standard normal, pooled and per stream: p > 1e-4 (family-wise
    false-alarm rate 1.7e-3)."""
    assert stats.kstest(draws.ravel(), "norm").pvalue > 1e-4
    for z in draws.reshape(16, -1):
        assert stats.kstest(z, "norm").pvalue > 1e-4


def test_generator_correlation_between_steps_runs_and_streams(draws):
    """Sample correlations of consecutive steps, consecutive runs and of every pair of
    streams (including the two normals of one Box-Muller pair) within Z/√n of zero."""

    def corr(a, b):
        a, b = a.ravel(), b.ravel()
        return np.corrcoef(a, b)[0, 1], a.size

    checks = [corr(draws[:, :, :-1], draws[:, :, 1:]), corr(draws[:, :-1], draws[:, 1:])]
    for i in range(16):
        for j in range(i + 1, 16):
            checks.append(corr(draws[i], draws[j]))
    for r, n in checks:
        assert abs(r) < Z / n**0.5, (r, n)
    # squared values too: Box-Muller's two outputs share one radius (independent only as
    # a pair), which a linear correlation would not see
    r, n = corr(draws[0] ** 2, draws[1] ** 2)
    assert abs(r) < Z / n**0.5


# --------------------------------------------------------------------------- studies


# The study the tests below share: 57 runs in chunks of at most 16, which monte_carlo evens
# out over the chunks in flight (15 runs each with 2 or 4 of them), the last chunk padded.
N_RUNS = 57
STUDY = {"chunk_size": 16, "record_every": 25, "n_keep": 4, "scheme": "midpoint"}


def study_setup():
    """(trajectory, times, P0, noise) of the shared study (also built by the processes of
    test_two_processes_give_the_statistics_of_one)."""
    traj = sim.helix()
    times = np.arange(0, 0.5 + 1e-9, 0.005)  # 100 steps
    P0 = np.diag([1e-6] * 3 + [1e-6] * 3 + [1e-6] * 3 + [1e-8] * 3 + [1e-6] * 3)
    noise = jaximu.ImuNoise(2e-3, 2e-2, 1e-4, 2e-3)
    return traj, times, P0, noise


def test_chunks_fill_every_round():
    """Chunks go out in rounds of ``slots``: their size keeps the fewest rounds that chunks
    of ``chunk_size`` would need, is at most ``chunk_size`` and at least 2 lanes, and
    leaves less than one chunk of idle lanes in the last round."""
    for n, size, slots in [
        (10_000, 2048, 2),
        (10_000, 2048, 1),
        (57, 16, 2),
        (57, 16, 4),
        (3, 1, 2),
        (1_000_000, 2048, 3),
        (5, 100, 8),
        (4097, 4096, 2),
    ]:
        chunk = _chunk_runs(n, size, slots)
        n_chunks = -(-n // chunk)
        rounds = -(-n_chunks // slots)
        assert 2 <= chunk <= max(2, min(size, n))
        assert rounds == max(1, -(-n // (slots * max(size, 2))))
        assert rounds * slots * chunk - n < chunk or n_chunks < slots
    assert _chunk_runs(10_000, 2048, 2) == 1667  # three full rounds, not 2048 × 5


@pytest.fixture(scope="module")
def setup():
    return study_setup()


@pytest.fixture(scope="module")
def study(setup):
    traj, times, P0, noise = setup
    return monte_carlo(traj, times, P0, noise, N_RUNS, jax.random.key(5), keep_nees=True, **STUDY)


@pytest.mark.default_codegen
def test_chunk_size_and_devices_do_not_change_the_statistics(setup, study):
    traj, times, P0, noise = setup
    # Chunks of 2 runs (29 of them, the last padded) against the study's 4 chunks of 15:
    # other lanes, other chunk boundaries and another order of the streamed sums, with the
    # lane kernel of `one` below (chunks of one run are 2 lanes), so no program is compiled
    # for this study alone (chunks of all 57 runs were one more lane kernel to compile with
    # XLA's default code generation).
    other = monte_carlo(
        traj,
        times,
        P0,
        noise,
        N_RUNS,
        jax.random.key(5),
        keep_nees=True,
        shard=False,
        **dict(STUDY, chunk_size=2),
    )
    scale = np.abs(study.error_cov).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(other.error_cov / scale, study.error_cov / scale, rtol=0, atol=1e-12)
    np.testing.assert_allclose(other.nees, study.nees, rtol=1e-10)
    np.testing.assert_array_equal(other.sample_errors, study.sample_errors)
    np.testing.assert_allclose(other.nees_mean, study.nees.mean(0), rtol=1e-12)
    # chunks of one run, and one kept run: a one-lane program would round differently
    one = monte_carlo(
        traj,
        times,
        P0,
        noise,
        3,
        jax.random.key(5),
        keep_nees=True,
        **dict(STUDY, chunk_size=1, n_keep=1),
    )
    np.testing.assert_allclose(one.nees, study.nees[:3], rtol=1e-10)
    np.testing.assert_array_equal(one.sample_errors, study.sample_errors[:1])
    assert one.settings["chunk_size"] == 1
    # the streamed moments equal the two-pass ones of the per-run errors
    errs = np.stack(
        [
            sample_run(
                traj, times, P0, noise, jax.random.key(5), i, record_every=25, scheme="midpoint"
            ).errors
            for i in (0, 1, 2, 3)
        ]
    )
    np.testing.assert_array_equal(errs, study.sample_errors)


@pytest.mark.default_codegen
def test_run_regenerated_alone_reproduces_the_study_and_its_samples(setup, study):
    """sample_run(i) gives run i's errors bit for bit, and its samples, propagated by the
    generic engine (jaximu.propagate) against the noise-free propagation, give them too."""
    traj, times, P0, noise = setup
    run = sample_run(
        traj, times, P0, noise, jax.random.key(5), 2, record_every=25, scheme="midpoint"
    )
    np.testing.assert_array_equal(run.errors, study.sample_errors[2])
    dt = np.diff(times)
    est = jaximu.propagate(run.start, run.gyro, run.accel, dt, "midpoint")
    t = jnp.asarray(times)
    gyro, accel = sim.ideal_imu(traj, t)
    x0 = sim.true_states(traj, t)[0]
    clean = jaximu.propagate(x0, gyro, accel, dt, "midpoint")
    rec = np.array([24, 49, 74, 99])
    truth = NavState(clean.q[rec], clean.p[rec], clean.v[rec], run.b_g[rec + 1], run.b_a[rec + 1])
    e = np.asarray(boxminus(truth, jax.tree_util.tree_map(lambda x: x[rec], est)))
    scale = np.sqrt(np.diagonal(study.predicted_cov, 0, 1, 2))
    np.testing.assert_allclose(e, run.errors, rtol=0, atol=1e-9 * scale.max())
    # the drawn noise has the documented standard deviations (white: σ/√dt per sample)
    white = run.gyro - np.asarray(gyro) - run.b_g
    assert np.std(white) == pytest.approx(2e-3 / np.sqrt(0.005), rel=0.25)


def test_nees_histogram_and_streaming_sums(study):
    h = study.nees_hist
    assert h.shape == (1, 200) and h.sum() == N_RUNS
    edges = study.nees_hist_edges
    expected = np.histogram(np.clip(study.nees[:, -1], 0, edges[-1] - 1e-9), edges)[0]
    np.testing.assert_array_equal(h[0], expected)
    np.testing.assert_allclose(study.nees_mean, study.nees.mean(0), rtol=1e-12)
    e = study.sample_errors  # the first runs: their NEES is eᵀ P⁻¹ e
    nees = np.einsum("nki,kij,nkj->nk", e, np.linalg.inv(study.predicted_cov), e)
    np.testing.assert_allclose(nees, study.nees[:4], rtol=1e-8)


def test_result_saves_and_loads(study, tmp_path):
    path = tmp_path / "mc.npz"
    study.save(path)
    back = load_result(path)
    for k in (
        "times",
        "mean_error",
        "error_cov",
        "predicted_cov",
        "nees",
        "nees_mean",
        "sample_errors",
        "nees_hist",
    ):
        np.testing.assert_array_equal(getattr(back, k), getattr(study, k))
    assert back.n_runs == N_RUNS and back.settings["scheme"] == "midpoint"
    assert back.nis_mean is None


def test_float32_study_agrees_with_float64(setup, study):
    """The same draws in float32 and float64 (a counter-based generator gives the same
    numbers to rounding): the average NEES agrees to 1e-3 relative, so a float32 study is
    as consistent as a float64 one (docs/DESIGN.md section 6, "Float32 consistency")."""
    traj, times, P0, noise = setup
    f32 = monte_carlo(traj, times, P0, noise, N_RUNS, jax.random.key(5), dtype=jnp.float32, **STUDY)
    np.testing.assert_allclose(f32.nees_mean, study.nees_mean, rtol=1e-3)
    np.testing.assert_allclose(
        f32.error_cov, study.error_cov, rtol=0, atol=1e-3 * np.abs(study.error_cov).max()
    )
    np.testing.assert_allclose(
        f32.sample_errors,
        study.sample_errors,
        rtol=0,
        atol=1e-4 * np.abs(study.sample_errors).max(),
    )


def _lowered_chunk(setup, key, *, scheme, record_every, dtype, route=None, **filt):
    """The HLO text of the lane kernel of a 4-run chunk of the shared set-up (``filt``: the
    filter study's ``update_every`` and ``measurement``; ``route``: a
    :class:`jaximu.engine._dispatch.MonteCarloRoute`, default the CPU's)."""
    from jaximu.kernels.montecarlo_lanes import run_chunk
    from jaximu.studies._montecarlo_setup import _prepare
    from jaximu.studies.montecarlo import _route_options

    traj, times, P0, noise = setup
    st = _prepare(
        traj,
        times,
        P0,
        noise,
        jax.random.key(key),
        scheme=scheme,
        gravity=9.81,
        b_g0=None,
        b_a0=None,
        record_every=record_every,
        dtype=dtype,
        **filt,
    )
    route = _dispatch.MONTE_CARLO[_dispatch.CPU] if route is None else route
    return run_chunk.lower(
        jnp.arange(4, dtype=jnp.uint32),
        jnp.ones(4, dtype),
        st.consts,
        scheme=st.scheme,
        seg=st.seg,
        mode="stats",
        filt=st.filt,
        **_route_options(route, st.filt),
    ).as_text()


def _lane_kernel_loops(route, filt, setup):
    """The number of while loops in the lowered lane kernel of the shared study's set-up
    under ``route``."""
    kw = dict(update_every=25) if filt else {}
    text = _lowered_chunk(
        setup, 5, scheme="midpoint", record_every=25, dtype=jnp.float64, route=route, **kw
    )
    return text.count("stablehlo.while")


def test_accelerator_route_runs_no_loop_inside_a_step(setup):
    """On an accelerator each loop iteration is a launch and a copy of its predicate to the
    host: the accelerator's route has only the segment loop and the step loop (one study's
    100 steps in 4 segments of 25), where the CPU's also loops over the hash's rounds inside
    every step."""
    for filt in (False, True):
        assert _lane_kernel_loops(_dispatch.MONTE_CARLO[_dispatch.ACCELERATOR], filt, setup) == 2
        assert _lane_kernel_loops(_dispatch.MONTE_CARLO[_dispatch.CPU], filt, setup) > 2


def test_accelerator_route_gives_the_cpu_routes_statistics(setup, study):
    """The study through the accelerator's route (its dispatch forced on the CPU: the hash's
    rounds written out, no staged copies, 4 steps a loop iteration, all 57 runs one chunk)
    equals the CPU route's (chunks of 15) to float64 rounding: the same draws, run by run,
    and the statistics of the same runs; its NEES lies in the χ² interval."""
    from _shared import dispatch_as  # here: the two-process test imports this module

    traj, times, P0, noise = setup
    with dispatch_as(_dispatch.ACCELERATOR):
        route = _dispatch.monte_carlo_route()
        acc = monte_carlo(
            traj,
            times,
            P0,
            noise,
            N_RUNS,
            jax.random.key(5),
            keep_nees=True,
            **dict(STUDY, chunk_size=None, n_keep=0),
        )
    assert route.chunk_runs >= N_RUNS and acc.settings["chunk_size"] == N_RUNS
    assert not route.rng_loop and route.unroll > 1
    # every run's NEES (another draw: a χ²₁₅ spread, ~40%), the moments of the same runs
    np.testing.assert_allclose(acc.nees, study.nees, rtol=1e-8)
    np.testing.assert_allclose(acc.nees_mean, study.nees_mean, rtol=1e-8)
    # errors of ~1e-3 from states of ~5 m, ~2 m/s: rounding relative to the errors' spread
    scale = np.sqrt(np.diagonal(study.predicted_cov, 0, 1, 2)).max(0)
    np.testing.assert_allclose(acc.mean_error / scale, study.mean_error / scale, atol=1e-9)
    cov_scale = np.abs(study.error_cov).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(acc.error_cov / cov_scale, study.error_cov / cov_scale, atol=1e-6)
    np.testing.assert_array_equal(acc.nees_hist, study.nees_hist)
    assert np.all(acc.consistent), (acc.nees_mean, acc.nees_bounds)


# --------------------------------------------------------------------------- EKF update


def _np_joseph(q, p, v, bg, ba, P, nu, H, R):
    """Plain numpy: S = HPHᵀ + R, K = PHᵀS⁻¹, δ = Kν, x ⊞ δ (scipy rotations; Hamilton
    [w, x, y, z]), P⁺ = (I - KH)P(I - KH)ᵀ + KRKᵀ, NIS = νᵀS⁻¹ν."""
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    d = K @ nu
    rot = Rotation.from_quat([q[1], q[2], q[3], q[0]]) * Rotation.from_rotvec(d[0:3])
    x, y, z, w = rot.as_quat()
    q1 = np.array([w, x, y, z]) * np.sign(np.dot([w, x, y, z], q))
    A = np.eye(15) - K @ H
    return (
        q1,
        p + d[3:6],
        v + d[6:9],
        bg + d[9:12],
        ba + d[12:15],
        A @ P @ A.T + K @ R @ K.T,
        nu @ np.linalg.solve(S, nu),
    )


def test_ekf_update_matches_numpy_transcription():
    rng = np.random.default_rng(1)
    B = 3
    q = Rotation.random(B, random_state=2).as_quat()[:, [3, 0, 1, 2]]
    p, v, bg, ba = (rng.normal(size=(B, 3)) for _ in range(4))
    A = rng.normal(size=(B, 15, 15)) * 0.1
    P = A @ np.swapaxes(A, 1, 2) + 1e-3 * np.eye(15)
    H = np.concatenate([position_jacobian(), rng.normal(size=(2, 15))])  # m = 5
    Rm = rng.normal(size=(5, 5)) * 0.1
    R = Rm @ Rm.T + 0.01 * np.eye(5)
    nu = rng.normal(size=(B, 5)) * 0.1
    st, P1, nis = ekf_update(NavState(q, p, v, bg, ba), P, nu, H, R)
    for b in range(B):
        ref = _np_joseph(q[b], p[b], v[b], bg[b], ba[b], P[b], nu[b], H, R)
        got = (
            np.asarray(st.q[b]) * np.sign(np.dot(st.q[b], ref[0])),
            st.p[b],
            st.v[b],
            st.b_g[b],
            st.b_a[b],
            P1[b],
            nis[b],
        )
        for g, r in zip(got, ref):
            np.testing.assert_allclose(g, r, rtol=1e-12, atol=1e-12 * np.abs(r).max())


def test_kalman_update_and_nees_on_soa_lanes_match_the_numpy_transcription():
    """The filter study's update runs the Joseph form on (3, 3, B) lanes with a position
    fix's H given by blocks (no product with its identity or zero blocks), and its NEES by a
    block Cholesky on lanes: both against the plain-numpy Joseph form and eᵀ P⁻¹ e."""
    from jaximu.kernels.lane_math import SOA
    from jaximu.schemes import _blocks

    rng = np.random.default_rng(3)
    B = 4
    A = rng.normal(size=(B, 15, 15)) * 0.1
    P = A @ np.swapaxes(A, 1, 2) + 1e-3 * np.eye(15)
    Rm = rng.normal(size=(3, 3)) * 0.1
    R = Rm @ Rm.T + 0.01 * np.eye(3)
    nu = rng.normal(size=(B, 3)) * 0.1
    e = rng.normal(size=(B, 15)) * 0.1
    lanes = {
        k: jnp.moveaxis(jnp.asarray(v), 0, -1) for k, v in _blocks.dense_to_blocks(P).items()
    }  # (3, 3, B)
    up = jax.jit(
        lambda Pb, nu: _blocks.kalman_update(
            Pb, (None, "I", None, None, None), SOA.from_arrays(R), nu, SOA
        )
    )(lanes, jnp.asarray(nu.T[:, None, :]))
    y = jax.jit(lambda Pb, e: _blocks.whiten(Pb, e, SOA))(
        lanes, [jnp.asarray(e.T[3 * i : 3 * i + 3, None]) for i in range(5)]
    )
    H = np.asarray(position_jacobian(jnp.float64))
    P1 = np.asarray(
        _blocks.blocks_to_dense({k: jnp.moveaxis(v, -1, 0) for k, v in up.P.items()})
    )  # (B, 15, 15)
    dx = np.concatenate([np.asarray(d)[:, 0] for d in up.dx], 0).T
    for b in range(B):
        S = H @ P[b] @ H.T + R
        K = P[b] @ H.T @ np.linalg.inv(S)
        A = np.eye(15) - K @ H
        ref = A @ P[b] @ A.T + K @ R @ K.T
        np.testing.assert_allclose(P1[b], ref, rtol=1e-12, atol=1e-12 * np.abs(ref).max())
        np.testing.assert_allclose(dx[b], K @ nu[b], rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(up.nis[0, 0, b], nu[b] @ np.linalg.solve(S, nu[b]), rtol=1e-12)
        nees = sum(float(np.sum(np.asarray(yi)[:, 0, b] ** 2)) for yi in y)
        np.testing.assert_allclose(nees, e[b] @ np.linalg.solve(P[b], e[b]), rtol=1e-10)


def test_ekf_update_gradient_wrt_noise_parameters_matches_finite_differences():
    """d/dσ of (trace P⁺ + NIS) through propagate_covariance_final and ekf_update, with
    respect to the IMU noise densities and the measurement σ: central differences agree."""
    t = jnp.linspace(0.0, 0.2, 21)
    traj = sim.helix()
    gyro, accel = sim.ideal_imu(traj, t)
    x0 = sim.true_states(traj, t)[0]
    P0 = jnp.eye(15) * 1e-4
    H = position_jacobian()
    nu = jnp.array([0.01, -0.02, 0.005])

    def f(params):
        sg, sa, sr = params[0], params[1], params[2]
        est, P = jaximu.propagate_covariance_final(
            x0, P0, gyro[:-1], accel[:-1], jnp.diff(t), jaximu.ImuNoise(sg, sa)
        )
        _, P1, nis = ekf_update(est, P, nu, H, sr**2 * jnp.eye(3))
        return jnp.trace(P1) * 1e3 + nis

    x = jnp.array([2e-3, 2e-2, 0.05])
    # compiled whole (op by op, the update's ~170 small operations each compile on their own),
    # once: the differences take f's values from the same program as the gradient
    value_and_grad = jax.jit(jax.value_and_grad(f))
    g = value_and_grad(x)[1]
    for i in range(3):
        h = 1e-6 * x[i]
        e = jnp.zeros(3).at[i].set(h)
        fd = (value_and_grad(x + e)[0] - value_and_grad(x - e)[0]) / (2 * h)
        assert np.isfinite(g[i])
        np.testing.assert_allclose(g[i], fd, rtol=1e-6)


# The filter study the tests below share: position fixes every 20 steps, 400 runs.
FILTER = dict(update_every=20, measurement=PositionFix(0.01), confidence=0.99, n_keep=0)


@pytest.fixture(scope="module")
def filter_study(setup):
    traj, times, P0, noise = setup
    return monte_carlo(traj, times, P0, noise, 400, jax.random.key(11), **FILTER)


def test_filter_study_nees_and_nis_inside_their_bounds_and_a_wrong_model_outside(
    setup, filter_study
):
    """Position fixes every 20 steps, 400 runs: the average NEES (dof 15 N) and NIS (dof 3 N)
    lie in their 99% intervals at every update (5 updates: family-wise false alarm < 10%
    if independent; they are positively correlated); a filter assuming twice the IMU noise
    is detected (its NEES far below)."""
    traj, times, P0, noise = setup
    res = filter_study
    assert res.nees_mean.shape == (5,) and res.nis_mean.shape == (5,)
    assert np.all(res.consistent), (res.nees_mean, res.nees_bounds)
    assert np.all((res.nis_mean > res.nis_bounds[0]) & (res.nis_mean < res.nis_bounds[1])), (
        res.nis_mean,
        res.nis_bounds,
    )
    twice = jaximu.ImuNoise(4e-3, 4e-2, 2e-4, 4e-3)
    wrong = monte_carlo(traj, times, P0, (noise, twice), 400, jax.random.key(11), **FILTER)
    assert np.all(wrong.nees_mean < wrong.nees_bounds[0])


def test_accelerator_route_filter_study_gives_the_cpu_routes_statistics(setup, filter_study):
    """The filter study through the accelerator's route (forced on the CPU; all 400 runs one
    chunk, the CPU's two of 200): the same NEES, NIS and average covariance per update to
    float64 rounding (another draw would differ by their sampling spread, ~1e-2)."""
    from _shared import dispatch_as

    traj, times, P0, noise = setup
    with dispatch_as(_dispatch.ACCELERATOR):
        acc = monte_carlo(traj, times, P0, noise, 400, jax.random.key(11), **FILTER)
    assert acc.settings["chunk_size"] == 400
    np.testing.assert_allclose(acc.nees_mean, filter_study.nees_mean, rtol=1e-8)
    np.testing.assert_allclose(acc.nis_mean, filter_study.nis_mean, rtol=1e-8)
    np.testing.assert_allclose(acc.predicted_cov, filter_study.predicted_cov, rtol=1e-8)
    assert np.all(acc.consistent), (acc.nees_mean, acc.nees_bounds)


def test_filter_study_kernel_calls_no_lapack(setup):
    """The filter study's compiled chunk holds no custom call (LAPACK): a batched LAPACK
    call splits its batch over XLA:CPU's intra-op thread pool and waits for it, and with one
    chunk in flight per core (the pool's threads running the chunks) two chunks deadlocked
    (seen with the dense update: 4096 runs in chunks of 2048 on 2 cores never returned).
    The update and the NEES run unrolled on the lanes instead."""
    hlo = _lowered_chunk(
        setup,
        0,
        scheme="euler",
        record_every=1,
        dtype=jnp.float32,
        update_every=20,
        measurement=PositionFix(0.01),
    )
    assert "while" in hlo  # the lowered study (its scans), not an empty text
    assert "custom_call" not in hlo, [ln for ln in hlo.splitlines() if "custom_call" in ln][:3]


# --------------------------------------------------------------------------- processes


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


_STUDY = """
import jax
jax.config.update("jax_enable_x64", True)
sys.path.insert(0, {tests!r})
from test_montecarlo import N_RUNS, STUDY, study_setup
from jaximu.montecarlo import monte_carlo
traj, times, P0, noise = study_setup()
r = monte_carlo(traj, times, P0, noise, N_RUNS, jax.random.key(5), **STUDY)
print(json.dumps(dict(cov=r.error_cov.tolist(), mean=r.mean_error.tolist(),
                      nees=r.nees_mean.tolist(), hist=r.nees_hist.tolist(),
                      keep=r.sample_errors.tolist())))
"""


def test_two_processes_give_the_statistics_of_one(study):
    """jax.distributed on 127.0.0.1 with the CPU backend (gloo collectives): two processes,
    each drawing its share of the chunks (two each, one of them the padded last chunk),
    return the single-process statistics (the shared study: the same settings, but
    keep_nees, which needs one process)."""
    port = _free_port()
    dist = textwrap.dedent("""
        import json, sys
        import jax
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(coordinator_address="127.0.0.1:{port}", num_processes=2,
                                   process_id=int(sys.argv[1]))
    """).format(port=port) + _STUDY.format(tests=os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ)  # the parent's XLA flags: the same compiled arithmetic
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", dist, str(i)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for i in range(2)
    ]
    ref = dict(
        cov=study.error_cov,
        mean=study.mean_error,
        nees=study.nees_mean,
        hist=study.nees_hist,
        keep=study.sample_errors,
    )
    outs = [p.communicate(timeout=300) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err
        got = json.loads(out.strip().splitlines()[-1])
        for k in ("cov", "mean", "nees"):
            r = np.asarray(ref[k])
            np.testing.assert_allclose(got[k], r, rtol=1e-6, atol=1e-6 * np.abs(r).max())
        np.testing.assert_array_equal(got["hist"], ref["hist"])
        np.testing.assert_array_equal(got["keep"], ref["keep"])
