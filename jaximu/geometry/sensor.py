"""Where the IMU sits on the body: the sensor pose ``body_P_sensor`` (GTSAM's name).

The state tracks a body frame B (its origin the point whose position and velocity are
estimated); the IMU's own frame S is rotated by ``R_BS`` and its origin sits at the lever
arm ``r = p_BS`` (in B). A :class:`SensorPose` ``(q, p)`` holds ``q_BS`` (Hamilton
``[w, x, y, z]``) and ``p_BS`` [m].

**Measurements into the body frame** (:func:`to_body`), a pure transformation of the
samples, so every scheme and kernel runs unchanged on the body's samples (the mean's and
the covariance's structure-of-arrays kernels apply it inside their time chunks,
:func:`chunk_to_body`: a pass over the whole input costs as much as the mean's kernel):

    ω_B = R_BS ω_S,      f_B = R_BS f_S - α_B × r - ω_B × (ω_B × r),

with ``ω_B = R_BS (w_m - b_g)`` (bias-corrected) and ``α_B = ω̇_B``. The biases are the
sensor's own, **in frame S** (GTSAM's convention: ``bias_hat``, ``NavState.b_g``/``b_a``
and the bias rows/columns of the covariances refer to S); the engine runs on
``b_B = R_BS b_S``.

**Angular acceleration.** ``α`` at sample k is the derivative of the rate at ``t_k``:
central differences of consecutive gyro samples on the (possibly uneven) sample grid,
``α_k = (h₋² ω_k+1 - h₊² ω_k-1 + (h₊² - h₋²) ω_k) / (h₋ h₊ (h₋ + h₊))`` (second order;
exact for a rate quadratic in time), one-sided at the first and last sample. Second order
is what the schemes need on sampled data (Euler 1, midpoint 2, RK4 2: linear interpolation
of the samples is itself second order), so the correction never limits their order. GTSAM
omits the tangential term ``α×r``; ``tangential=False`` does the same (to compare).

**Covariance.** Isotropic densities are unchanged by the rotation. Per-axis densities are
rotated as variances, ``σ²_B = diag(R_BS diag(σ²_S) R_BSᵀ)``: exact for axis permutations,
the cross-axis correlations of a general rotation are dropped. The lever arm couples the
gyro into the body's specific force: a rate error ``δω`` moves it by ``-K δω`` (a gyro bias
error ``δb_g``, which lowers the rate, by ``+K δb_g``) with
``K = ∂(ω×(ω×r))/∂ω = -[ω×r]x - [ω]x[r]x`` (:func:`centripetal_jacobian`; about
``2|ω||r|``). A gyro bias error therefore moves the velocity and position (``Φ``'s ``b_g``
column gains ``-Φ_ba K`` at every evaluation point of the scheme) and so does the gyro white
noise, which enters as the bias does (GTSAM's Manifold preintegration models the noise part
through ``D_correctedAcc_measuredOmega``; its bias Jacobians leave out the bias part, ours
keep it: they are the derivatives of the deltas). The noise carried by the tangential term
``α×r`` (on by default) is **not** modelled: ``α`` is a difference of neighbouring gyro
samples, so its white noise (``~ σ_g |r| / (h √h)`` per sample) does not accumulate in the
velocity (its sum over steps telescopes to the noise of the first and last rates), but it
is not small either: ``~ σ_g |r| / √h`` in total, 2e-4 m/s for EuRoC's gyro at 200 Hz and
``|r| = 0.1`` m, about 7× the modelled ``ω×(ω×r)`` coupling over a 1 s window at 1 rad/s
(both are small beside the accelerometer's own, ~2e-3 m/s over 1 s). :func:`jaximu.calibrate`
weighs its residuals with the exact sample-noise covariance, which includes it.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.geometry import _checks as val
from jaximu.geometry import _tolerances, so3
from jaximu.geometry._vec import V3, matvec, matvec_v3
from jaximu.geometry.noise import ImuNoise

__all__ = [
    "SensorPose",
    "check_pose",
    "to_body",
    "lever_arm_acceleration",
    "centripetal_jacobian",
    "angular_acceleration",
]

NAME = "body_P_sensor"


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class SensorPose:
    """The IMU's pose in the body frame (a registered pytree, differentiable).

    Attributes:
        q: ``(..., 4)`` ``q_BS``, Hamilton ``[w, x, y, z]``, unit norm (``R_BS`` maps sensor
            vectors into the body frame).
        p: ``(..., 3)`` ``p_BS`` [m]: the IMU's origin in the body frame (the lever arm).
    """

    q: jax.Array | np.ndarray
    p: jax.Array | np.ndarray

    @property
    def R(self):
        """``(..., 3, 3)`` ``R_BS``."""
        return so3.quat_to_matrix(self.q)

    @classmethod
    def identity(cls, dtype=None) -> SensorPose:
        """The IMU at the body's origin, unrotated (``dtype``: default JAX's float)."""
        dtype = jnp.result_type(float) if dtype is None else val.compute_dtype("dtype", dtype)
        return cls(jnp.array([1.0, 0, 0, 0], dtype), jnp.zeros(3, dtype))

    @classmethod
    def from_matrix(cls, T_BS) -> SensorPose:
        """From a ``(4, 4)`` homogeneous ``T_BS`` (Kalibr's ``T_BS``; a camera's
        ``T_cam_imu`` is ``T_CS``: pass it when the camera is the body). Its rotation must be
        orthonormal with determinant +1 (to 1e-6): it is checked, never re-orthonormalised."""
        T = _numbers(f"{NAME} (T_BS)", T_BS)
        if T.shape != (4, 4):
            raise ValueError(
                f"{NAME} must be a (4, 4) homogeneous transform T_BS, got shape {T.shape}"
            )
        if not np.all(np.isfinite(T)):
            raise ValueError(f"{NAME} contains non-finite values")
        if np.max(np.abs(T[3] - [0, 0, 0, 1])) > 1e-9:
            raise ValueError(f"{NAME}'s last row must be [0, 0, 0, 1], got {T[3].tolist()}")
        return cls.from_rotation(T[:3, :3], T[:3, 3])

    @classmethod
    def from_rotation(cls, R_BS, p_BS) -> SensorPose:
        """From a ``(3, 3)`` rotation matrix ``R_BS`` (orthonormal, det +1, to 1e-6) and the
        lever arm ``p_BS`` ``(3,)`` [m], finite."""
        R = _numbers(f"{NAME}: R_BS", R_BS)
        if R.shape != (3, 3):
            raise ValueError(f"{NAME}: R_BS must have shape (3, 3), got {R.shape}")
        err = np.max(np.abs(R.T @ R - np.eye(3)))  # as a unit quaternion's norm in float64
        if (
            not np.isfinite(err)
            or err > _tolerances.unit_tolerance(np.float64)
            or np.linalg.det(R) < 0
        ):
            raise ValueError(
                f"{NAME}: R_BS is not a rotation matrix (max |RᵀR - I| = {err:.3g}, det = "
                f"{np.linalg.det(R):.6g}); pass an orthonormal matrix with determinant +1 "
                "(re-orthonormalise it, e.g. with scipy's Rotation.from_matrix)"
            )
        p = _numbers(f"{NAME}: the lever arm p_BS", p_BS)
        if p.shape != (3,):
            raise ValueError(f"{NAME}: the lever arm p_BS must have shape (3,) [m], got {p.shape}")
        val.check_finite(f"{NAME}: the lever arm p_BS", p)
        q = np.asarray(so3.matrix_to_quat(jnp.asarray(R)))
        return cls(jnp.asarray(q), jnp.asarray(p))


def _numbers(name, x) -> np.ndarray:
    return val.as_numbers(name, x)


def check_pose(
    pose, dtype, name: str = NAME, batch=None, batch_name: str = "the samples"
) -> SensorPose:
    """Type, shapes, finiteness and unit ``q`` of a :class:`SensorPose` (``ValueError``
    naming ``body_P_sensor``); returns it as ``dtype`` arrays, never normalised. With
    ``batch``, the pose's batch shape must broadcast with it (``batch_name`` says whose)."""
    if not isinstance(pose, SensorPose):
        raise ValueError(
            f"{name} must be a jaximu.SensorPose(q, p) (q_BS [w, x, y, z], p_BS "
            f"[m]) or None, got {type(pose).__name__}"
        )
    q = val.to_dtype(f"{name}.q", pose.q, dtype)
    p = val.to_dtype(f"{name}.p", pose.p, dtype)
    if q.ndim < 1 or q.shape[-1] != 4:
        raise ValueError(
            f"{name}.q must be the quaternion q_BS of shape (..., 4) "
            f"[w, x, y, z], got shape {tuple(q.shape)}"
        )
    if p.ndim < 1 or p.shape[-1] != 3:
        raise ValueError(
            f"{name}.p must be the lever arm p_BS of shape (..., 3) [m], got shape {tuple(p.shape)}"
        )
    val.batch_shape(
        q.shape[:-1],
        p.shape[:-1],
        *(() if batch is None else (batch,)),
        names=(f"{name}.q", f"{name}.p") + (() if batch is None else (batch_name,)),
    )
    val.check_finite(f"{name}.q", q)
    val.check_finite(f"{name}.p", p)
    _tolerances.check_unit_norm(
        f"{name}.q",
        q,
        dtype,
        fix="normalise it first "
        "(jaximu.so3.quat_normalize), or build the pose with "
        "SensorPose.from_rotation(R_BS, p_BS)",
    )
    return SensorPose(q, p)


