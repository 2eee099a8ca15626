"""Online adaptation (issue 36, core.adapt): what `--adapt` gives, and what it must not cost.

    python -m egovib_research.experiments.adapt_compare --out DIR [--event-sets 5] [--quick]

`--quick` (tests, about 40 s): one event set, no oracle rows, 12 s PR2 runs.

Every figure compares the default method (hybrid, its drop-in output, band-passed to be
scored like `egovib evaluate` scores it) with the model fixed and with `adapt` at its
defaults (forget_s 30 s, guard 0.15 s, 10 dB/s), on data the model was not calibrated on.

1. Beyond the calibration: the shipped flight (bags/quadcopter_ar8) calibrated on a part
   and tested on the rest, known events added to the test part's real gyro
   (experiments.flight.events, the project's rule, `event_sets` seeds): `low` - calibrated
   on its low-throttle start (0-1 s: idle and spool-up, commands 0-0.30), tested on
   1-16.85 s (take-off, hover, punch-outs: 0.09-1.0; every test block on a cell the
   calibration never measured); `swapped` - methods_compare's split (calibrated on the
   hover, 8.5-16.85 s, tested on 0-8.5 s). Beside them the paper's table keyed on the
   summed (mean) motor command, calibrated on the same part. Target: noise reduction >= 3
   dB above the fixed model's, peak-SNR gain >= the fixed model's and >= the 1-D table's.
2. Warm-up: the PR2 simulator, a 60 s run (50 % speed, 1 tap/s) whose vibration grows by
   80 % over the 60 s (`--effects drift=0.8`), the model calibrated cold (a superposition
   sweep without drift) or warm (the same sweep at the run's end level, x 1.8: drift
   `warmup` with a 10 ms time constant). Target: with adapt the cold model recovers >= 80 %
   of the warm model's noise reduction (no `--noise-gain`).
3. Contacts kept: the PR2 at 2 taps/s (60 s, 50 % speed) and a contact-dense run (5 taps/s
   and a 0.3 s press about every second: band-limited vibration of a tap's size for 0.3 s),
   the cold model. Target: tap retention and F1 (the contact detector, thresholds from the
   calibration sweep) within 0.02 of the fixed model's. Figure: one cell's level over a
   third run that holds one speed (50 % of both joints, a cell the superposition sweep never
   measured) for 60 s while the robot warms up (+80 %) and is touched densely (5 taps/s and
   the presses): learnt as `adapt` learns it (gated), with the gate off, and from the same
   run without its contacts (what the cell should follow), the detector's crossings and the
   true contacts marked; the run's retention and F1 beside the others.

Scores are `egovib evaluate`'s (evaluation.evaluate.evaluate_recording) for the PR2 and
methods_compare's for the flight. The live figures (item 4 of the issue) come from
`egovib live-bench --adapt` (docs/live_bench.md). Writes DIR/adapt_compare.{md,json} and
DIR/adapt_cell_level.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import math
import time
from pathlib import Path

import numpy as np
from scipy import signal

from egovib_research.experiments import core_arrays, fmt, python_command, scoring
from egovib_research.experiments.flight import ATTRIBUTION
from egovib_research.experiments.flight.events import EventSpec, make_events
from egovib_research.experiments.flight.methods import build_methods
from egovib_research.experiments.flight.methods_compare import SPLITS
from egovib_research.experiments.flight.recording import read_flight_bag
from egovib_ros.bag import Recording, concat_recordings
from egovib_ros.core import calibrate_arrays
from egovib_ros.core.adapt import AdaptSettings
from egovib_ros.core.filters import combined_bandpassed
from egovib_ros.core.methods import (
    MethodCalibration,
    calibrate_detection,
    calibrate_methods,
    denoise_batch_method,
    make_denoiser,
)
from egovib_ros.evaluation import metrics
from egovib_ros.evaluation.evaluate import evaluate_recording
from egovib_ros.evaluation.metrics import json_safe
from egovib_ros.robot import load_profile
from egovib_ros.sim.hand import HandSimulator
from egovib_ros.sim.params import SimParams
from egovib_ros.sim.pr2 import JOINT_NAMES, MAX_SPEED
from egovib_ros.sim.scenarios import simulate_motion, simulate_sweep
from egovib_ros.viz import pyplot, save_figure

LOG = logging.getLogger("egovib_ros.adapt_compare")

FLIGHT_SPLITS = {"low": ((0.0, 1.0), (1.0, 16.85)), "swapped": SPLITS["swapped"]}
ADAPT = AdaptSettings()
KEYS = ("noise_reduction_db", "peak_snr_improvement_db", "tap_retention", "event_retention")
PRESS_S = 0.3
PRESS_EVERY_S = 1.0


# --------------------------------------------------------------------------------------
# 1. Beyond the calibration: the flight
# --------------------------------------------------------------------------------------
def _calibrated(rec, profile):
    paper, _ = calibrate_arrays(*core_arrays(rec), profile=profile, sweep="free")
    model, _ = calibrate_methods(paper, *core_arrays(rec))
    model, _ = calibrate_detection(model, *core_arrays(rec))
    return model


def _dropin_scored(rec, model, profile, adapt):
    """The default's drop-in output on `rec`, band-passed and summed as it is scored."""
    options = {} if adapt is None else {"adapt": adapt}
    stamps, values, _ = denoise_batch_method(*core_arrays(rec), model, **options)
    placed = np.zeros((len(rec.sensor_stamps_ns), 3))
    placed[np.searchsorted(rec.sensor_stamps_ns, stamps)] = values
    return combined_bandpassed(placed, profile)


