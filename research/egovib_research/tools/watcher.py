"""Watcher: an rclpy node inside the calling process (its own context) that follows
/diagnostics and publishes joint commands, and the decoding of the streams it receives; the
in-process side of `egovib demo`, `egovib live-bench` and the node tests (the processes:
egovib_research.tools.orchestration)."""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.experimental import EventsExecutor
from rclpy.task import Future
from std_msgs.msg import Float64MultiArray

from egovib_ros.nodes.common import use_package_fastdds_profiles
from egovib_ros.nodes.convert import decode_imu_raws, decode_joint_state_raws


def decode_imu_messages(
    raws: Sequence[bytes], field: str = "linear_acceleration"
) -> tuple[np.ndarray, np.ndarray, int]:
    """Raw Imu CDR messages -> (stamps_ns, values (n, 3), number dropped), dropping
    undecodable and non-finite messages (for analysing a received stream)."""
    stamps, values, _ = decode_imu_raws(raws, field)
    finite = np.all(np.isfinite(values), axis=1)
    return stamps[finite], values[finite], len(raws) - int(finite.sum())


def decode_joint_state_messages(
    raws: Sequence[bytes], names: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """As decode_joint_state_raws, but also dropping rows without a finite position and
    velocity of every named joint; the count returned covers both kinds."""
    stamps, position, velocity, _ = decode_joint_state_raws(raws, names)
    good = np.all(np.isfinite(position), axis=1) & np.all(np.isfinite(velocity), axis=1)
    return stamps[good], position[good], velocity[good], len(raws) - int(good.sum())


class Watcher:
    """An rclpy node in this process (own context): the latest /diagnostics status of each
    node, and a publisher of joint commands (ros2_control forward-command convention)."""

    def __init__(
        self,
        name: str = "egovib_watcher",
        commands_topic: str = "hand_velocity_controller/commands",
    ):
        use_package_fastdds_profiles()  # queue depths as asked (the tests ask 10 s)
        self.context = rclpy.Context()
        rclpy.init(
            context=self.context, signal_handler_options=rclpy.signals.SignalHandlerOptions.NO
        )
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = EventsExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.status: dict[str, str] = {}  # node status name -> message
        self.statuses: dict[str, object] = {}  # node status name -> latest DiagnosticStatus
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)
        self.commands = self.node.create_publisher(Float64MultiArray, commands_topic, 10)
        self._never = Future()  # spun "until" for a time: see _spin

    def _spin(self, seconds: float) -> None:
        # Events for `seconds`, all in one call: a call per event (spin_once) costs this
        # process a core's share at a 3 kHz subscription, and delays what it measures.
        self.executor.spin_until_future_complete(self._never, timeout_sec=max(0.0, seconds))

    def _on_diagnostics(self, msg) -> None:
        for status in msg.status:
            self.status[status.name] = status.message
            self.statuses[status.name] = status

    def spin_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self._spin(min(0.05, deadline - time.monotonic()))

    def spin_until(self, predicate, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if predicate():
                return True
            self._spin(0.01)
        return bool(predicate())

    def drain(self, *received: list, quiet_s: float = 0.5, timeout: float = 20.0) -> bool:
        """Spin until none of the `received` lists (filled by subscriptions) has grown for
        `quiet_s`: what DDS delivered but this process had not taken yet is then taken."""
        deadline = time.monotonic() + timeout
        sizes, since = None, time.monotonic()
        while time.monotonic() < deadline:
            now_sizes = [len(r) for r in received]
            if now_sizes != sizes:
                sizes, since = now_sizes, time.monotonic()
            elif time.monotonic() - since >= quiet_s:
                return True
            self._spin(0.01)
        return False

    def close(self) -> None:
        self.node.destroy_node()
        self.context.try_shutdown()
