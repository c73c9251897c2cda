"""Training recovers what was put into simulated data, and a saved model is the same model.

The simulation: 3-D rotation rates, a gyro with a known scale/misalignment error ``E``, a
constant bias ``b`` and white noise of density ``σ``: ``ω_m = (I + E) ω + b + n``; the ground
truth is scipy's integration of the true rates. The true rates carry a white part ten times
the noise's, so no filter can tell the sensor's noise from the motion (on smooth rates a
denoiser low-passes the noise away, and the density it should then learn is that of what is
left). The trained correction must invert the gyro model (least-squares fit of ``ω̂``
against ``ω_m``) and the learned noise density must be within 20 % of ``σ``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_learning_losses import DT, scipy_attitudes, smooth_rates

from jaximu import learning
from jaximu.learning import Denoiser, ModelConfig, Sequence, TrainConfig

E = np.array([[0.02, 0.005, -0.004], [0.003, -0.015, 0.006], [-0.005, 0.004, 0.01]])
BIAS = np.array([0.02, -0.015, 0.03])
SIGMA = 2e-3  # rad/s/√Hz: well above the float32 rounding of the ground truth's increments


def simulated(seed, seconds=100.0):
    rng = np.random.default_rng(seed)
    T = int(seconds / DT)
    true = smooth_rates(rng, T, 1.5) + 10 * SIGMA / np.sqrt(DT) * rng.standard_normal((T, 3))
    q, _ = scipy_attitudes(np.array([1.0, 0, 0, 0]), true, DT)
    gyro = true @ (np.eye(3) + E).T + BIAS + SIGMA / np.sqrt(DT) * rng.standard_normal((T, 3))
    accel = np.tile([0.0, 0.0, 9.81], (T, 1)) + 0.05 * rng.standard_normal((T, 3))
    z = np.zeros((T, 3))
    return Sequence(f"sim{seed}", np.arange(T) * DT, gyro, accel, q, z, z), true


@pytest.fixture(scope="module")
def trained():
    # 20 s of training and 10 s of validation per sequence: each step's time is its samples'.
    # With 30 s of training the recovered scale, bias and density ended at 34 %, 28 % and
    # 41 % of the tolerances below; with these 20 s at 35 %, 7 % and 38 % (the validation
    # AOE at 9 % of its bound against 8 %); with 15 s the density reached 68 %.
    seqs = [simulated(s, seconds=30.0)[0] for s in (0, 1)]
    cfg = TrainConfig(
        steps=300,
        learning_rate=0.01,
        min_learning_rate=0.002,
        restart=300,
        train_seconds=20.0,
        horizons=(16, 32, 64, 128),
        gyro_noise=0.0,
        accel_noise=0.0,
        gyro_bias_noise=0.0,
        accel_bias_noise=0.0,
        weight_decay=0.0,
        validate_every=300,
    )
    mcfg = ModelConfig(
        channels=(8, 8),
        kernel=3,
        dilations=(1, 2),
        dropout=0.0,
        gyro_scale=(0.05, 0.05, 0.05),
        gyro_density=1e-3,
        reference_sigma=1e-5,
        bias_tracking=False,  # the simulated accelerometer does not turn with the gyro
    )
    return learning.train(seqs, cfg, mcfg, seed=0, log=None)


def test_training_recovers_scale_bias_and_noise_density(trained):
    model = trained.model
    seq, true = simulated(7, seconds=30.0)  # a recording it never saw
    c = model(jnp.asarray(seq.gyro, jnp.float32), jnp.asarray(seq.accel, jnp.float32))
    w_hat = np.asarray(c.gyro, np.float64)
    # the learned map from ω_m to ω̂, by least squares (affine)
    X = np.concatenate([seq.gyro, np.ones((len(seq), 1))], 1)
    coef, *_ = np.linalg.lstsq(X, w_hat, rcond=None)
    M, c0 = coef[:3].T, coef[3]
    M_true = np.linalg.inv(np.eye(3) + E)
    np.testing.assert_allclose(M, M_true, atol=2e-3)  # E is 1e-2: the scale error is undone
    np.testing.assert_allclose(c0, -M_true @ BIAS, atol=1.5e-3)  # |b| = 4e-2
    density = np.median(np.asarray(c.gyro_density), axis=0)
    np.testing.assert_allclose(density, SIGMA, rtol=0.2)
    # the simulated ground truth is exact: training leaves σ_ref near its start (1e-5), and
    # the fit to the kept network after training (uncertainty.fit_reference_sigma) gives
    # the reference's two ends under a quarter of the shortest windows' noise variance (what
    # it takes is the network's misfit, 14 % when written)
    assert trained.record["uncertainty"]["learned_reference_sigma"] < 1e-4
    assert 2 * float(model.reference_sigma) ** 2 < 0.25 * SIGMA**2 * 16 * DT


def test_training_beats_the_constant_baseline_on_its_validation(trained):
    r = trained.record
    assert r["validation_aoe_mean_deg"] < 0.5 * min(r["validation_constant_bias_deg"])


def test_training_record_times_its_stages_apart_within_the_wall(trained):
    """The stages' times (first step and validation with their compiles, the steps, the
    validations, the uncertainty's fits) are disjoint intervals of the wall time, so they
    add up to at most it; the tracker and data are timed before it."""
    r = trained.record
    s = r["stage_seconds"]
    inside = ("first_step", "first_validation", "steps", "validation", "uncertainty_and_windows")
    assert all(s[k] > 0 for k in inside + ("tracker_and_data",)), s
    assert sum(s[k] for k in inside) <= r["wall_seconds"], (s, r["wall_seconds"])
    assert s["first_step"] + s["first_validation"] == pytest.approx(r["compile_seconds"])


def test_save_and_load_give_the_same_outputs(tmp_path, trained):
    path = learning.save(tmp_path / "model", trained.model, trained.record)
    back = learning.load(path)
    assert back.config == trained.model.config
    x = np.random.default_rng(0).standard_normal((2, 300, 3)).astype(np.float32)
    a = trained.model(jnp.asarray(x), jnp.asarray(x + [0, 0, 9.81]))
    b = back(jnp.asarray(x), jnp.asarray(x + [0, 0, 9.81]))
    for u, v in zip(a, b):
        np.testing.assert_array_equal(np.asarray(u), np.asarray(v))
    assert learning.checkpoint.record(path)["seed"] == 0


def _count_traces(event, duration, fun_name=None, **_):
    if event == "/jax/core/compile/jaxpr_trace_duration":  # one per jit cache miss
        _TRACES[0] += 1
        _TRACED.append(fun_name)


_TRACES = [0]
_TRACED: list = []  # the traced functions' names, in order
jax.monitoring.register_event_duration_secs_listener(_count_traces)


def test_training_is_deterministic_for_a_seed():
    """Two runs with one seed give the same weights, another seed others; the runs after
    the first, with the same data shapes and settings that differ only in what the step
    takes as data (the noise levels) or never reads (the validation's period, the steps
    within one warm restart), compile nothing (the step and the validation are cached by
    jaximu.learning.training, not rebuilt per call), nor does a training on another
    recording of the same length (the settings fitted to the data are the programs'
    arrays: each fold of a leave-one-out training runs the same programs); validating after
    every step leaves the steps' losses and the last validation as they are."""
    seqs = [simulated(3, seconds=12.0)[0]]
    cfg = TrainConfig(steps=3, validate_every=3, train_seconds=10.0, horizons=(16, 32))
    mcfg = ModelConfig(channels=(4,), kernel=3, dilations=(1,))
    a = learning.train(seqs, cfg, mcfg, seed=5, log=None)
    traced = _TRACES[0]
    b = learning.train(seqs, cfg, mcfg, seed=5, log=None)
    other = dataclasses.replace(cfg, steps=2, validate_every=2, gyro_bias_noise=1e-3)
    c = learning.train(seqs, other, mcfg, seed=6, log=None)
    # validated after every step instead of after the last: the steps are the same (the
    # validation takes nothing from the training's state or its random numbers)
    d = learning.train(seqs, dataclasses.replace(cfg, validate_every=1), mcfg, seed=5, log=None)
    # another recording of the same length: another normalisation and bias priors
    # (the model's fitted settings, arrays of its programs), the same programs
    e = learning.train([simulated(4, seconds=12.0)[0]], cfg, mcfg, seed=5, log=None)
    assert e.model.config.input_mean != a.model.config.input_mean
    assert e.model.config.input_std != a.model.config.input_std
    assert _TRACES[0] == traced, f"{_TRACES[0] - traced} programs traced again"
    assert [h["step"] for h in d.record["history"]] == [1, 2, 3]
    assert d.record["history"][-1] == a.record["history"][-1]
    la, lb, lc = (jax.tree_util.tree_leaves(x.model) for x in (a, b, c))
    assert all(np.array_equal(np.asarray(u), np.asarray(v)) for u, v in zip(la, lb))
    assert not all(np.array_equal(np.asarray(u), np.asarray(v)) for u, v in zip(la, lc))