def _oracles(model, cal, test, profile) -> dict:
    """What adaptation could reach at best, and which part of the calibration it would have
    to learn: the model with its residual table refitted on the test part's own noise (no
    events; the rest of the calibration kept); the table and the gain's statistics (alpha,
    bias, the guard's reference) refitted together, the calibration's harmonic map kept;
    the calibration part fitted again with the harmonic map the test part gives (the lines
    its speeds show); and the methods refitted on the test part altogether."""
    paper, _ = calibrate_arrays(*core_arrays(test), profile=profile, sweep="free")
    cal_fit = MethodCalibration.from_model(model)
    refit = MethodCalibration.from_model(
        calibrate_methods(paper, *core_arrays(test), harmonic=cal_fit.harmonic)[0]
    )
    table = dataclasses.replace(cal_fit, residual=refit.residual)
    table_gain = dataclasses.replace(
        table,
        alpha=refit.alpha,
        bias=refit.bias,
        open_alpha=refit.open_alpha,
        guard_ref=refit.guard_ref,
    )
    everything, _ = calibrate_methods(paper, *core_arrays(test))
    cal_paper, _ = calibrate_arrays(*core_arrays(cal), profile=profile, sweep="free")
    test_map = MethodCalibration.from_model(everything).harmonic
    with_map, _ = calibrate_methods(cal_paper, *core_arrays(cal), harmonic=test_map)

    def put(fit):
        return model.replace(extras={**model.extras, **fit.to_extras()})

    return {
        "oracle: table refitted on the test part": put(table),
        "oracle: table and gain statistics refitted on it": put(table_gain),
        "oracle: calibrated with the test part's harmonic map": with_map,
        "oracle: every method fit refitted on the test part": everything,
    }


