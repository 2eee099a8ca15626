"""Online adaptation: the model keeps learning while the contact detector sees no contact.

`cancel` and `hybrid` (core.methods.SampleMethodDenoiser) take `adapt=AdaptSettings(...)`
and go on calibrating, from the stretches the contact detector calls contact-free:

- the residual table (hybrid): each block of what the canceller leaves (framed as
  calibration frames it, steady within `steady_tolerance` grid steps, inside the grid)
  adds its magnitude spectrum to the cell nearest its velocity. A cell keeps the mean
  magnitude and mean power per channel and bin, exponential averages that forget with
  `forget_s` of contact-free time in the cell, starting from the model's value there
  (calibrated, or its fill for a cell never calibrated); a learnt cell counts as measured
  and replaces the table's value from the next update on.
- the harmonic map (cancel, hybrid): per joint and speed-grid point, the canceller's
  frequency correction and its lines' amplitudes, averaged alike; a stream starts its
  corrections from them (warm start). Fed forward while the speeds move, they made bursts
  at the PR2 sweep's speed steps that doubled the detector's no-contact level: not done.

Gating (`ContactGate`): the denoiser's output through the contact detector's envelope,
against its threshold for the method (stored in the model) times `gate_fraction`. A block
is learnt only once the output has passed its end by `guard_s` and nothing crossed from
`guard_s` before it to `guard_s` after it; at a segment's end the blocks whose guard
reaches beyond it are dropped. Beyond the gate, a cell's power moves at most
`max_rate_db_s` per second of its own learning (a missed contact moves it little);
`reset()` returns to the calibrated model.

Determinism: what is learnt takes effect every `period` samples (whole hops, about
UPDATE_S, counted from the stream's start), never at a chunk's edge, so any chunking gives
the same output to the bit. The learnt state is saved in the model's extras (`adapt.*`); a
model carrying it uses it whether or not it goes on adapting.
"""

from __future__ import annotations

import dataclasses
import math
import multiprocessing
import os
import sys
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import numba
import numpy as np

from egovib_ros.core.calibration import FREE_STEADY_TOLERANCE
from egovib_ros.core.contact import ContactSettings, DetectionEnvelope
from egovib_ros.core.harmonic import HarmonicCanceller, HarmonicMap, fit_harmonic_map
from egovib_ros.core.noise_model import NoiseModel
from egovib_ros.errors import ConfigError, EgovibError, ModelFileError, check_ranges

#: Keys of the learnt state in a model's extras.
ADAPT_PREFIX = "adapt."
RESIDUAL_KEYS = ("cells", "mean", "power", "blocks", "new")
HARMONIC_KEYS = ("correction", "amplitude", "blocks")
#: The speeds the map in use covers, and its lines found online (the map itself is saved
#: in the model's place for it).
LINES_COVERED = ADAPT_PREFIX + "lines.covered"
LINES_FOUND = ADAPT_PREFIX + "lines.found"
LINES_OPEN = ADAPT_PREFIX + "lines.open"  # the joints whose calibration showed no line
#: Least power (relative to the cell's largest bin) a bin's rate bound is measured from.
TINY = 1e-30
#: What is learnt takes effect about this often (a whole number of hops).
UPDATE_S = 0.04
#: A speed-grid point of the harmonic map is used once learnt over this many updates.
MIN_POINT_SPANS = 10
#: Lines found online (`LineFinder`): a refit starts once the contact-free data hold
#: REFIT_BEYOND_S at speeds beyond (by REFIT_MARGIN) those of the map and the last refit,
#: or twice the data of the last refit, and REFIT_SPACING_S are new; it fits the last
#: REFIT_WINDOW_S (about 0.6 CPU-s per second of data at 1 kHz, 4 motors), and its map is
#: used REFIT_APPLY_S (+ REFIT_APPLY_PER_S per second fitted) later, offline as live, if it
#: leaves REFIT_MIN_GAIN_DB less residual than the map in use.
REFIT_BEYOND_S = 0.5
REFIT_MARGIN = 0.1
REFIT_SPACING_S = 0.5
REFIT_WINDOW_S = 8.0
REFIT_APPLY_S = 0.5
REFIT_APPLY_PER_S = 0.35
REFIT_MIN_GAIN_DB = 0.5
REFIT_NICE = 10  # the worker process's niceness (the stream first)
#: TransientGate: a contact stands this far above the envelope's median over
#: TRANSIENT_LEVEL_S (a climb changes the level within a second) ...
TRANSIENT_FACTOR = 4.0
TRANSIENT_LEVEL_S = 0.5
#: ... and this long around a crossing is left out (onset and peak; the cells' 0.15 s left
#: out 40 % of the flight's input and cost 1.3 dB).
LINE_GUARD_S = 0.02


@dataclass(frozen=True, kw_only=True)
class AdaptSettings:
    """forget_s: forgetting time constant (s of contact-free time in a cell); guard_s: time
    around a contact that is never learnt; max_rate_db_s: a cell's power change per second
    of its learning, at most; gate_fraction: the gate's share of the detector's threshold;
    threshold: that threshold (None: the model's for the method); steady_tolerance: the
    largest change of a block's velocity (grid steps, half against half) that counts;
    harmonic: learn the map's corrections and amplitudes; find_lines: refit the map at
    speeds beyond its own (`LineFinder`); learn False: use what was learnt, learn no more."""

    forget_s: float = 30.0
    guard_s: float = 0.15
    max_rate_db_s: float = 10.0
    gate_fraction: float = 1.0
    threshold: float | None = None
    steady_tolerance: float = FREE_STEADY_TOLERANCE  # free-motion calibration's
    harmonic: bool = True
    find_lines: bool = True
    learn: bool = True

    def __post_init__(self) -> None:
        checks = (
            ("forget_s", 0.01, 1e6),
            ("guard_s", 0.0, 60.0),
            ("max_rate_db_s", 0.01, 1e4),
            ("gate_fraction", 0.01, 100.0),
            ("steady_tolerance", 0.01, 1.0),
        )
        check_ranges(self, checks, "adapt: ")
        if self.threshold is not None and not (
            isinstance(self.threshold, (int, float))
            and math.isfinite(self.threshold)
            and self.threshold > 0
        ):
            raise ConfigError(f"adapt: threshold must be a number > 0, got {self.threshold!r}")


