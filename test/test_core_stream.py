"""egovib_ros.core.stream: BlockFramer cuts a sensor stream into blocks with matched joint
velocity, the same for any chunking as frame_batch; bad input is counted (check_stream refuses
a mostly bad recording in one line); joint_lag_s moves joint states in time.

The sample rate is checked all along the stream, not only at its start. A stream whose rate
changes in the middle (e.g. halves) must not be "bridged" (every step of two periods looking
like one missing sample, filled by interpolation: seconds of invented samples). Two windows
in a row off by more than the framer's tolerance are a rate mismatch (StreamError naming the
source, and on every later push), for any chunking. Jitter (+-30 % per step, random or
alternating), lost samples (up to a third, scattered) and a short glitch stay what they
were: bridged and counted.
"""

import numpy as np
import pytest
from synthetic import CELLS, FS, calibrated_model, push_random_chunks, stream

from egovib_ros.core import StreamingDenoiser, calibrate_arrays, denoise_batch
from egovib_ros.core.stream import (
    RATE_WINDOW_BLOCKS,
    BlockFramer,
    FramerSettings,
    check_stream,
    feed,
    measured_periods,
)
from egovib_ros.core.velocity import HELD, MATCHED, MISSING
from egovib_ros.errors import ConfigError, StreamError

PERIOD_NS = 1e9 / FS
SOURCE = "bag: /accelerometer/raw"


def frame_batch(settings, n_joints, sensor_stamps_ns, accel, joint_stamps_ns, joint_velocity):
    """Whole arrays framed: everything pushed into a BlockFramer, then flushed."""
    framer = BlockFramer(settings, n_joints)
    framer.push_joint_states(joint_stamps_ns, joint_velocity)
    framer.push_sensor(sensor_stamps_ns, accel)
    framer.flush()
    return framer.pop_blocks(), framer.stats


@pytest.fixture(scope="module")
def model():
    return calibrated_model()


@pytest.fixture(scope="module")
def motion():
    return stream(6, CELLS, seed=3)


def with_stamps(data: dict, ticks: np.ndarray, rng=None) -> dict:
    """`data` with sensor samples at `ticks` nominal periods after its first stamp (values
    drawn afresh when the count changes)."""
    n = len(ticks)
    accel = data["accel"][:n] if n <= len(data["accel"]) else rng.normal(size=(n, 3))
    t_acc = (data["t_acc"][0] + np.round(np.asarray(ticks) * PERIOD_NS)).astype(np.int64)
    return dict(data, t_acc=t_acc, accel=accel)


def rate_changed_at(data: dict, seconds: float, factor: float, rng) -> dict:
    """Nominal rate up to `seconds`, then `factor` times it to the end of the joint states."""
    before = int(seconds * FS)
    after = int((len(data["t_acc"]) - before) * factor)
    ticks = np.r_[np.arange(before), before + np.arange(after) / factor]
    return with_stamps(data, ticks, rng)


def denoise_streaming(model, data, seed):
    denoiser = StreamingDenoiser(model, source=SOURCE)
    chunks = push_random_chunks(denoiser, data, np.random.default_rng(seed)) + [denoiser.flush()]
    chunks = [c for c in chunks if c is not None and len(c)]
    return (
        np.concatenate([c.stamps_ns for c in chunks]),
        np.concatenate([c.values for c in chunks]),
        denoiser.stats,
    )


def test_measured_periods_ignore_jitter_and_lost_samples_but_see_a_slower_clock():
    rng = np.random.default_rng(0)
    alternating = np.tile([0.7, 1.3], 128)[:255]  # an odd count: a median picks one side
    assert np.median(alternating) == pytest.approx(0.7)
    rows = {  # steps of one window -> the period it shows (nominal 1)
        "jitter": (1 + rng.uniform(-0.3, 0.3, 255), 1.0),
        "alternating": (alternating, 1.0),
        "30 % of the steps skip a sample": (np.where(rng.random(255) < 0.3, 2.0, 1.0), 1.0),
        "the rate halved": (np.full(255, 2.0), 2.0),
        "doubled": (np.full(255, 0.5), 0.5),
        "20 % slower": (np.full(255, 1.25), 1.25),
    }
    measured = measured_periods(np.array([steps for steps, _ in rows.values()]), 1.0)
    for (name, (steps, period)), value in zip(rows.items(), measured):
        assert value == pytest.approx(period, abs=0.03), name
        assert measured_periods(steps[None, :], 1.0)[0] == value, name  # alone, the same


