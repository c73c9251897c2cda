"""Gradient-based IMU calibration against a reference trajectory.

The sensor model (the one :func:`jaximu.simulate.add_noise` draws from)::

    w_m = (I + S_g) ω + b_g + n_g,      a_m = (I + S_a) f + b_a + n_a,

with ``S = diag(scale) + L(misalignment)``: scale-factor errors on the diagonal and the
three misalignment terms ``[S_10, S_20, S_21]`` strictly below it (the lower-triangular
form of Kalibr's ``scale-misalignment`` model). The reference (motion capture or a
dataset's ground truth) is time-stamped on its own clock: IMU time ``t`` is reference time
``t + time_offset``.

The reference tracks its own body frame B; the IMU frame S may be rotated from it by
``q_BS`` and sit at the lever arm ``p_BS`` (the extrinsics, :class:`jaximu.SensorPose`;
``body_P_sensor`` in :func:`jaximu.preintegrate`). With ``extrinsics=True`` in
:func:`calibration_problem` they join the model (and may be estimated: ``estimate=(...,
"q_BS", "p_BS")``); the frame check then initialises ``q_BS`` in closed form instead of
refusing a rotated IMU: the rotation vectors of the windows satisfy ``φ_B = R_BS φ_S``
exactly, a least-squares rotation fit (Wahba's problem, with a constant for the bias).

The loss compares the corrected IMU with the reference between keyframes a fixed number of
samples apart: the 9-dim preintegration residual ``[r_θ, r_p, r_v]`` of
:func:`jaximu.residual` (``model="preintegration"``), or the same quantities from
:func:`jaximu.propagate_final` started at the reference state (``model="propagation"``;
equal for ``"euler"``), whitened by the residual covariance (preintegration noise plus the
reference's own noise), ``loss = ½ Σ_k |L_k⁻¹ r_k|²``. The whitening is computed once at the
start (it depends on the samples, not on the parameters). Where the reference has no
velocities, the keyframe velocities are estimated with the parameters (nuisance).

The reference is not interpolated across its dropouts (motion capture loses the body for
tenths of a second): a window with a keyframe inside a reference gap longer than
``GAP_FACTOR`` × the reference's median interval (:meth:`jaximu.io.GroundTruth.interpolate`'s
rule) is left out of the fit (weight 0: nothing of it reaches the loss or its gradient), and
:attr:`CalibrationProblem.skip_note` says how many and which gaps.

Windows are evaluated in groups under :func:`jax.checkpoint`, so reverse-mode memory is
that of one group plus one scalar per group: gradients through 10⁶ samples fit in a laptop's
memory (``benchmarks/calibration.py`` measures it).

Parameters are optimised in normalised coordinates ``z = (θ - θ₀) / scale`` (the
:data:`SCALES`: 0.01 rad/s for ``b_g``, 0.1 m/s² for ``b_a``, ...), so one learning rate
suits every field. The uncertainty is the Gauss-Newton / Laplace approximation
``cov = (JᵀJ)⁻¹`` of the whitened residuals at the optimum; it is right when the noise
model is (check ``reduced_chi2`` ≈ 1).

The fit (:func:`calibrate`) is Levenberg–Marquardt on the whitened residuals by default:
one compiled function returns the residuals and their Jacobian (``jacfwd`` over the free
coordinates; 6 tangents per window for nuisance velocities) and serves every iteration and
the covariance. optax L-BFGS and Adam on the loss are there too.

Adding an estimable field (an IMU–body extrinsic, say): a pytree field of
:class:`ImuCalibration` with its default in :meth:`ImuCalibration.default`; its name in
:data:`FIELDS`, its size in ``_SIZES``, its typical magnitude in :data:`SCALES` (the unit of
its normalised coordinate); and its use in ``_group_residuals``, the one place the model
meets the data. The optimisers, the Jacobian, the Laplace covariance and ``estimate=`` follow.
Coordinates are additive (``θ = θ₀ + scale · z``), so a rotation is best estimated as a
rotation vector ``δ`` applied as ``R₀ Exp(δ)`` inside the model (``δ₀ = 0``).
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaximu import _validation as val
from jaximu.errors import Fix, InputError
from jaximu.io._common import GAP_FACTOR, in_gap
from jaximu import so3
from jaximu.noise import ImuNoise
from jaximu._preintegration_engine import Preintegrated, _chunk_scan, _pairs, _preintegrate
from jaximu._preintegration_steps import _step as _pim_step
from jaximu.preintegration import residual
from jaximu.propagate import propagate_final
from jaximu import world
from jaximu.sensor import SensorPose, to_body
from jaximu.state import ImuBias, NavState

__all__ = [
    "ImuCalibration",
    "Reference",
    "CalibrationProblem",
    "CalibrationResult",
    "CalibrationError",
    "calibration_problem",
    "calibration_loss",
    "calibration_residuals",
    "calibrate",
    "FIELDS",
    "SCALES",
]

FIELDS = ("b_g", "b_a", "gyro_scale", "gyro_misalignment", "accel_scale",
          "accel_misalignment", "gravity", "time_offset", "q_BS", "p_BS")
_SIZES = {"b_g": 3, "b_a": 3, "gyro_scale": 3, "gyro_misalignment": 3, "accel_scale": 3,
          "accel_misalignment": 3, "gravity": 1, "time_offset": 1, "q_BS": 4, "p_BS": 3}
_TANGENT = dict(_SIZES, q_BS=3)  # q_BS is estimated as a rotation vector: q̂ ⊗ Exp(δθ)
SCALES = {"b_g": 1e-2, "b_a": 1e-1, "gyro_scale": 1e-2, "gyro_misalignment": 1e-2,
          "accel_scale": 1e-2, "accel_misalignment": 1e-2, "gravity": 1e-1,
          "time_offset": 1e-2, "q_BS": 1e-2, "p_BS": 1e-1}
"""Typical magnitude of each field [its units]: the unit of the normalised coordinates."""
EXCITATION = {"q_BS": np.deg2rad(0.5), "p_BS": 0.02}
"""σ [rad, m] above which :func:`calibrate` warns that the motion does not excite the
extrinsics it estimates (turn the body faster, about more axes)."""
_VELOCITY_SCALE = 0.1  # m/s, nuisance keyframe velocities
MODELS = ("preintegration", "propagation")
OPTIMIZERS = ("lm", "lbfgs", "adam")


class CalibrationError(InputError):
    """The data cannot be calibrated as given (units, frames or conventions disagree)."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ImuCalibration:
    """IMU intrinsics and the IMU–reference time offset (a pytree; fields may be batched).

    Attributes:
        b_g: ``(..., 3)`` gyroscope bias [rad/s]; b_a: ``(..., 3)`` accelerometer bias [m/s²].
        gyro_scale, accel_scale: ``(..., 3)`` scale-factor errors (diagonal of ``S``) [-].
        gyro_misalignment, accel_misalignment: ``(..., 3)`` ``[S_10, S_20, S_21]`` [-].
        gravity: ``(...)`` gravity magnitude [m/s²] (``g_W = [0, 0, -g]``).
        time_offset: ``(...)`` IMU time minus reference time of one instant [s].
        q_BS: ``(..., 4)`` the IMU's rotation in the reference's body frame, ``[w, x, y, z]``
            (default identity; used with ``extrinsics``). In :attr:`CalibrationResult.std`
            it holds the ``(3,)`` σ of the rotation vector ``δθ`` of ``q̂ ⊗ Exp(δθ)`` [rad].
        p_BS: ``(..., 3)`` the IMU's origin in the body frame, the lever arm [m].
    """

    b_g: jax.Array
    b_a: jax.Array
    gyro_scale: jax.Array
    gyro_misalignment: jax.Array
    accel_scale: jax.Array
    accel_misalignment: jax.Array
    gravity: jax.Array
    time_offset: jax.Array
    q_BS: jax.Array
    p_BS: jax.Array

    @classmethod
    def default(cls, gravity=9.81, dtype=None, **fields) -> "ImuCalibration":
        """Zero biases, scale, misalignment and offset (unless given in ``fields``)."""
        dtype = val.compute_dtype("dtype", dtype) if dtype is not None else \
            jnp.zeros(()).dtype
        vals = {name: jnp.zeros((_SIZES[name],) if _SIZES[name] > 1 else (), dtype)
                for name in FIELDS}
        vals["gravity"] = val.to_dtype("gravity", gravity, dtype)
        vals["q_BS"] = jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype)
        for name, x in fields.items():
            if name not in vals:
                raise ValueError(f"unknown calibration field {name!r}; fields are {FIELDS}")
            vals[name] = val.to_dtype(name, x, dtype)
        return cls(**vals)

    @property
    def bias(self) -> ImuBias:
        return ImuBias(self.b_g, self.b_a)

    @property
    def body_P_sensor(self) -> SensorPose:
        """The extrinsics as a :class:`jaximu.SensorPose`."""
        return SensorPose(self.q_BS, self.p_BS)

    def gyro_matrix(self):
        """``(..., 3, 3)`` ``I + S_g``."""
        return sensor_matrix(self.gyro_scale, self.gyro_misalignment)

    def accel_matrix(self):
        """``(..., 3, 3)`` ``I + S_a``."""
        return sensor_matrix(self.accel_scale, self.accel_misalignment)

    def apply(self, gyro, accel):
        """Corrected samples ``(I + S)⁻¹ (m - b)`` from raw ``(..., T, 3)`` ones."""
        def fix(M, b, x):
            Minv = jnp.linalg.inv(M)[..., None, :, :]
            return jnp.einsum("...ij,...j->...i", Minv, x - b[..., None, :])

        return (fix(self.gyro_matrix(), self.b_g, gyro),
                fix(self.accel_matrix(), self.b_a, accel))