@dataclass(frozen=True)
class AdaptStats:
    """What the adaptation counted (reports, /diagnostics)."""

    blocks_learnt: int  # blocks added to the residual table
    blocks_gated: int  # blocks left out for a contact within the guard time
    blocks_unsteady: int  # velocity not steady, no joint state, gap fill, beyond the grid
    blocks_dropped: int  # guard time reaching past a segment's end
    contacts: int  # episodes of the gate's envelope above its threshold
    cells_learnt: int  # cells learnt online (in this run or saved before)
    cells_new: int  # ... of them, cells the calibration never measured
    harmonic_updates: int  # speed-grid points of the harmonic map updated
    harmonic_points: int  # speed-grid points learnt online
    resets: int  # resets to the calibrated model
    map_refits: int  # refits of the harmonic map at speeds beyond its range (LineFinder)
    lines_found: int  # lines of the map in use that were found online (0: the calibrated map)

    def as_dict(self) -> dict:
        return dict(vars(self))


# --- The gate -----------------------------------------------------------------------------
class ContactGate:
    """The contact detector's envelope on the denoiser's output (`push`: stamps (n,),
    values (n, 3), or (n, 1) band-passed and summed); `decide(first_ns, last_ns)`: whether
    nothing crossed the threshold within `guard_ns` of that span (None: not known yet)."""

    def __init__(
        self, settings: ContactSettings, *, guard_s: float, prefiltered: bool, summed: bool
    ):
        self.threshold = settings.threshold
        self.guard_ns = int(round(guard_s * 1e9))
        self._summed = summed
        self._envelope = DetectionEnvelope(settings, prefiltered=prefiltered)
        self._intervals: deque = deque()  # [first, last] stamps of runs above the threshold
        self._above = False  # the last sample pushed was above
        self.progress_ns: int | None = None  # stamp of the last output sample pushed
        self.contacts = 0

    def push(self, stamps: np.ndarray, values: np.ndarray) -> None:
        if not len(stamps):
            return
        values = np.asarray(values, np.float64)
        if self._summed or values.shape[1] == 1:  # band-passed axes, combined: the 1-D sum
            values = values.sum(axis=1)
        envelope = self._envelope.process(values)[1]
        above = envelope > self._limit(envelope)
        if above.any():
            # runs of consecutive samples above the threshold
            edges = np.diff(np.r_[False, above, False].astype(np.int8))
            starts = np.flatnonzero(edges == 1)
            stops = np.flatnonzero(edges == -1) - 1
            for a, b in zip(starts.tolist(), stops.tolist()):
                if a == 0 and self._above and self._intervals:
                    self._intervals[-1][1] = int(stamps[b])
                else:
                    self._intervals.append([int(stamps[a]), int(stamps[b])])
                    self.contacts += 1
        self._above = bool(above[-1])
        self.progress_ns = int(stamps[-1])

    def _limit(self, envelope: np.ndarray) -> float:
        return self.threshold

    def decide(self, first_ns: int, last_ns: int) -> bool | None:
        """Whether no sample from first - guard to last + guard crossed (None: not known)."""
        if self.progress_ns is None or self.progress_ns < last_ns + self.guard_ns:
            return None
        low, high = first_ns - self.guard_ns, last_ns + self.guard_ns
        for a, b in self._intervals:
            if a > high:
                break
            if b >= low:
                return False
        return True

    def prune(self, before_ns: int) -> None:
        """Forget runs that ended before `before_ns` (no block will ask about them)."""
        while self._intervals and self._intervals[0][1] < before_ns:
            self._intervals.popleft()

    def end_segment(self) -> None:
        """The next output may restart the clock: forget the stamps (not the envelope)."""
        self._intervals.clear()
        self._above = False
        self.progress_ns = None


class TransientGate(ContactGate):
    """LineFinder's gate, on the band-passed input: the threshold rises to TRANSIENT_FACTOR
    times the envelope's recent median. Where the model misses lines, its output stays above
    the detector's threshold and ContactGate clears nothing; contacts still stand out of the
    input as transients (on the output the gain's bursts do too: 130 crossings for 30
    events on the flight)."""

    def __init__(self, settings: ContactSettings, **options):
        super().__init__(settings, **options)
        self._levels: deque = deque()  # (samples, median envelope) per push, the last ones
        self._level_samples = 0
        self._keep = int(TRANSIENT_LEVEL_S * settings.sample_rate_hz)

    def _limit(self, envelope: np.ndarray) -> float:
        limit = self.threshold
        if self._levels:
            level = float(np.median([m for _, m in self._levels]))
            limit = max(limit, TRANSIENT_FACTOR * level)
        self._levels.append((len(envelope), float(np.median(envelope))))
        self._level_samples += len(envelope)
        while self._level_samples - self._levels[0][0] >= self._keep:
            self._level_samples -= self._levels.popleft()[0]
        return limit


# --- The residual table's cells -----------------------------------------------------------
@dataclass
class Candidate:
    """A block waiting for the gate."""

    first_ns: int
    last_ns: int
    cell: int  # flat cell id
    index: np.ndarray  # (J,) grid index
    magnitude: np.ndarray  # (C, F) |rfft| per model channel


def _layout_of(channels: tuple[str, ...]) -> str:
    for layout, names in (("all", ("combined", "x", "y", "z")), ("per_axis", ("x", "y", "z"))):
        if tuple(channels) == names:
            return layout
    raise ModelFileError(f"adapt: residual table channels {list(channels)} are not x, y, z")


@numba.njit(cache=True)
def _commit(mean, power, x, weight, row, rate, max_step):
    """One block `x` (C, F) into a cell's mean magnitude and power, in place: exponential
    averages (weight 1 / (blocks + 1), at least `rate`), a bin's power moving at most
    `max_step` in log (from at least TINY of the loudest bin), its mean half that, the mean
    never above the power's root."""
    a = 1.0 / (weight[row] + 1.0)
    if a < rate:
        a = rate
    loudest = TINY
    for c in range(power.shape[0]):
        for f in range(power.shape[1]):
            if power[c, f] > loudest:
                loudest = power[c, f]
    up, down = math.exp(max_step), math.exp(-max_step)
    up_m, down_m = math.exp(max_step / 2), math.exp(-max_step / 2)
    for c in range(power.shape[0]):
        for f in range(power.shape[1]):
            base = power[c, f] if power[c, f] > TINY * loudest else TINY * loudest
            p = power[c, f] + a * (x[c, f] * x[c, f] - power[c, f])
            p = min(max(p, base * down), base * up)
            root = math.sqrt(base)
            m = mean[c, f] + a * (x[c, f] - mean[c, f])
            m = min(max(m, root * down_m), root * up_m)
            power[c, f] = p
            mean[c, f] = min(m, math.sqrt(p))
    weight[row] = min(weight[row] + 1.0, 1.0 / rate)


