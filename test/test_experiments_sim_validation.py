"""The simulator reproduces the paper's observations (levels of section 4, Fig. 3 trend,
Fig. 4 superposition)."""

from __future__ import annotations

import numpy as np
import pytest

from egovib_research.experiments.sim_validation import (
    BAND_BINS,
    motion_levels,
    plot_fig3,
    plot_fig4,
    superposition_error,
    sweep_cell_stats,
)
from egovib_ros.sim.pr2 import MAX_SPEED
from egovib_ros.sim.scenarios import sweep_cells


@pytest.fixture(scope="module")
def full_map():
    return sweep_cell_stats(grid="full", dwell_s=1.0, seed=1)


@pytest.fixture(scope="module")
def subset_map():
    """The 41 single-joint cells + 40 random two-joint cells, 6 s each (sampling noise ~1 %)."""
    cells = sweep_cells("full")
    rng = np.random.default_rng(11)
    both = np.flatnonzero(np.all(cells != 0, axis=1))
    pick = np.concatenate(
        [sweep_cells("superposition"), cells[rng.choice(both, 40, replace=False)]]
    )
    return sweep_cell_stats(cells=pick, dwell_s=6.0, seed=1)


def test_levels_match_the_paper():
    levels = motion_levels(duration_s=40.0, max_speed=0.5, tap_rate_hz=1.0, seed=3)
    assert 0.15 <= levels["noise_mean_raw"] <= 0.35  # paper: 0.27 m/s^2
    assert levels["tap_peak_raw"] == pytest.approx(3.41, rel=0.15)  # paper: 3.41 m/s^2
    assert levels["peak_snr_raw_db"] == pytest.approx(22.0, abs=3.0)  # paper: 22 dB
    assert levels["stationary_background_mean"] < 0.25 * levels["noise_mean_raw"]
    assert levels["n_taps"] >= 25


def test_fig3_noise_grows_with_speed(full_map, tmp_path):
    total = (full_map.mean + full_map.std)[:, BAND_BINS].sum(axis=1)
    frac = np.abs(full_map.cells / np.asarray(MAX_SPEED))
    for joint in (0, 1):
        other = 1 - joint
        on_axis = frac[:, other] == 0
        speeds = frac[on_axis, joint]
        by_speed = np.array([total[on_axis][speeds == s].mean() for s in np.unique(speeds)])
        assert by_speed[-1] > 5 * by_speed[0] and by_speed[5] > 1.5 * by_speed[1]
        assert np.all(np.diff(by_speed) > -0.03 * by_speed[1:]), (
            by_speed
        )  # grows (saturates near 100 %)
    plot_fig3(full_map, tmp_path / "fig3.png")
    assert (tmp_path / "fig3.png").stat().st_size > 10_000


def test_fig4_base_superposes_within_5_percent(subset_map, full_map, tmp_path):
    err = superposition_error(subset_map)
    assert np.count_nonzero(~np.isnan(err)) == 81
    assert np.nanmax(err) <= 5.0
    assert np.nanmean(err) < 2.0
    full = superposition_error(full_map)  # all 441 cells, short dwell: only the figure is checked
    assert full.shape == (21, 21) and not np.isnan(full).any()
    plot_fig4(full, tmp_path / "fig4.png", "test")
    assert (tmp_path / "fig4.png").stat().st_size > 10_000
