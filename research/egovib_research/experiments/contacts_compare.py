"""Contact events side by side: the same detector on the raw signal, `paper` and `hybrid`.

    python -m egovib_research.experiments.contacts_compare --out DIR [--work DIR] [--event-sets 5]

The detector is `egovib detect`'s, called as the command calls it
(evaluation.contacts.detect_bag: the method's streaming denoiser, then core.contact's
detector; the threshold fixed beforehand from the no-contact calibration bag processed
the same way, at the run's joint speeds, 1.1 x its largest envelope, no false-alarm
budget). Every case is a bag on disk, as a user would have it:

- PR2, the demo's run: what `egovib demo` records, simulated offline (`egovib simulate
  sweep --grid superposition --dwell 1 --settle 0.3 --seed 1`; `egovib simulate motion
  --duration 30 --max-speed 0.5 --taps 2 --seed 7`), calibrated with `egovib calibrate
  --methods hybrid` on the sweep;
- PR2, README's offline sequence (sweep --dwell 2, motion --duration 60 --max-speed 0.5
  --taps 2, seed 0);
- the shipped quadcopter flight (bags/quadcopter_ar8), split as methods_compare splits it
  (primary: calibrate 0-8.5 s, test 8.5-16.85 s; swapped: the other way round), with
  known events added to the test part's real gyro by the methods comparison's injector
  (experiments.flight.events, at the project's rule and at half of it, `event_sets`
  seeds each), written as a bag with the events as its ground-truth topic.

Scores (against the ground truth, +-10 ms): F1, false alarms per minute, latency from a
tap's true onset to its event's report (the method's delay + the detector's 10 ms report
time), p50 / p99. With several event sets: F1 and false alarms from the pooled counts,
latency p50 the median of the sets' p50, p99 the largest of the sets' p99.

Why a method detects what it does, from the detection envelope of its output (the signal
the detector thresholds): noise reduction on it (no-contact samples, dB of power against
raw), each tap's envelope peak over raw's (retention, median), each tap's peak over the
method's threshold (margin, median; the share of taps above it is about the recall), and
the largest no-contact envelope of the run over the threshold (above 1: false alarms).
Writes DIR/contacts_compare.{md,json} and DIR/contacts_compare.png.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import logging
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egovib_research.experiments import python_command, scoring
from egovib_research.experiments.flight import ATTRIBUTION
from egovib_research.experiments.flight.events import EventSpec, make_events
from egovib_research.experiments.flight.methods_compare import SPLITS
from egovib_research.experiments.flight.recording import read_flight_bag
from egovib_ros.bag import Recording, read_recording, write_recording, write_recordings
from egovib_ros.bag.calibrate import calibrate_bag_methods, calibrate_bags
from egovib_ros.core.contact import THRESHOLD_MARGIN, ContactSettings, DetectionEnvelope
from egovib_ros.core.filters import combined_bandpassed
from egovib_ros.evaluation.contacts import (
    EDGE_S,
    check_detect_method,
    detect_bag,
    method_pieces,
)
from egovib_ros.evaluation.detection import scores_of
from egovib_ros.evaluation.metrics import json_safe, segment_contacts
from egovib_ros.robot import load_profile
from egovib_ros.sim.pr2 import ACCEL_FRAME
from egovib_ros.sim.scenarios import motion_slices, sweep_slices
from egovib_ros.viz import pyplot, save_figure

LOG = logging.getLogger("egovib_ros.contacts_compare")

METHODS = ("raw", "paper", "hybrid")
STRENGTHS = (1.0, 0.5)
FLIGHT_SPLITS = ("primary", "swapped")
SCORE_KEYS = (
    "f1",
    "precision",
    "recall",
    "false_alarms_per_min",
    "latency_ms_p50",
    "latency_ms_p99",
)
WHY_KEYS = (
    "noise_reduction_db",
    "tap_retention",
    "tap_margin",
    "taps_above",
    "noise_over_threshold",
)


@dataclass(frozen=True)
class Pr2Run:
    """A PR2 run as `egovib simulate` makes it: a sweep to calibrate on, a motion run with
    taps and ground truth."""

    label: str
    sweep_dwell_s: float
    sweep_settle_s: float
    sweep_seed: int
    motion_s: float
    motion_seed: int
    max_speed: float = 0.5
    tap_rate_hz: float = 2.0

    def commands(self) -> str:
        return (
            f"egovib simulate sweep --grid superposition --dwell {self.sweep_dwell_s:g} "
            f"--settle {self.sweep_settle_s:g} --seed {self.sweep_seed}; egovib simulate motion "
            f"--duration {self.motion_s:g} --max-speed {self.max_speed:g} "
            f"--taps {self.tap_rate_hz:g} --seed {self.motion_seed}"
        )


PR2_RUNS = {
    "pr2_demo": Pr2Run("PR2, the demo's run", 1.0, 0.3, 1, 30.0, 7),
    "pr2_readme": Pr2Run("PR2, README's offline sequence", 2.0, 1.0, 0, 60.0, 0),
}
QUICK_PR2_RUNS = {"pr2_demo": Pr2Run("PR2, short run", 0.4, 0.2, 1, 4.0, 7)}


# --------------------------------------------------------------------------------------
# One detection and why
# --------------------------------------------------------------------------------------
def _envelope(values: np.ndarray, model) -> np.ndarray:
    settings = ContactSettings(
        sample_rate_hz=model.sample_rate_hz,
        band_hz=model.band_hz,
        band_order=model.band_order,
        threshold=1.0,
    )
    return DetectionEnvelope(settings).process(values)[1]


def method_output(bag, model, method: str) -> tuple:
    """(stamps (N,), values (N, 3), ground truth (N, 3) or None): what `detect_bag` feeds
    its detector on `bag`, whole; for looking at why a method detects what it does."""
    method = check_detect_method(model, method)
    stamps, values, truth = [], [], []
    for s, v, contact, _ in method_pieces(bag, model, method, ground_truth=True):
        stamps.append(s)
        values.append(v)
        if contact is not None:
            truth.append(contact)
    stamps_all = np.concatenate(stamps) if stamps else np.zeros(0, np.int64)
    values_all = np.concatenate(values) if values else np.zeros((0, 3))
    contact_all = np.concatenate(truth) if truth else None
    if contact_all is not None and len(contact_all) != len(stamps_all):
        contact_all = None
    return stamps_all, values_all, contact_all


def run_method(bag: Path, calibration: Path, model, method: str) -> dict:
    """`egovib detect` on `bag` (threshold from `calibration`), with its scores and the
    detection envelope of what the detector saw."""
    detection = detect_bag(bag, model=model, method=method, calibration=calibration)
    stamps, values, contact = method_output(bag, model, method)
    if detection.scores is None or contact is None:
        raise RuntimeError(f"{bag}: no ground truth to score against")
    return {
        "detection": detection,
        "stamps": stamps,
        "envelope": _envelope(values, model),
        "contact": contact,
    }


def threshold_origin(calibration: Path, model, method: str, threshold: float) -> dict:
    """Where in the no-contact calibration recording the method's threshold came from:
    the sample whose envelope x the margin is the threshold (no false-alarm budget), its
    time, the joint velocity held there and the time since the last commanded change (if
    the bag has commands); and how far the threshold sits above that recording's median
    envelope."""

    stamps, values, _ = method_output(calibration, model, method)
    envelope = _envelope(values, model)
    edge = int(EDGE_S * model.sample_rate_hz)
    inner = envelope[edge:-edge]
    at = edge + int(np.argmin(np.abs(inner - threshold / THRESHOLD_MARGIN)))
    rec = read_recording(
        calibration, profile=model.robot_profile(), ground_truth=False, denoised=False
    )
    held = max(0, int(np.searchsorted(rec.joint_stamps_ns, stamps[at], side="right")) - 1)
    origin = {
        "threshold_over_calibration_median": float(threshold / np.median(inner)),
        "t_s": float(stamps[at] - stamps[0]) / 1e9,
        "joint_velocity": [round(float(v), 3) for v in rec.joint_velocity[held]],
        "since_command_change_s": None,
    }
    if rec.commands is not None and len(rec.commands) > 1:
        changed = np.flatnonzero(np.any(np.diff(rec.commands, axis=0) != 0, axis=1)) + 1
        before = rec.command_stamps_ns[changed][rec.command_stamps_ns[changed] <= stamps[at]]
        if len(before):
            origin["since_command_change_s"] = float(stamps[at] - before[-1]) / 1e9
    return origin


def why(runs: dict, model) -> dict:
    """Per method: what its detection envelope shows against raw's (see the module doc)."""
    raw = runs["raw"]
    reference = combined_bandpassed(raw["contact"], model.robot_profile())
    seg = segment_contacts(reference, sample_rate_hz=model.sample_rate_hz)
    quiet = seg.no_contact_mask
    raw_peaks = scoring.tap_peaks(raw["envelope"], seg.tap_windows)
    out = {"_onsets_ns": raw["stamps"][seg.onsets]}
    for method, run in runs.items():
        if not np.array_equal(run["stamps"], raw["stamps"]):
            raise RuntimeError(f"method {method}: output stamps differ from the input's")
        envelope, threshold = run["envelope"], run["detection"].threshold
        peaks = scoring.tap_peaks(envelope, seg.tap_windows)
        power = np.mean(envelope[quiet] ** 2)
        at = np.searchsorted(run["stamps"], [e.onset_ns for e in run["detection"].events])
        in_quiet = int(np.count_nonzero(quiet[np.clip(at, 0, len(quiet) - 1)]))
        out[method] = {
            "noise_reduction_db": float(
                10 * np.log10(np.mean(raw["envelope"][quiet] ** 2) / power)
            ),
            "tap_retention": float(np.median(peaks / raw_peaks)) if len(peaks) else None,
            "tap_margin": float(np.median(peaks / threshold)) if len(peaks) else None,
            "taps_above": float(np.mean(peaks > threshold)) if len(peaks) else None,
            "noise_over_threshold": float(envelope[quiet].max() / threshold),
            # reports in no-contact time; the other false alarms fall near a tap (a second
            # report of one tap, or an onset more than the tolerance away from it)
            "fp_in_quiet": in_quiet,
        }
    return out


