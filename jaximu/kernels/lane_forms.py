"""The attitude forms on lanes (:data:`LANE_FORMS`: a quaternion's 4 lanes, a matrix's 9, Euler
angles' 3), each advancing, rotating, giving its matrix, its tangents and error rows for the
autodiff blocks; and the mean step of every scheme on them (docs/DESIGN.md section 2).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from jaximu.geometry import so3
from jaximu.geometry._vec import V3
from jaximu.geometry.so3 import quat_mul_components
from jaximu.kernels.lane_directions import lane_directions, rotation_rows, rotation_tangents
from jaximu.kernels.lane_math import (
    _S3,
    _dtype_of,
    _half_any,
    _materialise,
    _quat_normalize,
    _quat_renormalize,
    _quat_rotate,
    half_angle,
    quat_matrix,
)
from jaximu.schemes import integrators
from jaximu.schemes.integrators import get_attitude, stage_sum

# ----------------------------------------------------------------------------- attitude forms
#
# The attitude forms of jaximu.integrators (``Attitude``) on lanes: a form's state is a tuple
# of lanes (4 for the quaternions, 9 for a matrix, row-major). Each form advances, rotates,
# gives its matrix, its tangents in the rotation error's 3 directions and the error's rows
# from a tangent of the result (autodiff blocks), and turns left (a rotating world).


def _quat_advance(q, phi: V3, half=None):
    """``normalize(q ⊗ Exp(φ))``: the exact exponential, renormalised so that rounding
    cannot let ``|q|`` drift; ``half``: ``(cos(θ/2), sin(θ/2)/θ)`` when the caller has them."""
    c, k = half_angle(phi.dot(phi)) if half is None else half
    return _quat_renormalize(quat_mul_components(q, (c, k * phi.x, k * phi.y, k * phi.z)))


def _quat_first_order(q, phi: V3, half=None):
    """``normalize(q ⊗ [1, φ/2])`` (:func:`jaximu.so3.quat_first_order_update`)."""
    return _quat_normalize(quat_mul_components(q, (1.0, 0.5 * phi.x, 0.5 * phi.y, 0.5 * phi.z)))


def _quat_rotate_left(q, dth):
    """``normalize(Exp(dθ) ⊗ q)`` for a rotation vector ``dθ`` ``(..., 3)``."""
    e = so3.exp(dth)
    return _quat_normalize(quat_mul_components(tuple(e[..., i] for i in range(4)), q))


def _lanes_matrix(x, dtype):
    """A matrix's 9 lanes (row-major) as ``(3, 3, B)`` (one-hot broadcasting)."""
    E = np.eye(9).reshape(9, 3, 3)
    return sum(jnp.asarray(E[n], dtype)[:, :, None] * x[n][None, None] for n in range(9))


def _mat_mul_lanes(X, Y):
    """``X Y`` of two matrices given as 9 lanes each (or ``(3, 3, …)`` blocks), 9 lanes."""
    return tuple(
        sum(X[3 * i + m] * Y[3 * m + j] for m in range(3)) for i in range(3) for j in range(3)
    )


