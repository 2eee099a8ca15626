"""From a sensor sample stream to band-passed samples, each with its joint velocity.

The per-sample counterpart of `stream.BlockFramer` (for harmonic cancellation and the
low-latency gain): the same input cleaning, band-pass and joint-state rule. A sample's
velocity is the latest joint state at or before it if at most `max_hold_s` old, else NaN
(passed through band-passed, counted). It is released once no joint state can still come
that changes this: one stamped at or after it is in, or it lies less than the joint
stream's spacing after the latest (`_thinned`), or `joint_wait_s` of sensor time later.
Any chunking pushed as `feed` pushes releases the same samples with the same velocities as
one push.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from egovib_ros.core.stream import FramerSettings, _Framer, joint_state_arrays
from egovib_ros.core.timebase import NS_PER_S

#: The joint stream's spacing G: this share of the smallest of its first JOINT_SPACING_LEARN
#: intervals, at most JOINT_SPACING_MAX_S (`SampleFramer._thinned`).
JOINT_SPACING_SHARE = 0.5
JOINT_SPACING_LEARN = 8
JOINT_SPACING_MAX_S = 0.005


@dataclass
class SampleBatch:
    """Samples released together, in order, all from one segment."""

    stamps_ns: np.ndarray  # (n,) input stamp; -1 for a synthetic (gap-fill) sample
    values: np.ndarray  # (n, 3) band-passed x, y, z
    velocity: np.ndarray  # (n, J) held joint velocity, NaN where there is none
    ends_segment: bool = False  # the last samples before a long gap, a clock jump or the end
    raw: np.ndarray | None = None  # (n, 3) the samples unfiltered (FramerSettings.keep_raw)

    def __len__(self) -> int:
        return len(self.stamps_ns)


class SampleFramer(_Framer):
    """Streaming: push joint states and sensor chunks in any sizes, `pop()` the released
    samples as SampleBatch objects."""

    def __init__(self, settings: FramerSettings, n_joints: int):
        if settings.layout != "per_axis":
            settings = dataclasses.replace(settings, layout="per_axis")
        super().__init__(settings, n_joints, 3)
        # Pending samples of the open segment: stamp, effective time (synthetic samples get
        # the time they stand for), band-passed values.
        self._pend_t = np.zeros(0, dtype=np.int64)
        self._pend_time = np.zeros(0, dtype=np.int64)
        # band-passed x, y, z (and with keep_raw the same unfiltered)
        self._pend_x = np.zeros((0, 6 if settings.keep_raw else 3))
        self._closed: list[list] = []  # [stamps, times, values, wait_for_joints] of ended segments
        self._ready: list[SampleBatch] = []
        self._last_time: int | None = None  # effective time of the last real sample appended
        self._segment_open = False  # samples appended since the segment started
        self.samples_no_joint_state = 0
        # the joint stream's spacing (ns; None until learnt) and what it is learnt from
        self._spacing_ns: int | None = None
        self._intervals: list[int] = []
        self._spacing_last: int | None = None  # the last joint stamp passed on
        self.joint_states_thinned = 0

    # --- input ---------------------------------------------------------------
    def push_joint_states(
        self, stamps_ns: np.ndarray, velocity: np.ndarray, *, release: bool = True
    ) -> None:
        stamps_ns, velocity = joint_state_arrays(stamps_ns, velocity, self.n_joints, self.s.error)
        if self._joint_lag_ns:
            stamps_ns = stamps_ns + self._joint_lag_ns
        stamps_ns, velocity = self._thinned(stamps_ns, velocity)
        if len(stamps_ns) and self._append_in_order(stamps_ns, velocity):  # the live case
            self.stats.joint_states_in += len(stamps_ns)
            if release:
                self._drain()
            return
        self._push_joint_states(stamps_ns, velocity)

    def _thinned(self, stamps_ns: np.ndarray, velocity: np.ndarray):
        """The joint states less those stamped less than the stream's spacing G after the
        last one passed on. Once no passed joint state is closer than G to the one before,
        a sample less than G after the latest is released at once (`_releasable`): none can
        come before it any more. Without it a sample waits for the next joint state, up to
        a joint-state period (10 ms at 100 Hz). G is learnt from the first intervals (a stream
        that starts in bursts gets a tiny G: little thinned, samples wait as before). On stamps
        alone, so any chunking thins the same joint states; later and earlier ones (out of
        order, a restarted clock) pass, for the framer to drop or restart on."""
        if self._spacing_ns is None:
            learnt = self._learn_spacing(stamps_ns)
            if learnt == len(stamps_ns):
                return stamps_ns, velocity
            rest, rest_velocity = self._thinned(stamps_ns[learnt:], velocity[learnt:])
            return (
                np.concatenate([stamps_ns[:learnt], rest]),
                np.concatenate([velocity[:learnt], rest_velocity]),
            )
        spacing, last = max(self._spacing_ns, 1), self._spacing_last
        if (  # the usual batch: nothing to thin
            len(stamps_ns)
            and last is not None
            and stamps_ns[0] - last >= spacing
            and (len(stamps_ns) == 1 or (stamps_ns[1:] - stamps_ns[:-1]).min() >= spacing)
        ):
            self._spacing_last = int(stamps_ns[-1])
            return stamps_ns, velocity
        keep = np.ones(len(stamps_ns), bool)
        for i, stamp in enumerate(stamps_ns.tolist()):
            if not self._passes(stamp):
                continue
            if self._spacing_last is not None and stamp - self._spacing_last < self._spacing_ns:
                keep[i] = False
                continue
            self._spacing_last = stamp
        if keep.all():
            return stamps_ns, velocity
        self.joint_states_thinned += int(np.count_nonzero(~keep))
        return stamps_ns[keep], velocity[keep]

    def _passes(self, stamp: int) -> bool:
        """Whether a joint stamp is later than the last one passed on (a restarted clock
        forgets that one); an earlier or equal one is the framer's to drop."""
        last = self._spacing_last
        if last is not None and stamp < last - int(self.s.clock_jump_s * NS_PER_S):
            self._spacing_last = last = None
        return last is None or stamp > last

    def _learn_spacing(self, stamps_ns: np.ndarray) -> int:
        """Learn the spacing from the first intervals; how many joint states that took."""
        for i, stamp in enumerate(stamps_ns.tolist()):
            if not self._passes(stamp):
                continue
            if self._spacing_last is not None:
                self._intervals.append(stamp - self._spacing_last)
            self._spacing_last = stamp
            if len(self._intervals) == JOINT_SPACING_LEARN:
                self._spacing_ns = min(
                    int(JOINT_SPACING_SHARE * min(self._intervals)),
                    int(JOINT_SPACING_MAX_S * NS_PER_S),
                )
                return i + 1
        return len(stamps_ns)

    def _push_joint_states(self, stamps_ns: np.ndarray, velocity: np.ndarray) -> None:
        self.stats.joint_states_in += len(stamps_ns)
        if len(stamps_ns) == 0:
            return
        last = int(self._joint_t[-1]) if len(self._joint_t) else None
        jump_ns = int(self.s.clock_jump_s * NS_PER_S)
        if last is not None and int(stamps_ns.min()) < last - jump_ns:
            # The joint clock went back: finish what waits on the old clock, then forget it.
            i = int(np.argmax(stamps_ns < last - jump_ns))
            self.stats.joint_states_in -= len(stamps_ns)
            self._push_joint_states(stamps_ns[:i], velocity[:i])
            self._close_segment(wait_for_joints=False)
            self._drain()
            self._joint_t, self._joint_v = self._joint_t[:0], self._joint_v[:0]
            self.stats.joint_states_in += len(stamps_ns) - i
            self._push_joint_states(stamps_ns[i:], velocity[i:])
            self.stats.joint_states_in -= len(stamps_ns) - i  # counted once, above
            return
        before = np.maximum.accumulate(
            np.concatenate([[last if last is not None else np.iinfo(np.int64).min], stamps_ns[:-1]])
        )
        self._keep_joint_states(stamps_ns, velocity, stamps_ns > before)
        self._drain()

    def flush(self) -> None:
        """End of stream: release everything pending (the last segment ends here)."""
        self._push_segments(self._cleaner.finish())
        self._close_segment(wait_for_joints=False)
        self._drain(final=True)

    def pop(self) -> list[SampleBatch]:
        ready, self._ready = self._ready, []
        return ready

    @property
    def backlog(self) -> tuple[int, int]:
        return len(self._pend_t) + self._cleaner.waiting, len(self._joint_t)

    # --- internals -------------------------------------------------------------
    def _append(self, stamps: np.ndarray, values: np.ndarray) -> None:
        if len(stamps) == 0:
            return
        filtered = self._bandpass.process(np.array(values, dtype=np.float64).T).T
        if self.s.keep_raw:
            filtered = np.concatenate([filtered, values], axis=1)
        # Effective times: a synthetic sample stands one period after the one before it.
        times = stamps.copy()
        if stamps.min() < 0:
            synthetic = np.flatnonzero(stamps < 0)
            period = int(round(self.s.period_ns))
            for i in synthetic:
                previous = times[i - 1] if i > 0 else self._last_time
                times[i] = (previous if previous is not None else 0) + period
        self._last_time = int(times[-1])
        self._segment_open = True
        self._pend_t = np.concatenate([self._pend_t, stamps])
        self._pend_time = np.concatenate([self._pend_time, times])
        self._pend_x = np.concatenate([self._pend_x, filtered])

    def _close_segment(self, *, wait_for_joints: bool) -> None:
        # Even when every sample of the segment is out already, its end is passed on (the
        # methods flush what they hold back, e.g. a look-ahead).
        if len(self._pend_t) or self._segment_open:
            self._closed.append([self._pend_t, self._pend_time, self._pend_x, wait_for_joints])
        self._segment_open = False
        self._pend_t = self._pend_t[:0]
        self._pend_time = self._pend_time[:0]
        self._pend_x = self._pend_x[:0]
        self._last_time = None
        self._bandpass.reset()

    def _drain(self, *, final: bool = False) -> None:
        while self._closed:
            stamps, times, values, wait = self._closed[0]
            n = self._releasable(times, wait=wait and not final)
            if n or not len(stamps):
                self._emit(stamps[:n], times[:n], values[:n], ends=n == len(stamps))
            if n < len(stamps):
                self._closed[0][:3] = stamps[n:], times[n:], values[n:]
                return
            self._closed.pop(0)
        if final or not len(self._pend_t):
            return
        n = self._releasable(self._pend_time, wait=True)
        if n:
            self._emit(self._pend_t[:n], self._pend_time[:n], self._pend_x[:n], ends=False)
            self._pend_t, self._pend_time, self._pend_x = (
                self._pend_t[n:],
                self._pend_time[n:],
                self._pend_x[n:],
            )

    def _releasable(self, times: np.ndarray, *, wait: bool) -> int:
        """How many leading samples may be released (strictly in order)."""
        if not wait or not len(times):
            return len(times)
        latest_joint = int(self._joint_t[-1]) if len(self._joint_t) else None
        newest = self._cleaner.last_stamp
        limit = newest - self._joint_wait_ns if newest is not None else None
        n = 0
        if latest_joint is not None and self._spacing_ns:  # before the next can come
            n = int(np.searchsorted(times, latest_joint + self._spacing_ns, side="left"))
        elif latest_joint is not None:
            n = int(np.searchsorted(times, latest_joint, side="right"))
        if limit is not None:
            n = max(n, int(np.searchsorted(times, limit, side="right")))
        return n

    def _emit(self, stamps, times, values, *, ends: bool) -> None:
        index = np.searchsorted(self._joint_t, times, side="right") - 1
        have = index >= 0
        # a joint state at or before each sample, held no longer than max_hold
        fresh = have
        if have.any():
            fresh = have.copy()
            fresh[have] = (times[have] - self._joint_t[index[have]]) <= self._max_hold_ns
        if fresh.all():  # the live case: every sample has its joint state
            velocity = self._joint_v[index]
        else:
            velocity = np.full((len(times), self.n_joints), np.nan)
            velocity[fresh] = self._joint_v[index[fresh]]
            self.samples_no_joint_state += int(np.count_nonzero(~fresh & (stamps >= 0)))
        raw = values[:, 3:] if self.s.keep_raw else None
        self._ready.append(SampleBatch(stamps, values[:, :3], velocity, ends, raw))
        if not len(times):
            return
        # Keep the joint state that holds for the next sample and anything after it.
        cut = int(index[-1])
        if cut > 256:
            self._joint_t = self._joint_t[cut:]
            self._joint_v = self._joint_v[cut:]
