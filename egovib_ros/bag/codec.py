"""The one codec of the project's ROS messages: CDR bytes <-> numpy, no rclpy.

A 3 kHz stream is one ``sensor_msgs/msg/Imu`` per sample, ~900k messages per topic for
five minutes; going through rosbags' per-message (de)serialiser would take minutes. So
messages travel packed (`MessageBatch`: one byte buffer, offsets per message, what the
bag reader hands out per topic) and Imu and JointState are read and written with numpy on
their fixed CDR layout: every message of a batch has the same length and structure, only
stamps and numbers differ. Anything unusual (mixed frame_id lengths, big-endian CDR, other
joint sets) goes through rosbags per message and gives the same result.

Every decoder takes a MessageBatch or a sequence of serialised messages (the nodes' raw
subscriptions); `replace_imu_field` gives back the same kind. CDR here is what rclpy
produces: a 4-byte encapsulation header ``00 01 00 00`` (little-endian CDR), then the
body, aligned from the body's start.

Imu vectors: `field` is ``linear_acceleration`` or ``angular_velocity`` (a gyro), the
robot profile's ``sensor.field``. `replace_imu_field` writes cleaned values into copies of
the input messages, every other byte (header, frame, orientation, covariances, the other
vector) kept: the denoiser's drop-in output.
"""

from __future__ import annotations

import dataclasses
import struct
from dataclasses import dataclass
from functools import lru_cache
from typing import Sequence, Union

import numpy as np
from rosbags.serde import SerdeError
from rosbags.typesys import Stores, get_typestore

from egovib_ros.bag.mcapfile import gather, rows
from egovib_ros.core.timebase import NS_PER_S

IMU_TYPE = "sensor_msgs/msg/Imu"
JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
COMMANDS_TYPE = "std_msgs/msg/Float64MultiArray"
IMU_FIELDS = ("linear_acceleration", "angular_velocity")

CDR_LE_HEADER = b"\x00\x01\x00\x00"
# doubles between the end of the header and each vector: orientation (4) + its covariance (9)
# [+ angular_velocity (3) + its covariance (9)]
_FIELD_DOUBLES = {"angular_velocity": 13, "linear_acceleration": 25}


@lru_cache(maxsize=1)
def typestore():
    """The ROS 2 Jazzy typestore of rosbags (cached)."""
    return get_typestore(Stores.ROS2_JAZZY)


def deserialize(raw: bytes | memoryview, typename: str):
    """One message from its CDR bytes, read as a DDS reader reads it: bytes after the
    message are ignored. rclpy's serialize_message leaves 8 stray bytes after some
    JointStates (positions only), bags written with it (rosbag2_py) keep them, and
    rosbags' deserialize_cdr refuses more than 3 bytes of padding."""
    if len(raw) < 4 or bytes(raw[:2]) not in (b"\x00\x00", b"\x00\x01"):
        raise SerdeError(f"{typename}: invalid or unsupported CDR encapsulation")
    ts = typestore()
    msgdef = ts.get_msgdef(typename)
    read = msgdef.deserialize_cdr_le if raw[1] else msgdef.deserialize_cdr_be
    try:
        return read(memoryview(raw)[4:], 0, msgdef.cls, ts)[0]
    except (struct.error, UnicodeDecodeError, ValueError, IndexError) as exc:
        raise SerdeError(f"could not deserialize {typename}: {exc}") from exc


