"""egovib_ros.bag.codec: the vectorised codec agrees with rosbags byte for byte (Imu, both vector
fields and any frame_id; JointState of any joints in any order)."""

from __future__ import annotations

import numpy as np
import pytest

from egovib_ros.bag import (
    codec,
    decode_imu,
    decode_joint_states,
    encode_imu_batch,
    encode_joint_state_batch,
)
from egovib_ros.bag.codec import joint_state_layout
from egovib_ros.sim.pr2 import JOINT_NAMES


@pytest.mark.parametrize("field", codec.IMU_FIELDS)
@pytest.mark.parametrize("frame_id", ["", "imu_link", "r_gripper_motor_accelerometer_link"])
def test_imu_field_roundtrip_matches_rosbags(field, frame_id):
    rng = np.random.default_rng(0)
    stamps = np.array([0, 1_500_000_123, 7_000_000_000_001])
    values = rng.normal(size=(3, 3))
    raws = codec.encode_imu_batch(stamps, values, frame_id, field)
    ts = codec.typestore()
    for stamp, xyz, raw in zip(stamps, values, raws):
        assert raw == bytes(
            ts.serialize_cdr(codec.rosbags_imu(int(stamp), xyz, frame_id, field), codec.IMU_TYPE)
        )
    got_stamps, got = codec.decode_imu(raws, field)
    assert np.array_equal(got_stamps, stamps) and np.array_equal(got, values)
    other = "angular_velocity" if field == "linear_acceleration" else "linear_acceleration"
    assert np.array_equal(codec.decode_imu(raws, other)[1], np.zeros((3, 3)))


@pytest.mark.parametrize("field", codec.IMU_FIELDS)
def test_replace_field_keeps_every_other_byte(field):
    ts = codec.typestore()
    msg = codec.rosbags_imu(42, [1.0, 2.0, 3.0], "imu", "linear_acceleration")
    msg.angular_velocity.x, msg.orientation.w, msg.orientation_covariance[4] = 5.0, 0.5, 0.25
    raw = bytes(ts.serialize_cdr(msg, codec.IMU_TYPE))
    fast = codec.replace_imu_field([raw, raw], np.array([[7.0, 8.0, 9.0], [0.0, 0.0, 1.0]]), field)
    # the per-message path (mixed lengths) gives the same bytes
    odd = bytes(
        ts.serialize_cdr(codec.rosbags_imu(1, [0, 0, 0], "a_longer_frame_name"), codec.IMU_TYPE)
    )
    slow = codec.replace_imu_field([raw, odd], np.array([[7.0, 8.0, 9.0], [0.0, 0.0, 1.0]]), field)
    assert fast[0] == slow[0]
    out = ts.deserialize_cdr(fast[0], codec.IMU_TYPE)
    assert (out.header.stamp.nanosec, out.header.frame_id) == (42, "imu")
    assert out.orientation.w == 0.5 and out.orientation_covariance[4] == 0.25
    vector = getattr(out, field)
    assert (vector.x, vector.y, vector.z) == (7.0, 8.0, 9.0)
    if field == "angular_velocity":
        assert out.linear_acceleration.x == 1.0
    else:
        assert out.angular_velocity.x == 5.0


def test_unknown_field_is_refused():
    with pytest.raises(ValueError, match="Imu field"):
        codec.decode_imu([b""], "magnetic_field")


def test_imu_codec_matches_rosbags_serialisation():
    ts = codec.typestore()
    stamps = np.array([0, 1, 1_500_000_123, 1_700_000_000_999_999_999], np.int64)
    accel = np.array([[0.0, -0.0, 1.5], [1e-9, 78.5, -78.5], [3.25, 2.0, 1.0], [-1.0, 0.5, 9.81]])
    fast = encode_imu_batch(stamps, accel)
    for stamp, xyz, raw in zip(stamps, accel, fast):
        reference = bytes(ts.serialize_cdr(codec.rosbags_imu(int(stamp), xyz), codec.IMU_TYPE))
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
        ts.serialize_cdr(codec.rosbags_imu(int(stamps[1]), accel[1], frame_id), codec.IMU_TYPE)
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
                codec.rosbags_joint_state(int(stamps[i]), JOINT_NAMES, pos[i], vel[i]),
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
            codec.rosbags_joint_state(7, JOINT_NAMES[::-1], [1.0, 2.0], [3.0, 4.0]),
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
                codec.rosbags_joint_state(
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


def test_empty_joint_state_batch_encodes_to_nothing():
    from egovib_ros.bag import encode_joint_state_batch

    assert (
        encode_joint_state_batch(
            np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 2)), JOINT_NAMES
        )
        == []
    )


