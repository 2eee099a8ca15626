"""The evaluation as a stream: `egovib evaluate` over a recording pushed in time slices
(`Recording`s, as `bag.iter_recording` yields them), in memory that does not grow with it;
`evaluate.evaluate_recording` pushes whole arrays as one slice through the same objects.

Passes over the test recording (and the calibration recording):

1. `SummaryPass` (test): what the evaluation needs of the whole run first: the sample
   count, the peak of the ground-truth reference (the contact activity threshold is 1e-3
   of it), the bad-sample counts (more than `max_bad_fraction` bad is refused before any
   other work) and what kind of output the bag's own denoised topic holds, if any.
2. `CalibrationPass` (calibration data): every method on the no-contact data, reduced to
   one detection threshold per method by the rule of `egovib detect` and the
   contact_detector node (detection.ThresholdReducer), and noisereduce's noise threshold
   (from its first 200 s). Without calibration data an `EvaluationPass` without
   thresholds takes its place: the same rule on the run's own no-contact samples.
3. `EvaluationPass` (test): every method as a stream (`baselines.method_stream`) and the
   metrics as accumulators (metrics, detection). A sample is scored once every signal has
   it and its contact and bad-input status is final: held are a run of bad samples until
   the next good one, each method's delay, the bag's denoised topic until its stamps pass
   (at most 10 s), the contact segmentation's margins, one block around bad samples, and
   what lies in a tap's window until the tap is known to be kept or dropped. Nothing is
   held for the whole run but counts, sums and the largest 0.1 % of the no-contact
   magnitudes (the 99.9 % spike quantile, exact).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy import signal

from egovib_ros.bag.recording import bag_topic_names
from egovib_ros.core import NoiseModel
from egovib_ros.core.contact import ContactSettings, DetectionEnvelope
from egovib_ros.core.filters import BandPass, channel_matrix
from egovib_ros.core.methods import SAMPLE_METHODS, has_method_calibration, motion_limits
from egovib_ros.core.stream import FramerSettings, check_joint_share, stamp_order
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import BagError, ConfigError, StreamError, bag_error
from egovib_ros.evaluation import baselines, detection, metrics

CLOCK_JUMP_NS = int(FramerSettings.clock_jump_s * NS_PER_S)  # a restarted clock, as the framers'
SEGMENT_ACTIVE_MIN = metrics.SEGMENT_LENGTH // 2  # segments at least half inside a contact
RECORDED_MAX_WAIT_S = 10.0  # the bag's denoised topic may lag its raw samples this much


def _combined(values: np.ndarray) -> np.ndarray:
    return channel_matrix(values, "combined").T


def _envelope(model: NoiseModel) -> DetectionEnvelope:
    """The one detector's envelope of a band-passed 1-D signal."""
    return DetectionEnvelope(ContactSettings.for_model(model, 1.0), prefiltered=True)


class LowBandEnergy:
    """Energy of a signal far below the band (below a quarter of its low edge; 2nd-order
    Butterworth low-pass, state carried across slices)."""

    def __init__(self, model: NoiseModel):
        self.sos = signal.butter(
            2, model.band_hz[0] / 4, btype="lowpass", fs=model.sample_rate_hz, output="sos"
        )
        self.zi = np.zeros((self.sos.shape[0], 2))
        self.energy = 0.0

    def push(self, values: np.ndarray) -> None:
        if len(values):
            low, self.zi = signal.sosfilt(self.sos, values, zi=self.zi)
            self.energy += float(np.dot(low, low))


class _Fifo:
    """Samples of one signal from index `start` on: put at the end, taken from the front."""

    def __init__(self, dtype=float):
        self.parts: list[np.ndarray] = []
        self.start = self.end = 0
        self.dtype = dtype

    def put(self, values: np.ndarray) -> None:
        if len(values):
            self.parts.append(values)
            self.end += len(values)

    def take(self, stop: int) -> np.ndarray:
        """Samples [start, stop)."""
        n = stop - self.start
        if n <= 0:
            return np.zeros(0, self.dtype)
        data = self.parts[0] if len(self.parts) == 1 else np.concatenate(self.parts)
        head, rest = data[:n], data[n:]
        self.parts = [rest] if len(rest) else []
        self.start = stop
        return head


