"""`egovib detect` as a library: contact events in a recorded bag (and their scores).

`detect_bag`: the bag's sensor stream through the core's denoiser (by default the model's
default method and its drop-in output; `raw`: none), then core.contact's detector, as the
denoiser and contact_detector nodes run live. The threshold is fixed before the bag is
looked at, by core.contact's rule on no-contact data processed the same way: stored in
the model by calibration, or computed again from a no-contact bag, or given. With the
simulator's ground truth in the bag the events are scored against the true tap onsets
(+-10 ms, as `egovib evaluate`): F1, false alarms per minute, and the latency from a
tap's onset to its event's report (the method's delay plus the detector's report time).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from egovib_ros.bag.reader import bag_topics
from egovib_ros.bag.recording import bag_topic_names, iter_recording, read_recording
from egovib_ros.core import NoiseModel
from egovib_ros.core.contact import (
    FALSE_ALARMS_PER_MIN,
    ContactDetector,
    ContactEvent,
    ContactSettings,
    DetectionEnvelope,
    MotionLimits,
    no_contact_threshold,
)
from egovib_ros.core.filters import combined_bandpassed
from egovib_ros.core.methods import (
    DETECTOR_BUDGET,
    EDGE_S,
    METHODS,
    make_denoiser,
    motion_limits,
    resolve_method,
    stored_threshold,
    with_motion,
)
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import ConfigError
from egovib_ros.evaluation.detection import TOLERANCE_S, match_events, scores_of
from egovib_ros.evaluation.metrics import segment_contacts

DETECT_METHODS = (*METHODS, "raw")
LOG = logging.getLogger("egovib_ros.evaluation")


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
    adapt: dict | None = None  # with adapt: its settings and what it counted


def check_detect_method(model: NoiseModel, method: str | None) -> str:
    """The method to detect after: the model's default when None, `raw` for none."""
    if method == "raw":
        return method
    if method is not None and method not in DETECT_METHODS:
        raise ConfigError(f"method: expected one of {list(DETECT_METHODS)}, got {method!r}")
    return resolve_method(model, method)


def method_pieces(
    bag,
    model: NoiseModel,
    method: str,
    joint_lag_s: float = 0.0,
    *,
    ground_truth: bool,
    adapt=None,
    used: list | None = None,
):
    """Pieces (stamps, values (N, 3), contact (N, 3) or None, (joint stamps, velocities))
    of what `detect_bag` feeds its detector on `bag`: the checked method's streaming
    output, or the raw stream, and the joint states read with it (`adapt`: the model
    learning as it goes, core.adapt; `used` gets the denoiser)."""
    profile = model.robot_profile()
    denoiser = None
    if method != "raw":  # its default output (the drop-in), as the denoiser node publishes
        source = f"{bag}: {profile.sensor_topic}"
        denoiser = make_denoiser(model, method, joint_lag_s=joint_lag_s, source=source, adapt=adapt)
    elif adapt is not None:
        raise ConfigError("adapt: method raw has no model to adapt")
    if used is not None:
        used.append(denoiser)
    truth: dict[int, np.ndarray] = {}
    lag_ns = int(round(joint_lag_s * NS_PER_S))
    for piece in iter_recording(
        bag, profile=profile, ground_truth=ground_truth, denoised=False, commands=False
    ):
        if ground_truth and piece.contact is not None:
            truth.update(zip(piece.sensor_stamps_ns.tolist(), piece.contact))
        # as the denoiser aligns them (its joint lag): the detector's motion limits
        joints = (piece.joint_stamps_ns + lag_ns, piece.joint_velocity)
        if denoiser is None:
            stamps, values = piece.sensor_stamps_ns, piece.sensor
        else:
            first = denoiser.push_joint_states(piece.joint_stamps_ns, piece.joint_velocity)
            then = denoiser.push_sensor(piece.sensor_stamps_ns, piece.sensor)
            stamps = np.concatenate([first.stamps_ns, then.stamps_ns])
            values = np.concatenate([first.values, then.values])
        yield stamps, values, _truth(truth, stamps), joints
    if denoiser is not None:
        chunk = denoiser.flush()
        no_joints = (np.zeros(0, np.int64), np.zeros((0, model.n_joints)))
        yield chunk.stamps_ns, chunk.values, _truth(truth, chunk.stamps_ns), no_joints


