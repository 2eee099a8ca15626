"""What the simulator nodes share (nodes.simulator: sim_hand and sim_robot), on real DDS."""

from __future__ import annotations

import random
import signal
import time

import pytest

from egovib_ros.nodes.convert import diagnostic_values

pytestmark = pytest.mark.nodes  # the node suite: `pytest -m nodes`


def test_ctrl_c_ends_both_simulators_cleanly_whatever_they_are_doing(nodes, ros_client):
    """Four simulators (two hands, two example arms) publishing every 2 ms (the tick is
    most of their main thread's time), each interrupted at a random moment: exit status 0
    and nothing in the log but the two start-up lines. Before the simulators stopped
    between ticks, rclpy's KeyboardInterrupt hit the tick: a [FATAL] 'Exception in timers
    callback' with a traceback and 'Failed to publish log message to rosout' (4 of 12
    Ctrl-C of sim_hand here). /diagnostics lists the command and velocity as numbers."""
    fast = {"publish_period": 0.002}
    arm = {"robot": "example_arm", **fast}
    procs = [nodes.start("sim_hand", fast, log_name=f"sim_hand_{k}") for k in range(2)] + [
        nodes.start("sim_robot", arm, log_name=f"sim_robot_{k}") for k in range(2)
    ]
    for proc in procs:
        nodes.wait_for_log(proc, "simulation started")
    assert ros_client.spin_until(
        lambda: {"sim_hand", "sim_robot"} <= set(ros_client.statuses), 30
    ), ros_client.statuses
    hand = diagnostic_values(ros_client.statuses["sim_hand"])
    assert hand["command"] == hand["velocity"] == "[0.0, 0.0]", hand
    values = diagnostic_values(ros_client.statuses["sim_robot"])
    assert values["command"] == "[0.0, 0.0, 0.0]" and int(values["samples_published"]) > 0, values
    rng = random.Random(0)
    for proc in procs:  # each at a moment of its own
        time.sleep(rng.uniform(0.0, 0.3))
        proc.send_signal(signal.SIGINT)
    for proc in procs:
        assert proc.wait(30) == 0, nodes.log(proc)
        lines = nodes.log(proc).splitlines()
        assert len(lines) == 2 and all(line.startswith("[INFO]") for line in lines), lines
