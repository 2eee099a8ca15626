"""The paper's metrics (INTERFACES.md section 6) and the magnitude-threshold detector as
whole-array functions, for the experiments. `egovib evaluate` computes the same
definitions as streams (egovib_ros.evaluation: metrics, detection); the shared parts
(segment_contacts, segmental_snr, signal_figures, match_events, scores_of) live there.

Detector: an event starts where the causal RMS envelope (`envelope`, 4 ms) first
exceeds the threshold; above-threshold samples closer than the refractory time to the
previous ones belong to the same event; its onset is where the envelope first reaches
25 % of the event's peak (constant-fraction timing, robust to block pre-echo). The
threshold comes from no-contact calibration data (`threshold_from_calibration`).
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from egovib_ros.core.contact import ONSET_FRACTION, REFRACTORY_S
from egovib_ros.evaluation.detection import TOLERANCE_S, match_events, scores_of
from egovib_ros.evaluation.metrics import (
    SEGMENT_HOP,
    SEGMENT_LENGTH,
    SPIKE_QUANTILE,
    ContactSegmentation,
    segmental_snr,
    signal_figures,
)

ENVELOPE_S = 0.004  # RMS window: shorter than a tap's ring-down, longer than a noise spike
CALIBRATION_MARGIN = 1.1


# --------------------------------------------------------------------------
# Metrics
# --------------------------------------------------------------------------
def noise_mean(x: np.ndarray, no_contact_mask: np.ndarray) -> float:
    """Mean magnitude of the band-passed signal outside contacts ("mean signal magnitude")."""
    values = np.abs(np.asarray(x, float)[no_contact_mask])
    return float(values.mean()) if values.size else float("nan")


def noise_spike(
    x: np.ndarray, no_contact_mask: np.ndarray, quantile: float = SPIKE_QUANTILE
) -> float:
    """High quantile (99.9 %) of the no-contact magnitude: the noise spikes a threshold
    must clear."""
    values = np.abs(np.asarray(x, float)[no_contact_mask])
    return float(np.quantile(values, quantile)) if values.size else float("nan")


def tap_peaks(x: np.ndarray, tap_windows: np.ndarray) -> np.ndarray:
    """(T,) largest magnitude of `x` inside each tap window."""
    magnitude = np.abs(np.asarray(x, float))
    return np.array([magnitude[start:stop].max() for start, stop in tap_windows if stop > start])


def segments_in_mask(mask: np.ndarray, *, min_fraction: float = 0.5) -> np.ndarray:
    """(S,) bool: which segments (segmental_snr's) have at least `min_fraction` of their
    samples in `mask`."""
    mask = np.asarray(mask, float)
    if mask.size < SEGMENT_LENGTH:
        return np.zeros(0, bool)
    frames = np.lib.stride_tricks.sliding_window_view(mask, SEGMENT_LENGTH)[::SEGMENT_HOP]
    return frames.mean(axis=1) >= min_fraction


def mean_segmental_snr(
    reference: np.ndarray,
    estimate: np.ndarray,
    mask: np.ndarray,
    excluded: np.ndarray | None = None,
) -> float:
    """Mean clamped segmental SNR over the segments that lie in `mask` and hold no
    `excluded` sample (nan if none)."""
    values = segmental_snr(reference, estimate)
    chosen = segments_in_mask(mask)
    if excluded is not None and chosen.size:
        chosen &= ~segments_in_mask(excluded, min_fraction=1e-9)
    return float(values[chosen].mean()) if chosen.any() else float("nan")


def signal_metrics(
    raw: np.ndarray, denoised: np.ndarray, reference: np.ndarray, seg: ContactSegmentation
) -> dict:
    """The signal-quality JSON fields of INTERFACES.md section 6 (all but the event F1s).

    raw, denoised, reference: (N,) band-passed 1-D signals on the same stamps.
    """
    raw = np.asarray(raw, float)
    denoised = np.asarray(denoised, float)
    if not (raw.shape == denoised.shape == reference.shape):
        raise ValueError(
            f"signal lengths differ: raw {raw.shape}, denoised {denoised.shape}, "
            f"reference {reference.shape}"
        )

    def mean_peak(x: np.ndarray) -> float:
        peaks = tap_peaks(x, seg.tap_windows)
        return float(peaks.mean()) if peaks.size else float("nan")

    return signal_figures(
        noise=[noise_mean(x, seg.no_contact_mask) for x in (raw, denoised)],
        spike=[noise_spike(x, seg.no_contact_mask) for x in (raw, denoised)],
        peak=[mean_peak(x) for x in (raw, denoised)],
        segsnr=[
            mean_segmental_snr(reference, x, seg.active_mask, seg.excluded_mask)
            for x in (raw, denoised)
        ],
        n_taps=seg.n_taps,
    )


# --------------------------------------------------------------------------
# Detection
# --------------------------------------------------------------------------
def envelope(x: np.ndarray, *, sample_rate_hz: float, window_s: float = ENVELOPE_S) -> np.ndarray:
    """Causal moving-RMS envelope of a 1-D signal (what the threshold is applied to)."""
    x = np.asarray(x, float)
    if not x.size:
        return x.copy()
    n = max(1, int(round(window_s * sample_rate_hz)))
    power, _ = signal.lfilter(np.full(n, 1.0 / n), [1.0], x**2, zi=np.zeros(n - 1))
    return np.sqrt(np.maximum(power, 0.0))


def detect_events(
    magnitude: np.ndarray,
    threshold: float,
    *,
    sample_rate_hz: float,
    refractory_s: float = REFRACTORY_S,
    onset_fraction: float = ONSET_FRACTION,
) -> np.ndarray:
    """Onset sample indices of events where `magnitude` (an envelope) exceeds `threshold`
    (see the module doc)."""
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


def threshold_from_calibration(calibration_magnitude: np.ndarray) -> float:
    """Detection threshold from no-contact calibration data: CALIBRATION_MARGIN x the
    largest |x| (no event on the calibration data itself; the test signal is never
    looked at)."""
    values = np.abs(np.asarray(calibration_magnitude, float))
    if values.size == 0:
        raise ValueError("no calibration samples to set a detection threshold from")
    return float(CALIBRATION_MARGIN * np.quantile(values, 1.0))


def precision_recall_f1(
    detected: np.ndarray,
    truth: np.ndarray,
    *,
    sample_rate_hz: float,
    tolerance_s: float = TOLERANCE_S,
) -> dict:
    """Precision, recall, F1 (and counts) of detected onsets against true onsets."""
    return scores_of(*match_events(detected, truth, int(round(tolerance_s * sample_rate_hz))))


def evaluate_detector(
    magnitude: np.ndarray,
    truth: np.ndarray,
    threshold: float,
    *,
    sample_rate_hz: float,
    tolerance_s: float = TOLERANCE_S,
) -> dict:
    """Detect on `magnitude` at `threshold` and score against `truth` onsets."""
    onsets = detect_events(magnitude, threshold, sample_rate_hz=sample_rate_hz)
    scores = precision_recall_f1(
        onsets, truth, sample_rate_hz=sample_rate_hz, tolerance_s=tolerance_s
    )
    scores["threshold"] = float(threshold)
    return scores


def pr_curve(
    magnitude: np.ndarray, truth: np.ndarray, *, sample_rate_hz: float, n_thresholds: int = 60
) -> dict:
    """Precision/recall/F1 over a threshold sweep, log-spaced over the signal's range."""
    magnitude = np.abs(np.asarray(magnitude, float))
    positive = magnitude[magnitude > 0]
    low = np.quantile(positive, 0.5) if positive.size else 1e-6
    high = magnitude.max() if positive.size else 1.0
    thresholds = np.geomspace(low, max(high, low * 1.01), n_thresholds)
    rows = [
        evaluate_detector(magnitude, truth, t, sample_rate_hz=sample_rate_hz) for t in thresholds
    ]
    return {
        key: np.array([row[key] for row in rows])
        for key in ("threshold", "precision", "recall", "f1")
    }


def pr_curves(report: dict, sample_rate_hz: float) -> dict:
    """PR curves of the raw signal and each method's output of an `evaluate_recording`
    report made with keep_signals=True (no detection where bad input was)."""
    signals = report["signals"]
    seg = signals["seg"]
    excluded = seg.excluded_mask

    def env_kept(x: np.ndarray) -> np.ndarray:
        env = envelope(x, sample_rate_hz=sample_rate_hz)
        return env if excluded is None else np.where(excluded, 0.0, env)

    keys = ["raw", *(name for name in report["methods"] if name != "bag_denoised")]
    return {
        ("raw_bandpassed" if key == "raw" else key): pr_curve(
            env_kept(signals[key]), seg.onsets, sample_rate_hz=sample_rate_hz
        )
        for key in keys
    }
