"""`egovib model show MODEL.npz --out DIR [--bag BAG]`: look at a noise model.

Writes into DIR (atomically): coverage.png (which velocity cells the calibration
measured, from how many blocks, and how the model fills the others: Eq. 6 from the
single-joint cells, or the nearest measured cell; a map for two joints, per-joint
marginals else, built from the sparse cells: an 8-joint grid is never allocated);
spectra_<channel>.png (mean and std spectra of a few measured cells, the paper's Fig. 3
for any robot); with --bag bag.png (where the recording's blocks fall, framed as the
denoiser frames them, streamed); for a model that learnt online (`egovib denoise --adapt
--save-model`, the denoiser node's save_model) online.png; and summary.md with the
numbers. Everything is computed before the output is written; bad input is one line,
exit status 2, and nothing written.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from egovib_ros.bag import BagReader, iter_recording
from egovib_ros.core.adapt import describe_learnt
from egovib_ros.core.methods import METHODS, default_method, motion_limits, stored_threshold
from egovib_ros.core.noise_model import MIN_BLOCKS_FOR_STD, grid_limits
from egovib_ros.core.stream import BlockFramer, FramerSettings, check_stream
from egovib_ros.core.velocity import MISSING
from egovib_ros.errors import BagError
from egovib_ros.viz import pyplot, save_figure

#: Fractions of a joint's max speed whose single-joint cells the spectra show (with rest).
SPEED_FRACTIONS = (0.25, 0.5, 0.75, 1.0)
#: Recording blocks kept (evenly thinned) to draw those beyond a 2-joint grid.
OUTSIDE_POINTS = 4000
SUMMARY = "summary.md"
COVERAGE_PNG = "coverage.png"
BAG_PNG = "bag.png"
ONLINE_PNG = "online.png"


def spectra_png(channel: str) -> str:
    return f"spectra_{channel}.png"


# --- coverage --------------------------------------------------------------------------
def _flat_ids(cells: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Row-major cell ids (int64 holds 21^8 and more)."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, len(shape))
    return np.ravel_multi_index(tuple(cells.T), shape)


@dataclass
class CellIndex:
    """The measured cells of a model for look-ups (sorted ids), and which unmeasured cells
    the model fills by Eq. 6 (from the all-stationary and single-joint cells) rather than
    from the nearest measured cell (see core.noise_model)."""

    shape: tuple[int, ...]
    ids: np.ndarray  # (K,) sorted flat ids of the measured cells
    rows: np.ndarray  # (K,) row in model.cells of each id
    zero: np.ndarray  # (J,) grid index of rest
    axis_measured: list[np.ndarray]  # per joint (n_j,) bool: single-joint cell measured
    superposition: bool

    @classmethod
    def of(cls, model) -> "CellIndex":
        shape = model.grid_shape
        ids = _flat_ids(model.cells, shape)
        order = np.argsort(ids)
        zero = np.array(model.zero_index(), dtype=np.int64)
        moving = model.cells != zero[None, :]
        axis_measured = []
        for j, n in enumerate(shape):
            on_axis = ~np.delete(moving, j, axis=1).any(axis=1)  # every other joint at rest
            have = np.zeros(n, dtype=bool)
            have[model.cells[on_axis, j]] = True
            axis_measured.append(have)
        return cls(
            shape=shape,
            ids=ids[order],
            rows=order,
            zero=zero,
            axis_measured=axis_measured,
            superposition=model.measured == "superposition",
        )

    def row_of(self, cells: np.ndarray) -> np.ndarray:
        """Row of each cell (B, J) in the model's table, -1 where not measured."""
        ids = _flat_ids(cells, self.shape)
        if not len(self.ids):
            return np.full(len(ids), -1, dtype=np.int64)
        at = np.minimum(np.searchsorted(self.ids, ids), len(self.ids) - 1)
        return np.where(self.ids[at] == ids, self.rows[at], -1)

    def eq6(self, cells: np.ndarray) -> np.ndarray:
        """(B,) whether the model gives an unmeasured cell by Eq. 6: always for a
        superposition model; for full/free ones where rest and every single-joint cell
        the cell needs are measured."""
        cells = np.asarray(cells, dtype=np.int64).reshape(-1, len(self.shape))
        if self.superposition:
            return np.ones(len(cells), dtype=bool)
        rest = bool(self.axis_measured[0][self.zero[0]])
        ok = np.full(len(cells), rest)
        for j, have in enumerate(self.axis_measured):
            ok &= (cells[:, j] == self.zero[j]) | have[cells[:, j]]
        return ok

    def eq6_count(self, measured_cells: np.ndarray) -> int:
        """Unmeasured grid cells the model fills by Eq. 6, counted without the grid."""
        total = int(np.prod(self.shape, dtype=object))
        if self.superposition:
            return total - len(measured_cells)
        if not self.axis_measured[0][self.zero[0]]:
            return 0
        reachable = 1
        for j, have in enumerate(self.axis_measured):
            reachable *= 1 + int(have.sum() - have[self.zero[j]])
        return reachable - int(self.eq6(measured_cells).sum())


