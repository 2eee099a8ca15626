"""core.lowlatency: the complementary bank and the per-band gain with look-ahead."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from egovib_ros.core.blocks import analysis_window
from egovib_ros.core.lowlatency import FilterBank, GainSettings, LowLatencyGain
from egovib_ros.errors import ConfigError

FS = 3000.0
BAND = (150.0, 750.0)


def bank(bands: int = 3) -> FilterBank:
    return FilterBank(sample_rate_hz=FS, band_hz=BAND, bands=bands)


def noise_powers(n: int, channels: int, value) -> np.ndarray:
    b = np.broadcast_to(np.asarray(value, float), (channels, len(np.atleast_1d(value))))
    return np.ascontiguousarray(np.broadcast_to(b, (n,) + b.shape))


@pytest.mark.parametrize("bands", [0, 1, 3, 8])
def test_open_gains_give_the_input_back_d_samples_later(bands):
    x = np.random.default_rng(0).normal(size=(2000, 2))
    fb = bank(bands)
    stage = LowLatencyGain(
        fb, GainSettings(bands=bands, oversubtraction=0.0, open_hold_ms=0.0), n_channels=2
    )
    out = stage.process(x, noise_powers(len(x), 2, np.ones(fb.n_bands)))
    d = stage.delay
    assert d == round(4e-3 * FS)
    np.testing.assert_allclose(out[d:], x[:-d], rtol=0, atol=1e-12)
    assert np.all(out[:d] == 0)


def test_band_powers_predicted_from_block_spectra_match_the_bank():
    """White noise: every rfft bin of a windowed block has E|X|^2 = var * sum(w^2); the weights
    turn that into the band signals' power."""
    rng = np.random.default_rng(1)
    x = rng.normal(size=(200_000, 1))
    fb = bank(3)
    window = analysis_window(64, 32)
    expected = fb.power_weights(64, window) @ np.full(33, np.sum(window**2))
    stage = LowLatencyGain(
        fb, GainSettings(oversubtraction=0.0, open_hold_ms=0.0, lookahead_ms=0.0), n_channels=1
    )
    _, ratios = stage.process(x, noise_powers(len(x), 1, expected), collect=True)
    # the band power measured by the stage (attack/release smoothed) over the expected one
    measured = ratios[1000:, 0, : fb.n_bands].mean(axis=0)
    np.testing.assert_allclose(measured, 1.0, atol=0.25)


def test_noise_at_the_table_level_is_gated_and_a_burst_keeps_its_waveform():
    rng = np.random.default_rng(2)
    n = int(4 * FS)
    noise = 0.1 * rng.normal(size=(n, 1))
    fb = bank(3)
    window = analysis_window(64, 32)
    table = fb.power_weights(64, window) @ np.full(33, 0.01 * np.sum(window**2))
    k = np.arange(int(0.03 * FS)) / FS
    burst = np.zeros((n, 1))
    onset = int(2.0 * FS)
    burst[onset : onset + len(k), 0] = 1.5 * np.exp(-k / 0.006) * np.sin(2 * np.pi * 410 * k)
    settings_ = GainSettings(oversubtraction=4.0)
    stage = LowLatencyGain(fb, settings_, n_channels=1, open_alpha=np.array([1.0]))
    out = stage.process(noise + burst, noise_powers(n, 1, table))
    d = stage.delay
    aligned = out[d:, 0]
    quiet = slice(int(0.5 * FS), onset - int(0.05 * FS))
    reduction = 20 * math.log10(np.abs(noise[quiet, 0]).mean() / np.abs(aligned[quiet]).mean())
    assert reduction > 20.0
    event = slice(onset, onset + len(k))
    assert np.abs(aligned[event]).max() / np.abs((noise + burst)[event, 0]).max() > 0.9
    # the waveform: as close to the burst as the noisy input (the noise under it is kept)
    raw = np.corrcoef((noise + burst)[event, 0], burst[event, 0])[0, 1]
    assert np.corrcoef(aligned[event], burst[event, 0])[0, 1] > min(0.93, raw - 0.01)


