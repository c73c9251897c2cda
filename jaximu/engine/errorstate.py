"""Error-state transition ``Φ``, noise Jacobian ``G``, process noise ``Q_d``, covariance propagation.

Error state ``δ = [dθ, dp, dv, db_g, db_a]`` (15), rotation error on the right
(``R = R̂ Exp(dθ)``); step noise ``n = [n_g, n_a, n_wg, n_wa]`` (12, see :mod:`jaximu.noise`).
For one step ``x⁺ = f(x, n)``:

    Φ = ∂ (f(x̂ ⊞ δ, 0) ⊟ f(x̂, 0)) / ∂δ,    G = ∂ (f(x̂, n) ⊟ f(x̂, 0)) / ∂n,
    P⁺ = Φ P Φᵀ + G Q_c Gᵀ,                  Q_c = diag(σ_g², σ_a², σ_bg², σ_ba²) / dt.

Two ways to get ``Φ`` and ``G``, tested equal:

* ``"autodiff"``: ``jax.jacfwd`` through ``boxplus``/``boxminus`` of the step function; any
  scheme and attitude form. The reference.
* ``"analytic"``: closed forms (OpenVINS / Solà) for the exact-exponential forms
  (``"quaternion"``, ``"matrix"``). With the stages of :mod:`jaximu.integrators`
  (``R_s = R̂ Exp(φ_s)``, ``u_s = R_s f_s``):

      Φ_θθ = Exp(φ_end)ᵀ            Φ_θbg = Jr(φ_end) ∂φ_end/∂b_g
      Φ_vθ = -[Σ wv_s u_s]x R̂       Φ_pθ = -[Σ wp_s u_s]x R̂      Φ_pv = dt I
      Φ_vbg = -Σ wv_s R_s [f_s]x Jr(φ_s) ∂φ_s/∂b_g      (zero for Euler)
      Φ_vba = -Σ wv_s R_s            (p rows: the same with wp_s)
      G = [[Φ_θbg, 0, 0, 0], [Φ_pbg, Φ_pba, 0, 0], [Φ_vbg, Φ_vba, 0, 0], [0, 0, dt I, 0], [0, 0, 0, dt I]]

  For Euler this is OpenVINS's discrete model (``Φ_θbg = -Jr(ω dt) dt``,
  ``Φ_vθ = -R̂ [f]x dt``, ``Φ_pθ = -½ R̂ [f]x dt²``, ``Φ_vba = -R̂ dt``, ``Φ_pba = -½ R̂ dt²``).

The analytic covariance update uses the block structure of ``Φ`` (identity and zero blocks,
a handful of 3×3 products on the upper blocks of the symmetric ``P``) instead of dense
15×15 products.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaximu.engine import _dispatch as dispatch
from jaximu.engine._batching import ArgSpec, leading_axes
from jaximu.engine._covariance_lanes import CovarianceInputs
from jaximu.engine._inputs import (
    broadcast_state,
    kernel_ready,
    n_steps,
    prepare,
    time_major,
)
from jaximu.engine.jacobians import (
    JACOBIANS,
    _resolve_jacobians,
    blocks_autodiff,
    discrete_process_noise,
    step_jacobians,
)
from jaximu.engine.propagate import (
    SAMPLES,
    STATE,
    VECTOR,
    _report_gimbal_lock,
    _sensor_options,
    coriolis_mode,
    mean_body,
    sensor_biases,
)
from jaximu.geometry import _checks as val
from jaximu.geometry import _tolerances, sensor
from jaximu.geometry.noise import ImuNoise, check_noise
from jaximu.geometry.state import NavState
from jaximu.schemes import _blocks as blk
from jaximu.schemes import world
from jaximu.schemes.integrators import (
    blocks_analytic,
    get_attitude,
)

__all__ = [
    "step_jacobians",
    "discrete_process_noise",
    "propagate_covariance",
    "propagate_covariance_final",
    "accumulate_covariance",
    "compose_transitions",
    "transition_products",
    "JACOBIANS",
]


# --------------------------------------------------------------------------- covariance


structured_update = blk.structured_update


def _check_cov(P0, dtype, name: str = "P0", n: int = 15):
    """Shape and finiteness of ``P0``, and (eager calls) its symmetry and semi-definiteness
    judged per axis (:func:`jaximu.geometry._tolerances.check_covariance`: no negative variance,
    60 ε of the computation dtype on ``D^-½ P0 D^-½``, ``D`` its variances). ``name``: the argument in the
    messages; ``n``: the matrix size (15 for the error state)."""
    P0 = val.to_dtype(name, P0, dtype)
    if P0.ndim < 2 or P0.shape[-2:] != (n, n):
        raise ValueError(f"{name} must have shape (..., {n}, {n}), got {tuple(P0.shape)}")
    val.check_finite(name, P0)
    _tolerances.check_covariance(name, P0, P0.dtype)
    return P0


def small_matmul(X, Y):
    """``X @ Y`` for small batched matrices as broadcast-and-sum: XLA:CPU fuses it, where it
    runs small batched dots one by one."""
    return jnp.sum(X[..., :, :, None] * Y[..., None, :, :], axis=-2)


def compose_transitions(first, then):
    """The pair ``(Φ, Q)`` of two consecutive spans: ``first = (Φ_a, Q_a)`` followed by
    ``then = (Φ_b, Q_b)`` gives ``(Φ_b Φ_a, Φ_b Q_a Φ_bᵀ + Q_b)``, the transition and
    accumulated noise of the covariance recursion over both (associative: any grouping of
    spans composes to the same pair). Dense arrays ``(..., n, n)``: the same composition as
    :func:`jaximu.schemes._blocks.compose_transitions` on the kernels' block layout."""
    (Fa, Qa), (Fb, Qb) = first, then
    return (small_matmul(Fb, Fa), small_matmul(small_matmul(Fb, Qa), jnp.swapaxes(Fb, -1, -2)) + Qb)


