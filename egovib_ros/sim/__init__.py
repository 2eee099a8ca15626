"""Simulated PR2 right hand (wrist roll + gripper) with accelerometer: numpy/scipy only.

SimParams.load(path=None)                 config/sim.yaml
parse_effects("position=0.5,timing=0.03")
HandSimulator(params, effects=..., seed=..., tap_rate_hz=0.0, tap_mode="random")
    .set_command(v) ; .step(n, commands=None) -> SimChunk
simulate_sweep(...), simulate_motion(...) -> (Recording, truth dict)
"""

from egovib_ros.sim.hand import HandSimulator, SimChunk
from egovib_ros.sim.params import SimParams, format_effects, parse_effects
from egovib_ros.sim.scenarios import (
    concat_recordings,
    motion_commands,
    motion_slices,
    simulate_motion,
    simulate_sweep,
    sweep_cells,
    sweep_slices,
)

__all__ = [
    "HandSimulator",
    "SimChunk",
    "SimParams",
    "format_effects",
    "parse_effects",
    "concat_recordings",
    "motion_commands",
    "motion_slices",
    "simulate_motion",
    "simulate_sweep",
    "sweep_cells",
    "sweep_slices",
]
