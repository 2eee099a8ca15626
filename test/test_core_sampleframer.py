"""core.sampleframer: cleaned, band-passed samples with their held joint velocity."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from egovib_ros.core.filters import BandPass
from egovib_ros.core.sampleframer import SampleFramer
from egovib_ros.core.stream import FramerSettings
from egovib_ros.errors import StreamError

FS = 1000.0
SETTINGS = FramerSettings(
    sample_rate_hz=FS, block_length=32, hop=16, band_hz=(80.0, 450.0), layout="per_axis"
)


def streams(n: int = 3000, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = (10**9 + np.cumsum(1 + rng.uniform(-0.3, 0.3, n)) * 1e6).astype(np.int64)
    accel = rng.normal(size=(n, 3))
    t_joint = t[::3] + 200_000
    velocity = rng.uniform(0, 1, size=(len(t_joint), 2))
    return t, accel, t_joint, velocity


def collect(framer: SampleFramer):
    batches = framer.pop()
    return batches, (
        np.concatenate([b.stamps_ns for b in batches]),
        np.concatenate([b.values for b in batches]),
        np.concatenate([b.velocity for b in batches]),
    )


def test_samples_are_band_passed_and_carry_the_latest_joint_state():
    t, accel, tj, vel = streams()
    framer = SampleFramer(SETTINGS, 2)
    framer.push_joint_states(tj, vel)
    framer.push_sensor(t, accel)
    framer.flush()
    _, (stamps, values, velocity) = collect(framer)
    assert np.array_equal(stamps, t)
    band = BandPass(sample_rate_hz=FS, band_hz=(80.0, 450.0), order=4, n_channels=3)
    np.testing.assert_array_equal(values, band.process(accel.T).T)
    index = np.searchsorted(tj, t, side="right") - 1
    held = np.where(index[:, None] >= 0, vel[np.maximum(index, 0)], np.nan)
    np.testing.assert_array_equal(velocity, held)
    assert framer.samples_no_joint_state == int(np.count_nonzero(index < 0))


def test_keep_raw_carries_each_sample_unfiltered_beside_its_band_passed_value():
    t, accel, tj, vel = streams()
    accel[:, 2] += 9.81
    framer = SampleFramer(dataclasses.replace(SETTINGS, keep_raw=True), 2)
    framer.push_joint_states(tj, vel)
    framer.push_sensor(t, accel)
    framer.flush()
    batches, (stamps, values, _) = collect(framer)
    assert np.array_equal(stamps, t)
    np.testing.assert_array_equal(np.concatenate([b.raw for b in batches]), accel)
    band = BandPass(sample_rate_hz=FS, band_hz=(80.0, 450.0), order=4, n_channels=3)
    np.testing.assert_array_equal(values, band.process(accel.T).T)


@settings(max_examples=20, deadline=None)
@given(
    st.lists(st.integers(min_value=1, max_value=400), min_size=1, max_size=10),
    st.lists(st.integers(min_value=1, max_value=300), min_size=1, max_size=10),
)
def test_any_chunking_releases_the_same_samples(accel_cuts, joint_cuts):
    t, accel, tj, vel = streams(2000, seed=1)
    whole = SampleFramer(SETTINGS, 2)
    whole.push_joint_states(tj, vel)
    whole.push_sensor(t, accel)
    whole.flush()
    _, want = collect(whole)
    framer = SampleFramer(SETTINGS, 2)
    a_edges = np.unique(np.clip(np.cumsum(accel_cuts), 0, len(t)))
    a_edges = np.r_[a_edges, len(t)]
    j_pos, start = 0, 0
    for stop in a_edges:
        # joint states first, up to a little past the chunk (as feed() interleaves them)
        limit = int(np.searchsorted(tj, t[stop - 1] + 21_000_000, side="right"))
        while j_pos < limit:
            step = joint_cuts[j_pos % len(joint_cuts)]
            framer.push_joint_states(
                tj[j_pos : min(j_pos + step, limit)], vel[j_pos : min(j_pos + step, limit)]
            )
            j_pos = min(j_pos + step, limit)
        framer.push_sensor(t[start:stop], accel[start:stop])
        start = stop
    framer.push_joint_states(tj[j_pos:], vel[j_pos:])
    framer.flush()
    _, got = collect(framer)
    for a, b in zip(got, want):
        np.testing.assert_array_equal(a, b)


def pushed_until(framer: SampleFramer, t, accel, tj, vel, until: int):
    """Joint states stamped up to sample `until`, then the samples up to it: (the stamps
    released so far, the joint states pushed)."""
    j = int(np.searchsorted(tj, t[until], side="right"))
    framer.push_joint_states(tj[:j], vel[:j])
    framer.push_sensor(t[: until + 1], accel[: until + 1])
    return np.concatenate([b.stamps_ns for b in framer.pop()]), j


@pytest.mark.parametrize(("offset_ms", "released_at_once"), [(0.6, True), (0.4, False)])
def test_a_sample_within_the_joint_spacing_is_released_before_the_next_joint_state(
    offset_ms, released_at_once
):
    """Joint states every 1 ms (spacing learnt: half of it): a sample 0.4 ms after the latest
    is released at once (no joint state can come before it any more); one 0.6 ms after waits
    for the next (one could still come before it). Either way its velocity is the one the
    whole stream gives it."""
    n = 400
    t = 10**9 + np.arange(n, dtype=np.int64) * 1_000_000
    accel = np.random.default_rng(5).normal(size=(n, 3))
    tj = t + int(offset_ms * 1e6)
    vel = np.random.default_rng(6).uniform(0, 1, size=(n, 2))
    framer = SampleFramer(SETTINGS, 2)
    released, j = pushed_until(framer, t, accel, tj, vel, 300)
    assert (released[-1] == t[300]) == released_at_once
    assert released[-1] >= t[299]
    whole = SampleFramer(SETTINGS, 2)
    whole.push_joint_states(tj, vel)
    whole.push_sensor(t, accel)
    whole.flush()
    _, (_, _, want) = collect(whole)
    framer.push_joint_states(tj[j:], vel[j:])
    framer.push_sensor(t[301:], accel[301:])
    framer.flush()
    _, (_, _, rest) = collect(framer)
    np.testing.assert_array_equal(want[len(released) :], rest)


@pytest.mark.parametrize("chunk", [1, 7, 1000])
def test_a_joint_state_closer_than_the_spacing_is_thinned_whatever_the_chunking(chunk):
    """A joint state 0.1 ms after another (a burst) in a 1 ms stream is left out, counted,
    for every chunking: the samples after it hold the one before."""
    t, accel, _, _ = streams(1000, seed=7)
    tj = 10**9 + np.arange(1000, dtype=np.int64) * 1_000_000
    tj = np.sort(np.r_[tj, tj[500] + 100_000])
    vel = np.random.default_rng(8).uniform(0, 1, size=(len(tj), 2))
    framer = SampleFramer(SETTINGS, 2)
    for start in range(0, len(tj), chunk):
        framer.push_joint_states(tj[start : start + chunk], vel[start : start + chunk])
    framer.push_sensor(t, accel)
    framer.flush()
    _, (stamps, _, velocity) = collect(framer)
    assert framer.joint_states_thinned == 1
    kept = np.ones(len(tj), bool)
    kept[501] = False
    index = np.searchsorted(tj[kept], stamps, side="right") - 1
    held = np.where(index[:, None] >= 0, vel[kept][np.maximum(index, 0)], np.nan)
    np.testing.assert_array_equal(velocity, held)


def test_a_long_gap_ends_the_segment_and_restarts_the_filter():
    t, accel, tj, vel = streams(2000, seed=2)
    keep = np.ones(len(t), bool)
    keep[1000:1050] = False  # 50 samples missing: more than max_fill_samples
    keep[1500:1503] = False  # 3 missing: bridged, never output
    framer = SampleFramer(SETTINGS, 2)
    framer.push_joint_states(tj, vel)
    framer.push_sensor(t[keep], accel[keep])
    framer.flush()
    batches, (stamps, values, _) = collect(framer)
    assert [b.ends_segment for b in batches if b.ends_segment] == [True, True]
    assert np.count_nonzero(stamps < 0) == 3
    real = stamps >= 0
    assert np.array_equal(stamps[real], t[keep])
    band = BandPass(sample_rate_hz=FS, band_hz=(80.0, 450.0), order=4, n_channels=3)
    np.testing.assert_array_equal(values[real][1000:1010], band.process(accel[1050:1060].T).T)
    assert framer.stats.resets == 1 and framer.stats.gap_filled_samples == 3


def test_bad_samples_and_stale_joint_states_are_counted_never_passed_on():
    t, accel, tj, vel = streams(1000, seed=3)
    accel[100] = np.nan
    accel[200, 1] = 1e6
    framer = SampleFramer(
        FramerSettings(**{**SETTINGS.__dict__, "sensor_range": 100.0, "max_hold_s": 0.05}), 2
    )
    framer.push_joint_states(tj[:100], vel[:100])  # none after ~0.3 s
    framer.push_sensor(t, accel)
    framer.flush()
    _, (stamps, values, velocity) = collect(framer)
    assert framer.stats.samples_bad == 2
    assert 100 not in np.searchsorted(t, stamps[stamps >= 0])
    assert np.all(np.isfinite(values))
    out_t = stamps[stamps >= 0]
    stale = (out_t - tj[99]) > 50_000_000
    before = out_t < tj[0]  # the first sample comes before any joint state
    assert np.all(np.isnan(velocity[stamps >= 0][stale | before]))
    assert framer.samples_no_joint_state == int(stale.sum() + before.sum())


def test_a_stream_at_another_rate_is_refused():
    t, accel, _, _ = streams(500)
    framer = SampleFramer(SETTINGS, 2)
    with pytest.raises(
        StreamError, match=r"runs at (4[5-9][0-9]|5[0-4][0-9]) Hz but the model expects 1000 Hz"
    ):
        framer.push_sensor(t[0] + 2 * (t - t[0]), accel)


@pytest.mark.parametrize("nominal_hz", [1600.0, 2000.0, 1333.0])
def test_steps_alternating_500_and_750_us_are_the_same_stream_to_every_framer(nominal_hz):
    """A small flight controller's gyro logged every 500 then 750 us (its mean: 1600 Hz):
    the per-sample methods measure the rate as the paper's blocks do (one rate check, in
    the framers' base; SampleFramer took the median step, 2000 Hz, and refused what the
    paper's method accepted), so a stream one method accepts every method accepts."""
    from egovib_ros.core.stream import BlockFramer

    n = 4000
    steps = np.tile([500_000, 750_000], n // 2)
    t = 10**9 + np.cumsum(steps).astype(np.int64)
    accel = np.random.default_rng(1).normal(size=(n, 3))
    settings = dataclasses.replace(SETTINGS, sample_rate_hz=nominal_hz)
    outcomes = []
    for framer in (SampleFramer(settings, 2), BlockFramer(settings, 2)):
        framer.push_joint_states(t[::4], np.zeros((n // 4, 2)))
        try:
            framer.push_sensor(t, accel)
            framer.flush()
            outcomes.append(framer.rate_checked)
        except StreamError as exc:
            assert f"expects {nominal_hz:g} Hz" in str(exc)
            outcomes.append(False)
    assert outcomes[0] == outcomes[1]
    if nominal_hz == 1600.0:
        assert outcomes == [True, True]