@pytest.mark.parametrize(
    "factor,measured", [(0.5, "1500 Hz"), (2.0, "6000 Hz"), (0.8, "2400 Hz"), (1.2, "3600 Hz")]
)
def test_rate_change_mid_stream_is_refused_for_any_chunking(model, motion, factor, measured):
    data = rate_changed_at(motion, 3.0, factor, np.random.default_rng(1))
    with pytest.raises(StreamError) as batch:
        denoise_batch(
            data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model, source=SOURCE
        )
    line = str(batch.value)
    assert line.startswith(f"{SOURCE}: sensor rate changed") and "\n" not in line, line
    assert measured in line and "3000 Hz" in line, line
    for seed in range(3):  # streaming: the same windows, the same error, then on every push
        denoiser = StreamingDenoiser(model, source=SOURCE)
        with pytest.raises(StreamError) as streamed:
            push_random_chunks(denoiser, data, np.random.default_rng(seed))
        assert str(streamed.value) == line
        with pytest.raises(StreamError, match="sensor rate changed"):
            denoiser.push_sensor(data["t_acc"][-5:] + 10**9, data["accel"][-5:])


def test_rate_change_is_refused_within_three_windows(model, motion):
    """At most 3 windows of samples at the new rate pass before the refusal (2 to measure,
    1 that straddles the change), and nothing after it."""
    data = rate_changed_at(motion, 3.0, 0.5, np.random.default_rng(1))
    denoiser = StreamingDenoiser(model, source=SOURCE)
    denoiser.push_joint_states(data["t_joint"], data["velocity"])
    change = int(np.searchsorted(data["t_acc"], data["t_acc"][0] + 3 * 10**9))
    refused_at = None
    for i in range(0, len(data["t_acc"]), 32):  # as live: a hop at a time
        try:
            denoiser.push_sensor(data["t_acc"][i : i + 32], data["accel"][i : i + 32])
        except StreamError:
            refused_at = i + 32
            break
    assert refused_at is not None
    window = RATE_WINDOW_BLOCKS * model.block_length
    assert refused_at - change <= 3 * window


@pytest.mark.parametrize(
    "case", ["jitter_30_percent", "alternating_jitter", "lost_30_percent", "bridged_gaps"]
)
def test_jitter_and_lost_samples_are_not_a_rate_change(model, motion, case):
    rng = np.random.default_rng(7)
    n = len(motion["t_acc"])
    if case == "jitter_30_percent":
        data = with_stamps(motion, np.cumsum(1 + rng.uniform(-0.3, 0.3, n)))
    elif case == "alternating_jitter":
        data = with_stamps(motion, np.cumsum(np.where(np.arange(n) % 2, 1.3, 0.7)))
    elif case == "lost_30_percent":
        keep = rng.random(n) > 0.3
        data = dict(motion, t_acc=motion["t_acc"][keep], accel=motion["accel"][keep])
    else:  # a gap of 8 samples (the most bridged) every 100 samples
        keep = (np.arange(n) % 100) >= 8
        data = dict(motion, t_acc=motion["t_acc"][keep], accel=motion["accel"][keep])
    stamps, values, stats = denoise_batch(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model
    )
    np.testing.assert_array_equal(stamps, data["t_acc"])  # one output per input sample
    if case in ("lost_30_percent", "bridged_gaps"):
        assert stats.gap_filled_samples > 0  # bridged and counted, as before
    s_stamps, s_values, _ = denoise_streaming(model, data, seed=2)
    np.testing.assert_array_equal(s_stamps, stamps)
    assert np.max(np.abs(s_values - values)) <= 1e-12


def test_a_short_glitch_at_half_rate_is_bridged_not_refused(model, motion):
    """Every other sample lost over 500 samples (~170 ms, one window): bridged and counted."""
    keep = np.ones(len(motion["t_acc"]), dtype=bool)
    keep[6000:6500:2] = False
    data = dict(motion, t_acc=motion["t_acc"][keep], accel=motion["accel"][keep])
    stamps, _, stats = denoise_batch(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model
    )
    assert len(stamps) == len(data["t_acc"]) and stats.gap_filled_samples == 250


def test_calibration_refuses_a_rate_change_too(motion):
    data = rate_changed_at(motion, 3.0, 0.5, np.random.default_rng(1))
    with pytest.raises(StreamError, match="sensor rate changed.*1500 Hz"):
        calibrate_arrays(data["t_acc"], data["accel"], data["t_joint"], data["velocity"])


