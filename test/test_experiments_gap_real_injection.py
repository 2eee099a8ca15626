"""The real-flight injections of the gap validation change only what they say."""

from __future__ import annotations

import numpy as np


def test_real_injections_change_only_what_they_say():
    """Timing re-stamps the joint states only; the gains multiply the real gyro only, by
    the stated functions of the joint states."""
    from egovib_ros.bag import read_recording
    from egovib_ros.experiments.gap_flight import SPLIT_S, _slice
    from egovib_ros.experiments.gap_real_injection import inject
    from egovib_ros.robot import load_profile

    rec = read_recording(
        "bags/quadcopter_ar8",
        profile=load_profile("quadcopter"),
        ground_truth=False,
        denoised=False,
    )
    part = _slice(rec, 0.0, SPLIT_S)
    late = inject(part, "timing", 0.04)
    assert np.array_equal(late.joint_stamps_ns, part.joint_stamps_ns + 40_000_000)
    assert np.array_equal(late.sensor, part.sensor)
    for effect in ("drift", "position", "acceleration", "coupling"):
        out = inject(part, effect, 0.8)
        assert np.array_equal(out.joint_velocity, part.joint_velocity), effect
        nonzero = np.all(part.sensor != 0, axis=1)
        gain = out.sensor[nonzero] / part.sensor[nonzero]
        g = np.median(gain, axis=1)
        assert np.max(np.abs(gain - g[:, None])) < 1e-9, effect  # one gain for all axes
        assert np.max(g) > 1.2 and np.min(g) > 0, effect
    warm = inject(part, "drift", 0.8)
    nonzero = part.sensor[:, 0] != 0
    g = warm.sensor[nonzero, 0] / part.sensor[nonzero, 0]
    assert g[0] < 1.05 and g[-1] > 1.75  # warms up from 1 towards 1.8
