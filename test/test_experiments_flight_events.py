"""The flight experiment's synthetic contact events: their documented form, amplitude (scaled to
the test noise) and timing, reproducible per seed.
"""

import numpy as np
import pytest
from synthetic import jittery_stamps

from egovib_research.experiments.flight.events import EventSpec, make_events
from egovib_ros.core.filters import combined_bandpassed
from egovib_ros.robot import load_profile

PROFILE = load_profile("quadcopter")


def test_events_follow_their_documented_form_amplitude_and_timing():
    n = 6000
    stamps = jittery_stamps(n, seed=4)
    noise = np.random.default_rng(4).normal(0, 0.05, (n, 3))
    spec = EventSpec(seed=7)
    events = make_events(stamps, noise, PROFILE, spec=spec)
    onset_s = (events.onset_ns - stamps[0]) / 1e9
    assert len(events.onsets) == len(
        np.arange(
            spec.margin_s + spec.jitter_s,
            (stamps[-1] - stamps[0]) / 1e9 - spec.margin_s - spec.jitter_s,
            spec.spacing_s,
        )
    )
    assert (
        onset_s.min() >= spec.margin_s - 1e-9
        and np.diff(onset_s).min() >= spec.spacing_s - 2 * spec.jitter_s
    )
    assert np.all((events.frequency_hz >= 100) & (events.frequency_hz <= 400))
    noise_peak = np.abs(combined_bandpassed(noise, PROFILE)[100 : n - 100]).max()
    assert events.target_peak == pytest.approx(noise_peak)
    for onset in events.onsets:  # each event alone peaks at the target
        alone = np.zeros((n, 3))
        stop = min(n, onset + 200)
        alone[onset - 1 : stop] = events.signal[onset - 1 : stop]
        assert np.abs(combined_bandpassed(alone, PROFILE)).max() == pytest.approx(
            events.target_peak, rel=0.02
        )
        assert np.all(events.signal[onset - 1] == 0)  # starts from zero, on one axis
        assert np.count_nonzero(np.any(events.signal[onset : onset + 5] != 0, axis=0)) == 1
    again = make_events(stamps, noise, PROFILE, spec=spec)
    np.testing.assert_array_equal(again.signal, events.signal)