def _stream(seed: int = 0, n: int = 6000):
    rng = np.random.default_rng(seed)
    stamps = np.arange(n, dtype=np.int64) * 333_333
    accel = rng.standard_normal((n, 3))
    joint_stamps = np.arange(0, n * 333_333, 1_000_000, dtype=np.int64) + 170_000
    t = joint_stamps / 1e9
    velocity = np.column_stack([np.sin(2 * np.pi * 0.7 * t), np.cos(2 * np.pi * 1.3 * t)])
    return stamps, accel, joint_stamps, velocity


@pytest.mark.parametrize("lag_s", [0.023, -0.031])
def test_joint_lag_equals_restamped_joint_states(lag_s):
    """joint_lag_s moves joint-state stamps later by that much before matching: the blocks
    equal those of joint states re-stamped by hand."""
    stamps, accel, joint_stamps, velocity = _stream()
    shifted = FramerSettings(joint_lag_s=lag_s)
    by_hand = FramerSettings()
    a, _ = frame_batch(shifted, 2, stamps, accel, joint_stamps, velocity)
    b, _ = frame_batch(by_hand, 2, stamps, accel, joint_stamps + int(round(lag_s * 1e9)), velocity)
    va = np.concatenate([x.velocity for x in a])
    vb = np.concatenate([x.velocity for x in b])
    assert va.shape == vb.shape and len(va) > 100
    np.testing.assert_allclose(va, vb)
    unshifted, _ = frame_batch(FramerSettings(), 2, stamps, accel, joint_stamps, velocity)
    assert not np.allclose(va, np.concatenate([x.velocity for x in unshifted]))


def test_joint_lag_out_of_range_is_refused():
    with pytest.raises(ConfigError, match="joint_lag_s"):
        FramerSettings(joint_lag_s=2.0)
    with pytest.raises(ConfigError, match="joint_lag_s"):
        FramerSettings(joint_lag_s=float("nan"))


# --------------------------------------------------------------------------
# BlockFramer: blocks, their joint velocity, any chunking, bad input counted
# --------------------------------------------------------------------------
def _framed(blocks):
    """The fields of a list of Blocks, concatenated."""
    return {
        name: np.concatenate([getattr(b, name) for b in blocks])
        for name in ("samples", "t_first_ns", "t_last_ns", "velocity", "status", "out_stamps_ns")
    }


def test_block_framer_in_any_chunks_equals_frame_batch(motion):
    settings = FramerSettings(source=SOURCE)
    whole, whole_stats = frame_batch(
        settings, 2, motion["t_acc"], motion["accel"], motion["t_joint"], motion["velocity"]
    )
    expected = _framed(whole)
    for seed in range(3):
        framer = BlockFramer(settings, 2)
        push_random_chunks(framer, motion, np.random.default_rng(seed), max_chunk=700)
        framer.flush()
        got = _framed(framer.pop_blocks())
        for name, value in expected.items():
            np.testing.assert_array_equal(got[name], value, err_msg=f"{name}, seed {seed}")
        assert framer.stats.blocks == whole_stats.blocks == len(expected["status"])
    n = len(motion["t_acc"])
    # one block every hop; each real sample is completed by exactly one block
    assert abs(len(expected["status"]) - n / settings.hop) <= 2
    out = expected["out_stamps_ns"].reshape(-1)
    np.testing.assert_array_equal(out[out >= 0], motion["t_acc"])


def test_blocks_carry_the_mean_joint_velocity_of_their_span(motion):
    settings = FramerSettings()
    blocks, stats = frame_batch(
        settings, 2, motion["t_acc"], motion["accel"], motion["t_joint"], motion["velocity"]
    )
    f = _framed(blocks)
    matched = f["status"] == MATCHED
    assert matched.mean() > 0.99 and stats.blocks_missing == 0
    assert np.all(f["t_last_ns"] - f["t_first_ns"] <= (settings.block_length - 1) * PERIOD_NS + 1)
    # inside a segment of constant velocity the block mean is that velocity
    for k, cell in enumerate(CELLS):
        lo, hi = motion["t_acc"][motion["segment"] == k][[0, -1]]
        inside = matched & (f["t_first_ns"] > lo + 20_000_000) & (f["t_last_ns"] < hi - 20_000_000)
        assert inside.sum() > 50
        np.testing.assert_allclose(f["velocity"][inside], np.broadcast_to(cell, (inside.sum(), 2)))


