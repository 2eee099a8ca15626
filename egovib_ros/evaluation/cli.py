"""`egovib evaluate` and `egovib figures` (CONTRACT sections 3 and 6).

    egovib evaluate BAG --model MODEL.npz --json FILE [--calibration BAG]
    egovib figures --out DIR [--quick]

`evaluate_recording(rec, model, **opts) -> dict` is re-exported here for the demo.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from egovib_ros import cliutil
from egovib_ros.errors import BagError, ConfigError
from egovib_ros.evaluation import metrics
from egovib_ros.evaluation.evaluate import (  # noqa: F401 (API)
    bad_samples_said,
    evaluate_recording,
    require_ground_truth,
)
from egovib_ros.fileutil import atomic_output, prepare_output, prepare_outputs_in

__all__ = ["evaluate_recording", "register"]

# What `egovib figures` writes into its --out directory (figures.py, experiments.py).
FIGURE_OUTPUTS = (
    "eval_results.json",
    "eval_results.md",
    "eval_fig5_a.png",
    "eval_fig5_b.png",
    "eval_pr_curve.png",
    "eval_speed.png",
    "eval_fig3_spectra.png",
    "eval_fig4_superposition.png",
)


def _calibration_bag(args, model) -> Path | None:
    """--calibration, else the model's source bag if it still exists (no-contact sweep data)."""
    if args.calibration:
        return Path(args.calibration)
    source = model.provenance.get("source", "")
    if source and (Path(source) / "metadata.yaml").is_file():
        return Path(source)
    return None


def run_evaluate(args: argparse.Namespace) -> int:
    from egovib_ros.bagio import read_recording
    from egovib_ros.core import NoiseModel
    from egovib_ros.evaluation import baselines

    model = NoiseModel.load(args.model)
    calibration_path = _calibration_bag(args, model)
    # before any work
    prepare_output(
        args.json,
        force=args.force,
        kind="json",
        option="--json",
        inputs=[args.bag, args.model, calibration_path, args.model_short],
    )
    model_short = NoiseModel.load(args.model_short) if args.model_short else None
    methods = None
    if args.methods:
        methods = [m.strip() for m in args.methods.split(",") if m.strip()]
        unknown = [m for m in methods if m not in baselines.METHOD_LABELS]
        if unknown:
            raise ConfigError(
                f"--methods: unknown method(s) {unknown}; expected {list(baselines.METHOD_LABELS)}"
            )
    # The joints the model is keyed on, as denoise reads them: a bag without them is refused.
    rec = read_recording(args.bag, denoised=True, joint_names=model.joint_names)
    require_ground_truth(rec, where=str(args.bag))
    calibration = None
    if calibration_path is not None:
        calibration = read_recording(
            calibration_path, ground_truth=False, denoised=False, joint_names=model.joint_names
        )
    try:
        report = evaluate_recording(
            rec,
            model,
            calibration=calibration,
            model_short=model_short,
            methods=methods,
            source=str(args.bag),
            calibration_source=str(calibration_path),
            max_bad_fraction=args.max_bad_fraction,
        )
    except ValueError as exc:
        raise BagError(f"{args.bag}: {exc}") from None
    report = {
        "bag": str(args.bag),
        "model": str(args.model),
        "calibration_bag": str(calibration_path) if calibration_path else None,
        **report,
    }
    with atomic_output(args.json) as tmp:
        tmp.write_text(json.dumps(metrics.json_safe(report), indent=2) + "\n")
    if bad_samples_said(report["bad_samples"]):  # always said, even with --quiet
        print(f"{args.bag}: {bad_samples_said(report['bad_samples'])}", file=sys.stderr)
    if not args.quiet:
        print(
            f"{args.bag}: {report['n_taps']} taps, "
            f"noise reduction {report['noise_reduction_db']:.1f} dB, "
            f"peak SNR {report['peak_snr_raw_db']:.1f} -> {report['peak_snr_denoised_db']:.1f} dB, "
            f"retention {report['tap_retention']:.2f}, F1 raw {report['f1_raw']:.2f} -> "
            f"denoised {report['f1_denoised']:.2f}; wrote {args.json}"
        )
    return 0


