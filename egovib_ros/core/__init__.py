"""The algorithm, free of ROS (numpy, scipy, numba): the noise model, calibration, the
denoisers (core.methods names them), framing and the contact detector."""

from egovib_ros.core.blocks import analysis_window, overlap_add
from egovib_ros.core.calibration import CalibrationAccumulator, calibrate_arrays
from egovib_ros.core.filters import BandPass, channel_matrix
from egovib_ros.core.noise_model import NoiseModel
from egovib_ros.core.stream import (
    MAX_BAD_SHARE,
    CalibrationStats,
    DenoiserStats,
    StreamConsumer,
    check_bad_share,
)
from egovib_ros.core.subtraction import StreamingDenoiser, denoise_batch
from egovib_ros.core.velocity import HELD, MATCHED, MISSING, JointVelocity, block_mean_velocity

__all__ = [
    "analysis_window",
    "overlap_add",
    "CalibrationAccumulator",
    "calibrate_arrays",
    "BandPass",
    "channel_matrix",
    "NoiseModel",
    "CalibrationStats",
    "DenoiserStats",
    "StreamConsumer",
    "MAX_BAD_SHARE",
    "check_bad_share",
    "StreamingDenoiser",
    "denoise_batch",
    "HELD",
    "MATCHED",
    "MISSING",
    "block_mean_velocity",
    "JointVelocity",
]
