"""A third PR2-hand generator for the gap diagnosis's blind validation, written from the
effect vocabulary (CONTRACT section 5) and the robot of section 1 alone: its author had not
read the project's simulator (egovib_ros/sim) nor the alternate reality
(egovib_research/altreality). Its drives, structure, motion and every effect form are its own
(hand.py's table); it shares with the others only the robot's joints, rates and sensor.

    rec, truth = simulate_third_motion(duration_s=120, effects={"coupling": 1.5},
                                       forms={"coupling": "line_signed"}, seed=3)
    python -m egovib_research.thirdhand --duration 120 --effects coupling=1.5 \
        --forms coupling=line_signed --out BAG

Imports numpy, scipy and the project's Recording container only
(test_thirdhand_hand.test_shares_no_code_with_the_other_generators).
"""

from __future__ import annotations

from egovib_research.thirdhand.hand import FORMS, JOINT_NAMES, simulate
from egovib_ros.bag.recording import Recording


def simulate_third_motion(
    *,
    duration_s: float = 120.0,
    effects: dict | None = None,
    forms: dict | None = None,
    seed: int = 0,
    tap_rate_hz: float = 0.5,
    max_speed: float = 0.8,
) -> tuple[Recording, dict]:
    """A Recording of the third hand moving freely (ground truth attached) and its truth:
    {"seed", "effects", "forms", "tap_onsets_ns"}. `forms`: effect -> form (FORMS; the
    first form of each effect when not given)."""
    effects = dict(effects or {})
    unknown = set(effects) - set(FORMS)
    if unknown:
        raise ValueError(f"unknown effect(s) {sorted(unknown)}; expected {sorted(FORMS)}")
    forms = {e: (forms or {}).get(e, FORMS[e][0]) for e in effects}
    for effect, form in forms.items():
        if form not in FORMS[effect]:
            raise ValueError(f"{effect}: unknown form {form!r}; expected {FORMS[effect]}")
    out = simulate(duration_s, effects, forms, seed, tap_rate_hz, max_speed)
    rec = Recording(
        sensor_stamps_ns=out["sensor_stamps_ns"],
        sensor=out["sensor"],
        joint_stamps_ns=out["joint_stamps_ns"],
        joint_position=out["joint_position"],
        joint_velocity=out["joint_velocity"],
        joint_names=JOINT_NAMES,
        contact=out["contact"],
        ego=out["ego"],
    )
    truth = {
        "seed": seed,
        "effects": effects,
        "forms": forms,
        "tap_onsets_ns": out["sensor_stamps_ns"][out["tap_onsets"]].tolist(),
    }
    return rec, truth


__all__ = ["FORMS", "simulate_third_motion"]
