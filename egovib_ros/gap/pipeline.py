"""`egovib gap` end to end: read the model and the real bag, diagnose,
write the report directory."""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path

from egovib_ros.core.noise_model import NoiseModel
from egovib_ros.errors import BagError, GapDataError
from egovib_ros.gap.diagnose import Diagnosis, DiagnosisOptions, diagnose
from egovib_ros.gap.effects import LAG_COARSE_S, LAG_RANGE_S
from egovib_ros.gap.features import (
    DEFAULT_BUDGET_MINUTES,
    JOINT_MARGIN_S,
    THIN_RUN_BLOCKS,
    BlockTable,
    build_table,
    table_from_bag,
)
from egovib_ros.gap.report import build_report, make_figures, render_markdown
from egovib_ros.gap.simref import model_matches_simulator, simulator_reference_lag
from egovib_ros.gap.writeback import write_back as do_write_back
from egovib_ros.outputs import atomic_output, check_replaceable
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
    try:
        return diagnose(table, options)
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
    """The lag timing is judged against: given, or measured on the simulator
    (0 for a foreign robot)."""
    if reference_lag is not None:
        return float(reference_lag)

    if not model_matches_simulator(model):
        return 0.0

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
    options: DiagnosisOptions | None = None,
) -> dict:
    """Diagnose `real_path` against the model file; write report.json, report.md and
    figures into out_dir.

    The directory appears only when complete. With `write_back`, the verdict's fitted
    effect is written into a copy of the sim config `sim_params` (default
    config/sim.yaml) as out_dir/sim_updated.yaml, and checked on the held-out data.
    `options`: how the diagnosis runs; its reference lag is replaced by `reference_lag`
    (or, when None, the lag measured on the simulator: `reference_lag_for`).
    """

    start = time.perf_counter()
    model = NoiseModel.load(model_path)
    if not Path(real_path).exists():
        raise BagError(f"{real_path}: no such bag")
    check_replaceable(out_dir, directory=True)  # refused now, not after the diagnosis
    lag = reference_lag_for(model, reference_lag, sim_params)
    options = dataclasses.replace(options or DiagnosisOptions(), reference_lag_s=lag)
    # streamed: the sensor samples are framed slice by slice, never held whole; a thinned
    # bag keeps the joint states near its blocks, as far as the lags tried reach
    table = table_from_bag(
        real_path,
        model,
        budget_minutes=budget_minutes,
        max_lag_s=max(
            JOINT_MARGIN_S,
            abs(lag) + max(LAG_RANGE_S, options.lag_tolerance_s) + LAG_COARSE_S,
        ),
        progress=progress,
    )
    notices = input_notices(table, budget_minutes)
    diag = diagnose_table(table, source=str(real_path), options=options)
    with atomic_output(out_dir, directory=True) as tmp:
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
        )
        if figures:
            report["figures"] = make_figures(diag, report, tmp)
        report["inputs"]["bad_input"] = {
            k: (round(v, 6) if isinstance(v, float) else int(v))
            for k, v in table.bad_input.items()
            if isinstance(v, (int, float))
        }
        report["inputs"]["notices"] = notices
        # what the model was calibrated on: our simulator (a sim-to-real gap), or a recording
        report["inputs"]["model_kind"] = (
            "simulator" if model_matches_simulator(model) else "recording"
        )
        report["runtime_s"] = round(time.perf_counter() - start, 2)
        (tmp / "report.json").write_text(json.dumps(report, indent=1))
        (tmp / "report.md").write_text(render_markdown(report))
    return report
