"""Event (tap) detection: magnitude threshold with a refractory time, scored with P/R/F1.

The detector is the "autonomous magnitude thresholding" the paper mentions,
applied to a short causal RMS envelope of the signal (`envelope`, 4 ms): an
event starts where the envelope first exceeds the threshold; above-threshold
samples closer than the refractory time to the previous ones belong to the same
event; its onset is timed where the envelope first reaches 25 % of the event's
peak (constant-fraction timing, robust to the block-processing pre-echo).
The threshold is fixed *before* looking at the test signal, from no-contact
calibration data processed by the same method (`threshold_from_calibration`).

Scoring: a detection is a true positive if its onset is within +/- 10 ms of a
true tap onset; each true tap matches at most one detection (optimal one-to-one
assignment by scipy's linear_sum_assignment).

The PR2 gripper sensor comparison (`pr2_magnitude`) thresholds the vector
magnitude of the raw 3-axis acceleration after a first-order high-pass
(RC = 3.3 ms, about 48 Hz, as in common PR2 contact-detection code) at fixed
levels of 2 and 5 m/s^2.
"""

from __future__ import annotations

import numpy as np
from scipy import optimize, signal

REFRACTORY_S = 0.05
TOLERANCE_S = 0.010
ONSET_FRACTION = 0.25  # onset = first sample at 25 % of the event's peak envelope
ENVELOPE_S = 0.004  # RMS window: shorter than a tap's ring-down, longer than a noise spike
PR2_THRESHOLDS_MS2 = (2.0, 5.0)
PR2_HIGHPASS_HZ = 1.0 / (2.0 * np.pi * 0.0033)  # first-order RC = 3.3 ms
CALIBRATION_MARGIN = 1.1


def envelope(x: np.ndarray, *, sample_rate_hz: float, window_s: float = ENVELOPE_S) -> np.ndarray:
    """Causal moving-RMS envelope of a 1-D signal (what the threshold is applied to)."""
    n = max(1, int(round(window_s * sample_rate_hz)))
    power = signal.lfilter(np.full(n, 1.0 / n), [1.0], np.asarray(x, float) ** 2)
    return np.sqrt(np.maximum(power, 0.0))


def detect_events(
    magnitude: np.ndarray,
    threshold: float,
    *,
    sample_rate_hz: float,
    refractory_s: float = REFRACTORY_S,
    onset_fraction: float = ONSET_FRACTION,
) -> np.ndarray:
    """Onset sample indices of events where `magnitude` (an envelope) exceeds `threshold`.

    Above-threshold samples less than `refractory_s` after the previous
    above-threshold sample continue the same event (a tap rings for a while).
    The onset is the first sample of the event reaching `onset_fraction` of the
    event's peak (a constant-fraction discriminator): block processing smears a
    few per cent of a tap up to one block (21 ms) before it, and a low threshold
    would otherwise time the event by that pre-echo instead of by its rise.
    """
    magnitude = np.asarray(magnitude, float)
    above = np.flatnonzero(magnitude > threshold)
    if above.size == 0:
        return np.zeros(0, np.int64)
    gap = max(1, int(round(refractory_s * sample_rate_hz)))
    new_event = np.concatenate(([True], np.diff(above) >= gap))
    starts = above[new_event]
    stops = np.append(above[np.flatnonzero(new_event)[1:] - 1], above[-1]) + 1
    onsets = np.empty(starts.size, np.int64)
    for i, (start, stop) in enumerate(zip(starts, stops)):
        span = magnitude[start:stop]
        onsets[i] = start + int(np.argmax(span >= onset_fraction * span.max()))
    return onsets


def threshold_from_calibration(
    calibration_magnitude: np.ndarray, *, quantile: float = 1.0, margin: float = CALIBRATION_MARGIN
) -> float:
    """Detection threshold from no-contact calibration data: margin x quantile of |x|.

    With the defaults (largest value x 1.1) the detector raises no event on the
    calibration data itself; the test signal is never looked at.
    """
    values = np.abs(np.asarray(calibration_magnitude, float))
    if values.size == 0:
        raise ValueError("no calibration samples to set a detection threshold from")
    return float(margin * np.quantile(values, quantile))


