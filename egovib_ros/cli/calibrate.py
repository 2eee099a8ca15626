"""`egovib calibrate`: a noise model from a sweep or any no-contact recording
(egovib_ros.bag.calibrate)."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from egovib_ros.bag.calibrate import calibrate_bag_methods, calibrate_bags
from egovib_ros.bag.many import expand_bags, raise_if_bugs, summary_lines
from egovib_ros.cli.jobs import parallel_options
from egovib_ros.cli.options import force_and_quiet, joint_lag_option
from egovib_ros.core import NoiseModel
from egovib_ros.core.methods import rest_detection_warning, short_detection_warning
from egovib_ros.core.noise_model import sweep_mask
from egovib_ros.core.stream import has_bad_input
from egovib_ros.errors import BagError
from egovib_ros.evaluation.contacts import warn_if_contacts
from egovib_ros.gap.advice import joint_lag_of
from egovib_ros.gap.simref import own_lag, with_own_lag
from egovib_ros.outputs import atomic_output, prepare_output
from egovib_ros.robot import load_profile


def register(subparsers: argparse._SubParsersAction) -> None:
    cal = subparsers.add_parser(
        "calibrate",
        help="build a noise model from a calibration sweep or any no-contact recording",
        description="Assign blocks of the bags' sensor signal to joint-velocity cells and write "
        "the per-cell mean/std noise spectra (INTERFACES.md section 4). Several bags (or "
        "directories "
        "of bags) give one model; they are read in parallel with --jobs.",
    )
    cal.add_argument("bags", nargs="+", metavar="BAG", help="rosbag2 bag(s) or directories of bags")
    cal.add_argument("--out", required=True, metavar="MODEL.npz", help="noise-model file to write")
    cal.add_argument(
        "--robot",
        metavar="PROFILE",
        default=None,
        help="robot profile (YAML path or shipped name); default the PR2 hand",
    )
    cal.add_argument(
        "--grid",
        choices=("auto", "full", "superposition", "free"),
        default="auto",
        help="what the bags hold: a full or superposition sweep, or free (any no-contact) motion; "
        "auto = decided from the data",
    )
    parallel_options(cal)
    cal.add_argument(
        "--methods",
        choices=("all", "paper", "hybrid"),
        default="all",
        help="all (default; 'hybrid' is the same): the paper's table and what methods cancel "
        "and hybrid need (the speed -> line map, the residual's table, the gain; fitted on the "
        "first bag); paper: the paper's table only. Either way the contact detector's "
        "thresholds for every method the model can run",
    )
    joint_lag_option(cal)
    force_and_quiet(cal, "replace an existing model written by egovib")
    cal.set_defaults(func=run_calibrate)


def _describe_calibrate(row: dict) -> str:
    """One bag's summary line, from its report row (CalibrationStats.as_dict + input counts)."""
    return (
        f"{row['samples_in']} samples, {row['blocks']} blocks, {row['blocks_used']} used "
        f"({row['mode']}); {row['input_counts']}"
    )


def coverage_lines(model: NoiseModel, detection_s: float | None = None) -> list[str]:
    """What `egovib calibrate` prints about the model's coverage (and, given the seconds of
    calibration data the detector's thresholds come from, whether they are few)."""
    c = model.coverage()
    lines = [
        model.summary(),
        f"coverage: {c['cells_measured']} of {c['cells_total']} cells measured "
        f"({100 * c['fraction_measured']:.1f} %), {c['blocks']} blocks; blocks per measured cell: "
        f"min {c['min_blocks']}, median {c['median_blocks']:g}"
        + (
            f"; {c['cells_under_min_blocks']} cells have too few blocks for a std"
            if c.get("cells_under_min_blocks")
            else ""
        ),
    ]
    if model.measured != "free" and model.dense_ok:
        missing = int(np.sum(model.counts[sweep_mask(model.grid, model.measured)] == 0))
        if missing:
            lines.append(
                f"warning: {missing} cells of the {model.measured} grid have no block; "
                f"they are filled at load time (see NoiseModel)"
            )
    short = None if detection_s is None else short_detection_warning(detection_s)
    return lines if short is None else [*lines, short]


