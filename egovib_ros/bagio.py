"""Recording <-> rosbag2 bags (MCAP or sqlite3) via rosbags; no rclpy.

A bag holds one ``sensor_msgs/msg/Imu`` per accelerometer sample (CONTRACT
section 2). Messages are (de)serialised in numpy batches by `egovib_ros.cdr`.

Reading MCAP bags scans the MCAP records directly (`_mcap_chunks`), ~2x faster
than rosbags' reader; sqlite3 bags, file-compressed bags and anything the scan
does not expect go through rosbags.

Public API:
    Recording, read_recording(path), write_recording(path, rec), write_recordings(path, slices)
    BagWriter                                                  (bag_recorder)
    the codec of egovib_ros.cdr, re-exported for existing callers
"""
from __future__ import annotations

import heapq
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

from egovib_ros.cdr import (COMMANDS_TYPE, IMU_TYPE, JOINT_STATE_TYPE, decode_commands,  # noqa: F401
                            decode_imu, decode_imu_batch, decode_joint_state_batch, encode_commands,
                            encode_imu_batch, encode_joint_state_batch, imu_message, joint_state_message,
                            replace_imu_field, typestore)
from egovib_ros.constants import BAG_TOPICS, JOINT_NAMES
from egovib_ros.errors import BagError

TOPIC_TYPES = {
    BAG_TOPICS["raw"]: IMU_TYPE,
    BAG_TOPICS["contact"]: IMU_TYPE,
    BAG_TOPICS["ego"]: IMU_TYPE,
    BAG_TOPICS["denoised"]: IMU_TYPE,
    BAG_TOPICS["joint_states"]: JOINT_STATE_TYPE,
    BAG_TOPICS["commands"]: COMMANDS_TYPE,
}

# Messages decoded per numpy batch while reading: bounds memory on long bags.
_READ_BATCH = 200_000


@dataclass
class Recording:
    """Everything the project keeps of a bag, as numpy arrays (see docs/DESIGN.md)."""

    accel_stamps_ns: np.ndarray          # (N,) int64, accelerometer sample stamps
    accel: np.ndarray                    # (N, 3) float64, m/s^2 (raw topic)
    joint_stamps_ns: np.ndarray          # (M,) int64
    joint_position: np.ndarray           # (M, J) float64
    joint_velocity: np.ndarray           # (M, J) float64
    joint_names: tuple[str, ...] = field(default=JOINT_NAMES)
    contact: np.ndarray | None = None    # (N, 3) ground truth, same stamps as accel
    ego: np.ndarray | None = None        # (N, 3) ground truth
    denoised_stamps_ns: np.ndarray | None = None
    denoised: np.ndarray | None = None   # (K, 3)
    command_stamps_ns: np.ndarray | None = None
    commands: np.ndarray | None = None   # (P, J)

    @property
    def duration_s(self) -> float:
        """Time span of the accelerometer stream in seconds."""
        if len(self.accel_stamps_ns) < 2:
            return 0.0
        return float(self.accel_stamps_ns[-1] - self.accel_stamps_ns[0]) / 1e9


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------
class BagWriter:
    """Thin wrapper of rosbags' Writer for already-serialised CDR messages.

    >>> with BagWriter("out_bag") as bag:
    ...     bag.add_topic("/accelerometer/raw", "sensor_msgs/msg/Imu")
    ...     bag.write("/accelerometer/raw", stamp_ns, cdr_bytes)

    `storage` is "mcap" (default) or "sqlite3"; `compress` enables zstd chunk
    compression (MCAP) - readable by rosbags and `ros2 bag`.
    """

    def __init__(self, path: str | os.PathLike, *, storage: str = "mcap", compress: bool = False):
        self.path = Path(path)
        plugins = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
        if storage not in plugins:
            raise BagError(f"{self.path}: unknown storage {storage!r} (mcap or sqlite3)")
        if self.path.exists():
            raise BagError(f"{self.path}: output bag already exists")
        self._writer = Writer(self.path, version=9, storage_plugin=plugins[storage])
        if compress:
            self._writer.set_compression(CompressionMode.STORAGE if storage == "mcap" else CompressionMode.MESSAGE,
                                         CompressionFormat.ZSTD)
        self._connections: dict[str, object] = {}
        self._open = False

    def open(self) -> "BagWriter":
        self._writer.open()
        self._open = True
        return self

    def __enter__(self) -> "BagWriter":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> None:
        self.close()

    def add_topic(self, topic: str, msgtype: str) -> None:
        """Declare a topic (idempotent)."""
        if topic not in self._connections:
            self._connections[topic] = self._writer.add_connection(topic, msgtype, typestore=typestore())

    def write(self, topic: str, stamp_ns: int, data: bytes) -> None:
        """Append one serialised message; bag log time = `stamp_ns`."""
        self._writer.write(self._connections[topic], int(stamp_ns), data)

    def write_many(self, topic: str, stamps_ns: Iterable[int], datas: Iterable[bytes]) -> None:
        """Append many serialised messages of one topic."""
        conn, write = self._connections[topic], self._writer.write
        for stamp, data in zip(stamps_ns, datas):
            write(conn, int(stamp), data)

    def close(self) -> None:
        if self._open:
            self._writer.close()
            self._open = False


