"""Quaternions and SO(3): products, exp/log, Jacobians, converters, Euler angles.

Every function acts on one sample and broadcasts over leading axes:

* quaternions are ``(..., 4)`` Hamilton, scalar first ``[w, x, y, z]``;
* rotation vectors and 3-vectors are ``(..., 3)``;
* rotation matrices are ``(..., 3, 3)``.

Inputs may be arrays or nested Python lists / tuples (a ROS quaternion ``[x, y, z, w]``).
Shapes are checked (a ``ValueError`` naming the function and the argument: ``so3.exp`` of a
quaternion is an error, not a 5-vector); values are not (these kernels run inside ``jit``
and ``grad`` loops), so a quaternion is assumed unit where the docstring says so.

A quaternion ``q`` represents ``R = R(q)``, which maps body vectors into the world
(``R_WB``, see docs/DESIGN.md). ``exp`` and ``log`` are the SO(3) exponential and logarithm of
the rotation vector ``phi = theta * axis``.

Values *and* gradients are finite and correct at zero angle, at tiny angles and near pi,
in float32 and float64: wherever a closed form divides by the angle, the small-angle
branch uses a Taylor series and the other branch sees a dummy, harmless argument (the
"double where" trick), so reverse-mode autodiff never multiplies a zero cotangent by an
infinite partial.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = [
    "skew",
    "quat_identity",
    "quat_mul",
    "quat_conj",
    "quat_normalize",
    "quat_rotate",
    "quat_to_matrix",
    "matrix_to_quat",
    "exp",
    "log",
    "exp_matrix",
    "log_matrix",
    "right_jacobian",
    "right_jacobian_inv",
    "left_jacobian",
    "quat_first_order_update",
    "xyzw_to_wxyz",
    "wxyz_to_xyzw",
    "jpl_to_hamilton",
    "hamilton_to_jpl",
    "euler_zyx_to_quat",
    "euler_zyx_to_matrix",
    "quat_to_euler_zyx",
    "euler_rate_matrix",
]


def _taylor_threshold(dtype) -> float:
    """Squared angle below which the Taylor branches are used.

    With series carried to theta^6 the truncation error at the threshold is below the
    dtype's epsilon, and the closed forms just above it lose at most ~1e-11 (float64) or
    ~2e-4 (float32) relative accuracy in their smallest coefficients, which multiply
    theta^2 and so stay at rounding level in the result.
    """
    return 1e-4 if jnp.dtype(dtype) == jnp.float64 else 4e-3


def _split(theta_sq):
    """(is_small, theta) with theta = sqrt(theta_sq) evaluated only where it is safe."""
    small = theta_sq < _taylor_threshold(theta_sq.dtype)
    safe_sq = jnp.where(small, jnp.ones_like(theta_sq), theta_sq)
    return small, jnp.sqrt(safe_sq)


def _arg(fn: str, name: str, x, tail: tuple):
    """``x`` as an array (a Python list or tuple is fine: a ROS quaternion), checked to end
    in ``tail``; else a ``ValueError`` naming ``so3.fn``, the argument and the shape wanted.
    A static check: it also runs inside ``jit``, at trace time only. Integers (``[1, 0, 0,
    0]``) are computed in the default float dtype, not in integer arithmetic."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.inexact):
        x = x.astype(jnp.result_type(float))
    n = len(tail)
    if x.ndim < n or tuple(x.shape[x.ndim - n :]) != tuple(tail):
        want = ", ".join(str(d) for d in tail)
        raise ValueError(f"so3.{fn}: {name} must have shape (..., {want}), got {tuple(x.shape)}")
    return x


def _batches(fn: str, a: str, x, na: int, b: str, y, nb: int):
    """The batch shapes of two arguments broadcast; else a ``ValueError`` naming both."""
    try:
        jnp.broadcast_shapes(x.shape[: x.ndim - na], y.shape[: y.ndim - nb])
    except ValueError:
        raise ValueError(
            f"so3.{fn}: the batch shapes of {a} {tuple(x.shape)} and {b} "
            f"{tuple(y.shape)} do not broadcast"
        ) from None


# column c of [e_i]x is e_i × e_c
SKEW_GENERATORS = np.stack([np.cross(np.eye(3)[i], np.eye(3)).T for i in range(3)])
"""``(3, 3, 3)``: ``[e_i]x`` for the axes ``e_i`` (so(3)'s generators): ``[v]x = Σ_i v_i
[e_i]x``, the one definition of the skew matrix in every layout (:func:`skew_of`)."""


