"""gap.pipeline: `run_gap` on a small simulated bag writes the report directory (report.json
as returned, report.md rendered from it), passes its options through, replaces only an
output of its own, and refuses bad input with a typed one-line error, writing nothing."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
from gaptables import synthetic_model, synthetic_table

from egovib_ros.bag import write_recording
from egovib_ros.core import NoiseModel
from egovib_ros.errors import BagError, EgovibError, GapDataError, ModelFileError
from egovib_ros.gap.diagnose import DiagnosisOptions
from egovib_ros.gap.features import THIN_RUN_BLOCKS
from egovib_ros.gap.pipeline import (
    diagnose_recording,
    diagnose_table,
    input_notices,
    reference_lag_for,
    run_gap,
)
from egovib_ros.gap.report import render_markdown
from egovib_ros.outputs import MARKER, OutputError
from egovib_ros.sim import simulate_motion

#: A quick diagnosis (one candidate, two folds) for the tests that are about files and
#: options, not about the verdict.
QUICK = DiagnosisOptions(effects=("acceleration",), folds=2)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """An 8 s motion bag (enough blocks to diagnose) and a 3 s one (too few), simulated."""
    root = tmp_path_factory.mktemp("gap_pipeline")
    motion, _ = simulate_motion(duration_s=8.0, max_speed=0.5, tap_rate_hz=0.5, seed=4)
    write_recording(root / "motion", motion)
    short, _ = simulate_motion(duration_s=3.0, max_speed=0.5, seed=4)
    write_recording(root / "short", short)
    return root, motion


@pytest.fixture(scope="module")
def gap_run(sim_model_path, recordings, tmp_path_factory):
    """`egovib gap`'s library call: the in-sync lag given (nothing simulated), no figures."""
    root, _ = recordings
    out = tmp_path_factory.mktemp("gap_run") / "report"
    report = run_gap(sim_model_path, root / "motion", out, reference_lag=0.0, figures=False)
    return report, out


def leftovers(directory) -> list[str]:
    """Staging directories of atomic_output left behind."""
    return [p.name for p in directory.iterdir() if p.name.endswith(".partial")]


def test_the_report_directory_holds_the_report_returned(gap_run, sim_model_path, recordings):
    report, out = gap_run
    assert sorted(p.name for p in out.iterdir()) == sorted(["report.json", "report.md", MARKER])
    assert json.loads((out / "report.json").read_text()) == json.loads(json.dumps(report))
    md = (out / "report.md").read_text()
    assert md == render_markdown(report)
    assert md.startswith("# Sim-to-real gap report\n")
    assert set(json.loads((out / MARKER).read_text())["files"]) == {"report.json", "report.md"}
    assert not leftovers(out.parent)
    inputs = report["inputs"]
    assert inputs["model"] == str(sim_model_path)
    assert inputs["real"] == str(recordings[0] / "motion")
    assert inputs["model_kind"] == "simulator"  # calibrated on our simulator: a sim-to-real gap
    assert inputs["notices"] == []  # clean input, far within the time budget
    assert inputs["bad_input"]["kept_share"] == 1.0
    assert report["figures"] == {} and report["runtime_s"] > 0.0
    assert report["baseline"]["reference_joint_lag_s"] == 0.0
    assert {c["effect"] for c in report["candidates"]} == set(DiagnosisOptions().effects)


def test_options_and_reference_lag_are_passed_through_and_its_own_output_replaced(
    gap_run, sim_model_path, recordings, tmp_path
):
    root, motion = recordings
    _, previous = gap_run
    out = tmp_path / "report"
    shutil.copytree(previous, out)  # an earlier report of ours: replaced
    options = dataclasses.replace(QUICK, reference_lag_s=0.5, window_blocks=6)
    report = run_gap(sim_model_path, root / "motion", out, reference_lag=0.004, options=options)
    written = json.loads((out / "report.json").read_text())
    assert written == json.loads(json.dumps(report))
    assert [c["effect"] for c in written["candidates"]] == ["acceleration"]
    assert written["split"]["folds"] == 2
    assert "(6 consecutive blocks" in written["metric"]["definition"]
    # the reference lag given to run_gap (joint states 4 ms late: a joint lag of -4 ms), not
    # the options', is what timing is judged against
    assert written["baseline"]["reference_joint_lag_s"] == -0.004
    figures = set(report["figures"].values())
    assert len(figures) == 4 and figures <= {p.name for p in out.iterdir()}
    assert all(f"({name})" in (out / "report.md").read_text() for name in figures)
    assert not leftovers(tmp_path)
    # the bag read slice by slice and the Recording in memory: the same diagnosis
    diag = diagnose_recording(
        motion,
        NoiseModel.load(sim_model_path),
        options=dataclasses.replace(options, reference_lag_s=0.004),
    )
    assert written["verdict"]["effect"] == diag.verdict
    assert written["blocks"]["total"] == diag.table.n_blocks
    assert written["gap"]["sim_as_is"] == pytest.approx(diag.gaps["sim_as_is"], abs=1e-4)
    assert written["gap"]["after_refit"] == pytest.approx(diag.gaps["refit"], abs=1e-4)
    assert written["gap"]["floor"] == pytest.approx(diag.floor, abs=1e-4)


