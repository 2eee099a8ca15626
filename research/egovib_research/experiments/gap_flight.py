"""The gap diagnosis on the real quadcopter flight (bags/quadcopter_ar8): no simulator exists.

    egovib real gap --bag bags/quadcopter_ar8 --out docs/gap_flight [--force]

The noise model is calibrated on one part of the flight (free motion, `calibrate_arrays`
with the quadcopter profile, and the joint lag the part shows, as `egovib calibrate` stores
it) and the gap diagnosis runs on the other part, in both directions (calibrate on the
first half and diagnose the second, and swapped), as `egovib gap` runs it: timing judged
against the model's own lag, the default tolerance.
Writes one report directory per direction (report.json, report.md, figures) and
OUT/summary.md; every verdict is reported with its confidence, whatever it is.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from egovib_research.experiments import core_arrays
from egovib_ros.bag import read_recording
from egovib_ros.core import calibrate_arrays, denoise_batch
from egovib_ros.core.filters import BandPass
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import BagError
from egovib_ros.gap.diagnose import DiagnosisOptions
from egovib_ros.gap.pipeline import diagnose_recording, reference_lag_for
from egovib_ros.gap.report import build_report, make_figures, render_markdown
from egovib_ros.gap.simref import with_own_lag
from egovib_ros.outputs import atomic_output, prepare_output
from egovib_ros.robot import load_profile, robot_option

#: The flight's usable span (s from the first sample): the last 0.15 s is a crash or hard
#: landing (motors cut, gyro saturating), not free motion (see docs/real_results.md).
FLIGHT_END_S = 16.85
SPLIT_S = 8.5


def _slice(rec, start_s: float, stop_s: float):
    """The part [start_s, stop_s) s after the first sample, without ground truth or commands."""

    t0 = int(rec.sensor_stamps_ns[0])
    lo, hi = t0 + int(start_s * NS_PER_S), t0 + int(stop_s * NS_PER_S)
    a, j = (
        slice(*np.searchsorted(s, [lo, hi])) for s in (rec.sensor_stamps_ns, rec.joint_stamps_ns)
    )
    return replace(
        rec,
        sensor_stamps_ns=rec.sensor_stamps_ns[a],
        sensor=rec.sensor[a],
        joint_stamps_ns=rec.joint_stamps_ns[j],
        joint_position=rec.joint_position[j],
        joint_velocity=rec.joint_velocity[j],
        contact=None,
        ego=None,
        denoised_stamps_ns=None,
        denoised=None,
        command_stamps_ns=None,
        commands=None,
    )


def calibrate_part(rec, profile, bag, part: tuple[float, float]):
    """The flight's `part` ((start, stop) s) and its free-motion noise model with the joint
    lag the part shows (as `egovib calibrate` stores it): (slice, model)."""

    cal = _slice(rec, *part)
    model, _ = calibrate_arrays(
        *core_arrays(cal),
        profile=profile,
        sweep="free",
        source=f"{bag} [{part[0]:g}, {part[1]:g}) s",
    )
    return cal, with_own_lag(model, cal)


def measure_joint_lag(
    cal,
    test,
    profile,
    joint_lag_s: float,
    *,
    calibration_lag_s: float | None = None,
    sweep: str = "free",
) -> dict:
    """Noise reduction on `test` (Recording) by the core denoiser calibrated on `cal`, with
    joint_lag_s 0 and with the given lag (in the calibration too, or `calibration_lag_s`
    there: 0 when only the test recording's joint states are off).

    Noise reduction = 20 log10 of the mean band-passed magnitude (summed axes) of the raw
    test recording over that of the denoised one (no events in either). Both runs are
    scored on the same samples, away from the ends by the lag: the blocks there have no
    joint state with the lag and pass through undenoised (counted in each run's
    `blocks_no_joint_state`; the core's warning about them is not printed). The lag advice
    applied with the core (docs/gap.md); `egovib gap` itself uses gap.advice.measure_advice."""

    runs = {}
    core_log = logging.getLogger("egovib_ros.core")
    level = core_log.level
    core_log.setLevel(logging.ERROR)
    try:
        for name, lag in (("without", 0.0), ("with", float(joint_lag_s))):
            cal_lag = lag if calibration_lag_s is None or name == "without" else calibration_lag_s
            model, _ = calibrate_arrays(
                cal.sensor_stamps_ns,
                cal.sensor,
                cal.joint_stamps_ns,
                cal.joint_velocity,
                profile=profile,
                joint_lag_s=cal_lag,
                sweep=sweep,
            )
            _, den, stats = denoise_batch(
                test.sensor_stamps_ns,
                test.sensor,
                test.joint_stamps_ns,
                test.joint_velocity,
                model,
                channels="combined",
                joint_lag_s=lag,
            )
            runs[name] = (lag, model, den[:, 0], stats)
    finally:
        core_log.setLevel(level)
    model = runs["without"][1]
    bp = BandPass(
        sample_rate_hz=model.sample_rate_hz,
        band_hz=model.band_hz,
        order=model.band_order,
        n_channels=1,
    )
    raw = bp.process(test.sensor.sum(axis=1)[None, :])[0]
    # filter start-up, and the blocks the lag leaves without joint states at either end
    skip = model.block_length * 4 + int(np.ceil(abs(joint_lag_s) * model.sample_rate_hz))
    scored = slice(skip, len(raw) - skip)
    noise_raw = float(np.mean(np.abs(raw[scored])))
    out = {}
    for name, (lag, _, den, stats) in runs.items():
        out[name] = {
            "joint_lag_s": lag,
            "noise_reduction_db": round(
                20.0 * np.log10(noise_raw / np.mean(np.abs(den[scored]))), 3
            ),
            "blocks_no_joint_state": int(stats.blocks_no_joint_state or 0),
        }
    out["scored_samples"] = len(raw) - 2 * skip
    out["gain_db"] = round(
        out["with"]["noise_reduction_db"] - out["without"]["noise_reduction_db"], 3
    )
    return out


def run_flight_gap(
    bag: str | Path, out_dir: str | Path, *, split_s: float = SPLIT_S, end_s: float = FLIGHT_END_S
) -> dict:
    profile = load_profile("quadcopter")
    rec = read_recording(bag, profile=profile, ground_truth=False, denoised=False)
    parts = {"first": (0.0, split_s), "second": (split_s, end_s)}
    out = Path(out_dir)
    summary = {
        "bag": str(bag),
        "profile": profile.name,
        "split_s": split_s,
        "end_s": end_s,
        "directions": {},
    }
    with atomic_output(out, directory=True, kind="report") as tmp:
        tmp.mkdir(parents=True)
        for calib, test in (("first", "second"), ("second", "first")):
            start = time.perf_counter()
            _, model = calibrate_part(rec, profile, bag, parts[calib])
            real = _slice(rec, *parts[test])
            diag = diagnose_recording(
                real,
                model,
                source=f"{bag} [{parts[test][0]:g}, {parts[test][1]:g}) s",
                options=DiagnosisOptions(reference_lag_s=reference_lag_for(model, None, None)),
            )
            name = f"calibrated_on_{calib}_half"
            sub = tmp / name
            sub.mkdir()
            report = build_report(
                diag,
                model_path=f"free-motion model of {bag} [{parts[calib][0]:g}, "
                f"{parts[calib][1]:g}) s",
                real_path=f"{bag} [{parts[test][0]:g}, {parts[test][1]:g}) s",
                figures={},
                runtime_s=0.0,
                robot=robot_option(profile),
            )
            # a model of the robot itself, not of our simulator ("the noise model is off by")
            report["inputs"]["model_kind"] = "recording"
            report["figures"] = make_figures(diag, report, sub)
            report["runtime_s"] = round(time.perf_counter() - start, 2)
            (sub / "report.json").write_text(json.dumps(report, indent=1))
            (sub / "report.md").write_text(render_markdown(report))
            deviance = {c["effect"]: c["deviance_reduction"] for c in diag.candidates}
            summary["directions"][name] = {
                "verdict": report["verdict"],
                "gap": report["gap"],
                "candidates": [
                    {
                        k: c[k]
                        for k in ("effect", "p_value", "heldout_gap", "block_mse_reduction_db2")
                    }
                    | {
                        "deviance_reduction": deviance[c["effect"]],
                        "shape_summary": c.get("shape_summary", ""),
                    }
                    for c in report["candidates"]
                ],
                "blocks": report["blocks"],
                "advice": report["advice"],
                "calibration_coverage": model.coverage(),
            }
        (tmp / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
        (tmp / "summary.md").write_text(render_summary(summary))
    return summary


def render_summary(summary: dict) -> str:
    lines = [
        "# Gap diagnosis on the real quadcopter flight",
        "",
        f"Bag `{summary['bag']}` (profile `{summary['profile']}`): the noise model is "
        "calibrated on one half of the flight (free motion, split at "
        f"{summary['split_s']} s, flight used up to {summary['end_s']} s) "
        "and the gap diagnosis runs on the other half, timing judged against the joint lag "
        "of the model's own half (as `egovib gap` does). Both directions are reported.",
        "",
        "| calibrated on | verdict | confidence | gap as-is | baseline | after effect | floor "
        "| left above floor |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, d in summary["directions"].items():
        g = d["gap"]
        left = d.get("advice", {}).get("unexplained", {}).get("above_floor_db")
        lines.append(
            f"| {name.replace('calibrated_on_', '').replace('_', ' ')} | "
            f"{d['verdict']['effect']} | {d['verdict']['confidence']} | "
            f"{g['sim_as_is']} | {g['after_refit']} | {g['after_effect']} | {g['floor']} | "
            f"{left} |"
        )
    lines.append("")
    for name, d in summary["directions"].items():
        if "advice" in d:
            lines.append(f"- {name.replace('_', ' ')}: **what to do:** {d['advice']['action']}")
    for name, d in summary["directions"].items():
        lines += [
            "",
            f"## {name.replace('_', ' ')}",
            "",
            "| candidate | p | deviance reduction | held-out gap | fitted shape |",
            "|---|---|---|---|---|",
        ]
        for c in d["candidates"]:
            lines.append(
                f"| {c['effect']} | {c['p_value']:.2g} | {c['deviance_reduction']:.4f} | "
                f"{c['heldout_gap']} | {c['shape_summary']} |"
            )
        lines += ["", f"Report: [{name}/report.md]({name}/report.md)"]
    lines.append("")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    if not Path(args.bag).exists():
        raise BagError(f"{args.bag}: no such bag (egovib real convert makes it)")
    prepare_output(args.out, force=args.force, inputs=[args.bag], kind="report")  # before work
    summary = run_flight_gap(args.bag, args.out, split_s=args.split)
    for name, d in summary["directions"].items():
        print(
            f"{name}: verdict {d['verdict']['effect']} "
            f"(confidence {d['verdict']['confidence']}), gap {d['gap']}"
        )
    print(f"wrote {args.out}/summary.md")
    return 0
