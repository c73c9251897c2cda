"""The input contract of ``jaximu.calibration``: ``calibration_problem``, ``calibrate``,
``calibration_loss`` / ``calibration_residuals`` and ``ImuCalibration.default`` name every
argument outside its domain (the initial calibration's included) before any work.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu import ImuNoise
from jaximu import calibration as cal


def a_reference(n=401, rate=200.0):
    t = np.arange(n) / rate
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    return t, cal.Reference(t, q, np.zeros((n, 3)), np.zeros((n, 3)))


@pytest.mark.parametrize(
    "value,message",
    [
        (-0.5, r"keyframe_interval must be positive and finite, got -0\.5"),
        (np.nan, r"keyframe_interval must be positive and finite, got nan"),
        (0.001, r"keyframe_interval = 0\.001 s is shorter than one sample interval \(0\.005 s\)"),
    ],
)
def test_keyframe_interval_domain(value, message):
    t, ref = a_reference()
    gyro = np.zeros((len(t), 3))
    accel = np.tile([0, 0, 9.81], (len(t), 1))
    with pytest.raises(ValueError, match=message):
        cal.calibration_problem(t, gyro, accel, ref, ImuNoise.euroc(), keyframe_interval=value)


@pytest.fixture(scope="module")
def cal_inputs():
    from jaximu import calibration as cal
    from jaximu import simulate as sim

    traj, t = sim.circle(), np.arange(60) * 0.01
    gyro, accel = sim.ideal_imu(traj, t)
    s = sim.true_states(traj, t)
    ref = cal.Reference(t, np.asarray(s.q), np.asarray(s.p), np.asarray(s.v))
    return t, gyro, accel, ref


def test_calibrate_refuses_estimate_given_as_a_string():
    """tuple("b_g") is ('b', '_', 'g'): "unknown calibration fields ['b', '_', 'g']"; None
    gave Python's "'NoneType' object is not iterable"."""
    from jaximu import calibration as cal

    with pytest.raises(
        ValueError,
        match=r"estimate must be a tuple of field names, got the "
        r"string 'b_g,b_a'; pass estimate=\('b_g', 'b_a'\)",
    ):
        cal.calibrate(cal.CalibrationProblem(*[None] * 13), estimate="b_g,b_a")
    with pytest.raises(ValueError, match=r"estimate must be a tuple of field names .*NoneType"):
        cal.calibrate(None, estimate=None)
    with pytest.raises(ValueError, match=r"estimate names no field, got \(\); pass at least"):
        cal.calibrate(None, estimate=())
    # a field named twice would be estimated once: refused, naming the repair
    with pytest.raises(
        ValueError,
        match=r"estimate names 'b_g' more than once, got \('b_g', 'b_a', 'b_g'\); name each "
        r"field once: estimate=\('b_g', 'b_a'\)",
    ):
        cal.calibrate(None, estimate=("b_g", "b_a", "b_g"))


def test_calibration_loss_names_its_arguments(cal_inputs):
    """AttributeError "'NoneType' object has no attribute 'velocities'"."""
    from jaximu import calibration as cal

    t, gyro, accel, ref = cal_inputs
    problem = cal.calibration_problem(
        t, gyro, accel, ref, jaximu.ImuNoise.euroc(), keyframe_interval=0.2, check=False
    )
    with pytest.raises(ValueError, match=r"problem must be a CalibrationProblem"):
        cal.calibration_loss(None, cal.ImuCalibration.default())
    with pytest.raises(ValueError, match=r"calib must be an ImuCalibration"):
        cal.calibration_residuals(problem, None)
    with pytest.raises(
        ValueError,
        match=r"velocities must have the shape \(3, 3\) of "
        r"problem\.velocities",
    ):
        cal.calibration_loss(problem, cal.ImuCalibration.default(), jnp.zeros((2, 3)))


def test_imu_calibration_default_names_its_arguments():
    from jaximu import calibration as cal

    with pytest.raises(ValueError, match=r"dtype must be a floating dtype .*'foo'"):
        cal.ImuCalibration.default(dtype="foo")
    with pytest.raises(ValueError, match=r"gravity must be an array of numbers, got str"):
        cal.ImuCalibration.default(gravity="9.81")
    with pytest.raises(ValueError, match=r"b_g must be an array of numbers, got str"):
        cal.ImuCalibration.default(b_g="abc")


