"""The whole-array metrics and detector of the experiments (experiments/scoring.py) on
synthetic signals with known answers."""

import numpy as np
import pytest
from synthetic import FS, tap_signals

from egovib_research.experiments import scoring
from egovib_ros.evaluation import metrics


def _bursts(n, onsets, amplitude=3.0, length=60):
    x = np.zeros(n)
    for onset in onsets:
        x[onset : onset + length] = amplitude * np.exp(-np.arange(length) / 20.0)
    return x


def test_known_tap_in_known_noise_gives_known_snr_reduction_retention():
    reference, noise = tap_signals(peak=4.0, noise=0.25)
    seg = metrics.segment_contacts(reference, sample_rate_hz=FS)
    # Noise only where there is no contact, so the per-tap peak is exactly the tap's peak.
    raw = np.where(seg.contact_mask, reference, noise)
    denoised = np.where(seg.contact_mask, 0.5 * reference, 0.1 * noise)
    m = scoring.signal_metrics(raw, denoised, reference, seg)
    assert m["noise_mean_raw"] == pytest.approx(0.25)
    assert m["noise_mean_denoised"] == pytest.approx(0.025)
    assert m["noise_reduction_db"] == pytest.approx(20.0)
    assert m["tap_peak_raw"] == pytest.approx(4.0, rel=1e-3)
    assert m["tap_retention"] == pytest.approx(0.5)
    assert m["peak_snr_raw_db"] == pytest.approx(20 * np.log10(4.0 / 0.25), abs=0.01)
    assert m["peak_snr_improvement_db"] == pytest.approx(20 * np.log10(5.0), abs=0.01)
    # raw equals the reference inside contacts: perfect segments clamp at the top.
    assert m["segsnr_contact_raw_db"] == pytest.approx(35.0)
    # denoised = half the reference: error = -s/2, SNR = 20 log10(2) per segment.
    assert m["segsnr_contact_denoised_db"] == pytest.approx(20 * np.log10(2.0), abs=0.01)
    assert m["n_taps"] == 3


def test_segments_in_mask_majority_rule():
    mask = np.zeros(256, bool)
    mask[64:128] = True
    chosen = scoring.segments_in_mask(mask)
    # segments start at 0,32,...,192; [32,96) and [64,128) and [96,160) are >= half inside
    assert np.flatnonzero(chosen).tolist() == [1, 2, 3]


def test_signal_metrics_rejects_misaligned_lengths():
    reference, noise = tap_signals()
    seg = metrics.segment_contacts(reference, sample_rate_hz=FS)
    with pytest.raises(ValueError):
        scoring.signal_metrics(noise, noise[:-1], reference, seg)


def test_detect_events_onsets_and_refractory_merging():
    x = _bursts(
        6000, [1000, 1100, 3000]
    )  # 1100 is 33 ms after 1000: same event at 50 ms refractory
    onsets = scoring.detect_events(x, 1.0, sample_rate_hz=FS, refractory_s=0.05)
    assert onsets.tolist() == [1000, 3000]
    onsets = scoring.detect_events(x, 1.0, sample_rate_hz=FS, refractory_s=0.01)
    assert onsets.tolist() == [1000, 1100, 3000]
    assert scoring.detect_events(x, 10.0, sample_rate_hz=FS).size == 0


def test_precision_recall_f1_values_and_edge_cases():
    truth = np.array([1000, 2000, 3000, 4000])
    scores = scoring.precision_recall_f1(np.array([1005, 2005, 9000]), truth, sample_rate_hz=FS)
    assert scores["precision"] == pytest.approx(2 / 3)
    assert scores["recall"] == pytest.approx(0.5)
    assert scores["f1"] == pytest.approx(2 * (2 / 3) * 0.5 / (2 / 3 + 0.5))
    empty = scoring.precision_recall_f1(np.array([], int), truth, sample_rate_hz=FS)
    assert (empty["precision"], empty["recall"], empty["f1"]) == (1.0, 0.0, 0.0)
    perfect = scoring.precision_recall_f1(truth, truth, sample_rate_hz=FS)
    assert perfect["f1"] == 1.0


def test_threshold_from_calibration_silences_calibration_and_finds_taps():
    rng = np.random.default_rng(0)
    calibration = rng.normal(scale=0.2, size=30000)
    threshold = scoring.threshold_from_calibration(calibration)
    assert threshold == pytest.approx(1.1 * np.abs(calibration).max())
    assert scoring.detect_events(np.abs(calibration), threshold, sample_rate_hz=FS).size == 0
    onsets = [3000, 9000, 15000, 21000]
    test = np.abs(rng.normal(scale=0.2, size=30000) * 0.5 + _bursts(30000, onsets, amplitude=5.0))
    scores = scoring.evaluate_detector(test, np.array(onsets), threshold, sample_rate_hz=FS)
    assert scores["f1"] == 1.0 and scores["threshold"] == threshold


def test_pr_curve_sweeps_from_merged_noise_to_missed_taps():
    rng = np.random.default_rng(1)
    onsets = np.arange(2000, 28000, 2000)
    amplitudes = np.linspace(0.5, 5.0, onsets.size)
    x = np.abs(rng.normal(scale=0.3, size=30000))
    for onset, amplitude in zip(onsets, amplitudes):
        x[onset : onset + 60] += amplitude * np.exp(-np.arange(60) / 20.0)
    curve = scoring.pr_curve(x, onsets, sample_rate_hz=FS, n_thresholds=25)
    assert curve["threshold"].shape == curve["precision"].shape == (25,)
    # Very low thresholds merge noise and taps into a few long events; very high ones miss
    # the weak taps; in between nearly every tap is found without false alarms.
    assert curve["recall"][0] < 1.0 and curve["recall"][-1] < 0.5
    assert curve["f1"].max() >= 0.9
    assert np.all((curve["f1"] >= 0) & (curve["f1"] <= 1))


def test_onset_is_timed_at_constant_fraction_not_by_pre_echo():
    """A weak 20 ms pre-echo before a tap (block smearing) must not move the onset early."""
    x = np.zeros(6000)
    x[2940:3000] = 0.05  # pre-echo, 5 % of the peak, 20 ms early
    x[3000:3060] = 1.0 * np.exp(-np.arange(60) / 20.0)
    onsets = scoring.detect_events(x, 0.02, sample_rate_hz=FS)
    assert onsets.tolist() == [3000]
    # With the fraction at 0 the onset is the first threshold crossing (the pre-echo).
    assert scoring.detect_events(x, 0.02, sample_rate_hz=FS, onset_fraction=0.0).tolist() == [2940]


def test_envelope_is_causal_rms():
    x = np.zeros(300)
    x[100] = 3.0
    env = scoring.envelope(x, sample_rate_hz=FS, window_s=0.004)  # 12 samples
    assert np.all(env[:100] == 0)
    assert env[100:112] == pytest.approx(np.full(12, 3.0 / np.sqrt(12)))
    assert np.all(env[112:] < 1e-9)