def summary(runs: dict, whys: dict) -> dict:
    """One row per method: the detection's scores and threshold, and why."""
    rows = {}
    for method, run in runs.items():
        d = run["detection"]
        rows[method] = {
            **{k: d.scores[k] for k in (*SCORE_KEYS, "tp", "fp", "fn", "n_taps")},
            "fp_near_taps": max(0, d.scores["fp"] - whys[method]["fp_in_quiet"]),
            "threshold": d.threshold,
            "method_delay_ms": d.method_delay_ms,
            "minutes": d.duration_s / 60.0,
            **whys[method],
        }
    return rows


def pool(sets: list[dict]) -> dict:
    """Rows of several event sets as one: counts pooled, F1 and false alarms from them;
    latency p50 the median of the sets', p99 the largest; the rest averaged."""
    out = {}
    for method in sets[0]:
        rows = [s[method] for s in sets]
        tp, fp, fn, near = (sum(r[k] for r in rows) for k in ("tp", "fp", "fn", "fp_near_taps"))
        minutes = sum(r["minutes"] for r in rows)
        scores = scores_of(tp, fp, fn)
        p50 = [r["latency_ms_p50"] for r in rows if r["latency_ms_p50"] is not None]
        p99 = [r["latency_ms_p99"] for r in rows if r["latency_ms_p99"] is not None]
        out[method] = {
            "f1": scores["f1"],
            "precision": scores["precision"],
            "recall": scores["recall"],
            "false_alarms_per_min": fp / minutes if minutes else None,
            "latency_ms_p50": float(np.median(p50)) if p50 else None,
            "latency_ms_p99": float(np.max(p99)) if p99 else None,
            "tp": tp,
            "fp": fp,
            "fn": fn,
            "fp_near_taps": near,
            "n_taps": sum(r["n_taps"] for r in rows),
            "minutes": minutes,
            "method_delay_ms": rows[0]["method_delay_ms"],
            "threshold": float(np.mean([r["threshold"] for r in rows])),
            **{
                k: float(np.mean([r[k] for r in rows if r[k] is not None]))
                for k in WHY_KEYS
                if any(r[k] is not None for r in rows)
            },
        }
    return out


