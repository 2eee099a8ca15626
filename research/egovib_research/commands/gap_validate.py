"""`egovib gap validate [...]`: the gap diagnosis checked blind on bags with hidden effects
(experiments/gap_validation.py, experiments/gap_real_injection.py; docs/gap.md)."""

from __future__ import annotations

import argparse

from egovib_research.experiments.gap_validation import output_names, run_validation
from egovib_ros.cli import options
from egovib_ros.outputs import prepare_outputs_in


def register(subparsers) -> None:
    """Add `validate` to `egovib gap`'s actions."""
    val = subparsers.add_parser(
        "validate",
        help="blind validation of the diagnosis on simulated bags with hidden effects",
        description="Check `egovib gap` blind: bags with hidden effects (drawn classes, "
        "strengths and seeds), each diagnosed with a model calibrated on our simulator; "
        "writes DIR/gap_validation*.md/.json/.png.",
    )
    val.add_argument(
        "--reality",
        choices=["sim", "alt", "third", "real"],
        default="sim",
        help='where the blind "real" bags come from: our simulator, the independent '
        "alternate-reality generator (egovib_research.altreality) or the third hand "
        "(egovib_research.thirdhand, written from the effect vocabulary alone), the model "
        "always calibrated on our simulator; or `real`: known effects injected into one part "
        "of the real flight bags/quadcopter_ar8, the model calibrated on the other part",
    )
    val.add_argument("--seeds", type=options.positive_int, default=5, help="seeds per effect class")
    val.add_argument(
        "--master-seed",
        type=options.int_in(0, 2**31),
        default=2026,
        help="seed from which all runs' classes, strengths and seeds are drawn",
    )
    val.add_argument(
        "--extra-none",
        type=options.int_in(0, 1000),
        default=0,
        help="this many more bags of every `none` class, for the false-positive rate",
    )
    val.add_argument(
        "--duration",
        type=options.float_in(30.0, 3600.0),
        default=120.0,
        help="seconds per blind real bag, 30 .. 3600",
    )
    val.add_argument(
        "--jobs", type=options.positive_int, default=1, help="parallel worker processes"
    )
    val.add_argument(
        "--no-ladder", action="store_true", help="skip the detectability strength ladder"
    )
    val.add_argument("--out", default="docs", help="output directory (default: docs)")
    options.force_and_quiet(val, "replace the files of a previous run in DIR")
    val.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    prepare_outputs_in(args.out, output_names(args.reality), force=args.force)  # before any work
    summary = run_validation(
        seeds=args.seeds,
        duration_s=args.duration,
        out_dir=args.out,
        jobs=args.jobs,
        ladder=not args.no_ladder,
        progress=not args.quiet,
        reality=args.reality,
        master_seed=args.master_seed,
        extra_none=args.extra_none,
    )
    flagged = summary["none_false_positive_rate"]
    if not args.quiet:
        print(
            f"gap validate ({args.reality}): accuracy {summary['accuracy']:.3f}, "
            f"none flagged {'n/a' if flagged is None else format(flagged, '.3f')}, "
            f"{summary['n_runs']} runs -> {summary['outputs']}"
        )
    return 0
