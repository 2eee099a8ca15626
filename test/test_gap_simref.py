"""gap.simref: the simulator's own lag between joint states and vibration, against which
`timing` is judged, and when it applies."""

from __future__ import annotations

import pytest
from gaptables import synthetic_model

from egovib_ros.gap.effects import LAG_TOLERANCE_S
from egovib_ros.gap.simref import model_matches_simulator, simulator_reference_lag
from egovib_ros.robot import default_profile


@pytest.fixture(scope="module")
def sim_model(sim_model_path):
    from egovib_ros.core import NoiseModel

    return NoiseModel.load(sim_model_path)


def test_the_reference_applies_to_models_of_the_simulated_joints_only(sim_model):
    assert tuple(sim_model.joint_names) == default_profile().joint_names
    assert model_matches_simulator(sim_model)
    other = synthetic_model()  # two joints named otherwise (test/gaptables.py)
    assert other.joint_names != sim_model.joint_names
    assert not model_matches_simulator(other)


def test_the_simulators_own_lag_is_a_few_ms_and_repeatable(sim_model):
    """Group delays of the structural paths and the band-pass: within a few ms of zero, the
    same for the same seed (the timing effect is a lag beyond it)."""
    lag = simulator_reference_lag(sim_model, duration_s=20.0, seed=3)
    assert abs(lag) <= 0.02
    assert simulator_reference_lag(sim_model, duration_s=20.0, seed=3) == lag
    assert abs(lag) < 0.03 - LAG_TOLERANCE_S  # inside the +-30 ms scan, away from its edge