def coverage_facts(model) -> dict:
    """The coverage numbers of the summary (sparse: any number of joints)."""

    facts = dict(model.coverage())
    index = CellIndex.of(model)
    total = int(np.prod(model.grid_shape, dtype=object))
    eq6 = index.eq6_count(model.cells)
    facts.update(
        cells_total=total,
        cells_unmeasured=total - facts["cells_measured"],
        cells_eq6=eq6,
        cells_nearest=total - facts["cells_measured"] - eq6,
        min_blocks_for_std=MIN_BLOCKS_FOR_STD,
    )
    if model.measured == "full":  # the sweep's cells: every grid cell
        facts.update(sweep_cells=total, sweep_cells_missing=total - facts["cells_measured"])
    elif model.measured == "superposition":  # rest and the cells with one joint moving
        in_sweep = int(((model.cells != index.zero[None, :]).sum(axis=1) <= 1).sum())
        expected = 1 + sum(n - 1 for n in model.grid_shape)
        facts.update(sweep_cells=expected, sweep_cells_missing=expected - in_sweep)
    return facts


def joint_marginals(model) -> list[dict]:
    """Per joint: blocks and measured cells at each of its grid velocities."""
    out = []
    for j, g in enumerate(model.grid):
        blocks = np.bincount(model.cells[:, j], weights=model.cell_counts, minlength=len(g))
        cells = np.bincount(model.cells[:, j], minlength=len(g))
        out.append({"grid": g, "blocks": blocks.astype(np.int64), "cells": cells})
    return out


# --- spectra selection ---------------------------------------------------------------
@dataclass
class SpectraPanel:
    title: str
    curves: list[tuple[str, int]] = field(default_factory=list)  # (label, model row)


def _speed_label(value: float, top: float) -> str:
    return f"{100 * value / top:+.0f} % ({value:.3g})" if top else f"{value:.3g}"


def spectra_panels(model) -> list[SpectraPanel]:
    """Which measured cells the spectra figures show: per joint, rest and the single-joint
    cells nearest 25/50/75/100 % of its max speed where measured; where no single-joint
    cell is (joints that move together), the best-populated cell near each of
    0/25/50/75/100 % mean speed."""
    index = CellIndex.of(model)
    counts = model.cell_counts
    zero = index.zero
    rest_row = int(index.row_of(zero[None, :])[0])
    panels = []
    for j, g in enumerate(model.grid):
        top = float(np.max(np.abs(g)))
        others = ", the others at rest" if model.n_joints > 1 else ""
        panel = SpectraPanel(title=f"{model.joint_names[j]} moving{others}")
        if rest_row >= 0:
            panel.curves.append((f"rest ({counts[rest_row]} blocks)", rest_row))
        for fraction in SPEED_FRACTIONS:
            for sign in (1.0, -1.0):  # the positive side first, else the negative one
                i = int(np.argmin(np.abs(g - sign * fraction * top)))
                if i == zero[j] or abs(abs(g[i]) - fraction * top) > 0.125 * top:
                    continue
                cell = zero.copy()
                cell[j] = i
                row = int(index.row_of(cell[None, :])[0])
                if row >= 0:
                    label = f"{_speed_label(float(g[i]), top)}, {counts[row]} blocks"
                    panel.curves.append((label, row))
                    break
        if any(row != rest_row for _, row in panel.curves):
            panels.append(panel)
    if panels:
        return panels
    tops = np.array([max(float(np.max(np.abs(g))), 1e-300) for g in model.grid])
    speeds = np.column_stack(
        [np.abs(model.grid[j][model.cells[:, j]]) for j in range(model.n_joints)]
    )
    mean_fraction = (speeds / tops[None, :]).mean(axis=1)
    panel = SpectraPanel(title="best-populated cells by mean speed (no single-joint cell measured)")
    for fraction in (0.0,) + SPEED_FRACTIONS:
        near = np.flatnonzero(np.abs(mean_fraction - fraction) <= 0.125)
        if not len(near):
            continue
        row = int(near[np.argmax(counts[near])])
        velocity = ", ".join(
            f"{model.grid[j][model.cells[row, j]]:.3g}" for j in range(model.n_joints)
        )
        panel.curves.append(
            (f"mean {100 * mean_fraction[row]:.0f} %: ({velocity}), {counts[row]} blocks", row)
        )
    return [panel] if panel.curves else []


