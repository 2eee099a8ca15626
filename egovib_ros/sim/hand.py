"""Streaming simulator of the PR2 right hand: joints, encoders, ego-vibration, taps, accelerometer.

Base model (obeys the paper's assumptions exactly):

* Joints: a first-order velocity controller (`controller_tau_s`) follows the commands;
  the wrist rolls freely, the gripper gap (0..0.086 m) reverses before a limit (speed
  kept, sign flipped). Joint states at 1 kHz on their own clock phase vs. the 3 kHz
  accelerometer: encoder positions quantised to `encoder_resolution`, velocity their
  first-order difference, as the PR2 reports it.
* Ego-vibration of joint j (speed fraction s_j = |v_j| / vmax_j): gear-mesh lines
  sum_l a_l s_j^e (1 + jitter) sin(phi_l), phi_l' = 2 pi o_l r_j |v_j| + a phase random
  walk, plus friction broadband (c_j (1 - exp(-s_j / 0.02)) + k_j s_j) w(t); through the
  joint's own structural path (a Butterworth band of modes + a resonance near 1000 Hz)
  onto its own sensor direction. The wrist's band is the lower part of 150-750 Hz, the
  gripper's the upper, so their spectra overlap little and superpose (paper Eq. 6).
* Accelerometer: gravity + idle hum + vibrations + contact + noise, quantised to 10 bits
  over +/-78.5 m/s^2 with clipping. The hum is periodic in 32 samples (lines on multiples
  of fs/32 = 93.75 Hz): a stationary background with a steady spectrum.
* Taps: solenoid-like transients (a few decaying modes), Poisson onsets with a dead
  time ("random") or evenly spaced ("periodic").

Effects (INTERFACES.md section 5), strength s; absent or 0 = bit-identical base. Each
has functional forms (`effect_forms` in the params, EFFECT_FORMS; docs/gap.md "Effect
forms"), the first the default: position `gain` (wrist x (1 + s cos(theta_w -
position_phase_rad)), gripper x (1 + s (gap / 0.086 - 0.5))) or `closing_rub`;
coupling `broadband` (on the gripper path, rms s coupling_gain s_w s_g) or `signed`;
acceleration `broadband` (rms s acceleration_gain |a_j| / (vmax_j / controller_tau_s))
or `speeding_up`; timing `stamps` (joint stamps = true time + s) or `filtered` (the
reported velocity low-passed with time constant |s|); drift `linear` (x (1 + s t /
drift_period_s)), `warmup` or `additive` (`_with_effects`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from egovib_ros.bag.recording import Recording
from egovib_ros.core.filters import lfilter_carried, sosfilt_carried
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import ConfigError
from egovib_ros.sim.params import EFFECT_FORMS, JointVibration, SimParams, validate_effects
from egovib_ros.sim.pr2 import (
    ACCEL_BITS,
    ACCEL_RANGE_MS2,
    ACCEL_RATE_HZ,
    BAND_HZ,
    BAND_ORDER,
    GRIPPER_GAP_RANGE_M,
    JOINT_NAMES,
    JOINT_RATE_HZ,
    MAX_SPEED,
)

LSB_MS2 = 2.0 * ACCEL_RANGE_MS2 / 2**ACCEL_BITS
HUM_PERIOD = 32  # samples: hum lines on multiples of fs/32


def quantise(accel: np.ndarray) -> np.ndarray:
    """10-bit quantisation over +/-78.5 m/s^2 with clipping (BMA150 at +/-8 g)."""
    half = 2 ** (ACCEL_BITS - 1)
    return np.clip(np.round(accel / LSB_MS2), -half, half - 1) * LSB_MS2


@dataclass
class SimChunk(Recording):
    """One step of the simulator: a time slice of the hand (raw quantised sensor, joint
    states as reported, ground-truth contact and ego parts; the scenarios add the commands)
    and what only the simulator knows."""

    tap_onsets_ns: np.ndarray | None = None  # (t,) accel stamps at which taps start
    true_velocity: np.ndarray | None = None  # (n, J) joint velocities at the accel samples
    true_position: np.ndarray | None = None  # (n, J)


def _unit(v) -> np.ndarray:
    v = np.asarray(v, float)
    norm = np.linalg.norm(v)
    if norm == 0:
        raise ConfigError("sim params: a direction vector is zero")
    return v / norm


class _JointSource:
    """Vibration source + structural path of one joint, with carried filter states."""

    def __init__(
        self, p: JointVibration, vmax: float, streams: list[np.random.Generator], fs: float
    ):
        # one generator per kind of draw, so that chunking never reorders draws
        self.p, self.vmax, self.fs = p, vmax, fs
        rng_start, self.rng_walk, self.rng_jitter, self.rng_friction = streams
        self.orders = np.asarray(p.line_orders, float)
        self.amps = np.asarray(p.line_amps, float)
        if self.orders.shape != self.amps.shape:
            raise ConfigError("sim params: line_orders and line_amps differ in length")
        # line phases: start phases, integrated sample by sample (lfilter keeps chunking exact)
        self.phase_zi = rng_start.uniform(0, 2 * np.pi, (1, len(self.orders)))
        alpha = 1.0 - np.exp(-2 * np.pi * p.amp_jitter_hz / fs)
        self.jit_ba = (np.array([alpha]), np.array([1.0, alpha - 1.0]))
        self.jit_scale = p.amp_jitter * np.sqrt((2.0 - alpha) / alpha)  # unit-rms low-pass noise
        self.jit_zi = np.zeros(1)
        self.band_sos = signal.butter(
            p.path_order, p.path_band_hz, btype="band", fs=fs, output="sos"
        )
        self.band_zi = np.zeros((self.band_sos.shape[0], 2))
        b, a = signal.iirpeak(p.resonance_hz, p.resonance_q, fs=fs)
        self.res_ba = (b * p.resonance_gain, a)
        self.res_zi = np.zeros(2)
        self.direction = _unit(p.direction)

    def source(self, speed: np.ndarray) -> np.ndarray:
        """Lines + friction of the base model for absolute speeds (n,)."""
        p, n = self.p, len(speed)
        frac = speed / self.vmax
        # phase increments: line frequency (scales with speed) + random walk
        walk = self.rng_walk.standard_normal((n, len(self.orders))) * (
            p.phase_jitter / np.sqrt(self.fs)
        )
        inc = (2 * np.pi / self.fs) * np.outer(speed * p.line_hz_per_unit, self.orders) + walk
        phases, self.phase_zi = lfilter_carried([1.0], [1.0, -1.0], inc, self.phase_zi, axis=0)
        jit, self.jit_zi = lfilter_carried(
            *self.jit_ba, self.rng_jitter.standard_normal(n) * self.jit_scale, self.jit_zi
        )
        lines = (
            (np.sin(phases) * self.amps).sum(axis=1) * (frac**p.line_speed_exponent) * (1.0 + jit)
        )
        friction = (
            p.friction_coulomb * (1.0 - np.exp(-frac / 0.02)) + p.friction_viscous * frac
        ) * self.rng_friction.standard_normal(n)
        return lines + friction

    def path(self, src: np.ndarray) -> np.ndarray:
        """Structural path: band of modes + resonance near 1000 Hz (states carried)."""
        band, self.band_zi = sosfilt_carried(self.band_sos, src, self.band_zi)
        res, self.res_zi = lfilter_carried(*self.res_ba, src, self.res_zi)
        return band + res


class HandSimulator:
    """Streaming simulated hand; `step(n)` advances n accelerometer samples (3 kHz).

    Chunked stepping equals one long step for the same seed and commands.
    """

    def __init__(
        self,
        params: SimParams | None = None,
        *,
        effects: dict | None = None,
        seed: int = 0,
        tap_rate_hz: float = 0.0,
        tap_mode: str = "random",
        start_ns: int = 0,
    ):
        self.params = p = params if params is not None else SimParams.load()
        self.effects = validate_effects({**p.effects, **(effects or {})})
        if tap_mode not in ("random", "periodic"):
            raise ConfigError(f"tap_mode must be random or periodic, not {tap_mode!r}")
        if tap_rate_hz < 0:
            raise ConfigError("tap_rate_hz must be >= 0")
        if not 0.0 <= p.joint_phase_s < 1.0 / ACCEL_RATE_HZ:
            raise ConfigError("sim params: joint_phase_s must be in [0, 1/3000) s")
        self.seed, self.tap_rate_hz, self.tap_mode = int(seed), float(tap_rate_hz), tap_mode
        self.fs, self.dt = ACCEL_RATE_HZ, 1.0 / ACCEL_RATE_HZ
        self.start_ns = int(start_ns)
        self.vmax = np.asarray(MAX_SPEED, float)
        self.n_joints = len(self.vmax)
        # Children of a SeedSequence depend only on their index: streams added for the
        # effect forms (13 on) leave the first 13 as they were.
        streams = [np.random.default_rng(s) for s in np.random.SeedSequence(self.seed).spawn(16)]
        (self.rng_sensor, self.rng_taps, self.rng_acc_w, self.rng_acc_g, self.rng_coupling) = (
            streams[8:13]
        )
        self.rng_rub, self.rng_wear_w, self.rng_wear_g = streams[13:16]
        self.forms = {
            name: p.effect_forms.get(name, forms[0]) for name, forms in EFFECT_FORMS.items()
        }
        self.vel_filter_zi: np.ndarray | None = None
        self.joints = [
            _JointSource(p.wrist, self.vmax[0], streams[0:4], self.fs),
            _JointSource(p.gripper, self.vmax[1], streams[4:8], self.fs),
        ]
        # controller: v[k] = alpha * target[k] + (1 - alpha) v[k-1]
        alpha = 1.0 - np.exp(-self.dt / p.controller_tau_s)
        self.ctrl_ba = (np.array([alpha]), np.array([1.0, alpha - 1.0]))
        self.ctrl_zi = [np.zeros(1) for _ in range(self.n_joints)]
        self.position = np.array([0.0, p.gripper_start_m])
        self.velocity = np.zeros(self.n_joints)
        self.gripper_dir = 1.0
        self.command = np.zeros(self.n_joints)
        self.index = 0  # next accel sample index
        res = np.asarray(p.encoder_resolution, float)
        self.enc_res = res
        self.last_enc = np.round(self.position / res) * res
        self.joint_frac = p.joint_phase_s * self.fs  # joint sample m sits at accel index 3m + frac
        self.joint_offset_ns = int(round(p.joint_phase_s * NS_PER_S))
        # hum: exactly periodic in the sample index
        harmonics = np.arange(1, len(p.hum_amps) + 1)
        k = np.arange(HUM_PERIOD)
        if len(p.hum_amps) > HUM_PERIOD // 2 - 1:
            raise ConfigError(
                f"sim params: at most {HUM_PERIOD // 2 - 1} hum_amps "
                "(harmonics of fs/32 below Nyquist)"
            )
        # equal phases: each odd rfft bin then gets the in-phase leakage of both neighbouring lines
        self.hum_period = np.sin(2 * np.pi * np.outer(k, harmonics) / HUM_PERIOD) @ np.asarray(
            p.hum_amps, float
        )
        self.hum_dir = _unit(p.hum_direction)
        self.zero_g_offset = np.asarray(p.zero_g_offset_ms2, float).reshape(3)
        # taps
        self.tap_dir = _unit(p.tap_direction)
        self.tap_len = int(round(p.tap_length_s * self.fs))
        self.tap_scale = p.tap_peak_ms2 / self._nominal_tap_peak()
        self.active_taps: list[tuple[int, float, np.ndarray]] = []
        self.next_tap = self._first_tap_index() if self.tap_rate_hz > 0 else None

    # --- commands ------------------------------------------------------------
    def set_command(self, velocity) -> None:
        """Target joint velocities [wrist rad/s, gripper m/s], held until the next command."""
        v = np.asarray(velocity, float).reshape(-1)
        if v.shape != (self.n_joints,) or not np.all(np.isfinite(v)):
            raise ConfigError(
                f"command must be {self.n_joints} finite velocities, got {velocity!r}"
            )
        self.command = v

    def stamps_ns(self, indices: np.ndarray) -> np.ndarray:
        """Accelerometer stamps of sample indices."""
        indices = np.asarray(indices, np.int64)
        return self.start_ns + (indices * NS_PER_S + int(self.fs) // 2) // int(self.fs)

    # --- taps -------------------------------------------------------------------
    def _tap_waveform(self, t: np.ndarray, freq_scale: np.ndarray) -> np.ndarray:
        p = self.params
        out = np.zeros_like(t)
        for f, a, tau, fsc in zip(p.tap_modes_hz, p.tap_mode_amps, p.tap_mode_decay_s, freq_scale):
            out += a * np.exp(-t / tau) * np.sin(2 * np.pi * f * fsc * t)
        return out

    def _nominal_tap_peak(self) -> float:
        t = np.arange(self.tap_len * 4) / self.fs
        wave = self._tap_waveform(t, np.ones(len(self.params.tap_modes_hz)))
        wave[self.tap_len :] = 0.0
        sos = signal.butter(BAND_ORDER, BAND_HZ, btype="band", fs=self.fs, output="sos")
        return float(np.max(np.abs(signal.sosfilt(sos, wave * self.tap_dir.sum()))))

    def _interval(self) -> int:
        p = self.params
        if self.tap_mode == "periodic":
            return max(1, int(round(self.fs / self.tap_rate_hz)))
        mean_free = max(1.0 / self.tap_rate_hz - p.tap_dead_time_s, 0.02)
        return int(round((p.tap_dead_time_s + self.rng_taps.exponential(mean_free)) * self.fs))

    def _first_tap_index(self) -> int:
        if self.tap_mode == "periodic":
            return int(round(0.5 * self.fs / self.tap_rate_hz))
        return self._interval()

    def _new_tap(self, onset: int) -> tuple[int, float, np.ndarray]:
        p = self.params
        z = self.rng_taps.standard_normal(1 + len(p.tap_modes_hz))
        amp = self.tap_scale * np.exp(p.tap_peak_spread * z[0] - 0.5 * p.tap_peak_spread**2)
        return onset, float(amp), 1.0 + 0.03 * np.clip(z[1:], -3, 3)

    def _contact(self, i0: int, n: int) -> tuple[np.ndarray, list[int]]:
        onsets = []
        while self.next_tap is not None and self.next_tap < i0 + n:
            self.active_taps.append(self._new_tap(self.next_tap))
            onsets.append(self.next_tap)
            self.next_tap += self._interval()
        contact_1d = np.zeros(n)
        keep = []
        for onset, amp, fsc in self.active_taps:
            a, b = max(onset, i0), min(onset + self.tap_len, i0 + n)
            if b > a:
                t = (np.arange(a, b) - onset) / self.fs
                contact_1d[a - i0 : b - i0] += amp * self._tap_waveform(t, fsc)
            if onset + self.tap_len > i0 + n:
                keep.append((onset, amp, fsc))
        self.active_taps = keep
        return contact_1d[:, None] * self.tap_dir, onsets

    # --- joints -------------------------------------------------------------------
    def _kinematics(self, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True velocities and positions (n, J) at the accel samples; gripper reverses before
        its limits."""
        n = len(targets)
        vel = np.empty((n, self.n_joints))
        pos = np.empty((n, self.n_joints))
        integ = (np.array([self.dt]), np.array([1.0, -1.0]))
        vel[:, 0], self.ctrl_zi[0] = lfilter_carried(*self.ctrl_ba, targets[:, 0], self.ctrl_zi[0])
        pos[:, 0], _ = lfilter_carried(*integ, vel[:, 0], [self.position[0]])
        lo, hi = GRIPPER_GAP_RANGE_M
        tau = self.params.controller_tau_s
        start = 0
        while start < n:
            seg_target = self.gripper_dir * targets[start:, 1]
            v, zf = lfilter_carried(*self.ctrl_ba, seg_target, self.ctrl_zi[1])
            p, _ = lfilter_carried(
                *integ, v, [self.position[1] if start == 0 else pos[start - 1, 1]]
            )
            stop = p + v * tau  # where the gap would come to rest
            hit = np.flatnonzero(
                ((seg_target > 0) & (stop >= hi)) | ((seg_target < 0) & (stop <= lo))
            )
            end = n - start if hit.size == 0 else hit[0] + 1
            vel[start : start + end, 1] = v[:end]
            pos[start : start + end, 1] = p[:end]
            if hit.size == 0:
                self.ctrl_zi[1] = zf
            else:
                _, self.ctrl_zi[1] = lfilter_carried(
                    *self.ctrl_ba, seg_target[:end], self.ctrl_zi[1]
                )
                self.gripper_dir = -self.gripper_dir
            start += end
        return vel, pos

    def _joint_states(self, i0: int, n: int, pos: np.ndarray, prev_pos: np.ndarray):
        """Encoder readings at 1 kHz: sample m lies between accel samples 3m and 3m+1."""
        m0 = -((1 - i0) // 3)  # first m with 3m + 1 >= i0
        m1 = (i0 + n - 2) // 3 + 1  # one past the last m with 3m + 1 <= i0 + n - 1
        m = np.arange(m0, max(m0, m1), dtype=np.int64)
        ext = np.vstack([prev_pos[None, :], pos])
        lo = ext[3 * m - i0 + 1]
        hi = ext[3 * m - i0 + 2]
        true = lo + self.joint_frac * (hi - lo)
        enc = np.round(true / self.enc_res) * self.enc_res
        prev = np.vstack([self.last_enc[None, :], enc[:-1]]) if len(m) else enc
        velocity = (enc - prev) * JOINT_RATE_HZ
        if len(m):
            self.last_enc = enc[-1]
        stamps = self.start_ns + self.joint_offset_ns + m * (NS_PER_S // int(JOINT_RATE_HZ))
        timing = self.effects.get("timing", 0.0)
        if timing and self.forms["timing"] == "stamps":
            stamps = stamps + int(round(timing * NS_PER_S))
        elif timing and len(m):  # the reported velocity through a first-order low-pass
            alpha = 1.0 - np.exp(-1.0 / (abs(timing) * JOINT_RATE_HZ))
            if self.vel_filter_zi is None:
                self.vel_filter_zi = velocity[0] * (1.0 - alpha)
            velocity, zf = lfilter_carried(
                [alpha], [1.0, alpha - 1.0], velocity, self.vel_filter_zi[None, :], axis=0
            )
            self.vel_filter_zi = zf[0]
        return stamps, enc, velocity

    # --- main step ----------------------------------------------------------------
    def step(self, n: int, commands: np.ndarray | None = None) -> SimChunk:
        """Advance n accelerometer samples.

        `commands` (n, J) gives a per-sample target velocity; without it the last
        `set_command` value is held.
        """
        n = int(n)
        if n < 0:
            raise ConfigError("step: n must be >= 0")
        p = self.params
        i0 = self.index
        idx = np.arange(i0, i0 + n, dtype=np.int64)
        if commands is None:
            targets = np.broadcast_to(self.command, (n, self.n_joints))
        else:
            targets = np.asarray(commands, float).reshape(n, self.n_joints)
            if n:
                self.command = targets[-1].copy()
        prev_vel, prev_pos = self.velocity.copy(), self.position.copy()
        vel, pos = self._kinematics(targets)
        if n:
            self.velocity, self.position = vel[-1].copy(), pos[-1].copy()
        speed = np.abs(vel)
        frac = speed / self.vmax
        t = idx / self.fs

        ego = np.zeros((n, 3))
        for j, joint in enumerate(self.joints):
            src = self._with_effects(j, joint.source(speed[:, j]), vel, frac, pos, prev_vel[j], t)
            ego += joint.path(src)[:, None] * joint.direction
        ego += self.hum_period[idx % HUM_PERIOD][:, None] * self.hum_dir
        tilt = p.gravity_tilt_rad
        if tilt:
            ego += p.gravity_ms2 * np.column_stack(
                [
                    np.sin(tilt) * np.cos(pos[:, 0]),
                    np.sin(tilt) * np.sin(pos[:, 0]),
                    np.full(n, np.cos(tilt)),
                ]
            )
        else:
            ego[:, 2] += p.gravity_ms2
        contact, onsets = self._contact(i0, n)
        noise = self.rng_sensor.standard_normal((n, 3)) * p.sensor_noise_rms
        raw = quantise(ego + contact + noise + self.zero_g_offset)
        j_stamps, j_pos, j_vel = self._joint_states(i0, n, pos, prev_pos)
        self.index += n
        return SimChunk(
            sensor_stamps_ns=self.stamps_ns(idx),
            sensor=raw,
            contact=contact,
            ego=ego,
            joint_stamps_ns=j_stamps,
            joint_position=j_pos,
            joint_velocity=j_vel,
            joint_names=JOINT_NAMES,
            tap_onsets_ns=self.stamps_ns(np.asarray(onsets, np.int64)),
            true_velocity=vel,
            true_position=pos,
        )

    def _with_effects(
        self,
        j: int,
        src: np.ndarray,
        vel: np.ndarray,
        frac: np.ndarray,
        pos: np.ndarray,
        prev_vel_j: float,
        t: np.ndarray,
    ) -> np.ndarray:
        """Joint j's vibration source (n,) with the effects in force: position, acceleration,
        coupling and drift, each in its form (`forms`); random parts from each effect's own
        generator, so that an effect added leaves the others' draws unchanged."""
        p, fx, forms = self.params, self.effects, self.forms
        n = len(src)
        if "position" in fx and forms["position"] == "gain":
            s = fx["position"]
            gain = (
                (1.0 + s * np.cos(pos[:, 0] - p.position_phase_rad))
                if j == 0
                else (1.0 + s * (pos[:, 1] / GRIPPER_GAP_RANGE_M[1] - 0.5))
            )
            src = src * gain
        if "position" in fx and forms["position"] == "closing_rub" and j == 1:
            closing = (vel[:, 1] < 0) * frac[:, 1]
            depth = np.clip(1.0 - pos[:, 1] / GRIPPER_GAP_RANGE_M[1], 0.0, 1.0)
            src = src + fx["position"] * p.closing_rub_gain * closing * depth * (
                self.rng_rub.standard_normal(n)
            )
        if "acceleration" in fx:
            dv = np.diff(np.concatenate([[prev_vel_j], vel[:, j]])) * self.fs
            a_ref = self.vmax[j] / p.controller_tau_s
            if forms["acceleration"] == "broadband":
                rng = self.rng_acc_w if j == 0 else self.rng_acc_g
                src = src + fx["acceleration"] * p.acceleration_gain * (
                    np.abs(dv) / a_ref
                ) * rng.standard_normal(n)
            else:  # speeding up: d|v|/dt > 0
                up = np.maximum(np.sign(vel[:, j]) * dv, 0.0) / a_ref
                src = src * (1.0 + fx["acceleration"] * p.speeding_up_gain * up)
        if "coupling" in fx and forms["coupling"] == "broadband" and j == 1:
            src = src + fx["coupling"] * p.coupling_gain * frac[:, 0] * frac[
                :, 1
            ] * self.rng_coupling.standard_normal(n)
        if "coupling" in fx and forms["coupling"] == "signed" and j == 0:
            same = np.sign(vel[:, 0]) * np.sign(vel[:, 1]) * frac[:, 0] * frac[:, 1]
            src = src * np.exp(fx["coupling"] * p.signed_coupling_gain * same)
        if "drift" in fx:
            if forms["drift"] == "linear":
                src = src * (1.0 + fx["drift"] * t / p.drift_period_s)
            elif forms["drift"] == "warmup":
                # twice the strength: after warm-up the level has changed as much as the
                # linear form's after two drift periods
                src = src * (1.0 + 2.0 * fx["drift"] * (1.0 - np.exp(-t / p.warmup_tau_s)))
            else:  # additive wear broadband
                rng = self.rng_wear_w if j == 0 else self.rng_wear_g
                src = src + fx["drift"] * p.wear_gain * frac[:, j] * (
                    t / p.drift_period_s
                ) * rng.standard_normal(n)
        return src
