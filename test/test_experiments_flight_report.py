"""experiments.flight.report: the real-flight report rendered from a small result dict with
known numbers (the shape run_experiment returns): tables, sentences, markdown, JSON, figures.
The full run over the shipped bag is test_experiments_flight_experiment's."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from egovib_research.experiments import fmt
from egovib_research.experiments.flight import report
from egovib_research.experiments.flight.events import EventSpec
from egovib_research.experiments.flight.experiment import FLIGHT_PHASES
from egovib_research.experiments.flight.methods import LABELS
from egovib_ros.evaluation.metrics import segment_contacts
from egovib_ros.robot import load_profile

PROFILE = load_profile("quadcopter")  # 1 kHz
FW = report.FIRMWARE_LABEL


def row(**values) -> dict:
    """One method's metrics at one amplitude (every key the report reads)."""
    base = dict(
        noise_mean_raw=0.05,
        noise_mean_denoised=0.01,
        noise_reduction_db=12.0,
        noise_spike_denoised=0.05,
        tap_peak_denoised=0.9,
        tap_retention=0.9,
        peak_snr_denoised_db=20.0,
        peak_snr_improvement_db=8.0,
        threshold=0.123,
        precision=0.8,
        recall=0.8,
        f1=0.8,
        f1_30ms=0.85,
        false_alarms_per_min=1.0,
    )
    base.update(values)
    return base


# At 1x: ours; raw (worse F1 and false alarms); global (wins retention only);
# mean_command (worse everywhere, its noise reduction not finite); notch_q5 (wins noise
# reduction, gain and false alarms; ties F1); the firmware row (noise only) listed first.
FIRMWARE = dict(
    noise_mean_raw=0.05,
    noise_mean_denoised=0.0123,
    noise_reduction_db=3.0,
    noise_spike_raw=0.2,
    noise_spike_denoised=0.1,
)
AT_1X = {
    "firmware": FIRMWARE,
    "raw": row(noise_reduction_db=0.0, tap_retention=1.0, peak_snr_improvement_db=0.0, f1=0.5,
               false_alarms_per_min=6.0),
    "ours": row(),
    "global": row(noise_reduction_db=6.0, tap_retention=0.95, peak_snr_improvement_db=4.0,
                  f1=0.6, false_alarms_per_min=2.0),
    "mean_command": row(noise_reduction_db=float("nan"), tap_retention=0.5,
                        peak_snr_improvement_db=1.0, f1=0.4, false_alarms_per_min=3.0),
    "notch_q5": row(noise_reduction_db=14.0, tap_retention=0.5, peak_snr_improvement_db=9.0,
                    f1=0.8, false_alarms_per_min=0.5, f1_30ms=None),
}  # fmt: skip
METHOD_NAMES = ("raw", "ours", "global", "mean_command", "notch_q5")


def methods(names=METHOD_NAMES, *, unmeasured: bool = True) -> dict:
    denoise = {"blocks": 40, "blocks_unmeasured": 3, "blocks_out_of_grid": 1}
    ours_info = {
        "coverage": {"cells_measured": 7, "cells_total": 14641, "blocks": 120, "median_blocks": 9},
        "denoise": denoise if unmeasured else {},
    }
    notch_info = {
        "map": {
            "coefficient_hz": 330.2,
            "exponent": 0.844,
            "windows_used": 21,
            "rms_error_hz": 4.56,
        }
    }
    info = {"ours": ours_info, "notch_q5": notch_info}
    return {
        name: {"delay_ms": 32.0 if name == "ours" else 0.0, "info": info.get(name, {})}
        for name in names
    }


def pooled_entry(mean: float, low: float, high: float) -> dict:
    return {"mean": mean, "min": low, "max": high}


OVER_SEEDS = {
    "seeds": [1, 2],
    "methods": {
        "raw": {
            "noise_reduction_db": pooled_entry(0.0, 0.0, 0.0),
            "tap_retention": pooled_entry(1.0, 1.0, 1.0),
            "peak_snr_improvement_db": pooled_entry(0.0, 0.0, 0.0),
            "f1": pooled_entry(0.5, 0.4, 0.6),
            "false_alarms_per_min": pooled_entry(6.0, 5.0, 7.0),
            "f1_pooled": 0.51,
            "events": 30,
        },
        "ours": {
            "noise_reduction_db": pooled_entry(12.0, 10.0, 14.0),
            "tap_retention": pooled_entry(0.9, 0.85, 0.95),
            "peak_snr_improvement_db": pooled_entry(8.0, 7.0, 9.0),
            "f1": pooled_entry(0.8, 0.7, 0.9),
            "false_alarms_per_min": pooled_entry(1.0, 0.5, 1.5),
            "f1_pooled": 0.82,
            "events": 30,
        },
        "global": {
            "noise_reduction_db": pooled_entry(13.0, 12.0, 14.0),
            "tap_retention": pooled_entry(0.7, 0.6, 0.8),
            "peak_snr_improvement_db": pooled_entry(5.0, 4.0, 6.0),
            "f1": pooled_entry(0.9, 0.8, 1.0),
            "false_alarms_per_min": pooled_entry(2.0, 1.0, 3.0),
            "f1_pooled": 0.6,
            "events": 30,
        },
    },
}


