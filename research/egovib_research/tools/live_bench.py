"""Live benchmark: does the denoiser node keep up with 3 kHz next to sim_hand on this machine?

    egovib live-bench --json docs/live_bench.json [--seconds 60]

Runs sim_hand (ground-truth topics off) and denoiser as separate processes in a private
ROS domain, drives the hand with random smooth motion from this process, and for
`--seconds` (after a warm-up) measures:

* dropped samples: at the denoiser's input, what its /diagnostics reports (the core's
  counts of bridged gaps, restarts, bad and out-of-order samples, and undecodable
  messages); at its output, denoised samples missing here (the stamp span received
  at the nominal rate minus the samples received);
* CPU share (fraction of one core, i.e. CPU seconds per real-time second) of the
  denoiser and of sim_hand, from /proc/<pid>/stat;
* latency, raw stamp -> denoised received: for each denoised sample received here,
  the receive time (system clock) minus its header stamp. The header stamp is the
  raw sample's time as sim_hand stamps it, so this includes sim_hand's batching
  (samples go out every `--publish-period`, by default 2 ms), the block delay of the
  algorithm (32-63 samples = 10.7-21 ms), processing, and DDS delivery twice.
  The denoiser's own figure (publish time minus stamp, from its /diagnostics) is
  reported too.

`--contacts` measures contact events live instead (run_contact_bench): sim_hand taps
(`--tap-rate`) and publishes its ground truth, and two contact_detector nodes run beside
the denoiser, one on its output (source denoised), one on the raw stream (source raw),
each with its threshold from a no-contact bag of the same random motion
(`--calibration-seconds`, simulated offline first) at no false-alarm budget. For each:
events, F1 and false alarms per minute against the true tap onsets (from the ground-truth
contact signal, +-10 ms, as `egovib evaluate`), and the latency on the wall clock from the
raw sample of the onset to the event message: receive time of the contact_events message
here minus its header stamp (the onset sample's stamp, which sim_hand sets from this
machine's clock), and minus the true onset. This process takes the ground truth instead of
the denoised stream (a second 3 kHz stream in one Python process starves it).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import Vector3Stamped
from sensor_msgs.msg import Imu

from egovib_research.tools.orchestration import NodeGroup
from egovib_research.tools.watcher import Watcher, decode_imu_messages
from egovib_ros.bag import write_recording
from egovib_ros.core import NoiseModel, calibrate_arrays
from egovib_ros.core.filters import combined_bandpassed
from egovib_ros.core.methods import (
    calibrate_detection,
    calibrate_methods,
    make_denoiser,
    resolve_method,
)
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.evaluation.contacts import TOLERANCE_S
from egovib_ros.evaluation.detection import match_events
from egovib_ros.evaluation.metrics import segment_contacts
from egovib_ros.nodes.common import drain, sensor_qos
from egovib_ros.nodes.convert import command_message, diagnostic_values, stamp_to_ns
from egovib_ros.outputs import atomic_output
from egovib_ros.robot import load_profile
from egovib_ros.sim import motion_commands, simulate_motion, simulate_sweep

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process, in seconds (fields 14 and 15 of /proc/<pid>/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def bench_model(path: Path) -> Path:
    """A noise model from a short offline superposition sweep, as `egovib calibrate` makes it
    (every method: the denoiser's default, hybrid, runs on it; the contact detector's
    thresholds, which adaptation needs)."""

    rec, _ = simulate_sweep(grid="superposition", dwell_s=1.0, settle_s=0.3, seed=5)
    arrays = (rec.sensor_stamps_ns, rec.sensor, rec.joint_stamps_ns, rec.joint_velocity)
    model, _ = calibrate_arrays(*arrays, sweep="superposition", source="live_bench sweep")
    model, _ = calibrate_methods(model, *arrays, source="live_bench sweep")
    model, _ = calibrate_detection(model, *arrays, source="live_bench sweep")
    model.save(path)
    return path


def algorithmic_latency_ms(
    model_path: Path,
    *,
    publish_period: float = 0.002,
    seconds: float = 10.0,
    method: str | None = None,
    channels: str = "per_axis",
) -> dict:
    """The latency the pipeline would have with zero transport and scheduling cost.

    sim_hand publishes each `publish_period`'s samples at its end. The paper's denoiser
    processes every hop of samples, and input sample k is output with the block that ends
    at input sample e(k) = floor((k + L - H) / H) * H + H - 1 (the first block starts with
    L - H samples of padding); `cancel` and `hybrid` output sample k once sample
    e(k) = k + d is in (d: the method's look-ahead; for hybrid's drop-in output, the default
    per axis, the look-ahead its split needs). Latency of sample k = stamp of the last
    sample of the batch that carries e(k) - stamp of k.
    """

    model = NoiseModel.load(model_path)
    method = resolve_method(model, method)
    rate, length, hop = model.sample_rate_hz, model.block_length, model.hop
    per_batch = max(1, int(round(publish_period * rate)))
    k = np.arange(int(seconds * rate))
    if method == "paper":
        completing = (k + length - hop) // hop * hop + hop - 1
    else:
        completing = k + make_denoiser(model, method, channels=channels).delay
    published_with = (completing // per_batch + 1) * per_batch - 1
    return _percentiles((published_with - k)[int(rate) :] / rate * 1e3)  # after the first second


def drive_motion(
    watcher: Watcher, processes: dict, warmup: float, seconds: float, at_measure
) -> tuple[float, dict[str, float]]:
    """Publish the bench's random motion (half speed) for `warmup` + `seconds`, spinning
    `watcher`; `at_measure()` is called when the measurement starts, after the warm-up.
    Returns the measured wall seconds and each process's CPU share over them."""
    times, commands = motion_commands(warmup + seconds + 1.0, 0.5, seed=9)
    start = time.monotonic()
    i, cpu0 = 0, None
    while time.monotonic() - start < warmup + seconds:
        elapsed = time.monotonic() - start
        while i < len(times) and times[i] <= elapsed:
            watcher.commands.publish(command_message(commands[i]))
            i += 1
        if cpu0 is None and elapsed >= warmup:
            measure_start = time.monotonic()
            cpu0 = {name: cpu_seconds(p.pid) for name, p in processes.items()}
            at_measure()
        watcher.spin_for(0.02)
    wall = time.monotonic() - measure_start
    return wall, {name: (cpu_seconds(p.pid) - cpu0[name]) / wall for name, p in processes.items()}


