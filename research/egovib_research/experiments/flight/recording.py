"""The flight bag as arrays, keyed by the robot profile, through the bag layer
(`egovib_ros.bag.read_recording`), plus the firmware-filtered gyro topic for baseline (d)."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass

import numpy as np

from egovib_ros.bag import bag_topics, read_recording
from egovib_ros.bag.codec import IMU_TYPE
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import BagError
from egovib_ros.robot import RobotProfile

FILTERED_TOPIC = "/imu/data_filtered"


@dataclass
class FlightRecording:
    """What the experiment needs of the bag (same attribute names as bag.Recording)."""

    sensor_stamps_ns: np.ndarray  # (N,) sensor stamps (the profile's Imu topic)
    sensor: np.ndarray  # (N, 3) the profile's field (here: gyro, rad/s)
    joint_stamps_ns: np.ndarray  # (M,)
    joint_velocity: np.ndarray  # (M, J) joints in profile order
    joint_position: np.ndarray  # (M, J)
    joint_names: tuple[str, ...]
    filtered_stamps_ns: np.ndarray | None = None  # firmware-filtered gyro (baseline d), if present
    filtered: np.ndarray | None = None

    @property
    def duration_s(self) -> float:
        return (
            float(self.sensor_stamps_ns[-1] - self.sensor_stamps_ns[0]) / NS_PER_S
            if len(self.sensor_stamps_ns) > 1
            else 0.0
        )

    def time_slice(self, start_ns: int, stop_ns: int) -> "FlightRecording":
        """Samples with start_ns <= stamp < stop_ns on every stream."""

        def cut(stamps):
            return slice(
                int(np.searchsorted(stamps, start_ns)), int(np.searchsorted(stamps, stop_ns))
            )

        a, j = cut(self.sensor_stamps_ns), cut(self.joint_stamps_ns)
        f = cut(self.filtered_stamps_ns) if self.filtered_stamps_ns is not None else None
        return FlightRecording(
            self.sensor_stamps_ns[a],
            self.sensor[a],
            self.joint_stamps_ns[j],
            self.joint_velocity[j],
            self.joint_position[j],
            self.joint_names,
            None if f is None else self.filtered_stamps_ns[f],
            None if f is None else self.filtered[f],
        )

    def part(self, start_s: float, stop_s: float) -> "FlightRecording":
        """`time_slice` from start_s to stop_s seconds after the first sensor sample."""
        t0 = int(self.sensor_stamps_ns[0])
        return self.time_slice(t0 + int(start_s * NS_PER_S), t0 + int(stop_s * NS_PER_S))


def read_flight_bag(path: str | os.PathLike, profile: RobotProfile) -> FlightRecording:
    """Sensor topic/field and joints from `profile` (through the bag layer); the
    firmware-filtered gyro when the bag has it."""
    rec = read_recording(path, profile=profile, ground_truth=False, denoised=False)
    filtered = (None, None)
    topics = bag_topics(path)
    if FILTERED_TOPIC in topics:
        if topics[FILTERED_TOPIC][0] != IMU_TYPE:
            raise BagError(
                f"{path}: topic {FILTERED_TOPIC} has type {topics[FILTERED_TOPIC][0]}, "
                f"expected {IMU_TYPE}"
            )
        other = dataclasses.replace(profile, sensor_topic=FILTERED_TOPIC)
        firmware = read_recording(path, profile=other, ground_truth=False, denoised=False)
        filtered = (firmware.sensor_stamps_ns, firmware.sensor)
    return FlightRecording(
        rec.sensor_stamps_ns,
        rec.sensor,
        rec.joint_stamps_ns,
        rec.joint_velocity,
        rec.joint_position,
        tuple(profile.joint_names),
        *filtered,
    )
