"""Any robot, simulated from its profile: free motion or a velocity-grid sweep.

A generic N-joint model of the ego-vibration the denoiser removes; topics, field, rate,
joints, speeds, grid and band come from the robot profile, the rest from the options.

- Each joint's motor vibrates at a line rising with its speed, from about 15 % to 75 %
  of the way across the band from rest to full speed (own idle frequency and slope per
  joint), with 2nd and 3rd harmonics (1/2, 1/3 of its amplitude, faded out before
  Nyquist); amplitude proportional to speed, each harmonic along its own direction. The
  build (frequencies, directions, tap direction) is drawn from the profile's name and
  joints, not the run's seed: every run of a profile is the same robot, so a model
  calibrated on one run fits another.
- A white sensor floor; gravity on z for linear_acceleration (a gyro does not measure
  it); values saturate at the profile's sensor range. Sensor stamps jitter +-30 % per
  step, as flight controllers and USB IMUs stamp them; joint states at `joint_rate_hz`
  (default 1 kHz, or the sensor rate if lower), stamped 150 us after their sensor
  sample, velocity read to 0.2 % of full speed (never below 0 on a one-way joint).
- Taps: damped sine bursts (8 ms decay, 50 ms long) at the band's geometric centre,
  three times the vibration level with a lognormal spread, Poisson (0.15 s dead time) or
  periodic; the contact-only signal and the ego-vibration are written as ground truth.

Motion: white noise through a 2nd-order 0.3 Hz low-pass within `max_speed` of each
joint's limit (one-way joints in 0..max); sweep: the profile's grid cells in turn, a
cosine ramp of `settle_s` between cells, then `dwell_s` on each. `RobotSimulator.step`
works from explicit carried state, every random stream drawn in sample order, so a run
cut into any steps gives the same output (tested to the bit). `CommandedRobot` (the
sim_robot node) follows velocity commands and says how many samples a clock time is due.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np
from scipy import signal

from egovib_ros.bag.recording import Recording
from egovib_ros.core.filters import lfilter_carried
from egovib_ros.core.noise_model import sweep_cells
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import ConfigError
from egovib_ros.robot import RobotProfile

MODES = ("motion", "sweep")
GRIDS = ("full", "superposition")
TAP_MODES = ("random", "periodic")
GRAVITY_MS2 = 9.80665
START_NS = 1_000_000_000  # first sensor stamp (a clock that is not at zero)
#: Imu frame_id of the simulated sensor (the profile names no frame).
SENSOR_FRAME = "imu_link"
#: Live: time constant of the simulated joints' velocity controller (a step of the
#: command is 98 % reached after 4 of them, 0.2 s).
CONTROLLER_TAU_S = 0.05
JOINT_LAG_NS = 150_000  # joint states stamped this long after their sensor sample
DEFAULT_JOINT_RATE_HZ = 1000.0
MOTION_CORNER_HZ = 0.3  # smooth random motion: a few direction changes per 10 s
TAP_DECAY_S, TAP_LENGTH_S, TAP_DEAD_TIME_S = 0.008, 0.05, 0.15
#: A full sweep of more cells than this is refused: an 8-joint grid has 21^8 of them.
MAX_SWEEP_CELLS = 100_000
#: Streams of random numbers, one per purpose, each drawn in sample order.
_STREAMS = ("jitter", "floor", "motion", "velocity_noise", "taps")


@dataclass(frozen=True)
class RobotBuild:
    """What makes a robot of a profile itself (fixed for the profile, see the module doc)."""

    idle: np.ndarray  # (J,) fundamental at rest, as a fraction of the band
    slope: np.ndarray  # (J,) rise of the fundamental from rest to full speed (band fraction)
    directions: np.ndarray  # (J, 3 harmonics, 3 axes) unit vectors
    tap_direction: np.ndarray  # (3,) unit vector
    level: float  # vibration amplitude of one joint's fundamental at full speed
    floor: float  # white sensor noise (std)

    @classmethod
    def of(cls, profile: RobotProfile) -> "RobotBuild":
        key = "\n".join((profile.name,) + profile.joint_names).encode()
        rng = np.random.default_rng(np.random.SeedSequence([zlib.crc32(key), 0x6275696C64]))
        n = profile.n_joints
        directions = rng.normal(size=(n, 3, 3))
        directions /= np.linalg.norm(directions, axis=2, keepdims=True)
        # all axes one sign: the paper's signal is the sum of the axes, where a tap along
        # (1, -1, 0) would vanish
        tap = np.abs(rng.normal(size=3)) + 0.2
        # A level the sensor can carry: 1 (m/s^2 or rad/s), less for a small range. Joints
        # add up incoherently: each gets 1/sqrt(J) of it.
        level = (
            min(1.0, 0.05 * profile.sensor_range) if math.isfinite(profile.sensor_range) else 1.0
        )
        return cls(
            idle=rng.uniform(0.10, 0.20, n),
            slope=rng.uniform(0.50, 0.65, n),
            directions=directions,
            tap_direction=tap / np.linalg.norm(tap),
            level=level / math.sqrt(n),
            floor=0.05 * level,
        )


def _rngs(seed: int) -> dict[str, np.random.Generator]:
    return {
        name: np.random.default_rng(np.random.SeedSequence([int(seed), k, 0x726F626F74]))
        for k, name in enumerate(_STREAMS)
    }


def _carried_cumsum(start, values: np.ndarray) -> np.ndarray:
    """cumsum continuing from `start`, summed left to right as over the whole run (so a
    run cut into steps gives the same floats as one step)."""
    values = np.asarray(values)
    head = np.asarray(start, dtype=values.dtype).reshape((1,) + values.shape[1:])
    return np.cumsum(np.concatenate([head, values]), axis=0)[1:]


class RobotSimulator:
    """The sensor and joint streams of a robot profile, for given joint velocities.

    >>> sim = RobotSimulator(profile, seed=1, tap_rate_hz=0.5)
    >>> piece = sim.step(velocity)          # (n, J) true joint velocities, one per sample
    >>> piece.sensor, piece.contact, sim.tap_onsets_ns
    """

    def __init__(
        self,
        profile: RobotProfile,
        *,
        seed: int = 0,
        tap_rate_hz: float = 0.0,
        tap_mode: str = "random",
        tap_amplitude: float | None = None,
        jitter: float = 0.3,
        joint_rate_hz: float | None = None,
        start_ns: int = START_NS,
    ):
        if tap_mode not in TAP_MODES:
            raise ConfigError(f"tap mode must be one of {TAP_MODES}, got {tap_mode!r}")
        if not (math.isfinite(tap_rate_hz) and tap_rate_hz >= 0):
            raise ConfigError(f"--taps: the tap rate must be >= 0 Hz, got {tap_rate_hz!r}")
        if tap_rate_hz > 1.0 / TAP_DEAD_TIME_S:
            raise ConfigError(
                f"--taps: at most {1.0 / TAP_DEAD_TIME_S:.3g} taps per second "
                f"(taps are {TAP_DEAD_TIME_S:g} s apart at least), got {tap_rate_hz:g}"
            )
        if not 0.0 <= jitter < 0.5:
            raise ConfigError(f"stamp jitter must be in [0, 0.5) of a period, got {jitter!r}")
        self.profile = profile
        self.build = RobotBuild.of(profile)
        self.fs = profile.rate_hz
        joint_rate = DEFAULT_JOINT_RATE_HZ if joint_rate_hz is None else float(joint_rate_hz)
        if not (math.isfinite(joint_rate) and joint_rate > 0):
            raise ConfigError(f"--joint-rate must be a positive number of Hz, got {joint_rate!r}")
        self.joint_every = max(1, int(round(self.fs / joint_rate)))
        self.seed, self.jitter = int(seed), float(jitter)
        self.tap_rate_hz, self.tap_mode = float(tap_rate_hz), tap_mode
        self.tap_amplitude = (
            3.0 * self.build.level * math.sqrt(profile.n_joints)
            if (tap_amplitude is None)
            else float(tap_amplitude)
        )
        self.rng = _rngs(seed)
        low, high = profile.band_hz
        self.band_low, self.band_span = low, high - low
        self.tap_hz = math.sqrt(low * high)
        self.max_speed = np.asarray(profile.max_speed, dtype=np.float64)
        self.one_way = ~np.asarray(profile.bidirectional)
        self.gravity = GRAVITY_MS2 if profile.sensor_field == "linear_acceleration" else 0.0
        # carried state
        self.index = 0  # next sensor sample
        self.start_ns = int(start_ns)  # the first sample's stamp
        self.last_stamp_ns = self.start_ns  # stamp of the previous sample (the first: start_ns)
        self.phase = np.zeros(profile.n_joints)
        self.position = np.zeros(profile.n_joints)
        self.tap_onsets_ns: list[int] = []
        self._taps: list[tuple[int, float]] = []  # (onset stamp ns, amplitude) under way
        self._next_tap = self._first_tap() if self.tap_rate_hz > 0 else None

    # --- taps ---------------------------------------------------------------------
    def _first_tap(self) -> int:
        if self.tap_mode == "periodic":
            return int(round(0.5 * self.fs / self.tap_rate_hz))
        return self._interval()

    def _interval(self) -> int:
        if self.tap_mode == "periodic":
            return max(1, int(round(self.fs / self.tap_rate_hz)))
        mean_free = max(1.0 / self.tap_rate_hz - TAP_DEAD_TIME_S, 0.02)
        wait = TAP_DEAD_TIME_S + self.rng["taps"].exponential(mean_free)
        return max(1, int(round(wait * self.fs)))

    def _tap_signal(self, stamps: np.ndarray) -> np.ndarray:
        """(n,) contact signal along the tap direction at these sensor stamps; new taps whose
        onset falls on these samples start here."""
        i0, n = self.index, len(stamps)
        while self._next_tap is not None and self._next_tap < i0 + n:
            onset = int(stamps[self._next_tap - i0])
            amplitude = self.tap_amplitude * float(np.exp(0.3 * self.rng["taps"].normal() - 0.045))
            self._taps.append((onset, amplitude))
            self.tap_onsets_ns.append(onset)
            self._next_tap += self._interval()
        out = np.zeros(n)
        still = []
        for onset, amplitude in self._taps:
            tau = (stamps - onset) / NS_PER_S
            on = (tau >= 0) & (tau < TAP_LENGTH_S)
            out[on] += (
                amplitude
                * np.exp(-tau[on] / TAP_DECAY_S)
                * np.sin(2 * np.pi * self.tap_hz * tau[on])
            )
            if len(stamps) and (stamps[-1] - onset) / NS_PER_S < TAP_LENGTH_S:
                still.append((onset, amplitude))
        self._taps = still
        return out

    # --- one step -------------------------------------------------------------------
    def step(self, velocity: np.ndarray) -> Recording:
        """The next len(velocity) sensor samples and the joint states among them, for the
        true joint velocities (n, J) at those samples."""
        velocity = np.asarray(velocity, dtype=np.float64)
        p, b = self.profile, self.build
        n = len(velocity)
        if velocity.shape != (n, p.n_joints):
            raise ConfigError(
                f"simulator: velocities must be (n, {p.n_joints}), got {velocity.shape}"
            )
        period_ns = NS_PER_S / self.fs
        steps_ns = np.maximum(
            1, np.rint(period_ns * (1.0 + self.rng["jitter"].uniform(-1, 1, n) * self.jitter))
        ).astype(np.int64)
        if self.index == 0 and n:
            steps_ns[0] = 0  # the first sample sits at start_ns
        stamps = self.last_stamp_ns + np.cumsum(steps_ns)  # integers: exact in any cut
        dt = steps_ns / NS_PER_S
        ego = np.zeros((n, 3))
        speed = np.abs(velocity) / self.max_speed
        for j in range(p.n_joints):
            fundamental = self.band_low + self.band_span * (b.idle[j] + b.slope[j] * speed[:, j])
            phase = _carried_cumsum(self.phase[j], 2 * np.pi * fundamental * dt)
            if n:
                self.phase[j] = phase[-1]
            for k in (1, 2, 3):
                fade = np.clip((0.45 * self.fs - k * fundamental) / (0.05 * self.fs), 0.0, 1.0)
                amplitude = (b.level / k) * speed[:, j] * fade
                ego += (amplitude * np.sin(k * phase + j + k))[:, None] * b.directions[j, k - 1]
        ego[:, 2] += self.gravity
        contact = self._tap_signal(stamps)[:, None] * b.tap_direction[None, :]
        accel = ego + contact + b.floor * self.rng["floor"].normal(size=(n, 3))
        if math.isfinite(p.sensor_range):  # a real sensor saturates at its full scale
            accel = np.clip(accel, -p.sensor_range, p.sensor_range)
        position = _carried_cumsum(self.position, velocity * dt[:, None])
        if n:
            self.position = position[-1]
        pick = np.arange((-self.index) % self.joint_every, n, self.joint_every)
        measured = velocity[pick] + 0.002 * self.max_speed * self.rng["velocity_noise"].normal(
            size=(len(pick), p.n_joints)
        )
        # a one-way joint (a propeller's motor) never reads a negative speed
        measured = np.where(self.one_way, np.maximum(measured, 0.0), measured)
        self.index += n
        if n:
            self.last_stamp_ns = int(stamps[-1])
        return Recording(
            sensor_stamps_ns=stamps,
            sensor=accel,
            joint_stamps_ns=stamps[pick] + JOINT_LAG_NS,
            joint_position=position[pick],
            joint_velocity=measured,
            joint_names=p.joint_names,
            contact=contact,
            ego=ego,
        )


# --- live: velocity commands in --------------------------------------------------------
class CommandedRobot:
    """A robot of a profile following velocity commands (the `sim_robot` node's simulator).

    The command (one velocity per joint in profile order, held until the next, as a
    ros2_control forward-command controller takes it) is limited to each joint's range
    (-max..max, or 0..max for a one-way joint: a velocity controller saturates) and reached
    through a first-order lag of CONTROLLER_TAU_S, sample by sample; the RobotSimulator
    (`options`: seed, tap_rate_hz, start_ns, ...) makes the samples at those velocities.

    >>> robot = CommandedRobot(profile, seed=1, start_ns=now_ns)
    >>> robot.set_command([0.5, 0.0, -1.0])
    >>> piece = robot.step(robot.samples_due(now_ns))      # a Recording, as sim.step's
    """

    def __init__(self, profile: RobotProfile, **options):
        self.profile = profile
        self.sim = RobotSimulator(profile, **options)
        n = profile.n_joints
        self.command = np.zeros(n)  # as held (within the joints' ranges)
        self.velocity = np.zeros(n)  # true velocity at the last sample
        top = np.asarray(profile.max_speed, dtype=np.float64)
        self.low, self.high = np.where(profile.bidirectional, -top, 0.0), top
        alpha = 1.0 - math.exp(-1.0 / (profile.rate_hz * CONTROLLER_TAU_S))
        self._ba = ([alpha], [1.0, alpha - 1.0])
        self._zi = np.zeros((1, n))

    def set_command(self, velocity) -> bool:
        """Hold these joint velocities from the next sample on; False when some were beyond
        their joint's range (then held at its limit)."""
        v = np.asarray(velocity, dtype=np.float64).reshape(-1)
        if v.shape != (self.profile.n_joints,) or not np.all(np.isfinite(v)):
            raise ConfigError(
                f"command must be {self.profile.n_joints} finite velocities, got {velocity!r}"
            )
        self.command = np.clip(v, self.low, self.high)
        return bool(np.array_equal(self.command, v))

    def samples_due(self, now_ns: int) -> int:
        """How many samples are due by clock time `now_ns`: those the nominal rate puts
        between the last sample's stamp and `now_ns` (the first sample sits at start_ns).
        Counted from the last stamp, not from the start, the jittered stamps stay within a
        few periods of the clock however long the run."""
        sim, fs = self.sim, self.profile.rate_hz
        if sim.index == 0:
            return max(0, math.floor((now_ns - sim.start_ns) * fs / NS_PER_S) + 1)
        return max(0, math.floor((now_ns - sim.last_stamp_ns) * fs / NS_PER_S))

    @property
    def index(self) -> int:
        """Samples made so far."""
        return self.sim.index

    @property
    def tap_onsets_ns(self) -> list[int]:
        return self.sim.tap_onsets_ns

    def step(self, n: int) -> Recording:
        """The next n samples (and the joint states among them) at the held command."""
        target = np.broadcast_to(self.command, (int(n), self.profile.n_joints))
        velocity, self._zi = lfilter_carried(*self._ba, target, self._zi, axis=0)
        if len(velocity):
            self.velocity = velocity[-1].copy()
        return self.sim.step(velocity)


# --- velocity schedules ----------------------------------------------------------------
class SmoothMotion:
    """Smooth random joint velocities, any number of samples at a time (causal filter with
    carried state; its own random stream)."""

    def __init__(self, profile: RobotProfile, max_speed: float, rng: np.random.Generator):
        if not 0.0 < max_speed <= 1.0:
            raise ConfigError(f"--max-speed must be a fraction in (0, 1], got {max_speed!r}")
        self.profile, self.max_speed, self.rng = profile, float(max_speed), rng
        fs = profile.rate_hz
        self.sos = signal.butter(2, MOTION_CORNER_HZ, fs=fs, output="sos")
        # unit rms: the filter's own gain for white noise (sum of its squared impulse response)
        impulse = np.zeros(int(20 * fs / MOTION_CORNER_HZ))
        impulse[0] = 1.0
        self.gain = float(np.sqrt(np.sum(signal.sosfilt(self.sos, impulse) ** 2)))
        # start in the filter's steady state: run it on 5 corner periods of noise first
        zi = np.zeros((self.sos.shape[0], 2, profile.n_joints))
        _, self.zi = signal.sosfilt(
            self.sos,
            rng.normal(size=(int(5 * fs / MOTION_CORNER_HZ), profile.n_joints)),
            axis=0,
            zi=zi,
        )
        self.bidirectional = np.asarray(profile.bidirectional)
        self.top = self.max_speed * np.asarray(profile.max_speed)

    def next(self, n: int) -> np.ndarray:
        x, self.zi = signal.sosfilt(
            self.sos, self.rng.normal(size=(n, self.profile.n_joints)), axis=0, zi=self.zi
        )
        x = x / self.gain
        fraction = np.where(
            self.bidirectional, np.clip(0.5 * x, -1.0, 1.0), np.clip(0.5 + 0.25 * x, 0.0, 1.0)
        )
        return fraction * self.top


class SweepSchedule:
    """The profile's grid cells in turn: a cosine ramp of `settle_s` from the previous cell
    (rest before the first), then `dwell_s` on the cell. A function of the sample index."""

    def __init__(self, profile: RobotProfile, grid: str, dwell_s: float, settle_s: float):
        if grid not in GRIDS:
            raise ConfigError(f"--grid must be one of {GRIDS}, got {grid!r}")
        if not (math.isfinite(dwell_s) and dwell_s > 0):
            raise ConfigError(f"--dwell must be > 0 seconds, got {dwell_s!r}")
        if not (math.isfinite(settle_s) and settle_s >= 0):
            raise ConfigError(f"--settle must be >= 0 seconds, got {settle_s!r}")
        self.velocities = sweep_velocities(profile, grid, where=f"--grid {grid}")
        fs = profile.rate_hz
        self.settle = int(round(settle_s * fs))
        self.per_cell = self.settle + max(1, int(round(dwell_s * fs)))
        self.total = self.per_cell * len(self.velocities)
        self.index = 0

    def next(self, n: int) -> np.ndarray:
        i = self.index + np.arange(n)
        self.index += n
        cell = np.minimum(i // self.per_cell, len(self.velocities) - 1)
        within = i - cell * self.per_cell
        target = self.velocities[cell]
        previous = np.where(
            (cell > 0)[:, None], self.velocities[np.maximum(cell - 1, 0)], 0.0 * target
        )
        if self.settle:
            ramp = 0.5 - 0.5 * np.cos(np.pi * np.minimum(within / self.settle, 1.0))
        else:
            ramp = np.ones(n)
        return previous + ramp[:, None] * (target - previous)


def sweep_velocities(profile: RobotProfile, grid: str, where: str = "") -> np.ndarray:
    """Velocities (C, J) of the cells a sweep over the profile's grid visits, in the core's
    order (egovib_ros.core.noise_model.sweep_cells: the one definition calibration uses);
    a full grid of more than MAX_SWEEP_CELLS cells is refused (`where`: what the refusal
    names, by default the profile)."""
    n_cells = sweep_cell_count(profile, grid)
    if n_cells > MAX_SWEEP_CELLS:
        raise ConfigError(
            f"{where or profile.name}: a full sweep has {n_cells} cells (more than "
            f"{MAX_SWEEP_CELLS}); sweep the superposition grid "
            f"({sweep_cell_count(profile, 'superposition')} cells) or calibrate from free motion"
        )
    axes = profile.grid()
    cells = sweep_cells(axes, grid)
    return np.column_stack([axes[j][cells[:, j]] for j in range(profile.n_joints)])


def sweep_cell_count(profile: RobotProfile, grid: str) -> int:
    shape = profile.grid_shape
    if grid == "full":
        return int(np.prod(shape, dtype=np.float64))
    return 1 + sum(n - 1 for n in shape)


# --- whole runs ---------------------------------------------------------------------
def robot_slices(
    profile: RobotProfile,
    *,
    mode: str = "motion",
    duration_s: float | None = None,
    max_speed: float = 0.9,
    grid: str = "superposition",
    dwell_s: float = 2.0,
    settle_s: float = 0.5,
    tap_rate_hz: float = 0.0,
    tap_mode: str = "random",
    seed: int = 0,
    joint_rate_hz: float | None = None,
    jitter: float = 0.3,
    tap_amplitude: float | None = None,
    progress: Callable[[float], None] | None = None,
) -> tuple[Iterator[Recording], dict, float]:
    """(iterator of 1-s Recording slices, truth dict filled as it runs, seconds
    simulated). Everything that can be refused is refused here, before the first sample."""
    if mode not in MODES:
        raise ConfigError(f"--mode must be one of {MODES}, got {mode!r}")
    sim = RobotSimulator(
        profile,
        seed=seed,
        tap_rate_hz=tap_rate_hz,
        tap_mode=tap_mode,
        tap_amplitude=tap_amplitude,
        jitter=jitter,
        joint_rate_hz=joint_rate_hz,
    )
    if mode == "sweep":
        schedule = SweepSchedule(profile, grid, dwell_s, settle_s)
        total = schedule.total
    else:
        if duration_s is None or not (math.isfinite(duration_s) and duration_s > 0):
            raise ConfigError(f"--duration must be > 0 seconds, got {duration_s!r}")
        schedule = SmoothMotion(profile, max_speed, sim.rng["motion"])
        total = int(round(duration_s * profile.rate_hz))
    chunk = max(1, int(round(profile.rate_hz)))
    truth = {"seed": int(seed), "effects": {}, "tap_onsets_ns": []}  # the --truth sidecar

    def generate() -> Iterator[Recording]:
        for start in range(0, total, chunk):
            n = min(chunk, total - start)
            taps_before = len(sim.tap_onsets_ns)
            piece = sim.step(schedule.next(n))
            truth["tap_onsets_ns"].extend(sim.tap_onsets_ns[taps_before:])
            if progress is not None:
                progress(n / profile.rate_hz)
            yield piece

    return generate(), truth, total / profile.rate_hz
