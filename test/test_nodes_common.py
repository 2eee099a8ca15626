"""egovib_ros.nodes.common over real DDS: a raw subscription drained per callback takes
every message once, in order, a burst at a time; run_node's exit status and close() for an
error raised in a callback and for SIGTERM."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from sensor_msgs.msg import Imu

from egovib_ros.bag.codec import decode_imu, encode_imu_batch
from egovib_ros.nodes.common import drain, sensor_subscription, stream_publisher


def test_drain_takes_each_message_once_in_order_a_burst_per_callback(ros_client):
    node = ros_client.node
    publisher = stream_publisher(node, Imu, "drain_test")
    batches: list[list[bytes]] = []
    sub = sensor_subscription(
        node, Imu, "drain_test", lambda data: batches.append(drain(sub, Imu, data))
    )
    assert ros_client.spin_until(lambda: publisher.get_subscription_count() > 0, 20.0)
    n_bursts, burst = 60, 30
    raws = encode_imu_batch(np.arange(n_bursts * burst), np.zeros((n_bursts * burst, 3)))
    for k in range(n_bursts):
        for raw in raws[k * burst : (k + 1) * burst]:
            publisher.publish(raw)
        ros_client.spin_for(0.01)
    assert ros_client.spin_until(lambda: sum(map(len, batches)) >= len(raws), 20.0)
    ros_client.spin_for(0.2)  # the executor's events of drained messages find nothing
    stamps, _ = decode_imu([raw for batch in batches for raw in batch])
    np.testing.assert_array_equal(stamps, np.arange(len(raws)))
    assert len(batches) < len(raws) / 2  # bursts taken whole, not a callback per message


NODE_SCRIPT = """
import os, signal, sys, threading
from rclpy.node import Node
from egovib_ros.errors import ConfigError
from egovib_ros.nodes.common import run_node

class Probe(Node):
    def __init__(self):
        super().__init__("probe")
        if sys.argv[1] == "raise":
            self.create_timer(0.2, self.fail)
        else:  # "term": stopped from outside while spinning
            threading.Timer(1.0, os.kill, (os.getpid(), signal.SIGTERM)).start()

    def fail(self):
        raise ConfigError("probe: a bad setting found in a callback")

    def close(self):
        print("closed", flush=True)

