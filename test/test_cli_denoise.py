"""`egovib denoise` on real bag files, as a user runs it after `egovib calibrate`: the drop-in
output, channels, compression, any robot profile, many bags in parallel, bad input."""

import dataclasses
import json
import shutil

import bagcorpus
import numpy as np
import pytest
import robots
from rosbags.rosbag2 import Reader
from simbags import egovib, egovib_process, topic_messages, write_robot_bag

from egovib_ros.bag import bag_topics, read_recording, write_recording
from egovib_ros.bag.codec import imu_field_offset, typestore
from egovib_ros.core import NoiseModel, calibrate_arrays
from egovib_ros.core.methods import denoise_batch_method
from egovib_ros.sim import simulate_motion


def test_calibrate_then_denoise_round_trip(sim_bags):
    model_path = sim_bags / "model.npz"
    result = egovib("calibrate", sim_bags / "sweep", "--out", model_path, "--quiet")
    assert result.returncode == 0, result.stderr
    model = NoiseModel.load(model_path)
    assert model.measured == "superposition"  # auto-detected
    assert np.all(model.counts[model.axis_mask()] > 0)
    assert model.provenance["source"].endswith("sweep")

    out = sim_bags / "denoised"
    result = egovib("denoise", sim_bags / "motion", "--model", model_path, "--out", out, "--quiet")
    assert result.returncode == 0, result.stderr
    topics = bag_topics(out)
    raw_count = topics["/accelerometer/raw"][1]
    assert topics["/accelerometer/denoised"] == ("sensor_msgs/msg/Imu", raw_count)
    for topic in ("/joint_states", "/accelerometer/contact", "/accelerometer/ego"):
        assert topic in topics
    rec = read_recording(out)
    np.testing.assert_array_equal(rec.denoised_stamps_ns, rec.sensor_stamps_ns)
    _, expected, _ = denoise_batch_method(  # the default: hybrid, drop-in
        rec.sensor_stamps_ns, rec.sensor, rec.joint_stamps_ns, rec.joint_velocity, model
    )
    np.testing.assert_allclose(rec.denoised, expected, rtol=0, atol=1e-12)
    assert "denoised by hybrid (per_axis, dropin" in result.stderr or "--quiet" in result.args


def test_combined_channel_goes_to_x(sim_bags):
    model_path = sim_bags / "model_c.npz"
    assert egovib("calibrate", sim_bags / "sweep", "--out", model_path, "--quiet").returncode == 0
    out = sim_bags / "denoised_combined"
    result = egovib(
        "denoise",
        sim_bags / "motion",
        "--model",
        model_path,
        "--out",
        out,
        "--channels",
        "combined",
        "--quiet",
    )
    assert result.returncode == 0, result.stderr
    rec = read_recording(out)
    assert np.all(rec.denoised[:, 1:] == 0) and np.any(rec.denoised[:, 0] != 0)


def test_bad_input_is_one_line_exit_2_and_leaves_nothing(sim_bags, tmp_path):
    result = egovib("calibrate", tmp_path / "absent", "--out", tmp_path / "m.npz")
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "absent: no such bag" in result.stderr
    assert not (tmp_path / "m.npz").exists()

    broken = tmp_path / "broken.npz"
    broken.write_bytes(b"PK\x03\x04 not really a zip")
    result = egovib("denoise", sim_bags / "motion", "--model", broken, "--out", tmp_path / "out")
    assert result.returncode == 2 and "broken.npz" in result.stderr
    assert result.stderr.strip().count("\n") == 0
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob("*.partial"))

    # A bag without steady grid velocities is not a calibration sweep.
    result = egovib("calibrate", sim_bags / "motion", "--out", tmp_path / "m.npz", "--quiet")
    if result.returncode == 2:
        assert "calibration sweep" in result.stderr and not (tmp_path / "m.npz").exists()
    else:  # random motion does cross grid cells now and then; then a (sparse) model is fine
        assert NoiseModel.load(tmp_path / "m.npz").counts.sum() > 0


