"""`egovib simulate` end to end: real bags written and read back."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from egovib_ros.bag import bag_topics, read_recording
from egovib_ros.bag.recording import bag_topic_names
from egovib_ros.cli import main

BAG_TOPICS = bag_topic_names()  # the PR2 hand's


def test_simulate_motion_bag_and_truth(tmp_path):
    out, truth = tmp_path / "motion", tmp_path / "truth.json"
    rc = main([
        "simulate", "motion", "--duration", "3", "--max-speed", "0.5", "--taps", "2",
        "--out", str(out), "--seed", "7", "--truth", str(truth),
        "--effects", "position=0.5,timing=0.01", "--quiet",
    ])  # fmt: skip
    assert rc == 0
    assert (out / "metadata.yaml").exists() and list(out.glob("*.mcap"))
    topics = bag_topics(out)
    assert set(topics) == {
        BAG_TOPICS[k] for k in ("raw", "contact", "ego", "joint_states", "commands")
    }
    assert topics[BAG_TOPICS["raw"]] == ("sensor_msgs/msg/Imu", 9000)
    data = json.loads(truth.read_text())
    assert data["seed"] == 7 and data["effects"] == {"position": 0.5, "timing": 0.01}
    rec = read_recording(out)
    assert np.all(np.isin(data["tap_onsets_ns"], rec.sensor_stamps_ns))
    # nothing about the effects inside the bag
    blob = b"".join(p.read_bytes() for p in out.iterdir())
    assert b"effects" not in blob and b"timing" not in blob and b"position=" not in blob


def test_simulate_sweep_cli_matches_library(tmp_path):
    from egovib_ros.sim import simulate_sweep

    out = tmp_path / "sweep"
    assert main([
        "simulate", "sweep", "--grid", "superposition", "--dwell", "0.1", "--settle", "0.05",
        "--out", str(out), "--seed", "3", "--quiet", "--compress",
    ]) == 0  # fmt: skip
    rec = read_recording(out)
    ref, _ = simulate_sweep(grid="superposition", dwell_s=0.1, settle_s=0.05, seed=3)
    np.testing.assert_array_equal(rec.sensor, ref.sensor)
    np.testing.assert_array_equal(rec.joint_velocity, ref.joint_velocity)
    np.testing.assert_array_equal(rec.ego, ref.ego)


def test_bad_input_exit_2_and_no_output(tmp_path, capsys):
    out = tmp_path / "bag"
    args = [
        "simulate", "motion", "--duration", "1", "--max-speed", "0.5", "--taps", "0",
        "--out", str(out), "--quiet",
    ]  # fmt: skip
    # the console script itself: one-line error, exit status 2
    res = subprocess.run(
        [sys.executable, "-m", "egovib_ros.cli", *args, "--effects", "wobble=1"],
        capture_output=True,
        text=True,
    )
    assert (
        res.returncode == 2 and "wobble" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    )
    bad = tmp_path / "bad.yaml"
    bad.write_text("controller_tau: 0.1\n")
    for extra, needle in (
        (["--params", str(tmp_path / "missing.yaml")], "missing.yaml"),
        (["--params", str(bad)], "controller_tau"),
        (["--max-speed", "2"], "max-speed"),
    ):
        assert main(args + extra) == 2
        err = capsys.readouterr().err
        assert needle in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    out.mkdir()
    assert main(args) == 2 and "already exists" in capsys.readouterr().err
