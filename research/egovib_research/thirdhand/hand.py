"""The third hand's physics: written from the effect vocabulary (CONTRACT section 5) and the
robot of section 1 alone, without reading the project's simulator (egovib_ros/sim) or the
alternate reality (egovib_research/altreality).

Drives (made up for this generator):
- wrist: a brushless motor through a three-stage planetary gear; tonal lines at WRIST_LINES
  Hz per rad/s of the wrist (stage meshes and a carrier-pass line), amplitudes growing as
  speed^1.3, each line's amplitude wandering slowly (mesh "breathing"), plus bearing hiss;
- gripper: a DC motor through a worm gear and a lead screw; lines at GRIPPER_LINES Hz per
  m/s, amplitudes as speed^0.8, plus brush noise (band-passed, level with speed).
Structure: three housing modes (MODES: Hz, Q, gain) shape everything; each source reaches
the three sensor axes along its own direction. Sensor: white noise, 10 bits over +-78.5
m/s^2, gravity turning with the wrist (out of band). Contacts: decaying sinusoids.

Effects, by form (strength s; position, coupling and acceleration: s = 1 makes the
vibration ~3 dB louder where the effect acts; drift: the relative level change; timing: s):

| effect | form | what |
|---|---|---|
| position | `twice` | wrist lines x (1 + 0.41 s (1 + cos 2(angle - phase)) / 2): twice a turn |
| position | `open_end` | gripper lines x (1 + 0.41 s ramp towards the open end of the gap) |
| position | `sector` | added hiss (400-700 Hz) while the wrist turns through a 1 rad sector |
| coupling | `line_gain` | wrist lines x (1 + 0.41 s |v_gripper| / top): magnitude |
| coupling | `line_signed` | gripper lines x exp(0.35 s sign(v_wrist) |v_wrist| / top): signed |
| coupling | `together` | a line at a fixed 560 Hz mode, only while both joints move |
| acceleration | `ringing` | the 980 Hz mode rung by the acceleration's jerk (speed changes) |
| acceleration | `torque` | wrist lines x (1 + 0.41 s |a_wrist| / a_ref): torque ripple |
| timing | `lag`, `lead` | joint-state stamps s late / early |
| timing | `polled` | joint states published every 8 ms, each the driver's last reading (0-8 ms
  old), stamped on publishing, + s |
| drift | `cooldown` | level x (1 - s (1 - exp(-t / 30 s))): falls, levels off |
| drift | `gripper_wear` | gripper sources x (1 + s t / T): one joint's level rises |
| drift | `cycle` | level x (1 + s sin(2 pi t / (0.8 T))): a thermal cycle |
"""

from __future__ import annotations

import numpy as np
from scipy import signal

from egovib_research.thirdhand.motion import TOP_SPEED, trajectories

FS = 3000.0
JOINT_RATE_HZ = 1000.0
#: The `polled` timing form: joint states published at this period (s).
POLL_S = 0.008
#: Wrist lines: Hz per rad/s, relative amplitude (m/s^2 at full speed before the structure).
WRIST_LINES = ((23.0, 0.35), (71.0, 0.6), (142.0, 0.3), (187.0, 0.45), (229.0, 0.2))
#: Gripper lines: Hz per m/s, relative amplitude.
GRIPPER_LINES = ((4200.0, 0.3), (9100.0, 0.55), (13600.0, 0.25))
#: Housing modes: (Hz, Q, gain); and the stiff direct path's gain.
MODES = ((330.0, 6.0, 1.6), (560.0, 9.0, 1.2), (980.0, 5.0, 1.0))
DIRECT = 0.5
#: Directions of the sources on the sensor axes (normalised in use).
DIRECTIONS = {
    "wrist": (0.8, 0.5, 0.3),
    "gripper": (0.2, 0.4, 0.9),
    "hiss": (0.6, 0.6, 0.5),
    "ring": (0.3, 0.9, 0.3),
}
RANGE = 78.5
BITS = 10
SENSOR_NOISE = 0.02
#: Encoder resolution: wrist (rad), gripper (m).
ENCODER_STEP = (2 * np.pi / 4096 / 50, 1e-6)
START_NS = 1_700_000_000_000_000_000
#: Joint names (CONTRACT section 1).
JOINT_NAMES = ("r_wrist_roll_joint", "r_gripper_joint")
FORMS = {
    "position": ("twice", "open_end", "sector"),
    "coupling": ("line_gain", "line_signed", "together"),
    "acceleration": ("ringing", "torque"),
    "timing": ("lag", "lead", "polled"),
    "drift": ("cooldown", "gripper_wear", "cycle"),
}
#: A gain that makes the vibration ~3 dB louder: 10^(3/20) - 1.
THREE_DB = 0.41


