"""Preintegration of IMU samples between two keyframes (Forster et al.; GTSAM; VINS-Mono).

Between keyframes i and j the samples are integrated once, in the body frame ``B_i`` of the
first keyframe and without gravity, at a linearisation bias ``b̂``:

    ΔR_ij = Π Exp(ω_k dt_k),   Δv_ij = Σ ΔR_ik f_k dt_k,   Δp_ij = Σ (Δv_ik dt_k + ½ ΔR_ik f_k dt_k²)

(``"euler"``, Forster's on-manifold scheme = GTSAM's ``ManifoldPreintegration``), or with
VINS-Mono's midpoint rule (``"midpoint"``, its ``IntegrationBase::midPointIntegration``
reproduced exactly: first-order quaternion update, its linearisation ``F`` and its 18-dim
noise model ``V``). When an optimiser moves the bias, the deltas are corrected to first
order with the bias Jacobians instead of re-integrating (:func:`correct`).

The error of a :class:`Preintegrated` is ``[δθ, δp, δv, δb_g, δb_a]`` (our error-state
order): ``ΔR = ΔR̂ Exp(δθ)`` and additive ``δp``, ``δv`` in frame ``B_i`` (VINS-Mono's
convention). ``transition`` is the accumulated ``Φ_ij`` of that error (VINS-Mono's
``jacobian``); its bias columns are the bias Jacobians. ``cov15`` includes the bias random
walk (GTSAM's combined factor, VINS-Mono's covariance); ``cov`` is the 9×9 covariance of
``[δθ, δp, δv]`` from the white noise alone (GTSAM's ``preintMeasCov``).

GTSAM expresses ``δp``, ``δv`` in the frame at j (its NavState chart ``p ⊞ ξ = p + R ξ``):
``Preintegrated.covariance(chart="gtsam")`` returns ``T cov Tᵀ`` with
``T = blockdiag(I, ΔRᵀ, ΔRᵀ)``.

Time is parallel too: a one-step transition ``(Φ_k, Q_k)`` composes associatively,
``(Φ, Q)_ac = (Φ_bc Φ_ab, Φ_bc Q_ab Φ_bcᵀ + Q_bc)``, and once the rotations ``ΔR_ik`` are
known (an associative scan of quaternion products) every increment is expressed in frame
``B_i`` and sums are prefix sums. ``method="parallel"`` therefore uses
``lax.associative_scan`` (O(log T) depth) and equals ``method="sequential"`` to rounding,
for both schemes, and can return every prefix ``i→k``.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from jaximu.engine._batching import ArgSpec, leading_axes
from jaximu.engine._preintegration_engine import (
    Preintegrated,
    _Acc,
    _combine,
    _finish,
    _preintegrate,
)
from jaximu.geometry import _checks as val
from jaximu.geometry import _tolerances, sensor, so3
from jaximu.geometry.noise import ImuNoise, check_noise
from jaximu.geometry.state import ImuBias, NavState, check_state
from jaximu.kernels.fast import dense_to_lanes
from jaximu.kernels.lane_math import SOA
from jaximu.kernels.soa import block_lanes, run_blocked
from jaximu.schemes import _blocks as blk
from jaximu.schemes import world
from jaximu.schemes._blocks import mm
from jaximu.schemes._preintegration_steps import _UPPER9
from jaximu.schemes.integrators import apply_deltas, compose_deltas

__all__ = [
    "Preintegrated",
    "preintegrate",
    "correct",
    "compose",
    "predict",
    "residual",
    "whitened_residual",
    "needs_reintegration",
    "bias_jacobians_autodiff",
    "REINTEGRATION_THRESHOLD",
    "SCHEMES",
]

SCHEMES = ("euler", "midpoint")
METHODS = ("auto", "sequential", "parallel")
REINTEGRATION_THRESHOLD = {"gyro": 0.01, "accel": 0.10}
"""Bias changes [rad/s, m/s²] past which VINS-Mono re-integrates instead of correcting."""


def _steps_of(args, batched):
    return args[0].shape[-2]  # gyro is argument 0


_SAMPLES = ArgSpec(2)
_VEC = ArgSpec(1, lambda args, batched: 3)  # bias fields (..., 3); densities scalar or (..., 3)


def routed_preintegrate(scheme, method, jacobians, prefixes):
    """:func:`_preintegrate` whose ``jax.vmap`` lands on the batched kernels; arguments
    ``(gyro, accel, dt, bias, noise, lever)`` (``noise`` and ``lever`` may be ``None``)."""
    return leading_axes(
        _preintegrate,
        (_SAMPLES, _SAMPLES, ArgSpec(1, _steps_of), _VEC, _VEC, _VEC),
        (("jacobians", jacobians), ("method", method), ("prefixes", prefixes), ("scheme", scheme)),
    )


def _check_bias(bias, dtype):
    if bias is None:
        return ImuBias(jnp.zeros(3, dtype), jnp.zeros(3, dtype))
    if not isinstance(bias, ImuBias):
        raise ValueError(f"bias must be a jaximu.ImuBias, got {type(bias).__name__}")
    out = []
    for name in ("b_g", "b_a"):
        x = val.to_dtype(f"bias.{name}", getattr(bias, name), dtype)
        if x.ndim < 1 or x.shape[-1] != 3:
            raise ValueError(f"bias.{name} must have shape (..., 3), got {tuple(x.shape)}")
        val.check_finite(f"bias.{name}", x)
        out.append(x)
    return ImuBias(*out)


def preintegrate(
    gyro,
    accel,
    dt,
    bias: ImuBias | None = None,
    noise: ImuNoise | None = None,
    scheme: str = "euler",
    method: str = "auto",
    *,
    prefixes: bool = False,
    jacobians: str = "analytic",
    body_P_sensor=None,
    tangential: bool = True,
) -> Preintegrated:
    """Preintegrate IMU samples between two keyframes.

    Args:
        gyro, accel: ``(..., T, 3)`` raw samples [rad/s], [m/s²] from keyframe i on.
        dt: ``(..., T)`` steps (sample k held over ``dt[k]``; for ``"midpoint"`` the last
            step then holds sample T-1), or ``(..., T-1)`` when the samples are the ends of
            the intervals (VINS-Mono's ``push_back``: step k uses samples k and k+1; Euler
            then leaves the last sample unused); or a scalar (``(T,)`` steps).
        bias: linearisation bias :class:`ImuBias` (default zero).
        noise: :class:`ImuNoise` densities (default none: zero covariances).
        scheme: ``"euler"`` (Forster / GTSAM Manifold) or ``"midpoint"`` (VINS-Mono).
        method: ``"auto"`` (default: the fastest for the shape, chosen by
            :func:`jaximu.engine._dispatch.preint_method`: ``"parallel"`` for few long windows,
            ``"sequential"`` otherwise), ``"sequential"`` (``lax.scan``) or ``"parallel"``
            (time chunks side by side composed associatively, O(log T) depth on the generic
            path); all give the same numbers to rounding.
        prefixes: return every prefix ``i→k`` (fields gain a time axis before their last
            axes) instead of only ``i→j``.
        jacobians: ``"analytic"`` (closed forms; VINS-Mono's own linearisation for the
            midpoint) or ``"autodiff"`` (``jax.jacfwd`` of each step's mean: exact
            derivatives, also for the midpoint).
        body_P_sensor: optional :class:`jaximu.SensorPose`: the IMU's pose in the body frame
            (GTSAM's ``PreintegrationParams.body_P_sensor``). The deltas are then the body's
            (frame ``B_i``); ``bias``, ``bias_hat`` and the bias rows and columns of
            ``transition`` and ``cov15`` are the sensor's, in S (:mod:`jaximu.sensor`; what
            is approximated in the covariance is said there).
        tangential: with ``body_P_sensor``, correct the tangential acceleration ``α×r``
            too; ``False`` reproduces GTSAM (centripetal ``ω×(ω×r)`` only).

    Returns:
        :class:`Preintegrated`.

    Raises:
        ValueError: on bad shapes, values or options (as :func:`jaximu.propagate`), and on
            an eager call whose result is not finite (``dt`` or samples too large, or ``dt``
            so small that the noise ``σ²/dt`` overflows the dtype).
    """
    if scheme not in SCHEMES:
        raise ValueError(f"unknown preintegration scheme {scheme!r}; choose one of {SCHEMES}")
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {METHODS}")
    if jacobians not in ("analytic", "autodiff"):
        raise ValueError(f"unknown jacobians {jacobians!r}; choose 'analytic' or 'autodiff'")
    prefixes = val.check_bool("prefixes", prefixes)
    tangential = val.check_bool("tangential", tangential)
    # the data's dtype; the noise densities and a sensor pose (constants) take it
    dtype = val.float_dtype(gyro, accel, dt, bias)
    gyro, accel, dt, _ = val.check_imu(gyro, accel, dt, dtype, allow_intervals=True)
    bias = _check_bias(bias, dtype)
    if noise is not None:
        noise = check_noise(noise, dtype)
    val.batch_shape(
        gyro.shape[:-2],
        accel.shape[:-2],
        dt.shape[:-1],
        bias.b_g.shape[:-1],
        bias.b_a.shape[:-1],
        names=("gyro", "accel", "dt", "bias.b_g", "bias.b_a"),
        noise=noise,
    )  # the densities' batch axes too, each named
    if body_P_sensor is not None:
        return _preintegrate_sensor(
            gyro,
            accel,
            dt,
            bias,
            noise,
            scheme,
            method,
            prefixes,
            jacobians,
            body_P_sensor,
            tangential,
        )
    pim = routed_preintegrate(scheme, method, jacobians, prefixes)(gyro, accel, dt, bias, noise)
    return val.check_output(
        "preintegrate",
        pim,
        "dt or the IMU samples are too large, or dt so small that the noise σ²/dt overflows,",
    )


def _preintegrate_sensor(
    gyro, accel, dt, bias, noise, scheme, method, prefixes, jacobians, body_P_sensor, tangential
):
    """:func:`preintegrate` of a sensor at ``body_P_sensor``: the body's samples
    (:func:`jaximu.sensor.to_body`) with body-frame biases, and the result's bias
    quantities back in the sensor frame (``Φ_S = Tᵀ Φ_B T``, ``C_S = Tᵀ C_B T``)."""
    tangential = val.check_bool("tangential", tangential)
    pose = sensor.check_pose(
        body_P_sensor,
        gyro.dtype,
        batch=jnp.broadcast_shapes(gyro.shape[:-2], bias.b_g.shape[:-1]),
        batch_name="samples and bias",
    )
    gyro_b, accel_b = sensor.to_body(pose, gyro, accel, dt, bias.b_g, tangential=tangential)
    bias_b = ImuBias(sensor.bias_to_body(pose, bias.b_g), sensor.bias_to_body(pose, bias.b_a))
    noise_b = None if noise is None else sensor.noise_to_body(pose, noise)
    pim = routed_preintegrate(scheme, method, jacobians, prefixes)(
        gyro_b, accel_b, dt, bias_b, noise_b, sensor.lever_of(pose)
    )
    T = sensor.bias_transform(pose)
    if prefixes:
        T = T[..., None, :, :]
    pim = dataclasses.replace(
        pim,
        transition=sensor.congruence(T, pim.transition, inverse=True),
        cov15=sensor.congruence(T, pim.cov15, inverse=True),
        bias_hat=ImuBias(
            *(
                jnp.broadcast_to(b if b.ndim == h.ndim else b[..., None, :], h.shape)
                for b, h in ((bias.b_g, pim.bias_hat.b_g), (bias.b_a, pim.bias_hat.b_a))
            )
        ),
    )
    return val.check_output(
        "preintegrate",
        pim,
        "dt or the IMU samples are too large, or dt so small that the noise σ²/dt overflows,",
    )


# --------------------------------------------------------------------------- use


def _check_pim(pim):
    """Type and finiteness of a :class:`Preintegrated` given to :func:`correct` & co.;
    returns its batch shape."""
    if not isinstance(pim, Preintegrated):
        raise ValueError(f"pim must be a jaximu.Preintegrated, got {type(pim).__name__}")
    for path, x in jax.tree_util.tree_leaves_with_path(pim):
        val.check_finite("pim" + jax.tree_util.keystr(path), x)
    return pim.delta_q.shape[:-1]


def _check_state_arg(name, state):
    """Shapes, finiteness and unit ``q`` of a state given to :func:`predict`/:func:`residual`
    (validation only: the state is used as given)."""
    if not isinstance(state, NavState):
        raise ValueError(f"{name} must be a jaximu.NavState, got {type(state).__name__}")
    try:
        check_state(state, val.float_dtype(*jax.tree_util.tree_leaves(state)))
    except ValueError as e:
        raise ValueError(str(e).replace("state", name, 1)) from None
    return state.batch_shape


def _output(fn_name, out):
    return val.check_output(fn_name, out, "the states or the preintegrated deltas are too large")


def _corrected_deltas(pim: Preintegrated, bias: ImuBias):
    """``(ΔR, Δv, Δp)`` corrected to first order from ``pim.bias_hat`` to ``bias``."""
    dbg = bias.b_g - pim.bias_hat.b_g
    dba = bias.b_a - pim.bias_hat.b_a

    def mv(M, x):
        return jnp.einsum("...ij,...j->...i", M, x)

    return (
        so3.quat_mul(pim.delta_q, so3.exp(mv(pim.dR_dbg, dbg))),
        pim.delta_v + mv(pim.dv_dbg, dbg) + mv(pim.dv_dba, dba),
        pim.delta_p + mv(pim.dp_dbg, dbg) + mv(pim.dp_dba, dba),
    )


def _correct(pim: Preintegrated, bias: ImuBias) -> Preintegrated:
    dq, dv, dp = _corrected_deltas(pim, bias)
    return dataclasses.replace(
        pim,
        delta_q=dq,
        delta_v=dv,
        delta_p=dp,
        bias_hat=ImuBias(
            jnp.broadcast_to(bias.b_g, pim.bias_hat.b_g.shape),
            jnp.broadcast_to(bias.b_a, pim.bias_hat.b_a.shape),
        ),
    )


def correct(pim: Preintegrated, bias: ImuBias) -> Preintegrated:
    """First-order bias update of the deltas (no re-integration).

    ``ΔR ← ΔR Exp(J_R δb_g)``, ``Δv ← Δv + J_vg δb_g + J_va δb_a``, ``Δp`` likewise, with
    ``δb = bias - pim.bias_hat``. The result has ``bias_hat = bias`` and keeps the Jacobians
    and covariances (a first-order re-linearisation). Past
    :data:`REINTEGRATION_THRESHOLD` re-integrating is advised (:func:`needs_reintegration`).
    ``bias`` may be shared or batched like ``pim`` (its batch must broadcast to ``pim``'s).
    """
    batch = _check_pim(pim)
    if not isinstance(bias, ImuBias):
        raise ValueError(f"bias must be a jaximu.ImuBias, got {type(bias).__name__}")
    bias = _check_bias(bias, val.float_dtype(bias.b_g, bias.b_a))
    if tuple(
        val.batch_shape(
            bias.b_g.shape[:-1], bias.b_a.shape[:-1], batch, names=("bias.b_g", "bias.b_a", "pim")
        )
    ) != tuple(batch):
        raise ValueError(
            f"bias has batch shape {bias.b_g.shape[:-1]} / {bias.b_a.shape[:-1]}, "
            f"which does not broadcast to the preintegrated batch shape {batch}"
        )
    return _output("correct", _correct(pim, bias))


def needs_reintegration(
    pim: Preintegrated, bias: ImuBias, gyro_threshold: float = 0.01, accel_threshold: float = 0.10
):
    """Whether ``bias`` is far enough from ``pim.bias_hat`` that re-integration is advised
    (VINS-Mono: ``|δb_a| > 0.10`` m/s² or ``|δb_g| > 0.01`` rad/s). ``(...,)`` bool.

    ``pim``: a :class:`Preintegrated`; ``bias``: an :class:`ImuBias` whose batch broadcasts
    to ``pim``'s; thresholds ``≥ 0`` and finite [rad/s], [m/s²]. Bad values (a NaN bias,
    which would answer False) raise ``ValueError`` on eager calls.
    """
    batch = _check_pim(pim)
    if not isinstance(bias, ImuBias):
        raise ValueError(f"bias must be a jaximu.ImuBias, got {type(bias).__name__}")
    bias = _check_bias(bias, val.float_dtype(bias.b_g, bias.b_a))
    val.batch_shape(
        bias.b_g.shape[:-1], bias.b_a.shape[:-1], batch, names=("bias.b_g", "bias.b_a", "pim")
    )
    for name, x in (("gyro_threshold", gyro_threshold), ("accel_threshold", accel_threshold)):
        if val.is_concrete(x):
            val.check_positive(name, x, allow_zero=True)
    dbg = jnp.linalg.norm(bias.b_g - pim.bias_hat.b_g, axis=-1)
    dba = jnp.linalg.norm(bias.b_a - pim.bias_hat.b_a, axis=-1)
    return (dbg > gyro_threshold) | (dba > accel_threshold)


def compose(pim_ab: Preintegrated, pim_bc: Preintegrated) -> Preintegrated:
    """``pim_ac`` from two consecutive intervals, each preintegrated in its own start frame.

    ``pim_bc`` is first corrected to ``pim_ab``'s linearisation bias (:func:`correct`). Its
    transition and noise are moved to frame ``B_a`` by ``T = blockdiag(I, ΔR_ab, ΔR_ab, I, I)``
    and composed: ``Φ_ac = (T Φ_bc T⁻¹) Φ_ab``, ``Q_ac = (T Φ_bc T⁻¹) Q_ab (·)ᵀ + T Q_bc Tᵀ``.
    Exact (to rounding) for ``"euler"``; for VINS-Mono's midpoint the conjugation is exact
    only to O((ω dt)²), because VINS-Mono rotates with an unnormalised quaternion.

    Both are :class:`Preintegrated` with finite values and batch shapes that broadcast
    (``ValueError`` naming ``pim_ab`` / ``pim_bc`` otherwise).
    """
    batches = []
    for name, p in (("pim_ab", pim_ab), ("pim_bc", pim_bc)):
        try:
            batches.append(_check_pim(p))
        except ValueError as e:
            raise ValueError(str(e).replace("pim", name, 1)) from None
    try:
        batch = jnp.broadcast_shapes(*batches)
    except ValueError:
        raise ValueError(
            f"pim_ab and pim_bc have batch shapes {tuple(batches[0])} and "
            f"{tuple(batches[1])}, which do not broadcast"
        ) from None

    def widen(p, own):  # a shared measurement against a batch: broadcast it first
        n = len(own)
        return (
            p
            if tuple(own) == tuple(batch)
            else jax.tree_util.tree_map(
                lambda x: jnp.broadcast_to(x, tuple(batch) + x.shape[n:]), p
            )
        )

    pim_ab, pim_bc = widen(pim_ab, batches[0]), widen(pim_bc, batches[1])
    bc = _correct(pim_bc, pim_ab.bias_hat)
    R = pim_ab.delta_R

    def mv(M, x):
        return jnp.einsum("...ij,...j->...i", M, x)

    F = blk.phi_from_dense(bc.transition)
    F = F._replace(
        Cp=mm(R, F.Cp),
        Cv=mm(R, F.Cv),
        Dp=mm(R, F.Dp),
        Dv=mm(R, F.Dv),
        Ep=mm(R, F.Ep),
        Ev=mm(R, F.Ev),
    )
    Phi_ab = blk.phi_from_dense(pim_ab.transition)
    Rb = {0: None, 1: R, 2: R, 3: None, 4: None}

    def ab_blocks(Qd, n):
        if n == 15:
            return blk.dense_to_blocks(Qd)
        return {(i, j): Qd[..., 3 * i : 3 * i + 3, 3 * j : 3 * j + 3] for i, j in _UPPER9}

    def conj(Qd, n):
        Qb = ab_blocks(Qd, n)
        out = {}
        for (i, j), X in Qb.items():
            X = X if Rb[i] is None else mm(Rb[i], X)
            out[(i, j)] = X if Rb[j] is None else mm(X, blk.t(Rb[j]))
        return out

    acc = _combine(
        _Acc(Phi_ab, ab_blocks(pim_ab.cov15, 15), ab_blocks(pim_ab.cov, 9)),
        _Acc(F, conj(bc.cov15, 15), conj(bc.cov, 9)),
    )
    dq, dp, dv, dt = compose_deltas(
        (pim_ab.delta_q, pim_ab.delta_p, pim_ab.delta_v, pim_ab.delta_t),
        (bc.delta_q, bc.delta_p, bc.delta_v, bc.delta_t),
        lambda x: mv(R, x),
    )
    return _finish(dt, dq, dv, dp, acc, pim_ab.bias_hat)


def _gravity(gravity, dtype):
    return val.gravity_vector(gravity, dtype)


def _world(omega_coriolis, dtype, batch, coriolis_exact, coriolis_second_order):
    """``omega_coriolis`` checked (and its batch against ``batch``), and the two bools."""
    val.check_bool("coriolis_exact", coriolis_exact)
    val.check_bool("coriolis_second_order", coriolis_second_order)
    if omega_coriolis is None:
        return None
    omega = world.check_omega(omega_coriolis, dtype)
    val.batch_shape(batch, omega.shape[:-1], names=("states and pim", "omega_coriolis"))
    return omega


def _coriolis_terms(state_i, pim, omega, second_order):
    """GTSAM ≤ 4.2's ``correctPIM`` increments from the state at i (:mod:`jaximu.world`):
    the world-frame ``(dθ, dp, dv)`` over ``Δt_ij``."""
    return world.coriolis_increments(omega, state_i.p, state_i.v, pim.delta_t, second_order)


def _delta_rotation(state_i, delta_q, dth):
    """GTSAM's classic ``Exp(Log ΔR + R_iᵀ dθ_W)``."""
    return so3.exp(so3.log(delta_q) + so3.quat_rotate(so3.quat_conj(state_i.q), dth))


