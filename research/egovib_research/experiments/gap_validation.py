"""`egovib gap validate`: blind validation of the diagnosis on "real" bags with hidden effects.

The noise model is always calibrated on OUR simulator (superposition sweep, as a user
would).  The "real" recordings come from either

* `--reality sim`: our simulator itself, with one effect at a random strength per bag,
  plus two extra `none` classes: a simulator 6 dB louder than the "real" robot, and a
  simulator whose spectra differ in shape (tones moved, a resonance missing, a
  structural band shifted) from the effect-free "real" robot;
* `--reality alt`: the independent alternate-reality generator (egovib_research.altreality),
  which shares no code or formulas with the simulator and has each effect in its own
  functional forms;
* `--reality third`: the third hand (egovib_research.thirdhand), written from the effect
  vocabulary alone by someone who had read neither the simulator nor the alternate reality:
  its own drives, housing modes, trapezoidal moves, and the interaction forms the other two
  lack (one joint's lines scaled by another's speed, by magnitude and signed; a line that
  sounds only while both joints move);
* `--reality real`: known effects injected into one part of a real flight, the model
  calibrated on the other part (experiments/gap_real_injection.py).

Every effect is drawn in each of its functional forms (FORMS: signed or not,
multiplicative or additive, tonal or broadband), `seeds` recordings per form with a
random strength from the reality's STRENGTH_RANGES and a random seed; ground truth is
stripped and the effect is never passed on, so the diagnosis sees only joint_states and
accelerometer/raw.  A strength ladder below each range, per form, shows where detection
stops (reported, not hidden).
"""

from __future__ import annotations

import copy
import json
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from egovib_research.altreality import simulate_alt_motion
from egovib_research.experiments import core_arrays
from egovib_research.experiments.gap_real_injection import render_markdown as render_real
from egovib_research.experiments.gap_real_injection import run_real_validation
from egovib_research.thirdhand import FORMS as THIRD_FORMS
from egovib_research.thirdhand import simulate_third_motion
from egovib_ros.core import NoiseModel, calibrate_arrays
from egovib_ros.gap.diagnose import DiagnosisOptions
from egovib_ros.gap.effects import EFFECTS
from egovib_ros.gap.pipeline import diagnose_recording
from egovib_ros.gap.simref import simulator_reference_lag
from egovib_ros.outputs import atomic_output
from egovib_ros.sim import SimParams, simulate_motion, simulate_sweep
from egovib_ros.viz import pyplot, save_figure

