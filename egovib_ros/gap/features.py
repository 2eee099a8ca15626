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
from numpy.lib.stride_tricks import sliding_window_view
from scipy import ndimage, signal

from egovib_ros.core.filters import BandPass, channel_matrix
from egovib_ros.core.velocity import block_mean_velocity
from egovib_ros.errors import BagError, ModelFileError

NS = 1_000_000_000
#: A block counts as contact if its band energy exceeds the local typical level by this
#: many robust standard deviations (log domain); taps are ~20 dB above ego-vibration.
CONTACT_Z = 4.0
#: Blocks on either side of a flagged block also dropped (tap tails, 10-30 ms).
CONTACT_DILATE = 2
#: Savitzky-Golay window for joint accelerations (s): long enough to average encoder
#: quantisation, short compared with the motion.
ACCEL_SMOOTH_S = 0.031


@dataclass
class JointSeries:
    """Joint-state streams on their own clock (seconds since the first accel sample)."""

    t_s: np.ndarray               # (M,)
    position: np.ndarray          # (M, J)
    velocity: np.ndarray          # (M, J)
    acceleration: np.ndarray      # (M, J) smoothed derivative of velocity


@dataclass
class BlockTable:
    """Everything the diagnosis needs about the blocks of one recording."""

    t_first_s: np.ndarray         # (B,) block start, s since the first accel sample
    t_last_s: np.ndarray          # (B,)
    magnitude: np.ndarray         # (B, F) observed |Y_b(f)|, in-band bins
    freqs_hz: np.ndarray          # (F,)
    velocity: np.ndarray          # (B, J) block mean joint velocity (lag 0)
    position: np.ndarray          # (B, J)
    acceleration: np.ndarray      # (B, J) block mean |joint acceleration|
    base_mean: np.ndarray         # (B, F) model mean magnitude at the block velocity
    base_std: np.ndarray          # (B, F) model std (for the denoising consequence)
    contact: np.ndarray           # (B,) bool, detected contact (excluded)
    vmax: np.ndarray              # (J,) largest grid speed per joint
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
        pick = {name: getattr(self, name)[rows] for name in
                ("t_first_s", "t_last_s", "magnitude", "velocity", "position", "acceleration",
                 "base_mean", "base_std", "contact")}
        return replace(self, **pick)

    def at_lag(self, lag_s: float) -> "BlockTable":
        """The table with joint states re-matched as if their stamps were `lag_s` late.

        Joint time is corrected to stamp - lag_s, i.e. a positive lag means the joint
        states are stamped later than the vibration they describe.
        """
        if self.joints is None or self.model is None:
            raise ValueError("table has no joint series to re-match")
        velocity, position, acceleration = _joint_block_means(self.joints, self.t_first_s, self.t_last_s, lag_s)
        mean, std = _model_lookup(self.model, velocity, self.freq_index)
        return replace(self, velocity=velocity, position=position, acceleration=acceleration,
                       base_mean=mean, base_std=std)

    freq_index: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0, dtype=np.intp))


