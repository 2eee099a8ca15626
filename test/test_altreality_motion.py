"""The alternate-reality hand's motion planner: both styles stay within the drives' limits and
the gripper's travel, the servo follows its reference, reversals are found where they are."""

from __future__ import annotations

import numpy as np
import pytest

from egovib_research.altreality.motion import (
    GAP_MAX,
    GAP_MIN,
    GRIPPER_LIMIT,
    WRIST_LIMIT,
    plan_motion,
    reversal_events,
    servo,
    smoothstep5,
)


def test_motion_styles_and_reversals():
    rng = np.random.default_rng(0)
    v, pos, acc = plan_motion(20.0, 3000.0, rng, style="smooth")
    assert np.max(np.abs(v[:, 0])) <= 3.0 and np.max(np.abs(v[:, 1])) <= 0.04 * 1.05
    idx, a = reversal_events(v[:, 1], 3000.0, 0.0008)
    assert len(idx) >= 3 and np.all(a >= 0)
    v2, _, _ = plan_motion(20.0, 3000.0, np.random.default_rng(0), style="segments")
    assert v2.shape == v.shape and not np.array_equal(v, v2)


@pytest.mark.parametrize("style", ["smooth", "segments"])
def test_position_and_acceleration_are_the_integral_and_derivative_of_velocity(style):
    fs = 1000.0
    v, pos, acc = plan_motion(30.0, fs, np.random.default_rng(3), style=style, top_speed=0.5)
    assert v.shape == pos.shape == acc.shape == (30_000, 2)
    assert np.max(np.abs(v[:, 0])) <= 0.5 * WRIST_LIMIT * 1.05  # the servo overshoots a little
    # a stroke whose speed wanders may exceed top_speed, never the drive's limit
    assert np.max(np.abs(v[:, 1])) <= GRIPPER_LIMIT * 1.05
    np.testing.assert_allclose(np.diff(pos[:, 0]), v[1:, 0] / fs, rtol=0, atol=1e-12)
    assert pos[:, 1].min() >= GAP_MIN and pos[:, 1].max() <= GAP_MAX
    np.testing.assert_array_equal(acc, np.gradient(v, 1.0 / fs, axis=0))


def test_servo_settles_on_a_step_and_the_blend_is_smooth():
    fs = 3000.0
    step = np.r_[np.zeros(300), np.ones(3000)]
    out = servo(step, fs)
    assert out[0] == 0.0 and abs(out[-1] - 1.0) < 1e-6
    assert 1.0 < out.max() < 1.05  # damping 0.8: a small overshoot, no ringing
    x = np.linspace(-0.5, 1.5, 201)
    s = smoothstep5(x)
    assert s[0] == 0.0 and s[-1] == 1.0 and np.all(np.diff(s) >= 0)


def test_reversals_are_the_first_samples_moving_the_other_way():
    fs = 100.0
    velocity = np.array([0.0, 0.5, 1.0, 0.2, 0.0, -0.4, -1.0, 0.0, 0.0, 0.3, -0.3])
    idx, acc = reversal_events(velocity, fs, 0.25)
    np.testing.assert_array_equal(idx, [5, 9, 10])  # a stop between two directions still counts
    np.testing.assert_allclose(acc, np.abs(np.gradient(velocity, 1.0 / fs))[[5, 9, 10]])
    assert len(reversal_events(np.full(50, 0.1), fs, 0.25)[0]) == 0


def test_unknown_style_is_refused():
    with pytest.raises(ValueError, match="motion style"):
        plan_motion(1.0, 1000.0, np.random.default_rng(0), style="random")
