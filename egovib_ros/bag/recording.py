"""Recordings (numpy arrays of a bag's sensor and joint streams) read in bounded memory.

`iter_recording(path, profile=...)` yields consecutive time slices of a bag as
`Recording`s; `read_recording` joins them. Topics, Imu field and joints come from the robot
profile (INTERFACES.md section 1b): the sensor topic's `sensor.field` vector becomes
`sensor`, and the joints are picked by name from JointStates of any joints in any order.

Slices are aligned for the streaming core: a slice carries every joint state read so far
and only sensor samples whose joint states (up to `HORIZON_NS` past them) and earlier
samples are all in, so pushing its joint states, then its samples, into a
StreamingDenoiser or CalibrationAccumulator gives the whole-array result (tested). "In":
the reader has passed that time (chunks come in the order of their first log time; each
stream's stamps are placed against log times by the least stamp - log time it has shown:
receive-time logs, another clock). A chunk holding a whole topic makes its samples wait
until the other topics come. Only when log times stop advancing for two batches while
`max_lag_s` of samples wait do the oldest go on without their joint states (counted in
`released_early`). Partial JointStates (one per controller) are merged as
joint_state_publisher does: each joint keeps its last value until published again.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, fields
from functools import lru_cache
from typing import Callable, Iterable, Iterator, Sequence

import numpy as np

from egovib_ros.bag.codec import (
    COMMANDS_TYPE,
    IMU_TYPE,
    JOINT_STATE_TYPE,
    MessageBatch,
    decode_commands,
    decode_imu,
    decode_joint_states,
    encode_commands,
    encode_imu_batch,
    encode_joint_state_batch,
)
from egovib_ros.bag.reader import BagReader, ReadBatch
from egovib_ros.bag.writer import BagWriter
from egovib_ros.core.stream import refuse_negative_stamps
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.core.velocity import JointVelocity, SplitJointStates, hold_missing_joints
from egovib_ros.errors import BagError
from egovib_ros.robot import COMMANDS_TOPIC, RobotProfile, load_profile

LOG = logging.getLogger("egovib_ros.bag")
HORIZON_NS = NS_PER_S // 10  # joint states a sensor sample waits for, past its stamp


@lru_cache(maxsize=1)
def _default_profile() -> RobotProfile:
    return load_profile(None)


def _default_joint_names() -> tuple[str, ...]:
    return _default_profile().joint_names


@dataclass
class Recording:
    """Everything the project keeps of a bag, as numpy arrays (see docs/DESIGN.md)."""

    sensor_stamps_ns: np.ndarray  # (N,) int64, sensor sample stamps
    sensor: np.ndarray  # (N, 3) float64, the profile's field (raw topic)
    joint_stamps_ns: np.ndarray  # (M,) int64
    joint_position: np.ndarray  # (M, J) float64
    joint_velocity: np.ndarray  # (M, J) float64
    joint_names: tuple[str, ...] = field(default_factory=_default_joint_names)
    contact: np.ndarray | None = None  # (N, 3) ground truth, same stamps as accel
    ego: np.ndarray | None = None  # (N, 3) ground truth
    denoised_stamps_ns: np.ndarray | None = None
    denoised: np.ndarray | None = None  # (K, 3)
    command_stamps_ns: np.ndarray | None = None
    commands: np.ndarray | None = None  # (P, J)

    @property
    def duration_s(self) -> float:
        """Time span of the sensor stream in seconds."""
        if len(self.sensor_stamps_ns) < 2:
            return 0.0
        return float(self.sensor_stamps_ns[-1] - self.sensor_stamps_ns[0]) / NS_PER_S


def bag_topic_names(profile: RobotProfile | None = None) -> dict[str, str]:
    """The topics a bag of this robot holds: raw, denoised, joint_states, commands and the
    simulator's ground truth (contact, ego: siblings of the sensor topic)."""
    profile = profile or _default_profile()
    head = profile.sensor_topic.rstrip("/").rpartition("/")[0]
    return {
        "joint_states": profile.joints_topic,
        "raw": profile.sensor_topic,
        "denoised": profile.denoised_topic,
        "contact": f"{head}/contact",
        "ego": f"{head}/ego",
        "commands": f"/{COMMANDS_TOPIC}",
    }


