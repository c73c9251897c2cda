"""The windowed orientation NEES (:func:`jaximu.learning.uncertainty.window_nees`) of a
simulated, exactly consistent model: the gyro's white noise drawn with the density the
model states, its bias drawn from the model's ``σ_b`` and walked with its random walk, the
ground truth's attitude perturbed with its ``σ_ref``; the truth integrated by scipy's
``Rotation``. The average NEES is then a mean of ``χ²₃`` draws, 3 within a confidence the
test computes from the number of windows."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_learning_losses import scipy_attitudes, smooth_rates

from jaximu.learning import Denoiser, ModelConfig, Sequence, uncertainty

DT = 0.05  # 20 Hz: the statistics need windows, not samples (and compile cost is per shape)
DENSITY, BIAS, WALK, REF = 2e-3, 4e-3, 1e-3, 5e-4  # rad/s/√Hz, rad/s, rad/s²/√Hz, rad
CFG = ModelConfig(
    rate_hz=1 / DT,
    channels=(4,),
    kernel=3,
    dilations=(1,),
    dropout=0.0,
    bias_tracking=False,
    gyro_density=DENSITY,
    gyro_random_walk=WALK,
    bias_sigma=BIAS,
    reference_sigma=REF,
)
MODEL = Denoiser(CFG, jax.random.key(0))  # untrained: ω̂ = ω_m, σ_g = DENSITY, C = 0


def consistent_sequence(seconds: float, window: int, seed: int = 0) -> Sequence:
    """``seconds`` of samples at ``1/DT`` Hz whose gyro error over each window of ``window``
    steps is what the model states: a bias drawn ``N(0, BIAS² I)`` at the window's first
    sample, walked by ``WALK √dt`` a step, and white noise ``DENSITY / √dt``; the attitude
    reference is the truth times ``Exp(n)``, ``n ~ N(0, REF² I)`` at every sample. Each
    window's bias is its own draw (the model's covariance starts each window from
    ``σ_b``), so the windows share nothing but the reference's noise at their common ends."""
    rng = np.random.default_rng(seed)
    T = int(round(seconds / DT)) + 1
    true = smooth_rates(rng, T)
    _, R = scipy_attitudes(np.array([0.9, 0.1, -0.3, 0.2]), true, DT)
    truth = Rotation.concatenate(R)
    noisy = truth * Rotation.from_rotvec(REF * rng.standard_normal((T, 3)))
    q = np.roll(noisy.as_quat(), 1, -1)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    k = np.arange(T)
    first = k - k % window  # each sample's window's first sample
    walk = WALK * np.sqrt(DT) * rng.standard_normal((T, 3))
    walk[k % window == 0] = 0.0
    bias = (
        BIAS * rng.standard_normal((T, 3))[first] + np.cumsum(walk, 0) - np.cumsum(walk, 0)[first]
    )
    gyro = true + bias + DENSITY / np.sqrt(DT) * rng.standard_normal((T, 3))
    accel = np.tile([0.0, 0.0, 9.81], (T, 1))
    z = np.zeros((T, 3))
    return Sequence("consistent", k * DT, gyro, accel, q, z, z)


@pytest.mark.parametrize("seconds", [0.25, 1.0])
def test_the_windowed_nees_of_an_exactly_consistent_model_is_three(seconds):
    """Each window's NEES is a ``χ²₃`` draw (mean 3, variance 6). Neighbouring windows share
    the reference's noise at their common sample, a cross-covariance ``C`` of their whitened
    errors with ``|C| ≤ σ_ref² / λ_min(S)``, so their correlation is at most
    ``ρ = (σ_ref² / λ_min(S))²`` and the mean of ``W`` windows has a standard deviation of
    at most ``√(6 (1 + 2ρ) / W)``: the test allows 4 of those (a 4σ bound; W = 800 and 200
    windows here: ±0.35 and ±0.70)."""
    n = int(round(seconds / DT))
    seq = consistent_sequence(200.0, n, seed=int(seconds * 4))
    t = uncertainty.window_nees_terms(MODEL, seq, seconds)
    W = len(t.r)
    assert W == (len(seq) - 1) // n
    got = uncertainty.window_nees(MODEL, seq, seconds)
    assert got == pytest.approx(uncertainty.average_nees(t, BIAS), rel=1e-6)
    S = (
        np.asarray(t.W)
        + BIAS**2 * np.asarray(t.B) @ np.swapaxes(np.asarray(t.B), -1, -2)
        + 2 * REF**2 * np.eye(3)
    )
    rho = (REF**2 / np.linalg.eigvalsh(S).min()) ** 2
    bound = 4.0 * np.sqrt(6.0 * (1.0 + 2.0 * rho) / W)
    assert abs(got - 3.0) < bound, (got, bound)
    # the bias term matters at this size: without it the same errors are far outside
    assert uncertainty.window_nees(MODEL, seq, seconds, bias_sigma=0.0) > 3 + bound


