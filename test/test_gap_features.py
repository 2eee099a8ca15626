"""gap.features.JointFeatures: the joint series' covariates slice by slice."""

from __future__ import annotations

import numpy as np
import pytest
from gaptables import detect_reversals, savgol_joint

from egovib_ros.gap.features import (
    JointFeatures,
    JointSeries,
    _interval_means,
    jerk_means,
    joint_period,
)

NS = 1_000_000_000


def joint_stream(seed: int = 3, seconds: float = 20.0, rate_hz: float = 1000.0):
    """Two joints: a wrist turning past +-pi (wrapped angle) and a gripper going back and
    forth; jittered stamps on an epoch clock."""
    rng = np.random.default_rng(seed)
    n = int(seconds * rate_hz)
    t_ns = 1_700_000_000 * NS + np.cumsum(rng.integers(900_000, 1_100_000, n))
    t = (t_ns - t_ns[0]) / NS
    velocity = np.column_stack([2.0 + 1.5 * np.sin(0.7 * t), 0.05 * np.sin(2.1 * t + 0.3)])
    velocity += rng.normal(0.0, 0.01, velocity.shape)
    angle = np.cumsum(velocity * 1e-3, axis=0)
    position = np.column_stack([np.angle(np.exp(1j * angle[:, 0])), angle[:, 1]])
    return t_ns, position, velocity


def streamed(t_ns, position, velocity, cuts, t0_ns):
    features = JointFeatures(np.array([3.5, 0.06]))
    for a, b in zip(cuts[:-1], cuts[1:]):
        features.push(t_ns[a:b], position[a:b], velocity[a:b])
    return features.finish(t0_ns)


def test_any_slicing_gives_the_series_of_one_slice():
    t_ns, position, velocity = joint_stream()
    n = len(t_ns)
    whole = streamed(t_ns, position, velocity, [0, n], t_ns[0])
    rng = np.random.default_rng(0)
    for cuts in (
        [0, 1, 2, 3, 700, 1001, 1002, n],  # the period fixed mid-slice, one-sample slices
        np.unique(np.concatenate([[0, n], rng.integers(0, n, 60)])),
        np.arange(0, n + 1, 97).tolist() + [n],
    ):
        got = streamed(t_ns, position, velocity, np.unique(cuts), t_ns[0])
        for name in ("t_s", "position", "velocity", "acceleration", "smooth_velocity"):
            np.testing.assert_array_equal(getattr(got, name), getattr(whole, name), err_msg=name)
        for j in range(2):
            np.testing.assert_array_equal(got.reversals[j], whole.reversals[j])


def test_the_series_is_the_whole_series_filters_of_the_batch_helpers():
    t_ns, position, velocity = joint_stream()
    got = streamed(t_ns, position, velocity, [0, 5000, len(t_ns)], t_ns[0])
    t_s = (t_ns - t_ns[0]) / NS
    assert joint_period(t_s) == pytest.approx(joint_period(t_ns, per_second=NS), rel=1e-12)
    np.testing.assert_allclose(got.position, np.unwrap(position, axis=0), rtol=0, atol=1e-12)
    assert np.ptp(got.position[:, 0]) > 4 * np.pi  # the wrist turned past +-pi several times
    np.testing.assert_allclose(got.smooth_velocity, savgol_joint(t_s, velocity), atol=1e-9)
    np.testing.assert_allclose(
        got.acceleration, savgol_joint(t_s, velocity, deriv=1), rtol=1e-7, atol=1e-7
    )
    want = detect_reversals(t_s, got.smooth_velocity, np.array([3.5, 0.06]))
    assert len(want[1]) >= 10  # the gripper went back and forth
    for j in range(2):
        np.testing.assert_allclose(got.reversals[j], want[j], rtol=0, atol=1e-12)


def test_a_series_too_short_for_the_filter_is_kept_as_is():
    t_ns, position, velocity = joint_stream(seconds=0.02)
    got = streamed(t_ns, position, velocity, [0, 7, len(t_ns)], t_ns[0])
    np.testing.assert_array_equal(got.smooth_velocity, velocity)
    assert not got.acceleration.any()


def test_block_means_past_the_ends_of_the_joint_series_hold_it_not_dilute_it():
    """Half past an end (a block at a lag): its covered half's mean; wholly past: the value."""
    t = np.linspace(0.0, 1.0, 1001)
    values = np.column_stack([2.0 + t, np.full_like(t, -3.0)])
    t0, t1 = np.array([0.2, 0.9, 1.2, -0.5, -0.1]), np.array([0.3, 1.1, 1.3, -0.4, 0.1])
    means = _interval_means(t, values, t0, t1)
    np.testing.assert_allclose(means, [[2.25, -3], [2.95, -3], [3, -3], [2, -3], [2.05, -3]])


def test_the_jerk_is_where_a_ramp_starts_and_ends_and_a_repeated_stamp_says_nothing():
    """A trapezoid (hold, ramp at 2 units/s^2 from 0.4 to 0.6 s, hold): |da/dt| only in the
    blocks around the ramp's two corners, each corner's integral 2 (the step in a). A stamp
    repeated (with its values) leaves every block mean finite and the same."""
    t = np.arange(0.0, 1.0, 0.001)
    acc = np.where((t >= 0.4) & (t < 0.6), 2.0, 0.0)[:, None]
    joints = JointSeries(
        t_s=t, position=np.zeros_like(acc), velocity=np.zeros_like(acc), acceleration=acc
    )
    t0 = np.arange(0.0, 0.95, 0.05)
    means = jerk_means(joints, t0, t0 + 0.05, 0.0)[:, 0]
    mid = t0 + 0.025
    near = [np.abs(mid - corner) < 0.05 for corner in (0.4, 0.6)]
    assert np.all(means[~(near[0] | near[1])] == 0.0)
    assert all(np.any(means[n] > 0.0) for n in near)
    np.testing.assert_allclose(np.sum(means * 0.05), 4.0, rtol=1e-9)
    twice = np.insert(np.arange(len(t)), 300, 300)
    repeated = JointSeries(
        t_s=t[twice], position=acc[twice], velocity=acc[twice], acceleration=acc[twice]
    )
    np.testing.assert_allclose(jerk_means(repeated, t0, t0 + 0.05, 0.0)[:, 0], means)
