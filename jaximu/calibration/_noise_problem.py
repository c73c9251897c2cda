"""The noise fit's problem: the windows of several lengths over one recording (``window_lengths``
of :func:`jaximu.calibration.calibration_problem`), their residuals and Jacobians, the
unit-density covariance bases and the densities' names (:class:`NoiseProblem`).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.calibration._checks import (
    _apply,
    _compiled,
    _device,
    _preintegrate_sequential,
)
from jaximu.calibration._fit import _unpack
from jaximu.calibration._model import (
    CalibrationError,
    CalibrationProblem,
    ImuCalibration,
    Reference,
    _interp,
    _preintegrate_mean,
)
from jaximu.calibration._noise_filter import state_space
from jaximu.engine.preintegration import compose, residual
from jaximu.errors import Fix, InputError
from jaximu.geometry import _checks as val
from jaximu.geometry import so3
from jaximu.geometry.noise import ImuNoise
from jaximu.geometry.state import ImuBias, NavState
from jaximu.schemes.integrators import compose_deltas

DENSITIES = (
    "gyroscope_noise_density",
    "accelerometer_noise_density",
    "gyroscope_random_walk",
    "accelerometer_random_walk",
)


NOISE_FIELDS = DENSITIES + ("reference_sigma",)
"""The noise parameters ``estimate=`` may name beside :data:`FIELDS` (isotropic densities,
and the reference's ``(σ_θ, σ_p, σ_v)``)."""


PER_AXIS_FIELDS = tuple(f"{n}_per_axis" for n in DENSITIES)
"""The densities fitted per axis (three values each, the IMU's x, y, z), which ``estimate=``
may name instead of their isotropic names in :data:`NOISE_FIELDS`, density by density."""


_REFERENCE_SIGMAS = ("reference_sigma_theta", "reference_sigma_p", "reference_sigma_v")
_SIGMAS = DENSITIES + _REFERENCE_SIGMAS


MIN_WINDOWS = 16
"""Fewest windows (of the shortest length) in a noise fit: the noises separate through the
residuals' correlation over consecutive windows, which a handful cannot show."""


@dataclasses.dataclass(frozen=True)
class NoiseProblem:
    """Windows of several lengths of one recording, for fitting the noise densities.

    Built by :func:`jaximu.calibration.calibration_problem` with ``window_lengths``.

    Attributes:
        base: the :class:`CalibrationProblem` of the shortest windows.
        multiples: each length in base windows (``window_lengths / shortest``), increasing.
        window_lengths: the lengths [s] (whole samples).
        kept: ``(K_all,)`` whether each window (every length in turn) is in the fit.
        start: ``(K_all,)`` each window's start, from the first keyframe [s].
        span: the recording's span ``T`` [s] (first to last keyframe of the base windows).
        cov_basis: ``(K_all, 4, 9, 9)`` ``σ_i0² C_ki``: each density at its initial value.
        bias_basis: ``(K_all, 2, 9, 9)`` ``σ_rw0² J Jᵀ`` (gyroscope, accelerometer).
        reference_basis: ``(K_all, 3, 9, 9)`` the reference's noise, one σ at a time.
        noise: the :class:`ImuNoise` given (initial values; per-axis values are kept).
        reference_sigma: ``(3,)`` the ``(σ_θ, σ_p, σ_v)`` given.
        rate_hz: the IMU's median sample rate [Hz].
        reference_velocity: the reference had velocities (else they are its positions'
            central differences, whose error ``σ_v`` absorbs).
        window_cov15: ``(K, 4, 15, 15)`` each base window's ``cov15`` with one density alone
            at its initial value.
        window_bias_jacobian: ``(K, 9, 6)`` each base window's bias Jacobian.
        window_reference_jacobian: ``(K, 9, 2, 9)`` each base window's residual in the
            reference's errors at its start and end.
        filter: ``(H, Qb, P0b, d)`` of :func:`jaximu.calibration._noise_filter.state_space` from those
            (the likelihood's state space, at the initial σ).
        initial: the :class:`ImuCalibration` the bases were computed at (``None``: the
            default), for the per-axis bases (:func:`noise_bases`).
    """

    base: CalibrationProblem
    multiples: tuple
    window_lengths: tuple
    kept: np.ndarray
    start: np.ndarray
    span: float
    cov_basis: np.ndarray
    bias_basis: np.ndarray
    reference_basis: np.ndarray
    noise: ImuNoise
    reference_sigma: np.ndarray
    rate_hz: float
    reference_velocity: bool
    window_cov15: np.ndarray
    window_bias_jacobian: np.ndarray
    window_reference_jacobian: np.ndarray
    filter: tuple
    initial: ImuCalibration | None = None

    @property
    def n_windows(self) -> tuple:
        """Windows in the fit, per length."""
        out, off = [], 0
        for m in self.multiples:
            k = self.base.n_windows // m
            out.append(int(self.kept[off : off + k].sum()))
            off += k
        return tuple(out)


def _isotropic(noise: ImuNoise) -> np.ndarray:
    """The four densities as scalars (per-axis values: their root mean square)."""
    return np.array(
        [float(np.sqrt(np.mean(np.asarray(getattr(noise, n), np.float64) ** 2))) for n in DENSITIES]
    )


def _check_lengths(window_lengths, period):
    """``window_lengths`` as sample counts ``(W, m_1, …)``: the base window ``W`` samples and
    each length a whole multiple of it."""
    try:
        lengths = np.asarray(window_lengths, np.float64)
    except (TypeError, ValueError):
        lengths = None
    if (
        lengths is None
        or lengths.ndim != 1
        or lengths.size == 0
        or not np.all(np.isfinite(lengths) & (lengths > 0))
    ):
        raise InputError(
            f"window_lengths must be window lengths in seconds, positive, got {window_lengths!r}",
            [Fix("window_lengths", (0.25, 1, 4))],
        )
    lengths = np.sort(lengths)
    W = int(round(lengths[0] / period))
    if W < 1:
        raise InputError(
            f"the shortest window length, {lengths[0]:g} s, is shorter than one "
            f"sample interval ({period:.3g} s)",
            [Fix("window_lengths", phrase=f"{{}} of {period:.3g} s or longer")],
        )
    ratio = lengths / (W * period)
    m = np.round(ratio).astype(int)
    bad = np.abs(ratio - m) > 1e-3 * ratio
    if bad.any():
        raise InputError(
            f"the window length {lengths[bad][0]:g} s is not a whole multiple of the shortest "
            f"length {W * period:g} s: a longer window is composed of whole base windows",
            [Fix("window_lengths", (0.25, 1, 4))],
        )
    return W, tuple(sorted({int(x) for x in m}))


def check_window_span(longest: float, span: float, shortest: float):
    """Refuse window lengths whose longest exceeds ``span`` [s], the time the recording and
    the reference share (or that the base windows cover), naming ``window_lengths``."""
    if longest > span * (1 + 1e-9):
        raise InputError(
            f"the longest window length, {longest:g} s, is longer than the {span:.4g} s "
            "the recording and the reference share (no window of it fits)",
            [
                Fix(
                    "window_lengths",
                    phrase=f"lengths of {shortest:g} … {span:.3g} s in {{}} (or a longer "
                    "recording)",
                )
            ],
        )


def _unit_noises(noise0, dtype, per_axis=False):
    """One :class:`ImuNoise` per density: that density at its initial value, the rest 0; or
    (``per_axis``) one per density and axis (density ``i``'s axis ``a`` at ``3 i + a``: that
    axis alone at the density's initial value)."""
    out = []
    for i in range(4):
        if not per_axis:
            vals = [jnp.zeros((), dtype)] * 4
            vals[i] = jnp.asarray(getattr(noise0, DENSITIES[i]), dtype)
            out.append(ImuNoise(*vals))
            continue
        for a in range(3):
            vals = [jnp.zeros(3, dtype)] * 4
            vals[i] = jnp.asarray(getattr(noise0, DENSITIES[i]), dtype) * jnp.eye(3, dtype=dtype)[a]
            out.append(ImuNoise(*vals))
    return out


def _fold(pims, m):
    """``(K, m)``-batched :class:`Preintegrated` → the ``(K,)`` composition of each row."""
    first = jax.tree_util.tree_map(lambda x: x[:, 0], pims)
    rest = jax.tree_util.tree_map(lambda x: jnp.moveaxis(x[:, 1:], 1, 0), pims)
    out, _ = jax.lax.scan(lambda acc, p: (compose(acc, p), None), first, rest)
    return out


def _rows(tree, m):
    """Leading axis ``K m`` (or more: the rest is dropped) → ``(K, m)``."""
    K = jax.tree_util.tree_leaves(tree)[0].shape[0] // m
    return jax.tree_util.tree_map(lambda x: x[: K * m].reshape((K, m) + x.shape[1:]), tree)


def _long_window_bases(gyro, accel, dt, noise0, multiples, *, scheme, fast, per_axis=False):
    """``(cov, jac, cov15)``: per window of every length (concatenated), ``(D, 9, 9)``
    covariances from each density alone (``D = 4``; per axis, ``D = 12``:
    :func:`_unit_noises`) and the ``(9, 6)`` bias Jacobian; per base window the whole
    ``(D, 15, 15)`` ``cov15`` (the bias random walk's block and its correlation with the
    window's noise: the filter's); ``gyro``, ``accel``, ``dt``: the ``K`` base windows'
    corrected samples."""
    dtype = gyro.dtype
    zero3 = jnp.zeros(3, dtype)

    def one(unit):
        pim = _preintegrate_sequential(
            gyro, accel, dt, ImuBias(zero3, zero3), unit, scheme=scheme, fast=fast
        )
        per_m = [pim if m == 1 else _fold(_rows(pim, m), m) for m in multiples]
        cov = jnp.concatenate([p.cov15[:, :9, :9] for p in per_m])
        jac = jnp.concatenate([p.transition[:, :9, 9:15] for p in per_m])
        return cov, jac, pim.cov15

    # one trace for the four (or twelve) unit noises, batched: their means and Jacobians are
    # the same; a loop would put four copies of the preintegration's scan in the program
    # (about 5× the compile time)
    units = _unit_noises(noise0, dtype, per_axis)
    cov, jac, full = jax.vmap(one)(jax.tree_util.tree_map(lambda *x: jnp.stack(x), *units))
    return jnp.moveaxis(cov, 0, 1), jac[0], jnp.moveaxis(full, 0, 1)


def noise_problem(
    build,
    t,
    gyro,
    accel,
    reference,
    noise,
    *,
    window_lengths,
    scheme,
    model,
    reference_sigma,
    initial,
    windows_per_group,
    check,
    extrinsics,
    omega_coriolis,
) -> NoiseProblem:
    """:func:`jaximu.calibration.calibration_problem` with ``window_lengths`` (``build`` is
    that function, called for the base windows)."""
    if model != "preintegration":
        raise InputError(
            "window_lengths: the noise densities are fitted with the "
            f"preintegration residual, got model={model!r}",
            [Fix("model", "preintegration")],
        )
    if extrinsics:
        raise InputError(
            "window_lengths: the noise fit does not estimate extrinsics (a lever "
            "arm adds the gyro's noise to the specific force): calibrate q_BS, "
            "p_BS first, then pass the rotated samples",
            [Fix("extrinsics", False)],
        )
    t_np = val.check_times("t", t, 3, val.TIMES_FIX)
    period = float(np.median(np.diff(t_np)))
    W, multiples = _check_lengths(window_lengths, period)
    if not isinstance(reference, Reference):
        raise ValueError(
            f"reference must be a jaximu.calibration.Reference, got {type(reference).__name__}"
        )
    rt = val.check_times("reference.t", reference.t, 2, val.TIMES_FIX)
    shared = min(t_np[-1], rt[-1]) - max(t_np[0], rt[0])  # an upper bound: before any work
    check_window_span(max(multiples) * W * period, shared, W * period)
    velocity = reference.v is not None
    if not velocity:  # central differences at the reference's own rate
        rp = val.as_numbers("reference.p", reference.p)
        rt = val.as_numbers("reference.t", reference.t)
        if rp.ndim == 2 and len(rt) == len(rp) and len(rt) >= 2 and np.all(np.diff(rt) > 0):
            reference = Reference(
                reference.t, reference.q, reference.p, np.gradient(rp, rt, axis=0)
            )
    base = build(
        t,
        gyro,
        accel,
        reference,
        noise,
        keyframe_interval=W * period,
        scheme=scheme,
        model=model,
        reference_sigma=reference_sigma,
        initial=initial,
        windows_per_group=windows_per_group,
        check=check,
        extrinsics=False,
        omega_coriolis=omega_coriolis,
    )
    dtype = base.gyro.dtype
    K0 = base.n_windows
    check_window_span(max(multiples) * W * period, K0 * W * period, W * period)
    flat = lambda x: np.asarray(x).reshape((-1,) + x.shape[2:])[:K0]  # noqa: E731
    init = initial if initial is not None else ImuCalibration.default(dtype=dtype)
    g_c, a_c = _compiled(_apply, True)(init, flat(base.gyro), flat(base.accel))
    noise0 = ImuNoise(*(_device(x, dtype) for x in _isotropic(noise)))
    cov, jac, cov15 = _compiled(_long_window_bases, True, ("multiples", "scheme", "fast"))(
        g_c, a_c, flat(base.dt), noise0, multiples, scheme=scheme, fast=False
    )
    cov, jac = np.asarray(cov, np.float64), np.asarray(jac, np.float64)
    cov15 = np.asarray(cov15, np.float64)
    s0 = _isotropic(noise)
    bias_basis = np.stack(
        [
            s0[2] ** 2 * jac[:, :, :3] @ np.swapaxes(jac[:, :, :3], 1, 2),
            s0[3] ** 2 * jac[:, :, 3:] @ np.swapaxes(jac[:, :, 3:], 1, 2),
        ],
        1,
    )
    kept0 = base.kept
    t_start = np.asarray(base.t_start, np.float64).reshape(-1)[:K0]
    t_end = np.asarray(base.t_end, np.float64).reshape(-1)[:K0]
    kept_parts, start_parts = [], []
    for m in multiples:
        K = K0 // m
        kept_parts.append(kept0[: K * m].reshape(K, m).all(1))
        start_parts.append(t_start[: K * m : m])
    kept, start = np.concatenate(kept_parts), np.concatenate(start_parts)
    sig = np.asarray(reference_sigma, np.float64)
    # the reference's errors at both ends, independent, through the residual's exact
    # linearisation: a tilt error δθ_i also turns gravity, g Δt δθ in r_v (g Δt² δθ / 2 in
    # r_p), which outgrows 2σ_v² beyond a fraction of a second
    Jr, F = (
        np.asarray(x, np.float64)
        for x in _compiled(_model_jacobians, True, ("multiples",))(init, base, multiples=multiples)
    )
    F = F[:K0]
    ref_basis = np.stack(
        [
            sig[j] ** 2
            * np.einsum("kaei,kbei->kab", Jr[..., 3 * j : 3 * j + 3], Jr[..., 3 * j : 3 * j + 3])
            for j in range(3)
        ],
        1,
    )
    for k, m in enumerate(multiples):
        if not kept[_length_slice(multiples, K0, k)].any():
            raise CalibrationError(
                f"no window of {m * W * period:g} s lies between the reference's gaps",
                [Fix("window_lengths", phrase="shorter lengths in {}")],
            )
    return NoiseProblem(
        base=base,
        multiples=multiples,
        window_lengths=tuple(m * W * period for m in multiples),
        kept=kept,
        start=start,
        span=float(t_end[-1] - t_start[0]),
        cov_basis=cov,
        bias_basis=bias_basis,
        reference_basis=ref_basis,
        noise=noise,
        reference_sigma=sig,
        rate_hz=1.0 / period,
        reference_velocity=velocity,
        window_cov15=cov15,
        window_bias_jacobian=F,
        window_reference_jacobian=Jr[:K0],
        filter=state_space(cov15, F, Jr[:K0], np.where(sig > 0, sig, 1.0)),
        initial=initial,
    )


def _length_slice(multiples, K0, k):
    off = sum(K0 // m for m in multiples[:k])
    return slice(off, off + K0 // multiples[k])


class NoiseBases(NamedTuple):
    """The covariance bases one fit uses: one per density (isotropic, ``D = 4``) or per
    density and axis (``D = 12``, density ``i``'s axis ``a`` at ``3 i + a``), then the
    reference's ``σ_θ, σ_p, σ_v``.

    Attributes:
        per_axis: whether the densities' bases are per axis.
        labels: ``(D + 3,)`` each σ's name (``gyroscope_noise_density[y]``, …).
        given: ``(D + 3,)`` the σ given to the problem (per axis: each axis's value; else
            the axes' root mean square).
        scale: ``(D + 3,)`` the σ the bases were built at (``σ = scale · e^u``).
        u0: ``(D + 3,)`` ``log(given / scale)`` (``-inf`` for a σ given as 0).
        cov_basis: ``(K_all, D, 9, 9)``; ``bias_basis``: ``(K_all, 2 D / 4, 9, 9)`` (the
            gyroscope's random walk, then the accelerometer's); ``filter``: ``(H, Qb, P0b, d)``,
            as :class:`NoiseProblem`'s.
    """

    per_axis: bool
    labels: tuple
    given: np.ndarray
    scale: np.ndarray
    u0: np.ndarray
    cov_basis: np.ndarray
    bias_basis: np.ndarray
    filter: tuple


def noise_bases(problem: NoiseProblem, per_axis: bool) -> NoiseBases:
    """The problem's isotropic bases, or (``per_axis``) the twelve per-axis ones: built here,
    at the same calibration and starting densities (each axis at its density's root mean
    square), the covariance being linear in the twelve per-axis variances."""
    ref = problem.reference_sigma
    ref_scale = np.where(ref > 0, ref, 1.0)
    with np.errstate(divide="ignore"):
        u_ref = np.log(ref / ref_scale)
    s0 = _isotropic(problem.noise)
    if not per_axis:
        return NoiseBases(
            False,
            _SIGMAS,
            np.concatenate([s0, ref]),
            np.concatenate([s0, ref_scale]),
            np.concatenate([np.zeros(4), u_ref]),
            problem.cov_basis,
            problem.bias_basis,
            problem.filter,
        )
    base = problem.base
    dtype = base.gyro.dtype
    K0 = base.n_windows
    flat = lambda x: np.asarray(x).reshape((-1,) + x.shape[2:])[:K0]  # noqa: E731
    init = problem.initial if problem.initial is not None else ImuCalibration.default(dtype=dtype)
    g_c, a_c = _compiled(_apply, True)(init, flat(base.gyro), flat(base.accel))
    noise0 = ImuNoise(*(_device(x, dtype) for x in s0))
    cov, jac, cov15 = _compiled(
        _long_window_bases, True, ("multiples", "scheme", "fast", "per_axis")
    )(
        g_c,
        a_c,
        flat(base.dt),
        noise0,
        problem.multiples,
        scheme=base.scheme,
        fast=False,
        per_axis=True,
    )
    cov, jac = np.asarray(cov, np.float64), np.asarray(jac, np.float64)
    bias = np.stack(
        [s0[2 + c // 3] ** 2 * jac[:, :, c, None] * jac[:, None, :, c] for c in range(6)], 1
    )
    given = np.stack(
        [
            np.broadcast_to(np.asarray(getattr(problem.noise, n), np.float64), (3,))
            for n in DENSITIES
        ]
    )
    scale = np.repeat(s0, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        u_d = np.where(scale > 0, np.log(given.reshape(-1) / np.where(scale > 0, scale, 1.0)), 0.0)
    labels = tuple(f"{n}[{'xyz'[a]}]" for n in DENSITIES for a in range(3)) + _REFERENCE_SIGMAS
    return NoiseBases(
        True,
        labels,
        np.concatenate([given.reshape(-1), ref]),
        np.concatenate([scale, ref_scale]),
        np.concatenate([u_d, u_ref]),
        cov,
        bias,
        state_space(
            np.asarray(cov15, np.float64),
            problem.window_bias_jacobian,
            problem.window_reference_jacobian,
            ref_scale,
        ),
    )


# --------------------------------------------------------------------------- the residuals


def _all_residuals(calib, problem: CalibrationProblem, multiples, d_i=None, d_j=None):
    """``(K_all, 9)`` raw residuals ``[r_θ, r_p, r_v]`` of the windows of every length
    (``multiples`` of the base windows, in turn), at the calibration ``calib``; ``d_i``,
    ``d_j``: ``(9,)`` errors ``[δθ, δp, δv]`` of the reference at every window's start
    (end), ``q ⊗ Exp(δθ)``, ``p + δp``, ``v + δv`` (for its Jacobian in them)."""
    K0 = problem.n_windows
    flat = lambda x: x.reshape((-1,) + x.shape[2:])[:K0]  # noqa: E731
    gyro_c, accel_c = calib.apply(flat(problem.gyro), flat(problem.accel))
    pim = _preintegrate_mean(gyro_c, accel_c, flat(problem.dt), problem.scheme)
    t_key = jnp.concatenate([flat(problem.t_start), flat(problem.t_end)[-1:]])
    q, p, v = _interp(
        t_key + calib.time_offset, problem.ref_t, problem.ref_q, problem.ref_p, problem.ref_v
    )
    deltas = (pim.delta_q, pim.delta_p, pim.delta_v, pim.delta_t)
    out = []
    for m in multiples:
        K = K0 // m
        d = _rows(deltas, m)
        if m > 1:
            first = tuple(x[:, 0] for x in d)
            rest = tuple(jnp.moveaxis(x[:, 1:], 1, 0) for x in d)
            d, _ = jax.lax.scan(lambda a, b: (compose_deltas(a, b), None), first, rest)
        else:
            d = tuple(x[:, 0] for x in d)
        dq, dp, dv, dt = d
        zero = jnp.zeros_like(dv)
        win = dataclasses.replace(
            pim,
            delta_t=dt,
            delta_q=dq,
            delta_v=dv,
            delta_p=dp,
            transition=pim.transition[:K],
            cov15=pim.cov15[:K],
            cov=pim.cov[:K],
            bias_hat=ImuBias(zero, zero),
        )
        i, j = slice(0, K * m, m), slice(m, K * m + 1, m)
        state_i = _perturbed(q[i], p[i], v[i], d_i)
        state_j = _perturbed(q[j], p[j], v[j], d_j)
        out.append(
            residual(
                state_i, state_j, win, gravity=calib.gravity, omega_coriolis=problem.omega_coriolis
            )[..., :9]
        )
    return jnp.concatenate(out)


def _perturbed(q, p, v, d):
    zero = jnp.zeros_like(p)
    if d is None:
        return NavState(q, p, v, zero, zero)
    return NavState(
        so3.quat_mul(q, so3.exp(jnp.broadcast_to(d[:3], p.shape))),
        p + d[3:6],
        v + d[6:9],
        zero,
        zero,
    )


def _model_jacobians(calib, problem, multiples):
    """``(J_ref, F)``: ``(K_all, 9, 2, 9)`` each window's residual in the reference's errors
    at its start and at its end, and ``(K_all, 9, 6)`` the model's ``F = ∂r/∂δb``
    (``δb = b_true - b̂``: ``-∂r/∂b̂``, through the residual as computed; the midpoint
    scheme's analytic transition is its first-order approximation). One forward-mode pass,
    24 tangents (one compilation)."""

    def f(x):
        d, db = x[:18].reshape(2, 9), x[18:]
        c = dataclasses.replace(calib, b_g=calib.b_g - db[:3], b_a=calib.b_a - db[3:])
        return _all_residuals(c, problem, multiples, d[0], d[1])

    J = jax.jacfwd(f)(jnp.zeros(24, problem.gyro.dtype))
    return J[..., :18].reshape(J.shape[:-1] + (2, 9)), J[..., 18:]


def _residuals_and_jacobian(z, init_vec, problem, multiples, layout, scale):
    """Scaled residuals ``(K_all, 9)`` and their Jacobian ``(K_all, 9, n)`` in the calibration's
    normalised coordinates ``z`` (forward mode: ``n`` ≤ 20 tangents)."""

    def res(zc):
        calib, _ = _unpack(zc, init_vec, problem.velocities, layout)
        r = _all_residuals(calib, problem, multiples) / scale
        return r, r

    if z.shape[0] == 0:
        r = res(z)[0]
        return r, jnp.zeros(r.shape + (0,), r.dtype)
    J, r = jax.jacfwd(res, has_aux=True)(z)
    return r, J
