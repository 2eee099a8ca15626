"""Spectral subtraction of the expected ego-vibration (paper Eqs. 2-4, Fig. 2).

Per block: X = max(|Y| - alpha N, beta N) with the noisy phase (alpha 1, beta 0: the
paper), N from the noise model at the block's mean joint velocity, then overlap-add.
`rule` can replace the magnitude rule ((|Y|, N) (B, C, F) -> |X|: baselines such as Wiener).

Outputs: "bandpassed" (the paper's), and "dropin" (the default per axis): the raw signal
less the estimated ego-vibration, gravity and motion untouched. It removes (1 - gain) of
each bin (the paper's gain on the band-passed block) from half the band's low edge up
(skirts included: a reader that band-passes it gets no ego-vibration back), taken from the
same block unfiltered (the raw phase, which the causal band-pass would shift) less what
lies far below the band (which would leak into the band's bins through the window). With
nothing to subtract the output is the input exactly, delayed by the block.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from egovib_ros.core.filters import CHANNEL_LAYOUTS
from egovib_ros.core.noise_model import NoiseModel
from egovib_ros.core.stream import BlockFramer, Blocks, DenoiserStats, FramerSettings, feed
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.core.velocity import MISSING
from egovib_ros.errors import ConfigError, StreamError, check_ranges

LOG = logging.getLogger("egovib_ros.core")

MagnitudeRule = Callable[[np.ndarray, np.ndarray], np.ndarray]


OUTPUTS = ("dropin", "bandpassed")
MAX_OVERSUBTRACTION = 10.0
MAX_FLOOR = 1.0
#: The drop-in output leaves the bins below this share of the band's low edge as they are.
DROPIN_LOWEST_FRACTION = 0.5
#: A level change over time beyond this (dB) is not a warm-up but a different robot.
MAX_NOISE_GAIN_DB = 20.0


@dataclass(frozen=True, kw_only=True)
class SubtractionSettings:
    """max(|Y| - alpha N, beta N): alpha `oversubtraction` (the paper: 1), beta `floor`
    (the paper: 0; Berouti 1979 keeps a little noise against "musical" artefacts)."""

    oversubtraction: float = 1.0
    floor: float = 0.0

    def __post_init__(self) -> None:
        checks = (("oversubtraction", 0.0, MAX_OVERSUBTRACTION), ("floor", 0.0, MAX_FLOOR))
        check_ranges(self, checks)

    def rule(self) -> MagnitudeRule:
        return paper_rule(self.oversubtraction, self.floor)


def paper_rule(oversubtraction: float = 1.0, floor: float = 0.0) -> MagnitudeRule:
    """Magnitude subtraction: max(|Y| - alpha N, beta N) (Boll 1979; floor as Berouti 1979)."""
    if (
        not (math.isfinite(oversubtraction) and math.isfinite(floor))
        or oversubtraction < 0
        or floor < 0
    ):
        raise ConfigError(
            f"oversubtraction and floor must be finite and >= 0, got {oversubtraction}, {floor}"
        )

    def rule(magnitude: np.ndarray, noise: np.ndarray) -> np.ndarray:
        cleaned = magnitude - oversubtraction * noise
        return np.maximum(cleaned, floor * noise) if floor > 0 else np.maximum(cleaned, 0.0)

    return rule


@dataclass
class DenoisedChunk:
    stamps_ns: np.ndarray  # (K,) input stamps of the output samples
    values: np.ndarray  # (K, C)

    def __len__(self) -> int:
        return len(self.stamps_ns)


def check_output(output: str | None, channels: str) -> str:
    """The output a denoiser of any method makes for `channels` (None: its default, the
    drop-in with per-axis channels); bad combinations are one ConfigError."""
    if channels not in ("per_axis", "combined"):
        raise ConfigError(f"channels: expected 'per_axis' or 'combined', got {channels!r}")
    if output is None:
        output = "dropin" if channels == "per_axis" else "bandpassed"
    if output not in OUTPUTS:
        raise ConfigError(f"output: expected one of {list(OUTPUTS)}, got {output!r}")
    if output == "dropin" and channels == "combined":
        raise ConfigError(
            "output: dropin needs channels per_axis (the combined signal is the paper's "
            "band-passed 1-D signal)"
        )
    return output


def noise_gain_curve(knots) -> tuple[np.ndarray, np.ndarray] | None:
    """(elapsed s, dB) knots of a level change over time (a warm-up the gap diagnosis
    fitted, `egovib gap`'s advice), checked: times ascending from 0, finite, at most
    +-MAX_NOISE_GAIN_DB; None for no knots."""
    if knots is None or len(knots) == 0:
        return None
    try:
        arr = np.asarray(knots, dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.zeros((0, 0))
    if arr.ndim != 2 or arr.shape[1] != 2 or not np.isfinite(arr).all():
        raise ConfigError(f"noise_gain_db: expected (elapsed s, dB) pairs, got {knots!r}")
    t, g = arr[:, 0], arr[:, 1]
    if t[0] < 0 or np.any(np.diff(t) <= 0) or np.abs(g).max() > MAX_NOISE_GAIN_DB:
        raise ConfigError(
            "noise_gain_db: times must rise from >= 0 s and gains stay within "
            f"+-{MAX_NOISE_GAIN_DB:g} dB, got {knots!r}"
        )
    return t, g


class FramedDenoiser:
    """The push/flush interface of a denoiser fed through a framer (`self._framer`): what
    the framer made ready (`_pop`) goes to `_process`, which returns the final samples."""

    def push_joint_states(self, stamps_ns: np.ndarray, velocity: np.ndarray) -> DenoisedChunk:
        self._framer.push_joint_states(stamps_ns, velocity)
        return self._process(self._pop())

    def push_sensor(self, stamps_ns: np.ndarray, accel: np.ndarray) -> DenoisedChunk:
        self._framer.push_sensor(stamps_ns, accel)
        return self._process(self._pop())

    def push(
        self,
        joint_stamps_ns: np.ndarray,
        joint_velocity: np.ndarray,
        stamps_ns: np.ndarray,
        accel: np.ndarray,
    ) -> DenoisedChunk:
        """push_joint_states then push_sensor, what both release processed in one pass (a
        live node's batch: the samples its new joint states release and the new ones)."""
        self._framer.push_joint_states(joint_stamps_ns, joint_velocity, release=False)
        self._framer.push_sensor(stamps_ns, accel)
        return self._process(self._pop())

    def flush(self) -> DenoisedChunk:
        self._framer.flush()
        return self._process(self._pop())

    @property
    def samples_pending(self) -> int:
        """Samples pushed still to be output (bad or out-of-order ones never will be),
        without building the stats (a live node asks at every batch)."""
        counts = self._framer.stats
        return (
            counts.samples_in - self.samples_out - counts.samples_bad - counts.dropped_out_of_order
        )

    @property
    def delay_ms(self) -> float:
        """The algorithmic delay (the most of `delay_samples`, joint wait aside), in ms."""
        return 1e3 * self.delay_samples[1] / self.model.sample_rate_hz

    @property
    def sensor_stamps(self) -> str:
        """What the sensor stamps mark: "sample", "receipt" (core.receipt) or "" (not yet
        told)."""
        return self._framer.stamps

    def run_arrays(
        self, sensor_stamps_ns, accel, joint_stamps_ns, joint_velocity, chunk_s: float
    ) -> tuple[np.ndarray, np.ndarray, DenoiserStats]:
        """Whole arrays through this denoiser, `chunk_s` seconds at a time (`feed`), then
        flushed: (stamps_ns (K,), values (K, C), stats)."""
        streams = (sensor_stamps_ns, accel, joint_stamps_ns, joint_velocity)
        rates = dict(
            sample_rate_hz=self.model.sample_rate_hz, joint_wait_s=self.settings.joint_wait_s
        )
        chunks = feed(self, *streams, chunk_s=chunk_s, **rates)
        chunks = [self._empty, *chunks, self.flush()]  # _empty: the (0, C) shape if none
        stamps = np.concatenate([c.stamps_ns for c in chunks])
        return stamps, np.concatenate([c.values for c in chunks]), self.stats


class StreamingDenoiser(FramedDenoiser):
    """Streaming spectral subtraction: push joint states and sensor chunks of any size;
    each push returns the samples that became final (output sample k carries input stamp
    k): `block_length - hop` .. `block_length - 1` samples after arrival (10.7-21 ms for the
    PR2), plus any wait for joint states. `noise_gain_db`: (elapsed s, dB) knots of a level
    change (the gap's drift advice) the noise estimate follows from the first block on."""

    def __init__(
        self,
        model: NoiseModel,
        *,
        channels: str = "per_axis",
        output: str | None = None,
        oversubtraction: float = 1.0,
        floor: float = 0.0,
        include_std: bool = True,
        rule: MagnitudeRule | None = None,
        joint_wait_s: float = 0.02,
        joint_lag_s: float = 0.0,
        noise_gain_db: tuple[tuple[float, float], ...] = (),
        source: str = "",
    ):
        output = check_output(output, channels)
        self.model = model
        self.channels = channels
        self.output = output
        self.subtraction = SubtractionSettings(oversubtraction=oversubtraction, floor=floor)
        self.settings = FramerSettings.for_model(
            model,
            layout=channels,
            joint_wait_s=joint_wait_s,
            joint_lag_s=joint_lag_s,
            with_steadiness=False,
            keep_raw=output == "dropin",
            source=source,
        )
        self._framer = BlockFramer(self.settings, model.n_joints)
        if not np.allclose(self._framer.window, model.window, rtol=0, atol=1e-12):
            raise StreamError(
                f"{model.provenance.get('path', 'model')}: analysis window differs from "
                f"{model.window_name} for L={model.block_length}, hop={model.hop}"
            )
        self._window = model.window
        # the drop-in output's bins left as they are (gravity, motion: module doc)
        freqs = np.fft.rfftfreq(model.block_length, 1.0 / model.sample_rate_hz)
        self._outside_band = freqs < DROPIN_LOWEST_FRACTION * model.band_hz[0]  # (F,)
        self.channel_index = model.channel_indices(CHANNEL_LAYOUTS[channels])
        self._include_std = include_std
        self._table = model.table(self.channel_index, include_std=include_std)  # None: huge grid
        self._custom_rule = rule
        self._rule = rule if rule is not None else self.subtraction.rule()
        n_channels = len(self.channel_index)
        self._tail = np.zeros((model.block_length // model.hop - 1, n_channels, model.hop))
        # Returned by pushes that complete no sample (most joint-state pushes): shared, read-only.
        self._empty = DenoisedChunk(np.zeros(0, dtype=np.int64), np.zeros((0, n_channels)))
        self._empty.stamps_ns.flags.writeable = False
        self._empty.values.flags.writeable = False
        self.blocks_out_of_grid = 0
        self.blocks_unmeasured = 0
        self.samples_out = 0
        self._warned: set[str] = set()
        self._noise_gain = noise_gain_curve(noise_gain_db)
        self._t0_ns: int | None = None  # the first block's first stamp: elapsed time's zero

    # --- API -----------------------------------------------------------------
    def set_subtraction(
        self, *, oversubtraction: float | None = None, floor: float | None = None
    ) -> None:
        """Change alpha/beta while streaming (takes effect from the next block)."""
        if self._custom_rule is not None:
            raise ConfigError(
                "this denoiser uses a custom magnitude rule: oversubtraction/floor do not apply"
            )
        current = self.subtraction
        self.subtraction = SubtractionSettings(
            oversubtraction=current.oversubtraction if oversubtraction is None else oversubtraction,
            floor=current.floor if floor is None else floor,
        )
        self._rule = self.subtraction.rule()

    @property
    def delay_samples(self) -> tuple[int, int]:
        """(min, max) samples between a sample's arrival and its output."""
        return self.model.block_length - self.model.hop, self.model.block_length - 1

    def _pop(self) -> list[Blocks]:
        return self._framer.pop_blocks()

    @property
    def stats(self) -> DenoiserStats:
        s = self._framer.stats
        return DenoiserStats.of(
            s,
            samples_out=self.samples_out,
            blocks=s.blocks,
            blocks_held_joint_state=s.blocks_held,
            blocks_no_joint_state=s.blocks_missing,
            blocks_out_of_grid=self.blocks_out_of_grid,
            blocks_unmeasured=self.blocks_unmeasured,
            rate_checked=self._framer.rate_checked,
        )

    # --- internals -------------------------------------------------------------
    def _process(self, batches: list[Blocks]) -> DenoisedChunk:
        if not batches:
            return self._empty
        if len(batches) == 1 and batches[0].n == 1 and not batches[0].ends_segment:
            # The live case: one block per call.
            blocks = batches[0]
            heads = self._overlap_add(self._subtract(blocks))[0]
            real = blocks.out_stamps_ns[0] >= 0
            if real.all():
                chunk = DenoisedChunk(blocks.out_stamps_ns[0], heads)
            else:
                chunk = DenoisedChunk(blocks.out_stamps_ns[0][real], heads[real])
            self.samples_out += len(chunk)
            return chunk
        stamps_out, values_out = [], []
        for blocks in batches:
            if blocks.n:
                heads = self._overlap_add(self._subtract(blocks))
                real = blocks.out_stamps_ns >= 0
                stamps_out.append(blocks.out_stamps_ns[real])
                values_out.append(heads[real])
            if blocks.ends_segment:
                # End of stream or a long gap: nothing overlaps the next block.
                self._tail = np.zeros_like(self._tail)
        if not stamps_out:
            return self._empty
        chunk = DenoisedChunk(np.concatenate(stamps_out), np.concatenate(values_out))
        self.samples_out += len(chunk)
        return chunk

    def _overlap_add(self, cleaned: np.ndarray) -> np.ndarray:
        """(B, C, L) processed blocks -> (B, hop, C) completed output hops; carries the tail.

        With 50 % overlap the additions are the same whatever B is (streaming == batch to
        the bit); with more overlap the tail is summed in another order (~1e-16 apart)."""
        n_blocks, n_channels, block_length = cleaned.shape
        hop = self.model.hop
        overlap = block_length // hop
        if n_blocks == 1 and overlap == 2:
            # Same additions as below: (0 + tail) + head == tail + head, 0 + new_tail == new_tail.
            head = self._tail[0] + cleaned[0, :, :hop]
            self._tail = cleaned[:, :, hop:]
            return head.T[None]
        segments = cleaned.reshape(n_blocks, n_channels, overlap, hop)
        extended = np.zeros((n_blocks + overlap - 1, n_channels, hop))
        extended[: overlap - 1] += self._tail
        for i in range(overlap):
            extended[i : i + n_blocks] += segments[:, :, i]
        self._tail = extended[n_blocks:]
        return extended[:n_blocks].transpose(0, 2, 1)

    def _subtract(self, blocks: Blocks) -> np.ndarray:
        """(B, C, L) blocks to overlap-add: the cleaned windowed blocks, or for the drop-in
        output the windowed raw blocks less what is removed from them."""
        if self.output == "bandpassed":
            spectrum = np.fft.rfft(blocks.samples * self._window, axis=-1)  # (B, C, F)
            gain = self._block_gain(blocks, np.abs(spectrum))
            return np.fft.irfft(spectrum * gain, n=self.model.block_length, axis=-1)
        c = len(self.channel_index)
        band = np.fft.rfft(blocks.samples[:, :c] * self._window, axis=-1)
        removed = 1.0 - self._block_gain(blocks, np.abs(band))  # (B, C, F)
        removed[..., self._outside_band] = 0.0
        above = np.fft.rfft(blocks.samples[:, 2 * c :] * self._window, axis=-1)
        removed = np.fft.irfft(above * removed, n=self.model.block_length, axis=-1)
        return blocks.samples[:, c : 2 * c] * self._window - removed

    def _block_gain(self, blocks: Blocks, magnitude: np.ndarray) -> np.ndarray:
        """(B, C, F) gain of each bin: the rule's |X| / |Y| at the blocks' noise estimates."""
        usable = blocks.status != MISSING
        if self._noise_gain is not None and self._t0_ns is None:  # any block, usable or not
            self._t0_ns = int(blocks.t_first_ns[0])
        if blocks.n == 1 and usable[0] and self._table is not None:
            # One block (the live case): skip the general lookup's bookkeeping.
            noise, outside, measured = self.model.estimate_one(blocks.velocity[0], self._table)
            self.blocks_unmeasured += not measured
            self._count_outside(outside)
            return self._gain(magnitude, self._scaled(noise, blocks.t_first_ns))
        if not usable.all():
            self._warn_once(
                "missing", f"no joint state for a block: passing the {self.output} signal through"
            )
        gain = np.ones_like(magnitude)
        if usable.any():
            noise, outside, measured = self.model.lookup(
                blocks.velocity[usable], self.channel_index, include_std=self._include_std
            )
            self.blocks_unmeasured += int((~measured).sum())
            self._count_outside(outside)
            noise = self._scaled(noise, blocks.t_first_ns[usable])
            gain[usable] = self._gain(magnitude[usable], noise)
        return gain

    def _count_outside(self, outside: np.ndarray) -> None:
        """Blocks beyond the grid (noise_model.grid_limits) counted (their noise: the edge
        cells'), and said once."""
        n_outside = int(outside[0]) if len(outside) == 1 else int(outside.sum())  # (live: one)
        if not n_outside:
            return
        self.blocks_out_of_grid += n_outside
        self._warn_once(
            "out_of_grid",
            "joint velocity beyond the model grid by more than half a cell: using the "
            "edge cells (calibrate at the speeds the robot runs at)",
        )

    def _scaled(self, noise: np.ndarray, t_first_ns: np.ndarray) -> np.ndarray:
        """The noise estimate (B, C, F) times the level change `noise_gain_db` gives at each
        block's elapsed time (from the first block's first stamp), when one is set."""
        if self._noise_gain is None:
            return noise
        elapsed = (t_first_ns - self._t0_ns) / NS_PER_S
        knots_s, gain_db = self._noise_gain
        scale = 10.0 ** (np.interp(elapsed, knots_s, gain_db) / 20.0)
        return noise * scale[:, None, None]

    def _gain(self, magnitude: np.ndarray, noise: np.ndarray) -> np.ndarray:
        cleaned = self._rule(magnitude, noise)
        # |Y| = 0 (a dead axis): gain 0, whatever the rule says (a floor would give inf * 0).
        return np.divide(cleaned, magnitude, out=np.zeros_like(magnitude), where=magnitude > 0)

    def _warn_once(self, key: str, message: str) -> None:
        if key not in self._warned:
            self._warned.add(key)
            source = self.settings.source  # the bag and topic: e.g. detect's no-contact bag
            LOG.warning(f"{source}: {message}" if source else message)


def denoise_batch(
    sensor_stamps_ns: np.ndarray,
    accel: np.ndarray,
    joint_stamps_ns: np.ndarray,
    joint_velocity: np.ndarray,
    model: NoiseModel,
    *,
    channels: str = "per_axis",
    chunk_s: float = 30.0,
    **options,
) -> tuple[np.ndarray, np.ndarray, DenoiserStats]:
    """Denoise whole arrays through the streaming denoiser, `chunk_s` seconds at a time
    (bounded working memory): (stamps_ns (K,), values (K, C), stats), K the valid samples."""
    denoiser = StreamingDenoiser(model, channels=channels, **options)
    return denoiser.run_arrays(sensor_stamps_ns, accel, joint_stamps_ns, joint_velocity, chunk_s)
