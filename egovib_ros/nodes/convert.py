"""ROS 2 message <-> numpy conversion for the nodes (imports rclpy message types).

Stamps are int64 nanoseconds, as in the core. The 3 kHz Imu and 1 kHz JointState streams
go as CDR bytes (published as bytes, subscribed with `raw=True`) and are decoded in batches
by egovib_ros.bag.codec. Joint names, the Imu field and frames come from the caller.
"""

from __future__ import annotations

from typing import Iterable, Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from std_msgs.msg import Float64MultiArray

from egovib_ros.bag.codec import decode_imu, decode_joint_states, joint_state_layout
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import StreamError


# --- stamps ------------------------------------------------------------------
def stamp_to_ns(stamp: Time) -> int:
    """builtin_interfaces/Time -> int nanoseconds."""
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_stamp(stamp_ns: int) -> Time:
    """int nanoseconds -> builtin_interfaces/Time."""
    sec, nanosec = divmod(int(stamp_ns), NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


# --- Imu ---------------------------------------------------------------------
def decode_imu_raws(
    raws: Sequence[bytes], field: str = "linear_acceleration"
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw Imu CDR messages -> (stamps_ns (n,), `field` values (n, 3), index (n,) of the
    decoded messages in `raws`). Undecodable messages are left out (len(raws) - n of
    them); non-finite values are kept: the core counts and handles them.

    Vectorised for the usual batch; a batch holding a bad message is decoded one by one
    so that only the bad messages are lost.
    """
    try:
        stamps, values = decode_imu(raws, field)
        return stamps, values, np.arange(len(raws))
    except Exception:  # noqa: BLE001 - any decoding failure: fall back to one by one
        pass
    stamps, values, index = [], [], []
    for i, raw in enumerate(raws):
        try:
            stamp, value = decode_imu([raw], field)
        except Exception:  # noqa: BLE001
            continue
        stamps.append(stamp[0])
        values.append(value[0])
        index.append(i)
    return (
        np.asarray(stamps, dtype=np.int64).reshape(-1),
        np.asarray(values, dtype=np.float64).reshape(-1, 3),
        np.asarray(index, dtype=np.int64),
    )


def decode_joint_state_raws(
    raws: Sequence[bytes], names: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Raw JointState CDR messages -> (stamps_ns, position (n, J), velocity (n, J), number
    of undecodable messages left out). Columns follow `names` (messages may list more
    joints, in any order); a joint a message lacks is NaN in its row."""
    try:
        stamps, position, velocity = decode_joint_states(raws, names)
        return stamps, position, velocity, 0
    except Exception:  # noqa: BLE001 - decode one by one, leaving out the bad ones
        pass
    parts = []
    for raw in raws:
        try:
            parts.append(decode_joint_states([raw], names))
        except Exception:  # noqa: BLE001
            continue
    if not parts:
        n = len(names)
        return np.zeros(0, np.int64), np.zeros((0, n)), np.zeros((0, n)), len(raws)
    return (
        np.concatenate([p[0] for p in parts]),
        np.concatenate([p[1] for p in parts]),
        np.concatenate([p[2] for p in parts]),
        len(raws) - len(parts),
    )


def joint_names_of(raw: bytes) -> tuple[str, ...]:
    """The joint names a serialised JointState carries (for error messages); () if undecodable."""
    try:
        return joint_state_layout(raw)[0]
    except Exception:  # noqa: BLE001
        return ()


# --- commands ------------------------------------------------------------------
def command_message(velocity: Sequence[float]) -> Float64MultiArray:
    """Joint velocity command, one value per joint (ros2_control forward-command convention)."""
    return Float64MultiArray(data=[float(v) for v in velocity])


def command_velocity(msg: Float64MultiArray, n_joints: int, topic: str = "commands") -> np.ndarray:
    """Float64MultiArray command -> velocity (J,); wrong length or non-finite raise StreamError."""
    values = np.asarray(msg.data, dtype=np.float64)
    if values.shape != (n_joints,) or not np.all(np.isfinite(values)):
        raise StreamError(f"{topic}: expected {n_joints} finite velocities, got {list(values)}")
    return values


# --- diagnostics ---------------------------------------------------------------
def diagnostic_array(
    stamp_ns: int,
    statuses: Iterable[tuple[str, str, str, Mapping[str, object]]],
    hardware_id: str = "",
) -> DiagnosticArray:
    """DiagnosticArray from (name, level 'ok'|'warn'|'error'|'stale', message, values) tuples."""
    array = DiagnosticArray()
    array.header.stamp = ns_to_stamp(max(int(stamp_ns), 0))
    for name, level, message, values in statuses:
        status = DiagnosticStatus(
            level=getattr(DiagnosticStatus, level.upper()),
            name=name,
            message=message,
            hardware_id=hardware_id,
        )
        status.values = [KeyValue(key=str(k), value=_format_value(v)) for k, v in values.items()]
        array.status.append(status)
    return array


def diagnostic_values(status: DiagnosticStatus) -> dict[str, str]:
    """KeyValue list of a DiagnosticStatus -> dict."""
    return {kv.key: kv.value for kv in status.values}


def _format_value(value: object, in_list: bool = False) -> str:
    """A diagnostic value as plain text: numbers as numbers (numpy's too: never
    "np.float64(0.0)"), lists and arrays as Python prints a list of such numbers."""
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, (float, np.floating)):
        return repr(float(value)) if in_list else f"{float(value):.6g}"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if not in_list and isinstance(value, (list, tuple, np.ndarray)):
        items = value.tolist() if isinstance(value, np.ndarray) else value
        return "[" + ", ".join(_format_value(v, in_list=True) for v in items) + "]"
    return repr(value) if in_list else str(value)