def _by_stamp(stamps: np.ndarray, *values: np.ndarray) -> tuple:
    """Stamps and their rows in stamp order (stable; usually already in order)."""
    if len(stamps) > 1 and np.any(stamps[1:] < stamps[:-1]):
        order = np.argsort(stamps, kind="stable")
        return (stamps[order],) + tuple(v[order] for v in values)
    return (stamps,) + values


def _concat(parts: list[np.ndarray], width: int | None) -> np.ndarray:
    if parts:
        return np.concatenate(parts)
    return np.zeros(0, np.int64) if width is None else np.zeros((0, width))


class RecordingStream:
    """Turns ReadBatches of one bag into aligned Recording slices (see the module doc):
    `add(batch)` for each of `reader.batches(stream.topics)`, then `finish()`."""

    def __init__(
        self,
        reader: BagReader,
        profile: RobotProfile | None = None,
        *,
        ground_truth: bool = True,
        denoised: bool = True,
        commands: bool = True,
        max_lag_s: float = 10.0,
        min_slice_s: float = 1.0,
    ):
        self.reader = reader
        self.profile = profile or _default_profile()
        self.names = bag_topic_names(self.profile)
        self.field = self.profile.sensor_field
        self._flat = _FlatWatch()  # a sensor that never changes is refused at the end
        self.joint_names = tuple(self.profile.joint_names)
        reader.require(self.names["raw"], IMU_TYPE)
        reader.require(self.names["joint_states"], JOINT_STATE_TYPE)
        optional = {
            "contact": ground_truth,
            "ego": ground_truth,
            "denoised": denoised,
            "commands": commands,
        }
        self.present = {"raw", "joint_states"}
        for key, wanted in optional.items():
            topic = self.names[key]
            if (
                wanted
                and topic in reader.topics
                and topic not in (self.names["raw"], self.names["joint_states"])
            ):
                reader.require(topic, COMMANDS_TYPE if key == "commands" else IMU_TYPE)
                self.present.add(key)
        self.topics = [self.names[k] for k in sorted(self.present)]
        self._key_of = {self.names[k]: k for k in self.present}
        self.max_pending = max(1, int(max_lag_s * self.profile.rate_hz))
        self.min_slice_ns = int(min_slice_s * NS_PER_S)
        self._sensor_keys = [k for k in ("raw", "contact", "ego") if k in self.present]
        self._sensor: dict[str, list] = {k: [] for k in self._sensor_keys}  # [(stamps, values)]
        self._joints: list[tuple] = []
        self._denoised: list[tuple] = []
        self._commands: list[tuple] = []
        self._last_joint_values: np.ndarray | None = None  # for merging partial JointStates
        self._split_joints = SplitJointStates()  # one message per joint, one stamp: one row
        self._joint_seen = np.zeros(len(self.joint_names), bool)
        self._joint_notes: dict = {}  # codec.decode_joint_states: joints named, short arrays
        self.joint_velocity = JointVelocity(
            len(self.joint_names), source=self.profile.velocity_source
        )
        self._velocity_usable = np.zeros(len(self.joint_names), np.int64)
        self._frontier_ns: int | None = None
        self._stuck = 0  # batches read since the frontier last moved
        self.released_early = 0  # sensor samples let go before their joint states could be in
        # per stream, the least header stamp - log time seen: where the frontier of log times
        # falls among its stamps (a latency, or another clock: simulated time, wall-time logs)
        self._lead_ns: dict[str, int] = {}
        self.counts = {k: 0 for k in self.present}
        self._started = False  # the sensor streams' starts aligned (`_align_ends`)
        self.repeated = {k: 0 for k in self.present}  # messages recorded twice, read once
        self._last_row: dict[str, np.ndarray] = {}
        self._last_stamp: dict[str, int] = {}
        self.unmatched_ends = {k: 0 for k in self._sensor_keys}
        self.decoded: dict[str, tuple] = {}  # the last batch's decoded streams, by key (raw, ...)

    # --- input -------------------------------------------------------------------------
    def add(self, batch: ReadBatch) -> list[Recording]:
        self.decoded = {}
        if batch.frontier_ns is None or (
            self._frontier_ns is not None and batch.frontier_ns <= self._frontier_ns
        ):
            self._stuck += 1
        else:
            self._stuck = 0
        self._frontier_ns = batch.frontier_ns
        for topic, messages in batch.messages.items():
            key = self._key_of.get(topic)
            if key is None or len(messages) == 0:
                continue
            self.counts[key] += len(messages)
            try:
                self._add(key, messages)
            except BagError:
                raise
            except Exception as exc:
                raise BagError(
                    f"{self.reader.path}: topic {topic}: cannot decode message ({exc})"
                ) from None
        return self._release(final=False)

    def finish(self) -> list[Recording]:
        """The remaining slices; then checks what the whole bag must satisfy."""
        held = self._split_joints.flush()  # the last stamp's joint states
        if held is not None:
            self._add_joint_rows(*held)
        pieces = self._release(final=True)
        where = self.reader.path
        if any(self.repeated.values()):
            LOG.warning(
                f"{where}: messages recorded twice (each the same stamp and numbers as the one "
                f"before it), read once: "
                + ", ".join(f"{n} of {self.names[k]}" for k, n in self.repeated.items() if n)
            )
        if any(self.unmatched_ends.values()):
            LOG.warning(
                f"{where}: the sensor topic and its ground truth start or stop at different "
                f"times (a recorder started or stopped between them); samples without their "
                f"counterpart left out: "
                + ", ".join(f"{n} of {self.names[k]}" for k, n in self.unmatched_ends.items() if n)
            )
        if self.released_early:
            LOG.warning(
                f"{where}: {self.released_early} sensor samples went on before their joint "
                f"states could be read (the bag's log times stop advancing)"
            )
        for key in ("raw", "joint_states"):
            if self.counts[key] == 0:
                raise BagError(f"{where}: topic {self.names[key]} has no messages")
        if self._flat.flat:
            raise BagError(
                f"{where}: {self.names['raw']}: its {self.field} never changes over "
                f"{self._flat.samples} samples (a dead or disconnected sensor, or a field its "
                f"messages leave unset: check the robot profile's sensor field)"
            )
        if not self._joint_seen.all():
            missing = [n for n, seen in zip(self.joint_names, self._joint_seen) if not seen]
            raise BagError(
                f"{where}: topic {self.names['joint_states']} lacks joint(s) {', '.join(missing)} "
                f"(named by robot profile {self.profile.name!r})"
            )
        if self._joint_notes.get("repeated"):
            LOG.warning(
                f"{where}: topic {self.names['joint_states']}: a joint named twice in a "
                f"message {self._joint_notes['repeated']} times (two drivers writing into one "
                f"message?): the first of each is used"
            )
        short = {k: self._joint_notes.get(f"short_{k}", 0) for k in ("position", "velocity")}
        for key, count in short.items():
            if count:  # neither empty nor one value per name: which joint is which?
                LOG.warning(
                    f"{where}: topic {self.names['joint_states']}: {count} messages carry fewer "
                    f"{key} values than joint names (a malformed JointState): the values "
                    f"are matched to the first names, the joints after them have no {key}"
                    + (
                        " (differentiated from positions where joints.velocity allows it)"
                        if key == "velocity"
                        else ""
                    )
                )
        if not self._velocity_usable.all():
            joints = [n for n, k in zip(self.joint_names, self._velocity_usable) if not k]
            why = (
                "no velocity (the profile's joints.velocity is 'measured'; 'auto' would "
                "differentiate positions)"
                if self.profile.velocity_source == "measured"
                else "neither a velocity nor positions to differentiate"
            )
            raise BagError(
                f"{where}: topic {self.names['joint_states']}: joint(s) {', '.join(joints)} "
                f"carry {why}"
            )
        return pieces

    def _add(self, key: str, messages: MessageBatch) -> None:
        if key in self._sensor:
            stamps, values = decode_imu(messages, self.field)
            self._refuse_negative(key, stamps)
            self.decoded[key] = (stamps, values)
            self._note_lead(key, stamps, messages.log_times)
            keep = self._not_repeated(key, stamps, values)
            self._sensor[key].append((stamps[keep], values[keep]))
        elif key == "joint_states":
            stamps, position, velocity = decode_joint_states(
                messages, self.joint_names, self._joint_notes
            )
            self._refuse_negative(key, stamps)
            self._note_lead(key, stamps, messages.log_times)
            keep = self._not_repeated(key, stamps, position, velocity)
            stamps, position, velocity = stamps[keep], position[keep], velocity[keep]
            self._add_joint_rows(*self._split_joints.push(stamps, position, velocity))
        elif key == "denoised":
            self._denoised.append(decode_imu(messages, self.field))
        elif key == "commands":
            values = [decode_commands(r) for r in messages.to_list()]
            self._commands.append((messages.log_times.copy(), values))

    def _not_repeated(self, key: str, stamps: np.ndarray, *values: np.ndarray) -> np.ndarray:
        """(n,) False for a message that repeats the one before it on its topic exactly (stamp
        and numbers: a recorder that wrote it twice): read once, counted (`repeated`)."""
        row = np.concatenate([stamps[:, None].astype(np.float64), *values], axis=1)
        if len(row) == 0:
            return np.ones(0, bool)
        last = self._last_row.get(key)
        before = np.concatenate([row[:1] * np.nan if last is None else last[None, :], row[:-1]])
        same = np.all((row == before) | (np.isnan(row) & np.isnan(before)), axis=1)
        same &= stamps == np.concatenate([[stamps[0] if last is not None else -1], stamps[:-1]])
        if last is not None:
            same[0] &= int(stamps[0]) == self._last_stamp[key]
        self._last_row[key], self._last_stamp[key] = row[-1], int(stamps[-1])
        self.repeated[key] += int(np.count_nonzero(same))
        return ~same

    def _refuse_negative(self, key: str, stamps: np.ndarray) -> None:
        """Stamps before 1970 (core.stream.refuse_negative_stamps), named by bag and topic."""
        where = f"{self.reader.path}: topic {self.names[key]}: messages"
        refuse_negative_stamps(stamps, where, BagError)

    def _add_joint_rows(self, stamps, position, velocity) -> None:
        """Velocity where the driver gives none (core.velocity), then joints missing from a
        message filled with their last published values."""
        velocity = self.joint_velocity.push(stamps, position, velocity)
        self._velocity_usable += np.isfinite(velocity).sum(axis=0)
        self._joint_seen |= (~(np.isnan(position) & np.isnan(velocity))).any(axis=0)
        position, velocity, self._last_joint_values = hold_missing_joints(
            position, velocity, self._last_joint_values
        )
        self._joints.append((stamps, position, velocity))

    def _note_lead(self, key: str, stamps: np.ndarray, log_times: np.ndarray) -> None:
        lead = int((stamps - log_times).min())
        self._lead_ns[key] = min(lead, self._lead_ns.get(key, lead))

    def _stamp_frontier(self, key: str) -> int:
        """Stamps of `key` not read yet are at least this (from the log-time frontier; a
        stream with none read yet holds everything back, see `_release`)."""
        if self._frontier_ns is None:
            return np.iinfo(np.int64).max
        frontier = self._frontier_ns + self._lead_ns[key]
        held = self._split_joints.held_from_ns if key == "joint_states" else None
        return frontier if held is None else min(frontier, held)  # read, not yet in

    # --- output ------------------------------------------------------------------------
    def _refuse_valueless_joints(self) -> None:
        """Before any slice goes on: joints the messages name but never give a number (an
        effort-only JointState) are refused as such, not as joints the topic lacks."""
        named = self._joint_notes.get("named")
        if named is None:
            return
        valueless = [n for n, a, b in zip(self.joint_names, named, self._joint_seen) if a and not b]
        if valueless:
            raise BagError(
                f"{self.reader.path}: topic {self.names['joint_states']}: joint(s) "
                f"{', '.join(valueless)} named in its messages but never given a position or a "
                f"velocity (effort only?)"
            )

    def _align_ends(self, sensor: dict, *, final: bool) -> dict:
        """The sensor topic and its ground truth (contact, ego) cut to the stamps they share
        at the start (first release) and at the end (final): a recorder subscribes to, and
        stops, the topics at slightly different times. The samples left out are counted
        (`unmatched_ends`); a stamp missing in the middle is still refused (`_release`)."""
        if len(sensor) < 2:
            return sensor
        if not self._started and all(len(s) for s, _ in sensor.values()):
            first = max(int(s[0]) for s, _ in sensor.values())
            if not final and first >= min(self._stamp_frontier(k) for k in sensor):
                return sensor  # a stream's first samples may still be unread: `_release` waits
            for k, (s, x) in sensor.items():
                i = int(np.searchsorted(s, first))
                if i and s[i : i + 1].tolist() == [first]:
                    self.unmatched_ends[k] += i
                    sensor[k] = (s[i:], x[i:])
            self._started = True
        if final:
            n = min(len(s) for s, _ in sensor.values())
            raw = sensor["raw"][0]
            if all(np.array_equal(s[:n], raw[:n]) for s, _ in sensor.values()):
                for k, (s, x) in sensor.items():
                    self.unmatched_ends[k] += len(s) - n
                    sensor[k] = (s[:n], x[:n])
        return sensor

    def _release(self, *, final: bool) -> list[Recording]:
        if not final and any(k not in self._lead_ns for k in [*self._sensor_keys, "joint_states"]):
            # A stream with no message read yet may still hold any stamp: a converter that
            # wrote one topic after the other, logging its own clock, puts every joint state
            # after every sensor sample in log time. Nothing goes on (nor is re-copied).
            return []
        sensor = {
            k: _by_stamp(_concat([s for s, _ in v], None), _concat([x for _, x in v], 3))
            for k, v in self._sensor.items()
        }
        sensor = self._align_ends(sensor, final=final)
        if not final and not self._started and len(sensor) > 1:
            self._sensor = {k: [v] for k, v in sensor.items()}
            return []
        raw_stamps = sensor["raw"][0]
        n = min(len(s) for s, _ in sensor.values())
        if final:
            take = n
        else:
            # Everything unread is logged at or after the frontier: a sample stamped that far
            # before it (on each stream's clock) has its joint states and earlier samples in.
            frontier = min(self._stamp_frontier(k) for k in [*self._sensor_keys, "joint_states"])
            take = int(np.searchsorted(raw_stamps[:n], frontier - HORIZON_NS, side="left"))
            early = 0
            if n - take > self.max_pending and self._stuck >= 2:
                # Log times that do not advance: hold no more than max_lag_s of samples (not so
                # for a chunk holding much of one topic: the next chunk moves the frontier).
                early = n - self.max_pending - take
                take = n - self.max_pending
            span = int(raw_stamps[take - 1]) - int(raw_stamps[0]) if take else 0
            if span < self.min_slice_ns:
                self._sensor = {k: [v] for k, v in sensor.items()}
                return []
            self.released_early += early  # counted once, when they do go on
        self._refuse_valueless_joints()
        width = len(self.joint_names)
        js_stamps, js_position, js_velocity = _by_stamp(
            _concat([j[0] for j in self._joints], None),
            _concat([j[1] for j in self._joints], width).reshape(-1, width),
            _concat([j[2] for j in self._joints], width).reshape(-1, width),
        )
        # joint states past the frontier wait: earlier ones may still be unread
        cut = (
            len(js_stamps)
            if final or self._frontier_ns is None
            else max(
                int(np.searchsorted(js_stamps, self._stamp_frontier("joint_states"), side="left")),
                int(np.searchsorted(js_stamps, raw_stamps[take - 1] + HORIZON_NS, side="right"))
                if take
                else 0,
            )
        )
        self._joints = (
            [(js_stamps[cut:], js_position[cut:], js_velocity[cut:])]
            if cut < len(js_stamps)
            else []
        )
        js_stamps, js_position, js_velocity = js_stamps[:cut], js_position[:cut], js_velocity[:cut]
        piece = Recording(
            sensor_stamps_ns=raw_stamps[:take],
            sensor=sensor["raw"][1][:take],
            joint_stamps_ns=js_stamps,
            joint_position=js_position,
            joint_velocity=js_velocity,
            joint_names=self.joint_names,
        )
        for key in ("contact", "ego"):
            if key in sensor:
                stamps, values = sensor[key]
                if not np.array_equal(stamps[:take], raw_stamps[:take]) or (
                    final and len(stamps) != len(raw_stamps)
                ):
                    raise BagError(
                        f"{self.reader.path}: topic {self.names[key]} does not have the stamps of "
                        f"{self.names['raw']}"
                    )
                setattr(piece, key, values[:take])
        self._sensor = {k: [(s[take:], x[take:])] for k, (s, x) in sensor.items()}
        if self._denoised:
            piece.denoised_stamps_ns = _concat([d[0] for d in self._denoised], None)
            piece.denoised = _concat([d[1] for d in self._denoised], 3)
            self._denoised = []
        if self._commands:
            values = [v for c in self._commands for v in c[1]]
            width_c = max(len(v) for v in values)
            piece.command_stamps_ns = np.concatenate([c[0] for c in self._commands])
            piece.commands = np.array(
                [np.pad(v, (0, width_c - len(v)), constant_values=np.nan) for v in values]
            )
            self._commands = []
        self._flat.see(piece.sensor)
        return [piece]


