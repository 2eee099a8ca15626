"""A real colcon build of the package installs every node where `ros2 run egovib_ros <name>` looks."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
NODES = ("sim_hand", "sweep_driver", "calibrator", "denoiser", "bag_recorder", "bag_player")


def test_colcon_build_installs_every_node(tmp_path):
    result = subprocess.run(
        [str(BIN / "colcon"), "--log-base", str(tmp_path / "log"), "build", "--base-paths", str(REPO),
         "--build-base", str(tmp_path / "build"), "--install-base", str(tmp_path / "install")],
        cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Finished <<< egovib_ros" in result.stdout

    prefix = tmp_path / "install" / "egovib_ros"
    lib = prefix / "lib" / "egovib_ros"
    for name in NODES + ("egovib",):
        script = lib / name
        assert script.is_file() and os.access(script, os.X_OK), f"missing {script}"
    share = prefix / "share" / "egovib_ros"
    assert (share / "package.xml").is_file()
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "egovib_ros").is_file()
    for name in ("sim_hand", "sweep_driver", "calibrator", "denoiser", "bag_recorder", "bag_player"):
        assert (share / "config" / f"{name}.yaml").is_file()

    # The installed node runs, and bad input is a one-line error naming the file, exit status 2.
    missing = tmp_path / "no_such_model.npz"
    run = subprocess.run([str(lib / "denoiser"), "--ros-args", "-p", f"model:={missing}"],
                         capture_output=True, text=True, timeout=60,
                         env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"))
    assert run.returncode == 2, run.stdout + run.stderr
    errors = [line for line in run.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and str(missing) in errors[0], run.stderr
