"""`egovib calibrate` and `egovib denoise` on real bag files, as a user runs them."""

import dataclasses
import json
import shutil
import subprocess
import sys

import bagcorpus
import numpy as np
import pytest
import robots
from rosbags.rosbag2 import Reader

from egovib_ros.bag import BagWriter, bag_topics, read_recording, write_recording
from egovib_ros.bag.codec import (
    encode_imu_batch,
    encode_joint_state_batch,
    imu_field_offset,
    joint_state_message,
    typestore,
)
from egovib_ros.bag.denoise import denoise_bag
from egovib_ros.core import NoiseModel, calibrate_arrays, denoise_batch
from egovib_ros.robot import load_profile
from egovib_ros.sim import simulate_motion, simulate_sweep


def egovib(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "egovib_ros.cli", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
    )


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("offline")
    sweep, _ = simulate_sweep(grid="superposition", dwell_s=1.0, settle_s=0.3, seed=3)
    # A calibration bag needs no ground truth; leaving it out keeps the test quick.
    write_recording(root / "sweep", dataclasses.replace(sweep, contact=None, ego=None))
    motion, _ = simulate_motion(duration_s=4.0, max_speed=0.5, tap_rate_hz=1.0, seed=4)
    write_recording(root / "motion", motion)
    return root


@pytest.fixture(scope="module")
def model_path(bags):
    path = bags / "fixture_model.npz"
    result = egovib("calibrate", bags / "sweep", "--out", path, "--quiet")
    assert result.returncode == 0, result.stderr
    return path


def test_calibrate_then_denoise_round_trip(bags):
    model_path = bags / "model.npz"
    result = egovib("calibrate", bags / "sweep", "--out", model_path, "--quiet")
    assert result.returncode == 0, result.stderr
    model = NoiseModel.load(model_path)
    assert model.measured == "superposition"  # auto-detected
    assert np.all(model.counts[model.axis_mask()] > 0)
    assert model.provenance["source"].endswith("sweep")

    out = bags / "denoised"
    result = egovib("denoise", bags / "motion", "--model", model_path, "--out", out, "--quiet")
    assert result.returncode == 0, result.stderr
    topics = bag_topics(out)
    raw_count = topics["/accelerometer/raw"][1]
    assert topics["/accelerometer/denoised"] == ("sensor_msgs/msg/Imu", raw_count)
    for topic in ("/joint_states", "/accelerometer/contact", "/accelerometer/ego"):
        assert topic in topics
    rec = read_recording(out)
    np.testing.assert_array_equal(rec.denoised_stamps_ns, rec.sensor_stamps_ns)
    _, expected, _ = denoise_batch(
        rec.sensor_stamps_ns, rec.sensor, rec.joint_stamps_ns, rec.joint_velocity, model
    )
    np.testing.assert_allclose(rec.denoised, expected, rtol=0, atol=1e-12)


def test_combined_channel_goes_to_x(bags):
    model_path = bags / "model_c.npz"
    assert egovib("calibrate", bags / "sweep", "--out", model_path, "--quiet").returncode == 0
    out = bags / "denoised_combined"
    result = egovib(
        "denoise",
        bags / "motion",
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


def test_bad_input_is_one_line_exit_2_and_leaves_nothing(bags, tmp_path):
    result = egovib("calibrate", tmp_path / "absent", "--out", tmp_path / "m.npz")
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0 and "absent: no such bag" in result.stderr
    assert not (tmp_path / "m.npz").exists()

    broken = tmp_path / "broken.npz"
    broken.write_bytes(b"PK\x03\x04 not really a zip")
    result = egovib("denoise", bags / "motion", "--model", broken, "--out", tmp_path / "out")
    assert result.returncode == 2 and "broken.npz" in result.stderr
    assert result.stderr.strip().count("\n") == 0
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob("*.partial"))

    # A bag without steady grid velocities is not a calibration sweep.
    result = egovib("calibrate", bags / "motion", "--out", tmp_path / "m.npz", "--quiet")
    if result.returncode == 2:
        assert "calibration sweep" in result.stderr and not (tmp_path / "m.npz").exists()
    else:  # random motion does cross grid cells now and then; then a (sparse) model is fine
        assert NoiseModel.load(tmp_path / "m.npz").counts.sum() > 0


# --------------------------------------------------------------------------
# Output: the input message with the field replaced, streamed, compressed
# --------------------------------------------------------------------------
def _messages(bag, topic):
    with Reader(bag) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        return [(t, bytes(d)) for _, t, d in reader.messages(connections=conns)]