def run_bench(
    *,
    seconds: float = 60.0,
    warmup: float = 5.0,
    model: Path | None = None,
    channels: str = "per_axis",
    method: str | None = None,
    publish_period: float = 0.002,
    adapt: bool = False,
) -> dict:
    """Run sim_hand + denoiser (`method`; `adapt`: learning online, core.adapt) for
    `seconds` (after `warmup`); return the figures."""
    workdir = Path(tempfile.mkdtemp(prefix="egovib_live_bench_"))
    model = model or bench_model(workdir / "model.npz")
    method = resolve_method(NoiseModel.load(model), method)  # none given: the model's default
    group = NodeGroup(workdir / "logs")
    group.use_domain_here()
    watcher = None
    try:
        watcher = Watcher()
        received: list[bytes] = []
        arrival_ns: list[int] = []
        clock = time.time_ns

        def on_denoised(data: bytes) -> None:
            # what else waits is taken now (stamped now: an upper bound of its arrival), so
            # a burst costs this process one callback and its backlog adds no latency
            taken = drain(denoised, Imu, data)
            received.extend(taken)
            arrival_ns.extend([clock()] * len(taken))

        denoised = watcher.node.create_subscription(
            Imu, "accelerometer/denoised", on_denoised, sensor_qos(), raw=True
        )
        denoiser_diag: list[dict] = []

        def on_diag(msg) -> None:
            for status in msg.status:
                if status.name == "denoiser":
                    denoiser_diag.append(diagnostic_values(status))

        watcher.node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)

        params = {"model": str(model), "channels": channels, "method": method}
        if adapt:
            params["adapt"] = True
        den = group.start("denoiser", "denoiser", params)
        sim = group.start(
            "sim_hand",
            "sim_hand",
            {"seed": 3, "publish_ground_truth": False, "publish_period": publish_period},
        )
        group.wait_for_log("denoiser", "denoising")
        first: dict[str, int] = {}  # messages and reports in before the measurement

        def at_measure() -> None:
            first.update(received=len(received), diagnostics=len(denoiser_diag))

        wall, cpu = drive_motion(
            watcher, {"denoiser": den, "sim_hand": sim}, warmup, seconds, at_measure
        )
        group.check_alive("denoiser", "sim_hand")
        watcher.spin_for(1.5)  # last diagnostics
    finally:
        group.close()
        if watcher is not None:
            watcher.close()

    return denoised_figures(
        received[first["received"] :],
        arrival_ns[first["received"] :],
        denoiser_diag,
        first["diagnostics"],
        model=model,
        run={
            "duration_s": wall,
            "warmup_s": warmup,
            "channels": channels,
            "method": method,
            "adapt": adapt,
        },
        cpu=cpu,
        publish_period=publish_period,
    )


