"""Robot profiles (INTERFACES.md section 1b, schema ``egovib.robot/1``).

Everything robot-specific - the Imu topic and field cleaned and its nominal rate, the
joints that key the noise and how fast they go, the velocity grid, the block processing
settings - comes from a profile. The PR2 right hand (``config/robots/pr2_right_hand.yaml``)
is the default; a model carries the profile it was calibrated with.

    profile = load_profile("quadcopter")          # a name in config/robots, or a path

Pure Python + numpy + yaml: imported by the core, the CLI and the nodes alike.
"""

from __future__ import annotations

import math
import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from egovib_ros.errors import ConfigError

SCHEMA = "egovib.robot/1"
PACKAGE = "egovib_ros"
DEFAULT_PROFILE = "pr2_right_hand"
SENSOR_FIELDS = ("linear_acceleration", "angular_velocity")
#: The joint-velocity commands of any robot's sweep (ros2_control's forward-command
#: convention; the simulated hand follows them too), relative to the node's namespace.
COMMANDS_TOPIC = "hand_velocity_controller/commands"
#: Where joint velocity comes from (`joints.velocity`; see core.velocity.JointVelocity).
VELOCITY_SOURCES = ("auto", "measured", "from_position")
#: What the sensor's header stamps mark (`sensor.stamps`): told from the first samples (auto),
#: sample times, or when a driver received each message (core.receipt).
STAMP_KINDS = ("auto", "sample", "receipt")
MAX_JOINTS = 8
#: The highest sensor rate a profile may give (Hz): beyond any IMU's and the fastest vibration
#: DAQs' (51.2-102.4 kHz); a larger value is a typo (1e9 would size arrays of 500 GB).
MAX_RATE_HZ = 200_000.0
#: A ROS 2 topic name as rcl validates it (absolute or relative, no substitutions): tokens of
#: letters, digits and '_' not starting with a digit, joined by single '/'.
_TOPIC_NAME = re.compile(r"/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")
# The keys each section of a profile may hold (INTERFACES.md section 1b, plus `sensor.range`
# and `sensor.stamps`), in the order written, and the field each sets.
_SECTION_KEYS = {
    "sensor": {
        "topic": "sensor_topic",
        "field": "sensor_field",
        "rate_hz": "rate_hz",
        "denoised_topic": "denoised_topic",
        "range": "sensor_range",
        "stamps": "sensor_stamps",
    },
    "joints": {
        "topic": "joints_topic",
        "names": "joint_names",
        "max_speed": "max_speed",
        "bidirectional": "bidirectional",
        "steps": "steps",
        "velocity": "velocity_source",
    },
    "processing": {k: k for k in ("block_length", "hop", "band_hz", "band_order")},
}
#: field -> its key in a profile file ("sensor.topic"), for error messages
_YAML_KEY = {f: f"{s}.{k}" for s, keys in _SECTION_KEYS.items() for k, f in keys.items()}


