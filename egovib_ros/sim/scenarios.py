"""Scenarios of the paper's section 3-4: velocity-grid sweeps and random smooth motion.

Both drive the same HandSimulator the ROS node `sim_hand` uses, with a
command schedule instead of a topic, so live and offline data agree.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable, Iterator

import numpy as np
from scipy import signal

from egovib_ros.bag import Recording, concat_recordings
from egovib_ros.core.noise_model import sweep_cells as grid_sweep_cells
from egovib_ros.errors import ConfigError
from egovib_ros.sim.hand import HandSimulator, SimChunk
from egovib_ros.sim.params import SimParams
from egovib_ros.sim.pr2 import ACCEL_RATE_HZ, GRID_FRACTIONS, JOINT_NAMES, MAX_SPEED

CHUNK = 3000  # samples per simulator step in offline runs (1 s)
COMMAND_RATE_HZ = 50.0  # motion: commands sent at this rate ...
MOTION_CUTOFF_HZ = 0.4  # ... low-passed white noise


def sweep_cells(grid: str) -> np.ndarray:
    """The hand's velocity cells (C, 2) in sweep order (core.noise_model.sweep_cells on its
    21 x 21 grid): 'full' = 441 cells, 'superposition' = the 41 with <= 1 joint moving."""
    axes = (GRID_FRACTIONS * MAX_SPEED[0], GRID_FRACTIONS * MAX_SPEED[1])
    index = grid_sweep_cells(axes, grid)
    return np.column_stack([axes[j][index[:, j]] for j in range(2)])


def _with_commands(chunk: SimChunk, stamps, commands) -> SimChunk:
    """A step's chunk (a Recording slice) with the commands sent during it."""
    return replace(
        chunk,
        command_stamps_ns=np.asarray(stamps, np.int64).reshape(-1),
        commands=np.asarray(commands, float).reshape(-1, len(JOINT_NAMES)),
    )


def _truth(seed: int, effects: dict) -> dict:
    """The `--truth` sidecar of INTERFACES.md section 3 (its tap onsets filled as it runs)."""
    return {
        "seed": int(seed),
        "effects": {k: float(v) for k, v in effects.items()},
        "tap_onsets_ns": [],
    }


def iter_sweep(
    sim: HandSimulator, cells: np.ndarray, *, dwell_s: float, settle_s: float
) -> Iterator[tuple[int, np.ndarray, int, SimChunk]]:
    """Yield (cell index, cell velocity, command stamp, chunk) while sweeping the cells."""
    if dwell_s <= 0 or settle_s < 0:
        raise ConfigError("sweep: dwell must be > 0 and settle >= 0 seconds")
    per_cell = int(round((dwell_s + settle_s) * ACCEL_RATE_HZ))
    for ci, cell in enumerate(cells):
        sim.set_command(cell)
        stamp = int(sim.stamps_ns(np.array([sim.index]))[0])
        left = per_cell
        while left > 0:
            n = min(CHUNK, left)
            yield ci, cell, stamp, sim.step(n)
            left -= n


def sweep_slices(
    *,
    grid: str = "superposition",
    dwell_s: float = 15.0,
    settle_s: float = 1.0,
    effects: dict | None = None,
    seed: int = 0,
    params: SimParams | None = None,
    tap_rate_hz: float = 0.0,
    tap_mode: str = "random",
    progress: Callable[[float], None] | None = None,
) -> tuple[Iterator[Recording], dict]:
    """Streaming form of simulate_sweep: (iterator of 1-s Recording slices, truth dict
    filled as it runs)."""
    params = params if params is not None else SimParams.load()
    sim = HandSimulator(
        params, effects=effects, seed=seed, tap_rate_hz=tap_rate_hz, tap_mode=tap_mode
    )
    cells = sweep_cells(grid)
    if dwell_s <= 0 or settle_s < 0:
        raise ConfigError("sweep: dwell must be > 0 and settle >= 0 seconds")
    truth = _truth(seed, sim.effects)

    def generate() -> Iterator[Recording]:
        last_cell = -1
        for ci, cell, stamp, chunk in iter_sweep(sim, cells, dwell_s=dwell_s, settle_s=settle_s):
            new_cell = ci != last_cell
            last_cell = ci
            truth["tap_onsets_ns"].extend(int(x) for x in chunk.tap_onsets_ns)
            if progress is not None:
                progress(len(chunk.sensor) / ACCEL_RATE_HZ)
            yield _with_commands(chunk, [stamp] if new_cell else [], [cell] if new_cell else [])

    return generate(), truth


