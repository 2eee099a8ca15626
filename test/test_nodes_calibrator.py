"""Live calibration on real DDS: sim_hand + sweep_driver + calibrator (+ bag_recorder)."""

from __future__ import annotations

import contextlib
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import matched, reports
from diagnostic_msgs.msg import DiagnosticStatus
from robots import profile, recording

from egovib_research.tools.orchestration import deep_output, reliable_input
from egovib_ros.core import NoiseModel, calibrate_arrays
from egovib_ros.core.methods import DEFAULT_METHOD, default_method
from egovib_ros.errors import ModelFileError
from egovib_ros.gap.simref import own_lag
from egovib_ros.nodes.convert import diagnostic_values
from egovib_ros.robot import config_dir

pytestmark = pytest.mark.nodes  # the node suite: `pytest -m nodes`

EGOVIB = str(Path(sys.executable).parent / "egovib")
SWEEP = {"grid": "superposition", "dwell": 0.3, "settle": 0.2}
# Lossless links on a loaded machine (standard QoS override parameters).
RELIABLE = reliable_input("/accelerometer/raw", "/joint_states")
DEEP_OUTPUT = deep_output("/accelerometer/raw", "/joint_states")  # sim_hand's


# A calibrator keeps up with 3 kHz only on a core of its own: beside another node test and a
# busy machine it fell minutes behind its input (the restarted one once did not end 240 s
# after Ctrl-C), so these run alone (`alone`: after the other node tests, one at a time).
@pytest.mark.alone
def test_live_calibration_equals_offline_calibration_of_recorded_bag(nodes, tmp_path):
    """With a joint lag set alike (the gap's timing advice): the node and `egovib calibrate`
    on a recording of what it received measure the same cells. Both fit the paper's table
    only (`methods: paper`): the tables and the joint lag are compared here, and fitting
    methods cancel and hybrid twice cost ~10 s (the node's `methods: all` is
    test_free_motion_calibration_of_a_three_joint_gyro_...'s)."""
    live_model, bag = tmp_path / "live.npz", tmp_path / "sweep"
    cal = nodes.start(
        "calibrator",
        {
            "output": str(live_model),
            "grid": "superposition",
            "joint_lag": 0.01,
            "methods": "paper",
            **RELIABLE,
        },
    )
    rec = nodes.start(
        "bag_recorder", {"output": str(bag), "topics": ["joint_states", "accelerometer/raw"]}
    )
    # sim_hand starts once both calibrator and recorder are matched: both see every sample.
    sim = nodes.start(
        "sim_hand",
        {"seed": 21, "publish_ground_truth": False, "wait_for_subscribers": 2, **DEEP_OUTPUT},
    )
    nodes.wait_for_log(rec, "/accelerometer/raw: subscribed")
    nodes.wait_for_log(rec, "/joint_states: subscribed")
    nodes.wait_for_log(sim, "simulation started")
    # started on its two subscribers, not on the gate's 30 s timeout (the gate once counted
    # sim_hand's /diagnostics publisher, which has none: every start waited it out)
    assert "starting anyway" not in nodes.log(sim), nodes.log(sim)
    driver = nodes.start("sweep_driver", SWEEP)
    assert driver.wait(120) == 0, nodes.log(driver)
    assert "superposition sweep done" in nodes.log(driver)
    nodes.stop(sim)
    time.sleep(0.5)
    assert nodes.stop(cal) == 0, nodes.log(cal)
    assert nodes.stop(rec) == 0, nodes.log(rec)
    offline_model = tmp_path / "offline.npz"
    subprocess.run([
        EGOVIB, "calibrate", str(bag), "--out", str(offline_model), "--grid", "superposition",
        "--joint-lag", "0.01", "--methods", "paper", "--quiet",
    ], check=True, capture_output=True)  # fmt: skip

    live, offline = NoiseModel.load(live_model), NoiseModel.load(offline_model)
    assert live.measured == offline.measured == "superposition"
    axis = live.axis_mask()
    # Every cell of the sweep measured. Not many blocks per cell: on a busy machine the
    # simulated hand may produce its 3 kHz slower than real time (17.5 s of samples during
    # a 32-s sweep in one stress run), and each wall-clock cell then holds fewer samples.
    assert np.all(live.counts[axis] > 0), live.counts[axis]
    # Both saw the stream from its first sample: the same blocks in the same cells. Slack:
    # one block per moving cell; at rest (zero cell: stream start and end, where the first
    # joint states may reach the two subscribers at different moments) 5 %.
    difference = np.abs(live.counts - offline.counts)
    zero = live.zero_index()
    assert difference[zero] <= 0.05 * offline.counts[zero], (live.counts - offline.counts)[axis]
    difference[zero] = 0
    assert difference.max() <= 1, (live.counts - offline.counts)[axis]
    both = axis & (live.counts > 5) & (offline.counts > 5)
    # Mean spectra equal within sampling error (standard error of the mean, 4 sigma + quantisation).
    sem = live.std[both] / np.sqrt(live.counts[both])[:, None, None]
    assert np.all(
        np.abs(live.mean[both] - offline.mean[both]) <= 4 * sem + 1e-9 * live.mean[both].max()
    )
    np.testing.assert_allclose(live.std[both], offline.std[both], rtol=0.25, atol=1e-6)
    # the joint lag `egovib gap` judges timing against, measured alike on what each received
    assert own_lag(offline) is not None
    assert own_lag(live) == pytest.approx(own_lag(offline), abs=0.002)


