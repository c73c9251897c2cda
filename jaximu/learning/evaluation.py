"""Whole-sequence evaluation: open-loop attitude from the first true attitude, at the IMU rate.

Metrics (both conventions of the field, named):

* **AOE**, absolute orientation error: the geodesic angle of ``R_gtᵀ R̂`` at every stamp of
  the ground truth (the attitude integrated at the IMU rate, carried from the sample before
  each stamp to it; a motion-capture dropout has no stamps, so no error spans it), in degrees; its **mean** over the sequence (AirIMU's ``evaluate_state.py``) and its
  **RMSE** (Brossard's).
* **AYE**: the same for the yaw alone: the heading part (ZYX Euler yaw, about the world's z)
  of the world-frame error ``R̂ R_gtᵀ``.
* **NEES** of the learned uncertainty: ``rᵀ S⁻¹ r`` with ``r = Log(R_gtᵀ R̂)`` and ``S`` the
  propagated orientation covariance (:func:`attitude_covariance`) plus the ground truth's own
  noise; averaged over the samples (3 when consistent), and the fraction of samples inside
  the 3σ region (``NEES ≤ χ²₃(0.9973) = 14.16``).
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.engine.errorstate import accumulate_covariance, transition_products
from jaximu.engine.propagate import propagate, propagate_final
from jaximu.errors import Fix, InputError
from jaximu.geometry import so3
from jaximu.geometry._checks import (
    batch_shape,
    check_finite,
    check_imu,
    check_int,
    check_output,
    check_positive,
    check_sign,
    check_vector,
    compute_dtype,
    float_dtype,
    to_dtype,
)
from jaximu.geometry._tolerances import check_unit_norm
from jaximu.geometry.state import NavState
from jaximu.io import DataError
from jaximu.learning.data import Sequence, check_rate, check_sequence, padded_length, to_length
from jaximu.learning.losses import rotation_step_blocks
from jaximu.learning.model import check_model
from jaximu.learning.tracking import LEVEL_SAMPLES

__all__ = [
    "integrate_attitude",
    "orientation_errors",
    "attitude_covariance",
    "markov_attitude",
    "Metrics",
    "SequenceReport",
    "evaluate_sequence",
    "window_errors",
    "stamp_steps",
    "window_samples",
    "CHI2_3_3SIGMA",
]

CHI2_3_3SIGMA = 14.156
"""``χ²`` quantile of 3 degrees of freedom at 99.73 % (the 3σ probability of one dimension)."""


def _quaternions(name: str, q, dtype):
    """``q`` ``(..., 4)`` as ``dtype``: finite unit ``[w, x, y, z]`` quaternions (eager)."""
    q = to_dtype(name, q, dtype)
    check_vector(name, q, 4, time_axis=False)
    check_finite(name, q, "pass finite unit quaternions")
    check_unit_norm(name, q, dtype)
    return q


def _intervals(name: str, dt, T: int, dtype, gyro):
    """``dt``: a scalar or ``(..., T-1)`` intervals between ``T`` samples, positive and
    finite (the engine's check, :func:`jaximu.geometry._checks.check_imu`)."""
    d = to_dtype(name, dt, dtype)
    if d.ndim and d.shape[-1] != T - 1:
        raise ValueError(
            f"{name} must be a scalar or have shape (..., T-1) = (..., {T - 1}), one interval "
            f"per step between the T = {T} samples of gyro, got {tuple(d.shape)}"
        )
    steps = gyro[..., :-1, :]
    return check_imu(steps, jnp.zeros_like(steps), dt, dtype)[2]


def integrate_attitude(q0, gyro, dt):
    """Attitude at every sample by the engine's exact-exponential Euler step.

    Args:
        q0: ``(..., 4)`` unit attitude ``[w, x, y, z]`` at sample 0, finite;
        gyro: ``(..., T, 3)`` [rad/s], finite, ``T ≥ 1``;
        dt: scalar or ``(..., T-1)`` intervals [s], positive (step k from sample k to k+1
            holds sample k).

    Returns:
        ``(..., T, 4)``: ``q0`` first, then the attitude after each step.
    """
    dtype = float_dtype(q0, gyro, dt)
    gyro = to_dtype("gyro", gyro, dtype)
    check_vector("gyro", gyro)
    if gyro.shape[-2] < 1:
        raise ValueError(f"gyro holds no samples (shape {tuple(gyro.shape)}); pass T ≥ 1")
    check_finite("gyro", gyro, "repair or drop those samples")
    q0 = _quaternions("q0", q0, dtype)
    batch = jnp.broadcast_shapes(q0.shape[:-1], gyro.shape[:-2])
    q0 = jnp.broadcast_to(q0, batch + (4,))
    if gyro.shape[-2] == 1:  # no step
        return q0[..., None, :]
    dt = _intervals("dt", dt, gyro.shape[-2], dtype, gyro)
    z = jnp.zeros(batch + (3,), dtype)
    state = NavState(q0, z, z, z, z)
    g = gyro[..., :-1, :]
    out = propagate(state, g, jnp.zeros_like(g), dt)
    return jnp.concatenate([state.q[..., None, :], out.q], axis=-2)


def orientation_errors(q_est, q_true):
    """``(r, aoe, aye)``: ``r = Log(R_trueᵀ R̂)`` ``(..., 3)`` [rad], its angle [rad] and the
    absolute yaw (ZYX Euler, about the world's z) of the world-frame error ``R̂ R_trueᵀ``
    [rad]. ``q_est``, ``q_true``: ``(..., 4)`` finite unit ``[w, x, y, z]`` quaternions whose
    batch axes broadcast."""
    dtype = float_dtype(q_est, q_true)
    q_est, q_true = _quaternions("q_est", q_est, dtype), _quaternions("q_true", q_true, dtype)
    batch_shape(q_est.shape[:-1], q_true.shape[:-1], names=("q_est", "q_true"))
    r = so3.log(so3.quat_mul(so3.quat_conj(q_true), q_est))
    aoe = jnp.linalg.norm(r, axis=-1)
    # the yaw of the world-frame error R̂ R_trueᵀ: the heading error about gravity. (The
    # difference of the two attitudes' Euler yaws is meaningless for an IMU mounted with
    # x up, as EuRoC's is: its pitch sits at the ±90° singularity.)
    yaw = so3.quat_to_euler_zyx(so3.quat_mul(q_est, so3.quat_conj(q_true)))[..., 2]
    return r, aoe, jnp.abs(yaw)


def markov_attitude(F, dt, time, save_all: bool = True):
    """The attitude error covariance ``(T, 3, 3)`` after each of the steps ``F``
    ``(T, 6, 6)`` (:func:`jaximu.learning.losses.rotation_step_blocks`' transitions of
    ``[δθ, δb_g]``) from a zero attitude error, of a gyro bias that is a first-order
    Gauss–Markov process of unit stationary standard deviation [rad/s] and correlation
    time ``time`` [s]: started from its stationary ``N(0, I)``, each step of ``dt`` [s]
    (scalar or ``(T,)``) multiplies it by ``a = exp(-dt/τ)`` and adds ``N(0, (1 - a²) I)``
    (the exact discretisation). A bias of stationary ``σ_m`` adds ``σ_m²`` times this; the
    final one alone without ``save_all``. Differentiable in ``time``."""
    h = jnp.broadcast_to(jnp.asarray(dt, F.dtype), F.shape[:-2])
    time = jnp.asarray(time).astype(F.dtype)
    eye = jnp.eye(3, dtype=F.dtype)
    a = jnp.exp(-h / time)[..., None, None]
    Fm = F.at[..., 3:6, 3:6].set(a * eye)
    Qm = jnp.zeros_like(F).at[..., 3:6, 3:6].set(-jnp.expm1(-2.0 * h / time)[..., None, None] * eye)
    P0 = jnp.zeros((6, 6), F.dtype).at[3:6, 3:6].set(eye)
    return accumulate_covariance(Fm, Qm, P0, save_all=save_all)[..., 0:3, 0:3]


def attitude_terms(gyro, density, dt, random_walk, tracked_sigma=None, markov=None):
    """``(W, B)``, each ``(T, 3, 3)``: the attitude error covariance of an open-loop run from
    a true attitude is ``W_k + B_k Σ_b B_kᵀ`` for a residual gyro bias of covariance
    ``Σ_b``. ``[δθ, δb_g]`` is propagated from zero with the per-sample ``density`` ``(T, 3)``
    and the bias ``random_walk`` (``W``), and ``B_k = ∂δθ_k/∂δb_g`` is the accumulated
    transition's bias column. The first sample's terms are zero.

    ``tracked_sigma``: ``(T, 3)`` the standard deviation of the bias that was subtracted at
    each sample (the tracker's, :meth:`jaximu.learning.Denoiser.track`), or None. Its errors
    are taken as one error shrinking with the tracker's ``σ`` (``δb_τ = diag(σ_τ) z``,
    ``z ~ N(0, I)``, fully correlated in time: the tracker's estimate moves slowly), whose
    covariance ``B'_k B'_kᵀ`` is added to ``W``: ``B'_k`` is ``B_k`` accumulated with each
    step's bias column scaled by ``σ_τ``.

    ``markov``: ``(σ_m [rad/s], τ [s])``, a Gauss–Markov part of the bias
    (:func:`markov_attitude`, independent of the rest), added to ``W``; or None."""
    F, Q = rotation_step_blocks(gyro[:-1], density[:-1], dt, random_walk)
    W = accumulate_covariance(F, Q, save_all=True)[..., 0:3, 0:3]
    if markov is not None:
        W = W + markov[0] ** 2 * markov_attitude(F, dt, markov[1])
    Phi = transition_products(F)
    z = jnp.zeros((1, 3, 3), gyro.dtype)
    if tracked_sigma is not None:
        scaled = F.at[..., 0:3, 3:6].multiply(jnp.asarray(tracked_sigma, gyro.dtype)[:-1, None, :])
        Bt = transition_products(scaled)[..., 0:3, 3:6]
        W = W + Bt @ jnp.swapaxes(Bt, -1, -2)
    return jnp.concatenate([z, W], 0), jnp.concatenate([z, Phi[..., 0:3, 3:6]], 0)


def attitude_covariance(
    gyro, density, dt, bias_sigma, random_walk, reference_sigma, tracked_sigma=None, markov=None
):
    """``(T, 3, 3)`` covariance of the attitude error at every sample of an open-loop run
    from a true attitude (:func:`attitude_terms` with ``Σ_b = σ_b² I``, the tracked
    bias's ``tracked_sigma`` and the Gauss–Markov bias ``markov``), plus the ground truth's
    own noise ``2 σ_ref² I`` (at the start and at each compared sample).

    Args:
        gyro: ``(T, 3)`` [rad/s]; density: ``(T, 3)`` [rad/s/√Hz] ``≥ 0``; dt: scalar or
            ``(T-1,)`` [s] ``> 0``; bias_sigma [rad/s], random_walk [rad/s²/√Hz]: ``≥ 0``;
            reference_sigma [rad] ``> 0``; tracked_sigma: ``(T, 3)`` [rad/s] ``≥ 0`` or None;
            markov: ``(σ_m [rad/s] ≥ 0, τ [s] > 0)`` or None (``ModelConfig.bias_markov``).
            All finite (checked on eager calls; shapes always).
    """
    dtype = float_dtype(gyro, density, dt, bias_sigma, random_walk, reference_sigma)
    gyro = to_dtype("gyro", gyro, dtype)
    if gyro.ndim != 2 or gyro.shape[-1] != 3 or gyro.shape[0] < 1:
        raise ValueError(f"gyro must have shape (T, 3) with T ≥ 1, got {tuple(gyro.shape)}")
    check_finite("gyro", gyro, "repair or drop those samples")
    T = gyro.shape[0]
    density = check_sign("density", density, dtype, unit="rad/s/√Hz")
    if density.shape != (T, 3):
        raise ValueError(f"density must have gyro's shape ({T}, 3), got {tuple(density.shape)}")
    bias_sigma = check_sign("bias_sigma", bias_sigma, dtype, unit="rad/s")
    random_walk = check_sign("random_walk", random_walk, dtype, unit="rad/s²/√Hz")
    reference_sigma = check_sign(
        "reference_sigma",
        reference_sigma,
        dtype,
        strict=True,
        unit="rad",
        fix="σ_ref > 0 keeps the first sample's covariance invertible",
    )
    for name, x in (("bias_sigma", bias_sigma), ("reference_sigma", reference_sigma)):
        if x.ndim:
            raise ValueError(f"{name} must be one number, got shape {tuple(x.shape)}")
    if random_walk.ndim and random_walk.shape != (3,):
        raise ValueError(f"random_walk must be a number or (3,), got {tuple(random_walk.shape)}")
    if tracked_sigma is not None:
        tracked_sigma = check_sign("tracked_sigma", tracked_sigma, dtype, unit="rad/s")
        if tracked_sigma.shape != (T, 3):
            raise ValueError(
                f"tracked_sigma must have gyro's shape ({T}, 3) (Corrected.gyro_bias_sigma), "
                f"got {tuple(tracked_sigma.shape)}"
            )
    if markov is not None:
        try:
            sm, tau = markov
        except (TypeError, ValueError):
            raise ValueError(
                f"markov must be a pair (sigma [rad/s], time [s]) or None, got {markov!r}"
            ) from None
        sm = check_sign("markov[0]", sm, dtype, unit="rad/s", fix="pass σ_m ≥ 0 (0: none)")
        tau = check_sign("markov[1]", tau, dtype, strict=True, unit="s", fix="pass τ > 0")
        if sm.ndim or tau.ndim:
            raise ValueError("markov must be two numbers (sigma [rad/s], time [s])")
        markov = (sm, tau)
    dt = _intervals("dt", dt, T, dtype, gyro) if T > 1 else to_dtype("dt", dt, dtype)
    W, B = attitude_terms(gyro, density, dt, random_walk, tracked_sigma, markov)
    eye = jnp.eye(3, dtype=gyro.dtype)
    return W + bias_sigma**2 * (B @ jnp.swapaxes(B, -1, -2)) + 2.0 * reference_sigma**2 * eye


@dataclasses.dataclass(frozen=True)
class Metrics:
    """Errors of one way of integrating a sequence, in degrees."""

    aoe_mean: float
    aoe_rmse: float
    aye_mean: float
    aye_rmse: float


@dataclasses.dataclass(frozen=True)
class SequenceReport:
    """Evaluation of one sequence.

    Attributes:
        name, samples, seconds: the sequence.
        metrics: ``{"raw", "constant_bias", "tracker", "learned"}`` → :class:`Metrics`
            (``"tracker"``: the tracked bias alone, for a model that tracks it).
        nees_orientation: the learned covariance's average NEES (3 when consistent).
        inside_3sigma: fraction of samples with ``NEES ≤ 14.16``.
        t: ``(M,)`` the comparison stamps [s] (the ground truth's own); aoe: ``{method:
            (M,) degrees}``; sigma3: ``(M,)`` the learned 3σ
            bound of the angle [deg] (``3 √trace S``), for plots.
    """

    name: str
    samples: int
    seconds: float
    metrics: dict
    nees_orientation: float | None
    inside_3sigma: float | None
    t: np.ndarray
    aoe: dict
    sigma3: np.ndarray | None

    def to_json(self) -> dict:
        keys = ("aoe_mean", "aoe_rmse", "aye_mean", "aye_rmse")
        out = {"name": self.name, "samples": self.samples, "seconds": self.seconds}
        for k in keys:
            out[k + "_deg"] = {m: getattr(v, k) for m, v in self.metrics.items()}
        out["nees_orientation"] = self.nees_orientation
        out["inside_3sigma"] = self.inside_3sigma
        return out


def _metrics(aoe, aye):
    d = np.degrees
    aoe, aye = np.asarray(aoe, np.float64), np.asarray(aye, np.float64)
    return Metrics(
        float(d(aoe.mean())),
        float(d(np.sqrt(np.mean(aoe**2)))),
        float(d(aye.mean())),
        float(d(np.sqrt(np.mean(aye**2)))),
    )


def _at_stamps(q, gyro, k, h):
    """The integrated attitude at the ground truth's stamps: ``q_k ⊗ Exp(ω_k h)`` for the
    sample ``k`` before each stamp and the time ``h`` from it (the sample is held over its
    interval, as the integration holds it)."""
    return so3.quat_mul(q[k], so3.exp(gyro[k] * h[:, None]))


@partial(jax.jit, static_argnames=("with_cov",))
def _learned_run(model, gyro, accel, q0, dt, k, h, q_ref, with_cov=True):
    c = model(gyro, accel)
    q = _at_stamps(integrate_attitude(q0, c.gyro, dt), c.gyro, k, h)
    r, aoe, aye = orientation_errors(q, q_ref)
    if not with_cov:
        return aoe, aye, None, None
    cfg = model.config
    S = attitude_covariance(
        c.gyro,
        c.gyro_density,
        dt,
        model.bias_sigma.astype(gyro.dtype),
        cfg.gyro_random_walk,
        model.reference_sigma.astype(gyro.dtype),
        c.gyro_bias_sigma,
        cfg.bias_markov,
    )[k]  # the sample's before the stamp (within one interval)
    L = jnp.linalg.cholesky(S)
    z = jax.scipy.linalg.solve_triangular(L, r[..., None], lower=True)[..., 0]
    return aoe, aye, jnp.sum(z * z, -1), 3.0 * jnp.sqrt(jnp.trace(S, axis1=-2, axis2=-1))


@jax.jit
def _plain_run(gyro, q0, dt, k, h, q_ref):
    q = _at_stamps(integrate_attitude(q0, gyro, dt), gyro, k, h)
    _, aoe, aye = orientation_errors(q, q_ref)
    return aoe, aye


@jax.jit
def _tracked_gyro(model, gyro, accel):
    return gyro - model.track(gyro, accel).gyro_bias


def stamp_steps(seq: Sequence) -> tuple[np.ndarray, np.ndarray]:
    """``(k, h)``: for each of the sequence's comparison stamps (:meth:`Sequence.stamps`),
    the sample before it and the time from that sample [s] (float64)."""
    tau, _ = seq.stamps()
    k = np.clip(np.searchsorted(seq.t, tau, side="right") - 1, 0, len(seq) - 2)
    return k, tau - seq.t[k]


def evaluate_sequence(model, seq: Sequence, dtype=None) -> SequenceReport:
    """Integrate ``seq`` whole from its first true attitude at the IMU rate — raw gyro, raw
    gyro minus the model's constant bias, minus the tracked bias alone (``"tracker"``, the
    model with its network's correction zeroed; only for a model that tracks its bias), the
    learned correction — and compare each with the ground truth at its own stamps
    (:meth:`Sequence.stamps`: a motion-capture dropout has none, so no error is measured
    across it). The samples are run padded to :func:`jaximu.learning.data.padded_length`
    (the last repeated; every step is causal, so the rows are the recording's own): the
    recordings of a test split, within a factor of 1.5 in length, share each compiled
    program.

    Args:
        model: a trained :class:`jaximu.learning.Denoiser`.
        seq: a :class:`Sequence` at the model's rate.
        dtype: computation dtype of the integration (default: JAX's default float).

    Raises:
        ValueError: ``model`` or ``seq`` of the wrong type; DataError: ``seq`` at another
            rate than the model's, too short for its bias tracker, or starting at a sample
            with no reference.
    """
    check_evaluable(model, seq)
    dtype = jnp.result_type(float) if dtype is None else compute_dtype("dtype", dtype)
    # the samples and the stamps padded (their last repeated) to lengths that recordings of
    # about one length share, so that each program compiles once for them (every step is
    # causal: the padding changes nothing before it, and its stamps' rows are cut off)
    N = padded_length(len(seq))
    k, h = stamp_steps(seq)
    tau, q_ref = seq.stamps()
    M, Mp = len(k), padded_length(len(k))
    cast = lambda x, n: jnp.asarray(to_length(x, n), dtype)  # noqa: E731
    gyro, accel, dt = cast(seq.gyro, N), cast(seq.accel, N), cast(seq.dt, N - 1)
    where = (
        jnp.asarray(seq.q[0], dtype),
        dt,
        jnp.asarray(to_length(k, Mp)),
        cast(h, Mp),
        cast(q_ref, Mp),
    )
    metrics = {}
    aoe = {}

    def row(name, a, y):
        a = np.asarray(a)[:M]
        metrics[name], aoe[name] = _metrics(a, np.asarray(y)[:M]), np.degrees(a)

    row("raw", *_plain_run(gyro, *where))
    row("constant_bias", *_plain_run(gyro - jnp.asarray(model.config.gyro_bias, dtype), *where))
    if model.config.bias_tracking:
        row("tracker", *_plain_run(_tracked_gyro(model, gyro, accel), *where))
    a, y, e, s3 = check_output(
        "evaluate_sequence",
        _learned_run(model, gyro, accel, *where),
        f"the model's corrections or covariance of sequence {seq.name!r} overflow {dtype.name}",
    )
    row("learned", a, y)
    e, s3 = np.asarray(e, np.float64)[:M], np.asarray(s3)[:M]
    return SequenceReport(
        seq.name,
        len(seq),
        seq.seconds,
        metrics,
        float(e.mean()),
        float(np.mean(e <= CHI2_3_3SIGMA)),
        np.asarray(tau),
        aoe,
        np.degrees(s3),
    )


@partial(jax.jit, static_argnames=("n",))
def _window_run(gyro, accel, q, p, v, dt, n):
    W = (gyro.shape[0] - 1) // n
    cut = lambda x: x[: W * n].reshape((W, n) + x.shape[1:])  # noqa: E731
    i0 = jnp.arange(W) * n
    z = jnp.zeros((W, 3), gyro.dtype)
    start = NavState(q[i0], p[i0], v[i0], z, z)
    end = propagate_final(start, cut(gyro), cut(accel), cut(dt))
    return (
        jnp.linalg.norm(end.v - v[i0 + n], axis=-1),
        jnp.linalg.norm(end.p - p[i0 + n], axis=-1),
    )


def window_errors(model, seq: Sequence, seconds: float, start: int = 0, dtype=jnp.float32) -> dict:
    """Velocity and position errors of dead reckoning over consecutive windows of
    ``seconds`` from the true state (AirIMU's setting), from sample ``start`` on (the network
    sees the samples before as context): ``{variant: (mean |δv| [m/s], mean |δp| [m])}`` for
    ``"constant_bias"`` (both sensors minus the stored biases), ``"learned_gyro"`` (the
    learned gyro, the accelerometer minus its constant bias) and ``"learned"`` (both
    corrected; the same as ``"learned_gyro"`` without an accelerometer head)."""
    n, start = window_samples(model, seq, seconds, start)
    dtype = compute_dtype("dtype", dtype)
    # padded as evaluate_sequence's (one program for recordings of about one length); the
    # windows after the recording's own are cut off
    N = padded_length(len(seq))
    windows = (len(seq) - 1 - start) // n
    cast = lambda x: jnp.asarray(to_length(x, N), dtype)  # noqa: E731
    gyro, accel = cast(seq.gyro), cast(seq.accel)
    c = model(gyro, accel)
    g0 = gyro - jnp.asarray(model.config.gyro_bias, dtype)
    a0 = accel - jnp.asarray(model.config.accel_bias, dtype)
    s = slice(start, None)
    out = {}
    for name, (g, a) in (
        ("constant_bias", (g0, a0)),
        ("learned_gyro", (c.gyro, a0)),
        ("learned", (c.gyro, c.accel)),
    ):
        dv, dp = check_output(
            "window_errors",
            _window_run(
                g[s], a[s], cast(seq.q)[s], cast(seq.p)[s], cast(seq.v)[s], cast(seq.dt)[s], n
            ),
            f"the dead reckoning of sequence {seq.name!r} overflows {dtype.name}",
        )
        dv, dp = np.asarray(dv)[:windows], np.asarray(dp)[:windows]
        out[name] = (float(np.mean(dv)), float(np.mean(dp)))
    return out


def window_samples(model, seq: Sequence, seconds: float, start: int = 0) -> tuple[int, int]:
    """``(n, start)``: the samples per window of ``seconds`` at ``seq``'s rate, and
    ``start``, once checked: ``model`` a :class:`jaximu.learning.Denoiser`, ``seq`` a
    :class:`Sequence` at its rate, ``seconds`` positive and between one sample interval and
    the recording's length from sample ``start`` on (:func:`window_errors`, and the
    windowed NEES, :func:`jaximu.learning.uncertainty.window_nees`); else an error naming
    the argument and the range to pass."""
    check_model("model", model)
    check_sequence("seq", seq)
    check_rate(seq, model.config.rate_hz)
    check_positive("seconds", seconds, hint=": pass the window's length [s], e.g. 1.0")
    start = check_int("start", start, 0)
    if start > len(seq) - 2:
        raise InputError(
            f"start = {start} leaves no step of sequence {seq.name!r} ({len(seq)} samples)",
            [Fix("start", 0)],
            lead="pass a smaller one, e.g.",
        )
    n = int(round(seconds * seq.rate_hz))
    span = (len(seq) - 1 - start) / seq.rate_hz
    if n < 1 or n > len(seq) - 1 - start:
        what = "shorter than one sample interval" if n < 1 else "longer than"
        raise InputError(
            f"seconds = {seconds!r}: a window {what} the {span:.4g} s of sequence "
            f"{seq.name!r} from sample {start} on",
            [Fix("seconds", phrase=f"{{}} between {1 / seq.rate_hz:.3g} and {span:.4g}")],
            lead="pass",
        )
    return n, start


def check_evaluable(model, seq: Sequence, name: str = "seq") -> None:
    """Everything :func:`evaluate_sequence` checks before its work, for a command to check
    each of its sequences before the first is evaluated: ``model`` a
    :class:`jaximu.learning.Denoiser` with finite weights, ``seq`` (named ``name``) a
    :class:`Sequence` at its rate, long enough for its bias tracker, starting at a sample
    with a reference."""
    check_model("model", model)
    check_sequence(name, seq)
    check_rate(seq, model.config.rate_hz)
    if model.config.bias_tracking and len(seq) < LEVEL_SAMPLES:
        raise DataError(
            f"sequence {seq.name!r}: its ground truth covers {len(seq)} IMU samples, and the "
            f"model's bias tracker needs at least {LEVEL_SAMPLES} (it levels the first "
            "attitude on their mean specific force): give a recording whose ground truth "
            "covers more of it"
        )
    if not seq.has_reference[0]:
        raise DataError(
            f"sequence {seq.name!r} starts inside a ground-truth gap, with no true attitude "
            "to start from: slice it from its first sample with a reference "
            "(seq.slice(int(np.argmax(seq.has_reference))))"
        )
