"""A low-latency residual stage: a parametric Wiener gain per band on a complementary bank.

What the canceller leaves (broadband friction, lines it could not follow) is removed by a
gain computed sample by sample per band from the band's short-time power P and the noise
power N the residual's velocity table expects at the current joint velocities:

    g = max(floor, max(0, 1 - alpha N / P) ** exponent)   (Lim & Oppenheim 1979; exponent
                                                            1: Wiener, 0.5: power subtraction)

The bank: K one-pole complex resonators evenly over the band (b_k = 2 Re(z_k)) and the rest
band x - sum_k b_k, so the bands add up to the input exactly: with every gain at 1 the
output is the input to the bit, and a contact that opens the gains keeps its waveform. No
block, no FFT, no filter delay. P follows 2 |z_k|^2 with an attack and a release time; the
gain computed at sample n is applied to sample n - D (`lookahead_ms`): the delay is D.

Noise: N = table(velocity) x c, c a slow per-band log-domain correction (`track_s`, each
step clipped: an event barely moves it) following the real level's drift from the table.
After the joints slow down, N is held from before, decaying with `hold_ms` (the canceller's
trackers and a rotor take tens of ms), so a speed step does not pass for an event.
Calibration sets `alpha` per band (the `opening_quantile` of P/N on its residual) and
`bias` (the offset of the table's block spectra from the bank's power, so c = 1 there).

Opening: when the largest P / (alpha N) over a channel's bands exceeds what the calibration
residual reached in an `open_quantile` of its samples (`open_alpha`), every band opens (fully
at `open_span` beyond) for about `open_hold_ms`: an event keeps its whole waveform.

Guard: where the real noise stands above the table longer than an event lasts (speeds or
phases the calibration never saw), every moment looks like an event. A slow log level of the
opening score (rising in `guard_up_s`, falling in `guard_down_s`) above its calibration
quantile (`guard_ref`) raises the opening threshold and, to the power `guard_gain`, the
expected noise. Models calibrated before the guard have no `guard_ref`: no guard.

The defaults were chosen on the simulator (seed 7, not the published seeds) and the first
half of the shipped flight; docs say where a figure was measured on data that chose them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from egovib_ros.errors import ConfigError, check_ranges

#: Algorithmic delay the low-latency methods promise at most (milliseconds).
MAX_DELAY_MS = 5.0
MIN_POLE_RADIUS = 0.5
#: Band power below this share of the expected noise: silence, the correction does not move.
SILENCE = 1e-6
#: The noise-level correction moves every this many samples (its time constant is ~0.3 s).
TRACK_EVERY = 8
#: Least opening score the guard takes the log of.
TINY = 1e-12
LOG_TINY = math.log(TINY)


@dataclass(frozen=True, kw_only=True)
class GainSettings:
    """bands: resonators across the band (plus the rest band); bandwidth: their 3 dB width
    over the spacing of the centres; lookahead_ms: the delay; attack_ms / release_ms: time
    constants of the band power rising / falling; split_ms: the look-ahead the drop-in
    split needs (core.methods.DropInSplit; set in calibration; 0: the gain's own);
    opening_quantile: the quantile of P/N that sets alpha (unless `oversubtraction`);
    exponent: 1 Wiener, 0.5 power subtraction; floor: least gain; track_s: time constant of
    the noise-level correction (0: none), track_clip: its largest log step per update,
    track_range_db: how far it may move; hold_ms: decay of the expected noise after the
    table's value drops; open_hold_ms: how long a channel stays open after an event (0: no
    opening), open_quantile, open_span: where it opens and how far beyond fully; guard_up_s /
    guard_down_s: the guard's rise and fall (guard_up_s 0: no guard); guard_quantile: its
    calibration quantile; guard_gain: the power of its excess on the noise (0: the opening
    only); guard_start: how far above that level it starts, and stands again after a long
    gap, while the canceller settles from nothing (a stream started in motion began with
    60 ms of ego-vibration a contact detector took for an event)."""

    bands: int = 3
    bandwidth: float = 1.0
    lookahead_ms: float = 4.0
    split_ms: float = 0.0
    attack_ms: float = 1.0
    release_ms: float = 10.0
    opening_quantile: float = 0.99
    oversubtraction: float | None = None
    exponent: float = 0.5
    # -34 dB: 0.03 left 2-7 dB of the default's noise reduction unused; at 0.01 the drop-in
    # split's leak (core.filters.SPLIT_LEAK_DB) showed: 2.1 dB short of the band-passed output
    floor: float = 0.02
    track_s: float = 0.3
    track_clip: float = 1.0
    track_range_db: float = 15.0
    hold_ms: float = 20.0
    open_hold_ms: float = 20.0
    open_quantile: float = 0.998
    open_span: float = 2.0
    guard_up_s: float = 0.02
    guard_down_s: float = 0.5
    guard_quantile: float = 0.99
    guard_gain: float = 1.0
    guard_start: float = 2.0

    def __post_init__(self) -> None:
        checks = (
            ("bandwidth", 0.05, 10.0),
            ("lookahead_ms", 0.0, 1000.0),
            ("split_ms", 0.0, 1000.0),
            ("attack_ms", 0.0, 1000.0),
            ("release_ms", 0.0, 10000.0),
            ("opening_quantile", 0.5, 1.0),
            ("exponent", 0.1, 4.0),
            ("floor", 0.0, 1.0),
            ("track_s", 0.0, 1000.0),
            ("track_clip", 0.0, 100.0),
            ("track_range_db", 0.0, 100.0),
            ("hold_ms", 0.0, 10000.0),
            ("open_hold_ms", 0.0, 10000.0),
            ("open_quantile", 0.5, 1.0),
            ("open_span", 0.01, 100.0),
            ("guard_up_s", 0.0, 1000.0),
            ("guard_down_s", 0.0, 1000.0),
            ("guard_quantile", 0.5, 1.0),
            ("guard_gain", 0.0, 1.0),
            ("guard_start", 0.0, 10.0),
        )
        check_ranges(self, checks, "gain: ")
        if (
            isinstance(self.bands, bool)
            or not isinstance(self.bands, int)
            or not 0 <= self.bands <= 64
        ):
            raise ConfigError(f"gain: bands must be an integer in [0, 64], got {self.bands!r}")
        if self.oversubtraction is not None and not (
            isinstance(self.oversubtraction, (int, float)) and 0.0 <= self.oversubtraction <= 1000.0
        ):
            raise ConfigError(
                f"gain: oversubtraction must be in [0, 1000] or None, got {self.oversubtraction!r}"
            )

    def delay_samples(self, sample_rate_hz: float) -> int:
        return int(round(self.lookahead_ms * 1e-3 * sample_rate_hz))


class FilterBank:
    """K one-pole complex resonators evenly over `band_hz`, plus the rest band (K = 0: the
    rest band is the whole signal, one broadband gain)."""

    def __init__(
        self,
        *,
        sample_rate_hz: float,
        band_hz: tuple[float, float],
        bands: int,
        bandwidth: float = 1.0,
    ):
        self.sample_rate_hz = float(sample_rate_hz)
        low, high = float(band_hz[0]), float(band_hz[1])
        if bands == 0:
            self.centres_hz = np.zeros(0)
        elif bands == 1:
            self.centres_hz = np.array([(low + high) / 2])
        else:
            self.centres_hz = np.linspace(low, high, bands)
        spacing = (high - low) / max(bands - 1, 1)
        width = bandwidth * spacing
        # A pole radius near 0 would make a "resonator" pass everything: keep it selective.
        radius = max(MIN_POLE_RADIUS, 1.0 - math.pi * width / self.sample_rate_hz)
        self.poles = radius * np.exp(2j * np.pi * self.centres_hz / self.sample_rate_hz)

    @property
    def n_bands(self) -> int:
        """Bands including the rest band."""
        return len(self.poles) + 1

    def responses(self, freqs_hz: np.ndarray) -> np.ndarray:
        """(K + 1, F) complex responses of the band signals (last: the rest band)."""
        z = np.exp(2j * np.pi * np.asarray(freqs_hz, float) / self.sample_rate_hz)
        out = np.empty((self.n_bands, len(z)), complex)
        for k, pole in enumerate(self.poles):
            gain = 1.0 - abs(pole)
            # b = 2 Re(z_k): half the resonator plus half its mirror at -f.
            out[k] = gain / (1.0 - pole / z) + gain / (1.0 - np.conj(pole) / z)
        out[-1] = 1.0 - out[:-1].sum(axis=0)
        return out

    def power_weights(self, block_length: int, window: np.ndarray) -> np.ndarray:
        """(K + 1, F) weights turning a block's expected |X(f)|^2 (rfft bins of a windowed
        block) into each band's expected power per sample."""
        freqs = np.fft.rfftfreq(block_length, 1.0 / self.sample_rate_hz)
        gains = np.abs(self.responses(freqs)) ** 2
        one_sided = np.full(len(freqs), 2.0)
        one_sided[0] = 1.0
        if block_length % 2 == 0:
            one_sided[-1] = 1.0
        return gains * one_sided / (block_length * float(np.sum(np.asarray(window) ** 2)))


