"""Axis handling and the streaming band-pass (paper section 3: sum of axes, 150-750 Hz)."""

from __future__ import annotations

import functools
import itertools

import numpy as np
from scipy import linalg, signal

from egovib_ros.errors import ConfigError, StreamError

#: Channel layouts. "combined" = sum of the three axes (the paper), "per_axis" = x, y, z,
#: "all" = combined, x, y, z (what calibration records, so one model serves both).
CHANNEL_LAYOUTS = {
    "combined": ("combined",),
    "per_axis": ("x", "y", "z"),
    "all": ("combined", "x", "y", "z"),
}


def channel_matrix(accel: np.ndarray, layout: str) -> np.ndarray:
    """Map (N, 3) accelerations to the (N, C) channels of `layout`."""
    if layout not in CHANNEL_LAYOUTS:
        raise ConfigError(
            f"channels: unknown layout {layout!r}; expected one of {sorted(CHANNEL_LAYOUTS)}"
        )
    accel = np.asarray(accel, dtype=np.float64)
    if accel.ndim != 2 or accel.shape[1] != 3:
        raise StreamError(f"accelerometer samples must have shape (N, 3), got {accel.shape}")
    if layout == "per_axis":
        return accel  # callers copy (the band-pass works on a copy)
    combined = accel.sum(axis=1, keepdims=True)
    if layout == "combined":
        return combined
    return np.concatenate([combined, accel], axis=1)


def butter_sos(order: int, corners_hz, btype: str, sample_rate_hz: float) -> np.ndarray:
    """scipy's Butterworth as second-order sections, designed once per setting (a copy:
    scipy's sosfilt kernel takes writable arrays): every denoiser a batch builds asks for the
    same few, and a design costs ~1 ms."""
    return _butter_sos(order, corners_hz, btype, sample_rate_hz).copy()


@functools.lru_cache(maxsize=64)
def _butter_sos(order: int, corners_hz, btype: str, sample_rate_hz: float) -> np.ndarray:
    return signal.butter(order, corners_hz, btype=btype, fs=sample_rate_hz, output="sos")


def design_bandpass(
    *, sample_rate_hz: float, band_hz: tuple[float, float], order: int
) -> np.ndarray:
    """Butterworth band-pass as second-order sections (scipy's order convention: `order`
    poles per band edge, as MATLAB's butter(4, [lo hi]) used in the paper's era)."""
    low, high = float(band_hz[0]), float(band_hz[1])
    nyquist = sample_rate_hz / 2.0
    if not 0.0 < low < high < nyquist:
        raise ConfigError(f"band_hz: need 0 < low < high < {nyquist:g} Hz (Nyquist), got {band_hz}")
    if order < 1:
        raise ConfigError(f"band_order: must be >= 1, got {order}")
    return butter_sos(int(order), (low, high), "bandpass", float(sample_rate_hz))


def bandpass_delay(*, sample_rate_hz: float, band_hz: tuple[float, float], order: int) -> float:
    """The band-pass's group delay (samples) averaged over its band: how late the band-passed
    signal shows what the raw one holds (~1.7 ms for the PR2 hand's 150-750 Hz, 25 ms for a
    40 Hz wide band at 300 Hz)."""
    sos = design_bandpass(sample_rate_hz=sample_rate_hz, band_hz=band_hz, order=order)
    freqs = np.linspace(band_hz[0], band_hz[1], 64)
    # a cascade's group delay: the sum of its sections' (better conditioned than one tf)
    delays = [signal.group_delay((s[:3], s[3:]), w=freqs, fs=sample_rate_hz)[1] for s in sos]
    return float(np.mean(np.sum(delays, axis=0)))


def _load_kernel():
    """scipy's compiled SOS kernel, which `signal.sosfilt` runs after ~90 us of argument
    checks (more than the filtering of a 32-sample hop): used when present and equal to
    the public function (checked here), else sosfilt."""
    try:
        from scipy.signal._sosfilt import _sosfilt  # deferred: private, absent in some builds
    except ImportError:  # pragma: no cover - depends on the scipy build
        return None
    sos = signal.butter(2, [0.1, 0.3], btype="bandpass", output="sos")
    x = np.random.default_rng(0).normal(size=(2, 50))
    zi = np.ones((sos.shape[0], 2, 2))
    want, want_zi = signal.sosfilt(sos, x, axis=-1, zi=zi)
    got, got_zi = x.copy(), np.ascontiguousarray(zi.transpose(1, 0, 2))
    try:
        _sosfilt(sos, got, got_zi)
    except Exception:  # pragma: no cover
        return None
    same = np.array_equal(got, want) and np.array_equal(got_zi.transpose(1, 0, 2), want_zi)
    return _sosfilt if same else None


