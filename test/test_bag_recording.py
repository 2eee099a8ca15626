"""Tests of egovib_ros.bag: CDR codecs against rosbags, bag round trips, bad bags."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag2 import Reader

from egovib_ros.bag import (
    BagReader,
    BagWriter,
    Recording,
    codec,
    concat_recordings,
    decode_imu,
    decode_joint_states,
    encode_imu_batch,
    encode_joint_state_batch,
    iter_recording,
    read_recording,
    write_recording,
)
from egovib_ros.bag.codec import joint_state_layout
from egovib_ros.bag.many import expand_bags
from egovib_ros.errors import BagError, ConfigError
from egovib_ros.robot import RobotProfile
from egovib_ros.sim.pr2 import BAG_TOPICS, JOINT_NAMES


def _random_recording(seed: int = 0, seconds: float = 0.5, with_truth: bool = True) -> Recording:
    rng = np.random.default_rng(seed)
    n, m = int(3000 * seconds), int(1000 * seconds)
    t0 = 1_700_000_000 * 10**9 + 123
    accel_stamps = t0 + np.round(np.arange(n) * 1e9 / 3000).astype(np.int64)
    joint_stamps = t0 + 170_000 + np.arange(m, dtype=np.int64) * 1_000_000
    contact = rng.normal(size=(n, 3))
    ego = rng.normal(size=(n, 3))
    rec = Recording(
        sensor_stamps_ns=accel_stamps,
        sensor=contact + ego,
        joint_stamps_ns=joint_stamps,
        joint_position=rng.normal(size=(m, 2)),
        joint_velocity=rng.normal(size=(m, 2)),
        joint_names=JOINT_NAMES,
        command_stamps_ns=joint_stamps[::100],
        commands=rng.normal(size=(len(joint_stamps[::100]), 2)),
    )
    if with_truth:
        rec.contact, rec.ego = contact, ego
    return rec


def test_imu_codec_matches_rosbags_serialisation():
    ts = codec.typestore()
    stamps = np.array([0, 1, 1_500_000_123, 1_700_000_000_999_999_999], np.int64)
    accel = np.array([[0.0, -0.0, 1.5], [1e-9, 78.5, -78.5], [3.25, 2.0, 1.0], [-1.0, 0.5, 9.81]])
    fast = encode_imu_batch(stamps, accel)
    for stamp, xyz, raw in zip(stamps, accel, fast):
        reference = bytes(ts.serialize_cdr(codec.imu_message(int(stamp), xyz), codec.IMU_TYPE))
        assert raw == reference
        assert raw[:4] == b"\x00\x01\x00\x00"
        msg = ts.deserialize_cdr(raw, codec.IMU_TYPE)
        assert msg.header.frame_id == ""  # no robot's frame by default: writers name theirs
        assert msg.orientation_covariance[0] == -1 and msg.angular_velocity_covariance[0] == -1
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp
    got_stamps, got_accel = decode_imu(fast)
    np.testing.assert_array_equal(got_stamps, stamps)
    np.testing.assert_array_equal(got_accel, accel)
    stamp, xyz = decode_imu([fast[2]])
    assert stamp[0] == stamps[2] and np.array_equal(xyz[0], accel[2])


@pytest.mark.parametrize("frame_id", ["", "a", "abcd", "imu_link_x"])
def test_imu_codec_other_frame_lengths(frame_id):
    ts = codec.typestore()
    stamps = np.array([5, 10**9 + 7], np.int64)
    accel = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    fast = encode_imu_batch(stamps, accel, frame_id=frame_id)
    assert fast[1] == bytes(
        ts.serialize_cdr(codec.imu_message(int(stamps[1]), accel[1], frame_id), codec.IMU_TYPE)
    )
    np.testing.assert_array_equal(decode_imu(fast)[1], accel)


def test_imu_decode_falls_back_on_mixed_frames():
    a = encode_imu_batch(np.array([1], np.int64), np.array([[1.0, 2.0, 3.0]]), frame_id="short")
    b = encode_imu_batch(np.array([2], np.int64), np.array([[4.0, 5.0, 6.0]]))
    stamps, accel = decode_imu(a + b)
    np.testing.assert_array_equal(stamps, [1, 2])
    np.testing.assert_array_equal(accel, [[1, 2, 3], [4, 5, 6]])


def test_joint_state_codec_matches_rosbags():
    ts = codec.typestore()
    rng = np.random.default_rng(1)
    stamps = np.array([3, 2_000_000_001], np.int64)
    pos, vel = rng.normal(size=(2, 2)), rng.normal(size=(2, 2))
    fast = encode_joint_state_batch(stamps, pos, vel, JOINT_NAMES)
    for i, raw in enumerate(fast):
        ref = bytes(
            ts.serialize_cdr(
                codec.joint_state_message(int(stamps[i]), JOINT_NAMES, pos[i], vel[i]),
                codec.JOINT_STATE_TYPE,
            )
        )
        assert raw == ref
    s, p, v = decode_joint_states(fast)
    names = joint_state_layout(fast[0])[0]
    assert names == JOINT_NAMES
    np.testing.assert_array_equal(s, stamps)
    np.testing.assert_array_equal(p, pos)
    np.testing.assert_array_equal(v, vel)


def test_joint_state_decode_reorders_by_name():
    ts = codec.typestore()
    raw = bytes(
        ts.serialize_cdr(
            codec.joint_state_message(7, JOINT_NAMES[::-1], [1.0, 2.0], [3.0, 4.0]),
            codec.JOINT_STATE_TYPE,
        )
    )
    s, p, v = decode_joint_states([raw], JOINT_NAMES)
    np.testing.assert_array_equal(p, [[2.0, 1.0]])
    np.testing.assert_array_equal(v, [[4.0, 3.0]])


def test_joint_state_decode_picks_joints_from_a_full_robot():
    ts = codec.typestore()
    names = ("torso_lift_joint", JOINT_NAMES[1], "head_pan_joint", JOINT_NAMES[0])
    raws = [
        bytes(
            ts.serialize_cdr(
                codec.joint_state_message(
                    k, names, [0.1, 0.02 + k, 0.3, 1.0 + k], [1.0, 0.01 * k, 3.0, 2.0 * k]
                ),
                codec.JOINT_STATE_TYPE,
            )
        )
        for k in range(3)
    ]
    s, p, v = decode_joint_states(raws, JOINT_NAMES)
    np.testing.assert_array_equal(p, [[1.0 + k, 0.02 + k] for k in range(3)])
    np.testing.assert_array_equal(v, [[2.0 * k, 0.01 * k] for k in range(3)])


@pytest.mark.parametrize("storage,compress", [("mcap", False), ("mcap", True), ("sqlite3", False)])
def test_recording_round_trip(tmp_path, storage, compress):
    rec = _random_recording()
    out = tmp_path / "bag"
    write_recording(out, rec, storage=storage, compress=compress)
    assert (out / "metadata.yaml").exists()
    back = read_recording(out)
    for name in (
        "sensor_stamps_ns",
        "sensor",
        "joint_stamps_ns",
        "joint_position",
        "joint_velocity",
        "contact",
        "ego",
        "command_stamps_ns",
        "commands",
    ):
        np.testing.assert_array_equal(getattr(back, name), getattr(rec, name), err_msg=name)
    assert back.joint_names == JOINT_NAMES
    assert back.denoised is None
    # rosbags' own reader sees the contract's topics, log time = header stamp.
    with Reader(out) as reader:
        topics = {c.topic for c in reader.connections}
        assert topics == {
            BAG_TOPICS[k] for k in ("raw", "contact", "ego", "joint_states", "commands")
        }
        conn = [c for c in reader.connections if c.topic == BAG_TOPICS["raw"]]
        log_time, raw = next((t, r) for _, t, r in reader.messages(connections=conn))
        assert log_time == decode_imu([raw])[0][0] == rec.sensor_stamps_ns[0]
        times = [t for _, t, _ in reader.messages()]
        assert times == sorted(times)


def test_denoised_topic_round_trip(tmp_path):
    rec = _random_recording(with_truth=False)
    rec.denoised_stamps_ns = rec.sensor_stamps_ns[:100]
    rec.denoised = rec.sensor[:100] * 0.5
    write_recording(tmp_path / "bag", rec)
    back = read_recording(tmp_path / "bag")
    assert back.contact is None and back.ego is None
    np.testing.assert_array_equal(back.denoised, rec.denoised)
    np.testing.assert_array_equal(back.denoised_stamps_ns, rec.denoised_stamps_ns)


def test_bag_writer_raw_bytes(tmp_path):
    stamps = np.arange(10, dtype=np.int64) * 333_333
    accel = np.arange(30, dtype=float).reshape(10, 3)
    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic(BAG_TOPICS["raw"], codec.IMU_TYPE)
        bag.add_topic(BAG_TOPICS["joint_states"], codec.JOINT_STATE_TYPE)
        bag.write_many(BAG_TOPICS["raw"], stamps, encode_imu_batch(stamps, accel))
        bag.write(
            BAG_TOPICS["joint_states"],
            0,
            encode_joint_state_batch([0], [[0.0, 0.01]], [[1.0, 0.02]], JOINT_NAMES)[0],
        )
    back = read_recording(tmp_path / "bag")
    np.testing.assert_array_equal(back.sensor, accel)
    np.testing.assert_array_equal(back.joint_velocity, [[1.0, 0.02]])


def test_missing_topic_is_bag_error(tmp_path):
    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic(BAG_TOPICS["raw"], codec.IMU_TYPE)
        bag.write(BAG_TOPICS["raw"], 1, encode_imu_batch([1], [[0.0, 0.0, 1.0]])[0])
    with pytest.raises(BagError, match=r"bag.*/joint_states"):
        read_recording(tmp_path / "bag")


def test_bad_bags_are_bag_errors(tmp_path):
    with pytest.raises(BagError, match="no such bag"):
        read_recording(tmp_path / "nothing")
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "metadata.yaml").write_text("not: a rosbag2 metadata\n")
    with pytest.raises(BagError, match="broken"):
        read_recording(broken)
    # A truncated .mcap file.
    rec = _random_recording(seconds=0.1)
    write_recording(tmp_path / "trunc", rec)
    mcap = next((tmp_path / "trunc").glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:5000])
    with pytest.raises(BagError, match="trunc"):
        read_recording(tmp_path / "trunc")


def test_existing_output_is_refused(tmp_path):
    (tmp_path / "bag").mkdir()
    with pytest.raises(BagError, match="already exists"):
        write_recording(tmp_path / "bag", _random_recording(seconds=0.01))


FIELDS = (
    "sensor_stamps_ns",
    "sensor",
    "joint_stamps_ns",
    "joint_position",
    "joint_velocity",
    "contact",
    "ego",
    "denoised_stamps_ns",
    "denoised",
    "command_stamps_ns",
    "commands",
)


@pytest.mark.parametrize("compress", [False, True])
def test_chunk_scan_equals_rosbags_reader(tmp_path, monkeypatch, compress):
    rec = _random_recording(seconds=2.0)
    rec.denoised_stamps_ns, rec.denoised = rec.sensor_stamps_ns, rec.sensor * 0.25
    write_recording(tmp_path / "bag", rec, compress=compress)
    with BagReader(tmp_path / "bag") as reader:
        assert reader.is_plain_mcap
    fast = read_recording(tmp_path / "bag")
    monkeypatch.setattr(
        BagReader, "is_plain_mcap", property(lambda self: False)
    )  # force rosbags' reader
    slow = read_recording(tmp_path / "bag")
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)
        np.testing.assert_array_equal(getattr(fast, name), getattr(rec, name), err_msg=name)


def test_missing_joint_is_bag_error(tmp_path):
    ts = codec.typestore()
    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic(BAG_TOPICS["raw"], codec.IMU_TYPE)
        bag.add_topic(BAG_TOPICS["joint_states"], codec.JOINT_STATE_TYPE)
        bag.write(BAG_TOPICS["raw"], 1, encode_imu_batch([1], [[0.0, 0.0, 1.0]])[0])
        raw = ts.serialize_cdr(
            codec.joint_state_message(1, [JOINT_NAMES[0]], [0.0], [0.0]), codec.JOINT_STATE_TYPE
        )
        bag.write(BAG_TOPICS["joint_states"], 1, bytes(raw))
    with pytest.raises(BagError, match=JOINT_NAMES[1]):
        read_recording(tmp_path / "bag")


def test_empty_joint_state_batch_encodes_to_nothing():
    from egovib_ros.bag import encode_joint_state_batch

    assert (
        encode_joint_state_batch(
            np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)), JOINT_NAMES
        )
        == []
    )


# --------------------------------------------------------------------------
# Robot profiles: other topics, the gyro field, JointStates of a whole robot
# --------------------------------------------------------------------------
GYRO_ROBOT = RobotProfile(
    name="test_arm",
    sensor_topic="/imu/data_raw",
    sensor_field="angular_velocity",
    rate_hz=1600.0,
    denoised_topic="/imu/data_denoised",
    joints_topic="/arm/joint_states",
    joint_names=("elbow", "wrist", "spindle"),
    max_speed=(2.0, 3.0, 50.0),
    bidirectional=(True, True, False),
    band_hz=(100.0, 600.0),
)
FULL_ROBOT = (
    "base",
    "shoulder",
    "spindle",
    "elbow",
    "head_pan",
    "head_tilt",
    "wrist",
    "torso",
    "finger_1",
    "finger_2",
    "finger_3",
    "caster",
)


def _write_robot_bag(
    path, *, seconds=1.0, names=FULL_ROBOT, shuffle=True, seed=0, writer_options=None
):
    """A bag of GYRO_ROBOT: gyro Imu (angular_velocity) and a 12-joint JointState whose joint
    order changes between messages. Returns the arrays written, joints in profile order."""
    rng = np.random.default_rng(seed)
    ts = codec.typestore()
    n, m = int(1600 * seconds), int(500 * seconds)
    stamps = 5_000_000_000 + np.round(np.arange(n) * 1e9 / 1600).astype(np.int64)
    gyro = rng.normal(size=(n, 3))
    js_stamps = 5_000_000_000 + np.arange(m, dtype=np.int64) * 2_000_000
    pos, vel = rng.normal(size=(m, len(names))), rng.normal(size=(m, len(names)))
    with BagWriter(path, **(writer_options or {})) as bag:
        bag.add_topic("/imu/data_raw", codec.IMU_TYPE)
        bag.add_topic("/arm/joint_states", codec.JOINT_STATE_TYPE)
        bag.write_batch(
            "/imu/data_raw",
            stamps,
            encode_imu_batch(stamps, gyro, "imu_link", "angular_velocity"),
        )
        for k in range(m):
            order = rng.permutation(len(names)) if shuffle else np.arange(len(names))
            msg = codec.joint_state_message(
                int(js_stamps[k]), [names[i] for i in order], pos[k, order], vel[k, order]
            )
            bag.write(
                "/arm/joint_states",
                int(js_stamps[k]),
                bytes(ts.serialize_cdr(msg, codec.JOINT_STATE_TYPE)),
            )
    columns = [names.index(j) for j in GYRO_ROBOT.joint_names if j in names]
    return stamps, gyro, js_stamps, pos[:, columns], vel[:, columns]


def test_profile_picks_topics_field_and_joints_by_name(tmp_path):
    stamps, gyro, js_stamps, pos, vel = _write_robot_bag(tmp_path / "bag")
    rec = read_recording(tmp_path / "bag", profile=GYRO_ROBOT)
    np.testing.assert_array_equal(rec.sensor_stamps_ns, stamps)
    np.testing.assert_array_equal(rec.sensor, gyro)  # the profile's field, whatever its name
    assert rec.joint_names == GYRO_ROBOT.joint_names
    np.testing.assert_array_equal(rec.joint_stamps_ns, js_stamps)
    np.testing.assert_array_equal(rec.joint_position, pos)
    np.testing.assert_array_equal(rec.joint_velocity, vel)
    assert rec.contact is None and rec.denoised is None


def test_joint_states_in_one_order_take_the_vectorised_path(tmp_path):
    _, _, _, pos, vel = _write_robot_bag(tmp_path / "bag", shuffle=False)
    rec = read_recording(tmp_path / "bag", profile=GYRO_ROBOT)
    np.testing.assert_array_equal(rec.joint_position, pos)
    np.testing.assert_array_equal(rec.joint_velocity, vel)


def test_named_joint_never_seen_is_bag_error_naming_joint_and_topic(tmp_path):
    names = tuple(n for n in FULL_ROBOT if n != "spindle")
    _write_robot_bag(tmp_path / "bag", names=names)
    with pytest.raises(
        BagError, match=r"bag: topic /arm/joint_states lacks joint\(s\) spindle"
    ) as info:
        read_recording(tmp_path / "bag", profile=GYRO_ROBOT)
    assert "\n" not in str(info.value)


def test_partial_joint_states_are_merged_per_joint(tmp_path):
    """Two controllers publish their own JointState on one topic: each joint keeps its
    last published value (as joint_state_publisher merges them)."""
    ts = codec.typestore()
    stamps = np.arange(3000, dtype=np.int64) * 625_000
    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic("/imu/data_raw", codec.IMU_TYPE)
        bag.add_topic("/arm/joint_states", codec.JOINT_STATE_TYPE)
        bag.write_batch("/imu/data_raw", stamps, encode_imu_batch(stamps, np.zeros((3000, 3))))
        for k in range(10):
            arm = codec.joint_state_message(
                k * 2_000_000, ["elbow", "wrist"], [k, 10 + k], [0.1 * k, 1 + k]
            )
            tool = codec.joint_state_message(
                k * 2_000_000 + 1_000_000, ["spindle"], [7.0], [20.0 + k]
            )
            for stamp, msg in ((k * 2_000_000, arm), (k * 2_000_000 + 1_000_000, tool)):
                bag.write(
                    "/arm/joint_states", stamp, bytes(ts.serialize_cdr(msg, codec.JOINT_STATE_TYPE))
                )
    rec = read_recording(tmp_path / "bag", profile=GYRO_ROBOT)
    assert len(rec.joint_stamps_ns) == 20
    assert np.isnan(rec.joint_velocity[0, 2])  # spindle not heard of yet
    np.testing.assert_array_equal(rec.joint_velocity[1], [0.0, 1.0, 20.0])
    np.testing.assert_array_equal(rec.joint_velocity[2], [0.1, 2.0, 20.0])
    np.testing.assert_array_equal(rec.joint_velocity[-1], [0.9, 10.0, 29.0])


def test_slices_are_bounded_and_join_to_the_whole(tmp_path):
    rec = _random_recording(seconds=12.0, with_truth=True)
    write_recording(tmp_path / "bag", rec, compress=True)
    slices = list(iter_recording(tmp_path / "bag", min_slice_s=1.0))
    assert len(slices) >= 6
    # when a slice's sensor samples come, every joint state up to the horizon past them has come
    joints_so_far = 0
    for piece in slices[:-1]:
        joints_so_far += len(piece.joint_stamps_ns)
        needed = np.searchsorted(
            rec.joint_stamps_ns, piece.sensor_stamps_ns.max() + int(0.1e9), side="right"
        )
        assert joints_so_far >= needed
        assert piece.duration_s < 4.0
    whole = concat_recordings(slices)
    for name in FIELDS:
        if getattr(rec, name) is not None:
            np.testing.assert_array_equal(getattr(whole, name), getattr(rec, name), err_msg=name)


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
    rec = _random_recording(seconds=1.0)
    write_recording(tmp_path / "bag", rec)
    _rewrite_with_mcap_library(tmp_path / "bag", **options)
    fast = read_recording(tmp_path / "bag")
    monkeypatch.setattr(BagReader, "is_plain_mcap", property(lambda self: False))
    slow = read_recording(tmp_path / "bag")
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)
        np.testing.assert_array_equal(getattr(fast, name), getattr(rec, name), err_msg=name)


def test_written_mcap_is_valid_for_the_mcap_library_and_rosbags(tmp_path):
    """CRCs, summary, statistics and log-time order as the `mcap` library and rosbags check them."""
    from mcap.reader import make_reader

    rec = _random_recording(seconds=3.0)
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
    rec = _random_recording(seconds=2.0)
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


def test_chunk_without_channels(tmp_path):
    rec = _random_recording(seconds=0.5)
    write_recording(tmp_path / "bag", rec)
    with BagReader(tmp_path / "bag") as reader:
        batch = next(iter(reader.batches()))
        drop = {c for c, t in batch.topic_of_channel.items() if t == BAG_TOPICS["contact"]}
        chunk = batch.chunks[0]
        kept = chunk.without(drop)
    assert set(kept.index) == set(chunk.index) - drop
    for channel, (times, offsets) in kept.index.items():
        np.testing.assert_array_equal(times, chunk.index[channel][0])
        old_times, old_starts, lengths = chunk.data_span(channel)
        _, new_starts, new_lengths = kept.data_span(channel)
        np.testing.assert_array_equal(lengths, new_lengths)
        for a, b, n in zip(old_starts[:5], new_starts[:5], lengths[:5]):
            assert chunk.records[a : a + n] == kept.records[b : b + n]


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
    rec = _random_recording(seconds=2.0, with_truth=False)
    rec.sensor = np.round(rec.sensor * 20) / 20  # 10-bit-like sensor values, as recorded
    write_recording(tmp_path / "plain", rec)
    write_recording(tmp_path / "zstd", rec, compress="zstd")
    size = {
        name: next((tmp_path / name).glob("*.mcap")).stat().st_size for name in ("plain", "zstd")
    }
    assert size["plain"] / size["zstd"] > 4
    np.testing.assert_array_equal(read_recording(tmp_path / "zstd").sensor, rec.sensor)


# --------------------------------------------------------------------------
# Several bags
# --------------------------------------------------------------------------
def test_expand_bags(tmp_path):
    for name in ("a/one", "a/two", "b/one", "solo"):
        write_recording(tmp_path / name, _random_recording(seconds=0.01))
    (tmp_path / "a" / ".hidden").mkdir()
    (tmp_path / "empty").mkdir()
    found = expand_bags([tmp_path / "a", tmp_path / "solo"])
    assert [(str(b.relative_to(tmp_path)), str(n)) for b, n in found] == [
        ("a/one", "one"),
        ("a/two", "two"),
        ("solo", "solo"),
    ]
    assert [str(n) for _, n in expand_bags([tmp_path])] == ["a/one", "a/two", "b/one", "solo"]
    with pytest.raises(ConfigError, match="one"):
        expand_bags([tmp_path / "a", tmp_path / "b"])
    with pytest.raises(BagError, match="empty: no rosbag2 bags"):
        expand_bags([tmp_path / "empty"])
    assert [b for b, _ in expand_bags([tmp_path / "missing"])] == [
        tmp_path / "missing"
    ]  # its task reports it


def test_topics_written_apart_are_read_together(tmp_path):
    """A bag whose sensor chunks all come before its joint-state chunks (a writer that
    flushes per topic): chunks are read in log-time order (seeking along the chunk index),
    so no slice waits long for its joint states and the slices equal the whole."""
    from egovib_ros.bag.mcapfile import McapScanner

    rec = _random_recording(seconds=6.0, with_truth=False)
    with BagWriter(tmp_path / "bag", chunk_bytes=200_000) as bag:
        bag.add_topic(BAG_TOPICS["raw"], codec.IMU_TYPE)
        bag.add_topic(BAG_TOPICS["joint_states"], codec.JOINT_STATE_TYPE)
        bag.write_batch(
            BAG_TOPICS["raw"],
            rec.sensor_stamps_ns,
            encode_imu_batch(rec.sensor_stamps_ns, rec.sensor),
        )
        bag.write_batch(
            BAG_TOPICS["joint_states"],
            rec.joint_stamps_ns,
            encode_joint_state_batch(
                rec.joint_stamps_ns, rec.joint_position, rec.joint_velocity, JOINT_NAMES
            ),
        )
    starts = [c.start_ns for c in McapScanner(next((tmp_path / "bag").glob("*.mcap"))).chunks()]
    assert starts == sorted(starts) and len(starts) > 10
    slices = list(iter_recording(tmp_path / "bag", min_slice_s=0.5))
    assert len(slices) >= 5
    whole = concat_recordings(slices)
    for name in ("sensor_stamps_ns", "sensor", "joint_stamps_ns", "joint_velocity"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(rec, name), err_msg=name)


@pytest.mark.parametrize("crc", [True, False])
def test_damaged_records_are_detected(tmp_path, crc):
    """A flipped byte inside a chunk: refused by the chunk CRC; without CRCs, a message record
    whose opcode was damaged is missing from the count the bag's index gives."""
    rec = _random_recording(seconds=2.0)
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


def test_metadata_spans_every_message(tmp_path):
    rec = _random_recording(seconds=2.0)
    write_recording(tmp_path / "bag", rec)
    with Reader(tmp_path / "bag") as reader:
        times = [t for _, t, _ in reader.messages()]
        assert (
            reader.start_time == min(times) and reader.end_time == max(times) + 1
        )  # rosbags: end + 1
        assert reader.message_count == len(times)
