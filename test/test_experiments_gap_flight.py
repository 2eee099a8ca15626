"""`egovib real gap`: the gap diagnosis on the real quadcopter flight (no simulator)."""

import json
from pathlib import Path

from egovib_ros.cli import main as egovib
from egovib_ros.gap.effects import EFFECTS

REPO = Path(__file__).resolve().parents[1]
BAG = REPO / "bags" / "quadcopter_ar8"


def test_flight_gap_both_directions(tmp_path, capsys):
    out = tmp_path / "gap_flight"
    assert egovib(["real", "gap", "--bag", str(BAG), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["profile"] == "quadcopter"
    assert set(summary["directions"]) == {"calibrated_on_first_half", "calibrated_on_second_half"}
    for name, d in summary["directions"].items():
        assert d["verdict"]["effect"] in ("none", *EFFECTS)
        assert 0.0 <= d["verdict"]["confidence"] <= 1.0
        g = d["gap"]
        # the baseline is fitted on this half's own training folds: never worse than the
        # other half's model by more than noise, and never below the floor by much
        assert g["after_refit"] <= g["sim_as_is"] + 0.1
        assert g["after_refit"] >= g["floor"] - 0.1
        report = json.loads((out / name / "report.json").read_text())
        assert {"metric", "split", "gap", "where", "candidates", "verdict"} <= set(report)
        assert all(c.get("shape_summary") for c in report["candidates"])
        assert (out / name / "which_effect_shapes.png").stat().st_size > 10_000
    assert "verdict" in capsys.readouterr().out
    # an existing report directory is not replaced without --force
    assert egovib(["real", "gap", "--bag", str(BAG), "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
