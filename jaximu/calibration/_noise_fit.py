"""The IMU's noise densities by maximum likelihood (:func:`jaximu.calibration.calibrate` on a
problem built with ``window_lengths``): the windows, their covariance bases, the fit and its
model checks.

Windows. The recording is cut into windows of the shortest length (the *base* windows, a
:class:`CalibrationProblem` of :func:`calibration_problem`). Their residuals' exact joint
likelihood (:mod:`jaximu.calibration._noise_filter`: a state space carrying the bias deviation and the
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
constant bias) and ``R_k`` the reference's noise at both ends. Per axis
(:data:`PER_AXIS_FIELDS` in ``estimate``), ``i`` runs over the twelve densities and axes
(:func:`noise_bases`: ``Q_c`` is diagonal, so the covariance is linear in each axis's
variance too) and ``J J ᵀ`` over the bias Jacobian's single columns.

Fit. Densities in log coordinates ``σ_i = σ_i0 exp(u_i)`` (positive), the calibration's
fields (biases, …) in the normalised coordinates of the rest of the calibration; damped
Newton with the residuals linearised in the fields (Gauss–Newton there, exact in ``u``), the
gradient and Hessian by autodiff through the filter, each step accepted when the true NLL
falls. Standard errors: the inverse Hessian at the optimum (observed information), mapped to
the densities by ``dσ = σ du``. A density named isotropically among per-axis bases is one
coordinate that sets its three axes' ``u`` (``tie`` of :func:`_noise_filter.nll`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.calibration import _noise_filter as nf
from jaximu.calibration._checks import (
    QUICK_COMPILE_SAMPLES,
    _compiled,
    _device,
)
from jaximu.calibration._fit import _flatten, _Layout, _n_free, _scale_vector, _unpack
from jaximu.calibration._model import (
    _TANGENT,
    FIELDS,
    ImuCalibration,
)
from jaximu.calibration._noise_problem import (
    DENSITIES,
    MIN_WINDOWS,
    NOISE_FIELDS,
    PER_AXIS_FIELDS,
    NoiseBases,
    NoiseProblem,
    _all_residuals,
    _isotropic,
    _length_slice,
    _residuals_and_jacobian,
    noise_bases,
)
from jaximu.errors import Fix, InputError
from jaximu.geometry.noise import ImuNoise

# --------------------------------------------------------------------------- the likelihood


def nll_and_gradient(problem: NoiseProblem, u, initial=None, bases: NoiseBases | None = None):
    """The negative log-likelihood of the base windows' residuals (the filter's exact joint
    one, :mod:`jaximu.calibration._noise_filter`) at log σ offsets ``u`` ``(7,)`` (``σ = σ_0 e^u`` for
    the four densities and ``σ_θ, σ_p, σ_v``; ``(15,)`` with per-axis ``bases``, the twelve
    per-axis densities first) at the calibration ``initial``, and its gradient in ``u``
    (autodiff through the filter). For checks; :func:`fit` minimises it."""
    dtype = problem.base.gyro.dtype
    init = initial if initial is not None else ImuCalibration.default(dtype=dtype)
    (H, Qb, P0b), kept, d, u0 = _filter_arrays(problem, dtype, bases)
    r = _compiled(_all_residuals, True, ("multiples",))(init, problem.base, multiples=(1,))
    value, grad = scaled_nll_and_gradient(
        _device(u, dtype), _device(u0, dtype), r, _device(d, dtype), H, Qb, P0b, kept
    )
    return float(value) + float(np.log(d[np.asarray(kept)]).sum()), np.asarray(grad)


@jax.jit
def scaled_nll_and_gradient(u, u0, r, d, H, Qb, P0b, kept):
    """``(NLL, ∂NLL/∂u)`` of the filter (:func:`_noise_filter.filter_pass`) at log σ offsets
    ``u + u0`` ``(D + 3,)``, of the raw residuals ``r`` ``(K, 9)`` scaled by ``d`` ``(K, 9)``
    (those not ``kept`` ``(K,)`` set to zero), without the ``Σ log d`` of the physical NLL.
    One program per problem shape, shared by every call (the gradient in reverse mode)."""
    e = jnp.where(kept[:, None], r / d, 0)
    return jax.value_and_grad(lambda x: nf.filter_pass(x + u0, e, H, Qb, P0b, kept)[0])(u)


def _covariances(u, basis):
    """``(K, 9, 9)`` ``Σ_b exp(2u_b) B_kb`` of ``(K, 7, 9, 9)`` bases."""
    return jnp.einsum("b,kbij->kij", jnp.exp(2 * u), basis)


@jax.jit
def _whitened(u, r, s, basis):
    """``L⁻¹ (r / s)`` (``L Lᵀ`` the covariance of :func:`_covariances`)."""
    L = jnp.linalg.cholesky(_covariances(u, basis))
    return jax.scipy.linalg.solve_triangular(L, (r / s)[..., None], lower=True)[..., 0]


def _bases(problem: NoiseProblem, bases: NoiseBases):
    """``(K_all, D + 3, 9, 9)`` bases of each window's *marginal* covariance under the model
    (each σ at its initial value; the bias drifting from its value at the first keyframe,
    variance ``σ_rw² t`` at the window's start ``t``), divided by ``s sᵀ``, ``s`` the square
    root of the initial covariance's diagonal (conditioning for float32), and ``log s``
    ``(K_all, 9)``."""
    t = problem.start
    cov = bases.cov_basis.copy()
    per = cov.shape[1] // 4  # bases per density
    for a in range(per):  # the random walks' bases: 2 per … 4 per
        cov[:, 2 * per + a] += t[:, None, None] * bases.bias_basis[:, a]
        cov[:, 3 * per + a] += t[:, None, None] * bases.bias_basis[:, per + a]
    basis = np.concatenate([cov, problem.reference_basis], 1)
    d = np.sqrt(np.diagonal(basis.sum(1), axis1=-2, axis2=-1))
    d = np.where(d > 0, d, 1.0)
    return basis / (d[:, None, :, None] * d[:, None, None, :]), np.log(d)


def length_check(problem: NoiseProblem, calibration, sigmas, bases: NoiseBases | None = None):
    """``χ²/dof`` of each window length's residuals, each window whitened by its own marginal
    covariance at the calibration and the σ of ``bases`` (default: the isotropic ones, ``(7,)``:
    four densities, ``σ_θ, σ_p, σ_v``; per axis ``(15,)``): ≈ 1 at every length when the
    model explains the residuals at every time scale. A rough check, not a χ² test: the
    windows overlap and share one realisation of the bias drift, which dominates the marginal
    variance of late windows, so tens of percent from 1 are expected; a factor of several,
    or a trend with the length, says the model misses something."""
    dtype = problem.base.gyro.dtype
    bases = bases if bases is not None else noise_bases(problem, False)
    basis, logd = _bases(problem, bases)
    # each σ over the σ its basis was built at (a σ of 0: no share of the covariance)
    sigmas, scale = np.asarray(sigmas, np.float64), bases.scale
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.where(sigmas > 0, np.log(sigmas / np.where(scale > 0, scale, 1.0)), -np.inf)
    r = _compiled(_all_residuals, True, ("multiples",))(
        calibration, problem.base, multiples=problem.multiples
    )
    w = np.asarray(
        _whitened(_device(u, dtype), r, _device(np.exp(logd), dtype), _device(basis, dtype)),
        np.float64,
    )
    out = []
    for k in range(len(problem.multiples)):
        sl = _length_slice(problem.multiples, problem.base.n_windows, k)
        keep = problem.kept[sl]
        out.append(float(np.mean(w[sl][keep] ** 2)) if keep.any() else float("nan"))
    return tuple(out)


# --------------------------------------------------------------------------- the fit


def _free_sigmas(estimate, bases: NoiseBases):
    """``(free, tie)``: the indices into ``bases``' σ of the estimated ones
    (``reference_sigma``: all three), and which fitted coordinate sets each (``None``: one
    each, in order; per-axis bases: a density named isotropically sets its three axes
    together)."""
    if not bases.per_axis:
        return [
            i
            for i, name in enumerate(bases.labels)
            if name in estimate
            or (name.startswith("reference_sigma") and "reference_sigma" in estimate)
        ], None
    free: list[int] = []
    tie: list[int] = []
    for i, name in enumerate(DENSITIES):
        if PER_AXIS_FIELDS[i] in estimate:
            for a in range(3):
                free.append(3 * i + a)
                tie.append(len(set(tie)))
        elif name in estimate:
            n = len(set(tie))
            free += [3 * i, 3 * i + 1, 3 * i + 2]
            tie += [n, n, n]
    if "reference_sigma" in estimate:
        for j in range(3):
            free.append(12 + j)
            tie.append(len(set(tie)))
    return free, tie


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
                    [
                        Fix(
                            "reference_sigma",
                            phrase="positive starting values in {}, e.g. (1e-3, 1e-3, 1e-2)",
                        )
                    ],
                )
        elif s0[DENSITIES.index(n)] <= 0:
            raise InputError(
                f"noise.{n} is {s0[DENSITIES.index(n)]:g}: the fit estimates its logarithm and "
                "starts from it",
                [
                    Fix(
                        "noise",
                        phrase=f"a positive {n} in {{}} (the datasheet's or an "
                        "Allan fit's) to start from",
                    )
                ],
            )
    K0 = problem.base.n_windows
    n_fit = int(problem.kept[:K0].sum())
    check_window_count(names, n_fit, problem.window_lengths[0], problem.span)


def check_window_count(estimate, n_fit: int, shortest: float, span: float):
    """Refuse ``n_fit`` windows of the ``shortest`` length [s] (of a recording of ``span``
    [s]) when they are too few for the densities ``estimate`` names: :data:`MIN_WINDOWS`,
    and :data:`MIN_WINDOWS_PER_AXIS` for a density per axis (the fields alone, densities
    fixed: any windows will do). The command calls it before any work, with the windows
    the recording can hold (an upper bound of those in the fit)."""
    per_axis = [n for n in PER_AXIS_FIELDS if n in estimate]
    if per_axis and n_fit < MIN_WINDOWS_PER_AXIS:
        raise InputError(
            f"the recording holds {n_fit} windows of {shortest:g} s in the fit; a density per "
            f"axis needs at least {MIN_WINDOWS_PER_AXIS} (three values where the isotropic "
            f"fit has one): {', '.join(per_axis)} cannot be identified",
            [
                Fix(
                    "window_lengths",
                    phrase=f"a shortest length ≤ {span / MIN_WINDOWS_PER_AXIS:.3g}"
                    " s in {} (or a longer recording, or the isotropic names in estimate)",
                )
            ],
        )
    if any(n in NOISE_FIELDS for n in estimate) and n_fit < MIN_WINDOWS:
        raise InputError(
            f"the recording holds {n_fit} windows of {shortest:g} s in the fit; estimating "
            f"noise needs at least {MIN_WINDOWS}: white noise, random walk and the reference's "
            "noise separate through how consecutive windows' residuals correlate",
            [
                Fix(
                    "window_lengths",
                    phrase=f"a shortest length ≤ {span / MIN_WINDOWS:.3g}"
                    " s in {} (or a longer recording)",
                )
            ],
        )


MIN_WINDOWS_PER_AXIS = 3 * MIN_WINDOWS
"""Fewest base windows for a density fitted per axis: each axis's density shows in a third
of the residual's components the isotropic one shows in, so the same information per
fitted value takes three times the windows."""


def _check_per_axis(problem: NoiseProblem, estimate):
    """Refuse a density named both per axis and isotropically, a per-axis starting value
    that is not positive on every axis, and too few windows for per-axis values."""
    named = [i for i, n in enumerate(PER_AXIS_FIELDS) if n in estimate]
    both = [DENSITIES[i] for i in named if DENSITIES[i] in estimate]
    if both:
        raise InputError(
            f"estimate names {both[0]} both isotropically and per axis "
            f"({PER_AXIS_FIELDS[DENSITIES.index(both[0])]}): one value or three",
            [Fix("estimate", phrase=f"one of the two names of {both[0]} in {{}}")],
        )
    for i in named:
        n = DENSITIES[i]
        v = np.broadcast_to(np.asarray(getattr(problem.noise, n), np.float64), (3,))
        if not np.all(v > 0):
            raise InputError(
                f"noise.{n} is {v.tolist()}: fitted per axis, each axis's logarithm is "
                "estimated, starting from it",
                [Fix("noise", phrase=f"a positive {n} on every axis in {{}} to start from")],
            )
    if not named:
        return
    K0 = problem.base.n_windows
    n_fit = int(problem.kept[:K0].sum())
    per_axis = [PER_AXIS_FIELDS[i] for i in named]
    check_window_count(per_axis, n_fit, problem.window_lengths[0], problem.span)


def _filter_arrays(problem: NoiseProblem, dtype, bases: NoiseBases | None = None):
    """The base windows' state space (:func:`jaximu.calibration._noise_filter.state_space`) as arrays of
    ``dtype``, their ``kept`` mask, the residual scale ``d`` and the log σ offsets ``u0``
    ``(D + 3,)`` of the given σ from those the bases were built at (``-inf`` for a σ given
    as 0); ``bases``: default the problem's isotropic ones."""
    bases = bases if bases is not None else noise_bases(problem, False)
    H, Qb, P0b, d = bases.filter
    K0 = problem.base.n_windows
    kept = problem.kept[:K0]
    u0 = bases.u0
    arrays = tuple(_device(x, dtype) for x in (H, Qb, P0b))
    return arrays, _device(kept), d, u0


def fit(problem: NoiseProblem, initial, estimate, steps, tol, bases: NoiseBases | None = None):
    """Maximise the exact joint likelihood of the base windows' residuals
    (:mod:`jaximu.calibration._noise_filter`) over the ``estimate``d fields and σ, with the
    covariance ``bases`` (default: the problem's isotropic ones; :func:`noise_bases`).

    Returns a dict: ``calibration`` (:class:`ImuCalibration`), ``sigmas`` ``(D + 3,)`` (the
    densities, four or twelve per axis, and ``σ_θ, σ_p, σ_v``), ``cov_z`` (inverse Hessian in
    ``[z, u]``), ``free``, ``free_sigmas`` (indices into ``sigmas``), ``tie`` (which fitted
    coordinate sets each, or ``None``: one each), ``first`` (each fitted coordinate's first
    σ), ``history`` (NLL per accepted step), ``converged``, ``chi2`` (of the whitened
    innovations), ``dof``, ``n_windows``."""
    base = problem.base
    dtype = base.gyro.dtype
    bases = bases if bases is not None else noise_bases(problem, False)
    s0 = np.concatenate([_isotropic(problem.noise), problem.reference_sigma])
    _check_identifiable(problem, estimate, s0)
    _check_per_axis(problem, estimate)
    free_c = tuple(n for n in FIELDS if n in estimate)
    free_s, tie = _free_sigmas(estimate, bases)
    first = free_s if tie is None else [free_s[tie.index(j)] for j in range(len(set(tie)))]
    layout = _Layout(free_c, 0)
    n_c = _n_free(free_c)
    (H, Qb, P0b), kept, d, u0 = _filter_arrays(problem, dtype, bases)
    if tie is not None:  # a density fitted isotropically starts at its axes' RMS
        for j in range(len(first)):
            members = [i for i, t in zip(free_s, tie) if t == j]
            if len(members) > 1:
                u0 = u0.copy()
                u0[members] = 0.0
    K0 = base.n_windows
    const = float(np.log(d[problem.kept[:K0]]).sum())
    scale = _device(d, dtype)
    init_vec = jnp.asarray(_flatten(initial), dtype)
    graph = _compiled(_residuals_and_jacobian, True, ("multiples", "layout"))
    idx = jnp.asarray(free_s, jnp.int32)
    tied = () if tie is None else (jnp.asarray(tie, jnp.int32),)
    derivs = nf.compiled_derivatives(base.gyro.size // 3 <= QUICK_COMPILE_SAMPLES)

    def evaluate(z):
        r, J = graph(
            jnp.asarray(z, dtype), init_vec, base, scale=scale, multiples=(1,), layout=layout
        )
        # windows in a reference gap: no update, and their residuals kept out of the sums
        r = jnp.where(kept[:, None], r, 0)
        return r, jnp.where(kept[:, None, None], J, 0)

    def derivatives(z, u, r, J):
        p = jnp.asarray(np.concatenate([np.zeros(n_c), u[first]]), dtype)
        f, g, Hs = derivs(p, r, J, H, Qb, P0b, kept, jnp.asarray(u, dtype), idx, *tied)
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
        u_new[free_s] += delta[n_c:] if tie is None else delta[n_c:][tie]
        r_new, J_new = evaluate(z_new)
        f_new, g_new, H_new = derivatives(z_new, u_new, r_new, J_new)
        if np.isfinite(f_new) and np.all(np.isfinite(g_new)) and f_new < f:
            z, u, r, J, f, g, Hn = z_new, u_new, r_new, J_new, f_new, g_new, H_new
            history.append(f + const)
            lam = lam / 3
        else:  # worse, or a covariance not positive definite at the trial point: damp
            lam = max(10 * lam, 1e-3 * float(np.max(np.abs(np.diag(Hn)))) or 1e-3)
    w = np.asarray(nf.whitened_innovations(jnp.asarray(u, dtype), r, H, Qb, P0b, kept), np.float64)
    chi2 = float(np.sum(w * w))
    cov_z = laplace_covariance(Hn)
    calib, _ = _unpack(jnp.asarray(z, dtype), init_vec, base.velocities, layout)
    scales = np.asarray(_scale_vector(free_c, dtype), np.float64) if n_c else np.zeros(0)
    n_kept = int(problem.kept[:K0].sum())
    n = n_c + len(first)
    sigmas = bases.scale * np.exp(u)  # 0 for a σ given as 0 (u = -inf)
    return dict(
        calibration=calib,
        sigmas=np.where(np.isfinite(sigmas), sigmas, 0.0),
        cov_z=cov_z,
        free=free_c,
        free_sigmas=free_s,
        tie=tie,
        first=first,
        scales=scales,
        history=np.asarray(history),
        converged=converged,
        chi2=chi2,
        dof=max(9 * n_kept - n, 1),
        n_windows=n_kept,
    )


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
    standard errors in physical units: the fields of the
    :class:`jaximu.calibration.CalibrationResult` (which :func:`calibrate` makes of them)."""
    import warnings

    dtype = problem.base.gyro.dtype
    rigid = [n for n in ("q_BS", "p_BS") if n in estimate]
    if rigid:
        raise InputError(
            f"estimate names {rigid} on a problem built with window_lengths: the "
            "noise fit does not estimate extrinsics",
            [Fix("estimate", phrase="{} without q_BS and p_BS")],
        )
    initial = initial if initial is not None else ImuCalibration.default(dtype=dtype)
    _check_per_axis(problem, estimate)  # before the per-axis bases are built
    bases = noise_bases(problem, any(n in estimate for n in PER_AXIS_FIELDS))
    out = fit(problem, initial, estimate, steps, tol, bases)
    free_s, sig, first = out["free_sigmas"], out["sigmas"], out["first"]
    jac = np.concatenate([out["scales"], sig[first]])  # physical per coordinate (dσ = σ du)
    cov = out["cov_z"] * jac[:, None] * jac[None, :]
    se = np.sqrt(np.diag(cov))  # NaN where the likelihood does not determine the value
    names = [f"{n}[{i}]" for n in out["free"] for i in range(_TANGENT[n])]
    names += [
        _label(bases, i, out["tie"] is not None and out["tie"].count(j) > 1)
        for j, i in enumerate(first)
    ]
    flat = [n for n, e in zip(names, se) if not np.isfinite(e)]
    if flat:
        warnings.warn(
            f"noise fit: the likelihood does not determine {', '.join(flat)} (flat "
            "or not at a minimum there): their standard errors are NaN; fix them, "
            "or add windows that separate them",
            RuntimeWarning,
            stacklevel=3,
        )
    std, off = {}, 0
    for name in FIELDS:
        shape = np.shape(getattr(initial, name)) if name != "q_BS" else (3,)
        if name in out["free"]:
            k = _TANGENT[name]
            std[name] = jnp.asarray(se[off : off + k].reshape(shape), dtype)
            off += k
        else:
            std[name] = jnp.zeros(shape, dtype)
    sig_std = np.zeros(len(sig))
    sig_std[free_s] = se[off:] if out["tie"] is None else se[off:][out["tie"]]
    given = problem.noise
    D = len(sig) - 3
    if bases.per_axis:
        fitted, noise_std = _per_axis_noise(given, estimate, sig, sig_std)
    else:
        fitted = ImuNoise(
            *(sig[i] if i in free_s else getattr(given, DENSITIES[i]) for i in range(4))
        )
        noise_std = ImuNoise(*sig_std[:4])
    ref = np.where(np.isin(np.arange(D, D + 3), free_s), sig[D:], problem.reference_sigma)
    red = out["chi2"] / out["dof"]
    if max_reduced_chi2 is not None and red > max_reduced_chi2:
        warnings.warn(
            f"noise fit: χ²/dof = {red:.3g} > {max_reduced_chi2:g} at the estimate: "
            "the model does not explain the reference (frames, units, time offset)",
            RuntimeWarning,
            stacklevel=3,
        )
    base = problem.base
    by_length = length_check(
        problem,
        out["calibration"],
        np.concatenate([sig[:D] if bases.per_axis else _isotropic(fitted), ref]),
        bases,
    )
    return dict(
        calibration=out["calibration"],
        std=ImuCalibration(**std),
        covariance=cov,
        free=out["free"] + tuple(n for n in NOISE_FIELDS + PER_AXIS_FIELDS if n in estimate),
        velocities=np.asarray(base.velocities, np.float64),
        loss_history=out["history"],
        chi2=out["chi2"],
        dof=out["dof"],
        reduced_chi2=red,
        converged=out["converged"],
        n_windows=out["n_windows"],
        skipped_windows=int((~problem.kept[: base.n_windows]).sum()),
        note=base.skip_note,
        noise=fitted,
        noise_std=noise_std,
        reference_sigma=ref,
        reference_sigma_std=sig_std[D:],
        noise_given=given,
        reference_sigma_given=problem.reference_sigma,
        rate_hz=problem.rate_hz,
        window_lengths=problem.window_lengths,
        chi2_by_length=by_length,
    )


def _label(bases: NoiseBases, i, tied):
    """The name of the fitted σ whose first basis is ``i`` (a density fitted isotropically
    among per-axis bases: its name)."""
    return DENSITIES[i // 3] if tied else bases.labels[i]


def _per_axis_noise(given: ImuNoise, estimate, sig, sig_std):
    """``(noise, noise_std)`` of a fit with per-axis bases (``sig``, ``sig_std``: ``(15,)``):
    a density named per axis as its ``(3,)`` values, one named isotropically as one number,
    the others as given (standard error 0)."""
    vals, errs = [], []
    for i, name in enumerate(DENSITIES):
        if PER_AXIS_FIELDS[i] in estimate:
            vals.append(sig[3 * i : 3 * i + 3].copy())
            errs.append(sig_std[3 * i : 3 * i + 3].copy())
        elif name in estimate:
            vals.append(float(sig[3 * i]))
            errs.append(float(sig_std[3 * i]))
        else:
            vals.append(getattr(given, name))
            errs.append(0.0)
    return ImuNoise(*vals), ImuNoise(*errs)
