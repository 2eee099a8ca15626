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

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage, signal

from egovib_ros.core.stream import FramerSettings
from egovib_ros.core.velocity import MISSING
from egovib_ros.errors import BagError, ModelFileError

NS = 1_000_000_000
#: A block counts as contact if its top-3-bin log ratio to the model exceeds the local
#: typical level by this many robust standard deviations.
CONTACT_Z = 3.5
#: Blocks after a flagged block also dropped (tap tails ring for 10-30 ms + filter decay).
CONTACT_DILATE = 5
#: Savitzky-Golay window for joint accelerations (s): long enough to average encoder
#: quantisation, short compared with the motion.
ACCEL_SMOOTH_S = 0.031


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

    def subset(self, rows: np.ndarray) -> "BlockTable":
        """Rows of the table (boolean mask or indices)."""
        pick = {
            name: getattr(self, name)[rows]
            for name in (
                "t_first_s",
                "t_last_s",
                "magnitude",
                "velocity",
                "position",
                "acceleration",
                "base_mean",
                "base_std",
                "contact",
                "axis_mean",
                "hats",
                "reversal_after_s",
                "reversal_before_s",
            )
            if getattr(self, name) is not None
        }
        return replace(self, **pick)

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
        axis, zero = axis_spectra(self.model, velocity, self.freq_index)
        hats, after, before = motion_features(
            self.joints, self.t_first_s, self.t_last_s, lag_s, self.knots, self.model.window
        )
        return replace(
            self,
            velocity=velocity,
            position=position,
            acceleration=acceleration,
            base_mean=mean,
            base_std=std,
            axis_mean=axis,
            zero_mean=zero,
            hats=hats,
            reversal_after_s=after,
            reversal_before_s=before,
            lag_s=float(lag_s),
        )

    freq_index: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, dtype=np.intp))
    axis_mean: np.ndarray | None = field(
        repr=False, default=None
    )  # (B, J, F) Eq. 6 single-joint spectra
    zero_mean: np.ndarray | None = field(repr=False, default=None)  # (F,) spectrum at rest
    #: Velocity knots per joint (the model's grid): the baseline's cells.
    knots: tuple[np.ndarray, ...] = field(repr=False, default=())
    #: (B, J, K) window-weighted mean over each block of the hat functions of the joint's
    #: velocity trajectory at the knots: what a velocity-only table predicts, linearly.
    hats: np.ndarray | None = field(repr=False, default=None)
    reversal_after_s: np.ndarray | None = field(
        repr=False, default=None
    )  # (B, J) since last reversal
    reversal_before_s: np.ndarray | None = field(
        repr=False, default=None
    )  # (B, J) until next reversal
    lag_s: float = 0.0  # joint-state lag of this table
    #: counts of bad input treated as missing (framer stats, joint states dropped)
    bad_input: dict = field(repr=False, default_factory=dict)


#: The baseline's velocity cells: the model's grid with each interval split in this many
#: (tonal lines sweep a DFT bin within a fraction of a 10 % grid step).
KNOT_REFINE = 4
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
    rows = np.repeat(np.arange(n_blocks), TRAJECTORY_POINTS)
    w = np.tile(weight, n_blocks)
    for j in range(n_joints):
        v = np.interp(times.ravel(), t_joint, vel[:, j])
        i, wl, wr = hat_basis(v, knots[j])
        np.add.at(hats[:, j], (rows, i), w * wl)
        np.add.at(hats[:, j], (rows, i + 1), w * wr)
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


