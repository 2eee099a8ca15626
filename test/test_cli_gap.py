"""`egovib gap` end to end on real bag files: simulator model, blind "real" bag,
report directory."""

from __future__ import annotations

import json

import numpy as np
import pytest

from egovib_research.experiments.gap_validation import calibrate_sim_model
from egovib_ros.bag import write_recording
from egovib_ros.cli import main
from egovib_ros.cli.gap import _change_said
from egovib_ros.sim import simulate_motion

CONTRACT_KEYS = {
    "schema",
    "metric",
    "split",
    "gap",
    "where",
    "candidates",
    "verdict",
    "added_effect",
}


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("gap_model") / "sim_model.npz"
    calibrate_sim_model(dwell_s=2.0).save(path)
    return path


@pytest.fixture(scope="module")
def position_bag(tmp_path_factory):
    rec, _ = simulate_motion(
        duration_s=60.0, max_speed=0.8, tap_rate_hz=0.5, effects={"position": 0.4}, seed=11
    )
    path = tmp_path_factory.mktemp("gap_real") / "real.bag"
    write_recording(path, rec)
    return path


def test_gap_report_on_blind_bag(model_path, position_bag, tmp_path, capsys):
    out = tmp_path / "report"
    args = ["gap", "--model", str(model_path), "--real", str(position_bag), "--out", str(out)]
    assert main([*args, "--write-back"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert set(report) >= CONTRACT_KEYS
    assert report["schema"] == "egovib.gap/1" and report["metric"]["unit"] == "dB"
    assert set(report["gap"]) == {"sim_as_is", "after_refit", "after_effect", "floor"}
    assert set(report["where"]) == {"frequency_hz", "velocity_cells", "covariates"}
    assert {"effect", "heldout_gap", "reduction", "p_value"} <= set(report["candidates"][0])
    # Blocked cross-validation in time: every block held out once, fitted on the other folds.
    assert report["split"]["folds"] == 5 and "cross-validation" in report["split"]["method"]
    assert report["split"]["heldout_s"] > report["split"]["train_s"] > 0
    # The hidden effect is found and adding it shrinks the held-out gap towards the floor.
    assert report["verdict"]["effect"] == "position"
    gap = report["gap"]
    assert gap["after_effect"] < gap["after_refit"] and gap["after_effect"] - gap["floor"] < 1.0
    assert report["added_effect"]["effect"] == "position"
    # Written back into a sim config that the simulator accepts, and checked on held-out data.
    from egovib_ros.sim import SimParams

    updated = SimParams.load(out / "sim_updated.yaml")
    assert 0.2 < updated.effects["position"] < 0.6
    check = report["added_effect"]["simulator"]
    assert check["heldout_gap_with_updated_simulator"] < check["heldout_gap_refit"]
    # The report's first lines say what to do, what the corrections are worth to the
    # denoiser and what is left, then answer where, which and how far, with figures that exist.
    md = (out / "report.md").read_text().splitlines()
    assert md[2].startswith("**What to do:** position-dependent")
    # the command that acts on it, an option egovib calibrate has (no position key exists)
    assert md[3] == "**All corrections together:**" and md[4] == "```sh"
    assert md[5].startswith("egovib calibrate NEW_RECORDING --grid free --out NEW_MODEL.npz")
    assert md[6] == "```" and md[7].startswith(
        "**What the corrections are worth to the denoiser (model estimate):**"
    )
    assert md[8].startswith("**Left unexplained:**")
    advice = report["advice"]
    assert advice["settings"]["calibration_grid"] == "free"
    assert advice["settings"]["position_joint"] == "r_wrist_roll_joint"
    assert advice["denoiser"]["gain_db"] > 0  # the position term denoises held-out data better
    assert advice["applied"] is None  # no flag of the denoiser acts on position
    # verdict.effects (CONTRACT section 6): the ordered list, its first entry the verdict
    first = report["verdict"]["effects"][0]
    assert {"effect", "reduction", "p_value", "confidence", "parameters", "advice"} <= set(first)
    assert first["effect"] == "position" and first["advice"] == advice["effects"][0]["action"]
    head = "\n".join(md[:16])
    assert (
        "**Where:**" in head
        and "**Which:**" in head
        and "**How far:**" in head
        and "`position`" in head
    )
    for fig in report["figures"].values():
        assert (out / fig).stat().st_size > 1000
        assert f"({fig})" in head
    # Every candidate states its fitted shape; the position term peaks near the hidden phase.
    assert "which_effect_shapes.png" in report["figures"].values()
    pos = next(c for c in report["candidates"] if c["effect"] == "position")
    wrist = pos["shape"]["position:r_wrist_roll_joint"]
    peak = wrist["x"][int(np.argmax(wrist["gain_db"]))]
    assert abs(np.angle(np.exp(1j * (peak - 0.6)))) < 0.6  # the simulator's phase is 0.6 rad
    assert (
        max(wrist["gain_db"]) - min(wrist["gain_db"]) > 1.5
    )  # band-averaged: the gripper band dilutes it
    assert "r_wrist_roll_joint" in pos["shape_summary"] and pos["shape_summary"] in "\n".join(md)
    assert report["baseline"]["definition"] and "transients" in report
    # The covariate breakdown covers positions, accelerations, time and lag.
    covs = report["where"]["covariates"]
    assert {"elapsed_time", "stream_lag"} <= set(covs)
    assert any(k.startswith("position:") for k in covs) and any(
        k.startswith("acceleration:") for k in covs
    )
    assert "verdict position" in capsys.readouterr().out


def test_gap_bad_input_is_one_line_error_without_output(model_path, tmp_path, capsys):
    out = tmp_path / "report"
    missing = tmp_path / "missing.bag"
    assert main(["gap", "--model", str(model_path), "--real", str(missing), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("egovib: error:") and "missing.bag" in err and len(err.splitlines()) == 1
    assert not out.exists()
    bad_model = tmp_path / "model.npz"
    bad_model.write_text("not a model")
    assert main(["gap", "--model", str(bad_model), "--real", str(tmp_path), "--out", str(out)]) == 2
    assert "model.npz" in capsys.readouterr().err
    assert not out.exists()
    assert main(["gap", "--model", str(model_path)]) == 2
    assert "--real" in capsys.readouterr().err


def test_streamed_table_equals_whole_recording(model_path, position_bag):
    """`egovib gap` frames the bag slice by slice (never holding the sensor stream); the
    table is the one built from the whole recording in memory."""
    from egovib_ros.bag import iter_recording, read_recording
    from egovib_ros.core import NoiseModel
    from egovib_ros.gap.features import build_table, table_from_bag

    model = NoiseModel.load(model_path)
    slices = sum(1 for _ in iter_recording(position_bag, profile=model.profile))
    assert slices > 3  # the bag really arrives in pieces
    streamed = table_from_bag(position_bag, model)
    whole = build_table(
        read_recording(position_bag, profile=model.profile, ground_truth=False, denoised=False),
        model,
    )
    assert streamed.n_blocks == whole.n_blocks > 1000
    for name in ("t_first_s", "magnitude", "velocity", "position", "base_mean", "hats"):
        np.testing.assert_array_equal(getattr(streamed, name), getattr(whole, name), err_msg=name)
    np.testing.assert_array_equal(streamed.contact, whole.contact)
    assert streamed.bad_input["samples_bad"] == whole.bad_input["samples_bad"] == 0


def test_several_bags_in_parallel_and_a_corrupt_one(model_path, position_bag, tmp_path, capsys):
    """A directory of bags: one report directory per bag; `--jobs 2` (a local Dask cluster)
    gives the reports of the one-process run; a corrupt bag is named in the summary and the
    others complete (exit status 2)."""
    import shutil

    bags = tmp_path / "bags"
    shutil.copytree(position_bag, bags / "a")  # (one good bag: each diagnosis takes ~15 s)
    shutil.copytree(position_bag, bags / "corrupt")
    mcap = next((bags / "corrupt").glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    data[len(data) // 3 : len(data) // 3 + 4096] = b"\xff" * 4096
    mcap.write_bytes(bytes(data))

    reports = {}
    for jobs in ("1", "2"):
        out = tmp_path / f"out{jobs}"
        args = ["gap", "--model", str(model_path), "--real", str(bags), "--out", str(out)]
        options = ["--jobs", jobs, "--reference-lag", "0", "--quiet", "--no-figures"]
        assert main(args + options) == 2  # (figures: test_gap_report_on_blind_bag)
        err = capsys.readouterr().err
        assert "FAILED" in err and "corrupt" in err and "1 done, 1 failed" in err
        assert not (out / "corrupt").exists()
        reports[jobs] = json.loads((out / "a" / "report.json").read_text())
    one, two = reports["1"], reports["2"]
    assert one["verdict"]["effect"] == "position"
    assert one["gap"] == two["gap"] and one["candidates"] == two["candidates"]


def test_a_bag_longer_than_the_budget_is_thinned_evenly(model_path, position_bag):
    """Past the block budget the diagnosis keeps one run of blocks in every k over the
    whole bag (memory and time stop growing); the kept blocks are the whole table's."""
    from egovib_ros.core import NoiseModel
    from egovib_ros.gap.effects import LAG_RANGE_S
    from egovib_ros.gap.features import (
        JOINT_MARGIN_S,
        THIN_RUN_BLOCKS,
        table_from_bag,
    )

    model = NoiseModel.load(model_path)
    whole = table_from_bag(position_bag, model)  # 60 s: within the default budget
    thin = table_from_bag(position_bag, model, budget_minutes=0.25)
    assert whole.bad_input["kept_share"] == 1.0 and thin.bad_input["kept_share"] < 0.26
    assert 0.2 < thin.n_blocks / whole.n_blocks < 0.3
    assert thin.t_first_s[-1] > 0.9 * whole.t_first_s[-1]  # spread over the whole bag
    rows = np.searchsorted(whole.t_first_s, thin.t_first_s)
    np.testing.assert_array_equal(whole.t_first_s[rows], thin.t_first_s)
    np.testing.assert_array_equal(whole.magnitude[rows], thin.magnitude)
    runs = np.flatnonzero(np.diff(rows) > 1)
    assert np.all(np.diff(runs) >= THIN_RUN_BLOCKS // 2)  # whole runs, not scattered blocks
    # Only the joint states near the kept blocks are held, and the covariates are the whole
    # table's, also at the lags the timing scan tries (block means are integrals from the
    # series' start: equal to rounding).
    assert 0.3 * len(whole.joints.t_s) < len(thin.joints.t_s) < 0.8 * len(whole.joints.t_s)
    assert thin.bad_input["joint_states_kept"] == len(thin.joints.t_s)
    for lag in (0.0, -LAG_RANGE_S, LAG_RANGE_S):
        a, b = whole.at_lag(lag), thin.at_lag(lag)
        for name in ("position", "acceleration", "hats", "reversal_after_s", "reversal_before_s"):
            np.testing.assert_allclose(
                getattr(b, name), getattr(a, name)[rows], rtol=1e-9, atol=1e-12, err_msg=name
            )
    with pytest.raises(ValueError, match="beyond"):
        thin.at_lag(JOINT_MARGIN_S + 0.01)


def test_out_of_order_joint_states_are_missing_for_the_covariates_too(model_path, position_bag):
    """Joint states stamped out of order are dropped and counted, and the covariates are
    those of the recording without them (not fed unsorted into the motion features)."""
    import dataclasses

    from egovib_ros.bag import read_recording
    from egovib_ros.core import NoiseModel
    from egovib_ros.gap.features import build_table

    model = NoiseModel.load(model_path)
    rec = read_recording(position_bag, profile=model.profile, ground_truth=False, denoised=False)
    swapped = np.arange(1000, 40000, 200)  # 195 swapped neighbours: 0.3 % of the messages
    order = np.arange(len(rec.joint_stamps_ns))
    order[swapped], order[swapped + 1] = swapped + 1, swapped
    shuffled = dataclasses.replace(
        rec,
        joint_stamps_ns=rec.joint_stamps_ns[order],
        joint_position=rec.joint_position[order],
        joint_velocity=rec.joint_velocity[order],
    )
    dropped = np.zeros(len(order), bool)
    dropped[swapped] = True  # the later of each pair arrived first; the earlier is late
    clean = dataclasses.replace(
        rec,
        joint_stamps_ns=rec.joint_stamps_ns[~dropped],
        joint_position=rec.joint_position[~dropped],
        joint_velocity=rec.joint_velocity[~dropped],
    )
    got, want = build_table(shuffled, model), build_table(clean, model)
    assert got.bad_input["joint_states_dropped"] == len(swapped)
    np.testing.assert_array_equal(got.hats, want.hats)
    np.testing.assert_array_equal(got.acceleration, want.acceleration)


def test_scattered_bad_samples_above_a_tenth_are_refused_as_such(model_path, position_bag):
    import dataclasses

    from egovib_ros.bag import read_recording
    from egovib_ros.core import NoiseModel
    from egovib_ros.errors import StreamError
    from egovib_ros.gap.features import build_table

    model = NoiseModel.load(model_path)
    rec = read_recording(position_bag, profile=model.profile, ground_truth=False, denoised=False)
    accel = rec.sensor.copy()
    accel[np.random.default_rng(0).random(len(accel)) < 0.15] = np.nan
    with pytest.raises(StreamError, match="bad|non-finite"):
        build_table(dataclasses.replace(rec, sensor=accel), model)


@pytest.fixture(scope="module")
def warm_pair(tmp_path_factory):
    """The same robot twice: a reference recording, and one with joint states 40 ms late and
    the vibration 40 % louder (a warm robot after a driver update)."""
    root = tmp_path_factory.mktemp("gap_pair")
    cold, _ = simulate_motion(duration_s=40.0, max_speed=0.8, tap_rate_hz=0.5, seed=31)
    write_recording(root / "cold", cold)
    warm, _ = simulate_motion(
        duration_s=40.0, max_speed=0.8, tap_rate_hz=0.5, seed=32, effects={"timing": 0.04}
    )
    warm.sensor = warm.sensor * 1.4  # in-band ego-vibration x 1.4 (+2.9 dB), gravity too
    write_recording(root / "warm", warm)
    return root


def test_what_changed_since_a_reference_recording(model_path, warm_pair, tmp_path, capsys):
    """`egovib gap --reference A`: `change` lists what differs, the lag shift in ms (the
    joint-lag convention: joint states 40 ms late = -40 ms) and the level change in dB; the
    summary line says it; the advice's commands carry the bag, model and report paths."""
    out = tmp_path / "report"
    args = ["gap", "--model", str(model_path), "--real", str(warm_pair / "warm")]
    args += ["--reference", str(warm_pair / "cold"), "--out", str(out), "--no-figures"]
    assert main(args) == 0  # not --quiet: the summary line is wanted
    line = capsys.readouterr().out
    report = json.loads((out / "report.json").read_text())
    change = {c["effect"]: c for c in report["change"]}
    assert set(change) == {"timing", "drift"}, report["change_info"]["selection"]
    for c in report["change"]:
        assert {"effect", "reduction", "p_value", "confidence", "parameters", "advice"} <= set(c)
    assert change["timing"]["parameters"]["lag_shift_ms"] == pytest.approx(-40.0, abs=8.0)
    assert change["drift"]["parameters"]["level_change_db"] == pytest.approx(2.9, abs=0.8)
    shift = change["timing"]["parameters"]["joint_lag_shift_s"]
    assert f"add {shift:+g} s to the joint lag" in change["timing"]["advice"]
    assert f"changed since {warm_pair / 'cold'}: " in line and "timing -4" in line
    assert report["inputs"]["reference"] == str(warm_pair / "cold")
    md = (out / "report.md").read_text()
    assert f"**What changed since `{warm_pair / 'cold'}`:**" in md
    # the warm recording's own diagnosis: its lag, with the exact flags and paths
    assert report["verdict"]["effects"][0]["effect"] == "timing"
    assert report["advice"]["settings"]["joint_lag_s"] == pytest.approx(-0.04, abs=0.008)
    denoise = report["advice"]["commands"]["denoise"]
    assert denoise.startswith(f"egovib denoise {warm_pair / 'warm'} --model {model_path} ")
    assert "--joint-lag -0.0" in denoise
    applied = report["advice"]["applied"]
    assert applied["method"] == "paper" and applied["gain_db"] > 0.3, applied


def test_references_pair_with_the_real_bags(model_path, warm_pair, tmp_path, capsys):
    """Several --real bags: one --reference for all, or one per bag (in order); a count that
    matches neither is one line naming --reference, exit 2, nothing written."""
    from egovib_ros.bag.many import BagJob
    from egovib_ros.cli.gap import reference_bags

    jobs = [BagJob(warm_pair / "warm"), BagJob(warm_pair / "cold")]
    reals = [str(warm_pair / "warm"), str(warm_pair / "cold")]
    one = reference_bags([str(warm_pair / "cold")], jobs, reals)
    assert set(one.values()) == {str(warm_pair / "cold")}
    paired = reference_bags([str(warm_pair / "cold"), str(warm_pair / "warm")], jobs, reals)
    assert paired == {str(warm_pair / "warm"): str(warm_pair / "cold"),
                      str(warm_pair / "cold"): str(warm_pair / "warm")}  # fmt: skip
    # a fleet: directories of bags, matched by the bags' names under them
    import shutil

    for fleet in ("today", "last_month"):
        for robot, bag in (("robot1", "warm"), ("robot2", "cold")):
            shutil.copytree(warm_pair / bag, tmp_path / fleet / robot)
    fleet_jobs = [BagJob(tmp_path / "today" / r) for r in ("robot1", "robot2")]
    matched = reference_bags([str(tmp_path / "last_month")], fleet_jobs, [str(tmp_path / "today")])
    assert matched == {
        str(tmp_path / "today" / r): str(tmp_path / "last_month" / r) for r in ("robot1", "robot2")
    }
    out = tmp_path / "out"
    args = ["gap", "--model", str(model_path), "--real", *reals, "--out", str(out)]
    # a reference may serve several bags; three for two is refused
    refs = ["--reference", *(str(warm_pair / b) for b in ("cold", "warm", "cold"))]
    assert main(args + refs + ["--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--reference: 3 bags for 2 --real bags" in err
    assert not out.exists()


def test_the_summary_line_names_each_change_by_its_effect():
    """A position or acceleration change carries the level it brings: the summary line names
    it by its effect, not as a drift (it did, from the level, once changes carried one)."""
    said = [
        _change_said({"effect": e, "parameters": p})
        for e, p in (
            ("timing", {"lag_shift_ms": -39.6, "joint_lag_shift_s": -0.0396}),
            ("drift", {"level_change_db": 2.94}),
            ("position", {"level_change_db": -0.31, "term": {}}),
            ("coupling", {"term": {}}),
        )
    ]
    assert said == ["timing -40 ms", "drift +2.9 dB", "position -0.3 dB", "coupling"]
