"""Contact events from a sensor stream: the detector of the contact_detector node and of
`egovib detect` (live and offline call the same class; any chunking gives the same events).

The signal: the three axes band-passed and summed (the paper's 1-D signal, which `egovib
evaluate` scores; a contact along (1, -1, 0) is seen weakly, as there), then a 4 ms causal
RMS envelope. An event starts where the envelope crosses a threshold set from no-contact
data (`no_contact_threshold`); crossings within `refractory_s` belong to it. It is reported
`report_after_s` (10 ms) after its crossing, whatever its length, with its onset (the first
sample, at most `lookback_s` before the crossing, where the envelope reaches
`onset_fraction` of its peak so far) and peak (the band-passed vector of largest magnitude
from the onset to the report: the contact's direction; strength: the envelope's peak).

The input may be raw or denoised (thresholds from data processed alike). A bad sample
(non-finite, or beyond `sensor_range`) is counted and held at the last good value (one NaN
in the band-pass would end detection for good); a sample stamped at or before an earlier
one is dropped; stamps back by more than CLOCK_JUMP_S restart detection (counted).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import signal

from egovib_ros.core.filters import BandPass
from egovib_ros.core.stream import bad_samples, stamp_order
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import ConfigError

ENVELOPE_S = 0.004  # RMS window: shorter than a tap's ring-down, longer than a noise spike
REFRACTORY_S = 0.05
ONSET_FRACTION = 0.25
THRESHOLD_MARGIN = 1.1  # the threshold: 1.1 x the no-contact envelope's level ...
#: ... that the no-contact envelope stays above for at most this long per false alarm allowed
#: per minute: an isolated burst (a speed step of a sweep, a gripper reversing) does not set it.
BURST_S = 0.02
#: The default false-alarm budget (per minute of no-contact data).
FALSE_ALARMS_PER_MIN = 1.0
CLOCK_JUMP_S = 1.0  # stamps this far back: a restarted clock (as core.stream's default)


@dataclass(frozen=True, kw_only=True)
class ContactSettings:
    """How events are found; validated on construction (one-line ConfigError)."""

    sample_rate_hz: float
    band_hz: tuple[float, float]
    band_order: int = 4
    threshold: float  # on the envelope, in the sensor field's unit
    envelope_s: float = ENVELOPE_S
    refractory_s: float = REFRACTORY_S
    onset_fraction: float = ONSET_FRACTION
    report_after_s: float = 0.010
    lookback_s: float = 0.010
    sensor_range: float = math.inf  # |value| beyond this on any axis: a bad sample

    def __post_init__(self) -> None:
        for name in ("sample_rate_hz", "threshold", "envelope_s", "refractory_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ConfigError(f"contact detector: {name} must be a number > 0, got {value!r}")
        for name in ("report_after_s", "lookback_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and 0 <= value <= 1.0):
                raise ConfigError(f"contact detector: {name} must be in [0, 1] s, got {value!r}")
        if not (isinstance(self.sensor_range, (int, float)) and self.sensor_range > 0):
            raise ConfigError(
                f"contact detector: sensor_range must be a number > 0, got {self.sensor_range!r}"
            )
        if not 0 < self.onset_fraction <= 1:
            raise ConfigError(
                f"contact detector: onset_fraction must be in (0, 1], got {self.onset_fraction!r}"
            )

    def samples(self, seconds: float) -> int:
        return max(1, int(round(seconds * self.sample_rate_hz)))

    @classmethod
    def for_model(cls, model, threshold: float, **options) -> "ContactSettings":
        """The settings for a noise model's stream (its rate, band and sensor range)."""
        return cls(
            sample_rate_hz=model.sample_rate_hz,
            band_hz=model.band_hz,
            band_order=model.band_order,
            threshold=threshold,
            sensor_range=model.robot_profile().sensor_range,
            **options,
        )


@dataclass(frozen=True)
class ContactEvent:
    onset_ns: int  # stamp of the onset sample
    peak: tuple[float, float, float]  # band-passed vector at the event's largest sample
    strength: float  # envelope peak (what was thresholded)
    crossing_ns: int  # stamp where the envelope crossed the threshold
    report_ns: int  # stamp of the sample after which the event was reported


def _as_x(signal_1d: np.ndarray) -> np.ndarray:
    """(N,) -> (N, 3) with the signal on x."""
    out = np.zeros((signal_1d.size, 3))
    out[:, 0] = signal_1d.reshape(-1)
    return out


