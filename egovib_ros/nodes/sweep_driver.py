"""sweep_driver: command the calibration sweep over the velocity grid, then stop and exit 0.

For each cell (the 21 x 21 grid, or the 41-cell superposition sweep, in the order of
egovib_ros.sim.sweep_cells) the joint velocities are commanded on
`hand_velocity_controller/commands` for `settle` + `dwell` seconds of node-clock time
(so it follows use_sim_time). Progress: a log line per cell and /diagnostics.
`start_cell` resumes an interrupted sweep.
"""
from __future__ import annotations

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from rclpy.task import Future
from std_msgs.msg import Float64MultiArray

from egovib_ros.constants import TOPIC_COMMANDS, TOPIC_DIAGNOSTICS
from egovib_ros.errors import ConfigError
from egovib_ros.nodes.common import declare, run_node
from egovib_ros.ros_convert import command_message, diagnostic_array
from egovib_ros.sim.scenarios import sweep_cells

_NS = 1_000_000_000
COMMAND_PERIOD_S = 0.05     # the command is repeated at 20 Hz (forward-command controllers hold it)


class SweepDriver(Node):
    def __init__(self):
        super().__init__("sweep_driver")
        grid = declare(self, "grid", "superposition", "full (441 cells) | superposition (41 cells)")
        self.dwell_s = float(declare(self, "dwell", 15.0, "seconds of data per cell, after settling"))
        self.settle_s = float(declare(self, "settle", 1.0, "seconds to reach a cell's velocity"))
        self.start_cell = int(declare(self, "start_cell", 0, "first cell (0-based) to command: resumes a sweep"))
        self.wait_for_subscriber = float(declare(
            self, "wait_for_subscriber", 10.0,
            "seconds to wait for a subscriber of the commands before starting (0 = do not wait)"))
        if grid not in ("full", "superposition"):
            raise ConfigError(f"sweep_driver: grid must be full or superposition, not {grid!r}")
        if self.dwell_s <= 0 or self.settle_s < 0:
            raise ConfigError("sweep_driver: dwell must be > 0 and settle >= 0")
        self.cells = sweep_cells(grid)
        if not 0 <= self.start_cell < len(self.cells):
            raise ConfigError(f"sweep_driver: start_cell must be in 0..{len(self.cells) - 1}")
        self.grid = grid
        self.pub = self.create_publisher(Float64MultiArray, TOPIC_COMMANDS, 10)
        self.pub_diag = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, 10)
        self.done = Future()
        self.cell = self.start_cell - 1
        self.cell_start_ns: int | None = None
        self.waited_ns = 0
        self._created_ns: int | None = None
        self.create_timer(COMMAND_PERIOD_S, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        total = (len(self.cells) - self.start_cell) * (self.dwell_s + self.settle_s)
        self.get_logger().info(f"{grid} sweep: cells {self.start_cell}..{len(self.cells) - 1}, "
                               f"settle {self.settle_s:g} s + dwell {self.dwell_s:g} s, ~{total:.0f} s")

    def _tick(self) -> None:
        if self.done.done():
            return
        now = self.get_clock().now().nanoseconds
        if now <= 0:                    # use_sim_time and no /clock yet
            return
        if self.cell_start_ns is None:
            if self._created_ns is None:
                self._created_ns = now
            waited = (now - self._created_ns) / _NS
            if self.pub.get_subscription_count() == 0 and waited < self.wait_for_subscriber:
                return
            self._next_cell(now)
        elif now - self.cell_start_ns >= (self.settle_s + self.dwell_s) * _NS:
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
        self.get_logger().info(f"cell {self.cell + 1}/{len(self.cells)}: wrist {velocity[0]:+.2f} rad/s, "
                               f"gripper {velocity[1]:+.4f} m/s")

    def _finish(self) -> None:
        stop = command_message(np.zeros(self.cells.shape[1]))
        for _ in range(3):
            self.pub.publish(stop)
        self.get_logger().info(f"{self.grid} sweep done: joints stopped")
        self._publish_diagnostics()
        self.done.set_result(0)

    def _publish_diagnostics(self) -> None:
        index = max(self.cell, self.start_cell)
        finished = self.cell >= len(self.cells)
        values = {"cell": min(index, len(self.cells) - 1) + 1, "cells": len(self.cells),
                  "grid": self.grid, "dwell_s": self.dwell_s, "settle_s": self.settle_s}
        if not finished and 0 <= self.cell < len(self.cells):
            values["command"] = list(self.cells[self.cell])
        message = "done" if finished else (f"cell {index + 1}/{len(self.cells)}"
                                           if self.cell_start_ns is not None else "waiting")
        self.pub_diag.publish(diagnostic_array(max(self.get_clock().now().nanoseconds, 0),
                                               [("sweep_driver", "ok", message, values)]))

    def close(self) -> None:
        # Interrupted or done: leave the joints stopped.
        try:
            self.pub.publish(command_message(np.zeros(self.cells.shape[1])))
        except Exception:  # noqa: BLE001 - context already shut down by Ctrl-C
            pass


def main(args: list[str] | None = None) -> int:
    return run_node(SweepDriver, args)


if __name__ == "__main__":
    raise SystemExit(main())
