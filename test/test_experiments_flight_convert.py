"""The real flight log: converter round trip, the shipped bag, the quadcopter profile."""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from egovib_research.experiments.flight.convert import FILTERED_TOPIC, convert, motor_positions
from egovib_research.experiments.flight.flightlog import (
    MOTOR_NAMES,
    FlightLogError,
    load_flight_log,
)
from egovib_research.experiments.flight.recording import read_flight_bag
from egovib_ros.cli import main as egovib
from egovib_ros.robot import load_profile

REPO = Path(__file__).resolve().parents[1]
SHIPPED_BAG = REPO / "bags" / "quadcopter_ar8"
# ../shared/real beside the checkout (main) or beside the worktree directory
NPZ = next(
    (
        p / "shared" / "real" / "quadcopter_ar8_flight.npz"
        for p in (REPO.parent, REPO.parent.parent)
        if (p / "shared" / "real" / "quadcopter_ar8_flight.npz").exists()
    ),
    REPO / "missing.npz",
)
needs_npz = pytest.mark.skipif(
    not NPZ.exists(), reason="the decoded flight log (../shared/real) is not here"
)


def _small_npz(path: Path, n: int = 400, seed: int = 0, drop: str | None = None) -> dict:
    """A flight-log-shaped npz with jittery stamps (the real log's field names and units)."""
    rng = np.random.default_rng(seed)
    time_s = np.cumsum(np.round(rng.uniform(0.0009, 0.00125, n) * 1e6) / 1e6) - 0.001
    fields = {
        "time_s": time_s,
        "gyro_unfiltered_dps": rng.normal(0, 20, (n, 3)).astype(np.float32),
        "gyro_filtered_dps": rng.normal(0, 5, (n, 3)).astype(np.float32),
        "motor_cmd_frac": rng.uniform(-0.001, 1.0, (n, 4)).astype(np.float32),
        "meta_json": np.array('{"firmware": "test"}'),
    }
    if drop:
        fields.pop(drop)
    np.savez(path, **fields)
    return fields


def test_profile_loads_with_the_logs_conventions():
    profile = load_profile("quadcopter")
    assert profile.sensor_topic == "/imu/data_raw" and profile.sensor_field == "angular_velocity"
    assert profile.rate_hz == 1000 and profile.joints_topic == "/joint_states"
    assert profile.joint_names == MOTOR_NAMES
    assert profile.max_speed == (1.0,) * 4 and profile.bidirectional == (False,) * 4
    assert profile.sensor_range == pytest.approx(math.radians(2000.0), rel=1e-6)
    assert (
        profile.band_hz[1] < profile.rate_hz / 2 and profile.band_hz[0] < 120
    )  # motor lines 120-400 Hz in band
    assert profile.grid_shape == (profile.steps + 1,) * 4
    assert profile.grid()[0][0] == 0.0 and profile.grid()[0][-1] == 1.0


def test_converter_round_trip_gives_the_samples_and_stamps(tmp_path):
    fields = _small_npz(tmp_path / "log.npz")
    summary = convert(tmp_path / "log.npz", tmp_path / "bag")
    assert summary["samples"] == 400
    profile = load_profile("quadcopter")
    rec = read_flight_bag(tmp_path / "bag", profile)
    stamps = np.round(fields["time_s"] * 1e6).astype(np.int64) * 1000
    np.testing.assert_array_equal(rec.sensor_stamps_ns, stamps)  # the log's jittery sample times
    np.testing.assert_array_equal(rec.joint_stamps_ns, stamps)  # joint states at the sensor rate
    np.testing.assert_array_equal(rec.filtered_stamps_ns, stamps)
    np.testing.assert_allclose(
        rec.sensor, np.deg2rad(fields["gyro_unfiltered_dps"].astype(float)), rtol=0, atol=0
    )
    np.testing.assert_allclose(
        rec.filtered, np.deg2rad(fields["gyro_filtered_dps"].astype(float)), rtol=0, atol=0
    )
    np.testing.assert_array_equal(rec.joint_velocity, fields["motor_cmd_frac"].astype(float))
    np.testing.assert_allclose(
        rec.joint_position, motor_positions(stamps, fields["motor_cmd_frac"].astype(float))
    )
    readme = (tmp_path / "bag" / "README.md").read_text()
    assert "MIT OR Apache-2.0" in readme and "LOG00037.BFL" in readme and "gyroflow" in readme


