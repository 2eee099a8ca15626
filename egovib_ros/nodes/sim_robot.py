"""sim_robot: any robot profile simulated live (sim.robot.CommandedRobot, the simulator of
`egovib simulate robot`), as a nodes.simulator.SimulatorNode (docs/live_nodes.md).

Each command is held, limited to the joints' ranges (beyond them: WARN) and reached
through a 50 ms first-order velocity controller.
"""

from __future__ import annotations

import numpy as np

from egovib_ros.errors import ConfigError
from egovib_ros.nodes.common import ROBOT_PARAM, Param, run_node
from egovib_ros.nodes.simulator import SimulatorNode, simulator_parameters
from egovib_ros.robot import RobotProfile, load_profile
from egovib_ros.sim.robot import (
    DEFAULT_JOINT_RATE_HZ,
    SENSOR_FRAME,
    TAP_DEAD_TIME_S,
    CommandedRobot,
)

PARAMETERS = (
    ROBOT_PARAM,
    Param(
        "joint_rate_hz",
        DEFAULT_JOINT_RATE_HZ,
        "joint-state rate (at most the sensor's: one joint state per sensor sample)",
        range=(0.1, 100_000.0),
    ),
    *simulator_parameters(
        frame_id=SENSOR_FRAME, truth="<parent of the sensor topic>/contact and /ego"
    ),
)


class SimRobot(SimulatorNode):
    WARN_COUNTERS = {
        **SimulatorNode.WARN_COUNTERS,
        "commands_limited": "{} commands beyond a joint's range (held at its limit)",
    }

    def __init__(self):
        self.commands_limited = 0
        self._taps_seen = 0
        super().__init__("sim_robot", PARAMETERS)

    def configure(self, params) -> RobotProfile:
        self.joint_rate_hz = params["joint_rate_hz"]
        if params["tap_rate_hz"] > 1.0 / TAP_DEAD_TIME_S:  # said here in the node's terms
            raise ConfigError(
                f"sim_robot: parameter 'tap_rate_hz': at most {1.0 / TAP_DEAD_TIME_S:.3g} taps "
                f"per second (taps are {TAP_DEAD_TIME_S:g} s apart at least), got "
                f"{params['tap_rate_hz']:g}"
            )
        return load_profile(params["robot"] or None)

    def make(self, start_ns: int) -> CommandedRobot:
        self._taps_seen = 0
        return CommandedRobot(
            self.profile,
            seed=self.seed,
            tap_rate_hz=self.tap_rate_hz,
            tap_mode=self.tap_mode,
            joint_rate_hz=self.joint_rate_hz,
            start_ns=start_ns,
        )

    def due(self, now_ns: int) -> int:
        return self.sim.samples_due(now_ns)

    def describe(self) -> str:
        p = self.profile
        joint_rate = p.rate_hz / max(1, round(p.rate_hz / self.joint_rate_hz))  # the simulator's
        return (
            f"simulating {p.name} from {p.source}: {p.sensor_field} on {p.sensor_topic} at "
            f"{p.rate_hz:g} Hz, joints {', '.join(p.joint_names)} on {p.joints_topic} at "
            f"{joint_rate:g} Hz; seed {self.seed}, taps {self.tap_rate_hz:g} Hz "
            f"({self.tap_mode}), ground truth {'on' if self.ground_truth else 'off'}"
        )

    def taps_in(self, chunk) -> int:
        seen, self._taps_seen = self._taps_seen, len(self.sim.tap_onsets_ns)
        return self._taps_seen - seen

    def command_note(self, requested: np.ndarray, within: bool) -> None:
        if not within:
            self.commands_limited += 1
            limits = ", ".join(
                f"{name} {low:g}..{high:g}"
                for name, low, high in zip(self.profile.joint_names, self.sim.low, self.sim.high)
            )
            self.get_logger().warning(
                f"command {[float(v) for v in requested]} beyond the joints' ranges ({limits}): "
                "held at the limits",
                throttle_duration_sec=5.0,
            )

    def extra_values(self) -> dict[str, object]:
        return {"commands_limited": self.commands_limited}


def main(args: list[str] | None = None) -> int:
    return run_node(SimRobot, args)


if __name__ == "__main__":
    raise SystemExit(main())