def test_an_output_it_did_not_create_is_left_alone(
    sim_model_path, recordings, tmp_path, monkeypatch
):
    out = tmp_path / "report"
    out.mkdir()
    (out / "notes.txt").write_text("mine")

    def never(*args, **kwargs):
        raise AssertionError("the bag was read although the output cannot be written")

    # refused before minutes of work, not after
    monkeypatch.setattr("egovib_ros.gap.pipeline.table_from_bag", never)
    with pytest.raises(OutputError, match="not an egovib output"):
        run_gap(
            sim_model_path,
            recordings[0] / "motion",
            out,
            reference_lag=0.0,
            figures=False,
            options=QUICK,
        )
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    assert (out / "notes.txt").read_text() == "mine"
    assert not leftovers(tmp_path)


def test_bad_input_is_a_typed_error_and_nothing_is_written(sim_model_path, recordings, tmp_path):
    root, _ = recordings
    out = tmp_path / "report"
    with pytest.raises(BagError, match="missing.bag: no such bag"):
        run_gap(sim_model_path, tmp_path / "missing.bag", out, reference_lag=0.0)
    not_a_model = tmp_path / "model.npz"
    not_a_model.write_text("not a model")
    with pytest.raises(ModelFileError, match="model.npz"):
        run_gap(not_a_model, root / "motion", out, reference_lag=0.0)
    # 3 s of data: too few blocks to fit and test
    with pytest.raises(GapDataError) as short:
        run_gap(sim_model_path, root / "short", out, reference_lag=0.0)
    message = str(short.value)
    assert isinstance(short.value, EgovibError) and "\n" not in message
    assert message.startswith(f"{root / 'short'}: too few no-contact blocks")
    assert not out.exists() and not leftovers(tmp_path)


def test_a_table_without_enough_clean_blocks_names_its_source():
    table = synthetic_table(duration_s=10.0)
    table.contact[:] = True
    with pytest.raises(GapDataError, match=r"^flight\.bag: too few no-contact blocks \(0\)$"):
        diagnose_table(table, source="flight.bag")


def test_the_notices_say_what_was_missing_and_what_was_thinned():
    table = synthetic_table(duration_s=5.0)
    clean = {"samples_bad": 0, "dropped_out_of_order": 0, "joint_states_dropped": 0}
    assert input_notices(dataclasses.replace(table, bad_input=clean), 2.0) == []
    said = "real.bag: 12 sensor samples not finite, treated as missing"
    bad = dict(clean, samples_bad=12, said=said)
    assert input_notices(dataclasses.replace(table, bad_input=bad), 2.0) == [said]
    thinned = dict(clean, kept_share=0.25, said="", recorded_s=480.0)
    assert input_notices(dataclasses.replace(table, bad_input=thinned), 2.0) == [
        "8.0 minutes of sensor data, more than the 2-minute budget (--budget-minutes): "
        f"25 % of its {THIN_RUN_BLOCKS}-block runs diagnosed, spread evenly"
    ]
    # just over the budget: some runs are left out, never said as "100 %"
    barely = dict(thinned, kept_share=120 / 120.5, recorded_s=120.5)
    (notice,) = input_notices(dataclasses.replace(table, bad_input=barely), 2.0)
    assert "99.5 % of its" in notice and "100 %" not in notice


def test_the_reference_lag_is_the_given_one_or_none_for_a_foreign_robot():
    foreign = synthetic_model()  # joints the simulator does not have: nothing to measure
    assert reference_lag_for(foreign, None, None) == 0.0
    given = reference_lag_for(foreign, np.float32(0.012), None)
    assert type(given) is float and given == pytest.approx(0.012)


def test_a_thinned_bag_keeps_the_joint_states_the_lag_scan_reaches(
    sim_model_path, recordings, tmp_path
):
    """A bag thinned to its time budget holds only the joint states near its kept blocks:
    as far as the lag scan reaches around the reference (+-LAG_RANGE_S), not a fixed
    margin that a large reference lag would overrun."""
    root, _ = recordings
    report = run_gap(
        sim_model_path,
        root / "motion",
        tmp_path / "report",
        reference_lag=0.1,  # the scan reaches 0.3 s, beyond the default margin
        budget_minutes=0.1,  # 8 s bag, 6 s budget: thinned
        options=QUICK,
        figures=False,
    )
    assert report["inputs"]["bad_input"]["kept_share"] < 1.0
    assert report["baseline"]["reference_joint_lag_s"] == -0.1
