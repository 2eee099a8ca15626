"""What the found effects cost the denoiser, what to do about each, and what is left.

`advise(diag)` gives report.json's "advice" and report.md's first lines: per effect found
(in the forward selection's order) one sentence with the flags or parameters that act on
it (options that exist: the model has no position key, so position is advised as what to
record); the commands applying all of them (`commands`); the cost: held-out noise
reduction of spectral subtraction with the velocity-only baseline and with the combined
model (a model estimate) and, measured by the caller (`measure_advice`), the flags applied
with the user's model; what the combined model leaves above the floor.

The joint lag has one sign convention everywhere (LAG_CONVENTION): the seconds the
vibration trails the joint states. The diagnosis scans `lag_s` = seconds the joint states
are stamped late, the opposite sign (`joint_lag_of`).
"""

from __future__ import annotations

import json
import logging
import shlex
from pathlib import Path

import numpy as np

from egovib_ros.core.filters import BandPass
from egovib_ros.core.methods import default_method, denoise_batch_method
from egovib_ros.core.subtraction import noise_gain_curve
from egovib_ros.errors import ConfigError
from egovib_ros.gap.baseline import fit_baseline, lag_residual, simulator_cells
from egovib_ros.gap.diagnose import Diagnosis
from egovib_ros.gap.effects import (
    LAG_COARSE_S,
    LAG_FINE_S,
    drift_reach,
    fit_scales,
    fit_variant,
)

#: A `none` verdict whose baseline stays more than this above the floor says so.
UNEXPLAINED_NOTE_DB = 0.3
#: ... and one whose model a velocity-only model fitted on the recording beats by more than
#: this says the model misses the recording's motion (speeds it never held: the shipped
#: flight's take-off against a hover model, 5.29 -> 2.77 dB) and advises calibrating on it.
RECALIBRATE_NOTE_DB = 1.0
#: The one sign convention of the joint lag (report.json, report.md, CLI help, docs).
LAG_CONVENTION = (
    "joint lag = seconds the vibration trails the joint states: their stamps are moved that "
    "much later before they are matched with the sensor (egovib denoise / calibrate "
    "--joint-lag, the nodes' joint_lag); negative: the vibration leads them (joint states "
    "stamped late)"
)
#: Corrections applied by `measure_advice` are fitted on this leading share of the
#: recording and scored on the rest.
MEASURE_TRAIN_FRACTION = 0.6
#: The held-out lag of `measure_advice` is re-fitted within this distance of the diagnosis's.
MEASURE_LAG_WINDOW_S = 0.015
#: An interaction (coupling) of a joint's lines is described when it moves them this much.
LINE_NOTE_DB = 1.0


def joint_lag_of(lag_s: float) -> float:
    """The internal lag (joint states stamped `lag_s` late) in the joint-lag convention."""
    return -float(lag_s)


def _shape_span(shape: dict, prefix: str) -> tuple[str, float, dict]:
    """The curve of `shape` (keys starting with prefix) with the largest peak-to-trough."""
    best, span, curve = "", 0.0, {}
    for key, c in shape.items():
        if key.startswith(prefix) and "gain_db" in c:
            g = np.asarray(c["gain_db"], float)
            if g.size and float(np.ptp(g)) > span:
                best, span, curve = key.split(":", 1)[1], float(np.ptp(g)), c
    return best, span, curve


def _timing_action(model) -> tuple[str, dict]:
    p = model.parameters
    offset = float(p.get("lag_s", 0.0)) - float(p.get("reference_lag_s", 0.0))
    joint_lag = round(joint_lag_of(offset), 4)
    way = "trails" if joint_lag > 0 else "leads"
    flag = f"{joint_lag:g}"
    return (
        f"the vibration {way} the joint states by {1000 * abs(joint_lag):.0f} ms more than the "
        f"model expects: joint lag {flag} s (`egovib denoise --joint-lag {flag}`, the denoiser "
        f"node's `joint_lag:={flag}`; calibrate with the same: `egovib calibrate --joint-lag "
        f"{flag}`, the calibrator's `joint_lag:={flag}`)",
        {"joint_lag_s": joint_lag},
    )