def sensor_matrix(scale, misalignment):
    """``I + diag(scale) + L(misalignment)`` with ``L`` strictly lower: ``(..., 3, 3)``."""
    s, m = jnp.asarray(scale), jnp.asarray(misalignment)
    z = jnp.zeros_like(s[..., 0])
    one = jnp.ones_like(z)
    rows = [
        jnp.stack([one + s[..., 0], z, z], -1),
        jnp.stack([m[..., 0], one + s[..., 1], z], -1),
        jnp.stack([m[..., 1], m[..., 2], one + s[..., 2]], -1),
    ]
    return jnp.stack(rows, -2)


@dataclasses.dataclass(frozen=True)
class Reference:
    """A reference trajectory of the IMU (body) frame, on the reference clock.

    Attributes:
        t: ``(M,)`` strictly increasing times [s].
        q: ``(M, 4)`` ``[w, x, y, z]`` of ``R_WB`` (within 1e-3 of unit norm; a normalised
            copy is used); p: ``(M, 3)`` positions in W [m].
        v: ``(M, 3)`` velocities in W [m/s], or ``None`` (then estimated at the keyframes).
    """

    t: np.ndarray
    q: np.ndarray
    p: np.ndarray
    v: np.ndarray | None = None


# --------------------------------------------------------------------------- the problem


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class CalibrationProblem:
    """Windows of IMU samples between keyframes with the reference, ready for a loss.

    Built by :func:`calibration_problem`. ``K`` windows of ``W`` samples, padded to
    ``G × C`` (groups of ``C = windows_per_group``; padding windows have weight 0).

    Attributes:
        gyro, accel: ``(G, C, W + 1, 3)`` raw samples, keyframe to keyframe; dt:
            ``(G, C, W)`` the intervals between them [s].
        t_start, t_end: ``(G, C)`` IMU times of each window's keyframes [s].
        window: ``(G, C)`` index of each window (its velocity is ``velocities[window]``).
        weight: ``(G, C)`` 1 for a window in the fit; 0 for padding and for a window left
            out because a keyframe of it falls inside a reference gap (see ``skipped``).
        sqrt_info: ``(G, C, 9, 9)`` ``L⁻¹`` of each residual covariance.
        ref_t, ref_q, ref_p, ref_v: the reference (``ref_v`` zeros when it has none).
        velocities: ``(K + 1, 3)`` keyframe velocities (reference or finite differences).
        scheme, model, has_velocity: static settings.
        diagnostics: the consistency checks' numbers (``gyro_ratio``, ``gyro_frame_error``,
            ``accel_ratio``, ``accel_frame_error``; NaN where the motion could not tell);
            with ``extrinsics`` also the closed-form rotation ``q_BS0``, its angle
            ``q_BS0_angle`` [rad], the likelihood ratio ``q_BS0_statistic`` against the
            identity and ``q_BS0_from`` (``"gyro"``, ``"accel"`` or ``"none"``).
        q_BS0: ``(4,)`` that closed-form ``q_BS`` (``None`` without ``extrinsics``).
        extrinsics: the residuals use ``q_BS``, ``p_BS`` (static).
        sample_density2: ``(2, 3)`` ``σ_g², σ_a²`` per axis; reference_var: ``(G, C, 9)``
            the reference's part of each residual's variance (for re-whitening).
        omega_coriolis: ``(3,)`` the world's rotation rate, or ``None``.
        max_gap: the longest reference interval interpolated across [s]: ``GAP_FACTOR`` × the
            reference's median interval, the rule of :meth:`jaximu.io.GroundTruth.interpolate`
            (static).
        skipped: the reference gaps that left windows out, ``((t, length, windows), ...)``:
            each gap's start on the reference clock [s], its length [s] and the number of
            windows with a keyframe inside it (static). :attr:`n_skipped` counts the windows
            left out, :attr:`skip_note` says it in words.
    """

    gyro: jax.Array
    accel: jax.Array
    dt: jax.Array
    t_start: jax.Array
    t_end: jax.Array
    window: jax.Array
    weight: jax.Array
    sqrt_info: jax.Array
    ref_t: jax.Array
    ref_q: jax.Array
    ref_p: jax.Array
    ref_v: jax.Array
    velocities: jax.Array
    scheme: str = dataclasses.field(metadata=dict(static=True), default="euler")
    model: str = dataclasses.field(metadata=dict(static=True), default="preintegration")
    has_velocity: bool = dataclasses.field(metadata=dict(static=True), default=True)
    diagnostics: dict = dataclasses.field(default_factory=dict)
    n_windows: int = dataclasses.field(metadata=dict(static=True), default=0)
    q_BS0: jax.Array | None = None
    extrinsics: bool = dataclasses.field(metadata=dict(static=True), default=False)
    sample_density2: jax.Array | None = None
    reference_var: jax.Array | None = None
    omega_coriolis: jax.Array | None = None
    max_gap: float = dataclasses.field(metadata=dict(static=True), default=float("inf"))
    skipped: tuple = dataclasses.field(metadata=dict(static=True), default=())

    @property
    def n_samples(self) -> int:
        return self.n_windows * self.dt.shape[-1]

    @property
    def kept(self) -> np.ndarray:
        """``(K,)`` whether each window is in the fit (not left out for a reference gap)."""
        return np.asarray(self.weight).reshape(-1)[: self.n_windows] > 0

    @property
    def n_skipped(self) -> int:
        """How many of the ``n_windows`` windows are left out for reference gaps."""
        return int(self.n_windows - np.count_nonzero(self.kept))

    @property
    def skip_note(self) -> str:
        """The windows left out and the gaps that did it, in one line ("" when none)."""
        return _skip_note(self.n_skipped, self.n_windows, self.max_gap, self.skipped)


def _interp(problem_t, ref_t, ref_q, ref_p, ref_v):
    """Reference pose and velocity at ``problem_t`` (linear, slerp; extrapolated past the ends)."""
    M = ref_t.shape[0]
    i = jnp.clip(jnp.searchsorted(ref_t, problem_t, side="right") - 1, 0, M - 2)
    t0, t1 = ref_t[i], ref_t[i + 1]
    a = ((problem_t - t0) / (t1 - t0))[..., None]  # no clip: exact gradients in time
    q0, q1 = ref_q[i], ref_q[i + 1]
    q = so3.quat_mul(q0, so3.exp(a * so3.log(so3.quat_mul(so3.quat_conj(q0), q1))))
    return q, ref_p[i] + a * (ref_p[i + 1] - ref_p[i]), ref_v[i] + a * (ref_v[i + 1] - ref_v[i])


def _window_residuals(problem: CalibrationProblem, calib: ImuCalibration, velocities, g_idx):
    """``(C, 9)`` whitened residuals of group ``g_idx`` (weights applied)."""
    if problem.has_velocity:
        return _group_residuals(problem, calib, g_idx)
    k = problem.window[g_idx]
    return _group_residuals(problem, calib, g_idx, velocities[k], velocities[k + 1])