# --------------------------------------------------------------------------------------
# PR2
# --------------------------------------------------------------------------------------
def pr2_case(name: str, run: Pr2Run, work: Path, keep_trace: bool) -> tuple[dict, dict | None]:
    profile = load_profile(None)
    sweep, motion = work / f"{name}_sweep", work / f"{name}_motion"
    slices, _ = sweep_slices(
        grid="superposition",
        dwell_s=run.sweep_dwell_s,
        settle_s=run.sweep_settle_s,
        seed=run.sweep_seed,
    )
    write_recordings(sweep, slices, profile=profile, frame_id=ACCEL_FRAME)
    slices, truth = motion_slices(
        duration_s=run.motion_s,
        max_speed=run.max_speed,
        tap_rate_hz=run.tap_rate_hz,
        seed=run.motion_seed,
    )
    write_recordings(motion, slices, profile=profile, frame_id=ACCEL_FRAME)
    model = calibrated(sweep, profile)
    runs = {m: run_method(motion, sweep, model, m) for m in METHODS}
    whys = why(runs, model)
    rows = summary(runs, whys)
    for m, r in runs.items():
        rows[m]["threshold_origin"] = threshold_origin(sweep, model, m, r["detection"].threshold)
    case = {
        "label": run.label,
        "data": run.commands(),
        "calibration": "egovib calibrate SWEEP --methods hybrid",
        "duration_s": run.motion_s,
        "taps": len(truth["tap_onsets_ns"]),
        "results": rows,
    }
    return case, (trace(runs, whys["_onsets_ns"]) if keep_trace else None)


