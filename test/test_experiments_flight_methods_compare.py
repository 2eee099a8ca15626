"""experiments.flight.methods_compare: the figures it adds to the evaluation's (waveform
correlation, pooling over event sets, the pass/fail table), on signals with known answers.
The driver itself runs for minutes (docs/methods_compare.md says how)."""

from __future__ import annotations

import numpy as np
import pytest

from egovib_ros.experiments.flight.methods_compare import flight_checks, pool, waveform_correlation


def test_waveform_correlation_is_per_event_and_ignores_silent_windows():
    t = np.arange(200) / 1000.0
    reference = np.sin(2 * np.pi * 150 * t)
    output = 0.5 * reference  # a gain does not change the waveform
    windows = np.array([[0, 50], [60, 120], [150, 151]])
    assert waveform_correlation(output, reference, windows) == pytest.approx(1.0)
    flipped = output.copy()
    flipped[60:120] *= -1
    assert waveform_correlation(flipped, reference, windows) == pytest.approx(0.0, abs=1e-12)
    assert np.isnan(waveform_correlation(output, reference, np.zeros((0, 2), int)))


def row(**values):
    base = dict(
        noise_reduction_db=10.0,
        tap_retention=0.9,
        waveform_corr=0.9,
        peak_snr_improvement_db=5.0,
        false_alarms_per_min=1.0,
        tp=9,
        fp=1,
        fn=1,
    )
    base.update(values)
    return base


def test_pool_averages_the_figures_and_pools_the_counts_for_f1():
    pooled = pool([row(tp=10, fp=0, fn=0), row(noise_reduction_db=20.0, tp=0, fp=0, fn=10)])
    assert pooled["noise_reduction_db"] == 15.0 and pooled["noise_reduction_db_min"] == 10.0
    assert pooled["events"] == 20
    assert pooled["f1"] == pytest.approx(2 * 1.0 * 0.5 / 1.5)


def test_checks_compare_each_target_and_say_which_are_missed():
    def results(hybrid_nr, retention, half_retention):
        one = {
            "hybrid": pool([row(noise_reduction_db=hybrid_nr, tap_retention=retention)]),
            "paper": pool([row()]),
            "mean_command": pool([row(noise_reduction_db=12.0)]),
            "firmware": {"noise_reduction_db": 17.4},
            "oracle": {"tap_retention": 0.86},
        }
        half = {key: dict(value) for key, value in one.items()}
        half["hybrid"] = pool([row(tap_retention=half_retention)])
        return {"1": one, "0.5": half}

    splits = {
        name: {"results": results(20.0, 0.95, 0.8), "delay_ms": {"hybrid": 4.0}}
        for name in ("primary", "swapped", "beyond")
    }
    splits["primary"]["results"] = results(16.0, 0.85, 0.6)
    checks = flight_checks(splits)
    primary = checks["primary"]
    assert not primary["noise_reduction >= firmware"]["met"]
    assert not primary["retention >= 0.9"]["met"]
    assert primary["delay_ms <= 5"]["met"]
    assert primary["(retention of the true event alone)"]["value"] == 0.86
    assert all(c["met"] for c in checks["swapped"].values())
    assert checks["beyond (beyond calibration)"]["noise_reduction >= 1-D table"]["met"]