# --- where a recording's blocks fall -----------------------------------------------------
class BagPlacement:
    """Streams a recording's blocks against a model: the model's framing (band-pass, blocks,
    joint-state matching, sensor range); each block with a joint state goes to the grid
    cell nearest its mean velocity, as the denoiser looks it up. Memory: counts per cell
    visited, per-joint histograms and at most OUTSIDE_POINTS velocities, however long
    the recording."""

    KINDS = ("measured", "eq6", "nearest", "outside")

    def __init__(self, model, *, source: str = ""):
        self.model = model
        self.index = CellIndex.of(model)
        settings = FramerSettings.for_model(
            model, layout="combined", with_steadiness=False, source=source
        )
        self.framer = BlockFramer(settings, model.n_joints)
        self.tally = dict.fromkeys(self.KINDS, 0)
        self.no_joint_state = 0
        self.cell_ids: dict[int, int] = {}  # inside the grid: flat id -> blocks
        self.edges = [_histogram_edges(g) for g in model.grid]
        self.histograms = [np.zeros(len(e) + 1, dtype=np.int64) for e in self.edges]
        self.outside_points = np.zeros((0, model.n_joints))
        self._outside_seen = 0
        self._stride = 1
        self.joint_states = 0

    def push_joint_states(self, stamps_ns: np.ndarray, velocity: np.ndarray) -> None:
        self.joint_states += len(stamps_ns)
        self.framer.push_joint_states(stamps_ns, velocity)
        self._collect()

    def push_sensor(self, stamps_ns: np.ndarray, accel: np.ndarray) -> None:
        self.framer.push_sensor(stamps_ns, accel)
        self._collect()

    def flush(self) -> None:
        self.framer.flush()
        self._collect()

    def _collect(self) -> None:
        for blocks in self.framer.pop_blocks():
            if not blocks.n:
                continue
            have = blocks.status != MISSING
            self.no_joint_state += int((~have).sum())
            if have.any():
                self.add_velocities(blocks.velocity[have])

    def add_velocities(self, velocity: np.ndarray) -> None:
        """Place blocks of these mean joint velocities (B, J)."""
        nearest, outside = nearest_cells(self.model.grid, velocity)
        for j, edges in enumerate(self.edges):
            bins = _histogram_bins(self.model.grid[j], edges, velocity[:, j])
            self.histograms[j] += np.bincount(bins, minlength=len(edges) + 1)
        self.tally["outside"] += int(outside.sum())
        self._keep_outside(velocity[outside])
        inside = nearest[~outside]
        measured = self.index.row_of(inside) >= 0
        eq6 = ~measured & self.index.eq6(inside)
        self.tally["measured"] += int(measured.sum())
        self.tally["eq6"] += int(eq6.sum())
        self.tally["nearest"] += int((~measured & ~eq6).sum())
        ids, n = np.unique(_flat_ids(inside, self.index.shape), return_counts=True)
        for cell_id, count in zip(ids.tolist(), n.tolist()):
            self.cell_ids[cell_id] = self.cell_ids.get(cell_id, 0) + count

    def _keep_outside(self, velocity: np.ndarray) -> None:
        """Every `_stride`-th block beyond the grid; the stride doubles when the kept ones
        reach OUTSIDE_POINTS (an even thinning of a recording of any length)."""
        seen = self._outside_seen + np.arange(len(velocity))
        self._outside_seen += len(velocity)
        self.outside_points = np.concatenate(
            [self.outside_points, velocity[seen % self._stride == 0]]
        )
        while len(self.outside_points) > OUTSIDE_POINTS:
            self._stride *= 2
            self.outside_points = self.outside_points[::2]

    @property
    def blocks(self) -> int:
        return sum(self.tally.values())

    def shares(self) -> dict:
        total = self.blocks
        share = {k: (v / total if total else 0.0) for k, v in self.tally.items()}
        # a superposition model fills every other cell from Eq. 6 by design: those are not
        # outside what it calibrated
        eq6 = 0 if self.model.measured == "superposition" else 1
        return {
            "blocks": total,
            "blocks_no_joint_state": self.no_joint_state,
            **{f"blocks_{k}": v for k, v in self.tally.items()},
            **{f"share_{k}": v for k, v in share.items()},
            "share_unmeasured": share["eq6"] + share["nearest"],
            "blocks_outside_calibrated": eq6 * self.tally["eq6"]
            + self.tally["nearest"]
            + self.tally["outside"],
            "share_outside_calibrated": eq6 * share["eq6"] + share["nearest"] + share["outside"],
        }

    def cell_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """(grid indices (K, J), blocks (K,)) of the cells the recording visited."""
        ids = np.array(sorted(self.cell_ids), dtype=np.int64)
        counts = np.array([self.cell_ids[i] for i in ids.tolist()], dtype=np.int64)
        return np.array(np.unravel_index(ids, self.index.shape)).T.reshape(
            -1, len(self.index.shape)
        ), counts