class CellLearner:
    """Blocks of the residual stream (`push`, one segment at a time) become candidates; one
    the gate clears is `commit`ted to its cell. Per learnt cell: mean magnitude and power
    (C, F), the weight averaged (up to the forgetting window), blocks learnt, and whether
    the calibration measured it."""

    def __init__(self, residual: NoiseModel, settings: AdaptSettings):
        self.model = residual
        self.settings = settings
        self.layout = _layout_of(residual.channels)
        self.L, self.hop = residual.block_length, residual.hop
        self.window = residual.window
        fs = residual.sample_rate_hz
        self.grid = residual.grid
        self.shape = residual.grid_shape
        self._spacing = [
            np.minimum(np.diff(g, prepend=-np.inf), np.diff(g, append=np.inf)) for g in self.grid
        ]
        # per block: the forgetting rate, and the largest log change of a bin's power
        self.rate = min(1.0, self.hop / (settings.forget_s * fs))
        self.max_step = settings.max_rate_db_s * self.hop / fs * math.log(10.0) / 10.0
        C, F = len(residual.channels), self.L // 2 + 1
        self.row_of: dict[int, int] = {}
        self.cells = np.zeros((0, residual.n_joints), np.int64)
        self.mean = np.zeros((0, C, F))
        self.power = np.zeros((0, C, F))
        self.weight = np.zeros(0)
        self.blocks = np.zeros(0, np.int64)
        self.new = np.zeros(0, bool)
        self._calibrated = set(residual._cell_ids.tolist()) if len(residual.cells) else set()
        self.changed: set[int] = set()
        self.learnt = 0
        self.unsteady = 0
        self._reset_buffer()

    # --- blocks of the stream ---------------------------------------------------------
    def _reset_buffer(self) -> None:
        J = self.model.n_joints
        self._stamps = np.zeros(0, np.int64)
        self._values = np.zeros((0, 3))
        self._velocity = np.zeros((0, J))

    def end_segment(self) -> None:
        self._reset_buffer()

    def push(self, stamps: np.ndarray, values: np.ndarray, velocity: np.ndarray) -> list:
        """Samples of one segment, in order; returns the candidates of the blocks they end."""
        self._stamps = np.concatenate([self._stamps, stamps])
        self._values = np.concatenate([self._values, values])
        self._velocity = np.concatenate([self._velocity, velocity])
        L, hop = self.L, self.hop
        ends = np.arange(L, len(self._stamps) + 1, hop)
        if not len(ends):
            return []
        out = self._candidates(ends - L)
        keep = int(ends[-1]) + hop - L
        self._stamps = self._stamps[keep:]
        self._values = self._values[keep:]
        self._velocity = self._velocity[keep:]
        return out

    def _candidates(self, starts: np.ndarray) -> list:
        """The blocks starting at `starts` (buffer rows) that may teach a cell: all samples
        real, with joint states, steady and inside the grid (calibration's free rules)."""
        L = self.L
        rows = starts[:, None] + np.arange(L)[None, :]
        stamps = self._stamps[rows]
        velocity = self._velocity[rows]  # (b, L, J)
        ok = (stamps.min(axis=1) >= 0) & np.all(np.isfinite(velocity), axis=(1, 2))
        velocity = np.where(ok[:, None, None], velocity, 0.0)
        half = L // 2
        mean = velocity.mean(axis=1)
        drift = np.abs(velocity[:, :half].mean(axis=1) - velocity[:, half:].mean(axis=1))
        index = np.empty(mean.shape, np.int64)
        for j, g in enumerate(self.grid):
            i = np.abs(mean[:, j, None] - g[None, :]).argmin(axis=1)
            step = self._spacing[j][i]
            ok &= np.abs(mean[:, j] - g[i]) <= 0.5 * step  # beyond the grid's edge: no
            ok &= drift[:, j] <= self.settings.steady_tolerance * step
            index[:, j] = i
        self.unsteady += int((~ok).sum())
        if not ok.any():
            return []
        blocks = self._values[rows[ok]]  # (b, L, 3)
        if self.layout == "all":
            blocks = np.concatenate([blocks.sum(axis=2, keepdims=True), blocks], axis=2)
        magnitude = np.abs(np.fft.rfft(blocks.transpose(0, 2, 1) * self.window, axis=-1))
        cells = np.ravel_multi_index(tuple(index[ok].T), self.shape)
        return [
            Candidate(int(st[0]), int(st[-1]), int(c), i, m)
            for st, c, i, m in zip(stamps[ok], cells.tolist(), index[ok], magnitude)
        ]

    # --- cells ---------------------------------------------------------------------------
    def _row(self, cell: int, index: np.ndarray) -> int:
        row = self.row_of.get(cell)
        if row is not None:
            return row
        point = np.array([g[i] for g, i in zip(self.grid, index)])[None]
        mean, _, _ = self.model.lookup(point, include_std=False)
        high, _, _ = self.model.lookup(point, include_std=True)
        std = np.maximum(high[0] - mean[0], 0.0)
        calibrated = cell in self._calibrated
        counts = 0
        if calibrated:
            counts = int(self.model.cell_counts[self.model._rows_of(index[None])[0]])
        return self._add(
            cell, index, mean[0], mean[0] ** 2 + std**2, min(counts, 1.0 / self.rate), 0,
            not calibrated,
        )  # fmt: skip

    def _add(self, cell, index, mean, power, weight, blocks, new) -> int:
        row = self.row_of[cell] = len(self.row_of)
        self.cells = np.concatenate([self.cells, np.asarray(index, np.int64)[None]])
        self.mean = np.concatenate([self.mean, np.asarray(mean, float)[None]])
        self.power = np.concatenate([self.power, np.asarray(power, float)[None]])
        self.weight = np.append(self.weight, float(weight))
        self.blocks = np.append(self.blocks, int(blocks))
        self.new = np.append(self.new, bool(new))
        return row

    def commit(self, candidate: Candidate) -> None:
        row = self._row(candidate.cell, candidate.index)
        _commit(
            self.mean[row], self.power[row], candidate.magnitude, self.weight, row,
            self.rate, self.max_step,
        )  # fmt: skip
        self.blocks[row] += 1
        self.learnt += 1
        self.changed.add(row)

    def load(self, learnt: dict) -> None:
        """Cells learnt before (the model's `adapt.residual.*`), as they were saved."""
        for k in range(len(learnt["cells"])):
            index = learnt["cells"][k]
            cell = int(np.ravel_multi_index(tuple(index), self.shape))
            blocks = int(learnt["blocks"][k])
            weight = min(blocks, 1.0 / self.rate)
            if not learnt["new"][k]:  # calibrated too: its calibration's blocks count
                rows = self.model._rows_of(np.asarray(index)[None])
                if rows[0] >= 0:
                    weight = min(blocks + int(self.model.cell_counts[rows[0]]), 1.0 / self.rate)
            self._add(
                cell, index, learnt["mean"][k], learnt["power"][k], weight, blocks,
                bool(learnt["new"][k]),
            )  # fmt: skip

    @property
    def online(self) -> np.ndarray:
        """Rows of the cells learnt online (at least one block)."""
        return np.flatnonzero(self.blocks > 0)


