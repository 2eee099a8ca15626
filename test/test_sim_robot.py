"""`egovib simulate robot`: any robot profile simulated, then calibrated and denoised."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from egovib_ros.bag import bag_topics, iter_recording, read_recording
from egovib_ros.cli import main
from egovib_ros.errors import ConfigError
from egovib_ros.robot import RobotProfile, load_profile
from egovib_ros.sim.robot import (
    CONTROLLER_TAU_S,
    GRAVITY_MS2,
    CommandedRobot,
    RobotSimulator,
    SmoothMotion,
    SweepSchedule,
    robot_slices,
    sweep_cell_count,
)

ARM = """\
schema: egovib.robot/1
name: arm3
sensor:
  topic: /arm/imu
  field: linear_acceleration
  rate_hz: 2000
  range: 78.5
joints:
  topic: /joint_states
  names: [shoulder, elbow, gripper]
  max_speed: [2.0, 3.0, 0.05]
  bidirectional: [true, true, false]
  steps: 10
processing:
  block_length: 64
  hop: 32
  band_hz: [100, 900]
"""


@pytest.fixture(scope="module")
def arm_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("profile") / "arm3.yaml"
    path.write_text(ARM)
    return path


@pytest.fixture(scope="module")
def arm(arm_path) -> RobotProfile:
    return load_profile(arm_path)


def _run(*argv) -> int:
    return main([str(a) for a in argv])


def _concat(pieces, name):
    return np.concatenate([getattr(p, name) for p in pieces])


def test_any_cut_of_a_run_gives_the_same_samples_and_seeds_decide(arm):
    """Streaming: one step or many of any size give the same floats; the seed alone decides."""
    n = 9000

    def run(seed, cuts):
        sim = RobotSimulator(arm, seed=seed, tap_rate_hz=2.0, joint_rate_hz=500.0)
        motion = SmoothMotion(arm, 0.8, sim.rng["motion"])
        bounds = np.concatenate([[0], np.sort(cuts), [n]]).astype(int)
        pieces = [sim.step(motion.next(b - a)) for a, b in zip(bounds[:-1], bounds[1:])]
        return pieces, sim.tap_onsets_ns

    whole, taps = run(3, [])
    rng = np.random.default_rng(0)
    cut, cut_taps = run(3, rng.choice(np.arange(1, n), 40, replace=False))
    assert taps == cut_taps and len(taps) >= 5
    for name in (
        "sensor_stamps_ns",
        "sensor",
        "contact",
        "ego",
        "joint_stamps_ns",
        "joint_velocity",
        "joint_position",
    ):
        np.testing.assert_array_equal(_concat(whole, name), _concat(cut, name), err_msg=name)
    other, other_taps = run(4, [])
    assert not np.array_equal(_concat(other, "sensor"), _concat(whole, "sensor"))
    assert other_taps != taps
    # same profile, another seed: the same robot (build), other motion and noise
    assert np.array_equal(RobotSimulator(arm, seed=4).build.idle, RobotSimulator(arm).build.idle)

    stamps = _concat(whole, "sensor_stamps_ns")
    steps = np.diff(stamps)
    assert stamps[0] == 1_000_000_000 and steps.min() >= 0.69 * 5e5 and steps.max() <= 1.31 * 5e5
    assert steps.std() > 0.1 * 5e5  # jittered, not uniform
    velocity = _concat(whole, "joint_velocity")
    assert len(velocity) == n // 4  # 500 Hz of a 2 kHz sensor
    assert np.all(np.abs(velocity[:, :2]) <= 1.01 * np.array([0.8 * 2.0, 0.8 * 3.0]))
    assert velocity[:, 2].min() >= 0.0 and velocity[:, 2].max() <= 0.8 * 0.05 * 1.01


def test_gravity_on_z_for_an_accelerometer_none_for_a_gyro(arm):
    gyro = RobotProfile(
        **{
            **{f: getattr(arm, f) for f in arm.__dataclass_fields__},
            "sensor_field": "angular_velocity",
        }
    )
    for profile, z in ((arm, GRAVITY_MS2), (gyro, 0.0)):
        pieces, _, _ = robot_slices(profile, mode="motion", duration_s=3.0, seed=1)
        accel = _concat(list(pieces), "sensor")
        assert abs(accel[:, 2].mean() - z) < 0.05 and np.all(np.abs(accel[:, :2].mean(0)) < 0.05)


def test_sweep_dwells_on_the_grid_cells(arm):
    schedule = SweepSchedule(arm, "superposition", dwell_s=0.3, settle_s=0.1)
    assert len(schedule.velocities) == sweep_cell_count(arm, "superposition") == 1 + 20 + 20 + 10
    velocity = schedule.next(schedule.total)
    grid = arm.grid()
    dwell_mid = np.arange(len(schedule.velocities)) * schedule.per_cell + schedule.settle + 300
    held = velocity[dwell_mid]
    for j, g in enumerate(grid):
        np.testing.assert_allclose(np.unique(held[:, j]), g, atol=1e-12)
    assert np.all((held != 0).sum(axis=1) <= 1)  # at most one joint moving
    assert velocity[:, 2].min() >= 0  # one-way gripper: 0..max
    # cosine ramps between cells, no jumps
    largest = np.abs(np.diff(np.vstack([np.zeros(3), schedule.velocities]), axis=0)).max(axis=0)
    steepest = largest * np.pi / (2 * schedule.settle)
    assert np.all(np.abs(np.diff(velocity, axis=0)).max(axis=0) <= 1.0001 * steepest)
    full = SweepSchedule(
        RobotProfile(**{**{f: getattr(arm, f) for f in arm.__dataclass_fields__}, "steps": 2}),
        "full",
        dwell_s=0.1,
        settle_s=0.0,
    )
    assert len(full.velocities) == 5 * 5 * 3 == len(np.unique(full.velocities, axis=0))
    eight = RobotProfile(
        **{
            **{f: getattr(arm, f) for f in arm.__dataclass_fields__},
            "joint_names": tuple(f"j{k}" for k in range(8)),
            "max_speed": (1.0,) * 8,
            "bidirectional": (True,) * 8,
        }
    )
    with pytest.raises(ConfigError, match="superposition grid \\(161 cells\\)"):
        SweepSchedule(eight, "full", dwell_s=1.0, settle_s=0.5)
    assert len(SweepSchedule(eight, "superposition", dwell_s=0.01, settle_s=0.0).velocities) == 161


def test_commanded_robot_follows_commands_within_the_joints_ranges_in_any_cut(arm):
    """Live (sim_robot): a held command reached through the 50 ms controller, limited to
    each joint's range; the same samples whatever the steps, for commands given at the
    same samples; the stamps start at start_ns."""
    commands = {0: [1.0, -2.0, 0.03], 3000: [-5.0, 1.0, -0.01], 5000: [0.0, 0.0, 0.05]}

    def run(cuts):
        robot = CommandedRobot(arm, seed=5, tap_rate_hz=1.0, start_ns=7_000_000_000)
        bounds = np.unique(np.concatenate([[0, 8000], cuts, list(commands)]).astype(int))
        within, pieces = [], []
        for a, b in zip(bounds[:-1], bounds[1:]):
            if a in commands:
                within.append(robot.set_command(commands[a]))
            pieces.append(robot.step(b - a))
        return robot, pieces, within

    robot, whole, within = run([])
    assert within == [True, False, True]  # -5 beyond the shoulder's 2, -0.01 a one-way joint
    np.testing.assert_array_equal(robot.command, [0.0, 0.0, 0.05])
    _, cut, _ = run(np.random.default_rng(1).choice(np.arange(1, 8000), 30, replace=False))
    for name in ("sensor_stamps_ns", "sensor", "contact", "joint_stamps_ns", "joint_velocity"):
        np.testing.assert_array_equal(_concat(whole, name), _concat(cut, name), err_msg=name)
    assert _concat(whole, "sensor_stamps_ns")[0] == 7_000_000_000
    # the true velocity (no measurement noise): a first-order lag to the held command
    velocity = robot.velocity
    np.testing.assert_allclose(velocity, [0.0, 0.0, 0.05], atol=1e-3)
    measured = _concat(whole, "joint_velocity")  # at 1 kHz, every other sample
    settled = int(4 * CONTROLLER_TAU_S * 1000)  # 98 % of the step after 4 time constants
    np.testing.assert_allclose(measured[1500 - 1], [1.0, -2.0, 0.03], atol=0.03)
    np.testing.assert_allclose(measured[1500 + settled], [-2.0, 1.0, 0.0], atol=0.1)
    assert measured[:, 2].min() >= 0.0 and np.abs(measured[:, 0]).max() <= 2.0 + 0.02
    with pytest.raises(ConfigError, match="3 finite velocities"):
        robot.set_command([1.0, np.nan, 0.0])


def test_samples_due_keep_jittered_stamps_on_the_clock(arm):
    """Counted from the last stamp, the stamps (+-30 % jitter per step, a random walk over
    the samples) stay near the clock they are due by, however long the run: within 5
    periods (2.5 ms at 2 kHz) at sim_robot's 10 ms ticks; within the walk of one tick at
    1 s ticks for 10 minutes (counted from the start, they would have wandered ~190
    periods)."""
    start = 5_000_000_000
    period = 1e9 / arm.rate_hz
    robot = CommandedRobot(arm, seed=2, start_ns=start)
    assert robot.samples_due(start - 1) == 0 and robot.samples_due(start) == 1

    def worst(tick_ns: int, ticks: int) -> float:
        now, most = int(robot.sim.last_stamp_ns), 0.0
        for _ in range(ticks):
            now += tick_ns
            piece = robot.step(robot.samples_due(now))
            most = max(most, abs(now - int(piece.sensor_stamps_ns[-1])) / period)
        return most

    assert worst(10_000_000, 2000) < 5.0  # 20 s; one tick's walk: 0.8 periods rms
    assert worst(1_000_000_000, 600) < 40.0  # 10 min; one tick's walk: 7.7 periods rms


def _in_band_rms(profile, values, keep):
    sos = signal.butter(4, profile.band_hz, btype="bandpass", fs=profile.rate_hz, output="sos")
    band = signal.sosfiltfilt(sos, values.sum(axis=1))
    return float(np.sqrt(np.mean(band[keep] ** 2)))


def test_motion_and_sweep_bags_calibrate_denoise_and_reduce_noise(arm, arm_path, tmp_path):
    sweep, motion, test = tmp_path / "sweep", tmp_path / "motion", tmp_path / "test"
    truth = tmp_path / "test.truth.json"
    common = ("--robot", arm_path, "--quiet")
    assert _run("simulate", "robot", *common, "--mode", "sweep", "--dwell", "0.5",
                "--settle", "0.2", "--out", sweep, "--seed", "1") == 0  # fmt: skip
    assert (
        _run("simulate", "robot", *common, "--duration", "20", "--out", motion, "--seed", "2") == 0
    )
    assert _run("simulate", "robot", *common, "--duration", "6", "--taps", "1", "--out", test,
                "--seed", "3", "--truth", truth) == 0  # fmt: skip
    assert bag_topics(test) == {
        "/arm/imu": ("sensor_msgs/msg/Imu", 12000),
        "/arm/contact": ("sensor_msgs/msg/Imu", 12000),
        "/arm/ego": ("sensor_msgs/msg/Imu", 12000),
        "/joint_states": ("sensor_msgs/msg/JointState", 6000),
    }
    reductions = {}
    for name, bag in (("sweep", sweep), ("motion", motion)):
        model = tmp_path / f"{name}.npz"
        assert _run("calibrate", bag, "--robot", arm_path, "--out", model, "--quiet") == 0
        denoised = tmp_path / f"{name}.denoised"
        assert _run("denoise", test, "--model", model, "--out", denoised, "--quiet") == 0
        rec = read_recording(denoised, profile=arm)
        assert np.array_equal(rec.denoised_stamps_ns, rec.sensor_stamps_ns)
        # drop-in output: gravity kept
        assert abs(rec.denoised[:, 2].mean() - GRAVITY_MS2) < 0.05
        quiet = signal.convolve(np.abs(rec.contact).sum(1) > 0, np.ones(200), mode="same") == 0
        quiet[:2000] = quiet[-2000:] = False  # leave the filters' edges out
        raw = _in_band_rms(arm, rec.sensor, quiet)
        cleaned = _in_band_rms(arm, rec.denoised, quiet)
        reductions[name] = 20 * np.log10(raw / cleaned)
    # measured: sweep 24.9 dB, 20 s of free motion 19.9 dB (in-band, away from the taps, on
    # 6 s; 40 s and 12 s gave 26.1 and 21.5 dB)
    assert reductions["sweep"] > 15 and reductions["motion"] > 8, reductions


def test_truth_onsets_are_where_the_contact_topic_starts(arm, arm_path, tmp_path):
    out, truth = tmp_path / "taps", tmp_path / "taps.json"
    assert _run("simulate", "robot", "--robot", arm_path, "--duration", "20", "--taps", "2",
                "--seed", "5", "--out", out, "--truth", truth, "--quiet") == 0  # fmt: skip
    data = json.loads(truth.read_text())
    assert data["seed"] == 5 and data["effects"] == {}
    pieces = list(iter_recording(out, profile=arm))
    stamps, contact = _concat(pieces, "sensor_stamps_ns"), _concat(pieces, "contact")
    active = np.abs(contact).sum(axis=1) > 0
    # a burst rises from zero at its onset (as the PR2 simulator's): the onset is the sample
    # just before the first non-zero one
    starts = np.flatnonzero(active & ~np.r_[False, active[:-1]])
    assert data["tap_onsets_ns"] == stamps[starts - 1].tolist()
    assert 25 <= len(starts) <= 55  # 2 per second, Poisson with a dead time


def test_bad_options_are_one_line_exit_2(arm_path, tmp_path, capsys):
    out = tmp_path / "bag"
    assert _run("simulate", "robot", "--robot", arm_path, "--mode", "sweep", "--duration", "3",
                "--out", out) == 2  # fmt: skip
    assert "--duration: not an option of --mode sweep" in capsys.readouterr().err
    assert _run("simulate", "robot", "--robot", tmp_path / "none.yaml", "--out", out) == 2
    err = capsys.readouterr().err.strip()
    assert "none.yaml: no such robot profile" in err and len(err.splitlines()) == 1
    assert _run("simulate", "robot", "--robot", arm_path, "--taps", "50", "--out", out) == 2
    assert "at most 6.67 taps per second" in capsys.readouterr().err
    assert not out.exists()


def test_console_script_writes_a_bag(arm_path, tmp_path):
    out = tmp_path / "bag"
    egovib = [str(Path(sys.executable).parent / "egovib")]  # the console script
    done = subprocess.run(
        egovib
        + ["simulate", "robot", "--robot", str(arm_path), "--duration", "1", "--out", str(out)],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    assert "wrote" in done.stdout and bag_topics(out)["/arm/imu"][1] == 2000
