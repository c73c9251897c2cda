"""The training's judgements of its validation parts, computed for all of them in one
program (jaximu.learning._validation), equal the per-sequence functions that a user calls
(uncertainty.nees_terms, evaluation.window_errors, themselves tested against scipy
integrations): padding the parts to one length and shifting each to its own start changes
nothing at a sample of its own."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_learning_losses import DT
from test_learning_training import simulated

from jaximu.learning import Denoiser, ModelConfig, Sequence, _validation, evaluation, uncertainty
from jaximu.learning._batches import _tracked_biases, _validation_arrays
from jaximu.learning.data import split


def _full_state(seed, seconds, tilt):
    """A simulated recording with velocities and a position that moves (the windows'
    dead reckoning has something to get wrong), its specific force tilted by ``tilt``
    [m/s²] on x (the tracker follows a bias)."""
    s, _ = simulated(seed, seconds)
    rng = np.random.default_rng(seed)
    v = np.cumsum(0.01 * rng.standard_normal((len(s), 3)), 0)
    p = np.cumsum(v * DT, 0)
    accel = s.accel + [tilt, 0.0, 0.0]
    z = np.zeros((len(s), 3))
    return Sequence(s.name, s.t, s.gyro, accel, s.q, p, v, z + 0.01, z)


def _close(got, want):
    want = np.asarray(want, np.float64)
    scale = max(float(np.max(np.abs(want))), np.finfo(np.float32).tiny)
    np.testing.assert_allclose(np.asarray(got, np.float64), want, rtol=0, atol=2e-5 * scale)


def test_validation_batch_gives_each_parts_own_nees_terms_and_windows():
    seqs = [_full_state(20, 8.0, 0.0), _full_state(21, 9.5, 0.2)]  # two lengths
    model = Denoiser(ModelConfig(channels=(4, 4), kernel=3, dilations=(1, 2)), jax.random.key(3))
    vals = [split(s, 6.0)[1] for s in seqs]
    v = _validation_arrays(seqs, vals, _tracked_biases(model, seqs), model.config.receptive_field)
    terms = _validation.nees_terms(model, v)
    windows = _validation.window_errors(model, v, DT, (1.0,))
    for s, val, t, w in zip(seqs, vals, terms, windows):
        start = len(s) - len(val)
        want = uncertainty.nees_terms(model, s, start)
        assert t.r.shape == want.r.shape == (len(val), 3)
        for got, ref in ((t.r, want.r), (t.W, want.W), (t.B, want.B)):
            _close(got, ref)
        got_nees, want_nees = (uncertainty.average_nees(x, 1e-3) for x in (t, want))
        assert abs(got_nees / want_nees - 1) < 1e-4, (got_nees, want_nees)
        for name, pair in evaluation.window_errors(model, s, 1.0, start).items():
            _close(w["1s"][name], pair)


def test_an_accelerometer_network_of_its_own_leaves_the_gyro_as_trained_without_it():
    """With ``ModelConfig(accel_network=True)`` the gyro is trained and kept as by a
    gyro-only training of the same seed (the velocity loss trains none of its weights), and
    the accelerometer's layers are kept from the step with the lowest ratio of the
    dead-reckoning errors over the validation windows, the corrected accelerometer's to the
    constant bias's, which evaluation.window_errors gives again, recording by recording,
    for the kept model. The recordings rotate in place (``v = p = 0``) with an
    accelerometer bias of 0.3 m/s² on x that the ground truth's biases leave out."""
    from jaximu.learning import TrainConfig, train

    seqs = []
    for seed in (30, 31):
        s, _ = simulated(seed, 12.0)
        up = Rotation.from_quat(np.roll(s.q, -1, axis=-1)).inv().apply([0.0, 0.0, 9.81])
        z = np.zeros((len(s), 3))
        accel = up + [0.3, 0.0, 0.0] + 0.02 * np.random.default_rng(seed).standard_normal(z.shape)
        seqs.append(Sequence(s.name, s.t, s.gyro, accel, s.q, z, z, z + 0.02, z))
    cfg = TrainConfig(
        steps=4,
        validate_every=2,
        train_seconds=6.5,
        horizons=(16, 32),
        learning_rate=0.05,
        min_learning_rate=0.005,
        ema=0.0,
        calibrate_uncertainty=False,
    )
    base = dict(channels=(4,), kernel=3, dilations=(1,), bias_tracking=False)
    mcfg = ModelConfig(accel_head=True, accel_network=True, accel_scale=(1.0,) * 3, **base)
    own = train(seqs, cfg, mcfg, seed=0, log=None)
    gyro_only = train(seqs, cfg, ModelConfig(**base), seed=0, log=None)
    rec = own.record
    assert rec["best_step"] == gyro_only.record["best_step"]
    for s in seqs:
        a, b = own.model(s.gyro, s.accel), gyro_only.model(s.gyro, s.accel)
        np.testing.assert_allclose(a.gyro, b.gyro, rtol=0, atol=1e-6)
        np.testing.assert_allclose(a.gyro_density, b.gyro_density, rtol=1e-6)
    ratios = [1.0] + [h["validation_accel_ratio"] for h in rec["history"]]
    steps = [0] + [h["step"] for h in rec["history"]]
    assert rec["accel_step"] == steps[int(np.argmin(ratios))] > 0  # the bias is learned
    rows = []
    for s in seqs:
        start = len(s) - len(split(s, 6.5)[1])
        rows.append({w: evaluation.window_errors(own.model, s, w, start) for w in (1.0, 5.0)})
    ratio = np.mean(
        [r[w]["learned"][i] / r[w]["learned_gyro"][i] for r in rows for w in r for i in (0, 1)]
    )
    assert ratio == pytest.approx(min(ratios), rel=1e-4) and ratio < 0.95