def match_events(detected: np.ndarray, truth: np.ndarray, tolerance: int) -> tuple[int, int, int]:
    """(true positives, false positives, false negatives) for onset indices within `tolerance`."""
    detected = np.asarray(detected, np.int64)
    truth = np.asarray(truth, np.int64)
    if detected.size == 0 or truth.size == 0:
        return 0, int(detected.size), int(truth.size)
    distance = np.abs(detected[:, None] - truth[None, :]).astype(float)
    # Pairs beyond the tolerance must never be chosen over leaving both unmatched.
    cost = np.where(distance <= tolerance, distance, 1e12)
    rows, cols = optimize.linear_sum_assignment(cost)
    tp = int(np.count_nonzero(cost[rows, cols] <= tolerance))
    return tp, int(detected.size) - tp, int(truth.size) - tp


def precision_recall_f1(
    detected: np.ndarray,
    truth: np.ndarray,
    *,
    sample_rate_hz: float,
    tolerance_s: float = TOLERANCE_S,
) -> dict:
    """Precision, recall, F1 (and counts) of detected onsets against true onsets.

    Conventions: precision = 1 when nothing is detected, recall = 1 when there
    is nothing to detect, F1 = 0 when precision + recall = 0.
    """
    tp, fp, fn = match_events(detected, truth, int(round(tolerance_s * sample_rate_hz)))
    precision = tp / (tp + fp) if tp + fp else 1.0
    recall = tp / (tp + fn) if tp + fn else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"precision": precision, "recall": recall, "f1": f1, "tp": tp, "fp": fp, "fn": fn}


def evaluate_detector(
    magnitude: np.ndarray,
    truth: np.ndarray,
    threshold: float,
    *,
    sample_rate_hz: float,
    refractory_s: float = REFRACTORY_S,
    tolerance_s: float = TOLERANCE_S,
) -> dict:
    """Detect on `magnitude` at `threshold` and score against `truth` onsets."""
    onsets = detect_events(
        magnitude, threshold, sample_rate_hz=sample_rate_hz, refractory_s=refractory_s
    )
    scores = precision_recall_f1(
        onsets, truth, sample_rate_hz=sample_rate_hz, tolerance_s=tolerance_s
    )
    scores["threshold"] = float(threshold)
    return scores


def pr_curve(
    magnitude: np.ndarray,
    truth: np.ndarray,
    *,
    sample_rate_hz: float,
    thresholds: np.ndarray | None = None,
    n_thresholds: int = 60,
    refractory_s: float = REFRACTORY_S,
    tolerance_s: float = TOLERANCE_S,
) -> dict:
    """Precision/recall/F1 over a threshold sweep (log-spaced over the signal's range by
    default)."""
    magnitude = np.abs(np.asarray(magnitude, float))
    if thresholds is None:
        positive = magnitude[magnitude > 0]
        low = np.quantile(positive, 0.5) if positive.size else 1e-6
        high = magnitude.max() if positive.size else 1.0
        thresholds = np.geomspace(low, max(high, low * 1.01), n_thresholds)
    rows = [
        evaluate_detector(
            magnitude,
            truth,
            t,
            sample_rate_hz=sample_rate_hz,
            refractory_s=refractory_s,
            tolerance_s=tolerance_s,
        )
        for t in thresholds
    ]
    return {
        key: np.array([row[key] for row in rows])
        for key in ("threshold", "precision", "recall", "f1")
    }


def pr2_magnitude(
    accel: np.ndarray, *, sample_rate_hz: float, highpass_hz: float = PR2_HIGHPASS_HZ
) -> np.ndarray:
    """(N,) magnitude of the high-passed raw 3-axis acceleration (the PR2 gripper
    sensor's input)."""
    sos = signal.butter(1, highpass_hz, btype="highpass", fs=sample_rate_hz, output="sos")
    accel = np.asarray(accel, float)
    # Start the filter at rest on the first sample so gravity does not produce a start-up spike.
    zi = signal.sosfilt_zi(sos)[:, :, None] * accel[:1][None, :, :]
    filtered, _ = signal.sosfilt(sos, accel, axis=0, zi=zi)
    return np.linalg.norm(filtered, axis=1)
