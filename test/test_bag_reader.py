"""egovib_ros.bag.reader: the chunk scan reads what rosbags' reader reads, from this project's
bags and from the layouts the `mcap` library writes.
"""

from __future__ import annotations

import numpy as np
import pytest
from synthetic import RECORDING_FIELDS, random_recording

from egovib_ros.bag import BagReader, BagWriter, codec, read_recording, write_recording
from egovib_ros.bag.codec import encode_imu_batch
from egovib_ros.errors import BagError


@pytest.mark.parametrize("compress", [False, True])
def test_chunk_scan_equals_rosbags_reader(tmp_path, monkeypatch, compress):
    rec = random_recording(seconds=2.0)
    rec.denoised_stamps_ns, rec.denoised = rec.sensor_stamps_ns, rec.sensor * 0.25
    write_recording(tmp_path / "bag", rec, compress=compress)
    with BagReader(tmp_path / "bag") as reader:
        assert reader.is_plain_mcap
    fast = read_recording(tmp_path / "bag")
    monkeypatch.setattr(
        BagReader, "is_plain_mcap", property(lambda self: False)
    )  # force rosbags' reader
    slow = read_recording(tmp_path / "bag")
    for name in RECORDING_FIELDS:
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)
        np.testing.assert_array_equal(getattr(fast, name), getattr(rec, name), err_msg=name)


# --------------------------------------------------------------------------
# MCAP as other writers lay it out
# --------------------------------------------------------------------------
def _rewrite_with_mcap_library(bag, **writer_options):
    """Rewrite a bag's .mcap with the `mcap` library's writer (same topics, schemas, times)."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    mcap = next(bag.glob("*.mcap"))
    with open(mcap, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        messages = [(c.id, m.log_time, m.data) for _, c, m in reader.iter_messages()]
    with open(mcap, "wb") as out:
        writer = Writer(out, **writer_options)
        writer.start(profile="ros2", library="test")
        for s in summary.schemas.values():
            writer.register_schema(s.name, s.encoding, s.data)
        for c in summary.channels.values():
            writer.register_channel(c.topic, c.message_encoding, c.schema_id, dict(c.metadata))
        for channel, t, data in messages:
            writer.add_message(channel, t, data, t)
        writer.finish()


@pytest.mark.parametrize("layout", ["indexed_zstd", "chunks_without_index", "unchunked"])
def test_reads_mcap_from_other_writers(tmp_path, monkeypatch, layout):
    from mcap.writer import CompressionType, IndexType

    options = {
        "indexed_zstd": dict(chunk_size=20_000, compression=CompressionType.ZSTD),
        "chunks_without_index": dict(
            chunk_size=50_000, compression=CompressionType.NONE, index_types=IndexType.NONE
        ),
        "unchunked": dict(use_chunking=False, compression=CompressionType.NONE),
    }[layout]
    rec = random_recording(seconds=1.0)
    write_recording(tmp_path / "bag", rec)
    _rewrite_with_mcap_library(tmp_path / "bag", **options)
    fast = read_recording(tmp_path / "bag")
    monkeypatch.setattr(BagReader, "is_plain_mcap", property(lambda self: False))
    slow = read_recording(tmp_path / "bag")
    for name in RECORDING_FIELDS:
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)
        np.testing.assert_array_equal(getattr(fast, name), getattr(rec, name), err_msg=name)


def test_a_missing_topic_names_what_the_bag_has_instead(tmp_path):
    """The README's commands without --robot on the arm's bag, and a profile topic written
    without its leading slash: each refusal says what is there."""
    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic("/arm/imu", codec.IMU_TYPE)
        bag.write_batch(
            "/arm/imu", np.array([1, 2]), encode_imu_batch(np.array([1, 2]), np.ones((2, 3)))
        )
    with BagReader(tmp_path / "bag") as reader:
        with pytest.raises(
            BagError,
            match=r"missing topic /accelerometer/raw \(its Imu topics: /arm/imu: the profile "
            r"of another robot\?\)$",
        ):
            reader.require("/accelerometer/raw", codec.IMU_TYPE)
        with pytest.raises(
            BagError,
            match=r"missing topic arm/imu \(it has /arm/imu: a topic in a robot profile "
            r"starts with /\)$",
        ):
            reader.require("arm/imu", codec.IMU_TYPE)


def test_a_topic_carrying_two_message_types_is_refused_naming_both(tmp_path):
    """Two publishers of different types on one topic (a probe's bag: an Imu and a
    Vector3Stamped on /arm/imu): said, not 'cannot decode message (buffer size is 40)'."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    store = codec.typestore()
    with Writer(tmp_path / "bag", version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
        for msgtype in (codec.IMU_TYPE, "geometry_msgs/msg/Vector3Stamped"):
            writer.add_connection("/arm/imu", msgtype, typestore=store)
    with (
        BagReader(tmp_path / "bag") as reader,
        pytest.raises(BagError, match=r"topic /arm/imu carries 2 message types \("),
    ):
        reader.require("/arm/imu", codec.IMU_TYPE)
