"""`egovib detect BAG --model M --out EVENTS.json|.csv`: contact events in a recorded bag
(evaluation/contacts.py: the core's denoiser, then the contact detector)."""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
from pathlib import Path

from egovib_ros.cli.evaluate import calibration_bag
from egovib_ros.cli.options import (
    adapt_options,
    adapt_settings,
    float_in,
    force_and_quiet,
    nonneg_float,
)
from egovib_ros.core import NoiseModel
from egovib_ros.errors import ConfigError
from egovib_ros.evaluation.contacts import (
    DETECT_METHODS,
    check_detect_method,
    detect_bag,
    detection_threshold_needs_data,
)
from egovib_ros.outputs import atomic_output, json_holding, prepare_output, text_starting_with

SCHEMA = "egovib.events/1"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "detect",
        help="contact events (onset, peak per axis) in a bag, thresholds from no-contact data",
        description="Run the model's denoiser over BAG (its default output, as the denoiser "
        "node publishes it) and detect contact events on it (band-passed vector, 4 ms RMS "
        "envelope, 50 ms refractory time; each event reported 10 ms after it crosses the "
        "threshold, with its onset stamp and its peak vector), as the contact_detector node "
        "does and `egovib evaluate` scores. The threshold is fixed beforehand from no-contact "
        "data processed the same way: the one `egovib calibrate` stored in the model, or one "
        "from --calibration at a false-alarm budget, or given (--threshold). With the "
        "simulator's ground truth in BAG, the events are scored (F1, false alarms per minute, "
        "onset-to-report latency). --out: JSON (all of it) or CSV (one row per event).",
    )
    parser.add_argument("bag", metavar="BAG", help="rosbag2 bag with the model's topics")
    parser.add_argument("--model", required=True, metavar="MODEL.npz")
    parser.add_argument("--out", required=True, metavar="EVENTS.json|EVENTS.csv")
    parser.add_argument(
        "--method",
        choices=DETECT_METHODS,
        default=None,
        help="the denoiser before the detector (default: the model's, hybrid where it was "
        "calibrated for it; raw: none, the raw signal)",
    )
    parser.add_argument(
        "--calibration",
        metavar="BAG",
        default=None,
        help="no-contact bag to set the threshold from (default: the threshold stored in the "
        "model, else the bag the model was calibrated from)",
    )
    parser.add_argument(
        "--threshold",
        type=float_in(0.0, 1e9, low_open=True),
        default=None,
        help="the envelope threshold itself, in the sensor field's unit (no calibration data)",
    )
    parser.add_argument(
        "--false-alarms-per-min",
        type=nonneg_float,
        default=None,
        metavar="RATE",
        help="false-alarm budget on the no-contact data (default: the model's, 1 a minute; "
        "0: 1.1 x its largest envelope)",
    )
    parser.add_argument(
        "--joint-lag", type=float_in(-1.0, 1.0), default=0.0, metavar="SECONDS",
        help="joint lag: seconds the vibration trails the joint states (as egovib denoise)",
    )  # fmt: skip
    adapt_options(parser)
    force_and_quiet(parser, "replace an output egovib wrote")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    suffix = Path(args.out).suffix.lower()
    if suffix not in (".json", ".csv"):
        raise ConfigError(
            f"--out {args.out}: name it EVENTS.json (all of it) or EVENTS.csv (one row per event)"
        )
    kind = "file" if suffix == ".csv" else "json"
    prepare_output(
        args.out,
        force=args.force,
        inputs=[args.bag, args.model, args.calibration],
        kind=kind,
        ours=text_starting_with(",".join(CSV_HEADER))
        if kind == "file"
        else json_holding(schema=SCHEMA),
    )
    adapt = adapt_settings(args)
    model = NoiseModel.load(args.model)
    model.robot_profile()
    method = check_detect_method(model, args.method)
    calibration = None
    if args.threshold is None and (
        args.calibration is not None
        or detection_threshold_needs_data(model, method, args.false_alarms_per_min, args.joint_lag)
    ):
        calibration = calibration_bag(args.calibration, model, thresholds_from_run=False)
        if calibration is None:
            raise ConfigError(
                f"{args.model}: no threshold for {method} and no calibration bag stored in the "
                f"model; give --calibration BAG (no-contact data) or --threshold"
            )
    result = detect_bag(
        args.bag,
        model=model,
        method=method,
        threshold=args.threshold,
        calibration=calibration,
        false_alarms_per_min=args.false_alarms_per_min,
        joint_lag_s=args.joint_lag,
        adapt=adapt,
    )
    with atomic_output(args.out) as tmp:
        tmp.write_text(render_csv(result) if kind == "file" else render_json(result, args))
    default = " (the model's default)" if args.method is None else ""
    if adapt is not None:
        default += ", adapting"

    line = (
        f"{len(result.events)} events in {result.duration_s:.1f} s after {result.method}{default}, "
        f"threshold {result.threshold:.3g} ({result.threshold_source})"
    )
    beyond = result.counts.get("samples_beyond_calibration_motion", 0)
    if beyond:
        line += (
            f", raised on {beyond / max(result.counts['samples'], 1):.1%} of the samples "
            "(motion beyond the calibration's)"
        )
    if result.scores is not None:
        s = result.scores
        line += (
            f"; against the ground truth: F1 {s['f1']:.2f}, false alarms "
            f"{s['false_alarms_per_min']:.1f}/min, latency p50 {s['latency_ms_p50'] or 0:.1f} ms"
        )
    if not args.quiet:
        print(f"{line}; wrote {args.out}", file=sys.stderr)
    return 0


def render_json(result, args) -> str:
    body = {
        "schema": SCHEMA,
        "bag": str(args.bag),
        "model": str(args.model),
        "method": result.method,
        "method_delay_ms": result.method_delay_ms,
        "adapt": result.adapt,
        "threshold": result.threshold,
        "threshold_source": result.threshold_source,
        "false_alarm_budget_per_min": result.false_alarm_budget_per_min,
        "calibration_false_alarms_per_min": result.calibration_false_alarms_per_min,
        "duration_s": result.duration_s,
        "counts": result.counts,
        "scores": result.scores,
        "events": [
            {
                "onset_ns": e.onset_ns,
                "peak": list(e.peak),
                "strength": e.strength,
                "crossing_ns": e.crossing_ns,
                "report_ns": e.report_ns,
            }
            for e in result.events
        ],
    }
    return json.dumps(body, indent=1) + "\n"


CSV_HEADER = ["onset_ns", "peak_x", "peak_y", "peak_z", "strength", "report_ns"]


def render_csv(result) -> str:
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow(CSV_HEADER)
    for e in result.events:
        writer.writerow(
            [e.onset_ns, *(f"{v:.6g}" for v in e.peak), f"{e.strength:.6g}", e.report_ns]
        )
    return out.getvalue()
