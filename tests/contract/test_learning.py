"""The learning package's bad inputs: the denoiser, the gyro-bias tracker, the settings, the
model files and the evaluation. Each bad input is refused before any work with a
``ValueError`` that names the argument as the user wrote it, the offending value (or its
index) and the fix; nothing is left on disk. The property tests (hypothesis) draw finite
inputs, whose outputs must be finite, and inputs with one non-finite value, which must be
refused naming the argument and the index the value was put at (the reference: where the
test put it).

Compile cost: one tiny model (2 layers of 4 channels) on 40 samples, float32, one shape for
every call; the refusals compile nothing.
"""

from __future__ import annotations

import dataclasses
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _shared import fast_settings
from hypothesis import given
from hypothesis import strategies as st

from jaximu import learning
from jaximu.errors import InputError
from jaximu.geometry.noise import ImuNoise
from jaximu.io import DataError
from jaximu.learning import Denoiser, ModelConfig, TrainConfig, track_gyro_bias

T = 40
DT = 0.005
CFG = ModelConfig(channels=(4, 4), kernel=3, dilations=(1, 2), update_samples=20)
MODEL = Denoiser(CFG, jax.random.key(0))
SETTINGS = CFG.tracker()


def samples(seed=0, T=T):
    """Rates of 0.1 rad/s and gravity along a tilted direction, float32."""
    rng = np.random.default_rng(seed)
    g = 0.1 * rng.standard_normal((T, 3))
    a = np.array([0.5, -0.3, 9.79]) + 0.05 * rng.standard_normal((T, 3))
    return g.astype(np.float32), a.astype(np.float32)


def sequence(T=60):
    g, a = samples(1, T)
    t = np.arange(T) * DT
    q = np.tile([1.0, 0.0, 0.0, 0.0], (T, 1))
    z = np.zeros((T, 3))
    return learning.Sequence("short", t, g, a, q, z, z)


def diverged():
    """The model with one NaN weight, as a diverged training leaves it."""
    w = MODEL.layers[1].weight
    return eqx.tree_at(lambda m: m.layers[1].weight, MODEL, w.at[1, 2, 3].set(jnp.nan))


# --------------------------------------------------------------------------- NaN in, refused


@pytest.mark.parametrize("call", ["model", "track", "tracker"])
def test_a_nan_sample_is_refused_naming_its_index(call):
    g, a = samples()
    g[17, 1] = np.nan
    fn = {
        "model": lambda: MODEL(g, a),
        "track": lambda: MODEL.track(g, a),
        "tracker": lambda: track_gyro_bias(g, a, DT, SETTINGS),
    }[call]
    with pytest.raises(ValueError, match=r"^gyro contains non-finite .* index \[17, 1\].*drop"):
        fn()


@pytest.mark.parametrize(
    "change, message",
    [
        (
            dict(gyro_bias=(np.nan, 0.0, 0.0)),
            r"settings\.gyro_bias contains non-finite values .* index \[0\]",
        ),
        (
            dict(noise=ImuNoise(np.nan, 2e-3, 2e-5, 3e-3)),
            r"settings\.noise\.gyroscope_noise_density contains non-finite values .*: it is nan",
        ),
        (
            dict(noise=ImuNoise(-1.7e-4, 2e-3, 2e-5, 3e-3)),
            r"settings\.noise\.gyroscope_noise_density must be non-negative, got -0\.00017.*"
            r"magnitude",
        ),
        (
            dict(gyro_bias=((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))),
            r"settings\.gyro_bias must have shape \(3,\), got \(2, 3\)",
        ),
        (dict(accel_bias=(0.0, 0.0)), r"settings\.accel_bias must have shape \(3,\), got \(2,\)"),
        (dict(update_samples=2.5), r"settings\.update_samples must be a positive integer"),
        (dict(gravity=-9.81), r"settings\.gravity must be positive and finite, got -9\.81"),
    ],
)
def test_tracker_settings_outside_their_domain_are_refused_naming_the_field(change, message):
    g, a = samples()
    with pytest.raises(ValueError, match=message):
        track_gyro_bias(g, a, DT, SETTINGS._replace(**change))


def test_a_dead_accelerometer_is_refused_naming_accel_and_its_recording():
    g, a = samples()
    g2 = np.stack([g, g])
    a2 = np.stack([a, np.zeros_like(a)])
    with pytest.raises(
        ValueError, match=r"^accel of recording \[1\]: its first 10 samples .*0 m/s²"
    ):
        track_gyro_bias(g2, a2, DT, SETTINGS)
    with pytest.raises(ValueError, match=r"^accel: .* dead or disconnected"):
        MODEL(g, np.zeros_like(a))


