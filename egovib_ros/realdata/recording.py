"""Read the flight bag back into arrays, keyed by the robot profile.

A small stand-in for ``egovib_ros.bagio.read_recording(path, profile=...)`` (being made
profile-aware on another branch): rosbags' reader plus the project's CDR decoders,
joints picked by name. Replace by that one call when it lands on main.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egovib_ros.cdr import IMU_TYPE, JOINT_STATE_TYPE, decode_imu_batch, decode_joint_state_batch
from egovib_ros.errors import BagError
from egovib_ros.robot import RobotProfile

FILTERED_TOPIC = "/imu/data_filtered"


@dataclass
class FlightRecording:
    """What the experiment needs of the bag (same attribute names as bagio.Recording)."""

    accel_stamps_ns: np.ndarray  # (N,) sensor stamps (the profile's Imu topic)
    accel: np.ndarray  # (N, 3) the profile's field (here: gyro, rad/s)
    joint_stamps_ns: np.ndarray  # (M,)
    joint_velocity: np.ndarray  # (M, J) joints in profile order
    joint_position: np.ndarray  # (M, J)
    joint_names: tuple[str, ...]
    filtered_stamps_ns: np.ndarray | None = None  # firmware-filtered gyro (baseline d), if present
    filtered: np.ndarray | None = None

    @property
    def duration_s(self) -> float:
        return (
            float(self.accel_stamps_ns[-1] - self.accel_stamps_ns[0]) / 1e9
            if len(self.accel_stamps_ns) > 1
            else 0.0
        )

    def time_slice(self, start_ns: int, stop_ns: int) -> "FlightRecording":
        """Samples with start_ns <= stamp < stop_ns on every stream."""

        def cut(stamps):
            return slice(
                int(np.searchsorted(stamps, start_ns)), int(np.searchsorted(stamps, stop_ns))
            )

        a, j = cut(self.accel_stamps_ns), cut(self.joint_stamps_ns)
        f = cut(self.filtered_stamps_ns) if self.filtered_stamps_ns is not None else None
        return FlightRecording(
            self.accel_stamps_ns[a],
            self.accel[a],
            self.joint_stamps_ns[j],
            self.joint_velocity[j],
            self.joint_position[j],
            self.joint_names,
            None if f is None else self.filtered_stamps_ns[f],
            None if f is None else self.filtered[f],
        )


def read_flight_bag(
    path: str | os.PathLike, profile: RobotProfile, *, filtered_topic: str = FILTERED_TOPIC
) -> FlightRecording:
    """Sensor topic/field and joints from `profile`; the filtered gyro when the bag has it."""
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if not path.exists():
        raise BagError(f"{path}: no such bag")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise BagError(f"{path}: not a readable rosbag2 bag ({reason})") from None
    try:
        types = {c.topic: c.msgtype for c in reader.connections}
        expected = {
            profile.sensor_topic: IMU_TYPE,
            profile.joints_topic: JOINT_STATE_TYPE,
            filtered_topic: IMU_TYPE,
        }
        for topic in (profile.sensor_topic, profile.joints_topic):
            if topic not in types:
                raise BagError(f"{path}: missing topic {topic}")
        for topic, msgtype in expected.items():
            if topic in types and types[topic] != msgtype:
                raise BagError(f"{path}: topic {topic} has type {types[topic]}, expected {msgtype}")
        raws: dict[str, list[bytes]] = {topic: [] for topic in expected if topic in types}
        try:
            for conn, _, raw in reader.messages(
                connections=[c for c in reader.connections if c.topic in raws]
            ):
                raws[conn.topic].append(raw)
        except Exception as exc:
            raise BagError(f"{path}: unreadable bag data ({exc})") from None
    finally:
        reader.close()
    field = profile.sensor_field
    try:
        stamps, values = decode_imu_batch(raws[profile.sensor_topic], field)
        j_stamps, j_pos, j_vel, _ = decode_joint_state_batch(
            raws[profile.joints_topic], profile.joint_names
        )
        filtered = (
            decode_imu_batch(raws[filtered_topic], field)
            if raws.get(filtered_topic)
            else (None, None)
        )
    except Exception as exc:
        raise BagError(f"{path}: cannot decode a message ({exc})") from None
    if len(stamps) == 0:
        raise BagError(f"{path}: topic {profile.sensor_topic} has no messages")
    for j, name in enumerate(profile.joint_names):
        if len(j_vel) == 0 or np.all(np.isnan(j_vel[:, j])):
            raise BagError(f"{path}: joint {name!r} never appears on {profile.joints_topic}")
    return FlightRecording(
        stamps, values, j_stamps, j_vel, j_pos, tuple(profile.joint_names), *filtered
    )