class AdaptiveTable:
    """core.methods.ResidualTable with the band powers of the cells learnt online: dense
    grids, the same compiled look-up on a copy of the table whose learnt rows are changed
    and marked measured; larger grids, the nearest grid point's learnt powers."""

    def __init__(self, table):
        self.base = table
        self.dense = table._table is not None
        if self.dense:
            self._original = (table._table, table._measured)
            table._table = table._table.copy()
            table._measured = table._measured.copy()
        self._learnt: dict[int, np.ndarray] = {}  # flat cell -> (C, B) powers (larger grids)
        if not self.dense:
            base_at = table._at

            def at(rows):
                found, measured, outside = base_at(rows)
                if self._learnt:
                    index = np.empty(rows.shape, np.int64)
                    for j, g in enumerate(table.model.grid):
                        index[:, j] = np.abs(rows[:, j, None] - g[None]).argmin(axis=1)
                    cells = np.ravel_multi_index(tuple(index.T), table.model.grid_shape)
                    for k, cell in enumerate(cells.tolist()):
                        learnt = self._learnt.get(cell)
                        if learnt is not None:
                            found[k] = learnt
                            measured[k] = True
                return found, measured, outside

            table._at = at

    def set(self, cell: int, power: np.ndarray) -> None:
        """A cell's mean power per model channel and bin (C, F), as band powers (3, B)."""
        bands = power[self.base.channel_index] @ self.base.weights.T
        if self.dense:
            self.base._table[cell] = bands.reshape(-1)
            self.base._measured[cell] = True
        else:
            self._learnt[cell] = bands

    def restore(self) -> None:
        if self.dense:
            self.base._table[:] = self._original[0]
            self.base._measured[:] = self._original[1]
        self._learnt.clear()

    # the ResidualTable interface the denoiser uses
    def rows(self, velocity):
        return self.base.rows(velocity)

    @property
    def samples_unmeasured(self) -> int:
        return self.base.samples_unmeasured

    @property
    def samples_out_of_grid(self) -> int:
        return self.base.samples_out_of_grid


# --- The harmonic map's corrections and amplitudes ----------------------------------------
class HarmonicLearner:
    """Per joint and point of its speed grid (|grid values|): the canceller's frequency
    correction (J, G) and line amplitudes per axis (lines, G, C), averaged over the spans
    between updates the gate clears (speed within half a grid step of the point, and steady
    within it), forgotten like the cells; `warm_start` (module doc)."""

    def __init__(self, hmap, grid, canceller, settings: AdaptSettings):
        self.map = hmap
        self.canceller = canceller
        self.settings = settings
        self.points = [np.unique(np.abs(np.asarray(g, float))) for g in grid]
        self._half_step = [
            0.5 * float(np.diff(p).min()) if len(p) > 1 else math.inf for p in self.points
        ]
        G = max(len(p) for p in self.points)
        C = canceller.n_channels
        J = hmap.n_joints
        self.lines = [np.flatnonzero(hmap.line_joint == j) for j in range(J)]
        self.correction = np.full((J, G), np.nan)
        self.amplitude = np.full((hmap.n_lines, G, C), np.nan)
        self.weight = np.zeros((J, G))
        self.blocks = np.zeros((J, G), np.int64)
        self._started = False  # the warm start is done
        self._snapshot: tuple | None = None  # the state at the last update
        self.updates = 0

    def reset(self) -> None:
        self.correction[:] = np.nan
        self.amplitude[:] = np.nan
        self.weight[:] = 0.0
        self.blocks[:] = 0
        self._snapshot = None

    def snapshot(self, first_ns: int, last_ns: int) -> tuple | None:
        """The span since the previous snapshot: (first_ns, last_ns of its real samples,
        speeds then, (speeds, corrections, line amplitudes) now); None without a previous
        snapshot or a real sample."""
        st = self.canceller.state
        amplitude = np.hypot(st.weights[:, :, 0], st.weights[:, :, 1]).T  # (lines, C)
        now = (st.lagged.copy(), st.correction.copy(), amplitude)
        before, self._snapshot = self._snapshot, now
        if before is None or first_ns < 0:
            return None
        return (first_ns, last_ns, before[0], now)

    def commit(self, span: tuple, rate: float) -> None:
        _, _, speed_before, (speed, correction, amplitude) = span
        for j, points in enumerate(self.points):
            k = int(np.abs(points - speed[j]).argmin())
            half = self._half_step[j]
            if abs(points[k] - speed[j]) > half or abs(speed[j] - speed_before[j]) > half:
                continue
            if speed[j] <= self.map.min_speed[j]:
                continue  # its lines are off
            a = max(1.0 / (self.weight[j, k] + 1.0), rate)
            lines = self.lines[j]
            if np.isnan(self.correction[j, k]):
                self.correction[j, k] = correction[j]
                self.amplitude[lines, k] = amplitude[lines]
            else:
                self.correction[j, k] += a * (correction[j] - self.correction[j, k])
                self.amplitude[lines, k] += a * (amplitude[lines] - self.amplitude[lines, k])
            self.weight[j, k] = min(self.weight[j, k] + 1.0, 1.0 / rate)
            self.blocks[j, k] += 1
            self.updates += 1

    def _at(self, j: int, speed: float) -> tuple[float, np.ndarray] | None:
        """Learnt correction and amplitudes (lines of j, C) at `speed`, linear between the
        two grid points around it; None unless both (or the one it sits on) were learnt over
        at least MIN_POINT_SPANS spans (no extrapolation to speeds the map has not seen)."""
        points = self.points[j]
        k = int(np.searchsorted(points, speed))
        if k < len(points) and points[k] == speed:
            around = (k, k)
        elif 0 < k < len(points):
            around = (k - 1, k)
        else:
            return None
        if (
            self.blocks[j, around[0]] < MIN_POINT_SPANS
            or self.blocks[j, around[1]] < MIN_POINT_SPANS
        ):
            return None
        lo, hi = around
        w = 0.0 if lo == hi else (speed - points[lo]) / (points[hi] - points[lo])
        lines = self.lines[j]
        correction = (1.0 - w) * self.correction[j, lo] + w * self.correction[j, hi]
        amplitude = (1.0 - w) * self.amplitude[lines, lo] + w * self.amplitude[lines, hi]
        return float(correction), amplitude

    def warm_start(self) -> None:
        """At the stream's first update: each joint's frequency correction from the map at
        its speed, where learnt (the canceller's PLL otherwise starts from none)."""
        if self._started:
            return
        self._started = True
        st = self.canceller.state
        bound = float(self.canceller.settings.max_correction)
        for j in range(len(self.points)):
            learnt = self._at(j, float(st.lagged[j]))
            if learnt is not None and st.lagged[j] > self.map.min_speed[j]:
                st.correction[j] = min(max(learnt[0], -bound), bound)

    def load(self, learnt: dict) -> None:
        correction, amplitude, blocks = learnt["correction"], learnt["amplitude"], learnt["blocks"]
        if (
            correction.shape != self.correction.shape
            or amplitude.shape != self.amplitude.shape
            or blocks.shape != self.blocks.shape
        ):
            raise ModelFileError("adapt: the learnt harmonic map does not fit the model's")
        self.correction[:], self.amplitude[:], self.blocks[:] = correction, amplitude, blocks
        self.weight[:] = blocks


