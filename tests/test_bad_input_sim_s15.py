"""Input contract of ImuNoise, the simulator and the Allan module (session 15 findings).

Bad input raises a ``ValueError`` naming the argument; nothing the user gave is altered
without a word (complex parts dropped, integer ``dt`` turning the densities into integers,
float16 computation, a ``taus`` list sorted). Errors come before any compilation.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaximu import ImuNoise, allan
from jaximu import simulate as sim
from jaximu.errors import InputError

N = ImuNoise.euroc()
KEY = jax.random.PRNGKey(0)
G = np.zeros((20, 3))
A = G + [0.0, 0.0, 9.81]
T20 = np.arange(20) * 0.01
TRAJ = sim.circle()


# --------------------------------------------------------------------------- ImuNoise (item 4)

def test_integer_dt_computes_in_floats():
    """An int dt cast the densities to int (all zeros); a bool one to 1."""
    want = N.sample_std(1.0)
    got = N.sample_std(1)
    for g, w in zip(got, want):
        assert jnp.issubdtype(g.dtype, jnp.floating)
        np.testing.assert_allclose(g, w, rtol=1e-6)
    np.testing.assert_allclose(N.gyroscope_noise_density, got[0][0], rtol=1e-6)
    Q = np.asarray(N.discrete_covariance(2))
    np.testing.assert_allclose(Q[0, 0], N.gyroscope_noise_density**2 / 2, rtol=1e-6)
    np.testing.assert_allclose(N.discrete_variances(np.array([1, 2]))[:, 0],
                               N.gyroscope_noise_density**2 / np.array([1, 2]), rtol=1e-6)


def test_bool_dt_and_integer_dtype_are_refused():
    with pytest.raises(ValueError, match=r"dt must be a time step in seconds, got a bool"):
        N.sample_std(True)
    with pytest.raises(ValueError, match=r"dt must be a time step .* bool"):
        N.discrete_variances(np.array([True, True]))
    with pytest.raises(ValueError, match=r"dtype must be a floating dtype .* got int32"):
        N.variances(jnp.int32)
    with pytest.raises(ValueError, match=r"dtype must be a floating dtype .* got int32"):
        N.sample_std(0.01, dtype=jnp.int32)
    with pytest.raises(ValueError, match=r"dtype must be a floating dtype .* got bool"):
        N.discrete_covariance(0.01, dtype=bool)
    with pytest.raises(ValueError, match=r"dt must be an array of numbers, got str"):
        N.sample_std("0.01")
    with pytest.raises(ValueError, match=r"dt must be real, got a complex"):
        N.sample_std(0.01 + 0j)


@pytest.mark.parametrize("bad,message", [
    (-1.0, r"noise\.gyroscope_noise_density must be non-negative"),
    (float("nan"), r"noise\.gyroscope_noise_density contains non-finite"),
    ("0.1", r"noise\.gyroscope_noise_density must be an array of numbers, got str"),
    (0.1 + 1j, r"noise\.gyroscope_noise_density must be real, got a complex"),
    (True, r"noise\.gyroscope_noise_density must be an array of numbers, got booleans"),
])
def test_densities_are_checked(bad, message):
    n = ImuNoise(bad, 1.0)
    for call in (lambda: n.sample_std(0.01), lambda: n.variances(),
                 lambda: n.discrete_variances(0.01), lambda: n.discrete_covariance(0.01)):
        with pytest.raises(ValueError, match=message):
            call()


def test_noise_methods_still_trace_under_jit():
    """Value checks only on concrete values: tracers (densities and dt) pass through."""
    f = jax.jit(lambda n, dt: n.discrete_variances(dt))
    out = f(N, jnp.float32(0.01))
    np.testing.assert_allclose(out[0], N.gyroscope_noise_density**2 / 0.01, rtol=1e-5)


# --------------------------------------------------------------------------- simulate

def test_half_precision_times_are_computed_in_float32():
    """Item 8: a float16 t gave float16 signals and states (the README promises float32)."""
    t = T20[:5].astype(np.float16)
    gyro, accel = sim.ideal_imu(TRAJ, t)
    assert gyro.dtype == accel.dtype == jnp.float32
    assert sim.true_states(TRAJ, t).p.dtype == jnp.float32


@pytest.mark.parametrize("call,message", [
    (lambda: sim.add_noise(KEY, G + 0j, A, 0.01, N), r"gyro must be real, got a complex"),
    (lambda: sim.add_noise(KEY, G, A + 1j, 0.01, N), r"accel must be real, got a complex"),
    (lambda: sim.add_noise(KEY, G, A, 0.01, N, b_g0=np.zeros(3) + 1j), r"b_g0 must be real"),
    (lambda: sim.add_noise(KEY, G, A, 0.01, N, accel_misalignment=np.eye(3) * 1j),
     r"accel_misalignment must be real"),
    (lambda: sim.ideal_imu(TRAJ, T20 + 0j), r"t must be real, got a complex"),
    (lambda: sim.true_states(TRAJ, T20 + 0j), r"t must be real, got a complex"),
    (lambda: sim.ideal_imu(TRAJ, T20, gravity=9.81 + 0j), r"gravity must be real"),
    (lambda: sim.helix(wobble=0.2j), r"wobble must be real"),
])
def test_complex_inputs_are_refused(call, message):
    """Item 6: the imaginary part was dropped with only a warning."""
    with pytest.raises(ValueError, match=message):
        call()


@pytest.mark.parametrize("call,message", [
    (lambda: sim.add_noise(KEY, G, A, 0.01, N, gyro_misalignment=np.full((3, 3), np.nan)),
     r"gyro_misalignment contains non-finite values"),
    (lambda: sim.add_noise(KEY, G, A, np.full(19, 0.01), N),
     r"dt must be a scalar or have shape \(T,\) = \(20,\) .* got \(19,\)"),
    (lambda: sim.add_noise(KEY, G[:0], A[:0], 0.01, N), r"hold no samples \(T = 0\)"),
    (lambda: sim.add_noise(KEY, G, A, 0.01, N, batch_shape=(-1,)),
     r"batch_shape must be a tuple of non-negative ints, got \(-1,\)"),
    (lambda: sim.add_noise(KEY, G, A, 0.01, N, batch_shape=(2.5,)),
     r"batch_shape must be a tuple of non-negative ints"),
    (lambda: sim.add_noise(KEY, G, A, 0.01, N, b_g0="0.1"), r"b_g0 must be an array of numbers"),
    (lambda: sim.add_noise(KEY, G, A, 0.01, N, gyro_misalignment=[["a"] * 3] * 3),
     r"gyro_misalignment must be an array of numbers"),
    (lambda: sim.add_noise(KEY, G.astype(str), A, 0.01, N), r"gyro must be an array of numbers"),
    (lambda: sim.add_noise(KEY, G, A, "0.01", N), r"dt must be an array of numbers"),
    (lambda: sim.add_noise(KEY, G, A, True, N),
     r"dt must be sample periods in seconds, got a bool"),
    (lambda: sim.ideal_imu(TRAJ, "0.1"), r"t must be an array of numbers, got str"),
    (lambda: sim.true_states(TRAJ, [0.0, "0.1"]), r"t must be an array of numbers"),
    (lambda: sim.circle(speed="2"), r"speed must be a number, got str"),
    (lambda: sim.circle(radius=True), r"radius must be a number, got bool"),
    (lambda: sim.lissajous(amplitude=(1.0, 2.0, "3")), r"amplitude must be numbers of shape"),
])
def test_simulate_names_the_bad_argument(call, message):
    """Items 10 and 11: NaN misalignment gave NaN samples; the rest raised JAX or numpy
    errors that named no argument."""
    with pytest.raises(ValueError, match=message):
        call()


def test_batch_shape_int_gets_the_fix():
    with pytest.raises(ValueError, match=r"batch_shape must be a tuple of ints, got the int 3; "
                                         r"pass batch_shape=\(3,\)"):
        sim.add_noise(KEY, G, A, 0.01, N, batch_shape=3)


# --------------------------------------------------------------------------- allan (item 12, 14)

Y = np.random.default_rng(0).normal(size=(400, 3))


@pytest.mark.parametrize("kwargs,message", [
    ({"y": Y + 1j}, r"y must be real, got a complex value"),
    ({"y": Y.astype(str)}, r"y must be an array of numbers"),
    ({"dt": "0.005"}, r"dt must be a real number of seconds, got str"),
    ({"dt": 0.005 + 0j}, r"dt must be a real number of seconds, got complex"),
    ({"taus": [0.1, 0.01]}, r"taus must be strictly increasing .* taus\[0\] = 0\.1 and "
                            r"taus\[1\] = 0\.01; pass np\.unique\(taus\)"),
    ({"taus": [0.1, 0.01, 0.1]}, r"taus must be strictly increasing"),
    ({"taus": [0.01, 0.01]}, r"taus must be strictly increasing"),
    ({"taus": ["0.1"]}, r"taus must be an array of numbers"),
    ({"points_per_decade": "10"}, r"points_per_decade must be a positive number"),
])
def test_allan_deviation_refuses_what_it_would_alter(kwargs, message):
    with pytest.raises(ValueError, match=message):
        allan.allan_deviation(**{"y": Y, "dt": 0.005, **kwargs})


def test_allan_deviation_returns_one_tau_per_given_tau_in_order():
    """The τ used come back one per given τ (rounded to whole samples, at least one); they
    used to be deduplicated, so the output no longer lined up with the list given."""
    taus, adev = allan.allan_deviation(Y, 0.005, taus=[0.001, 0.004, 0.02])
    np.testing.assert_allclose(taus, [0.005, 0.005, 0.02])
    assert adev.shape == (3, 3)
    np.testing.assert_array_equal(adev[0], adev[1])


def test_fit_noise_flags_densities_it_could_not_determine():
    """Item 14 (real data): a term the data did not show came back as a density of 0 that
    read as a measurement; it is now flagged not determined."""
    taus = np.logspace(-2, 1, 10)
    adev = np.stack([np.sqrt(1e-3**2 / taus), np.sqrt(1e-4**2 * taus / 3),
                     np.sqrt(1e-3**2 / taus + 1e-4**2 * taus / 3)], axis=1)
    fit = allan.fit_noise(taus, adev)
    np.testing.assert_array_equal(fit.white_determined, [True, False, True])
    np.testing.assert_array_equal(fit.random_walk_determined, [False, True, True])
    assert "not determined" in allan.NoiseFit.__doc__
    one = allan.fit_noise(taus, adev[:, 0])
    assert one.white_determined and not one.random_walk_determined


def test_check_units_judges_only_determined_axes():
    """Axes whose white density is not determined (0) no longer pull the median down: a deg/s
    gyro with one undetermined axis was passed."""
    taus = np.logspace(-2, 1, 10)
    loud = np.sqrt(1e-2**2 / taus)  # 1e-2 rad/s/√Hz: a gyro in deg/s
    walk_only = np.sqrt(1e-4**2 * taus / 3)
    fit = allan.fit_noise(taus, np.stack([loud, walk_only, walk_only], axis=1))
    with pytest.raises(InputError, match=r"gyro white-noise density 0\.01 rad/s/√Hz"):
        allan.check_units(fit)
    allan.check_units(allan.fit_noise(taus, np.stack([walk_only] * 3, axis=1)))  # nothing to judge
