"""sim_hand: the simulated PR2 right hand (egovib_ros.sim.HandSimulator) as a ROS 2 node.

Subscribes `hand_velocity_controller/commands` and publishes, in real time on the
node clock (so `use_sim_time` works), `joint_states` (1 kHz), `accelerometer/raw`
(3 kHz, one Imu per sample) and the ground truth `accelerometer/contact` and
`accelerometer/ego`. Every `publish_period` the samples due since the last tick are
generated and sent as pre-serialised CDR, which keeps the CPU cost of 3 kHz low.
"""

from __future__ import annotations

import numpy as np
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState
from std_msgs.msg import Float64MultiArray

from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import StreamError
from egovib_ros.nodes.common import (
    Health,
    Param,
    SubscriberGate,
    declare_parameters,
    run_node,
    stream_publisher,
)
from egovib_ros.nodes.convert import command_velocity, encode_imu_batch, encode_joint_state_batch
from egovib_ros.robot import load_profile
from egovib_ros.sim import HandSimulator, SimParams, format_effects, parse_effects
from egovib_ros.sim.params import default_config_path
from egovib_ros.sim.pr2 import (
    ACCEL_FRAME,
    ACCEL_RATE_HZ,
    TOPIC_COMMANDS,
    TOPIC_CONTACT,
    TOPIC_EGO,
)

