"""Event (tap) detection for `egovib evaluate`'s scores, over signals arriving in pieces.

The one contact detector (core.contact, `OnsetStream`) on each method's signal; the PR2
gripper sensor's comparison (`PR2Magnitude`: the vector magnitude of the raw 3-axis
acceleration after a first-order high-pass, RC = 3.3 ms, about 48 Hz, as in common PR2
contact-detection code, at fixed levels of 2 and 5 m/s^2, `EventDetector`). Scoring: a
detection is a true positive if its onset is within +/- 10 ms of a true tap onset; each
true tap matches at most one detection (optimal one-to-one assignment by scipy's
linear_sum_assignment). Whole-array forms: research/egovib_research/experiments/scoring.py.
"""

from __future__ import annotations

import numpy as np
from scipy import optimize, signal

from egovib_ros.core.contact import (
    BURST_S,
    FALSE_ALARMS_PER_MIN,
    ONSET_FRACTION,
    REFRACTORY_S,
    THRESHOLD_MARGIN,
    ContactDetector,
    ContactSettings,
)

TOLERANCE_S = 0.010
PR2_THRESHOLDS_MS2 = (2.0, 5.0)
PR2_HIGHPASS_HZ = 1.0 / (2.0 * np.pi * 0.0033)  # first-order RC = 3.3 ms


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


def scores_of(tp: int, fp: int, fn: int) -> dict:
    """Precision, recall, F1 and the counts they come from.

    Conventions: precision = 1 when nothing is detected, recall = 1 when there
    is nothing to detect, F1 = 0 when precision + recall = 0.
    """
    precision = tp / (tp + fp) if tp + fp else 1.0
    recall = tp / (tp + fn) if tp + fn else 1.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
    return {"precision": precision, "recall": recall, "f1": f1, "tp": tp, "fp": fp, "fn": fn}


class PR2Magnitude:
    """(N,) magnitude of the high-passed raw 3-axis acceleration (the PR2 gripper
    sensor's input), with carried filter state (any chunking, the same samples)."""

    def __init__(self, *, sample_rate_hz: float):
        self.sos = signal.butter(
            1, PR2_HIGHPASS_HZ, btype="highpass", fs=sample_rate_hz, output="sos"
        )
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


class EventDetector:
    """Events where a magnitude stream exceeds `threshold`: above-threshold samples less
    than REFRACTORY_S apart are one event, whose onset is its first sample at
    ONSET_FRACTION of its peak (constant-fraction timing: block processing smears a few
    per cent of a tap up to a block before it). An event is emitted once no later sample
    can join it, or at `finish`; of an open event only its running peak and the candidate
    onsets (strict running maxima of at least that fraction of it) are kept.

    `horizon`: every onset still to come is at or after this sample."""

    def __init__(self, threshold: float, *, sample_rate_hz: float):
        self.threshold = float(threshold)
        self.gap = max(1, int(round(REFRACTORY_S * sample_rate_hz)))
        self.fraction = float(ONSET_FRACTION)
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
    """match_events' scores over onsets that arrive in order: the optimal one-to-one
    assignment splits into groups no pair within the tolerance connects, so each group is
    scored once no later onset can join it, and only counts are kept."""

    def __init__(self, *, sample_rate_hz: float):
        self.tolerance = int(round(TOLERANCE_S * sample_rate_hz))
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
        """scores_of's dict (call after `finish`)."""
        return scores_of(self.tp, self.fp, self.fn)


class OnsetStream:
    """The one contact detector (core.contact, as `egovib detect` and the contact_detector
    node run it) on a band-passed 1-D signal arriving in pieces: push(x, stamps),
    push_joints (for `motion` limits), take() -> onsets (sample indices from 0) closed since
    the last call; `horizon`: every onset still to come is at or after this sample."""

    def __init__(self, threshold: float, model, motion=None):
        self.threshold = float(threshold)
        self.detector = ContactDetector(
            ContactSettings.for_model(model, self.threshold), prefiltered=True, motion=motion
        )
        self.pos = 0
        self._onsets: list[int] = []

    @property
    def horizon(self) -> int:
        return self.detector.onsets_settled

    def push(self, x: np.ndarray, stamps: np.ndarray | None = None) -> None:
        """`stamps`: the samples' stamps, for the motion limits' joint states (the detector
        counts samples: a stream of stamps that go back, a bag's loop, is scored whole)."""
        x = np.asarray(x, float)
        index = np.arange(self.pos, self.pos + x.size, dtype=np.int64)
        self.pos += x.size
        self._onsets += [e.onset_index for e in self.detector.push(index, x, stamps)]

    def push_joints(self, stamps: np.ndarray, velocity: np.ndarray) -> None:
        self._onsets += [e.onset_index for e in self.detector.push_joints(stamps, velocity)]

    def finish(self) -> None:
        self._onsets += [e.onset_index for e in self.detector.finish()]

    def take(self) -> np.ndarray:
        onsets, self._onsets = self._onsets, []
        return np.asarray(onsets, np.int64)


class ThresholdReducer:
    """core.contact.no_contact_threshold at its default budget over an envelope arriving
    in pieces: the largest values pushed are kept (a slack of twice the budget's share,
    and 256 more, over what the quantile needs as the count grows), then the same rule."""

    def __init__(self):
        self.share = min(float(FALSE_ALARMS_PER_MIN) * BURST_S / 60.0, 0.5)  # > 0
        self.top = np.zeros(0)
        self.count = 0

    def push(self, envelope: np.ndarray) -> None:
        envelope = np.asarray(envelope, float)
        if not envelope.size:
            return
        self.count += envelope.size
        keep = int(2 * np.ceil(self.share * self.count)) + 256
        merged = np.concatenate([self.top, envelope])
        if merged.size > keep:
            merged = np.partition(merged, merged.size - keep)[-keep:]
        self.top = merged

    def threshold(self) -> float:
        if not self.count:
            raise ValueError("no calibration samples to set a detection threshold from")
        top = np.sort(self.top)
        q = 1.0 - self.share
        virtual = (self.count - 1) * q  # np.quantile's 'linear' position, in the full count
        below = int(np.floor(virtual)) - (self.count - top.size)
        if below < 0:
            raise ValueError("ThresholdReducer: the budget's quantile fell out of the kept values")
        upper = top[min(below + 1, top.size - 1)]
        return THRESHOLD_MARGIN * float(top[below] + (upper - top[below]) * (virtual % 1.0))
