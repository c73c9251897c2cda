"""The set-up of a Monte Carlo study: the position fixes' type, the arguments checked, the true
trajectory's samples and states, the filter's start and the draws' keys, gathered in a
:class:`_Study`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.engine.errorstate import _check_cov, propagate_covariance
from jaximu.engine.propagate import _propagate
from jaximu.errors import Fix, InputError
from jaximu.geometry import _checks as val
from jaximu.geometry import _tolerances
from jaximu.geometry.noise import check_noise
from jaximu.geometry.state import NavState, boxminus
from jaximu.kernels import rng as _rng
from jaximu.kernels.device import host_device
from jaximu.kernels.montecarlo_lanes import N_STREAMS
from jaximu.schemes.integrators import SCHEME_OBJECTS, SCHEMES
from jaximu.studies.simulate import Trajectory, ideal_imu, true_states


class PositionFix(NamedTuple):
    """A position measurement ``z = p + ν``, ``ν ~ N(0, R)``, for the filter study.

    Attributes:
        sigma: standard deviation of each axis [m], a scalar or ``(3,)``, ``> 0``.
    """

    sigma: float | tuple = 0.1


# --------------------------------------------------------------------------- set-up


class _Study(NamedTuple):
    consts: dict  # device constants of the kernel
    scheme: str
    seg: tuple
    rec: np.ndarray  # recorded step indices
    times: np.ndarray
    P_rec: np.ndarray | None  # open loop: the linearised covariance at the recorded times
    disc: np.ndarray
    dtype: object
    filt: bool


def _prepare(
    trajectory,
    times,
    P0,
    noise,
    key,
    *,
    scheme,
    gravity,
    b_g0,
    b_a0,
    record_every,
    dtype,
    update_every=None,
    measurement=None,
    nees=True,
):
    """Validate the inputs and build the kernel's constants (shared by :func:`monte_carlo`
    and :func:`sample_run`). ``nees``: refuse an open-loop study whose NEES is undefined at
    every recorded time (a single run's errors do not need it)."""
    if not isinstance(trajectory, Trajectory):
        raise ValueError(
            "trajectory must be a jaximu.simulate.Trajectory (e.g. "
            f"jaximu.simulate.circle()), got {type(trajectory).__name__}"
        )
    if isinstance(noise, tuple):
        if len(noise) != 2:
            raise ValueError(
                "noise must be an ImuNoise or a pair (draw, predict) of them, got a "
                f"tuple of {len(noise)}"
            )
        draw_noise, model_noise = noise
    else:
        draw_noise = model_noise = noise
    record_every = val.check_int("record_every", record_every, 1)
    filt = update_every is not None
    if filt:
        record_every = val.check_int("update_every", update_every, 1)
        measurement = PositionFix() if measurement is None else measurement
        if not isinstance(measurement, PositionFix):
            raise ValueError(
                "measurement must be a jaximu.montecarlo.PositionFix, got "
                f"{type(measurement).__name__}"
            )
        sigma = val.as_numbers("measurement.sigma", measurement.sigma)
        meas_sd = np.broadcast_to(sigma, (3,)) if sigma.ndim == 0 else sigma
        if meas_sd.shape != (3,) or not np.all(np.isfinite(meas_sd) & (meas_sd > 0)):
            raise ValueError(
                f"measurement.sigma must be positive and finite, a scalar or (3,), "
                f"got {measurement.sigma!r}"
            )
    elif measurement is not None:
        raise InputError(
            "measurement is used only by the filter study, and update_every is "
            "None (open loop): it would be ignored",
            [
                Fix("update_every", phrase="{}=N (a measurement every N steps)"),
                Fix("measurement", None),
            ],
        )
    val.check_choice("scheme", scheme, SCHEMES)
    dtype = val.compute_dtype("dtype", dtype) if dtype is not None else jnp.result_type(float)
    times = val.check_times("times", times)
    if filt and record_every > len(times) - 1:
        raise InputError(
            f"update_every = {record_every} is more than the {len(times) - 1} "
            "steps of times: no update would happen",
            [Fix("update_every", len(times) - 1, "")],
            lead="pass at most",
        )
    P0 = val.as_numbers("P0", P0)
    if P0.shape != (15, 15):
        raise ValueError(f"P0 must have shape (15, 15), got {P0.shape}")
    _check_cov(P0, dtype)
    lam, V = np.linalg.eigh(0.5 * (P0 + P0.T))
    L0 = V * np.sqrt(np.clip(lam, 0, None))  # L0 L0ᵀ = P0, also if singular
    model_noise = check_noise(model_noise, dtype)
    draw_noise = check_noise(draw_noise, dtype)
    val.check_unbatched_noise(model_noise, "a Monte Carlo study")
    val.check_unbatched_noise(draw_noise, "a Monte Carlo study")
    g = val.gravity_vector(gravity, dtype)
    if g.ndim != 1:
        raise ValueError(f"gravity must be a magnitude or a (3,) vector, got shape {g.shape}")
    b_g0 = np.zeros(3) if b_g0 is None else val.check_array("b_g0", b_g0, (3,))
    b_a0 = np.zeros(3) if b_a0 is None else val.check_array("b_a0", b_a0, (3,))
    # The reference is one trajectory's sequential work: on an accelerator it runs on the
    # host's CPU (device.host_device), where its kernels compile in a few seconds (the
    # accelerator's time-chunked ones for one trajectory took 8-13 s on an H100,
    # docs/DESIGN.md section 3); the study moves the constants to its devices.
    with host_device():
        keys = _rng.stream_keys(key, N_STREAMS)
        T = len(times) - 1
        dt64 = np.diff(times)
        dt = jnp.asarray(dt64, dtype)
        t = jnp.asarray(times, dtype)
        gyro, accel = ideal_imu(trajectory, t, gravity)
        truth = true_states(trajectory, t)
        b_g0 = jnp.asarray(b_g0, dtype)
        b_a0 = jnp.asarray(b_a0, dtype)
        x0 = NavState(truth.q[0], truth.p[0], truth.v[0], b_g0, b_a0)
        rec = np.unique(np.r_[np.arange(record_every - 1, T, record_every), T - 1])
        n_seg = T // record_every
        seg = (record_every, n_seg, T - n_seg * record_every)
        rec_j = jnp.asarray(rec)

        # The reference: noise-free propagation of the exact signals (with the true biases added
        # to the samples and to the state, which cancel), and (open loop) the linearised
        # covariance; the filter study's runs carry their own.
        clean = _propagate(
            x0,
            gyro + b_g0,
            accel + b_a0,
            dt,
            g,
            scheme=scheme,
            attitude="quaternion",
            save_all=True,
        )[0]
        P_rec = W = None
        if not filt:
            _, P = propagate_covariance(
                x0, jnp.asarray(P0, dtype), gyro + b_g0, accel + b_a0, dt, model_noise, scheme
            )
            P_rec = np.asarray(P, np.float64)[rec]
            # NEES = |W e|², W = L⁻¹, P = L Lᵀ, where P is positive definite to the dtype's
            # precision; elsewhere the NEES is undefined (NaN in the result, W = 0 meanwhile)
            defined = _tolerances.definiteness(P_rec, dtype)[0]
            if nees and not defined.any():
                k = len(rec) - 1
                _tolerances.check_definite(
                    f"the predicted covariance at times[{rec[k] + 1}] = {times[rec[k] + 1]:g} "
                    "(and at every recorded time)",
                    P_rec[k],
                    dtype,
                    axes=_tolerances.ERROR_AXES,
                    what="the NEES eᵀ P⁻¹ e, undefined at every recorded time",
                    fix="P0 with the noise leaves some error direction without variance for the "
                    "whole study; give P0 positive variances on every axis (e.g. P0 = "
                    "diag(σ²), σ > 0), or the noise positive random walks",
                )
            W = np.zeros_like(P_rec)
            W[defined] = np.linalg.inv(np.linalg.cholesky(P_rec[defined]))
            W = jnp.asarray(W, dtype)
        truth_rec = jax.tree_util.tree_map(lambda x: x[rec_j + 1], truth)
        clean_rec = jax.tree_util.tree_map(lambda x: x[rec_j], clean)
        disc = np.asarray(
            boxminus(clean_rec, truth_rec.replace(b_g=clean_rec.b_g, b_a=clean_rec.b_a)), np.float64
        )

        # per-sample white-noise std (sample j held over dt_j; the last sample over dt_{T-1}) and
        # per-step bias-walk std, in float64 then rounded once
        sg, sa, sbg, sba = (
            np.broadcast_to(np.asarray(x, np.float64), (3,))
            if np.ndim(x) == 0
            else np.asarray(x, np.float64)
            for x in (
                draw_noise.gyroscope_noise_density,
                draw_noise.accelerometer_noise_density,
                draw_noise.gyroscope_random_walk,
                draw_noise.accelerometer_random_walk,
            )
        )
        dt_s = np.r_[dt64, dt64[-1]]
        sd = np.concatenate([sg, sa])[None] / np.sqrt(dt_s)[:, None]  # (T+1, 6)
        sw = np.concatenate([sbg, sba])[None] * np.sqrt(dt64)[:, None]  # (T, 6)
        nxt = SCHEME_OBJECTS[scheme].uses_next_sample
        sl = slice(1, None) if nxt else slice(0, T)  # the sample each step draws
        consts = dict(
            keys=keys,
            L0=jnp.asarray(L0, dtype),
            x0=x0.replace(b_g=b_g0 * 0, b_a=b_a0 * 0),
            dt=dt,
            g=g,
            w_in=gyro[sl],
            a_in=accel[sl],
            sd_in=jnp.asarray(sd[sl], dtype),
            w0=gyro[0],
            a0=accel[0],
            sd0=jnp.asarray(sd[0], dtype),
            sw=jnp.asarray(sw, dtype),
            ref=(clean_rec.q, clean_rec.p, clean_rec.v),
            W=W,
            gyro=gyro,
            accel=accel,
            sd=jnp.asarray(sd, dtype),
            b0=jnp.concatenate([b_g0, b_a0]),
        )
        if filt:
            consts.update(
                qc=model_noise.discrete_variances(dt),
                P0=jnp.asarray(P0, dtype),
                meas_sd=jnp.asarray(meas_sd, dtype),
                meas_R=jnp.asarray(np.diag(meas_sd**2), dtype),
            )
        return _Study(consts, scheme, seg, rec, times[rec + 1], P_rec, disc, dtype, filt)