def _truth(truth: dict, stamps: np.ndarray):
    if not truth or not len(stamps):
        return None
    return np.array([truth.pop(int(s), np.zeros(3)) for s in stamps.tolist()]).reshape(-1, 3)


def warn_if_contacts(bag, profile) -> int:
    """Calibration data is motion without contact. A bag that holds the simulator's contact
    ground truth with taps in it (a run of `egovib simulate motion --taps`, not a sweep) is
    said in a WARNING: its taps would count as ego-vibration, the detector's thresholds
    raised above them. Returns the taps found (0 without that topic: a real robot's bag)."""
    topic = bag_topic_names(profile)["contact"]
    if bag_topics(bag).get(topic, ("", 0))[1] == 0:
        return 0
    rec = read_recording(bag, profile=profile, ground_truth=True, denoised=False)
    if rec.contact is None:
        return 0
    reference = combined_bandpassed(rec.contact, profile)
    taps = segment_contacts(reference, sample_rate_hz=profile.rate_hz).n_taps
    if taps:
        LOG.warning(
            "%s: its ground truth (%s) holds %d contacts: calibration data should be motion "
            "without contact (the taps count as ego-vibration and raise the detector's "
            "thresholds)",
            bag,
            topic,
            taps,
        )
    return taps


def calibration_threshold(
    bag,
    model: NoiseModel,
    *,
    method: str,
    false_alarms_per_min: float = FALSE_ALARMS_PER_MIN,
    joint_lag_s: float = 0.0,
    joints: list | None = None,
) -> tuple[float, float]:
    """(threshold, false alarms per minute on these data) from a no-contact bag processed
    as the run will be (the method, then the detector's envelope), by core.contact's rule;
    its first and last EDGE_S left out (filter start-up and flush). `joints`: gets the
    bag's joint states, (stamps, velocities) per piece, read in the same pass."""
    envelope = DetectionEnvelope(ContactSettings.for_model(model, 1.0))
    parts = []
    for _, values, _, piece_joints in method_pieces(
        bag, model, method, joint_lag_s, ground_truth=False
    ):
        parts.append(envelope.process(values)[1])
        if joints is not None:
            joints.append(piece_joints)
    values = np.concatenate(parts) if parts else np.zeros(0)
    edge = int(EDGE_S * model.sample_rate_hz)
    if len(values) <= 2 * edge:
        raise ConfigError(f"{bag}: too short for detection thresholds")
    return no_contact_threshold(
        values[edge:-edge],
        sample_rate_hz=model.sample_rate_hz,
        false_alarms_per_min=false_alarms_per_min,
    )


def detection_threshold_needs_data(
    model: NoiseModel, method: str, false_alarms_per_min: float | None, joint_lag_s: float
) -> bool:
    """Whether a threshold for these settings needs no-contact data: the model stores none
    for `method`, or one made at another budget or without the joint lag."""
    budget = model.extras.get(DETECTOR_BUDGET)
    return (
        stored_threshold(model, method) is None
        or budget is None
        or (false_alarms_per_min is not None and float(budget) != float(false_alarms_per_min))
        or joint_lag_s != 0.0
    )


def detection_threshold(
    model: NoiseModel,
    method: str,
    *,
    threshold: float | None = None,
    calibration: str | os.PathLike | None = None,
    false_alarms_per_min: float | None = None,
    joint_lag_s: float = 0.0,
) -> tuple[float, str, float | None, MotionLimits | None]:
    """(threshold, where it came from, false alarms per minute it gave on its no-contact
    data or None, the detector's motion limits): `threshold` if given; else the model's
    stored one when nothing asks for another (no `calibration` bag, no budget but the
    stored one's, no joint lag); else computed from `calibration` (default: the bag the
    model was calibrated from), and the motion limits with it: that bag's speeds and
    accelerations, its raw signal's threshold at the same budget over the method's (else
    the model's stored limits)."""
    if threshold is not None:
        return float(threshold), "given", None, motion_limits(model, method)
    if calibration is None and not detection_threshold_needs_data(
        model, method, false_alarms_per_min, joint_lag_s
    ):
        budget = float(model.extras[DETECTOR_BUDGET])
        source = f"stored in the model, {budget:g}/min"
        return stored_threshold(model, method), source, None, motion_limits(model, method)
    calibration = calibration or model.provenance.get("source_bag")
    if not calibration:
        raise ConfigError(
            "detect: the model stores no detection threshold for this method and names no "
            "calibration bag: give --calibration (a no-contact bag) or --threshold"
        )
    budget = FALSE_ALARMS_PER_MIN if false_alarms_per_min is None else false_alarms_per_min
    options = dict(false_alarms_per_min=budget, joint_lag_s=joint_lag_s)
    value, rate = calibration_threshold(calibration, model, method=method, **options)
    source = f"no-contact data {Path(calibration)}, {budget:g}/min"
    return value, source, rate, calibration_motion(calibration, model, method, value, **options)


