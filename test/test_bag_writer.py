"""egovib_ros.bag.writer: bags the `mcap` library and rosbags read back as written, in log-time
order, compressed, with chunks copied verbatim.
"""

from __future__ import annotations

import numpy as np
from rosbags.rosbag2 import Reader
from synthetic import random_recording

from egovib_ros.bag import (
    BagReader,
    BagWriter,
    codec,
    encode_imu_batch,
    encode_joint_state_batch,
    read_recording,
    write_recording,
)
from egovib_ros.bag.recording import bag_topic_names
from egovib_ros.sim.pr2 import JOINT_NAMES

BAG_TOPICS = bag_topic_names()  # the PR2 hand's


def test_bag_writer_raw_bytes(tmp_path):
    stamps = np.arange(10, dtype=np.int64) * 333_333
    accel = np.arange(30, dtype=float).reshape(10, 3)
    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic(BAG_TOPICS["raw"], codec.IMU_TYPE)
        bag.add_topic(BAG_TOPICS["joint_states"], codec.JOINT_STATE_TYPE)
        bag.write_batch(BAG_TOPICS["raw"], stamps, encode_imu_batch(stamps, accel))
        bag.write(
            BAG_TOPICS["joint_states"],
            0,
            encode_joint_state_batch([0], [[0.0, 0.01]], [[1.0, 0.02]], JOINT_NAMES)[0],
        )
    back = read_recording(tmp_path / "bag")
    np.testing.assert_array_equal(back.sensor, accel)
    np.testing.assert_array_equal(back.joint_velocity, [[1.0, 0.02]])


def test_written_mcap_is_valid_for_the_mcap_library_and_rosbags(tmp_path):
    """CRCs, summary, statistics and log-time order as the `mcap` library and rosbags check them."""
    from mcap.reader import make_reader

    rec = random_recording(seconds=3.0)
    write_recording(tmp_path / "bag", rec, compress="zstd")
    with open(next((tmp_path / "bag").glob("*.mcap")), "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        summary = reader.get_summary()
        times = [m.log_time for _, _, m in reader.iter_messages(log_time_order=True)]
    n = len(rec.sensor_stamps_ns)
    expected = 3 * n + len(rec.joint_stamps_ns) + len(rec.commands)
    assert summary.statistics.message_count == len(times) == expected
    assert all(ci.compression == "zstd" for ci in summary.chunk_indexes)
    assert times == sorted(times)
    with Reader(tmp_path / "bag") as reader:
        assert reader.message_count == expected
        log_times = [t for _, t, _ in reader.messages()]
        assert log_times == sorted(log_times)


def test_verbatim_chunk_copy(tmp_path):
    rec = random_recording(seconds=2.0)
    write_recording(tmp_path / "bag", rec)
    with (
        BagReader(tmp_path / "bag") as reader,
        BagWriter(tmp_path / "copy", compress="zstd") as writer,
    ):
        for topic in reader.topics:
            writer.copy_topic(reader, topic)
        copied = [writer.copy_batch(b) > 0 for b in reader.batches()]
    assert copied and all(copied)
    with Reader(tmp_path / "bag") as a, Reader(tmp_path / "copy") as b:
        assert [(c.topic, t, bytes(d)) for c, t, d in a.messages()] == [
            (c.topic, t, bytes(d)) for c, t, d in b.messages()
        ]
        assert {c.topic: c.msgtype for c in a.connections} == {
            c.topic: c.msgtype for c in b.connections
        }


def test_single_messages_and_batches_mix_in_log_time_order(tmp_path):
    stamps = np.arange(200, dtype=np.int64) * 1_000_000
    with BagWriter(tmp_path / "bag", chunk_bytes=10_000) as bag:
        bag.add_topic(BAG_TOPICS["raw"], codec.IMU_TYPE)
        bag.add_topic(BAG_TOPICS["joint_states"], codec.JOINT_STATE_TYPE)
        for k in range(0, 200, 20):
            bag.write_batch(
                BAG_TOPICS["raw"],
                stamps[k : k + 20],
                encode_imu_batch(stamps[k : k + 20], np.ones((20, 3)) * k),
            )
            bag.write(
                BAG_TOPICS["joint_states"],
                int(stamps[k]) + 1,
                encode_joint_state_batch(
                    [int(stamps[k]) + 1], [[0.0, 0.0]], [[float(k), 0.0]], JOINT_NAMES
                )[0],
            )
    with Reader(tmp_path / "bag") as reader:
        times = [t for _, t, _ in reader.messages()]
        assert times == sorted(times) and len(times) == 210
    back = read_recording(tmp_path / "bag")
    np.testing.assert_array_equal(back.sensor[:, 0], np.repeat(np.arange(0, 200, 20), 20))
    np.testing.assert_array_equal(back.joint_velocity[:, 0], np.arange(0, 200, 20))


def test_zstd_chunks_shrink_the_imu_stream(tmp_path):
    rec = random_recording(seconds=2.0, with_truth=False)
    rec.sensor = np.round(rec.sensor * 20) / 20  # 10-bit-like sensor values, as recorded
    write_recording(tmp_path / "plain", rec)
    write_recording(tmp_path / "zstd", rec, compress="zstd")
    size = {
        name: next((tmp_path / name).glob("*.mcap")).stat().st_size for name in ("plain", "zstd")
    }
    assert size["plain"] / size["zstd"] > 4
    np.testing.assert_array_equal(read_recording(tmp_path / "zstd").sensor, rec.sensor)


def test_metadata_spans_every_message(tmp_path):
    rec = random_recording(seconds=2.0)
    write_recording(tmp_path / "bag", rec)
    with Reader(tmp_path / "bag") as reader:
        times = [t for _, t, _ in reader.messages()]
        assert (
            reader.start_time == min(times) and reader.end_time == max(times) + 1
        )  # rosbags: end + 1
        assert reader.message_count == len(times)
