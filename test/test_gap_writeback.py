"""gap.writeback: the found effect written into a copy of the simulator's config; the
config it started from is never touched."""

from __future__ import annotations

import hashlib

import pytest
from gaptables import diagnosed

from egovib_ros.gap.writeback import write_back
from egovib_ros.sim import SimParams
from egovib_ros.sim.params import default_config_path


def digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def timing_and_none():
    # the diagnoses test_gap_advice reads too (gaptables.diagnosed: made once per process)
    return diagnosed("timing", 0.05, seed=5), diagnosed("none", 0.0, seed=5)


def test_a_found_lag_is_written_as_the_simulators_timing_strength(timing_and_none, tmp_path):
    timing, _ = timing_and_none
    assert timing.verdict == "timing"
    source = tmp_path / "sim.yaml"
    source.write_text(default_config_path().read_text())
    before = digest(source)
    result = write_back(timing, source, tmp_path / "sim_updated.yaml")
    assert digest(source) == before  # the input config is read, never written
    written = SimParams.load(tmp_path / "sim_updated.yaml")
    lag = timing.models["timing"].parameters["lag_vs_simulator_s"]
    assert written.effects["timing"] == pytest.approx(lag, abs=1e-5)
    assert result["strength"] == pytest.approx(lag, abs=1e-5)
    # everything but the effect is the source's
    original = SimParams.load(source).to_dict()
    updated = written.to_dict()
    assert {k: v for k, v in updated.items() if k != "effects"} == {
        k: v for k, v in original.items() if k != "effects"
    }
    assert result["heldout_gap_with_updated_simulator"] == pytest.approx(
        timing.gaps["timing"], abs=1e-4
    )


def test_no_effect_writes_the_config_unchanged_and_says_so(timing_and_none, tmp_path):
    _, none = timing_and_none
    assert none.verdict == "none"
    default_before = digest(default_config_path())
    result = write_back(none, None, tmp_path / "sim_updated.yaml")
    assert result["note"] == "no effect to add"
    assert SimParams.load(tmp_path / "sim_updated.yaml").to_dict() == SimParams.load().to_dict()
    assert digest(default_config_path()) == default_before
