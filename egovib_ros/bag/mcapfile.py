"""MCAP files chunk by chunk, with numpy doing the per-message work.

A 3 kHz Imu stream is ~11 million messages per topic an hour; one Python call per message
(rosbags, or the `mcap` library's reader and writer) costs minutes per hour of recording
(docs/bench_bags.md). Here a chunk is the unit of work:

- reading: the chunk is decompressed once; its messages' offsets come from its Message
  Index records (checked: every byte they do not cover must be a non-message record, else
  the records are walked one by one); fields are then gathered with numpy;
- writing: a chunk is a list of parts, each either records copied verbatim from an input
  chunk (topics only copied are never decoded) or a topic's messages laid out as one
  (n, 31 + L) byte array. Records are grouped by part, not interleaved by time: readers
  order messages by log time (rosbags sorts each chunk, MCAP readers use the indexes).

The structural records (header, schema, channel, chunk index, statistics, summary offsets,
footer) are the `mcap` library's record classes (https://mcap.dev/spec).
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Iterator

import numpy as np
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.reader import make_reader
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

MAGIC = b"\x89MCAP0\r\n"
OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK, OP_MESSAGE_INDEX = 2, 3, 4, 5, 6, 7
OP_CHUNK_INDEX, OP_STATISTICS, OP_METADATA_INDEX, OP_DATA_END = 8, 11, 13, 15
MESSAGE_HEADER = 31  # opcode 1 + length 8 + channel 2 + sequence 4 + log time 8 + publish time 8
_U16, _U32, _U64 = np.dtype("<u2"), np.dtype("<u4"), np.dtype("<u8")
_RECORD_HEADER = struct.Struct("<BQ")
# the leading fields of every message record, for writing (n, 31 + L) arrays
_MESSAGE_FIELDS = dict(
    names=["op", "length", "channel", "sequence", "log_time", "publish_time"],
    formats=["u1", "<u8", "<u2", "<u4", "<u8", "<u8"],
    offsets=[0, 1, 9, 11, 15, 23],
)


class McapFormatError(ValueError):
    """The file is not the MCAP the scan expects (the caller names the file)."""


class McapDamaged(McapFormatError):
    """The file is damaged (CRC mismatch, records that contradict the index, truncation)."""


def rows(buf: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray:
    """(n, width) copy of the byte runs buf[s:s + width] (a row gather on a sliding-window
    view: one memcpy per row, ~10x faster than a 2-D index array)."""
    if len(buf) < width:
        return (
            np.zeros((0, width), np.uint8)
            if len(starts) == 0
            else buf[starts[:, None] + np.arange(width)]
        )
    windows = np.ndarray((len(buf) - width + 1, width), np.uint8, buffer=buf, strides=(1, 1))
    return windows[starts]


def gather(buf: np.ndarray, positions: np.ndarray, dtype: np.dtype | str) -> np.ndarray:
    """Little-endian values of `dtype` starting at byte `positions` of a uint8 buffer."""
    dtype = np.dtype(dtype)
    return rows(buf, positions, dtype.itemsize).view(dtype).reshape(len(positions))


# --- reading ------------------------------------------------------------------------------
@dataclass
class ChunkData:
    """The records of one chunk (or of loose top-level messages), decompressed.

    `index` maps channel id -> (log times, record offsets), each channel in record order.
    `definitions` lists the schema/channel records found inside the chunk (opcode, id).
    """

    records: bytes
    index: dict[int, tuple[np.ndarray, np.ndarray]]
    definitions: list[tuple[int, int]] = field(default_factory=list)
    file_bytes: int = 0  # bytes of the file consumed up to this chunk (progress bars)
    # No message read after this chunk has a log time below `frontier_ns` (None: unknown).
    frontier_ns: int | None = None
    # record lengths per channel, if known
    lengths: dict[int, np.ndarray] = field(default_factory=dict)
    start_ns: int | None = None  # the chunk record's message start/end time (None: loose messages)
    end_ns: int | None = None

    @property
    def buffer(self) -> np.ndarray:
        return np.frombuffer(self.records, np.uint8)

    def data_span(self, channel_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(log times, data starts, data lengths) of a channel's messages in `records`."""
        times, offsets = self.index[channel_id]
        lengths = self.lengths.get(channel_id)
        if lengths is None:
            lengths = gather(self.buffer, offsets + 1, _U64).astype(np.int64)
        return times, offsets + MESSAGE_HEADER, lengths - 22

    def without(self, channel_ids: set[int]) -> "ChunkData":
        """A copy without the messages (and channel records) of `channel_ids`."""
        buf, keep, pos = self.records, [], 0
        while pos < len(buf):
            op, length = _RECORD_HEADER.unpack_from(buf, pos)
            of_channel = op in (OP_MESSAGE, OP_CHANNEL)  # its channel id follows the header
            if not of_channel or struct.unpack_from("<H", buf, pos + 9)[0] not in channel_ids:
                keep.append(memoryview(buf)[pos : pos + 9 + length])
            pos += 9 + length
        return _walk(b"".join(keep), lambda op, body: (op, struct.unpack_from("<H", body)[0]))