def participant_env(directory: Path, participant_id: int, *, lease_s: int = 0) -> dict[str, str]:
    """Environment for a node of the kill test: the package's Fast DDS profiles plus a
    participant id no other process of the test uses and, with `lease_s`, a lease that
    short (the default is 20 s).

    A process started after a SIGKILL may take the killed one's id, hence its shared-memory
    port, to which Fast DDS 2.14 may keep writing for the dead process (once the resumed
    sweep_driver took it, its commands were never acknowledged and the hand never moved).
    And until the killed participant's lease ends, sim_hand keeps resending its deep
    reliable history to the dead reader (beside `stress-ng --cpu 2` the restarted
    calibrator then received nothing for 30 s, and half the samples after)."""
    profiles = (config_dir() / "fastdds_profiles.xml").read_text()
    lease = (
        "<builtin><discovery_config>"
        f"<leaseDuration><sec>{lease_s}</sec></leaseDuration>"
        "<leaseAnnouncement><sec>0</sec><nanosec>500000000</nanosec></leaseAnnouncement>"
        "</discovery_config></builtin>"
        if lease_s
        else ""
    )
    participant = (
        f'    <participant profile_name="test_{participant_id}" is_default_profile="true">\n'
        f"      <rtps><participantID>{participant_id}</participantID>{lease}</rtps>\n"
        "    </participant>\n"
    )
    path = directory / f"participant_{participant_id}.xml"
    path.write_text(profiles.replace("  <profiles>\n", "  <profiles>\n" + participant, 1))
    return {"FASTRTPS_DEFAULT_PROFILES_FILE": str(path)}


@pytest.mark.alone
def test_calibrator_killed_mid_sweep_keeps_finished_cells(nodes, ros_client, tmp_path):
    model_path, checkpoint = tmp_path / "model.npz", tmp_path / "model.checkpoint.npz"
    # the paper's table only: the checkpoints are what is tested (see the test above)
    params = {"output": str(model_path), "grid": "superposition", "methods": "paper", **RELIABLE}
    first = nodes.start("calibrator", params, env=participant_env(tmp_path, 29, lease_s=2))
    sim = nodes.start("sim_hand", {"seed": 22, "publish_ground_truth": False, **DEEP_OUTPUT})
    nodes.wait_for_log(first, "calibrating")
    driver = nodes.start("sweep_driver", SWEEP)

    deadline = time.monotonic() + 60
    saved = None
    while saved is None or (saved.counts > 0).sum() < 8:
        assert time.monotonic() < deadline and driver.poll() is None, nodes.log(first)
        time.sleep(0.2)
        with contextlib.suppress(ModelFileError):  # not written yet
            saved = NoiseModel.load(checkpoint)
    assert nodes.stop(first, sig=9) == -9  # SIGKILL: no chance to write anything at exit
    assert not model_path.exists()
    saved = NoiseModel.load(checkpoint)  # the last checkpoint before the kill
    # The sweep is stopped too and resumed below at the cell it was in, once the restarted
    # calibrator receives the stream (how long a restart takes depends on the machine's load).
    assert nodes.stop(driver) == 0, nodes.log(driver)
    current_cell, n_cells = map(int, re.findall(r"cell (\d+)/(\d+):", nodes.log(driver))[-1])
    # Restart once the dead calibrator's lease has ended: it is out of the graph, and
    # sim_hand no longer sends to it.
    assert ros_client.spin_until(
        lambda: ros_client.node.count_subscribers("/accelerometer/raw") == 0, timeout=30
    )

    second = nodes.start(
        "calibrator",
        params,
        remap={"__node": "calibrator_restarted"},  # its own /diagnostics status
        env=participant_env(tmp_path, 30),
    )
    nodes.wait_for_log(second, "resumed from")

    def receiving() -> bool:
        status = ros_client.statuses.get("calibrator_restarted")
        return (
            matched(ros_client, "calibrator_restarted", sensor_publishers=1)
            and int(diagnostic_values(status)["samples_in"]) > 0
        )

    assert ros_client.spin_until(receiving, timeout=60), (
        ros_client.statuses.get("calibrator_restarted"),
        nodes.log(second),
    )
    # The resumed sweep covers the last cells only (they were not reached before the kill):
    # enough to show the restarted calibrator adds to the checkpoint, in half the time.
    resume_at = max(current_cell - 1, n_cells - 8)
    driver = nodes.start(
        "sweep_driver",
        {**SWEEP, "start_cell": resume_at},
        env=participant_env(tmp_path, 31),
    )
    assert driver.wait(120) == 0, nodes.log(driver)
    time.sleep(0.5)
    # Ctrl-C: it fits the detector's thresholds and its joint lag on all it holds (here also
    # the minute of rest it received before the resumed sweep) before writing.
    assert nodes.stop(second, timeout=240) == 0, nodes.log(second)
    nodes.stop(sim)

    final = NoiseModel.load(model_path)
    assert not checkpoint.exists()
    kept = saved.counts > 0
    assert np.all(final.counts >= saved.counts)
    assert np.all(final.counts[kept] > 0)
    # The restarted calibrator added the cells swept after the restart.
    assert (final.counts[final.axis_mask()] > 0).sum() > kept.sum(), (
        nodes.log(second)[-3000:],
        nodes.log(driver)[-1500:],
        nodes.log(sim)[-1500:],
    )


