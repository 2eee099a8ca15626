"""The alternate-reality hand: drive trains, housing modes, friction, sensor, joint states, effects.

Everything here is this module's own invention (see the package docstring); numbers
are physical choices of this imaginary robot, not fitted to anything.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from egovib_research.altreality.motion import (
    GAP_MAX as GAP_MAX_M,
)
from egovib_research.altreality.motion import (
    GRIPPER_LIMIT,
    WRIST_LIMIT,
    plan_motion,
    reversal_events,
)
from egovib_ros.bag import Recording
from egovib_ros.core.timebase import NS_PER_S

FS = 3000.0  # accelerometer output rate (Hz)
JOINT_RATE = 1000.0  # joint_states rate (Hz)
# The PR2 hand's joint names (this generator is of the same hand, so a PR2 model reads it).
HAND_JOINTS = ("r_wrist_roll_joint", "r_gripper_joint")
EFFECTS = ("position", "coupling", "acceleration", "timing", "drift")
# wall-clock start of every recording (a real bag's epoch stamps)
START_NS = 1_726_000_000 * NS_PER_S

# --- drive trains -------------------------------------------------------------------------------
#: Wrist: BLDC motor -> timing belt (16:40 teeth) -> harmonic drive (50:1, 100-tooth flexspline).
WRIST_MOTOR_REV_PER_RAD = 2.5 * 50.0 / (2 * np.pi)
#: Gripper: brushed DC motor -> spur gears 14:41 -> ball screw 1.5 mm lead -> finger linkage 1.2.
GRIPPER_MOTOR_REV_PER_M = 1.0 / (1.5e-3 * 1.2 * 14.0 / 41.0)
#: Lines of each drive: (multiple of motor rev/s, amplitude at full speed [m/s^2], speed exponent).
WRIST_LINES = (
    (16.0, 0.55, 1.4),  # belt tooth mesh (955 Hz at full speed)
    (32.0, 0.18, 1.4),  # its second harmonic
    # motor cogging (12 slots x 8 poles): torque ripple, nearly speed-independent
    (24.0, 0.16, 0.3),
    (80.0, 0.30, 0.8),  # harmonic-drive tooth engagement (2 lobes x 100 teeth / belt 2.5)
    (2 * 1.432, 0.22, 1.0),  # wave-generator bearing outer-race ball pass, harmonics 2..6
    (3 * 1.432, 0.18, 1.0),
    (4 * 1.432, 0.16, 1.0),
    (5 * 1.432, 0.14, 1.0),
    (6 * 1.432, 0.12, 1.0),
)
GRIPPER_LINES = (
    (14.0, 0.50, 1.2),  # spur-gear mesh (14-tooth pinion)
    (28.0, 0.15, 1.2),  # its second harmonic
    (10.0, 0.32, 0.6),  # brush commutation (5 segments, 2 per turn)
    (2 * 1.605, 0.20, 1.0),  # ball-screw ball pass, harmonics 2..5
    (3 * 1.605, 0.17, 1.0),
    (4 * 1.605, 0.14, 1.0),
    (5 * 1.605, 0.12, 1.0),
)
#: Overall scale of the drive vibration at the housing input.
DRIVE_GAIN = 2.0
#: Lines fade out above this (the sensor's anti-alias filter), gone at ALIAS_STOP_HZ.
ALIAS_START_HZ, ALIAS_STOP_HZ = 1300.0, 1450.0
LINE_AM_SIGMA = 0.15  # slow load-dependent amplitude modulation (log-normal)
LINE_AM_HZ = 6.0
LINE_PHASE_WALK = 1.5  # rad / sqrt(s)

# --- friction: stick-slip impulses + grinding -------------------------------------------------
STICK_SLIP_RATE = (350.0, 550.0)  # impulses per second at full speed (wrist, gripper)
STICK_SLIP_SIZE = (0.9, 0.8)  # impulse strength scale
GRIND_RMS = (0.05, 0.06)  # broadband grinding at full speed (m/s^2)

# --- housing: structural modes that mix into all three axes ---------------------------------------
#: (frequency Hz, Q, sensor direction, participation of wrist drive, gripper drive, contact)
MODES = (
    (240.0, 6.0, (0.15, 0.95, 0.27), 1.00, 0.30, 0.9),
    (430.0, 9.0, (0.90, 0.20, -0.38), 0.70, 0.80, 0.8),
    (655.0, 5.0, (-0.30, 0.45, 0.84), 0.35, 1.00, 1.0),
    (1230.0, 12.0, (0.60, -0.60, 0.53), 0.50, 0.60, 0.6),
)
# stiff mount: direction, weight, high-pass corner (Hz)
DIRECT_PATH = ((0.5, 0.5, 0.7), 0.25, 100.0)

# --- sensor and background ----------------------------------------------------------------------
SENSOR_RANGE = 78.45  # +/- 8 g
SENSOR_BITS = 12
SENSOR_NOISE = 0.012  # m/s^2 rms per axis
SENSOR_LOWPASS_HZ = 1100.0  # the sensor's own first-order digital low-pass
GRAVITY = 9.81
HAND_TILT = 0.4  # rad between gravity and the roll axis: gravity turns with the wrist
MAINS_HARMONICS = ((3, 0.012), (5, 0.009), (7, 0.007), (9, 0.006), (11, 0.004), (13, 0.003))
MAINS_HZ = 50.0
FAN = (437.0, 2.0, 0.008)  # fan line: centre Hz, slow wander Hz, amplitude

# --- taps ----------------------------------------------------------------------------------------
TAP_DEAD_S = 0.25
TAP_FORCE = 7.0  # half-sine force pulse scale
TAP_CONTACT_MODE = (330.0, 4.0)

# --- effects -------------------------------------------------------------------------------------
SPOT_WIDTH_RAD = 0.22  # position "spot": Gaussian-like width of the tight spot
END_ZONE_M = 0.015  # position "end": rub within this distance of the closed end
RUB_RMS = 2.6  # rub broadband rms at full gripper speed deep in the zone (strength 1)
INTERMOD = 2.4  # coupling: intermodulation amplitude scale (strength 1)
CLICK = 5.0  # acceleration: backlash click scale (strength 1)
CLICK_ACC_REF = (30.0, 0.4)  # |acceleration| (rad/s^2, m/s^2) of a "typical" reversal
REVERSAL_THRESHOLD = (0.05, 0.0008)
#: Each effect's functional forms in this hand (the first ones are the original ones; a form
#: of None for position draws "spot" or "end" per seed as before).
EFFECT_FORMS = {
    "position": ("spot", "end", "closing"),
    "coupling": ("intermod", "signed"),
    "acceleration": ("clicks", "braking"),
    "timing": ("stamps", "filtered"),
    "drift": ("step", "wear"),
}
CLOSING_RUB_RMS = 1.6  # position "closing": rub rms at full closing speed (strength 1)
SIGNED_COUPLING = 1.6  # coupling "signed": log-gain of the wrist lines at full speeds (strength 1)
SIGNED_GRIND = 0.5  # coupling "signed": same-direction grinding rms at full speeds (strength 1)
BRAKING_RMS = 0.9  # acceleration "braking": broadband rms per unit deceleration / reference
BRAKING_ACC_REF = (20.0, 0.25)  # deceleration (rad/s^2, m/s^2) of reference
WEAR_RMS = 0.8  # drift "wear": grinding rms at full speed after 60 s (strength 1)


def resonator(freq_hz: float, q: float, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """Two-pole resonator with zeros at DC and Nyquist, unit gain at its peak."""
    r = np.exp(-np.pi * freq_hz / (q * fs))
    theta = 2 * np.pi * freq_hz / fs
    g = 1.0 - r
    return np.array([g, 0.0, -g]), np.array([1.0, -2 * r * np.cos(theta), r * r])


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _slow_noise(rng: np.random.Generator, n: int, bandwidth_hz: float, fs: float) -> np.ndarray:
    """Unit-rms low-pass Gaussian noise."""
    a = np.exp(-2 * np.pi * bandwidth_hz / fs)
    x = signal.lfilter([np.sqrt(1 - a * a)], [1.0, -a], rng.standard_normal(n))
    return x


@dataclass
class Drive:
    """One joint's drive train: lines whose frequencies follow the motor speed."""

    motor_rev_per_unit: float
    lines: tuple
    limit: float

    def line_signals(
        self, speed: np.ndarray, rng: np.random.Generator, fs: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-line (n, L) signals, their instantaneous frequencies and amplitudes."""
        n = len(speed)
        motor = speed * self.motor_rev_per_unit  # rev/s
        frac = np.clip(speed / self.limit, 0.0, 1.5)
        mults = np.array([line[0] for line in self.lines])
        amps = np.array([line[1] for line in self.lines])
        exps = np.array([line[2] for line in self.lines])
        freq = motor[:, None] * mults[None, :]
        taper = np.clip((ALIAS_STOP_HZ - freq) / (ALIAS_STOP_HZ - ALIAS_START_HZ), 0.0, 1.0)
        am = np.exp(
            LINE_AM_SIGMA
            * np.column_stack([_slow_noise(rng, n, LINE_AM_HZ, fs) for _ in self.lines])
            - 0.5 * LINE_AM_SIGMA**2
        )
        amplitude = amps[None, :] * frac[:, None] ** exps[None, :] * taper * am
        walk = np.cumsum(rng.standard_normal((n, len(self.lines))), axis=0) * (
            LINE_PHASE_WALK / np.sqrt(fs)
        )
        phase = (
            2 * np.pi * np.cumsum(freq, axis=0) / fs
            + walk
            + rng.uniform(0, 2 * np.pi, len(self.lines))
        )
        return amplitude * np.cos(phase), freq, amplitude


class AltHand:
    """Generates one recording of the alternate-reality hand (whole arrays, not streaming)."""

    def __init__(
        self,
        *,
        seed: int = 0,
        effects: dict | None = None,
        tap_rate_hz: float = 0.0,
        top_speed: float = 0.85,
        motion: str = "smooth",
        forms: dict | None = None,
        stick_slip: float = 1.0,
    ):
        self.seed = int(seed)
        self.stick_slip = float(stick_slip)  # scale on the stick-slip impulses (0: none)
        self.forms = dict(forms or {})
        for name, form in self.forms.items():
            if name not in EFFECT_FORMS or (form is not None and form not in EFFECT_FORMS[name]):
                raise ValueError(f"alternate reality: unknown form {form!r} of {name!r}")
        self.effects = {k: float(v) for k, v in (effects or {}).items() if v}
        unknown = set(self.effects) - set(EFFECTS)
        if unknown:
            raise ValueError(
                f"alternate reality: unknown effects {sorted(unknown)} (known: {list(EFFECTS)})"
            )
        self.tap_rate_hz = float(tap_rate_hz)
        self.top_speed = float(top_speed)
        self.motion = motion
        # Separate streams per ingredient: switching an effect on leaves everything else identical.
        names = (
            "motion",
            "wrist_lines",
            "gripper_lines",
            "friction",
            "sensor",
            "background",
            "taps",
            "joints",
            "effect_params",
            "effect_noise",
            "start",
        )
        seqs = np.random.SeedSequence([self.seed, 0xA17]).spawn(len(names))
        self.rng = {n: np.random.default_rng(s) for n, s in zip(names, seqs)}
        p = self.rng["effect_params"]
        # Effect parameters drawn whatever the effects are, so they do not shift other draws.
        self.variant = "spot" if p.random() < 0.5 else "end"
        if self.forms.get("position"):
            self.variant = self.forms["position"]
        self.spot_angle = float(p.uniform(-np.pi, np.pi))
        self.drift_centre_frac = float(p.uniform(0.1, 0.45))
        self.drift_width_s = float(p.uniform(1.5, 5.0))
        self.drift_sign = 1.0 if p.random() < 0.5 else -1.0
        self.wrist = Drive(WRIST_MOTOR_REV_PER_RAD, WRIST_LINES, WRIST_LIMIT)
        self.gripper = Drive(GRIPPER_MOTOR_REV_PER_M, GRIPPER_LINES, GRIPPER_LIMIT)

    # --- parts -----------------------------------------------------------------------------------
    def _friction(self, speed: np.ndarray, j: int) -> np.ndarray:
        """Stick-slip impulses (rate and size grow with speed) plus grinding broadband."""
        rng = self.rng["friction"]
        limit = (WRIST_LIMIT, GRIPPER_LIMIT)[j]
        frac = np.clip(speed / limit, 0.0, 1.5)
        counts = rng.poisson(STICK_SLIP_RATE[j] * frac**0.7 / FS)
        sizes = rng.lognormal(0.0, 0.7, len(speed)) * STICK_SLIP_SIZE[j] * (0.3 + frac)
        sizes *= self.stick_slip
        impulses = counts * sizes
        b, a = signal.butter(1, 600.0, fs=FS)
        grind = (
            signal.lfilter(b, a, rng.standard_normal(len(speed))) * GRIND_RMS[j] * frac**1.5 * 2.0
        )
        return impulses + grind

    def _background(self, n: int) -> np.ndarray:
        rng = self.rng["background"]
        t = np.arange(n) / FS
        out = np.zeros((n, 3))
        mains = MAINS_HZ + 0.03 * _slow_noise(rng, n, 0.2, FS)
        mains_phase = 2 * np.pi * np.cumsum(mains) / FS
        for k, amp in MAINS_HARMONICS:
            out += (amp * np.sin(k * mains_phase + rng.uniform(0, 2 * np.pi)))[:, None] * _unit(
                (0.3, 0.2, 0.93)
            )
        fan_f = FAN[0] + FAN[1] * _slow_noise(rng, n, 0.1, FS)
        out += (FAN[2] * np.sin(2 * np.pi * np.cumsum(fan_f) / FS))[:, None] * _unit(
            (0.8, -0.5, 0.3)
        )
        del t
        return out

    def _taps(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Tap force pulses (n,) and onset indices."""
        rng = self.rng["taps"]
        force = np.zeros(n)
        onsets = []
        if self.tap_rate_hz <= 0:
            return force, np.zeros(0, np.int64)
        i = int(rng.exponential(1.0 / self.tap_rate_hz) * FS)
        while i < n:
            width = int(round(rng.uniform(0.0006, 0.0012) * FS)) + 2
            pulse = (
                np.sin(np.pi * np.arange(1, width) / width) * TAP_FORCE * rng.lognormal(0.0, 0.25)
            )
            force[i : i + len(pulse)] += pulse[: n - i]
            onsets.append(i)
            i += int(
                (TAP_DEAD_S + rng.exponential(max(1.0 / self.tap_rate_hz - TAP_DEAD_S, 0.05))) * FS
            )
        return force, np.asarray(onsets, np.int64)

    def _clicks(self, velocity: np.ndarray, n: int) -> np.ndarray:
        """Backlash clicks at each joint's reversals: impact strength ~ sqrt(|a| / a_ref)."""
        out = np.zeros(n)
        s = self.effects.get("acceleration", 0.0)
        if not s or self._form("acceleration") != "clicks":
            return out
        rng = self.rng["effect_noise"]
        for j in range(2):
            idx, acc = reversal_events(velocity[:, j], FS, REVERSAL_THRESHOLD[j])
            idx = idx + int(0.002 * FS)  # the backlash gap closes ~2 ms after motion resumes
            keep = idx < n - 3
            size = (
                s
                * CLICK
                * DRIVE_GAIN
                * np.sqrt(acc[keep] / CLICK_ACC_REF[j])
                * rng.lognormal(0.0, 0.2, keep.sum())
            )
            for k, shape in enumerate((0.5, 1.0, 0.5)):
                np.add.at(out, idx[keep] + k, size * shape)
        return out

    def _intermodulation(self, w_freq, w_amp, g_freq, g_amp) -> np.ndarray:
        """Lines at f_w +- f_g for the main wrist and gripper lines
        (quadratic bearing stiffness)."""
        s = self.effects.get("coupling", 0.0)
        n = len(w_freq)
        if not s or self._form("coupling") != "intermod":
            return np.zeros(n)
        rng = self.rng["effect_noise"]
        out = np.zeros(n)
        ref = 0.3
        for i in (0, 3, 4):  # belt mesh, HD tooth, bearing
            for k in (0, 2, 3):  # spur mesh, commutation, ball pass
                amp = s * INTERMOD * DRIVE_GAIN * w_amp[:, i] * g_amp[:, k] / ref
                for sign in (1.0, -1.0):
                    f = np.abs(w_freq[:, i] + sign * g_freq[:, k])
                    taper = np.clip(
                        (ALIAS_STOP_HZ - f) / (ALIAS_STOP_HZ - ALIAS_START_HZ), 0.0, 1.0
                    )
                    phase = 2 * np.pi * np.cumsum(f) / FS + rng.uniform(0, 2 * np.pi)
                    out += amp * taper * np.cos(phase)
        return out

    def _form(self, effect: str) -> str:
        return self.forms.get(effect) or EFFECT_FORMS[effect][0]

    def _braking(self, velocity: np.ndarray, n: int) -> np.ndarray:
        """Broadband while a joint slows down (regenerative braking chatter), rms ~ deceleration."""
        out = np.zeros(n)
        s = self.effects.get("acceleration", 0.0)
        if not s or self._form("acceleration") != "braking":
            return out
        rng = self.rng["effect_noise"]
        for j in range(2):
            speed = np.abs(velocity[:, j])
            b, a = signal.butter(1, 15.0, fs=FS)
            rate = signal.filtfilt(b, a, np.gradient(speed) * FS)
            slowing = np.clip(-rate / BRAKING_ACC_REF[j], 0.0, 4.0)
            out += s * BRAKING_RMS * DRIVE_GAIN * slowing * rng.standard_normal(n)
        return out

    def _wear(self, speed: np.ndarray, n: int) -> np.ndarray:
        """Grinding added as the drives wear: grows linearly with time, while moving."""
        s = self.effects.get("drift", 0.0)
        if not s or self._form("drift") != "wear":
            return np.zeros(n)
        t = np.arange(n) / FS
        frac = np.clip(speed[:, 0] / WRIST_LIMIT, 0, 1.5) + np.clip(
            speed[:, 1] / GRIPPER_LIMIT, 0, 1.5
        )
        b, a = signal.butter(1, 800.0, fs=FS)
        noise = signal.lfilter(b, a, self.rng["effect_noise"].standard_normal(n))
        return s * WEAR_RMS * DRIVE_GAIN * 2.0 * frac * (t / 60.0) * noise

    def _drift_level(self, n: int) -> np.ndarray:
        s = self.effects.get("drift", 0.0)
        if not s or self._form("drift") != "step":
            return np.ones(n)
        t = np.arange(n) / FS
        centre = self.drift_centre_frac * n / FS
        step = 1.0 / (1.0 + np.exp(-(t - centre) / self.drift_width_s))
        return (1.0 + s) ** (self.drift_sign * step)

    def _housing(self, inputs: dict[str, np.ndarray]) -> np.ndarray:
        """Drive, contact and effect inputs through the housing modes into three sensor axes."""
        n = len(next(iter(inputs.values())))
        out = np.zeros((n, 3))
        for f, q, direction, w_wrist, w_grip, w_contact in MODES:
            u = (
                w_wrist * inputs["wrist"]
                + w_grip * inputs["gripper"]
                + w_contact * inputs["contact"]
                + 0.7 * inputs["shared"]
            )
            b, a = resonator(f, q, FS)
            out += signal.lfilter(b, a, u)[:, None] * _unit(direction)
        direction, weight, corner = DIRECT_PATH
        b, a = signal.butter(1, corner, btype="high", fs=FS)
        u = inputs["wrist"] + inputs["gripper"] + inputs["shared"]
        out += (weight * signal.lfilter(b, a, u))[:, None] * _unit(direction)
        return out

    # --- the recording ---------------------------------------------------------------------------
    def generate(self, duration_s: float) -> tuple[Recording, dict]:
        """`duration_s` seconds of the hand: the recording and its truth."""
        n = int(round(duration_s * FS))
        velocity, position, _ = plan_motion(
            duration_s, FS, self.rng["motion"], top_speed=self.top_speed, style=self.motion
        )
        speed = np.abs(velocity)
        wrist, gripper, lines = self._drives(velocity, position, n)
        shared = (
            self._intermodulation(*lines)
            + self._clicks(velocity, n)
            + self._braking(velocity, n)
            + self._wear(speed, n)
        )
        level = self._drift_level(n)
        force, onsets = self._taps(n)
        drive = {
            "wrist": wrist * level,
            "gripper": gripper * level,
            "shared": shared * level,
            "contact": np.zeros(n),
        }
        ego = self._housing(drive)
        contact = self._housing(
            {"wrist": np.zeros(n), "gripper": np.zeros(n), "shared": np.zeros(n), "contact": force}
        )
        b, a = resonator(*TAP_CONTACT_MODE, FS)
        contact += (0.6 * signal.lfilter(b, a, force))[:, None] * _unit((0.2, 0.3, 0.93))
        ego += self._background(n)
        theta = position[:, 0]
        ego += GRAVITY * np.column_stack(
            [
                np.sin(HAND_TILT) * np.cos(theta),
                -np.sin(HAND_TILT) * np.sin(theta),
                np.full(n, np.cos(HAND_TILT)),
            ]
        )
        raw = self._sensor(ego + contact)
        accel_stamps = START_NS + (np.arange(n, dtype=np.int64) * NS_PER_S) // int(FS)

        j_stamps, j_pos, j_vel = self._joint_states(position, n)
        rec = Recording(
            sensor_stamps_ns=accel_stamps,
            sensor=raw,
            joint_stamps_ns=j_stamps,
            joint_position=j_pos,
            joint_velocity=j_vel,
            joint_names=HAND_JOINTS,
            contact=contact,
            ego=ego,
        )
        return rec, self._truth(duration_s, accel_stamps[onsets])

    def _drives(self, velocity: np.ndarray, position: np.ndarray, n: int):
        """The wrist's and the gripper's drive signals (their lines and friction, with the
        coupling and position effects in force), and the lines' (frequencies, amplitudes)
        of both for the intermodulation."""
        speed = np.abs(velocity)
        w_sig, w_freq, w_amp = self.wrist.line_signals(speed[:, 0], self.rng["wrist_lines"], FS)
        g_sig, g_freq, g_amp = self.gripper.line_signals(speed[:, 1], self.rng["gripper_lines"], FS)
        wrist = DRIVE_GAIN * (w_sig.sum(axis=1) + self._friction(speed[:, 0], 0))
        gripper = DRIVE_GAIN * (g_sig.sum(axis=1) + self._friction(speed[:, 1], 1))
        fx = self.effects
        if "coupling" in fx and self._form("coupling") == "signed":
            # the wrist gear is loaded one way when the gripper moves the same way as the
            # wrist turns, relieved the other: its lines grow or shrink with the directions
            same = (
                np.sign(velocity[:, 0])
                * np.sign(velocity[:, 1])
                * np.clip(speed[:, 0] / WRIST_LIMIT, 0, 1.5)
                * np.clip(speed[:, 1] / GRIPPER_LIMIT, 0, 1.5)
            )
            wrist = wrist * np.exp(fx["coupling"] * SIGNED_COUPLING * same)
            b, a = signal.butter(1, 700.0, fs=FS)
            grind = signal.lfilter(b, a, self.rng["effect_noise"].standard_normal(n))
            wrist = wrist + fx["coupling"] * SIGNED_GRIND * DRIVE_GAIN * np.maximum(same, 0) * grind
        if "position" in fx and self.variant == "closing":
            # a rub anywhere along the travel, but only while the fingers close
            closing = np.clip(-velocity[:, 1] / GRIPPER_LIMIT, 0.0, 1.5)
            rub = self.rng["effect_noise"].standard_normal(n) * CLOSING_RUB_RMS * DRIVE_GAIN
            gripper = gripper + fx["position"] * closing * rub * (
                1.0 - np.clip(position[:, 1] / GAP_MAX_M, 0, 1)
            )
        elif "position" in fx:
            if self.variant == "spot":
                bump = np.exp((np.cos(position[:, 0] - self.spot_angle) - 1.0) / SPOT_WIDTH_RAD**2)
                wrist = wrist * (1.0 + fx["position"] * bump)
            else:
                depth = np.clip((END_ZONE_M - position[:, 1]) / END_ZONE_M, 0.0, 1.0)
                rub = (
                    self.rng["effect_noise"].standard_normal(n)
                    * RUB_RMS
                    * DRIVE_GAIN
                    * fx["position"]
                    * np.clip(speed[:, 1] / GRIPPER_LIMIT, 0, 1.5) ** 0.8
                    * depth
                )
                gripper = gripper + rub
        return wrist, gripper, (w_freq, w_amp, g_freq, g_amp)

    def _sensor(self, acceleration: np.ndarray) -> np.ndarray:
        """The accelerometer's reading of `acceleration` (n, 3): its noise, its low-pass and
        its quantisation over its range."""
        n = len(acceleration)
        raw = acceleration + self.rng["sensor"].standard_normal((n, 3)) * SENSOR_NOISE
        b, a = signal.butter(1, SENSOR_LOWPASS_HZ, fs=FS)
        raw = signal.lfilter(b, a, raw, axis=0, zi=signal.lfilter_zi(b, a)[:, None] * raw[:1])[0]
        lsb = 2 * SENSOR_RANGE / 2**SENSOR_BITS
        raw = (
            np.clip(np.round(raw / lsb), -(2 ** (SENSOR_BITS - 1)), 2 ** (SENSOR_BITS - 1) - 1)
            * lsb
        )
        return raw

    def _truth(self, duration_s: float, onsets_ns: np.ndarray) -> dict:
        """What the generator put into the run (effects, their forms and variants, taps)."""
        fx = self.effects
        truth = {
            "reality": "alt",
            "seed": self.seed,
            "effects": dict(self.effects),
            "motion": self.motion,
            "tap_onsets_ns": [int(x) for x in onsets_ns],
        }
        if "position" in fx:
            truth["position_variant"] = self.variant
            truth["position_angle_rad" if self.variant == "spot" else "position_end_zone_m"] = (
                round(self.spot_angle, 4) if self.variant == "spot" else END_ZONE_M
            )
        truth["forms"] = {k: self._form(k) for k in fx if k != "position"}
        if "drift" in fx and self._form("drift") == "step":
            truth["drift_step"] = {
                "centre_s": round(self.drift_centre_frac * duration_s, 3),
                "width_s": round(self.drift_width_s, 3),
                "direction": self.drift_sign,
            }
        return truth

    def _joint_states(self, position: np.ndarray, n: int):
        """1 kHz encoder readings with stamp jitter and dropped messages;
        velocity over two samples."""
        rng = self.rng["joints"]
        m = int(n / FS * JOINT_RATE) - 2
        t_true = np.arange(m) / JOINT_RATE + 0.00031 + rng.normal(0.0, 25e-6, m)
        t_true = np.clip(t_true, 0.0, (n - 1) / FS)
        idx = t_true * FS
        i0 = np.minimum(idx.astype(np.int64), n - 2)
        frac = (idx - i0)[:, None]
        pos = position[i0] * (1 - frac) + position[i0 + 1] * frac
        resolution = np.array(
            [2 * np.pi / (8192 * 125.0), 1.0 / (GRIPPER_MOTOR_REV_PER_M * 2000.0)]
        )
        enc = np.round(pos / resolution) * resolution
        vel = np.zeros_like(enc)
        vel[2:] = (enc[2:] - enc[:-2]) / (2.0 / JOINT_RATE)
        vel[:2] = vel[2]
        keep = rng.random(m) > 0.003
        timing = self.effects.get("timing", 0.0)
        if timing and self._form("timing") == "filtered":
            # the drive reports a velocity estimate through a first-order low-pass
            alpha = 1.0 - np.exp(-1.0 / (abs(timing) * JOINT_RATE))
            vel = signal.lfilter(
                [alpha], [1.0, alpha - 1.0], vel, axis=0, zi=vel[:1] * (1 - alpha)
            )[0]
            timing = 0.0
        stamps = START_NS + np.round((t_true + timing) * NS_PER_S).astype(np.int64)
        # The wrist reports its angle wrapped to (-pi, pi] like a continuous joint's
        # raw encoder count.
        enc[:, 0] = np.angle(np.exp(1j * enc[:, 0]))
        order = np.argsort(stamps[keep], kind="stable")
        return stamps[keep][order], enc[keep][order], vel[keep][order]


def simulate_alt_motion(
    *,
    duration_s: float = 120.0,
    effects: dict | None = None,
    seed: int = 0,
    tap_rate_hz: float = 0.0,
    top_speed: float = 0.85,
    motion: str = "smooth",
    forms: dict | None = None,
    stick_slip: float = 1.0,
) -> tuple[Recording, dict]:
    """One recording of random motion ("smooth" or task-like "segments")
    of the alternate-reality hand; `forms`: effect -> form (EFFECT_FORMS); `stick_slip`: a
    scale on the friction's stick-slip impulses (0: none; everything else the same)."""
    if duration_s <= 0:
        raise ValueError("duration_s must be > 0")
    return AltHand(
        seed=seed,
        effects=effects,
        tap_rate_hz=tap_rate_hz,
        top_speed=top_speed,
        motion=motion,
        forms=forms,
        stick_slip=stick_slip,
    ).generate(duration_s)


def effect_audibility_db(
    effect: str,
    strength: float,
    *,
    duration_s: float = 60.0,
    seed: int = 0,
    band_hz: tuple[float, float] = (150.0, 750.0),
) -> dict:
    """How loud an effect is: band-passed ego-vibration power with vs without it (same seed).

    Returns the overall power ratio (dB), and the ratio over the 20 ms frames where the
    effect changes the signal power by more than 10 % ("where it acts") with their share of time.
    """
    if effect == "timing":
        return {"overall_db": 0.0, "active_db": 0.0, "active_fraction": 0.0}
    with_fx, _ = simulate_alt_motion(duration_s=duration_s, effects={effect: strength}, seed=seed)
    base, _ = simulate_alt_motion(duration_s=duration_s, effects={}, seed=seed)
    sos = signal.butter(4, band_hz, btype="band", fs=FS, output="sos")
    a = signal.sosfilt(sos, with_fx.ego.sum(axis=1))
    b = signal.sosfilt(sos, base.ego.sum(axis=1))
    frame = int(0.02 * FS)
    k = len(a) // frame
    pa = np.mean(a[: k * frame].reshape(k, frame) ** 2, axis=1)
    pb = np.mean(b[: k * frame].reshape(k, frame) ** 2, axis=1)
    active = np.abs(pa / np.maximum(pb, 1e-12) - 1.0) > 0.1
    overall = 10 * np.log10(pa.sum() / pb.sum())
    act = 10 * np.log10(pa[active].sum() / pb[active].sum()) if active.any() else 0.0
    return {
        "overall_db": round(float(overall), 3),
        "active_db": round(float(act), 3),
        "active_fraction": round(float(active.mean()), 4),
    }
