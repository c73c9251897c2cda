"""``allan.motion_ratio`` and ``allan.static_intervals``: telling a static recording (for the
Allan deviation) from one with motion.

References: closed forms of the ratio (a ramp ``y_k = k`` over ``n`` windows of ``m``
samples: ``m·√((n² - 1)/(N² - 1))``; a square wave of one window per level: 1; a sign that
alternates every sample: 0); white noise's ``1/√m`` with its sampling spread (5σ); and a
synthetic gyro whose static stretch is known.
"""

from __future__ import annotations

import numpy as np

from jaximu import allan


def test_motion_ratio_closed_forms():
    dt, m, n = 0.01, 10, 30  # window 0.1 s = 10 samples, 30 whole windows
    N = n * m
    ramp = np.arange(N, dtype=float)
    expected = m * np.sqrt((n**2 - 1) / (N**2 - 1))
    np.testing.assert_allclose(allan.motion_ratio(ramp, dt, 0.1), expected, rtol=1e-12)
    # per axis, the largest; an affine map or a change of unit (57×) leaves it alone
    y = np.stack([ramp, 5 - 3 * ramp, 57.3 * ramp], axis=1)
    np.testing.assert_allclose(allan.motion_ratio(y, dt, 0.1), expected, rtol=1e-12)
    square = np.repeat(np.tile([1.0, -1.0], n // 2), m)  # constant over each window
    np.testing.assert_allclose(allan.motion_ratio(square, dt, 0.1), 1.0, rtol=1e-12)
    alternating = np.tile([1.0, -1.0], N // 2)  # every window's mean is 0
    assert allan.motion_ratio(alternating, dt, 0.1) <= 1e-15
    both = np.stack([alternating, square], axis=1)
    np.testing.assert_allclose(allan.motion_ratio(both, dt, 0.1), 1.0, rtol=1e-12)


def test_motion_ratio_of_white_noise_is_one_over_root_m():
    # 400 windows of 100 samples: the sample spread of the means is 1/√(2·399) ≈ 3.5% relative
    y = np.random.default_rng(1).normal(size=40_000) * 2e-3 + 0.01
    ratio = allan.motion_ratio(y, 0.005, 0.5)
    np.testing.assert_allclose(ratio, 1 / np.sqrt(100), rtol=5 / np.sqrt(2 * 399))
    assert ratio < allan.STATIC_MOTION_RATIO


def test_motion_ratio_too_short_to_judge_and_constant_axes():
    assert np.isnan(allan.motion_ratio(np.arange(15.0), 0.01, 0.1))  # one whole window
    y = np.stack([np.full(300, 2.0), np.arange(300.0)], axis=1)  # a constant axis counts 0
    np.testing.assert_allclose(
        allan.motion_ratio(y, 0.01, 0.1), allan.motion_ratio(y[:, 1], 0.01, 0.1), rtol=0
    )
    assert allan.motion_ratio(np.full(300, 2.0), 0.01, 0.1) == 0.0


def gyro_with_static_stretch(start, stop, seconds=60.0, rate=200.0):
    """White noise about a bias, plus a slow rotation outside ``[start, stop)`` seconds."""
    t = np.arange(int(seconds * rate)) / rate
    rng = np.random.default_rng(2)
    y = rng.normal(size=(len(t), 3)) * 0.01 + [0.002, -0.01, 0.03]
    moving = (t < start) | (t >= stop)
    y[moving] += 0.5 * np.sin(2 * np.pi * t[moving] / 5.0)[:, None] * [1.0, 0.5, -0.3]
    return y


def test_static_intervals_find_the_known_static_stretch():
    dt = 0.005
    # aligned with the 10 s pieces: exactly the stretch, as sample ranges
    got = allan.static_intervals(gyro_with_static_stretch(20.0, 50.0), dt)
    assert got.tolist() == [[4000, 10000]]
    # not aligned: the pieces wholly inside it (the piece 20–30 s is half motion)
    got = allan.static_intervals(gyro_with_static_stretch(25.0, 50.0), dt)
    assert got.tolist() == [[6000, 10000]]
    # all static: one stretch, the samples after the last whole piece included
    y = gyro_with_static_stretch(0.0, np.inf, seconds=60.5)
    assert allan.static_intervals(y, dt).tolist() == [[0, 12100]]
    none = allan.static_intervals(gyro_with_static_stretch(0.0, 0.0), dt)
    assert none.shape == (0, 2)
