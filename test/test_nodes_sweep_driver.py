"""sweep_driver on real DDS: commands the cells in order from `start_cell`, stops the joints, exits 0."""
from __future__ import annotations

import numpy as np
from std_msgs.msg import Float64MultiArray

from egovib_ros.sim import sweep_cells


def test_resumed_sweep_commands_remaining_cells_then_stops(nodes, ros_client):
    received = []
    ros_client.node.create_subscription(Float64MultiArray, "hand_velocity_controller/commands",
                                        lambda m: received.append(list(m.data)), 100)
    driver = nodes.start("sweep_driver", {"grid": "superposition", "dwell": 0.3, "settle": 0.1,
                                          "start_cell": 38})
    assert ros_client.spin_until(lambda: driver.poll() is not None, timeout=30), nodes.log(driver)
    ros_client.spin_for(0.2)
    assert driver.returncode == 0, nodes.log(driver)

    cells = sweep_cells("superposition")
    # Distinct commands in the order sent: cells 38, 39, 40, then the joints stopped.
    distinct = [received[0]] + [c for prev, c in zip(received, received[1:]) if c != prev]
    np.testing.assert_allclose(distinct, np.vstack([cells[38:], [[0.0, 0.0]]]))
    assert received[-1] == [0.0, 0.0]
    # ~ (settle + dwell) / 50 ms repetitions of each cell's command
    assert 5 <= sum(1 for c in received if np.allclose(c, cells[39])) <= 12
    log = nodes.log(driver)
    assert "cell 39/41" in log and "cell 41/41" in log and "sweep done" in log
