"""Block tables of a synthetic spectral process with known effects, for the gap tests.

The process: a real NoiseModel (grid of mean/std spectra, separable in the two joints)
and smooth random joint motion; each block's observed magnitude is the true expected
magnitude times Rayleigh scatter (unit mean).  "True" expected magnitude = model mean
times a known effect, so the right answers are known without the simulator.
"""

from __future__ import annotations

import functools

import numpy as np
from scipy import signal

from egovib_ros.core.blocks import analysis_window
from egovib_ros.core.noise_model import NoiseModel
from egovib_ros.gap.diagnose import Diagnosis, diagnose
from egovib_ros.gap.features import (
    REVERSAL_THRESHOLD,
    BlockTable,
    JointSeries,
    _joint_block_means,
    _model_lookup,
    attach_motion,
    in_band_bins,
    jerk_means,
    joint_period,
    savgol_window,
)

VMAX = np.array([3.0, 0.04])


def savgol_joint(t_s: np.ndarray, velocity: np.ndarray, *, deriv: int = 0) -> np.ndarray:
    """Velocity smoothed (deriv 0) or differentiated (deriv 1) by a quadratic
    Savitzky-Golay filter over features.ACCEL_SMOOTH_S; a series too short for it is returned
    as is (deriv 0) or as zeros (deriv 1): what `JointFeatures` computes slice by slice."""
    dt = joint_period(t_s)
    window = savgol_window(dt)
    if len(velocity) <= window:
        return velocity if deriv == 0 else np.zeros_like(velocity)
    return signal.savgol_filter(velocity, window, 2, deriv=deriv, axis=0, delta=dt, mode="interp")


