"""`egovib bench`: performance figures as ratios to real time, with the machine noted.

Measured (targets in brackets):
  batch denoise throughput, 3 kHz 3-axis        (>= 1000x real time, one core)
  streaming cost per 32-sample hop, median/p99  (<= 150 us median)
  calibration of 441 cells x 2 s of data        (<= 5 s)
  simulator speed                               (>= 200x real time)
  bag write / read throughput                   (x real time)
  methods paper / cancel / hybrid on a simulated PR2 run, with a model calibrated on a
  simulated sweep: batch (combined and per axis) and streaming in 32-sample hops, x
  real time in wall and in CPU time, and each over paper's (the default, hybrid per
  axis: >= 300x, CPU time)
  `egovib denoise` end to end on a bag with the default method (>= 30x real time) and
  with the paper's, side by side with a plain copy of the same bag (file copy, and a
  chunk-by-chunk bag copy) and with zstd output, and the zstd size ratio of the 3 kHz
  Imu stream
  reading / writing MCAP: this package's chunk scanner and writer next to the
  `mcap` library and rosbags, on the same bag   (docs/bench_bags.md)

Inputs are synthetic (seeded) or simulated, so the figures do not depend on any
file; the robot is the default profile (the PR2 hand) and the noise model a
synthetic table of its shape (21 x 21 cells, 4 channels, 33 bins), except for the
methods figures and the default's `egovib denoise`, which need a fitted model (harmonic
map, canceller, gain): there the model is calibrated on a simulated superposition sweep
(the demo's: 1 s dwell). Writes FILE (JSON) and a markdown summary next to it (FILE.md).
`--bag-seconds` sets the length of the simulated bag (the 10-minute figures of
docs/bench_bags.md: 600).
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import os
import platform
import shutil
import tempfile
import time
from functools import lru_cache
from pathlib import Path

import numpy as np
import scipy
from mcap.reader import make_reader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapLibWriter
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from tqdm import tqdm

from egovib_research.experiments import best_wall_and_cpu
from egovib_ros import __version__
from egovib_ros.bag import BagReader, BagWriter, iter_recording, read_recording, write_recording
from egovib_ros.bag.codec import decode_imu, decode_joint_states, typestore
from egovib_ros.bag.denoise import denoise_bag
from egovib_ros.bag.many import bag_size
from egovib_ros.bag.recording import bag_topic_names, recording_streams
from egovib_ros.core import StreamingDenoiser, calibrate_arrays, denoise_batch
from egovib_ros.core.blocks import analysis_window, n_bins
from egovib_ros.core.methods import (
    METHODS,
    calibrate_methods,
    denoise_batch_method,
    make_denoiser,
)
from egovib_ros.core.noise_model import MODEL_CHANNELS, NoiseModel
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.outputs import atomic_output, json_holding, prepare_output, text_starting_with
from egovib_ros.robot import RobotProfile, default_profile
from egovib_ros.sim import simulate_motion
from egovib_ros.sim.scenarios import motion_slices, simulate_sweep

SYNTHETIC_JOINT_RATE_HZ = 1000.0  # joint states of the synthetic streams
#: What --force may replace: files whose schema / title say `egovib bench` wrote them.
BENCH_SCHEMA = "egovib.bench/1"
MARKDOWN_TITLE = "# egovib bench"


@lru_cache(maxsize=1)
def _robot() -> RobotProfile:
    """The robot the figures are for: the default profile (PR2 hand, 3 kHz, 2 joints)."""
    return default_profile()


TARGETS = {
    "batch_x_realtime": (">=", 1000.0),
    "stream_hop_median_us": ("<=", 150.0),
    "calibration_s": ("<=", 5.0),
    "simulation_x_realtime": (">=", 200.0),
    "denoise_bag_x_realtime": (">=", 30.0),
    # the default: hybrid, per axis, drop-in output (issue 32)
    "hybrid_batch_per_axis_x_realtime_cpu": (">=", 300.0),
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

    try:
        load = [round(x, 2) for x in os.getloadavg()]  # other work on the machine skews timings
    except OSError:
        load = None
    return {
        "platform": platform.platform(),
        "cpu_model": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "egovib_ros": __version__,
        "load_average_1_5_15min": load,
    }


def synthetic_streams(duration_s: float, *, seed: int = 0) -> dict:
    """Seeded accelerometer (3 kHz, 3 axes) and joint-state (1 kHz) arrays with smooth
    velocities."""
    rng = np.random.default_rng(seed)
    robot = _robot()
    n_accel = int(duration_s * robot.rate_hz)
    n_joint = int(duration_s * SYNTHETIC_JOINT_RATE_HZ)
    accel_stamps = (np.arange(n_accel) * (NS_PER_S / robot.rate_hz)).astype(np.int64)
    joint_stamps = (np.arange(n_joint) * (NS_PER_S / SYNTHETIC_JOINT_RATE_HZ)).astype(np.int64)
    accel = rng.normal(scale=0.5, size=(n_accel, 3)) + np.array([0.0, 0.0, 9.81])
    t = joint_stamps / NS_PER_S
    velocity = np.stack(
        [
            0.8 * robot.max_speed[j] * np.sin(2 * np.pi * (0.13 + 0.07 * j) * t + j)
            for j in range(robot.n_joints)
        ],
        axis=1,
    )
    return {
        "sensor_stamps_ns": accel_stamps,
        "accel": accel,
        "joint_stamps_ns": joint_stamps,
        "joint_velocity": velocity,
    }


def synthetic_model(*, seed: int = 0):
    """A NoiseModel of the real shape filled with seeded positive spectra."""

    rng = np.random.default_rng(seed)
    robot = _robot()
    grid = robot.grid()
    shape = robot.grid_shape + (len(MODEL_CHANNELS), n_bins(robot.block_length))
    return NoiseModel(
        grid=grid,
        joint_names=robot.joint_names,
        mean=rng.uniform(0.05, 1.0, shape),
        std=rng.uniform(0.01, 0.3, shape),
        counts=np.full(robot.grid_shape, 100),
        sample_rate_hz=robot.rate_hz,
        block_length=robot.block_length,
        hop=robot.hop,
        window=analysis_window(robot.block_length, robot.hop),
        band_hz=robot.band_hz,
        band_order=robot.band_order,
        profile=robot,
        provenance={"source": "bench synthetic"},
    )


def bench_batch(duration_s: float = 60.0, repeats: int = 3) -> dict:
    """Whole-array denoising (combined channel, the paper's pipeline) in x real time."""

    data, model = synthetic_streams(duration_s), synthetic_model()
    streams = [data[k] for k in ("sensor_stamps_ns", "accel", "joint_stamps_ns", "joint_velocity")]
    seconds, seconds_axes = (
        best_wall_and_cpu(
            lambda channels=channels: denoise_batch(*streams, model, channels=channels), repeats
        )[0]
        for channels in ("combined", "per_axis")
    )
    # the same samples stamped as a USB driver reads them (1 ms frames): the rebuilt clock
    frames = (streams[0] // 1_000_000 + 1) * 1_000_000
    receipt = [frames + np.arange(len(frames)), *streams[1:]]
    core_log = logging.getLogger("egovib_ros.core")
    disabled, core_log.disabled = core_log.disabled, True  # its "read as receipt times" line
    try:
        seconds_receipt, _ = best_wall_and_cpu(
            lambda: denoise_batch(*receipt, model, channels="per_axis"), repeats
        )
    finally:
        core_log.disabled = disabled
    return {
        "signal_s": duration_s,
        "seconds": seconds,
        "batch_x_realtime": duration_s / seconds,
        "batch_per_axis_x_realtime": duration_s / seconds_axes,
        "batch_receipt_stamps_x_realtime": duration_s / seconds_receipt,
    }


def bench_stream(duration_s: float = 10.0) -> dict:
    """StreamingDenoiser cost of one 32-sample hop (with its ~11 joint states), in microseconds."""

    data, model = synthetic_streams(duration_s, seed=1), synthetic_model()
    denoiser = StreamingDenoiser(model, channels="combined")
    joint_t, accel_t = data["joint_stamps_ns"], data["sensor_stamps_ns"]
    costs = []
    hop = _robot().hop
    for samples, joints in _hops(accel_t, joint_t, hop, whole=True):
        begin = time.perf_counter_ns()
        denoiser.push_joint_states(joint_t[joints], data["joint_velocity"][joints])
        denoiser.push_sensor(accel_t[samples], data["accel"][samples])
        costs.append(time.perf_counter_ns() - begin)
    costs_us = np.array(costs[len(costs) // 10 :]) / 1e3  # skip warm-up
    hop_us = hop / _robot().rate_hz * 1e6
    return {
        "hops": int(costs_us.size),
        "stream_hop_median_us": float(np.median(costs_us)),
        "stream_hop_p99_us": float(np.percentile(costs_us, 99)),
        "stream_x_realtime": float(hop_us / np.median(costs_us)),
    }


def _hops(sensor_stamps, joint_stamps, hop: int, *, whole: bool = False):
    """Per hop of `hop` sensor samples (`whole`: full hops only), its slice of the sensor
    samples and the slice of the joint states that arrived up to its last sample: the
    order in which a live stream feeds a denoiser."""
    joint_from = 0
    for start in range(0, len(sensor_stamps) - (hop - 1 if whole else 0), hop):
        stop = min(start + hop, len(sensor_stamps))
        joint_to = int(np.searchsorted(joint_stamps, sensor_stamps[stop - 1], side="right"))
        yield slice(start, stop), slice(joint_from, joint_to)
        joint_from = joint_to


def bench_calibration(cell_s: float = 2.0) -> dict:
    """CalibrationAccumulator over 441 cells x `cell_s` s of data (3 kHz accel, 1 kHz joints)."""

    robot = _robot()
    grid = robot.grid()
    cells = list(itertools.product(*grid))
    data = synthetic_streams(cell_s * len(cells), seed=2)
    # Hold each cell's velocity for `cell_s` seconds, as in a sweep.
    per_cell = int(round(cell_s * SYNTHETIC_JOINT_RATE_HZ))
    velocity = np.repeat(np.array(cells), per_cell, axis=0)[: len(data["joint_stamps_ns"])]
    _, seconds = _timed(
        lambda: calibrate_arrays(
            data["sensor_stamps_ns"],
            data["accel"],
            data["joint_stamps_ns"],
            velocity,
            profile=robot,
            sweep="full",
            source="bench synthetic",
        )
    )
    signal_s = cell_s * len(cells)
    return {
        "cells": len(cells),
        "signal_s": signal_s,
        "calibration_s": seconds,
        "calibration_x_realtime": signal_s / seconds,
    }


def _timed(fn) -> tuple:
    """(fn(), its wall-clock seconds)."""
    start = time.perf_counter()
    result = fn()
    return result, time.perf_counter() - start


@lru_cache(maxsize=2)
def methods_model(dwell_s: float = 1.0, settle_s: float = 0.3) -> tuple:
    """(model, seconds to calibrate it, the sweep's seconds): every method calibrated on a
    simulated superposition sweep of `dwell_s` per cell (paper's table, then the harmonic
    map, canceller and gain), as `egovib calibrate` with no option fits it."""
    robot = _robot()
    sweep, _ = simulate_sweep(grid="superposition", dwell_s=dwell_s, settle_s=settle_s, seed=1)
    arrays = (sweep.sensor_stamps_ns, sweep.sensor, sweep.joint_stamps_ns, sweep.joint_velocity)
    (model, _), calibration_s = _timed(
        lambda: calibrate_methods(
            calibrate_arrays(*arrays, profile=robot, sweep="superposition")[0], *arrays
        )
    )
    return model, calibration_s, sweep.duration_s


def bench_methods(
    duration_s: float = 30.0, *, repeats: int = 3, dwell_s: float = 1.0, settle_s: float = 0.3
) -> dict:
    """Methods paper, cancel and hybrid (core.methods) on a simulated PR2 motion run at 50 %
    speed with taps, the model calibrated on a simulated superposition sweep (`dwell_s`
    per cell; paper's table, then the harmonic map, canceller and gain): batch (combined,
    per axis: the drop-in output) and streaming in hops of the profile's hop, in x real
    time of wall and CPU time, best of `repeats` after one warm-up (numba compiles on first
    use)."""

    robot = _robot()
    model, calibration_s, sweep_s = methods_model(dwell_s, settle_s)
    run, _ = simulate_motion(duration_s=duration_s, max_speed=0.5, tap_rate_hz=2.0, seed=7)
    args = (run.sensor_stamps_ns, run.sensor, run.joint_stamps_ns, run.joint_velocity, model)
    hop = robot.hop

    def streamed(method: str) -> None:
        denoiser = make_denoiser(model, method, channels="combined")
        for samples, joints in _hops(run.sensor_stamps_ns, run.joint_stamps_ns, hop):
            denoiser.push_joint_states(run.joint_stamps_ns[joints], run.joint_velocity[joints])
            denoiser.push_sensor(run.sensor_stamps_ns[samples], run.sensor[samples])
        denoiser.flush()

    figures: dict = {
        "signal_s": run.duration_s,
        "calibration_sweep_s": sweep_s,
        "methods_calibration_s": calibration_s,
    }
    for method in METHODS:
        denoise_batch_method(*args, method=method, channels="combined")  # warm-up
        runs = {
            "batch": lambda method=method: denoise_batch_method(
                *args, method=method, channels="combined"
            ),
            "batch_per_axis": lambda method=method: denoise_batch_method(
                *args, method=method, channels="per_axis"
            ),
            "stream": lambda method=method: streamed(method),
        }
        for name, fn in runs.items():
            wall, cpu = best_wall_and_cpu(fn, repeats)
            figures[f"{method}_{name}_x_realtime"] = run.duration_s / wall
            figures[f"{method}_{name}_x_realtime_cpu"] = run.duration_s / cpu
    for method in METHODS[1:]:
        for name in ("batch", "batch_per_axis", "stream"):
            figures[f"{method}_{name}_cpu_over_paper"] = (
                figures[f"paper_{name}_x_realtime_cpu"] / figures[f"{method}_{name}_x_realtime_cpu"]
            )
    return figures


def bench_simulation_and_bags(duration_s: float = 20.0) -> dict:
    """Simulator speed and bag write/read throughput on one simulated motion recording."""

    (rec, _), sim_s = _timed(
        lambda: simulate_motion(
            duration_s=duration_s, max_speed=1.0, tap_rate_hz=1.0, effects={}, seed=3
        )
    )
    with tempfile.TemporaryDirectory(prefix="egovib-bench-") as tmp:
        bag = Path(tmp) / "bench_bag"
        _, write_s = _timed(lambda: write_recording(bag, rec))
        _, read_s = _timed(lambda: read_recording(bag))
        size = bag_size(bag)
    n_messages = len(rec.sensor_stamps_ns) * (
        1 + (rec.contact is not None) + (rec.ego is not None)
    ) + len(rec.joint_stamps_ns)
    return {
        "signal_s": duration_s,
        "simulation_s": sim_s,
        "simulation_x_realtime": duration_s / sim_s,
        "bag_messages": int(n_messages),
        "bag_bytes": int(size),
        "bag_write_x_realtime": duration_s / write_s,
        "bag_read_x_realtime": duration_s / read_s,
        "bag_write_msgs_per_s": n_messages / write_s,
        "bag_read_msgs_per_s": n_messages / read_s,
    }


# --------------------------------------------------------------------------
# Bags at recording scale
# --------------------------------------------------------------------------
def write_interleaved_bag(path: Path, duration_s: float) -> None:
    """A simulated motion bag laid out as a recorder writes one: one message at a time in
    stamp order (all topics interleaved), rosbags' writer, 1 MB chunks."""

    robot = _robot()
    slices, _ = motion_slices(
        duration_s=duration_s, max_speed=0.5, tap_rate_hz=2.0, effects={}, seed=3
    )
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {}
        for piece in slices:
            merged = []
            for topic, msgtype, stamps, encode in recording_streams(
                piece, bag_topic_names(robot), robot.sensor_field
            ):
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=typestore())
                merged += [
                    (int(t), topic, d) for t, d in zip(stamps.tolist(), encode(0, len(stamps)))
                ]
            for stamp, topic, data in sorted(merged, key=lambda m: m[0]):
                writer.write(conns[topic], stamp, data)


def _stream_copy(src: Path, dst: Path) -> None:
    """A plain bag copy through this package: every chunk copied as it is."""

    with BagReader(src) as reader, BagWriter(dst) as writer:
        for topic in reader.topics:
            writer.copy_topic(reader, topic)
        for batch in reader.batches():
            writer.copy_batch(batch)


def bench_bag_denoise(bag: Path, workdir: Path, *, repeats: int = 1, dwell_s: float = 1.0) -> dict:
    """`egovib denoise` (the same function) on `bag`, side by side with a file copy of the
    bag and a chunk-by-chunk bag copy, in alternation, best of `repeats`; plus zstd output:
    the paper's method on a synthetic table (as the rounds before measured it), and the
    default (hybrid, drop-in) with a model of every method (methods_model(dwell_s))."""

    with BagReader(bag) as reader:
        duration_s = float(reader.info["duration"]["nanoseconds"]) / NS_PER_S
    model = synthetic_model()
    default_model = methods_model(dwell_s)[0]
    runs = {
        "file_copy": lambda out: shutil.copytree(bag, out),
        "bag_copy": lambda out: _stream_copy(bag, out),
        "denoise": lambda out: denoise_bag(bag, out, model=model),
        "denoise_zstd": lambda out: denoise_bag(bag, out, model=model, compress="zstd"),
        "denoise_default": lambda out: denoise_bag(bag, out, model=default_model),
    }
    best = {name: float("inf") for name in runs}
    sizes = {}
    for _ in range(repeats):
        for name, run in runs.items():
            out = workdir / f"bench_{name}"
            best[name] = min(best[name], _timed(lambda run=run, out=out: run(out))[1])
            sizes[name] = bag_size(out)
            shutil.rmtree(out)
    figures = {"bag_signal_s": duration_s, "bag_input_bytes": bag_size(bag)}
    for name, seconds in best.items():
        figures[f"{name}_s"] = seconds
        figures[f"{name}_x_realtime"] = duration_s / seconds
        figures[f"{name}_output_bytes"] = sizes[name]
    figures["denoise_bag_x_realtime"] = figures["denoise_default_x_realtime"]  # what users run
    for name in ("denoise", "denoise_default"):
        figures[f"{name}_vs_file_copy"] = best[name] / best["file_copy"]
        figures[f"{name}_vs_bag_copy"] = best[name] / best["bag_copy"]
    figures["zstd_output_size_ratio"] = sizes["denoise"] / sizes["denoise_zstd"]
    figures["imu_stream_zstd_size_ratio"] = imu_stream_size_ratio(bag, workdir)
    return figures


def imu_stream_size_ratio(bag: Path, workdir: Path) -> float:
    """Size of the 3 kHz Imu topic alone, uncompressed / zstd MCAP chunks."""

    topic = _robot().sensor_topic
    sizes = []
    for compress in (False, True):
        out = workdir / f"imu_only_{int(compress)}"
        with BagReader(bag) as reader, BagWriter(out, compress=compress) as writer:
            writer.copy_topic(reader, topic)
            for batch in reader.batches([topic]):
                messages = batch.messages.get(topic)
                if messages is not None:
                    writer.write_batch(topic, messages.log_times, messages)
        sizes.append(next(out.glob("*.mcap")).stat().st_size)
        shutil.rmtree(out)
    return sizes[0] / sizes[1]


def bench_mcap_libraries(bag: Path, workdir: Path) -> dict:
    """Reading the sensor and joint topics of `bag` into arrays, and writing the sensor
    topic, with this package's chunk scanner / writer, the `mcap` library and rosbags.
    Every reader hands its raw messages to the same vectorised decoders."""

    robot = _robot()
    topics = [robot.sensor_topic, robot.joints_topic]
    figures: dict = {}

    def decode(raw: dict) -> int:
        decode_imu(raw[robot.sensor_topic], robot.sensor_field)
        decode_joint_states(raw[robot.joints_topic], robot.joint_names)
        return sum(len(v) for v in raw.values())

    def read_mcap_library() -> int:
        raw = {t: [] for t in topics}
        with open(next(bag.glob("*.mcap")), "rb") as fh:
            for _, channel, message in make_reader(fh).iter_messages(
                topics=topics, log_time_order=False
            ):
                raw[channel.topic].append(message.data)
        return decode(raw)

    def read_rosbags() -> int:
        raw = {t: [] for t in topics}
        with Reader(bag) as reader:
            conns = [c for c in reader.connections if c.topic in topics]
            for conn, _, data in reader.messages(connections=conns):
                raw[conn.topic].append(data)
        return decode(raw)

    def read_scanner() -> int:
        return sum(
            len(p.sensor_stamps_ns) + len(p.joint_stamps_ns)
            for p in iter_recording(
                bag, profile=robot, ground_truth=False, denoised=False, commands=False
            )
        )

    for name, read in (
        ("scanner", read_scanner),
        ("mcap_library", read_mcap_library),
        ("rosbags", read_rosbags),
    ):
        n, seconds = _timed(read)
        figures[f"read_{name}_msgs_per_s"] = n / seconds
        figures[f"read_{name}_s"] = seconds

    with BagReader(bag) as reader:
        batches = [
            b.messages[robot.sensor_topic]
            for b in reader.batches([robot.sensor_topic])
            if robot.sensor_topic in b.messages
        ]
    stamps = np.concatenate([b.log_times for b in batches])
    datas = [d for b in batches for d in b.to_list()]
    msgdef, _ = typestore().generate_msgdef("sensor_msgs/msg/Imu", ros_version=2)

    def write_package(out: Path) -> None:
        with BagWriter(out) as writer:
            writer.add_topic(robot.sensor_topic, "sensor_msgs/msg/Imu")
            for b in batches:
                writer.write_batch(robot.sensor_topic, b.log_times, b)

    def write_mcap_library(out: Path) -> None:
        out.mkdir()
        with open(out / "out.mcap", "wb") as fh:
            writer = McapLibWriter(fh, compression=CompressionType.NONE)
            writer.start(profile="ros2", library="bench")
            schema = writer.register_schema("sensor_msgs/msg/Imu", "ros2msg", msgdef.encode())
            channel = writer.register_channel(robot.sensor_topic, "cdr", schema)
            for t, d in zip(stamps.tolist(), datas):
                writer.add_message(channel, t, d, t)
            writer.finish()

    def write_rosbags(out: Path) -> None:
        with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            conn = writer.add_connection(
                robot.sensor_topic, "sensor_msgs/msg/Imu", typestore=typestore()
            )
            for t, d in zip(stamps.tolist(), datas):
                writer.write(conn, t, d)

    for name, write in (
        ("package", write_package),
        ("mcap_library", write_mcap_library),
        ("rosbags", write_rosbags),
    ):
        out = workdir / f"write_{name}"
        _, seconds = _timed(lambda write=write, out=out: write(out))
        shutil.rmtree(out)
        figures[f"write_{name}_msgs_per_s"] = len(datas) / seconds
        figures[f"write_{name}_s"] = seconds
    figures["messages_read"] = n
    figures["messages_written"] = len(datas)
    return figures


def bench_bags(
    duration_s: float = 60.0,
    *,
    repeats: int = 1,
    bag: Path | None = None,
    workdir: Path | None = None,
    dwell_s: float = 1.0,
) -> dict:
    """Bag-scale figures on a simulated recorder-style bag of `duration_s` (or on `bag`)."""
    with tempfile.TemporaryDirectory(prefix="egovib-bench-bags-", dir=workdir) as tmp:
        tmp = Path(tmp)
        if bag is None:
            bag = tmp / "input_bag"
            write_interleaved_bag(bag, duration_s)
        figures = bench_bag_denoise(Path(bag), tmp, repeats=repeats, dwell_s=dwell_s)
        figures["mcap"] = bench_mcap_libraries(Path(bag), tmp)
    return figures


def run_benchmarks(
    *,
    quick: bool = False,
    progress=None,
    bag_seconds: float | None = None,
    bag: Path | None = None,
    workdir: Path | None = None,
) -> dict:
    """All figures as one dict (`quick` shortens the inputs, for tests)."""
    bag_seconds = bag_seconds if bag_seconds is not None else (3.0 if quick else 60.0)
    dwell_s = 0.2 if quick else 1.0  # the methods' calibration sweep
    steps = [
        ("batch", lambda: bench_batch(10.0 if quick else 60.0, 1 if quick else 3)),
        ("stream", lambda: bench_stream(2.0 if quick else 10.0)),
        ("calibration", lambda: bench_calibration(0.2 if quick else 2.0)),
        ("simulation_and_bags", lambda: bench_simulation_and_bags(2.0 if quick else 20.0)),
        (
            "methods",
            lambda: bench_methods(
                2.0 if quick else 30.0, repeats=1 if quick else 3, dwell_s=dwell_s
            ),
        ),
        (
            "bags",
            lambda: bench_bags(
                bag_seconds, repeats=1 if quick else 2, bag=bag, workdir=workdir, dwell_s=dwell_s
            ),
        ),
    ]
    results = {"schema": BENCH_SCHEMA, "machine": machine_info(), "quick": quick}
    for name, step in steps:
        results[name] = step()
        if progress is not None:
            progress(name)
    flat = {
        k: v
        for section in results.values()
        if isinstance(section, dict)
        for k, v in section.items()
        if not isinstance(v, dict)
    }
    results["targets"] = {
        key: {
            "value": flat.get(key),
            "target": f"{op} {limit:g}",
            "met": (flat[key] >= limit if op == ">=" else flat[key] <= limit)
            if key in flat
            else None,
        }
        for key, (op, limit) in TARGETS.items()
    }
    return results


def markdown_summary(results: dict) -> str:
    """Human-readable table of `run_benchmarks` results."""
    m = results["machine"]
    rows = _core_rows(results)
    if results.get("methods"):
        rows += _method_rows(results["methods"])
    if results.get("bags"):
        rows += _bag_rows(results["bags"])
    lines = [
        MARKDOWN_TITLE,
        "",
        f"Machine: {m['cpu_model']}, {m['cores']} cores, {m['platform']}, "
        f"Python {m['python']}, numpy {m['numpy']}, scipy {m['scipy']}"
        + (
            f"; load average {m['load_average_1_5_15min']} while measuring"
            if m.get("load_average_1_5_15min")
            else ""
        )
        + (" (quick run)" if results.get("quick") else ""),
        "",
        "Regenerate: `egovib bench --json docs/bench.json` (also writes docs/bench.md).",
        "",
        "| figure | measured | target |",
        "|---|---|---|",
    ]
    lines += [f"| {name} | {value} | {target} |" for name, value, target in rows]
    unmet = [k for k, t in results["targets"].items() if t["met"] is False]
    lines += ["", "All targets met." if not unmet else f"Targets missed: {', '.join(unmet)}.", ""]
    return "\n".join(lines)


def _core_rows(results: dict) -> list[tuple[str, str, str]]:
    """(figure, measured, target) of the batch, streaming, calibration, simulator and bag
    figures."""
    b, s, c, g = (results[k] for k in ("batch", "stream", "calibration", "simulation_and_bags"))
    return [
        (
            "Batch denoise, combined (3 kHz, 3 axes)",
            f"{b['batch_x_realtime']:.0f}x real time",
            ">= 1000x",
        ),
        ("Batch denoise, per axis", f"{b['batch_per_axis_x_realtime']:.0f}x real time", ""),
        (
            "Batch denoise, per axis, stamps taken on receipt",
            f"{b.get('batch_receipt_stamps_x_realtime', float('nan')):.0f}x real time",
            "",
        ),
        (
            "Streaming, per 32-sample hop (median)",
            f"{s['stream_hop_median_us']:.0f} us",
            "<= 150 us",
        ),
        ("Streaming, per hop (p99)", f"{s['stream_hop_p99_us']:.0f} us", ""),
        ("Streaming, ratio to real time", f"{s['stream_x_realtime']:.0f}x", ""),
        (
            f"Calibration, {c['cells']} cells x {c['signal_s'] / c['cells']:g} s",
            f"{c['calibration_s']:.2f} s ({c['calibration_x_realtime']:.0f}x real time)",
            "<= 5 s",
        ),
        ("Simulator", f"{g['simulation_x_realtime']:.0f}x real time", ">= 200x"),
        (
            "Bag write (MCAP)",
            f"{g['bag_write_x_realtime']:.1f}x real time "
            f"({g['bag_write_msgs_per_s'] / 1e3:.0f}k msg/s)",
            "",
        ),
        (
            "Bag read",
            f"{g['bag_read_x_realtime']:.1f}x real time "
            f"({g['bag_read_msgs_per_s'] / 1e3:.0f}k msg/s)",
            "",
        ),
    ]


def _method_rows(methods: dict) -> list[tuple[str, str, str]]:
    """(figure, measured, target) of each method, batch and streaming, and their calibration."""
    rows = []
    for method in METHODS:
        for name, label in (
            ("batch", "batch, combined"),
            ("batch_per_axis", "batch, per axis, drop-in output"),
            ("stream", f"streaming, {_robot().hop}-sample hops"),
        ):
            over = (
                f"; {methods[f'{method}_{name}_cpu_over_paper']:.1f}x paper's CPU time"
                if method != "paper"
                else ""
            )
            target = ">= 300x (CPU)" if (method, name) == ("hybrid", "batch_per_axis") else ""
            rows.append(
                (
                    f"Method `{method}`, {label}{' (the default)' if target else ''} "
                    f"(PR2 run, {methods['signal_s']:.0f} s)",
                    f"{methods[f'{method}_{name}_x_realtime']:.0f}x real time wall, "
                    f"{methods[f'{method}_{name}_x_realtime_cpu']:.0f}x CPU{over}",
                    target,
                )
            )
    rows.append(
        (
            "Calibration of cancel + hybrid (paper's table, harmonic map, canceller, gain)",
            f"{methods['methods_calibration_s']:.1f} s for a "
            f"{methods['calibration_sweep_s']:.0f} s sweep",
            "",
        )
    )
    return rows


def _bag_rows(bags: dict) -> list[tuple[str, str, str]]:
    """(figure, measured, target) of `egovib denoise` on a bag and the MCAP comparison."""
    mc = bags["mcap"]
    name = f"{bags['bag_signal_s']:.0f} s bag, {bags['bag_input_bytes'] / 1e6:.0f} MB"

    def end_to_end(key: str) -> str:
        return (
            f"{bags[f'{key}_x_realtime']:.0f}x real time ({bags[f'{key}_s']:.1f} s; "
            f"{bags[f'{key}_vs_file_copy']:.2f}x a file copy, "
            f"{bags[f'{key}_vs_bag_copy']:.2f}x a bag copy)"
        )

    return [
        (
            f"`egovib denoise`, {name}, the default (hybrid)",
            end_to_end("denoise_default"),
            ">= 30x",
        ),
        (
            f"`egovib denoise`, {name}, `--method paper` (a synthetic table)",
            end_to_end("denoise"),
            "",
        ),
        (
            "... with zstd output",
            f"{bags['denoise_zstd_x_realtime']:.0f}x real time, output "
            f"{bags['zstd_output_size_ratio']:.1f}x smaller",
            "",
        ),
        (
            "File copy / bag copy of the same bag",
            f"{bags['file_copy_x_realtime']:.0f}x / {bags['bag_copy_x_realtime']:.0f}x real time",
            "",
        ),
        ("zstd size ratio, 3 kHz Imu stream", f"{bags['imu_stream_zstd_size_ratio']:.1f}", ""),
        (
            "Read sensor + joints: scanner / mcap library / rosbags",
            " / ".join(
                f"{mc[f'read_{k}_msgs_per_s'] / 1e3:.0f}k"
                for k in ("scanner", "mcap_library", "rosbags")
            )
            + " msg/s",
            "",
        ),
        (
            "Write the Imu stream: package / mcap library / rosbags",
            " / ".join(
                f"{mc[f'write_{k}_msgs_per_s'] / 1e3:.0f}k"
                for k in ("package", "mcap_library", "rosbags")
            )
            + " msg/s",
            "",
        ),
    ]


def run(args: argparse.Namespace) -> int:
    # before any work
    prepare_output(
        args.json,
        force=args.force,
        kind="json",
        option="--json",
        inputs=[args.markdown],
        ours=json_holding(schema=BENCH_SCHEMA),
    )
    prepare_output(
        args.markdown or Path(args.json).with_suffix(".md"),  # as given (not through Path)
        force=args.force,
        kind="file",
        option="--markdown",
        inputs=[args.json],
        ours=text_starting_with(MARKDOWN_TITLE),
    )
    with tqdm(total=6, desc="bench", unit="step", disable=args.quiet) as bar:
        results = run_benchmarks(
            quick=args.quick,
            bag_seconds=args.bag_seconds,
            bag=args.bag,
            workdir=args.workdir,
            progress=lambda name: (bar.set_postfix_str(name), bar.update()),
        )
    json_path = Path(args.json)
    md_path = Path(args.markdown) if args.markdown else json_path.with_suffix(".md")
    with atomic_output(json_path) as tmp:
        tmp.write_text(json.dumps(results, indent=2) + "\n")
    with atomic_output(md_path) as tmp:
        tmp.write_text(markdown_summary(results))
    if not args.quiet:
        print(markdown_summary(results))
    return 0