#: A drift (the whole vibration's, or one joint's own: dB from start to end) is acted on
#: from this size on: below it, a correction buys nothing a user would measure (the shipped
#: flight's hover: a significant -0.1 dB, whose noise-gain curve cost 0.2 dB of noise removed).
DRIFT_MIN_DB = 0.5


def _drift_action(model) -> tuple[str, dict]:
    shape = model.shape or {}
    # the whole vibration's level (the interleaved check's, when the diagnosis added one)
    curves = [c for k, c in shape.items() if k.startswith("drift:elapsed_time")]
    curve = curves[-1] if curves else {}
    g = np.asarray(curve.get("gain_db", [0.0]), float)
    x = np.asarray(curve.get("x", [0.0]), float)
    change_db, reach = drift_reach(x, g)
    pct = 100.0 * (10 ** (change_db / 20.0) - 1.0)
    span = float(x[-1] - x[0]) if x.size else 0.0
    saturates = reach < 0.7 * (x[-1] if x.size else 0.0)
    settings: dict = {}
    head = f"vibration {'grows' if pct > 0 else 'falls'} {abs(pct):.0f} % over {span:.0f} s"
    # one joint's own trend, when it is over twice any other's (a drive wearing in or out)
    ends = sorted(
        ((abs(c["gain_db"][-1]), c) for c in shape.values() if "joint" in c and c["gain_db"]),
        key=lambda pair: pair[0],
    )
    worst = ends[-1][1] if ends else None
    if len(ends) > 1 and ends[-1][0] > max(2.0 * ends[-2][0], DRIFT_MIN_DB):
        own = 100.0 * (10 ** (worst["gain_db"][-1] / 20.0) - 1.0)
        head = (
            f"{worst['joint']}'s vibration {'grows' if own > 0 else 'falls'} {abs(own):.0f} % "
            f"over {span:.0f} s (the whole vibration {pct:+.0f} %)"
        )
        settings = {"joint": worst["joint"], "joint_change_percent": round(own, 1)}
    elif abs(change_db) < DRIFT_MIN_DB:
        return (
            f"the vibration's level barely moves ({change_db:+.2f} dB over {span:.0f} s; a "
            f"drift is acted on from {DRIFT_MIN_DB:g} dB): nothing to recalibrate for or apply",
            {"level_change_percent": round(pct, 1)},
        )
    return (
        head
        + (
            f" (90 % of it within {reach:.0f} s): recalibrate after warm-up"
            if saturates
            else ": recalibrate periodically, or calibrate on a recording as long as use"
        )
        + "; until then the denoiser follows the fitted level: `egovib denoise --noise-gain "
        "REPORT.json` (the denoiser node's `noise_gain:=REPORT.json`)",
        {
            **settings,
            "recalibrate_after_s": round(reach, 1),
            "level_change_percent": round(pct, 1),
            # for `egovib denoise --noise-gain`: the level change from the start
            "noise_gain_db": [
                [round(float(t - x[0]), 2), round(float(v - g[0]), 3)] for t, v in zip(x, g)
            ],
        },
    )


def _position_action(model) -> tuple[str, dict]:
    joint, span, curve = _shape_span(model.shape or {}, "position:")
    loud = ""
    settings = {"calibration_grid": "free", "position_joint": joint}
    if curve:
        k = int(np.argmax(curve["gain_db"]))
        loud = f", loudest at {curve['x'][k]:.3g} {curve.get('unit', '')}"
        settings["loudest_at"] = curve["x"][k]
    where = f"{joint}: {span:.1f} dB peak-to-trough{loud}" if span >= 0.1 else "bin by bin"
    return (
        f"position-dependent ({where}): the noise model has no position key, so calibrate on "
        "free motion that covers the positions the task uses (`egovib calibrate BAG --grid "
        "free`: the model holds their average) and keep contact sensing away from the "
        "loudest range",
        settings,
    )


