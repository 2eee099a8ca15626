"""Denoising methods selectable by name: `paper`, `cancel`, `hybrid`.

    paper   the paper's block spectral subtraction (core.subtraction.StreamingDenoiser):
            block_length - 1 samples of delay (21 ms for the PR2, 32 ms for the quadcopter)
    cancel  speed-locked harmonic cancellation (core.harmonic) on each band-passed axis:
            no delay, removes the actuators' lines only
    hybrid  cancel, then the low-latency gain (core.lowlatency) keyed on the velocity table
            of what cancellation leaves: `lookahead_ms` of delay (4 ms by default)

What `cancel` and `hybrid` need (`calibrate_methods`: the speed -> line-frequency map, the
residual's velocity table, the gain's statistics) is stored in the noise model's `extras`.
All three have one push interface (`make_denoiser` builds one by name), so batch equals
streaming for any chunking. The new methods clean x, y and z separately (`combined`: the
sum of the cleaned axes); their drop-in output splits the raw samples by a low-pass fitted
to the calibration recording (DropInSplit): gravity and motion pass untouched, at the
split's delay (4.0 ms on the simulated PR2 hand, 10 ms on the 1 kHz flight).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass

import numba
import numpy as np
from scipy import signal

from egovib_ros.core.adapt import (
    Adaptation,
    AdaptiveTable,
    AdaptSettings,
    AdaptStats,
    learnt_state,
    without_learnt,
)
from egovib_ros.core.calibration import calibrate_arrays
from egovib_ros.core.contact import (
    FALSE_ALARMS_PER_MIN,
    ContactSettings,
    DetectionEnvelope,
    MotionLimits,
    hold_bad,
    joint_acceleration,
    no_contact_threshold,
)
from egovib_ros.core.filters import (
    SPLIT_LEAK_DB,
    CarriedFilter,
    bandpass_delay,
    highpass_inverse,
    lines_highpass,
    split_for,
    split_leak_db,
    split_taps,
)
from egovib_ros.core.harmonic import (
    CancellerSettings,
    HarmonicCanceller,
    HarmonicMap,
    fit_harmonic_map,
)
from egovib_ros.core.lowlatency import FilterBank, GainSettings, LowLatencyGain
from egovib_ros.core.noise_model import NoiseModel
from egovib_ros.core.sampleframer import SampleBatch, SampleFramer
from egovib_ros.core.stream import DenoiserStats, FramerSettings, bad_samples, feed
from egovib_ros.core.subtraction import (
    DenoisedChunk,
    FramedDenoiser,
    StreamingDenoiser,
    check_output,
    noise_gain_curve,
)
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import ConfigError, ModelFileError, StreamError

METHODS = ("paper", "cancel", "hybrid")
#: The methods that need what calibrate_methods fits (the model's extras) and can adapt online.
SAMPLE_METHODS = tuple(m for m in METHODS if m != "paper")
#: What a command or node runs when no method is named: the one that removes the most and
#: keeps events best (docs/methods_compare.md), where the model carries what it needs.
DEFAULT_METHOD = "hybrid"
AXES = ("x", "y", "z")
LOG = logging.getLogger("egovib_ros.core")
#: Keys of the noise model's extras written by calibrate_methods.
HARMONIC_PREFIX = "harmonic."
RESIDUAL_PREFIX = "residual."
GAIN_PREFIX = "gain."
CANCELLER_PREFIX = "canceller."
#: ... and the contact detector's thresholds, per method (and "raw": no denoising)
DETECTOR_PREFIX = "detector.threshold."
DETECTOR_BUDGET = "detector.false_alarms_per_min"
#: The motion of the calibration data (core.contact.MotionLimits): its largest joint
#: acceleration, each joint's lowest and highest speed.
DETECTOR_MOTION = "detector.motion."
MOTION_SPEED_MARGIN = 0.02
#: The ends of a calibration recording the thresholds leave out (filter start-up, flush).
EDGE_S = 0.1
#: Calibration samples the gain statistics skip while the trackers settle (seconds).
SETTLE_S = 0.5
#: Least expected residual power, dB below the channel and band's mean over measured cells.
FLOOR_DB = 30.0


#: How far ahead the hybrid gain of the drop-in output may look (ms): the event onset
#: tolerance of evaluation.detection (a gain opens up to its look-ahead early).
MAX_EARLY_OPENING_MS = 10.0


def check_method(method: str) -> str:
    if method not in METHODS:
        raise ConfigError(f"method: expected one of {list(METHODS)}, got {method!r}")
    return method


def has_method_calibration(model: NoiseModel) -> bool:
    """Whether the model carries what `cancel` and `hybrid` need (calibrate_methods)."""
    return HARMONIC_PREFIX + "exponent" in model.extras


def default_method(model: NoiseModel) -> str:
    """DEFAULT_METHOD, or `paper` for a model calibrated for the paper's method only."""
    return DEFAULT_METHOD if has_method_calibration(model) else "paper"


def resolve_method(model: NoiseModel, method: str | None) -> str:
    """The method asked for (checked), or the model's default when none is."""
    return default_method(model) if method is None else check_method(method)


def stored_threshold(model: NoiseModel, method: str) -> float | None:
    """The contact detector's threshold for `method`'s default output (or "raw") that
    calibration stored in the model (calibrate_detection); None if it did not."""
    return model.scalar_extra(DETECTOR_PREFIX + method, low=0.0, high=math.inf)


def motion_limits(
    model: NoiseModel, method: str, thresholds: dict | None = None
) -> MotionLimits | None:
    """The contact detector's motion limits for `method`'s output (core.contact): the
    calibration data's joint speeds and largest joint acceleration (motion_extras), and the
    raw signal's threshold over the method's (`thresholds` by method, "raw" included; default: the
    stored ones). None for the raw signal, a model calibrated before the limits, or
    thresholds that leave the method's output no quieter than the raw signal."""
    accel = model.scalar_extra(DETECTOR_MOTION + "accel", low=0.0, high=math.inf)
    if thresholds is None:
        thresholds = {m: stored_threshold(model, m) for m in ("raw", method)}
    raw, own = thresholds.get("raw"), thresholds.get(method)
    if method == "raw" or accel is None or not raw or not own or raw <= own:
        return None
    speeds = []
    for key in ("speed_low", "speed_high"):
        value = np.asarray(model.extras.get(DETECTOR_MOTION + key, ()), np.float64)
        if value.shape != (model.n_joints,) or np.isnan(value).any():
            raise ModelFileError(f"{model.where}: malformed field {DETECTOR_MOTION + key!r}")
        speeds.append(tuple(value.tolist()))
    return MotionLimits(speed_low=speeds[0], speed_high=speeds[1], accel=accel, factor=raw / own)


#: Below this much no-contact data, the detector's thresholds (a level its envelope crosses
#: once a minute) rest on the recording's few largest bursts and differ from run to run
#: (0.12-0.30 over ten 6 s sweeps of the example arm, test_nodes_sim_robot).
DETECTION_MIN_S = 60.0


def short_detection_warning(seconds: float) -> str | None:
    """What calibration says of detection thresholds set from `seconds` of data (None: enough)."""
    if seconds >= DETECTION_MIN_S:
        return None
    return (
        f"warning: the contact detector's thresholds come from {seconds:.0f} s of calibration "
        "data: a level crossed once a minute rests on its few largest bursts and may differ "
        f"from run to run; calibrate on {DETECTION_MIN_S:.0f} s or more of motion without contact"
    )


