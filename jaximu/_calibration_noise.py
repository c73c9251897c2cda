"""The IMU's noise densities by maximum likelihood (:func:`jaximu.calibration.calibrate` on a
problem built with ``window_lengths``): the windows, their covariance bases, the fit and its
model checks.

Windows. The recording is cut into windows of the shortest length (the *base* windows, a
:class:`CalibrationProblem` of :func:`calibration_problem`). Their residuals' exact joint
likelihood (:mod:`jaximu._noise_filter`: a state space carrying the bias deviation and the
reference's keyframe errors, evaluated by a Kalman filter) is what the fit maximises; it
needs per base window the preintegration covariance ``cov15`` with each density alone (the
covariance is linear in the squared densities: ``Q_c = diag(σ²)/dt``), the residual's bias
Jacobian and its Jacobian in the reference's errors at both ends.

A window of ``m`` times the base length is ``m`` consecutive base windows, its preintegrated
deltas their composition (:func:`jaximu.integrators.compose_deltas`, Forster et al.) and its
covariance and bias Jacobian those of :func:`jaximu.compose`. The longer lengths do not add
information to the exact likelihood (their residuals are functions of the base windows'):
they check the fitted model at longer time scales, each window whitened by its own marginal
covariance under the model (:func:`length_check`),

    Σ_k = Σ_i σ_i² C_ki  +  t_k (σ_bg² J_g J_gᵀ + σ_ba² J_a J_aᵀ)  +  R_k(σ_θ, σ_p, σ_v),

``C_ki`` the window's 9×9 covariance with density ``i`` alone at 1, ``J`` its bias
Jacobians, ``t_k`` its start (the bias drifts from its value at the first keyframe, the fit's
constant bias) and ``R_k`` the reference's noise at both ends.

Fit. Densities in log coordinates ``σ_i = σ_i0 exp(u_i)`` (positive), the calibration's
fields (biases, …) in the normalised coordinates of the rest of the calibration; damped
Newton with the residuals linearised in the fields (Gauss–Newton there, exact in ``u``), the
gradient and Hessian by autodiff through the filter, each step accepted when the true NLL
falls. Standard errors: the inverse Hessian at the optimum (observed information), mapped to
the densities by ``dσ = σ du``.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaximu import _validation as val
from jaximu import so3
from jaximu._calibration_checks import (
    QUICK_COMPILE_SAMPLES,
    _apply,
    _compiled,
    _preintegrate_sequential,
)
from jaximu._calibration_fit import _Layout, _n_free, _scale_vector, _unpack
from jaximu._calibration_model import (
    FIELDS,
    CalibrationError,
    CalibrationProblem,
    _interp,
    _preintegrate_mean,
)
from jaximu._noise_filter import state_space
from jaximu.errors import Fix, InputError
from jaximu.integrators import compose_deltas
from jaximu.noise import ImuNoise
from jaximu.preintegration import compose, residual
from jaximu.state import ImuBias, NavState

DENSITIES = ("gyroscope_noise_density", "accelerometer_noise_density",
             "gyroscope_random_walk", "accelerometer_random_walk")
NOISE_FIELDS = DENSITIES + ("reference_sigma",)
"""The noise parameters ``estimate=`` may name beside :data:`FIELDS` (isotropic densities,
and the reference's ``(σ_θ, σ_p, σ_v)``)."""
_SIGMAS = DENSITIES + ("reference_sigma_theta", "reference_sigma_p", "reference_sigma_v")
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
        filter: ``(H, Qb, P0b, d)`` of :func:`jaximu._noise_filter.state_space` from those
            (the likelihood's state space, at the initial σ).
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

    @property
    def n_windows(self) -> tuple:
        """Windows in the fit, per length."""
        out, off = [], 0
        for m in self.multiples:
            k = self.base.n_windows // m
            out.append(int(self.kept[off:off + k].sum()))
            off += k
        return tuple(out)


def _isotropic(noise: ImuNoise) -> np.ndarray:
    """The four densities as scalars (per-axis values: their root mean square)."""
    return np.array([float(np.sqrt(np.mean(np.asarray(getattr(noise, n), np.float64) ** 2)))
                     for n in DENSITIES])


def _check_lengths(window_lengths, period):
    """``window_lengths`` as sample counts ``(W, m_1, …)``: the base window ``W`` samples and
    each length a whole multiple of it."""
    try:
        lengths = np.asarray(window_lengths, np.float64)
    except (TypeError, ValueError):
        lengths = None
    if lengths is None or lengths.ndim != 1 or not np.all(np.isfinite(lengths) & (lengths > 0)):
        raise InputError(f"window_lengths must be window lengths in seconds, positive, got "
                         f"{window_lengths!r}",
                         [Fix("window_lengths", (0.25, 1, 4))])
    lengths = np.sort(lengths)
    W = int(round(lengths[0] / period))
    if W < 1:
        raise InputError(f"window_lengths: the shortest, {lengths[0]:g} s, is shorter than one "
                         f"sample interval ({period:.3g} s)",
                         [Fix("window_lengths", phrase=f"{{}} of {period:.3g} s or longer")])
    ratio = lengths / (W * period)
    m = np.round(ratio).astype(int)
    bad = np.abs(ratio - m) > 1e-3 * ratio
    if bad.any():
        raise InputError(
            f"window_lengths: {lengths[bad][0]:g} s is not a whole multiple of the shortest "
            f"length {W * period:g} s: a longer window is composed of whole base windows",
            [Fix("window_lengths", (0.25, 1, 4))])
    return W, tuple(sorted({int(x) for x in m}))


def _unit_noises(noise0, dtype):
    """One :class:`ImuNoise` per density: that density at its initial value, the rest 0."""
    out = []
    for i in range(4):
        vals = [jnp.zeros((), dtype)] * 4
        vals[i] = jnp.asarray(getattr(noise0, DENSITIES[i]), dtype)
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
    return jax.tree_util.tree_map(lambda x: x[:K * m].reshape((K, m) + x.shape[1:]), tree)


def _long_window_bases(gyro, accel, dt, noise0, multiples, *, scheme, fast):
    """``(cov, jac, cov15)``: per window of every length (concatenated), ``(4, 9, 9)``
    covariances from each density alone and the ``(9, 6)`` bias Jacobian; per base window
    the whole ``(4, 15, 15)`` ``cov15`` (the bias random walk's block and its correlation
    with the window's noise: the filter's); ``gyro``, ``accel``, ``dt``: the ``K`` base
    windows' corrected samples."""
    dtype = gyro.dtype
    zero3 = jnp.zeros(3, dtype)
    covs, jac, full = [], [], []
    for i, unit in enumerate(_unit_noises(noise0, dtype)):
        pim = _preintegrate_sequential(gyro, accel, dt, ImuBias(zero3, zero3), unit,
                                       scheme=scheme, fast=fast)
        per_m = []
        for m in multiples:
            per_m.append(pim if m == 1 else _fold(_rows(pim, m), m))
        covs.append(jnp.concatenate([p.cov15[:, :9, :9] for p in per_m]))
        full.append(pim.cov15)
        if i == 0:
            jac = jnp.concatenate([p.transition[:, :9, 9:15] for p in per_m])
    return jnp.stack(covs, 1), jac, jnp.stack(full, 1)


def noise_problem(build, t, gyro, accel, reference, noise, *, window_lengths, scheme, model,
                  reference_sigma, initial, windows_per_group, check, extrinsics,
                  omega_coriolis) -> NoiseProblem:
    """:func:`jaximu.calibration.calibration_problem` with ``window_lengths`` (``build`` is
    that function, called for the base windows)."""
    from jaximu.calibration import ImuCalibration, Reference

    if model != "preintegration":
        raise InputError("window_lengths: the noise densities are fitted with the "
                         f"preintegration residual, got model={model!r}",
                         [Fix("model", "preintegration")])
    if extrinsics:
        raise InputError("window_lengths: the noise fit does not estimate extrinsics (a lever "
                         "arm adds the gyro's noise to the specific force): calibrate q_BS, "
                         "p_BS first, then pass the rotated samples",
                         [Fix("extrinsics", False)])
    t_np = val.as_numbers("t", t)
    if t_np.ndim != 1 or len(t_np) < 3:
        raise ValueError(f"t must have shape (N,) with N ≥ 3, got {t_np.shape}")
    period = float(np.median(np.diff(t_np)))
    W, multiples = _check_lengths(window_lengths, period)
    velocity = reference.v is not None
    if not velocity:  # central differences at the reference's own rate
        rp = val.as_numbers("reference.p", reference.p)
        rt = val.as_numbers("reference.t", reference.t)
        if rp.ndim == 2 and len(rt) == len(rp) and len(rt) >= 2 and np.all(np.diff(rt) > 0):
            reference = Reference(reference.t, reference.q, reference.p,
                                  np.gradient(rp, rt, axis=0))
    base = build(t, gyro, accel, reference, noise, keyframe_interval=W * period, scheme=scheme,
                 model=model, reference_sigma=reference_sigma, initial=initial,
                 windows_per_group=windows_per_group, check=check, extrinsics=False,
                 omega_coriolis=omega_coriolis)
    dtype = base.gyro.dtype
    K0 = base.n_windows
    flat = lambda x: x.reshape((-1,) + x.shape[2:])[:K0]  # noqa: E731
    init = initial if initial is not None else ImuCalibration.default(dtype=dtype)
    g_c, a_c = _compiled(_apply, True)(init, flat(base.gyro), flat(base.accel))
    noise0 = ImuNoise(*(jnp.asarray(x, dtype) for x in _isotropic(noise)))
    cov, jac, cov15 = _compiled(_long_window_bases, True, ("multiples", "scheme", "fast"))(
        g_c, a_c, flat(base.dt), noise0, multiples, scheme=scheme, fast=False)
    cov, jac = np.asarray(cov, np.float64), np.asarray(jac, np.float64)
    cov15 = np.asarray(cov15, np.float64)
    s0 = _isotropic(noise)
    bias_basis = np.stack([s0[2] ** 2 * jac[:, :, :3] @ np.swapaxes(jac[:, :, :3], 1, 2),
                           s0[3] ** 2 * jac[:, :, 3:] @ np.swapaxes(jac[:, :, 3:], 1, 2)], 1)
    kept0 = base.kept
    t_start = np.asarray(base.t_start, np.float64).reshape(-1)[:K0]
    t_end = np.asarray(base.t_end, np.float64).reshape(-1)[:K0]
    kept_parts, start_parts = [], []
    for m in multiples:
        K = K0 // m
        kept_parts.append(kept0[:K * m].reshape(K, m).all(1))
        start_parts.append(t_start[:K * m:m])
    kept, start = np.concatenate(kept_parts), np.concatenate(start_parts)
    sig = np.asarray(reference_sigma, np.float64)
    # the reference's errors at both ends, independent, through the residual's exact
    # linearisation: a tilt error δθ_i also turns gravity, g Δt δθ in r_v (g Δt² δθ / 2 in
    # r_p), which outgrows 2σ_v² beyond a fraction of a second
    Jr, F = (np.asarray(x, np.float64) for x in _compiled(
        _model_jacobians, True, ("multiples",))(init, base, multiples=multiples))
    F = F[:K0]
    ref_basis = np.stack([sig[j] ** 2 * np.einsum("kaei,kbei->kab", Jr[..., 3 * j:3 * j + 3],
                                                  Jr[..., 3 * j:3 * j + 3])
                          for j in range(3)], 1)
    for k, m in enumerate(multiples):
        if not kept[_length_slice(multiples, K0, k)].any():
            raise CalibrationError(f"no window of {m * W * period:g} s lies between the "
                                   "reference's gaps: pass shorter window_lengths")
    return NoiseProblem(base=base, multiples=multiples,
                        window_lengths=tuple(m * W * period for m in multiples), kept=kept,
                        start=start, span=float(t_end[-1] - t_start[0]), cov_basis=cov,
                        bias_basis=bias_basis, reference_basis=ref_basis, noise=noise,
                        reference_sigma=sig, rate_hz=1.0 / period, reference_velocity=velocity,
                        window_cov15=cov15, window_bias_jacobian=F,
                        window_reference_jacobian=Jr[:K0],
                        filter=state_space(cov15, F, Jr[:K0], np.where(sig > 0, sig, 1.0)))


def _length_slice(multiples, K0, k):
    off = sum(K0 // m for m in multiples[:k])
    return slice(off, off + K0 // multiples[k])


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
    q, p, v = _interp(t_key + calib.time_offset, problem.ref_t, problem.ref_q, problem.ref_p,
                      problem.ref_v)
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
        win = dataclasses.replace(pim, delta_t=dt, delta_q=dq, delta_v=dv, delta_p=dp,
                                  transition=pim.transition[:K], cov15=pim.cov15[:K],
                                  cov=pim.cov[:K], bias_hat=ImuBias(zero, zero))
        i, j = slice(0, K * m, m), slice(m, K * m + 1, m)
        state_i = _perturbed(q[i], p[i], v[i], d_i)
        state_j = _perturbed(q[j], p[j], v[j], d_j)
        out.append(residual(state_i, state_j, win, gravity=calib.gravity,
                            omega_coriolis=problem.omega_coriolis)[..., :9])
    return jnp.concatenate(out)


def _perturbed(q, p, v, d):
    zero = jnp.zeros_like(p)
    if d is None:
        return NavState(q, p, v, zero, zero)
    return NavState(so3.quat_mul(q, so3.exp(jnp.broadcast_to(d[:3], p.shape))), p + d[3:6],
                    v + d[6:9], zero, zero)


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


# --------------------------------------------------------------------------- the likelihood


def nll_and_gradient(problem: NoiseProblem, u, initial=None):
    """The negative log-likelihood of the base windows' residuals (the filter's exact joint
    one, :mod:`jaximu._noise_filter`) at log σ offsets ``u`` ``(7,)`` (``σ = σ_0 e^u`` for
    the four densities and ``σ_θ, σ_p, σ_v``) at the calibration ``initial``, and its
    gradient in ``u`` (autodiff through the filter). For checks; :func:`fit` minimises it."""
    from jaximu import _noise_filter as nf
    from jaximu.calibration import ImuCalibration

    dtype = problem.base.gyro.dtype
    init = initial if initial is not None else ImuCalibration.default(dtype=dtype)
    (H, Qb, P0b), kept, d, u0 = _filter_arrays(problem, dtype)
    r = _compiled(_all_residuals, True, ("multiples",))(init, problem.base, multiples=(1,))
    r = jnp.where(kept[:, None], r / jnp.asarray(d, dtype), 0)
    f = lambda x: nf.filter_pass(x + jnp.asarray(u0, dtype), r, H, Qb, P0b, kept)[0]  # noqa: E731
    value, grad = jax.value_and_grad(f)(jnp.asarray(u, dtype))
    return float(value) + float(np.log(d[np.asarray(kept)]).sum()), np.asarray(grad)


def _covariances(u, basis):
    """``(K, 9, 9)`` ``Σ_b exp(2u_b) B_kb`` of ``(K, 7, 9, 9)`` bases."""
    return jnp.einsum("b,kbij->kij", jnp.exp(2 * u), basis)


@jax.jit
def _whitened(u, r, basis):
    L = jnp.linalg.cholesky(_covariances(u, basis))
    return jax.scipy.linalg.solve_triangular(L, r[..., None], lower=True)[..., 0]


def _bases(problem: NoiseProblem):
    """``(K_all, 7, 9, 9)`` bases of each window's *marginal* covariance under the model (each
    σ at its initial value; the bias drifting from its value at the first keyframe, variance
    ``σ_rw² t`` at the window's start ``t``), divided by ``s sᵀ``, ``s`` the square root of
    the initial covariance's diagonal (conditioning for float32), and ``log s`` ``(K_all, 9)``."""
    t = problem.start
    cov = problem.cov_basis.copy()
    cov[:, 2] += t[:, None, None] * problem.bias_basis[:, 0]
    cov[:, 3] += t[:, None, None] * problem.bias_basis[:, 1]
    basis = np.concatenate([cov, problem.reference_basis], 1)
    d = np.sqrt(np.diagonal(basis.sum(1), axis1=-2, axis2=-1))
    d = np.where(d > 0, d, 1.0)
    return basis / (d[:, None, :, None] * d[:, None, None, :]), np.log(d)


def length_check(problem: NoiseProblem, calibration, sigmas):
    """``χ²/dof`` of each window length's residuals, each window whitened by its own marginal
    covariance at the calibration and the seven σ (``(7,)``): ≈ 1 at every length when the
    model explains the residuals at every time scale. A rough check, not a χ² test: the
    windows overlap and share one realisation of the bias drift, which dominates the marginal
    variance of late windows, so tens of percent from 1 are expected; a factor of several,
    or a trend with the length, says the model misses something."""
    dtype = problem.base.gyro.dtype
    basis, logd = _bases(problem)
    s0 = np.concatenate([_isotropic(problem.noise), problem.reference_sigma])
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(s0 > 0, np.log(np.asarray(sigmas) / np.where(s0 > 0, s0, 1.0)), 0.0)
    r = _compiled(_all_residuals, True, ("multiples",))(calibration, problem.base,
                                                         multiples=problem.multiples)
    w = np.asarray(_whitened(jnp.asarray(u, dtype), r / jnp.asarray(np.exp(logd), dtype),
                             jnp.asarray(basis, dtype)), np.float64)
    out = []
    for k in range(len(problem.multiples)):
        sl = _length_slice(problem.multiples, problem.base.n_windows, k)
        keep = problem.kept[sl]
        out.append(float(np.mean(w[sl][keep] ** 2)) if keep.any() else float("nan"))
    return tuple(out)


# --------------------------------------------------------------------------- the fit


def _free_sigmas(estimate):
    """Indices into :data:`_SIGMAS` of the estimated σ (``reference_sigma``: all three)."""
    return [i for i, name in enumerate(_SIGMAS)
            if name in estimate or (name.startswith("reference_sigma")
                                    and "reference_sigma" in estimate)]


def _check_identifiable(problem: NoiseProblem, estimate, s0):
    """Refuse a problem whose windows cannot separate what ``estimate`` names (or whose
    starting densities are not positive: the fit works in their logarithms)."""
    names = [n for n in NOISE_FIELDS if n in estimate]
    for n in names:
        if n == "reference_sigma":
            if np.any(problem.reference_sigma <= 0):
                raise InputError(
                    f"reference_sigma = {tuple(problem.reference_sigma)} holds a zero: the fit "
                    "estimates its logarithm and starts from it",
                    [Fix("reference_sigma", phrase="positive starting values in {}, e.g. (1e-3, 1e-3, 1e-2)")])
        elif s0[DENSITIES.index(n)] <= 0:
            raise InputError(
                f"noise.{n} is {s0[DENSITIES.index(n)]:g}: the fit estimates its logarithm and "
                "starts from it", [Fix("noise", phrase=f"a positive {n} in {{}} (the datasheet's or an "
                                                       "Allan fit's) to start from")])
    if not names:  # the fields alone (densities fixed): any windows will do
        return
    K0 = problem.base.n_windows
    n_fit = int(problem.kept[:K0].sum())
    W = problem.window_lengths[0]
    if n_fit < MIN_WINDOWS:
        raise InputError(
            f"the recording holds {n_fit} windows of {W:g} s in the fit; estimating noise "
            f"needs at least {MIN_WINDOWS}: white noise, random walk and the reference's "
            "noise separate through how consecutive windows' residuals correlate",
            [Fix("window_lengths", phrase=f"a shortest length ≤ {problem.span / MIN_WINDOWS:.3g}"
                                          " s in {} (or a longer recording)")])


def _filter_arrays(problem: NoiseProblem, dtype):
    """The base windows' state space (:func:`jaximu._noise_filter.state_space`) as arrays of
    ``dtype``, their ``kept`` mask, the residual scale ``d`` and the log σ offsets ``u0``
    ``(7,)`` of the given σ from those the bases were built at (``-inf`` for a reference σ
    given as 0)."""
    H, Qb, P0b, d = problem.filter
    K0 = problem.base.n_windows
    kept = problem.kept[:K0]
    ref0 = problem.reference_sigma
    with np.errstate(divide="ignore"):
        u_ref = np.log(ref0 / np.where(ref0 > 0, ref0, 1.0))
    u0 = np.concatenate([np.zeros(4), u_ref])
    arrays = tuple(jnp.asarray(x, dtype) for x in (H, Qb, P0b))
    return arrays, jnp.asarray(kept), d, u0


def fit(problem: NoiseProblem, initial, estimate, steps, tol):
    """Maximise the exact joint likelihood of the base windows' residuals
    (:mod:`jaximu._noise_filter`) over the ``estimate``d fields and σ.

    Returns a dict: ``calibration`` (:class:`ImuCalibration`), ``sigmas`` ``(7,)`` (the four
    densities and ``σ_θ, σ_p, σ_v``), ``cov_z`` (inverse Hessian in ``[z, u]``), ``free``,
    ``free_sigmas``, ``history`` (NLL per accepted step), ``converged``, ``chi2`` (of the
    whitened innovations), ``dof``, ``n_windows``."""
    from jaximu import _noise_filter as nf
    from jaximu._calibration_fit import _flatten

    base = problem.base
    dtype = base.gyro.dtype
    s0 = np.concatenate([_isotropic(problem.noise), problem.reference_sigma])
    _check_identifiable(problem, estimate, s0)
    free_c = tuple(n for n in FIELDS if n in estimate)
    free_s = _free_sigmas(estimate)
    layout = _Layout(free_c, 0)
    n_c = _n_free(free_c)
    (H, Qb, P0b), kept, d, u0 = _filter_arrays(problem, dtype)
    K0 = base.n_windows
    const = float(np.log(d[problem.kept[:K0]]).sum())
    scale = jnp.asarray(d, dtype)
    init_vec = jnp.asarray(_flatten(initial), dtype)
    graph = _compiled(_residuals_and_jacobian, True, ("multiples", "layout"))
    idx = jnp.asarray(free_s, jnp.int32)
    derivs = nf.compiled_derivatives(base.gyro.size // 3 <= QUICK_COMPILE_SAMPLES)

    def evaluate(z):
        r, J = graph(jnp.asarray(z, dtype), init_vec, base, scale=scale, multiples=(1,),
                     layout=layout)
        # windows in a reference gap: no update, and their residuals kept out of the sums
        r = jnp.where(kept[:, None], r, 0)
        return r, jnp.where(kept[:, None, None], J, 0)

    def derivatives(z, u, r, J):
        p = jnp.asarray(np.concatenate([np.zeros(n_c), u[free_s]]), dtype)
        f, g, Hs = derivs(p, r, J, H, Qb, P0b, kept, jnp.asarray(u, dtype), idx)
        return float(f), np.asarray(g, np.float64), np.asarray(Hs, np.float64)

    z, u = np.zeros(n_c), u0.copy()
    r, J = evaluate(z)
    f, g, Hn = derivatives(z, u, r, J)
    if not np.isfinite(f):
        raise FloatingPointError(f"the negative log-likelihood is {f} at the initial values")
    history, converged, lam = [f + const], False, 0.0
    # NLL changes far below 1 are statistically nothing (a χ² of 1 is one σ): a predicted
    # decrease below 1e-3 puts the estimate within √(2e-3) ≈ 0.05 standard errors of the
    # optimum along every direction, and stops a density running to 0 in log coordinates
    # (whose NLL falls by ever smaller amounts) after a few steps, not a few tens.
    threshold = max(max(tol, 1e-8, 10 * float(jnp.finfo(dtype).eps)) * (1 + abs(f)), 1e-3)
    for _ in range(steps):
        if not np.any(g):
            converged = True
            break
        delta = _damped_step(Hn, g, lam)
        predicted = -float(g @ delta + 0.5 * delta @ Hn @ delta)
        if predicted <= threshold:
            converged = True
            break
        z_new, u_new = z + delta[:n_c], u.copy()
        u_new[free_s] += delta[n_c:]
        r_new, J_new = evaluate(z_new)
        f_new, g_new, H_new = derivatives(z_new, u_new, r_new, J_new)
        if np.isfinite(f_new) and np.all(np.isfinite(g_new)) and f_new < f:
            z, u, r, J, f, g, Hn = z_new, u_new, r_new, J_new, f_new, g_new, H_new
            history.append(f + const)
            lam = lam / 3
        else:  # worse, or a covariance not positive definite at the trial point: damp
            lam = max(10 * lam, 1e-3 * float(np.max(np.abs(np.diag(Hn)))) or 1e-3)
    w = np.asarray(nf.whitened_innovations(jnp.asarray(u, dtype), r, H, Qb, P0b, kept),
                   np.float64)
    chi2 = float(np.sum(w * w))
    cov_z = laplace_covariance(Hn)
    calib, _ = _unpack(jnp.asarray(z, dtype), init_vec, base.velocities, layout)
    scales = np.asarray(_scale_vector(free_c, dtype), np.float64) if n_c else np.zeros(0)
    n_kept = int(problem.kept[:K0].sum())
    n = n_c + len(free_s)
    with np.errstate(invalid="ignore"):
        sigmas = s0 * np.exp(u - u0)
    return dict(calibration=calib, sigmas=np.where(np.isfinite(sigmas), sigmas, 0.0),
                cov_z=cov_z, free=free_c, free_sigmas=free_s, scales=scales,
                history=np.asarray(history), converged=converged, chi2=chi2,
                dof=max(9 * n_kept - n, 1), n_windows=n_kept)


def laplace_covariance(H):
    """The Laplace covariance ``H⁻¹`` of the fit's coordinates from the NLL's Hessian ``H``,
    with NaN rows and columns for the coordinates the likelihood does not determine: those
    that lie along a direction of ``H`` that is flat or curved downward (eigenvalue at most
    ``n·ε`` times the largest; a coordinate counts when that direction holds more than 1 % of
    it, ``Σ V_ik² > 10⁻⁴``). A pseudo-inverse would give them a variance of zero — a standard
    error that claims certainty where the data say nothing. The other coordinates' variances
    are those with the flat directions held fixed (a scale going to zero in log coordinates,
    such as a reference σ far below what the residuals show, is such a direction)."""
    H = 0.5 * (np.asarray(H, np.float64) + np.asarray(H, np.float64).T)
    w, V = np.linalg.eigh(H)
    flat = w <= len(w) * np.finfo(np.float64).eps * max(float(np.max(np.abs(w))), 1e-300)
    keep = ~flat
    cov = (V[:, keep] / w[keep]) @ V[:, keep].T
    undetermined = np.sum(V[:, flat] ** 2, axis=1) > 1e-4
    cov[undetermined, :] = np.nan
    cov[:, undetermined] = np.nan
    return cov


def _damped_step(H, g, lam):
    """``(H + λ I)⁻¹ (-g)``, λ raised until ``H + λ I`` is positive definite."""
    n = len(g)
    lam = max(lam, 0.0)
    for _ in range(60):
        try:
            L = np.linalg.cholesky(H + lam * np.eye(n))
            return -np.linalg.solve(L.T, np.linalg.solve(L, g))
        except np.linalg.LinAlgError:
            lam = max(10 * lam, 1e-6 * (1 + float(np.max(np.abs(np.diag(H))))))
    return -g / (1 + float(np.max(np.abs(np.diag(H)))))


def noise_result(problem: NoiseProblem, initial, estimate, steps, tol, max_reduced_chi2):
    """:func:`jaximu.calibration.calibrate` on a :class:`NoiseProblem`: the fit, its Laplace
    standard errors in physical units and the :class:`CalibrationResult`."""
    import warnings

    from jaximu._calibration_model import _TANGENT
    from jaximu.calibration import CalibrationResult, ImuCalibration

    dtype = problem.base.gyro.dtype
    rigid = [n for n in ("q_BS", "p_BS") if n in estimate]
    if rigid:
        raise InputError(f"estimate names {rigid} on a problem built with window_lengths: the "
                         "noise fit does not estimate extrinsics",
                         [Fix("estimate", phrase="{} without q_BS and p_BS")])
    initial = initial if initial is not None else ImuCalibration.default(dtype=dtype)
    out = fit(problem, initial, estimate, steps, tol)
    free_s, sig = out["free_sigmas"], out["sigmas"]
    jac = np.concatenate([out["scales"], sig[free_s]])  # physical per coordinate (dσ = σ du)
    cov = out["cov_z"] * jac[:, None] * jac[None, :]
    se = np.sqrt(np.diag(cov))  # NaN where the likelihood does not determine the value
    names = [f"{n}[{i}]" for n in out["free"] for i in range(_TANGENT[n])]
    names += [_SIGMAS[i] for i in free_s]
    flat = [n for n, e in zip(names, se) if not np.isfinite(e)]
    if flat:
        warnings.warn(f"noise fit: the likelihood does not determine {', '.join(flat)} (flat "
                      "or not at a minimum there): their standard errors are NaN; fix them, "
                      "or add windows that separate them", RuntimeWarning, stacklevel=3)
    std, off = {}, 0
    for name in FIELDS:
        shape = np.shape(getattr(initial, name)) if name != "q_BS" else (3,)
        if name in out["free"]:
            k = _TANGENT[name]
            std[name] = jnp.asarray(se[off:off + k].reshape(shape), dtype)
            off += k
        else:
            std[name] = jnp.zeros(shape, dtype)
    sig_std = np.zeros(7)
    sig_std[free_s] = se[off:]
    given = problem.noise
    fitted = ImuNoise(*(sig[i] if i in free_s else getattr(given, DENSITIES[i])
                        for i in range(4)))
    ref = np.where(np.isin(np.arange(4, 7), free_s), sig[4:], problem.reference_sigma)
    red = out["chi2"] / out["dof"]
    if max_reduced_chi2 is not None and red > max_reduced_chi2:
        warnings.warn(f"noise fit: χ²/dof = {red:.3g} > {max_reduced_chi2:g} at the estimate: "
                      "the model does not explain the reference (frames, units, time offset)",
                      RuntimeWarning, stacklevel=3)
    base = problem.base
    by_length = length_check(problem, out["calibration"],
                             np.concatenate([_isotropic(fitted), ref]))
    return CalibrationResult(
        calibration=out["calibration"], std=ImuCalibration(**std), covariance=cov,
        free=out["free"] + tuple(n for n in NOISE_FIELDS if n in estimate),
        velocities=np.asarray(base.velocities, np.float64), loss_history=out["history"],
        chi2=out["chi2"], dof=out["dof"], reduced_chi2=red, converged=out["converged"],
        n_windows=out["n_windows"],
        skipped_windows=int((~problem.kept[:base.n_windows]).sum()),
        note=base.skip_note, noise=fitted, noise_std=ImuNoise(*sig_std[:4]),
        reference_sigma=ref, reference_sigma_std=sig_std[4:], noise_given=given,
        reference_sigma_given=problem.reference_sigma, rate_hz=problem.rate_hz,
        window_lengths=problem.window_lengths, chi2_by_length=by_length)
