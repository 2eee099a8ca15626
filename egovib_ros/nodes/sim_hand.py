"""sim_hand: the simulated PR2 right hand (egovib_ros.sim.HandSimulator) as a ROS 2 node,
a nodes.simulator.SimulatorNode (docs/live_nodes.md): `joint_states` (1 kHz),
`accelerometer/raw` (3 kHz, one Imu per sample) and the ground truth
`accelerometer/contact` and `accelerometer/ego`.
"""

from __future__ import annotations

from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.nodes.common import Param, run_node
from egovib_ros.nodes.simulator import SimulatorNode, simulator_parameters
from egovib_ros.robot import RobotProfile, load_profile
from egovib_ros.sim import HandSimulator, SimParams, format_effects, parse_effects
from egovib_ros.sim.params import default_config_path
from egovib_ros.sim.pr2 import ACCEL_FRAME, ACCEL_RATE_HZ

PARAMETERS = (
    Param("effects", "none", "effects SPEC 'name=strength,...' (INTERFACES.md section 5), or none"),
    Param("sim_params", "", "simulator parameter YAML; empty = config/sim.yaml of the package"),
    *simulator_parameters(
        frame_id=ACCEL_FRAME, truth="accelerometer/contact and accelerometer/ego"
    ),
)


class SimHand(SimulatorNode):
    """Steps the simulator from a timer; the simulator starts at the first non-zero clock time."""

    RATE_KEY = "accel_rate_hz"

    def __init__(self):
        super().__init__("sim_hand", PARAMETERS)

    def configure(self, params) -> RobotProfile:
        self.effects = parse_effects(params["effects"])
        self.params_file = params["sim_params"] or str(default_config_path())
        self.params = SimParams.load(self.params_file)
        return load_profile()  # the simulated robot: joint names and topics

    def make(self, start_ns: int) -> HandSimulator:
        return HandSimulator(
            self.params,
            effects=self.effects,
            seed=self.seed,
            tap_rate_hz=self.tap_rate_hz,
            tap_mode=self.tap_mode,
            start_ns=start_ns,
        )

    def due(self, now_ns: int) -> int:
        """Samples on the exact 3 kHz grid from the start up to now, not yet made."""
        due = (now_ns - self.sim.start_ns) * int(ACCEL_RATE_HZ) // NS_PER_S + 1
        return due - self.sim.index

    def describe(self) -> str:
        return (
            f"simulating seed {self.seed}, effects {format_effects(self.effects)}, taps "
            f"{self.tap_rate_hz:g} Hz ({self.tap_mode}), "
            f"ground truth {'on' if self.ground_truth else 'off'}, "
            f"simulator parameters from {self.params_file}"
        )


def main(args: list[str] | None = None) -> int:
    return run_node(SimHand, args)


if __name__ == "__main__":
    raise SystemExit(main())