def test_denoised_message_is_the_raw_message_with_the_field_replaced(bags, model_path):
    out = bags / "dropin"
    assert (
        egovib(
            "denoise", bags / "motion", "--model", model_path, "--out", out, "--quiet"
        ).returncode
        == 0
    )
    raw, den = _messages(out, "/accelerometer/raw"), _messages(out, "/accelerometer/denoised")
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
        assert _messages(out, topic) == _messages(bags / "motion", topic), topic


def test_streaming_through_small_chunks_equals_batch(bags, model_path, tmp_path):
    """Input in 20 kB MCAP chunks (~40 samples): slices, chunk boundaries and the joint-state
    horizon all fall in different places; the result is the whole-array one."""
    motion = read_recording(bags / "motion")
    write_recording(tmp_path / "small", motion, chunk_bytes=20_000, window_s=0.01)
    out = tmp_path / "out"
    model = NoiseModel.load(model_path)
    figures = denoise_bag(tmp_path / "small", out, model=model)
    assert figures["chunks_copied_verbatim"] > 100
    _, expected, _ = denoise_batch(
        motion.sensor_stamps_ns, motion.sensor, motion.joint_stamps_ns, motion.joint_velocity, model
    )
    np.testing.assert_array_equal(read_recording(out).denoised, expected)


def test_zstd_output_reads_back_identical(bags, model_path):
    plain, packed = bags / "out_plain", bags / "out_zstd"
    for out, extra in ((plain, ()), (packed, ("--compress", "zstd"))):
        result = egovib(
            "denoise", bags / "motion", "--model", model_path, "--out", out, "--quiet", *extra
        )
        assert result.returncode == 0, result.stderr
    assert "zstd size ratio" in result.stderr
    assert _messages(plain, "/accelerometer/denoised") == _messages(
        packed, "/accelerometer/denoised"
    )
    size = {p: next(p.glob("*.mcap")).stat().st_size for p in (plain, packed)}
    assert size[plain] > 5 * size[packed]


def test_a_bag_already_denoised_gets_its_denoised_topic_replaced(bags, model_path, tmp_path):
    once, twice = tmp_path / "once", tmp_path / "twice"
    model = NoiseModel.load(model_path)
    denoise_bag(bags / "motion", once, model=model)
    figures = denoise_bag(once, twice, model=model, channels="combined")
    assert figures["chunks_copied_verbatim"] > 0  # the old topic was cut out of the chunks
    topics = bag_topics(twice)
    assert topics["/accelerometer/denoised"][1] == topics["/accelerometer/raw"][1]
    rec = read_recording(twice)
    assert np.all(rec.denoised[:, 1:] == 0)  # the new (combined) output, not the old


# --------------------------------------------------------------------------
# Any robot: topics, field and joints from the profile (calibrate) and the model (denoise)
# --------------------------------------------------------------------------
def _robot_bag(
    path,
    p,
    data,
    *,
    extra_joints=("base", "arm_1", "arm_2", "lift", "pan", "tilt", "grip_l", "grip_r", "caster"),
):
    """The sensor topic (gyro) and a JointState carrying the profile's joints among others,
    in an order that changes from message to message."""
    ts = typestore()
    rng = np.random.default_rng(5)
    names = list(p.joint_names) + list(extra_joints)
    position = np.cumsum(data["velocity"], axis=0) * 1e-3
    with BagWriter(path, compress="zstd") as bag:
        bag.add_topic(p.sensor_topic, "sensor_msgs/msg/Imu")
        bag.add_topic(p.joints_topic, "sensor_msgs/msg/JointState")
        bag.write_batch(
            p.sensor_topic,
            data["t_acc"],
            encode_imu_batch(data["t_acc"], data["accel"], "imu_link", p.sensor_field),
        )
        for k, stamp in enumerate(data["t_joint"].tolist()):
            order = rng.permutation(len(names))
            pos = np.concatenate([position[k], np.zeros(len(extra_joints))])[order]
            vel = np.concatenate([data["velocity"][k], np.ones(len(extra_joints))])[order]
            msg = joint_state_message(stamp, [names[i] for i in order], pos, vel)
            bag.write(
                p.joints_topic, stamp, bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/JointState"))
            )


