"""The calibration's model (:mod:`jaximu.calibration`): its fields and scales, the calibration,
the reference trajectory and the problem's data, and the whitened window residuals that
the loss sums."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.engine._preintegration_engine import Preintegrated, _chunk_scan, _pairs
from jaximu.engine.preintegration import residual
from jaximu.engine.propagate import propagate_final
from jaximu.errors import InputError
from jaximu.geometry import _checks as val
from jaximu.geometry import so3
from jaximu.geometry.sensor import SensorPose, to_body
from jaximu.geometry.state import ImuBias, NavState
from jaximu.io._common import GAP_FACTOR
from jaximu.schemes._preintegration_steps import _step as _pim_step

FIELDS = (
    "b_g",
    "b_a",
    "gyro_scale",
    "gyro_misalignment",
    "accel_scale",
    "accel_misalignment",
    "gravity",
    "time_offset",
    "q_BS",
    "p_BS",
)
_SIZES = {
    "b_g": 3,
    "b_a": 3,
    "gyro_scale": 3,
    "gyro_misalignment": 3,
    "accel_scale": 3,
    "accel_misalignment": 3,
    "gravity": 1,
    "time_offset": 1,
    "q_BS": 4,
    "p_BS": 3,
}
_TANGENT = dict(_SIZES, q_BS=3)  # q_BS is estimated as a rotation vector: q̂ ⊗ Exp(δθ)
SCALES = {
    "b_g": 1e-2,
    "b_a": 1e-1,
    "gyro_scale": 1e-2,
    "gyro_misalignment": 1e-2,
    "accel_scale": 1e-2,
    "accel_misalignment": 1e-2,
    "gravity": 1e-1,
    "time_offset": 1e-2,
    "q_BS": 1e-2,
    "p_BS": 1e-1,
}
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
    def default(cls, gravity=9.81, dtype=None, **fields) -> ImuCalibration:
        """Zero biases, scale, misalignment and offset (unless given in ``fields``)."""
        dtype = val.compute_dtype("dtype", dtype) if dtype is not None else jnp.zeros(()).dtype
        vals = {
            name: jnp.zeros((_SIZES[name],) if _SIZES[name] > 1 else (), dtype) for name in FIELDS
        }
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

        return (fix(self.gyro_matrix(), self.b_g, gyro), fix(self.accel_matrix(), self.b_a, accel))


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


def _group_residuals(
    problem: CalibrationProblem,
    calib: ImuCalibration,
    g_idx,
    vi=None,
    vj=None,
    gyro=None,
    accel=None,
    raw=False,
):
    """``(C, 9)`` whitened residuals of group ``g_idx``; ``vi``, ``vj``: ``(C, 3)`` keyframe
    velocities of each window's ends (default: the reference's); ``gyro``, ``accel``: the
    group's raw samples (default: the problem's); ``raw``: the residuals before whitening."""
    gyro = problem.gyro[g_idx] if gyro is None else gyro
    accel = problem.accel[g_idx] if accel is None else accel
    dt = problem.dt[g_idx]
    td = calib.time_offset
    ends = jnp.stack([problem.t_start[g_idx], problem.t_end[g_idx]]) + td  # one graph, both
    (qi, qj), (pi, pj), (vi_ref, vj_ref) = _interp(
        ends, problem.ref_t, problem.ref_q, problem.ref_p, problem.ref_v
    )
    if vi is None:
        vi, vj = vi_ref, vj_ref
    gyro_c, accel_c = calib.apply(gyro, accel)
    zero = jnp.zeros_like(pi)
    state_i = NavState(qi, pi, vi, zero, zero)
    state_j = NavState(qj, pj, vj, zero, zero)
    pose = calib.body_P_sensor if problem.extrinsics else None
    if problem.model == "preintegration":
        if pose is not None:  # the sensor's samples as the body's (jaximu/geometry/sensor.py)
            gyro_c, accel_c = to_body(pose, gyro_c, accel_c, dt, jnp.zeros_like(pi))
        pim = _preintegrate_mean(gyro_c, accel_c, dt, problem.scheme)
        r = residual(
            state_i, state_j, pim, gravity=calib.gravity, omega_coriolis=problem.omega_coriolis
        )[..., :9]
    else:
        pred = propagate_final(
            state_i,
            gyro_c,
            accel_c,
            dt,
            problem.scheme,
            gravity=calib.gravity,
            body_P_sensor=pose,
            omega_coriolis=problem.omega_coriolis,
        )
        qi_inv = so3.quat_conj(qi)
        r = jnp.concatenate(
            [
                so3.log(so3.quat_mul(so3.quat_conj(pred.q), qj)),
                so3.quat_rotate(qi_inv, pj - pred.p),
                so3.quat_rotate(qi_inv, vj - pred.v),
            ],
            axis=-1,
        )
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
            return _group_residuals(problem, calib, g, vi, vj, gyro + d[0], accel + d[1], raw=True)

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
    final, _ = _chunk_scan(
        scheme,
        _pim_step,
        zero,
        zero,
        None,
        (None, w0, a0, w1, a1, h, None),
        batch,
        dtype,
        False,
        blocks=False,
    )
    dq, dv, dp, t, _ = final
    eye = lambda n: jnp.broadcast_to(jnp.eye(n, dtype=dtype), batch + (n, n))  # noqa: E731
    return Preintegrated(
        delta_t=t,
        delta_q=so3.quat_normalize(dq),
        delta_v=dv,
        delta_p=dp,
        transition=jnp.zeros(batch + (15, 15), dtype),
        cov15=eye(15),
        cov=eye(9),
        bias_hat=ImuBias(zero, zero),
    )


def _gap_list(gaps, limit=4) -> str:
    """``0.483 s at t = 45.183 s, ...`` of ``((t, length, windows), ...)``."""
    shown = ", ".join(f"{length:.3f} s at t = {t:.3f} s" for t, length, _ in gaps[:limit])
    return shown + (f", … ({len(gaps)} gaps in all)" if len(gaps) > limit else "")


def _skip_note(n_skipped, n_windows, max_gap, gaps) -> str:
    if not n_skipped:
        return ""
    return (
        f"left out {n_skipped} of {n_windows} keyframe windows with a keyframe inside a "
        f"reference gap longer than {max_gap:.4g} s ({GAP_FACTOR:g} × its median interval; "
        f"the reference is not interpolated across gaps): {_gap_list(gaps)}"
    )


def _check_loss_args(problem, calib, velocities):
    """Types (and ``velocities``' shape) of :func:`calibration_loss`'s arguments: static,
    so free inside ``jit``/``grad``. Returns the velocities to use."""
    if not isinstance(problem, CalibrationProblem):
        raise ValueError(
            "problem must be a CalibrationProblem (from calibration_problem), got "
            f"{type(problem).__name__}"
        )
    if not isinstance(calib, ImuCalibration):
        raise ValueError(
            "calib must be an ImuCalibration (e.g. ImuCalibration.default()), got "
            f"{type(calib).__name__}"
        )
    if velocities is None:
        return problem.velocities
    if jnp.shape(velocities) != problem.velocities.shape:
        raise ValueError(
            f"velocities must have the shape {problem.velocities.shape} of "
            f"problem.velocities (one per keyframe), got {jnp.shape(velocities)}"
        )
    return velocities


def calibration_residuals(problem: CalibrationProblem, calib: ImuCalibration, velocities=None):
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

    dtype = problem.gyro.dtype

    @jax.checkpoint
    def group(g):
        r = _window_residuals(problem, calib, v, g)
        return 0.5 * jnp.sum(r * r)

    def body(acc, g):
        # in the problem's dtype: a calibration in another one (an optimiser's float64 line
        # search over a float32 problem) must not change the carry's type
        return acc + group(g).astype(dtype), None

    total, _ = jax.lax.scan(body, jnp.zeros((), dtype), jnp.arange(problem.gyro.shape[0]))
    return total
