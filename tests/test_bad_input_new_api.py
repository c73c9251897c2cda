"""The bad-input contract on the newest public API: ``ekf_update`` and ``position_jacobian``,
``body_P_sensor`` / ``tangential``, ``earth_rate`` / ``omega_coriolis`` / ``coriolis_exact``,
``monte_carlo``'s filter options, ``MonteCarloResult.save`` / ``load_result``, the Kalibr
readers and the command's ``--filter``, ``--fix-sigma``, ``--earth-rate``.

One block per defect class found by trying them as a new user would (each was silent or
raised an error that did not name the argument): an option whose truth value decided it
(``tangential="no"`` ran with the tangential term), values that were never checked
(``ekf_update``'s ``R``, ``P``, ``residual``: NaN out), options beyond the data
(``update_every > T``: NaN statistics), options silently ignored (``measurement`` without
``update_every``, ``--fix-sigma`` without ``--filter``), files silently renamed or misread
(``save("r")`` wrote ``r.npz``), and text or ``None`` where numbers belong. Every
expectation is independent of the code under test: the argument's name in the message, the
repair as data, numpy's closed-form Kalman update, the closed form of Earth's rate.

Compile cost: every error is raised before any kernel compiles; the valid calls use tiny
inputs (the ``ekf_update`` ones run op by op, one small preintegration is shared).
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu import ImuNoise, NavState, SensorPose, cli, kalibr, montecarlo, simulate
from jaximu.errors import Fix, InputError
from jaximu.errorstate import position_jacobian
from jaximu.montecarlo import MonteCarloResult, PositionFix

X0 = NavState(jnp.array([1.0, 0, 0, 0]), jnp.zeros(3), jnp.zeros(3), jnp.zeros(3), jnp.zeros(3))
T = 4
GYRO = jnp.zeros((T, 3))
ACCEL = jnp.tile(jnp.array([0.0, 0.0, 9.81]), (T, 1))
DT = 0.01
NOISE = ImuNoise(1e-3, 1e-2, 1e-5, 1e-4)
POSE = SensorPose(jnp.array([1.0, 0, 0, 0]), jnp.array([0.1, 0.0, 0.0]))
OMEGA = [0.0, 5e-5, 5e-5]


# --------------------------------------------------------------------------- ekf_update

P15 = np.diag(np.r_[[1e-4] * 3, [0.04] * 3, [1e-2] * 3, [1e-6] * 3, [1e-4] * 3])
H3 = np.asarray(position_jacobian())
R3 = np.eye(3) * 0.01
NU = np.array([0.1, -0.2, 0.05])


def _ekf(**kw):
    args = dict(state=X0, P=P15, residual=NU, H=H3, R=R3)
    args.update(kw)
    return jaximu.ekf_update(**args)


def _with(a, idx, v):
    a = np.array(a, float)
    a[idx] = v
    return a


@pytest.mark.parametrize("kw, name", [
    (dict(R=-R3), r"\bR\b.*not positive semi-definite"),
    (dict(R=_with(R3, (0, 1), 0.005)), r"\bR\b is not symmetric"),
    (dict(R=0 * R3, P=0 * P15), r"innovation covariance S = H P Hᵀ \+ R is singular"),
    (dict(residual=_with(NU, 1, np.nan)), r"residual contains non-finite"),
    (dict(P=_with(P15, (0, 0), np.inf)), r"\bP contains non-finite"),
    (dict(P=_with(P15, (0, 3), 1e-3)), r"\bP is not symmetric"),
    (dict(P=-P15), r"\bP is not positive semi-definite"),
    (dict(H=_with(H3, (0, 3), np.nan)), r"\bH contains non-finite"),
    (dict(state=X0.replace(q=jnp.array([1.1, 0, 0, 0]))), r"state\.q is not a unit quaternion"),
    (dict(P=np.broadcast_to(P15, (4, 15, 15)), residual=np.zeros((3, 3))),
     r"do not broadcast: .*P \(4,\), residual \(3,\)"),
    (dict(P="eye"), r"\bP must be an array of numbers"),
    (dict(R=None), r"\bR must be an array of numbers"),
    (dict(H=np.zeros((0, 15)), residual=np.zeros(0), R=np.zeros((0, 0))), r"H has no rows"),
])
def test_ekf_update_refuses_values_outside_its_domain_naming_the_argument(kw, name):
    # before: NaN out (R, residual, P, H non-finite or singular S), a silent update with a
    # non-PSD or one-sided P, JAX's unnamed broadcasting error, or a TypeError for text
    with pytest.raises(ValueError, match=name):
        _ekf(**kw)


EKF = jax.jit(jaximu.ekf_update)  # one compile per dtype (op by op eagerly: many small ones)


def test_ekf_update_still_computes_the_textbook_update_in_float32_for_half_inputs():
    """The checks change nothing of a valid update (eager: all value checks run): numpy's
    Kalman update (gain by a plain inverse). Inside the caller's jit, where the value checks
    cannot run, it traces, and float16 inputs are computed in float32 (as everywhere)."""
    x, P, nis = _ekf(P=P15.astype(np.float16).astype(np.float64))
    P16 = P15.astype(np.float16).astype(np.float64)
    S = H3 @ P16 @ H3.T + R3
    K = P16 @ H3.T @ np.linalg.inv(S)
    A = np.eye(15) - K @ H3
    scale = np.abs(P16).max()
    np.testing.assert_allclose(np.asarray(P), A @ P16 @ A.T + K @ R3 @ K.T,
                               atol=1e-6 * scale, rtol=1e-5)
    np.testing.assert_allclose(float(nis), NU @ np.linalg.solve(S, NU), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(x.p), K[3:6] @ NU, rtol=1e-5, atol=1e-9)
    half = dict(state=jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float16), X0),
                **{k: np.asarray(v, np.float16) for k, v in
                   dict(P=P15, residual=NU, H=H3, R=R3).items()})
    x_h, P_h, nis_h = EKF(**half)
    assert P_h.dtype == x_h.p.dtype == nis_h.dtype == jnp.float32


@pytest.mark.parametrize("dtype", ["banana", np.int32, np.float16])
def test_position_jacobian_refuses_a_dtype_that_is_not_float32_or_float64(dtype):
    with pytest.raises(ValueError, match=r"dtype must be a floating dtype"):
        position_jacobian(dtype)


# --------------------------------------------------------------------------- bool options


def _pim():
    return jaximu.preintegrate(GYRO, ACCEL, DT)


BOOL_OPTIONS = [
    ("tangential", lambda v: jaximu.propagate(X0, GYRO, ACCEL, DT, body_P_sensor=POSE,
                                              tangential=v)),
    ("tangential", lambda v: jaximu.propagate_covariance(
        X0, np.eye(15) * 1e-4, GYRO, ACCEL, DT, NOISE, body_P_sensor=POSE, tangential=v)),
    ("tangential", lambda v: jaximu.preintegrate(GYRO, ACCEL, DT, body_P_sensor=POSE,
                                                 tangential=v)),
    ("coriolis_exact", lambda v: jaximu.propagate(X0, GYRO, ACCEL, DT, omega_coriolis=OMEGA,
                                                  coriolis_exact=v)),
    ("coriolis_second_order", lambda v: jaximu.propagate_final(
        X0, GYRO, ACCEL, DT, omega_coriolis=OMEGA, coriolis_exact=False,
        coriolis_second_order=v)),
    ("coriolis_exact", lambda v: jaximu.predict(X0, _pim(), omega_coriolis=OMEGA,
                                                coriolis_exact=v)),
    ("coriolis_second_order", lambda v: jaximu.residual(X0, X0, _pim(), omega_coriolis=OMEGA,
                                                        coriolis_second_order=v)),
]


@pytest.mark.parametrize("word, value", [("no", False), ("False", False), ("yes", True)])
@pytest.mark.parametrize("name, call", BOOL_OPTIONS,
                         ids=[f"{n}-{i}" for i, (n, _) in enumerate(BOOL_OPTIONS)])
def test_a_bool_option_given_as_a_word_is_refused_with_its_repair(name, call, word, value):
    # before: the string's truth value decided ("no" is true: the option silently on)
    with pytest.raises(InputError, match=rf"{name} must be True or False") as e:
        call(word)
    assert e.value.fixes == (Fix(name, value),)


@pytest.mark.parametrize("name, call", BOOL_OPTIONS[:2] + BOOL_OPTIONS[3:5])
def test_a_bool_option_given_as_none_is_refused(name, call):
    with pytest.raises(ValueError, match=rf"{name} must be True or False, got NoneType"):
        call(None)


# --------------------------------------------------------------------------- body_P_sensor


@pytest.mark.parametrize("call", [
    lambda pose: jaximu.propagate(X0, jnp.broadcast_to(GYRO, (2, T, 3)),
                                  jnp.broadcast_to(ACCEL, (2, T, 3)), DT, body_P_sensor=pose),
    lambda pose: jaximu.preintegrate(jnp.broadcast_to(GYRO, (2, T, 3)),
                                     jnp.broadcast_to(ACCEL, (2, T, 3)), DT,
                                     body_P_sensor=pose),
])
def test_a_sensor_pose_whose_batch_does_not_fit_is_named(call):
    # before: JAX's "mul got incompatible shapes" / einsum's label error
    pose = SensorPose(jnp.tile(jnp.array([1.0, 0, 0, 0]), (3, 1)), jnp.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"do not broadcast: body_P_sensor\.q \(3,\)"):
        call(pose)


def test_a_sensor_pose_of_none_or_text_names_the_field():
    with pytest.raises(ValueError, match=r"body_P_sensor\.q must be an array of numbers"):
        jaximu.propagate(X0, GYRO, ACCEL, DT, body_P_sensor=SensorPose(None, [0.1, 0, 0]))
    with pytest.raises(ValueError, match=r"R_BS must be an array of numbers"):
        SensorPose.from_rotation("eye", [0, 0, 0])


def test_from_rotation_refuses_a_non_finite_lever_arm():
    # before: a SensorPose holding NaN
    with pytest.raises(ValueError, match=r"lever arm p_BS contains non-finite"):
        SensorPose.from_rotation(np.eye(3), [np.nan, 0, 0])


# --------------------------------------------------------------------------- rotating world


def test_earth_rate_names_the_bad_latitude_and_refuses_text_and_non_float_dtypes():
    with pytest.raises(ValueError, match=r"latitude_deg\[1\] = 95"):
        jaximu.earth_rate([10, 95])
    for bad in ("45", None):  # before: "45" ran, None said "got None" from a numpy error
        with pytest.raises(ValueError, match=r"latitude_deg must be an array of numbers"):
            jaximu.earth_rate(bad)
    for dtype in (np.int32, "banana"):  # before: an int computation / numpy's TypeError
        with pytest.raises(ValueError, match=r"dtype must be a floating dtype"):
            jaximu.earth_rate(45.0, dtype=dtype)


def test_earth_rate_is_the_closed_form():
    lat = np.array([-90.0, -30.0, 0.0, 48.1, 90.0])
    phi = np.deg2rad(lat)
    want = 7.292115e-5 * np.stack([0 * phi, np.cos(phi), np.sin(phi)], -1)
    np.testing.assert_allclose(np.asarray(jaximu.earth_rate(lat)), want, rtol=1e-6,
                               atol=1e-6 * 7.3e-5)


def test_omega_coriolis_whose_batch_does_not_fit_is_named():
    with pytest.raises(ValueError, match=r"do not broadcast: .*omega_coriolis \(3,\)"):
        jaximu.propagate(X0, jnp.zeros((2, T, 3)), jnp.broadcast_to(ACCEL, (2, T, 3)), DT,
                         omega_coriolis=jnp.zeros((3, 3)))


@pytest.mark.parametrize("dt, name", [(None, "dt"), ("0.01", "dt")])
def test_text_or_none_for_an_array_names_the_argument(dt, name):
    # before: "None is not a valid value for jnp.array", or numpy's isfinite TypeError
    with pytest.raises(ValueError, match=rf"^{name} must be an array of numbers"):
        jaximu.propagate(X0, GYRO, ACCEL, dt)


def test_mismatched_batches_name_the_arguments():
    with pytest.raises(ValueError, match=r"gyro \(2,\), accel \(3,\)"):
        jaximu.propagate(X0, jnp.zeros((2, T, 3)), jnp.zeros((3, T, 3)), DT)


# --------------------------------------------------------------------------- Monte Carlo

TRAJ = simulate.circle()
TIMES = np.arange(T + 1) * 0.01
P0 = np.eye(15) * 1e-6
KEY = jax.random.key(0)


def _mc(**kw):
    return montecarlo.monte_carlo(TRAJ, kw.pop("times", TIMES), P0, NOISE, 4,
                                  kw.pop("key", KEY), chunk_size=4, **kw)


def test_update_every_beyond_the_steps_is_refused_with_the_largest_that_works():
    # before: NaN statistics (no update ever happened)
    for call in (lambda: _mc(update_every=T + 1),
                 lambda: montecarlo.sample_run(TRAJ, TIMES, P0, NOISE, KEY, 0,
                                               update_every=T + 1)):
        with pytest.raises(InputError, match=rf"update_every = {T + 1} is more than the {T} "):
            call()
    with pytest.raises(InputError) as e:
        _mc(update_every=10 * T)
    assert e.value.fixes == (Fix("update_every", T),)


def test_a_measurement_without_update_every_is_refused_not_ignored():
    with pytest.raises(InputError, match=r"measurement is used only by the filter study") as e:
        _mc(measurement=PositionFix(0.1))
    assert [f.option for f in e.value.fixes] == ["update_every", "measurement"]


@pytest.mark.parametrize("kw, name", [
    (dict(update_every=2, measurement=PositionFix("0.1")), r"measurement\.sigma must be an "
                                                           r"array of numbers"),
    (dict(nees_bins=[0.0, np.nan, 3.0]), r"nees_bins must be .* finite"),
    (dict(nees_bins=[0.0, 1.0, np.inf]), r"nees_bins must be .* finite"),
    (dict(nees_bins="auto"), r"nees_bins must be an array of numbers"),
    (dict(times="0:1"), r"times must be an array of numbers"),
    (dict(key="seed"), r"key must be a threefry jax.random key"),
])
def test_monte_carlo_names_values_it_did_not_check(kw, name):
    # before: sigma "0.1" parsed, NaN/inf edges gave NaN histograms, numpy's messages
    with pytest.raises(ValueError, match=name):
        _mc(**kw)


@pytest.mark.parametrize("name", ["progress", "shard", "keep_nees"])
def test_monte_carlo_bool_options_are_bools(name):
    with pytest.raises(InputError, match=rf"{name} must be True or False") as e:
        _mc(**{name: "no"})
    assert e.value.fixes == (Fix(name, False),)


def _result():
    K = 2
    return MonteCarloResult(
        times=np.arange(K) * 0.1, mean_error=np.zeros((K, 15)), error_cov=np.ones((K, 15, 15)),
        predicted_cov=np.ones((K, 15, 15)), nees=None, nees_mean=np.full(K, 15.0),
        nees_bounds=np.array([10.0, 20.0]), sample_errors=np.zeros((1, K, 15)),
        discretization_error=np.zeros((K, 15)), n_runs=7, confidence=0.9,
        settings=dict(scheme="euler"))


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


# --------------------------------------------------------------------------- Kalibr files

SENSOR = ("T_BS:\n  cols: 4\n  rows: 4\n  data: [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]\n"
          "rate_hz: 200\ngyroscope_noise_density: 1.7e-04\ngyroscope_random_walk: 1.9e-05\n"
          "accelerometer_noise_density: 2.0e-3\naccelerometer_random_walk: 3.0e-3\n")


def test_sensor_yaml_refuses_a_zero_rate_a_yes_and_files_that_are_not_yaml(tmp_path):
    (tmp_path / "r0.yaml").write_text(SENSOR.replace("rate_hz: 200", "rate_hz: 0"))
    with pytest.raises(ValueError, match=r"r0\.yaml: rate_hz must be finite and > 0"):
        kalibr.read_sensor_yaml(tmp_path / "r0.yaml")  # before: rate_hz = 0.0 returned
    (tmp_path / "yes.yaml").write_text(SENSOR.replace("1.7e-04", "yes"))
    with pytest.raises(ValueError, match=r"gyroscope_noise_density must be a number, got True"):
        kalibr.read_sensor_yaml(tmp_path / "yes.yaml")  # before: a density of 1.0
    (tmp_path / "bin.yaml").write_bytes(b"PK\x03\x04\xff\xfe\xa4")
    with pytest.raises(ValueError, match=r"bin\.yaml: not a text \(YAML\) file"):
        kalibr.read_sensor_yaml(tmp_path / "bin.yaml")  # before: UnicodeDecodeError
    with pytest.raises(ValueError, match=r"is a folder; name the sensor YAML file"):
        kalibr.read_sensor_yaml(tmp_path)  # before: IsADirectoryError
    with pytest.raises(ValueError, match=r"--body-P-sensor .*: is a folder"):
        kalibr.parse_body_P_sensor(str(tmp_path))
    with pytest.raises(ValueError, match=r"--body-P-sensor must be text"):
        kalibr.parse_body_P_sensor(None)


# --------------------------------------------------------------------------- the command


@pytest.mark.parametrize("argv, msg", [
    (["montecarlo", "--seconds", "0.05", "--rate", "100", "--fix-sigma", "0.1"],
     r"--fix-sigma is the position fix of the filter study; pass --filter N"),
    (["montecarlo", "--seconds", "0.05", "--rate", "100", "--filter", "100"],
     r"--filter 100 is more than the 5 samples .* pass at most --filter 5"),
    (["montecarlo", "--rate", "0"], r"--rate must be positive"),
    (["propagate", "no_such_folder", "--earth-rate", "100"],
     r"--earth-rate is a latitude in degrees, in \[-90, 90\]; got 100"),
])
def test_the_command_names_the_flag_before_the_work(argv, msg, capsys):
    # before: --fix-sigma ignored without --filter, an IndexError traceback for --filter >
    # samples, "latitude_deg" (not the flag) after reading the data
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert __import__("re").search(msg, err), err


def test_the_library_fix_for_update_every_renders_as_the_filter_flag():
    e = InputError("update_every too large", [Fix("update_every", 5)], lead="pass at most")
    assert e.render(cli.flag_of).endswith("pass at most --filter 5")


@pytest.mark.parametrize("field,value,message", [
    ("q_BS", [1.0, 0.1, 0.0, 0.0], r"initial\.q_BS must be a unit quaternion"),
    ("b_g", [0.0, np.nan, 0.0], r"initial\.b_g"),
    ("gravity", -9.81, r"initial\.gravity is a magnitude"),
    ("p_BS", [[0.0, 0.0, 0.1]] * 2, r"initial\.p_BS must have shape \(3,\)"),
])
@pytest.mark.parametrize("entry", ["calibration_problem", "calibrate"])
def test_calibration_initial_outside_its_domain_is_named_before_any_work(entry, field, value,
                                                                        message):
    """A non-unit q_BS (the fit would start from a scaled rotation), NaN, a negative gravity
    magnitude or a batched field are refused naming initial.<field>, before anything
    compiles (calibrate is given a placeholder problem: the check comes first)."""
    from jaximu import calibration as cal

    bad = cal.ImuCalibration.default(**{field: value})
    with pytest.raises(ValueError, match=message):
        if entry == "calibration_problem":
            t = np.arange(10) * 0.01
            ref = cal.Reference(t, np.tile([1.0, 0, 0, 0], (10, 1)), np.zeros((10, 3)))
            cal.calibration_problem(t, np.zeros((10, 3)), np.zeros((10, 3)), ref,
                                    ImuNoise.euroc(), initial=bad)
        else:
            cal.calibrate(_placeholder_problem(), bad)


def _placeholder_problem():
    from jaximu import calibration as cal

    fields = {f.name: None for f in cal.dataclasses.fields(cal.CalibrationProblem)}
    return cal.CalibrationProblem(**fields)
