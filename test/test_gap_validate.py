"""`egovib gap validate` in its reduced form: one blind seed per class, short bags."""

from __future__ import annotations

from egovib_ros.gap.effects import EFFECTS
from egovib_ros.gap.validate import MISCALIBRATED, plan_runs, render_markdown, run_validation


def test_plan_is_blind_and_covers_every_class():
    runs = plan_runs(2, ladder=True)
    blind = [r for r in runs if not r.get("ladder")]
    assert {r["truth"] for r in blind} == {"none", MISCALIBRATED, *EFFECTS}
    assert len(blind) == 2 * (len(EFFECTS) + 2)
    assert len({r["seed"] for r in runs}) == len(runs)  # every bag its own random seed
    assert plan_runs(2, ladder=True) == runs  # reproducible from the master seed


def test_reduced_blind_validation(tmp_path):
    summary = run_validation(
        seeds=1, duration_s=60.0, out_dir=tmp_path, ladder=False, calibration_dwell_s=2.0
    )
    report = summary["report"]
    assert summary["n_runs"] == len(EFFECTS) + 2
    # Every class has a confusion row summing to its runs, and the two `none` rows stay `none`.
    for truth, row in summary["confusion"].items():
        assert sum(row.values()) == 1, truth
    assert summary["none_false_positive_rate"] == 0.0
    assert summary["accuracy"] >= 6 / 7
    for effect, shrink in summary["heldout_shrink"].items():
        assert shrink["mean_gap_after_effect"] < shrink["mean_gap_after_refit"], effect
    md = (tmp_path / "gap_validation.md").read_text()
    assert md == render_markdown(report) and "Confusion matrix" in md
    assert (tmp_path / "gap_validation.json").exists()
