"""bag_player and bag_recorder on real DDS; the denoiser on a replayed bag vs `egovib denoise`."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Reader
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu

from egovib_ros.bagio import decode_imu_batch, read_recording, write_recording
from egovib_ros.nodes.common import sensor_qos
from egovib_ros.ros_convert import stamp_to_ns
from egovib_ros.sim import simulate_motion

EGOVIB = str(Path(sys.executable).parent / "egovib")


def bag_imu(path: Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """Stamps and values of an Imu topic of a bag."""
    with Reader(path) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        raws = [bytes(data) for _, _, data in reader.messages(connections=conns)]
    return decode_imu_batch(raws)


def make_motion_bag(path: Path, seconds: float, seed: int) -> None:
    rec, _ = simulate_motion(duration_s=seconds, max_speed=0.5, tap_rate_hz=2.0, seed=seed)
    write_recording(path, rec)


def wait_for_log(nodes, proc, text: str, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while text not in nodes.log(proc):
        assert time.monotonic() < deadline and proc.poll() is None, nodes.log(proc)
        time.sleep(0.1)


def test_replayed_bag_denoised_live_equals_offline(nodes, sim_model_path, tmp_path):
    source = tmp_path / "motion"
    make_motion_bag(source, 3.0, seed=3)
    offline = tmp_path / "offline"
    subprocess.run(
        [
            EGOVIB,
            "denoise",
            str(source),
            "--model",
            str(sim_model_path),
            "--out",
            str(offline),
            "--quiet",
        ],
        check=True,
        capture_output=True,
    )
    want_stamps, want = bag_imu(offline, "/accelerometer/denoised")

    # Reliable input (standard QoS override): the replay must not lose samples on a loaded machine.
    den = nodes.start(
        "denoiser",
        {
            "model": str(sim_model_path),
            "flush_after_idle": 0.3,
            "qos_overrides./accelerometer/raw.subscription.reliability": "reliable",
            "qos_overrides./joint_states.subscription.reliability": "reliable",
        },
    )
    rec = nodes.start(
        "bag_recorder", {"output": str(tmp_path / "live"), "topics": ["accelerometer/denoised"]}
    )
    wait_for_log(nodes, rec, "/accelerometer/denoised: subscribed")
    time.sleep(0.5)
    player = nodes.start(
        "bag_player",
        {
            "bag": str(source),
            "wait_for_subscribers": 1,
            "topics": ["/joint_states", "/accelerometer/raw"],
        },
    )
    assert player.wait(60) == 0, nodes.log(player)
    time.sleep(1.5)  # idle flush of the last held samples, and delivery
    assert nodes.stop(rec) == 0, nodes.log(rec)
    assert nodes.stop(den) == 0, nodes.log(den)
    assert "received 9000, written 9000" in nodes.log(rec), nodes.log(rec)

    got_stamps, got = bag_imu(tmp_path / "live", "/accelerometer/denoised")
    np.testing.assert_array_equal(got_stamps, want_stamps)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_player_timing_rate_and_clock(nodes, ros_client, tmp_path):
    source = tmp_path / "motion"
    make_motion_bag(source, 2.0, seed=4)
    want = read_recording(source, ground_truth=False, denoised=False)
    node = ros_client.node
    raw, clock, arrival = [], [], []
    node.create_subscription(
        Imu,
        "accelerometer/raw",
        lambda m: (raw.append(m), arrival.append(time.monotonic())),
        sensor_qos(),
        raw=True,
    )
    node.create_subscription(Clock, "/clock", lambda m: clock.append(stamp_to_ns(m.clock)), 100)
    player = nodes.start(
        "bag_player",
        {
            "bag": str(source),
            "rate": 2.0,
            "clock": True,
            "wait_for_subscribers": 1,
            "topics": ["/accelerometer/raw"],
        },
    )
    assert ros_client.spin_until(lambda: player.poll() is not None, timeout=60), nodes.log(player)
    ros_client.spin_for(0.3)
    assert player.returncode == 0, nodes.log(player)

    stamps, _ = decode_imu_batch(raw)
    np.testing.assert_array_equal(stamps, want.accel_stamps_ns)
    played_s = arrival[-1] - arrival[0]
    assert 0.8 * want.duration_s / 2 < played_s < 1.5 * want.duration_s / 2
    clock = np.asarray(clock)
    assert len(clock) > 100 and np.all(np.diff(clock) > 0)
    with Reader(source) as reader:
        assert reader.start_time <= clock[0] and clock[-1] <= reader.end_time