def transition_products(Phi, axis: int = -3):
    """Accumulated transitions ``Φ_k ⋯ Φ_1 Φ_0`` for every ``k`` along ``axis`` of
    ``Phi`` ``(..., T, n, n)``, by a parallel prefix product (``jax.lax.associative_scan``)."""
    return jax.lax.associative_scan(lambda A, B: small_matmul(B, A), Phi, axis=axis)


def accumulate_covariance(Phi, Q, P0=None, *, save_all: bool = False):
    """The covariance recursion ``P_{k+1} = Φ_k P_k Φ_kᵀ + Q_k`` over given per-step terms.

    The building block for covariances whose per-step terms are known already: per-sample
    noise densities (``Q_k`` from :func:`discrete_process_noise` with a time axis in the
    densities), a sub-block of the error state (the rotation rows ``[:3, :3]`` of
    :func:`step_jacobians`' ``Φ`` are exact on their own: the rotation error depends only on
    itself and the gyro bias), or chunk summaries composed in turn.

    Args:
        Phi: ``(..., T, n, n)`` transitions; Q: ``(..., T, n, n)`` step noise (symmetric).
        P0: ``(..., n, n)`` covariance before step 0 (default zero).
        save_all: return every ``P_1 … P_T`` (``(..., T, n, n)``) instead of ``P_T``.

    Returns:
        ``(..., n, n)`` (or ``(..., T, n, n)``), symmetrised at each step.
    """
    Phi, Q = jnp.asarray(Phi), jnp.asarray(Q)
    if Phi.ndim < 3 or Phi.shape[-1] != Phi.shape[-2] or Q.shape[-3:] != Phi.shape[-3:]:
        raise ValueError(
            f"Phi and Q must have shapes (..., T, n, n) with the same T and n, "
            f"got {tuple(Phi.shape)} and {tuple(Q.shape)}"
        )
    batch = jnp.broadcast_shapes(
        Phi.shape[:-3], Q.shape[:-3], () if P0 is None else jnp.shape(P0)[:-2]
    )
    n = Phi.shape[-1]
    dtype = jnp.result_type(Phi, Q)
    P = (
        jnp.zeros(batch + (n, n), dtype)
        if P0 is None
        else jnp.broadcast_to(jnp.asarray(P0, dtype), batch + (n, n))
    )

    def step(P, fq):
        F, Qk = fq
        P = blk.sym(small_matmul(small_matmul(F, P), jnp.swapaxes(F, -1, -2)) + Qk)
        return P, (P if save_all else None)

    xs = tuple(jnp.moveaxis(jnp.broadcast_to(x, batch + x.shape[-3:]), -3, 0) for x in (Phi, Q))
    P, every = jax.lax.scan(step, P, xs)
    return jnp.moveaxis(every, 0, -3) if save_all else P


