"""`egovib model show`: coverage, spectra and where a recording falls, for any model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import robots
from matplotlib import image

from egovib_ros.bag import Recording, write_recording
from egovib_ros.bag.calibrate import calibrate_bags
from egovib_ros.cli import main
from egovib_ros.core.methods import motion_limits, stored_threshold
from egovib_ros.core.noise_model import NoiseModel, sweep_cells
from egovib_ros.core.stream import CalibrationStats
from egovib_ros.outputs import MARKER
from egovib_ros.robot import default_profile, load_profile
from egovib_ros.viz.model_show import (
    CellIndex,
    coverage_facts,
    joint_marginals,
    nearest_cells,
    place_bag,
    spectra_panels,
    summary_lines,
)

REPO = Path(__file__).resolve().parents[1]
VIEWS = {"coverage.png", "spectra_combined.png", "spectra_x.png", "spectra_y.png", "spectra_z.png"}


def _show(model, out, *extra) -> int:
    return main(["model", "show", str(model), "--out", str(out), "--quiet", *map(str, extra)])


def _readable_png(path: Path) -> None:
    picture = image.imread(path)
    assert picture.ndim == 3 and min(picture.shape[:2]) >= 300, picture.shape
    assert picture[..., :3].std() > 0.05  # not a blank page


def _row(text: str, name: str) -> str:
    """The value columns of a summary table row, joined by " | "."""
    line = next(line for line in text.splitlines() if line.startswith(f"| {name} |"))
    return " | ".join(part.strip() for part in line.split("|")[2:-1]).strip(" |")


@pytest.fixture(scope="module")
def pr2_bag_beyond(tmp_path_factory) -> Path:
    """A PR2 recording in three equal parts: a measured single-joint cell (wrist at half
    speed), a cell where both joints move (not measured by a superposition sweep: Eq. 6),
    and the wrist at 1.5 times its max speed (beyond the grid)."""
    profile = default_profile()
    fs, seconds = 3000, 9
    stamps = 1_000_000_000 + (np.arange(fs * seconds) * 1e9 / fs).astype(np.int64)
    joint_stamps = stamps[::3]
    velocity = np.zeros((len(joint_stamps), 2))
    third = len(joint_stamps) // 3
    velocity[:third] = [1.5, 0.0]
    velocity[third : 2 * third] = [1.5, 0.02]
    velocity[2 * third :] = [4.5, 0.0]
    rec = Recording(
        sensor_stamps_ns=stamps,
        sensor=np.random.default_rng(0).normal(size=(len(stamps), 3)),
        joint_stamps_ns=joint_stamps,
        joint_position=np.cumsum(velocity, axis=0) / 1000.0,
        joint_velocity=velocity,
        joint_names=profile.joint_names,
    )
    path = tmp_path_factory.mktemp("pr2") / "beyond"
    write_recording(path, rec, profile=profile)
    return path


@pytest.fixture(scope="module")
def quadcopter_model(tmp_path_factory) -> tuple[Path, CalibrationStats]:
    """Free-motion model of the shipped quadcopter flight (its own profile)."""
    profile = load_profile(REPO / "config" / "robots" / "quadcopter.yaml")
    model, stats, _ = calibrate_bags([REPO / "bags" / "quadcopter_ar8"], profile=profile)
    path = tmp_path_factory.mktemp("quad") / "quadcopter.npz"
    model.save(path)
    return path, stats


def test_pr2_superposition_model_every_view_and_its_numbers(sim_model_path, tmp_path):
    out = tmp_path / "show"
    assert _show(sim_model_path, out) == 0
    assert {p.name for p in out.iterdir()} == VIEWS | {"summary.md", MARKER}
    for name in VIEWS:
        _readable_png(out / name)
    model = NoiseModel.load(sim_model_path)
    c = model.coverage()
    text = (out / "summary.md").read_text()
    assert _row(text, "measured kind") == "superposition"
    assert _row(text, "grid") == "21 x 21 (441 cells)"
    assert _row(text, "cells measured") == "41 of 441 (9.3 %)"
    assert _row(text, "blocks") == str(c["blocks"])
    assert _row(text, "blocks per measured cell") == (
        f"median {c['median_blocks']:g}, min {c['min_blocks']}"
    )
    assert _row(text, "cells under 5 blocks (std borrowed)") == str(c["cells_under_min_blocks"])
    assert _row(text, "unmeasured cells filled by Eq. 6") == "400"
    assert _row(text, "unmeasured cells filled from the nearest measured cell") == "0"
    assert _row(text, "superposition sweep cells without a block") == "0 of 41"
    assert _row(text, "sample rate") == "3000 Hz"
    assert _row(text, "block length / hop") == "64 / 32 samples (21.3 ms / 10.7 ms)"
    assert _row(text, "band") == "150 - 750 Hz (Butterworth order 4)"
    assert _row(text, "provenance: source") == "test sweep"
    # Fig. 3: per joint, rest and four speeds, all single-joint cells
    panels = spectra_panels(model)
    assert [p.title.split()[0] for p in panels] == list(model.joint_names)
    zero = np.array(model.zero_index())
    for j, panel in enumerate(panels):
        assert panel.curves[0][0].startswith("rest") and len(panel.curves) == 5
        cells = model.cells[[row for _, row in panel.curves]]
        assert np.all(np.delete(cells, j, axis=1) == np.delete(zero, j))
        speeds = np.abs(model.grid[j][cells[1:, j]]) / model.grid[j].max()
        np.testing.assert_allclose(speeds, [0.2, 0.5, 0.7, 1.0])  # nearest 25/50/75/100 %


def test_pr2_recording_beyond_the_calibration_is_counted(sim_model_path, pr2_bag_beyond, tmp_path):
    out = tmp_path / "show"
    assert _show(sim_model_path, out, "--bag", pr2_bag_beyond) == 0
    assert {p.name for p in out.iterdir()} == VIEWS | {"bag.png", "summary.md", MARKER}
    _readable_png(out / "bag.png")
    model = NoiseModel.load(sim_model_path)
    placement = place_bag(model, pr2_bag_beyond)
    s = placement.shares()
    # a third each, but for the few blocks that straddle a change of speed
    assert s["blocks_no_joint_state"] == 0 and s["blocks_nearest"] == 0
    for key in ("measured", "eq6", "outside"):
        assert abs(s[f"share_{key}"] - 1 / 3) < 3 / s["blocks"], (key, s)
    # a superposition model fills the cell where both joints move from Eq. 6 by design: only
    # the third beyond the grid is outside what it calibrated (all of Eq. 6's third was
    # counted too, and said in bold, for a model whose every such cell is filled so)
    assert model.measured == "superposition"
    assert abs(s["share_outside_calibrated"] - 1 / 3) < 3 / s["blocks"]
    assert s["blocks_outside_calibrated"] == s["blocks_outside"]
    assert s["blocks"] == placement.framer.stats.blocks > 800  # every block of the recording
    text = (out / "summary.md").read_text()
    assert _row(text, "beyond the grid (edge cells used)") == (
        f"{s['blocks_outside']} | {100 * s['share_outside']:.1f} %"
    )
    assert f"**{100 * s['share_outside_calibrated']:.1f} %**" in text
    assert "Eq. 6 is the design of a superposition model" in text
    # the command's summary line says what fills the unmeasured cells
    line = summary_lines(model, placement)[-1]
    assert f"{100 * s['share_outside_calibrated']:.1f} % outside the calibrated speeds" in line
    assert f"{100 * s['share_eq6']:.1f} % filled by superposition, Eq. 6" in line


def test_fill_rules_and_lookups_follow_the_noise_model():
    """Which unmeasured cells Eq. 6 fills, and which blocks land on measured cells or
    beyond the grid, as the model itself decides (a free model with gaps)."""
    p = robots.profile(3, rate_hz=1000.0, steps=3)  # 7 x 7 x 4 cells
    rng = np.random.default_rng(1)
    every = np.indices(p.grid_shape).reshape(3, -1).T
    axis = sweep_cells(p.grid(), "superposition")
    rest = np.array([[int(np.argmin(np.abs(g))) for g in p.grid()]])  # Eq. 6 needs it
    cells = np.unique(np.vstack([axis[rng.random(len(axis)) < 0.6], rest, every[::5]]), axis=0)
    bins = p.block_length // 2 + 1
    mean = rng.uniform(0.1, 1.0, (len(cells), 4, bins))
    model = NoiseModel(
        grid=p.grid(),
        joint_names=p.joint_names,
        cells=cells,
        mean=mean,
        std=0.1 * mean,
        counts=rng.integers(1, 40, len(cells)),
        sample_rate_hz=p.rate_hz,
        block_length=p.block_length,
        hop=p.hop,
        band_hz=p.band_hz,
        measured="free",
        profile=p,
    )
    index = CellIndex.of(model)
    unmeasured = every[index.row_of(every) < 0]
    by_eq6 = index.eq6(unmeasured)
    np.testing.assert_array_equal(by_eq6, model._superposable(unmeasured))
    facts = coverage_facts(model)
    assert facts["cells_eq6"] == by_eq6.sum() > 0
    assert facts["cells_nearest"] == len(unmeasured) - by_eq6.sum() > 0
    top = np.array(p.max_speed)
    velocity = rng.uniform(-1.3, 1.3, (3000, 3)) * top
    velocity[:, 2] = rng.uniform(-0.3, 1.3, 3000) * top[2]  # one-way joint
    velocity[:10] = np.array([g[-1] for g in p.grid()])  # exactly on the grid's corner
    nearest, outside = nearest_cells(model.grid, velocity)
    _, model_outside, model_measured = model.lookup(velocity)
    np.testing.assert_array_equal(outside, model_outside)
    np.testing.assert_array_equal(index.row_of(nearest) >= 0, model_measured)
    marginals = joint_marginals(model)
    assert all(m["blocks"].sum() == model.cell_counts.sum() for m in marginals)
    assert all(m["cells"].sum() == len(cells) for m in marginals)


def test_free_motion_quadcopter_model_and_its_own_flight(quadcopter_model, tmp_path):
    path, stats = quadcopter_model
    out = tmp_path / "show"
    flight = REPO / "bags" / "quadcopter_ar8"
    assert _show(path, out, "--bag", flight) == 0
    for name in VIEWS | {"bag.png"}:
        _readable_png(out / name)
    model = NoiseModel.load(path)
    assert model.measured == "free" and model.grid_shape == (11, 11, 11, 11)
    text = (out / "summary.md").read_text()
    c = model.coverage()
    assert _row(text, "grid") == "11 x 11 x 11 x 11 (14 641 cells)"
    assert _row(text, "cells measured").startswith(f"{c['cells_measured']} of 14 641 (")
    assert _row(text, "blocks") == str(stats.blocks_used) == str(c["blocks"])
    # motors move together: no single-motor cell, the best-populated cells by mean speed
    (panel,) = spectra_panels(model)
    assert panel.title.startswith("best-populated")
    assert panel.curves[0][0].startswith("mean 0 %: (0, 0, 0, 0)")
    rows = [row for _, row in panel.curves]
    assert len(rows) >= 3 and len(set(rows)) == len(rows)
    placement = place_bag(model, flight)
    s = placement.shares()
    # the calibration's blocks are this flight's: all placed, nearly all on measured cells
    assert s["blocks"] + s["blocks_no_joint_state"] == stats.blocks
    assert s["share_measured"] > 0.9
    assert s["blocks_measured"] + s["blocks_outside"] >= c["blocks"]
    assert s["blocks_eq6"] + s["blocks_nearest"] + s["blocks_outside"] > 0
    assert (
        _row(text, "on measured cells")
        == f"{s['blocks_measured']} | {100 * s['share_measured']:.1f} %"
    )


def test_eight_joint_model_is_shown_from_its_sparse_cells(tmp_path):
    p = robots.profile(8, rate_hz=1000.0, bidirectional=(True,) * 8, field="linear_acceleration")
    rng = np.random.default_rng(2)
    axis = sweep_cells(p.grid(), "superposition")  # 161 of 21^8 = 3.8e10 cells
    several = rng.integers(0, 21, (100, 8))
    cells = np.unique(np.vstack([axis, several]), axis=0)
    moving = (cells != 10).sum(axis=1)
    bins = p.block_length // 2 + 1
    mean = rng.uniform(0.1, 1.0, (len(cells), 4, bins)) * (1 + moving)[:, None, None]
    model = NoiseModel(
        grid=p.grid(),
        joint_names=p.joint_names,
        cells=cells,
        mean=mean,
        std=0.2 * mean,
        counts=rng.integers(1, 60, len(cells)),
        sample_rate_hz=p.rate_hz,
        block_length=p.block_length,
        hop=p.hop,
        band_hz=p.band_hz,
        measured="free",
        profile=p,
    )
    path = tmp_path / "eight.npz"
    model.save(path)
    bag = tmp_path / "eight_bag"
    write_recording(
        bag,
        robots.as_recording(p, robots.recording(p, 5.0, seed=8, joint_rate_hz=250.0)),
        profile=p,
    )
    out = tmp_path / "show"
    assert _show(path, out, "--bag", bag) == 0
    for name in VIEWS | {"bag.png"}:
        _readable_png(out / name)
    text = (out / "summary.md").read_text()
    assert _row(text, "cells measured").startswith(f"{len(cells)} of 37 822 859 361 (")
    facts = coverage_facts(model)
    # every single-joint cell and rest measured: Eq. 6 fills every other cell
    assert facts["cells_eq6"] == 21**8 - len(cells) and facts["cells_nearest"] == 0
    assert _row(text, "unmeasured cells filled by Eq. 6") == f"{21**8 - len(cells):,}".replace(
        ",", " "
    )
    assert len(spectra_panels(model)) == 8
    s = place_bag(NoiseModel.load(path), bag).shares()
    # free motion within 0.9 of max speed: inside the grid, mostly on cells Eq. 6 fills
    assert s["blocks"] > 100 and s["blocks_outside"] == 0 and s["blocks_nearest"] == 0
    assert s["share_eq6"] > 0.9


def test_bad_input_is_one_line_exit_2_and_nothing_written(
    quadcopter_model, sim_model_path, tmp_path, capsys
):
    out = tmp_path / "show"
    notes = tmp_path / "notes.txt"
    notes.write_text("not a model\n")
    assert _show(notes, out) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"egovib: error: {notes}: not a readable noise-model") and "\n" not in err
    pr2_bag = REPO / "bags" / "sim_motion_10s"
    assert _show(quadcopter_model[0], out, "--bag", pr2_bag) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        f"egovib: error: {pr2_bag}: missing topic /imu/data_raw (its Imu topics: "
        "/accelerometer/contact, /accelerometer/ego, /accelerometer/raw: the profile of another "
        "robot?)"
    )
    assert not out.exists() and not list(tmp_path.glob(".show*"))
    # outputs: never replaced without --force, never replaced if not ours (refused before
    # any work)
    out.mkdir()
    assert _show(sim_model_path, out) == 2
    assert "already exists (use --force to replace it)" in capsys.readouterr().err
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "mine.txt").write_text("keep me")
    assert _show(sim_model_path, foreign, "--force") == 2
    assert "is not an egovib output" in capsys.readouterr().err
    assert [p.name for p in foreign.iterdir()] == ["mine.txt"]


def test_the_detectors_thresholds_and_the_motion_they_hold_are_shown(sim_bags_model, tmp_path):
    """A model `egovib calibrate` made: its detection thresholds per method, and for the
    default method the speeds and acceleration its calibration held (beyond them the
    threshold rises by the factor shown)."""
    out = tmp_path / "show"
    assert _show(sim_bags_model, out) == 0
    text = (out / "summary.md").read_text()
    model = NoiseModel.load(sim_bags_model)
    for method in ("raw", "paper", "hybrid"):
        assert _row(text, f"detector threshold, {method}") == (
            f"{stored_threshold(model, method):.4g}"
        )
    limits = motion_limits(model, "hybrid")
    name = model.joint_names[0]
    assert _row(text, f"detector: joint `{name}` speeds held") == (
        f"{limits.speed_low[0]:.4g} .. {limits.speed_high[0]:.4g} "
        f"(beyond: threshold x{limits.factor:.3g})"
    )
    assert _row(text, "detector: largest joint acceleration held") == f"{limits.accel:.4g} /s^2"