class DetectionEnvelope:
    """The signal the detector thresholds, as a stream: the three axes band-passed, then the
    causal RMS of their sum over `envelope_s`. `process` returns (band-passed axes (N, 3),
    envelope (N,)); any chunking gives the same samples."""

    def __init__(self, settings: ContactSettings, *, prefiltered: bool = False):
        # prefiltered: the input is the 1-D signal, summed and band-passed already (what
        # `egovib evaluate` scores every method on), taken as the x axis
        self._band = None if prefiltered else BandPass.of(settings, 3)
        self._n = settings.samples(settings.envelope_s)
        self._tail = np.zeros(self._n - 1)  # the last n - 1 squared sums (zeros before the start)

    def process(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        values = np.asarray(values, np.float64)
        if self._band is None and values.ndim == 1:
            values = _as_x(values)
        values = values.reshape(-1, 3)
        if not len(values):
            return np.zeros((0, 3)), np.zeros(0)
        axes = values if self._band is None else self._band.process(values.T).T
        # Moving mean over n samples, added tap by tap in a fixed order: every output sums the
        # same values in the same order whatever the chunking (lfilter's FIR state does not:
        # it differs in the last bit between chunkings).
        squared = np.concatenate([self._tail, axes.sum(axis=1) ** 2])
        total = np.zeros(len(values))
        for k in range(self._n):
            total += squared[k : k + len(values)]
        self._tail = squared[len(values) :]
        return axes, np.sqrt(total / self._n)


class ContactDetector:
    """Streaming contact-event detector (see the module doc).

    >>> detector = ContactDetector(ContactSettings(sample_rate_hz=3000, band_hz=(150, 750),
    ...                                           threshold=0.4))
    >>> events = detector.push(stamps_ns, values)   # (N,), (N, 3): any chunk sizes
    >>> events += detector.finish()
    """

    def __init__(self, settings: ContactSettings, *, prefiltered: bool = False):
        self.s = settings
        self._prefiltered = prefiltered
        self._envelope = DetectionEnvelope(settings, prefiltered=prefiltered)
        self._gap = settings.samples(settings.refractory_s)
        self._after = settings.samples(settings.report_after_s)
        self._back = settings.samples(settings.lookback_s)
        # history of the last samples (for onsets and peaks): global index of its first row
        self._base = 0
        self._stamps = np.zeros(0, np.int64)
        self._env = np.zeros(0)
        self._axes = np.zeros((0, 3))
        self._last_above: int | None = None  # global index of the last above-threshold sample
        self._pending: list[int] = []  # crossings whose report is not due yet
        self._last_good = np.zeros(3)  # what a bad sample is held at
        self._last_stamp: int | None = None  # the latest stamp accepted since the (re)start
        self.samples = 0
        self.samples_bad = 0
        self.samples_out_of_order = 0
        self.restarts = 0
        self.events = 0

    def push(self, stamps_ns: np.ndarray, values: np.ndarray) -> list[ContactEvent]:
        """Events reported by the end of these samples (stamps (N,), values (N, 3); with
        `prefiltered`, the band-passed 1-D signal (N,))."""
        stamps_ns = np.asarray(stamps_ns, np.int64).reshape(-1)
        values = np.asarray(values, np.float64)
        values = (_as_x(values) if self._prefiltered else values).reshape(-1, 3)
        if not len(stamps_ns):
            return []
        keep, i = stamp_order(self._last_stamp, stamps_ns, int(CLOCK_JUMP_S * NS_PER_S))
        if i is not None:  # a restarted clock: what came before, a fresh start, what follows
            events = self.push(stamps_ns[:i], values[:i]) + self._restart()
            return events + self.push(stamps_ns[i:], values[i:])
        if not keep.all():
            self.samples_out_of_order += int((~keep).sum())
            stamps_ns, values = stamps_ns[keep], values[keep]
            if not len(stamps_ns):
                return []
        self._last_stamp = int(stamps_ns[-1])
        values = self._hold_bad(values)
        axes, envelope = self._envelope.process(values)
        start = self._base + len(self._stamps)
        self._stamps = np.concatenate([self._stamps, stamps_ns])
        self._env = np.concatenate([self._env, envelope])
        self._axes = np.concatenate([self._axes, axes])
        for i in (np.flatnonzero(envelope > self.s.threshold) + start).tolist():
            if self._last_above is None or i - self._last_above >= self._gap:
                self._pending.append(i)
            self._last_above = i
        self.samples += len(stamps_ns)
        events = self._report(final=False)
        self._trim()
        return events

    def _restart(self) -> list[ContactEvent]:
        """The clock went back: report what is pending, then detect afresh (filter state,
        history and refractory time cleared)."""
        events = self._report(final=True)
        self._envelope = DetectionEnvelope(self.s, prefiltered=self._prefiltered)
        self._base += len(self._stamps)
        self._stamps, self._env, self._axes = np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))
        self._last_above, self._pending, self._last_stamp = None, [], None
        self.restarts += 1
        return events

    def _hold_bad(self, values: np.ndarray) -> np.ndarray:
        """Bad samples counted and replaced by the last good one (carried across pushes)."""
        values, bad = hold_bad(values, self.s.sensor_range, self._last_good)
        self.samples_bad += bad
        self._last_good = values[-1].copy()
        return values

    def finish(self) -> list[ContactEvent]:
        """End of stream: events whose report falls after the last sample, reported now."""
        return self._report(final=True)

    @property
    def onsets_settled(self) -> int:
        """Every onset still to be reported lies at or after this sample (counted from the
        first sample pushed): the pending crossings' and the next one's look-back."""
        end = self._base + len(self._stamps)
        first = self._pending[0] if self._pending else end
        return max(first - self._back, 0)

    def _report(self, *, final: bool) -> list[ContactEvent]:
        end = self._base + len(self._stamps)  # global index past the last sample
        events = []
        while self._pending and (final or self._pending[0] + self._after <= end):
            crossing = self._pending.pop(0)
            report = min(crossing + self._after, end)
            first = max(crossing - self._back, self._base)
            env = self._env[first - self._base : report - self._base]
            running = np.maximum.accumulate(env)
            onset = first + int(np.argmax(env >= self.s.onset_fraction * running[-1]))
            axes = self._axes[onset - self._base : report - self._base]
            peak = axes[int(np.argmax(np.square(axes).sum(axis=1)))]
            events.append(
                ContactEvent(
                    onset_ns=int(self._stamps[onset - self._base]),
                    peak=tuple(float(v) for v in peak),
                    strength=float(running[-1]),
                    crossing_ns=int(self._stamps[crossing - self._base]),
                    report_ns=int(self._stamps[report - 1 - self._base]),
                )
            )
        self.events += len(events)
        return events

    def _trim(self) -> None:
        """Keep what a pending or a future event may still look back at."""
        end = self._base + len(self._stamps)
        keep_from = end - self._back - self._after
        if self._pending:
            keep_from = min(keep_from, self._pending[0] - self._back)
        cut = max(0, keep_from - self._base)
        if cut > 4096:
            self._stamps, self._env, self._axes = (
                self._stamps[cut:],
                self._env[cut:],
                self._axes[cut:],
            )
            self._base += cut