def _coupling_action(model) -> tuple[str, dict]:
    shape = model.shape or {}
    _, span, curve = _shape_span(shape, "coupling:")
    parts = []
    lines = (model.parameters.get("lines") or {}).get("pairs", {})
    for name, entry in lines.items():
        big = {k: v for k, v in entry.items() if abs(v) >= LINE_NOTE_DB}
        if big:
            parts.append(
                f"{name}: "
                + ", ".join(
                    f"{k.replace('_db', '').replace('_', ' ')} {v:+.1f} dB" for k, v in big.items()
                )
            )
    signed = np.asarray(curve.get("same_minus_opposite_direction_db", [[0.0]]), float)
    if span >= 0.1:
        direction = (
            f", same vs opposite direction up to {np.max(np.abs(signed)):.1f} dB"
            if signed.size and np.max(np.abs(signed)) >= 0.5
            else ""
        )
        parts.append(f"{' x '.join(curve['joints'])} together: up to {span:.1f} dB{direction}")
    if not parts:
        # the interaction of the largest single-bin gain: where it is, not only that it is
        peaks = [
            (abs(c.get("per_bin_peak_db", 0.0)), c)
            for key, c in shape.items()
            if key.startswith("coupling:")
        ]
        size, c = max(peaks, key=lambda p: p[0], default=(0.0, {}))
        where = "bin by bin, flat across the band" + (
            f"; largest: {' x '.join(c['joints'])} {c['per_bin_peak_db']:+.1f} dB at "
            f"{c['per_bin_peak_hz']:.0f} Hz"
            if size >= 0.1
            else ""
        )
    else:
        where = "; ".join(parts)
    joints = sorted(
        {
            n
            for key, c in shape.items()
            if key.startswith("coupling")
            for n in c.get("joints") or (c["lines_of"], c["speed_of"])
        }
    )
    return (
        f"joints do not add ({where}): calibrate these joints together, on a full velocity "
        "grid (`sweep_driver --ros-args -p grid:=full`, then `egovib calibrate BAG --grid "
        "full`) or on free motion covering their combinations (`egovib calibrate BAG --grid "
        "free`), not by superposition",
        {"calibration_grid": "full", "joints": joints if parts else []},
    )


def _acceleration_action(model) -> tuple[str, dict]:
    return (
        "joint acceleration adds vibration (speed changes, reversals): calibrate on free motion "
        "with speed changes like the task's (`egovib calibrate BAG --grid free`)",
        {"calibration_grid": "free"},
    )


_ACTIONS = {
    "timing": _timing_action,
    "drift": _drift_action,
    "position": _position_action,
    "coupling": _coupling_action,
    "acceleration": _acceleration_action,
}


def effect_action(effect: str, model) -> tuple[str, dict]:
    """One sentence saying what to change about `effect` (its fitted `model`: parameters,
    shape), with the flags, and the settings it names."""
    return _ACTIONS[effect](model)


def _none_action(diag: Diagnosis) -> tuple[str, dict]:
    as_is, refit = float(diag.gaps["sim_as_is"]), float(diag.gaps["refit"])
    above = refit - float(diag.floor)
    parts, settings = [], {}
    if as_is - refit > RECALIBRATE_NOTE_DB:
        parts.append(
            "the model misses this recording's motion: a velocity-only model fitted on it "
            f"comes {as_is - refit:.2f} dB closer ({as_is:.2f} -> {refit:.2f} dB); calibrate "
            "on motion like it, without contact"
        )
        settings["calibration_grid"] = "free"
    if above > UNEXPLAINED_NOTE_DB:
        parts.append(
            f"no effect of the vocabulary explains the rest ({above:.2f} dB above the floor "
            "stays unexplained): keep calibrating on velocity; record longer or more varied "
            "motion to tell more"
        )
    elif not parts:
        parts.append("the velocity-only model fits this recording: nothing to change")
    return "; ".join(parts), settings


def action(diag: Diagnosis) -> tuple[str, dict]:
    """The first effect's sentence and settings (`none`: whether anything is left)."""
    if diag.verdict == "none":
        return _none_action(diag)
    return effect_action(diag.verdict, diag.models[diag.verdict])