def denoised_figures(
    received: list[bytes],
    arrival_ns: list[int],
    denoiser_diag: list[dict],
    diag0: int,
    *,
    model: Path,
    run: dict,
    cpu: dict[str, float],
    publish_period: float,
) -> dict:
    """The live bench's figures from what the watcher received in the measured window (the
    denoised messages and their arrival times) and the denoiser's reports (`diag0`: the
    first of the window)."""
    channels, method = run["channels"], run["method"]
    stamps, _, bad = decode_imu_messages(received)
    arrival = np.asarray(arrival_ns[: len(stamps)], dtype=np.int64)
    latency_ms = (arrival - stamps) / 1e6
    # sim_hand stamps samples exactly at the nominal rate: the span received says how many
    # were sent.
    missing_out = int(round((stamps[-1] - stamps[0]) * 3000.0 / NS_PER_S)) + 1 - len(stamps)
    first, last = denoiser_diag[diag0 - 1] if diag0 else denoiser_diag[0], denoiser_diag[-1]
    node_drops = {
        key: int(last[key]) - int(first[key])
        for key in (
            "undecodable_messages",
            "samples_bad",
            "samples_out_of_order",
            "gap_filled_samples",
            "stream_restarts",
            "samples_withheld",
        )
    }
    node_latency = [
        (float(d["latency_p50_ms"]), float(d["latency_p99_ms"]))
        for d in denoiser_diag[diag0:]
        if d["latency_p50_ms"] != "nan"
    ]
    algorithmic = algorithmic_latency_ms(
        model, publish_period=publish_period, method=method, channels=channels
    )
    return {
        **run,
        "sim_hand_publish_period_s": publish_period,
        "cpu_cores": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0],
        "denoised_samples_received": int(len(stamps)),
        "denoised_rate_hz": (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / NS_PER_S),
        "dropped_samples": {
            "denoiser_input": node_drops,
            "denoised_output_gaps": missing_out,
            "undecodable": int(bad),
            "total": int(sum(node_drops.values()) + missing_out + bad),
        },
        "cpu_share": {name: round(value, 4) for name, value in cpu.items()},
        "adaptation": {
            key: int(last[key])
            for key in (
                "cells_learnt_online",
                "cells_new_online",
                "adapt_blocks_learnt",
                "adapt_blocks_gated",
                "adapt_contacts",
                "adapt_map_refits",
                "adapt_lines_found",
            )
            if key in last
        },
        "latency_ms": {
            **_percentiles(latency_ms),
            "block_length_ms": 64 / 3.0 if method == "paper" else None,
        },
        "latency_definition": "receive time of accelerometer/denoised in a subscriber process "
        "minus the "
        "header stamp (= raw sample time set by sim_hand); includes sim_hand's "
        f"{publish_period * 1e3:g} ms batching, the method's delay (paper: the 32-63 sample "
        "block delay), "
        "processing and two DDS hops",
        "algorithmic_latency_ms": {
            **algorithmic,
            "definition": "same batching and processing rule "
            "computed in one process: no transport or scheduling delay",
        },
        "denoiser_reported_latency_ms": {
            "p50_median_over_seconds": float(np.median([p for p, _ in node_latency]))
            if node_latency
            else None,
            "p99_max_over_seconds": float(np.max([q for _, q in node_latency]))
            if node_latency
            else None,
            "definition": "denoiser's wall clock: receive of an input message to publish of "
            "its denoised copy",
        },
    }


