"""The input contract of the error-state functions: ``propagate_covariance(_final)``'s ``P0``
(judged relative to its own scale), ``step_jacobians`` and ``discrete_process_noise``
(batches, ``dt``, ``G``), ``ekf_update`` (every argument, against numpy's textbook Kalman
update) and ``position_jacobian``. Every expectation is independent of the code under
test: the argument's name in the message, numpy's update, the closed form of ``Q``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu import ImuNoise, NavState
from jaximu.errorstate import position_jacobian

S64 = NavState.identity((), jnp.float64)
W1 = np.zeros((1, 3))
A1 = np.array([[0.0, 0.0, 9.81]])


def cov_final(P0, dtype=np.float64):
    s = NavState.identity((), dtype)
    return jaximu.propagate_covariance_final(
        s, P0, W1.astype(dtype), A1.astype(dtype), 0.01, ImuNoise.euroc()
    )


# --------------------------------------------------------------------------- P0


def test_p0_symmetry_is_judged_relative_to_its_scale():
    P0 = np.eye(15) * 1e-6
    P0[0, 1] = 1e-7  # one-sided: 10% of the matrix's scale
    with pytest.raises(ValueError, match="P0 is not symmetric"):
        cov_final(P0)


def test_p0_definiteness_is_judged_relative_to_its_scale():
    P0 = np.eye(15) * 1e-6
    P0[4, 4] = -1e-10  # a negative variance, 1e-4 of the scale
    with pytest.raises(ValueError, match="P0 is not positive semi-definite"):
        cov_final(P0)


def test_p0_from_rounding_at_any_scale_is_accepted():
    """A covariance ``A Aᵀ`` computed in the dtype (rounding-level asymmetry, a singular
    direction) is valid at 1e-12 and at 1e6; the output variances are non-negative."""
    rng = np.random.default_rng(1)
    A = rng.normal(size=(15, 14))
    for scale in (1e-12, 1e6):
        for dtype in (np.float64, np.float32):
            Ad = (A * np.sqrt(scale)).astype(dtype)
            P0 = Ad @ Ad.T
            _, P = cov_final(P0, dtype)
            assert np.all(np.diag(np.asarray(P, np.float64)) >= 0)


# ----------------------------------------------------------- step_jacobians, discrete_process_noise


def state(batch=(), dtype=jnp.float64):
    z = jnp.zeros(batch + (3,), dtype)
    return jaximu.NavState(
        jnp.broadcast_to(jnp.asarray([1.0, 0, 0, 0], dtype), batch + (4,)), z, z, z, z
    )


@pytest.mark.parametrize(
    "kw, named",
    [
        (dict(gyro=jnp.zeros((3, 3))), r"state \(2,\), gyro \(3,\)"),
        (dict(dt=jnp.full(3, 0.01)), r"dt \(3,\)"),
        (dict(gyro_next=jnp.zeros((3, 3)), scheme="midpoint"), r"gyro_next \(3,\)"),
        (dict(gravity=jnp.zeros((3, 3))), r"gravity \(3,\)"),
    ],
)
def test_step_jacobians_names_the_batch_that_does_not_fit(kw, named):
    args = dict(gyro=jnp.zeros((2, 3)), accel=jnp.zeros((2, 3)), dt=0.01) | kw
    with pytest.raises(ValueError, match=r"do not broadcast: .*" + named):
        jaximu.step_jacobians(state((2,)), **args)


def test_discrete_process_noise_names_the_batch_that_does_not_fit():
    G = jnp.zeros((3, 15, 12))
    with pytest.raises(ValueError, match=r"do not broadcast: G \(3,\), dt \(2,\)"):
        jaximu.discrete_process_noise(G, jaximu.ImuNoise.euroc(), jnp.full(2, 0.01))
    noise = jaximu.ImuNoise(jnp.full((2, 3), 1e-3), 1e-2, 1e-5, 1e-4)
    with pytest.raises(
        ValueError,
        match=r"G \(3,\), dt \(\), "
        r"noise\.gyroscope_noise_density \(2,\)",
    ):
        jaximu.discrete_process_noise(G, noise, 0.01)


def test_discrete_process_noise_keeps_a_float64_dt():
    """A float64 ``dt`` beside a float32 ``G`` was rounded to float32 (only ``G`` counted)."""
    G = jnp.zeros((15, 12), jnp.float32)
    assert (
        jaximu.discrete_process_noise(G, jaximu.ImuNoise.euroc(), np.float64(0.001)).dtype
        == jnp.float64
    )
    assert jaximu.discrete_process_noise(G, jaximu.ImuNoise.euroc(), 0.001).dtype == jnp.float32


def test_discrete_process_noise_checks_dt():
    G = np.zeros((15, 12))
    G[np.arange(12) + 3, np.arange(12)] = 1.0
    for dt in (0.0, -0.01, np.nan):
        with pytest.raises(ValueError, match=r"dt must be positive and finite"):
            jaximu.discrete_process_noise(G, ImuNoise.euroc(), dt)
    for bad, message in (
        (G.T, r"G must have shape \(\.\.\., 15, 12\) .*got \(12, 15\)"),
        (G[:12], r"G must have shape \(\.\.\., 15, 12\)"),
        (np.zeros(12), r"G must have shape \(\.\.\., 15, 12\)"),
        (np.where(G > 0, np.nan, 0.0), r"G contains non-finite"),
    ):
        with pytest.raises(ValueError, match=message):
            jaximu.discrete_process_noise(bad, ImuNoise.euroc(), 0.01)
    with pytest.raises(ValueError, match=r"noise must be a jaximu\.ImuNoise, got tuple"):
        jaximu.discrete_process_noise(G, (1e-3, 1e-2, 1e-5, 1e-4), 0.01)
    n = ImuNoise.euroc()
    Q = np.asarray(jaximu.discrete_process_noise(G, n, 0.01))
    want = (
        np.r_[
            [n.gyroscope_noise_density**2] * 3,
            [n.accelerometer_noise_density**2] * 3,
            [n.gyroscope_random_walk**2] * 3,
            [n.accelerometer_random_walk**2] * 3,
        ]
        / 0.01
    )
    np.testing.assert_allclose(np.diag(Q)[3:], want, rtol=1e-6)


# --------------------------------------------------------------------------- ekf_update


X0 = NavState(jnp.array([1.0, 0, 0, 0]), jnp.zeros(3), jnp.zeros(3), jnp.zeros(3), jnp.zeros(3))
P15 = np.diag(np.r_[[1e-4] * 3, [0.04] * 3, [1e-2] * 3, [1e-6] * 3, [1e-4] * 3])
H3 = np.asarray(position_jacobian())
R3 = np.eye(3) * 0.01
NU = np.array([0.1, -0.2, 0.05])


def _ekf(**kw):
    args = dict(state=X0, P=P15, residual=NU, H=H3, R=R3)
    args.update(kw)
    return jaximu.ekf_update(**args)


def _with(a, idx, v):
    a = np.array(a, float)
    a[idx] = v
    return a


@pytest.mark.parametrize(
    "kw, name",
    [
        (dict(R=-R3), r"\bR\b.*not positive semi-definite"),
        (dict(R=_with(R3, (0, 1), 0.005)), r"\bR\b is not symmetric"),
        (dict(R=0 * R3, P=0 * P15), r"innovation covariance S = H P Hᵀ \+ R is singular"),
        (dict(residual=_with(NU, 1, np.nan)), r"residual contains non-finite"),
        (dict(P=_with(P15, (0, 0), np.inf)), r"\bP contains non-finite"),
        (dict(P=_with(P15, (0, 3), 1e-3)), r"\bP is not symmetric"),
        (dict(P=-P15), r"\bP is not positive semi-definite"),
        (dict(H=_with(H3, (0, 3), np.nan)), r"\bH contains non-finite"),
        (dict(state=X0.replace(q=jnp.array([1.1, 0, 0, 0]))), r"state\.q is not a unit quaternion"),
        (
            dict(P=np.broadcast_to(P15, (4, 15, 15)), residual=np.zeros((3, 3))),
            r"do not broadcast: .*P \(4,\), residual \(3,\)",
        ),
        (dict(P="eye"), r"\bP must be an array of numbers"),
        (dict(R=None), r"\bR must be an array of numbers"),
        (dict(H=np.zeros((0, 15)), residual=np.zeros(0), R=np.zeros((0, 0))), r"H has no rows"),
    ],
)
def test_ekf_update_refuses_values_outside_its_domain_naming_the_argument(kw, name):
    # before: NaN out (R, residual, P, H non-finite or singular S), a silent update with a
    # non-PSD or one-sided P, JAX's unnamed broadcasting error, or a TypeError for text
    with pytest.raises(ValueError, match=name):
        _ekf(**kw)


EKF = jax.jit(jaximu.ekf_update)  # one compile per dtype (op by op eagerly: many small ones)


def test_ekf_update_still_computes_the_textbook_update_in_float32_for_half_inputs():
    """The checks change nothing of a valid update (eager: all value checks run): numpy's
    Kalman update (gain by a plain inverse). Inside the caller's jit, where the value checks
    cannot run, it traces, and float16 inputs are computed in float32 (as everywhere)."""
    x, P, nis = _ekf(P=P15.astype(np.float16).astype(np.float64))
    P16 = P15.astype(np.float16).astype(np.float64)
    S = H3 @ P16 @ H3.T + R3
    K = P16 @ H3.T @ np.linalg.inv(S)
    A = np.eye(15) - K @ H3
    scale = np.abs(P16).max()
    np.testing.assert_allclose(
        np.asarray(P), A @ P16 @ A.T + K @ R3 @ K.T, atol=1e-6 * scale, rtol=1e-5
    )
    np.testing.assert_allclose(float(nis), NU @ np.linalg.solve(S, NU), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(x.p), K[3:6] @ NU, rtol=1e-5, atol=1e-9)
    half = dict(
        state=jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float16), X0),
        **{k: np.asarray(v, np.float16) for k, v in dict(P=P15, residual=NU, H=H3, R=R3).items()},
    )
    x_h, P_h, nis_h = EKF(**half)
    assert P_h.dtype == x_h.p.dtype == nis_h.dtype == jnp.float32


@pytest.mark.parametrize("dtype", ["banana", np.int32, np.float16])
def test_position_jacobian_refuses_a_dtype_that_is_not_float32_or_float64(dtype):
    with pytest.raises(ValueError, match=r"dtype must be a floating dtype"):
        position_jacobian(dtype)


def test_ekf_update_does_not_round_a_float64_state_field_to_float32():
    """Only ``state.q`` decided the dtype: a float64 position beside float32 ``q`` and
    covariances came back float32, its 1e-9 m gone."""
    s32 = state(dtype=jnp.float32)
    s = s32.replace(p=jnp.asarray([1.0, 2.0, 3.0]) + 1e-9)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    out, _, _ = jaximu.ekf_update(
        s,
        f32(1e-2 * np.eye(15)),
        jnp.zeros(3, jnp.float32),
        position_jacobian(jnp.float32),
        f32(1e-2 * np.eye(3)),
    )
    assert out.p.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(out.p), np.asarray(s.p))  # a zero residual