def _group_residuals(problem: CalibrationProblem, calib: ImuCalibration, g_idx, vi=None,
                     vj=None, gyro=None, accel=None, raw=False):
    """``(C, 9)`` whitened residuals of group ``g_idx``; ``vi``, ``vj``: ``(C, 3)`` keyframe
    velocities of each window's ends (default: the reference's); ``gyro``, ``accel``: the
    group's raw samples (default: the problem's); ``raw``: the residuals before whitening."""
    gyro = problem.gyro[g_idx] if gyro is None else gyro
    accel = problem.accel[g_idx] if accel is None else accel
    dt = problem.dt[g_idx]
    td = calib.time_offset
    ends = jnp.stack([problem.t_start[g_idx], problem.t_end[g_idx]]) + td  # one graph, both
    (qi, qj), (pi, pj), (vi_ref, vj_ref) = _interp(ends, problem.ref_t, problem.ref_q,
                                                   problem.ref_p, problem.ref_v)
    if vi is None:
        vi, vj = vi_ref, vj_ref
    gyro_c, accel_c = calib.apply(gyro, accel)
    zero = jnp.zeros_like(pi)
    state_i = NavState(qi, pi, vi, zero, zero)
    state_j = NavState(qj, pj, vj, zero, zero)
    pose = calib.body_P_sensor if problem.extrinsics else None
    if problem.model == "preintegration":
        if pose is not None:  # the sensor's samples as the body's (jaximu/sensor.py)
            gyro_c, accel_c = to_body(pose, gyro_c, accel_c, dt, jnp.zeros_like(pi))
        pim = _preintegrate_mean(gyro_c, accel_c, dt, problem.scheme)
        r = residual(state_i, state_j, pim, gravity=calib.gravity,
                     omega_coriolis=problem.omega_coriolis)[..., :9]
    else:
        pred = propagate_final(state_i, gyro_c, accel_c, dt, problem.scheme,
                               gravity=calib.gravity, body_P_sensor=pose,
                               omega_coriolis=problem.omega_coriolis)
        qi_inv = so3.quat_conj(qi)
        r = jnp.concatenate([
            so3.log(so3.quat_mul(so3.quat_conj(pred.q), qj)),
            so3.quat_rotate(qi_inv, pj - pred.p),
            so3.quat_rotate(qi_inv, vj - pred.v),
        ], axis=-1)
    if raw:
        return r
    w = jnp.einsum("...ij,...j->...i", problem.sqrt_info[g_idx], r)
    return w * problem.weight[g_idx][..., None]


def _sample_noise_covariance(problem: CalibrationProblem, calib: ImuCalibration, velocities):
    """``(G, C, 9, 9)`` covariance of the residuals from white noise on every raw sample
    (variance ``σ²/h``, ``h`` the sample's interval), ``J diag(σ²/h) Jᵀ`` with ``J`` by
    ``jax.jacfwd`` of the residuals in the samples (one perturbation shared by the group's
    windows, which are independent). Exact for the model the residual computes, the lever
    arm's ``ω×(ω×r) + α×r`` included (``α`` differentiates noisy rates), of which the
    preintegration covariance holds the first only (:mod:`jaximu.sensor`)."""
    dens2 = problem.sample_density2  # (2, 3): σ_g², σ_a² per axis

    def group(g):
        gyro, accel = problem.gyro[g], problem.accel[g]

        def f(d):
            vi = vj = None
            if not problem.has_velocity:
                k = problem.window[g]
                vi, vj = velocities[k], velocities[k + 1]
            return _group_residuals(problem, calib, g, vi, vj, gyro + d[0], accel + d[1],
                                    raw=True)

        J = jax.jacfwd(f)(jnp.zeros((2,) + gyro.shape[-2:], gyro.dtype))  # (C, 9, 2, W+1, 3)
        h = problem.dt[g]
        h = jnp.concatenate([h, h[:, -1:]], -1)  # the last sample: its window's last interval
        var = dens2[None, :, None, :] / h[:, None, :, None]
        return jnp.einsum("cixyz,cxyz,cjxyz->cij", J, var, J)

    return jax.lax.map(group, jnp.arange(problem.gyro.shape[0]))


def _preintegrate_mean(gyro, accel, dt, scheme):
    """The preintegrated mean of ``(C, W + 1, 3)`` windows, as :func:`jaximu.preintegrate`
    computes it (its step and scan; zero bias: the samples are already corrected), without
    the noise, the bias Jacobians or the covariance: the loss is differentiated (``jacfwd``,
    ``grad``) through it, and a graph carrying the 15×15 blocks (or the structure-of-arrays
    kernels the dispatch table picks for many windows) compiles for longer than a whole
    calibration runs. The returned ``transition`` is zero (no bias correction is applied:
    the states' biases are zero) and the covariances identity (unused: the whitening is
    computed once, in :func:`calibration_problem`)."""
    dtype = gyro.dtype
    batch = gyro.shape[:-2]
    w0, a0, w1, a1, h = _pairs(gyro, accel, dt, scheme)
    zero = jnp.zeros(batch + (3,), dtype)
    final, _ = _chunk_scan(scheme, _pim_step, zero, zero, None, (None, w0, a0, w1, a1, h, None),
                           batch, dtype, False, blocks=False)
    dq, dv, dp, t, _ = final
    eye = lambda n: jnp.broadcast_to(jnp.eye(n, dtype=dtype), batch + (n, n))  # noqa: E731
    return Preintegrated(delta_t=t, delta_q=so3.quat_normalize(dq), delta_v=dv, delta_p=dp,
                         transition=jnp.zeros(batch + (15, 15), dtype), cov15=eye(15),
                         cov=eye(9), bias_hat=ImuBias(zero, zero))


def _check_loss_args(problem, calib, velocities):
    """Types (and ``velocities``' shape) of :func:`calibration_loss`'s arguments: static,
    so free inside ``jit``/``grad``. Returns the velocities to use."""
    if not isinstance(problem, CalibrationProblem):
        raise ValueError("problem must be a CalibrationProblem (from calibration_problem), got "
                         f"{type(problem).__name__}")
    if not isinstance(calib, ImuCalibration):
        raise ValueError("calib must be an ImuCalibration (e.g. ImuCalibration.default()), got "
                         f"{type(calib).__name__}")
    if velocities is None:
        return problem.velocities
    if jnp.shape(velocities) != problem.velocities.shape:
        raise ValueError(f"velocities must have the shape {problem.velocities.shape} of "
                         f"problem.velocities (one per keyframe), got {jnp.shape(velocities)}")
    return velocities


def calibration_residuals(problem: CalibrationProblem, calib: ImuCalibration,
                          velocities=None):
    """``(K, 9)`` whitened residuals ``L_k⁻¹ [r_θ, r_p, r_v]_k`` of every window (zero for
    a window left out for a reference gap: :attr:`CalibrationProblem.kept`)."""
    v = _check_loss_args(problem, calib, velocities)
    G = problem.gyro.shape[0]
    r = jax.vmap(lambda g: _window_residuals(problem, calib, v, g))(jnp.arange(G))
    return r.reshape(-1, 9)[: problem.n_windows]


def calibration_loss(problem: CalibrationProblem, calib: ImuCalibration, velocities=None):
    """``½ Σ_k |L_k⁻¹ r_k|²`` (a scalar), differentiable in ``calib`` and ``velocities``.

    Groups of windows are scanned under :func:`jax.checkpoint`: reverse mode stores one
    group's intermediates at a time.
    """
    v = _check_loss_args(problem, calib, velocities)

    @jax.checkpoint
    def group(g):
        r = _window_residuals(problem, calib, v, g)
        return 0.5 * jnp.sum(r * r)

    def body(acc, g):
        return acc + group(g), None

    dtype = problem.gyro.dtype
    total, _ = jax.lax.scan(body, jnp.zeros((), dtype), jnp.arange(problem.gyro.shape[0]))
    return total


QUICK_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
"""XLA options for graphs that run once or a few times on little data: about half the
compile time, several times the run time (benchmarks/calibration.py --command: a cold
`jaximu calibrate` on 30 s at 200 Hz is mostly compilation)."""
QUICK_COMPILE_SAMPLES = 30_000
"""Problems of at most this many samples (150 s at 200 Hz) compile their fit with
:data:`QUICK_COMPILE`: one evaluation of the residuals and their Jacobian then takes about
0.1 s per 6,000 samples instead of 0.015 s, less than the compile time it saves over the
ten-odd evaluations of a Levenberg–Marquardt fit."""


@functools.lru_cache(maxsize=None)
def _compiled(fn, quick: bool, static_argnames=()):
    """``jax.jit(fn)``, with :data:`QUICK_COMPILE` when ``quick``."""
    return jax.jit(fn, static_argnames=static_argnames,
                   compiler_options=QUICK_COMPILE if quick else None)


