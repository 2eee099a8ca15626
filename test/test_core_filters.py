"""Axis handling, band-pass with carried state, window and overlap-add."""

import numpy as np
import pytest
from scipy import signal

from egovib_ros.core import BandPass, analysis_window, channel_matrix, filters, overlap_add
from egovib_ros.core.blocks import validate_blocking
from egovib_ros.errors import ConfigError, StreamError


def test_channel_layouts():
    accel = np.arange(12.0).reshape(4, 3)
    np.testing.assert_array_equal(channel_matrix(accel, "combined")[:, 0], accel.sum(axis=1))
    np.testing.assert_array_equal(channel_matrix(accel, "per_axis"), accel)
    assert channel_matrix(accel, "all").shape == (4, 4)
    with pytest.raises(ConfigError, match="unknown layout"):
        channel_matrix(accel, "xyz")
    with pytest.raises(StreamError, match=r"\(N, 3\)"):
        channel_matrix(accel[:, :2], "combined")


@pytest.mark.parametrize("use_kernel", [True, False])
def test_bandpass_chunked_equals_whole_and_scipy(monkeypatch, use_kernel):
    if not use_kernel:
        monkeypatch.setattr(filters, "_SOS_KERNEL", None)
    x = np.random.default_rng(0).normal(size=(3, 5000)) + 9.81
    whole = BandPass(sample_rate_hz=3000, band_hz=(150, 750), order=4, n_channels=3).process(x)
    bp = BandPass(sample_rate_hz=3000, band_hz=(150, 750), order=4, n_channels=3)
    cuts = np.sort(np.random.default_rng(1).choice(5000, 40, replace=False))
    chunked = np.concatenate([bp.process(part) for part in np.split(x, cuts, axis=1)], axis=1)
    np.testing.assert_array_equal(chunked, whole)
    sos = bp.sos
    reference = signal.sosfilt(
        sos, x, axis=-1, zi=signal.sosfilt_zi(sos)[:, None, :] * x[None, :, 0, None]
    )[0]
    np.testing.assert_allclose(whole, reference, rtol=0, atol=1e-12)
    # Steady-state start: a constant (gravity) input gives no ringing at all.
    flat = BandPass(sample_rate_hz=3000, band_hz=(150, 750), order=4, n_channels=1).process(
        np.full((1, 300), 9.81)
    )
    assert np.max(np.abs(flat)) < 1e-9


@pytest.mark.parametrize("use_kernels", [True, False])
def test_carried_lfilter_and_sosfilt_equal_scipy_to_the_bit(monkeypatch, use_kernels):
    if not use_kernels:
        monkeypatch.setattr(filters, "_LFILTER_KERNEL", None)
        monkeypatch.setattr(filters, "_SOS_KERNEL", None)
    rng = np.random.default_rng(4)
    x1, x2 = rng.normal(size=37), rng.normal(size=(37, 4))
    for b, a in (([1.0], [1.0, -1.0]), signal.iirpeak(1000, 8, fs=3000), ([0.2], [1.0, -0.8])):
        zi1 = rng.normal(size=len(a) - 1)
        y, zf = filters.lfilter_carried(b, a, x1, list(zi1))  # a list, as a caller may give
        want_y, want_zf = signal.lfilter(b, a, x1, zi=zi1)
        assert np.array_equal(y, want_y) and np.array_equal(zf, want_zf)
        zi2 = rng.normal(size=(len(a) - 1, 4))
        y, zf = filters.lfilter_carried(b, a, x2, zi2, axis=0)
        want_y, want_zf = signal.lfilter(b, a, x2, axis=0, zi=zi2)
        assert np.array_equal(y, want_y) and np.array_equal(zf, want_zf)
    sos = signal.butter(3, [100, 900], btype="band", fs=3000, output="sos")
    zi = rng.normal(size=(sos.shape[0], 2))
    y, zf = filters.sosfilt_carried(sos, x1, zi)
    want_y, want_zf = signal.sosfilt(sos, x1, zi=zi)
    assert np.array_equal(y, want_y) and np.array_equal(zf, want_zf)
    assert np.array_equal(x1, np.random.default_rng(4).normal(size=37))  # input untouched


def test_bandpass_rejects_bad_settings():
    with pytest.raises(ConfigError, match="Nyquist"):
        BandPass(sample_rate_hz=1000, band_hz=(150, 750), order=4, n_channels=1)
    with pytest.raises(ConfigError, match="band_order"):
        BandPass(sample_rate_hz=3000, band_hz=(150, 750), order=0, n_channels=1)


