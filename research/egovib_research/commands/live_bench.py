"""`egovib live-bench`: does the denoiser node keep up live (tools/live_bench.py)."""

from __future__ import annotations

from egovib_research.tools import live_bench as tool
from egovib_ros.core.methods import METHODS


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "live-bench",
        help="does the denoiser node keep up live (drops, CPU, latency)",
        description=tool.__doc__.split("\n\n")[0],
    )
    parser.add_argument("--json", required=True, help="output JSON file")
    parser.add_argument(
        "--seconds", type=float, default=60.0, help="length of the measured run (s, default 60)"
    )
    parser.add_argument(
        "--warmup", type=float, default=5.0, help="left out of the figures at the start (s)"
    )
    parser.add_argument("--model", help="noise model (default: a quick offline calibration)")
    parser.add_argument(
        "--channels",
        choices=("per_axis", "combined"),
        default="per_axis",
        help="the denoiser's channels: each axis cleaned, or the paper's 1-D sum",
    )
    parser.add_argument(
        "--method",
        choices=METHODS,
        default=None,
        help="the denoiser's method (default: the model's, hybrid; the bench's own model is "
        "calibrated for every method)",
    )
    parser.add_argument(
        "--adapt",
        action="store_true",
        help="the denoiser learns its model online (adapt:=true; cancel and hybrid)",
    )
    parser.add_argument(
        "--publish-period",
        type=float,
        default=0.002,
        help="sim_hand's batching period (s): part of the measured latency",
    )
    parser.add_argument(
        "--contacts",
        action="store_true",
        help="also run contact_detector on the denoised and on the raw stream, sim_hand "
        "tapping: event F1 and onset-to-event-message latency",
    )
    parser.add_argument("--tap-rate", type=float, default=1.0, help="taps per second (--contacts)")
    parser.add_argument(
        "--calibration-seconds",
        type=float,
        default=30.0,
        help="no-contact motion simulated for the detectors' thresholds (--contacts)",
    )
    parser.set_defaults(func=tool.run)