def _recording_streams(rec: Recording) -> list[tuple[str, np.ndarray, object]]:
    """(topic, stamps, encoder) per topic present in the recording."""
    n = len(rec.accel_stamps_ns)

    def imu(values, stamps):
        return lambda a, b: encode_imu_batch(stamps[a:b], values[a:b])

    streams = [(BAG_TOPICS["raw"], rec.accel_stamps_ns, imu(rec.accel, rec.accel_stamps_ns))]
    for key in ("contact", "ego"):
        values = getattr(rec, key)
        if values is not None:
            if len(values) != n:
                raise BagError(f"recording: {key} has {len(values)} samples, accel has {n}")
            streams.append((BAG_TOPICS[key], rec.accel_stamps_ns, imu(values, rec.accel_stamps_ns)))
    if rec.denoised is not None:
        streams.append((BAG_TOPICS["denoised"], rec.denoised_stamps_ns, imu(rec.denoised, rec.denoised_stamps_ns)))
    streams.append((BAG_TOPICS["joint_states"], rec.joint_stamps_ns,
                    lambda a, b: encode_joint_state_batch(rec.joint_stamps_ns[a:b], rec.joint_position[a:b],
                                                          rec.joint_velocity[a:b], rec.joint_names)))
    if rec.commands is not None and len(rec.commands):
        streams.append((BAG_TOPICS["commands"], rec.command_stamps_ns,
                        lambda a, b: [encode_commands(c) for c in rec.commands[a:b]]))
    return streams


def write_recording(path: str | os.PathLike, rec: Recording, *, storage: str = "mcap",
                    compress: bool = False, progress=None) -> None:
    """Write a Recording as a rosbag2 bag: one message per sample, log time = stamp.

    Messages of all topics are written in stamp order.  `progress(n_messages)`
    is called now and then with the number written since the last call.
    """
    write_recordings(path, [rec], storage=storage, compress=compress, progress=progress)


def write_recordings(path: str | os.PathLike, pieces: Iterable[Recording], *, storage: str = "mcap",
                     compress: bool = False, progress=None) -> None:
    """Write consecutive time slices of a recording into one bag (constant memory for long runs).

    Each slice is written in stamp order; topics are declared when first seen.
    """
    chunk = 50_000
    with BagWriter(path, storage=storage, compress=compress) as bag:
        write = bag._writer.write
        for rec in pieces:
            streams = _recording_streams(rec)
            for topic, _, _ in streams:
                bag.add_topic(topic, TOPIC_TYPES[topic])
            conns = [bag._connections[topic] for topic, _, _ in streams]

            def messages(index: int):
                _, stamps, encode = streams[index]
                stamps = np.asarray(stamps, np.int64)
                for a in range(0, len(stamps), chunk):
                    datas = encode(a, a + chunk)
                    for stamp, data in zip(stamps[a:a + chunk].tolist(), datas):
                        yield stamp, index, data

            count = 0
            for stamp, index, data in heapq.merge(*(messages(i) for i in range(len(streams)))):
                write(conns[index], stamp, data)
                count += 1
                if progress is not None and count == chunk:
                    progress(count)
                    count = 0
            if progress is not None and count:
                progress(count)


# --------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------
def _open_reader(path: Path) -> Reader:
    if not path.exists():
        raise BagError(f"{path}: no such bag")
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # rosbags raises several types for broken bags
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise BagError(f"{path}: not a readable rosbag2 bag ({reason})") from None
    return reader


def bag_topics(path: str | os.PathLike) -> dict[str, tuple[str, int]]:
    """{topic: (msgtype, message count)} of a bag."""
    path = Path(path)
    reader = _open_reader(path)
    try:
        return {c.topic: (c.msgtype, reader.topics[c.topic].msgcount) for c in reader.connections}
    finally:
        reader.close()


_MCAP_MAGIC = b"\x89MCAP0\r\n"