def _joint_state(stamp, names, position, velocity, frame_id=""):
    msg = codec.rosbags_joint_state(stamp, names, position, velocity, frame_id)
    return bytes(codec.typestore().serialize_cdr(msg, codec.JOINT_STATE_TYPE))


def test_joint_state_layouts_alternating_between_calls_decode_by_name():
    # the fast path remembers the last layout: a batch of another layout of the same length
    # (joints swapped, another frame of the same length, more joints) is walked afresh
    a, b = JOINT_NAMES
    layouts = [
        ((a, b), "base"),
        ((b, a), "base"),
        ((a, b), "hand"),
        ((a, "x", b), "base"),
        ((a, b), "base"),
    ]
    for k, (names, frame) in enumerate(layouts * 2):
        values = {n: 10.0 * k + i for i, n in enumerate(names)}
        raws = [
            _joint_state(k, names, [values[n] for n in names], [-values[n] for n in names], frame)
            for _ in range(2)
        ]
        _, p, v = decode_joint_states(raws, JOINT_NAMES)
        np.testing.assert_array_equal(p, [[values[a], values[b]]] * 2)
        np.testing.assert_array_equal(v, [[-values[a], -values[b]]] * 2)


def test_packed_and_scattered_batches_read_the_same_bytes():
    rng = np.random.default_rng(0)
    raws = [rng.integers(0, 256, 40, dtype=np.uint8).tobytes() for _ in range(5)]
    packed = codec.MessageBatch.from_list(raws, np.zeros(5, np.int64))
    assert packed.packed is not None
    # the same messages inside a larger buffer, in another order: no packed view
    buf = np.frombuffer(b"".join([b"\0" * 3 + r for r in raws[::-1]]), np.uint8)
    starts = np.arange(4, -1, -1) * 43 + 3
    scattered = codec.MessageBatch(buf, starts, np.full(5, 40), np.zeros(5, np.int64))
    assert scattered.packed is None
    np.testing.assert_array_equal(packed.matrix(), scattered.matrix())
    assert packed.to_list() == scattered.to_list() == raws


def test_messages_serialised_by_rclpy_decode_with_their_stray_trailing_bytes():
    """rclpy's serialize_message (what rosbag2_py writers are given) leaves 8 stray bytes
    after a positions-only JointState; rosbags refuses more than 3, a DDS reader ignores
    them, and so does the codec (bags written that way were refused as undecodable)."""
    serialization = pytest.importorskip("rclpy.serialization")
    from sensor_msgs.msg import Imu, JointState

    msg = JointState(name=list(JOINT_NAMES), position=[0.5, 0.02])
    msg.header.stamp.sec, msg.header.stamp.nanosec = 12, 345
    raw = bytes(serialization.serialize_message(msg))
    stamps, position, velocity = decode_joint_states([raw], JOINT_NAMES)
    assert stamps.tolist() == [12_000_000_345]
    np.testing.assert_array_equal(position, [[0.5, 0.02]])
    assert np.isnan(velocity).all()
    imu = Imu()
    imu.header.frame_id = "imu_link"
    imu.linear_acceleration.z = 9.81
    padded = bytes(serialization.serialize_message(imu)) + bytes(8)
    _, values = decode_imu([padded])
    np.testing.assert_array_equal(values, [[0.0, 0.0, 9.81]])


def test_a_joint_named_twice_decodes_to_its_first_values_in_any_batch():
    """A JointState naming a joint twice (a broken driver) gives the first occurrence's
    values whether its batch takes the packed path or the per-message one."""
    from egovib_ros.bag.codec import JOINT_STATE_TYPE, rosbags_joint_state, typestore

    def cdr(names, position, velocity) -> bytes:
        msg = rosbags_joint_state(
            10**18, names, np.array(position, float), np.array(velocity, float)
        )
        return bytes(typestore().serialize_cdr(msg, JOINT_STATE_TYPE))

    names = list(JOINT_NAMES)
    twice = cdr([*names, names[0]], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0])
    alone = decode_joint_states([twice], names)
    mixed = decode_joint_states([twice, cdr(names, [1.0, 2.0], [4.0, 5.0])], names)
    for _, position, velocity in (alone, mixed):
        np.testing.assert_array_equal(position[0], [1.0, 2.0])
        np.testing.assert_array_equal(velocity[0], [4.0, 5.0])
