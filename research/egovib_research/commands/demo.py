"""`egovib demo` (= `make demo`): the whole pipeline live on ROS 2 nodes (tools/demo.py)."""

from __future__ import annotations

from egovib_research.tools import demo as tool


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "demo",
        help="the whole pipeline live on ROS 2 nodes (make demo)",
        description=tool.__doc__.split("\n\n")[0],
    )
    parser.add_argument(
        "--out", default="demo_output", help="directory for the model, bag, logs, figures"
    )
    parser.add_argument("--dwell", type=float, default=1.0, help="sweep dwell per cell (s)")
    parser.add_argument("--settle", type=float, default=0.3, help="sweep settle time per cell (s)")
    parser.add_argument(
        "--seconds", type=float, default=30.0, help="length of the recorded run (s)"
    )
    parser.add_argument("--max-speed", type=float, default=0.5, help="fraction of max joint speed")
    parser.add_argument("--taps", type=float, default=2.0, help="tap rate (Hz)")
    parser.add_argument(
        "--seed", type=int, default=7, help="seed of the simulated hand (taps, noise; default 7)"
    )
    parser.set_defaults(func=tool.run)
