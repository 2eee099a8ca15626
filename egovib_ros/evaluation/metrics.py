"""Paper metrics (INTERFACES.md section 6) on signals in the paper's measurement space:
axes combined and band-passed (150-750 Hz) with the *same causal filter* for the raw
signal, each method's output and the clean reference (the ground-truth contact signal),
so that all three share phase and compare sample by sample.

* noise mean: mean magnitude over no-contact samples (contacts dilated by a margin: the
  band-pass and the blocks smear a tap over its neighbours); noise spike: its 99.9th
  percentile; noise reduction: 20 log10(noise mean raw / noise mean denoised).
* tap peak: mean over taps of the largest magnitude in each tap window (onset - margin
  .. end of contact + margin); peak SNR: 20 log10(tap peak / noise mean); tap retention:
  tap peak denoised / tap peak raw (paper: 1.27/3.41 = 0.37).
* segmental SNR: on 64-sample segments with 50 % overlap, 10 log10(sum s^2 / sum (x -
  s)^2) against the reference s, clamped to [-10, 35] dB, averaged over the segments at
  least half inside a contact.

Bad samples (non-finite, or beyond the sensor's range) are missing data: bridged so that
filters stay finite, and every sample they can have touched is left out of every metric
(a tap touched by them is dropped and counted). The forms here are the streaming ones
`egovib evaluate` runs (memory bounded by the longest contact or bad run, never by the
recording); the whole-array ones: research/egovib_research/experiments/scoring.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import signal

from egovib_ros.core.stream import MAX_BAD_SHARE

SEGMENT_LENGTH = 64
SEGMENT_HOP = 32
SEGSNR_CLAMP_DB = (-10.0, 35.0)

# Contact segmentation defaults (seconds).
MARGIN_BEFORE_S = 0.010  # block smearing / pre-echo reaches up to one block (21 ms) early;
MARGIN_AFTER_S = 0.030  # the band-pass ringing and the block tail come after the contact
MIN_GAP_S = 0.030  # contact activity closer than this belongs to the same tap
SPIKE_QUANTILE = 0.999  # "noise spikes": 99.9th percentile of the no-contact magnitude
EDGE_S = 0.10  # ignore filter/denoiser start-up and flush at both ends
MAX_BAD_FRACTION = MAX_BAD_SHARE  # more bad than this: refused, not scored (as calibrate/denoise)


@dataclass(frozen=True)
class ContactSegmentation:
    """Where the ground-truth contact signal is active.

    onsets:       (T,) sample index of each tap's first active sample.
    tap_windows:  (T, 2) [start, stop) sample ranges used for per-tap peaks.
    contact_mask: (N,) bool, contact activity dilated by the margins.
    active_mask:  (N,) bool, contact activity itself (for segmental SNR).
    no_contact_mask: (N,) bool, neither contact nor the start/end edges.
    excluded_mask: (N,) bool or None, samples touched by bad input (`exclude_samples`).
    """

    onsets: np.ndarray
    tap_windows: np.ndarray
    contact_mask: np.ndarray
    active_mask: np.ndarray
    no_contact_mask: np.ndarray
    excluded_mask: np.ndarray | None = None

    @property
    def n_taps(self) -> int:
        return int(self.onsets.size)


def _runs(mask: np.ndarray) -> np.ndarray:
    """(R, 2) [start, stop) of the True runs of a 1-D bool array."""
    padded = np.concatenate(([False], np.asarray(mask, bool), [False]))
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    return edges.reshape(-1, 2)


def _merge_runs(runs: np.ndarray, min_gap: int) -> np.ndarray:
    """Merge [start, stop) runs separated by fewer than `min_gap` samples."""
    if runs.shape[0] == 0:
        return runs.reshape(0, 2)
    new_group = np.concatenate(([True], runs[1:, 0] - runs[:-1, 1] >= min_gap))
    group = np.cumsum(new_group) - 1
    starts = runs[new_group, 0]
    stops = np.zeros_like(starts)
    np.maximum.at(stops, group, runs[:, 1])
    return np.stack([starts, stops], axis=1)


def activity_threshold(contact: np.ndarray) -> float:
    """Default level above which the ground-truth contact magnitude counts as contact."""
    peak = float(np.max(np.abs(contact))) if contact.size else 0.0
    return max(1e-3 * peak, 1e-6)


def segment_contacts(
    contact: np.ndarray, *, sample_rate_hz: float, threshold: float | None = None
) -> ContactSegmentation:
    """Split a recording into taps and no-contact time from the ground-truth contact signal
    (1-D, combined axes, band-passed or not: only where it is non-negligible matters).
    Taps are the runs of |contact| > threshold, merged when closer than MIN_GAP_S."""
    contact = np.asarray(contact, dtype=float)
    n = contact.size
    level = activity_threshold(contact) if threshold is None else float(threshold)
    active = np.abs(contact) > level
    runs = _merge_runs(_runs(active), max(1, int(round(MIN_GAP_S * sample_rate_hz))))
    before = int(round(MARGIN_BEFORE_S * sample_rate_hz))
    after = int(round(MARGIN_AFTER_S * sample_rate_hz))
    windows = np.stack(
        [np.clip(runs[:, 0] - before, 0, n), np.clip(runs[:, 1] + after, 0, n)], axis=1
    )
    contact_mask = np.zeros(n, bool)
    for start, stop in windows:
        contact_mask[start:stop] = True
    active_mask = np.zeros(n, bool)
    for start, stop in runs:
        active_mask[start:stop] = True
    edge = min(int(round(EDGE_S * sample_rate_hz)), n // 2)
    no_contact = ~contact_mask
    no_contact[:edge] = False
    no_contact[n - edge :] = False
    return ContactSegmentation(
        onsets=runs[:, 0].astype(np.int64),
        tap_windows=windows.astype(np.int64),
        contact_mask=contact_mask,
        active_mask=active_mask,
        no_contact_mask=no_contact,
    )


def db20(ratio: float) -> float:
    """20 log10 of an amplitude ratio; +/-inf at the ends, nan if undefined."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(20.0 * np.log10(ratio))


