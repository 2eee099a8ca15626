"""`egovib denoise`: remove ego-vibration from bags (egovib_ros.bag.denoise)."""

from __future__ import annotations

import argparse
import functools
from pathlib import Path

from egovib_ros.bag.denoise import denoise_bag
from egovib_ros.bag.many import run_bags
from egovib_ros.cli.jobs import output_jobs, parallel_options, report_results
from egovib_ros.cli.options import (
    adapt_options,
    adapt_settings,
    force_and_quiet,
    joint_lag_option,
    nonneg_float,
)
from egovib_ros.core import NoiseModel
from egovib_ros.core.methods import METHODS, make_denoiser, resolve_method
from egovib_ros.errors import ConfigError
from egovib_ros.gap.advice import noise_gain_from_report
from egovib_ros.outputs import prepare_output


def register(subparsers: argparse._SubParsersAction) -> None:
    den = subparsers.add_parser(
        "denoise",
        help="remove ego-vibration from bags",
        description="Remove the ego-vibration the model holds at the recorded joint velocities "
        "(the model's default method, hybrid unless the model lacks it; --method paper: the "
        "paper's spectral subtraction); writes a bag with the input topics (copied as they "
        "are) plus the model's denoised topic: one message per raw sample, the input "
        "message with the cleaned field, the raw sample's stamp. Several bags (or "
        "directories of bags): --out is a directory, one output bag per input.",
    )
    den.add_argument("bags", nargs="+", metavar="BAG", help="rosbag2 bag(s) or directories of bags")
    den.add_argument("--model", required=True, metavar="MODEL.npz")
    den.add_argument(
        "--out",
        required=True,
        metavar="BAG",
        help="output bag directory (one input bag) or directory of output bags (several)",
    )
    den.add_argument(
        "--method",
        choices=METHODS,
        default=None,
        help="hybrid (the default, where the model was calibrated for it): speed-locked "
        "harmonic cancellation, then a low-latency gain (4 ms band-passed; the drop-in "
        "output takes the look-ahead its split needs, 4-10 ms); paper: the paper's block "
        "spectral subtraction (a block of delay); cancel: the cancellation alone (no delay)",
    )
    joint_lag_option(den)
    den.add_argument(
        "--noise-gain",
        metavar="REPORT.json",
        default=None,
        help="an egovib gap report whose verdict is drift: the noise estimate follows the "
        "level change it fitted over the recording's elapsed time (a warm-up), from the "
        "level the model was calibrated at",
    )
    den.add_argument(
        "--channels",
        choices=("per_axis", "combined"),
        default="per_axis",
        help="per_axis: each axis cleaned (default); combined: the paper's 1-D signal in x",
    )
    den.add_argument(
        "--output",
        choices=("dropin", "bandpassed"),
        default=None,
        help="dropin (default with per_axis): the raw field minus the estimated ego-vibration, "
        "gravity and everything outside the band kept; bandpassed: the cleaned band-passed "
        "signal (the paper's; always with --channels combined)",
    )
    den.add_argument(
        "--oversubtraction",
        type=nonneg_float,
        default=1.0,
        help="alpha in max(|Y| - alpha N, beta N)",
    )
    den.add_argument(
        "--floor", type=nonneg_float, default=0.0, help="beta in max(|Y| - alpha N, beta N)"
    )
    den.add_argument(
        "--compress",
        choices=("none", "zstd"),
        default="none",
        help="MCAP chunk compression of the output bag (readable by rosbags and ros2 bag)",
    )
    den.add_argument(
        "--replace-denoised",
        action="store_true",
        help="a bag that holds the model's denoised topic already (a recorded live run) is "
        "refused; with this option that topic is left out of the copy and egovib's written in "
        "its place",
    )
    adapt_options(den)
    den.add_argument(
        "--save-model",
        metavar="FILE",
        default=None,
        help="with --adapt: write the model as adapted by the end of the bag (one bag; a "
        "model like any other: the cells learnt online are marked, `egovib model show` "
        "shows them)",
    )
    parallel_options(den)
    force_and_quiet(den, "replace an existing bag (and --save-model file) written by egovib")
    den.set_defaults(func=run_denoise)


