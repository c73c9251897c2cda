"""Smooth trajectories, exact IMU signals by autodiff, and IMU noise and bias processes.

A :class:`Trajectory` is a pure function ``pose(t) -> (q, p)`` of a scalar time ``t`` [s]:
``q`` the Hamilton quaternion ``[w, x, y, z]`` of ``R_WB``, ``p`` the position in W. The ideal
IMU signals come from **autodiff of** ``pose(t)``, not finite differences, so they are exact to
float precision:

    ω_B = 2 vec(q* ⊗ q̇)          (jax.jacfwd of q),
    f_B = R_WBᵀ (p̈ - g_W)        (jax.jacfwd twice of p).

Noise (:func:`add_noise`) follows :mod:`jaximu.noise`: per-sample white noise with std
``σ/√dt``; a bias random walk whose steps have std ``σ_rw·√dt``; a constant turn-on bias;
optionally a scale factor and misalignment ``M = I + S`` applied to the true signal. Every
draw is a function of a PRNG key, so batches are ``jax.vmap`` over keys (or leading key axes).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.geometry import _checks as val
from jaximu.geometry import _tolerances, so3
from jaximu.geometry.noise import ImuNoise, check_noise
from jaximu.geometry.sensor import check_pose, lever_arm_acceleration
from jaximu.geometry.state import NavState
from jaximu.schemes.world import check_omega

__all__ = [
    "Trajectory",
    "circle",
    "figure_eight",
    "lissajous",
    "helix",
    "waypoints",
    "ideal_imu",
    "true_states",
    "ImuErrors",
    "add_noise",
]


@dataclasses.dataclass(frozen=True)
class Trajectory:
    """A smooth motion: ``pose(t) -> (q (4,), p (3,))`` for a scalar ``t`` [s].

    Attributes:
        pose: the pose function (jax-traceable, twice differentiable in ``t``).
        name: a label for plots and reports.
    """

    pose: Callable
    name: str = "trajectory"

    def __call__(self, t):
        return self.pose(t)


def _finite(name, x, positive=False, shape=None):
    """A trajectory parameter: numbers (not text, complex or bool), finite (and > 0 with
    ``positive``; of ``shape`` if given)."""
    if isinstance(x, jax.core.Tracer):
        return x
    val.check_real(name, x)
    if val.kind_of(x) in "bUSOV":  # text is never parsed for you; True is not 1
        what = "a number" if shape is None else f"numbers of shape {shape}"
        raise ValueError(f"{name} must be {what}, got {type(x).__name__} {x!r}")
    arr = np.asarray(x, float)
    if shape is not None and arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)) or (positive and not np.all(arr > 0)):
        raise ValueError(f"{name} must be {'positive and ' if positive else ''}finite, got {x!r}")
    return x


def _check_traj(traj, t):
    if not isinstance(traj, Trajectory):
        raise ValueError(
            f"traj must be a jaximu.simulate.Trajectory (e.g. circle()), got {type(traj).__name__}"
        )
    t = val.to_dtype("t", t, None)  # text, complex, None, ragged lists: an error naming t
    if t.ndim != 1:
        raise ValueError(f"t must be a 1-D array of times (T,), got shape {tuple(t.shape)}")
    if t.dtype == jnp.bool_:
        raise ValueError("t must be times in seconds, got a bool array")
    if not jnp.issubdtype(t.dtype, jnp.floating) or jnp.dtype(t.dtype).itemsize < 4:
        t = t.astype(val.float_dtype(t))  # integers and half precision: float32 (README)
    val.check_finite("t", t)
    return t


def _yaw_pitch_roll_quat(yaw, pitch, roll):
    return so3.euler_zyx_to_quat(jnp.stack([roll, pitch, yaw]))


def circle(radius: float = 5.0, speed: float = 2.0, height: float = 1.0) -> Trajectory:
    """Level circle, counter-clockwise, body x along the velocity (GTSAM's "Circle").

    Yaw rate ``ω = speed / radius``; the IMU reads ``gyro = (0, 0, ω)`` and
    ``accel = (0, speed·ω, g)`` (centripetal force plus gravity reaction), constant.
    ``radius > 0`` [m], ``speed`` and ``height`` finite [m/s], [m].
    """
    _finite("radius", radius, True), _finite("speed", speed), _finite("height", height)
    w = speed / radius

    def pose(t):
        wt = w * t
        p = jnp.stack([radius * jnp.sin(wt), radius * (1 - jnp.cos(wt)), height + 0 * wt])
        return _yaw_pitch_roll_quat(wt, 0 * wt, 0 * wt), p

    return Trajectory(pose, f"circle(r={radius}, v={speed})")


def figure_eight(
    a: float = 6.0, b: float = 3.0, period: float = 20.0, height: float = 1.5, bank: float = 0.25
) -> Trajectory:
    """Horizontal figure eight ``(a sin wt, b sin 2wt)`` with heading along the velocity and a
    banking roll ``bank·sin(2wt)`` [rad]. ``a``, ``b``, ``height``, ``bank`` finite [m, rad];
    ``period > 0`` [s]."""
    for name, x in (("a", a), ("b", b), ("height", height), ("bank", bank)):
        _finite(name, x)
    _finite("period", period, True)
    w = 2 * np.pi / period

    def pose(t):
        wt = w * t
        p = jnp.stack([a * jnp.sin(wt), b * jnp.sin(2 * wt), height + 0.3 * jnp.sin(wt)])
        yaw = jnp.arctan2(2 * b * jnp.cos(2 * wt), a * jnp.cos(wt))
        return _yaw_pitch_roll_quat(yaw, 0.1 * jnp.sin(wt), bank * jnp.sin(2 * wt)), p

    return Trajectory(pose, f"figure_eight(a={a}, b={b}, T={period})")


def lissajous(
    amplitude=(3.0, 2.0, 0.5),
    frequency=(0.1, 0.15, 0.23),
    attitude_amplitude=(0.3, 0.2, 0.8),
    attitude_frequency=(0.21, 0.17, 0.07),
) -> Trajectory:
    """3-D Lissajous curve with independently oscillating roll, pitch and yaw [rad, Hz].
    Each argument: three finite numbers (amplitudes [m, rad], frequencies [Hz])."""
    for name, x in (
        ("amplitude", amplitude),
        ("frequency", frequency),
        ("attitude_amplitude", attitude_amplitude),
        ("attitude_frequency", attitude_frequency),
    ):
        _finite(name, x, shape=(3,))
    A, f = np.asarray(amplitude, float), np.asarray(frequency, float)
    B, g = np.asarray(attitude_amplitude, float), np.asarray(attitude_frequency, float)

    def pose(t):
        p = jnp.asarray(A) * jnp.sin(2 * np.pi * jnp.asarray(f) * t + jnp.array([0.0, 0.5, 1.0]))
        chi = jnp.asarray(B) * jnp.sin(2 * np.pi * jnp.asarray(g) * t + jnp.array([0.3, 0.0, 0.7]))
        return so3.euler_zyx_to_quat(chi), p

    return Trajectory(pose, "lissajous")


def helix(
    radius: float = 3.0, turn_rate: float = 0.4, climb_rate: float = 0.2, wobble: float = 0.2
) -> Trajectory:
    """Climbing helix, heading along the track, with roll and pitch wobbling by ``wobble`` rad.
    ``radius > 0`` [m]; ``turn_rate`` [rad/s], ``climb_rate`` [m/s], ``wobble`` finite."""
    _finite("radius", radius, True)
    for name, x in (("turn_rate", turn_rate), ("climb_rate", climb_rate), ("wobble", wobble)):
        _finite(name, x)

    def pose(t):
        wt = turn_rate * t
        p = jnp.stack([radius * jnp.sin(wt), radius * (1 - jnp.cos(wt)), climb_rate * t])
        return _yaw_pitch_roll_quat(wt, wobble * jnp.sin(1.3 * wt), wobble * jnp.cos(0.9 * wt)), p

    return Trajectory(pose, f"helix(r={radius})")


def _natural_cubic_spline(times, values):
    """Coefficients of the C2 natural cubic spline through ``values`` ``(K, d)`` at ``times``."""
    t = np.asarray(times, float)
    y = np.asarray(values, float)
    K = len(t)
    h = np.diff(t)
    A = np.zeros((K, K))
    rhs = np.zeros_like(y)
    A[0, 0] = A[-1, -1] = 1.0
    for i in range(1, K - 1):
        A[i, i - 1], A[i, i], A[i, i + 1] = h[i - 1], 2 * (h[i - 1] + h[i]), h[i]
        rhs[i] = 3 * ((y[i + 1] - y[i]) / h[i] - (y[i] - y[i - 1]) / h[i - 1])
    c = np.linalg.solve(A, rhs)  # second-derivative / 2 at the knots
    b = (y[1:] - y[:-1]) / h[:, None] - h[:, None] * (2 * c[:-1] + c[1:]) / 3
    d = (c[1:] - c[:-1]) / (3 * h[:, None])
    return t, y[:-1], b, c[:-1], d


def _eval_spline(coeffs, t):
    knots, a, b, c, d = (jnp.asarray(x) for x in coeffs)
    i = jnp.clip(jnp.searchsorted(knots, t, side="right") - 1, 0, a.shape[0] - 1)
    s = t - knots[i]
    return a[i] + s * (b[i] + s * (c[i] + s * d[i]))


def _numbers(name, x) -> np.ndarray:
    """A waypoint array as float64 numbers: text, ``None``, ragged lists, complex values
    (whose imaginary part numpy drops with a warning) and booleans are refused, naming it."""
    if not isinstance(x, jax.core.Tracer) and val.kind_of(x) == "b":
        raise ValueError(f"{name} must be numbers, got booleans; pass floats")
    return val.as_numbers(name, x)


def waypoints(times, positions, quaternions=None) -> Trajectory:
    """A C2 trajectory through waypoints: natural cubic splines through the positions and
    through the rotation vectors of the orientations (unwrapped so that consecutive ones
    differ by less than π); ``R(t) = Exp(r(t))``.

    Args:
        times: ``(K,)`` increasing waypoint times [s], K ≥ 2.
        positions: ``(K, 3)`` positions in W [m].
        quaternions: ``(K, 4)`` orientations ``[w, x, y, z]`` (default: identity).

    The curve passes exactly through every waypoint; outside ``[t_0, t_K-1]`` the end
    polynomials extend it.
    """
    times, positions = _numbers("times", times), _numbers("positions", positions)
    val.check_finite("times", times)
    val.check_finite("positions", positions)
    if times.ndim != 1 or len(times) < 2 or np.any(np.diff(times) <= 0):
        raise ValueError("times must be a strictly increasing 1-D array of at least 2 waypoints")
    if positions.shape != (len(times), 3):
        raise ValueError(f"positions must have shape ({len(times)}, 3), got {positions.shape}")
    if quaternions is None:
        rotvecs = np.zeros_like(positions)
    else:
        quaternions = _numbers("quaternions", quaternions)
        if quaternions.shape != (len(times), 4):
            raise ValueError(
                f"quaternions must have shape ({len(times)}, 4), got {quaternions.shape}"
            )
        val.check_finite("quaternions", quaternions)
        _tolerances.check_unit_norm(
            "quaternions",
            quaternions,
            np.float64,
            where=lambda i: f" at row {i[0]}",
            fix="normalise them first",
        )
        rotvecs = np.array(so3.log(jnp.asarray(quaternions)), float)  # a writable copy
        for k in range(1, len(rotvecs)):  # unwrap: pick r or r - 2π r̂ closest to the previous
            r = rotvecs[k]
            n = np.linalg.norm(r)
            if n > 1e-12:
                alt = r - 2 * np.pi * r / n
                if np.linalg.norm(alt - rotvecs[k - 1]) < np.linalg.norm(r - rotvecs[k - 1]):
                    rotvecs[k] = alt
    pos = _natural_cubic_spline(times, positions)
    rot = _natural_cubic_spline(times, rotvecs)

    def pose(t):
        return so3.exp(_eval_spline(rot, t)), _eval_spline(pos, t)

    return Trajectory(pose, f"waypoints({len(times)})")


def _kinematics(traj: Trajectory, t):
    """q, p, v, body rate ω_B and world acceleration at one scalar time, by forward AD."""
    q, p = traj.pose(t)
    q_dot, v = jax.jacfwd(traj.pose)(t)
    a = jax.jacfwd(lambda s: jax.jacfwd(traj.pose)(s)[1])(t)
    omega = 2.0 * so3.quat_mul(so3.quat_conj(q), q_dot)[1:]
    return q, p, v, omega, a


@functools.partial(jax.jit, static_argnums=0)
def _kinematics_at(traj: Trajectory, t):
    return jax.vmap(lambda s: _kinematics(traj, s))(t)


def _check_poses(traj: Trajectory, t, q, *derived):
    """On eager calls: ``traj.pose`` gave unit quaternions (the body rate ``2 vec(q* ⊗ q̇)``
    assumes them: a non-unit ``q`` gives a wrong rate, silently) and finite values, and
    what was derived from them is finite; a ``ValueError`` naming ``traj.pose`` and the
    first time otherwise."""
    if not val.is_concrete(t, q, *derived):
        return
    tn = np.asarray(t)
    for x in (q,) + derived:
        bad = ~np.all(np.isfinite(np.asarray(x)), axis=-1)
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(
                f"traj.pose ({traj.name}) gave non-finite values at t[{i}] = "
                f"{tn[i]:g} (in its pose or their derivatives); it must be finite "
                "and twice differentiable at every t"
            )
    _tolerances.check_unit_norm(
        f"traj.pose ({traj.name})",
        q,
        q.dtype,
        what="gave a non-unit quaternion",
        where=lambda i: f" at t[{i[0]}] = {tn[i[0]]:g}",
        fix="return a unit q, e.g. normalised with jaximu.so3.quat_normalize inside pose",
    )


def _one(name, x, shape_of):
    """``x`` (a checked gravity vector, world rate or sensor pose) of one trajectory: no
    batch axes, which would land beside the time axis of the outputs."""
    if len(shape_of) > 1:
        raise ValueError(
            f"{name} must be one {x} for a trajectory's samples, got shape "
            f"{tuple(shape_of)}; jax.vmap over ideal_imu for several"
        )


def true_states(traj: Trajectory, t) -> NavState:
    """The exact states at times ``t`` ``(T,)`` (finite; zero biases): fields ``(T, ·)``."""
    t = _check_traj(traj, t)
    q, p, v, _, _ = _kinematics_at(traj, t)
    _check_poses(traj, t, q, p, v)
    z = jnp.zeros_like(p)
    return NavState(q, p, v, z, z)


def _sensor_kinematics(traj: Trajectory, t, q_bs, r):
    """Like :func:`_kinematics` for the point ``r`` (body frame) and the frame rotated by
    ``q_BS``: the sensor's position is ``p_S(t) = p(t) + R_WB(t) r``, differentiated by AD."""
    q, _, _, omega, _ = _kinematics(traj, t)

    def pos(s):
        q_s, p_s = traj.pose(s)
        return p_s + so3.quat_rotate(q_s, r)

    v = jax.jacfwd(pos)(t)
    a = jax.jacfwd(jax.jacfwd(pos))(t)
    return so3.quat_mul(q, q_bs), pos(t), v, so3.quat_rotate(so3.quat_conj(q_bs), omega), a


@functools.partial(jax.jit, static_argnums=0)
def _sensor_kinematics_at(traj: Trajectory, t, q_bs, r):
    return jax.vmap(lambda s: _sensor_kinematics(traj, s, q_bs, r))(t)


def ideal_imu(traj: Trajectory, t, gravity=9.81, *, body_P_sensor=None, omega_coriolis=None):
    """Exact body rate and specific force at times ``t`` ``(T,)`` (finite); ``gravity`` a
    magnitude ``≥ 0`` or a ``(3,)`` vector as :func:`jaximu.propagate`.

    Args:
        body_P_sensor: optional :class:`jaximu.SensorPose`: the signals of an IMU mounted at
            that pose on the body (rotated by ``R_BS``, at the lever arm ``p_BS``), exact:
            ``ω_S = R_BSᵀ ω_B`` and ``f_S = R_WSᵀ(p̈_S - g_W)`` with the sensor's position
            ``p_S = p + R_WB p_BS`` differentiated twice by autodiff (not the lever-arm formula
            of :mod:`jaximu.sensor`, which it tests).
        omega_coriolis: optional ``(3,)`` rotation rate ``ω_W`` [rad/s] of the world frame in
            which ``traj`` is given (e.g. :func:`jaximu.earth_rate`): the gyro then measures
            the rate relative to inertial space, ``ω + R_WSᵀ ω_W``, and the accelerometer the
            inertial acceleration, ``f = R_WSᵀ(p̈ + 2ω_W×ṗ + ω_W×(ω_W×p) - g_W)`` (Coriolis and
            centrifugal both; ``g_W`` the gravity given).

    Returns:
        ``(gyro, accel)``, each ``(T, 3)``: ``ω_B`` [rad/s] and ``f_B = R_WBᵀ(a_W - g_W)`` [m/s²]
        (of the sensor frame S with ``body_P_sensor``).
    """
    t = _check_traj(traj, t)
    g = val.gravity_vector(gravity, t.dtype)  # refuses a complex gravity (to_dtype)
    _one("gravity", "magnitude or (3,) vector", g.shape)
    if omega_coriolis is not None:
        w = check_omega(omega_coriolis, t.dtype)
        _one("omega_coriolis", "(3,) world rate", w.shape)
    if body_P_sensor is None:
        q, p, v, omega, a = _kinematics_at(traj, t)
    else:
        pose = check_pose(body_P_sensor, t.dtype)
        _one("body_P_sensor.q", "(4,) quaternion", pose.q.shape)
        _one("body_P_sensor.p", "(3,) lever arm", pose.p.shape)
        q, p, v, omega, a = _sensor_kinematics_at(traj, t, pose.q, pose.p)
    _check_poses(traj, t, q, p, v, omega, a)
    if omega_coriolis is not None:
        omega = omega + so3.quat_rotate(so3.quat_conj(q), jnp.broadcast_to(w, omega.shape))
        # Coriolis, and ω×(ω×p): a point fixed in the turning world (on components)
        a = a + 2 * jnp.cross(w, v) + lever_arm_acceleration(w, None, p)
    accel = so3.quat_rotate(so3.quat_conj(q), a - g)
    return omega, accel


class ImuErrors(NamedTuple):
    """What :func:`add_noise` drew, for checking a filter against the truth.

    Attributes:
        b_g, b_a: ``(..., T, 3)`` the true biases during each sample (turn-on + random walk).
        b_g_end, b_a_end: ``(..., 3)`` the true biases after the last sample.
    """

    b_g: jax.Array
    b_a: jax.Array
    b_g_end: jax.Array
    b_a_end: jax.Array


def add_noise(
    key,
    gyro,
    accel,
    dt,
    noise: ImuNoise,
    *,
    b_g0=0.0,
    b_a0=0.0,
    gyro_misalignment=None,
    accel_misalignment=None,
    batch_shape=(),
):
    """Measured samples from true ones: ``w_m = M_g ω + b_g + n_g``, ``a_m = M_a f + b_a + n_a``.

    Args:
        key: a ``jax.random`` key.
        gyro, accel: ``(T, 3)`` true body rate and specific force (e.g. :func:`ideal_imu`),
            finite.
        dt: ``(T,)`` or scalar sample periods [s] (sample k held over ``dt[k]``), ``> 0``.
        noise: the densities; white-noise std ``σ/√dt``, bias steps std ``σ_rw·√dt``.
        b_g0, b_a0: turn-on biases ``(..., 3)`` (or scalars), finite.
        gyro_misalignment, accel_misalignment: optional ``(3, 3)`` ``S`` with ``M = I + S``
            (scale factors on the diagonal, misalignment off it).
        batch_shape: draw this many independent streams at once (outputs ``batch + (T, 3)``);
            one draw of ``batch + (T, 12)`` normals, the fastest way on CPU.

    Returns:
        ``(gyro_m, accel_m, errors)`` with :class:`ImuErrors`. The bias during sample k is
        the turn-on bias plus the sum of the random-walk steps before k.
    """
    # (complex inputs are refused by to_dtype below, naming them)
    if val.kind_of(dt) == "b":
        raise ValueError("dt must be sample periods in seconds, got a bool (True would be 1 s)")
    key = val.check_key("key", key)
    dtype = val.float_dtype(gyro, accel, dt, b_g0, b_a0)  # the data's; a float64 dt counts
    gyro, accel = val.to_dtype("gyro", gyro, dtype), val.to_dtype("accel", accel, dtype)
    val.check_vector("gyro", gyro)
    val.check_vector("accel", accel)
    if gyro.shape[-2] != accel.shape[-2]:
        raise ValueError(
            f"gyro and accel have different numbers of samples: {gyro.shape[-2]} "
            f"and {accel.shape[-2]}"
        )
    T = gyro.shape[-2]
    if T == 0:
        raise ValueError("gyro and accel hold no samples (T = 0)")
    val.check_finite("gyro", gyro)
    val.check_finite("accel", accel)
    noise = check_noise(noise, dtype)
    batch_shape = val.check_batch_shape(batch_shape)
    mis = {}
    for name, M in (
        ("gyro_misalignment", gyro_misalignment),
        ("accel_misalignment", accel_misalignment),
    ):
        if M is None:
            continue
        M = val.to_dtype(name, M, dtype)
        if M.shape != (3, 3):
            raise ValueError(f"{name} must have shape (3, 3) or be None, got {tuple(M.shape)}")
        val.check_finite(name, M)
        mis[name] = M
    dt = val.to_dtype("dt", dt, dtype)
    if dt.ndim > 1 or (dt.ndim == 1 and dt.shape[0] != T):
        raise ValueError(
            f"dt must be a scalar or have shape (T,) = ({T},) (one period per "
            f"sample), got {tuple(dt.shape)}"
        )
    dt = jnp.broadcast_to(dt, (T,))
    # a density per sample broadcasts with dt's (T,)
    val.batch_shape((T,), names=("dt",), noise=noise)
    sg, sa, sbg, sba = noise.sample_std(dt, dtype)  # (T, 3) each; checks dt > 0
    bias0 = {}
    for name, b in (("b_g0", b_g0), ("b_a0", b_a0)):
        b = val.to_dtype(name, b, dtype)
        if b.ndim and b.shape[-1] != 3:
            raise ValueError(
                f"{name} must be a scalar or have shape (..., 3), got {tuple(b.shape)}"
            )
        val.check_finite(name, b)
        bias0[name] = b[..., None, :] if b.ndim else b
    b_g0, b_a0 = bias0["b_g0"], bias0["b_a0"]
    # the outputs are batch_shape + (T, 3): a batch of the inputs beyond it would share one
    # noise stream (the same noise in every element), so it is refused
    given = (
        ("gyro", gyro.shape[:-2]),
        ("accel", accel.shape[:-2]),
        ("b_g0", b_g0.shape[:-2]),
        ("b_a0", b_a0.shape[:-2]),
    )
    full = val.batch_shape(
        batch_shape, *(s for _, s in given), names=("batch_shape",) + tuple(n for n, _ in given)
    )
    if tuple(full) != batch_shape:
        name, shape = next(
            (n, s) for n, s in given if jnp.broadcast_shapes(batch_shape, s) != batch_shape
        )
        raise ValueError(
            f"{name} has batch axes {tuple(shape)} beyond batch_shape = "
            f"{batch_shape}: every element would get the same noise draw; pass "
            f"batch_shape={tuple(full)} (one independent stream each)"
        )
    z = jax.random.normal(key, batch_shape + (T, 12), dtype)
    walk_g = jnp.cumsum(z[..., 6:9] * sbg, axis=-2)
    walk_a = jnp.cumsum(z[..., 9:12] * sba, axis=-2)

    def before(walk):  # sum of the steps before each sample
        return jnp.concatenate([jnp.zeros_like(walk[..., :1, :]), walk[..., :-1, :]], axis=-2)

    b_g, b_a = b_g0 + before(walk_g), b_a0 + before(walk_a)
    Mg, Ma = mis.get("gyro_misalignment"), mis.get("accel_misalignment")
    w = gyro if Mg is None else gyro + gyro @ Mg.T
    f = accel if Ma is None else accel + accel @ Ma.T
    gyro_m = w + b_g + z[..., 0:3] * sg
    accel_m = f + b_a + z[..., 3:6] * sa
    errors = ImuErrors(
        b_g, b_a, (b_g0 + walk_g[..., -1:, :])[..., 0, :], (b_a0 + walk_a[..., -1:, :])[..., 0, :]
    )
    return gyro_m, accel_m, errors
