"""Joint motion of the third hand: trapezoidal velocity segments with pauses.

Each joint, independently, holds a speed drawn uniformly (either sign, up to `max_speed` of
its top speed) for 0.3-1.6 s, ramps to the next at an acceleration drawn per ramp, and now
and then pauses (speed 0 for 0.2-1.0 s). The gripper's gap is kept inside its travel: a
segment that would cross an end is turned around there (with its own ramp). The motion is
made on the sensor's sample grid; the joint states are sampled from it (hand.py).
"""

from __future__ import annotations

import numpy as np

#: Top speeds (rad/s, m/s) and the gripper's travel (m): CONTRACT section 1.
TOP_SPEED = np.array([3.0, 0.04])
GRIPPER_TRAVEL = (0.0, 0.086)
#: Held segments and pauses (s); share of segments that are pauses.
HOLD_S = (0.3, 1.6)
PAUSE_S = (0.2, 1.0)
PAUSE_SHARE = 0.15
#: Ramp accelerations, in top speeds per second.
RAMP_PER_S = (1.5, 8.0)
#: The gripper turns around this far (m) from either end of its travel.
END_MARGIN = 0.004


def _targets(rng: np.random.Generator, n: int, fs: float, max_speed: float) -> np.ndarray:
    """Piecewise-constant target speed fractions (n,), segments of random length."""
    out = np.zeros(n)
    i = 0
    while i < n:
        pause = rng.random() < PAUSE_SHARE
        length = int(fs * rng.uniform(*(PAUSE_S if pause else HOLD_S)))
        out[i : i + length] = 0.0 if pause else rng.uniform(-max_speed, max_speed)
        i += max(length, 1)
    return out


def _ramped(target: np.ndarray, rng: np.random.Generator, fs: float) -> np.ndarray:
    """The target followed with a bounded slope (a trapezoid per change), slope drawn per
    change of target."""
    out = np.empty_like(target)
    v = 0.0
    slope = rng.uniform(*RAMP_PER_S) / fs
    last = target[0]
    for k, want in enumerate(target):
        if want != last:
            slope = rng.uniform(*RAMP_PER_S) / fs
            last = want
        v += float(np.clip(want - v, -slope, slope))
        out[k] = v
    return out


def trajectories(
    duration_s: float, fs: float, rng: np.random.Generator, max_speed: float = 0.8
) -> tuple[np.ndarray, np.ndarray]:
    """(velocity (n, 2), position (n, 2)) on the sensor grid: wrist rad/s and rad, gripper m/s
    and m (gap). Positions integrate the velocities; the gripper turns around at its ends."""
    n = int(round(duration_s * fs))
    frac = np.stack([_ramped(_targets(rng, n, fs, max_speed), rng, fs) for _ in range(2)], 1)
    vel = frac * TOP_SPEED
    pos = np.zeros((n, 2))
    pos[:, 0] = rng.uniform(-np.pi, np.pi) + np.cumsum(vel[:, 0]) / fs
    gap = rng.uniform(0.02, 0.066)
    lo, hi = GRIPPER_TRAVEL[0] + END_MARGIN, GRIPPER_TRAVEL[1] - END_MARGIN
    flip = 1.0
    for k in range(n):
        v = flip * vel[k, 1]
        if (gap >= hi and v > 0) or (gap <= lo and v < 0):
            flip = -flip
            v = -v
        vel[k, 1] = v
        gap += v / fs
        pos[k, 1] = gap
    return vel, pos
