"""Ours and what a user would otherwise pick, on one footing.

Every method maps a recording (raw gyro + motor commands) to the paper's 1-D measurement
signal on the input stamps: axes summed, band-passed by the core's causal filter with the
profile's band (as egovib_ros.evaluation.baselines does for the PR2), so metrics compare
them sample by sample.

  raw            band-pass only                                                   delay 0
  ours           the paper's spectral subtraction keyed on all four motor
                 commands: the 4-joint quadcopter profile, calibrated from free
                 flight (core calibrate_arrays(sweep="free"), denoise_batch)       L / fs
  ours_L64       the same with the paper's 64-sample blocks (hop 32), to show
                 the profile's choice of L = 32                                   64 / fs
  global         (a) one average noise spectrum (mean + std over every
                 calibration block), subtracted whatever the motors do: the core
                 with a one-cell table                                            L / fs
  mean_command   (b) the paper's table keyed on one number, the mean motor
                 command: the core with a 1-joint profile                         L / fs
  notch_q5       (c) harmonic notch bank keyed on each motor's command, 3
                 harmonics, Q 5 (Betaflight RPM filter defaults)                  0 (IIR)
  notch_q2       (c) the same with Q 2 (ArduPilot's throttle-based setup,
                 bandwidth = half the centre frequency)                           0 (IIR)

Baseline (d), the firmware's own filtered gyro, is a signal of the log, not a method:
see experiment.py.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from egovib_research.experiments.flight.notch import (
    ARDUPILOT_Q,
    BETAFLIGHT_Q,
    HarmonicNotchBank,
    fit_speed_frequency_map,
    hold,
)
from egovib_ros.core import BandPass, calibrate_arrays, denoise_batch, filters
from egovib_ros.evaluation.metrics import json_safe
from egovib_ros.robot import RobotProfile

LABELS = {
    "raw": "band-pass only (raw)",
    "ours": "ours: paper's subtraction keyed on 4 motor commands",
    "ours_L64": "ours with the paper's block, L = 64 (64 ms)",
    "global": "(a) global average spectrum, not keyed",
    "mean_command": "(b) paper's table keyed on mean motor command (1-D)",
    "notch_q5": "(c) harmonic notch bank per motor, 3 harmonics, Q 5 (Betaflight)",
    "notch_q2": "(c) harmonic notch bank per motor, 3 harmonics, Q 2 (ArduPilot)",
}
METHODS = tuple(LABELS)


def on_input_stamps(
    out_stamps: np.ndarray, values: np.ndarray, in_stamps: np.ndarray
) -> np.ndarray:
    """Sum the output channels and place them on the input stamps (0 where a sample is missing).

    Denoised samples carry the stamp of the input sample they replace, so matching
    is by stamp: dropped inputs or a shorter output (e.g. a live node stopped before
    flushing) leave zeros, never a shift.
    """
    summed = np.asarray(values, float).sum(axis=1)
    if len(out_stamps) == len(in_stamps) and np.array_equal(out_stamps, in_stamps):
        return summed
    result = np.zeros(len(in_stamps))
    index = np.searchsorted(in_stamps, out_stamps)
    ok = (index < len(in_stamps)) & (in_stamps[np.minimum(index, len(in_stamps) - 1)] == out_stamps)
    result[index[ok]] = summed[ok]
    return result


def single_joint_profile(
    profile: RobotProfile, joint: str, *, steps: int | None = None
) -> RobotProfile:
    """The robot's profile with one synthetic one-directional joint (0..1) instead of its own."""
    return dataclasses.replace(
        profile,
        name=f"{profile.name}_{joint}",
        joint_names=(joint,),
        max_speed=(1.0,),
        bidirectional=(False,),
        steps=profile.steps if steps is None else steps,
        source="",
    )