def _merged(current: HarmonicMap, fitted: HarmonicMap, open_: np.ndarray) -> HarmonicMap | None:
    """`current` with the joints of `open_` as `fitted` has them (their parameters and
    lines); None if `fitted` has no line on them."""
    take = open_[fitted.line_joint]
    if not take.any():
        return None
    keep = ~open_[current.line_joint]

    def per_joint(name):
        return np.where(open_, getattr(fitted, name), getattr(current, name))

    return HarmonicMap(
        joint_names=current.joint_names,
        exponent=per_joint("exponent"),
        tau_up_s=per_joint("tau_up_s"),
        tau_down_s=per_joint("tau_down_s"),
        min_speed=per_joint("min_speed"),
        line_joint=np.r_[current.line_joint[keep], fitted.line_joint[take]],
        line_coefficient=np.r_[current.line_coefficient[keep], fitted.line_coefficient[take]],
        line_score_db=np.r_[current.line_score_db[keep], fitted.line_score_db[take]],
        residual_rms=current.residual_rms,
    )


_POOL: ProcessPoolExecutor | None = None


def _refit_pool() -> ProcessPoolExecutor:
    """One worker process (spawned at the first refit) for every LineFinder, at a lower
    priority: a fit in the node's process took the interpreter from the stream's callbacks
    (3 kHz: p99 latency 11.3 ms with fits in a thread, the budget 10)."""
    global _POOL
    if _POOL is None:
        _POOL = ProcessPoolExecutor(
            1, mp_context=multiprocessing.get_context("spawn"), initializer=_lower_priority
        )
    return _POOL


def _discard_pool() -> None:
    global _POOL
    _POOL = None


def _lower_priority() -> None:
    os.nice(REFIT_NICE)


def _submit_refit(*args) -> Future:
    """`_refit(*args)` in the worker process, the caller's `__main__` hidden while it
    starts (spawn would run a user's script without a main guard again)."""
    main = sys.modules["__main__"]
    saved = {k: main.__dict__[k] for k in ("__file__", "__spec__") if k in main.__dict__}
    main.__dict__.pop("__file__", None)
    main.__spec__ = None
    try:
        return _refit_pool().submit(_refit, *args)
    finally:
        main.__dict__.pop("__spec__", None)
        main.__dict__.update(saved)


def _refit(x, speed, current: HarmonicMap, open_: np.ndarray, fit: dict) -> HarmonicMap | None:
    """LineFinder's refit (in the worker): `current` with the `open_` joints fitted on (x,
    speed); None unless that leaves REFIT_MIN_GAIN_DB less residual than `current`."""
    try:
        fitted = fit_harmonic_map(x, speed, **fit)[0]
    except EgovibError:  # data a fit refuses (too short, no steady window): no lines
        return None
    fitted = _merged(current, fitted, open_)
    if fitted is None:
        return None
    settle = len(x) // 10  # the trackers settling, left out as the fit leaves it out

    def residual_power(hmap: HarmonicMap) -> float:
        if not hmap.n_lines:
            return float(np.mean(x[settle:] ** 2))
        canceller = HarmonicCanceller(
            hmap,
            sample_rate_hz=fit["sample_rate_hz"],
            band_hz=fit["band_hz"],
            n_channels=x.shape[1],
            settings=fit["settings"],
        )
        return float(np.mean(canceller.process(x, speed)[settle:] ** 2))

    gain_db = 10 * math.log10(residual_power(current) / max(residual_power(fitted), 1e-300))
    return fitted if gain_db >= REFIT_MIN_GAIN_DB else None


def _measured_speeds(table: NoiseModel) -> np.ndarray:
    """Per joint, the largest |velocity| of a measured cell (the calibrated map's speeds)."""
    return np.array(
        [
            np.abs(np.asarray(g, float)[table.cells[:, j]]).max() if len(table.cells) else 0.0
            for j, g in enumerate(table.grid)
        ]
    )