@pytest.mark.parametrize(
    "dt, message",
    [
        (np.full(T, DT), r"dt must be one sampling interval .* got an array of shape \(40,\)"),
        (-DT, r"dt must be positive and finite, got -0\.005"),
        (np.nan, r"dt must be positive and finite, got nan"),
        ("0.005", r"dt must be a number, got '0\.005'"),
    ],
)
def test_the_tracker_takes_one_sampling_interval(dt, message):
    g, a = samples()
    with pytest.raises(ValueError, match=message):
        track_gyro_bias(g, a, dt, SETTINGS)


@pytest.mark.parametrize(
    "bias, message",
    [
        (np.zeros((T + 1, 3)), r"gyro_bias must have gyro's shape \(40, 3\) .* got \(41, 3\)"),
        (np.zeros((T, 2)), r"gyro_bias must have gyro's shape \(40, 3\) .* got \(40, 2\)"),
        (np.full((T, 3), np.inf), r"gyro_bias contains non-finite values .* index \[0, 0\]"),
        ("0", r"gyro_bias must be an array of numbers"),
    ],
)
def test_a_given_gyro_bias_is_checked_against_the_samples(bias, message):
    g, a = samples()
    with pytest.raises(ValueError, match=message):
        MODEL(g, a, gyro_bias=bias)


def test_a_constant_given_gyro_bias_is_subtracted_as_given():
    g, a = samples()
    b = np.array([1e-3, -2e-3, 3e-3], np.float32)
    per_sample = MODEL(g, a, gyro_bias=np.broadcast_to(b, g.shape)).gyro
    np.testing.assert_array_equal(np.asarray(MODEL(g, a, gyro_bias=b).gyro), per_sample)
    zero = MODEL(g, a, gyro_bias=np.zeros(3)).gyro  # untrained: the raw gyro exactly
    np.testing.assert_allclose(np.asarray(per_sample), np.asarray(zero) - b, atol=1e-7)


# --------------------------------------------------------------------------- a diverged model


def test_a_model_with_a_nan_weight_is_refused_by_every_use(tmp_path):
    bad = diverged()
    g, a = samples()
    named = r"model's weights hold 1 non-finite values .* model\.layers\[1\]\.weight\[1, 2, 3\]"
    with pytest.raises(ValueError, match=named + r".*retrain"):
        bad(g, a)
    with pytest.raises(ValueError, match=named):
        learning.save(tmp_path / "m", bad)
    assert not (tmp_path / "m").exists()  # nothing written
    with pytest.raises(ValueError, match=named):
        learning.evaluate_sequence(bad, sequence())
    with pytest.raises(ValueError, match=named):
        learning.evaluation.window_errors(bad, sequence(), 0.1)
    # a folder whose weights file holds the NaN (written by an older jaximu)
    learning.save(tmp_path / "m", MODEL)
    eqx.tree_serialise_leaves(tmp_path / "m" / "weights.eqx", learning.checkpoint.weights(bad))
    with pytest.raises(DataError, match=r"weights\.eqx: " + named):
        learning.load(tmp_path / "m")


# --------------------------------------------------------------------------- settings


def test_a_minimum_learning_rate_above_the_learning_rate_is_refused():
    with pytest.raises(
        InputError,
        match=r"min_learning_rate = 0\.01 exceeds learning_rate = "
        r"0\.003.*pass at most learning_rate, e\.g\. min_learning_rate=0\.0003",
    ):
        TrainConfig(min_learning_rate=0.01, learning_rate=0.003)
    TrainConfig(min_learning_rate=0.003, learning_rate=0.003)  # a constant rate


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(kernel=0), r"^ModelConfig\.kernel must be a positive odd number, got 0$"),
        (dict(kernel=4), r"^ModelConfig\.kernel .* got 4; pass kernel=5"),
        (dict(accel_head="yes"), r"^ModelConfig\.accel_head must be True or False"),
        (dict(matrix_after_bias=1), r"^ModelConfig\.matrix_after_bias must be True or False"),
        (dict(gyro_bias=((0, 0, 0), (0, 0, 0))), r"ModelConfig\.gyro_bias must have shape"),
        (
            dict(bias_markov_sigma=-1e-3),
            r"^ModelConfig\.bias_markov_sigma must be non-negative .*pass 0 for no Gauss",
        ),
        (
            dict(bias_markov_time=0.0),
            r"^ModelConfig\.bias_markov_time must be positive .*pass the bias's correlation",
        ),
        (dict(bias_markov_time=float("inf")), r"^ModelConfig\.bias_markov_time must be positive"),
    ],
)
def test_model_settings_name_the_field_they_fail_on(kwargs, message):
    with pytest.raises(ValueError, match=message):
        ModelConfig(**kwargs)


