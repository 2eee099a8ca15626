"""`egovib detect` on real bag files: JSON and CSV events equal to the library's, the
threshold from the model's own calibration bag, bad input one line and exit 2, nothing written."""

from __future__ import annotations

import csv
import json

import pytest

from egovib_ros.cli import main
from egovib_ros.core import NoiseModel
from egovib_ros.evaluation.contacts import detect_bag


def test_json_and_csv_hold_the_librarys_events(sim_bags, sim_bags_model, tmp_path, capsys):
    bag = sim_bags / "motion"
    args = ["detect", str(bag), "--model", str(sim_bags_model)]
    assert main([*args, "--out", str(tmp_path / "events.json")]) == 0
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert "events in 4.0 s after hybrid (the model's default), threshold" in line
    assert "(stored in the model, 1/min); against the ground truth: F1 1.00" in line
    report = json.loads((tmp_path / "events.json").read_text())
    # the threshold calibration stored: the calibration bag at the same budget gives it again
    expected = detect_bag(
        bag, model=NoiseModel.load(sim_bags_model), calibration=sim_bags / "sweep",
        false_alarms_per_min=1.0,
    )  # fmt: skip
    assert report["threshold"] == pytest.approx(expected.threshold, rel=1e-9)
    assert report["method"] == "hybrid" and report["threshold_source"].startswith("stored")
    assert [e["onset_ns"] for e in report["events"]] == [e.onset_ns for e in expected.events]
    # another budget: set from the bag the model was calibrated from
    assert main([*args, "--false-alarms-per-min", "2", "--out", str(tmp_path / "b.json")]) == 0
    other = json.loads((tmp_path / "b.json").read_text())
    assert other["threshold_source"] == f"no-contact data {sim_bags / 'sweep'}, 2/min"
    assert report["scores"]["f1"] == 1.0 and report["counts"]["events"] == len(expected.events)
    assert main([*args, "--out", str(tmp_path / "events.csv"), "--threshold", "0.7"]) == 0
    with open(tmp_path / "events.csv") as fh:
        rows = list(csv.DictReader(fh))
    given = detect_bag(bag, model=NoiseModel.load(sim_bags_model), threshold=0.7)
    assert [int(r["onset_ns"]) for r in rows] == [e.onset_ns for e in given.events]
    assert list(rows[0]) == ["onset_ns", "peak_x", "peak_y", "peak_z", "strength", "report_ns"]


def test_bad_input_is_one_line_exit_2_and_writes_nothing(
    sim_bags, sim_bags_model, tmp_path, capsys
):
    out = tmp_path / "events.json"
    cases = [
        (["--threshold", "-1"], "--threshold"),
        (["--method", "wiener"], "--method"),
        (["--calibration", str(tmp_path / "absent")], "absent: no such bag"),
    ]
    for extra, named in cases:
        args = ["detect", str(sim_bags / "motion"), "--model", str(sim_bags_model)]
        assert main([*args, "--out", str(out), *extra]) == 2, extra
        err = capsys.readouterr().err.strip()
        assert named in err and "\n" not in err, err
        assert not out.exists()
    # neither JSON nor CSV by its name: refused, not written as JSON under another name
    args = ["detect", str(sim_bags / "motion"), "--model", str(sim_bags_model)]
    assert main([*args, "--out", str(tmp_path / "events.txt")]) == 2
    assert "EVENTS.json" in capsys.readouterr().err
    assert not (tmp_path / "events.txt").exists()


def test_force_replaces_only_event_files_detect_wrote(sim_bags, sim_bags_model, tmp_path, capsys):
    """--force replaces a previous events file, never a JSON or CSV of the user's."""
    args = ["detect", str(sim_bags / "motion"), "--model", str(sim_bags_model), "--force"]
    for name, foreign in (("events.json", "[1, 2, 3]\n"), ("events.csv", "a,b\n1,2\n")):
        out = tmp_path / name
        out.write_text(foreign)
        assert main([*args, "--out", str(out), "--threshold", "0.7"]) == 2
        assert "not an output of this command" in capsys.readouterr().err
        assert out.read_text() == foreign
        out.unlink()
        assert main([*args, "--out", str(out), "--threshold", "0.7"]) == 0
        assert main([*args, "--out", str(out), "--threshold", "0.9"]) == 0  # ours: replaced
        capsys.readouterr()


