"""egovib_ros.evaluation.contacts (`egovib detect` as a library): contact events of a simulated
bag with ground truth, the threshold from a no-contact bag at the run's joint speeds, the
latency counted from the true onset, the same events for any slicing of the bag."""

from __future__ import annotations

import numpy as np
import pytest

from egovib_ros.bag import read_recording, write_recording
from egovib_ros.core import NoiseModel
from egovib_ros.errors import ConfigError
from egovib_ros.evaluation.contacts import detect_bag, run_speed_limit


@pytest.fixture(scope="module")
def model(sim_bags_model):
    return NoiseModel.load(sim_bags_model)


@pytest.mark.parametrize("method", ["paper", "raw"])
def test_taps_are_found_with_a_threshold_from_no_contact_data(sim_bags, model, method):
    found = detect_bag(
        sim_bags / "motion", model=model, method=method, calibration=sim_bags / "sweep",
        false_alarms_per_min=1.0,
    )  # fmt: skip
    assert found.threshold_source.startswith("no-contact data at this run's joint speeds")
    assert found.calibration_false_alarms_per_min <= 1.0
    scores = found.scores
    assert scores["n_taps"] >= 4 and scores["f1"] == 1.0 and scores["false_alarms_per_min"] == 0
    assert found.counts == {"samples": 12_000, "events": scores["tp"]}
    # a live system publishes an event after the method's delay plus the detector's report time
    delay = 1e3 * (model.block_length - 1) / model.sample_rate_hz if method == "paper" else 0.0
    assert found.method_delay_ms == pytest.approx(delay)
    assert delay < scores["latency_ms_p50"] < delay + 20.0


def test_a_threshold_given_gives_the_same_events_for_any_slicing(sim_bags, model, tmp_path):
    motion = read_recording(sim_bags / "motion")
    write_recording(tmp_path / "small", motion, chunk_bytes=20_000, window_s=0.01)
    whole = detect_bag(sim_bags / "motion", model=model, threshold=0.7)
    sliced = detect_bag(tmp_path / "small", model=model, threshold=0.7)
    assert whole.threshold_source == "given" and whole.calibration_false_alarms_per_min is None
    assert [(e.onset_ns, e.report_ns) for e in sliced.events] == [
        (e.onset_ns, e.report_ns) for e in whole.events
    ]
    higher = detect_bag(sim_bags / "motion", model=model, threshold=5.0)
    assert len(higher.events) < len(whole.events)


def test_the_speed_limit_is_the_runs_top_speed_with_a_margin(sim_bags, model):
    motion = read_recording(sim_bags / "motion")
    np.testing.assert_allclose(
        run_speed_limit(sim_bags / "motion", model),
        1.05 * np.nanmax(np.abs(motion.joint_velocity), axis=0),
    )


def test_bad_requests_are_config_errors(sim_bags, model):
    with pytest.raises(ConfigError, match="method: expected one of"):
        detect_bag(sim_bags / "motion", model=model, method="wiener", threshold=1.0)
    with pytest.raises(ConfigError, match="a threshold or a no-contact calibration bag"):
        detect_bag(sim_bags / "motion", model=model)
