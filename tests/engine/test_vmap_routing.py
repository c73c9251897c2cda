"""``jax.vmap`` of the engine entries lands on the batched kernels (jaximu/engine/_batching.py).

References, independent of the routing: a Python loop over the batch elements, each
propagated alone through the generic kernels (``fast=False``), for values and gradients;
and the jaxpr of the vmapped call, which must hold one engine call over the whole batch
(no per-element kernel batched by JAX).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaximu
from jaximu.engine.errorstate import _propagate_covariance
from jaximu.engine.preintegration import _preintegrate
from jaximu.engine.propagate import _propagate

T = 7
DT = 0.01
NOISE = jaximu.ImuNoise(2e-3, 3e-2, 1e-4, 2e-3)
G_W = jnp.array([0.0, 0.0, -9.81])


def inputs(n, seed=0):
    rng = np.random.default_rng(seed)
    q = Rotation.random(n, random_state=seed).as_quat(scalar_first=True)
    state = jaximu.NavState(
        *(
            jnp.asarray(x)
            for x in (
                q,
                rng.normal(size=(n, 3)),
                rng.normal(size=(n, 3)),
                0.01 * rng.normal(size=(n, 3)),
                0.1 * rng.normal(size=(n, 3)),
            )
        )
    )
    gyro = jnp.asarray(rng.normal(size=(n, T, 3)))
    accel = jnp.asarray(rng.normal(size=(n, T, 3)) * 2 + [0, 0, 9.81])
    return state, gyro, accel


P0 = jnp.asarray(np.diag(np.linspace(1e-4, 1e-2, 15)))

# Each case: (public call on one or many elements, generic reference on one element).
CASES = {
    "propagate/midpoint": (
        lambda s, w, a: jaximu.propagate(s, w, a, DT, "midpoint"),
        lambda s, w, a: _propagate(
            s,
            w,
            a,
            jnp.full(T, DT),
            G_W,
            scheme="midpoint",
            attitude="quaternion",
            save_all=True,
            fast=False,
        )[0],
    ),
    "propagate_final/euler": (
        lambda s, w, a: jaximu.propagate_final(s, w, a, DT),
        lambda s, w, a: _propagate(
            s,
            w,
            a,
            jnp.full(T, DT),
            G_W,
            scheme="euler",
            attitude="quaternion",
            save_all=False,
            fast=False,
        )[0],
    ),
    "propagate_covariance_final/euler": (
        lambda s, w, a: jaximu.propagate_covariance_final(s, P0, w, a, DT, NOISE),
        lambda s, w, a: _propagate_covariance(
            s,
            P0,
            w,
            a,
            jnp.full(T, DT),
            G_W,
            NOISE,
            scheme="euler",
            attitude="quaternion",
            jacobians="analytic",
            save_all=False,
            fast=False,
        )[:2],
    ),
    "propagate_covariance/rk4": (
        lambda s, w, a: jaximu.propagate_covariance(s, P0, w, a, DT, NOISE, "rk4"),
        lambda s, w, a: _propagate_covariance(
            s,
            P0,
            w,
            a,
            jnp.full(T, DT),
            G_W,
            NOISE,
            scheme="rk4",
            attitude="quaternion",
            jacobians="analytic",
            save_all=True,
            fast=False,
        )[:2],
    ),
    "preintegrate/euler": (
        lambda s, w, a: jaximu.preintegrate(w, a, DT, s.bias, NOISE),
        lambda s, w, a: _preintegrate(
            w,
            a,
            jnp.full(T, DT),
            s.bias,
            NOISE,
            scheme="euler",
            method="sequential",
            jacobians="analytic",
            prefixes=False,
            fast=False,
        ),
    ),
    "preintegrate/midpoint": (
        lambda s, w, a: jaximu.preintegrate(w, a, DT, s.bias, NOISE, "midpoint"),
        lambda s, w, a: _preintegrate(
            w,
            a,
            jnp.full(T, DT),
            s.bias,
            NOISE,
            scheme="midpoint",
            method="sequential",
            jacobians="analytic",
            prefixes=False,
            fast=False,
        ),
    ),
    "preintegrate/midpoint/autodiff": (
        lambda s, w, a: jaximu.preintegrate(
            w, a, DT, s.bias, NOISE, "midpoint", jacobians="autodiff"
        ),
        lambda s, w, a: _preintegrate(
            w,
            a,
            jnp.full(T, DT),
            s.bias,
            NOISE,
            scheme="midpoint",
            method="sequential",
            jacobians="autodiff",
            prefixes=False,
            fast=False,
        ),
    ),
}


def leaves(tree):
    return [x for x in jax.tree_util.tree_leaves(tree) if x.dtype != bool]


def assert_close(got, want, rtol=1e-12):
    for a, b in zip(leaves(got), leaves(want), strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=rtol * max(1.0, float(np.abs(b).max())))


def loop_reference(ref, state, gyro, accel):
    """Each element alone through the generic kernels, stacked."""
    ref = jax.jit(ref)
    n = gyro.shape[0]
    outs = [ref(jax.tree_util.tree_map(lambda x: x[i], state), gyro[i], accel[i]) for i in range(n)]
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *outs)


def loss(out):
    return sum(jnp.sum(jnp.sin(x)) for x in leaves(out))


@pytest.mark.parametrize("name", list(CASES))
def test_vmap_equals_elementwise_generic(name):
    fn, ref = CASES[name]
    state, gyro, accel = inputs(6)
    want = loop_reference(ref, state, gyro, accel)
    assert_close(jax.vmap(fn)(state, gyro, accel), want)
    # nested vmap under jit over (2, 3), and leading axes (2, 3) inside one vmap
    r = lambda x: x.reshape((2, 3) + x.shape[1:])  # noqa: E731
    nested = jax.jit(jax.vmap(jax.vmap(fn)))(*jax.tree_util.tree_map(r, (state, gyro, accel)))
    assert_close(nested, jax.tree_util.tree_map(r, want))
    if name.startswith("propagate/"):  # leading axes inside a vmap
        inner = jax.vmap(fn)(*jax.tree_util.tree_map(r, (state, gyro, accel)))
        assert_close(inner, jax.tree_util.tree_map(r, want))


# Derivatives of the structure-of-arrays kernels take long to compile (~50 s each for the
# covariance ones at the tests' optimisation level): every order on the mean kernel, and the
# order that routes to the batched kernel (grad of vmap) on a preintegration kernel.
@pytest.mark.parametrize(
    "name,orders",
    [
        ("propagate_final/euler", ("grad_vmap", "vmap_grad", "jacfwd")),
        ("preintegrate/euler", ("grad_vmap",)),
    ],
)
def test_gradients_through_vmap(name, orders):
    """grad of vmap, vmap of grad and jacfwd of vmap equal the element-wise generic gradient."""
    fn, ref = CASES[name]
    state, gyro, accel = inputs(3, seed=1)
    ref_grad = jax.jit(jax.grad(lambda w, s, a: loss(ref(s, w, a))))
    want = jnp.stack(
        [
            ref_grad(gyro[i], jax.tree_util.tree_map(lambda x: x[i], state), accel[i])
            for i in range(3)
        ]
    )
    # each order under one jit: the same transforms and routing, one compiled program
    # instead of op-by-op reverse mode (some hundred small compilations)
    grads = {
        "grad_vmap": (jax.grad(lambda w: loss(jax.vmap(fn)(state, w, accel))), (gyro,)),
        "vmap_grad": (
            jax.vmap(jax.grad(lambda s, w, a: loss(fn(s, w, a)), argnums=1)),
            (state, gyro, accel),
        ),
        "jacfwd": (jax.jacfwd(lambda w: loss(jax.vmap(fn)(state, w, accel))), (gyro,)),
    }
    for order in orders:
        derivative, args = grads[order]
        g = jax.jit(derivative)(*args)
        np.testing.assert_allclose(g, want, rtol=1e-10, atol=1e-12 * float(np.abs(want).max()))


def test_mixed_batches_broadcast_as_leading_axes():
    """A mapped state against samples with their own batch axes (not mapped), a mapped scalar
    dt, and a mapped isotropic density: each gets the broadcast of a single call."""
    state, gyro, accel = inputs(4)
    fn = jax.vmap(lambda s: jaximu.propagate_final(s, gyro, accel, DT))
    out = fn(state)
    assert out.q.shape == (4, 4, 4)
    for i in range(4):
        one = jaximu.propagate_final(jax.tree_util.tree_map(lambda x: x[i], state), gyro, accel, DT)
        assert_close(jax.tree_util.tree_map(lambda x: x[i], out), one)
    steps = jnp.array([0.005, 0.02])
    out = jax.vmap(lambda h: jaximu.propagate_final(state, gyro, accel, h))(steps)
    assert_close(
        jax.tree_util.tree_map(lambda x: x[1], out),
        jaximu.propagate_final(state, gyro, accel, 0.02),
    )
    sig = jnp.array([1e-3, 4e-3])
    pim = jax.vmap(lambda s: jaximu.preintegrate(gyro, accel, DT, noise=jaximu.ImuNoise(s, 3e-2)))(
        sig
    )
    one = jaximu.preintegrate(gyro, accel, DT, noise=jaximu.ImuNoise(4e-3, 3e-2))
    assert_close(jax.tree_util.tree_map(lambda x: x[1], pim), one)


@pytest.mark.parametrize(
    "entry,call",
    [
        ("jaximu_propagate", lambda s, w, a: jaximu.propagate(s, w, a, DT)),
        (
            "jaximu_propagate_covariance",
            lambda s, w, a: jaximu.propagate_covariance_final(s, P0, w, a, DT, NOISE),
        ),
        ("jaximu_preintegrate", lambda s, w, a: jaximu.preintegrate(w, a, DT, s.bias, NOISE)),
    ],
)
def test_vmap_is_one_engine_call_over_the_batch(entry, call):
    """The structural property behind the speed: the vmapped program is the engine entry
    called once with the mapped axis in front, not a per-element kernel batched by JAX."""
    state, gyro, accel = inputs(5)
    jaxpr = jax.make_jaxpr(jax.vmap(jax.vmap(call)))(
        *jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), (state, gyro, accel))
    )
    eqns = [e for e in jaxpr.jaxpr.eqns if e.primitive.name == entry]
    assert len(eqns) == 1
    assert not [e for e in jaxpr.jaxpr.eqns if e.primitive.name in ("scan", "while")]
    shapes = {tuple(v.aval.shape) for v in eqns[0].invars}
    assert (2, 5, T, 3) in shapes