def iter_recording(
    path: str | os.PathLike,
    *,
    profile: RobotProfile | None = None,
    progress: Callable[[int], None] | None = None,
    **options,
) -> Iterator[Recording]:
    """Consecutive aligned time slices of a bag (see the module doc), in memory bounded by
    the slice length; `options`: RecordingStream's (ground_truth, denoised, commands: the
    optional topics read when present). `progress(bytes)` is called as the bag is read."""
    with BagReader(path) as reader:
        stream = RecordingStream(reader, profile, **options)
        for batch in reader.batches(stream.topics):
            yield from stream.add(batch)
            if progress is not None:
                progress(batch.bytes_read)
        yield from stream.finish()


class _FlatWatch:
    """Whether every finite sensor sample seen equals the first (`flat`, from two on)."""

    def __init__(self):
        self.first: np.ndarray | None = None
        self.samples = 0
        self.varies = False

    def see(self, sensor: np.ndarray) -> None:
        if self.varies or not len(sensor):
            return
        finite = sensor[np.all(np.isfinite(sensor), axis=1)]
        if len(finite):
            self.first = finite[0] if self.first is None else self.first
            self.samples += len(finite)
            self.varies = bool(np.any(finite != self.first))

    @property
    def flat(self) -> bool:
        return self.samples > 1 and not self.varies