def test_any_robot_from_profile_to_denoised_bag(tmp_path):
    p = robots.profile(3, rate_hz=1600.0)
    (tmp_path / "robot.yaml").write_text(p.dumps())
    train, test = (
        robots.recording(p, 60.0, seed=1, joint_rate_hz=400.0),
        robots.recording(p, 8.0, seed=2, joint_rate_hz=400.0, taps_per_s=2.0),
    )
    _robot_bag(tmp_path / "train", p, train)
    _robot_bag(tmp_path / "test", p, test)
    result = egovib(
        "calibrate",
        tmp_path / "train",
        "--robot",
        tmp_path / "robot.yaml",
        "--grid",
        "free",
        "--out",
        tmp_path / "m.npz",
        "--quiet",
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
    stamps, values, _ = denoise_batch(
        test["t_acc"], test["accel"], test["t_joint"], test["velocity"], model
    )
    np.testing.assert_array_equal(out.denoised_stamps_ns, stamps)
    np.testing.assert_array_equal(out.denoised, values)


def test_missing_joint_is_one_line_exit_2(tmp_path):
    p = robots.profile(3, rate_hz=1600.0)
    (tmp_path / "robot.yaml").write_text(p.dumps())
    data = robots.recording(p, 2.0, seed=3, joint_rate_hz=400.0)
    renamed = dataclasses.replace(p, joint_names=("joint_0", "joint_1", "other"))
    _robot_bag(tmp_path / "bag", renamed, data)
    result = egovib(
        "calibrate",
        tmp_path / "bag",
        "--robot",
        tmp_path / "robot.yaml",
        "--out",
        tmp_path / "m.npz",
    )
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0
    assert (
        "joint_2" in result.stderr and "/joint_states" in result.stderr and "bag" in result.stderr
    )
    assert not (tmp_path / "m.npz").exists()


# --------------------------------------------------------------------------
# Many bags
# --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fleet(bags):
    """Four short bags (one broken) in a directory tree."""
    root = bags / "fleet"
    for seed in range(3):
        motion, _ = simulate_motion(duration_s=2.0, max_speed=0.5, tap_rate_hz=1.0, seed=20 + seed)
        write_recording(root / ("day1" if seed < 2 else "day2") / f"run{seed}", motion)
    broken = root / "day2" / "broken"
    shutil.copytree(root / "day1" / "run0", broken)
    mcap = next(broken.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[: len(mcap.read_bytes()) // 2])
    return root


def test_many_bags_in_parallel_equal_single_runs_and_a_broken_one_is_named(
    bags, fleet, model_path, tmp_path
):
    singles = {}
    for name in ("day1/run0", "day1/run1", "day2/run2"):
        out = tmp_path / "single" / name
        assert (
            egovib(
                "denoise", fleet / name, "--model", model_path, "--out", out, "--quiet"
            ).returncode
            == 0
        )
        singles[name] = _messages(out, "/accelerometer/denoised")
    for jobs in ("1", "2"):
        out = tmp_path / f"jobs{jobs}"
        result = egovib(
            "denoise", fleet, "--model", model_path, "--out", out, "--jobs", jobs, "--quiet"
        )
        assert result.returncode == 2
        assert "day2/broken" in result.stderr and "FAILED" in result.stderr
        assert "4 bag(s): 3 done, 1 failed" in result.stderr
        assert not (out / "day2" / "broken").exists()
        assert not list(out.rglob("*.partial"))
        for name, expected in singles.items():
            assert _messages(out / name, "/accelerometer/denoised") == expected, (jobs, name)
    # Outputs inside the input directory would be taken for inputs by the next run.
    inside = fleet / "clean"
    result = egovib("denoise", fleet, "--model", model_path, "--out", inside, "--quiet")
    assert result.returncode == 2 and "inside the input" in result.stderr
    assert [line for line in result.stderr.splitlines() if "error" in line] == [
        f"egovib: error: {inside}: --out is inside the input {fleet}; write it elsewhere"
    ]
    assert not inside.exists()


def test_calibrate_pools_several_bags(bags, tmp_path):
    sweep, _ = simulate_sweep(grid="superposition", dwell_s=0.5, settle_s=0.3, seed=8)
    write_recording(
        tmp_path / "more" / "sweep2", dataclasses.replace(sweep, contact=None, ego=None)
    )
    shutil.copytree(bags / "sweep", tmp_path / "more" / "sweep1")
    results = {}
    for name, args in (
        ("one", [tmp_path / "more" / "sweep1"]),
        ("two", [tmp_path / "more" / "sweep2"]),
        ("both", [tmp_path / "more"]),
        ("both_j2", [tmp_path / "more", "--jobs", "2"]),
    ):
        result = egovib("calibrate", *args, "--out", tmp_path / f"{name}.npz", "--quiet")
        assert result.returncode == 0, result.stderr
        results[name] = NoiseModel.load(tmp_path / f"{name}.npz")
    one, two, both = results["one"], results["two"], results["both"]
    assert both.measured == "superposition"
    np.testing.assert_array_equal(both.counts, one.counts + two.counts)
    n1, n2 = one.counts[..., None, None], two.counts[..., None, None]
    pooled = np.divide(
        one.mean * n1 + two.mean * n2, n1 + n2, out=np.zeros_like(one.mean), where=n1 + n2 > 0
    )
    np.testing.assert_allclose(both.mean, pooled, rtol=1e-9, atol=1e-12)
    for name in ("cells", "cell_mean", "cell_std", "cell_counts"):
        np.testing.assert_array_equal(getattr(results["both_j2"], name), getattr(both, name))


def test_unusual_imu_messages_take_the_general_path(bags, model_path, tmp_path):
    """Raw messages whose frame_id changes length mid-stream (no fixed layout): the output is
    still each input message with only the field replaced, as the vectorised path makes it."""
    motion = read_recording(bags / "motion")
    n = len(motion.sensor_stamps_ns)
    half = n // 2
    with BagWriter(tmp_path / "mixed") as bag:
        bag.add_topic("/accelerometer/raw", "sensor_msgs/msg/Imu")
        bag.add_topic("/joint_states", "sensor_msgs/msg/JointState")
        stamps = motion.sensor_stamps_ns
        raws = encode_imu_batch(stamps[:half], motion.sensor[:half], "imu") + encode_imu_batch(
            stamps[half:], motion.sensor[half:], "imu_link_long_name"
        )
        bag.write_batch("/accelerometer/raw", stamps, raws)
        bag.write_batch(
            "/joint_states",
            motion.joint_stamps_ns,
            encode_joint_state_batch(
                motion.joint_stamps_ns,
                motion.joint_position,
                motion.joint_velocity,
                motion.joint_names,
            ),
        )
    denoise_bag(tmp_path / "mixed", tmp_path / "out", model=NoiseModel.load(model_path))
    _, expected, _ = denoise_batch(
        motion.sensor_stamps_ns,
        motion.sensor,
        motion.joint_stamps_ns,
        motion.joint_velocity,
        NoiseModel.load(model_path),
    )
    np.testing.assert_array_equal(read_recording(tmp_path / "out").denoised, expected)
    raw, den = (
        _messages(tmp_path / "out", "/accelerometer/raw"),
        _messages(tmp_path / "out", "/accelerometer/denoised"),
    )
    assert [t for t, _ in raw] == [t for t, _ in den]
    for (_, a), (_, b), frame in (
        (raw[0], den[0], "imu"),
        (raw[-1], den[-1], "imu_link_long_name"),
    ):
        at = imu_field_offset(len(frame), "linear_acceleration")
        assert (
            a[:at] == b[:at] and a[at + 24 :] == b[at + 24 :] and a[at : at + 24] != b[at : at + 24]
        )


def test_positions_only_joint_states_give_the_same_denoising_within_half_a_db(bags, tmp_path):
    """A driver that publishes JointState positions only (no velocity): calibrate, denoise
    and evaluate differentiate the positions (profile joints.velocity: auto) and denoise
    within 0.5 dB of the same run with velocities."""
    positions_only = bagcorpus.Layout("positions_only", velocity=False)
    figures = {}
    for name, layout in (("with", None), ("without", positions_only)):
        sweep, motion = bags / "sweep", bags / "motion"
        if layout is not None:
            sweep = bagcorpus.write_layout(sweep, tmp_path / "sweep_positions", layout)
            motion = bagcorpus.write_layout(motion, tmp_path / "motion_positions", layout)
        model = tmp_path / f"{name}.npz"
        result = egovib("calibrate", sweep, "--out", model, "--quiet")
        assert result.returncode == 0, result.stderr
        result = egovib("denoise", motion, "--model", model, "--out", tmp_path / f"den_{name}")
        assert result.returncode == 0, result.stderr
        report = tmp_path / f"{name}.json"
        result = egovib("evaluate", motion, "--model", model, "--json", report, "--quiet")
        assert result.returncode == 0, result.stderr
        figures[name] = json.loads(report.read_text())["noise_reduction_db"]
    assert figures["with"] > 15 and abs(figures["with"] - figures["without"]) < 0.5, figures
    with Reader(tmp_path / "motion_positions") as reader:  # positions only, indeed
        conn = next(c for c in reader.connections if c.msgtype.endswith("JointState"))
        _, _, data = next(reader.messages(connections=[conn]))
        assert len(typestore().deserialize_cdr(data, conn.msgtype).velocity) == 0


def test_joint_states_without_velocity_or_position_are_named(bags, tmp_path):
    """Neither is usable: one line naming the joint-state topic and the joint."""
    profile = tmp_path / "measured.yaml"
    text = load_profile(None).dumps().replace("velocity: auto", "velocity: measured")
    profile.write_text(text)
    motion = bagcorpus.write_layout(
        bags / "motion", tmp_path / "positions", bagcorpus.Layout("p", velocity=False)
    )
    result = egovib("calibrate", motion, "--robot", profile, "--out", tmp_path / "m.npz")
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert "/joint_states" in lines[0] and "r_wrist_roll_joint" in lines[0], lines[0]
    assert "no velocity" in lines[0] and "auto" in lines[0]