REALITIES = ("sim", "alt", "third", "real")
#: The functional forms of each effect the blind runs draw from, per generated reality (the
#: generators' own form names; timing "lag"/"lead" are the stamp shift of either sign).
#: Together: position 5 forms, coupling 4, acceleration 4, timing 3, drift 5 (docs/gap.md).
FORMS = {
    "sim": {
        "position": ("gain", "closing_rub"),
        "coupling": ("broadband", "signed"),
        "acceleration": ("broadband", "speeding_up"),
        "timing": ("lag", "lead", "filtered"),
        "drift": ("linear", "warmup", "additive"),
    },
    "alt": {
        "position": ("spot", "end", "closing"),
        "coupling": ("intermod", "signed"),
        "acceleration": ("clicks", "braking"),
        "timing": ("lag", "lead", "filtered"),
        "drift": ("step", "wear"),
    },
    "third": THIRD_FORMS,
}
#: What each form is (for the reports).
FORM_TEXT = {
    "gain": "multiplicative: wrist x (1 + s cos angle), gripper linear in gap (unsigned, tonal)",
    "closing_rub": "additive broadband on the gripper path only while closing (signed)",
    "coupling/broadband": "additive broadband ~ product of speeds (unsigned)",
    "acceleration/broadband": "additive broadband ~ |acceleration| (unsigned)",
    "signed": "wrist lines x exp(+-s ...): louder same direction, quieter opposite (signed, tonal)",
    "speeding_up": "source gain only while the joint speeds up (signed, multiplicative)",
    "lag": "joint-state stamps late",
    "lead": "joint-state stamps early",
    "filtered": "reported velocity through a first-order low-pass (dispersive lag)",
    "linear": "gain 1 + s t / 60 s (multiplicative)",
    "warmup": "gain 1 + 2 s (1 - exp(-t / 20 s)) (multiplicative, saturating)",
    "additive": "wear broadband added, growing with time (additive)",
    "spot": "tight spot once per wrist turn (multiplicative, tonal)",
    "end": "rub near the gripper's closed end (additive broadband)",
    "closing": "rub only while the gripper closes (signed, additive)",
    "intermod": "intermodulation lines f_w +- f_g (additive, tonal, unsigned)",
    "clicks": "backlash clicks at reversals (impulsive)",
    "braking": "broadband while a joint slows down (signed, additive)",
    "step": "warm-up step, logistic, up or down (multiplicative)",
    "wear": "grinding added, growing with time (additive)",
    "twice": "wrist lines x (1 + 0.41 s (1 + cos 2(angle - phase)) / 2): twice a turn",
    "open_end": "gripper lines louder towards the open end of its travel (multiplicative)",
    "sector": "hiss added while the wrist turns through a 1 rad sector (additive)",
    "line_gain": "wrist lines x (1 + 0.41 s |v_gripper| / top): one joint's lines scaled by "
    "another's speed (magnitude)",
    "line_signed": "gripper lines x exp(0.35 s sign(v_wrist) |v_wrist| / top): scaled by "
    "another's speed (signed)",
    "together": "a line at a fixed 560 Hz mode, only while both joints move",
    "ringing": "a housing mode rung by the jerk of speed changes (additive, impulsive)",
    "torque": "wrist lines x (1 + 0.41 s |a_wrist| / a_ref): torque ripple (multiplicative)",
    "polled": "joint states published every 8 ms, each the last reading (0-8 ms old), "
    "stamped on publishing, plus s",
    "cooldown": "level x (1 - s (1 - exp(-t / 30 s))): falls and levels off",
    "gripper_wear": "gripper sources x (1 + s t / T): one joint's level rises",
    "cycle": "level x (1 + s sin(2 pi t / (0.8 T))): a thermal cycle",
}
#: Strength ranges of the blind runs (INTERFACES.md section 5 units: timing in s, sign random).
STRENGTH_RANGES = {
    "position": (0.2, 0.5),
    "coupling": (2.0, 5.0),
    "acceleration": (4.0, 10.0),
    "timing": (0.015, 0.05),
    "drift": (0.2, 0.6),
}
#: The alternate reality's own units (egovib_research.altreality): strength 1 of position,
#: coupling and acceleration makes the vibration ~3 dB louder where the effect acts (see
#: docs/gap_validation_alt.md, "audibility"); drift = relative level change of the
#: warm-up step (0.4 = 2.9 dB); timing in s, random sign.
ALT_STRENGTH_RANGES = {
    "position": (1.0, 2.5),
    "coupling": (1.0, 2.5),
    "acceleration": (1.0, 2.5),
    "timing": (0.012, 0.04),
    "drift": (0.4, 1.0),
}
#: The third hand's units (egovib_research.thirdhand): position, coupling, acceleration: s = 1
#: makes the affected source ~3 dB louder where the effect is largest; drift: the relative
#: level change (0.3 = 2.3 dB); timing in s, random sign.
THIRD_STRENGTH_RANGES = {
    "position": (1.0, 2.5),
    "coupling": (1.0, 2.5),
    "acceleration": (1.0, 2.5),
    "timing": (0.012, 0.04),
    "drift": (0.2, 0.5),
}
LADDER_FRACTIONS = (0.25, 0.5)
MISCALIBRATED = "none (sim 6 dB too loud)"
SHAPE_DIFFERS = "none (sim shape differs)"
MOTION_MAX_SPEED = 0.8
TAP_RATE_HZ = 0.5
CALIBRATION_DWELL_S = 4.0

_WORKER: dict = {}


def strength_ranges(reality: str) -> dict:
    return {"alt": ALT_STRENGTH_RANGES, "third": THIRD_STRENGTH_RANGES}.get(
        reality, STRENGTH_RANGES
    )


def none_classes(reality: str) -> list[str]:
    return ["none", MISCALIBRATED, SHAPE_DIFFERS] if reality == "sim" else ["none"]


def shape_differs_params(params=None):
    """A simulator whose spectra differ in shape: gear tones moved, the wrist resonance missing,
    the gripper's structural band shifted (the "real" robot stays the default simulator)."""

    out = copy.deepcopy(params if params is not None else SimParams.load())
    out.wrist.line_hz_per_unit *= 1.25
    out.wrist.line_orders = [1.5, 2.5, 4.0]
    out.wrist.resonance_gain = 0.0
    out.gripper.line_orders = [1.25, 1.75, 2.5]
    out.gripper.path_band_hz = [420.0, 700.0]
    return out


def calibrate_sim_model(*, dwell_s: float = CALIBRATION_DWELL_S, seed: int = 100, params=None):
    """Noise model of the (effect-free) simulator from a superposition sweep,
    as `egovib calibrate` would."""

    rec, _ = simulate_sweep(
        grid="superposition", dwell_s=dwell_s, settle_s=0.5, seed=seed, params=params
    )
    model, _ = calibrate_arrays(
        *core_arrays(rec),
        sweep="superposition",
        source="simulated superposition sweep (gap validate)",
    )
    return model


