"""Tolerances relative to the data, and singular covariances named where they are inverted.

Every value check that allows rounding allows it relative to its input and to the dtype's
epsilon (``jaximu.geometry._checks``): the same relative defect is refused at every scale, and a
legitimate matrix is accepted at every scale. The references are independent of the code
under test: numpy's eigenvalues of hand-built matrices and of their correlation matrices,
numpy's Cholesky solve, and the defect each matrix was built with.

Where a covariance is factored or inverted (the EKF's innovation covariance, the whitened
preintegration residual, the Monte Carlo NEES, the calibration's weights), a matrix that is
singular to the dtype's precision is refused naming it (or, for the NEES, reported as
undefined) instead of being turned into inf, NaN or rounding divided by zero.

Compile cost: the helpers run on numpy; the entry points refuse before any kernel compiles,
except the few valid calls (tiny shapes) and two short Monte Carlo studies.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

import jaximu
from jaximu import ImuNoise, NavState, montecarlo, simulate
from jaximu.errorstate import position_jacobian
from jaximu.geometry import _tolerances

SCALES = (1e-12, 1.0, 1e12)
DTYPES = (np.float32, np.float64)
EPS60 = {np.float32: 60 * np.finfo(np.float32).eps, np.float64: 60 * np.finfo(np.float64).eps}


def covariance(scale, dtype, rank=14, seed=1):
    """``A Aᵀ`` computed in ``dtype`` (rounding-level asymmetry; singular when rank < 15)."""
    A = (np.random.default_rng(seed).normal(size=(15, rank)) * np.sqrt(scale)).astype(dtype)
    return A @ A.T


def correlation(P):
    d = np.sqrt(np.diag(P))
    return P / d[:, None] / d[None, :]


# --------------------------------------------------------------------------- semi-definite


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("scale", SCALES)
def test_a_covariance_computed_in_the_dtype_is_accepted_at_every_scale(scale, dtype):
    P = covariance(scale, dtype)
    lam = np.linalg.eigvalsh(0.5 * (P + P.T).astype(np.float64))
    assert lam[0] >= -EPS60[dtype] * np.abs(P).max()  # the reference: PSD to rounding
    _tolerances.check_covariance("P0", P, dtype)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("scale", SCALES)
def test_the_same_relative_defect_is_refused_at_every_scale(scale, dtype):
    P = covariance(scale, np.float64, rank=15)
    big = np.abs(P).max()
    neg = P.copy()
    neg[4, 4] = -1e-4 * big
    with pytest.raises(
        ValueError,
        match=r"P0 is not positive semi-definite: the variance "
        r"P0\[4, 4\] = -.* is negative \(1 in all\); variances are σ² ≥ 0",
    ):
        _tolerances.check_covariance("P0", neg.astype(dtype), dtype)
    asym = P.copy()
    asym[0, 1] += 1e-3 * big
    with pytest.raises(ValueError, match=r"P0 is not symmetric: P0\[0, 1\] = .* but P0\[1, 0\]"):
        _tolerances.check_covariance("P0", asym.astype(dtype), dtype)
    # variances ≥ 0 but cross terms beyond them: eigenvalue -0.01 of the 2×2 block [[1, 1.01],
    # [1.01, 1]] (numpy's eigvalsh is the reference)
    bad = np.eye(15) * scale
    bad[2, 3] = bad[3, 2] = 1.01 * scale
    lam = np.linalg.eigvalsh(correlation(bad))[0]
    np.testing.assert_allclose(lam, -0.01, rtol=1e-9)
    with pytest.raises(
        ValueError,
        match=r"P0 is not positive semi-definite: the smallest eigenvalue of its "
        r"correlation matrix",
    ) as e:
        _tolerances.check_covariance("P0", bad.astype(dtype), dtype)
    assert f"{lam:.3g}" in str(e.value)


@pytest.mark.parametrize("dtype", DTYPES)
def test_a_covariance_of_mixed_units_is_judged_per_axis(dtype):
    """Variances of 1e-4 beside gyro-bias variances of 1e-12 (rad/s)²: a
    negative variance is refused however small beside the largest entry (-1e-10 is 1e-6 of
    it, inside float32's rounding of that entry), and a cross term beyond what its own two
    variances allow (correlation 1.5, numpy's eigenvalue of the correlation matrix the
    reference) is refused though it is 1.5e-8 of the largest entry."""
    P = np.diag([1e-4] * 9 + [1e-12] * 6)
    _tolerances.check_covariance("P0", P.astype(dtype), dtype)
    neg = P.copy()
    neg[9, 9] = -1e-10
    assert -1e-10 / np.abs(P).max() > -EPS60[np.float32]  # hidden by a largest-entry scale
    with pytest.raises(ValueError, match=r"the variance P0\[9, 9\] = -1e-10 is negative"):
        _tolerances.check_covariance("P0", neg.astype(dtype), dtype)
    cross = P.copy()
    cross[10, 11] = cross[11, 10] = 1.5e-12
    assert np.linalg.eigvalsh(correlation(cross))[0] < -0.4
    assert np.linalg.eigvalsh(cross)[0] > -EPS60[np.float32] * np.abs(P).max()
    with pytest.raises(ValueError, match=r"P0 is not positive semi-definite: the smallest"):
        _tolerances.check_covariance("P0", cross.astype(dtype), dtype)
    with pytest.raises(ValueError, match=r"P0 is not positive semi-definite: the variance"):
        jaximu.propagate_covariance_final(
            NavState.identity((), dtype),
            neg.astype(dtype),
            np.zeros((1, 3), dtype),
            np.array([[0, 0, 9.81]], dtype),
            0.01,
            ImuNoise.euroc(),
        )


def test_each_matrix_of_a_batch_is_judged_at_its_own_scale():
    """A batch of a 1e12 and a 1e-12 covariance: the small one's negative variance (1e-4 of
    its own scale) is refused and named by its batch index, though it is far below the
    rounding of the large one."""
    ok = np.stack([covariance(1e12, np.float64), covariance(1e-12, np.float64)])
    _tolerances.check_covariance("P0", ok, np.float64)
    bad = ok.copy()
    bad[1, 7, 7] = -1e-4 * np.abs(ok[1]).max()
    with pytest.raises(ValueError, match=r"the variance P0\[1, 7, 7\] = .* is negative"):
        _tolerances.check_covariance("P0", bad, np.float64)


@pytest.mark.parametrize("scale", SCALES)
def test_the_entry_points_refuse_the_defect_at_every_scale(scale):
    """``propagate_covariance_final``'s ``P0`` and ``ekf_update``'s ``P`` and ``R``, before any
    computation."""
    s = NavState.identity((), np.float64)
    P0 = np.eye(15) * scale
    P0[4, 4] = -1e-4 * scale
    with pytest.raises(
        ValueError,
        match=r"P0 is not positive semi-definite: the variance "
        r"P0\[4, 4\]",
    ):
        jaximu.propagate_covariance_final(
            s, P0, np.zeros((1, 3)), [[0, 0, 9.81]], 0.01, ImuNoise.euroc()
        )
    H = np.asarray(position_jacobian())
    R = np.eye(3) * scale
    R[0, 1] = 1e-3 * scale
    with pytest.raises(ValueError, match=r"R is not symmetric"):
        jaximu.ekf_update(s, np.eye(15) * scale, np.zeros(3), H, R)
    with pytest.raises(ValueError, match=r"P is not positive semi-definite"):
        jaximu.ekf_update(s, P0, np.zeros(3), H, np.eye(3) * scale)


def test_io_writers_judge_variances_with_float32_rounding_at_every_scale(tmp_path):
    from jaximu import io

    t = np.arange(2) * 0.01
    z = np.zeros((2, 3))
    states = NavState(np.tile([1.0, 0, 0, 0], (2, 1)), z, z, z, z)
    for scale in SCALES:
        cov = np.broadcast_to(np.eye(15) * scale, (2, 15, 15)).copy()
        cov[:, 5, 5] = -1e-6 * scale  # float32 rounding of the largest variance: written
        io.write_states(tmp_path / "s.csv", t, states, cov=cov)
        cov[1, 5, 5] = -1e-4 * scale
        with pytest.raises(ValueError, match=r"cov\[1, 5, 5\] = .* is a negative variance"):
            io.write_states(tmp_path / "s.csv", t, states, cov=cov)


# --------------------------------------------------------------------------- definite


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("scale", SCALES)
def test_dependent_axes_are_singular_at_every_scale(scale, dtype):
    """One step's position and velocity noise (``dp = h/2 dv``): singular, though numpy may
    factor the rounded matrix."""
    P = np.eye(15) * scale
    P[3, 3] = scale * 0.25e-4
    P[3, 6] = P[6, 3] = scale * 0.5e-2
    P = P.astype(dtype)
    assert np.linalg.eigvalsh(correlation(P.astype(np.float64)))[0] < 1e-6  # the reference
    ok, lam, zero = _tolerances.definiteness(P, dtype)
    assert not ok and zero == -1
    with pytest.raises(
        ValueError,
        match=rf"S is singular to {np.dtype(dtype).name} precision: "
        r"the smallest eigenvalue of its correlation matrix "
        r"is .*, so dpx, dvx are linearly dependent.*fix it",
    ):
        _tolerances.check_definite("S", P, dtype, fix="fix it", axes=_tolerances.ERROR_AXES)


@pytest.mark.parametrize("dtype", DTYPES)
def test_axes_in_mixed_units_are_definite(dtype):
    """Variances from 1e-12 to 1e4 (rad², m², a condition number of 1e16) with moderate
    correlations: positive definite in both dtypes; numpy's correlation matrix says so."""
    rng = np.random.default_rng(0)
    B = rng.normal(size=(15, 15))
    C = B @ B.T + 15 * np.eye(15)
    C = correlation(C)
    d = np.sqrt(np.logspace(-12, 4, 15))
    P = (C * d[:, None] * d[None, :]).astype(dtype)
    lam = np.linalg.eigvalsh(correlation(P.astype(np.float64)))[0]
    assert lam > 0.1
    ok, got, _ = _tolerances.definiteness(P, dtype)
    assert ok
    np.testing.assert_allclose(got, lam, rtol=1e-4)
    _tolerances.check_definite("P", P, dtype, fix="")


