"""`egovib detect` as a library: contact events in a recorded bag (and their scores).

The bag's sensor stream goes through the core's denoiser (any method; or none: `raw`),
then through core.contact's detector, exactly as the denoiser and contact_detector nodes
run live. The threshold is fixed before the bag is looked at: from no-contact data (the
model's calibration bag, or another) processed the same way, at a stated false-alarm
budget per minute (core.contact.no_contact_threshold), or given.

    detect_bag(bag, model=..., method=..., threshold=None, calibration=...) -> Detection

With the simulator's ground truth in the bag (`<sensor parent>/contact`), the events are
scored against the true tap onsets (+-10 ms, as `egovib evaluate`): F1, false alarms per
minute, and the latency from a tap's onset to its event's report (the method's delay plus
the detector's report time).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from egovib_ros.bag.recording import iter_recording
from egovib_ros.core import NoiseModel
from egovib_ros.core.contact import (
    ContactDetector,
    ContactEvent,
    ContactSettings,
    DetectionEnvelope,
    no_contact_threshold,
)
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import ConfigError

METHODS = ("paper", "cancel", "hybrid", "raw")
EDGE_S = 0.1  # filter start-up and flush at the ends of a calibration recording
TOLERANCE_S = 0.010  # a detection within this of a true onset is a true positive


@dataclass
class Detection:
    events: list[ContactEvent]
    threshold: float
    threshold_source: str
    false_alarm_budget_per_min: float
    calibration_false_alarms_per_min: float | None
    method: str
    method_delay_ms: float
    duration_s: float
    scores: dict | None = None  # with ground truth
    counts: dict = field(default_factory=dict)


def _denoiser(model: NoiseModel, method: str, joint_lag_s: float, source: str):
    if method == "raw":
        return None
    from egovib_ros.bag.denoise import make_method_denoiser

    # cancel and hybrid: the band-passed output, their drop-in's is later and the detector
    # band-passes its input anyway
    return make_method_denoiser(
        model,
        method,
        channels="per_axis",
        output=None if method == "paper" else "bandpassed",
        joint_lag_s=joint_lag_s,
        source=source,
    )


def _delay_ms(model: NoiseModel, method: str) -> float:
    if method == "raw":
        return 0.0
    if method == "paper":
        return 1e3 * (model.block_length - 1) / model.sample_rate_hz
    from egovib_ros.core.methods import method_delay_ms

    return method_delay_ms(model, method, output="bandpassed")  # what _denoiser makes


def _stream(
    bag, model: NoiseModel, method: str, joint_lag_s: float, *, ground_truth: bool,
    speed_limit: np.ndarray | None = None,
):  # fmt: skip
    """(stamps, values (N, 3), contact (N, 3) or None, within (N,) bool) of the method's
    output on `bag`; `within`: the joint speeds held at each sample are within
    `speed_limit` (all True without one)."""
    profile = model.robot_profile()
    denoiser = _denoiser(model, method, joint_lag_s, f"{bag}: {profile.sensor_topic}")
    truth: dict[int, np.ndarray] = {}
    speed_ok: dict[int, bool] = {}
    for piece in iter_recording(
        bag, profile=profile, ground_truth=ground_truth, denoised=False, commands=False
    ):
        if ground_truth and piece.contact is not None:
            truth.update(zip(piece.sensor_stamps_ns.tolist(), piece.contact))
        if speed_limit is not None:
            speed_ok.update(zip(piece.sensor_stamps_ns.tolist(), _within(piece, speed_limit)))
        if denoiser is None:
            outputs = [(piece.sensor_stamps_ns, piece.sensor)]
        else:
            outputs = [
                (c.stamps_ns, c.values)
                for c in (
                    denoiser.push_joint_states(piece.joint_stamps_ns, piece.joint_velocity),
                    denoiser.push_sensor(piece.sensor_stamps_ns, piece.sensor),
                )
            ]
        for stamps, values in outputs:
            if len(stamps):
                yield stamps, values, _truth(truth, stamps), _pop(speed_ok, stamps)
    if denoiser is not None:
        chunk = denoiser.flush()
        if len(chunk):
            stamps = chunk.stamps_ns
            yield stamps, chunk.values, _truth(truth, stamps), _pop(speed_ok, stamps)


def method_output(
    bag, model: NoiseModel, method: str, joint_lag_s: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(stamps (N,), values (N, 3), ground truth (N, 3) or None): what `detect_bag` feeds
    its detector on `bag` (the method's streaming output, or the raw stream), whole; for
    looking at why a method detects what it does."""
    stamps, values, truth = [], [], []
    for s, v, contact, _ in _stream(bag, model, method, joint_lag_s, ground_truth=True):
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