def concat_recordings(pieces: Sequence[Recording]) -> Recording:
    """Join consecutive slices (as from `iter_recording`) into one Recording."""
    first = pieces[0]
    values = {}
    for f in fields(Recording):
        if f.name == "joint_names":
            continue
        parts = [getattr(p, f.name) for p in pieces if getattr(p, f.name) is not None]
        if not parts:
            values[f.name] = None
        elif len(parts) == 1:
            values[f.name] = parts[0]
        else:
            width = [p.shape[1] for p in parts if p.ndim == 2]
            if width and len(set(width)) > 1:  # commands of different lengths
                w = max(width)
                parts = [
                    np.pad(p, ((0, 0), (0, w - p.shape[1])), constant_values=np.nan) for p in parts
                ]
            values[f.name] = np.concatenate(parts)
    return Recording(joint_names=first.joint_names, **values)


def read_recording(
    path: str | os.PathLike, *, profile: RobotProfile | None = None, **options
) -> Recording:
    """A whole bag as one Recording (`iter_recording`'s slices joined), each stream sorted
    by stamp (a bag's file order is receive order). BagError names the bag and problem."""
    return _sorted(concat_recordings(list(iter_recording(path, profile=profile, **options))))


def _sorted(rec: Recording) -> Recording:
    truth = [key for key in ("contact", "ego") if getattr(rec, key) is not None]
    rec.sensor_stamps_ns, rec.sensor, *values = _by_stamp(
        rec.sensor_stamps_ns, rec.sensor, *(getattr(rec, key) for key in truth)
    )
    for key, value in zip(truth, values):
        setattr(rec, key, value)
    rec.joint_stamps_ns, rec.joint_position, rec.joint_velocity = _by_stamp(
        rec.joint_stamps_ns, rec.joint_position, rec.joint_velocity
    )
    if rec.denoised_stamps_ns is not None:
        rec.denoised_stamps_ns, rec.denoised = _by_stamp(rec.denoised_stamps_ns, rec.denoised)
    return rec


