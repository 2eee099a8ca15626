"""Robot and interface constants of the PR2 hand fixed by docs/INTERFACES.md.

Pure Python/numpy: imported by the core, the simulator, the nodes and the CLI.
"""

from __future__ import annotations

import numpy as np

# --- robot (INTERFACES.md section 1) -------------------------------------------
JOINT_NAMES: tuple[str, ...] = ("r_wrist_roll_joint", "r_gripper_joint")
MAX_SPEED: tuple[float, ...] = (3.0, 0.04)  # rad/s, m/s
GRIPPER_GAP_RANGE_M: tuple[float, float] = (0.0, 0.086)
ACCEL_RATE_HZ: float = 3000.0
JOINT_RATE_HZ: float = 1000.0
ACCEL_RANGE_MS2: float = 78.5  # +/- 8 g
ACCEL_BITS: int = 10
ACCEL_FRAME: str = "r_gripper_motor_accelerometer_link"

# Velocity grid: -100 % .. +100 % of max speed in 10 % steps (21 x 21 = 441 cells).
GRID_FRACTIONS: np.ndarray = np.round(np.arange(-10, 11) / 10.0, 10)


def grid_values(joint: int) -> np.ndarray:
    """Grid velocities of one joint in its own unit (rad/s or m/s)."""
    return GRID_FRACTIONS * MAX_SPEED[joint]


# --- paper's algorithm defaults (sections 2-3) -----------------------------
BLOCK_LENGTH: int = 64
HOP: int = 32
BAND_HZ: tuple[float, float] = (150.0, 750.0)
BAND_ORDER: int = 4  # 4th-order Butterworth band-pass

EFFECT_NAMES: tuple[str, ...] = ("position", "coupling", "acceleration", "timing", "drift")