CORIOLIS_DOC = """
    ``omega_coriolis``: optional ``(3,)`` world rotation rate [rad/s] in W (GTSAM's
    ``omegaCoriolis``, e.g. :func:`jaximu.earth_rate`), with ``coriolis_exact=True``
    (default) the exact rotating-world transition over ``Δt_ij`` (GTSAM ≥ 4.3's prediction,
    Coriolis and centrifugal both; :mod:`jaximu.world`), or with ``coriolis_exact=False``
    GTSAM ≤ 4.2's classic ``correctPIM`` terms, ``R_j = R_i Exp(Log ΔR - Δt R_iᵀ ω)``,
    ``v_j += -2Δt ω×v_i``, ``p_j += -Δt² ω×v_i``, and with ``coriolis_second_order`` the
    centrifugal ``-Δt ω×(ω×p_i)``, ``-½Δt² ω×(ω×p_i)``.
"""


def predict(
    state_i: NavState,
    pim: Preintegrated,
    gravity=9.81,
    *,
    omega_coriolis=None,
    coriolis_exact: bool = True,
    coriolis_second_order: bool = False,
) -> NavState:
    """The state at keyframe j from the state at i and the preintegrated measurement.

    The deltas are first corrected to ``state_i``'s biases; then ``R_j = R_i ΔR``,
    ``v_j = v_i + g_W Δt + R_i Δv``, ``p_j = p_i + v_i Δt + ½ g_W Δt² + R_i Δp``; the
    biases are carried over.
    {coriolis}"""
    batch = (_check_state_arg("state_i", state_i), _check_pim(pim))
    g = _gravity(gravity, pim.delta_v.dtype)
    batch = val.batch_shape(*batch, g.shape[:-1], names=("state_i", "pim", "gravity"))
    omega = _world(omega_coriolis, pim.delta_v.dtype, batch, coriolis_exact, coriolis_second_order)
    delta_q, delta_v, delta_p = _corrected_deltas(pim, state_i.bias)
    v_i = state_i.v
    if omega is not None and coriolis_exact:
        v_i = world.to_inertial(omega, state_i.p, v_i)
    q, p, v = apply_deltas(state_i.q, state_i.p, v_i, g, (delta_q, delta_p, delta_v, pim.delta_t))
    if omega is not None and coriolis_exact:
        dth, p, v = world.leave_inertial(omega, pim.delta_t, g, p, v)
        q = so3.quat_mul(so3.exp(dth), q)
    elif omega is not None:
        dth, dp, dv = _coriolis_terms(state_i, pim, omega, coriolis_second_order)
        p, v = p + dp, v + dv
        q = so3.quat_mul(state_i.q, _delta_rotation(state_i, delta_q, dth))
    return _output("predict", NavState(q=q, p=p, v=v, b_g=state_i.b_g, b_a=state_i.b_a))


