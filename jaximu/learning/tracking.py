"""Gravity-aided tracking of the gyro bias: what the network cannot see in 2.5 s of samples.

A new recording's gyro bias differs from the training recordings' mean by up to
``4e-3 rad/s`` on EuRoC (its biases cluster by recording day), which integrates to degrees
within a minute: more than any local correction removes. Two of its three axes are
observable from the accelerometer: a bias about a horizontal axis tilts the integrated
attitude, and a tilted attitude turns gravity into a growing apparent velocity, while a
vehicle in a room keeps its true velocity bounded. The tracker is therefore an error-state
EKF on jaximu's own propagation (:func:`jaximu.engine.errorstate.propagate_covariance_final`)
and update (:func:`jaximu.engine.update.ekf_update`), started level from the first
specific force with the stored constant biases, and updated every ``update_samples``
samples with the pseudo-measurement ``v = 0 ± velocity_sigma``. It needs no ground truth, only
the raw samples before each instant: the bias it gives sample ``k`` comes from the samples
before the block that holds ``k`` (causal, as the evaluation's open-loop integration needs).

The bias about the vertical (the heading's) is not observable from gravity at rest and only
weakly, through the tilting and the bounded-velocity assumption, in motion. A standstill
observes it directly: a vehicle at rest turns at zero rate (Earth's 7e-5 rad/s is below the
biases' spread), so its mean gyro is its bias, the zero-rate update of the static
initialisations of OpenVINS and VINS-Mono. Every ``standstill_samples`` the tracker tests the
window that ends there: its update blocks' mean specific forces must stay within
``standstill_accel_std`` of their mean (no tilting, no shaking beyond a parked vehicle's
running motors), that mean must be gravity's norm within ``standstill_gravity_tolerance``
(no sustained acceleration), and the mean rate about that direction, less the tracked bias,
must pass a 3σ gate on its prior and ``standstill_sigma``. A window that passes updates the
bias about the vertical only, ``u·(ω̄ - b̂) = 0 ± standstill_sigma``: the horizontal axes
keep the gravity tracking, which a resting drone's running motors do not fool as they do a
mean (on EuRoC the means at rest differ from the estimated biases by 1-2e-3 rad/s about the
IMU's y and z axes, 1-2e-4 about its x, which is near the vertical). What the specific force cannot tell from rest
is a turn about the vertical slower than the gate (``3 √(σ_b² + standstill_sigma²)``, about
``4e-3 rad/s`` on EuRoC before a first standstill): its rate is then taken for bias, one
window at a time.

The position is reset to zero (and its covariance rows to zero) at every update: nothing is
measured of it, and its unbounded variance would otherwise span too many decades for float32.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.engine.errorstate import propagate_covariance_final
from jaximu.engine.update import ekf_update
from jaximu.geometry._checks import (
    check_array,
    check_finite,
    check_int,
    check_output,
    check_positive,
    check_unbatched_noise,
    float_dtype,
    is_concrete,
    to_dtype,
)
from jaximu.geometry.noise import ImuNoise, check_noise
from jaximu.geometry.state import NavState

__all__ = ["TrackerSettings", "Tracked", "track_gyro_bias", "level_attitude", "check_settings"]

LEVEL_SAMPLES = 10
"""Samples whose mean specific force gives the first attitude's roll and pitch."""


class TrackerSettings(NamedTuple):
    """What the tracker assumes (all SI; per-axis values in the IMU frame).

    Attributes:
        gyro_bias, accel_bias: ``(3,)`` the prior biases [rad/s], [m/s²] (the constant ones).
        gyro_bias_sigma, accel_bias_sigma: ``(3,)`` their prior standard deviations.
        noise: the sensor's :class:`ImuNoise` densities.
        velocity_sigma: [m/s] the pseudo-measurement ``v = 0``'s standard deviation.
        tilt_sigma: [rad] the first attitude's roll and pitch standard deviation (the first
            samples' specific force is not gravity alone when the vehicle moves).
        update_samples: samples between updates.
        gravity: [m/s²].
        standstill_samples: the window a standstill is tested on [samples] (a whole
            number of ``update_samples``; the default is 1 s at 200 Hz; 0: no standstill
            updates).
        standstill_accel_std: [m/s²] the largest spread of the update blocks' mean specific
            forces about the window's mean at a standstill.
        standstill_gravity_tolerance: [m/s²] the largest difference of the window's mean
            specific force's norm from ``gravity`` at a standstill.
        standstill_sigma: [rad/s] the standard deviation of a standstill's rate about the
            vertical, as the measurement of the bias about it.
    """

    gyro_bias: tuple
    accel_bias: tuple
    gyro_bias_sigma: tuple
    accel_bias_sigma: tuple
    noise: ImuNoise
    velocity_sigma: float = 1.0
    tilt_sigma: float = 0.1
    update_samples: int = 20
    gravity: float = 9.81
    standstill_samples: int = 200
    standstill_accel_std: float = 0.1
    standstill_gravity_tolerance: float = 0.2
    standstill_sigma: float = 1e-3


