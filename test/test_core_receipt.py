"""egovib_ros.core.receipt: sensor streams stamped on receipt (a driver stamping each message
as it reads it: a USB IMU's packets, a serial link's latency) are told from streams stamped
at their samples, and are counted on a rebuilt sample clock instead of being refused as a
wrong rate or bridged into invented samples.

The stamps below trail true sample times the way such drivers do: every sample of a 1 ms
USB frame stamped at the frame's end plus up to 0.2 ms of host latency, or each sample late
by 0 to 2 ms. What the framer sees of them must be what it sees of the true stamps: the same
samples in the same blocks, no bridged sample, no restart, the rate accepted; a stream at
the wrong rate is still refused, and a stream stamped at its samples is treated as before
(bit for bit, without waiting)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from synthetic import CELLS, FS, calibrated_model, push_random_chunks, stream

from egovib_ros.core import StreamingDenoiser, denoise_batch
from egovib_ros.core.receipt import ReceiptClock, receipt_latency
from egovib_ros.core.stream import PROBE_EARLY, BlockFramer, FramerSettings
from egovib_ros.errors import StreamError

PERIOD_NS = 1e9 / FS


def usb_frames(t_ns: np.ndarray, seed: int = 0, frame_ns: int = 1_000_000) -> np.ndarray:
    """Receipt stamps of samples read in USB frames: each frame's samples stamped at its end
    plus 0-0.2 ms of host latency, in order (each message's own now())."""
    rng = np.random.default_rng(seed)
    frame_end = (t_ns // frame_ns + 1) * frame_ns
    late = frame_end + rng.integers(0, 200_000, len(t_ns))
    return np.maximum.accumulate(late) + np.arange(len(t_ns))


def random_latency(t_ns: np.ndarray, seed: int = 0, max_ns: int = 2_000_000) -> np.ndarray:
    """Receipt stamps 0 to `max_ns` late, in order."""
    rng = np.random.default_rng(seed)
    return np.maximum.accumulate(t_ns + rng.integers(0, max_ns, len(t_ns))) + np.arange(len(t_ns))


def grid(n: int) -> np.ndarray:
    return (5_000_000 + np.round(np.arange(n) * PERIOD_NS)).astype(np.int64)


@pytest.fixture(scope="module")
def model():
    return calibrated_model()


@pytest.fixture(scope="module")
def motion():
    return stream(6, CELLS, seed=3)


def test_sample_stamps_are_not_receipt_stamps():
    rng = np.random.default_rng(1)
    t = grid(128)
    per_step = np.concatenate([[0], np.cumsum(rng.uniform(0.7, 1.3, 127) * PERIOD_NS)])
    lost = np.delete(t, rng.choice(np.arange(1, 127), 6, replace=False))
    for stamps in (t, t[0] + per_step.astype(np.int64), lost):
        assert receipt_latency(stamps, PERIOD_NS) is None


def test_receipt_stamps_are_told_with_their_latency():
    t = grid(128)
    usb = receipt_latency(usb_frames(t), PERIOD_NS)
    late = receipt_latency(random_latency(t), PERIOD_NS)
    assert usb is not None and 0.6e6 < usb < 1.4e6  # a frame (1 ms) plus host latency
    assert late is not None and 1.0e6 < late < 2.2e6
    # at another rate too: the rate check refuses it, measured as receipt stamps show it
    assert receipt_latency(usb_frames(grid(256)[::2]), PERIOD_NS) is not None


def test_the_rebuilt_clock_finds_a_long_gap_and_invents_nothing_else():
    t = grid(6000)
    stamps = usb_frames(t, seed=2)
    clock = ReceiptClock(PERIOD_NS, receipt_latency(stamps[:128], PERIOD_NS), max_fill=100)
    missing, times = clock.gaps(stamps)
    assert missing.sum() == 0
    assert np.mean(np.diff(times)) == pytest.approx(PERIOD_NS, rel=1e-3)
    # 30 samples (10 ms, beyond any latency seen) lost at sample 3000, in chunks
    kept = np.delete(stamps, np.arange(3000, 3030))
    clock = ReceiptClock(PERIOD_NS, receipt_latency(kept[:128], PERIOD_NS), max_fill=100)
    missing = np.concatenate([clock.gaps(part)[0] for part in np.array_split(kept, 7)])
    assert np.flatnonzero(missing).tolist() == [3000]
    assert abs(int(missing[3000]) - 30) <= 3  # within the frame's latency


@pytest.mark.parametrize("restamp", [usb_frames, random_latency])
def test_a_receipt_stamped_stream_is_framed_like_its_sample_stamps(model, motion, restamp):
    data = dict(motion, t_acc=restamp(motion["t_acc"]))
    stamps, values, stats = denoise_batch(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model
    )
    want_stamps, want_values, want = denoise_batch(
        motion["t_acc"], motion["accel"], motion["t_joint"], motion["velocity"], model
    )
    assert stats.rate_checked and stats.gap_filled_samples == 0 and stats.resets == 0
    np.testing.assert_array_equal(stamps, data["t_acc"])  # the stamps go out as they came
    assert stats.blocks == want.blocks
    # the blocks hold the same samples; only joint states matched 0-2 ms later can differ
    same = np.isclose(values, want_values, rtol=0, atol=1e-12).all(axis=1)
    assert same.mean() > 0.9


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000), max_chunk=st.sampled_from([5, 64, 400]))
def test_receipt_stamps_stream_equal_batch_for_any_chunking(model, motion, seed, max_chunk):
    data = dict(motion, t_acc=usb_frames(motion["t_acc"], seed=seed % 7))
    denoiser = StreamingDenoiser(model)
    outputs = push_random_chunks(denoiser, data, np.random.default_rng(seed), max_chunk=max_chunk)
    outputs.append(denoiser.flush())
    got = np.concatenate([c.values for c in outputs if c is not None and len(c)])
    _, want, _ = denoise_batch(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model
    )
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("frame_ms", [1, 4])
@pytest.mark.parametrize("rate", [0.5, 0.85, 1.15, 2.0])
def test_receipt_stamps_at_the_wrong_rate_are_refused_at_the_rate_they_show(
    model, motion, rate, frame_ms
):
    """Half the rate in 4 ms frames used to restart the stream at every frame and pass."""
    t = motion["t_acc"]
    stamps = usb_frames(t[0] + ((t - t[0]) / rate).astype(np.int64), frame_ns=frame_ms * 10**6)
    with pytest.raises(StreamError, match="runs at (\\d+) Hz but the model expects 3000") as err:
        denoise_batch(stamps, motion["accel"], motion["t_joint"], motion["velocity"], model)
    shown = float(str(err.value).split("runs at ")[1].split(" Hz")[0])
    assert shown == pytest.approx(FS * rate, rel=0.03)


