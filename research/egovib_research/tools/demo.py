"""`make demo`: the whole pipeline on ROS 2 nodes, end to end, in a few minutes.

1. Calibration: sim_hand + sweep_driver (superposition sweep, short dwell) + calibrator
   -> noise model.
   The calibrator fits every method at shutdown (as `egovib calibrate`), so the model
   runs the default method (hybrid) and carries the contact detector's thresholds.
2. Run: sim_hand with random smooth motion and taps + two denoisers side by side: the
   default one (no method given: hybrid, its drop-in output on accelerometer/denoised)
   and the paper's method (on accelerometer/denoised_paper) + bag_recorder -> bag with
   raw, ground truth and both live denoised topics.
3. Evaluation of the recorded run (egovib_ros.evaluation): noise reduction, peak SNR,
   tap retention and event F1 (the one contact detector), raw vs each live topic, and a
   Fig. 5-style figure of the default.

The nodes run as separate processes (the console scripts beside this Python) in a
private random ROS domain with localhost-only discovery, so nothing else on the
network sees or disturbs them (egovib_research.tools.orchestration). Usage: `egovib demo
[--out DIR]` (or python -m egovib_research.tools.demo).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from egovib_research.experiments import paper_figures as figures
from egovib_research.tools.orchestration import NodeGroup, reliable_input
from egovib_research.tools.watcher import Watcher
from egovib_ros.bag import BagReader, decode_imu, read_recording
from egovib_ros.bag.recording import bag_topic_names
from egovib_ros.core import NoiseModel
from egovib_ros.evaluation import metrics
from egovib_ros.evaluation.evaluate import evaluate_recording
from egovib_ros.nodes.convert import command_message
from egovib_ros.outputs import atomic_output, prepare_output
from egovib_ros.sim import motion_commands

BAG_TOPICS = bag_topic_names()  # the PR2 hand's

PR2_INPUT = ("/accelerometer/raw", "/joint_states")  # the simulated hand's streams (PR2 profile)
PAPER_TOPIC = (
    "accelerometer/denoised_paper"  # the paper's method's live output, beside the default's
)


def calibrate(
    group: NodeGroup, watcher: Watcher, model: Path, *, dwell: float, settle: float
) -> None:
    print(
        f"[1/3] calibration: superposition sweep, 41 cells x "
        f"({settle:g} s settle + {dwell:g} s dwell)",
        flush=True,
    )
    group.start(
        "calibrator",
        "calibrator",
        {
            "output": str(model),
            "grid": "superposition",
            "resume": False,
            **reliable_input(*PR2_INPUT),
        },
    )
    group.start("sim_hand_sweep", "sim_hand", {"seed": 1, "publish_ground_truth": False})
    group.wait_for_log("calibrator", "calibrating")
    driver = group.start(
        "sweep_driver", "sweep_driver", {"grid": "superposition", "dwell": dwell, "settle": settle}
    )
    last_print = 0.0
    while driver.poll() is None:
        watcher.spin_for(0.5)
        group.check_alive("calibrator", "sim_hand_sweep")
        if time.monotonic() - last_print > 10:
            last_print = time.monotonic()
            print(
                f"      sweep: {watcher.status.get('sweep_driver', 'starting')}; "
                f"calibrator: {watcher.status.get('calibrator', 'starting')}",
                flush=True,
            )
    if driver.returncode != 0:
        raise RuntimeError(f"sweep_driver failed:\n{group.log('sweep_driver')[-3000:]}")
    group.stop("sim_hand_sweep")
    watcher.spin_for(0.5)
    # at shutdown the calibrator also fits hybrid and the detector's thresholds (seconds)
    if group.stop("calibrator", timeout=300.0) != 0 or not model.exists():
        raise RuntimeError(f"calibrator failed:\n{group.log('calibrator')[-3000:]}")
    for line in group.log("calibrator").strip().splitlines()[-2:]:
        print("      " + line, flush=True)  # whole (was cut at 300 characters, mid-dict)


def run_motion(
    group: NodeGroup,
    watcher: Watcher,
    model: Path,
    bag: Path,
    *,
    seconds: float,
    max_speed: float,
    tap_rate_hz: float,
    seed: int,
) -> None:
    print(
        f"[2/3] run: {seconds:g} s of random motion (max {max_speed:.0%} speed) with taps at "
        f"{tap_rate_hz:g} Hz; the default denoiser and the paper's side by side, and recorder",
        flush=True,
    )
    # Start order: denoisers, then the recorder matched to their outputs, then the hand,
    # which waits until its streams are subscribed, so that the bag holds every sample.
    group.start("denoiser", "denoiser", {"model": str(model), **reliable_input(*PR2_INPUT)})
    group.start(
        "denoiser_paper",
        "denoiser",
        {"model": str(model), "method": "paper", **reliable_input(*PR2_INPUT)},
        remap={"__node": "denoiser_paper", "accelerometer/denoised": PAPER_TOPIC},
    )
    for name in ("denoiser", "denoiser_paper"):
        group.wait_for_log(name, "denoising")
    # Recorded: what the evaluation needs (the ego-only ground truth is left out to spare CPU).
    group.start(
        "bag_recorder",
        "bag_recorder",
        {
            "output": str(bag),
            "topics": [
                "joint_states",
                "accelerometer/raw",
                "accelerometer/denoised",
                PAPER_TOPIC,
                "accelerometer/contact",
                "hand_velocity_controller/commands",
            ],
        },
    )
    for topic in ("/accelerometer/denoised", f"/{PAPER_TOPIC}"):
        group.wait_for_log("bag_recorder", f"{topic}: subscribed")
    group.start(
        "sim_hand",
        "sim_hand",
        {"seed": seed, "tap_rate_hz": tap_rate_hz, "publish_ego": False, "wait_for_subscribers": 1},
    )
    for topic in ("/accelerometer/raw", "/accelerometer/contact", "/joint_states"):
        group.wait_for_log("bag_recorder", f"{topic}: subscribed")
    times, commands = motion_commands(seconds, max_speed, seed)
    start = time.monotonic()
    last_print = start
    for t, command in zip(times, commands):
        watcher.commands.publish(command_message(command))
        watcher.spin_for(max(0.0, start + t - time.monotonic()))
        if time.monotonic() - last_print > 10:
            last_print = time.monotonic()
            group.check_alive("denoiser", "denoiser_paper", "bag_recorder", "sim_hand")
            print(
                f"      {t:4.0f} s: denoiser {watcher.status.get('denoiser', 'starting')}",
                flush=True,
            )
    watcher.commands.publish(command_message([0.0, 0.0]))
    group.stop("sim_hand")
    watcher.spin_for(1.0)  # the denoisers flush their last samples after 0.5 s idle
    group.stop("denoiser")
    group.stop("denoiser_paper")
    if group.stop("bag_recorder") != 0:
        raise RuntimeError(
            f"bag_recorder lost messages or failed:\n{group.log('bag_recorder')[-3000:]}"
        )
    print("      " + group.log("bag_recorder").strip().splitlines()[-1][:400], flush=True)


def read_live_recording(bag: Path):
    """read_recording for a bag recorded live: the recorder subscribed to each topic at a
    slightly different moment, so raw and ground truth are cut to the stamps they share."""

    rec = read_recording(bag, ground_truth=False, denoised=True)
    truth = {}
    with BagReader(bag) as reader:
        topics = {
            BAG_TOPICS[key]: key for key in ("contact", "ego") if BAG_TOPICS[key] in reader.topics
        }
        parts = {key: [] for key in topics.values()}
        for batch in reader.batches(topics):
            for topic, messages in batch.messages.items():
                parts[topics[topic]].append(decode_imu(messages))
    for key, decoded in parts.items():
        stamps = np.concatenate([s for s, _ in decoded])
        order = np.argsort(stamps, kind="stable")
        truth[key] = (stamps[order], np.concatenate([v for _, v in decoded])[order])
    keep = np.ones(len(rec.sensor_stamps_ns), bool)
    for stamps, _ in truth.values():
        keep &= np.isin(rec.sensor_stamps_ns, stamps)
    first, last = np.flatnonzero(keep)[[0, -1]]
    keep[:first] = keep[last + 1 :] = False
    stamps = rec.sensor_stamps_ns[keep]
    values = {key: v[np.searchsorted(s, stamps)] for key, (s, v) in truth.items()}
    joints = (rec.joint_stamps_ns >= stamps[0]) & (rec.joint_stamps_ns <= stamps[-1])
    return dataclasses.replace(
        rec,
        sensor_stamps_ns=stamps,
        sensor=rec.sensor[keep],
        **values,
        joint_stamps_ns=rec.joint_stamps_ns[joints],
        joint_position=rec.joint_position[joints],
        joint_velocity=rec.joint_velocity[joints],
    )


LIVE_KEYS = (
    "noise_reduction_db",
    "peak_snr_raw_db",
    "peak_snr_denoised_db",
    "tap_retention",
    "f1",
    "samples_missing",
    "rms_difference_vs_batch",
)


def evaluate(model_path: Path, bag: Path, out: Path) -> dict:
    print("[3/3] evaluation of the recorded run", flush=True)
    model = NoiseModel.load(model_path)
    rec = read_live_recording(bag)
    report = evaluate_recording(rec, model, methods=["paper"], keep_signals=True)
    signals = report.pop("signals")
    figure = figures.fig5(
        {**report, "signals": signals},
        out / "demo_fig5.png",
        title=f"make demo: the default ({report['method']}, drop-in output band-passed), "
        f"offline on the recorded raw signal",
    )
    # the paper's live topic, scored the same way (the recording with it as the denoised one)
    with BagReader(bag) as reader:
        parts = [
            decode_imu(b.messages[f"/{PAPER_TOPIC}"]) for b in reader.batches([f"/{PAPER_TOPIC}"])
        ]
    stamps = np.concatenate([p[0] for p in parts])
    values = np.concatenate([p[1] for p in parts])
    order = np.argsort(stamps, kind="stable")
    paper_rec = dataclasses.replace(rec, denoised_stamps_ns=stamps[order], denoised=values[order])
    paper = evaluate_recording(paper_rec, model, methods=["paper"])
    summary = {
        "bag": str(bag),
        "model": str(model_path),
        "figure": str(figure),
        "n_taps": report["n_taps"],
        "default_method": report["method"],
        "live_default": {k: report["methods"]["bag_denoised"].get(k) for k in LIVE_KEYS},
        "live_paper": {k: paper["methods"]["bag_denoised"].get(k) for k in LIVE_KEYS},
        "offline": {
            name: {
                k: report["methods"][name].get(k)
                for k in (
                    "noise_reduction_db",
                    "peak_snr_denoised_db",
                    "tap_retention",
                    "f1",
                    "delay_ms",
                )
            }  # fmt: skip
            for name in ("default", "paper")
        },
        "f1_raw": report["f1_raw"],
    }
    with atomic_output(out / "demo_evaluation.json") as tmp:
        tmp.write_text(json.dumps(metrics.json_safe(summary), indent=2) + "\n")
    return summary


def clear_previous_run(out: Path) -> None:
    """Remove what a previous demo run left in `out` - only if it is recognisably ours
    (outputs.prepare_output); anything else there is refused, never deleted."""
    outputs = {
        "noise_model.npz": "model",
        "run_bag": "bag",
        "demo_evaluation.json": "json",
        "demo_fig5.png": "file",
    }
    for name, kind in outputs.items():
        prepare_output(out / name, force=True, kind=kind)
    for name in outputs:
        path = out / name
        if path.is_dir():
            shutil.rmtree(path)
        elif path.exists():
            path.unlink()


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    model, bag = out / "noise_model.npz", out / "run_bag"
    clear_previous_run(out)
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    group = NodeGroup(out / "logs")
    group.use_domain_here()
    print(
        f"egovib_ros demo: ROS_DOMAIN_ID={group.domain_id} (localhost only), output in {out}/",
        flush=True,
    )
    watcher = None
    try:
        watcher = Watcher()
        calibrate(group, watcher, model, dwell=args.dwell, settle=args.settle)
        run_motion(
            group,
            watcher,
            model,
            bag,
            seconds=args.seconds,
            max_speed=args.max_speed,
            tap_rate_hz=args.taps,
            seed=args.seed,
        )
    except (RuntimeError, KeyboardInterrupt) as exc:
        print(f"demo: {exc}", file=sys.stderr)
        return 1
    finally:
        group.close()
        if watcher is not None:
            watcher.close()
    summary = evaluate(model, bag, out)
    print(f"\nResult ({summary['n_taps']} taps, {time.monotonic() - started:.0f} s in all):")
    for label, key in ((f"default ({summary['default_method']})", "live_default"),
                       ("paper's method", "live_paper")):  # fmt: skip
        live = summary[key]
        print(
            f"  live {label:17s}: noise reduction {live['noise_reduction_db']:.1f} dB, "
            f"peak SNR {live['peak_snr_raw_db']:.1f} -> {live['peak_snr_denoised_db']:.1f} dB, "
            f"tap retention {live['tap_retention']:.2f}, event F1 {summary['f1_raw']:.2f} raw -> "
            f"{live['f1']:.2f}, samples missing {live['samples_missing']}"
        )
    offline = summary["offline"]
    print(
        f"  offline, same bag  : the default {offline['default']['noise_reduction_db']:.1f} dB "
        f"in {offline['default']['delay_ms']:.1f} ms, the paper's "
        f"{offline['paper']['noise_reduction_db']:.1f} dB in {offline['paper']['delay_ms']:.1f} ms"
    )
    print(
        f"  model:  {model}\n  bag:    {bag}\n  figure: {summary['figure']}\n"
        f"  report: {out / 'demo_evaluation.json'}\n  logs:   {out / 'logs'}/"
    )
    return 0
