"""ROS 2 message <-> numpy conversion, used by the nodes only (imports rclpy message types).

Stamps are int64 nanoseconds throughout, as in the core. The Imu stream runs at
3 kHz, one message per sample (CONTRACT section 2), so it has a fast path: batches
of samples are encoded to CDR bytes with numpy (rclpy's `Publisher.publish` takes
bytes) and raw CDR bytes are decoded with `struct`, skipping message objects.
"""
from __future__ import annotations

import struct
from typing import Iterable, Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray

from egovib_ros.constants import ACCEL_FRAME, JOINT_NAMES
from egovib_ros.errors import StreamError

_NS_PER_S = 1_000_000_000
_CDR_LE_HEADER = b"\x00\x01\x00\x00"
# Doubles of the Imu body after the header, in order: orientation (4), its
# covariance (9), angular_velocity (3), covariance (9), linear_acceleration (3),
# covariance (9). linear_acceleration starts at double 25.
_IMU_DOUBLES = 37
_IMU_ACCEL_DOUBLE = 25


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


def _imu_layout(frame_id: str) -> tuple[bytes, int, int]:
    """(template body, offset of first double, total length) of an Imu CDR message."""
    name = frame_id.encode() + b"\x00"
    body_prefix = 8 + 4 + len(name)                  # stamp + string length + string
    first_double = (body_prefix + 7) // 8 * 8        # CDR aligns doubles to 8 in the body
    total = 4 + first_double + 8 * _IMU_DOUBLES
    doubles = np.zeros(_IMU_DOUBLES)
    doubles[3] = 1.0                                 # orientation.w, rclpy's default
    doubles[4] = -1.0                                # orientation_covariance[0]
    doubles[13 + 3] = -1.0                           # angular_velocity_covariance[0]
    template = (_CDR_LE_HEADER + b"\x00" * 8 + struct.pack("<I", len(name)) + name
                + b"\x00" * (first_double - body_prefix) + doubles.astype("<f8").tobytes())
    assert len(template) == total
    return template, 4 + first_double, total


_LAYOUT_CACHE: dict[str, tuple[bytes, int, int]] = {}


def encode_imu_batch(stamps_ns: np.ndarray, accel: np.ndarray,
                     frame_id: str = ACCEL_FRAME) -> list[bytes]:
    """Serialise N samples to N Imu CDR messages (little-endian), vectorised.

    Equal, field by field, to `serialize_message(imu_message(...))`.
    """
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    accel = np.asarray(accel, dtype=np.float64).reshape(len(stamps_ns), 3)
    if frame_id not in _LAYOUT_CACHE:
        _LAYOUT_CACHE[frame_id] = _imu_layout(frame_id)
    template, accel_offset, size = _LAYOUT_CACHE[frame_id]
    count = len(stamps_ns)
    rows = np.tile(np.frombuffer(template, dtype=np.uint8), (count, 1))
    sec, nanosec = np.divmod(stamps_ns, _NS_PER_S)
    rows[:, 4:8] = sec.astype("<i4").view(np.uint8).reshape(count, 4)
    rows[:, 8:12] = nanosec.astype("<u4").view(np.uint8).reshape(count, 4)
    accel_at = accel_offset + 8 * _IMU_ACCEL_DOUBLE
    rows[:, accel_at:accel_at + 24] = accel.astype("<f8").view(np.uint8).reshape(count, 24)
    flat = rows.tobytes()
    return [flat[i * size:(i + 1) * size] for i in range(count)]


_UNPACK_STAMP = struct.Struct("<iII").unpack_from
_UNPACK_ACCEL = struct.Struct("<3d").unpack_from


def decode_imu(data: bytes, topic: str = "accelerometer/raw") -> tuple[int, tuple[float, float, float]]:
    """Raw Imu CDR bytes -> (stamp_ns, (ax, ay, az)). Raises StreamError on a bad message."""
    if data[:2] == _CDR_LE_HEADER[:2] and len(data) >= 16:
        sec, nanosec, name_len = _UNPACK_STAMP(data, 4)
        first_double = (12 + name_len + 7) // 8 * 8
        if len(data) == 4 + first_double + 8 * _IMU_DOUBLES:
            return sec * _NS_PER_S + nanosec, _UNPACK_ACCEL(data, 4 + first_double + 8 * _IMU_ACCEL_DOUBLE)
    try:  # other encodings (big-endian CDR): let rclpy do it
        msg = deserialize_message(bytes(data), Imu)
    except Exception as exc:  # noqa: BLE001 - any decoding failure is a bad message
        raise StreamError(f"{topic}: undecodable Imu message ({len(data)} bytes): {exc}") from None
    stamp_ns, accel = imu_sample(msg)
    return stamp_ns, tuple(accel)


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