@pytest.mark.parametrize("dtype", DTYPES)
def test_definiteness_is_decided_at_60_eps_of_the_correlation(dtype):
    tol = EPS60[dtype]
    for margin, ok in ((10.0, True), (0.1, False)):
        r = 1 - margin * tol  # the 2×2 correlation [[1, r], [r, 1]] has eigenvalue 1 - r
        P = np.eye(15)
        P[0, 1] = P[1, 0] = r
        for scale in SCALES:
            assert bool(_tolerances.definiteness(P * scale, dtype)[0]) is ok


def test_a_zero_variance_is_named_with_its_axis_and_batch_index():
    P = np.stack([np.eye(9), np.eye(9)]) * 1e-3
    P[1, 4, 4] = 0.0
    with pytest.raises(
        ValueError,
        match=r"the residuals' covariance is singular \(batch index "
        r"\[1\], 1 of 2\): its variance \[1, 4, 4\] \(dpy\) is "
        r"0, not positive",
    ):
        _tolerances.check_definite(
            "the residuals' covariance", P, np.float64, fix="", axes=_tolerances.ERROR_AXES
        )


# --------------------------------------------------------------------------- where inverted


@pytest.mark.parametrize("scale", (1e-12, 1e12))
def test_ekf_update_names_a_singular_innovation_covariance_at_every_scale(scale):
    """``R = 0`` and ``P`` with no variance along y: ``S = H P Hᵀ`` is singular at any
    scale."""
    s = NavState.identity((), np.float64)
    H = np.asarray(position_jacobian())
    P = np.eye(15) * scale
    P[4, 4] = 0.0
    with pytest.raises(
        ValueError,
        match=r"the innovation covariance S = H P Hᵀ \+ R is "
        r"singular: its variance \[1, 1\] \(axis 1\) is 0.*"
        r"R must be positive definite",
    ):
        jaximu.ekf_update(s, P, np.zeros(3), H, np.zeros((3, 3)))