def test_blocks_without_joint_states_are_held_then_missing(motion):
    """Joint states stop after 2 s: blocks up to max_hold_s later are HELD (the last one's
    velocity), later blocks MISSING (NaN, not denoised or calibrated)."""
    settings = FramerSettings(max_hold_s=0.05)
    keep = motion["t_joint"] < motion["t_joint"][0] + 2_000_000_000
    blocks, stats = frame_batch(
        settings, 2, motion["t_acc"], motion["accel"], motion["t_joint"][keep],
        motion["velocity"][keep],
    )  # fmt: skip
    f = _framed(blocks)
    last_joint = motion["t_joint"][keep][-1]
    after = f["t_first_ns"] > last_joint
    held = f["status"] == HELD
    assert held.any() and np.all(f["t_first_ns"][held] <= last_joint + 50_000_000)
    np.testing.assert_array_equal(
        f["velocity"][held], np.tile(motion["velocity"][keep][-1], (held.sum(), 1))
    )
    missing = f["status"] == MISSING
    assert np.array_equal(missing, after & ~held)
    assert np.isnan(f["velocity"][missing]).all()
    assert stats.blocks_missing == missing.sum() and stats.blocks_held == held.sum()


def test_gaps_are_bridged_or_end_the_segment_and_bad_samples_are_counted(motion):
    t, x = motion["t_acc"].copy(), motion["accel"].copy()
    short = np.r_[3000:3005]  # 5 samples lost: bridged
    long = np.r_[6000:6050]  # 50 lost: the segment ends, the filter restarts
    x[9000] = np.nan  # a bad sample: missing, bridged, never output
    x[9500] = [1e9, 0.0, 0.0]
    t[12_000] = t[11_990]  # stamped before its predecessor: dropped
    keep = np.ones(len(t), bool)
    keep[short] = keep[long] = False
    blocks, stats = frame_batch(
        FramerSettings(max_fill_samples=8, sensor_range=1e6), 2, t[keep], x[keep],
        motion["t_joint"], motion["velocity"],
    )  # fmt: skip
    # the short gap, the two bad samples and the hole the dropped sample leaves
    assert stats.gap_filled_samples == 5 + 2 + 1
    assert stats.samples_bad == 2 and stats.dropped_out_of_order == 1 and stats.resets == 1
    assert sum(b.ends_segment for b in blocks) >= 1
    out = _framed(blocks)["out_stamps_ns"].reshape(-1)
    output = out[out >= 0]
    # every good sample once, in order; not the bad ones, not the dropped repeat
    expected = np.unique(t[keep])
    np.testing.assert_array_equal(output, expected[~np.isin(expected, t[[9000, 9500]])])


def test_the_backlog_stays_bounded_on_a_long_stream():
    data = stream(60, CELLS, seed=5)
    framer = BlockFramer(FramerSettings(), 2)
    most = 0
    for i in range(0, len(data["t_acc"]), 3000):
        j = np.searchsorted(data["t_joint"], data["t_acc"][min(i + 2999, len(data["t_acc"]) - 1)])
        j0 = np.searchsorted(data["t_joint"], data["t_acc"][i] - 1) if i else 0
        framer.push_joint_states(data["t_joint"][j0 : j + 20], data["velocity"][j0 : j + 20])
        framer.push_sensor(data["t_acc"][i : i + 3000], data["accel"][i : i + 3000])
        framer.pop_blocks()
        most = max(most, *framer.backlog)
    assert most < 4000  # about a second of either stream, not the minute


def test_a_wrong_shape_is_one_line_naming_the_source():
    framer = BlockFramer(FramerSettings(source=SOURCE), 2)
    with pytest.raises(StreamError, match=f"^{SOURCE}: sensor chunk: expected"):
        framer.push_sensor(np.arange(4), np.zeros((4, 2)))
    with pytest.raises(StreamError, match=f"^{SOURCE}: joint states: expected"):
        framer.push_joint_states(np.arange(4), np.zeros((4, 3)))


@pytest.mark.parametrize(
    "name, value, named",
    [("sample_rate_hz", 0.0, "sample_rate_hz"), ("band_hz", (800.0, 100.0), "band_hz"),
     ("layout", "diagonal", "channels"), ("max_fill_samples", -1, "max_fill_samples"),
     ("rate_tolerance", float("nan"), "rate_tolerance"), ("band_order", True, "band_order")],
)  # fmt: skip
def test_bad_settings_are_one_line_config_errors(name, value, named):
    with pytest.raises(ConfigError, match=f"^{SOURCE}: {named}") as info:
        FramerSettings(**{name: value}, source=SOURCE)
    assert "\n" not in str(info.value)


