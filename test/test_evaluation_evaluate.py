"""evaluate_recording on a small simulated recording: fields, fallbacks and ground-truth checks."""

import dataclasses

import numpy as np
import pytest

from egovib_research.experiments import scoring
from egovib_ros.core import calibrate_arrays
from egovib_ros.errors import BagError
from egovib_ros.evaluation.evaluate import REPORT_FIELDS, evaluate_recording, require_ground_truth
from egovib_ros.sim import simulate_motion, simulate_sweep


@pytest.fixture(scope="module")
def model():
    sweep, _ = simulate_sweep(grid="superposition", dwell_s=0.6, settle_s=0.3, effects={}, seed=21)
    model, _ = calibrate_arrays(
        sweep.sensor_stamps_ns,
        sweep.sensor,
        sweep.joint_stamps_ns,
        sweep.joint_velocity,
        sweep="superposition",
    )
    return model


@pytest.fixture(scope="module")
def recording():
    rec, truth = simulate_motion(
        duration_s=8.0, max_speed=0.5, tap_rate_hz=2.0, effects={}, seed=22
    )
    return rec, truth


def test_without_calibration_uses_own_no_contact_part_and_says_so(model, recording):
    rec, truth = recording
    report = evaluate_recording(rec, model, keep_signals=True)
    for field in REPORT_FIELDS:
        assert field in report
    assert report["threshold_source"].startswith("no-contact part of this recording")
    # No noise clip and no short-block model: those two baselines cannot run.
    assert set(report["methods"]) == {"default", "bandpass", "boll", "paper", "wiener", "per_axis"}
    assert report["n_taps"] == len(truth["tap_onsets_ns"])
    # Taps found from the contact topic start within a millisecond of the simulator's onsets.
    found = rec.sensor_stamps_ns[report["signals"]["seg"].onsets]
    assert np.max(np.abs(found - np.asarray(truth["tap_onsets_ns"]))) <= 1_000_000
    curve = scoring.pr_curves(report, model.sample_rate_hz)["paper"]  # the paper's figures
    assert curve["precision"].shape == curve["recall"].shape == curve["threshold"].shape
    assert report["signals"]["paper"].shape == rec.sensor[:, 0].shape


def test_primary_fields_are_the_default_methods(model, recording):
    """The figures at the top are what a user gets without options: the model's default
    method (here the paper's: the model holds no other) and its drop-in output."""
    rec, _ = recording
    report = evaluate_recording(rec, model, methods=["bandpass"])
    assert {"default", "paper"} <= set(report["methods"])  # these two always run
    default = report["methods"]["default"]
    assert report["method"] == "paper"
    assert report["noise_reduction_db"] == default["noise_reduction_db"]
    assert report["f1_denoised"] == default["f1"]
    assert report["f1_raw"] == report["detection"]["raw_bandpassed"]["f1"]
    assert report["delay_ms"] == pytest.approx(63 / 3.0)


def test_require_ground_truth(recording):
    rec, _ = recording
    with pytest.raises(BagError, match="/accelerometer/contact"):
        require_ground_truth(dataclasses.replace(rec, contact=None), where="some_bag")
    with pytest.raises(BagError, match="samples"):
        require_ground_truth(dataclasses.replace(rec, contact=rec.contact[:-5]), where="some_bag")
