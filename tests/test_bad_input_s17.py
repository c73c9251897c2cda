"""Bad input on the less-trodden entries (probe s17): each case raised JAX's or numpy's own
error deep in the stack (naming no argument), altered the user's data silently, or returned
a wrong result, before its fix. Tiny shapes: the suite is compile-bound."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu.errorstate import position_jacobian


def state(batch=(), dtype=jnp.float64):
    z = jnp.zeros(batch + (3,), dtype)
    return jaximu.NavState(jnp.broadcast_to(jnp.asarray([1.0, 0, 0, 0], dtype), batch + (4,)),
                           z, z, z, z)


# --------------------------------------------------------------------------- error state


@pytest.mark.parametrize("kw, named", [
    (dict(gyro=jnp.zeros((3, 3))), r"state \(2,\), gyro \(3,\)"),
    (dict(dt=jnp.full(3, 0.01)), r"dt \(3,\)"),
    (dict(gyro_next=jnp.zeros((3, 3)), scheme="midpoint"), r"gyro_next \(3,\)"),
    (dict(gravity=jnp.zeros((3, 3))), r"gravity \(3,\)"),
])
def test_step_jacobians_names_the_batch_that_does_not_fit(kw, named):
    args = dict(gyro=jnp.zeros((2, 3)), accel=jnp.zeros((2, 3)), dt=0.01) | kw
    with pytest.raises(ValueError, match=r"do not broadcast: .*" + named):
        jaximu.step_jacobians(state((2,)), **args)


def test_discrete_process_noise_names_the_batch_that_does_not_fit():
    G = jnp.zeros((3, 15, 12))
    with pytest.raises(ValueError, match=r"do not broadcast: G \(3,\), dt \(2,\)"):
        jaximu.discrete_process_noise(G, jaximu.ImuNoise.euroc(), jnp.full(2, 0.01))
    noise = jaximu.ImuNoise(jnp.full((2, 3), 1e-3), 1e-2, 1e-5, 1e-4)
    with pytest.raises(ValueError, match=r"G \(3,\), dt \(\), "
                                         r"noise\.gyroscope_noise_density \(2,\)"):
        jaximu.discrete_process_noise(G, noise, 0.01)


def test_discrete_process_noise_keeps_a_float64_dt():
    """A float64 ``dt`` beside a float32 ``G`` was rounded to float32 (only ``G`` counted)."""
    G = jnp.zeros((15, 12), jnp.float32)
    assert jaximu.discrete_process_noise(G, jaximu.ImuNoise.euroc(),
                                         np.float64(0.001)).dtype == jnp.float64
    assert jaximu.discrete_process_noise(G, jaximu.ImuNoise.euroc(), 0.001).dtype == jnp.float32


def test_ekf_update_does_not_round_a_float64_state_field_to_float32():
    """Only ``state.q`` decided the dtype: a float64 position beside float32 ``q`` and
    covariances came back float32, its 1e-9 m gone."""
    s32 = state(dtype=jnp.float32)
    s = s32.replace(p=jnp.asarray([1.0, 2.0, 3.0]) + 1e-9)
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    out, _, _ = jaximu.ekf_update(s, f32(1e-2 * np.eye(15)), jnp.zeros(3, jnp.float32),
                                  position_jacobian(jnp.float32), f32(1e-2 * np.eye(3)))
    assert out.p.dtype == jnp.float64
    np.testing.assert_array_equal(np.asarray(out.p), np.asarray(s.p))  # a zero residual


def test_correct_names_the_batches_that_do_not_broadcast():
    gyro = jnp.zeros((2, 4, 3))
    pim = jaximu.preintegrate(gyro, gyro.at[..., 2].set(9.81), 0.01)
    with pytest.raises(ValueError, match=r"bias\.b_g \(3,\), bias\.b_a \(\), pim \(2,\)"):
        jaximu.correct(pim, jaximu.ImuBias(jnp.zeros((3, 3)), jnp.zeros(3)))


# --------------------------------------------------------------------------- Monte Carlo

MC = dict(n_runs=2, n_keep=0, chunk_size=2)


def mc_study(**kw):
    import jax

    from jaximu import montecarlo, simulate
    args = dict(trajectory=simulate.circle(), times=np.arange(5) * 0.01,
                P0=1e-6 * np.eye(15), noise=jaximu.ImuNoise.euroc(), key=jax.random.key(0))
    return montecarlo.monte_carlo(**(args | MC | kw))


def test_monte_carlo_names_a_batched_density_before_the_work():
    """A (2, 3) density reached numpy's IndexError after the reference propagation."""
    noise = jaximu.ImuNoise(1.6e-4, np.full((2, 3), 2.8e-3), 2.2e-5, 8.6e-4)
    with pytest.raises(ValueError, match=r"noise\.accelerometer_noise_density must be a scalar "
                                         r"or \(3,\) for a Monte Carlo study.*\(2, 3\)"):
        mc_study(noise=noise)


def test_monte_carlo_with_a_singular_predicted_covariance_names_p0():
    """P0 = 0 is positive semi-definite (accepted) but its first predicted covariance is
    singular: numpy's bare LinAlgError "Matrix is not positive definite" came out."""
    with pytest.raises(ValueError, match=r"covariance at times\[1\] = 0\.01 is singular.*"
                                         r"give P0 positive variances"):
        mc_study(P0=np.zeros((15, 15)))


def test_host_side_inputs_under_jit_name_the_argument():
    """monte_carlo under jit: "P0 must be an array of numbers, got DynamicJaxprTracer"."""
    import jax
    with pytest.raises(ValueError, match=r"P0 must be concrete numbers, got a traced value.*"
                                         r"outside jax\.jit"):
        jax.jit(lambda P: mc_study(P0=P).nees_mean)(jnp.eye(15) * 1e-6)
