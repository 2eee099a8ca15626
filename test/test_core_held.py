"""egovib_ros.core.held: the held input rows the output samples are, whatever the core dropped,
for stamps in order (binary search) and across a restarted clock (forward scan); the same rows
as a plain forward scan in every case."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from egovib_ros.core import StreamingDenoiser
from egovib_ros.core.held import output_rows


def scan(held, out):
    """The definition: each output stamp is the next held row with that stamp."""
    rows, i = [], 0
    for stamp in out:
        while held[i] != stamp:
            i += 1
        rows.append(i)
        i += 1
    return rows


def test_nothing_dropped_some_dropped_and_a_restarted_clock():
    held = np.array([10, 20, 30, 40, 50])
    assert output_rows(held, held[:3]).tolist() == [0, 1, 2]
    assert output_rows(held, [20, 50]).tolist() == [1, 4]
    assert output_rows([10, 20, 20, 30], [20, 30]).tolist() == [1, 3]  # a repeat: its first row
    jumped = np.array([900, 910, 5, 15, 25])  # the clock restarted after 910
    assert output_rows(jumped, [910, 5, 25]).tolist() == [1, 2, 4]
    assert output_rows(held, []).tolist() == []


def test_an_output_sample_not_held_is_an_internal_error():
    with pytest.raises(RuntimeError, match="stamped 35 has no held input sample"):
        output_rows([10, 20, 30, 40], [20, 35])
    with pytest.raises(RuntimeError, match="stamped 7 has no held input sample"):
        output_rows([900, 5, 15], [5, 7])


@given(
    st.lists(st.integers(0, 50), min_size=1, max_size=60),
    st.lists(st.booleans(), min_size=60, max_size=60),
    st.booleans(),
)
def test_the_rows_are_those_of_a_forward_scan(steps, keep, restart):
    held = np.cumsum(steps)  # non-decreasing; a 0 step repeats a stamp
    if restart:
        held = np.concatenate([held + 10_000, held])
    picked, last = [], None
    for i, stamp in enumerate(held.tolist()):  # what a core outputs: strictly later stamps
        if keep[i % 60] and (last is None or stamp > last or (restart and i == len(held) // 2)):
            picked.append(stamp)
            last = stamp
    assert output_rows(held, picked).tolist() == scan(held.tolist(), picked)


def test_a_denoisers_output_is_found_among_its_input(sim_model_path):
    """Samples the core drops (a NaN, a stamp out of order) are the rows no output takes."""
    from egovib_ros.core import NoiseModel

    model = NoiseModel.load(sim_model_path)
    rng = np.random.default_rng(0)
    stamps = np.arange(3000, dtype=np.int64) * 333_333 + 10**9
    stamps[1500] = stamps[1400]  # out of order: dropped
    values = rng.normal(size=(3000, 3))
    values[700] = np.nan  # bad: bridged, never output
    denoiser = StreamingDenoiser(model)
    joint_t = np.arange(0, 1_100_000_000, 1_000_000, dtype=np.int64) + 10**9
    denoiser.push_joint_states(joint_t, np.zeros((len(joint_t), model.n_joints)))
    out = [denoiser.push_sensor(stamps, values), denoiser.flush()]
    out_stamps = np.concatenate([c.stamps_ns for c in out if len(c)])
    rows = output_rows(stamps, out_stamps)
    assert set(range(3000)) - set(rows.tolist()) == {700, 1500}
