"""What every `egovib simulate` scenario (sweep, motion: cli/simulate.py; robot:
cli/simulate_robot.py) shares: the --seed/--truth and bag-output options, the outputs
refused before any work, the bag written slice by slice with the truth file, the progress
bar."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tqdm import tqdm

from egovib_ros.bag import write_recordings
from egovib_ros.cli import options
from egovib_ros.outputs import TRUTH_KEYS, atomic_output, json_holding, prepare_output


def seed_and_truth_options(parser: argparse.ArgumentParser) -> None:
    """--seed and --truth of every `simulate` scenario (robot too)."""
    parser.add_argument("--seed", type=options.seed, default=0, help=f"0 .. {options.MAX_SEED}")
    parser.add_argument(
        "--truth",
        metavar="FILE",
        help="write {seed, effects, tap_onsets_ns} to this JSON file "
        "(must not exist unless --force)",
    )


def bag_output_options(parser: argparse.ArgumentParser) -> None:
    """How every `simulate` scenario writes (`write_bag`): --storage .. --quiet."""
    parser.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    parser.add_argument("--compress", action="store_true", help="zstd chunk compression (MCAP)")
    options.force_and_quiet(parser, "replace an existing output bag / truth file written by egovib")


def progress_bar(total: float, quiet: bool):
    """(update, close) of the progress bar of a run of `total` simulated seconds."""
    if quiet:
        return None, lambda: None
    bar = tqdm(total=round(total, 1), unit="sim-s", desc="simulate", leave=False)
    return (lambda s: bar.update(s)), bar.close


def prepare_outputs(args: argparse.Namespace, source) -> Path:
    """Refuse before any work: the bag --out and the --truth file (`source`: the file they
    are made from, never to be replaced)."""
    out = prepare_output(args.out, force=args.force, inputs=[source, args.truth], kind="bag")
    if args.truth:
        prepare_output(
            args.truth,
            force=args.force,
            inputs=[source, args.out],
            kind="json",
            option="--truth",
            ours=json_holding(TRUTH_KEYS),
        )
    return out


def write_bag(args: argparse.Namespace, out: Path, slices, truth: dict, close, **options) -> None:
    """Simulate and write slice by slice (constant memory however long the run), then the
    --truth file; `close` (the progress bar's) runs whatever happens."""
    try:
        with atomic_output(out, directory=True, kind="bag") as tmp:
            write_recordings(tmp, slices, storage=args.storage, compress=args.compress, **options)
            if args.truth:
                with atomic_output(args.truth) as tmp_truth:
                    tmp_truth.write_text(json.dumps(truth) + "\n")
    finally:
        close()