def calibrated(bag: Path, profile):
    """`egovib calibrate BAG --methods hybrid` (grid auto)."""
    model, _, results = calibrate_bags([bag], profile=profile, sweep="auto")
    if model is None:
        raise RuntimeError(f"{bag}: calibration failed: {results[0].error}")
    model, _ = calibrate_bag_methods(bag, model)
    return model


def trace(runs: dict, onsets_ns: np.ndarray) -> dict:
    """What the figure's example trace needs: envelopes, thresholds, true and found onsets."""
    raw = runs["raw"]
    return {
        "t0_ns": int(raw["stamps"][0]),
        "stamps": raw["stamps"],
        "onsets_ns": onsets_ns,
        "methods": {
            m: {
                "envelope": r["envelope"],
                "threshold": r["detection"].threshold,
                "onsets_ns": [e.onset_ns for e in r["detection"].events],
            }
            for m, r in runs.items()
        },
    }


# --------------------------------------------------------------------------------------
# Flight
# --------------------------------------------------------------------------------------
def _as_recording(part, contact=None) -> Recording:
    return Recording(
        sensor_stamps_ns=part.sensor_stamps_ns,
        sensor=part.sensor,
        joint_stamps_ns=part.joint_stamps_ns,
        joint_position=part.joint_position,
        joint_velocity=part.joint_velocity,
        joint_names=tuple(part.joint_names),
        contact=contact,
    )


def flight_case(
    bag: str, split: str, work: Path, event_sets: int, test_s: tuple | None = None
) -> dict:
    profile = load_profile("quadcopter")
    rec = read_flight_bag(bag, profile)
    (c0, c1), (t0, t1) = SPLITS[split]
    if test_s is not None:
        t0, t1 = test_s
    cal, test = rec.part(c0, c1), rec.part(t0, t1)
    cal_bag = work / f"flight_{split}_calibration"
    write_recording(cal_bag, _as_recording(cal), profile=profile)
    model = calibrated(cal_bag, profile)
    results, origins = {}, {}
    for strength in STRENGTHS:
        sets = []
        for seed in range(1, event_sets + 1):
            events = make_events(
                test.sensor_stamps_ns,
                test.sensor,
                profile,
                spec=EventSpec(relative_amplitude=strength, seed=seed),
            )
            test_bag = work / f"flight_{split}_events_{strength:g}_{seed}"
            noisy = dataclasses.replace(test, sensor=test.sensor + events.signal)
            write_recording(test_bag, _as_recording(noisy, events.signal), profile=profile)
            runs = {m: run_method(test_bag, cal_bag, model, m) for m in METHODS}
            sets.append(summary(runs, why(runs, model)))
            for m, r in runs.items():  # the same for every event set: same data, same speeds
                if m not in origins:
                    origins[m] = threshold_origin(cal_bag, model, m, r["detection"].threshold)
            shutil.rmtree(test_bag)
        results[f"{strength:g}"] = pool(sets)
        for m in METHODS:
            results[f"{strength:g}"][m]["threshold_origin"] = origins[m]
        LOG.info("flight %s, events at %gx: done", split, strength)
    return {
        "label": f"quadcopter flight, {split} split",
        "data": f"{bag}: calibrate {c0:g}-{c1:g} s, test {t0:g}-{t1:g} s, events added",
        "calibration": "egovib calibrate CALIBRATION_PART --robot quadcopter --methods hybrid",
        "event_sets": event_sets,
        "results": results,
    }


