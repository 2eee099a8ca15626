"""Shared plumbing of the egovib_ros nodes: parameters, QoS, raw-message batching, health
(/diagnostics), executor and clean shutdown."""

from __future__ import annotations

import contextlib
import math
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
    qos_profile_sensor_data,
)
from rclpy.qos_overriding_options import QoSOverridingOptions
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future
from sensor_msgs.msg import Imu, JointState

from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.core.velocity import JointVelocity, SplitJointStates, hold_missing_joints
from egovib_ros.errors import ConfigError, EgovibError
from egovib_ros.nodes.convert import (
    decode_imu_raws,
    decode_joint_state_raws,
    diagnostic_array,
    joint_names_of,
)
from egovib_ros.robot import config_dir

# Queue depth of the 3 kHz streams (1 s): publishers send them in batches, which a depth
# of 5 would cut, and a starved process must not lose what DDS delivered.
SENSOR_QUEUE_DEPTH = 3000
SPIN_TIMEOUT_S = 0.1
#: After our writers see their subscribers, time for the subscribers' readers to see our
#: writers too (DDS matches each side on its own): a reliable sample sent before that is
#: resent only at the writer's next heartbeat (Fast DDS: every 3 s), i.e. arrives late.
MATCH_SETTLE_S = 1.0
#: How long a node that is about to exit waits for its subscribers to acknowledge what it
#: sent last (reliable QoS): unacknowledged samples die with the process.
DELIVERY_TIMEOUT_S = 5.0
#: Latest sensor and joint-state stamps further apart than this (s), with joint states
#: still arriving, are two clocks (any lag a robot has is well below it).
CLOCKS_APART_S = 1.0
FASTDDS_PROFILES_VARIABLE = "FASTRTPS_DEFAULT_PROFILES_FILE"


def use_package_fastdds_profiles() -> None:
    """Call before rclpy.init: unless the user chose Fast DDS profiles (the variable is set)
    or another middleware, point Fast DDS at config/fastdds_profiles.xml, which lets every
    queue have the depth its QoS asks for. Fast DDS 2.x otherwise caps each reader's queue
    at 5000 samples whatever the depth (bag_recorder asks 30000: 10 s at 3 kHz)."""
    if os.environ.get(FASTDDS_PROFILES_VARIABLE):
        return
    if not os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps"):
        return
    try:
        path = config_dir() / "fastdds_profiles.xml"
    except ConfigError:
        return
    if path.is_file():
        os.environ[FASTDDS_PROFILES_VARIABLE] = str(path)


def sensor_qos() -> QoSProfile:
    """The contract's qos_profile_sensor_data (best effort, volatile), SENSOR_QUEUE_DEPTH deep."""
    return QoSProfile(
        **{
            k: getattr(qos_profile_sensor_data, k)
            for k in ("reliability", "durability", "history", "liveliness")
        },
        depth=SENSOR_QUEUE_DEPTH,
    )


def stream_publisher_qos(depth: int = SENSOR_QUEUE_DEPTH) -> QoSProfile:
    """Publishers of 3 kHz streams: reliable (so a reliable recorder can match too), keep-last."""
    return QoSProfile(
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
    )


def stream_publisher(node: Node, msg_type, topic: str):
    """A publisher of a 3 kHz stream with stream_publisher_qos(), overridable by the ROS
    parameters `qos_overrides.<topic>.publisher.{depth,reliability}`. The deep history makes
    a reliable link lossless on a loaded machine: a sample lost on the way is resent at the
    writer's next heartbeat (Fast DDS: every 3 s), only if the writer still holds it."""
    return node.create_publisher(
        msg_type,
        topic,
        stream_publisher_qos(),
        qos_overriding_options=QoSOverridingOptions.with_default_policies(),
    )