def quieter_params(params, factor: float = 0.5):
    """Simulator parameters with every joint vibration mechanism scaled by `factor`
    (0.5 = -6 dB)."""
    out = copy.deepcopy(params)
    for joint in (out.wrist, out.gripper):
        joint.line_amps = [a * factor for a in joint.line_amps]
        joint.friction_coulomb *= factor
        joint.friction_viscous *= factor
    return out


def plan_runs(
    seeds: int, *, ladder: bool, master_seed: int = 2026, reality: str = "sim", extra_none: int = 0
) -> list[dict]:
    """The blind runs: (class, form, strength, seed) drawn reproducibly from `master_seed`;
    every form of every effect `seeds` times; the ladder one run per form and rung;
    `extra_none` more bags of every `none` class (drawn last)."""
    ranges = strength_ranges(reality)
    rng = np.random.default_rng(
        [master_seed, REALITIES.index(reality)] if reality != "sim" else master_seed
    )
    runs = []

    def add(run: dict, **after) -> None:
        runs.append({**run, "seed": int(rng.integers(1, 2**31)), **after})

    def add_nones() -> None:
        for label in none_classes(reality):
            add({"truth": label, "strength": 0.0})

    for _ in range(seeds):
        add_nones()
        for effect in EFFECTS:
            lo, hi = ranges[effect]
            for form in FORMS[reality][effect]:
                s = float(rng.uniform(lo, hi))
                if form == "lead":
                    s = -s
                add({"truth": effect, "form": form, "strength": round(s, 4)})
    if ladder:
        for effect in EFFECTS:
            for form in FORMS[reality][effect]:
                for frac in LADDER_FRACTIONS:
                    s = ranges[effect][0] * frac * (-1 if form == "lead" else 1)
                    add({"truth": effect, "form": form, "strength": round(s, 5)}, ladder=True)
    for _ in range(extra_none):
        add_nones()
    for r in runs:
        r["reality"] = reality
    return runs


def _init_worker(model_paths: dict, reference_lags: dict) -> None:
    _WORKER["models"] = {k: NoiseModel.load(p) for k, p in model_paths.items()}
    _WORKER["reference_lags"] = dict(reference_lags)


def make_recording(run: dict, duration_s: float):
    """The blind "real" recording of a run (ground truth stripped) and its truth dict."""
    truth_label = run["truth"]
    effects = {} if truth_label.startswith("none") else {truth_label: run["strength"]}
    form = run.get("form")
    generator_form = "stamps" if form in ("lag", "lead") else form
    if run.get("reality", "sim") == "third":
        rec, truth = simulate_third_motion(
            duration_s=duration_s,
            effects=effects,
            seed=run["seed"],
            tap_rate_hz=TAP_RATE_HZ,
            forms={truth_label: form} if form else None,
            max_speed=MOTION_MAX_SPEED,
        )
    elif run.get("reality", "sim") == "alt":
        rec, truth = simulate_alt_motion(
            duration_s=duration_s,
            effects=effects,
            seed=run["seed"],
            tap_rate_hz=TAP_RATE_HZ,
            forms={truth_label: generator_form} if form else None,
        )
    else:
        params = SimParams.load()
        if form:
            params.effect_forms = {truth_label: generator_form}
        if truth_label == MISCALIBRATED:
            params = quieter_params(params)
        rec, truth = simulate_motion(
            duration_s=duration_s,
            max_speed=MOTION_MAX_SPEED,
            tap_rate_hz=TAP_RATE_HZ,
            effects=effects,
            seed=run["seed"],
            params=params,
        )
    rec.contact = rec.ego = None
    return rec, truth


