"""`egovib calibrate` and `egovib denoise` on real bag files, as a user runs them."""
import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from egovib_ros.bagio import bag_topics, read_recording, write_recording
from egovib_ros.core import NoiseModel, denoise_batch
from egovib_ros.sim import simulate_motion, simulate_sweep


def egovib(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "egovib_ros.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=300)


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("offline")
    sweep, _ = simulate_sweep(grid="superposition", dwell_s=1.0, settle_s=0.3, seed=3)
    # A calibration bag needs no ground truth; leaving it out keeps the test quick.
    write_recording(root / "sweep", dataclasses.replace(sweep, contact=None, ego=None))
    motion, _ = simulate_motion(duration_s=4.0, max_speed=0.5, tap_rate_hz=1.0, seed=4)
    write_recording(root / "motion", motion)
    return root


def test_calibrate_then_denoise_round_trip(bags):
    model_path = bags / "model.npz"
    result = egovib("calibrate", bags / "sweep", "--out", model_path, "--quiet")
    assert result.returncode == 0, result.stderr
    model = NoiseModel.load(model_path)
    assert model.measured == "superposition"                       # auto-detected
    assert np.all(model.counts[model.axis_mask()] > 0)
    assert model.provenance["source"].endswith("sweep")

    out = bags / "denoised"
    result = egovib("denoise", bags / "motion", "--model", model_path, "--out", out, "--quiet")
    assert result.returncode == 0, result.stderr
    topics = bag_topics(out)
    raw_count = topics["/accelerometer/raw"][1]
    assert topics["/accelerometer/denoised"] == ("sensor_msgs/msg/Imu", raw_count)
    for topic in ("/joint_states", "/accelerometer/contact", "/accelerometer/ego"):
        assert topic in topics
    rec = read_recording(out)
    np.testing.assert_array_equal(rec.denoised_stamps_ns, rec.accel_stamps_ns)
    _, expected, _ = denoise_batch(rec.accel_stamps_ns, rec.accel, rec.joint_stamps_ns, rec.joint_velocity, model)
    np.testing.assert_allclose(rec.denoised, expected, rtol=0, atol=1e-12)


def test_combined_channel_goes_to_x(bags):
    model_path = bags / "model_c.npz"
    assert egovib("calibrate", bags / "sweep", "--out", model_path, "--quiet").returncode == 0
    out = bags / "denoised_combined"
    result = egovib("denoise", bags / "motion", "--model", model_path, "--out", out, "--channels", "combined",
                    "--quiet")
    assert result.returncode == 0, result.stderr
    rec = read_recording(out)
    assert np.all(rec.denoised[:, 1:] == 0) and np.any(rec.denoised[:, 0] != 0)


def test_bad_input_is_one_line_exit_2_and_leaves_nothing(bags, tmp_path):
    result = egovib("calibrate", tmp_path / "absent", "--out", tmp_path / "m.npz")
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "absent: no such bag" in result.stderr
    assert not (tmp_path / "m.npz").exists()

    broken = tmp_path / "broken.npz"
    broken.write_bytes(b"PK\x03\x04 not really a zip")
    result = egovib("denoise", bags / "motion", "--model", broken, "--out", tmp_path / "out")
    assert result.returncode == 2 and "broken.npz" in result.stderr
    assert result.stderr.strip().count("\n") == 0
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob("*.partial"))

    # A bag without steady grid velocities is not a calibration sweep.
    result = egovib("calibrate", bags / "motion", "--out", tmp_path / "m.npz", "--quiet")
    if result.returncode == 2:
        assert "calibration sweep" in result.stderr and not (tmp_path / "m.npz").exists()
    else:   # random motion does cross grid cells now and then; then a (sparse) model is fine
        assert NoiseModel.load(tmp_path / "m.npz").counts.sum() > 0
