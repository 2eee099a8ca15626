"""The ego-vibration noise model: per velocity cell mean and std magnitude spectra.

Paper Eq. 5: |N(f, v)| = mu_N(f, v) + sd_N(f, v).
Paper Eq. 6 (superposition from cells where at most one joint moves), for J joints:
    mu  = sum_j mu(v_j on axis j) - (J - 1) mu(0)
    sd  = sqrt(sum_j sd(v_j on axis j)^2 + (J - 1) sd(0)^2)
which for J = 2 is exactly the paper's equation, including its + sd(0, 0)^2 term (so
at an on-axis cell Eq. 6 gives sqrt(sd^2 + sd0^2), and at (0, 0) sqrt(3) sd0, not the
measured sd: the paper's over-subtraction), and for J = 1 returns the measured table.
Between grid points the estimate is interpolated multilinearly (bilinear for 2 joints);
outside the grid it is clamped to the edge and the block is counted as out of grid.
"""
from __future__ import annotations

import datetime as _dt
import itertools
import math
import logging
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from egovib_ros import __version__
from egovib_ros.core.blocks import WINDOW_NAME, n_bins, validate_blocking
from egovib_ros.errors import ConfigError, ModelFileError

LOG = logging.getLogger("egovib_ros.core")

SCHEMA = "egovib.noise_model"
SCHEMA_VERSION = 1
MODEL_CHANNELS = ("combined", "x", "y", "z")
MEASURED_KINDS = ("full", "superposition")


