"""Small simulated bags and the `egovib` command, for the tests of the offline commands
(test_cli_*) and of the library behind them (test_bag_*).

The bags themselves are session fixtures in conftest.py (`sim_bags`, `sim_bags_model`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import subprocess
import sys
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import Reader

from egovib_ros import cli
from egovib_ros.bag import BagWriter, write_recording
from egovib_ros.bag.codec import encode_imu_batch, rosbags_joint_state, typestore
from egovib_ros.sim import simulate_motion, simulate_sweep


def egovib(*args, cwd=None) -> subprocess.CompletedProcess:
    """`egovib ARGS` through the console script's entry point (cli.main) in this process:
    the command's whole path, without a new interpreter's ~3 s of imports per call.
    test_walkthrough and test_faults run the installed console command as a process."""
    argv = [str(a) for a in args]
    out, err = io.StringIO(), io.StringIO()
    with (
        contextlib.chdir(cwd or Path.cwd()),
        contextlib.redirect_stdout(out),
        contextlib.redirect_stderr(err),
    ):
        code = cli.main(argv)
    return subprocess.CompletedProcess(["egovib", *argv], code, out.getvalue(), err.getvalue())


def egovib_process(*args, cwd=None) -> subprocess.CompletedProcess:
    """`egovib ARGS` in a process of its own: what it logs, once per process, on stderr."""
    command = [sys.executable, "-m", "egovib_ros.cli", *map(str, args)]
    return subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=cwd)


def sim_sweep():
    """The superposition calibration sweep of `write_sim_bags` (no ground truth: a calibration
    bag has none). Test modules that calibrate a sweep of their own calibrate this one: the
    harmonic fit of every calibration (conftest.py `harmonic_fits_once`, ~8 s) is then done
    once per test session for all of them."""
    sweep, _ = simulate_sweep(grid="superposition", dwell_s=1.0, settle_s=0.3, seed=3)
    return dataclasses.replace(sweep, contact=None, ego=None)


def write_sim_bags(root: Path) -> Path:
    """root/sweep (a superposition calibration sweep) and root/motion (4 s, taps, truth)."""
    write_recording(root / "sweep", sim_sweep())
    motion, _ = simulate_motion(duration_s=4.0, max_speed=0.5, tap_rate_hz=1.0, seed=4)
    write_recording(root / "motion", motion)
    return root


def topic_messages(bag: Path, topic: str) -> list[tuple[int, bytes]]:
    """(log time, serialised message) of one topic, read by rosbags."""
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [(t, bytes(d)) for _, t, d in reader.messages(connections=conns)]


def write_robot_bag(
    path,
    p,
    data,
    *,
    extra_joints=("base", "arm_1", "arm_2", "lift", "pan", "tilt", "grip_l", "grip_r", "caster"),
):
    """The sensor topic (gyro) and a JointState carrying the profile's joints among others,
    in an order that changes from message to message."""
    ts = typestore()
    rng = np.random.default_rng(5)
    names = list(p.joint_names) + list(extra_joints)
    position = np.cumsum(data["velocity"], axis=0) * 1e-3
    with BagWriter(path, compress="zstd") as bag:
        bag.add_topic(p.sensor_topic, "sensor_msgs/msg/Imu")
        bag.add_topic(p.joints_topic, "sensor_msgs/msg/JointState")
        bag.write_batch(
            p.sensor_topic,
            data["t_acc"],
            encode_imu_batch(data["t_acc"], data["accel"], "imu_link", p.sensor_field),
        )
        for k, stamp in enumerate(data["t_joint"].tolist()):
            order = rng.permutation(len(names))
            pos = np.concatenate([position[k], np.zeros(len(extra_joints))])[order]
            vel = np.concatenate([data["velocity"][k], np.ones(len(extra_joints))])[order]
            msg = rosbags_joint_state(stamp, [names[i] for i in order], pos, vel)
            bag.write(
                p.joints_topic, stamp, bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
            )