def effect_actions(diag: Diagnosis) -> list[dict]:
    """Every effect found, in order: {"effect", "action", "settings"}."""
    out = []
    for entry, model in zip(diag.effects, diag.effect_models):
        text, settings = effect_action(entry["effect"], model)
        out.append({"effect": entry["effect"], "action": text, "settings": settings})
    return out


def merged_settings(actions: list[dict]) -> dict:
    """The settings of every action in one dict (the first wins a clash; a full grid wins
    over free motion: it covers the combinations free motion may miss)."""
    merged: dict = {}
    for a in actions:
        for key, value in a["settings"].items():
            if key == "calibration_grid" and merged.get(key) == "free" and value == "full":
                merged[key] = value
            merged.setdefault(key, value)
    return merged


def commands(
    settings: dict,
    *,
    model: str = "MODEL.npz",
    bag: str = "BAG",
    report: str = "REPORT.json",
    robot: str | None = None,
) -> dict:
    """The command lines that apply every advised correction together, each one line a
    shell runs as it is (`robot`: calibrate's --robot, robot.robot_option)."""
    flags, params = [], []
    q = shlex.quote  # a path with a space is one word when pasted
    if settings.get("joint_lag_s"):
        lag = f"{settings['joint_lag_s']:g}"
        flags.append(f"--joint-lag {lag}")
        params.append(f"-p joint_lag:={lag}")
    if settings.get("noise_gain_db"):
        flags.append(f"--noise-gain {q(report)}")
        params.append(f"-p {q(f'noise_gain:={report}')}")
    out = {}
    if flags:
        out["denoise"] = f"egovib denoise {q(bag)} --model {q(model)} --out DENOISED " + " ".join(
            flags
        )
        out["denoiser_node"] = f"denoiser --ros-args -p {q(f'model:={model}')} " + " ".join(params)
    if settings.get("calibration_grid"):
        grid = settings["calibration_grid"]
        lag = f" --joint-lag {settings['joint_lag_s']:g}" if settings.get("joint_lag_s") else ""
        robot_flag = f" --robot {robot}" if robot else ""
        out["calibrate"] = (
            f"egovib calibrate NEW_RECORDING{robot_flag} --grid {grid}{lag} --out NEW_MODEL.npz"
            + (
                "  # NEW_RECORDING: a sweep_driver sweep with grid:=full"
                if grid == "full"
                else "  # NEW_RECORDING: free motion of the robot, no contact"
            )
        )
    return out


def _for_robot(text: str, robot: str | None) -> str:
    """The commands in an action's text as they run for this robot (robot.robot_option:
    None for the default PR2 hand)."""
    if not robot:
        return text
    text = text.replace("`egovib calibrate BAG ", f"`egovib calibrate BAG --robot {robot} ")
    return text.replace("`sweep_driver --ros-args ", f"`sweep_driver --ros-args -p robot:={robot} ")


def advise(diag: Diagnosis, *, paths: dict | None = None, measured: dict | None = None) -> dict:
    """report.json "advice": per effect action and settings, the commands applying them all,
    cost to the denoiser (model estimate; `measured`: the flags applied with the user's
    model, `measure_advice`), unexplained rest. `paths`: model, bag and report paths for
    the commands."""
    actions = effect_actions(diag)
    if actions:
        text = (
            "; ".join(f"{a['effect']}: {a['action']}" for a in actions)
            if len(actions) > 1
            else actions[0]["action"]
        )
        settings = merged_settings(actions)
    else:
        text, settings = _none_action(diag)
    robot = (paths or {}).get("robot")
    text = _for_robot(text, robot)
    for a in actions:
        a["action"] = _for_robot(a["action"], robot)
    without = -float(diag.residual_noise["after_refit"])  # noise reduction, dB
    with_fix = -float(diag.residual_noise["after_effect"])
    after, floor = diag.gaps["combined"], diag.floor  # the baseline and every effect found
    excess_base = max(diag.gaps["refit"] ** 2 - floor**2, 1e-12)
    excess_after = max(after**2 - floor**2, 0.0)
    return {
        "effect": diag.verdict,
        "effects": actions,
        "action": text,
        "settings": settings,
        "commands": commands(settings, **(paths or {})),
        "lag_convention": LAG_CONVENTION,
        "denoiser": {
            "definition": "model estimate: held-out noise reduction (dB, no-contact blocks, "
            "spectral subtraction with mean + sd noise) with the velocity-only baseline "
            "(without the corrections) and with the baseline times every found effect's term "
            "(with them), all fitted on the other folds",
            "noise_reduction_without_db": round(without, 3),
            "noise_reduction_with_db": round(with_fix, 3),
            "gain_db": round(with_fix - without, 3),
        },
        "applied": measured,
        "unexplained": {
            "above_floor_db": round(after - floor, 3),
            "share_of_baseline_excess": round(float(excess_after / excess_base), 3),
            "note": "held-out gap of the baseline plus every found effect minus the floor; "
            "share = (gap^2 - floor^2) / (baseline gap^2 - floor^2)",
        },
    }