class Tracked(NamedTuple):
    """The tracker's output per sample, each ``(..., T, 3)``: ``gyro_bias`` [rad/s] and its
    standard deviation ``gyro_bias_sigma`` [rad/s]."""

    gyro_bias: jax.Array
    gyro_bias_sigma: jax.Array


def level_attitude(specific_force):
    """``(..., 4)``: the attitude ``R_WB`` (``[w, x, y, z]``) of least rotation that turns the
    body's ``specific_force`` ``(..., 3)`` [m/s²] to world +z (yaw: that of least rotation).
    Upside down (the force along -z) it turns by π about x."""
    u = specific_force / jnp.linalg.norm(specific_force, axis=-1, keepdims=True)
    # the rotation taking u to e_z: q ∝ [1 + u·e_z, u × e_z]
    w = 1.0 + u[..., 2]
    xyz = jnp.stack([u[..., 1], -u[..., 0], jnp.zeros_like(w)], -1)
    flipped = w < 1e-6
    q = jnp.concatenate([w[..., None], xyz], -1)
    q = jnp.where(flipped[..., None], jnp.asarray([0.0, 1.0, 0.0, 0.0], q.dtype), q)
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def _standstills(gyro, accel, s: TrackerSettings, M: int, K: int):
    """Per update block of ``M`` samples ``(n_blocks, ·)``: whether the window of the ``K``
    blocks ending with it is tested for a standstill and passes the specific-force tests,
    the window's mean rate ``ω̄`` and its mean specific force's direction ``u``."""
    mean = lambda x: x.reshape((-1, M, 3)).mean(1)  # noqa: E731
    g, a = mean(gyro), mean(accel)
    n = g.shape[0]

    def window(x):  # the mean of the K blocks up to each block (the first K-1: partial)
        c = jnp.concatenate([jnp.zeros((K,) + x.shape[1:], x.dtype), jnp.cumsum(x, 0)], 0)
        return (c[K:] - c[:n]) / K

    w_g, w_a = window(g), window(a)
    spread = jnp.sqrt(jnp.maximum(window(jnp.sum(a * a, -1)) - jnp.sum(w_a * w_a, -1), 0.0))
    norm = jnp.linalg.norm(w_a, axis=-1)
    j = jnp.arange(n)
    tested = (j % K == K - 1) & (s.standstill_samples > 0)  # whole windows, each once
    still = (
        tested
        & (spread < s.standstill_accel_std)
        & (jnp.abs(norm - s.gravity) < s.standstill_gravity_tolerance)
    )
    return still, w_g, w_a / norm[:, None]


