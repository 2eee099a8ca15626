"""`egovib simulate robot`: free motion or a velocity-grid sweep for any robot profile.

A subcommand of `egovib simulate` (registered by cli/simulate.py), so a user can try a profile
(calibrate, look at the model, denoise, detect) before touching hardware. The simulator is
egovib_ros.sim.robot; the bag is written slice by slice (constant memory) with the
profile's topics, plus the ground truth beside the sensor topic (`<parent>/contact`,
`<parent>/ego`).
"""

from __future__ import annotations

import argparse

from egovib_ros.cli import options
from egovib_ros.cli.simulate_output import (
    bag_output_options,
    prepare_outputs,
    progress_bar,
    seed_and_truth_options,
    write_bag,
)
from egovib_ros.errors import ConfigError
from egovib_ros.robot import load_profile
from egovib_ros.sim.robot import SENSOR_FRAME, robot_slices


def register(scenarios) -> None:
    """Add `robot` to the `simulate` subcommands."""
    robot = scenarios.add_parser(
        "robot",
        help="free motion or a grid sweep of any robot profile (generic N-joint simulator)",
        description="Simulate a robot described by a profile (INTERFACES.md section 1b): each "
        "joint's motor "
        "shakes the sensor with a line rising with its speed plus harmonics, over a sensor floor "
        "(gravity on z for linear_acceleration), stamps jittering around the nominal rate, "
        "optional taps. Writes a rosbag2 MCAP bag with the profile's sensor and joint topics "
        "and the ground truth (<sensor topic's parent>/contact and /ego).",
    )
    robot.add_argument(
        "--robot",
        required=True,
        metavar="PROFILE",
        help="robot profile (YAML path or shipped name)",
    )
    robot.add_argument(
        "--out", required=True, help="output bag directory (must not exist unless --force)"
    )
    robot.add_argument(
        "--mode",
        choices=("motion", "sweep"),
        default="motion",
        help="motion: smooth random free motion (default); sweep: dwell on the grid velocities",
    )
    robot.add_argument(
        "--duration",
        type=options.positive_float,
        default=None,
        metavar="SECONDS",
        help="length of a motion run (default 60; a sweep lasts cells x (settle + dwell))",
    )
    robot.add_argument(
        "--max-speed",
        type=options.positive_fraction,
        default=None,
        metavar="FRACTION",
        help="motion stays within this fraction of each joint's max speed (default 0.9)",
    )
    robot.add_argument(
        "--grid",
        choices=("full", "superposition"),
        default=None,
        help="sweep: every grid cell, or the cells with at most one joint moving (default)",
    )
    robot.add_argument(
        "--dwell",
        type=options.positive_float,
        default=None,
        metavar="SECONDS",
        help="sweep: recorded time per cell (default 2.0)",
    )
    robot.add_argument(
        "--settle",
        type=options.nonneg_float,
        default=None,
        metavar="SECONDS",
        help="sweep: ramp time from one cell to the next, before the dwell (default 0.5)",
    )
    robot.add_argument(
        "--taps",
        type=options.nonneg_float,
        default=0.0,
        metavar="RATE_HZ",
        help="mean tap rate (default 0: no taps)",
    )
    robot.add_argument(
        "--tap-mode",
        choices=("random", "periodic"),
        default="random",
        help="tap onsets: Poisson with a dead time, or evenly spaced",
    )
    robot.add_argument(
        "--joint-rate",
        type=options.positive_float,
        default=None,
        metavar="HZ",
        help="joint-state rate (default 1000, or the sensor rate if lower)",
    )
    seed_and_truth_options(robot)
    bag_output_options(robot)
    robot.set_defaults(func=run)


_MOTION_ONLY = (("duration", "--duration"), ("max_speed", "--max-speed"))
_SWEEP_ONLY = (("grid", "--grid"), ("dwell", "--dwell"), ("settle", "--settle"))


def run(args: argparse.Namespace) -> int:
    # Everything that can be refused is refused before the first sample is simulated.
    other = _SWEEP_ONLY if args.mode == "motion" else _MOTION_ONLY
    given = [option for name, option in other if getattr(args, name) is not None]
    if given:
        raise ConfigError(f"{', '.join(given)}: not an option of --mode {args.mode}")
    out = prepare_outputs(args, args.robot)
    profile = load_profile(args.robot)
    slices, truth, total = robot_slices(
        profile,
        mode=args.mode,
        duration_s=60.0 if args.duration is None else args.duration,
        max_speed=0.9 if args.max_speed is None else args.max_speed,
        grid=args.grid or "superposition",
        dwell_s=2.0 if args.dwell is None else args.dwell,
        settle_s=0.5 if args.settle is None else args.settle,
        tap_rate_hz=args.taps,
        tap_mode=args.tap_mode,
        seed=args.seed,
        joint_rate_hz=args.joint_rate,
        # the bar is made below, once the length of the run is known; it moves as the
        # slices are simulated, in write_bag
        progress=None if args.quiet else lambda seconds: update(seconds),
    )
    update, close = progress_bar(total, args.quiet)
    write_bag(args, out, slices, truth, close, profile=profile, frame_id=SENSOR_FRAME)
    if not args.quiet:
        print(
            f"wrote {out} ({profile.name}, {args.mode}, {total:.1f} s simulated, "
            f"{len(truth['tap_onsets_ns'])} taps)"
        )
    return 0