def test_check_stream_prints_the_counts_and_refuses_a_mostly_bad_recording():
    from dataclasses import replace

    from egovib_ros.core.stream import FramerStats

    stats = FramerStats(samples_in=1000, samples_bad=30, dropped_out_of_order=20,
                        gap_filled_samples=45, resets=1, joint_states_dropped=3)  # fmt: skip
    line = check_stream(stats, "bag", joint_states=500)
    assert line == (
        "bad input treated as missing: 30 sensor samples non-finite or beyond the sensor "
        "range, 20 out of order, 45 bridged, 1 restarts; 3 of 500 joint states dropped"
    )
    with pytest.raises(StreamError, match=r"^bag: 150 of 1000 sensor samples \(15.0 %\) are bad"):
        check_stream(replace(stats, samples_bad=130), "bag", joint_states=500)
    with pytest.raises(StreamError, match=r"^bag: 60 of 500 joint states \(12.0 %\) are unusable"):
        check_stream(replace(stats, joint_states_dropped=60), "bag", joint_states=500)
    assert check_stream(replace(stats, samples_bad=130), "bag", joint_states=500, limit=0.2)
    with pytest.raises(StreamError, match="^bag: no sensor samples"):
        check_stream(FramerStats(), "bag", joint_states=0)


def test_every_streaming_class_is_a_stream_consumer(model):
    from egovib_ros.core import CalibrationAccumulator, StreamConsumer
    from egovib_ros.core.methods import SampleMethodDenoiser
    from egovib_ros.core.sampleframer import SampleFramer

    settings = FramerSettings()
    for consumer in (
        BlockFramer(settings, 2),
        SampleFramer(settings, 2),
        StreamingDenoiser(model),
        CalibrationAccumulator(),
    ):
        assert isinstance(consumer, StreamConsumer), type(consumer).__name__
    assert issubclass(SampleMethodDenoiser, StreamConsumer)
    assert not isinstance(object(), StreamConsumer)


def test_feed_pushes_everything_in_time_order_for_any_chunk_length(model, motion):
    """feed gives a consumer every joint state and sensor sample once, joint states ahead of
    the sensor chunk they cover, so no block waits: the framing of the whole arrays."""
    expected, _ = frame_batch(
        FramerSettings(), 2, motion["t_acc"], motion["accel"], motion["t_joint"], motion["velocity"]
    )
    for chunk_s in (0.05, 0.7, 10.0):
        framer = BlockFramer(FramerSettings(), 2)
        pushed = feed(
            framer, motion["t_acc"], motion["accel"], motion["t_joint"], motion["velocity"],
            sample_rate_hz=FS, joint_wait_s=0.02, chunk_s=chunk_s,
        )  # fmt: skip
        assert pushed and all(p is None for p in pushed)  # the framer keeps what it releases
        framer.flush()
        got = _framed(framer.pop_blocks())
        for name, value in _framed(expected).items():
            np.testing.assert_array_equal(got[name], value, err_msg=f"{name}, chunk {chunk_s}")


#: The keys of the stats as written (reports, /diagnostics), in their order.
PAPER_KEYS = [
    "samples_in", "samples_out", "dropped_out_of_order", "samples_bad", "gap_filled_samples",
    "resets", "joint_states_in", "joint_states_dropped", "blocks", "blocks_held_joint_state",
    "blocks_no_joint_state", "blocks_out_of_grid", "blocks_unmeasured", "rate_checked",
    "duplicates", "joint_states_duplicates",
]  # fmt: skip
PER_SAMPLE_KEYS = [
    "method", "samples_in", "samples_out", "dropped_out_of_order", "samples_bad",
    "gap_filled_samples", "resets", "joint_states_in", "joint_states_dropped",
    "samples_no_joint_state", "rate_checked", "delay_samples", "frequency_correction",
    "samples_unmeasured", "samples_out_of_grid", "duplicates", "joint_states_duplicates",
]  # fmt: skip
CALIBRATION_KEYS = [
    "mode", "samples_in", "samples_bad", "blocks", "blocks_used", "cells", "rejected",
    "dropped_out_of_order", "gap_filled_samples", "resets", "joint_states_dropped",
    "duplicates", "joint_states_duplicates",
]  # fmt: skip


