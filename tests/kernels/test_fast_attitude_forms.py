"""The structure-of-arrays kernels in the attitude forms other than the exact quaternion:
the rotation matrix (exact exponential, closed-form and autodiff Jacobians), the
first-order quaternion (autodiff Jacobians) and Euler angles (autodiff Jacobians, their
pitch singularity reported), against the generic kernels (``fast=False``), which carry the same
forms as ``(..., 3, 3)`` / ``(..., 4)`` / ``(..., 3)`` arrays and differentiate the
quaternion state with ``jax.jacfwd`` (jaximu/engine/errorstate.py)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _shared import random_inputs

import jaximu
from jaximu.engine import _dispatch
from jaximu.engine.errorstate import _propagate_covariance
from jaximu.engine.propagate import _propagate

G_W = jnp.array([0.0, 0.0, -9.81])
NOISE = jaximu.ImuNoise(jnp.asarray([1e-3, 2e-3, 3e-3]), 2e-3, 1e-4, 3e-3)
EARTH = jnp.asarray(jaximu.earth_rate(48.0))


def inputs(B, T, seed=0, big_angles=False, dtype=np.float64):
    """:func:`_shared.random_inputs` and a dt per lane and step ``(B, T)``."""
    state, gyro, accel = random_inputs(B, T, seed, big_angles, dtype)
    dt = np.random.default_rng(seed + 100).uniform(0.002, 0.02, size=(B, T))
    return state, gyro, accel, jnp.asarray(dt, dtype)


def assert_close(got, want, rtol=1e-12):
    """Every leaf within ``rtol`` of the largest value of the reference's leaf."""
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        assert a.shape == b.shape and a.dtype == b.dtype
        np.testing.assert_allclose(a, b, rtol=0, atol=rtol * max(1.0, float(np.abs(b).max())))


@functools.partial(jax.jit, static_argnames=("attitude", "scheme", "save_all", "fast"))
def mean(state, gyro, accel, dt, omega, *, attitude, scheme, save_all, fast):
    return _propagate(
        state,
        gyro,
        accel,
        dt,
        G_W.astype(gyro.dtype),
        omega,
        scheme=scheme,
        attitude=attitude,
        save_all=save_all,
        fast=fast,
    )[0]


@functools.partial(jax.jit, static_argnames=("attitude", "scheme", "jacobians", "save_all", "fast"))
def covariance(
    state, P0, gyro, accel, dt, omega, lever, *, attitude, scheme, jacobians, save_all, fast
):
    return _propagate_covariance(
        state,
        P0,
        gyro,
        accel,
        dt,
        G_W,
        NOISE,
        omega,
        lever,
        scheme=scheme,
        attitude=attitude,
        jacobians=jacobians,
        save_all=save_all,
        fast=fast,
    )[:2]


def test_dispatch_of_the_attitude_forms():
    """Every attitude form runs the SoA kernels (closed forms only for the exact
    exponential; the CPU's rows)."""
    k = functools.partial(_dispatch.kernel, on=_dispatch.CPU)
    for att in ("matrix", "quaternion_first_order"):
        assert k("mean", "rk4", attitude=att, lanes=40) == "soa_mean"
        assert (
            k("mean", "euler", attitude=att, lanes=1, steps=10**5, dtype="float64") == "soa_mean"
        )  # the time chunks compose quaternions
        assert (
            k("covariance", "midpoint", attitude=att, jacobians="autodiff", lanes=3)
            == "soa_cov_autodiff"
        )
    assert (
        k("covariance", "rk4", attitude="matrix", jacobians="analytic", lanes=3)
        == "soa_cov_analytic"
    )
    assert (
        k("covariance", "rk4", attitude="quaternion_first_order", jacobians="analytic", lanes=3)
        == "generic"
    )
    assert k("mean", "rk4", attitude="euler_angles", lanes=40) == "soa_mean"
    assert (
        k("covariance", "euler", attitude="euler_angles", jacobians="autodiff", lanes=3)
        == "soa_cov_autodiff"
    )
    assert (
        k("covariance", "euler", attitude="euler_angles", jacobians="analytic", lanes=3)
        == "generic"
    )  # which raises: no closed form


