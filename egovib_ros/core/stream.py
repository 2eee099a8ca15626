"""From an accelerometer sample stream to analysis blocks with matched joint velocity.

`BlockFramer`, shared by calibration and denoising, cleans the input, band-passes it,
cuts blocks of `block_length` samples every `hop` and hands each out once the joint states
covering its span are in: any chunking gives the same blocks (to the bit for the paper's
settings, within ~1e-16 otherwise).

Bad input is counted in `stats`, never a silent wrong result:
- a sample stamped at or before the previous one is dropped;
- a bad sample (non-finite, or beyond the sensor's range) is missing: never averaged
  into a model, never output;
- a gap of up to `max_fill_samples` is bridged by linear interpolation (never output); a
  longer one ends the segment (flushed as at the end of a stream; the filter restarts);
- stamps jitter (+-30 % per step) around the nominal rate; 1.5 periods or more is a gap;
- stamps taken on receipt (core.receipt) are told apart on the first samples, which wait;
  gaps and the rate are then judged on a rebuilt sample clock;
- the rate is measured on the first 2 blocks' worth, then on every RATE_WINDOW_BLOCKS
  blocks' worth (blocks of RATE_BLOCK_MIN samples at least); off by more than
  `rate_tolerance` at the start, or on two windows in a row later, the stream is refused
  (StreamError on every push), not bridged into invented samples;
- a block with no joint state in or shortly before its span is MISSING: the denoiser
  passes it through band-passed, the calibrator skips it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import MISSING as NO_DEFAULT
from dataclasses import asdict, dataclass, fields
from typing import Any, Protocol, runtime_checkable

import numpy as np

from egovib_ros.core.blocks import analysis_window, validate_blocking
from egovib_ros.core.filters import CHANNEL_LAYOUTS, BandPass, BelowBand, channel_matrix
from egovib_ros.core.receipt import ReceiptClock, envelope_period, receipt_latency
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.core.velocity import MISSING, block_mean_velocity
from egovib_ros.errors import ConfigError, RateError, StreamError
from egovib_ros.robot import STAMP_KINDS

LOG = logging.getLogger("egovib_ros.core")

#: A recording with more bad samples than this share (non-finite, beyond the sensor range,
#: out of order) gives an error, not a result: whatever came out would describe the faults.
MAX_BAD_SHARE = 0.1
#: After the start, the sample rate is measured again on every window of this many blocks'
#: worth of samples; two windows in a row beyond the tolerance are a rate mismatch.
RATE_WINDOW_BLOCKS = 4
#: ... blocks of at least this many samples: a window of a few short blocks (16 samples of a
#: 4-sample block) measures a jittery driver's stamps, not its rate
RATE_BLOCK_MIN = 64
#: With FramerSettings.stamps "auto", up to this many first samples wait while the stamps tell
#: whether they mark sample times or a driver's receipt times (the first rate window); the
#: first PROBE_EARLY are enough when none of their steps is shorter than half a period.
PROBE_SAMPLES = 128
PROBE_EARLY = 16


def measured_periods(windows: np.ndarray, period: float) -> np.ndarray:
    """The sample period each row of (W, n) stamp steps shows: the mean of the steps under
    1.5 nominal periods (longer ones are gaps; the mean, unlike a median, averages
    alternating jitter), or, where most steps are that long (a slower stream), their median."""
    windows = np.asarray(windows, dtype=np.float64)
    gaps = windows >= 1.5 * period
    kept = windows.shape[1] - np.count_nonzero(gaps, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        periods = np.where(gaps, 0.0, windows).sum(axis=1) / kept
    slow = 2 * (windows.shape[1] - kept) > windows.shape[1]
    if slow.any():
        periods[slow] = np.median(windows[slow], axis=1)
    return periods


class RateWatch:
    """After a RateError: `push(stamps)` gives the stream's rate once two windows of
    `window` steps in a row fit the model again (within `rate_tolerance`), else None."""

    def __init__(self, settings: "FramerSettings", *, receipt: bool = False, window: int = 0):
        self.s, self.receipt = settings, receipt
        self.window = window or RATE_WINDOW_BLOCKS * max(settings.block_length, RATE_BLOCK_MIN)
        self._stamps = np.zeros(0, np.int64)
        self._fitting = 0

    def push(self, stamps_ns: np.ndarray) -> float | None:
        self._stamps = np.concatenate([self._stamps, np.asarray(stamps_ns, np.int64)])
        while len(self._stamps) > self.window:
            stamps, self._stamps = self._stamps[: self.window + 1], self._stamps[self.window :]
            if self.receipt:
                period = envelope_period(stamps, self.s.period_ns)
            else:
                steps = np.diff(stamps)
                steps = steps[steps > 0]
                period = measured_periods(steps[None], self.s.period_ns)[0] if len(steps) else 0
            hz = NS_PER_S / period if period > 0 else math.inf
            fits = abs(hz / self.s.sample_rate_hz - 1.0) <= self.s.rate_tolerance
            self._fitting = self._fitting + 1 if fits else 0
            if self._fitting >= 2:
                return hz
        return None


def stamp_order(
    last_ns: int | None, stamps_ns: np.ndarray, clock_jump_ns: int
) -> tuple[np.ndarray, int | None]:
    """(keep (N,): stamps later than every one before them (`last_ns`: the latest accepted
    before, or None); index of the first stamp more than `clock_jump_ns` before an earlier
    one (a restarted clock), or None). The one rule of the framers and the detector."""
    sentinel = np.iinfo(np.int64).min
    before = np.maximum.accumulate(
        np.concatenate([[sentinel if last_ns is None else last_ns], stamps_ns[:-1]])
    )
    known = before != sentinel  # the sentinel would wrap when subtracted from
    jump = np.flatnonzero(known & (stamps_ns < np.where(known, before, 0) - clock_jump_ns))
    return stamps_ns > before, (int(jump[0]) if len(jump) else None)


def repeats(last_ns, last_values, stamps_ns, values, keep) -> int:
    """How many rows dropped (~keep) repeat the row before them exactly (a message recorded
    twice; the first against `last_ns`, `last_values`, None: none): not bad input."""
    dropped = np.flatnonzero(~keep)
    if len(dropped) == 0:
        return 0
    prev_t = np.concatenate([[-1 if last_ns is None else last_ns], stamps_ns[:-1]])[dropped]
    width = values.shape[1]
    first = np.full(width, np.nan) if last_values is None else np.asarray(last_values, float)
    prev_v = np.concatenate([first[None, :], values[:-1]])[dropped]
    same = (prev_t == stamps_ns[dropped]) & np.all(prev_v == values[dropped], axis=1)
    return int(np.count_nonzero(same))


def bad_samples(values: np.ndarray, sensor_range: float) -> np.ndarray:
    """(N,) samples (N, 3) that are non-finite or beyond `sensor_range` on any axis."""
    with np.errstate(invalid="ignore"):
        return ~(
            np.all(np.isfinite(values), axis=1) & np.all(np.abs(values) <= sensor_range, axis=1)
        )


def rate_refusal(measured_hz: float, settings: "FramerSettings", stats) -> str:
    """Why a stream's first rate window is refused (naming repeated stamps if they explain it)."""
    text = (
        f"sensor stream runs at {measured_hz:.0f} Hz but the model expects "
        f"{settings.sample_rate_hz:g} Hz"
    )
    dropped, total = int(stats.dropped_out_of_order), int(stats.samples_in)
    if 4 * dropped > total:
        text += (
            f" ({dropped} of {total} samples stamped at or before the one before them: "
            f"a driver stamping a packet of samples with one stamp?)"
        )
    return text


