"""gap.baseline: the velocity-only baseline on synthetic block tables whose expected spectrum
is known (test/gaptables.py: model mean x a known factor x Rayleigh scatter of unit mean).
Fitted to a process with a pure velocity structure it leaves no misfit beyond the scatter;
what it cannot represent (position) stays in its residual."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from gaptables import VMAX, synthetic_table
from hypothesis import given
from hypothesis import strategies as st
from scipy import sparse

from egovib_ros.gap import metric
from egovib_ros.gap.baseline import (
    SCALE_FLOOR,
    SMOOTH_BLOCKS,
    _row_products,
    _solve,
    coarse_hats,
    coarse_knots,
    fit_baseline,
    lag_residual,
    simulator_cells,
)
from egovib_ros.gap.diagnose import time_split
from egovib_ros.gap.features import hat_matrix, motion_features

#: E|Y|^2 / (E|Y|)^2 of a Rayleigh magnitude: 4 / pi.
RAYLEIGH_POWER = 4.0 / np.pi


def db(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 20.0 * np.log10(a / b)


@pytest.fixture(scope="module")
def miscalibrated():
    """A velocity-only process 6 dB louder than the model says; fitted on the first 60 %."""
    table = synthetic_table(gain=2.0, seed=3, duration_s=30.0)
    train, heldout, _ = time_split(table, 0.6)
    return table, train, heldout, fit_baseline(table, train)


def test_a_velocity_only_process_leaves_no_misfit_beyond_the_scatter(miscalibrated):
    table, train, heldout, base = miscalibrated
    truth = 2.0 * table.base_mean  # the process's expected magnitude
    rows = np.flatnonzero(heldout)
    windows = metric.make_windows(len(rows), metric.DEFAULT_WINDOW_BLOCKS)

    def gap(predicted):
        return metric.gap_db(
            metric.window_errors_db(table.magnitude[rows], predicted[rows], windows)
        )

    assert gap(table.base_mean) > 5.5  # the simulator's model as it is: 6 dB too quiet
    # held out, the baseline scores within 0.3 dB of the process's own expected spectrum
    assert gap(base.magnitude) < gap(truth) + 0.3
    # block by block it is within a dB of the truth, mean and power alike
    assert np.sqrt(np.mean(db(base.magnitude[heldout], truth[heldout]) ** 2)) < 1.0
    power_ratio = base.power[heldout] / (RAYLEIGH_POWER * truth[heldout] ** 2)
    assert np.median(power_ratio) == pytest.approx(1.0, abs=0.05)
    # a moving joint adds power: cells are non-negative, and the cell at rest is carried by c(f)
    assert np.all(base.cell_power >= 0.0) and np.all(base.rest_power > 0.0)
    for j, knots in enumerate(table.knots):
        np.testing.assert_array_equal(base.cell_power[j, np.flatnonzero(knots == 0.0)], 0.0)
    assert base.info["cells_per_joint"] == [len(k) for k in table.knots]


def test_the_baseline_takes_the_recordings_level_not_the_simulators(miscalibrated):
    """The same data 6 dB louder: the prediction is 6 dB louder, nothing else changes
    (the simulator's spectra only shape the prior, scaled to the recording's level)."""
    table, train, _, base = miscalibrated
    louder = fit_baseline(dataclasses.replace(table, magnitude=2.0 * table.magnitude), train)
    np.testing.assert_allclose(louder.magnitude, 2.0 * base.magnitude, rtol=1e-6)
    np.testing.assert_allclose(louder.power, 4.0 * base.power, rtol=1e-6)


def test_only_the_training_rows_are_fitted(miscalibrated):
    table, train, heldout, base = miscalibrated
    magnitude = table.magnitude.copy()
    magnitude[heldout] *= 10.0  # whatever happens in the held-out part
    other = fit_baseline(dataclasses.replace(table, magnitude=magnitude), train)
    np.testing.assert_allclose(other.magnitude, base.magnitude, rtol=1e-9)
    np.testing.assert_allclose(other.power, base.power, rtol=1e-9)


def test_a_position_effect_stays_in_the_residual():
    """The baseline is velocity only: a gain 1 + 0.4 cos(angle - 0.7) of the wrist is not
    absorbed; the held-out log residual follows it with the slope log(1 + 0.4 c) has on c."""
    c = np.cos(np.linspace(0.0, 2.0 * np.pi, 1001))
    expected = np.polyfit(c, np.log1p(0.4 * c), 1)[0]  # 0.42
    for effect, slope in (("position", expected), ("none", 0.0)):
        table = synthetic_table(effect, 0.4, seed=5, duration_s=30.0)
        train, heldout, _ = time_split(table, 0.6)
        base = fit_baseline(table, train)
        residual = np.mean(np.log(table.magnitude / base.magnitude), axis=1)
        angle = np.cos(table.position[heldout, 0] - 0.7)
        fitted = np.polyfit(angle, residual[heldout], 1)[0]
        assert fitted == pytest.approx(slope, abs=0.1), effect


def test_the_simulator_cells_are_the_models_power_with_one_joint_moving():
    """Known from the synthetic model's formula: mean = 0.05 + 1.5 |v_w| / 3 s_w(f) +
    |v_g| / 0.04 s_g(f), bell-shaped bands s at 300 and 600 Hz."""
    table = synthetic_table(duration_s=5.0)
    rest, cells = simulator_cells(table)
    f = table.freqs_hz
    bands = (1.5 * np.exp(-(((f - 300.0) / 120.0) ** 2)), np.exp(-(((f - 600.0) / 120.0) ** 2)))
    np.testing.assert_allclose(rest, 0.05**2, rtol=1e-9)
    for j, grid in enumerate(coarse_knots(table)):
        mean = 0.05 + (np.abs(grid) / VMAX[j])[:, None] * bands[j][None, :]
        np.testing.assert_allclose(cells[j, : len(grid)], mean**2 - 0.05**2, atol=1e-12)


def test_coarse_cells_are_exact_combinations_of_the_fine_ones():
    table = synthetic_table(duration_s=5.0)
    values = np.random.default_rng(0).uniform(-1.1, 1.1, 500)
    for fine, coarse in zip(table.knots, coarse_knots(table)):
        v = values * np.max(np.abs(coarse))
        np.testing.assert_allclose(
            hat_matrix(v, fine) @ hat_matrix(fine, coarse), hat_matrix(v, coarse), atol=1e-12
        )
    # the table's trajectory features, re-expressed on the model grid, are the grid's own
    direct, _, _ = motion_features(
        table.joints, table.t_first_s, table.t_last_s, 0.0, coarse_knots(table), table.model.window
    )
    np.testing.assert_allclose(coarse_hats(table, table.hats), direct, atol=1e-12)


def test_the_lag_residual_is_smallest_at_the_lag_in_the_data():
    """Joint states stamped 50 ms after the vibration they describe: re-matched at +50 ms
    the baseline fits best."""
    table = synthetic_table("timing", 0.05, seed=5, duration_s=30.0)
    rows = np.flatnonzero(~table.contact)[::2]
    prior = simulator_cells(table)
    lags = np.array([-0.05, -0.025, 0.0, 0.025, 0.05, 0.075, 0.1])
    residual = [lag_residual(table, rows, float(lag), prior) for lag in lags]
    assert lags[int(np.argmin(residual))] == 0.05
    assert residual[2] > residual[4]  # in sync is worse than the true lag


@given(
    seed=st.integers(0, 2**32 - 1),
    n_rows=st.integers(0, 60),
    n_par=st.integers(1, 12),
    n_bins=st.integers(1, 5),
    per_row=st.integers(1, 4),
)
def test_every_bin_solved_at_once_equals_each_bin_solved_alone(
    seed, n_rows, n_par, n_bins, per_row
):
    """_solve's Gram matrices from the rows' outer products and its batched solve give each
    bin's penalised weighted least squares, as a dense per-bin solve does (rows with a few
    non-zeros, duplicate entries, empty rows and no rows at all included)."""
    rng = np.random.default_rng(seed)
    rows = np.repeat(np.arange(n_rows), per_row)
    cols = rng.integers(0, n_par, len(rows))  # may repeat within a row: summed
    xt = sparse.csr_matrix((rng.random(len(rows)), (rows, cols)), shape=(n_rows, n_par))
    yn, weights = rng.random((n_rows, n_bins)), rng.random((n_rows, n_bins)) + 0.1
    prior, scale = rng.random((n_bins, n_par)), rng.random((n_bins, n_par)) + 0.05
    n_smooth = max(n_par - 2, 0)
    d2 = np.zeros((n_smooth, n_par))
    centres = np.full((n_smooth, 3), -1)
    for r in range(n_smooth):
        d2[r, r : r + 3] = (1.0, -2.0, 1.0)
        centres[r] = (r, r + 1, r + 2) if r % 2 else (r, -1, r + 2)
    got = _solve(xt, _row_products(xt), yn, weights, prior, 0.3, scale, d2, centres)
    x = xt.toarray()
    for f in range(n_bins):
        lhs = x.T @ (weights[:, f, None] * x) + np.diag(0.3 / scale[f] ** 2)
        rhs = x.T @ (weights[:, f] * yn[:, f]) + 0.3 / scale[f] ** 2 * prior[f]
        if n_smooth:
            local = np.max(np.where(centres >= 0, scale[f][np.maximum(centres, 0)], 0.0), axis=1)
            ds = d2 / np.maximum(local, SCALE_FLOOR)[:, None]
            lhs += SMOOTH_BLOCKS * ds.T @ ds
        np.testing.assert_allclose(got[f], np.linalg.solve(lhs, rhs), rtol=1e-9, atol=1e-9)
