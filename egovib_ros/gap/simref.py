"""What the model's own source looks like to the diagnosis: its reference lag.

Even the recording a model was calibrated on fits best at a non-zero lag: the simulated
vibration envelope trails the joint velocity by the group delay of the structural paths
and of the band-pass (a few ms); a real robot's motors trail their commands (the shipped
flight: about 30 ms). That lag is in the model's table already, so the timing effect is
a lag *beyond* it: judged against 0, a model calibrated on the robot itself named its
own lag on every recording of it, and the advised correction cost held-out noise
reduction (docs/gap.md, "The reference lag").

`egovib calibrate` and the calibrator node measure it on the calibration recording and
store it in the model (`with_own_lag`); for a model without it, of the simulated joints,
it is measured on an effect-free simulated motion (`simulator_reference_lag`).
"""

from __future__ import annotations

import numpy as np

from egovib_ros.bag.recording import Recording
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.gap.diagnose import MIN_BLOCKS
from egovib_ros.gap.effects import fit_lag
from egovib_ros.gap.features import DEFAULT_BUDGET_MINUTES, build_table
from egovib_ros.robot import default_profile
from egovib_ros.sim import simulate_motion

#: The model's extras key of its own lag (internal convention: seconds the joint states are
#: stamped late).
OWN_LAG_KEY = "gap_own_lag_s"
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
    lag = fit_lag(table, train, lag_range_s=0.03)
    return float(lag)


def model_matches_simulator(model) -> bool:
    """The reference is meaningful only for a model of the simulated robot's joints."""

    return tuple(model.joint_names) == default_profile().joint_names


def with_own_lag(model, rec):
    """`model` with the lag its own calibration recording `rec` (a Recording, joint states
    as calibrated: any --joint-lag applied) fits best at, the scan the diagnosis runs on
    its first DEFAULT_BUDGET_MINUTES (the diagnosis's own budget: time and memory do not
    grow with a long calibration); the model as it is when they hold fewer no-contact
    blocks than a diagnosis needs."""
    end = rec.sensor_stamps_ns[0] + int(DEFAULT_BUDGET_MINUTES * 60 * NS_PER_S)
    n, m = (np.searchsorted(s, end) for s in (rec.sensor_stamps_ns, rec.joint_stamps_ns))
    if n < len(rec.sensor_stamps_ns):
        rec = Recording(
            rec.sensor_stamps_ns[:n],
            rec.sensor[:n],
            rec.joint_stamps_ns[:m],
            rec.joint_position[:m],
            rec.joint_velocity[:m],
            rec.joint_names,
        )
    table = build_table(rec, model, source="calibration recording")
    if (~table.contact).sum() < MIN_BLOCKS:
        return model
    lag = fit_lag(table, ~table.contact)
    return model.replace(extras={**model.extras, OWN_LAG_KEY: np.array(float(lag))})


def own_lag(model) -> float | None:
    """The lag stored by `with_own_lag` (within +-1 s, as --reference-lag), or None."""
    return model.scalar_extra(OWN_LAG_KEY, low=-1.0, high=1.0)
