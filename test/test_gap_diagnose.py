"""Gap metric, effect regressors and significance test on a synthetic spectral process.

The process: a real NoiseModel (grid of mean/std spectra, separable in the two joints)
and smooth random joint motion; each block's observed magnitude is the true expected
magnitude times Rayleigh scatter (unit mean).  "True" expected magnitude = model mean
times a known effect, so the right answers are known without the simulator.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from egovib_ros.core.blocks import analysis_window
from egovib_ros.core.noise_model import NoiseModel
from egovib_ros.gap import metric
from egovib_ros.gap.diagnose import diagnose
from egovib_ros.gap.features import (
    BlockTable,
    JointSeries,
    _joint_block_means,
    _model_lookup,
    attach_motion,
    axis_spectra,
    in_band_bins,
)

VMAX = np.array([3.0, 0.04])


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
) -> BlockTable:
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
    joints = JointSeries(t_s=t_joint, position=pos, velocity=vel, acceleration=acc)
    n_blocks = int((duration_s * 3000 - 64) // 32)
    t_first = np.arange(n_blocks) * 32 / 3000.0
    t_last = t_first + 63 / 3000.0
    freq_index = in_band_bins(model)
    true_lag = strength if effect == "timing" else 0.0
    # The vibration follows the true motion; the reported joint states are stamped true_lag late.
    v_true, p_true, a_true = _joint_block_means(joints, t_first, t_last, true_lag)
    mean_true, _ = _model_lookup(model, v_true, freq_index)
    factor = np.full(n_blocks, gain)
    if effect == "position":
        factor *= 1.0 + strength * np.cos(p_true[:, 0] - 0.7)
    elif effect == "coupling":
        # extra vibration power in the gripper's band growing with both speeds
        # (joints no longer add)
        f = model.freqs_hz[freq_index]
        extra = strength * (np.abs(v_true[:, 0]) / 3.0) * (np.abs(v_true[:, 1]) / 0.04)
        mean_true = np.sqrt(
            mean_true**2 + (extra[:, None] * np.exp(-(((f - 600.0) / 120.0) ** 2))) ** 2
        )
    elif effect == "acceleration":
        factor *= 1.0 + strength * np.abs(a_true[:, 0]) / np.percentile(np.abs(a_true[:, 0]), 95)
    elif effect == "drift":
        factor *= 1.0 + strength * t_first / 60.0
    magnitude = mean_true * factor[:, None] * rng.rayleigh(np.sqrt(2 / np.pi), mean_true.shape)
    v0, p0, a0 = _joint_block_means(joints, t_first, t_last, 0.0)
    mean0, std0 = _model_lookup(model, v0, freq_index)
    axis0, zero0 = axis_spectra(model, v0, freq_index)
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
        axis_mean=axis0,
        zero_mean=zero0,
    )
    return attach_motion(table)


def test_perfect_model_scores_at_floor():
    table = synthetic_table()
    rows = np.arange(table.n_blocks)
    windows = metric.make_windows(len(rows), 32)
    e = metric.window_errors_db(table.magnitude, table.base_mean, windows)
    gap, floor = metric.gap_db(e), metric.floor_db(table.magnitude, table.base_mean, windows)
    assert floor > 0.3
    assert abs(gap - floor) < 0.15 * floor


def test_gain_error_raises_gap_and_decomposes():
    table = synthetic_table(gain=2.0)
    windows = metric.make_windows(table.n_blocks, 32)
    e = metric.window_errors_db(table.magnitude, table.base_mean, windows)
    assert metric.gap_db(e) == pytest.approx(6.0, abs=0.5)
    labels = np.arange(windows.n_windows) % 3
    share, counts = metric.contributions(e, labels, 3)
    assert share.sum() == pytest.approx(metric.gap_db(e) ** 2)
    assert counts.sum() == windows.n_windows


def test_signflip_pvalue_detects_improvement_and_not_noise():
    rng = np.random.default_rng(1)
    base = rng.normal(0, 1.0, (60, 13)) + 0.8
    better = rng.normal(0, 1.0, (60, 13))
    assert metric.paired_signflip_pvalue(base, better) < 0.001
    same = rng.normal(0, 1.0, (60, 13))
    assert metric.paired_signflip_pvalue(same, rng.normal(0, 1.0, (60, 13))) > 0.01


def test_miscalibrated_model_resolved_by_refit_gives_none():
    diag = diagnose(synthetic_table(gain=2.0, seed=3))
    assert diag.gaps["sim_as_is"] > 5.0
    assert diag.gaps["refit"] < diag.floor + 0.3
    assert diag.verdict == "none"


@pytest.mark.parametrize(
    "effect,strength,duration",
    [
        ("position", 0.4, 40.0),
        ("coupling", 5.0, 90.0),
        ("acceleration", 0.5, 40.0),
        ("drift", 0.5, 40.0),
        ("timing", 0.05, 40.0),
    ],
)
def test_effect_is_identified(effect, strength, duration):
    diag = diagnose(synthetic_table(effect, strength, seed=5, duration_s=duration))
    assert diag.verdict == effect, diag.candidates
    assert diag.gaps[effect] < diag.floor + 1.0
    if effect == "timing":
        assert diag.models["timing"].parameters["lag_s"] == pytest.approx(strength, abs=0.004)
