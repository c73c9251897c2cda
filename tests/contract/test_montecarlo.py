"""The input contract of ``jaximu.montecarlo``: ``monte_carlo`` and ``sample_run`` name every
argument outside its domain before the work (the filter options included: ``update_every``
beyond the steps, a measurement without it), ``chi2_interval`` against scipy, and
``MonteCarloResult.save`` / ``load_result`` refuse what they would rename or misread.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu import ImuNoise, montecarlo, simulate
from jaximu.errors import Fix, InputError
from jaximu.montecarlo import MonteCarloResult, PositionFix

TRAJ = simulate.circle()
TIMES = np.arange(11) * 0.01
P0_MC = np.eye(15) * 1e-6


def mc(**kw):
    args = dict(
        trajectory=TRAJ,
        times=TIMES,
        P0=P0_MC,
        noise=ImuNoise.euroc(),
        n_runs=4,
        key=jax.random.PRNGKey(0),
    )
    args.update(kw)
    return montecarlo.monte_carlo(**args)


T = 4
NOISE = ImuNoise(1e-3, 1e-2, 1e-5, 1e-4)
P0 = np.eye(15) * 1e-6
KEY = jax.random.key(0)


def _mc(**kw):
    return montecarlo.monte_carlo(
        TRAJ, kw.pop("times", TIMES_T), P0, NOISE, 4, kw.pop("key", KEY), chunk_size=4, **kw
    )


TIMES_T = np.arange(T + 1) * 0.01
MC = dict(n_runs=2, n_keep=0, chunk_size=2)


def mc_study(**kw):
    import jax

    from jaximu import montecarlo, simulate

    args = dict(
        trajectory=simulate.circle(),
        times=np.arange(5) * 0.01,
        P0=1e-6 * np.eye(15),
        noise=jaximu.ImuNoise.euroc(),
        key=jax.random.key(0),
    )
    return montecarlo.monte_carlo(**(args | MC | kw))


# --------------------------------------------------------------------------- domains and names


@pytest.mark.parametrize(
    "kw,message",
    [
        ({"confidence": 95}, r"confidence must be in \(0, 1\).*got 95.*0\.95"),
        ({"confidence": 0.0}, r"confidence must be in \(0, 1\)"),
        ({"record_every": 0}, r"record_every must be a positive integer, got 0"),
        ({"record_every": 1.5}, r"record_every must be a positive integer, got 1\.5"),
        ({"n_runs": 1}, r"n_runs must be an integer ≥ 2, got 1"),
        ({"n_runs": 10.5}, r"n_runs must be an integer ≥ 2, got 10\.5"),
        ({"chunk_size": 0}, r"chunk_size must be a positive integer, got 0"),
        ({"n_keep": -1}, r"n_keep must be a non-negative integer, got -1"),
        ({"gravity": -9.81}, r"gravity = -9\.81 is a magnitude"),
        ({"scheme": "heun"}, r"unknown scheme 'heun'"),
        ({"dtype": np.int32}, r"dtype must be a floating dtype"),
    ],
)
def test_monte_carlo_parameters_outside_their_domain(kw, message):
    with pytest.raises(ValueError, match=message):
        mc(**kw)


def test_chi2_interval_confidence_domain():
    with pytest.raises(ValueError, match=r"confidence must be in \(0, 1\)"):
        montecarlo.chi2_interval(15, 95)
    with pytest.raises(ValueError, match=r"dof must be positive"):
        montecarlo.chi2_interval(0)
    from scipy.stats import chi2

    lo, hi = montecarlo.chi2_interval(1500, 0.95)
    np.testing.assert_allclose([lo, hi], chi2.interval(0.95, 1500), rtol=1e-4)


def test_monte_carlo_times_nan_is_named_as_times():
    times = TIMES.copy()
    times[3] = np.nan
    with pytest.raises(ValueError, match=r"times contains non-finite values .*\[3\]") as err:
        mc(times=times)
    assert "gyro" not in str(err.value)


def test_monte_carlo_bias_shape_is_named():
    with pytest.raises(ValueError, match=r"b_g0 must have shape \(3,\), got \(2,\)"):
        mc(b_g0=np.zeros(2))
    with pytest.raises(ValueError, match=r"b_a0 contains non-finite"):
        mc(b_a0=np.array([0, np.nan, 0]))
    with pytest.raises(ValueError, match=r"trajectory must be a jaximu\.simulate\.Trajectory"):
        mc(trajectory=lambda t: t)


def test_monte_carlo_names_a_batched_density_before_the_work():
    """A (2, 3) density reached numpy's IndexError after the reference propagation."""
    noise = jaximu.ImuNoise(1.6e-4, np.full((2, 3), 2.8e-3), 2.2e-5, 8.6e-4)
    with pytest.raises(
        ValueError,
        match=r"noise\.accelerometer_noise_density must be a scalar "
        r"or \(3,\) for a Monte Carlo study.*\(2, 3\)",
    ):
        mc_study(noise=noise)


def test_host_side_inputs_under_jit_name_the_argument():
    """monte_carlo under jit: "P0 must be an array of numbers, got DynamicJaxprTracer"."""
    import jax

    with pytest.raises(
        ValueError,
        match=r"P0 must be concrete numbers, got a traced value.*"
        r"outside jax\.jit",
    ):
        jax.jit(lambda P: mc_study(P0=P).nees_mean)(jnp.eye(15) * 1e-6)


