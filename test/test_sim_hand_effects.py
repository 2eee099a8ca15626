"""Each effect of docs/INTERFACES.md section 5, switched on alone, changes the simulated
signal the way its name says; switched off (absent or strength 0) it leaves the base
output bit-identical."""

from __future__ import annotations

import numpy as np
import pytest

from egovib_research.experiments.sim_validation import (
    BAND_BINS,
    bandpass_combined,
    block_magnitudes,
    sweep_cell_stats,
)
from egovib_ros.sim import HandSimulator, SimParams
from egovib_ros.sim.pr2 import EFFECT_NAMES, GRIPPER_GAP_RANGE_M, MAX_SPEED

FS = 3000
FIELDS = (
    "sensor",
    "contact",
    "ego",
    "joint_stamps_ns",
    "joint_position",
    "joint_velocity",
    "tap_onsets_ns",
)


@pytest.fixture(scope="module")
def params():
    return SimParams.load()


def run(params, command, seconds, effects=None, seed=5, taps=0.0):
    sim = HandSimulator(params, seed=seed, effects=effects, tap_rate_hz=taps)
    if callable(command):
        t = np.arange(int(seconds * FS)) / FS
        return sim.step(len(t), commands=command(t))
    sim.set_command(command)
    return sim.step(int(seconds * FS))


def band_rms(x: np.ndarray, width: int) -> np.ndarray:
    """Moving rms of the band-passed sum of axes."""
    bp = bandpass_combined(x)
    return np.sqrt(np.convolve(bp**2, np.ones(width) / width, mode="same"))


@pytest.mark.parametrize("name", EFFECT_NAMES)
def test_strength_zero_is_bit_identical(params, name):
    def command(t):
        return np.column_stack(
            [2.5 * np.sin(2 * np.pi * 0.5 * t), 0.03 * np.cos(2 * np.pi * 0.4 * t)]
        )

    base = run(params, command, 3.0, taps=2.0)
    off = run(params, command, 3.0, effects={name: 0.0}, taps=2.0)
    for field in FIELDS:
        np.testing.assert_array_equal(getattr(off, field), getattr(base, field), err_msg=field)
    on = run(params, command, 3.0, effects={name: 0.5}, taps=2.0)
    changed = [f for f in FIELDS if not np.array_equal(getattr(on, f), getattr(base, f))]
    assert changed == (["joint_stamps_ns"] if name == "timing" else ["sensor", "ego"])


def test_position_spectrum_depends_on_wrist_angle(params):
    speed = 0.5 * MAX_SPEED[0]
    angle_of_max = params.position_phase_rad
    levels = {}
    for s in (0.0, 0.5):
        chunk = run(params, [speed, 0.0], 12.0, effects={"position": s} if s else None)
        mags = block_magnitudes(bandpass_combined(chunk.sensor))[:, BAND_BINS].sum(axis=1)
        angle = chunk.true_position[32::32, 0][: len(mags)]
        near = np.cos(angle - angle_of_max)
        levels[s] = mags[near > 0.9].mean() / mags[near < -0.9].mean()
    assert 0.9 < levels[0.0] < 1.1
    assert levels[0.5] > 2.0  # (1 + 0.5) / (1 - 0.5) = 3 for the wrist source


def test_position_gripper_gap_dependence(params):
    chunk = run(params, [0.0, 0.5 * MAX_SPEED[1]], 10.0, effects={"position": 0.8})
    gap = chunk.true_position[:, 1] / GRIPPER_GAP_RANGE_M[1]
    level = band_rms(chunk.ego, 96)
    steady = np.abs(np.abs(chunk.true_velocity[:, 1]) - 0.5 * MAX_SPEED[1]) < 1e-4
    wide, narrow = level[steady & (gap > 0.8)].mean(), level[steady & (gap < 0.2)].mean()
    assert wide / narrow > 1.4  # (1 + 0.8 * 0.4) / (1 - 0.8 * 0.4) ~ 1.9


