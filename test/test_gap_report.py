"""gap.report: report.json, report.md and the figures of a known diagnosis (a synthetic block
table with a position effect, test/gaptables.py): the numbers are the diagnosis's, gap^2
adds up over bins, cells and covariate bins, the position breakdown shows the generated
gain, and report.md opens with the advice, then where, which and how far."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from gaptables import synthetic_table

from egovib_ros.gap.advice import first_lines
from egovib_ros.gap.diagnose import DiagnosisOptions, diagnose
from egovib_ros.gap.report import (
    SCHEMA,
    build_report,
    describe_shape,
    make_figures,
    render_markdown,
)

FIGURES = {"where: frequency x velocity cell": "where_frequency_velocity.png"}


@pytest.fixture(scope="module")
def position():
    """Diagnosis of a wrist gain 1 + 0.4 cos(angle - 0.7) (the model is otherwise exact);
    drift, whose interleaved second look costs most, left out."""
    options = DiagnosisOptions(effects=("position", "coupling", "acceleration", "timing"))
    diag = diagnose(synthetic_table("position", 0.4, seed=5, duration_s=30.0), options)
    assert diag.verdict == "position"
    return diag


def report_of(diag) -> dict:
    return build_report(
        diag, model_path="model.npz", real_path="real.bag", figures=FIGURES, runtime_s=1.23456
    )


def test_report_json_holds_the_diagnosis(position):
    report = report_of(position)
    assert report["schema"] == SCHEMA and report["metric"]["unit"] == "dB"
    assert report["gap"] == pytest.approx(
        {
            "sim_as_is": position.gaps["sim_as_is"],
            "after_refit": position.gaps["refit"],
            "after_effect": position.gaps["position"],
            "floor": position.floor,
        },
        abs=1e-4,
    )
    assert [c["effect"] for c in report["candidates"]] == [c["effect"] for c in position.candidates]
    for c in report["candidates"]:
        assert c["heldout_gap"] == pytest.approx(position.gaps[c["effect"]], abs=1e-4)
        assert c["shape_summary"] == describe_shape(c["shape"])
    assert report["verdict"]["effect"] == "position"
    assert report["added_effect"]["effect"] == "position"
    fitted = position.models["position"].parameters
    assert report["added_effect"]["parameters"]["wrist_roll"] == fitted["wrist_roll"]
    assert report["blocks"] == {
        "total": position.table.n_blocks,
        "contact_excluded": int(position.table.contact.sum()),
        "train": int(position.train.sum()),
        "heldout": len(position.heldout_rows),
        "heldout_windows": position.windows.n_windows,
    }
    assert report["inputs"] == {"model": "model.npz", "real": "real.bag"}
    assert report["figures"] == FIGURES and report["runtime_s"] == 1.23
    assert f"({position.window_blocks} consecutive blocks" in report["metric"]["definition"]
    # strict JSON: no NaN or infinity anywhere (non-finite numbers are written as null)
    assert json.loads(json.dumps(report, allow_nan=False)) == json.loads(json.dumps(report))


def test_gap_squared_adds_up_over_bins_cells_and_covariate_bins(position):
    report = report_of(position)
    where, gap = report["where"], report["gap"]
    n_bins = len(position.table.freqs_hz)
    assert len(where["frequency_hz"]) == n_bins
    shares = [f["share_of_gap2_sim_as_is"] for f in where["frequency_hz"]]
    assert sum(shares) == pytest.approx(1.0, abs=n_bins * 1e-4)
    cells = where["velocity_cells"]
    assert sum(c["gap2_share_sim_as_is_db2"] for c in cells) == pytest.approx(
        gap["sim_as_is"] ** 2, rel=1e-3
    )
    assert sum(c["windows"] for c in cells) == position.windows.n_windows
    assert [c["gap2_share_sim_as_is_db2"] for c in cells] == sorted(
        (c["gap2_share_sim_as_is_db2"] for c in cells), reverse=True
    )
    for name, cov in where["covariates"].items():
        if name == "stream_lag":
            continue
        assert sum(cov["gap2_share_after_refit_db2"]) == pytest.approx(
            gap["after_refit"] ** 2, rel=1e-3
        ), name
        assert sum(cov["blocks"]) == len(position.heldout_rows), name
    ranked = [r["share_of_gap2"] for r in report["ranked_regions"]]
    assert ranked == sorted(ranked, reverse=True) and 0.0 < sum(ranked) <= 1.0 + 1e-3


def test_the_position_breakdown_shows_the_generated_gain(position):
    """Held-out bias after the velocity-only refit, per bin of the wrist angle: the generated
    20 log10(1 + 0.4 cos(angle - 0.7)) dB (plus a level), louder at 0.7 rad than opposite."""
    wrist = report_of(position)["where"]["covariates"]["position:wrist_roll"]
    edges = np.asarray(wrist["bin_edges"])
    assert wrist["unit"] == "rad (mod 2pi)"
    np.testing.assert_allclose(edges, np.linspace(0.0, 2 * np.pi, 9), atol=1e-4)
    centre = 0.5 * (edges[1:] + edges[:-1])
    generated = 20.0 * np.log10(1.0 + 0.4 * np.cos(centre - 0.7))
    bias = np.asarray(wrist["bias_db_after_refit"])
    slope = np.polyfit(generated, bias, 1)[0]
    assert np.corrcoef(generated, bias)[0, 1] > 0.95
    assert slope == pytest.approx(1.0, abs=0.3)
    gripper = report_of(position)["where"]["covariates"]["position:gripper"]
    assert wrist["spread_db_after_refit"] > gripper["spread_db_after_refit"] + 2.0


def test_report_md_opens_with_the_advice_then_where_which_how_far(position):
    report = report_of(position)
    md = render_markdown(report)
    lines = md.splitlines()
    advice = first_lines(report["advice"])
    assert lines[0] == "# Sim-to-real gap report" and lines[1] == ""
    assert lines[2 : 2 + len(advice)] == advice
    where, which, how_far = lines[3 + len(advice) : 6 + len(advice)]
    gap = report["gap"]
    assert where.startswith("**Where:** on held-out real data the simulator's noise model is off")
    assert f"**{gap['sim_as_is']:.2f} dB** (floor {gap['floor']:.2f} dB" in where
    # the covariate the refit leaves most spread over is named
    spreads = {
        k: v["spread_db_after_refit"]
        for k, v in report["where"]["covariates"].items()
        if k != "stream_lag"
    }
    assert f"varies most with {max(spreads, key=spreads.get)} " in where
    assert which.startswith("**Which:** the unmodelled effect is **`position`**")
    shape = next(c for c in report["candidates"] if c["effect"] == "position")["shape_summary"]
    assert f"Fitted shape: {shape}." in which
    assert "interleaved" not in which
    # an effect decided on interleaved folds (a drift) says so beside its blocked reduction
    for c in report["candidates"]:
        if c["effect"] == "position":
            c["decided_by"] = "interleaved"
    which = render_markdown(report).splitlines()[4 + len(advice)]
    assert "baseline on blocked folds; decided on interleaved ones, where a trend" in which
    assert how_far.startswith(f"**How far:** held-out gap {gap['sim_as_is']:.2f} dB (sim as-is)")
    assert f"**{gap['after_effect']:.2f} dB** (refit + position)" in how_far
    assert lines[7 + len(advice)] == f"![{next(iter(FIGURES))}]({next(iter(FIGURES.values()))})"
    # one table row per candidate, in the report's order
    rows = [line for line in lines if line.startswith("| ") and not line.startswith("| effect")]
    assert [row.split(" | ")[0][2:] for row in rows] == [c["effect"] for c in report["candidates"]]
    blocks = report["blocks"]
    assert (
        f"Blocks: {blocks['total']} in all, {blocks['contact_excluded']} set aside as "
        f"contact-like, {blocks['train']} to fit, {blocks['heldout']} held out in "
        f"{blocks['heldout_windows']} windows." in md
    )
    assert md.endswith("\n")


def test_a_joint_named_roll_in_any_case_is_an_angle_for_the_model_and_the_report(position):
    """One rule, case-insensitive: a joint named roll is an angle (the report bins it by
    angle whatever its travel; the model fits its harmonics once it has turned a
    revolution in training, over its travel before that)."""
    from egovib_ros.gap.effects import angle_joints, fit_scales
    from egovib_ros.gap.report import covariate_series

    table = position.table
    names = ("R_WRIST_ROLL", *table.joint_names[1:])
    renamed = dataclasses.replace(position, table=dataclasses.replace(table, joint_names=names))
    quiet = dataclasses.replace(
        renamed.table,
        position=np.zeros_like(table.position),  # no travel: the name decides
    )
    assert angle_joints(names, quiet.position)[0]
    assert covariate_series(dataclasses.replace(renamed, table=quiet))["position:R_WRIST_ROLL"][2]
    everywhere = np.ones(table.n_blocks, bool)
    assert not fit_scales(quiet, everywhere).periodic[0]  # no travel: hats, not harmonics
    turned = quiet.position.copy()
    turned[:, 0] = np.linspace(0.0, 7.0, table.n_blocks)  # a whole turn: its harmonics
    assert fit_scales(dataclasses.replace(quiet, position=turned), everywhere).periodic[0]


def test_no_effect_and_a_model_from_a_recording_are_said_so(position):
    none = dataclasses.replace(
        position,
        verdict="none",
        confidence=0.5,
        effects=[],
        effect_models=[],
        gaps={**position.gaps, "combined": position.gaps["refit"]},
    )
    report = report_of(none)
    assert report["verdict"]["effects"] == []
    assert report["gap"]["after_effect"] == report["gap"]["after_refit"]
    assert report["added_effect"] == {"effect": "none", "parameters": {}}
    report["inputs"]["model_kind"] = "recording"
    md = render_markdown(report)
    best = report["candidates"][0]
    assert "**Which:** **no effect** (`none`)" in md
    # the best candidate with why it is not named (once "best: X, +0.000 dB, p = 0.0037",
    # a significant-looking p beside no reduction, and nothing said of the rule)
    assert f"(the best, `{best['effect']}`: held-out reduction {best['reduction']:+.3f} dB" in md
    assert "an effect is named only where p < 0.05/" in md
    assert "on held-out real data the noise model is off by" in md
    assert "the simulator's noise model" not in md
    assert "(refit + none)" in md


def known_shapes() -> dict[str, tuple[dict, str]]:
    """name -> (a fitted shape made by hand, the sentence it reads as)."""
    angle = np.linspace(0.0, 2 * np.pi, 73)
    t = np.arange(41.0)
    acceleration = np.linspace(0.0, 20.0, 41)
    sp = np.linspace(0.0, 1.0, 11)
    peak = 3.0 * np.exp(-((sp[:, None] - 0.5) ** 2 + (sp[None, :] - 0.3) ** 2) / 0.02)
    return {
        "position:wrist": (
            {"x": angle, "gain_db": 3.0 * np.cos(angle - 0.7), "unit": "rad"},
            "wrist: 6.0 dB peak-to-trough, loudest at 0.698 rad",
        ),
        "drift:elapsed_time": (
            {"x": t, "gain_db": 2.0 * (1.0 - np.exp(-t / 5.0))},  # 90 % at 5 ln 10 = 11.5 s
            "elapsed_time: +2.0 dB from start to end, 90 % of it reached at 12 s (2.0 dB range)",
        ),
        "acceleration:wrist": (
            {"x": acceleration, "gain_db": 0.5 * acceleration},
            "wrist: +5.0 dB at 10x the typical |acceleration|",
        ),
        "coupling:wristxgripper": (
            {
                "speed_fraction": sp,
                "gain_db": peak,
                "same_minus_opposite_direction_db": np.full_like(peak, -1.0),
            },
            "wristxgripper: up to +3.0 dB at speed fractions 0.5/0.3 "
            "(+0.0 dB with both at full speed; same vs opposite direction -1.0 dB)",
        ),
        "coupling:motor1xmotor3": (
            {
                "speed_fraction": sp,
                "gain_db": np.zeros_like(peak),
                "per_bin_peak_db": -0.31,
                "per_bin_peak_hz": 281.3,
            },
            "motor1xmotor3: flat across the band; bin by bin up to -0.3 dB at 281 Hz",
        ),
        "timing:lag_scan": (
            {"fitted_joint_lag_s": -0.05, "in_sync_band_s": [-0.005, 0.005]},
            "best joint lag -50.0 ms (in sync: -5..+5 ms)",
        ),
        "coupling-lines:wristxgripper": (
            {
                "x": sp,
                "gain_db": 2.0 * sp,
                "same_minus_opposite_direction_db": -4.0 * sp,
                "lines_of": "wrist",
                "speed_of": "gripper",
            },
            "wrist lines up to +2.0 dB with gripper's speed, same vs opposite direction -4.0 dB",
        ),
    }


def test_shapes_are_described_in_one_sentence_each():
    shapes = known_shapes()
    for name, (shape, sentence) in shapes.items():
        assert describe_shape({name: shape}) == sentence
    # several shapes: their sentences in order, joined
    two = ["timing:lag_scan", "drift:elapsed_time"]
    assert describe_shape({k: shapes[k][0] for k in two}) == "; ".join(shapes[k][1] for k in two)
    assert describe_shape({}) == ""


def test_joint_names_holding_an_x_are_reported_and_drawn(tmp_path):
    """ROS joints are often named *_flex_joint: a coupling shape keyed "AxB" cannot be split
    back into its two joints (the figures raised ValueError, the advice listed halves of
    names); the shape names them."""
    table = synthetic_table("coupling", 5.0, seed=5, duration_s=30.0)
    names = ("r_wrist_flex_joint", "r_gripper_joint")
    options = DiagnosisOptions(effects=("position", "coupling", "acceleration", "timing"))
    diag = diagnose(dataclasses.replace(table, joint_names=names), options)
    assert diag.verdict == "coupling"
    report = report_of(diag)
    advice = next(a for a in report["advice"]["effects"] if a["effect"] == "coupling")
    assert advice["settings"]["joints"] == sorted(names)
    assert "r_wrist_flex_joint x r_gripper_joint" in advice["action"]
    assert set(make_figures(diag, report, tmp_path).values()) <= {
        p.name for p in tmp_path.iterdir()
    }


def test_figures_are_written_and_named(position, tmp_path):
    report = report_of(position)
    figures = make_figures(position, report, tmp_path)
    assert set(figures.values()) == {
        "where_frequency_velocity.png",
        "where_covariates.png",
        "which_candidates.png",
        "which_effect_shapes.png",
    }
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(figures.values())
    for name in figures.values():
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert (tmp_path / name).stat().st_size > 1000
