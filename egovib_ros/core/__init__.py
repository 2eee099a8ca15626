"""The paper's algorithm, free of ROS: numpy/scipy only.

Public surface:
    NoiseModel                        noise table, Eq. 5/6 estimate, .npz I/O
    CalibrationAccumulator            one-pass per-cell statistics -> NoiseModel
    StreamingDenoiser, denoise_batch  spectral subtraction, streaming and batch
    StreamConsumer, feed              the push protocol of every streaming class; its driver
    block_mean_velocity               per-block joint velocity matched by stamps
    JointVelocity                     velocity from positions for drivers without it
    BandPass, channel_matrix          axis handling and band-pass
    analysis_window, overlap_add      block-processing primitives
"""

from egovib_ros.core.blocks import analysis_window, overlap_add
from egovib_ros.core.calibration import CalibrationAccumulator, calibrate_arrays
from egovib_ros.core.filters import BandPass, channel_matrix, design_bandpass
from egovib_ros.core.noise_model import MODEL_CHANNELS, NoiseModel
from egovib_ros.core.stream import (
    MAX_BAD_SHARE,
    BlockFramer,
    Blocks,
    CalibrationStats,
    DenoiserStats,
    FramerSettings,
    StreamConsumer,
    check_bad_share,
    feed,
    frame_batch,
)
from egovib_ros.core.subtraction import (
    DenoisedChunk,
    StreamingDenoiser,
    SubtractionSettings,
    denoise_batch,
    paper_rule,
)
from egovib_ros.core.velocity import (
    HELD,
    MATCHED,
    MISSING,
    VELOCITY_SOURCES,
    JointVelocity,
    block_mean_velocity,
)

__all__ = [
    "analysis_window",
    "overlap_add",
    "CalibrationAccumulator",
    "calibrate_arrays",
    "BandPass",
    "channel_matrix",
    "design_bandpass",
    "MODEL_CHANNELS",
    "NoiseModel",
    "BlockFramer",
    "Blocks",
    "FramerSettings",
    "CalibrationStats",
    "DenoiserStats",
    "StreamConsumer",
    "feed",
    "frame_batch",
    "MAX_BAD_SHARE",
    "check_bad_share",
    "DenoisedChunk",
    "StreamingDenoiser",
    "SubtractionSettings",
    "denoise_batch",
    "paper_rule",
    "HELD",
    "MATCHED",
    "MISSING",
    "block_mean_velocity",
    "JointVelocity",
    "VELOCITY_SOURCES",
]
