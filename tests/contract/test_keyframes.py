"""The input contract of ``jaximu.keyframes``: times that are not strictly increasing, a
window longer than the recording, a ground truth of another type or without velocities,
and a measurement of another number of windows are each named, with the fix where there
is one."""

from __future__ import annotations

import numpy as np
import pytest

from jaximu import io, keyframes


def truth(velocities=True):
    t = np.arange(11) * 0.1
    q = np.tile([1.0, 0.0, 0.0, 0.0], (11, 1))
    return io.GroundTruth(t, q, np.zeros((11, 3)), np.zeros((11, 3)) if velocities else None)


@pytest.mark.parametrize(
    "call, message",
    [
        (
            lambda: keyframes.keyframe_windows(np.arange(5.0), 5),
            r"samples = 5 intervals is more than the 4 intervals of t: pass samples ≤ 4",
        ),
        (
            lambda: keyframes.keyframe_windows(np.arange(5.0), 0),
            r"samples must be a positive integer",
        ),
        (
            lambda: keyframes.keyframe_windows(np.arange(5.0), True),
            r"samples must be a positive integer",
        ),
        (
            lambda: keyframes.keyframe_windows(np.array([0.0, 1.0, 1.0, 2.0]), 1),
            r"t must be strictly increasing, but t\[1\] = 1 and t\[2\] = 1",
        ),
        (
            lambda: keyframes.keyframe_windows(np.array([0.0, np.nan, 2.0]), 1),
            r"t contains non-finite",
        ),
        (lambda: keyframes.keyframe_windows(np.zeros((3, 2)), 1), r"t must be an \(N,\) array"),
        (
            lambda: keyframes.groundtruth_coverage(None, [0.0], [1.0]),
            r"ground_truth must be a jaximu.io.GroundTruth, got NoneType",
        ),
        (
            lambda: keyframes.groundtruth_coverage(truth(), [0.0, 1.0], [1.0]),
            r"t_i and t_j must have the same shape",
        ),
    ],
)
def test_bad_input_is_named(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_a_pose_only_ground_truth_cannot_check_a_measurement():
    with pytest.raises(ValueError, match=r"ground_truth has no velocities"):
        keyframes.groundtruth_residuals(None, truth(velocities=False), [0.0], [1.0], None)
    with pytest.raises(ValueError, match=r"pim must be a Preintegrated of 1 windows"):
        keyframes.groundtruth_residuals(None, truth(), [0.0], [1.0], None)
