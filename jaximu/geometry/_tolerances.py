"""Tolerances relative to the data and the dtype (docs/accepts.md): unit norms, covariances'
symmetry and semi-definiteness, and the definiteness of a matrix that is inverted or factored,
each scaled by its input and the computation dtype's ε.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaximu.geometry._checks import _index, is_concrete

# --------------------------------------------------------------------------- tolerances
#
# The one home of the tolerances of the value checks: each is relative to its input (a
# covariance's own scale, a norm's 1) and to the epsilon of the dtype the input is computed
# in, so that the same relative defect is refused at every scale and rounding passes.

ROUNDING = 60
"""The rounding a matrix check allows, in units of the dtype's ε: ``60 ε`` (``4 n ε`` for
the 15-dimensional error state), the rounding of a covariance ``A Aᵀ`` computed in the
dtype."""


ERROR_AXES = (
    "dθx",
    "dθy",
    "dθz",
    "dpx",
    "dpy",
    "dpz",
    "dvx",
    "dvy",
    "dvz",
    "db_gx",
    "db_gy",
    "db_gz",
    "db_ax",
    "db_ay",
    "db_az",
)
"""Names of the 15 error-state axes ``[dθ, dp, dv, db_g, db_a]`` (in messages)."""


def rounding_tolerance(dtype) -> float:
    """``60 ε`` of ``dtype`` (float32: 7.2e-6, float64: 1.3e-14): the relative tolerance of
    every symmetry and definiteness check. A non-floating dtype counts as float64."""
    d = np.dtype(dtype) if not isinstance(dtype, np.dtype) else dtype
    return ROUNDING * float(np.finfo(d if d.kind == "f" else np.float64).eps)


def unit_tolerance(dtype) -> float:
    """How far from 1 the norm of a unit quaternion may be: 1e-5 in float32 (≈ 84 ε, the
    rounding of a quaternion computed in float32), 1e-6 in float64 (a quaternion written
    with 7 significant digits passes; the engines normalise their start, so no tighter
    bound is needed)."""
    return 1e-6 if jnp.dtype(dtype) == jnp.float64 else 1e-5


def check_unit_norm(
    name: str,
    x,
    dtype,
    *,
    tol: float | None = None,
    fix: str = "normalise it first (jaximu.so3.quat_normalize)",
    what: str = "is not a unit quaternion",
    where=None,
    error=ValueError,
):
    """On concrete ``x``: every vector along the last axis has norm 1 within ``tol``
    (default :func:`unit_tolerance` of ``dtype``; data rounded by a file or a person have
    their own, passed by the caller); else ``error`` (a ``ValueError``) saying ``name``
    ``what``, the first offending vector and its norm, and ``fix``. ``where(i)``: how to
    name the vector at index ``i`` (default ``" at batch index [i]"``)."""
    if not is_concrete(x):
        return
    norm = np.linalg.norm(np.asarray(x, np.float64), axis=-1)
    err = np.abs(norm - 1.0)
    tol = unit_tolerance(dtype) if tol is None else tol
    bad = ~(err <= tol)
    if bad.any():
        i = tuple(np.argwhere(bad)[0]) if bad.ndim else ()
        at = where(i) if where is not None else (f" at batch index {_index(i)}" if bad.ndim else "")
        raise error(
            f"{name} {what}{at}: its norm is {norm[i]:.9g} (| |q| - 1 | = "
            f"{err[i]:.3g} > {tol:g}); {fix}"
        )


ROUNDED_QUATERNION = 1e-3
"""How far from 1 the norm of a quaternion that a person typed or a text file rounded (four
significant digits: a reference trajectory, a sensor YAML) may be; such a quaternion is
normalised by its user (the calibration's reference, ``--body-P-sensor``). File readers
have their own (``jaximu.io._common.QUATERNION_NORM_TOLERANCE``)."""


def _scale(arr):
    """Per matrix of ``(..., n, n)``: its largest absolute entry (its largest variance if it
    is a covariance), ``(..., 1, 1)``, 1 where the matrix is zero."""
    s = np.abs(arr).max(axis=(-2, -1), keepdims=True, initial=0.0)
    return np.where(s > 0, s, 1.0)


def axis_scales(arr):
    """Per axis of each matrix of ``(..., n, n)`` ``arr``: its own standard deviation
    ``√P_ii`` ``(..., n)``; an axis without a positive variance takes the matrix's largest
    entry's square root (its cross terms must then be rounding of that scale)."""
    d = np.diagonal(arr, axis1=-2, axis2=-1)
    big = np.sqrt(_scale(arr)[..., 0])
    return np.where(d > 0, np.sqrt(np.where(d > 0, d, 1.0)), big)


def check_covariance(name: str, P, dtype, *, fix: str = ""):
    """On concrete ``P`` (``(..., n, n)``, finite): each matrix has no negative variance (a
    negative diagonal is never rounding: ``A Aᵀ``'s diagonal is a sum of squares), and is
    symmetric and positive semi-definite within :func:`rounding_tolerance` of ``dtype``
    judged per axis, on ``D^-½ P D^-½`` (``D`` its variances): a covariance of mixed units
    (1e-4 rad² beside 1e-10 (rad/s)²) holds each entry to the rounding of its own axes, and
    one of 1e-12 and one of 1e12 to the same relative rounding. A ``ValueError`` names
    ``name``, the offending entry or eigenvalue, the tolerance, and the repair (``fix``,
    appended)."""
    if not is_concrete(P):
        return
    arr = np.asarray(P, np.float64)
    if arr.size == 0:
        return
    tol = rounding_tolerance(dtype)
    nb = arr.ndim - 2
    tail = f"; {fix}" if fix else ""
    diag = np.diagonal(arr, axis1=-2, axis2=-1)
    if (diag < 0).any():
        i = tuple(np.argwhere(diag < 0)[0])
        k = i + (i[-1],)
        raise ValueError(
            f"{name} is not positive semi-definite: the variance {name}{_index(k)} = "
            f"{arr[k]:.3g} is negative ({int((diag < 0).sum())} in all); variances are "
            f"σ² ≥ 0, and a negative one is never rounding{tail}"
        )
    s = axis_scales(arr)
    rel = arr / s[..., :, None] / s[..., None, :]  # relative, per axis; no overflow
    asym = np.abs(rel - np.swapaxes(rel, -1, -2))
    if asym.max() > tol:
        i = np.unravel_index(int(np.argmax(asym)), asym.shape)
        j = i[:-2] + (i[-1], i[-2])
        scale = float(s[i[:-1]] * s[i[:-2] + (i[-2],)])
        raise ValueError(
            f"{name} is not symmetric: {name}{_index(i)} = {arr[i]:.6g} but "
            f"{name}{_index(j)} = {arr[j]:.6g}, a difference of {asym[i]:.2g} of "
            f"√({name}_ii {name}_jj) = {scale:.3g} (beyond the rounding allowance {tol:.2g}, "
            f"{ROUNDING} ε of {np.dtype(dtype).name}); set both, e.g. "
            f"{name} = ({name} + {name}ᵀ) / 2{tail}"
        )
    lam = np.linalg.eigvalsh(0.5 * (rel + np.swapaxes(rel, -1, -2)))[..., 0]
    if lam.min() < -tol:
        b = np.unravel_index(int(np.argmin(lam)), lam.shape) if nb else ()
        raise ValueError(
            f"{name} is not positive semi-definite{f' (batch index {_index(b)})' if nb else ''}"
            f": the smallest eigenvalue of its correlation matrix D^-½ {name} D^-½ (D its "
            f"variances) is {lam[b]:.3g} (beyond the rounding allowance {tol:.2g}): the "
            f"cross terms exceed what the variances allow{tail}"
        )


def check_variances(name: str, P, dtype, *, fix: str = ""):
    """The variances (diagonal) of ``(..., n, n)`` ``P`` are not negative beyond
    :func:`rounding_tolerance` of ``dtype`` times the matrix's largest entry: for covariances
    the library computed and a writer stores (a propagation's ``F P Fᵀ + Q`` in float32 may
    round a variance of a direction it shrank to slightly below zero), not for a user's
    input, whose negative variance :func:`check_covariance` refuses always."""
    arr = np.asarray(P, np.float64)
    if arr.size == 0:
        return
    diag = np.diagonal(arr / _scale(arr), axis1=-2, axis2=-1)
    neg = diag < -rounding_tolerance(dtype)
    if neg.any():
        i = tuple(np.argwhere(neg)[0])
        raise ValueError(
            f"{name}{_index(i + (i[-1],))} = {arr[i + (i[-1],)]:.3g} is a negative variance "
            f"({int(neg.sum())} in all): variances are σ² ≥ 0" + (f"; {fix}" if fix else "")
        )


def definiteness(P, dtype):
    """How far each matrix of ``(..., n, n)`` ``P`` is from singular, in the dtype's terms:
    ``(ok, lam, zero)`` with ``ok`` (``(...)`` bool) whether it is positive definite to
    the precision of ``dtype``, ``lam`` the smallest eigenvalue of its correlation matrix
    ``D^-½ P D^-½`` (``D`` its variances; 1 for uncorrelated axes, 0 for dependent ones),
    and ``zero`` the index of a variance that is not positive (``-1`` if none). Judged on
    the correlation matrix, the test does not depend on the axes' units (variances from
    1e-12 rad² to 1e4 m² alike; a small variance is not a zero one), and it is what decides
    whether a Cholesky factor of ``P`` means anything: ``lam`` ≤ :func:`rounding_tolerance`
    is a direction that the dtype cannot tell from none. (A variance that is only rounding
    comes with cross terms of the same size, whose correlations exceed 1: caught by
    ``lam``.)"""
    arr = np.asarray(P, np.float64)
    tol = rounding_tolerance(dtype)
    d = np.diagonal(arr, axis1=-2, axis2=-1)
    tiny = ~(d > 0)
    zero = np.where(tiny.any(-1), np.argmax(tiny, -1), -1)
    s = 1.0 / np.sqrt(np.where(tiny, 1.0, d))
    C = arr * s[..., :, None] * s[..., None, :]
    keep = ~tiny
    C = np.where(keep[..., :, None] & keep[..., None, :], C, 0.0)
    C = C + np.where(tiny, 1.0, 0.0)[..., None] * np.eye(arr.shape[-1])
    C = 0.5 * (C + np.swapaxes(C, -1, -2))
    lam = np.linalg.eigvalsh(C)[..., 0] if C.size else np.ones(C.shape[:-2])
    lam = np.where(zero >= 0, 0.0, lam)
    return (lam > tol) & (zero < 0), lam, zero


def check_definite(name: str, P, dtype, *, fix: str, axes=None, what: str = ""):
    """On concrete ``P`` (``(..., n, n)``, finite, symmetric): each matrix is positive
    definite to the precision of ``dtype`` (:func:`definiteness`), as anything factored or
    inverted must be; else a ``ValueError`` naming ``name`` (``what`` says why it is
    inverted), the matrix in a batch, the zero variance or the dependent axes (``axes``:
    their names, default the index), and ``fix``."""
    if not is_concrete(P):
        return
    arr = np.asarray(P, np.float64)
    if arr.size == 0:
        return
    ok, lam, zero = definiteness(arr, dtype)
    if ok.all():
        return
    nb = arr.ndim - 2
    b = tuple(np.argwhere(~ok)[0]) if nb else ()
    label = (lambda k: axes[k]) if axes is not None else (lambda k: f"axis {k}")
    at = f" (batch index {_index(b)}, {int((~ok).sum())} of {ok.size})" if nb else ""
    why = f" ({what})" if what else ""
    if zero[b] >= 0:
        k = int(zero[b])
        raise ValueError(
            f"{name} is singular{at}: its variance {_index(b + (k, k))} ({label(k)}) is "
            f"{arr[b + (k, k)]:.3g}, not positive, so it cannot be inverted{why}; {fix}"
        )
    d = np.sqrt(np.diagonal(arr[b], axis1=-2, axis2=-1))
    w, v = np.linalg.eigh(arr[b] / d[:, None] / d[None, :])
    v = np.abs(v[:, 0])
    dep = ", ".join(label(k) for k in np.flatnonzero(v >= 0.25 * v.max()))
    raise ValueError(
        f"{name} is singular to {np.dtype(dtype).name} precision{at}: the smallest eigenvalue "
        f"of its correlation matrix is {lam[b]:.3g} (≤ {rounding_tolerance(dtype):.2g}, "
        f"{ROUNDING} ε), so {dep} are linearly dependent and it cannot be inverted{why}; "
        f"{fix}"
    )
