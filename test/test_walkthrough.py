"""README's "your robot in five commands", as a user runs them: the console commands of
the venv, in a fresh directory, on the example arm profile (config/robots/example_arm.yaml):
profile -> simulate robot -> calibrate -> model show -> denoise -> detect."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from egovib_ros.bag import read_recording
from egovib_ros.robot import load_profile

EGOVIB = str(Path(sys.executable).parent / "egovib")


def egovib(*args, cwd: Path) -> str:
    done = subprocess.run(
        [EGOVIB, *map(str, args)], cwd=cwd, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, (args, done.stderr)
    return done.stderr


def test_your_robot_in_five_commands(tmp_path):
    robot = "example_arm"
    egovib("simulate", "robot", "--robot", robot, "--mode", "sweep", "--grid", "superposition",
           "--dwell", "1.5", "--out", "arm_sweep", "--quiet", cwd=tmp_path)  # fmt: skip
    egovib("simulate", "robot", "--robot", robot, "--duration", "20", "--taps", "1",
           "--seed", "2", "--out", "arm_run", "--truth", "arm_run.truth.json", "--quiet",
           cwd=tmp_path)  # fmt: skip
    coverage = egovib("calibrate", "arm_sweep", "--robot", robot, "--out", "arm.npz",
                      cwd=tmp_path)  # fmt: skip
    assert "coverage:" in coverage
    # the README's sweep is long enough for every default (62 s): calibrate warns of nothing
    # (its 46 s once warned that the detector's thresholds rest on too little data)
    assert "warning" not in coverage.lower(), coverage
    egovib("model", "show", "arm.npz", "--out", "arm_model", "--bag", "arm_run", "--quiet",
           cwd=tmp_path)  # fmt: skip
    assert (tmp_path / "arm_model" / "coverage.png").is_file()
    assert "measured" in (tmp_path / "arm_model" / "summary.md").read_text()
    egovib("denoise", "arm_run", "--model", "arm.npz", "--out", "arm_denoised", "--quiet",
           cwd=tmp_path)  # fmt: skip
    egovib("detect", "arm_run", "--model", "arm.npz", "--out", "events.json", cwd=tmp_path)

    # the denoised topic is a drop-in Imu: gravity kept, one message per raw sample
    profile = load_profile(robot)
    out = read_recording(tmp_path / "arm_denoised", profile=profile)
    np.testing.assert_array_equal(out.denoised_stamps_ns, out.sensor_stamps_ns)
    assert abs(out.denoised[:, 2].mean() - out.sensor[:, 2].mean()) < 0.05
    assert out.sensor[:, 2].mean() > 9.0
    # events: scored against the simulator's truth
    events = json.loads((tmp_path / "events.json").read_text())
    truth = json.loads((tmp_path / "arm_run.truth.json").read_text())
    assert events["scores"]["n_taps"] == len(truth["tap_onsets_ns"]) > 10
    assert events["scores"]["f1"] > 0.8, events["scores"]
