"""Tests of egovib_ros.sim.scenarios: sweeps and random smooth motion."""

from __future__ import annotations

import numpy as np
import pytest

from egovib_ros.errors import ConfigError
from egovib_ros.sim import motion_commands, simulate_motion, simulate_sweep, sweep_cells
from egovib_ros.sim.pr2 import GRID_FRACTIONS, JOINT_NAMES, MAX_SPEED


def test_sweep_cells():
    full = sweep_cells("full")
    assert full.shape == (441, 2)
    assert len({tuple(c) for c in np.round(full / MAX_SPEED, 6)}) == 441
    sup = sweep_cells("superposition")
    assert sup.shape == (41, 2)
    assert np.all(np.count_nonzero(sup, axis=1) <= 1)
    np.testing.assert_allclose(np.unique(np.round(sup[:, 0] / MAX_SPEED[0], 6)), GRID_FRACTIONS)
    with pytest.raises(ConfigError):
        sweep_cells("half")


def test_simulate_sweep_recording():
    rec, truth = simulate_sweep(grid="superposition", dwell_s=0.2, settle_s=0.1, seed=4)
    assert len(rec.sensor) == 41 * 900
    assert rec.joint_names == JOINT_NAMES
    assert rec.commands.shape == (41, 2) and len(rec.command_stamps_ns) == 41
    np.testing.assert_array_equal(rec.commands, sweep_cells("superposition"))
    # each command is reached: mean reported |velocity| over the last 0.1 s of each cell
    js = rec.joint_stamps_ns
    for stamp, cmd in zip(rec.command_stamps_ns, rec.commands):
        sel = (js > stamp + 0.2e9) & (js < stamp + 0.3e9)
        np.testing.assert_allclose(
            np.abs(rec.joint_velocity[sel]).mean(axis=0),
            np.abs(cmd),
            atol=0.02 * np.asarray(MAX_SPEED).max() + 1e-3,
        )
    np.testing.assert_allclose(rec.sensor, rec.sensor)  # finite
    assert truth == {"seed": 4, "effects": {}, "tap_onsets_ns": []}


def test_motion_commands_smooth_and_bounded():
    t, cmds = motion_commands(60.0, 0.5, seed=1)
    assert np.all(np.abs(cmds) <= 0.5 * np.asarray(MAX_SPEED) + 1e-12)
    frac = np.abs(cmds) / np.asarray(MAX_SPEED)
    assert frac.max() > 0.4  # uses the allowed range
    step = np.abs(np.diff(cmds, axis=0)).max(axis=0) / np.asarray(MAX_SPEED)
    assert np.all(step < 0.1)  # low-pass filtered: no jumps at 50 Hz
    t2, cmds2 = motion_commands(60.0, 0.5, seed=1)
    np.testing.assert_array_equal(cmds, cmds2)
    with pytest.raises(ConfigError):
        motion_commands(1.0, 1.5, seed=0)


def test_simulate_motion_with_taps_and_truth():
    rec, truth = simulate_motion(
        duration_s=8.0, max_speed=0.5, tap_rate_hz=1.0, seed=2, effects={"position": 0.3}
    )
    assert len(rec.sensor) == 24000
    assert truth["seed"] == 2 and truth["effects"] == {"position": 0.3}
    onsets = np.asarray(truth["tap_onsets_ns"])
    assert 3 <= len(onsets) <= 16
    assert np.all(np.isin(onsets, rec.sensor_stamps_ns))
    k = np.searchsorted(rec.sensor_stamps_ns, onsets)
    assert np.all(np.abs(rec.contact[k + 5]).sum(axis=1) > 0)
    # commands topic: within the speed limit; the reported joint speeds follow them
    assert np.all(np.abs(rec.commands) <= 0.5 * np.asarray(MAX_SPEED) + 1e-12)
    assert np.abs(rec.joint_velocity[:, 0]).max() > 0.3