@pytest.mark.parametrize("field", ["whole_recordings", "bias_noise_shown"])
def test_train_flags_must_be_booleans(field):
    with pytest.raises(ValueError, match=rf"^TrainConfig\.{field} must be True or False"):
        TrainConfig(**{field: "no"})


def test_an_unknown_selection_names_the_choices():
    with pytest.raises(ValueError, match="'leave_one_out', 'leave_one_out_worst'"):
        TrainConfig(selection="worst")


# --------------------------------------------------------------------------- evaluation


def test_windows_longer_than_the_recording_are_refused_naming_seconds():
    seq = sequence(60)  # 0.295 s
    with pytest.raises(
        InputError,
        match=r"seconds = 1\.0: a window longer than the 0\.295 s "
        r"of sequence 'short'.*pass seconds between 0\.005 and 0\.295",
    ):
        learning.evaluation.window_errors(MODEL, seq, 1.0)
    with pytest.raises(InputError, match=r"seconds = 0\.001: a window shorter than one sample"):
        learning.evaluation.window_errors(MODEL, seq, 0.001)
    with pytest.raises(InputError, match=r"start = 59 leaves no step"):
        learning.evaluation.window_errors(MODEL, seq, 0.1, start=59)
    out = learning.evaluation.window_errors(MODEL, seq, 0.1)
    assert all(np.isfinite(v).all() for v in out.values())


def test_the_windowed_nees_refuses_bad_windows_naming_the_argument_and_the_fix():
    u = learning.uncertainty
    seq = sequence(60)  # 0.295 s
    with pytest.raises(
        InputError,
        match=r"seconds = 1\.0: a window longer than the 0\.295 s "
        r"of sequence 'short'.*pass seconds between 0\.005 and 0\.295",
    ):
        u.window_nees(MODEL, seq, 1.0)
    with pytest.raises(InputError, match=r"seconds = 0\.001: a window shorter than one sample"):
        u.window_nees_terms(MODEL, seq, 0.001)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(
            ValueError,
            match=r"^seconds must be positive and finite, got .*: pass the window.s length",
        ):
            u.window_nees(MODEL, seq, bad)
    with pytest.raises(InputError, match=r"start = 59 leaves no step.*pass a smaller one"):
        u.window_nees(MODEL, seq, 0.1, start=59)
    with pytest.raises(ValueError, match=r"^bias_sigma must be non-negative and finite"):
        u.window_nees(MODEL, seq, 0.1, bias_sigma=-1e-3)
    with pytest.raises(ValueError, match=r"^model's weights hold 1 non-finite"):
        u.window_nees(diverged(), seq, 0.1)
    with pytest.raises(ValueError, match=r"^seq must be a jaximu\.learning\.Sequence"):
        u.window_nees(MODEL, "seq", 0.1)
    # a reference at the first and the last sample only (a dropout between): no window of
    # 0.1 s has one at both its ends
    ref = np.zeros(60, bool)
    ref[[0, 59]] = True
    gap = dataclasses.replace(seq, reference=ref)
    with pytest.raises(DataError, match=r"none of its windows of 0\.1 s.*pass shorter seconds"):
        u.window_nees(MODEL, gap, 0.1)
    assert np.isfinite(u.window_nees(MODEL, seq, 0.1))


