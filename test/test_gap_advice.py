"""gap.advice: the report's first lines, from diagnoses of synthetic block tables with a
known effect (test/gaptables.py), and the lag advice applied with the core."""

from __future__ import annotations

import dataclasses
import shlex
import subprocess

import numpy as np
import pytest
from gaptables import diagnosed

from egovib_ros.gap.advice import action, advise, commands, first_lines
from egovib_ros.robot import load_profile, robot_option


@pytest.fixture(scope="module")
def diagnoses() -> dict:
    """One diagnosis per effect whose advice names a setting, and one without an effect
    (shared with test_gap_diagnose and test_gap_writeback: gaptables.diagnosed)."""
    cases = {"none": ("none", 0.0), "timing": ("timing", 0.05), "drift": ("drift", 0.5)}
    cases["position"] = ("position", 0.4)
    return {name: diagnosed(e, s, seed=5) for name, (e, s) in cases.items()}


def test_a_lag_is_advised_as_the_joint_lag_that_undoes_it(diagnoses):
    diag = diagnoses["timing"]
    assert diag.verdict == "timing"
    text, settings = action(diag)
    p = diag.models["timing"].parameters
    offset = p["lag_s"] - p.get("reference_lag_s", 0.0)
    # joint states stamped 50 ms after the vibration: the vibration leads them, joint lag -50 ms
    assert settings["joint_lag_s"] == pytest.approx(-offset, abs=1e-4)
    assert settings["joint_lag_s"] == pytest.approx(-0.05, abs=0.005)
    lag = f"{settings['joint_lag_s']:g}"
    assert "the vibration leads the joint states by" in text
    # the exact flags and parameters, one sign everywhere
    assert f"`egovib denoise --joint-lag {lag}`" in text and f"`joint_lag:={lag}`" in text
    assert f"`egovib calibrate --joint-lag {lag}`" in text


def test_the_sign_of_the_lag_names_lead_or_lag(diagnoses):
    diag = diagnoses["timing"]
    model = diag.models["timing"]
    lead = dataclasses.replace(model, parameters={**model.parameters, "lag_s": -0.03})
    text, settings = action(dataclasses.replace(diag, models={**diag.models, "timing": lead}))
    assert "the vibration trails the joint states by 30 ms" in text
    assert settings["joint_lag_s"] == pytest.approx(0.03) and "--joint-lag 0.03`" in text


def test_drift_and_position_name_what_to_change(diagnoses):
    drift_text, drift = action(diagnoses["drift"])
    assert diagnoses["drift"].verdict == "drift"
    assert "recalibrate" in drift_text and drift["level_change_percent"] != 0.0
    assert "`egovib denoise --noise-gain REPORT.json`" in drift_text
    # the fitted level change from the start, for `egovib denoise --noise-gain`
    knots = np.asarray(drift["noise_gain_db"])
    assert knots[0].tolist() == [0.0, 0.0] and np.all(np.diff(knots[:, 0]) > 0)
    pct = 100 * (10 ** (knots[-1, 1] / 20) - 1)
    assert pct == pytest.approx(drift["level_change_percent"], abs=0.5)
    position_text, position = action(diagnoses["position"])
    assert diagnoses["position"].verdict == "position"
    assert position["calibration_grid"] == "free" and position["position_joint"]
    # no option keys a model by position: not advised; an option that exists is
    assert "position as a key" not in position_text
    assert "`egovib calibrate BAG --grid free`" in position_text


def test_a_drift_of_one_joint_names_that_joint(diagnoses):
    """Where one joint's own trend is over twice any other's, the advice names it (its
    change, and the whole vibration's beside it); the level it applies stays the whole's."""
    diag = diagnoses["drift"]
    model = diag.models["drift"]
    shape = {k: v for k, v in model.shape.items() if "joint" not in v}
    x = model.shape["drift:elapsed_time"]["x"]
    for name, end_db in (("wrist_roll", 0.2), ("gripper", 3.0)):
        curve = list(np.linspace(0.0, end_db, len(x)))
        shape[f"drift:{name}"] = {"x": x, "gain_db": curve, "joint": name}
    one = dataclasses.replace(model, shape=shape)
    text, settings = action(dataclasses.replace(diag, models={**diag.models, "drift": one}))
    level = action(diag)[1]
    assert text.startswith("gripper's vibration grows 41 % over")
    assert settings["joint"] == "gripper" and settings["joint_change_percent"] == 41.3
    assert settings["noise_gain_db"] == level["noise_gain_db"]
    shape["drift:wrist_roll"]["gain_db"] = list(np.linspace(0.0, 2.0, len(x)))
    both = dataclasses.replace(model, shape=shape)
    text, settings = action(dataclasses.replace(diag, models={**diag.models, "drift": both}))
    assert text.startswith("vibration grows") and "joint" not in settings


