"""Per-block joint velocity matched by stamps (issue 2)."""

import numpy as np

from egovib_ros.core import HELD, MATCHED, MISSING, block_mean_velocity


def test_mean_over_span_hold_and_missing():
    t = np.array([0, 1, 2, 3, 10, 11], dtype=np.int64) * 1_000_000
    v = np.array([[1, 10], [2, 20], [3, 30], [4, 40], [5, 50], [6, 60]], dtype=float)
    first = np.array([0, 4, 40, 1], dtype=np.int64) * 1_000_000
    last = np.array([2, 5, 41, 3], dtype=np.int64) * 1_000_000
    mean, steady, status = block_mean_velocity(t, v, first, last, max_hold_ns=5_000_000)
    np.testing.assert_allclose(mean[0], [2, 20])
    np.testing.assert_allclose(mean[1], [4, 40])  # none inside: hold stamp 3 ms (1 ms old)
    assert np.isnan(mean[2]).all()  # last state 29 ms old: missing
    np.testing.assert_allclose(mean[3], [3, 30])
    assert status.tolist() == [MATCHED, HELD, MISSING, MATCHED]
    # Steadiness: first half [1] vs second half [2, 3] -> |1 - 2.5| = 1.5
    np.testing.assert_allclose(steady[0], [1.5, 15.0])


def test_one_block_path_is_bit_identical_to_vectorised():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.integers(900_000, 1_100_000, size=5000)).astype(np.int64)
    v = rng.normal(size=(5000, 2)) * [3.0, 0.04]
    first = np.sort(rng.integers(t[0], t[-1], size=300)).astype(np.int64)
    last = first + 21_000_000
    many = block_mean_velocity(t, v, first, last, max_hold_ns=50_000_000, with_steadiness=False)[0]
    for b in range(0, 300, 7):
        one = block_mean_velocity(
            t, v, first[b : b + 1], last[b : b + 1], max_hold_ns=50_000_000, with_steadiness=False
        )[0]
        np.testing.assert_array_equal(one[0], many[b])
