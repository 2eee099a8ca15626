"""Denoising methods compared on the same data, each returning the paper's 1-D signal.

Every method returns an (N,) array on the input's accelerometer stamps, in the
paper's measurement space (axes summed, 150-750 Hz band-passed by the core's
causal filter), so metrics can compare them sample by sample. Delays are the
algorithmic latency of a streaming implementation, in ms:

  bandpass      band-pass only (what a user gets without a noise model)       0
  boll          Boll 1979 magnitude subtraction of the mean noise only        L/fs
  paper         the paper: subtract mean + std (Eq. 5/6)                      L/fs
  wiener        decision-directed Wiener gain (Ephraim-Malah 1984 a-priori
                SNR) with the same noise table as noise amplitude             L/fs
  noisereduce   stationary spectral gating (noisereduce), noise clip from
                no-contact calibration data; offline, non-causal STFT         n_fft/fs
  per_axis      the paper's subtraction on x, y, z separately, then summed    L/fs
  paper_L32     the paper with 32-sample blocks (a model calibrated at L=32)  32/fs

Everything block-based goes through the core (`denoise_batch` with its `rule`,
`include_std`, `channels` options); nothing here re-implements framing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from egovib_ros.core import NoiseModel, denoise_batch, filters

NOISEREDUCE_N_FFT = 64

#: name -> human label, in table order.
METHOD_LABELS = {
    "bandpass": "band-pass only",
    "boll": "Boll (mean only)",
    "paper": "paper (mean + std)",
    "wiener": "Wiener (decision-directed)",
    "noisereduce": "noisereduce (stationary gate)",
    "per_axis": "paper, per axis",
    "paper_L32": "paper, L = 32",
}


@dataclass
class MethodContext:
    """What the methods may use besides the test signal itself.

    model:        the noise model (L = 64 in the paper).
    model_short:  a model calibrated from the same data with shorter blocks (paper_L32).
    noise_clip:   (n,) no-contact calibration signal, combined and band-passed (noisereduce).
    """

    model: NoiseModel
    model_short: NoiseModel | None = None
    noise_clip: np.ndarray | None = None


def combined_bandpassed(accel: np.ndarray, model: NoiseModel) -> np.ndarray:
    """(N,) sum of the three axes, band-passed with the core's causal filter and the
    model's band."""
    return filters.combined_bandpassed(
        accel, sample_rate_hz=model.sample_rate_hz, band_hz=model.band_hz, order=model.band_order
    )


def on_input_stamps(
    out_stamps: np.ndarray, values: np.ndarray, in_stamps: np.ndarray
) -> np.ndarray:
    """Sum the output channels and place them on the input stamps (0 where a sample is missing).

    Denoised samples carry the stamp of the input sample they replace, so matching
    is by stamp: dropped inputs or a shorter output (e.g. a live node stopped before
    flushing) leave zeros, never a shift.
    """
    summed = np.asarray(values, float).sum(axis=1)
    if len(out_stamps) == len(in_stamps) and np.array_equal(out_stamps, in_stamps):
        return summed
    result = np.zeros(len(in_stamps))
    index = np.searchsorted(in_stamps, out_stamps)
    ok = (index < len(in_stamps)) & (in_stamps[np.minimum(index, len(in_stamps) - 1)] == out_stamps)
    result[index[ok]] = summed[ok]
    return result


class WienerRule:
    """Decision-directed Wiener gain as a core magnitude rule (stateful across blocks).

    a-priori SNR xi = a |X_prev|^2 / N^2 + (1 - a) max(|Y|^2 / N^2 - 1, 0),
    gain = xi / (1 + xi). N is the model's noise magnitude (mean + std): as noise
    power it over-estimates E|N|^2 a little, a mild over-subtraction.
    """

    def __init__(self, smoothing: float = 0.9):
        self.smoothing = float(smoothing)
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


def _core(rec, model: NoiseModel, **options) -> np.ndarray:
    stamps, values, _ = denoise_batch(
        rec.accel_stamps_ns, rec.accel, rec.joint_stamps_ns, rec.joint_velocity, model, **options
    )
    return on_input_stamps(stamps, values, rec.accel_stamps_ns)


def _noisereduce(rec, ctx: MethodContext) -> np.ndarray:
    import noisereduce

    if ctx.noise_clip is None:
        raise ValueError("noisereduce needs a no-contact noise clip (MethodContext.noise_clip)")
    signal = combined_bandpassed(rec.accel, ctx.model)
    # No mask smoothing: a 64-sample STFT gate, the same latency class as the paper.
    return noisereduce.reduce_noise(
        y=signal,
        sr=int(ctx.model.sample_rate_hz),
        stationary=True,
        y_noise=np.asarray(ctx.noise_clip, float),
        n_fft=NOISEREDUCE_N_FFT,
        freq_mask_smooth_hz=None,
        time_mask_smooth_ms=None,
    )


def _block_delay_ms(model: NoiseModel | None) -> float | None:
    return None if model is None else 1e3 * model.block_length / model.sample_rate_hz


RUNNERS: dict[str, Callable] = {
    "bandpass": lambda rec, ctx: combined_bandpassed(rec.accel, ctx.model),
    "boll": lambda rec, ctx: _core(rec, ctx.model, channels="combined", include_std=False),
    "paper": lambda rec, ctx: _core(rec, ctx.model, channels="combined"),
    "wiener": lambda rec, ctx: _core(rec, ctx.model, channels="combined", rule=WienerRule()),
    "noisereduce": _noisereduce,
    "per_axis": lambda rec, ctx: _core(rec, ctx.model, channels="per_axis"),
    "paper_L32": lambda rec, ctx: _core(rec, ctx.model_short, channels="combined"),
}


def method_delay_ms(name: str, ctx: MethodContext) -> float | None:
    """Algorithmic latency of a method in ms (None if it cannot run in this context)."""
    if name == "bandpass":
        return 0.0
    if name == "noisereduce":
        return 1e3 * NOISEREDUCE_N_FFT / ctx.model.sample_rate_hz
    if name == "paper_L32":
        return _block_delay_ms(ctx.model_short)
    return _block_delay_ms(ctx.model)


def available_methods(ctx: MethodContext) -> list[str]:
    """Methods that can run with what the context holds, in table order."""
    names = list(METHOD_LABELS)
    if ctx.model_short is None:
        names.remove("paper_L32")
    if ctx.noise_clip is None:
        names.remove("noisereduce")
    return names


def run_method(name: str, rec, ctx: MethodContext) -> np.ndarray:
    """(N,) combined band-passed output of method `name` on the recording `rec`."""
    if name not in RUNNERS:
        raise ValueError(f"unknown method {name!r}; expected one of {list(RUNNERS)}")
    if name == "paper_L32" and ctx.model_short is None:
        raise ValueError(
            "paper_L32 needs a model calibrated with 32-sample blocks (MethodContext.model_short)"
        )
    return np.asarray(RUNNERS[name](rec, ctx), float)
