"""Axis handling and the streaming band-pass (paper section 3: sum of axes, 150-750 Hz)."""

from __future__ import annotations

import functools

import numpy as np
from scipy import signal

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
    return signal.butter(order, [low, high], btype="bandpass", fs=sample_rate_hz, output="sos")


def _load_kernel():
    """scipy's compiled SOS kernel, the one `signal.sosfilt` runs after ~90 us of argument
    checks. At 32-sample hops those checks would cost more than the filtering, so the
    streaming path calls the kernel directly when it is present and gives the same
    result as the public function (checked here); otherwise it falls back to sosfilt."""
    try:
        from scipy.signal._sosfilt import _sosfilt
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
    """scipy's compiled direct-form filter, the one `signal.lfilter` runs for a denominator
    of two or more coefficients after ~15 us of argument conversion (a simulator step of
    a few samples runs ten filters): used when present and equal to the public function
    (checked here), else lfilter."""
    try:
        from scipy.signal._sigtools import _linear_filter
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
    """An IIR filter (second-order sections `sos`) with carried state, channels-first:
    (C, N) in, (C, N) out.

    The state starts in steady state for the first sample (no start-up ringing from the
    gravity offset), so chunked and whole-signal filtering agree exactly.
    """

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
        sos = signal.butter(4, band_hz[0] / 4.0, btype="lowpass", fs=sample_rate_hz, output="sos")
        super().__init__(sos, n_channels=n_channels)


def combined_bandpassed(values: np.ndarray, profile) -> np.ndarray:
    """(N,) sum of the three axes of (N, 3) samples, band-passed with the streaming filter
    from steady state in the robot profile's band (`profile`: a RobotProfile): the paper's
    1-D signal, the reference every metric is taken on."""
    band = BandPass(
        sample_rate_hz=profile.rate_hz,
        band_hz=profile.band_hz,
        order=profile.band_order,
        n_channels=1,
    )
    return band.process(channel_matrix(values, "combined").T)[0]  # BandPass works on (C, N) rows


#: How close the band-pass followed by `band_inverse` comes to a pure delay, averaged over
#: the band (where the band-pass passes at least half amplitude), dB.
INVERSE_ERROR_DB = -30.0
#: Longest delay `band_inverse` may take to get there (seconds).
INVERSE_MAX_DELAY_S = 0.020
#: Below this share of the band's low edge the FIR's gain is held down with this weight:
#: what it maps there lands below the band, where the drop-in output must pass the input.
INVERSE_STOP_FRACTION = 0.5
INVERSE_STOP_WEIGHT = 0.1
#: ... and everywhere else with this one (a bounded filter).
INVERSE_WEIGHT = 1e-3


def band_inverse(
    *, sample_rate_hz: float, band_hz: tuple[float, float], order: int
) -> tuple[np.ndarray, int, float]:
    """(taps, delay, error dB): a causal FIR that undoes the band-pass inside the band, up
    to `delay` samples, and passes little below it. What a method removes from the
    band-passed signal, filtered by it, is what to remove from the raw signal (the drop-in
    output of the per-sample methods): the band-pass's phase, not only its gain, matters
    there, and raw - removed without it would leave more than it takes near the band's
    edges.

    Least squares over the band's frequencies (|band-pass| >= 0.5), with the FIR's gain
    held down below the band (INVERSE_STOP_*) and bounded elsewhere; the delay is the
    shortest whole number of samples whose fit reaches INVERSE_ERROR_DB on the band's mean,
    else the longest allowed (INVERSE_MAX_DELAY_S), with the error it reaches."""
    taps, delay, error_db = _band_inverse(
        float(sample_rate_hz), (float(band_hz[0]), float(band_hz[1])), int(order)
    )
    return taps.copy(), delay, error_db


@functools.lru_cache(maxsize=32)  # every denoiser of a model asks for the same one
def _band_inverse(
    sample_rate_hz: float, band_hz: tuple[float, float], order: int
) -> tuple[np.ndarray, int, float]:
    sos = design_bandpass(sample_rate_hz=sample_rate_hz, band_hz=band_hz, order=order)
    # the band sampled densely whatever its width
    freqs = np.unique(
        np.r_[np.linspace(0.0, sample_rate_hz / 2.0, 1024), np.linspace(*band_hz, 256)]
    )
    response = signal.sosfreqz(sos, worN=freqs, fs=sample_rate_hz)[1]
    band = np.abs(response) >= 0.5
    omega = 2.0 * np.pi * freqs / sample_rate_hz
    weight = np.sqrt(
        np.where(freqs < INVERSE_STOP_FRACTION * band_hz[0], INVERSE_STOP_WEIGHT, INVERSE_WEIGHT)
    )

    def fit(delay: int) -> tuple[np.ndarray, float]:
        basis = np.exp(-1j * np.outer(omega, np.arange(2 * delay + 1)))  # the FIR's response
        passed = response[band, None] * basis[band]
        target = np.exp(-1j * omega[band] * delay)
        system = np.vstack([passed, weight[:, None] * basis])
        rhs = np.r_[target, np.zeros(len(freqs))]
        taps = np.linalg.lstsq(
            np.vstack([system.real, system.imag]), np.r_[rhs.real, rhs.imag], rcond=None
        )[0]
        return taps, float(10.0 * np.log10(np.mean(np.abs(passed @ taps - target) ** 2)))

    longest = max(1, int(INVERSE_MAX_DELAY_S * sample_rate_hz + 1e-9))
    step = max(1, longest // 16)  # coarse steps up, then back sample by sample
    delay = longest
    for coarse in range(step, longest + step, step):
        if fit(min(coarse, longest))[1] <= INVERSE_ERROR_DB:
            delay = min(coarse, longest)
            while delay > 1 and fit(delay - 1)[1] <= INVERSE_ERROR_DB:
                delay -= 1
            break
    taps, error_db = fit(delay)
    taps.flags.writeable = False
    return taps, delay, error_db