def test_window_sums_to_one_and_overlap_add_reconstructs():
    for length, hop in [(64, 32), (32, 16), (64, 16)]:
        window = analysis_window(length, hop)
        shifted = sum(np.roll(np.tile(window, 4), k * hop) for k in range(length // hop))
        np.testing.assert_allclose(shifted, 1.0, atol=1e-12)
    window = analysis_window(64, 32)
    x = np.random.default_rng(2).normal(size=(64 * 10, 1))
    padded = np.concatenate([np.zeros((32, 1)), x, np.zeros((64, 1))])
    blocks = np.stack(
        [padded[i : i + 64] * window[:, None] for i in range(0, len(padded) - 63, 32)]
    )
    y = overlap_add(blocks, 32)
    np.testing.assert_allclose(y[32 : 32 + len(x)], x, atol=1e-12)


def test_blocking_validation_messages():
    with pytest.raises(ConfigError, match="hop: must divide"):
        validate_blocking(64, 24)
    with pytest.raises(ConfigError, match="must overlap"):
        validate_blocking(64, 64)
    with pytest.raises(ConfigError, match="block_length"):
        validate_blocking(2, 1)


@pytest.mark.parametrize(
    "fs, band", [(3000.0, (150.0, 750.0)), (1000.0, (80.0, 450.0)), (250.0, (40.0, 110.0))]
)
def test_the_dropin_split_passes_gravity_and_stops_the_band_with_no_phase(fs, band):
    freqs = np.linspace(0.0, fs / 2, 4000)
    for delay in (int(0.004 * fs), int(0.010 * fs)):
        taps = filters.split_taps(sample_rate_hz=fs, band_hz=band, delay=delay)
        assert len(taps) == 2 * delay + 1 and np.allclose(taps, taps[::-1])  # linear phase
        response = np.abs(signal.freqz(taps, worN=freqs, fs=fs)[1])
        assert taps.sum() == pytest.approx(1.0, abs=1e-12)  # gravity passes as it is
        assert response.max() < 1.1  # nothing amplified
    # a longer split stops the band better: 10 ms keep at most 3 % of it (PR2, flight)
    if fs >= 1000:
        assert response[freqs >= band[0]].max() < 0.03
    assert filters.split_taps(sample_rate_hz=fs, band_hz=band, delay=0).tolist() == [1.0]


def test_the_split_takes_as_long_as_the_recordings_noise_near_the_band_asks():
    fs, band = 3000.0, (150.0, 750.0)
    freqs = np.linspace(0.0, fs / 2, 1501)
    inside = ((freqs > 200) & (freqs < 700)).astype(float)
    near_edge = inside + ((freqs > 120) & (freqs < 170))
    args = dict(sample_rate_hz=fs, band_hz=band, order=4, freqs_hz=freqs)
    h = signal.sosfreqz(filters.design_bandpass(sample_rate_hz=fs, band_hz=band, order=4),
                        worN=freqs, fs=fs)[1]  # fmt: skip

    def leak_db(taps, power):
        lp = np.abs(signal.freqz(taps, worN=freqs, fs=fs)[1])
        return 10 * np.log10((power * abs(h) ** 2 * lp**2).sum() / (power * abs(h) ** 2).sum())

    (mid, mid_delay), (edge, edge_delay) = (
        filters.split_for(power=p, **args) for p in (inside, near_edge)
    )
    assert 1 <= mid_delay < edge_delay <= filters.SPLIT_MAX_DELAY_S * fs
    for taps, delay, power in ((mid, mid_delay, inside), (edge, edge_delay, near_edge)):
        assert taps.sum() == pytest.approx(1.0, abs=1e-12)  # gravity passes as it is
        assert leak_db(taps, power) <= filters.SPLIT_LEAK_DB  # its own criterion holds
        # linear phase, or a low-delay split within its bounds of a pure delay below the band
        if len(taps) != 2 * delay + 1:
            assert len(taps) > 2 * delay + 1
            for below, bound in (
                (filters.SPLIT_PASS_FRACTION, filters.SPLIT_PASS_ERROR),
                (filters.SPLIT_TRANSITION_FRACTION, filters.SPLIT_TRANSITION_ERROR),
            ):
                f = freqs[freqs <= below * band[0]]
                error = signal.freqz(taps, worN=f, fs=fs)[1] - np.exp(-2j * np.pi * f / fs * delay)
                assert np.abs(error).max() <= bound
        else:
            assert np.allclose(taps, taps[::-1])
    # fitted to the noise, it stops more of it than the plain design of the same delay ...
    plain = filters.split_taps(sample_rate_hz=fs, band_hz=band, delay=edge_delay)
    assert leak_db(edge, near_edge) < leak_db(plain, near_edge) - 3.0
    # ... and never with less delay than asked (the gain's look-ahead, which it shares)
    taps, delay = filters.split_for(power=inside, min_delay=edge_delay + 3, **args)
    assert delay == edge_delay + 3 and leak_db(taps, inside) <= filters.SPLIT_LEAK_DB


def test_a_low_delay_split_stops_the_band_sooner_than_a_linear_phase_one():
    """The PR2 hand's band at 3 kHz, noise all over it: the linear-phase split that stops it
    needs more delay than the gain's 4 ms look-ahead; a low-delay one stops it in that."""
    fs, band = 3000.0, (150.0, 750.0)
    freqs = np.linspace(0.0, fs / 2, 1501)
    power = ((freqs > 130) & (freqs < 800)).astype(float)
    args = dict(sample_rate_hz=fs, band_hz=band, order=4, freqs_hz=freqs, power=power)
    look_ahead = round(0.004 * fs)
    taps, delay = filters.split_for(min_delay=look_ahead, **args)
    # (the linear-phase split of that delay, tried first, passes more than SPLIT_LEAK_DB)
    assert delay == look_ahead and len(taps) > 2 * delay + 1


def test_the_lines_highpass_is_undone_exactly_at_every_line():
    fs, band = 1000.0, (80.0, 450.0)
    inverse = filters.highpass_inverse(sample_rate_hz=fs, band_hz=band)
    sos = filters.lines_highpass(sample_rate_hz=fs, band_hz=band)
    freqs = np.linspace(0.0, fs / 2, len(inverse))
    response = signal.sosfreqz(sos, worN=freqs, fs=fs)[1]
    usable = freqs >= band[0] / 2
    product = response[usable] * (inverse[usable, 0] + 1j * inverse[usable, 1])
    np.testing.assert_allclose(product, 1.0, atol=1e-9)
    assert np.abs(response[freqs < 2.0]).max() < 1e-4  # gravity and slow motion stopped
