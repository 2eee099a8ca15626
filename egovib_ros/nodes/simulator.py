"""What the simulator nodes share (sim_hand: the PR2 hand; sim_robot: any robot profile).

A SimulatorNode steps a streaming simulator from a timer in real time on the node clock
(from the first non-zero clock time, or once every stream has its subscribers), follows
the velocity commands and publishes the profile's joint states, sensor stream and ground
truth (`<parent of the sensor topic>/contact`, `/ego`) as pre-serialised CDR. A node says
what to simulate through configure (its parameters, the profile), make (the simulator),
due (samples due by a clock time) and describe (its start-up line). docs/live_nodes.md.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.task import Future
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray

from egovib_ros.bag.codec import encode_imu_batch, encode_joint_state_batch
from egovib_ros.bag.recording import bag_topic_names
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import StreamError
from egovib_ros.nodes.common import (
    Health,
    Param,
    SubscriberGate,
    declare_parameters,
    stream_publisher,
    wait_for_delivery,
)
from egovib_ros.nodes.convert import command_velocity
from egovib_ros.robot import COMMANDS_TOPIC, RobotProfile


def simulator_parameters(*, frame_id: str, truth: str) -> tuple[Param, ...]:
    """The parameters every simulator node declares (`truth`: its ground-truth topics, for
    the descriptions; `frame_id`: the default frame of its Imu messages)."""
    return (
        Param("seed", 0, "random seed of the simulator", range=(0, 2**31 - 1)),
        Param(
            "duration",
            0.0,
            "seconds to simulate, then exit 0 once the subscribers have the last samples "
            "(0: until stopped)",
            range=(0.0, 1e7),
        ),
        Param("tap_rate_hz", 0.0, "mean rate of simulated taps (0 = none)", range=(0.0, 100.0)),
        Param(
            "tap_mode",
            "random",
            "tap onsets: random (Poisson) | periodic",
            choices=("random", "periodic"),
        ),
        Param(
            "publish_period",
            0.01,
            "seconds between publishing batches of samples",
            range=(0.0005, 1.0),
        ),
        Param("publish_ground_truth", True, f"publish {truth}"),
        Param("publish_ego", True, "with publish_ground_truth: also publish the ego topic"),
        Param("frame_id", frame_id, "frame_id of the Imu messages"),
        Param(
            "max_batch",
            0.1,
            "most seconds of samples generated per tick when catching up",
            range=(0.001, 10.0),
        ),
        Param(
            "wait_for_subscribers",
            0,
            "start simulating only once every published stream has this many subscribers",
            range=(0, 100),
        ),
        Param(
            "wait_timeout",
            30.0,
            "seconds to wait for those subscribers before starting anyway",
            range=(0.0, 3600.0),
        ),
    )


class SimulatorNode(Node):
    """The simulator of a robot profile as a node; subclasses say which (module doc)."""

    #: /diagnostics key of the rate of samples published
    RATE_KEY = "sensor_rate_hz"

    def __init__(self, name: str, parameters: tuple[Param, ...]):
        super().__init__(name)
        params = declare_parameters(self, parameters)
        self.profile: RobotProfile = self.configure(params)
        self.seed, self.tap_rate_hz = int(params["seed"]), params["tap_rate_hz"]
        self.tap_mode = params["tap_mode"]
        self.period_s = params["publish_period"]
        self.ground_truth = params["publish_ground_truth"]
        self.frame_id = params["frame_id"]
        self.max_batch_s = params["max_batch"]
        self.duration_s = params["duration"]
        #: samples to simulate (0: until stopped)
        self.total_samples = int(round(self.duration_s * self.profile.rate_hz))
        self.done = Future()  # run_node spins until it is done: its result, the exit status
        self.make(start_ns=0)  # validate the settings now, not at the first tick
        # sim.HandSimulator or sim.robot.CommandedRobot: command, index, velocity, set_command
        # and step (sensor_stamps_ns, sensor, contact, ego, joint_*)
        self.sim: Any = None
        # Commands with their arrival time, each applied from the first sample stamped at or
        # after it: a simulator that fell behind (a busy machine) then still moves as
        # commanded when commanded, instead of skipping what it missed at the latest command.
        self._commands: deque[tuple[int, np.ndarray]] = deque()

        profile, topics = self.profile, bag_topic_names(self.profile)
        self.pub_joint = stream_publisher(self, JointState, profile.node_joints_topic)
        self.pub_raw = stream_publisher(self, Imu, profile.node_sensor_topic)
        self.pub_contact = (
            stream_publisher(self, Imu, topics["contact"].lstrip("/"))
            if self.ground_truth
            else None
        )
        self.pub_ego = (
            stream_publisher(self, Imu, topics["ego"].lstrip("/"))
            if self.ground_truth and params["publish_ego"]
            else None
        )
        # not `_publishers`: rclpy's Node keeps its own list under that name and appends every
        # later publisher to it (/diagnostics then held the gate shut until its timeout)
        self._streams = [
            p
            for p in (self.pub_joint, self.pub_raw, self.pub_contact, self.pub_ego)
            if p is not None
        ]
        self.gate = SubscriberGate(
            self._streams,
            params["wait_for_subscribers"],
            params["wait_timeout"],
        )
        self.health = Health(self, hardware_id=profile.name)
        self.create_subscription(Float64MultiArray, COMMANDS_TOPIC, self._on_command, 10)
        self.commands_received = 0
        self.commands_rejected = 0
        self.samples_published = 0
        self.taps = 0
        self.max_lag_samples = 0
        self._last_diag = (0, 0)
        self.create_timer(self.period_s, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(self.describe())

    # --- what a subclass says -------------------------------------------------------
    def configure(self, params: dict[str, Any]) -> RobotProfile:
        """Read the node's own parameters; the robot profile simulated."""
        raise NotImplementedError

    def make(self, start_ns: int) -> Any:
        """A simulator whose first sample is stamped `start_ns`."""
        raise NotImplementedError

    def due(self, now_ns: int) -> int:
        """How many samples of self.sim are due by clock time `now_ns`."""
        raise NotImplementedError

    def describe(self) -> str:
        """The start-up log line."""
        raise NotImplementedError

    def taps_in(self, chunk) -> int:
        """How many taps began in `chunk` (a step's output)."""
        return len(chunk.tap_onsets_ns)

    def command_note(self, requested: np.ndarray, result) -> None:
        """Called with each command applied and what the simulator's set_command said."""

    def extra_values(self) -> dict[str, object]:
        """More /diagnostics values of the subclass (its WARN_COUNTERS among them)."""
        return {}

    #: Counters (keys of the /diagnostics values) whose growth since the previous report is
    #: a WARN, with its text.
    WARN_COUNTERS = {"commands_rejected": "{} commands rejected"}

    # --- commands and stepping ------------------------------------------------------
    def _on_command(self, msg: Float64MultiArray) -> None:
        try:
            velocity = command_velocity(msg, self.profile.n_joints, topic=COMMANDS_TOPIC)
        except StreamError as exc:
            self.commands_rejected += 1
            self.get_logger().warning(str(exc), throttle_duration_sec=5.0)
            return
        self.commands_received += 1
        if self.sim is None:  # not started: only the latest command will matter
            self._commands.clear()
        self._commands.append((self.get_clock().now().nanoseconds, velocity))

    def _apply_commands_due(self) -> int:
        """Apply the commands that arrived by the next sample's stamp; how many samples
        may be made before the next command is due (-1: no command waiting)."""
        while self._commands:
            arrival_ns, velocity = self._commands[0]
            ahead = self.due(arrival_ns)  # samples stamped before the command arrived
            if ahead > 0:
                return ahead
            self._commands.popleft()
            self.command_note(velocity, self.sim.set_command(velocity))
        return -1

    def _tick(self) -> None:
        now_ns = self.get_clock().now().nanoseconds
        if now_ns <= 0 or self.done.done():  # use_sim_time and no /clock yet; or finished
            return
        if self.sim is None:
            if not self._subscribers_ready():
                return
            self.sim = self.make(start_ns=now_ns)
            self.get_logger().info(f"simulation started at stamp {now_ns} ns")
        lag = self.due(now_ns)
        if self.total_samples:
            lag = min(lag, self.total_samples - self.sim.index)
        if lag <= 0:
            return
        self.max_lag_samples = max(self.max_lag_samples, lag)
        remaining = min(lag, max(1, int(self.max_batch_s * self.profile.rate_hz)))
        while remaining > 0:
            ahead = self._apply_commands_due()
            n = remaining if ahead < 0 else min(remaining, ahead)
            self._publish(self.sim.step(n))
            remaining -= n
        if self.total_samples and self.sim.index >= self.total_samples:
            self._finish()

    def _publish(self, chunk) -> None:
        self.taps += self.taps_in(chunk)
        if len(chunk.joint_stamps_ns):  # a short step may hold no joint state
            for data in encode_joint_state_batch(
                chunk.joint_stamps_ns,
                chunk.joint_position,
                chunk.joint_velocity,
                self.profile.joint_names,
            ):
                self.pub_joint.publish(data)
        field = self.profile.sensor_field
        for publisher, values in (
            (self.pub_raw, chunk.sensor),
            (self.pub_contact, chunk.contact),
            (self.pub_ego, chunk.ego),
        ):
            if publisher is not None:
                for data in encode_imu_batch(chunk.sensor_stamps_ns, values, self.frame_id, field):
                    publisher.publish(data)
        self.samples_published += len(chunk.sensor_stamps_ns)

    def _finish(self) -> None:
        """`duration` simulated: the subscribers get the last samples, then exit status 0."""
        self.get_logger().info(
            f"simulated {self.duration_s:g} s: {self.samples_published} samples, {self.taps} taps"
        )
        wait_for_delivery(self, self._streams, "the last samples")
        self._publish_diagnostics()
        self.done.set_result(0)

    def _subscribers_ready(self) -> bool:
        """All streams matched (or waited long enough): recordings then start complete."""
        if self.gate.is_open():
            if self.gate.timed_out:
                self.get_logger().warning("not every stream has its subscribers: starting anyway")
            return True
        return False

    # --- health ---------------------------------------------------------------------
    def _publish_diagnostics(self) -> None:
        if self.sim is None:
            return
        now_ns = self.get_clock().now().nanoseconds
        last_ns, last_samples = self._last_diag
        rate = (
            (self.samples_published - last_samples) * NS_PER_S / (now_ns - last_ns)
            if last_ns and now_ns > last_ns
            else 0.0
        )
        self._last_diag = (now_ns, self.samples_published)
        values = {
            self.RATE_KEY: rate,
            "samples_published": self.samples_published,
            "max_lag_samples": self.max_lag_samples,
            "taps": self.taps,
            "commands_received": self.commands_received,
            "commands_rejected": self.commands_rejected,
            "command": [float(v) for v in np.round(self.sim.command, 6)],
            "velocity": [float(v) for v in np.round(self.sim.velocity, 6)],
        }
        values.update(self.extra_values())
        grown = self.health.changes({key: values[key] for key in self.WARN_COUNTERS})
        self.health.publish(
            warnings=[
                text.format(grown[key]) for key, text in self.WARN_COUNTERS.items() if grown[key]
            ],
            ok="done"
            if self.total_samples and self.sim.index >= self.total_samples
            else "simulating",
            values=values,
        )
        self.max_lag_samples = 0
