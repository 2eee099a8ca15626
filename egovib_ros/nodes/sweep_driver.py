"""sweep_driver: command the calibration sweep over a robot's velocity grid, then stop and exit 0.

Each cell (`full`: every cell; `superposition`: the rest cell, then each joint's other
values with the others at rest; in the core's `sweep_cells` order) is commanded for
`settle` + `dwell` s of node-clock time on `hand_velocity_controller/commands`, one value
per joint (ros2_control forward-command convention). docs/live_nodes.md.
"""

from __future__ import annotations

import numpy as np
from rclpy.node import Node
from rclpy.task import Future
from std_msgs.msg import Float64MultiArray

from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import ConfigError
from egovib_ros.nodes.common import (
    ROBOT_PARAM,
    Health,
    Param,
    SubscriberGate,
    declare_parameters,
    run_node,
    wait_for_delivery,
)
from egovib_ros.nodes.convert import command_message
from egovib_ros.robot import COMMANDS_TOPIC, load_profile
from egovib_ros.sim.robot import MAX_SWEEP_CELLS, sweep_velocities

COMMAND_PERIOD_S = 0.05  # the command is repeated at 20 Hz (forward-command controllers hold it)
PARAMETERS = (
    ROBOT_PARAM,
    Param(
        "grid",
        "superposition",
        "full (every cell of the grid) | superposition (cells with at most one joint moving)",
        choices=("full", "superposition"),
    ),
    Param("dwell", 15.0, "seconds of data per cell, after settling", range=(0.001, 3600.0)),
    Param("settle", 1.0, "seconds to reach a cell's velocity", range=(0.0, 3600.0)),
    Param(
        "start_cell",
        0,
        "first cell (0-based) to command: resumes a sweep",
        range=(0, MAX_SWEEP_CELLS),
    ),
    Param(
        "wait_for_subscriber",
        10.0,
        "seconds to wait for a subscriber of the commands before starting (0 = do not wait)",
        range=(0.0, 3600.0),
    ),
)


class SweepDriver(Node):
    def __init__(self):
        super().__init__("sweep_driver")
        params = declare_parameters(self, PARAMETERS)
        self.profile = load_profile(params["robot"] or None)
        self.grid = params["grid"]
        self.dwell_s, self.settle_s = params["dwell"], params["settle"]
        self.start_cell = params["start_cell"]
        self.cells = sweep_velocities(self.profile, self.grid)
        if not 0 <= self.start_cell < len(self.cells):
            raise ConfigError(f"sweep_driver: start_cell must be in 0..{len(self.cells) - 1}")
        self.pub = self.create_publisher(Float64MultiArray, COMMANDS_TOPIC, 10)
        self.health = Health(self, hardware_id=self.profile.name)
        self.done = Future()
        self.cell = self.start_cell - 1
        self.cell_start_ns: int | None = None
        wait_s = params["wait_for_subscriber"]
        self.gate = SubscriberGate([self.pub], 1 if wait_s > 0 else 0, wait_s)
        self.create_timer(COMMAND_PERIOD_S, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        total = (len(self.cells) - self.start_cell) * (self.dwell_s + self.settle_s)
        self.get_logger().info(
            f"{self.grid} sweep of {self.profile.name} ({', '.join(self.profile.joint_names)}): "
            f"cells {self.start_cell}..{len(self.cells) - 1}, "
            f"settle {self.settle_s:g} s + dwell {self.dwell_s:g} s, ~{total:.0f} s"
        )

    def _tick(self) -> None:
        if self.done.done():
            return
        now = self.get_clock().now().nanoseconds
        if now <= 0:  # use_sim_time and no /clock yet
            return
        if self.cell_start_ns is None:
            if not self.gate.is_open():
                return
            self._next_cell(now)
        elif now - self.cell_start_ns >= (self.settle_s + self.dwell_s) * NS_PER_S:
            self._next_cell(now)
        if not self.done.done():
            self.pub.publish(command_message(self.cells[self.cell]))

    def _next_cell(self, now: int) -> None:
        self.cell += 1
        if self.cell >= len(self.cells):
            self._finish()
            return
        self.cell_start_ns = now
        velocity = self.cells[self.cell]
        command = ", ".join(
            f"{name} {v:+.4g}" for name, v in zip(self.profile.joint_names, velocity)
        )
        self.get_logger().info(f"cell {self.cell + 1}/{len(self.cells)}: {command}")

    def _finish(self) -> None:
        stop = command_message(np.zeros(self.cells.shape[1]))
        for _ in range(3):
            self.pub.publish(stop)
        wait_for_delivery(self, [self.pub], "stop command")
        self.get_logger().info(f"{self.grid} sweep done: joints stopped")
        self._publish_diagnostics()
        self.done.set_result(0)

    def _publish_diagnostics(self) -> None:
        index = max(self.cell, self.start_cell)
        finished = self.cell >= len(self.cells)
        values = {
            "cell": min(index, len(self.cells) - 1) + 1,
            "cells": len(self.cells),
            "grid": self.grid,
            "dwell_s": self.dwell_s,
            "settle_s": self.settle_s,
        }
        commanding = not finished and 0 <= self.cell < len(self.cells)
        for j, name in enumerate(self.profile.joint_names):  # same keys every time (dashboards)
            values[f"command.{name}"] = float(self.cells[self.cell][j]) if commanding else 0.0
        waiting = self.cell_start_ns is None and not finished
        message = (
            "done" if finished else "waiting" if waiting else f"cell {index + 1}/{len(self.cells)}"
        )
        warnings = []
        if waiting and self.pub.get_subscription_count() == 0:
            warnings.append("no subscriber of the commands yet")
        self.health.publish(warnings=warnings, ok=message, values=values)

    def close(self) -> None:
        # Interrupted or done: leave the joints stopped (acknowledged: DDS may drop what is
        # unacknowledged when the process exits).
        try:
            self.pub.publish(command_message(np.zeros(self.cells.shape[1])))
            wait_for_delivery(self, [self.pub], "stop command")
        except Exception:  # noqa: BLE001 - context already shut down by Ctrl-C
            pass


def main(args: list[str] | None = None) -> int:
    return run_node(SweepDriver, args)


if __name__ == "__main__":
    raise SystemExit(main())