def angular_acceleration(omega, dt):
    """``α`` at every sample from the rates ``omega`` ``(..., T, 3)`` on the grid of ``dt``.

    ``dt``: scalar, ``(..., T)`` (sample k held over ``dt[k]``) or ``(..., T-1)`` (the
    intervals between samples); the spacing between samples k and k+1 is ``dt[k]`` either
    way. Central differences inside, one-sided at the ends (module docstring); zero for
    ``T = 1``. Returns ``(..., T, 3)`` [rad/s²].
    """
    return _angular_acceleration(V3.of(omega), dt).stack()


def _angular_acceleration(omega: V3, dt) -> V3:
    """:func:`angular_acceleration` on components ``(..., T)`` (one pass per component: on
    ``(..., T, 3)`` arrays XLA:CPU reads the components with strides, as scalar code)."""
    T = omega.x.shape[-1]
    if T < 2:
        return V3(*(jnp.zeros_like(c) for c in omega))
    dt = jnp.asarray(dt, omega.x.dtype)
    h = jnp.broadcast_to(dt, (T - 1,)) if dt.ndim == 0 else dt[..., : T - 1]

    def one(x):
        d = jnp.diff(x, axis=-1) / h  # (..., T-1) forward differences
        if T == 2:
            return jnp.concatenate([d, d], axis=-1)
        mid = _central(d[..., :-1], d[..., 1:], h[..., :-1], h[..., 1:])
        return jnp.concatenate([d[..., :1], mid, d[..., -1:]], axis=-1)

    return V3(*(one(c) for c in omega))


