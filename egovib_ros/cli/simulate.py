"""`egovib simulate sweep|motion` (the PR2 hand: egovib_ros.sim.scenarios) and `simulate
robot` (free motion or a grid sweep of any robot profile: egovib_ros.sim.robot, so a user
can try a profile before touching hardware). Every scenario refuses its outputs before any
work, writes the bag slice by slice (constant memory) with the profile's topics plus the
ground truth beside the sensor topic (`<parent>/contact`, `<parent>/ego`), then --truth."""

from __future__ import annotations

import argparse
import functools
import json
from pathlib import Path

from tqdm import tqdm

from egovib_ros.bag import write_recordings
from egovib_ros.cli import options
from egovib_ros.errors import ConfigError
from egovib_ros.outputs import TRUTH_KEYS, atomic_output, json_holding, prepare_output
from egovib_ros.robot import load_profile
from egovib_ros.sim.params import SimParams
from egovib_ros.sim.pr2 import ACCEL_FRAME
from egovib_ros.sim.robot import SENSOR_FRAME, robot_slices
from egovib_ros.sim.scenarios import motion_slices, sweep_cells, sweep_slices


def _options(p: argparse.ArgumentParser, *, robot: bool, taps: dict) -> None:
    """What every scenario takes: --out, --taps (`taps`: its default or required), --tap-mode,
    --seed, --truth and how the bag is written; the PR2 hand's scenarios also --effects and
    --params."""
    p.add_argument(
        "--out", required=True, help="output bag directory (must not exist unless --force)"
    )
    p.add_argument("--taps", type=options.nonneg_float, metavar="RATE_HZ", **taps)
    p.add_argument(
        "--tap-mode",
        choices=("random", "periodic"),
        default="random",
        help="tap onsets: Poisson with a dead time, or evenly spaced",
    )
    if not robot:
        p.add_argument(
            "--effects",
            default={},
            type=options.effects_spec,
            metavar="SPEC",
            help="comma list name=strength over position, coupling, acceleration, timing, "
            "drift (e.g. position=0.5,timing=0.03); never written into the bag",
        )
        p.add_argument(
            "--params", metavar="YAML", help="simulator parameters (default config/sim.yaml)"
        )
    p.add_argument("--seed", type=options.seed, default=0, help=f"0 .. {options.MAX_SEED}")
    p.add_argument(
        "--truth",
        metavar="FILE",
        help="write {seed, effects, tap_onsets_ns} to this JSON file "
        "(must not exist unless --force)",
    )
    p.add_argument("--storage", choices=("mcap", "sqlite3"), default="mcap")
    p.add_argument("--compress", action="store_true", help="zstd chunk compression (MCAP)")
    options.force_and_quiet(p, "replace an existing output bag / truth file written by egovib")


def _sweep_options(p: argparse.ArgumentParser, *, robot: bool) -> None:
    """--grid, --dwell, --settle (the robot's: optional, defaults in `run_robot`)."""
    p.add_argument(
        "--grid",
        choices=("full", "superposition"),
        default=None if robot else "superposition",
        help="full: every grid cell (441 on the PR2); superposition (default): the cells with "
        "at most one joint moving",
    )
    p.add_argument(
        "--dwell",
        type=options.positive_float,
        metavar="SECONDS",
        help="recorded time per cell" + (" (default 2.0)" if robot else ""),
        **({"default": None} if robot else {"required": True}),
    )
    p.add_argument(
        "--settle",
        type=options.nonneg_float,
        default=None if robot else 1.0,
        metavar="SECONDS",
        help=f"time per cell to reach it before the dwell (default {0.5 if robot else 1.0})",
    )


def _motion_options(p: argparse.ArgumentParser, *, robot: bool) -> None:
    """--duration, --max-speed (the robot's: optional, defaults in `run_robot`)."""
    given = {"default": None} if robot else {"required": True}
    p.add_argument(
        "--duration",
        type=options.positive_float,
        metavar="SECONDS",
        help="length of a motion run" + (" (default 60)" if robot else ""),
        **given,
    )
    p.add_argument(
        "--max-speed",
        type=options.positive_fraction,
        metavar="FRACTION",
        help="commands stay within this fraction of each joint's max speed"
        + (" (default 0.9)" if robot else ""),
        **given,
    )