def flight_split(rec, profile, name: str, event_sets: int, oracles: bool = True) -> dict:
    """One split (FLIGHT_SPLITS): fixed, adapt, the 1-D table and (`oracles`) the bounds."""
    (c0, c1), (t0, t1) = FLIGHT_SPLITS[name]
    cal, test = rec.part(c0, c1), rec.part(t0, t1)
    model = _calibrated(cal, profile)
    one_d = build_methods(profile, ("mean_command",))["mean_command"]
    one_d.fit(cal)
    oracles = _oracles(model, cal, test, profile) if oracles else {}
    rows = {"fixed": [], "adapt": [], "1-D table": [], **{key: [] for key in oracles}}
    fs = profile.rate_hz
    for seed in range(1, event_sets + 1):
        events = make_events(test.sensor_stamps_ns, test.sensor, profile,
                             spec=EventSpec(relative_amplitude=1.0, seed=seed))  # fmt: skip
        noisy = dataclasses.replace(test, sensor=test.sensor + events.signal)
        reference = combined_bandpassed(events.signal, profile)
        seg = metrics.segment_contacts(reference, sample_rate_hz=fs)
        raw = combined_bandpassed(noisy.sensor, profile)
        outputs = {
            "fixed": _dropin_scored(noisy, model, profile, None),
            "adapt": _dropin_scored(noisy, model, profile, ADAPT),
            "1-D table": one_d.run(noisy),
            **{key: _dropin_scored(noisy, m, profile, None) for key, m in oracles.items()},
        }
        peaks = scoring.tap_peaks(reference, seg.tap_windows)
        for key, out in outputs.items():
            row = scoring.signal_metrics(raw, out, reference, seg)
            row["event_retention"] = float(
                scoring.tap_peaks(out, seg.tap_windows).mean() / peaks.mean()
            )
            rows[key].append(row)
    pooled = {key: {k: float(np.mean([r[k] for r in v])) for k in KEYS} for key, v in rows.items()}
    span = [float(cal.joint_velocity.min()), float(cal.joint_velocity.max())]
    tested = [float(test.joint_velocity.min()), float(test.joint_velocity.max())]
    return {
        "calibration_s": [c0, c1],
        "test_s": [t0, t1],
        "commands": {"calibration": span, "test": tested},
        "event_sets": event_sets,
        "results": pooled,
    }


# --------------------------------------------------------------------------------------
# 2-3. The PR2 simulator: warm-up, contacts
# --------------------------------------------------------------------------------------
def _pr2_model(sweep):
    arrays = core_arrays(sweep)
    paper, _ = calibrate_arrays(*arrays, sweep="superposition")
    model, _ = calibrate_methods(paper, *arrays)
    model, _ = calibrate_detection(model, *arrays)
    return model


def _evaluated(run, model, calibration, adapt) -> dict:
    report = evaluate_recording(
        run, model, calibration=calibration, methods=["default"], adapt=adapt
    )
    default = report["methods"]["default"]
    out = {k: default[k] for k in ("noise_reduction_db", "peak_snr_improvement_db",
                                   "tap_retention", "f1")}  # fmt: skip
    if "adapt" in default:
        out["adapt"] = default["adapt"]
    return out


def warm_up(cold_sweep, cold, params, duration_s: float, dwell_s: float) -> dict:
    warm_params = dataclasses.replace(
        params, effect_forms={**params.effect_forms, "drift": "warmup"}, warmup_tau_s=0.01
    )
    warm_sweep, _ = simulate_sweep(
        grid="superposition", dwell_s=dwell_s, settle_s=0.5, effects={"drift": 0.4}, seed=11,
        params=warm_params,
    )  # fmt: skip
    warm = _pr2_model(warm_sweep)
    run, _ = simulate_motion(
        duration_s=duration_s, max_speed=0.5, tap_rate_hz=1.0, effects={"drift": 0.8},
        seed=3, params=params,
    )  # fmt: skip
    return {
        "run": f"{duration_s:g} s at 50 % speed, 1 tap/s, drift=0.8 (x1.8 at 60 s)",
        "cold fixed": _evaluated(run, cold, cold_sweep, None),
        "cold adapt": _evaluated(run, cold, cold_sweep, ADAPT),
        "warm fixed": _evaluated(run, warm, warm_sweep, None),
    }