@numba.njit(cache=True, fastmath=True)
def _gain_kernel(r, noise, row, poles, cal, levels, rates, st, out, collect, v, out_v, power_scale):  # noqa: C901 (numba per-sample loop: one pass, no calls)
    """r (n, C) residual; noise (n, C, B) table band powers (B = K + 1), row[i] each
    sample's; state updated in place; out[i]: the output for sample i - D (hist holds D + 1
    samples per band). Optional (else empty arrays): collect (n, C, B + 2), P / N per band,
    the opening score over open_alpha and the guard's log level (calibration); v (n, C), a
    second signal (the drop-in's unfiltered one, already D late) split by the same bank
    (states zv) and weighted by the same gains into out_v; power_scale (n,), a factor on
    each sample's expected noise (the gap's drift advice).

    `cal`, `levels`, `rates`, `st`: tuples of the calibrated arrays, the settings' levels,
    the per-sample rates (LowLatencyGain builds them) and the state's arrays (GainState's
    fields), unpacked below.

    One function: numba compiles it into one pass per sample over every channel and band,
    the state in local variables, no call per sample (what makes 3 kHz cheap in Python)."""
    alpha, bias, open_alpha, guard_ref = cal
    floor, exponent, track_clip, track_range, open_span, guard_gain = levels
    a_attack, a_release, a_track, open_decay, hold_decay, a_guard_up, a_guard_down = rates
    z, power, hist, position, log_ratio, correction, opening, open_wait, noise_held, guard, zv = st
    n, C = r.shape
    K = poles.shape[0]
    B = K + 1
    size = hist.shape[2]
    keep = collect.shape[0] == n
    second = v.shape[0] == n
    scaled = power_scale.shape[0] == n
    pos = position[0]
    phase = position[1]  # samples since the last correction update
    ratio = np.empty((C, B))
    level = np.empty(C)
    inflow = np.empty(K)  # each resonator's input gain, 1 - |pole| (a hypot: not per sample)
    for k in range(K):
        inflow[k] = 1.0 - abs(poles[k])
    for i in range(n):
        write = pos
        read = (pos + 1) % size  # the oldest: D samples ago
        for c in range(C):
            x = r[i, c]
            total = 0.0
            for k in range(K):
                pole = poles[k]
                zk = pole * z[c, k] + inflow[k] * x
                z[c, k] = zk
                band = 2.0 * zk.real
                hist[c, k, write] = band
                total += band
                inst = 2.0 * (zk.real * zk.real + zk.imag * zk.imag)
                power[c, k] += (a_attack if inst > power[c, k] else a_release) * (
                    inst - power[c, k]
                )
            rest = x - total
            hist[c, K, write] = rest
            inst = rest * rest
            power[c, K] += (a_attack if inst > power[c, K] else a_release) * (inst - power[c, K])
            score = 0.0
            update = a_track > 0.0 and (phase + i) % TRACK_EVERY == 0
            for k in range(B):
                p = power[c, k]
                expected = noise[row[i], c, k]
                if scaled:
                    expected *= power_scale[i]
                if expected > 0.0:
                    # The noise of the speeds just left, decaying (see the module doc).
                    decayed = noise_held[c, k] * hold_decay
                    if decayed > expected:
                        expected = decayed
                noise_held[c, k] = expected  # no joint state (0): start afresh
                if update and expected > 0.0 and p > SILENCE * expected:
                    # (A silent channel - an axis at rest reads a constant - teaches nothing.)
                    step = math.log(p / expected) - log_ratio[c, k]
                    if step > track_clip:
                        step = track_clip
                    elif step < -track_clip:
                        step = -track_clip
                    value = log_ratio[c, k] + a_track * step
                    low = bias[c, k] - track_range
                    high = bias[c, k] + track_range
                    log_ratio[c, k] = low if value < low else (high if value > high else value)
                    correction[c, k] = math.exp(log_ratio[c, k] - bias[c, k])
                expected *= correction[c, k]
                ratio[c, k] = p / expected if expected > 0.0 else 0.0
                if keep:
                    collect[i, c, k] = ratio[c, k]
                if expected > 0.0 and alpha[c, k] > 0.0 and ratio[c, k] > score * alpha[c, k]:
                    score = ratio[c, k] / alpha[c, k]
            # Opening: when some band stands out beyond what noise reaches, every band
            # opens for a while (the event keeps its waveform; the noise under it is not
            # touched either).
            score /= open_alpha[c]
            # The guard: a slow level of the score (in logs; rises in tens of ms, falls in
            # hundreds). Where the noise stands above the table for longer than an event
            # lasts (speeds the calibration never saw, a flight phase it did not hold),
            # the opening asks for that much more and the expected noise rises with it.
            if a_guard_up > 0.0:
                log_score = math.log(score) if score > TINY else LOG_TINY
                rate = a_guard_up if log_score > guard[c] else a_guard_down
                guard[c] += rate * (log_score - guard[c])
                if guard[c] > guard_ref[c]:
                    score /= math.exp(guard[c] - guard_ref[c])
                    lift = math.exp(guard_gain * (guard[c] - guard_ref[c]))
                    for k in range(B):
                        ratio[c, k] /= lift
            if keep:
                collect[i, c, B] = score
                collect[i, c, B + 1] = guard[c]
            level[c] = (score - 1.0) / open_span if open_span > 0.0 else 0.0
        # A contact shakes the sensor, not one axis: an event seen on any channel opens
        # every channel (an axis whose calibration residual had bursts would not open on
        # its own and would take part of the event away).
        shared = 0.0
        for c in range(C):
            if level[c] > shared:
                shared = level[c]
        if shared > 1.0:
            shared = 1.0
        for c in range(C):
            if open_span > 0.0:
                # An opening holds for the look-ahead (the event it saw leaves that much
                # later), then decays over open_hold_ms.
                if shared >= opening[c]:
                    opening[c] = shared
                    open_wait[c] = size - 1
                elif open_wait[c] > 0:
                    open_wait[c] -= 1
                else:
                    opening[c] *= open_decay
                    if shared > opening[c]:
                        opening[c] = shared
            y = 0.0
            yv = 0.0
            rest_v = v[i, c] if second else 0.0
            for k in range(B):
                g = 1.0 - alpha[c, k] / ratio[c, k] if ratio[c, k] > 0.0 else 1.0
                if g <= 0.0:
                    g = 0.0
                elif exponent == 0.5:
                    g = math.sqrt(g)
                elif exponent != 1.0:
                    g = g**exponent
                if g < opening[c]:
                    g = opening[c]
                if g < floor:
                    g = floor
                y += g * hist[c, k, read]
                if second:
                    if k < K:
                        pole = poles[k]
                        zk = pole * zv[c, k] + inflow[k] * v[i, c]
                        zv[c, k] = zk
                        band = 2.0 * zk.real
                        rest_v -= band
                        yv += g * band
                    else:
                        yv += g * rest_v
            out[i, c] = y
            if second:
                out_v[i, c] = yv
        pos = read
    position[0] = pos
    position[1] = (phase + n) % TRACK_EVERY
    return out


