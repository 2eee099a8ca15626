"""egovib_ros.core.blocks: the analysis window's hop-shifted copies sum to one, so overlap-add
of unmodified windowed blocks gives the input back; block settings are checked."""

from __future__ import annotations

import numpy as np
import pytest

from egovib_ros.core.blocks import analysis_window, n_bins, overlap_add, validate_blocking
from egovib_ros.errors import ConfigError


@pytest.mark.parametrize("block_length, hop", [(64, 32), (64, 16), (128, 64), (256, 32)])
def test_windowed_blocks_overlap_add_to_the_input(block_length, hop):
    window = analysis_window(block_length, hop)
    shifted = np.zeros(block_length * 4)
    for start in range(0, len(shifted) - block_length + 1, hop):
        shifted[start : start + block_length] += window
    steady = slice(block_length, len(shifted) - block_length)
    np.testing.assert_allclose(shifted[steady], 1.0, atol=1e-12)
    x = np.random.default_rng(0).normal(size=(20 * hop + block_length, 2))
    starts = np.arange(0, len(x) - block_length + 1, hop)
    blocks = np.stack([x[s : s + block_length] * window[:, None] for s in starts])
    y = overlap_add(blocks, hop)
    assert y.shape == ((len(starts) - 1) * hop + block_length, 2)
    inner = slice(block_length - hop, len(starts) * hop)  # every sample covered L/hop times
    np.testing.assert_allclose(y[inner], x[inner], atol=1e-12)
    assert n_bins(block_length) == len(np.fft.rfftfreq(block_length))


@pytest.mark.parametrize(
    "block_length, hop, named",
    [(3, 1, "block_length"), (64.0, 32, "block_length"), (64, 24, "hop"), (64, 64, "hop"),
     (64, 0, "hop")],
)  # fmt: skip
def test_bad_blocking_is_a_config_error_naming_the_setting(block_length, hop, named):
    with pytest.raises(ConfigError, match=f"^{named}: "):
        validate_blocking(block_length, hop)
