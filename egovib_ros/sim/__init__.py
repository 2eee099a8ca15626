"""The simulated PR2 right hand (hand.py, scenarios.py: sweeps and motion runs) and any
robot profile (robot.py); numpy/scipy only."""

from egovib_ros.sim.hand import HandSimulator
from egovib_ros.sim.params import SimParams, format_effects, parse_effects
from egovib_ros.sim.scenarios import motion_commands, simulate_motion, simulate_sweep, sweep_cells

__all__ = [
    "HandSimulator",
    "SimParams",
    "format_effects",
    "parse_effects",
    "motion_commands",
    "simulate_motion",
    "simulate_sweep",
    "sweep_cells",
]