def calibration_bag(path: Path, seconds: float) -> Path:
    """No-contact random motion of the simulated hand (as the bench drives it): the bag the
    contact detectors take their thresholds from."""

    rec, _ = simulate_motion(duration_s=seconds, max_speed=0.5, seed=17)
    write_recording(path, rec)
    return path


def _percentiles(values) -> dict:
    if not len(values):
        return {"p50": None, "p99": None, "max": None}
    return {
        "p50": float(np.percentile(values, 50)),
        "p99": float(np.percentile(values, 99)),
        "max": float(np.max(values)),
    }


def contact_figures(
    events: list[tuple[int, int]],
    true_onsets_ns: np.ndarray,
    window_ns: tuple[int, int],
    diagnostics: dict,
) -> dict:
    """Detection and latency figures of one detector: `events` as (onset stamp, receive
    time) in ns, the true tap onsets, the measured window [start, end] (ns)."""

    start, end = window_ns
    onsets = true_onsets_ns[(true_onsets_ns >= start) & (true_onsets_ns <= end)]
    inside = [(o, r) for o, r in events if start <= o <= end]
    detected = np.array([o for o, _ in inside], np.int64)
    received = np.array([r for _, r in inside], np.int64)
    us = 1000  # matched in microseconds
    tp, fp, fn = match_events(detected // us, onsets // us, int(TOLERANCE_S * 1e9) // us)
    from_truth = []
    for onset, arrival in zip(detected, received):
        near = onsets[np.abs(onsets - onset) <= TOLERANCE_S * 1e9]
        if len(near):
            from_truth.append((arrival - near[0]) / 1e6)
    minutes = (end - start) / 60e9
    return {
        "threshold": float(diagnostics.get("threshold", "nan")),
        "taps": int(len(onsets)),
        "events": int(len(inside)),
        "f1": 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 1.0,
        "tp": tp,
        "fp": fp,
        "fn": fn,
        "false_alarms_per_min": fp / minutes if minutes > 0 else None,
        "latency_onset_stamp_to_event_received_ms": _percentiles((received - detected) / 1e6),
        "latency_true_onset_to_event_received_ms": _percentiles(np.array(from_truth)),
        "node_reported_latency_p99_ms": float(diagnostics.get("latency_p99_ms", "nan")),
    }


def run_contact_bench(
    *,
    seconds: float = 60.0,
    warmup: float = 5.0,
    model: Path | None = None,
    tap_rate_hz: float = 1.0,
    calibration_seconds: float = 30.0,
    publish_period: float = 0.002,
) -> dict:
    """sim_hand (taps) + denoiser + contact_detector on its output + contact_detector on the
    raw stream for `seconds` (after `warmup`); the figures (see the module doc)."""
    workdir = Path(tempfile.mkdtemp(prefix="egovib_live_bench_"))
    model = model or bench_model(workdir / "model.npz")
    no_contact = calibration_bag(workdir / "no_contact", calibration_seconds)
    detectors = {"contact_detector": "denoised", "contact_detector_raw": "raw"}
    group = NodeGroup(workdir / "logs")
    group.use_domain_here()
    watcher = None
    try:
        watcher = Watcher()
        clock = time.time_ns
        events: dict[str, list[tuple[int, int]]] = {name: [] for name in detectors}
        truth: list[bytes] = []
        diagnostics: dict[str, list[dict]] = {name: [] for name in ("denoiser", *detectors)}

        def on_event(name: str):
            return lambda msg: events[name].append((stamp_to_ns(msg.header.stamp), clock()))

        def on_diagnostics(msg) -> None:
            for status in msg.status:
                if status.name in diagnostics:
                    diagnostics[status.name].append(diagnostic_values(status))

        for name in detectors:
            topic = name.replace("detector", "events")
            watcher.node.create_subscription(Vector3Stamped, topic, on_event(name), 100)
        watcher.node.create_subscription(
            Imu, "accelerometer/contact", truth.append, sensor_qos(), raw=True
        )
        watcher.node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics, 10)
        for name, source in detectors.items():
            group.start(
                name,
                "contact_detector",
                {"model": str(model), "source": source, "calibration_bag": str(no_contact)},
                remap={"__node": name, "contact_events": name.replace("detector", "events")},
            )
        processes = {
            "denoiser": group.start("denoiser", "denoiser", {"model": str(model)}),
            "sim_hand": group.start(
                "sim_hand",
                "sim_hand",
                {
                    "seed": 3,
                    "tap_rate_hz": tap_rate_hz,
                    "publish_ego": False,
                    "publish_period": publish_period,
                },
            ),
            **{name: group.procs[name] for name in detectors},
        }
        group.wait_for_log("denoiser", "denoising")
        for name in detectors:  # each takes its threshold from the no-contact bag first
            group.wait_for_log(name, "contact events from", timeout=120.0)
        first: dict[str, int] = {}  # reports of each node in before the measurement
        window_ns = [0, 0]

        def at_measure() -> None:
            window_ns[0] = clock()
            first.update({name: len(d) for name, d in diagnostics.items()})

        wall, cpu = drive_motion(watcher, processes, warmup, seconds, at_measure)
        window_ns[1] = clock() - 100_000_000  # an event is out 10 ms after its crossing
        group.check_alive(*processes)
        watcher.spin_for(1.5)  # the last events and reports
    finally:
        group.close()
        if watcher is not None:
            watcher.close()

    run = {
        "duration_s": wall,
        "warmup_s": warmup,
        "tap_rate_hz": tap_rate_hz,
        "calibration_seconds": calibration_seconds,
        "sim_hand_publish_period_s": publish_period,
    }
    return contact_figures_of_run(run, cpu, truth, events, diagnostics, first, window_ns, detectors)


