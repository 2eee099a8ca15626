"""`egovib gap` end to end: read the model and the real bag, diagnose,
write the report directory."""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from egovib_ros.errors import BagError, EgovibError
from egovib_ros.fileutil import atomic_output
from egovib_ros.gap.diagnose import Diagnosis, diagnose
from egovib_ros.gap.features import build_table
from egovib_ros.gap.report import build_report, make_figures, render_markdown


class GapDataError(EgovibError):
    """The recording does not hold enough usable (no-contact, matched) data for a diagnosis."""


def diagnose_recording(rec, model, *, source: str = "bag", **kwargs) -> Diagnosis:
    """Diagnosis of an in-memory Recording against a NoiseModel (no files written)."""
    table = build_table(rec, model, source=source)
    try:
        return diagnose(table, **kwargs)
    except ValueError as exc:
        raise GapDataError(f"{source}: {exc}") from None


def reference_lag_for(model, reference_lag: float | None, sim_params: str | Path | None) -> float:
    """The lag timing is judged against: given, or measured on the simulator
    (0 for a foreign robot)."""
    if reference_lag is not None:
        return float(reference_lag)
    from egovib_ros.gap.simref import model_matches_simulator, simulator_reference_lag

    if not model_matches_simulator(model):
        return 0.0
    from egovib_ros.sim import SimParams

    return simulator_reference_lag(model, params=SimParams.load(sim_params))


def run_gap(
    model_path: str | Path,
    real_path: str | Path,
    out_dir: str | Path,
    *,
    write_back: bool = False,
    sim_params: str | Path | None = None,
    reference_lag: float | None = None,
    figures: bool = True,
    **kwargs,
) -> dict:
    """Diagnose `real_path` against the model file; write report.json, report.md and
    figures into out_dir.

    The directory appears only when complete. With `write_back`, the verdict's fitted
    effect is written into a copy of the sim config `sim_params` (default
    config/sim.yaml) as out_dir/sim_updated.yaml, and checked on the held-out data.
    """
    from egovib_ros.bagio import read_recording
    from egovib_ros.core.noise_model import NoiseModel

    start = time.perf_counter()
    model = NoiseModel.load(model_path)
    if not Path(real_path).exists():
        raise BagError(f"{real_path}: no such bag")
    rec = read_recording(real_path, profile=model.profile, ground_truth=False, denoised=False)
    rec = _without_bad_input(rec, model, str(real_path))
    lag = reference_lag_for(model, reference_lag, sim_params)
    diag = diagnose_recording(rec, model, source=str(real_path), reference_lag_s=lag, **kwargs)
    with atomic_output(out_dir, directory=True) as tmp:
        tmp.mkdir(parents=True)
        wb = None
        if write_back:
            from egovib_ros.gap.writeback import write_back as do_write_back

            wb = do_write_back(diag, sim_params, tmp / "sim_updated.yaml")
        report = build_report(
            diag,
            model_path=str(model_path),
            real_path=str(real_path),
            figures={},
            runtime_s=0.0,
            write_back=wb,
        )
        if figures:
            report["figures"] = make_figures(diag, report, tmp)
        report["runtime_s"] = round(time.perf_counter() - start, 2)
        (tmp / "report.json").write_text(json.dumps(report, indent=1))
        (tmp / "report.md").write_text(render_markdown(report, diag.table.joint_names))
    return report


def _without_bad_input(rec, model, where: str):
    """Bad input is missing data, counted, never averaged in: joint states with a non-finite
    velocity or position are dropped here; sensor samples that are non-finite or beyond the
    sensor's range are dropped by the core's framer (FramerSettings.for_model). Both counts
    are printed; more than 10 % bad is refused (core.MAX_BAD_SHARE)."""
    import dataclasses

    from egovib_ros.core import MAX_BAD_SHARE

    sensor_range = model.profile.sensor_range if model.profile is not None else math.inf
    with np.errstate(invalid="ignore"):
        bad_samples = int(
            np.count_nonzero(
                ~np.all(np.isfinite(rec.accel) & (np.abs(rec.accel) <= sensor_range), axis=1)
            )
        )
    good_joints = np.all(np.isfinite(rec.joint_velocity), axis=1) & np.all(
        np.isfinite(rec.joint_position), axis=1
    )
    bad_joints = int(np.count_nonzero(~good_joints))
    for bad, total, what in (
        (bad_samples, len(rec.accel), "sensor samples"),
        (bad_joints, len(rec.joint_velocity), "joint states"),
    ):
        if total and bad > MAX_BAD_SHARE * total:
            raise BagError(
                f"{where}: {bad} of {total} {what} are bad (non-finite or out of range); "
                f"more than {100 * MAX_BAD_SHARE:g} % is refused"
            )
    if bad_samples or bad_joints:
        print(
            f"gap: {where}: {bad_samples} bad sensor samples (non-finite or beyond the sensor "
            f"range) and {bad_joints} joint states with a non-finite value treated as missing",
            file=sys.stderr,
        )
    if bad_joints:
        rec = dataclasses.replace(
            rec,
            joint_stamps_ns=rec.joint_stamps_ns[good_joints],
            joint_position=rec.joint_position[good_joints],
            joint_velocity=rec.joint_velocity[good_joints],
        )
    return rec