@functools.partial(
    jax.jit,
    static_argnames=(
        "scheme",
        "attitude",
        "jacobians",
        "save_all",
        "fast",
        "coriolis",
        "tangential",
    ),
)
def _propagate_covariance(
    state,
    P0,
    gyro,
    accel,
    dt,
    g,
    noise,
    omega=None,
    lever=None,
    pose=None,
    *,
    scheme,
    attitude,
    jacobians,
    save_all,
    fast=True,
    coriolis="exact",
    tangential=True,
):
    """The covariance's engine. ``pose``: ``None``, or the samples are a sensor's there and
    ``state``'s biases the sensor's (:func:`jaximu.engine._inputs.sensor_engine_inputs`; ``P0``,
    ``noise`` and ``lever`` are already the body's); the returned biases are the body's."""
    get_attitude(attitude)  # an unknown form is named here, before the table is read
    nb = lambda x: x.shape[:-1] if x.ndim else ()  # noqa: E731
    batch = jnp.broadcast_shapes(
        state.batch_shape,
        P0.shape[:-2],
        gyro.shape[:-2],
        accel.shape[:-2],
        dt.shape[:-1],
        g.shape[:-1],
        *(nb(jnp.asarray(x)) for x in jax.tree_util.tree_leaves(noise)),
        *(nb(x) for x in (omega, lever) if x is not None),
        *(() if pose is None else (nb(pose.q), nb(pose.p))),
    )
    lanes = int(np.prod(batch, dtype=np.int64))
    run = dispatch.implementation(
        "covariance",
        scheme,
        attitude=attitude,
        jacobians=jacobians,
        save_all=save_all,
        lanes=lanes,
        steps=n_steps(gyro, dt),
        dtype=gyro.dtype,
        fast=fast,
        rotating=omega is not None,
        lever=lever is not None,
    )
    return run(
        CovarianceInputs(
            state,
            P0,
            gyro,
            accel,
            dt,
            g,
            noise,
            batch,
            scheme,
            jacobians,
            omega,
            coriolis,
            lever,
            save_all,
            attitude,
            pose,
            tangential,
        )
    )


