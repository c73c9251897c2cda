"""NavState / ImuBias / ImuNoise pytrees, boxplus/boxminus, and the noise discretisation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaximu
from jaximu.state import BA, BG, POS, THETA, VEL


def random_nav(seed, batch=()):
    rng = np.random.default_rng(seed)
    n = int(np.prod(batch, dtype=int))
    q = Rotation.random(n, random_state=seed).as_quat(scalar_first=True).reshape(batch + (4,))
    return jaximu.NavState(
        jnp.asarray(q), *(jnp.asarray(rng.normal(size=batch + (3,))) for _ in range(4))
    )


@pytest.mark.parametrize("batch", [(), (7,), (2, 3)])
def test_boxplus_is_right_perturbation_and_boxminus_inverts_it(batch):
    """x ⊞ δ = (R Exp(dθ), p + dp, ...) checked with scipy; (x ⊞ δ) ⊟ x = δ for |dθ| < π."""
    x = random_nav(1, batch)
    delta = np.random.default_rng(2).normal(size=batch + (15,))
    delta[..., THETA] *= 0.5
    y = jaximu.boxplus(x, jnp.asarray(delta))
    R_expected = Rotation.from_quat(
        np.asarray(x.q).reshape(-1, 4), scalar_first=True
    ) * Rotation.from_rotvec(delta[..., THETA].reshape(-1, 3))
    R_got = Rotation.from_quat(np.asarray(y.q).reshape(-1, 4), scalar_first=True)
    assert np.max((R_expected.inv() * R_got).magnitude()) < 1e-14
    np.testing.assert_allclose(y.p, np.asarray(x.p) + delta[..., POS], atol=1e-15)
    np.testing.assert_allclose(y.v, np.asarray(x.v) + delta[..., VEL], atol=1e-15)
    np.testing.assert_allclose(y.b_g, np.asarray(x.b_g) + delta[..., BG], atol=1e-15)
    np.testing.assert_allclose(y.b_a, np.asarray(x.b_a) + delta[..., BA], atol=1e-15)
    np.testing.assert_allclose(jaximu.boxminus(y, x), delta, atol=1e-13)


def test_boxminus_rotation_is_in_the_reference_body_frame():
    """Log(R_refᵀ R): a small rotation about the reference's body x axis reads as (ε, 0, 0)."""
    ref = jaximu.NavState(
        jnp.asarray(Rotation.from_euler("ZYX", [1.0, 0.2, 0.3]).as_quat(scalar_first=True)),
        *(jnp.zeros(3),) * 4,
    )
    R = Rotation.from_quat(np.asarray(ref.q), scalar_first=True) * Rotation.from_rotvec(
        [1e-3, 0, 0]
    )
    other = ref.replace(q=jnp.asarray(R.as_quat(scalar_first=True)))
    np.testing.assert_allclose(jaximu.boxminus(other, ref)[THETA], [1e-3, 0, 0], atol=1e-15)


def test_navstate_is_a_pytree_that_jits_vmaps_and_indexes():
    x = random_nav(3, (5,))
    leaves, treedef = jax.tree_util.tree_flatten(x)
    assert len(leaves) == 5 and jax.tree_util.tree_unflatten(treedef, leaves) == x
    doubled = jax.jit(lambda s: jax.tree_util.tree_map(lambda a: 2 * a, s))(x)
    np.testing.assert_allclose(doubled.p, 2 * np.asarray(x.p))
    norms = jax.vmap(lambda s: jnp.linalg.norm(s.q))(x)
    np.testing.assert_allclose(norms, 1.0, atol=1e-15)
    assert x[2].p.shape == (3,) and x.batch_shape == (5,)
    np.testing.assert_allclose(
        x.R, Rotation.from_quat(np.asarray(x.q), scalar_first=True).as_matrix(), atol=1e-15
    )
    assert isinstance(x.bias, jaximu.ImuBias)


def test_identity_constructors():
    s = jaximu.NavState.identity((2, 3), jnp.float32)
    assert s.q.shape == (2, 3, 4) and s.q.dtype == jnp.float32
    np.testing.assert_array_equal(s.q[..., 0], 1.0)
    b = jaximu.ImuBias.zeros((4,), jnp.float64)
    assert b.b_g.shape == (4, 3)


def test_noise_discretisation_follows_the_kalibr_convention():
    """σ/√dt for the white noises, σ_rw·√dt for the bias steps; Q_c = diag(σ²)/dt."""
    n = jaximu.ImuNoise(1.6968e-04, 2.0e-3, 1.9393e-05, 3.0e-3)
    dt = 0.005
    sg, sa, sbg, sba = n.sample_std(dt)
    np.testing.assert_allclose(sg, 1.6968e-04 / np.sqrt(dt))
    np.testing.assert_allclose(sa, 2.0e-3 / np.sqrt(dt))
    np.testing.assert_allclose(sbg, 1.9393e-05 * np.sqrt(dt))
    np.testing.assert_allclose(sba, 3.0e-3 * np.sqrt(dt))
    Qc = n.discrete_covariance(dt)
    expected = np.repeat(np.array([1.6968e-04, 2.0e-3, 1.9393e-05, 3.0e-3]) ** 2 / dt, 3)
    np.testing.assert_allclose(Qc, np.diag(expected))
    assert n == jaximu.ImuNoise.euroc()


def test_noise_per_axis_and_batched():
    n = jaximu.ImuNoise(jnp.array([1.0, 2.0, 3.0]), 0.5, jnp.ones((4, 3)), 0.0)
    var = n.discrete_variances(jnp.full((4,), 0.25))
    assert var.shape == (4, 12)
    np.testing.assert_allclose(var[0, :3], np.array([1.0, 4.0, 9.0]) / 0.25)
    np.testing.assert_allclose(var[:, 6:9], 1.0 / 0.25)


def test_white_noise_statistics_match_the_density():
    """Simulated per-sample noise with σ/√dt: the variance of its sum over 1 s equals σ²·1 s
    (the density's meaning), within the 99.9% chi-square interval of the sample variance."""
    from scipy import stats

    sigma, dt, n_runs = 2e-3, 0.005, 4000
    std = np.asarray(jaximu.ImuNoise(1.0, sigma).sample_std(dt)[1])[0]
    rng = np.random.default_rng(0)
    integrated = (rng.normal(size=(n_runs, 200)) * std).sum(axis=1) * dt  # ∫ n dt over 1 s
    s2 = integrated.var(ddof=1)
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], n_runs - 1) / (n_runs - 1)
    assert lo * sigma**2 * 1.0 < s2 < hi * sigma**2 * 1.0