# --------------------------------------------------------------------------
# Input: bad samples, the bag's own denoised topic
# --------------------------------------------------------------------------
class Screen:
    """Bad samples (metrics.bad_samples) over streams of (N, 3) samples on the same stamps:
    a bad sample (non-finite or beyond its stream's range) is bridged linearly between
    the good samples either side (held at the ends), so it is released once the next good
    sample of its stream is in. Counts per stream: `nonfinite`, `beyond`."""

    def __init__(self, ranges: Sequence[float]):
        self.ranges = list(ranges)
        k = len(self.ranges)
        self.base = 0
        self.stamps = np.zeros(0, np.int64)
        self.values = [np.zeros((0, 3)) for _ in range(k)]
        self.bad = [np.zeros(0, bool) for _ in range(k)]
        self.anchor: list[tuple[int, np.ndarray] | None] = [None] * k
        self.nonfinite = [0] * k
        self.beyond = [0] * k

    def push(self, stamps: np.ndarray, *streams: np.ndarray):
        """-> (stamps, [filled values], [bad flags]) of the samples released."""
        self.stamps = np.concatenate([self.stamps, np.asarray(stamps, np.int64)])
        for i, values in enumerate(streams):
            values = np.asarray(values, float).reshape(-1, 3)
            bad, nonfinite, beyond = metrics.bad_samples(values, self.ranges[i])
            self.nonfinite[i] += nonfinite
            self.beyond[i] += beyond
            self.values[i] = np.concatenate([self.values[i], values])
            self.bad[i] = np.concatenate([self.bad[i], bad])
        return self._release(min(self._resolved(i) for i in range(len(self.ranges))))

    def finish(self):
        return self._release(len(self.stamps), final=True)

    def _resolved(self, i: int) -> int:
        good = np.flatnonzero(~self.bad[i])
        return int(good[-1]) + 1 if good.size else 0

    def _release(self, r: int, final: bool = False):
        out_values, out_bad = [], []
        for i in range(len(self.ranges)):
            values, bad = self.values[i], self.bad[i]
            head, head_bad = values[:r], bad[:r]
            if head_bad.any():
                head = head.copy()
                limit = len(values) if final else self._resolved(i)
                good = np.flatnonzero(~bad[:limit])
                xp, fp = good + self.base, values[good]
                if self.anchor[i] is not None:
                    xp = np.concatenate([[self.anchor[i][0]], xp])
                    fp = np.concatenate([self.anchor[i][1][None, :], fp])
                if not xp.size:
                    raise ValueError("no valid sample at all")
                missing = np.flatnonzero(head_bad)
                for column in range(3):
                    head[missing, column] = np.interp(missing + self.base, xp, fp[:, column])
            good_head = np.flatnonzero(~head_bad)
            if good_head.size:
                g = int(good_head[-1])
                self.anchor[i] = (self.base + g, values[g].copy())
            out_values.append(head)
            out_bad.append(head_bad)
            self.values[i], self.bad[i] = values[r:], bad[r:]
        stamps, self.stamps = self.stamps[:r], self.stamps[r:]
        self.base += r
        return stamps, out_values, out_bad


class RecordedDenoised:
    """The bag's own denoised topic on the input samples: the sum of the axes of the
    message stamped like the input sample (the last one if several), 0 if none; a
    non-finite message counts as 0 and makes its sample bad. An input sample is resolved
    once a denoised message stamped later has been read (or at the end, or `max_pending`
    samples later: then it has none)."""

    def __init__(self, *, max_pending: int):
        self.max_pending = int(max_pending)
        self.stamps = np.zeros(0, np.int64)
        self.values = np.zeros(0)
        self.bad = np.zeros(0, bool)
        self.inputs = np.zeros(0, np.int64)
        self.latest: int | None = None
        self.rows = self.rows_bad = self.missing = 0
        self.any_yz = False  # a (finite) message with y or z != 0: per-axis output

    def add_denoised(self, stamps: np.ndarray | None, values: np.ndarray | None) -> None:
        if stamps is None or not len(stamps):
            return
        values = np.asarray(values, float).reshape(-1, 3)
        row_bad = ~np.all(np.isfinite(values), axis=1)
        clean = np.where(row_bad[:, None], 0.0, values)
        self.rows += len(values)
        self.rows_bad += int(row_bad.sum())
        self.any_yz = self.any_yz or bool(np.any(clean[:, 1:]))
        stamps = np.asarray(stamps, np.int64)
        all_stamps = np.concatenate([self.stamps, stamps])
        order = np.argsort(all_stamps, kind="stable")
        self.stamps = all_stamps[order]
        self.values = np.concatenate([self.values, clean.sum(axis=1)])[order]
        self.bad = np.concatenate([self.bad, row_bad])[order]
        top = int(stamps.max())
        self.latest = top if self.latest is None else max(self.latest, top)

    def add_input(self, stamps: np.ndarray) -> None:
        self.inputs = np.concatenate([self.inputs, np.asarray(stamps, np.int64)])

    def take(self, final: bool) -> tuple[np.ndarray, np.ndarray]:
        """(values, bad flags) of the input samples resolved since the last call."""
        if final:
            k = len(self.inputs)
        else:
            k = 0 if self.latest is None else int(np.searchsorted(self.inputs, self.latest))
            k = max(k, len(self.inputs) - self.max_pending)
        if k <= 0:
            return np.zeros(0), np.zeros(0, bool)
        wanted, self.inputs = self.inputs[:k], self.inputs[k:]
        left = np.searchsorted(self.stamps, wanted, side="left")
        right = np.searchsorted(self.stamps, wanted, side="right")
        found = right > left
        values = np.zeros(k)
        values[found] = self.values[right[found] - 1]
        bad_before = np.concatenate([[0], np.cumsum(self.bad)])
        bad = bad_before[right] - bad_before[left] > 0
        self.missing += int(np.count_nonzero(~found))
        cut = int(np.searchsorted(self.stamps, wanted.max(), side="right"))
        self.stamps, self.values, self.bad = self.stamps[cut:], self.values[cut:], self.bad[cut:]
        return values, bad


def _screen_rest(screen: Screen, source: str):
    """screen.finish(); a recording without any valid sample is the recording's error."""
    try:
        return screen.finish()
    except ValueError as exc:
        raise bag_error(source, exc) from None


def _refuse_bad(source: str, bad: int, n: int, max_fraction: float, sensor_range: float):
    """BagError if more than `max_fraction` of the `n` samples are bad."""
    if n and bad / n > max_fraction:
        raise BagError(
            f"{source}: {bad} of {n} samples ({bad / n:.1%}) are non-finite or beyond the "
            f"sensor range (+/-{sensor_range:g}); more than {max_fraction:.0%} bad: no metrics"
        )


