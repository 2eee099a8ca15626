"""egovib_ros.gap.metric: the gap of a perfect model is the floor, a gain error raises it by its
decibels and decomposes over labels, the sign-flip test sees a real improvement only.

Tables: gaptables.synthetic_table (known effects, Rayleigh scatter).
"""

from __future__ import annotations

import numpy as np
import pytest
from gaptables import synthetic_table

from egovib_ros.gap import metric


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
