"""sim_robot on real DDS: a robot that is not the PR2, live end to end, as README's "Your
robot, live" runs it, shortened (0.35 s per cell, a 6 s run whose motion this test
commands). config/robots/example_arm.yaml (3 joints, an accelerometer on /arm/imu at
2 kHz): sweep_driver commands its superposition grid to sim_robot, the calibrator measures
the model while bag_recorder keeps the sweep (no contact: the detector's threshold, its
`calibration_bag`); then sim_robot with taps, the denoiser with the live model, and
contact_detector on its output find the simulator's true taps. And a sim_robot behind its
clock (this test publishes /clock) moves when commanded, not when it catches up."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from conftest import matched
from geometry_msgs.msg import Vector3Stamped
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from scipy import signal
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray

from egovib_research.tools.orchestration import deep_output, reliable_input
from egovib_research.tools.watcher import decode_imu_messages, decode_joint_state_messages
from egovib_ros.core import NoiseModel
from egovib_ros.evaluation.contacts import TOLERANCE_S
from egovib_ros.nodes.common import stream_publisher_qos
from egovib_ros.nodes.convert import command_message, diagnostic_values, stamp_to_ns
from egovib_ros.robot import load_profile

pytestmark = pytest.mark.nodes  # the node suite: `pytest -m nodes`

ARM = load_profile("example_arm")
TOPICS = ("/arm/imu", "/joint_states")  # the profile's
EVENTS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
RUN_S = 6.0  # the run with taps


def test_example_arm_live_sweep_calibrate_denoise_and_detect_its_taps(nodes, ros_client, tmp_path):
    """The sweep (31 cells of 0.15 s settle + 0.4 s dwell) calibrates every cell of the
    superposition grid live; 6 s of motion with taps (2 per second) come out of the
    denoiser one message per raw sample, stamps kept, the ego-vibration lowered in the band;
    contact_detector (threshold from the recorded sweep, `calibration_bag`) reports the taps
    within 10 ms of their true onsets (the `<parent>/contact` ground truth sim_robot
    publishes) with few false alarms."""
    model_path, sweep_bag = tmp_path / "arm.npz", tmp_path / "arm_sweep"
    calibrator = nodes.start(
        "calibrator",
        {
            "robot": "example_arm",
            "output": str(model_path),
            "grid": "superposition",
            **reliable_input(*TOPICS),
        },
    )
    recorder = nodes.start(
        "bag_recorder", {"output": str(sweep_bag), "topics": ["arm/imu", "joint_states"]}
    )
    sim = nodes.start(
        "sim_robot",
        {
            "robot": "example_arm",
            "seed": 1,
            "publish_ground_truth": False,
            "wait_for_subscribers": 2,  # the calibrator and the recorder see every sample
            **deep_output(*TOPICS),
        },
    )
    nodes.wait_for_log(recorder, "/arm/imu: subscribed")
    nodes.wait_for_log(recorder, "/joint_states: subscribed")
    nodes.wait_for_log(sim, "simulation started")
    driver = nodes.start(
        "sweep_driver",
        {"robot": "example_arm", "grid": "superposition", "dwell": 0.4, "settle": 0.15},
    )
    # The driver exits once its stop command is acknowledged (up to a DDS heartbeat later)
    assert ros_client.spin_until(lambda: "sweep done" in nodes.log(driver), 120), nodes.log(driver)
    assert "cell 31/31" in nodes.log(driver)
    # a busy machine may leave sim_robot behind the clock: it applies each command at the
    # stamp it arrived, so the sweep is whole once it has caught up (lag < 0.1 s)
    ros_client.statuses.pop("sim_robot", None)
    assert ros_client.spin_until(
        lambda: (
            "sim_robot" in ros_client.statuses
            and int(diagnostic_values(ros_client.statuses["sim_robot"])["max_lag_samples"]) < 200
        ),
        60,
    ), ros_client.statuses.get("sim_robot")
    sim_values = diagnostic_values(ros_client.statuses["sim_robot"])
    assert nodes.stop(sim) == 0, nodes.log(sim)
    assert "Traceback" not in nodes.log(sim), nodes.log(sim)  # a clean Ctrl-C
    ros_client.spin_for(0.5)
    assert nodes.stop(calibrator) == 0, nodes.log(calibrator)
    assert nodes.stop(recorder) == 0, nodes.log(recorder)
    assert driver.wait(30) == 0, nodes.log(driver)

    model = NoiseModel.load(model_path)
    assert model.robot_profile().name == "example_arm" and model.sample_rate_hz == 2000
    assert model.measured == "superposition"
    assert np.all(model.counts[model.axis_mask()] >= 3), model.counts[model.axis_mask()]
    # sim_robot's own report: the profile's rate, the driver's commands within the ranges
    assert sim_values["command"].startswith("[0.0, 0.0, "), sim_values  # the wrist's cells
    assert int(sim_values["commands_received"]) > 0 and int(sim_values["commands_limited"]) == 0
    assert abs(float(sim_values["sensor_rate_hz"]) - 2000) < 300, sim_values

    # --- the run: taps, denoised live, contact events ---------------------------------
    denoiser = nodes.start(
        "denoiser",
        {
            "model": str(model_path),
            "joint_wait": 1.0,  # a busy machine may deliver joint states late
            **reliable_input(*TOPICS),
            **deep_output("/arm/imu_denoised"),
        },
    )
    detector = nodes.start(
        "contact_detector",
        {
            "model": str(model_path),
            "calibration_bag": str(sweep_bag),
            **reliable_input("/arm/imu_denoised"),
        },
    )
    node, lossless = ros_client.node, stream_publisher_qos(depth=30_000)
    received = {topic: [] for topic in ("arm/contact", "arm/ego", "arm/imu_denoised")}
    readers = [
        node.create_subscription(Imu, topic, messages.append, lossless, raw=True)
        for topic, messages in received.items()
    ]
    events = []
    node.create_subscription(Vector3Stamped, "contact_events", events.append, EVENTS)
    assert ros_client.spin_until(
        lambda: (
            matched(ros_client, "denoiser", output_subscribers=2)
            and matched(ros_client, "contact_detector", input_publishers=1, event_subscribers=1)
            and readers[-1].get_publisher_count() > 0
        ),
        60.0,
    ), nodes.log(denoiser) + nodes.log(detector)
    sim = nodes.start(
        "sim_robot",
        {
            "robot": "example_arm",
            "seed": 2,
            "tap_rate_hz": 2.0,
            "duration": RUN_S,
            "wait_for_subscribers": 1,
            **deep_output(*TOPICS, "/arm/contact", "/arm/ego"),
        },
        log_name="sim_robot_taps",
    )
    # Smooth motion within half of each joint's top speed, commanded at 20 Hz
    top = np.asarray(ARM.max_speed)
    commands = node.create_publisher(Float64MultiArray, "hand_velocity_controller/commands", 10)
    t = 0.0
    while "simulated 6 s" not in nodes.log(sim):  # then it waits for the acknowledgements
        speed = 0.5 * top * np.sin(2 * np.pi * np.array([0.3, 0.5, 0.7]) * t + [0.0, 1.0, 2.0])
        commands.publish(Float64MultiArray(data=[float(v) for v in speed]))
        ros_client.spin_for(0.05)
        t += 0.05
        assert t < 90 and sim.poll() is None, nodes.log(sim)

    def detector_took_all() -> bool:
        status = ros_client.statuses.get("contact_detector")
        n = len(received["arm/contact"])
        return status is not None and int(diagnostic_values(status)["samples_in"]) == n > 0

    assert ros_client.spin_until(detector_took_all, 60.0), (
        len(received["arm/contact"]),
        diagnostic_values(ros_client.statuses["denoiser"]),
        diagnostic_values(ros_client.statuses["contact_detector"]),
    )
    ros_client.spin_for(0.5)  # the last events, then a report counting them
    den_values = diagnostic_values(ros_client.statuses["denoiser"])
    det_values = diagnostic_values(ros_client.statuses["contact_detector"])
    assert nodes.stop(detector) == 0, nodes.log(detector)
    assert nodes.stop(denoiser) == 0, nodes.log(denoiser)
    assert sim.wait(30) == 0, nodes.log(sim)  # `duration` done: exit status 0
    log = nodes.log(sim)
    assert "simulating example_arm" in log and "2000 Hz" in log and "Traceback" not in log

    # Every sample of the run: the ground truth's stamps are the raw ones; one denoised
    # message per raw sample, each with its raw sample's stamp.
    n = int(round(RUN_S * ARM.rate_hz))
    stamps, contact, _ = decode_imu_messages(received["arm/contact"])
    ego_stamps, ego, _ = decode_imu_messages(received["arm/ego"])
    den_stamps, denoised, _ = decode_imu_messages(received["arm/imu_denoised"])
    assert len(stamps) == n and np.array_equal(ego_stamps, stamps), (len(stamps), n)
    np.testing.assert_array_equal(den_stamps, stamps)
    assert int(den_values["samples_in"]) == n and int(den_values["samples_bad"]) == 0
    steps = np.diff(stamps) / 1e6
    assert np.all(steps > 0) and abs(np.median(steps) - 0.5) < 0.05  # 2 kHz, jittered

    # The ego-vibration lowered in the profile's band, outside the taps and the first 0.5 s
    rises = np.flatnonzero(np.any(contact[1:] != 0, axis=1) & np.all(contact[:-1] == 0, axis=1))
    onsets = stamps[rises]  # a tap rises from a zero sample: its onset
    band = signal.butter(4, ARM.band_hz, btype="band", fs=ARM.rate_hz, output="sos")
    quiet = stamps > stamps[0] + 500_000_000
    for onset in onsets:
        quiet &= ~((stamps >= onset) & (stamps < onset + 60_000_000))
    before = signal.sosfilt(band, ego, axis=0)[quiet]
    after = signal.sosfilt(band, denoised - contact, axis=0)[quiet]
    reduction_db = 10 * np.log10(np.mean(before**2) / np.mean(after**2))
    assert reduction_db > 6.0, reduction_db

    # Contact events at the true onsets (within 10 ms), few false alarms
    # (the last 100 ms left out: an event is reported 10 ms after its crossing)
    found = np.array([stamp_to_ns(e.header.stamp) for e in events], np.int64)
    found = found[found < stamps[-1] - 100_000_000]
    truth = onsets[onsets < stamps[-1] - 100_000_000]
    assert len(truth) >= 5, truth
    error_s = np.array([np.abs(found - t).min() / 1e9 if len(found) else 1.0 for t in truth])
    hits = int(np.sum(error_s <= TOLERANCE_S))
    false_alarms = sum(np.abs(truth - f).min() / 1e9 > TOLERANCE_S for f in found)
    f1 = 2 * hits / (len(truth) + len(found))
    # The threshold comes from the sweep's steady data (31 x 0.4 s): its top samples set it,
    # and it varies from run to run (0.12-0.30 measured with 0.2 s dwells, where two fresh-clone
    # runs had 3 and 4 false alarms; 0.16-0.36 with 0.4 s): room for one false alarm more.
    assert f1 >= 0.8 and false_alarms <= 3, (f1, false_alarms, error_s)
    assert int(det_values["events"]) == len(events) >= len(found)
    assert {e.header.frame_id for e in events} == {"imu_link"}
    print(
        f"example_arm live: {len(model.counts[model.axis_mask()])} cells calibrated, "
        f"noise {reduction_db:.1f} dB lower, {hits}/{len(truth)} taps found, "
        f"{false_alarms} false alarms, threshold {float(det_values['threshold']):.3g}"
    )


def test_bad_parameters_are_one_line_exit_2(ros_domain):
    """A profile that does not exist, more taps than the simulator makes: one line naming
    the profile or the parameter (not the simulator's command-line option), exit status 2."""
    cases = {
        "no_such_arm": (["robot:=no_such_arm"], "no such robot profile"),
        "'tap_rate_hz'": (["robot:=example_arm", "tap_rate_hz:=8.0"], "at most 6.67 taps"),
    }
    runs = {
        key: subprocess.Popen(
            [str(Path(sys.executable).parent / "sim_robot"), "--ros-args"]
            + [a for p in params for a in ("-p", p)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for key, (params, _) in cases.items()
    }
    for key, run in runs.items():
        stdout, stderr = run.communicate(timeout=60)
        assert run.returncode == 2, (key, stdout + stderr)
        errors = [line for line in stderr.splitlines() if "error" in line]
        assert len(errors) == 1 and key in errors[0] and cases[key][1] in errors[0], stderr


def test_a_simulator_behind_its_clock_moves_when_commanded_not_when_it_catches_up(
    nodes, ros_client
):
    """This test is the /clock: it jumps 2 s ahead of sim_robot (which then makes at most
    `max_batch` 0.05 s of samples per tick), a command comes at clock 3 s, and the clock
    creeps on while the simulator catches up. The wrist starts moving at the command's
    clock time, not at the samples the simulator was making when it arrived (1.05 s)."""
    node = ros_client.node
    clock_pub = node.create_publisher(Clock, "/clock", 10)
    command_pub = node.create_publisher(Float64MultiArray, "hand_velocity_controller/commands", 10)
    joints: list = []
    reader = node.create_subscription(
        JointState, "joint_states", joints.append, stream_publisher_qos(depth=30_000), raw=True
    )
    sim = nodes.start(
        "sim_robot",
        {
            "robot": "example_arm",
            "use_sim_time": True,
            "max_batch": 0.05,
            "publish_ground_truth": False,
            **deep_output(*TOPICS),
        },
    )
    assert ros_client.spin_until(
        lambda: (
            reader.get_publisher_count() > 0
            and clock_pub.get_subscription_count() > 0
            and command_pub.get_subscription_count() > 0
        ),
        60,
    ), nodes.log(sim)

    def clock(seconds: float) -> None:
        ns = int(round(seconds * 1e9))
        clock_pub.publish(Clock(clock=Time(sec=ns // 10**9, nanosec=ns % 10**9)))

    def made_until() -> float:  # the last joint state's stamp (s) received: that one decoded
        stamps = decode_joint_state_messages(joints[-1:], ARM.joint_names)[0]
        return stamps[-1] / 1e9 if len(stamps) else 0.0

    # each clock time sent until seen: the first may go before sim_robot's side matched
    assert ros_client.spin_until(lambda: clock(1.0) or "simulation started" in nodes.log(sim), 30)
    assert ros_client.spin_until(lambda: clock(3.0) or made_until() > 1.04, 30), made_until()
    wrist = [0.0, 0.0, 2.0]
    for _ in range(10):  # as sweep_driver repeats it, all at clock 3 s
        command_pub.publish(command_message(wrist))
        ros_client.spin_for(0.05)
    assert made_until() < 2.0  # behind when the command came
    for k in range(1, 151):  # 1.5 s more clock, 10 ms a step: it catches up
        clock(3.0 + 0.01 * k)
        ros_client.spin_for(0.01)
    assert ros_client.spin_until(lambda: made_until() > 4.0, 30), nodes.log(sim)
    assert nodes.stop(sim) == 0, nodes.log(sim)
    stamps, _, velocity, _ = decode_joint_state_messages(joints, ARM.joint_names)
    moving = stamps[velocity[:, 2] > 0.5 * wrist[2]]  # the 50 ms controller: half way ~35 ms
    assert 3.0e9 < moving[0] < 3.1e9, moving[0] / 1e9
