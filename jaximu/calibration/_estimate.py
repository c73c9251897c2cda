"""The estimate of a calibration problem: :func:`calibrate` (Levenberg–Marquardt or optax, the
Laplace covariance) and what it returns (:class:`CalibrationResult`).
"""

from __future__ import annotations

import dataclasses
import warnings

import jax.numpy as jnp
import numpy as np

from jaximu.calibration._checks import (
    _compiled,
)
from jaximu.calibration._fit import (
    _flatten,
    _Layout,
    _levenberg_marquardt,
    _n_free,
    _optax_loop,
    _quick,
    _residuals_jacobian,
    _residuals_jacobian_compiled,  # noqa: F401  (tests)
    _scale_vector,
    _unpack,
)
from jaximu.calibration._model import (
    _TANGENT,
    _VELOCITY_SCALE,
    EXCITATION,
    FIELDS,
    OPTIMIZERS,
    CalibrationProblem,
    ImuCalibration,
    _sample_noise_covariance,
    sensor_matrix,  # noqa: F401  (calibration.sensor_matrix)
)
from jaximu.calibration._noise_fit import noise_result
from jaximu.calibration._noise_problem import NOISE_FIELDS, PER_AXIS_FIELDS, NoiseProblem
from jaximu.calibration._noise_table import noise_table
from jaximu.calibration.problem import _check_initial, _sqrt_information
from jaximu.errors import Fix, InputError
from jaximu.geometry import _checks as val
from jaximu.geometry.noise import ImuNoise


@dataclasses.dataclass(frozen=True)
class CalibrationResult:
    """What :func:`calibrate` found.

    Attributes:
        calibration: the estimate :class:`ImuCalibration`.
        std: an :class:`ImuCalibration` of 1σ uncertainties (0 for fixed fields).
        covariance: ``(n, n)`` Laplace covariance of the estimated fields, in the order of
            ``free`` (each field's components in turn), physical units.
        free: names of the estimated fields.
        velocities: ``(K + 1, 3)`` keyframe velocities used (estimated if the reference
            had none); NaN at a keyframe that bounds no window of the fit (reference gaps).
        loss_history: the loss at the start, after each (accepted, for ``"lm"``) step, and
            at the estimate.
        chi2, dof, reduced_chi2: ``2·loss`` at the estimate, its degrees of freedom
            (9 × the windows in the fit - parameters) and their ratio (≈ 1 when the noise
            model is right).
        converged: whether the stopping rule was met before ``steps``.
        n_windows: the windows in the fit; skipped_windows: those left out because a
            keyframe of theirs falls inside a reference gap; note: why, in words
            (:attr:`CalibrationProblem.skip_note`; "" when none was left out).
        noise, noise_std: with ``window_lengths`` (a noise fit), the :class:`ImuNoise` at
            the estimate (a density named in :data:`NOISE_FIELDS` one number, in
            :data:`PER_AXIS_FIELDS` a ``(3,)`` array per axis; the others as given) and the
            1σ of each (0 for fixed ones), from the observed information of the likelihood;
            ``None`` otherwise. reference_sigma, reference_sigma_std: ``(3,)``
            ``(σ_θ [rad], σ_p [m], σ_v [m/s])`` and its 1σ. noise_given,
            reference_sigma_given: the values the problem was built with. rate_hz: the IMU's
            rate (for the discrete-time standard deviations); window_lengths [s] (the
            likelihood is that of the shortest windows; see :mod:`jaximu.calibration._noise_filter`).
            chi2_by_length: per window length, the mean squared residual of each window
            whitened by its own marginal covariance at the estimate (≈ 1 at every length,
            to tens of percent, when the model explains every time scale: a rough check,
            the windows share one realisation of the bias drift). :meth:`noise_table` prints them
            side by side.
    """

    calibration: ImuCalibration
    std: ImuCalibration
    covariance: np.ndarray
    free: tuple
    velocities: np.ndarray
    loss_history: np.ndarray
    chi2: float
    dof: int
    reduced_chi2: float
    converged: bool
    n_windows: int = 0
    skipped_windows: int = 0
    note: str = ""
    noise: ImuNoise | None = None
    noise_std: ImuNoise | None = None
    reference_sigma: np.ndarray | None = None
    reference_sigma_std: np.ndarray | None = None
    noise_given: ImuNoise | None = None
    reference_sigma_given: np.ndarray | None = None
    rate_hz: float | None = None
    window_lengths: tuple = ()
    chi2_by_length: tuple = ()

    def noise_table(self, allan=None) -> str:
        """The fitted densities in words: :func:`noise_table`."""
        return noise_table(self, allan)