def test_the_commands_apply_every_correction_together():
    settings = {"joint_lag_s": 0.032, "noise_gain_db": [[0.0, 0.0], [10.0, 2.0]]}
    cmds = commands(settings, model="m.npz", bag="run", report="out/report.json")
    assert cmds["denoise"] == (
        "egovib denoise run --model m.npz --out DENOISED --joint-lag 0.032 "
        "--noise-gain out/report.json"
    )
    assert cmds["denoiser_node"] == (
        "denoiser --ros-args -p model:=m.npz -p joint_lag:=0.032 -p noise_gain:=out/report.json"
    )
    both = commands({**settings, "calibration_grid": "full"})
    assert both["calibrate"].startswith(
        "egovib calibrate NEW_RECORDING --grid full --joint-lag 0.032 --out NEW_MODEL.npz"
    )
    assert commands({}) == {}
    # another robot's: calibrate names its profile; every line one a shell runs as it is
    # (the note on NEW_RECORDING was once in parentheses: a syntax error, and no --robot)
    arm = commands({**settings, "calibration_grid": "free"}, robot="example_arm")
    assert arm["calibrate"].startswith("egovib calibrate NEW_RECORDING --robot example_arm ")
    for line in arm.values():
        assert subprocess.run(["bash", "-n", "-c", line], capture_output=True).returncode == 0
    assert robot_option(load_profile("example_arm")) == "example_arm"
    assert robot_option(load_profile(None)) is None  # the PR2 hand: the default
    # a copy of a shipped profile, edited, that kept its name: the user's file, not ours
    edited = dataclasses.replace(load_profile("quadcopter"), sensor_topic="/imu/data_filtered")
    assert robot_option(edited) == "PROFILE.yaml"
    # paths with spaces: one word each, as pasted
    spaced = commands(settings, bag="my runs/run 1", model="my models/m.npz", report="r 1.json")
    for line in spaced.values():
        words = shlex.split(line)
        assert "my runs/run 1" in words or "model:=my models/m.npz" in words, line
    assert shlex.split(spaced["denoise"])[2:5] == ["my runs/run 1", "--model", "my models/m.npz"]


def test_cost_and_unexplained_rest_follow_the_held_out_gaps(diagnoses):
    for name, diag in diagnoses.items():
        advice = advise(diag)
        gaps, floor = diag.gaps, diag.floor
        after = gaps["combined"]  # every effect found, or the baseline
        if diag.verdict == "none":
            assert after == gaps["refit"]
        assert advice["unexplained"]["above_floor_db"] == pytest.approx(after - floor, abs=1e-3)
        share = advice["unexplained"]["share_of_baseline_excess"]
        assert 0.0 <= share <= 1.0 + 1e-9, name
        d = advice["denoiser"]
        assert d["gain_db"] == pytest.approx(
            d["noise_reduction_with_db"] - d["noise_reduction_without_db"], abs=2e-3
        )
        lines = first_lines(advice)
        assert lines[0].startswith("**What to do") and lines[-1].startswith("**Left unexplained")
        # the worth line only where an effect was found
        assert any("What the corrections are worth" in line for line in lines) == (
            diag.verdict != "none"
        )


def test_no_effect_says_whether_the_velocity_model_leaves_much(diagnoses):
    diag = diagnoses["none"]
    assert diag.verdict == "none"
    fits = {**diag.gaps, "sim_as_is": diag.floor + 0.2, "refit": diag.floor + 0.1}
    text, settings = action(dataclasses.replace(diag, gaps=fits))
    assert (text, settings) == (
        "the velocity-only model fits this recording: nothing to change",
        {},
    )
    worse = dataclasses.replace(diag, gaps={**fits, "refit": diag.floor + 1.0})
    assert "1.00 dB above the floor stays unexplained" in action(worse)[0]
    assert np.isfinite(advise(worse)["unexplained"]["above_floor_db"])


def test_a_model_that_misses_the_recordings_motion_is_said_to_need_calibrating_on_it(diagnoses):
    """`none`, but a velocity-only model fitted on the recording is far closer than the
    model (speeds it never held): calibrate on such motion, the command that does it."""
    diag = diagnoses["none"]
    gaps = {**diag.gaps, "sim_as_is": 5.29, "refit": 2.77}
    text, settings = action(dataclasses.replace(diag, gaps=gaps, floor=1.93))
    assert text.startswith(
        "the model misses this recording's motion: a velocity-only model fitted on it comes "
        "2.52 dB closer (5.29 -> 2.77 dB); calibrate on motion like it, without contact; "
        "no effect of the vocabulary explains the rest (0.84 dB above the floor"
    )
    assert settings == {"calibration_grid": "free"}
    assert commands(settings)["calibrate"].startswith("egovib calibrate NEW_RECORDING --grid free")