def _eq6_error(cells, effects, params):
    stats = sweep_cell_stats(params=params, cells=cells, dwell_s=1.5, effects=effects)
    mu, sd = stats.mean[:, BAND_BINS], stats.std[:, BAND_BINS]
    n6 = mu[1] + mu[2] - mu[0] + np.sqrt(sd[1] ** 2 + sd[2] ** 2 + sd[0] ** 2)
    obs = mu[3] + sd[3]
    return 100 * abs(n6.sum() - obs.sum()) / obs.sum()


def test_coupling_breaks_superposition_at_speed(params):
    w, g = MAX_SPEED
    fast = np.array([[0, 0], [w, 0], [0, g], [w, g]])
    slow = np.array([[0, 0], [0.2 * w, 0], [0, g], [0.2 * w, g]])
    base = _eq6_error(fast, None, params)
    coupled_fast = _eq6_error(fast, {"coupling": 1.0}, params)
    coupled_slow = _eq6_error(slow, {"coupling": 1.0}, params)
    assert base < 5.0
    assert 10.0 < coupled_fast < 25.0
    assert coupled_slow < coupled_fast / 2  # grows with wrist speed


def test_acceleration_adds_vibration_at_speed_changes(params):
    # wrist reverses between +/-50 % every 0.5 s: large |acceleration| around each reversal
    def command(t):
        return np.column_stack([np.where((t // 0.5) % 2 == 0, 1.5, -1.5), np.zeros_like(t)])

    acc = {}
    for s in (0.0, 1.0):
        chunk = run(params, command, 6.0, effects={"acceleration": s} if s else None)
        level = band_rms(chunk.ego, 96)
        a = np.abs(np.gradient(chunk.true_velocity[:, 0])) * FS
        acc[s] = (level[a > 40].mean(), level[a < 1].mean())
    assert acc[0.0][0] < acc[0.0][1]  # base: slower around a reversal -> quieter
    assert acc[1.0][0] > 1.3 * acc[0.0][0]  # effect: reversals get louder
    assert acc[1.0][0] / acc[1.0][1] > acc[0.0][0] / acc[0.0][1] + 0.2
    assert acc[1.0][1] == pytest.approx(acc[0.0][1], rel=0.02)  # steady motion unchanged


def _lag_joint_states_vs_vibration(chunk) -> float:
    """Time from the vibration change to the reported joint-velocity change, for a
    0 -> 2 rad/s step at 1 s."""
    level = band_rms(chunk.sensor, 48)
    steady = level[int(2.0 * FS) :].mean()
    t_accel = chunk.sensor_stamps_ns / 1e9
    t_vib = t_accel[np.argmax((level > 0.5 * steady) & (t_accel > 0.9))]
    js_speed = np.abs(chunk.joint_velocity[:, 0])
    t_js = chunk.joint_stamps_ns[np.argmax(js_speed > 0.5 * 2.0)] / 1e9
    return t_js - t_vib


@pytest.mark.parametrize("strength", [0.03, -0.02])
def test_timing_lag_equals_strength(params, strength):
    def command(t):
        return np.column_stack([np.where(t >= 1.0, 2.0, 0.0), np.zeros_like(t)])

    base = _lag_joint_states_vs_vibration(run(params, command, 3.0))
    shifted = _lag_joint_states_vs_vibration(
        run(params, command, 3.0, effects={"timing": strength})
    )
    assert shifted - base == pytest.approx(strength, abs=1e-4)
    assert abs(base) < 0.025  # in sync (within the controller's rise time) without the effect


def test_drift_changes_level_at_fixed_velocity(params):
    command = [0.5 * MAX_SPEED[0], 0.5 * MAX_SPEED[1]]
    ratios = {}
    for s in (0.0, 1.0):
        chunk = run(params, command, 40.0, effects={"drift": s} if s else None)
        bp = bandpass_combined(chunk.sensor)
        ratios[s] = np.sqrt(np.mean(bp[-5 * FS :] ** 2) / np.mean(bp[FS : 6 * FS] ** 2))
    assert 0.93 < ratios[0.0] < 1.07
    expected = (1 + 37.5 / 60) / (1 + 3.5 / 60)
    assert ratios[1.0] == pytest.approx(expected, rel=0.1)
