"""core.harmonic: the speed -> line-frequency map, its fit, and the canceller."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import signal

from egovib_ros.core import harmonic
from egovib_ros.core.harmonic import (
    CancellerSettings,
    HarmonicCanceller,
    HarmonicMap,
    fit_harmonic_map,
    fold,
)
from egovib_ros.errors import ConfigError, ModelFileError

FS = 1000.0
BAND = (60.0, 450.0)


def two_joint_map(*, coefficient=(200.0, 150.0), exponent=(1.0, 0.8), lag_s=0.0) -> HarmonicMap:
    return HarmonicMap(
        joint_names=("a", "b"),
        exponent=np.array(exponent),
        tau_up_s=np.full(2, lag_s),
        tau_down_s=np.full(2, lag_s),
        min_speed=np.full(2, 0.05),
        line_joint=np.array([0, 0, 1, 1]),
        line_coefficient=np.array(
            [coefficient[0], 2 * coefficient[0], coefficient[1], 1.5 * coefficient[1]]
        ),
        line_score_db=np.zeros(4),
        residual_rms=np.full(3, 0.1),
    )


def robot(duration_s: float, *, seed: int, truth: HarmonicMap, scale=(1.0, 1.0), noise=0.05):
    """Band-passed 3-axis signal of two joints whose lines follow `truth` with the real
    speed `scale` x the reported one (a proxy a few % off), amplitude and phase drifting."""
    rng = np.random.default_rng(seed)
    n = int(duration_s * FS)
    sos = signal.butter(2, 0.4, fs=FS, output="sos")
    speed = np.empty((n, 2))
    for j in range(2):
        walk = signal.sosfiltfilt(sos, rng.normal(size=n + 2000))[1000:-1000]
        speed[:, j] = np.clip(0.6 + 0.25 * walk / walk.std(), 0.15, 1.0)
    x = noise * rng.normal(size=(n, 3))
    mixing = rng.normal(size=(truth.n_lines, 3))
    real = speed * np.asarray(scale)[None, :]
    for line in range(truth.n_lines):
        j = truth.line_joint[line]
        freq = truth.line_coefficient[line] * real[:, j] ** truth.exponent[j]
        phase = 2 * np.pi * np.cumsum(freq) / FS + 0.3 * np.cumsum(rng.normal(size=n)) / np.sqrt(FS)
        amplitude = 0.5 * real[:, j] * (1 + 0.05 * np.sin(2 * np.pi * 0.7 * np.arange(n) / FS))
        x += (amplitude * np.sin(phase))[:, None] * mixing[line][None, :]
    sos_band = signal.butter(4, BAND, "bandpass", fs=FS, output="sos")
    return signal.sosfilt(sos_band, x, axis=0), speed


def db(a: np.ndarray, b: np.ndarray) -> float:
    return 10 * math.log10(float(np.mean(a**2)) / float(np.mean(b**2)))


def test_fold_places_lines_above_nyquist_where_sampling_puts_them():
    assert fold(np.array([100.0, 600.0, 1100.0, 1600.0]), 1000.0).tolist() == [
        100.0,
        400.0,
        100.0,
        400.0,
    ]


def test_map_validates_and_round_trips_through_plain_arrays():
    hmap = two_joint_map()
    arrays = hmap.to_arrays("h.")
    assert all(a.dtype != object for a in arrays.values())
    back = HarmonicMap.from_arrays(arrays, "h.")
    assert back.joint_names == hmap.joint_names
    np.testing.assert_array_equal(back.line_coefficient, hmap.line_coefficient)
    with pytest.raises(ModelFileError, match="line_coefficient|coefficients"):
        HarmonicMap.from_arrays(
            {**arrays, "h.line_coefficient": -arrays["h.line_coefficient"]}, "h."
        )
    with pytest.raises(ModelFileError, match="lacks 'h.exponent'"):
        HarmonicMap.from_arrays({k: v for k, v in arrays.items() if k != "h.exponent"}, "h.")
    with pytest.raises(ConfigError, match="tracking_hz"):
        CancellerSettings(tracking_hz=-1.0)


def test_canceller_removes_lines_whose_speed_proxy_is_off_and_the_pll_finds_by_how_much():
    truth = two_joint_map()
    x, speed = robot(12.0, seed=1, truth=truth, scale=(1.05, 0.96))
    settle = int(4 * FS)
    with_pll = HarmonicCanceller(truth, sample_rate_hz=FS, band_hz=BAND, n_channels=3)
    residual = with_pll.process(x, speed)
    without = HarmonicCanceller(
        truth,
        sample_rate_hz=FS,
        band_hz=BAND,
        n_channels=3,
        settings=CancellerSettings(pll_hz=0.0),
    ).process(x, speed)
    assert db(x[settle:], residual[settle:]) > 15.0
    assert db(x[settle:], residual[settle:]) > db(x[settle:], without[settle:]) + 6.0
    # f ~ (1.05 v)^1 and (0.96 v)^0.8: the corrections the loop settled on
    np.testing.assert_allclose(with_pll.state.correction, [0.05, 0.96**0.8 - 1], atol=0.01)


def test_a_tap_passes_the_canceller_and_does_not_drag_its_weights():
    truth = two_joint_map()
    x, speed = robot(6.0, seed=2, truth=truth)
    n = len(x)
    k = np.arange(int(0.04 * FS)) / FS
    tap = np.zeros((n, 3))
    onset = int(4.0 * FS)
    tap[onset : onset + len(k), 0] = 3.0 * np.exp(-k / 0.006) * np.sin(2 * np.pi * 230 * k)
    clean = HarmonicCanceller(truth, sample_rate_hz=FS, band_hz=BAND, n_channels=3).process(
        x, speed
    )
    with_tap = HarmonicCanceller(truth, sample_rate_hz=FS, band_hz=BAND, n_channels=3).process(
        x + tap, speed
    )
    window = slice(onset, onset + len(k))
    kept = with_tap[window] - clean[window]
    assert np.corrcoef(kept[:, 0], tap[window, 0])[0, 1] > 0.98
    assert np.abs(kept[:, 0]).max() / np.abs(tap[window, 0]).max() > 0.95
    # after the tap the canceller is back to what it did without it
    after = slice(onset + int(0.3 * FS), n)
    assert db(x[after], with_tap[after]) > db(x[after], clean[after]) - 1.0


def test_lines_that_stop_at_once_are_not_subtracted_on():
    """The motors stop shaking the sensor at once (a stop, a reversal) while the reported
    speed still says they run: the trackers keep predicting the lines for tens of ms, and
    subtracting them would add a burst the sensor never felt. The guard keeps the output
    about as quiet as the input; without it the output is the whole prediction."""
    truth = two_joint_map()
    x, speed = robot(5.0, seed=5, truth=truth)
    stop = int(4.0 * FS)
    quiet = 0.01 * np.random.default_rng(6).normal(size=x[stop:].shape)
    x[stop:] = quiet
    # The input's short-time power takes ~7 guard time constants to fall 30 dB.
    after = slice(stop + int(0.03 * FS), stop + int(0.1 * FS))
    results = {}
    for guard_ms in (0.0, CancellerSettings().guard_ms):
        canceller = HarmonicCanceller(
            truth,
            sample_rate_hz=FS,
            band_hz=BAND,
            n_channels=3,
            settings=CancellerSettings(guard_ms=guard_ms),
        )
        results[guard_ms] = canceller.process(x, speed)
    before = slice(stop - int(1.0 * FS), stop)
    # while the lines are there the guard changes nothing
    assert db(results[0.0][before], results[3.0][before]) == pytest.approx(0.0, abs=0.2)
    assert db(results[0.0][after], x[after]) > 20.0  # the prediction, subtracted from silence
    assert db(results[3.0][after], x[after]) < 4.0  # about the input (<= +3 dB at most)


def reference_cancel(hmap: HarmonicMap, x, speed, s: CancellerSettings, band):
    """The canceller written as plain Python/numpy, one sample at a time."""
    mu, kp, ki, rate, guard = s.gains(FS)
    p_in, p_res = np.zeros(x.shape[1]), np.zeros(x.shape[1])
    n, C = x.shape
    J, L = hmap.n_joints, hmap.n_lines
    lagged, corr, theta = np.zeros(J), np.zeros(J), np.zeros(L)
    w = np.zeros((C, L, 2))
    spread2 = np.full(C, np.mean(hmap.residual_rms) ** 2)
    a_up = [1 - math.exp(-1 / (FS * t)) if t > 0 else 1.0 for t in hmap.tau_up_s]
    a_dn = [1 - math.exp(-1 / (FS * t)) if t > 0 else 1.0 for t in hmap.tau_down_s]
    out = np.empty_like(x)
    for i in range(n):
        g = np.zeros(J)
        for j in range(J):
            v = abs(speed[i, j])
            lagged[j] += (a_up[j] if v > lagged[j] else a_dn[j]) * (v - lagged[j])
            g[j] = lagged[j] ** hmap.exponent[j] if lagged[j] > hmap.min_speed[j] else 0.0
        rates = hmap.line_coefficient * g[hmap.line_joint] * (1 + corr[hmap.line_joint])
        theta = np.mod(theta + rates / FS, 1.0)
        active = (
            (g[hmap.line_joint] > 0) & (fold(rates, FS) >= band[0]) & (fold(rates, FS) <= band[1])
        )
        cos, sin = np.cos(2 * np.pi * theta), np.sin(2 * np.pi * theta)
        num, den = np.zeros(J), np.zeros(J)
        for c in range(C):
            estimate = np.sum(active * (w[c, :, 0] * cos + w[c, :, 1] * sin))
            e = x[i, c] - estimate
            p_in[c] += guard * (x[i, c] ** 2 - p_in[c])
            p_res[c] += guard * (e**2 - p_res[c])
            scale = math.sqrt(p_in[c] / p_res[c]) if p_res[c] > p_in[c] else 1.0
            out[i, c] = x[i, c] - scale * estimate
            limit = s.clip_sigma * math.sqrt(spread2[c])
            ec = min(max(e, -limit), limit)
            spread2[c] += rate * (ec * ec - spread2[c])
            k = 2 * np.pi * hmap.line_coefficient
            d = k * (w[c, :, 1] * cos - w[c, :, 0] * sin)
            np.add.at(num, hmap.line_joint, np.where(active, ec * d, 0.0))
            np.add.at(
                den,
                hmap.line_joint,
                np.where(active, 0.5 * k**2 * (w[c, :, 0] ** 2 + w[c, :, 1] ** 2), 0.0),
            )
            w[c, :, 0] += np.where(active, mu * ec * cos, 0.0)
            w[c, :, 1] += np.where(active, mu * ec * sin, 0.0)
        for j in range(J):
            if g[j] > 0 and den[j] > 0:
                err = num[j] / (den[j] + spread2.sum())
                mine = hmap.line_joint == j
                theta[mine] = np.mod(theta[mine] + kp * err * hmap.line_coefficient[mine], 1.0)
                corr[j] = min(
                    max(corr[j] + ki * err * FS / g[j], -s.max_correction), s.max_correction
                )
    return out


def test_compiled_canceller_equals_the_plain_reference():
    truth = two_joint_map(lag_s=0.02)
    x, speed = robot(1.0, seed=3, truth=truth)
    s = CancellerSettings()
    got = HarmonicCanceller(
        truth, sample_rate_hz=FS, band_hz=BAND, n_channels=3, settings=s
    ).process(x, speed)
    want = reference_cancel(truth, x, speed, s, BAND)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(x).max())


@settings(max_examples=15, deadline=None)
@given(st.lists(st.integers(min_value=1, max_value=700), min_size=1, max_size=8))
def test_any_chunking_gives_the_one_call_result_to_the_bit(cuts):
    truth = two_joint_map()
    x, speed = robot(2.0, seed=4, truth=truth)
    speed[500:520] = np.nan  # no joint state for a while: the speed is held
    whole = HarmonicCanceller(truth, sample_rate_hz=FS, band_hz=BAND, n_channels=3).process(
        x, speed
    )
    chunked = HarmonicCanceller(truth, sample_rate_hz=FS, band_hz=BAND, n_channels=3)
    edges = np.unique(np.clip(np.cumsum(cuts), 0, len(x)))
    pieces = [
        chunked.process(x[a:b], speed[a:b]) for a, b in zip(np.r_[0, edges], np.r_[edges, len(x)])
    ]
    assert np.array_equal(np.concatenate(pieces), whole)


def test_fit_finds_orders_exponent_and_coefficients_from_free_motion():
    truth = two_joint_map()
    x, speed = robot(30.0, seed=5, truth=truth)
    hmap, info = fit_harmonic_map(
        x,
        speed,
        sample_rate_hz=FS,
        band_hz=BAND,
        joint_names=("a", "b"),
        max_speed=np.ones(2),
        max_seconds=15.0,
    )
    for j, (coefficient, orders, exponent) in enumerate(
        ((200.0, [1.0, 2.0], 1.0), (150.0, [1.0, 1.5], 0.8))
    ):
        fitted = info["joints"]["ab"[j]]
        assert sorted(fitted["orders"])[:2] == orders, fitted
        assert fitted["exponent"] == pytest.approx(exponent, abs=0.11)
        # the line at the median speed lands within 2 % of the truth
        lines = hmap.line_coefficient[hmap.line_joint == j]
        f = lines.min() * 0.6 ** hmap.exponent[j]
        assert f == pytest.approx(coefficient * 0.6**exponent, rel=0.02)
    assert info["residual_db"] > 5.0  # on the fit's own pieces, trackers settling in each
    residual = HarmonicCanceller(hmap, sample_rate_hz=FS, band_hz=BAND, n_channels=3).process(
        x, speed
    )
    assert db(x[4000:], residual[4000:]) > 13.0


def test_the_search_on_several_cores_makes_the_choices_of_one_core(monkeypatch):
    """The map search runs a step's trials side by side (a thread per core): the same map,
    info and costs as one trial after the other."""
    truth = two_joint_map()
    x, speed = robot(8.0, seed=7, truth=truth)
    options = dict(
        sample_rate_hz=FS, band_hz=BAND, joint_names=("a", "b"), max_speed=np.ones(2),
        max_seconds=4.0,
    )  # fmt: skip
    monkeypatch.setattr(harmonic.os, "sched_getaffinity", lambda pid: {0, 1, 2}, raising=False)
    side_by_side = fit_harmonic_map(x, speed, **options)
    monkeypatch.setattr(harmonic.os, "sched_getaffinity", lambda pid: {0}, raising=False)
    one_by_one = fit_harmonic_map(x, speed, **options)
    for a, b in zip(dataclasses.astuple(side_by_side[0]), dataclasses.astuple(one_by_one[0])):
        np.testing.assert_array_equal(a, b)
    assert side_by_side[1] == one_by_one[1]


def test_a_joint_without_lines_gets_none():
    truth = two_joint_map()
    x, speed = robot(10.0, seed=6, truth=truth)
    rng = np.random.default_rng(0)
    still = np.column_stack([speed, np.clip(0.5 + 0.1 * rng.normal(size=len(speed)), 0, 1)])
    hmap, info = fit_harmonic_map(
        x,
        still,
        sample_rate_hz=FS,
        band_hz=BAND,
        joint_names=("a", "b", "c"),
        max_speed=np.ones(3),
        max_seconds=8.0,
    )
    assert info["joints"]["c"]["orders"] == []
    assert not np.any(hmap.line_joint == 2)