def residual(
    state_i: NavState,
    state_j: NavState,
    pim: Preintegrated,
    gravity=9.81,
    *,
    omega_coriolis=None,
    coriolis_exact: bool = True,
    coriolis_second_order: bool = False,
):
    """The 15-dim residual ``[r_θ, r_p, r_v, r_bg, r_ba]`` (VINS-Mono's ``evaluate``, our order).

    ``r_θ = Log(ΔR̃ᵀ R_iᵀ R_j)``, ``r_p = R_iᵀ(p_j - p_i - v_i Δt - ½ g_W Δt²) - Δp̃``,
    ``r_v = R_iᵀ(v_j - v_i - g_W Δt) - Δṽ``, ``r_b = b_j - b_i``, with ``~`` the deltas
    corrected to ``state_i``'s biases. Zero for states that agree with the measurement.
    {coriolis}
    The residual then measures ``state_j`` against that prediction: with the exact
    transition in the inertial frame of ``t_i`` (``state_j`` mapped there, the transported
    velocities ``v + ω×p`` and the turning gravity); with the classic terms ``ΔR̃`` becomes
    ``Exp(Log ΔR̃ + R_iᵀ dθ_W)`` and ``dp``, ``dv`` join the gravity terms. Zero for
    ``state_j = predict(state_i, ...)`` with the same options.
    """
    batch = (
        _check_state_arg("state_i", state_i),
        _check_state_arg("state_j", state_j),
        _check_pim(pim),
    )
    g = _gravity(gravity, pim.delta_v.dtype)
    batch = val.batch_shape(*batch, g.shape[:-1], names=("state_i", "state_j", "pim", "gravity"))
    omega = _world(omega_coriolis, pim.delta_v.dtype, batch, coriolis_exact, coriolis_second_order)
    delta_q, delta_v, delta_p = _corrected_deltas(pim, state_i.bias)
    dt = pim.delta_t[..., None]
    qi_inv = so3.quat_conj(state_i.q)
    p_i, v_i, p_j, v_j, q_j, rot = state_i.p, state_i.v, state_j.p, state_j.v, state_j.q, delta_q
    if omega is not None and coriolis_exact:
        v_i = world.to_inertial(omega, p_i, v_i)
        dth, p_j, v_j = world.enter_inertial(omega, pim.delta_t, g, p_j, v_j)
        q_j = so3.quat_mul(so3.exp(-dth), q_j)
    dp_w = p_j - p_i - v_i * dt - 0.5 * g * dt * dt
    dv_w = v_j - v_i - g * dt
    if omega is not None and not coriolis_exact:
        dth, dp, dv = _coriolis_terms(state_i, pim, omega, coriolis_second_order)
        dp_w, dv_w = dp_w - dp, dv_w - dv
        rot = _delta_rotation(state_i, delta_q, dth)
    r_theta = so3.log(so3.quat_mul(so3.quat_conj(rot), so3.quat_mul(qi_inv, q_j)))
    r_p = so3.quat_rotate(qi_inv, dp_w)
    r_v = so3.quat_rotate(qi_inv, dv_w)
    parts = [
        r_theta,
        r_p - delta_p,
        r_v - delta_v,
        state_j.b_g - state_i.b_g,
        state_j.b_a - state_i.b_a,
    ]
    shape = jnp.broadcast_shapes(*(x.shape for x in parts))
    return _output(
        "residual", jnp.concatenate([jnp.broadcast_to(x, shape) for x in parts], axis=-1)
    )


