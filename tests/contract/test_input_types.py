"""What kind of thing each input is. The computation dtype promotes over every input (a
float64 ``state.p``, ``dt``, ``P0`` or bias beside float32 samples computes in float64; a
Python scalar stays weak, as in JAX; the model's constants take the data's dtype); complex
numbers, booleans, text and ``None`` are refused naming the argument; and an option that
is a bool must be one (``"no"`` is true: a word is refused with its repair).

The references: the same call with every input float64 (the suite runs with
``jax_enable_x64``), and the argument's name and repair in the message.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu import ImuBias, ImuNoise, NavState, SensorPose
from jaximu.errors import Fix, InputError

T = 4
F32 = np.float32
Q32 = np.array([1.0, 0, 0, 0], F32)
Z32 = np.zeros(3, F32)
GYRO = np.tile(np.array([0.1, -0.2, 0.3], F32), (T, 1))
ACCEL = np.tile(np.array([0.0, 0.0, 9.81], F32), (T, 1))


def as64(tree):
    return jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), tree)


X0 = NavState(jnp.array([1.0, 0, 0, 0]), jnp.zeros(3), jnp.zeros(3), jnp.zeros(3), jnp.zeros(3))
DT = 0.01
NOISE = ImuNoise(1e-3, 1e-2, 1e-5, 1e-4)
POSE = SensorPose(jnp.array([1.0, 0, 0, 0]), jnp.array([0.1, 0.0, 0.0]))
OMEGA = [0.0, 5e-5, 5e-5]
ZERO_GYRO = jnp.zeros((T, 3))
STILL_ACCEL = jnp.tile(jnp.array([0.0, 0.0, 9.81]), (T, 1))


# --------------------------------------------------------------------------- dtype promotion


def test_a_float64_state_field_beside_float32_samples_computes_in_float64():
    state = NavState(Q32, np.array([1e6 + 0.123, 0.0, 0.0]), Z32, Z32, Z32)  # p float64
    got = jaximu.propagate_final(state, GYRO, ACCEL, 0.01)
    want = jaximu.propagate_final(
        as64(state), GYRO.astype(np.float64), ACCEL.astype(np.float64), 0.01
    )
    assert got.p.dtype == jnp.float64
    np.testing.assert_array_equal(got.p, want.p)
    assert abs(float(got.p[0]) - (1e6 + 0.123)) < 1e-3  # the 0.123 m kept


def test_a_float64_dt_or_covariance_or_bias_promotes_and_a_python_scalar_does_not():
    s32 = NavState(Q32, Z32, Z32, Z32, Z32)
    assert jaximu.propagate_final(s32, GYRO, ACCEL, 0.01).p.dtype == jnp.float32
    assert jaximu.propagate_final(s32, GYRO, ACCEL, [0.01] * T).p.dtype == jnp.float32  # weak
    assert jaximu.propagate_final(s32, GYRO, ACCEL, np.full(T, 0.01)).p.dtype == jnp.float64
    P0 = np.eye(15) * 1e-6  # numpy float64
    _, P = jaximu.propagate_covariance_final(s32, P0, GYRO, ACCEL, 0.01, ImuNoise.euroc())
    assert P.dtype == jnp.float64
    _, P = jaximu.propagate_covariance_final(
        s32, P0.astype(F32), GYRO, ACCEL, 0.01, ImuNoise.euroc()
    )
    assert P.dtype == jnp.float32
    bias = ImuBias(np.full(3, 1 + 1e-9), np.zeros(3))
    pim = jaximu.preintegrate(GYRO, ACCEL, 0.01, bias=bias)
    assert pim.delta_p.dtype == jnp.float64
    np.testing.assert_array_equal(pim.bias_hat.b_g, bias.b_g)  # not rounded to 1.0


def test_the_models_constants_take_the_datas_dtype():
    """Gravity, a sensor pose, the world's rate and noise densities given as float64 arrays
    leave a float32 run float32 (a float64 ``earth_rate()`` must not double its cost)."""
    s32 = NavState(Q32, Z32, Z32, Z32, Z32)
    pose = jaximu.SensorPose(np.array([1.0, 0, 0, 0]), np.array([0.1, 0.0, 0.0]))
    out = jaximu.propagate_final(
        s32,
        GYRO,
        ACCEL,
        0.01,
        gravity=np.array([0.0, 0.0, -9.81]),
        body_P_sensor=pose,
        omega_coriolis=np.asarray(jaximu.earth_rate(48.0), np.float64),
    )
    assert out.p.dtype == jnp.float32
    noise = ImuNoise(np.full(3, 1e-3), np.full(3, 1e-2), 1e-5, 1e-4)
    _, P = jaximu.propagate_covariance_final(s32, np.eye(15, dtype=F32), GYRO, ACCEL, 0.01, noise)
    assert P.dtype == jnp.float32
    assert jaximu.preintegrate(GYRO, ACCEL, 0.01, noise=noise).cov.dtype == jnp.float32


# --------------------------------------------------------------------------- not numbers


@pytest.mark.parametrize("name", ["gyro", "accel", "state.p"])
def test_complex_inputs_are_refused_naming_them(name):
    s = NavState(Q32, Z32, Z32, Z32, Z32)
    gyro, accel = GYRO, ACCEL
    if name == "gyro":
        gyro = GYRO + 1j
    elif name == "accel":
        accel = ACCEL + 0j
    else:
        s = NavState(Q32, Z32 + 1j, Z32, Z32, Z32)
    with pytest.raises(ValueError, match=rf"{name.replace('.', '[.]')}.*complex"):
        jaximu.propagate(s, gyro, accel, 0.01)


@pytest.mark.parametrize("name", ["dt", "gyro"])
def test_booleans_are_not_numbers(name):
    s = NavState(Q32, Z32, Z32, Z32, Z32)
    kw = dict(gyro=GYRO, dt=0.01)
    kw[name] = True if name == "dt" else np.zeros((T, 3), bool)
    with pytest.raises(ValueError, match=rf"{name} must be an array of numbers, got booleans"):
        jaximu.propagate(s, kw["gyro"], ACCEL, kw["dt"])


@pytest.mark.parametrize("dt, name", [(None, "dt"), ("0.01", "dt")])
def test_text_or_none_for_an_array_names_the_argument(dt, name):
    # before: "None is not a valid value for jnp.array", or numpy's isfinite TypeError
    with pytest.raises(ValueError, match=rf"^{name} must be an array of numbers"):
        jaximu.propagate(X0, ZERO_GYRO, STILL_ACCEL, dt)


# --------------------------------------------------------------------------- bool options


@pytest.mark.parametrize("option", ["prefixes", "tangential"])
def test_preintegrate_options_are_bools_not_truth_values(option):
    with pytest.raises(InputError, match=f"{option} must be True or False") as e:
        jaximu.preintegrate(GYRO, ACCEL, 0.01, **{option: "no"})
    assert tuple(e.value.fixes) == (Fix(option, False),)


def test_the_combined_covariance_option_is_a_bool():
    pim = jaximu.preintegrate(GYRO, ACCEL, 0.01, noise=ImuNoise.euroc())
    with pytest.raises(InputError, match="combined must be True or False"):
        pim.covariance(combined="no")
    assert pim.covariance(combined=False).shape == (9, 9)


def _pim():
    return jaximu.preintegrate(ZERO_GYRO, STILL_ACCEL, DT)


BOOL_OPTIONS = [
    (
        "tangential",
        lambda v: jaximu.propagate(
            X0, ZERO_GYRO, STILL_ACCEL, DT, body_P_sensor=POSE, tangential=v
        ),
    ),
    (
        "tangential",
        lambda v: jaximu.propagate_covariance(
            X0,
            np.eye(15) * 1e-4,
            ZERO_GYRO,
            STILL_ACCEL,
            DT,
            NOISE,
            body_P_sensor=POSE,
            tangential=v,
        ),
    ),
    (
        "tangential",
        lambda v: jaximu.preintegrate(ZERO_GYRO, STILL_ACCEL, DT, body_P_sensor=POSE, tangential=v),
    ),
    (
        "coriolis_exact",
        lambda v: jaximu.propagate(
            X0, ZERO_GYRO, STILL_ACCEL, DT, omega_coriolis=OMEGA, coriolis_exact=v
        ),
    ),
    (
        "coriolis_second_order",
        lambda v: jaximu.propagate_final(
            X0,
            ZERO_GYRO,
            STILL_ACCEL,
            DT,
            omega_coriolis=OMEGA,
            coriolis_exact=False,
            coriolis_second_order=v,
        ),
    ),
    (
        "coriolis_exact",
        lambda v: jaximu.predict(X0, _pim(), omega_coriolis=OMEGA, coriolis_exact=v),
    ),
    (
        "coriolis_second_order",
        lambda v: jaximu.residual(X0, X0, _pim(), omega_coriolis=OMEGA, coriolis_second_order=v),
    ),
]


@pytest.mark.parametrize("word, value", [("no", False), ("False", False), ("yes", True)])
@pytest.mark.parametrize(
    "name, call", BOOL_OPTIONS, ids=[f"{n}-{i}" for i, (n, _) in enumerate(BOOL_OPTIONS)]
)
def test_a_bool_option_given_as_a_word_is_refused_with_its_repair(name, call, word, value):
    # before: the string's truth value decided ("no" is true: the option silently on)
    with pytest.raises(InputError, match=rf"{name} must be True or False") as e:
        call(word)
    assert e.value.fixes == (Fix(name, value),)


@pytest.mark.parametrize("name, call", BOOL_OPTIONS[:2] + BOOL_OPTIONS[3:5])
def test_a_bool_option_given_as_none_is_refused(name, call):
    with pytest.raises(ValueError, match=rf"{name} must be True or False, got NoneType"):
        call(None)
