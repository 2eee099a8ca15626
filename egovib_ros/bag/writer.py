"""Writing rosbag2 bags: MCAP chunk by chunk (`mcapfile.McapWriter`), optionally
zstd-compressed per chunk, plus `metadata.yaml` (rosbag2 version 9, as rosbags writes it):
the result reads with rosbags and `ros2 bag`. sqlite3 output goes through rosbags' writer.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
import yaml
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

from egovib_ros.bag.codec import MessageBatch, typestore
from egovib_ros.bag.mcapfile import McapWriter
from egovib_ros.errors import BagError

COMPRESSIONS = ("none", "zstd")


def compression_name(compress: bool | str | None) -> str:
    """'' or 'zstd' from the user's spelling (True/False, 'zstd', 'none', '')."""
    if compress in (None, False, "", "none"):
        return ""
    if compress is True or compress == "zstd":
        return "zstd"
    raise BagError(f"unknown compression {compress!r} (choose from {', '.join(COMPRESSIONS)})")


@dataclass
class _Topic:
    topic: str
    msgtype: str
    channel_id: int
    metadata: dict  # topic_metadata of metadata.yaml
    count: int = 0


def _library() -> str:
    try:
        return f"egovib_ros-{version('egovib_ros')}"
    except PackageNotFoundError:
        return "egovib_ros"