def test_after_a_speed_drop_the_noise_fading_out_is_not_taken_for_an_event():
    """The table's value drops 30 dB at once (the joints slowed down) while the residual
    fades out over ~10 ms (the canceller's trackers settle, a rotor spins down): the noise
    held from before keeps the gate shut; without the hold the fading noise passes."""
    rng = np.random.default_rng(5)
    n = int(2 * FS)
    drop = int(1.0 * FS)
    fb = bank(3)
    window = analysis_window(64, 32)
    loud = fb.power_weights(64, window) @ np.full(33, 0.01 * np.sum(window**2))
    level = np.ones(n)
    level[drop:] = np.maximum(np.exp(-np.arange(n - drop) / (0.01 * FS)), 10**-1.5)
    residual = 0.1 * level[:, None] * rng.normal(size=(n, 1))
    table = np.ones((n, 1, fb.n_bands)) * loud
    table[drop:] *= 1e-3
    after = slice(drop, drop + int(0.1 * FS))
    peaks = {}
    for hold_ms in (0.0, GainSettings().hold_ms):
        stage = LowLatencyGain(fb, GainSettings(oversubtraction=4.0, hold_ms=hold_ms), n_channels=1)
        out = stage.process(residual, table)[stage.delay :, 0]
        peaks[hold_ms] = np.abs(out[after]).max() / np.abs(residual[after, 0]).max()
    assert peaks[0.0] > 0.5  # the fading noise passes nearly whole
    assert peaks[GainSettings().hold_ms] < 0.2


def reference_gain(fb: FilterBank, s: GainSettings, r, noise, alpha, bias, open_alpha, guard_ref):
    """The gain stage in plain Python, one sample at a time (no look-ahead ring tricks)."""
    n, C = r.shape
    K, B = len(fb.poles), fb.n_bands
    D = s.delay_samples(FS)

    def rate(ms):
        return 1 - math.exp(-1 / (ms * 1e-3 * FS)) if ms > 0 else 1.0

    a_att, a_rel = rate(s.attack_ms), rate(s.release_ms)
    every = 8
    a_track = 1 - math.exp(-every / (s.track_s * FS))
    span = s.open_span
    decay = math.exp(-1 / (s.open_hold_ms * 1e-3 * FS))
    hold = math.exp(-1 / (s.hold_ms * 1e-3 * FS)) if s.hold_ms > 0 else 0.0
    held = np.zeros((C, B))
    rng_ = s.track_range_db * math.log(10) / 10
    z = np.zeros((C, K), complex)
    power = np.zeros((C, B))
    log_ratio = bias.copy()
    correction = np.ones((C, B))
    opening = np.zeros(C)
    wait = np.zeros(C, int)
    a_up, a_down = rate(1e3 * s.guard_up_s), rate(1e3 * s.guard_down_s)
    guard = guard_ref + s.guard_start  # the guard starts raised
    bands_hist = np.zeros((n + D, C, B))
    out = np.zeros((n, C))
    for i in range(n):
        ratios, levels = np.zeros((C, B)), np.zeros(C)
        for c in range(C):
            bands_ = np.zeros(B)
            for k in range(K):
                z[c, k] = fb.poles[k] * z[c, k] + (1 - abs(fb.poles[k])) * r[i, c]
                bands_[k] = 2 * z[c, k].real
                inst = 2 * abs(z[c, k]) ** 2
                power[c, k] += (a_att if inst > power[c, k] else a_rel) * (inst - power[c, k])
            bands_[K] = r[i, c] - bands_[:K].sum()
            inst = bands_[K] ** 2
            power[c, K] += (a_att if inst > power[c, K] else a_rel) * (inst - power[c, K])
            bands_hist[i + D, c] = bands_
            ratio = np.zeros(B)
            score = 0.0
            for k in range(B):
                expected = noise[i, c, k]
                if expected > 0:
                    expected = held[c, k] = max(expected, held[c, k] * hold)
                if i % every == 0 and power[c, k] > 1e-6 * expected:
                    step = min(
                        max(math.log(power[c, k] / expected) - log_ratio[c, k], -s.track_clip),
                        s.track_clip,
                    )
                    log_ratio[c, k] = min(
                        max(log_ratio[c, k] + a_track * step, bias[c, k] - rng_), bias[c, k] + rng_
                    )
                    correction[c, k] = math.exp(log_ratio[c, k] - bias[c, k])
                expected *= correction[c, k]
                ratio[k] = power[c, k] / expected
                score = max(score, ratio[k] / alpha[c, k])
            score /= open_alpha[c]
            level_now = math.log(score)
            guard[c] += (a_up if level_now > guard[c] else a_down) * (level_now - guard[c])
            excess = max(guard[c] - guard_ref[c], 0.0)
            score /= math.exp(excess)
            ratios[c] = ratio / math.exp(s.guard_gain * excess)
            levels[c] = (score - 1) / span
        level = min(max(levels.max(), 0.0), 1.0)  # an event on any channel opens them all
        for c in range(C):
            if level >= opening[c]:  # held for the look-ahead, then decaying
                opening[c], wait[c] = level, D
            elif wait[c] > 0:
                wait[c] -= 1
            else:
                opening[c] = max(level, opening[c] * decay)
            g = np.sqrt(np.clip(1 - alpha[c] / ratios[c], 0, None))
            g = np.maximum(np.maximum(g, opening[c]), s.floor)
            out[i, c] = np.sum(g * bands_hist[i, c])
    return out