def skew_of(components, lanes_last=False):
    """``[v]x = Σ_i v_i [e_i]x`` from ``v``'s three components (arrays of one batch shape
    ``S``): ``S + (3, 3)``, or with ``lanes_last`` ``(3, 3) + S`` (the structure-of-arrays
    layout of :mod:`jaximu.kernels.lane_math`, lanes minor). The dtype is the components'."""
    dtype = jnp.result_type(*components)
    G = jnp.asarray(SKEW_GENERATORS, dtype)
    if lanes_last:
        return sum(G[i][:, :, None] * components[i][None, None] for i in range(3))
    return sum(G[i] * components[i][..., None, None] for i in range(3))


def skew(v):
    """Skew-symmetric matrix ``[v]x`` with ``[v]x w = v x w``. ``(..., 3) -> (..., 3, 3)``."""
    v = _arg("skew", "v", v, (3,))
    return skew_of((v[..., 0], v[..., 1], v[..., 2]))


def _skew_sq(v):
    """``[v]x² = v vᵀ - |v|² I`` (``(..., 3) -> (..., 3, 3)``): the square of :func:`skew`
    without a matrix product (XLA:CPU turns batched 3×3 products into library calls that
    cannot run inside one compiled kernel: docs/DESIGN.md, "One kernel per block")."""
    eye = jnp.eye(3, dtype=v.dtype)
    return v[..., :, None] * v[..., None, :] - jnp.sum(v * v, axis=-1)[..., None, None] * eye


# --------------------------------------------------------------------------- quaternions


def quat_identity(batch_shape=(), dtype=jnp.float32):
    """Identity quaternion ``[1, 0, 0, 0]`` of shape ``batch_shape + (4,)``."""
    return jnp.zeros(tuple(batch_shape) + (4,), dtype).at[..., 0].set(1.0)


def quat_mul(p, q):
    """Hamilton product ``p ⊗ q`` (``R(p ⊗ q) = R(p) R(q)``). ``(..., 4), (..., 4) -> (..., 4)``."""
    p = _arg("quat_mul", "p", p, (4,))
    q = _arg("quat_mul", "q", q, (4,))
    _batches("quat_mul", "p", p, 1, "q", q, 1)
    return jnp.stack(
        quat_mul_components(tuple(p[..., i] for i in range(4)), tuple(q[..., i] for i in range(4))),
        axis=-1,
    )


