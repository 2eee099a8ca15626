"""Simulator parameters (config/sim.yaml) and the effects SPEC of INTERFACES.md section 5."""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from egovib_ros.errors import ConfigError
from egovib_ros.robot import config_dir
from egovib_ros.sim.pr2 import EFFECT_NAMES


def default_config_path() -> Path:
    """config/sim.yaml of the package: the source tree's, or the installed share directory's
    (colcon/ament or pip install), found like the robot profiles (robot.config_dir)."""
    return config_dir() / "sim.yaml"


@dataclass
class JointVibration:
    """Ego-vibration of one joint (sim/hand.py): gear-mesh / commutation lines + friction
    broadband, through its own structural path onto its own sensor direction."""

    line_hz_per_unit: float  # gear-mesh fundamental (Hz) per joint speed unit (rad/s or m/s)
    line_orders: list[float]  # multiples of the fundamental (mesh harmonics, commutation)
    line_amps: list[float]  # amplitude (m/s^2) of each line at full speed, before the path
    line_speed_exponent: float  # line amplitude ~ speed_fraction ** exponent
    friction_coulomb: float  # friction broadband rms (m/s^2) once moving at all
    friction_viscous: float  # extra friction broadband rms at full speed (linear in speed)
    path_band_hz: list[float]  # structural band that carries this joint's vibration
    path_order: int  # Butterworth order of that band
    resonance_hz: float  # structural resonance near 1000 Hz (removed by the band-pass)
    resonance_q: float
    resonance_gain: float
    direction: list[float]  # sensor direction (unit vector, normalised on use)
    amp_jitter: float  # relative amplitude jitter (rms) of the lines
    amp_jitter_hz: float  # bandwidth of that jitter
    phase_jitter: float  # phase random walk of the lines (rad per sqrt(s))


def _joint_default(**own) -> JointVibration:
    """A PR2 hand joint's defaults: what both joints share, and `own` (what differs)."""
    return JointVibration(
        line_amps=[2.2, 1.1, 0.77],
        line_speed_exponent=0.7,
        friction_coulomb=0.01,
        friction_viscous=0.4,
        path_order=4,
        resonance_q=12.0,
        resonance_gain=0.3,
        amp_jitter=0.12,
        amp_jitter_hz=20.0,
        phase_jitter=3.0,
        **own,
    )


def _wrist_default() -> JointVibration:
    return _joint_default(
        line_hz_per_unit=60.0,
        line_orders=[1.0, 2.0, 3.0],
        path_band_hz=[150.0, 380.0],
        resonance_hz=980.0,
        direction=[1.0, 0.0, 0.0],
    )


def _gripper_default() -> JointVibration:
    return _joint_default(
        line_hz_per_unit=15000.0,
        line_orders=[1.0, 1.5, 2.0],
        path_band_hz=[480.0, 750.0],
        resonance_hz=1040.0,
        direction=[0.0, 1.0, 0.0],
    )


@dataclass
class SimParams:
    """All simulator parameters; round-trips to YAML (`load`/`save`/`to_dict`)."""

    # joints / controller / encoders
    controller_tau_s: float = 0.03
    encoder_resolution: list[float] = field(default_factory=lambda: [2.0e-5, 1.0e-6])
    gripper_start_m: float = 0.043
    joint_phase_s: float = 0.00017
    # accelerometer
    sensor_noise_rms: float = 0.002
    gravity_ms2: float = 9.81
    gravity_tilt_rad: float = 0.0
    zero_g_offset_ms2: list[float] = field(default_factory=lambda: [0.02, -0.03, 0.0025])
    hum_amps: list[float] = field(default_factory=lambda: [0.009] + [0.03] * 7 + [0.009] * 7)
    hum_direction: list[float] = field(default_factory=lambda: [0.0, 0.0, 1.0])
    # joints' vibration mechanisms
    wrist: JointVibration = field(default_factory=_wrist_default)
    gripper: JointVibration = field(default_factory=_gripper_default)
    # taps
    tap_peak_ms2: float = 3.4
    tap_peak_spread: float = 0.2
    tap_modes_hz: list[float] = field(default_factory=lambda: [230.0, 410.0, 640.0])
    tap_mode_amps: list[float] = field(default_factory=lambda: [1.0, 0.8, 0.5])
    tap_mode_decay_s: list[float] = field(default_factory=lambda: [0.008, 0.005, 0.004])
    tap_length_s: float = 0.03
    tap_dead_time_s: float = 0.25
    tap_direction: list[float] = field(default_factory=lambda: [0.35, 0.35, 0.87])
    # effects: parameters of each effect's term (strengths come from the SPEC)
    position_phase_rad: float = 0.6
    coupling_gain: float = 1.6
    acceleration_gain: float = 1.5
    drift_period_s: float = 60.0
    #: Functional form of each effect (EFFECT_FORMS; a missing effect takes its first form).
    effect_forms: dict[str, str] = field(default_factory=dict)
    #: Forms' own parameters: rub rms on the gripper path at full closing speed (position
    #: "closing_rub"), log-gain of the signed wrist-line coupling, gain per unit of speeding
    #: up relative to vmax/controller_tau_s (acceleration "speeding_up"), wear broadband rms
    #: at full speed after drift_period_s (drift "additive"), warm-up time constant.
    closing_rub_gain: float = 6.0
    signed_coupling_gain: float = 0.6
    speeding_up_gain: float = 2.0
    wear_gain: float = 10.0
    warmup_tau_s: float = 20.0
    effects: dict[str, float] = field(default_factory=dict)

    # --- YAML round trip -------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, source: str = "sim params") -> "SimParams":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"{source}: unknown parameter(s) {', '.join(unknown)}")
        kwargs = dict(data)
        joint_fields = {f.name for f in dataclasses.fields(JointVibration)}
        for name, default in (("wrist", _wrist_default), ("gripper", _gripper_default)):
            if name in kwargs:
                sub = kwargs[name] or {}
                if not isinstance(sub, dict) or set(sub) - joint_fields:
                    raise ConfigError(
                        f"{source}: {name}: unknown field(s) {sorted(set(sub) - joint_fields)}"
                    )
                kwargs[name] = JointVibration(**{**dataclasses.asdict(default()), **sub})
        if "effects" in kwargs:
            kwargs["effects"] = validate_effects(kwargs["effects"] or {}, source=source)
        if "effect_forms" in kwargs:
            kwargs["effect_forms"] = validate_forms(kwargs["effect_forms"] or {}, source=source)
        try:
            return cls(**kwargs)
        except TypeError as exc:
            raise ConfigError(f"{source}: {exc}") from None

    @classmethod
    def load(cls, path: str | os.PathLike | None = None) -> "SimParams":
        """Parameters from a YAML file (default: the package's config/sim.yaml; a missing
        default is an error, not a silent fall-back to built-in values)."""
        if path is None:
            path = default_config_path()
            if not path.is_file():
                raise ConfigError(
                    f"{path}: the package's simulator parameters are missing; reinstall the package"
                )
        path = Path(path)
        try:
            data = yaml.safe_load(path.read_text())
        except OSError as exc:
            raise ConfigError(f"{path}: cannot read ({exc.strerror})") from None
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: expected a mapping of parameters")
        data = data.get("sim", data)
        return cls.from_dict(data, source=str(path))

    def save(self, path: str | os.PathLike) -> None:
        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))