def _within(piece, speed_limit: np.ndarray) -> np.ndarray:
    """Per sensor sample: the last joint state before it has every |speed| within limit."""
    if not len(piece.joint_stamps_ns):
        return np.zeros(len(piece.sensor_stamps_ns), bool)
    at = np.searchsorted(piece.joint_stamps_ns, piece.sensor_stamps_ns, side="right") - 1
    speeds = np.abs(piece.joint_velocity[np.maximum(at, 0)])
    return (at >= 0) & np.all(speeds <= speed_limit, axis=1)


def _pop(flags: dict, stamps: np.ndarray) -> np.ndarray:
    if not flags:
        return np.ones(len(stamps), bool)
    return np.array([flags.pop(int(s), False) for s in stamps.tolist()], bool)


def run_speed_limit(bag, model: NoiseModel, margin: float = 1.05) -> np.ndarray:
    """(J,) the run's largest |joint speed| per joint x `margin`: the calibration samples a
    threshold is taken from stay within the speeds the run reaches (as `egovib evaluate`
    does)."""
    top = np.zeros(model.n_joints)
    for piece in iter_recording(
        bag, profile=model.robot_profile(), ground_truth=False, denoised=False, commands=False
    ):
        if len(piece.joint_velocity):
            top = np.fmax(top, np.nanmax(np.abs(piece.joint_velocity), axis=0))
    return margin * top


def _truth(truth: dict, stamps: np.ndarray):
    if not truth:
        return None
    return np.array([truth.pop(int(s), np.zeros(3)) for s in stamps.tolist()]).reshape(-1, 3)


def _settings(model: NoiseModel, threshold: float) -> ContactSettings:
    return ContactSettings(
        sample_rate_hz=model.sample_rate_hz,
        band_hz=model.band_hz,
        band_order=model.band_order,
        threshold=threshold,
        sensor_range=model.robot_profile().sensor_range,
    )


def calibration_threshold(
    bag,
    model: NoiseModel,
    *,
    method: str,
    false_alarms_per_min: float,
    joint_lag_s: float = 0.0,
    speed_limit: np.ndarray | None = None,
) -> tuple[float, float]:
    """(threshold, false alarms per minute on these data) from a no-contact bag processed
    as the run will be (the method, then the detector's envelope); its first and last
    EDGE_S left out (filter start-up and flush), and with `speed_limit` only the samples at
    joint speeds within it (if at least a second of them remains)."""
    envelope = DetectionEnvelope(_settings(model, 1.0))
    parts, masks = [], []
    for _, values, _, within in _stream(
        bag, model, method, joint_lag_s, ground_truth=False, speed_limit=speed_limit
    ):
        parts.append(envelope.process(values)[1])
        masks.append(within)
    values = np.concatenate(parts) if parts else np.zeros(0)
    within = np.concatenate(masks) if masks else np.zeros(0, bool)
    edge = int(EDGE_S * model.sample_rate_hz)
    if len(values) <= 2 * edge:
        raise ConfigError(f"{bag}: too short for detection thresholds")
    values, within = values[edge:-edge], within[edge:-edge]
    if np.count_nonzero(within) >= model.sample_rate_hz:
        values = values[within]
    return no_contact_threshold(
        values,
        sample_rate_hz=model.sample_rate_hz,
        false_alarms_per_min=false_alarms_per_min,
    )