class SpectralTable:
    """The core's spectral subtraction with a profile and a way to get its joint 'velocities'."""

    def __init__(self, profile: RobotProfile, joints, *, channels: str = "combined"):
        self.profile = profile
        self.joints = joints  # rec -> (M, J) joint velocities on rec.joint_stamps_ns
        self.channels = channels
        self.model = None
        self.calibration_stats = None  # core.CalibrationStats after fit
        self.denoise_stats = None  # core.DenoiserStats after run

    @property
    def delay_ms(self) -> float:
        return 1e3 * self.profile.block_length / self.profile.rate_hz

    def fit(self, rec) -> "SpectralTable":
        # no-contact free motion: every steady block to its nearest cell of the profile's grid
        self.model, self.calibration_stats = calibrate_arrays(
            rec.sensor_stamps_ns,
            rec.sensor,
            rec.joint_stamps_ns,
            self.joints(rec),
            profile=self.profile,
            sweep="free",
            source=self.profile.name,
        )
        return self

    def run(self, rec) -> np.ndarray:
        stamps, values, self.denoise_stats = denoise_batch(
            rec.sensor_stamps_ns,
            rec.sensor,
            rec.joint_stamps_ns,
            self.joints(rec),
            self.model,
            channels=self.channels,
            output="bandpassed",  # scored as band-passed signals, like every method here
        )
        return on_input_stamps(stamps, values, rec.sensor_stamps_ns)

    def info(self) -> dict:
        model = self.model
        info = {
            "profile": self.profile.name,
            "joints": list(self.profile.joint_names),
            "block_length": self.profile.block_length,
            "hop": self.profile.hop,
            "calibration": json_safe(self.calibration_stats.as_dict()),
            "coverage": json_safe(model.coverage()),
        }
        if self.denoise_stats is not None:
            info["denoise"] = json_safe(self.denoise_stats.as_dict())
        return info


class NotchMethod:
    """Baseline (c): the harmonic notch bank with a speed -> frequency map fitted on calibration."""

    delay_ms = 0.0

    def __init__(self, profile: RobotProfile, *, q: float):
        self.profile = profile
        self.q = float(q)
        self.bank: HarmonicNotchBank | None = None

    def fit(self, rec) -> "NotchMethod":
        motors = hold(rec.joint_stamps_ns, rec.joint_velocity, rec.sensor_stamps_ns)
        frequency_map = fit_speed_frequency_map(
            rec.sensor.sum(axis=1), motors, self.profile.rate_hz
        )
        self.bank = HarmonicNotchBank(frequency_map, sample_rate_hz=self.profile.rate_hz, q=self.q)
        return self

    def run(self, rec) -> np.ndarray:
        notched = self.bank.apply(
            rec.sensor_stamps_ns, rec.sensor.sum(axis=1), rec.joint_stamps_ns, rec.joint_velocity
        )
        band = BandPass(
            sample_rate_hz=self.profile.rate_hz,
            band_hz=self.profile.band_hz,
            order=self.profile.band_order,
            n_channels=1,
        )
        return band.process(notched[None, :])[0]

    def info(self) -> dict:
        return {
            "map": self.bank.frequency_map.to_dict(),
            "q": self.q,
            "harmonics": self.bank.harmonics,
            "min_hz": self.bank.min_hz,
            "max_hz": self.bank.max_hz,
            "update_every_samples": self.bank.update_samples,
        }


class BandPassOnly:
    delay_ms = 0.0

    def __init__(self, profile: RobotProfile):
        self.profile = profile

    def fit(self, rec) -> "BandPassOnly":
        return self

    def run(self, rec) -> np.ndarray:
        return filters.combined_bandpassed(rec.sensor, self.profile)

    def info(self) -> dict:
        return {"band_hz": list(self.profile.band_hz), "order": self.profile.band_order}


def build_methods(profile: RobotProfile, names=METHODS) -> dict:
    """The methods by name, not yet fitted."""
    makers = {
        "raw": lambda: BandPassOnly(profile),
        "ours": lambda: SpectralTable(profile, lambda rec: rec.joint_velocity),
        "ours_L64": lambda: SpectralTable(
            dataclasses.replace(
                profile, name=f"{profile.name}_L64", block_length=64, hop=32, source=""
            ),
            lambda rec: rec.joint_velocity,
        ),
        "global": lambda: SpectralTable(
            single_joint_profile(profile, "constant", steps=1),
            lambda rec: np.zeros((len(rec.joint_stamps_ns), 1)),
        ),
        "mean_command": lambda: SpectralTable(
            single_joint_profile(profile, "mean_command"),
            lambda rec: rec.joint_velocity.mean(axis=1, keepdims=True),
        ),
        "notch_q5": lambda: NotchMethod(profile, q=BETAFLIGHT_Q),
        "notch_q2": lambda: NotchMethod(profile, q=ARDUPILOT_Q),
    }
    unknown = [n for n in names if n not in makers]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; expected some of {list(makers)}")
    return {name: makers[name]() for name in names}
