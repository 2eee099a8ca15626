"""Block processing settings: analysis window, framing and overlap-add (paper section 2)."""

from __future__ import annotations

import numpy as np
from scipy import signal

from egovib_ros.errors import ConfigError

WINDOW_NAME = "hamming_periodic_cola"


def analysis_window(block_length: int, hop: int) -> np.ndarray:
    """Periodic Hamming window scaled so its hop-shifted copies sum to exactly one.

    With that scaling, overlap-add of unmodified blocks reconstructs the input, which
    is what makes "zero noise estimate = band-passed input" hold.
    """
    validate_blocking(block_length, hop)
    window = signal.get_window("hamming", block_length, fftbins=True)
    window = window * (hop / window.sum())
    if not signal.check_COLA(window, block_length, block_length - hop, tol=1e-10):
        raise ConfigError(
            f"hop {hop} does not give a constant overlap-add for a "
            f"{block_length}-sample Hamming window"
        )
    return window


def validate_blocking(block_length: int, hop: int) -> None:
    if not isinstance(block_length, (int, np.integer)) or block_length < 4:
        raise ConfigError(f"block_length: must be an integer >= 4, got {block_length!r}")
    if not isinstance(hop, (int, np.integer)) or hop < 1 or block_length % hop:
        raise ConfigError(f"hop: must divide block_length ({block_length}), got {hop!r}")
    if block_length // hop < 2:
        raise ConfigError(f"hop: blocks must overlap (hop < block_length), got hop={hop}")


def n_bins(block_length: int) -> int:
    return block_length // 2 + 1


def overlap_add(blocks: np.ndarray, hop: int) -> np.ndarray:
    """Overlap-add (B, L, C) blocks spaced `hop` apart into (B*hop + L - hop, C) samples."""
    n_blocks, block_length, n_channels = blocks.shape
    overlap = block_length // hop
    out = np.zeros(((n_blocks + overlap - 1) * hop, n_channels))
    # Segment i of every block lands `i` hops after the block start: one vectorised add per segment.
    segments = blocks.reshape(n_blocks, overlap, hop, n_channels)
    for i in range(overlap):
        out[i * hop : (i + n_blocks) * hop] += segments[:, i].reshape(n_blocks * hop, n_channels)
    return out