def _dropped_not_duplicated(stats) -> tuple[int, int, int, int]:
    """(sensor samples out of order, joint states dropped, each less its exact duplicates,
    and those duplicates)."""
    duplicates = int(getattr(stats, "duplicates", 0) or 0)
    joint_duplicates = int(getattr(stats, "joint_states_duplicates", 0) or 0)
    return (
        int(stats.dropped_out_of_order) - duplicates,
        int(getattr(stats, "joint_states_dropped", 0) or 0) - joint_duplicates,
        duplicates,
        joint_duplicates,
    )


def check_bad_share(stats, where: str, limit: float = MAX_BAD_SHARE) -> None:
    """Raise a one-line StreamError when more than `limit` of the samples pushed were bad
    (`stats`: DenoiserStats, CalibrationStats or a framer's FramerStats)."""
    out_of_order, _, duplicates, _ = _dropped_not_duplicated(stats)
    bad = int(stats.samples_bad) + out_of_order
    total = int(stats.samples_in) - duplicates
    if total == 0:
        raise StreamError(f"{where}: no sensor samples")
    if bad > limit * total:
        raise StreamError(
            f"{where}: {bad} of {total} sensor samples ({100 * bad / total:.1f} %) are bad "
            f"(non-finite, beyond the sensor range or out of order); more than "
            f"{100 * limit:g} % is refused"
        )


def has_bad_input(stats) -> bool:
    """Whether the line `check_stream` gives counts anything (what `--quiet` still says)."""
    return any(
        int(getattr(stats, name, 0) or 0)
        for name in (
            "samples_bad",
            "dropped_out_of_order",
            "gap_filled_samples",
            "resets",
            "joint_states_dropped",
        )
    )


def check_joint_share(unusable: int, joint_states: int, where: str, limit: float) -> None:
    """StreamError if more than `limit` of the `joint_states` are unusable."""
    if joint_states and unusable > limit * joint_states:
        raise StreamError(
            f"{where}: {unusable} of {joint_states} joint states "
            f"({100 * unusable / joint_states:.1f} %) are unusable (non-finite, or not stamped "
            f"after the previous one: a stuck clock?); more than {100 * limit:g} % is refused"
        )


def check_stream(
    stats,
    where: str,
    *,
    joint_states: int,
    limit: float | None = None,
    joints_where: str | None = None,
) -> str:
    """The line of counts to print, or a one-line StreamError: more than `limit`
    (MAX_BAD_SHARE) of the sensor samples bad, or of the `joint_states` dropped (then
    naming `joints_where`, the joint-state topic, if given)."""
    limit = MAX_BAD_SHARE if limit is None else limit
    check_bad_share(stats, where, limit)
    out_of_order, dropped, duplicates, joint_duplicates = _dropped_not_duplicated(stats)
    check_joint_share(dropped, joint_states, joints_where or where, limit)
    return (
        f"bad input treated as missing: {int(stats.samples_bad)} sensor samples "
        f"non-finite or beyond the sensor range, {out_of_order} out of order, "
        f"{int(stats.gap_filled_samples)} bridged, "
        f"{int(stats.resets)} restarts; {dropped} of {joint_states} joint states "
        f"dropped"
    ) + (
        f"; duplicates (recorded twice) dropped: {duplicates} sensor samples, "
        f"{joint_duplicates} joint states"
        if duplicates or joint_duplicates
        else ""
    )