def _once(fn):
    """``fn`` jitted with :data:`QUICK_COMPILE`, for the one-shot computations of
    :func:`calibration_problem` and its checks: run op by op, JAX would compile every
    primitive apart (about 0.1 s each on 2 cores, 12 s of a cold `jaximu calibrate`)."""
    return _compiled(fn, True)


def _keyframe_rotations(q):
    """``R_i`` ``(K, 3, 3)`` of keyframes ``0..K-1`` and the rotation vectors ``(K, 3)`` of
    ``q_i⁻¹ q_{i+1}``, from ``(K + 1, 4)`` keyframe attitudes."""
    return (so3.quat_to_matrix(q[:-1]),
            so3.log(so3.quat_mul(so3.quat_conj(q[:-1]), q[1:])))


def _apply(calib, gyro, accel):
    return calib.apply(gyro, accel)


def _preintegrate_sequential(gyro, accel, dt, bias, noise, *, scheme, fast):
    return _preintegrate(gyro, accel, dt, bias, noise, scheme=scheme, method="sequential",
                         jacobians="analytic", prefixes=False, fast=fast)


def _rotation_vectors(dq):
    return np.asarray(_once(so3.log)(dq), np.float64)


GYRO_BIAS_MAX = 0.5
"""Largest gyro bias [rad/s] the checks put down to the sensor (29 °/s: beyond the turn-on
bias of any MEMS gyro); a larger steady disagreement with the reference is a unit mistake."""
FRAME_ANGLE_TOL = 0.3
"""Smallest rotation [rad] (17°) between the IMU's axes and the reference's body frame that the
frame check reports, when the data determine it."""
FRAME_SIGNIFICANCE = 21.1
"""χ²(3) at 1 - 1e-4: how far beyond its own uncertainty a fitted rotation must be."""


def _rotation_fit(x, y, floor):
    """Wahba's problem ``y ≈ R x + c`` over rows (the constant absorbs a bias: ``b Δt`` per
    window): the best rotation's vector ``θ`` and the likelihood-ratio statistic of ``R``
    against ``I``, ``(RSS(I) - RSS(R)) / σ²``, ``χ²(3)`` if the frames agree. ``σ²`` is the
    residual variance per component, at least ``floor²`` (the reference's own noise), so
    rows that barely vary (a still segment) cannot make a rotation significant: the check
    judges only what the data can show."""
    x, y = x - x.mean(0), y - y.mean(0)
    U, _, Vt = np.linalg.svd(x.T @ y)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    theta = np.asarray(_once(so3.log_matrix)(jnp.asarray(R)), np.float64)
    rss_r = float(np.sum((y - x @ R.T) ** 2))
    rss_i = float(np.sum((y - x) ** 2))
    dof = max(3 * len(x) - 6, 1)
    sigma2 = max(rss_r / dof, floor**2, 1e-300)
    return theta, (rss_i - rss_r) / sigma2


def _check_frame(name, x_imu, x_ref, floor, diag):
    label = "gyroscope" if name == "gyro" else "accelerometer"
    what = "rotation" if name == "gyro" else "velocity change"
    if len(x_imu) < 3:
        return
    theta, stat = _rotation_fit(x_imu, x_ref, floor)
    angle = float(np.linalg.norm(theta))
    diag[f"{name}_frame_error"] = angle
    if angle > FRAME_ANGLE_TOL and stat > FRAME_SIGNIFICANCE:
        raise CalibrationError(
            f"the {label}'s axes do not match the reference's body frame: the {what} per "
            f"window fits ref ≈ R imu best with R a rotation of {np.degrees(angle):.0f}° about "
            f"{np.array2string(theta / angle, precision=2)} (likelihood ratio {stat:.3g} against "
            "R = I). Is the reference the pose of the IMU frame, and its quaternion "
            "[w, x, y, z] of R_WB? If the IMU is mounted rotated on the reference's body, pass "
            "extrinsics=True (jaximu calibrate: --estimate ...,q_BS): the rotation then "
            "starts from this fit and is estimated (q_BS)")


def _check_consistency(phi_imu, phi_ref, dv_imu, dv_ref, Dt, reference_sigma=(1e-3, 1e-3, 1e-2)):
    """Catch unit and frame mistakes before fitting (see :func:`calibration_problem`),
    judging only what the data can show and blaming the sensor that is wrong.

    1. Gyro units, where the reference turns (> 0.2 rad/s in at least 3 windows): the
       median ratio of the rotations must be within a factor 3 of 1 (deg/s gives 57).
       Where it does not turn, the gyro's mean rate must not exceed the reference's by more
       than a bias can (:data:`GYRO_BIAS_MAX`): a still deg/s gyro reads its bias × 57.
    2. Accelerometer units: the median ratio of the velocity changes (gravity included,
       always excited) within a factor 3 of 1 (g gives 0.10).
    3. Frames: the best rotation between the IMU's and the reference's rotations (with a
       bias constant) and velocity changes must be below :data:`FRAME_ANGLE_TOL` or not
       significant (:func:`_rotation_fit`; the reference's ``σ_θ``, ``σ_v`` bound the noise
       from below).
    """
    diag = dict.fromkeys(("gyro_ratio", "gyro_frame_error", "accel_ratio",
                          "accel_frame_error"), np.nan)
    rate_ref = np.linalg.norm(phi_ref, axis=-1) / Dt
    rate_imu = np.linalg.norm(phi_imu, axis=-1) / Dt
    moving = rate_ref > 0.2  # rad/s; below, a bias could dominate the gyro's magnitude
    if moving.sum() >= 3:
        ratio = float(np.median(rate_imu[moving] / rate_ref[moving]))
        diag["gyro_ratio"] = ratio
        if not 1 / 3 < ratio < 3:
            raise CalibrationError(
                f"the gyroscope's rotation is {ratio:.3g} times the reference's (expected ≈ 1): "
                "a gyro in deg/s read as rad/s gives ≈ 57; convert to rad/s")
    excess = float(np.median(rate_imu - rate_ref))
    if excess > GYRO_BIAS_MAX:
        raise CalibrationError(
            f"the gyroscope reads {float(np.median(rate_imu)):.3g} rad/s (median over the windows) "
            f"where the reference turns at {float(np.median(rate_ref)):.3g} rad/s: more than a "
            f"bias can explain ({GYRO_BIAS_MAX:g} rad/s); is the gyro in deg/s? convert to rad/s")
    ratio = float(np.median(np.linalg.norm(dv_imu, axis=-1)
                            / np.maximum(np.linalg.norm(dv_ref, axis=-1), 1e-300)))
    diag["accel_ratio"] = ratio
    if not 1 / 3 < ratio < 3:
        raise CalibrationError(
            f"the accelerometer's velocity change is {ratio:.3g} times the reference's (expected"
            " ≈ 1): an accelerometer in g read as m/s² gives ≈ 0.10; convert to m/s²")
    s_th, _, s_v = (max(float(x), 0.0) for x in reference_sigma)
    _check_frame("gyro", phi_imu, phi_ref, np.sqrt(2) * s_th, diag)
    _check_frame("accel", dv_imu, dv_ref, np.sqrt(2) * s_v, diag)
    return diag


def _initial_rotation(phi_imu, phi_ref, dv_imu, dv_ref, reference_sigma):
    """The closed-form ``R_BS``: the least-squares rotation (:func:`_rotation_fit`) of the
    windows' rotation vectors (``φ_B = R_BS φ_S``), or, where the rotations do not
    determine it, of their velocity changes (gravity always excites them); the identity
    where neither does. Returns ``(θ, statistic, source)`` with ``R_BS = Exp(θ)``.

    Determined: the second singular value of the centred inputs exceeds 10× the fit's
    residual noise (two independent directions of motion)."""
    s_th, _, s_v = (max(float(x), 0.0) for x in reference_sigma)
    for source, x, y, floor in (("gyro", phi_imu, phi_ref, np.sqrt(2) * s_th),
                                ("accel", dv_imu, dv_ref, np.sqrt(2) * s_v)):
        if len(x) < 3:
            continue
        theta, stat = _rotation_fit(x, y, floor)
        xc, yc = x - x.mean(0), y - y.mean(0)
        R = np.asarray(_once(so3.exp_matrix)(jnp.asarray(theta)), np.float64)
        sigma = np.sqrt(max(float(np.sum((yc - xc @ R.T) ** 2)) / max(3 * len(x) - 6, 1),
                            floor**2, 1e-300))
        if np.linalg.svd(xc, compute_uv=False)[1] > 10 * sigma:
            return theta, stat, source
    return np.zeros(3), np.nan, "none"