@pytest.mark.parametrize(
    "change, message",
    [
        (
            dict(extrinsics="no"),
            r"extrinsics must be True or False, got the string 'no'; "
            r"pass extrinsics=False",
        ),
        (dict(check="no"), r"check must be True or False"),
        (dict(omega_coriolis=np.zeros((2, 3))), r"omega_coriolis must be one \(3,\) world rate"),
        (
            dict(noise=jaximu.ImuNoise(np.full((2, 3), 1e-3), 1e-2)),
            r"noise\.gyroscope_noise_density must be a scalar or \(3,\) for a calibration problem",
        ),
        (
            dict(noise=jaximu.ImuNoise(0.0, 0.0), reference_sigma=(0, 0, 0)),
            r"the residuals' covariance is singular.*give noise positive densities",
        ),
        (dict(t="abc"), r"t must be an array of numbers, got str"),
        (dict(reference_t="abc"), r"reference\.t must be an array of numbers, got str"),
        (dict(reference_t=np.nan), r"reference\.t contains non-finite values .* \[5\]"),
    ],
)
def test_calibration_problem_names_what_it_took_silently_or_raised_deep(
    cal_inputs, change, message
):
    """extrinsics="no" and check="no" counted as True; a (2, 3) world rate was kept; a batched
    density and text reached JAX's/numpy's own errors; zero densities numpy's LinAlgError; a
    NaN reference time passed the order test."""
    from jaximu import calibration as cal

    t, gyro, accel, ref = cal_inputs
    kw = dict(noise=jaximu.ImuNoise.euroc(), keyframe_interval=0.2, check=False) | change
    rt = kw.pop("reference_t", ref.t)
    if isinstance(rt, float):
        rt = np.where(np.arange(len(ref.t)) == 5, rt, ref.t)
    ref = cal.Reference(rt, ref.q, ref.p, ref.v)
    with pytest.raises(ValueError, match=message):
        cal.calibration_problem(kw.pop("t", t), gyro, accel, ref, **kw)


@pytest.mark.parametrize(
    "field,value,message",
    [
        ("q_BS", [1.0, 0.1, 0.0, 0.0], r"initial\.q_BS must be a unit quaternion"),
        ("b_g", [0.0, np.nan, 0.0], r"initial\.b_g"),
        ("gravity", -9.81, r"initial\.gravity is a magnitude"),
        ("p_BS", [[0.0, 0.0, 0.1]] * 2, r"initial\.p_BS must have shape \(3,\)"),
    ],
)
@pytest.mark.parametrize("entry", ["calibration_problem", "calibrate"])
def test_calibration_initial_outside_its_domain_is_named_before_any_work(
    entry, field, value, message
):
    """A non-unit q_BS (the fit would start from a scaled rotation), NaN, a negative gravity
    magnitude or a batched field are refused naming initial.<field>, before anything
    compiles (calibrate is given a placeholder problem: the check comes first)."""
    from jaximu import calibration as cal

    bad = cal.ImuCalibration.default(**{field: value})
    with pytest.raises(ValueError, match=message):
        if entry == "calibration_problem":
            t = np.arange(10) * 0.01
            ref = cal.Reference(t, np.tile([1.0, 0, 0, 0], (10, 1)), np.zeros((10, 3)))
            cal.calibration_problem(
                t, np.zeros((10, 3)), np.zeros((10, 3)), ref, ImuNoise.euroc(), initial=bad
            )
        else:
            cal.calibrate(_placeholder_problem(), bad)


def _placeholder_problem():
    from jaximu import calibration as cal

    fields = {f.name: None for f in cal.dataclasses.fields(cal.CalibrationProblem)}
    return cal.CalibrationProblem(**fields)


def test_calibration_loss_of_a_float32_problem_takes_a_float64_calibration(cal_inputs):
    """A float64 calibration (``ImuCalibration.default()`` with x64 on, or L-BFGS's float64
    line search over a float32 problem) raised JAX's "scan body function carry input and
    carry output must have equal types": the loss is in the problem's dtype, whatever the
    calibration's. Reference: the same calibration rounded to float32 first."""
    t, gyro, accel, ref = cal_inputs
    g32 = (np.asarray(gyro) + [0.01, -0.02, 0.005]).astype(np.float32)
    problem = cal.calibration_problem(
        t, g32, np.asarray(accel, np.float32), ref, ImuNoise.euroc(), keyframe_interval=0.2
    )
    calib = cal.ImuCalibration.default()
    assert calib.b_g.dtype == jnp.float64
    loss = cal.calibration_loss(problem, calib)
    rounded = cal.calibration_loss(
        problem, jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), calib)
    )
    assert loss.dtype == jnp.float32
    np.testing.assert_allclose(float(loss), float(rounded), rtol=1e-5)


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(window_lengths=()), r"window_lengths must be window lengths in seconds.* got \(\)"),
        (dict(t="zero"), r"t must increase strictly; t\[1\] = 0 ≤ t\[0\] = 0 .*zero duration"),
        (dict(t="nan"), r"t contains non-finite values .* index \[7\].*drop_nonfinite"),
        (
            dict(window_lengths=(0.1, 0.4, 1.2)),
            r"the longest window length, 1\.2 s, is longer than the 0\.59 s the recording "
            r"and the reference share.*pass lengths of 0\.1 … 0\.59 s in window_lengths",
        ),
    ],
)
def test_the_noise_problem_refuses_windows_and_stamps_by_name_before_any_work(
    cal_inputs, change, message
):
    """An empty window_lengths raised IndexError, equal stamps OverflowError, a NaN stamp
    "cannot convert float NaN to integer", and windows longer than the recording "no window
    lies between the reference's gaps" (it has none)."""
    t, gyro, accel, ref = cal_inputs  # 0.59 s at 100 Hz
    kw = dict(window_lengths=(0.05, 0.1)) | change
    t = {"zero": np.zeros_like(t), "nan": np.where(np.arange(len(t)) == 7, np.nan, t)}.get(
        kw.pop("t", None), t
    )
    with pytest.raises(ValueError, match=message):
        cal.calibration_problem(t, gyro, accel, ref, ImuNoise.euroc(), **kw)
