"""The sample rate is checked all along the stream, not only at its start.

A stream whose rate changes in the middle (e.g. halves) used to be "bridged": every
step of two periods looked like one missing sample and was filled by interpolation,
seconds of invented samples without a word. Now two windows in a row off by more than
the framer's tolerance are a rate mismatch (StreamError naming the source, and on every
later push), for any chunking. Jitter (+-30 % per step, random or alternating), lost
samples (up to a third, scattered) and a short glitch stay what they were: bridged and
counted.
"""

import numpy as np
import pytest
from synthetic import FS, push_random_chunks, stream

from egovib_ros.core import StreamingDenoiser, calibrate_arrays, denoise_batch
from egovib_ros.core.stream import RATE_WINDOW_BLOCKS, measured_period
from egovib_ros.errors import StreamError

CELLS = [(0.0, 0.0), (1.5, 0.0), (0.0, 0.02), (1.5, 0.02), (-3.0, -0.04), (0.9, -0.012)]
PERIOD_NS = 1e9 / FS
SOURCE = "bag: /accelerometer/raw"


@pytest.fixture(scope="module")
def model():
    data = stream(24, CELLS, sigma=[0.2, 1.0, 0.6, 1.3, 2.0, 0.8])
    model, _ = calibrate_arrays(data["t_acc"], data["accel"], data["t_joint"], data["velocity"])
    return model


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


def test_measured_period_ignores_jitter_and_lost_samples_but_sees_a_slower_clock():
    rng = np.random.default_rng(0)
    p = 1.0
    assert measured_period(1 + rng.uniform(-0.3, 0.3, 256), p) == pytest.approx(1, abs=0.03)
    alternating = np.tile([0.7, 1.3], 128)[:255]  # an odd count: a median picks one side
    assert np.median(alternating) == pytest.approx(0.7)
    assert measured_period(alternating, p) == pytest.approx(1, abs=0.01)
    lost = np.where(rng.random(256) < 0.3, 2.0, 1.0)  # 30 % of the steps skip a sample
    assert measured_period(lost, p) == pytest.approx(1)
    assert measured_period(np.full(256, 2.0), p) == pytest.approx(2)  # the rate halved
    assert measured_period(np.full(256, 0.5), p) == pytest.approx(0.5)  # doubled
    assert measured_period(np.full(256, 1.25), p) == pytest.approx(1.25)  # 20 % slower


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
        assert stats["gap_filled_samples"] > 0  # bridged and counted, as before
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
    assert len(stamps) == len(data["t_acc"]) and stats["gap_filled_samples"] == 250


def test_calibration_refuses_a_rate_change_too(motion):
    data = rate_changed_at(motion, 3.0, 0.5, np.random.default_rng(1))
    with pytest.raises(StreamError, match="sensor rate changed.*1500 Hz"):
        calibrate_arrays(data["t_acc"], data["accel"], data["t_joint"], data["velocity"])