def _matrix_advance(R, phi: V3, half=None):
    """``R Exp(φ)`` (:func:`jaximu.so3.exp_matrix`, from the same half angle)."""
    c, k = half_angle(phi.dot(phi)) if half is None else half
    E = quat_matrix((c, k * phi.x, k * phi.y, k * phi.z), _dtype_of(phi))
    return _mat_mul_lanes(R, tuple(E[n // 3, n % 3] for n in range(9)))


def _matrix_rotate(R, f):
    return tuple(R[3 * i] * f[0] + R[3 * i + 1] * f[1] + R[3 * i + 2] * f[2] for i in range(3))


def _matrix_rotate_left(R, dth):
    """``Exp(dθ) R`` (:func:`jaximu.so3.exp_matrix`) for ``dθ`` ``(..., 3)``."""
    E = so3.exp_matrix(dth)
    return _mat_mul_lanes(tuple(E[..., n // 3, n % 3] for n in range(9)), R)


def _matrix_tangents(R, world=False):
    """The tangents of ``R Exp(δθ)`` (``world``: ``Exp(δθ) R``) in the 3 directions of
    ``δθ``: ``R [e_j]x`` (``[e_j]x R``), 9 lanes of ``(3, *lanes)``."""
    dtype, lanes = R[0].dtype, R[0].shape
    # [e_j]x (_S3[j]) as 9 lanes of (3 directions, *lanes)
    S = tuple(
        jnp.broadcast_to(
            jnp.asarray(_S3[:, n // 3, n % 3], dtype).reshape((3,) + (1,) * len(lanes)),
            (3,) + lanes,
        )
        for n in range(9)
    )
    Rd = tuple(x[None] for x in R)
    return _mat_mul_lanes(S, Rd) if world else _mat_mul_lanes(Rd, S)


def _matrix_rows(tR1, R1, world=False):
    """The rotation error's rows from a tangent ``δR⁺`` of ``R⁺``: ``vee(R⁺ᵀ δR⁺)``
    (``world``: ``vee(δR⁺ R⁺ᵀ)``), the tangent of ``Log(R̂⁺ᵀ R⁺)`` (its skew part: the
    exact derivative for an orthonormal ``R⁺``)."""
    R1t = tuple(R1[3 * (n % 3) + n // 3][None] for n in range(9))
    M = _mat_mul_lanes(tR1, R1t) if world else _mat_mul_lanes(R1t, tR1)
    return (0.5 * (M[7] - M[5]), 0.5 * (M[2] - M[6]), 0.5 * (M[3] - M[1]))


def _sincos(a):
    """``(sin a, cos a)`` per lane from the range-reduced half angle of ``θ = 2|a|``
    (:func:`_half_any`: ``cos a`` and ``sin|a| / 2|a|``): vectorised arithmetic, where
    ``jnp.sin``/``cos`` are scalar library calls on XLA:CPU."""
    c, k = _half_any(4.0 * (a * a))
    return 2.0 * a * k, c


def _euler_trig(chi):
    """``(sin, cos)`` of roll, pitch and yaw."""
    return tuple(_sincos(x) for x in chi)


def _euler_matrix(chi, trig=None):
    """``R(χ)`` of ZYX angles ``χ = (roll, pitch, yaw)`` as 9 lanes
    (:func:`jaximu.so3.euler_zyx_to_matrix`)."""
    (sr, cr), (sp, cp), (sy, cy) = _euler_trig(chi) if trig is None else trig
    return (
        cy * cp,
        cy * sp * sr - sy * cr,
        cy * sp * cr + sy * sr,
        sy * cp,
        sy * sp * sr + cy * cr,
        sy * sp * cr - cy * sr,
        -sp,
        cp * sr,
        cp * cr,
    )


def _euler_rate(chi, w, trig=None):
    """``E(χ) ω``: the angles' rate for a body rate ``ω`` (:func:`jaximu.so3.euler_rate_matrix`;
    singular at pitch ±π/2, which the kernels report)."""
    (sr, cr), (sp, cp) = (_euler_trig(chi) if trig is None else trig)[:2]
    tp = sp / cp
    return V3(
        w[0] + (sr * tp) * w[1] + (cr * tp) * w[2],
        cr * w[1] + (-sr) * w[2],
        (sr / cp) * w[1] + (cr / cp) * w[2],
    )


def _euler_advance(chi, phi: V3, half=None):
    """``χ + E(χ) φ`` (the ``"euler_angles"`` form's update)."""
    return tuple(V3(*chi) + _euler_rate(chi, phi))


def _euler_rotate_left(chi, dth):
    """The angles of ``Exp(dθ) R(χ)`` (as the generic kernels: through quaternions)."""
    q = so3.euler_zyx_to_quat(jnp.stack(jnp.broadcast_arrays(*chi), -1))
    chi1 = so3.quat_to_euler_zyx(so3.quat_normalize(so3.quat_mul(so3.exp(dth), q)))
    return tuple(chi1[..., i] for i in range(3))


def _euler_rates_to_body(trig, d):
    """``W(χ) δχ = E(χ)⁻¹ δχ``: the body-frame rotation of an angle change ``δχ`` (the
    inverse of :func:`_euler_rate`: ``[[1, 0, -sp], [0, cr, sr cp], [0, -sr, cr cp]]``;
    ``trig`` the angles' :func:`_euler_trig`, ``d`` components broadcasting against it)."""
    (sr, cr), (sp, cp) = trig[:2]
    return (d[0] - sp * d[2], cr * d[1] + (sr * cp) * d[2], (-sr) * d[1] + (cr * cp) * d[2])


def _euler_tangents(chi, world=False):
    """The tangents of the angles of ``R(χ) Exp(δθ)`` in the 3 directions of ``δθ``:
    ``E(χ) e_j``, 3 lanes of ``(3, *lanes)`` — the derivative the generic kernels take
    through ``quat_to_euler_zyx`` (periodic in roll and yaw, so the same for angles carried
    past ±π). Body frame only: the angles' step is no right multiplication of ``R``, so the
    world-frame error's ``Φ_θθ`` is not the identity the kernels' world frame assumes
    (:func:`jaximu.kernels.fast.blocks_autodiff`)."""
    if world:
        raise NotImplementedError("Euler angles keep the body-frame rotation error")
    dtype, lanes = chi[0].dtype, chi[0].shape
    trig = _euler_trig(chi)
    cols = [_euler_rate(chi, tuple(float(x) for x in np.eye(3)[j]), trig) for j in range(3)]
    onehot = lane_directions(np.eye(3), dtype, lanes)
    return tuple(sum(onehot[j] * cols[j][i][None] for j in range(3)) for i in range(3))


def _euler_rows(tchi1, chi1, world=False):
    """The rotation error's rows from a tangent ``δχ⁺`` of the angles ``χ⁺``: ``W(χ⁺) δχ⁺``,
    the tangent of ``Log(R̂⁺ᵀ R⁺)`` (body frame only, as :func:`_euler_tangents`)."""
    if world:
        raise NotImplementedError("Euler angles keep the body-frame rotation error")
    trig = tuple((s[None], c[None]) for s, c in _euler_trig(chi1))
    return _euler_rates_to_body(trig, tchi1)


def rk4_euler_angles(chi, p: V3, v: V3, omega0, f0, omega1, f1, h, g: V3):
    """The ``"euler_angles"`` form's RK4 on lanes: :func:`jaximu.schemes.integrators.rk4_euler_angles`
    with the angles' rates and matrix from the half angle's polynomials (:func:`_euler_trig`)."""

    def deriv(c, w, f):
        trig = _euler_trig(c)
        return _euler_rate(c, w, trig), V3(*_matrix_rotate(_euler_matrix(c, trig), f)) + g

    chi1, p1, v1 = integrators.rk4_euler_angles(deriv, V3(*chi), p, v, omega0, f0, omega1, f1, h)
    return tuple(chi1), tuple(p1), tuple(v1)


class LaneForm(NamedTuple):
    """An attitude form (:class:`jaximu.integrators.Attitude`) on SoA lanes."""

    name: str
    size: int  # lanes of its state
    advance: Callable  # (x, φ: V3, half=None) -> x ⊞ φ
    rotate: Callable  # (x, f) -> R(x) f, 3 lanes
    matrix: Callable  # (x, dtype) -> R(x) as (3, 3, B)
    tangents: Callable  # (x, world) -> tangents of x ⊞ δθ in 3 directions
    rows: Callable  # (tx⁺, x⁺, world) -> the rotation error's 3 rows
    rotate_left: Callable  # (x, dθ (…, 3)) -> Exp(dθ) R(x), the form's state


_QUAT: dict[str, Any] = dict(
    size=4,
    rotate=_quat_rotate,
    matrix=quat_matrix,
    tangents=rotation_tangents,
    rows=rotation_rows,
    rotate_left=_quat_rotate_left,
)


LANE_FORMS = {
    "quaternion": LaneForm("quaternion", advance=_quat_advance, **_QUAT),
    "quaternion_first_order": LaneForm(
        "quaternion_first_order", advance=_quat_first_order, **_QUAT
    ),
    "matrix": LaneForm(
        "matrix",
        9,
        _matrix_advance,
        _matrix_rotate,
        _lanes_matrix,
        _matrix_tangents,
        _matrix_rows,
        _matrix_rotate_left,
    ),
    # no closed-form Jacobian (autodiff blocks only), the pitch singularity reported by the
    # kernels (jaximu.kernels.fast.propagate_mean, propagate_cov)
    "euler_angles": LaneForm(
        "euler_angles",
        3,
        _euler_advance,
        lambda chi, f: _matrix_rotate(_euler_matrix(chi), f),
        lambda chi, dtype: _lanes_matrix(_euler_matrix(chi), dtype),
        _euler_tangents,
        _euler_rows,
        _euler_rotate_left,
    ),
}
"""The attitude forms the structure-of-arrays kernels run, each as its own lanes."""


def lane_form(name) -> LaneForm:
    return LANE_FORMS[name]


def from_quat(form: LaneForm, q):
    """The form's state ``(B, size)`` from quaternions ``(B, 4)``: the generic kernels'
    ``Attitude.from_quat``, a matrix flattened row-major."""
    return get_attitude(form.name).from_quat(q).reshape(q.shape[:-1] + (form.size,))


def to_quat(form: LaneForm, x):
    """Quaternions ``(…, 4)`` from the form's states ``(…, size)`` (``Attitude.to_quat``)."""
    shape = (3, 3) if form.size == 9 else (form.size,)
    return get_attitude(form.name).to_quat(x.reshape(x.shape[:-1] + shape))


# ----------------------------------------------------------------------------- mean step


def _rotate_stage(form, x, f):
    """``R f`` of one stage, computed once into memory: the position and velocity rows
    that read it are separate loops, and each would otherwise recompute the rotation (mean
    kernels 1.07-1.25x faster; docs/DESIGN.md, "Stage boundaries")."""
    return V3(*_materialise(form.rotate(x, f)))


def mean_step(
    scheme,
    q,
    p,
    v,
    omega0,
    f0,
    omega1,
    f1,
    h,
    g,
    end_half=None,
    form: LaneForm = LANE_FORMS["quaternion"],
):
    """One step of ``scheme`` (a :class:`jaximu.integrators.Scheme`) on SoA lanes in the
    attitude form ``form`` (:data:`LANE_FORMS`; default the exact quaternion exponential):
    :func:`jaximu.integrators.step` in this layout.

    Args:
        q: the form's state (4-tuple of ``(B,)`` for a quaternion).
        p, v, omega0, f0, omega1, f1, g: :class:`V3` of ``(B,)`` lanes, or scalars.
        h: ``(B,)`` or scalar step [s].
        end_half: ``(cos(θ/2), sin(θ/2)/θ)`` of the end rotation when the caller has them.

    Returns:
        ``(q⁺, p⁺, v⁺)``.
    """
    if form.name == "euler_angles" and scheme.name == "rk4":
        return rk4_euler_angles(q, p, v, omega0, f0, omega1, f1, h, g)
    pts, phi_end = scheme.points(omega0, f0, omega1, f1, h)
    q_end = form.advance(q, phi_end, end_half)
    p1, v1 = stage_sum(
        pts, q, q_end, form.advance, lambda x, f: _rotate_stage(form, x, f), p, v, h, g
    )
    return q_end, tuple(p1), tuple(v1)