_SOS_KERNEL = _load_kernel()


def _load_linear_filter():
    """scipy's compiled direct-form filter, which `signal.lfilter` runs after ~15 us of
    argument conversion (a simulator step runs ten filters): used when present and equal
    to the public function (checked here), else lfilter."""
    try:
        from scipy.signal._sigtools import _linear_filter  # deferred: private, as above
    except ImportError:  # pragma: no cover - depends on the scipy build
        return None
    b, a = signal.butter(2, 0.2)
    x = np.random.default_rng(0).normal(size=(50, 2))
    zi = np.ones((2, 2))
    want = signal.lfilter(b, a, x, axis=0, zi=zi)
    try:
        got = _linear_filter(b, a, x, 0, zi)
    except Exception:  # pragma: no cover
        return None
    same = all(np.array_equal(g, w) for g, w in zip(got, want))
    return _linear_filter if same else None


_LFILTER_KERNEL = _load_linear_filter()


def lfilter_carried(b, a, x, zi, *, axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """`signal.lfilter(b, a, x, axis=axis, zi=zi)`: (y, final state), to the bit."""
    b, a = np.atleast_1d(np.asarray(b, np.float64)), np.atleast_1d(np.asarray(a, np.float64))
    if _LFILTER_KERNEL is None or len(a) < 2:
        return signal.lfilter(b, a, x, axis=axis, zi=zi)
    return _LFILTER_KERNEL(b, a, np.asarray(x, np.float64), axis, np.asarray(zi, np.float64))


def sosfilt_carried(
    sos: np.ndarray, x: np.ndarray, zi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """`signal.sosfilt(sos, x, zi=zi)` of a 1-D `x`: (y, final state (n_sections, 2)), to
    the bit (the same kernel, without its argument checks)."""
    if _SOS_KERNEL is None:
        return signal.sosfilt(sos, x, zi=zi)
    y = np.array(x, dtype=np.float64, order="C").reshape(1, -1)
    state = np.array(zi, dtype=np.float64, order="C").reshape(1, -1, 2)
    _SOS_KERNEL(np.asarray(sos, np.float64), y, state)  # in place
    return y[0], state[0]


class CarriedFilter:
    """An IIR filter (second-order sections) with carried state, channels-first (C, N); it
    starts in steady state for the first sample (no ringing from the gravity offset), so
    chunked and whole-signal filtering agree exactly."""

    def __init__(self, sos: np.ndarray, *, n_channels: int):
        self.sos = sos
        self.n_channels = int(n_channels)
        self._zi: np.ndarray | None = None  # (C, n_sections, 2)

    def reset(self) -> None:
        self._zi = None

    def process(self, x: np.ndarray) -> np.ndarray:
        """Filter (C, N) samples; returns a new (C, N) array."""
        x = np.array(x, dtype=np.float64, order="C")
        if x.ndim != 2 or x.shape[0] != self.n_channels:
            raise StreamError(f"filter expects ({self.n_channels}, N) samples, got {x.shape}")
        if x.shape[1] == 0:
            return x
        if self._zi is None:
            zi = signal.sosfilt_zi(self.sos)  # (n_sections, 2)
            self._zi = np.ascontiguousarray(zi[None, :, :] * x[:, 0, None, None])
        if _SOS_KERNEL is not None:
            _SOS_KERNEL(self.sos, x, self._zi)  # in place
            return x
        y, zi = signal.sosfilt(self.sos, x, axis=-1, zi=self._zi.transpose(1, 0, 2))
        self._zi = np.ascontiguousarray(zi.transpose(1, 0, 2))
        return y


class BandPass(CarriedFilter):
    """The paper's band-pass (Butterworth, `design_bandpass`) with carried state."""

    def __init__(
        self, *, sample_rate_hz: float, band_hz: tuple[float, float], order: int, n_channels: int
    ):
        sos = design_bandpass(sample_rate_hz=sample_rate_hz, band_hz=band_hz, order=order)
        super().__init__(sos, n_channels=n_channels)

    @classmethod
    def of(cls, source, n_channels: int) -> "BandPass":
        """The band-pass of a NoiseModel, FramerSettings or ContactSettings (their
        sample_rate_hz, band_hz and band_order)."""
        return cls(
            sample_rate_hz=source.sample_rate_hz,
            band_hz=source.band_hz,
            order=source.band_order,
            n_channels=n_channels,
        )


class BelowBand(CarriedFilter):
    """What lies far below the band: a 4th-order Butterworth low-pass at a quarter of the
    band's low edge (-48 dB at the edge). Gravity and rigid-body motion are in it; the
    band is not (its complement, input minus this, is the input to within 0.4 % there)."""

    def __init__(self, *, sample_rate_hz: float, band_hz: tuple[float, float], n_channels: int):
        sos = butter_sos(4, band_hz[0] / 4.0, "lowpass", sample_rate_hz)
        super().__init__(sos, n_channels=n_channels)


def combined_bandpassed(values: np.ndarray, profile) -> np.ndarray:
    """(N,) the paper's 1-D signal of (N, 3) samples: their sum band-passed in the robot
    profile's band, as streamed (the reference every metric is taken on)."""
    band = BandPass(
        sample_rate_hz=profile.rate_hz,
        band_hz=profile.band_hz,
        order=profile.band_order,
        n_channels=1,
    )
    return band.process(channel_matrix(values, "combined").T)[0]  # BandPass works on (C, N) rows


# --- The per-sample methods' drop-in output (core.methods): what they remove from the
# band-passed signal, removed from the unfiltered one with nothing below the band touched.
#: The split's low-pass passes up to this share of the band's low edge and stops from the
#: next on (least squares, unit gain at 0 Hz).
SPLIT_PASS_FRACTION = 0.1
SPLIT_STOP_FRACTION = 0.9
#: It may pass at most this (dB) of the calibration recording's band-passed noise into its
#: untouched low part (the drop-in output then removes within 1 dB of the band-passed one),
#: with the shortest delay that reaches it, at most SPLIT_MAX_DELAY_S.
SPLIT_LEAK_DB = -45.0
SPLIT_MAX_DELAY_S = 0.025
#: A low-delay split may err from a pure delay by SPLIT_PASS_ERROR over the passband and
#: SPLIT_TRANSITION_ERROR up to SPLIT_TRANSITION_FRACTION of the band's low edge (the PR2
#: hand's linear-phase split: 0.03-0.04 and 0.15): what the gains may take from motion.
SPLIT_PASS_ERROR = 0.05
SPLIT_TRANSITION_ERROR = 0.15
SPLIT_TRANSITION_FRACTION = 0.2
#: Weight of the passband against the noise to stop in a design fitted to a recording, and
#: the weights a low-delay split tries in turn at each length.
SPLIT_PASS_WEIGHT = 1e-3
SPLIT_PASS_WEIGHTS = (SPLIT_PASS_WEIGHT, 1e-2, 1e-1, 1.0)
#: The lines are tracked in the unfiltered signal after a 4th-order high-pass at this share
#: of the band's low edge (gravity and motion never reach their trackers; its phase at a line
#: is undone exactly: `highpass_inverse`).
LINES_HIGHPASS_FRACTION = 0.25


def _split_response(taps: np.ndarray, freqs: np.ndarray, sample_rate_hz: float) -> np.ndarray:
    return np.abs(signal.freqz(taps, 1, worN=freqs, fs=sample_rate_hz)[1])


def _symmetric_lowpass(
    sample_rate_hz: float, low_edge_hz: float, delay: int, freqs: np.ndarray, stop_weight
) -> np.ndarray:
    """(2 delay + 1,) symmetric taps, unit gain at 0 Hz, least squares: 1 over the passband
    (SPLIT_PASS_FRACTION of the band's low edge), 0 elsewhere weighted by `stop_weight`."""
    omega = 2.0 * np.pi * freqs / sample_rate_hz
    # symmetric taps h[delay +- k] = a_k: response e^{-j w delay} (a_0 + 2 sum_k a_k cos(w k))
    basis = np.cos(np.outer(omega, np.arange(delay + 1)))
    basis[:, 1:] *= 2.0
    passed = freqs <= SPLIT_PASS_FRACTION * low_edge_hz
    pass_weight = SPLIT_PASS_WEIGHT if stop_weight is not None else 1.0
    if stop_weight is None:  # the band and everything from its edge's skirt up, alike
        stop_weight = (freqs >= SPLIT_STOP_FRACTION * low_edge_hz).astype(float)
    rows = np.vstack([np.sqrt(stop_weight)[:, None] * basis, pass_weight * basis[passed]])
    target = np.r_[np.zeros(len(freqs)), pass_weight * np.ones(passed.sum())]
    # least squares with the response at 0 Hz exactly 1: gravity passes as it is
    dc = basis[0]
    system = np.block([[rows.T @ rows, dc[:, None]], [dc[None, :], np.zeros((1, 1))]])
    half = np.linalg.lstsq(system, np.r_[rows.T @ target, 1.0], rcond=None)[0][:-1]
    taps = np.r_[half[:0:-1], half]
    taps.flags.writeable = False
    return taps


@functools.lru_cache(maxsize=64)
def _split_taps(sample_rate_hz: float, low_edge_hz: float, delay: int) -> np.ndarray:
    freqs = np.linspace(0.0, sample_rate_hz / 2.0, 2048)
    return _symmetric_lowpass(sample_rate_hz, low_edge_hz, delay, freqs, None)


def split_taps(*, sample_rate_hz: float, band_hz: tuple[float, float], delay: int) -> np.ndarray:
    """(2 delay + 1,) symmetric taps of the drop-in split's linear-phase low-pass (unit gain
    at 0 Hz; passes what lies far below the band, stops the band); delay 0: [1.0]. The
    design for no recording in particular: a model fitted one to its calibration recording
    (`split_for`) and carries it."""
    if delay <= 0:
        return np.ones(1)
    return _split_taps(float(sample_rate_hz), float(band_hz[0]), int(delay))


class _LowDelayDesign:
    """Low-delay splits for one recording's stop weights: taps of a given length, least
    squares against a pure `delay` over the passband (weight `pass_weight`) and 0 elsewhere
    (`stop_weight`), exactly 1 at 0 Hz with a group delay there of exactly `delay` (slow
    motion errs with the square of its frequency). Longer than 2 delay + 1, they stop more
    than the linear-phase split of that delay. The Toeplitz normal equations are built once."""

    def __init__(self, sample_rate_hz, low_edge_hz, freqs, stop_weight, longest: int):
        omega = 2.0 * np.pi * np.asarray(freqs, float) / sample_rate_hz
        passed = freqs <= SPLIT_PASS_FRACTION * low_edge_hz
        lags = np.arange(longest)
        self._stop = np.cos(np.outer(lags, omega)) @ stop_weight
        self._pass = np.cos(np.outer(lags, omega[passed])).sum(axis=1)

    def taps(self, delay: int, length: int, pass_weight: float) -> np.ndarray:
        w2 = pass_weight**2
        gram = linalg.toeplitz(self._stop[:length] + w2 * self._pass[:length])
        target = w2 * self._pass[np.abs(np.arange(length) - delay)]
        fixed = np.vstack([np.ones(length), np.arange(length, dtype=float)])
        system = np.block([[gram, fixed.T], [fixed, np.zeros((2, 2))]])
        taps = np.linalg.lstsq(system, np.r_[target, 1.0, float(delay)], rcond=None)[0][:-2]
        taps.flags.writeable = False
        return taps


def split_for(
    *,
    sample_rate_hz: float,
    band_hz: tuple[float, float],
    order: int,
    freqs_hz: np.ndarray,
    power: np.ndarray,
    min_delay: int = 1,
) -> tuple[np.ndarray, int]:
    """The drop-in split (taps, delay) for a recording of power spectrum `power`: the
    shortest delay from `min_delay` at which taps fitted to stop its band-passed noise (5-6
    dB less leak than the plain design) pass at most SPLIT_LEAK_DB of it: the linear-phase
    split's, then by bisection below it the least delay of a low-delay split within its
    errors of a pure delay (the PR2 hand: 4.0 ms, the linear-phase 5.7). Seconds at most."""
    freqs_hz = np.asarray(freqs_hz, float)
    band = _band_passed_power(sample_rate_hz, band_hz, order, freqs_hz, power)
    low_edge = band_hz[0]
    # what the split must stop: the band-passed noise from half the band's edge up
    weight = np.where(freqs_hz >= 0.5 * low_edge, band / band.max(), 0.0) + 1e-6

    def stops(taps) -> bool:
        return _leak_db(taps, band, freqs_hz, sample_rate_hz) <= SPLIT_LEAK_DB

    below = freqs_hz[freqs_hz <= SPLIT_TRANSITION_FRACTION * low_edge]
    passed = below <= SPLIT_PASS_FRACTION * low_edge

    def near_delay(taps, delay) -> bool:
        """Within its bounds of a pure delay over the passband and below the transition."""
        response = signal.freqz(taps, 1, worN=below, fs=sample_rate_hz)[1]
        error = np.abs(response - np.exp(-2j * np.pi * below / sample_rate_hz * delay))
        return (
            error[passed].max(initial=0.0) <= SPLIT_PASS_ERROR
            and error.max(initial=0.0) <= SPLIT_TRANSITION_ERROR
        )

    start = max(1, min_delay)
    longest = max(start, int(SPLIT_MAX_DELAY_S * sample_rate_hz))
    for delay in range(start, longest + 1):  # the linear-phase split
        taps = _symmetric_lowpass(sample_rate_hz, low_edge, delay, freqs_hz, weight)
        if stops(taps):
            break
    else:  # none stops the band: the longest, unless a low-delay split does
        delay += 1
    if delay == start:  # no delay to save
        return taps, delay
    design = _LowDelayDesign(sample_rate_hz, low_edge, freqs_hz, weight, 6 * delay + 2)

    def low_delay(delay: int) -> np.ndarray | None:
        step = 4 * max(1, delay // 16)  # (a long split: fewer lengths tried)
        for length, pass_weight in itertools.product(
            range(2 * delay + 5, 6 * delay + 2, step), SPLIT_PASS_WEIGHTS
        ):
            candidate = design.taps(delay, length, pass_weight)
            if stops(candidate) and near_delay(candidate, delay):
                return candidate
        return None

    # a low-delay split of less delay: the least, by bisection (a longer delay stops more)
    best, low, high = (taps, min(delay, longest)), start, delay
    while low < high:
        middle = (low + high) // 2
        candidate = low_delay(middle)
        if candidate is None:
            low = middle + 1
        else:
            best, high = (candidate, middle), middle
    return best


def split_leak_db(
    taps: np.ndarray,
    *,
    sample_rate_hz: float,
    band_hz: tuple[float, float],
    order: int,
    freqs_hz: np.ndarray,
    power: np.ndarray,
) -> float:
    """dB of a recording's band-passed noise (spectrum `power`) the split `taps` passes into
    its low part, which no gain touches (`split_for` aims at SPLIT_LEAK_DB)."""
    freqs_hz = np.asarray(freqs_hz, float)
    band = _band_passed_power(sample_rate_hz, band_hz, order, freqs_hz, power)
    return _leak_db(taps, band, freqs_hz, sample_rate_hz)


def _band_passed_power(sample_rate_hz, band_hz, order, freqs_hz, power) -> np.ndarray:
    sos = design_bandpass(sample_rate_hz=sample_rate_hz, band_hz=band_hz, order=order)
    response = signal.sosfreqz(sos, worN=freqs_hz, fs=sample_rate_hz)[1]
    return np.asarray(power, float) * np.abs(response) ** 2


def _leak_db(taps, band, freqs_hz, sample_rate_hz) -> float:
    leak = float((band * _split_response(taps, freqs_hz, sample_rate_hz) ** 2).sum())
    return 10.0 * np.log10(max(leak, 1e-300) / max(float(band.sum()), 1e-300))


def lines_highpass(*, sample_rate_hz: float, band_hz: tuple[float, float]) -> np.ndarray:
    """SOS of the high-pass the lines are tracked after in the unfiltered signal."""
    return butter_sos(4, LINES_HIGHPASS_FRACTION * band_hz[0], "highpass", sample_rate_hz)


@functools.lru_cache(maxsize=32)
def _highpass_inverse(sample_rate_hz: float, band_hz: tuple[float, float], points: int):
    sos = lines_highpass(sample_rate_hz=sample_rate_hz, band_hz=band_hz)
    freqs = np.linspace(0.0, sample_rate_hz / 2.0, points)
    response = signal.sosfreqz(sos, worN=freqs, fs=sample_rate_hz)[1]
    usable = np.abs(response) >= 0.01
    inverse = np.where(usable, 1.0 / np.where(usable, response, 1.0), 0.0)
    table = np.ascontiguousarray(np.stack([inverse.real, inverse.imag], axis=1))
    table.flags.writeable = False
    return table


def highpass_inverse(
    *, sample_rate_hz: float, band_hz: tuple[float, float], points: int = 4096
) -> np.ndarray:
    """(points, 2) real and imaginary parts of 1 / F(f) from 0 to Nyquist, F the response
    of `lines_highpass` (0 where F stops): a line of amplitude A after it is A / F(f) before."""
    return _highpass_inverse(float(sample_rate_hz), (float(band_hz[0]), float(band_hz[1])), points)