def fold(*, over_seeds=None, firmware=True, transfer=None, amplitudes=("1",), **extra) -> dict:
    at_1x = {k: v for k, v in AT_1X.items() if firmware or k != "firmware"}
    results = {a: at_1x for a in amplitudes}
    if len(amplitudes) > 1:  # other amplitudes: ours scaled, so each column is known
        results = {
            a: {**at_1x, "ours": row(f1=0.8 * float(a) / 2, peak_snr_improvement_db=4 * float(a))}
            for a in amplitudes
        }
        results["1"] = at_1x
    out = {
        "calibration_s": [0.0, 8.5],
        "test_s": [8.5, 16.85],
        "motor_command_range": {"calibration": [-0.0004, 0.91], "test": [0.251, 0.5]},
        "methods": methods(),
        "events": {a: {"n_events": 15, "target_peak_rad_s": 0.4567} for a in amplitudes},
        "results": results,
        "over_seeds": over_seeds or {},
    }
    if transfer:
        out["firmware_transfer"] = transfer
    out.update(extra)
    return out


def signals(n: int = 2000) -> dict:
    """2 s at 1 kHz: noise, three events; every key the figures read."""
    rng = np.random.default_rng(0)
    t = np.arange(n) / PROFILE.rate_hz
    reference = np.zeros(n)
    for onset in (300, 900, 1500):
        k = np.arange(n - onset)
        reference[onset:] += np.exp(-k / 8.0) * np.sin(2 * np.pi * 0.2 * k)
    noise = 0.05 * rng.standard_normal(n)
    t0 = 1_000_000_000
    return {
        "raw_input": reference + noise,
        "ours": reference + 0.2 * noise,
        "global": 0.8 * reference + 0.3 * noise,  # the best baseline over the event sets
        "firmware": 0.3 * noise,
        "reference": reference,
        "seg": segment_contacts(reference, sample_rate_hz=PROFILE.rate_hz),
        "stamps_ns": (t0 + 8.5e9 + t * 1e9).astype(np.int64),
        "t0_ns": t0,
    }


def result(
    *, swapped: bool = True, over_seeds=OVER_SEEDS, keep_signals: bool = False, phases=FLIGHT_PHASES
) -> dict:
    out = {
        "schema": "egovib.real/1",
        "command": "egovib real evaluate --bag bags/quadcopter_ar8 --out docs",
        "bag": "bags/quadcopter_ar8",
        "runtime_s": 41.6,
        "data": {
            "attribution": "A Betaflight log.",
            "samples": 16977,
            "duration_s": 17.0449,
            "sample_step_ms": {"min": 0.9, "median": 1.0, "max": 1.25, "mean": 1.0},
        },
        "profile": PROFILE.to_dict(),
        "protocol": {"events": EventSpec().to_dict(), "phases": phases},
        "primary": fold(
            over_seeds=over_seeds,
            transfer={"band_hz": [80, 450], "median_gain_db": -1.5, "median_coherence": 0.95},
        ),
    }
    if keep_signals:
        out["primary"]["signals"] = signals()
    if swapped:
        out["swapped"] = fold(calibration_s=[8.5, 16.85], test_s=[0.0, 8.5])
    return out


# --- numbers -------------------------------------------------------------------
def test_fmt_rounds_and_says_na_for_missing_or_non_finite():
    assert fmt(12.345) == "12.3" and fmt(0.12345, 3) == "0.123"
    assert fmt(32.0, 0) == "32" and fmt(np.float64(-1.25), 2) == "-1.25"
    for missing in (None, float("nan"), float("inf"), -float("inf")):
        assert fmt(missing) == "n/a"