def validate_effects(effects: dict[str, Any], *, source: str = "effects") -> dict[str, float]:
    """Check names against the vocabulary; drop zero strengths (zero = effect off)."""
    out: dict[str, float] = {}
    for name, value in effects.items():
        if name == "none":
            continue
        if name not in EFFECT_NAMES:
            raise ConfigError(
                f"{source}: unknown effect {name!r} (known: {', '.join(EFFECT_NAMES)}, none)"
            )
        try:
            strength = float(value)
        except (TypeError, ValueError):
            raise ConfigError(
                f"{source}: effect {name} has non-numeric strength {value!r}"
            ) from None
        if strength != strength or abs(strength) == float("inf"):
            raise ConfigError(f"{source}: effect {name} strength must be finite")
        if strength != 0.0:
            out[name] = strength
    return out


# Effect strengths the simulator models sensibly (sim/hand.py):
# position scales a source by 1 + s cos(...), so |s| <= 1 keeps it non-negative;
# coupling/acceleration/drift are gains (>= 0); timing is a clock offset in seconds.
EFFECT_RANGES: dict[str, tuple[float, float]] = {
    "position": (-1.0, 1.0),
    "coupling": (0.0, 100.0),
    "acceleration": (0.0, 100.0),
    "timing": (-1.0, 1.0),
    "drift": (0.0, 100.0),
}


def check_effects(effects: dict[str, float], *, source: str = "--effects") -> dict[str, float]:
    """Raise ConfigError unless every strength is finite and within EFFECT_RANGES."""
    for name, strength in effects.items():
        if not math.isfinite(strength):
            raise ConfigError(f"{source}: {name}={strength!r}: strength must be finite")
        low, high = EFFECT_RANGES.get(name, (-math.inf, math.inf))
        if not low <= strength <= high:
            unit = " s" if name == "timing" else ""
            raise ConfigError(f"{source}: {name}={strength:g} is outside [{low:g}, {high:g}]{unit}")
    return effects


#: The functional forms each effect can take in the simulator (the first is the default):
#: which mechanism carries it (multiplicative gain or added power, tonal or broadband,
#: signed by the direction of travel or not).
EFFECT_FORMS: dict[str, tuple[str, ...]] = {
    "position": ("gain", "closing_rub"),
    "coupling": ("broadband", "signed"),
    "acceleration": ("broadband", "speeding_up"),
    "timing": ("stamps", "filtered"),
    "drift": ("linear", "warmup", "additive"),
}


def validate_forms(forms: dict[str, Any], *, source: str = "effect_forms") -> dict[str, str]:
    """Check each effect's form against EFFECT_FORMS."""
    out: dict[str, str] = {}
    for name, form in forms.items():
        if name not in EFFECT_FORMS:
            raise ConfigError(f"{source}: effect_forms: unknown effect {name!r}")
        if form not in EFFECT_FORMS[name]:
            raise ConfigError(
                f"{source}: effect_forms: {name} has no form {form!r} "
                f"(known: {', '.join(EFFECT_FORMS[name])})"
            )
        out[name] = str(form)
    return out


def parse_effects(spec: str | None) -> dict[str, float]:
    """Parse the SPEC `name=strength,...` (INTERFACES.md section 3); '' / None / 'none':
    no effect."""
    if spec is None or not spec.strip():
        return {}
    raw: dict[str, str] = {}
    for item in spec.split(","):
        item = item.strip()
        if not item or item == "none":
            continue
        name, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"--effects {spec!r}: item {item!r} is not name=strength")
        name = name.strip()
        if name in raw:
            raise ConfigError(f"--effects {spec!r}: effect {name} given twice")
        raw[name] = value.strip()
    return validate_effects(raw, source=f"--effects {spec!r}")


def format_effects(effects: dict[str, float]) -> str:
    """Inverse of parse_effects."""
    return ",".join(f"{k}={v:g}" for k, v in effects.items()) or "none"