@dataclass(frozen=True, kw_only=True)
class RobotProfile:
    """A validated robot profile. Build with `load_profile`, `RobotProfile.from_dict` or
    keywords; every field is checked on construction (one-line ConfigError naming it)."""

    name: str
    sensor_topic: str
    sensor_field: str
    rate_hz: float
    denoised_topic: str
    joints_topic: str
    joint_names: tuple[str, ...]
    max_speed: tuple[float, ...]
    bidirectional: tuple[bool, ...]
    steps: int = 10
    # joint velocity: the message's (measured), differentiated positions (from_position), or
    # the message's where it has one and positions elsewhere (auto: drivers without velocity)
    velocity_source: str = "auto"
    sensor_range: float = math.inf  # |value| beyond this on any axis: a bad sample
    sensor_stamps: str = "auto"  # STAMP_KINDS
    block_length: int = 64
    hop: int = 32
    band_hz: tuple[float, float] = (150.0, 750.0)
    band_order: int = 4
    source: str = field(default="", compare=False)  # where it was read (error messages)

    def __post_init__(self) -> None:  # noqa: C901 (one check per profile field, each its own message)
        set_ = object.__setattr__
        where = self.source or f"robot profile {self.name!r}"

        def bad(message: str) -> ConfigError:
            return ConfigError(f"{where}: {message}")

        if not isinstance(self.name, str) or not self.name:
            raise bad("name must be a non-empty string")
        for key in ("sensor_topic", "denoised_topic", "joints_topic"):
            value = getattr(self, key)
            if not isinstance(value, str) or not value.strip("/"):
                raise bad(f"{key} must be a topic name, got {value!r}")
            if not _TOPIC_NAME.fullmatch(value):
                raise bad(
                    f"{_YAML_KEY[key]} {value!r} is not a valid ROS topic "
                    f"name (letters, digits, '_' and '/' only, no token starting with a digit, "
                    f"no '//' nor trailing '/')"
                )
        # One topic for two roles: the denoiser would read its own output, offline the
        # denoised topic would replace the raw one. Named by their keys in the YAML file.
        roles = [(_YAML_KEY[k], getattr(self, k)) for k in ("sensor_topic", "denoised_topic")]
        roles.append(("joints.topic", self.joints_topic))
        for i, (key, topic) in enumerate(roles):
            for other, other_topic in roles[i + 1 :]:
                if topic.strip("/") == other_topic.strip("/"):
                    raise bad(f"{other} is {other_topic}, the same topic as {key}")
        if self.sensor_field not in SENSOR_FIELDS:
            raise bad(f"sensor field must be one of {SENSOR_FIELDS}, got {self.sensor_field!r}")
        set_(self, "rate_hz", _positive(self.rate_hz, "rate_hz", bad))
        if self.rate_hz > MAX_RATE_HZ:
            raise bad(f"sensor.rate_hz {self.rate_hz:g} is beyond {MAX_RATE_HZ:g} Hz (a typo?)")
        names = (
            (self.joint_names,) if isinstance(self.joint_names, str) else tuple(self.joint_names)
        )
        if not 1 <= len(names) <= MAX_JOINTS:
            raise bad(f"between 1 and {MAX_JOINTS} joints are supported, got {len(names)}")
        if any(not isinstance(n, str) or not n for n in names) or len(set(names)) != len(names):
            raise bad(f"joint names must be distinct non-empty strings, got {list(names)}")
        set_(self, "joint_names", names)
        for key in ("max_speed", "bidirectional"):
            values = getattr(self, key)
            values = (values,) * len(names) if np.isscalar(values) else tuple(values)
            if len(values) != len(names):
                raise bad(f"{key} has {len(values)} entries for {len(names)} joints")
            set_(self, key, values)
        set_(self, "max_speed", tuple(_positive(v, "max_speed", bad) for v in self.max_speed))
        if not all(isinstance(b, (bool, np.bool_)) for b in self.bidirectional):
            raise bad(f"bidirectional must be true/false per joint, got {list(self.bidirectional)}")
        set_(self, "bidirectional", tuple(bool(b) for b in self.bidirectional))
        set_(self, "steps", _integer(self.steps, "steps", 1, 100, bad))
        if self.velocity_source not in VELOCITY_SOURCES:
            raise bad(
                f"joints.velocity must be one of {list(VELOCITY_SOURCES)}, "
                f"got {self.velocity_source!r}"
            )
        set_(
            self, "sensor_range", _positive(self.sensor_range, "sensor range", bad, allow_inf=True)
        )
        if self.sensor_stamps not in STAMP_KINDS:
            raise bad(
                f"sensor.stamps must be one of {list(STAMP_KINDS)}, got {self.sensor_stamps!r}"
            )
        set_(self, "block_length", _integer(self.block_length, "block_length", 4, 65536, bad))
        set_(self, "hop", _integer(self.hop, "hop", 1, 65536, bad))
        if self.block_length % self.hop or self.block_length // self.hop < 2:
            raise bad(
                f"hop must divide block_length and be smaller ({self.hop}, {self.block_length})"
            )
        try:
            low, high = (float(b) for b in self.band_hz)
        except (TypeError, ValueError):
            raise bad(f"band_hz must be [low, high], got {self.band_hz!r}") from None
        if not (math.isfinite(low) and math.isfinite(high) and 0 < low < high < self.rate_hz / 2):
            raise bad(
                f"band_hz must satisfy 0 < low < high < {self.rate_hz / 2:g} Hz (Nyquist), "
                f"got [{low:g}, {high:g}]"
            )
        set_(self, "band_hz", (low, high))
        set_(self, "band_order", _integer(self.band_order, "band_order", 1, 12, bad))

    # --- derived facts --------------------------------------------------------
    @property
    def n_joints(self) -> int:
        return len(self.joint_names)

    def grid_values(self, joint: int) -> np.ndarray:
        """Grid velocities of one joint in its own unit: -max..max (bidirectional) or 0..max
        in `steps` steps per direction."""
        low = -self.steps if self.bidirectional[joint] else 0
        return np.round(np.arange(low, self.steps + 1) / self.steps, 10) * self.max_speed[joint]

    def grid(self) -> tuple[np.ndarray, ...]:
        return tuple(self.grid_values(j) for j in range(self.n_joints))

    @property
    def grid_shape(self) -> tuple[int, ...]:
        return tuple((2 if b else 1) * self.steps + 1 for b in self.bidirectional)

    @property
    def node_sensor_topic(self) -> str:
        """The sensor topic as a relative name (remappable, namespaceable), for nodes."""
        return self.sensor_topic.lstrip("/")

    @property
    def node_denoised_topic(self) -> str:
        return self.denoised_topic.lstrip("/")

    @property
    def node_joints_topic(self) -> str:
        return self.joints_topic.lstrip("/")

    # --- (de)serialisation ----------------------------------------------------
    def to_dict(self) -> dict:
        """The profile as the YAML mapping of INTERFACES.md section 1b (plus `sensor.range`
        when finite, `sensor.stamps` when not auto)."""
        out = {"schema": SCHEMA, "name": self.name}
        for section, keys in _SECTION_KEYS.items():
            values = {key: getattr(self, field) for key, field in keys.items()}
            out[section] = {k: list(v) if isinstance(v, tuple) else v for k, v in values.items()}
        if not math.isfinite(self.sensor_range):
            del out["sensor"]["range"]
        if self.sensor_stamps == "auto":
            del out["sensor"]["stamps"]
        return out

    def dumps(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    @classmethod
    def from_dict(cls, data: dict, *, source: str = "") -> "RobotProfile":
        where = source or "robot profile"
        if not isinstance(data, dict):
            raise ConfigError(f"{where}: expected a mapping, got {type(data).__name__}")
        if data.get("schema") != SCHEMA:
            raise ConfigError(f"{where}: schema must be {SCHEMA!r}, got {data.get('schema')!r}")
        top = sorted(set(data) - {"schema", "name", "sensor", "joints", "processing"}, key=str)
        if top:  # a misspelt section would silently give its defaults
            raise ConfigError(
                f"{where}: unknown top-level key(s) {top} (known: "
                f"['schema', 'name', 'sensor', 'joints', 'processing'])"
            )
        sections = {}
        for key in _SECTION_KEYS:
            value = data.get(key, {} if key == "processing" else None)
            if not isinstance(value, dict):
                raise ConfigError(f"{where}: section '{key}' is missing or not a mapping")
            sections[key] = value
        for key, known in _SECTION_KEYS.items():
            unknown = sorted(set(sections[key]) - set(known))
            if unknown:
                raise ConfigError(
                    f"{where}: unknown key(s) {unknown} in '{key}' (known: {list(known)})"
                )
        sensor, joints = sections["sensor"], sections["joints"]
        for key in ("topic", "field", "rate_hz"):
            if key not in sensor:
                raise ConfigError(f"{where}: sensor.{key} is required")
        for key in ("names", "max_speed"):
            if key not in joints:
                raise ConfigError(f"{where}: joints.{key} is required")
        values = {
            field: sections[section][key]
            for section, keys in _SECTION_KEYS.items()
            for key, field in keys.items()
            if key in sections[section]
        }
        values.setdefault("denoised_topic", _denoised_name(sensor["topic"]))
        values.setdefault("joints_topic", "/joint_states")
        values.setdefault("bidirectional", True)
        return cls(name=str(data.get("name", "")), source=source, **values)

    @classmethod
    def loads(cls, text: str, *, source: str = "") -> "RobotProfile":
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            mark, problem = getattr(exc, "problem_mark", None), getattr(exc, "problem", None)
            if mark is not None and problem:  # where the parser stopped, and why
                why = f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
            else:
                why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise ConfigError(f"{source or 'robot profile'}: not valid YAML ({why})") from None
        return cls.from_dict(data, source=source)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "RobotProfile":
        path = Path(path)
        try:
            text = path.read_text()
        except FileNotFoundError:
            raise ConfigError(f"{path}: no such robot profile") from None
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(
                f"{path}: cannot read robot profile ({exc.__class__.__name__})"
            ) from None
        return cls.loads(text, source=str(path))


def _positive(value, name: str, bad, *, allow_inf: bool = False) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise bad(f"{name} must be a positive number, got {value!r}") from None
    if (
        isinstance(value, bool)
        or not number > 0  # NaN too
        or (math.isinf(number) and not allow_inf)
    ):
        raise bad(
            f"{name} must be a positive{'' if allow_inf else ' finite'} number, got {value!r}"
        )
    return number


def _integer(value, name: str, low: int, high: int, bad) -> int:
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, np.integer))
        or not low <= value <= high
    ):
        raise bad(f"{name} must be an integer in [{low}, {high}], got {value!r}")
    return int(value)


