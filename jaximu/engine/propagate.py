"""Mean propagation over time: the ``lax.scan`` drivers.

Batch axes stay inside the scan step (every kernel broadcasts over leading axes), the
fastest layout (docs/DESIGN.md, section 3); a ``jax.vmap`` of these functions is routed to
the same batched kernels (section 4), and :mod:`jaximu.engine._dispatch` picks the kernel.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.engine import _chunked
from jaximu.engine import _dispatch as dispatch
from jaximu.engine._batching import ArgSpec, leading_axes
from jaximu.engine._inputs import (
    broadcast_state,
    flatten_batch,
    kernel_ready,
    kernel_samples,
    lane_values,
    n_steps,
    prepare,
    soa_samples,
    time_major,
)
from jaximu.geometry import _checks as val
from jaximu.geometry import sensor, so3
from jaximu.geometry.state import NavState
from jaximu.kernels import fast as _fast
from jaximu.kernels import lane_forms
from jaximu.schemes import world
from jaximu.schemes.integrators import GIMBAL_LOCK_COS, get_attitude, get_scheme, step

__all__ = ["propagate", "propagate_final"]


def _propagate_fast(
    scheme,
    state,
    gyro,
    accel,
    dt,
    g,
    batch,
    save_all,
    omega=None,
    coriolis="exact",
    attitude="quaternion",
    pose=None,
    tangential=True,
):
    """The ``soa_mean`` kernel (``pose``: :func:`sensor_engine_inputs`)."""
    gyro, accel, dt, pose, n_samples = soa_samples(scheme, gyro, accel, dt, pose, batch)
    (q, p, v, b_g, b_a), gyro_f, accel_f, dt_f, g_f = flatten_batch(
        batch, state, gyro, accel, dt, g
    )
    if omega is not None:  # a world rate shared, or per batch element
        omega = lane_values(omega, batch)
    form = lane_forms.lane_form(attitude)  # the attitude form's state on lanes, and back after
    out = _fast.propagate_mean(
        get_scheme(scheme),
        lane_forms.from_quat(form, q),
        p,
        v,
        b_g,
        b_a,
        gyro_f,
        accel_f,
        dt_f,
        g_f,
        save_all,
        omega,
        coriolis,
        form,
        pose,
        tangential,
        n_samples,
    )
    unflat = lambda x: x.reshape(tuple(batch) + x.shape[1:])  # noqa: E731
    q, p, v = (unflat(x) for x in (lane_forms.to_quat(form, out[0]),) + tuple(out[1:3]))
    # Euler angles: the lanes that reached the pitch singularity (by the last step)
    locked = (
        unflat(out[3][..., -1, 0] if save_all else out[3][..., 0])
        if len(out) > 3
        else jnp.zeros(batch, bool)
    )
    if save_all:
        bshape = q.shape[:-1] + (3,)
        states = NavState(
            q,
            p,
            v,
            jnp.broadcast_to(state.b_g[..., None, :], bshape),
            jnp.broadcast_to(state.b_a[..., None, :], bshape),
        )
    else:
        states = NavState(
            q,
            p,
            v,
            jnp.broadcast_to(state.b_g, tuple(batch) + (3,)),
            jnp.broadcast_to(state.b_a, tuple(batch) + (3,)),
        )
    return states, locked


def _propagate_chunked(scheme, state, gyro, accel, dt, g, batch, save_all=False):
    """The states of a few long sequences, cut into ``C`` time chunks that run side by side
    as lanes (:mod:`jaximu.engine._chunked`).

    Every scheme's update is linear in ``(R, v, p)`` once the rotations inside the step are
    known relative to its start, and its acceleration weights sum to ``h`` (in v) and
    ``h²/2`` (in p). So a chunk propagated from the identity with zero gravity gives its
    exact deltas ``(ΔR, Δv, Δp, Δt)`` in its start frame (its preintegration). They
    compose associatively (:func:`jaximu.integrators.compose_deltas`), so their product is
    reduced as a tree (``log2 C`` launches, not ``C``). ``save_all``: a parallel prefix
    scan of the deltas gives every chunk's start state, and the chunks run again from those
    starts, storing their states (twice the arithmetic, for ``C`` times fewer sequential
    steps). Equal to the plain scan to rounding. An accelerator's kernel (each sequential
    step there is a launch); the CPU runs long sequences on the one-block kernel
    (docs/DESIGN.md, "Dispatch").
    """
    sch = get_scheme(scheme)
    n = n_steps(gyro, dt)
    dtype = gyro.dtype
    B = int(np.prod(batch, dtype=np.int64))
    C = dispatch.mean_chunks(B, n)
    L = _chunked.chunk_length(n, C)
    gyro, accel, dt = kernel_samples(scheme, gyro, accel, dt)
    (q, p, v, b_g, b_a), gyro_f, accel_f, dt_f, g_f = flatten_batch(
        batch, state, gyro, accel, dt, g
    )
    gyro_c, accel_c, dt_c = _chunked.chunk_lanes(
        gyro_f, accel_f, jnp.broadcast_to(dt_f, (B, n)), C, L, int(sch.uses_next_sample)
    )

    def rep(x):
        return _chunked.repeat_lanes(x, C)

    z = jnp.zeros((B * C, 3), dtype)
    q_id = jnp.zeros((B * C, 4), dtype).at[:, 0].set(1)
    dq, dp, dv = _fast.propagate_mean(
        sch, q_id, z, z, rep(b_g), rep(b_a), gyro_c, accel_c, dt_c, jnp.zeros(3, dtype), False
    )
    deltas = tuple(
        _chunked.by_chunk(x, B, C) for x in (dq, dp, dv, jnp.sum(dt_c, axis=-1))
    )  # (C, B, ·)
    g_b = jnp.broadcast_to(g_f, (B, 3))

    def unflat(x):
        return x.reshape(tuple(batch) + x.shape[1:])

    if not save_all:
        qf, pf, vf = _chunked.apply_deltas(q, p, v, g_b, _chunked.total_deltas(deltas))
        states = NavState(
            unflat(qf),
            unflat(pf),
            unflat(vf),
            jnp.broadcast_to(state.b_g, tuple(batch) + (3,)),
            jnp.broadcast_to(state.b_a, tuple(batch) + (3,)),
        )
        return states, jnp.zeros(batch, bool)
    # every state: chunk c starts where chunks 0..c-1 end (an exclusive prefix of the deltas)
    starts = _chunked.apply_deltas(q, p, v, g_b, _chunked.deltas_before(deltas))
    q_s, p_s, v_s = (_chunked.by_lane(x) for x in starts)
    out = _fast.propagate_mean(
        sch, q_s, p_s, v_s, rep(b_g), rep(b_a), gyro_c, accel_c, dt_c, rep(g_b), True
    )
    q_t, p_t, v_t = (unflat(x.reshape((B, C * L) + x.shape[2:])[:, :n]) for x in out[:3])
    bshape = q_t.shape[:-1] + (3,)
    states = NavState(
        q_t,
        p_t,
        v_t,
        jnp.broadcast_to(state.b_g[..., None, :], bshape),
        jnp.broadcast_to(state.b_a[..., None, :], bshape),
    )
    return states, jnp.zeros(batch, bool)


CORIOLIS = ("exact", "first_order", "second_order")


def coriolis_mode(exact, second_order) -> str:
    """The rotating world's model (:mod:`jaximu.world`): ``"exact"`` or GTSAM ≤ 4.2's
    classic ``"first_order"`` / ``"second_order"`` terms. Both options must be bools."""
    exact = val.check_bool("coriolis_exact", exact)
    second_order = val.check_bool("coriolis_second_order", second_order)
    return "exact" if exact else ("second_order" if second_order else "first_order")


def _rotate_left(att, x, dth):
    """``Exp(dθ) R`` in the attitude form's representation."""
    if att.name == "matrix":
        return so3.exp_matrix(dth) @ x
    return att.from_quat(so3.quat_normalize(so3.quat_mul(so3.exp(dth), att.to_quat(x))))