PR2 = load_profile()  # the simulated robot: joint names and topics
PARAMETERS = (
    Param("seed", 0, "random seed of the simulator", range=(0, 2**31 - 1)),
    Param("tap_rate_hz", 0.0, "mean rate of simulated taps (0 = none)", range=(0.0, 100.0)),
    Param(
        "tap_mode",
        "random",
        "tap onsets: random (Poisson) | periodic",
        choices=("random", "periodic"),
    ),
    Param("effects", "none", "effects SPEC 'name=strength,...' (INTERFACES.md section 5), or none"),
    Param("sim_params", "", "simulator parameter YAML; empty = config/sim.yaml of the package"),
    Param(
        "publish_period", 0.01, "seconds between publishing batches of samples", range=(0.0005, 1.0)
    ),
    Param("publish_ground_truth", True, "publish accelerometer/contact and accelerometer/ego"),
    Param("publish_ego", True, "with publish_ground_truth: also publish accelerometer/ego"),
    Param("frame_id", ACCEL_FRAME, "frame_id of the Imu messages"),
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


class SimHand(Node):
    """Steps the simulator from a timer; the simulator starts at the first non-zero clock time."""

    def __init__(self):
        super().__init__("sim_hand")
        params = declare_parameters(self, PARAMETERS)
        seed, tap_rate_hz, tap_mode = params["seed"], params["tap_rate_hz"], params["tap_mode"]
        self.period_s = params["publish_period"]
        self.ground_truth = params["publish_ground_truth"]
        publish_ego = params["publish_ego"]
        self.frame_id = params["frame_id"]
        self.max_batch_s = params["max_batch"]
        self.wait_for_subscribers = params["wait_for_subscribers"]
        self.wait_timeout_s = params["wait_timeout"]
        self.effects = parse_effects(params["effects"])
        self.params_file = params["sim_params"] or str(default_config_path())
        self.params = SimParams.load(self.params_file)
        self.seed, self.tap_rate_hz, self.tap_mode = int(seed), tap_rate_hz, tap_mode
        self.sim: HandSimulator | None = None
        HandSimulator(
            self.params,
            effects=self.effects,
            seed=self.seed,
            tap_rate_hz=tap_rate_hz,
            tap_mode=tap_mode,
        )  # validate the settings now, not at the first tick

        self.pub_joint = stream_publisher(self, JointState, PR2.node_joints_topic)
        self.pub_raw = stream_publisher(self, Imu, PR2.node_sensor_topic)
        self.pub_contact = stream_publisher(self, Imu, TOPIC_CONTACT) if self.ground_truth else None
        self.pub_ego = (
            stream_publisher(self, Imu, TOPIC_EGO) if self.ground_truth and publish_ego else None
        )
        self.gate = SubscriberGate(
            [self.pub_joint, self.pub_raw, self.pub_contact, self.pub_ego],
            self.wait_for_subscribers,
            self.wait_timeout_s,
        )
        self.health = Health(self, hardware_id=PR2.name)
        self.create_subscription(Float64MultiArray, TOPIC_COMMANDS, self._on_command, 10)
        self.commands_received = 0
        self.commands_rejected = 0
        self.samples_published = 0
        self.taps = 0
        self.max_lag_samples = 0
        self._last_diag = (0, 0)
        self.create_timer(self.period_s, self._tick)
        self.create_timer(1.0, self._publish_diagnostics)
        self.get_logger().info(
            f"simulating seed {self.seed}, effects {format_effects(self.effects)}, taps "
            f"{tap_rate_hz:g} Hz ({tap_mode}), "
            f"ground truth {'on' if self.ground_truth else 'off'}, "
            f"simulator parameters from {self.params_file}"
        )

    def _on_command(self, msg: Float64MultiArray) -> None:
        try:
            velocity = command_velocity(msg, PR2.n_joints, topic=TOPIC_COMMANDS)
        except StreamError as exc:
            self.commands_rejected += 1
            self.get_logger().warning(str(exc), throttle_duration_sec=5.0)
            return
        self.commands_received += 1
        if self.sim is None:
            self._pending_command = velocity
        else:
            self.sim.set_command(velocity)

    def _tick(self) -> None:
        now_ns = self.get_clock().now().nanoseconds
        if now_ns <= 0:  # use_sim_time and no /clock yet
            return
        if self.sim is None:
            if not self._subscribers_ready():
                return
            self.sim = HandSimulator(
                self.params,
                effects=self.effects,
                seed=self.seed,
                tap_rate_hz=self.tap_rate_hz,
                tap_mode=self.tap_mode,
                start_ns=now_ns,
            )
            pending = getattr(self, "_pending_command", None)
            if pending is not None:
                self.sim.set_command(pending)
            self.get_logger().info(f"simulation started at stamp {now_ns} ns")
        due = (now_ns - self.sim.start_ns) * int(ACCEL_RATE_HZ) // NS_PER_S + 1
        lag = due - self.sim.index
        if lag <= 0:
            return
        self.max_lag_samples = max(self.max_lag_samples, lag)
        n = min(lag, max(1, int(self.max_batch_s * ACCEL_RATE_HZ)))
        chunk = self.sim.step(n)
        self.taps += len(chunk.tap_onsets_ns)
        if len(chunk.joint_stamps_ns):  # a short step may hold no 1 kHz sample
            for data in encode_joint_state_batch(
                chunk.joint_stamps_ns, chunk.joint_position, chunk.joint_velocity, PR2.joint_names
            ):
                self.pub_joint.publish(data)
        for data in encode_imu_batch(chunk.sensor_stamps_ns, chunk.sensor, self.frame_id):
            self.pub_raw.publish(data)
        if self.pub_contact is not None:
            for data in encode_imu_batch(chunk.sensor_stamps_ns, chunk.contact, self.frame_id):
                self.pub_contact.publish(data)
        if self.pub_ego is not None:
            for data in encode_imu_batch(chunk.sensor_stamps_ns, chunk.ego, self.frame_id):
                self.pub_ego.publish(data)
        self.samples_published += n

    def _subscribers_ready(self) -> bool:
        """All streams matched (or waited long enough): recordings then start complete."""
        if self.gate.is_open():
            if self.gate.timed_out:
                self.get_logger().warning("not every stream has its subscribers: starting anyway")
            return True
        return False

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
        velocity = self.sim.velocity
        values = {
            "accel_rate_hz": rate,
            "samples_published": self.samples_published,
            "max_lag_samples": self.max_lag_samples,
            "taps": self.taps,
            "commands_received": self.commands_received,
            "commands_rejected": self.commands_rejected,
            "command": list(np.round(self.sim.command, 6)),
            "velocity": list(np.round(velocity, 6)),
        }
        rejected = self.health.changes({"commands_rejected": self.commands_rejected})[
            "commands_rejected"
        ]
        self.health.publish(
            warnings=[f"{rejected} commands rejected"] if rejected else [],
            ok="simulating",
            values=values,
        )
        self.max_lag_samples = 0


def main(args: list[str] | None = None) -> int:
    return run_node(SimHand, args)


if __name__ == "__main__":
    raise SystemExit(main())
