"""Experiments that write docs/: the paper's tables and figures, the simulator's validation,
the gap diagnosis's blind validation, the real quadcopter flights. Here: what they share
with each other and with the benchmarks (tools/ imports experiments/, never the reverse)."""

from __future__ import annotations

import math
import shlex
import sys
import time


def core_arrays(rec) -> tuple:
    """(sensor stamps, sensor, joint stamps, joint velocity) of a recording: the arrays the
    core's batch functions (calibrate_arrays, denoise_batch_method, ...) take first."""
    return rec.sensor_stamps_ns, rec.sensor, rec.joint_stamps_ns, rec.joint_velocity


def fmt(value, digits: int = 1) -> str:
    """`value` with `digits` decimals; "n/a" for None and non-finite floats."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    return f"{value:.{digits}f}"


def python_command(module: str, argv: list[str] | None) -> str:
    """The shell command `python -m module` with these arguments (None: this process's)."""
    argv = sys.argv[1:] if argv is None else argv
    return " ".join(shlex.quote(a) for a in ["python", "-m", module, *argv])


def best_wall_and_cpu(fn, repeats: int) -> tuple[float, float]:
    """Best wall-clock and best CPU seconds (this process) of `repeats` calls: on a shared
    machine the wall time also counts the time other jobs ran."""
    wall = cpu = float("inf")
    for _ in range(repeats):
        begin, begin_cpu = time.perf_counter(), time.process_time()
        fn()
        wall = min(wall, time.perf_counter() - begin)
        cpu = min(cpu, time.process_time() - begin_cpu)
    return wall, cpu