def rotating_step(scheme, att, x, p, v, omega0, f0, omega1, f1, h, g, omega, coriolis):
    """One step in the world turning at ``omega`` (:mod:`jaximu.world`): the exact transition
    (the scheme's still-world step in the inertial frame of the step's start), or the
    classic increments applied after the step at its end state."""
    if coriolis == "exact":
        v = world.to_inertial(omega, p, v)
        x, p, v = step(scheme, att, x, p, v, omega0, f0, omega1, f1, h, g)
        dth, p, v = world.leave_inertial(omega, h, g, p, v)
        return _rotate_left(att, x, dth), p, v
    x, p, v = step(scheme, att, x, p, v, omega0, f0, omega1, f1, h, g)
    dth, dp, dv = world.coriolis_increments(omega, p, v, h, coriolis == "second_order")
    return _rotate_left(att, x, dth), p + dp, v + dv


def mean_body(scheme, att, b_g, b_a, g, omega=None, coriolis="exact"):
    """The scan body of the mean: carry ``(x, p, v, locked)``, input one time slice;
    ``omega``: the world's rotation rate (``None``: a still world), ``coriolis`` its model."""

    def body(carry, xs):
        x, p, v, locked = carry
        w0, a0, w1, a1, h = xs
        if omega is None:
            x, p, v = step(scheme, att, x, p, v, w0 - b_g, a0 - b_a, w1 - b_g, a1 - b_a, h, g)
        else:
            x, p, v = rotating_step(
                scheme, att, x, p, v, w0 - b_g, a0 - b_a, w1 - b_g, a1 - b_a, h, g, omega, coriolis
            )
        if att.name == "euler_angles":
            # Report the pitch ±90° singularity: from the first step that reaches it the
            # state is NaN, never a silently wrong attitude.
            locked = locked | (jnp.cos(x[..., 1]) < GIMBAL_LOCK_COS)
            nan = jnp.asarray(jnp.nan, x.dtype)
            x, p, v = (jnp.where(locked[..., None], nan, y) for y in (x, p, v))
        return (x, p, v, locked), None

    return body


