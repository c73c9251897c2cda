"""``ImuNoise``'s methods check what they are given: an integer ``dt`` computes in floats (it
turned the densities into integers), a bool ``dt`` and an integer dtype are refused, each
density is checked where it is used, and the checks let tracers through under ``jit``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaximu import ImuNoise

N = ImuNoise.euroc()


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
    np.testing.assert_allclose(
        N.discrete_variances(np.array([1, 2]))[:, 0],
        N.gyroscope_noise_density**2 / np.array([1, 2]),
        rtol=1e-6,
    )


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


@pytest.mark.parametrize(
    "bad,message",
    [
        (-1.0, r"noise\.gyroscope_noise_density must be non-negative"),
        (float("nan"), r"noise\.gyroscope_noise_density contains non-finite"),
        ("0.1", r"noise\.gyroscope_noise_density must be an array of numbers, got str"),
        (0.1 + 1j, r"noise\.gyroscope_noise_density must be real, got a complex"),
        (True, r"noise\.gyroscope_noise_density must be an array of numbers, got booleans"),
    ],
)
def test_densities_are_checked(bad, message):
    n = ImuNoise(bad, 1.0)
    for call in (
        lambda: n.sample_std(0.01),
        lambda: n.variances(),
        lambda: n.discrete_variances(0.01),
        lambda: n.discrete_covariance(0.01),
    ):
        with pytest.raises(ValueError, match=message):
            call()


def test_noise_methods_still_trace_under_jit():
    """Value checks only on concrete values: tracers (densities and dt) pass through."""
    f = jax.jit(lambda n, dt: n.discrete_variances(dt))
    out = f(N, jnp.float32(0.01))
    np.testing.assert_allclose(out[0], N.gyroscope_noise_density**2 / 0.01, rtol=1e-5)