#: A joint below this fraction of its top speed is at rest ...
REST_SPEED_FRACTION = 0.02
#: ... and calibration data more than this share of it with every joint at rest sets the
#: detector's thresholds mostly on the robot standing still: a live calibration left running
#: after its sweep (70 of 108 s in a probe: F1 0.79 at 30 false alarms a minute in motion).
REST_SHARE_WARN = 0.5


def rest_detection_warning(
    sensor_stamps_ns: np.ndarray,
    joint_stamps_ns: np.ndarray,
    joint_velocity: np.ndarray,
    max_speed,
) -> str | None:
    """What calibration says of detection thresholds set on data that is mostly the robot at
    rest (None: it is not): each sample takes the last joint state before it."""
    if not len(sensor_stamps_ns) or not len(joint_stamps_ns):
        return None
    row = np.clip(np.searchsorted(joint_stamps_ns, sensor_stamps_ns, side="right") - 1, 0, None)
    still = np.abs(joint_velocity) < REST_SPEED_FRACTION * np.asarray(max_speed, float)
    share = float(np.mean(np.all(still, axis=1)[row]))  # NaN (unknown): not at rest
    if share <= REST_SHARE_WARN:
        return None
    return (
        f"warning: {share:.0%} of the calibration data is the robot at rest (every joint below "
        f"{REST_SPEED_FRACTION:.0%} of its top speed): the contact detector's thresholds, a "
        "level crossed once a minute of it, may sit below what motion reaches; calibrate on "
        "motion without contact (end a live calibration soon after its sweep)"
    )


def calibrate_detection(
    model: NoiseModel,
    sensor_stamps_ns: np.ndarray,
    accel: np.ndarray,
    joint_stamps_ns: np.ndarray,
    joint_velocity: np.ndarray,
    *,
    source: str = "",
) -> tuple[NoiseModel, dict]:
    """The contact detector's threshold for each method the model can run (its default
    output, as `egovib detect` and the contact_detector node read it) and for the raw
    signal, from no-contact data: core.contact's rule at FALSE_ALARMS_PER_MIN, the first
    and last EDGE_S left out. Returns the model with them in its extras (a model
    calibrated live feeds the detector alone) and them."""
    streams = (sensor_stamps_ns, accel, joint_stamps_ns, joint_velocity)
    settings = ContactSettings.for_model(model, 1.0)
    edge = int(EDGE_S * model.sample_rate_hz)
    methods = [m for m in METHODS if m == "paper" or has_method_calibration(model)]
    thresholds = {}
    for method in ["raw", *methods]:
        if method == "raw":  # bad samples held, as the detector holds them
            values, _ = hold_bad(accel, settings.sensor_range)
        else:
            _, values, _ = denoise_batch_method(*streams, model, method=method, source=source)
        envelope = DetectionEnvelope(settings).process(values)[1]
        if len(envelope) <= 2 * edge:
            raise StreamError(f"{source or 'calibration'}: too short for detection thresholds")
        thresholds[method], _ = no_contact_threshold(
            envelope[edge:-edge],
            sample_rate_hz=model.sample_rate_hz,
            false_alarms_per_min=FALSE_ALARMS_PER_MIN,
        )
    extras = {DETECTOR_PREFIX + m: np.array(t) for m, t in thresholds.items()}
    extras[DETECTOR_BUDGET] = np.array(float(FALSE_ALARMS_PER_MIN))
    extras.update(motion_extras(model, joint_stamps_ns, joint_velocity))
    return model.replace(extras={**model.extras, **extras}), thresholds


def with_motion(model: NoiseModel, joint_stamps_ns, joint_velocity) -> NoiseModel:
    """The model with the motion of other no-contact data in place of its own (none if
    that robot never moved): what motion_limits reads when thresholds come from them."""
    extras = {k: v for k, v in model.extras.items() if not k.startswith(DETECTOR_MOTION)}
    extras.update(motion_extras(model, joint_stamps_ns, joint_velocity))
    return model.replace(extras=extras)


def motion_extras(
    model: NoiseModel, joint_stamps_ns: np.ndarray, joint_velocity: np.ndarray
) -> dict[str, np.ndarray]:
    """The motion of no-contact data, as the model's extras keep it (motion_limits reads
    them): its largest joint acceleration, each joint's lowest and highest speed past the
    speeds seen by MOTION_SPEED_MARGIN of its top grid speed (a run at a sweep's top speed
    is not beyond it). None for a robot that never moved."""
    joint_velocity = np.asarray(joint_velocity, np.float64).reshape(len(joint_stamps_ns), -1)
    accel = joint_acceleration(joint_stamps_ns, joint_velocity)
    known = np.isfinite(joint_velocity).all(axis=1)
    if not known.any() or not accel.max() > 0:
        return {}
    margin = MOTION_SPEED_MARGIN * np.array([np.abs(g).max() for g in model.grid])
    return {
        DETECTOR_MOTION + "accel": np.array(float(accel.max())),
        DETECTOR_MOTION + "speed_low": joint_velocity[known].min(axis=0) - margin,
        DETECTOR_MOTION + "speed_high": joint_velocity[known].max(axis=0) + margin,
    }


# --- What the methods calibrate, stored in the model's extras -----------------------------
def _settings_arrays(prefix: str, settings) -> dict[str, np.ndarray]:
    out = {}
    for f in dataclasses.fields(settings):
        value = getattr(settings, f.name)
        out[prefix + f.name] = np.array(np.nan if value is None else value)
    return out


def _settings_from(extras: dict, prefix: str, cls, where: str):
    values = {}
    for f in dataclasses.fields(cls):
        key = prefix + f.name
        if key not in extras:
            continue  # written by an older version: the default
        value = np.asarray(extras[key])
        if value.ndim != 0 or value.dtype.kind not in "iuf":
            raise ModelFileError(f"{where}: malformed field {key!r}")
        number = float(value)
        if f.name == "oversubtraction" and math.isnan(number):
            values[f.name] = None
        elif f.name == "bands":
            values[f.name] = int(number)
        else:
            values[f.name] = number
    try:
        return cls(**values)
    except ConfigError as exc:
        raise ModelFileError(f"{where}: {exc}") from None


