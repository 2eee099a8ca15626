"""`egovib evaluate` (INTERFACES.md sections 3 and 6).

egovib evaluate BAG [BAG ...] --model MODEL.npz --json FILE|DIR [--calibration BAG]
                [--jobs N | --scheduler ADDRESS]
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
from pathlib import Path

import numpy as np

from egovib_ros.bag.many import is_bag, run_bags
from egovib_ros.bag.reader import bag_fingerprint
from egovib_ros.bag.recording import bag_topic_names
from egovib_ros.cli import options
from egovib_ros.cli.jobs import output_jobs, parallel_options, report_results
from egovib_ros.core import NoiseModel
from egovib_ros.errors import BagError, ConfigError, bag_error
from egovib_ros.evaluation import baselines, metrics
from egovib_ros.evaluation.contacts import warn_if_contacts
from egovib_ros.evaluation.evaluate import REPORT_FIELDS, bad_samples_said, evaluate_bag
from egovib_ros.outputs import atomic_output, json_holding, prepare_output


def calibration_bag(given, model, *, thresholds_from_run: bool = False) -> Path | None:
    """The no-contact bag the detection thresholds come from: --calibration, else the
    bag the model was calibrated from (`egovib calibrate` stores its absolute path and
    fingerprint), found and unchanged. A model that names a bag that is gone or changed is
    refused, not silently scored with thresholds from the run itself (that takes
    --thresholds-from-run). Models without a stored bag (made from arrays, or before
    paths were stored) use their `source` if it is a bag found here, else the run."""
    if given:
        warn_if_contacts(given, model.robot_profile())
        return Path(given)
    if thresholds_from_run:
        return None
    where = model.provenance.get("path", "noise model")
    stored = model.provenance.get("source_bag", "")
    if not stored:
        source = Path(model.provenance.get("source", "") or "-")
        return source if is_bag(source) else None
    fix = "give --calibration BAG (no-contact data) or --thresholds-from-run"
    if not is_bag(Path(stored)):
        raise ConfigError(
            f"{where}: the bag it was calibrated from ({stored}) is not found; it sets the "
            f"detection thresholds: {fix}"
        )
    fingerprint = model.provenance.get("source_fingerprint")
    if fingerprint and bag_fingerprint(stored) != fingerprint:
        raise ConfigError(
            f"{where}: the bag it was calibrated from ({stored}) has changed since; {fix}"
        )
    return Path(stored)


def evaluate_task(bag: Path, out: Path, progress, *, model_path: str, **options) -> dict:
    """One bag: streamed evaluation, its JSON written atomically; returns the summary
    figures (what the summary line shows). Runs in a worker with --jobs/--scheduler."""

    calibration = options.get("calibration")
    try:
        report = evaluate_bag(bag, progress=progress, **options)
    except ValueError as exc:  # a method that cannot run on these data
        raise bag_error(str(bag), exc) from None
    report = {
        "bag": str(bag),
        "model": str(model_path),
        "calibration_bag": str(calibration) if calibration else None,
        **report,
    }
    with atomic_output(out) as tmp:
        tmp.write_text(json.dumps(metrics.json_safe(report), indent=2) + "\n")
    fields = (
        "n_taps",
        "noise_reduction_db",
        "peak_snr_raw_db",
        "peak_snr_denoised_db",
        "tap_retention",
        "f1_raw",
        "f1_denoised",
    )
    recorded = report.get("methods", {}).get("bag_denoised")
    return {
        **{field: report[field] for field in fields},
        "bad_samples": bad_samples_said(report["bad_samples"]),
        # the bag's own denoised topic (a live run recorded, or `egovib denoise` with the
        # gap advice's --joint-lag / --noise-gain): its figures beside egovib's own
        **(
            {
                "bag_denoised": {
                    "topic": bag_topic_names(options["model"].profile)["denoised"],
                    **{k: recorded.get(k) for k in ("noise_reduction_db", "f1")},
                }
            }
            if recorded
            else {}
        ),
    }


def _describe(figures: dict) -> str:
    def number(value, form):
        return "n/a" if value is None or not np.isfinite(value) else format(value, form)

    def f1(value):  # no tap: no F1 to score (its false alarms are in the JSON)
        return number(value, ".2f") if figures["n_taps"] else "n/a"

    text = (
        f"{figures['n_taps']} taps, noise reduction {number(figures['noise_reduction_db'], '.1f')} "
        f"dB, peak SNR {number(figures['peak_snr_raw_db'], '.1f')} -> "
        f"{number(figures['peak_snr_denoised_db'], '.1f')} dB, retention "
        f"{number(figures['tap_retention'], '.2f')}, F1 raw {f1(figures['f1_raw'])} -> "
        f"denoised {f1(figures['f1_denoised'])}"
    )
    recorded = figures.get("bag_denoised")
    if recorded:
        text += (
            f"; the bag's {recorded['topic']}: noise reduction "
            f"{number(recorded['noise_reduction_db'], '.1f')} dB, F1 "
            f"{number(recorded['f1'], '.2f')}"
        )
    return text + (f"; {figures['bad_samples']}" if figures["bad_samples"] else "")


def run_evaluate(args: argparse.Namespace) -> int:
    options.adapt_settings(args)  # --forget-s without --adapt: before any work
    model = NoiseModel.load(args.model)  # a bad model fails once, before any bag is touched
    model.robot_profile()
    calibration_path = calibration_bag(
        args.calibration, model, thresholds_from_run=args.thresholds_from_run
    )
    # One bag given as such -> --json is the JSON file (docs/INTERFACES.md); several bags or a
    # directory -> a directory holding <bag name>.json per bag (the bag's path relative to the
    # directory it was found in, e.g. OUT/day1/run0.json).
    jobs = output_jobs(args.bags, args.json, suffix=".json", option="--json")
    for job in jobs:  # before any work: every JSON may be written (or replaced with --force)
        prepare_output(
            job.out,
            force=args.force,
            kind="json",
            option="--json",
            inputs=[job.bag, args.model, calibration_path, args.model_short],
            ours=json_holding(REPORT_FIELDS),  # what egovib evaluate wrote
        )
    model_short = NoiseModel.load(args.model_short) if args.model_short else None
    methods = None
    if args.methods:
        methods = [m.strip() for m in args.methods.split(",") if m.strip()]
        unknown = [m for m in methods if m not in baselines.METHOD_LABELS]
        if unknown:
            raise ConfigError(
                f"--methods: unknown method(s) {unknown}; expected {list(baselines.METHOD_LABELS)}"
            )
    task = functools.partial(
        evaluate_task,
        model_path=str(args.model),
        model=model,
        calibration=calibration_path,
        model_short=model_short,
        methods=methods,
        max_bad_fraction=args.max_bad_fraction,
        adapt=options.adapt_settings(args),
    )
    results = run_bags(
        task, jobs, jobs=args.jobs, scheduler=args.scheduler, desc="evaluate", quiet=args.quiet
    )
    if len(jobs) == 1:
        r = results[0]
        if not r.ok:
            raise BagError(r.error.splitlines()[0] if r.error else f"{r.bag}: failed")
        if r.value["bad_samples"]:  # always said, even with --quiet
            print(f"{r.bag}: {r.value['bad_samples']}", file=sys.stderr)
        if not args.quiet:
            print(f"{r.bag}: {_describe({**r.value, 'bad_samples': ''})}; wrote {r.out}")
        return 0
    return report_results(
        results,
        _describe,
        single=False,
        quiet=args.quiet,
        said=lambda value: value["bad_samples"],
    )


def register(subparsers) -> None:
    ev = subparsers.add_parser(
        "evaluate",
        help="paper metrics on bags with ground truth (JSON)",
        description="Denoise BAG with MODEL by every method and write the paper's "
        "metrics (INTERFACES.md section 6) as JSON. Topics come from the model's robot "
        "profile: its sensor topic, joint states and the ground truth beside the sensor "
        "topic, <parent of the sensor topic>/contact (PR2: /accelerometer/raw, "
        "/joint_states, /accelerometer/contact). If BAG also holds the profile's denoised "
        "topic (from `egovib denoise` or the live node), it is scored too, as method "
        "'bag_denoised'. Bags are streamed (memory does not "
        "grow with their length). Several bags (or directories of bags): --json is a "
        "directory, one JSON per bag (<bag name>.json), processed in parallel with --jobs.",
    )
    ev.add_argument(
        "bags",
        nargs="+",
        metavar="BAG",
        help="rosbag2 bag(s) with the model's sensor topic, joint states and ground truth "
        "(<parent of the sensor topic>/contact), or directories of bags",
    )
    ev.add_argument("--model", required=True, help="noise model .npz")
    ev.add_argument(
        "--json",
        required=True,
        metavar="FILE",
        help="output JSON (one bag), or directory of <bag name>.json (several bags)",
    )
    ev.add_argument(
        "--calibration",
        metavar="BAG",
        help="no-contact bag for detection thresholds (default: the bag the model was "
        "calibrated from; refused if it is gone or changed)",
    )
    ev.add_argument(
        "--thresholds-from-run",
        action="store_true",
        help="take detection thresholds from this run's own no-contact samples (no "
        "calibration bag)",
    )
    ev.add_argument(
        "--model-short", metavar="MODEL", help="model with 32-sample blocks (adds method paper_L32)"
    )
    ev.add_argument("--methods", help="comma list of methods (default: all that can run)")
    ev.add_argument(
        "--max-bad-fraction",
        type=options.fraction,
        default=metrics.MAX_BAD_FRACTION,
        metavar="FRACTION",
        help="refuse a recording with more bad (non-finite or out-of-range) samples "
        f"than this (default {metrics.MAX_BAD_FRACTION:g})",
    )
    options.adapt_options(ev)
    parallel_options(ev)
    options.force_and_quiet(ev, "replace an existing JSON file")
    ev.set_defaults(func=run_evaluate)
