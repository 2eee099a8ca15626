"""Tests of egovib_ros.bagio: CDR codecs against rosbags, bag round trips, bad bags."""
from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag2 import Reader

from egovib_ros import bagio
from egovib_ros.bagio import (BagWriter, Recording, decode_imu, decode_imu_batch, decode_joint_state_batch,
                              encode_imu_batch, encode_joint_state_batch, read_recording, write_recording)
from egovib_ros.constants import ACCEL_FRAME, BAG_TOPICS, JOINT_NAMES
from egovib_ros.errors import BagError


def _random_recording(seed: int = 0, seconds: float = 0.5, with_truth: bool = True) -> Recording:
    rng = np.random.default_rng(seed)
    n, m = int(3000 * seconds), int(1000 * seconds)
    t0 = 1_700_000_000 * 10**9 + 123
    accel_stamps = t0 + np.round(np.arange(n) * 1e9 / 3000).astype(np.int64)
    joint_stamps = t0 + 170_000 + np.arange(m, dtype=np.int64) * 1_000_000
    contact = rng.normal(size=(n, 3))
    ego = rng.normal(size=(n, 3))
    rec = Recording(accel_stamps_ns=accel_stamps, accel=contact + ego,
                    joint_stamps_ns=joint_stamps, joint_position=rng.normal(size=(m, 2)),
                    joint_velocity=rng.normal(size=(m, 2)), joint_names=JOINT_NAMES,
                    command_stamps_ns=joint_stamps[::100], commands=rng.normal(size=(len(joint_stamps[::100]), 2)))
    if with_truth:
        rec.contact, rec.ego = contact, ego
    return rec


def test_imu_codec_matches_rosbags_serialisation():
    ts = bagio.typestore()
    stamps = np.array([0, 1, 1_500_000_123, 1_700_000_000_999_999_999], np.int64)
    accel = np.array([[0.0, -0.0, 1.5], [1e-9, 78.5, -78.5], [3.25, 2.0, 1.0], [-1.0, 0.5, 9.81]])
    fast = encode_imu_batch(stamps, accel)
    for stamp, xyz, raw in zip(stamps, accel, fast):
        reference = bytes(ts.serialize_cdr(bagio.imu_message(int(stamp), xyz), bagio.IMU_TYPE))
        assert raw == reference
        assert raw[:4] == b"\x00\x01\x00\x00"
        msg = ts.deserialize_cdr(raw, bagio.IMU_TYPE)
        assert msg.header.frame_id == ACCEL_FRAME
        assert msg.orientation_covariance[0] == -1 and msg.angular_velocity_covariance[0] == -1
        assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == stamp
    got_stamps, got_accel = decode_imu_batch(fast)
    np.testing.assert_array_equal(got_stamps, stamps)
    np.testing.assert_array_equal(got_accel, accel)
    stamp, xyz = decode_imu(fast[2])
    assert stamp == stamps[2] and np.array_equal(xyz, accel[2])


@pytest.mark.parametrize("frame_id", ["", "a", "abcd", "imu_link_x"])
def test_imu_codec_other_frame_lengths(frame_id):
    ts = bagio.typestore()
    stamps = np.array([5, 10**9 + 7], np.int64)
    accel = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    fast = encode_imu_batch(stamps, accel, frame_id=frame_id)
    assert fast[1] == bytes(ts.serialize_cdr(bagio.imu_message(int(stamps[1]), accel[1], frame_id), bagio.IMU_TYPE))
    np.testing.assert_array_equal(decode_imu_batch(fast)[1], accel)


def test_imu_decode_falls_back_on_mixed_frames():
    a = encode_imu_batch(np.array([1], np.int64), np.array([[1.0, 2.0, 3.0]]), frame_id="short")
    b = encode_imu_batch(np.array([2], np.int64), np.array([[4.0, 5.0, 6.0]]))
    stamps, accel = decode_imu_batch(a + b)
    np.testing.assert_array_equal(stamps, [1, 2])
    np.testing.assert_array_equal(accel, [[1, 2, 3], [4, 5, 6]])


def test_joint_state_codec_matches_rosbags():
    ts = bagio.typestore()
    rng = np.random.default_rng(1)
    stamps = np.array([3, 2_000_000_001], np.int64)
    pos, vel = rng.normal(size=(2, 2)), rng.normal(size=(2, 2))
    fast = encode_joint_state_batch(stamps, pos, vel)
    for i, raw in enumerate(fast):
        ref = bytes(ts.serialize_cdr(bagio.joint_state_message(int(stamps[i]), JOINT_NAMES, pos[i], vel[i]),
                                     bagio.JOINT_STATE_TYPE))
        assert raw == ref
    s, p, v, names = decode_joint_state_batch(fast)
    assert names == JOINT_NAMES
    np.testing.assert_array_equal(s, stamps)
    np.testing.assert_array_equal(p, pos)
    np.testing.assert_array_equal(v, vel)


def test_joint_state_decode_reorders_by_name():
    ts = bagio.typestore()
    raw = bytes(ts.serialize_cdr(bagio.joint_state_message(7, JOINT_NAMES[::-1], [1.0, 2.0], [3.0, 4.0]),
                                 bagio.JOINT_STATE_TYPE))
    s, p, v, _ = decode_joint_state_batch([raw], JOINT_NAMES)
    np.testing.assert_array_equal(p, [[2.0, 1.0]])
    np.testing.assert_array_equal(v, [[4.0, 3.0]])


