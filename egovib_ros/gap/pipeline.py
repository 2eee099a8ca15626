"""`egovib gap` end to end: read the model and the real bag, diagnose,
write the report directory."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from egovib_ros.errors import BagError, EgovibError
from egovib_ros.fileutil import atomic_output
from egovib_ros.gap.diagnose import Diagnosis, diagnose
from egovib_ros.gap.features import (
    DEFAULT_BUDGET_MINUTES,
    THIN_RUN_BLOCKS,
    BlockTable,
    build_table,
    table_from_bag,
)
from egovib_ros.gap.report import build_report, make_figures, render_markdown


class GapDataError(EgovibError):
    """The recording does not hold enough usable (no-contact, matched) data for a diagnosis."""


def diagnose_recording(rec, model, *, source: str = "bag", **kwargs) -> Diagnosis:
    """Diagnosis of an in-memory Recording against a NoiseModel (no files written)."""
    return diagnose_table(build_table(rec, model, source=source), source=source, **kwargs)


def diagnose_table(table: BlockTable, *, source: str = "bag", **kwargs) -> Diagnosis:
    """Diagnosis of a block table (`build_table` / `table_from_bag`)."""
    try:
        return diagnose(table, **kwargs)
    except ValueError as exc:
        raise GapDataError(f"{source}: {exc}") from None


def screened_input(table: BlockTable, where: str) -> str:
    """Bad input is missing data, counted, never averaged in (sensor samples non-finite or
    beyond the sensor range; joint states non-finite or out of order): more than
    core.MAX_BAD_SHARE of either is refused (one-line StreamError); else the line of counts
    to print, or "" if nothing was bad."""
    from egovib_ros.cliutil import check_stream

    counts = dict(table.bad_input)
    dropped = counts.get("joint_states_dropped", 0) + counts.get("joint_states_bad", 0)
    counts["joint_states_dropped"] = dropped
    line = check_stream(counts, where, joint_states=int(counts.get("joint_states", 0)))
    bad = dropped + sum(
        int(counts.get(k, 0)) for k in ("samples_bad", "dropped_out_of_order", "resets")
    )
    return line if bad else ""


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
    budget_minutes: float | None = DEFAULT_BUDGET_MINUTES,
    progress=None,
    **kwargs,
) -> dict:
    """Diagnose `real_path` against the model file; write report.json, report.md and
    figures into out_dir.

    The directory appears only when complete. With `write_back`, the verdict's fitted
    effect is written into a copy of the sim config `sim_params` (default
    config/sim.yaml) as out_dir/sim_updated.yaml, and checked on the held-out data.
    """
    from egovib_ros.core.noise_model import NoiseModel

    start = time.perf_counter()
    model = NoiseModel.load(model_path)
    if not Path(real_path).exists():
        raise BagError(f"{real_path}: no such bag")
    # streamed: the sensor samples are framed slice by slice, never held whole
    table = table_from_bag(real_path, model, budget_minutes=budget_minutes, progress=progress)
    if table.bad_input.get("stride", 1) > 1:
        print(
            f"gap: {real_path}: longer than the {budget_minutes:g}-minute budget: one "
            f"{THIN_RUN_BLOCKS}-block run in every {table.bad_input['stride']} is diagnosed",
            file=sys.stderr,
        )
    topic = model.profile.sensor_topic if model.profile is not None else "sensor topic"
    said = screened_input(table, f"{real_path}: {topic}")
    if said:
        print(f"gap: {real_path}: {said}", file=sys.stderr)
    lag = reference_lag_for(model, reference_lag, sim_params)
    diag = diagnose_table(table, source=str(real_path), reference_lag_s=lag, **kwargs)
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
        report["inputs"]["bad_input"] = {
            k: int(v) for k, v in table.bad_input.items() if isinstance(v, (int, float))
        }
        report["runtime_s"] = round(time.perf_counter() - start, 2)
        (tmp / "report.json").write_text(json.dumps(report, indent=1))
        (tmp / "report.md").write_text(render_markdown(report, diag.table.joint_names))
    return report