def test_the_gauss_markov_fit_and_setting_refuse_bad_inputs_naming_them():
    u = learning.uncertainty
    seq = sequence(60)
    with pytest.raises(ValueError, match=r"^sequences must be a non-empty list"):
        u.fit_bias_markov(MODEL, seq)
    with pytest.raises(ValueError, match=r"^sequences\[0\] must be a jaximu\.learning\.Sequence"):
        u.fit_bias_markov(MODEL, ["seq"])
    with pytest.raises(ValueError, match=r"^starts must give one sample per sequence \(1\), got 2"):
        u.fit_bias_markov(MODEL, [seq], starts=[0, 0])
    with pytest.raises(ValueError, match=r"^seconds\[1\] must be positive.*e\.g\. \(1\.0, 5\.0\)"):
        u.fit_bias_markov(MODEL, [seq], seconds=(0.1, -1.0))
    with pytest.raises(ValueError, match=r"^seconds must name at least one window length"):
        u.fit_bias_markov(MODEL, [seq], seconds=())
    with pytest.raises(DataError, match=r"no sequence holds a window of 1 s.*shorter seconds"):
        u.fit_bias_markov(MODEL, [seq])  # 0.295 s
    with pytest.raises(ValueError, match=r"^ModelConfig\.bias_markov_sigma must be non-negative"):
        u.with_bias_markov(MODEL, -1.0)
    m = u.with_bias_markov(MODEL, 1e-3, 30.0)
    assert m.config.bias_markov == (1e-3, 30.0) and MODEL.config.bias_markov is None
    for bad, message in (
        ((1e-3,), r"^markov must be a pair"),
        ((-1e-3, 1.0), r"^markov\[0\] must be"),
        ((1e-3, 0.0), r"^markov\[1\] must be"),
    ):
        with pytest.raises(ValueError, match=message):
            learning.attitude_covariance(samples()[0], DENSITY, DT, 1e-3, 2e-5, 1e-3, markov=bad)


# --------------------------------------------------------------------------- properties


def finite_samples(data):
    """Rates within ±5 rad/s and a specific force of 5 to 15 m/s² along a random direction
    with ±2 m/s² on each sample (a moving vehicle), drawn by hypothesis."""
    seed = data.draw(st.integers(0, 2**32 - 1), label="seed")
    rng = np.random.default_rng(seed)
    g = rng.uniform(-5, 5, (T, 3))
    u = rng.standard_normal(3)
    f = u / np.linalg.norm(u) * rng.uniform(5, 15)
    a = f + rng.uniform(-2, 2, (T, 3))
    return g.astype(np.float32), a.astype(np.float32)


def assert_finite(out):
    for leaf in jax.tree_util.tree_leaves(out):
        assert np.isfinite(np.asarray(leaf)).all()


@fast_settings(8)
@given(st.data())
def test_finite_samples_give_finite_corrections_and_biases(data):
    g, a = finite_samples(data)
    assert_finite(MODEL(g, a))
    assert_finite(track_gyro_bias(g, a, DT, SETTINGS))


@fast_settings(12)
@given(st.data())
def test_a_non_finite_sample_anywhere_is_refused_naming_it_and_its_index(data):
    g, a = finite_samples(data)
    name = data.draw(st.sampled_from(["gyro", "accel"]), label="argument")
    i = data.draw(st.integers(0, T - 1), label="sample")
    j = data.draw(st.integers(0, 2), label="axis")
    value = data.draw(st.sampled_from([np.nan, np.inf, -np.inf]), label="value")
    (g if name == "gyro" else a)[i, j] = value
    fn = data.draw(st.sampled_from(["model", "tracker"]), label="function")
    where = re.escape(f"[{i}, {j}]")
    with pytest.raises(ValueError, match=rf"^{name} contains non-finite .* index {where}"):
        if fn == "model":
            MODEL(g, a)
        else:
            track_gyro_bias(g, a, DT, SETTINGS)


@fast_settings(25)
@given(
    st.sampled_from(list(learning.tracking._POSITIVE)),
    st.sampled_from([0.0, -1.0, np.nan, np.inf, -np.inf]),
)
def test_a_tracker_setting_outside_its_domain_is_refused_by_name(field, value):
    g, a = samples()
    with pytest.raises(ValueError, match=rf"^settings\.{field} must be positive and finite"):
        track_gyro_bias(g, a, DT, SETTINGS._replace(**{field: value}))


@fast_settings(25)
@given(
    st.floats(1e-6, 1.0),
    st.floats(1e-6, 1.0),
)
def test_the_learning_rates_are_accepted_exactly_when_they_anneal_downwards(lr, low):
    if low <= lr:
        cfg = TrainConfig(learning_rate=lr, min_learning_rate=low)
        assert (cfg.learning_rate, cfg.min_learning_rate) == (lr, low)  # as given
    else:
        with pytest.raises(InputError, match=r"TrainConfig\.min_learning_rate = .* exceeds"):
            TrainConfig(learning_rate=lr, min_learning_rate=low)


# --------------------------------------------------------------------------- the evaluation's parts

Q = np.tile([1.0, 0.0, 0.0, 0.0], (T, 1))
DENSITY = np.full((T, 3), 1.7e-4)
INTERVALS = np.full(T - 1, DT)


