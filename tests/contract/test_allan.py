"""The input contract of ``jaximu.allan``: ``allan_deviation`` refuses what it would alter
(complex, text, unsorted ``taus``) and returns one τ per τ given, in order; ``fit_noise``
refuses NaN and flags the densities the data do not determine; ``check_units`` judges only
determined axes; a traced input is named.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaximu import allan
from jaximu.errors import InputError

Y = np.random.default_rng(0).normal(size=(400, 3))


def test_fit_noise_refuses_nan_silently(capfd):
    taus = np.logspace(-2, 1, 10)
    with pytest.raises(ValueError, match=r"adev contains non-finite"):
        allan.fit_noise(taus, np.full(10, np.nan))
    with pytest.raises(ValueError, match=r"taus must be positive and finite"):
        allan.fit_noise(-taus, np.ones(10))
    with pytest.raises(ValueError, match=r"taus and adev have different lengths"):
        allan.fit_noise(taus, np.ones(9))
    with pytest.raises(ValueError, match=r"adev must be positive"):
        allan.fit_noise(taus, np.zeros(10))
    assert capfd.readouterr().out == ""  # LAPACK printed to stdout
    fit = allan.fit_noise(taus, np.sqrt(0.01**2 / taus))  # pure white noise
    np.testing.assert_allclose(fit.white, 0.01, rtol=1e-6)


def test_allan_names_a_traced_input_and_a_wrong_fit():
    """allan_deviation under jit raised JAX's TracerArrayConversionError; check_units(None)
    an AttributeError."""

    from jaximu import allan

    with pytest.raises(ValueError, match=r"y must be concrete numbers, got a traced value"):
        jax.jit(lambda y: allan.allan_deviation(y, 0.01)[1])(jnp.zeros((20, 3)))
    with pytest.raises(ValueError, match=r"gyro must be the NoiseFit of the gyro"):
        allan.check_units(None)


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"y": Y + 1j}, r"y must be real, got a complex value"),
        ({"y": Y.astype(str)}, r"y must be an array of numbers"),
        ({"dt": "0.005"}, r"dt must be a real number of seconds, got str"),
        ({"dt": 0.005 + 0j}, r"dt must be a real number of seconds, got complex"),
        (
            {"taus": [0.1, 0.01]},
            r"taus must be strictly increasing .* taus\[0\] = 0\.1 and "
            r"taus\[1\] = 0\.01; pass np\.unique\(taus\)",
        ),
        ({"taus": [0.1, 0.01, 0.1]}, r"taus must be strictly increasing"),
        ({"taus": [0.01, 0.01]}, r"taus must be strictly increasing"),
        ({"taus": ["0.1"]}, r"taus must be an array of numbers"),
        ({"points_per_decade": "10"}, r"points_per_decade must be a positive number"),
        (
            {"taus": [0.01, 10.0]},
            r"taus\[1\] = 10 s, and the .* samples of 0\.005 s hold clusters of at most "
            r"[0-9.]+ s; pass taus up to",
        ),
    ],
)
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
    """A term the data do not show (as in real recordings) is flagged not determined, not
    returned as a density of 0 that reads as a measurement."""
    taus = np.logspace(-2, 1, 10)
    adev = np.stack(
        [
            np.sqrt(1e-3**2 / taus),
            np.sqrt(1e-4**2 * taus / 3),
            np.sqrt(1e-3**2 / taus + 1e-4**2 * taus / 3),
        ],
        axis=1,
    )
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


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: allan.motion_ratio(np.array([0.0, np.nan, 1.0]), 0.01), r"y contains non-finite"),
        (lambda: allan.motion_ratio(Y, 0.0), r"dt must be positive and finite"),
        (lambda: allan.motion_ratio(Y, 0.01, window=-1.0), r"window must be positive and finite"),
        (lambda: allan.motion_ratio(Y + 1j, 0.01), r"y must be real, got a complex value"),
        (lambda: allan.motion_ratio(np.zeros((4, 3, 2)), 0.01), r"y must have shape \(N,\) or"),
        (
            lambda: allan.static_intervals(Y, 0.01, segment=1.5),
            r"segment = 1.5 s must hold at least two windows of 1 s .*pass segment ≥ 2",
        ),
        (lambda: allan.static_intervals(Y, 0.01, segment=0.0), r"segment must be positive"),
    ],
)
def test_motion_detection_names_bad_input(call, message):
    with pytest.raises(ValueError, match=message):
        call()
