"""egovib_ros.bag.mcapfile: MCAP files written and scanned chunk by chunk with numpy, as the
`mcap` library reads and writes them; chunks edited and copied verbatim; damage detected."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from synthetic import random_recording

from egovib_ros.bag import BagReader, encode_imu_batch, read_recording, write_recording
from egovib_ros.bag.mcapfile import McapFormatError, McapScanner, McapWriter, gather, rows
from egovib_ros.bag.recording import bag_topic_names
from egovib_ros.errors import BagError

BAG_TOPICS = bag_topic_names()  # the PR2 hand's


def test_chunk_without_channels(tmp_path):
    rec = random_recording(seconds=0.5)
    write_recording(tmp_path / "bag", rec)
    with BagReader(tmp_path / "bag") as reader:
        batch = next(iter(reader.batches()))
        drop = {c for c, t in batch.topic_of_channel.items() if t == BAG_TOPICS["contact"]}
        chunk = batch.chunks[0]
        kept = chunk.without(drop)
    assert set(kept.index) == set(chunk.index) - drop
    for channel, (times, _offsets) in kept.index.items():
        np.testing.assert_array_equal(times, chunk.index[channel][0])
        old_times, old_starts, lengths = chunk.data_span(channel)
        _, new_starts, new_lengths = kept.data_span(channel)
        np.testing.assert_array_equal(lengths, new_lengths)
        for a, b, n in zip(old_starts[:5], new_starts[:5], lengths[:5]):
            assert chunk.records[a : a + n] == kept.records[b : b + n]


@pytest.mark.parametrize("crc", [True, False])
def test_damaged_records_are_detected(tmp_path, crc):
    """A flipped byte inside a chunk: refused by the chunk CRC; without CRCs, a message record
    whose opcode was damaged is missing from the count the bag's index gives."""
    rec = random_recording(seconds=2.0)
    write_recording(tmp_path / "bag", rec, crc=crc)
    mcap = next((tmp_path / "bag").glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    at = data.find(encode_imu_batch(rec.sensor_stamps_ns[4000:4001], rec.sensor[4000:4001])[0])
    assert at > 31 and data[at - 31] == 0x05
    data[at - 31] = 0xFA  # no longer a message record
    mcap.write_bytes(bytes(data))
    expected = "CRC mismatch" if crc else "lost to damaged records|do not match|index lists"
    with pytest.raises(BagError, match=f"bag.*({expected})") as info:
        read_recording(tmp_path / "bag")
    assert "\n" not in str(info.value)


# --------------------------------------------------------------------------
# McapWriter and McapScanner on their own, against the `mcap` library
# --------------------------------------------------------------------------
def _write_two_topics(path, *, compression="", chunk_bytes=4096, seed=0):
    """A fixed-width topic (numpy rows) and a topic of messages of different lengths,
    interleaved in time; returns {topic: [(log time, data)]} as written."""
    rng = np.random.default_rng(seed)
    times_a = np.arange(500, dtype=np.int64) * 1_000_000 + 7
    data_a = rng.integers(0, 256, (500, 40), dtype=np.uint8)
    times_b = np.arange(60, dtype=np.int64) * 8_000_000 + 3
    data_b = [bytes(rng.integers(0, 256, int(k), dtype=np.uint8)) for k in rng.integers(1, 90, 60)]
    writer = McapWriter(path, compression=compression, chunk_bytes=chunk_bytes)
    schema = writer.add_schema("pkg/msg/A", "ros2msg", b"uint8[40] data")
    a = writer.add_channel("/a", schema, "cdr", {"offered_qos_profiles": ""})
    b = writer.add_channel("/b", writer.add_schema("pkg/msg/B", "ros2msg", b"uint8[] d"), "cdr", {})
    cuts = np.r_[np.iinfo(np.int64).min, times_a[50::50], np.iinfo(np.int64).max]
    for k in range(10):  # in time order: topic b's messages between a's batches
        writer.add_records(a, times_a[50 * k : 50 * k + 50], data_a[50 * k : 50 * k + 50])
        now = np.flatnonzero((times_b >= cuts[k]) & (times_b < cuts[k + 1]))
        writer.add_records(b, times_b[now], [data_b[i] for i in now])
    writer.close(metadata={"rosbag2": {"serialized_metadata": "x"}})
    return {
        "/a": [(int(t), bytes(d)) for t, d in zip(times_a, data_a)],
        "/b": [(int(t), d) for t, d in zip(times_b, data_b)],
    }


@pytest.mark.parametrize("compression", ["", "zstd"])
def test_written_records_read_back_by_the_mcap_library_and_the_scanner(tmp_path, compression):
    from mcap.reader import make_reader

    path = tmp_path / "two.mcap"
    written = _write_two_topics(path, compression=compression)
    with open(path, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        got = {"/a": [], "/b": []}
        for _, channel, message in reader.iter_messages(log_time_order=False):
            assert message.publish_time == message.log_time
            got[channel.topic].append((message.log_time, bytes(message.data)))
        summary = reader.get_summary()
    assert got == written
    assert len(summary.chunk_indexes) > 5  # 4 kB chunks
    assert all(c.compression == compression for c in summary.chunk_indexes)
    scanner = McapScanner(path)
    scanned = {"/a": [], "/b": []}
    frontier = None
    for chunk in scanner.chunks():
        assert chunk.start_ns is not None and any(len(t) for t, _ in chunk.index.values())
        for channel, (times, _) in chunk.index.items():
            assert frontier is None or times.min() >= frontier  # no message older than promised
            log_times, starts, lengths = chunk.data_span(channel)
            topic = scanner.channels[channel].topic
            scanned[topic] += [
                (int(t), chunk.records[s : s + n]) for t, s, n in zip(log_times, starts, lengths)
            ]
        frontier = chunk.frontier_ns
    assert {t: sorted(m) for t, m in scanned.items()} == written
    assert {c.topic for c in scanner.channels.values()} == {"/a", "/b"}


def test_chunks_come_in_log_time_order_when_the_file_is_not(tmp_path):
    """A file whose chunks were written one topic after the other: the scan seeks along the
    chunk index, so each chunk's messages come no earlier than the frontier promised."""
    path = tmp_path / "by_topic.mcap"
    times = np.arange(2000, dtype=np.int64) * 1_000_000
    writer = McapWriter(path, chunk_bytes=20_000)
    schema = writer.add_schema("pkg/msg/A", "ros2msg", b"")
    for topic in ("/a", "/b"):
        channel = writer.add_channel(topic, schema, "cdr", {})
        writer.add_records(channel, times, np.zeros((2000, 16), np.uint8))
        writer.flush_chunk()
    writer.close()
    starts, promised = [], None
    for chunk in McapScanner(path).chunks():
        starts.append(chunk.start_ns)
        if promised is not None:
            assert all(t.min() >= promised for t, _ in chunk.index.values())
        promised = chunk.frontier_ns
    assert starts == sorted(starts) and len(starts) > 4


def test_rows_and_gather_read_what_struct_reads():
    rng = np.random.default_rng(2)
    raw = bytes(rng.integers(0, 256, 1000, dtype=np.uint8))
    buf = np.frombuffer(raw, np.uint8)
    positions = np.array([0, 3, 17, 500, 991])
    np.testing.assert_array_equal(
        gather(buf, positions, "<u8"), [struct.unpack_from("<Q", raw, p)[0] for p in positions]
    )
    np.testing.assert_array_equal(
        gather(buf, positions, "<f4"), [struct.unpack_from("<f", raw, p)[0] for p in positions]
    )
    assert rows(buf, positions, 9).tolist() == [list(raw[p : p + 9]) for p in positions]
    short = np.frombuffer(b"abc", np.uint8)
    assert rows(short, np.array([], np.int64), 8).shape == (0, 8)


def test_a_chunk_is_copied_verbatim_only_into_the_same_definitions(tmp_path):
    written = tmp_path / "in.mcap"
    _write_two_topics(written)
    scanner = McapScanner(written)
    chunk = next(iter(scanner.chunks()))
    same = McapWriter(tmp_path / "same.mcap")
    for s in scanner.schemas.values():
        same.add_schema(s.name, s.encoding, s.data, schema_id=s.id)
    for c in scanner.channels.values():
        same.add_channel(c.topic, c.schema_id, c.message_encoding, c.metadata, channel_id=c.id)
    assert same.accepts_verbatim(chunk, scanner.schemas, scanner.channels)
    same.add_chunk_records(chunk)
    same.close()
    copied = next(iter(McapScanner(tmp_path / "same.mcap").chunks()))
    assert copied.records == chunk.records
    other = McapWriter(tmp_path / "other.mcap")
    sid = other.add_schema("pkg/msg/A", "ros2msg", b"uint8[40] data")
    other.add_channel("/renamed", sid, "cdr", {})
    assert not other.accepts_verbatim(chunk, scanner.schemas, scanner.channels)
    other.abort()


def test_not_mcap_and_truncated_files_are_format_errors(tmp_path):
    (tmp_path / "text.mcap").write_bytes(b"hello, not an mcap file")
    with pytest.raises(McapFormatError, match="bad magic"):
        list(McapScanner(tmp_path / "text.mcap").chunks())
    _write_two_topics(tmp_path / "whole.mcap")
    data = (tmp_path / "whole.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    with pytest.raises(McapFormatError):
        list(McapScanner(tmp_path / "cut.mcap").chunks())


@pytest.fixture(scope="module")
def small_zstd_bag(tmp_path_factory):
    """A 1 s bag in zstd chunks without CRCs (damage is met by the parser, not the CRC), and
    where its chunk records and message indexes start (damage there is what a parser meets
    first: compression names, sizes, frame headers, index lengths)."""
    from mcap.reader import make_reader

    path = tmp_path_factory.mktemp("fuzz") / "bag"
    write_recording(path, random_recording(seconds=1.0), compress=True, crc=False)
    with open(next(path.glob("*.mcap")), "rb") as fh:
        chunks = make_reader(fh).get_summary().chunk_indexes
    spots = [c.chunk_start_offset for c in chunks]
    spots += [c.chunk_start_offset + c.chunk_length for c in chunks]  # message indexes
    return path, spots


@settings(
    max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    spot=st.integers(0, 10_000),
    offset=st.integers(0, 80),
    anywhere=st.floats(0.0, 1.0, exclude_max=True),
    near_structure=st.booleans(),
    junk=st.binary(min_size=1, max_size=8),
)
def test_damaged_bytes_anywhere_are_a_bag_error_or_nothing(
    small_zstd_bag, tmp_path, spot, offset, anywhere, near_structure, junk
):
    """Bytes overwritten in the MCAP file (near a chunk record's or message index's start,
    or anywhere): reading gives the recording or one BagError line, never another exception
    (an unexpected one would be an internal error, exit 1)."""
    import shutil
    import uuid

    source, spots = small_zstd_bag
    bag = tmp_path / uuid.uuid4().hex
    shutil.copytree(source, bag)
    mcap = next(bag.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    at = spots[spot % len(spots)] + offset if near_structure else int(anywhere * len(data))
    at = min(at, len(data) - 1)
    data[at : at + len(junk)] = junk[: len(data) - at]
    mcap.write_bytes(bytes(data))
    try:
        read_recording(bag)
    except BagError as exc:
        assert "\n" not in str(exc)