def _track_one(gyro, accel, dt, s: TrackerSettings, M: int, K: int):
    """One recording ``(T, 3)``; ``T`` a multiple of ``M`` (``s.update_samples``); ``K``
    update blocks per standstill window."""
    dtype = gyro.dtype
    f = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    first = jnp.mean(accel[:LEVEL_SAMPLES], 0)
    zero = jnp.zeros(3, dtype)
    state = NavState(level_attitude(first), zero, zero, f(s.gyro_bias), f(s.accel_bias))
    # the tilt is uncertain about the two body axes across gravity, the heading not at all
    # (the world's yaw is defined by the first attitude)
    u = first / jnp.linalg.norm(first)
    I3 = jnp.eye(3, dtype=dtype)
    tilt = s.tilt_sigma**2 * (I3 - jnp.outer(u, u))
    P0 = jnp.zeros((15, 15), dtype)
    P0 = P0.at[0:3, 0:3].set(tilt)
    P0 = P0.at[6:9, 6:9].set(s.velocity_sigma**2 * I3)
    P0 = P0.at[9:12, 9:12].set(jnp.diag(f(s.gyro_bias_sigma) ** 2))
    P0 = P0.at[12:15, 12:15].set(jnp.diag(f(s.accel_bias_sigma) ** 2))
    H = jnp.zeros((3, 15), dtype).at[:, 6:9].set(I3)  # the velocity
    R = s.velocity_sigma**2 * I3
    keep = jnp.ones(15, dtype).at[3:6].set(0.0)  # the position's rows and columns
    steps = jnp.full((M,), dt, dtype)
    R_still = jnp.reshape(jnp.asarray(s.standstill_sigma, dtype) ** 2, (1, 1))

    def block(carry, samples):
        state, P = carry
        g, a, still, w, u_w = samples
        out = (state.b_g, jnp.sqrt(jnp.diagonal(P)[9:12]))
        state, P = propagate_covariance_final(state, P, g, a, steps, s.noise, gravity=s.gravity)
        state, P, _ = ekf_update(state, P, -state.v, H, R)
        # a standstill: the rate about the vertical is zero, so u·(ω̄ - b̂) measures u·δb_g
        Hs = jnp.zeros((1, 15), dtype).at[0, 9:12].set(u_w)
        nu = jnp.dot(u_w, w - state.b_g)[None]
        gate = 9.0 * (u_w @ P[9:12, 9:12] @ u_w + R_still[0, 0])
        use = still & (nu[0] ** 2 < gate)
        s_new, P_new, _ = ekf_update(state, P, nu, Hs, R_still)
        state = jax.tree_util.tree_map(lambda x, y: jnp.where(use, x, y), s_new, state)
        P = jnp.where(use, P_new, P)
        state = NavState(state.q, zero, state.v, state.b_g, state.b_a)
        P = P * keep[:, None] * keep[None, :]
        return (state, 0.5 * (P + P.T)), out

    blocks = lambda x: x.reshape((-1, M, 3))  # noqa: E731
    still, w, u_w = _standstills(gyro, accel, s, M, K)
    _, (b, sd) = jax.lax.scan(block, (state, P0), (blocks(gyro), blocks(accel), still, w, u_w))
    return jnp.repeat(b, M, axis=0), jnp.repeat(sd, M, axis=0)


_POSITIVE = {
    "velocity_sigma": "m/s",
    "tilt_sigma": "rad",
    "gravity": "m/s²",
    "standstill_accel_std": "m/s²",
    "standstill_gravity_tolerance": "m/s²",
    "standstill_sigma": "rad/s",
}


def check_settings(settings: TrackerSettings, name: str = "settings") -> None:
    """Raise ``ValueError`` naming ``name.field`` for a field of ``settings`` outside its
    domain: the prior biases 3 finite numbers, the standard deviations, ``gravity`` and the
    standstill thresholds positive and finite, the noise densities finite and non-negative
    (:func:`jaximu.geometry.noise.check_noise`), ``update_samples`` a positive whole number,
    ``standstill_samples`` 0 or a whole number of ``update_samples``.
    (:class:`jaximu.learning.ModelConfig` checks its tracker's settings with it, under its
    own name.)"""
    if not isinstance(settings, TrackerSettings):
        raise ValueError(
            f"{name} must be a jaximu.learning.TrackerSettings (or model.config.tracker()), "
            f"got {type(settings).__name__}"
        )
    for field, unit in _POSITIVE.items():
        check_positive(f"{name}.{field}", getattr(settings, field), hint=f" [{unit}]")
    for field in ("gyro_bias", "accel_bias", "gyro_bias_sigma", "accel_bias_sigma"):
        x = getattr(settings, field)
        if not is_concrete(x):  # a traced model's fitted priors (checked when it was built)
            if jnp.shape(x) != (3,):
                raise ValueError(f"{name}.{field} must have shape (3,), got {jnp.shape(x)}")
            continue
        v = check_array(f"{name}.{field}", x, (3,))
        if field.endswith("sigma") and not np.all(v > 0):
            raise ValueError(f"{name}.{field} must be 3 positive numbers, got {v.tolist()}")
    noise = check_noise(settings.noise, jnp.result_type(float), f"{name}.noise")
    check_unbatched_noise(noise, "the tracker")
    M = check_int(f"{name}.update_samples", settings.update_samples, 1)
    W = check_int(f"{name}.standstill_samples", settings.standstill_samples, 0)
    if W % M:
        raise ValueError(
            f"{name}.standstill_samples must be 0 or a whole number of update_samples "
            f"({M}), got {W}"
        )