@dataclass(frozen=True, kw_only=True)
class FramerSettings:
    """How a sensor stream is cleaned, filtered and cut into blocks (validated on
    construction); from a model: `FramerSettings.for_model(model, layout=..., **overrides)`."""

    sample_rate_hz: float = 3000.0
    block_length: int = 64
    hop: int = 32
    band_hz: tuple[float, float] = (150.0, 750.0)
    band_order: int = 4
    layout: str = "combined"  # see filters.CHANNEL_LAYOUTS
    sensor_range: float = math.inf  # |value| beyond this on any axis: a bad sample
    max_fill_samples: int = 8
    joint_wait_s: float = 0.02  # give joint states this long to cover a block
    max_hold_s: float = 0.05  # use a joint state this old when none falls in a block
    #: Joint-state stamps are moved this much later before matching (the vibration trails
    #: them, e.g. motor commands ahead of the speed they cause; negative: earlier).
    joint_lag_s: float = 0.0
    rate_tolerance: float = 0.1  # accepted relative error of the measured sample rate
    clock_jump_s: float = 1.0  # a stamp this far back means a restarted clock (bag loop, reset)
    #: What a sensor stamp marks: "sample" time, "receipt" time (core.receipt) or "auto"
    #: (told apart on the first PROBE_SAMPLES samples, which wait for it).
    stamps: str = "auto"
    with_steadiness: bool = True  # compute per-block velocity steadiness (calibration needs it)
    keep_raw: bool = False  # blocks also carry the unfiltered samples (the drop-in output)
    prefiltered: bool = False  # band-passed already (a residual of the band-passed signal)
    source: str = ""  # topic or file named in error messages

    def __post_init__(self) -> None:
        where = f"{self.source}: " if self.source else ""
        validate_blocking(self.block_length, self.hop)
        if self.stamps not in STAMP_KINDS:
            raise ConfigError(
                f"{where}stamps must be one of {list(STAMP_KINDS)}, got {self.stamps!r}"
            )
        if self.layout not in CHANNEL_LAYOUTS:
            raise ConfigError(
                f"{where}channels: unknown layout {self.layout!r}; expected one of "
                f"{sorted(CHANNEL_LAYOUTS)}"
            )
        lag = self.joint_lag_s
        checks = (
            ("sample_rate_hz", self.sample_rate_hz, 0.0, math.inf, False),
            ("sensor_range", self.sensor_range, 0.0, math.inf, True),
            ("joint_wait_s", self.joint_wait_s, 0.0, 10.0, False),
            ("max_hold_s", self.max_hold_s, 0.0, 10.0, False),
            ("joint_lag_s", abs(lag) if isinstance(lag, (int, float)) else lag, 0.0, 1.0, False),
            ("rate_tolerance", self.rate_tolerance, 0.0, 1.0, False),
            ("clock_jump_s", self.clock_jump_s, 0.0, 3600.0, False),
        )
        for name, value, low, high, inf_ok in checks:
            ok = (
                isinstance(value, (int, float))
                and not isinstance(value, bool)
                and not math.isnan(value)
                and (math.isfinite(value) or inf_ok)
                and low <= value <= high
                and (value > 0 or name in ("joint_wait_s", "max_hold_s", "joint_lag_s"))
            )
            if not ok:
                raise ConfigError(
                    f"{where}{name} must be a number in {'(' if low == 0 else '['}{low:g}, "
                    f"{high:g}], got {value!r}"
                )
        for name, value, low, high in (
            ("max_fill_samples", self.max_fill_samples, 0, 1000),
            ("band_order", self.band_order, 1, 12),
        ):
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ConfigError(
                    f"{where}{name} must be an integer in [{low}, {high}], got {value!r}"
                )
        low, high = self.band_hz
        if not (
            math.isfinite(low) and math.isfinite(high) and 0 < low < high < self.sample_rate_hz / 2
        ):
            raise ConfigError(
                f"{where}band_hz must satisfy 0 < low < high < {self.sample_rate_hz / 2:g} Hz, "
                f"got {self.band_hz}"
            )

    @classmethod
    def for_model(cls, model, *, layout: str, **overrides) -> "FramerSettings":
        """The framing a noise model was calibrated with, for a stream of `layout`."""
        profile = model.profile
        fields = dict(
            stamps=profile.sensor_stamps if profile is not None else "auto",
            sample_rate_hz=model.sample_rate_hz,
            block_length=model.block_length,
            hop=model.hop,
            band_hz=model.band_hz,
            band_order=model.band_order,
            layout=layout,
            sensor_range=profile.sensor_range if profile is not None else math.inf,
        )
        fields.update(overrides)
        return cls(**fields)

    @property
    def period_ns(self) -> float:
        return NS_PER_S / self.sample_rate_hz

    def error(self, message: str, kind: type[StreamError] = StreamError) -> StreamError:
        return kind(f"{self.source}: {message}" if self.source else message)


@dataclass
class Blocks:
    """A batch of analysis blocks (B may be 0)."""

    # (B, C, L) band-passed, not yet windowed; with FramerSettings.keep_raw (B, 3C, L): the
    # C band-passed channels, then the same C channels unfiltered, then those minus what
    # lies far below the band (filters.BelowBand: gravity, rigid-body motion)
    samples: np.ndarray
    t_first_ns: np.ndarray  # (B,) stamp of the first real sample in the block
    t_last_ns: np.ndarray  # (B,)
    velocity: np.ndarray  # (B, J) mean joint velocity (NaN when MISSING)
    steadiness: np.ndarray  # (B, J) |mean(first half) - mean(second half)|
    status: np.ndarray  # (B,) velocity.MATCHED / HELD / MISSING
    # Output bookkeeping: the hop of samples that each block completes.
    out_stamps_ns: np.ndarray  # (B, hop) stamps of those samples (-1 for padding/synthetic)
    complete: np.ndarray  # (B,) every sample real (no padding or gap fill)
    # (B,) gap-filled samples inside a block whose first and last samples are real (a
    # bridged bad or missing sample); the block length when an end is padding or fill
    bridged: np.ndarray
    ends_segment: bool = False  # last blocks before a flush or a long gap

    @property
    def n(self) -> int:
        return len(self.samples)


@dataclass
class _Segment:
    stamps: np.ndarray  # int64, -1 marks synthetic (gap-fill) samples
    values: np.ndarray  # (n, 3) raw, cleaned
    ends_stream: bool  # a long gap or a clock jump follows: close the segment
    wait_for_joints: bool = True  # False after a clock jump: no more joint states on the old clock


@dataclass
class FramerStats:
    samples_in: int = 0
    dropped_out_of_order: int = 0
    samples_bad: int = 0  # non-finite or beyond the sensor range: treated as missing
    gap_filled_samples: int = 0
    resets: int = 0
    joint_states_in: int = 0
    joint_states_dropped: int = 0
    blocks: int = 0
    blocks_held: int = 0
    blocks_missing: int = 0
    receipt_latency_ns: int = 0  # stamps read as receipt times: their latency spread, else 0
    # of those dropped as out of order, exact repeats (recorded twice): not bad input
    duplicates: int = 0
    joint_states_duplicates: int = 0


class _Counts:
    """Base of the typed stats of a streaming class: what its framer counted plus its own."""

    @classmethod
    def of(cls, framer: FramerStats, **own):
        """The stats from a framer's counts and the class's own (`own`): the required fields
        that FramerStats has come from `framer` unless given; optional ones (None: not of
        this kind) only when given."""
        counted = {f.name for f in fields(FramerStats)}
        taken = {
            f.name: getattr(framer, f.name)
            for f in fields(cls)
            if f.name in counted and f.default is NO_DEFAULT and f.name not in own
        }
        return cls(**taken, **own)

    def as_dict(self) -> dict:
        """The fields that apply (not None), in declaration order."""
        return {k: v for k, v in asdict(self).items() if v is not None}


