"""Reading rosbag2 bags batch by batch, in bounded memory.

`BagReader(path)` opens a bag (MCAP or sqlite3; validated by rosbags) and `batches(topics)`
yields `ReadBatch`es: the wanted topics' messages as packed `MessageBatch`es and, for MCAP
bags, the chunks they came from (for verbatim copies). MCAP files are scanned chunk by chunk
(`mcapfile`); sqlite3 bags, file-compressed bags and MCAP files the scan does not understand
go through rosbags' reader, a fixed number of messages at a time.
"""

from __future__ import annotations

import contextlib
import hashlib
import heapq
import logging
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np
import yaml
from mcap.reader import make_reader
from mcap.records import Schema
from rosbags.rosbag2 import Reader

from egovib_ros.bag.codec import MessageBatch
from egovib_ros.bag.many import is_bare_mcap
from egovib_ros.bag.mcapfile import (
    ChunkData,
    McapDamaged,
    McapFormatError,
    McapScanner,
    ends_complete,
)
from egovib_ros.errors import BagError

LOG = logging.getLogger("egovib_ros.bag")
_NO_SCHEMA = Schema(id=0, data=b"", encoding="", name="")  # a channel without (schemaless)


@dataclass
class TopicInfo:
    msgtype: str
    count: int
    metadata: dict  # the topic's entry in metadata.yaml (topic_metadata), for copying
    msgdef: str = ""  # message definition (as rosbags has it)
    msgdef_format: str = "ros2msg"
    digest: str = ""


@dataclass
class ReadBatch:
    """Messages of the wanted topics from one stretch of the bag, in file order."""

    messages: dict[str, MessageBatch]
    # the MCAP chunks they came from, in order (verbatim copies); small chunks are read
    # several to a batch, so that per-batch work does not multiply with tiny chunks
    chunks: list[ChunkData] = field(default_factory=list)
    scanner: McapScanner | None = None  # their schemas/channels
    topic_of_channel: dict[int, str] = field(default_factory=dict)
    bytes_read: int = 0  # of the bag's files, for progress bars
    frontier_ns: int | None = None  # messages read later have log times >= this (None: unknown)


