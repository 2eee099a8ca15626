"""The alternate-reality hand: a valid, reproducible Recording, independent of the simulator."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from egovib_research.altreality import (
    EFFECTS,
    HAND_JOINTS,
    AltHand,
    effect_audibility_db,
    simulate_alt_motion,
)

PACKAGE = Path(__file__).resolve().parents[1] / "research" / "egovib_research" / "altreality"


def test_shares_no_code_with_the_simulator():
    """The generator imports only numpy/scipy, its own modules, the Recording container and
    the time base; its command-line writer (__main__.py) also the bag and CLI helpers, never
    the simulator or the PR2 constants."""
    allowed = {
        "numpy",
        "scipy",
        "dataclasses",
        "__future__",
        "egovib_research.altreality",
        "egovib_ros.bag",
        "egovib_ros.core.timebase",
    }
    writer = PACKAGE / "__main__.py"
    tree = ast.parse(writer.read_text())
    imported = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    imported += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert imported and not any(
        m.startswith(("egovib_ros.sim", "egovib_ros.sim.pr2")) for m in imported
    )
    for path in PACKAGE.glob("*.py"):
        if path == writer:
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            else:
                continue
            for name in names:
                assert any(name == a or name.startswith(a + ".") for a in allowed), (
                    f"{path.name} imports {name}"
                )


def test_recording_is_valid_and_reproducible():
    rec, truth = simulate_alt_motion(duration_s=8.0, seed=3, tap_rate_hz=1.0)
    n = len(rec.sensor_stamps_ns)
    assert n == 24000 and rec.sensor.shape == (n, 3) and np.all(np.isfinite(rec.sensor))
    assert np.all(np.diff(rec.sensor_stamps_ns) > 0)
    assert abs(np.median(np.diff(rec.sensor_stamps_ns)) - 1e9 / 3000) < 1
    assert rec.joint_names == HAND_JOINTS
    m = len(rec.joint_stamps_ns)
    assert rec.joint_position.shape == rec.joint_velocity.shape == (m, 2)
    assert 7500 < m < 8000  # 1 kHz minus a few dropped messages
    assert np.all(np.diff(rec.joint_stamps_ns) > 0)
    # The gripper stays inside its travel, the wrist angle is reported wrapped.
    assert rec.joint_position[:, 1].min() >= 0.0 and rec.joint_position[:, 1].max() <= 0.09
    assert np.all(np.abs(rec.joint_position[:, 0]) <= np.pi + 1e-9)
    assert truth["tap_onsets_ns"] and truth["effects"] == {} and truth["reality"] == "alt"
    again, _ = simulate_alt_motion(duration_s=8.0, seed=3, tap_rate_hz=1.0)
    assert np.array_equal(again.sensor, rec.sensor) and np.array_equal(
        again.joint_stamps_ns, rec.joint_stamps_ns
    )
    other, _ = simulate_alt_motion(duration_s=8.0, seed=4, tap_rate_hz=1.0)
    assert not np.array_equal(other.sensor, rec.sensor)


@pytest.mark.parametrize("effect", [e for e in EFFECTS if e != "timing"])
def test_an_effect_changes_only_the_vibration(effect):
    base, _ = simulate_alt_motion(duration_s=10.0, seed=5)
    with_fx, truth = simulate_alt_motion(
        duration_s=10.0, seed=5, effects={effect: 2.0 if effect != "drift" else 0.8}
    )
    assert truth["effects"] == {effect: 2.0 if effect != "drift" else 0.8}
    assert np.array_equal(base.joint_position, with_fx.joint_position)
    assert np.array_equal(base.joint_stamps_ns, with_fx.joint_stamps_ns)
    assert not np.array_equal(base.ego, with_fx.ego)


def test_stick_slip_scale_changes_only_the_friction_impulses():
    base, _ = simulate_alt_motion(duration_s=4.0, seed=5, tap_rate_hz=2.0)
    quiet, _ = simulate_alt_motion(duration_s=4.0, seed=5, tap_rate_hz=2.0, stick_slip=0.0)
    assert np.array_equal(base.contact, quiet.contact)
    assert np.array_equal(base.joint_position, quiet.joint_position)
    # the impulses are a loud part of the in-band vibration (gravity aside)
    band = signal.butter(4, (150.0, 750.0), btype="band", fs=3000.0, output="sos")
    power = [np.mean(signal.sosfilt(band, rec.ego.sum(axis=1)) ** 2) for rec in (quiet, base)]
    assert power[0] < 0.7 * power[1]


def test_timing_shifts_joint_stamps_both_ways():
    base, _ = simulate_alt_motion(duration_s=3.0, seed=2)
    for lag in (0.025, -0.015):
        shifted, _ = simulate_alt_motion(duration_s=3.0, seed=2, effects={"timing": lag})
        assert np.all(shifted.joint_stamps_ns - base.joint_stamps_ns == round(lag * 1e9))
        assert np.array_equal(shifted.sensor, base.sensor)


def test_effects_are_audible_where_they_act():
    for effect in ("position", "coupling", "acceleration"):
        loud = effect_audibility_db(effect, 2.0, duration_s=30.0, seed=3)
        assert loud["active_db"] > 1.0 and loud["active_fraction"] > 0.0, (effect, loud)
    drift = effect_audibility_db("drift", 0.5, duration_s=20.0, seed=3)
    assert abs(drift["overall_db"]) > 1.0


def test_an_unknown_effect_is_refused():
    with pytest.raises(ValueError):
        AltHand(effects={"wobble": 1.0})


def test_written_to_a_bag_that_a_pr2_model_reads(tmp_path, capsys):
    """`python -m egovib_research.altreality` writes a bag with the PR2 topics; the effects go to
    the truth file only; an existing bag is not replaced without --force."""
    import json

    from egovib_research.altreality.__main__ import main
    from egovib_ros.bag import read_recording

    bag, truth = tmp_path / "alt", tmp_path / "alt.truth.json"
    args = ["--duration", "10", "--effects", "coupling=1.5", "--seed", "4", "--taps", "0"]
    args += ["--out", str(bag)]
    assert main(args + ["--truth", str(truth)]) == 0
    rec = read_recording(bag)
    direct, _ = simulate_alt_motion(duration_s=10.0, effects={"coupling": 1.5}, seed=4)
    np.testing.assert_allclose(rec.sensor, direct.sensor, rtol=0, atol=1e-6)
    assert rec.joint_names == direct.joint_names
    assert json.loads(truth.read_text())["effects"] == {"coupling": 1.5}
    assert "coupling" not in (bag / "metadata.yaml").read_text()
    assert main(args) == 2 and "--force" in capsys.readouterr().err
