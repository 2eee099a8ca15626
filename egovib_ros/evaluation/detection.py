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

The PR2 gripper sensor comparison (`PR2Magnitude`) thresholds the vector
magnitude of the raw 3-axis acceleration after a first-order high-pass
(RC = 3.3 ms, about 48 Hz, as in common PR2 contact-detection code) at fixed
levels of 2 and 5 m/s^2.
"""

from __future__ import annotations

import numpy as np
from scipy import optimize, signal

from egovib_ros.core.contact import (
    BURST_S,
    THRESHOLD_MARGIN,
    ContactDetector,
    ContactSettings,
)

REFRACTORY_S = 0.05
TOLERANCE_S = 0.010
ONSET_FRACTION = 0.25  # onset = first sample at 25 % of the event's peak envelope
ENVELOPE_S = 0.004  # RMS window: shorter than a tap's ring-down, longer than a noise spike
PR2_THRESHOLDS_MS2 = (2.0, 5.0)
PR2_HIGHPASS_HZ = 1.0 / (2.0 * np.pi * 0.0033)  # first-order RC = 3.3 ms
CALIBRATION_MARGIN = 1.1


def envelope(x: np.ndarray, *, sample_rate_hz: float, window_s: float = ENVELOPE_S) -> np.ndarray:
    """Causal moving-RMS envelope of a 1-D signal (what the threshold is applied to)."""
    return Envelope(sample_rate_hz=sample_rate_hz, window_s=window_s).process(x)


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
    """Precision, recall, F1 (and counts) of detected onsets against true onsets."""
    return scores_of(*match_events(detected, truth, int(round(tolerance_s * sample_rate_hz))))


def scores_of(tp: int, fp: int, fn: int) -> dict:
    """Precision, recall, F1 and the counts they come from.

    Conventions: precision = 1 when nothing is detected, recall = 1 when there
    is nothing to detect, F1 = 0 when precision + recall = 0.
    """
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


class PR2Magnitude:
    """(N,) magnitude of the high-passed raw 3-axis acceleration (the PR2 gripper
    sensor's input), with carried filter state (any chunking, the same samples)."""

    def __init__(self, *, sample_rate_hz: float, highpass_hz: float = PR2_HIGHPASS_HZ):
        self.sos = signal.butter(1, highpass_hz, btype="highpass", fs=sample_rate_hz, output="sos")
        self._zi: np.ndarray | None = None

    def process(self, accel: np.ndarray) -> np.ndarray:
        accel = np.asarray(accel, float)
        if not len(accel):
            return np.zeros(0)
        if self._zi is None:
            # Start at rest on the first sample so gravity does not produce a start-up spike.
            self._zi = signal.sosfilt_zi(self.sos)[:, :, None] * accel[:1][None, :, :]
        filtered, self._zi = signal.sosfilt(self.sos, accel, axis=0, zi=self._zi)
        return np.linalg.norm(filtered, axis=1)


# --------------------------------------------------------------------------
# Streaming forms (evaluation/stream.py): the same detector and scores over a signal
# that arrives in pieces, with explicit carried state.
# --------------------------------------------------------------------------
class Envelope:
    """`envelope` with carried filter state: any chunking gives the same samples."""

    def __init__(self, *, sample_rate_hz: float, window_s: float = ENVELOPE_S):
        n = max(1, int(round(window_s * sample_rate_hz)))
        self._b = np.full(n, 1.0 / n)
        self._zi = np.zeros(n - 1)

    def process(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, float)
        if not x.size:
            return x.copy()
        power, self._zi = signal.lfilter(self._b, [1.0], x**2, zi=self._zi)
        return np.sqrt(np.maximum(power, 0.0))


class EventDetector:
    """`detect_events` over a magnitude stream. An event is emitted once no later sample
    can join it (`refractory_s` below the threshold) or at `finish`; of an open event only
    its running peak and the candidate onsets (strict running maxima of at least
    `onset_fraction` of that peak) are kept, so memory does not grow with its length.

    `horizon`: every onset still to come is at or after this sample."""

    def __init__(
        self,
        threshold: float,
        *,
        sample_rate_hz: float,
        refractory_s: float = REFRACTORY_S,
        onset_fraction: float = ONSET_FRACTION,
    ):
        self.threshold = float(threshold)
        self.gap = max(1, int(round(refractory_s * sample_rate_hz)))
        self.fraction = float(onset_fraction)
        self.pos = 0
        self._open = False
        self._start = self._last = 0
        self._peak = -np.inf
        self._records: list[tuple[int, float]] = []  # (index, value), increasing values
        self._onsets: list[int] = []

    @property
    def horizon(self) -> int:
        return self._start if self._open else self.pos

    def push(self, magnitude: np.ndarray) -> None:
        magnitude = np.asarray(magnitude, float)
        p = self.pos
        above = np.flatnonzero(magnitude > self.threshold) + p
        if above.size:
            previous = np.concatenate(([self._last if self._open else -(1 << 62)], above[:-1]))
            new = np.flatnonzero(above - previous >= self.gap)
            bounds = list(new) + [above.size]
            if bounds[0] > 0:  # continues the open event
                self._extend(magnitude, p, p, int(above[bounds[0] - 1]))
            for k in range(len(bounds) - 1):
                if self._open:
                    self._close()
                first, last = int(above[bounds[k]]), int(above[bounds[k + 1] - 1])
                self._open, self._start = True, first
                self._peak, self._records = -np.inf, []
                self._extend(magnitude, p, first, last)
        self.pos = p + magnitude.size
        if self._open and self.pos - self._last >= self.gap:
            self._close()

    def _extend(self, magnitude: np.ndarray, p: int, first: int, last: int) -> None:
        """Add samples [first, last] (global) of the open event; `last` is above threshold."""
        span = magnitude[first - p : last - p + 1]
        running = np.maximum.accumulate(span)
        before = np.maximum(np.concatenate(([self._peak], running[:-1])), self._peak)
        new = np.flatnonzero(span > before)
        self._peak = max(self._peak, float(running[-1]))
        floor = self.fraction * self._peak
        records = [r for r in self._records if r[1] >= floor]
        records += [(first + int(i), float(span[i])) for i in new if span[i] >= floor]
        self._records = records
        self._last = last

    def _close(self) -> None:
        level = self.fraction * self._peak
        self._onsets.append(next(i for i, v in self._records if v >= level))
        self._open = False

    def finish(self) -> None:
        if self._open:
            self._close()

    def take(self) -> np.ndarray:
        """Onsets of the events closed since the last call (in order)."""
        onsets, self._onsets = self._onsets, []
        return np.asarray(onsets, np.int64)


class EventMatcher:
    """`precision_recall_f1` over onsets that arrive in order: the optimal one-to-one
    assignment splits into groups no pair within the tolerance connects, so each group is
    scored (match_events) once no later onset can join it, and only counts are kept."""

    def __init__(self, *, sample_rate_hz: float, tolerance_s: float = TOLERANCE_S):
        self.tolerance = int(round(tolerance_s * sample_rate_hz))
        self._detected: list[int] = []
        self._truth: list[int] = []
        self.tp = self.fp = self.fn = 0

    def add(self, detected=(), truth=()) -> None:
        self._detected += [int(i) for i in detected]
        self._truth += [int(i) for i in truth]

    def advance(self, horizon: int) -> None:
        """Score the groups that no onset at or after `horizon` can join."""
        points = np.sort(np.asarray(self._detected + self._truth, np.int64))
        if not points.size:
            return
        gaps = np.flatnonzero(np.diff(points) > self.tolerance) + 1
        cuts = np.concatenate([gaps, [points.size]])
        cuts = cuts[points[cuts - 1] + self.tolerance < horizon]
        if cuts.size:
            self._score(int(points[cuts[-1] - 1]))

    def _score(self, upto: int) -> None:
        """Score every pending onset <= upto."""
        detected = [i for i in self._detected if i <= upto]
        truth = [i for i in self._truth if i <= upto]
        self._detected = [i for i in self._detected if i > upto]
        self._truth = [i for i in self._truth if i > upto]
        tp, fp, fn = match_events(np.asarray(detected), np.asarray(truth), self.tolerance)
        self.tp, self.fp, self.fn = self.tp + tp, self.fp + fp, self.fn + fn

    def finish(self) -> None:
        self._score(np.iinfo(np.int64).max)

    def scores(self) -> dict:
        """precision_recall_f1's dict (call after `finish`)."""
        return scores_of(self.tp, self.fp, self.fn)


class OnsetStream:
    """The one contact detector (core.contact.ContactDetector, as `egovib detect` and the
    contact_detector node run it) on a band-passed 1-D signal arriving in pieces, its
    events' onsets as sample indices, for `egovib evaluate`'s scoring (EventMatcher):
    push(x), take() -> onsets closed since the last call, `horizon`: every onset still to
    come is at or after this sample."""

    def __init__(self, threshold: float, model):
        self.threshold = float(threshold)
        self.detector = ContactDetector(
            ContactSettings.for_model(model, self.threshold), prefiltered=True
        )
        self.pos = 0
        self._onsets: list[int] = []

    @property
    def horizon(self) -> int:
        return self.detector.onsets_settled

    def push(self, x: np.ndarray) -> None:
        x = np.asarray(x, float)
        index = np.arange(self.pos, self.pos + x.size, dtype=np.int64)
        self.pos += x.size
        self._onsets += [e.onset_ns for e in self.detector.push(index, x)]

    def finish(self) -> None:
        self._onsets += [e.onset_ns for e in self.detector.finish()]

    def take(self) -> np.ndarray:
        onsets, self._onsets = self._onsets, []
        return np.asarray(onsets, np.int64)


class ThresholdReducer:
    """core.contact.no_contact_threshold over an envelope arriving in pieces: the largest
    values pushed are kept (a slack of twice the budget's share, and 256 more, over what
    the quantile needs as the count grows), then the same rule. `threshold()` also says
    the false alarms a minute it gives, counted on the kept values' peaks (as many as
    rose above it)."""

    def __init__(self, *, sample_rate_hz: float, false_alarms_per_min: float):
        self.fs = float(sample_rate_hz)
        self.budget = float(false_alarms_per_min)
        self.share = min(self.budget * BURST_S / 60.0, 0.5)
        self.top = np.zeros(0)
        self.largest = -np.inf
        self.count = 0

    def push(self, envelope: np.ndarray) -> None:
        envelope = np.asarray(envelope, float)
        if not envelope.size:
            return
        self.count += envelope.size
        self.largest = max(self.largest, float(envelope.max()))
        keep = int(2 * np.ceil(self.share * self.count)) + 256
        merged = np.concatenate([self.top, envelope])
        if merged.size > keep:
            merged = np.partition(merged, merged.size - keep)[-keep:]
        self.top = merged

    def threshold(self) -> float:
        if not self.count:
            raise ValueError("no calibration samples to set a detection threshold from")
        if self.share <= 0:
            return THRESHOLD_MARGIN * self.largest
        top = np.sort(self.top)
        q = 1.0 - self.share
        virtual = (self.count - 1) * q  # np.quantile's 'linear' position, in the full count
        below = int(np.floor(virtual)) - (self.count - top.size)
        if below < 0:
            raise ValueError("ThresholdReducer: the budget's quantile fell out of the kept values")
        upper = top[min(below + 1, top.size - 1)]
        return THRESHOLD_MARGIN * float(top[below] + (upper - top[below]) * (virtual % 1.0))