@dispatch.implements("covariance", dispatch.GENERIC)
def _covariance_generic(inputs: CovarianceInputs):
    """The covariance by ``lax.scan`` on ``(..., 3)`` arrays: the reference kernel."""
    a = kernel_ready(inputs, soa=False)
    scheme, jacobians, noise, g, batch = a.scheme, a.jacobians, a.noise, a.g, a.batch
    omega, coriolis, lever, save_all = a.omega, a.coriolis, a.lever, a.save_all
    att = get_attitude(a.attitude)
    state = broadcast_state(a.state, batch)
    P0 = jnp.broadcast_to(a.P0, tuple(batch) + (15, 15))
    xs = time_major(a.gyro, a.accel, a.dt, scheme)
    b_g, b_a = state.b_g, state.b_a
    mean = mean_body(scheme, att, b_g, b_a, g, omega, coriolis)

    def body(carry, xs):
        x, p, v, locked, Pc = carry
        w0, a0, w1, a1, h = xs
        qc = noise.discrete_variances(h, x.dtype)
        if jacobians == "analytic":
            b = blocks_analytic(
                scheme, att.to_matrix(x), w0 - b_g, a0 - b_a, w1 - b_g, a1 - b_a, h, lever
            )
        else:
            v_lin = v if omega is None or coriolis != "exact" else world.to_inertial(omega, p, v)
            lin = NavState(att.to_quat(x), p, v_lin, b_g, b_a)
            b = blocks_autodiff(scheme, att, lin, w0, a0, w1, a1, h, g, lever)
        if omega is None:
            Pn = structured_update(Pc, b, qc)
        else:
            Pn = world.covariance_step(Pc, b, qc, omega, h, coriolis)
        (x, p, v, locked), _ = mean((x, p, v, locked), xs)
        out = None
        if save_all:
            out = (att.to_quat(x), p, v, blk.blocks_to_dense(Pn))
        return (x, p, v, locked, Pn), out

    P_init = blk.dense_to_blocks(P0)
    carry0 = (att.from_quat(state.q), state.p, state.v, jnp.zeros(batch, bool), P_init)
    (x, p, v, locked, Pc), out = jax.lax.scan(body, carry0, xs)
    if save_all:
        T = n_steps(a.gyro, a.dt)
        q_t, p_t, v_t, P_t = out
        q_t, p_t, v_t = (jnp.moveaxis(y, 0, -2) for y in (q_t, p_t, v_t))
        P_t = jnp.moveaxis(P_t, 0, -3)
        bshape = tuple(batch) + (T, 3)
        states = NavState(
            q_t,
            p_t,
            v_t,
            jnp.broadcast_to(b_g[..., None, :], bshape),
            jnp.broadcast_to(b_a[..., None, :], bshape),
        )
        return states, P_t, locked
    P_final = blk.blocks_to_dense(Pc)
    return NavState(att.to_quat(x), p, v, b_g, b_a), P_final, locked


NOISE = ArgSpec(1, lambda args, batched: 3)  # a density: scalar (isotropic) or (..., 3)


COVARIANCE = ArgSpec(2)


def _steps_of(args, batched):
    return args[2].shape[-2]  # gyro is argument 2


def routed_covariance(scheme, attitude, jacobians, save_all, coriolis="exact", tangential=True):
    """:func:`_propagate_covariance` whose ``jax.vmap`` lands on the batched kernels;
    arguments ``(state, P0, gyro, accel, dt, g, noise, omega, lever, pose)`` (``omega``,
    ``lever`` and ``pose`` may be ``None``)."""
    return leading_axes(
        _propagate_covariance,
        (
            STATE,
            COVARIANCE,
            SAMPLES,
            SAMPLES,
            ArgSpec(1, _steps_of),
            VECTOR,
            NOISE,
            VECTOR,
            VECTOR,
            VECTOR,
        ),
        (
            ("attitude", attitude),
            ("jacobians", jacobians),
            ("save_all", save_all),
            ("scheme", scheme),
            ("coriolis", coriolis),
            ("tangential", tangential),
        ),
    )


def _covariance_entry(
    state,
    P0,
    gyro,
    accel,
    dt,
    noise,
    scheme,
    attitude,
    gravity,
    jacobians,
    save_all,
    body_P_sensor=None,
    tangential=True,
    omega_coriolis=None,
    coriolis="exact",
):

    state, gyro, accel, dt, g, batch = prepare(
        state, gyro, accel, dt, gravity, scheme, attitude, (P0,)
    )
    dtype = state.q.dtype
    P0 = _check_cov(P0, dtype)
    noise = check_noise(noise, dtype)
    val.batch_shape(batch, P0.shape[:-2], names=("state and samples", "P0"), noise=noise)
    jac = _resolve_jacobians(jacobians, get_attitude(attitude))
    tangential, omega, pose = _sensor_options(
        state, gyro, accel, body_P_sensor, tangential, omega_coriolis
    )
    lever = None
    if pose is not None:  # bias errors in S outside, in B inside (jaximu/geometry/sensor.py)
        T = sensor.bias_transform(pose)
        P0 = sensor.congruence(T, P0)
        noise = sensor.noise_to_body(pose, noise)
        lever = sensor.lever_of(pose)
    # the samples move into the body frame inside the engine
    states, P, locked = routed_covariance(scheme, attitude, jac, save_all, coriolis, tangential)(
        state, P0, gyro, accel, dt, g, noise, omega, lever, pose
    )
    if body_P_sensor is not None:
        states = sensor_biases(states, state, save_all)
        P = sensor.congruence(T[..., None, :, :] if save_all else T, P, inverse=True)
    _report_gimbal_lock(locked, attitude)
    name = "propagate_covariance" if save_all else "propagate_covariance_final"
    return val.check_output(
        name,
        (states, P),
        "dt or the IMU samples are too large, or dt so small that the noise σ²/dt overflows,",
    )


