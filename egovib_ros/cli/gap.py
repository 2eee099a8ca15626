"""`egovib gap --model M --real BAG --out DIR` (INTERFACES.md section 3). In the
repository's venv `egovib gap validate` joins it (research/: commands/gap_validate.py)."""

from __future__ import annotations

import argparse
import functools
import sys

from egovib_ros.bag.many import run_bags
from egovib_ros.cli import options
from egovib_ros.cli.jobs import output_jobs, report_results
from egovib_ros.core.noise_model import NoiseModel
from egovib_ros.errors import ConfigError
from egovib_ros.gap.diagnose import DiagnosisOptions
from egovib_ros.gap.features import DEFAULT_BUDGET_MINUTES
from egovib_ros.gap.pipeline import reference_lag_for, run_gap
from egovib_ros.outputs import prepare_output


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "gap",
        help="sim-to-real gap diagnosis",
        description="Where does a simulator-calibrated noise model miss a real recording, "
        "which unmodelled effect causes it, and how far does the gap shrink once it is added.",
    )
    parser.add_argument("--model", help="noise-model .npz calibrated on the simulator")
    parser.add_argument(
        "--real",
        nargs="+",
        action="extend",
        metavar="BAG",
        help="real recording(s): rosbag2 bags with the model's sensor and joint-state topics, "
        "or directories of bags (several: one report directory per bag under --out)",
    )
    parser.add_argument(
        "--out",
        help="output directory (report.json, report.md, figures); with several bags, the "
        "directory holding one report directory per bag",
    )
    parser.add_argument(
        "--write-back",
        action="store_true",
        help="write the fitted effect into a copy of the sim config as OUT/sim_updated.yaml "
        "and check it on the held-out data",
    )
    parser.add_argument(
        "--sim-params", metavar="YAML", help="simulator config (default config/sim.yaml)"
    )
    parser.add_argument(
        "--reference-lag",
        type=options.float_in(-1.0, 1.0),
        metavar="SECONDS",
        help="lag between joint states and vibration that counts as in sync (default: "
        "measured on the simulator for this robot's model, else 0)",
    )
    parser.add_argument(
        "--folds",
        type=options.int_in(2, 20),
        default=5,
        help="blocked cross-validation in time: contiguous folds, each held out once (default 5)",
    )
    parser.add_argument(
        "--train-fraction",
        type=options.float_in(0.2, 0.9),
        default=None,
        help="instead of cross-validation: fit on this leading share of the recording "
        "(0.2 .. 0.9), test on the rest",
    )
    parser.add_argument(
        "--budget-minutes",
        type=options.float_in(1.0, 1e6),
        default=DEFAULT_BUDGET_MINUTES,
        metavar="MINUTES",
        help="diagnose at most this many minutes of blocks per bag: a longer bag is thinned "
        "evenly over its whole length (with the joint states near the kept blocks), so "
        "memory and time stop growing with the bag "
        f"(default {DEFAULT_BUDGET_MINUTES:g}, the bag length the diagnosis is validated on)",
    )
    parser.add_argument(
        "--force", action="store_true", help="replace an existing report directory of egovib"
    )
    parser.add_argument(
        "--jobs",
        type=options.positive_int,
        default=1,
        help="bags diagnosed at once (a local Dask cluster)",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="diagnose the bags on an existing Dask cluster (e.g. tcp://host:8786)",
    )
    parser.add_argument("--quiet", action="store_true", help=options.QUIET_HELP)
    parser.add_argument(
        "--no-figures",
        action="store_true",
        help="write report.json and report.md only (quicker, for many bags)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    missing = [
        flag
        for flag, value in (("--model", args.model), ("--real", args.real), ("--out", args.out))
        if not value
    ]
    if missing:
        raise ConfigError(
            f"gap: missing {', '.join(missing)} (usage: egovib gap --model M --real BAG --out DIR)"
        )

    model = NoiseModel.load(args.model)  # a broken model is named first, as before
    jobs = output_jobs(args.real, args.out)
    for job in jobs:  # before any work
        prepare_output(
            job.out, force=args.force, inputs=[args.model, job.bag, args.sim_params], kind="report"
        )
    # measured once on the simulator, not once per bag
    lag = reference_lag_for(model, args.reference_lag, args.sim_params)
    task = functools.partial(
        gap_task,
        model_path=args.model,
        write_back=args.write_back,
        sim_params=args.sim_params,
        reference_lag=lag,
        options=DiagnosisOptions(train_fraction=args.train_fraction, folds=args.folds),
        budget_minutes=args.budget_minutes,
        figures=not args.no_figures,
    )
    results = run_bags(
        task, jobs, jobs=args.jobs, scheduler=args.scheduler, desc="gap", quiet=args.quiet
    )
    if len(jobs) == 1 and results[0].ok:  # one bag: its line on stdout, as before
        summary = results[0].value
        for notice in summary["notices"]:
            print(f"gap: {jobs[0].bag}: {notice}", file=sys.stderr)
        if not args.quiet:
            print(f"gap: {describe_gap(dict(summary, notices=()))}", file=sys.stdout)
        return 0
    return report_results(
        results,
        describe_gap,
        single=len(jobs) == 1,
        quiet=args.quiet,
        said=lambda summary: "; ".join(summary["notices"]),
    )


def gap_task(bag, out, progress, *, model_path, **options) -> dict:
    """One bag's diagnosis into its report directory; the summary line's figures."""

    report = run_gap(model_path, bag, out, progress=progress, **options)
    return {
        "notices": report["inputs"]["notices"],
        "gap": report["gap"],
        "verdict": report["verdict"]["effect"],
        "confidence": report["verdict"].get("confidence"),
        "report": f"{out}/report.md",
    }


def describe_gap(summary: dict) -> str:
    g = {
        k: "n/a" if summary["gap"].get(k) is None else f"{summary['gap'][k]:.2f}"
        for k in ("sim_as_is", "after_refit", "after_effect", "floor")
    }
    notices = "".join(f" ({n})" for n in summary.get("notices", ()))
    return (
        f"sim as-is {g['sim_as_is']} dB, baseline {g['after_refit']} dB, "
        f"+{summary['verdict']} {g['after_effect']} dB, floor {g['floor']} dB; "
        f"verdict {summary['verdict']} -> {summary['report']}{notices}"
    )