class SubscriberGate:
    """Whether a node may start publishing: every one of `publishers` has `count` subscribers
    and MATCH_SETTLE_S has passed since (the subscribers' side of the match), or `timeout_s`
    has passed (`timed_out` then says so). `count` 0: open at once. Polled, never blocks;
    once open it stays open."""

    def __init__(self, publishers: Sequence, count: int, timeout_s: float):
        self.publishers = tuple(publishers)  # its own copy: a list appended to later is not its
        self.count, self.timeout_s = count, timeout_s
        self.timed_out = False
        self._open = count <= 0
        self._since: float | None = None
        self._matched_since: float | None = None

    def is_open(self) -> bool:
        if self._open:
            return True
        now = time.monotonic()
        if self._since is None:
            self._since = now
        if all(p.get_subscription_count() >= self.count for p in self.publishers):
            if self._matched_since is None:
                self._matched_since = now
            self._open = now - self._matched_since >= MATCH_SETTLE_S
        else:
            self._matched_since = None
        if not self._open and now - self._since > self.timeout_s:
            self.timed_out = self._open = True
        return self._open


def wait_for_delivery(node: Node, publishers: Sequence, what: str) -> None:
    """Before exiting: wait up to DELIVERY_TIMEOUT_S for every subscriber to acknowledge what
    `publishers` sent (reliable QoS); warn naming the topics that were not acknowledged."""
    deadline = time.monotonic() + DELIVERY_TIMEOUT_S
    late = []
    for pub in publishers:
        left = max(deadline - time.monotonic(), 0.0)
        if not pub.wait_for_all_acked(Duration(nanoseconds=int(left * NS_PER_S))):
            late.append(pub.topic_name)
    if late:
        node.get_logger().warning(
            f"{what} not acknowledged within {DELIVERY_TIMEOUT_S:g} s by every subscriber of "
            f"{', '.join(late)}"
        )


def sensor_subscription(node: Node, msg_type, topic: str, callback):
    """Subscribe a sensor stream raw with sensor_qos(), overridable by the ROS parameters
    `qos_overrides.<topic>.subscription.{reliability,depth}` (e.g. reliable for a lossless
    replay of a bag on a loaded machine)."""
    return node.create_subscription(
        msg_type,
        topic,
        callback,
        sensor_qos(),
        raw=True,
        qos_overriding_options=QoSOverridingOptions.with_default_policies(),
    )


# --- parameters ------------------------------------------------------------------
@dataclass(frozen=True)
class Param:
    """A node parameter. `read_only` (the default) for anything whose change needs a restart;
    `choices` are checked at start (`ros2 param describe` shows them); `range` is inclusive,
    enforced by rclpy on every set."""

    name: str
    default: Any
    description: str
    read_only: bool = True
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] = ()

    def descriptor(self, default: Any) -> ParameterDescriptor:
        descriptor = ParameterDescriptor(description=self.description, read_only=self.read_only)
        if self.choices:
            descriptor.additional_constraints = "one of: " + ", ".join(self.choices)
        if self.range is not None:
            low, high = self.range
            if isinstance(default, int):
                descriptor.integer_range = [
                    IntegerRange(from_value=int(low), to_value=int(high), step=1)
                ]
            else:
                descriptor.floating_point_range = [
                    FloatingPointRange(from_value=float(low), to_value=float(high), step=0.0)
                ]
        return descriptor


#: The `robot` parameter of the nodes that take a robot profile rather than a model.
ROBOT_PARAM = Param(
    "robot",
    "",
    "robot profile: a YAML path or a shipped name (config/robots); empty = the PR2 hand",
)


