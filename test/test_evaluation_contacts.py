"""egovib_ros.evaluation.contacts (`egovib detect` as a library): contact events of a simulated
bag with ground truth after the model's default method, the threshold stored in the model
(or set again from a no-contact bag by the same rule), the latency counted from the true
onset, the same events for any slicing of the bag."""

from __future__ import annotations

import pytest

from egovib_ros.bag import read_recording, write_recording
from egovib_ros.core import NoiseModel
from egovib_ros.core.methods import DETECTOR_PREFIX, method_delay_ms
from egovib_ros.errors import ConfigError
from egovib_ros.evaluation.contacts import detect_bag


@pytest.fixture(scope="module")
def model(sim_bags_model):
    return NoiseModel.load(sim_bags_model)


@pytest.mark.parametrize("method", ["paper", "hybrid"])
def test_taps_are_found_with_a_threshold_from_no_contact_data(sim_bags, model, method):
    found = detect_bag(
        sim_bags / "motion", model=model, method=method, calibration=sim_bags / "sweep",
        false_alarms_per_min=1.0,
    )  # fmt: skip
    assert found.threshold_source.startswith("no-contact data")
    # the rule's budget is a quantile of the no-contact envelope: about that many a minute
    assert found.calibration_false_alarms_per_min <= 2.0
    scores = found.scores
    assert scores["n_taps"] >= 4 and scores["f1"] == 1.0 and scores["false_alarms_per_min"] == 0
    assert found.counts == {
        "samples": 12_000, "events": scores["tp"], "samples_beyond_calibration_motion": 0
    }  # fmt: skip
    # a live system publishes an event after the method's delay plus the detector's report time
    delay = method_delay_ms(model, method)  # paper: a block; hybrid: its drop-in's look-ahead
    assert delay >= 4.0 and found.method_delay_ms == pytest.approx(delay)
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


def test_by_default_the_models_method_and_its_stored_threshold(sim_bags, model):
    """The default: hybrid (the model was calibrated for every method) on its drop-in output,
    at the threshold `egovib calibrate` stored, which the same rule on the calibration bag
    gives again."""
    found = detect_bag(sim_bags / "motion", model=model)
    assert found.method == "hybrid" and found.threshold_source.startswith("stored in the model")
    assert found.threshold == pytest.approx(float(model.extras[DETECTOR_PREFIX + "hybrid"]))
    again = detect_bag(
        sim_bags / "motion", model=model, calibration=sim_bags / "sweep", false_alarms_per_min=1.0
    )
    assert again.threshold == pytest.approx(found.threshold, rel=1e-9)
    assert [e.onset_ns for e in again.events] == [e.onset_ns for e in found.events]
    assert found.scores["f1"] == 1.0


def test_bad_requests_are_config_errors(sim_bags, model):
    with pytest.raises(ConfigError, match="method: expected one of"):
        detect_bag(sim_bags / "motion", model=model, method="wiener", threshold=1.0)
    bare = model.replace(
        extras={k: v for k, v in model.extras.items() if not k.startswith("detector.")},
        provenance={k: v for k, v in model.provenance.items() if k != "source_bag"},
    )
    with pytest.raises(ConfigError, match="stores no detection threshold"):
        detect_bag(sim_bags / "motion", model=bare)