@dataclass
class MethodCalibration:
    """What `cancel` and `hybrid` need beyond the paper's table."""

    harmonic: HarmonicMap
    canceller: CancellerSettings
    residual: NoiseModel  # the velocity table of the cancellation residual (x, y, z)
    gain: GainSettings
    alpha: np.ndarray  # (3, B) per axis and band
    bias: np.ndarray  # (3, B)
    open_alpha: np.ndarray  # (3,) per axis
    guard_ref: np.ndarray | None = None  # (3,) per axis; None: calibrated before the guard
    split_taps: np.ndarray | None = None  # the drop-in output's split fitted to the recording
    split_delay: int | None = None  # its delay (samples); None: linear phase, half its length

    def to_extras(self) -> dict[str, np.ndarray]:
        extras = self.harmonic.to_arrays(HARMONIC_PREFIX)
        extras.update(_settings_arrays(CANCELLER_PREFIX, self.canceller))
        extras.update(_settings_arrays(GAIN_PREFIX, self.gain))
        r = self.residual
        extras.update(
            {
                RESIDUAL_PREFIX + "cells": r.cells.astype(np.int32),
                RESIDUAL_PREFIX + "mean": r.cell_mean,
                RESIDUAL_PREFIX + "std": r.cell_std,
                RESIDUAL_PREFIX + "counts": r.cell_counts,
                RESIDUAL_PREFIX + "measured": np.array(r.measured),
                GAIN_PREFIX + "alpha": self.alpha,
                GAIN_PREFIX + "bias": self.bias,
                GAIN_PREFIX + "open_alpha": self.open_alpha,
            }
        )
        if self.guard_ref is not None:
            extras[GAIN_PREFIX + "guard_ref"] = self.guard_ref
        if self.split_taps is not None:
            extras[GAIN_PREFIX + "split_taps"] = np.asarray(self.split_taps, float)
            extras[GAIN_PREFIX + "split_delay"] = np.array(self.dropin_split[1])
        return extras

    @classmethod
    def of(cls, model: NoiseModel) -> "MethodCalibration":
        """from_model, read once per model (a model is not changed once built): a denoiser
        built again for every bag of a batch reuses it, and the residual table's caches."""
        return model._cached("method_calibration", lambda: cls.from_model(model))

    @classmethod
    def from_model(cls, model: NoiseModel) -> "MethodCalibration":
        where, extras = model.where, model.extras
        if HARMONIC_PREFIX + "exponent" not in extras:
            raise ModelFileError(
                f"{where}: calibrated for the paper's method only; calibrate it with "
                f"`egovib calibrate --methods hybrid` to use methods cancel and hybrid"
            )
        harmonic = HarmonicMap.from_arrays(extras, HARMONIC_PREFIX, where=where)
        if harmonic.joint_names != model.joint_names:
            raise ModelFileError(f"{where}: harmonic map joints differ from the model's")
        canceller = _settings_from(extras, CANCELLER_PREFIX, CancellerSettings, where)
        gain = _settings_from(extras, GAIN_PREFIX, GainSettings, where)
        keys = [RESIDUAL_PREFIX + k for k in ("cells", "mean", "std", "counts", "measured")]
        missing = [k for k in keys if k not in extras]
        if missing:
            raise ModelFileError(f"{where}: missing field(s) {missing}")
        residual = model.replace(
            cells=extras[keys[0]],
            mean=extras[keys[1]],
            std=extras[keys[2]],
            counts=extras[keys[3]],
            measured=str(extras[keys[4]]),
            provenance={**model.provenance, "path": f"{where} (residual table)"},
            extras={},
        )
        bands = gain.bands + 1
        alpha = np.asarray(extras.get(GAIN_PREFIX + "alpha", np.zeros(0)), float)
        bias = np.asarray(extras.get(GAIN_PREFIX + "bias", np.zeros(0)), float)
        for name, value in (("alpha", alpha), ("bias", bias)):
            if value.shape != (len(AXES), bands) or not np.all(np.isfinite(value)):
                raise ModelFileError(f"{where}: gain {name} must be finite with shape (3, {bands})")
        open_alpha = np.asarray(extras.get(GAIN_PREFIX + "open_alpha", np.ones(len(AXES))), float)
        if open_alpha.shape != (len(AXES),) or not np.all(
            np.isfinite(open_alpha) & (open_alpha > 0)
        ):
            raise ModelFileError(f"{where}: gain open_alpha must hold 3 positive values")
        guard_ref = extras.get(GAIN_PREFIX + "guard_ref")
        if guard_ref is not None:
            guard_ref = np.asarray(guard_ref, float)
            if guard_ref.shape != (len(AXES),) or not np.all(np.isfinite(guard_ref)):
                raise ModelFileError(f"{where}: gain guard_ref must hold 3 finite values")
        split = extras.get(GAIN_PREFIX + "split_taps")
        delay = extras.get(GAIN_PREFIX + "split_delay")
        if split is not None:
            split = np.asarray(split, float)
            if split.ndim != 1 or not len(split) or not np.all(np.isfinite(split)):
                raise ModelFileError(f"{where}: gain split_taps must be finite taps")
            linear = len(split) % 2 == 1 and np.allclose(split, split[::-1])
            if delay is None and not linear:
                raise ModelFileError(
                    f"{where}: gain split_taps without split_delay must be symmetric and odd"
                )
            if delay is not None:
                delay = int(delay)
                if not 0 <= delay < len(split):
                    raise ModelFileError(f"{where}: gain split_delay must be within its taps")
        return cls(
            harmonic, canceller, residual, gain, alpha, bias, open_alpha, guard_ref, split, delay
        )

    @property
    def dropin_split(self) -> tuple[np.ndarray, int] | None:
        """The fitted split as (taps, delay in samples); None if calibrated without one."""
        if self.split_taps is None:
            return None
        taps = np.asarray(self.split_taps, float)
        return taps, (len(taps) - 1) // 2 if self.split_delay is None else self.split_delay


@numba.njit(cache=True)
def _dense_rows(velocity, grids, grid_len, limits, table, strides, measured, floor):  # noqa: C901 (numba loop: one compiled pass per call)
    """Expected band powers once per run of equal velocities: multilinear in the flattened
    dense table (cells, M) (np.interp's position rule, clamped), at least `floor` (M,).
    Returns (values (n, M), the first R rows used, zeros without joint state; index (n,);
    R; samples whose nearest cell is unmeasured; samples beyond the grid's `limits` (J, 2):
    noise_model.grid_limits). Compiled: a live stream calls it every few samples."""
    n, J = velocity.shape
    M = table.shape[1]
    values = np.empty((n, M))  # rows zeroed as used: R is often a third of n or less
    index = np.empty(n, np.int64)
    lower = np.empty(J, np.int64)
    frac = np.empty(J)
    r = -1
    known = False
    unmeasured = False
    outside = False
    n_unmeasured = 0
    n_outside = 0
    previous_ok = False
    for i in range(n):
        ok = True
        for j in range(J):
            if not np.isfinite(velocity[i, j]):
                ok = False
        change = i == 0 or ok != previous_ok
        if not change:
            for j in range(J):
                if velocity[i, j] != velocity[i - 1, j]:
                    change = True
        previous_ok = ok
        if change:
            r += 1
            values[r] = 0.0
            known = ok
            unmeasured = False
            outside = False
            if ok:
                nearest = 0
                for j in range(J):
                    g = grids[j]
                    last = grid_len[j] - 1
                    v = velocity[i, j]
                    if v < limits[j, 0] or v > limits[j, 1]:
                        outside = True
                    if v <= g[0]:
                        position = 0.0
                    elif v >= g[last]:
                        position = float(last)
                    else:
                        k = np.searchsorted(g[: last + 1], v, side="right") - 1
                        position = (v - g[k]) * (1.0 / (g[k + 1] - g[k])) + k
                    i0 = min(int(math.floor(position)), last - 1)
                    lower[j] = i0
                    frac[j] = position - i0
                    nearest += (i0 + (1 if frac[j] >= 0.5 else 0)) * strides[j]
                unmeasured = not measured[nearest]
                for corner in range(1 << J):
                    weight = 1.0
                    cell = 0
                    for j in range(J):
                        if (corner >> j) & 1:
                            weight *= frac[j]
                            cell += (lower[j] + 1) * strides[j]
                        else:
                            weight *= 1.0 - frac[j]
                            cell += lower[j] * strides[j]
                    if weight != 0.0:
                        for m in range(M):
                            values[r, m] += weight * table[cell, m]
                for m in range(M):
                    if values[r, m] < floor[m]:
                        values[r, m] = floor[m]
        index[i] = r
        if known:
            n_unmeasured += unmeasured
            n_outside += outside
    return values, index, r + 1, n_unmeasured, n_outside