@functools.partial(
    jax.jit, static_argnames=("scheme", "attitude", "save_all", "fast", "coriolis", "tangential")
)
def _propagate(
    state,
    gyro,
    accel,
    dt,
    g,
    omega=None,
    pose=None,
    *,
    scheme,
    attitude,
    save_all,
    fast=True,
    coriolis="exact",
    tangential=True,
):
    """The mean's engine. ``pose``: ``None``, or a checked :class:`jaximu.SensorPose`: the
    samples are the sensor's and ``state``'s biases are in its frame (:mod:`jaximu.sensor`);
    the structure-of-arrays kernel moves the samples into the body frame in its time chunks,
    the others read them moved (:func:`jaximu.sensor.to_body`). The returned states' biases
    are then the body's."""
    get_attitude(attitude)  # an unknown form is named here, before the table is read
    batch = jnp.broadcast_shapes(
        state.batch_shape,
        gyro.shape[:-2],
        accel.shape[:-2],
        dt.shape[:-1],
        g.shape[:-1],
        *(() if omega is None else (omega.shape[:-1],)),
        *(() if pose is None else (pose.q.shape[:-1], pose.p.shape[:-1])),
    )
    lanes = int(np.prod(batch, dtype=np.int64))
    run = dispatch.implementation(
        "mean",
        scheme,
        attitude=attitude,
        save_all=save_all,
        lanes=lanes,
        steps=n_steps(gyro, dt),
        dtype=gyro.dtype,
        fast=fast,
        rotating=omega is not None,
    )
    return run(
        MeanInputs(
            scheme,
            state,
            gyro,
            accel,
            dt,
            g,
            batch,
            save_all,
            omega,
            coriolis,
            attitude,
            pose,
            tangential,
        )
    )