def test_free_motion_calibration_of_a_three_joint_gyro_keeps_statistics_when_checkpoints_fail(
    nodes, ros_client, feeder, tmp_path
):
    """A robot that is not the PR2 (3 joints, one one-directional, a gyro at 1 kHz with
    jittery stamps, joint states at 500 Hz among ten other joints, positions only, as many
    drivers publish them): free-motion calibration through its profile, velocities
    differentiated from the positions (profile joints.velocity: auto). The checkpoint
    directory is unusable at first (a file stands where it should be): ERROR on
    /diagnostics, statistics kept, the write retried; once the directory exists the
    checkpoint appears, and the final model equals the offline one (calibrated from the
    velocities themselves)."""
    robot = profile(3, rate_hz=1000.0)
    robot_path = tmp_path / "robot.yaml"
    robot_path.write_text(robot.dumps())
    data = recording(robot, 8.0, seed=3, joint_rate_hz=500.0)
    blocked = tmp_path / "models"
    blocked.write_text("a file where the model directory should be")
    output = blocked / "model.npz"
    cal = nodes.start(
        "calibrator",
        {
            "robot": str(robot_path),
            "grid": "free",
            "output": str(output),
            "checkpoint_period": 1.0,
            "retry_period": 0.5,
            **reliable_input(robot.sensor_topic, robot.joints_topic),
        },
    )
    stream = feeder(robot, positions_only=True)
    assert stream.wait_for_subscribers("calibrator"), nodes.log(cal)
    t_acc, accel, t_joint, velocity = (
        data["t_acc"],
        data["accel"],
        data["t_joint"],
        data["velocity"],
    )
    half = len(t_acc) // 2
    joint_half = int(np.searchsorted(t_joint, t_acc[half]))
    stream.publish(t_acc[:half], accel[:half], t_joint[:joint_half], velocity[:joint_half])

    def failing() -> bool:
        return reports(
            ros_client,
            "calibrator",
            DiagnosticStatus.ERROR,
            "cannot write checkpoint",
            str(output.parent),
        )

    assert ros_client.spin_until(failing, timeout=30.0), (
        ros_client.statuses.get("calibrator"),
        nodes.log(cal),
    )
    assert cal.poll() is None
    failures = int(diagnostic_values(ros_client.statuses["calibrator"])["checkpoint_failures"])
    blocked.unlink()
    blocked.mkdir()
    checkpoint = blocked / "model.checkpoint.npz"
    assert ros_client.spin_until(checkpoint.exists, timeout=30.0), nodes.log(cal)
    assert ros_client.spin_until(
        lambda: ros_client.statuses["calibrator"].level != DiagnosticStatus.ERROR, 30.0
    )
    stream.publish(t_acc[half:], accel[half:], t_joint[joint_half:], velocity[joint_half:])

    def everything_received() -> bool:  # by the node's callbacks: Ctrl-C loses nothing then
        values = diagnostic_values(ros_client.statuses["calibrator"])
        return int(values["samples_in"]) == len(t_acc) and int(values["joint_states_in"]) == len(
            t_joint
        )

    assert ros_client.spin_until(everything_received, timeout=30.0), diagnostic_values(
        ros_client.statuses["calibrator"]
    )
    assert diagnostic_values(ros_client.statuses["calibrator"])["velocity_source"] == (
        "from_position"
    )
    assert nodes.stop(cal) == 0, nodes.log(cal)
    # free motion measures some of the grid: the summary says how much, never "missing: none"
    summary = next(line for line in nodes.log(cal).splitlines() if "calibrator: wrote" in line)
    total = int(np.prod(robot.grid_shape))
    assert re.search(rf"\d+ of {total} grid cells measured", summary) and "none" not in summary
    # a line that ends whole (the demo cut it at 300 characters, mid-dict): no dict's repr
    assert "{" not in summary and re.search(r"; bad samples: \d+$", summary.rstrip()), summary
    assert failures >= 1 and "cannot write checkpoint" in nodes.log(cal)

    live = NoiseModel.load(output)
    # `methods: all` (the default): the model feeds the default method
    assert default_method(live) == DEFAULT_METHOD, summary
    offline, stats = calibrate_arrays(t_acc, accel, t_joint, velocity, profile=robot, sweep="free")
    assert live.profile == robot and live.measured == offline.measured == "free"
    live_cells, live_counts = live.cells_measured()
    cells, counts = offline.cells_measured()
    assert len(cells) > 20 and np.array_equal(live_cells, cells), (len(live_cells), len(cells))
    assert (
        np.abs(live_counts - counts).max() <= 1
        and abs(live_counts.sum() - counts.sum()) <= 0.01 * counts.sum()
    )
    assert not checkpoint.exists()


