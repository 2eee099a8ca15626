"""Write a recording of the alternate-reality hand to a bag (for `egovib gap` by hand).

    python -m egovib_research.altreality --duration 120 --effects position=1.5 --seed 3 \\
        --out bags/alt_position [--truth bags/alt_position.truth.json] [--compress]

The bag holds the PR2 topics (joint_states with its joints, accelerometer/raw), so a
noise model calibrated on our simulator reads it as a user's robot. Strength 1 of
position, coupling and acceleration makes the vibration ~3 dB louder where the effect
acts; drift is the relative level change of the warm-up step; timing in seconds (either
sign). Nothing about the effects is written into the bag; `--truth` writes them apart.
"""

from __future__ import annotations

import argparse
import json
import sys

from egovib_research.altreality.hand import EFFECTS, simulate_alt_motion
from egovib_ros.bag import write_recording
from egovib_ros.cli import options
from egovib_ros.errors import EgovibError
from egovib_ros.outputs import TRUTH_KEYS, atomic_output, json_holding, prepare_output

# This generator's own strengths (not the simulator's ranges): a gain above the base
# vibration for position, coupling, acceleration and drift; seconds of either sign for timing.
STRENGTH_RANGES = {name: (0.0, 10.0) for name in EFFECTS} | {"timing": (-1.0, 1.0)}


def _effects(text: str) -> dict[str, float]:
    effects = {}
    for item in filter(None, (p.strip() for p in text.split(","))):
        name, _, value = item.partition("=")
        if name not in EFFECTS:
            raise argparse.ArgumentTypeError(f"unknown effect {name!r}; expected one of {EFFECTS}")
        try:
            effects[name] = float(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{item!r}: expected name=number") from None
    for name, value in effects.items():
        low, high = STRENGTH_RANGES[name]
        if not low <= value <= high:  # also refuses nan and inf
            raise argparse.ArgumentTypeError(f"{name}={value:g} is outside [{low:g}, {high:g}]")
    return effects


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m egovib_research.altreality",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--duration", type=options.float_in(10.0, 3600.0), default=120.0)
    parser.add_argument("--effects", type=_effects, default={}, metavar="SPEC")
    parser.add_argument("--seed", type=options.seed, default=0)
    parser.add_argument("--taps", type=options.float_in(0.0, 5.0), default=0.5, help="taps/s")
    parser.add_argument("--out", required=True, help="output bag directory")
    parser.add_argument("--truth", help="write {seed, effects, tap onsets, details} here")
    parser.add_argument("--compress", action="store_true", help="zstd chunk compression")
    parser.add_argument("--force", action="store_true")
    args = parser.parse_args(argv)
    try:
        out = prepare_output(args.out, force=args.force, kind="bag")
        if args.truth:
            prepare_output(
                args.truth,
                force=args.force,
                kind="json",
                option="--truth",
                ours=json_holding(TRUTH_KEYS),
            )
        rec, truth = simulate_alt_motion(
            duration_s=args.duration, effects=args.effects, seed=args.seed, tap_rate_hz=args.taps
        )
        with atomic_output(out, directory=True, kind="bag") as tmp:
            write_recording(tmp, rec, compress=args.compress)
        if args.truth:
            with atomic_output(args.truth) as tmp:
                tmp.write_text(json.dumps(truth, default=str) + "\n")
    except EgovibError as exc:
        print(f"egovib: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out} ({args.duration:g} s of the alternate-reality hand)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