predict.__doc__ = (predict.__doc__ or "").replace("{coriolis}", CORIOLIS_DOC)
residual.__doc__ = (residual.__doc__ or "").replace("{coriolis}", CORIOLIS_DOC)


def whitened_residual(
    state_i: NavState,
    state_j: NavState,
    pim: Preintegrated,
    gravity=9.81,
    *,
    omega_coriolis=None,
    coriolis_exact: bool = True,
    coriolis_second_order: bool = False,
):
    """``L⁻¹ r`` with ``cov15 = L Lᵀ`` (Cholesky): ``|L⁻¹ r|² = rᵀ cov15⁻¹ r``.

    ``cov15`` must be positive definite to the precision of its dtype (the smallest
    eigenvalue of its correlation matrix above 60 ε:
    :func:`jaximu.geometry._tolerances.definiteness`): preintegrate with ``noise=`` whose densities
    and random walks are all non-zero, over at least two samples (one sample's position and
    velocity noise are the same accelerometer noise, fully correlated). On an eager call a
    ``cov15`` that is not (a measurement preintegrated without noise) raises ``ValueError``
    naming the window and the dependent axes (the check runs on the host: about 10 µs a
    window); inside a caller's ``jit`` nothing is checked and the result is then not finite
    (NaN or inf) or meaningless (rounding divided by a near-zero pivot).

    The factorisation is a block Cholesky on lanes (:func:`_whiten`): 65536 windows in
    0.03 s, against 0.13 s for LAPACK's, one matrix at a time (float64, 2-core CPU, 1 device).
    """
    r = residual(
        state_i,
        state_j,
        pim,
        gravity,
        omega_coriolis=omega_coriolis,
        coriolis_exact=coriolis_exact,
        coriolis_second_order=coriolis_second_order,
    )
    _tolerances.check_definite(
        "pim.cov15",
        pim.cov15,
        pim.cov15.dtype,
        axes=_tolerances.ERROR_AXES,
        what="the residual is whitened by its Cholesky factor",
        fix="preintegrate with noise=jaximu.ImuNoise(...) whose four densities are > 0, over "
        "at least two samples",
    )
    return _output("whitened_residual", _whiten(pim.cov15, r))


