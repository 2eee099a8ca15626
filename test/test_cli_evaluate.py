"""`egovib evaluate` end to end on a small simulated bag, and its bad-input errors."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from egovib_ros.bag import read_recording, write_recording
from egovib_ros.cli import main
from egovib_ros.core import calibrate_arrays
from egovib_ros.evaluation.evaluate import REPORT_FIELDS


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A superposition sweep -> model file, a 10 s motion bag with taps, and a no-contact bag."""
    from egovib_ros.sim import simulate_motion, simulate_sweep

    root = tmp_path_factory.mktemp("evaluate")
    sweep, _ = simulate_sweep(
        grid="superposition", dwell_s=1.0, settle_s=0.3, effects={}, seed=11, params=None
    )
    model, _ = calibrate_arrays(
        sweep.sensor_stamps_ns,
        sweep.sensor,
        sweep.joint_stamps_ns,
        sweep.joint_velocity,
        sweep="superposition",
        source="test sweep",
    )
    model_path = root / "model.npz"
    model.save(model_path)
    motion, truth = simulate_motion(
        duration_s=10.0, max_speed=0.5, tap_rate_hz=2.0, effects={}, seed=12, params=None
    )
    bag = root / "motion_bag"
    write_recording(bag, motion)
    quiet, _ = simulate_motion(
        duration_s=6.0, max_speed=0.5, tap_rate_hz=0.0, effects={}, seed=13, params=None
    )
    quiet_bag = root / "quiet_bag"
    write_recording(quiet_bag, quiet)
    # The same data as a real robot would record it: no ground-truth topics.
    robot_bag = root / "robot_bag"
    write_recording(robot_bag, dataclasses.replace(quiet, contact=None, ego=None))
    return {
        "root": root,
        "model": model_path,
        "bag": bag,
        "quiet_bag": quiet_bag,
        "robot_bag": robot_bag,
        "truth": truth,
    }


def test_evaluate_writes_contract_fields(simulated, capsys):
    out = simulated["root"] / "report.json"
    code = main([
        "evaluate", str(simulated["bag"]), "--model", str(simulated["model"]), "--json", str(out),
        "--calibration", str(simulated["quiet_bag"]),
    ])  # fmt: skip
    assert code == 0
    report = json.loads(out.read_text())
    for field in REPORT_FIELDS:
        assert field in report, field
    # The taps found from the contact topic are the simulator's taps (truth file onsets).
    onsets_ns = simulated["truth"].get("tap_onsets_ns", [])
    assert report["n_taps"] == len(onsets_ns) > 0
    assert report["noise_mean_denoised"] < report["noise_mean_raw"]
    assert report["noise_reduction_db"] == pytest.approx(
        20 * np.log10(report["noise_mean_raw"] / report["noise_mean_denoised"])
    )
    assert report["peak_snr_denoised_db"] > report["peak_snr_raw_db"]
    assert 0 < report["tap_retention"] <= 1.5
    assert report["alignment_lag_samples"] == 0
    assert report["threshold_source"].startswith("calibration")
    assert set(report["methods"]) >= {
        "bandpass",
        "boll",
        "paper",
        "wiener",
        "noisereduce",
        "per_axis",
    }
    assert "wrote" in capsys.readouterr().out


def test_evaluate_without_ground_truth_is_a_one_line_error(simulated, capsys):
    out = simulated["root"] / "no_truth.json"
    bag, model = str(simulated["robot_bag"]), str(simulated["model"])
    code = main(["evaluate", bag, "--model", model, "--json", str(out)])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "/accelerometer/contact" in err and "robot_bag" in err
    assert not out.exists()