def detect_bag(
    bag: str | os.PathLike,
    *,
    model: NoiseModel,
    method: str = "paper",
    threshold: float | None = None,
    calibration: str | os.PathLike | None = None,
    false_alarms_per_min: float = 0.0,
    joint_lag_s: float = 0.0,
) -> Detection:
    """Contact events of `bag` (see the module doc). `threshold` given, else from the
    no-contact bag `calibration`."""
    if method not in METHODS:
        raise ConfigError(f"method: expected one of {list(METHODS)}, got {method!r}")
    if threshold is None:
        if calibration is None:
            raise ConfigError("detect: a threshold or a no-contact calibration bag is needed")
        threshold, rate = calibration_threshold(
            calibration,
            model,
            method=method,
            false_alarms_per_min=false_alarms_per_min,
            joint_lag_s=joint_lag_s,
            speed_limit=run_speed_limit(bag, model),
        )
        source = f"no-contact data at this run's joint speeds: {Path(calibration)}"
    else:
        rate, source = None, "given"
    detector = ContactDetector(_settings(model, threshold))
    events: list[ContactEvent] = []
    truth_parts, stamp_parts = [], []
    for stamps, values, contact, _ in _stream(bag, model, method, joint_lag_s, ground_truth=True):
        events += detector.push(stamps, values)
        stamp_parts.append(stamps)
        if contact is not None:
            truth_parts.append(contact)
    events += detector.finish()
    stamps = np.concatenate(stamp_parts) if stamp_parts else np.zeros(0, np.int64)
    duration_s = float(stamps[-1] - stamps[0]) / NS_PER_S if len(stamps) > 1 else 0.0
    result = Detection(
        events=events,
        threshold=float(threshold),
        threshold_source=source,
        false_alarm_budget_per_min=float(false_alarms_per_min),
        calibration_false_alarms_per_min=rate,
        method=method,
        method_delay_ms=_delay_ms(model, method),
        duration_s=duration_s,
        counts={"samples": int(len(stamps)), "events": len(events)},
    )
    if truth_parts and len(np.concatenate(truth_parts)) == len(stamps):
        result.scores = score_events(events, stamps, np.concatenate(truth_parts), model, result)
    return result


def score_events(events, stamps, contact, model: NoiseModel, result: Detection) -> dict:
    """F1 and false alarms per minute against the ground truth's tap onsets (+-10 ms), and
    the latency from each detected tap's true onset to its event's report (with the
    method's delay: when a live system would publish it)."""
    from egovib_ros.core.filters import combined_bandpassed
    from egovib_ros.evaluation.detection import match_events, scores_of
    from egovib_ros.evaluation.metrics import segment_contacts

    reference = combined_bandpassed(contact, model.robot_profile())
    onsets = stamps[segment_contacts(reference, sample_rate_hz=model.sample_rate_hz).onsets]
    detected = np.array([e.onset_ns for e in events], np.int64)
    us = 1000  # match in microseconds
    scores = scores_of(
        *match_events(detected // us, onsets // us, int(TOLERANCE_S * NS_PER_S) // us)
    )
    minutes = result.duration_s / 60.0
    latency = []
    for event in events:
        near = onsets[np.abs(onsets - event.onset_ns) <= TOLERANCE_S * NS_PER_S]
        if len(near):
            latency.append((event.report_ns - near[0]) / 1e6 + result.method_delay_ms)
    return {
        "n_taps": int(len(onsets)),
        **{key: scores[key] for key in ("f1", "precision", "recall", "tp", "fp", "fn")},
        "false_alarms_per_min": scores["fp"] / minutes if minutes > 0 else float("nan"),
        "latency_ms_p50": float(np.percentile(latency, 50)) if latency else None,
        "latency_ms_p99": float(np.percentile(latency, 99)) if latency else None,
    }
