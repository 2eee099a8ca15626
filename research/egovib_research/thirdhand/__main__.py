"""`python -m egovib_research.thirdhand --duration 120 --effects coupling=1.5
--forms coupling=together --seed 3 --out BAG [--truth FILE]`: a bag of the third hand
(the PR2 profile's topics, ground truth beside the sensor topic)."""

from __future__ import annotations

import argparse
import json
import sys

from egovib_research.thirdhand import FORMS, simulate_third_motion
from egovib_ros.bag.recording import write_recording
from egovib_ros.errors import ConfigError


def _pairs(text: str, what: str) -> dict[str, str]:
    out = {}
    for item in filter(None, (p.strip() for p in (text or "").split(","))):
        name, sep, value = item.partition("=")
        if not sep or name not in FORMS:
            raise ConfigError(
                f"--{what}: expected NAME=VALUE with NAME in {sorted(FORMS)}, got {item!r}"
            )
        out[name] = value
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m egovib_research.thirdhand")
    parser.add_argument("--duration", type=float, default=120.0, help="seconds")
    parser.add_argument("--effects", default="", help="NAME=STRENGTH,... (CONTRACT section 5)")
    parser.add_argument("--forms", default="", help="NAME=FORM,... (hand.py's table)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--taps", type=float, default=0.5, help="contacts per second")
    parser.add_argument("--out", required=True, help="bag directory to write")
    parser.add_argument("--truth", help="JSON file for the effects, forms and tap onsets")
    args = parser.parse_args(argv)
    try:
        effects = {k: float(v) for k, v in _pairs(args.effects, "effects").items()}
        rec, truth = simulate_third_motion(
            duration_s=args.duration,
            effects=effects,
            forms=_pairs(args.forms, "forms"),
            seed=args.seed,
            tap_rate_hz=args.taps,
        )
    except (ConfigError, ValueError) as exc:
        print(f"thirdhand: {exc}", file=sys.stderr)
        return 2
    write_recording(args.out, rec, frame_id="r_gripper_motor_accelerometer_link")
    if args.truth:
        with open(args.truth, "w") as fh:
            json.dump(truth, fh)
    print(
        f"wrote {args.out}: {args.duration:g} s, effects {truth['effects']}, forms {truth['forms']}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
