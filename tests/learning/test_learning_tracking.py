"""The gravity-aided gyro-bias tracker, against a simulated IMU whose bias is known.

The simulation: an IMU that rotates (band-limited rates about every axis) in place, so its
true velocity is zero, its specific force is gravity seen in the body frame (scipy's
integration of the true rates) plus a constant accelerometer bias and white noise, and its
gyro reads the true rate plus a constant bias ``b_g`` and white noise at the EuRoC
ADIS16448's densities. The tracker starts from a prior bias that is wrong by about one of
its prior standard deviations on every axis and must end near ``b_g``: within three of the
standard deviations it reports, and far inside the prior's error.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_learning_losses import DT, scipy_attitudes, smooth_rates

from jaximu.geometry.noise import ImuNoise
from jaximu.learning import ModelConfig
from jaximu.learning.tracking import TrackerSettings, level_attitude, track_gyro_bias

B_G = np.array([-2.0e-3, 2.3e-2, 7.9e-2])  # rad/s (EuRoC's ADIS16448 reads about these)
B_A = np.array([-0.02, 0.11, 0.07])  # m/s²
NOISE = ImuNoise.euroc()


def rotating_in_place(seed, seconds):
    rng = np.random.default_rng(seed)
    T = int(seconds / DT)
    true = smooth_rates(rng, T, 1.5)  # every axis turns through the horizontal
    q0 = Rotation.random(random_state=seed).as_quat()  # xyzw
    q, rots = scipy_attitudes(np.roll(q0, 1), true, DT)
    f = np.stack([r.inv().apply([0.0, 0.0, 9.81]) for r in rots])
    gyro = true + B_G + NOISE.gyroscope_noise_density / np.sqrt(DT) * rng.standard_normal((T, 3))
    accel = f + B_A + NOISE.accelerometer_noise_density / np.sqrt(DT) * rng.standard_normal((T, 3))
    return gyro, accel


def settings(**kw):
    prior = B_G + np.array([1.5e-3, -2.0e-3, 2.5e-3])
    return TrackerSettings(
        tuple(prior),
        tuple(B_A + 0.02),
        (2.5e-3, 2.5e-3, 2.5e-3),
        (0.03, 0.03, 0.03),
        NOISE,
        **kw,
    )


def test_tracked_gyro_bias_converges_to_the_simulated_bias():
    gyro, accel = rotating_in_place(0, 60.0)
    s = settings()
    out = track_gyro_bias(jnp.asarray(gyro), jnp.asarray(accel), DT, s)
    b, sd = np.asarray(out.gyro_bias, np.float64), np.asarray(out.gyro_bias_sigma, np.float64)
    assert b.shape == sd.shape == gyro.shape
    np.testing.assert_array_equal(b[0], np.asarray(s.gyro_bias, b.dtype))  # the prior first
    err = np.abs(b[-1] - B_G)
    assert np.all(err < 3 * sd[-1]), (err, sd[-1])
    prior_err = np.abs(np.asarray(s.gyro_bias) - B_G)
    assert np.all(err < 0.2 * prior_err), (err, prior_err)
    assert np.all(sd[-1] < 0.3 * np.asarray(s.gyro_bias_sigma))


def test_tracked_gyro_bias_is_causal_and_batched():
    """The bias given sample k depends on no sample after the block that holds k, and a
    batch of recordings is tracked as each alone."""
    gyro, accel = rotating_in_place(1, 6.0)
    s = settings(update_samples=20)
    one = np.asarray(track_gyro_bias(jnp.asarray(gyro), jnp.asarray(accel), DT, s).gyro_bias)
    k = 600  # a block boundary
    g2, a2 = gyro.copy(), accel.copy()
    g2[k:] += 0.3
    a2[k:] *= 1.5
    both = track_gyro_bias(
        jnp.asarray(np.stack([gyro, g2])), jnp.asarray(np.stack([accel, a2])), DT, s
    )
    both = np.asarray(both.gyro_bias)
    np.testing.assert_allclose(both[0], one, rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(both[1, : k + 20], both[0, : k + 20])
    assert not np.allclose(both[1, k + 20 :], both[0, k + 20 :])


def resting(seed, seconds, turn_rate=0.0):
    """An IMU at rest, tilted so that gravity falls on all three axes, turning about the
    vertical at ``turn_rate`` [rad/s] (which leaves the specific force unchanged)."""
    rng = np.random.default_rng(seed)
    T = int(seconds / DT)
    u = Rotation.from_euler("xy", [20.0, -30.0], degrees=True).inv().apply([0.0, 0.0, 1.0])
    gyro = (
        turn_rate * u
        + B_G
        + NOISE.gyroscope_noise_density / np.sqrt(DT) * rng.standard_normal((T, 3))
    )
    accel = (
        9.81 * u
        + B_A
        + NOISE.accelerometer_noise_density / np.sqrt(DT) * rng.standard_normal((T, 3))
    )
    return gyro, accel, u


def test_a_standstill_gives_the_bias_about_the_vertical():
    """At rest the mean gyro is the bias: each 1-s window updates the bias about the vertical
    with ``standstill_sigma``, so after ``N`` windows its error is within 3 of the filter's
    ``standstill_sigma/√N`` (the white noise's own, ``σ_g/√1 s``, is 6× smaller). Without the
    standstill updates the bias about the vertical is unobservable and keeps most of the
    prior's error."""
    gyro, accel, u = resting(4, 10.0)
    s = settings()
    on = np.asarray(track_gyro_bias(gyro, accel, DT, s).gyro_bias, np.float64)
    off = np.asarray(
        track_gyro_bias(gyro, accel, DT, s._replace(standstill_samples=0)).gyro_bias, np.float64
    )
    prior_err = abs(float(u @ (np.asarray(s.gyro_bias) - B_G)))
    windows = len(gyro) // s.standstill_samples - 1  # the last one updates after the last sample
    bound = 3 * s.standstill_sigma / np.sqrt(windows)
    assert bound < 0.5 * prior_err  # the check can tell the update from the prior
    assert abs(float(u @ (on[-1] - B_G))) < bound, (u @ (on[-1] - B_G), bound)
    assert abs(float(u @ (off[-1] - B_G))) > 0.5 * prior_err


@pytest.mark.parametrize("case", ["turning about the vertical", "rotating"])
def test_motion_is_no_standstill(case):
    """A turn about the vertical at 0.05 rad/s leaves the specific force of rest but fails
    the gate (3 √(σ_b² + standstill_sigma²) ≈ 8e-3 rad/s here); a rotation through the
    horizontal fails the specific-force test: no window updates the bias, which is then the
    one tracked without standstill updates."""
    if case == "rotating":
        gyro, accel = rotating_in_place(5, 10.0)
    else:
        gyro, accel, _ = resting(5, 10.0, turn_rate=0.05)
    s = settings()
    on = track_gyro_bias(gyro, accel, DT, s).gyro_bias
    off = track_gyro_bias(gyro, accel, DT, s._replace(standstill_samples=0)).gyro_bias
    np.testing.assert_allclose(np.asarray(on), np.asarray(off), rtol=1e-12, atol=0.0)


def test_a_recording_shorter_than_the_standstill_window_has_no_standstill():
    gyro, accel, _ = resting(6, 0.5)  # 100 samples: half a window
    s = settings()
    on = track_gyro_bias(gyro, accel, DT, s).gyro_bias
    off = track_gyro_bias(gyro, accel, DT, s._replace(standstill_samples=0)).gyro_bias
    np.testing.assert_allclose(np.asarray(on), np.asarray(off), rtol=1e-12, atol=0.0)


def test_level_attitude_turns_the_specific_force_to_world_up():
    rng = np.random.default_rng(3)
    f = rng.standard_normal((50, 3)) * [1.0, 1.0, 3.0]
    f = np.concatenate([f, [[0.0, 0.0, -9.81], [9.81, 0.0, 0.0], [0.0, 0.0, 9.81]]])
    q = np.asarray(level_attitude(jnp.asarray(f)), np.float64)
    up = Rotation.from_quat(np.roll(q, -1, axis=-1)).apply(f / np.linalg.norm(f, axis=1)[:, None])
    np.testing.assert_allclose(up, np.tile([0.0, 0.0, 1.0], (len(f), 1)), atol=1e-6)


@pytest.mark.parametrize(
    "kw, name",
    [
        ({"gyro_bias_sigma": (1e-3, 0.0, 1e-3)}, "gyro_bias_sigma"),
        ({"accel_bias_sigma": (0.03, 0.03)}, "accel_bias_sigma"),
        ({"velocity_sigma": float("nan")}, "velocity_sigma"),
        ({"update_samples": 0}, "update_samples"),
        ({"standstill": "yes"}, "standstill"),
    ],
)
def test_tracker_settings_outside_their_domain_are_refused(kw, name):
    with pytest.raises(ValueError, match=f"ModelConfig.{name}"):
        ModelConfig(**kw)


@pytest.mark.parametrize(
    "gyro, accel, dt, sets, match",
    [
        (np.zeros((50, 3)), np.zeros((50, 2)), DT, True, "gyro and accel must have one shape"),
        (np.zeros((5, 3)), np.ones((5, 3)), DT, True, "at least 10 samples"),
        (np.zeros((50, 3)), np.ones((50, 3)), 0.0, True, "dt must be"),
        (np.zeros((50, 3)), np.ones((50, 3)), DT, False, "settings must be"),
    ],
)
def test_track_gyro_bias_refuses_bad_input_naming_it(gyro, accel, dt, sets, match):
    with pytest.raises(ValueError, match=match):
        track_gyro_bias(gyro, accel, dt, settings() if sets else {"gyro_bias": (0, 0, 0)})


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"standstill_samples": 30}, "settings.standstill_samples must be 0 or a whole"),
        ({"standstill_sigma": 0.0}, "settings.standstill_sigma must be positive and finite"),
        ({"standstill_accel_std": float("nan")}, "settings.standstill_accel_std must be"),
        ({"velocity_sigma": -1.0}, "settings.velocity_sigma must be positive and finite"),
        ({"update_samples": 0}, "settings.update_samples must be a positive integer"),
    ],
)
def test_tracker_settings_given_directly_are_checked_naming_the_field(kw, match):
    with pytest.raises(ValueError, match=match):
        track_gyro_bias(np.zeros((50, 3)), np.ones((50, 3)), DT, settings(**kw))


def test_tracker_settings_with_a_bad_prior_sigma_are_refused():
    bad = settings()._replace(gyro_bias_sigma=(1e-3, -1e-3, 1e-3))
    with pytest.raises(ValueError, match="settings.gyro_bias_sigma must be 3 positive numbers"):
        track_gyro_bias(np.zeros((50, 3)), np.ones((50, 3)), DT, bad)


def test_a_model_saved_without_the_standstill_setting_loads_without_standstill_updates():
    """The standstill window is one second in whole update blocks; a configuration written
    before the setting existed reads back as it was trained: without standstill updates."""
    assert ModelConfig(rate_hz=200.0).tracker().standstill_samples == 200
    assert ModelConfig(rate_hz=100.0, update_samples=20).tracker().standstill_samples == 100
    assert ModelConfig(standstill=False).tracker().standstill_samples == 0
    old = {k: v for k, v in ModelConfig().to_json().items() if k != "standstill"}
    assert ModelConfig.from_json(old).tracker().standstill_samples == 0
    assert ModelConfig.from_json(ModelConfig().to_json()).standstill
