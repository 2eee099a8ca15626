"""One-pass calibration of the noise model (paper section 3, "PR2 Ego-vibration Estimation").

Blocks are framed as in denoising, assigned to the velocity cell of their mean joint
velocity and summed per cell (magnitudes and their squares: constant memory; only cells
that receive blocks are stored, so 1 to 8 joints work). Two tallies side by side: a sweep
(the paper: the robot dwells on grid velocities; a block counts when steady and within
CELL_TOLERANCE grid steps of a grid point) and free motion (any steady block counts for
its nearest cell). `sweep="auto"` takes the sweep's when most usable blocks sat on grid
points (AUTO_SWEEP_SHARE), else free motion's, and says which in `stats.mode`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from egovib_ros import __version__
from egovib_ros.core.filters import CHANNEL_LAYOUTS
from egovib_ros.core.noise_model import MODEL_CHANNELS, NoiseModel, sweep_cells
from egovib_ros.core.stream import BlockFramer, Blocks, CalibrationStats, FramerSettings, feed
from egovib_ros.core.velocity import MATCHED
from egovib_ros.errors import ConfigError
from egovib_ros.robot import RobotProfile, default_profile

SWEEPS = ("auto", "full", "superposition", "free")
#: In "auto", the share of usable blocks that must sit on grid points to call it a sweep.
AUTO_SWEEP_SHARE = 0.7
#: ... and a superposition sweep if at most this share of them has two joints or more moving
#: (a few blocks of one joint settling while the next one starts; the simulated 3-joint arm's
#: superposition sweep: 22 of 2641, which made it a "full" sweep of 39 cells, 8 of them from
#: 2-3 blocks, and every cell Eq. 6 fills "outside the calibration"). They are left out.
AUTO_STRAY_SHARE = 0.05
#: A block with at most this many gap-filled samples inside it (both ends real) is used.
MAX_BRIDGED_SAMPLES = 2
#: A sweep's block counts within this many grid steps of a grid point, its velocity steady
#: within STEADY_TOLERANCE steps (first half against second); free motion's within
#: FREE_STEADY_TOLERANCE (settling and gripper reversals are rejected).
CELL_TOLERANCE = 0.3
STEADY_TOLERANCE = 0.3
FREE_STEADY_TOLERANCE = 0.5


class _Tally:
    """Sparse per-cell sums of magnitude and squared magnitude (rows grow as cells appear)."""

    def __init__(self, n_joints: int, n_channels: int, n_bins: int):
        self.row_of: dict[int, int] = {}
        self.cells = np.zeros((0, n_joints), dtype=np.int64)
        self.sum = np.zeros((16, n_channels, n_bins))
        self.sumsq = np.zeros_like(self.sum)
        self.counts = np.zeros(16, dtype=np.int64)
        self.rejected = {
            "partial": 0,
            "no_joint_state": 0,
            "unsteady": 0,
            "off_grid": 0,
            "not_in_sweep": 0,
        }

    @property
    def n(self) -> int:
        return len(self.row_of)

    def rows(self, ids: np.ndarray, cells: np.ndarray) -> np.ndarray:
        out = np.empty(len(ids), dtype=np.int64)
        for k, cell_id in enumerate(ids.tolist()):
            row = self.row_of.get(cell_id)
            if row is None:
                row = self.row_of[cell_id] = len(self.row_of)
                if row >= len(self.counts):
                    grow = len(self.counts)
                    self.sum = np.concatenate([self.sum, np.zeros_like(self.sum[:grow])])
                    self.sumsq = np.concatenate([self.sumsq, np.zeros_like(self.sumsq[:grow])])
                    self.counts = np.concatenate([self.counts, np.zeros(grow, dtype=np.int64)])
                self.cells = np.concatenate([self.cells, cells[k : k + 1]])
            out[k] = row
        return out

    def add(self, ids: np.ndarray, cells: np.ndarray, magnitude: np.ndarray) -> None:
        unique, first, inverse = np.unique(ids, return_index=True, return_inverse=True)
        rows = self.rows(unique, cells[first])[inverse]
        np.add.at(self.sum, rows, magnitude)
        np.add.at(self.sumsq, rows, magnitude**2)
        np.add.at(self.counts, rows, 1)

    def only(self, keep: np.ndarray, reason: str) -> "_Tally":
        """A copy with the rows `keep` (n,) only; the blocks of the others counted as
        rejected for `reason`."""
        out = _Tally(self.cells.shape[1], self.sum.shape[1], self.sum.shape[2])
        rows = np.flatnonzero(keep)
        out.cells, out.sum, out.sumsq = self.cells[rows], self.sum[rows], self.sumsq[rows]
        out.counts = self.counts[rows]
        out.row_of = {cell_id: k for k, cell_id in enumerate(np.array(list(self.row_of))[rows])}
        out.rejected = dict(self.rejected)
        out.rejected[reason] += int(self.counts[: self.n][~keep].sum())
        return out

    def statistics(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        k = self.n
        n = self.counts[:k, None, None].astype(np.float64)
        mean = self.sum[:k] / np.maximum(n, 1)
        var = np.divide(self.sumsq[:k] - n * mean**2, n - 1, out=np.zeros_like(mean), where=n > 1)
        return self.cells.copy(), mean, np.sqrt(np.maximum(var, 0.0)), self.counts[:k].copy()


class CalibrationAccumulator:
    """Per-cell magnitude statistics from streamed joint states and sensor samples. The
    robot profile (default: the PR2 hand) gives the grid, joints, rate and blocking; the
    other settings override it (tests, other block lengths)."""

    def __init__(
        self,
        *,
        profile: RobotProfile | None = None,
        sweep: str = "full",
        grid: tuple[np.ndarray, ...] | None = None,
        joint_names: tuple[str, ...] | None = None,
        sample_rate_hz: float | None = None,
        block_length: int | None = None,
        hop: int | None = None,
        band_hz: tuple[float, float] | None = None,
        band_order: int | None = None,
        joint_wait_s: float = 0.02,
        prefiltered: bool = False,
        joint_lag_s: float = 0.0,
        source: str = "",
    ):
        if sweep not in SWEEPS:
            raise ConfigError(f"grid: expected one of {SWEEPS}, got {sweep!r}")
        base = profile if profile is not None else default_profile()
        overrides = (grid, joint_names, sample_rate_hz, block_length, hop, band_hz, band_order)
        # The model carries the profile only when nothing was overridden.
        self.profile = base if all(v is None for v in overrides) else None
        self.grid = tuple(
            np.asarray(g, dtype=np.float64) for g in (grid if grid is not None else base.grid())
        )
        self.joint_names = tuple(
            joint_names
            if joint_names is not None
            else (
                base.joint_names if grid is None else [f"joint{j}" for j in range(len(self.grid))]
            )
        )
        if len(self.joint_names) != len(self.grid):
            raise ConfigError(f"{len(self.joint_names)} joint names for {len(self.grid)} grid axes")
        self.sweep = sweep
        self.settings = FramerSettings(
            sample_rate_hz=sample_rate_hz or base.rate_hz,
            block_length=block_length or base.block_length,
            hop=hop or base.hop,
            band_hz=band_hz or base.band_hz,
            band_order=band_order or base.band_order,
            layout="all",
            sensor_range=base.sensor_range,
            stamps=base.sensor_stamps,
            joint_wait_s=joint_wait_s,
            prefiltered=prefiltered,
            joint_lag_s=joint_lag_s,
            source=source,
        )
        self._framer = BlockFramer(self.settings, len(self.grid))
        self._retired: list = []  # FramerStats of framers before a restart_stream
        self.window = self._framer.window
        n_bins = self.settings.block_length // 2 + 1
        self._sweep_tally = _Tally(len(self.grid), len(MODEL_CHANNELS), n_bins)
        self._free_tally = _Tally(len(self.grid), len(MODEL_CHANNELS), n_bins)
        self._spacing = [
            np.minimum(np.diff(g, prepend=-np.inf), np.diff(g, append=np.inf)) for g in self.grid
        ]
        self._shape = tuple(len(g) for g in self.grid)
        self._zero = np.array([int(np.argmin(np.abs(g))) for g in self.grid])
        assert CHANNEL_LAYOUTS["all"] == MODEL_CHANNELS

    @property
    def grid_shape(self) -> tuple[int, ...]:
        return self._shape

    @property
    def mode(self) -> str:
        """Which tally the model comes from: a sweep ("full"/"superposition") or "free"."""
        if self.sweep in ("full", "superposition", "free"):
            return self.sweep
        sweep_blocks = int(self._sweep_tally.counts.sum())
        free_blocks = int(self._free_tally.counts.sum())
        if free_blocks and sweep_blocks >= AUTO_SWEEP_SHARE * free_blocks:
            several = self._several_moving()
            stray = int(self._sweep_tally.counts[: self._sweep_tally.n][several].sum())
            return "superposition" if stray <= AUTO_STRAY_SHARE * sweep_blocks else "full"
        return "free"

    def _several_moving(self) -> np.ndarray:
        """(n,) whether two joints or more move in each cell of the sweep's tally."""
        return (self._sweep_tally.cells != self._zero).sum(axis=1) > 1

    def _tally(self) -> _Tally:
        """The tally the model comes from (in "auto" taken for a superposition sweep: without
        its few cells where several joints moved)."""
        mode = self.mode
        if mode == "free":
            return self._free_tally
        if mode == "superposition" and self.sweep == "auto":
            return self._sweep_tally.only(~self._several_moving(), "not_in_sweep")
        return self._sweep_tally

    def expected_cell_list(self) -> np.ndarray:
        """Grid indices (K, J) of the cells this sweep should visit."""
        return sweep_cells(self.grid, "full" if self.mode == "free" else self.mode)

    def cell_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """(grid indices (K, J), block counts (K,)) of the cells measured so far."""
        cells, _, _, counts = self._tally().statistics()
        return cells, counts

    def restart_stream(self) -> None:
        """The stream was refused for its rate (RateError) and runs at the model's rate
        again: framing starts afresh, as on a new stream; the statistics gathered and the
        counts so far are kept."""
        self._retired.append(self._framer.stats)
        self._framer = BlockFramer(self.settings, len(self.grid))

    @property
    def stats(self) -> CalibrationStats:
        tally = self._tally()
        counts = self._framer.stats
        if self._retired:  # summed over the framers of the stream's restarts
            counts = dataclasses.replace(
                counts,
                **{
                    f.name: sum(getattr(c, f.name) for c in (*self._retired, counts))
                    for f in dataclasses.fields(counts)
                    if f.name != "receipt_latency_ns"
                },
            )
        return CalibrationStats.of(
            counts,
            mode=self.mode,
            blocks_used=int(tally.counts.sum()),
            cells=tally.n,
            rejected=dict(tally.rejected),
        )

    @property
    def backlog(self) -> tuple[int, int]:
        """(samples buffered, joint states held) by the framer."""
        return self._framer.backlog

    @property
    def sensor_stamps(self) -> str:
        """What the sensor stamps mark: "sample", "receipt" (core.receipt), or "" while the
        first samples still wait to tell."""
        return self._framer.stamps

    def push_joint_states(self, stamps_ns: np.ndarray, velocity: np.ndarray) -> None:
        self._framer.push_joint_states(stamps_ns, velocity)
        self._accumulate(self._framer.pop_blocks())

    def push_sensor(self, stamps_ns: np.ndarray, accel: np.ndarray) -> None:
        self._framer.push_sensor(stamps_ns, accel)
        self._accumulate(self._framer.pop_blocks())

    def flush(self) -> None:
        self._framer.flush()
        self._accumulate(self._framer.pop_blocks())

    def cell_of(self, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest cell index per joint (B, J) and the distance to it in grid steps (B, J)."""
        velocity = np.atleast_2d(velocity)
        index = np.empty(velocity.shape, dtype=np.intp)
        distance = np.empty(velocity.shape)
        for j, g in enumerate(self.grid):
            i = np.abs(velocity[:, j, None] - g[None, :]).argmin(axis=1)
            index[:, j] = i
            distance[:, j] = np.abs(velocity[:, j] - g[i]) / self._spacing[j][i]
        return index, distance

    def _accumulate(self, batches: list[Blocks]) -> None:
        for blocks in batches:
            if blocks.n == 0:
                continue
            # Blocks holding start/end padding or runs of gap fill would bias the statistics;
            # a sample or two bridged inside a block (a bad sample now and then) does not,
            # and rejecting those left no block of a stream with 1.6 % NaN samples.
            complete = blocks.complete | (blocks.bridged <= MAX_BRIDGED_SAMPLES)
            usable = complete & (blocks.status == MATCHED)
            velocity = np.where(usable[:, None], blocks.velocity, 0.0)
            index, distance = self.cell_of(velocity)
            spacing = np.column_stack([s[index[:, j]] for j, s in enumerate(self._spacing)])
            steadiness = np.nan_to_num(blocks.steadiness, nan=np.inf) / spacing
            # Beyond the grid edge by more than half a step: not this grid's velocity.
            inside = np.all(distance <= 0.5, axis=1)
            accepted = []
            for tally, steady_tol, cell_tol in (
                (self._sweep_tally, STEADY_TOLERANCE, CELL_TOLERANCE),
                (self._free_tally, FREE_STEADY_TOLERANCE, None),
            ):
                tally.rejected["partial"] += int((~complete).sum())
                tally.rejected["no_joint_state"] += int(
                    (complete & (blocks.status != MATCHED)).sum()
                )
                steady = np.all(steadiness <= steady_tol, axis=1)
                near = np.all(distance <= cell_tol, axis=1) if cell_tol is not None else inside
                tally.rejected["unsteady"] += int((usable & ~steady).sum())
                tally.rejected["off_grid"] += int((usable & steady & ~near).sum())
                accept = usable & steady & near
                if tally is self._sweep_tally and self.sweep == "superposition":
                    in_sweep = (index != self._zero).sum(axis=1) <= 1
                    tally.rejected["not_in_sweep"] += int((accept & ~in_sweep).sum())
                    accept &= in_sweep
                accepted.append(accept)
            union = accepted[0] | accepted[1]
            if not union.any():
                continue
            magnitude = np.zeros((blocks.n,) + self._sweep_tally.sum.shape[1:])
            # (b, C, F)
            magnitude[union] = np.abs(np.fft.rfft(blocks.samples[union] * self.window, axis=-1))
            ids = np.ravel_multi_index(tuple(index.T), self._shape)
            for tally, accept in zip((self._sweep_tally, self._free_tally), accepted):
                if accept.any():
                    tally.add(ids[accept], index[accept], magnitude[accept])

    def merge(self, other: "CalibrationAccumulator") -> None:
        """Pool another accumulator's per-cell sums and counts into this one (several bags of
        one robot: each was framed and flushed on its own, only the statistics are pooled).
        Both tallies are pooled, so "auto" decides on the pooled data."""
        if (
            other.grid_shape != self.grid_shape
            or other.joint_names != self.joint_names
            or other.settings.block_length != self.settings.block_length
        ):
            raise ConfigError(
                f"calibration: cannot pool {other.joint_names} {other.grid_shape} into "
                f"{self.joint_names} {self.grid_shape}"
            )
        for mine, theirs in (
            (self._sweep_tally, other._sweep_tally),
            (self._free_tally, other._free_tally),
        ):
            k = theirs.n
            if k:
                rows = mine.rows(
                    np.ravel_multi_index(tuple(theirs.cells.T), self._shape), theirs.cells
                )
                np.add.at(mine.sum, rows, theirs.sum[:k])
                np.add.at(mine.sumsq, rows, theirs.sumsq[:k])
                np.add.at(mine.counts, rows, theirs.counts[:k])
            for key, value in theirs.rejected.items():
                mine.rejected[key] = mine.rejected.get(key, 0) + value
        for key, value in vars(other._framer.stats).items():
            if isinstance(value, int):
                setattr(self._framer.stats, key, getattr(self._framer.stats, key) + value)

    def to_model(self, *, source: str = "", measured: str | None = None) -> NoiseModel:
        """The noise model from what has been accumulated so far (only measured cells)."""
        cells, mean, std, counts = self._tally().statistics()
        s = self.settings
        return NoiseModel(
            grid=self.grid,
            joint_names=self.joint_names,
            cells=cells,
            mean=mean,
            std=std,
            counts=counts,
            sample_rate_hz=s.sample_rate_hz,
            block_length=s.block_length,
            hop=s.hop,
            window=self.window,
            band_hz=s.band_hz,
            band_order=s.band_order,
            channels=MODEL_CHANNELS,
            measured=measured or self.mode,
            profile=self.profile,
            provenance={"source": source, "software_version": __version__},
        )

    @classmethod
    def from_model(cls, model: NoiseModel, **options) -> "CalibrationAccumulator":
        """Resume from a checkpoint: the model's cells become the accumulated statistics."""
        if model.profile is not None and "profile" not in options:
            acc = cls(profile=model.profile, sweep=model.measured, **options)
        else:
            acc = cls(
                grid=model.grid,
                joint_names=model.joint_names,
                sample_rate_hz=model.sample_rate_hz,
                block_length=model.block_length,
                hop=model.hop,
                band_hz=model.band_hz,
                band_order=model.band_order,
                sweep=model.measured,
                **options,
            )
        cells, counts = model.cells_measured()
        if len(cells):
            n = counts[:, None, None].astype(np.float64)
            tally = acc._free_tally if acc.mode == "free" else acc._sweep_tally  # (written)
            rows = tally.rows(np.ravel_multi_index(tuple(cells.T), acc._shape), cells)
            tally.counts[rows] = counts
            tally.sum[rows] = model.cell_mean * n
            tally.sumsq[rows] = model.cell_std**2 * np.maximum(n - 1, 0) + n * model.cell_mean**2
        return acc


def calibrate_arrays(
    sensor_stamps_ns: np.ndarray,
    accel: np.ndarray,
    joint_stamps_ns: np.ndarray,
    joint_velocity: np.ndarray,
    *,
    chunk_s: float = 10.0,
    source: str = "",
    progress=None,
    **options,
) -> tuple[NoiseModel, CalibrationStats]:
    """Calibrate from whole arrays in one pass, `chunk_s` seconds at a time (bounded memory);
    `options` go to CalibrationAccumulator, `progress(n)`: samples consumed."""
    acc = CalibrationAccumulator(source=source, **options)
    streams = (sensor_stamps_ns, accel, joint_stamps_ns, joint_velocity)
    rates = dict(sample_rate_hz=acc.settings.sample_rate_hz, joint_wait_s=acc.settings.joint_wait_s)
    feed(acc, *streams, chunk_s=chunk_s, progress=progress, **rates)
    acc.flush()
    return acc.to_model(source=source), acc.stats
