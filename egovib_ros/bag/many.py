"""Many bags at once: expand arguments to bags, run one task per bag, one progress bar,
one summary; a failing bag is reported by name and never stops or spoils the others.

Parallel runs go through Dask (`dask.distributed`): a LocalCluster of `jobs` worker
processes, or an existing cluster at a scheduler address (its workers must see the bags and
outputs under the same paths). The task is the function the one-process path calls, on the
same arguments: the same results. With `jobs=1` and no scheduler the bags are processed one
after the other in this process.

A task is a picklable `task(bag: Path, out: Path | None, progress)` returning a small
picklable summary; `progress(n_bytes)` may be called as the bag is read.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

from tqdm import tqdm

from egovib_ros.errors import BagError, ConfigError, EgovibError
from egovib_ros.outputs import clean_partials_of


@dataclass
class BagResult:
    bag: str
    ok: bool
    value: Any = None
    error: str = ""
    seconds: float = 0.0
    out: str | None = None
    internal: bool = False  # not bad input but an unexpected exception (a bug?)
    traceback: str = ""  # of that exception


class BagTaskBug(Exception):
    """Some bags of a run failed on an unexpected exception (a bug): the CLI reports it as
    an internal error (exit status 1) with their tracebacks (`details`) in its log."""

    def __init__(self, results: Sequence[BagResult]):
        bugs = [r for r in results if r.internal]
        super().__init__(
            f"{len(bugs)} of {len(results)} bag(s) failed on an unexpected exception "
            f"(first: {bugs[0].error})"
        )
        self.details = "\n".join(f"--- {r.bag}\n{r.traceback}" for r in bugs)


def raise_if_bugs(results: Sequence[BagResult]) -> None:
    """After the summary of a run over several bags: BagTaskBug if any failed on a bug."""
    if any(r.internal for r in results):
        raise BagTaskBug(results)


@dataclass
class BagJob:
    bag: Path
    out: Path | None = None
    size: int = 0


def is_bare_mcap(path: Path) -> bool:
    """A bag's .mcap file given alone, without its directory (BagReader reads it)."""
    path = Path(path)
    return path.suffix == ".mcap" and path.is_file()


def is_bag(path: Path) -> bool:
    """A rosbag2 bag directory, or a bare .mcap file (BagReader reads both)."""
    return (Path(path) / "metadata.yaml").is_file() or is_bare_mcap(path)


def expand_bags(
    specs: Sequence[str | os.PathLike], *, outputs_per_bag: bool = True
) -> list[tuple[Path, Path]]:
    """(bag, name) pairs from bag directories and directories of bags (searched
    recursively, sorted; hidden and `.partial` directories skipped). `name`, the bag's path
    relative to the directory it was found in, is where its output goes: two bags of one
    name are refused when `outputs_per_bag` (not for calibration's one model). A path that
    does not exist is kept: its task reports it like any other bad bag."""
    found: list[tuple[Path, Path]] = []
    for spec in specs:
        path = Path(spec)
        if path.is_dir() and not is_bag(path):
            bags = sorted(
                p.parent
                for p in path.rglob("metadata.yaml")
                if not any(
                    part.startswith(".") or part.endswith(".partial")
                    for part in p.parent.relative_to(path).parts
                )
            )
            # no bags inside bags
            bags = [b for b in bags if not any(b != o and o in b.parents for o in bags)]
            if not bags:
                files = sorted(p.name for p in path.glob("*.mcap"))
                hint = f" (give its MCAP file itself: {path / files[0]})" if files else ""
                raise BagError(
                    f"{path}: no rosbag2 bags (directories with metadata.yaml) in this "
                    f"directory{hint}"
                )
            found += [(b, b.relative_to(path)) for b in bags]
        else:
            found.append((path, Path(path.name)))
    names = [str(n) for _, n in found]
    resolved = [str(b.resolve()) for b, _ in found]
    twice = sorted({str(b) for (b, _), r in zip(found, resolved) if resolved.count(r) > 1})
    if twice:  # e.g. a directory and a bag inside it: its data would count twice
        raise ConfigError(
            f"{twice[0]}: the same bag is given twice (directly or inside a directory)"
        )
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates and outputs_per_bag:
        raise ConfigError(
            f"several input bags are named {duplicates[0]!r}; their outputs would collide "
            f"(give them in separate runs or directories)"
        )
    return found


def bag_size(path: Path) -> int:
    try:
        return sum(f.stat().st_size for f in path.iterdir() if f.is_file())
    except OSError:
        return 0


def run_guarded(
    task: Callable,
    job: BagJob,
    progress: Callable[[int], None] | None = None,
    *,
    reraise: bool = False,
) -> BagResult:
    """Run `task` on one bag; any failure becomes a BagResult naming the bag (bad input:
    its one-line message; anything else: the exception, with the traceback logged)."""
    start = time.perf_counter()
    result = BagResult(str(job.bag), False)
    try:
        result.value = task(job.bag, job.out, progress)
        result.ok, result.out = True, None if job.out is None else str(job.out)
    except EgovibError as exc:
        message = str(exc)
        result.error = message if str(job.bag) in message else f"{job.bag}: {message}"
    except Exception as exc:  # a bug or an unexpected file: report it, keep going with the others
        if reraise:
            raise
        result.traceback = traceback.format_exc()
        logging.getLogger("egovib_ros.bag").debug("%s", result.traceback)
        first = (str(exc).strip().splitlines() or [""])[0]
        result.error, result.internal = f"{job.bag}: {type(exc).__name__}: {first}", True
    result.seconds = time.perf_counter() - start
    return result


