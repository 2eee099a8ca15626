"""`egovib bench`: performance figures (x real time) as JSON and markdown (tools/bench.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

from egovib_research.tools import bench as tool


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="performance figures (x real time) as JSON + markdown",
        description=tool.__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--json", required=True, metavar="FILE", help="where to write the JSON figures"
    )
    parser.add_argument(
        "--markdown", metavar="FILE", help="markdown summary (default: FILE with .md suffix)"
    )
    parser.add_argument("--quick", action="store_true", help="short inputs (seconds), for tests")
    parser.add_argument(
        "--bag-seconds",
        type=float,
        default=None,
        metavar="S",
        help="length of the simulated bag for the bag figures (default 60; quick 3)",
    )
    parser.add_argument(
        "--bag", type=Path, default=None, help="measure the bag figures on this bag instead"
    )
    parser.add_argument(
        "--workdir",
        type=Path,
        default=None,
        help="where the bench writes its bags (default: the system temp directory)",
    )
    parser.add_argument("--force", action="store_true", help="replace existing output files")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    parser.set_defaults(func=tool.run)
