"""Serialised messages of one topic, packed: one byte buffer plus per-message offsets.

A `MessageBatch` is what the bag reader hands out per topic: no Python object per
message. Imu messages are decoded (and their vector replaced) with numpy on the
fixed CDR layout of `egovib_ros.cdr`; anything unusual goes through the codec's
per-message fallback, which gives the same result.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from egovib_ros import cdr
from egovib_ros.bag.mcapfile import gather, rows

_NS = 1_000_000_000


@dataclass
class MessageBatch:
    """n serialised messages: message i is buf[starts[i]:starts[i] + lengths[i]]."""

    buf: np.ndarray  # uint8
    starts: np.ndarray  # (n,) int64
    lengths: np.ndarray  # (n,) int64
    log_times: np.ndarray  # (n,) int64, bag log time (receive time) of each message

    def __len__(self) -> int:
        return len(self.starts)

    @classmethod
    def empty(cls) -> "MessageBatch":
        z = np.zeros(0, np.int64)
        return cls(np.zeros(0, np.uint8), z, z.copy(), z.copy())

    @classmethod
    def from_list(cls, datas: Sequence[bytes], log_times) -> "MessageBatch":
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
        return cls(
            matrix.reshape(-1),
            np.arange(n, dtype=np.int64) * width,
            np.full(n, width, np.int64),
            np.asarray(log_times, np.int64),
        )

    @property
    def uniform_length(self) -> int | None:
        if len(self) == 0:
            return None
        first = int(self.lengths[0])
        return first if np.all(self.lengths == first) else None

    def matrix(self) -> np.ndarray | None:
        """(n, L) uint8 copy of the messages when all have the same length L, else None."""
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
        return gather(self.buf, self.starts + at, dtype)


# --------------------------------------------------------------------------
# Imu
# --------------------------------------------------------------------------
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
    if cdr.imu_field_offset(frame_len, "linear_acceleration") + 12 * 8 != width:
        return None
    return cdr.imu_field_offset(frame_len, field)


def decode_imu(
    batch: MessageBatch, field: str = "linear_acceleration"
) -> tuple[np.ndarray, np.ndarray]:
    """Header stamps (n,) int64 ns and the `field` vectors (n, 3) of Imu messages."""
    if len(batch) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3))
    offset = imu_layout(batch, field)
    if offset is None:
        return cdr.decode_imu_batch(batch.to_list(), field)
    stamps = batch.field(4, "<i4").astype(np.int64) * _NS + batch.field(8, "<u4").astype(np.int64)
    return stamps, _vectors(batch, offset)


def _vectors(batch: MessageBatch, offset: int) -> np.ndarray:
    return rows(batch.buf, batch.starts + offset, 24).view("<f8").astype(np.float64)


def replace_imu_field(
    batch: MessageBatch, values: np.ndarray, field: str = "linear_acceleration"
) -> MessageBatch:
    """Copies of Imu messages with `field` set to `values` (n, 3), every other byte kept
    (the drop-in output of CONTRACT section 1b)."""
    values = np.asarray(values, np.float64).reshape(-1, 3)
    if len(values) != len(batch):
        raise ValueError(f"replace_imu_field: {len(values)} values for {len(batch)} messages")
    offset = imu_layout(batch, field) if len(batch) else None
    if offset is None:
        return MessageBatch.from_list(
            cdr.replace_imu_field(batch.to_list(), values, field), batch.log_times
        )
    matrix = np.array(batch.matrix())  # a copy: the input stays as it was
    matrix[:, offset : offset + 24] = (
        np.ascontiguousarray(values, "<f8").view(np.uint8).reshape(-1, 24)
    )
    return MessageBatch.from_matrix(matrix, batch.log_times)


# --------------------------------------------------------------------------
# JointState
# --------------------------------------------------------------------------
def decode_joint_states(
    batch: MessageBatch, names: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps (n,), positions and velocities (n, J) with columns picked by joint name (NaN
    where a message lacks a joint)."""
    if len(batch) == 0:
        return np.zeros(0, np.int64), np.zeros((0, len(names))), np.zeros((0, len(names)))
    fast = _joint_states_fast(batch, tuple(names))
    if fast is not None:
        return fast
    stamps, position, velocity, _ = cdr.decode_joint_state_batch(batch.to_list(), tuple(names))
    return stamps, position, velocity


def _joint_states_fast(batch: MessageBatch, names: tuple[str, ...]):
    """The codec's fast path on packed messages: every message has the first one's length
    and structure (frame, joint names, array sizes), only stamps and numbers differ."""
    width = batch.uniform_length
    if width is None:
        return None
    first = batch.buf[int(batch.starts[0]) : int(batch.starts[0]) + width].tobytes()
    if first[:2] != cdr.CDR_LE_HEADER[:2]:
        return None
    try:
        msg_names, pos_off, n_pos, vel_off, n_vel, _ = cdr.joint_state_layout(first)
    except Exception:
        return None
    if not set(names) <= set(msg_names) or not n_pos == n_vel == len(msg_names):
        return None
    structure = rows(batch.buf, batch.starts + 12, pos_off - 12)  # frame_id, names, position count
    if not np.all(structure == structure[0]) or not np.all(
        batch.field(vel_off - 8, "<u8") == batch.field(vel_off - 8, "<u8")[0]
    ):
        return None
    columns = [msg_names.index(n) for n in names]
    stamps = batch.field(4, "<i4").astype(np.int64) * _NS + batch.field(8, "<u4").astype(np.int64)
    position = (
        rows(batch.buf, batch.starts + pos_off, 8 * n_pos)
        .view("<f8")[:, columns]
        .astype(np.float64)
    )
    velocity = (
        rows(batch.buf, batch.starts + vel_off, 8 * n_vel)
        .view("<f8")[:, columns]
        .astype(np.float64)
    )
    return stamps, position, velocity