def _denoised_name(topic: str) -> str:
    head, _, tail = topic.rstrip("/").rpartition("/")
    return f"{head}/denoised" if head else "/denoised"


# --- where profiles live -------------------------------------------------------
def config_dir() -> Path:
    """The package's config directory: the source tree's `config/` (checkout, editable
    install) or `share/egovib_ros/config` of a colcon/ament or pip install."""
    here = Path(__file__).resolve()
    candidates = [here.parents[1] / "config"]
    for prefix in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep):
        if prefix:
            candidates.append(Path(prefix) / "share" / PACKAGE / "config")
    # an install tree: <prefix>/lib/pythonX.Y/site-packages/egovib_ros/robot.py
    candidates += [parent / "share" / PACKAGE / "config" for parent in here.parents[1:6]]
    candidates.append(Path(sys.prefix) / "share" / PACKAGE / "config")
    for candidate in candidates:
        if (candidate / "robots" / f"{DEFAULT_PROFILE}.yaml").is_file():
            return candidate
    raise ConfigError(
        f"cannot find the {PACKAGE} config directory (looked in "
        f"{', '.join(str(c) for c in candidates[:3])}, ...); is the package installed?"
    )


def profile_names() -> list[str]:
    """Names of the profiles shipped in config/robots."""
    return sorted(p.stem for p in (config_dir() / "robots").glob("*.yaml"))


