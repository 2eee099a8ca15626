"""Test robot profiles; their recordings come from the package's generic simulator.

`profile(n_joints, ...)` builds a RobotProfile for core tests (no PR2 in it);
`recording(p, duration_s, seed=...)` is a free-motion run of the package's generic simulator
(egovib_ros.sim.robot: lines per joint rising with speed plus harmonics, smooth random
motion, jittered stamps, taps) as whole arrays, and `as_recording` turns them into a bag
Recording.
"""

from __future__ import annotations

import numpy as np

from egovib_ros.bag import Recording
from egovib_ros.robot import RobotProfile
from egovib_ros.sim.robot import robot_slices

__all__ = ["profile", "recording", "free_motion_arrays", "as_recording"]


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


def free_motion_arrays(
    profile: RobotProfile,
    duration_s: float,
    *,
    seed: int,
    joint_rate_hz: float | None = None,
    jitter: float = 0.3,
    taps_per_s: float = 0.0,
    tap_amplitude: float = 3.0,
    speed_fraction: float = 0.9,
    tap_mode: str = "periodic",
) -> dict:
    """A free-motion run as whole arrays: t_acc (N,), accel (N, 3),
    t_joint (M,), velocity (M, J), position (M, J), contact (N, 3), ego (N, 3), onsets
    (sample indices of the taps) and onsets_ns. Joint states at the sensor rate unless
    `joint_rate_hz` says otherwise."""
    slices, truth, _ = robot_slices(
        profile,
        mode="motion",
        duration_s=duration_s,
        max_speed=speed_fraction,
        tap_rate_hz=taps_per_s,
        tap_mode=tap_mode,
        tap_amplitude=tap_amplitude,
        seed=seed,
        joint_rate_hz=profile.rate_hz if joint_rate_hz is None else joint_rate_hz,
        jitter=jitter,
    )
    pieces = list(slices)

    def cat(name):
        return np.concatenate([getattr(piece, name) for piece in pieces])

    t_acc = cat("sensor_stamps_ns")
    onsets_ns = np.asarray(truth["tap_onsets_ns"], dtype=np.int64)
    return {
        "t_acc": t_acc,
        "accel": cat("sensor"),
        "t_joint": cat("joint_stamps_ns"),
        "velocity": cat("joint_velocity"),
        "position": cat("joint_position"),
        "contact": cat("contact"),
        "ego": cat("ego"),
        "onsets": np.searchsorted(t_acc, onsets_ns),
        "onsets_ns": onsets_ns,
    }


def as_recording(profile: RobotProfile, arrays: dict) -> Recording:
    """`free_motion_arrays`'s arrays as a bag Recording of the profile (the contact as
    ground truth; callers may have cut the sensor arrays, so not the ego)."""
    return Recording(
        sensor_stamps_ns=arrays["t_acc"],
        sensor=arrays["accel"],
        joint_stamps_ns=arrays["t_joint"],
        joint_position=arrays["position"],
        joint_velocity=arrays["velocity"],
        joint_names=profile.joint_names,
        contact=arrays["contact"],
    )


recording = free_motion_arrays