def test_compiled_gain_equals_the_plain_reference():
    rng = np.random.default_rng(3)
    r = rng.normal(size=(600, 2))
    r[300:320] *= 8.0
    fb = bank(3)
    s = GainSettings()
    noise = np.abs(rng.normal(size=(600, 2, fb.n_bands))) + 0.5
    alpha = 1 + rng.uniform(size=(2, fb.n_bands))
    bias = 0.1 * rng.normal(size=(2, fb.n_bands))
    open_alpha = np.array([1.5, 2.0])
    guard_ref = np.array([-1.0, 0.5])
    got = LowLatencyGain(
        fb, s, n_channels=2, alpha=alpha, bias=bias, open_alpha=open_alpha, guard_ref=guard_ref
    ).process(r, noise)
    want = reference_gain(fb, s, r, noise, alpha, bias, open_alpha, guard_ref)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


@settings(max_examples=15, deadline=None)
@given(st.lists(st.integers(min_value=1, max_value=500), min_size=1, max_size=8))
def test_any_chunking_gives_the_one_call_result_to_the_bit(cuts):
    rng = np.random.default_rng(4)
    r = rng.normal(size=(2000, 3))
    r[900:960] *= 10
    fb = bank(3)
    noise = np.abs(rng.normal(size=(2000, 3, fb.n_bands))) + 0.3

    def make():
        return LowLatencyGain(fb, GainSettings(), n_channels=3, alpha=np.full((3, fb.n_bands), 2.0))  # noqa: E731

    whole = make().process(r, noise)
    stage = make()
    edges = np.unique(np.clip(np.cumsum(cuts), 0, len(r)))
    pieces = [
        stage.process(r[a:b], noise[a:b]) for a, b in zip(np.r_[0, edges], np.r_[edges, len(r)])
    ]
    assert np.array_equal(np.concatenate(pieces), whole)


def test_a_lasting_excess_over_the_table_is_taken_for_noise_a_short_burst_still_opens():
    # Noise 10 dB above what the table expects, for a second (speeds the calibration never
    # saw): without the guard it passes as if it were an event; with it, it is removed as
    # well as noise at the table's level is, and a burst on top of it still opens the gain.
    rng = np.random.default_rng(8)
    fb = bank(3)
    n = int(1.2 * FS)
    residual = rng.normal(size=(n, 1))
    residual[int(0.1 * FS) :] *= math.sqrt(10.0)
    burst = slice(int(0.9 * FS), int(0.91 * FS))
    residual[burst] *= 8.0
    window = analysis_window(64, 32)
    unit = fb.power_weights(64, window) @ np.full(33, np.sum(window**2))  # unit white noise
    table = noise_powers(n, 1, unit)
    settled = slice(int(0.4 * FS), int(0.85 * FS))

    def stage_(guard_ref):
        return LowLatencyGain(
            fb,
            GainSettings(track_s=0.0),
            n_channels=1,
            alpha=np.full((1, fb.n_bands), 2.0),
            open_alpha=np.array([2.0]),
            guard_ref=guard_ref,
        )

    # The guard's reference as calibration sets it: its 99 % level on noise at the table.
    calm = rng.normal(size=(int(FS), 1))
    probe = stage_(None)
    out, collected = probe.process(calm, table[: len(calm)], collect=True)
    reference = np.quantile(collected[int(0.1 * FS) :, 0, fb.n_bands + 1], 0.99)
    at_table = np.sqrt(np.mean(out[int(0.1 * FS) :] ** 2) / np.mean(calm**2))
    assert at_table < 0.5
    kept = {}
    for guard_ref in (None, np.array([reference])):
        stage = stage_(guard_ref)
        out = stage.process(residual, table)[stage.delay :, 0]
        quiet = np.sqrt(np.mean(out[settled] ** 2) / np.mean(residual[settled, 0] ** 2))
        kept[guard_ref is None] = quiet, np.abs(out[burst]).max() / np.abs(residual[burst, 0]).max()
    assert kept[True][0] > 0.9  # no guard: the lasting excess passes
    assert kept[False][0] < 1.2 * at_table  # the guard: removed as noise at the table is
    assert kept[False][1] > 0.7  # and the burst on top of it is kept


def test_settings_are_checked_with_one_line_errors():
    with pytest.raises(ConfigError, match="bands"):
        GainSettings(bands=-1)
    with pytest.raises(ConfigError, match="lookahead_ms"):
        GainSettings(lookahead_ms=-2)
    with pytest.raises(ConfigError, match="oversubtraction"):
        GainSettings(oversubtraction=-1.0)
    assert dataclasses.replace(GainSettings(), bands=0).bands == 0