def with_presses(run, params: SimParams, seed: int):
    """`run` with a PRESS_S press about every PRESS_EVERY_S: band-limited vibration (200-600
    Hz) along the taps' direction, 10 ms raised-cosine edges, band-passed peak about a tap's
    (tap_peak_ms2), added to the sensor and to the ground truth. Returns (run, onsets)."""
    rng = np.random.default_rng(seed)
    fs = 3000.0
    n = len(run.sensor_stamps_ns)
    length, edge = int(PRESS_S * fs), int(0.01 * fs)
    envelope = np.ones(length)
    ramp = 0.5 - 0.5 * np.cos(np.pi * np.arange(edge) / edge)
    envelope[:edge], envelope[-edge:] = ramp, ramp[::-1]
    sos = signal.butter(4, (200.0, 600.0), btype="band", fs=fs, output="sos")
    direction = np.asarray(params.tap_direction, float)
    direction /= np.linalg.norm(direction)
    contact = np.zeros((n, 3))
    onsets = []
    start = int(rng.uniform(0.3, PRESS_EVERY_S) * fs)
    while start + length < n:
        texture = signal.sosfilt(sos, rng.normal(size=length + 600))[600:]
        texture *= params.tap_peak_ms2 / (3.0 * texture.std()) * envelope
        contact[start : start + length] += texture[:, None] * direction[None, :]
        onsets.append(start)
        start += int(rng.uniform(0.6, 1.4) * PRESS_EVERY_S * fs)
    changed = dataclasses.replace(run, sensor=run.sensor + contact, contact=run.contact + contact)
    return changed, np.array(onsets)


def dense_params(params: SimParams) -> SimParams:
    """The simulator's taps at 5 a second: random onsets 0.1 s apart at least (its dead
    time, 0.25 s by default, caps them at 3.7 a second)."""
    return dataclasses.replace(params, tap_dead_time_s=0.1)


def held_run(params: SimParams, duration_s: float, seed: int):
    """The hand holding 50 % of both joints' speeds (the gripper reversing at its limits)
    for `duration_s`, warming up (drift=0.8), tapped at 5 a second, with the presses."""
    sim = HandSimulator(dense_params(params), effects={"drift": 0.8}, seed=seed, tap_rate_hz=5.0)
    sim.set_command(0.5 * np.asarray(MAX_SPEED, float))
    chunks = [sim.step(3000) for _ in range(int(round(duration_s)))]
    run = concat_recordings(
        [
            Recording(
                sensor_stamps_ns=c.sensor_stamps_ns,
                sensor=c.sensor,
                joint_stamps_ns=c.joint_stamps_ns,
                joint_position=c.joint_position,
                joint_velocity=c.joint_velocity,
                joint_names=JOINT_NAMES,
                contact=c.contact,
                ego=c.ego,
            )
            for c in chunks
        ]
    )
    return with_presses(run, params, seed=seed + 1)[0]


def contacts(cold_sweep, cold, params, duration_s: float) -> tuple[dict, dict]:
    out = {}
    taps2, _ = simulate_motion(
        duration_s=duration_s, max_speed=0.5, tap_rate_hz=2.0, seed=21, params=params
    )
    dense, _ = simulate_motion(
        duration_s=duration_s, max_speed=0.5, tap_rate_hz=5.0, seed=22,
        params=dense_params(params),
    )  # fmt: skip
    dense, _ = with_presses(dense, params, seed=23)
    held = held_run(params, duration_s, seed=24)
    runs = (
        ("2 taps/s", taps2),
        ("dense: 5 taps/s + 0.3 s presses", dense),
        ("held speed, warming up, dense", held),
    )
    for name, run in runs:
        out[name] = {
            "fixed": _evaluated(run, cold, cold_sweep, None),
            "adapt": _evaluated(run, cold, cold_sweep, ADAPT),
        }
    return out, cell_trace(held, cold)


