"""Joint motion of the alternate-reality hand: planned references and a servo.

Two styles:

* "smooth" (default; random exploratory motion like the paper's section 4): the wrist
  velocity is a cubic spline through random values at random intervals (0.25-1.2 s), with
  occasional pauses; the gripper makes open/close strokes between random gap targets whose
  speed varies continuously along each stroke, with random dwells at the ends.
* "segments" (task-like): the wrist holds one random speed per segment (0.6-3.2 s) and
  moves between them through quintic blends; the gripper strokes at one speed each.
  Speeds are then visited at a few discrete values only.

Both references go through a second-order servo (natural frequency SERVO_HZ, damping
SERVO_ZETA) that the robot actually follows.
"""

from __future__ import annotations

import numpy as np
from scipy import interpolate, signal

#: Speed limits of this hand's drives (rad/s, m/s): the PR2 hand's published limits.
WRIST_LIMIT = 3.0
GRIPPER_LIMIT = 0.04
#: Gripper travel (m) of this hand's fingers.
GAP_MIN, GAP_MAX = 0.0, 0.088
SERVO_HZ = 7.0
SERVO_ZETA = 0.8


def smoothstep5(x: np.ndarray) -> np.ndarray:
    """Quintic blend 0 -> 1 with zero slope and curvature at both ends."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (10.0 + x * (-15.0 + 6.0 * x))


def _blend_segments(
    t: np.ndarray, starts: np.ndarray, levels: np.ndarray, blends: np.ndarray
) -> np.ndarray:
    """Piecewise-constant levels entered through quintic blends starting at `starts`."""
    out = np.full(len(t), levels[0])
    bounds = np.append(np.searchsorted(t, starts), len(t))
    for k in range(1, len(starts)):
        i0, i1 = bounds[k], bounds[k + 1]
        if i0 >= len(t):
            break
        ramp = smoothstep5((t[i0:i1] - starts[k]) / blends[k])
        out[i0:i1] = levels[k - 1] + (levels[k] - levels[k - 1]) * ramp
    return out


def wrist_reference(t: np.ndarray, rng: np.random.Generator, top_speed: float) -> np.ndarray:
    """Wrist velocity reference (rad/s): holds, slow and fast turns, occasional reversals."""
    starts, levels, blends = [0.0], [0.0], [0.2]
    now, sign = 0.0, 1.0
    while now < t[-1] + 1.0:
        now += rng.uniform(0.6, 3.2)
        if rng.random() < 0.12:
            level = 0.0
        else:
            if rng.random() < 0.35:
                sign = -sign
            level = sign * rng.uniform(0.06, 1.0) * top_speed * WRIST_LIMIT
        starts.append(now)
        levels.append(level)
        blends.append(rng.uniform(0.12, 0.5))
    return _blend_segments(t, np.array(starts), np.array(levels), np.array(blends))


def wrist_reference_smooth(t: np.ndarray, rng: np.random.Generator, top_speed: float) -> np.ndarray:
    """Wrist velocity reference (rad/s): cubic spline through random values, occasional pauses."""
    times, values = [-1.0], [0.0]
    now = 0.0
    while now < t[-1] + 2.0:
        times.append(now)
        if rng.random() < 0.08:
            values.append(0.0)
        else:
            values.append(float(np.clip(rng.normal(0.0, 0.5), -1.0, 1.0)) * top_speed * WRIST_LIMIT)
        now += rng.uniform(0.25, 1.2)
    ref = interpolate.CubicSpline(times, values, bc_type="clamped")(t)
    return np.clip(ref, -top_speed * WRIST_LIMIT, top_speed * WRIST_LIMIT)


def gripper_reference(
    t: np.ndarray, rng: np.random.Generator, top_speed: float, gap0: float, *, vary: bool = False
) -> np.ndarray:
    """Gripper gap velocity reference (m/s): strokes between random gap targets,
    dwells at the ends."""
    dt = t[1] - t[0]
    v = np.zeros(len(t))
    gap, i = gap0, 0
    lo, hi = GAP_MIN + 0.003, GAP_MAX - 0.003
    while i < len(t):
        target = rng.uniform(lo, hi)
        if abs(target - gap) < 0.008:
            target = lo if gap > 0.5 * (lo + hi) else hi
        dist = abs(target - gap)
        direction = np.sign(target - gap)
        speed = rng.uniform(0.1, 1.0) * top_speed * GRIPPER_LIMIT
        ramp = rng.uniform(0.06, 0.25)
        if speed * ramp > dist:  # short stroke: slower, shorter ramps
            ramp = min(ramp, 0.5 * dist / speed)
            speed = min(speed, dist / ramp) if ramp > 0 else speed
        cruise = max(dist - speed * ramp, 0.0) / speed
        n_ramp = max(int(round(ramp / dt)), 1)
        n_cruise = int(round(cruise / dt))
        up = smoothstep5(np.arange(n_ramp) / n_ramp)
        shape = np.ones(n_cruise)
        if vary and n_cruise > 1:
            # speed wanders along the stroke (a sum of two slow random sinusoids, +-45 %)
            u = np.arange(n_cruise) * dt
            for period in (rng.uniform(0.3, 0.8), rng.uniform(0.8, 2.0)):
                shape += rng.uniform(0.1, 0.25) * np.sin(
                    2 * np.pi * u / period + rng.uniform(0, 2 * np.pi)
                )
            shape = np.clip(shape, 0.3, 1.0 / max(top_speed, 1e-9))
        profile = np.concatenate([up, shape, up[::-1]]) * speed * direction
        # rescale so the stroke travels exactly `dist`
        travelled = abs(profile.sum() * dt)
        if travelled > 0:
            profile *= dist / travelled
        j = min(i + len(profile), len(t))
        v[i:j] = profile[: j - i]
        gap += direction * dist
        i = j + int(round(rng.choice([0.0, rng.uniform(0.05, 1.2)], p=[0.3, 0.7]) / dt))
    return v


def servo(reference: np.ndarray, fs: float) -> np.ndarray:
    """The joint's velocity following its reference through a second-order servo."""
    wn = 2 * np.pi * SERVO_HZ
    b, a = signal.bilinear([wn * wn], [1.0, 2 * SERVO_ZETA * wn, wn * wn], fs=fs)
    return signal.lfilter(b, a, reference)


