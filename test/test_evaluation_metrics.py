"""Metrics of docs/INTERFACES.md section 6 on synthetic signals with known answers."""

import numpy as np
import pytest
from synthetic import FS, tap_signals

from egovib_ros.evaluation import metrics


def test_segment_contacts_finds_onsets_and_masks():
    reference, _ = tap_signals()
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


@pytest.mark.parametrize(
    "error_scale, expected", [(0.1, 20.0), (10.0, -10.0), (0.0, 35.0), (0.01, 35.0)]
)
def test_segmental_snr_known_ratios_and_clamping(error_scale, expected):
    rng = np.random.default_rng(2)
    reference = rng.normal(size=640)
    snr = metrics.segmental_snr(reference, reference * (1 + error_scale))
    assert snr.shape == (19,)  # (640 - 64) / 32 + 1
    assert np.allclose(snr, expected, atol=1e-9)


def _lag(reference, x) -> int:
    lag = metrics.LagCorrelation()
    lag.push(reference, x)
    return lag.lag()


def test_lag_correlation_recovers_shift():
    rng = np.random.default_rng(3)
    x = rng.normal(size=3000)
    assert _lag(x, x) == 0
    delayed = np.concatenate([np.zeros(7), x[:-7]])
    assert _lag(x, delayed) == 7


def test_json_safe_replaces_non_finite():
    out = metrics.json_safe({"a": float("inf"), "b": [np.float64(1.5), np.nan], "c": np.int64(3)})
    assert out == {"a": None, "b": [1.5, None], "c": 3}