def _central(d_before, d_after, h_before, h_after):
    """The rate's derivative at a sample from the slopes of the intervals before and after it
    (lengths ``h_before``, ``h_after``): their weighted mean, exact for a quadratic rate."""
    return (h_after * d_before + h_before * d_after) / (h_before + h_after)


def chunk_to_body(R, b_g: V3, r: V3, n_samples: int, tangential: bool, halo: int):
    """:func:`to_body` inside a kernel's time chunks: the ``samples`` function of
    :func:`jaximu.kernels.soa._time_chunks` (its ``w``, ``a``, ``hw``, ``k``), on time-major
    components ``(n + halo + 1, Bc)`` with ``halo`` samples before the chunk and one after
    (the kernel's :data:`jaximu.kernels.soa.HALO`).

    ``R``: ``R_BS`` ``(Bc, 3, 3)`` or ``(3, 3)``; ``b_g``: the gyro bias in the body frame
    (``R_BS b_g``) and ``r`` the lever arm, components ``(Bc,)`` or scalars;
    ``n_samples``: the samples the user gave (a next-sample scheme's kernel holds the last
    one once more: it gets the derivative of the last). The derivative ``α`` is
    :func:`angular_acceleration`'s: central inside, one-sided at the first and last sample.
    """

    def samples(w, a, hw, k):
        n = k.shape[0]
        gyro_b = matvec_v3(R, V3(*w))  # (n + 3, Bc)
        own = lambda x: V3(*(c[halo : halo + n] for c in x))  # noqa: E731
        alpha = None
        if tangential and n_samples > 1:
            h = hw[:, None] if hw.ndim == 1 else hw
            d = V3(*((c[1:] - c[:-1]) / h for c in gyro_b))  # slopes, (n + 2, Bc)
            at = lambda j: V3(*(c[j : j + n] for c in d))  # noqa: E731 (interval k - halo + j)
            before, after, held = at(halo - 1), at(halo), at(halo - 2)
            mid = V3(
                *(
                    _central(b, f, h[halo - 1 : halo - 1 + n], h[halo : halo + n])
                    for b, f in zip(before, after)
                )
            )
            kk = k[:, None]
            pick = lambda c0, cb, ch, cm: jnp.where(  # noqa: E731
                kk == 0, c0, jnp.where(kk == n_samples - 1, cb, jnp.where(kk >= n_samples, ch, cm))
            )
            alpha = V3(*(pick(*c) for c in zip(after, before, held, mid)))
        gyro_b = own(gyro_b)
        return tuple(gyro_b), tuple(_body_specific_force(R, own(V3(*a)), gyro_b - b_g, alpha, r))

    return samples