def test_comparison_values_are_the_single_set_or_the_means_over_sets():
    single = report.comparison_values(fold())
    assert list(single) == ["raw", "ours", "global", "mean_command", "notch_q5"]  # no firmware
    assert single["notch_q5"] == {
        "noise_reduction_db": 14.0,
        "tap_retention": 0.5,
        "peak_snr_improvement_db": 9.0,
        "f1": 0.8,
        "false_alarms_per_min": 0.5,
    }
    pooled = report.comparison_values(fold(over_seeds=OVER_SEEDS))
    assert list(pooled) == ["raw", "ours", "global"]
    # means, except F1: from the pooled counts
    assert pooled["ours"] == {
        "noise_reduction_db": 12.0,
        "tap_retention": 0.9,
        "peak_snr_improvement_db": 8.0,
        "f1": 0.82,
        "false_alarms_per_min": 1.0,
    }


def test_best_baseline_is_highest_f1_then_gain_among_the_baselines_present():
    assert report.best_baseline(fold()) == "notch_q5"  # F1 0.8 (ours and raw never count)
    assert report.best_baseline(fold(over_seeds=OVER_SEEDS)) == "global"  # the only one there
    tied = fold()
    tied["results"]["1"] = {
        **AT_1X,
        "global": row(f1=0.8 + 1e-9, peak_snr_improvement_db=9.5),  # equal F1 at 6 digits
    }
    assert report.best_baseline(tied) == "global"  # higher gain decides


# --- tables ----------------------------------------------------------------------
def test_table_has_a_row_per_method_in_order_and_the_firmware_last():
    lines = report.table(fold())
    assert lines[1] == "|" + "---|" * 15 and lines[0].count(" | ") == 14
    labels = [line.split(" | ")[0].removeprefix("| ") for line in lines[2:]]
    assert labels == [LABELS[n] for n in METHOD_NAMES] + [
        f"{FW}: filtered in flight, before any event"
    ]
    assert lines[3] == (
        f"| {LABELS['ours']} | 32 | 0.0100 | 12.0 | 0.050 | 0.900 | 0.90 | 20.0 | 8.0 | 0.123 "
        "| 0.80 | 0.80 | 0.80 | 0.85 | 1.0 |"
    )
    assert lines[5].split(" | ")[3] == "n/a"  # mean_command's noise reduction: nan
    assert lines[6].split(" | ")[-2] == "n/a"  # notch_q5's F1 +-30 ms: None
    assert lines[-1].endswith("| n/a | 0.0123 | 3.0 | 0.100 " + "| n/a " * 10 + "|")
    assert len(report.table(fold(firmware=False))) == 2 + len(METHOD_NAMES)


def test_pooled_table_gives_mean_and_range_and_is_empty_for_one_set():
    assert report.pooled_table(fold()) == []
    lines = report.pooled_table(fold(over_seeds=OVER_SEEDS))
    assert lines[0] == (
        "| method | noise red. dB | retention | peak-SNR gain dB | F1 pooled (30 events) "
        "| F1 per set | FA/min |"
    )
    assert lines[3] == (
        f"| {LABELS['ours']} | 12.0 (10.0-14.0) | 0.90 (0.85-0.95) | 8.0 (7.0-9.0) | 0.82 "
        "| 0.70-0.90 | 1.0 (0.5-1.5) |"
    )
    assert lines[-1] == f"| {FW} | 3.0 | n/a | n/a | n/a | n/a | n/a |"
    assert len(report.pooled_table(fold(over_seeds=OVER_SEEDS, firmware=False))) == 2 + 3


def test_amplitude_table_has_one_f1_and_one_gain_column_per_amplitude():
    lines = report.amplitude_table(fold(amplitudes=("0.5", "1", "2")))
    assert lines[0] == (
        "| method | F1 at 0.5x | F1 at 1x | F1 at 2x | gain dB at 0.5x | gain dB at 1x "
        "| gain dB at 2x |"
    )
    assert len(lines) == 2 + len(METHOD_NAMES)
    assert lines[3] == f"| {LABELS['ours']} | 0.20 | 0.80 | 0.80 | 2.0 | 8.0 | 8.0 |"