def hold_bad(
    values: np.ndarray, sensor_range: float, last_good: np.ndarray | None = None
) -> tuple[np.ndarray, int]:
    """(values with each bad sample replaced by the last good one before it (`last_good`,
    zeros by default, before the first), how many were bad)."""
    values = np.asarray(values, np.float64)
    bad = bad_samples(values, sensor_range)
    if not bad.any():
        return values, 0
    # index of the last good row at or before each row (-1: before these values)
    last = np.maximum.accumulate(np.where(bad, -1, np.arange(len(values))))
    first = np.zeros(3) if last_good is None else last_good
    return np.vstack([first[None], values])[last + 1], int(bad.sum())


def no_contact_threshold(
    envelope: np.ndarray,
    *,
    sample_rate_hz: float,
    false_alarms_per_min: float = FALSE_ALARMS_PER_MIN,
    refractory_s: float = REFRACTORY_S,
    margin: float = THRESHOLD_MARGIN,
) -> tuple[float, float]:
    """(threshold, false alarms per minute it gives here) from the detection envelope of
    no-contact data: `margin` x the level it stays above for `false_alarms_per_min` x
    BURST_S seconds per minute (budget 0: its largest value). The one threshold rule; a
    quantile, so a short recording is not set by its single largest burst."""
    envelope = np.asarray(envelope, np.float64)
    if not envelope.size:
        raise ConfigError("no no-contact samples to set a detection threshold from")
    if not (math.isfinite(false_alarms_per_min) and false_alarms_per_min >= 0):
        raise ConfigError(
            f"false_alarms_per_min must be a number >= 0, got {false_alarms_per_min!r}"
        )
    share = min(false_alarms_per_min * BURST_S / 60.0, 0.5)
    threshold = margin * float(np.quantile(envelope, 1.0 - share) if share > 0 else envelope.max())
    minutes = envelope.size / sample_rate_hz / 60.0
    gap = max(1, int(round(refractory_s * sample_rate_hz)))
    above = envelope[signal.find_peaks(envelope, distance=gap)[0]] > threshold
    return threshold, float(np.count_nonzero(above)) / minutes if minutes > 0 else 0.0