# --- writing ------------------------------------------------------------------------------
def write_recording(path: str | os.PathLike, rec: Recording, **options) -> None:
    """Write a Recording as a rosbag2 bag: one message per sample, log time = stamp."""
    write_recordings(path, [rec], **options)


def write_recordings(
    path: str | os.PathLike,
    pieces: Iterable[Recording],
    *,
    profile: RobotProfile | None = None,
    storage: str = "mcap",
    compress: bool | str = False,
    window_s: float = 1.0,
    chunk_bytes: int = 4 << 20,
    crc: bool = True,
    frame_id: str = "",
) -> None:
    """Write consecutive time slices of a recording into one bag, in constant memory; Imu
    messages carry `frame_id` (the sensor's frame). Each slice is cut into `window_s`
    windows whose messages go into the bag together (grouped by topic): chunks follow time."""
    profile = profile or _default_profile()
    names = bag_topic_names(profile)
    with BagWriter(
        path, storage=storage, compress=compress, chunk_bytes=chunk_bytes, crc=crc
    ) as bag:
        for rec in pieces:
            streams = recording_streams(rec, names, profile.sensor_field, frame_id)
            for topic, msgtype, _, _ in streams:
                bag.add_topic(topic, msgtype)
            start = min(int(s[0]) for _, _, s, _ in streams if len(s))
            stop = max(int(s[-1]) for _, _, s, _ in streams if len(s)) + 1
            step = max(1, int(window_s * NS_PER_S))
            for t0 in range(start, stop, step):
                for topic, _, stamps, encode in streams:
                    a, b = np.searchsorted(stamps, [t0, t0 + step])
                    if b > a:
                        bag.write_batch(topic, stamps[a:b], encode(a, b))