class McapScanner:
    """Reader of one MCAP file, chunk by chunk (bounded memory: one chunk); `schemas` and
    `channels` (mcap records by id) fill in before the chunks that use them."""

    # group messages outside chunks (unchunked files) this many bytes at a time
    loose_bytes = 4 << 20

    def __init__(self, path: str | Path, *, cut: bool = False):
        """`cut`: the file ends without its summary and footer (a recorder killed mid-write,
        `ends_complete` False): read every complete record up to where it stops, and say
        where that was in `cut_at` (file offset; None while not reached)."""
        self.path = Path(path)
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.cut = cut
        self.cut_at: int | None = None
        # A cut file's chunk index, rebuilt by a first scan: a second scanner given it
        # (`reuse`) reads the chunks in time order, as from a summary.
        self.chunk_index: list[ChunkIndex] = []
        self.rebuilt: list[ChunkIndex] | None = None

    def chunks(self) -> Iterator[ChunkData]:
        """Chunks in order of their first message's log time: file order for files written
        in time order (read front to back), else by seeking along the summary's chunk index
        (chunks written per topic, or out of order) so that the topics arrive together.
        Bytes that do not parse are damage (McapDamaged), wherever they are in the file."""
        try:
            with open(self.path, "rb") as fh:
                if hasattr(os, "posix_fadvise"):  # one pass front to back: read ahead further
                    os.posix_fadvise(fh.fileno(), 0, 0, os.POSIX_FADV_SEQUENTIAL)
                if fh.read(8) != MAGIC:
                    raise McapFormatError("not an MCAP file (bad magic)")
                by_time, by_file = self._time_order(fh)
                if by_time is not None:
                    yield from self._seeking(fh, by_time)
                    return
                fh.seek(8)
                yield from self._sequential(
                    fh, [c.message_start_time for c in by_file] if by_file else None
                )
        except McapFormatError:
            raise
        except Exception as exc:  # struct, decoding, seeks and reads sized by damaged fields
            raise _damage("record", exc) from None

    def reuse(self, first: "McapScanner") -> "McapScanner":
        """Read a cut file with the chunk index and definitions a first scan rebuilt."""
        self.rebuilt = list(first.chunk_index)
        self.schemas.update(first.schemas)
        self.channels.update(first.channels)
        return self

    def _time_order(self, fh) -> tuple[list | None, list | None]:
        """(the summary's chunk indexes by start time if that differs from file order, else
        None; the chunk indexes in file order, or None without a summary)."""
        if self.rebuilt:
            indexes = self.rebuilt
        else:
            try:
                fh.seek(0)
                summary = make_reader(fh).get_summary()
            except Exception:
                return None, None
            if summary is None or not summary.chunk_indexes:
                return None, None
            indexes = summary.chunk_indexes
            self.schemas.update(summary.schemas)
            self.channels.update(summary.channels)
        by_file = sorted(indexes, key=lambda c: c.chunk_start_offset)
        # stable: ties keep file order
        by_time = sorted(by_file, key=lambda c: c.message_start_time)
        if [c.chunk_start_offset for c in by_time] == [c.chunk_start_offset for c in by_file]:
            return None, by_file
        return by_time, by_file

    def _seeking(self, fh, order: list) -> Iterator[ChunkData]:
        starts = [c.message_start_time for c in order[1:]] + [None]
        for index, frontier in zip(order, starts):
            fh.seek(index.chunk_start_offset)
            op, length = _RECORD_HEADER.unpack(_read_exact(fh, 9))
            if op != OP_CHUNK:
                raise McapFormatError("chunk index points at something else than a chunk")
            body = _read_exact(fh, length)
            fh.seek(index.chunk_start_offset + index.chunk_length)
            raw = _read_exact(fh, index.message_index_length)
            bodies, pos = [], 0
            while pos + 9 <= len(raw):
                op, length = _RECORD_HEADER.unpack_from(raw, pos)
                if op == OP_MESSAGE_INDEX:
                    bodies.append(raw[pos + 9 : pos + 9 + length])
                pos += 9 + length
            chunk = self._finish_chunk(body, bodies)
            chunk.file_bytes = index.chunk_length + index.message_index_length
            chunk.frontier_ns = frontier if frontier is not None else index.message_end_time
            yield chunk

    def _sequential(self, fh, starts: list[int] | None) -> Iterator[ChunkData]:  # noqa: C901 (one pass over MCAP's record kinds; split, its pending-chunk state would be passed around)
        """Front to back. `starts`: each chunk's first log time (from the summary), which
        tells where the next chunk begins; without it a chunk's own start is the bound."""
        pending: tuple | None = None  # a chunk waiting for its message indexes
        pending_at = (0, 0)  # where its record starts and ends in the file
        loose: list[bytes] = []
        loose_size = 0
        consumed = 0
        n_chunks = 0

        def progress(chunk: ChunkData) -> ChunkData:
            nonlocal consumed, n_chunks
            chunk.file_bytes, consumed = fh.tell() - consumed, fh.tell()
            if chunk.start_ns is None:  # loose messages
                chunk.frontier_ns = chunk.end_ns
            elif starts is None:  # no summary: the chunk's own start is the bound
                chunk.frontier_ns = chunk.start_ns
            else:  # the next chunk's start
                n_chunks += 1
                chunk.frontier_ns = starts[n_chunks] if n_chunks < len(starts) else chunk.end_ns
            return chunk

        while True:
            at = fh.tell()
            head = fh.read(9)
            if len(head) < 9:
                if not self.cut:
                    raise McapDamaged("truncated (no footer)")
                self.cut_at = at
                break
            op, length = _RECORD_HEADER.unpack(head)
            if self.cut and length > os.fstat(fh.fileno()).st_size - fh.tell():
                # the record the recorder was writing when it stopped: what came before is
                # whole (a chunk whose message indexes are cut is read by its records)
                self.cut_at = at
                if op == OP_MESSAGE_INDEX and pending is not None:
                    pending = (pending[0], [])
                break
            if op == OP_MESSAGE_INDEX and pending is not None:
                pending[1].append(_read_exact(fh, length))
                continue
            if pending is not None:
                yield progress(self._finish_chunk(*pending))
                self._note_chunk(pending[0], pending_at, at)
                pending = None
            if op == OP_CHUNK:
                pending, pending_at = (_read_exact(fh, length), []), (at, fh.tell())
            elif op == OP_MESSAGE:
                loose.append(head + _read_exact(fh, length))
                loose_size += 9 + length
                if loose_size >= self.loose_bytes:
                    yield progress(_walk(b"".join(loose), self._define))
                    loose, loose_size = [], 0
            elif op in (OP_SCHEMA, OP_CHANNEL):
                self._define(op, _read_exact(fh, length))
            elif op in (OP_DATA_END, OP_FOOTER):
                break
            else:
                fh.seek(length, io.SEEK_CUR)
        if pending is not None:  # cut after this chunk
            yield progress(self._finish_chunk(*pending))
            self._note_chunk(
                pending[0], pending_at, pending_at[1] if not pending[1] else self.cut_at
            )
        if loose:
            yield progress(_walk(b"".join(loose), self._define))

    # --- internals -------------------------------------------------------------
    def _note_chunk(self, body: bytes, at: tuple[int, int], indexes_end: int) -> None:
        """A cut file: the chunk index entry of a chunk read (its record's body, start and
        end, where its message indexes end), as a summary would have listed it."""
        if not self.cut:
            return
        start, end = at
        first, last = struct.unpack_from("<QQ", body)
        self.chunk_index.append(
            ChunkIndex(
                message_start_time=first,
                message_end_time=last,
                chunk_start_offset=start,
                chunk_length=end - start,
                message_index_offsets={},
                message_index_length=indexes_end - end,
                compression="",
                compressed_size=0,
                uncompressed_size=0,
            )
        )

    def _define(self, op: int, body: bytes | memoryview) -> tuple[int, int]:
        stream = ReadDataStream(io.BytesIO(bytes(body)))
        if op == OP_SCHEMA:
            schema = Schema.read(stream)
            self.schemas[schema.id] = schema
            return op, schema.id
        channel = Channel.read(stream)
        self.channels[channel.id] = channel
        return op, channel.id

    def _finish_chunk(self, body: bytes, index_bodies: list[bytes]) -> ChunkData:
        """The chunk's records, decompressed and indexed. Any failure to parse them is
        damage (McapDamaged): the bytes of a chunk record are the file's, not ours."""
        try:
            return self._parse_chunk(body, index_bodies)
        except McapFormatError:
            raise
        except Exception as exc:  # struct, decoding, decompression, index arithmetic
            raise _damage("chunk", exc) from None

    def _parse_chunk(self, body: bytes, index_bodies: list[bytes]) -> ChunkData:
        start, end, size, crc = struct.unpack_from("<QQQI", body, 0)
        n = struct.unpack_from("<I", body, 28)[0]
        compression = bytes(body[32 : 32 + n]).decode()
        compressed_size = struct.unpack_from("<Q", body, 32 + n)[0]
        data = memoryview(body)[40 + n : 40 + n + compressed_size]
        if len(data) != compressed_size:
            raise McapFormatError("chunk shorter than its declared size")
        if compression and size > max(1 << 30, 1000 * compressed_size):
            raise McapDamaged(f"chunk claims {size} bytes from {compressed_size} (damaged size)")
        records = _decompress(data, compression, size)
        if crc and zlib.crc32(records) != crc:
            raise McapDamaged("chunk CRC mismatch (damaged file)")
        index = {}
        for ib in index_bodies:
            channel, nbytes = struct.unpack_from("<HI", ib, 0)
            pairs = (
                np.frombuffer(ib, _U64, count=nbytes // 8, offset=6).reshape(-1, 2).astype(np.int64)
            )
            index[channel] = (pairs[:, 0], pairs[:, 1])
        checked = self._check_index(records, index) if index else None
        chunk = checked if checked is not None else _walk(records, self._define)
        if index and checked is None:
            # the index lists messages the records do not hold as such: records were damaged
            listed = {c: len(t) for c, (t, _) in index.items() if len(t)}
            found = {c: len(t) for c, (t, _) in chunk.index.items() if len(t)}
            if listed != found:
                differ = sorted(c for c in {*listed, *found} if listed.get(c) != found.get(c))
                raise McapDamaged(
                    "a chunk's message records do not match its index (damaged records): "
                    + ", ".join(
                        f"channel {c}: {found.get(c, 0)} records, {listed.get(c, 0)} indexed"
                        for c in differ[:3]
                    )
                )
        chunk.start_ns, chunk.end_ns = start, end
        return chunk

    def _check_index(self, records: bytes, index: dict) -> ChunkData | None:
        """ChunkData from the message indexes if they account for every message record
        of the chunk, else None (the caller walks the records)."""
        buf = np.frombuffer(records, np.uint8)
        size = len(buf)
        channels = np.concatenate([np.full(len(o), c, np.int64) for c, (_, o) in index.items()])
        offsets = np.concatenate([o for _, o in index.values()])
        if len(offsets) == 0:
            return None
        if offsets.min() < 0 or offsets.max() + MESSAGE_HEADER > size:
            return None
        if not np.all(buf[offsets] == OP_MESSAGE) or not np.array_equal(
            gather(buf, offsets + 9, _U16), channels
        ):
            return None
        record_lengths = gather(buf, offsets + 1, _U64).astype(np.int64)
        ends = offsets + 9 + record_lengths
        order = np.argsort(offsets, kind="stable")
        starts_sorted, ends_sorted = offsets[order], ends[order]
        if ends_sorted.max() > size or np.any(starts_sorted[1:] < ends_sorted[:-1]):
            return None
        # Every gap between indexed messages must hold only non-message records.
        definitions = []
        gap_from = np.concatenate([[0], ends_sorted])
        gap_to = np.concatenate([starts_sorted, [size]])
        for a, b in zip(gap_from[gap_from != gap_to].tolist(), gap_to[gap_from != gap_to].tolist()):
            pos = a
            while pos < b:
                if pos + 9 > b:
                    return None
                op, length = _RECORD_HEADER.unpack_from(records, pos)
                if op == OP_MESSAGE:
                    return None
                if op in (OP_SCHEMA, OP_CHANNEL):
                    definitions.append(
                        self._define(op, memoryview(records)[pos + 9 : pos + 9 + length])
                    )
                pos += 9 + length
            if pos != b:
                return None
        lengths, at = {}, 0
        for channel, (times, offs) in index.items():
            lengths[channel] = record_lengths[at : at + len(offs)]
            at += len(offs)
            if len(offs) > 1 and np.any(np.diff(offs) < 0):  # keep record order per channel
                order = np.argsort(offs, kind="stable")
                index[channel] = (times[order], offs[order])
                lengths[channel] = lengths[channel][order]
        return ChunkData(records, index, definitions, lengths=lengths)


def _walk(records: bytes, define) -> ChunkData:
    """Record by record (chunks without usable message indexes, loose messages, edited
    chunks); `define(op, body)` takes a schema or channel record, returns (op, id)."""
    per_channel: dict[int, tuple[list, list]] = {}
    definitions = []
    pos, size = 0, len(records)
    unpack_message = struct.Struct("<HIQ").unpack_from
    while pos < size:
        if pos + 9 > size:
            raise McapFormatError("truncated record in chunk")
        op, length = _RECORD_HEADER.unpack_from(records, pos)
        if pos + 9 + length > size:
            raise McapFormatError("truncated record in chunk")
        if op == OP_MESSAGE:
            channel, _, log_time = unpack_message(records, pos + 9)
            times, offsets = per_channel.setdefault(channel, ([], []))
            times.append(log_time)
            offsets.append(pos)
        elif op in (OP_SCHEMA, OP_CHANNEL):
            definitions.append(define(op, memoryview(records)[pos + 9 : pos + 9 + length]))
        pos += 9 + length
    index = {c: (np.array(t, np.int64), np.array(o, np.int64)) for c, (t, o) in per_channel.items()}
    chunk = ChunkData(records, index, definitions)
    times = [t.max() for t, _ in index.values() if len(t)]
    chunk.end_ns = int(max(times)) if times else None  # loose messages: the latest log time
    return chunk


def _damage(what: str, exc: Exception) -> McapDamaged:
    reason = (str(exc).splitlines() or [""])[0]
    return McapDamaged(f"damaged {what} ({type(exc).__name__}: {reason})")


def ends_complete(path: str | Path) -> bool:
    """The file ends with the MCAP magic (its footer was written): not cut short."""
    with open(path, "rb") as fh:
        size = fh.seek(0, io.SEEK_END)
        if size < 2 * len(MAGIC):
            return False
        fh.seek(size - len(MAGIC))
        return fh.read(len(MAGIC)) == MAGIC


def _read_exact(fh: BinaryIO, n: int) -> bytes:
    # a damaged length field must not become a read of exabytes (MemoryError, EINVAL)
    if n > os.fstat(fh.fileno()).st_size - fh.tell():
        raise McapDamaged("a record runs past the end of the file (damaged length)")
    data = fh.read(n)
    if len(data) != n:
        raise McapFormatError("truncated record")
    return data


def _decompress(data: memoryview, compression: str, size: int) -> bytes | memoryview:
    if compression == "":
        return data  # a view of the chunk record just read: no copy
    if compression == "zstd":
        import zstandard  # deferred: a codec library, loaded for the files that use it

        out = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    elif compression == "lz4":
        import lz4.frame  # deferred: a codec library, loaded for the files that use it

        out = lz4.frame.decompress(bytes(data))
    else:
        raise McapFormatError(f"unsupported chunk compression {compression!r}")
    if len(out) != size:
        raise McapFormatError("chunk size mismatch after decompression")
    return out


# --- writing ------------------------------------------------------------------------------
def message_records(
    channel_id: int, log_times: np.ndarray, data: np.ndarray | None, width: int | None = None
) -> np.ndarray:
    """(n, 31 + L) uint8: one MCAP message record per row of `data` (n, L); publish time =
    log time, sequence 0 (as rosbag2 and rosbags write them). With `data` None the
    message bytes (columns 31:) are left for the caller to fill (`width` = L)."""
    n = len(log_times)
    width = data.shape[1] if data is not None else width
    out = np.empty((n, MESSAGE_HEADER + width), np.uint8)
    head = out.view(np.dtype(dict(_MESSAGE_FIELDS, itemsize=MESSAGE_HEADER + width))).reshape(n)
    head["op"] = OP_MESSAGE
    head["length"] = MESSAGE_HEADER - 9 + width
    head["channel"] = channel_id
    head["sequence"] = 0
    head["log_time"] = log_times
    head["publish_time"] = log_times
    if data is not None:
        out[:, MESSAGE_HEADER:] = data
    return out


class McapWriter:
    """Writes an MCAP file chunk by chunk from parts (see the module docstring): add_schema,
    add_channel, then add_records(channel, log_times, data) ... and close()."""

    def __init__(
        self,
        path: str | Path,
        *,
        compression: str = "",
        chunk_bytes: int = 4 << 20,
        library: str = "egovib_ros",
        crc: bool = True,
    ):
        if compression not in ("", "zstd"):
            raise ValueError(f"compression must be '' or 'zstd', got {compression!r}")
        self.path = Path(path)
        self._fh = open(self.path, "xb")  # noqa: SIM115 (the writer's own; closed by close())
        self.compression = compression
        self.chunk_bytes = int(chunk_bytes)
        self.crc = crc  # chunk CRCs: damage is detected on reading
        self._compress = None
        if compression == "zstd":
            import zstandard  # deferred: a codec library, loaded for the files that use it

            self._compress = zstandard.ZstdCompressor(level=1).compress
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.counts: dict[int, int] = {}
        self.start_time: int | None = None
        self.end_time: int | None = None
        self.bytes_uncompressed = 0
        self.bytes_compressed = 0
        self._chunk_indexes: list[ChunkIndex] = []
        self._parts: list[tuple[bytes | np.ndarray, dict]] = []
        self._pending = 0
        self._fh.write(MAGIC)
        self._write_record(Header(profile="ros2", library=library))

    # --- definitions -------------------------------------------------------------
    def add_schema(
        self, name: str, encoding: str, data: bytes, *, schema_id: int | None = None
    ) -> int:
        for s in self.schemas.values():
            if (s.name, s.encoding, s.data) == (name, encoding, data) and schema_id in (None, s.id):
                return s.id
        schema_id = schema_id if schema_id is not None else max(self.schemas, default=0) + 1
        if schema_id in self.schemas:
            raise ValueError(f"schema id {schema_id} already used")
        self.schemas[schema_id] = Schema(
            id=schema_id, name=name, encoding=encoding, data=bytes(data)
        )
        self._write_record(self.schemas[schema_id])
        return schema_id

    def add_channel(
        self,
        topic: str,
        schema_id: int,
        message_encoding: str,
        metadata: dict[str, str],
        *,
        channel_id: int | None = None,
    ) -> int:
        channel_id = channel_id if channel_id is not None else max(self.channels, default=0) + 1
        if channel_id in self.channels:
            raise ValueError(f"channel id {channel_id} already used")
        self.channels[channel_id] = Channel(
            id=channel_id,
            topic=topic,
            message_encoding=message_encoding,
            metadata=dict(metadata),
            schema_id=schema_id,
        )
        self.counts[channel_id] = 0
        self._write_record(self.channels[channel_id])
        return channel_id

    def accepts_verbatim(
        self, chunk: ChunkData, schemas: dict[int, Schema], channels: dict[int, Channel]
    ) -> bool:
        """Whether `chunk`'s records can be copied as they are: every channel and schema it
        uses or defines has the same id and content here (`schemas`/`channels`: the input's)."""
        for channel_id in chunk.index:
            mine, theirs = self.channels.get(channel_id), channels.get(channel_id)
            if (
                mine is None
                or theirs is None
                or (mine.topic, mine.schema_id, mine.message_encoding)
                != (theirs.topic, theirs.schema_id, theirs.message_encoding)
            ):
                return False
            if self.schemas.get(mine.schema_id) != schemas.get(theirs.schema_id):
                return False
        for op, ident in chunk.definitions:
            mine = (self.schemas if op == OP_SCHEMA else self.channels).get(ident)
            theirs = (schemas if op == OP_SCHEMA else channels).get(ident)
            if mine is None or mine != theirs:
                return False
        return True

    # --- messages ------------------------------------------------------------------
    def add_chunk_records(self, chunk: ChunkData) -> None:
        """Append an input chunk's records verbatim (see `accepts_verbatim`)."""
        index = {c: (t, o) for c, (t, o) in chunk.index.items() if len(t)}
        self._add_part(chunk.records, index, len(chunk.records))

    def add_records(self, channel_id: int, log_times: np.ndarray, data) -> None:
        """Append messages of one channel: `data` is (n, L) uint8 or a list of bytes."""
        log_times = np.asarray(log_times, np.int64)
        if len(log_times) == 0:
            return
        if not isinstance(data, np.ndarray):
            lengths = np.fromiter((len(d) for d in data), np.int64, len(data))
            if np.any(lengths != lengths[0]):  # rare topics: commands, odd bags
                pack, parts = struct.Struct("<BQHIQQ").pack, []
                for t, d in zip(log_times.tolist(), data):
                    parts += (pack(OP_MESSAGE, MESSAGE_HEADER - 9 + len(d), channel_id, 0, t, t), d)
                blob, sizes = b"".join(parts), lengths + MESSAGE_HEADER
                self._add_part(blob, {channel_id: (log_times, np.cumsum(sizes) - sizes)}, len(blob))
                return
            data = np.frombuffer(b"".join(data), np.uint8).reshape(len(data), int(lengths[0]))
        width = MESSAGE_HEADER + data.shape[1]
        step = max(1, (self.chunk_bytes - self._pending) // width)
        if step < len(log_times):  # keep chunks near chunk_bytes: split the batch
            self.add_records(channel_id, log_times[:step], data[:step])
            for a in range(step, len(log_times), max(1, self.chunk_bytes // width)):
                b = a + max(1, self.chunk_bytes // width)
                self.add_records(channel_id, log_times[a:b], data[a:b])
            return
        self.add_message_records(
            channel_id, log_times, message_records(channel_id, log_times, data)
        )

    def add_message_records(
        self, channel_id: int, log_times: np.ndarray, records: np.ndarray
    ) -> None:
        """Append records made by `message_records` (n, 31 + L) for this channel."""
        if len(log_times):
            offsets = np.arange(len(log_times), dtype=np.int64) * records.shape[1]
            self._add_part(
                np.ascontiguousarray(records),
                {channel_id: (np.asarray(log_times, np.int64), offsets)},
                records.nbytes,
            )

    def flush_chunk(self) -> None:
        """Close the chunk being built (if any)."""
        if not self._parts:
            return
        parts, self._parts, self._pending = self._parts, [], 0
        buffers = [p.reshape(-1).data if isinstance(p, np.ndarray) else p for p, _ in parts]
        index: dict[int, list] = {}
        base = 0
        for buffer, (_, part_index) in zip(buffers, parts):
            for channel, (times, offsets) in part_index.items():
                index.setdefault(channel, []).append((times, offsets + base))
            base += memoryview(buffer).nbytes
        merged = {}
        for channel, pieces in index.items():
            times = np.concatenate([t for t, _ in pieces])
            offsets = np.concatenate([o for _, o in pieces])
            if len(times) > 1 and np.any(np.diff(times) < 0):
                order = np.argsort(times, kind="stable")
                times, offsets = times[order], offsets[order]
            merged[channel] = (times, offsets)
            self.counts[channel] = self.counts.get(channel, 0) + len(times)
        start = min(int(t[0]) for t, _ in merged.values())
        end = max(int(t.max()) for t, _ in merged.values())
        self.start_time = start if self.start_time is None else min(self.start_time, start)
        self.end_time = end if self.end_time is None else max(self.end_time, end)
        size = base
        crc = 0
        for b in buffers if self.crc else ():
            crc = zlib.crc32(b, crc)
        if self._compress:
            buffers = [self._compress(b"".join(buffers))]
        data_size = sum(memoryview(b).nbytes for b in buffers)
        self.bytes_uncompressed += size
        self.bytes_compressed += data_size
        compression = self.compression.encode()
        chunk_start = self._fh.tell()
        length = 8 * 3 + 4 + 4 + len(compression) + 8 + data_size
        head = struct.pack("<BQQQQII", OP_CHUNK, length, start, end, size, crc, len(compression))
        self._fh.write(head + compression + struct.pack("<Q", data_size))
        for b in buffers:
            self._fh.write(b)
        chunk_end = self._fh.tell()
        index_offsets = {}
        for channel in sorted(merged):
            times, offsets = merged[channel]
            index_offsets[channel] = self._fh.tell()
            pairs = np.empty((len(times), 2), _U64)
            pairs[:, 0], pairs[:, 1] = times, offsets
            self._fh.write(
                struct.pack("<BQHI", OP_MESSAGE_INDEX, 6 + pairs.nbytes, channel, pairs.nbytes)
            )
            self._fh.write(pairs.tobytes())
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=start,
                message_end_time=end,
                chunk_start_offset=chunk_start,
                chunk_length=chunk_end - chunk_start,
                message_index_offsets=index_offsets,
                message_index_length=self._fh.tell() - chunk_end,
                compression=self.compression,
                compressed_size=data_size,
                uncompressed_size=size,
            )
        )

    def close(self, *, metadata: dict[str, dict[str, str]] | None = None) -> None:
        """Last chunk, then the summary section and footer. `metadata`: named Metadata
        records (rosbag2 stores its metadata.yaml text as "rosbag2")."""
        self.flush_chunk()
        metadata_indexes = []
        for name, values in (metadata or {}).items():
            offset = self._fh.tell()
            self._write_record(Metadata(name=name, metadata=values))
            metadata_indexes.append(
                MetadataIndex(offset=offset, length=self._fh.tell() - offset, name=name)
            )
        self._write_record(DataEnd(data_section_crc=0))
        summary_start = self._fh.tell()
        builder = RecordBuilder()
        offsets = []
        groups = [
            (OP_SCHEMA, list(self.schemas.values())),
            (OP_CHANNEL, list(self.channels.values())),
            (
                OP_STATISTICS,
                [
                    Statistics(
                        message_count=sum(self.counts.values()),
                        schema_count=len(self.schemas),
                        channel_count=len(self.channels),
                        attachment_count=0,
                        metadata_count=len(metadata_indexes),
                        chunk_count=len(self._chunk_indexes),
                        message_start_time=self.start_time or 0,
                        message_end_time=self.end_time or 0,
                        channel_message_counts=dict(sorted(self.counts.items())),
                    )
                ],
            ),
            (OP_CHUNK_INDEX, self._chunk_indexes),
            (OP_METADATA_INDEX, metadata_indexes),
        ]
        for opcode, records in groups:
            if not records:
                continue
            group_start = builder.count
            for record in records:
                record.write(builder)
            offsets.append(
                SummaryOffset(
                    group_opcode=opcode,
                    group_start=summary_start + group_start,
                    group_length=builder.count - group_start,
                )
            )
        summary_offset_start = summary_start + builder.count
        for offset in offsets:
            offset.write(builder)
        summary = builder.end()
        crc = zlib.crc32(
            struct.pack("<BQQQ", OP_FOOTER, 20, summary_start, summary_offset_start),
            zlib.crc32(summary),
        )
        self._fh.write(summary)
        self._write_record(
            Footer(
                summary_start=summary_start,
                summary_offset_start=summary_offset_start,
                summary_crc=crc,
            )
        )
        self._fh.write(MAGIC)
        self._fh.close()

    def abort(self) -> None:
        self._fh.close()

    # --- internals -------------------------------------------------------------------
    def _add_part(self, part, index: dict, nbytes: int) -> None:
        self._parts.append((part, index))
        self._pending += nbytes
        if self._pending >= self.chunk_bytes:
            self.flush_chunk()

    def _write_record(self, record) -> None:
        builder = RecordBuilder()
        record.write(builder)
        self._fh.write(builder.end())