def run_one(run: dict, duration_s: float) -> dict:
    """Make one blind "real" bag and diagnose it; returns the run with the outcome."""

    start = time.perf_counter()
    rec, truth = make_recording(run, duration_s)
    key = "shape" if run["truth"] == SHAPE_DIFFERS else "sim"
    # Blind: the diagnosis gets no ground truth and no effect names.
    diag = diagnose_recording(
        rec,
        _WORKER["models"][key],
        source=f"blind run seed {run['seed']}",
        options=DiagnosisOptions(reference_lag_s=_WORKER["reference_lags"][key]),
    )
    label = "none" if run["truth"].startswith("none") else run["truth"]
    extra = {k: v for k, v in truth.items() if k.startswith(("position_", "drift_"))}
    found = [e["effect"] for e in diag.effects]
    return {
        **run,
        **({"truth_details": extra} if extra else {}),
        "verdict": diag.verdict,
        "effects": found,
        "correct": diag.verdict == label,
        # the forward selection: the truth anywhere in verdict.effects, and what else it named
        "in_effects": label in found if label != "none" else not found,
        "extra_effects": [e for e in found if e != label],
        "confidence": diag.confidence,
        "gap": {
            "sim_as_is": round(diag.gaps["sim_as_is"], 4),
            "after_refit": round(diag.gaps["refit"], 4),
            "after_truth_effect": round(diag.gaps[label], 4) if label != "none" else None,
            "after_verdict": round(
                diag.gaps[diag.verdict] if diag.verdict != "none" else diag.gaps["refit"], 4
            ),
            "floor": round(diag.floor, 4),
        },
        "p_values": {c["effect"]: c["p_value"] for c in diag.candidates},
        "gains_db2": {c["effect"]: c["block_mse_reduction_db2"] for c in diag.candidates},
        "deviance_gains": {c["effect"]: c["deviance_reduction"] for c in diag.candidates},
        "seconds": round(time.perf_counter() - start, 2),
    }


def summarise(results: list[dict], reality: str = "sim") -> dict:
    """Confusion matrix, accuracy, false positives on none, shrink per effect, detectability."""
    labels = ["none"] + list(EFFECTS)
    ranges = strength_ranges(reality)
    blind = [r for r in results if not r.get("ladder")]
    rows = none_classes(reality) + list(EFFECTS)
    confusion = {t: {p: 0 for p in labels} for t in rows}
    for r in blind:
        confusion[r["truth"]][r["verdict"]] += 1
    per_class = {}
    for t in rows:
        rs = [r for r in blind if r["truth"] == t]
        per_class[t] = round(float(np.mean([r["correct"] for r in rs])), 4) if rs else None
    nones = [r for r in blind if r["truth"].startswith("none")]
    effects_only = [r for r in blind if not r["truth"].startswith("none")]
    shrink = {}
    for e in EFFECTS:
        rs = [r for r in blind if r["truth"] == e and r["correct"]]
        if rs:
            above = [r["gap"]["after_verdict"] - r["gap"]["floor"] for r in rs]
            shrink[e] = {
                "runs": len(rs),
                "mean_gap_sim_as_is": _mean_gap(rs, "sim_as_is"),
                "mean_gap_after_refit": _mean_gap(rs, "after_refit"),
                "mean_gap_after_effect": _mean_gap(rs, "after_verdict"),
                "mean_floor": _mean_gap(rs, "floor"),
                "max_above_floor_db": round(float(np.max(above)), 3),
                "all_within_1db_of_floor": bool(np.max(above) <= 1.0),
            }
    none_gap = {}
    for t in none_classes(reality):
        rs = [r for r in blind if r["truth"] == t]
        if rs:
            none_gap[t] = {
                "runs": len(rs),
                "mean_gap_sim_as_is": _mean_gap(rs, "sim_as_is"),
                "mean_gap_after_refit": _mean_gap(rs, "after_refit"),
                "mean_floor": _mean_gap(rs, "floor"),
                "max_refit_above_floor_db": round(
                    float(np.max([r["gap"]["after_refit"] - r["gap"]["floor"] for r in rs])), 3
                ),
            }
    detect = {}
    for e in EFFECTS:
        lad = _ladder(results, e)
        blind_e = sorted([r for r in blind if r["truth"] == e], key=lambda r: abs(r["strength"]))
        if not lad and not blind_e:
            continue
        detect[e] = {
            "ladder": _points(lad, e),
            "detected_from_strength": _detected_from(lad),
            "blind": _points(blind_e, e),
            "range_of_blind_runs": list(ranges[e]),
        }
    per_form = {}
    for e in EFFECTS:
        for form in FORMS.get(reality, {}).get(e, ()):
            rs = [r for r in blind if r["truth"] == e and r.get("form") == form]
            lad = _ladder(results, e, form)
            per_form[f"{e}/{form}"] = {
                "effect": e,
                "form": form,
                "what": FORM_TEXT.get(f"{e}/{form}", FORM_TEXT.get(form, "")),
                "runs": len(rs),
                "correct": int(sum(r["correct"] for r in rs)),
                "top1": round(float(np.mean([r["correct"] for r in rs])), 4) if rs else None,
                "missed_as_none": int(sum(r["verdict"] == "none" for r in rs)),
                "verdicts": [r["verdict"] for r in rs],
                "strengths": [r["strength"] for r in rs],
                "ladder": [{"strength": r["strength"], "verdict": r["verdict"]} for r in lad],
                "detected_from_strength": _detected_from(lad),
            }
    none_flags = {
        t: {
            "runs": sum(r["truth"] == t for r in blind),
            "wrongly_flagged": sum(r["truth"] == t and r["verdict"] != "none" for r in blind),
        }
        for t in none_classes(reality)
    }
    effect_runs = [r for r in effects_only if "effects" in r]
    extras = Counter(e for r in effect_runs for e in r["extra_effects"])
    selection = {
        "runs": len(effect_runs),
        "truth_in_effects": round(float(np.mean([r["in_effects"] for r in effect_runs])), 4)
        if effect_runs
        else None,
        "runs_with_an_extra_effect": int(sum(bool(r["extra_effects"]) for r in effect_runs)),
        "extra_effects": dict(sorted(extras.items())),
    }
    return {
        "reality": reality,
        "per_form": per_form,
        "selection": selection,
        "none_false_flags": none_flags,
        "accuracy": round(float(np.mean([r["correct"] for r in blind])), 4),
        "accuracy_effects": round(float(np.mean([r["correct"] for r in effects_only])), 4)
        if effects_only
        else None,
        "none_false_positive_rate": round(
            float(np.mean([r["verdict"] != "none" for r in nones])), 4
        )
        if nones
        else None,
        "per_class_accuracy": per_class,
        "confusion": confusion,
        "heldout_shrink": shrink,
        "none_gaps": none_gap,
        "detectability": detect,
        "n_runs": len(blind),
        "n_ladder_runs": len(results) - len(blind),
    }


