"""egovib_ros.gap.diagnose on synthetic block tables with a known effect (gaptables.py): a
miscalibrated model is resolved by the refit, each effect is identified and its parameter found.
"""

from __future__ import annotations

import numpy as np
import pytest
from gaptables import synthetic_table

from egovib_ros.errors import GapDataError
from egovib_ros.gap.diagnose import (
    DiagnosisOptions,
    blocked_folds,
    combined_floor,
    diagnose,
    forward_split,
    interleaved_splits,
    time_split,
)


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


def test_a_robot_whose_own_lag_is_beyond_the_scan_range_is_in_sync_at_it():
    # Joint states 150 ms late on the robot itself (its reference lag), beyond the +-0.1 s a
    # scan centred on zero covers: the scan is centred on the reference, so the robot is in
    # sync at its own lag and no timing effect is named.
    table = synthetic_table("timing", 0.15, seed=5, duration_s=30.0)
    diag = diagnose(table, DiagnosisOptions(reference_lag_s=0.15, effects=("timing",)))
    assert diag.sync_lag_s == pytest.approx(0.15, abs=0.005)
    assert diag.verdict == "none", diag.candidates


def test_splits_partition_the_clean_blocks_in_time():
    table = synthetic_table(duration_s=20.0)
    table.contact[100:160] = True
    clean = ~table.contact
    folds = blocked_folds(table, 5)
    assert len(folds) == 5
    held = np.sum([s.test for s in folds], axis=0)
    np.testing.assert_array_equal(held, clean.astype(int))  # every clean block held out once
    for s in folds:
        assert not (s.train & s.test).any() and np.array_equal(s.train | s.test, clean)
        tested = np.flatnonzero(s.test)
        span = np.arange(tested[0], tested[-1] + 1)
        assert np.all(s.test[span] | table.contact[span])  # one stretch of time
    (forward,) = forward_split(table, 0.6)
    train, heldout, split_s = time_split(table, 0.6)
    np.testing.assert_array_equal(forward.train, train)
    assert table.t_mid_s[train].max() < split_s <= table.t_mid_s[heldout].min()
    rotations = interleaved_splits(table, chunk_s=2.0, period=3)
    np.testing.assert_array_equal(np.sum([s.test for s in rotations], axis=0), clean.astype(int))
    chunk = np.floor((table.t_mid_s - table.t_mid_s[0]) / 2.0).astype(int)
    assert set(chunk[rotations[1].test] % 3) == {1}


def test_the_floor_is_the_smaller_finite_estimate():
    assert combined_floor({"block_ratio": 0.8, "window": 0.6}) == 0.6
    assert combined_floor({"block_ratio": float("nan"), "window": 0.7}) == 0.7
    assert np.isnan(combined_floor({"block_ratio": float("nan")}))


def test_a_forward_split_tests_only_the_later_part():
    table = synthetic_table(seed=2)
    diag = diagnose(table, DiagnosisOptions(train_fraction=0.6, effects=("drift",)))
    assert diag.split_info["train_s"] == pytest.approx(0.6 * np.ptp(table.t_mid_s))
    assert diag.heldout_rows.min() > 0.55 * table.n_blocks
    assert diag.verdict == "none" and set(diag.gaps) == {"sim_as_is", "refit", "drift"}
    assert diag.gaps["sim_as_is"] >= diag.gaps["refit"] - 0.1


def test_too_few_clean_blocks_are_refused():
    table = synthetic_table(duration_s=10.0)
    table.contact[:] = True
    table.contact[:300] = False
    with pytest.raises(GapDataError, match="too few no-contact blocks"):
        diagnose(table)


@pytest.mark.parametrize(
    "bad, named",
    [
        ({"folds": 1}, "folds"),
        ({"train_fraction": 1.0}, "train_fraction"),
        ({"alpha": 0.0}, "alpha"),
        ({"effects": ("friction",)}, "effects"),
        ({"effects": ()}, "effects"),
        ({"reference_lag_s": float("nan")}, "reference_lag_s"),
        ({"lag_tolerance_s": -0.001}, "lag_tolerance_s"),
        ({"window_blocks": 0}, "window_blocks"),
    ],
)
def test_options_are_checked_when_made_one_line_naming_the_setting(bad, named):
    with pytest.raises(ValueError) as raised:
        DiagnosisOptions(**bad)
    message = str(raised.value)
    assert "\n" not in message and message.startswith(f"gap options: {named} must be")


def test_options_are_keyword_only_and_effects_a_tuple():
    with pytest.raises(TypeError):
        DiagnosisOptions(5)
    assert DiagnosisOptions(effects=["drift", "timing"]).effects == ("drift", "timing")