def test_ekf_update_of_a_valid_tiny_covariance_is_numpys():
    """At 1e-12 m² the update is valid: the NIS equals numpy's ``νᵀ S⁻¹ ν``."""
    s = NavState.identity((), np.float64)
    H = np.asarray(position_jacobian())
    P = np.diag(np.r_[[1e-14] * 3, [1e-12] * 3, [1e-12] * 3, [1e-16] * 6])
    R = np.eye(3) * 1e-12
    nu = np.array([1e-6, -2e-6, 0.5e-6])
    _, _, nis = jaximu.ekf_update(s, P, nu, H, R)
    S = H @ P @ H.T + R
    np.testing.assert_allclose(float(nis), nu @ np.linalg.solve(S, nu), rtol=1e-10)


def test_whitened_residual_of_one_sample_names_the_dependent_axes():
    """One sample's position and velocity noise are the same accelerometer noise: ``cov15``
    is singular (numpy's correlation matrix says so), though every density is positive; two
    samples make it definite, and the whitening is numpy's ``L⁻¹ r``."""
    s = NavState.identity((), np.float64)
    one = jaximu.preintegrate(np.zeros((1, 3)), [[0, 0, 9.81]], 0.01, noise=ImuNoise.euroc())
    assert np.linalg.eigvalsh(correlation(np.asarray(one.cov15)))[0] < 1e-12
    with pytest.raises(
        ValueError,
        match=r"pim\.cov15 is singular to float64 precision: .*"
        r"so (dp|dv).* are linearly dependent.*at least two "
        r"samples",
    ):
        jaximu.whitened_residual(s, s, one)
    two = jaximu.preintegrate(np.zeros((2, 3)), [[0, 0, 9.81]] * 2, 0.01, noise=ImuNoise.euroc())
    s_j = NavState(s.q, s.p + 1e-3, s.v, s.b_g, s.b_a)
    r = np.asarray(jaximu.residual(s, s_j, two))
    L = np.linalg.cholesky(np.asarray(two.cov15))
    np.testing.assert_allclose(
        np.asarray(jaximu.whitened_residual(s, s_j, two)), np.linalg.solve(L, r), rtol=1e-8
    )


