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

Where the robot moves as its calibration never did (`MotionLimits`: a joint faster or
slower than anywhere in the calibration data, or the joints accelerating harder),
its own transients are ego-vibration no model knows, as strong and short as a contact (a
quadcopter's take-off, its motors cut and restarted): for MOTION_HOLD_S after such a joint
state the threshold is `factor` times higher (the raw signal's threshold over the method's:
there the output must stand out as far as the raw signal would). What stays above the
base threshold but below the raised one is the robot's own, and so is its continuation past
the raised span (no event where the raising ends). With limits, a sample is decided once
the joint states reach its stamp, or once `release` lets it go without them (live: a joint
topic that stalls does not stall detection).

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
#: Joint acceleration: the summed change of the joints' speeds over this long (not between
#: two joint states: their jitter would make it), per second.
MOTION_ACCEL_S = 0.01
#: How long the threshold stays raised after a joint state beyond the limits: a transient
#: of the robot's rings down in tens of ms (20 ms let half of a flight's through).
MOTION_HOLD_S = 0.05


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


@dataclass(frozen=True, kw_only=True)
class MotionLimits:
    """The motion calibration held (see the module doc): per joint, the lowest and highest
    speed (core.methods.calibrate_detection: those of its data, a margin past them); the
    largest joint acceleration (`joint_acceleration`) of its data; the threshold's factor
    beyond them (>= 1)."""

    speed_low: tuple[float, ...]
    speed_high: tuple[float, ...]
    accel: float
    factor: float

    def __post_init__(self) -> None:
        if len(self.speed_low) != len(self.speed_high):
            raise ConfigError("motion limits: one low and one high speed per joint")
        if not (self.accel > 0 and not math.isnan(self.accel)):
            raise ConfigError(f"motion limits: accel must be > 0, got {self.accel!r}")
        if not (math.isfinite(self.factor) and self.factor >= 1.0):
            raise ConfigError(f"motion limits: factor must be a number >= 1, got {self.factor!r}")


def joint_acceleration(
    stamps_ns: np.ndarray, velocity: np.ndarray, before: tuple | None = None
) -> np.ndarray:
    """Per joint state, the summed |change| of the joints' speeds since the last state at
    least MOTION_ACCEL_S before it, over the time between them (0 where there is none; NaN
    speeds left out): the same at any joint-state rate. `before`: (stamps, velocity) of
    earlier states to look back into."""
    stamps_ns = np.asarray(stamps_ns, np.int64).reshape(-1)
    if not len(stamps_ns):
        return np.zeros(0)
    velocity = np.asarray(velocity, np.float64).reshape(len(stamps_ns), -1)
    if before is not None:
        all_stamps = np.concatenate([before[0], stamps_ns])
        all_velocity = np.vstack([before[1], velocity])
    else:
        all_stamps, all_velocity = stamps_ns, velocity
    step = int(MOTION_ACCEL_S * NS_PER_S)
    back = np.searchsorted(all_stamps, stamps_ns - step, side="right") - 1
    change = np.abs(velocity - all_velocity[np.maximum(back, 0)])
    elapsed = (stamps_ns - all_stamps[np.maximum(back, 0)]) / NS_PER_S
    return np.where(back >= 0, np.nansum(change, axis=1) / np.maximum(elapsed, 1e-9), 0.0)


class MotionGuard:
    """The threshold's factor per sample from the joint states (MotionLimits): push the
    joint states in order, then ask `factors` for samples the joint states `reach`. A joint
    clock that restarts (a bag's loop) begins an epoch; samples of the detector's k-th
    epoch (its own restarts) read the joint states of the k-th, whatever arrived first."""

    def __init__(self, limits: MotionLimits):
        self.limits = limits
        self._low, self._high = np.array(limits.speed_low), np.array(limits.speed_high)
        self._marks: list[np.ndarray] = []  # per epoch: stamps of joint states beyond
        self._covered: list[int] = []  # per epoch: its latest joint stamp
        self._restart()

    def _restart(self) -> None:
        self._history = (np.zeros(0, np.int64), np.zeros((0, len(self._low))))
        self._marks.append(np.zeros(0, np.int64))
        self._covered.append(-1)

    def push(self, stamps_ns: np.ndarray, velocity: np.ndarray) -> None:
        stamps_ns = np.asarray(stamps_ns, np.int64).reshape(-1)
        if not len(stamps_ns):
            return
        velocity = np.asarray(velocity, np.float64).reshape(len(stamps_ns), -1)
        latest = None if self._covered[-1] < 0 else self._covered[-1]
        keep, jump = stamp_order(latest, stamps_ns, int(CLOCK_JUMP_S * NS_PER_S))
        if jump is not None:  # a restarted joint clock: what came before is another time
            self.push(stamps_ns[:jump], velocity[:jump])
            self._restart()
            self.push(stamps_ns[jump:], velocity[jump:])
            return
        stamps_ns, velocity = stamps_ns[keep], velocity[keep]
        if not len(stamps_ns):
            return
        accel = joint_acceleration(stamps_ns, velocity, self._history)
        with np.errstate(invalid="ignore"):  # NaN speeds: unknown, not beyond
            fast = np.any((velocity < self._low) | (velocity > self._high), axis=1)
        beyond = fast | (accel > self.limits.accel)
        self._marks[-1] = np.concatenate([self._marks[-1], stamps_ns[beyond]])
        self._covered[-1] = int(stamps_ns[-1])
        stamps = np.concatenate([self._history[0], stamps_ns])
        step = int(MOTION_ACCEL_S * NS_PER_S)
        first = max(np.searchsorted(stamps, stamps[-1] - step, side="right") - 1, 0)
        self._history = (stamps[first:], np.vstack([self._history[1], velocity])[first:])

    def reach(self, epoch: int) -> float:
        """How far the joint states of `epoch` reach (stamp; inf once a later one began;
        a sensor clock restarted alone reads the latest)."""
        if epoch < len(self._covered) - 1:
            return math.inf
        return self._covered[-1]

    def factors(self, stamps_ns: np.ndarray, epoch: int = 0) -> np.ndarray:
        """The factor for samples of `epoch` (stamps in order): `factor` within
        MOTION_HOLD_S after a joint state beyond the limits, else 1; marks before these
        samples' reach dropped."""
        stamps_ns = np.asarray(stamps_ns, np.int64)
        e = min(epoch, len(self._marks) - 1)
        marks = self._marks[e]
        if not len(marks) or not len(stamps_ns):
            return np.ones(len(stamps_ns))
        hold = int(MOTION_HOLD_S * NS_PER_S)
        last = np.searchsorted(marks, stamps_ns, side="right") - 1
        marked = (last >= 0) & (stamps_ns - marks[np.maximum(last, 0)] < hold)
        self._marks[e] = marks[max(np.searchsorted(marks, stamps_ns[-1] - hold) - 1, 0) :]
        return np.where(marked, self.limits.factor, 1.0)


@dataclass(frozen=True)
class ContactEvent:
    onset_ns: int  # stamp of the onset sample
    peak: tuple[float, float, float]  # band-passed vector at the event's largest sample
    strength: float  # envelope peak (what was thresholded)
    crossing_ns: int  # stamp where the envelope crossed the threshold
    report_ns: int  # stamp of the sample after which the event was reported
    onset_index: int = -1  # the onset sample's place among every sample pushed (from 0)


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

    def __init__(
        self,
        settings: ContactSettings,
        *,
        prefiltered: bool = False,
        motion: MotionLimits | None = None,
    ):
        self.s = settings
        self._prefiltered = prefiltered
        self._guard = None if motion is None else MotionGuard(motion)
        self._released = -1  # samples stamped up to here are decided without joint states
        self._decided = 0  # global index of the first sample not compared with the threshold
        self.samples_motion = 0  # samples decided at the raised threshold
        self._envelope = DetectionEnvelope(settings, prefiltered=prefiltered)
        self._gap = settings.samples(settings.refractory_s)
        self._after = settings.samples(settings.report_after_s)
        self._back = settings.samples(settings.lookback_s)
        # history of the last samples (for onsets and peaks): global index of its first row
        self._base = 0
        self._stamps = np.zeros(0, np.int64)
        self._clock = np.zeros(0, np.int64)  # the same samples on the joint states' clock
        self._env = np.zeros(0)
        self._axes = np.zeros((0, 3))
        self._last_above: int | None = None  # global index of the last above-threshold sample
        self._last_own: int | None = None  # ... above the base one, but the robot's own
        self._pending: list[int] = []  # crossings whose report is not due yet
        self._last_good = np.zeros(3)  # what a bad sample is held at
        self._last_stamp: int | None = None  # the latest stamp accepted since the (re)start
        self.samples = 0
        self.samples_bad = 0
        self.samples_out_of_order = 0
        self.restarts = 0
        self.events = 0

    def push(
        self, stamps_ns: np.ndarray, values: np.ndarray, clock: np.ndarray | None = None
    ) -> list[ContactEvent]:
        """Events reported by the end of these samples (stamps (N,), values (N, 3); with
        `prefiltered`, the band-passed 1-D signal (N,)). `clock`: the samples' times on the
        joint states' clock, where the stamps are not (`egovib evaluate` counts samples)."""
        stamps_ns = np.asarray(stamps_ns, np.int64).reshape(-1)
        clock = stamps_ns if clock is None else np.asarray(clock, np.int64).reshape(-1)
        values = np.asarray(values, np.float64)
        values = (_as_x(values) if self._prefiltered else values).reshape(-1, 3)
        if not len(stamps_ns):
            return []
        keep, i = stamp_order(self._last_stamp, stamps_ns, int(CLOCK_JUMP_S * NS_PER_S))
        if i is not None:  # a restarted clock: what came before, a fresh start, what follows
            events = self.push(stamps_ns[:i], values[:i], clock[:i]) + self._restart()
            return events + self.push(stamps_ns[i:], values[i:], clock[i:])
        if not keep.all():
            self.samples_out_of_order += int((~keep).sum())
            stamps_ns, values, clock = stamps_ns[keep], values[keep], clock[keep]
            if not len(stamps_ns):
                return []
        self._last_stamp = int(stamps_ns[-1])
        values = self._hold_bad(values)
        axes, envelope = self._envelope.process(values)
        self._clock = np.concatenate([self._clock, clock])
        self._stamps = np.concatenate([self._stamps, stamps_ns])
        self._env = np.concatenate([self._env, envelope])
        self._axes = np.concatenate([self._axes, axes])
        self.samples += len(stamps_ns)
        return self._advance()

    def push_joints(self, stamps_ns: np.ndarray, velocity: np.ndarray) -> list[ContactEvent]:
        """Joint states (stamps (M,), velocities (M, J)) for the motion limits; events that
        the samples they decide report (none without limits)."""
        if self._guard is None:
            return []
        self._guard.push(stamps_ns, velocity)
        return self._advance()

    def release(self, upto_ns: int) -> list[ContactEvent]:
        """Samples stamped up to `upto_ns` are decided with the joint states in by now
        (live, after waiting for them long enough); the events that reports."""
        self._released = max(self._released, int(upto_ns))
        return self._advance()

    def _advance(self) -> list[ContactEvent]:
        self._decide(final=False)
        events = self._report(final=False)
        self._trim()
        return events

    def _decide(self, *, final: bool) -> None:
        """Threshold the samples that can be: all without motion limits (or at the end),
        else those the joint states reach or `release` let go."""
        end = self._base + len(self._stamps)
        upto = end
        if self._guard is not None and not final:
            reach = max(self._guard.reach(self.restarts), self._released)
            # the samples up to the first one beyond (a clock may go back: a bag's loop)
            beyond = self._clock[self._decided - self._base :] > reach
            first = int(np.argmax(beyond)) if beyond.any() else len(beyond)
            upto = self._decided + first
        if upto <= self._decided:
            return
        lo, hi = self._decided - self._base, upto - self._base
        env = self._env[lo:hi]
        factors = (
            np.ones(hi - lo)
            if self._guard is None
            else self._guard.factors(self._clock[lo:hi], self.restarts)
        )
        self.samples_motion += int(np.count_nonzero(factors > 1.0))
        for k in np.flatnonzero(env > self.s.threshold).tolist():
            i = k + self._decided
            if self._last_above is not None and i - self._last_above < self._gap:
                self._last_above = i  # an event going on, as long as it stays above
                continue
            quiet_since = None if self._last_own is None else i - self._last_own
            if (factors[k] > 1.0 and env[k] <= self.s.threshold * factors[k]) or (
                factors[k] == 1.0 and quiet_since is not None and quiet_since < self._gap
            ):
                # below the raised threshold, the robot's own; and so is what goes on from
                # it where the raising ends (no event at the end of a raised span)
                self._last_own = i
                continue
            self._pending.append(i)
            self._last_above = i
        self._decided = upto

    def _restart(self) -> list[ContactEvent]:
        """The clock went back: report what is pending, then detect afresh (filter state,
        history and refractory time cleared)."""
        events = self.finish()
        self._envelope = DetectionEnvelope(self.s, prefiltered=self._prefiltered)
        self._base += len(self._stamps)
        self._decided = self._base
        self._stamps, self._env, self._axes = np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))
        self._clock = np.zeros(0, np.int64)
        self._last_above, self._pending, self._last_stamp = None, [], None
        self._last_own = None
        self.restarts += 1
        return events

    def _hold_bad(self, values: np.ndarray) -> np.ndarray:
        """Bad samples counted and replaced by the last good one (carried across pushes)."""
        values, bad = hold_bad(values, self.s.sensor_range, self._last_good)
        self.samples_bad += bad
        self._last_good = values[-1].copy()
        return values

    def finish(self) -> list[ContactEvent]:
        """End of stream: the samples not decided yet decided with the joint states in,
        and events whose report falls after the last sample, reported now."""
        self._decide(final=True)
        return self._report(final=True)

    @property
    def onsets_settled(self) -> int:
        """Every onset still to be reported lies at or after this sample (counted from the
        first sample pushed): the pending crossings' and the next one's look-back."""
        first = self._pending[0] if self._pending else self._decided
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
                    onset_index=onset,
                )
            )
        self.events += len(events)
        return events

    def _trim(self) -> None:
        """Keep what a pending or a future event may still look back at."""
        end = self._base + len(self._stamps)
        keep_from = min(end - self._back - self._after, self._decided - self._back)
        if self._pending:
            keep_from = min(keep_from, self._pending[0] - self._back)
        cut = max(0, keep_from - self._base)
        if cut > 4096:
            self._clock = self._clock[cut:]
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
