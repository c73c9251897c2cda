"""The learning losses and the whole-sequence evaluation, against independent references:
central finite differences for the gradients (float64), scipy's ``Rotation`` for the
open-loop integration and its errors, and jaximu's preintegration covariance (a separate
code path) for the per-sample noise propagation."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaximu
from jaximu.learning import Denoiser, ModelConfig, Sequence, evaluate_sequence, losses

DT = 0.005
TINY = ModelConfig(channels=(4, 4), kernel=3, dilations=(1, 2), dropout=0.0)


def smooth_rates(rng, T, amplitude=1.0):
    """``(T, 3)`` band-limited angular rates [rad/s] (sums of a few sines)."""
    t = np.arange(T) * DT
    f = rng.uniform(0.1, 1.5, (3, 3))
    ph = rng.uniform(0, 2 * np.pi, (3, 3))
    return (
        amplitude
        * np.stack(
            [np.sin(2 * np.pi * f[i, :, None] * t + ph[i, :, None]).sum(0) for i in range(3)], -1
        )
        / 2
    )


def scipy_attitudes(q0_wxyz, gyro, dt):
    """``R_{k+1} = R_k Exp(ω_k dt)`` with scipy, ``(T, 4)`` wxyz, ``q0`` first."""
    R = Rotation.from_quat(np.roll(q0_wxyz, -1))
    out = [R]
    for w in gyro[:-1]:
        R = R * Rotation.from_rotvec(w * dt)
        out.append(R)
    xyzw = np.stack([r.as_quat() for r in out])
    return np.roll(xyzw, 1, axis=-1), out


def make_sequence(rng, T=600, bias=(0.01, -0.02, 0.015)):
    true = smooth_rates(rng, T)
    q0 = np.array([0.9, 0.1, -0.3, 0.2])
    q0 /= np.linalg.norm(q0)
    q, _ = scipy_attitudes(q0, true, DT)
    gyro = true + np.asarray(bias) + 1e-3 * rng.standard_normal((T, 3))
    accel = np.tile([0.0, 0.0, 9.81], (T, 1)) + 0.05 * rng.standard_normal((T, 3))
    t = np.arange(T) * DT
    z = np.zeros((T, 3))
    return Sequence("sim", t, gyro, accel, q, z, z), true


@pytest.fixture(scope="module")
def model64():
    m = Denoiser(TINY, jax.random.key(3)).astype(jnp.float64)
    # non-zero heads, so every parameter reaches the loss
    k1, k2, k3 = jax.random.split(jax.random.key(4), 3)
    m = eqx.tree_at(
        lambda m: m.head.weight, m, 0.3 * jax.random.normal(k1, m.head.weight.shape, jnp.float64)
    )
    m = eqx.tree_at(
        lambda m: m.noise_head.weight,
        m,
        0.3 * jax.random.normal(k2, m.noise_head.weight.shape, jnp.float64),
    )
    m = eqx.tree_at(lambda m: m.gyro_matrix, m, 0.01 * jax.random.normal(k3, (3, 3), jnp.float64))
    return m


def _central_differences(f, model, leaves, eps=1e-6):
    """∂f/∂x by central differences for chosen ``(path_fn, index)`` parameters."""
    out = []
    for where, idx in leaves:
        x = where(model)

        def at(v):
            return f(eqx.tree_at(where, model, x.at[idx].set(v)))

        v = x[idx]
        out.append((at(v + eps) - at(v - eps)) / (2 * eps))
    return np.array(out)


LEAVES = [
    (lambda m: m.layers[0].weight, (1, 2, 3)),
    (lambda m: m.layers[1].bias, (2,)),
    (lambda m: m.head.weight, (0, 1, 0)),
    (lambda m: m.head.bias, (2,)),
    (lambda m: m.gyro_matrix, (0, 1)),
    (lambda m: m.gyro_matrix, (2, 2)),
]
NOISE_LEAVES = [
    (lambda m: m.noise_head.weight, (0, 3, 1)),
    (lambda m: m.noise_head.bias, (0,)),
    (lambda m: m.log_bias_sigma, ()),
    (lambda m: m.log_reference_sigma, ()),
]


def test_increment_loss_gradient_equals_central_differences(model64):
    seq, _ = make_sequence(np.random.default_rng(0), T=257)
    g, a, q = (jnp.asarray(x) for x in (seq.gyro[:256], seq.accel[:256], seq.q))

    def huber(m):
        return losses.increment_loss(m(g, a), q, DT, (16, 32), huber_delta=1e-3)[0]

    def nll(m):
        return losses.increment_loss(
            m(g, a),
            q,
            DT,
            (16, 32),
            bias_sigma=m.bias_sigma,
            reference_sigma=m.reference_sigma,
            random_walk=1e-4,
        )[1]

    for f, leaves in ((huber, LEAVES), (nll, NOISE_LEAVES)):
        f = eqx.filter_jit(f)  # one compilation for the 4 evaluations of each parameter
        grads = eqx.filter_jit(eqx.filter_grad(f))(model64)
        auto = np.array([np.asarray(where(grads))[idx] for where, idx in leaves])
        fd = _central_differences(f, model64, leaves)
        assert np.all(np.abs(auto) > 0), "every chosen parameter reaches the loss"
        np.testing.assert_allclose(auto, fd, rtol=2e-5, atol=1e-9 * np.abs(fd).max())


def test_windows_without_a_reference_at_both_ends_are_left_out_of_the_loss(model64):
    """A dropout over the second half (its attitudes replaced by random ones): the masked
    loss of the 256 samples is the loss of the first 128 alone, both terms."""
    rng = np.random.default_rng(7)
    seq, _ = make_sequence(rng, T=257)
    q = seq.q.copy()
    q[129:] = Rotation.random(128, random_state=8).as_quat()[:, [3, 0, 1, 2]]
    reference = jnp.asarray(np.arange(257) <= 128)
    g, a = jnp.asarray(seq.gyro[:256]), jnp.asarray(seq.accel[:256])
    c = model64(g, a)
    kw = dict(bias_sigma=model64.bias_sigma, reference_sigma=model64.reference_sigma)
    masked = losses.increment_loss(c, jnp.asarray(q), DT, (16, 32), reference=reference, **kw)
    half = type(c)(*(x[:128] for x in c))
    cut = losses.increment_loss(half, jnp.asarray(q[:129]), DT, (16, 32), **kw)
    np.testing.assert_allclose(np.asarray(masked), np.asarray(cut), rtol=1e-12)
    unmasked = losses.increment_loss(c, jnp.asarray(q), DT, (16, 32), **kw)
    assert float(unmasked[0]) > 10 * float(cut[0])  # the random attitudes would count


def test_window_rotation_covariance_equals_preintegration_covariance():
    """Per-sample densities that are constant equal preintegrate's 9×9 rotation block (the
    engine's own recursion, a separate code path), and a per-sample density is the sum of
    its windows' parts: doubling the second half's variance adds exactly that half's share."""
    rng = np.random.default_rng(1)
    H = 32
    gyro = jnp.asarray(smooth_rates(rng, 4 * H, 2.0).reshape(4 * H, 3))
    accel = jnp.zeros_like(gyro)
    sigma = jnp.asarray([2e-3, 1e-3, 3e-3])
    w = losses.windows(gyro, accel, DT, H, jnp.broadcast_to(sigma, gyro.shape))
    pim = jaximu.preintegrate(
        gyro.reshape(4, H, 3), accel.reshape(4, H, 3), DT, noise=jaximu.ImuNoise(sigma, 0.0)
    )
    P = np.asarray(w.Q[..., 0:3, 0:3])
    np.testing.assert_allclose(
        P, np.asarray(pim.cov[..., 0:3, 0:3]), rtol=1e-12, atol=1e-12 * np.abs(P).max()
    )
    np.testing.assert_allclose(np.asarray(w.delta_q), np.asarray(pim.delta_q), atol=1e-14)
    # the bias column of the window's transition is the preintegrated ∂ΔR/∂b_g
    np.testing.assert_allclose(
        np.asarray(w.Phi[..., 0:3, 3:6]), np.asarray(pim.dR_dbg), rtol=1e-12, atol=1e-15
    )
    # composing two windows equals one window of twice the length
    w2 = losses.compose_pairs(w)
    pim2 = jaximu.preintegrate(
        gyro.reshape(2, 2 * H, 3), accel.reshape(2, 2 * H, 3), DT, noise=jaximu.ImuNoise(sigma, 0.0)
    )
    np.testing.assert_allclose(
        np.asarray(w2.Q[..., 0:3, 0:3]), np.asarray(pim2.cov[..., 0:3, 0:3]), rtol=1e-12, atol=1e-20
    )
    np.testing.assert_allclose(np.asarray(w2.delta_v), np.asarray(pim2.delta_v), atol=1e-13)


