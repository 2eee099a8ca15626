"""The real-flight experiment: the paper's experiment (b) on a quadcopter's gyro.

    egovib real evaluate --bag bags/quadcopter_ar8 --out docs

1. Read the bag with the quadcopter profile (gyro in `angular_velocity`, 4 motors).
2. Split the flight: calibrate on the first part, [0, split_s) - idle on the ground,
   take-off, hover, both punch-outs and flips: free motion, no contact - and test on
   [split_s, end_s), mostly hover with stick inputs. The log's last 0.15 s (from 16.9 s:
   motors cut, gyro jumps to 215 deg/s, a crash or hard landing) is no free motion and
   no known event, so it is left out of both parts.
3. Fit every method on the calibration part only (noise tables, the notch map).
4. Detection thresholds: each method's own output on the calibration part, restricted
   to the motor speeds the test part reaches (its motor commands only, never its gyro),
   edges dropped; threshold = 1.1 x the largest 4 ms RMS envelope
   (egovib_ros.evaluation.detection). Never tuned on the test part.
5. Add known contact-like events to the test part's real gyro signal (events.py: form,
   amplitude relative to the noise, timing), run every method, score with
   egovib_ros.evaluation.metrics/detection: noise outside events, event peak retention,
   peak SNR and its gain, event P/R/F1 (+-10 ms), at 0.5x, 1x (primary) and 2x the
   paper's amplitude rule.
6. Baseline (d): the firmware's own filtered gyro (logged beside the raw one). Its
   filters ran in flight, before any event could be added, so only its noise level
   outside events is comparable.
7. The same with the parts swapped (calibrate on the second part, test on the first):
   a test with motor speeds the calibration never saw. Both are reported; the worse
   figure is the one to quote.

Writes DIR/real_results.md, DIR/real_results.json, DIR/real_spectrogram.png,
DIR/real_methods.png (each file complete or absent).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import shlex
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import signal as sps

from egovib_research.experiments import scoring
from egovib_research.experiments.flight import ATTRIBUTION
from egovib_research.experiments.flight import report as report_module
from egovib_research.experiments.flight.events import EventSpec, make_events
from egovib_research.experiments.flight.methods import (
    LABELS,
    METHODS,
    build_methods,
)
from egovib_research.experiments.flight.recording import FlightRecording, read_flight_bag
from egovib_ros.core.filters import combined_bandpassed
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import ConfigError
from egovib_ros.evaluation import detection, metrics
from egovib_ros.outputs import prepare_outputs_in
from egovib_ros.robot import RobotProfile, load_profile

SCHEMA = "egovib.real/1"
PRIMARY_AMPLITUDE = 1.0
# also scored: an event found up to 30 ms off (IIR notches ring and delay)
LENIENT_TOLERANCE_S = 0.030
SCORES = ("f1", "precision", "recall", "tp", "fp", "fn", "threshold")  # of the detector, per row


#: What happens in the shipped flight's parts at the default split (the report tells it only
#: for that split: other splits hold other phases).
FLIGHT_PHASES = {
    "calibration": "idle, take-off, hover, both punch-outs and flips: free motion",
    "test": "hover with stick inputs",
    "left_out": "the final impact at 16.9 s is left out of both",
    "swapped_calibration": "hover only",
    "swapped_test": "idle on the ground, take-off, punch-outs and flips",
}


@dataclass
class RealConfig:
    split_s: float = 8.5  # calibration = [start, split), test = [split, end)
    end_s: float | None = 16.85  # None: to the end of the recording
    events: EventSpec = field(default_factory=EventSpec)
    amplitudes: tuple[float, ...] = (0.5, 1.0, 2.0)
    methods: tuple[str, ...] = METHODS
    swapped: bool = True  # also calibrate on the test part and test on the calibration part
    # Event sets at the primary amplitude (seeds seed, seed + 1, ...): about 15 events each,
    # so one set decides F1 by single events; the pooled table uses them all.
    event_sets: int = 5

    def __post_init__(self) -> None:
        if self.event_sets < 1:
            raise ConfigError(f"event sets must be at least 1, got {self.event_sets}")
        if PRIMARY_AMPLITUDE not in self.amplitudes:
            self.amplitudes = tuple(sorted(set(self.amplitudes) | {PRIMARY_AMPLITUDE}))
        if "raw" not in self.methods:
            self.methods = ("raw",) + tuple(self.methods)


def speed_envelope_mask(calibration, rec, margin: float = 1.05) -> np.ndarray:
    """Calibration accelerometer samples whose joint speeds stay within the largest joint
    speeds of `rec` (per joint, times `margin`)."""
    limit = np.nanmax(np.abs(rec.joint_velocity), axis=0) * margin
    mask = np.ones(len(calibration.sensor_stamps_ns), bool)
    for j in range(calibration.joint_velocity.shape[1]):
        speed = np.interp(
            calibration.sensor_stamps_ns,
            calibration.joint_stamps_ns,
            np.abs(calibration.joint_velocity[:, j]),
        )
        mask &= speed <= limit[j]
    return mask


def calibration_mask(cal, test, fs: float) -> np.ndarray:
    """The calibration samples a detection threshold is taken on: the edges dropped, and
    then only those at joint speeds the test part reaches if a second of them is left."""
    n = len(cal.sensor_stamps_ns)
    edge = min(int(metrics.EDGE_S * fs), n // 4)
    mask = np.ones(n, bool)
    mask[:edge] = False
    mask[n - edge :] = False
    within = speed_envelope_mask(cal, test)
    if np.count_nonzero(mask & within) >= fs:
        mask &= within
    return mask


def score_events(
    fitted: dict,
    thresholds: dict,
    test: FlightRecording,
    profile: RobotProfile,
    spec: EventSpec,
    firmware_bp: np.ndarray | None,
    *,
    keep_signals: bool = False,
) -> dict:
    """Add one set of events to the test part, run every fitted method, score it."""
    fs = profile.rate_hz
    t0 = int(test.sensor_stamps_ns[0])
    events = make_events(test.sensor_stamps_ns, test.sensor, profile, spec=spec)
    noisy = dataclasses.replace(test, sensor=test.sensor + events.signal)
    reference = combined_bandpassed(events.signal, profile)
    seg = metrics.segment_contacts(reference, sample_rate_hz=fs)
    truth = seg.onsets
    raw = combined_bandpassed(noisy.sensor, profile)
    minutes = len(test.sensor_stamps_ns) / fs / 60.0
    rows, signals = {}, {}
    for name, method in fitted.items():
        output = method.run(noisy)
        envelope = scoring.envelope(output, sample_rate_hz=fs)
        row = scoring.signal_metrics(raw, output, reference, seg)
        scores = scoring.evaluate_detector(envelope, truth, thresholds[name], sample_rate_hz=fs)
        lenient = scoring.evaluate_detector(
            envelope, truth, thresholds[name], sample_rate_hz=fs, tolerance_s=LENIENT_TOLERANCE_S
        )
        row.update({key: scores[key] for key in SCORES})
        row.update(
            false_alarms=scores["fp"],
            false_alarms_per_min=scores["fp"] / minutes,
            f1_30ms=lenient["f1"],
        )
        rows[name] = row
        if keep_signals:
            signals[name] = output
    if firmware_bp is not None:
        noise_fw = scoring.noise_mean(firmware_bp, seg.no_contact_mask)
        rows["firmware"] = {
            "noise_mean_raw": rows["raw"]["noise_mean_raw"],
            "noise_mean_denoised": noise_fw,
            "noise_reduction_db": metrics.db20(rows["raw"]["noise_mean_raw"] / noise_fw),
            "noise_spike_raw": rows["raw"]["noise_spike_raw"],
            "noise_spike_denoised": scoring.noise_spike(firmware_bp, seg.no_contact_mask),
        }
    info = {
        "seed": spec.seed,
        "n_events": int(len(events.onsets)),
        "n_taps_segmented": seg.n_taps,
        "target_peak_rad_s": events.target_peak,
        "onsets_s": ((events.onset_ns - t0) / NS_PER_S).round(4).tolist(),
        "axis": events.axis.tolist(),
        "frequency_hz": events.frequency_hz.round(1).tolist(),
        "decay_ms": (1e3 * events.decay_s).round(2).tolist(),
        "amplitude_rad_s": events.amplitude.round(5).tolist(),
    }
    if keep_signals:
        signals.update(
            raw_input=raw,
            reference=reference,
            seg=seg,
            stamps_ns=test.sensor_stamps_ns,
            firmware=firmware_bp,
        )
    return {"rows": rows, "events": info, "signals": signals}


def firmware_transfer(test: FlightRecording, profile: RobotProfile, nperseg: int = 128) -> dict:
    """How the firmware's filters treat the band: |H| = |P_xy / P_xx| from raw to filtered gyro and
    their coherence (Welch, per axis, then averaged in dB / linearly), summarised over the band."""

    fs = profile.rate_hz
    gains, coherences = [], []
    for axis in range(3):
        x, y = test.sensor[:, axis], test.filtered[:, axis]
        freqs, pxy = sps.csd(x, y, fs=fs, nperseg=nperseg)
        _, pxx = sps.welch(x, fs=fs, nperseg=nperseg)
        _, coherence = sps.coherence(x, y, fs=fs, nperseg=nperseg)
        gains.append(20 * np.log10(np.abs(pxy) / np.maximum(pxx, 1e-30) + 1e-30))
        coherences.append(coherence)
    gain_db, coherence = np.mean(gains, axis=0), np.mean(coherences, axis=0)
    band = (freqs >= profile.band_hz[0]) & (freqs <= profile.band_hz[1])
    return {
        "band_hz": list(profile.band_hz),
        "median_gain_db": float(np.median(gain_db[band])),
        "median_coherence": float(np.median(coherence[band])),
        "freqs_hz": freqs.round(2).tolist(),
        "gain_db": gain_db.round(1).tolist(),
        "coherence": coherence.round(3).tolist(),
    }


POOLED = (
    "noise_reduction_db",
    "tap_retention",
    "peak_snr_improvement_db",
    "f1",
    "false_alarms_per_min",
)


def pool_seeds(per_seed: list[dict], seeds: list[int]) -> dict:
    """Per method over event sets: mean/min/max of the main metrics, and F1 from pooled counts."""
    pooled = {"seeds": list(seeds), "methods": {}}
    for name in per_seed[0]:
        if name == "firmware":
            continue
        entry = {}
        for key in POOLED:
            values = np.array([rows[name][key] for rows in per_seed], float)
            entry[key] = {
                "mean": float(values.mean()),
                "min": float(values.min()),
                "max": float(values.max()),
            }
        tp, fp, fn = (sum(rows[name][k] for rows in per_seed) for k in ("tp", "fp", "fn"))
        entry["f1_pooled"] = detection.scores_of(tp, fp, fn)["f1"]
        entry["events"] = int(tp + fn)
        pooled["methods"][name] = entry
    return pooled


def run_fold(
    rec: FlightRecording,
    profile: RobotProfile,
    calibration_s: tuple[float, float],
    test_s: tuple[float, float],
    config: RealConfig,
    *,
    keep_signals: bool = False,
) -> dict:
    """Calibrate on one time range, test on another; every method, every event amplitude."""
    fs = profile.rate_hz
    t0 = int(rec.sensor_stamps_ns[0])
    cal, test = rec.part(*calibration_s), rec.part(*test_s)
    for part, name in ((cal, "calibration"), (test, "test")):
        if len(part.sensor_stamps_ns) < 4 * profile.block_length or len(part.joint_stamps_ns) == 0:
            raise ConfigError(
                f"{name} part {calibration_s if name == 'calibration' else test_s} s holds "
                f"{len(part.sensor_stamps_ns)} samples: too short"
            )

    fitted = build_methods(profile, config.methods)
    cal_mask = calibration_mask(cal, test, fs)
    thresholds, fit_seconds = {}, {}
    for name, method in fitted.items():
        start = time.perf_counter()
        method.fit(cal)
        fit_seconds[name] = time.perf_counter() - start
        envelope = scoring.envelope(method.run(cal), sample_rate_hz=fs)
        thresholds[name] = scoring.threshold_from_calibration(envelope[cal_mask])

    firmware_bp = combined_bandpassed(test.filtered, profile) if test.filtered is not None else None
    results, event_info, signals = {}, {}, {}
    for amplitude in config.amplitudes:
        spec = dataclasses.replace(config.events, relative_amplitude=amplitude)
        primary = amplitude == PRIMARY_AMPLITUDE
        scored = score_events(
            fitted,
            thresholds,
            test,
            profile,
            spec,
            firmware_bp,
            keep_signals=keep_signals and primary,
        )
        results[f"{amplitude:g}"] = scored["rows"]
        event_info[f"{amplitude:g}"] = dict(scored["events"])
        if keep_signals and primary:
            signals = {**scored["signals"], "t0_ns": t0}
    # Fifteen events or so per set: the same at the primary amplitude over several event sets.
    over_seeds = {}
    extra_seeds = [config.events.seed + k for k in range(1, config.event_sets)]
    if extra_seeds:
        per_seed = [results[f"{PRIMARY_AMPLITUDE:g}"]]
        for seed in extra_seeds:
            spec = dataclasses.replace(
                config.events, relative_amplitude=PRIMARY_AMPLITUDE, seed=seed
            )
            per_seed.append(
                score_events(fitted, thresholds, test, profile, spec, firmware_bp)["rows"]
            )
        over_seeds = pool_seeds(per_seed, [config.events.seed, *extra_seeds])
    fold = {
        "calibration_s": [float(calibration_s[0]), float(calibration_s[1])],
        "test_s": [float(test_s[0]), float(test_s[1])],
        "calibration_samples": int(len(cal.sensor_stamps_ns)),
        "test_samples": int(len(test.sensor_stamps_ns)),
        "motor_command_range": {
            "calibration": [float(cal.joint_velocity.min()), float(cal.joint_velocity.max())],
            "test": [float(test.joint_velocity.min()), float(test.joint_velocity.max())],
        },
        "threshold_source": "each method's output on the calibration part, at motor commands "
        "within the test part's per-motor maxima x 1.05, edges dropped: 1.1 x largest 4 ms "
        "RMS envelope",
        "threshold_samples": int(np.count_nonzero(cal_mask)),
        "methods": {
            name: {
                "label": LABELS[name],
                "delay_ms": method.delay_ms,
                "threshold": thresholds[name],
                "fit_seconds": round(fit_seconds[name], 3),
                "info": method.info(),
            }
            for name, method in fitted.items()
        },
        "events": event_info,
        "results": results,
        "over_seeds": over_seeds,
    }
    if test.filtered is not None:
        fold["firmware_transfer"] = firmware_transfer(test, profile)
    if keep_signals:
        fold["signals"] = signals
    return fold


def run_experiment(
    rec: FlightRecording,
    profile: RobotProfile,
    config: RealConfig | None = None,
    *,
    keep_signals: bool = False,
) -> dict:
    """Both folds (the primary split and, if configured, the swapped one) -> report dict."""
    config = config or RealConfig()
    duration = rec.duration_s
    end = (
        duration + 1.0 / profile.rate_hz
        if config.end_s is None
        else min(config.end_s, duration + 1e-9)
    )
    if not 0 < config.split_s < end:
        raise ConfigError(
            f"split {config.split_s} s must lie inside the recording (0 .. {end:.2f} s)"
        )
    steps = np.diff(rec.sensor_stamps_ns) / 1e6
    report = {
        "schema": SCHEMA,
        "data": {
            "attribution": ATTRIBUTION,
            "licence": "MIT OR Apache-2.0",
            "samples": int(len(steps) + 1),
            "duration_s": duration,
            "sample_step_ms": {
                "min": float(steps.min()),
                "median": float(np.median(steps)),
                "max": float(steps.max()),
                "mean": float(steps.mean()),
            },
        },
        "profile": profile.to_dict(),
        "protocol": {
            "split_s": config.split_s,
            "end_s": end,
            "phases": FLIGHT_PHASES
            if (config.split_s, config.end_s) == (RealConfig.split_s, RealConfig.end_s)
            else None,
            "events": config.events.to_dict(),
            "amplitudes": list(config.amplitudes),
            "primary_amplitude": PRIMARY_AMPLITUDE,
            "detection": {
                "envelope": f"causal RMS over {scoring.ENVELOPE_S * 1e3:g} ms",
                "refractory_s": scoring.REFRACTORY_S,
                "tolerance_s": detection.TOLERANCE_S,
                "threshold": f"{scoring.CALIBRATION_MARGIN} x max envelope on calibration data",
            },
            "metrics": "egovib_ros.evaluation.metrics (INTERFACES.md section 6), on the combined, "
            f"{profile.band_hz[0]:g}-{profile.band_hz[1]:g} Hz band-passed gyro, rad/s",
        },
        "primary": run_fold(
            rec,
            profile,
            (0.0, config.split_s),
            (config.split_s, end),
            config,
            keep_signals=keep_signals,
        ),
    }
    if config.swapped:
        report["swapped"] = run_fold(
            rec, profile, (config.split_s, end), (0.0, config.split_s), config
        )
    return report


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--bag", default="bags/quadcopter_ar8", help="the flight bag (default: bags/quadcopter_ar8)"
    )
    parser.add_argument("--robot", default="quadcopter", help="robot profile (default: quadcopter)")
    parser.add_argument(
        "--out", required=True, help="directory for real_results.{md,json}, real_*.png"
    )
    parser.add_argument(
        "--split",
        type=float,
        default=RealConfig.split_s,
        help=f"end of the calibration part, s (default {RealConfig.split_s})",
    )
    parser.add_argument(
        "--end",
        type=float,
        default=RealConfig.end_s,
        help=f"end of the test part, s (default {RealConfig.end_s}: before the final impact)",
    )
    parser.add_argument("--seed", type=int, default=EventSpec.seed, help="seed of the added events")
    parser.add_argument(
        "--event-sets",
        type=int,
        default=RealConfig.event_sets,
        help=f"event sets (seeds SEED, SEED+1, ...) pooled at 1x (default {RealConfig.event_sets})",
    )
    parser.add_argument("--no-swapped", action="store_true", help="skip the swapped split")
    parser.add_argument(
        "--force", action="store_true", help="replace real_* files written by an earlier run"
    )


def command_line(args: argparse.Namespace) -> str:
    """The command that reproduces this run (non-default options included)."""
    words = ["egovib", "real", "evaluate", "--bag", str(args.bag), "--out", str(args.out)]
    if args.robot != "quadcopter":
        words += ["--robot", str(args.robot)]
    for flag, value, default in (
        ("--split", args.split, RealConfig.split_s),
        ("--end", args.end, RealConfig.end_s),
        ("--seed", args.seed, EventSpec.seed),
        ("--event-sets", args.event_sets, RealConfig.event_sets),
    ):
        if value != default:
            words += [flag, f"{value:g}"]
    if args.no_swapped:
        words.append("--no-swapped")
    return " ".join(shlex.quote(w) for w in words)


def run(args: argparse.Namespace) -> int:
    # before any work: never replace what this command did not write
    prepare_outputs_in(
        args.out, list(report_module.FILES.values()), force=args.force, inputs=[args.bag]
    )
    profile = load_profile(args.robot)
    rec = read_flight_bag(args.bag, profile)
    config = RealConfig(
        split_s=args.split,
        end_s=args.end,
        events=EventSpec(seed=args.seed),
        swapped=not args.no_swapped,
        event_sets=args.event_sets,
    )
    start = time.perf_counter()
    # The core warns once per denoiser about idle commands of -0.0005 (one DShot step below the
    # grid); every such block is counted in the report instead.
    core_log = logging.getLogger("egovib_ros.core")
    level = core_log.level
    core_log.setLevel(logging.ERROR)
    try:
        result = run_experiment(rec, profile, config, keep_signals=True)
    finally:
        core_log.setLevel(level)
    result["command"] = command_line(args)
    result["bag"] = str(args.bag)
    result["runtime_s"] = round(time.perf_counter() - start, 1)
    written = report_module.write_report(result, profile, Path(args.out))
    print(report_module.summary_text(result))
    print("wrote " + ", ".join(str(p) for p in written))
    return 0