@jax.jit
def _whiten(cov15, r):
    """``L⁻¹ r`` for ``cov15 = L Lᵀ``, ``(..., 15, 15)`` and ``(..., 15)`` broadcast together:
    the block Cholesky of :func:`jaximu.schemes._blocks.whiten` (the Monte Carlo NEES's) on lanes,
    3×3 blocks ``(3, 3, N)`` (a batch of 15×15 factorisations as LAPACK calls ran one
    matrix at a time: 2 µs per window). Not positive definite: NaN or inf."""
    batch = jnp.broadcast_shapes(cov15.shape[:-2], r.shape[:-1])
    P = jnp.broadcast_to(cov15, batch + (15, 15)).reshape(-1, 15, 15)
    e = jnp.broadcast_to(r, batch + (15,)).reshape(-1, 15)
    if e.shape[0] == 0:  # an empty batch: no lanes to run
        return e.reshape(batch + (15,))

    def block(P, e):  # (Bc, 15, 15), (Bc, 15): one kernel per block of lanes
        Pb = dict(zip(blk.UPPER, dense_to_lanes(P)))
        eT = e.T
        y = blk.whiten(Pb, [eT[3 * i : 3 * i + 3, None] for i in range(5)], SOA)
        return jnp.concatenate([b[:, 0] for b in y], 0).T

    return run_blocked(block, e.shape[0], block_lanes(e.dtype), P, e).reshape(batch + (15,))