def test_joint_state_decode_picks_joints_from_a_full_robot():
    ts = bagio.typestore()
    names = ("torso_lift_joint", JOINT_NAMES[1], "head_pan_joint", JOINT_NAMES[0])
    raws = [bytes(ts.serialize_cdr(bagio.joint_state_message(k, names, [0.1, 0.02 + k, 0.3, 1.0 + k],
                                                             [1.0, 0.01 * k, 3.0, 2.0 * k]),
                                   bagio.JOINT_STATE_TYPE)) for k in range(3)]
    s, p, v, got = decode_joint_state_batch(raws, JOINT_NAMES)
    assert got == JOINT_NAMES
    np.testing.assert_array_equal(p, [[1.0 + k, 0.02 + k] for k in range(3)])
    np.testing.assert_array_equal(v, [[2.0 * k, 0.01 * k] for k in range(3)])


@pytest.mark.parametrize("storage,compress", [("mcap", False), ("mcap", True), ("sqlite3", False)])
def test_recording_round_trip(tmp_path, storage, compress):
    rec = _random_recording()
    out = tmp_path / "bag"
    write_recording(out, rec, storage=storage, compress=compress)
    assert (out / "metadata.yaml").exists()
    back = read_recording(out)
    for name in ("accel_stamps_ns", "accel", "joint_stamps_ns", "joint_position", "joint_velocity", "contact",
                 "ego", "command_stamps_ns", "commands"):
        np.testing.assert_array_equal(getattr(back, name), getattr(rec, name), err_msg=name)
    assert back.joint_names == JOINT_NAMES
    assert back.denoised is None
    # rosbags' own reader sees the contract's topics, log time = header stamp.
    with Reader(out) as reader:
        topics = {c.topic for c in reader.connections}
        assert topics == {BAG_TOPICS[k] for k in ("raw", "contact", "ego", "joint_states", "commands")}
        conn = [c for c in reader.connections if c.topic == BAG_TOPICS["raw"]]
        log_time, raw = next((t, r) for _, t, r in reader.messages(connections=conn))
        assert log_time == decode_imu(raw)[0] == rec.accel_stamps_ns[0]
        times = [t for _, t, _ in reader.messages()]
        assert times == sorted(times)


def test_denoised_topic_round_trip(tmp_path):
    rec = _random_recording(with_truth=False)
    rec.denoised_stamps_ns = rec.accel_stamps_ns[:100]
    rec.denoised = rec.accel[:100] * 0.5
    write_recording(tmp_path / "bag", rec)
    back = read_recording(tmp_path / "bag")
    assert back.contact is None and back.ego is None
    np.testing.assert_array_equal(back.denoised, rec.denoised)
    np.testing.assert_array_equal(back.denoised_stamps_ns, rec.denoised_stamps_ns)


def test_bag_writer_raw_bytes(tmp_path):
    stamps = np.arange(10, dtype=np.int64) * 333_333
    accel = np.arange(30, dtype=float).reshape(10, 3)
    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic(BAG_TOPICS["raw"], bagio.IMU_TYPE)
        bag.add_topic(BAG_TOPICS["joint_states"], bagio.JOINT_STATE_TYPE)
        bag.write_many(BAG_TOPICS["raw"], stamps, encode_imu_batch(stamps, accel))
        bag.write(BAG_TOPICS["joint_states"], 0, encode_joint_state_batch([0], [[0.0, 0.01]], [[1.0, 0.02]])[0])
    back = read_recording(tmp_path / "bag")
    np.testing.assert_array_equal(back.accel, accel)
    np.testing.assert_array_equal(back.joint_velocity, [[1.0, 0.02]])


def test_missing_topic_is_bag_error(tmp_path):
    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic(BAG_TOPICS["raw"], bagio.IMU_TYPE)
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


@pytest.mark.parametrize("compress", [False, True])
def test_fast_mcap_scan_equals_rosbags_reader(tmp_path, monkeypatch, compress):
    rec = _random_recording(seconds=2.0)
    rec.denoised_stamps_ns, rec.denoised = rec.accel_stamps_ns, rec.accel * 0.25
    write_recording(tmp_path / "bag", rec, compress=compress)
    assert bagio._mcap_files(tmp_path / "bag") is not None
    fast = read_recording(tmp_path / "bag")
    monkeypatch.setattr(bagio, "_mcap_files", lambda path: None)      # force rosbags' reader
    slow = read_recording(tmp_path / "bag")
    for name in ("accel_stamps_ns", "accel", "joint_stamps_ns", "joint_position", "joint_velocity", "contact",
                 "ego", "denoised_stamps_ns", "denoised", "command_stamps_ns", "commands"):
        np.testing.assert_array_equal(getattr(fast, name), getattr(slow, name), err_msg=name)
        np.testing.assert_array_equal(getattr(fast, name), getattr(rec, name), err_msg=name)


def test_missing_joint_is_bag_error(tmp_path):
    ts = bagio.typestore()
    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic(BAG_TOPICS["raw"], bagio.IMU_TYPE)
        bag.add_topic(BAG_TOPICS["joint_states"], bagio.JOINT_STATE_TYPE)
        bag.write(BAG_TOPICS["raw"], 1, encode_imu_batch([1], [[0.0, 0.0, 1.0]])[0])
        raw = ts.serialize_cdr(bagio.joint_state_message(1, [JOINT_NAMES[0]], [0.0], [0.0]), bagio.JOINT_STATE_TYPE)
        bag.write(BAG_TOPICS["joint_states"], 1, bytes(raw))
    with pytest.raises(BagError, match=JOINT_NAMES[1]):
        read_recording(tmp_path / "bag")


def test_empty_joint_state_batch_encodes_to_nothing():
    from egovib_ros.bagio import encode_joint_state_batch
    assert encode_joint_state_batch(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2))) == []
