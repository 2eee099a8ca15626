"""The joint-state lag the advice names, applied by the core; injections into real data."""

from __future__ import annotations

import numpy as np
import pytest

from egovib_ros.core.stream import FramerSettings, frame_batch
from egovib_ros.errors import ConfigError


def _stream(seed: int = 0, n: int = 6000):
    rng = np.random.default_rng(seed)
    stamps = np.arange(n, dtype=np.int64) * 333_333
    accel = rng.standard_normal((n, 3))
    joint_stamps = np.arange(0, n * 333_333, 1_000_000, dtype=np.int64) + 170_000
    t = joint_stamps / 1e9
    velocity = np.column_stack([np.sin(2 * np.pi * 0.7 * t), np.cos(2 * np.pi * 1.3 * t)])
    return stamps, accel, joint_stamps, velocity


@pytest.mark.parametrize("lag_s", [0.023, -0.031])
def test_joint_lag_equals_restamped_joint_states(lag_s):
    """joint_lag_s moves joint-state stamps later by that much before matching: the blocks
    equal those of joint states re-stamped by hand."""
    stamps, accel, joint_stamps, velocity = _stream()
    shifted = FramerSettings(joint_lag_s=lag_s)
    by_hand = FramerSettings()
    a, _ = frame_batch(shifted, 2, stamps, accel, joint_stamps, velocity)
    b, _ = frame_batch(by_hand, 2, stamps, accel, joint_stamps + int(round(lag_s * 1e9)), velocity)
    va = np.concatenate([x.velocity for x in a])
    vb = np.concatenate([x.velocity for x in b])
    assert va.shape == vb.shape and len(va) > 100
    np.testing.assert_allclose(va, vb)
    unshifted, _ = frame_batch(FramerSettings(), 2, stamps, accel, joint_stamps, velocity)
    assert not np.allclose(va, np.concatenate([x.velocity for x in unshifted]))


def test_joint_lag_out_of_range_is_refused():
    with pytest.raises(ConfigError, match="joint_lag_s"):
        FramerSettings(joint_lag_s=2.0)
    with pytest.raises(ConfigError, match="joint_lag_s"):
        FramerSettings(joint_lag_s=float("nan"))


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
