"""The training's judgements of its validation parts, computed for all of them in one
program (jaximu.learning._validation), equal the per-sequence functions that a user calls
(uncertainty.nees_terms, evaluation.window_errors, themselves tested against scipy
integrations): padding the parts to one length and shifting each to its own start changes
nothing at a sample of its own."""

from __future__ import annotations

import jax
import numpy as np
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