def run_figures(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from egovib_ros.evaluation import experiments, figures

    out = prepare_outputs_in(args.out, FIGURE_OUTPUTS, force=args.force)  # before any work
    config = experiments.ExperimentConfig(seed=args.seed)
    if args.quick:
        config = config.quick()
    steps = 1 + len(config.speeds) + bool(config.robustness_effects) + 2
    with tqdm(total=steps, desc="figures", unit="step", disable=args.quiet) as bar:

        def progress(name: str) -> None:
            bar.set_postfix_str(name)
            bar.update()

        results = experiments.run_experiments(config, progress=progress, keep_signals=True)
        out.mkdir(parents=True, exist_ok=True)
        paths = figures.make_figures(results, out)
        progress("evaluation figures")
        paths += experiments.validation_figures(results, out)
        progress("Fig. 3 / Fig. 4 analogues")
        with atomic_output(out / "eval_results.json") as tmp:
            tmp.write_text(json.dumps(experiments.results_json(results), indent=2) + "\n")
        with atomic_output(out / "eval_results.md") as tmp:
            tmp.write_text(experiments.results_markdown(results))
    if not args.quiet:
        print(
            f"wrote {out / 'eval_results.md'}, {out / 'eval_results.json'} and "
            + ", ".join(str(p) for p in paths)
        )
    return 0


def register(subparsers) -> None:
    ev = subparsers.add_parser(
        "evaluate",
        help="paper metrics on a bag with ground truth (JSON)",
        description="Denoise BAG with MODEL by every method and write the paper's "
        "metrics (CONTRACT section 6) as JSON. Needs the ground-truth "
        "topic /accelerometer/contact. If BAG also holds "
        "/accelerometer/denoised (from `egovib denoise` or the live node), "
        "it is scored too, as method 'bag_denoised'.",
    )
    ev.add_argument(
        "bag",
        help="rosbag2 directory with /accelerometer/raw, /joint_states, /accelerometer/contact",
    )
    ev.add_argument("--model", required=True, help="noise model .npz")
    ev.add_argument("--json", required=True, metavar="FILE", help="output JSON")
    ev.add_argument(
        "--calibration",
        metavar="BAG",
        help="no-contact bag for detection thresholds (default: the model's source bag if present)",
    )
    ev.add_argument(
        "--model-short", metavar="MODEL", help="model with 32-sample blocks (adds method paper_L32)"
    )
    ev.add_argument("--methods", help="comma list of methods (default: all that can run)")
    ev.add_argument(
        "--max-bad-fraction",
        type=cliutil.fraction,
        default=metrics.MAX_BAD_FRACTION,
        metavar="FRACTION",
        help="refuse a recording with more bad (non-finite or out-of-range) samples "
        f"than this (default {metrics.MAX_BAD_FRACTION:g})",
    )
    ev.add_argument("--force", action="store_true", help="replace an existing JSON file")
    ev.add_argument("--quiet", action="store_true")
    ev.set_defaults(func=run_evaluate)

    fig = subparsers.add_parser(
        "figures",
        help="regenerate the evaluation table and all figures",
        description="Run the paper's experiments on the simulator (speeds 25-100 %%, "
        "all methods) and write eval_results.md/.json and eval_*.png.",
    )
    fig.add_argument("--out", default="docs", help="output directory (default: docs)")
    fig.add_argument("--seed", type=cliutil.seed, default=1)
    fig.add_argument("--quick", action="store_true", help="small run (for tests)")
    fig.add_argument(
        "--force", action="store_true", help="replace the files of a previous run in DIR"
    )
    fig.add_argument("--quiet", action="store_true")
    fig.set_defaults(func=run_figures)