def test_the_gauss_markov_fit_recovers_a_simulated_slowly_varying_bias():
    """A gyro whose error is white noise of the model's density plus a first-order
    Gauss–Markov bias of known ``σ_m = 2e-3 rad/s``, ``τ = 5 s`` (stationary, exactly
    discretised), at 20 Hz over 200 s cut into two recordings: the likelihood fit of the
    windows of 1 s and 5 s (:func:`uncertainty.fit_bias_markov`) recovers ``σ_m`` within 20 % and ``τ`` within a
    factor 2. The bias dominates each window's covariance, so ``σ_m``'s relative standard
    error is about ``1/√(6 W)``: 3 % for the W = 200 windows of 1 s, about twice that for
    the correlation of neighbouring windows (the bias is shared over ``τ``), so 20 % is a
    3σ bound; ``τ`` shows only in how the error grows from 1 s to 5 s (the 40 windows of
    5 s), a weaker constraint, hence the factor 2. The fitted model's windowed NEES is then
    3 within the bound of the consistent test above."""
    dt, sigma_m, tau, density = DT, 2e-3, 5.0, 1e-3  # CFG's rate
    cfg = dataclasses.replace(
        CFG, gyro_density=density, gyro_random_walk=1e-9, bias_sigma=1e-7, reference_sigma=1e-4
    )
    model = Denoiser(cfg, jax.random.key(0))
    rng = np.random.default_rng(5)
    T = int(200 / dt) + 1
    true = smooth_rates(rng, T)  # (its frequencies are per sample of DT: slower here)
    q, _ = scipy_attitudes(np.array([1.0, 0.0, 0.0, 0.0]), true, dt)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    a = np.exp(-dt / tau)
    z = rng.standard_normal((T, 3))
    b = np.empty((T, 3))
    b[0] = sigma_m * z[0]
    for k in range(1, T):
        b[k] = a * b[k - 1] + sigma_m * np.sqrt(1 - a * a) * z[k]
    gyro = true + b + density / np.sqrt(dt) * rng.standard_normal((T, 3))
    zero = np.zeros((T, 3))
    seq = Sequence("markov", np.arange(T) * dt, gyro, np.tile([0, 0, 9.81], (T, 1)), q, zero, zero)
    # as two recordings of 120 s and 80 s, fitted in one program (the shorter padded): each
    # one's windows there are those it has alone
    cut = 2401
    parts = [
        Sequence(
            f"markov{i}", seq.t[k] - seq.t[k][0], *(x[k] for x in (gyro, seq.accel, q, zero, zero))
        )
        for i, k in enumerate((slice(0, cut), slice(cut, T)))
    ]
    both = uncertainty._markov_parts(model, parts, [0, 0], (1.0, 5.0))
    for w in (1.0, 5.0):
        assert [row[0] for row in both[w]] == [0, 1]
        for i, t, F, h in both[w]:
            alone = uncertainty.window_nees_terms(model, parts[i], w)
            assert F.shape == (len(alone.r), round(w / dt), 6, 6) and h.shape == F.shape[:2]
            for a, b in ((t.r, alone.r), (t.W, alone.W), (t.B, alone.B)):
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-9)
    got_sigma, got_tau = uncertainty.fit_bias_markov(model, parts, steps=30)
    assert got_sigma == pytest.approx(sigma_m, rel=0.2)
    assert tau / 2 < got_tau < 2 * tau
    fitted = uncertainty.with_bias_markov(model, got_sigma, got_tau)
    assert fitted.config.bias_markov == (got_sigma, got_tau)
    nees = uncertainty.window_nees(fitted, seq, 1.0)  # the whole recording's 200 windows
    assert abs(nees - 3.0) < 4.0 * np.sqrt(6.0 * 3.0 / 200), nees
