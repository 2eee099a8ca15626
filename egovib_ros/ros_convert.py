"""ROS 2 message <-> numpy conversion, used by the nodes only (imports rclpy message types).

Stamps are int64 nanoseconds throughout, as in the core. The 3 kHz Imu and 1 kHz
JointState streams have a fast path: nodes publish CDR bytes (rclpy's
`Publisher.publish` takes bytes) and subscribe with `raw=True`, collecting bytes and
decoding them in batches with the vectorised codec of egovib_ros.cdr.
"""
from __future__ import annotations

from typing import Iterable, Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray

from egovib_ros.cdr import (decode_imu_batch, decode_joint_state_batch,  # noqa: F401 (re-exported)
                              encode_imu_batch, encode_joint_state_batch)
from egovib_ros.constants import ACCEL_FRAME, JOINT_NAMES
from egovib_ros.errors import StreamError

_NS_PER_S = 1_000_000_000


# --- stamps ------------------------------------------------------------------
def stamp_to_ns(stamp: Time) -> int:
    """builtin_interfaces/Time -> int nanoseconds."""
    return int(stamp.sec) * _NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(stamp_ns: int) -> Time:
    """int nanoseconds -> builtin_interfaces/Time."""
    sec, nanosec = divmod(int(stamp_ns), _NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


# --- Imu ---------------------------------------------------------------------
def imu_message(stamp_ns: int, accel: Sequence[float], frame_id: str = ACCEL_FRAME) -> Imu:
    """One accelerometer sample as an Imu message (REP 145: orientation and
    angular velocity unknown, covariance[0] = -1)."""
    msg = Imu()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.orientation_covariance[0] = -1.0
    msg.angular_velocity_covariance[0] = -1.0
    msg.linear_acceleration.x = float(accel[0])
    msg.linear_acceleration.y = float(accel[1])
    msg.linear_acceleration.z = float(accel[2])
    return msg


def imu_sample(msg: Imu) -> tuple[int, np.ndarray]:
    """Imu message -> (stamp_ns, accel (3,))."""
    acc = msg.linear_acceleration
    return stamp_to_ns(msg.header.stamp), np.array([acc.x, acc.y, acc.z])


def decode_imu_messages(raws: list[bytes], topic: str = "accelerometer/raw"
                        ) -> tuple[np.ndarray, np.ndarray, int]:
    """Raw Imu CDR messages -> (stamps_ns (n,), accel (n, 3), number of undecodable messages dropped).

    Vectorised (egovib_ros.bagio) for the usual batch; a batch holding a bad message is
    decoded one by one so that only the bad messages are dropped.
    """
    try:
        stamps, accel = decode_imu_batch(raws)
        if np.all(np.isfinite(accel)):
            return stamps, accel, 0
    except Exception:  # noqa: BLE001 - any decoding failure: fall back to one by one
        pass
    good_stamps, good_accel = [], []
    for raw in raws:
        try:
            stamp, values = decode_imu_batch([raw])
        except Exception:  # noqa: BLE001
            continue
        if np.all(np.isfinite(values)):
            good_stamps.append(stamp[0])
            good_accel.append(values[0])
    n_bad = len(raws) - len(good_stamps)
    return (np.asarray(good_stamps, dtype=np.int64).reshape(-1),
            np.asarray(good_accel, dtype=np.float64).reshape(-1, 3), n_bad)


def decode_joint_state_messages(raws: list[bytes], names: Sequence[str] = JOINT_NAMES
                                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Raw JointState CDR messages -> (stamps_ns, position (n, J), velocity (n, J), n dropped).

    Columns follow `names` (messages may list more joints in any order); messages
    that cannot be decoded or lack a finite position/velocity of a joint are dropped.
    """
    try:
        stamps, position, velocity, _ = decode_joint_state_batch(raws, names=names)
    except Exception:  # noqa: BLE001 - decode one by one, dropping the bad ones
        parts = []
        for raw in raws:
            try:
                parts.append(decode_joint_state_batch([raw], names=names)[:3])
            except Exception:  # noqa: BLE001
                continue
        if not parts:
            n = len(names)
            return np.zeros(0, np.int64), np.zeros((0, n)), np.zeros((0, n)), len(raws)
        stamps = np.concatenate([p[0] for p in parts])
        position = np.concatenate([p[1] for p in parts])
        velocity = np.concatenate([p[2] for p in parts])
    good = np.all(np.isfinite(position), axis=1) & np.all(np.isfinite(velocity), axis=1)
    n_bad = len(raws) - int(good.sum())
    if n_bad:
        stamps, position, velocity = stamps[good], position[good], velocity[good]
    return stamps, position, velocity, n_bad


# --- JointState ----------------------------------------------------------------
def joint_state_message(stamp_ns: int, position: Sequence[float], velocity: Sequence[float],
                        names: Sequence[str] = JOINT_NAMES) -> JointState:
    """Joint positions and velocities (joint order of `names`) as a JointState."""
    msg = JointState()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.name = list(names)
    msg.position = [float(p) for p in position]
    msg.velocity = [float(v) for v in velocity]
    return msg


def joint_state_arrays(msg: JointState, names: Sequence[str] = JOINT_NAMES,
                       topic: str = "joint_states") -> tuple[int, np.ndarray, np.ndarray]:
    """JointState -> (stamp_ns, position (J,), velocity (J,)) in the order of `names`.

    Messages may list more joints, in any order; missing joints or velocities raise StreamError.
    """
    msg_names = list(msg.name)
    try:
        index = [msg_names.index(name) for name in names]
    except ValueError:
        missing = sorted(set(names) - set(msg_names))
        raise StreamError(f"{topic}: joint state lacks joints {missing}") from None
    if len(msg.velocity) != len(msg_names) or len(msg.position) != len(msg_names):
        raise StreamError(f"{topic}: joint state has {len(msg_names)} names but "
                          f"{len(msg.position)} positions and {len(msg.velocity)} velocities")
    position = np.asarray(msg.position, dtype=np.float64)[index]
    velocity = np.asarray(msg.velocity, dtype=np.float64)[index]
    if not (np.all(np.isfinite(velocity)) and np.all(np.isfinite(position))):
        raise StreamError(f"{topic}: joint state holds non-finite values")
    return stamp_to_ns(msg.header.stamp), position, velocity


# --- commands ------------------------------------------------------------------
def command_message(velocity: Sequence[float]) -> Float64MultiArray:
    """Joint velocity command `[wrist rad/s, gripper m/s]` (forward-command convention)."""
    return Float64MultiArray(data=[float(v) for v in velocity])


def command_velocity(msg: Float64MultiArray, n_joints: int = len(JOINT_NAMES),
                     topic: str = "hand_velocity_controller/commands") -> np.ndarray:
    """Float64MultiArray command -> velocity (J,); wrong length or non-finite raise StreamError."""
    values = np.asarray(msg.data, dtype=np.float64)
    if values.shape != (n_joints,) or not np.all(np.isfinite(values)):
        raise StreamError(f"{topic}: expected {n_joints} finite velocities, got {list(values)}")
    return values


# --- diagnostics ---------------------------------------------------------------
LEVELS = {"ok": DiagnosticStatus.OK, "warn": DiagnosticStatus.WARN,
          "error": DiagnosticStatus.ERROR, "stale": DiagnosticStatus.STALE}


def diagnostic_array(stamp_ns: int, statuses: Iterable[tuple[str, str, str, Mapping[str, object]]],
                     hardware_id: str = "r_gripper_motor_accelerometer") -> DiagnosticArray:
    """DiagnosticArray from (name, level 'ok'|'warn'|'error'|'stale', message, values) tuples."""
    array = DiagnosticArray()
    array.header.stamp = ns_to_stamp(stamp_ns)
    for name, level, message, values in statuses:
        status = DiagnosticStatus(level=LEVELS[level], name=name, message=message,
                                  hardware_id=hardware_id)
        status.values = [KeyValue(key=str(k), value=_format_value(v)) for k, v in values.items()]
        array.status.append(status)
    return array


def diagnostic_values(status: DiagnosticStatus) -> dict[str, str]:
    """KeyValue list of a DiagnosticStatus -> dict."""
    return {kv.key: kv.value for kv in status.values}


def _format_value(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)