def quat_mul_components(p, q):
    """:func:`quat_mul` on components: ``p``, ``q`` are 4-tuples ``(w, x, y, z)`` of arrays
    (or scalars) that broadcast; returns the 4-tuple of ``p ⊗ q``. The one home of the
    product, for the ``(..., 4)`` arrays above and the structure-of-arrays lanes
    (:mod:`jaximu.kernels.lane_math`)."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


def quat_conj(q):
    """Conjugate ``[w, -x, -y, -z]`` (the inverse of a unit quaternion)."""
    q = _arg("quat_conj", "q", q, (4,))
    return q * jnp.array([1, -1, -1, -1], dtype=q.dtype)


def quat_normalize(q):
    """``q / |q|``. The caller guarantees ``q != 0``."""
    q = _arg("quat_normalize", "q", q, (4,))
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def quat_rotate(q, v):
    """Rotate a vector: ``R(q) v`` for unit ``q``. ``(..., 4), (..., 3) -> (..., 3)``.

    Uses ``v + 2 w (u x v) + 2 u x (u x v)`` (u the vector part), cheaper than forming R.
    """
    q = _arg("quat_rotate", "q", q, (4,))
    v = _arg("quat_rotate", "v", v, (3,))
    _batches("quat_rotate", "q", q, 1, "v", v, 1)
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * jnp.cross(u, v)
    return v + w * t + jnp.cross(u, t)


def quat_to_matrix(q):
    """Rotation matrix of a unit quaternion. ``(..., 4) -> (..., 3, 3)``."""
    q = _arg("quat_to_matrix", "q", q, (4,))
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)], axis=-1),
            jnp.stack([2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)], axis=-1),
            jnp.stack([2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)], axis=-1),
        ],
        axis=-2,
    )


def matrix_to_quat(R):
    """Unit quaternion of a rotation matrix, with ``w >= 0``. ``(..., 3, 3) -> (..., 4)``.

    Shepperd's method: of the four candidate formulas the one with the largest
    denominator is chosen, so it is accurate everywhere, including at pi. The result is
    normalised, so a slightly non-orthogonal ``R`` gives the nearest-direction quaternion.
    """
    R = _arg("matrix_to_quat", "R", R, (3, 3))
    r00, r11, r22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    r01, r02, r10 = R[..., 0, 1], R[..., 0, 2], R[..., 1, 0]
    r12, r20, r21 = R[..., 1, 2], R[..., 2, 0], R[..., 2, 1]
    trace = r00 + r11 + r22
    # 4w^2 = 1 + tr, 4x^2 = 1 + r00 - r11 - r22, ... ; the largest is >= 1.
    d = jnp.stack([1 + trace, 1 + r00 - r11 - r22, 1 - r00 + r11 - r22, 1 - r00 - r11 + r22], -1)
    choice = jnp.argmax(d, axis=-1)
    # Clamp so that branches not chosen stay finite (and so do their gradients).
    s = 2.0 * jnp.sqrt(jnp.maximum(d, 0.25))
    s0, s1, s2, s3 = s[..., 0], s[..., 1], s[..., 2], s[..., 3]
    cands = [
        jnp.stack([s0 / 4, (r21 - r12) / s0, (r02 - r20) / s0, (r10 - r01) / s0], -1),
        jnp.stack([(r21 - r12) / s1, s1 / 4, (r01 + r10) / s1, (r02 + r20) / s1], -1),
        jnp.stack([(r02 - r20) / s2, (r01 + r10) / s2, s2 / 4, (r12 + r21) / s2], -1),
        jnp.stack([(r10 - r01) / s3, (r02 + r20) / s3, (r12 + r21) / s3, s3 / 4], -1),
    ]
    q = cands[3]
    for i in (2, 1, 0):
        q = jnp.where((choice == i)[..., None], cands[i], q)
    q = jnp.where(q[..., :1] < 0, -q, q)
    return quat_normalize(q)


def exp(phi):
    """SO(3) exponential as a quaternion: ``[cos(θ/2), sin(θ/2) φ/θ]``. ``(..., 3) -> (..., 4)``.

    This is the exact constant-rate orientation update ``Θ(Δt)`` of docs/DESIGN.md for
    ``φ = ω Δt``.
    """
    phi = _arg("exp", "phi", phi, (3,))
    theta_sq = jnp.sum(phi * phi, axis=-1)
    small, theta = _split(theta_sq)
    t2, t4, t6 = theta_sq, theta_sq * theta_sq, theta_sq * theta_sq * theta_sq
    half = 0.5 * theta
    w = jnp.where(small, 1 - t2 / 8 + t4 / 384 - t6 / 46080, jnp.cos(half))
    k = jnp.where(small, 0.5 - t2 / 48 + t4 / 3840 - t6 / 645120, jnp.sin(half) / theta)
    return jnp.concatenate([w[..., None], k[..., None] * phi], axis=-1)


def log(q):
    """SO(3) logarithm of a unit quaternion: the rotation vector with angle in ``[0, π]``.

    ``q`` and ``-q`` give the same result. ``(..., 4) -> (..., 3)``.
    """
    q = _arg("log", "q", q, (4,))
    q = jnp.where(q[..., :1] < 0, -q, q)
    w = q[..., 0]
    u = q[..., 1:]
    n_sq = jnp.sum(u * u, axis=-1)
    # n = sin(θ/2); the Taylor threshold is on θ^2 ≈ 4 n^2.
    small, n = _split(4.0 * n_sq)
    n = 0.5 * n
    # 2 atan(n / w) / n = (2 / w) (1 - n^2 / (3 w^2) + n^4 / (5 w^4) - ...), with w ≈ 1 here.
    safe_w = jnp.where(small, w, jnp.ones_like(w))
    r = n_sq / (safe_w * safe_w)
    series = (2.0 / safe_w) * (1 - r / 3 + r * r / 5 - r * r * r / 7)
    k = jnp.where(small, series, 2.0 * jnp.arctan2(n, w) / n)
    return k[..., None] * u


def exp_matrix(phi):
    """SO(3) exponential as a rotation matrix (Rodrigues). ``(..., 3) -> (..., 3, 3)``."""
    phi = _arg("exp_matrix", "phi", phi, (3,))
    return quat_to_matrix(exp(phi))


def log_matrix(R):
    """SO(3) logarithm of a rotation matrix, angle in ``[0, π]``. ``(..., 3, 3) -> (..., 3)``."""
    R = _arg("log_matrix", "R", R, (3, 3))
    return log(matrix_to_quat(R))


def _jacobian_coeffs(phi):
    """a = (1 - cos θ)/θ², b = (θ - sin θ)/θ³, c = 1/θ² - cot(θ/2)/(2θ), all NaN-safe."""
    theta_sq = jnp.sum(phi * phi, axis=-1)
    small, theta = _split(theta_sq)
    t2, t4, t6 = theta_sq, theta_sq * theta_sq, theta_sq * theta_sq * theta_sq
    s_half = jnp.sin(0.5 * theta)
    safe_sq = theta * theta  # not theta_sq: the unused branch must not divide by zero
    a_closed = 2.0 * (s_half / theta) ** 2  # (1 - cos θ)/θ² without cancellation
    b_closed = (theta - jnp.sin(theta)) / (safe_sq * theta)
    c_closed = 1.0 / safe_sq - jnp.cos(0.5 * theta) / (2.0 * theta * s_half)
    a = jnp.where(small, 0.5 - t2 / 24 + t4 / 720 - t6 / 40320, a_closed)
    b = jnp.where(small, 1.0 / 6 - t2 / 120 + t4 / 5040 - t6 / 362880, b_closed)
    c = jnp.where(small, 1.0 / 12 + t2 / 720 + t4 / 30240 + t6 / 1209600, c_closed)
    return a, b, c


def right_jacobian(phi):
    """Right Jacobian ``Jr(φ) = I - a[φ]x + b[φ]x²`` of SO(3). ``(..., 3) -> (..., 3, 3)``.

    ``Exp(φ + δ) ≈ Exp(φ) Exp(Jr(φ) δ)``; GTSAM's ``Rot3::ExpmapDerivative``.
    """
    phi = _arg("right_jacobian", "phi", phi, (3,))
    a, b, _ = _jacobian_coeffs(phi)
    K = skew(phi)
    eye = jnp.eye(3, dtype=phi.dtype)
    return eye - a[..., None, None] * K + b[..., None, None] * _skew_sq(phi)


def right_jacobian_inv(phi):
    """Inverse right Jacobian ``Jr(φ)⁻¹ = I + ½[φ]x + c[φ]x²`` (θ < 2π). ``(..., 3) -> (..., 3, 3)``.

    ``Log(Exp(φ) Exp(δ)) ≈ φ + Jr(φ)⁻¹ δ``; GTSAM's ``Rot3::LogmapDerivative``.
    """
    phi = _arg("right_jacobian_inv", "phi", phi, (3,))
    _, _, c = _jacobian_coeffs(phi)
    K = skew(phi)
    eye = jnp.eye(3, dtype=phi.dtype)
    return eye + 0.5 * K + c[..., None, None] * _skew_sq(phi)


def left_jacobian(phi):
    """Left Jacobian ``Jl(φ) = Jr(-φ) = Jr(φ)ᵀ``. ``(..., 3) -> (..., 3, 3)``."""
    phi = _arg("left_jacobian", "phi", phi, (3,))
    return right_jacobian(-phi)


def quat_first_order_update(q, phi):
    """First-order orientation update ``normalize(q ⊗ [1, φ/2])``. ``(..., 4), (..., 3) -> (..., 4)``.

    Equals ``q ⊗ Exp(φ')`` with angle ``2 atan(θ/2)``: an angle error of ``θ³/12`` per step.
    """
    q = _arg("quat_first_order_update", "q", q, (4,))
    phi = _arg("quat_first_order_update", "phi", phi, (3,))
    _batches("quat_first_order_update", "q", q, 1, "phi", phi, 1)
    dq = jnp.concatenate([jnp.ones_like(phi[..., :1]), 0.5 * phi], axis=-1)
    return quat_normalize(quat_mul(q, dq))


# --------------------------------------------------------------------------- converters


def xyzw_to_wxyz(q):
    """``[x, y, z, w]`` (scipy, Eigen ``coeffs()``, PyPose, ROS) to ``[w, x, y, z]``."""
    q = _arg("xyzw_to_wxyz", "q", q, (4,))
    return jnp.concatenate([q[..., 3:], q[..., :3]], axis=-1)


def wxyz_to_xyzw(q):
    """``[w, x, y, z]`` to ``[x, y, z, w]`` (scipy, Eigen ``coeffs()``, PyPose, ROS)."""
    q = _arg("wxyz_to_xyzw", "q", q, (4,))
    return jnp.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def jpl_to_hamilton(q_jpl):
    """JPL ``^I_G q̄`` (OpenVINS, stored ``[q1, q2, q3, q4]``, scalar last) to Hamilton ``q_WB``.

    A JPL quaternion with vector ``u`` and scalar ``s`` has ``C(q̄) = R_Hamilton(s, u)ᵀ``;
    OpenVINS's ``C(^I_G q̄) = R_GtoI = R_WBᵀ``, so ``q_WB = [s, u]``: the same four numbers,
    reordered (Trawny & Roumeliotis, TR 2005-002, eq. 62).
    """
    q_jpl = _arg("jpl_to_hamilton", "q_jpl", q_jpl, (4,))
    return xyzw_to_wxyz(q_jpl)


def hamilton_to_jpl(q_wb):
    """Hamilton ``q_WB`` ``[w, x, y, z]`` to JPL ``^I_G q̄`` ``[q1, q2, q3, q4]`` (OpenVINS)."""
    q_wb = _arg("hamilton_to_jpl", "q_wb", q_wb, (4,))
    return wxyz_to_xyzw(q_wb)


# --------------------------------------------------------------------------- Euler angles


def euler_zyx_to_quat(chi):
    """ZYX Euler angles ``χ = [roll, pitch, yaw]`` to a quaternion.

    ``R = Rz(yaw) Ry(pitch) Rx(roll)`` (GTSAM ``Rot3::Ypr(yaw, pitch, roll)``, scipy
    ``Rotation.from_euler("ZYX", [yaw, pitch, roll])``). ``(..., 3) -> (..., 4)``.
    """
    chi = _arg("euler_zyx_to_quat", "chi", chi, (3,))
    hr, hp, hy = 0.5 * chi[..., 0], 0.5 * chi[..., 1], 0.5 * chi[..., 2]
    cr, sr = jnp.cos(hr), jnp.sin(hr)
    cp, sp = jnp.cos(hp), jnp.sin(hp)
    cy, sy = jnp.cos(hy), jnp.sin(hy)
    return jnp.stack(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ],
        axis=-1,
    )


def euler_zyx_to_matrix(chi):
    """``Rz(yaw) Ry(pitch) Rx(roll)`` for ``χ = [roll, pitch, yaw]``. ``(..., 3) -> (..., 3, 3)``."""
    chi = _arg("euler_zyx_to_matrix", "chi", chi, (3,))
    cr, sr = jnp.cos(chi[..., 0]), jnp.sin(chi[..., 0])
    cp, sp = jnp.cos(chi[..., 1]), jnp.sin(chi[..., 1])
    cy, sy = jnp.cos(chi[..., 2]), jnp.sin(chi[..., 2])
    return jnp.stack(
        [
            jnp.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            jnp.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            jnp.stack([-sp, cp * sr, cp * cr], -1),
        ],
        axis=-2,
    )


def quat_to_euler_zyx(q):
    """Unit quaternion to ``[roll, pitch, yaw]`` with pitch in ``[-π/2, π/2]``.

    At pitch ±π/2 (gimbal lock) roll and yaw are not unique and their gradients are
    infinite; this is the representation's singularity, not hidden here.
    ``(..., 4) -> (..., 3)``.
    """
    q = _arg("quat_to_euler_zyx", "q", q, (4,))
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    roll = jnp.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = jnp.arcsin(jnp.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return jnp.stack([roll, pitch, yaw], axis=-1)


def euler_rate_matrix(chi):
    """``E(χ)`` with ``χ̇ = E(χ) ω_B`` for ZYX angles ``χ = [roll, pitch, yaw]``.

    Singular at pitch ±π/2 (``1/cos(pitch)``). ``(..., 3) -> (..., 3, 3)``.
    """
    chi = _arg("euler_rate_matrix", "chi", chi, (3,))
    cr, sr = jnp.cos(chi[..., 0]), jnp.sin(chi[..., 0])
    cp = jnp.cos(chi[..., 1])
    tp = jnp.tan(chi[..., 1])
    one, zero = jnp.ones_like(cr), jnp.zeros_like(cr)
    return jnp.stack(
        [
            jnp.stack([one, sr * tp, cr * tp], -1),
            jnp.stack([zero, cr, -sr], -1),
            jnp.stack([zero, sr / cp, cr / cp], -1),
        ],
        axis=-2,
    )
