"""Per-block observations and covariates for the gap diagnosis (numpy/scipy only).

Each 64-sample block (the core's framing: band-passed sum of axes, the model's window,
hop 32) gives the observed magnitude spectrum |Y_b(f)| over the in-band bins, the
model's expected magnitude mu(f, v_b) at the block's mean joint velocity, and the
covariates an unmodelled effect could depend on: joint positions, joint accelerations,
elapsed time.  The stream lag is not a per-block covariate: `BlockTable.at_lag`
re-matches the joint states shifted by a candidate lag.
Contact blocks are found from the data alone (energy outliers against the model);
ground-truth topics are never read.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage, signal

from egovib_ros.bag import iter_recording
from egovib_ros.bag.recording import duration_of
from egovib_ros.core.stream import BlockFramer, FramerSettings, check_stream
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.core.velocity import MISSING
from egovib_ros.errors import BagError, ModelFileError

#: A block counts as contact if its top-3-bin log ratio to the model exceeds the local
#: typical level by this many robust standard deviations.
CONTACT_Z = 3.5
#: Blocks after a flagged block also dropped (tap tails ring for 10-30 ms + filter decay).
CONTACT_DILATE = 5
#: Savitzky-Golay window for joint accelerations (s): long enough to average encoder
#: quantisation, short compared with the motion.
ACCEL_SMOOTH_S = 0.031
#: The joint-state period is the median of the first this many intervals.
PERIOD_INTERVALS = 1000
#: A thinned table keeps the joint states within this time of a kept block (by default):
#: the lags the diagnosis tries (effects.LAG_RANGE_S, refined by a coarse step, and a
#: reference lag of a few ms) stay inside it.
JOINT_MARGIN_S = 0.25


@dataclass
class JointSeries:
    """Joint-state streams on their own clock (seconds since the first accel sample)."""

    t_s: np.ndarray  # (M,)
    position: np.ndarray  # (M, J)
    velocity: np.ndarray  # (M, J)
    acceleration: np.ndarray  # (M, J) smoothed derivative of velocity
    smooth_velocity: np.ndarray | None = None  # (M, J) Savitzky-Golay smoothed velocity
    reversals: tuple[np.ndarray, ...] = ()  # per joint: joint-clock times (s) where motion
    # resumes opposite to the last direction
    #: Largest lag the series can be re-matched at: a thinned series holds the joint states
    #: only within this margin of the kept blocks.
    max_lag_s: float = np.inf


@dataclass
class BlockTable:
    """Everything the diagnosis needs about the blocks of one recording."""

    t_first_s: np.ndarray  # (B,) block start, s since the first accel sample
    t_last_s: np.ndarray  # (B,)
    magnitude: np.ndarray  # (B, F) observed |Y_b(f)|, in-band bins
    freqs_hz: np.ndarray  # (F,)
    velocity: np.ndarray  # (B, J) block mean joint velocity (lag 0)
    position: np.ndarray  # (B, J)
    acceleration: np.ndarray  # (B, J) block mean |joint acceleration|
    base_mean: np.ndarray  # (B, F) model mean magnitude at the block velocity
    base_std: np.ndarray  # (B, F) model std (for the denoising consequence)
    contact: np.ndarray  # (B,) bool, detected contact (excluded)
    vmax: np.ndarray  # (J,) largest grid speed per joint
    joint_names: tuple[str, ...]
    model: object = field(repr=False, default=None)
    joints: JointSeries | None = field(repr=False, default=None)

    @property
    def n_blocks(self) -> int:
        return len(self.t_first_s)

    @property
    def t_mid_s(self) -> np.ndarray:
        return 0.5 * (self.t_first_s + self.t_last_s)

    def at_lag(self, lag_s: float) -> "BlockTable":
        """The table with joint states re-matched as if their stamps were `lag_s` late.

        Joint time is corrected to stamp - lag_s, i.e. a positive lag means the joint
        states are stamped later than the vibration they describe.
        """
        if self.joints is None or self.model is None:
            raise ValueError("table has no joint series to re-match")
        velocity, position, acceleration = _joint_block_means(
            self.joints, self.t_first_s, self.t_last_s, lag_s
        )
        mean, std = _model_lookup(self.model, velocity, self.freq_index)
        return _attach_trajectory(
            replace(
                self,
                velocity=velocity,
                position=position,
                acceleration=acceleration,
                base_mean=mean,
                base_std=std,
                lag_s=float(lag_s),
            )
        )

    freq_index: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, dtype=np.intp))
    #: Velocity knots per joint (the model's grid): the baseline's cells.
    knots: tuple[np.ndarray, ...] = field(repr=False, default=())
    #: (B, J, K) window-weighted mean over each block of the hat functions of the joint's
    #: velocity trajectory at the knots: what a velocity-only table predicts, linearly.
    hats: np.ndarray | None = field(repr=False, default=None)
    #: (B, J) time since the last reversal
    reversal_after_s: np.ndarray | None = field(repr=False, default=None)
    #: (B, J) time until the next reversal
    reversal_before_s: np.ndarray | None = field(repr=False, default=None)
    lag_s: float = 0.0  # joint-state lag of this table
    #: (B, J) block mean rate of change of the joint's *speed* (d|v|/dt, joint unit/s^2):
    #: positive while it speeds up, negative while it slows down
    speed_rate: np.ndarray | None = field(repr=False, default=None)
    #: (B, J) block mean |d acceleration/dt| (joint unit/s^3): where a speed change starts
    #: or ends (a gear's backlash knocked, a housing mode rung)
    jerk: np.ndarray | None = field(repr=False, default=None)
    #: counts of bad input treated as missing (framer stats, joint states dropped)
    bad_input: dict = field(repr=False, default_factory=dict)
    #: (B,) on a table joining two recordings (`join_tables`): 0 = the reference's blocks,
    #: 1 = the recording diagnosed; None on one recording's table
    recording: np.ndarray | None = field(repr=False, default=None)


#: The baseline's velocity cells: the model's grid with each interval split in this many
#: (tonal lines sweep a DFT bin within a fraction of a 10 % grid step).
KNOT_REFINE = 6
KNOT_REFINE_LOW = 10
LOW_SPEED_FRACTION = 0.2
#: Points per block at which the velocity trajectory is sampled for the baseline's features.
TRAJECTORY_POINTS = 16
#: A joint is moving in one direction once |smoothed velocity| exceeds this share of its top speed.
REVERSAL_THRESHOLD = 0.03


def hat_basis(values: np.ndarray, knots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Piecewise-linear interpolation weights: (left knot index, left weight, right weight)."""
    v = np.clip(values, knots[0], knots[-1])
    i = np.clip(np.searchsorted(knots, v, side="right") - 1, 0, len(knots) - 2)
    frac = (v - knots[i]) / (knots[i + 1] - knots[i])
    return i, 1.0 - frac, frac