def _check_initial(initial):
    """``initial``: ``None`` or an :class:`ImuCalibration` of single (unbatched) fields of
    their documented shapes, finite, with a unit ``q_BS`` (relative 1e-3, as
    :class:`Reference`'s quaternions) and ``gravity ≥ 0`` (a magnitude)."""
    if initial is None:
        return
    if not isinstance(initial, ImuCalibration):
        raise ValueError(f"initial must be an ImuCalibration or None, got {type(initial).__name__}")
    for name in FIELDS:
        x = np.asarray(getattr(initial, name), np.float64)
        shape = (_SIZES[name],) if _SIZES[name] > 1 else ()
        if x.shape != shape:
            raise ValueError(f"initial.{name} must have shape {shape}, got {x.shape}")
        val.check_finite(f"initial.{name}", x)
    val.check_unit_norm("initial.q_BS", np.asarray(initial.q_BS, np.float64), np.float64,
                        tol=val.ROUNDED_QUATERNION, fix="normalise it: q / |q|",
                        what="must be a unit quaternion [w, x, y, z]")
    if float(np.asarray(initial.gravity)) < 0:
        raise ValueError(f"initial.gravity is a magnitude [m/s²] and must be ≥ 0, got "
                         f"{float(np.asarray(initial.gravity)):g} (g_W = [0, 0, -g])")


def _sqrt_information(cov, dtype) -> np.ndarray:
    """``L⁻¹`` for the residuals' covariances ``cov = L Lᵀ`` (``(..., 9, 9)``, one per window),
    which whiten the residuals; a covariance singular to the precision of ``dtype``
    (:func:`jaximu._validation.check_definite`) is refused, naming the window and its axes:
    its whitened residual would be the rounding divided by zero."""
    val.check_definite(
        "the residuals' covariance", cov, dtype, axes=val.ERROR_AXES[:9],
        what="the residuals are whitened by its inverse Cholesky factor",
        fix="noise (its white-noise densities) and reference_sigma leave some residual "
            "without variance; give noise positive densities (its datasheet's or an Allan "
            "fit's) or reference_sigma positive values")
    return np.linalg.inv(np.linalg.cholesky(cov))


def _gap_list(gaps, limit=4) -> str:
    """``0.483 s at t = 45.183 s, ...`` of ``((t, length, windows), ...)``."""
    shown = ", ".join(f"{length:.3f} s at t = {t:.3f} s" for t, length, _ in gaps[:limit])
    return shown + (f", … ({len(gaps)} gaps in all)" if len(gaps) > limit else "")


def _skip_note(n_skipped, n_windows, max_gap, gaps) -> str:
    if not n_skipped:
        return ""
    return (f"left out {n_skipped} of {n_windows} keyframe windows with a keyframe inside a "
            f"reference gap longer than {max_gap:.4g} s ({GAP_FACTOR:g} × its median interval; "
            f"the reference is not interpolated across gaps): {_gap_list(gaps)}")


def _velocities_from_positions(p, t, good):
    """Keyframe velocities by differences of the keyframe positions ``p`` at times ``t``
    (``np.gradient``: central inside, one-sided at the ends) using only keyframes where
    ``good``; a keyframe with no good neighbour gets 0 (its windows are left out)."""
    v = np.gradient(p, t, axis=0)
    if good.all():
        return v
    n = len(t)
    for k in range(n):
        lo_ok = k > 0 and good[k - 1]
        hi_ok = k < n - 1 and good[k + 1]
        if not good[k]:
            v[k] = 0.0
        elif not (lo_ok and hi_ok):
            lo, hi = (k - 1 if lo_ok else k), (k + 1 if hi_ok else k)
            v[k] = (p[hi] - p[lo]) / (t[hi] - t[lo]) if hi > lo else 0.0
    return v