@pytest.mark.parametrize("frame_ms", [4, 10])
def test_big_frames_and_a_clock_a_few_percent_off_are_accepted(model, motion, frame_ms):
    """An IMU read from its FIFO every 10 ms, stamped as read: latency up to 10 ms. The rate
    is measured on the least late samples (the first window used to see 3750 Hz)."""
    t = motion["t_acc"]
    for rate in (0.92, 0.97, 1.0, 1.05, 1.08):
        clock = t[0] + ((t - t[0]) / rate).astype(np.int64)
        for stamps in (usb_frames(clock, frame_ns=frame_ms * 10**6), random_latency(clock)):
            _, _, stats = denoise_batch(
                stamps, motion["accel"], motion["t_joint"], motion["velocity"], model
            )
            assert stats.rate_checked and stats.gap_filled_samples == 0, (frame_ms, rate, stats)


def test_what_the_stamps_mark_is_told_on_the_first_samples_whatever_the_chunking(model, motion):
    """A receipt stream that stops 2 s after 1 s: batch (one chunk) and any streaming
    chunking decide alike, on the first samples, and give the same output."""
    keep = np.r_[0:3000, 9000 : len(motion["t_acc"])]
    data = dict(motion, t_acc=usb_frames(motion["t_acc"])[keep], accel=motion["accel"][keep])
    _, want, stats = denoise_batch(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model
    )
    assert stats.resets == 1 and stats.gap_filled_samples == 0
    for max_chunk in (3, 50, 700):
        denoiser = StreamingDenoiser(model)
        chunks = push_random_chunks(denoiser, data, np.random.default_rng(max_chunk), max_chunk)
        chunks.append(denoiser.flush())
        got = np.concatenate([c.values for c in chunks if c is not None and len(c)])
        np.testing.assert_array_equal(got, want)


def test_bad_samples_of_a_receipt_stream_are_bridged_in_their_slots(model, motion):
    data = dict(motion, t_acc=usb_frames(motion["t_acc"]), accel=motion["accel"].copy())
    data["accel"][[500, 900, 2000, 2001, 2002, 2003, 2004]] = np.nan
    _, _, stats = denoise_batch(
        data["t_acc"], data["accel"], data["t_joint"], data["velocity"], model
    )
    assert stats.samples_bad == 7 and stats.gap_filled_samples == 7 and stats.resets == 0