@dataclass
class GainState:
    z: np.ndarray  # (C, K) complex resonator states
    power: np.ndarray  # (C, B) band powers
    hist: np.ndarray  # (C, B, D + 1) band signals of the last D + 1 samples
    position: np.ndarray  # (2,) ring write position, samples since the last correction update
    log_ratio: np.ndarray  # (C, B) tracked log(P / table)
    correction: np.ndarray  # (C, B) exp(log_ratio - bias)
    opening: np.ndarray  # (C,) how far all bands are held open
    open_wait: np.ndarray  # (C,) samples the opening is held before it decays
    noise_held: np.ndarray  # (C, B) expected band noise, held after the table's value drops
    guard: np.ndarray  # (C,) log of the opening score's slow level
    zv: np.ndarray  # (C, K) complex resonator states of the second signal (drop-in)

    def arrays(self) -> tuple:
        """The arrays in field order, as the kernel unpacks them (not copied: it updates them).
        The instance dict holds exactly the fields, in order (a per-batch call: `fields()`
        cost more than the kernel on a live node's few samples)."""
        return tuple(vars(self).values())


def _filled(value, default: float, shape: tuple) -> np.ndarray:
    """A copy of `value` broadcast to `shape`; `default` everywhere if it is None."""
    if value is None:
        return np.full(shape, default)
    return np.broadcast_to(np.asarray(value, float), shape).copy()


