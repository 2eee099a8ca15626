"""The ego-vibration noise model: per velocity cell mean and std magnitude spectra.

Paper Eq. 5: |N(f, v)| = mu_N(f, v) + sd_N(f, v). Eq. 6 (superposition from the cells
where at most one joint moves), for J joints:
    mu = sum_j mu(v_j on axis j) - (J - 1) mu(0)
    sd = sqrt(sum_j sd(v_j on axis j)^2 + (J - 1) sd(0)^2)
(for J = 2 the paper's equation with its + sd(0, 0)^2 term: its over-subtraction).

Only measured cells are stored (schema 2, 3: grid indices (K, J) with their spectra), so
8 joints cost what their measurements cost. A velocity is looked up as follows: a
"superposition" model uses Eq. 6 everywhere (an empty single-joint cell filled from its
nearest measured neighbour on the axis); otherwise a measured cell gives its Eq. 5, an
unmeasured one Eq. 6 where the cells it needs are measured, else the nearest measured
cell. Cells of fewer than MIN_BLOCKS_FOR_STD blocks borrow the pooled relative std.
Between grid points the estimate is multilinear where a dense table fits in
DENSE_LIMIT_BYTES, else the nearest grid point's; outside the grid it is clamped to the
edge and counted.
"""

from __future__ import annotations

import datetime as _dt
import itertools
import logging
import math
import os
import zipfile
from pathlib import Path

import numpy as np

from egovib_ros import __version__
from egovib_ros.core.blocks import WINDOW_NAME, analysis_window, n_bins, validate_blocking
from egovib_ros.errors import ConfigError, ModelFileError
from egovib_ros.robot import RobotProfile, default_profile

LOG = logging.getLogger("egovib_ros.core")

SCHEMA = "egovib.noise_model"
SCHEMA_VERSION = 3  # 3: optional `extras` (what other denoising methods calibrated); 1, 2 load
#: Prefix of the extras' keys in the .npz.
EXTRA_PREFIX = "extra."
MODEL_CHANNELS = ("combined", "x", "y", "z")
MEASURED_KINDS = ("full", "superposition", "free")
MIN_BLOCKS_FOR_STD = 5
DENSE_LIMIT_BYTES = 64 * 2**20
FILL_RULES = (
    "superposition: Eq. 6 from single-joint cells everywhere; full/free: measured cell -> Eq. 5, "
    "else Eq. 6 where its single-joint cells are measured, else nearest measured cell; "
    f"cells with < {MIN_BLOCKS_FOR_STD} blocks borrow the pooled relative std"
)


