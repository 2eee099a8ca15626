"""egovib_ros.bag.codec: the vectorised codec agrees with rosbags for both Imu vector fields."""

import numpy as np
import pytest

from egovib_ros.bag import codec


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
            ts.serialize_cdr(codec.imu_message(int(stamp), xyz, frame_id, field), codec.IMU_TYPE)
        )
    got_stamps, got = codec.decode_imu(raws, field)
    assert np.array_equal(got_stamps, stamps) and np.array_equal(got, values)
    other = "angular_velocity" if field == "linear_acceleration" else "linear_acceleration"
    assert np.array_equal(codec.decode_imu(raws, other)[1], np.zeros((3, 3)))


@pytest.mark.parametrize("field", codec.IMU_FIELDS)
def test_replace_field_keeps_every_other_byte(field):
    ts = codec.typestore()
    msg = codec.imu_message(42, [1.0, 2.0, 3.0], "imu", "linear_acceleration")
    msg.angular_velocity.x, msg.orientation.w, msg.orientation_covariance[4] = 5.0, 0.5, 0.25
    raw = bytes(ts.serialize_cdr(msg, codec.IMU_TYPE))
    fast = codec.replace_imu_field([raw, raw], np.array([[7.0, 8.0, 9.0], [0.0, 0.0, 1.0]]), field)
    # the per-message path (mixed lengths) gives the same bytes
    odd = bytes(
        ts.serialize_cdr(codec.imu_message(1, [0, 0, 0], "a_longer_frame_name"), codec.IMU_TYPE)
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