def require_ground_truth(rec, where: str = "recording", profile=None) -> None:
    """Raise BagError unless `rec` (a Recording or a slice of one) carries the ground-truth
    contact signal, sample for sample (the topic `contact` beside the profile's sensor
    topic, e.g. /accelerometer/contact for /accelerometer/raw)."""
    names = bag_topic_names(profile)
    if rec.contact is None:
        raise BagError(
            f"{where}: missing ground-truth topic {names['contact']} (the contact-only part "
            f"of {names['raw']}; evaluate needs a recording with ground truth, e.g. from "
            f"`egovib simulate`)"
        )
    if len(rec.contact) != len(rec.sensor):
        raise BagError(
            f"{where}: topic {names['contact']} has {len(rec.contact)} samples, "
            f"{names['raw']} has {len(rec.sensor)}"
        )


# --------------------------------------------------------------------------
# Pass 1: what the evaluation needs of the whole run
# --------------------------------------------------------------------------
@dataclass
class RunSummary:
    samples: int
    activity_level: float  # ground-truth contact threshold (metrics.activity_threshold)
    recorded: bool  # the run carries its own denoised topic
    recorded_like: str | None  # which method made it: "paper" (y = z = 0) or "per_axis"
    # the recorded output is the drop-in kind (raw minus the ego-vibration: out-of-band
    # content kept), scored like the others once band-passed
    recorded_dropin: bool = False
    counts: dict = field(default_factory=dict)  # the report's "bad_samples" counts


class SummaryPass:
    """Pass 1 over the test run (see the module doc)."""

    def __init__(
        self,
        model: NoiseModel,
        *,
        source: str = "recording",
        max_bad_fraction: float = metrics.MAX_BAD_FRACTION,
    ):
        self.model, self.source, self.max_bad_fraction = model, source, float(max_bad_fraction)
        self.sensor_range = float(model.profile.sensor_range)
        self.screen = Screen([self.sensor_range, np.inf])
        self.band = BandPass.of(model, 1)
        self.recorded = RecordedDenoised(
            max_pending=int(RECORDED_MAX_WAIT_S * model.sample_rate_hz)
        )
        self.bad = _Fifo(bool)
        self.recorded_bad = _Fifo(bool)
        self.low_raw, self.low_recorded = LowBandEnergy(model), LowBandEnergy(model)
        self.peak = 0.0
        self.joint_states_nonfinite = 0
        self.joint_started = False  # a finite joint state seen
        self.joint_states_unusable, self.joint_states = 0, 0
        self.last_joint_stamp: int | None = None
        self.union_bad = 0
        self.n = 0

    def push(self, piece) -> None:
        require_ground_truth(piece, self.source, self.model.profile)
        self._rows(*self.screen.push(piece.sensor_stamps_ns, piece.sensor, piece.contact))
        self.recorded.add_denoised(piece.denoised_stamps_ns, piece.denoised)
        finite = np.all(np.isfinite(piece.joint_velocity), axis=1)
        if not self.joint_started:
            # a stream's first velocities may be unknown without being bad: a driver that
            # publishes positions only has no difference before its second message
            lead = len(finite) if not finite.any() else int(np.argmax(finite))
            self.joint_started = lead < len(finite)
            finite = finite.copy()
            finite[:lead] = True
        self.joint_states_nonfinite += int(np.count_nonzero(~finite))
        # as the denoiser takes them (core.stream.stamp_order): each finite and stamped after
        # the one before, a clock that jumps back a restart
        stamps = piece.joint_stamps_ns[finite]
        late = 0
        while len(stamps):
            keep, jump = stamp_order(self.last_joint_stamp, stamps, CLOCK_JUMP_NS)
            head = slice(0, len(stamps) if jump is None else jump)
            late += int(np.count_nonzero(~keep[head]))
            if keep[head].any():
                self.last_joint_stamp = int(stamps[head][keep[head]].max())
            if jump is None:
                break
            self.last_joint_stamp, stamps = None, stamps[jump:]
        self.joint_states_unusable += int(np.count_nonzero(~finite)) + late
        self.joint_states += len(finite)
        self._count(final=False)

    def _rows(self, stamps, values, bad) -> None:
        self.n += len(stamps)
        if len(stamps):
            reference = self.band.process(_combined(values[1]))[0]
            self.peak = max(self.peak, float(np.max(np.abs(reference))))
            self.low_raw.push(_combined(values[0])[0])
        self.bad.put(bad[0] | bad[1])
        self.recorded.add_input(stamps)

    def _count(self, final: bool) -> None:
        """Bad samples: the screen's or those of a bad message of the denoised topic."""
        values, flags = self.recorded.take(final)
        self.low_recorded.push(values)
        self.recorded_bad.put(flags)
        stop = min(self.bad.end, self.recorded_bad.end)
        flags = self.bad.take(stop) | self.recorded_bad.take(stop)
        self.union_bad += int(np.count_nonzero(flags))

    def finish(self) -> RunSummary:
        self._rows(*_screen_rest(self.screen, self.source))
        self._count(final=True)
        n = self.n
        counts = {
            "raw_nonfinite": self.screen.nonfinite[0],
            "raw_beyond_range": self.screen.beyond[0],
            "contact_nonfinite": self.screen.nonfinite[1] + self.screen.beyond[1],
            "denoised_nonfinite": self.recorded.rows_bad,
            "joint_states_nonfinite": self.joint_states_nonfinite,
            "samples": n,
            "bad": self.union_bad,
            "bad_fraction": self.union_bad / n if n else 0.0,
            "max_bad_fraction": self.max_bad_fraction,
            "sensor_range": self.sensor_range,
        }
        _refuse_bad(self.source, self.union_bad, n, self.max_bad_fraction, self.sensor_range)
        joints = f"{self.source}: {self.model.profile.joints_topic}"
        try:
            check_joint_share(
                self.joint_states_unusable, self.joint_states, joints, self.max_bad_fraction
            )
        except StreamError as exc:
            raise BagError(str(exc)) from None
        if n and self.union_bad == n:
            raise BagError(f"{self.source}: no valid sample")
        recorded = self.recorded.rows > 0
        # drop-in output keeps what lies far below the band (gravity, motion), band-passed
        # output keeps none of it (4th order: -48 dB at a quarter of the band's low edge)
        dropin = bool(
            recorded
            and self.low_raw.energy > 0
            and self.low_recorded.energy > 0.1 * self.low_raw.energy
        )
        return RunSummary(
            samples=n,
            activity_level=max(1e-3 * self.peak, 1e-6),  # metrics.activity_threshold
            recorded=recorded,
            recorded_like=_like(self.recorded.any_yz, dropin) if recorded else None,
            recorded_dropin=dropin,
            counts=counts,
        )


