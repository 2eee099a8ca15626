"""Simulated PR2 right hand (wrist roll + gripper) with accelerometer: numpy/scipy only.

    SimParams.load(path=None)                 config/sim.yaml
    parse_effects("position=0.5,timing=0.03")
    HandSimulator(params, effects=..., seed=..., tap_rate_hz=0.0, tap_mode="random")
        .set_command(v) ; .step(n, commands=None) -> SimChunk
    simulate_sweep(...), simulate_motion(...) -> (Recording, truth dict)
"""
from egovib_ros.sim.params import SimParams, format_effects, parse_effects  # noqa: F401
from egovib_ros.sim.hand import HandSimulator, SimChunk  # noqa: F401
from egovib_ros.sim.scenarios import (concat_recordings, motion_commands, motion_slices,  # noqa: F401
                                      simulate_motion, simulate_sweep, sweep_cells, sweep_slices)