def declare_parameters(
    node: Node, params: Sequence[Param], defaults: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Declare `params` (defaults may be replaced, e.g. from a model) and return their values.

    A value out of range, of the wrong type or not among the choices is a one-line
    ConfigError naming the node and the parameter (exit status 2 via run_node)."""
    values = {}
    for param in params:
        default = (defaults or {}).get(param.name, param.default)
        where = f"{node.get_name()}: parameter '{param.name}'"
        try:
            value = node.declare_parameter(param.name, default, param.descriptor(default)).value
        except ParameterException as exc:
            raise ConfigError(f"{where}: {_parameter_reason(exc)}") from None
        if param.choices and value not in param.choices:
            named = ", ".join(c for c in param.choices if c)
            unset = " (or unset: the default)" if "" in param.choices else ""
            raise ConfigError(f"{where} must be one of {named}{unset}; got {value!r}")
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{where} must be finite, got {value}")
        values[param.name] = value
    return values


def _parameter_reason(exc: ParameterException) -> str:
    text = str(exc)
    if "Reason:" in text:  # InvalidParameterValueException: "... Reason: <why>: name"
        text = text.split("Reason:", 1)[1].strip().rsplit(":", 1)[0]
    elif "expecting type" in text:  # InvalidParameterTypeException
        text = (
            text.rsplit(":", 1)[0] + " (write floating-point values with a decimal point, e.g. 2.0)"
        )
    return text


# --- raw input, batched ----------------------------------------------------------
@dataclass
class SensorBatch:
    stamps_ns: np.ndarray  # (n,)
    values: np.ndarray  # (n, 3) the profile's Imu field; non-finite kept
    raws: list[bytes]  # (n) the input messages (kept for the drop-in output)
    arrival_ns: np.ndarray  # (n,) monotonic receive time of each message


@dataclass
class JointBatch:
    stamps_ns: np.ndarray  # (m,)
    velocity: np.ndarray  # (m, J) in profile order; NaN where a message lacks a joint


def drain(subscription, msg_type, data: bytes) -> list[bytes]:
    """`data` (a raw subscription's callback argument) and every message waiting in the
    subscription's queue: a driver's burst is taken as one batch, without an executor round
    per message of a 3 kHz stream (the executor finds nothing left for their events)."""
    taken = [data]
    take = subscription.handle.take_message
    while (more := take(msg_type, True)) is not None:
        taken.append(more[0])
    return taken


class StreamInput:
    """The profile's sensor and joint-state topics, subscribed raw: CDR bytes collected in
    the callbacks, decoded in batches. `on_batch` is called at every `batch_samples`-th
    sensor message counted from the first, with the rest of its burst (batch_samples = hop:
    a block as soon as it is complete); with `from_first` False, as soon as `batch_samples`
    messages wait (a per-sample method's batches follow the driver's bursts). Undecodable
    messages are counted and left out; the rest, NaN included, go to the core. Joint
    velocity as offline (bag.recording.RecordingStream): the profile's `joints.velocity`
    through core.velocity.JointVelocity, then a joint a message lacks keeps its last value.
    """

    def __init__(
        self,
        node: Node,
        profile,
        *,
        batch_samples: int,
        on_batch: Callable[[], None],
        on_joint_state: Callable[[], None] | None = None,
        from_first: bool = True,
        sensor_topic: str | None = None,
    ):
        """`sensor_topic`: another topic of the profile's Imu (the contact detector's input:
        the denoised one) instead of the sensor's."""
        self.field = profile.sensor_field
        self.profile_name = profile.name
        self.joint_names = tuple(profile.joint_names)
        self.batch_samples = int(batch_samples)
        self._from_first = from_first
        self._on_batch = on_batch
        self._on_joint_state = on_joint_state
        sensor_topic = sensor_topic or profile.node_sensor_topic
        self._sensor_sub = sensor_subscription(node, Imu, sensor_topic, self._on_sensor)
        self._joints_sub = sensor_subscription(
            node, JointState, profile.node_joints_topic, self._on_joints
        )
        self._logger = node.get_logger()
        self._logged_missing: list[str] = []
        self.sensor_topic = node.resolve_topic_name(sensor_topic)
        self.joints_topic = node.resolve_topic_name(profile.node_joints_topic)
        self._sensor: list[bytes] = []
        self._arrival: list[int] = []
        self._joints: list[bytes] = []
        self.sensor_messages = self.joint_messages = 0
        self.undecodable_sensor = self.undecodable_joints = 0
        self.last_sensor_s: float | None = None  # monotonic times of the last messages
        self.last_joint_s: float | None = None
        self.joints_seen = np.zeros(len(self.joint_names), bool)
        self.velocity_setting = profile.velocity_source
        self._joint_velocity = JointVelocity(len(self.joint_names), source=self.velocity_setting)
        self.velocities_measured = 0  # joint velocities taken from the messages
        self._last_joint: np.ndarray | None = None  # (2, J) last position and velocity
        self._split_joints = SplitJointStates()  # per-joint messages of one stamp joined
        self.carried_joint_names: tuple[str, ...] = ()  # names in a message lacking a named joint
        # header stamps of the last decoded sensor sample and joint state (ns), for clocks
        self.last_sensor_stamp_ns: int | None = None
        self.last_joint_stamp_ns: int | None = None
        self._counted = (0, 0)  # sensor and joint-state messages at the last stamp_notes

    # callbacks: keep them minimal, 3 kHz
    def _on_sensor(self, data: bytes) -> None:
        taken = drain(self._sensor_sub, Imu, data)
        now = time.monotonic_ns()
        self._sensor.extend(taken)
        self._arrival.extend([now] * len(taken))
        before, self.sensor_messages = self.sensor_messages, self.sensor_messages + len(taken)
        if self._from_first:
            due = self.sensor_messages // self.batch_samples > before // self.batch_samples
        else:
            due = len(self._sensor) >= self.batch_samples
        if due:
            self._on_batch()

    def _on_joints(self, data: bytes) -> None:
        taken = drain(self._joints_sub, JointState, data)
        self._joints.extend(taken)
        self.joint_messages += len(taken)
        if self._on_joint_state is not None:
            self._on_joint_state()

    def publisher_counts(self) -> dict[str, int]:
        """Publishers matched per input topic, for /diagnostics (0: nobody publishes it, e.g.
        a wrong remapping; a publisher sees this side of the match is done too)."""
        return {
            "sensor_publishers": self._sensor_sub.get_publisher_count(),
            "joint_state_publishers": self._joints_sub.get_publisher_count(),
        }

    @property
    def sensor_pending(self) -> int:
        return len(self._sensor)

    def take_sensor(self) -> SensorBatch | None:
        """Decode the sensor messages received since the last call."""
        if not self._sensor:
            return None
        raws, self._sensor = self._sensor, []
        arrival, self._arrival = np.asarray(self._arrival, dtype=np.int64), []
        self.last_sensor_s = arrival[-1] / NS_PER_S
        stamps, values, index = decode_imu_raws(raws, self.field)
        if len(index) < len(raws):
            self.undecodable_sensor += len(raws) - len(index)
            raws = [raws[i] for i in index]
            arrival = arrival[index]
        if len(stamps):
            self.last_sensor_stamp_ns = int(stamps[-1])
        return SensorBatch(stamps, values, raws, arrival)

    def take_joints(self, *, final: bool = False) -> JointBatch | None:
        """Decode the joint states received since the last call (columns by name); `final`
        (the stream has gone quiet): also the last stamp's, held back while the next
        message could still complete it."""
        flush = final and self._split_joints.held_from_ns is not None
        if not self._joints and not flush:
            return None
        raws, self._joints = self._joints, []
        if raws:
            self.last_joint_s = time.monotonic()
        stamps, position, velocity, bad = decode_joint_state_raws(raws, self.joint_names)
        self.undecodable_joints += bad
        # one message per joint, one stamp: one row, as the bag layer reads it offline
        stamps, position, velocity = self._split_joints.push(stamps, position, velocity)
        held = self._split_joints.flush() if final else None
        if held is not None:  # the end of the stream: the last stamp's, held back, goes last
            stamps, position, velocity = (
                np.concatenate([a, b]) for a, b in zip((stamps, position, velocity), held)
            )
        if len(stamps):
            present = ~(np.isnan(position) & np.isnan(velocity))
            self.joints_seen |= present.any(axis=0)
            if not self.joints_seen.all() and not self.carried_joint_names and raws:
                self.carried_joint_names = joint_names_of(raws[-1])
            derived_before = self._joint_velocity.derived
            velocity = self._joint_velocity.push(stamps, position, velocity)
            usable = int(np.isfinite(velocity).sum())
            self.velocities_measured += usable - (self._joint_velocity.derived - derived_before)
            # a joint a message lacks keeps its last value, as the bag layer reads it offline
            _, velocity, self._last_joint = hold_missing_joints(
                position, velocity, self._last_joint
            )
            self.last_joint_stamp_ns = int(stamps[-1])
        return JointBatch(stamps, velocity)

    def velocity_values(self) -> dict[str, object]:
        """For /diagnostics: the profile's setting and where the joint velocities received so
        far came from: measured (the messages'), from_position, both (auto) or none (yet)."""
        derived = self._joint_velocity.derived
        if derived and self.velocities_measured:
            source = "both"
        else:
            source = (
                "from_position" if derived else "measured" if self.velocities_measured else "none"
            )
        return {
            "velocity_setting": self.velocity_setting,
            "velocity_source": source,
            "joint_velocities_from_position": derived,
        }

    def stamp_notes(self, grown: dict[str, float]) -> list[str]:
        """For the periodic report (`grown`: the stream counters' growth since the last): a
        topic most of whose messages since were dropped as their stamps repeat or go back,
        with the likely cause (a driver that stamps zero, a stuck clock, two publishers)."""
        received = (self.sensor_messages, self.joint_messages)
        sensor_in, joints_in = (now - before for now, before in zip(received, self._counted))
        self._counted = received
        notes = []
        for topic, dropped, came, key in (
            (self.sensor_topic, "samples_out_of_order", sensor_in, "sensor_publishers"),
            (self.joints_topic, "joint_states_dropped", joints_in, "joint_state_publishers"),
        ):
            if came and grown.get(dropped, 0) > 0.5 * came:
                publishers = self.publisher_counts()[key]
                why = (
                    f"{publishers} publishers on it: two sensors, or one twice?"
                    if publishers > 1
                    else "a driver that stamps zero, or a stuck clock?"
                )
                notes.append(f"{topic}: most stamps repeat or go back ({why})")
        return notes

    def publishers_note(self) -> str:
        """' (N publishers on <sensor topic>)' when more than one: two sensors on one topic
        look like one stream at another rate."""
        n = self.publisher_counts()["sensor_publishers"]
        return f" ({n} publishers on {self.sensor_topic})" if n > 1 else ""

    def clock_note(self) -> str:
        """'joint-state stamps X s behind the sensor's: ...' when the two streams' latest
        stamps are further apart than any lag (CLOCKS_APART_S) while joint states keep
        coming: two clocks (sim time and wall time, a driver that stamps zero), else ''."""
        if self.last_sensor_stamp_ns is None or self.last_joint_stamp_ns is None:
            return ""
        if self.last_joint_s is None or time.monotonic() - self.last_joint_s > CLOCKS_APART_S:
            return ""  # joint states stopped: not a clock
        apart = (self.last_sensor_stamp_ns - self.last_joint_stamp_ns) / NS_PER_S
        if abs(apart) <= CLOCKS_APART_S:
            return ""
        way = "behind" if apart > 0 else "ahead of"
        return (
            f"joint-state stamps {abs(apart):.3g} s {way} the sensor's: the two topics are "
            "stamped by different clocks?"
        )

    def missing_joints(self) -> list[str]:
        """Named joints that no joint state received so far has carried."""
        if self.last_joint_s is None:
            return []
        return [name for name, seen in zip(self.joint_names, self.joints_seen) if not seen]

    def missing_joints_error(self, consequence: str) -> str | None:
        """For the periodic report: the ERROR text for named joints never seen (None when all
        were), logged with its `consequence` once per change. Not per message: joint states
        split over several publishers lack some joints until each has been heard once."""
        missing = self.missing_joints()
        message = self.missing_joints_message(missing) if missing else None
        if missing != self._logged_missing:
            self._logged_missing = missing
            if message:
                self._logger.error(f"{message}: {consequence}")
        return message

    def missing_joints_message(self, missing: list[str]) -> str:
        carried = set(self.carried_joint_names)
        if self.undecodable_joints and not self.joints_seen.any():
            why = f" ({self.undecodable_joints} of its messages undecodable)"
        elif carried and set(missing) <= carried:
            why = " (its messages name them, with no position or velocity)"
        elif carried and not self.joints_seen.any():
            why = (
                f" (its messages carry {list(self.carried_joint_names)}, none of robot profile "
                f"{self.profile_name!r}: a model of another robot?)"
            )
        elif carried:
            why = f" (its messages carry {list(self.carried_joint_names)})"
        else:
            why = ""
        return (
            f"{self.joints_topic}: joint{'s' if len(missing) > 1 else ''} "
            f"{', '.join(repr(m) for m in missing)} never seen{why}"
        )


# --- health ------------------------------------------------------------------------
def stream_counters(inp: "StreamInput", stats) -> dict[str, int]:
    """The input-quality counters (cumulative) of a stream node: its undecodable messages and
    the core's counts (`stats`: DenoiserStats or CalibrationStats)."""
    return {
        "undecodable_messages": inp.undecodable_sensor + inp.undecodable_joints,
        "samples_bad": stats.samples_bad,
        "samples_out_of_order": stats.dropped_out_of_order,
        "samples_duplicate": stats.duplicates,  # of those, exact repeats (recorded twice)
        "gap_filled_samples": stats.gap_filled_samples,
        "stream_restarts": stats.resets,
        "joint_states_dropped": stats.joint_states_dropped,
    }


class Health:
    """The node's DiagnosticStatus on /diagnostics (~1 Hz), named by its fully qualified name
    without the leading '/'; ERROR > STALE > WARN (since the previous report) > OK, every
    report with the same keys (docs/live_nodes.md, Health)."""

    def __init__(self, node: Node, *, hardware_id: str = "", stale_after_s: float = 3.0):
        self.node = node
        self.name = node.get_fully_qualified_name().lstrip("/")
        self.hardware_id = hardware_id
        self.stale_after_s = float(stale_after_s)
        self.publisher = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._previous: dict[str, float] = {}
        self.level = "stale"

    def changes(self, counters: dict[str, float]) -> dict[str, float]:
        """How much each counter grew since the previous call."""
        grown = {k: v - self._previous.get(k, 0) for k, v in counters.items()}
        self._previous = dict(counters)
        return grown

    def stale_message(self, last_input_s: float | None, what: str) -> str | None:
        """'no input ...' when nothing arrived for stale_after_s (or ever), else None."""
        if last_input_s is None:
            return f"no input on {what} yet"
        idle = time.monotonic() - last_input_s
        return f"no input on {what} for {idle:.1f} s" if idle >= self.stale_after_s else None

    def publish(
        self,
        *,
        errors: Sequence[str] = (),
        stale: str | None = None,
        warnings: Sequence[str] = (),
        ok: str = "ok",
        values: dict[str, object],
    ) -> None:
        if errors:
            level, message = "error", "; ".join(errors)
        elif stale:
            level, message = "stale", stale
        elif warnings:
            level, message = "warn", "; ".join(warnings)
        else:
            level, message = "ok", ok
        self.level = level
        self.publisher.publish(
            diagnostic_array(
                self.node.get_clock().now().nanoseconds,
                [(self.name, level, message, values)],
                self.hardware_id,
            )
        )


# --- running ----------------------------------------------------------------------
def run_node(make_node: Callable[[], Node], args: list[str] | None = None) -> int:
    """Create the node, spin it on an EventsExecutor until it is done or Ctrl-C/SIGTERM.

    A node with a `run()` method is run instead of spun, its return value the exit status.
    A node may define `done` (an rclpy Future ending the spin, its result the exit status)
    and `close()` (called once at the end, also after Ctrl-C). Bad input (EgovibError) is a
    one-line error and exit status 2.
    """
    use_package_fastdds_profiles()
    # Ctrl-C and SIGTERM are ours (_StopOnSignal), not rclpy's: its handlers shut the context
    # down under running callbacks ("[FATAL] ... publisher's context is invalid", and close()
    # logging "Failed to publish log message to rosout"). A signal while spinning ends the
    # spin loop (within SPIN_TIMEOUT_S); the node closes with its context valid.
    program = os.path.basename(sys.argv[0]) or "egovib_ros"
    try:
        rclpy.init(
            args=sys.argv if args is None else args, signal_handler_options=SignalHandlerOptions.NO
        )
    except _rclpy.RCLError as exc:  # the command line's --ros-args (e.g. `-p model:=`, no value)
        reason = str(exc).split(", at ")[0].removeprefix("failed to initialize rcl: ")
        reason = reason.split(". Error: ")[0]
        print(f"{program}: error: {reason}", file=sys.stderr)
        return 2
    stop = _StopOnSignal()
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
            # EventsExecutor.spin() (rclpy 7.1) busy-waits at 100 % CPU; spinning until a
            # future with a timeout does not, and serves many events per call (spin_once
            # costs Python overhead at every message of a 3 kHz stream).
            until = done if done is not None else Future()
            with stop.deferred():
                while not stop.received and rclpy.ok() and not until.done():
                    executor.spin_until_future_complete(until, timeout_sec=SPIN_TIMEOUT_S)
            if done is not None and done.done() and done.result() is not None:
                status = int(done.result())
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:
        # a publish failing as the context was shut down from outside is no failure
        if rclpy.ok():
            raise
    except EgovibError as exc:
        name = node.get_name() if node is not None else program
        # said once: "denoiser: error: denoiser: parameter ..." named the node twice
        print(f"{name}: error: {str(exc).removeprefix(f'{name}: ')}", file=sys.stderr)
        status = 2
    finally:
        if node is not None:
            close = getattr(node, "close", None)
            try:
                if close is not None:  # its exit status counts unless there is one already
                    extra = int(close() or 0)
                    status = status or extra
            except EgovibError as exc:
                print(f"{node.get_name()}: error: {exc}", file=sys.stderr)
                status = 2
            node.destroy_node()
        rclpy.try_shutdown()
        stop.restore()
    return status


class _StopOnSignal:
    """SIGINT and SIGTERM for a node process: outside `deferred()` (start-up, a node's own
    `run()`) they raise KeyboardInterrupt at once; inside (the spin loop) they are recorded
    in `received`, which the loop checks between spins, so no callback is interrupted. A
    second signal meanwhile raises at once (a callback that does not return)."""

    def __init__(self):
        self.received: list[int] = []
        self._deferring = False
        self._previous = {}
        if threading.current_thread() is threading.main_thread():
            for number in (signal.SIGINT, signal.SIGTERM):
                if signal.getsignal(number) is not signal.SIG_IGN:  # a background job's stays
                    self._previous[number] = signal.signal(number, self._on_signal)

    def _on_signal(self, number, frame) -> None:
        self.received.append(number)
        if not self._deferring or len(self.received) > 1:
            raise KeyboardInterrupt

    @contextlib.contextmanager
    def deferred(self):
        self._deferring = True
        try:
            yield
        finally:
            self._deferring = False

    def restore(self) -> None:
        for number, handler in self._previous.items():
            signal.signal(number, handler)
