"""Tests of egovib_ros.sim.params: config/sim.yaml, YAML round trip, the effects SPEC."""

from __future__ import annotations

import pytest

from egovib_ros.errors import ConfigError
from egovib_ros.sim.params import SimParams, default_config_path, format_effects, parse_effects


def test_config_file_equals_defaults_and_round_trips(tmp_path):
    assert default_config_path().exists()
    loaded = SimParams.load()
    assert loaded == SimParams()
    loaded.wrist.line_amps = [0.5, 0.2, 0.1]
    loaded.effects = {"position": 0.3, "drift": 0.2}
    loaded.coupling_gain = 0.7
    path = tmp_path / "fitted.yaml"
    loaded.save(path)
    again = SimParams.load(path)
    assert again == loaded and again.wrist.line_amps == [0.5, 0.2, 0.1]


def test_partial_yaml_and_sim_section(tmp_path):
    path = tmp_path / "p.yaml"
    path.write_text("sim:\n  controller_tau_s: 0.05\n  gripper:\n    line_amps: [2.0, 1.0, 0.5]\n")
    p = SimParams.load(path)
    assert p.controller_tau_s == 0.05 and p.gripper.line_amps == [2.0, 1.0, 0.5]
    assert p.gripper.path_band_hz == SimParams().gripper.path_band_hz


@pytest.mark.parametrize(
    "text,needle",
    [
        ("nonsense_key: 1\n", "nonsense_key"),
        ("wrist:\n  teeth: 3\n", "teeth"),
        ("effects: {wobble: 1}\n", "wobble"),
        ("[1, 2]\n", "mapping"),
        ("a: [\n", "YAML"),
    ],
)
def test_bad_yaml_is_config_error(tmp_path, text, needle):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=needle):
        SimParams.load(path)


def test_parse_effects():
    assert parse_effects("position=0.5,timing=0.03") == {"position": 0.5, "timing": 0.03}
    assert parse_effects("") == {} and parse_effects(None) == {} and parse_effects("none") == {}
    assert parse_effects("drift=0,coupling=1") == {"coupling": 1.0}  # zero = off
    assert parse_effects(" position = 0.5 , ") == {"position": 0.5}
    assert parse_effects(format_effects({"position": 0.5, "timing": -0.02})) == {
        "position": 0.5,
        "timing": -0.02,
    }
    for bad in ("position", "position=abc", "wobble=1", "position=1,position=2", "drift=nan"):
        with pytest.raises(ConfigError):
            parse_effects(bad)
