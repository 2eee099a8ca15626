"""What several commands share: options for many bags, outputs per bag, the summary."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Sequence

from egovib_ros.bag.many import BagJob, expand_bags, raise_if_bugs, summary_lines
from egovib_ros.cli.options import int_in
from egovib_ros.errors import BagError, ConfigError


def parallel_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--jobs",
        type=int_in(1, 4096),
        default=1,
        metavar="N",
        help="bags processed at once (N > 1: a local Dask cluster of N worker processes)",
    )
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help="run on an existing Dask cluster (e.g. tcp://host:8786) instead of a local one",
    )


def output_jobs(
    specs: Sequence[str], out: str | os.PathLike, *, suffix: str = "", option: str = "--out"
) -> list[BagJob]:
    """One input bag -> `out` is its output; several (or a directory) -> `out` is a
    directory holding one output per input, under the input's relative name + `suffix`."""
    pairs = expand_bags(specs)
    target = Path(out).resolve()
    for spec in specs:  # a later run over the same input would take the outputs for inputs
        if target.is_relative_to(Path(spec).resolve()):
            raise ConfigError(f"{out}: {option} is inside the input {spec}; write it elsewhere")
    single = len(specs) == 1 and len(pairs) == 1 and Path(specs[0]) == pairs[0][0]
    if single:
        return [BagJob(pairs[0][0], Path(out))]
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: with several input bags {option} must be a directory")
    return [BagJob(bag, out / f"{name}{suffix}") for bag, name in pairs]


def report_results(results, describe, *, single: bool, quiet: bool = False, said=None) -> int:
    """Single bag: its line, or its one-line error (exit 2). Several: the summary. `quiet`
    (--quiet): only what `said(value)` gives (the counts of bad input, if any) and the
    failures with the totals."""
    if single:
        r = results[0]
        if not r.ok:
            raise BagError(r.error.splitlines()[0]) if r.error else BagError(f"{r.bag}: failed")
        if not quiet:
            print(describe(r.value), file=sys.stderr)
            print(f"wrote {r.out}", file=sys.stderr)
        elif said is not None and said(r.value):
            print(f"{r.bag}: {said(r.value)}", file=sys.stderr)
        return 0
    lines = summary_lines(results, describe)
    if quiet:
        lines = [f"  {r.bag}: {said(r.value)}" for r in results if r.ok and said and said(r.value)]
        if not all(r.ok for r in results):
            lines += [f"  FAILED {r.error}" for r in results if not r.ok]
            lines.append(summary_lines(results, describe)[-1])
    for line in lines:
        print(line, file=sys.stderr)
    raise_if_bugs(results)  # a bag failed on a bug: an internal error (exit 1), not bad input
    return 0 if all(r.ok for r in results) else 2
