"""The methods `egovib evaluate` compares, each a stream giving the paper's 1-D signal.

Every method outputs one value per input sample, in the paper's measurement space (axes
summed, band-passed by the core's causal filter), so metrics compare them sample by
sample. Delays are the algorithmic latency of a streaming implementation:

  bandpass      band-pass only (what a user gets without a noise model)       0
  boll          Boll 1979 magnitude subtraction of the mean noise only        L/fs
  paper         the paper: subtract mean + std (Eq. 5/6)                      L/fs
  wiener        decision-directed Wiener gain (Ephraim-Malah 1984 a-priori
                SNR) with the same noise table as noise amplitude             L/fs
  noisereduce   noisereduce's stationary spectral gate as a stream
                (`StationaryGate`), noise threshold from no-contact data      n_fft/fs
  per_axis      the paper's subtraction on x, y, z separately, then summed    L/fs
  paper_L32     the paper with 32-sample blocks (a model calibrated at L=32)  32/fs
  cancel, hybrid  core.methods' (band-passed output)                          their own
  default       what `egovib denoise` writes and the denoiser node publishes without
                options, band-passed as a reader of the topic sees it         its own

Everything block-based goes through the core's denoisers (core.methods.make_denoiser:
its `rule`, `include_std`, `channels` options); nothing here re-implements their framing.
"""

from __future__ import annotations

import numpy as np
from scipy import fft as sp_fft
from scipy import signal

from egovib_ros.core import NoiseModel
from egovib_ros.core.filters import BandPass
from egovib_ros.core.methods import SAMPLE_METHODS, default_method, make_denoiser

NOISEREDUCE_N_FFT = 64
NOISEREDUCE_N_STD = 1.5  # reduce_noise's n_std_thresh_stationary
NOISE_CLIP_SAMPLES = 600_000  # reduce_noise clips its noise clip to chunk_size samples

#: name -> (human label, its core denoiser's options or None), in table order.
METHOD_TABLE = {
    "default": (
        "the default: the model's default method, drop-in output band-passed",
        dict(channels="per_axis", method=None, output="dropin"),
    ),
    "bandpass": ("band-pass only", None),
    "boll": ("Boll (mean only)", dict(channels="combined", include_std=False)),
    "paper": ("paper (mean + std)", dict(channels="combined")),
    "wiener": ("Wiener (decision-directed)", dict(channels="combined")),
    "noisereduce": ("noisereduce (stationary gate)", None),
    "per_axis": ("paper, per axis", dict(channels="per_axis")),
    "paper_L32": ("paper, L = 32", dict(channels="combined")),
    "cancel": ("speed-locked harmonic cancellation", dict(channels="combined", method="cancel")),
    "hybrid": ("cancellation + low-latency gain", dict(channels="combined", method="hybrid")),
}
METHOD_LABELS = {name: label for name, (label, _) in METHOD_TABLE.items()}


class WienerRule:
    """Decision-directed Wiener gain as a core magnitude rule (stateful across blocks).

    a-priori SNR xi = a |X_prev|^2 / N^2 + (1 - a) max(|Y|^2 / N^2 - 1, 0),
    gain = xi / (1 + xi). N is the model's noise magnitude (mean + std): as noise
    power it over-estimates E|N|^2 a little, a mild over-subtraction.
    """

    def __init__(self):
        self.smoothing = 0.9
        self._previous_clean_power: np.ndarray | None = None

    def __call__(self, magnitude: np.ndarray, noise: np.ndarray) -> np.ndarray:
        noise_power = np.maximum(noise**2, 1e-20)
        posterior = magnitude**2 / noise_power
        cleaned = np.empty_like(magnitude)
        previous = self._previous_clean_power
        a = self.smoothing
        for i in range(len(magnitude)):
            instantaneous = np.maximum(posterior[i] - 1.0, 0.0)
            prior = (
                instantaneous
                if previous is None
                else a * previous / noise_power[i] + (1 - a) * instantaneous
            )
            cleaned[i] = prior / (1.0 + prior) * magnitude[i]
            previous = cleaned[i] ** 2
        self._previous_clean_power = previous
        return cleaned