def test_adapt_detects_after_the_adapting_denoiser_and_evaluate_reports_it(
    sim_bags, sim_bags_model, tmp_path, capsys
):
    from egovib_ros.core.adapt import AdaptSettings

    bag, model = sim_bags / "motion", NoiseModel.load(sim_bags_model)
    args = ["detect", str(bag), "--model", str(sim_bags_model), "--adapt", "--forget-s", "5"]
    assert main([*args, "--out", str(tmp_path / "events.json")]) == 0
    assert "after hybrid (the model's default), adapting, threshold" in capsys.readouterr().err
    report = json.loads((tmp_path / "events.json").read_text())
    expected = detect_bag(bag, model=model, adapt=AdaptSettings(forget_s=5.0))
    assert [e["onset_ns"] for e in report["events"]] == [e.onset_ns for e in expected.events]
    assert report["adapt"]["forget_s"] == 5.0 and report["adapt"]["blocks_learnt"] > 0
    assert report["adapt"] == expected.adapt
    code = main(
        ["evaluate", str(bag), "--model", str(sim_bags_model), "--methods", "default,hybrid",
         "--json", str(tmp_path / "report.json"), "--adapt", "--quiet"]
    )  # fmt: skip
    assert code == 0
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["adapt"]["forget_s"] == AdaptSettings().forget_s
    assert report["methods"]["default"]["adapt"]["blocks_learnt"] > 0
    assert "adapt" in report["methods"]["hybrid"] and "adapt" not in report["methods"]["paper"]
    assert main(["detect", str(bag), "--model", str(sim_bags_model), "--method", "raw",
                 "--adapt", "--out", str(tmp_path / "raw.json")]) == 2  # fmt: skip
    assert "method raw has no model to adapt" in capsys.readouterr().err
    assert not (tmp_path / "raw.json").exists()


def test_beyond_the_calibrations_motion_detect_and_evaluate_raise_the_threshold_alike(
    tmp_path, capsys
):
    """Calibrated on free motion at 30 % of top speed, a run at 90 %: `egovib detect` says
    on what share of the samples its threshold rose (the joints beyond the calibration's
    speeds), raises fewer false alarms than without the rule (the model's limits removed),
    and `egovib evaluate` scores the same detector: the same F1. With thresholds from
    another no-contact bag (`--calibration`), the limits are that bag's."""
    cal, run, model = tmp_path / "cal", tmp_path / "run", tmp_path / "m.npz"
    simulate = ["simulate", "motion", "--quiet", "--duration"]
    assert main([*simulate, "20", "--max-speed", "0.3", "--taps", "0", "--out", str(cal)]) == 0
    assert main([*simulate, "10", "--max-speed", "0.9", "--taps", "2", "--out", str(run)]) == 0
    assert main(["calibrate", str(cal), "--grid", "free", "--out", str(model), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["detect", str(run), "--model", str(model), "--out", str(tmp_path / "e.json")]) == 0
    line = capsys.readouterr().err
    assert "% of the samples (motion beyond the calibration's)" in line
    report = json.loads((tmp_path / "e.json").read_text())
    assert report["counts"]["samples_beyond_calibration_motion"] > 0.5 * report["counts"]["samples"]
    loaded = NoiseModel.load(model)
    plain = loaded.replace(
        extras={k: v for k, v in loaded.extras.items() if not k.startswith("detector.motion.")}
    )
    without = detect_bag(run, model=plain)
    assert without.counts["samples_beyond_calibration_motion"] == 0
    assert report["scores"]["fp"] < without.scores["fp"]
    assert (
        main(["evaluate", str(run), "--model", str(model), "--json", str(tmp_path / "v.json")]) == 0
    )
    assert json.loads((tmp_path / "v.json").read_text())["f1_denoised"] == report["scores"]["f1"]
    # thresholds from a no-contact bag at the run's speeds (--calibration): the limits are
    # that bag's too, so hardly anything rises
    fast = tmp_path / "fast"
    assert main([*simulate, "10", "--max-speed", "0.9", "--taps", "0", "--out", str(fast)]) == 0
    given = detect_bag(run, model=loaded, calibration=fast)
    assert given.threshold_source.startswith(f"no-contact data {fast}")
    assert given.counts["samples_beyond_calibration_motion"] < 0.1 * given.counts["samples"]
    # and `egovib evaluate --calibration` takes the same limits from it: the same F1
    args = ["evaluate", str(run), "--model", str(model), "--calibration", str(fast)]
    assert main([*args, "--json", str(tmp_path / "f.json")]) == 0
    assert json.loads((tmp_path / "f.json").read_text())["f1_denoised"] == given.scores["f1"]
