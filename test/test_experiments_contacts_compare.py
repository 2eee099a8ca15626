"""experiments.contacts_compare: the quick run (a short simulated PR2 run, 2.5 s of the
shipped flight with one event set) writes its three files, with every figure per case and
method, and its F1 agrees with the counts it reports. The full run takes minutes
(docs/contacts_compare.md says how)."""

from __future__ import annotations

import json

import pytest

from egovib_research.experiments import contacts_compare

FIELDS = {
    "f1",
    "precision",
    "recall",
    "false_alarms_per_min",
    "latency_ms_p50",
    "latency_ms_p99",
    "tp",
    "fp",
    "fn",
    "fp_near_taps",
    "n_taps",
    "threshold",
    "method_delay_ms",
    "noise_reduction_db",
    "tap_retention",
    "tap_margin",
    "taps_above",
    "noise_over_threshold",
    "threshold_origin",
}


def _check(rows: dict) -> None:
    assert set(rows) == set(contacts_compare.METHODS)
    for method, r in rows.items():
        assert set(r) >= FIELDS, (method, FIELDS - set(r))
        assert r["tp"] + r["fn"] == r["n_taps"] > 0
        precision = r["tp"] / (r["tp"] + r["fp"]) if r["tp"] + r["fp"] else 1.0
        recall = r["tp"] / r["n_taps"]
        f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
        assert r["f1"] == pytest.approx(f1)
        assert 0 <= r["fp_near_taps"] <= r["fp"]
        assert r["threshold"] > 0
        assert r["threshold_origin"]["threshold_over_calibration_median"] > 1
    assert rows["raw"]["method_delay_ms"] == 0.0 and rows["raw"]["noise_reduction_db"] == 0.0
    assert rows["raw"]["tap_retention"] == pytest.approx(1.0)
    assert rows["paper"]["method_delay_ms"] > rows["hybrid"]["method_delay_ms"] > 0
    # both methods remove noise from what the detector sees
    assert rows["paper"]["noise_reduction_db"] > 3 and rows["hybrid"]["noise_reduction_db"] > 3


def test_quick_run_writes_json_markdown_and_figure(tmp_path):
    assert contacts_compare.main(["--out", str(tmp_path), "--quick"]) == 0
    result = json.loads((tmp_path / "contacts_compare.json").read_text())
    assert "--quick" in result["command"] and result["runtime_s"] > 0
    (pr2,) = result["pr2"].values()
    assert pr2["taps"] > 0
    _check(pr2["results"])
    (flight,) = result["flight"].values()
    assert set(flight["results"]) == {"1", "0.5"}
    for rows in flight["results"].values():
        _check(rows)
    markdown = (tmp_path / "contacts_compare.md").read_text()
    assert "Where denoising costs detection" in markdown
    assert markdown.count("| hybrid |") == 3  # PR2, flight at 1x and 0.5x
    assert (tmp_path / "contacts_compare.png").stat().st_size > 20_000
