"""`egovib simulate sweep|motion` (the PR2 hand) and `simulate robot` (any profile:
cli/simulate_robot.py)."""

from __future__ import annotations

import argparse
import functools

from egovib_ros.cli import options, simulate_robot
from egovib_ros.cli.simulate_output import (
    bag_output_options,
    prepare_outputs,
    progress_bar,
    seed_and_truth_options,
    write_bag,
)
from egovib_ros.errors import ConfigError
from egovib_ros.sim.params import SimParams
from egovib_ros.sim.pr2 import ACCEL_FRAME
from egovib_ros.sim.scenarios import motion_slices, sweep_cells, sweep_slices


def register(subparsers) -> None:
    """Add `simulate` with its `sweep` and `motion` subcommands."""
    sim = subparsers.add_parser(
        "simulate",
        help="simulate the PR2 hand or any robot profile and write a rosbag2 (MCAP) bag",
        description="Simulate the PR2 right hand (wrist roll + gripper) with its "
        "accelerometer (sweep, motion), or any robot profile (robot), and write a rosbag2 "
        "MCAP bag with the contract's topics, including the ground-truth contact/ego topics.",
    )
    scen = sim.add_subparsers(dest="scenario", required=True, metavar="SCENARIO")

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument(
            "--out", required=True, help="output bag directory (must not exist unless --force)"
        )
        p.add_argument(
            "--effects",
            default={},
            type=options.effects_spec,
            metavar="SPEC",
            help="comma list name=strength over position, coupling, acceleration, timing, drift "
            "(e.g. position=0.5,timing=0.03); never written into the bag",
        )
        seed_and_truth_options(p)
        p.add_argument(
            "--params", metavar="YAML", help="simulator parameters (default config/sim.yaml)"
        )
        p.add_argument(
            "--tap-mode",
            choices=("random", "periodic"),
            default="random",
            help="tap onsets: Poisson with dead time, or evenly spaced",
        )
        bag_output_options(p)

    sweep = scen.add_parser("sweep", help="velocity-grid sweep for calibration (paper section 3)")
    sweep.add_argument(
        "--grid",
        choices=("full", "superposition"),
        default="superposition",
        help="full: 441 cells; superposition: the 41 cells with at most one joint moving",
    )
    sweep.add_argument(
        "--dwell",
        type=options.positive_float,
        required=True,
        metavar="SECONDS",
        help="recorded time per cell",
    )
    sweep.add_argument(
        "--settle",
        type=options.nonneg_float,
        default=1.0,
        metavar="SECONDS",
        help="time per cell for the controller to settle before the dwell (default 1.0)",
    )
    sweep.add_argument(
        "--taps",
        type=options.nonneg_float,
        default=0.0,
        metavar="RATE_HZ",
        help="tap rate (default 0)",
    )
    common(sweep)
    sweep.set_defaults(func=run)

    motion = scen.add_parser("motion", help="random smooth motion with taps (paper section 4)")
    motion.add_argument("--duration", type=options.positive_float, required=True, metavar="SECONDS")
    motion.add_argument(
        "--max-speed",
        type=options.positive_fraction,
        required=True,
        metavar="FRACTION",
        help="commands stay within this fraction of each joint's max speed",
    )
    motion.add_argument(
        "--taps", type=options.nonneg_float, required=True, metavar="RATE_HZ", help="mean tap rate"
    )
    common(motion)
    motion.set_defaults(func=run)

    simulate_robot.register(scen)


def run(args: argparse.Namespace) -> int:
    # Everything that can be refused is refused before the first sample is simulated.
    out = prepare_outputs(args, args.params)
    effects = args.effects
    if effects.get("timing", 0.0) < 0:
        # The simulated clock starts at 0: leading joint stamps would be negative.
        raise ConfigError(
            f"--effects: timing={effects['timing']:g} s: joint states leading the "
            f"accelerometer (timing < 0) is not supported by simulate; "
            f"use timing >= 0"
        )
    params = SimParams.load(args.params)
    if args.scenario == "sweep":
        total = len(sweep_cells(args.grid)) * (args.dwell + args.settle)
        scenario = functools.partial(
            sweep_slices, grid=args.grid, dwell_s=args.dwell, settle_s=args.settle
        )
    else:
        total = args.duration
        scenario = functools.partial(
            motion_slices, duration_s=args.duration, max_speed=args.max_speed
        )
    update, close = progress_bar(total, args.quiet)
    slices, truth = scenario(
        effects=effects,
        seed=args.seed,
        params=params,
        tap_rate_hz=args.taps,
        tap_mode=args.tap_mode,
        progress=update,
    )
    write_bag(args, out, slices, truth, close, frame_id=ACCEL_FRAME)
    if not args.quiet:
        print(f"wrote {out} ({total:.1f} s simulated, {len(truth['tap_onsets_ns'])} taps)")
    return 0