@dataclass(frozen=True, kw_only=True)
class DenoiserStats(_Counts):
    """What a denoiser counted (`.stats`); the other kind of denoiser's fields are None (the
    blocks: `paper`; per-sample counts: `cancel`, `hybrid`) and left out of `as_dict()`."""

    method: str | None = None  # cancel | hybrid (None: the paper's StreamingDenoiser)
    samples_in: int
    samples_out: int
    dropped_out_of_order: int
    samples_bad: int
    gap_filled_samples: int
    resets: int
    joint_states_in: int
    joint_states_dropped: int
    blocks: int | None = None
    blocks_held_joint_state: int | None = None
    blocks_no_joint_state: int | None = None
    blocks_out_of_grid: int | None = None
    blocks_unmeasured: int | None = None
    samples_no_joint_state: int | None = None
    rate_checked: bool
    delay_samples: int | None = None
    frequency_correction: list | None = None  # per actuator, relative
    samples_unmeasured: int | None = None
    samples_out_of_grid: int | None = None
    duplicates: int  # of dropped_out_of_order: exact repeats (recorded twice), not bad input
    joint_states_duplicates: int  # of joint_states_dropped: the same


@dataclass(frozen=True, kw_only=True)
class CalibrationStats(_Counts):
    """What a CalibrationAccumulator counted (`.stats`); `mode` is sweep or free."""

    mode: str
    samples_in: int
    samples_bad: int
    blocks: int
    blocks_used: int
    cells: int
    rejected: dict  # reason -> blocks
    dropped_out_of_order: int
    gap_filled_samples: int
    resets: int
    joint_states_dropped: int
    duplicates: int
    joint_states_duplicates: int


def refuse_negative_stamps(stamps_ns: np.ndarray, what: str, error) -> None:
    """`error(message)` if a stamp lies before 1970 (a ROS message can carry one, but rclpy
    refuses them and the core marks synthetic samples -1): refused, never dropped silently."""
    if len(stamps_ns) and int(stamps_ns.min()) < 0:
        first = int(stamps_ns[np.argmax(stamps_ns < 0)])
        raise error(
            f"{what} stamped before 1970 ({first / NS_PER_S:.9f} s: a negative header stamp, "
            f"e.g. a bag restamped to start before 0) are not supported (nor by rclpy); "
            f"shift the stamps to start at or after 0"
        )


