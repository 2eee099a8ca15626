"""`egovib` console script (CONTRACT section 3).

Each command lives in its own module, which exposes `register(subparsers)`;
the parser it adds sets `func(args) -> int`. Bad input raises EgovibError,
turned here into a one-line error and exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from egovib_ros import __version__
from egovib_ros.cliutil import OneLineErrorParser
from egovib_ros.errors import EgovibError

# Order = order in `egovib --help`.
COMMAND_MODULES = (
    "egovib_ros.sim.cli",  # simulate sweep|motion
    "egovib_ros.offline",  # calibrate, denoise
    "egovib_ros.evaluation.cli",  # evaluate, figures
    "egovib_ros.gap.cli",  # gap, gap validate
    "egovib_ros.bench",  # bench
    "egovib_ros.realdata.cli",  # real convert|evaluate
    "egovib_ros.demo",  # demo (live, ROS 2 nodes)
    "egovib_ros.live_bench",  # live-bench (live, ROS 2 nodes)
)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineErrorParser(  # one-line errors for bad options, like every bad input
        prog="egovib",
        description="Ego-vibration removal for robot accelerometers (spectral subtraction).",
    )
    parser.add_argument("--version", action="version", version=f"egovib {__version__}")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(format="egovib: %(levelname)s: %(message)s")
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help / --version (0), a bad option (2, one line printed)
        return exc.code if isinstance(exc.code, int) else 2
    try:
        return int(args.func(args) or 0)
    except EgovibError as exc:
        print(f"egovib: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("egovib: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