def run_bags(
    task: Callable,
    jobs_list: Sequence[BagJob],
    *,
    jobs: int = 1,
    scheduler: str | None = None,
    desc: str = "bags",
    quiet: bool = False,
) -> list[BagResult]:
    """Run `task` on every bag; results in the order of `jobs_list`."""
    if jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {jobs}")
    for job in jobs_list:
        job.size = job.size or bag_size(job.bag)
    total = sum(j.size for j in jobs_list)
    bar = tqdm(
        total=total,
        unit="B",
        unit_scale=True,
        desc=desc,
        disable=quiet or None,
        file=sys.stderr,
        dynamic_ncols=True,
    )
    results: list[BagResult | None] = [None] * len(jobs_list)
    try:
        if jobs == 1 and scheduler is None:
            for i, job in enumerate(jobs_list):
                read = [0]

                def progress(n: int, read=read, job=job) -> None:
                    step = min(n, job.size - read[0])
                    read[0] += step
                    bar.update(step)

                # a single bag in this process: let an unexpected exception show its traceback
                results[i] = run_guarded(task, job, progress, reraise=len(jobs_list) == 1)
                bar.update(job.size - read[0])
        else:
            results = _run_dask(task, jobs_list, jobs=jobs, scheduler=scheduler, bar=bar)
    finally:
        bar.close()
    return results


def _run_dask(
    task: Callable, jobs_list: Sequence[BagJob], *, jobs: int, scheduler: str | None, bar
) -> list[BagResult]:
    try:  # deferred: an optional extra (egovib_ros[cluster]), and seconds to import
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise ConfigError(
            "parallel runs need dask.distributed (pip install 'egovib_ros[cluster]', or apt "
            "python3-distributed)"
        ) from None
    cluster, workers = None, set()
    quiet_loggers = {
        name: logging.getLogger(name).level for name in ("distributed", "dask", "tornado", "bokeh")
    }
    for name in quiet_loggers:  # Dask reports at INFO level; our summary is the report
        logging.getLogger(name).setLevel(logging.ERROR)
    try:
        if scheduler:
            try:
                client = Client(scheduler, timeout="10s")
            except Exception as exc:
                raise ConfigError(
                    f"--scheduler {scheduler}: cannot connect ({type(exc).__name__}: {exc})"
                ) from None
        else:
            with _sigint_blocked():  # the workers never see Ctrl-C: this process handles it
                cluster = LocalCluster(
                    n_workers=jobs,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                    scheduler_kwargs={"dashboard": False},
                    # the workers' own logs: a stopped run's last heartbeats fail with an
                    # ERROR and a traceback; what fails in a task comes back as its result
                    silence_logs=logging.CRITICAL,
                )
            client = Client(cluster)
            workers = set(client.run(os.getpid).values())
        with client:
            futures = client.map(run_guarded, [task] * len(jobs_list), list(jobs_list), pure=False)
            index = {f.key: i for i, f in enumerate(futures)}
            results: list[BagResult | None] = [None] * len(jobs_list)
            for future in as_completed(futures):
                i = index[future.key]
                try:
                    results[i] = future.result()
                except Exception as exc:  # the worker died (memory, signal): only this bag fails
                    results[i] = BagResult(
                        str(jobs_list[i].bag),
                        False,
                        error=f"{jobs_list[i].bag}: worker failed ({type(exc).__name__}: {exc})",
                    )
                bar.update(jobs_list[i].size)
            return results
    finally:
        if cluster is not None:
            stopping = sys.exc_info()[0] is not None  # Ctrl-C, SIGTERM, an error: say nothing
            if stopping:
                logging.getLogger("distributed").setLevel(logging.CRITICAL + 1)
            cluster.close()
            if stopping:  # the staging of the bags its workers were writing when stopped
                for directory in {Path(j.out).parent for j in jobs_list if j.out is not None}:
                    clean_partials_of(directory, workers)
        for name, level in quiet_loggers.items():
            logging.getLogger(name).setLevel(level)


@contextlib.contextmanager
def _sigint_blocked():
    """While Dask starts its worker processes, SIGINT is ignored (the workers inherit that
    across exec: a Ctrl-C at the terminal reaches only this process, which stops the run,
    instead of making each worker print a traceback) and blocked in this thread (kept
    pending, not discarded: a Ctrl-C meanwhile is delivered once our handler is back)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def summary_lines(results: Sequence[BagResult], describe: Callable[[Any], str] = str) -> list[str]:
    """One line per bag and a total line."""
    lines = []
    for r in results:
        if r.ok:
            where = f"{r.bag} -> {r.out}" if r.out else r.bag
            lines.append(f"  ok     {where} ({r.seconds:.1f} s): {describe(r.value)}")
        else:
            lines.append(f"  FAILED {r.error}")
    failed = sum(not r.ok for r in results)
    lines.append(f"{len(results)} bag(s): {len(results) - failed} done, {failed} failed")
    return lines