# --------------------------------------------------------------------------
# Packed messages
# --------------------------------------------------------------------------
@dataclass
class MessageBatch:
    """n serialised messages: message i is buf[starts[i]:starts[i] + lengths[i]]."""

    buf: np.ndarray  # uint8
    starts: np.ndarray  # (n,) int64
    lengths: np.ndarray  # (n,) int64
    log_times: np.ndarray  # (n,) int64, bag log time (receive time) of each message
    # (n, L) view of buf when the messages are L bytes each, back to back (from_matrix):
    # field reads are then column slices (a live node decodes a few messages 500 times a s)
    packed: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.starts)

    @classmethod
    def empty(cls) -> "MessageBatch":
        z = np.zeros(0, np.int64)
        return cls(np.zeros(0, np.uint8), z, z.copy(), z.copy())

    @classmethod
    def from_list(cls, datas: Sequence[bytes], log_times) -> "MessageBatch":
        if datas and len({len(d) for d in datas}) == 1:
            width = len(datas[0])
            matrix = np.frombuffer(b"".join(datas), np.uint8).reshape(len(datas), width)
            return cls.from_matrix(matrix, log_times)
        lengths = np.fromiter((len(d) for d in datas), np.int64, len(datas))
        starts = (
            np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
            if len(datas)
            else lengths
        )
        return cls(
            np.frombuffer(b"".join(datas), np.uint8),
            starts,
            lengths,
            np.asarray(log_times, np.int64),
        )

    @classmethod
    def concat(cls, batches: Sequence["MessageBatch"]) -> "MessageBatch":
        batches = [b for b in batches if len(b)]
        if not batches:
            return cls.empty()
        if len(batches) == 1:
            return batches[0]
        matrices = [b.matrix() for b in batches]
        times = np.concatenate([b.log_times for b in batches])
        if all(m is not None for m in matrices) and len({m.shape[1] for m in matrices}) == 1:
            return cls.from_matrix(np.concatenate(matrices), times)
        return cls.from_list([d for b in batches for d in b.to_list()], times)

    @classmethod
    def from_matrix(cls, matrix: np.ndarray, log_times) -> "MessageBatch":
        n, width = matrix.shape
        matrix = np.ascontiguousarray(matrix)
        return cls(
            matrix.reshape(-1),
            np.arange(n, dtype=np.int64) * width,
            np.full(n, width, np.int64),
            np.asarray(log_times, np.int64),
            packed=matrix if n and width else None,
        )

    @property
    def uniform_length(self) -> int | None:
        if len(self) == 0:
            return None
        if self.packed is not None:
            return self.packed.shape[1]
        first = int(self.lengths[0])
        return first if np.all(self.lengths == first) else None

    def matrix(self) -> np.ndarray | None:
        """(n, L) uint8 copy of the messages when all have the same length L, else None."""
        if self.packed is not None:
            return self.packed
        width = self.uniform_length
        if width is None:
            return None if len(self) else np.zeros((0, 0), np.uint8)
        if len(self) * width == len(self.buf) and np.array_equal(
            self.starts, np.arange(len(self)) * width
        ):
            return self.buf.reshape(len(self), width)
        return rows(self.buf, self.starts, width)

    def to_list(self) -> list[bytes]:
        raw = self.buf.tobytes()
        return [raw[s : s + n] for s, n in zip(self.starts.tolist(), self.lengths.tolist())]

    def take(self, index: np.ndarray) -> "MessageBatch":
        return MessageBatch(
            self.buf, self.starts[index], self.lengths[index], self.log_times[index]
        )

    def field(self, at: int, dtype) -> np.ndarray:
        """The value of `dtype` at byte `at` of every message (callers check the lengths)."""
        if self.packed is not None:
            dtype = np.dtype(dtype)
            return self.columns(at, dtype.itemsize).view(dtype).reshape(len(self))
        return gather(self.buf, self.starts + at, dtype)

    def columns(self, at: int, width: int) -> np.ndarray:
        """(n, width) copy of bytes at..at + width of every message (callers check the lengths)."""
        if self.packed is not None:
            return np.ascontiguousarray(self.packed[:, at : at + width])
        return rows(self.buf, self.starts + at, width)


# --------------------------------------------------------------------------
# CDR helpers
# --------------------------------------------------------------------------
def _align(offset: int, size: int) -> int:
    return (offset + size - 1) // size * size


def _split(buf: bytes, n: int, length: int) -> list[bytes]:
    """Cut a contiguous buffer of n equal messages into n bytes objects."""
    return [buf[i : i + length] for i in range(0, n * length, length)]