class LowLatencyGain:
    """Streaming gain stage for C channels. process(r (n, C), noise (n, C, B)) returns n
    output samples, each D samples behind the input (the first D outputs of a stream
    belong to samples before its start: zeros). State explicit: any chunking gives the
    result of one call, to the bit."""

    def __init__(
        self,
        bank: FilterBank,
        settings: GainSettings,
        *,
        n_channels: int,
        alpha: np.ndarray | None = None,
        bias: np.ndarray | None = None,
        open_alpha: np.ndarray | None = None,
        guard_ref: np.ndarray | None = None,
    ):
        self.bank = bank
        self.settings = settings
        self.n_channels = int(n_channels)
        fs = bank.sample_rate_hz
        shape = (self.n_channels, bank.n_bands)
        self.delay = settings.delay_samples(fs)
        if settings.oversubtraction is not None:
            alpha = np.full(shape, float(settings.oversubtraction))
        self.alpha = _filled(alpha, 1.0, shape)
        self.bias = _filled(bias, 0.0, shape)
        self.open_alpha = _filled(open_alpha, 1.0, (self.n_channels,))

        # No reference level (a model calibrated before the guard): the guard never acts.
        self.guard_ref = _filled(guard_ref, np.inf, (self.n_channels,))

        def rate(ms: float) -> float:
            return 1.0 - math.exp(-1.0 / (ms * 1e-3 * fs)) if ms > 0 else 1.0

        def decay(ms: float) -> float:
            return math.exp(-1.0 / (ms * 1e-3 * fs)) if ms > 0 else 0.0

        # The correction is updated every TRACK_EVERY samples: its rate per update.
        a_track = (
            1.0 - math.exp(-TRACK_EVERY / (settings.track_s * fs)) if settings.track_s > 0 else 0.0
        )
        self._rates = (  # the kernel's order
            rate(settings.attack_ms),
            rate(settings.release_ms),
            a_track,
            decay(settings.open_hold_ms),
            decay(settings.hold_ms),
            rate(1e3 * settings.guard_up_s) if settings.guard_up_s > 0 else 0.0,
            rate(1e3 * settings.guard_down_s),
        )
        self._levels = (
            float(settings.floor),
            float(settings.exponent),
            float(settings.track_clip),
            float(settings.track_range_db) * math.log(10.0) / 10.0,
            float(settings.open_span) if settings.open_hold_ms > 0 else 0.0,
            float(settings.guard_gain),
        )
        self.state = self.initial_state()

    def initial_state(self) -> GainState:
        C, B = self.n_channels, self.bank.n_bands
        return GainState(
            z=np.zeros((C, B - 1), complex),
            power=np.zeros((C, B)),
            hist=np.zeros((C, B, self.delay + 1)),
            position=np.zeros(2, np.int64),
            log_ratio=self.bias.copy(),
            correction=np.ones((C, B)),
            opening=np.zeros(C),
            open_wait=np.zeros(C, np.int64),
            noise_held=np.zeros((C, B)),
            # From below when there is no reference (calibration): the guard rises to the
            # noise's level within a few guard_up_s, instead of falling for guard_down_s.
            guard=np.where(
                np.isfinite(self.guard_ref), self.guard_ref + self.settings.guard_start, LOG_TINY
            ),
            zv=np.zeros((C, B - 1), complex),
        )

    def reset_signal(self) -> None:
        """A new segment (after a long gap): forget the signal, keep the noise correction and
        the guard (they describe the noise, not the signal), the guard at least at its start
        (the lines' phases are lost over the gap: the canceller settles again)."""
        kept = self.state
        self.state = self.initial_state()
        self.state.log_ratio, self.state.correction = kept.log_ratio, kept.correction
        self.state.guard = np.maximum(kept.guard, self.state.guard)
        self.state.position[1] = kept.position[1]

    def process(
        self,
        r: np.ndarray,
        noise: np.ndarray,
        *,
        index: np.ndarray | None = None,
        collect: bool = False,
        unfiltered: np.ndarray | None = None,
        power_scale: np.ndarray | None = None,
    ):
        """r (n, C) samples; noise (n, C, B) expected band powers per sample, or (R, C, B)
        rows with `index` (n,) naming each sample's row (held joint states: one row per
        joint state, not per sample). `unfiltered` (n, C): the signal whose band-passed
        image, D samples late, is `r` (the drop-in output's); it is split by the same bank
        and weighted by the same gains: returns (out, out_unfiltered). `power_scale` (n,):
        a factor on each sample's expected noise powers."""
        r = np.ascontiguousarray(r, dtype=np.float64)
        noise = np.ascontiguousarray(noise, dtype=np.float64)
        C, B = self.n_channels, self.bank.n_bands
        rows = len(r) if index is None else len(noise)
        if r.ndim != 2 or r.shape[1] != C or noise.shape != (rows, C, B):
            raise ConfigError(
                f"gain: expected ({len(r)}, {C}) samples and ({rows}, {C}, {B}) noise powers, "
                f"got {r.shape} and {noise.shape}"
            )
        if index is None:
            index = np.arange(len(r))
        index = np.ascontiguousarray(index, dtype=np.int64)
        if index.shape != (len(r),) or (len(r) and (index.min() < 0 or index.max() >= rows)):
            raise ConfigError(f"gain: index must name a noise row for each of the {len(r)} samples")
        out = np.empty_like(r)
        ratios = np.empty((len(r), C, B + 2)) if collect else np.empty((0, C, B + 2))
        if unfiltered is None:
            v = np.empty((0, C))
        else:
            v = np.ascontiguousarray(unfiltered, dtype=np.float64)
            if v.shape != r.shape:
                raise ConfigError(f"gain: unfiltered samples {v.shape} differ from {r.shape}")
        out_v = np.empty_like(v)
        scale = (
            np.empty(0)
            if power_scale is None
            else np.ascontiguousarray(np.broadcast_to(power_scale, (len(r),)), dtype=np.float64)
        )
        if len(r):
            cal = (self.alpha, self.bias, self.open_alpha, self.guard_ref)
            state = self.state.arrays()
            args = (index, self.bank.poles, cal, self._levels, self._rates, state)
            _gain_kernel(r, noise, *args, out, ratios, v, out_v, scale)
        if unfiltered is not None:
            return out, out_v
        return (out, ratios) if collect else out
