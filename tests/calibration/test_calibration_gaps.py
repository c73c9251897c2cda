"""Calibration against a reference with dropouts, and windows that are not in the fit.

A window that is not in the fit (padding of the last group; a keyframe inside a reference
gap) adds nothing to the loss, the residuals or their gradient. References: the loss as the
sum of the squared residuals, a problem without padding, and a problem built on the whole
reference from which the same windows are removed before any tracing.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaximu
from jaximu import calibration as cal
from jaximu import simulate as sim

RATE = 200.0
SECONDS = 10.0
NOISE = jaximu.ImuNoise.euroc()
WHITE = jaximu.ImuNoise(NOISE.gyroscope_noise_density, NOISE.accelerometer_noise_density, 0.0, 0.0)
TRAJ = sim.lissajous(attitude_amplitude=(0.8, 0.6, 1.5), attitude_frequency=(0.31, 0.23, 0.13))
B_G, B_A = np.array([0.003, -0.002, 0.004]), np.array([0.05, -0.08, 0.1])


def simulate_data(seed=0):
    """IMU at 200 Hz; reference at 100 Hz (pose and velocity), 0.5 s beyond either end."""
    t = np.arange(int(SECONDS * RATE) + 1) / RATE
    gyro, accel = sim.ideal_imu(TRAJ, jnp.asarray(t))
    gm, am, _ = sim.add_noise(
        jax.random.key(seed), gyro, accel, 1 / RATE, WHITE, b_g0=B_G, b_a0=B_A
    )
    t_ref = np.arange(-0.5, SECONDS + 0.5, 0.01)
    truth = sim.true_states(TRAJ, jnp.asarray(t_ref))
    ref = cal.Reference(t_ref, np.asarray(truth.q), np.asarray(truth.p), np.asarray(truth.v))
    return t, np.asarray(gm), np.asarray(am), ref


def problem_for(t, gm, am, ref, **kw):
    kw = dict(dict(scheme="midpoint", reference_sigma=(0, 0, 0)), **kw)
    return cal.calibration_problem(t, gm, am, ref, NOISE, **kw)


def test_padding_windows_add_nothing_to_the_loss_or_its_gradient():
    """20 windows in groups of 8: 4 padding windows (copies of window 0) must weigh 0: the
    loss and gradient equal those of one group of 20 (no padding)."""
    data = simulate_data()
    padded = problem_for(*data, windows_per_group=8)
    whole = problem_for(*data, windows_per_group=20)
    assert padded.weight.shape == (3, 8) and whole.weight.shape == (1, 20)
    c = cal.ImuCalibration.default(dtype=jnp.float64, b_g=0.5 * B_G, b_a=-B_A)
    value_and_grad = jax.jit(jax.value_and_grad(cal.calibration_loss, argnums=1))
    loss, grad = value_and_grad(padded, c)
    want_loss, want = value_and_grad(whole, c)
    np.testing.assert_allclose(float(loss), float(want_loss), rtol=1e-12)
    for name in ("b_g", "b_a"):
        np.testing.assert_allclose(getattr(grad, name), getattr(want, name), rtol=1e-10)


# A dropout of the reference: the samples strictly between 3.30 s and 5.20 s are removed.
GAP = (3.30, 5.20)


def cut(ref, lo, hi, velocity=True):
    """The reference without its samples strictly between ``lo`` and ``hi`` (a dropout)."""
    keep = ~((ref.t > lo + 0.005) & (ref.t < hi - 0.005))  # the stamps are multiples of 0.01
    return cal.Reference(ref.t[keep], ref.q[keep], ref.p[keep], ref.v[keep] if velocity else None)


def skipped_by_hand(lo, hi, interval=0.5, n_windows=20):
    """Keyframes at 0, 0.5, ..., 10 s; a window is left out when either keyframe lies
    strictly inside the dropout."""
    key = interval * np.arange(n_windows + 1)
    inside = (key > lo + 1e-9) & (key < hi - 1e-9)
    return inside[:-1] | inside[1:]


def without_windows(prob, keep):
    """The problem as if the windows outside ``keep`` had never been built: every per-window
    array cut to the kept windows, in one group (no padding, no zero weights)."""
    K, n = prob.n_windows, int(np.count_nonzero(keep))

    def take(x):
        x = np.asarray(x)
        return jnp.asarray(x.reshape((-1,) + x.shape[2:])[:K][keep].reshape((1, n) + x.shape[2:]))

    per_window = (
        "gyro",
        "accel",
        "dt",
        "t_start",
        "t_end",
        "window",
        "weight",
        "sqrt_info",
        "reference_var",
    )
    return dataclasses.replace(prob, n_windows=n, **{f: take(getattr(prob, f)) for f in per_window})


def test_windows_with_a_keyframe_in_a_dropout_are_left_out_as_if_never_built():
    """A 1.9 s dropout: the 5 windows with a keyframe at 3.5, 4, 4.5 or 5 s are out of the fit,
    said in the problem and the result; no window of the fit reads the reference inside the
    dropout; the estimate, its σ and χ² are those of the problem on the whole reference with
    those windows never built; the left-out windows' residuals and Jacobian rows are 0."""
    t, gm, am, ref = simulate_data(1)
    prob = problem_for(t, gm, am, cut(ref, *GAP))
    skip = skipped_by_hand(*GAP)
    assert prob.n_windows == 20 and np.count_nonzero(skip) == 5
    np.testing.assert_array_equal(prob.kept, ~skip)
    assert prob.n_skipped == 5
    assert "left out 5 of 20 keyframe windows" in prob.skip_note
    assert "1.900 s at t = 3.300 s" in prob.skip_note
    t0 = t[0]
    ts = t0 + np.asarray(prob.t_start).reshape(-1)[:20][prob.kept]
    te = t0 + np.asarray(prob.t_end).reshape(-1)[:20][prob.kept]
    assert np.all((te <= GAP[0] + 1e-9) | (ts >= GAP[1] - 1e-9))  # no fitted window spans it

    res = cal.calibrate(prob)
    never = cal.calibrate(without_windows(problem_for(t, gm, am, ref), ~skip))
    assert (res.n_windows, res.skipped_windows, never.skipped_windows) == (15, 5, 0)
    assert res.note == prob.skip_note and never.note == ""
    assert res.dof == never.dof == 9 * 15 - 6
    for name in ("b_g", "b_a"):
        np.testing.assert_allclose(
            getattr(res.calibration, name),
            getattr(never.calibration, name),
            rtol=0,
            atol=1e-6 * float(np.min(getattr(never.std, name))),
        )
        np.testing.assert_allclose(getattr(res.std, name), getattr(never.std, name), rtol=1e-9)
    np.testing.assert_allclose(res.chi2, never.chi2, rtol=1e-9)
    assert np.all(np.abs(res.calibration.b_g - B_G) < 4 * res.std.b_g)

    layout = cal._Layout(("b_g", "b_a"), 0)
    init_vec = cal._flatten(cal.ImuCalibration.default(dtype=jnp.float64))
    r, J = cal._residuals_jacobian(jnp.full(6, 0.3), prob, init_vec, layout=layout)
    r, J = np.asarray(r).reshape(20, 9), np.asarray(J).reshape(20, 9, 6)
    assert np.all(r[skip] == 0) and np.all(J[skip] == 0) and np.all(r[~skip] != 0)