def lever_arm_acceleration(omega, alpha, r):
    """``α × r + ω × (ω × r)``: the acceleration of a point at ``r`` on a rigid body relative
    to its origin (body frame, ``(..., 3)``); ``alpha=None`` drops the tangential term."""
    return _lever_arm_acceleration(
        V3.of(omega), None if alpha is None else V3.of(alpha), V3.of(r)
    ).stack()


def _lever_arm_acceleration(omega: V3, alpha, r: V3) -> V3:
    """:func:`lever_arm_acceleration` on components (``jnp.cross`` on ``(..., 3)`` arrays
    slices and stacks; nested, XLA:CPU recomputed its operands per component: 1024 × 1000
    samples took 0.2 s)."""
    a = omega.cross(omega.cross(r))
    return a if alpha is None else a + alpha.cross(r)


def moved_specific_force(accel, omega_hat, omega, r):
    """``accel + c(ω̂) - c(ω)`` with ``c(ω) = ω×(ω×r)``: a body specific force corrected at
    the rate ``omega_hat`` (``(..., 3)``), as it would be at the rate ``omega`` instead. The
    autodiff Jacobians perturb the rate (bias or noise) and read this; it equals ``accel`` at
    ``omega = omega_hat``."""
    return (
        accel + lever_arm_acceleration(omega_hat, None, r) - lever_arm_acceleration(omega, None, r)
    )


def centripetal_jacobian(omega, r, ops):
    """``K = ∂(ω×(ω×r))/∂ω = -[ω×r]x - [ω]x[r]x`` as a 3×3 block of the layout ``ops``
    (:class:`jaximu.schemes._blocks.Layout`), for the body rate ``omega`` and lever arm ``r``
    (:class:`jaximu.geometry._vec.V3`; ``r`` may be shared by every element).

    The body's specific force ``f_B = R_BS f_S - ω×(ω×r) - α×r`` depends on the rate, so a
    gyro bias or noise ``δω`` moves it by ``-K δω``: ``Φ``'s ``b_g`` column gains
    ``-Φ_ba K`` (the white noise enters as the bias does; module docstring)."""
    return -(ops.skew(omega.cross(r)) + ops.matmul(ops.skew(omega), ops.skew(r)))


def to_body(pose: SensorPose, gyro, accel, dt, b_g, *, tangential: bool = True):
    """The raw samples of the sensor as raw samples of the body (module docstring).

    Args:
        pose: checked :class:`SensorPose`.
        gyro, accel: ``(..., T, 3)`` raw sensor samples (frame S).
        dt: the steps as :func:`jaximu.propagate` takes them.
        b_g: ``(..., 3)`` gyro bias in S (the centripetal term uses the corrected rate).
        tangential: include ``α × r``.

    Returns:
        ``(gyro_B, accel_B)``: ``(..., T, 3)`` raw body-frame samples whose bias is
        ``R_BS b`` (:func:`bias_to_body`), i.e. ``gyro_B - R_BS b_g = ω_B`` and
        ``accel_B - R_BS b_a = f_B``.
    """
    return _to_body(pose, gyro, accel, dt, b_g, tangential=bool(tangential))


