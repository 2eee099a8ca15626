"""Test robot profiles; their recordings come from the package's generic simulator.

`profile(n_joints, ...)` builds a RobotProfile for core tests (no PR2 in it);
`recording(p, duration_s, seed=...)` is egovib_ros.sim.robot.free_motion_arrays (lines per
joint rising with speed plus harmonics, smooth random motion, jittered stamps, taps) and
`as_recording` turns its arrays into a bag Recording.
"""

from __future__ import annotations

from egovib_ros.robot import RobotProfile
from egovib_ros.sim.robot import as_recording
from egovib_ros.sim.robot import free_motion_arrays as recording

__all__ = ["profile", "recording", "as_recording"]


def profile(
    n_joints: int = 3,
    *,
    rate_hz: float = 1600.0,
    bidirectional=(True, True, False),
    steps: int = 10,
    field: str = "angular_velocity",
) -> RobotProfile:
    bidirectional = tuple(bidirectional)[:n_joints] + (True,) * max(
        0, n_joints - len(bidirectional)
    )
    return RobotProfile(
        name=f"test_robot_{n_joints}",
        sensor_topic="/imu/data_raw",
        sensor_field=field,
        rate_hz=rate_hz,
        denoised_topic="/imu/denoised",
        joints_topic="/joint_states",
        joint_names=tuple(f"joint_{j}" for j in range(n_joints)),
        max_speed=tuple(2.0 + j for j in range(n_joints)),
        bidirectional=bidirectional,
        steps=steps,
        sensor_range=500.0,
        block_length=64,
        hop=32,
        band_hz=(0.04 * rate_hz, 0.44 * rate_hz),
        band_order=4,
    )
