"""`egovib real ...`: the real quadcopter flight, end to end.

egovib real convert NPZ --out bags/quadcopter_ar8          # flight log -> rosbag2 bag
egovib real evaluate --bag bags/quadcopter_ar8 --out docs   # the experiment: docs/real_*
egovib real gap --bag bags/quadcopter_ar8 --out docs/gap_flight   # gap diagnosis, half vs half
"""

from __future__ import annotations

import argparse

from egovib_research.experiments import gap_flight as flight
from egovib_research.experiments.flight import convert, experiment
from egovib_ros.cli import options


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "real",
        help="the real quadcopter flight log: convert, evaluate, gap",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    commands = parser.add_subparsers(dest="real_command", required=True, metavar="COMMAND")
    conv = commands.add_parser(
        "convert",
        help="flight log (npz) -> rosbag2 bag (zstd MCAP)",
        description=convert.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    convert.add_arguments(conv)
    conv.set_defaults(func=convert.run)

    ev = commands.add_parser(
        "evaluate",
        help="calibrate on the first part, denoise the rest with events added, "
        "compare with the baselines; writes DIR/real_*",
        description=experiment.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    experiment.add_arguments(ev)
    ev.set_defaults(func=experiment.run)

    gap = commands.add_parser(
        "gap",
        help="gap diagnosis of the flight: a model calibrated on one half, diagnosed on the "
        "other (both ways); writes DIR/summary.md and one report directory per direction",
        description=flight.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    gap.add_argument("--bag", default="bags/quadcopter_ar8", help="the converted flight bag")
    gap.add_argument(
        "--out", default="docs/gap_flight", help="report directory (default docs/gap_flight)"
    )
    gap.add_argument(
        "--split",
        type=options.float_in(2.0, flight.FLIGHT_END_S - 2.0),
        default=flight.SPLIT_S,
        metavar="SECONDS",
        help=f"where the flight is cut into the two parts (default {flight.SPLIT_S:g} s)",
    )
    gap.add_argument(
        "--force", action="store_true", help="replace an existing report directory of egovib"
    )
    gap.set_defaults(func=flight.run)