class MeanInputs(NamedTuple):
    """The mean engine's inputs once checked and dispatched, in the order of
    :func:`_propagate_fast`'s parameters: the scheme, ``state``, the samples and ``dt``,
    gravity ``g``, the broadcast ``batch`` shape, the static options and the optional world
    rate and sensor pose (``None`` when not given)."""

    scheme: str
    state: NavState
    gyro: Any
    accel: Any
    dt: Any
    g: Any
    batch: tuple
    save_all: bool
    omega: Any
    coriolis: str
    attitude: str
    pose: Any
    tangential: bool


# The mean's implementations, one per kernel of the table's "mean" rows, each taking the
# engine's MeanInputs. Only the structure-of-arrays kernel moves a sensor's samples into the
# body frame itself (in its time chunks); the others read them moved (kernel_ready).


@dispatch.implements("mean", "soa_mean")
def _mean_soa(inputs: MeanInputs):
    return _propagate_fast(*kernel_ready(inputs, soa=True))


@dispatch.implements("mean", "soa_mean_chunked")
def _mean_chunked(inputs: MeanInputs):
    a = kernel_ready(inputs, soa=False)
    return _propagate_chunked(a.scheme, a.state, a.gyro, a.accel, a.dt, a.g, a.batch, a.save_all)


@dispatch.implements("mean", dispatch.GENERIC)
def _mean_generic(inputs: MeanInputs):
    """The mean by ``lax.scan`` on ``(..., 3)`` arrays: the reference kernel."""
    a = kernel_ready(inputs, soa=False)
    scheme, batch, save_all, gyro, dt = a.scheme, a.batch, a.save_all, a.gyro, a.dt
    att = get_attitude(a.attitude)
    state = broadcast_state(a.state, batch)
    xs = time_major(gyro, a.accel, dt, scheme)
    body = mean_body(scheme, att, state.b_g, state.b_a, a.g, a.omega, a.coriolis)

    def scan_body(carry, xs):
        carry, _ = body(carry, xs)
        x, p, v, _ = carry
        return carry, ((att.to_quat(x), p, v) if save_all else None)

    locked0 = jnp.zeros(batch, bool)
    carry0 = (att.from_quat(state.q), state.p, state.v, locked0)
    (x, p, v, locked), out = jax.lax.scan(scan_body, carry0, xs)
    T = n_steps(gyro, dt)
    if save_all:
        q_t, p_t, v_t = (jnp.moveaxis(y, 0, -2) for y in out)
        bshape = tuple(batch) + (T, 3)
        states = NavState(
            q_t,
            p_t,
            v_t,
            jnp.broadcast_to(state.b_g[..., None, :], bshape),
            jnp.broadcast_to(state.b_a[..., None, :], bshape),
        )
    else:
        states = NavState(att.to_quat(x), p, v, state.b_g, state.b_a)
    return states, locked


def _n_steps_arg(args, batched):
    """Steps a scalar ``dt`` stands for: T, the time length of ``gyro`` (argument 1)."""
    return args[1].shape[-2]


STATE = ArgSpec(1)


SAMPLES = ArgSpec(2)


STEPS = ArgSpec(1, _n_steps_arg)


VECTOR = ArgSpec(1)


def routed_propagate(scheme, attitude, save_all, coriolis="exact", tangential=True):
    """:func:`_propagate` whose ``jax.vmap`` lands on the batched kernels (:mod:`jaximu.engine._batching`).

    Its arguments: ``(state, gyro, accel, dt, g, omega, pose)``, ``omega`` ``None`` or
    ``(..., 3)``, ``pose`` ``None`` or a :class:`jaximu.SensorPose`."""
    return leading_axes(
        _propagate,
        (STATE, SAMPLES, SAMPLES, STEPS, VECTOR, VECTOR, VECTOR),
        (
            ("attitude", attitude),
            ("save_all", save_all),
            ("scheme", scheme),
            ("coriolis", coriolis),
            ("tangential", tangential),
        ),
    )