class LineFinder:
    """Lines of the joints whose calibration showed none (`open`: a quadcopter calibrated at
    idle meets its motors' lines in flight): the last REFIT_WINDOW_S of contact-free samples
    TransientGate clears (`push`) are refitted (module constants: when) in a worker process
    (`_refit`); later `at_update` returns the map whose open joints take the fitted lines,
    exponent and lags (the others keep the calibrated ones, which cancel more at their
    speeds). Refitting the residual table and the gain's statistics too gave less (26.5
    against 27.0 dB on the low flight split)."""

    def __init__(
        self, hmap: HarmonicMap, model: NoiseModel, residual: NoiseModel, canceller_settings
    ):
        self.model = model
        self.canceller_settings = canceller_settings
        self.map = hmap
        self.open = np.array([not np.any(hmap.line_joint == j) for j in range(hmap.n_joints)])
        fs = model.sample_rate_hz
        self.calibrated = _measured_speeds(residual)
        self.covered = self.calibrated.copy()
        self._keep = int(REFIT_WINDOW_S * fs)
        self._beyond = int(REFIT_BEYOND_S * fs)
        self._spacing = int(REFIT_SPACING_S * fs)
        # [values (n, C), |velocity| (n, J), samples beyond] cleared by the gate
        self._pieces: deque = deque()
        self._held = 0
        self._held_beyond = 0  # of them, at speeds beyond (`_beyond_of`)
        self._new = 0  # samples pushed since the last refit started
        self._updates = 0
        # (apply at update, the fit, the speeds it covers)
        self._pending: tuple[int, Future, np.ndarray] | None = None
        self._tried_on = 0  # samples the last refit was given
        self._tried = np.zeros_like(self.covered)  # the largest speeds refits were given
        self.refits = 0
        self.lines_found = 0

    def push(self, values: np.ndarray, velocity: np.ndarray) -> None:
        ok = np.all(np.isfinite(velocity), axis=1)
        if not ok.any():
            return
        speed = np.abs(velocity[ok])
        beyond = self._beyond_of(speed)
        self._pieces.append([values[ok], speed, beyond])
        self._held += len(speed)
        self._new += len(speed)
        self._held_beyond += beyond
        while self._held - len(self._pieces[0][0]) >= self._keep:
            dropped = self._pieces.popleft()
            self._held -= len(dropped[0])
            self._held_beyond -= dropped[2]

    def _beyond_of(self, speed: np.ndarray) -> int:
        """Samples at speeds beyond the map's and the last refit's (by REFIT_MARGIN)."""
        known = np.maximum(self.covered, self._tried) * (1 + REFIT_MARGIN)
        return int(np.count_nonzero((speed > known).any(axis=1)))

    def _recount(self) -> None:
        """The held samples beyond, counted again per piece (the covered speeds moved)."""
        for piece in self._pieces:
            piece[2] = self._beyond_of(piece[1])
        self._held_beyond = sum(piece[2] for piece in self._pieces)

    def at_update(self) -> HarmonicMap | None:
        """The new map to use from now on, or None."""
        self._updates += 1
        if self._pending is not None:
            apply_at, future, covers = self._pending
            if self._updates < apply_at:
                return None
            self._pending = None
            try:
                found = future.result()
            except BrokenProcessPool:  # the worker died (killed, out of memory): a new one
                _discard_pool()
                found = None
            if found is not None:
                self.map = found
                self.lines_found = int(np.count_nonzero(self.open[found.line_joint]))
                self.covered = np.maximum(self.covered, covers)
                self._recount()
            return found
        if self._new < self._spacing:
            return None
        # new speeds (beyond the map's and the last refit's), or twice the data of the
        # last refit: a robot without lines there is tried a few times, not at every update
        if self._held_beyond < self._beyond and self._held < 2 * self._tried_on:
            return None
        speed = np.concatenate([p[1] for p in self._pieces])
        values = np.concatenate([p[0] for p in self._pieces])
        self._new = 0
        self._tried_on = len(speed)
        self._tried = np.maximum(self._tried, speed.max(axis=0))
        self._recount()
        self.refits += 1
        m = self.model
        fit = dict(
            sample_rate_hz=m.sample_rate_hz,
            band_hz=m.band_hz,
            joint_names=m.joint_names,
            max_speed=np.array(m.robot_profile().max_speed, float),
            settings=self.canceller_settings,
        )
        future = _submit_refit(values, speed, self.map, self.open, fit)
        wait_s = REFIT_APPLY_S + REFIT_APPLY_PER_S * len(speed) / self.model.sample_rate_hz
        self._pending = (
            self._updates + max(1, round(wait_s / UPDATE_S)),
            future,
            speed.max(axis=0),
        )
        return None

    def reset(self, hmap: HarmonicMap) -> None:
        """Back to the calibrated map (a refit under way is dropped)."""
        self.map = hmap
        self.covered = self.calibrated.copy()
        self._pending = None
        self.lines_found = 0
        self._tried_on = 0
        self._tried[:] = 0.0
        self._recount()


# --- The model's extras -------------------------------------------------------------------
def learnt_state(model: NoiseModel) -> tuple[dict | None, dict | None]:
    """(residual cells, harmonic map) learnt online that the model carries (None: none)."""
    where = model.where
    extras = model.extras
    residual = harmonic = None
    keys = [ADAPT_PREFIX + "residual." + k for k in RESIDUAL_KEYS]
    if any(k in extras for k in keys):
        if not all(k in extras for k in keys):
            raise ModelFileError(f"{where}: learnt residual cells lack some of {keys}")
        residual = {k: np.asarray(extras[key]) for k, key in zip(RESIDUAL_KEYS, keys)}
        K = len(residual["cells"])
        mean, power = residual["mean"], residual["power"]
        if (
            residual["cells"].ndim != 2
            or residual["cells"].shape[1] != model.n_joints
            or mean.shape[0] != K
            or mean.shape != power.shape
            or residual["blocks"].shape != (K,)
            or residual["new"].shape != (K,)
            or not np.all(np.isfinite(mean))
            or not np.all(np.isfinite(power))
            or np.any(power < 0)
            or np.any(residual["cells"] < 0)
            or np.any(residual["cells"] >= np.array(model.grid_shape))
        ):
            raise ModelFileError(f"{where}: malformed learnt residual cells ({keys[0]} ...)")
        residual["cells"] = residual["cells"].astype(np.int64)
        residual["new"] = residual["new"].astype(bool)
    hkeys = [ADAPT_PREFIX + "harmonic." + k for k in HARMONIC_KEYS]
    if any(k in extras for k in hkeys):
        if not all(k in extras for k in hkeys):
            raise ModelFileError(f"{where}: learnt harmonic map lacks some of {hkeys}")
        harmonic = {k: np.asarray(extras[key], float) for k, key in zip(HARMONIC_KEYS, hkeys)}
        harmonic["blocks"] = harmonic["blocks"].astype(np.int64)
    return residual, harmonic