def joint_state_arrays(stamps_ns, velocity, n_joints: int, error) -> tuple[np.ndarray, np.ndarray]:
    """Joint-state input as (stamps int64 (M,), velocities (M, n_joints)), or `error`."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    velocity = np.asarray(velocity, dtype=np.float64)
    if velocity.ndim != 2 or velocity.shape != (len(stamps_ns), n_joints):
        raise error(
            f"joint states: expected stamps (M,) and velocities (M, {n_joints}), "
            f"got {stamps_ns.shape} and {velocity.shape}"
        )
    return stamps_ns, velocity


class _Cleaner:
    """Sequential input checks (order, finiteness, gaps) with carried state."""

    def __init__(self, settings: FramerSettings, stats: FramerStats):
        self.s = settings
        self.stats = stats
        self.last_stamp: int | None = None
        self.last_value: np.ndarray | None = None
        # what the stamps mark: "sample" or "receipt" (None: the first samples wait in _probe)
        self.kind: str | None = "sample" if settings.stamps == "sample" else None
        self.receipt: ReceiptClock | None = None  # the rebuilt sample clock, for "receipt"
        self._bad_carry = 0  # receipt: slots of the bad samples after the last good one
        self._probe: list[tuple[np.ndarray, np.ndarray]] = []
        self._probe_n = 0

    def segments(self, stamps: np.ndarray, accel: np.ndarray) -> list[_Segment]:
        stamps = np.asarray(stamps, dtype=np.int64).reshape(-1)
        accel = np.asarray(accel, dtype=np.float64)
        if accel.ndim != 2 or accel.shape != (len(stamps), 3):
            raise self.s.error(
                f"sensor chunk: expected stamps (N,) and samples (N, 3), "
                f"got {stamps.shape} and {accel.shape}"
            )
        refuse_negative_stamps(stamps, "sensor samples", self.s.error)
        self.stats.samples_in += len(stamps)
        if self.kind is None:
            self._probe.append((stamps, accel))
            self._probe_n += len(stamps)
            return self._decide(final=False)
        return self._segments(stamps, accel)

    def finish(self) -> list[_Segment]:
        """End of stream: the samples still waiting to tell what their stamps mark."""
        return self._decide(final=True) if self.kind is None else []

    @property
    def waiting(self) -> int:
        """Samples held until the stamps are told apart (PROBE_SAMPLES at most)."""
        return self._probe_n

    def _decide(self, *, final: bool) -> list[_Segment]:
        """Tell from the waiting samples' in-order good stamps whether they mark sample or
        receipt times, then pass the samples on: no step under half a period in the first
        PROBE_EARLY, sample times; else the first PROBE_SAMPLES decide (core.receipt)."""
        if self._probe_n == 0:
            return []  # nothing yet (an empty push, or a flush before any sample)
        if len(self._probe) > 1:
            self._probe = [
                (_cat_t([t for t, _ in self._probe]), _cat_v([v for _, v in self._probe]))
            ]
        stamps, accel = self._probe[0]
        head = slice(0, PROBE_SAMPLES)
        keep, jump = stamp_order(None, stamps[head], int(self.s.clock_jump_s * NS_PER_S))
        good = keep & ~bad_samples(accel[head], self.s.sensor_range)
        good[len(good) if jump is None else jump :] = False
        in_order = stamps[head][good]
        if (
            self.s.stamps == "auto"
            and len(in_order) >= PROBE_EARLY
            and np.all(np.diff(in_order[:PROBE_EARLY]) >= 0.5 * self.s.period_ns)
        ):
            latency = None
        elif self._probe_n < PROBE_SAMPLES and not final:
            return []
        else:
            latency = receipt_latency(in_order, self.s.period_ns, known=self.s.stamps == "receipt")
        self._probe, self._probe_n = [], 0
        self.kind = "sample" if latency is None else "receipt"
        if latency is not None:
            self.receipt = ReceiptClock(self.s.period_ns, latency, self.s.max_fill_samples)
            self.stats.receipt_latency_ns = int(latency)
            if self.s.stamps == "auto":
                LOG.warning(
                    "%ssensor stamps step under half a period: read as receipt times "
                    "(latency up to %.2f ms: a driver stamping on arrival?); samples counted "
                    "on a rebuilt sample clock",
                    f"{self.s.source}: " if self.s.source else "",
                    latency / 1e6,
                )
        return self._segments(stamps, accel)

    def _segments(self, stamps: np.ndarray, accel: np.ndarray) -> list[_Segment]:
        if len(stamps) == 0:
            return []
        if self.last_stamp is not None and self.receipt is None:
            # Fast path (the live case): in order, no gap, all finite.
            limit = 1.5 * self.s.period_ns
            first_step = int(stamps[0]) - self.last_stamp
            steps = stamps[1:] - stamps[:-1]
            if (
                0 < first_step < limit
                and (len(steps) == 0 or (steps.min() > 0 and steps.max() < limit))
                and self._all_good(accel)
            ):
                self.last_stamp = int(stamps[-1])
                self.last_value = accel[-1].copy()
                return [_Segment(stamps, accel, ends_stream=False)]
        # Out of order: keep a sample only if later than everything accepted before it.
        keep, i = stamp_order(self.last_stamp, stamps, int(self.s.clock_jump_s * NS_PER_S))
        if i is not None:
            # The clock went back (bag loop, sensor reset): end the segment, start afresh.
            head = self._segments(stamps[:i], accel[:i])
            if not head:
                head = [_Segment(np.zeros(0, dtype=np.int64), np.zeros((0, 3)), ends_stream=True)]
            head[-1].ends_stream, head[-1].wait_for_joints = True, False
            self.stats.resets += 1
            self.last_stamp = None
            return head + self._segments(stamps[i:], accel[i:])
        if not keep.all():
            self.stats.dropped_out_of_order += int((~keep).sum())
            self.stats.duplicates += repeats(self.last_stamp, self.last_value, stamps, accel, keep)
            stamps, accel = stamps[keep], accel[keep]
        if len(stamps) == 0:
            return []
        # Bad samples (non-finite, beyond the sensor range) are missing: the gap rules below
        # bridge or restart around them, exactly as if they had never arrived.
        bad = bad_samples(accel, self.s.sensor_range)
        if self.receipt is not None:
            missing = self._receipt_gaps(stamps, bad)
        if bad.any():
            self.stats.samples_bad += int(bad.sum())
            stamps, accel = stamps[~bad], accel[~bad]
            if len(stamps) == 0:
                return []
        if self.receipt is None:
            # Gaps, measured against the previous accepted sample.
            prev_stamp = np.concatenate(
                [[self.last_stamp if self.last_stamp is not None else stamps[0]], stamps[:-1]]
            )
            missing = np.rint((stamps - prev_stamp) / self.s.period_ns).astype(np.int64) - 1
            missing[0] = missing[0] if self.last_stamp is not None else 0
        segments: list[_Segment] = []
        prev_value = self.last_value
        start = 0
        pieces_t, pieces_v = [], []
        for i in np.flatnonzero(missing > 0):
            pieces_t.append(stamps[start:i])
            pieces_v.append(accel[start:i])
            left_value = accel[i - 1] if i > 0 else prev_value
            if missing[i] <= self.s.max_fill_samples and left_value is not None:
                k = int(missing[i])
                self.stats.gap_filled_samples += k
                frac = (np.arange(1, k + 1) / (k + 1))[:, None]
                pieces_t.append(np.full(k, -1, dtype=np.int64))
                pieces_v.append(left_value[None, :] + frac * (accel[i] - left_value)[None, :])
            else:
                self.stats.resets += 1
                segments.append(_Segment(_cat_t(pieces_t), _cat_v(pieces_v), ends_stream=True))
                pieces_t, pieces_v = [], []
            start = i
        pieces_t.append(stamps[start:])
        pieces_v.append(accel[start:])
        segments.append(_Segment(_cat_t(pieces_t), _cat_v(pieces_v), ends_stream=False))
        self.last_stamp = int(stamps[-1])
        self.last_value = accel[-1].copy()
        return segments

    def _receipt_gaps(self, stamps: np.ndarray, bad: np.ndarray) -> np.ndarray:
        """Samples missing before each good sample on the rebuilt sample clock: the gap the
        clock finds plus the bad samples since the previous good one (bridged like lost ones)."""
        if self.last_stamp is None:  # a new segment: its first stamp anchors the clock
            self.receipt.restart()
            self._bad_carry = 0
        own, _ = self.receipt.gaps(stamps)
        slots = np.cumsum(own + bad)  # a bad sample: its own slot and the gap before it
        good = np.flatnonzero(~bad)
        if len(good) == 0:
            self._bad_carry += int(slots[-1])
            return np.zeros(0, dtype=np.int64)
        before = np.concatenate([[-self._bad_carry], slots[good[:-1]]])
        missing = slots[good] - before
        self._bad_carry = int(slots[-1] - slots[good[-1]])
        if self.last_stamp is None:
            missing[0] = 0  # the first good sample of a segment: nothing before it to bridge
        return missing

    def _all_good(self, accel: np.ndarray) -> bool:
        if not np.isfinite(accel).all():
            return False
        return (
            math.isinf(self.s.sensor_range)
            or float(np.abs(accel).max(initial=0.0)) <= self.s.sensor_range
        )


def _cat_t(pieces: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(pieces) if pieces else np.zeros(0, dtype=np.int64)


def _cat_v(pieces: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(pieces) if pieces else np.zeros((0, 3))


class _Framer:
    """What BlockFramer and SampleFramer share: the input cleaning (`_Cleaner`, its segments
    to the subclass's `_push_segments`), the band-pass, the joint states and the rate check."""

    def __init__(self, settings: FramerSettings, n_joints: int, n_channels: int):
        self.s = settings
        self.n_joints = int(n_joints)
        self.stats = FramerStats()
        self._cleaner = _Cleaner(settings, self.stats)
        self._bandpass = BandPass.of(settings, n_channels)
        self._joint_t = np.zeros(0, dtype=np.int64)
        self._joint_v = np.zeros((0, self.n_joints))
        self._rate_checked = False
        self._rate_error = ""
        self._rate_steps: list[np.ndarray] = []  # stamp steps not yet measured
        self._rate_ends: list[np.ndarray] = []  # the stamp each of those steps ends at
        self._rate_count = 0  # how many
        self._rate_last: int | None = None  # last real stamp of the open segment
        self._rate_off_windows = 0  # consecutive windows measured beyond the tolerance
        self._max_hold_ns = int(settings.max_hold_s * NS_PER_S)
        self._joint_lag_ns = int(round(settings.joint_lag_s * NS_PER_S))
        # joint states moved later arrive that much later relative to the samples they cover
        self._joint_wait_ns = int(settings.joint_wait_s * NS_PER_S) + max(self._joint_lag_ns, 0)

    def push_sensor(self, stamps_ns: np.ndarray, accel: np.ndarray) -> None:
        self._push_segments(self._cleaner.segments(stamps_ns, accel))

    def _push_segments(self, segments: list[_Segment]) -> None:
        for segment in segments:
            self._check_rate(segment.stamps)
            self._append(segment.stamps, segment.values)
            if segment.ends_stream:
                self._rate_segment_ends(segment)
                self._close_segment(wait_for_joints=segment.wait_for_joints)
            self._drain(final=False)

    def _keep_joint_states(self, stamps_ns: np.ndarray, velocity: np.ndarray, in_order) -> None:
        """Append the joint states in order (`in_order`) and finite; count the dropped and
        the repeated."""
        keep = in_order & np.all(np.isfinite(velocity), axis=1)
        self.stats.joint_states_dropped += int((~keep).sum())
        last = int(self._joint_t[-1]) if len(self._joint_t) else None
        last_v = self._joint_v[-1] if len(self._joint_v) else None
        self.stats.joint_states_duplicates += repeats(last, last_v, stamps_ns, velocity, keep)
        if keep.any():
            self._joint_t = np.concatenate([self._joint_t, stamps_ns[keep]])
            self._joint_v = np.concatenate([self._joint_v, velocity[keep]])

    def _append_in_order(self, stamps_ns: np.ndarray, velocity: np.ndarray) -> bool:
        """Append joint states that are in order and finite (the live case: nothing to drop
        or count); False if not all are."""
        if len(self._joint_t) and stamps_ns[0] <= self._joint_t[-1]:
            return False
        if len(stamps_ns) > 1 and not (stamps_ns[1:] > stamps_ns[:-1]).all():
            return False
        if not np.isfinite(velocity).all():
            return False
        self._joint_t = np.concatenate([self._joint_t, stamps_ns])
        self._joint_v = np.concatenate([self._joint_v, velocity])
        return True

    @property
    def rate_checked(self) -> bool:
        """The stream's rate was measured on its first 2 blocks' worth and found right."""
        return self._rate_checked and not self._rate_error

    @property
    def stamps(self) -> str:
        """What the sensor stamps mark: "sample", "receipt" or "" (not yet told)."""
        return self._cleaner.kind or ""

    def _rate_window(self) -> int:
        """Samples (steps) per rate window: 2 blocks' worth, then RATE_WINDOW_BLOCKS'."""
        blocks = RATE_WINDOW_BLOCKS if self._rate_checked else 2
        need = blocks * max(self.s.block_length, RATE_BLOCK_MIN)
        if self._cleaner.receipt is not None:
            need = self._cleaner.receipt.rate_window(need, first=not self._rate_checked)
        return need

    def _check_rate(self, stamps: np.ndarray) -> None:
        """Measure the rate on the steps between a segment's real samples (receipt stamps:
        `envelope_period`) over consecutive windows counted in samples: any chunking and
        either framer measures the same windows, so every method accepts the same streams."""
        if self._rate_error:
            # refused for good (a live node restarts on a new framer: RateWatch)
            raise self.s.error(self._rate_error, RateError)
        receipt = self._cleaner.receipt is not None
        if receipt:
            steps = ends = stamps  # every sample: envelope_period counts those received
        else:
            real = stamps[stamps >= 0]
            if len(real) == 0:
                return
            if self._rate_last is not None:
                steps, ends = real - np.concatenate(([self._rate_last], real[:-1])), real
            else:
                steps, ends = np.diff(real), real[1:]
            self._rate_last = int(real[-1])
        self._rate_steps.append(steps)
        self._rate_ends.append(ends)
        self._rate_count += len(steps)
        if self._rate_count < self._rate_window():
            return
        # joined once per chunk and walked by offset: a long chunk (batch) holds many windows
        seen, ends = np.concatenate(self._rate_steps), np.concatenate(self._rate_ends)
        start = 0
        while len(seen) - start >= (need := self._rate_window()):
            count = 1 if receipt or not self._rate_checked else (len(seen) - start) // need
            windows = seen[start : start + count * need].reshape(count, need)
            if receipt:
                periods = np.array([envelope_period(windows[0], self.s.period_ns)])
            else:  # every whole window of the chunk at once
                periods = measured_periods(windows, self.s.period_ns)
            first, start = start, start + count * need
            self._rate_steps, self._rate_ends = [seen[start:]], [ends[start:]]
            self._rate_count = len(seen) - start
            if not self._rate_checked:
                self._judge_first_rate(NS_PER_S / periods[0])
                continue
            off = np.abs(NS_PER_S / periods / self.s.sample_rate_hz - 1.0) > self.s.rate_tolerance
            for w in range(count):
                self._rate_off_windows = self._rate_off_windows + 1 if off[w] else 0
                if self._rate_off_windows >= 2:
                    begin = first + w * need
                    self._refuse_rate_change(
                        NS_PER_S / periods[w], windows[w], int(ends[begin : begin + need].max())
                    )

    def _refuse_rate_change(self, measured: float, window: np.ndarray, end_ns: int) -> None:
        """Two windows in a row beyond the tolerance: refused from here on."""
        self._rate_error = (
            f"sensor rate changed: the stream ran at {measured:.0f} Hz over the "
            f"{len(window)} samples up to stamp {end_ns / NS_PER_S:.3f} s but the model "
            f"expects {self.s.sample_rate_hz:g} Hz (tolerance "
            f"{100 * self.s.rate_tolerance:g} %); refused, not interpolated"
        )
        if self._cleaner.receipt is None and np.mean(window < 0.5 * self.s.period_ns) > 0.1:
            self._rate_error += (
                "; many of its steps are under half a period: stamped on receipt "
                "from there on (the driver or its settings changed?)"
            )
        raise self.s.error(self._rate_error, RateError)

    def _judge_first_rate(self, measured: float) -> None:
        """The first window's rate: off by more than the tolerance, the stream is refused."""
        self._rate_checked = True
        if abs(measured / self.s.sample_rate_hz - 1.0) > self.s.rate_tolerance:
            self._rate_error = rate_refusal(measured, self.s, self.stats)
            raise self.s.error(self._rate_error, RateError)

    def _rate_segment_ends(self, segment) -> None:
        """No step is measured across a long gap or a clock jump; receipt stamps: a window
        spans gaps (it counts samples received) but not a clock jump."""
        self._rate_last = None
        if self._cleaner.receipt is not None and not segment.wait_for_joints:
            self._rate_steps, self._rate_ends, self._rate_count = [], [], 0


class BlockFramer(_Framer):
    """Streaming framer: push joint states and sensor chunks in any sizes; `pop_blocks()`."""

    def __init__(self, settings: FramerSettings, n_joints: int):
        self.n_channels = len(CHANNEL_LAYOUTS[settings.layout])
        super().__init__(settings, n_joints, self.n_channels)
        self._rows = self.n_channels * (3 if settings.keep_raw else 1)  # rows of the buffer
        self.window = analysis_window(settings.block_length, settings.hop)
        self._below_band = BelowBand(
            sample_rate_hz=settings.sample_rate_hz,
            band_hz=settings.band_hz,
            n_channels=self.n_channels,
        )
        self._ready: list[Blocks] = []
        self._closed: list[list] = []  # [buf_x, buf_t, wait_for_joints] of ended segments
        self._offsets = np.arange(settings.block_length)
        self._start_segment()

    # --- input ---------------------------------------------------------------
    def push_joint_states(
        self, stamps_ns: np.ndarray, velocity: np.ndarray, *, release: bool = True
    ) -> None:
        """Joint states in; `release` False: what they complete waits for the next push
        (a sensor push right after releases it all at once: a live node's batch)."""
        stamps_ns, velocity = joint_state_arrays(stamps_ns, velocity, self.n_joints, self.s.error)
        self.stats.joint_states_in += len(stamps_ns)
        if len(stamps_ns) == 0:
            return
        if self._joint_lag_ns:
            stamps_ns = stamps_ns + self._joint_lag_ns
        if self._append_in_order(stamps_ns, velocity):  # the live case
            if release:
                self._drain(final=False)
            return
        last = self._joint_t[-1] if len(self._joint_t) else np.iinfo(np.int64).min
        in_order, i = stamp_order(
            last if len(self._joint_t) else None, stamps_ns, int(self.s.clock_jump_s * NS_PER_S)
        )
        if i is not None:
            # The joint clock went back (bag loop, reset): forget the old timeline.
            # (the pushes below shift the stamps again: undo the shift here)
            self.push_joint_states(stamps_ns[:i] - self._joint_lag_ns, velocity[:i])
            self.stats.joint_states_in -= len(stamps_ns)  # counted once, here
            # Complete the accelerometer blocks still pending on the old clock with its joint
            # states, then forget them.
            self._close_segment(wait_for_joints=False)
            self._drain(final=False)
            self._joint_t, self._joint_v = self._joint_t[:0], self._joint_v[:0]
            self.push_joint_states(stamps_ns[i:] - self._joint_lag_ns, velocity[i:])
            self.stats.joint_states_in += i
            return
        self._keep_joint_states(stamps_ns, velocity, in_order)
        self._drain(final=False)

    def flush(self) -> None:
        """End of stream: complete all pending blocks (zero padding at the end)."""
        self._push_segments(self._cleaner.finish())
        self._drain(final=True)

    def pop_blocks(self) -> list[Blocks]:
        ready, self._ready = self._ready, []
        return ready

    @property
    def backlog(self) -> tuple[int, int]:
        """(samples buffered, joint states held): bounded however long the stream runs."""
        return len(self._buf_t) + self._cleaner.waiting, len(self._joint_t)

    # --- internals -------------------------------------------------------------
    def _start_segment(self) -> None:
        pad = self.s.block_length - self.s.hop
        # Front padding so the first real sample is covered by L/hop blocks like all others.
        self._buf_x = np.zeros((self._rows, pad))  # channels first
        self._buf_t = np.full(pad, -1, dtype=np.int64)
        self._bandpass.reset()
        self._below_band.reset()

    def _append(self, stamps: np.ndarray, values: np.ndarray) -> None:
        if len(stamps) == 0:
            return
        channels = channel_matrix(values, self.s.layout).T
        rows = np.array(channels) if self.s.prefiltered else self._bandpass.process(channels)
        if self.s.keep_raw:
            above = channels - self._below_band.process(channels)
            rows = np.concatenate([rows, channels, above], axis=0)
        self._buf_x = np.concatenate([self._buf_x, rows], axis=1)
        self._buf_t = np.concatenate([self._buf_t, stamps])

    def _close_segment(self, *, wait_for_joints: bool) -> None:
        """End the open segment (long gap, clock jump, flush): pad it and queue it; its last
        blocks wait for their joint states like any other, unless the joint clock restarted."""
        L, H = self.s.block_length, self.s.hop
        buf_x, buf_t = self._buf_x, self._buf_t
        real_pos = np.flatnonzero(buf_t >= 0)
        if len(real_pos):
            # Zero-pad so the block completing the last real sample exists.
            required = (int(real_pos[-1]) // H) * H + L
            if required > len(buf_t):
                need = required - len(buf_t)
                buf_x = np.concatenate([buf_x, np.zeros((self._rows, need))], axis=1)
                buf_t = np.concatenate([buf_t, np.full(need, -1, dtype=np.int64)])
            self._closed.append([buf_x, buf_t, wait_for_joints])
        self._start_segment()

    def _drain(self, *, final: bool) -> None:
        L, H = self.s.block_length, self.s.hop
        if final:
            self._close_segment(wait_for_joints=False)
        # Closed segments first, in order; each ends with a block flagged ends_segment.
        while self._closed:
            buf_x, buf_t, wait = self._closed[0]
            buf_x, buf_t = self._release(buf_x, buf_t, wait=wait and not final, closing=True)
            if len(buf_t) >= L:  # blocks still waiting for their joint states
                self._closed[0][:2] = buf_x, buf_t
                return
            self._closed.pop(0)
        if final:
            return
        if L <= len(self._buf_t) < L + H:
            self._drain_one()
        else:
            self._buf_x, self._buf_t = self._release(
                self._buf_x, self._buf_t, wait=True, closing=False
            )

    def _release(
        self, buf_x: np.ndarray, buf_t: np.ndarray, *, wait: bool, closing: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """Cut the blocks available in a buffer (those whose joint states are in, if `wait`),
        queue them, and return what is left of the buffer."""
        L, H = self.s.block_length, self.s.hop
        n_blocks = (len(buf_t) - L) // H + 1 if len(buf_t) >= L else 0
        if n_blocks <= 0:
            return buf_x, buf_t
        index = (np.arange(n_blocks) * H)[:, None] + self._offsets[None, :]  # (B, L)
        window_t = buf_t[index]
        real = window_t >= 0
        any_real = real.any(axis=1)
        t_last = window_t.max(axis=1)  # stamps increase; non-real samples are -1
        t_first = np.where(real, window_t, np.iinfo(np.int64).max).min(axis=1)
        if wait:
            latest_joint = self._joint_t[-1] if len(self._joint_t) else None
            waited = (self._cleaner.last_stamp - t_last) >= int(self.s.joint_wait_s * NS_PER_S)
            ready = waited if latest_joint is None else (t_last <= latest_joint) | waited
            if not ready.all():  # blocks are released strictly in order
                n_blocks = int(np.argmin(ready))
                if n_blocks == 0:
                    return buf_x, buf_t
                index, window_t, real = index[:n_blocks], window_t[:n_blocks], real[:n_blocks]
                any_real, t_first, t_last = (a[:n_blocks] for a in (any_real, t_first, t_last))
        samples = buf_x[:, index].transpose(1, 0, 2).copy()  # (B, C, L)
        velocity, steadiness, status = self._matched(
            np.where(any_real, t_first, 0), np.where(any_real, t_last, 0)
        )
        status[~any_real] = MISSING
        self.stats.blocks += n_blocks
        self.stats.blocks_held += int(np.count_nonzero(status == 1))
        self.stats.blocks_missing += int(np.count_nonzero(status == MISSING))
        rest_x, rest_t = buf_x[:, n_blocks * H :], buf_t[n_blocks * H :]
        self._ready.append(
            Blocks(
                samples,
                t_first,
                t_last,
                velocity,
                steadiness,
                status,
                window_t[:, :H],
                ends_segment=closing and len(rest_t) < L,
                complete=real.all(axis=1),
                bridged=np.where(real[:, 0] & real[:, -1], L - real.sum(axis=1), L),
            )
        )
        if any_real.any():
            self._trim_joints(int(t_first[any_real][-1]))
        return rest_x, rest_t

    def _drain_one(self) -> None:
        """The live case, one block: `_release`'s result with Python scalars and views."""
        L, H = self.s.block_length, self.s.hop
        window_t = self._buf_t[:L]
        t_last = int(window_t[-1])
        if t_last < 0:  # ends in gap fill: rare
            t_last = int(window_t.max())
            if t_last < 0:
                return
        # Readiness first, on Python ints: most calls find the joint states not yet in.
        joint_t = self._joint_t
        if not (
            (len(joint_t) and t_last <= int(joint_t[-1]))
            or self._cleaner.last_stamp - t_last >= self._joint_wait_ns
        ):
            return
        real = window_t >= 0
        complete = bool(real.all())
        t_first = (
            int(window_t[0]) if complete or window_t[0] >= 0 else int(window_t[int(real.argmax())])
        )
        first, last = np.array([t_first], dtype=np.int64), np.array([t_last], dtype=np.int64)
        velocity, steadiness, status = self._matched(first, last)
        self.stats.blocks += 1
        if status[0] == 1:
            self.stats.blocks_held += 1
        elif status[0] == MISSING:
            self.stats.blocks_missing += 1
        self._ready.append(
            Blocks(
                self._buf_x[None, :, :L],
                first,
                last,
                velocity,
                steadiness,
                status,
                window_t[None, :H],
                ends_segment=False,
                complete=np.array([complete]),
                bridged=np.array([L - int(real.sum()) if real[0] and real[-1] else L]),
            )
        )
        self._buf_x, self._buf_t = self._buf_x[:, H:], self._buf_t[H:]
        self._trim_joints(t_first)

    def _matched(self, first: np.ndarray, last: np.ndarray) -> tuple:
        """The blocks' joint velocity, steadiness and status (core.velocity)."""
        hold, steadiness = self._max_hold_ns, self.s.with_steadiness
        joints = (self._joint_t, self._joint_v)
        return block_mean_velocity(
            *joints, first, last, max_hold_ns=hold, with_steadiness=steadiness
        )

    def _trim_joints(self, oldest_needed_ns: int) -> None:
        # Keep one joint state before the next block's span for the hold rule.
        cut = int(np.searchsorted(self._joint_t, oldest_needed_ns, side="left")) - 1
        if cut > 256:
            self._joint_t = self._joint_t[cut:]
            self._joint_v = self._joint_v[cut:]


@runtime_checkable
class StreamConsumer(Protocol):
    """What `feed` drives and every streaming class of the core is: joint states and sensor
    chunks pushed in time order, in any sizes; each push returns what became ready (None
    for a consumer that keeps its results); `flush()` is the caller's."""

    def push_joint_states(self, stamps_ns: np.ndarray, velocity: np.ndarray) -> Any: ...

    def push_sensor(self, stamps_ns: np.ndarray, accel: np.ndarray) -> Any: ...


def feed(
    consumer: StreamConsumer,
    sensor_stamps_ns: np.ndarray,
    accel: np.ndarray,
    joint_stamps_ns: np.ndarray,
    joint_velocity: np.ndarray,
    *,
    sample_rate_hz: float,
    joint_wait_s: float,
    chunk_s: float = 10.0,
    progress=None,
) -> list:
    """Push whole arrays into a streaming consumer `chunk_s` seconds at a time, joint states
    first up to a little past each sensor chunk so that no block waits (every batch path);
    returns what the pushes returned; the caller flushes. `progress(n)`: samples consumed."""
    sensor_stamps_ns = np.asarray(sensor_stamps_ns, dtype=np.int64).reshape(-1)
    joint_stamps_ns = np.asarray(joint_stamps_ns, dtype=np.int64).reshape(-1)
    step = max(1, int(chunk_s * sample_rate_hz))
    wait_ns = int(joint_wait_s * NS_PER_S) + 1
    outputs, joint_pos = [], 0
    for start in range(0, len(sensor_stamps_ns), step):
        stop = min(start + step, len(sensor_stamps_ns))
        last = stop == len(sensor_stamps_ns)
        joint_stop = (
            len(joint_stamps_ns)
            if last
            else int(
                np.searchsorted(joint_stamps_ns, sensor_stamps_ns[stop - 1] + wait_ns, side="right")
            )
        )
        if joint_stop > joint_pos:
            outputs.append(
                consumer.push_joint_states(
                    joint_stamps_ns[joint_pos:joint_stop], joint_velocity[joint_pos:joint_stop]
                )
            )
            joint_pos = joint_stop
        outputs.append(consumer.push_sensor(sensor_stamps_ns[start:stop], accel[start:stop]))
        if progress is not None:
            progress(stop - start)
    if joint_pos < len(joint_stamps_ns):
        outputs.append(
            consumer.push_joint_states(joint_stamps_ns[joint_pos:], joint_velocity[joint_pos:])
        )
    return outputs