def test_pretrained_model_loads_and_corrects_at_its_rate():
    model = learning.pretrained("euroc")
    assert model.config.rate_hz == pytest.approx(200.0, rel=1e-3)  # EuRoC: 200.003 Hz
    rec = learning.checkpoint.record("euroc")
    assert rec["command"].startswith("jaximu learn train")
    x = np.zeros((100, 3), np.float32)
    out = model(jnp.asarray(x), jnp.asarray(x + [9.81, 0, 0]))
    assert np.all(np.isfinite(np.asarray(out.gyro)))
    assert Denoiser is type(model)


def test_leave_one_out_never_lets_a_recording_choose_its_own_model():
    """Three recordings with different gyro biases, each left out in turn: a fold's model is
    trained on the other two only (their constant bias: the untrained network of a fold
    integrates the left-out recording whole minus the others' mean bias, which scipy
    integrates here apart), and the kept step is the one with the lowest mean over the
    folds, taken from the model trained on all. The folds, on recordings of one length, run
    one compiled step, although their first recordings' clocks differ in the last digits
    (as real recordings' do): the model's rate is the first recording's of all."""
    biases = ([0.01, -0.02, 0.015], [0.03, 0.01, -0.02], [-0.02, 0.02, 0.01])
    seqs = []
    for i, b in enumerate(biases):
        s, _ = simulated(10 + i, seconds=5.0)
        gyro = s.gyro - BIAS + np.asarray(b)
        bg = np.tile(b, (len(s), 1))
        t = s.t * (1 + 1e-7 * i)  # a clock 0.1 ppm off: the same rate to the user
        seqs.append(Sequence(f"rec{i}", t, gyro, s.accel, s.q, s.p, s.v, bg, 0 * bg))
    cfg = TrainConfig(
        steps=2, validate_every=1, train_seconds=3.0, horizons=(16, 32), selection="leave_one_out"
    )
    mcfg = ModelConfig(channels=(4,), kernel=3, dilations=(1,), bias_tracking=False)
    traced = len(_TRACED)
    result = learning.train(seqs, cfg, mcfg, seed=0, log=None)
    # the folds' step (two recordings each) and the final model's (three) at most
    assert _TRACED[traced:].count("_step") <= 2, _TRACED[traced:]
    loo = result.record["leave_one_out"]
    names = [s.name for s in seqs]
    for f, s, b in zip(loo["folds"], seqs, biases):
        assert f["left_out"] == s.name and s.name not in f["trained_on"]
        assert sorted(f["trained_on"] + [s.name]) == names
        others = np.mean([x for x in biases if x is not b], 0)
        _, Rs = scipy_attitudes(s.q[0], s.gyro - others, DT)
        est = Rotation.concatenate(Rs)
        truth = Rotation.from_quat(np.roll(s.q, -1, axis=-1))
        aoe = np.degrees((truth.inv() * est).magnitude()).mean()
        assert aoe > 1.0  # the others' bias is not this recording's: a real error
        np.testing.assert_allclose(f["aoe_mean_deg"][0], aoe, rtol=2e-3)
    mean = np.mean([f["aoe_mean_deg"] for f in loo["folds"]], 0)
    np.testing.assert_allclose(loo["mean_aoe_deg"], mean, rtol=1e-12)
    assert loo["steps"] == [0, 1, 2]
    assert loo["chosen_step"] == result.record["best_step"] == int(np.argmin(mean))
    # the same folds (the same seed), judged by the worst recording: kept only if a step is
    # below the untrained network on every recording left out
    worst = learning.train(
        seqs, dataclasses.replace(cfg, selection="leave_one_out_worst"), mcfg, log=None
    )
    w = worst.record["leave_one_out"]
    assert [f["aoe_mean_deg"] for f in w["folds"]] == [f["aoe_mean_deg"] for f in loo["folds"]]
    ratios = [
        max(f["aoe_mean_deg"][k] / f["aoe_mean_deg"][0] for f in w["folds"]) for k in range(3)
    ]
    best = min(range(3), key=lambda k: (ratios[k], k))
    assert w["criterion"] == "leave_one_out_worst" and w["chosen_step"] == best
    with pytest.raises(ValueError, match="TrainConfig.selection must be 'validation' or"):
        TrainConfig(selection="leave-one-out")
    with pytest.raises(learning.data.DataError, match="needs two recordings or more"):
        learning.train(seqs[:1], cfg, mcfg, log=None)


