"""The ground truth's clock offset fitted from the gyro (``jaximu.learning.alignment``),
against a motion capture simulated on a clock ahead of the IMU's by scipy's rotations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaximu.io import DataError
from jaximu.learning import Sequence
from jaximu.learning.alignment import reference_offset, shifted_reference

FINE = 1200.0  # [Hz]: the IMU's 200 Hz and the mocap's 120 Hz samples both lie on it
AHEAD = 5  # fine steps (4.17 ms) the mocap reads ahead of the IMU


def fine_truth(seconds=12.0, seed=0):
    """``R(t)`` on the fine grid: a body rate of sines (about 1 rad/s), integrated by
    scipy one fine step at a time."""
    rng = np.random.default_rng(seed)
    n = int(seconds * FINE) + AHEAD + 1
    t = np.arange(n) / FINE
    f, ph = rng.uniform(0.3, 1.2, 3), rng.uniform(0, 2 * np.pi, 3)
    w = np.sin(2 * np.pi * f * t[:, None] + ph)
    steps = Rotation.from_rotvec(w[:-1] / FINE)
    R = [Rotation.identity()]
    for s in steps:
        R.append(R[-1] * s)
    return Rotation.concatenate(R)


def wxyz(R):
    return np.roll(R.as_quat(), 1, axis=-1)


def simulated(seconds=12.0):
    """A 200-Hz IMU whose gyro turns exactly as the truth between its samples, and a
    120-Hz mocap whose stamp ``τ`` holds the attitude at ``τ + AHEAD / FINE``."""
    R = fine_truth(seconds)
    n_imu = int(seconds * 200)
    k = 6 * np.arange(n_imu)  # IMU samples on the fine grid
    gyro = (R[k[:-1]].inv() * R[k[1:]]).as_rotvec() * 200.0
    gyro = np.concatenate([gyro, gyro[-1:]])
    j = 10 * np.arange(int(seconds * 120) - 1)  # mocap stamps on the fine grid
    t = k / FINE
    z = np.zeros((n_imu, 3))
    seq = Sequence(
        "sim",
        t,
        gyro,
        z + [0.0, 0.0, 9.81],
        wxyz(R[k]),
        z,
        z,
        gt_t=j / FINE,
        gt_q=wxyz(R[j + AHEAD]),
    )
    return seq, wxyz(R[k])


def test_the_offset_of_a_mocap_ahead_of_the_imu_is_found_and_undone():
    seq, truth = simulated()
    delta = reference_offset(seq)
    assert delta == pytest.approx(-AHEAD / FINE, abs=3e-4)
    q = shifted_reference(seq, delta).q
    # against scipy's truth at the IMU samples (the mocap's ends held: leave them out)
    inner = slice(10, -10)
    err = Rotation.from_quat(np.roll(q, -1, -1)) * Rotation.from_quat(np.roll(truth, -1, -1)).inv()
    assert np.max(err.magnitude()[inner]) < 1e-3  # the ω·δ error of 4 mrad is gone
    before = Rotation.from_quat(np.roll(shifted_reference(seq, 0.0).q, -1, -1))
    lag = (before * Rotation.from_quat(np.roll(truth, -1, -1)).inv()).magnitude()[inner]
    assert np.sqrt(np.mean(lag**2)) > 2e-3


def test_bad_arguments_are_named():
    seq, _ = simulated(seconds=2.0)
    with pytest.raises(ValueError, match="resolution .* must be at most search"):
        reference_offset(seq, search=1e-3, resolution=2e-3)
    with pytest.raises(ValueError, match="horizon"):
        reference_offset(seq, horizon=1)
    with pytest.raises(DataError, match="at least 3 are needed"):
        reference_offset(seq, horizon=200)
    with pytest.raises(ValueError, match="shift must be a finite number"):
        shifted_reference(seq, float("nan"))
    for shift in ("0.003", True, np.array([0.003])):  # never parsed nor taken apart
        with pytest.raises(ValueError, match="shift must be a number"):
            shifted_reference(seq, shift)
