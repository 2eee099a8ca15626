"""Tests of the streaming simulator egovib_ros.sim.hand (base model)."""

from __future__ import annotations

import numpy as np
import pytest

from egovib_ros.errors import ConfigError
from egovib_ros.sim import HandSimulator, SimParams
from egovib_ros.sim.hand import LSB_MS2, quantise
from egovib_ros.sim.pr2 import GRIPPER_GAP_RANGE_M, JOINT_RATE_HZ, MAX_SPEED

FIELDS = (
    "sensor_stamps_ns",
    "sensor",
    "contact",
    "ego",
    "joint_stamps_ns",
    "joint_position",
    "joint_velocity",
    "tap_onsets_ns",
    "true_velocity",
    "true_position",
)


@pytest.fixture(scope="module")
def params():
    return SimParams.load()


def _run(params, chunk_sizes, *, seed=3, effects=None, profile=None, taps=2.0):
    sim = HandSimulator(params, seed=seed, effects=effects, tap_rate_hz=taps)
    sim.set_command([0.6 * MAX_SPEED[0], 0.9 * MAX_SPEED[1]])
    out, start = [], 0
    for n in chunk_sizes:
        cmds = None if profile is None else profile[start : start + n]
        out.append(sim.step(n, commands=cmds))
        start += n
    return {f: np.concatenate([getattr(c, f) for c in out]) for f in FIELDS}


def _random_chunks(total, rng):
    sizes = []
    while sum(sizes) < total:
        sizes.append(int(min(rng.integers(1, 700), total - sum(sizes))))
    return sizes


@pytest.mark.parametrize(
    "effects",
    [None, {"position": 0.5, "coupling": 1.0, "acceleration": 1.0, "timing": 0.02, "drift": 0.5}],
)
def test_chunked_steps_equal_one_long_step(params, effects):
    total = 9000  # 3 s: includes gripper reversals and taps
    rng = np.random.default_rng(0)
    t = np.arange(total) / 3000
    profile = np.column_stack(
        [2.5 * np.sin(2 * np.pi * 0.7 * t), 0.04 * np.sign(np.sin(2 * np.pi * 0.5 * t))]
    )
    whole = _run(params, [total], effects=effects, profile=profile)
    for _ in range(2):
        parts = _run(params, _random_chunks(total, rng), effects=effects, profile=profile)
        for f in FIELDS:
            np.testing.assert_array_equal(parts[f], whole[f], err_msg=f)
    assert len(whole["tap_onsets_ns"]) > 0


def test_deterministic_per_seed(params):
    a = _run(params, [6000], seed=1)
    b = _run(params, [6000], seed=1)
    c = _run(params, [6000], seed=2)
    for f in FIELDS:
        np.testing.assert_array_equal(a[f], b[f])
    assert not np.array_equal(a["sensor"], c["sensor"])


def test_accelerometer_is_quantised_and_clipped(params):
    out = _run(params, [3000])
    codes = out["sensor"] / LSB_MS2
    np.testing.assert_allclose(codes, np.round(codes), atol=1e-9)
    assert pytest.approx(157.0 / 1024) == LSB_MS2
    clipped = quantise(np.array([[1000.0, -1000.0, 0.0]]))
    assert clipped[0, 0] == pytest.approx(511 * LSB_MS2) and clipped[0, 1] == pytest.approx(
        -512 * LSB_MS2
    )
    # raw = quantised (ego + contact + small sensor noise): within half an LSB + a few noise sigma
    resid = out["sensor"] - out["ego"] - out["contact"] - np.asarray(params.zero_g_offset_ms2)
    assert np.abs(resid).max() < LSB_MS2 / 2 + 6 * params.sensor_noise_rms


def test_joint_states_like_the_pr2(params):
    out = _run(params, [3000 * 4])
    stamps = out["joint_stamps_ns"]
    assert np.all(np.diff(stamps) == 1_000_000)  # 1 kHz
    phase = (stamps[0] - out["sensor_stamps_ns"][0]) % (10**9 // 3000)
    assert phase != 0  # own clock phase vs the accelerometer
    pos, vel = out["joint_position"], out["joint_velocity"]
    res = np.asarray(params.encoder_resolution)
    np.testing.assert_allclose(pos / res, np.round(pos / res), atol=1e-6)  # encoder quantisation
    np.testing.assert_allclose(vel[1:], np.diff(pos, axis=0) * JOINT_RATE_HZ, rtol=1e-9, atol=1e-9)
    # gripper reverses inside its gap limits; wrist is continuous
    gap = out["true_position"][:, 1]
    assert gap.min() >= GRIPPER_GAP_RANGE_M[0] - 1e-9 and gap.max() <= GRIPPER_GAP_RANGE_M[1] + 1e-9
    assert np.any(np.diff(np.sign(out["true_velocity"][:, 1])) != 0)
    assert out["true_position"][-1, 0] > 2 * np.pi  # 1.8 rad/s for 4 s


def test_velocity_controller_is_smooth(params):
    sim = HandSimulator(params, seed=0)
    sim.set_command([3.0, 0.0])
    v = sim.step(1200).true_velocity[:, 0]
    assert np.all(np.diff(v) >= 0) and v[-1] == pytest.approx(3.0, rel=1e-3)
    tau_index = np.searchsorted(v, 3.0 * (1 - np.exp(-1)))
    assert tau_index / 3000 == pytest.approx(params.controller_tau_s, abs=1 / 3000)


def test_stationary_background_is_small_and_vibration_grows_with_speed(params):
    from egovib_research.experiments.sim_validation import bandpass_combined

    levels = []
    for frac in (0.0, 0.3, 1.0):
        sim = HandSimulator(params, seed=0)
        sim.set_command([frac * MAX_SPEED[0], frac * MAX_SPEED[1]])
        sim.step(600)
        levels.append(np.abs(bandpass_combined(sim.step(6000).sensor))[600:].mean())
    assert levels[0] < 0.05
    assert levels[0] < levels[1] < levels[2]


def test_taps_periodic_and_random(params):
    sim = HandSimulator(params, seed=0, tap_rate_hz=2.0, tap_mode="periodic")
    onsets = sim.step(3000 * 5).tap_onsets_ns
    assert len(onsets) == 10 and np.allclose(np.diff(onsets), 0.5e9, atol=1e6)
    sim = HandSimulator(params, seed=0, tap_rate_hz=2.0, tap_mode="random")
    chunk = sim.step(3000 * 30)
    gaps = np.diff(chunk.tap_onsets_ns) / 1e9
    assert gaps.min() >= params.tap_dead_time_s - 1e-3
    assert 1.5 < len(chunk.tap_onsets_ns) / 30 < 2.5
    # contact truth is non-zero only right after onsets
    k = np.searchsorted(chunk.sensor_stamps_ns, chunk.tap_onsets_ns)
    assert np.all(np.abs(chunk.contact[k + 3]).sum(axis=1) > 0)
    active = np.zeros(len(chunk.contact), bool)
    for start in k:
        active[start : start + int(params.tap_length_s * 3000)] = True
    assert np.all(chunk.contact[~active] == 0)


def test_bad_settings(params):
    with pytest.raises(ConfigError):
        HandSimulator(params, tap_mode="sometimes")
    with pytest.raises(ConfigError):
        HandSimulator(params, effects={"wobble": 1.0})
    with pytest.raises(ConfigError):
        HandSimulator(params).set_command([1.0])