def _check_level(accel, gravity: float) -> None:
    """The first attitude is levelled on the mean specific force of the first
    :data:`LEVEL_SAMPLES`: refuse (naming ``accel`` and the recording) a mean that is no
    direction, below ``1e-3 · gravity`` (an accelerometer that reads zeros)."""
    if not is_concrete(accel):
        return
    first = np.asarray(accel, np.float64)[..., :LEVEL_SAMPLES, :].mean(-2)
    norm = np.linalg.norm(first, axis=-1)
    bad = ~(norm > 1e-3 * gravity)
    if bad.any():
        i = tuple(np.argwhere(bad)[0]) if bad.ndim else ()
        at = f" of recording {[int(k) for k in i]}" if i else ""
        raise ValueError(
            f"accel{at}: its first {LEVEL_SAMPLES} samples average to a specific force of "
            f"{norm[i]:.3g} m/s² (gravity is {gravity:g}), so no level attitude can be taken "
            "from them (a dead or disconnected accelerometer reads zeros); pass the "
            "accelerometer's samples in m/s², from where it reads gravity"
        )


def track_gyro_bias(gyro, accel, dt: float, settings: TrackerSettings) -> Tracked:
    """The gyro bias at every sample, tracked from the raw samples before it.

    Args:
        gyro, accel: ``(..., T, 3)`` raw samples [rad/s], [m/s²] at a constant interval,
            finite, ``T ≥ 10``; leading axes are independent recordings. The first 10
            samples' mean specific force must be a direction (not zeros).
        dt: the sampling interval [s], one positive number.
        settings: :class:`TrackerSettings` (:func:`check_settings`).

    Returns:
        :class:`Tracked`, ``(..., T, 3)`` each, in the samples' dtype; not differentiated
        (the tracker is a fixed estimator, not a learned one).
    """
    check_settings(settings)
    dtype = float_dtype(gyro, accel)
    gyro, accel = to_dtype("gyro", gyro, dtype), to_dtype("accel", accel, dtype)
    if gyro.ndim < 2 or gyro.shape[-1] != 3 or gyro.shape != accel.shape:
        raise ValueError(
            f"gyro and accel must have one shape (..., T, 3), got {tuple(gyro.shape)} and "
            f"{tuple(accel.shape)}"
        )
    if gyro.shape[-2] < LEVEL_SAMPLES:
        raise ValueError(
            f"gyro and accel need at least {LEVEL_SAMPLES} samples (the first attitude is "
            f"levelled on their mean specific force), got {gyro.shape[-2]}"
        )
    check_sampling_interval("dt", dt)
    fix = "repair or drop those samples (the readers' drop_nonfinite=True)"
    check_finite("gyro", gyro, fix)
    check_finite("accel", accel, fix)
    _check_level(accel, float(settings.gravity))
    M, W = int(settings.update_samples), int(settings.standstill_samples)
    # the settings' numbers are arguments of one compiled program per shape, M and K, not
    # constants of a program per call (standstill_samples stays as an off switch)
    out = _track(
        gyro,
        accel,
        dt,
        settings._replace(update_samples=0, standstill_samples=W),
        M,
        max(W // M, 1),
    )
    return check_output("track_gyro_bias", out, "the samples or the settings' scales")


def check_sampling_interval(name: str, dt) -> float:
    """``dt`` as a ``float``: one sampling interval [s], positive and finite (a constant
    rate); an array of intervals is refused naming ``name``, with the fix."""
    if np.ndim(dt) != 0 and not isinstance(dt, (str, bytes)):
        raise ValueError(
            f"{name} must be one sampling interval in seconds (the samples are at a constant "
            f"rate), got an array of shape {np.shape(dt)}; pass its median, e.g. "
            f"{name}=float(np.median(intervals))"
        )
    return check_positive(name, dt, hint=" (the sampling interval [s])")


@partial(jax.jit, static_argnums=(4, 5))
def _track(gyro, accel, dt, settings: TrackerSettings, M: int, K: int) -> Tracked:
    gyro, accel = jax.lax.stop_gradient(gyro), jax.lax.stop_gradient(accel)
    T = gyro.shape[-2]
    n = -(-T // M) * M
    lead = gyro.shape[:-2]

    def pad(x):  # the last sample held to a whole block; its outputs are cut off
        x = x.reshape((-1,) + x.shape[-2:])
        return jnp.concatenate([x, jnp.repeat(x[:, -1:], n - T, axis=1)], axis=1)

    run = jax.vmap(lambda g, a: _track_one(g, a, dt, settings, M, K))
    b, sd = run(pad(gyro), pad(accel))
    return Tracked(b[:, :T].reshape(lead + (T, 3)), sd[:, :T].reshape(lead + (T, 3)))