def _structure(f: np.ndarray) -> np.ndarray:
    """|H(f)| of the housing: the modes and the direct path."""
    h = np.full(np.shape(f), DIRECT, dtype=complex)
    for fm, q, g in MODES:
        r = np.asarray(f) / fm
        h = h + g / (1.0 - r**2 + 1j * r / q)
    return np.abs(h)


def _direction(name: str) -> np.ndarray:
    d = np.asarray(DIRECTIONS[name], float)
    return d / np.linalg.norm(d)


def _tone(freq: np.ndarray, amp: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A line of instantaneous frequency `freq` (Hz) and amplitude `amp`, shaped by the
    structure at its frequency, random phase."""
    phase = 2 * np.pi * np.cumsum(freq) / FS + rng.uniform(0, 2 * np.pi)
    return amp * _structure(freq) * np.sin(phase)


def _wander(n: int, rng: np.random.Generator, depth: float = 0.0, tau_s: float = 2.0):
    """A slow random amplitude factor around 1 (mesh breathing): white noise on a 10 Hz
    grid through a first-order low-pass of time constant `tau_s`, `depth` standard
    deviation, interpolated to the samples."""
    grid_hz = 10.0
    x = rng.standard_normal(int(n / FS * grid_hz) + 2)
    slow = signal.lfilter(
        [1.0 - np.exp(-1.0 / (tau_s * grid_hz))], [1.0, -np.exp(-1.0 / (tau_s * grid_hz))], x
    )
    slow = (slow - slow.mean()) / max(np.std(slow), 1e-9)
    return 1.0 + depth * np.interp(np.arange(n) / FS * grid_hz, np.arange(len(x)), slow)


def _band_noise(n: int, lo: float, hi: float, rng: np.random.Generator) -> np.ndarray:
    sos = signal.butter(3, [lo, hi], btype="band", fs=FS, output="sos")
    x = signal.sosfilt(sos, rng.standard_normal(n))
    return x / np.std(x)


def _mode_noise(n: int, f0: float, q: float, rng: np.random.Generator) -> np.ndarray:
    b, a = signal.iirpeak(f0, q, fs=FS)
    x = signal.lfilter(b, a, rng.standard_normal(n))
    return x / np.std(x)


def _acceleration(vel: np.ndarray) -> np.ndarray:
    """Smoothed joint acceleration (n, 2)."""
    b, a = signal.butter(2, 30.0, fs=FS)
    return signal.filtfilt(b, a, np.gradient(vel, 1.0 / FS, axis=0), axis=0)


def ego_vibration(
    vel: np.ndarray, pos: np.ndarray, t: np.ndarray, effects: dict, forms: dict, rng, rng_effect
) -> np.ndarray:
    """The robot's own vibration (n, 3) for the true motion, with the effects (their random
    parts from `rng_effect`, so that the rest of the run is the same with and without)."""
    n = len(t)
    u = np.abs(vel) / TOP_SPEED  # speed fractions
    acc = _acceleration(vel)
    a_ref = np.percentile(np.abs(acc), 95, axis=0) + 1e-9
    wrist_gain = np.ones(n)
    gripper_gain = np.ones(n)
    level = np.ones(n)
    extra = np.zeros((n, 3))
    s = effects.get("position", 0.0)
    form = forms.get("position")
    if s and form == "twice":
        phase = rng_effect.uniform(0, np.pi)
        wrist_gain *= 1 + THREE_DB * s * (1 + np.cos(2 * (pos[:, 0] - phase))) / 2
    elif s and form == "open_end":
        ramp = np.clip((pos[:, 1] - 0.05) / 0.032, 0.0, 1.0)
        gripper_gain *= 1 + THREE_DB * s * ramp
    elif s and form == "sector":
        start = rng_effect.uniform(-np.pi, np.pi)
        inside = np.mod(pos[:, 0] - start, 2 * np.pi) < 1.0
        hiss = _band_noise(n, 400.0, 700.0, rng_effect) * 0.35 * s * u[:, 0] * inside
        extra += hiss[:, None] * _direction("hiss")
    s = effects.get("coupling", 0.0)
    form = forms.get("coupling")
    if s and form == "line_gain":
        wrist_gain *= 1 + THREE_DB * s * u[:, 1]
    elif s and form == "line_signed":
        gripper_gain *= np.exp(0.35 * s * np.sign(vel[:, 0]) * u[:, 0])
    elif s and form == "together":
        both = np.sqrt(u[:, 0] * u[:, 1])
        line = _tone(np.full(n, 560.0), 0.25 * s * both, rng_effect) / _structure(560.0)
        extra += line[:, None] * _direction("ring")
    s = effects.get("acceleration", 0.0)
    form = forms.get("acceleration")
    if s and form == "ringing":
        jerk = np.abs(np.gradient(acc, 1.0 / FS, axis=0)).sum(axis=1)
        drive = jerk / (np.percentile(jerk, 99) + 1e-9)
        ring = _mode_noise(n, 980.0, 12.0, rng_effect) * 0.3 * s * np.minimum(drive, 4.0)
        extra += ring[:, None] * _direction("ring")
    elif s and form == "torque":
        wrist_gain *= 1 + THREE_DB * s * np.minimum(np.abs(acc[:, 0]) / a_ref[0], 3.0)
    s = effects.get("drift", 0.0)
    form = forms.get("drift")
    span = max(float(t[-1] - t[0]), 1e-9)
    if s and form == "cooldown":
        level *= 1 - s * (1 - np.exp(-(t - t[0]) / 30.0))
    elif s and form == "gripper_wear":
        gripper_gain *= 1 + s * (t - t[0]) / span
    elif s and form == "cycle":
        level *= 1 + s * np.sin(2 * np.pi * (t - t[0]) / (0.8 * span))
    out = np.zeros((n, 3))
    wrist = np.zeros(n)
    for hz, amp in WRIST_LINES:
        wrist += _tone(hz * np.abs(vel[:, 0]), amp * u[:, 0] ** 1.3 * _wander(n, rng), rng)
    wrist += 0.12 * u[:, 0] * _band_noise(n, 150.0, 1200.0, rng)  # bearing hiss
    out += (wrist * wrist_gain)[:, None] * _direction("wrist")
    gripper = np.zeros(n)
    for hz, amp in GRIPPER_LINES:
        gripper += _tone(hz * np.abs(vel[:, 1]), amp * u[:, 1] ** 0.8 * _wander(n, rng), rng)
    gripper += 0.15 * u[:, 1] * _band_noise(n, 250.0, 1400.0, rng)  # brushes
    out += (gripper * gripper_gain)[:, None] * _direction("gripper")
    return (out + extra) * level[:, None]


def taps(n: int, rate_hz: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """Contacts (n, 3): decaying sinusoids at Poisson times; their onsets (sample index)."""
    out = np.zeros((n, 3))
    onsets = []
    k = int(rng.exponential(FS / rate_hz)) if rate_hz > 0 else n
    while k < n - int(0.1 * FS):
        length = int(0.06 * FS)
        tt = np.arange(length) / FS
        burst = (
            rng.uniform(5.0, 20.0)
            * np.exp(-tt / rng.uniform(0.005, 0.015))
            * np.sin(2 * np.pi * rng.uniform(200.0, 800.0) * tt)
        )
        d = rng.standard_normal(3)
        out[k : k + length] += burst[:, None] * d / np.linalg.norm(d)
        onsets.append(k)
        k += int(0.15 * FS + rng.exponential(FS / rate_hz))
    return out, np.array(onsets, dtype=np.int64)


def sensor(ego: np.ndarray, contact: np.ndarray, wrist_angle: np.ndarray, rng) -> np.ndarray:
    """What the accelerometer reports: gravity turning with the wrist, vibration, contact,
    white noise, clipped to its range and quantised to its bits."""
    gravity = 9.81 * np.stack(
        [0.3 * np.sin(wrist_angle), 0.3 * np.cos(wrist_angle), np.full_like(wrist_angle, 0.95)],
        axis=1,
    )
    x = gravity + ego + contact + SENSOR_NOISE * rng.standard_normal(ego.shape)
    step = 2 * RANGE / 2**BITS
    return np.clip(np.round(x / step) * step, -RANGE, RANGE - step)


def joint_states(
    vel: np.ndarray, pos: np.ndarray, effects: dict, forms: dict, rng
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps ns, positions, velocities) at JOINT_RATE_HZ: encoder positions, velocity by
    first-order differences of them (as on the PR2), stamps moved by the timing effect
    (`polled`: at 1 / POLL_S, each the last reading, stamped on publishing)."""
    s = effects.get("timing", 0.0)
    rate = JOINT_RATE_HZ
    if s and forms.get("timing") == "polled":
        # published every 8 ms, each message the driver's last encoder reading (0-8 ms old),
        # stamped when published, then the lag s; velocity over the nominal 8 ms
        rate = 1.0 / POLL_S
        publish = np.arange(POLL_S, len(pos) / FS, POLL_S)
        read = publish - rng.uniform(0.0, POLL_S, len(publish))
        idx = np.minimum(np.round(read * FS).astype(np.int64), len(pos) - 1)
        true_ns = START_NS + (publish * 1e9).astype(np.int64)
    else:
        idx = np.arange(0, len(pos), int(FS / rate))
        true_ns = START_NS + (idx * (1e9 / FS)).astype(np.int64)
    q = np.round(pos[idx] / ENCODER_STEP) * ENCODER_STEP
    v = np.vstack([np.zeros((1, 2)), np.diff(q, axis=0) * rate])
    return true_ns + int(round(s * 1e9)), q, v


def simulate(
    duration_s: float,
    effects: dict,
    forms: dict,
    seed: int,
    tap_rate_hz: float = 0.5,
    max_speed: float = 0.8,
) -> dict:
    """Arrays of one run: sensor stamps and samples, joint states, ground truth."""
    # one stream per part: an effect changes what it says and nothing else
    rng_motion, rng_vib, rng_effect, rng_taps, rng_noise = (
        np.random.default_rng([seed, k]) for k in range(5)
    )
    vel, pos = trajectories(duration_s, FS, rng_motion, max_speed)
    n = len(vel)
    t = np.arange(n) / FS
    ego = ego_vibration(vel, pos, t, effects, forms, rng_vib, rng_effect)
    contact, onsets = taps(n, tap_rate_hz, rng_taps)
    values = sensor(ego, contact, pos[:, 0], rng_noise)
    stamps, q, v = joint_states(vel, pos, effects, forms, rng_noise)
    return {
        "sensor_stamps_ns": START_NS + (np.arange(n) * (1e9 / FS)).astype(np.int64),
        "sensor": values,
        "joint_stamps_ns": stamps,
        "joint_position": q,
        "joint_velocity": v,
        "contact": contact,
        "ego": ego,
        "tap_onsets": onsets,
    }