# --------------------------------------------------------------------------
# Pass 2: detection thresholds from calibration data
# --------------------------------------------------------------------------
@dataclass
class CalibrationResult:
    thresholds: dict  # "raw" and each method -> detection threshold
    gate: np.ndarray | None  # noisereduce's noise threshold per frequency (dB)
    bad: int  # bad calibration samples
    joints: tuple  # its joint states (stamps, velocities): the detector's motion limits


class _Reducer:
    """The threshold rule's reducer of one signal's envelope over the calibration mask."""

    def __init__(self):
        self.values = _Fifo()
        self.rule = detection.ThresholdReducer()


class CalibrationPass:
    """Pass 2 over the calibration recording (see the module doc). Mask of the samples a
    threshold is taken from (evaluate.py): not the first and last EDGE_S (filter start-up
    and flush), no sample bad input can have touched; the threshold rule is the one of
    `egovib detect` and the contact_detector node (core.contact.no_contact_threshold at the
    default budget), on the detector's envelope of each method's signal."""

    def __init__(
        self,
        model: NoiseModel,
        *,
        names: Sequence[str],
        model_short: NoiseModel | None,
        source: str = "calibration recording",
        max_bad_fraction: float = metrics.MAX_BAD_FRACTION,
        adapt=None,
    ):
        self.model, self.source, self.max_bad_fraction = model, source, float(max_bad_fraction)
        fs = model.sample_rate_hz
        self.screen = Screen([float(model.profile.sensor_range)])
        self.band = BandPass.of(model, 1)
        self.streams = {
            name: baselines.method_stream(
                name, model=model, model_short=model_short, source=source, adapt=adapt
            )
            for name in names
        }
        self.needs_gate = "noisereduce" in self.streams
        # joint states, small beside the sensor's: (stamps, velocities) per piece
        self.joints: list[tuple] = [(np.zeros(0, np.int64), np.zeros((0, model.n_joints)))]
        self.clip: list[np.ndarray] = []
        self.clip_n = 0
        self.gate: np.ndarray | None = None
        self.envelopes = {key: _envelope(model) for key in ["raw", *names]}
        self.reducers = {key: _Reducer() for key in ["raw", *names]}
        self.exclusion = metrics.BadRunExclusion(
            margin=int(model.block_length),
            settle_max=int(round(metrics.EDGE_S * fs)),
            n=np.iinfo(np.int64).max // 4,
        )
        self.edge = int(metrics.EDGE_S * fs)  # each end of the data left out: min(this, n // 4)
        self.mask_base = 0  # the mask kept from this sample on
        self.mask_end = 0  # the mask known up to here
        self.mask = np.zeros(0, bool)  # from mask_base
        self.n = 0

    def push(self, piece) -> None:
        for name, stream in self.streams.items():
            self._signal(
                name, stream.push_joint_states(piece.joint_stamps_ns, piece.joint_velocity)
            )
        self.joints.append((piece.joint_stamps_ns, piece.joint_velocity))
        self._rows(*self.screen.push(piece.sensor_stamps_ns, piece.sensor))
        self._advance(final=False)

    def _rows(self, stamps, values, bad) -> None:
        if not len(stamps):
            return
        accel = values[0]
        self.n += len(stamps)
        clip = self.band.process(_combined(accel))[0]
        self._signal("raw", clip)
        self.exclusion.push(bad[0])
        if self.needs_gate and self.gate is None:
            self.clip.append(clip[: baselines.NOISE_CLIP_SAMPLES - self.clip_n])
            self.clip_n += len(self.clip[-1])
            if self.clip_n >= baselines.NOISE_CLIP_SAMPLES:
                self._set_gate()
        for name, stream in self.streams.items():
            self._signal(name, stream.push(stamps, accel, clip))

    def _set_gate(self) -> None:
        self.gate = baselines.gate_threshold(np.concatenate(self.clip))
        self.clip = []
        self._signal("noisereduce", self.streams["noisereduce"].gate.set_threshold(self.gate))

    def _signal(self, key: str, values: np.ndarray) -> None:
        if len(values):
            self.reducers[key].values.put(self.envelopes[key].process(values)[1])

    def _advance(self, final: bool) -> None:
        if final:
            self.exclusion.finish()
            known = self.n
            edge = min(self.edge, self.n // 4)
        else:
            known = min(
                self.exclusion.known - self.exclusion.margin - 1,
                self.n - self.edge if self.n >= 4 * self.edge else 0,
            )
            edge = self.edge
        if known > self.mask_end:
            a, b = self.mask_end, known
            index = np.arange(a, b)
            base = (index >= edge) & (index < self.n - edge) & ~self.exclusion.mask(a, b)
            self.mask = np.concatenate([self.mask, base])
            self.mask_end = b
            self.exclusion.prune(a - self.exclusion.margin)
        for reducer in self.reducers.values():
            stop = min(reducer.values.end, self.mask_end)
            start = reducer.values.start
            if stop > start:
                env = reducer.values.take(stop)
                lo, hi = start - self.mask_base, stop - self.mask_base
                reducer.rule.push(env[self.mask[lo:hi]])
        low = min(r.values.start for r in self.reducers.values())
        if low > self.mask_base:
            cut = low - self.mask_base
            self.mask = self.mask[cut:]
            self.mask_base = low

    def finish(self) -> CalibrationResult:
        self._rows(*_screen_rest(self.screen, self.source))
        bad, n = self.exclusion.bad, self.n
        sensor_range = self.model.profile.sensor_range
        _refuse_bad(self.source, bad, n, self.max_bad_fraction, sensor_range)
        if self.needs_gate and self.gate is None:
            if not self.clip_n:
                raise ValueError("noisereduce needs a no-contact noise clip (calibration data)")
            self._set_gate()
        for name, stream in self.streams.items():
            self._signal(name, stream.finish())
        try:
            self._advance(final=True)
        except ValueError as exc:
            raise bag_error(self.source, exc) from None
        thresholds = {key: reducer.rule.threshold() for key, reducer in self.reducers.items()}
        stamps, velocity = (np.concatenate(part) for part in zip(*self.joints))
        order = np.argsort(stamps, kind="stable")
        joints = stamps[order], velocity[order]
        return CalibrationResult(thresholds=thresholds, gate=self.gate, bad=bad, joints=joints)


# --------------------------------------------------------------------------
# Pass 3: the metrics
# --------------------------------------------------------------------------
@dataclass
class _Pending:
    """Segments (their SNRs) waiting for the taps around them to be decided."""

    starts: np.ndarray
    snr: np.ndarray  # (S, signals)


class EvaluationPass:
    """Pass 3 over the test run (see the module doc); without `thresholds` it only finds
    them (the largest envelope of each signal on no-contact samples)."""

    def __init__(
        self,
        model: NoiseModel,
        *,
        names: Sequence[str],
        summary: RunSummary,
        thresholds: dict | None,
        model_short: NoiseModel | None = None,
        gate: np.ndarray | None = None,
        extra: Sequence[str] = (),
        keep_signals: bool = False,
        source: str = "recording",
        adapt=None,
        limits_model: NoiseModel | None = None,
    ):
        """`limits_model`: the model whose motion the thresholds' data had (the detector's
        motion limits; None: none, the thresholds come from this run)."""
        fs = model.sample_rate_hz
        self.model, self.fs, self.source = model, fs, source
        self.summary = summary
        self.n = n = summary.samples
        self.names = list(names)
        self.recorded = (
            RecordedDenoised(max_pending=int(RECORDED_MAX_WAIT_S * fs))
            if summary.recorded
            else None
        )
        self.like = summary.recorded_like
        self.recorded_band = BandPass.of(model, 1) if summary.recorded_dropin else None
        self.metric_keys = ["raw", *self.names] + (["bag_denoised"] if self.recorded else [])
        self.detect_keys = self.metric_keys + [k for k in extra if k not in self.metric_keys]
        self.streams = {
            name: baselines.method_stream(
                name, model=model, model_short=model_short, gate=gate, source=source, adapt=adapt
            )
            for name in self.detect_keys
            if name not in ("raw", "bag_denoised")
        }
        self.screen = Screen([float(model.profile.sensor_range), np.inf])
        self.raw_band, self.ref_band = BandPass.of(model, 1), BandPass.of(model, 1)
        self.pr2 = detection.PR2Magnitude(sample_rate_hz=fs)
        self.fifos = {key: _Fifo() for key in ["reference", "pr2", *self.detect_keys]}
        self.fifos["stamps"] = _Fifo(np.int64)  # the detector's motion limits need them
        self.screen_bad, self.recorded_bad = _Fifo(bool), _Fifo(bool)
        self.segmenter = metrics.ContactSegmenter(
            level=summary.activity_level, n=n, sample_rate_hz=fs
        )
        self.exclusion = metrics.BadRunExclusion(
            margin=int(model.block_length), settle_max=int(round(metrics.EDGE_S * fs)), n=n
        )
        self.edge = min(int(round(metrics.EDGE_S * fs)), n // 2)
        self.pos = 0  # samples scored
        # accumulators (per metric signal)
        k = len(self.metric_keys)
        self.noise_sum, self.noise_count = np.zeros(k), 0
        self.top = [metrics.TopValues.for_quantile(metrics.SPIKE_QUANTILE, n) for _ in range(k)]
        self.peak_sum = np.zeros(k)
        self.seg_sum, self.seg_count = np.zeros(k), 0
        self.taps: deque[metrics.Tap] = deque()  # not decided yet (the last may be open)
        self.decided: deque[metrics.Tap] = deque()  # decided, still needed for lookups
        self.kept = self.dropped = 0
        self.excluded = 0  # samples excluded (bad input around, dropped taps' windows)
        self.dropped_until = 0  # dropped windows counted up to here
        self.seg_next = 0
        self.seg_tail = {key: np.zeros(0) for key in ["reference", *self.metric_keys]}
        self.pending_segments: deque[_Pending] = deque()
        # detection
        self.envelopes = {key: _envelope(model) for key in self.detect_keys}
        self.own_thresholds = {key: detection.ThresholdReducer() for key in self.detect_keys}
        # the one detector (core.contact) on each signal; the PR2 gripper's own magnitude
        # thresholds are a baseline of their own (detection.PR2Magnitude)
        self.detectors: dict[str, tuple] = {}
        if thresholds is not None:
            for key in self.metric_keys:
                motion = None
                if limits_model is not None:
                    motion = motion_limits(limits_model, key, thresholds)
                self.detectors[key] = (key, detection.OnsetStream(thresholds[key], model, motion))
            for level in detection.PR2_THRESHOLDS_MS2:
                self.detectors[f"pr2_{level:g}ms2"] = (
                    "pr2",
                    detection.EventDetector(level, sample_rate_hz=fs),
                )
        self.matchers = {key: detection.EventMatcher(sample_rate_hz=fs) for key in self.detectors}
        self.unfiltered = {key: np.zeros(0, np.int64) for key in self.detectors}
        # alignment and the bag's own output against the batch method
        self.lags = {key: metrics.LagCorrelation() for key in ("default", "bag_denoised")}
        self.compare = self.recorded is not None and self.like in self.names
        self.held_difference: list[np.ndarray] = []  # (index, diff^2, batch^2) in tap windows
        self.difference = np.zeros(2)
        self.keep = keep_signals
        self.kept_signals = {key: [] for key in ["reference", "excluded", *self.metric_keys]}

    # --- input --------------------------------------------------------------------
    def push(self, piece) -> None:
        require_ground_truth(piece, self.source, self.model.profile)
        for name, stream in self.streams.items():
            self.fifos[name].put(
                stream.push_joint_states(piece.joint_stamps_ns, piece.joint_velocity)
            )
        for _, detector in self.detectors.values():
            if isinstance(detector, detection.OnsetStream):
                detector.push_joints(piece.joint_stamps_ns, piece.joint_velocity)
        self._rows(*self.screen.push(piece.sensor_stamps_ns, piece.sensor, piece.contact))
        if self.recorded is not None:
            self.recorded.add_denoised(piece.denoised_stamps_ns, piece.denoised)
        self._advance(final=False)

    def finish(self) -> None:
        self._rows(*_screen_rest(self.screen, self.source))
        for name, stream in self.streams.items():
            self.fifos[name].put(stream.finish())
        self._advance(final=True)

    def _rows(self, stamps, values, bad) -> None:
        if not len(stamps):
            return
        accel, contact = values
        raw = self.raw_band.process(_combined(accel))[0]
        reference = self.ref_band.process(_combined(contact))[0]
        self.fifos["raw"].put(raw)
        self.fifos["stamps"].put(stamps)
        self.fifos["reference"].put(reference)
        self.segmenter.push(reference)
        self.screen_bad.put(bad[0] | bad[1])
        self.fifos["pr2"].put(self.pr2.process(accel))
        for name, stream in self.streams.items():
            self.fifos[name].put(stream.push(stamps, accel, raw))
        if self.recorded is not None:
            self.recorded.add_input(stamps)

    # --- scoring ------------------------------------------------------------------
    def _advance(self, final: bool) -> None:
        if self.recorded is not None:
            values, flags = self.recorded.take(final)
            if self.recorded_band is not None and len(values):
                values = self.recorded_band.process(values[None, :])[0]
            self.fifos["bag_denoised"].put(values)
            self.recorded_bad.put(flags)
        # a sample is bad once it is bad in any stream (the bag's denoised topic may lag)
        fifos = [self.screen_bad] + ([self.recorded_bad] if self.recorded is not None else [])
        stop = min(fifo.end for fifo in fifos)
        self.exclusion.push(np.logical_or.reduce([fifo.take(stop) for fifo in fifos]))
        if final:
            self.exclusion.finish()
            self.segmenter.finish()
            horizon = self.n
        else:
            horizon = min(
                min(f.end for f in self.fifos.values()),
                self.exclusion.known - self.exclusion.margin - 1,
                self.segmenter.pos - self.segmenter.lag,
            )
        for tap in self.segmenter.take_new():
            tap.peaks = np.zeros(len(self.metric_keys))
            self.taps.append(tap)
        if horizon > self.pos:
            self._score(self.pos, horizon)
            self.pos = horizon
        self._decide(final)

    def _score(self, p: int, q: int) -> None:
        data = {key: fifo.take(q) for key, fifo in self.fifos.items()}
        excluded = self.exclusion.mask(p, q)
        self.excluded += int(np.count_nonzero(excluded))
        contact = np.zeros(q - p, bool)
        for tap in self.taps:
            if tap.window_start < q and tap.window_stop > p:
                contact[max(tap.window_start, p) - p : min(tap.window_stop, q) - p] = True
        index = np.arange(p, q)
        no_contact = ~contact & ~excluded & (index >= self.edge) & (index < self.n - self.edge)
        for i, key in enumerate(self.metric_keys):
            magnitude = np.abs(data[key])
            quiet = magnitude[no_contact]
            self.noise_sum[i] += quiet.sum()
            self.top[i].push(quiet)
            for tap in self.taps:
                a, b = max(tap.window_start, p), min(tap.window_stop, q)
                if b > a:
                    tap.peaks[i] = max(tap.peaks[i], float(magnitude[a - p : b - p].max()))
        self.noise_count += int(np.count_nonzero(no_contact))
        if self.detectors:
            for signal_key, detector in self.detectors.values():
                if isinstance(detector, detection.OnsetStream):
                    detector.push(data[signal_key], data["stamps"])
                else:
                    detector.push(data[signal_key])
        else:  # this pass only sets the thresholds, from the run's own no-contact samples
            for key in self.detect_keys:
                envelope = self.envelopes[key].process(data[key])[1]
                self.own_thresholds[key].push(envelope[no_contact])
        self._segments(p, q, data)
        self.lags["default"].push(data["reference"], data["default"])
        if self.recorded is not None:
            self.lags["bag_denoised"].push(data["reference"], data["bag_denoised"])
            if self.compare:
                batch = data[self.like]
                keep = ~excluded
                self.held_difference.append(
                    np.stack(
                        [
                            index[keep],
                            (data["bag_denoised"][keep] - batch[keep]) ** 2,
                            batch[keep] ** 2,
                        ]
                    )
                )
        if self.keep:
            for key in ["reference", *self.metric_keys]:
                self.kept_signals[key].append(data[key])
            self.kept_signals["excluded"].append(excluded)

    def _segments(self, p: int, q: int, data: dict) -> None:
        length, hop = metrics.SEGMENT_LENGTH, metrics.SEGMENT_HOP
        keys = ["reference", *self.metric_keys]
        ext_start = p - len(self.seg_tail["reference"])
        extended = {key: np.concatenate([self.seg_tail[key], data[key]]) for key in keys}
        starts = np.arange(self.seg_next, q - length + 1, hop)
        if starts.size:
            first = starts[0] - ext_start  # the batch function frames from there on
            snr = np.stack(
                [
                    metrics.segmental_snr(extended["reference"][first:], extended[key][first:])
                    for key in self.metric_keys
                ],
                axis=1,
            )
            self.pending_segments.append(_Pending(starts, snr))
            self.seg_next = int(starts[-1]) + hop
        keep_from = max(self.seg_next, ext_start) - ext_start
        self.seg_tail = {key: extended[key][keep_from:] for key in keys}

    def _decide(self, final: bool) -> None:
        settled = self.pos  # samples scored
        while self.taps and self.taps[0].closed and self.taps[0].window_stop <= settled:
            tap = self.taps.popleft()
            a, b = tap.window_start, tap.window_stop
            tap.kept = not self.exclusion.any_in(a, b)
            if tap.kept:
                self.kept += 1
                self.peak_sum += tap.peaks
                for matcher in self.matchers.values():
                    matcher.add(truth=[tap.start])
            else:
                self.dropped += 1
                lo = max(a, self.dropped_until)
                if b > lo:
                    self.excluded += int(np.count_nonzero(~self.exclusion.mask(lo, b)))
                self.dropped_until = max(self.dropped_until, b)
            self.decided.append(tap)
        # every sample before `ready` is decided: scored and outside undecided tap windows
        ready = min(settled, self.taps[0].window_start) if self.taps else settled
        if final:
            ready = self.n
        self._resolve_segments(ready)
        for key, (_, detector) in self.detectors.items():
            if final:
                detector.finish()
            onsets = np.concatenate([self.unfiltered[key], detector.take()])
            now, self.unfiltered[key] = onsets[onsets < ready], onsets[onsets >= ready]
            keep = [int(o) for o in now if not self._excluded_at(int(o))]
            matcher = self.matchers[key]
            matcher.add(detected=keep)
            if final:
                matcher.finish()
            else:
                matcher.advance(min(ready, detector.horizon))
        self._release_difference(ready)
        low = ready - metrics.SEGMENT_LENGTH
        while self.decided and self.decided[0].window_stop <= low:
            self.decided.popleft()
        self.exclusion.prune(low)

    def _excluded_at(self, i: int) -> bool:
        if self.exclusion.any_in(i, i + 1):
            return True
        return any(not tap.kept and tap.window_start <= i < tap.window_stop for tap in self.decided)

    def _resolve_segments(self, ready: int) -> None:
        length = metrics.SEGMENT_LENGTH
        while self.pending_segments:
            batch = self.pending_segments[0]
            done = batch.starts + length <= ready
            if not done.any():
                return
            starts, snr = batch.starts[done], batch.snr[done]
            a, b = int(starts[0]), int(starts[-1]) + length
            active = np.zeros(b - a, bool)
            excluded = self.exclusion.mask(a, b)
            for tap in self.decided:
                if tap.kept:
                    lo, hi = max(tap.start, a), min(tap.stop, b)
                    if hi > lo:
                        active[lo - a : hi - a] = True
                else:
                    lo, hi = max(tap.window_start, a), min(tap.window_stop, b)
                    if hi > lo:
                        excluded[lo - a : hi - a] = True
            active_before = np.concatenate([[0], np.cumsum(active)])
            excluded_before = np.concatenate([[0], np.cumsum(excluded)])
            offsets = starts - a
            chosen = (
                active_before[offsets + length] - active_before[offsets] >= SEGMENT_ACTIVE_MIN
            ) & (excluded_before[offsets + length] == excluded_before[offsets])
            self.seg_sum += snr[chosen].sum(axis=0)
            self.seg_count += int(np.count_nonzero(chosen))
            if done.all():
                self.pending_segments.popleft()
                continue
            self.pending_segments[0] = _Pending(batch.starts[~done], batch.snr[~done])
            return

    def _release_difference(self, ready: int) -> None:
        if not self.held_difference:
            return
        held = np.concatenate(self.held_difference, axis=1)
        index = held[0].astype(np.int64)
        now = index < ready
        use = now.copy()
        for tap in self.decided:
            if not tap.kept:
                use &= ~((index >= tap.window_start) & (index < tap.window_stop))
        self.difference += held[1:, use].sum(axis=1)
        self.held_difference = [held[:, ~now]] if (~now).any() else []

    # --- results ------------------------------------------------------------------
    def noise_thresholds(self) -> dict:
        """Detection thresholds from this run's own no-contact samples (no calibration)."""
        return {key: self.own_thresholds[key].threshold() for key in self.detect_keys}

    def signal_metrics(self, key: str) -> dict:
        """metrics.signal_figures of signal `key` against the raw signal."""
        i = self.metric_keys.index(key)

        def mean(total: np.ndarray, count: int) -> np.ndarray:
            return total / count if count else np.full(len(total), np.nan)

        noise = mean(self.noise_sum, self.noise_count)
        peaks = mean(self.peak_sum, self.kept)
        segsnr = mean(self.seg_sum, self.seg_count)
        return metrics.signal_figures(
            noise=(float(noise[0]), float(noise[i])),
            spike=[self.top[k].quantile(metrics.SPIKE_QUANTILE) for k in (0, i)],
            peak=(float(peaks[0]), float(peaks[i])),
            segsnr=(float(segsnr[0]), float(segsnr[i])),
            n_taps=self.kept,
        )

    def scores(self, key: str) -> dict:
        """detection.scores_of's dict and the threshold of detector `key` (a signal or pr2_*)."""
        scores = self.matchers[key].scores()
        scores["threshold"] = float(self.detectors[key][1].threshold)
        return scores

    def minutes(self) -> float:
        return (self.n - self.excluded) / self.fs / 60.0

    def difference_vs_batch(self) -> float | None:
        if not self.compare:
            return None
        diff, batch = self.difference
        n = self.n - self.excluded
        return float(np.sqrt(diff / n) / max(np.sqrt(batch / n), 1e-300)) if n else float("nan")

    def signals(self) -> dict:
        """The whole signals and the contact segmentation (keep_signals=True)."""
        out = {
            key: np.concatenate([np.zeros(0)] + parts)
            for key, parts in self.kept_signals.items()
            if key != "excluded"
        }
        excluded = np.concatenate([np.zeros(0, bool)] + self.kept_signals["excluded"])
        seg = metrics.segment_contacts(
            out["reference"], sample_rate_hz=self.fs, threshold=self.summary.activity_level
        )
        if excluded.any():
            seg = metrics.exclude_samples(seg, excluded)
        out["seg"] = seg
        return out


def _like(per_axis: bool, dropin: bool) -> str:
    """The method a recorded denoised topic is compared with: the default output (per axis,
    drop-in), the paper's per-axis band-passed one, or the paper's combined one."""
    if not per_axis:
        return "paper"
    return "default" if dropin else "per_axis"


def method_names(
    methods: Sequence[str] | None,
    *,
    calibration: bool,
    model_short: NoiseModel | None,
    model: NoiseModel | None = None,
) -> list[str]:
    """The methods to run: `methods` (the paper's always), else all that can run."""
    fitted = model is not None and has_method_calibration(model)
    if methods is None:
        names = list(baselines.METHOD_LABELS)
        if model_short is None:
            names.remove("paper_L32")
        if not calibration:
            names.remove("noisereduce")
        if not fitted:
            names = [n for n in names if n not in SAMPLE_METHODS]
    else:
        names = list(methods)
        unknown = [m for m in names if m not in baselines.METHOD_LABELS]
        if unknown:
            raise ConfigError(
                f"methods: unknown method(s) {unknown}; expected {list(baselines.METHOD_LABELS)}"
            )
        if "noisereduce" in names and not calibration:
            raise ValueError("noisereduce needs a no-contact noise clip (calibration data)")
        if "paper_L32" in names and model_short is None:
            raise ValueError(
                "paper_L32 needs a model calibrated with 32-sample blocks (--model-short)"
            )
        needs = [n for n in names if n in SAMPLE_METHODS]
        if needs and not fitted:
            raise ConfigError(
                f"methods {needs} need a model calibrated with `egovib calibrate --methods hybrid`"
            )
    # the default (what a user gets: the figures reported at the top) and the paper's, always
    for always in ("paper", "default"):
        if always not in names:
            names = [always] + names
    return names
