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


def test_the_summary_and_page_of_the_injections():
    """Per injection and direction: the strengths at which the injected effect is in
    verdict.effects, first, and first in the change; the lag errors against the tolerance;
    the advice applied; all on the page."""
    from egovib_research.experiments.gap_real_injection import (
        INJECTIONS,
        LAG_TOLERANCE_MS,
        _summary,
        render_markdown,
    )

    d = "calibrated on first part, diagnosed 8.5-16.85 s"
    applied = {
        "noise_reduction_without_db": 10.0,
        "noise_reduction_with_db": 11.0,
        "gain_db": 1.0,
        "applied_text": "--joint-lag 0.02",
    }
    runs = [
        {"direction": d, "truth": "none", "injection": "untouched", "strength": 0.0,
         "verdict": "timing", "effects": ["timing"], "in_effects": False, "correct": False,
         "applied": applied},
        {"direction": d, "truth": "timing", "injection": "lag", "strength": 0.04,
         "verdict": "timing", "effects": ["timing", "drift"], "in_effects": True,
         "correct": True, "joint_lag_moved_ms": -37.0, "lag_error_ms": 3.0,
         "change": {"effects": ["timing"], "first_is_injected": True}, "applied": applied},
        {"direction": d, "truth": "drift", "injection": "warm-up", "strength": 0.8,
         "verdict": "timing", "effects": ["timing", "drift"], "in_effects": True,
         "correct": False, "change": {"effects": ["coupling", "drift"],
                                      "first_is_injected": False}},
        {"direction": d, "truth": "timing", "injection": "lead", "strength": -0.02,
         "verdict": "refused", "effects": [], "in_effects": False, "correct": False,
         "refused": "too few no-contact blocks (3)"},
    ]  # fmt: skip
    directions = {d: {"own_joint_lag_s": 0.03, "untouched": {
        "verdict": "timing", "effects": ["timing"], "confidence": 1.0,
        "fitted_joint_lag_s": 0.032}}}  # fmt: skip
    s = _summary(runs, directions, "bags/quadcopter_ar8")
    assert s["in_effects_at_strengths"]["lag"][d] == [0.04]
    assert s["in_effects_at_strengths"]["warm-up"][d] == [0.8]
    assert s["first_at_strengths"]["warm-up"][d] == []
    assert s["change_first_at_strengths"]["lag"][d] == [0.04]
    assert s["in_effects"] == round(2 / 3, 4) and s["change_first"] == round(1 / 3, 4)
    assert s["lag_errors_ms"] == [3.0] and s["lags_within_tolerance"] == 1
    assert s["advice_applied_gain_db"] == [1.0, 1.0]
    report = {
        "summary": s,
        "runs": runs,
        "runtime_s": 60.0,
        "settings": {
            "command": "egovib gap validate --reality real",
            "lag_tolerance_ms": LAG_TOLERANCE_MS,
            "injections": [
                {"effect": e, "label": lb, "strengths": list(v)} for e, lb, v in INJECTIONS
            ],  # fmt: skip
        },
    }
    page = render_markdown(report)
    assert "**1 of 1** runs" in page and "| lag | 0.04 / 0.04 / 0.04 |" in page
    assert "| warm-up | 0.8 / - / - |" in page
    assert "10.00 -> 11.00 dB (+1.00; --joint-lag 0.02)" in page
    assert "refused: too few no-contact blocks (3)" in page
