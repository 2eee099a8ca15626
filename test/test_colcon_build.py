"""A real colcon build of the package installs every node where `ros2 run egovib_ros <name>` looks,
and its data (parameter files, robot profiles, launch files) where the installed code finds them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from egovib_ros.nodes import NODES

pytestmark = pytest.mark.nodes  # the node suite: `pytest -m nodes`

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def test_colcon_build_installs_every_node(tmp_path):
    command = [
        str(BIN / "colcon"), "--log-base", str(tmp_path / "log"), "build",
        "--base-paths", str(REPO), "--build-base", str(tmp_path / "build"),
        "--install-base", str(tmp_path / "install"),
    ]  # fmt: skip
    result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Finished <<< egovib_ros" in result.stdout

    prefix = tmp_path / "install" / "egovib_ros"
    lib = prefix / "lib" / "egovib_ros"
    for name in NODES + ("egovib",):
        script = lib / name
        assert script.is_file() and os.access(script, os.X_OK), f"missing {script}"
    share = prefix / "share" / "egovib_ros"
    assert (share / "package.xml").is_file()
    assert (
        prefix / "share" / "ament_index" / "resource_index" / "packages" / "egovib_ros"
    ).is_file()
    for name in (*NODES, "sim"):
        assert (share / "config" / f"{name}.yaml").is_file()
    for source in (
        sorted((REPO / "config" / "robots").glob("*.yaml"))
        + sorted((REPO / "launch").glob("*.py"))
        + [REPO / "config" / "fastdds_profiles.xml"]
    ):
        installed = share / source.relative_to(REPO)
        assert installed.is_file() and installed.read_text() == source.read_text(), (
            f"missing {installed}"
        )
    assert {p.name for p in (share / "launch").glob("*.launch.py")} == {
        "calibrate.launch.py",
        "denoise.launch.py",
    }

    # The installed package (not the source tree) finds its data in the installed share directory:
    # sim_hand reads config/sim.yaml from there (no silent fall-back to built-in values).
    site = next((prefix / "lib").glob("python3*/site-packages"))
    env = dict(
        os.environ,
        PYTHONPATH=str(site),
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        PYTHONUNBUFFERED="1",
    )
    env.pop("AMENT_PREFIX_PATH", None)
    where = subprocess.run(
        [
            sys.executable,
            "-c",
            "import egovib_ros.sim.params as p, egovib_ros.robot as r; "
            "print(p.__file__); print(p.default_config_path()); print(r.load_profile().source)",
        ],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=60,
    )
    module, sim_yaml, robot = where.stdout.split()
    assert module.startswith(str(site)), where.stdout
    assert sim_yaml == str(share / "config" / "sim.yaml") and robot.startswith(
        str(share / "config" / "robots")
    )
    with open(tmp_path / "sim_hand.log", "w") as log:
        sim = subprocess.Popen(
            [str(lib / "sim_hand")], stdout=log, stderr=subprocess.STDOUT, env=env, cwd=tmp_path
        )
    try:
        deadline = time.monotonic() + 60  # a fresh install compiles its modules first
        while "simulator parameters from" not in (tmp_path / "sim_hand.log").read_text():
            assert sim.poll() is None and time.monotonic() < deadline, (
                tmp_path / "sim_hand.log"
            ).read_text()
            time.sleep(0.1)
    finally:
        sim.send_signal(signal.SIGINT)
        sim.wait(60)
    assert (
        f"simulator parameters from {share / 'config' / 'sim.yaml'}"
        in (tmp_path / "sim_hand.log").read_text()
    )

    # The installed node runs, and bad input is a one-line error naming the file, exit status 2.
    missing = tmp_path / "no_such_model.npz"
    run = subprocess.run(
        [str(lib / "denoiser"), "--ros-args", "-p", f"model:={missing}"],
        capture_output=True,
        text=True,
        timeout=60,
        env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"),
    )
    assert run.returncode == 2, run.stdout + run.stderr
    errors = [line for line in run.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and str(missing) in errors[0], run.stderr
