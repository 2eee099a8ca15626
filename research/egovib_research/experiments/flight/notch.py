"""Baseline (c): a motor-speed-keyed harmonic notch bank, as flight controllers do it.

Betaflight's RPM filter (src/main/flight/rpm_filter.c) runs, per gyro axis, one biquad
notch per motor and harmonic (3 harmonics x 4 motors), centred on harmonic h of each
motor's rotation frequency, Q = rpm_filter_q / 100 (default 5), centres constrained to
[rpm_filter_min_hz (100), 0.48 x loop rate], all coefficients refreshed within 1 ms.
ArduPilot's harmonic notch does the same from throttle when it has no RPM telemetry
(INS_HNTCH_MODE = 1): f = INS_HNTCH_FREQ * sqrt(throttle / INS_HNTCH_REF), i.e. a map
from actuator command to line frequency.

This log has motor commands but no RPM, so the map is fitted on the calibration part:
f1(u) = c * u**p (ArduPilot's throttle map is p = 1/2) by `fit_speed_frequency_map`,
and the bank puts notches at h * f1(u_m) for each motor m and h = 1..3. The log's gyro
was decimated from 8 kHz to 1 kHz without anti-aliasing, so a harmonic above Nyquist
appears folded back into the band: the bank puts its notch at the folded frequency
(on the 8 kHz firmware no harmonic ever reached Nyquist, so nothing there corresponds).

Causal and streaming: coefficients are refreshed every `update_s` from the latest motor
command at or before the first sample of the update block, and the filter state is
carried across updates (scipy sosfilt, transposed direct form II).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

BETAFLIGHT_Q = 5.0  # rpm_filter_q default 500 -> Q 5
ARDUPILOT_Q = 2.0  # INS_HNTCH_BW = half of INS_HNTCH_FREQ (throttle-based setup) -> Q 2
BETAFLIGHT_MIN_HZ = 100.0  # rpm_filter_min_hz default
MAX_RATIO = 0.48  # centres below 0.48 x sample rate ("to avoid oscillations")
HARMONICS = 3


def fold(freq_hz: np.ndarray, sample_rate_hz: float) -> np.ndarray:
    """Where a line at `freq_hz` appears when sampled at `sample_rate_hz` without anti-aliasing."""
    f = np.mod(np.asarray(freq_hz, float), sample_rate_hz)
    return np.where(f > sample_rate_hz / 2, sample_rate_hz - f, f)


def notch_sos(freq_hz: np.ndarray, q: float, sample_rate_hz: float) -> np.ndarray:
    """(..., 6) second-order sections of scipy.signal.iirnotch(f, q, fs) for every centre in
    `freq_hz` (vectorised, same formulas)."""
    w0 = 2.0 * np.asarray(freq_hz, float) / sample_rate_hz
    bandwidth = w0 / q * np.pi
    gain = 1.0 / (1.0 + np.tan(bandwidth / 2.0))
    cos = np.cos(w0 * np.pi)
    one = np.ones_like(w0)
    b = gain[..., None] * np.stack([one, -2.0 * cos, one], axis=-1)
    a = np.stack([one, -2.0 * gain * cos, 2.0 * gain - 1.0], axis=-1)
    return np.concatenate([b, a], axis=-1)


@dataclass(frozen=True)
class SpeedFrequencyMap:
    """Motor command (0..1) -> fundamental line frequency (Hz): f = coefficient * u**exponent."""

    coefficient: float
    exponent: float
    windows_used: int = 0
    rms_error_hz: float = float("nan")

    def __call__(self, command: np.ndarray) -> np.ndarray:
        return self.coefficient * np.maximum(np.asarray(command, float), 0.0) ** self.exponent

    def to_dict(self) -> dict:
        return {
            "form": "f = coefficient * command**exponent",
            "coefficient_hz": self.coefficient,
            "exponent": self.exponent,
            "windows_used": self.windows_used,
            "rms_error_hz": self.rms_error_hz,
        }


def fit_speed_frequency_map(
    x: np.ndarray,
    motors: np.ndarray,
    sample_rate_hz: float,
    *,
    window: int = 256,
    hop: int = 32,
    harmonics: int = HARMONICS,
    search_hz: tuple[float, float] = (60.0, 300.0),
    min_command: float = 0.1,
    max_unsteady: float = 0.02,
) -> SpeedFrequencyMap:
    """Fit f1(u) = c u^p on no-contact data: x (N,) the 1-D sensor signal, motors (N, M) the
    commands on the same samples.

    Per window (Hann, `window` samples every `hop`), the fundamental is where the comb of
    `harmonics` (folded) harmonics has the most log power; windows where the motors are not
    steady or barely spin are skipped. Then log f1 = log c + p log(mean command), least
    squares with outliers beyond 3 MAD dropped (a window where another line wins).
    """
    x = np.asarray(x, float)
    motors = np.asarray(motors, float)
    nfft = 4096
    freqs = np.fft.rfftfreq(nfft, 1.0 / sample_rate_hz)
    candidates = np.arange(search_hz[0], search_hz[1], 0.5)
    comb = np.stack(
        [fold(h * candidates, sample_rate_hz) for h in range(1, harmonics + 1)]
    )  # (H, K)
    taper = np.hanning(window)
    f_peak, command = [], []
    for start in range(0, len(x) - window + 1, hop):
        u = motors[start : start + window]
        level = u.mean()
        if level < min_command or u.mean(axis=1).std() > max_unsteady:
            continue
        seg = x[start : start + window]
        power = np.abs(np.fft.rfft((seg - seg.mean()) * taper, nfft)) ** 2 + 1e-30
        score = np.log(np.interp(comb, freqs, power)).sum(axis=0)
        f_peak.append(candidates[int(np.argmax(score))])
        command.append(level)
    if len(f_peak) < 5:
        raise ValueError(
            f"only {len(f_peak)} steady windows with spinning motors: cannot fit the "
            "speed -> frequency map"
        )
    log_u, log_f = np.log(np.asarray(command)), np.log(np.asarray(f_peak))
    keep = np.ones(len(log_u), bool)
    for _ in range(10):
        slope, intercept = np.polyfit(log_u[keep], log_f[keep], 1)
        residual = log_f - (intercept + slope * log_u)
        mad = np.median(np.abs(residual[keep] - np.median(residual[keep]))) * 1.4826
        new_keep = np.abs(residual) <= 3.0 * max(mad, 1e-3)
        if np.array_equal(new_keep, keep):
            break
        keep = new_keep
    fitted = np.exp(intercept + slope * log_u[keep])
    rms = float(np.sqrt(np.mean((np.exp(log_f[keep]) - fitted) ** 2)))
    return SpeedFrequencyMap(float(np.exp(intercept)), float(slope), int(keep.sum()), rms)


def hold(joint_stamps_ns: np.ndarray, values: np.ndarray, at_ns: np.ndarray) -> np.ndarray:
    """The latest joint state at or before each stamp (zeros before the first): causal."""
    index = np.searchsorted(joint_stamps_ns, at_ns, side="right") - 1
    held = np.asarray(values, float)[np.maximum(index, 0)]
    held[index < 0] = 0.0
    return held


class HarmonicNotchBank:
    """Notches at the folded harmonics h = 1..H of each motor's line, keyed on its command."""

    def __init__(
        self,
        frequency_map: SpeedFrequencyMap,
        *,
        sample_rate_hz: float,
        harmonics: int = HARMONICS,
        q: float = BETAFLIGHT_Q,
        min_hz: float = BETAFLIGHT_MIN_HZ,
        max_ratio: float = MAX_RATIO,
        update_s: float = 0.001,
    ):
        self.frequency_map = frequency_map
        self.sample_rate_hz = float(sample_rate_hz)
        self.harmonics = int(harmonics)
        self.q = float(q)
        self.min_hz = float(min_hz)
        self.max_hz = max_ratio * self.sample_rate_hz
        self.update_samples = max(1, int(round(update_s * self.sample_rate_hz)))

    def centres(self, commands: np.ndarray) -> np.ndarray:
        """(B, M) motor commands -> (B, M * H) notch centres in Hz (folded, constrained)."""
        fundamental = self.frequency_map(commands)  # (B, M)
        lines = fundamental[..., None] * np.arange(1, self.harmonics + 1)  # (B, M, H)
        folded = fold(lines, self.sample_rate_hz)
        return np.clip(folded, self.min_hz, self.max_hz).reshape(len(commands), -1)

    def apply(
        self,
        stamps_ns: np.ndarray,
        x: np.ndarray,
        joint_stamps_ns: np.ndarray,
        commands: np.ndarray,
    ) -> np.ndarray:
        """Filter the 1-D signal x (N,) sampled at stamps_ns; commands (K, M) at joint_stamps_ns."""
        x = np.asarray(x, float)
        n = len(x)
        starts = np.arange(0, n, self.update_samples)
        held = hold(joint_stamps_ns, commands, stamps_ns[starts])  # at each update's first sample
        sos = notch_sos(self.centres(held), self.q, self.sample_rate_hz)  # (B, K, 6)
        out = np.empty(n)
        zi = np.zeros((sos.shape[1], 2))
        for i, start in enumerate(starts):
            stop = min(start + self.update_samples, n)
            out[start:stop], zi = signal.sosfilt(sos[i], x[start:stop], zi=zi)
        return out