def describe_methods(fitted: dict) -> str:
    """What was fitted for cancel and hybrid, in one line."""
    bands = ", ".join(f"{f:g}" for f in fitted["gain"]["bands_hz"])
    return (
        f"harmonic cancellation removes {fitted['cancellation_db_on_calibration']:g} dB of the "
        f"calibration data; gain bands at {bands} Hz"
    )


def _first_bag_warned(specs, profile):
    """The first of the calibration bags (the methods are fitted on it); each bag that holds
    a simulated run's taps is said in a WARNING (calibration data is motion without contact)."""
    bags = [bag for bag, _ in expand_bags(specs, outputs_per_bag=False)]
    for bag in bags:
        warn_if_contacts(bag, profile)
    return bags[0]


def run_calibrate(args: argparse.Namespace) -> int:
    prepare_output(args.out, force=args.force, inputs=args.bags, kind="model")  # before any work
    profile = load_profile(args.robot)
    methods = "all" if args.methods == "hybrid" else args.methods
    model, stats, results = calibrate_bags(
        args.bags,
        profile=profile,
        sweep=args.grid,
        joint_lag_s=args.joint_lag,
        jobs=args.jobs,
        scheduler=args.scheduler,
        quiet=args.quiet,
    )
    if len(results) > 1 or model is None:
        if len(results) == 1:
            raise BagError(results[0].error)
        for line in summary_lines(results, _describe_calibrate):
            if not args.quiet or line.startswith("  FAILED") or model is None:
                print(line, file=sys.stderr)
        raise_if_bugs(results)
        if model is None:
            print(
                f"egovib: error: no model written: {sum(not r.ok for r in results)} bag(s) failed",
                file=sys.stderr,
            )
            return 2
    where = args.bags[0] if len(args.bags) == 1 else f"{len(results)} bags"
    if model.coverage()["blocks"] == 0:
        raise BagError(
            f"{where}: no steady block near any grid velocity "
            f"(rejected: {stats.rejected}); is this a calibration sweep or free motion?"
        )
    first = _first_bag_warned(args.bags, profile)
    model, fitted = calibrate_bag_methods(first, model, joint_lag_s=args.joint_lag, methods=methods)
    model = with_own_lag(model, fitted["recording"])  # what `egovib gap` judges timing against
    with atomic_output(args.out) as tmp:  # said only once written: a failed save is one line
        model.save(tmp)
    on = "" if len(results) == 1 else f" (fitted on {first})"
    if fitted["methods"] is not None and not args.quiet:
        print(f"methods cancel and hybrid{on}: {describe_methods(fitted['methods'])}",
              file=sys.stderr)  # fmt: skip
    rec = fitted["recording"]
    rest = rest_detection_warning(
        rec.sensor_stamps_ns, rec.joint_stamps_ns, rec.joint_velocity, profile.max_speed
    )
    coverage = coverage_lines(model, fitted["seconds"]) + ([rest] if rest else [])
    if args.quiet:  # warnings and the counts of bad input only, if any (--quiet)
        for line in coverage:
            if line.startswith("warning:"):
                print(line, file=sys.stderr)
        if len(results) == 1 and has_bad_input(stats):
            print(results[0].value["input_counts"], file=sys.stderr)
        return 0
    thresholds = ", ".join(f"{m} {value:.3g}" for m, value in fitted["thresholds"].items())
    print(
        f"contact detector thresholds{on}, 1 false alarm a minute of it: {thresholds}",
        file=sys.stderr,
    )
    for line in coverage:
        print(line, file=sys.stderr)
    lag = own_lag(model)
    if lag is not None:
        print(
            f"joint lag of the recording{on}: {round(1000 * joint_lag_of(lag)):+d} ms (the "
            "vibration trailing the joint states; `egovib gap` names timing only beyond it)",
            file=sys.stderr,
        )
    print(f"rejected blocks: {stats.rejected}", file=sys.stderr)
    if len(results) == 1:
        print(results[0].value["input_counts"], file=sys.stderr)
    print(f"wrote {args.out}", file=sys.stderr)
    return 0