class ResidualTable:
    """Expected band powers of the residual at joint velocities, from the residual's
    velocity table (Eq. 5/6 and the nearest-cell rules of NoiseModel): a block's expected
    |X(f)|^2 = mean^2 + std^2, turned into each band's power by the bank's responses."""

    def __init__(self, residual: NoiseModel, bank: FilterBank):
        self.model = residual
        self.channel_index = residual.channel_indices(AXES)
        self.weights = bank.power_weights(residual.block_length, residual.window)  # (B, F)
        self._table = None  # (cells, 3 B) band powers of the dense grid, where there is one
        if residual.dense_ok:
            mean = residual.table(self.channel_index, include_std=False)
            high = residual.table(self.channel_index, include_std=True)
            power = mean**2 + (high - mean) ** 2  # (grid..., C, F)
            dense = power @ self.weights.T  # (grid..., C, B)
            J = residual.n_joints
            self._table = np.ascontiguousarray(dense.reshape(int(np.prod(dense.shape[:J])), -1))
            self._strides = np.array(
                [int(np.prod(dense.shape[j + 1 : J])) for j in range(J)], np.int64
            )
            self._measured = np.ascontiguousarray((residual.counts > 0).reshape(-1))
            self._grid_len = np.array([len(g) for g in residual.grid], np.int64)
            self._grid_limits = np.array(residual.grid_limits)
            self._grid_rows = np.zeros((J, int(self._grid_len.max())))
            for j, g in enumerate(residual.grid):
                self._grid_rows[j, : len(g)] = g
        # A channel the joints never shake (an axis at rest reads a constant) has a table of
        # zeros: keep every expected power at least FLOOR_DB below the channel's typical one.
        cells = (
            residual.cell_mean[:, self.channel_index, :] ** 2
            + residual.cell_std[:, self.channel_index, :] ** 2
        )
        typical = (
            (cells @ self.weights.T).mean(axis=0)
            if len(cells)
            else np.zeros((len(AXES), self.weights.shape[0]))
        )
        self.floor = np.maximum(typical * 10 ** (-FLOOR_DB / 10), 1e-300)
        self._floor_flat = np.ascontiguousarray(self.floor.reshape(-1))  # per call: no copy
        self.samples_unmeasured = 0
        self.samples_out_of_grid = 0

    def powers(self, velocity: np.ndarray) -> np.ndarray:
        """(n, J) velocities (NaN rows: no joint state) -> (n, 3, B) band powers (0 where NaN)."""
        rows, index = self.rows(velocity)
        return rows[index]

    def rows(self, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The band powers once per run of equal velocities (joint states are held between
        updates): ((R, 3, B) powers, (n,) row of each sample); a sample without joint
        state gets a row of zeros (its gains stay open)."""
        B = self.weights.shape[0]
        if self._table is not None:
            grid = (
                self._grid_rows,
                self._grid_len,
                self._grid_limits,
                self._table,
                self._strides,
                self._measured,
            )
            velocity = np.ascontiguousarray(velocity, dtype=np.float64)
            values, index, R, unmeasured, outside = _dense_rows(velocity, *grid, self._floor_flat)
            self.samples_unmeasured += unmeasured
            self.samples_out_of_grid += outside
            return values[:R].reshape(R, len(AXES), B), index
        n = len(velocity)
        ok = np.all(np.isfinite(velocity), axis=1)
        change = np.ones(n, bool)
        change[1:] = np.any(velocity[1:] != velocity[:-1], axis=1) | (ok[1:] != ok[:-1])
        starts = np.flatnonzero(change)
        index = np.cumsum(change) - 1
        values = np.zeros((len(starts), len(AXES), B))
        known = ok[starts]
        if known.any():
            found, measured, outside = self._at(velocity[starts[known]])
            values[known] = np.maximum(found, self.floor)
            runs = np.diff(np.append(starts, n))[known]
            self.samples_unmeasured += int(runs[~measured].sum())
            self.samples_out_of_grid += int(runs[outside].sum())
        return values, index

    def _at(self, rows: np.ndarray):
        """Sparse tables (no dense grid): the model's own nearest-cell lookup."""
        mean, outside, measured = self.model.lookup(rows, self.channel_index, include_std=False)
        high, _, _ = self.model.lookup(rows, self.channel_index, include_std=True)
        return (mean**2 + (high - mean) ** 2) @ self.weights.T, measured, outside


def _band_passed_calibration(
    model: NoiseModel, sensor_stamps_ns, accel, joint_stamps_ns, joint_velocity, source: str
):
    """Run the calibration recording through a SampleFramer: real samples only."""
    settings = FramerSettings.for_model(
        model, layout="per_axis", with_steadiness=False, source=source
    )
    framer = SampleFramer(settings, model.n_joints)
    streams = (sensor_stamps_ns, accel, joint_stamps_ns, joint_velocity)
    # the framer keeps what it releases
    feed(framer, *streams, sample_rate_hz=model.sample_rate_hz, joint_wait_s=settings.joint_wait_s)
    framer.flush()
    batches = framer.pop()
    stamps = np.concatenate([b.stamps_ns for b in batches]) if batches else np.zeros(0, np.int64)
    values = np.concatenate([b.values for b in batches]) if batches else np.zeros((0, 3))
    velocity = (
        np.concatenate([b.velocity for b in batches]) if batches else np.zeros((0, model.n_joints))
    )
    return stamps, values, velocity


def _split(model: NoiseModel, accel: np.ndarray, gain: GainSettings, source: str) -> tuple | None:
    """The drop-in output's split (taps, delay) fitted to the calibration recording
    (core.filters.split_for), no shorter than the gain's look-ahead; None for a recording
    too short to tell. Said when none within SPLIT_MAX_DELAY_S stops the band's noise."""
    values = np.asarray(accel, float)
    # the framer's bad samples (non-finite, beyond the sensor's range) are no spectrum
    sensor_range = model.profile.sensor_range if model.profile is not None else math.inf
    values = values[~bad_samples(values, sensor_range)]
    fs = model.sample_rate_hz
    if len(values) < 8 * model.block_length:
        return None
    freqs, power = signal.welch(
        values - values.mean(axis=0), fs, nperseg=min(len(values), 1 << int(np.log2(fs))), axis=0
    )
    spectrum = dict(
        sample_rate_hz=fs, band_hz=model.band_hz, order=model.band_order, freqs_hz=freqs,
        power=power.sum(axis=1),
    )  # fmt: skip
    taps, delay = split_for(**spectrum, min_delay=gain.delay_samples(fs))
    leak = split_leak_db(taps, **spectrum)
    if leak > SPLIT_LEAK_DB:
        LOG.warning(
            f"{source or 'calibration'}: the band's low edge ({model.band_hz[0]:g} Hz) is too "
            f"low for the drop-in output to keep motion apart from the band within "
            f"{1e3 * delay / fs:.0f} ms: {leak:.0f} dB of the ego-vibration stays in it "
            f"(aim: {SPLIT_LEAK_DB:g} dB), and contacts carry an echo up to that much "
            f"before them; `output: bandpassed` has neither (or raise the band's low edge)"
        )
    return taps, delay


def calibrate_methods(
    model: NoiseModel,
    sensor_stamps_ns: np.ndarray,
    accel: np.ndarray,
    joint_stamps_ns: np.ndarray,
    joint_velocity: np.ndarray,
    *,
    gain: GainSettings | None = None,
    harmonic: HarmonicMap | None = None,
    source: str = "",
) -> tuple[NoiseModel, dict]:
    """Fit what `cancel` and `hybrid` need on the no-contact recording the paper's table
    `model` came from; returns the model with it in its extras, and what was fitted:

    1. the speed -> line-frequency map (core.harmonic.fit_harmonic_map) on the band-passed
       axes with each sample's held joint velocity (`harmonic`: one fitted before);
    2. the canceller's residual over the recording gets its own velocity table (the
       paper's calibration on it: same grid, blocks, sweep or free-motion rules);
    3. the gain stage's statistics on that residual (`_gain_statistics`)."""
    canceller = CancellerSettings()
    gain = gain or GainSettings()
    finite = np.asarray(accel)[np.all(np.isfinite(accel), axis=1)]
    if len(finite) and not np.any(finite != finite[0]):  # the fits would divide by zero power
        raise StreamError(
            f"{source or 'calibration'}: the sensor never changes (a dead sensor, or a field "
            f"its messages leave unset?): nothing to calibrate"
        )
    split = _split(model, accel, gain, source)
    if split is not None and not gain.split_ms:  # the look-ahead the fitted split needs
        delay_ms = 1e3 * split[1] / model.sample_rate_hz
        gain = dataclasses.replace(gain, split_ms=max(gain.lookahead_ms, round(delay_ms, 3)))
    if model.profile is None:
        raise ConfigError("calibrate_methods: the model carries no robot profile")
    fs = model.sample_rate_hz
    stamps, x, velocity = _band_passed_calibration(
        model, sensor_stamps_ns, accel, joint_stamps_ns, joint_velocity, source
    )
    real = stamps >= 0
    known = real & np.all(np.isfinite(velocity), axis=1)
    if np.count_nonzero(known) < 2 * model.block_length:
        raise StreamError(
            f"{source or 'calibration'}: too few samples with joint states to calibrate"
        )
    fit_info = {"given": True}
    if harmonic is None:
        harmonic, fit_info = fit_harmonic_map(
            x[known],
            velocity[known],
            sample_rate_hz=fs,
            band_hz=model.band_hz,
            joint_names=model.joint_names,
            max_speed=np.array(model.profile.max_speed, float),
            settings=canceller,
        )
    cancel = HarmonicCanceller(
        harmonic, sample_rate_hz=fs, band_hz=model.band_hz, n_channels=3, settings=canceller
    )
    residual = cancel.process(x, np.where(np.isfinite(velocity), velocity, np.nan))
    residual_model, residual_stats = calibrate_arrays(
        stamps[real],
        residual[real],
        joint_stamps_ns,
        joint_velocity,
        profile=model.profile,
        sweep=model.measured if model.measured != "full" else "auto",
        prefiltered=True,
        source=source,
    )
    bank = FilterBank(
        sample_rate_hz=fs, band_hz=model.band_hz, bands=gain.bands, bandwidth=gain.bandwidth
    )
    table = ResidualTable(residual_model, bank)
    use = known.copy()
    use[: min(int(SETTLE_S * fs), len(x) // 4)] = False
    stats = _gain_statistics(bank, gain, residual, table, velocity, use)
    alpha, _, _, guard_ref = stats
    calibration = MethodCalibration(
        harmonic, canceller, residual_model, gain, *stats, *(split or (None, None))
    )
    cancelled_db = 0.0
    if use.any():
        ratio = float(np.mean(x[use] ** 2)) / max(float(np.mean(residual[use] ** 2)), 1e-300)
        cancelled_db = round(10 * math.log10(ratio), 2)
    info = {
        "harmonic": {**harmonic.describe(), "fit": fit_info},
        "residual_table": residual_model.coverage(),
        "residual_calibration": {
            k: v for k, v in residual_stats.as_dict().items() if k != "rejected"
        },
        "gain": {
            "bands_hz": bank.centres_hz.round(1).tolist(),
            "alpha_median": float(np.median(alpha)),
            "alpha_db": (10 * np.log10(alpha)).round(1).tolist(),
            "guard_ref_db": (10 * guard_ref / math.log(10)).round(1).tolist(),
        },
        "cancellation_db_on_calibration": cancelled_db,
    }
    extras = {**model.extras, **calibration.to_extras()}
    return model.replace(extras=extras), info


def _gain_statistics(bank, gain, residual, table, velocity, use) -> tuple:
    """(alpha, bias (3, B), open_alpha, guard_ref (3,)) of the gain stage on the calibration
    residual at the samples `use`: `bias` the mean log of band power over the table's
    prediction, `alpha` the `opening_quantile` of that ratio once corrected, `open_alpha`
    the `open_quantile` of the opening score (largest P / (alpha N) over bands), `guard_ref`
    the `guard_quantile` of the guard's slow log level of it (less log open_alpha). Without
    the hold after speed drops: the statistics are the scatter about the table's value at
    the current velocity (the hold is a run-time guard that only makes the gain warier)."""
    noise = table.powers(velocity)
    steady = dataclasses.replace(gain, hold_ms=0.0)
    probe = LowLatencyGain(
        bank, dataclasses.replace(steady, track_s=0.0, oversubtraction=1.0), n_channels=3
    )
    _, ratios = probe.process(residual, noise, collect=True)
    ratios = ratios[:, :, : bank.n_bands]
    # only where the table expects noise (an axis at rest reads a constant: nothing to learn)
    usable = use[:, None, None] & (noise > 1.001 * table.floor[None]) & (ratios > 0)
    logs = np.where(usable, np.clip(np.log(np.where(usable, ratios, 1.0)), -20.0, 20.0), 0.0)
    bias = logs.sum(axis=0) / np.maximum(usable.sum(axis=0), 1)
    probe = LowLatencyGain(
        bank, dataclasses.replace(steady, oversubtraction=1.0), n_channels=3, bias=bias
    )
    _, ratios = probe.process(residual, noise, collect=True)
    alpha = np.ones_like(bias)
    for c in range(alpha.shape[0]):
        for b in range(alpha.shape[1]):
            values = ratios[usable[:, c, b], c, b]
            values = values[np.isfinite(values) & (values > 0)]
            if len(values):
                alpha[c, b] = float(np.quantile(values, gain.opening_quantile))
    probe = LowLatencyGain(bank, steady, n_channels=3, alpha=alpha, bias=bias)
    _, ratios = probe.process(residual, noise, collect=True)
    open_alpha = np.ones(3)
    guard_ref = np.zeros(3)
    for c in range(3):
        where = usable[:, c].any(axis=1)
        values = ratios[where, c, bank.n_bands]
        values = values[np.isfinite(values) & (values > 0)]
        if len(values):
            open_alpha[c] = float(np.quantile(values, gain.open_quantile))
        levels = ratios[where, c, bank.n_bands + 1]
        if len(levels):
            guard_ref[c] = float(np.quantile(levels, gain.guard_quantile)) - math.log(open_alpha[c])
    return alpha, bias, open_alpha, guard_ref


# --- The streaming denoisers --------------------------------------------------------------
_WARM = False


def warm_up() -> None:
    """Compile (or load from numba's cache) every per-sample kernel now, on a few dummy
    samples: the first compile takes seconds, which a live stream must not wait for."""
    global _WARM
    if _WARM:
        return
    hmap = HarmonicMap(
        joint_names=("j",),
        exponent=np.ones(1),
        tau_up_s=np.zeros(1),
        tau_down_s=np.zeros(1),
        min_speed=np.zeros(1),
        line_joint=np.zeros(1, np.int64),
        line_coefficient=np.ones(1),
        line_score_db=np.zeros(1),
        residual_rms=np.ones(3),
    )
    HarmonicCanceller(hmap, sample_rate_hz=100.0, band_hz=(1.0, 40.0), n_channels=3).process(
        np.zeros((2, 3)), np.ones((2, 1))
    )
    bank = FilterBank(sample_rate_hz=100.0, band_hz=(1.0, 40.0), bands=1)
    LowLatencyGain(bank, GainSettings(), n_channels=3).process(np.zeros((2, 3)), np.ones((2, 3, 2)))
    _dense_rows(
        np.zeros((2, 1)),
        np.array([[0.0, 1.0]]),
        np.array([2], np.int64),
        np.array([[-0.5, 1.5]]),
        np.ones((2, 1)),
        np.ones(1, np.int64),
        np.ones(2, np.bool_),
        np.zeros(1),
    )
    _fir(np.ones(3), np.zeros((4, 3)))
    _WARM = True


class SampleMethodDenoiser(FramedDenoiser):
    """`cancel` or `hybrid` as a stream: each push returns the samples that became final
    (output sample k carries input stamp k): `cancel` as soon as their joint state is in,
    `hybrid` `delay` samples (its look-ahead) later."""

    def __init__(
        self,
        model: NoiseModel,
        *,
        method: str = "hybrid",
        channels: str = "per_axis",
        joint_wait_s: float = 0.02,
        floor: float | None = None,
        lookahead_ms: float | None = None,
        output: str | None = None,
        joint_lag_s: float = 0.0,
        noise_gain_db: tuple[tuple[float, float], ...] = (),
        source: str = "",
        adapt: AdaptSettings | None = None,
    ):
        """The stages the model's extras describe: framer, canceller, gain and split
        (hybrid), adaptation."""
        if check_method(method) == "paper":
            raise ConfigError(
                "SampleMethodDenoiser runs `cancel` or `hybrid`; use StreamingDenoiser"
            )
        output = check_output(output, channels)
        self.model = model
        self.method = method
        self.channels = channels
        self.output = output
        self.calibration = MethodCalibration.of(model)
        warm_up()
        cal = self.calibration
        fs = model.sample_rate_hz
        self.settings = FramerSettings.for_model(
            model,
            layout="per_axis",
            joint_wait_s=joint_wait_s,
            with_steadiness=False,
            keep_raw=output == "dropin",
            joint_lag_s=joint_lag_s,
            source=source,
        )
        self._framer = SampleFramer(self.settings, model.n_joints)
        # the gap diagnosis's drift advice: the expected noise follows a level change over
        # the elapsed time from the first sample (as the paper's StreamingDenoiser does)
        self._noise_gain = noise_gain_curve(noise_gain_db)
        self._t0_ns: int | None = None
        # The drop-in output: the lines tracked again in the unfiltered signal (high-passed
        # below the band: gravity and motion never reach their trackers).
        self._lines_input = (
            CarriedFilter(lines_highpass(sample_rate_hz=fs, band_hz=model.band_hz), n_channels=3)
            if output == "dropin"
            else None
        )
        self._canceller = HarmonicCanceller(
            cal.harmonic,
            sample_rate_hz=fs,
            band_hz=model.band_hz,
            n_channels=3,
            settings=cal.canceller,
            unfiltered_inverse=None
            if output != "dropin"
            else highpass_inverse(sample_rate_hz=fs, band_hz=model.band_hz),
        )
        self._gain = self._table = self._split = None
        look = 0  # the gain's look-ahead
        self.delay = 0  # samples from input to output
        if method == "hybrid":
            look = self._build_gain(cal, floor, lookahead_ms, output)
        self._control_delay = self.delay - look
        self._held_residual = np.zeros((self._control_delay, 3))
        self._held_velocity = np.full((self._control_delay, model.n_joints), np.nan)
        # Stamps of the samples inside the look-ahead (-1: synthetic or before the start).
        self._lag_stamps = np.full(self.delay, -1, dtype=np.int64)
        self._last_velocity = np.full(model.n_joints, np.nan)  # of the last sample in
        n_out = 3 if channels == "per_axis" else 1
        self._empty = DenoisedChunk(np.zeros(0, dtype=np.int64), np.zeros((0, n_out)))
        self.samples_out = 0
        self.samples_no_joint_state = 0
        # Online adaptation (core.adapt): with `adapt`, or a model that learnt before.
        self._adaptation: Adaptation | None = None
        if adapt is not None or any(part is not None for part in learnt_state(model)):
            if self._table is not None:
                self._table = AdaptiveTable(self._table)
            adapt = adapt if adapt is not None else AdaptSettings(learn=False)
            threshold = adapt.threshold
            if threshold is None and adapt.learn:
                threshold = stored_threshold(model, method)
            self._adaptation = Adaptation(self, adapt, threshold=threshold)
            self._adaptation.apply_loaded()

    def _build_gain(self, cal: MethodCalibration, floor, lookahead_ms, output: str) -> int:
        """hybrid's gain, table and (drop-in) split; sets `delay`, returns the gain's look-ahead.

        The drop-in output waits for its split (fitted to the robot's calibration recording:
        the longer, the lower the band's edge) and its gain looks as far ahead (the longer,
        the more it removes), but at most MAX_EARLY_OPENING_MS: a gain looking further opens
        that much before a contact, and the ego-vibration it lets through moved onsets 10-20
        ms early (F1 0.30 on a 500 Hz robot whose 40 Hz band edge needs a 16 ms split). What
        the gain is given then waits the difference."""
        fs = self.model.sample_rate_hz
        split = cal.dropin_split if output == "dropin" else None
        gain_lookahead_ms = lookahead_ms
        if lookahead_ms is None and split is not None:
            split_ms = 1e3 * split[1] / fs
            # and never less than the band-pass's delay: the gains are decided on the
            # band-passed signal, the raw one must not pass before them (a 40 Hz wide band
            # at 300 Hz shows a tap 25 ms late: a 4 ms split let 70 % of each tap go)
            band, order = self.model.band_hz, self.model.band_order
            late_ms = 1e3 / fs * bandpass_delay(sample_rate_hz=fs, band_hz=band, order=order)
            gain_lookahead_ms = max(
                cal.gain.lookahead_ms, min(split_ms, MAX_EARLY_OPENING_MS), late_ms
            )
        self._gain, self._table = _hybrid_gain(cal, floor, gain_lookahead_ms)
        look = self._gain.delay
        self.delay = look
        if output == "dropin":
            if lookahead_ms is None and split is not None:
                self.delay = max(look, split[1])
            if split is None or split[1] != self.delay:  # another look-ahead: the plain design
                band = self.model.band_hz
                split = split_taps(sample_rate_hz=fs, band_hz=band, delay=self.delay), self.delay
            self._split = DropInSplit(*split)
        return look

    # --- API -------------------------------------------------------------------
    @property
    def delay_samples(self) -> tuple[int, int]:
        """(min, max) samples between a sample's arrival and its output (joint wait aside)."""
        return self.delay, self.delay

    def _pop(self):
        return self._framer.pop()

    @property
    def stats(self) -> DenoiserStats:
        table = self._table
        return DenoiserStats.of(
            self._framer.stats,
            method=self.method,
            samples_out=self.samples_out,
            samples_no_joint_state=self._framer.samples_no_joint_state,
            rate_checked=self._framer.rate_checked,
            delay_samples=self.delay,
            frequency_correction=self._canceller.state.correction.round(4).tolist(),
            samples_unmeasured=None if table is None else table.samples_unmeasured,
            samples_out_of_grid=None if table is None else table.samples_out_of_grid,
        )

    # --- internals ---------------------------------------------------------------
    def _process(self, batches) -> DenoisedChunk:
        if not batches:
            return self._empty
        stamps_out, values_out = [], []
        for batch in _joined(batches):
            if len(batch):
                s, v = self._run(batch.stamps_ns, batch.values, batch.velocity, batch.raw)
                stamps_out.append(s)
                values_out.append(v)
            if batch.ends_segment and self.delay:
                s, v = self._release_lookahead()
                stamps_out.append(s)
                values_out.append(v)
                if self._adaptation is not None:
                    self._adaptation.observe(s, v)
            if batch.ends_segment and self._adaptation is not None:
                self._adaptation.end_segment()
        if not stamps_out:
            return self._empty
        chunk = DenoisedChunk(np.concatenate(stamps_out), np.concatenate(values_out))
        self.samples_out += len(chunk)
        return chunk

    def _run(self, stamps, values, velocity, raw):
        """Band-passed `values` (and `raw`, for the drop-in output) through the method."""
        if self._adaptation is not None:  # in pieces, each ending where what it learns applies
            return self._adaptation.run(stamps, values, velocity, raw)
        return self._run_piece(stamps, values, velocity, raw)[:2]

    def _run_piece(self, stamps, values, velocity, raw):
        """The released (stamps, values) of a piece of the stream, and the canceller's
        residual (what an adapting stream's residual table learns from: core.adapt)."""
        unfiltered = None
        if self._lines_input is not None:
            tracked = self._lines_input.process(raw.T).T
            residual, lines = self._canceller.process(values, velocity, unfiltered=tracked)
            unfiltered = (raw, raw - lines)
        else:
            residual = self._canceller.process(values, velocity)
        if self._gain is None:
            out = self._output(stamps, residual if unfiltered is None else unfiltered[1])
            return (*out, residual)
        if len(velocity):
            self._last_velocity = velocity[-1]
        return (*self._gained(stamps, residual, velocity, unfiltered), residual)

    # --- adaptation (core.adapt) ------------------------------------------------------
    @property
    def adapting(self) -> bool:
        """Whether the model goes on learning (`adapt` given, learning on)."""
        return self._adaptation is not None and self._adaptation.settings.learn

    @property
    def adaptation_stats(self) -> AdaptStats | None:
        """What the adaptation counted; None without adaptation."""
        return None if self._adaptation is None else self._adaptation.stats

    def adapted_model(self) -> NoiseModel:
        """The model with what was learnt online so far in its extras (`adapt.*`): saved,
        it denoises with the learnt cells and corrections, and goes on learning with adapt."""
        if self._adaptation is None:
            raise ConfigError("adapted_model: this denoiser does not adapt (adapt not given)")
        extras = {
            **without_learnt(self.model.extras),
            # the map in use: the calibrated one, or one LineFinder found online
            **self.calibration.harmonic.to_arrays(HARMONIC_PREFIX),
            **self._adaptation.extras(),
        }
        provenance = {
            **self.model.provenance,
            "adapted_from": self.model.provenance.get("path", ""),
            "adapted_stats": str(self._adaptation.stats.as_dict()),
        }
        return self.model.replace(extras=extras, provenance=provenance)

    def reset_adaptation(self) -> None:
        """Back to the calibrated model: what was learnt (online, or saved in the model) is
        forgotten from the next sample on; learning goes on if it was on."""
        if self._adaptation is None:
            raise ConfigError("reset_adaptation: this denoiser does not adapt (adapt not given)")
        self._adaptation.reset()

    def _gained(self, stamps, residual, velocity, unfiltered=None):
        if self._control_delay:
            residual, self._held_residual = _delayed(self._held_residual, residual)
            velocity, self._held_velocity = _delayed(self._held_velocity, velocity)
        rows, index = self._table.rows(velocity)
        scale = self._power_scale(stamps)
        stamps, self._lag_stamps = _delayed(self._lag_stamps, stamps)
        if unfiltered is None:
            out = self._gain.process(residual, rows, index=index, power_scale=scale)
            return self._output(stamps, out)
        low, high = self._split.process(*unfiltered)
        _, high = self._gain.process(
            residual, rows, index=index, unfiltered=high, power_scale=scale
        )
        return self._output(stamps, low + high)

    def _power_scale(self, stamps: np.ndarray) -> np.ndarray | None:
        """Per sample, the factor on the expected noise power that `noise_gain_db` gives at
        its time since the first sample (a synthetic sample: the last real one's); None
        without a level change."""
        if self._noise_gain is None:
            return None
        real = stamps >= 0
        if self._t0_ns is None and real.any():
            self._t0_ns = int(stamps[real][0])
        t0 = self._t0_ns if self._t0_ns is not None else 0
        held = np.maximum.accumulate(np.where(real, stamps, t0))
        knots_s, gain_db = self._noise_gain
        return 10.0 ** (np.interp((held - t0) / NS_PER_S, knots_s, gain_db) / 10.0)

    def _release_lookahead(self):
        """The segment ended: silence through the gain releases the samples it holds, then
        it starts afresh. The silence keeps the last joint velocity (NaN would open the gain
        on the last samples) and never reaches the canceller (it would drag its trackers)."""
        d = self.delay
        velocity = np.broadcast_to(self._last_velocity, (d, self.model.n_joints))
        zeros = np.zeros((d, 3))
        out = self._gained(
            np.full(d, -1, np.int64),
            zeros,
            np.array(velocity),
            None if self._split is None else self._split.held(d),
        )
        self._gain.reset_signal()
        if self._split is not None:
            self._split.reset()
            self._lines_input.reset()
        self._lag_stamps[:] = -1
        self._held_residual[:] = 0.0
        self._held_velocity[:] = np.nan
        self._last_velocity = np.full(self.model.n_joints, np.nan)
        return out

    def _output(self, stamps, cleaned):
        """The released samples (synthetic ones dropped), summed for `combined`."""
        real = stamps >= 0
        if self.channels == "combined":
            cleaned = cleaned.sum(axis=1, keepdims=True)
        return stamps[real], cleaned[real]


def _hybrid_gain(cal: MethodCalibration, floor, lookahead_ms) -> tuple:
    """`hybrid`'s gain stage and residual table; `floor`, `lookahead_ms`: None for the
    calibrated ones."""
    gain = cal.gain
    if floor is not None:
        gain = dataclasses.replace(gain, floor=floor)
    if lookahead_ms is not None:
        gain = dataclasses.replace(gain, lookahead_ms=lookahead_ms)
    model = cal.residual
    bank = FilterBank(
        sample_rate_hz=model.sample_rate_hz,
        band_hz=model.band_hz,
        bands=gain.bands,
        bandwidth=gain.bandwidth,
    )
    stage = LowLatencyGain(
        bank,
        gain,
        n_channels=3,
        alpha=cal.alpha,
        bias=cal.bias,
        open_alpha=cal.open_alpha,
        guard_ref=cal.guard_ref,
    )
    return stage, ResidualTable(model, bank)


def _delayed(line: np.ndarray, new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A delay line of len(line) samples: (the len(new) samples that leave it, the line
    after `new` entered it)."""
    both = np.concatenate([line, new])
    return both[: len(new)], both[len(new) :]


#: Output values per tile of the FIRs below (24 kB: in L1 cache with the input they read; a
#: pass of every tap over a whole 30 s chunk went to memory, at 2.5x the time).
_FIR_TILE = 3072


@numba.njit(cache=True)
def _fir(taps, history):
    """(n, C) outputs of the symmetric FIR `taps` (odd length N) over `history` (N - 1
    samples before, then the n new): one multiply per pair of equal taps; the sums in one
    order whatever the chunking (scipy's lfilter with carried state differs in the last
    bit). Rows are contiguous, so a tap's terms for a run of samples and every channel are
    one flat run: the innermost loop vectorises, tile by tile."""
    N = len(taps)
    mid = (N - 1) // 2
    C = history.shape[1]
    x = np.ascontiguousarray(history).reshape(-1)
    out = np.empty((history.shape[0] - (N - 1), C))
    o = out.reshape(-1)
    for start in range(0, len(o), _FIR_TILE):
        ot = o[start : start + _FIR_TILE]
        m = len(ot)
        t = taps[mid]
        xm = x[mid * C + start : mid * C + start + m]
        for i in range(m):
            ot[i] = t * xm[i]
        for k in range(mid):
            t = taps[k]
            near = x[k * C + start : k * C + start + m]
            far = x[(N - 1 - k) * C + start : (N - 1 - k) * C + start + m]
            for i in range(m):
                ot[i] += t * (far[i] + near[i])
    return out


@numba.njit(cache=True)
def _fir_lowdelay(taps, history):
    """_fir for taps of no symmetry (a low-delay split): the plain sum, same layout."""
    N = len(taps)
    C = history.shape[1]
    x = np.ascontiguousarray(history).reshape(-1)
    out = np.zeros((history.shape[0] - (N - 1), C))
    o = out.reshape(-1)
    for start in range(0, len(o), _FIR_TILE):
        ot = o[start : start + _FIR_TILE]
        m = len(ot)
        for k in range(N):
            t = taps[k]
            xk = x[(N - 1 - k) * C + start : (N - 1 - k) * C + start + m]
            for i in range(m):
                ot[i] += t * xk[i]
    return out


def _joined(batches: list[SampleBatch]) -> list[SampleBatch]:
    """Batches of one segment released together, as one (every stage holds its state
    explicitly: one pass over them gives the same samples, at half the calls per push)."""
    out: list[SampleBatch] = []
    for batch in batches:
        last = out[-1] if out else None
        if last is None or last.ends_segment or not len(last) or not len(batch):
            out.append(batch)
            continue
        out[-1] = SampleBatch(
            np.concatenate([last.stamps_ns, batch.stamps_ns]),
            np.concatenate([last.values, batch.values]),
            np.concatenate([last.velocity, batch.velocity]),
            batch.ends_segment,
            None if batch.raw is None else np.concatenate([last.raw, batch.raw]),
        )
    return out


class DropInSplit:
    """The drop-in output's split, `delay` samples late: `process(raw, cleaned)` (`cleaned`
    = raw less its lines) gives (low, high): `low` the raw samples through the split's
    low-pass (core.filters.split_for), gravity and motion untouched; `high` the cleaned
    samples delayed less their own low part, in the band the cleaned samples themselves (an
    IIR split would shift their phase), for the gains; low + high is the raw signal late,
    less its lines."""

    def __init__(self, taps: np.ndarray, delay: int, n_channels: int = 3):
        self.taps = np.asarray(taps, float)
        self.delay = int(delay)
        symmetric = 2 * self.delay + 1 == len(self.taps) and np.array_equal(taps, taps[::-1])
        self._fir = _fir if symmetric else _fir_lowdelay
        self.n_channels = int(n_channels)
        self.reset()

    def reset(self) -> None:
        """A new segment: the FIRs' histories are filled with its first samples (as if the
        stream had been steady before it: gravity passes from the first sample on)."""
        self._raw: np.ndarray | None = None
        self._cleaned: np.ndarray | None = None
        self._last = (np.zeros((1, self.n_channels)), np.zeros((1, self.n_channels)))

    def held(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """n more samples of each input held at its last value: what releases the last
        `delay` samples at a segment's end with gravity still in them."""
        return np.repeat(self._last[0], n, axis=0), np.repeat(self._last[1], n, axis=0)

    def _low(self, history: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        both = np.concatenate([history, np.asarray(x, float)])
        late = both[len(self.taps) - 1 - self.delay : len(both) - self.delay]
        return self._fir(self.taps, both), late, both[len(both) - len(history) :]

    def process(self, raw: np.ndarray, cleaned: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self._raw is None:
            if not len(raw):
                return np.zeros((0, self.n_channels)), np.zeros((0, self.n_channels))
            size = (len(self.taps) - 1, 1)
            self._raw = np.tile(np.asarray(raw[:1], float), size)
            self._cleaned = np.tile(np.asarray(cleaned[:1], float), size)
        self._last = (np.asarray(raw[-1:], float), np.asarray(cleaned[-1:], float))
        low_raw, _, self._raw = self._low(self._raw, raw)
        low_cleaned, late, self._cleaned = self._low(self._cleaned, cleaned)
        return low_raw, late - low_cleaned


def make_denoiser(model: NoiseModel, method: str | None = None, *, output=None, **options):
    """The streaming denoiser of `method` for `model` (one push interface for all). Options
    the method does not take are refused (ConfigError); one at its neutral value
    (oversubtraction 1, floor 0, no joint lag) is no option. `output`: "dropin" (the default
    per axis) or "bandpassed", for every method."""
    method = resolve_method(model, method)
    if method == "paper":
        if options.pop("lookahead_ms", None) is not None:
            raise ConfigError(
                "method paper: lookahead_ms applies to `hybrid` only (paper: a block)"
            )
        if options.get("floor") is None:
            options.pop("floor", None)
        if options.pop("adapt", None) is not None:
            raise ConfigError("method paper: adapt applies to `cancel` and `hybrid`")
        return StreamingDenoiser(model, output=output, **options)
    defaults = {
        "oversubtraction": 1.0,
        "floor": 0.0,
        "joint_lag_s": 0.0,
        "noise_gain_db": (),
        "adapt": None,
    }
    for name, value in defaults.items():
        if name in options and (options[name] == value or options[name] is None):
            del options[name]
    paper_only = {"oversubtraction", "include_std", "rule"} & set(options)
    if paper_only:
        raise ConfigError(f"method {method}: option(s) {sorted(paper_only)} apply to `paper` only")
    return SampleMethodDenoiser(model, method=method, output=output, **options)


def denoise_batch_method(
    sensor_stamps_ns: np.ndarray,
    accel: np.ndarray,
    joint_stamps_ns: np.ndarray,
    joint_velocity: np.ndarray,
    model: NoiseModel,
    *,
    method: str | None = None,
    channels: str = "per_axis",
    chunk_s: float = 30.0,
    **options,
) -> tuple[np.ndarray, np.ndarray, DenoiserStats]:
    """Whole arrays through the streaming denoiser of `method` (as denoise_batch does for
    `paper`): (stamps (K,), values (K, C), stats)."""
    denoiser = make_denoiser(model, method, channels=channels, **options)
    return denoiser.run_arrays(sensor_stamps_ns, accel, joint_stamps_ns, joint_velocity, chunk_s)


def method_delay_ms(model: NoiseModel, method: str | None = None, **options) -> float:
    """Algorithmic delay (ms) of the denoiser `make_denoiser(model, method, **options)`
    builds (paper: a block; cancel and hybrid: their drop-in output's is the longer)."""
    return make_denoiser(model, method, **options).delay_ms