def test_converted_imu_is_rep145_with_the_gyro_in_angular_velocity(tmp_path):
    from rosbags.rosbag2 import Reader

    from egovib_ros.bag.codec import typestore

    _small_npz(tmp_path / "log.npz", n=20)
    convert(tmp_path / "log.npz", tmp_path / "bag")
    with Reader(tmp_path / "bag") as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        assert topics == {
            "/imu/data_raw": "sensor_msgs/msg/Imu",
            FILTERED_TOPIC: "sensor_msgs/msg/Imu",
            "/joint_states": "sensor_msgs/msg/JointState",
        }
        conn = next(c for c in reader.connections if c.topic == "/imu/data_raw")
        _, _, raw = next(reader.messages(connections=[conn]))
        joints = next(c for c in reader.connections if c.topic == "/joint_states")
        _, _, raw_js = next(reader.messages(connections=[joints]))
    msg = typestore().deserialize_cdr(raw, "sensor_msgs/msg/Imu")
    assert msg.orientation_covariance[0] == -1 and msg.linear_acceleration_covariance[0] == -1
    assert msg.angular_velocity_covariance[0] == 0 and msg.angular_velocity.x != 0
    js = typestore().deserialize_cdr(raw_js, "sensor_msgs/msg/JointState")
    assert list(js.name) == list(MOTOR_NAMES) and len(js.velocity) == 4


@needs_npz
def test_shipped_bag_holds_the_flight_log():
    log = load_flight_log(NPZ)
    rec = read_flight_bag(SHIPPED_BAG, load_profile("quadcopter"))
    np.testing.assert_array_equal(rec.sensor_stamps_ns, log.stamps_ns)
    np.testing.assert_array_equal(rec.sensor, log.gyro)
    np.testing.assert_array_equal(rec.filtered, log.gyro_filtered)
    np.testing.assert_array_equal(rec.joint_velocity, log.motors)
    steps = np.diff(rec.sensor_stamps_ns) / 1e6
    assert 0.85 < steps.min() < 0.95 and 1.2 < steps.max() < 1.3  # the log's jitter is kept
    assert sum(f.stat().st_size for f in SHIPPED_BAG.iterdir()) < 4e6  # small (zstd MCAP chunks)
    assert "MIT OR Apache-2.0" in (SHIPPED_BAG / "README.md").read_text()


def test_bad_flight_log_is_a_one_line_error_and_leaves_no_bag(tmp_path, capsys):
    assert (
        egovib(["real", "convert", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "bag")])
        == 2
    )
    assert not (tmp_path / "bag").exists()
    _small_npz(tmp_path / "nomotors.npz", drop="motor_cmd_frac")
    assert (
        egovib(["real", "convert", str(tmp_path / "nomotors.npz"), "--out", str(tmp_path / "bag")])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "missing.npz" in err[0] and "motor_cmd_frac" in err[1]
    assert not (tmp_path / "bag").exists() and not list(tmp_path.glob("*.partial"))
    with pytest.raises(FlightLogError, match="not a readable"):
        (tmp_path / "junk.npz").write_bytes(b"not a zip")
        load_flight_log(tmp_path / "junk.npz")


def test_a_joint_the_bag_lacks_is_named(tmp_path):
    import dataclasses

    from egovib_ros.errors import BagError

    _small_npz(tmp_path / "log.npz", n=20)
    convert(tmp_path / "log.npz", tmp_path / "bag")
    profile = load_profile("quadcopter")
    names = ("motor1", "motor5", "motor3", "motor4")
    other = dataclasses.replace(profile, joint_names=names, source="")
    with pytest.raises(BagError, match=r"topic /joint_states lacks joint\(s\) motor5"):
        read_flight_bag(tmp_path / "bag", other)
    with pytest.raises(BagError, match="missing topic /imu/other"):
        other = dataclasses.replace(profile, sensor_topic="/imu/other", source="")
        read_flight_bag(tmp_path / "bag", other)


def test_converter_command(tmp_path):
    _small_npz(tmp_path / "log.npz", n=50)
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "egovib_ros.cli",
            "real",
            "convert",
            str(tmp_path / "log.npz"),
            "--out",
            str(tmp_path / "bag"),
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert done.returncode == 0, done.stderr
    assert "50 samples" in done.stdout and (tmp_path / "bag" / "metadata.yaml").exists()