def _mean_gap(runs: list[dict], key: str) -> float:
    return round(float(np.mean([r["gap"][key] for r in runs])), 3)


def _ladder(results: list[dict], effect: str, form: str | None = None) -> list[dict]:
    """The ladder runs of an effect (of one of its forms), weakest first."""
    return sorted(
        (
            r
            for r in results
            if r.get("ladder") and r["truth"] == effect and form in (None, r.get("form"))
        ),
        key=lambda r: abs(r["strength"]),
    )


def _points(runs: list[dict], effect: str) -> list[dict]:
    return [
        {"strength": r["strength"], "verdict": r["verdict"], "p_value": r["p_values"].get(effect)}
        for r in runs
    ]


def _detected_from(ladder: list[dict]) -> float | None:
    """The smallest ladder strength from which every stronger ladder run was found."""
    found = [r["correct"] for r in ladder]
    return next((abs(r["strength"]) for i, r in enumerate(ladder) if all(found[i:])), None)


REALITY_TEXT = {
    "sim": (
        "our simulator (egovib_ros/sim) with one hidden effect per bag; two extra `none` classes: "
        "the simulator 6 dB louder than the robot, and a simulator whose spectra differ in shape "
        "(gear tones moved, wrist resonance missing, gripper structural band shifted); every "
        "effect in each of its forms (table below)"
    ),
    "third": (
        "the third hand (research/egovib_research/thirdhand, written from the effect "
        "vocabulary alone: a planetary wrist drive and a worm-and-screw gripper, three housing "
        "modes, trapezoidal moves with held speeds, 10-bit sensor; effects as twice-a-turn "
        "wrist lines, a rub towards the gripper's open end, hiss in a wrist sector, one "
        "joint's lines scaled by the other's speed (magnitude and signed), a line only while "
        "both move, a mode rung by jerk, torque ripple, late / early / polled joint states, a "
        "cool-down, one joint's wear and a thermal cycle; table below)"
    ),
    "alt": (
        "the independent alternate-reality hand (research/egovib_research/altreality: its own "
        "drive trains, housing modes, impulsive friction, sensor and motion; effects as a tight "
        "spot per wrist turn or a rub near the gripper's closed end, intermodulation lines, "
        "backlash clicks at reversals, a warm-up step, a stamp lag, and the forms added since: "
        "a rub only while closing, a signed wrist x gripper interaction, broadband while "
        "braking, a filtered velocity, wear; table below)"
    ),
}


def render_markdown(report: dict) -> str:
    """gap_validation*.md: the accuracy and its settings, the confusion matrix, the gaps of
    the found effects and the `none` classes, per form, the detectability ladder, every run."""
    s = report["summary"]
    lines = (
        _summary_lines(report)
        + _gap_lines(s)
        + _form_lines(s)
        + _detectability_lines(s)
        + _run_lines(report["runs"])
    )
    lines.append("")
    return "\n".join(lines)