def detect_reversals(
    t_s: np.ndarray, smooth_velocity: np.ndarray, vmax: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Per joint: times at which motion resumes opposite to the previous direction of motion
    (`JointFeatures`'s, in one piece)."""
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


def smoothed_series(t_s, position, velocity, acceleration) -> JointSeries:
    """A joint series with its smoothed velocity and reversal times, as JointFeatures gives."""
    smooth = savgol_joint(t_s, velocity)
    return JointSeries(
        t_s=t_s,
        position=position,
        velocity=velocity,
        acceleration=acceleration,
        smooth_velocity=smooth,
        reversals=detect_reversals(t_s, smooth, VMAX),
    )


def synthetic_model() -> NoiseModel:
    grid = tuple(np.round(np.arange(-10, 11) / 10.0, 10) * v for v in VMAX)
    f = np.fft.rfftfreq(64, 1 / 3000.0)
    sw = np.abs(grid[0])[:, None, None] / 3.0
    sg = np.abs(grid[1])[None, :, None] / 0.04
    shape_w = np.exp(-(((f - 300.0) / 120.0) ** 2))[None, None, :]
    shape_g = np.exp(-(((f - 600.0) / 120.0) ** 2))[None, None, :]
    mean = 0.05 + 1.5 * sw * shape_w + 1.0 * sg * shape_g
    mean = np.repeat(mean[:, :, None, :], 4, axis=2)
    return NoiseModel(
        grid=grid,
        joint_names=("wrist_roll", "gripper"),
        mean=mean,
        std=0.5 * mean,
        counts=np.full((21, 21), 100),
        window=analysis_window(64, 32),
    )


def synthetic_table(
    effect: str = "none",
    strength: float = 0.0,
    *,
    duration_s: float = 40.0,
    seed: int = 0,
    gain: float = 1.0,
    effects: dict[str, float] | None = None,
) -> BlockTable:
    """`effect` at `strength`, or several at once (`effects`: name -> strength). Beyond the
    vocabulary's names, "lines": the wrist's lines scaled by the gripper's speed, louder when
    both move the same way and quieter when opposite (a per-line signed interaction);
    "gripper_wear": the gripper's part louder over time (one joint's drift); "jerk": louder
    where the wrist's acceleration changes (a speed change starting or ending)."""
    effects = dict(effects) if effects is not None else {effect: strength}
    rng = np.random.default_rng(seed)
    model = synthetic_model()
    # Joint states at 1 kHz: low-pass random velocities up to 60 % of max speed.
    n = int(duration_s * 1000)
    t_joint = np.arange(n) / 1000.0
    sos = signal.butter(2, 1.0, fs=1000.0, output="sos")
    raw = rng.standard_normal((n, 2))
    vel = signal.sosfiltfilt(sos, raw, axis=0)
    vel = np.clip(
        0.5 * VMAX * vel / np.percentile(np.abs(vel), 95, axis=0), -0.9 * VMAX, 0.9 * VMAX
    )
    vel[:, 0] += 0.3  # the wrist keeps turning, so all angles are visited
    pos = np.cumsum(vel, axis=0) / 1000.0
    pos[:, 1] = 0.043 + 0.04 * np.sin(pos[:, 1] / 0.04 * 3)  # gripper gap stays in range
    acc = np.gradient(vel, t_joint, axis=0)
    joints = smoothed_series(t_joint, pos, vel, acc)
    n_blocks = int((duration_s * 3000 - 64) // 32)
    t_first = np.arange(n_blocks) * 32 / 3000.0
    t_last = t_first + 63 / 3000.0
    freq_index = in_band_bins(model)
    true_lag = effects.get("timing", 0.0)
    # The vibration follows the true motion; the reported joint states are stamped true_lag late.
    v_true, p_true, a_true = _joint_block_means(joints, t_first, t_last, true_lag)
    mean_true, _ = _model_lookup(model, v_true, freq_index)
    factor = np.full(n_blocks, gain)
    f = model.freqs_hz[freq_index]
    for effect, strength in effects.items():
        if effect == "position":
            factor *= 1.0 + strength * np.cos(p_true[:, 0] - 0.7)
        elif effect == "coupling":
            # extra vibration power in the gripper's band growing with both speeds
            # (joints no longer add)
            extra = strength * (np.abs(v_true[:, 0]) / 3.0) * (np.abs(v_true[:, 1]) / 0.04)
            mean_true = np.sqrt(
                mean_true**2 + (extra[:, None] * np.exp(-(((f - 600.0) / 120.0) ** 2))) ** 2
            )
        elif effect == "lines":
            # the wrist's part of the spectrum (its lines) times exp(+-s |v_g|): the sign of
            # the product of the directions
            wrist = (
                1.5 * (np.abs(v_true[:, 0]) / 3.0)[:, None] * np.exp(-(((f - 300.0) / 120.0) ** 2))
            )
            same = np.sign(v_true[:, 0]) * np.sign(v_true[:, 1])
            gain_w = np.exp(strength * same * np.abs(v_true[:, 1]) / 0.04)
            mean_true = mean_true + wrist * (gain_w[:, None] - 1.0)
        elif effect == "gripper_wear":
            # the gripper's part of the spectrum x (1 + s t / 60 s): one drive wearing in
            gripper = (np.abs(v_true[:, 1]) / 0.04)[:, None] * np.exp(-(((f - 600.0) / 120.0) ** 2))
            mean_true = mean_true + gripper * (strength * t_first / 60.0)[:, None]
        elif effect == "jerk":
            jerk = jerk_means(joints, t_first, t_last, true_lag)[:, 0]
            factor *= 1.0 + strength * np.minimum(jerk / np.percentile(jerk, 95), 3.0)
        elif effect == "acceleration":
            factor *= 1.0 + strength * np.abs(a_true[:, 0]) / np.percentile(
                np.abs(a_true[:, 0]), 95
            )
        elif effect == "drift":
            factor *= 1.0 + strength * t_first / 60.0
    magnitude = mean_true * factor[:, None] * rng.rayleigh(np.sqrt(2 / np.pi), mean_true.shape)
    v0, p0, a0 = _joint_block_means(joints, t_first, t_last, 0.0)
    mean0, std0 = _model_lookup(model, v0, freq_index)
    table = BlockTable(
        t_first_s=t_first,
        t_last_s=t_last,
        magnitude=magnitude,
        freqs_hz=model.freqs_hz[freq_index],
        velocity=v0,
        position=p0,
        acceleration=a0,
        base_mean=mean0,
        base_std=std0,
        contact=np.zeros(n_blocks, dtype=bool),
        vmax=VMAX,
        joint_names=("wrist_roll", "gripper"),
        model=model,
        joints=joints,
        freq_index=freq_index,
    )
    return attach_motion(table)


def diagnosed(
    effect: str = "none", strength: float = 0.0, *, seed: int = 0, duration_s: float = 40.0
) -> Diagnosis:
    """`diagnose` with the default options on `synthetic_table(effect, strength, ...)`, made
    once per test process: test_gap_diagnose, test_gap_advice and test_gap_writeback assert
    different things on the same diagnoses (seed 5, 40 s). Shared: read it, never change it
    (dataclasses.replace makes a changed copy)."""
    return _diagnosed(effect, float(strength), seed, float(duration_s))


@functools.cache
def _diagnosed(effect: str, strength: float, seed: int, duration_s: float) -> Diagnosis:
    # one key however the arguments were spelled (functools.cache keys on the call's form)
    return diagnose(synthetic_table(effect, strength, seed=seed, duration_s=duration_s))
