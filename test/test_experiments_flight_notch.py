"""The flight experiment's notch filters: folding, scipy's notch, the speed-to-frequency map fitted
from lines, and the harmonic notch bank keyed on the motor commands.
"""

import numpy as np
from scipy import signal
from synthetic import jittery_stamps

from egovib_research.experiments.flight.notch import (
    HarmonicNotchBank,
    SpeedFrequencyMap,
    fit_speed_frequency_map,
    fold,
    notch_sos,
)

FS = 1000.0  # the flight log's rate


def _lines(stamps, commands, frequency_map, harmonics=(1.0, 0.6, 0.4), noise=0.002, seed=0):
    """(N,) sum over motors of harmonic lines at h * f(u_m), folded by sampling."""
    rng = np.random.default_rng(seed)
    t = (stamps - stamps[0]) / 1e9
    dt = np.diff(t, prepend=t[0])
    x = rng.normal(0, noise, len(t))
    for m in range(commands.shape[1]):
        phase = 2 * np.pi * np.cumsum(frequency_map(commands[:, m]) * dt) + m
        for h, amplitude in enumerate(harmonics, start=1):
            x += amplitude * 0.05 * np.sin(h * phase)
    return x


def test_fold_and_notch_match_sampling_and_scipy():
    assert fold(np.array([125.0, 560.0, 690.0, 1020.0]), FS).tolist() == [125.0, 440.0, 310.0, 20.0]
    for f0, q in ((125.0, 5.0), (333.0, 2.0)):
        b, a = signal.iirnotch(f0, q, FS)
        np.testing.assert_allclose(notch_sos(np.array([f0]), q, FS)[0], np.r_[b, a], rtol=1e-12)


def test_speed_frequency_map_is_recovered_from_lines():
    truth = SpeedFrequencyMap(330.0, 0.8)
    n = 12000
    stamps = jittery_stamps(n)
    # Steady levels 0.2 .. 0.7 held 0.6 s each, the four motors a little apart.
    level = np.repeat(np.linspace(0.2, 0.7, 20), n // 20)[:n]
    commands = level[:, None] + np.array([0.0, 0.01, -0.01, 0.005])
    x = _lines(stamps, commands, truth)
    fitted = fit_speed_frequency_map(x, commands, FS)
    u = np.linspace(0.25, 0.65, 9)
    np.testing.assert_allclose(fitted(u), truth(u), rtol=0.03)


def test_notch_bank_removes_the_tracked_lines_and_passes_a_tone_between_them():
    truth = SpeedFrequencyMap(330.0, 0.8)
    n = 6000
    stamps = jittery_stamps(n, seed=1)
    ramp = np.linspace(0.3, 0.6, n)  # motors speed up: lines move 126 -> 220 Hz
    commands = np.stack([ramp, ramp + 0.02, ramp - 0.02, ramp + 0.01], axis=1)
    lines = _lines(stamps, commands, truth, noise=0.0)
    bank = HarmonicNotchBank(truth, sample_rate_hz=FS, q=5.0)
    out = bank.apply(stamps, lines, stamps, commands)
    settle = slice(500, n)
    assert 20 * np.log10(np.std(lines[settle]) / np.std(out[settle])) > 15  # keyed lines removed
    t = (stamps - stamps[0]) / 1e9
    tone = 0.05 * np.sin(
        2 * np.pi * 95.0 * t
    )  # below every notch (min 100 Hz, fundamentals >= 126)
    assert np.std(bank.apply(stamps, tone, stamps, commands)[settle]) / np.std(tone[settle]) > 0.8
    # Centres: 3 harmonics per motor, folded, constrained to [min_hz, 0.48 fs].
    centres = bank.centres(np.array([[0.0, 0.5, 1.0, 0.9]]))[0]
    assert centres.shape == (12,) and centres.min() >= 100.0 and centres.max() <= 480.0
    np.testing.assert_allclose(centres[3:6], fold(np.array([1, 2, 3]) * truth(0.5), FS))