@pytest.mark.parametrize(
    "attitude,scheme,save_all,rotating",
    [
        ("matrix", "euler", False, False),
        ("matrix", "midpoint", True, False),
        ("matrix", "rk4", False, True),
        ("quaternion_first_order", "euler", True, False),
        ("quaternion_first_order", "midpoint", False, True),
    ],
)
def test_mean_in_attitude_forms_equals_generic(attitude, scheme, save_all, rotating):
    """40 lanes (a batch block), per-lane dt, a third of the lanes past π/2 per step."""
    state, gyro, accel, dt = inputs(40, 31, big_angles=True)
    omega = 1e3 * EARTH if rotating else None  # a fast-turning world, so that it shows
    if scheme != "euler":
        dt = dt[:, :-1]  # samples at the ends of the intervals
    args = (state, gyro, accel, dt, omega)
    fast = mean(*args, attitude=attitude, scheme=scheme, save_all=save_all, fast=True)
    ref = mean(*args, attitude=attitude, scheme=scheme, save_all=save_all, fast=False)
    assert_close(fast, ref)
    # the form is not the quaternion's: the first-order update differs from the exact one
    if attitude == "quaternion_first_order":
        exact = mean(*args, attitude="quaternion", scheme=scheme, save_all=save_all, fast=True)
        assert float(jnp.max(jnp.abs(exact.q - fast.q))) > 1e-6


def test_mean_matrix_form_float32_and_batch_shapes():
    state, gyro, accel, dt = inputs(6, 20, seed=3, dtype=np.float32)
    r = lambda x: x.reshape((2, 3) + x.shape[1:])  # noqa: E731
    state, gyro, accel, dt = jax.tree_util.tree_map(r, (state, gyro, accel, dt))
    fast = mean(
        state, gyro, accel, dt, None, attitude="matrix", scheme="rk4", save_all=True, fast=True
    )
    ref = mean(
        state, gyro, accel, dt, None, attitude="matrix", scheme="rk4", save_all=True, fast=False
    )
    assert fast.q.shape == (2, 3, 20, 4) and fast.q.dtype == jnp.float32
    assert_close(fast, ref, rtol=2e-6)


@pytest.mark.parametrize(
    "attitude,scheme,jacobians,save_all,extra",
    [
        ("matrix", "euler", "analytic", False, None),
        ("matrix", "rk4", "analytic", True, None),
        ("matrix", "midpoint", "autodiff", False, "lever"),
        ("quaternion_first_order", "rk4", "autodiff", False, "rotating"),
    ],
)
def test_covariance_in_attitude_forms_equals_generic(attitude, scheme, jacobians, save_all, extra):
    """Mean and 15×15 covariance, final or after every step, with a turning world or a
    sensor's lever arm in the Jacobians, against the generic kernel with the same option."""
    B, T = 3, 19
    state, gyro, accel, dt = inputs(B, T, seed=4, big_angles=True)
    rng = np.random.default_rng(5)
    A = rng.normal(size=(15, 15)) * 0.02
    P0 = jnp.asarray(A @ A.T + 1e-6 * np.eye(15))
    omega = 1e3 * EARTH if extra == "rotating" else None
    lever = jnp.asarray([0.3, -0.2, 0.15]) if extra == "lever" else None
    kw = dict(attitude=attitude, scheme=scheme, jacobians=jacobians, save_all=save_all)
    s1, P1 = covariance(state, P0, gyro, accel, dt, omega, lever, fast=True, **kw)
    s2, P2 = covariance(state, P0, gyro, accel, dt, omega, lever, fast=False, **kw)
    assert P1.shape == P2.shape == (B,) + ((T,) if save_all else ()) + (15, 15)
    np.testing.assert_allclose(P1, P2, rtol=0, atol=1e-12 * np.abs(P2).max())
    assert_close(s1, s2)