@dataclass
class NoiseModel:
    """Per-cell noise statistics; see the module docstring for the estimate."""

    grid: tuple[np.ndarray, ...]          # grid velocities of each joint (joint units)
    joint_names: tuple[str, ...]
    mean: np.ndarray                      # grid_shape + (C, F), magnitude of rfft(window * block)
    std: np.ndarray                       # same shape
    counts: np.ndarray                    # grid_shape, blocks per cell
    sample_rate_hz: float = 3000.0
    block_length: int = 64
    hop: int = 32
    window: np.ndarray = field(default_factory=lambda: np.zeros(0))
    window_name: str = WINDOW_NAME
    band_hz: tuple[float, float] = (150.0, 750.0)
    band_order: int = 4
    channels: tuple[str, ...] = MODEL_CHANNELS
    measured: str = "full"                # which sweep filled the table
    provenance: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.grid = tuple(np.asarray(g, dtype=np.float64) for g in self.grid)
        self.joint_names = tuple(str(n) for n in self.joint_names)
        self.channels = tuple(str(c) for c in self.channels)
        self.mean = np.asarray(self.mean, dtype=np.float64)
        self.std = np.asarray(self.std, dtype=np.float64)
        self.counts = np.asarray(self.counts, dtype=np.int64)
        self.window = np.asarray(self.window, dtype=np.float64)
        self.band_hz = (float(self.band_hz[0]), float(self.band_hz[1]))
        self._table: np.ndarray | None = None
        self._table_mean: np.ndarray | None = None
        self._filled: np.ndarray | None = None
        self._subtables: dict = {}
        self.validate()
        self._positions = [np.arange(len(g), dtype=np.float64) for g in self.grid]
        self._bounds = [(float(g[0]), float(g[-1])) for g in self.grid]
        # Grid step per joint if the grid is uniform (to the last bit of the step), else 0.
        self._steps = []
        for g in self.grid:
            step = (g[-1] - g[0]) / (len(g) - 1)
            self._steps.append(float(step) if np.allclose(np.diff(g), step, rtol=1e-12, atol=0) else 0.0)

    # --- shape facts -------------------------------------------------------
    @property
    def grid_shape(self) -> tuple[int, ...]:
        return tuple(len(g) for g in self.grid)

    @property
    def n_joints(self) -> int:
        return len(self.grid)

    @property
    def freqs_hz(self) -> np.ndarray:
        return np.fft.rfftfreq(self.block_length, 1.0 / self.sample_rate_hz)

    def zero_index(self) -> tuple[int, ...]:
        """Grid index of the all-stationary cell."""
        return tuple(int(np.argmin(np.abs(g))) for g in self.grid)

    def validate(self) -> None:
        where = self.provenance.get("path", "noise model")
        shape = self.grid_shape + (len(self.channels), n_bins(self.block_length))
        if len(self.joint_names) != self.n_joints:
            raise ModelFileError(f"{where}: {len(self.joint_names)} joint names for {self.n_joints} grid axes")
        for name, arr in (("mean", self.mean), ("std", self.std)):
            if arr.shape != shape:
                raise ModelFileError(f"{where}: '{name}' has shape {arr.shape}, expected {shape}")
            if not np.all(np.isfinite(arr)) or np.any(arr < 0):
                raise ModelFileError(f"{where}: '{name}' holds negative or non-finite values")
        if self.counts.shape != self.grid_shape or np.any(self.counts < 0):
            raise ModelFileError(f"{where}: 'counts' has shape {self.counts.shape}, expected {self.grid_shape}")
        for j, g in enumerate(self.grid):
            if g.ndim != 1 or len(g) < 2 or not np.all(np.isfinite(g)) or np.any(np.diff(g) <= 0):
                raise ModelFileError(f"{where}: grid of joint {j} must be finite and increasing with >= 2 values")
        if not (np.isfinite(self.sample_rate_hz) and self.sample_rate_hz > 0):
            raise ModelFileError(f"{where}: sample rate must be a positive number, got {self.sample_rate_hz}")
        try:
            validate_blocking(self.block_length, self.hop)
        except ConfigError as exc:
            raise ModelFileError(f"{where}: {exc}") from None
        if not (np.all(np.isfinite(self.band_hz)) and 0 < self.band_hz[0] < self.band_hz[1] < self.sample_rate_hz / 2):
            raise ModelFileError(f"{where}: band {self.band_hz} Hz does not fit the sample rate {self.sample_rate_hz:g} Hz")
        if self.window.shape != (self.block_length,):
            raise ModelFileError(f"{where}: window has {self.window.size} samples, block_length is {self.block_length}")
        if self.measured not in MEASURED_KINDS:
            raise ModelFileError(f"{where}: measured must be one of {MEASURED_KINDS}, got {self.measured!r}")

    def channel_indices(self, names: tuple[str, ...]) -> list[int]:
        missing = [n for n in names if n not in self.channels]
        if missing:
            raise ModelFileError(f"{self.provenance.get('path', 'noise model')}: no channel(s) {missing}; "
                                 f"the model has {list(self.channels)}")
        return [self.channels.index(n) for n in names]

    # --- Eq. 5 / Eq. 6 tables ---------------------------------------------
    def axis_mask(self) -> np.ndarray:
        """Cells where at most one joint moves (the 41-cell superposition sweep)."""
        return sweep_mask(self.grid, "superposition")

    def superposed(self) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 6 mean and std for every cell, from the single-joint cells only."""
        zero = self.zero_index()
        mu0, sd0 = self.mean[zero], self.std[zero]
        mu = np.zeros_like(self.mean) - (self.n_joints - 1) * mu0
        var = np.zeros_like(self.std) + (self.n_joints - 1) * sd0 ** 2
        for j in range(self.n_joints):
            index = list(zero)
            index[j] = slice(None)
            mu_axis = self.mean[tuple(index)]          # (n_j, C, F)
            sd_axis = self.std[tuple(index)]
            expand = [np.newaxis] * self.n_joints
            expand[j] = slice(None)
            mu = mu + mu_axis[tuple(expand)]
            var = var + sd_axis[tuple(expand)] ** 2
        return np.maximum(mu, 0.0), np.sqrt(var)

    def _build_tables(self) -> None:
        have = self.counts > 0
        if self.measured == "superposition":
            mu, sd = self.superposed()
            axis = self.axis_mask()
            if not np.all(have[axis]):
                LOG.warning("noise model: %d of %d single-joint cells are empty; filled from the nearest cell",
                            int(np.sum(~have[axis])), int(axis.sum()))
                mu, sd = self._superposed_with_fill(have)
            filled = ~have
        else:
            mu, sd = self.mean.copy(), self.std.copy()
            filled = ~have
            if not have.any():
                raise ModelFileError(f"{self.provenance.get('path', 'noise model')}: no measured cell at all")
            if filled.any():
                LOG.warning("noise model: %d of %d cells are empty; filled by superposition (Eq. 6) "
                            "where its single-joint cells exist, else from the nearest measured cell",
                            int(filled.sum()), filled.size)
                axis_ok = np.all(have[self.axis_mask()])
                if axis_ok:
                    smu, ssd = self.superposed()
                else:
                    smu, ssd = _nearest_fill(self.mean, have), _nearest_fill(self.std, have)
                mu[filled], sd[filled] = smu[filled], ssd[filled]
        self._table_mean = mu
        self._table = mu + sd
        self._filled = filled

    def _superposed_with_fill(self, have: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        axis = self.axis_mask()
        usable = have & axis
        if not usable.any():
            raise ModelFileError(f"{self.provenance.get('path', 'noise model')}: no measured cell at all")
        filled_model = NoiseModel(**{**self.__dict_for_copy__(),
                                     "mean": _nearest_fill(self.mean, usable),
                                     "std": _nearest_fill(self.std, usable)})
        return filled_model.superposed()

    def __dict_for_copy__(self) -> dict:
        return dict(grid=self.grid, joint_names=self.joint_names, mean=self.mean, std=self.std,
                    counts=self.counts, sample_rate_hz=self.sample_rate_hz, block_length=self.block_length,
                    hop=self.hop, window=self.window, window_name=self.window_name, band_hz=self.band_hz,
                    band_order=self.band_order, channels=self.channels, measured=self.measured,
                    provenance=dict(self.provenance))

    def estimate_table(self, *, include_std: bool = True) -> np.ndarray:
        """grid_shape + (C, F): the noise magnitude used at each grid point (Eq. 5 or Eq. 6)."""
        if self._table is None:
            self._build_tables()
        return self._table if include_std else self._table_mean

    @property
    def filled_cells(self) -> np.ndarray:
        if self._filled is None:
            self._build_tables()
        return self._filled

    def estimate(self, velocity: np.ndarray, channel_index: list[int] | slice = slice(None), *,
                 include_std: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Noise magnitude spectra at velocities (B, J) -> ((B, C, F), out_of_grid (B,))."""
        if not (isinstance(velocity, np.ndarray) and velocity.ndim == 2 and velocity.dtype == np.float64):
            velocity = np.atleast_2d(np.asarray(velocity, dtype=np.float64))
        key = (tuple(channel_index) if isinstance(channel_index, list) else str(channel_index), include_std)
        table = self._subtables.get(key)
        if table is None:
            table = np.ascontiguousarray(self.estimate_table(include_std=include_std)[..., channel_index, :])
            self._subtables[key] = table
        n_blocks = velocity.shape[0]
        if n_blocks == 1:
            return self._estimate_one(velocity[0], table)
        lower, frac = [], []
        outside = np.zeros(n_blocks, dtype=bool)
        for j, g in enumerate(self.grid):
            v = velocity[:, j]
            outside |= (v < g[0] - 1e-9 * abs(g[0])) | (v > g[-1] + 1e-9 * abs(g[-1]))
            step = self._steps[j]
            if step:   # uniform grid: plain arithmetic (the one-block path does the same on floats)
                position = np.minimum(np.maximum((v - g[0]) / step, 0.0), len(g) - 1.0)
            else:
                position = np.interp(v, g, self._positions[j])
            i0 = np.minimum(np.floor(position).astype(np.intp), len(g) - 2)
            lower.append(i0)
            frac.append(position - i0)
        out = np.zeros((n_blocks,) + table.shape[self.n_joints:])
        for corner in itertools.product((0, 1), repeat=self.n_joints):
            weight = np.ones(n_blocks)
            index = []
            for j, c in enumerate(corner):
                weight = weight * (frac[j] if c else 1.0 - frac[j])
                index.append(lower[j] + c)
            out += weight[:, None, None] * table[tuple(index)]
        return out, outside

    def _estimate_one(self, velocity: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`estimate` for a single block (the streaming case): the same operations in the
        same order on Python floats and array views, so the result is bit-identical."""
        lower, frac = [], []
        outside = False
        for j, (low, high) in enumerate(self._bounds):
            v = float(velocity[j])
            outside = outside or v < low - 1e-9 * abs(low) or v > high + 1e-9 * abs(high)
            step = self._steps[j]
            n = len(self.grid[j])
            if step:
                position = min(max((v - low) / step, 0.0), n - 1.0)
            else:
                position = float(np.interp(v, self.grid[j], self._positions[j]))
            i0 = min(int(math.floor(position)), n - 2)
            lower.append(i0)
            frac.append(position - i0)
        if self.n_joints == 2:
            # Spelled out: same weights, same products, same left-to-right sum as below.
            (i, j), (a, b) = lower, frac
            out = ((1.0 - a) * (1.0 - b)) * table[i, j] + ((1.0 - a) * b) * table[i, j + 1] \
                + (a * (1.0 - b)) * table[i + 1, j] + (a * b) * table[i + 1, j + 1]
            return out[None], np.array([outside])
        out = None
        for corner in itertools.product((0, 1), repeat=self.n_joints):
            weight = 1.0
            for j, c in enumerate(corner):
                weight = weight * (frac[j] if c else 1.0 - frac[j])
            term = weight * table[tuple(lower[j] + c for j, c in enumerate(corner))]
            out = term if out is None else out + term
        return out[None], np.array([outside])

    # --- file I/O (CONTRACT section 4) --------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Write the .npz (loadable with allow_pickle=False). Use atomic_output for safety."""
        provenance = {"source": "", "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                      "software_version": __version__, **{k: v for k, v in self.provenance.items() if k != "path"}}
        arrays = {
            "schema": np.array(SCHEMA), "schema_version": np.array(SCHEMA_VERSION),
            "sample_rate_hz": np.array(self.sample_rate_hz), "block_length": np.array(self.block_length),
            "hop": np.array(self.hop), "window": self.window, "window_name": np.array(self.window_name),
            "band_hz": np.array(self.band_hz), "band_order": np.array(self.band_order),
            "joint_names": np.array(self.joint_names), "channels": np.array(self.channels),
            "n_joints": np.array(self.n_joints), "mean": self.mean, "std": self.std, "counts": self.counts,
            "measured": np.array(self.measured),
            "provenance_keys": np.array(list(provenance.keys())),
            "provenance_values": np.array([str(v) for v in provenance.values()]),
        }
        for j, g in enumerate(self.grid):
            arrays[f"grid_{j}"] = g
        with open(path, "wb") as fh:
            np.savez_compressed(fh, **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "NoiseModel":
        where = str(path)
        if not Path(path).is_file():
            raise ModelFileError(f"{where}: no such noise-model file")
        try:
            with np.load(path, allow_pickle=False) as data:
                fields = {k: data[k] for k in data.files}
        except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
            raise ModelFileError(f"{where}: not a readable noise-model .npz ({exc.__class__.__name__}: {exc})") from None
        if str(fields.get("schema", "")) != SCHEMA:
            raise ModelFileError(f"{where}: not an egovib noise model (schema {str(fields.get('schema', 'missing'))!r})")
        version = int(fields.get("schema_version", -1))
        if version > SCHEMA_VERSION:
            raise ModelFileError(f"{where}: model schema version {version} is newer than this software "
                                 f"supports ({SCHEMA_VERSION}); upgrade egovib_ros")
        if version < 1:
            raise ModelFileError(f"{where}: invalid schema version {version}")
        required = ("sample_rate_hz", "block_length", "hop", "window", "window_name", "band_hz", "band_order",
                    "joint_names", "channels", "n_joints", "mean", "std", "counts", "measured")
        missing = [k for k in required if k not in fields]
        if missing:
            raise ModelFileError(f"{where}: missing field(s) {missing}")
        try:
            n_joints = int(fields["n_joints"])
        except (TypeError, ValueError):
            raise ModelFileError(f"{where}: malformed field 'n_joints'") from None
        grid_keys = [f"grid_{j}" for j in range(n_joints)]
        if any(k not in fields for k in grid_keys):
            raise ModelFileError(f"{where}: missing grid arrays for {n_joints} joints")
        try:
            return cls._from_fields(fields, grid_keys, where)
        except ModelFileError:
            raise
        except (TypeError, ValueError, IndexError, KeyError) as exc:
            raise ModelFileError(f"{where}: malformed field ({exc.__class__.__name__}: {exc})") from None

    @classmethod
    def _from_fields(cls, fields: dict, grid_keys: list[str], where: str) -> "NoiseModel":
        provenance = dict(zip([str(k) for k in fields.get("provenance_keys", [])],
                              [str(v) for v in fields.get("provenance_values", [])]))
        provenance["path"] = where
        return cls(grid=tuple(fields[k] for k in grid_keys),
                   joint_names=tuple(str(n) for n in fields["joint_names"]),
                   mean=fields["mean"], std=fields["std"], counts=fields["counts"],
                   sample_rate_hz=float(fields["sample_rate_hz"]), block_length=int(fields["block_length"]),
                   hop=int(fields["hop"]), window=fields["window"], window_name=str(fields["window_name"]),
                   band_hz=tuple(float(b) for b in fields["band_hz"]), band_order=int(fields["band_order"]),
                   channels=tuple(str(c) for c in fields["channels"]), measured=str(fields["measured"]),
                   provenance=provenance)

    def summary(self) -> str:
        measured = int(np.sum(self.counts > 0))
        return (f"noise model: {self.n_joints} joints {self.grid_shape} grid ({self.measured} sweep), "
                f"{measured}/{self.counts.size} cells measured, {int(self.counts.sum())} blocks, "
                f"{self.sample_rate_hz:g} Hz, L={self.block_length}, hop={self.hop}")


def sweep_mask(grid: tuple[np.ndarray, ...], sweep: str) -> np.ndarray:
    """Grid-shaped mask of the cells a sweep visits: all of them ("full") or those where
    at most one joint moves ("superposition", the cells Eq. 6 needs)."""
    shape = tuple(len(g) for g in grid)
    if sweep == "full":
        return np.ones(shape, dtype=bool)
    if sweep != "superposition":
        raise ConfigError(f"grid: expected one of {MEASURED_KINDS}, got {sweep!r}")
    index = np.indices(shape)
    zero = [int(np.argmin(np.abs(g))) for g in grid]
    return sum((index[j] != zero[j]).astype(int) for j in range(len(shape))) <= 1


def _nearest_fill(values: np.ndarray, have: np.ndarray) -> np.ndarray:
    """Fill cells where `have` is False with the nearest (in grid-index space) measured cell."""
    from scipy import ndimage
    if have.all():
        return values.copy()
    _, indices = ndimage.distance_transform_edt(~have, return_indices=True)
    return values[tuple(indices)]