def _mcap_files(path: Path) -> list[Path] | None:
    """The bag's .mcap files when it is an uncompressed-file MCAP bag, else None (use rosbags)."""
    import yaml
    try:
        info = yaml.safe_load((path / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    except Exception:
        return None
    if info.get("storage_identifier") != "mcap" or info.get("compression_mode") not in ("", None):
        return None
    files = [path / name for name in info.get("relative_file_paths") or []]
    return files if files and all(f.suffix == ".mcap" and f.exists() for f in files) else None


def _mcap_chunks(file: Path, topics: set[str]):
    """Yield ({topic: [raw CDR, ...]}, [command log times]) per MCAP chunk, in file order.

    A plain scan of the MCAP records (spec: mcap.dev/spec) that keeps Python work
    per message to a few operations; rosbags' reader is ~3x slower on
    one-message-per-sample bags.  Raises on anything unexpected (caller falls back).
    """
    import mmap
    from rosbags.rosbag2.storage_mcap import decompress

    unpack_u16, unpack_u32, unpack_u64 = (struct.Struct(f).unpack_from for f in ("<H", "<I", "<Q"))
    channels: dict[int, str] = {}
    commands_topic = BAG_TOPICS["commands"]

    def string_at(buf, pos: int) -> tuple[str, int]:
        n = unpack_u32(buf, pos)[0]
        return bytes(buf[pos + 4:pos + 4 + n]).decode(), pos + 4 + n

    unpack_record = struct.Struct("<BQH").unpack_from        # opcode, record length, channel id (messages)

    def scan(buf, pos: int, end: int, out: dict, times: list) -> None:
        mv = memoryview(buf)
        get_topic = channels.get
        while pos < end:
            op, length, channel_id = unpack_record(buf, pos)
            body = pos + 9
            if op == 0x05:
                topic = get_topic(channel_id)
                if topic is not None:
                    out[topic].append(mv[body + 22:body + length])
                    if topic == commands_topic:
                        times.append(unpack_u64(buf, body + 6)[0])
            elif op == 0x04:
                channel_id = unpack_u16(buf, body)[0]
                topic, _ = string_at(buf, body + 4)
                if topic in topics:
                    channels[channel_id] = topic
            elif op == 0x06:
                chunk_pos = body + 24
                crc = unpack_u32(buf, chunk_pos)[0]
                compression, chunk_pos = string_at(buf, chunk_pos + 4)
                size = unpack_u64(buf, chunk_pos)[0]
                raw = decompress(bytes(mv[chunk_pos + 8:chunk_pos + 8 + size]), compression,
                                 unpack_u64(buf, body + 16)[0], crc)
                inner: dict[str, list] = {t: [] for t in topics}
                inner_times: list[int] = []
                scan(raw, 0, len(raw), inner, inner_times)
                out["__chunks__"].append((inner, inner_times))
            elif op in (0x02, 0x0F):          # footer / data end: the rest is the summary
                return
            pos = body + length
        if pos != end:
            raise ValueError("truncated MCAP record")

    with open(file, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as buf:
        if buf[:8] != _MCAP_MAGIC:
            raise ValueError("not an MCAP file")
        top: dict[str, list] = {t: [] for t in topics}
        top["__chunks__"] = []
        top_times: list[int] = []
        # scan top-level records lazily, chunk by chunk, so memory stays bounded
        pos, end = 8, len(buf) - 8
        while pos < end:
            op = buf[pos]
            length = unpack_u64(buf, pos + 1)[0]
            if op in (0x02, 0x0F):
                break
            top["__chunks__"] = []
            scan(buf, pos, pos + 9 + length, top, top_times)
            for inner, inner_times in top["__chunks__"]:
                yield inner, inner_times
            if any(top[t] for t in topics):            # messages outside chunks
                yield {t: [bytes(x) for x in top[t]] for t in topics}, list(top_times)
                for t in topics:
                    top[t] = []
                top_times.clear()
            pos += 9 + length


def read_recording(path: str | os.PathLike, *, ground_truth: bool = True, denoised: bool = True,
                   joint_names: Sequence[str] = JOINT_NAMES) -> Recording:
    """Read a rosbag2 bag (MCAP or sqlite3) into a Recording.

    Requires `/accelerometer/raw` and `/joint_states`; the ground-truth,
    denoised and command topics are read when present (and asked for).
    Raises BagError naming the bag and the problem.
    """
    path = Path(path)
    reader = _open_reader(path)
    try:
        types = {c.topic: c.msgtype for c in reader.connections}
        for key in ("raw", "joint_states"):
            topic = BAG_TOPICS[key]
            if topic not in types:
                raise BagError(f"{path}: missing topic {topic}")
        wanted = {BAG_TOPICS["raw"], BAG_TOPICS["joint_states"], BAG_TOPICS["commands"]}
        if ground_truth:
            wanted |= {BAG_TOPICS["contact"], BAG_TOPICS["ego"]}
        if denoised:
            wanted.add(BAG_TOPICS["denoised"])
        for topic in wanted & set(types):
            if types[topic] != TOPIC_TYPES[topic]:
                raise BagError(f"{path}: topic {topic} has type {types[topic]}, expected {TOPIC_TYPES[topic]}")
        connections = [c for c in reader.connections if c.topic in wanted]

        pending: dict[str, list[bytes]] = {c.topic: [] for c in connections}
        decoded: dict[str, list] = {c.topic: [] for c in connections}
        command_times: list[int] = []

        def flush(topic: str) -> None:
            raws = pending[topic]
            if not raws:
                return
            try:
                if TOPIC_TYPES[topic] == IMU_TYPE:
                    decoded[topic].append(decode_imu_batch(raws))
                elif TOPIC_TYPES[topic] == JOINT_STATE_TYPE:
                    decoded[topic].append(decode_joint_state_batch(raws, joint_names))
                else:
                    decoded[topic].append([decode_commands(r) for r in raws])
            except Exception as exc:
                raise BagError(f"{path}: topic {topic}: cannot decode message ({exc})") from None
            pending[topic] = []

        fast_done = False
        files = _mcap_files(path)
        if files is not None:
            try:
                for file in files:
                    for batch, times in _mcap_chunks(file, set(pending)):
                        for topic, raws in batch.items():
                            if raws:
                                pending[topic].extend(raws)
                                if len(pending[topic]) >= _READ_BATCH and topic != BAG_TOPICS["commands"]:
                                    flush(topic)
                        command_times.extend(times)
                fast_done = True
            except BagError:
                raise
            except Exception:
                # anything unexpected: start again with rosbags' reader, which reports errors properly
                pending = {topic: [] for topic in pending}
                decoded = {topic: [] for topic in decoded}
                command_times.clear()
        if not fast_done:
            try:
                for conn, log_time, raw in reader.messages(connections=connections):
                    bucket = pending[conn.topic]
                    bucket.append(raw)
                    if conn.topic == BAG_TOPICS["commands"]:
                        command_times.append(log_time)
                    elif len(bucket) >= _READ_BATCH:
                        flush(conn.topic)
            except BagError:
                raise
            except Exception as exc:
                raise BagError(f"{path}: unreadable bag data ({exc})") from None
        for topic in list(pending):
            flush(topic)
    finally:
        reader.close()

    def imu_arrays(topic: str) -> tuple[np.ndarray, np.ndarray] | None:
        parts = decoded.get(topic)
        if not parts:
            return None
        stamps = np.concatenate([p[0] for p in parts])
        values = np.concatenate([p[1] for p in parts])
        if np.any(np.diff(stamps) < 0):
            order = np.argsort(stamps, kind="stable")
            stamps, values = stamps[order], values[order]
        return stamps, values

    raw = imu_arrays(BAG_TOPICS["raw"])
    if raw is None:
        raise BagError(f"{path}: topic {BAG_TOPICS['raw']} has no messages")
    js_parts = decoded.get(BAG_TOPICS["joint_states"])
    if not js_parts:
        raise BagError(f"{path}: topic {BAG_TOPICS['joint_states']} has no messages")
    js_stamps = np.concatenate([p[0] for p in js_parts])
    js_pos = np.concatenate([p[1] for p in js_parts])
    js_vel = np.concatenate([p[2] for p in js_parts])
    if np.any(np.diff(js_stamps) < 0):
        order = np.argsort(js_stamps, kind="stable")
        js_stamps, js_pos, js_vel = js_stamps[order], js_pos[order], js_vel[order]
    if np.isnan(js_vel).all(axis=0).any():
        missing = [joint_names[j] for j in np.flatnonzero(np.isnan(js_vel).all(axis=0))]
        raise BagError(f"{path}: topic {BAG_TOPICS['joint_states']} lacks joint(s) {', '.join(missing)}")

    rec = Recording(accel_stamps_ns=raw[0], accel=raw[1], joint_stamps_ns=js_stamps,
                    joint_position=js_pos, joint_velocity=js_vel, joint_names=tuple(joint_names))
    for key in ("contact", "ego"):
        arrays = imu_arrays(BAG_TOPICS[key])
        if arrays is not None:
            if len(arrays[0]) != len(raw[0]) or not np.array_equal(arrays[0], raw[0]):
                raise BagError(f"{path}: topic {BAG_TOPICS[key]} does not have the stamps of {BAG_TOPICS['raw']}")
            setattr(rec, key, arrays[1])
    den = imu_arrays(BAG_TOPICS["denoised"])
    if den is not None:
        rec.denoised_stamps_ns, rec.denoised = den
    cmd_parts = decoded.get(BAG_TOPICS["commands"])
    if cmd_parts:
        cmds = [c for part in cmd_parts for c in part]
        width = max(len(c) for c in cmds)
        rec.commands = np.array([np.pad(c, (0, width - len(c)), constant_values=np.nan) for c in cmds])
        rec.command_stamps_ns = np.asarray(command_times, np.int64)
    return rec
