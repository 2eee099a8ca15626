"""The one codec of the project's ROS messages: CDR bytes <-> numpy, no rclpy.

A 3 kHz stream is one ``sensor_msgs/msg/Imu`` per sample: rosbags' per-message
(de)serialiser would take minutes per recording. So messages travel packed (`MessageBatch`:
one byte buffer, offsets per message) and Imu and JointState are read and written with
numpy on their fixed CDR layout (little-endian, as rclpy produces: header ``00 01 00 00``,
body aligned from its start). Anything unusual (mixed frame_id lengths, big-endian CDR,
other joint sets) goes through rosbags per message and gives the same result.

Decoders take a MessageBatch or a sequence of serialised messages (the nodes' raw
subscriptions). The Imu `field` is the profile's ``sensor.field``: ``linear_acceleration``
or ``angular_velocity`` (a gyro).
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

from egovib_ros.bag.mcapfile import rows
from egovib_ros.core.timebase import NS_PER_S

IMU_TYPE = "sensor_msgs/msg/Imu"
JOINT_STATE_TYPE = "sensor_msgs/msg/JointState"
COMMANDS_TYPE = "std_msgs/msg/Float64MultiArray"
IMU_FIELDS = ("linear_acceleration", "angular_velocity")
# doubles between the end of the header and each vector: orientation (4) + its covariance (9)
# [+ angular_velocity (3) + its covariance (9)]
_FIELD_DOUBLES = {"angular_velocity": 13, "linear_acceleration": 25}
_HEADER_STAMP = (("sec", "<i4", 4), ("nanosec", "<u4", 8))  # std_msgs/Header's, after the CDR's


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


@dataclass
class MessageBatch:
    """n serialised messages: message i is buf[starts[i]:starts[i] + lengths[i]]."""

    buf: np.ndarray  # uint8
    starts: np.ndarray  # (n,) int64
    lengths: np.ndarray  # (n,) int64
    log_times: np.ndarray  # (n,) int64, bag log time (receive time) of each message
    # (n, L) view of buf when the messages are L bytes each, back to back (from_matrix)
    packed: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.starts)

    @classmethod
    def from_list(cls, datas: Sequence[bytes], log_times) -> "MessageBatch":
        if datas and len({len(d) for d in datas}) == 1:
            matrix = np.frombuffer(b"".join(datas), np.uint8).reshape(len(datas), len(datas[0]))
            return cls.from_matrix(matrix, log_times)
        lengths = np.fromiter((len(d) for d in datas), np.int64, len(datas))
        buf = np.frombuffer(b"".join(datas), np.uint8)
        return cls(buf, np.cumsum(lengths) - lengths, lengths, np.asarray(log_times, np.int64))

    @classmethod
    def concat(cls, batches: Sequence["MessageBatch"]) -> "MessageBatch":
        batches = [b for b in batches if len(b)]
        if len(batches) <= 1:
            return batches[0] if batches else cls.from_list([], [])
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


Messages = Union[MessageBatch, Sequence[bytes]]


def as_batch(messages: Messages) -> MessageBatch:
    """A MessageBatch of `messages` (itself, or packed from a sequence of bytes)."""
    if isinstance(messages, MessageBatch):
        return messages
    return MessageBatch.from_list([bytes(m) for m in messages], np.zeros(len(messages), np.int64))


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


@lru_cache(maxsize=32)
def _record_dtype(fields: tuple, itemsize: int) -> np.dtype:
    names, formats, offsets = zip(*fields)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": itemsize})


def _templated(template: bytes, stamps_ns, fields: tuple, *values: np.ndarray) -> list[bytes]:
    """Copies of `template` (a message that starts with a std_msgs/Header), one per stamp,
    with its header stamp and `fields` ((name, format, offset), ...) set to `values` (the
    copies are a byte buffer: a structured array's copy would not keep the gap bytes)."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    n = len(stamps_ns)
    buf = np.frombuffer(template * n, dtype=np.uint8).copy()
    arr = buf.view(_record_dtype(_HEADER_STAMP + fields, len(template)))
    arr["sec"], arr["nanosec"] = stamps_ns // NS_PER_S, stamps_ns % NS_PER_S
    for (name, _, _), value in zip(fields, values):
        arr[name] = value
    return _split(buf.tobytes(), n, len(template))


# --- Imu ----------------------------------------------------------------------------------
def _check_field(field: str) -> str:
    if field not in _FIELD_DOUBLES:
        raise ValueError(f"Imu field must be one of {IMU_FIELDS}, got {field!r}")
    return field


def imu_field_offset(frame_len: int, field: str = "linear_acceleration") -> int:
    """Byte offset (from message start) of `field`.x for a frame_id of given length."""
    body = _align(12 + frame_len + 1, 8)  # sec, nanosec, strlen, chars + NUL, then doubles
    return 4 + body + _FIELD_DOUBLES[_check_field(field)] * 8


def rosbags_imu(
    stamp_ns: int,
    xyz: Sequence[float],
    frame_id: str = "",
    field: str = "linear_acceleration",
):
    """A rosbags Imu object following REP 145 with `xyz` in `field`; the other vector is
    zero and marked unknown (covariance[0] = -1), as is the orientation."""
    types = typestore().types
    vector = types["geometry_msgs/msg/Vector3"]
    unknown = np.zeros(9)
    unknown[0] = -1.0
    vectors = {}
    for name in IMU_FIELDS:
        mine = name == _check_field(field)
        x, y, z = (float(xyz[i]) if mine else 0.0 for i in range(3))
        vectors[name] = vector(x=x, y=y, z=z)
        vectors[f"{name}_covariance"] = np.zeros(9) if mine else unknown.copy()
    return types[IMU_TYPE](
        header=_header(stamp_ns, frame_id),
        orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=unknown.copy(),
        **vectors,
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
    if len(stamps_ns) != len(values):
        raise ValueError(f"encode_imu_batch: {len(stamps_ns)} stamps for {len(values)} samples")
    vector = ("vector", ("<f8", 3), imu_field_offset(len(frame_id.encode()), field))
    return _templated(_imu_template(frame_id, field), stamps_ns, (vector,), values)


def imu_layout(batch: MessageBatch, field: str) -> int | None:
    """Byte offset of `field` when every message has the codec's fixed little-endian
    layout with one frame_id length, else None (use the per-message fallback)."""
    records = _imu_records(batch, field)
    return None if records is None else records.dtype.fields["vector"][1]


def _back_to_back(messages: Messages) -> tuple[object, int, int] | None:
    """(buffer, n, width): the messages back to back, each `width` bytes (the usual
    stream: one driver, one frame_id), or None."""
    if not len(messages):
        return None
    if isinstance(messages, MessageBatch):
        matrix = messages.matrix()
        return None if matrix is None else (matrix.reshape(-1), *matrix.shape)
        return None
    width = len(messages[0])
    buf = b"".join(messages)
    return (buf, len(messages), width) if len(buf) == len(messages) * width else None


def _imu_records(messages: Messages, field: str, *, writable: bool = False):
    """The messages as records ("sec", "nanosec", "vector": `field`) when they lie back to
    back with the codec's fixed little-endian layout and one frame_id, else None. Without
    a MessageBatch's bookkeeping: a live node decodes a few messages 500 times a second.
    `writable`: records over a copy of the bytes, to change."""
    packed = _back_to_back(messages)
    if packed is None:
        return None
    buf, n, width = packed
    if width < 16:
        return None
    frame_len = int.from_bytes(bytes(buf[12:16]), "little") - 1
    if frame_len < 0 or imu_field_offset(frame_len) + 12 * 8 != width:
        return None
    fields = (
        ("encapsulation", "<u2", 0),
        *_HEADER_STAMP,
        ("frame_length", "<u4", 12),
        ("vector", ("<f8", 3), imu_field_offset(frame_len, field)),
    )
    records = np.frombuffer(bytearray(buf) if writable else buf, _record_dtype(fields, width))
    if (records["encapsulation"] == 0x0100).all() and (
        records["frame_length"] == frame_len + 1
    ).all():
        return records
    return None


def _record_stamps(records: np.ndarray) -> np.ndarray:
    return records["sec"].astype(np.int64) * NS_PER_S + records["nanosec"]


def decode_imu(
    messages: Messages, field: str = "linear_acceleration"
) -> tuple[np.ndarray, np.ndarray]:
    """Header stamps (n,) int64 ns and the `field` vectors (n, 3) of Imu messages."""
    records = _imu_records(messages, _check_field(field))
    if records is not None:
        return _record_stamps(records), records["vector"].astype(np.float64)
    batch = as_batch(messages)
    stamps = np.empty(len(batch), np.int64)  # unusual messages: rosbags, one by one
    values = np.empty((len(batch), 3))
    for i, raw in enumerate(batch.to_list()):
        msg = deserialize(raw, IMU_TYPE)
        v = getattr(msg, field)
        stamps[i] = msg.header.stamp.sec * NS_PER_S + msg.header.stamp.nanosec
        values[i] = np.array([v.x, v.y, v.z])
    return stamps, values


def replace_imu_field(messages: Messages, values: np.ndarray, field: str = "linear_acceleration"):
    """Copies of Imu messages with `field` set to `values` (n, 3), every other byte kept
    (the denoiser's drop-in output); a MessageBatch for a MessageBatch, else a list of bytes."""
    values = np.asarray(values, np.float64).reshape(-1, 3)
    if len(values) != len(messages):
        raise ValueError(f"replace_imu_field: {len(values)} values for {len(messages)} messages")
    records = _imu_records(messages, _check_field(field), writable=True)
    if records is not None:
        records["vector"] = values
        if isinstance(messages, MessageBatch):
            return MessageBatch.from_matrix(
                records.view(np.uint8).reshape(len(records), -1), messages.log_times
            )
        return _split(records.tobytes(), len(records), records.itemsize)
    batch = as_batch(messages)
    ts = typestore()
    out = []
    for raw, xyz in zip(batch.to_list(), values):
        msg = deserialize(raw, IMU_TYPE)
        vector = getattr(msg, field)
        vector.x, vector.y, vector.z = (float(v) for v in xyz)
        out.append(bytes(ts.serialize_cdr(msg, IMU_TYPE)))
    result = MessageBatch.from_list(out, batch.log_times)
    return result if isinstance(messages, MessageBatch) else result.to_list()


# --- JointState ---------------------------------------------------------------------------
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

    off = _align(12 + u32(8), 4)  # after the stamp and the frame_id string
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


@lru_cache(maxsize=8)
def _joint_state_template(
    names: tuple[str, ...], n_joints: int, n_velocity: int
) -> tuple[bytes, int, int]:
    """A JointState of `names` with zero arrays and its position and velocity offsets."""
    template = bytes(
        typestore().serialize_cdr(
            rosbags_joint_state(0, names, np.zeros(n_joints), np.zeros(n_velocity)),
            JOINT_STATE_TYPE,
        )
    )
    _, pos_off, _, vel_off, _, _ = joint_state_layout(template)
    return template, pos_off, vel_off


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
    template, pos_off, vel_off = _joint_state_template(
        tuple(names), n_joints, n_joints if velocity is not None else 0
    )
    fields, values = (("pos", ("<f8", n_joints), pos_off),), [position]
    if velocity is not None:
        fields += (("vel", ("<f8", n_joints), vel_off),)
        values.append(np.asarray(velocity, np.float64).reshape(n, n_joints))
    return _templated(template, stamps_ns, fields, *values)


def decode_joint_states(
    messages: Messages, names: Sequence[str] | None = None, notes: dict | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps (n,), positions and velocities (n, J) with columns picked by joint name
    (`names`; default the first message's joints), NaN where a message lacks a joint or
    a value (a driver that publishes no velocity gives NaN velocities).

    `notes` (a dict, updated): "named" (J,) bool, the joints some message names (with or
    without a value: effort only); "short_position" / "short_velocity", how many messages
    carry fewer values than names (neither empty nor one per name: malformed); "repeated",
    how many times a message names one of `names` again (its first values are used)."""
    n = len(messages)
    if n == 0:
        k = len(names) if names is not None else 0
        return np.zeros(0, np.int64), np.zeros((0, k)), np.zeros((0, k))
    if names is None:
        first = messages.to_list()[0] if isinstance(messages, MessageBatch) else messages[0]
        names = joint_state_layout(bytes(first))[0]
    names = tuple(names)
    notes = {} if notes is None else notes
    named = notes.setdefault("named", np.zeros(len(names), bool))
    fast = _joint_states_fast(messages, names)
    if fast is not None:
        named[:] = True  # every named joint, one value each (the fast path's condition)
        return fast
    batch = as_batch(messages)
    # Unusual batch: rosbags per message, columns matched by joint name.
    stamps = np.empty(n, np.int64)
    position = np.full((n, len(names)), np.nan)
    velocity = np.full((n, len(names)), np.nan)
    column = {name: j for j, name in enumerate(names)}
    for i, raw in enumerate(batch.to_list()):
        msg = deserialize(raw, JOINT_STATE_TYPE)
        stamps[i] = msg.header.stamp.sec * NS_PER_S + msg.header.stamp.nanosec
        for key, values in (("short_position", msg.position), ("short_velocity", msg.velocity)):
            if 0 < len(values) < len(msg.name):
                notes[key] = notes.get(key, 0) + 1
        taken = set()
        for k, name in enumerate(msg.name):
            j = column.get(name)
            if j is not None and j in taken:  # a name given twice: its first values
                notes["repeated"] = notes.get("repeated", 0) + 1
            if j is None or j in taken:
                continue
            taken.add(j)
            named[j] = True
            if k < len(msg.position):
                position[i, j] = msg.position[k]
            if k < len(msg.velocity):
                velocity[i, j] = msg.velocity[k]
    return stamps, position, velocity


def _joint_states_fast(messages: Messages, names: tuple[str, ...]):
    """The codec's fast path on messages back to back: every message has the first one's
    length and structure (frame, joint names, array sizes), only stamps and numbers differ."""
    packed = _back_to_back(messages)
    if packed is None:
        return None
    buf, _, width = packed
    first = bytes(buf[:width])
    layout = _joint_columns(first, names) if first[:2] == b"\x00\x01" else None
    if layout is None:
        return None
    pos_off, vel_off, n_joints, columns = layout
    fields = (
        *_HEADER_STAMP,
        ("structure", f"V{pos_off - 12}", 12),  # frame_id, names, position count
        ("velocity_count", "<u8", vel_off - 8),  # (and its alignment)
        ("position", ("<f8", n_joints), pos_off),
        ("velocity", ("<f8", n_joints), vel_off),
    )
    records = np.frombuffer(buf, _record_dtype(fields, width))
    if not (
        (records["structure"] == records["structure"][0]).all()
        and (records["velocity_count"] == records["velocity_count"][0]).all()
    ):
        return None
    position = records["position"][:, columns].astype(np.float64)
    return _record_stamps(records), position, records["velocity"][:, columns].astype(np.float64)


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
    if any(msg_names.count(n) > 1 for n in names):  # the slow path counts the repeats
        return None
    layout = (pos_off, vel_off, n_pos, [msg_names.index(n) for n in names])
    head, count = first[12:pos_off], first[vel_off - 8 : vel_off]
    _last_joint_columns[0] = (len(first), head, count, names, layout)
    return layout


# --- Float64MultiArray commands -----------------------------------------------------------
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