@pytest.mark.parametrize(
    "kw, name",
    [
        (
            dict(update_every=2, measurement=PositionFix("0.1")),
            r"measurement\.sigma must be an "
            r"array of numbers",
        ),
        (dict(nees_bins=[0.0, np.nan, 3.0]), r"nees_bins must be .* finite"),
        (dict(nees_bins=[0.0, 1.0, np.inf]), r"nees_bins must be .* finite"),
        (dict(nees_bins="auto"), r"nees_bins must be an array of numbers"),
        (dict(times="0:1"), r"times must be an array of numbers"),
        (dict(key="seed"), r"key must be a threefry jax.random key"),
    ],
)
def test_monte_carlo_names_values_it_did_not_check(kw, name):
    # before: sigma "0.1" parsed, NaN/inf edges gave NaN histograms, numpy's messages
    with pytest.raises(ValueError, match=name):
        _mc(**kw)


@pytest.mark.parametrize("name", ["progress", "shard", "keep_nees"])
def test_monte_carlo_bool_options_are_bools(name):
    with pytest.raises(InputError, match=rf"{name} must be True or False") as e:
        _mc(**{name: "no"})
    assert e.value.fixes == (Fix(name, False),)


# --------------------------------------------------------------------------- the filter study


def test_update_every_beyond_the_steps_is_refused_with_the_largest_that_works():
    # before: NaN statistics (no update ever happened)
    for call in (
        lambda: _mc(update_every=T + 1),
        lambda: montecarlo.sample_run(TRAJ, TIMES_T, P0, NOISE, KEY, 0, update_every=T + 1),
    ):
        with pytest.raises(InputError, match=rf"update_every = {T + 1} is more than the {T} "):
            call()
    with pytest.raises(InputError) as e:
        _mc(update_every=10 * T)
    assert e.value.fixes == (Fix("update_every", T),)


def test_a_measurement_without_update_every_is_refused_not_ignored():
    with pytest.raises(InputError, match=r"measurement is used only by the filter study") as e:
        _mc(measurement=PositionFix(0.1))
    assert [f.option for f in e.value.fixes] == ["update_every", "measurement"]


# --------------------------------------------------------------------------- save and load


def _result():
    K = 2
    return MonteCarloResult(
        times=np.arange(K) * 0.1,
        mean_error=np.zeros((K, 15)),
        error_cov=np.ones((K, 15, 15)),
        predicted_cov=np.ones((K, 15, 15)),
        nees=None,
        nees_mean=np.full(K, 15.0),
        nees_bounds=np.array([10.0, 20.0]),
        sample_errors=np.zeros((1, K, 15)),
        discretization_error=np.zeros((K, 15)),
        n_runs=7,
        confidence=0.9,
        settings=dict(scheme="euler"),
    )


def test_save_refuses_a_path_it_would_rename_and_load_round_trips(tmp_path):
    res = _result()
    with pytest.raises(InputError, match=r"must end in \.npz") as e:
        res.save(tmp_path / "r")  # before: numpy silently wrote r.npz
    assert e.value.fixes == (Fix("path", str(tmp_path / "r") + ".npz"),)
    with pytest.raises(InputError, match=r"must end in \.npz"):
        res.save(tmp_path)  # before: wrote a sibling file <folder>.npz
    with pytest.raises(ValueError, match=r"the folder .* does not exist"):
        res.save(tmp_path / "nope" / "r.npz")
    assert list(tmp_path.iterdir()) == []
    res.save(tmp_path / "r.npz")
    back = montecarlo.load_result(tmp_path / "r.npz")
    assert back.n_runs == 7 and back.confidence == 0.9 and back.settings == res.settings
    np.testing.assert_array_equal(back.error_cov, res.error_cov)


def test_load_result_names_the_file_and_what_is_wrong(tmp_path):
    (tmp_path / "t.txt").write_text("hello")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    np.savez(tmp_path / "bad_meta.npz", __meta__=np.asarray("not json"))
    np.savez(tmp_path / "v2.npz", __meta__=np.asarray(json.dumps({"format": "x/2"})))
    tag = {"format": "jaximu.montecarlo/1", "n_runs": 3, "confidence": 0.9}
    np.savez(tmp_path / "empty.npz", __meta__=np.asarray(json.dumps(tag)))
    cases = {  # before: pickle advice, KeyError, JSONDecodeError, "no format tag", a result
        "t.txt": r"not an \.npz archive",  # of None fields, IsADirectoryError
        "other.npz": r"holds the arrays \['a'\] and no format tag",
        "bad_meta.npz": r"__meta__ is not the JSON settings",
        "v2.npz": r"format tag is 'x/2'",
        "empty.npz": r"damaged Monte Carlo result: times, mean_error",
    }
    for name, msg in cases.items():
        with pytest.raises(ValueError, match=msg):
            montecarlo.load_result(tmp_path / name)
    with pytest.raises(ValueError, match=r"is a folder"):
        montecarlo.load_result(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"missing\.npz'?: no such file"):
        montecarlo.load_result(tmp_path / "missing.npz")
    with pytest.raises(ValueError, match=r"path must be a file name"):
        montecarlo.load_result(None)
