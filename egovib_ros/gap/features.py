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
            )
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
        return replace(
            self,
            velocity=velocity,
            position=position,
            acceleration=acceleration,
            base_mean=mean,
            base_std=std,
            axis_mean=axis,
            zero_mean=zero,
        )

    freq_index: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, dtype=np.intp))
    axis_mean: np.ndarray | None = field(
        repr=False, default=None
    )  # (B, J, F) Eq. 6 single-joint spectra
    zero_mean: np.ndarray | None = field(repr=False, default=None)  # (F,) spectrum at rest


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
) -> np.ndarray:
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
        return np.zeros(len(ratio), dtype=bool)
    dt = np.median(np.diff(t_s)) if len(t_s) > 1 else 0.01
    size = int(max(5, min(len(ratio), round(2.0 / max(dt, 1e-6))))) | 1
    local = ndimage.median_filter(ratio, size=size, mode="nearest")
    resid = ratio - local
    scale = 1.4826 * np.median(np.abs(resid - np.median(resid))) + 1e-9
    flagged = resid > z * scale
    if flagged.any():
        # A tap rings on after its onset: drop `dilate` blocks after each flagged block
        # and one before (the block straddling the onset may be below threshold).
        structure = np.zeros(2 * dilate + 1, dtype=bool)
        structure[dilate - 1 :] = True  # origin at the centre: -1 .. +dilate
        flagged = ndimage.binary_dilation(flagged, structure=structure)
    return flagged


def build_table(rec, model, *, max_hold_s: float = 0.05, source: str = "bag") -> BlockTable:
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
            f"{source}: fewer than 10 usable blocks (accelerometer and joint_states do not "
            "overlap?)"
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
    joints = JointSeries(
        t_s=joint_t, position=position, velocity=velocity, acceleration=acceleration
    )

    _, pos_b, acc_b = _joint_block_means(joints, t_first, t_last, 0.0)
    mean, std = _model_lookup(model, v_core, freq_index)
    vmax = np.array([np.max(np.abs(g)) for g in model.grid])
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
    )
    table.axis_mean, table.zero_mean = axis_spectra(model, v_core, freq_index)
    table.contact = detect_contacts(table.magnitude, table.base_mean, table.t_mid_s)
    return table
