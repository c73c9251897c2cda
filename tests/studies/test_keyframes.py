"""``jaximu.keyframes``: windows cut from a recording, which of them a ground truth with a
known gap can check, and their residuals against it.

References: the windows written out sample by sample; the coverage read off the rule
(inside the span to the clock tolerance, a keyframe strictly inside a gap longer than 5
median intervals); the residuals of a level IMU moving at constant velocity in closed form
(zero with the true biases; ``r_p = ½Δt²δ``, ``r_v = Δtδ`` for an accelerometer bias
``δ`` the measurement was not corrected for).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import jaximu
from jaximu import io, keyframes

P0, V0 = np.array([1.0, 2.0, 3.0]), np.array([0.5, -0.2, 0.1])


def constant_velocity_truth(gap=(4.0, 5.5), rate=100.0, seconds=10.0):
    """Level, constant velocity ``V0`` from ``P0``; the rows strictly inside ``gap`` dropped
    (a mocap dropout)."""
    t = np.arange(int(seconds * rate) + 1) / rate
    keep = ~((t > gap[0] + 1e-9) & (t < gap[1] - 1e-9))
    t = t[keep]
    q = np.tile([1.0, 0.0, 0.0, 0.0], (len(t), 1))
    return io.GroundTruth(t, q, P0 + V0 * t[:, None], np.tile(V0, (len(t), 1)))


def test_windows_are_the_samples_from_keyframe_to_keyframe():
    rng = np.random.default_rng(0)
    t = np.cumsum(0.005 + 0.001 * rng.random(23))
    w = keyframes.keyframe_windows(t, 5)
    assert w.sample_index.shape == (4, 6) and w.dt.shape == (4, 5)  # (23 - 1) // 5 = 4 windows
    for k in range(4):
        samples = list(range(5 * k, 5 * k + 6))
        assert w.sample_index[k].tolist() == samples
        assert w.dt[k].tolist() == [t[i + 1] - t[i] for i in samples[:-1]]
        assert (w.t_i[k], w.t_j[k]) == (t[5 * k], t[5 * k + 5])
    assert w.sample_index[1:, 0].tolist() == w.sample_index[:-1, -1].tolist()  # keyframes shared


def test_coverage_of_a_ground_truth_with_a_known_gap():
    gt = constant_velocity_truth()
    t_i = np.arange(11.0)
    t_j = t_i + 1.0
    cover = keyframes.groundtruth_coverage(gt, t_i, t_j)
    # [10, 11] ends after the ground truth (10 s); 5 s lies inside the (4, 5.5) s gap, so
    # [4, 5] and [5, 6] are left out; 4 s itself is a ground-truth row, not inside the gap
    assert cover.inside.tolist() == [True] * 10 + [False]
    assert cover.in_gap.tolist() == [False] * 4 + [True, True] + [False] * 5
    assert cover.checked.tolist() == [True] * 4 + [False, False] + [True] * 4 + [False]
    # the span counts to the clock tolerance, and no further
    near = keyframes.groundtruth_coverage(
        gt, [-0.5 * io.CLOCK_TOLERANCE, -2 * io.CLOCK_TOLERANCE], [1.0, 1.0]
    )
    assert near.inside.tolist() == [True, False]


def test_residuals_against_a_constant_velocity_truth():
    gt = constant_velocity_truth()
    t = np.arange(2201) * 0.005  # 11 s of a level IMU at 200 Hz: 11 windows of 1 s
    w = keyframes.keyframe_windows(t, 200)
    K = len(w.t_i)
    gyro = jnp.zeros((K, 201, 3))
    accel = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 9.81]), (K, 201, 3))
    pim = jaximu.preintegrate(gyro, accel, jnp.asarray(w.dt), None, None, "euler")
    checked = keyframes.groundtruth_coverage(gt, w.t_i, w.t_j).checked
    zero = jaximu.ImuBias(jnp.zeros(3), jnp.zeros(3))
    r = keyframes.groundtruth_residuals(pim, gt, w.t_i, w.t_j, zero)
    assert r.shape == (K, 15)
    assert np.all(np.isnan(r[~checked])) and not np.any(np.isnan(r[checked]))
    np.testing.assert_allclose(r[checked], 0.0, atol=1e-10)
    delta = np.array([0.01, -0.02, 0.03])
    r = keyframes.groundtruth_residuals(
        pim, gt, w.t_i, w.t_j, jaximu.ImuBias(jnp.zeros(3), jnp.asarray(delta))
    )
    dt = 1.0
    np.testing.assert_allclose(
        r[checked][:, 3:6], np.tile(0.5 * dt**2 * delta, (8, 1)), rtol=1e-9, atol=1e-12
    )
    np.testing.assert_allclose(
        r[checked][:, 6:9], np.tile(dt * delta, (8, 1)), rtol=1e-9, atol=1e-12
    )
    np.testing.assert_allclose(r[checked][:, [0, 1, 2, 9, 10, 11, 12, 13, 14]], 0.0, atol=1e-10)
    # in float32: the residuals in pim's dtype, the same to float32 rounding of |p| ≈ 10 m
    pim32 = jaximu.preintegrate(
        gyro.astype(jnp.float32),
        accel.astype(jnp.float32),
        jnp.asarray(w.dt, jnp.float32),
        None,
        None,
        "euler",
    )
    r32 = keyframes.groundtruth_residuals(
        pim32,
        gt,
        w.t_i,
        w.t_j,
        jaximu.ImuBias(jnp.zeros(3, jnp.float32), jnp.asarray(delta, jnp.float32)),
    )
    assert r32.dtype == np.float64 and np.array_equal(np.isnan(r32), np.isnan(r))
    np.testing.assert_allclose(
        r32[checked], r[checked], rtol=0, atol=50 * np.finfo(np.float32).eps * 10
    )