def test_raw_whole_sequence_evaluation_equals_scipy_integration():
    rng = np.random.default_rng(2)
    seq, _ = make_sequence(rng, T=1500)
    model = Denoiser(TINY, jax.random.key(0))
    rep = evaluate_sequence(model, seq, dtype=jnp.float64)
    _, Rs = scipy_attitudes(seq.q[0], seq.gyro, DT)
    Rt = Rotation.from_quat(np.roll(seq.q, -1, axis=-1))
    est = Rotation.concatenate(Rs)
    aoe = np.degrees((Rt.inv() * est).magnitude())
    aye = np.degrees(np.abs((est * Rt.inv()).as_euler("ZYX")[:, 0]))
    m = rep.metrics["raw"]
    assert aoe.mean() > 1.0  # the bias makes a real error
    np.testing.assert_allclose(
        [m.aoe_mean, m.aoe_rmse, m.aye_mean, m.aye_rmse],
        [aoe.mean(), np.sqrt(np.mean(aoe**2)), aye.mean(), np.sqrt(np.mean(aye**2))],
        rtol=1e-9,
    )
    np.testing.assert_allclose(rep.aoe["raw"], aoe, rtol=1e-9, atol=1e-11)


def test_attitude_terms_equal_preintegration_prefixes():
    """The open-loop covariance terms at every sample equal preintegration's prefixes: ``W``
    its rotation block with the white density and bias walk, ``B`` its ``∂ΔR/∂b_g``."""
    from jaximu.learning.evaluation import attitude_terms

    rng = np.random.default_rng(3)
    T = 200
    gyro = jnp.asarray(smooth_rates(rng, T, 2.0))
    sigma, walk = jnp.asarray([2e-3, 1e-3, 3e-3]), 4e-4
    W, B = attitude_terms(gyro, jnp.broadcast_to(sigma, gyro.shape), DT, walk)
    pim = jaximu.preintegrate(
        gyro[:-1],
        jnp.zeros((T - 1, 3)),
        DT,
        prefixes=True,
        noise=jaximu.ImuNoise(sigma, 0.0, walk, 0.0),
    )
    np.testing.assert_allclose(np.asarray(B[1:]), np.asarray(pim.dR_dbg), rtol=1e-10, atol=1e-15)
    P = np.asarray(pim.cov15[..., 0:3, 0:3])
    np.testing.assert_allclose(np.asarray(W[1:]), P, rtol=1e-10, atol=1e-12 * np.abs(P).max())
    assert np.all(np.asarray(W[0]) == 0)


