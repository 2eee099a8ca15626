"""Shared plumbing of the egovib_ros nodes: parameters, QoS, executor, clean shutdown."""
from __future__ import annotations

import sys
from typing import Any, Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.qos import (HistoryPolicy, QoSProfile, ReliabilityPolicy, DurabilityPolicy,
                       qos_profile_sensor_data)
from rclpy.qos_overriding_options import QoSOverridingOptions
from rcl_interfaces.msg import ParameterDescriptor

from egovib_ros.errors import EgovibError

# Sensor subscriptions: the contract's qos_profile_sensor_data (best effort, volatile)
# with a deeper queue (1 s at 3 kHz): publishers send 3 kHz streams in batches, which
# a depth of 5 would cut, and a starved process must not lose what DDS delivered.
SENSOR_QUEUE_DEPTH = 3000
SPIN_TIMEOUT_S = 0.1


def sensor_qos(depth: int = SENSOR_QUEUE_DEPTH) -> QoSProfile:
    """qos_profile_sensor_data with a queue deep enough for batched 3 kHz streams."""
    profile = QoSProfile(**{k: getattr(qos_profile_sensor_data, k) for k in
                            ("reliability", "durability", "history", "liveliness")}, depth=depth)
    return profile


def stream_publisher_qos(depth: int = SENSOR_QUEUE_DEPTH) -> QoSProfile:
    """Publishers of 3 kHz streams: reliable (so a reliable recorder can match too), keep-last."""
    return QoSProfile(reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
                      history=HistoryPolicy.KEEP_LAST, depth=depth)


def sensor_subscription(node: Node, msg_type, topic: str, callback, *, raw: bool = True):
    """Subscribe a sensor stream with sensor_qos(); reliability and depth may be overridden by
    the standard ROS parameters `qos_overrides.<topic>.subscription.{reliability,depth}`
    (e.g. reliable for a lossless replay of a bag on a loaded machine)."""
    return node.create_subscription(
        msg_type, topic, callback, sensor_qos(), raw=raw,
        qos_overriding_options=QoSOverridingOptions.with_default_policies())


def declare(node: Node, name: str, default: Any, description: str) -> Any:
    """Declare a parameter with a description and return its value."""
    return node.declare_parameter(name, default, ParameterDescriptor(description=description)).value


class NodeExit(Exception):
    """Raised inside a node callback to end spinning with an exit status."""

    def __init__(self, status: int = 0):
        super().__init__(status)
        self.status = status


def run_node(make_node: Callable[[], Node], args: list[str] | None = None) -> int:
    """Create the node, spin it on an EventsExecutor until it is done or Ctrl-C/SIGTERM.

    A node with a `run()` method (no callbacks to serve) is run instead of spun;
    its return value is the exit status. A node may define `done` (an rclpy Future: spinning stops when it completes, its
    result being the exit status) and `close()` (called once at the end, also after
    Ctrl-C: write files, log summaries). Bad input (EgovibError) is a one-line error
    and exit status 2.
    """
    rclpy.init(args=sys.argv if args is None else args)
    node = None
    status = 0
    try:
        node = make_node()
        executor = EventsExecutor()
        executor.add_node(node)
        done = getattr(node, "done", None)
        if hasattr(node, "run"):
            status = int(node.run() or 0)
        else:
            # spin_once in a loop: EventsExecutor.spin() (rclpy 7.1) busy-waits at 100 % CPU.
            while rclpy.ok() and not (done is not None and done.done()):
                executor.spin_once(timeout_sec=SPIN_TIMEOUT_S)
            if done is not None and done.done() and done.result() is not None:
                status = int(done.result())
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except EgovibError as exc:
        print(f"{getattr(node, 'get_name', lambda: 'egovib_ros')()}: error: {exc}", file=sys.stderr)
        status = 2
    finally:
        if node is not None:
            close = getattr(node, "close", None)
            try:
                if close is not None:
                    extra = close()
                    if extra:
                        status = status or int(extra)
            except EgovibError as exc:
                print(f"{node.get_name()}: error: {exc}", file=sys.stderr)
                status = 2
            node.destroy_node()
        rclpy.try_shutdown()
    return status
