"""`egovib gap` end to end: read the model and the real bag, diagnose,
write the report directory."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np

from egovib_ros.bag import concat_recordings, iter_recording
from egovib_ros.core.noise_model import NoiseModel
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import BagError, GapDataError
from egovib_ros.gap.advice import effect_actions, measure_advice, merged_settings
from egovib_ros.gap.change import diagnose_change
from egovib_ros.gap.diagnose import Diagnosis, DiagnosisOptions, diagnose
from egovib_ros.gap.effects import LAG_COARSE_S, LAG_RANGE_S
from egovib_ros.gap.features import (
    DEFAULT_BUDGET_MINUTES,
    JOINT_MARGIN_S,
    THIN_RUN_BLOCKS,
    BlockTable,
    build_table,
    joint_order,
    table_from_bag,
)
from egovib_ros.gap.report import build_report, change_report, make_figures, render_markdown
from egovib_ros.gap.simref import model_matches_simulator, own_lag, simulator_reference_lag
from egovib_ros.gap.writeback import write_back as do_write_back
from egovib_ros.outputs import atomic_output, check_replaceable
from egovib_ros.robot import robot_option
from egovib_ros.sim import SimParams


def diagnose_recording(
    rec, model, *, source: str = "bag", options: DiagnosisOptions | None = None
) -> Diagnosis:
    """Diagnosis of an in-memory Recording against a NoiseModel (no files written)."""
    return diagnose_table(build_table(rec, model, source=source), source=source, options=options)


def diagnose_table(
    table: BlockTable, *, source: str = "bag", options: DiagnosisOptions | None = None
) -> Diagnosis:
    """Diagnosis of a block table (`build_table` / `table_from_bag`)."""
    return _naming(source, diagnose, table, options)


def _naming(source: str, function, *args):
    """`function(*args)`, its data errors (GapDataError) naming `source`."""
    try:
        return function(*args)
    except GapDataError as exc:
        raise GapDataError(f"{source}: {exc}") from None


def input_notices(table: BlockTable, budget_minutes: float | None) -> list[str]:
    """What the caller should say about the input: bad data treated as missing (counted;
    more than core.MAX_BAD_SHARE was already refused) and the thinning of a long bag."""
    bad = table.bad_input
    notices = []
    if any(bad.get(k, 0) for k in ("samples_bad", "dropped_out_of_order", "joint_states_dropped")):
        notices.append(bad["said"])
    if bad.get("kept_share", 1.0) < 1.0:
        share = 100 * bad["kept_share"]  # never rounded up to "100 %": some runs are left out
        share = f"{share:.0f}" if share < 99.5 else f"{math.floor(10 * share) / 10:.1f}"
        held = (
            f"{bad['recorded_s'] / 60:.1f} minutes of sensor data, " if "recorded_s" in bad else ""
        )
        notices.append(
            f"{held}more than the {budget_minutes:g}-minute budget (--budget-minutes): "
            f"{share} % of its {THIN_RUN_BLOCKS}-block runs diagnosed, spread evenly"
        )
    return notices


def reference_lag_for(model, reference_lag: float | None, sim_params: str | Path | None) -> float:
    """The lag timing is judged against: given; else the one the model's calibration
    recording showed (stored by `egovib calibrate`); else, for a model of the simulated
    joints, measured on the simulator; else 0."""
    if reference_lag is not None:
        return float(reference_lag)
    stored = own_lag(model)
    if stored is not None:
        return stored
    if not model_matches_simulator(model):
        return 0.0
    return simulator_reference_lag(model, params=SimParams.load(sim_params))


def read_first_part(path: str | Path, model, max_s: float | None):
    """The bag's first `max_s` seconds (all of it: None) as one Recording, streams sorted
    by stamp (the advice is applied to them with the user's model)."""
    pieces, t0 = [], None
    for piece in iter_recording(
        path, profile=model.profile, ground_truth=False, denoised=False, commands=False
    ):
        if len(piece.sensor_stamps_ns):
            t0 = int(piece.sensor_stamps_ns.min()) if t0 is None else t0
        pieces.append(piece)
        if (
            max_s is not None
            and t0 is not None
            and piece.sensor_stamps_ns.size
            and piece.sensor_stamps_ns.max() > t0 + max_s * NS_PER_S
        ):
            break
    rec = concat_recordings(pieces)
    s, j = (
        np.argsort(rec.sensor_stamps_ns, kind="stable"),
        np.argsort(rec.joint_stamps_ns, kind="stable"),
    )
    rec.sensor_stamps_ns, rec.sensor = rec.sensor_stamps_ns[s], rec.sensor[s]
    rec.joint_stamps_ns = rec.joint_stamps_ns[j]
    rec.joint_position, rec.joint_velocity = rec.joint_position[j], rec.joint_velocity[j]
    if max_s is not None:
        keep = rec.sensor_stamps_ns <= rec.sensor_stamps_ns[0] + max_s * NS_PER_S
        rec.sensor_stamps_ns, rec.sensor = rec.sensor_stamps_ns[keep], rec.sensor[keep]
    return rec


def _input_notes(table, notices: list[str], model) -> dict:
    """report.json's inputs: the bad input counted, the notices, what the model was
    calibrated on (our simulator: a sim-to-real gap; or a recording)."""
    return {
        "bad_input": {
            k: (round(v, 6) if isinstance(v, float) else int(v))
            for k, v in table.bad_input.items()
            if isinstance(v, (int, float))
        },
        "notices": notices,
        "model_kind": "simulator" if model_matches_simulator(model) else "recording",
    }


def run_gap(
    model_path: str | Path,
    real_path: str | Path,
    out_dir: str | Path,
    *,
    write_back: bool = False,
    sim_params: str | Path | None = None,
    reference_lag: float | None = None,
    figures: bool = True,
    budget_minutes: float | None = DEFAULT_BUDGET_MINUTES,
    progress=None,
    options: DiagnosisOptions | None = None,
    reference_path: str | Path | None = None,
) -> dict:
    """Diagnose `real_path` against the model file; write report.json, report.md and
    figures into out_dir (the directory appears only when complete).

    `write_back`: the verdict's fitted effect written into a copy of the sim config
    `sim_params` (default config/sim.yaml) as out_dir/sim_updated.yaml, checked on the
    held-out data. `options`: how the diagnosis runs, its reference lag replaced by
    `reference_lag` (internal convention: seconds the joint states are stamped late; None:
    `reference_lag_for`). A timing or drift found: the advised flags are applied with the
    model on the bag's held-out part (`advice.measure_advice`; its first budget minutes read
    again). `reference_path`: a recording of the same robot: report.json's `change` lists
    what differs (gap.change).
    """

    start = time.perf_counter()
    model = NoiseModel.load(model_path)
    for path in (real_path, reference_path):
        if path is not None and not Path(path).exists():
            raise BagError(f"{path}: no such bag")
    check_replaceable(
        out_dir, directory=True, kind="report"
    )  # refused now, not after the diagnosis
    lag = reference_lag_for(model, reference_lag, sim_params)
    options = dataclasses.replace(options or DiagnosisOptions(), reference_lag_s=lag)
    # streamed: the sensor samples are framed slice by slice, never held whole; a thinned
    # bag keeps the joint states near its blocks, as far as the lags tried reach
    max_lag_s = max(
        JOINT_MARGIN_S, abs(lag) + max(LAG_RANGE_S, options.lag_tolerance_s) + LAG_COARSE_S
    )
    table = table_from_bag(
        real_path,
        model,
        budget_minutes=budget_minutes,
        max_lag_s=max_lag_s,
        progress=progress,
    )
    notices = input_notices(table, budget_minutes)
    diag = diagnose_table(table, source=str(real_path), options=options)
    change = None
    if reference_path is not None:
        reference = table_from_bag(
            reference_path,
            model,
            budget_minutes=budget_minutes,
            max_lag_s=max_lag_s,
        )
        notices += [
            f"reference {reference_path}: {n}" for n in input_notices(reference, budget_minutes)
        ]
        change = _naming(str(reference_path), diagnose_change, reference, diag, options)
    measured = None
    if any(e["effect"] in ("timing", "drift") for e in diag.effects):
        rec = read_first_part(
            real_path, model, None if budget_minutes is None else 60.0 * budget_minutes
        )
        settings = merged_settings(effect_actions(diag))
        order = joint_order(model, rec.joint_names, str(real_path))
        measured = measure_advice(rec, model, diag, settings, order)
    with atomic_output(out_dir, directory=True, kind="report") as tmp:
        tmp.mkdir(parents=True)
        wb = None
        if write_back:
            wb = do_write_back(diag, sim_params, tmp / "sim_updated.yaml")
        report = build_report(
            diag,
            model_path=str(model_path),
            real_path=str(real_path),
            figures={},
            runtime_s=0.0,
            write_back=wb,
            measured=measured,
            report_path=str(Path(out_dir) / "report.json"),
            robot=robot_option(model.robot_profile()),
        )
        if figures:
            report["figures"] = make_figures(diag, report, tmp)
        if change is not None:
            report.update(change_report(change, reference=str(reference_path)))
            report["inputs"]["reference"] = str(reference_path)
        report["inputs"].update(_input_notes(table, notices, model))
        report["runtime_s"] = round(time.perf_counter() - start, 2)
        (tmp / "report.json").write_text(json.dumps(report, indent=1))
        (tmp / "report.md").write_text(render_markdown(report))
    return report