# --- sentences ---------------------------------------------------------------------
def test_where_baselines_win_names_every_metric_a_baseline_beats_ours_on():
    lines = report.where_baselines_win(fold())
    assert lines[:4] == [
        f"- {LABELS['raw']}: ours is as good or better on event F1 and false alarms here.",
        f"- {LABELS['global']} beats ours on event peak retention 0.95 vs ours 0.90.",
        f"- {LABELS['mean_command']}: ours is as good or better on every metric here.",
        f"- {LABELS['notch_q5']} beats ours on noise reduction 14.00 vs ours 12.00; "
        "peak-SNR gain 9.00 vs ours 8.00; false alarms per minute 0.50 vs ours 1.00.",
    ]  # F1 tied: no win; notch_q2 absent: no line
    assert lines[4] == (
        "- (d) the firmware's filtered gyro leaves 0.0123 rad/s of noise in the band "
        "(3.0 dB below raw), more than ours (0.0100 rad/s)."
    )
    assert len(lines) == 5


def test_where_raw_wins_only_f1_and_false_alarms_count():
    raw_better = fold(firmware=False)
    raw_better["results"]["1"] = {
        **{k: v for k, v in AT_1X.items() if k != "firmware"},
        "raw": row(noise_reduction_db=99.0, tap_retention=1.0, f1=0.9, false_alarms_per_min=0.0),
    }
    lines = report.where_baselines_win(raw_better)
    assert lines[0] == (
        f"- {LABELS['raw']} beats ours on event F1 0.90 vs ours 0.80; "
        "false alarms per minute 0.00 vs ours 1.00."
    )
    assert not any("firmware" in line for line in lines)


def test_the_firmware_sentence_says_less_and_adds_its_transfer_when_measured():
    quiet = fold(transfer={"band_hz": [80, 450], "median_gain_db": -1.5, "median_coherence": 0.95})
    quiet["results"]["1"] = {**AT_1X, "firmware": {**FIRMWARE, "noise_mean_denoised": 0.005}}
    assert report.where_baselines_win(quiet)[-1] == (
        "- (d) the firmware's filtered gyro leaves 0.0050 rad/s of noise in the band "
        "(3.0 dB below raw), less than ours (0.0100 rad/s). It is no event-preserving "
        "filter: its estimated transfer from the raw gyro (Welch cross-spectrum over the test "
        "part) has a median gain of -1.5 dB over 80-450 Hz (median coherence 0.95), so an "
        "event in the band would be cut about as much as the noise."
    )


# --- documents ---------------------------------------------------------------------
def test_markdown_sections_and_numbers_come_from_the_result():
    text = report.markdown(result())
    headings = [line for line in text.splitlines() if line.startswith("#")]
    assert headings == [
        "# On real data: a quadcopter's gyro and its four motors",
        "## Results: events at 1x, over 2 event sets (seeds 1, 2): mean (min-max)",
        "### Where a baseline wins (computed over the event sets)",
        "## Every metric, first event set (seed 1), 1x",
        "## Event F1 and peak-SNR gain vs event amplitude (x the paper's rule, first event set)",
        "## Swapped: calibrate on 8.5-16.85 s (hover only), test on 0-8.5 s",
        "## Figures",
    ]
    assert "`egovib real evaluate --bag bags/quadcopter_ar8 --out docs` (42 s)" in text
    assert "16977 samples in 17.04 s, steps 0.900-1.250 ms (median 1.000)." in text
    assert "4 one-directional joints, 10 steps, L = 32, hop 16, band 80-450 Hz." in text
    # protocol: the split, the motor commands (no "-0.00"), the events
    assert "Calibrate on 0-8.5 s (idle, take-off" in text and "motor commands 0.00-0.91);" in text
    assert "(hover with stick inputs, commands" in text and "left out of both." in text
    assert "15 known events" in text and "100-400 Hz, tau uniform in 4-12 ms" in text
    assert "(0.457 rad/s;" in text and "(seed 1)" in text
    assert "3 of 40 test blocks fell on cells the calibration never measured" in text
    assert "1 outside the grid." in text
    assert "7 of the 14641 cells" in text and "(median 9 blocks per cell" in text
    assert "f1 = 330 Hz x u^0.84 (21 windows, rms error 4.6 Hz)" in text
    assert f"Best baseline here (by event F1, then peak-SNR gain): {LABELS['global']}." in text
    for line in report.pooled_table(result()["primary"]) + report.table(result()["primary"]):
        assert line in text
    # the swapped fold has one event set: its full table stands in for the pooled one
    swapped = text.split("## Swapped")[1]
    assert report.table(result()["swapped"])[3] in swapped
    assert "motor commands 0.25-0.50, the calibration only" in swapped


