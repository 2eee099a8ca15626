"""`egovib calibrate` on real bag files, as a user runs it: sweeps of the PR2 hand and of any
robot profile, several bags pooled, bad input one line and exit 2.
"""

import dataclasses
import shutil

import bagcorpus
import numpy as np
import robots
from simbags import egovib, egovib_process, write_robot_bag

from egovib_ros.bag import read_recording, write_recording
from egovib_ros.core import NoiseModel
from egovib_ros.gap.simref import own_lag
from egovib_ros.robot import load_profile
from egovib_ros.sim import simulate_sweep


def test_missing_joint_is_one_line_exit_2(tmp_path):
    p = robots.profile(3, rate_hz=1600.0)
    (tmp_path / "robot.yaml").write_text(p.dumps())
    data = robots.recording(p, 2.0, seed=3, joint_rate_hz=400.0)
    renamed = dataclasses.replace(p, joint_names=("joint_0", "joint_1", "other"))
    write_robot_bag(tmp_path / "bag", renamed, data)
    result = egovib(
        "calibrate",
        tmp_path / "bag",
        "--robot",
        tmp_path / "robot.yaml",
        "--out",
        tmp_path / "m.npz",
    )
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0
    assert (
        "joint_2" in result.stderr and "/joint_states" in result.stderr and "bag" in result.stderr
    )
    assert not (tmp_path / "m.npz").exists()


def test_calibrate_pools_several_bags(sim_bags, tmp_path):
    sweep, _ = simulate_sweep(grid="superposition", dwell_s=0.5, settle_s=0.3, seed=8)
    write_recording(
        tmp_path / "more" / "sweep2", dataclasses.replace(sweep, contact=None, ego=None)
    )
    shutil.copytree(sim_bags / "sweep", tmp_path / "more" / "sweep1")
    results = {}
    for name, args in (
        ("one", [tmp_path / "more" / "sweep1"]),
        ("two", [tmp_path / "more" / "sweep2"]),
        ("both", [tmp_path / "more"]),
        ("both_j2", [tmp_path / "more", "--jobs", "2"]),
    ):
        # the paper's table is what pools (the methods are fitted on the first bag alone)
        out = tmp_path / f"{name}.npz"
        result = egovib("calibrate", *args, "--out", out, "--quiet", "--methods", "paper")
        assert result.returncode == 0, result.stderr
        results[name] = NoiseModel.load(out)
    one, two, both = results["one"], results["two"], results["both"]
    assert both.measured == "superposition"
    np.testing.assert_array_equal(both.counts, one.counts + two.counts)
    n1, n2 = one.counts[..., None, None], two.counts[..., None, None]
    pooled = np.divide(
        one.mean * n1 + two.mean * n2, n1 + n2, out=np.zeros_like(one.mean), where=n1 + n2 > 0
    )
    np.testing.assert_allclose(both.mean, pooled, rtol=1e-9, atol=1e-12)
    for name in ("cells", "cell_mean", "cell_std", "cell_counts"):
        np.testing.assert_array_equal(getattr(results["both_j2"], name), getattr(both, name))
    # the joint lag `egovib gap` judges timing against: the simulator's few ms, measured on
    # the first bag as the methods are
    assert abs(own_lag(one)) <= 0.02
    assert own_lag(both) == own_lag(one)


def test_joint_states_without_velocity_or_position_are_named(sim_bags, tmp_path):
    """Neither is usable: one line naming the joint-state topic and the joint."""
    profile = tmp_path / "measured.yaml"
    text = load_profile(None).dumps().replace("velocity: auto", "velocity: measured")
    profile.write_text(text)
    motion = bagcorpus.write_layout(
        sim_bags / "motion", tmp_path / "positions", bagcorpus.Layout("p", velocity=False)
    )
    result = egovib("calibrate", motion, "--robot", profile, "--out", tmp_path / "m.npz")
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert "/joint_states" in lines[0] and "r_wrist_roll_joint" in lines[0], lines[0]
    assert "no velocity" in lines[0] and "auto" in lines[0]


def test_several_bags_one_of_them_bad_names_it_and_writes_nothing(sim_bags, tmp_path):
    """Pooling bags where one is unreadable: each bag's line (the good one's counts), the
    bad one named, exit 2 and no model."""
    shutil.copytree(sim_bags / "sweep", tmp_path / "bad")
    mcap = next((tmp_path / "bad").glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[:100])  # truncated
    result = egovib(
        "calibrate", sim_bags / "sweep", tmp_path / "bad", "--out", tmp_path / "m.npz", "--quiet"
    )
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert any(line.strip().startswith("ok") and "blocks" in line for line in lines), lines
    assert any(line.strip().startswith("FAILED") and "bad" in line for line in lines), lines
    assert "no model written" in lines[-1] and "internal error" not in result.stderr
    assert not (tmp_path / "m.npz").exists()


