"""``lane_math._quat_renormalize`` (``q (3 - |q|²)/2``, the kernels' normalisation after a unit
increment) against numpy's division by the norm, and the engines from a start quaternion
off unit against the same start normalised."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _shared import random_inputs
from scipy.spatial.transform import Rotation

import jaximu
from jaximu.geometry.so3 import quat_mul_components
from jaximu.kernels import lane_math


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_renormalize_after_unit_increments_is_the_division(dtype):
    """A unit quaternion times a unit increment (both from scipy, rounded to ``dtype``):
    the renormalised product equals numpy's ``q / |q|`` (float64) to two units of
    ``dtype``'s rounding; and 500 such steps in a row keep ``|q|`` within 4 units of 1
    (unnormalised, rounding walks away by ~√500 units) and the product within 500 units
    of the float64 chain's."""
    n = 256
    eps = np.finfo(dtype).eps
    q = Rotation.random(n, random_state=1).as_quat(scalar_first=True)
    ref = q.copy()
    qs = tuple(jnp.asarray(q[:, i], dtype) for i in range(4))
    renorm = jax.jit(lambda a, b: lane_math._quat_renormalize(quat_mul_components(a, b)))
    for k in range(500):
        d = Rotation.random(n, random_state=10 + k).as_quat(scalar_first=True)
        ds = tuple(jnp.asarray(d[:, i], dtype) for i in range(4))
        if k == 0:  # one step against the division of the same (rounded) product
            p64 = np.stack([np.asarray(x, np.float64) for x in quat_mul_components(qs, ds)], -1)
            np.testing.assert_allclose(
                np.stack([np.asarray(x) for x in renorm(qs, ds)], -1),
                p64 / np.linalg.norm(p64, axis=-1, keepdims=True),
                rtol=0,
                atol=2 * eps,
            )
        qs = renorm(qs, ds)
        r = np.stack(quat_mul_components(tuple(ref.T), tuple(d.T)), -1)
        ref = r / np.linalg.norm(r, axis=-1, keepdims=True)
    got = np.stack([np.asarray(x, np.float64) for x in qs], -1)
    np.testing.assert_allclose(np.linalg.norm(got, axis=-1), 1.0, rtol=0, atol=4 * eps)
    np.testing.assert_allclose(got, ref, rtol=0, atol=500 * eps)


def test_renormalize_off_unit_keeps_the_direction():
    """``|q|² = 1 + ε`` with ``ε`` up to 2e-6 (further from unit than any product of unit
    quaternions): the direction is the division's to rounding and ``|q|`` within
    ``3ε²/8`` of 1, the error of the series ``1 - ε/2``; a second renormalisation brings it
    to rounding."""
    rng = np.random.default_rng(3)
    u = rng.normal(size=(1000, 4))
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    scale = 1.0 + rng.uniform(-1e-6, 1e-6, size=(1000, 1))
    q = u * scale
    once = np.stack(lane_math._quat_renormalize(tuple(jnp.asarray(q[:, i]) for i in range(4))), -1)
    norm = np.linalg.norm(once, axis=-1)
    eps2 = (scale[:, 0] ** 2 - 1.0) ** 2
    assert np.all(np.abs(norm - 1.0) <= 0.375 * eps2 * (1 + 1e-3) + 4e-16)
    assert np.abs(norm - 1.0).max() > 0.1 * 0.375 * eps2.max()  # the bound is the error's
    np.testing.assert_allclose(once / norm[:, None], u, rtol=0, atol=4e-16)
    twice = np.stack(
        lane_math._quat_renormalize(tuple(jnp.asarray(once[:, i]) for i in range(4))), -1
    )
    np.testing.assert_allclose(np.linalg.norm(twice, axis=-1), 1.0, rtol=0, atol=4e-16)


@pytest.mark.parametrize("norm", [1 + 1e-6, 1.01, 2.5])
def test_a_start_off_unit_propagates_as_its_rotation(norm):
    """float64, every scheme, under ``jit`` (no value check): a batch whose start
    quaternions are scaled off unit (by 1e-6, the eager check's tolerance, and by 1.01 and
    2.5, which only ``jit`` lets through) propagates, on the fast kernels and on the
    generic scan, as the same batch with the unit quaternions would: every state to 1e-12
    of its scale (the engines start from ``q / |q|``; the kernels' renormalisation after a
    step assumes a unit start, and from ``|q| = 2.5`` it would diverge)."""
    from jaximu.engine.propagate import _propagate

    state, gyro, accel = random_inputs(4, 200, seed=5)
    scaled = jaximu.NavState(
        state.q * jnp.asarray([norm, 1.0, norm, 1 / norm])[:, None],
        state.p,
        state.v,
        state.b_g,
        state.b_a,
    )
    dt = jnp.full((200,), 0.005)
    g = jnp.asarray([0.0, 0.0, -9.81])
    for scheme in ("euler", "midpoint", "rk4"):
        ref = _propagate(
            state,
            gyro,
            accel,
            dt,
            g,
            scheme=scheme,
            attitude="quaternion",
            save_all=True,
            fast=False,
        )[0]
        for fast in (True, False):
            got = _propagate(
                scaled,
                gyro,
                accel,
                dt,
                g,
                scheme=scheme,
                attitude="quaternion",
                save_all=True,
                fast=fast,
            )[0]
            for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(ref)):
                np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * max(1.0, np.abs(b).max()))
