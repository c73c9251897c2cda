"""IMU integration inside learned models: a small network that corrects raw samples,
trained end to end through :func:`jaximu.propagate_final`.

Pure JAX (no framework dependency): an MLP is a list of ``(W, b)`` pairs. The corrector
sees a causal window of raw samples and outputs an additive correction of the current
gyro and accelerometer sample (a learned, signal-dependent bias). Its last layer starts at
zero, so training starts from the uncorrected integration.

Typical use (``examples/learned_correction.py``)::

    params = init_mlp(key, [6 * window, 64, 64, 6])
    segs = segments(t, gyro, accel, truth, length=200)    # 1 s pieces at 200 Hz
    loss = lambda p: segment_loss(p, segs, window=window)  # optax over jax.grad(loss)
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu import so3
from jaximu.propagate import propagate_final
from jaximu.state import NavState

__all__ = [
    "init_mlp",
    "mlp",
    "causal_windows",
    "correct_samples",
    "Segments",
    "segments",
    "segment_errors",
    "segment_loss",
    "GYRO_UNIT",
    "ACCEL_UNIT",
]

GYRO_UNIT = 1.0
"""Inputs are divided by these [rad/s], [m/s²] (the network sees O(1) numbers)."""
ACCEL_UNIT = 9.81
CORRECTION_UNIT = (0.01, 0.1)
"""The network's outputs are in these units [rad/s], [m/s²] (typical bias magnitudes)."""


def init_mlp(key, sizes, dtype=None):
    """``[(W, b), ...]`` for layer sizes ``sizes`` (input first); Glorot-uniform hidden
    layers and a zero last layer (the initial output is 0)."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.zeros(()).dtype
    params = []
    keys = jax.random.split(key, len(sizes) - 1)
    for i, (k, n_in, n_out) in enumerate(zip(keys, sizes[:-1], sizes[1:])):
        if i == len(sizes) - 2:
            W = jnp.zeros((n_in, n_out), dtype)
        else:
            lim = np.sqrt(6.0 / (n_in + n_out))
            W = jax.random.uniform(k, (n_in, n_out), dtype, -lim, lim)
        params.append((W, jnp.zeros((n_out,), dtype)))
    return params


def mlp(params, x):
    """``(..., n_in) -> (..., n_out)``: tanh hidden layers, linear output."""
    for W, b in params[:-1]:
        x = jnp.tanh(x @ W + b)
    W, b = params[-1]
    return x @ W + b


def causal_windows(x, size: int):
    """``(..., T, d) -> (..., T, size·d)``: row k holds samples ``k-size+1 … k`` (before the
    start, sample 0 is repeated), oldest first."""
    T = x.shape[-2]
    idx = jnp.clip(jnp.arange(T)[:, None] + jnp.arange(-size + 1, 1)[None, :], 0, T - 1)
    w = jnp.take(x, idx, axis=-2)  # (..., T, size, d)
    return w.reshape(w.shape[:-2] + (size * x.shape[-1],))


def correct_samples(params, gyro, accel, window: int):
    """Raw ``(..., T, 3)`` samples plus the network's correction of each."""
    feats = causal_windows(jnp.concatenate([gyro / GYRO_UNIT, accel / ACCEL_UNIT], -1), window)
    out = mlp(params, feats)
    return (gyro + CORRECTION_UNIT[0] * out[..., 0:3],
            accel + CORRECTION_UNIT[1] * out[..., 3:6])


class Segments(NamedTuple):
    """Pieces of a recording with the true state at both ends (a pytree of arrays).

    Attributes:
        start, end: :class:`NavState` with ``(S, ·)`` fields (biases zero: the raw samples
            are integrated as they are, so the correction has to learn the bias).
        gyro, accel: ``(S, L + context, 3)`` raw samples, the first ``context`` ones before
            ``start`` (the network's history); dt: ``(S, L)`` [s].
    """

    start: NavState
    end: NavState
    gyro: jax.Array
    accel: jax.Array
    dt: jax.Array


def segments(t, gyro, accel, truth: NavState, length: int, context: int = 0,
             stride: int | None = None) -> Segments:
    """Cut a recording into pieces of ``length`` steps with the truth at both ends.

    Args:
        t: ``(N,)`` sample times [s]; gyro, accel: ``(N, 3)`` raw samples.
        truth: :class:`NavState` with ``(N, ·)`` fields: the true state at each sample time.
        length: steps per piece; context: samples of history kept before each piece;
        stride: samples between piece starts (default ``length``).
    """
    t = np.asarray(t, np.float64)
    stride = length if stride is None else stride
    starts = np.arange(context, len(t) - length, stride)
    if len(starts) == 0:
        raise ValueError(f"the recording ({len(t)} samples) is shorter than one piece "
                         f"({length} steps after {context} samples of context)")
    sl = starts[:, None] + np.arange(-context, length)[None, :]
    dt = np.diff(t)[starts[:, None] + np.arange(length)[None, :]]
    dtype = jnp.asarray(gyro).dtype

    def at(i):
        return NavState(truth.q[i], truth.p[i], truth.v[i],
                        jnp.zeros((len(i), 3), dtype), jnp.zeros((len(i), 3), dtype))

    return Segments(at(starts), at(starts + length), jnp.asarray(gyro)[sl],
                    jnp.asarray(accel)[sl], jnp.asarray(dt, dtype))


def segment_errors(params, segs: Segments, window: int, scheme: str = "euler",
                   gravity=9.81):
    """``(rotation error (S, 3) [rad], position error (S, 3) [m])`` at the end of each piece
    after integrating the corrected samples from the true start state (``params=None``:
    the raw samples)."""
    gyro, accel = segs.gyro, segs.accel
    if params is not None:
        gyro, accel = correct_samples(params, gyro, accel, window)
    L = segs.dt.shape[-1]
    gyro, accel = gyro[..., -L:, :], accel[..., -L:, :]
    end = propagate_final(segs.start, gyro, accel, segs.dt, scheme, gravity=gravity)
    rot = so3.log(so3.quat_mul(so3.quat_conj(segs.end.q), end.q))
    return rot, end.p - segs.end.p


def segment_loss(params, segs: Segments, window: int, scheme: str = "euler", gravity=9.81,
                 rotation_scale: float = 0.01, position_scale: float = 0.01):
    """Mean squared end-of-piece error, rotation and position each in units of
    ``rotation_scale`` [rad] and ``position_scale`` [m]."""
    rot, pos = segment_errors(params, segs, window, scheme, gravity)
    return (jnp.mean(jnp.sum(rot**2, -1)) / rotation_scale**2
            + jnp.mean(jnp.sum(pos**2, -1)) / position_scale**2)