@pytest.mark.parametrize("method", ["paper", "hybrid"])
def test_denoised_message_is_the_raw_message_with_the_field_replaced(
    sim_bags, sim_bags_model, sim_methods_model_path, method
):
    """The default output of every method is the drop-in one: gravity kept."""
    out = sim_bags / f"dropin_{method}"
    model = sim_bags_model if method == "paper" else sim_methods_model_path
    run = egovib(
        "denoise", sim_bags / "motion", "--model", model, "--method", method, "--out", out,
        "--quiet",
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    rec = read_recording(out)
    assert np.array_equal(rec.denoised_stamps_ns, rec.sensor_stamps_ns)
    assert abs(rec.denoised[:, 2].mean() - rec.sensor[:, 2].mean()) < 0.01  # 9.81: gravity
    raw, den = (
        topic_messages(out, "/accelerometer/raw"),
        topic_messages(out, "/accelerometer/denoised"),
    )
    assert len(raw) == len(den)
    assert [t for t, _ in raw] == [t for t, _ in den]  # the raw sample's stamp and log time
    a = np.frombuffer(b"".join(d for _, d in raw), np.uint8).reshape(len(raw), -1)
    b = np.frombuffer(b"".join(d for _, d in den), np.uint8).reshape(len(den), -1)
    frame_len = int.from_bytes(raw[0][1][12:16], "little") - 1  # the CDR string length of frame_id
    field_at = imu_field_offset(frame_len, "linear_acceleration")
    changed = np.flatnonzero((a != b).any(axis=0))
    assert changed.min() >= field_at and changed.max() < field_at + 24
    # every input topic is in the output byte for byte
    for topic in (
        "/accelerometer/raw",
        "/accelerometer/contact",
        "/joint_states",
        "/hand_velocity_controller/commands",
    ):
        assert topic_messages(out, topic) == topic_messages(sim_bags / "motion", topic), topic


def test_a_bag_holding_the_denoised_topic_already_is_refused_unless_replaced(
    sim_bags, sim_bags_model, tmp_path
):
    """A recorded live run carries the denoiser's topic: its copy was dropped and replaced
    without a word. Now refused in one line (exit 2, nothing written); --replace-denoised
    writes egovib's in its place and says so; the other topics are copied as they were."""
    first = tmp_path / "first"
    run = egovib("denoise", sim_bags / "motion", "--model", sim_bags_model, "--out", first)
    assert run.returncode == 0, run.stderr
    refused = egovib("denoise", first, "--model", sim_bags_model, "--out", tmp_path / "again")
    assert refused.returncode == 2, refused.stderr
    line = refused.stderr.strip()
    assert "\n" not in line and "already holds /accelerometer/denoised" in line, line
    assert str(first) in line and "--replace-denoised" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["first"]
    again = egovib(
        "denoise", first, "--model", sim_bags_model, "--out", tmp_path / "again",
        "--method", "paper", "--oversubtraction", "2", "--replace-denoised",
    )  # fmt: skip
    assert again.returncode == 0, again.stderr
    n = bag_topics(first)["/accelerometer/raw"][1]
    assert f"the bag's own denoised topic replaced ({n} messages)" in again.stderr
    replaced = topic_messages(tmp_path / "again", "/accelerometer/denoised")
    assert len(replaced) == n and replaced != topic_messages(first, "/accelerometer/denoised")
    for topic in ("/accelerometer/raw", "/joint_states"):
        assert topic_messages(tmp_path / "again", topic) == topic_messages(first, topic), topic


def test_zstd_output_reads_back_identical(sim_bags, sim_bags_model):
    plain, packed = sim_bags / "out_plain", sim_bags / "out_zstd"
    for out, extra in ((plain, ()), (packed, ("--compress", "zstd"))):
        result = egovib(
            "denoise",
            sim_bags / "motion",
            "--model",
            sim_bags_model,
            "--out",
            out,
            *extra,
        )
        assert result.returncode == 0, result.stderr
    assert "zstd size ratio" in result.stderr  # the summary (not with --quiet)
    assert topic_messages(plain, "/accelerometer/denoised") == topic_messages(
        packed, "/accelerometer/denoised"
    )
    size = {p: next(p.glob("*.mcap")).stat().st_size for p in (plain, packed)}
    assert size[plain] > 5 * size[packed]


def test_any_robot_from_profile_to_denoised_bag(tmp_path):
    p = robots.profile(3, rate_hz=1600.0)
    (tmp_path / "robot.yaml").write_text(p.dumps())
    train, test = (
        robots.recording(p, 60.0, seed=1, joint_rate_hz=400.0),
        robots.recording(p, 8.0, seed=2, joint_rate_hz=400.0, taps_per_s=2.0),
    )
    write_robot_bag(tmp_path / "train", p, train)
    write_robot_bag(tmp_path / "test", p, test)
    result = egovib(
        "calibrate",
        tmp_path / "train",
        "--robot",
        tmp_path / "robot.yaml",
        "--grid",
        "free",
        "--out",
        tmp_path / "m.npz",
    )
    assert result.returncode == 0, result.stderr
    assert "coverage:" in result.stderr and "blocks per measured cell" in result.stderr
    model = NoiseModel.load(tmp_path / "m.npz")
    expected_model, _ = calibrate_arrays(
        train["t_acc"], train["accel"], train["t_joint"], train["velocity"], profile=p, sweep="free"
    )
    assert model.profile == p
    np.testing.assert_array_equal(model.cells, expected_model.cells)
    np.testing.assert_array_equal(model.cell_counts, expected_model.cell_counts)
    np.testing.assert_allclose(model.cell_mean, expected_model.cell_mean, rtol=1e-12, atol=0)

    result = egovib(
        "denoise",
        tmp_path / "test",
        "--model",
        tmp_path / "m.npz",
        "--out",
        tmp_path / "out",
        "--quiet",
    )
    assert result.returncode == 0, result.stderr
    assert set(bag_topics(tmp_path / "out")) == {p.sensor_topic, p.joints_topic, p.denoised_topic}
    out = read_recording(tmp_path / "out", profile=p)
    stamps, values, _ = denoise_batch_method(
        test["t_acc"], test["accel"], test["t_joint"], test["velocity"], model
    )
    np.testing.assert_array_equal(out.denoised_stamps_ns, stamps)
    np.testing.assert_array_equal(out.denoised, values)


# --------------------------------------------------------------------------
# Many bags
# --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fleet(sim_bags):
    """Four short bags (one broken) in a directory tree."""
    root = sim_bags / "fleet"
    for seed in range(3):
        motion, _ = simulate_motion(duration_s=2.0, max_speed=0.5, tap_rate_hz=1.0, seed=20 + seed)
        write_recording(root / ("day1" if seed < 2 else "day2") / f"run{seed}", motion)
    broken = root / "day2" / "broken"
    shutil.copytree(root / "day1" / "run0", broken)
    mcap = next(broken.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[: len(mcap.read_bytes()) // 2])
    return root


def test_many_bags_in_parallel_equal_single_runs_and_a_broken_one_is_named(
    sim_bags, fleet, sim_bags_model, tmp_path
):
    singles = {}
    for name in ("day1/run0", "day1/run1", "day2/run2"):
        out = tmp_path / "single" / name
        assert (
            egovib(
                "denoise", fleet / name, "--model", sim_bags_model, "--out", out, "--quiet"
            ).returncode
            == 0
        )
        singles[name] = topic_messages(out, "/accelerometer/denoised")
    for jobs in ("1", "2"):
        out = tmp_path / f"jobs{jobs}"
        result = egovib(
            "denoise", fleet, "--model", sim_bags_model, "--out", out, "--jobs", jobs, "--quiet"
        )
        assert result.returncode == 2
        assert "day2/broken" in result.stderr and "FAILED" in result.stderr
        assert "4 bag(s): 3 done, 1 failed" in result.stderr
        assert not (out / "day2" / "broken").exists()
        assert not list(out.rglob("*.partial"))
        for name, expected in singles.items():
            assert topic_messages(out / name, "/accelerometer/denoised") == expected, (jobs, name)
    # Outputs inside the input directory would be taken for inputs by the next run.
    inside = fleet / "clean"
    result = egovib("denoise", fleet, "--model", sim_bags_model, "--out", inside, "--quiet")
    assert result.returncode == 2 and "inside the input" in result.stderr
    assert [line for line in result.stderr.splitlines() if "error" in line] == [
        f"egovib: error: {inside}: --out is inside the input {fleet}; write it elsewhere"
    ]
    assert not inside.exists()


def test_positions_only_joint_states_give_the_same_denoising_within_half_a_db(
    sim_bags, sim_bags_model, tmp_path
):
    """A driver that publishes JointState positions only (no velocity): calibrate, denoise
    and evaluate differentiate the positions (profile joints.velocity: auto) and denoise
    within 0.5 dB of the same run with velocities (its model: `egovib calibrate` of the
    sweep with them, the session's)."""
    positions_only = bagcorpus.Layout("positions_only", velocity=False)
    figures = {}
    for name, layout in (("with", None), ("without", positions_only)):
        motion, model = sim_bags / "motion", sim_bags_model
        if layout is not None:
            sweep = bagcorpus.write_layout(sim_bags / "sweep", tmp_path / "sweep_positions", layout)
            motion = bagcorpus.write_layout(motion, tmp_path / "motion_positions", layout)
            model = tmp_path / f"{name}.npz"
            result = egovib("calibrate", sweep, "--out", model, "--quiet")
            assert result.returncode == 0, result.stderr
        result = egovib("denoise", motion, "--model", model, "--out", tmp_path / f"den_{name}")
        assert result.returncode == 0, result.stderr
        report = tmp_path / f"{name}.json"
        evaluate = ("evaluate", motion, "--model", model, "--json", report, "--quiet")
        result = egovib(*evaluate, "--methods", "default")  # the figure asserted
        assert result.returncode == 0, result.stderr
        # the first joint state has no velocity yet (no difference): not bad input, unsaid
        assert "joint states" not in result.stderr, result.stderr
        figures[name] = json.loads(report.read_text())["noise_reduction_db"]
    assert figures["with"] > 15 and abs(figures["with"] - figures["without"]) < 0.5, figures
    with Reader(tmp_path / "motion_positions") as reader:  # positions only, indeed
        conn = next(c for c in reader.connections if c.msgtype.endswith("JointState"))
        _, _, data = next(reader.messages(connections=[conn]))
        assert len(typestore().deserialize_cdr(data, conn.msgtype).velocity) == 0


def test_joint_states_of_a_stuck_clock_are_refused_naming_the_joint_state_topic(
    sim_bags, sim_bags_model, tmp_path
):
    """A driver that stamps every JointState 0: one line naming the joint-state topic (not
    the sensor topic), exit 2, no output."""
    conns, messages = bagcorpus.read_messages(sim_bags / "motion")
    stuck = [
        (t, log, bagcorpus._with_stamp(d, 0)) if t == "/joint_states" else (t, log, d)
        for t, log, d in messages
    ]
    bagcorpus._write_rosbags(tmp_path / "stuck", conns, stuck, bagcorpus.Layout("stuck"))
    result = egovib(
        "denoise", tmp_path / "stuck", "--model", sim_bags_model, "--out", tmp_path / "out"
    )
    assert result.returncode == 2
    assert result.stderr.count("error:") == 1
    line = result.stderr.strip().splitlines()[-1]  # after the warnings it met on the way
    assert "stuck: /joint_states: " in line and "joint states" in line
    assert "/accelerometer/raw" not in line
    assert not (tmp_path / "out").exists()


def test_noise_gain_from_a_gap_report_follows_the_warm_up_and_bad_reports_are_one_line(
    sim_bags, sim_bags_model, tmp_path
):
    """--noise-gain takes a gap report's drift advice (the fitted level change over elapsed
    time): the denoiser's noise estimate follows it, so more is removed where it rose; a
    file that is not a report with a drift verdict is one line, exit 2, nothing written."""
    report = tmp_path / "report.json"
    knots = [[0.0, 0.0], [1.0, 0.0], [2.0, 6.0]]  # 6 dB louder from 2 s on
    report.write_text(json.dumps({"advice": {"settings": {"noise_gain_db": knots}}}))
    for method, less in (("paper", 0.8), ("hybrid", 1.0)):
        # (hybrid's gains follow a level change of the noise by themselves, within a few
        # tenths of a second, and sit near their floor on noise: the advice moves it little)
        outs = {}
        for name, extra in (("plain", ()), ("followed", ("--noise-gain", report))):
            outs[name] = tmp_path / f"{name}_{method}"
            result = egovib(
                "denoise", sim_bags / "motion", "--model", sim_bags_model, "--out", outs[name],
                "--channels", "combined", "--method", method, "--quiet", *extra,
            )  # fmt: skip
            assert result.returncode == 0, result.stderr
        plain, followed = (
            read_recording(outs[n], ground_truth=False) for n in ("plain", "followed")
        )
        t = (plain.denoised_stamps_ns - plain.denoised_stamps_ns[0]) / 1e9
        np.testing.assert_array_equal(plain.denoised[t < 0.9], followed.denoised[t < 0.9])
        late = t > 2.5
        assert (
            np.abs(followed.denoised[late, 0]).mean()
            < less * np.abs(plain.denoised[late, 0]).mean()
        ), method

    no_drift = tmp_path / "no_drift.json"
    no_drift.write_text(json.dumps({"advice": {"settings": {"joint_lag_s": 0.02}}}))
    for bad, said in ((no_drift, "drift verdict"), (tmp_path / "absent.json", "absent.json")):
        result = egovib(
            "denoise", sim_bags / "motion", "--model", sim_bags_model, "--out", tmp_path / "x",
            "--noise-gain", bad,
        )  # fmt: skip
        assert result.returncode == 2 and said in result.stderr, result.stderr
        assert result.stderr.strip().count("\n") == 0 and not (tmp_path / "x").exists()


def test_adapt_learns_while_denoising_and_save_model_writes_the_adapted_model(
    sim_bags, sim_bags_model, tmp_path
):
    """--adapt: the denoised topic of a model learning as it goes (the library's adapting
    denoiser, message for message); --save-model: the model as adapted, which
    `egovib model show` marks and `egovib denoise` uses; bad combinations one line."""
    from egovib_ros.core.adapt import AdaptSettings, learnt_state

    out, saved = tmp_path / "adapted", tmp_path / "adapted.npz"
    args = ["denoise", sim_bags / "motion", "--model", sim_bags_model, "--out", out]
    result = egovib(*args, "--adapt", "--forget-s", "10", "--save-model", saved)
    assert result.returncode == 0, result.stderr
    assert "adapted:" in result.stderr and f"model written to {saved}" in result.stderr
    model = NoiseModel.load(sim_bags_model)
    rec = read_recording(out)
    _, expected, _ = denoise_batch_method(
        rec.sensor_stamps_ns,
        rec.sensor,
        rec.joint_stamps_ns,
        rec.joint_velocity,
        model,
        adapt=AdaptSettings(forget_s=10.0),
    )
    np.testing.assert_allclose(rec.denoised, expected, rtol=0, atol=1e-12)
    adapted = NoiseModel.load(saved)
    residual, harmonic = learnt_state(adapted)
    assert len(residual["cells"]) > 0 and residual["blocks"].sum() > 0
    assert residual["new"].any()  # the motion goes where the superposition sweep never did
    show = tmp_path / "show"
    result = egovib("model", "show", saved, "--out", show)
    assert result.returncode == 0, result.stderr
    assert "learnt online (adapt, forgetting time 10 s)" in result.stderr
    assert (show / "online.png").is_file()
    assert "## Learnt online" in (show / "summary.md").read_text()
    for extra, message in (
        (["--save-model", tmp_path / "x.npz"], "--save-model: applies with --adapt only"),
        (["--forget-s", "5"], "--forget-s applies with --adapt only"),
        (["--adapt", "--method", "paper"], "method paper: adapt applies to `cancel` and `hybrid`"),
        (["--adapt", "--forget-s", "0"], "--forget-s: expected a number in [0.01, 1e+06]"),
    ):
        result = egovib(*args[:-1], tmp_path / "never", *extra)
        errors = [line for line in result.stderr.splitlines() if "error" in line]
        assert result.returncode == 2 and len(errors) == 1 and message in errors[0], result.stderr
        assert not (tmp_path / "never").exists() and not (tmp_path / "x.npz").exists()


def test_samples_left_without_joint_states_are_said_even_quiet(sim_bags, sim_bags_model, tmp_path):
    """Joint states that stop 0.5 s before the sensor (a recording cut short): the default
    writes those samples as read; the run says so in a WARNING, --quiet too (it once said
    it only in the summary --quiet drops). A bag whose joint states span it says nothing."""
    rec = read_recording(sim_bags / "motion", ground_truth=False, denoised=False)
    keep = rec.joint_stamps_ns < rec.sensor_stamps_ns[-1] - 500_000_000
    short = dataclasses.replace(
        rec,
        joint_stamps_ns=rec.joint_stamps_ns[keep],
        joint_position=rec.joint_position[keep],
        joint_velocity=rec.joint_velocity[keep],
    )
    write_recording(tmp_path / "short", short)
    said = {}
    for name, bag in (("short", tmp_path / "short"), ("whole", sim_bags / "motion")):
        run = egovib_process(
            "denoise", bag, "--model", sim_bags_model, "--out", tmp_path / f"out_{name}", "--quiet"
        )
        assert run.returncode == 0, run.stderr
        said[name] = [line for line in run.stderr.splitlines() if "no joint state" in line]
    assert len(said["short"]) == 1 and "written without denoising" in said["short"][0]
    head = f"egovib: WARNING: {tmp_path / 'short'}: "
    assert said["short"][0].startswith(head), said
    # the last 0.5 s (1500 samples) but the joint state's hold after the last one
    assert 1000 < int(said["short"][0][len(head) :].split()[0]) <= 1500, said
    assert said["whole"] == []
