"""The calibration's unit and frame checks accept every correct 3 s
excerpt of the bundled real recordings, and still catch deg/s, g and a rotated frame where
the motion allows, blaming the sensor that is wrong.

The recordings: ``jaximu/data`` (EuRoC V1_02 and V2_01, 20 s each) and ``tests/data``
(EuRoC V1_02, 5 s; TUM-VI room4, 8 s with motion-capture dropouts). Excerpts slide by 1 s
(0.25 s was checked by hand: all accepted). ``calibration_problem`` only preintegrates (one
compilation per window count), so the ~45 excerpts × 4 variants stay cheap.
"""

from __future__ import annotations

import pathlib

import numpy as np
import pytest

from jaximu import ImuNoise, datasets, io
from jaximu import calibration as cal

DATA = pathlib.Path(__file__).resolve().parents[1] / "data"
LENGTH, STRIDE = 3.0, 1.0
SAMPLES = 600  # LENGTH at 200 Hz
RZ90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def recordings():
    out = []
    for name, seg in (
        ("jaximu/data V1_02", datasets.euroc_v1_02_segment()),
        ("jaximu/data V2_01", datasets.euroc_v2_01_segment()),
    ):
        out.append(
            (
                name,
                seg.t,
                seg.gyro,
                seg.accel,
                cal.Reference(seg.t_gt, seg.q_gt, seg.p_gt, seg.v_gt),
                ImuNoise.euroc(),
            )
        )
    for name, read, folder, noise in (
        ("tests/data V1_02", io.read_euroc, "euroc_v1_02_medium", ImuNoise.euroc()),
        ("tests/data TUM-VI", io.read_tumvi, "tumvi_room4", ImuNoise.tum_vi()),
    ):
        d = read(DATA / folder)
        gt = d.ground_truth
        out.append((name, d.t, d.gyro, d.accel, cal.Reference(gt.t, gt.q, gt.p, gt.v), noise))
    return out


@pytest.fixture(scope="module")
def excerpts():
    """``(label, t, gyro, accel, reference, noise)`` for every 3 s excerpt inside the truth."""
    out = []
    for name, t, gyro, accel, ref, noise in recordings():
        start, end = max(t[0], ref.t[0]), min(t[-1], ref.t[-1])
        for s in np.arange(start, end - LENGTH + 1e-9, STRIDE):
            # SAMPLES samples from the first at or after s: one array shape for every excerpt
            # of every recording (all ~200 Hz), so calibration_problem compiles once
            sel = slice(k := int(np.searchsorted(t, s)), k + SAMPLES)
            if len(t[sel]) < SAMPLES or t[sel][-1] > end:
                continue
            out.append(
                (
                    f"{name} {s - start:.0f}–{s - start + LENGTH:.0f} s",
                    t[sel],
                    gyro[sel],
                    accel[sel],
                    ref,
                    noise,
                )
            )
    assert len(out) >= 40
    return out


def problem(e, gyro=None, accel=None, ref=None):
    _, t, g, a, r, noise = e
    return cal.calibration_problem(
        t,
        g if gyro is None else gyro,
        a if accel is None else accel,
        r if ref is None else ref,
        noise,
    )


def test_every_correct_excerpt_is_accepted(excerpts):
    refused = []
    for e in excerpts:
        try:
            problem(e)
        except cal.CalibrationError as err:
            refused.append(f"{e[0]}: {err}")
    assert not refused, "\n".join(refused)


def test_a_gyro_in_degrees_is_caught_and_blamed_on_the_gyro(excerpts):
    """On every excerpt, moving or near-still (the reported defect: a deg/s gyro on a still
    segment was called an accelerometer frame problem)."""
    for e in excerpts:
        with pytest.raises(cal.CalibrationError) as err:
            problem(e, gyro=np.rad2deg(e[2]))
        msg = str(err.value)
        assert "gyroscope" in msg and "deg/s" in msg, f"{e[0]}: {msg}"


def test_an_accelerometer_in_g_is_caught(excerpts):
    for e in excerpts:
        with pytest.raises(cal.CalibrationError, match=r"accelerometer.*in g"):
            problem(e, accel=e[3] / 9.81)


def test_a_rotated_imu_is_caught_where_the_motion_shows_it(excerpts):
    """An IMU mounted 90° about z from the reference's body: caught on the excerpts whose
    motion determines the rotation (all but near-still ones), never blamed on units."""
    caught = 0
    for e in excerpts:
        try:
            problem(e, gyro=e[2] @ RZ90.T, accel=e[3] @ RZ90.T)
        except cal.CalibrationError as err:
            assert "axes do not match" in str(err), f"{e[0]}: {err}"
            caught += 1
    assert caught >= 0.9 * len(excerpts), (caught, len(excerpts))


@pytest.mark.parametrize("index", [0, 1])
def test_a_quaternion_in_xyzw_order_is_caught_on_a_whole_recording(index):
    name, t, g, a, ref, noise = recordings()[index]
    swapped = cal.Reference(ref.t, ref.q[:, [1, 2, 3, 0]], ref.p, ref.v)
    with pytest.raises(cal.CalibrationError, match="axes do not match|times the reference's"):
        cal.calibration_problem(t, g, a, swapped, noise)