class NoiseModel:
    """Per-cell noise statistics (the estimate: module doc), from sparse cells (`cells`
    (K, J) grid indices, `mean`/`std` (K, C, F), `counts` (K,)) or, for small grids, dense
    grid-shaped arrays (`counts` 0: unmeasured)."""

    def __init__(
        self,
        *,
        grid: tuple[np.ndarray, ...],
        joint_names: tuple[str, ...],
        mean: np.ndarray,
        std: np.ndarray,
        counts: np.ndarray,
        cells: np.ndarray | None = None,
        sample_rate_hz: float = 3000.0,
        block_length: int = 64,
        hop: int = 32,
        window: np.ndarray | None = None,
        window_name: str = WINDOW_NAME,
        band_hz: tuple[float, float] = (150.0, 750.0),
        band_order: int = 4,
        channels: tuple[str, ...] = MODEL_CHANNELS,
        measured: str = "full",
        profile: RobotProfile | None = None,
        provenance: dict | None = None,
        extras: dict[str, np.ndarray] | None = None,
    ):
        self.provenance = dict(provenance or {})
        # Arrays other methods fitted at calibration (core.methods), saved beside the table.
        self.extras = {str(k): np.asarray(v) for k, v in (extras or {}).items()}
        where = self.where
        self.grid = tuple(np.asarray(g, dtype=np.float64) for g in grid)
        self.joint_names = tuple(str(n) for n in joint_names)
        self.channels = tuple(str(c) for c in channels)
        self.sample_rate_hz = float(sample_rate_hz)
        self.block_length, self.hop = block_length, hop
        self.window_name = str(window_name)
        self.band_hz = (float(band_hz[0]), float(band_hz[1]))
        self.band_order = band_order
        self.measured = str(measured)
        self._check_settings(where)
        self.window = (
            analysis_window(self.block_length, self.hop)
            if window is None
            else np.asarray(window, dtype=np.float64)
        )
        mean, std, counts = (np.asarray(a) for a in (mean, std, counts))
        if cells is None:  # dense grid-shaped input
            self._check_dense(mean, std, counts, where)
            have = counts > 0
            cells = np.argwhere(have)
            mean, std, counts = mean[have], std[have], counts[have]
        self.cells = np.asarray(cells, dtype=np.int64).reshape(-1, self.n_joints)
        self.cell_mean = np.asarray(mean, dtype=np.float64)
        self.cell_std = np.asarray(std, dtype=np.float64)
        self.cell_counts = np.asarray(counts, dtype=np.int64).reshape(-1)
        self._check_cells(where)
        order = np.argsort(self._flat(self.cells), kind="stable")
        tables = (self.cells, self.cell_mean, self.cell_std, self.cell_counts)
        self.cells, self.cell_mean, self.cell_std, self.cell_counts = (t[order] for t in tables)
        self._cell_ids = self._flat(self.cells)
        self.profile = profile if profile is not None else self._derived_profile()
        if self.profile is not None:
            self._check_profile(where)
        self._cache: dict = {}
        self._positions = [np.arange(len(g), dtype=np.float64) for g in self.grid]
        # Grid step per joint if the grid is uniform (to the last bit of the step), else 0.
        self._steps = []
        for g in self.grid:
            step = (g[-1] - g[0]) / (len(g) - 1)
            self._steps.append(
                float(step) if np.allclose(np.diff(g), step, rtol=1e-12, atol=0) else 0.0
            )
        self.grid_limits = tuple(grid_limits(g) for g in self.grid)  # per joint (low, high)

    # --- construction checks --------------------------------------------------------
    def _check_settings(self, where: str) -> None:
        if not 1 <= len(self.grid) <= 8:
            raise ModelFileError(
                f"{where}: 1 to 8 joints are supported, the model has {len(self.grid)}"
            )
        if len(self.joint_names) != self.n_joints:
            raise ModelFileError(
                f"{where}: {len(self.joint_names)} joint names for {self.n_joints} grid axes"
            )
        for j, g in enumerate(self.grid):
            if g.ndim != 1 or len(g) < 2 or not np.all(np.isfinite(g)) or np.any(np.diff(g) <= 0):
                raise ModelFileError(
                    f"{where}: grid of joint {j} must be finite and increasing with >= 2 values"
                )
        if not (math.isfinite(self.sample_rate_hz) and self.sample_rate_hz > 0):
            raise ModelFileError(
                f"{where}: sample rate must be a positive number, got {self.sample_rate_hz}"
            )
        try:
            validate_blocking(self.block_length, self.hop)
        except ConfigError as exc:
            raise ModelFileError(f"{where}: {exc}") from None
        self.block_length, self.hop = int(self.block_length), int(self.hop)
        if not (
            np.all(np.isfinite(self.band_hz))
            and 0 < self.band_hz[0] < self.band_hz[1] < self.sample_rate_hz / 2
        ):
            raise ModelFileError(
                f"{where}: band {self.band_hz} Hz does not fit the sample rate "
                f"{self.sample_rate_hz:g} Hz"
            )
        if (
            isinstance(self.band_order, bool)
            or not isinstance(self.band_order, (int, np.integer))
            or not 1 <= self.band_order <= 12
        ):
            raise ModelFileError(
                f"{where}: band order must be an integer in [1, 12], got {self.band_order!r}"
            )
        self.band_order = int(self.band_order)
        if self.measured not in MEASURED_KINDS:
            raise ModelFileError(
                f"{where}: measured must be one of {MEASURED_KINDS}, got {self.measured!r}"
            )
        if not self.channels or any(c not in MODEL_CHANNELS for c in self.channels):
            raise ModelFileError(
                f"{where}: channels must be among {MODEL_CHANNELS}, got {list(self.channels)}"
            )

    def _check_dense(
        self, mean: np.ndarray, std: np.ndarray, counts: np.ndarray, where: str
    ) -> None:
        shape = self.grid_shape + (len(self.channels), n_bins(self.block_length))
        for name, arr in (("mean", mean), ("std", std)):
            if arr.shape != shape:
                raise ModelFileError(f"{where}: '{name}' has shape {arr.shape}, expected {shape}")
        if counts.shape != self.grid_shape:
            raise ModelFileError(
                f"{where}: 'counts' has shape {counts.shape}, expected {self.grid_shape}"
            )

    def _check_cells(self, where: str) -> None:
        if self.window.shape != (self.block_length,):
            raise ModelFileError(
                f"{where}: window has {self.window.size} samples, "
                f"block_length is {self.block_length}"
            )
        if not np.all(np.isfinite(self.window)):
            bad = int(np.count_nonzero(~np.isfinite(self.window)))
            raise ModelFileError(
                f"{where}: window holds {bad} non-finite value(s) of {self.block_length}"
            )
        k = len(self.cells)
        shape = (k, len(self.channels), n_bins(self.block_length))
        for name, arr in (("mean", self.cell_mean), ("std", self.cell_std)):
            if arr.shape != shape:
                raise ModelFileError(f"{where}: '{name}' has shape {arr.shape}, expected {shape}")
            if not np.all(np.isfinite(arr)) or np.any(arr < 0):
                raise ModelFileError(f"{where}: '{name}' holds negative or non-finite values")
        if self.cell_counts.shape != (k,) or np.any(self.cell_counts <= 0):
            raise ModelFileError(
                f"{where}: 'counts' must hold one positive block count per measured cell"
            )
        if k and (np.any(self.cells < 0) or np.any(self.cells >= np.array(self.grid_shape))):
            raise ModelFileError(
                f"{where}: 'cells' holds grid indices outside the grid {self.grid_shape}"
            )
        if k != len(np.unique(self._flat(self.cells))):
            raise ModelFileError(f"{where}: 'cells' lists a cell twice")

    def _derived_profile(self) -> RobotProfile | None:
        """For a model built without a profile: the PR2 hand's on the PR2 grid, else generic
        topics on a profile grid (uniform, symmetric or from 0)."""
        try:
            pr2 = default_profile()
        except ConfigError:
            pr2 = None
        settings = dict(
            rate_hz=self.sample_rate_hz,
            block_length=self.block_length,
            hop=self.hop,
            band_hz=self.band_hz,
            band_order=self.band_order,
        )
        if (
            pr2 is not None
            and pr2.joint_names == self.joint_names
            and pr2.grid_shape == self.grid_shape
            and all(np.allclose(a, b) for a, b in zip(pr2.grid(), self.grid))
        ):
            try:
                return RobotProfile(**{**_profile_kwargs(pr2), **settings})
            except ConfigError:
                return None
        steps, max_speed, bidirectional = set(), [], []
        for g in self.grid:
            two_way = g[0] < 0
            n = (len(g) - 1) // 2 if two_way else len(g) - 1
            steps.add(n)
            max_speed.append(float(g[-1]))
            bidirectional.append(bool(two_way))
        try:
            profile = RobotProfile(
                name="unnamed",
                sensor_topic="/accelerometer/raw",
                sensor_field="linear_acceleration",
                denoised_topic="/accelerometer/denoised",
                joints_topic="/joint_states",
                joint_names=self.joint_names,
                max_speed=tuple(max_speed),
                bidirectional=tuple(bidirectional),
                steps=steps.pop() if len(steps) == 1 else 0,
                **settings,
            )
        except ConfigError:
            return None
        same = all(np.allclose(a, b) for a, b in zip(profile.grid(), self.grid))
        return profile if same and profile.grid_shape == self.grid_shape else None

    def _check_profile(self, where: str) -> None:
        p = self.profile
        problems = []
        if p.joint_names != self.joint_names:
            problems.append(f"joints {list(p.joint_names)} vs {list(self.joint_names)}")
        if abs(p.rate_hz - self.sample_rate_hz) > 1e-9 * self.sample_rate_hz:
            problems.append(f"rate {p.rate_hz:g} vs {self.sample_rate_hz:g} Hz")
        if (p.block_length, p.hop) != (self.block_length, self.hop):
            problems.append(f"blocks {p.block_length}/{p.hop} vs {self.block_length}/{self.hop}")
        if problems:
            raise ModelFileError(
                f"{where}: robot profile {p.name!r} does not match the model "
                f"({'; '.join(problems)})"
            )

    @property
    def where(self) -> str:
        """The model's file (or "noise model"), for error messages."""
        return self.provenance.get("path", "noise model")

    def scalar_extra(self, key: str, *, low: float, high: float) -> float | None:
        """The number stored in the extras under `key` (None if absent); a ModelFileError
        unless it is one finite number in (low, high]."""
        value = self.extras.get(key)
        if value is None:
            return None
        value = np.asarray(value)
        if (
            value.ndim != 0
            or value.dtype.kind not in "if"
            or not (np.isfinite(value) and low < value <= high)
        ):
            raise ModelFileError(f"{self.where}: malformed field {key!r}")
        return float(value)

    # --- shape facts -------------------------------------------------------
    @property
    def grid_shape(self) -> tuple[int, ...]:
        return tuple(len(g) for g in self.grid)

    @property
    def n_joints(self) -> int:
        return len(self.grid)

    @property
    def n_cells(self) -> int:
        """Grid points of the whole grid (measured or not)."""
        return int(np.prod(self.grid_shape, dtype=np.float64))

    @property
    def freqs_hz(self) -> np.ndarray:
        return np.fft.rfftfreq(self.block_length, 1.0 / self.sample_rate_hz)

    def zero_index(self) -> tuple[int, ...]:
        """Grid index of the all-stationary cell."""
        return tuple(int(np.argmin(np.abs(g))) for g in self.grid)

    def channel_indices(self, names: tuple[str, ...]) -> list[int]:
        missing = [n for n in names if n not in self.channels]
        if missing:
            raise ModelFileError(
                f"{self.where}: no channel(s) {missing}; the model has {list(self.channels)}"
            )
        return [self.channels.index(n) for n in names]

    def _flat(self, cells: np.ndarray) -> np.ndarray:
        """Flat cell ids (row-major over the grid; int64 holds 21^8 and more)."""
        cells = np.asarray(cells, dtype=np.int64).reshape(-1, self.n_joints)
        return np.ravel_multi_index(tuple(cells.T), self.grid_shape)

    @property
    def dense_ok(self) -> bool:
        """Small enough for grid-shaped tables (and the dense `mean`/`std`/`counts` views)."""
        per_cell = len(self.channels) * n_bins(self.block_length) * 8
        return self.n_cells * per_cell * 3 <= DENSE_LIMIT_BYTES

    # --- measured cells ---------------------------------------------------------
    def cells_measured(self) -> tuple[np.ndarray, np.ndarray]:
        """(grid indices (K, J), block counts (K,)) of the measured cells."""
        return self.cells.copy(), self.cell_counts.copy()

    def coverage(self) -> dict:
        """How much of the grid the calibration measured, for reports and /diagnostics."""
        counts = self.cell_counts
        return {
            "cells_measured": int(len(counts)),
            "cells_total": self.n_cells,
            "fraction_measured": float(len(counts) / self.n_cells),
            "blocks": int(counts.sum()),
            "min_blocks": int(counts.min()) if len(counts) else 0,
            "median_blocks": float(np.median(counts)) if len(counts) else 0.0,
            "cells_under_min_blocks": int(np.sum(counts < MIN_BLOCKS_FOR_STD)),
            "measured": self.measured,
        }

    def _rows_of(self, cells: np.ndarray) -> np.ndarray:
        """Row of each cell (B, J) in the measured table, -1 where not measured."""
        ids = self._flat(cells)
        if not len(self._cell_ids):
            return np.full(len(ids), -1, dtype=np.intp)
        pos = np.minimum(np.searchsorted(self._cell_ids, ids), len(self._cell_ids) - 1)
        return np.where(self._cell_ids[pos] == ids, pos, -1)

    def _dense(self, values: np.ndarray) -> np.ndarray:
        if not self.dense_ok:
            raise ModelFileError(
                f"{self.where}: grid of {self.n_cells:.3g} cells is too large for a dense view; "
                f"use cells_measured()"
            )
        out = np.zeros(self.grid_shape + values.shape[1:], dtype=values.dtype)
        out[tuple(self.cells.T)] = values
        return out

    @property
    def mean(self) -> np.ndarray:
        """Dense grid_shape + (C, F) mean magnitudes (0 where unmeasured); small grids only."""
        return self._cached("dense_mean", lambda: self._dense(self.cell_mean))

    @property
    def std(self) -> np.ndarray:
        return self._cached("dense_std", lambda: self._dense(self.cell_std))

    @property
    def counts(self) -> np.ndarray:
        """Dense grid-shaped block counts (0 = unmeasured); small grids only."""
        return self._cached("dense_counts", lambda: self._dense(self.cell_counts))

    def _cached(self, key, make):
        value = self._cache.get(key)
        if value is None:
            value = self._cache[key] = make()
        return value

    # --- Eq. 5 / Eq. 6 ---------------------------------------------------------
    def _effective_std(self) -> np.ndarray:
        """Per measured cell std, with thinly measured cells borrowing the pooled spread."""

        def make():
            std = self.cell_std.copy()
            thin = self.cell_counts < MIN_BLOCKS_FOR_STD
            solid = ~thin & np.all(self.cell_mean > 0, axis=(1, 2))
            if thin.any() and solid.any():
                pooled = np.median(self.cell_std[solid] / self.cell_mean[solid], axis=0)  # (C, F)
                std[thin] = np.maximum(std[thin], pooled[None] * self.cell_mean[thin])
            return std

        return self._cached("effective_std", make)

    def axis_mask(self) -> np.ndarray:
        """Cells where at most one joint moves (the superposition sweep); small grids only."""
        return sweep_mask(self.grid, "superposition")

    def _axis_tables(self) -> tuple[list, list, list]:
        """Per joint: mean (n_j, C, F), std (n_j, C, F) and measured (n_j,) along its axis
        (the other joints at zero)."""

        def make():
            zero = np.array(self.zero_index())
            std = self._effective_std()
            means, stds, have = [], [], []
            for j, n in enumerate(self.grid_shape):
                cells = np.repeat(zero[None], n, axis=0)
                cells[:, j] = np.arange(n)
                rows = self._rows_of(cells)
                ok = rows >= 0
                mu = np.zeros((n,) + self.cell_mean.shape[1:])
                sd = np.zeros_like(mu)
                mu[ok], sd[ok] = self.cell_mean[rows[ok]], std[rows[ok]]
                means.append(mu)
                stds.append(sd)
                have.append(ok)
            return means, stds, have

        return self._cached("axis", make)

    def _filled_axes(self) -> tuple[list, list]:
        """Axis tables with unmeasured single-joint cells filled from the nearest measured
        one on the same axis (the superposition sweep with a cell missing)."""
        means, stds, have = self._axis_tables()
        if not all(h.any() for h in have):
            raise ModelFileError(
                f"{self.where}: superposition needs measured single-joint cells on every axis"
            )
        out_mu, out_sd = [], []
        for mu, sd, ok in zip(means, stds, have):
            index = np.flatnonzero(ok)
            nearest = index[np.abs(np.arange(len(ok))[:, None] - index[None, :]).argmin(axis=1)]
            out_mu.append(mu[nearest])
            out_sd.append(sd[nearest])
        return out_mu, out_sd

    def _superposable(self, cells: np.ndarray) -> np.ndarray:
        """(B,) whether Eq. 6 at each cell (B, J) uses only measured single-joint cells."""
        _, _, have = self._axis_tables()
        zero = self.zero_index()
        ok = np.full(len(cells), bool(have[0][zero[0]]))
        for j in range(self.n_joints):
            ok &= (cells[:, j] == zero[j]) | have[j][cells[:, j]]
        return ok

    def _eq6_at(self, cells: np.ndarray, *, filled_axes: bool) -> tuple[np.ndarray, np.ndarray]:
        means, stds = self._filled_axes() if filled_axes else self._axis_tables()[:2]
        zero = self.zero_index()
        mu0, sd0 = means[0][zero[0]], stds[0][zero[0]]
        mu = -(self.n_joints - 1) * mu0 + sum(means[j][cells[:, j]] for j in range(self.n_joints))
        var = (self.n_joints - 1) * sd0**2 + sum(
            stds[j][cells[:, j]] ** 2 for j in range(self.n_joints)
        )
        return np.maximum(mu, 0.0), np.sqrt(var)

    def _nearest_measured(self, cells: np.ndarray) -> np.ndarray:
        """Row of the measured cell nearest (grid-index distance) to each cell (B, J)."""
        if not len(self.cells):
            raise ModelFileError(f"{self.where}: no measured cell at all")
        rows = np.empty(len(cells), dtype=np.int64)
        for start in range(0, len(cells), 4096):
            part = cells[start : start + 4096]
            d = ((part[:, None, :] - self.cells[None, :, :]) ** 2).sum(axis=2)
            rows[start : start + 4096] = d.argmin(axis=1)
        return rows

    def _cell_estimates(
        self, cells: np.ndarray, include_std: bool
    ) -> tuple[np.ndarray, np.ndarray]:
        """Noise magnitude at grid cells (B, J) -> ((B, C, F), measured (B,)) by the
        lookup rules."""
        rows = self._rows_of(cells)
        measured = rows >= 0
        if self.measured == "superposition":
            mu, sd = self._eq6_at(cells, filled_axes=True)
            return (mu + sd if include_std else mu), measured
        out = np.empty((len(cells),) + self.cell_mean.shape[1:])
        std = self._effective_std()
        out[measured] = self.cell_mean[rows[measured]] + (
            std[rows[measured]] if include_std else 0.0
        )
        missing = np.flatnonzero(~measured)
        if len(missing):
            sup = self._superposable(cells[missing])
            if sup.any():
                mu, sd = self._eq6_at(cells[missing[sup]], filled_axes=False)
                out[missing[sup]] = mu + sd if include_std else mu
            near = missing[~sup]
            if len(near):
                r = self._nearest_measured(cells[near])
                out[near] = self.cell_mean[r] + (std[r] if include_std else 0.0)
        return out, measured

    def estimate_table(self, *, include_std: bool = True) -> np.ndarray:
        """grid_shape + (C, F): the noise magnitude used at each grid point (small grids)."""

        def make():
            if not self.dense_ok:
                raise ModelFileError(f"{self.where}: grid too large for a table")
            if not len(self.cells):
                raise ModelFileError(f"{self.where}: no measured cell at all")
            cells = np.indices(self.grid_shape).reshape(self.n_joints, -1).T
            values, measured = self._cell_estimates(cells, include_std)
            filled = int(np.count_nonzero(~measured))
            if filled and include_std and self.measured != "superposition":
                # (a superposition sweep fills the cells off the axes by design)
                LOG.info(
                    "noise model: %d of %d cells are not measured; filled by Eq. 6 or the "
                    "nearest measured cell",
                    filled,
                    measured.size,
                )
            return values.reshape(self.grid_shape + values.shape[1:])

        return self._cached(("table", include_std), make)

    # --- look-ups ------------------------------------------------------------------
    def _table_for(self, channel_index, include_std: bool) -> np.ndarray:
        key = (
            "sub",
            tuple(channel_index) if isinstance(channel_index, list) else str(channel_index),
            include_std,
        )
        return self._cached(
            key,
            lambda: np.ascontiguousarray(
                self.estimate_table(include_std=include_std)[..., channel_index, :]
            ),
        )

    def _positions_of(self, velocity: np.ndarray) -> tuple[list, list, np.ndarray]:
        """Lower grid index and fraction per joint, and whether each block lies outside."""
        lower, frac = [], []
        outside = np.zeros(len(velocity), dtype=bool)
        for j, g in enumerate(self.grid):
            v = velocity[:, j]
            low, high = self.grid_limits[j]
            outside |= (v < low) | (v > high)
            step = self._steps[j]
            if step:  # uniform grid: plain arithmetic
                position = np.minimum(np.maximum((v - g[0]) / step, 0.0), len(g) - 1.0)
            else:
                position = np.interp(v, g, self._positions[j])
            i0 = np.minimum(np.floor(position).astype(np.intp), len(g) - 2)
            lower.append(i0)
            frac.append(position - i0)
        return lower, frac, outside

    def lookup(
        self,
        velocity: np.ndarray,
        channel_index: list[int] | slice = slice(None),
        *,
        include_std: bool = True,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Noise magnitude spectra at velocities (B, J) -> ((B, C, F), outside (B,), measured (B,)):
        `measured` says whether the grid cell nearest each velocity was measured."""
        velocity = np.atleast_2d(np.asarray(velocity, dtype=np.float64))
        if velocity.shape[1:] != (self.n_joints,):
            raise ConfigError(
                f"noise model: velocities must have shape (B, {self.n_joints}), "
                f"got {velocity.shape}"
            )
        lower, frac, outside = self._positions_of(velocity)
        nearest = np.stack([lo + (fr >= 0.5) for lo, fr in zip(lower, frac)], axis=1)
        measured = self._rows_of(nearest) >= 0
        if not self.dense_ok:
            values, _ = self._cell_estimates(nearest, include_std)
            return values[:, channel_index, :], outside, measured
        table = self._table_for(channel_index, include_std)
        return _interpolate(table, lower, frac), outside, measured

    def estimate(
        self,
        velocity: np.ndarray,
        channel_index: list[int] | slice = slice(None),
        *,
        include_std: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Noise magnitude spectra at velocities (B, J) -> ((B, C, F), out_of_grid (B,))."""
        noise, outside, _ = self.lookup(velocity, channel_index, include_std=include_std)
        return noise, outside

    def table(
        self, channel_index: list[int] | slice = slice(None), *, include_std: bool = True
    ) -> np.ndarray | None:
        """The dense estimate table of some channels for `estimate_one`, or None when the grid
        is too large for a table (then use `lookup`)."""
        return self._table_for(channel_index, include_std) if self.dense_ok else None

    def estimate_one(
        self, velocity: np.ndarray, table: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, bool]:
        """`lookup` for one block (the streaming case) on a `table()`: `_positions_of`'s
        operations on Python floats (a quarter of the time), the same bits. Returns (noise
        (1, C, F), outside (1,), whether the nearest grid cell was measured)."""
        measured_grid = self._cached("measured_grid", lambda: self.counts > 0)
        lower, frac = [], []
        outside = False
        for j, g in enumerate(self.grid):
            v, low, n = float(velocity[j]), float(g[0]), len(g)
            limit_low, limit_high = self.grid_limits[j]
            outside = outside or v < limit_low or v > limit_high
            if self._steps[j]:
                position = min(max((v - low) / self._steps[j], 0.0), n - 1.0)
            else:
                position = float(np.interp(v, g, self._positions[j]))
            i0 = min(int(math.floor(position)), n - 2)
            lower.append(i0)
            frac.append(position - i0)
        nearest = tuple(i + (f >= 0.5) for i, f in zip(lower, frac))
        noise = _interpolate(table, lower, frac)[None]
        return noise, np.array([outside]), bool(measured_grid[nearest])

    # --- copies ---------------------------------------------------------------------
    def robot_profile(self) -> RobotProfile:
        """The robot profile the model was calibrated with (topics, field, joints); a
        one-line ConfigError for a model that carries none."""
        if self.profile is None:
            raise ConfigError(
                f"{self.where}: the model carries no robot profile (topics, Imu field); "
                f"calibrate it again with `egovib calibrate --robot PROFILE`"
            )
        return self.profile

    def replace(self, **changes) -> "NoiseModel":
        """A copy with some fields changed (`mean`/`std`/`counts` dense for small grids, or
        sparse with `cells`)."""
        fields = dict(
            grid=self.grid,
            joint_names=self.joint_names,
            cells=self.cells,
            mean=self.cell_mean,
            std=self.cell_std,
            counts=self.cell_counts,
            sample_rate_hz=self.sample_rate_hz,
            block_length=self.block_length,
            hop=self.hop,
            window=self.window,
            window_name=self.window_name,
            band_hz=self.band_hz,
            band_order=self.band_order,
            channels=self.channels,
            measured=self.measured,
            profile=self.profile,
            provenance=dict(self.provenance),
            extras=dict(self.extras),
        )
        if {"mean", "std", "counts"} & set(changes) and "cells" not in changes:
            fields.update(cells=None, mean=self.mean, std=self.std, counts=self.counts)
        if {"joint_names", "grid"} & set(changes) and "profile" not in changes:
            fields["profile"] = None
        fields.update(changes)
        return NoiseModel(**fields)

    # --- file I/O (INTERFACES.md section 4) --------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Write the .npz (loadable with allow_pickle=False). Use atomic_output for safety."""
        provenance = {
            "source": "",
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "software_version": __version__,
            **{k: v for k, v in self.provenance.items() if k != "path"},
        }
        arrays = {
            "schema": np.array(SCHEMA),
            "schema_version": np.array(SCHEMA_VERSION),
            "profile": np.array(self.profile.dumps() if self.profile is not None else ""),
            "sample_rate_hz": np.array(self.sample_rate_hz),
            "block_length": np.array(self.block_length),
            "hop": np.array(self.hop),
            "window": self.window,
            "window_name": np.array(self.window_name),
            "band_hz": np.array(self.band_hz),
            "band_order": np.array(self.band_order),
            "joint_names": np.array(self.joint_names),
            "channels": np.array(self.channels),
            "n_joints": np.array(self.n_joints),
            "cells": self.cells.astype(np.int32),
            "mean": self.cell_mean,
            "std": self.cell_std,
            "counts": self.cell_counts,
            "measured": np.array(self.measured),
            "fill": np.array(FILL_RULES),
            "provenance_keys": np.array(list(provenance.keys())),
            "provenance_values": np.array([str(v) for v in provenance.values()]),
        }
        for j, g in enumerate(self.grid):
            arrays[f"grid_{j}"] = g
        for key, value in self.extras.items():
            arrays[EXTRA_PREFIX + key] = value
        with open(path, "wb") as fh:
            np.savez_compressed(fh, **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "NoiseModel":
        where = str(path)
        if not Path(path).is_file():
            what = "a directory, not a" if Path(path).is_dir() else "no such"
            raise ModelFileError(f"{where}: {what} noise-model file (a .npz of `egovib calibrate`)")
        try:
            with np.load(path, allow_pickle=False) as data:
                if not hasattr(data, "files"):
                    raise ModelFileError(f"{where}: not a noise-model .npz (a single .npy array)")
                fields = {k: _array_field(data, k, where) for k in data.files}
        except ModelFileError:
            raise
        except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
            # numpy's message for a non-npz file suggests allow_pickle: not useful here.
            reason = (
                "not a zip archive" if "pickle" in str(exc) else f"{exc.__class__.__name__}: {exc}"
            )
            raise ModelFileError(f"{where}: not a readable noise-model .npz ({reason})") from None
        if str(fields.get("schema", "")) != SCHEMA:
            raise ModelFileError(
                f"{where}: not an egovib noise model "
                f"(schema {str(fields.get('schema', 'missing'))!r})"
            )
        version = _integer_field(
            fields.get("schema_version", np.array(-1)), "schema_version", where
        )
        if version > SCHEMA_VERSION:
            raise ModelFileError(
                f"{where}: model schema version {version} is newer than this software "
                f"supports ({SCHEMA_VERSION}); upgrade egovib_ros"
            )
        if version < 1:
            raise ModelFileError(f"{where}: invalid schema version {version}")
        required = [
            "sample_rate_hz",
            "block_length",
            "hop",
            "window",
            "window_name",
            "band_hz",
            "band_order",
            "joint_names",
            "channels",
            "n_joints",
            "mean",
            "std",
            "counts",
            "measured",
        ]
        if version >= 2:  # a model of schema 2 or later always carries its profile key
            required += ["cells", "profile"]
        missing = [k for k in required if k not in fields]
        if missing:
            raise ModelFileError(f"{where}: missing field(s) {missing}")
        n_joints = _integer_field(fields["n_joints"], "n_joints", where)
        if not 1 <= n_joints <= 8:
            raise ModelFileError(f"{where}: malformed field 'n_joints' ({n_joints})")
        grid_keys = [f"grid_{j}" for j in range(n_joints)]
        if any(k not in fields for k in grid_keys):
            raise ModelFileError(f"{where}: missing grid arrays for {n_joints} joints")
        _check_dtypes(fields, grid_keys, where)
        try:
            return cls._from_fields(fields, grid_keys, where, version)
        except ModelFileError:
            raise
        except ConfigError as exc:
            raise ModelFileError(f"{where}: {exc}") from None
        except (TypeError, ValueError, IndexError, KeyError) as exc:
            raise ModelFileError(
                f"{where}: malformed field ({exc.__class__.__name__}: {exc})"
            ) from None

    @classmethod
    def _from_fields(
        cls, fields: dict, grid_keys: list[str], where: str, version: int
    ) -> "NoiseModel":
        provenance = dict(
            zip(
                [str(k) for k in fields.get("provenance_keys", [])],
                [str(v) for v in fields.get("provenance_values", [])],
            )
        )
        provenance["path"] = where
        profile_text = str(fields.get("profile", ""))
        profile = (
            RobotProfile.loads(profile_text, source=f"{where} (profile)") if profile_text else None
        )
        if fields["joint_names"].ndim != 1 or fields["channels"].ndim != 1:
            raise ModelFileError(
                f"{where}: malformed field 'joint_names' or 'channels' (not a list)"
            )
        common = dict(
            grid=tuple(fields[k] for k in grid_keys),
            joint_names=tuple(str(n) for n in fields["joint_names"]),
            sample_rate_hz=float(fields["sample_rate_hz"]),
            block_length=_integer_field(fields["block_length"], "block_length", where),
            hop=_integer_field(fields["hop"], "hop", where),
            window=fields["window"],
            window_name=str(fields["window_name"]),
            band_hz=tuple(float(b) for b in fields["band_hz"]),
            band_order=_integer_field(fields["band_order"], "band_order", where),
            channels=tuple(str(c) for c in fields["channels"]),
            measured=str(fields["measured"]),
            profile=profile,
            provenance=provenance,
        )
        cells = fields["cells"] if version >= 2 else None
        common["extras"] = {
            k[len(EXTRA_PREFIX) :]: v for k, v in fields.items() if k.startswith(EXTRA_PREFIX)
        }
        if version < 2:  # v1: dense tables of a 2-joint PR2-style grid
            for name in ("mean", "std"):
                if not (np.all(np.isfinite(fields[name])) and np.all(fields[name] >= 0)):
                    raise ModelFileError(f"{where}: '{name}' holds negative or non-finite values")
        return cls(
            mean=fields["mean"], std=fields["std"], counts=fields["counts"], cells=cells, **common
        )

    def summary(self) -> str:
        c = self.coverage()
        name = self.profile.name if self.profile is not None else "unnamed robot"
        return (
            f"noise model ({name}): {self.n_joints} joints {self.grid_shape} grid "
            f"({self.measured}), "
            f"{c['cells_measured']}/{c['cells_total']} cells measured, {c['blocks']} blocks "
            f"(median {c['median_blocks']:g} per cell), {self.sample_rate_hz:g} Hz, "
            f"L={self.block_length}, hop={self.hop}"
        )


def _interpolate(table: np.ndarray, lower: list, frac: list) -> np.ndarray:
    """Multilinear interpolation of `table` (grid + (C, F)) from the lower grid index and
    fraction per joint: arrays (B,) -> (B, C, F), or numbers (one block) -> (C, F); the
    corners summed in one order, so one block and many give the same bits."""
    out = None
    for corner in itertools.product((0, 1), repeat=len(lower)):
        weight = 1.0
        for j, c in enumerate(corner):
            weight = weight * (frac[j] if c else 1.0 - frac[j])
        term = table[tuple(lower[j] + c for j, c in enumerate(corner))]
        term = weight * term if np.isscalar(weight) else weight[:, None, None] * term
        out = term if out is None else out + term
    return out


def _array_field(data, key: str, where: str) -> np.ndarray:
    """One array of an open .npz; an object array (loadable only by unpickling, never done
    here) is a one-line ModelFileError naming it."""
    try:
        return data[key]
    except ValueError as exc:
        if "pickle" not in str(exc):
            raise
        raise ModelFileError(
            f"{where}: field {key!r} is an array of Python objects, which no noise model holds "
            f"(not loaded: that would run code from the file)"
        ) from None


#: Tables stored as floating point numbers (an integer table would quantise the spectra).
_FLOAT_FIELDS = ("mean", "std", "window")


def _check_dtypes(fields: dict, grid_keys: list[str], where: str) -> None:
    """Numbers where numbers belong: the spectra and the window as floating point (float32
    or float64), grids, counts, cells and scalars as real numbers; complex values nowhere."""
    for key, value in fields.items():
        kind = np.asarray(value).dtype
        if kind.kind == "c":
            raise ModelFileError(f"{where}: field {key!r} holds complex numbers ({kind})")
        wanted = None
        if key in _FLOAT_FIELDS and not (kind.kind == "f" and kind.itemsize >= 4):
            wanted = "float32 or float64"
        elif key in ("counts", "cells") and kind.kind not in "iu":
            wanted = "integers"
        elif key in ("sample_rate_hz", "band_hz", *grid_keys) and kind.kind not in "iuf":
            wanted = "real numbers"
        if wanted:
            raise ModelFileError(f"{where}: field {key!r} is stored as {kind}, expected {wanted}")


def _integer_field(value: np.ndarray, name: str, where: str) -> int:
    """An integer scalar field of a model file, or a one-line ModelFileError."""
    arr = np.asarray(value)
    if arr.ndim != 0 or arr.dtype.kind not in "iu":
        if arr.ndim == 0 and arr.dtype.kind == "f" and np.isfinite(arr) and float(arr).is_integer():
            return int(arr)
        raise ModelFileError(
            f"{where}: malformed field '{name}' (expected an integer, got {arr!r})"
        )
    return int(arr)


def _profile_kwargs(profile: RobotProfile) -> dict:
    return {f: getattr(profile, f) for f in profile.__dataclass_fields__ if f != "source"}


def grid_limits(grid: np.ndarray) -> tuple[float, float]:
    """Where a joint's velocity lies beyond its grid: past an edge by more than half the edge
    step, where the edge cell stops being the nearest (a sweep's dwell at a top speed
    overshoots it a little, and the edge cell is its cell)."""
    g = np.asarray(grid, float)
    if len(g) < 2:
        return float(g[0]), float(g[0])
    return float(g[0] - (g[1] - g[0]) / 2), float(g[-1] + (g[-1] - g[-2]) / 2)


def sweep_mask(grid: tuple[np.ndarray, ...], sweep: str) -> np.ndarray:
    """Grid-shaped mask of the cells a sweep visits: all of them ("full") or those where
    at most one joint moves ("superposition", the cells Eq. 6 needs)."""
    mask = np.zeros(tuple(len(g) for g in grid), dtype=bool)
    mask[tuple(sweep_cells(grid, sweep).T)] = True
    return mask


def sweep_cells(grid: tuple[np.ndarray, ...], sweep: str) -> np.ndarray:
    """Grid indices (K, J) of the cells a sweep visits, in sweep order, without allocating
    the grid for the superposition sweep (41 cells of the PR2; 1 + sum(n_j - 1) for any
    robot): the first joint's whole axis (rest included), then each other joint's axis
    without the rest cell."""
    shape = tuple(len(g) for g in grid)
    if sweep == "full":
        return np.indices(shape).reshape(len(shape), -1).T
    if sweep != "superposition":
        raise ConfigError(f"grid: expected 'full' or 'superposition', got {sweep!r}")
    zero = np.array([int(np.argmin(np.abs(g))) for g in grid])
    cells = []
    for j, n in enumerate(shape):
        for i in range(n):
            if j == 0 or i != zero[j]:
                cell = zero.copy()
                cell[j] = i
                cells.append(cell)
    return np.array(cells)
