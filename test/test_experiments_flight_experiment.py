"""The real-flight experiment on a short slice of the shipped bag: fields, thresholds, CLI."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from egovib_research.experiments.flight.events import EventSpec
from egovib_research.experiments.flight.experiment import RealConfig, run_experiment, run_fold
from egovib_research.experiments.flight.recording import read_flight_bag
from egovib_ros.cli import main as egovib
from egovib_ros.robot import load_profile

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "quadcopter_ar8"
PROFILE = load_profile("quadcopter")
# Calibration 0-4 s (idle, take-off, hover), test 4-6 s (hover): a few seconds of the real flight.
SHORT = dict(split_s=4.0, end_s=6.0, amplitudes=(1.0,), swapped=False, event_sets=1)
METRIC_FIELDS = (
    "noise_mean_raw",
    "noise_mean_denoised",
    "noise_reduction_db",
    "tap_peak_raw",
    "tap_peak_denoised",
    "tap_retention",
    "peak_snr_raw_db",
    "peak_snr_denoised_db",
    "peak_snr_improvement_db",
    "f1",
    "precision",
    "recall",
    "threshold",
    "false_alarms_per_min",
    "n_taps",
)


@pytest.fixture(scope="module")
def flight():
    return read_flight_bag(BAG, PROFILE)


@pytest.fixture(scope="module")
def short_result(flight):
    return run_experiment(flight, PROFILE, RealConfig(**SHORT), keep_signals=False)


def test_short_slice_gives_every_metric_for_every_method(short_result):
    fold = short_result["primary"]
    assert fold["calibration_s"] == [0.0, 4.0] and fold["test_s"] == [4.0, 6.0]
    rows = fold["results"]["1"]
    assert set(rows) == {
        "raw",
        "ours",
        "ours_L64",
        "global",
        "mean_command",
        "notch_q5",
        "notch_q2",
        "firmware",
    }
    for name, row in rows.items():
        if name == "firmware":
            assert row["noise_mean_denoised"] < row["noise_mean_raw"] and np.isfinite(
                row["noise_reduction_db"]
            )
            continue
        for key in METRIC_FIELDS:
            assert key in row and np.isfinite(row[key]), (name, key)
        assert row["n_taps"] == fold["events"]["1"]["n_events"] >= 2
    assert rows["raw"]["noise_reduction_db"] == 0.0
    assert rows["ours"]["noise_reduction_db"] > 6  # real motor noise, removed
    assert fold["methods"]["ours"]["delay_ms"] == pytest.approx(
        1e3 * PROFILE.block_length / PROFILE.rate_hz
    )
    assert fold["methods"]["notch_q5"]["info"]["map"]["windows_used"] > 0


def test_more_event_sets_are_pooled(flight):
    fold = run_fold(
        flight,
        PROFILE,
        (0.0, 4.0),
        (4.0, 6.0),
        RealConfig(**{**SHORT, "methods": ("raw", "mean_command"), "event_sets": 2}),
    )
    pooled = fold["over_seeds"]
    assert pooled["seeds"] == [1, 2]
    entry = pooled["methods"]["mean_command"]
    first = fold["results"]["1"]["mean_command"]
    assert entry["events"] == 2 * first["n_taps"]
    assert entry["f1"]["min"] <= first["f1"] <= entry["f1"]["max"] and 0 <= entry["f1_pooled"] <= 1


def test_thresholds_come_from_the_calibration_part_only(flight):
    config = RealConfig(**{**SHORT, "methods": ("raw", "ours", "notch_q5")})
    base = run_fold(flight, PROFILE, (0.0, 4.0), (4.0, 6.0), config)
    # Multiply the test part's gyro by 10: no threshold may move (they never look at it) ...
    t0 = flight.sensor_stamps_ns[0]
    louder = flight.sensor.copy()
    test = (flight.sensor_stamps_ns >= t0 + 4e9) & (flight.sensor_stamps_ns < t0 + 6e9)
    louder[test] *= 10.0
    loud = run_fold(
        dataclasses.replace(flight, sensor=louder), PROFILE, (0.0, 4.0), (4.0, 6.0), config
    )
    for name in config.methods:
        assert loud["methods"][name]["threshold"] == base["methods"][name]["threshold"], name
    assert (
        loud["results"]["1"]["raw"]["noise_mean_raw"]
        > 5 * base["results"]["1"]["raw"]["noise_mean_raw"]
    )
    # ... while changing the calibration part does move them.
    quieter = flight.sensor.copy()
    quieter[~test] *= 0.5
    cal = run_fold(
        dataclasses.replace(flight, sensor=quieter), PROFILE, (0.0, 4.0), (4.0, 6.0), config
    )
    assert cal["methods"]["raw"]["threshold"] == pytest.approx(
        0.5 * base["methods"]["raw"]["threshold"]
    )


def test_events_are_repeatable_and_scaled_to_the_test_noise(short_result, flight):
    again = run_fold(
        flight, PROFILE, (0.0, 4.0), (4.0, 6.0), RealConfig(**{**SHORT, "methods": ("raw",)})
    )
    first = short_result["primary"]["events"]["1"]
    assert again["events"]["1"]["onsets_s"] == first["onsets_s"]
    raw = short_result["primary"]["results"]["1"]["raw"]
    # Band-passed event peak = the largest noise magnitude (paper: "similar to the maximum noise").
    assert first["target_peak_rad_s"] > 2 * raw["noise_mean_raw"]
    other = run_fold(
        flight,
        PROFILE,
        (0.0, 4.0),
        (4.0, 6.0),
        RealConfig(**{**SHORT, "methods": ("raw",), "events": EventSpec(seed=2)}),
    )
    assert other["events"]["1"]["onsets_s"] != first["onsets_s"]


def test_cli_writes_the_report_files(tmp_path, capsys):
    out = tmp_path / "docs"
    code = egovib([
        "real", "evaluate", "--bag", str(BAG), "--out", str(out), "--split", "4", "--end", "6",
        "--no-swapped", "--event-sets", "2",
    ])  # fmt: skip
    assert code == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == [
        "real_methods.png",
        "real_readme_section.md",
        "real_results.json",
        "real_results.md",
        "real_spectrogram.png",
        "real_timeseries.png",
    ]
    report = json.loads((out / "real_results.json").read_text())
    assert report["schema"] == "egovib.real/1" and "signals" not in report["primary"]
    assert (
        report["command"].startswith("egovib real evaluate --bag")
        and "--split 4" in report["command"]
        and "--event-sets 2" in report["command"]
    )
    markdown = (out / "real_results.md").read_text()
    assert "MIT OR Apache-2.0" in markdown and "Where a baseline wins" in markdown
    ours = report["primary"]["results"]["1"]["ours"]
    assert f"{ours['noise_reduction_db']:.1f}" in markdown
    pooled = report["primary"]["over_seeds"]["methods"]["ours"]
    assert f"| {pooled['f1_pooled']:.2f} |" in (out / "real_readme_section.md").read_text()
    # a second run into the same directory needs --force; nothing is touched without it
    before = (out / "real_results.json").read_bytes()
    capsys.readouterr()
    assert egovib(["real", "evaluate", "--bag", str(BAG), "--out", str(out)]) == 2
    assert (
        "--force" in capsys.readouterr().err and (out / "real_results.json").read_bytes() == before
    )


def test_cli_bad_bag_is_a_one_line_error_without_output(tmp_path, capsys):
    out = tmp_path / "docs"
    assert egovib(["real", "evaluate", "--bag", str(tmp_path / "nope"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nope" in err[0]
    assert not out.exists() or not any(out.iterdir())
    assert egovib(["real", "evaluate", "--bag", str(BAG), "--out", str(out), "--split", "40"]) == 2
    assert "split" in capsys.readouterr().err