def simulate_sweep(**options) -> tuple[Recording, dict]:
    """Sweep the velocity grid (sweep_slices' options): each cell is commanded for
    settle_s + dwell_s seconds. The gripper reverses at its gap limits (speed kept, sign
    flipped), so a cell's blocks are split between +v and -v and the blocks around a
    reversal are unsteady; calibration bins blocks by measured velocity anyway.
    Returns the whole Recording (with ground truth) and the truth dict."""
    slices, truth = sweep_slices(**options)
    return concat_recordings(list(slices)), truth


def motion_commands(
    duration_s: float, max_speed: float, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Random smooth velocity commands, (times_s (P,), commands (P, 2)) at COMMAND_RATE_HZ:
    low-pass filtered white noise, within +/- max_speed * vmax."""
    rate_hz, cutoff_hz = COMMAND_RATE_HZ, MOTION_CUTOFF_HZ
    if not 0.0 <= max_speed <= 1.0:
        raise ConfigError(f"--max-speed must be a fraction in [0, 1], not {max_speed}")
    n = max(1, int(np.ceil(duration_s * rate_hz)))
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x6D6F74]))  # own stream: "mot"
    warm = int(5 * rate_hz / cutoff_hz)  # let the filter settle before t = 0
    sos = signal.butter(2, cutoff_hz, fs=rate_hz, output="sos")
    noise = rng.standard_normal((n + warm, len(MAX_SPEED)))
    smooth = signal.sosfilt(sos, noise, axis=0)[warm:]
    # ~unit rms for a 2nd-order low-pass
    smooth /= np.sqrt(cutoff_hz / rate_hz * np.pi / 2) / np.sqrt(2)
    frac = np.clip(smooth / 2.0, -1.0, 1.0)  # ~2 sigma reaches the limit
    return np.arange(n) / rate_hz, frac * max_speed * np.asarray(MAX_SPEED)


def motion_slices(
    *,
    duration_s: float,
    max_speed: float = 0.5,
    tap_rate_hz: float = 0.0,
    effects: dict | None = None,
    seed: int = 0,
    params: SimParams | None = None,
    tap_mode: str = "random",
    progress: Callable[[float], None] | None = None,
) -> tuple[Iterator[Recording], dict]:
    """Streaming form of simulate_motion: (iterator of 1-s Recording slices, truth dict
    filled as it runs)."""
    if duration_s <= 0:
        raise ConfigError("--duration must be > 0 seconds")
    params = params if params is not None else SimParams.load()
    sim = HandSimulator(
        params, effects=effects, seed=seed, tap_rate_hz=tap_rate_hz, tap_mode=tap_mode
    )
    _, cmds = motion_commands(duration_s, max_speed, seed)
    total = int(round(duration_s * ACCEL_RATE_HZ))
    # zero-order hold of the commands at the accelerometer rate; a command is sent when it starts
    hold = np.minimum(
        (np.arange(total) * COMMAND_RATE_HZ / ACCEL_RATE_HZ).astype(np.int64), len(cmds) - 1
    )
    starts = np.flatnonzero(np.diff(hold, prepend=-1))
    truth = _truth(seed, sim.effects)

    def generate() -> Iterator[Recording]:
        for a in range(0, total, CHUNK):
            b = min(a + CHUNK, total)
            chunk = sim.step(b - a, commands=cmds[hold[a:b]])
            sent = starts[(starts >= a) & (starts < b)]
            truth["tap_onsets_ns"].extend(int(x) for x in chunk.tap_onsets_ns)
            if progress is not None:
                progress(len(chunk.sensor) / ACCEL_RATE_HZ)
            yield _with_commands(chunk, sim.stamps_ns(sent), cmds[hold[sent]])

    return generate(), truth


def simulate_motion(**options) -> tuple[Recording, dict]:
    """Random smooth motion (paper section 4) with optional taps (motion_slices' options),
    whole: (Recording, truth)."""
    slices, truth = motion_slices(**options)
    return concat_recordings(list(slices)), truth