def test_stats_take_the_framers_counts_and_write_only_the_fields_that_apply():
    from egovib_ros.core import CalibrationStats, DenoiserStats
    from egovib_ros.core.stream import FramerStats

    framer = FramerStats(*range(1, 11), 0, 14, 15)  # distinct counts in declaration order
    paper = DenoiserStats.of(
        framer, samples_out=11, blocks=8, blocks_held_joint_state=9, blocks_no_joint_state=10,
        blocks_out_of_grid=12, blocks_unmeasured=13, rate_checked=True,
    )  # fmt: skip
    assert list(paper.as_dict().items()) == list(
        zip(PAPER_KEYS, [1, 11, 2, 3, 4, 5, 6, 7, 8, 9, 10, 12, 13, True, 14, 15])
    )
    hybrid = DenoiserStats.of(
        framer, method="hybrid", samples_out=11, samples_no_joint_state=12, rate_checked=False,
        delay_samples=4, frequency_correction=[0.01, -0.02], samples_unmeasured=13,
        samples_out_of_grid=14,
    )  # fmt: skip
    assert list(hybrid.as_dict().items()) == list(
        zip(
            PER_SAMPLE_KEYS,
            ["hybrid", 1, 11, 2, 3, 4, 5, 6, 7, 12, False, 4, [0.01, -0.02], 13, 14, 14, 15],
        )
    )
    # without a table (cancel): its counts are None and left out; what is given wins
    cancel = DenoiserStats.of(
        framer, method="cancel", samples_in=99, samples_out=11, samples_no_joint_state=0,
        rate_checked=True, delay_samples=0, frequency_correction=[0.0], samples_unmeasured=None,
    )  # fmt: skip
    assert list(cancel.as_dict()) == PER_SAMPLE_KEYS[:-4] + PER_SAMPLE_KEYS[-2:]
    assert cancel.samples_in == 99
    calibration = CalibrationStats.of(
        framer, mode="free", blocks_used=7, cells=3, rejected={"partial": 1}
    )
    assert list(calibration.as_dict().items()) == list(
        zip(CALIBRATION_KEYS, ["free", 1, 3, 8, 7, 3, {"partial": 1}, 2, 4, 5, 7, 14, 15])
    )


def test_stats_of_the_streaming_classes_keep_their_keys(model, motion):
    from egovib_ros.core import CalibrationAccumulator

    _, _, stats = denoise_streaming(model, motion, seed=0)
    assert list(stats.as_dict()) == PAPER_KEYS
    assert stats.samples_in == len(motion["t_acc"]) and stats.blocks > 0
    _, calibrated = calibrate_arrays(
        motion["t_acc"], motion["accel"], motion["t_joint"], motion["velocity"]
    )
    accumulator = CalibrationAccumulator()
    feed(
        accumulator, motion["t_acc"], motion["accel"], motion["t_joint"], motion["velocity"],
        sample_rate_hz=FS, joint_wait_s=0.02, chunk_s=0.5,
    )  # fmt: skip
    accumulator.flush()
    for cal in (calibrated, accumulator.stats):
        assert list(cal.as_dict()) == CALIBRATION_KEYS
        assert cal.samples_in == len(motion["t_acc"]) and cal.blocks >= cal.blocks_used > 0


def test_short_blocks_measure_the_rate_over_enough_samples(motion):
    """A profile with 4-sample blocks: the rate windows are RATE_BLOCK_MIN samples per block
    at least, so a driver's +-30 % stamp jitter is not a rate change (16 samples measured
    2294 Hz of a 2000 Hz stream: a probe's sweep was refused), and a real change still is."""
    rng = np.random.default_rng(5)
    n = len(motion["t_acc"])
    jittery = with_stamps(motion, np.cumsum(1 + rng.uniform(-0.3, 0.3, n)))
    short = FramerSettings(sample_rate_hz=FS, block_length=4, hop=2, source=SOURCE)
    blocks, stats = frame_batch(
        short, 2, jittery["t_acc"], jittery["accel"], jittery["t_joint"], jittery["velocity"]
    )
    assert sum(len(b.samples) for b in blocks) > n // 2 - 10  # every hop of 2 samples
    halved = with_stamps(
        motion, np.concatenate([np.arange(n // 2), n // 2 + 2 * np.arange(n // 2)])
    )
    with pytest.raises(StreamError, match="sensor rate changed"):
        frame_batch(
            short, 2, halved["t_acc"], halved["accel"], halved["t_joint"], halved["velocity"]
        )