def _summary_lines(report: dict) -> list[str]:
    """Title, accuracy, settings, strength ranges, figure and the confusion matrix."""
    s = report["summary"]
    reality = s.get("reality", "sim")
    labels = ["none"] + list(EFFECTS)
    ranges = strength_ranges(reality)
    st = report["settings"]
    lines = [
        f"# Gap diagnosis: blind validation, reality `{reality}`",
        "",
        f"Model calibrated on our simulator ({st['calibration']}); "
        f'"real" bags from {REALITY_TEXT[reality]}.',
        "",
        f"Top-1 accuracy **{s['accuracy']:.3f}** over {s['n_runs']} blind runs "
        f"({st['seeds']} seeds per form of every effect and per `none` class"
        + (f", {st['extra_none']} more per `none` class" if st.get("extra_none") else "")
        + f", {st['duration_s']:.0f} s bags; effects only: "
        f"{s['accuracy_effects']:.3f}); `none` wrongly flagged "
        f"**{100 * s['none_false_positive_rate']:.1f} %** "
        f"({sum(1 for t in s['confusion'] if t.startswith('none'))} `none` classes). "
        + _selection_text(s.get("selection"))
        + "Produced by `"
        + st["command"]
        + f"` in {report['runtime_s'] / 60:.0f} min.",
        "",
        "Strength ranges (blind runs): "
        + ", ".join(f"{e} {lo:g}..{hi:g}" for e, (lo, hi) in ranges.items())
        + " (timing in s, random sign).",
        "",
        f"![confusion and ladder]({st.get('figure', '')})",
        "",
        "## Confusion matrix (rows: truth, columns: verdict)",
        "",
        "| truth \\ verdict | " + " | ".join(labels) + " | accuracy |",
        "|---" * (len(labels) + 2) + "|",
    ]
    for t, row in s["confusion"].items():
        lines.append(
            f"| {t} | "
            + " | ".join(str(row[p]) for p in labels)
            + f" | {s['per_class_accuracy'][t]} |"
        )
    return lines


def _selection_text(sel: dict | None) -> str:
    """The forward selection's figures over the effect runs (one effect generated each)."""
    if not sel or not sel.get("runs"):
        return ""
    extras = ", ".join(f"{k} {v}" for k, v in sel["extra_effects"].items()) or "none"
    return (
        f"Forward selection: the generated effect is in verdict.effects in "
        f"{100 * sel['truth_in_effects']:.0f} % of the {sel['runs']} effect runs; "
        f"{sel['runs_with_an_extra_effect']} name a second effect besides it ({extras}). "
    )