def first_lines(advice: dict) -> list[str]:
    """report.md's opening: what to do (each effect, its flags), the commands, what it
    costs and what applying it gave, what is left."""
    d, u = advice["denoiser"], advice["unexplained"]
    effects = advice.get("effects") or []
    if len(effects) > 1:
        lines = ["**What to do** (effects in the order found; each flag below applies one):"]
        lines += [f"{k}. `{a['effect']}`: {a['action']}." for k, a in enumerate(effects, 1)]
    else:
        lines = [f"**What to do:** {advice['action']}."]
    cmds = advice.get("commands") or {}
    applied = advice.get("applied")
    costs = bool(applied) and applied.get("recommended") is False
    if cmds:
        lines.append(
            f"**All corrections together** (not with `{applied['method']}`, this model's "
            "default method: measured below, they cost it held-out noise reduction):"
            if costs
            else "**All corrections together:**"
        )
        lines += ["```sh"] + list(cmds.values()) + ["```"]
    if advice.get("settings", {}).get("joint_lag_s") is not None:
        lines.append(f"*Sign of the joint lag:* {advice.get('lag_convention', LAG_CONVENTION)}.")
    if applied and applied.get("noise_reduction_with_db") is not None:
        lines.append(
            f"**Applied together, measured:** the model as given, its default method "
            f"`{applied['method']}`, with {applied['applied_text']}: held-out noise reduction "
            f"{applied['noise_reduction_without_db']:.2f} dB without, "
            f"{applied['noise_reduction_with_db']:.2f} dB with ({applied['gain_db']:+.2f} dB; "
            f"{applied['heldout']})"
            + (
                ": do not apply them with this method (what the model's own fit already follows, "
                "e.g. the canceller's lags, the flags would correct twice)."
                if costs
                else "."
            )
        )
    elif applied and applied.get("note"):
        lines.append(f"**Applied together:** {applied['note']}.")
    if advice["effect"] != "none" and cmds:  # (nothing advised: no cost to state)
        lines.append(
            f"**What the corrections are worth to the denoiser (model estimate):** held-out "
            f"noise reduction "
            f"{d['noise_reduction_without_db']:.2f} dB without the corrections, "
            f"{d['noise_reduction_with_db']:.2f} dB with them ({d['gain_db']:+.2f} dB)."
        )
    lines.append(
        f"**Left unexplained:** {u['above_floor_db']:.2f} dB above the floor "
        f"({100 * u['share_of_baseline_excess']:.0f} % of the baseline's excess)."
    )
    return lines


def noise_gain_from_report(path: str | None, *, where: str) -> tuple[tuple[float, float], ...]:
    """The (elapsed s, dB) knots of a gap report's drift advice, for the denoiser's
    noise_gain_db; () without a report (`path` None or ""). Errors name `where` (the option
    or parameter) and the file."""
    if not path:
        return ()
    try:
        report = json.loads(Path(path).read_text())
        knots = report["advice"]["settings"]["noise_gain_db"]
    except OSError as exc:
        raise ConfigError(f"{where} {path}: {exc.strerror or exc}") from None
    except (ValueError, KeyError, TypeError):
        raise ConfigError(
            f"{where} {path}: not an egovib gap report with a drift verdict "
            "(advice.settings.noise_gain_db)"
        ) from None
    noise_gain_curve(knots)  # checked here, once, with the file named
    return tuple((float(t), float(g)) for t, g in knots)