def test_matrix_form_closed_forms_equal_its_autodiff_blocks():
    """The matrix form's blocks by autodiff (tangents ``R [e_j]x``, rows ``vee(R⁺ᵀ δR⁺)``)
    against its closed forms, both on the SoA kernels."""
    state, gyro, accel, dt = inputs(3, 17, seed=6)
    P0 = jnp.eye(15) * 1e-3
    kw = dict(attitude="matrix", scheme="midpoint", save_all=False, fast=True)
    s1, P1 = covariance(state, P0, gyro, accel, dt, None, None, jacobians="autodiff", **kw)
    s2, P2 = covariance(state, P0, gyro, accel, dt, None, None, jacobians="analytic", **kw)
    np.testing.assert_allclose(P1, P2, rtol=0, atol=1e-12 * np.abs(P2).max())
    assert_close(s1, s2)


def test_gradient_through_the_matrix_form_kernel_at_zero_rate():
    """d(final state)/d(gyro) through the SoA matrix-form kernel equals the generic one's,
    and is finite, at a zero rotation rate (the half angle's 0/0)."""
    state, _, accel, dt = inputs(2, 9, seed=7)
    gyro = jnp.zeros((2, 9, 3))

    def loss(w, fast):
        s = mean(
            state,
            w,
            accel,
            dt[:, :-1],
            None,
            attitude="matrix",
            scheme="midpoint",
            save_all=False,
            fast=fast,
        )
        return jnp.sum(jnp.sin(s.q)) + jnp.sum(jnp.sin(s.p)) + jnp.sum(jnp.sin(s.v))

    grad = jax.jit(jax.grad(loss), static_argnums=1)  # one program each
    g1 = grad(gyro, True)
    g2 = grad(gyro, False)
    assert np.all(np.isfinite(g1))
    np.testing.assert_allclose(g1, g2, rtol=0, atol=1e-11 * np.abs(g2).max())


def test_vmap_of_the_matrix_form_lands_on_the_batched_kernel():
    """``jax.vmap`` of the public call in the matrix form equals the element-wise generic
    kernel, and its program holds one engine call over the batch (no per-element kernel)."""
    state, gyro, accel, dt = inputs(4, 11, seed=8)
    h = dt[0]

    def fn(s, w, a):
        return jaximu.propagate_final(s, w, a, h, "rk4", attitude="matrix")

    got = jax.vmap(fn)(state, gyro, accel)
    want = jax.tree_util.tree_map(
        lambda *x: jnp.stack(x),
        *[
            mean(
                jax.tree_util.tree_map(lambda x: x[i : i + 1], state),
                gyro[i : i + 1],
                accel[i : i + 1],
                h,
                None,
                attitude="matrix",
                scheme="rk4",
                save_all=False,
                fast=False,
            )
            for i in range(4)
        ],
    )
    want = jax.tree_util.tree_map(lambda x: x[:, 0], want)
    assert_close(got, want)
    jaxpr = jax.make_jaxpr(jax.vmap(fn))(state, gyro, accel)
    eqns = [e for e in jaxpr.jaxpr.eqns if e.primitive.name == "jaximu_propagate"]
    assert len(eqns) == 1
    assert not [e for e in jaxpr.jaxpr.eqns if e.primitive.name in ("scan", "while")]
    assert (4, 11, 3) in {tuple(v.aval.shape) for v in eqns[0].invars}