@pytest.mark.parametrize("case", ["missing_bag", "missing_model", "corrupt_model", "not_a_bag"])
def test_evaluate_bad_input_exit_2_no_output(simulated, tmp_path, capsys, case):
    bag, model = str(simulated["bag"]), str(simulated["model"])
    if case == "missing_bag":
        bag = str(tmp_path / "nope")
    elif case == "missing_model":
        model = str(tmp_path / "nope.npz")
    elif case == "corrupt_model":
        Path(tmp_path / "bad.npz").write_bytes(b"not a zip")
        model = str(tmp_path / "bad.npz")
    else:
        (tmp_path / "empty_dir").mkdir()
        bag = str(tmp_path / "empty_dir")
    out = tmp_path / "out.json"
    assert main(["evaluate", bag, "--model", model, "--json", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("egovib: error:") and err.count("\n") == 0
    assert not out.exists()


def test_evaluate_unknown_method_is_config_error(simulated, tmp_path, capsys):
    out = tmp_path / "out.json"
    bag, model = str(simulated["bag"]), str(simulated["model"])
    args = ["evaluate", bag, "--model", model, "--json", str(out), "--methods", "paper,magic"]
    assert main(args) == 2
    assert "magic" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize(
    "channels, output, like",
    [("combined", "bandpassed", "paper"), ("per_axis", "bandpassed", "per_axis"),
     ("per_axis", "dropin", "default")],
)  # fmt: skip
def test_evaluate_scores_the_bags_own_denoised_topic(simulated, tmp_path, channels, output, like):
    """A bag from `egovib denoise` is scored as 'bag_denoised' and matches the batch
    method it came from; a drop-in output (gravity and all outside the band kept) is
    recognised, band-passed first, and compared with the default (what `egovib denoise`
    writes without options: here the paper's, the model holds no other)."""
    denoised_bag = tmp_path / "denoised_bag"
    assert main([
        "denoise", str(simulated["bag"]), "--model", str(simulated["model"]), "--out",
        str(denoised_bag), "--channels", channels, "--output", output, "--quiet",
    ]) == 0  # fmt: skip
    out = tmp_path / "report.json"
    assert main([
        "evaluate", str(denoised_bag), "--model", str(simulated["model"]), "--json", str(out),
        "--calibration", str(simulated["quiet_bag"]), "--methods", f"paper,{like}", "--quiet",
    ]) == 0  # fmt: skip
    bag = json.loads(out.read_text())["methods"]["bag_denoised"]
    assert like in bag["label"] and ("drop-in" in bag["label"]) == (output == "dropin")
    assert bag["samples_missing"] == 0 and bag["alignment_lag_samples"] == 0
    assert bag["rms_difference_vs_batch"] < 1e-6
    if output == "dropin":
        # the same figures as the default's; within 0.5 dB of the band-passed output; gravity
        methods = json.loads(out.read_text())["methods"]
        assert bag["noise_reduction_db"] == pytest.approx(methods[like]["noise_reduction_db"])
        assert abs(bag["noise_reduction_db"] - methods["paper"]["noise_reduction_db"]) < 0.5
        rec = read_recording(denoised_bag)
        assert rec.sensor[:, 2].mean() > 9.0
        assert abs(rec.denoised[:, 2].mean() - rec.sensor[:, 2].mean()) < 1e-3


def test_force_replaces_only_a_report_evaluate_wrote(simulated, tmp_path, capsys):
    """--force replaces a previous report, never a JSON of the user's."""
    out = tmp_path / "settings.json"
    out.write_text('{"my": "settings"}\n')
    args = [
        "evaluate", str(simulated["bag"]), "--model", str(simulated["model"]),
        "--calibration", str(simulated["quiet_bag"]), "--json", str(out), "--force", "--quiet",
        "--methods", "paper",  # (which methods: test_evaluate_writes_contract_fields)
    ]  # fmt: skip
    assert main(args) == 2
    assert "not an output of this command" in capsys.readouterr().err
    assert out.read_text() == '{"my": "settings"}\n'
    out.unlink()
    assert main(args) == 0
    first = out.read_text()
    assert main(args) == 0 and out.read_text() == first  # ours: replaced (same figures)


def test_the_summary_line_shows_the_bags_denoised_topic_and_a_gap_advice_applied(
    simulated, tmp_path, capsys
):
    """Joint states stamped 40 ms late; the gap advice (joint lag -0.04) applied with
    `egovib denoise --joint-lag`: the summary line gives the bag's own denoised topic beside
    egovib's re-denoising of the raw topic, and the gain shows there (issue 34 item 4)."""
    from egovib_ros.sim import simulate_motion

    late, _ = simulate_motion(
        duration_s=10.0, max_speed=0.6, tap_rate_hz=1.0, effects={"timing": 0.04}, seed=21
    )
    raw = tmp_path / "late"
    write_recording(raw, late)
    lines = {}
    for name, extra in (("without", []), ("with", ["--joint-lag", "-0.04"])):
        denoised = tmp_path / f"den_{name}"
        args = ["denoise", str(raw), "--model", str(simulated["model"]), "--out", str(denoised)]
        assert main(args + extra + ["--quiet"]) == 0
        out = tmp_path / f"{name}.json"
        capsys.readouterr()
        args = ["evaluate", str(denoised), "--model", str(simulated["model"]), "--json", str(out)]
        args += ["--calibration", str(simulated["quiet_bag"]), "--methods", "default"]
        assert main(args) == 0
        lines[name] = capsys.readouterr().out.strip()
        report = json.loads(out.read_text())
        recorded = report["methods"]["bag_denoised"]["noise_reduction_db"]
        assert (
            f"the bag's /accelerometer/denoised: noise reduction {recorded:.1f} dB" in lines[name]
        ), lines[name]

    def figures(line: str) -> tuple[float, float]:
        own = float(line.split("noise reduction ")[1].split(" dB")[0])
        bag = float(line.split("/accelerometer/denoised: noise reduction ")[1].split(" dB")[0])
        return own, bag

    (own_without, bag_without), (own_with, bag_with) = (
        figures(lines["without"]),
        figures(lines["with"]),
    )
    assert own_with == own_without  # egovib's own re-denoising of the raw topic: no lag
    assert bag_with > bag_without + 0.5, lines  # the advice applied shows in the line