def block_spectra(accel: np.ndarray, model) -> tuple[np.ndarray, np.ndarray]:
    """|rfft(window * block)| of the band-passed sum of axes, core framing.

    Returns (spectra (B, n_bins), first-sample index of each block).
    """
    x = channel_matrix(accel, "combined")
    band = BandPass(sample_rate_hz=model.sample_rate_hz, band_hz=model.band_hz,
                    order=model.band_order, n_channels=1)
    y = band.process(x)[:, 0]
    if len(y) < model.block_length:
        return np.zeros((0, model.block_length // 2 + 1)), np.zeros(0, dtype=np.intp)
    frames = sliding_window_view(y, model.block_length)[::model.hop]
    return np.abs(np.fft.rfft(frames * model.window, axis=1)), np.arange(len(frames)) * model.hop


def in_band_bins(model) -> np.ndarray:
    """Indices of the DFT bins inside the model's band-pass."""
    f = model.freqs_hz
    return np.flatnonzero((f >= model.band_hz[0]) & (f <= model.band_hz[1]))


def _interval_means(t: np.ndarray, values: np.ndarray, t0: np.ndarray, t1: np.ndarray) -> np.ndarray:
    """Mean of a sampled series over [t0, t1] (trapezoid integral of the linear interpolant)."""
    dt = np.diff(t)
    cum = np.concatenate([np.zeros((1, values.shape[1])),
                          np.cumsum(0.5 * (values[1:] + values[:-1]) * dt[:, None], axis=0)])

    def integral(tq: np.ndarray) -> np.ndarray:
        tq = np.clip(tq, t[0], t[-1])
        i = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 2)
        frac = (tq - t[i])[:, None]
        slope = (values[i + 1] - values[i]) / np.maximum(dt[i], 1e-12)[:, None]
        return cum[i] + values[i] * frac + 0.5 * slope * frac ** 2

    span = np.maximum(t1 - t0, 1e-9)[:, None]
    return (integral(t1) - integral(t0)) / span


def _joint_block_means(joints: JointSeries, t_first: np.ndarray, t_last: np.ndarray, lag_s: float):
    t = joints.t_s - lag_s
    velocity = _interval_means(t, joints.velocity, t_first, t_last)
    position = _interval_means(t, joints.position, t_first, t_last)
    acceleration = _interval_means(t, np.abs(joints.acceleration), t_first, t_last)
    return velocity, position, acceleration


def _model_lookup(model, velocity: np.ndarray, freq_index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ch = model.channel_indices(("combined",))
    mean, _ = model.estimate(velocity, ch, include_std=False)
    full, _ = model.estimate(velocity, ch, include_std=True)
    mean = mean[:, 0, freq_index]
    return mean, np.maximum(full[:, 0, freq_index] - mean, 0.0)


def detect_contacts(magnitude: np.ndarray, predicted: np.ndarray, t_s: np.ndarray, *,
                    z: float = CONTACT_Z, dilate: int = CONTACT_DILATE) -> np.ndarray:
    """Flag blocks whose band energy is an outlier above the model's prediction.

    The log energy ratio is compared with its running median over ~2 s (so a
    mis-calibrated or drifting model does not flag everything) using a robust
    (MAD) scale; flagged blocks are widened by `dilate` blocks on each side.
    """
    ratio = 10.0 * np.log10(np.maximum(np.sum(magnitude ** 2, axis=1), 1e-300)
                            / np.maximum(np.sum(predicted ** 2, axis=1), 1e-300))
    if len(ratio) < 5:
        return np.zeros(len(ratio), dtype=bool)
    dt = np.median(np.diff(t_s)) if len(t_s) > 1 else 0.01
    size = int(max(5, min(len(ratio), round(2.0 / max(dt, 1e-6))))) | 1
    local = ndimage.median_filter(ratio, size=size, mode="nearest")
    resid = ratio - local
    scale = 1.4826 * np.median(np.abs(resid - np.median(resid))) + 1e-9
    flagged = resid > z * scale
    if dilate > 0 and flagged.any():
        flagged = ndimage.binary_dilation(flagged, iterations=dilate)
    return flagged


def build_table(rec, model, *, max_hold_s: float = 0.05, source: str = "bag") -> BlockTable:
    """Blocks, spectra, model prediction and covariates of a Recording for a NoiseModel."""
    if model.n_joints != len(rec.joint_names):
        raise ModelFileError(f"{model.provenance.get('path', 'noise model')}: model has {model.n_joints} joints "
                             f"{list(model.joint_names)}, {source} has {list(rec.joint_names)}")
    if tuple(model.joint_names) != tuple(rec.joint_names):
        order = [list(rec.joint_names).index(n) if n in rec.joint_names else -1 for n in model.joint_names]
        if min(order) < 0:
            raise ModelFileError(f"{model.provenance.get('path', 'noise model')}: joints {list(model.joint_names)} "
                                 f"not in {source} joint_states {list(rec.joint_names)}")
    else:
        order = list(range(model.n_joints))
    if len(rec.accel_stamps_ns) < 4 * model.block_length:
        raise BagError(f"{source}: /accelerometer/raw has only {len(rec.accel_stamps_ns)} samples")
    if len(rec.joint_stamps_ns) < 10:
        raise BagError(f"{source}: /joint_states has only {len(rec.joint_stamps_ns)} messages")

    spectra, first = block_spectra(rec.accel, model)
    freq_index = in_band_bins(model)
    t0_ns = int(rec.accel_stamps_ns[0])
    accel_t = (rec.accel_stamps_ns - t0_ns) / NS
    t_first = accel_t[first]
    t_last = accel_t[first + model.block_length - 1]

    joint_t = (rec.joint_stamps_ns - t0_ns) / NS
    velocity = rec.joint_velocity[:, order]
    # Unwrap so a block mean of the continuous wrist angle never straddles a +-pi jump.
    position = np.unwrap(rec.joint_position[:, order], axis=0)
    window = int(round(ACCEL_SMOOTH_S / max(np.median(np.diff(joint_t)), 1e-6))) | 1
    window = max(window, 5)
    acceleration = signal.savgol_filter(velocity, window, 2, deriv=1, axis=0,
                                        delta=float(np.median(np.diff(joint_t))), mode="interp") \
        if len(velocity) > window else np.zeros_like(velocity)
    joints = JointSeries(t_s=joint_t, position=position, velocity=velocity, acceleration=acceleration)

    # Lag-0 velocity exactly as the core matches it (same as calibration and denoising).
    v_core, _, status = block_mean_velocity(rec.joint_stamps_ns, velocity,
                                            rec.accel_stamps_ns[first],
                                            rec.accel_stamps_ns[first + model.block_length - 1],
                                            max_hold_ns=int(max_hold_s * NS))
    valid = status != 2
    _, pos_b, acc_b = _joint_block_means(joints, t_first, t_last, 0.0)
    mean, std = _model_lookup(model, np.nan_to_num(v_core), freq_index)
    vmax = np.array([np.max(np.abs(g)) for g in model.grid])
    table = BlockTable(t_first_s=t_first, t_last_s=t_last, magnitude=spectra[:, freq_index],
                       freqs_hz=model.freqs_hz[freq_index], velocity=v_core, position=pos_b,
                       acceleration=acc_b, base_mean=mean, base_std=std,
                       contact=np.zeros(len(first), dtype=bool), vmax=vmax,
                       joint_names=tuple(model.joint_names), model=model, joints=joints,
                       freq_index=freq_index)
    table = table.subset(valid)
    table.contact = detect_contacts(table.magnitude, table.base_mean, table.t_mid_s)
    return table
