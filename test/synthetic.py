"""Synthetic streams for core tests: known joint velocities and known noise per cell."""

from __future__ import annotations

import numpy as np

from egovib_ros.bag import Recording
from egovib_ros.sim.pr2 import JOINT_NAMES

FS = 3000.0
JOINT_FS = 1000.0
#: Two joints' cells the core tests stream through, with a noise level (std) each
CELLS = [(0.0, 0.0), (1.5, 0.0), (0.0, 0.02), (1.5, 0.02), (-3.0, -0.04), (0.9, -0.012)]
SIGMA = [0.2, 1.0, 0.6, 1.3, 2.0, 0.8]


def calibrated_model():
    """A model calibrated on 24 s over CELLS with the noise levels SIGMA."""
    from egovib_ros.core import calibrate_arrays

    data = stream(24, CELLS, sigma=SIGMA)
    model, _ = calibrate_arrays(data["t_acc"], data["accel"], data["t_joint"], data["velocity"])
    return model


def stamps(n: int, rate_hz: float, offset_ns: int = 0) -> np.ndarray:
    return (offset_ns + np.round(np.arange(n) * 1e9 / rate_hz)).astype(np.int64)


def stream(
    duration_s: float,
    cells: list[tuple[float, float]],
    *,
    sigma: list[float] | None = None,
    seed: int = 0,
    gravity: float = 9.81,
) -> dict:
    """Piecewise-constant joint velocities (one cell per equal segment), white noise whose
    std per segment is `sigma`, gravity on z. Joint and accelerometer clocks are offset."""
    rng = np.random.default_rng(seed)
    n = int(duration_s * FS)
    m = int(duration_s * JOINT_FS)
    t_acc = stamps(n, FS, offset_ns=1_234_567)
    t_joint = stamps(m, JOINT_FS, offset_ns=400_000)
    seg_acc = np.minimum((np.arange(n) * len(cells)) // n, len(cells) - 1)
    seg_joint = np.minimum((np.arange(m) * len(cells)) // m, len(cells) - 1)
    velocity = np.asarray(cells, dtype=float)[seg_joint]
    sig = np.ones(len(cells)) if sigma is None else np.asarray(sigma, dtype=float)
    accel = rng.normal(size=(n, 3)) * sig[seg_acc, None]
    accel[:, 2] += gravity
    return {
        "t_acc": t_acc,
        "accel": accel,
        "t_joint": t_joint,
        "velocity": velocity,
        "segment": seg_acc,
    }


def push_random_chunks(
    processor,
    data: dict,
    rng: np.random.Generator,
    max_chunk: int = 400,
    joint_lead_ns: int = 25_000_000,
):
    """Interleave joint-state and accelerometer chunks of random sizes in time order, joint
    states running `joint_lead_ns` ahead. Returns what the pushes returned."""
    t_acc, accel, t_joint, velocity = (
        data["t_acc"],
        data["accel"],
        data["t_joint"],
        data["velocity"],
    )
    out = []
    i = j = 0
    while i < len(t_acc):
        k = int(rng.integers(1, max_chunk))
        horizon = t_acc[min(i + k, len(t_acc)) - 1] + joint_lead_ns
        j_stop = int(np.searchsorted(t_joint, horizon, side="right"))
        if j_stop > j:
            out.append(processor.push_joint_states(t_joint[j:j_stop], velocity[j:j_stop]))
            j = j_stop
        out.append(processor.push_sensor(t_acc[i : i + k], accel[i : i + k]))
        i += k
    if j < len(t_joint):
        out.append(processor.push_joint_states(t_joint[j:], velocity[j:]))
    return out


# every array field of a Recording
RECORDING_FIELDS = (
    "sensor_stamps_ns",
    "sensor",
    "joint_stamps_ns",
    "joint_position",
    "joint_velocity",
    "contact",
    "ego",
    "denoised_stamps_ns",
    "denoised",
    "command_stamps_ns",
    "commands",
)


def random_recording(seed: int = 0, seconds: float = 0.5, with_truth: bool = True) -> Recording:
    """`seconds` of random PR2-hand streams (3 kHz sensor, 1 kHz joints), truth optional."""
    rng = np.random.default_rng(seed)
    n, m = int(3000 * seconds), int(1000 * seconds)
    t0 = 1_700_000_000 * 10**9 + 123
    accel_stamps = t0 + np.round(np.arange(n) * 1e9 / 3000).astype(np.int64)
    joint_stamps = t0 + 170_000 + np.arange(m, dtype=np.int64) * 1_000_000
    contact = rng.normal(size=(n, 3))
    ego = rng.normal(size=(n, 3))
    rec = Recording(
        sensor_stamps_ns=accel_stamps,
        sensor=contact + ego,
        joint_stamps_ns=joint_stamps,
        joint_position=rng.normal(size=(m, 2)),
        joint_velocity=rng.normal(size=(m, 2)),
        joint_names=JOINT_NAMES,
        command_stamps_ns=joint_stamps[::100],
        commands=rng.normal(size=(len(joint_stamps[::100]), 2)),
    )
    if with_truth:
        rec.contact, rec.ego = contact, ego
    return rec


def jittery_stamps(n: int, seed: int = 0) -> np.ndarray:
    """Jittery 1 kHz stamps like the quadcopter log's (0.9-1.25 ms steps around 1 ms)."""
    rng = np.random.default_rng(seed)
    steps = np.where(rng.random(n) < 0.1, rng.uniform(0.9, 1.25, n), 1.0) * 1e6
    return np.cumsum(steps).astype(np.int64)


# --- two motors at 1 kHz: the per-sample methods' core tests (test_core_methods, _adapt) ---
TWO_MOTOR_FS = 1000.0
#: (joint, c, p): a line at c x (1.03 x the reported speed)^p Hz (the real speed 3 % off)
TWO_MOTOR_LINES = ((0, 210.0, 1.0), (0, 420.0, 1.0), (1, 160.0, 0.8), (1, 240.0, 0.8))


def two_motor_profile(name: str):
    """A gyro at 1 kHz on two one-directional motors (top speed 1), band 60-450 Hz."""
    from egovib_ros.robot import RobotProfile

    return RobotProfile(
        name=name,
        sensor_topic="/imu/data_raw",
        sensor_field="angular_velocity",
        rate_hz=TWO_MOTOR_FS,
        denoised_topic="/imu/denoised",
        joints_topic="/joint_states",
        joint_names=("m1", "m2"),
        max_speed=(1.0, 1.0),
        bidirectional=(False, False),
        steps=10,
        sensor_range=100.0,
        block_length=32,
        hop=16,
        band_hz=(60.0, 450.0),
        band_order=4,
    )


def two_motor_recording(speed, steps, rng, *, mixing, gain=1.0, taps_per_s=0.0, tap_peak=2.0):
    """Arrays of the two motors at `speed` (n, 2), sample steps `steps` (n,) in ms: gravity,
    their lines (mixed onto the axes by `mixing` (4, 3)) and broadband growing with speed,
    all times `gain` (n,); taps (40 ms bursts, 120-380 Hz, one axis) every 1 / taps_per_s s;
    joint states at 500 Hz, 0.3 ms late."""
    fs, n = TWO_MOTOR_FS, len(speed)
    t = (10**9 + np.round(np.cumsum(steps) * 1e6)).astype(np.int64)
    accel = np.zeros((n, 3))
    accel[:, 2] = 9.81
    for k, (j, c, p) in enumerate(TWO_MOTOR_LINES):
        phase = 2 * np.pi * np.cumsum(c * (1.03 * speed[:, j]) ** p * steps) / fs
        accel += (0.6 * gain * speed[:, j] * np.sin(phase + k))[:, None] * mixing[k][None, :]
    accel += (gain * (0.02 + 0.05 * speed.mean(axis=1)))[:, None] * rng.normal(size=(n, 3))
    contact = np.zeros((n, 3))
    onsets = np.zeros(0, dtype=np.int64)
    if taps_per_s:
        gap = int(fs / taps_per_s)
        onsets = np.arange(gap // 2, n - int(0.2 * fs), gap)
        k = np.arange(int(0.04 * fs)) / fs
        for o in onsets:
            burst = np.exp(-k / 0.008) * np.sin(2 * np.pi * rng.uniform(120, 380) * k)
            contact[o : o + len(k), rng.integers(0, 3)] += tap_peak * burst
    pick = np.arange(0, n, 2)
    return {
        "t": t,
        "accel": accel + contact,
        "tj": t[pick] + 300_000,
        "velocity": speed[pick],
        "contact": contact,
        "onsets": onsets,
    }


def decaying_tap(n, peak, freq=400.0, tau=0.01):
    """A tap: a decaying 400 Hz sine at FS."""
    t = np.arange(n) / FS
    return peak * np.exp(-t / tau) * np.sin(2 * np.pi * freq * t + np.pi / 2)


def tap_signals(n=3 * 3000, onsets=(3000, 4500, 6000), tap_len=150, peak=4.0, noise=0.25, seed=1):
    """(reference with taps at known onsets, sign noise of magnitude `noise`)."""
    rng = np.random.default_rng(seed)
    reference = np.zeros(n)
    for onset in onsets:
        reference[onset : onset + tap_len] = decaying_tap(tap_len, peak)
    return reference, noise * rng.choice([-1.0, 1.0], size=n)