def _train_rows(diag: Diagnosis, t_end_s: float) -> tuple[np.ndarray, float]:
    """The clean blocks of the leading MEASURE_TRAIN_FRACTION of [start, t_end_s], and the
    split time."""
    t = diag.table.t_mid_s
    start = float(t[0])
    split = start + MEASURE_TRAIN_FRACTION * (min(float(t[-1]), t_end_s) - start)
    return ~diag.table.contact & (t < split), split


def _held_out_joint_lag(diag: Diagnosis, train: np.ndarray) -> float:
    """The joint lag re-fitted on the training rows only, within MEASURE_LAG_WINDOW_S of the
    diagnosis's (coarse grid, then 1 ms), relative to the reference, in the joint-lag
    convention."""
    table = diag.table
    rows = np.flatnonzero(train)
    prior = simulator_cells(table)
    centre = float(diag.lag_scan.get("timing_lag_s", diag.sync_lag_s))
    coarse = centre + np.arange(-MEASURE_LAG_WINDOW_S, MEASURE_LAG_WINDOW_S + 1e-9, LAG_COARSE_S)
    coarse = (
        coarse[[abs(lag) <= table.joints.max_lag_s for lag in coarse]] if table.joints else coarse
    )
    curve = [lag_residual(table, rows, float(lag), prior) for lag in coarse]
    best = float(coarse[int(np.argmin(curve))])
    fine = best + np.arange(-LAG_COARSE_S + LAG_FINE_S, LAG_COARSE_S - 1e-9, LAG_FINE_S)
    values = [lag_residual(table, rows, float(lag), prior) for lag in fine]
    lag = float(fine[int(np.argmin(values))])
    return round(joint_lag_of(lag - diag.reference_lag_s), 4)


def _held_out_noise_gain(diag: Diagnosis, train: np.ndarray) -> list[list[float]]:
    """The drift term fitted on the training rows only (held flat beyond them but for its
    linear trend), as (elapsed s, dB) knots for the denoiser's noise_gain_db."""
    table = diag.table.at_lag(diag.sync_lag_s)
    table.contact = diag.table.contact
    prior = simulator_cells(table)
    base = fit_baseline(table, train, prior=prior)
    scales = fit_scales(table, train, base.magnitude)
    fitted = fit_variant(table, train, "drift", scales, base)
    curve = (fitted.shape or {}).get("drift:elapsed_time", {})
    x, g = np.asarray(curve.get("x", [0.0]), float), np.asarray(curve.get("gain_db", [0.0]), float)
    return [[round(float(t - x[0]), 2), round(float(v - g[0]), 3)] for t, v in zip(x, g)]