def _report_gimbal_lock(locked, attitude):
    if attitude == "euler_angles" and val.is_concrete(locked) and bool(np.any(np.asarray(locked))):
        raise ValueError(
            "the Euler-angle attitude form reached the pitch ±90° singularity (gimbal lock) "
            f"in batch element {val._first_bad(np.asarray(locked)) if np.ndim(locked) else '[]'}; "
            "the states from that step on are NaN. Use attitude='quaternion' or 'matrix'."
        )


def _finite_output(fn_name, out):
    """Eager calls: an overflow of the dtype is a ``ValueError``, never a NaN/inf result."""
    return val.check_output(fn_name, out, "dt or the IMU samples are too large")


SENSOR_ARGS_DOC = """
        body_P_sensor: optional :class:`jaximu.SensorPose` ``(q_BS, p_BS)``: the IMU's pose in
            the body frame. The samples are then the sensor's (frame S, at the lever arm
            ``p_BS``), ``state`` is the body's, and the biases are the sensor's, in S
            (:mod:`jaximu.sensor`). ``None``: the IMU is the body.
        tangential: with ``body_P_sensor``, correct the lever arm's tangential acceleration
            ``α×r`` too (``α`` from central differences of the gyro samples); ``False``
            keeps only the centripetal ``ω×(ω×r)``, as GTSAM does.
        omega_coriolis: optional ``(3,)`` rotation rate of the world frame [rad/s] in W
            (GTSAM's ``omegaCoriolis``; :func:`jaximu.earth_rate` gives Earth's): the samples
            are then relative to inertial space and the states relative to the turning W.
        coriolis_exact: ``True`` (default): the exact rotating-world transition of each step
            (Coriolis and centrifugal, GTSAM ≥ 4.3; the scheme keeps its order);
            ``False``: GTSAM ≤ 4.2's classic additive terms after each step (first order
            in dt), the centrifugal one only with ``coriolis_second_order``
            (:mod:`jaximu.world`).
        coriolis_second_order: with ``coriolis_exact=False``, add the centrifugal term
            (inert with the exact transition, which holds it, as in GTSAM ≥ 4.3).
"""


def _sensor_options(state, gyro, accel, body_P_sensor, tangential, omega_coriolis):
    """The checked ``tangential``, ``ω_W`` (``omega_coriolis``) and ``body_P_sensor``
    (``None`` each when not given)."""
    dtype = state.q.dtype
    tangential = val.check_bool("tangential", tangential)
    batch = val.batch_shape(state.batch_shape, gyro.shape[:-2], accel.shape[:-2])
    omega = None if omega_coriolis is None else world.check_omega(omega_coriolis, dtype)
    if omega is not None:
        val.batch_shape(batch, omega.shape[:-1], names=("state and samples", "omega_coriolis"))
    pose = None
    if body_P_sensor is not None:
        pose = sensor.check_pose(body_P_sensor, dtype, batch=batch, batch_name="state and samples")
    return tangential, omega, pose


def sensor_biases(states, state, per_step):
    """``states`` with the (constant) biases of ``state`` (the sensor-frame ones) again."""

    def put(b, like):
        return jnp.broadcast_to(b[..., None, :] if per_step else b, like.shape)

    return NavState(
        states.q, states.p, states.v, put(state.b_g, states.b_g), put(state.b_a, states.b_a)
    )


def _entry(
    fn_name,
    save_all,
    state,
    gyro,
    accel,
    dt,
    scheme,
    attitude,
    gravity,
    body_P_sensor,
    tangential,
    omega_coriolis,
    coriolis,
):
    state, gyro, accel, dt, g, _ = prepare(state, gyro, accel, dt, gravity, scheme, attitude)
    tangential, omega, pose = _sensor_options(
        state, gyro, accel, body_P_sensor, tangential, omega_coriolis
    )
    # the samples move into the body frame inside the engine (in the kernel's time chunks)
    out, locked = routed_propagate(scheme, attitude, save_all, coriolis, tangential)(
        state, gyro, accel, dt, g, omega, pose
    )
    if body_P_sensor is not None:
        out = sensor_biases(out, state, save_all)
    _report_gimbal_lock(locked, attitude)
    return _finite_output(fn_name, out)