def load_profile(spec: str | os.PathLike | None = None) -> RobotProfile:
    """A profile from a path, a shipped profile's name (e.g. ``quadcopter``), or the
    default PR2 hand for None/empty."""
    if spec is None or str(spec) == "":
        return RobotProfile.load(config_dir() / "robots" / f"{DEFAULT_PROFILE}.yaml")
    path = Path(spec)
    if path.suffix in (".yaml", ".yml") or path.exists() or os.sep in str(spec):
        return RobotProfile.load(path)
    shipped = config_dir() / "robots" / f"{spec}.yaml"
    if shipped.is_file():
        return RobotProfile.load(shipped)
    raise ConfigError(
        f"{spec}: no such robot profile file, nor a shipped profile "
        f"(shipped: {', '.join(profile_names())})"
    )


def robot_option(profile: RobotProfile) -> str | None:
    """What `egovib calibrate --robot` names this profile by in a command line the project
    advises: nothing for the default PR2 hand, a shipped profile's name, else PROFILE.yaml
    (the user's own file, wherever it is; also a copy of a shipped one that kept its name)."""
    if profile.name not in profile_names() or load_profile(profile.name) != profile:
        return "PROFILE.yaml"
    return None if profile.name == DEFAULT_PROFILE else profile.name


def default_profile() -> RobotProfile:
    return load_profile(None)