def _learn_in_steps(run, model, adapt: AdaptSettings, cell: int | None):
    """`run` through an adapting denoiser 50 ms at a time; after each, the learnt power of
    `cell` (x, y, z, all bins; NaN before it is learnt). Returns (denoiser, the gate's runs
    above its threshold, [(stamp, power)])."""
    denoiser = make_denoiser(model, adapt=adapt)
    adaptation = denoiser._adaptation
    above, trace = [], []
    push = adaptation.gate.push

    def spy(stamps, values):
        push(stamps, values)
        for r in adaptation.gate._intervals:
            if r not in above:
                above.append(list(r))

    adaptation.gate.push = spy
    t, accel, tj, vj = core_arrays(run)
    step = int(0.05 * model.sample_rate_hz)
    j = 0
    for a in range(0, len(t), step):
        stop = min(a + step, len(t))
        k = int(np.searchsorted(tj, t[stop - 1] + 21_000_000, side="right"))
        denoiser.push_joint_states(tj[j:k], vj[j:k])
        j = k
        denoiser.push_sensor(t[a:stop], accel[a:stop])
        if cell is not None:
            row = adaptation.cells.row_of.get(cell)
            power = np.nan if row is None else float(adaptation.cells.power[row, 1:].sum())
            trace.append((int(t[stop - 1]), power))
    denoiser.push_joint_states(tj[j:], vj[j:])
    denoiser.flush()
    return denoiser, above, trace


def cell_trace(run, model) -> dict:
    """The held run's most-taught cell, learnt three ways (see the module doc)."""
    first, _, _ = _learn_in_steps(run, model, ADAPT, None)
    cells = first._adaptation.cells
    row = int(np.argmax(cells.blocks))
    cell = int(np.ravel_multi_index(tuple(cells.cells[row]), cells.shape))
    gated, above, trace = _learn_in_steps(run, model, ADAPT, cell)
    open_gate = dataclasses.replace(ADAPT, threshold=1e12)
    ungated, _, trace_open = _learn_in_steps(run, model, open_gate, cell)
    quiet = dataclasses.replace(run, sensor=run.sensor - run.contact, contact=0 * run.contact)
    clean, _, trace_clean = _learn_in_steps(run=quiet, model=model, adapt=open_gate, cell=cell)
    t0 = int(run.sensor_stamps_ns[0])
    fs = model.sample_rate_hz
    contact_env = np.abs(combined_bandpassed(run.contact, model.robot_profile())) > 0.05
    edges = np.diff(np.r_[False, contact_env, False].astype(np.int8))
    truth = np.stack([np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)], axis=1) / fs
    blocks = {
        name: int(d._adaptation.cells.blocks[d._adaptation.cells.row_of[cell]])
        if cell in d._adaptation.cells.row_of
        else 0
        for name, d in (("gated", gated), ("gate off", ungated), ("no contacts", clean))
    }
    return {
        "cell": [float(model.grid[j][i]) for j, i in enumerate(cells.cells[row].tolist())],
        "cell_new": bool(cells.new[row]),
        "blocks": blocks,
        "contact_share": float(contact_env.mean()),
        "trace": [
            [(s - t0) / 1e9, p, q, r]
            for (s, p), (_, q), (_, r) in zip(trace, trace_open, trace_clean)
        ],
        "detections": [[(a - t0) / 1e9, (b - t0) / 1e9] for a, b in above],
        "contacts": truth.tolist(),
    }


# --------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------
def checks(result: dict) -> list[tuple[str, str, float, float, bool]]:
    out = []
    for split, r in result["flight"].items():
        res = r["results"]
        fixed, adapt, one = res["fixed"], res["adapt"], res["1-D table"]
        where = f"flight, {split}"
        out += [
            (where, "noise reduction >= fixed + 3 dB", adapt["noise_reduction_db"],
             fixed["noise_reduction_db"] + 3.0, None),
            (where, "peak-SNR gain >= fixed", adapt["peak_snr_improvement_db"],
             fixed["peak_snr_improvement_db"], None),
            (where, "peak-SNR gain >= 1-D table", adapt["peak_snr_improvement_db"],
             one["peak_snr_improvement_db"], None),
        ]  # fmt: skip
    w = result["warm_up"]
    out.append(
        ("warm-up", "noise reduction >= 80 % of the warm model's",
         w["cold adapt"]["noise_reduction_db"], 0.8 * w["warm fixed"]["noise_reduction_db"], None)
    )  # fmt: skip
    for name, r in result["contacts"].items():
        for key in ("tap_retention", "f1"):
            diff = r["adapt"][key] - r["fixed"][key]
            out.append((name, f"{key}: adapt - fixed within 0.02", diff, 0.02, abs(diff) <= 0.02))
    return [
        (where, what, value, target, value >= target - 1e-12 if met is None else met)
        for where, what, value, target, met in out
    ]