class BagWriter:
    """A rosbag2 bag being written (a context manager): `add_topic`, then serialised CDR
    messages one by one (`write`) or many at once (`write_batch`).

    `storage`: "mcap" or "sqlite3". `compress`: zstd per MCAP chunk; for sqlite3, per message
    (rosbag2's "message" mode). `crc`: MCAP chunk CRCs, so that a damaged file is refused on
    reading rather than read wrong. Messages of one topic must come in log-time order; topics
    may interleave. Memory: one chunk (`chunk_bytes`) plus what `write` has buffered."""

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        storage: str = "mcap",
        compress: bool | str = False,
        chunk_bytes: int = 4 << 20,
        crc: bool = True,
    ):
        self.path = Path(path)
        if storage not in ("mcap", "sqlite3"):
            raise BagError(f"{self.path}: unknown storage {storage!r} (mcap or sqlite3)")
        if self.path.exists():
            raise BagError(f"{self.path}: output bag already exists")
        self.storage = storage
        self.compression = compression_name(compress)
        self.chunk_bytes = chunk_bytes
        self.crc = crc
        self.topics: dict[str, _Topic] = {}
        self._mcap: McapWriter | None = None
        self._rosbags = None
        self._buffered: dict[str, tuple[list, list]] = {}
        self._buffered_bytes = 0
        self._open = False

    # --- lifetime --------------------------------------------------------------------
    def open(self) -> "BagWriter":
        if self.storage == "mcap":
            self.path.mkdir(parents=True)
            self._mcap = McapWriter(
                self.path / f"{self.path.name}.mcap",
                compression=self.compression,
                chunk_bytes=self.chunk_bytes,
                library=_library(),
                crc=self.crc,
            )
        else:
            self._rosbags = Writer(self.path, version=9, storage_plugin=StoragePlugin.SQLITE3)
            if self.compression:
                self._rosbags.set_compression(CompressionMode.MESSAGE, CompressionFormat.ZSTD)
            self._rosbags.open()
            self._rosbags_conns: dict[str, object] = {}
        self._open = True
        return self

    def __enter__(self) -> "BagWriter":
        return self.open()

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def close(self) -> None:
        """Write the index, summary and metadata.yaml. Before this the bag is incomplete."""
        if not self._open:
            return
        self._open = False
        if self._rosbags is not None:
            self._rosbags.close()
            return
        try:
            self._drain_buffer()
            self._mcap.flush_chunk()  # the last chunk's times count in the metadata
            info = self._metadata()
            text = yaml.safe_dump({"rosbag2_bagfile_information": info}, sort_keys=False)
            self._mcap.close(
                metadata={"rosbag2": {"serialized_metadata": yaml.safe_dump(info, sort_keys=False)}}
            )
        except BaseException:  # e.g. the disk is full: the file is given up, not left open
            self._abort_mcap()
            raise
        (self.path / "metadata.yaml").write_text(text)

    def abort(self) -> None:
        if self._open:
            self._open = False
            self._abort_mcap()

    def _abort_mcap(self) -> None:
        """Close the MCAP file of a bag given up; its buffered bytes cannot be written when the
        disk is full: that second failure would hide the first, so it is dropped."""
        if self._mcap is not None:
            with contextlib.suppress(OSError):
                self._mcap.abort()

    @property
    def size_ratio(self) -> float | None:
        """Uncompressed / written bytes of the MCAP chunks so far (None before any chunk)."""
        if self._mcap is None or not self._mcap.bytes_compressed:
            return None
        return self._mcap.bytes_uncompressed / self._mcap.bytes_compressed

    # --- topics ----------------------------------------------------------------------
    def add_topic(
        self,
        topic: str,
        msgtype: str,
        *,
        msgdef: str | None = None,
        msgdef_format: str = "ros2msg",
        type_hash: str | None = None,
        offered_qos_profiles=None,
        channel_metadata: dict | None = None,
        channel_id: int | None = None,
        schema=None,
    ) -> int:
        """Declare a topic (idempotent); returns its MCAP channel id. Definitions default to
        the Jazzy typestore's (`copy_topic` passes an input bag's; `schema`: an mcap Schema
        record to reuse with its id)."""
        if topic in self.topics:
            return self.topics[topic].channel_id
        if msgdef is None and schema is None:
            try:
                msgdef, _ = typestore().generate_msgdef(msgtype, ros_version=2)
            except Exception:
                raise BagError(f"{self.path}: unknown message type {msgtype} for {topic}") from None
        if type_hash is None:
            try:
                type_hash = typestore().hash_rihs01(msgtype)
            except Exception:
                type_hash = ""
        qos = offered_qos_profiles if offered_qos_profiles is not None else []
        if isinstance(qos, str):  # metadata.yaml before version 9 holds a YAML string
            qos = yaml.safe_load(qos) or []
        metadata = {
            "name": topic,
            "type": msgtype,
            "serialization_format": "cdr",
            "offered_qos_profiles": qos,
            "type_description_hash": type_hash,
        }
        if self._rosbags is not None:
            if schema is not None and msgdef is None:
                msgdef = bytes(schema.data).decode()
            conn = (
                self._rosbags.add_connection(topic, msgtype, msgdef=msgdef, rihs01=type_hash or "")
                if msgdef is not None and type_hash
                else self._rosbags.add_connection(topic, msgtype, typestore=typestore())
            )
            self._rosbags_conns[topic] = conn
            self.topics[topic] = _Topic(topic, msgtype, conn.id, metadata)
            return conn.id
        if schema is not None:
            schema_id = self._mcap.add_schema(
                schema.name,
                schema.encoding,
                schema.data,
                schema_id=schema.id if schema.id not in self._mcap.schemas else None,
            )
        else:
            schema_id = self._mcap.add_schema(msgtype, msgdef_format, msgdef.encode())
        if channel_metadata is None:
            channel_metadata = {"offered_qos_profiles": yaml.safe_dump(qos).strip()}
        if channel_id is not None and channel_id in self._mcap.channels:
            channel_id = None
        channel_id = self._mcap.add_channel(
            topic, schema_id, "cdr", channel_metadata, channel_id=channel_id
        )
        self.topics[topic] = _Topic(topic, msgtype, channel_id, metadata)
        return channel_id

    def copy_topic(self, reader, topic: str, *, as_topic: str | None = None) -> int:
        """Declare `topic` as the input bag (`BagReader`) has it: same definition, QoS and,
        for an MCAP input, the same schema and channel ids when free (verbatim chunk copies)."""
        info = reader.topics[topic]
        name = as_topic or topic
        schema = channel = None
        definitions = reader.mcap_definitions if self._mcap is not None else None
        if definitions is not None:
            schemas, channels = definitions
            channel = next((c for c in channels.values() if c.topic == topic), None)
            schema = schemas.get(channel.schema_id) if channel is not None else None
        qos = info.metadata.get("offered_qos_profiles")
        if channel is not None and "offered_qos_profiles" in channel.metadata:
            # rosbags pairs metadata.yaml's topics with the file's channels by QoS too: a topic
            # recorded on several connections (QoS variants) is one channel, alike in both
            try:
                qos = yaml.safe_load(channel.metadata["offered_qos_profiles"]) or []
            except yaml.YAMLError:
                raise BagError(
                    f"{reader.path}: topic {topic}: its channel's QoS profiles are not YAML"
                ) from None
        return self.add_topic(
            name,
            info.msgtype,
            msgdef=info.msgdef or None,
            msgdef_format=info.msgdef_format,
            type_hash=info.metadata.get("type_description_hash") or info.digest or None,
            offered_qos_profiles=qos,
            channel_metadata=dict(channel.metadata) if channel is not None else None,
            channel_id=channel.id if channel is not None and as_topic is None else None,
            schema=schema,
        )

    # --- messages --------------------------------------------------------------------
    def write(self, topic: str, stamp_ns: int, data: bytes) -> None:
        """Append one serialised message; bag log time = `stamp_ns`."""
        if self._rosbags is not None:
            self._rosbags.write(self._rosbags_conns[topic], int(stamp_ns), data)
            self.topics[topic].count += 1
            return
        datas, stamps = self._buffered.setdefault(topic, ([], []))
        datas.append(bytes(data))
        stamps.append(int(stamp_ns))
        self._buffered_bytes += len(data) + 31
        if self._buffered_bytes >= self.chunk_bytes:
            self._drain_buffer()
            self._mcap.flush_chunk()

    def write_batch(self, topic: str, log_times: np.ndarray, data) -> None:
        """Append messages of one topic: `data` is an (n, L) uint8 array, a MessageBatch or
        a list of bytes; `log_times` (n,) their bag log times."""
        if isinstance(data, MessageBatch):
            matrix = data.matrix()
            data = matrix if matrix is not None else data.to_list()
        log_times = np.asarray(log_times, np.int64)
        if self._rosbags is not None:
            rows = data if not isinstance(data, np.ndarray) else [r.tobytes() for r in data]
            for stamp, row in zip(log_times.tolist(), rows):
                self.write(topic, stamp, row)
            return
        if topic in self._buffered:
            self._drain_buffer()
        self._mcap.add_records(self.topics[topic].channel_id, log_times, data)
        self.topics[topic].count += len(log_times)

    def write_message_records(self, topic: str, log_times: np.ndarray, records: np.ndarray) -> None:
        """Append ready-made MCAP message records of `topic` (see `mcapfile.message_records`,
        whose channel id must be this topic's); MCAP storage only."""
        if topic in self._buffered:
            self._drain_buffer()
        self._mcap.add_message_records(self.topics[topic].channel_id, log_times, records)
        self.topics[topic].count += len(log_times)

    def copy_batch(self, batch, topics: set[str] | None = None) -> int:
        """Copy a `ReadBatch`'s messages of `topics` (default: all of the batch's): its
        input MCAP chunks as they are when each can be (MCAP output, the chunk's channel ids
        and definitions this bag's; returns how many), else message by message (returns 0).
        Topics must have been declared (`copy_topic`)."""
        if batch.chunks and self._mcap is not None:
            other = (
                {c for c, t in batch.topic_of_channel.items() if t not in topics}
                if topics is not None
                else set()
            )
            chunks = [chunk.without(other) if other else chunk for chunk in batch.chunks]
            schemas, channels = batch.scanner.schemas, batch.scanner.channels
            by_id = {t.channel_id: t for t in self.topics.values()}
            if all(
                self._mcap.accepts_verbatim(chunk, schemas, channels)
                and all(c in by_id for c in chunk.index)
                for chunk in chunks
            ):
                self._drain_buffer()
                for chunk in chunks:
                    self._mcap.add_chunk_records(chunk)
                    for channel, (times, _) in chunk.index.items():
                        by_id[channel].count += len(times)
                return len(chunks)
        for topic, messages in batch.messages.items():
            if (topics is None or topic in topics) and len(messages):
                self.write_batch(topic, messages.log_times, messages)
        return 0

    # --- internals ---------------------------------------------------------------------
    def _drain_buffer(self) -> None:
        buffered, self._buffered, self._buffered_bytes = self._buffered, {}, 0
        for topic, (datas, stamps) in buffered.items():
            self._mcap.add_records(
                self.topics[topic].channel_id, np.asarray(stamps, np.int64), datas
            )
            self.topics[topic].count += len(stamps)

    def _metadata(self) -> dict:
        start = self._mcap.start_time or 0
        duration = max(0, (self._mcap.end_time or 0) - start)
        count = sum(t.count for t in self.topics.values())
        name = f"{self.path.name}.mcap"
        return {
            "version": 9,
            "storage_identifier": "mcap",
            "relative_file_paths": [name],
            "duration": {"nanoseconds": duration},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": count,
            "topics_with_message_count": [
                {"topic_metadata": t.metadata, "message_count": t.count}
                for t in self.topics.values()
            ],
            "compression_format": "",
            "compression_mode": "",
            "files": [
                {
                    "path": name,
                    "starting_time": {"nanoseconds_since_epoch": start},
                    "duration": {"nanoseconds": duration},
                    "message_count": count,
                }
            ],
            "custom_data": None,
            "ros_distro": "jazzy",
        }
