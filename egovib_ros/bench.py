"""`egovib bench`: performance figures as ratios to real time, with the machine noted.

Measured (issue 2/3 targets in brackets):
  batch denoise throughput, 3 kHz 3-axis        (>= 1000x real time, one core)
  streaming cost per 32-sample hop, median/p99  (<= 150 us median)
  calibration of 441 cells x 2 s of data        (<= 5 s)
  simulator speed                               (>= 200x real time)
  bag write / read throughput                   (x real time)

Inputs are synthetic (seeded) so the figures do not depend on any file; the
noise model is a synthetic table of the real shape (21 x 21 cells, 4 channels,
33 bins). Writes FILE (JSON) and a markdown summary next to it (FILE.md).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from egovib_ros import __version__
from egovib_ros.constants import (ACCEL_RATE_HZ, BAND_HZ, BAND_ORDER, BLOCK_LENGTH, HOP, JOINT_NAMES,
                                  JOINT_RATE_HZ, MAX_SPEED, default_grid)
from egovib_ros.fileutil import atomic_output, prepare_output

TARGETS = {
    "batch_x_realtime": (">=", 1000.0),
    "stream_hop_median_us": ("<=", 150.0),
    "calibration_s": ("<=", 5.0),
    "simulation_x_realtime": (">=", 200.0),
}


def machine_info() -> dict:
    """Platform, CPU model, core count and library versions of this machine."""
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import scipy
    try:
        load = [round(x, 2) for x in os.getloadavg()]    # other work on the machine skews timings
    except OSError:
        load = None
    return {"platform": platform.platform(), "cpu_model": cpu, "cores": os.cpu_count(),
            "python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
            "egovib_ros": __version__, "load_average_1_5_15min": load}


def synthetic_streams(duration_s: float, *, seed: int = 0) -> dict:
    """Seeded accelerometer (3 kHz, 3 axes) and joint-state (1 kHz) arrays with smooth velocities."""
    rng = np.random.default_rng(seed)
    n_accel = int(duration_s * ACCEL_RATE_HZ)
    n_joint = int(duration_s * JOINT_RATE_HZ)
    accel_stamps = (np.arange(n_accel) * (1e9 / ACCEL_RATE_HZ)).astype(np.int64)
    joint_stamps = (np.arange(n_joint) * (1e9 / JOINT_RATE_HZ)).astype(np.int64)
    accel = rng.normal(scale=0.5, size=(n_accel, 3)) + np.array([0.0, 0.0, 9.81])
    t = joint_stamps / 1e9
    velocity = np.stack([0.8 * MAX_SPEED[j] * np.sin(2 * np.pi * (0.13 + 0.07 * j) * t + j)
                         for j in range(len(JOINT_NAMES))], axis=1)
    return {"accel_stamps_ns": accel_stamps, "accel": accel, "joint_stamps_ns": joint_stamps,
            "joint_velocity": velocity}


def synthetic_model(*, seed: int = 0):
    """A NoiseModel of the real shape filled with seeded positive spectra."""
    from egovib_ros.core.blocks import analysis_window, n_bins
    from egovib_ros.core.noise_model import MODEL_CHANNELS, NoiseModel
    rng = np.random.default_rng(seed)
    grid = default_grid()
    shape = tuple(len(g) for g in grid) + (len(MODEL_CHANNELS), n_bins(BLOCK_LENGTH))
    return NoiseModel(grid=grid, joint_names=JOINT_NAMES, mean=rng.uniform(0.05, 1.0, shape),
                      std=rng.uniform(0.01, 0.3, shape), counts=np.full(shape[:2], 100),
                      block_length=BLOCK_LENGTH, hop=HOP, window=analysis_window(BLOCK_LENGTH, HOP),
                      band_hz=BAND_HZ, band_order=BAND_ORDER, provenance={"source": "bench synthetic"})


def _best_of(fn, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - start)
    return best


def bench_batch(duration_s: float = 60.0, repeats: int = 3) -> dict:
    """Whole-array denoising (combined channel, the paper's pipeline) in x real time."""
    from egovib_ros.core import denoise_batch
    data, model = synthetic_streams(duration_s), synthetic_model()
    seconds = _best_of(lambda: denoise_batch(data["accel_stamps_ns"], data["accel"], data["joint_stamps_ns"],
                                             data["joint_velocity"], model, channels="combined"), repeats)
    seconds_axes = _best_of(lambda: denoise_batch(data["accel_stamps_ns"], data["accel"],
                                                  data["joint_stamps_ns"], data["joint_velocity"], model,
                                                  channels="per_axis"), repeats)
    return {"signal_s": duration_s, "seconds": seconds, "batch_x_realtime": duration_s / seconds,
            "batch_per_axis_x_realtime": duration_s / seconds_axes}


def bench_stream(duration_s: float = 10.0) -> dict:
    """StreamingDenoiser cost of one 32-sample hop (with its ~11 joint states), in microseconds."""
    from egovib_ros.core import StreamingDenoiser
    data, model = synthetic_streams(duration_s, seed=1), synthetic_model()
    denoiser = StreamingDenoiser(model, channels="combined")
    joint_t, accel_t = data["joint_stamps_ns"], data["accel_stamps_ns"]
    costs = []
    joint_from = 0
    for start in range(0, len(accel_t) - HOP + 1, HOP):
        stop = start + HOP
        joint_to = int(np.searchsorted(joint_t, accel_t[stop - 1], side="right"))
        begin = time.perf_counter_ns()
        denoiser.push_joint_states(joint_t[joint_from:joint_to], data["joint_velocity"][joint_from:joint_to])
        denoiser.push_accel(accel_t[start:stop], data["accel"][start:stop])
        costs.append(time.perf_counter_ns() - begin)
        joint_from = joint_to
    costs_us = np.array(costs[len(costs) // 10:]) / 1e3      # skip warm-up
    hop_us = HOP / ACCEL_RATE_HZ * 1e6
    return {"hops": int(costs_us.size), "stream_hop_median_us": float(np.median(costs_us)),
            "stream_hop_p99_us": float(np.percentile(costs_us, 99)),
            "stream_x_realtime": float(hop_us / np.median(costs_us))}


def bench_calibration(cell_s: float = 2.0) -> dict:
    """CalibrationAccumulator over 441 cells x `cell_s` s of data (3 kHz accel, 1 kHz joints)."""
    from egovib_ros.core import calibrate_arrays
    grid = default_grid()
    cells = [(a, b) for a in grid[0] for b in grid[1]]
    data = synthetic_streams(cell_s * len(cells), seed=2)
    # Hold each cell's velocity for `cell_s` seconds, as in a sweep.
    per_cell = int(round(cell_s * JOINT_RATE_HZ))
    velocity = np.repeat(np.array(cells), per_cell, axis=0)[:len(data["joint_stamps_ns"])]
    start = time.perf_counter()
    model, _ = calibrate_arrays(data["accel_stamps_ns"], data["accel"], data["joint_stamps_ns"], velocity,
                                grid=grid, sample_rate_hz=ACCEL_RATE_HZ, block_length=BLOCK_LENGTH, hop=HOP,
                                band_hz=BAND_HZ, source="bench synthetic")
    seconds = time.perf_counter() - start
    signal_s = cell_s * len(cells)
    return {"cells": len(cells), "signal_s": signal_s, "calibration_s": seconds,
            "calibration_x_realtime": signal_s / seconds}


def bench_simulation_and_bags(duration_s: float = 20.0) -> dict:
    """Simulator speed and bag write/read throughput on one simulated motion recording."""
    from egovib_ros.bagio import read_recording, write_recording
    from egovib_ros.sim import simulate_motion
    start = time.perf_counter()
    rec, _ = simulate_motion(duration_s=duration_s, max_speed=1.0, tap_rate_hz=1.0, effects={}, seed=3)
    sim_s = time.perf_counter() - start
    with tempfile.TemporaryDirectory(prefix="egovib-bench-") as tmp:
        bag = Path(tmp) / "bench_bag"
        start = time.perf_counter()
        write_recording(bag, rec)
        write_s = time.perf_counter() - start
        start = time.perf_counter()
        read_recording(bag)
        read_s = time.perf_counter() - start
        size = sum(f.stat().st_size for f in bag.iterdir())
    n_messages = len(rec.accel_stamps_ns) * (1 + (rec.contact is not None) + (rec.ego is not None)) \
        + len(rec.joint_stamps_ns)
    return {"signal_s": duration_s, "simulation_s": sim_s, "simulation_x_realtime": duration_s / sim_s,
            "bag_messages": int(n_messages), "bag_bytes": int(size),
            "bag_write_x_realtime": duration_s / write_s, "bag_read_x_realtime": duration_s / read_s,
            "bag_write_msgs_per_s": n_messages / write_s, "bag_read_msgs_per_s": n_messages / read_s}


def run_benchmarks(*, quick: bool = False, progress=None) -> dict:
    """All figures as one dict (`quick` shortens the inputs, for tests)."""
    steps = [
        ("batch", lambda: bench_batch(10.0 if quick else 60.0, 1 if quick else 3)),
        ("stream", lambda: bench_stream(2.0 if quick else 10.0)),
        ("calibration", lambda: bench_calibration(0.2 if quick else 2.0)),
        ("simulation_and_bags", lambda: bench_simulation_and_bags(2.0 if quick else 20.0)),
    ]
    results = {"schema": "egovib.bench/1", "machine": machine_info(), "quick": quick}
    for name, step in steps:
        results[name] = step()
        if progress is not None:
            progress(name)
    flat = {k: v for section in results.values() if isinstance(section, dict) for k, v in section.items()}
    results["targets"] = {
        key: {"value": flat.get(key), "target": f"{op} {limit:g}",
              "met": (flat[key] >= limit if op == ">=" else flat[key] <= limit) if key in flat else None}
        for key, (op, limit) in TARGETS.items()}
    return results


def markdown_summary(results: dict) -> str:
    """Human-readable table of `run_benchmarks` results."""
    m = results["machine"]
    b, s, c, g = results["batch"], results["stream"], results["calibration"], results["simulation_and_bags"]
    rows = [
        ("Batch denoise, combined (3 kHz, 3 axes)", f"{b['batch_x_realtime']:.0f}x real time", ">= 1000x"),
        ("Batch denoise, per axis", f"{b['batch_per_axis_x_realtime']:.0f}x real time", ""),
        ("Streaming, per 32-sample hop (median)", f"{s['stream_hop_median_us']:.0f} us", "<= 150 us"),
        ("Streaming, per hop (p99)", f"{s['stream_hop_p99_us']:.0f} us", ""),
        ("Streaming, ratio to real time", f"{s['stream_x_realtime']:.0f}x", ""),
        (f"Calibration, {c['cells']} cells x {c['signal_s'] / c['cells']:g} s",
         f"{c['calibration_s']:.2f} s ({c['calibration_x_realtime']:.0f}x real time)", "<= 5 s"),
        ("Simulator", f"{g['simulation_x_realtime']:.0f}x real time", ">= 200x"),
        ("Bag write (MCAP)", f"{g['bag_write_x_realtime']:.1f}x real time "
                             f"({g['bag_write_msgs_per_s'] / 1e3:.0f}k msg/s)", ""),
        ("Bag read", f"{g['bag_read_x_realtime']:.1f}x real time ({g['bag_read_msgs_per_s'] / 1e3:.0f}k msg/s)", ""),
    ]
    lines = ["# egovib bench", "",
             f"Machine: {m['cpu_model']}, {m['cores']} cores, {m['platform']}, "
             f"Python {m['python']}, numpy {m['numpy']}, scipy {m['scipy']}"
             + (f"; load average {m['load_average_1_5_15min']} while measuring"
                if m.get("load_average_1_5_15min") else "")
             + (" (quick run)" if results.get("quick") else ""), "",
             "Regenerate: `egovib bench --json docs/bench.json` (also writes docs/bench.md).", "",
             "| figure | measured | target |", "|---|---|---|"]
    lines += [f"| {name} | {value} | {target} |" for name, value, target in rows]
    unmet = [k for k, t in results["targets"].items() if t["met"] is False]
    lines += ["", "All targets met." if not unmet else f"Targets missed: {', '.join(unmet)}.", ""]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm
    # before any work
    prepare_output(args.json, force=args.force, kind="json", option="--json",
                   inputs=[args.markdown])
    prepare_output(args.markdown or Path(args.json).with_suffix(".md"), force=args.force,
                   kind="file", option="--markdown", inputs=[args.json])
    with tqdm(total=4, desc="bench", unit="step", disable=args.quiet) as bar:
        results = run_benchmarks(quick=args.quick, progress=lambda name: (bar.set_postfix_str(name), bar.update()))
    json_path = Path(args.json)
    md_path = Path(args.markdown) if args.markdown else json_path.with_suffix(".md")
    with atomic_output(json_path) as tmp:
        tmp.write_text(json.dumps(results, indent=2) + "\n")
    with atomic_output(md_path) as tmp:
        tmp.write_text(markdown_summary(results))
    if not args.quiet:
        print(markdown_summary(results))
    return 0


def register(subparsers) -> None:
    parser = subparsers.add_parser("bench", help="performance figures (x real time) as JSON + markdown",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", required=True, metavar="FILE", help="where to write the JSON figures")
    parser.add_argument("--markdown", metavar="FILE", help="markdown summary (default: FILE with .md suffix)")
    parser.add_argument("--quick", action="store_true", help="short inputs (seconds), for tests")
    parser.add_argument("--force", action="store_true", help="replace existing output files")
    parser.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    parser.set_defaults(func=run)