class BagReader:
    """A rosbag2 bag opened for reading (context manager)."""

    rosbags_batch = 50_000  # messages per batch when reading through rosbags
    batch_bytes = 1 << 20  # MCAP chunks smaller than this are read several to a batch

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        if not self.path.exists():
            raise BagError(f"{self.path}: no such bag")
        try:
            self.info = yaml.safe_load((self.path / "metadata.yaml").read_text())[
                "rosbag2_bagfile_information"
            ]
        except Exception:
            self.info = {}
        self.cut_files: dict[Path, int] = {}  # MCAP files cut short: their readable bytes
        self._rebuilt: dict[Path, McapScanner] = {}
        self._types: dict[str, set[str]] = {}  # the message types of each topic
        try:
            self._reader = Reader(self.path)
            self._reader.open()
        except Exception as exc:  # rosbags raises several types for broken bags
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            self._reader = None
            if not self._open_cut_mcap():
                raise BagError(f"{self.path}: not a readable rosbag2 bag ({reason})") from None
            return
        entries = self._topic_entries()
        self.topics: dict[str, TopicInfo] = {}
        for conn in self._reader.connections:
            self._types.setdefault(conn.topic, set()).add(conn.msgtype)
            if conn.topic in self.topics:
                continue
            msgdef = getattr(conn, "msgdef", None)
            self.topics[conn.topic] = TopicInfo(
                msgtype=conn.msgtype,
                count=self._reader.topics[conn.topic].msgcount,
                metadata=dict(entries.get(conn.topic, {})),
                msgdef=getattr(msgdef, "data", "") or "",
                msgdef_format="ros2idl"
                if str(getattr(getattr(msgdef, "format", None), "name", "")) == "IDL"
                else "ros2msg",
                digest=getattr(conn, "digest", "") or "",
            )
        self.files = [self.path / name for name in self.info.get("relative_file_paths") or []]
        if not self.files and is_bare_mcap(self.path):
            self.files = [self.path]
        self.total_bytes = sum(f.stat().st_size for f in self.files if f.exists())

    def _open_cut_mcap(self) -> bool:
        """A bag whose MCAP file(s) a recorder left without summary and footer (killed, out
        of power): rosbags cannot open it, but every complete chunk is there. Read them
        (topics, types and counts from one scan of the records), as `ros2 bag reindex` would
        recover them, and say so; False if this is not such a bag (the caller refuses it)."""
        files = [self.path / n for n in self.info.get("relative_file_paths") or []]
        files = files or (
            [self.path] if is_bare_mcap(self.path) else sorted(self.path.glob("*.mcap"))
        )
        if (
            not files
            or any(f.suffix != ".mcap" or not f.is_file() for f in files)
            or self.info.get("storage_identifier", "mcap") != "mcap"
            or self.info.get("compression_mode") not in ("", None)
        ):
            return False
        cut = [f for f in files if not ends_complete(f)]
        if not cut:
            return False  # whole files rosbags still refused: not a cut recording
        entries, counts = self._topic_entries(), {}
        self.topics = {}
        try:
            for file in files:
                scanner = McapScanner(file, cut=file in cut)
                for chunk in scanner.chunks():
                    for channel, (times, _) in chunk.index.items():
                        topic = scanner.channels[channel].topic
                        counts[topic] = counts.get(topic, 0) + len(times)
                for channel in scanner.channels.values():
                    schema = scanner.schemas.get(channel.schema_id) or _NO_SCHEMA
                    self._types.setdefault(channel.topic, set()).add(schema.name)
                    if channel.topic in self.topics:
                        continue
                    self.topics[channel.topic] = TopicInfo(
                        msgtype=schema.name,
                        count=0,
                        metadata=dict(entries.get(channel.topic, {})),
                        msgdef=schema.data.decode(),
                        msgdef_format="ros2idl" if schema.encoding == "ros2idl" else "ros2msg",
                    )
                if scanner.cut_at is not None:
                    self.cut_files[file] = scanner.cut_at
                    self._rebuilt[file] = scanner  # its chunk index, for reading in time order
        except (McapFormatError, KeyError, UnicodeDecodeError):
            return False
        if not any(counts.values()):
            sizes = ", ".join(f"{f.name} ({f.stat().st_size} bytes)" for f in cut)
            raise BagError(
                f"{self.path}: {sizes} cut short without one complete chunk (a recorder killed "
                f"at its start?): nothing to read"
            )
        for topic, info in self.topics.items():
            info.count = counts.get(topic, 0)
        self.info = {**self.info, "storage_identifier": "mcap"}
        self.info.setdefault("relative_file_paths", [f.name for f in files])
        self.files = files
        self.total_bytes = sum(f.stat().st_size for f in files)
        LOG.warning(
            "%s: truncated: %s without summary and footer (the recorder stopped without "
            "closing the file); read its %d complete messages%s (`ros2 bag reindex` or "
            "`mcap recover` rebuild the file)",
            self.path,
            ", ".join(f.name for f in cut),
            sum(counts.values()),
            "".join(
                f", {f.stat().st_size - at} incomplete bytes at the end of {f.name} skipped"
                for f, at in self.cut_files.items()
                if f.stat().st_size > at
            ),
        )
        return True

    # --- facts -----------------------------------------------------------------
    def _topic_entries(self) -> dict[str, dict]:
        """metadata.yaml's entry of each topic (topic_metadata), for copying."""
        return {
            e["topic_metadata"]["name"]: e["topic_metadata"]
            for e in self.info.get("topics_with_message_count") or []
            if "topic_metadata" in e
        }

    @property
    def is_plain_mcap(self) -> bool:
        """MCAP storage without file-level compression: the chunk scan applies."""
        return (
            self.info.get("storage_identifier") == "mcap"
            and self.info.get("compression_mode") in ("", None)
            and bool(self.files)
            and all(f.suffix == ".mcap" and f.exists() for f in self.files)
        )

    @cached_property
    def mcap_definitions(self):
        """(schemas, channels) by id from the summary of the bag's first MCAP file (read with
        the `mcap` library), or None (not MCAP, no summary)."""
        if self.is_plain_mcap:
            with contextlib.suppress(Exception), open(self.files[0], "rb") as fh:
                summary = make_reader(fh).get_summary()
                return (dict(summary.schemas), dict(summary.channels)) if summary else None
        return None

    def require(self, topic: str, msgtype: str) -> None:
        """BagError unless the bag has `topic` with type `msgtype`."""
        if topic not in self.topics:
            raise BagError(f"{self.path}: missing topic {topic}{self._near(topic, msgtype)}")
        types = sorted(self._types.get(topic, ()))
        if len(types) > 1:  # publishers of different types on one topic: which is which?
            raise BagError(
                f"{self.path}: topic {topic} carries {len(types)} message types "
                f"({', '.join(types)}): publishers of different types on one topic?"
            )
        if self.topics[topic].msgtype != msgtype:
            found = self.topics[topic].msgtype
            raise BagError(f"{self.path}: topic {topic} has type {found}, expected {msgtype}")

    def _near(self, topic: str, msgtype: str) -> str:
        """What the bag has instead: the topic with a leading slash, or its topics of the
        type (another robot's bag, or a command without --robot)."""
        if "/" + topic in self.topics:
            return f" (it has /{topic}: a topic in a robot profile starts with /)"
        same = sorted(t for t, info in self.topics.items() if info.msgtype == msgtype)
        if not same:
            return ""
        listed = ", ".join(same[:3]) + (f" and {len(same) - 3} more" if len(same) > 3 else "")
        kind = msgtype.rsplit("/", 1)[-1]
        return f" (its {kind} topics: {listed}: the profile of another robot?)"

    # --- reading ---------------------------------------------------------------
    def batches(self, topics: Iterable[str] | None = None) -> Iterator[ReadBatch]:
        """ReadBatches of `topics` (default: all) in file order; BagError on unreadable data."""
        wanted = set(self.topics) if topics is None else set(topics) & set(self.topics)
        started = False
        read = dict.fromkeys(wanted, 0)
        if self.is_plain_mcap:
            try:
                for batch in self._checked(self._mcap_batches(wanted), read):
                    started = True
                    yield batch
                self._check_counts(read)
                return
            except McapFormatError as exc:
                if started or isinstance(exc, McapDamaged):
                    raise BagError(f"{self.path}: unreadable MCAP data ({exc})") from None
            # not yet started: rosbags' reader gets its chance (and reports errors its way)
        yield from self._checked(self._rosbags_batches(wanted), read)
        self._check_counts(read)

    def _checked(self, batches: Iterator[ReadBatch], read: dict[str, int]) -> Iterator[ReadBatch]:
        """Count the messages read, and hold each batch to the promise of the one before: no
        message logged before its frontier. Files with a chunk index are read in chunk start
        order, and sqlite3 in log-time order, so the promise holds whatever the order of the
        messages in the file; a file with neither index nor order cannot be streamed."""
        frontier = None
        for batch in batches:
            for topic, messages in batch.messages.items():
                read[topic] += len(messages)
                if frontier is not None and len(messages) and messages.log_times.min() < frontier:
                    raise BagError(
                        f"{self.path}: topic {topic}: messages are not in log-time order and the "
                        f"file has no chunk index to read them in order (re-index it, e.g. "
                        f"`mcap recover`, or rewrite it with rosbags)"
                    )
            if batch.frontier_ns is not None:
                frontier = (
                    batch.frontier_ns if frontier is None else max(frontier, batch.frontier_ns)
                )
            yield batch

    def _check_counts(self, read: dict[str, int]) -> None:
        """Every message the bag's index counts must have been read: records damaged into
        something else would otherwise be skipped without a word."""
        for topic, n in sorted(read.items()):
            expected = self.topics[topic].count
            if expected and n != expected:
                raise BagError(
                    f"{self.path}: topic {topic}: {n} messages read, the bag lists {expected} "
                    f"({expected - n} lost to damaged records)"
                )

    def _mcap_batches(self, wanted: set[str]) -> Iterator[ReadBatch]:
        """Batches of chunks from every file of the bag, merged in log-time order: a bag may
        be split by time (one file after the other) or by topic (each file spanning the whole
        recording), so the next chunk is the one that starts first in any file. A file is
        opened when the merge reaches the start time metadata.yaml gives it (all at once if
        it gives none), so a bag of many files split by time holds one open at a time; one
        decompressed chunk is held per open file, and a batch holds chunks of one file (its
        scanner's channel ids)."""
        scanners = [
            McapScanner(file, cut=True).reuse(self._rebuilt[file])
            if file in self._rebuilt
            else McapScanner(file)
            for file in self.files
        ]
        chunks: list = [None] * len(scanners)  # iterators of the files opened
        heads: list = [None] * len(scanners)  # the next chunk of each open file
        starts = self._file_starts()
        waiting = set(range(len(scanners)))  # not opened yet
        group: list[ChunkData] = []
        group_file, size = None, 0
        while waiting or any(h is not None for h in heads):
            keys = {i: (_first_time(h), i) for i, h in enumerate(heads) if h is not None}
            keys.update({i: (starts[i], i) for i in waiting})
            k = min(keys, key=keys.get)
            if k in waiting:  # open it: its first chunk joins the merge
                waiting.discard(k)
                chunks[k] = self._checked_chunks(scanners[k])
                heads[k] = next(chunks[k], None)
                continue
            chunk, heads[k] = heads[k], next(chunks[k], None)
            # what is still unread in the other files starts no earlier than their next
            # chunk, or than the start metadata.yaml gives a file not opened yet
            bounds = [chunk.frontier_ns]
            bounds += [_first_time(h) for i, h in enumerate(heads) if h is not None and i != k]
            bounds += [starts[i] for i in waiting]
            chunk.frontier_ns = None if None in bounds else min(bounds)
            if group and (k != group_file or size >= self.batch_bytes):
                yield self._chunk_batch(group, scanners[group_file], wanted)
                group, size = [], 0
            group.append(chunk)
            group_file = k
            size += len(chunk.records)
        if group:
            yield self._chunk_batch(group, scanners[group_file], wanted)

    def _file_starts(self) -> list[int]:
        """Each file's first log time from metadata.yaml (`files`), or the earliest
        possible time for all of them when it does not give every one."""
        entries = {
            e.get("path"): e.get("starting_time", {}).get("nanoseconds_since_epoch")
            for e in self.info.get("files") or []
            if isinstance(e, dict) and isinstance(e.get("starting_time"), dict)
        }
        starts = [entries.get(f.name) for f in self.files]
        if any(not isinstance(t, int) for t in starts):
            return [np.iinfo(np.int64).min] * len(self.files)
        return starts

    @staticmethod
    def _checked_chunks(scanner: McapScanner) -> Iterator[ChunkData]:
        for chunk in scanner.chunks():
            missing = [c for c in chunk.index if c not in scanner.channels]
            if missing:
                raise McapFormatError(f"messages on undefined channel {missing[0]}")
            yield chunk

    @staticmethod
    def _chunk_batch(chunks: list[ChunkData], scanner: McapScanner, wanted: set[str]) -> ReadBatch:
        topic_of = {c: scanner.channels[c].topic for chunk in chunks for c in chunk.index}
        per_topic: dict[str, list[MessageBatch]] = {}
        for chunk in chunks:
            buf = chunk.buffer
            for channel in chunk.index:
                topic = topic_of[channel]
                if topic in wanted:
                    times, starts, lengths = chunk.data_span(channel)
                    per_topic.setdefault(topic, []).append(
                        MessageBatch(buf, starts, lengths, times)
                    )
        messages = {t: (b[0] if len(b) == 1 else _merge_by_time(b)) for t, b in per_topic.items()}
        return ReadBatch(
            messages,
            chunks,
            scanner,
            topic_of,
            bytes_read=sum(c.file_bytes for c in chunks),
            frontier_ns=chunks[-1].frontier_ns,
        )

    def _rosbags_batches(self, wanted: set[str]) -> Iterator[ReadBatch]:
        connections = [c for c in self._reader.connections if c.topic in wanted]
        if not connections:
            return
        pending: dict[str, tuple[list, list]] = {}
        count = 0
        size = 0
        latest = None

        def emit() -> ReadBatch:
            messages = {t: MessageBatch.from_list(d, ts) for t, (d, ts) in pending.items()}
            # rosbags reads in log-time order
            return ReadBatch(messages, bytes_read=size, frontier_ns=latest)

        try:
            for topic, log_time, raw in self._rosbags_messages(connections):
                datas, times = pending.setdefault(topic, ([], []))
                datas.append(bytes(raw))
                times.append(log_time)
                count += 1
                size += len(raw)
                latest = log_time
                if count >= self.rosbags_batch:
                    yield emit()
                    pending, count, size = {}, 0, 0
        except BagError:
            raise
        except Exception as exc:
            reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise BagError(f"{self.path}: unreadable bag data ({reason})") from None
        if pending:
            yield emit()

    def _rosbags_messages(self, connections) -> Iterator[tuple[str, int, bytes]]:
        """(topic, log time, data) in log-time order. rosbags reads a bag's files one after
        the other; a bag split by topic (each file spanning the whole recording) is read
        file by file, each in log-time order, merged."""
        plain = (
            len(self.files) > 1
            and self.info.get("compression_mode") in ("", None)
            and all(f.suffix in (".db3", ".mcap") and f.exists() for f in self.files)
        )
        if not plain:
            for conn, log_time, raw in self._reader.messages(connections=connections):
                yield conn.topic, log_time, raw
            return
        wanted = {c.topic for c in connections}
        with contextlib.ExitStack() as stack:
            streams = []
            for file in self.files:
                reader = stack.enter_context(Reader(file))
                conns = [c for c in reader.connections if c.topic in wanted]
                if conns:  # none: rosbags would read every connection
                    streams.append(
                        (c.topic, t, raw) for c, t, raw in reader.messages(connections=conns)
                    )
            yield from heapq.merge(*streams, key=lambda m: m[1])

    # --- lifetime ----------------------------------------------------------------
    def close(self) -> None:
        if self._reader is not None:
            self._reader.close()

    def __enter__(self) -> "BagReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _first_time(chunk: ChunkData) -> int:
    """The earliest log time in a chunk (its record's start time, or its messages' least)."""
    if chunk.start_ns is not None:
        return chunk.start_ns
    times = [t.min() for t, _ in chunk.index.values() if len(t)]
    return int(min(times)) if times else np.iinfo(np.int64).max


def _merge_by_time(batches: list[MessageBatch]) -> MessageBatch:
    """Several chunks, or several channels of one topic in a chunk (e.g. two QoS variants):
    one batch, in log-time order."""
    merged = MessageBatch.concat(batches)
    order = np.argsort(merged.log_times, kind="stable")
    return merged.take(order)


def bag_fingerprint(path: str | os.PathLike) -> str:
    """SHA-256 of a bag's content (metadata.yaml and its data files, in the order the
    metadata lists them): tells whether a bag is still the one a model was made from."""
    path = Path(path)
    digest = hashlib.sha256()
    with BagReader(path) as reader:
        files = [*([path / "metadata.yaml"] if path.is_dir() else []), *reader.files]
    for file in files:
        digest.update(file.name.encode() + b"\0")
        with open(file, "rb") as fh:
            while block := fh.read(1 << 22):
                digest.update(block)
    return digest.hexdigest()


def bag_topics(path: str | os.PathLike) -> dict[str, tuple[str, int]]:
    """{topic: (msgtype, message count)} of a bag."""
    with BagReader(path) as reader:
        return {t: (i.msgtype, i.count) for t, i in reader.topics.items()}
