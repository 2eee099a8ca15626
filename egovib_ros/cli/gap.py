"""`egovib gap --model M --real BAG --out DIR` (INTERFACES.md section 3). In the
repository's venv `egovib gap validate` joins it (research/: commands/gap_validate.py)."""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

from egovib_ros.bag.many import expand_bags, is_bag, run_bags
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
        "--reference",
        nargs="+",
        action="extend",
        metavar="BAG",
        help="an earlier recording of the same robot (cold vs warm, before vs after "
        "maintenance, last month): report.json's `change` lists what differs in --real (a "
        "joint-lag shift in ms, a level change in dB, a new interaction). One bag for every "
        "--real bag, or one per --real bag (in order, or directories matched by the bags' "
        "names)",
    )
    parser.add_argument(
        "--reference-lag",
        type=options.float_in(-1.0, 1.0),
        metavar="SECONDS",
        help="the joint lag that counts as in sync: seconds the vibration trails the joint "
        "states, as --joint-lag of egovib denoise (default: the one the model's calibration "
        "recording showed, stored by egovib calibrate; for an older model of the simulated "
        "joints measured on the simulator; else 0)",
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
    references = reference_bags(args.reference, jobs, args.real)  # before any output
    for job in jobs:  # before any work
        prepare_output(
            job.out,
            force=args.force,
            inputs=[args.model, job.bag, args.sim_params, *(args.reference or [])],
            kind="report",
        )
    # measured once on the simulator, not once per bag; the diagnosis scans the opposite
    # sign internally (joint states stamped late)
    given = None if args.reference_lag is None else -args.reference_lag
    lag = reference_lag_for(model, given, args.sim_params)
    task = functools.partial(
        gap_task,
        references=references,
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


def reference_bags(specs, jobs, real_specs) -> dict[str, str]:
    """--reference for each --real bag (keyed by the bag's path): one bag for all; or one
    per bag, directories matched by the bags' names under them, else in order."""
    if not specs:
        return {}
    # each spec on its own: references write nothing, and one may serve several bags
    refs = [ref for spec in specs for ref in expand_bags([spec], outputs_per_bag=False)]
    if len(refs) == 1:
        return {str(job.bag): str(refs[0][0]) for job in jobs}
    if all(Path(spec).is_dir() and not is_bag(Path(spec)) for spec in specs):
        # directories of bags: each --real bag's reference by its name under them
        names = {str(name): str(bag) for bag, name in refs}
        reals = expand_bags(real_specs)
        missing = [str(name) for _, name in reals if str(name) not in names]
        if missing:
            raise ConfigError(
                f"--reference: no bag named {missing[0]} under {', '.join(map(str, specs))} "
                "(directories are matched by the bags' names)"
            )
        return {str(job.bag): names[str(name)] for job, (_, name) in zip(jobs, reals)}
    if len(refs) == len(jobs):
        return {str(job.bag): str(ref) for job, (ref, _) in zip(jobs, refs)}
    raise ConfigError(
        f"--reference: {len(refs)} bags for {len(jobs)} --real bags (give one for all, one "
        "per bag in the same order, or directories holding bags of the same names)"
    )


def gap_task(bag, out, progress, *, model_path, references=None, **options) -> dict:
    """One bag's diagnosis into its report directory; the summary line's figures."""

    reference = (references or {}).get(str(bag))
    report = run_gap(model_path, bag, out, progress=progress, reference_path=reference, **options)
    return {
        "notices": report["inputs"]["notices"],
        "gap": report["gap"],
        "verdict": report["verdict"]["effect"],
        "effects": [e["effect"] for e in report["verdict"].get("effects", [])],
        "change": [_change_said(c) for c in report.get("change", [])],
        "reference": reference,
        "confidence": report["verdict"].get("confidence"),
        "report": f"{out}/report.md",
    }


def _change_said(change: dict) -> str:
    """A change in a few words: the lag shift, or the level it brings (a drift is one)."""
    p, effect = change["parameters"], change["effect"]
    if "lag_shift_ms" in p:
        return f"{effect} {p['lag_shift_ms']:+.0f} ms"
    if "level_change_db" in p:
        return f"{effect} {p['level_change_db']:+.1f} dB"
    return effect


def describe_gap(summary: dict) -> str:
    g = {
        k: "n/a" if summary["gap"].get(k) is None else f"{summary['gap'][k]:.2f}"
        for k in ("sim_as_is", "after_refit", "after_effect", "floor")
    }
    notices = "".join(f" ({n})" for n in summary.get("notices", ()))
    effects = summary.get("effects") or (
        [] if summary["verdict"] == "none" else [summary["verdict"]]
    )
    found = "+".join(effects) or "none"
    changed = ""
    if summary.get("reference"):
        changed = f"; changed since {summary['reference']}: " + (
            ", ".join(summary.get("change") or []) or "nothing"
        )
    return (
        f"sim as-is {g['sim_as_is']} dB, baseline {g['after_refit']} dB, "
        f"+{found} {g['after_effect']} dB, floor {g['floor']} dB; "
        f"verdict {found}{changed} -> {summary['report']}{notices}"
    )