def calibration_problem(t, gyro, accel, reference: Reference, noise: ImuNoise, *,
                        keyframe_interval: float = 0.5, scheme: str = "euler",
                        model: str = "preintegration", reference_sigma=(1e-3, 1e-3, 1e-2),
                        initial: ImuCalibration | None = None, windows_per_group: int = 64,
                        check: bool = True, extrinsics: bool = False,
                        omega_coriolis=None) -> CalibrationProblem:
    """Cut the IMU stream into keyframe windows and pair them with the reference.

    Args:
        t: ``(N,)`` IMU times [s] (IMU clock); gyro, accel: ``(N, 3)`` raw samples [rad/s],
            [m/s²]. Their dtype is the computation's.
        reference: the :class:`Reference` (reference clock). Keyframes lie where both exist.
            It is not interpolated across its gaps (dropouts): intervals longer than
            ``GAP_FACTOR`` × its median interval, the rule of
            :meth:`jaximu.io.GroundTruth.interpolate`. A window with a keyframe strictly
            inside one is left out of the fit (weight 0; :attr:`CalibrationProblem.skip_note`
            says how many and where); a gap between two keyframes of a window does not
            matter (the residual reads the reference at the keyframes only). A
            :class:`CalibrationError` names the gaps when they leave no window.
        noise: :class:`ImuNoise` of the IMU (whitening of the residuals).
        keyframe_interval: seconds between keyframes, positive, at least one sample interval
            (rounded to whole samples).
        scheme: ``"euler"`` or ``"midpoint"``; model: ``"preintegration"`` or ``"propagation"``.
        reference_sigma: ``(σ_θ [rad], σ_p [m], σ_v [m/s])``, each ``≥ 0``, of the
            reference's own errors,
            added to each residual's covariance as ``diag(2σ_θ², 2σ_p² + σ_v²Δt², 2σ_v²)``
            (ends assumed independent).
        initial: the calibration at which the consistency checks integrate (default zero).
        windows_per_group: windows per checkpointed group (memory of a gradient), ≥ 1.
        check: run the unit and frame checks, raising :class:`CalibrationError`: the
            rotation (velocity change) of each window from the raw gyro (accel) is compared
            with the reference's (a gyro in deg/s reads 57× too much, an accelerometer in g
            0.10×; an IMU frame rotated from the reference's body frame or a quaternion in
            ``[x, y, z, w]`` order gives a rotation between them). The checks judge only
            what the data can show: a rotation is reported when it exceeds
            :data:`FRAME_ANGLE_TOL` *and* the windows' motion determines it (a likelihood
            ratio beyond :data:`FRAME_SIGNIFICANCE`, noise bounded below by
            ``reference_sigma``); a near-still segment passes the frame check, and a
            deg/s gyro is caught there by its mean rate (:data:`GYRO_BIAS_MAX`). Every 3 s
            excerpt of the bundled recordings passes (``tests/test_calibration_checks.py``).
        extrinsics: the IMU frame may be rotated from the reference's body frame and sit at
            a lever arm (``q_BS``, ``p_BS`` of :class:`ImuCalibration` join the model). The
            frame check then becomes the initialiser: the least-squares rotation between the
            windows' gyro and reference rotations (or velocity changes, where the rotations
            do not determine it; :func:`_initial_rotation`) is ``q_BS0``, reported in
            ``diagnostics``, and the other checks run on the rotated samples. A
            ``RuntimeWarning`` says when the motion determines no rotation (``q_BS0`` is
            then the identity).
        omega_coriolis: optional ``(3,)`` rotation rate of the reference's world [rad/s] in W
            (:func:`jaximu.earth_rate`): the residuals then use the exact rotating-world
            prediction (:func:`jaximu.residual`).

    Returns:
        :class:`CalibrationProblem`.
    """
    if scheme not in ("euler", "midpoint"):
        raise ValueError(f"unknown scheme {scheme!r}; choose 'euler' or 'midpoint'")
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}; choose one of {MODELS}")
    keyframe_interval = val.check_positive("keyframe_interval", keyframe_interval)
    windows_per_group = val.check_int("windows_per_group", windows_per_group, 1)
    sig = np.asarray(reference_sigma, np.float64) if np.ndim(reference_sigma) == 1 else None
    if sig is None or sig.shape != (3,) or not np.all(np.isfinite(sig) & (sig >= 0)):
        raise ValueError("reference_sigma must be three non-negative numbers (σ_θ [rad], σ_p [m], "
                         f"σ_v [m/s]), got {reference_sigma!r}")
    if not isinstance(reference, Reference):
        raise ValueError(f"reference must be a jaximu.calibration.Reference, got "
                         f"{type(reference).__name__}")
    check = val.check_bool("check", check)
    extrinsics = val.check_bool("extrinsics", extrinsics)
    _check_initial(initial)
    dtype = val.float_dtype(gyro, accel)
    t = val.as_numbers("t", t)
    gyro_np, accel_np = val.as_numbers("gyro", gyro, None), val.as_numbers("accel", accel, None)
    if t.ndim != 1 or gyro_np.shape != (len(t), 3) or accel_np.shape != (len(t), 3):
        raise ValueError(f"t, gyro, accel must have shapes (N,), (N, 3), (N, 3); got "
                         f"{t.shape}, {gyro_np.shape}, {accel_np.shape}")
    if len(t) < 3:
        raise ValueError(f"t, gyro, accel hold {len(t)} samples; a calibration needs at least "
                         "two keyframe windows of samples")
    val.check_finite("t", t)
    if np.any(np.diff(t) <= 0):
        i = int(np.argmax(np.diff(t) <= 0))
        raise ValueError(f"IMU times must increase strictly; t[{i + 1}] <= t[{i}]")
    val.check_finite("gyro", gyro_np)
    val.check_finite("accel", accel_np)
    noise = val.check_noise(noise, dtype)
    val.check_unbatched_noise(noise, "a calibration problem")
    if omega_coriolis is not None:
        omega_coriolis = world.check_omega(omega_coriolis, dtype)
        if omega_coriolis.ndim != 1:
            raise ValueError(f"omega_coriolis must be one (3,) world rate for a calibration "
                             f"problem (one recording), got shape {omega_coriolis.shape}")
    rt, rq, rp = (val.as_numbers(f"reference.{n}", getattr(reference, n)) for n in "tqp")
    M = len(rt) if rt.ndim else 0
    if rt.ndim != 1 or rq.shape != (M, 4) or rp.shape != (M, 3) or M < 2:
        raise ValueError("reference t, q, p must have shapes (M,), (M, 4), (M, 3) with M ≥ 2")
    val.check_finite("reference.t", rt)  # a NaN time passes the order test below
    if np.any(np.diff(rt) <= 0):
        i = int(np.argmax(np.diff(rt) <= 0))
        raise ValueError(f"reference times must increase strictly; t[{i + 1}] <= t[{i}]")
    for name, x in (("reference.q", rq), ("reference.p", rp)):
        val.check_finite(name, x)
    val.check_unit_norm("reference.q", rq, np.float64, tol=val.ROUNDED_QUATERNION,
                        what="is not unit ([w, x, y, z] quaternions)",
                        where=lambda i: f" at row {i[0]}",
                        fix="pass unit quaternions (a normalised copy is used within this "
                            "tolerance)")
    rq = rq / np.linalg.norm(rq, axis=-1, keepdims=True)
    has_v = reference.v is not None
    rv = val.as_numbers("reference.v", reference.v) if has_v else np.zeros_like(rp)
    if rv.shape != (M, 3):
        raise ValueError(f"reference.v must have shape (M, 3), got {rv.shape}")
    val.check_finite("reference.v", rv)

    init = initial if initial is not None else ImuCalibration.default(dtype=dtype)
    td0 = float(np.asarray(init.time_offset))
    period = float(np.median(np.diff(t)))
    W = int(round(keyframe_interval / period))
    if W < 1:
        raise InputError(f"keyframe_interval = {keyframe_interval:g} s is shorter than one sample "
                         f"interval ({period:.3g} s): keyframes are whole samples apart "
                         "(typically 0.1–1 s)",
                         [Fix("keyframe_interval", phrase=f"{{}} ≥ {period:.3g}")])
    inside = np.nonzero((t + td0 >= rt[0]) & (t + td0 <= rt[-1]))[0]
    if len(inside) < W + 2:
        raise ValueError("the IMU and the reference overlap by less than one keyframe interval")
    first, last = inside[0], inside[-1]
    K = (last - first) // W
    if K < 1:
        raise ValueError("the IMU and the reference overlap by less than one keyframe interval")
    idx = first + W * np.arange(K + 1)
    # Keyframes inside a reference dropout: their windows are left out (weight 0), never
    # fitted to a pose interpolated across the gap.
    inside, gap_of, max_gap = in_gap(rt, t[idx] + td0)  # the keyframes on the reference clock
    kept = ~(inside[:-1] | inside[1:])
    gap_windows = {}  # gap index -> windows with a keyframe inside it
    for k in np.flatnonzero(~kept):
        for end in (k, k + 1):
            if inside[end]:
                gap_windows[gap_of[end]] = gap_windows.get(gap_of[end], 0) + 1
    skipped = tuple((float(rt[i]), float(rt[i + 1] - rt[i]), n)
                    for i, n in sorted(gap_windows.items()))
    if not kept.any():
        raise CalibrationError(
            f"every one of the {K} keyframe windows has a keyframe inside a reference gap "
            f"(an interval longer than {max_gap:.4g} s, {GAP_FACTOR:g} × the reference's median "
            f"interval), and the reference is not interpolated across gaps: "
            f"{_gap_list(skipped)}. Calibrate on a stretch the reference covers")
    # Each window holds the W + 1 samples from keyframe to keyframe and the W intervals
    # between them (the midpoint rule uses both ends; Euler leaves the last one unused).
    sl = idx[:-1, None] + np.arange(W + 1)  # (K, W + 1)
    dt_all = np.diff(t)
    win_gyro, win_accel, win_dt = gyro_np[sl], accel_np[sl], dt_all[sl[:, :-1]]

    # Keyframe velocities where the reference has none: central differences of positions.
    t0 = t[idx[0]]  # common time origin: keeps float32 times (and absolute stamps) precise
    qk, pk, vk = (np.asarray(x, np.float64) for x in _once(_interp)(
        jnp.asarray(t[idx] - t0 + td0), jnp.asarray(rt - t0), jnp.asarray(rq),
        jnp.asarray(rp), jnp.asarray(rv)))
    if not has_v:
        vk = _velocities_from_positions(pk, t[idx], ~inside)

    # Raw preintegration (for the whitening and the checks) at the initial calibration.
    g_c, a_c = (np.asarray(x) for x in _once(_apply)(init, jnp.asarray(win_gyro, dtype),
                                                      jnp.asarray(win_accel, dtype)))
    # Run once per problem, so its compile time is what the user waits for: the plain scan
    # (it compiles in a fraction of the time of the side-by-side chunks "auto" picks for a few
    # dozen windows; the inputs are checked above). Small problems compile it at the quick
    # level and on the generic kernel, which compiles faster than the structure-of-arrays
    # one there.
    zero3 = jnp.zeros(3, dtype)
    quick = K * W <= QUICK_COMPILE_SAMPLES
    pim = _compiled(_preintegrate_sequential, quick, ("scheme", "fast"))(
        jnp.asarray(g_c, dtype), jnp.asarray(a_c, dtype), jnp.asarray(win_dt, dtype),
        ImuBias(zero3, zero3), noise, scheme=scheme, fast=not quick)
    cov = np.asarray(pim.cov, np.float64)
    Dt = win_dt.sum(-1)
    s_th, s_p, s_v = (float(x) for x in reference_sigma)
    extra = np.zeros((K, 9))
    extra[:, 0:3] = 2 * s_th**2
    extra[:, 3:6] = (2 * s_p**2 + (s_v * Dt) ** 2)[:, None] if has_v else 2 * s_p**2
    extra[:, 6:9] = 2 * s_v**2 if has_v else 0.0
    cov = cov + extra[:, :, None] * np.eye(9)
    sqrt_info = _sqrt_information(cov, dtype)

    diagnostics = dict.fromkeys(("gyro_ratio", "gyro_frame_error", "accel_ratio",
                                 "accel_frame_error"), np.nan)
    q_BS0 = None
    if check or extrinsics:
        g = float(np.asarray(init.gravity))
        gW = np.array([0.0, 0.0, -g])
        R_i, phi_ref = (np.asarray(x, np.float64)
                        for x in _once(_keyframe_rotations)(jnp.asarray(qk)))
        phi_imu = _rotation_vectors(jnp.asarray(np.asarray(pim.delta_q, np.float64)))
        dv_imu = np.asarray(pim.delta_v, np.float64)
        dv_ref = np.einsum("kji,kj->ki", R_i, vk[1:] - vk[:-1] - gW * Dt[:, None])
        # the checks judge the windows of the fit only
        phi_imu, phi_ref, dv_imu, dv_ref = (x[kept] for x in (phi_imu, phi_ref, dv_imu, dv_ref))
        found = {}
        if extrinsics:
            theta, stat, source = _initial_rotation(phi_imu, phi_ref, dv_imu, dv_ref,
                                                    reference_sigma)
            if source == "none":
                warnings.warn("the motion determines no rotation between the IMU and the "
                              "reference's body frame (no two independent directions of "
                              "rotation or of velocity change): q_BS starts at the identity",
                              RuntimeWarning, stacklevel=2)
            R0 = np.asarray(_once(so3.exp_matrix)(jnp.asarray(theta)), np.float64)
            q_BS0 = np.asarray(_once(so3.exp)(jnp.asarray(theta)), np.float64)
            found = {"q_BS0": q_BS0, "q_BS0_angle": float(np.linalg.norm(theta)),
                     "q_BS0_statistic": stat}
            phi_imu, dv_imu = phi_imu @ R0.T, dv_imu @ R0.T  # the checks on the body's axes
        if check:
            diagnostics = _check_consistency(phi_imu, phi_ref, dv_imu, dv_ref, Dt[kept],
                                             reference_sigma)
        diagnostics.update(found)

    C = max(1, min(int(windows_per_group), K))
    G = -(-K // C)
    pad = G * C - K

    def grp(x):
        x = np.concatenate([x, np.repeat(x[:1], pad, axis=0)]) if pad else x
        return jnp.asarray(x.reshape((G, C) + x.shape[1:]))

    as_d = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    return CalibrationProblem(
        gyro=as_d(grp(win_gyro)), accel=as_d(grp(win_accel)), dt=as_d(grp(win_dt)),
        t_start=as_d(grp(t[idx[:-1]] - t0)), t_end=as_d(grp(t[idx[1:]] - t0)),
        window=grp(np.arange(K)),
        weight=as_d(np.concatenate([kept, np.zeros(pad)]).reshape(G, C)),  # padding: 0
        sqrt_info=as_d(grp(sqrt_info)), ref_t=as_d(rt - t0), ref_q=as_d(rq), ref_p=as_d(rp),
        ref_v=as_d(rv), velocities=as_d(vk), scheme=scheme, model=model, has_velocity=has_v,
        diagnostics={k: as_d(v) for k, v in diagnostics.items()},
        n_windows=int(K), q_BS0=None if q_BS0 is None else as_d(q_BS0),
        extrinsics=bool(extrinsics),
        sample_density2=as_d(np.stack([np.broadcast_to(np.asarray(
            getattr(noise, f"{s}_noise_density"), np.float64) ** 2, (3,))
            for s in ("gyroscope", "accelerometer")])),
        reference_var=as_d(grp(extra)),
        omega_coriolis=omega_coriolis,
        max_gap=float(max_gap), skipped=skipped)


# --------------------------------------------------------------------------- fitting


class _Layout(NamedTuple):
    free: tuple  # names of the estimated fields, in FIELDS order
    n_velocity: int  # 0, or 3 (K + 1) nuisance velocities


def _n_free(free):
    return sum(_TANGENT[n] for n in free)


def _scale_vector(free, dtype):
    return jnp.asarray(np.concatenate([np.full(_TANGENT[n], SCALES[n]) for n in FIELDS
                                       if n in free]), dtype)


def _flatten(calib: ImuCalibration):
    return jnp.concatenate([jnp.reshape(getattr(calib, n), (-1,)) for n in FIELDS])


def _unflatten(vec) -> ImuCalibration:
    out, off = {}, 0
    for n in FIELDS:
        k = _SIZES[n]
        out[n] = vec[off:off + k] if k > 1 else vec[off]
        off += k
    return ImuCalibration(**out)


def _unpack(z, init_vec, v0, layout: _Layout):
    """The calibration at normalised coordinates ``z``: additive fields ``θ₀ + scale·z``,
    ``q_BS = q₀ ⊗ Exp(scale·z)``; then the nuisance velocities."""
    init = _unflatten(init_vec)
    fields, off = {f.name: getattr(init, f.name) for f in dataclasses.fields(init)}, 0
    for name in FIELDS:
        if name not in layout.free:
            continue
        k = _TANGENT[name]
        step = SCALES[name] * (z[off:off + k] if _SIZES[name] > 1 else z[off])
        if name == "q_BS":
            fields[name] = so3.quat_mul(fields[name], so3.exp(step))
        else:
            fields[name] = fields[name] + step
        off += k
    v = v0 if layout.n_velocity == 0 else v0 + _VELOCITY_SCALE * z[off:].reshape(v0.shape)
    return ImuCalibration(**fields), v


def _objective(z, problem, init_vec, layout):
    calib, v = _unpack(z, init_vec, problem.velocities, layout)
    return calibration_loss(problem, calib, v)


@functools.lru_cache(maxsize=None)
def _optimizer(name, learning_rate):
    if name == "adam":
        return optax.adam(learning_rate)
    return optax.lbfgs(memory_size=20)


@functools.partial(jax.jit, static_argnames=("layout", "optimizer", "learning_rate"))
def _step(z, opt_state, problem, init_vec, *, layout, optimizer, learning_rate):
    """One optimiser step (module-level jit: compiled once per problem shape and settings)."""
    opt = _optimizer(optimizer, learning_rate)
    fn = functools.partial(_objective, problem=problem, init_vec=init_vec, layout=layout)
    if optimizer == "lbfgs":
        value, grad = optax.value_and_grad_from_state(fn)(z, state=opt_state)
        updates, opt_state = opt.update(grad, opt_state, z, value=value, grad=grad, value_fn=fn)
    else:
        value, grad = jax.value_and_grad(fn)(z)
        updates, opt_state = opt.update(grad, opt_state, z)
    return optax.apply_updates(z, updates), opt_state, value, jnp.linalg.norm(grad)


def _quick(problem: CalibrationProblem) -> bool:
    return problem.n_samples <= QUICK_COMPILE_SAMPLES


def _residuals_jacobian_compiled(problem: CalibrationProblem):
    """:func:`_residuals_jacobian_graph` jitted for the problem's size (:data:`QUICK_COMPILE`)."""
    return _compiled(_residuals_jacobian_graph, _quick(problem), ("layout",))


def _residuals_jacobian(z, problem, init_vec, *, layout):
    return _residuals_jacobian_compiled(problem)(z, problem, init_vec, layout=layout)


def _residuals_jacobian_graph(z, problem, init_vec, *, layout):
    """``(r, J)``: the whitened residuals ``(9K,)`` at ``z`` and their Jacobian
    ``(9K, n + n_v)`` in the normalised coordinates. One compiled function serves every
    Levenberg–Marquardt iteration and the Laplace covariance.

    The calibration columns are forward-mode (``n`` ≤ 20 tangents through every window).
    A keyframe velocity enters only the two windows it bounds, so the velocity columns
    take 6 tangents, not ``3(K + 1)``: the same direction of ``v_i`` (then ``v_j``) in every
    window at once gives each window's ``9 × 6`` block, scattered to its two keyframes.
    """
    n = _n_free(layout.free)
    calib, v = _unpack(z, init_vec, problem.velocities, layout)

    def res(zc):
        c, _ = _unpack(jnp.concatenate([zc, z[n:]]), init_vec, problem.velocities, layout)
        r = calibration_residuals(problem, c, v).reshape(-1)
        return r, r

    J, r = jax.jacfwd(res, has_aux=True)(z[:n])
    if layout.n_velocity == 0:
        return r, J
    K = problem.n_windows
    dtype = z.dtype
    eye6 = jnp.eye(6, dtype=dtype)

    def group_blocks(g):
        k = problem.window[g]
        vi, vj = v[k], v[k + 1]

        def f(ti, tj):
            return _group_residuals(problem, calib, g, vi + ti, vj + tj)

        zero = jnp.zeros_like(vi)

        def column(e):  # one of the 6 directions, in every window of the group
            return jax.jvp(f, (zero, zero), (jnp.broadcast_to(e[:3], vi.shape),
                                             jnp.broadcast_to(e[3:], vj.shape)))[1]

        return jax.vmap(column, out_axes=-1)(eye6)  # (C, 9, 6)

    B = jax.vmap(group_blocks)(jnp.arange(problem.gyro.shape[0]))
    B = _VELOCITY_SCALE * B.reshape((-1, 9, 6))[:K]
    kk = jnp.arange(K)
    Jv = jnp.zeros((K, 9, K + 1, 3), dtype)
    Jv = Jv.at[kk, :, kk, :].set(B[..., :3]).at[kk, :, kk + 1, :].set(B[..., 3:])
    return r, jnp.concatenate([J, Jv.reshape(9 * K, 3 * (K + 1))], axis=1)


def _levenberg_marquardt(evaluate, z, steps, threshold):
    """Minimise ``½|r(z)|²`` (float64 numpy algebra on ``evaluate(z) -> (r, J)``).

    Damped Gauss–Newton steps ``(JᵀJ + λI) δ = -Jᵀr`` (the coordinates are normalised, so
    one ``λ`` suits all), accepted when the loss falls; ``λ`` follows the gain ratio
    (Nielsen's rule). Stops when the decrease the local model predicts is below
    ``threshold · (1 + loss)``. A trial point whose residuals are not finite is rejected
    like one that raises the loss.

    Returns:
        ``(z, history, converged, r, J)``.
    """
    r, J = evaluate(z)
    cost = 0.5 * float(r @ r)
    if not (np.isfinite(cost) and np.all(np.isfinite(J))):
        raise FloatingPointError(f"the calibration loss is {cost} at the initial values")
    history, converged = [cost], False
    lam, nu = None, 2.0
    for _ in range(steps):
        A, g = J.T @ J, J.T @ r
        if not np.any(g):
            converged = True
            break
        if lam is None:
            lam = 1e-3 * max(float(np.max(np.diag(A))), 1e-300)
        try:
            delta = np.linalg.solve(A + lam * np.eye(len(z)), -g)
        except np.linalg.LinAlgError:
            delta = np.linalg.lstsq(A + lam * np.eye(len(z)), -g, rcond=None)[0]
        predicted = -float(g @ delta + 0.5 * delta @ A @ delta)
        if predicted <= threshold * (1 + cost):
            converged = True
            break
        r_new, J_new = evaluate(z + delta)
        cost_new = 0.5 * float(r_new @ r_new)
        rho = (cost - cost_new) / predicted
        if np.isfinite(cost_new) and np.all(np.isfinite(J_new)) and rho > 0:  # else: reject
            z, r, J, cost = z + delta, r_new, J_new, cost_new
            history.append(cost)
            lam *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
            nu = 2.0
        else:
            lam *= nu
            nu *= 2
    return z, history, converged, r, J


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


def _optax_loop(z, problem, init_vec, layout, optimizer, learning_rate, steps, tol, dtype):
    """The optax optimiser's steps (one compiled :func:`_step`); ``(z, history, converged)``."""
    opt = _optimizer(optimizer, float(learning_rate))
    # Strong-typed leaves (optax's init has weak-typed scalars): the state of step 1 then has
    # the same types as that of later steps, and the step compiles once.
    opt_state = jax.tree_util.tree_map(lambda x: jnp.array(x, dtype=jnp.asarray(x).dtype),
                                       opt.init(z))
    steps = steps if steps is not None else (100 if optimizer == "lbfgs" else 1000)
    history, quiet, converged = [], 0, False
    for _ in range(steps):
        z_new, opt_state, value, gnorm = _step(z, opt_state, problem, init_vec, layout=layout,
                                               optimizer=optimizer,
                                               learning_rate=float(learning_rate))
        value = float(value)
        if not np.isfinite(value):
            raise FloatingPointError(f"the calibration loss became {value} at step {len(history)}")
        if history and abs(history[-1] - value) <= tol * (1 + abs(value)):
            quiet += 1
        else:
            quiet = 0
        history.append(value)
        z = z_new
        if quiet >= 5 or float(gnorm) == 0.0:
            converged = True
            break
    return z, history, converged


def calibrate(problem: CalibrationProblem, initial: ImuCalibration | None = None,
              estimate=("b_g", "b_a"), *, optimizer: str = "lm", steps: int | None = None,
              learning_rate: float = 0.05, tol: float = 1e-10,
              max_reduced_chi2: float | None = 100.0) -> CalibrationResult:
    """Fit the ``estimate``d fields of an :class:`ImuCalibration` by gradient descent.

    Args:
        problem: from :func:`calibration_problem`.
        initial: starting values (default :meth:`ImuCalibration.default`); the other fields
            stay at these values.
        estimate: names from :data:`FIELDS` (at least one).
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
        raise ValueError(f"estimate must be a tuple of field names, got the string "
                         f"{estimate!r}; pass estimate={fix!r}")
    try:
        estimate = tuple(estimate)
    except TypeError:
        raise ValueError(f"estimate must be a tuple of field names from {FIELDS}, got "
                         f"{type(estimate).__name__} {estimate!r}") from None
    unknown = [n for n in estimate if n not in FIELDS]
    if unknown:
        raise ValueError(f"unknown calibration fields {unknown}; fields are {FIELDS}")
    if not estimate:
        raise ValueError("estimate names no field")
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"unknown optimizer {optimizer!r}; choose one of {OPTIMIZERS}")
    if not isinstance(problem, CalibrationProblem):
        raise ValueError("problem must be a CalibrationProblem (from calibration_problem), got "
                         f"{type(problem).__name__}")
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
            or np.any(np.asarray(initial.p_BS) != 0)):
        problem = dataclasses.replace(problem, extrinsics=True)
    init_vec = jnp.asarray(_flatten(initial), dtype)
    n_v = 0 if problem.has_velocity else problem.velocities.size
    layout = _Layout(free, n_v)
    n = _n_free(free)
    z = jnp.zeros(n + n_v, dtype)
    def fit(problem, z0):
        if optimizer == "lm":
            def evaluate(z_):
                r_, J_ = _residuals_jacobian(jnp.asarray(z_, dtype), problem, init_vec,
                                             layout=layout)
                return np.asarray(r_, np.float64), np.asarray(J_, np.float64)

            threshold = max(tol, 10 * float(jnp.finfo(dtype).eps))  # below: loss rounding
            z_np, history, converged, r, J = _levenberg_marquardt(
                evaluate, np.asarray(z0, np.float64), steps if steps is not None else 50,
                threshold)
            return jnp.asarray(z_np, dtype), history, converged, r, J
        z, history, converged = _optax_loop(z0, problem, init_vec, layout, optimizer,
                                            learning_rate, steps, tol, dtype)
        r, J = _residuals_jacobian(z, problem, init_vec, layout=layout)
        return z, history, converged, r, J

    z, history, converged, r, J = fit(problem, z)
    if problem.extrinsics:
        # Whiten again at the estimate with the samples' noise through the whole model (the
        # lever arm's ω×(ω×r) + α×r carry gyro noise), then refine from there.
        calib_now, v_now = _unpack(z, init_vec, problem.velocities, layout)
        cov = _compiled(_sample_noise_covariance, _quick(problem))(problem, calib_now, v_now)
        cov = np.asarray(cov, np.float64) + np.asarray(problem.reference_var, np.float64)[
            ..., None] * np.eye(9)
        problem = dataclasses.replace(problem, sqrt_info=jnp.asarray(
            _sqrt_information(cov, dtype), dtype))
        z, more, converged, r, J = fit(problem, z)
        history = list(history) + list(more)
    r, J = np.asarray(r, np.float64), np.asarray(J, np.float64)
    chi2 = float(r @ r)
    if optimizer != "lm":  # the Levenberg–Marquardt history ends at this point already
        history.append(0.5 * chi2)
    cov_z = np.linalg.pinv(J.T @ J)
    scale = np.concatenate([np.asarray(_scale_vector(free, dtype), np.float64),
                            np.full(n_v, _VELOCITY_SCALE)])
    cov_all = cov_z * scale[:, None] * scale[None, :]
    cov = cov_all[:n, :n]
    calib, v = _unpack(z, init_vec, problem.velocities, layout)
    sig = np.sqrt(np.clip(np.diag(cov), 0, None))
    std, off = {}, 0
    for name in FIELDS:
        k, shape = _TANGENT[name], (3,) if name == "q_BS" else np.shape(getattr(initial, name))
        if name in free:
            std[name] = jnp.asarray(sig[off:off + k].reshape(shape), dtype)
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
                "as ω×(ω×r) + α×r: turn the body faster, about more axes", RuntimeWarning,
                stacklevel=2)
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
            " the noise densities)", RuntimeWarning, stacklevel=2)
    return CalibrationResult(
        calibration=calib, std=ImuCalibration(**std), covariance=cov,
        free=free, velocities=v, loss_history=np.asarray(history), chi2=chi2,
        dof=dof, reduced_chi2=red, converged=converged, n_windows=int(kept.sum()),
        skipped_windows=problem.n_skipped, note=problem.skip_note)