@functools.partial(jax.jit, static_argnames=("tangential",))
def _to_body(pose: SensorPose, gyro, accel, dt, b_g, *, tangential: bool):
    """:func:`to_body` as one compiled program: called outside a ``jit`` (the preintegration
    of a sensor, a test's reference), its few dozen operations would each compile alone, for
    every new shape."""
    # on components (..., T), stacked once at the end (docs/DESIGN.md, "kernel layout")
    R = pose.R[..., None, :, :]
    gyro_b = matvec_v3(R, V3.of(gyro))
    omega = gyro_b - V3(*(c[..., None] for c in matvec_v3(pose.R, V3.of(b_g))))
    alpha = _angular_acceleration(gyro_b, dt) if tangential else None
    r = V3(*(c[..., None] for c in V3.of(pose.p)))
    return gyro_b.stack(), _body_specific_force(R, V3.of(accel), omega, alpha, r).stack()


def _body_specific_force(R, accel: V3, omega: V3, alpha, r: V3) -> V3:
    """``f_B = R_BS f_S - α×r - ω×(ω×r)`` on components: the raw sensor specific force
    ``accel`` as the body's (its bias then ``R_BS b_a``), at the bias-corrected body rate
    ``omega`` (``alpha`` ``None``: no tangential term)."""
    return matvec_v3(R, accel) - _lever_arm_acceleration(omega, alpha, r)


def lever_of(pose: SensorPose):
    """The lever arm the kernels' Jacobians need (:func:`centripetal_jacobian`): ``pose.p``,
    or ``None`` for a sensor known to sit at the body's origin (a concrete zero ``p``), whose
    kernels then skip the coupling."""
    p = pose.p
    if val.is_concrete(p) and not np.any(np.asarray(p)):
        return None
    return p


@jax.jit
def bias_to_body(pose: SensorPose, b):
    """``R_BS b`` for a ``(..., 3)`` sensor-frame bias."""
    return matvec(pose.R, b)


def noise_to_body(pose: SensorPose, noise: ImuNoise) -> ImuNoise:
    """Densities of the body-frame samples: isotropic ones unchanged (the same object);
    per-axis ones rotated as variances, ``σ_B² = (R∘R) σ_S²`` (module docstring)."""
    RR = pose.R * pose.R

    def rot(s):
        s = jnp.asarray(s)
        if s.ndim == 0:
            return s
        # a body axis with no noise (a zero per-axis density, as zero random walks given as
        # (3,) arrays are) has σ_B² = 0 at its minimum: its derivative is zero, and so is
        # the square root's taken here (jnp.sqrt's at 0 is inf: NaN gradients downstream)
        v = matvec(RR, s * s)
        pos = v > 0
        return jnp.where(pos, jnp.sqrt(jnp.where(pos, v, jnp.ones_like(v))), jnp.zeros_like(v))

    return ImuNoise(*(rot(getattr(noise, f.name)) for f in dataclasses.fields(ImuNoise)))


@functools.partial(jax.jit, static_argnames=("n",))
def bias_transform(pose: SensorPose, n: int = 15):
    """``T = blockdiag(I₉, R_BS, R_BS)`` ``(..., n, n)``: error with sensor-frame bias
    errors → error with body-frame ones (``n = 15``, error order ``[θ, p, v, b_g, b_a]``)."""
    R = pose.R
    T = jnp.broadcast_to(jnp.eye(n, dtype=R.dtype), R.shape[:-2] + (n, n))
    return T.at[..., 9:12, 9:12].set(R).at[..., 12:15, 12:15].set(R)


@functools.partial(jax.jit, static_argnames=("inverse",))
def congruence(T, P, inverse=False):
    """``T P Tᵀ``, or ``Tᵀ P T`` with ``inverse`` (``T`` orthogonal)."""
    Tt = jnp.swapaxes(T, -1, -2)
    return Tt @ P @ T if inverse else T @ P @ Tt