def test_nothing_in_gives_nothing_out(model):
    assert len(StreamingDenoiser(model).flush()) == 0
    stamps, values, stats = denoise_batch(
        np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 2)), model
    )
    assert len(stamps) == len(values) == stats.samples_in == 0


def test_stamps_that_turn_to_receipt_times_mid_stream_are_named(model, motion):
    t = motion["t_acc"]
    stamps = np.concatenate([t[:6000], usb_frames(t[6000:])])
    with pytest.raises(StreamError, match="stamped on receipt from there on"):
        denoise_batch(stamps, motion["accel"], motion["t_joint"], motion["velocity"], model)


def test_stamps_set_to_sample_refuse_receipt_stamps_as_before(motion):
    framer = BlockFramer(FramerSettings(stamps="sample", source="imu"), n_joints=2)
    with pytest.raises(StreamError, match="imu: sensor stream runs at"):
        framer.push_sensor(usb_frames(motion["t_acc"])[:400], motion["accel"][:400])


def test_a_packet_stamped_once_is_refused_naming_the_repeated_stamps(model, motion):
    packets = (motion["t_acc"] // 1_000_000 + 1) * 1_000_000  # one stamp per 1 ms packet
    with pytest.raises(StreamError, match="stamped at or before the one before them"):
        denoise_batch(packets, motion["accel"], motion["t_joint"], motion["velocity"], model)


def test_sample_stamps_wait_only_for_the_first_few_samples():
    settings_ = FramerSettings(source="imu")
    framer = BlockFramer(settings_, n_joints=2)
    t = grid(200)
    framer.push_sensor(t[: PROBE_EARLY - 1], np.zeros((PROBE_EARLY - 1, 3)))
    assert framer.backlog[0] >= PROBE_EARLY - 1 and framer._cleaner.kind is None
    framer.push_sensor(t[PROBE_EARLY - 1 : PROBE_EARLY], np.zeros((1, 3)))
    assert framer._cleaner.kind == "sample" and framer._cleaner.waiting == 0
    # receipt stamps wait for the whole probe, then are told
    framer = BlockFramer(settings_, n_joints=2)
    stamps = usb_frames(t)
    framer.push_sensor(stamps[:100], np.zeros((100, 3)))
    assert framer._cleaner.kind is None and framer._cleaner.waiting == 100
    framer.push_sensor(stamps[100:], np.zeros((100, 3)))
    assert framer._cleaner.kind == "receipt" and framer.stats.receipt_latency_ns > 0


def test_receipt_stamps_the_first_samples_cannot_tell_can_be_named():
    """A 1 kHz sensor read in 1 ms USB frames steps a period, or two when its clock runs
    slow and a frame comes empty: stamps alike to a sample clock losing samples, which is
    what `auto` reads (bridging the empty frames). stamps="receipt" counts them right."""
    t = (10**12 + np.round(np.arange(20_000) * 1e6 / 0.97)).astype(np.int64)  # 3 % slow
    stamps = usb_frames(t)
    got = {}
    for kind in ("auto", "receipt"):
        settings_ = FramerSettings(
            sample_rate_hz=1000.0, band_hz=(50.0, 400.0), stamps=kind, source="imu"
        )
        framer = BlockFramer(settings_, n_joints=2)
        framer.push_sensor(stamps, np.zeros((len(stamps), 3)))
        framer.flush()
        got[kind] = (framer.stamps, framer.stats.gap_filled_samples, framer.rate_checked)
    assert got["auto"][0] == "sample" and got["auto"][1] > 300
    assert got["receipt"] == ("receipt", 0, True)


def test_a_profile_saying_receipt_stamps_reaches_every_framer_through_the_model(model):
    """sensor.stamps in the robot profile (the model carries it): the calibrator's and every
    denoiser's framing take it, so every command and node reads the stream alike."""
    import dataclasses

    from egovib_ros.core import CalibrationAccumulator
    from egovib_ros.robot import load_profile

    profile = dataclasses.replace(load_profile(), sensor_stamps="receipt")
    assert CalibrationAccumulator(profile=profile).settings.stamps == "receipt"
    usb_model = model.replace(profile=profile)
    assert FramerSettings.for_model(usb_model, layout="per_axis").stamps == "receipt"
    assert StreamingDenoiser(usb_model).settings.stamps == "receipt"
    assert FramerSettings.for_model(model, layout="per_axis").stamps == "auto"