def peak_snr_db(peak: float, noise: float) -> float:
    """Peak SNR = 20 log10(mean tap peak / no-contact noise mean)."""
    return db20(peak / noise) if noise > 0 else float("inf")


def segmental_snr(reference: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """Per-segment SNR in dB of `estimate` against the clean `reference`, clamped: one value
    per segment of SEGMENT_LENGTH samples starting every SEGMENT_HOP while a whole one fits."""
    length, hop, clamp_db = SEGMENT_LENGTH, SEGMENT_HOP, SEGSNR_CLAMP_DB
    reference = np.asarray(reference, float)
    error = np.asarray(estimate, float) - reference
    if reference.size < length:
        return np.zeros(0)
    ref_frames = np.lib.stride_tricks.sliding_window_view(reference, length)[::hop]
    err_frames = np.lib.stride_tricks.sliding_window_view(error, length)[::hop]
    signal_energy = np.sum(ref_frames**2, axis=1)
    error_energy = np.sum(err_frames**2, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        snr = 10.0 * np.log10(signal_energy / error_energy)
    snr = np.where(error_energy == 0, clamp_db[1], snr)  # perfect segment
    snr = np.where(signal_energy == 0, clamp_db[0], snr)  # nothing to recover
    return np.clip(snr, *clamp_db)


def signal_figures(*, noise, spike, peak, segsnr, n_taps: int) -> dict:
    """The signal-quality fields of INTERFACES.md section 6 (all but the event F1s) from the
    (raw, denoised) pairs of the figures they are made of: mean no-contact level, its
    spike, mean tap peak, segmental SNR over the contacts."""
    (noise_raw, noise_den), (peak_raw, peak_den) = noise, peak
    snr_raw = peak_snr_db(peak_raw, noise_raw)
    snr_den = peak_snr_db(peak_den, noise_den)
    return {
        "noise_mean_raw": noise_raw,
        "noise_mean_denoised": noise_den,
        "noise_reduction_db": db20(noise_raw / noise_den) if noise_den > 0 else float("inf"),
        "noise_spike_raw": spike[0],
        "noise_spike_denoised": spike[1],
        "tap_peak_raw": peak_raw,
        "tap_peak_denoised": peak_den,
        "tap_retention": peak_den / peak_raw if peak_raw > 0 else float("nan"),
        "peak_snr_raw_db": snr_raw,
        "peak_snr_denoised_db": snr_den,
        "peak_snr_improvement_db": snr_den - snr_raw,
        "segsnr_contact_raw_db": segsnr[0],
        "segsnr_contact_denoised_db": segsnr[1],
        "n_taps": n_taps,
    }


def bad_samples(values: np.ndarray, sensor_range: float = np.inf) -> tuple[np.ndarray, int, int]:
    """(N,) bool of samples (rows) that are missing data, and how many of them are
    non-finite and how many finite but beyond +/- `sensor_range` (the sensor cannot
    have measured them: corrupt data)."""
    values = np.asarray(values, float)
    if values.ndim == 1:
        values = values[:, None]
    nonfinite = ~np.all(np.isfinite(values), axis=1)
    with np.errstate(invalid="ignore"):
        beyond = ~nonfinite & np.any(np.abs(values) > sensor_range, axis=1)
    return nonfinite | beyond, int(nonfinite.sum()), int(beyond.sum())


def exclude_samples(seg: ContactSegmentation, excluded: np.ndarray) -> ContactSegmentation:
    """`seg` without the samples in `excluded` (bad input and what it touched).

    No-contact statistics skip them; a tap whose window holds one is dropped whole
    (its peak and onset would be guesses) and its window joins the excluded samples (so
    its detection counts neither way).
    """
    excluded = np.asarray(excluded, bool)
    if excluded.shape != seg.no_contact_mask.shape:
        raise ValueError(
            f"excluded mask has shape {excluded.shape}, signals {seg.no_contact_mask.shape}"
        )
    if seg.excluded_mask is not None:
        excluded = excluded | seg.excluded_mask
    if not excluded.any():
        return seg
    cumulative = np.concatenate(([0], np.cumsum(excluded)))
    windows = seg.tap_windows
    keep = cumulative[windows[:, 1]] - cumulative[windows[:, 0]] == 0
    active = np.zeros_like(seg.active_mask)
    for start, stop in windows[keep]:
        active[start:stop] = seg.active_mask[start:stop]
    excluded = excluded.copy()
    for start, stop in windows[~keep]:  # a dropped tap's detection must not count as false
        excluded[start:stop] = True
    return ContactSegmentation(
        onsets=seg.onsets[keep],
        tap_windows=windows[keep],
        contact_mask=seg.contact_mask,
        active_mask=active,
        no_contact_mask=seg.no_contact_mask & ~excluded,
        excluded_mask=excluded,
    )


def json_safe(value):
    """Replace non-finite floats (not valid JSON) by None, recursively."""
    if isinstance(value, dict):
        return {key: json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(item) for item in value]
    if isinstance(value, (np.floating, float)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.ndarray):
        return json_safe(value.tolist())
    return value


# --------------------------------------------------------------------------
# Streaming forms (evaluation/stream.py), with explicit carried state
# --------------------------------------------------------------------------
class BadRunExclusion:
    """What bridging bad samples can have disturbed (the blocks holding them, then filter
    settling), over a bad-sample flag stream: each bad run [a, b) excludes
    [a - margin, b + margin + min(b - a, settle_max)), clipped to [0, n).

    `push(flags)` appends the flags of the next samples. The exclusion of sample i is
    final once the flags up to i + margin are in (`known`)."""

    def __init__(self, *, margin: int, settle_max: int, n: int):
        self.margin, self.settle_max, self.n = int(margin), int(settle_max), int(n)
        self.intervals: list[tuple[int, int]] = []  # [start, stop) of ended runs, by start
        self.open_start: int | None = None  # first sample of a run not yet ended
        self.known = 0  # flags are in for [0, known)
        self.bad = 0

    def push(self, flags: np.ndarray) -> None:
        flags = np.asarray(flags, bool)
        p = self.known
        self.known += flags.size
        if not flags.size:
            return
        self.bad += int(np.count_nonzero(flags))
        if self.open_start is not None and not flags[0]:
            self._close(self.open_start, p)
            self.open_start = None
        for a, b in _runs(flags) + p:
            a, b = int(a), int(b)
            if a == p and self.open_start is not None:  # continues the run open before
                a, self.open_start = self.open_start, None
            if b == self.known:  # may go on in the next flags
                self.open_start = a
            else:
                self._close(a, b)

    def _close(self, start: int, stop: int) -> None:
        end = min(stop + self.margin + min(stop - start, self.settle_max), self.n)
        self.intervals.append((max(start - self.margin, 0), end))

    def finish(self) -> None:
        if self.open_start is not None:
            self._close(self.open_start, self.known)
            self.open_start = None

    def _all(self) -> list[tuple[int, int]]:
        if self.open_start is None:
            return self.intervals
        return self.intervals + [(max(self.open_start - self.margin, 0), self.n)]

    def mask(self, p: int, q: int) -> np.ndarray:
        """(q - p,) bool: excluded samples of [p, q) (final for q <= known - margin)."""
        out = np.zeros(max(q - p, 0), bool)
        for a, b in self._all():
            if a < q and b > p:
                out[max(a, p) - p : min(b, q) - p] = True
        return out

    def any_in(self, p: int, q: int) -> bool:
        return any(a < q and b > p for a, b in self._all())

    def prune(self, before: int) -> None:
        """Forget intervals that end at or before `before` (no longer asked about)."""
        self.intervals = [iv for iv in self.intervals if iv[1] > before]


@dataclass
class Tap:
    """One tap of the ground truth: a merged run of contact activity [start, stop) and its
    window [window_start, window_stop) (final once `closed`)."""

    start: int
    stop: int
    closed: bool = False
    window_start: int = 0
    window_stop: int = 0
    peaks: np.ndarray | None = None  # per metric signal, max |x| over the window so far
    kept: bool | None = None  # decided: True kept, False dropped (bad input in its window)


class ContactSegmenter:
    """`segment_contacts` over a reference stream: taps appear as their contact starts and
    close once no later activity can merge with them (MIN_GAP_S of quiet).

    The `level` is the activity threshold of the whole recording (activity_threshold of
    its reference, found by a pass before). A sample's window membership is final once
    the reference is in up to `lag` samples past it."""

    def __init__(self, *, level: float, n: int, sample_rate_hz: float):
        self.level, self.n = float(level), int(n)
        self.before = int(round(MARGIN_BEFORE_S * sample_rate_hz))
        self.after = int(round(MARGIN_AFTER_S * sample_rate_hz))
        self.min_gap = max(1, int(round(MIN_GAP_S * sample_rate_hz)))
        self.lag = self.before + self.min_gap + 1
        self.open: Tap | None = None
        self.new: list[Tap] = []  # taps started since the last `take_new`
        self.pos = 0

    def push(self, reference: np.ndarray) -> None:
        reference = np.asarray(reference, float)
        p = self.pos
        self.pos += reference.size
        active = np.flatnonzero(np.abs(reference) > self.level) + p
        if active.size:
            # a new group where the quiet before an active sample is >= min_gap
            previous = np.concatenate(([self.open.stop - 1 if self.open else -(1 << 62)], active))
            starts = np.flatnonzero(active - previous[:-1] - 1 >= self.min_gap)
            bounds = list(starts) + [active.size]
            if bounds[0] > 0:  # the first active samples continue the open tap
                self.open.stop = int(active[bounds[0] - 1]) + 1
            for k in range(len(bounds) - 1):
                if self.open is not None:
                    self._close()
                self.open = Tap(
                    start=int(active[bounds[k]]), stop=int(active[bounds[k + 1] - 1]) + 1
                )
                self.open.window_start = max(self.open.start - self.before, 0)
                self.new.append(self.open)
        if self.open is not None:
            self.open.window_stop = min(self.open.stop + self.after, self.n)
            if self.pos - self.open.stop >= self.min_gap:
                self._close()

    def _close(self) -> None:
        tap, self.open = self.open, None
        tap.window_stop = min(tap.stop + self.after, self.n)
        tap.closed = True

    def finish(self) -> None:
        if self.open is not None:
            self._close()

    def take_new(self) -> list[Tap]:
        new, self.new = self.new, []
        return new


class TopValues:
    """The largest `capacity` values pushed (and how many were pushed): enough for an exact
    `quantile(q)` of everything pushed as long as (1 - q) * count + 3 <= capacity."""

    def __init__(self, capacity: int):
        self.capacity = max(int(capacity), 0)
        self.values = np.zeros(0)
        self.count = 0

    @classmethod
    def for_quantile(cls, quantile: float, max_count: int) -> "TopValues":
        return cls(int(math.ceil((1.0 - quantile) * max_count)) + 3)

    def push(self, values: np.ndarray) -> None:
        values = np.asarray(values, float)
        self.count += values.size
        if not values.size or not self.capacity:
            return
        merged = np.concatenate([self.values, values])
        if merged.size > self.capacity:
            merged = np.partition(merged, merged.size - self.capacity)[-self.capacity :]
        self.values = merged

    def quantile(self, quantile: float) -> float:
        """np.quantile(all values pushed, quantile) ('linear'), from the largest ones kept."""
        m = self.count
        if m == 0:
            return float("nan")
        top = np.sort(self.values)
        virtual = (m - 1) * quantile
        if virtual >= m - 1:
            return float(top[-1])
        below = int(math.floor(virtual))
        gamma = virtual - below
        first = below - (m - top.size)  # index into the kept values
        if first < 0:
            raise ValueError("TopValues: capacity too small for this quantile")
        a, b = top[first], top[first + 1]
        diff = b - a
        return float(b - diff * (1 - gamma) if gamma >= 0.5 else a + diff * gamma)


class LagCorrelation:
    """The lag (samples, positive: `x` late) of `x` relative to `reference` maximising their
    cross-correlation sum_n x[n + lag] ref[n] over |lag| <= max_lag, over two streams,
    accumulated as pairs complete (history of max_lag samples). The output sample k of
    every method carries input stamp k: this checks it (expected 0)."""

    def __init__(self):
        self.max_lag = 96
        self.corr = np.zeros(2 * self.max_lag + 1)
        self._ref = np.zeros(0)
        self._x = np.zeros(0)
        self.count = 0

    def push(self, reference: np.ndarray, x: np.ndarray) -> None:
        m = len(reference)
        if not m:
            return
        lag_max, o = self.max_lag, len(self._ref)
        ref = np.concatenate([np.zeros(lag_max - o), self._ref, np.asarray(reference, float)])
        xs = np.concatenate([np.zeros(lag_max - o), self._x, np.asarray(x, float)])
        # FFT correlation (a direct sum is slow on a reference that decays into subnormal
        # numbers between taps). Pairs whose later sample is in this piece:
        # x[j] ref[j - lag] (lag >= 0) and ref[j] x[j + lag] (lag < 0), j in the piece.
        late = signal.correlate(ref, xs[lag_max:], mode="valid", method="fft")  # lag L .. 0
        early = signal.correlate(xs, ref[lag_max:], mode="valid", method="fft")  # -L .. 0
        self.corr[lag_max:] += late[::-1]
        self.corr[:lag_max] += early[:lag_max]
        self._ref, self._x = ref[-lag_max:], xs[-lag_max:]
        self.count += m

    def lag(self) -> int:
        lags = np.arange(-self.max_lag, self.max_lag + 1)
        keep = np.abs(lags) <= max(self.count - 1, 0)
        return int(lags[keep][np.argmax(self.corr[keep])])