def test_poses_only_with_a_dropout_the_velocities_it_leaves_unbounded_are_no_parameters():
    """Motion capture without velocities: the keyframes at 3.5–5 s bound only left-out
    windows, so their velocities are reported NaN and not counted in the degrees of freedom;
    the biases equal those of the whole-reference problem with the same windows weighted 0."""
    t, gm, am, ref = simulate_data(2)
    prob = problem_for(t, gm, am, cut(ref, *GAP, velocity=False))
    skip = skipped_by_hand(*GAP)
    np.testing.assert_array_equal(prob.kept, ~skip)
    res = cal.calibrate(prob)
    unbounded = np.zeros(21, bool)
    unbounded[7:11] = True  # 3.5, 4, 4.5, 5 s
    assert np.all(np.isnan(res.velocities[unbounded]))
    assert np.all(np.isfinite(res.velocities[~unbounded]))
    assert res.dof == 9 * 15 - 6 - 3 * 17
    whole = problem_for(t, gm, am, cal.Reference(ref.t, ref.q, ref.p))
    weight = np.asarray(whole.weight).copy()
    weight.reshape(-1)[:20][skip] = 0
    masked = cal.calibrate(dataclasses.replace(whole, weight=jnp.asarray(weight)))
    for name in ("b_g", "b_a"):
        np.testing.assert_allclose(
            getattr(res.calibration, name),
            getattr(masked.calibration, name),
            rtol=0,
            atol=1e-3 * float(np.min(getattr(masked.std, name))),
        )
    np.testing.assert_allclose(res.velocities[~unbounded], masked.velocities[~unbounded], atol=1e-6)


def test_a_gap_between_two_keyframes_leaves_every_window_in():
    """0.3 s without reference inside the window 3.5–4 s: the residual reads the reference
    only at the keyframes, which it covers."""
    t, gm, am, ref = simulate_data(3)
    prob = problem_for(t, gm, am, cut(ref, 3.6, 3.9))
    assert prob.n_skipped == 0 and prob.skip_note == "" and prob.kept.all()


def test_a_reference_that_is_all_gap_is_refused_naming_the_gap():
    """Reference samples only before 0.1 s and after 9.9 s: every window has a keyframe in
    the 9.8 s dropout."""
    t, gm, am, ref = simulate_data(4)
    with pytest.raises(
        cal.CalibrationError,
        match=r"every one of the 20 keyframe windows.*"
        r"9\.800 s at t = 0\.100 s",
    ):
        problem_for(t, gm, am, cut(ref, 0.1, 9.9))
