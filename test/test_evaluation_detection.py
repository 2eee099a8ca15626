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
