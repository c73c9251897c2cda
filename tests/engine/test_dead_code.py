"""A jitted program computes only what it returns: the engine entries' dead-code rule
(jaximu/engine/_batching.py, ``_dce``) prunes the kernel of outputs nothing reads.

References: the generic recursion (``fast=False``, which has no dead-code rule of its own)
for the values, and the structure of the program JAX lowers (the entry's call keeps only
the outputs read, and the time loops inside carry fewer values).
"""

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import jaxpr_as_fun
from jax.interpreters import partial_eval as pe

import jaximu
from jaximu.engine.preintegration import ImuBias, _preintegrate

T = 40
NOISE = jaximu.ImuNoise(2e-3, 3e-2, 1e-4, 2e-3)
NINE = ("delta_t", "delta_q", "delta_v", "delta_p", "cov", "transition")


def windows(n, seed=0):
    rng = np.random.default_rng(seed)
    gyro = jnp.asarray(rng.normal(size=(n, T, 3)) * 0.8)
    accel = jnp.asarray(rng.normal(size=(n, T, 3)) * 2 + [0, 0, 9.81])
    dt = jnp.asarray(0.005 + 0.001 * rng.random((n, T)))
    bias = ImuBias(
        jnp.asarray(rng.normal(size=(n, 3)) * 0.01), jnp.asarray(rng.normal(size=(n, 3)) * 0.1)
    )
    return gyro, accel, dt, bias


def nine(gyro, accel, dt, bias):
    pim = jaximu.preintegrate(gyro, accel, dt, bias, NOISE)
    return tuple(getattr(pim, k) for k in NINE)


def generic(gyro, accel, dt, bias):
    pim = _preintegrate(
        gyro,
        accel,
        dt,
        bias,
        NOISE,
        scheme="euler",
        method="sequential",
        jacobians="analytic",
        prefixes=False,
        fast=False,
    )
    return tuple(getattr(pim, k) for k in NINE)


def entry_eqns(jaxpr, name):
    """The equations of primitive ``name`` in ``jaxpr`` and its sub-jaxprs."""
    out = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == name:
            out.append(eqn)
        for v in eqn.params.values():
            for x in v if isinstance(v, (tuple, list)) else (v,):
                sub = getattr(x, "jaxpr", x)
                if hasattr(sub, "eqns"):
                    out += entry_eqns(sub, name)
    return out


def scan_carries(jaxpr):
    """The number of carried values of every scan in ``jaxpr`` (sub-jaxprs included)."""
    return [e.params["num_carry"] for e in entry_eqns(jaxpr, "scan")]


def test_unread_cov15_is_pruned_and_values_hold():
    gyro, accel, dt, bias = windows(3)
    closed = jax.make_jaxpr(nine)(gyro, accel, dt, bias)
    (entry,) = entry_eqns(closed.jaxpr, "jaximu_preintegrate")
    whole = len(entry.outvars)
    pruned, _ = pe.dce_jaxpr(closed.jaxpr, [True] * len(closed.jaxpr.outvars))
    (kept,) = entry_eqns(pruned, "jaximu_preintegrate")
    # cov15 and the bias_hat copies are not computed
    assert len(kept.outvars) < whole and kept.params["kept"] is not None
    # the 15×15 recursion's blocks left the kernel's time loop
    assert max(scan_carries(pruned)) < max(scan_carries(closed.jaxpr))
    got = jax.jit(nine)(gyro, accel, dt, bias)
    ref = generic(gyro, accel, dt, bias)
    for k, x, y in zip(NINE, got, ref):
        np.testing.assert_allclose(
            x, y, rtol=1e-11, atol=1e-11 * float(jnp.max(jnp.abs(y))), err_msg=k
        )


def test_vmap_of_a_pruned_call():
    """The batching rule of a pruned call binds the whole entry and returns the outputs kept
    (``kept``): ``vmap`` of the pruned program equals the reference per window."""
    gyro, accel, dt, bias = windows(4, seed=1)
    closed = jax.make_jaxpr(nine)(gyro[0], accel[0], dt[0], ImuBias(bias.b_g[0], bias.b_a[0]))
    pruned, _ = pe.dce_jaxpr(
        closed.jaxpr, [False, False, True, False, True, True], instantiate=True
    )
    (kept,) = entry_eqns(pruned, "jaximu_preintegrate")
    assert kept.params["kept"] is not None
    fn = jaxpr_as_fun(jax.extend.core.ClosedJaxpr(pruned, closed.consts))
    got = jax.vmap(lambda g, a, d, bg, ba: fn(g, a, d, bg, ba))(gyro, accel, dt, bias.b_g, bias.b_a)
    for i in range(4):
        ref = generic(gyro[i], accel[i], dt[i], ImuBias(bias.b_g[i], bias.b_a[i]))
        for x, y in zip(got, (ref[2], ref[4], ref[5])):
            np.testing.assert_allclose(x[i], y, rtol=1e-11, atol=1e-11 * float(jnp.max(jnp.abs(y))))


def test_gradient_through_a_pruned_program():
    """``grad`` of a loss on the 9×9 covariance only, jitted: equal to central differences
    of the generic recursion."""
    gyro, accel, dt, bias = windows(2, seed=2)

    def loss(scale, run):
        out = run(gyro * scale, accel, dt, bias)
        return jnp.sum(out[4] ** 2) * 1e6 + jnp.sum(out[2] ** 2)

    g = jax.jit(jax.grad(lambda s: loss(s, nine)))(1.0)
    eps = 1e-6
    fd = (loss(1.0 + eps, generic) - loss(1.0 - eps, generic)) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_an_unread_call_is_dropped():
    """A program that reads nothing of an entry's call drops the call (its equation is gone
    after dead-code elimination) and still compiles and runs."""
    gyro, accel, dt, bias = windows(2, seed=3)

    def f(g, a, d, b):
        jaximu.preintegrate(g, a, d, b, NOISE)
        jaximu.propagate_final(
            jaximu.NavState(jnp.array([1.0, 0, 0, 0]), *(jnp.zeros(3),) * 4), g[0], a[0], d[0]
        )
        return jnp.sum(g)

    closed = jax.make_jaxpr(f)(gyro, accel, dt, bias)
    assert entry_eqns(closed.jaxpr, "jaximu_preintegrate")
    pruned, _ = pe.dce_jaxpr(closed.jaxpr, [True])
    assert not entry_eqns(pruned, "jaximu_preintegrate")
    assert not entry_eqns(pruned, "jaximu_propagate")
    np.testing.assert_allclose(jax.jit(f)(gyro, accel, dt, bias), np.sum(gyro), rtol=1e-12)
