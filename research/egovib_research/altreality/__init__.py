"""An independent "alternate reality" of the PR2 right hand (numpy/scipy only).

Written from scratch to test the gap diagnosis on data that our simulator
(egovib_ros/sim) did not shape: it shares no code, constants or formulas with
it.  Its robot: a wrist roll driven by a BLDC motor through a timing belt and a
harmonic drive, a gripper driven by a brushed DC motor through a spur-gear pair
and a ball screw, a housing with several structural modes that mix into all three
sensor axes, impulsive stick-slip friction, mains and fan hum, its own
accelerometer, its own motion (segments with quintic blends, gripper strokes with
dwells) and its own joint-state reporting (two-sample encoder differences,
stamp jitter, occasional dropped messages).

Its effects (INTERFACES.md section 5 vocabulary), each in a functional form unlike
the simulator's:

* ``position``:     variant "spot": a tight spot once per wrist turn (a burr on the
                    flexspline: the wrist drive is louder within ~0.3 rad of one
                    angle); variant "end": the gripper rubs near its closed end.
* ``coupling``:     intermodulation lines at the sums and differences of wrist and
                    gripper drive lines (a quadratic bearing stiffness), present
                    only when both joints move.
* ``acceleration``: backlash clicks when a joint reverses (impact ~ sqrt|a|).
* ``drift``:        a warm-up step: the drive vibration level moves by a factor
                    (1 + s) or 1/(1 + s) through a logistic step early in the run.
* ``timing``:       joint-state stamps shifted by s seconds (either sign).

    simulate_alt_motion(duration_s=120, effects={"position": 1.0}, seed=0, tap_rate_hz=0.5)
        -> (egovib_ros.bag.Recording, truth dict)
"""

from egovib_research.altreality.hand import (
    EFFECTS,
    HAND_JOINTS,
    AltHand,
    effect_audibility_db,
    simulate_alt_motion,
)

__all__ = [
    "EFFECTS",
    "HAND_JOINTS",
    "AltHand",
    "effect_audibility_db",
    "simulate_alt_motion",
]
