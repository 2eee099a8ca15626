"""One-pass calibration of the noise model (paper section 3, "PR2 Ego-vibration Estimation").

Blocks are framed exactly as in denoising, assigned to the velocity cell nearest their
mean joint velocity, and accumulated as per-cell sums of magnitudes and of squared
magnitudes, so memory stays constant however long the recording. A block is rejected
when its velocity is not steady (e.g. the gripper reversing at a limit, or the
controller still settling on a new cell) or not close to any grid point.
"""
from __future__ import annotations

import numpy as np

from egovib_ros import __version__
from egovib_ros.constants import BAND_HZ, BAND_ORDER, BLOCK_LENGTH, HOP, JOINT_NAMES, default_grid
from egovib_ros.core.filters import CHANNEL_LAYOUTS
from egovib_ros.core.noise_model import MEASURED_KINDS, MODEL_CHANNELS, NoiseModel, sweep_mask
from egovib_ros.core.stream import BlockFramer, Blocks, FramerSettings
from egovib_ros.core.velocity import MATCHED
from egovib_ros.errors import ConfigError


class CalibrationAccumulator:
    """Accumulates per-cell magnitude statistics from streamed joint states and accelerations."""

    def __init__(self, *, grid: tuple[np.ndarray, ...] | None = None, joint_names: tuple[str, ...] = JOINT_NAMES,
                 sample_rate_hz: float = 3000.0, block_length: int = BLOCK_LENGTH, hop: int = HOP,
                 band_hz: tuple[float, float] = BAND_HZ, band_order: int = BAND_ORDER, sweep: str = "full",
                 cell_tolerance: float = 0.3, steady_tolerance: float = 0.3,
                 joint_wait_s: float = 0.02, max_hold_s: float = 0.05, source: str = ""):
        if sweep not in MEASURED_KINDS:
            raise ConfigError(f"grid: expected one of {MEASURED_KINDS}, got {sweep!r}")
        self.grid = tuple(np.asarray(g, dtype=np.float64) for g in (grid if grid is not None else default_grid()))
        self.joint_names = tuple(joint_names)
        if len(self.joint_names) != len(self.grid):
            raise ConfigError(f"{len(self.joint_names)} joint names for {len(self.grid)} grid axes")
        self.sweep = sweep
        self.cell_tolerance = float(cell_tolerance)
        self.steady_tolerance = float(steady_tolerance)
        self.settings = FramerSettings(sample_rate_hz=sample_rate_hz, block_length=block_length, hop=hop,
                                       band_hz=band_hz, band_order=band_order, layout="all",
                                       joint_wait_s=joint_wait_s, max_hold_s=max_hold_s, source=source)
        self._framer = BlockFramer(self.settings, len(self.grid))
        self.window = self._framer.window
        shape = self.grid_shape + (len(MODEL_CHANNELS), block_length // 2 + 1)
        self._sum = np.zeros(shape)
        self._sumsq = np.zeros(shape)
        self._counts = np.zeros(self.grid_shape, dtype=np.int64)
        self._spacing = [np.minimum(np.diff(g, prepend=-np.inf), np.diff(g, append=np.inf)) for g in self.grid]
        self.expected_cells = sweep_mask(self.grid, sweep)     # the cells this sweep visits
        self.rejected = {"partial": 0, "no_joint_state": 0, "unsteady": 0, "off_grid": 0, "not_in_sweep": 0}
        assert CHANNEL_LAYOUTS["all"] == MODEL_CHANNELS

    @property
    def grid_shape(self) -> tuple[int, ...]:
        return tuple(len(g) for g in self.grid)

    @property
    def counts(self) -> np.ndarray:
        return self._counts.copy()

    @property
    def stats(self) -> dict:
        s = self._framer.stats
        return {"samples_in": s.samples_in, "blocks": s.blocks, "blocks_used": int(self._counts.sum()),
                "rejected": dict(self.rejected), "dropped_out_of_order": s.dropped_out_of_order,
                "nonfinite_replaced": s.nonfinite_replaced, "resets": s.resets}

    def push_joint_states(self, stamps_ns: np.ndarray, velocity: np.ndarray) -> None:
        self._framer.push_joint_states(stamps_ns, velocity)
        self._accumulate(self._framer.pop_blocks())

    def push_accel(self, stamps_ns: np.ndarray, accel: np.ndarray) -> None:
        self._framer.push_accel(stamps_ns, accel)
        self._accumulate(self._framer.pop_blocks())

    def flush(self) -> None:
        self._framer.flush()
        self._accumulate(self._framer.pop_blocks())

    def cell_of(self, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest cell index per joint (B, J) and whether every joint is within tolerance."""
        velocity = np.atleast_2d(velocity)
        index = np.empty(velocity.shape, dtype=np.intp)
        ok = np.ones(len(velocity), dtype=bool)
        for j, g in enumerate(self.grid):
            i = np.abs(velocity[:, j, None] - g[None, :]).argmin(axis=1)
            index[:, j] = i
            ok &= np.abs(velocity[:, j] - g[i]) <= self.cell_tolerance * self._spacing[j][i]
        return index, ok

    def _accumulate(self, batches: list[Blocks]) -> None:
        for blocks in batches:
            if blocks.n == 0:
                continue
            # Blocks holding start/end padding or gap-filled samples would bias the statistics.
            complete = blocks.complete
            self.rejected["partial"] += int((~complete).sum())
            usable = complete & (blocks.status == MATCHED)
            self.rejected["no_joint_state"] += int((complete & (blocks.status != MATCHED)).sum())
            velocity = np.where(usable[:, None], blocks.velocity, 0.0)
            index, near = self.cell_of(velocity)
            steady = np.ones(blocks.n, dtype=bool)
            for j in range(len(self.grid)):
                steady &= np.nan_to_num(blocks.steadiness[:, j], nan=np.inf) <= \
                    self.steady_tolerance * self._spacing[j][index[:, j]]
            self.rejected["unsteady"] += int((usable & ~steady).sum())
            self.rejected["off_grid"] += int((usable & steady & ~near).sum())
            accept = usable & steady & near
            if self.sweep == "superposition":
                in_sweep = self.expected_cells[tuple(index.T)]
                self.rejected["not_in_sweep"] += int((accept & ~in_sweep).sum())
                accept &= in_sweep
            if not accept.any():
                continue
            magnitude = np.abs(np.fft.rfft(blocks.samples[accept] * self.window, axis=-1))   # (b, C, F)
            cells = np.ravel_multi_index(tuple(index[accept].T), self.grid_shape)
            flat_sum = self._sum.reshape((-1,) + self._sum.shape[len(self.grid):])
            flat_sumsq = self._sumsq.reshape(flat_sum.shape)
            np.add.at(flat_sum, cells, magnitude)
            np.add.at(flat_sumsq, cells, magnitude ** 2)
            np.add.at(self._counts.reshape(-1), cells, 1)

    def to_model(self, *, source: str = "", measured: str | None = None) -> NoiseModel:
        """The noise model from what has been accumulated so far (empty cells have count 0)."""
        n = self._counts[..., None, None].astype(np.float64)
        mean = np.divide(self._sum, n, out=np.zeros_like(self._sum), where=n > 0)
        var = np.divide(self._sumsq - n * mean ** 2, n - 1, out=np.zeros_like(self._sum), where=n > 1)
        std = np.sqrt(np.maximum(var, 0.0))
        return NoiseModel(grid=self.grid, joint_names=self.joint_names, mean=mean, std=std,
                          counts=self._counts.copy(), sample_rate_hz=self.settings.sample_rate_hz,
                          block_length=self.settings.block_length, hop=self.settings.hop, window=self.window,
                          band_hz=self.settings.band_hz, band_order=self.settings.band_order,
                          channels=MODEL_CHANNELS, measured=measured or self.sweep,
                          provenance={"source": source, "software_version": __version__})

    @classmethod
    def from_model(cls, model: NoiseModel, **options) -> "CalibrationAccumulator":
        """Resume from a checkpoint: the model's cells become the accumulated statistics."""
        acc = cls(grid=model.grid, joint_names=model.joint_names, sample_rate_hz=model.sample_rate_hz,
                  block_length=model.block_length, hop=model.hop, band_hz=model.band_hz,
                  band_order=model.band_order, sweep=model.measured, **options)
        n = model.counts[..., None, None].astype(np.float64)
        acc._counts = model.counts.copy()
        acc._sum = model.mean * n
        acc._sumsq = model.std ** 2 * np.maximum(n - 1, 0) + n * model.mean ** 2
        return acc


def calibrate_arrays(accel_stamps_ns: np.ndarray, accel: np.ndarray, joint_stamps_ns: np.ndarray,
                     joint_velocity: np.ndarray, *, chunk_s: float = 10.0, source: str = "",
                     progress=None, **options) -> tuple[NoiseModel, dict]:
    """Calibrate from whole arrays in one pass, `chunk_s` seconds at a time (bounded memory).

    `progress`, if given, is called with the number of accelerometer samples consumed."""
    acc = CalibrationAccumulator(source=source, **options)
    accel_stamps_ns = np.asarray(accel_stamps_ns, dtype=np.int64)
    joint_stamps_ns = np.asarray(joint_stamps_ns, dtype=np.int64)
    step = max(1, int(chunk_s * acc.settings.sample_rate_hz))
    joint_pos = 0
    for start in range(0, len(accel_stamps_ns), step):
        stop = min(start + step, len(accel_stamps_ns))
        # Joint states first, up to a little past the chunk, so no block waits.
        horizon = accel_stamps_ns[stop - 1] + int(1e9 * acc.settings.joint_wait_s) + 1
        joint_stop = int(np.searchsorted(joint_stamps_ns, horizon, side="right")) if stop < len(accel_stamps_ns) \
            else len(joint_stamps_ns)
        if joint_stop > joint_pos:
            acc.push_joint_states(joint_stamps_ns[joint_pos:joint_stop], joint_velocity[joint_pos:joint_stop])
            joint_pos = joint_stop
        acc.push_accel(accel_stamps_ns[start:stop], accel[start:stop])
        if progress is not None:
            progress(stop - start)
    acc.flush()
    return acc.to_model(source=source), acc.stats
