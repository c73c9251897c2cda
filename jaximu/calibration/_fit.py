"""The fit behind :func:`jaximu.calibration.calibrate`: the free fields' layout in one scaled
vector with the nuisance keyframe velocities, the objective and its Jacobian, the
Levenberg–Marquardt loop and the optax loops."""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaximu.calibration._checks import QUICK_COMPILE_SAMPLES, _compiled
from jaximu.calibration._model import (
    _SIZES,
    _TANGENT,
    _VELOCITY_SCALE,
    FIELDS,
    SCALES,
    CalibrationProblem,
    ImuCalibration,
    _group_residuals,
    calibration_loss,
    calibration_residuals,
)
from jaximu.geometry import so3

# --------------------------------------------------------------------------- fitting


class _Layout(NamedTuple):
    free: tuple  # names of the estimated fields, in FIELDS order
    n_velocity: int  # 0, or 3 (K + 1) nuisance velocities


def _n_free(free):
    return sum(_TANGENT[n] for n in free)


def _scale_vector(free, dtype):
    return jnp.asarray(
        np.concatenate([np.full(_TANGENT[n], SCALES[n]) for n in FIELDS if n in free]), dtype
    )


def _flatten(calib: ImuCalibration):
    return jnp.concatenate([jnp.reshape(getattr(calib, n), (-1,)) for n in FIELDS])


def _unflatten(vec) -> ImuCalibration:
    out, off = {}, 0
    for n in FIELDS:
        k = _SIZES[n]
        out[n] = vec[off : off + k] if k > 1 else vec[off]
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
        step = SCALES[name] * (z[off : off + k] if _SIZES[name] > 1 else z[off])
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


@functools.cache
def _optimizer(name, learning_rate):
    if name == "adam":
        return optax.adam(learning_rate)
    return optax.lbfgs(memory_size=20)


@functools.partial(jax.jit, static_argnames=("layout",))
def _value_and_grad(z, problem, init_vec, *, layout):
    """The loss at ``z`` and its gradient (module-level jit: compiled once per problem shape
    and layout): Adam's every step and L-BFGS's first."""
    return jax.value_and_grad(_objective)(z, problem, init_vec, layout)


@functools.partial(jax.jit, static_argnames=("layout", "learning_rate"))
def _lbfgs_step(z, opt_state, value, grad, problem, init_vec, *, layout, learning_rate):
    """One L-BFGS step from ``z`` with the loss's ``value`` and ``grad`` there (its line
    search's, kept in ``opt_state``, or :func:`_value_and_grad`'s on the first step): the
    program holds the gradient once, in the line search, not a second time for the start."""
    opt = _optimizer("lbfgs", learning_rate)
    fn = functools.partial(_objective, problem=problem, init_vec=init_vec, layout=layout)
    updates, opt_state = opt.update(grad, opt_state, z, value=value, grad=grad, value_fn=fn)
    return optax.apply_updates(z, updates), opt_state


@functools.partial(jax.jit, static_argnames=("learning_rate",))
def _adam_update(z, opt_state, grad, *, learning_rate):
    updates, opt_state = _optimizer("adam", learning_rate).update(grad, opt_state, z)
    return optax.apply_updates(z, updates), opt_state


def _step(z, opt_state, problem, init_vec, *, layout, optimizer, learning_rate):
    """One optimiser step: ``(z_new, opt_state, value, |grad|)``, the loss and its gradient
    at ``z``. Compiled once per problem shape and settings, in pieces that share the
    gradient's program (:func:`_value_and_grad`)."""
    if optimizer == "lbfgs":
        # the value and gradient the line search found at z (optax.value_and_grad_from_state,
        # host-side): computed afresh where the state has none (the first step) or a
        # non-finite one
        value, grad = optax.tree.get(opt_state, "value"), optax.tree.get(opt_state, "grad")
        if not np.isfinite(float(value)):
            value, grad = _value_and_grad(z, problem, init_vec, layout=layout)
        z_new, opt_state = _lbfgs_step(
            z,
            opt_state,
            value,
            grad,
            problem,
            init_vec,
            layout=layout,
            learning_rate=learning_rate,
        )
    else:
        value, grad = _value_and_grad(z, problem, init_vec, layout=layout)
        z_new, opt_state = _adam_update(z, opt_state, grad, learning_rate=learning_rate)
    return z_new, opt_state, value, jnp.linalg.norm(grad)


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
            return jax.jvp(
                f,
                (zero, zero),
                (jnp.broadcast_to(e[:3], vi.shape), jnp.broadcast_to(e[3:], vj.shape)),
            )[1]

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


def _optax_loop(z, problem, init_vec, layout, optimizer, learning_rate, steps, tol, dtype):
    """The optax optimiser's steps (one compiled :func:`_step`); ``(z, history, converged)``."""
    opt = _optimizer(optimizer, float(learning_rate))
    # Strong-typed leaves (optax's init has weak-typed scalars): the state of step 1 then has
    # the same types as that of later steps, and the step compiles once.
    opt_state = jax.tree_util.tree_map(
        lambda x: jnp.array(x, dtype=jnp.asarray(x).dtype), opt.init(z)
    )
    steps = steps if steps is not None else (100 if optimizer == "lbfgs" else 1000)
    history, quiet, converged = [], 0, False
    for _ in range(steps):
        z_new, opt_state, value, gnorm = _step(
            z,
            opt_state,
            problem,
            init_vec,
            layout=layout,
            optimizer=optimizer,
            learning_rate=float(learning_rate),
        )
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
