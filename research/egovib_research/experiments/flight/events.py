"""Known events added to the real noise: the paper's experiment (b) on the flight log.

The flight has no contacts, so contact-like transients with known onsets are added to
the real gyro signal of the test part, as the paper added recorded solenoid taps to
recorded ego-vibration (section 4, Fig. 5 right).

Form of one event (a knock on the frame ringing down, e.g. a prop guard or landing leg
touching something): a damped sinusoid on one gyro axis,

    e(t) = A * s * exp(-(t - t0) / tau) * sin(2 pi f (t - t0))   for t >= t0, else 0,

evaluated at the log's own (jittery) sample times, with, per event, the axis drawn from
roll/pitch/yaw, the sign s = +-1, the ring frequency f ~ U(frequency_hz) inside the
band, the decay time tau ~ U(decay_s). It starts from zero (no step), so its band-passed
onset is where it really begins.

Amplitude (paper: "the magnitude of the original taps is similar to the maximum noise
magnitude"): every event is scaled so that its own peak after the combined-axis
band-pass equals `relative_amplitude` x the largest band-passed noise magnitude of the
test part (edges excluded), the same rule as the simulator's experiment (b).

Timing: one event every `spacing_s` on average, each onset jittered uniformly by
+-`jitter_s`, none within `margin_s` of either end; a fixed seed makes them repeatable.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from egovib_ros.core.filters import combined_bandpassed
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.evaluation.metrics import EDGE_S


@dataclass(frozen=True)
class EventSpec:
    spacing_s: float = 0.5
    jitter_s: float = 0.15
    margin_s: float = 0.4
    frequency_hz: tuple[float, float] = (100.0, 400.0)
    decay_s: tuple[float, float] = (0.004, 0.012)
    relative_amplitude: float = 1.0
    seed: int = 1

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Events:
    signal: np.ndarray  # (N, 3) the events alone, rad/s, on the test part's samples
    onsets: np.ndarray  # (T,) sample index of each onset (first sample at or after t0)
    onset_ns: np.ndarray  # (T,) t0 in stamp time
    axis: np.ndarray  # (T,)
    frequency_hz: np.ndarray  # (T,)
    decay_s: np.ndarray  # (T,)
    amplitude: np.ndarray  # (T,) A, rad/s on its axis
    target_peak: float  # band-passed peak every event was scaled to


def make_events(
    stamps_ns: np.ndarray, noise: np.ndarray, profile, *, spec: EventSpec = EventSpec()
) -> Events:
    """Events for a recording with sensor stamps `stamps_ns` and sensor values `noise` (N, 3)
    (the real signal they will be added to; only its band-passed maximum is used), in the
    band of the robot profile `profile`."""
    stamps_ns = np.asarray(stamps_ns, np.int64)
    n = len(stamps_ns)
    rng = np.random.default_rng(spec.seed)
    t = (stamps_ns - stamps_ns[0]) / NS_PER_S
    duration = t[-1]
    centres = np.arange(
        spec.margin_s + spec.jitter_s, duration - spec.margin_s - spec.jitter_s, spec.spacing_s
    )
    onset_s = centres + rng.uniform(-spec.jitter_s, spec.jitter_s, len(centres))
    count = len(onset_s)
    axis = rng.integers(0, 3, count)
    sign = rng.choice([-1.0, 1.0], count)
    frequency = rng.uniform(*spec.frequency_hz, count)
    decay = rng.uniform(*spec.decay_s, count)

    edge = int(round(EDGE_S * profile.rate_hz))
    noise_bp = combined_bandpassed(noise, profile)
    target = spec.relative_amplitude * float(np.abs(noise_bp[edge : n - edge]).max())

    total = np.zeros((n, 3))
    amplitude = np.zeros(count)
    onsets = np.searchsorted(t, onset_s, side="left")
    for k in range(count):
        dt = t - onset_s[k]
        active = (dt >= 0) & (dt < 12 * decay[k])  # exp(-12) ~ 6e-6: the rest is nothing
        unit = np.zeros((n, 3))
        unit[active, axis[k]] = (
            sign[k] * np.exp(-dt[active] / decay[k]) * np.sin(2 * np.pi * frequency[k] * dt[active])
        )
        peak = np.abs(combined_bandpassed(unit, profile)).max()
        amplitude[k] = target / peak
        total += amplitude[k] * unit
    return Events(
        signal=total,
        onsets=onsets.astype(np.int64),
        onset_ns=stamps_ns[0] + np.round(onset_s * NS_PER_S).astype(np.int64),
        axis=axis,
        frequency_hz=frequency,
        decay_s=decay,
        amplitude=amplitude,
        target_peak=target,
    )
