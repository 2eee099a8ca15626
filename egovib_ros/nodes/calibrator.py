"""calibrator: live calibration of the noise model (egovib_ros.core.CalibrationAccumulator).

Subscribes `joint_states` and `accelerometer/raw`; blocks are assigned to velocity
cells from the measured joint velocities, so it needs no message from the driver
and works with any driver or a real robot. A checkpoint model is written (atomically)
whenever the blocks move on to another cell, i.e. after each completed cell, so a
crash loses at most the cell in progress; a restarted calibrator resumes from it.
At shutdown (Ctrl-C / SIGTERM) it writes the model to `output` and reports coverage.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState

from egovib_ros.constants import JOINT_NAMES, TOPIC_DIAGNOSTICS, TOPIC_JOINT_STATES, TOPIC_RAW
from egovib_ros.core import CalibrationAccumulator, NoiseModel
from egovib_ros.errors import ConfigError, EgovibError
from egovib_ros.fileutil import atomic_output
from egovib_ros.nodes.common import declare, run_node, sensor_subscription
from egovib_ros.ros_convert import (decode_imu_messages, decode_joint_state_messages,
                                    diagnostic_array)


# The two topics come on separate DDS readers: on a busy machine (e.g. while another
# process starts) joint states can fall well behind the samples. Calibration has no latency
# to keep, so blocks wait up to this long (stream time) for the joint states covering them.
JOINT_WAIT_S = 2.0


def default_checkpoint(output: str) -> str:
    """Checkpoint path beside the model: MODEL.checkpoint.npz."""
    path = Path(output)
    return str(path.with_name(path.stem + ".checkpoint.npz"))


class Calibrator(Node):
    def __init__(self):
        super().__init__("calibrator")
        self.output = declare(self, "output", "noise_model.npz", "noise-model file written at the end")
        grid = declare(self, "grid", "full", "full (21 x 21 cells) | superposition (the 41 one-joint cells)")
        self.checkpoint = declare(self, "checkpoint", "",
                                  "checkpoint model path; empty = <output stem>.checkpoint.npz") \
            or default_checkpoint(self.output)
        resume = declare(self, "resume", True, "resume from the checkpoint if it exists")
        self.batch_samples = int(declare(self, "batch_samples", 96,
                                         "accelerometer samples collected before processing"))
        if grid not in ("full", "superposition"):
            raise ConfigError(f"calibrator: grid must be full or superposition, not {grid!r}")
        self.grid = grid
        if resume and os.path.exists(self.checkpoint):
            self.acc = CalibrationAccumulator.from_model(NoiseModel.load(self.checkpoint), joint_wait_s=JOINT_WAIT_S)
            if self.acc.sweep != grid:
                raise ConfigError(f"{self.checkpoint}: checkpoint of a {self.acc.sweep} sweep, "
                                  f"but grid is {grid}")
            self.get_logger().info(f"resumed from {self.checkpoint}: "
                                   f"{int((self.acc.counts > 0).sum())} cells, {int(self.acc.counts.sum())} blocks")
        else:
            self.acc = CalibrationAccumulator(sweep=grid, joint_wait_s=JOINT_WAIT_S)
        self.expected = self.acc.expected_cells
        self.pub_diag = self.create_publisher(DiagnosticArray, TOPIC_DIAGNOSTICS, 10)
        sensor_subscription(self, Imu, TOPIC_RAW, self._on_accel)
        sensor_subscription(self, JointState, TOPIC_JOINT_STATES, self._on_joint_state)
        self._accel_raw: list[bytes] = []
        self._joint_raw: list[bytes] = []
        self.bad_messages = 0
        self._counts = self.acc.counts
        self._current_cell: int | None = None
        self._checkpoint_due = False
        self.checkpoints_written = 0
        self._last_input = time.monotonic()
        self.create_timer(0.25, self._on_timer)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(f"calibrating a {grid} grid into {self.output} "
                               f"(checkpoint {self.checkpoint})")

    # --- input ------------------------------------------------------------------------
    def _on_joint_state(self, data: bytes) -> None:
        self._joint_raw.append(data)

    def _on_accel(self, data: bytes) -> None:
        self._accel_raw.append(data)
        if len(self._accel_raw) >= self.batch_samples:
            self._process()

    def _process(self) -> None:
        """Push what arrived, joint states first; the core holds each block until the
        joint states covering it are in (at most JOINT_WAIT_S)."""
        self._last_input = time.monotonic()
        try:
            if self._joint_raw:
                raws, self._joint_raw = self._joint_raw, []
                stamps, _, velocity, n_bad = decode_joint_state_messages(raws, JOINT_NAMES)
                self.bad_messages += n_bad
                if len(stamps):
                    self.acc.push_joint_states(stamps, velocity)
            if self._accel_raw:
                raws, self._accel_raw = self._accel_raw, []
                stamps, accel, n_bad = decode_imu_messages(raws, TOPIC_RAW)
                self.bad_messages += n_bad
                if len(stamps):
                    self.acc.push_accel(stamps, accel)
        except EgovibError as exc:
            self.bad_messages += 1
            self.get_logger().warning(f"dropped a batch: {exc}", throttle_duration_sec=5.0)
        self._track_cells()

    def _track_cells(self) -> None:
        """A cell is complete when blocks start landing in another one: checkpoint then."""
        counts = self.acc.counts
        grown = np.flatnonzero((counts - self._counts).ravel() > 0)
        if grown.size:
            newest = int(grown[np.argmax((counts - self._counts).ravel()[grown])])
            if self._current_cell is not None and newest != self._current_cell:
                self._log_cell(self._current_cell, counts)
                self._checkpoint_due = True
            self._current_cell = newest
        self._counts = counts

    def _log_cell(self, flat: int, counts: np.ndarray) -> None:
        index = np.unravel_index(flat, counts.shape)
        velocity = ", ".join(f"{self.acc.grid[j][i]:+.3g}" for j, i in enumerate(index))
        covered = int((counts[self.expected] > 0).sum())
        self.get_logger().info(f"cell [{velocity}] done: {counts[index]} blocks; "
                               f"coverage {covered}/{int(self.expected.sum())} cells")

    def _on_timer(self) -> None:
        if self._accel_raw and time.monotonic() - self._last_input > 0.05:
            self._process()
        if self._checkpoint_due:
            self._checkpoint_due = False
            self.write_model(self.checkpoint)
            self.checkpoints_written += 1

    # --- output -----------------------------------------------------------------------
    def write_model(self, path: str) -> NoiseModel:
        """Write the model accumulated so far to `path`, atomically."""
        model = self.acc.to_model(source=f"live:{self.resolve_topic_name(TOPIC_RAW)}", measured=self.grid)
        with atomic_output(path) as tmp:
            model.save(tmp)
        return model

    def coverage(self) -> dict:
        counts = self.acc.counts
        missing = [tuple(float(self.acc.grid[j][i]) for j, i in enumerate(idx))
                   for idx in zip(*np.nonzero(self.expected & (counts == 0)))]
        return {"cells_covered": int((counts[self.expected] > 0).sum()),
                "cells_expected": int(self.expected.sum()), "blocks": int(counts.sum()),
                "min_blocks": int(counts[self.expected].min()), "missing_cells": missing}

    def _publish_diagnostics(self) -> None:
        cov = self.coverage()
        values = {k: v for k, v in cov.items() if k != "missing_cells"}
        values.update({"rejected": self.acc.stats["rejected"], "bad_messages": self.bad_messages,
                       "checkpoints_written": self.checkpoints_written,
                       "missing_cells": len(cov["missing_cells"])})
        level = "ok" if not self.bad_messages else "warn"
        message = f"{cov['cells_covered']}/{cov['cells_expected']} cells covered"
        self.pub_diag.publish(diagnostic_array(self.get_clock().now().nanoseconds,
                                               [("calibrator", level, message, values)]))

    def close(self) -> int:
        """Write the final model and report coverage; 1 if no block was collected."""
        self._process()
        self.acc.flush()
        cov = self.coverage()
        if cov["blocks"] == 0:
            print("calibrator: no steady block near any grid velocity: no model written", flush=True)
            return 1
        self.write_model(self.output)
        if os.path.exists(self.checkpoint):
            os.remove(self.checkpoint)
        print(f"calibrator: wrote {self.output}: {cov['cells_covered']}/{cov['cells_expected']} cells, "
              f"{cov['blocks']} blocks (min {cov['min_blocks']} per cell); missing cells: "
              f"{cov['missing_cells'] or 'none'}; rejected: {self.acc.stats['rejected']}", flush=True)
        return 0


def main(args: list[str] | None = None) -> int:
    return run_node(Calibrator, args)


if __name__ == "__main__":
    raise SystemExit(main())