def propagate(
    state: NavState,
    gyro,
    accel,
    dt,
    scheme: str = "euler",
    *,
    attitude: str = "quaternion",
    gravity=9.81,
    body_P_sensor=None,
    tangential: bool = True,
    omega_coriolis=None,
    coriolis_exact: bool = True,
    coriolis_second_order: bool = False,
) -> NavState:
    """Propagate the navigation state through IMU samples, returning every state.

        Args:
            state: initial :class:`NavState` at ``t_0`` (fields ``(..., 4)`` / ``(..., 3)``);
                ``q`` must be a unit quaternion (checked on eager calls, an error beyond the
                tolerance, never silently normalised); the step starts from ``q / |q|``.
            gyro: ``(..., T, 3)`` raw body rate ``w_m`` [rad/s]; sample k is held over ``dt[k]``.
            accel: ``(..., T, 3)`` raw specific force ``a_m`` [m/s²] (level and still: ``[0, 0, +g]``).
            dt: ``(..., T)`` or scalar step lengths [s], each ``> 0``; may vary per sample. Or
                ``(..., T-1)``: the samples are then the ends of the intervals, and step k uses
                samples k and k+1 (Euler: sample k) over ``dt[k]``.
            scheme: ``"euler"`` (zero-order hold on sample k), ``"midpoint"`` (VINS-Mono: samples
                k and k+1 averaged) or ``"rk4"`` (samples interpolated linearly); see
                :mod:`jaximu.integrators`. At the last step midpoint and RK4 have no sample
                k+1 and hold sample T-1 (a zero-order hold, like Euler's).
            attitude: orientation update form: ``"quaternion"`` (exact exponential),
                ``"quaternion_first_order"``, ``"matrix"`` or ``"euler_angles"`` (its pitch
                ±90° singularity is reported: states become NaN from that step, and an eager
                call raises ``ValueError``).
            gravity: magnitude ``g`` (``g_W = [0, 0, -g]``, default 9.81) or a ``(..., 3)`` vector.
    {sensor}
        Returns:
            :class:`NavState` whose fields have shape ``batch + (n, ·)`` with ``n`` the number of
            steps (``dt``'s length): entry k is the state at ``t_k + dt_k``, after step k (time
            first for an unbatched call). Biases
            are held constant (the mean of their random walk).

        Raises:
            ValueError: on mismatched shapes, a wrong last-axis size, ``dt ≤ 0`` or non-finite,
                non-finite samples, an unknown scheme or attitude form, or a non-unit ``q`` (of
                the state or of ``body_P_sensor``); on
                a value the computation dtype cannot hold (``dt = 1e300`` in float32) and on a
                non-finite result (finite inputs too large for the dtype: the state overflows).
                Value checks run only on concrete inputs (not inside a caller's ``jit``/``vmap``).
    """
    return _entry(
        "propagate",
        True,
        state,
        gyro,
        accel,
        dt,
        scheme,
        attitude,
        gravity,
        body_P_sensor,
        tangential,
        omega_coriolis,
        coriolis_mode(coriolis_exact, coriolis_second_order),
    )


def propagate_final(
    state: NavState,
    gyro,
    accel,
    dt,
    scheme: str = "euler",
    *,
    attitude: str = "quaternion",
    gravity=9.81,
    body_P_sensor=None,
    tangential: bool = True,
    omega_coriolis=None,
    coriolis_exact: bool = True,
    coriolis_second_order: bool = False,
) -> NavState:
    """Like :func:`propagate` but returns only the final state, without storing the trajectory.

    Returns:
        :class:`NavState` with fields of shape ``batch + (·)`` at ``t_0 + Σ dt``.
    """
    return _entry(
        "propagate_final",
        False,
        state,
        gyro,
        accel,
        dt,
        scheme,
        attitude,
        gravity,
        body_P_sensor,
        tangential,
        omega_coriolis,
        coriolis_mode(coriolis_exact, coriolis_second_order),
    )


propagate.__doc__ = (propagate.__doc__ or "").replace("{sensor}", SENSOR_ARGS_DOC)
