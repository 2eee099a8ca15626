"""egovib_research.thirdhand, the third generator of the gap validation: a valid, reproducible
Recording of the PR2 hand; every form of every effect changes what it says and nothing else;
it shares no code with the simulator or the alternate reality; its command writes a bag."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import numpy as np
import pytest

import egovib_research.thirdhand as third
from egovib_research.thirdhand import FORMS, simulate_third_motion
from egovib_research.thirdhand.__main__ import main
from egovib_ros.bag import read_recording

DURATION = 6.0


def run(effects=None, forms=None, seed=3):
    return simulate_third_motion(
        duration_s=DURATION, effects=effects or {}, forms=forms, seed=seed, tap_rate_hz=1.0
    )


def test_a_valid_reproducible_recording_of_the_pr2_hand():
    rec, truth = run()
    again, _ = run()
    np.testing.assert_array_equal(rec.sensor, again.sensor)
    assert rec.joint_names == ("r_wrist_roll_joint", "r_gripper_joint")
    n = len(rec.sensor_stamps_ns)
    assert n == int(DURATION * 3000) and rec.sensor.shape == (n, 3)
    assert np.all(np.diff(rec.sensor_stamps_ns) > 0) and np.all(np.diff(rec.joint_stamps_ns) > 0)
    assert len(rec.joint_stamps_ns) == pytest.approx(DURATION * 1000, abs=2)
    # within the sensor's range and its 10-bit steps; the gripper inside its travel
    step = 2 * 78.5 / 2**10
    assert np.abs(rec.sensor).max() <= 78.5
    np.testing.assert_allclose(rec.sensor / step, np.round(rec.sensor / step), atol=1e-9)
    assert rec.joint_position[:, 1].min() >= 0.0 and rec.joint_position[:, 1].max() <= 0.086
    assert np.abs(rec.joint_velocity).max(axis=0).tolist() <= [3.1, 0.045]
    # the ground truth adds up to what the sensor holds (but for gravity, noise, steps)
    assert truth["tap_onsets_ns"] and rec.contact.shape == rec.ego.shape == (n, 3)
    assert np.std(rec.ego) > 0.2


@pytest.mark.parametrize("effect,form", [(e, f) for e, fs in FORMS.items() for f in fs])
def test_each_form_changes_only_what_it_says(effect, form):
    strength = 0.03 if effect == "timing" else 2.0
    base, _ = run()
    rec, truth = run({effect: strength}, {effect: form})
    assert truth["effects"] == {effect: strength} and truth["forms"] == {effect: form}
    np.testing.assert_array_equal(rec.contact, base.contact)
    if effect == "timing":
        # the joint states only: the vibration is the same
        np.testing.assert_array_equal(rec.sensor, base.sensor)
        if form == "polled":
            # every 8 ms, each the last reading (0-8 ms old), stamped 30 ms late
            assert np.allclose(np.diff(rec.joint_stamps_ns), 8e6, atol=1)
            assert len(rec.joint_stamps_ns) == pytest.approx(DURATION / 0.008, abs=1)
            first = (rec.joint_stamps_ns[0] - base.joint_stamps_ns[0]) / 1e9
            assert first == pytest.approx(0.008 + 0.03)
        else:
            np.testing.assert_array_equal(rec.joint_position, base.joint_position)
            shift = (rec.joint_stamps_ns - base.joint_stamps_ns) / 1e9
            assert np.allclose(shift, 0.03)
    else:
        np.testing.assert_array_equal(rec.joint_position, base.joint_position)
        np.testing.assert_array_equal(rec.joint_stamps_ns, base.joint_stamps_ns)
        assert not np.allclose(rec.ego, base.ego)


def test_unknown_effects_and_forms_are_refused():
    with pytest.raises(ValueError, match="unknown effect"):
        run({"friction": 1.0})
    with pytest.raises(ValueError, match="unknown form"):
        run({"coupling": 1.0}, {"coupling": "intermod"})


def test_shares_no_code_with_the_other_generators():
    """Written from the effect vocabulary alone: nothing of the simulator, the alternate
    reality or the project's constants is imported."""
    for path in Path(third.__file__).parent.glob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            for name in names:
                assert not name.startswith(("egovib_ros.sim", "egovib_research.altreality"))
                assert name.split(".")[0] in {
                    "__future__", "numpy", "scipy", "argparse", "json", "sys",
                    "egovib_ros", "egovib_research",
                }, (path.name, name)  # fmt: skip
                if name.startswith("egovib_ros"):
                    assert name in {"egovib_ros.bag.recording", "egovib_ros.errors"}, name


def test_the_command_writes_a_bag_and_its_truth(tmp_path, capsys):
    out, truth = tmp_path / "bag", tmp_path / "truth.json"
    args = ["--duration", "2", "--effects", "coupling=1.5", "--forms", "coupling=together"]
    assert main(args + ["--seed", "4", "--out", str(out), "--truth", str(truth)]) == 0
    rec = read_recording(out)
    assert len(rec.sensor_stamps_ns) == 6000 and rec.contact is not None
    assert json.loads(truth.read_text())["forms"] == {"coupling": "together"}
    assert main(["--effects", "wobble=1", "--out", str(tmp_path / "x")]) == 2
    assert "--effects: expected NAME=VALUE" in capsys.readouterr().err