def _histogram_edges(grid: np.ndarray) -> np.ndarray:
    """Bin edges of a joint's velocity histogram: one bin per grid velocity (half-way
    between grid velocities, the edge cells reaching to `grid_limits`), then bins of the
    edge step beyond, half the grid's span on each side (blocks further out land in the
    two end bins)."""
    g = np.asarray(grid, dtype=np.float64)
    low, high = grid_limits(g)
    low_step, high_step = g[1] - g[0], g[-1] - g[-2]
    extra = max(1, (len(g) - 1) // 2)
    below = low - low_step * np.arange(extra, 0, -1)
    above = high + high_step * np.arange(1, extra + 1)
    return np.concatenate([below, [low], 0.5 * (g[1:] + g[:-1]), [high], above])


def _histogram_bins(grid: np.ndarray, edges: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Bin of each value: 0 below the first edge, len(edges) above the last; a value within
    `grid_limits` is in its grid velocity's bin, as the denoiser sees it."""
    low, high = grid_limits(grid)
    bins = np.searchsorted(edges, values, side="right")
    inside = (values >= low) & (values <= high)
    first = int(np.searchsorted(edges, low, side="right"))  # the first grid velocity's bin
    bins[inside] = np.clip(bins[inside], first, first + len(grid) - 1)
    return bins


def nearest_cells(grid, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The grid cell (B, J) nearest each velocity (B, J), clamped to the grid, and whether
    the velocity lies beyond the grid (B,): the denoiser's look-up rule."""
    velocity = np.atleast_2d(np.asarray(velocity, dtype=np.float64))
    nearest = np.empty(velocity.shape, dtype=np.int64)
    outside = np.zeros(len(velocity), dtype=bool)
    for j, g in enumerate(grid):
        v = velocity[:, j]
        low, high = grid_limits(g)
        outside |= (v < low) | (v > high)
        position = np.interp(v, g, np.arange(len(g), dtype=np.float64))
        lower = np.minimum(np.floor(position).astype(np.int64), len(g) - 2)
        nearest[:, j] = lower + (position - lower >= 0.5)
    return nearest, outside


def place_bag(model, bag: str, *, quiet: bool = True) -> BagPlacement:
    """Stream a bag through BagPlacement (the model's topics, field and joints)."""

    profile = model.robot_profile()
    where = f"{bag}: {profile.sensor_topic}"
    placement = BagPlacement(model, source=where)
    with BagReader(bag) as reader:
        total = reader.total_bytes
    with tqdm(
        total=total, unit="B", unit_scale=True, desc="model show", leave=False, disable=quiet
    ) as bar:
        for piece in iter_recording(
            bag,
            profile=profile,
            ground_truth=False,
            denoised=False,
            commands=False,
            progress=bar.update,
        ):
            placement.push_joint_states(piece.joint_stamps_ns, piece.joint_velocity)
            placement.push_sensor(piece.sensor_stamps_ns, piece.sensor)
    placement.flush()
    placement.input_counts = check_stream(
        placement.framer.stats,
        where,
        joint_states=placement.joint_states,
        joints_where=f"{bag}: {profile.joints_topic}",
    )
    if placement.blocks == 0:
        raise BagError(
            f"{where}: no block with a joint state ({placement.no_joint_state} blocks without); "
            f"are the joints {list(profile.joint_names)} on {profile.joints_topic}?"
        )
    placement.bag = str(bag)
    return placement


# --- summary -------------------------------------------------------------------------
def _fmt_count(n: int) -> str:
    return f"{n:,}".replace(",", " ") if n < 10**15 else f"{n:.3g}"


def summary_lines(model, placement: BagPlacement | None = None) -> list[str]:
    """The short summary printed by the command (the markdown has more)."""
    c = coverage_facts(model)
    lines = [
        model.summary(),
        f"coverage: {c['cells_measured']} of {_fmt_count(c['cells_total'])} cells measured, "
        f"{c['cells_under_min_blocks']} with fewer than {c['min_blocks_for_std']} blocks",
    ]
    learnt = describe_learnt(model)
    if learnt is not None:
        lines.append(_learnt_line(learnt))
    if placement is not None:
        s = placement.shares()
        lines.append(
            f"{placement.bag}: {s['blocks']} blocks, {100 * s['share_outside_calibrated']:.1f} % "
            f"outside the calibrated speeds (on unmeasured cells: "
            f"{100 * s['share_eq6']:.1f} % filled by superposition, Eq. 6, "
            f"{100 * s['share_nearest']:.1f} % from the nearest measured cell; "
            f"{100 * s['share_outside']:.1f} % beyond the grid)"
        )
    return lines


def _learnt_line(learnt: dict) -> str:
    parts = []
    cells = learnt.get("cells")
    if cells is not None:
        parts.append(
            f"{len(cells)} cells of the residual table ({int(learnt['new'].sum())} the "
            f"calibration never measured), {int(learnt['blocks'].sum())} blocks"
        )
    if "harmonic_points" in learnt:
        parts.append(f"harmonic map at {learnt['harmonic_points']} joint speeds")
    if learnt.get("lines_found"):
        parts.append(f"{learnt['lines_found']} lines found beyond the calibrated speeds")
    return f"learnt online (adapt, forgetting time {learnt['forget_s']:g} s): " + ", ".join(parts)


def summary_markdown(
    model, placement: BagPlacement | None, figures: list[str], model_path: str = ""
) -> str:
    c = coverage_facts(model)
    p = model.profile
    rows = [
        f"# Noise model {Path(model_path).name or ''}".rstrip(),
        "",
        f"Robot `{_robot_name(model)}`"
        + (
            f", sensor `{p.sensor_topic}` ({p.sensor_field}), joints on `{p.joints_topic}`"
            if p
            else ""
        )
        + ".",
        "",
        "| | |",
        "|---|---|",
        f"| measured kind | {model.measured} |",
        f"| grid | {' x '.join(str(n) for n in model.grid_shape)} "
        f"({_fmt_count(c['cells_total'])} cells) |",
    ]
    for j, g in enumerate(model.grid):
        step = (g[-1] - g[0]) / (len(g) - 1)
        rows.append(
            f"| joint `{model.joint_names[j]}` | {g[0]:.4g} .. {g[-1]:.4g} in {len(g)} values "
            f"(step {step:.4g}) |"
        )
    rows += [
        f"| cells measured | {c['cells_measured']} of {_fmt_count(c['cells_total'])} "
        f"({100 * c['cells_measured'] / c['cells_total']:.3g} %) |",
        f"| blocks | {c['blocks']} |",
        f"| blocks per measured cell | median {c['median_blocks']:g}, min {c['min_blocks']} |",
        f"| cells under {c['min_blocks_for_std']} blocks (std borrowed) | "
        f"{c['cells_under_min_blocks']} |",
        f"| unmeasured cells filled by Eq. 6 | {_fmt_count(c['cells_eq6'])} |",
        f"| unmeasured cells filled from the nearest measured cell | "
        f"{_fmt_count(c['cells_nearest'])} |",
    ]
    if "sweep_cells" in c:
        rows.append(
            f"| {model.measured} sweep cells without a block | {c['sweep_cells_missing']} of "
            f"{_fmt_count(c['sweep_cells'])} |"
        )
    rows += [
        f"| sample rate | {model.sample_rate_hz:g} Hz |",
        f"| block length / hop | {model.block_length} / {model.hop} samples "
        f"({1e3 * model.block_length / model.sample_rate_hz:.3g} ms / "
        f"{1e3 * model.hop / model.sample_rate_hz:.3g} ms) |",
        f"| band | {model.band_hz[0]:g} - {model.band_hz[1]:g} Hz "
        f"(Butterworth order {model.band_order}) |",
        f"| channels | {', '.join(model.channels)} |",
    ]
    for key, value in model.provenance.items():
        if key != "path" and str(value):
            rows.append(f"| provenance: {key} | {str(value).replace('|', '/')} |")
    rows += _detector_rows(model) + _learnt_rows(model) + _placement_rows(model, placement)
    rows += ["", "Figures: " + ", ".join(f"[{f}]({f})" for f in figures), ""]
    return "\n".join(rows)


def _detector_rows(model) -> list[str]:
    """The contact detector's stored thresholds, and the motion its calibration held
    (beyond it the threshold rises: core.contact.MotionLimits)."""
    rows = [
        f"| detector threshold, {method} | {threshold:.4g} |"
        for method in ("raw", *METHODS)
        if (threshold := stored_threshold(model, method)) is not None
    ]
    limits = motion_limits(model, default_method(model))
    if limits is not None:
        rows += [
            f"| detector: joint `{name}` speeds held | {limits.speed_low[j]:.4g} .. "
            f"{limits.speed_high[j]:.4g} (beyond: threshold x{limits.factor:.3g}) |"
            for j, name in enumerate(model.joint_names)
        ]
        rows.append(f"| detector: largest joint acceleration held | {limits.accel:.4g} /s^2 |")
    return rows


def _learnt_rows(model) -> list[str]:
    """The summary's section on what adaptation learnt online (none: no rows)."""
    learnt = describe_learnt(model)
    if learnt is None:
        return []
    rows = ["", "## Learnt online", "", _learnt_line(learnt) + "."]
    if learnt.get("cells") is not None and len(learnt["cells"]):
        rows += [
            "",
            "The residual table's cells (methods cancel and hybrid) that adaptation "
            "learnt while no contact was detected; a cell the calibration never measured "
            "started from the model's fill there. Those cells replace the table's value "
            "at their grid point.",
            "",
            "| cell (joint velocities) | blocks learnt | calibrated before |",
            "|---|---|---|",
        ]
        order = np.argsort(-learnt["blocks"])[:20]
        for k in order.tolist():
            speeds = ", ".join(
                f"{model.grid[j][i]:.3g}" for j, i in enumerate(learnt["cells"][k].tolist())
            )
            rows.append(
                f"| {speeds} | {int(learnt['blocks'][k])} | {'no' if learnt['new'][k] else 'yes'} |"
            )
        if len(learnt["cells"]) > len(order):
            rows.append(f"| ... {len(learnt['cells']) - len(order)} more | | |")
    return rows


def _placement_rows(model, placement: "BagPlacement | None") -> list[str]:
    """The summary's section on where a recording's blocks fall on the grid."""
    if placement is None:
        return []
    s = placement.shares()
    rows = [
        "",
        f"## Recording `{placement.bag}`",
        "",
        "Blocks framed as the denoiser frames them; each goes to the grid cell nearest its "
        "mean joint velocity.",
        "",
        "| | blocks | share |",
        "|---|---|---|",
        f"| on measured cells | {s['blocks_measured']} | {100 * s['share_measured']:.1f} % |",
        f"| on unmeasured cells, Eq. 6 | {s['blocks_eq6']} | {100 * s['share_eq6']:.1f} % |",
        f"| on unmeasured cells, nearest measured cell | {s['blocks_nearest']} | "
        f"{100 * s['share_nearest']:.1f} % |",
        f"| beyond the grid (edge cells used) | {s['blocks_outside']} | "
        f"{100 * s['share_outside']:.1f} % |",
        "| **outside the calibrated speeds** ("
        + (
            "nearest measured cell + beyond: Eq. 6 is the design of a superposition model"
            if model.measured == "superposition"
            else "unmeasured + beyond"
        )
        + f") | {s['blocks_outside_calibrated']} | "
        f"**{100 * s['share_outside_calibrated']:.1f} %** |",
        f"| without a joint state (not placed) | {s['blocks_no_joint_state']} | |",
        "",
        placement.input_counts,
    ]
    if model.measured == "superposition":
        rows += [
            "",
            "A superposition sweep measures only the cells where at most one joint moves; "
            "every other cell comes from Eq. 6 by design.",
        ]
    return rows


# --- figures ---------------------------------------------------------------------------
def _robot_name(model) -> str:
    return model.profile.name if model.profile is not None else "unnamed robot"


def _velocity_ticks(ax, grid: np.ndarray, axis: str) -> None:
    """About five tick labels in velocity units, one of them at rest."""
    step = max(1, int(round((len(grid) - 1) / 4)))
    zero = int(np.argmin(np.abs(grid)))
    ticks = np.arange(len(grid))[(np.arange(len(grid)) - zero) % step == 0]
    getattr(ax, f"set_{axis}ticks")(ticks, [f"{grid[i]:.3g}" for i in ticks])


def _count_norm(values: np.ndarray):
    """Colour scale of block counts: logarithmic when they span more than a decade."""
    # deferred: matplotlib loads only when a figure is drawn (as in pyplot())
    from matplotlib.colors import LogNorm, Normalize

    low, high = float(np.min(values)), float(np.max(values))
    if high >= 10 * max(low, 1.0):
        return LogNorm(vmin=max(1.0, low), vmax=high)
    return Normalize(vmin=0.0, vmax=max(high, 1.0))


def coverage_figure(model, path: Path) -> None:
    """Which cells the calibration measured, from how many blocks: the grid's map for two
    joints, per joint marginals (and joints moving per cell) for any other number."""
    c = coverage_facts(model)
    title = (
        f"{_robot_name(model)} ({model.measured}): {c['cells_measured']} of "
        f"{_fmt_count(c['cells_total'])} cells measured, {c['blocks']} blocks "
        f"(median {c['median_blocks']:g} per cell)"
    )
    draw = _coverage_map if model.n_joints == 2 else _coverage_marginals
    draw(model, c, CellIndex.of(model), title, path)


def _coverage_map(model, c: dict, index: CellIndex, title: str, path: Path) -> None:
    """Two joints: blocks per measured cell on the grid, the unmeasured cells marked by how
    the model fills them, the cells too thin for a std ringed."""
    # deferred: matplotlib loads only when a figure is drawn (as in pyplot())
    from matplotlib.lines import Line2D

    plt = pyplot()
    thin = model.cell_counts < c["min_blocks_for_std"]
    shape = model.grid_shape
    counts = np.zeros(shape)
    counts[tuple(model.cells.T)] = model.cell_counts
    every = np.indices(shape).reshape(2, -1).T
    unmeasured = every[index.row_of(every) < 0]
    by_eq6 = index.eq6(unmeasured)
    fig, ax = plt.subplots(figsize=(8.5, 7))
    shown = np.ma.masked_where(counts == 0, counts)
    image = ax.imshow(
        shown.T,
        origin="lower",
        cmap="viridis",
        norm=_count_norm(model.cell_counts if len(model.cell_counts) else np.ones(1)),
        aspect="auto",
    )
    ax.set_facecolor("#eeeeee")
    fig.colorbar(image, ax=ax, label="blocks per measured cell")
    ax.scatter(*unmeasured[by_eq6].T, s=6, c="0.55", marker="o", linewidths=0)
    ax.scatter(*unmeasured[~by_eq6].T, s=22, c="tab:red", marker="x", linewidths=1)
    ax.scatter(*model.cells[thin].T, s=60, facecolors="none", edgecolors="tab:orange")
    learnt = describe_learnt(model)
    online = learnt.get("cells") if learnt is not None else None
    if online is not None and len(online):
        ax.scatter(*online.T, s=70, marker="*", c="white", edgecolors="black", linewidths=0.6)
    _velocity_ticks(ax, model.grid[0], "x")
    _velocity_ticks(ax, model.grid[1], "y")
    ax.set_xlabel(model.joint_names[0])
    ax.set_ylabel(model.joint_names[1])
    handles = [
        Line2D([], [], ls="", marker="s", color="tab:green", label="measured (colour: blocks)"),
        Line2D([], [], ls="", marker="o", color="0.55", ms=4, label="not measured: Eq. 6"),
        Line2D([], [], ls="", marker="x", color="tab:red", label="not measured: nearest measured"),
        Line2D(
            [],
            [],
            ls="",
            marker="o",
            mfc="none",
            mec="tab:orange",
            label=f"< {c['min_blocks_for_std']} blocks (std borrowed)",
        ),
    ]
    if online is not None and len(online):
        star = dict(ls="", marker="*", mfc="white", mec="black", ms=10)
        handles.append(Line2D([], [], label="learnt online (residual table)", **star))
    ax.legend(
        handles=handles,
        loc="upper center",
        bbox_to_anchor=(0.5, -0.1),
        ncol=2,
        fontsize=8,
        frameon=False,
    )
    ax.set_title(title, fontsize=10)
    save_figure(fig, path, dpi=100)


def _coverage_marginals(model, c: dict, index: CellIndex, title: str, path: Path) -> None:
    """One joint or three and more: blocks and measured cells at each grid velocity of each
    joint, and how many joints move in the measured cells."""
    fig, axes = _panels(model.n_joints + (1 if model.n_joints > 1 else 0))
    for j, m in enumerate(joint_marginals(model)):
        ax = axes[j]
        x = np.arange(len(m["grid"]))
        ax.bar(x, m["blocks"], color="tab:blue", label="blocks")
        ax.plot(x, m["cells"], "o-", color="tab:orange", ms=3, lw=1, label="cells measured")
        none = m["cells"] == 0
        if none.any():
            ax.plot(x[none], np.zeros(none.sum()), "x", color="tab:red", ms=7, mew=1.5,
                    label="no measured cell", zorder=3)  # fmt: skip
        _count_axes(ax, model, j)
        ax.set_ylim(bottom=-0.4)  # room for the markers at zero
    if len(axes) > model.n_joints:
        ax = axes[model.n_joints]
        moving = (model.cells != index.zero[None, :]).sum(axis=1)
        cells = np.bincount(moving, minlength=model.n_joints + 1)
        blocks = np.bincount(moving, weights=model.cell_counts, minlength=model.n_joints + 1)
        k = np.arange(model.n_joints + 1)
        ax.bar(k - 0.2, cells, width=0.4, color="tab:orange", label="cells measured")
        ax.bar(k + 0.2, blocks, width=0.4, color="tab:blue", label="blocks")
        ax.set_yscale("symlog", linthresh=1)
        ax.set_xticks(k)
        ax.set_xlabel("joints moving in the cell")
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    save_figure(fig, path, dpi=100)


def _panels(n: int) -> tuple:
    """(figure, its n axes) side by side in two columns (one for one panel), the spare hidden."""
    cols = 1 if n == 1 else 2
    rows = math.ceil(n / cols)
    fig, axes = pyplot().subplots(rows, cols, figsize=(6 * cols, 2.6 * rows + 0.8), squeeze=False)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    return fig, list(axes.flat)[:n]


def _count_axes(ax, model, j: int) -> None:
    """A per-joint panel's axes: counts (symlog) over joint j's grid velocities."""
    ax.set_yscale("symlog", linthresh=1)
    ax.set_ylabel("count")
    _velocity_ticks(ax, model.grid[j], "x")
    ax.set_xlabel(f"{model.joint_names[j]} velocity")
    if j == 0:
        ax.legend(fontsize=7, loc="upper left")


def spectra_figure(model, channel: str, panels: list[SpectraPanel], path: Path) -> None:
    plt = pyplot()
    c = model.channels.index(channel)
    freqs = model.freqs_hz
    cols = 1 if len(panels) == 1 else 2
    rows = max(1, math.ceil(len(panels) / cols))
    fig, axes = plt.subplots(
        rows, cols, figsize=(6.5 * cols, 3.3 * rows + 0.8), squeeze=False, sharey=True
    )
    for ax, panel in zip(axes.flat, panels):
        ax.axvspan(*model.band_hz, color="0.92", zorder=0)
        for k, (label, row) in enumerate(panel.curves):
            color = f"C{k}"
            ax.plot(freqs, model.cell_mean[row, c], color=color, lw=1.4, label=label)
            ax.plot(freqs, model.cell_std[row, c], color=color, lw=1.0, ls="--")
        ax.set_title(panel.title, fontsize=9)
        ax.set_xlabel("Hz")
        ax.set_ylabel("|N|")
        ax.set_xlim(0, model.sample_rate_hz / 2)
        ax.legend(fontsize=7, loc="upper right")
    for ax in list(axes.flat)[len(panels) :]:
        ax.set_visible(False)
    fig.suptitle(
        f"{_robot_name(model)}: noise spectra of measured cells, channel {channel}\n"
        f"(mean solid, std dashed; shaded: band {model.band_hz[0]:g}-{model.band_hz[1]:g} Hz)",
        fontsize=10,
    )
    save_figure(fig, path, dpi=100)


def bag_figure(model, placement: BagPlacement, path: Path) -> None:
    """Where the recording's blocks fall against the model's measured cells (a map for two
    joints, per joint histograms else), over the shares bar."""
    s = placement.shares()
    title = (
        f"{Path(placement.bag).name}: {s['blocks']} blocks; outside the calibrated speeds "
        f"{100 * s['share_outside_calibrated']:.1f} % (unmeasured cells "
        f"{100 * s['share_unmeasured']:.1f} %, beyond the grid {100 * s['share_outside']:.1f} %)"
    )
    draw = _bag_map if model.n_joints == 2 else _bag_histograms
    fig, share_ax = draw(model, placement, s)
    _share_bar(share_ax, s)
    fig.suptitle(title, fontsize=9)
    save_figure(fig, path, dpi=100)


def _bag_map(model, placement: BagPlacement, s: dict):
    """Two joints: the recording's blocks per cell, the measured cells outlined, the blocks
    beyond the grid as points; (figure, the axes for the shares bar)."""
    # deferred: matplotlib loads only when a figure is drawn (as in pyplot())
    from matplotlib.colors import LogNorm
    from matplotlib.patches import Rectangle

    plt = pyplot()
    cells, counts = placement.cell_counts()
    fig, (ax, share_ax) = plt.subplots(
        2, 1, figsize=(8.5, 8.2), gridspec_kw={"height_ratios": [7, 0.45]}
    )
    g0, g1 = model.grid
    e0, e1 = _cell_edges(g0), _cell_edges(g1)
    grid_counts = np.zeros(model.grid_shape)
    if len(cells):
        grid_counts[tuple(cells.T)] = counts
    shown = np.ma.masked_where(grid_counts == 0, grid_counts)
    mesh = ax.pcolormesh(
        e0,
        e1,
        shown.T,
        cmap="magma_r",
        norm=LogNorm(vmin=1, vmax=max(2, grid_counts.max())),
    )
    fig.colorbar(mesh, ax=ax, label="recording blocks per cell")
    for i0, i1 in model.cells:
        ax.add_patch(
            Rectangle(
                (e0[i0], e1[i1]),
                e0[i0 + 1] - e0[i0],
                e1[i1 + 1] - e1[i1],
                fill=False,
                ec="tab:blue",
                lw=0.8,
            )
        )
    ax.add_patch(
        Rectangle(
            (e0[0], e1[0]), e0[-1] - e0[0], e1[-1] - e1[0], fill=False, ec="k", lw=1.2, ls="--"
        )
    )
    if len(placement.outside_points):
        ax.scatter(*placement.outside_points.T, s=10, c="tab:red", alpha=0.5, linewidths=0)
    ax.set_xlabel(model.joint_names[0])
    ax.set_ylabel(model.joint_names[1])
    ax.plot([], [], "s", mfc="none", mec="tab:blue", label="measured cell")
    ax.plot([], [], "--", color="k", label="grid edge")
    ax.plot([], [], ".", color="tab:red", label=f"blocks beyond the grid ({s['blocks_outside']})")
    ax.legend(fontsize=8, loc="upper left", framealpha=0.85)
    # the view: the grid and the blocks beyond it, with a margin (pcolormesh would pin
    # the limits to the grid's edges)
    low = np.array([e0[0], e1[0]])
    high = np.array([e0[-1], e1[-1]])
    if len(placement.outside_points):
        low = np.minimum(low, placement.outside_points.min(axis=0))
        high = np.maximum(high, placement.outside_points.max(axis=0))
    pad = 0.04 * (high - low)
    ax.set_xlim(low[0] - pad[0], high[0] + pad[0])
    ax.set_ylim(low[1] - pad[1], high[1] + pad[1])
    return fig, share_ax


def _bag_histograms(model, placement: BagPlacement, s: dict):
    """One joint or three and more: a histogram of the recording's blocks per joint;
    (figure, the axes for the shares bar)."""
    plt = pyplot()
    n = model.n_joints
    cols = 1 if n == 1 else 2
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(
        rows + 1,
        cols,
        figsize=(6 * cols, 2.5 * rows + 1.6),
        squeeze=False,
        gridspec_kw={"height_ratios": [2.5] * rows + [0.45]},
    )
    marginals = joint_marginals(model)
    for j in range(n):
        _bag_joint_panel(axes[j // cols, j % cols], model, placement, j, marginals[j]["cells"])
    for k in range(n, rows * cols):
        axes[k // cols, k % cols].set_visible(False)
    for k in range(1, cols):
        axes[rows, k].set_visible(False)
    share_ax = axes[rows, 0]
    return fig, share_ax


def _bag_joint_panel(
    ax, model, placement: BagPlacement, j: int, cells_measured: np.ndarray
) -> None:
    """Joint j's histogram of the recording's block velocities against the grid (shaded)
    and the velocities with measured cells."""
    edges = placement.edges[j]
    hist = placement.histograms[j]
    g = model.grid[j]
    # bins between the edges; the two end bins also hold everything beyond them
    counts_in_bins = hist[1:-1].copy()
    counts_in_bins[0] += hist[0]
    counts_in_bins[-1] += hist[-1]
    centres = 0.5 * (edges[1:] + edges[:-1])
    beyond = (centres < g[0]) | (centres > g[-1])
    widths = np.diff(edges)
    for mask, color, label in (
        (~beyond, "tab:purple", "recording blocks"),
        (beyond, "tab:red", "beyond the grid (end bins: and further)"),
    ):
        ax.bar(
            edges[:-1][mask],
            counts_in_bins[mask],
            width=widths[mask],
            align="edge",
            color=color,
            alpha=0.85,
            label=label,
        )
    used = np.flatnonzero(counts_in_bins)
    low = min(g[0], edges[used[0]]) if len(used) else g[0]
    high = max(g[-1], edges[used[-1] + 1]) if len(used) else g[-1]
    pad = 0.05 * (high - low)
    ax.set_xlim(low - pad, high + pad)
    ax.axvspan(g[0], g[-1], color="0.93", zorder=0)
    measured = g[cells_measured > 0]
    ax.plot(
        measured,
        np.zeros(len(measured)),
        "|",
        color="tab:blue",
        ms=14,
        mew=2,
        label="velocities with measured cells",
    )
    ax.set_yscale("symlog", linthresh=1)
    ax.set_xlabel(f"{model.joint_names[j]} velocity (shaded: the grid)")
    ax.set_ylabel("blocks")
    if j == 0:
        ax.legend(fontsize=7, loc="upper left")


def _cell_edges(grid: np.ndarray) -> np.ndarray:
    g = np.asarray(grid, dtype=np.float64)
    mids = 0.5 * (g[1:] + g[:-1])
    return np.concatenate([[g[0] - (mids[0] - g[0])], mids, [g[-1] + (g[-1] - mids[-1])]])


def _share_bar(ax, shares: dict) -> None:
    parts = (
        ("measured", "tab:blue", "measured cells"),
        ("eq6", "0.6", "Eq. 6"),
        ("nearest", "tab:orange", "nearest measured"),
        ("outside", "tab:red", "beyond the grid"),
    )
    left = 0.0
    for key, color, label in parts:
        value = shares[f"share_{key}"]
        ax.barh(0, value, left=left, color=color, label=f"{label} {100 * value:.1f} %")
        left += value
    ax.set_xlim(0, 1)
    ax.set_yticks([])
    ax.set_title("share of the recording's blocks", fontsize=8)
    ax.legend(fontsize=7, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.5), frameon=False)


def online_figure(model, learnt: dict, path: Path) -> None:
    """The residual table's cells learnt online: per joint, at each of its grid
    velocities, the blocks learnt and the cells learnt (those never calibrated apart)."""
    cells, blocks, new = learnt["cells"], learnt["blocks"], learnt["new"]
    fig, axes = _panels(model.n_joints)
    for j, g in enumerate(model.grid):
        ax = axes[j]
        x = np.arange(len(g))
        ax.bar(x, np.bincount(cells[:, j], weights=blocks, minlength=len(g)), color="tab:green",
               label="blocks learnt online")  # fmt: skip
        ax.plot(x, np.bincount(cells[new, j], minlength=len(g)), "^-", color="tab:red", ms=4,
                lw=1, label="cells never calibrated, learnt")  # fmt: skip
        ax.plot(x, np.bincount(cells[~new, j], minlength=len(g)), "o-", color="tab:blue", ms=3,
                lw=1, label="calibrated cells, learnt further")  # fmt: skip
        _count_axes(ax, model, j)
    fig.suptitle(f"{_robot_name(model)}: {_learnt_line(learnt)}", fontsize=9)
    save_figure(fig, path, dpi=100)


def write_views(
    model, directory: Path, *, placement: BagPlacement | None = None, model_path: str = ""
) -> list[str]:
    """Write every view and summary.md into `directory`; the names written."""
    directory = Path(directory)
    written = [COVERAGE_PNG]
    coverage_figure(model, directory / COVERAGE_PNG)
    learnt = describe_learnt(model)
    if learnt is not None and learnt.get("cells") is not None and len(learnt["cells"]):
        online_figure(model, learnt, directory / ONLINE_PNG)
        written.append(ONLINE_PNG)
    panels = spectra_panels(model)
    for channel in model.channels:
        spectra_figure(model, channel, panels, directory / spectra_png(channel))
        written.append(spectra_png(channel))
    if placement is not None:
        bag_figure(model, placement, directory / BAG_PNG)
        written.append(BAG_PNG)
    (directory / SUMMARY).write_text(summary_markdown(model, placement, written, model_path))
    return written + [SUMMARY]
