"""The engine entries' inputs made ready for a kernel: checked and broadcast (:func:`prepare`),
time-major samples, the state's start, the batch flattened into lanes, the samples a
next-sample scheme or a sensor pose needs. Shared by the mean (:mod:`jaximu.engine.propagate`)
and the covariance (:mod:`jaximu.engine.errorstate`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.geometry import _checks as val
from jaximu.geometry import sensor, so3
from jaximu.geometry.state import NavState, check_state, require_navstate
from jaximu.kernels import fast as _fast
from jaximu.schemes.integrators import check_scheme, get_attitude, get_scheme


def prepare(state, gyro, accel, dt, gravity, scheme, attitude, others=()):
    """Validate the public inputs; returns arrays in one float dtype and the batch shape.

    The dtype is the promotion of the data: the state, the samples, ``dt`` and ``others``
    (an entry's further data: the covariance ``P0``; :func:`jaximu.geometry._checks.float_dtype`).
    Constants of the model (gravity, noise densities, a sensor pose, the world's rate) take
    the data's dtype, as a Python constant does: a float64 ``earth_rate()`` beside float32
    samples must not turn the computation into float64."""
    check_scheme(scheme)
    get_attitude(attitude)
    require_navstate(state)
    dtype = val.float_dtype(state, gyro, accel, dt, *others)
    state = check_state(state, dtype)
    gyro, accel, dt, T = val.check_imu(gyro, accel, dt, dtype, allow_intervals=True)
    g = val.gravity_vector(gravity, dtype)
    batch = val.batch_shape(
        state.batch_shape,
        gyro.shape[:-2],
        accel.shape[:-2],
        dt.shape[:-1],
        g.shape[:-1],
        names=("state", "gyro", "accel", "dt", "gravity"),
    )
    return state, gyro, accel, dt, g, batch


def time_major(gyro, accel, dt, scheme):
    """Inputs as scan ``xs``: samples k and k+1 with time first, dt of shape ``(n, ...)``.

    With ``n = T`` steps, midpoint and RK4 have no sample k+1 at the last step: the last
    sample is held (the step is then a zero-order hold, as Euler's). With ``n = T - 1``
    (the samples are the ends of the intervals) every step has both.
    """
    n = n_steps(gyro, dt)
    w = jnp.moveaxis(gyro, -2, 0)
    a = jnp.moveaxis(accel, -2, 0)
    h = jnp.moveaxis(dt, -1, 0) if dt.ndim else jnp.broadcast_to(dt, (n,))
    if scheme == "euler":
        w1, a1 = w[:n], a[:n]  # unused by the Euler stages
    elif n == w.shape[0]:
        w1 = jnp.concatenate([w[1:], w[-1:]], axis=0)
        a1 = jnp.concatenate([a[1:], a[-1:]], axis=0)
    else:
        w1, a1 = w[1:], a[1:]
    return w[:n], a[:n], w1, a1, h


def n_steps(gyro, dt) -> int:
    """Number of steps: ``dt``'s length (T or T-1), or T for a scalar ``dt``."""
    return dt.shape[-1] if dt.ndim else gyro.shape[-2]


def unit_start(state: NavState, soa: bool, attitude: str) -> NavState:
    """``state`` with ``q / |q|``: the engines start from the rotation ``q`` stands for.
    Eager calls refuse a ``q`` further from unit than the tolerance; under ``jit`` nothing
    can check it, and the kernels' renormalisation after each step assumes a unit start
    (:func:`jaximu.kernels.lane_math._quat_renormalize`). For a unit ``q`` it changes nothing but
    rounding. ``soa``: a structure-of-arrays kernel runs; for the quaternion forms it
    normalises inside the kernel (:func:`jaximu.kernels.fast._unit_start`: outside, the O(B)
    normalisation is more modules for XLA:CPU to compile), so ``state`` stays as it is."""
    if soa and attitude in _fast.QUATERNION_FORMS:
        return state
    return NavState(so3.quat_normalize(state.q), state.p, state.v, state.b_g, state.b_a)


def kernel_ready(inputs, soa: bool):
    """``inputs`` (an engine's inputs after the dispatch: a ``NamedTuple`` with ``state``,
    ``gyro``, ``accel``, ``dt``, ``attitude``, ``pose``, ``tangential``) as the chosen kernel
    reads them: the start normalised (:func:`unit_start`) and a sensor's samples moved into
    the body frame, except where a structure-of-arrays kernel (``soa``) does either itself
    (:func:`sensor_engine_inputs`)."""
    state = unit_start(inputs.state, soa, inputs.attitude)
    state, gyro, accel = sensor_engine_inputs(
        soa, inputs.pose, state, inputs.gyro, inputs.accel, inputs.dt, inputs.tangential
    )
    return inputs._replace(state=state, gyro=gyro, accel=accel)


def broadcast_state(state: NavState, batch) -> NavState:
    return jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, tuple(batch) + x.shape[-1:]), state)


def flatten_batch(batch, state, gyro, accel, dt, g):
    """Broadcast to ``batch`` and flatten it to one leading axis ``B`` (the fast-path layout).

    ``dt`` stays ``(T,)`` when shared by all batch elements, ``g`` ``(3,)`` likewise.
    """
    T = gyro.shape[-2]
    B = int(np.prod(batch, dtype=np.int64))
    flat = lambda x, tail: jnp.broadcast_to(x, tuple(batch) + tail).reshape((B,) + tail)  # noqa: E731
    steps = dt.shape[-1] if dt.ndim else T  # gyro may hold one sample more
    fields = [
        flat(getattr(state, n), (k,))
        for n, k in (("q", 4), ("p", 3), ("v", 3), ("b_g", 3), ("b_a", 3))
    ]
    dt = jnp.broadcast_to(dt, (steps,)) if dt.ndim <= 1 else flat(dt, (steps,))
    g = g if g.ndim == 1 else flat(g, (3,))
    k = gyro.shape[-1]
    return fields, flat(gyro, (T, k)), flat(accel, (T, k)), dt, g


def extended_samples(gyro, accel, dt):
    """``(..., n + 1, 3)`` samples for the steps of a scheme that uses sample k+1: with
    ``n = T`` steps the last sample is held (repeated once, as :func:`time_major`); with
    ``n = T - 1`` the samples are already the ends of the intervals."""
    n, T = n_steps(gyro, dt), gyro.shape[-2]
    if n < T:
        return gyro, accel
    return tuple(jnp.concatenate([x, x[..., -1:, :]], -2) for x in (gyro, accel))


def kernel_samples(scheme, gyro, accel, dt):
    """What a structure-of-arrays kernel reads: ``dt`` with one entry per step (a scalar
    broadcast), and the samples of the steps — the first ``n`` (Euler), or ``n + 1`` for a
    scheme that uses sample k+1 (:func:`extended_samples`)."""
    n = n_steps(gyro, dt)
    dt = jnp.broadcast_to(dt, (n,)) if dt.ndim == 0 else dt
    if get_scheme(scheme).uses_next_sample:
        return (*extended_samples(gyro, accel, dt), dt)
    return gyro[..., :n, :], accel[..., :n, :], dt


def sensor_engine_inputs(soa, pose, state, gyro, accel, dt, tangential):
    """An engine's inputs for a sensor at ``pose`` (``None``: unchanged), ``state``'s biases
    the sensor's: the state with the body's biases, and the samples moved into the body frame
    (:func:`jaximu.sensor.to_body`) unless the kernel is a structure-of-arrays one (``soa``),
    which moves them in its time chunks. Returns ``(state, gyro, accel)``."""
    if pose is None:
        return state, gyro, accel
    if not soa:
        gyro, accel = sensor.to_body(pose, gyro, accel, dt, state.b_g, tangential=tangential)
    state = NavState(
        state.q,
        state.p,
        state.v,
        sensor.bias_to_body(pose, state.b_g),
        sensor.bias_to_body(pose, state.b_a),
    )
    return state, gyro, accel


def soa_samples(scheme, gyro, accel, dt, pose, batch):
    """:func:`kernel_samples` for a structure-of-arrays kernel that may move a sensor's
    samples (``pose``, see :func:`sensor_engine_inputs`) in its time chunks. Returns
    ``(gyro, accel, dt, pose, n_samples)``: the pose as ``(q_BS, p_BS)`` flattened to the
    lanes (``(4,)``, ``(3,)`` when shared), ``n_samples`` the samples given."""
    n_samples = gyro.shape[-2]
    g_k, a_k, dt = kernel_samples(scheme, gyro, accel, dt)
    if pose is None:
        return g_k, a_k, dt, None, n_samples
    if get_scheme(scheme).uses_next_sample:
        gyro, accel = g_k, a_k
    # (Euler over the intervals between samples keeps the last sample: the derivative at the
    # last step's sample reads it)
    return gyro, accel, dt, tuple(lane_values(x, batch) for x in (pose.q, pose.p)), n_samples


def lane_values(x, batch):
    """A ``(..., n)`` value shared by every lane (``(n,)``, kept) or one per lane (flattened
    to ``(B, n)``)."""
    if x.ndim == 1:
        return x
    return jnp.broadcast_to(x, tuple(batch) + x.shape[-1:]).reshape((-1, x.shape[-1]))