def test_joint_states_on_another_clock_are_said_while_calibrating(
    nodes, ros_client, feeder, tmp_path
):
    """Joint states stamped by another clock (sim time beside wall time): no block has a
    joint state. /diagnostics said OK ('0 cells measured') for the whole run, and only the
    exit said 'no usable block'; now it warns while it happens and names the clocks."""
    from egovib_ros.robot import load_profile

    output = tmp_path / "model.npz"
    cal = nodes.start("calibrator", {"grid": "free", "output": str(output), **RELIABLE})
    stream = feeder(load_profile(None), joint_clock_offset_s=1000.0)
    assert stream.wait_for_subscribers("calibrator"), nodes.log(cal)

    def warned() -> bool:
        return reports(ros_client, "calibrator", DiagnosticStatus.WARN, "different clocks")

    assert stream.run_until(warned, at_most_s=4.0), ros_client.statuses.get("calibrator")
    assert "blocks without joint state, not used" in ros_client.statuses["calibrator"].message
    assert "1e+03 s ahead" in ros_client.statuses["calibrator"].message
    assert nodes.stop(cal) == 1 and not output.exists()
    assert "no usable block" in nodes.log(cal)


def test_a_driver_stamping_on_receipt_is_calibrated_on_a_rebuilt_sample_clock(
    nodes, ros_client, feeder, tmp_path
):
    """Sensor messages stamped as a USB driver reads them (1 ms frames): the calibrator
    counts blocks as with sample stamps (nothing bridged, no restart) and says what the
    stamps mark."""
    from egovib_ros.robot import load_profile

    cal = nodes.start("calibrator", {"grid": "free", "output": str(tmp_path / "m.npz"), **RELIABLE})
    stream = feeder(load_profile(None), receipt_stamps=True)
    assert stream.wait_for_subscribers("calibrator"), nodes.log(cal)

    def counted() -> bool:
        status = ros_client.statuses.get("calibrator")
        values = diagnostic_values(status) if status is not None else {}
        return values.get("sensor_stamps") == "receipt" and int(values["blocks"]) > 50

    assert stream.run_until(counted, at_most_s=4.0), ros_client.statuses.get("calibrator")
    values = diagnostic_values(ros_client.statuses["calibrator"])
    assert int(values["gap_filled_samples"]) == 0 and int(values["stream_restarts"]) == 0
    assert nodes.stop(cal) == 0, nodes.log(cal)