def test_pieces_reach_the_whole_recording_only_when_asked():
    """Brossard's pieces (the shortest part, starts 0 … offset-1) against pieces of a window
    anywhere in each whole part: every allowed start leaves the piece and the attitude after
    its last step inside its own part, and the last start reaches the part's end; the
    stacked arrays repeat each part's last sample past its end."""
    from jaximu.learning._batches import _stack, pieces

    parts = [simulated(20 + i, seconds=s)[0] for i, s in enumerate((3.0, 5.0, 4.0))]
    n = [len(p) for p in parts]
    L, bounds, length = pieces(parts, 16, 32, None)
    assert (L, length) == ((min(n) - 33) // 16 * 16, min(n))
    assert np.asarray(bounds).tolist() == [32] * 3
    L, bounds, length = pieces(parts, 16, 32, 400)
    assert L == 400 and length == max(n)
    for k, b in zip(n, np.asarray(bounds)):
        assert (b - 1) + L + 1 == k  # the last start's piece and its end attitude: the end
    L, _, _ = pieces(parts, 16, 32, 10_000)  # a window longer than a part: the shortest's
    assert L == (min(n) - 1) // 16 * 16
    biases = [np.zeros((k, 3)) for k in n]
    G, *_ = _stack(parts, biases, max(n))
    for i, p in enumerate(parts):
        np.testing.assert_array_equal(np.asarray(G[i, : n[i]]), p.gyro.astype(np.float32))
        np.testing.assert_array_equal(
            np.asarray(G[i, n[i] :]), np.tile(G[i, n[i] - 1], (max(n) - n[i], 1))
        )


def test_whole_recordings_train_under_leave_one_out_only():
    """With whole_recordings each part is the whole recording (its start bound its length
    less the piece's), and no recording chooses its own model; without leave-one-out
    selection nothing would be left to validate on, and it is refused."""
    seqs = [simulated(30 + i, seconds=s)[0] for i, s in enumerate((5.0, 6.0, 5.5))]
    cfg = TrainConfig(
        steps=1,
        validate_every=1,
        train_seconds=2.0,
        horizons=(16, 32),
        selection="leave_one_out",
        whole_recordings=True,
        calibrate_uncertainty=False,
    )
    mcfg = ModelConfig(channels=(4,), kernel=3, dilations=(1,), bias_tracking=False)
    result = learning.train(seqs, cfg, mcfg, seed=0, log=None)
    L = round(2.0 / DT) // 32 * 32
    assert result.record["samples_per_step"] == 3 * L
    assert result.record["piece_start_bounds"] == [len(s) - L for s in seqs]
    for f, s in zip(result.record["leave_one_out"]["folds"], seqs):
        assert s.name not in f["trained_on"]
    with pytest.raises(ValueError, match="whole_recordings=True. keeps no seconds"):
        learning.train(seqs, dataclasses.replace(cfg, selection="validation"), mcfg, log=None)


def test_the_matrix_after_the_bias_scales_the_unbiased_rate():
    """``matrix_after_bias``: ``ω̂ = (ω_m - b) + C (ω_m - b)`` (the closed form, with a zero
    network), against ``ω̂ = (I + C) ω_m - b`` without it; a model saved before the setting
    loads with it off."""
    import equinox as eqx

    C = np.array([[0.01, 0.002, 0.0], [0.0, -0.02, 0.003], [0.001, 0.0, 0.005]], np.float32)
    rng = np.random.default_rng(0)
    g = rng.normal(0.0, 0.5, (1, 40, 3)).astype(np.float32)
    a = np.tile(np.float32([0.0, 0.0, 9.81]), (1, 40, 1))
    b = np.float32([0.01, 0.02, 0.08])
    for after in (True, False):
        mcfg = ModelConfig(channels=(4,), kernel=3, dilations=(1,), matrix_after_bias=after)
        model = eqx.tree_at(lambda m: m.gyro_matrix, Denoiser(mcfg, jax.random.key(0)), C)
        out = np.asarray(model(jnp.asarray(g), jnp.asarray(a), gyro_bias=jnp.asarray(b)).gyro)
        u = g[0] - b if after else g[0]
        np.testing.assert_allclose(out[0], g[0] - b + u @ C.T, atol=1e-6)
    old = ModelConfig().to_json()
    del old["matrix_after_bias"]
    assert ModelConfig.from_json(old).matrix_after_bias is False


def test_a_shown_bias_shift_leaves_the_untrained_loss_as_it_is():
    """The untrained network is the bias shown alone: a constant added per piece to the gyro
    and to the bias shown (``bias_noise_shown``) leaves the first step's loss as without it
    (to float32 rounding); not shown, the correction is asked to remove it and the loss
    grows."""
    seqs = [simulated(40, seconds=6.0)[0]]
    base = dict(steps=1, validate_every=1, train_seconds=5.0, horizons=(16, 32))
    quiet = dict(gyro_noise=0.0, accel_noise=0.0, accel_bias_noise=0.0, calibrate_uncertainty=False)
    mcfg = ModelConfig(channels=(4,), kernel=3, dilations=(1,), bias_tracking=False)

    def huber(**kw):
        cfg = TrainConfig(**base, **quiet, **kw)
        return learning.train(seqs, cfg, mcfg, seed=0, log=None).record["history"][0]["huber"]

    clean = huber(gyro_bias_noise=0.0)
    assert huber(gyro_bias_noise=0.05) == pytest.approx(clean, rel=1e-3)
    assert huber(gyro_bias_noise=0.05, bias_noise_shown=False) > 2 * clean


def test_the_worst_fold_keeps_a_step_only_if_it_helps_every_recording():
    """Hand-made fold tables (folds × steps, step 0 the untrained network): the mean picks
    the lowest column mean even where one recording gets worse; the worst-fold criterion
    picks the lowest worst ratio to step 0, and step 0 when no step helps every recording."""
    from jaximu.learning._selection import choose_step

    table = [[2.0, 1.5, 1.9], [3.0, 3.3, 2.9], [1.0, 0.9, 0.95]]  # means 2.0, 1.9, 1.917
    assert choose_step(table, "leave_one_out") == 1  # although fold 1 gets 10 % worse
    assert choose_step(table, "leave_one_out_worst") == 2  # worst ratios 1, 1.1, 0.967
    table = [[2.0, 1.5, 2.1], [3.0, 3.3, 3.1], [1.0, 0.9, 0.95]]
    assert choose_step(table, "leave_one_out_worst") == 0  # every step hurts one recording
    with pytest.raises(ValueError, match="criterion must be one of"):
        choose_step(table, "mean")