@pytest.mark.parametrize(
    "call, message",
    [
        (
            lambda: learning.integrate_attitude(2 * Q[0], samples()[0], INTERVALS),
            r"^q0 is not a unit",
        ),
        (
            lambda: learning.integrate_attitude(Q[0], samples()[0], np.full(T, DT)),
            r"^dt must be a scalar or have shape \(\.\.\., T-1\) = \(\.\.\., 39\).* got \(40,\)",
        ),
        (lambda: learning.integrate_attitude(Q[0], samples()[0], -DT), r"^dt must be positive"),
        (lambda: learning.orientation_errors(Q * np.nan, Q), r"^q_est contains non-finite"),
        (lambda: learning.orientation_errors(Q, 2 * Q), r"^q_true is not a unit quaternion"),
        (
            lambda: learning.orientation_errors(Q[:3], Q[:4]),
            r"batch shapes .* q_est \(3,\), q_true \(4,\)",
        ),
        (
            lambda: learning.attitude_covariance(samples()[0], -DENSITY, DT, 1e-3, 2e-5, 1e-3),
            r"^density must be non-negative .* density\[0, 0\] = -0\.00017.*lost in σ²",
        ),
        (
            lambda: learning.attitude_covariance(samples()[0], DENSITY, DT, np.nan, 2e-5, 1e-3),
            r"^bias_sigma contains non-finite values \(NaN or inf\): it is nan",
        ),
        (
            lambda: learning.attitude_covariance(samples()[0], DENSITY, DT, 1e-3, 2e-5, 0.0),
            r"^reference_sigma must be positive \[rad\], got reference_sigma = 0",
        ),
        (
            lambda: learning.attitude_covariance(samples()[0], DENSITY[1:], DT, 1e-3, 2e-5, 1e-3),
            r"^density must have gyro's shape \(40, 3\), got \(39, 3\)",
        ),
        (
            lambda: learning.attitude_covariance(
                samples()[0], DENSITY, DT, 1e-3, 2e-5, 1e-3, DENSITY[:, :2]
            ),
            r"^tracked_sigma must have gyro's shape \(40, 3\)",
        ),
        (lambda: learning.CausalConv(2, 3, 0, 1, jax.random.key(0)), r"^kernel must be a pos"),
        (lambda: learning.Denoiser(CFG, 0), r"^key must be a jax\.random key"),
        (lambda: learning.split("seq.csv"), r"^seq must be a jaximu\.learning\.Sequence"),
    ],
)
def test_the_evaluations_parts_refuse_bad_input_by_name(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_the_evaluations_parts_take_lists_and_one_sample():
    """Python lists are numbers as the arrays are; one sample is the start attitude (no
    step); the covariance of a still gyro at a constant density grows by σ² per second
    about each axis, plus the reference's 2 σ_ref² (the closed form)."""
    g = np.zeros((T, 3))
    q = np.asarray(learning.integrate_attitude(Q[0].tolist(), g.tolist(), DT))
    np.testing.assert_allclose(q, Q, atol=1e-7)
    one = learning.integrate_attitude(Q[0], g[:1], INTERVALS[:0])
    np.testing.assert_array_equal(np.asarray(one), Q[:1])
    S = np.asarray(learning.attitude_covariance(g.tolist(), DENSITY, DT, 0.0, 0.0, 1e-3))
    k = np.arange(T)
    want = 1.7e-4**2 * k * DT + 2 * 1e-3**2
    np.testing.assert_allclose(S[:, 0, 0], want, rtol=1e-5)


def evaluation_inputs(data):
    """Finite inputs of the evaluation's parts, drawn by hypothesis: unit quaternions,
    rates within ±5 rad/s, densities and standard deviations within their domains."""
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1), label="seed"))
    q = rng.standard_normal((T, 4))
    return {
        "q0": q[0] / np.linalg.norm(q[0]),
        "q_est": q / np.linalg.norm(q, axis=1, keepdims=True),
        "q_true": np.roll(q, 1, 0) / np.linalg.norm(np.roll(q, 1, 0), axis=1, keepdims=True),
        "gyro": rng.uniform(-5, 5, (T, 3)),
        "density": rng.uniform(0, 1e-2, (T, 3)),
        "bias_sigma": rng.uniform(0, 1e-2),
        "random_walk": rng.uniform(0, 1e-3),
        "reference_sigma": rng.uniform(1e-4, 1e-2),
        "tracked_sigma": rng.uniform(0, 1e-2, (T, 3)),
    }