def contact_figures_of_run(
    run: dict,
    cpu: dict[str, float],
    truth: list[bytes],
    events: dict[str, list[tuple[int, int]]],
    diagnostics: dict[str, list[dict]],
    first: dict[str, int],
    window_ns: list[int],
    detectors: dict[str, str],
) -> dict:
    """The contact bench's figures: each detector's events against the taps of the
    ground-truth contact signal in the measured window, and the denoiser's input losses."""
    profile = load_profile()
    stamps, contact, _ = decode_imu_messages(truth)
    order = np.argsort(stamps, kind="stable")
    stamps, contact = stamps[order], contact[order]
    reference = combined_bandpassed(contact, profile)
    true_onsets = stamps[segment_contacts(reference, sample_rate_hz=profile.rate_hz).onsets]
    gaps = int(round((stamps[-1] - stamps[0]) * profile.rate_hz / 1e9)) + 1 - len(stamps)
    den_first, den_last = diagnostics["denoiser"][first["denoiser"]], diagnostics["denoiser"][-1]
    result = {
        **run,
        "cpu_cores": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0],
        "cpu_share": {name: round(value, 4) for name, value in cpu.items()},
        "denoiser_input_dropped": {
            key: int(den_last[key]) - int(den_first[key])
            for key in ("gap_filled_samples", "stream_restarts", "samples_bad")
        },
        "ground_truth_samples_missing_here": gaps,
        **{
            source: contact_figures(
                events[name],
                true_onsets,
                tuple(window_ns),
                diagnostics[name][-1] if diagnostics[name] else {},
            )
            for name, source in detectors.items()
        },
        "definition": "contact_detector on the denoiser's output (denoised) and on the raw "
        "stream (raw), thresholds from a no-contact bag of the same random motion at no "
        "false-alarm budget; taps from the ground-truth contact signal (+-10 ms); latency = "
        "receive time of the contact_events message in a subscriber process minus its header "
        "stamp (the onset sample's stamp, set by sim_hand from this machine's clock) or minus "
        "the true onset: sim_hand's batching, the denoiser's block (denoised), the detector's "
        "10 ms report delay and 2 ms batching, processing and DDS hops",
    }
    return result