def _oracle_sentence(result: dict) -> str:
    """What the oracle rows of each split add to the fixed model's noise reduction."""
    parts = []
    for split, r in result["flight"].items():
        res = r["results"]
        fixed = res["fixed"]["noise_reduction_db"]
        gains = {
            key.removeprefix("oracle: "): res[key]["noise_reduction_db"] - fixed
            for key in res
            if key.startswith("oracle: ")
        }
        if gains:
            listed = "; ".join(f"{key} {value:+.1f} dB" for key, value in gains.items())
            parts.append(f"On the {split} split: {listed}.")
    if not parts:
        return "(not computed: --quick)."
    return (
        " ".join(parts) + " So the low split lacks the motor lines its 1-s idle start never "
        "showed (the map alone reaches +3 dB there: line discovery, not cells), and "
        "the swapped split lacks the table and the gain's opening statistics refitted "
        "together (each alone adds a fraction of what both do: the gain's alpha is a "
        "quantile of the level over the table's prediction)."
    )


def _gain(result: dict, split: str) -> str:
    """`adapt` against the fixed model on a split, in words."""
    res = result["flight"][split]["results"]
    fixed, adapt = (res[k]["noise_reduction_db"] for k in ("fixed", "adapt"))
    return f"{fixed:.1f} -> {adapt:.1f} dB ({adapt - fixed:+.1f})"


