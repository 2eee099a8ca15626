"""gap.change: what differs between two recordings of the same robot, on synthetic block
tables with known effects (test/gaptables.py): a lag shift and a level change are named with
their size, an effect both recordings share is no change, two identical conditions give none."""

from __future__ import annotations

import numpy as np
import pytest
from gaptables import synthetic_table

from egovib_ros.errors import GapDataError
from egovib_ros.gap.change import change_folds, diagnose_change
from egovib_ros.gap.diagnose import diagnose
from egovib_ros.gap.features import JOIN_GAP_S, join_tables


def change_of(reference_kw: dict, real_kw: dict):
    reference = synthetic_table(**reference_kw)
    real = diagnose(synthetic_table(**real_kw))
    return diagnose_change(reference, real)


def test_a_lag_shift_and_a_level_change_are_named_with_their_size():
    change = change_of(
        {"seed": 11, "duration_s": 20.0},
        {"effects": {"timing": 0.04}, "gain": 1.4, "seed": 12, "duration_s": 20.0},
    )
    # (20 s each: on seed pairs 11/12, 21/22, 31/32 the lag shift is -41, -39, -42 ms and
    # the level change 2.72, 2.81, 2.69 dB, both at p = 5e-5; 30 s gives the same)
    found = {e["effect"]: e for e in change.effects}
    assert set(found) == {"timing", "drift"}, change.steps
    # joint states stamped 40 ms late: the vibration leads them by 40 ms more than before
    assert found["timing"]["parameters"]["lag_shift_ms"] == pytest.approx(-40.0, abs=5.0)
    # a gain of 1.4 = +2.9 dB at every velocity
    assert found["drift"]["parameters"]["level_change_db"] == pytest.approx(2.92, abs=0.5)
    for e in change.effects:
        assert e["p_value"] < 0.01 / 5 and e["reduction"] > 0 and 0 <= e["confidence"] <= 1
    assert change.gaps["after_changes"] < change.gaps["baseline"]


def test_an_effect_both_share_is_no_change_and_a_new_one_is():
    """The same interaction in both recordings: nothing changed (the null model has what both
    share of it); in the recording only: a new interaction, first (the recording is louder
    wherever both joints move: before the changes were ranked by their gain over the changes
    taken, the level's gain 0.018 came before the interaction's 0.015 on seed pairs 13/14 and
    17/18, each over a model of its own). (40 s each; the recording's diagnosis serves both.)"""
    real = diagnose(synthetic_table(effects={"coupling": 5.0}, seed=14, duration_s=40.0))
    both = diagnose_change(
        synthetic_table(effects={"coupling": 5.0}, seed=13, duration_s=40.0), real
    )
    assert both.effects == [], both.steps
    new = diagnose_change(synthetic_table(seed=13, duration_s=40.0), real)
    assert [e["effect"] for e in new.effects][:1] == ["coupling"], new.steps


@pytest.mark.parametrize("effect", ["position", "acceleration"])
def test_a_new_dependence_is_named_before_the_level_it_brings(effect):
    """A recording louder where a new position or acceleration dependence acts: the change is
    that dependence (with the level it brings), first, not a level change. (30 s each: the
    same on seed pairs 13/14 and 21/22; before its term was fitted on the recording together
    with its level, pair 15/16 gave no change for position and `drift` first for
    acceleration; fitted in two stages the position term predicted held-out blocks worse
    than no change at all on a real flight.)"""
    real = diagnose(synthetic_table(effects={effect: 1.0}, seed=16, duration_s=30.0))
    change = diagnose_change(synthetic_table(seed=15, duration_s=30.0), real)
    assert [e["effect"] for e in change.effects][:1] == [effect], change.steps


def test_joined_table_and_its_folds_hold_both_recordings():
    a, b = synthetic_table(seed=1, duration_s=20.0), synthetic_table(seed=2, duration_s=10.0)
    joined = join_tables(a, b)
    assert joined.n_blocks == a.n_blocks + b.n_blocks
    assert np.all(np.diff(joined.t_mid_s) > 0)
    assert joined.t_first_s[a.n_blocks] == pytest.approx(a.t_last_s[-1] + JOIN_GAP_S)
    assert joined.recording.tolist() == [0] * a.n_blocks + [1] * b.n_blocks
    for split in change_folds(joined, 5):
        # every fold holds out a part of each recording and trains on the rest of both
        for r in (0, 1):
            mine = joined.recording == r
            assert split.test[mine].any() and split.train[mine].any()
        assert not (split.train & split.test).any()


def test_a_reference_without_enough_clean_blocks_is_refused():
    short = synthetic_table(seed=1, duration_s=3.0)
    with pytest.raises(GapDataError, match="too few no-contact blocks"):
        diagnose_change(short, diagnose(synthetic_table(seed=2, duration_s=20.0)))