def _describe_denoise(figures: dict) -> str:
    text = (
        f"{figures['denoised_messages']} samples denoised by {figures['method']} "
        f"({figures['channels']}, {figures['output']}, {figures['delay_ms']:.1f} ms); "
    )
    if figures["method"] == "paper":
        text += (
            f"blocks {figures['blocks']}, out of grid {figures['blocks_out_of_grid']}, "
            f"no joint state {figures['blocks_no_joint_state']}"
        )
        if figures.get("blocks_unmeasured"):
            text += f", on unmeasured cells {figures['blocks_unmeasured']}"
    else:
        text += f"samples with no joint state {figures['samples_no_joint_state']}"
        if figures.get("samples_unmeasured"):
            text += f", on unmeasured cells {figures['samples_unmeasured']}"
    adapt = figures.get("adapt")
    if adapt:
        text += (
            f"; adapted: {adapt['blocks_learnt']} blocks learnt, {adapt['blocks_gated']} left "
            f"out for contacts, cells learnt online {adapt['cells_learnt']} "
            f"({adapt['cells_new']} never calibrated)"
        )
        if adapt.get("lines_found"):
            text += f", {adapt['lines_found']} harmonic lines found beyond the calibrated speeds"
        if figures.get("saved_model"):
            text += f", model written to {figures['saved_model']}"
    if figures["raw_without_output"]:
        text += (
            f", raw messages without a denoised one (bad, out of order or recorded twice) "
            f"{figures['raw_without_output']}"
        )
    if figures.get("replaced_denoised"):
        text += f", the bag's own denoised topic replaced ({figures['replaced_denoised']} messages)"
    if figures["compression"] != "none" and figures["size_ratio"]:
        text += f"; zstd size ratio {figures['size_ratio']:.1f}"
    return text + f"; {figures['input_counts']}"


def _denoise_task(bag: Path, out: Path, progress, **options) -> dict:
    return denoise_bag(bag, out, progress=progress, **options)


def run_denoise(args: argparse.Namespace) -> int:
    model = NoiseModel.load(args.model)  # a bad model fails once, before any bag is touched
    model.robot_profile()
    noise_gain_db = noise_gain_from_report(args.noise_gain, where="--noise-gain")
    settings = dict(
        channels=args.channels,
        output=args.output,
        oversubtraction=args.oversubtraction,
        floor=args.floor,
        joint_lag_s=args.joint_lag,
        noise_gain_db=noise_gain_db,
    )
    adapt = adapt_settings(args)
    if adapt is not None:
        settings["adapt"] = adapt
    elif args.save_model is not None:
        raise ConfigError("--save-model: applies with --adapt only")
    # Bad options fail here too; this also builds the model's look-up table once, which
    # the workers then receive with the model instead of each building (and logging) it.
    method = resolve_method(model, args.method)
    make_denoiser(model, method, **settings)  # also: a model without detector thresholds
    jobs = output_jobs(args.bags, args.out)
    for job in jobs:  # before any work: every output may be written (or replaced with --force)
        prepare_output(job.out, force=args.force, inputs=[job.bag, args.model], kind="bag")
    if args.save_model is not None:
        if len(jobs) != 1:
            raise ConfigError(f"--save-model: takes one bag, got {len(jobs)}")
        prepare_output(
            args.save_model,
            force=args.force,
            inputs=[jobs[0].bag, args.model, jobs[0].out],
            kind="model",
            option="--save-model",
        )
        settings["save_model"] = args.save_model
    task = functools.partial(
        _denoise_task,
        model=model,
        method=method,
        compress=args.compress,
        replace_denoised=args.replace_denoised,
        **settings,
    )
    results = run_bags(
        task, jobs, jobs=args.jobs, scheduler=args.scheduler, desc="denoise", quiet=args.quiet
    )
    return report_results(
        results,
        _describe_denoise,
        single=len(jobs) == 1,
        quiet=args.quiet,
        said=lambda figures: figures["input_counts"] if figures["bad_input"] else "",
    )