def markdown(result: dict) -> str:
    lines = [
        "# Online adaptation: `--adapt` against the fixed model",
        "",
        f"Regenerate: `{result['command']}` ({result['runtime_s']:.0f} s; load average "
        f"{result['load_average']:.1f} at the start). The default method (hybrid, drop-in "
        f"output band-passed to score) with the model fixed and with `adapt` at its defaults "
        f"(forget_s {ADAPT.forget_s:g} s, guard {ADAPT.guard_s:g} s, "
        f"{ADAPT.max_rate_db_s:g} dB/s). Flight data: {ATTRIBUTION}.",
        "",
        "## Targets",
        "",
        "| where | criterion | value | target | met |",
        "|---|---|---|---|---|",
    ]
    for where, what, value, target, met in checks(result):
        lines.append(f"| {where} | {what} | {value:.3f} | {target:.3f} | "
                     f"{'yes' if met else '**no**'} |")  # fmt: skip
    lines += ["", "## Beyond the calibration: the flight", ""]
    for split, r in result["flight"].items():
        c = r["commands"]
        lines += [
            f"**{split}**: calibrated on {r['calibration_s'][0]:g}-{r['calibration_s'][1]:g} s "
            f"(commands {c['calibration'][0]:.2f}-{c['calibration'][1]:.2f}), tested on "
            f"{r['test_s'][0]:g}-{r['test_s'][1]:g} s ({c['test'][0]:.2f}-{c['test'][1]:.2f}), "
            f"events at the project's rule, {r['event_sets']} sets (means).",
            "",
            "| | noise reduction dB | peak-SNR gain dB | retention of the raw peak | "
            "retention of the event |",
            "|---|---|---|---|---|",
        ]
        for key, row in r["results"].items():
            lines.append(
                f"| {key} | {fmt(row['noise_reduction_db'])} | "
                f"{fmt(row['peak_snr_improvement_db'])} | {fmt(row['tap_retention'], 2)} | "
                f"{fmt(row['event_retention'], 2)} |"
            )
        lines.append("")
    lines += [
        "**Lines the calibration never showed.** The low split's calibration (1 s at "
        "idle) found no motor line, so its harmonic map has none; `adapt` finds them "
        "(core.adapt.LineFinder: once the contact-free input holds 0.5 s at speeds beyond "
        "the calibrated ones, the map is fitted again on its last 8 s in a worker process, "
        "and the joints whose calibration showed no line take its lines if they cancel "
        f"0.5 dB more there): {_gain(result, 'low')}. The first map is in use about 2.4 s "
        "into the test part (a fit needs about 1 s of contact-free input at the new speeds, "
        "and runs beside the stream for 0.5 s plus 0.35 s per second fitted), after the "
        "loudest seconds of the climb; later refits on more data replace it where they "
        "cancel more (a map fitted on the last 8 s, used from the first sample, removes "
        "less than this succession: the maps follow the flight). The oracle with the test "
        "part's map from its first sample is the bound. Where the "
        "calibration's map has lines on every joint (the swapped split, the PR2), nothing "
        "is refitted: a map fitted at the new speeds alone cancelled less at the "
        "calibrated ones.",
        "",
        "**Why the cells add little.** The default method's gain already follows how "
        "the noise level stands against its table: a per-band level tracker (0.3 s, +-15 dB) "
        "and a guard that treats a lasting excess as noise. A learnt cell gives the tracker a "
        "better starting point where the speeds come back; on this flight a cell beyond the "
        "calibration is met for about 25 ms at a time (4 motors on a 0.1 grid: 123 new cells "
        "in 3 s of the swapped test), and in the long hover the tracker has long converged. "
        "The oracle rows say what an online learner would have to learn to reach +3 dB, "
        "each fitted on the test part's own noise (without the events), so out of reach of "
        "any learner but a bound. " + _oracle_sentence(result) + " What the cells and the "
        "map's amplitudes and corrections learn is none of these; learning faster does not "
        "help either (forget_s 3 s, 100 dB/s, a looser steadiness rule: -0.1 to -0.3 dB on "
        "both splits, one event set). A per-band online quantile of the gain's opening, "
        "tried as a prototype on the swapped split without the table, gave at most +2 dB, "
        "and only when learning fast.",
        "",
    ]
    w = result["warm_up"]
    lines += [
        "## Warm-up: the PR2 simulator",
        "",
        f"{w['run']}; thresholds from each model's own sweep.",
        "",
        "| model | noise reduction dB | peak-SNR gain dB | tap retention | F1 |",
        "|---|---|---|---|---|",
    ]
    for key in ("cold fixed", "cold adapt", "warm fixed"):
        row = w[key]
        lines.append(
            f"| {key} | {fmt(row['noise_reduction_db'])} | "
            f"{fmt(row['peak_snr_improvement_db'])} | {fmt(row['tap_retention'], 3)} | "
            f"{fmt(row['f1'], 3)} |"
        )
    lines += [
        "",
        "## Contacts kept: the PR2 simulator",
        "",
        "| run | model | noise reduction dB | tap retention | F1 | blocks learnt / left out "
        "for contacts | cells learnt (new) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, r in result["contacts"].items():
        for key in ("fixed", "adapt"):
            row = r[key]
            a = row.get("adapt")
            learnt = f"{a['blocks_learnt']} / {a['blocks_gated']}" if a else ""
            cells = f"{a['cells_learnt']} ({a['cells_new']})" if a else ""
            lines.append(
                f"| {name} | {key} | {fmt(row['noise_reduction_db'])} | "
                f"{fmt(row['tap_retention'], 3)} | {fmt(row['f1'], 3)} | {learnt} | {cells} |"
            )
    tr = result["cell_trace"]
    cell = ", ".join(f"{v:.3g}" for v in tr["cell"])
    lines += [
        "",
        "![one cell's level over the held run](adapt_cell_level.png)",
        "",
        f"The held run's most-visited cell ({cell}: "
        f"{'never calibrated' if tr['cell_new'] else 'calibrated'}; contacts "
        f"{100 * tr['contact_share']:.0f} % of the time): its learnt power (x, y, z) over "
        f"time, as `adapt` learns it (the gate: nothing within {ADAPT.guard_s:g} s of a "
        f"detector crossing; {tr['blocks']['gated']} blocks), with the gate off "
        f"({tr['blocks']['gate off']} blocks: the contacts learnt as noise) and from the same "
        f"run without its contacts ({tr['blocks']['no contacts']} blocks: the warm-up it "
        "should follow).",
        "",
    ]
    return "\n".join(lines)


def figure(trace: dict, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(11, 4.4))
    data = np.array(trace["trace"], float)
    t = data[:, 0]
    clean = data[:, 3]
    reference = clean[np.isfinite(clean)][0] if np.isfinite(clean).any() else 1.0
    for a, b in trace["contacts"]:
        ax.axvspan(a, b, color="0.88", lw=0)
    for a, _ in trace["detections"]:
        ax.axvline(a, ymin=0.0, ymax=0.04, color="tab:orange", lw=0.6)
    styles = (
        (1, "adapt (gated by the contact detector)", "tab:blue", 1.8),
        (2, "the gate off: contacts learnt as noise", "tab:red", 1.0),
        (3, "the run without its contacts (the warm-up to follow)", "black", 1.0),
    )
    for column, label, colour, width in styles:
        ax.plot(t, 10 * np.log10(data[:, column] / reference), color=colour, lw=width,
                label=label)  # fmt: skip
    ax.plot([], [], color="0.88", lw=6, label="true contacts (taps, 0.3 s presses)")
    ax.plot([], [], color="tab:orange", lw=1, label="contact detector crossings")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("learnt power, dB")
    ax.set_xlim(t[0], t[-1])
    ax.legend(fontsize=7, loc="upper left")
    cell = ", ".join(f"{v:.3g}" for v in trace["cell"])
    ax.set_title(
        f"One cell ({cell}) over 60 s at a held speed: warming up +80 %, 5 taps/s and presses",
        fontsize=10,
    )
    save_figure(fig, path, dpi=110)


def run(out_dir: Path, *, event_sets: int, quick: bool, bag: str, command: str) -> dict:
    begin = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    result = {"command": command, "load_average": __import__("os").getloadavg()[0]}
    profile = load_profile("quadcopter")
    rec = read_flight_bag(bag, profile)
    result["flight"] = {}
    for split in FLIGHT_SPLITS:
        LOG.info("flight, %s split", split)
        result["flight"][split] = flight_split(
            rec, profile, split, 1 if quick else event_sets, oracles=not quick
        )
    params = SimParams.load()
    dwell = 0.6 if quick else 2.0
    duration = 12.0 if quick else 60.0
    LOG.info("PR2: cold sweep")
    cold_sweep, _ = simulate_sweep(
        grid="superposition", dwell_s=dwell, settle_s=0.5, seed=11, params=params
    )
    cold = _pr2_model(cold_sweep)
    LOG.info("PR2: warm-up")
    result["warm_up"] = warm_up(cold_sweep, cold, params, duration, dwell)
    LOG.info("PR2: contacts")
    result["contacts"], result["cell_trace"] = contacts(cold_sweep, cold, params, duration)
    result["runtime_s"] = time.perf_counter() - begin
    result["checks"] = [
        {"where": w, "criterion": c, "value": v, "target": t, "met": m}
        for w, c, v, t, m in checks(result)
    ]
    figure(result["cell_trace"], out_dir / "adapt_cell_level.png")
    (out_dir / "adapt_compare.json").write_text(json.dumps(json_safe(result), indent=1) + "\n")
    (out_dir / "adapt_compare.md").write_text(markdown(result))
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", required=True, help="directory for adapt_compare.*")
    parser.add_argument("--bag", default="bags/quadcopter_ar8", help="the flight bag")
    parser.add_argument("--event-sets", type=int, default=5)
    parser.add_argument(
        "--quick", action="store_true", help="short runs, no oracle rows (for tests)"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("egovib_ros.core").setLevel(logging.ERROR)
    out = Path(args.out)
    result = run(
        out,
        event_sets=args.event_sets,
        quick=args.quick,
        bag=args.bag,
        command=python_command("egovib_research.experiments.adapt_compare", argv),
    )
    print(markdown(result))
    print(f"wrote {out / 'adapt_compare.md'}, {out / 'adapt_compare.json'}")
    return 0 if math.isfinite(result["runtime_s"]) else 1


if __name__ == "__main__":
    raise SystemExit(main())