def describe_learnt(model: NoiseModel) -> dict | None:
    """What a model learnt online (for `egovib model show`), None if nothing."""
    residual, harmonic = learnt_state(model)
    found = int(model.extras.get(LINES_FOUND, 0))
    if residual is None and harmonic is None and not found:
        return None
    out = {"forget_s": float(model.extras.get(ADAPT_PREFIX + "forget_s", np.nan))}
    if residual is not None:
        online = residual["blocks"] > 0
        out.update(
            cells=residual["cells"][online],
            blocks=residual["blocks"][online],
            new=residual["new"][online],
        )
    if harmonic is not None:
        out["harmonic_points"] = int((harmonic["blocks"] > 0).sum())
    if found:
        out["lines_found"] = found
    return out


# --- The whole of it, for SampleMethodDenoiser --------------------------------------------
class Adaptation:
    """Runs beside a SampleMethodDenoiser (`denoiser`): `run` takes a batch of framed samples
    and hands it to the denoiser in pieces that end on the update schedule; `observe` takes
    what the denoiser outputs besides (a segment's look-ahead released), `end_segment` the
    end of a segment. The learning runs at each update (see the module doc)."""

    def __init__(self, denoiser, settings: AdaptSettings, *, threshold: float | None):
        self.d = denoiser
        self.settings = settings
        model = denoiser.model
        cal = denoiser.calibration
        fs = model.sample_rate_hz
        hop = int(model.hop)
        self.period = hop * max(1, int(round(UPDATE_S * fs / hop)))  # the update schedule
        self.rate = min(1.0, self.period / (settings.forget_s * fs))  # per update (harmonic)
        self._phase = 0
        residual_learnt, harmonic_learnt = learnt_state(model)
        self.table = denoiser._table  # an AdaptiveTable for hybrid, None for cancel
        self.cells = None
        if self.table is not None:
            self.cells = CellLearner(cal.residual, settings)
            if residual_learnt is not None:
                self.cells.load(residual_learnt)
        self.harmonic = None
        if settings.harmonic and cal.harmonic.n_lines:
            self.harmonic = HarmonicLearner(cal.harmonic, model.grid, denoiser._canceller, settings)
            if harmonic_learnt is not None:
                self.harmonic.load(harmonic_learnt)
        self._calibrated_map = cal.harmonic
        self.lines = None
        if settings.learn and settings.find_lines:
            lines = LineFinder(cal.harmonic, model, cal.residual, cal.canceller)
            if LINES_OPEN in model.extras:  # a model that found lines before: its state
                try:
                    lines.open[:] = np.asarray(model.extras[LINES_OPEN], bool)
                    lines.covered[:] = np.maximum(lines.covered, model.extras[LINES_COVERED])
                    lines.lines_found = int(model.extras[LINES_FOUND])
                except (KeyError, ValueError, TypeError):
                    raise ModelFileError(
                        f"{model.where}: malformed {ADAPT_PREFIX}lines.*"
                    ) from None
            if lines.open.any():  # else every joint has its calibrated lines
                self.lines = lines
        self.gate = self.line_gate = None
        if settings.learn:
            if threshold is None:
                raise ConfigError(
                    f"{model.where}: adapt needs the contact detector's threshold for method "
                    f"{denoiser.method}, and the model stores none; calibrate it again "
                    f"(`egovib calibrate` stores them) or give the threshold"
                )
            contact = ContactSettings.for_model(model, threshold * settings.gate_fraction)
            dropin = denoiser.output == "dropin" and denoiser.channels == "per_axis"
            self.gate = ContactGate(
                contact,
                guard_s=settings.guard_s,
                prefiltered=not dropin,
                summed=not dropin and denoiser.channels == "per_axis",
            )
            # on the canceller's input (band-passed): the gain's output stands low most of
            # the time and lets bursts through, transients against its own median
            self.line_gate = (
                TransientGate(contact, guard_s=LINE_GUARD_S, prefiltered=True, summed=True)
                if self.lines is not None
                else None
            )
        # what the pieces since the last update left: (stamps, residual, velocity), outputs
        self._inputs: list = []
        self._outputs: list = []
        self._pending: deque = deque()  # candidates (cells) waiting for the gate
        self._spans: deque = deque()  # harmonic spans waiting for the gate
        self._line_spans: deque = deque()  # (first, last, values, velocity) for LineFinder
        self.blocks_gated = 0
        self.blocks_dropped = 0
        self.resets = 0

    # --- the stream -----------------------------------------------------------------------
    def run(self, stamps, values, velocity, raw):
        """A framed batch through the denoiser, in pieces ending on the schedule."""
        out_s, out_v = [], []
        n, i = len(stamps), 0
        learn = self.settings.learn
        while i < n:
            take = min(n - i, self.period - self._phase)
            part = slice(i, i + take)
            s, v, residual = self.d._run_piece(
                stamps[part], values[part], velocity[part], None if raw is None else raw[part]
            )
            out_s.append(s)
            out_v.append(v)
            if learn:
                self._inputs.append((stamps[part], residual, velocity[part], values[part]))
                self._outputs.append((s, v))
            self._phase += take
            i += take
            if self._phase == self.period:
                self._phase = 0
                self._update()
        if len(out_s) == 1:
            return out_s[0], out_v[0]
        return np.concatenate(out_s), np.concatenate(out_v)

    def observe(self, stamps: np.ndarray, values: np.ndarray) -> None:
        if self.settings.learn and len(stamps):
            self._outputs.append((stamps, values))

    def end_segment(self) -> None:
        """A segment ended (its output is all out): learn what can be decided, drop the rest."""
        if self.settings.learn:
            self._take(final=True)
            if self.cells is not None:
                self.cells.end_segment()
            self.gate.end_segment()
            if self.line_gate is not None:
                self.line_gate.end_segment()
            if self.harmonic is not None:
                self.harmonic._snapshot = None
            self._apply()

    # --- learning -------------------------------------------------------------------------
    def _update(self) -> None:
        """An update: learn what the gate can decide now, and put it to use."""
        if self.settings.learn:
            self._take(final=False)
            self._apply()
            found = self.lines.at_update() if self.lines is not None else None
            if found is not None:
                self._use_map(found)
        if self.harmonic is not None:
            self.harmonic.warm_start()

    def _take(self, *, final: bool) -> None:
        """The pieces since the last update: blocks (cells), a span (harmonic map), the
        output through the gate; then what the gate clears is learnt."""
        if self._inputs:
            stamps = np.concatenate([p[0] for p in self._inputs])
            velocity = np.concatenate([p[2] for p in self._inputs])
            if self.cells is not None:
                residual = np.concatenate([p[1] for p in self._inputs])
                self._pending.extend(self.cells.push(stamps, residual, velocity))
            if self.harmonic is not None:
                real = stamps[stamps >= 0]
                first, last = (int(real[0]), int(real[-1])) if len(real) else (-1, -1)
                span = self.harmonic.snapshot(first, last)
                if span is not None:
                    self._spans.append(span)
            real = stamps >= 0
            if self.lines is not None and real.any():
                values = np.concatenate([p[3] for p in self._inputs])[real]
                self.line_gate.push(stamps[real], values)
                self._line_spans.append(
                    (int(stamps[real][0]), int(stamps[real][-1]), values, velocity[real])
                )
            self._inputs = []
        if self._outputs:
            self.gate.push(
                np.concatenate([o[0] for o in self._outputs]),
                np.concatenate([o[1] for o in self._outputs]),
            )
            self._outputs = []
        self._decide(final=final)

    def _decide(self, *, final: bool) -> None:
        gate, line_gate = self.gate, self.line_gate
        for c, clear in _decided(self._pending, gate, final):
            if clear:
                self.cells.commit(c)
            elif clear is None:
                self.blocks_dropped += 1
            else:
                self.blocks_gated += 1
        for span, clear in _decided(self._spans, gate, final):
            if clear:
                self.harmonic.commit(span, self.rate)
        for (_, _, values, velocity), clear in _decided(self._line_spans, line_gate, final):
            if clear:
                self.lines.push(values, velocity)
        if line_gate is not None and line_gate.progress_ns is not None:
            oldest = self._line_spans[0][0] if self._line_spans else line_gate.progress_ns
            line_gate.prune(min(oldest, line_gate.progress_ns) - line_gate.guard_ns)
        if gate.progress_ns is not None:
            oldest = [gate.progress_ns]
            if self._pending:
                oldest.append(self._pending[0].first_ns)
            if self._spans:
                oldest.append(self._spans[0][0])
            gate.prune(min(oldest) - gate.guard_ns)

    def _use_map(self, hmap: HarmonicMap) -> None:
        """A harmonic map in place of the one in use, from the next sample on (its lines'
        learnt amplitudes and corrections start afresh)."""
        d = self.d
        d._canceller = d._canceller.with_map(hmap)
        d.calibration = dataclasses.replace(d.calibration, harmonic=hmap)
        self._spans.clear()
        self.harmonic = None
        if self.settings.harmonic and hmap.n_lines:
            self.harmonic = HarmonicLearner(hmap, d.model.grid, d._canceller, self.settings)

    def _apply(self) -> None:
        """Changed cells into the table."""
        if self.cells is None or not self.cells.changed:
            return
        cells = self.cells
        for row in sorted(cells.changed):
            cell = int(np.ravel_multi_index(tuple(cells.cells[row]), cells.shape))
            self.table.set(cell, cells.power[row])
        cells.changed.clear()

    # --- state ------------------------------------------------------------------------------
    def apply_loaded(self) -> None:
        """The cells a model learnt before go into the table (from the first sample on)."""
        if self.cells is not None:
            self.cells.changed.update(range(len(self.cells.row_of)))
            self._apply()

    def reset(self) -> None:
        """Back to the calibrated model: nothing learnt (in this run or saved before); what
        waits for the gate is dropped."""
        if self.cells is not None:
            fresh = CellLearner(self.d.calibration.residual, self.settings)
            fresh.unsteady, fresh.learnt = self.cells.unsteady, self.cells.learnt
            for name in ("_stamps", "_values", "_velocity"):  # the blocks in the making
                setattr(fresh, name, getattr(self.cells, name))
            self.cells = fresh
            self.table.restore()
        if self.lines is not None and self.lines.lines_found:
            self._use_map(self._calibrated_map)
        if self.lines is not None:
            self.lines.reset(self._calibrated_map)
        if self.harmonic is not None:
            self.harmonic.reset()
        self._pending.clear()
        self._spans.clear()
        self._line_spans.clear()
        self.resets += 1

    @property
    def stats(self) -> AdaptStats:
        cells = self.cells
        online = cells.online if cells is not None else np.zeros(0, np.int64)
        h = self.harmonic
        return AdaptStats(
            blocks_learnt=cells.learnt if cells is not None else 0,
            blocks_gated=self.blocks_gated,
            blocks_unsteady=cells.unsteady if cells is not None else 0,
            blocks_dropped=self.blocks_dropped,
            contacts=self.gate.contacts if self.gate is not None else 0,
            cells_learnt=int(len(online)),
            cells_new=int(cells.new[online].sum()) if cells is not None else 0,
            harmonic_updates=h.updates if h is not None else 0,
            harmonic_points=int((h.blocks > 0).sum()) if h is not None else 0,
            resets=self.resets,
            map_refits=self.lines.refits if self.lines is not None else 0,
            lines_found=self.lines.lines_found if self.lines is not None else 0,
        )

    def extras(self) -> dict[str, np.ndarray]:
        """The learnt state as model extras (`adapt.*`), for NoiseModel.replace."""
        out: dict[str, np.ndarray] = {ADAPT_PREFIX + "forget_s": np.array(self.settings.forget_s)}
        cells = self.cells
        if cells is not None:
            for key in RESIDUAL_KEYS:  # cells, mean, power, blocks, new of the cells learnt
                value = getattr(cells, key)[cells.online]
                out[ADAPT_PREFIX + "residual." + key] = (
                    value.astype(np.int32) if key == "cells" else value
                )
        if self.harmonic is not None:
            for key in HARMONIC_KEYS:
                out[ADAPT_PREFIX + "harmonic." + key] = getattr(self.harmonic, key).copy()
        if self.lines is not None:
            out[LINES_COVERED] = self.lines.covered.copy()
            out[LINES_FOUND] = np.array(self.lines.lines_found)
            out[LINES_OPEN] = self.lines.open.copy()
        return out


def _decided(queue: deque, gate: ContactGate, final: bool):
    """The queued blocks or spans (first by their (first_ns, last_ns)) the gate can decide,
    each taken off the queue with its verdict (None: not known, only when `final`)."""
    while queue:
        item = queue[0]
        span = (item.first_ns, item.last_ns) if isinstance(item, Candidate) else item[:2]
        clear = gate.decide(*span)
        if clear is None and not final:
            return
        yield queue.popleft(), clear


def without_learnt(extras: dict) -> dict:
    """Extras less what adaptation saved (a model back to its calibration)."""
    return {k: v for k, v in extras.items() if not k.startswith(ADAPT_PREFIX)}
