"""The real-flight injections of the gap validation change only what they say."""

from __future__ import annotations

import numpy as np


def test_real_injections_change_only_what_they_say():
    """Timing re-stamps the joint states only; the gains multiply the real gyro only, by
    the stated functions of the joint states."""
    from egovib_research.experiments.gap_flight import SPLIT_S, _slice
    from egovib_research.experiments.gap_real_injection import inject
    from egovib_ros.bag import read_recording
    from egovib_ros.robot import load_profile

    rec = read_recording(
        "bags/quadcopter_ar8",
        profile=load_profile("quadcopter"),
        ground_truth=False,
        denoised=False,
    )
    part = _slice(rec, 0.0, SPLIT_S)
    late = inject(part, "timing", 0.04)
    assert np.array_equal(late.joint_stamps_ns, part.joint_stamps_ns + 40_000_000)
    assert np.array_equal(late.sensor, part.sensor)
    for effect in ("drift", "position", "acceleration", "coupling"):
        out = inject(part, effect, 0.8)
        assert np.array_equal(out.joint_velocity, part.joint_velocity), effect
        nonzero = np.all(part.sensor != 0, axis=1)
        gain = out.sensor[nonzero] / part.sensor[nonzero]
        g = np.median(gain, axis=1)
        assert np.max(np.abs(gain - g[:, None])) < 1e-9, effect  # one gain for all axes
        assert np.max(g) > 1.2 and np.min(g) > 0, effect
    warm = inject(part, "drift", 0.8)
    nonzero = part.sensor[:, 0] != 0
    g = warm.sensor[nonzero, 0] / part.sensor[nonzero, 0]
    assert g[0] < 1.05 and g[-1] > 1.75  # warms up from 1 towards 1.8


def _flight_part(stop_s: float):
    from egovib_research.experiments.gap_flight import _slice
    from egovib_ros.bag import read_recording
    from egovib_ros.robot import load_profile

    rec = read_recording(
        "bags/quadcopter_ar8",
        profile=load_profile("quadcopter"),
        ground_truth=False,
        denoised=False,
    )
    return rec, _slice(rec, 0.0, stop_s)


def test_the_position_injection_is_a_function_of_the_turning_angle():
    """A position effect of a turning part is a function of its angle: the injected gain
    is a harmonic of the motor's position taken as an angle (equal at x and x + 2 pi),
    with more than one of its periods inside the part, so that held-out blocks can be
    predicted from the training ones."""
    from egovib_research.experiments.gap_flight import SPLIT_S
    from egovib_research.experiments.gap_real_injection import POSITION_HARMONIC, _at_accel, inject

    _, part = _flight_part(SPLIT_S)
    out = inject(part, "position", 0.8)
    x = _at_accel(part, part.joint_position)[:, 0]
    nonzero = part.sensor[:, 0] != 0
    gain = out.sensor[nonzero, 0] / part.sensor[nonzero, 0]
    expected = 1.0 + 0.4 * (1.0 + np.cos(POSITION_HARMONIC * np.mod(x[nonzero], 2 * np.pi)))
    np.testing.assert_allclose(gain, expected, rtol=1e-9)
    assert np.ptp(x) > 1.5 * 2 * np.pi / POSITION_HARMONIC


def test_an_injection_the_diagnosis_refuses_is_a_recorded_miss():
    """A part too short to diagnose is refused (too few blocks): the run is kept as a miss
    with the reason, and the validation goes on."""
    from egovib_research.experiments.gap_flight import calibrate_part
    from egovib_research.experiments.gap_real_injection import diagnose_case
    from egovib_ros.robot import load_profile

    rec, short = _flight_part(2.0)
    _, model = calibrate_part(rec, load_profile("quadcopter"), "flight", (8.5, 16.85))
    diag, entry = diagnose_case(short, model, 0.0, "d", "drift", "warm-up", 0.8)
    assert diag is None
    assert entry["verdict"] == "refused" and not entry["correct"]
    assert "too few no-contact blocks" in entry["refused"]
