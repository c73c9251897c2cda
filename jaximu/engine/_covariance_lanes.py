"""The covariance's structure-of-arrays implementations (docs/DESIGN.md, "Dispatch"): the
kernels of the table's ``soa_cov_analytic``, ``soa_cov_autodiff`` and ``soa_cov_chunked``
rows, registered with :func:`jaximu.engine._dispatch.implements`, each taking the
engine's :class:`CovarianceInputs` (the generic one is :mod:`jaximu.engine.errorstate`'s)."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from jaximu.engine import _chunked
from jaximu.engine import _dispatch as dispatch
from jaximu.engine._inputs import (
    flatten_batch,
    kernel_ready,
    kernel_samples,
    lane_values,
    soa_samples,
)
from jaximu.geometry.state import NavState
from jaximu.kernels import fast as _fast
from jaximu.kernels import lane_forms
from jaximu.schemes.integrators import get_scheme


class CovarianceInputs(NamedTuple):
    """The covariance engine's inputs once checked and dispatched, in the order every
    implementation reads them: ``state``, ``P0``, the samples and ``dt``, gravity ``g``,
    ``noise``, the broadcast ``batch`` shape, then the static options and the optional
    world rate, lever arm and sensor pose (``None`` when not given)."""

    state: NavState
    P0: Any
    gyro: Any
    accel: Any
    dt: Any
    g: Any
    noise: Any
    batch: tuple
    scheme: str
    jacobians: str
    omega: Any
    coriolis: str
    lever: Any
    save_all: bool
    attitude: str
    pose: Any
    tangential: bool


@dispatch.implements("covariance", "soa_cov_analytic", "soa_cov_autodiff")
def covariance_soa(inputs: CovarianceInputs):
    """Mean and covariance (final, or after every step with ``save_all``) on the
    :mod:`jaximu.kernels.fast` layout, any scheme with closed-form or autodiff blocks
    (:func:`jaximu.kernels.fast.cov_step_blocks`), the attitude form's state on lanes
    (:data:`jaximu.kernels.lane_forms.LANE_FORMS`); the block-structured update. ``pose``: the samples are
    a sensor's, moved into the body frame in the kernel's time chunks."""
    a = kernel_ready(inputs, soa=True)
    state, batch, scheme, save_all = a.state, a.batch, a.scheme, a.save_all
    gyro, accel, dt, pose, n_samples = soa_samples(scheme, a.gyro, a.accel, a.dt, a.pose, batch)
    (q, p, v, b_g, b_a), gyro_f, accel_f, dt_f, g_f = flatten_batch(
        batch, state, gyro, accel, dt, a.g
    )
    P0_f, var, omega, lever = _lane_inputs(a.P0, a.noise, a.omega, a.lever, batch, q.dtype)

    form = lane_forms.lane_form(a.attitude)
    x, p, v, P, *locked = _fast.propagate_cov(
        lane_forms.from_quat(form, q),
        p,
        v,
        b_g,
        b_a,
        P0_f,
        gyro_f,
        accel_f,
        dt_f,
        g_f,
        var,
        get_scheme(scheme),
        a.jacobians,
        omega,
        a.coriolis,
        lever,
        save_all,
        form,
        pose,
        a.tangential,
        n_samples,
    )
    q = lane_forms.to_quat(form, x)
    unflat = lambda x: x.reshape(tuple(batch) + x.shape[1:])  # noqa: E731
    lead = tuple(batch) + (q.shape[1:2] if save_all else ())  # (B, T, 4) with save_all
    st = NavState(
        unflat(q),
        unflat(p),
        unflat(v),
        jnp.broadcast_to(state.b_g[..., None, :] if save_all else state.b_g, lead + (3,)),
        jnp.broadcast_to(state.b_a[..., None, :] if save_all else state.b_a, lead + (3,)),
    )
    # Euler angles: the lanes that reached the pitch singularity (by the last step)
    return st, unflat(P), unflat(locked[0]) if locked else jnp.zeros(batch, bool)


def _lane_inputs(P0, noise, omega, lever, batch, dtype):
    """The covariance kernels' lanes of ``P0`` ``(B, 15, 15)``, the noise's variances
    (``(12,)`` shared or ``(B, 12)``) and a world rate and lever arm (shared ``(3,)`` or
    ``(B, 3)``; ``None`` when not given)."""
    B = int(np.prod(batch, dtype=np.int64))
    P0_f = jnp.broadcast_to(P0, tuple(batch) + (15, 15)).reshape((B, 15, 15))
    var = noise.variances(dtype)  # (..., 12)
    if var.ndim > 1:  # noise per batch element
        var = jnp.broadcast_to(var, tuple(batch) + (12,)).reshape((B, 12))
    omega, lever = (None if x is None else lane_values(x, batch) for x in (omega, lever))
    return P0_f, var, omega, lever


@dispatch.implements("covariance", "soa_cov_chunked")
def covariance_chunked(inputs: CovarianceInputs):
    """Mean and covariance of a few long sequences in time chunks side by side
    (:mod:`jaximu.engine._chunked`); a sensor's samples are moved into the body frame first
    (a chunk's own ends have no neighbours for the lever arm's rate derivative)."""
    a = kernel_ready(inputs, soa=False)
    state, batch, scheme, save_all = a.state, a.batch, a.scheme, a.save_all
    gyro, accel, dt = kernel_samples(scheme, a.gyro, a.accel, a.dt)
    (q, p, v, b_g, b_a), gyro_f, accel_f, dt_f, g_f = flatten_batch(
        batch, state, gyro, accel, dt, a.g
    )
    P0_f, var, omega, lever = _lane_inputs(a.P0, a.noise, a.omega, a.lever, batch, q.dtype)
    form = lane_forms.lane_form(a.attitude)
    x, p, v, P, locked = _chunked.covariance(
        get_scheme(scheme),
        form,
        lane_forms.from_quat(form, q),
        p,
        v,
        b_g,
        b_a,
        P0_f,
        gyro_f,
        accel_f,
        dt_f,
        g_f,
        var,
        a.jacobians,
        omega,
        a.coriolis,
        lever,
        save_all,
    )
    q = lane_forms.to_quat(form, x)
    lead = tuple(batch) + (q.shape[1:2] if save_all else ())

    def unflat(x):
        return x.reshape(tuple(batch) + x.shape[1:])

    def bias(b):
        return jnp.broadcast_to(b[..., None, :] if save_all else b, lead + (3,))

    st = NavState(unflat(q), unflat(p), unflat(v), bias(state.b_g), bias(state.b_a))
    return st, unflat(P), jnp.zeros(batch, bool) if locked is None else unflat(locked)
