"""ROS message <-> numpy conversion against rclpy's own serialisation."""
from __future__ import annotations

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import Imu, JointState

from egovib_ros.errors import StreamError
from egovib_ros.ros_convert import (command_message, command_velocity, decode_imu_messages,
                                    decode_joint_state_messages, diagnostic_array, diagnostic_values,
                                    encode_imu_batch, encode_joint_state_batch, imu_message, imu_sample,
                                    joint_state_arrays, joint_state_message, ns_to_stamp, stamp_to_ns)


def test_stamps_round_trip():
    for ns in (0, 1, 999_999_999, 1_700_000_000_123_456_789):
        assert stamp_to_ns(ns_to_stamp(ns)) == ns


def test_imu_batch_bytes_are_rclpy_messages_and_decode_back():
    rng = np.random.default_rng(0)
    stamps = 1_700_000_000_000_000_000 + np.arange(50, dtype=np.int64) * 333_333
    accel = rng.normal(size=(50, 3))
    raws = encode_imu_batch(stamps, accel)
    for raw, stamp, values in zip(raws, stamps, accel):
        msg = deserialize_message(raw, Imu)
        assert msg == imu_message(int(stamp), values)            # REP 145 conventions included
        assert msg.orientation_covariance[0] == -1 and msg.angular_velocity_covariance[0] == -1
    got_stamps, got, bad = decode_imu_messages(raws)
    assert bad == 0
    np.testing.assert_array_equal(got_stamps, stamps)
    np.testing.assert_array_equal(got, accel)
    # rclpy's own bytes decode the same way
    stamp, values = imu_sample(deserialize_message(serialize_message(imu_message(5, [1, 2, 3])), Imu))
    assert stamp == 5 and list(values) == [1, 2, 3]


def test_bad_imu_messages_are_dropped_not_fatal():
    raws = encode_imu_batch(np.arange(4, dtype=np.int64), np.ones((4, 3)))
    raws[1] = raws[1][:40]                                       # truncated
    raws[2] = encode_imu_batch(np.array([2]), np.array([[np.nan, 0, 0]]))[0]
    stamps, accel, bad = decode_imu_messages(raws)
    assert bad == 2
    np.testing.assert_array_equal(stamps, [0, 3])


def test_joint_states_follow_requested_names():
    msg = joint_state_message(7, [0.1, 0.2], [1.0, 2.0], names=("r_gripper_joint", "r_wrist_roll_joint"))
    stamp, position, velocity = joint_state_arrays(msg)
    assert stamp == 7
    np.testing.assert_array_equal(position, [0.2, 0.1])
    np.testing.assert_array_equal(velocity, [2.0, 1.0])
    with pytest.raises(StreamError, match="joint_states: .*lacks"):
        joint_state_arrays(joint_state_message(7, [0.1], [1.0], names=("other_joint",)))
    raws = encode_joint_state_batch(np.array([1, 2]), np.zeros((2, 2)), np.array([[1.0, 2.0], [3.0, 4.0]]))
    assert deserialize_message(raws[0], JointState).velocity.tolist() == [1.0, 2.0]
    stamps, _, velocity, bad = decode_joint_state_messages(raws + [b"\x00\x01\x00\x00garbage"])
    assert bad == 1
    np.testing.assert_array_equal(stamps, [1, 2])
    np.testing.assert_array_equal(velocity, [[1.0, 2.0], [3.0, 4.0]])


def test_commands_are_checked():
    np.testing.assert_array_equal(command_velocity(command_message([1.5, -0.02])), [1.5, -0.02])
    with pytest.raises(StreamError, match="hand_velocity_controller/commands"):
        command_velocity(command_message([1.0]))
    with pytest.raises(StreamError):
        command_velocity(command_message([np.inf, 0.0]))


def test_diagnostic_array_carries_values():
    array = diagnostic_array(3, [("denoiser", "warn", "drops", {"rate": 2999.51234, "n": 3})])
    status = array.status[0]
    assert status.name == "denoiser" and status.message == "drops" and status.level == b"\x01"
    assert diagnostic_values(status) == {"rate": "2999.51", "n": "3"}