def test_bags_of_one_name_in_different_directories_pool_into_one_model(sim_bags, tmp_path):
    """Calibration writes one model, so two bags both named 'bag' do not collide."""
    for d in ("day1", "day2"):
        shutil.copytree(sim_bags / "sweep", tmp_path / d / "bag")
    result = egovib(
        "calibrate", tmp_path / "day1" / "bag", tmp_path / "day2" / "bag",
        "--out", tmp_path / "m.npz", "--quiet", "--methods", "paper",
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    one = egovib(
        "calibrate", sim_bags / "sweep", "--out", tmp_path / "one.npz", "--quiet",
        "--methods", "paper",
    )  # fmt: skip
    assert one.returncode == 0, one.stderr
    np.testing.assert_array_equal(
        NoiseModel.load(tmp_path / "m.npz").cell_counts,
        2 * NoiseModel.load(tmp_path / "one.npz").cell_counts,
    )


def test_one_bag_given_twice_is_refused_not_counted_twice(sim_bags, tmp_path):
    shutil.copytree(sim_bags / "sweep", tmp_path / "bags" / "sweep")
    for args in ([tmp_path / "bags", tmp_path / "bags" / "sweep"], [sim_bags / "sweep"] * 2):
        result = egovib("calibrate", *args, "--out", tmp_path / "m.npz", "--quiet")
        assert result.returncode == 2 and "given twice" in result.stderr, result.stderr
        assert not (tmp_path / "m.npz").exists()


def test_quiet_still_says_the_cells_a_sweep_left_without_a_block(sim_bags, tmp_path):
    """--quiet drops the progress and the summary, not the warnings (options.QUIET_HELP): a
    superposition sweep calibrated as a full grid leaves most of that grid to the fill."""
    args = ("calibrate", sim_bags / "sweep", "--grid", "full", "--methods", "paper")
    loud = egovib(*args, "--out", tmp_path / "loud.npz")
    quiet = egovib(*args, "--out", tmp_path / "quiet.npz", "--quiet")
    assert loud.returncode == 0 and quiet.returncode == 0, quiet.stderr
    warning = [line for line in loud.stderr.splitlines() if line.startswith("warning:")]
    assert "of the full grid have no block" in warning[0]
    # ... and the ~20 s sweep's few largest bursts set the detector's thresholds
    seconds = len(read_recording(sim_bags / "sweep", ground_truth=False).sensor) / 3000
    assert f"thresholds come from {seconds:.0f} s of calibration data" in warning[1]
    assert quiet.stderr.splitlines() == warning  # those, and nothing else


def test_a_sweep_cut_by_a_crash_is_said_truncated_once(sim_bags, tmp_path):
    """Given as a relative path, as users type it: the bag's warning once, not again by the
    absolute path the model's fingerprint once opened it by (the console script says each
    message once per run; a second path was a second message)."""
    shutil.copytree(sim_bags / "sweep", tmp_path / "cut")
    (data,) = (tmp_path / "cut").glob("*.mcap")
    data.write_bytes(data.read_bytes()[: data.stat().st_size * 9 // 10])
    run = egovib_process(
        "calibrate", "cut", "--out", "m.npz", "--methods", "paper", "--quiet", cwd=tmp_path
    )
    assert run.returncode == 0, run.stderr
    said = [line for line in run.stderr.splitlines() if "without summary and footer" in line]
    assert len(said) == 1 and said[0].startswith("egovib: WARNING: cut: truncated"), run.stderr


def test_a_run_with_taps_given_as_calibration_data_is_said(
    sim_bags, sim_bags_model, tmp_path, caplog
):
    """calibrate, and detect's --calibration, on a simulated run whose ground truth holds
    taps: a WARNING naming the bag and the taps (their thresholds were once raised above
    the taps silently); the sweep, without that topic, says nothing."""

    def said() -> list[str]:
        return [
            r.getMessage() for r in caplog.records if "calibration data should" in r.getMessage()
        ]

    motion = sim_bags / "motion"
    run = egovib("calibrate", motion, "--out", tmp_path / "m.npz", "--methods", "paper", "--quiet")
    assert run.returncode == 0, run.stderr
    assert len(said()) == 1 and said()[0].startswith(f"{motion}: its ground truth"), said()
    assert int(said()[0].split(" holds ")[1].split()[0]) >= 2  # 4 s of taps at 1 Hz
    caplog.clear()
    run = egovib(
        "detect", motion, "--model", sim_bags_model, "--out", tmp_path / "e.json",
        "--calibration", motion, "--quiet",
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert len(said()) == 1, said()
    caplog.clear()
    sweep = ("calibrate", sim_bags / "sweep", "--methods", "paper", "--quiet")
    assert egovib(*sweep, "--out", tmp_path / "s.npz").returncode == 0
    assert said() == []
