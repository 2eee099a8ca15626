"""The decoded Betaflight flight log (``quadcopter_ar8_flight.npz``) as validated arrays.

Fields used (see ../shared/real/README.md): ``time_s`` (flight-controller clock, s, steps
jitter 0.9-1.25 ms around 1 ms), ``gyro_unfiltered_dps`` (N, 3) before the firmware's
motor-noise filters, ``gyro_filtered_dps`` (N, 3) after them, ``motor_cmd_frac`` (N, 4)
motor commands as a fraction of full scale, ``meta_json``.

Units here are those of the bag: stamps in integer ns (the log's microsecond clock
times 1000), angular rates in rad/s.
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import EgovibError

REQUIRED = ("time_s", "gyro_unfiltered_dps", "gyro_filtered_dps", "motor_cmd_frac")
MOTOR_NAMES = ("motor1", "motor2", "motor3", "motor4")


class FlightLogError(EgovibError):
    """The flight-log file is missing, unreadable or lacks a field."""


@dataclass(frozen=True)
class FlightLog:
    stamps_ns: np.ndarray  # (N,) int64, strictly increasing
    gyro: np.ndarray  # (N, 3) rad/s, unfiltered (the vibration channel)
    gyro_filtered: np.ndarray  # (N, 3) rad/s, after Betaflight's own filters
    motors: np.ndarray  # (N, 4) command fraction 0..1 (one DShot step below 0 at idle)
    meta: dict
    source: str = ""

    @property
    def n(self) -> int:
        return len(self.stamps_ns)

    @property
    def duration_s(self) -> float:
        return float(self.stamps_ns[-1] - self.stamps_ns[0]) / NS_PER_S if self.n > 1 else 0.0


def seconds_to_ns(time_s: np.ndarray) -> np.ndarray:
    """The log's clock counts microseconds: round to them, then ns (exact, no float drift)."""
    return np.round(np.asarray(time_s, np.float64) * 1e6).astype(np.int64) * 1000


def load_flight_log(path: str | os.PathLike) -> FlightLog:
    """Read and check the npz; raises FlightLogError naming the file and the problem."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [key for key in REQUIRED if key not in data.files]
            if missing:
                raise FlightLogError(f"{path}: missing field(s) {missing} (need {list(REQUIRED)})")
            fields = {key: np.asarray(data[key]) for key in REQUIRED}
            meta_text = str(data["meta_json"]) if "meta_json" in data.files else "{}"
    except FileNotFoundError:
        raise FlightLogError(f"{path}: no such flight log") from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise FlightLogError(
            f"{path}: not a readable .npz flight log ({exc.__class__.__name__})"
        ) from None
    n = fields["time_s"].shape[0] if fields["time_s"].ndim == 1 else -1
    shapes = {
        "time_s": (n,),
        "gyro_unfiltered_dps": (n, 3),
        "gyro_filtered_dps": (n, 3),
        "motor_cmd_frac": (n, len(MOTOR_NAMES)),
    }
    for key, shape in shapes.items():
        if fields[key].shape != shape or n < 2:
            raise FlightLogError(
                f"{path}: field {key} has shape {fields[key].shape}, expected {shape}"
            )
        if not np.all(np.isfinite(fields[key])):
            raise FlightLogError(f"{path}: field {key} holds non-finite values")
    stamps = seconds_to_ns(fields["time_s"])
    if np.any(np.diff(stamps) <= 0):
        raise FlightLogError(f"{path}: time_s is not strictly increasing")
    try:
        meta = json.loads(meta_text)
    except json.JSONDecodeError:
        meta = {"meta_json": meta_text}
    return FlightLog(
        stamps_ns=stamps,
        gyro=np.deg2rad(fields["gyro_unfiltered_dps"].astype(np.float64)),
        gyro_filtered=np.deg2rad(fields["gyro_filtered_dps"].astype(np.float64)),
        motors=fields["motor_cmd_frac"].astype(np.float64),
        meta=meta,
        source=str(path),
    )