def run_contacts(args: argparse.Namespace) -> int:
    result = run_contact_bench(
        seconds=args.seconds,
        warmup=args.warmup,
        model=Path(args.model) if args.model else None,
        tap_rate_hz=args.tap_rate,
        calibration_seconds=args.calibration_seconds,
        publish_period=args.publish_period,
    )
    with atomic_output(args.json) as tmp:
        tmp.write_text(json.dumps({"contacts": result}, indent=2) + "\n")
    print(
        f"{result['duration_s']:.0f} s, load average {result['load_average_1min']:.1f} on "
        f"{result['cpu_cores']} cores, CPU share {result['cpu_share']}, denoiser input "
        f"dropped {result['denoiser_input_dropped']}; wrote {args.json}"
    )
    for source in ("denoised", "raw"):
        figures = result[source]
        latency = figures["latency_onset_stamp_to_event_received_ms"]
        truth = figures["latency_true_onset_to_event_received_ms"]
        print(
            f"contacts on {source}: {figures['events']} events for {figures['taps']} taps, F1 "
            f"{figures['f1']:.2f}, false alarms {figures['false_alarms_per_min']:.1f}/min; onset "
            f"stamp -> event received p50 {latency['p50']:.1f} ms, p99 {latency['p99']:.1f} ms "
            f"(from the true onset p50 {truth['p50']:.1f}, p99 {truth['p99']:.1f} ms)"
        )
    return 0


def run(args: argparse.Namespace) -> int:
    if getattr(args, "contacts", False):
        return run_contacts(args)
    result = run_bench(
        seconds=args.seconds,
        warmup=args.warmup,
        channels=args.channels,
        method=args.method,
        model=Path(args.model) if args.model else None,
        publish_period=args.publish_period,
        adapt=getattr(args, "adapt", False),
    )
    with atomic_output(args.json) as tmp:
        tmp.write_text(json.dumps(result, indent=2) + "\n")
    lat, drops, cpu = result["latency_ms"], result["dropped_samples"], result["cpu_share"]
    algorithmic = result["algorithmic_latency_ms"]
    adapting = ", adapting" if result["adapt"] else ""
    print(
        f"{result['method']}{adapting}, {result['duration_s']:.0f} s at "
        f"{result['denoised_rate_hz']:.0f} Hz: "
        f"dropped {drops['total']}, denoiser CPU {cpu['denoiser']:.1%} of a core "
        f"(sim_hand {cpu['sim_hand']:.1%}), latency p50 "
        f"{lat['p50']:.1f} ms, p99 {lat['p99']:.1f} ms (algorithmic p50 "
        f"{algorithmic['p50']:.1f}, p99 {algorithmic['p99']:.1f} ms; load average "
        f"{result['load_average_1min']:.1f} on "
        f"{result['cpu_cores']} cores); wrote {args.json}"
    )
    return 0
