"""egovib_ros.bag.denoise: the core's denoiser run on a bag, streamed; the output holds every
input message and, per raw sample, the raw message with the cleaned field.
"""

import numpy as np
import pytest
from simbags import topic_messages

from egovib_ros.bag import BagWriter, bag_topics, read_recording, write_recording
from egovib_ros.bag.codec import encode_imu_batch, encode_joint_state_batch, imu_field_offset
from egovib_ros.bag.denoise import denoise_bag
from egovib_ros.core import NoiseModel
from egovib_ros.core.methods import denoise_batch_method
from egovib_ros.errors import BagError


def test_streaming_through_small_chunks_equals_batch(sim_bags, sim_bags_model, tmp_path):
    """Input in 20 kB MCAP chunks (~40 samples): slices, chunk boundaries and the joint-state
    horizon all fall in different places; the result is the whole-array one."""
    motion = read_recording(sim_bags / "motion")
    write_recording(tmp_path / "small", motion, chunk_bytes=20_000, window_s=0.01)
    out = tmp_path / "out"
    model = NoiseModel.load(sim_bags_model)
    figures = denoise_bag(tmp_path / "small", out, model=model)
    assert figures["chunks_copied_verbatim"] > 100
    _, expected, _ = denoise_batch_method(  # the model's default method (hybrid)
        motion.sensor_stamps_ns, motion.sensor, motion.joint_stamps_ns, motion.joint_velocity, model
    )
    assert figures["method"] == "hybrid"
    np.testing.assert_array_equal(read_recording(out).denoised, expected)


def test_a_bag_already_denoised_is_refused_or_gets_its_denoised_topic_replaced(
    sim_bags, sim_bags_model, tmp_path
):
    """A bag holding the denoised topic (a recorded live run) is refused, nothing written;
    with replace_denoised its topic is cut out and the new one written (it was replaced
    without a word)."""
    once, twice = tmp_path / "once", tmp_path / "twice"
    model = NoiseModel.load(sim_bags_model)
    denoise_bag(sim_bags / "motion", once, model=model)
    with pytest.raises(BagError, match="already holds /accelerometer/denoised"):
        denoise_bag(once, twice, model=model, channels="combined")
    assert not twice.exists() and not list(tmp_path.glob(".*.partial"))
    figures = denoise_bag(once, twice, model=model, channels="combined", replace_denoised=True)
    assert figures["replaced_denoised"] == bag_topics(once)["/accelerometer/denoised"][1]
    assert figures["chunks_copied_verbatim"] > 0  # the old topic was cut out of the chunks
    topics = bag_topics(twice)
    assert topics["/accelerometer/denoised"][1] == topics["/accelerometer/raw"][1]
    rec = read_recording(twice)
    assert np.all(rec.denoised[:, 1:] == 0)  # the new (combined) output, not the old


def test_unusual_imu_messages_take_the_general_path(sim_bags, sim_bags_model, tmp_path):
    """Raw messages whose frame_id changes length mid-stream (no fixed layout): the output is
    still each input message with only the field replaced, as the vectorised path makes it."""
    motion = read_recording(sim_bags / "motion")
    n = len(motion.sensor_stamps_ns)
    half = n // 2
    with BagWriter(tmp_path / "mixed") as bag:
        bag.add_topic("/accelerometer/raw", "sensor_msgs/msg/Imu")
        bag.add_topic("/joint_states", "sensor_msgs/msg/JointState")
        stamps = motion.sensor_stamps_ns
        raws = encode_imu_batch(stamps[:half], motion.sensor[:half], "imu") + encode_imu_batch(
            stamps[half:], motion.sensor[half:], "imu_link_long_name"
        )
        bag.write_batch("/accelerometer/raw", stamps, raws)
        bag.write_batch(
            "/joint_states",
            motion.joint_stamps_ns,
            encode_joint_state_batch(
                motion.joint_stamps_ns,
                motion.joint_position,
                motion.joint_velocity,
                motion.joint_names,
            ),
        )
    denoise_bag(tmp_path / "mixed", tmp_path / "out", model=NoiseModel.load(sim_bags_model))
    _, expected, _ = denoise_batch_method(
        motion.sensor_stamps_ns,
        motion.sensor,
        motion.joint_stamps_ns,
        motion.joint_velocity,
        NoiseModel.load(sim_bags_model),
    )
    np.testing.assert_array_equal(read_recording(tmp_path / "out").denoised, expected)
    raw, den = (
        topic_messages(tmp_path / "out", "/accelerometer/raw"),
        topic_messages(tmp_path / "out", "/accelerometer/denoised"),
    )
    assert [t for t, _ in raw] == [t for t, _ in den]
    for (_, a), (_, b), frame in (
        (raw[0], den[0], "imu"),
        (raw[-1], den[-1], "imu_link_long_name"),
    ):
        at = imu_field_offset(len(frame), "linear_acceleration")
        assert (
            a[:at] == b[:at] and a[at + 24 :] == b[at + 24 :] and a[at : at + 24] != b[at : at + 24]
        )


def test_a_topic_on_two_connections_stays_readable_by_rosbags(sim_bags, sim_bags_model, tmp_path):
    """The sensor topic recorded on two connections with different QoS (two publishers, a
    reliable and a best-effort one): the output declares the topic alike in metadata.yaml
    and in the MCAP file, so rosbags reads every message of it and of its denoised copy."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )
    from rosbags.rosbag2 import Reader, StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    best_effort = Qos(
        QosHistory.KEEP_LAST, 10, QosReliability.BEST_EFFORT, QosDurability.VOLATILE,
        QosTime(0, 0), QosTime(0, 0), QosLiveliness.AUTOMATIC, QosTime(0, 0), False,
    )  # fmt: skip
    with Reader(sim_bags / "motion") as reader:
        messages = [(c.topic, c.msgtype, t, bytes(d)) for c, t, d in reader.messages()]
        topics = {c.topic: c.msgtype for c in reader.connections}
    bag = tmp_path / "two_connections"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {t: writer.add_connection(t, m, typestore=store) for t, m in topics.items()}
        second = writer.add_connection(
            "/accelerometer/raw", topics["/accelerometer/raw"], typestore=store,
            offered_qos_profiles=[best_effort],
        )  # fmt: skip
        k = 0
        for topic, _, log_time, data in sorted(messages, key=lambda m: m[2]):
            conn = conns[topic]
            if topic == "/accelerometer/raw":
                k += 1
                conn = second if (k // 500) % 2 else conn
            writer.write(conn, log_time, data)
    out = tmp_path / "out"
    denoise_bag(bag, out, model=NoiseModel.load(sim_bags_model))
    n_raw = sum(1 for m in messages if m[0] == "/accelerometer/raw")
    for topic in ("/accelerometer/raw", "/accelerometer/denoised"):
        with Reader(out) as reader:
            conns = [c for c in reader.connections if c.topic == topic]
            assert sum(1 for _ in reader.messages(connections=conns)) == n_raw, topic