MC = dict(
    trajectory=simulate.circle(),
    times=np.arange(5) * 0.01,
    n_runs=2,
    n_keep=0,
    chunk_size=2,
    key=jax.random.key(0),
)


@pytest.mark.parametrize("dtype", DTYPES)
def test_monte_carlo_from_an_exact_start_reports_an_undefined_nees(dtype):
    """From ``P0 = 0`` the first step's covariance is singular (its position and velocity
    errors are one accelerometer noise): the NEES there is NaN and said undefined, not a
    number from rounding (float32 reported 2·10⁵); later it is defined and finite. The
    reference: numpy's eigenvalues of each predicted covariance's correlation matrix."""
    res = montecarlo.monte_carlo(
        P0=np.zeros((15, 15)),
        noise=ImuNoise.euroc(),
        dtype=dtype,
        keep_nees=True,
        nees_hist_times=(0, -1),
        **MC,
    )
    lam = np.array([np.linalg.eigvalsh(correlation(P))[0] for P in res.predicted_cov])
    want = lam > EPS60[dtype]
    assert not want[0] and want[1:].all()
    np.testing.assert_array_equal(res.nees_defined, want)
    assert np.isnan(res.nees_mean[0]) and np.isnan(res.nees[:, 0]).all()
    assert np.isfinite(res.nees_mean[1:]).all() and np.isfinite(res.nees[:, 1:]).all()
    assert np.isnan(res.nees_hist[0]).all() and res.nees_hist[1].sum() == 2
    assert not res.consistent[0]


def test_monte_carlo_whose_nees_is_undefined_at_every_time_is_refused():
    """``P0 = 0`` and no bias random walk: the biases have no variance at any time, so the
    study is refused before the work; one run's errors (``sample_run``) need no NEES and are
    regenerated, their bias part exactly zero."""
    noise = ImuNoise(1.7e-4, 2e-3)
    with pytest.raises(
        ValueError,
        match=r"the predicted covariance at times\[4\] = 0\.04 "
        r"\(and at every recorded time\) is singular: its "
        r"variance \[9, 9\] \(db_gx\) is 0.*give P0 positive "
        r"variances",
    ):
        montecarlo.monte_carlo(P0=np.zeros((15, 15)), noise=noise, **MC)
    run = montecarlo.sample_run(
        MC["trajectory"], MC["times"], np.zeros((15, 15)), noise, MC["key"], 0
    )
    assert run.errors.shape == (4, 15) and np.all(run.errors[:, 9:] == 0)