MOTION_STYLES = ("smooth", "segments")


def plan_motion(
    duration_s: float,
    fs: float,
    rng: np.random.Generator,
    *,
    top_speed: float = 0.85,
    gap0: float = 0.045,
    style: str = "smooth",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True joint velocity, position and acceleration (n, 2) at the sensor rate."""
    if style not in MOTION_STYLES:
        raise ValueError(f"motion style must be one of {MOTION_STYLES}, not {style!r}")
    n = int(round(duration_s * fs))
    t = np.arange(n) / fs
    wrist = (
        wrist_reference_smooth(t, rng, top_speed)
        if style == "smooth"
        else wrist_reference(t, rng, top_speed)
    )
    v = np.column_stack(
        [
            servo(wrist, fs),
            servo(gripper_reference(t, rng, top_speed, gap0, vary=style == "smooth"), fs),
        ]
    )
    pos = np.cumsum(v, axis=0) / fs
    pos[:, 1] = np.clip(pos[:, 1] + gap0, GAP_MIN, GAP_MAX)
    pos[:, 0] += rng.uniform(-np.pi, np.pi)
    acc = np.gradient(v, 1.0 / fs, axis=0)
    return v, pos, acc


def reversal_events(
    velocity: np.ndarray, fs: float, threshold: float
) -> tuple[np.ndarray, np.ndarray]:
    """Sample indices where a joint starts moving opposite to its last direction,
    and the |accel| there.

    A direction is "moving" once |v| exceeds `threshold`; a reversal is the first
    sample of motion in the direction opposite to the previous motion (after a
    turnaround or after a stop).
    """
    moving = np.where(velocity > threshold, 1, np.where(velocity < -threshold, -1, 0))
    idx = np.flatnonzero(moving)
    if len(idx) < 2:
        return np.zeros(0, np.int64), np.zeros(0)
    flips = idx[1:][np.diff(moving[idx]) != 0]
    acc = np.abs(np.gradient(velocity, 1.0 / fs))
    return flips.astype(np.int64), acc[flips]