EVALUATION_CALLS = {
    "integrate_attitude": (
        ("q0", "gyro"),
        lambda x: learning.integrate_attitude(x["q0"], x["gyro"], DT),
    ),
    "orientation_errors": (
        ("q_est", "q_true"),
        lambda x: learning.orientation_errors(x["q_est"], x["q_true"]),
    ),
    "attitude_covariance": (
        ("gyro", "density", "bias_sigma", "random_walk", "reference_sigma", "tracked_sigma"),
        lambda x: learning.attitude_covariance(
            x["gyro"],
            x["density"],
            DT,
            x["bias_sigma"],
            x["random_walk"],
            x["reference_sigma"],
            x["tracked_sigma"],
        ),
    ),
}


@fast_settings(6)
@given(st.data())
def test_finite_inputs_give_finite_attitudes_errors_and_covariances(data):
    x = evaluation_inputs(data)
    for _, call in EVALUATION_CALLS.values():
        assert_finite(call(x))


@fast_settings(20)
@given(st.data())
def test_a_non_finite_or_out_of_domain_argument_of_the_evaluation_is_refused_by_name(data):
    x = evaluation_inputs(data)
    fn = data.draw(st.sampled_from(sorted(EVALUATION_CALLS)), label="function")
    names, call = EVALUATION_CALLS[fn]
    name = data.draw(st.sampled_from(names), label="argument")
    spoil = (
        ["nan", "inf"]
        + (["unit"] if name.startswith("q") else [])
        + (["negative"] if name not in ("gyro",) and not name.startswith("q") else [])
    )
    kind = data.draw(st.sampled_from(spoil), label="kind")
    v = np.array(x[name], np.float64)
    if kind == "unit":
        v = 1.5 * v
    elif kind == "negative":
        v = -np.abs(v) - 1e-3
    else:
        v.flat[data.draw(st.integers(0, v.size - 1), label="index")] = {
            "nan": np.nan,
            "inf": np.inf,
        }[kind]
    x[name] = v
    with pytest.raises(ValueError, match=rf"^{name} "):
        call(x)


def test_the_losses_check_the_ground_truth_against_the_samples():
    g, a = samples()
    c = MODEL(g, a)
    q = np.tile([1.0, 0.0, 0.0, 0.0], (T + 1, 1))
    v = np.zeros((T + 1, 3))
    loss = learning.losses.increment_loss
    with pytest.raises(ValueError, match=r"^q_true must have shape \(\.\.\., T \+ 1, 4\) = "):
        loss(c, q[:-1], DT, (8, 16))
    with pytest.raises(ValueError, match=r"^q_true contains non-finite .* index \[3, 0\]"):
        loss(c, np.where(np.arange(T + 1)[:, None] == 3, np.nan, q), DT, (8, 16))
    with pytest.raises(ValueError, match=r"^dt must be positive \[s\], got dt = -0\.005"):
        loss(c, q, -DT, (8, 16))
    with pytest.raises(ValueError, match=r"^dt must be one sampling interval"):
        loss(c, q, np.full(T, DT), (8, 16))
    with pytest.raises(ValueError, match=r"^corrected must be the model's output"):
        loss((g, a), q, DT, (8, 16))
    residuals = learning.losses.velocity_residuals
    with pytest.raises(ValueError, match=r"^H = 50: no window of 50 samples fits in the 40"):
        residuals(c.gyro, c.accel, q, v, DT, 50)
    with pytest.raises(ValueError, match=r"^v_true must have shape \(\.\.\., T \+ 1, 3\)"):
        residuals(c.gyro, c.accel, q, v[:, :2], DT, 8)
    assert np.isfinite(np.asarray(loss(c, q, DT, (8, 16))[0]))


def test_the_uncertainty_fits_refuse_a_diverged_model_and_a_start_past_the_end():
    bad = diverged()
    u = learning.uncertainty
    with pytest.raises(ValueError, match=r"^model's weights hold 1 non-finite"):
        u.with_bias_sigma(bad, 1e-3)
    with pytest.raises(ValueError, match=r"^model's weights hold 1 non-finite"):
        u.nees_terms(bad, sequence())
    with pytest.raises(ValueError, match=r"^start = 59 leaves no step of the 60 samples"):
        u.nees_terms(MODEL, sequence(), 59)
    with pytest.raises(ValueError, match=r"^seq must be a jaximu\.learning\.Sequence"):
        u.nees_terms(MODEL, "seq")
