"""What the simulator itself looks like to the diagnosis: its reference lag.

The simulated vibration envelope trails the joint velocity by the group delay of the
structural paths and of the band-pass (a few ms), so even an effect-free simulator
bag fits best at a small non-zero lag.  The timing effect is a lag *beyond* that;
measuring it on an effect-free simulated motion keeps it from being flagged on every
recording.
"""

from __future__ import annotations

from egovib_ros.gap.effects import fit_lag
from egovib_ros.gap.features import build_table
from egovib_ros.robot import default_profile
from egovib_ros.sim import simulate_motion

REFERENCE_DURATION_S = 60.0
REFERENCE_MAX_SPEED = 0.8


def simulator_reference_lag(
    model, *, params=None, seed: int = 0, duration_s: float = REFERENCE_DURATION_S
) -> float:
    """Best-fitting lag (s) of an effect-free simulated random motion against `model`."""

    rec, _ = simulate_motion(
        duration_s=duration_s,
        max_speed=REFERENCE_MAX_SPEED,
        tap_rate_hz=0.0,
        effects={},
        seed=seed,
        params=params,
    )
    table = build_table(rec, model, source="simulated reference motion")
    train = ~table.contact
    # The simulator's own lag is a few ms (group delays): a +-30 ms scan suffices.
    lag, _, _ = fit_lag(table, train, lag_range_s=0.03)
    return float(lag)


def model_matches_simulator(model) -> bool:
    """The reference is meaningful only for a model of the simulated robot's joints."""

    return tuple(model.joint_names) == default_profile().joint_names
