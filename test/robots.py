"""A generic N-joint robot for core tests, written apart from egovib_ros.sim (no PR2 in it).

Each joint drives a motor whose vibration is a line at a frequency proportional to its
speed plus two harmonics, with amplitude growing with speed, over a white sensor floor.
Joint velocities are smooth random motions (one-directional joints stay in 0..max);
sensor stamps jitter +-30 % per step around the nominal rate, as flight controllers and
USB IMUs log them. Contacts are damped-sine bursts at known onsets.
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from egovib_ros.robot import RobotProfile


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


def _smooth_random(
    rng: np.random.Generator, n: int, rate_hz: float, corner_hz: float = 0.3
) -> np.ndarray:
    sos = signal.butter(2, corner_hz, fs=rate_hz, output="sos")
    x = signal.sosfiltfilt(sos, rng.normal(size=n + 2000))[1000:-1000]
    return x / (np.std(x) + 1e-12)


def recording(
    p: RobotProfile,
    duration_s: float,
    *,
    seed: int,
    joint_rate_hz: float | None = None,
    jitter: float = 0.3,
    taps_per_s: float = 0.0,
    tap_amplitude: float = 3.0,
    speed_fraction: float = 0.9,
) -> dict:
    """Arrays of a free-motion recording: t_acc (N,), accel (N, 3), t_joint (M,), velocity (M, J),
    contact (N, 3) and the tap onsets (sample indices)."""
    rng = np.random.default_rng(seed)
    fs = p.rate_hz
    n = int(duration_s * fs)
    steps = 1.0 + rng.uniform(-jitter, jitter, n)
    t = np.cumsum(steps) / fs
    t_acc = (1_000_000_000 + np.round(t * 1e9)).astype(np.int64)
    # joint motion, evaluated on the sensor clock (the mechanism) and sampled for joint states
    velocity = np.empty((n, p.n_joints))
    for j in range(p.n_joints):
        x = _smooth_random(rng, n, fs)
        if p.bidirectional[j]:
            v = np.clip(0.5 * x, -1, 1)
        else:
            v = np.clip(0.5 + 0.25 * x, 0, 1)
        velocity[:, j] = speed_fraction * p.max_speed[j] * v
    accel = 0.05 * rng.normal(size=(n, 3))
    mixing = rng.normal(size=(p.n_joints, 3))
    for j in range(p.n_joints):
        speed = np.abs(velocity[:, j]) / p.max_speed[j]
        freq = 0.08 * fs + 0.25 * fs * speed  # line within the band
        phase = 2 * np.pi * np.cumsum(freq * steps / fs)
        line = sum(
            (0.8 / k) * np.sin(k * phase + k) for k in (1, 2, 3) if k * freq.max() < 0.45 * fs
        )
        accel += (speed * line)[:, None] * mixing[j][None, :]
    contact = np.zeros((n, 3))
    onsets = np.zeros(0, dtype=int)
    if taps_per_s > 0:
        gap = int(fs / taps_per_s)
        onsets = np.arange(gap // 2, n - int(0.1 * fs), gap) + rng.integers(
            -gap // 4, gap // 4, size=1
        )
        k = np.arange(int(0.05 * fs)) / fs
        burst = tap_amplitude * np.exp(-k / 0.008) * np.sin(2 * np.pi * 0.2 * fs * k)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        for o in onsets:
            contact[o : o + len(burst)] += burst[:, None] * direction[None, :]
    accel = accel + contact
    joint_rate = joint_rate_hz or fs
    every = max(1, int(round(fs / joint_rate)))
    pick = np.arange(0, n, every)
    return {
        "t_acc": t_acc,
        "accel": accel,
        "t_joint": t_acc[pick] + 150_000,
        "velocity": velocity[pick],
        "contact": contact,
        "onsets": onsets,
    }


def as_recording(p: RobotProfile, arrays: dict):
    """`recording`'s arrays as a bag Recording of profile `p` (joint positions integrated
    from the velocities)."""
    from egovib_ros.bag import Recording

    t_joint = arrays["t_joint"]
    dt = np.diff(t_joint, prepend=t_joint[0]) / 1e9
    return Recording(
        accel_stamps_ns=arrays["t_acc"],
        accel=arrays["accel"],
        joint_stamps_ns=t_joint,
        joint_position=np.cumsum(arrays["velocity"] * dt[:, None], axis=0),
        joint_velocity=arrays["velocity"],
        joint_names=p.joint_names,
        contact=arrays["contact"],
    )