def test_the_lag_advice_applied_with_the_core_is_scored_like_for_like(caplog):
    """Joint states stamped 50 ms late in the recording denoised, not in the calibration:
    the advised joint_lag (-50 ms) removes more noise; both runs are scored on the same
    samples (the end blocks the lag leaves without joint states are counted, not scored,
    and not warned about)."""
    from egovib_research.experiments.gap_flight import measure_joint_lag
    from egovib_ros.robot import load_profile
    from egovib_ros.sim import simulate_motion

    cal, _ = simulate_motion(duration_s=20.0, max_speed=0.8, seed=3)
    test, _ = simulate_motion(duration_s=20.0, max_speed=0.8, seed=4, effects={"timing": 0.05})
    with caplog.at_level("WARNING", logger="egovib_ros.core"):
        out = measure_joint_lag(cal, test, load_profile(), -0.05, calibration_lag_s=0.0)
    assert not [r for r in caplog.records if "no joint state" in r.getMessage()]
    assert out["with"]["blocks_no_joint_state"] + out["without"]["blocks_no_joint_state"] > 0
    assert 0 < out["scored_samples"] < len(test.sensor)
    assert out["gain_db"] > 0.3, out


@pytest.mark.parametrize("gain_db", [0.8, -0.85])
def test_flags_that_cost_the_users_model_are_said_not_to_apply(gain_db):
    """Measured with the user's model and its default method (measure_advice): a flag that
    lowers held-out noise reduction (the untouched real flight's joint lag with hybrid:
    -0.85 dB) is shown with its measurement and the advice not to apply it with that method."""
    applied = {
        "method": "hybrid",
        "applied_text": "joint lag -0.032 s (fitted on the first 60 %)",
        "noise_reduction_without_db": 20.0,
        "noise_reduction_with_db": 20.0 + gain_db,
        "gain_db": gain_db,
        "heldout": "scored on the last 40 % (40 s), no-contact blocks",
        "recommended": gain_db > 0,
    }
    advice = {
        "effect": "timing",
        "effects": [{"effect": "timing", "action": "set the joint lag"}],
        "action": "set the joint lag",
        "settings": {"joint_lag_s": -0.032},
        "commands": {"denoise": "egovib denoise BAG --model M --out OUT --joint-lag -0.032"},
        "lag_convention": "negative: the joint states lead",
        "denoiser": {
            "noise_reduction_without_db": 1.0,
            "noise_reduction_with_db": 2.0,
            "gain_db": 1.0,
        },  # fmt: skip
        "applied": applied,
        "unexplained": {"above_floor_db": 0.5, "share_of_baseline_excess": 0.2},
    }
    text = "\n".join(first_lines(advice))
    assert ("do not apply them with this method" in text) == (gain_db < 0)
    assert ("not with `hybrid`" in text) == (gain_db < 0)
    assert f"({gain_db:+.2f} dB;" in text and "--joint-lag -0.032" in text


def test_a_drift_too_small_to_measure_is_said_so_and_nothing_is_applied(diagnoses):
    """A significant drift of a tenth of a dB (the shipped flight's hover) is named, but
    neither a recalibration nor a noise-gain curve is advised for it."""
    diag = diagnoses["drift"]
    model = diag.models["drift"]
    x = model.shape["drift:elapsed_time"]["x"]
    tiny = {k: v for k, v in model.shape.items() if "joint" not in v}
    tiny = {k: {**v, "gain_db": list(np.linspace(0.0, -0.1, len(x)))} for k, v in tiny.items()}
    text, settings = action(
        dataclasses.replace(
            diag, models={**diag.models, "drift": dataclasses.replace(model, shape=tiny)}
        )
    )
    assert text.startswith("the vibration's level barely moves (-0.10 dB over")
    assert "nothing to recalibrate for or apply" in text
    assert "noise_gain_db" not in settings and commands(settings) == {}


def test_the_calibrate_commands_in_the_text_name_the_robot(diagnoses):
    """A probe pasted the text's `egovib calibrate BAG --grid free` for a quadcopter model:
    without --robot it reads the PR2 hand's topics. The text names the robot as the commands
    do; the PR2 hand's (the default) stays as it was."""
    diag = diagnoses["position"]
    plain = advise(diag)
    assert "`egovib calibrate BAG --grid free`" in plain["action"]
    arm = advise(diag, paths={"robot": "example_arm"})
    assert "`egovib calibrate BAG --robot example_arm --grid free`" in arm["action"]
    assert arm["effects"][0]["action"] == arm["action"]
    assert advise(diag, paths={"robot": None})["action"] == plain["action"]
