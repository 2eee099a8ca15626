"""`egovib model show MODEL.npz --out DIR [--bag BAG]`: look at a noise model
(viz/model_show.py: coverage, spectra, where a recording falls)."""

from __future__ import annotations

import argparse
import sys

from egovib_ros.cli.options import force_and_quiet
from egovib_ros.core.noise_model import NoiseModel
from egovib_ros.outputs import atomic_output, prepare_output
from egovib_ros.viz.model_show import place_bag, summary_lines, write_views


def register(subparsers) -> None:
    """Add `model` with its `show` subcommand."""
    model = subparsers.add_parser(
        "model",
        help="look at a noise model (coverage, spectra, where a recording falls)",
        description="Commands on a noise model (.npz written by egovib calibrate).",
    )
    actions = model.add_subparsers(dest="action", required=True, metavar="ACTION")
    show = actions.add_parser(
        "show",
        help="coverage and spectra figures and a summary.md of a noise model",
        description="Write figures of a noise model into DIR: coverage.png (cells measured, "
        "blocks per cell), spectra_<channel>.png (mean and std spectra of a few measured "
        "cells, the paper's Fig. 3), with --bag bag.png (where the recording's blocks fall "
        "against the measured cells), and summary.md with the numbers.",
    )
    show.add_argument("model", metavar="MODEL.npz", help="noise model written by egovib calibrate")
    show.add_argument("--out", required=True, metavar="DIR", help="output directory")
    show.add_argument(
        "--bag",
        metavar="BAG",
        default=None,
        help="a recording of the model's robot: where its blocks fall against the model's cells",
    )
    force_and_quiet(show, "replace an existing output directory written by egovib")
    show.set_defaults(func=run_show)


def run_show(args: argparse.Namespace) -> int:
    out = prepare_output(
        args.out, force=args.force, inputs=[args.model, args.bag], kind="directory"
    )
    model = NoiseModel.load(args.model)
    placement = None
    if args.bag is not None:
        placement = place_bag(model, args.bag, quiet=args.quiet)
    with atomic_output(out, directory=True, kind="directory") as tmp:
        tmp.mkdir()
        written = write_views(model, tmp, placement=placement, model_path=args.model)
    if not args.quiet:
        for line in summary_lines(model, placement):
            print(line, file=sys.stderr)
        print(f"wrote {out} ({', '.join(written)})", file=sys.stderr)
    return 0