def register(subparsers) -> None:
    """Add `simulate` with its `sweep`, `motion` and `robot` subcommands."""
    sim = subparsers.add_parser(
        "simulate",
        help="simulate the PR2 hand or any robot profile and write a rosbag2 (MCAP) bag",
        description="Simulate the PR2 right hand (wrist roll + gripper) with its "
        "accelerometer (sweep, motion), or any robot profile (robot), and write a rosbag2 "
        "MCAP bag with the contract's topics, including the ground-truth contact/ego topics.",
    )
    scen = sim.add_subparsers(dest="scenario", required=True, metavar="SCENARIO")

    sweep = scen.add_parser("sweep", help="velocity-grid sweep for calibration (paper section 3)")
    _sweep_options(sweep, robot=False)
    _options(sweep, robot=False, taps={"default": 0.0, "help": "tap rate (default 0)"})
    sweep.set_defaults(func=run)

    motion = scen.add_parser("motion", help="random smooth motion with taps (paper section 4)")
    _motion_options(motion, robot=False)
    _options(motion, robot=False, taps={"required": True, "help": "mean tap rate"})
    motion.set_defaults(func=run)

    robot = scen.add_parser(
        "robot",
        help="free motion or a grid sweep of any robot profile (generic N-joint simulator)",
        description="Simulate a robot described by a profile (INTERFACES.md section 1b): each "
        "joint's motor shakes the sensor with a line rising with its speed plus harmonics, "
        "over a sensor floor (gravity on z for linear_acceleration), stamps jittering around "
        "the nominal rate, optional taps. Writes a rosbag2 MCAP bag with the profile's sensor "
        "and joint topics and the ground truth (<sensor topic's parent>/contact and /ego).",
    )
    robot.add_argument(
        "--robot",
        required=True,
        metavar="PROFILE",
        help="robot profile (YAML path or shipped name)",
    )
    robot.add_argument(
        "--mode",
        choices=("motion", "sweep"),
        default="motion",
        help="motion: smooth random free motion (default); sweep: dwell on the grid velocities",
    )
    _motion_options(robot, robot=True)
    _sweep_options(robot, robot=True)
    robot.add_argument(
        "--joint-rate",
        type=options.positive_float,
        default=None,
        metavar="HZ",
        help="joint-state rate (default 1000, or the sensor rate if lower)",
    )
    _options(robot, robot=True, taps={"default": 0.0, "help": "mean tap rate (default 0)"})
    robot.set_defaults(func=run_robot)


def run(args: argparse.Namespace) -> int:
    # Everything that can be refused is refused before the first sample is simulated.
    out = _prepare_outputs(args, args.params)
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
    update, close = _progress_bar(total, args.quiet)
    slices, truth = scenario(
        effects=effects,
        seed=args.seed,
        params=params,
        tap_rate_hz=args.taps,
        tap_mode=args.tap_mode,
        progress=update,
    )
    _write_bag(args, out, slices, truth, close, frame_id=ACCEL_FRAME)
    if not args.quiet:
        print(f"wrote {out} ({total:.1f} s simulated, {len(truth['tap_onsets_ns'])} taps)")
    return 0


_MOTION_ONLY = (("duration", "--duration"), ("max_speed", "--max-speed"))
_SWEEP_ONLY = (("grid", "--grid"), ("dwell", "--dwell"), ("settle", "--settle"))


def run_robot(args: argparse.Namespace) -> int:
    other = _SWEEP_ONLY if args.mode == "motion" else _MOTION_ONLY
    given = [option for name, option in other if getattr(args, name) is not None]
    if given:
        raise ConfigError(f"{', '.join(given)}: not an option of --mode {args.mode}")
    out = _prepare_outputs(args, args.robot)
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
        # slices are simulated, in _write_bag
        progress=None if args.quiet else lambda seconds: update(seconds),
    )
    update, close = _progress_bar(total, args.quiet)
    _write_bag(args, out, slices, truth, close, profile=profile, frame_id=SENSOR_FRAME)
    if not args.quiet:
        print(
            f"wrote {out} ({profile.name}, {args.mode}, {total:.1f} s simulated, "
            f"{len(truth['tap_onsets_ns'])} taps)"
        )
    return 0


def _progress_bar(total: float, quiet: bool):
    """(update, close) of the progress bar of a run of `total` simulated seconds."""
    if quiet:
        return None, lambda: None
    bar = tqdm(total=round(total, 1), unit="sim-s", desc="simulate", leave=False)
    return (lambda s: bar.update(s)), bar.close


def _prepare_outputs(args: argparse.Namespace, source) -> Path:
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


def _write_bag(args: argparse.Namespace, out: Path, slices, truth: dict, close, **options) -> None:
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