def _gap_lines(s: dict) -> list[str]:
    """The held-out gap of the correctly found effects and of the `none` classes."""
    lines = [
        "",
        "## Held-out gap per correctly found effect (dB, mean over runs)",
        "",
        "| effect | runs | sim as-is | after baseline | after effect | floor "
        "| worst above floor | within 1 dB |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e, d in s["heldout_shrink"].items():
        lines.append(
            f"| {e} | {d['runs']} | {d['mean_gap_sim_as_is']} | {d['mean_gap_after_refit']} | "
            f"{d['mean_gap_after_effect']} | {d['mean_floor']} | {d['max_above_floor_db']} | "
            f"{d['all_within_1db_of_floor']} |"
        )
    lines += [
        "",
        "## `none` classes: how close the velocity-only baseline gets (dB)",
        "",
        "| class | runs | sim as-is | after baseline | floor | worst baseline above floor |",
        "|---|---|---|---|---|---|",
    ]
    for t, d in s["none_gaps"].items():
        lines.append(
            f"| {t} | {d['runs']} | {d['mean_gap_sim_as_is']} | {d['mean_gap_after_refit']} | "
            f"{d['mean_floor']} | {d['max_refit_above_floor_db']} |"
        )
    return lines


def _form_lines(s: dict) -> list[str]:
    """Per form of each effect: top-1 and the ladder; `none` wrongly flagged per class."""
    lines = []
    if s.get("per_form"):
        lines += [
            "",
            "## Per form: top-1 and the ladder (one seed per rung, x the lower end of the range)",
            "",
            "| effect | form | what | blind runs | top-1 | missed as none | ladder "
            "| detected from |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for d in s["per_form"].values():
            ladder = ", ".join(f"{r['strength']:g} -> {r['verdict']}" for r in d["ladder"])
            lines.append(
                f"| {d['effect']} | {d['form']} | {d['what']} | {d['runs']} | "
                f"{d['correct']}/{d['runs']} | {d['missed_as_none']} | {ladder} | "
                f"{d['detected_from_strength']} |"
            )
        lines += [
            "",
            "`none` wrongly flagged per `none` class: "
            + ", ".join(
                f"{t} {d['wrongly_flagged']}/{d['runs']}" for t, d in s["none_false_flags"].items()
            )
            + ".",
        ]
    return lines


def _detectability_lines(s: dict) -> list[str]:
    """Per effect, the weakest strength of the ladder the diagnosis found."""
    lines = ["", "## Detectability (strength ladder below the blind ranges, one seed each)", ""]
    for e, d in s["detectability"].items():
        ladder = ", ".join(f"{r['strength']:g} -> {r['verdict']}" for r in d["ladder"])
        lines.append(f"- {e}: detected from {d['detected_from_strength']} (ladder: {ladder})")
    return lines


def _run_lines(runs: list[dict]) -> list[str]:
    """One table row per run (blind and ladder)."""
    lines = [
        "",
        "## Runs",
        "",
        "| truth | strength | seed | verdict | confidence | gap as-is | baseline | after | floor | "
        "p (truth) | details |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        g = r["gap"]
        label = "none" if r["truth"].startswith("none") else r["truth"]
        p = r["p_values"].get(label)
        details = ", ".join(f"{k}={v}" for k, v in r.get("truth_details", {}).items())
        form = f"/{r['form']}" if r.get("form") else ""
        lines.append(
            f"| {r['truth']}{form}{' (ladder)' if r.get('ladder') else ''} | "
            f"{r['strength']} | {r['seed']} | "
            f"{r['verdict']} | {r['confidence']} | {g['sim_as_is']} | {g['after_refit']} | "
            f"{g['after_verdict']} | {g['floor']} | {'' if p is None else f'{p:.2g}'} | {details} |"
        )
    return lines


def output_names(reality: str) -> tuple[str, str, str]:
    stem = "gap_validation" if reality == "sim" else f"gap_validation_{reality}"
    return f"{stem}.json", f"{stem}.md", f"{stem}.png"


def make_figure(summary: dict, path: Path) -> None:
    """Confusion matrix and, per effect, verdicts along the strength ladder and the blind runs."""
    plt = pyplot()

    labels = ["none"] + list(EFFECTS)
    rows = list(summary["confusion"])
    mat = np.array([[summary["confusion"][t][p] for p in labels] for t in rows], float)
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2), gridspec_kw={"width_ratios": [1, 1.3]})
    ax = axes[0]
    ax.imshow(mat / np.maximum(mat.sum(axis=1, keepdims=True), 1), cmap="Blues", vmin=0, vmax=1)
    for i in range(len(rows)):
        for j in range(len(labels)):
            if mat[i, j]:
                ax.text(j, i, int(mat[i, j]), ha="center", va="center", fontsize=9)
    ax.set_xticks(range(len(labels)))
    ax.set_xticklabels(labels, rotation=30, fontsize=8)
    ax.set_yticks(range(len(rows)))
    ax.set_yticklabels(rows, fontsize=8)
    ax.set_xlabel("verdict")
    ax.set_title(
        f"reality {summary['reality']}: top-1 {summary['accuracy']:.2f}, none flagged "
        f"{100 * summary['none_false_positive_rate']:.0f} %",
        fontsize=10,
    )
    ax = axes[1]
    for k, (e, d) in enumerate(summary["detectability"].items()):
        lo = d["range_of_blind_runs"][0]
        for kind, marker in (("ladder", "s"), ("blind", "o")):
            for r in d[kind]:
                ax.scatter(
                    abs(r["strength"]) / lo,
                    k,
                    marker=marker,
                    s=40,
                    color="C2" if r["verdict"] == e else "C3",
                    edgecolor="k",
                    linewidth=0.5,
                )
    ax.axvline(1.0, color="0.5", ls="--", lw=0.8)
    ax.set_xscale("log")
    ax.set_yticks(range(len(summary["detectability"])))
    ax.set_yticklabels(list(summary["detectability"]), fontsize=8)
    ax.set_xlabel("strength / lower end of the blind range (squares: ladder, circles: blind runs)")
    ax.set_title("detected (green) or missed (red) by strength", fontsize=10)
    save_figure(fig, path)


def prepare_models(tmp: Path, reality: str, calibration_dwell_s: float) -> tuple[dict, dict]:
    """Model files and reference lags: the default simulator,
    and for `sim` the shape-changed one."""

    paths, lags = {}, {}
    configs = {"sim": SimParams.load()}
    if reality == "sim":
        configs["shape"] = shape_differs_params()
    for key, params in configs.items():
        model = calibrate_sim_model(dwell_s=calibration_dwell_s, params=params)
        lags[key] = simulator_reference_lag(model, params=params)
        paths[key] = str(tmp / f"model_{key}.npz")
        model.save(paths[key])
    return paths, lags


def run_validation(
    *,
    seeds: int = 5,
    duration_s: float = 120.0,
    out_dir: str | Path = "docs",
    jobs: int = 1,
    ladder: bool = True,
    progress: bool = False,
    master_seed: int = 2026,
    calibration_dwell_s: float = CALIBRATION_DWELL_S,
    reality: str = "sim",
    runs: list[dict] | None = None,
    extra_none: int = 0,
) -> dict:
    """Run the blind validation; write gap_validation[_alt].json/.md/.png into out_dir;
    return the summary.

    `runs`: an explicit list of runs (class, strength, seed) instead of the planned ones (tests).
    """

    if reality not in REALITIES:
        raise ValueError(f"reality must be one of {REALITIES}, not {reality!r}")
    if reality == "real":
        return _run_real(out_dir)
    start = time.perf_counter()
    if runs is None:
        runs = plan_runs(
            seeds, ladder=ladder, master_seed=master_seed, reality=reality, extra_none=extra_none
        )
    else:
        runs = [{**r, "reality": reality} for r in runs]
    with tempfile.TemporaryDirectory(prefix="egovib_gap_validate_") as tmp:
        model_paths, reference_lags = prepare_models(Path(tmp), reality, calibration_dwell_s)
        if jobs > 1:
            with ProcessPoolExecutor(
                jobs, initializer=_init_worker, initargs=(model_paths, reference_lags)
            ) as pool:
                iterator = pool.map(run_one, runs, [duration_s] * len(runs))
                results = _progress(iterator, len(runs), progress)
        else:
            _init_worker(model_paths, reference_lags)
            results = _progress((run_one(r, duration_s) for r in runs), len(runs), progress)
    summary = summarise(results, reality)
    command = (
        f"egovib gap validate --reality {reality} --seeds {seeds} --duration {duration_s:g} "
        f"--master-seed {master_seed}"
        + (f" --extra-none {extra_none}" if extra_none else "")
        + ("" if ladder else " --no-ladder")
        + f" --out {out_dir}"
    )
    json_name, md_name, png_name = output_names(reality)
    report = {
        "schema": "egovib.gap_validation/2",
        "summary": summary,
        "settings": {
            "reality": reality,
            "seeds": seeds,
            "extra_none": extra_none,
            "duration_s": duration_s,
            "max_speed": MOTION_MAX_SPEED,
            "tap_rate_hz": TAP_RATE_HZ,
            "strength_ranges": strength_ranges(reality),
            "master_seed": master_seed,
            "calibration": f"superposition sweep of the simulator, {calibration_dwell_s:g} s dwell",
            "reference_lag_s": {k: round(v, 5) for k, v in reference_lags.items()},
            "command": command,
            "figure": png_name,
        },
        "runs": results,
        "runtime_s": round(time.perf_counter() - start, 1),
    }
    out = Path(out_dir)
    outputs = _write_report(out, report, render_markdown(report), json_name, md_name)
    with atomic_output(out / png_name) as tmp_path:
        make_figure(summary, tmp_path)
    summary["outputs"] = outputs + [str(out / png_name)]
    summary["report"] = report
    return summary


def _run_real(out_dir) -> dict:
    """Known effects injected into the real flight (experiments/gap_real_injection.py)."""

    report = run_real_validation()
    report["settings"]["command"] = f"egovib gap validate --reality real --out {out_dir}"
    summary = dict(report["summary"])
    # the share of injections named in verdict.effects; the untouched flight has effects of
    # its own (its motors' lag): no `none` class to flag wrongly
    summary["accuracy"] = summary["in_effects"]
    summary["none_false_positive_rate"] = None
    json_name, md_name, _ = output_names("real")
    summary["outputs"] = _write_report(
        Path(out_dir), report, render_real(report), json_name, md_name
    )
    summary["report"] = report
    summary["n_runs"] = report["summary"]["n_runs"]
    return summary


def _write_report(out: Path, report: dict, markdown: str, json_name: str, md_name: str) -> list:
    """The report as JSON and as markdown in directory `out` (made if missing); their paths."""
    out.mkdir(parents=True, exist_ok=True)
    for name, text in ((json_name, json.dumps(report, indent=1)), (md_name, markdown)):
        with atomic_output(out / name) as tmp_path:
            tmp_path.write_text(text)
    return [str(out / json_name), str(out / md_name)]


def _progress(iterator, total: int, show: bool) -> list:
    if not show:
        return list(iterator)

    return list(tqdm(iterator, total=total, desc="gap validate", unit="run"))