def _header(stamp_ns: int, frame_id: str):
    """A rosbags std_msgs/Header."""
    types = typestore().types
    stamp = types["builtin_interfaces/msg/Time"](
        sec=int(stamp_ns // NS_PER_S), nanosec=int(stamp_ns % NS_PER_S)
    )
    return types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def _stamp_fields(stamps_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    return stamps_ns // NS_PER_S, stamps_ns % NS_PER_S


# --------------------------------------------------------------------------
# Imu
# --------------------------------------------------------------------------
def _check_field(field: str) -> str:
    if field not in _FIELD_DOUBLES:
        raise ValueError(f"Imu field must be one of {IMU_FIELDS}, got {field!r}")
    return field


def imu_field_offset(frame_len: int, field: str = "linear_acceleration") -> int:
    """Byte offset (from message start) of `field`.x for a frame_id of given length."""
    body = _align(12 + frame_len + 1, 8)  # sec, nanosec, strlen, chars + NUL, then doubles
    return 4 + body + _FIELD_DOUBLES[_check_field(field)] * 8


def _imu_length(frame_len: int) -> int:
    return imu_field_offset(frame_len) + 12 * 8


@lru_cache(maxsize=32)
def _imu_dtype(frame_len: int, field: str = "linear_acceleration") -> np.dtype:
    return np.dtype(
        {
            "names": ["sec", "nanosec", "strlen", "vector"],
            "formats": ["<i4", "<u4", "<u4", ("<f8", 3)],
            "offsets": [4, 8, 12, imu_field_offset(frame_len, field)],
            "itemsize": _imu_length(frame_len),
        }
    )


def rosbags_imu(
    stamp_ns: int,
    xyz: Sequence[float],
    frame_id: str = "",
    field: str = "linear_acceleration",
):
    """A rosbags Imu object following REP 145 with `xyz` in `field`; the other vector is
    zero and marked unknown (covariance[0] = -1), as is the orientation."""
    ts = typestore()
    Imu, Quaternion, Vector3 = (
        ts.types[IMU_TYPE],
        ts.types["geometry_msgs/msg/Quaternion"],
        ts.types["geometry_msgs/msg/Vector3"],
    )
    unknown = np.zeros(9)
    unknown[0] = -1.0
    vectors = {name: Vector3(x=0.0, y=0.0, z=0.0) for name in IMU_FIELDS}
    vectors[_check_field(field)] = Vector3(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))
    return Imu(
        header=_header(stamp_ns, frame_id),
        orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=unknown.copy(),
        angular_velocity=vectors["angular_velocity"],
        angular_velocity_covariance=unknown.copy()
        if field == "linear_acceleration"
        else np.zeros(9),
        linear_acceleration=vectors["linear_acceleration"],
        linear_acceleration_covariance=np.zeros(9)
        if field == "linear_acceleration"
        else unknown.copy(),
    )


@lru_cache(maxsize=8)
def _imu_template(frame_id: str, field: str = "linear_acceleration") -> bytes:
    return bytes(
        typestore().serialize_cdr(rosbags_imu(0, (0.0, 0.0, 0.0), frame_id, field), IMU_TYPE)
    )


def encode_imu_batch(
    stamps_ns: np.ndarray,
    values: np.ndarray,
    frame_id: str = "",
    field: str = "linear_acceleration",
) -> list[bytes]:
    """Serialise one Imu per sample, `values` in `field`, to CDR bytes (identical to
    rclpy/rosbags serialisation of `rosbags_imu`)."""
    values = np.asarray(values, dtype=np.float64).reshape(-1, 3)
    n = len(values)
    if len(stamps_ns) != n:
        raise ValueError(f"encode_imu_batch: {len(stamps_ns)} stamps for {n} samples")
    template = _imu_template(frame_id, field)
    frame_len = len(frame_id.encode())
    # Work on a byte buffer: copying a structured array does not keep the gap bytes.
    buf = np.frombuffer(template * n, dtype=np.uint8).copy()
    arr = buf.view(_imu_dtype(frame_len, field))
    arr["sec"], arr["nanosec"] = _stamp_fields(stamps_ns)
    arr["vector"] = values
    return _split(buf.tobytes(), n, len(template))


def _decode_imu_slow(raw: bytes, field: str) -> tuple[int, np.ndarray]:
    msg = deserialize(raw, IMU_TYPE)
    v = getattr(msg, field)
    return msg.header.stamp.sec * NS_PER_S + msg.header.stamp.nanosec, np.array([v.x, v.y, v.z])


def imu_layout(batch: MessageBatch, field: str) -> int | None:
    """Byte offset of `field` when every message has the codec's fixed little-endian
    layout with one frame_id length, else None (use the per-message fallback)."""
    width = batch.uniform_length
    if width is None or width < 16:
        return None
    if not np.all(batch.field(0, "<u2") == 0x0100):  # CDR little-endian encapsulation
        return None
    strlen = batch.field(12, "<u4")
    frame_len = int(strlen[0]) - 1
    if frame_len < 0 or not np.all(strlen == strlen[0]):
        return None
    if imu_field_offset(frame_len, "linear_acceleration") + 12 * 8 != width:
        return None
    return imu_field_offset(frame_len, field)


def _vectors(batch: MessageBatch, offset: int) -> np.ndarray:
    return batch.columns(offset, 24).view("<f8").astype(np.float64)


Messages = Union["MessageBatch", Sequence[bytes]]


def as_batch(messages: Messages) -> "MessageBatch":
    """A MessageBatch of `messages` (itself, or packed from a sequence of bytes)."""
    if isinstance(messages, MessageBatch):
        return messages
    return MessageBatch.from_list([bytes(m) for m in messages], np.zeros(len(messages), np.int64))


def decode_imu(
    messages: Messages, field: str = "linear_acceleration"
) -> tuple[np.ndarray, np.ndarray]:
    """Header stamps (n,) int64 ns and the `field` vectors (n, 3) of Imu messages."""
    _check_field(field)
    batch = as_batch(messages)
    if len(batch) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    offset = imu_layout(batch, field)
    if offset is None:  # unusual messages: rosbags, one by one
        stamps = np.empty(len(batch), np.int64)
        values = np.empty((len(batch), 3))
        for i, raw in enumerate(batch.to_list()):
            stamps[i], values[i] = _decode_imu_slow(raw, field)
        return stamps, values
    stamps = batch.field(4, "<i4").astype(np.int64) * NS_PER_S + batch.field(8, "<u4").astype(
        np.int64
    )
    return stamps, _vectors(batch, offset)


def replace_imu_field(messages: Messages, values: np.ndarray, field: str = "linear_acceleration"):
    """Copies of Imu messages with `field` set to `values` (n, 3), every other byte kept
    (the drop-in output); a MessageBatch for a MessageBatch, else a list of bytes."""
    values = np.asarray(values, np.float64).reshape(-1, 3)
    batch = as_batch(messages)
    if len(values) != len(batch):
        raise ValueError(f"replace_imu_field: {len(values)} values for {len(batch)} messages")
    offset = imu_layout(batch, field) if len(batch) else None
    if offset is None:  # unusual messages: rosbags, one by one
        ts = typestore()
        out = []
        for raw, xyz in zip(batch.to_list(), values):
            msg = deserialize(raw, IMU_TYPE)
            vector = getattr(msg, field)
            vector.x, vector.y, vector.z = (float(v) for v in xyz)
            out.append(bytes(ts.serialize_cdr(msg, IMU_TYPE)))
        result = MessageBatch.from_list(out, batch.log_times)
    else:
        matrix = np.array(batch.matrix())  # a copy: the input stays as it was
        packed = np.ascontiguousarray(values, "<f8").view(np.uint8).reshape(-1, 24)
        matrix[:, offset : offset + 24] = packed
        result = MessageBatch.from_matrix(matrix, batch.log_times)
    return result if isinstance(messages, MessageBatch) else result.to_list()


# --------------------------------------------------------------------------
# JointState
# --------------------------------------------------------------------------
def rosbags_joint_state(
    stamp_ns: int, names: Sequence[str], position, velocity, frame_id: str = ""
):
    """A rosbags JointState object (no effort)."""
    return typestore().types[JOINT_STATE_TYPE](
        header=_header(stamp_ns, frame_id),
        name=list(names),
        position=np.asarray(position, np.float64),
        velocity=np.asarray(velocity, np.float64),
        effort=np.zeros(0),
    )


def joint_state_layout(raw: bytes) -> tuple[tuple[str, ...], int, int, int, int, int]:
    """Walk the CDR of one JointState:
    (names, pos_offset, n_pos, vel_offset, n_vel, effort_count_offset).

    Offsets are counted from the message start (4-byte encapsulation header included).
    """

    def u32(body_off: int) -> int:
        return struct.unpack_from("<I", raw, 4 + body_off)[0]

    off = 8
    off = 12 + u32(off)  # frame_id string
    off = _align(off, 4)
    n_names = u32(off)
    off += 4
    names = []
    for _ in range(n_names):
        off = _align(off, 4)
        slen = u32(off)
        names.append(raw[4 + off + 4 : 4 + off + 4 + slen - 1].decode())
        off += 4 + slen
    seqs = []
    for _ in range(2):  # position, velocity
        off = _align(off, 4)
        count = u32(off)
        off += 4
        if count:
            off = _align(off, 8)
        seqs.append((4 + off, count))
        off += 8 * count
    off = _align(off, 4)
    return tuple(names), seqs[0][0], seqs[0][1], seqs[1][0], seqs[1][1], 4 + off


def encode_joint_state_batch(
    stamps_ns: np.ndarray,
    position: np.ndarray,
    velocity: np.ndarray | None,
    names: Sequence[str],
) -> list[bytes]:
    """Serialise one JointState (name, position, velocity; no effort) per row to CDR bytes.
    `velocity` None: an empty velocity field, as drivers that publish positions only."""
    if len(stamps_ns) == 0:
        return []
    position = np.asarray(position, np.float64).reshape(len(stamps_ns), -1)
    n, n_joints = position.shape
    n_velocity = n_joints if velocity is not None else 0
    template = bytes(
        typestore().serialize_cdr(
            rosbags_joint_state(0, names, np.zeros(n_joints), np.zeros(n_velocity)),
            JOINT_STATE_TYPE,
        )
    )
    _, pos_off, _, vel_off, _, _ = joint_state_layout(template)
    fields = {"sec": ("<i4", 4), "nanosec": ("<u4", 8), "pos": (("<f8", n_joints), pos_off)}
    if velocity is not None:
        fields["vel"] = (("<f8", n_joints), vel_off)
    dtype = np.dtype(
        {
            "names": list(fields),
            "formats": [f for f, _ in fields.values()],
            "offsets": [o for _, o in fields.values()],
            "itemsize": len(template),
        }
    )
    buf = np.frombuffer(template * n, dtype=np.uint8).copy()
    arr = buf.view(dtype)
    arr["sec"], arr["nanosec"] = _stamp_fields(stamps_ns)
    arr["pos"] = position
    if velocity is not None:
        arr["vel"] = np.asarray(velocity, np.float64).reshape(n, n_joints)
    return _split(buf.tobytes(), n, len(template))


def decode_joint_states(
    messages: Messages, names: Sequence[str] | None = None, notes: dict | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps (n,), positions and velocities (n, J) with columns picked by joint name
    (`names`; default the first message's joints), NaN where a message lacks a joint or
    a value (a driver that publishes no velocity gives NaN velocities).

    `notes` (a dict, updated): "named" (J,) bool, the joints some message names (with or
    without a value: effort only); "short_position" / "short_velocity", how many messages
    carry fewer values than names (neither empty nor one per name: malformed)."""
    batch = as_batch(messages)
    n = len(batch)
    if n == 0:
        k = len(names) if names is not None else 0
        return np.zeros(0, np.int64), np.zeros((0, k)), np.zeros((0, k))
    if names is None:
        names = joint_state_layout(batch.to_list()[0])[0]
    names = tuple(names)
    fast = _joint_states_fast(batch, names)
    if notes is not None:
        named = notes.setdefault("named", np.zeros(len(names), bool))
    if fast is not None:
        if notes is not None:
            named[:] = True  # every named joint, one value each (the fast path's condition)
        return fast
    raws = batch.to_list()
    # Unusual batch: rosbags per message, columns matched by joint name.
    stamps = np.empty(n, np.int64)
    position = np.full((n, len(names)), np.nan)
    velocity = np.full((n, len(names)), np.nan)
    column = {name: j for j, name in enumerate(names)}
    for i, raw in enumerate(raws):
        msg = deserialize(raw, JOINT_STATE_TYPE)
        stamps[i] = msg.header.stamp.sec * NS_PER_S + msg.header.stamp.nanosec
        taken = set()
        if notes is not None:
            for key, values in (("short_position", msg.position), ("short_velocity", msg.velocity)):
                if 0 < len(values) < len(msg.name):
                    notes[key] = notes.get(key, 0) + 1
        for k, name in enumerate(msg.name):
            j = column.get(name)
            if j is None or j in taken:  # a name given twice: its first values, as the fast path
                continue
            taken.add(j)
            if notes is not None:
                named[j] = True
            if k < len(msg.position):
                position[i, j] = msg.position[k]
            if k < len(msg.velocity):
                velocity[i, j] = msg.velocity[k]
    return stamps, position, velocity


def _joint_states_fast(batch: MessageBatch, names: tuple[str, ...]):
    """The codec's fast path on packed messages: every message has the first one's length
    and structure (frame, joint names, array sizes), only stamps and numbers differ."""
    width = batch.uniform_length
    if width is None:
        return None
    start = int(batch.starts[0])
    first = batch.buf[start : start + width].tobytes()
    if first[:2] != CDR_LE_HEADER[:2]:
        return None
    layout = _joint_columns(first, names)
    if layout is None:
        return None
    pos_off, vel_off, n_joints, columns = layout
    structure = batch.columns(12, pos_off - 12)  # frame_id, names, position count
    counts = batch.field(vel_off - 8, "<u8")  # velocity count (and its alignment)
    if not (np.all(structure == structure[0]) and np.all(counts == counts[0])):
        return None
    stamps = batch.field(4, "<i4").astype(np.int64) * NS_PER_S + batch.field(8, "<u4").astype(
        np.int64
    )
    position = batch.columns(pos_off, 8 * n_joints).view("<f8")[:, columns].astype(np.float64)
    velocity = batch.columns(vel_off, 8 * n_joints).view("<f8")[:, columns].astype(np.float64)
    return stamps, position, velocity


# The last layout walked: a live node decodes messages of one structure 1000 times a second.
_last_joint_columns: list = [None]


def _joint_columns(first: bytes, names: tuple[str, ...]):
    """(position offset, velocity offset, joints, columns of `names`) of JointStates laid
    out as `first`, or None when the fast path does not apply (a named joint missing,
    arrays not one value per joint, unparsable)."""
    cached = _last_joint_columns[0]
    if cached is not None:
        width, head, count, wanted, layout = cached
        pos_off, vel_off = layout[0], layout[1]
        if (
            width == len(first)
            and wanted == names
            and first[12:pos_off] == head
            and first[vel_off - 8 : vel_off] == count
        ):
            return layout
    try:
        msg_names, pos_off, n_pos, vel_off, n_vel, _ = joint_state_layout(first)
    except Exception:
        return None
    if not set(names) <= set(msg_names) or not n_pos == n_vel == len(msg_names):
        return None
    layout = (pos_off, vel_off, n_pos, [msg_names.index(n) for n in names])
    _last_joint_columns[0] = (
        len(first),
        first[12:pos_off],
        first[vel_off - 8 : vel_off],
        names,
        layout,
    )
    return layout


# --------------------------------------------------------------------------
# Float64MultiArray commands
# --------------------------------------------------------------------------
def encode_commands(values: Sequence[float]) -> bytes:
    """Serialise one ``[wrist rad/s, gripper m/s]`` Float64MultiArray command."""
    ts = typestore()
    msg = ts.types[COMMANDS_TYPE](
        layout=ts.types["std_msgs/msg/MultiArrayLayout"](dim=[], data_offset=0),
        data=np.asarray(values, np.float64),
    )
    return bytes(ts.serialize_cdr(msg, COMMANDS_TYPE))


def decode_commands(raw: bytes) -> np.ndarray:
    """The data array of a serialised Float64MultiArray."""
    return np.asarray(deserialize(raw, COMMANDS_TYPE).data, np.float64)