# --------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------
def _f(value, digits: int = 2) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def table(rows: dict) -> list[str]:
    lines = [
        "| method | delay ms | F1 | precision / recall | false alarms /min (near a tap) "
        "| latency p50 / p99 ms "
        "| noise red. dB | tap retention | tap peak / threshold | taps above threshold "
        "| run's no-contact max / threshold | threshold / calibration median |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for method, r in rows.items():
        lines.append(
            f"| {method} | {r['method_delay_ms']:.1f} | {_f(r['f1'])} | "
            f"{_f(r['precision'])} / {_f(r['recall'])} | "
            f"{_f(r['false_alarms_per_min'], 1)} ({r['fp_near_taps']}) | "
            f"{_f(r['latency_ms_p50'], 1)} / {_f(r['latency_ms_p99'], 1)} | "
            f"{_f(r['noise_reduction_db'], 1)} | {_f(r['tap_retention'])} | "
            f"{_f(r['tap_margin'])} | {_f(r['taps_above'])} | {_f(r['noise_over_threshold'])} | "
            f"{_f(r['threshold_origin']['threshold_over_calibration_median'], 0)} |"
        )
    return lines


def costs(result: dict) -> list[str]:
    """One line per (case, method) where denoising lowered F1 below raw's, with the figures
    that say why."""

    def height(row: dict) -> float:
        return row["threshold_origin"]["threshold_over_calibration_median"]

    lines = []
    for name, rows in _rows(result):
        raw = rows["raw"]
        for method in METHODS[1:]:
            r = rows[method]
            if r["f1"] >= raw["f1"] - 0.005:
                continue
            origin = r["threshold_origin"]
            where = f"t = {origin['t_s']:.2f} s of the calibration data"
            if origin["since_command_change_s"] is not None:
                where += f", {origin['since_command_change_s']:.2f} s after a commanded speed step"
            causes = []
            if r["taps_above"] < raw["taps_above"] - 0.02:
                causes.append(
                    f"fewer taps clear its threshold ({raw['taps_above']:.2f} -> "
                    f"{r['taps_above']:.2f}): the taps' envelope kept {r['tap_retention']:.2f} of "
                    f"raw's, and the threshold sits {height(r):.0f} x the calibration data's "
                    f"median envelope (raw: {height(raw):.0f} x), set "
                    f"by one burst ({where})"
                )
            if (
                r["noise_over_threshold"] > 1
                and r["false_alarms_per_min"] > (raw["false_alarms_per_min"])
            ):
                causes.append(
                    f"the run's no-contact envelope reaches {r['noise_over_threshold']:.1f} x the "
                    f"threshold (raw {raw['noise_over_threshold']:.1f} x): noise the calibration "
                    f"data never showed (speeds it did not cover) makes false alarms"
                )
            if r["recall"] < r["taps_above"] - 0.02:
                causes.append(
                    f"taps over the threshold ({r['taps_above']:.2f}) not all hit (recall "
                    f"{r['recall']:.2f}): a tap within 50 ms of an earlier report is merged into "
                    f"it, or its onset is found more than 10 ms off"
                )
            lines.append(
                f"- {name}, {method}: F1 {raw['f1']:.2f} raw -> {r['f1']:.2f} (recall "
                f"{raw['recall']:.2f} -> {r['recall']:.2f}, false alarms "
                f"{raw['false_alarms_per_min']:.1f} -> {r['false_alarms_per_min']:.1f}/min, "
                f"noise down {r['noise_reduction_db']:.1f} dB). "
                + (_sentence("; ".join(causes)) if causes else "A tap or two.")
            )
    return lines or ["- none: no method lowered F1 below the raw signal's in these runs."]


def _sentence(text: str) -> str:
    return text[:1].upper() + text[1:] + "."


def _rows(result: dict):
    for case in result["pr2"].values():
        yield case["label"], case["results"]
    for case in result["flight"].values():
        for strength, rows in case["results"].items():
            yield f"{case['label']}, events {strength}x", rows


NOTES = [
    "## How to read it",
    "",
    "- The threshold of each method comes from its own output on no-contact data (the",
    "  calibration recording, at the run's joint speeds): 1.1 x the largest envelope there.",
    "  A method that removes most of the noise but leaves one burst on the calibration data",
    "  (a speed step, a reversal) gets a threshold set by that burst, not by its typical",
    "  noise ('threshold / calibration median' large; the JSON's threshold_origin gives the",
    "  burst's time, joint velocity and time since the last commanded step); 'run's",
    "  no-contact max / threshold' well below 1 then means the threshold sits far above the",
    "  run's noise, and the taps must clear it. Above 1: the run is noisier than anything the",
    "  calibration data showed, and false alarms follow.",
    "- Retention: denoising also takes part of each tap ('tap retention' < 1). If the",
    "  noise falls by less than the taps do near the threshold, taps end below it ('taps",
    "  above threshold' < raw's) and F1 drops although the noise went down.",
    "- Latency: the method's algorithmic delay (paper: a block, L - 1 samples) plus the",
    "  detector's report time (10 ms after the crossing).",
    "- A detection within +-10 ms of a true onset is a hit; so a method whose onsets move",
    "  by more than that (a block's smearing) loses hits it did see.",
    "",
]


def markdown(result: dict) -> str:
    out = [
        "# Contact events: raw, `paper`, `hybrid` through the same detector",
        "",
        f"Regenerate: `{result['command']}` ({result['runtime_s']:.0f} s). The detector is "
        "`egovib detect`'s (evaluation.contacts.detect_bag; thresholds from no-contact data, "
        "no false-alarm budget). Flight data: " + result["attribution"],
        "",
    ]
    for case in result["pr2"].values():
        out += [
            f"## {case['label']}: {case['duration_s']:g} s, {case['taps']} taps",
            "",
            f"Data: `{case['data']}`; model: `{case['calibration']}`.",
            "",
            *table(case["results"]),
            "",
        ]
    for case in result["flight"].values():
        out += [f"## {_sentence(case['label'])[:-1]}", "", f"Data: {case['data']}.", ""]
        for strength, rows in case["results"].items():
            n = rows["raw"]["n_taps"]
            out += [
                f"Events at {strength}x the project's rule ({case['event_sets']} event sets, "
                f"{n} events in all):",
                "",
                *table(rows),
                "",
            ]
    out += ["## Where denoising costs detection", "", *costs(result), "", *NOTES]
    return "\n".join(out)


def figure(result: dict, example: dict | None, path: Path) -> Path:
    plt = pyplot()

    colors = {"raw": "grey", "paper": "tab:blue", "hybrid": "tab:red"}
    fig = plt.figure(figsize=(13, 7))
    grid = fig.add_gridspec(3, 2, width_ratios=(1, 1.6))
    ax = fig.add_subplot(grid[:, 0])
    markers = iter("osD^v<>ph*")
    for name, rows in _rows(result):
        marker = next(markers, "o")
        xs = [rows[m]["noise_reduction_db"] for m in METHODS]
        ys = [rows[m]["f1"] for m in METHODS]
        ax.plot(xs, ys, color="0.8", lw=0.8, zorder=1)
        for m, x, y in zip(METHODS, xs, ys):
            ax.scatter(x, y, color=colors[m], marker=marker, zorder=2)
        ax.scatter([], [], color="k", marker=marker, label=name)
    for m in METHODS:
        ax.scatter([], [], color=colors[m], label=m)
    ax.set_xlabel("noise reduction on the detection envelope (dB, no-contact)")
    ax.set_ylabel("event F1 (+-10 ms)")
    ax.set_ylim(-0.02, 1.02)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2)
    ax.set_title("F1 against noise reduction, one point per method and case", fontsize=9)
    if example is not None:
        t = (np.asarray(example["stamps"]) - example["t0_ns"]) / 1e9
        window = (t >= 2.0) & (t < 5.0)
        onsets = (np.asarray(example["onsets_ns"]) - example["t0_ns"]) / 1e9
        for row, m in enumerate(METHODS):
            axm = fig.add_subplot(grid[row, 1])
            data = example["methods"][m]
            axm.plot(t[window], data["envelope"][window], color=colors[m], lw=0.7)
            axm.axhline(data["threshold"], color="k", ls="--", lw=0.8, label="threshold")
            for o in onsets[(onsets >= 2.0) & (onsets < 5.0)]:
                axm.axvline(o, color="g", lw=0.8, alpha=0.6)
            found = (np.asarray(data["onsets_ns"]) - example["t0_ns"]) / 1e9
            found = found[(found >= 2.0) & (found < 5.0)]
            axm.plot(found, np.full(len(found), data["threshold"]), "kv", ms=5, label="event")
            axm.set_ylabel(f"{m}\nenvelope")
            axm.set_yscale("log")
            if row == 0:
                axm.set_title(
                    f"{example['label']}: detection envelope, threshold (dashed), true onsets "
                    "(green), events (triangles)",
                    fontsize=9,
                )
                axm.legend(fontsize=7, loc="upper right")
        axm.set_xlabel("s into the run")
    return save_figure(fig, path)