sys.exit(run_node(Probe, []))
"""


@pytest.mark.parametrize(
    "mode, status, text",
    # the node named once (it was "probe: error: probe: ..." for a message naming it)
    [("raise", 2, "probe: error: a bad setting found in a callback"), ("term", 0, "closed")],
)
def test_run_node_exit_status_and_close_for_errors_in_callbacks_and_sigterm(
    ros_domain, mode, status, text
):
    done = subprocess.run(
        [sys.executable, "-c", NODE_SCRIPT, mode], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == status, done.stderr
    assert text in done.stdout + done.stderr
    assert "closed" in done.stdout  # close() runs on every way out


def test_joint_states_split_per_joint_are_joined_live_and_the_held_stamp_flushed_at_the_end(
    ros_client,
):
    """StreamInput (the nodes' input) joins one message per joint of one stamp into one row,
    as the bag reader does offline; when the input goes quiet (`final`) the last stamp,
    held back while it could still grow, comes out too, even with no new message."""
    from egovib_ros.bag.codec import encode_joint_state_batch
    from egovib_ros.nodes.common import StreamInput
    from egovib_ros.robot import load_profile

    profile = load_profile(None)  # the PR2 hand: two joints
    names = list(profile.joint_names)
    inp = StreamInput(ros_client.node, profile, batch_samples=32, on_batch=lambda: None)
    stamps = np.arange(1, 6, dtype=np.int64) * 1_000_000
    velocity = np.column_stack([np.arange(5.0), -np.arange(5.0)])
    for k, name in enumerate(names):  # one publisher per joint, both stamping a tick alike
        raws = encode_joint_state_batch(
            stamps, velocity[:, k : k + 1] * 0, velocity[:, k : k + 1], [name]
        )
        inp._joints += [bytes(r) for r in raws]  # as the subscription callback collects them
    per_joint = inp._joints
    # interleaved in arrival, and the second joint's message of the last stamp never comes
    inp._joints = [per_joint[i // 2 + (i % 2) * 5] for i in range(9)]
    first = inp.take_joints()
    np.testing.assert_array_equal(first.stamps_ns, stamps[:4])  # the last stamp held
    np.testing.assert_array_equal(first.velocity, velocity[:4])
    assert inp.take_joints() is None  # nothing new, not the end: still held
    last = inp.take_joints(final=True)
    np.testing.assert_array_equal(last.stamps_ns, stamps[4:])
    # the joint it lacks keeps its last value (hold_missing_joints), as offline
    np.testing.assert_array_equal(last.velocity, [[velocity[4, 0], velocity[3, 1]]])


def test_a_joint_never_seen_says_why_undecodable_or_without_values(ros_client):
    """The missing-joint ERROR names the cause: messages that do not decode, messages that
    name the joints with no position or velocity (effort only), or only other joints (the
    model of another robot)."""
    from rosbags.typesys.stores.ros2_jazzy import (
        builtin_interfaces__msg__Time as Time,
    )
    from rosbags.typesys.stores.ros2_jazzy import sensor_msgs__msg__JointState as JointState
    from rosbags.typesys.stores.ros2_jazzy import std_msgs__msg__Header as Header

    from egovib_ros.bag.codec import JOINT_STATE_TYPE, typestore
    from egovib_ros.nodes.common import StreamInput
    from egovib_ros.robot import load_profile

    profile = load_profile(None)
    names = list(profile.joint_names)
    empty = np.zeros(0)
    effort_only = JointState(
        header=Header(stamp=Time(sec=1, nanosec=0), frame_id=""),
        name=names,
        position=empty,
        velocity=empty,
        effort=np.ones(len(names)),
    )
    raw = bytes(typestore().serialize_cdr(effort_only, JOINT_STATE_TYPE))
    arm = JointState(  # the example arm's joints: a model of another robot was given
        header=Header(stamp=Time(sec=1, nanosec=0), frame_id=""),
        name=["shoulder", "elbow", "wrist"],
        position=np.zeros(3),
        velocity=np.ones(3),
        effort=empty,
    )
    cases = {
        "with no position or velocity": [raw],
        "2 of its messages undecodable": [raw[:9]] * 2,
        "none of robot profile 'pr2_right_hand': a model of another robot?": [
            bytes(typestore().serialize_cdr(arm, JOINT_STATE_TYPE))
        ],
    }
    for why, raws in cases.items():
        inp = StreamInput(ros_client.node, profile, batch_samples=32, on_batch=lambda: None)
        inp._joints += raws  # as the subscription callback collects them
        inp.take_joints(final=True)  # the row is not held back as a stamp still growing
        assert inp.missing_joints() == names
        message = inp.missing_joints_message(inp.missing_joints())
        assert why in message and all(name in message for name in names), message


def test_the_clock_note_names_stamps_far_apart_while_joint_states_arrive(ros_client):
    """Latest sensor and joint-state stamps more than a second apart, with joint states
    arriving: two clocks, ahead or behind; a few ms apart (any lag): nothing."""
    from egovib_ros.bag.codec import encode_imu_batch, encode_joint_state_batch
    from egovib_ros.nodes.common import StreamInput
    from egovib_ros.robot import load_profile

    profile = load_profile(None)
    names = list(profile.joint_names)
    sensor = np.arange(1, 31, dtype=np.int64) * 333_333 + 1_700_000_000 * 10**9
    notes = {}
    for offset_s in (0.005, 5.0, -1.8e9):
        inp = StreamInput(ros_client.node, profile, batch_samples=32, on_batch=lambda: None)
        joints = sensor[::3] + int(offset_s * 1e9)
        inp._sensor += [bytes(r) for r in encode_imu_batch(sensor, np.zeros((30, 3)))]
        inp._arrival += [0] * 30
        inp._joints += [
            bytes(r)
            for r in encode_joint_state_batch(joints, np.zeros((10, 2)), np.ones((10, 2)), names)
        ]
        inp.take_sensor()
        inp.take_joints(final=True)
        notes[offset_s] = inp.clock_note()
    assert notes[0.005] == ""
    assert notes[5.0].startswith("joint-state stamps 5 s ahead of the sensor's"), notes
    assert notes[-1.8e9].startswith("joint-state stamps 1.8e+09 s behind"), notes
    assert all("different clocks" in notes[k] for k in (5.0, -1.8e9))


def test_stamps_that_repeat_are_said_with_their_likely_cause(ros_client):
    """Most of a report's sensor samples dropped as out of order (every stamp zero): the
    report says the stamps repeat and names the likely causes; a few: nothing more."""
    from egovib_ros.nodes.common import StreamInput
    from egovib_ros.robot import load_profile

    inp = StreamInput(ros_client.node, load_profile(None), batch_samples=32, on_batch=lambda: None)
    inp.sensor_messages, inp.joint_messages = 3000, 1000
    notes = inp.stamp_notes({"samples_out_of_order": 2999, "joint_states_dropped": 3})
    assert len(notes) == 1 and notes[0].startswith(f"{inp.sensor_topic}: most stamps repeat")
    assert "stamps zero" in notes[0]
    inp.sensor_messages, inp.joint_messages = 6000, 2000  # the next report: counted anew
    assert inp.stamp_notes({"samples_out_of_order": 10, "joint_states_dropped": 999}) == [
        f"{inp.joints_topic}: most stamps repeat or go back (a driver that stamps zero, or a "
        "stuck clock?)"
    ]


def test_a_burst_delivered_in_pieces_is_processed_once_whole(ros_client, monkeypatch):
    """A per-sample method's batches follow the driver's bursts: in a stream that began with
    1 sample, then bursts of 6, the second delivered as 5 + 1 (each callback takes what
    waits), that burst is processed at its last message; a block method (`from_first`)
    processes at every 6th message counted from the first, so that burst's last message
    waits for the next burst."""
    from egovib_ros.bag.codec import encode_imu_batch
    from egovib_ros.nodes import common
    from egovib_ros.robot import load_profile

    messages = encode_imu_batch(np.arange(13, dtype=np.int64) * 333_333, np.zeros((13, 3)))
    deliveries = [[0], [1, 2, 3, 4, 5, 6], [7, 8, 9, 10, 11], [12]]
    wants = {
        False: [[0, 1, 2, 3, 4, 5, 6], [7, 8, 9, 10, 11, 12]],
        True: [[0, 1, 2, 3, 4, 5, 6], [7, 8, 9, 10, 11]],
    }
    for from_first, want in wants.items():
        batches = []
        inp = common.StreamInput(
            ros_client.node,
            load_profile(None),
            batch_samples=6,
            on_batch=lambda: batches.append(inp.take_sensor()),  # noqa: B023
            from_first=from_first,
        )
        for delivery in deliveries:
            taken = [messages[k] for k in delivery]
            monkeypatch.setattr(common, "drain", lambda sub, kind, data, taken=taken: taken)
            inp._on_sensor(taken[0])
        got = [(b.stamps_ns // 333_333).tolist() for b in batches]
        assert got == want, (from_first, got)


def test_two_publishers_on_the_sensor_topic_are_named(ros_client):
    """Two sensors on one topic look like one stream at another rate: the refusal says how
    many publish on it."""
    from egovib_ros.nodes.common import StreamInput
    from egovib_ros.robot import load_profile

    profile = load_profile(None)
    inp = StreamInput(ros_client.node, profile, batch_samples=32, on_batch=lambda: None)
    assert inp.publishers_note() == ""
    publishers = [
        ros_client.node.create_publisher(Imu, profile.node_sensor_topic, 10) for _ in range(2)
    ]
    assert ros_client.spin_until(lambda: inp.publisher_counts()["sensor_publishers"] == 2, 10.0)
    assert inp.publishers_note() == f" (2 publishers on {inp.sensor_topic})"
    for publisher in publishers:
        ros_client.node.destroy_publisher(publisher)


def test_ctrl_c_of_busy_nodes_ends_each_cleanly(nodes, sim_model_path, tmp_path):
    """Ctrl-C at a terminal (SIGINT to every node at once) while sim_hand streams through the
    denoiser into contact_detector, the calibrator and bag_recorder: every node exits 0,
    having closed (the recorder's bag, the calibrator's model), and none prints a traceback,
    a "[FATAL] ... context is invalid" (a callback publishing after rclpy's own handler had
    shut the context down: 3 of 3 such runs here) or "Failed to publish log message to
    rosout" (close() logging after it)."""
    import signal
    import time

    from egovib_research.tools.orchestration import deep_output

    topics = ("/accelerometer/raw", "/joint_states")
    procs = {
        "sim_hand": nodes.start(
            "sim_hand", {"seed": 3, "tap_rate_hz": 5.0, **deep_output(*topics)}
        ),
        "denoiser": nodes.start("denoiser", {"model": str(sim_model_path)}),
        "contact_detector": nodes.start(
            "contact_detector", {"model": str(sim_model_path), "threshold": 0.5}
        ),
        "calibrator": nodes.start("calibrator", {"output": str(tmp_path / "live.npz")}),
        "bag_recorder": nodes.start(
            "bag_recorder",
            {
                "output": str(tmp_path / "rec"),
                "topics": ["accelerometer/raw", "accelerometer/denoised"],
            },
        ),
    }
    nodes.wait_for_log(procs["sim_hand"], "simulation started")
    nodes.wait_for_log(procs["bag_recorder"], "/accelerometer/denoised: subscribed")
    time.sleep(3.0)  # everything busy
    for proc in procs.values():
        proc.send_signal(signal.SIGINT)
    for name, proc in procs.items():
        assert proc.wait(60) == 0, nodes.log(proc)
        log = nodes.log(proc)
        for text in ("Traceback", "[FATAL]", "rosout", "context is invalid"):
            assert text not in log, (name, log[-3000:])
    assert (tmp_path / "rec" / "metadata.yaml").is_file() and (tmp_path / "live.npz").is_file()