@pytest.mark.parametrize(
    "scheme,save_all,rotating",
    [("euler", False, False), ("midpoint", True, True), ("rk4", True, False)],
)
def test_mean_in_euler_angles_equals_generic_and_reports_the_singularity(
    scheme, save_all, rotating
):
    """Euler angles on the SoA kernel: the generic kernel's states (the pitch singularity
    makes the lanes that approach it ill-conditioned, so values are compared on the others),
    the same NaN from the step that reaches ±90° and the same locked lanes; an eager call
    raises."""
    B, T = 40, 31
    state, gyro, accel, dt = inputs(B, T, seed=9)
    # five lanes start level and pitch up at 20 rad/s: they reach ±90° within the run
    gyro = gyro.at[:5, :, 1].set(20.0)
    state = state.replace(q=state.q.at[:5].set(jnp.asarray([1.0, 0.0, 0.0, 0.0])))
    if scheme != "euler":
        dt = dt[:, :-1]
    omega = 1e3 * EARTH if rotating else None
    kw = dict(attitude="euler_angles", scheme=scheme, save_all=save_all)
    runs = [
        jax.jit(lambda *a, fast=fast: _propagate(*a, G_W, omega, fast=fast, **kw))(
            state, gyro, accel, dt
        )
        for fast in (True, False)
    ]
    (fast, locked), (ref, locked_ref) = runs
    np.testing.assert_array_equal(locked, locked_ref)
    if not rotating:  # the singularity is reached (a step may also jump over it)
        assert np.sum(np.asarray(locked)[:5]) >= 3 and not np.any(np.asarray(locked)[5:])
    for a, b in zip(jax.tree_util.tree_leaves(fast), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        assert_close(a[5:], b[5:])
    with pytest.raises(ValueError, match="gimbal lock"):
        jaximu.propagate_final(
            jax.tree_util.tree_map(lambda x: x[:5], state),
            gyro[:5],
            accel[:5],
            dt[:5],
            scheme,
            attitude="euler_angles",
        )


@pytest.mark.parametrize(
    "scheme,save_all,extra",
    [("euler", False, "rotating"), ("midpoint", True, "lever"), ("rk4", False, None)],
)
def test_covariance_in_euler_angles_equals_generic_and_reports_the_singularity(
    scheme, save_all, extra
):
    """Euler angles' covariance on the SoA kernel (autodiff blocks from the angles' own
    tangents ``E(χ) e_j`` and rows ``W(χ⁺) δχ⁺``) against the generic kernel, which
    differentiates through ``quat_to_euler_zyx``: the same locked lanes, NaN in the same
    places of the states and covariances, the other lanes' values at 1e-12 (a quarter of
    the lanes turn past π a step, so roll and yaw leave (-π, π]); an eager call raises."""
    B, T = 8, 23
    state, gyro, accel, dt = inputs(B, T, seed=10, big_angles=True)
    # two lanes start level and pitch up at 40 rad/s: they reach ±90° within the run
    gyro = gyro.at[:2, :, 1].set(40.0)
    state = state.replace(q=state.q.at[:2].set(jnp.asarray([1.0, 0.0, 0.0, 0.0])))
    if scheme != "euler":
        dt = dt[:, :-1]
    rng = np.random.default_rng(11)
    A = rng.normal(size=(15, 15)) * 0.02
    P0 = jnp.asarray(A @ A.T + 1e-6 * np.eye(15))
    omega = 1e3 * EARTH if extra == "rotating" else None
    lever = jnp.asarray([0.3, -0.2, 0.15]) if extra == "lever" else None
    kw = dict(attitude="euler_angles", scheme=scheme, jacobians="autodiff", save_all=save_all)
    (s1, P1, l1), (s2, P2, l2) = [
        jax.jit(
            lambda *a, fast=fast: _propagate_covariance(
                *a, G_W, NOISE, omega, lever, fast=fast, **kw
            )
        )(state, P0, gyro, accel, dt)
        for fast in (True, False)
    ]
    np.testing.assert_array_equal(l1, l2)
    if extra != "rotating":
        assert np.all(np.asarray(l1)[:2]) and not np.any(np.asarray(l1)[2:])
        assert np.any(np.isnan(P1[:2])) and not np.any(np.isnan(P1[2:]))
    np.testing.assert_array_equal(np.isnan(P1), np.isnan(P2))
    np.testing.assert_allclose(P1[2:], P2[2:], rtol=0, atol=1e-12 * np.abs(P2[2:]).max())
    for a, b in zip(jax.tree_util.tree_leaves(s1), jax.tree_util.tree_leaves(s2)):
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b))
        assert_close(a[2:], b[2:])
    if scheme == "midpoint":  # the eager error (one scheme: each call compiles a kernel)
        with pytest.raises(ValueError, match="gimbal lock"):
            jaximu.propagate_covariance_final(
                jax.tree_util.tree_map(lambda x: x[:2], state),
                P0,
                gyro[:2],
                accel[:2],
                dt[:2],
                NOISE,
                scheme,
                attitude="euler_angles",
            )
