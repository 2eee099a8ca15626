"""Metrics of docs/INTERFACES.md section 6 on synthetic signals with known answers."""

import numpy as np
import pytest

from egovib_ros.evaluation import metrics

FS = 3000.0


def _decaying_tap(n, peak, freq=400.0, tau=0.01):
    t = np.arange(n) / FS
    return peak * np.exp(-t / tau) * np.sin(2 * np.pi * freq * t + np.pi / 2)


def _synthetic(n=3 * 3000, onsets=(3000, 4500, 6000), tap_len=150, peak=4.0, noise=0.25, seed=1):
    """Reference with taps at known onsets; raw = reference + sign noise
    (|noise| = `noise`) outside taps."""
    rng = np.random.default_rng(seed)
    reference = np.zeros(n)
    for onset in onsets:
        reference[onset : onset + tap_len] = _decaying_tap(tap_len, peak)
    noise_signal = noise * rng.choice([-1.0, 1.0], size=n)
    return reference, noise_signal


def test_segment_contacts_finds_onsets_and_masks():
    reference, _ = _synthetic()
    seg = metrics.segment_contacts(reference, sample_rate_hz=FS)
    assert seg.onsets.tolist() == [3000, 4500, 6000]
    assert seg.n_taps == 3
    before = int(metrics.MARGIN_BEFORE_S * FS)
    assert seg.tap_windows[0, 0] == 3000 - before
    assert not seg.no_contact_mask[2990:3200].any()
    assert seg.no_contact_mask[1000:2900].all()
    edge = int(metrics.EDGE_S * FS)
    assert not seg.no_contact_mask[:edge].any() and not seg.no_contact_mask[-edge:].any()
    # contact mask and no-contact mask never overlap
    assert not (seg.contact_mask & seg.no_contact_mask).any()


def test_known_tap_in_known_noise_gives_known_snr_reduction_retention():
    reference, noise = _synthetic(peak=4.0, noise=0.25)
    seg = metrics.segment_contacts(reference, sample_rate_hz=FS)
    # Noise only where there is no contact, so the per-tap peak is exactly the tap's peak.
    raw = np.where(seg.contact_mask, reference, noise)
    denoised = np.where(seg.contact_mask, 0.5 * reference, 0.1 * noise)
    m = metrics.signal_metrics(raw, denoised, reference, seg)
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


@pytest.mark.parametrize(
    "error_scale, expected", [(0.1, 20.0), (10.0, -10.0), (0.0, 35.0), (0.01, 35.0)]
)
def test_segmental_snr_known_ratios_and_clamping(error_scale, expected):
    rng = np.random.default_rng(2)
    reference = rng.normal(size=640)
    snr = metrics.segmental_snr(reference, reference * (1 + error_scale))
    assert snr.shape == (19,)  # (640 - 64) / 32 + 1
    assert np.allclose(snr, expected, atol=1e-9)


def test_segments_in_mask_majority_rule():
    mask = np.zeros(256, bool)
    mask[64:128] = True
    chosen = metrics.segments_in_mask(mask)
    # segments start at 0,32,...,192; [32,96) and [64,128) and [96,160) are >= half inside
    assert np.flatnonzero(chosen).tolist() == [1, 2, 3]


def test_estimate_lag_recovers_shift():
    rng = np.random.default_rng(3)
    x = rng.normal(size=3000)
    assert metrics.estimate_lag(x, x) == 0
    delayed = np.concatenate([np.zeros(7), x[:-7]])
    assert metrics.estimate_lag(x, delayed) == 7


def test_signal_metrics_rejects_misaligned_lengths():
    reference, noise = _synthetic()
    seg = metrics.segment_contacts(reference, sample_rate_hz=FS)
    with pytest.raises(ValueError):
        metrics.signal_metrics(noise, noise[:-1], reference, seg)


def test_json_safe_replaces_non_finite():
    out = metrics.json_safe({"a": float("inf"), "b": [np.float64(1.5), np.nan], "c": np.int64(3)})
    assert out == {"a": None, "b": [1.5, None], "c": 3}
