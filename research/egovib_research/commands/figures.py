"""`egovib figures --out DIR [--quick]`: the paper's experiments on the simulator, their
table and every figure (experiments/paper.py, experiments/paper_figures.py)."""

from __future__ import annotations

import argparse
import json

from tqdm import tqdm

from egovib_research.experiments import paper as experiments
from egovib_research.experiments import paper_figures as figures
from egovib_ros.cli import options
from egovib_ros.outputs import atomic_output, prepare_outputs_in

#: What `egovib figures` writes into its --out directory.
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


def run_figures(args: argparse.Namespace) -> int:
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
    fig = subparsers.add_parser(
        "figures",
        help="regenerate the evaluation table and all figures",
        description="Run the paper's experiments on the simulator (speeds 25-100 %, "
        "all methods) and write eval_results.md/.json and eval_*.png.",
    )
    fig.add_argument("--out", default="docs", help="output directory (default: docs)")
    fig.add_argument("--seed", type=options.seed, default=1)
    fig.add_argument("--quick", action="store_true", help="small run (for tests)")
    options.force_and_quiet(fig, "replace the files of a previous run in DIR")
    fig.set_defaults(func=run_figures)