def test_tracked_bias_term_equals_scipy_differences_of_a_shrinking_bias():
    """The tracked bias's covariance term ``B'B'ᵀ``: ``B'_k`` is the attitude error at ``k``
    per unit of a bias error ``diag(σ_τ) z`` that shrinks with the tracker's ``σ_τ``, here
    central differences of scipy's integration with that error added to the rates."""
    from jaximu.learning.evaluation import attitude_terms

    rng = np.random.default_rng(5)
    T = 160
    gyro = smooth_rates(rng, T, 2.0)
    tracked = np.stack(
        [np.linspace(3e-3, 2e-4, T), np.full(T, 1e-3), np.geomspace(2e-3, 1e-4, T)], -1
    )
    sigma = np.full(3, 1e-3)
    W0, _ = attitude_terms(jnp.asarray(gyro), jnp.broadcast_to(sigma, gyro.shape), DT, 0.0)
    W1, _ = attitude_terms(jnp.asarray(gyro), jnp.broadcast_to(sigma, gyro.shape), DT, 0.0, tracked)
    eps = 1e-3
    cols = []
    for j in range(3):
        e = np.zeros(3)
        e[j] = eps
        _, plus = scipy_attitudes(np.array([1.0, 0, 0, 0]), gyro + tracked * e, DT)
        _, minus = scipy_attitudes(np.array([1.0, 0, 0, 0]), gyro - tracked * e, DT)
        cols.append(np.stack([(m.inv() * p).as_rotvec() for p, m in zip(plus, minus)]) / (2 * eps))
    Bt = np.stack(cols, -1)  # (T, 3, 3)
    expected = np.asarray(W0) + Bt @ np.swapaxes(Bt, -1, -2)
    got = np.asarray(W1)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6 * np.abs(expected).max())


