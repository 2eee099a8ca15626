"""End to end on real DDS: sim_hand and denoiser in their own processes, a subscriber here."""
from __future__ import annotations

import numpy as np
from scipy import signal
from sensor_msgs.msg import Imu
from std_msgs.msg import Float64MultiArray
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus

from egovib_ros.constants import BAND_HZ, BAND_ORDER, MAX_SPEED
from egovib_ros.nodes.common import sensor_qos, stream_publisher_qos
from egovib_ros.ros_convert import command_message, decode_imu_messages, diagnostic_values, encode_imu_batch


def test_live_denoiser_keeps_stamps_and_lowers_noise(nodes, ros_client, sim_model_path):
    sim = nodes.start("sim_hand", {"seed": 5, "tap_rate_hz": 0.0, "publish_ground_truth": False})
    den = nodes.start("denoiser", {"model": str(sim_model_path)})
    node = ros_client.node
    raw, denoised, diagnostics = [], [], []
    node.create_subscription(Imu, "accelerometer/raw", raw.append, sensor_qos(), raw=True)
    node.create_subscription(Imu, "accelerometer/denoised", denoised.append, sensor_qos(), raw=True)
    node.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)
    commands = node.create_publisher(Float64MultiArray, "hand_velocity_controller/commands", 10)
    moving = command_message([0.5 * MAX_SPEED[0], 0.0])     # no contact: all of raw is ego-vibration

    assert ros_client.spin_until(lambda: len(denoised) > 300 and len(raw) > 300, timeout=30), \
        nodes.log(sim) + nodes.log(den)
    raw.clear()           # both streams flow now: compare from here on
    denoised.clear()
    for _ in range(60):                                       # 3 s of motion, command repeated
        commands.publish(moving)
        ros_client.spin_for(0.05)
    assert nodes.stop(den) == 0
    assert nodes.stop(sim) == 0

    raw_stamps, raw_accel, bad = decode_imu_messages(raw)
    den_stamps, den_accel, bad_denoised = decode_imu_messages(denoised)
    assert bad == bad_denoised == 0
    # Every output sample carries the stamp of a raw sample, in order, one per sample
    # (within the span this subscriber received raw samples).
    seen = (den_stamps >= raw_stamps[0]) & (den_stamps <= raw_stamps[-1])
    assert seen.sum() > 3000 * 2
    assert np.all(np.isin(den_stamps[seen], raw_stamps))
    assert np.all(np.diff(den_stamps) > 0)
    # No sample lost between the first and last denoised one this subscriber saw.
    span = (raw_stamps >= den_stamps[seen][0]) & (raw_stamps <= den_stamps[seen][-1])
    assert seen.sum() == span.sum()
    # No-contact noise level (paper: mean magnitude of the band-passed signal) while moving.
    sos = signal.butter(BAND_ORDER, BAND_HZ, btype="bandpass", fs=3000.0, output="sos")
    raw_bp = signal.sosfilt(sos, raw_accel, axis=0)
    moving_from = raw_stamps[0] + int((raw_stamps[-1] - raw_stamps[0]) * 0.5)   # the last half
    raw_level = np.abs(raw_bp[raw_stamps >= moving_from]).mean()
    den_level = np.abs(den_accel[den_stamps >= moving_from]).mean()
    assert den_level < 0.7 * raw_level, (raw_level, den_level)
    status = [s for d in diagnostics for s in d.status if s.name == "denoiser"]
    assert status and float(diagnostic_values(status[-1])["input_rate_hz"]) > 1000


def test_denoiser_survives_bad_messages_and_passes_through_without_joint_states(nodes, ros_client,
                                                                                   sim_model_path):
    den = nodes.start("denoiser", {"model": str(sim_model_path)})
    node = ros_client.node
    denoised, diagnostics = [], []
    node.create_subscription(Imu, "accelerometer/denoised", denoised.append, sensor_qos(), raw=True)
    node.create_subscription(DiagnosticArray, "/diagnostics", diagnostics.append, 10)
    raw_pub = node.create_publisher(Imu, "accelerometer/raw", stream_publisher_qos())
    assert ros_client.spin_until(lambda: raw_pub.get_subscription_count() > 0, timeout=30), nodes.log(den)
    ros_client.spin_for(0.5)

    rng = np.random.default_rng(1)
    n = 3000
    stamps = 1_700_000_000_000_000_000 + np.arange(n, dtype=np.int64) * 1_000_000_000 // 3000
    accel = rng.normal(0.0, 1.0, (n, 3))
    messages = encode_imu_batch(stamps, accel)
    for i in range(0, n, 30):
        for data in messages[i:i + 30]:
            raw_pub.publish(data)
        if i == 1500:
            raw_pub.publish(b"\x00\x01\x00\x00 not an Imu")   # a bad message mid-stream
        ros_client.spin_for(0.01)
    assert ros_client.spin_until(lambda: len(denoised) >= n, timeout=20), len(denoised)
    ros_client.spin_for(1.2)                                     # one more diagnostics round
    assert den.poll() is None, nodes.log(den)                    # still alive

    den_stamps, den_accel, _ = decode_imu_messages(denoised)
    np.testing.assert_array_equal(den_stamps, stamps)
    # No joint state: the output is the band-passed input (per axis).
    sos = signal.butter(BAND_ORDER, BAND_HZ, btype="bandpass", fs=3000.0, output="sos")
    expected = signal.sosfilt(sos, accel, axis=0)
    np.testing.assert_allclose(den_accel[200:], expected[200:], atol=1e-6 * np.abs(expected).max())
    status = [s for d in diagnostics for s in d.status if s.name == "denoiser"][-1]
    values = diagnostic_values(status)
    assert status.level == DiagnosticStatus.WARN and "no joint state" in status.message
    assert int(values["bad_messages"]) == 1 and int(values["samples_in"]) == n
    assert nodes.stop(den) == 0