def calibration_motion(
    bag, model: NoiseModel, method: str, threshold: float, **options
) -> MotionLimits | None:
    """The detector's motion limits from the no-contact `bag` its `threshold` came from
    (`options`: calibration_threshold's): the bag's motion (core.methods.with_motion)
    and its raw signal's threshold over `threshold`."""
    if method == "raw":
        return None
    joints: list = []  # read in the raw signal's pass (the bag is read once more, not twice)
    raw, _ = calibration_threshold(bag, model, method="raw", joints=joints, **options)
    stamps, velocity = (np.concatenate(part) for part in zip(*joints))
    bags = with_motion(model, stamps, velocity)
    return motion_limits(bags, method, {"raw": raw, method: threshold})


def detect_bag(
    bag: str | os.PathLike,
    *,
    model: NoiseModel,
    method: str | None = None,
    threshold: float | None = None,
    calibration: str | os.PathLike | None = None,
    false_alarms_per_min: float | None = None,
    joint_lag_s: float = 0.0,
    adapt=None,
) -> Detection:
    """Contact events of `bag` (see the module doc); `adapt` (core.adapt.AdaptSettings):
    the denoiser's model goes on learning while no contact is detected."""
    method = check_detect_method(model, method)
    threshold, source, rate, motion = detection_threshold(
        model,
        method,
        threshold=threshold,
        calibration=calibration,
        false_alarms_per_min=false_alarms_per_min,
        joint_lag_s=joint_lag_s,
    )
    detector = ContactDetector(ContactSettings.for_model(model, threshold), motion=motion)
    events: list[ContactEvent] = []
    truth_parts, stamp_parts = [], []
    used: list = []
    for stamps, values, contact, joints in method_pieces(
        bag, model, method, joint_lag_s, ground_truth=True, adapt=adapt, used=used
    ):
        events += detector.push_joints(*joints)
        events += detector.push(stamps, values)
        stamp_parts.append(stamps)
        if contact is not None:
            truth_parts.append(contact)
    events += detector.finish()
    stamps = np.concatenate(stamp_parts) if stamp_parts else np.zeros(0, np.int64)
    duration_s = float(stamps[-1] - stamps[0]) / NS_PER_S if len(stamps) > 1 else 0.0
    budget = model.extras.get(DETECTOR_BUDGET, FALSE_ALARMS_PER_MIN)
    result = Detection(
        events=events,
        threshold=float(threshold),
        threshold_source=source,
        false_alarm_budget_per_min=float(
            false_alarms_per_min if false_alarms_per_min is not None else budget
        ),
        calibration_false_alarms_per_min=rate,
        method=method,
        method_delay_ms=used[0].delay_ms if used and used[0] is not None else 0.0,
        duration_s=duration_s,
        counts={
            "samples": int(len(stamps)),
            "events": len(events),
            "samples_beyond_calibration_motion": detector.samples_motion,
        },
        adapt=None
        if adapt is None or not used
        else {**vars(adapt), **used[0].adaptation_stats.as_dict()},
    )
    if truth_parts and len(np.concatenate(truth_parts)) == len(stamps):
        result.scores = score_events(events, stamps, np.concatenate(truth_parts), model, result)
    return result


def score_events(events, stamps, contact, model: NoiseModel, result: Detection) -> dict:
    """F1 and false alarms per minute against the ground truth's tap onsets (+-10 ms), and
    the latency from each detected tap's true onset to its event's report (with the
    method's delay: when a live system would publish it)."""

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
