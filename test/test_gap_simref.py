"""gap.simref: the lag between joint states and vibration that the model's own source
shows (its calibration recording, or the simulator), against which `timing` is judged."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from gaptables import synthetic_model

from egovib_ros.core import NoiseModel, calibrate_arrays
from egovib_ros.errors import ModelFileError
from egovib_ros.gap import simref
from egovib_ros.gap.diagnose import DiagnosisOptions
from egovib_ros.gap.effects import LAG_TOLERANCE_S
from egovib_ros.gap.pipeline import diagnose_recording, reference_lag_for
from egovib_ros.gap.simref import (
    OWN_LAG_KEY,
    model_matches_simulator,
    own_lag,
    simulator_reference_lag,
    with_own_lag,
)
from egovib_ros.robot import default_profile
from egovib_ros.sim import simulate_motion


@pytest.fixture(scope="module")
def sim_model(sim_model_path):
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


@pytest.fixture(scope="module")
def late_robot():
    """The simulator's free motion as a robot whose joint states reach the recorder 40 ms
    late: (its calibration recording, the model `egovib calibrate` makes of it, on time and
    late)."""
    rec, _ = simulate_motion(duration_s=20.0, max_speed=0.8, tap_rate_hz=0.0, effects={}, seed=5)
    late = dataclasses.replace(rec, joint_stamps_ns=rec.joint_stamps_ns + 40_000_000)
    models = {}
    for name, r in (("on_time", rec), ("late", late)):
        model, _ = calibrate_arrays(
            r.sensor_stamps_ns, r.sensor, r.joint_stamps_ns, r.joint_velocity, sweep="free"
        )
        models[name] = with_own_lag(model, r)
    return late, models


def test_a_models_own_lag_is_the_one_its_calibration_recording_shows(late_robot, tmp_path):
    late, models = late_robot
    on_time, lagging = own_lag(models["on_time"]), own_lag(models["late"])
    assert abs(on_time) <= 0.02  # the simulator's own few ms
    assert lagging - on_time == pytest.approx(0.040, abs=0.002)
    # kept in the file; what `egovib gap` judges timing against unless one is given
    models["late"].save(tmp_path / "m.npz")
    loaded = NoiseModel.load(tmp_path / "m.npz")
    assert own_lag(loaded) == lagging
    assert reference_lag_for(loaded, None, None) == lagging
    assert reference_lag_for(loaded, 0.0, None) == 0.0
    # too little data to scan (fewer no-contact blocks than a diagnosis needs): none stored
    n = 3000
    short = dataclasses.replace(
        late,
        sensor_stamps_ns=late.sensor_stamps_ns[:n],
        sensor=late.sensor[:n],
    )
    bare = models["late"].replace(extras={})
    assert own_lag(with_own_lag(bare, short)) is None
    with pytest.raises(ModelFileError, match=OWN_LAG_KEY):
        own_lag(bare.replace(extras={OWN_LAG_KEY: np.array([0.1, 0.2])}))


def test_a_robot_diagnosed_against_its_own_model_is_not_out_of_sync(late_robot):
    """Another recording of the late robot: in sync with the model calibrated on it (the
    lag is in its table), though 40 ms off the simulator's (docs/gap.md, "The reference
    lag")."""
    _, models = late_robot
    rec, _ = simulate_motion(duration_s=40.0, max_speed=0.8, tap_rate_hz=0.0, effects={}, seed=6)
    again = dataclasses.replace(rec, joint_stamps_ns=rec.joint_stamps_ns + 40_000_000)
    model = models["late"]
    diag = diagnose_recording(
        again,
        model,
        source="the late robot again",
        options=DiagnosisOptions(reference_lag_s=reference_lag_for(model, None, None)),
    )
    assert "timing" not in [e["effect"] for e in diag.effects]
    fitted = diag.lag_scan["timing_lag_s"]
    assert fitted == pytest.approx(own_lag(model), abs=LAG_TOLERANCE_S)


def test_a_long_calibration_is_scanned_on_its_first_minutes_only(late_robot, monkeypatch):
    """Time and memory of the scan stay those of the diagnosis's budget, whatever the
    calibration's length."""
    late, models = late_robot
    model = models["late"].replace(extras={})
    monkeypatch.setattr(simref, "DEFAULT_BUDGET_MINUTES", 0.1)  # 6 s of the 20 s
    end = late.sensor_stamps_ns[0] + 6_000_000_000
    n, m = (np.searchsorted(s, end) for s in (late.sensor_stamps_ns, late.joint_stamps_ns))
    head = dataclasses.replace(
        late,
        sensor_stamps_ns=late.sensor_stamps_ns[:n],
        sensor=late.sensor[:n],
        joint_stamps_ns=late.joint_stamps_ns[:m],
        joint_position=late.joint_position[:m],
        joint_velocity=late.joint_velocity[:m],
    )
    assert own_lag(with_own_lag(model, late)) == own_lag(with_own_lag(model, head)) is not None