class MethodStream:
    """push_joint_states(stamps, velocity) and push(stamps, accel, raw) return the output
    samples that became final (in input order; `raw` is the combined band-passed input);
    finish() returns the rest. Over a whole run the outputs add up to one per input, the
    same for any slicing. `delay_ms`: the method's algorithmic delay."""

    delay_ms = 0.0

    def push_joint_states(self, stamps_ns: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        return _EMPTY

    def push(self, stamps_ns: np.ndarray, accel: np.ndarray, raw: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def finish(self) -> np.ndarray:
        return _EMPTY


_EMPTY = np.zeros(0)
_EMPTY.flags.writeable = False


class BandpassStream(MethodStream):
    """The band-passed input itself (causal, no delay)."""

    def push(self, stamps_ns, accel, raw):
        return np.asarray(raw, float)


class CoreStream(MethodStream):
    """The core's denoiser, its output summed over channels and placed on the input stamps
    (a sample the core drops gets 0)."""

    def __init__(
        self, model: NoiseModel, *, method: str | None = "paper", source: str = "", **options
    ):
        # the metrics are those of the band-passed signal (the paper's): band-passed output,
        # or the drop-in output band-passed after the sum, as a reader of the topic sees it
        options = {"output": "bandpassed", **options}
        self.denoiser = make_denoiser(model, method, source=source, **options)
        self._band = BandPass.of(model, 1) if options["output"] == "dropin" else None
        self._pending = np.zeros(0, np.int64)  # input stamps without output yet
        self.delay_ms = self.denoiser.delay_ms

    def push_joint_states(self, stamps_ns, velocity):
        return self._place(self.denoiser.push_joint_states(stamps_ns, velocity))

    def push(self, stamps_ns, accel, raw):
        self._pending = np.concatenate([self._pending, np.asarray(stamps_ns, np.int64)])
        return self._place(self.denoiser.push_sensor(stamps_ns, accel))

    def finish(self):
        out = self._place(self.denoiser.flush())
        rest, self._pending = np.zeros(len(self._pending)), self._pending[:0]
        if self._band is not None and len(rest):
            rest = self._band.process(rest[None])[0]
        return np.concatenate([out, rest])

    def _place(self, chunk) -> np.ndarray:
        out = self._placed(chunk)
        return out if self._band is None or not len(out) else self._band.process(out[None])[0]

    def _placed(self, chunk) -> np.ndarray:
        if not len(chunk):
            return _EMPTY
        summed = np.asarray(chunk.values, float).sum(axis=1)
        n, pending = len(chunk), self._pending
        if n <= len(pending) and np.array_equal(pending[:n], chunk.stamps_ns):
            self._pending = pending[n:]
            return summed
        index = np.searchsorted(pending, chunk.stamps_ns)
        ok = index < len(pending)
        ok[ok] = pending[index[ok]] == chunk.stamps_ns[ok]
        if not ok.all():  # every output sample carries the stamp of an input sample
            raise RuntimeError("denoised sample without its input sample")
        out = np.zeros(int(index[-1]) + 1)
        out[index] = summed
        self._pending = pending[len(out) :]
        return out


class StationaryGate:
    """noisereduce's stationary spectral gate (reduce_noise(stationary=True, n_fft=64, no
    mask smoothing)) as a stream, with bounded look-ahead.

    As noisereduce does it: Hann frames of n_fft samples every n_fft // 4 on the signal
    zero-padded at both ends, a bin kept where its level 20 log10(|X| + eps) exceeds the
    noise threshold of its frequency (mean + 1.5 std of the noise clip's levels, see
    `gate_threshold`), else zeroed; inverse by windowed overlap-add. Output sample i is
    final once the frame starting at the multiple of n_fft // 4 at or before i is complete:
    up to n_fft - 1 samples of look-ahead (21 ms at 3 kHz).

    One change makes it a stream: noisereduce floors each level at the maximum level of
    its frequency over the whole signal (per 200 s chunk) minus 80 dB; that floor needs
    the whole signal and is left out (it only matters where a bin is > 80 dB below the
    loudest moment of its frequency and yet above the noise threshold).

    `threshold` may come later (`set_threshold`): the input waits until then."""

    def __init__(self, threshold: np.ndarray | None = None):
        self.n_fft, self.hop = NOISEREDUCE_N_FFT, NOISEREDUCE_N_FFT // 4
        self.overlap = self.n_fft // self.hop
        self.window = signal.get_window("hann", self.n_fft)
        self.scale = np.sqrt(1.0 / self.window.sum() ** 2)  # scipy.signal.stft, "spectrum"
        # the sum of squared windows over a sample's frames, added in frame order as istft does
        square = (self.window**2).reshape(self.overlap, self.hop)
        norm = np.zeros(self.hop)
        for k in range(self.overlap - 1, -1, -1):
            norm = norm + square[k]
        self.norm = np.where(norm > 1e-10, norm, 1.0)
        self.threshold = None if threshold is None else np.asarray(threshold, float)
        lead = self.n_fft - self.hop
        self._buf = np.zeros(lead)  # input from sample -lead on (zero padding before 0)
        self._tail = np.zeros((self.overlap - 1, self.hop))  # partial sums of coming hops
        self._out_pos = -lead  # index of the next output sample (negative: padding)
        self._waiting: list[np.ndarray] = []
        self.count = 0  # input samples pushed

    def set_threshold(self, threshold: np.ndarray) -> np.ndarray:
        """Set the noise threshold; returns the output of the input pushed before."""
        self.threshold = np.asarray(threshold, float)
        waiting, self._waiting = self._waiting, []
        return np.concatenate([_EMPTY] + [self._run(x) for x in waiting])

    def push(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, float)
        self.count += x.size
        if self.threshold is None:
            self._waiting.append(x)
            return _EMPTY
        return self._run(x)

    def finish(self) -> np.ndarray:
        if self.threshold is None:
            raise ValueError("StationaryGate: no noise threshold")
        if not self.count:
            return _EMPTY
        # zeros after the end until the frames covering the last sample are complete
        last_hop = (self.count - 1) // self.hop * self.hop
        start = self._out_pos
        out = self._run(np.zeros(last_hop + self.n_fft - self.count))
        return out[: self.count - max(start, 0)]

    def _run(self, x: np.ndarray) -> np.ndarray:
        buf = np.concatenate([self._buf, x])
        n_frames = (len(buf) - self.n_fft) // self.hop + 1 if len(buf) >= self.n_fft else 0
        if n_frames <= 0:
            self._buf = buf
            return _EMPTY
        frames = np.lib.stride_tricks.sliding_window_view(buf, self.n_fft)[:: self.hop][:n_frames]
        spectrum = sp_fft.rfft(self.window * frames, n=self.n_fft, axis=-1) * self.scale
        level = 20 * np.log10(np.abs(spectrum) + np.finfo(np.float64).eps)
        mask = (level > self.threshold) * 1.0  # prop_decrease = 1
        pieces = sp_fft.irfft(spectrum * mask, n=self.n_fft, axis=-1)[:, : self.n_fft]
        pieces = (pieces * self.window.sum()) * self.window
        segments = pieces.reshape(n_frames, self.overlap, self.hop)
        extended = np.zeros((n_frames + self.overlap - 1, self.hop))
        extended[: self.overlap - 1] += self._tail
        for k in range(self.overlap - 1, -1, -1):  # frame order, as scipy.signal.istft adds
            extended[k : k + n_frames] += segments[:, k]
        self._tail = extended[n_frames:]
        self._buf = buf[n_frames * self.hop :]
        out = (extended[:n_frames] / self.norm).reshape(-1)
        start, self._out_pos = self._out_pos, self._out_pos + out.size
        return out[max(-start, 0) :] if start < 0 else out


def gate_threshold(noise_clip: np.ndarray) -> np.ndarray:
    """Per-frequency noise threshold (dB) of noisereduce's stationary gate from a noise clip
    (its first NOISE_CLIP_SAMPLES samples, as reduce_noise clips it), as noisereduce 3.0
    computes it: levels 20 log10(|X| + eps), floored 80 dB below each frame's top level."""
    clip = np.asarray(noise_clip, float)[:NOISE_CLIP_SAMPLES]
    n_fft = NOISEREDUCE_N_FFT
    _, _, stft = signal.stft(
        clip, nfft=n_fft, noverlap=n_fft - n_fft // 4, nperseg=n_fft, padded=False
    )
    level = 20 * np.log10(np.abs(stft) + np.finfo(np.float64).eps)
    level = np.maximum(level, np.max(level, axis=-1, keepdims=True) - 80.0)
    return np.mean(level, axis=1) + np.std(level, axis=1) * NOISEREDUCE_N_STD


class GateStream(MethodStream):
    """`StationaryGate` on the combined band-passed input."""

    def __init__(self, threshold: np.ndarray | None, sample_rate_hz: float):
        self.gate = StationaryGate(threshold)
        self.delay_ms = 1e3 * NOISEREDUCE_N_FFT / sample_rate_hz

    def push(self, stamps_ns, accel, raw):
        return self.gate.push(raw)

    def finish(self):
        return self.gate.finish()


def adapts(name: str, model: NoiseModel) -> bool:
    """Whether method `name` adapts its model online when asked to (core.adapt); `default`
    where the model's default is one of them."""
    if name == "default":
        name = default_method(model)
    return name in SAMPLE_METHODS


def method_stream(
    name: str,
    *,
    model: NoiseModel,
    model_short: NoiseModel | None = None,
    gate: np.ndarray | None = None,
    source: str = "",
    adapt=None,
) -> MethodStream:
    """A fresh stream of method `name` (`gate`: noisereduce's noise threshold, may be set
    later on the stream's gate; `adapt`: core.adapt.AdaptSettings for the methods that
    adapt, `adapts`)."""
    if name not in METHOD_LABELS:
        raise ValueError(f"unknown method {name!r}; expected one of {list(METHOD_LABELS)}")
    if name == "bandpass":
        return BandpassStream()
    if name == "noisereduce":
        return GateStream(gate, model.sample_rate_hz)
    if name == "paper_L32":
        if model_short is None:
            raise ValueError("paper_L32 needs a model calibrated with 32-sample blocks")
        model = model_short
    options = dict(METHOD_TABLE[name][1])
    if name == "wiener":
        options["rule"] = WienerRule()
    if adapt is not None and adapts(name, model):
        options["adapt"] = adapt
    return CoreStream(model, source=source, **options)