def test_bias_sigma_is_set_for_an_average_nees_of_three():
    from jaximu.learning import uncertainty

    T = 400
    B = np.broadcast_to(np.eye(3) * np.arange(T)[:, None, None] * DT, (T, 3, 3))
    W = np.broadcast_to(1e-14 * np.eye(3), (T, 3, 3)) * np.arange(T)[:, None, None]
    # errors of a constant bias of 1e-3 rad/s per axis: r = B b
    terms = [
        uncertainty.NeesTerms(
            jnp.asarray(B @ (s * 1e-3 * np.ones(3))),
            jnp.asarray(W),
            jnp.asarray(B),
            jnp.asarray(1e-6),
        )
        for s in (0.5, 1.5)
    ]
    sigma = uncertainty.fit_bias_sigma(terms)
    assert np.mean([uncertainty.average_nees(t, sigma) for t in terms]) == pytest.approx(3, 1e-6)
    # bias-dominated errors: the NEES is 3 (s·1e-3)²/σ_b², averaged over s² = 0.25 and 2.25
    assert sigma == pytest.approx(np.sqrt(1.25e-6), rel=0.01)
    (s0, n0), (s1, n1) = uncertainty.leave_one_out(terms)
    assert n0 < 3 < n1 and s0 > s1


def test_reference_sigma_fit_recovers_the_ground_truths_attitude_noise():
    """Simulated ground truth with white attitude noise of known ``σ_ref`` at every sample
    (``R_k Exp(n_k)``, ``n_k ~ N(0, σ_ref² I)``) and a gyro with white noise of the model's
    density: the likelihood fit of the training windows' increments
    (:func:`uncertainty.fit_reference_sigma`, horizons 16 and 32) recovers ``σ_ref`` within
    10 %. Its standard error here is about 2 % (about 3000 residual components of the
    shortest windows), so 10 % is a 5σ bound; the two noises are of one size at 16 samples,
    so the fit must split them as the covariance says."""
    from jaximu.learning import uncertainty

    sigma_ref, density, T = 5e-4, 2e-3, 4000
    rng = np.random.default_rng(21)
    cfg = ModelConfig(
        channels=(4,),
        kernel=3,
        dilations=(1,),
        dropout=0.0,
        bias_tracking=False,
        gyro_density=density,
        reference_sigma=1e-3,
    )
    model = Denoiser(cfg, jax.random.key(0)).astype(jnp.float64)  # untrained: ω̂ = ω_m
    G, Q = [], []
    for _ in range(2):
        true = smooth_rates(rng, T + 1)
        q, _ = scipy_attitudes(np.array([1.0, 0, 0, 0]), true, DT)
        noisy = Rotation.from_quat(np.roll(q, -1, -1)) * Rotation.from_rotvec(
            sigma_ref * rng.standard_normal((T + 1, 3))
        )
        Q.append(np.roll(noisy.as_quat(), 1, -1))
        G.append(true[:T] + density / np.sqrt(DT) * rng.standard_normal((T, 3)))
    G, Q = jnp.asarray(np.stack(G)), jnp.asarray(np.stack(Q))
    fitted, _ = uncertainty.fit_reference_sigma(model, G, jnp.zeros_like(G), Q, DT, (16, 32))
    assert fitted == pytest.approx(sigma_ref, rel=0.1)
