"""egovib_ros.bag.recording: Recordings written and read back, sliced in time, from any robot
profile (topics, the Imu field, joints picked by name); bad bags are one-line BagErrors."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from synthetic import RECORDING_FIELDS, random_recording

from egovib_ros.bag import (
    BagWriter,
    codec,
    concat_recordings,
    decode_imu,
    encode_imu_batch,
    encode_joint_state_batch,
    iter_recording,
    read_recording,
    write_recording,
)
from egovib_ros.bag.recording import bag_topic_names
from egovib_ros.errors import BagError
from egovib_ros.robot import RobotProfile
from egovib_ros.sim.pr2 import JOINT_NAMES

BAG_TOPICS = bag_topic_names()  # the PR2 hand's


@pytest.mark.parametrize("storage,compress", [("mcap", False), ("mcap", True), ("sqlite3", False)])
def test_recording_round_trip(tmp_path, storage, compress):
    rec = random_recording()
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
    rec = random_recording(with_truth=False)
    rec.denoised_stamps_ns = rec.sensor_stamps_ns[:100]
    rec.denoised = rec.sensor[:100] * 0.5
    write_recording(tmp_path / "bag", rec)
    back = read_recording(tmp_path / "bag")
    assert back.contact is None and back.ego is None
    np.testing.assert_array_equal(back.denoised, rec.denoised)
    np.testing.assert_array_equal(back.denoised_stamps_ns, rec.denoised_stamps_ns)


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
    rec = random_recording(seconds=0.1)
    write_recording(tmp_path / "trunc", rec)
    mcap = next((tmp_path / "trunc").glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:5000])
    with pytest.raises(BagError, match="trunc"):
        read_recording(tmp_path / "trunc")


def test_existing_output_is_refused(tmp_path):
    (tmp_path / "bag").mkdir()
    with pytest.raises(BagError, match="already exists"):
        write_recording(tmp_path / "bag", random_recording(seconds=0.01))


def test_missing_joint_is_bag_error(tmp_path):
    ts = codec.typestore()
    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic(BAG_TOPICS["raw"], codec.IMU_TYPE)
        bag.add_topic(BAG_TOPICS["joint_states"], codec.JOINT_STATE_TYPE)
        bag.write(BAG_TOPICS["raw"], 1, encode_imu_batch([1], [[0.0, 0.0, 1.0]])[0])
        raw = ts.serialize_cdr(
            codec.rosbags_joint_state(1, [JOINT_NAMES[0]], [0.0], [0.0]), codec.JOINT_STATE_TYPE
        )
        bag.write(BAG_TOPICS["joint_states"], 1, bytes(raw))
    with pytest.raises(BagError, match=JOINT_NAMES[1]):
        read_recording(tmp_path / "bag")


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
            msg = codec.rosbags_joint_state(
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
        gyro = np.random.default_rng(0).normal(scale=0.01, size=(3000, 3))
        raws = encode_imu_batch(stamps, gyro, field="angular_velocity")
        bag.write_batch("/imu/data_raw", stamps, raws)
        for k in range(10):
            arm = codec.rosbags_joint_state(
                k * 2_000_000, ["elbow", "wrist"], [k, 10 + k], [0.1 * k, 1 + k]
            )
            tool = codec.rosbags_joint_state(
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
    rec = random_recording(seconds=12.0, with_truth=True)
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
    for name in RECORDING_FIELDS:
        if getattr(rec, name) is not None:
            np.testing.assert_array_equal(getattr(whole, name), getattr(rec, name), err_msg=name)


def test_topics_written_apart_are_read_together(tmp_path):
    """A bag whose sensor chunks all come before its joint-state chunks (a writer that
    flushes per topic): chunks are read in log-time order (seeking along the chunk index),
    so no slice waits long for its joint states and the slices equal the whole."""
    from egovib_ros.bag.mcapfile import McapScanner

    rec = random_recording(seconds=6.0, with_truth=False)
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


@pytest.mark.parametrize("order", ["topic", "rtopic"])
def test_a_converter_clock_holds_the_samples_until_their_joint_states_are_in(tmp_path, order):
    """A converter that writes one topic after the other and logs its own clock puts every
    sensor sample before every joint state in log time (or the reverse): a topic not read
    yet may hold any stamp, so no slice goes on before the joint states its samples need."""
    import bagcorpus

    rec = random_recording(seconds=12.0, with_truth=True)
    write_recording(tmp_path / "bag", rec)
    layout = bagcorpus.Layout("converter", order=order, log="writer", chunk_bytes=64 << 10)
    bagcorpus.write_layout(tmp_path / "bag", tmp_path / "converted", layout)
    # without the ground truth (as denoise reads): the frontier moves on through topics the
    # stream does not want, while the joint states are still to come
    slices = list(iter_recording(tmp_path / "converted", min_slice_s=0.3, ground_truth=False))
    joints_so_far = 0
    for piece in slices:
        joints_so_far += len(piece.joint_stamps_ns)
        if len(piece.sensor_stamps_ns):
            needed = np.searchsorted(
                rec.joint_stamps_ns, piece.sensor_stamps_ns.max() + int(0.1e9), side="right"
            )
            assert joints_so_far >= needed
    whole = concat_recordings(slices)
    for name in ("sensor_stamps_ns", "sensor", "joint_stamps_ns", "joint_velocity"):
        if getattr(rec, name) is not None:
            np.testing.assert_array_equal(getattr(whole, name), getattr(rec, name), err_msg=name)


def test_log_times_that_never_advance_count_each_early_sample_once(tmp_path, caplog):
    """Every message logged at one time: the frontier never moves, so at most max_lag_s of
    samples is held and the rest goes on early, each sample counted once in the warning."""
    import logging

    import bagcorpus

    from egovib_ros.bag import BagReader
    from egovib_ros.bag.recording import RecordingStream

    rec = random_recording(seconds=12.0, with_truth=False)
    write_recording(tmp_path / "bag", rec)
    layout = bagcorpus.Layout("constant", log="same", chunk_bytes=64 << 10)
    bagcorpus.write_layout(tmp_path / "bag", tmp_path / "constant", layout)
    with BagReader(tmp_path / "constant") as reader:
        stream = RecordingStream(reader, max_lag_s=2.0, min_slice_s=1.0)
        pieces = [p for batch in reader.batches(stream.topics) for p in stream.add(batch)]
        with caplog.at_level(logging.WARNING):
            pieces += stream.finish()
    assert 0 < stream.released_early <= len(rec.sensor_stamps_ns)
    assert f"{stream.released_early} sensor samples went on" in caplog.text
    whole = concat_recordings(pieces)
    np.testing.assert_array_equal(whole.sensor, rec.sensor)


# --------------------------------------------------------------------------
# A recorder's topics start and stop at their own moments (bag_recorder, ros2 bag record)
# --------------------------------------------------------------------------
def _truth_cut_bag(path, rec, cuts: dict[str, tuple[int, int]]) -> None:
    """The recording with the ground-truth topics written from/up to other samples than
    the raw topic: cuts = {"contact": (first, stop), "ego": (first, stop)}."""
    with BagWriter(path) as bag:
        for key, values in (("raw", rec.sensor), ("contact", rec.contact), ("ego", rec.ego)):
            a, b = cuts.get(key, (0, len(values)))
            stamps = rec.sensor_stamps_ns[a:b]
            bag.add_topic(BAG_TOPICS[key], codec.IMU_TYPE)
            bag.write_batch(BAG_TOPICS[key], stamps, encode_imu_batch(stamps, values[a:b]))
        bag.add_topic(BAG_TOPICS["joint_states"], codec.JOINT_STATE_TYPE)
        bag.write_batch(
            BAG_TOPICS["joint_states"],
            rec.joint_stamps_ns,
            encode_joint_state_batch(
                rec.joint_stamps_ns, rec.joint_position, rec.joint_velocity, JOINT_NAMES
            ),
        )


def test_ground_truth_starting_later_and_stopping_earlier_is_cut_to_the_shared_stamps(
    tmp_path, caplog
):
    """The sensor topic and its ground truth are read over the stamps they share; the samples
    at either end without their counterpart are left out and counted (one warning)."""
    rec = random_recording(seconds=3.0)
    n = len(rec.sensor_stamps_ns)
    _truth_cut_bag(tmp_path / "bag", rec, {"contact": (5, n - 7), "ego": (3, n - 2)})
    with caplog.at_level("WARNING", logger="egovib_ros.bag"):
        back = read_recording(tmp_path / "bag")
    np.testing.assert_array_equal(back.sensor_stamps_ns, rec.sensor_stamps_ns[5 : n - 7])
    np.testing.assert_array_equal(back.sensor, rec.sensor[5 : n - 7])
    np.testing.assert_array_equal(back.contact, rec.contact[5 : n - 7])
    np.testing.assert_array_equal(back.ego, rec.ego[5 : n - 7])
    (said,) = [r.getMessage() for r in caplog.records if "start or stop" in r.getMessage()]
    assert "12 of /accelerometer/raw" in said and "7 of /accelerometer/ego" in said, said
    assert "5 of /accelerometer/contact" not in said  # its own ends are the shared ones


def test_ground_truth_missing_a_sample_in_the_middle_is_still_refused(tmp_path):
    rec = random_recording(seconds=3.0)
    with BagWriter(tmp_path / "bag") as bag:
        for key, values in (("raw", rec.sensor), ("contact", rec.contact), ("ego", rec.ego)):
            keep = np.ones(len(values), bool)
            keep[4000] = key != "contact"
            stamps = rec.sensor_stamps_ns[keep]
            bag.add_topic(BAG_TOPICS[key], codec.IMU_TYPE)
            bag.write_batch(BAG_TOPICS[key], stamps, encode_imu_batch(stamps, values[keep]))
        bag.add_topic(BAG_TOPICS["joint_states"], codec.JOINT_STATE_TYPE)
        bag.write_batch(
            BAG_TOPICS["joint_states"],
            rec.joint_stamps_ns,
            encode_joint_state_batch(
                rec.joint_stamps_ns, rec.joint_position, rec.joint_velocity, JOINT_NAMES
            ),
        )
    with pytest.raises(BagError, match="/accelerometer/contact does not have the stamps"):
        read_recording(tmp_path / "bag")


# --------------------------------------------------------------------------
# JointStates that name the joints but carry too few numbers
# --------------------------------------------------------------------------
def _joint_state_bag(path, rec, position, velocity, effort) -> None:
    """The recording's raw topic with JointStates whose arrays are built by the callables
    `position(row)`, `velocity(row)`, `effort(row)` (any lengths)."""
    ts = codec.typestore()
    with BagWriter(path) as bag:
        bag.add_topic(BAG_TOPICS["raw"], codec.IMU_TYPE)
        bag.write_batch(
            BAG_TOPICS["raw"],
            rec.sensor_stamps_ns,
            encode_imu_batch(rec.sensor_stamps_ns, rec.sensor),
        )
        bag.add_topic(BAG_TOPICS["joint_states"], codec.JOINT_STATE_TYPE)
        for i, stamp in enumerate(rec.joint_stamps_ns.tolist()):
            msg = codec.rosbags_joint_state(stamp, JOINT_NAMES, position(i), velocity(i))
            msg.effort = effort(i)
            bag.write(
                BAG_TOPICS["joint_states"],
                stamp,
                bytes(ts.serialize_cdr(msg, codec.JOINT_STATE_TYPE)),
            )


def test_joint_states_with_effort_only_are_refused_as_such(tmp_path):
    """Every message names both joints but carries only efforts: said so, not that the
    topic lacks the joints."""
    rec = random_recording(seconds=1.5, with_truth=False)
    none = np.zeros(0)
    _joint_state_bag(
        tmp_path / "bag", rec, lambda i: none, lambda i: none, lambda i: np.array([0.1, 0.2])
    )
    with pytest.raises(BagError) as info:
        read_recording(tmp_path / "bag")
    message = str(info.value)
    assert "r_wrist_roll_joint, r_gripper_joint named in its messages" in message, message
    assert "effort only" in message and "lacks" not in message and "\n" not in message


def test_a_velocity_array_shorter_than_the_names_is_said(tmp_path, caplog):
    """Velocities for the first joint only: a malformed JointState. The value goes to the
    first name, the second joint's velocity comes from its positions (joints.velocity:
    auto), and a warning says how many messages were so."""
    rec = random_recording(seconds=1.5, with_truth=False)
    rec.joint_position = np.cumsum(np.full_like(rec.joint_position, 1e-3), axis=0)
    _joint_state_bag(
        tmp_path / "bag",
        rec,
        lambda i: rec.joint_position[i],
        lambda i: rec.joint_velocity[i, :1],
        lambda i: np.zeros(0),
    )
    with caplog.at_level("WARNING", logger="egovib_ros.bag"):
        back = read_recording(tmp_path / "bag")
    np.testing.assert_array_equal(back.joint_velocity[:, 0], rec.joint_velocity[:, 0])
    assert np.allclose(back.joint_velocity[5:, 1], 1.0)  # 1e-3 per 1 ms, from the positions
    said = caplog.text
    assert f"{len(rec.joint_stamps_ns)} messages carry fewer velocity values than" in said, said


def test_a_joint_named_twice_in_a_message_is_said(tmp_path, caplog):
    """Two drivers writing into one JointState (a probe's bag: the wrist named first with
    another's values): the first of each name is used, and said (it was silent)."""
    rec = random_recording(seconds=1.5, with_truth=False)
    ts = codec.typestore()
    names = (JOINT_NAMES[0], *JOINT_NAMES)
    with BagWriter(tmp_path / "bag") as bag:
        bag.add_topic(BAG_TOPICS["raw"], codec.IMU_TYPE)
        stamps = rec.sensor_stamps_ns
        bag.write_batch(BAG_TOPICS["raw"], stamps, encode_imu_batch(stamps, rec.sensor))
        bag.add_topic(BAG_TOPICS["joint_states"], codec.JOINT_STATE_TYPE)
        for i, stamp in enumerate(rec.joint_stamps_ns.tolist()):
            values = np.r_[9.0, rec.joint_velocity[i]]
            msg = codec.rosbags_joint_state(stamp, names, np.zeros(3), values)
            raw = bytes(ts.serialize_cdr(msg, codec.JOINT_STATE_TYPE))
            bag.write(BAG_TOPICS["joint_states"], stamp, raw)
    with caplog.at_level("WARNING", logger="egovib_ros.bag"):
        back = read_recording(tmp_path / "bag")
    assert np.all(back.joint_velocity[:, 0] == 9.0)  # the first of the two
    np.testing.assert_array_equal(back.joint_velocity[:, 1], rec.joint_velocity[:, 1])
    n = len(rec.joint_stamps_ns)
    assert f"a joint named twice in a message {n} times" in caplog.text, caplog.text