# --------------------------------------------------------------------------------------
# Driver
# --------------------------------------------------------------------------------------
def run(
    out_dir: Path,
    *,
    work: Path | None = None,
    quick: bool = False,
    event_sets: int = 5,
    bag: str = "bags/quadcopter_ar8",
    command: str = "",
) -> dict:
    begin = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    if work is None:
        scratch = tempfile.TemporaryDirectory(prefix="egovib-contacts-")
    else:
        work.mkdir(parents=True, exist_ok=True)
        scratch = contextlib.nullcontext(str(work))
    with scratch as where:
        work = Path(where)
        result = {"command": command, "attribution": ATTRIBUTION, "pr2": {}, "flight": {}}
        example = None
        for name, pr2_run in (QUICK_PR2_RUNS if quick else PR2_RUNS).items():
            LOG.info("%s", pr2_run.label)
            case, tr = pr2_case(name, pr2_run, work, keep_trace=example is None)
            result["pr2"][name] = case
            if tr is not None:
                example = {**tr, "label": pr2_run.label}
        for split in FLIGHT_SPLITS[:1] if quick else FLIGHT_SPLITS:
            LOG.info("flight, %s split", split)
            result["flight"][split] = flight_case(
                bag, split, work, 1 if quick else event_sets, (8.5, 11.0) if quick else None
            )
    result["runtime_s"] = time.perf_counter() - begin
    figure(result, example, out_dir / "contacts_compare.png")
    (out_dir / "contacts_compare.json").write_text(json.dumps(json_safe(result), indent=1) + "\n")
    (out_dir / "contacts_compare.md").write_text(markdown(result))
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="directory for contacts_compare.*")
    parser.add_argument("--work", default=None, help="keep the bags here (default: a temp dir)")
    parser.add_argument("--bag", default="bags/quadcopter_ar8", help="the flight bag")
    parser.add_argument("--event-sets", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="tiny runs (for tests)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("egovib_ros.core").setLevel(logging.ERROR)
    out = Path(args.out)
    result = run(
        out,
        work=Path(args.work) if args.work else None,
        quick=args.quick,
        event_sets=args.event_sets,
        bag=args.bag,
        command=python_command("egovib_research.experiments.contacts_compare", argv),
    )
    print(markdown(result))
    print(
        f"wrote {out / 'contacts_compare.md'}, {out / 'contacts_compare.json'}, "
        f"{out / 'contacts_compare.png'}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
