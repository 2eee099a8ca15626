"""sweep_driver on real DDS: commands a robot profile's cells in the core's sweep order from
`start_cell` (N joints, ros2_control forward-command convention), stops the joints, exits 0."""

from __future__ import annotations

import numpy as np
import pytest
from std_msgs.msg import Float64MultiArray

from egovib_ros.core.noise_model import sweep_cells
from egovib_ros.errors import ConfigError
from egovib_ros.robot import RobotProfile, load_profile
from egovib_ros.sim import sweep_cells as simulator_sweep
from egovib_ros.sim.robot import sweep_velocities

pytestmark = pytest.mark.nodes  # the node suite: `pytest -m nodes`

# Three joints, the last one-directional (a motor that only spins one way), 2 steps.
ROBOT = RobotProfile(
    name="three_joint_arm",
    sensor_topic="/imu/data_raw",
    sensor_field="angular_velocity",
    rate_hz=1000.0,
    denoised_topic="/imu/denoised",
    joints_topic="/joint_states",
    joint_names=("shoulder", "elbow", "rotor"),
    max_speed=(2.0, 1.0, 50.0),
    bidirectional=(True, True, False),
    steps=2,
    band_hz=(40.0, 440.0),
)


def test_sweep_cells_come_from_the_profile_grid():
    cells = sweep_velocities(ROBOT, "superposition")
    assert cells.shape == (1 + 4 + 4 + 2, 3)
    assert sum(not c.any() for c in cells) == 1  # the rest cell, once
    assert np.all((cells != 0).sum(axis=1) <= 1)
    np.testing.assert_allclose(sorted(cells[:, 2][cells[:, 2] != 0]), [25.0, 50.0])  # 0..max only
    assert len(sweep_velocities(ROBOT, "full")) == 5 * 5 * 3
    # The PR2 hand: the same cells as the simulator's calibration sweeps.
    pr2 = load_profile()
    for grid in ("superposition", "full"):
        ours, simulator = sweep_velocities(pr2, grid), simulator_sweep(grid)
        assert {tuple(np.round(c, 9)) for c in ours} == {tuple(np.round(c, 9)) for c in simulator}
    eight = RobotProfile(
        **{
            **{
                k: getattr(ROBOT, k)
                for k in (
                    "sensor_topic",
                    "sensor_field",
                    "rate_hz",
                    "denoised_topic",
                    "joints_topic",
                    "band_hz",
                )
            },
            "name": "eight",
            "joint_names": tuple(f"j{i}" for i in range(8)),
            "max_speed": (1.0,) * 8,
            "bidirectional": (True,) * 8,
            "steps": 10,
        }
    )
    assert len(sweep_velocities(eight, "superposition")) == 1 + 8 * 20
    with pytest.raises(ConfigError, match="full sweep has 37822859361 cells"):
        sweep_velocities(eight, "full")


def test_resumed_sweep_of_a_three_joint_robot_commands_remaining_cells_then_stops(
    nodes, ros_client, tmp_path
):
    profile_path = tmp_path / "three_joint_arm.yaml"
    profile_path.write_text(ROBOT.dumps())
    received = []
    ros_client.node.create_subscription(
        Float64MultiArray,
        "hand_velocity_controller/commands",
        lambda m: received.append(list(m.data)),
        100,
    )
    driver = nodes.start(
        "sweep_driver",
        {
            "robot": str(profile_path),
            "grid": "superposition",
            "dwell": 0.3,
            "settle": 0.1,
            "start_cell": 8,
        },
    )
    assert ros_client.spin_until(lambda: driver.poll() is not None, timeout=30), nodes.log(driver)
    assert ros_client.drain(received)
    assert driver.returncode == 0, nodes.log(driver)

    cells = sweep_velocities(ROBOT, "superposition")
    np.testing.assert_allclose(
        cells,
        np.column_stack(
            [ROBOT.grid()[j][sweep_cells(ROBOT.grid(), "superposition")[:, j]] for j in range(3)]
        ),
    )
    # Distinct commands in the order sent: cells 8, 9, 10, then the joints stopped.
    distinct = [received[0]] + [c for prev, c in zip(received, received[1:]) if c != prev]
    np.testing.assert_allclose(distinct, np.vstack([cells[8:], [[0.0, 0.0, 0.0]]]))
    assert received[-1] == [0.0, 0.0, 0.0]
    # ~ (settle + dwell) / 50 ms repetitions of each cell's command (a timer skips the
    # periods a stalled process missed)
    assert 3 <= sum(1 for c in received if np.allclose(c, cells[9])) <= 12
    log = nodes.log(driver)
    assert "cell 9/11" in log and "cell 11/11" in log and "sweep done" in log and "rotor +50" in log
