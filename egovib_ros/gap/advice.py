"""What the found effect costs the denoiser, what to do about it, and what is left.

`advise(diag)` turns a diagnosis into the report's first lines:

* the cost: held-out noise reduction of spectral subtraction (Eq. 3 with Eq. 5 noise) on
  the no-contact blocks with the velocity-only baseline ("without the correction") and
  with the baseline times the found effect's term ("with"), both fitted on the other
  folds;
* the action, in the user's terms: a joint-state lag to set (the core's `joint_lag_s`,
  FramerSettings / StreamingDenoiser / CalibrationAccumulator), a recalibration after
  warm-up, a calibration key (position), a joint grid instead of superposition, motion
  with speed changes in the calibration;
* what the model still leaves above the floor (dB and share of the baseline's excess).

`measure_joint_lag(...)` applies the lag advice with the core itself: calibrate on one
recording and denoise another, with and without `joint_lag_s`, and compares the noise
reduction (the real flight in docs/gap.md).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from egovib_ros.core import calibrate_arrays, denoise_batch
from egovib_ros.core.filters import BandPass
from egovib_ros.core.subtraction import noise_gain_curve
from egovib_ros.errors import ConfigError
from egovib_ros.gap.diagnose import Diagnosis
from egovib_ros.gap.effects import drift_reach

#: A `none` verdict whose baseline stays more than this above the floor says so.
UNEXPLAINED_NOTE_DB = 0.3


def _noise_reduction(diag: Diagnosis, name: str) -> float:
    return -float(diag.residual_noise.get(name, float("nan")))


def _shape_span(shape: dict, prefix: str) -> tuple[str, float, dict]:
    """The curve of `shape` (keys starting with prefix) with the largest peak-to-trough."""
    best, span, curve = "", 0.0, {}
    for key, c in shape.items():
        if key.startswith(prefix) and "gain_db" in c:
            g = np.asarray(c["gain_db"], float)
            if g.size and float(np.ptp(g)) > span:
                best, span, curve = key.split(":", 1)[1], float(np.ptp(g)), c
    return best, span, curve


def action(diag: Diagnosis) -> tuple[str, dict]:
    """One sentence saying what to change, and the settings it names."""
    effect = diag.verdict
    model = diag.models.get(effect)
    shape = (model.shape or {}) if model is not None else {}
    if effect == "timing":
        p = model.parameters
        offset = float(p.get("lag_s", 0.0)) - float(p.get("reference_lag_s", 0.0))
        joint_lag = round(-offset, 4)
        way = "lead" if offset < 0 else "lag"
        return (
            f"joint states {way} the vibration by {1000 * abs(offset):.0f} ms: set "
            f"joint_lag: {joint_lag:g} (joint_lag_s of the calibration and the denoiser; "
            "it moves joint-state stamps later by that much)",
            {"joint_lag_s": joint_lag},
        )
    if effect == "drift":
        curves = [c for k, c in shape.items() if k.startswith("drift:")]
        curve = curves[-1] if curves else {}
        g = np.asarray(curve.get("gain_db", [0.0]), float)
        x = np.asarray(curve.get("x", [0.0]), float)
        change_db, reach = drift_reach(x, g)
        pct = 100.0 * (10 ** (change_db / 20.0) - 1.0)
        span = float(x[-1] - x[0]) if x.size else 0.0
        saturates = reach < 0.7 * (x[-1] if x.size else 0.0)
        return (
            f"vibration {'grows' if pct > 0 else 'falls'} {abs(pct):.0f} % over {span:.0f} s"
            + (
                f" (90 % of it within {reach:.0f} s): recalibrate after warm-up"
                if saturates
                else ": recalibrate periodically, or calibrate on a recording as long as use"
            ),
            {
                "recalibrate_after_s": round(reach, 1),
                "level_change_percent": round(pct, 1),
                # for `egovib denoise --noise-gain`: the level change from the start
                "noise_gain_db": [
                    [round(float(t - x[0]), 2), round(float(v - g[0]), 3)] for t, v in zip(x, g)
                ],
            },
        )
    if effect == "position":
        joint, span, curve = _shape_span(shape, "position:")
        loud = ""
        if curve:
            k = int(np.argmax(curve["gain_db"]))
            loud = f", loudest at {curve['x'][k]:.3g} {curve.get('unit', '')}"
        where = f"{joint}: {span:.1f} dB peak-to-trough{loud}" if span >= 0.1 else "bin by bin"
        return (
            f"position-dependent ({where}): calibrate with position as a key (or avoid that "
            "range while sensing)",
            {"calibration_key": "position", "joint": joint},
        )
    if effect == "coupling":
        pair, span, curve = _shape_span(shape, "coupling:")
        signed = np.asarray(curve.get("same_minus_opposite_direction_db", [[0.0]]), float)
        direction = (
            f", same vs opposite direction up to {np.max(np.abs(signed)):.1f} dB"
            if signed.size and np.max(np.abs(signed)) >= 0.5
            else ""
        )
        where = (
            f"{pair.replace('x', ' x ')}: up to {span:.1f} dB{direction}"
            if span >= 0.1
            else "bin by bin, flat across the band"
        )
        return (
            f"joints do not add ({where}): calibrate these joints on a joint velocity grid "
            "(sweep 'full' or free motion covering their combinations), not by superposition",
            {"calibration_sweep": "full", "joints": pair.split("x") if span >= 0.1 else []},
        )
    if effect == "acceleration":
        return (
            "joint acceleration adds vibration (speed changes, reversals): calibrate on free "
            "motion with speed changes like the task's, or over-subtract while joints "
            "accelerate",
            {"calibration_sweep": "free"},
        )
    above = float(diag.gaps["refit"] - diag.floor)
    if above > UNEXPLAINED_NOTE_DB:
        return (
            f"no effect of the vocabulary explains the rest ({above:.2f} dB above the floor "
            "stays unexplained): keep calibrating on velocity; record longer or more varied "
            "motion to tell more",
            {},
        )
    return ("the velocity-only model fits this recording: nothing to change", {})


def advise(diag: Diagnosis) -> dict:
    """report.json "advice": action, cost to the denoiser, unexplained rest."""
    text, settings = action(diag)
    without = _noise_reduction(diag, "after_refit")
    with_fix = _noise_reduction(diag, "after_effect")
    gaps = diag.gaps
    after = gaps[diag.verdict] if diag.verdict != "none" else gaps["refit"]
    floor = diag.floor
    excess_base = max(gaps["refit"] ** 2 - floor**2, 1e-12)
    excess_after = max(after**2 - floor**2, 0.0)
    return {
        "effect": diag.verdict,
        "action": text,
        "settings": settings,
        "denoiser": {
            "definition": "held-out noise reduction (dB, no-contact blocks, spectral "
            "subtraction with mean + sd noise) with the velocity-only baseline (without the "
            "correction) and with the baseline times the found effect's term (with it)",
            "noise_reduction_without_db": round(without, 3),
            "noise_reduction_with_db": round(with_fix, 3),
            "gain_db": round(with_fix - without, 3),
        },
        "unexplained": {
            "above_floor_db": round(after - floor, 3),
            "share_of_baseline_excess": round(float(excess_after / excess_base), 3),
            "note": "held-out gap of the baseline plus the found effect minus the floor; "
            "share = (gap^2 - floor^2) / (baseline gap^2 - floor^2)",
        },
    }


def first_lines(advice: dict) -> list[str]:
    """report.md's opening: what to do, what it costs, what is left."""
    d, u = advice["denoiser"], advice["unexplained"]
    lines = [f"**What to do:** {advice['action']}."]
    if advice["effect"] != "none":
        lines.append(
            f"**What it costs the denoiser:** held-out noise reduction "
            f"{d['noise_reduction_without_db']:.2f} dB without the correction, "
            f"{d['noise_reduction_with_db']:.2f} dB with it ({d['gain_db']:+.2f} dB)."
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
    `blocks_no_joint_state`; the core's warning about them is not printed)."""

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


__all__ = ["advise", "action", "first_lines", "measure_joint_lag"]
