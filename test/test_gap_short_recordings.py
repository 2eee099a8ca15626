"""The diagnosis's decision on short recordings (a few seconds of a real flight): the
confidence of `none`, the in-sample drift look's knot spacing, the drift trend's unit.

Pins the fixes of the real-flight injections (docs/gap_validation_real.md): `none` was
reported with confidence 0.97 beside a drift term that took 0.6 dB off the baseline at
p = 0.0066; the in-sample time trend of an 8.5 s part had knots 1.25 chunks apart (a local
level that carried a flip's misfit into the next chunk); the per-minute trend column of an
8 s training span ranged over 0.11 and was shrunk to nothing.
"""

from __future__ import annotations

import numpy as np
import pytest
from gaptables import synthetic_table

from egovib_ros.gap import diagnose as D
from egovib_ros.gap.baseline import simulator_cells
from egovib_ros.gap.effects import effect_regressors, fit_scales, trend_unit_s


def _decide(gain_per_block: float, p_value: float, seed: int = 0):
    """`_verdict` on 20 segments of 30 blocks: one candidate whose held-out deviance gain
    per block is `gain_per_block` on average (noisy), the others none."""
    rng = np.random.default_rng(seed)
    segments = np.repeat(np.arange(20), 30)
    base = 0.6 + 0.05 * rng.standard_normal(len(segments))
    loss = {"refit": base}
    candidates = []
    for k, name in enumerate(D.EFFECTS):
        gain = gain_per_block if k == 0 else 0.0
        loss[name] = base - gain - 0.02 * rng.standard_normal(len(segments))
        candidates.append(
            {
                "effect": name,
                "p_value": p_value if k == 0 else 0.5,
                "deviance_reduction": float(np.mean(base - loss[name])),
                "gap_reduction_decisive": 0.5 if k == 0 else 0.0,
            }
        )
    return D._verdict(candidates, loss, D.ALPHA, segments, np.random.default_rng(1))


def test_none_beside_a_large_but_insignificant_gain_has_low_confidence():
    verdict, confidence = _decide(0.09, p_value=0.0066)  # the drift of the real flight
    assert verdict == "none"
    assert confidence < 0.05


def test_none_with_nothing_gaining_has_high_confidence():
    verdict, confidence = _decide(0.0, p_value=0.0066)  # significant but no gain
    assert verdict == "none"
    assert confidence > 0.95


def test_a_significant_large_gain_is_named_as_before():
    verdict, confidence = _decide(0.09, p_value=1e-4)
    assert verdict == D.EFFECTS[0]
    assert confidence > 0.95


def test_in_sample_drift_knots_span_several_chunks_on_a_short_recording():
    table = synthetic_table(duration_s=10.0, seed=2)
    out = D._interleaved_drift(table, simulator_cells(table), 8, np.random.default_rng(0))
    span = float(table.t_mid_s[-1] - table.t_mid_s[0])
    chunk = span / D.INTERLEAVE_MIN_CHUNKS
    knot_spacing = span / (out["knots"] - 1)
    assert knot_spacing >= D.INTERLEAVE_KNOT_CHUNKS * chunk - 1e-6
    assert out["knots"] == 5
    # effect-free: the trend does not win on held-out chunks
    assert out["p_value"] > 0.01


def test_long_recordings_keep_their_knots():
    """120 s (the blind validations): chunks 4 s, knots 10 s, as before."""
    span = 120.0
    chunk = min(D.INTERLEAVE_CHUNK_S, span / D.INTERLEAVE_MIN_CHUNKS)
    knot = max(
        min(D.INTERLEAVE_KNOT_S, span / D.INTERLEAVE_MIN_KNOTS), D.INTERLEAVE_KNOT_CHUNKS * chunk
    )
    assert (chunk, knot) == (4.0, 10.0)


def test_drift_trend_column_spans_the_training_range_on_a_short_recording():
    table = synthetic_table(duration_s=10.0, seed=2)
    train = table.t_mid_s < 8.0
    scales = fit_scales(table, train)
    x, names = effect_regressors("drift", table, scales)
    trend = x[:, names.index("t_min")]
    assert np.ptp(trend[train]) == pytest.approx(1.0)
    # a minute stays the unit once the training span is longer
    scales.t_end_s = scales.t_ref_s + 96.0
    assert trend_unit_s(scales) == 60.0