def detect_reversals(
    t_s: np.ndarray, smooth_velocity: np.ndarray, vmax: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Per joint: times at which motion resumes opposite to the previous direction of motion."""
    out = []
    for j in range(smooth_velocity.shape[1]):
        v = smooth_velocity[:, j]
        thr = REVERSAL_THRESHOLD * vmax[j]
        state = np.where(v > thr, 1, np.where(v < -thr, -1, 0))
        moving = np.flatnonzero(state)
        if len(moving) < 2:
            out.append(np.zeros(0))
            continue
        flips = moving[1:][np.diff(state[moving]) != 0]
        out.append(t_s[flips])
    return tuple(out)


#: A bag longer than the block budget is thinned in runs of this many consecutive blocks
#: (~0.7 s at 3 kHz): a run holds 8 metric windows and about one 0.5 s test segment.
THIN_RUN_BLOCKS = 64
#: Default budget of `egovib gap`: the diagnosis's memory and time grow with the blocks it
#: fits (~100 MB per minute of 3 kHz recording), not with the bag beyond this.
DEFAULT_BUDGET_MINUTES = 5.0


class BlockSpectra:
    """The core's own framing (a BlockFramer, as calibration uses: band-passed sum of axes,
    the model's window and sensor range) fed as a stream: push joint states, then sensor
    samples, slice by slice; `finish()` gives the in-band magnitude spectra of the complete
    blocks that have a joint state. The framer is the only state, so any slicing of the
    same arrays gives the same blocks (tested); a bag is never held whole."""

    def __init__(self, model, n_joints: int, *, max_hold_s: float = 0.05, keep: float = 1.0):
        """`keep` < 1: keep that share of the runs of THIN_RUN_BLOCKS consecutive blocks,
        spread evenly (a long bag thinned over its whole length, see `table_from_bag`)."""
        from egovib_ros.core.stream import BlockFramer

        # the model's framing, including its sensor range: bad samples are missing
        settings = FramerSettings.for_model(model, layout="combined", max_hold_s=max_hold_s)
        self._framer = BlockFramer(settings, n_joints)
        self._window = model.window
        self._bins = in_band_bins(model)
        self._n_joints = n_joints
        self._parts: list[tuple[np.ndarray, ...]] = []
        self._keep = float(keep)
        self._blocks_seen = 0
        self.samples = 0
        self.first_stamp_ns: int | None = None

    @property
    def stats(self) -> dict:
        return dict(vars(self._framer.stats))

    def push_joint_states(self, stamps_ns: np.ndarray, velocity: np.ndarray) -> None:
        self._framer.push_joint_states(stamps_ns, velocity)
        self._collect()

    def push_accel(self, stamps_ns: np.ndarray, accel: np.ndarray) -> None:
        if len(stamps_ns) and self.first_stamp_ns is None:
            self.first_stamp_ns = int(stamps_ns[0])
        self.samples += len(stamps_ns)
        self._framer.push_accel(stamps_ns, accel)
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
            if ok.any():
                spectra = np.abs(np.fft.rfft(b.samples[ok, 0, :] * self._window, axis=1))
                self._parts.append(
                    (spectra[:, self._bins], b.t_first_ns[ok], b.t_last_ns[ok], b.velocity[ok])
                )

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

    def __call__(self, stamps_ns: np.ndarray, position: np.ndarray, velocity: np.ndarray):
        finite = np.all(np.isfinite(velocity), axis=1) & np.all(np.isfinite(position), axis=1)
        good = np.zeros(len(stamps_ns), dtype=bool)
        last = self.last_ns
        for i in np.flatnonzero(finite):  # joint rate: a Python loop is cheap here
            if last is None or stamps_ns[i] > last:
                good[i], last = True, int(stamps_ns[i])
        self.last_ns = last
        self.seen += len(good)
        self.bad += int((~good).sum())
        return good


def _sensor_topic(model) -> str:
    return model.profile.sensor_topic if model.profile is not None else "sensor topic"


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
    """Mean of a sampled series over [t0, t1] (trapezoid integral of the linear interpolant)."""
    dt = np.diff(t)
    cum = np.concatenate(
        [
            np.zeros((1, values.shape[1])),
            np.cumsum(0.5 * (values[1:] + values[:-1]) * dt[:, None], axis=0),
        ]
    )

    def integral(tq: np.ndarray) -> np.ndarray:
        tq = np.clip(tq, t[0], t[-1])
        i = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 2)
        frac = (tq - t[i])[:, None]
        slope = (values[i + 1] - values[i]) / np.maximum(dt[i], 1e-12)[:, None]
        return cum[i] + values[i] * frac + 0.5 * slope * frac**2

    span = np.maximum(t1 - t0, 1e-9)[:, None]
    return (integral(t1) - integral(t0)) / span


def _joint_block_means(joints: JointSeries, t_first: np.ndarray, t_last: np.ndarray, lag_s: float):
    t = joints.t_s - lag_s
    velocity = _interval_means(t, joints.velocity, t_first, t_last)
    position = _interval_means(t, joints.position, t_first, t_last)
    acceleration = _interval_means(t, np.abs(joints.acceleration), t_first, t_last)
    return velocity, position, acceleration


def _model_lookup(
    model, velocity: np.ndarray, freq_index: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    ch = model.channel_indices(("combined",))
    mean, _ = model.estimate(velocity, ch, include_std=False)
    full, _ = model.estimate(velocity, ch, include_std=True)
    mean = mean[:, 0, freq_index]
    return mean, np.maximum(full[:, 0, freq_index] - mean, 0.0)


def axis_spectra(
    model, velocity: np.ndarray, freq_index: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 6 ingredients: mean spectra with only joint j moving, (B, J, F), and at rest, (F,)."""
    ch = model.channel_indices(("combined",))
    n_joints = velocity.shape[1]
    zero, _ = model.estimate(np.zeros((1, n_joints)), ch, include_std=False)
    axis = np.empty((len(velocity), n_joints, len(freq_index)))
    for j in range(n_joints):
        only = np.zeros_like(velocity)
        only[:, j] = velocity[:, j]
        m, _ = model.estimate(only, ch, include_std=False)
        axis[:, j] = m[:, 0, freq_index]
    return axis, zero[0, 0, freq_index]


def detect_contacts(
    magnitude: np.ndarray,
    predicted: np.ndarray,
    t_s: np.ndarray,
    *,
    z: float = CONTACT_Z,
    dilate: int = CONTACT_DILATE,
    return_raw: bool = False,
):
    """Flag blocks whose spectrum is an outlier above the model's prediction.

    The statistic (mean of the three largest per-bin log ratios) is compared with its
    running median over ~2 s (so a mis-calibrated or drifting model does not flag
    everything) using a robust (MAD) scale; flagged blocks are widened by one block
    before and `dilate` blocks after (tap tails).
    """
    # A tap rings in a few modes: the mean of the three largest per-bin log ratios
    # separates taps from ego-vibration better than the band energy when the hand moves fast.
    log_ratio = np.log(np.maximum(magnitude, 1e-300) / np.maximum(predicted, 1e-300))
    ratio = np.sort(log_ratio, axis=1)[:, -3:].mean(axis=1)
    if len(ratio) < 5:
        none = np.zeros(len(ratio), dtype=bool)
        return (none, none.copy()) if return_raw else none
    dt = np.median(np.diff(t_s)) if len(t_s) > 1 else 0.01
    size = int(max(5, min(len(ratio), round(2.0 / max(dt, 1e-6))))) | 1
    local = ndimage.median_filter(ratio, size=size, mode="nearest")
    resid = ratio - local
    scale = 1.4826 * np.median(np.abs(resid - np.median(resid))) + 1e-9
    flagged = raw = resid > z * scale
    if flagged.any():
        # A tap rings on after its onset: drop `dilate` blocks after each flagged block
        # and one before (the block straddling the onset may be below threshold).
        structure = np.zeros(2 * dilate + 1, dtype=bool)
        structure[dilate - 1 :] = True  # origin at the centre: -1 .. +dilate
        flagged = ndimage.binary_dilation(flagged, structure=structure)
    return (flagged, raw) if return_raw else flagged


def baseline_knots(
    grid, refine: int = 1, low_refine: int | None = None, low_fraction: float = LOW_SPEED_FRACTION
) -> tuple[np.ndarray, ...]:
    """The model's velocity grid per joint, each interval split into `refine` cells
    (`low_refine` within `low_fraction` of the top speed: a line whose frequency is a
    high multiple of the shaft speed sweeps a DFT bin per ~1 % of speed there)."""
    low_refine = refine if low_refine is None else low_refine
    out = []
    for g in grid:
        g = np.asarray(g, float)
        top = np.max(np.abs(g))
        pieces = []
        for a, b in zip(g[:-1], g[1:]):
            n = low_refine if max(abs(a), abs(b)) <= low_fraction * top + 1e-12 else refine
            pieces.append(np.linspace(a, b, n + 1)[:-1])
        out.append(np.round(np.concatenate(pieces + [g[-1:]]), 12))
    return tuple(out)


def savgol_joint(t_s: np.ndarray, velocity: np.ndarray, *, deriv: int = 0) -> np.ndarray:
    """Velocity smoothed (deriv 0) or differentiated (deriv 1) by a quadratic
    Savitzky-Golay filter over ACCEL_SMOOTH_S; a series too short for it is returned as is
    (deriv 0) or as zeros (deriv 1)."""
    dt = float(np.median(np.diff(t_s)))
    window = max(int(round(ACCEL_SMOOTH_S / max(dt, 1e-6))) | 1, 5)
    if len(velocity) <= window:
        return velocity if deriv == 0 else np.zeros_like(velocity)
    return signal.savgol_filter(velocity, window, 2, deriv=deriv, axis=0, delta=dt, mode="interp")


def smooth_joint_series(joints: JointSeries, vmax: np.ndarray) -> JointSeries:
    """Fill in the smoothed velocity and the reversal times of a joint series (if missing)."""
    if joints.smooth_velocity is None:
        joints.smooth_velocity = savgol_joint(joints.t_s, joints.velocity)
    if not joints.reversals:
        joints.reversals = detect_reversals(joints.t_s, joints.smooth_velocity, vmax)
    return joints


def attach_motion(table: BlockTable, *, knot_refine: int = KNOT_REFINE) -> BlockTable:
    """Baseline cells, velocity-trajectory features and reversal times of a table built by hand."""
    smooth_joint_series(table.joints, table.vmax)
    table.knots = baseline_knots(
        table.model.grid,
        knot_refine,
        KNOT_REFINE_LOW if knot_refine == KNOT_REFINE else knot_refine,
    )
    table.hats, table.reversal_after_s, table.reversal_before_s = motion_features(
        table.joints, table.t_first_s, table.t_last_s, table.lag_s, table.knots, table.model.window
    )
    return table


def build_table(
    rec, model, *, max_hold_s: float = 0.05, source: str = "bag", knot_refine: int = KNOT_REFINE
) -> BlockTable:
    """Blocks, spectra, model prediction and covariates of a Recording for a NoiseModel
    (the whole recording pushed as one slice; `table_from_bag` streams a bag)."""
    order = joint_order(model, rec.joint_names, source)
    screen = JointScreen()
    good = screen(rec.joint_stamps_ns, rec.joint_position, rec.joint_velocity)
    position = rec.joint_position[good][:, order]
    velocity = rec.joint_velocity[good][:, order]
    framing = BlockSpectra(model, model.n_joints, max_hold_s=max_hold_s)
    framing.push_joint_states(rec.joint_stamps_ns[good], velocity)
    framing.push_accel(rec.accel_stamps_ns, rec.accel)
    bad_input = dict(joint_states=screen.seen, joint_states_bad=screen.bad)
    return table_from_blocks(
        model,
        framing,
        rec.joint_stamps_ns[good],
        position,
        velocity,
        bad_input=bad_input,
        source=source,
        knot_refine=knot_refine,
    )


def table_from_bag(
    path,
    model,
    *,
    max_hold_s: float = 0.05,
    knot_refine: int = KNOT_REFINE,
    budget_minutes: float | None = DEFAULT_BUDGET_MINUTES,
    progress=None,
) -> BlockTable:
    """`build_table` of a bag read slice by slice (bag.iter_recording with the model's robot
    profile): the sensor samples are framed as they arrive and never held; only the joint
    states (joint rate) and the blocks' in-band spectra are kept. Same table as
    `build_table(read_recording(path))` (tested).

    A bag longer than `budget_minutes` is thinned evenly: one run of THIN_RUN_BLOCKS
    blocks kept in the share budget / duration, spread evenly, so that the diagnosis's
    memory and time stop growing with the bag (the joint states are still kept whole);
    `table.bad_input["kept_share"]` says the share. None: no budget."""
    from egovib_ros.bag import iter_recording
    from egovib_ros.bag.recording import duration_of

    source = str(path)
    keep = 1.0
    if budget_minutes is not None:
        duration_s = duration_of(path)
        if duration_s > 60.0 * budget_minutes:
            keep = 60.0 * budget_minutes / duration_s
    framing = BlockSpectra(model, model.n_joints, max_hold_s=max_hold_s, keep=keep)
    stamps, positions, velocities = [], [], []
    order, screen = None, JointScreen()
    for piece in iter_recording(
        path,
        profile=model.profile,
        ground_truth=False,
        denoised=False,
        commands=False,
        progress=progress,
    ):
        if order is None:
            order = joint_order(model, piece.joint_names, source)
        good = screen(piece.joint_stamps_ns, piece.joint_position, piece.joint_velocity)
        stamps.append(piece.joint_stamps_ns[good])
        positions.append(piece.joint_position[good][:, order])
        velocities.append(piece.joint_velocity[good][:, order])
        framing.push_joint_states(stamps[-1], velocities[-1])
        framing.push_accel(piece.accel_stamps_ns, piece.accel)
    if order is None:
        raise BagError(f"{source}: no sensor or joint-state messages")
    bad_input = dict(joint_states=screen.seen, joint_states_bad=screen.bad, kept_share=keep)
    return table_from_blocks(
        model,
        framing,
        np.concatenate(stamps),
        np.concatenate(positions),
        np.concatenate(velocities),
        bad_input=bad_input,
        source=source,
        knot_refine=knot_refine,
    )


def table_from_blocks(
    model,
    framing: BlockSpectra,
    joint_stamps_ns: np.ndarray,
    position: np.ndarray,
    velocity: np.ndarray,
    *,
    bad_input: dict,
    source: str,
    knot_refine: int = KNOT_REFINE,
) -> BlockTable:
    """The table from the framed blocks and the (usable, model-ordered) joint states.
    More than core.MAX_BAD_SHARE of bad sensor samples or joint states is refused (one-line
    StreamError) before anything else is said about the data."""
    from egovib_ros.cliutil import check_stream

    magnitude, first_ns, last_ns, v_core = framing.finish()
    counts = {k: v for k, v in framing.stats.items() if isinstance(v, (int, float))}
    bad_input = dict(counts, **bad_input)
    bad_input["joint_states_dropped"] = bad_input.pop("joint_states_bad", 0) + counts.get(
        "joint_states_dropped", 0
    )
    bad_input["said"] = check_stream(
        bad_input, f"{source}: {_sensor_topic(model)}", joint_states=bad_input["joint_states"]
    )
    if framing.samples < 4 * model.block_length:
        raise BagError(f"{source}: the sensor topic has only {framing.samples} samples")
    if len(joint_stamps_ns) < 10:
        raise BagError(f"{source}: joint_states has only {len(joint_stamps_ns)} usable messages")
    if len(magnitude) < 10:
        raise BagError(
            f"{source}: fewer than 10 usable blocks "
            "(accelerometer and joint_states do not overlap?)"
        )
    freq_index = in_band_bins(model)
    t0_ns = framing.first_stamp_ns
    t_first = (first_ns - t0_ns) / NS
    t_last = (last_ns - t0_ns) / NS

    joint_t = (joint_stamps_ns - t0_ns) / NS
    # Unwrap so a block mean of the continuous wrist angle never straddles a +-pi jump.
    position = np.unwrap(position, axis=0)
    acceleration = savgol_joint(joint_t, velocity, deriv=1)
    smooth = savgol_joint(joint_t, velocity)
    vmax = np.array([np.max(np.abs(g)) for g in model.grid])
    joints = JointSeries(
        t_s=joint_t,
        position=position,
        velocity=velocity,
        acceleration=acceleration,
        smooth_velocity=smooth,
        reversals=detect_reversals(joint_t, smooth, vmax),
    )

    _, pos_b, acc_b = _joint_block_means(joints, t_first, t_last, 0.0)
    mean, std = _model_lookup(model, v_core, freq_index)
    knots = baseline_knots(
        model.grid, knot_refine, KNOT_REFINE_LOW if knot_refine == KNOT_REFINE else knot_refine
    )
    hats, after, before = motion_features(joints, t_first, t_last, 0.0, knots, model.window)
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
        vmax=vmax,
        joint_names=tuple(model.joint_names),
        model=model,
        joints=joints,
        freq_index=freq_index,
        knots=knots,
        hats=hats,
        reversal_after_s=after,
        reversal_before_s=before,
    )
    table.axis_mean, table.zero_mean = axis_spectra(model, v_core, freq_index)
    table.contact = detect_contacts(table.magnitude, table.base_mean, table.t_mid_s)
    table.bad_input = bad_input
    return table
