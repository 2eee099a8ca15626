"""`egovib gap validate --reality real`: known effects injected into a real recording.

The real flight (bags/quadcopter_ar8, profile `quadcopter`) is cut in two parts. A noise
model is calibrated on one part (free motion); into the *real data* of the other part a
known effect is injected, and `egovib gap`'s diagnosis must name it. Both directions.

Injections (all on the real recording; `t` = seconds from the part's start; the gains
multiply the real gyro sample by sample, with joint states interpolated to its stamps):

* timing, either sign: joint-state stamps re-stamped `s` seconds late (+) or early (-);
* drift: a warm-up gain 1 + s (1 - exp(-t / 2 s));
* position: a gain 1 + s (1 + cos(4 x1)) / 2 in motor 1's reported position x1 (the
  integral of its command, the only position this robot reports), a function of x1 as
  an angle (the same at x1 and x1 + 2 pi, as a position effect of a turning part is):
  its 4th harmonic, a period of 1.57, of which each part of the flight (x1 spans ~2.6
  and ~3.0) covers ~1.8 (the earlier period of 1.5 was not a function of the angle);
* acceleration: a gain 1 + s while motor 1 speeds up (d|u1|/dt above its 80th
  percentile), 1 otherwise (a direction of change, not a position);
* coupling: a gain exp(s z1 z3) with z = (u - median) / (90th - 10th percentile) of
  motors 1 and 3: louder when both are above or both below their typical command,
  quieter when one is above and the other below (a signed interaction).

The diagnosis runs as `egovib gap` runs it for a model calibrated on the robot itself:
timing is judged against the joint lag the calibration part shows (stored in the model as
`egovib calibrate` stores it; the motors' command-to-speed lag, about +30 ms), and each
injected effect is looked for in verdict.effects, on top of the flight's own other effects.
For every run also:

* the fitted joint lag against the untouched part's: a lag injection moves it by the
  injected amount (the joint-lag convention: joint states re-stamped s late move it by -s);
* the change from the untouched part to the injected one (gap.change, what `egovib gap
  --reference` reports): the injected effect should come first;
* where verdict.effects holds timing or drift, the advice's flags applied together with the
  user's model (calibrated for every method, as `egovib calibrate` does: the default method
  hybrid) on held-out data (advice.measure_advice).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
from scipy import signal

from egovib_research.experiments import core_arrays
from egovib_research.experiments.gap_flight import FLIGHT_END_S, SPLIT_S, _slice, calibrate_part
from egovib_ros.bag import read_recording
from egovib_ros.core.methods import calibrate_methods
from egovib_ros.core.timebase import NS_PER_S
from egovib_ros.errors import GapDataError
from egovib_ros.gap.advice import effect_actions, joint_lag_of, measure_advice, merged_settings
from egovib_ros.gap.change import diagnose_change
from egovib_ros.gap.diagnose import DiagnosisOptions
from egovib_ros.gap.features import build_table, joint_order
from egovib_ros.gap.pipeline import diagnose_recording, reference_lag_for
from egovib_ros.robot import load_profile

#: (effect, label, strengths): a ladder of four strengths per injection, the last well
#: beyond what a robot would show, so that the report can say from which strength each
#: effect is named on 8.5 s of real flight, or that it is not named at all.
INJECTIONS = (
    ("timing", "lag", (0.02, 0.04, 0.08, 0.15)),
    ("timing", "lead", (-0.02, -0.04, -0.08, -0.15)),
    ("drift", "warm-up", (0.3, 0.8, 2.0, 4.0)),
    ("position", "motor1 position", (0.3, 0.8, 2.0, 4.0)),
    ("acceleration", "motor1 speeding up", (0.3, 0.8, 2.0, 4.0)),
    ("coupling", "motors 1x3 signed", (0.3, 0.8, 2.0, 4.0)),
)
WARMUP_TAU_S = 2.0
#: The position injection's harmonic of motor 1's angle (a function of the angle mod 2 pi).
POSITION_HARMONIC = 4
SPEEDING_UP_QUANTILE = 0.8


def _at_accel(rec, values: np.ndarray) -> np.ndarray:
    return np.stack(
        [
            np.interp(rec.sensor_stamps_ns, rec.joint_stamps_ns, values[:, j])
            for j in range(values.shape[1])
        ],
        axis=1,
    )


def inject(rec, effect: str, strength: float):
    """The recording with one known effect injected into its real data."""
    if effect == "timing":
        return replace(rec, joint_stamps_ns=rec.joint_stamps_ns + int(round(strength * NS_PER_S)))
    t = (rec.sensor_stamps_ns - rec.sensor_stamps_ns[0]) / NS_PER_S
    cmd = _at_accel(rec, rec.joint_velocity)
    if effect == "drift":
        gain = 1.0 + strength * (1.0 - np.exp(-t / WARMUP_TAU_S))
    elif effect == "position":
        x = _at_accel(rec, rec.joint_position)[:, 0]
        gain = 1.0 + strength * 0.5 * (1.0 + np.cos(POSITION_HARMONIC * x))
    elif effect == "acceleration":
        dt = np.gradient(t)

        b, a = signal.butter(1, 10.0, fs=1.0 / float(np.median(dt)))
        rate = signal.filtfilt(b, a, np.gradient(np.abs(cmd[:, 0])) / np.maximum(dt, 1e-6))
        gain = 1.0 + strength * (rate > np.quantile(rate, SPEEDING_UP_QUANTILE))
    elif effect == "coupling":
        z = []
        for j in (0, 2):
            lo, mid, hi = np.quantile(cmd[:, j], [0.1, 0.5, 0.9])
            z.append((cmd[:, j] - mid) / max(hi - lo, 1e-6))
        gain = np.exp(strength * np.clip(z[0] * z[1], -3, 3))
    else:
        raise ValueError(f"unknown injection {effect!r}")
    return replace(rec, sensor=rec.sensor * gain[:, None])


#: A lag injection counts as moving the fitted joint lag by the injected amount within this.
LAG_TOLERANCE_MS = 8.0


def user_model(cal, model, source: str):
    """The model a user has after `egovib calibrate` (every method): the paper's table plus
    what cancel and hybrid need, fitted on the same part."""
    full, _ = calibrate_methods(model, *core_arrays(cal), source=source)
    return full


def run_real_validation(bag: str = "bags/quadcopter_ar8") -> dict:
    start = time.perf_counter()
    profile = load_profile("quadcopter")
    rec = read_recording(bag, profile=profile, ground_truth=False, denoised=False)
    parts = {"first": (0.0, SPLIT_S), "second": (SPLIT_S, FLIGHT_END_S)}
    results, directions = [], {}
    for calib, test in (("first", "second"), ("second", "first")):
        cal, model = calibrate_part(rec, profile, bag, parts[calib])  # with its own lag
        users = user_model(cal, model, f"{bag} {calib} part")
        own_lag = reference_lag_for(model, None, None)  # as `egovib gap` judges timing
        real = _slice(rec, *parts[test])
        name = f"calibrated on {calib} part, diagnosed {parts[test][0]:g}-{parts[test][1]:g} s"
        directions[name] = {"own_joint_lag_s": round(joint_lag_of(own_lag), 4)}
        reference = build_table(real, model, source=f"{name}: untouched")
        untouched = None
        cases = [("none", "untouched", 0.0)] + [
            (e, label, s) for e, label, strengths in INJECTIONS for s in strengths
        ]
        for effect, label, strength in cases:
            data = real if effect == "none" else inject(real, effect, strength)
            diag, entry = diagnose_case(data, model, own_lag, name, effect, label, strength)
            results.append(entry)
            if diag is None:
                continue
            if effect == "none":
                untouched = diag
                directions[name]["untouched"] = {
                    "verdict": diag.verdict,
                    "effects": entry["effects"],
                    "confidence": diag.confidence,
                    "fitted_joint_lag_s": entry["fitted_joint_lag_s"],
                }
            elif untouched is not None:
                _compare_with_untouched(entry, diag, untouched, reference)
            if any(e["effect"] in ("timing", "drift") for e in diag.effects):
                settings = merged_settings(effect_actions(diag))
                entry["advice"] = settings
                entry["applied"] = measure_advice(
                    data, users, diag, settings, joint_order(model, data.joint_names, name)
                )
    return {
        "schema": "egovib.gap_validation/3",
        "summary": _summary(results, directions, bag),
        "runs": results,
        "settings": {
            "command": "egovib gap validate --reality real",
            "reference_joint_lag_s": 0.0,
            "injections": [
                {"effect": e, "label": label, "strengths": list(s)} for e, label, s in INJECTIONS
            ],
            "warmup_tau_s": WARMUP_TAU_S,
            "position_harmonic": POSITION_HARMONIC,
            "lag_tolerance_ms": LAG_TOLERANCE_MS,
        },
        "runtime_s": round(time.perf_counter() - start, 1),
    }


def _compare_with_untouched(entry: dict, diag, untouched, reference) -> None:
    """The fitted joint lag moved from the untouched part's, and the change from the
    untouched part to this one (what `egovib gap --reference` says)."""
    moved = entry["fitted_joint_lag_s"] - joint_lag_of(untouched.lag_scan["timing_lag_s"])
    entry["joint_lag_moved_ms"] = round(1000.0 * moved, 1)
    if entry["truth"] == "timing":
        # joint states re-stamped s late: the joint lag moves by -s
        entry["lag_error_ms"] = round(1000.0 * (moved + entry["strength"]), 1)
    try:
        change = diagnose_change(replace(reference, contact=reference.contact.copy()), diag)
    except GapDataError as exc:
        entry["change"] = {"refused": str(exc)}
        return
    entry["change"] = {
        "effects": [c["effect"] for c in change.effects],
        "first_is_injected": bool(change.effects) and change.effects[0]["effect"] == entry["truth"],
        "parameters": [
            c["parameters"] for c in change.effects if c["effect"] in ("timing", "drift")
        ],
    }


def _summary(results: list[dict], directions: dict, bag: str) -> dict:
    """Per injection and direction: the strengths at which the injected effect is in
    verdict.effects (and first), the lag moved, the change named first, the advice applied."""
    injected = [r for r in results if r["truth"] != "none"]
    named_at, first_at, change_first_at = {}, {}, {}
    for _effect, label, _strengths in INJECTIONS:
        for name in directions:
            runs = [r for r in injected if r["direction"] == name and r["injection"] == label]
            named_at.setdefault(label, {})[name] = [r["strength"] for r in runs if r["in_effects"]]
            first_at.setdefault(label, {})[name] = [r["strength"] for r in runs if r["correct"]]
            change_first_at.setdefault(label, {})[name] = [
                r["strength"] for r in runs if r.get("change", {}).get("first_is_injected")
            ]
    lags = [r for r in injected if "lag_error_ms" in r]
    applied = [r["applied"] for r in results if r.get("applied", {}).get("gain_db") is not None]
    return {
        "reality": "real",
        "bag": bag,
        "directions": directions,
        "in_effects_at_strengths": named_at,
        "first_at_strengths": first_at,
        "change_first_at_strengths": change_first_at,
        "in_effects": round(float(np.mean([r["in_effects"] for r in injected])), 4),
        "accuracy_injected": round(float(np.mean([r["correct"] for r in injected])), 4),
        "change_first": round(
            float(np.mean([r.get("change", {}).get("first_is_injected", False) for r in injected])),
            4,
        ),
        "lag_errors_ms": [r["lag_error_ms"] for r in lags],
        "lags_within_tolerance": int(sum(abs(r["lag_error_ms"]) <= LAG_TOLERANCE_MS for r in lags)),
        "lag_runs": len(lags),
        "advice_applied_gain_db": [a["gain_db"] for a in applied],
        "untouched_correct": [r["verdict"] == "none" for r in results if r["truth"] == "none"],
        "n_runs": len(results),
    }


def diagnose_case(
    data, model, own_lag: float, direction: str, effect: str, label: str, strength: float
):
    """One run: (diagnosis or None, its entry). An injection so strong that most blocks
    look like contacts is refused by the diagnosis: a miss, not the end of the validation."""

    t0 = time.perf_counter()
    try:
        diag = diagnose_recording(
            data,
            model,
            source=f"{direction}: {label}",
            options=DiagnosisOptions(reference_lag_s=own_lag),
        )
    except GapDataError as exc:
        return None, _refused(direction, effect, label, strength, str(exc), t0)
    return diag, _run_entry(diag, direction, effect, label, strength, t0)


def _run_entry(diag, direction: str, effect: str, label: str, strength: float, t0: float) -> dict:
    by = {c["effect"]: c for c in diag.candidates}
    found = [e["effect"] for e in diag.effects]
    return {
        "direction": direction,
        "truth": effect,
        "injection": label,
        "strength": strength,
        "verdict": diag.verdict,
        "effects": found,
        "in_effects": effect in found,
        "effect_confidences": [e["confidence"] for e in diag.effects],
        "confidence": diag.confidence,
        "correct": diag.verdict == effect,
        "p_truth": by[effect]["p_value"] if effect in by else None,
        "deviance_gain_truth": by[effect]["deviance_reduction"] if effect in by else None,
        "runner_up": next(
            (c["effect"] for c in diag.candidates if c["effect"] != diag.verdict), None
        ),
        "gap": {
            "sim_as_is": round(diag.gaps["sim_as_is"], 4),
            "after_refit": round(diag.gaps["refit"], 4),
            "after_verdict": round(
                diag.gaps[diag.verdict] if diag.verdict != "none" else diag.gaps["refit"], 4
            ),
            "floor": round(diag.floor, 4),
        },
        "fitted_joint_lag_s": round(joint_lag_of(diag.lag_scan.get("timing_lag_s", 0.0)), 4),
        "seconds": round(time.perf_counter() - t0, 1),
    }


def _refused(direction: str, effect: str, label: str, strength: float, why: str, t0: float) -> dict:
    return {
        "direction": direction,
        "truth": effect,
        "injection": label,
        "strength": strength,
        "verdict": "refused",
        "effects": [],
        "in_effects": False,
        "refused": why,
        "confidence": None,
        "correct": False,
        "p_truth": None,
        "deviance_gain_truth": None,
        "runner_up": None,
        "gap": None,
        "fitted_joint_lag_s": None,
        "seconds": round(time.perf_counter() - t0, 1),
    }


def _at(values: list) -> str:
    return ", ".join(f"{v:g}" for v in values) if values else "-"


def render_markdown(report: dict) -> str:
    s = report["summary"]
    st = report["settings"]
    dirs = list(s["directions"])
    lines = [
        "# Gap diagnosis: known effects injected into a real flight (`--reality real`)",
        "",
        f"Bag `{s['bag']}` (real quadcopter flight, profile `quadcopter`): a free-motion model "
        "is calibrated on one part of the flight; into the real gyro and joint states of the "
        "other part one known effect is injected "
        "(research/egovib_research/experiments/gap_real_injection.py), on top of the flight's "
        "own effects; the diagnosis runs as `egovib gap` does for a model of the robot itself "
        "(timing judged against the joint lag of the model's own part, stored by "
        "`egovib calibrate`). Produced by `" + st["command"] + "` in "
        f"{report['runtime_s'] / 60:.1f} min.",
        "",
        f"Injected effect in verdict.effects: **{100 * s['in_effects']:.0f} %** of "
        f"{sum(1 for r in report['runs'] if r['truth'] != 'none')} runs (first: "
        f"{100 * s['accuracy_injected']:.0f} %); named first by the change from the untouched "
        f"part (`--reference`): **{100 * s['change_first']:.0f} %**. Lag injections: the fitted "
        f"joint lag moved by the injected amount within {st['lag_tolerance_ms']:g} ms in "
        f"**{s['lags_within_tolerance']} of {s['lag_runs']}** runs (errors "
        + ", ".join(f"{v:+.0f}" for v in s["lag_errors_ms"])
        + " ms).",
        "",
        "Strengths of the ladder ("
        + "; ".join(f"{e['label']} {_at(e['strengths'])}" for e in st["injections"])
        + ") at which the injected effect is in verdict.effects / first / first in the change:",
        "",
        "| injected | " + " | ".join(dirs) + " |",
        "|---" * (1 + len(dirs)) + "|",
    ]
    for label in s["in_effects_at_strengths"]:
        cells = [
            " / ".join(
                _at(s[key][label][d])
                for key in (
                    "in_effects_at_strengths",
                    "first_at_strengths",
                    "change_first_at_strengths",
                )
            )
            for d in dirs
        ]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append("")
    for name, d in s["directions"].items():
        u = d.get("untouched", {})
        lines += [
            f"## {name}",
            "",
            f"Untouched part: verdict.effects **{', '.join(u.get('effects') or ['none'])}** "
            f"(confidence {u.get('confidence')}); fitted joint lag "
            f"{1000 * (u.get('fitted_joint_lag_s') or 0.0):+.0f} ms; the robot's own joint lag "
            f"on the calibration part {1000 * d['own_joint_lag_s']:+.0f} ms.",
            "",
            "| injected | strength | verdict.effects | joint lag moved [ms] | change (first "
            "listed first) | advice applied: noise reduction without -> with |",
            "|---|---|---|---|---|---|",
        ]
        for r in report["runs"]:
            if r["direction"] != name:
                continue
            if r["verdict"] == "refused":
                lines.append(
                    f"| {r['injection']} | {r['strength']:g} | refused: {r['refused']} | | | |"
                )
                continue
            change = r.get("change", {})
            applied = r.get("applied") or {}
            app = (
                f"{applied['noise_reduction_without_db']:.2f} -> "
                f"{applied['noise_reduction_with_db']:.2f} dB ({applied['gain_db']:+.2f}; "
                f"{applied['applied_text']})"
                if applied.get("gain_db") is not None
                else ""
            )
            lines.append(
                f"| {r['injection']} | {r['strength']:g} | {', '.join(r['effects']) or 'none'} | "
                f"{r.get('joint_lag_moved_ms', '')} | "
                f"{', '.join(change.get('effects', [])) or change.get('refused', '')} | {app} |"
            )
        lines.append("")
    return "\n".join(lines)


__all__ = ["INJECTIONS", "inject", "run_real_validation", "render_markdown"]