def test_another_split_names_no_flight_phases():
    # The phases are those of the shipped flight at the default split: with another split
    # (egovib real evaluate --split/--end) they would describe the wrong seconds.
    text = report.markdown(result(phases=None)) + report.readme_section(result(phases=None))
    for phase in FLIGHT_PHASES.values():
        assert phase not in text
    assert "Calibrate on 0-8.5 s, motor commands 0.00-0.91; test on 8.5-16.85 s" in text
    assert "## Swapped: calibrate on 8.5-16.85 s, test on 0-8.5 s" in text
    assert "With the halves swapped ours gives 12.0 dB" in text


def test_markdown_without_event_sets_or_swapped_fold():
    text = report.markdown(result(swapped=False, over_seeds=None))
    assert "## Results" not in text and "## Swapped" not in text
    assert "### Where a baseline wins (computed)\n" in text
    assert f"Best baseline here (by event F1, then peak-SNR gain): {LABELS['notch_q5']}." in text


def test_readme_section_is_the_headline_table_and_the_worse_split():
    text = report.readme_section(result())
    assert text.startswith("### On real data (a quadcopter's gyro)\n")
    assert f"| {LABELS['ours']} | 12.0 | 0.90 | 8.0 | 0.82 | 1.0 |" in text
    assert f"| {FW} | 3.0 | n/a | n/a | n/a | n/a |" in text
    assert "Means over 2 event sets; F1 pooled." in text
    assert "ours gives 12.0 dB, gain 8.0 dB, F1 0.80: the worse figure." in text
    alone = report.readme_section(result(swapped=False, over_seeds=None))
    assert "Means over" not in alone and "the worse figure" not in alone
    assert f"| {LABELS['notch_q5']} | 14.0 | 0.50 | 9.0 | 0.80 | 0.5 |" in alone


def test_summary_text_lines_up_one_method_a_line():
    assert report.summary_text(result()).splitlines() == [
        "method         noise red dB  retention  gain dB    F1",
        "raw                     0.0       1.00      0.0  0.51",
        "ours                   12.0       0.90      8.0  0.82",
        "global                 13.0       0.70      5.0  0.60",
        "firmware                3.0   (noise only)",
    ]


def test_strip_signals_drops_arrays_and_makes_json_without_touching_the_input():
    full = result(keep_signals=True)
    full["swapped"]["signals"] = {"x": np.zeros(3)}
    out = report.strip_signals(full)
    assert "signals" not in out["primary"] and "signals" not in out["swapped"]
    assert "signals" in full["primary"] and "signals" in full["swapped"]
    assert out["primary"]["results"]["1"]["mean_command"]["noise_reduction_db"] is None  # nan
    assert json.loads(json.dumps(out, allow_nan=False)) == out


# --- figures and files -------------------------------------------------------------
def png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def test_figures_are_pngs_with_one_panel_per_signal():
    full = result(keep_signals=True)
    dpi = 110
    # spectrogram: raw, ours, best baseline, firmware: 11 x (2.4 x 4 + 0.6) in
    assert png_size(report.spectrogram_figure(full, PROFILE)) == (11 * dpi, round(10.2 * dpi))
    full["primary"]["signals"]["firmware"] = None  # no firmware gyro logged: one panel less
    assert png_size(report.spectrogram_figure(full, PROFILE)) == (11 * dpi, round(7.8 * dpi))
    assert png_size(report.timeseries_figure(full, PROFILE)) == (11 * dpi, 7 * dpi)
    assert png_size(report.methods_figure(full)) == (15 * dpi, round(4.8 * dpi))


def test_write_report_writes_every_file_from_the_same_result(tmp_path):
    full = result(keep_signals=True)
    written = report.write_report(full, PROFILE, tmp_path)
    assert written == [tmp_path / name for name in report.FILES.values()]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(report.FILES.values())
    assert (tmp_path / "real_results.md").read_text() == report.markdown(full)
    assert (tmp_path / "real_readme_section.md").read_text() == report.readme_section(full)
    assert json.loads((tmp_path / "real_results.json").read_text()) == report.strip_signals(full)
    for key in ("spectrogram", "timeseries", "methods"):
        png_size((tmp_path / report.FILES[key]).read_bytes())


@pytest.mark.parametrize("missing", ["blocks_unmeasured", "notch"])
def test_models_sentence_leaves_out_what_was_not_measured(missing):
    primary = fold()
    if missing == "notch":
        del primary["methods"]["notch_q5"]
    else:
        primary["methods"] = methods(unmeasured=False)
    text = report._models(primary)
    assert text.startswith("Ours: 7 of the 14641 cells")
    assert ("test blocks" in text) == (missing != "blocks_unmeasured")
    assert ("Notch map" in text) == (missing != "notch")