def hat_matrix(values: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """(n, K) piecewise-linear basis over `knots` (values clipped to the knot range)."""
    i, wl, wr = hat_basis(values, knots)
    out = np.zeros((len(values), len(knots)))
    rows = np.arange(len(values))
    out[rows, i] += wl
    out[rows, i + 1] += wr
    return out


def motion_features(
    joints: JointSeries,
    t_first: np.ndarray,
    t_last: np.ndarray,
    lag_s: float,
    knots: tuple[np.ndarray, ...],
    window: np.ndarray,
):
    """Velocity-trajectory hat features (B, J, K) and times since / until the nearest
    reversal (B, J).

    Each block's features are the analysis-window^2-weighted mean, over TRAJECTORY_POINTS
    instants inside the block, of the hat functions of the (smoothed) joint velocity: a
    velocity table interpolated linearly between its cells and averaged over the block's
    own velocity trajectory (a block straddling a reversal sees both directions' speeds,
    not their mean, which is near zero).
    """
    check_lag(joints, lag_s)
    n_blocks, n_joints = len(t_first), len(knots)
    pts = np.linspace(0.0, 1.0, TRAJECTORY_POINTS)
    idx = np.clip(np.round(pts * (len(window) - 1)).astype(int), 0, len(window) - 1)
    weight = window[idx] ** 2
    weight = weight / weight.sum()
    times = t_first[:, None] + pts[None, :] * (t_last - t_first)[:, None]  # (B, Q)
    t_joint = joints.t_s - lag_s
    vel = joints.smooth_velocity if joints.smooth_velocity is not None else joints.velocity
    n_knots = max(len(k) for k in knots)
    hats = np.zeros((n_blocks, n_joints, n_knots))
    cell = np.repeat(np.arange(n_blocks), TRAJECTORY_POINTS) * n_knots  # flat (block, knot)
    w = np.tile(weight, n_blocks)
    for j in range(n_joints):
        v = np.interp(times.ravel(), t_joint, vel[:, j])
        i, wl, wr = hat_basis(v, knots[j])
        # np.bincount, not np.add.at: the same sums in the same order, several times faster
        # (the lag scan calls this ~120 times)
        flat = np.bincount(
            np.concatenate([cell + i, cell + i + 1]),
            np.concatenate([w * wl, w * wr]),
            minlength=n_blocks * n_knots,
        )
        hats[:, j] = flat.reshape(n_blocks, n_knots)
    t_mid = 0.5 * (t_first + t_last)
    after = np.full((n_blocks, n_joints), np.inf)
    before = np.full((n_blocks, n_joints), np.inf)
    for j, events in enumerate(joints.reversals):
        if len(events) == 0:
            continue
        ev = np.sort(events) - lag_s
        k = np.searchsorted(ev, t_mid, side="right")
        has_prev = k > 0
        after[has_prev, j] = t_mid[has_prev] - ev[k[has_prev] - 1]
        has_next = k < len(ev)
        before[has_next, j] = ev[k[has_next]] - t_mid[has_next]
    return hats, after, before


#: A bag longer than the block budget is thinned in runs of this many consecutive blocks
#: (~0.7 s at 3 kHz): a run holds 8 metric windows and about one 0.5 s test segment.
THIN_RUN_BLOCKS = 64
#: Default budget of `egovib gap`: the diagnosis's memory and time grow with the blocks it
#: fits (~80 MB per minute of 3 kHz recording), not with the bag beyond this. Two minutes:
#: the bag length `egovib gap validate` measures the diagnosis on.
DEFAULT_BUDGET_MINUTES = 2.0


class BlockSpectra:
    """The core's own framing (a BlockFramer, as calibration uses: band-passed sum of axes,
    the model's window and sensor range) fed as a stream: push joint states, then sensor
    samples, slice by slice; `finish()` gives the in-band magnitude spectra of the complete
    blocks that have a joint state. The framer is the only state, so any slicing of the
    same arrays gives the same blocks (tested); a bag is never held whole."""

    def __init__(self, model, n_joints: int, *, keep: float = 1.0):
        """`keep` < 1: keep that share of the runs of THIN_RUN_BLOCKS consecutive blocks,
        spread evenly (a long bag thinned over its whole length, see `table_from_bag`)."""

        # the model's framing, including its sensor range: bad samples are missing
        settings = FramerSettings.for_model(model, layout="combined", max_hold_s=0.05)
        self._framer = BlockFramer(settings, n_joints)
        self._window = model.window
        self._bins = in_band_bins(model)
        self._n_joints = n_joints
        self._parts: list[tuple[np.ndarray, ...]] = []
        self._keep = float(keep)
        self._blocks_seen = 0
        self.samples = 0
        self.first_stamp_ns: int | None = None
        #: Kept blocks as merged time spans (ns; blocks closer than 2 JOINT_MARGIN_S
        #: joined) and the last stamp of the latest block framed: a joint state older than
        #: that minus the margin can no longer come near a block still to come.
        self.span_starts: list[int] = []
        self.span_ends: list[int] = []
        self.framed_until_ns: int | None = None

    @property
    def stats(self):
        """The framer's counts (core.stream.FramerStats)."""
        return self._framer.stats

    def push_joint_states(self, stamps_ns: np.ndarray, velocity: np.ndarray) -> None:
        self._framer.push_joint_states(stamps_ns, velocity)
        self._collect()

    def push_sensor(self, stamps_ns: np.ndarray, accel: np.ndarray) -> None:
        if len(stamps_ns) and self.first_stamp_ns is None:
            self.first_stamp_ns = int(stamps_ns[0])
        self.samples += len(stamps_ns)
        self._framer.push_sensor(stamps_ns, accel)
        self._collect()

    def _collect(self) -> None:
        for b in self._framer.pop_blocks():
            if not b.n:
                continue
            ok = (b.complete if b.complete is not None else np.ones(b.n, bool)) & (
                b.status != MISSING
            )
            if self._keep < 1.0:  # run r is kept when floor(r * keep) steps up
                run = (self._blocks_seen + np.arange(b.n)) // THIN_RUN_BLOCKS
                ok &= np.floor((run + 1) * self._keep) > np.floor(run * self._keep)
            self._blocks_seen += b.n
            self.framed_until_ns = int(b.t_last_ns.max())
            if ok.any():
                if self.thinned:
                    self._extend_spans(b.t_first_ns[ok], b.t_last_ns[ok])
                spectra = np.abs(np.fft.rfft(b.samples[ok, 0, :] * self._window, axis=1))
                self._parts.append(
                    (spectra[:, self._bins], b.t_first_ns[ok], b.t_last_ns[ok], b.velocity[ok])
                )

    def _extend_spans(self, t_first: np.ndarray, t_last: np.ndarray) -> None:
        join = 2 * int(JOINT_MARGIN_S * NS_PER_S)
        for start, end in zip(t_first.tolist(), t_last.tolist()):
            if self.span_ends and start <= self.span_ends[-1] + join:
                self.span_ends[-1] = max(self.span_ends[-1], end)
            else:
                self.span_starts.append(start)
                self.span_ends.append(end)

    @property
    def thinned(self) -> bool:
        return self._keep < 1.0

    def near_kept(self, stamps_ns: np.ndarray, margin_ns: int) -> np.ndarray:
        """Which stamps lie within `margin_ns` of a kept block framed so far."""
        if not self.span_starts:
            return np.zeros(len(stamps_ns), dtype=bool)
        starts = np.asarray(self.span_starts, dtype=np.int64) - margin_ns
        ends = np.asarray(self.span_ends, dtype=np.int64) + margin_ns
        i = np.searchsorted(starts, stamps_ns, side="right") - 1
        return (i >= 0) & (stamps_ns <= ends[np.maximum(i, 0)])

    def finish(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Flush; (in-band magnitudes (B, F), t_first_ns (B,), t_last_ns (B,), block mean
        velocity (B, J))."""
        self._framer.flush()
        self._collect()
        if not self._parts:
            return (
                np.zeros((0, len(self._bins))),
                np.zeros(0, np.int64),
                np.zeros(0, np.int64),
                np.zeros((0, self._n_joints)),
            )
        return tuple(np.concatenate(column) for column in zip(*self._parts))


class JointScreen:
    """Usable joint states, slice by slice: finite position and velocity, stamped after
    every earlier usable one (a stuck or jumping clock); the rest are missing data,
    counted. The covariates then see exactly the joint states the framer uses."""

    def __init__(self):
        self.last_ns = None
        self.seen = 0
        self.bad = 0
        self.duplicates = 0  # of the bad, exact repeats of the usable one before (recorded twice)
        self._last_row = None

    def __call__(self, stamps_ns: np.ndarray, position: np.ndarray, velocity: np.ndarray):
        finite = np.all(np.isfinite(velocity), axis=1) & np.all(np.isfinite(position), axis=1)
        good = np.zeros(len(stamps_ns), dtype=bool)
        last, row = self.last_ns, self._last_row
        for i in np.flatnonzero(finite):  # joint rate: a Python loop is cheap here
            if last is None or stamps_ns[i] > last:
                good[i], last, row = True, int(stamps_ns[i]), (position[i], velocity[i])
            elif stamps_ns[i] == last and all(
                np.array_equal(a, b[i]) for a, b in zip(row, (position, velocity))
            ):
                self.duplicates += 1
        self.last_ns, self._last_row = last, row
        self.seen += len(good)
        self.bad += int((~good).sum())
        return good


class JointFeatures:
    """The joint series and its motion covariates, slice by slice: position unwrapped,
    velocity smoothed and differentiated (a quadratic Savitzky-Golay filter over
    ACCEL_SMOOTH_S), the reversal times.

    The state is explicit (the filter's unfinished tail, the unwrapping's running
    correction, each joint's last direction of motion), so any slicing gives the result
    of one slice (tested). With `blocks` (a BlockSpectra thinning a long bag), only the
    joint states within `margin_s` of a kept block are held, so the series grows
    with the block budget, not with the bag; the reversal times (a few per second at
    most) are kept for the whole bag."""

    def __init__(
        self,
        vmax: np.ndarray,
        *,
        blocks: BlockSpectra | None = None,
        margin_s: float = JOINT_MARGIN_S,
    ):
        self._vmax = np.asarray(vmax, dtype=float)
        self._blocks = blocks if blocks is not None and blocks.thinned else None
        self._margin_s = float(margin_s)
        self._margin_ns = int(margin_s * NS_PER_S)
        self.count = 0  # joint states pushed
        self._period_s: float | None = None
        self._window = 0
        # filter input: samples from global index _buf_start on; outputs before _emitted done
        self._t = np.zeros(0, dtype=np.int64)
        self._pos: np.ndarray | None = None
        self._vel: np.ndarray | None = None
        self._buf_start = 0
        self._emitted = 0
        self._last_raw: np.ndarray | None = None  # unwrapping: last raw position
        self._correction: np.ndarray | None = None  # and the running 2 pi correction
        self._direction: np.ndarray | None = None  # last non-zero direction per joint
        self._reversals: list[list[np.ndarray]] = []
        self._pending: list[tuple[np.ndarray, ...]] = []  # filtered, not yet kept or dropped
        self._kept: list[tuple[np.ndarray, ...]] = []

    def push(self, stamps_ns: np.ndarray, position: np.ndarray, velocity: np.ndarray) -> None:
        """Usable joint states (JointScreen), stamps increasing, columns in model order."""
        if len(stamps_ns) == 0:
            return
        position = self._unwrap(np.asarray(position, dtype=float))
        if self._pos is None:
            self._t = np.asarray(stamps_ns, dtype=np.int64)
            self._pos, self._vel = position, np.asarray(velocity, dtype=float)
            n_joints = position.shape[1]
            self._direction = np.zeros(n_joints, dtype=int)
            self._reversals = [[] for _ in range(n_joints)]
        else:
            self._t = np.concatenate([self._t, stamps_ns])
            self._pos = np.concatenate([self._pos, position])
            self._vel = np.concatenate([self._vel, velocity])
        self.count += len(stamps_ns)
        if self._period_s is None:
            if self.count <= PERIOD_INTERVALS:
                return
            self._fix_period()
        self._filter(final=False)
        self._sort_out(final=False)

    def finish(self, t0_ns: int) -> JointSeries:
        """The series (times in s since `t0_ns`) once every joint state is pushed."""
        if self.count == 0:
            raise ValueError("no joint states")
        if self._period_s is None:
            self._fix_period()
        self._filter(final=True)
        self._sort_out(final=True)
        empty = (np.zeros(0, np.int64),) + (np.zeros((0, self._pos.shape[1])),) * 4
        parts = self._kept or [empty]
        t, position, velocity, acceleration, smooth = (np.concatenate(c) for c in zip(*parts))
        return JointSeries(
            t_s=(t - t0_ns) / NS_PER_S,
            position=position,
            velocity=velocity,
            acceleration=acceleration,
            smooth_velocity=smooth,
            reversals=tuple(
                (np.concatenate(r) - t0_ns) / NS_PER_S if r else np.zeros(0)
                for r in self._reversals
            ),
            max_lag_s=self._margin_s if self._blocks is not None else np.inf,
        )

    def _unwrap(self, position: np.ndarray) -> np.ndarray:
        # np.unwrap over the whole series, carried across slices: the correction is a
        # running sum continued element by element, so slicing does not change it.
        if self._last_raw is None:
            self._last_raw = position[0].copy()
            self._correction = np.zeros(position.shape[1])
        steps = np.diff(np.concatenate([self._last_raw[None], position]), axis=0)
        wrapped = np.mod(steps + np.pi, 2 * np.pi) - np.pi
        wrapped[(wrapped == -np.pi) & (steps > 0)] = np.pi
        fix = wrapped - steps
        fix[np.abs(steps) < np.pi] = 0.0
        running = np.cumsum(np.concatenate([self._correction[None], fix]), axis=0)[1:]
        self._last_raw, self._correction = position[-1].copy(), running[-1].copy()
        return position + running

    def _fix_period(self) -> None:
        # from the integer stamps: epoch seconds as floats are too coarse for a 1 ms step
        self._period_s = joint_period(self._t, per_second=NS_PER_S) if len(self._t) > 1 else 1e-3
        self._window = savgol_window(self._period_s)

    def _filter(self, *, final: bool) -> None:
        """Filter what the buffer allows: a sample once its whole window is in (all at the
        end), exactly as one filter over the whole series (scipy's 'interp' edges are fitted
        only at the series' true ends: the buffer starts at the series' start until then)."""
        n_total = self._buf_start + len(self._t)
        w = self._window
        stop = n_total if final else n_total - w // 2
        if stop <= self._emitted:
            return
        if self.count <= w:  # too short for the filter (only at the end): kept, acceleration 0
            smooth, acceleration = self._vel, np.zeros_like(self._vel)
        else:
            smooth, acceleration = (
                signal.savgol_filter(
                    self._vel, w, 2, deriv=d, axis=0, delta=self._period_s, mode="interp"
                )
                for d in (0, 1)
            )
        a, b = self._emitted - self._buf_start, stop - self._buf_start
        out = (self._t[a:b], self._pos[a:b], self._vel[a:b], acceleration[a:b], smooth[a:b])
        self._find_reversals(out[0], out[4])
        self._pending.append(out)
        self._emitted = stop
        keep_from = max(0, stop - w - self._buf_start)  # the next outputs' left context
        self._t, self._pos, self._vel = (x[keep_from:] for x in (self._t, self._pos, self._vel))
        self._buf_start += keep_from

    def _find_reversals(self, t_ns: np.ndarray, smooth: np.ndarray) -> None:
        """Times where motion resumes opposite to each joint's last direction (|smoothed
        velocity| above REVERSAL_THRESHOLD of its top speed), continued across slices."""
        for j in range(smooth.shape[1]):
            thr = REVERSAL_THRESHOLD * self._vmax[j]
            state = np.where(smooth[:, j] > thr, 1, np.where(smooth[:, j] < -thr, -1, 0))
            moving = np.flatnonzero(state)
            if len(moving) == 0:
                continue
            seq = np.concatenate([[self._direction[j]], state[moving]])
            flips = np.flatnonzero((np.diff(seq) != 0) & (seq[:-1] != 0))
            if len(flips):
                self._reversals[j].append(t_ns[moving[flips]])
            self._direction[j] = state[moving[-1]]

    def _sort_out(self, *, final: bool) -> None:
        """Move filtered joint states to the kept series: all of them, or (thinning) those
        near a kept block, once no block still to come can be near them."""
        if not self._pending:
            return
        if self._blocks is None:
            self._kept.extend(self._pending)
            self._pending = []
            return
        until = self._blocks.framed_until_ns
        if not final and until is None:
            return
        parts = [np.concatenate(c) for c in zip(*self._pending)]
        settled = np.ones(len(parts[0]), bool) if final else parts[0] <= until - self._margin_ns
        near = settled & self._blocks.near_kept(parts[0], self._margin_ns)
        if near.any():
            self._kept.append(tuple(x[near] for x in parts))
        self._pending = [tuple(x[~settled] for x in parts)] if not settled.all() else []


def joint_order(model, joint_names, source: str) -> list[int]:
    """Columns of a recording's joints in the model's joint order (ModelFileError if absent)."""
    where = model.provenance.get("path", "noise model")
    if model.n_joints != len(joint_names):
        raise ModelFileError(
            f"{where}: model has {model.n_joints} joints "
            f"{list(model.joint_names)}, {source} has {list(joint_names)}"
        )
    names = list(joint_names)
    if any(n not in names for n in model.joint_names):
        raise ModelFileError(
            f"{where}: joints {list(model.joint_names)} not in {source} joint_states {names}"
        )
    return [names.index(n) for n in model.joint_names]


def in_band_bins(model) -> np.ndarray:
    """Indices of the DFT bins inside the model's band-pass."""
    f = model.freqs_hz
    return np.flatnonzero((f >= model.band_hz[0]) & (f <= model.band_hz[1]))


def _interval_means(
    t: np.ndarray, values: np.ndarray, t0: np.ndarray, t1: np.ndarray
) -> np.ndarray:
    """Mean of a sampled series over the part of [t0, t1] it covers (trapezoid integral of the
    linear interpolant); a block wholly past an end, or of no length, the value at its clipped
    instant: held past its ends, as `motion_features` and the denoiser hold joint states (over
    the whole block, the first and last blocks at a lag were diluted towards standstill)."""
    dt = np.diff(t)
    cum = np.zeros((len(t), values.shape[1]))
    cum[1:] = np.cumsum(0.5 * (values[1:] + values[:-1]) * dt[:, None], axis=0)

    def integral(tq: np.ndarray) -> np.ndarray:
        i = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 2)
        frac = (tq - t[i])[:, None]
        slope = (values[i + 1] - values[i]) / np.maximum(dt[i], 1e-12)[:, None]
        return cum[i] + values[i] * frac + 0.5 * slope * frac**2

    a, b = np.clip(t0, t[0], t[-1]), np.clip(t1, t[0], t[-1])
    covered = b - a > 1e-9
    means = np.empty((len(a), values.shape[1]))
    means[covered] = (integral(b[covered]) - integral(a[covered])) / (b - a)[covered, None]
    means[~covered] = np.column_stack([np.interp(a[~covered], t, column) for column in values.T])
    return means


def speed_rate_means(
    joints: JointSeries, t_first: np.ndarray, t_last: np.ndarray, lag_s: float
) -> np.ndarray:
    """Block means of d|v|/dt (sign of the smoothed velocity times its derivative): speeding
    up vs slowing down, whichever the direction of travel."""
    check_lag(joints, lag_s)
    smooth = joints.smooth_velocity if joints.smooth_velocity is not None else joints.velocity
    return _interval_means(
        joints.t_s - lag_s, np.sign(smooth) * joints.acceleration, t_first, t_last
    )


def jerk_means(
    joints: JointSeries, t_first: np.ndarray, t_last: np.ndarray, lag_s: float
) -> np.ndarray:
    """Block means of |d a/dt|, a the smoothed derivative of the velocity."""
    check_lag(joints, lag_s)
    t, acc = joints.t_s, joints.acceleration
    if len(t) < 2:
        return np.zeros((len(t_first), acc.shape[1]))
    dt = np.diff(t)
    # per interval; a repeated stamp (dt 0) says nothing about the rate
    rate = np.abs(np.diff(acc, axis=0)) / np.where(dt > 0, dt, np.inf)[:, None]
    jerk = np.concatenate([rate[:1], 0.5 * (rate[1:] + rate[:-1]), rate[-1:]])
    return _interval_means(t - lag_s, jerk, t_first, t_last)


def check_lag(joints: JointSeries, lag_s: float) -> None:
    """A thinned series holds joint states only near its blocks: refuse a lag beyond that."""
    if abs(lag_s) > joints.max_lag_s:
        raise ValueError(
            f"joint-state lag {lag_s:+.3f} s is beyond the +-{joints.max_lag_s:g} s of joint "
            "states kept around the blocks of a thinned bag"
        )


def _joint_block_means(joints: JointSeries, t_first: np.ndarray, t_last: np.ndarray, lag_s: float):
    """Block means of velocity, position and |acceleration| (joint states `lag_s` late)."""
    check_lag(joints, lag_s)
    t = joints.t_s - lag_s
    series = (joints.velocity, joints.position, np.abs(joints.acceleration))
    return tuple(_interval_means(t, s, t_first, t_last) for s in series)


def _model_lookup(
    model, velocity: np.ndarray, freq_index: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    ch = model.channel_indices(("combined",))
    mean, _ = model.estimate(velocity, ch, include_std=False)
    full, _ = model.estimate(velocity, ch, include_std=True)
    mean = mean[:, 0, freq_index]
    return mean, np.maximum(full[:, 0, freq_index] - mean, 0.0)


def detect_contacts(
    magnitude: np.ndarray, predicted: np.ndarray, t_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Flag blocks whose spectrum is an outlier above the model's prediction: (flagged, the
    outliers themselves before widening).

    The statistic (mean of the three largest per-bin log ratios) is compared with its
    running median over ~2 s (so a mis-calibrated or drifting model does not flag
    everything) using a robust (MAD) scale; flagged blocks are widened by one block
    before and CONTACT_DILATE blocks after (tap tails).
    """
    # A tap rings in a few modes: the mean of the three largest per-bin log ratios
    # separates taps from ego-vibration better than the band energy when the hand moves fast.
    log_ratio = np.log(np.maximum(magnitude, 1e-300) / np.maximum(predicted, 1e-300))
    ratio = np.sort(log_ratio, axis=1)[:, -3:].mean(axis=1)
    if len(ratio) < 5:
        none = np.zeros(len(ratio), dtype=bool)
        return none, none.copy()
    dt = np.median(np.diff(t_s)) if len(t_s) > 1 else 0.01
    size = int(max(5, min(len(ratio), round(2.0 / max(dt, 1e-6))))) | 1
    local = ndimage.median_filter(ratio, size=size, mode="nearest")
    resid = ratio - local
    scale = 1.4826 * np.median(np.abs(resid - np.median(resid))) + 1e-9
    flagged = raw = resid > CONTACT_Z * scale
    if flagged.any():
        # A tap rings on after its onset: drop CONTACT_DILATE blocks after each flagged
        # block and one before (the block straddling the onset may be below threshold).
        structure = np.zeros(2 * CONTACT_DILATE + 1, dtype=bool)
        structure[CONTACT_DILATE - 1 :] = True  # origin at the centre: -1 .. +dilate
        flagged = ndimage.binary_dilation(flagged, structure=structure)
    return flagged, raw


def baseline_knots(grid) -> tuple[np.ndarray, ...]:
    """The model's velocity grid per joint, each interval split into KNOT_REFINE cells
    (KNOT_REFINE_LOW within LOW_SPEED_FRACTION of the top speed: a line whose frequency is a
    high multiple of the shaft speed sweeps a DFT bin per ~1 % of speed there)."""
    out = []
    for g in grid:
        g = np.asarray(g, float)
        top = np.max(np.abs(g))
        pieces = []
        for a, b in zip(g[:-1], g[1:]):
            low = max(abs(a), abs(b)) <= LOW_SPEED_FRACTION * top + 1e-12
            n = KNOT_REFINE_LOW if low else KNOT_REFINE
            pieces.append(np.linspace(a, b, n + 1)[:-1])
        out.append(np.round(np.concatenate(pieces + [g[-1:]]), 12))
    return tuple(out)


def joint_period(t: np.ndarray, *, per_second: float = 1.0) -> float:
    """The joint-state period (s) the Savitzky-Golay filter assumes: the median of the first
    PERIOD_INTERVALS intervals of the times `t` (`per_second` units per second; a stream
    fixes the period early, not at the end of the bag)."""
    return float(np.median(np.diff(t[: PERIOD_INTERVALS + 1]))) / per_second


def savgol_window(period_s: float) -> int:
    """Odd Savitzky-Golay window (samples) spanning ACCEL_SMOOTH_S at this joint period."""
    return max(int(round(ACCEL_SMOOTH_S / max(period_s, 1e-6))) | 1, 5)


def attach_motion(table: BlockTable) -> BlockTable:
    """Baseline cells, velocity-trajectory features and reversal times of a table whose
    joint series is smoothed (JointFeatures; by hand: test/gaptables.py)."""
    table.knots = baseline_knots(table.model.grid)
    return _attach_trajectory(table)


def _attach_trajectory(table: BlockTable) -> BlockTable:
    """The velocity-trajectory features, reversal times and speed rates at the table's lag."""
    table.hats, table.reversal_after_s, table.reversal_before_s = motion_features(
        table.joints, table.t_first_s, table.t_last_s, table.lag_s, table.knots, table.model.window
    )
    table.speed_rate = speed_rate_means(table.joints, table.t_first_s, table.t_last_s, table.lag_s)
    table.jerk = jerk_means(table.joints, table.t_first_s, table.t_last_s, table.lag_s)
    return table


def build_table(rec, model, *, source: str = "bag") -> BlockTable:
    """Blocks, spectra, model prediction and covariates of a Recording for a NoiseModel
    (the whole recording as one slice; `table_from_bag` streams a bag)."""
    return _table_of_pieces([rec], model, source=source)


def grid_speeds(model) -> np.ndarray:
    """Largest grid speed per joint (the reversal threshold's scale)."""
    return np.array([np.max(np.abs(g)) for g in model.grid])


def table_from_bag(
    path,
    model,
    *,
    budget_minutes: float | None = DEFAULT_BUDGET_MINUTES,
    max_lag_s: float = JOINT_MARGIN_S,
    progress=None,
) -> BlockTable:
    """`build_table` of a bag read slice by slice (bag.iter_recording with the model's robot
    profile): the sensor samples are framed as they arrive and never held; the joint
    states are filtered as they arrive. Same table as `build_table(read_recording(path))`
    (tested).

    A bag longer than `budget_minutes` is thinned evenly: one run of THIN_RUN_BLOCKS
    blocks kept in the share budget / duration, spread evenly, and the joint states
    within `max_lag_s` of them (the largest lag the table can then be re-matched at), so
    that memory and time stop growing with the bag; `table.bad_input["kept_share"]` says
    the share. None: no budget."""

    keep, budget = 1.0, {}
    if budget_minutes is not None:
        # the seconds of data, not of stamps: a pause in the recording thins nothing
        duration_s = duration_of(path, model.profile)
        if duration_s > 60.0 * budget_minutes:
            keep = 60.0 * budget_minutes / duration_s
        budget["recorded_s"] = duration_s  # seconds of sensor data the budget was held to
    pieces = iter_recording(
        path,
        profile=model.profile,
        ground_truth=False,
        denoised=False,
        commands=False,
        progress=progress,
    )
    return _table_of_pieces(
        pieces, model, source=str(path), keep=keep, max_lag_s=max_lag_s, budget=budget
    )


def _table_of_pieces(
    pieces,
    model,
    *,
    source: str,
    keep: float = 1.0,
    max_lag_s: float = JOINT_MARGIN_S,
    budget: dict | None = None,
) -> BlockTable:
    """The table of Recording slices (`keep` < 1: thinned, see `table_from_bag`; `budget`:
    its recorded seconds, for bad_input beside kept_share)."""
    framing = BlockSpectra(model, model.n_joints, keep=keep)
    joints = JointFeatures(grid_speeds(model), blocks=framing, margin_s=max_lag_s)
    order, screen = None, JointScreen()
    for piece in pieces:
        if order is None:
            order = joint_order(model, piece.joint_names, source)
        good = screen(piece.joint_stamps_ns, piece.joint_position, piece.joint_velocity)
        stamps = piece.joint_stamps_ns[good]
        velocity = piece.joint_velocity[good][:, order]
        framing.push_joint_states(stamps, velocity)
        framing.push_sensor(piece.sensor_stamps_ns, piece.sensor)
        # after the framing, so the blocks these joint states may be near are known
        joints.push(stamps, piece.joint_position[good][:, order], velocity)
    if order is None:
        raise BagError(f"{source}: no sensor or joint-state messages")
    bad_input = dict(
        joint_states=screen.seen,
        joint_states_bad=screen.bad,
        joint_states_duplicates=screen.duplicates,
    )
    if budget is not None:
        bad_input.update(kept_share=keep, **budget)
    return table_from_blocks(model, framing, joints, bad_input=bad_input, source=source)


def table_from_blocks(
    model,
    framing: BlockSpectra,
    joint_features: JointFeatures,
    *,
    bad_input: dict,
    source: str,
) -> BlockTable:
    """The table from the framed blocks and the (usable, model-ordered) joint states.
    More than core.MAX_BAD_SHARE of bad sensor samples or joint states is refused (one-line
    StreamError) before anything else is said about the data."""

    magnitude, first_ns, last_ns, v_core = framing.finish()
    counts = dict(vars(framing.stats))
    bad_input = dict(counts, **bad_input)
    bad_input["joint_states_dropped"] = bad_input.pop("joint_states_bad", 0) + counts.get(
        "joint_states_dropped", 0
    )
    # the framer's counts, with the joint states the bag reader already found unusable
    counted = dataclasses.replace(
        framing.stats,
        joint_states_dropped=bad_input["joint_states_dropped"],
        joint_states_duplicates=bad_input.pop("joint_states_duplicates", 0)
        + counts.get("joint_states_duplicates", 0),
    )
    p = model.profile
    topics = (p.sensor_topic, p.joints_topic) if p else ("sensor topic", "joint-state topic")
    bad_input["said"] = check_stream(
        counted,
        f"{source}: {topics[0]}",
        joint_states=bad_input["joint_states"],
        joints_where=f"{source}: {topics[1]}",
    )
    if framing.samples < 4 * model.block_length:
        raise BagError(f"{source}: the sensor topic has only {framing.samples} samples")
    if joint_features.count < 10:
        raise BagError(f"{source}: joint_states has only {joint_features.count} usable messages")
    if len(magnitude) < 10:
        raise BagError(
            f"{source}: fewer than 10 usable blocks "
            "(accelerometer and joint_states do not overlap?)"
        )
    freq_index = in_band_bins(model)
    t0_ns = framing.first_stamp_ns
    t_first = (first_ns - t0_ns) / NS_PER_S
    t_last = (last_ns - t0_ns) / NS_PER_S
    joints = joint_features.finish(t0_ns)
    bad_input["joint_states_kept"] = len(joints.t_s)
    _, pos_b, acc_b = _joint_block_means(joints, t_first, t_last, 0.0)
    mean, std = _model_lookup(model, v_core, freq_index)
    table = BlockTable(
        t_first_s=t_first,
        t_last_s=t_last,
        magnitude=magnitude,
        freqs_hz=model.freqs_hz[freq_index],
        velocity=v_core,
        position=pos_b,
        acceleration=acc_b,
        base_mean=mean,
        base_std=std,
        contact=np.zeros(len(t_first), dtype=bool),
        vmax=grid_speeds(model),
        joint_names=tuple(model.joint_names),
        model=model,
        joints=joints,
        freq_index=freq_index,
    )
    attach_motion(table)  # baseline cells, trajectory, reversals
    table.contact = detect_contacts(table.magnitude, table.base_mean, table.t_mid_s)[0]
    table.bad_input = bad_input
    return table


#: Seconds between the two recordings on the time axis of a joined table.
JOIN_GAP_S = 10.0


def join_tables(reference: BlockTable, real: BlockTable) -> BlockTable:
    """One table of two recordings of the same robot, each at the joint-state lag it was
    re-matched at: the reference's blocks, then the recording's, its times shifted to start
    JOIN_GAP_S after the reference's end; `recording` says whose each block is. The joint
    series is not joined (the tables are at their lags already: no `at_lag`)."""
    if tuple(reference.joint_names) != tuple(real.joint_names) or len(reference.freqs_hz) != len(
        real.freqs_hz
    ):
        raise ValueError("join_tables: the recordings' tables differ in joints or bins")
    offset = float(reference.t_last_s[-1]) + JOIN_GAP_S - float(real.t_first_s[0])
    per_block = ("magnitude", "velocity", "position", "acceleration", "base_mean", "base_std")
    per_block += ("contact", "hats", "reversal_after_s", "reversal_before_s", "speed_rate", "jerk")
    return replace(
        reference,
        t_first_s=np.concatenate([reference.t_first_s, real.t_first_s + offset]),
        t_last_s=np.concatenate([reference.t_last_s, real.t_last_s + offset]),
        **{n: np.concatenate([getattr(reference, n), getattr(real, n)]) for n in per_block},
        joints=None,
        recording=np.concatenate(
            [np.zeros(reference.n_blocks, np.int8), np.ones(real.n_blocks, np.int8)]
        ),
        bad_input={},
    )
