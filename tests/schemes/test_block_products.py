"""The block algebra's transition products and noise against dense 15×15 numpy matrices:
a product of block rows restricted to some block columns, the shortcut for a p row that is
``s`` times the v row, and the covariance update with a per-element factor of the noise's
variances."""

import jax.numpy as jnp
import numpy as np
import pytest

from jaximu.schemes import _blocks as blk

RNG = np.random.default_rng(11)


def random_blocks(s):
    """A transition's blocks with ``Cp = s Cv``, ``Dp = s Dv``, ``Ep = s Ev`` (Euler's
    structure, ``s = dt/2``)."""
    X = {k: RNG.standard_normal((3, 3)) for k in ("A", "B", "Cv", "Dv", "Ev")}
    return blk.Blocks(
        A=X["A"],
        B=X["B"],
        Cp=s * X["Cv"],
        Cv=X["Cv"],
        Dp=s * X["Dv"],
        Dv=X["Dv"],
        Ep=s * X["Ev"],
        Ev=X["Ev"],
        dt=np.float64(2 * s),
    )


def dense(rows):
    """The 15×15 matrix that is the identity but for block ``rows`` (``{i: {j: entry}}``)."""
    M = np.eye(15)
    for i, row in rows.items():
        M[3 * i : 3 * i + 3] = 0
        for j, X in row.items():
            if X is None:
                continue
            if isinstance(X, str):
                X = np.eye(3)
            elif isinstance(X, blk.ScaledIdentity):
                X = float(X.s) * np.eye(3)
            M[3 * i : 3 * i + 3, 3 * j : 3 * j + 3] = np.asarray(X)
    return M


@pytest.mark.parametrize("columns", [range(5), (3, 4), (0, 3)])
@pytest.mark.parametrize("shortcut", [False, True])
def test_rows_product_equals_dense_product_on_its_columns(columns, shortcut):
    s = 0.0035
    F = blk.transition_rows(random_blocks(s), blk.ARRAYS, s)
    G_full = blk.transition_rows(random_blocks(0.002))
    # G given by the block columns kept (its other columns never enter those of F G)
    G = {i: {j: X for j, X in row.items() if j in columns} for i, row in G_full.items()}
    product = blk.rows_product(F, G, blk.ARRAYS, columns, s if shortcut else None)
    want = dense(F) @ dense(G_full)
    got = dense(product)
    cols = np.concatenate([np.arange(3 * j, 3 * j + 3) for j in columns])
    scale = np.abs(want).max()
    np.testing.assert_allclose(got[:9, cols], want[:9, cols], rtol=0, atol=1e-14 * scale)


def test_phi_compose_equals_dense_product_and_rows_to_blocks_inverts_transition_rows():
    F, P = random_blocks(0.003), random_blocks(0.0015)
    got = blk.phi_compose(F, P)
    want = dense(blk.transition_rows(F)) @ dense(blk.transition_rows(P))
    np.testing.assert_allclose(
        np.asarray(blk.phi_to_dense(got)), want, rtol=0, atol=1e-14 * np.abs(want).max()
    )
    back = blk.rows_to_blocks(blk.transition_rows(F))
    for name, x in F._asdict().items():
        np.testing.assert_array_equal(np.asarray(getattr(back, name)), np.asarray(x))
    with pytest.raises(ValueError, match=r"outside a transition"):
        blk.rows_to_blocks({0: {0: F.A, 1: F.B}, 1: blk.transition_rows(F)[1], 2: {}})


def test_structured_update_with_a_noise_factor_equals_dense_update():
    s = 0.0025
    b = random_blocks(s)
    A = RNG.standard_normal((15, 15))
    P = A @ A.T
    sigma2 = RNG.uniform(0.5, 2.0, 12)
    factor = 1.0 / (2 * s)  # σ²/dt with dt = 2s
    Pb = blk.dense_to_blocks(jnp.asarray(P))
    qc = tuple(jnp.asarray(sigma2[3 * k : 3 * k + 3]) for k in range(4))
    new = blk.structured_update(Pb, b, qc, blk.ARRAYS, s, qc_scale=jnp.asarray(factor))
    got = np.asarray(blk.blocks_to_dense(new))
    Phi = dense(blk.transition_rows(b))
    # G: the white noises enter θ, p, v as the biases do (Φ's bias columns), the random
    # walks the biases as dt I
    G = np.zeros((15, 12))
    G[:9, 0:6] = Phi[:9, 9:15]
    G[9:12, 6:9] = 2 * s * np.eye(3)
    G[12:15, 9:12] = 2 * s * np.eye(3)
    want = Phi @ P @ Phi.T + G @ np.diag(sigma2 * factor) @ G.T
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-13 * np.abs(want).max())
