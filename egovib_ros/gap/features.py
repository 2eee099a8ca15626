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

from egovib_ros.core.stream import FramerSettings, frame_batch
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


def frame_blocks(rec, model, velocity: np.ndarray, max_hold_s: float):
    """The core's own framing (`frame_batch`, as calibration uses): band-passed sum of axes.

    Returns (magnitude spectra (B, n_bins) of complete blocks with a joint state,
    t_first_ns (B,), t_last_ns (B,), block mean velocity (B, J)).
    """
    # the model's framing, including its sensor range: bad samples are missing, as in calibration
    settings = FramerSettings.for_model(model, layout="combined", max_hold_s=max_hold_s)
    batches, _ = frame_batch(
        settings, velocity.shape[1], rec.accel_stamps_ns, rec.accel, rec.joint_stamps_ns, velocity
    )
    batches = [b for b in batches if b.n]
    if not batches:
        n_bins = model.block_length // 2 + 1
        return (
            np.zeros((0, n_bins)),
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            np.zeros((0, velocity.shape[1])),
        )
    samples = np.concatenate([b.samples[:, 0, :] for b in batches])
    t_first = np.concatenate([b.t_first_ns for b in batches])
    t_last = np.concatenate([b.t_last_ns for b in batches])
    v = np.concatenate([b.velocity for b in batches])
    ok = np.concatenate(
        [
            (b.complete if b.complete is not None else np.ones(b.n, bool)) & (b.status != MISSING)
            for b in batches
        ]
    )
    spectra = np.abs(np.fft.rfft(samples[ok] * model.window, axis=1))
    return spectra, t_first[ok], t_last[ok], v[ok]


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


def smooth_joint_series(joints: JointSeries, vmax: np.ndarray) -> JointSeries:
    """Fill in the smoothed velocity and the reversal times of a joint series (if missing)."""
    if joints.smooth_velocity is None:
        dt = float(np.median(np.diff(joints.t_s)))
        window = max(int(round(ACCEL_SMOOTH_S / max(dt, 1e-6))) | 1, 5)
        joints.smooth_velocity = (
            signal.savgol_filter(joints.velocity, window, 2, axis=0, mode="interp")
            if len(joints.velocity) > window
            else joints.velocity
        )
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
    """Blocks, spectra, model prediction and covariates of a Recording for a NoiseModel."""
    if model.n_joints != len(rec.joint_names):
        raise ModelFileError(
            f"{model.provenance.get('path', 'noise model')}: model has {model.n_joints} joints "
            f"{list(model.joint_names)}, {source} has {list(rec.joint_names)}"
        )
    if tuple(model.joint_names) != tuple(rec.joint_names):
        order = [
            list(rec.joint_names).index(n) if n in rec.joint_names else -1
            for n in model.joint_names
        ]
        if min(order) < 0:
            raise ModelFileError(
                f"{model.provenance.get('path', 'noise model')}: joints {list(model.joint_names)} "
                f"not in {source} joint_states {list(rec.joint_names)}"
            )
    else:
        order = list(range(model.n_joints))
    if len(rec.accel_stamps_ns) < 4 * model.block_length:
        raise BagError(f"{source}: /accelerometer/raw has only {len(rec.accel_stamps_ns)} samples")
    if len(rec.joint_stamps_ns) < 10:
        raise BagError(f"{source}: /joint_states has only {len(rec.joint_stamps_ns)} messages")

    velocity = rec.joint_velocity[:, order]
    spectra, first_ns, last_ns, v_core = frame_blocks(rec, model, velocity, max_hold_s)
    if len(spectra) < 10:
        raise BagError(
            f"{source}: fewer than 10 usable blocks "
            "(accelerometer and joint_states do not overlap?)"
        )
    freq_index = in_band_bins(model)
    t0_ns = int(rec.accel_stamps_ns[0])
    t_first = (first_ns - t0_ns) / NS
    t_last = (last_ns - t0_ns) / NS

    joint_t = (rec.joint_stamps_ns - t0_ns) / NS
    # Unwrap so a block mean of the continuous wrist angle never straddles a +-pi jump.
    position = np.unwrap(rec.joint_position[:, order], axis=0)
    window = int(round(ACCEL_SMOOTH_S / max(np.median(np.diff(joint_t)), 1e-6))) | 1
    window = max(window, 5)
    acceleration = (
        signal.savgol_filter(
            velocity,
            window,
            2,
            deriv=1,
            axis=0,
            delta=float(np.median(np.diff(joint_t))),
            mode="interp",
        )
        if len(velocity) > window
        else np.zeros_like(velocity)
    )
    smooth = (
        signal.savgol_filter(velocity, window, 2, axis=0, mode="interp")
        if len(velocity) > window
        else velocity
    )
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
        magnitude=spectra[:, freq_index],
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
    return table
