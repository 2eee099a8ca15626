"""Each real-data baseline of the flight experiment does what it claims, on synthetic signals
with known lines."""

import numpy as np
from synthetic import jittery_stamps

from egovib_research.experiments.flight.methods import build_methods, single_joint_profile
from egovib_research.experiments.flight.recording import FlightRecording
from egovib_ros.core.filters import combined_bandpassed
from egovib_ros.robot import load_profile

FS = 1000.0
PROFILE = load_profile("quadcopter")


def _recording(stamps, commands, x):
    gyro = np.zeros((len(stamps), 3))
    gyro[:, 0] = x
    return FlightRecording(
        stamps, gyro, stamps, commands, np.zeros_like(commands), tuple(PROFILE.joint_names)
    )


def _two_regimes(seed=0):
    """Motors in two combinations with the same mean command but different lines: motor 1 fast
    (line at 300 Hz) or motor 2 fast (line at 150 Hz)."""
    n = 12000
    stamps = jittery_stamps(n, seed=seed)
    regime = (np.arange(n) // 1500) % 2  # 1.5 s each, alternating
    commands = np.where(regime[:, None] == 0, [0.6, 0.2, 0.4, 0.4], [0.2, 0.6, 0.4, 0.4]).astype(
        float
    )
    rng = np.random.default_rng(seed)
    t = (stamps - stamps[0]) / 1e9
    noise = rng.normal(0, 0.003, n)
    line = np.where(regime == 0, np.sin(2 * np.pi * 300 * t), np.sin(2 * np.pi * 150 * t)) * 0.1
    return _recording(stamps, commands, line + noise)


def _reduction_db(method, cal, test):
    method.fit(cal)
    raw = combined_bandpassed(test.sensor, PROFILE)
    out = method.run(test)
    keep = slice(200, len(raw) - 200)
    return 20 * np.log10(np.mean(np.abs(raw[keep])) / np.mean(np.abs(out[keep])))


def test_only_the_four_motor_table_keeps_a_signal_where_the_other_regime_has_its_line():
    cal, test = _two_regimes(0), _two_regimes(1)
    # A steady 150 Hz signal while motor 1 is fast (its line at 300 Hz): 150 Hz is where the
    # *other* regime (same mean command) has its line.
    t = (test.sensor_stamps_ns - test.sensor_stamps_ns[0]) / 1e9
    regime0 = test.joint_velocity[:, 0] > 0.5
    probe = np.zeros_like(test.sensor)
    probe[:, 1] = np.where(regime0, 0.05 * np.sin(2 * np.pi * 150 * t), 0.0)
    test_with_probe = _recording(
        test.sensor_stamps_ns, test.joint_velocity, test.sensor[:, 0] + probe[:, 1]
    )
    reference = combined_bandpassed(probe, PROFILE)
    inside = regime0.copy()
    inside[:200] = False
    snr = {}
    for name, method in build_methods(PROFILE, ("ours", "mean_command", "global")).items():
        out = method.fit(cal).run(test_with_probe)
        snr[name] = 10 * np.log10(
            np.sum(reference[inside] ** 2) / np.sum((out - reference)[inside] ** 2)
        )
    assert snr["ours"] > snr["mean_command"] + 6, snr
    assert snr["ours"] > snr["global"] + 6, snr
    assert snr["ours"] > 6, snr


def test_tables_remove_lines_keyed_on_the_motors():
    cal, test = _two_regimes(0), _two_regimes(1)
    for name, method in build_methods(PROFILE, ("ours", "mean_command", "global")).items():
        assert _reduction_db(method, cal, test) > 12, name


def test_mean_command_table_beats_the_global_average_when_speed_moves_the_line():
    n = 12000
    stamps = jittery_stamps(n, seed=3)
    level = np.where((np.arange(n) // 1000) % 2 == 0, 0.3, 0.6)
    commands = np.repeat(level[:, None], 4, axis=1)
    t = (stamps - stamps[0]) / 1e9
    x = 0.1 * np.sin(2 * np.pi * np.where(level < 0.5, 150.0, 300.0) * t)
    rec = _recording(stamps, commands, x + np.random.default_rng(0).normal(0, 0.003, n))
    methods = build_methods(PROFILE, ("mean_command", "global"))
    cal, test = rec.time_slice(0, stamps[n // 2]), rec.time_slice(stamps[n // 2], stamps[-1] + 1)
    reduction = {name: _reduction_db(method, cal, test) for name, method in methods.items()}
    assert reduction["mean_command"] > reduction["global"] + 6, reduction


def test_single_joint_profiles_keep_the_robots_processing():
    one = single_joint_profile(PROFILE, "mean_command")
    assert (
        one.joint_names == ("mean_command",)
        and one.bidirectional == (False,)
        and one.max_speed == (1.0,)
    )
    assert (one.rate_hz, one.block_length, one.hop, one.band_hz) == (
        PROFILE.rate_hz,
        PROFILE.block_length,
        PROFILE.hop,
        PROFILE.band_hz,
    )
    assert single_joint_profile(PROFILE, "constant", steps=1).grid_shape == (2,)
