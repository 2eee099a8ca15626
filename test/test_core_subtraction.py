"""Spectral subtraction: latency, streaming == batch, and bad input."""

import logging

import numpy as np
import pytest
from synthetic import CELLS, FS, calibrated_model, push_random_chunks, stream

from egovib_ros.core import (
    BandPass,
    StreamingDenoiser,
    calibrate_arrays,
    channel_matrix,
    denoise_batch,
)
from egovib_ros.errors import StreamError


@pytest.fixture(scope="module")
def model():
    return calibrated_model()


def zero(model):
    return model.replace(mean=np.zeros_like(model.mean), std=np.zeros_like(model.std))


def bandpassed(accel, channels):
    bp = BandPass(
        sample_rate_hz=FS,
        band_hz=(150.0, 750.0),
        order=4,
        n_channels=3 if channels == "per_axis" else 1,
    )
    return bp.process(channel_matrix(accel, channels).T).T


def collect(chunks):
    chunks = [c for c in chunks if c is not None and len(c)]
    return np.concatenate([c.stamps_ns for c in chunks]), np.concatenate([c.values for c in chunks])


@pytest.mark.parametrize(
    "channels, output", [("per_axis", "bandpassed"), ("combined", None), ("per_axis", "dropin")]
)
def test_zero_noise_estimate_gives_the_input_delayed_by_one_block(model, channels, output):
    """Nothing to subtract: the band-passed input, or for the drop-in output the input
    itself, gravity included (to rounding)."""
    data = stream(3, [(1.5, 0.02)], seed=1)
    data["accel"] = data["accel"] + [0.3, -0.2, 9.81]  # gravity, tilted
    dropin = output == "dropin"
    expected = data["accel"] if dropin else bandpassed(data["accel"], channels)
    denoiser = StreamingDenoiser(zero(model), channels=channels, output=output)
    denoiser.push_joint_states(data["t_joint"], data["velocity"])
    lo, hi = denoiser.delay_samples
    assert (lo, hi) == (32, 63)  # 10.7 .. 21 ms at 3 kHz
    chunks, emitted = [], 0
    for n in range(1, 700):  # one sample at a time
        chunk = denoiser.push_sensor(data["t_acc"][n - 1 : n], data["accel"][n - 1 : n])
        chunks.append(chunk)
        emitted += len(chunk)
        if n >= 64:
            assert lo <= n - emitted <= hi
    chunks.append(denoiser.push_sensor(data["t_acc"][699:], data["accel"][699:]))
    chunks.append(denoiser.flush())
    stamps, values = collect(chunks)
    np.testing.assert_array_equal(stamps, data["t_acc"])
    assert np.max(np.abs(values - expected)) <= (1e-12 if dropin else 1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_chunkings_of_60_s_equal_batch(model, seed):
    data = stream(60, CELLS, seed=10 + seed)
    b_stamps, b_values, _ = denoise_batch(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model
    )
    denoiser = StreamingDenoiser(model)
    chunks = push_random_chunks(denoiser, data, np.random.default_rng(seed))
    stats = denoiser.stats  # the node's cheap count agrees with the stats
    assert denoiser.samples_pending == stats.samples_in - stats.samples_out > 0  # none bad
    stamps, values = collect(chunks + [denoiser.flush()])
    np.testing.assert_array_equal(stamps, b_stamps)
    assert np.max(np.abs(values - b_values)) <= 1e-12
    assert len(stamps) == len(data["t_acc"])


def test_samples_pending_leaves_out_what_is_never_output(model):
    """Bad and out-of-order samples are counted, never output: nothing is pending after a
    flush (a live node takes pending samples for blocks held back)."""
    data = stream(2, CELLS[:2], seed=6)
    accel, stamps = data["accel"].copy(), data["t_acc"].copy()
    accel[100:400:7] = np.nan  # 43 bad samples, each bridged
    stamps[1000], stamps[1001] = stamps[1001], stamps[1000]  # one goes back: dropped
    denoiser = StreamingDenoiser(model)
    denoiser.push_joint_states(data["t_joint"], data["velocity"])
    denoiser.push_sensor(stamps, accel)
    denoiser.flush()
    stats = denoiser.stats
    assert stats.samples_bad == 43 and stats.dropped_out_of_order == 1
    assert stats.samples_out == len(stamps) - 44 and denoiser.samples_pending == 0


def test_combined_channel_streaming_equals_batch_and_reduces_noise(model):
    data = stream(10, CELLS[1:4], seed=5)
    _, b_values, _ = denoise_batch(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model, channels="combined"
    )
    denoiser = StreamingDenoiser(model, channels="combined")
    _, values = collect(
        push_random_chunks(denoiser, data, np.random.default_rng(3)) + [denoiser.flush()]
    )
    assert np.max(np.abs(values - b_values)) <= 1e-12
    raw = bandpassed(data["accel"], "combined")
    # Pure ego-noise: subtraction of mean + std removes most of it.
    assert np.mean(np.abs(values)) < 0.3 * np.mean(np.abs(raw))


@pytest.mark.parametrize("output", ["bandpassed", "dropin"])
def test_no_joint_state_passes_the_signal_and_counts(model, caplog, output):
    data = stream(2, [(1.5, 0.0)], seed=2)
    denoiser = StreamingDenoiser(model, channels="per_axis", output=output)
    with caplog.at_level(logging.WARNING, logger="egovib_ros.core"):
        chunks = [denoiser.push_sensor(data["t_acc"], data["accel"]), denoiser.flush()]
    _, values = collect(chunks)
    expected = data["accel"] if output == "dropin" else bandpassed(data["accel"], "per_axis")
    assert np.max(np.abs(values - expected)) <= 1e-9
    assert denoiser.stats.blocks_no_joint_state == denoiser.stats.blocks > 0
    assert "no joint state" in caplog.text


def test_stale_joint_state_is_held_briefly_then_missing(model):
    data = stream(2, [(1.5, 0.0)], seed=2)
    denoiser = StreamingDenoiser(model)  # max_hold_s 0.05
    denoiser.push_joint_states(data["t_joint"][:200], data["velocity"][:200])  # first 0.2 s only
    denoiser.push_sensor(data["t_acc"], data["accel"])
    denoiser.flush()
    stats = denoiser.stats
    assert stats.blocks_held_joint_state >= 1
    assert stats.blocks_no_joint_state > stats.blocks // 2


def test_bad_samples_are_missing_counted_and_never_output(model):
    data = stream(2, [(1.5, 0.02)], seed=3)
    accel = data["accel"].copy()
    accel[[100, 101, 2000], 1] = [np.nan, np.inf, -np.inf]
    accel[3000, 2] = 1e181  # flipped bytes: far beyond the sensor's +-78.5
    stamps, values, stats = denoise_batch(
        data["t_acc"], accel, data["t_joint"], data["velocity"], model
    )
    assert np.all(np.isfinite(values)) and len(values) == len(accel) - 4
    assert stats.samples_bad == 4 and stats.gap_filled_samples == 4
    assert not np.isin(data["t_acc"][[100, 101, 2000, 3000]], stamps).any()
    # bridged like any short gap: the same as never having received those samples
    keep = np.ones(len(accel), dtype=bool)
    keep[[100, 101, 2000, 3000]] = False
    _, gapped, _ = denoise_batch(
        data["t_acc"][keep], data["accel"][keep], data["t_joint"], data["velocity"], model
    )
    np.testing.assert_array_equal(values, gapped)


def test_gaps_small_filled_long_reset_out_of_order_dropped_and_streaming_agrees(model):
    data = stream(4, [(1.5, 0.02)], seed=4)
    keep = np.ones(len(data["t_acc"]), dtype=bool)
    keep[1000:1003] = False  # 3 missing samples: bridged
    keep[5000:5600] = False  # 0.2 s gap: segment ends, filter restarts
    t_acc, accel = data["t_acc"][keep], data["accel"][keep]
    t_acc = t_acc.copy()
    t_acc[[7000, 7001]] = t_acc[[7001, 7000]]  # one sample out of order
    stamps, values, stats = denoise_batch(t_acc, accel, data["t_joint"], data["velocity"], model)
    # 3 bridged + 1: dropping the late sample leaves a one-sample hole, bridged too.
    assert stats.gap_filled_samples == 4
    assert stats.resets == 1
    assert stats.dropped_out_of_order == 1
    assert len(stamps) == len(t_acc) - 1 and np.all(np.diff(stamps) > 0)
    data_gappy = dict(data, t_acc=t_acc, accel=accel)
    denoiser = StreamingDenoiser(model)
    s_stamps, s_values = collect(
        push_random_chunks(denoiser, data_gappy, np.random.default_rng(9)) + [denoiser.flush()]
    )
    np.testing.assert_array_equal(s_stamps, stamps)
    assert np.max(np.abs(s_values - values)) <= 1e-12


def test_out_of_grid_velocity_uses_edge_cells_and_is_counted(model):
    data = stream(2, [(5.0, 0.02)], seed=6)
    edge = dict(data, velocity=np.minimum(data["velocity"], 3.0))
    _, outside, stats = denoise_batch(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model
    )
    _, clamped, _ = denoise_batch(
        edge["t_acc"], edge["accel"], edge["t_joint"], edge["velocity"], model
    )
    assert stats.blocks_out_of_grid == stats.blocks
    np.testing.assert_array_equal(outside, clamped)


def _beyond_grid(model, caplog, wrist: float, source: str) -> tuple[int, list[str]]:
    """(blocks counted beyond the grid, the warnings) of a denoiser over 2 s at `wrist` rad/s."""
    data = stream(2, [(wrist, 0.02)], seed=6)
    denoiser = StreamingDenoiser(model, source=source)
    with caplog.at_level(logging.WARNING, logger="egovib_ros.core"):
        denoiser.push_joint_states(data["t_joint"], data["velocity"])
        denoiser.push_sensor(data["t_acc"], data["accel"])
        denoiser.flush()
    warned = [r.getMessage() for r in caplog.records if "beyond the model grid" in r.getMessage()]
    return denoiser.stats.blocks_out_of_grid, warned


def test_the_out_of_grid_warning_names_the_recording(model, caplog):
    """`detect` and `evaluate` run the denoiser over the calibration bag too: the warning says
    which recording went beyond the grid (it was the sweep, not the run)."""
    blocks, warned = _beyond_grid(model, caplog, 5.0, "sweep: /accelerometer/raw")
    assert blocks > 0
    assert warned == [
        "sweep: /accelerometer/raw: joint velocity beyond the model grid by more than half a "
        "cell: using the edge cells (calibrate at the speeds the robot runs at)"
    ]


def test_a_sweep_overshooting_its_top_speed_a_little_is_inside_the_grid(model, caplog):
    """The edge cell is the cell of a dwell at the top speed that overshoots it a little (the
    example arm's simulated sweep: 0.7 %): neither counted nor said, by the paper's method
    and hybrid's table alike (noise_model.grid_limits)."""
    top, step = float(model.grid[0][-1]), float(model.grid[0][-1] - model.grid[0][-2])
    assert _beyond_grid(model, caplog, top + 0.3 * step, "sweep") == (0, [])
    assert _beyond_grid(model, caplog, top + 0.6 * step, "sweep")[0] > 0


def test_stream_rate_or_block_length_differing_from_model_is_an_error(model):
    data = stream(1, [(0.0, 0.0)])
    denoiser = StreamingDenoiser(model)
    with pytest.raises(StreamError, match="1500 Hz but the model expects 3000 Hz"):
        denoiser.push_sensor((np.arange(1000) * 666_667).astype(np.int64), data["accel"][:1000])
    with pytest.raises(StreamError, match="1500 Hz"):  # and it keeps refusing
        denoiser.push_sensor(
            (np.arange(1000, 1100) * 666_667).astype(np.int64), data["accel"][:100]
        )


def test_bad_shapes_are_errors(model):
    denoiser = StreamingDenoiser(model)
    with pytest.raises(StreamError, match=r"\(N, 3\)"):
        denoiser.push_sensor(np.arange(10, dtype=np.int64), np.zeros((10, 2)))
    with pytest.raises(StreamError, match="joint states"):
        denoiser.push_joint_states(np.arange(10, dtype=np.int64), np.zeros((10, 3)))


def test_oversubtraction_and_floor_options(model):
    data = stream(3, [(1.5, 0.02)], seed=8)
    args = (data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model)
    paper = denoise_batch(*args)[1]
    harder = denoise_batch(*args, oversubtraction=2.0)[1]
    floored = denoise_batch(*args, floor=0.1)[1]
    level = lambda x: np.mean(np.abs(x))  # noqa: E731
    assert level(harder) < level(paper) < level(floored)


def test_joint_states_lagging_the_accelerometer_across_long_gaps_still_equal_batch(model):
    data = stream(6, CELLS[1:5], seed=12)
    keep = np.ones(len(data["t_acc"]), dtype=bool)
    for start in (3000, 9000, 14000):
        keep[start : start + 300] = False  # 0.1 s gaps: each ends a segment
    data = dict(data, t_acc=data["t_acc"][keep], accel=data["accel"][keep])
    b_stamps, b_values, stats = denoise_batch(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model
    )
    assert stats.resets == 3
    denoiser = StreamingDenoiser(model)  # joint states arrive 10 ms late (< joint_wait 20 ms)
    chunks = push_random_chunks(denoiser, data, np.random.default_rng(4), joint_lead_ns=-10_000_000)
    stamps, values = collect(chunks + [denoiser.flush()])
    np.testing.assert_array_equal(stamps, b_stamps)
    assert np.max(np.abs(values - b_values)) <= 1e-12


@pytest.mark.parametrize("length,hop", [(64, 16), (32, 16)])
def test_other_block_settings_keep_latency_and_streaming_equal_batch(length, hop):
    data = stream(6, CELLS[:4], seed=13)
    model, _ = calibrate_arrays(
        data["t_acc"],
        data["accel"],
        data["t_joint"],
        data["velocity"],
        block_length=length,
        hop=hop,
    )
    denoiser = StreamingDenoiser(model)
    assert denoiser.delay_samples == (length - hop, length - 1)
    denoiser.push_joint_states(data["t_joint"], data["velocity"])
    emitted, chunks = 0, []
    for n in range(1, 400):
        chunks.append(denoiser.push_sensor(data["t_acc"][n - 1 : n], data["accel"][n - 1 : n]))
        emitted += len(chunks[-1])
        if n >= length:
            assert length - hop <= n - emitted <= length - 1
    chunks += [denoiser.push_sensor(data["t_acc"][399:], data["accel"][399:]), denoiser.flush()]
    stamps, values = collect(chunks)
    b_stamps, b_values, _ = denoise_batch(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model
    )
    np.testing.assert_array_equal(stamps, b_stamps)
    assert np.max(np.abs(values - b_values)) <= 1e-12


def test_dead_axis_with_spectral_floor_stays_finite(model):
    data = stream(1, [(1.5, 0.02)], seed=14)
    accel = np.zeros_like(data["accel"])  # a sensor delivering exact zeros
    _, values, _ = denoise_batch(
        data["t_acc"], accel, data["t_joint"], data["velocity"], model, floor=1.0
    )
    assert np.all(values == 0)


def test_leading_nonfinite_samples_are_dropped_not_zeroed(model):
    data = stream(2, [(1.5, 0.02)], seed=15)
    accel = data["accel"].copy()
    accel[:5] = np.nan  # nothing to hold yet
    stamps, values, stats = denoise_batch(
        data["t_acc"], accel, data["t_joint"], data["velocity"], model
    )
    clean_stamps, clean, _ = denoise_batch(
        data["t_acc"][5:], data["accel"][5:], data["t_joint"], data["velocity"], model
    )
    np.testing.assert_array_equal(stamps, clean_stamps)
    np.testing.assert_array_equal(values, clean)  # no zero-to-gravity step ringing like a tap


def test_backward_clock_jump_restarts_instead_of_dropping_everything(model):
    first, second = stream(2, [(1.5, 0.02)], seed=16), stream(2, [(1.5, 0.02)], seed=17)
    assert second["t_acc"][0] < first["t_acc"][-1]  # a bag played in a loop
    denoiser = StreamingDenoiser(model)
    rng = np.random.default_rng(5)
    chunks = push_random_chunks(denoiser, first, rng) + push_random_chunks(denoiser, second, rng)
    stamps, values = collect(chunks + [denoiser.flush()])
    expected = np.concatenate([first["t_acc"], second["t_acc"]])
    np.testing.assert_array_equal(stamps, expected)
    stats = denoiser.stats
    assert stats.resets == 1 and stats.dropped_out_of_order == stats.joint_states_dropped == 0
    assert stats.blocks_no_joint_state == 0 and np.all(np.isfinite(values))


def test_stream_errors_name_their_source(model):
    denoiser = StreamingDenoiser(model, source="/accelerometer/raw")
    with pytest.raises(StreamError, match=r"^/accelerometer/raw: sensor chunk"):
        denoiser.push_sensor(np.arange(4, dtype=np.int64), np.zeros((4, 2)))


def test_a_mostly_bad_recording_is_refused_not_denoised(model):
    from egovib_ros.core import check_bad_share

    data = stream(2, [(1.5, 0.02)], seed=21)
    accel = data["accel"].copy()
    accel[: len(accel) // 4] = np.nan  # 25 % bad
    _, _, stats = denoise_batch(data["t_acc"], accel, data["t_joint"], data["velocity"], model)
    assert stats.samples_bad == len(accel) // 4
    with pytest.raises(
        StreamError, match=r"bag.mcap: 1500 of 6000 sensor samples \(25.0 %\) are bad"
    ):
        check_bad_share(stats, "bag.mcap")
    check_bad_share(stats, "bag.mcap", limit=0.3)


def test_stats_are_typed_frozen_and_report_the_paper_denoisers_keys(model):
    """`stats` is a DenoiserStats read by attribute; as_dict() gives what reports and
    /diagnostics have always shown for the paper's method (no per-sample-method fields)."""
    import dataclasses

    data = stream(1, [(1.5, 0.02)], seed=4)
    accel = data["accel"].copy()
    accel[50, 0] = np.nan
    _, _, stats = denoise_batch(data["t_acc"], accel, data["t_joint"], data["velocity"], model)
    assert stats.samples_bad == 1 and stats.method is None
    with pytest.raises(dataclasses.FrozenInstanceError):
        stats.samples_bad = 0
    assert list(stats.as_dict()) == [
        "samples_in",
        "samples_out",
        "dropped_out_of_order",
        "samples_bad",
        "gap_filled_samples",
        "resets",
        "joint_states_in",
        "joint_states_dropped",
        "blocks",
        "blocks_held_joint_state",
        "blocks_no_joint_state",
        "blocks_out_of_grid",
        "blocks_unmeasured",
        "rate_checked",
        "duplicates",
        "joint_states_duplicates",
    ]


def test_a_noise_gain_over_time_follows_a_warm_up_and_streaming_equals_batch(model):
    """The vibration 6 dB louder from 5 s on (a warm-up the gap diagnosis fits as drift):
    with noise_gain_db following it, more of it is removed after 5 s and the same before;
    any chunking gives the batch result; bad knots are refused in one line."""
    from egovib_ros.errors import ConfigError

    data = stream(10, CELLS[1:4], seed=7)
    t = (data["t_acc"] - data["t_acc"][0]) / 1e9
    louder = data["accel"].copy()
    louder[t >= 5.0] = (louder[t >= 5.0] - [0.0, 0.0, 9.81]) * 2.0 + [0.0, 0.0, 9.81]
    data = {**data, "accel": louder}
    knots = ((0.0, 0.0), (4.9, 0.0), (5.1, 6.0))  # flat beyond the last knot
    arrays = (data["t_acc"], louder, data["t_joint"], data["velocity"])
    _, plain, _ = denoise_batch(*arrays, model, channels="combined")
    _, followed, _ = denoise_batch(*arrays, model, channels="combined", noise_gain_db=knots)
    raw = bandpassed(louder, "combined")
    late, early = t >= 5.5, (t > 0.5) & (t < 4.5)

    def reduction(values, rows):
        return 20 * np.log10(np.mean(np.abs(raw[rows])) / np.mean(np.abs(values[rows])))

    assert reduction(followed, late) > reduction(plain, late) + 3.0
    assert reduction(followed, early) == pytest.approx(reduction(plain, early), abs=1e-9)
    denoiser = StreamingDenoiser(model, channels="combined", noise_gain_db=knots)
    _, values = collect(
        push_random_chunks(denoiser, data, np.random.default_rng(4)) + [denoiser.flush()]
    )
    assert np.max(np.abs(values - followed)) <= 1e-12
    # joint states only from 0.5 s: the first blocks pass through, elapsed time still
    # counts from the first block, in batch and streamed alike
    late_joints = data["t_joint"] >= data["t_acc"][0] + 500_000_000
    data = {
        **data,
        "t_joint": data["t_joint"][late_joints],
        "velocity": data["velocity"][late_joints],
    }
    arrays = (data["t_acc"], louder, data["t_joint"], data["velocity"])
    _, batch, _ = denoise_batch(*arrays, model, channels="combined", noise_gain_db=knots)
    denoiser = StreamingDenoiser(model, channels="combined", noise_gain_db=knots)
    _, values = collect(
        push_random_chunks(denoiser, data, np.random.default_rng(5), max_chunk=40)
        + [denoiser.flush()]
    )
    assert np.max(np.abs(values - batch)) <= 1e-12
    for bad in (((1.0, 0.0), (0.5, 1.0)), ((0.0, 40.0),), ((0.0, float("nan")),), ((0.0,),)):
        with pytest.raises(ConfigError, match="noise_gain_db"):
            StreamingDenoiser(model, noise_gain_db=bad)