def _scored_mask(diag: Diagnosis, t_s: np.ndarray, split_s: float, margin_s: float) -> np.ndarray:
    """Samples (times t_s, s since the table's origin) after the split, inside a block the
    diagnosis kept, not in a contact-like block, away from the ends by `margin_s`."""
    table = diag.table
    lo = np.searchsorted(t_s, table.t_first_s)
    hi = np.searchsorted(t_s, table.t_last_s, side="right")

    def covered(starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
        edges = np.zeros(len(t_s) + 1, int)
        np.add.at(edges, starts, 1)
        np.add.at(edges, stops, -1)
        return np.cumsum(edges)[:-1] > 0

    inside = covered(lo, hi) & ~covered(lo[table.contact], hi[table.contact])
    return inside & (t_s >= split_s) & (t_s >= t_s[0] + margin_s) & (t_s <= t_s[-1] - margin_s)


def measure_advice(rec, model, diag: Diagnosis, settings: dict, order) -> dict:
    """The advice's flags (joint lag, noise gain) applied together with the user's `model`
    and its default method, held out: the corrections are re-fitted on the leading
    MEASURE_TRAIN_FRACTION of `rec` (the recording diagnosed, or its first part; `order`: its
    joint columns in model order) and both runs, without and with them, are scored on the
    rest: the band-passed sum of axes over the no-contact blocks the diagnosis kept, away
    from the ends by the lag.

    Returns the figures, or {"note": why nothing was applied} when no flag is advised."""
    want_lag = "joint_lag_s" in settings and any(e["effect"] == "timing" for e in diag.effects)
    want_gain = "noise_gain_db" in settings and any(e["effect"] == "drift" for e in diag.effects)
    if not (want_lag or want_gain):
        note = "no advised correction is a flag of the denoiser (joint lag, noise gain)"
        if settings.get("calibration_grid"):
            note += "; what the advice changes is the calibration"
        return {"note": note}
    method = default_method(model)
    t_s = (rec.sensor_stamps_ns - rec.sensor_stamps_ns[0]) / 1e9
    train, split = _train_rows(diag, float(t_s[-1]))
    options: dict = {}
    texts = []
    if want_lag:
        options["joint_lag_s"] = _held_out_joint_lag(diag, train)
        texts.append(f"joint lag {options['joint_lag_s']:+g} s")
    if want_gain:
        knots = _held_out_noise_gain(diag, train)
        noise_gain_curve(knots)
        options["noise_gain_db"] = tuple((float(a), float(b)) for a, b in knots)
        texts.append(f"noise gain {knots[-1][1]:+.1f} dB at {knots[-1][0]:.0f} s")
    velocity = rec.joint_velocity[:, order]
    core_log = logging.getLogger("egovib_ros.core")
    level = core_log.level
    core_log.setLevel(logging.ERROR)
    runs = {}
    try:
        for name, opts in (("without", {}), ("with", options)):
            stamps, values, _ = denoise_batch_method(
                rec.sensor_stamps_ns,
                rec.sensor,
                rec.joint_stamps_ns,
                velocity,
                model,
                method=method,
                channels="combined",
                **opts,
            )
            runs[name] = (stamps, values[:, 0])
    finally:
        core_log.setLevel(level)
    raw = BandPass.of(model, 1).process(rec.sensor.sum(axis=1)[None, :])[0]
    margin = 4 * model.block_length / model.sample_rate_hz + abs(options.get("joint_lag_s", 0.0))
    scored = _scored_mask(diag, t_s, split, margin)
    out = {
        "method": method,
        "applied": {
            k: (list(map(list, v)) if k == "noise_gain_db" else v) for k, v in options.items()
        },
        "applied_text": ", ".join(texts)
        + f" (fitted on the first {100 * MEASURE_TRAIN_FRACTION:.0f} %)",
        "advised_from_all_data": {
            k: settings[k] for k in ("joint_lag_s",) if k in settings and want_lag
        },
        "heldout": f"scored on the last {100 * (1 - MEASURE_TRAIN_FRACTION):.0f} % "
        f"({float(t_s[-1]) - split:.0f} s), no-contact blocks",
        "definition": "20 log10 of the mean band-passed magnitude (sum of axes) of the raw "
        "signal over that of the denoised one (channels combined), both runs on the same samples",
    }
    full = {}
    for name, (stamps, values) in runs.items():
        full[name] = np.full(len(raw), np.nan)
        full[name][np.searchsorted(rec.sensor_stamps_ns, stamps)] = values
    keep = scored & np.isfinite(full["without"]) & np.isfinite(full["with"])
    noise_raw = float(np.mean(np.abs(raw[keep])))
    for name, values in full.items():
        out[f"noise_reduction_{name}_db"] = round(
            float(20.0 * np.log10(noise_raw / max(float(np.mean(np.abs(values[keep]))), 1e-300))),
            3,
        )
    out["scored_samples"] = int(keep.sum())
    out["gain_db"] = round(out["noise_reduction_with_db"] - out["noise_reduction_without_db"], 3)
    out["recommended"] = out["gain_db"] > 0  # what it gave the user's model, held out
    return out