def bias_jacobians_autodiff(gyro, accel, dt, bias: ImuBias | None = None, scheme: str = "euler"):
    """The bias Jacobians by ``jax.jacfwd`` of the mean deltas over the whole window.

    Returns ``(dR_dbg, dp_dbg, dp_dba, dv_dbg, dv_dba)``, each ``(..., 3, 3)``, with the
    rotation one defined as in :class:`Preintegrated` (``Log(ΔR̂ᵀ ΔR(b̂ + δ))``).
    ``gyro``, ``accel``, ``dt``, ``bias`` as :func:`preintegrate`; ``scheme`` ``"euler"`` or
    ``"midpoint"``.
    """
    if scheme not in SCHEMES:
        raise ValueError(f"unknown preintegration scheme {scheme!r}; choose one of {SCHEMES}")
    dtype = val.float_dtype(gyro, accel, dt, bias)
    gyro, accel, dt, _ = val.check_imu(gyro, accel, dt, dtype, allow_intervals=True)
    bias = _check_bias(bias, dtype)
    return _bias_jacobians_autodiff(gyro, accel, dt, bias, scheme=scheme)


@functools.partial(jax.jit, static_argnames=("scheme",))
def _bias_jacobians_autodiff(gyro, accel, dt, bias, *, scheme):
    def deltas(delta_b):
        b = ImuBias(bias.b_g + delta_b[..., 0:3], bias.b_a + delta_b[..., 3:6])
        pim = _preintegrate(
            gyro,
            accel,
            dt,
            b,
            None,
            scheme=scheme,
            method="sequential",
            jacobians="analytic",
            prefixes=False,
        )
        return pim.delta_q, pim.delta_p, pim.delta_v

    q0, _, _ = deltas(jnp.zeros(6, gyro.dtype))

    def errors(delta_b):
        q, p, v = deltas(delta_b)
        return so3.log(so3.quat_mul(so3.quat_conj(q0), q)), p, v

    Jq, Jp, Jv = jax.jacfwd(errors)(jnp.zeros(6, gyro.dtype))
    return Jq[..., 0:3], Jp[..., 0:3], Jp[..., 3:6], Jv[..., 0:3], Jv[..., 3:6]