def propagate_covariance(
    state: NavState,
    P0,
    gyro,
    accel,
    dt,
    noise: ImuNoise,
    scheme: str = "euler",
    *,
    attitude: str = "quaternion",
    gravity=9.81,
    jacobians: str = "auto",
    body_P_sensor=None,
    tangential: bool = True,
    omega_coriolis=None,
    coriolis_exact: bool = True,
    coriolis_second_order: bool = False,
):
    """Propagate the state and its 15×15 error-state covariance through IMU samples.

    ``P⁺ = Φ P Φᵀ + G Q_c Gᵀ`` at every sample, linearised at the state before the step.

    Args:
        state, gyro, accel, dt, scheme, attitude, gravity: as :func:`jaximu.propagate`.
        P0: ``(..., 15, 15)`` symmetric PSD covariance of ``[dθ, dp, dv, db_g, db_a]`` at t_0.
        noise: :class:`ImuNoise` densities (fields may be batched ``(..., 3)``).
        jacobians: ``"analytic"`` (closed forms + block-structured update; exact-exponential
            forms), ``"autodiff"`` (``jax.jvp`` of the step in the 9 non-structural
            directions, :func:`blocks_autodiff`; any form; the same block update) or ``"auto"``
            (analytic where available).
        body_P_sensor, tangential, omega_coriolis, coriolis_exact, coriolis_second_order: as
            :func:`jaximu.propagate`. With ``body_P_sensor`` the bias rows and columns of
            ``P0`` and of the result refer to the sensor frame, and the densities are the
            sensor's (what is approximated: :mod:`jaximu.sensor`). With ``omega_coriolis``
            the covariance takes the rotating world's transition through its exact Jacobian
            (generic kernels).

    Returns:
        ``(states, covariances)``: a :class:`NavState` with fields ``batch + (T, ·)`` as
        :func:`jaximu.propagate`, and ``batch + (T, 15, 15)`` covariances (entry k after
        sample k), symmetric and positive semi-definite.
    """
    return _covariance_entry(
        state,
        P0,
        gyro,
        accel,
        dt,
        noise,
        scheme,
        attitude,
        gravity,
        jacobians,
        True,
        body_P_sensor,
        tangential,
        omega_coriolis,
        coriolis_mode(coriolis_exact, coriolis_second_order),
    )


def propagate_covariance_final(
    state: NavState,
    P0,
    gyro,
    accel,
    dt,
    noise: ImuNoise,
    scheme: str = "euler",
    *,
    attitude: str = "quaternion",
    gravity=9.81,
    jacobians: str = "auto",
    body_P_sensor=None,
    tangential: bool = True,
    omega_coriolis=None,
    coriolis_exact: bool = True,
    coriolis_second_order: bool = False,
):
    """Like :func:`propagate_covariance`, returning only the final state and ``(..., 15, 15)`` covariance."""
    return _covariance_entry(
        state,
        P0,
        gyro,
        accel,
        dt,
        noise,
        scheme,
        attitude,
        gravity,
        jacobians,
        False,
        body_P_sensor,
        tangential,
        omega_coriolis,
        coriolis_mode(coriolis_exact, coriolis_second_order),
    )
