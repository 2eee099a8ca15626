"""Event matching and the PR2 gripper sensor's magnitude on constructed signals."""

import numpy as np
import pytest

from egovib_ros.evaluation import detection

FS = 3000.0


def test_match_events_tolerance_one_to_one():
    tol = int(0.010 * FS)  # 30 samples
    truth = np.array([1000, 2000, 3000])
    detected = np.array([1010, 1020, 2031, 2990, 5000])
    tp, fp, fn = detection.match_events(detected, truth, tol)
    # 1010 -> 1000 (1020 is a duplicate), 2031 is outside +/-30, 2990 -> 3000
    assert (tp, fp, fn) == (2, 3, 1)


def test_pr2_magnitude_ignores_gravity_and_passes_vibration():
    t = np.arange(6000) / FS
    gravity = np.tile([0.0, 0.0, 9.81], (t.size, 1))
    assert detection.PR2Magnitude(sample_rate_hz=FS).process(gravity).max() < 1e-9
    vibration = gravity.copy()
    vibration[:, 0] += 3.0 * np.sin(2 * np.pi * 400 * t)
    magnitude = detection.PR2Magnitude(sample_rate_hz=FS).process(vibration)
    assert magnitude[3000:].max() == pytest.approx(3.0, rel=0.03)


def test_onsets_count_samples_whatever_the_stamps_do():
    """`egovib evaluate` scores samples in its own order; their stamps (for the detector's
    motion limits) may go back, a bag's loop: the onsets are the same sample indices as
    without stamps (stamps as the detector's order once halved F1 on a looped bag)."""
    from types import SimpleNamespace

    from egovib_ros.core.contact import MotionLimits

    model = SimpleNamespace(
        sample_rate_hz=3000.0,
        band_hz=(150.0, 750.0),
        band_order=4,
        robot_profile=lambda: SimpleNamespace(sensor_range=float("inf")),
    )
    rng = np.random.default_rng(2)
    half = 6000
    x = 0.05 * rng.normal(size=2 * half)
    for onset in (500, 2500, 4500, half + 700, half + 3100):
        k = np.arange(90)
        x[onset : onset + 90] += 3.0 * np.exp(-k / 18) * np.sin(2 * np.pi * 400 * k / 3000)
    once = 10**9 + np.arange(half, dtype=np.int64) * 333_333
    looped = np.concatenate([once, once])  # the second half stamped as the first
    limits = MotionLimits(speed_low=(-1.0,), speed_high=(1.0,), accel=1e9, factor=2.0)
    joints = (once[::3], np.zeros((len(once[::3]), 1)))  # within the limits
    plain = detection.OnsetStream(0.5, model)
    plain.push(x)
    plain.finish()
    expected = plain.take()
    assert len(expected) == 5
    for motion in (None, limits):
        stream = detection.OnsetStream(0.5, model, motion)
        stream.push_joints(*joints)
        for piece in np.array_split(np.arange(2 * half), 7):
            stream.push(x[piece], looped[piece])
        stream.finish()
        np.testing.assert_array_equal(stream.take(), expected)