def calibrate(
    problem: CalibrationProblem,
    initial: ImuCalibration | None = None,
    estimate=("b_g", "b_a"),
    *,
    optimizer: str = "lm",
    steps: int | None = None,
    learning_rate: float = 0.05,
    tol: float = 1e-10,
    max_reduced_chi2: float | None = 100.0,
) -> CalibrationResult:
    """Fit the ``estimate``d fields of an :class:`ImuCalibration` by gradient descent.

    Args:
        problem: from :func:`calibration_problem`.
        initial: starting values (default :meth:`ImuCalibration.default`); the other fields
            stay at these values.
        estimate: names from :data:`FIELDS` (at least one); on a problem built with
            ``window_lengths``, also :data:`NOISE_FIELDS` (the densities isotropic: one value
            for the three axes) and :data:`PER_AXIS_FIELDS` (a density per axis, e.g.
            ``"gyroscope_noise_density_per_axis"``: three values; each density by one name).
        optimizer: ``"lm"`` (default: Levenberg–Marquardt on the whitened residuals, whose
            one compiled residuals-and-Jacobian function also gives the Laplace covariance;
            default 50 steps), ``"lbfgs"`` (optax L-BFGS with zoom line search; default 100
            steps) or ``"adam"`` (``learning_rate > 0`` in normalised units; default 1000
            steps). ``"lm"`` compiles the least and needs the fewest steps: the loss is a sum
            of squares.
        steps: the most optimiser steps, an integer ≥ 1 (default: by optimizer).
        tol: ``≥ 0``; ``"lm"`` stops when the decrease its local model predicts is below
            ``max(tol, 10 ε) · (1 + loss)`` (ε of the computation dtype: the loss's own
            rounding); the optax optimisers when the loss changes by less than
            ``tol · (1 + loss)`` for 5 steps.
        max_reduced_chi2: warn (``RuntimeWarning``) when ``χ²/dof`` at the estimate is above
            this: the model does not explain the data (frames, units, time offset, or a
            noise model far too optimistic); positive, or ``None`` to disable.

    Returns:
        :class:`CalibrationResult`.
    """
    if isinstance(estimate, str):  # tuple("b_g") would be ('b', '_', 'g')
        fix = tuple(n.strip() for n in estimate.split(",") if n.strip())
        raise ValueError(
            f"estimate must be a tuple of field names, got the string "
            f"{estimate!r}; pass estimate={fix!r}"
        )
    try:
        estimate = tuple(estimate)
    except TypeError:
        raise ValueError(
            f"estimate must be a tuple of field names from {FIELDS}, got "
            f"{type(estimate).__name__} {estimate!r}"
        ) from None
    unknown = [n for n in estimate if n not in FIELDS + NOISE_FIELDS + PER_AXIS_FIELDS]
    if unknown:
        raise ValueError(
            f"unknown calibration fields {unknown}; fields are {FIELDS} and the "
            f"noise's {NOISE_FIELDS} (a density per axis: {PER_AXIS_FIELDS})"
        )
    if not estimate:
        raise ValueError(
            f"estimate names no field, got {estimate!r}; pass at least one of {FIELDS} or "
            f"the noise's {NOISE_FIELDS}, e.g. estimate=('b_g', 'b_a')"
        )
    twice = sorted({n for n in estimate if estimate.count(n) > 1})
    if twice:
        unique = tuple(dict.fromkeys(estimate))
        raise ValueError(
            f"estimate names {', '.join(map(repr, twice))} more than once, got {estimate!r}; "
            f"name each field once: estimate={unique!r}"
        )
    if isinstance(problem, NoiseProblem):
        if optimizer != "lm":
            raise InputError(
                f"optimizer={optimizer!r}: the noise densities are fitted by "
                "damped Newton on the likelihood",
                [Fix("optimizer", "lm")],
            )
        _check_initial(initial)
        steps = 50 if steps is None else val.check_int("steps", steps, 1)
        tol = val.check_positive("tol", tol, allow_zero=True)
        if max_reduced_chi2 is not None:
            max_reduced_chi2 = val.check_positive("max_reduced_chi2", max_reduced_chi2)
        return CalibrationResult(
            **noise_result(problem, initial, estimate, steps, tol, max_reduced_chi2)
        )
    noise_names = [n for n in estimate if n in NOISE_FIELDS + PER_AXIS_FIELDS]
    if noise_names:
        raise InputError(
            f"estimate names {noise_names}, but the problem was built without window_lengths: "
            "the noise fit needs the windows' covariance bases and reference Jacobians",
            [Fix("window_lengths", (0.25, 1, 4))],
            lead="build the problem with",
        )
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {optimizer!r}; choose one of {OPTIMIZERS}")
    if not isinstance(problem, CalibrationProblem):
        raise ValueError(
            "problem must be a CalibrationProblem (from calibration_problem), got "
            f"{type(problem).__name__}"
        )
    _check_initial(initial)
    if steps is not None:
        steps = val.check_int("steps", steps, 1)
    learning_rate = val.check_positive("learning_rate", learning_rate)
    tol = val.check_positive("tol", tol, allow_zero=True)
    if max_reduced_chi2 is not None:
        max_reduced_chi2 = val.check_positive("max_reduced_chi2", max_reduced_chi2)
    dtype = problem.gyro.dtype
    free = tuple(n for n in FIELDS if n in estimate)
    if initial is None:
        initial = ImuCalibration.default(dtype=dtype)
        if problem.q_BS0 is not None:  # the closed-form rotation of calibration_problem
            initial = dataclasses.replace(initial, q_BS=jnp.asarray(problem.q_BS0, dtype))
    if not problem.extrinsics and (
        {"q_BS", "p_BS"} & set(free)
        or np.any(np.asarray(initial.q_BS) != [1, 0, 0, 0])
        or np.any(np.asarray(initial.p_BS) != 0)
    ):
        problem = dataclasses.replace(problem, extrinsics=True)
    init_vec = jnp.asarray(_flatten(initial), dtype)
    n_v = 0 if problem.has_velocity else problem.velocities.size
    layout = _Layout(free, n_v)
    n = _n_free(free)
    z = jnp.zeros(n + n_v, dtype)

    def fit(problem, z0):
        if optimizer == "lm":

            def evaluate(z_):
                r_, J_ = _residuals_jacobian(
                    jnp.asarray(z_, dtype), problem, init_vec, layout=layout
                )
                return np.asarray(r_, np.float64), np.asarray(J_, np.float64)

            threshold = max(tol, 10 * float(jnp.finfo(dtype).eps))  # below: loss rounding
            z_np, history, converged, r, J = _levenberg_marquardt(
                evaluate, np.asarray(z0, np.float64), steps if steps is not None else 50, threshold
            )
            return jnp.asarray(z_np, dtype), history, converged, r, J
        z, history, converged = _optax_loop(
            z0, problem, init_vec, layout, optimizer, learning_rate, steps, tol, dtype
        )
        r, J = _residuals_jacobian(z, problem, init_vec, layout=layout)
        return z, history, converged, r, J

    z, history, converged, r, J = fit(problem, z)
    if problem.extrinsics:
        # Whiten again at the estimate with the samples' noise through the whole model (the
        # lever arm's ω×(ω×r) + α×r carry gyro noise), then refine from there.
        calib_now, v_now = _unpack(z, init_vec, problem.velocities, layout)
        cov = _compiled(_sample_noise_covariance, _quick(problem))(problem, calib_now, v_now)
        cov = np.asarray(cov, np.float64) + np.asarray(problem.reference_var, np.float64)[
            ..., None
        ] * np.eye(9)
        problem = dataclasses.replace(
            problem, sqrt_info=jnp.asarray(_sqrt_information(cov, dtype), dtype)
        )
        z, more, converged, r, J = fit(problem, z)
        history = list(history) + list(more)
    r, J = np.asarray(r, np.float64), np.asarray(J, np.float64)
    chi2 = float(r @ r)
    if optimizer != "lm":  # the Levenberg–Marquardt history ends at this point already
        history.append(0.5 * chi2)
    cov_z = np.linalg.pinv(J.T @ J)
    scale = np.concatenate(
        [np.asarray(_scale_vector(free, dtype), np.float64), np.full(n_v, _VELOCITY_SCALE)]
    )
    cov_all = cov_z * scale[:, None] * scale[None, :]
    cov = cov_all[:n, :n]
    calib, v = _unpack(z, init_vec, problem.velocities, layout)
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    std, off = {}, 0
    for name in FIELDS:
        k, shape = _TANGENT[name], (3,) if name == "q_BS" else np.shape(getattr(initial, name))
        if name in free:
            std[name] = jnp.asarray(sig[off : off + k].reshape(shape), dtype)
            off += k
        else:
            std[name] = jnp.zeros(shape, dtype)
        if name in EXCITATION and name in free and float(np.max(std[name])) > EXCITATION[name]:
            what = "lever arm p_BS" if name == "p_BS" else "rotation q_BS"
            unit = "m" if name == "p_BS" else "rad"
            warnings.warn(
                f"the motion does not excite the {what}: its 1σ is "
                f"{np.array2string(np.asarray(std[name], np.float64), precision=3)} {unit} "
                f"(> {EXCITATION[name]:.3g} {unit}); a lever arm shows in the specific force only "
                "as ω×(ω×r) + α×r: turn the body faster, about more axes",
                RuntimeWarning,
                stacklevel=2,
            )
    # Windows left out (reference gaps) add zero rows; a keyframe velocity that bounds none of
    # the fit's windows has a zero column and is no parameter.
    kept = problem.kept
    k = np.asarray(problem.window).reshape(-1)[: problem.n_windows][kept]
    used = np.zeros(len(problem.velocities), bool)
    used[k] = used[k + 1] = True
    n_v_used = 3 * int(used.sum()) if n_v else 0
    dof = max(9 * int(kept.sum()) - n - n_v_used, 1)
    v = np.where(used[:, None], np.asarray(v), np.nan)
    red = chi2 / dof
    if max_reduced_chi2 is not None and red > max_reduced_chi2:
        warnings.warn(
            f"calibration residual χ²/dof = {red:.3g} > {max_reduced_chi2:g}: the model does not"
            " explain the reference (check the IMU-reference frame, units, the time offset, or"
            " the noise densities)",
            RuntimeWarning,
            stacklevel=2,
        )
    return CalibrationResult(
        calibration=calib,
        std=ImuCalibration(**std),
        covariance=cov,
        free=free,
        velocities=v,
        loss_history=np.asarray(history),
        chi2=chi2,
        dof=dof,
        reduced_chi2=red,
        converged=converged,
        n_windows=int(kept.sum()),
        skipped_windows=problem.n_skipped,
        note=problem.skip_note,
    )