def recording_streams(rec: Recording, names: dict, field_: str, frame_id: str = "") -> list:
    """(topic, type, stamps, encode(a, b)) per topic present in the recording: stamps in
    order (a slice's normally are), encode(a, b) the messages of stamps[a:b]."""
    n = len(rec.sensor_stamps_ns)
    streams = []

    def add(topic: str, msgtype: str, stamps, encode_rows) -> None:
        stamps = np.asarray(stamps, np.int64)
        order = None
        if len(stamps) > 1 and np.any(np.diff(stamps) < 0):
            order = np.argsort(stamps, kind="stable")

        def encode(a: int, b: int) -> list[bytes]:
            return encode_rows(slice(a, b) if order is None else order[a:b])

        streams.append((topic, msgtype, stamps if order is None else stamps[order], encode))

    def add_imu(key: str, stamps, values) -> None:
        stamps = np.asarray(stamps, np.int64)
        add(
            names[key],
            IMU_TYPE,
            stamps,
            lambda r: encode_imu_batch(stamps[r], values[r], frame_id, field_),
        )

    add_imu("raw", rec.sensor_stamps_ns, rec.sensor)
    for key in ("contact", "ego"):
        values = getattr(rec, key)
        if values is not None:
            if len(values) != n:
                raise BagError(f"recording: {key} has {len(values)} samples, accel has {n}")
            add_imu(key, rec.sensor_stamps_ns, values)
    if rec.denoised is not None:
        add_imu("denoised", rec.denoised_stamps_ns, rec.denoised)
    js = np.asarray(rec.joint_stamps_ns, np.int64)
    add(
        names["joint_states"],
        JOINT_STATE_TYPE,
        js,
        lambda r: encode_joint_state_batch(
            js[r], rec.joint_position[r], rec.joint_velocity[r], rec.joint_names
        ),
    )
    if rec.commands is not None and len(rec.commands):
        add(
            names["commands"],
            COMMANDS_TYPE,
            rec.command_stamps_ns,
            lambda r: [encode_commands(c) for c in rec.commands[r]],
        )
    return streams


def duration_of(path: str | os.PathLike, profile: RobotProfile | None = None) -> float:
    """Seconds of recording a bag holds: its sensor topic's message count at the profile's
    rate when listed (a pause does not count), else the time spanned (metadata.yaml)."""
    with BagReader(path) as reader:
        span = float((reader.info.get("duration") or {}).get("nanoseconds", 0)) / NS_PER_S
        if profile is None:
            return span
        topic = reader.topics.get(profile.sensor_topic)
        count = topic.count if topic is not None else 0
        return min(span, count / profile.rate_hz) if count else span
