"""report.json (INTERFACES.md section 6), report.md and figures of a gap diagnosis."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from egovib_ros.gap import metric
from egovib_ros.gap.advice import LAG_CONVENTION, advise, effect_action, first_lines, joint_lag_of
from egovib_ros.gap.diagnose import (
    ALPHA,
    METRIC_DEFINITION,
    METRIC_NAME,
    MIN_DEVIANCE_GAIN,
    MIN_DEVIANCE_GAIN_LATER,
    Diagnosis,
)
from egovib_ros.gap.effects import angle_joints, drift_reach
from egovib_ros.gap.features import KNOT_REFINE
from egovib_ros.viz import pyplot, save_figure

SCHEMA = "egovib.gap/1"
#: Frequency bands used to name regions (Hz edges; bins are assigned by centre frequency).
REGION_BANDS_HZ = (150.0, 300.0, 450.0, 600.0, 751.0)
N_COVARIATE_BINS = 8
#: Speed classes (fraction of the joint's top grid speed) naming regions.
SPEED_CLASSES = ("still", "slow", "fast")
SPEED_CLASS_EDGES = (0.1, 0.5)


def _r(x: float, nd: int = 4) -> float:
    return None if x is None or not np.isfinite(x) else round(float(x), nd)


def _pick(entry: dict, *keys: str) -> dict:
    """Those of `keys` that `entry` holds, in that order (a p-value rounded to 6 digits)."""
    return {k: _r(entry[k], 6) if k == "p_value" else entry[k] for k in keys if k in entry}


def velocity_cells(diag: Diagnosis, velocity: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """Nearest model grid cell (flat index) of each velocity row, and the grids."""
    grid = diag.table.model.grid
    idx = [np.abs(velocity[:, j, None] - g[None, :]).argmin(axis=1) for j, g in enumerate(grid)]
    return np.ravel_multi_index(idx, tuple(len(g) for g in grid)), list(grid)


def _percent_of_max(grid: list[np.ndarray], index) -> list[int]:
    """A velocity cell's speeds, in % of each joint's top grid speed."""
    return [int(round(100 * grid[j][i] / np.max(np.abs(grid[j])))) for j, i in enumerate(index)]


def _window_means(diag: Diagnosis, values: np.ndarray) -> np.ndarray:
    """Means of per-block values (B, K) over each held-out window."""
    w = diag.windows
    counts = np.bincount(w.index[w.members()], minlength=w.n_windows)
    return metric.window_sums(values[diag.heldout_rows], w) / counts[:, None]


def covariate_series(diag: Diagnosis) -> dict[str, tuple[np.ndarray, str, bool]]:
    """name -> (per-block value, unit, periodic) for the covariate breakdowns."""
    t = diag.table
    out = {}
    angles = angle_joints(t.joint_names, t.position)
    for j, name in enumerate(t.joint_names):
        periodic = bool(angles[j])
        pos = np.mod(t.position[:, j], 2 * np.pi) if periodic else t.position[:, j]
        out[f"position:{name}"] = (pos, "rad (mod 2pi)" if periodic else "joint unit", periodic)
    for j, name in enumerate(t.joint_names):
        out[f"acceleration:{name}"] = (t.acceleration[:, j], "|joint unit/s^2|", False)
    out["elapsed_time"] = (t.t_mid_s, "s", False)
    return out


def _bin_edges(values: np.ndarray, periodic: bool) -> np.ndarray:
    if periodic:
        return np.linspace(0.0, 2 * np.pi, N_COVARIATE_BINS + 1)
    edges = np.unique(np.quantile(values, np.linspace(0, 1, N_COVARIATE_BINS + 1)))
    return edges if len(edges) > 1 else np.array([values.min(), values.min() + 1e-9])


def covariate_breakdown(diag: Diagnosis) -> dict:
    """Per covariate: bins, held-out bias [dB] of sim as-is and after refit,
    share of the refit's gap^2."""
    rows = diag.heldout_rows
    t = diag.table
    refit = diag.models["refit"].predicted
    out = {}
    for name, (values, unit, periodic) in covariate_series(diag).items():
        v = values[rows]
        edges = _bin_edges(v, periodic)
        nb = len(edges) - 1
        labels = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, nb - 1)
        bias_as_is, counts = metric.grouped_bias_db(
            t.magnitude[rows], t.base_mean[rows], labels, nb
        )
        bias_refit, _ = metric.grouped_bias_db(t.magnitude[rows], refit[rows], labels, nb)
        wvals = _window_means(diag, values[:, None])[:, 0]
        wl = np.clip(np.searchsorted(edges, wvals, side="right") - 1, 0, nb - 1)
        share, _ = metric.contributions(diag.errors["refit"], wl, nb)
        out[name] = {
            "unit": unit,
            "bin_edges": [_r(e, 5) for e in edges],
            "blocks": counts.tolist(),
            "bias_db_sim_as_is": [_r(b, 3) for b in bias_as_is],
            "bias_db_after_refit": [_r(b, 3) for b in bias_refit],
            "gap2_share_after_refit_db2": [_r(s, 5) for s in share.sum(axis=1)],
            "spread_db_after_refit": _r(np.nanmax(bias_refit) - np.nanmin(bias_refit), 3),
        }
    if diag.lag_scan:
        scan = diag.lag_scan
        out["stream_lag"] = {
            "unit": "s (joint lag: " + LAG_CONVENTION + ")",
            "fitted_joint_lag_s": round(joint_lag_of(scan["timing_lag_s"]), 5),
            "in_sync_joint_lag_s": round(joint_lag_of(scan["sync_lag_s"]), 5),
            "joint_lag_s": [round(joint_lag_of(x), 4) for x in scan["lag_s"]][::-1],
            "train_log_residual": [round(float(x), 6) for x in scan["train_log_residual"]][::-1],
            "note": "residual of the velocity-only baseline with joint states "
            "re-matched at each joint lag",
        }
    return out


def _band_of_bins(freqs: np.ndarray) -> np.ndarray:
    return np.clip(
        np.searchsorted(REGION_BANDS_HZ, freqs, side="right") - 1, 0, len(REGION_BANDS_HZ) - 2
    )


def where_breakdown(diag: Diagnosis) -> dict:
    """Gap by frequency bin, by velocity cell, by covariate; ranked regions."""
    t = diag.table
    e_as_is, e_refit = diag.errors["sim_as_is"], diag.errors["refit"]
    e_eff = diag.errors[diag.verdict] if diag.verdict != "none" else e_refit
    total = max(metric.gap_db(e_as_is) ** 2, 1e-12)
    freq = [
        {
            "hz": _r(f, 2),
            "sim_as_is_db": _r(np.sqrt(np.mean(e_as_is[:, k] ** 2)), 3),
            "bias_db_sim_as_is": _r(np.mean(e_as_is[:, k]), 3),
            "after_refit_db": _r(np.sqrt(np.mean(e_refit[:, k] ** 2)), 3),
            "after_effect_db": _r(np.sqrt(np.mean(e_eff[:, k] ** 2)), 3),
            "share_of_gap2_sim_as_is": _r(
                np.mean(e_as_is[:, k] ** 2) / e_as_is.shape[1] / total, 4
            ),
        }
        for k, f in enumerate(t.freqs_hz)
    ]
    wv = _window_means(diag, t.velocity)
    cell, grid = velocity_cells(diag, wv)
    shape = tuple(len(g) for g in grid)
    share, counts = metric.contributions(e_as_is, cell, int(np.prod(shape)))
    share_r, _ = metric.contributions(e_refit, cell, int(np.prod(shape)))
    cells = []
    for c in np.flatnonzero(counts):
        idx = np.unravel_index(c, shape)
        sel = cell == c
        cells.append(
            {
                "velocity": [_r(grid[j][i], 5) for j, i in enumerate(idx)],
                "percent_of_max": _percent_of_max(grid, idx),
                "windows": int(counts[c]),
                "bias_db_sim_as_is": _r(np.mean(e_as_is[sel]), 3),
                "gap2_share_sim_as_is_db2": _r(share[c].sum(), 5),
                "gap2_share_after_refit_db2": _r(share_r[c].sum(), 5),
            }
        )
    cells.sort(key=lambda d: -d["gap2_share_sim_as_is_db2"])
    # Ranked regions: (speed class of each joint, frequency band), by share of the sim's gap^2.
    bands = _band_of_bins(t.freqs_hz)
    speed_class = np.digitize(np.abs(wv) / t.vmax, SPEED_CLASS_EDGES)  # (n_windows, J) 0..2
    region_id = np.ravel_multi_index(
        tuple(speed_class.T), (len(SPEED_CLASSES),) * speed_class.shape[1]
    )
    regions = []
    for rid in np.unique(region_id):
        sel = region_id == rid
        classes = np.unravel_index(rid, (len(SPEED_CLASSES),) * speed_class.shape[1])
        for b in range(len(REGION_BANDS_HZ) - 1):
            cols = bands == b
            if not cols.any():
                continue
            s2 = float(np.sum(e_as_is[sel][:, cols] ** 2) / e_as_is.size)
            regions.append(
                {
                    "speeds": {n: SPEED_CLASSES[c] for n, c in zip(t.joint_names, classes)},
                    "band_hz": [REGION_BANDS_HZ[b], min(REGION_BANDS_HZ[b + 1], 750.0)],
                    "share_of_gap2": _r(s2 / total, 4),
                    "bias_db": _r(np.mean(e_as_is[sel][:, cols]), 3),
                    "rms_db": _r(np.sqrt(np.mean(e_as_is[sel][:, cols] ** 2)), 3),
                    "windows": int(sel.sum()),
                }
            )
    regions.sort(key=lambda d: -d["share_of_gap2"])
    return {
        "frequency_hz": freq,
        "velocity_cells": cells,
        "covariates": covariate_breakdown(diag),
        "ranked_regions": regions[:15],
    }


def public_parameters(params: dict) -> dict:
    """A term's parameters for the report: the diagnosis's internal lags (joint states
    stamped that late) in the joint-lag convention (LAG_CONVENTION); `joint_lag_s` is the
    correction to set (the recording's joint lag minus the reference's)."""
    out = dict(params)
    if "lag_s" in out:
        lag = float(out.pop("lag_s"))
        reference = float(out.pop("reference_lag_s", 0.0))
        sync = out.pop("sync_lag_s", None)
        out.pop("lag_vs_simulator_s", None)
        out = {
            "joint_lag_s": round(joint_lag_of(lag - reference), 5),
            "fitted_joint_lag_s": round(joint_lag_of(lag), 5),
            "reference_joint_lag_s": round(joint_lag_of(reference), 5),
            **({"in_sync_joint_lag_s": round(joint_lag_of(sync), 5)} if sync is not None else {}),
            **out,
        }
    return out


def public_shape(shape: dict) -> dict:
    """A term's fitted shapes for the report, the lag scan in the joint-lag convention."""
    out = dict(shape)
    scan = out.get("timing:lag_scan")
    if scan is not None:
        lo, hi = scan["in_sync_band_s"]
        out["timing:lag_scan"] = {
            "x": [round(joint_lag_of(v), 4) for v in scan["x"]][::-1],
            "unit": "s (joint lag)",
            "train_log_residual": list(scan["train_log_residual"])[::-1],
            "in_sync_band_s": [round(joint_lag_of(hi), 4), round(joint_lag_of(lo), 4)],
            "fitted_joint_lag_s": round(joint_lag_of(scan["fitted_lag_s"]), 5),
        }
    return out


def effects_list(diag: Diagnosis) -> list[dict]:
    """verdict.effects: the effects found in order, each with its held-out reduction given
    the ones before, p-value, confidence, parameters and advice (CONTRACT section 6)."""
    out = []
    for entry, model in zip(diag.effects, diag.effect_models):
        text, settings = effect_action(entry["effect"], model)
        out.append(
            {
                **_pick(entry, "effect", "reduction", "p_value", "confidence"),
                "parameters": public_parameters(model.parameters),
                "advice": text,
                "settings": settings,
                **_pick(entry, "step", "heldout_gap_before", "heldout_gap", "deviance_reduction"),
                "shape_summary": describe_shape(public_shape(model.shape or {})),
                **_pick(entry, "decided_by"),
            }
        )
    return out


def selection_steps(diag: Diagnosis) -> list[dict]:
    """Every forward-selection step: the effects it was given, what each remaining candidate
    added on top of them (held out) and the effect it took (none: the selection stopped)."""
    return [
        {
            "step": st["step"],
            "given": st["prefix"],
            "effect": st["effect"],
            "confidence": st["confidence"],
            "candidates": [
                _pick(c, "effect", "heldout_gap", "reduction", "p_value", "deviance_reduction")
                for c in st["candidates"]
            ],
        }
        for st in diag.steps
    ]


def build_report(
    diag: Diagnosis,
    *,
    model_path: str,
    real_path: str,
    figures: dict[str, str],
    runtime_s: float,
    write_back: dict | None = None,
    measured: dict | None = None,
    report_path: str | None = None,
    robot: str | None = None,
) -> dict:
    """The report.json dictionary (INTERFACES.md section 6 keys, plus documented extras).
    `measured`: the advice applied with the user's model (advice.measure_advice);
    `report_path`: where report.json will be (the advice's commands name it); `robot`:
    calibrate's --robot in them (robot.robot_option)."""
    t = diag.table
    found = diag.verdict != "none"
    added = {
        "effect": diag.verdict,
        "parameters": public_parameters(diag.models[diag.verdict].parameters) if found else {},
    }
    if write_back:
        added["simulator"] = write_back
    where = where_breakdown(diag)
    paths = {"model": str(model_path), "bag": str(real_path), "robot": robot}
    if report_path:
        paths["report"] = str(report_path)

    return {
        "schema": SCHEMA,
        "advice": advise(diag, paths=paths, measured=measured),
        "conventions": {"joint_lag": LAG_CONVENTION},
        "metric": {
            "name": METRIC_NAME,
            "unit": "dB",
            "definition": METRIC_DEFINITION.format(
                w=diag.window_blocks, ws=diag.window_blocks * float(np.median(np.diff(t.t_mid_s)))
            ),
        },
        "split": {k: (_r(v, 3) if isinstance(v, float) else v) for k, v in diag.split_info.items()},
        "gap": {
            "sim_as_is": _r(diag.gaps["sim_as_is"]),
            "after_refit": _r(diag.gaps["refit"]),
            "after_effect": _r(diag.gaps["combined"]),
            "floor": _r(diag.floor),
        },
        "where": {k: where[k] for k in ("frequency_hz", "velocity_cells", "covariates")},
        "candidates": [
            {
                **_pick(c, "effect", "heldout_gap", "reduction", "p_value", "excess_removed"),
                **_pick(c, "deviance_reduction", "block_mse_reduction_db2"),
                **_pick(c, "folds", "interleaved", "decided_by"),
                "parameters": public_parameters(diag.models[c["effect"]].parameters),
                "shape": public_shape(diag.models[c["effect"]].shape or {}),
                "shape_summary": describe_shape(public_shape(diag.models[c["effect"]].shape or {})),
            }
            for c in diag.candidates
        ],
        "verdict": {
            "effect": diag.verdict,
            "confidence": diag.confidence,
            "effects": effects_list(diag),
            "rule": VERDICT_RULE,
        },
        "selection": selection_steps(diag),
        "added_effect": added,
        "ranked_regions": where["ranked_regions"],
        "residual_noise_db": {k: _r(v, 3) for k, v in diag.residual_noise.items()},
        "floor_estimates": {k: _r(v) for k, v in diag.floor_estimates.items()},
        "baseline": {
            "definition": BASELINE_DEFINITION,
            **diag.models["refit"].parameters,
            "in_sync_joint_lag_s": _r(joint_lag_of(diag.sync_lag_s), 5),
            "reference_joint_lag_s": _r(joint_lag_of(diag.reference_lag_s), 5),
        },
        "transients": {
            k: (_r(v, 6) if isinstance(v, float) else v) for k, v in diag.transients.items()
        },
        "blocks": {
            "total": int(t.n_blocks),
            "contact_excluded": int(t.contact.sum()),
            "train": int(diag.train.sum()),
            "heldout": int(diag.heldout.sum()),
            "heldout_windows": int(diag.windows.n_windows),
        },
        "inputs": {"model": str(model_path), "real": str(real_path)},
        "figures": figures,
        "runtime_s": _r(runtime_s, 2),
    }


def _ms(seconds: float) -> str:
    """Signed whole milliseconds, "+0" (not "-0") for a lag under half a millisecond."""
    return f"{round(1000 * seconds):+d}"


def change_advice(effect: str, params: dict, summary: str) -> str:
    """One sentence on what a change since the reference means and what to do."""
    if effect == "timing":
        shift = params["joint_lag_shift_s"]
        return (
            f"the joint lag moved by {_ms(shift)} ms since the reference (the vibration "
            f"now trails the joint states by {_ms(params['real_joint_lag_s'])} ms, was "
            f"{_ms(params['reference_joint_lag_s'])} ms): add {shift:+g} s to the joint "
            "lag set for the reference (`egovib denoise --joint-lag`, the denoiser node's "
            "`joint_lag:=`)"
        )
    if effect == "drift":
        level = params["level_change_db"]
        return (
            f"the vibration is {abs(level):.1f} dB {'louder' if level > 0 else 'quieter'} than "
            "in the reference at the same joint velocities (warm vs cold, wear, maintenance): "
            "recalibrate in these conditions (`egovib calibrate`)"
        )
    what = {
        "coupling": "a new or changed interaction between joints",
        "position": "a new or changed dependence on joint position",
        "acceleration": "a new or changed dependence on joint acceleration",
    }[effect]
    if "level_change_db" in params:  # a new dependence brings its level
        what += f", {params['level_change_db']:+.1f} dB on average"
    return (
        f"{what} since the reference ({summary or 'bin by bin'}): look at the mechanism, and "
        "recalibrate as the advice for that effect says"
    )


def change_report(change, *, reference: str) -> dict:
    """report.json's `change` (CONTRACT section 6: the same list as verdict.effects, for
    what differs between the reference recording and the recording diagnosed) and
    `change_info` (the lags, gaps and steps it rests on)."""
    entries = []
    for entry, model in zip(change.effects, change.models):
        params = dict(entry["parameters"])
        summary = ""
        if model is not None:
            params = {**params, "term": public_parameters(model.parameters)}
            summary = describe_shape(public_shape(model.shape or {}))
            if summary:
                params["shape_summary"] = summary
        entries.append(
            {
                **_pick(entry, "effect", "reduction", "p_value", "confidence"),
                "parameters": params,
                "advice": change_advice(entry["effect"], params, summary),
                **_pick(entry, "heldout_gap_before", "heldout_gap", "deviance_reduction", "step"),
            }
        )
    return {
        "change": entries,
        "change_info": {
            "reference": reference,
            "joint_lag_s": {
                "reference": _r(joint_lag_of(change.lags["reference"]), 5),
                "real": _r(joint_lag_of(change.lags["real"]), 5),
            },
            "gap": change.gaps,
            "blocks": change.blocks,
            "selection": [
                {
                    **_pick(st, "step", "given", "effect", "confidence"),
                    "candidates": [{**c, "p_value": _r(c["p_value"], 6)} for c in st["candidates"]],
                }
                for st in change.steps
            ],
            "definition": CHANGE_DEFINITION,
        },
    }


CHANGE_DEFINITION = (
    "the two recordings' blocks in one table, a velocity-only baseline fitted on both; each "
    "change is a term on the diagnosed recording's blocks only (timing: its joint states at "
    "its own lag instead of the reference's; drift: a level per bin; coupling: the effect's "
    "term again, on top of the same term on both; position, acceleration: the effect's term "
    "with the recording's level, which must beat both the term on both recordings and the "
    "level alone), tested on held-out blocks of both (5 contiguous folds within each "
    "recording) by forward selection with the rule of verdict.effects, ranked by the gain "
    "over the changes taken; a position or acceleration change whose shape adds nothing to "
    "its level once the others are taken is dropped and the selection run again without it"
)


VERDICT_RULE = (
    "forward selection on held-out data: at each step every remaining candidate is fitted on "
    "top of the effects found so far (the velocity-only baseline at the first step) and tested "
    "against them; the one with the largest held-out reduction of the Gamma deviance of the "
    f"expected power is taken among those with p < {ALPHA:g}/number of candidates of the step "
    "(paired sign-flip permutation test over 0.5 s held-out segments; drift: the better of "
    f"two looks, Bonferroni x2), a reduction of at least {MIN_DEVIANCE_GAIN:g} per block and "
    f"bin ({MIN_DEVIANCE_GAIN_LATER:g} from the second step on), and a "
    "smaller held-out gap; the selection stops when none qualifies. verdict.effect = the "
    "first effect taken (none: none qualified at the first step); confidence = "
    "block-bootstrap share of resamples in which that effect stays best among its step's "
    "candidates (for none: in which no candidate reaches the minimum reduction)"
)


BASELINE_DEFINITION = (
    "velocity-only table re-estimated on the training folds of this recording: expected power "
    "per frequency bin = rest power + sum over joints of a free non-negative function of that "
    "joint's velocity (cells = the model's grid, each step split "
    f"{KNOT_REFINE}x, 10x below 20 % of top "
    "speed; averaged over each block's velocity trajectory), neighbouring cells smoothed, the "
    "simulator's spectrum used only where cells are thin; then a per-joint, per-cell mean/rms "
    "correction. It cannot represent interactions between joints, position, acceleration, "
    "time or lag."
)


def _peak(x: np.ndarray, g: np.ndarray) -> tuple[float, float, float]:
    k = int(np.argmax(g))
    return float(x[k]), float(g[k]), float(g.max() - g.min())


def describe_shape(shape: dict) -> str:
    """One sentence on the fitted shape of a candidate term (broadband gain, dB)."""
    parts = []
    for name, c in shape.items():
        x, g = (np.asarray(c.get(key, ()), float) for key in ("x", "gain_db"))
        if name.startswith("position:"):
            at, top, span = _peak(x, g)
            parts.append(
                f"{name[9:]}: {span:.1f} dB peak-to-trough, loudest at {at:.3g} {c['unit']}"
            )
        elif name.startswith("coupling:"):
            i, j = np.unravel_index(int(np.argmax(g)), g.shape)
            sp = c["speed_fraction"]
            signed = np.asarray(c.get("same_minus_opposite_direction_db", [[0.0]]), float)
            bin_by_bin = (
                f"; bin by bin up to {c['per_bin_peak_db']:+.1f} dB "
                f"at {c['per_bin_peak_hz']:.0f} Hz"
                if abs(c.get("per_bin_peak_db", 0.0)) >= 0.05
                else ""
            )
            pair = " x ".join(c["joints"]) if "joints" in c else name[9:]
            if np.max(np.abs(g)) < 0.05 and np.max(np.abs(signed)) < 0.05:
                parts.append(f"{pair}: flat across the band{bin_by_bin}")
                continue
            parts.append(
                f"{pair}: up to {g.max():+.1f} dB at speed fractions {sp[i]:.1f}/{sp[j]:.1f} "
                f"({g[-1, -1]:+.1f} dB with both at full speed"
                + (
                    f"; same vs opposite direction {signed.flat[np.argmax(np.abs(signed))]:+.1f} dB"
                    if np.max(np.abs(signed)) >= 0.05
                    else ""
                )
                + bin_by_bin
                + ")"
            )
        elif name.startswith("acceleration:"):
            parts.append(
                f"{name[13:]}: {g[np.searchsorted(x, 10.0)]:+.1f} dB at 10x the typical "
                "|acceleration|"
            )
        elif name.startswith("jerk:"):
            parts.append(
                f"{name[5:]}: {g[np.searchsorted(x, 10.0)]:+.1f} dB at 10x the typical |jerk| "
                "(where a speed change starts or ends)"
            )
        elif name.startswith("reversal:"):
            at, top, span = _peak(x, g)
            parts.append(
                f"{name[9:]} reversals: {top:+.1f} dB at {1000 * at:+.0f} ms from the reversal"
            )
        elif name.startswith("drift:"):
            change, reach = drift_reach(x, g)
            parts.append(
                f"{name[6:]}: {change:+.1f} dB from start to end, 90 % of it reached at "
                f"{reach:.0f} s ({g.max() - g.min():.1f} dB range)"
            )
        elif name.startswith("timing:"):
            parts.append(
                f"best joint lag {1000 * c.get('fitted_joint_lag_s', 0.0):+.1f} ms (in sync: "
                f"{1000 * c['in_sync_band_s'][0]:+.0f}..{1000 * c['in_sync_band_s'][1]:+.0f} ms)"
            )
        elif name.startswith("coupling-lines:"):
            signed = [
                np.asarray(c[k], float)
                for k in c
                if k.endswith("_minus_opposite_direction_db") or k == "one_way_minus_other_db"
            ]
            if max([float(np.max(np.abs(a))) for a in [g, *signed] if a.size] or [0.0]) >= 0.05:
                parts.append(
                    f"{c['lines_of']} lines up to {_signed_peak(g):+.1f} dB with {c['speed_of']}'s "
                    "speed"
                    + "".join(
                        f", {label} {_signed_peak(np.asarray(c[key], float)):+.1f} dB"
                        for key, label in (
                            ("one_way_minus_other_db", "one way vs the other"),
                            ("same_minus_opposite_direction_db", "same vs opposite direction"),
                        )
                        if key in c and abs(c[key][-1]) >= 0.05
                    )
                )
    return "; ".join(parts)


def _signed_peak(values: np.ndarray) -> float:
    """The value of largest magnitude (its sign kept)."""
    return float(values[int(np.argmax(np.abs(values)))]) if values.size else 0.0


def _describe_region(r: dict) -> str:
    speeds = ", ".join(f"{n} {c}" for n, c in r["speeds"].items())
    return (
        f"{r['band_hz'][0]:.0f}-{r['band_hz'][1]:.0f} Hz with {speeds} "
        f"(model {'too quiet' if r['bias_db'] > 0 else 'too loud'} by "
        f"{abs(r['bias_db']):.1f} dB on average, "
        f"{100 * r['share_of_gap2']:.0f} % of the gap^2)"
    )


def _strongest_covariate(report: dict) -> str:
    covs = {
        k: v
        for k, v in report["where"]["covariates"].items()
        if k != "stream_lag" and v["spread_db_after_refit"]
    }
    if not covs:
        return ""
    name, c = max(covs.items(), key=lambda kv: kv[1]["spread_db_after_refit"])
    return (
        f" After the velocity-only baseline, the remaining gap varies most with {name} "
        f"(held-out bias spread {c['spread_db_after_refit']:.1f} dB across its bins)."
    )


def _blocks_text(blocks: dict) -> str:
    return (
        f"{blocks['total']} in all, {blocks['contact_excluded']} set aside as contact-like, "
        f"{blocks['train']} to fit, {blocks['heldout']} held out in "
        f"{blocks['heldout_windows']} windows"
    )


def render_markdown(report: dict) -> str:
    """report.md: the answer first (where, which, how far), then the evidence."""
    lines = ["# Sim-to-real gap report", ""]
    if "advice" in report:
        lines += first_lines(report["advice"]) + [""]
    lines += [_where_line(report), _which_line(report), _how_far_line(report), ""]
    if "change" in report:
        lines += _change_lines(report) + [""]
    lines.append(" ".join(f"![{name}]({path})" for name, path in report["figures"].items()))
    lines += _metric_lines(report) + _candidate_lines(report) + _effect_and_region_lines(report)
    lines.append("")
    return "\n".join(lines)


def _where_line(report: dict) -> str:
    g = report["gap"]
    freq = report["where"]["frequency_hz"]
    worst_bin = max(freq, key=lambda f: f["sim_as_is_db"]) if freq else None
    mean_bias = float(np.mean([f["bias_db_sim_as_is"] for f in freq])) if freq else 0.0
    from_simulator = report["inputs"].get("model_kind", "simulator") == "simulator"
    model_name = "the simulator's noise model" if from_simulator else "the noise model"
    return (
        f"**Where:** on held-out real data {model_name} is off by "
        f"**{g['sim_as_is']:.2f} dB** (floor {g['floor']:.2f} dB; overall the model is "
        f"{'too quiet' if mean_bias > 0 else 'too loud'} by "
        f"{abs(mean_bias):.1f} dB). Largest shares: "
        + "; ".join(_describe_region(r) for r in report["ranked_regions"][:3])
        + (
            f". Worst frequency bin {worst_bin['hz']:.0f} Hz ({worst_bin['sim_as_is_db']:.2f} dB)."
            if worst_bin
            else "."
        )
        + _strongest_covariate(report)
    )


def _change_lines(report: dict) -> list[str]:
    """What changed since the reference recording (--reference)."""
    info = report["change_info"]
    lags = info["joint_lag_s"]
    head = (
        f"**What changed since `{info['reference']}`:** "
        f"(joint lag {_ms(lags['reference'])} ms there, {_ms(lags['real'])} ms "
        f"here; held-out gap of what both share {info['gap']['baseline']:.2f} dB, "
        f"{info['gap']['after_changes']:.2f} dB with the changes below)"
    )
    if not report["change"]:
        return [head + " nothing significant."]
    return [head] + [
        f"{k}. `{c['effect']}` ({c['reduction']:.3f} dB, p = {c['p_value']:.2g}, confidence "
        f"{c['confidence']:.2f}): {c['advice']}."
        for k, c in enumerate(report["change"], 1)
    ]


def _which_line(report: dict) -> str:
    v = report["verdict"]
    cands = report["candidates"]
    found = v.get("effects") or []
    if len(found) > 1:
        return (
            f"**Which:** {len(found)} unmodelled effects, in the order the forward selection "
            "took them (each one's held-out reduction given the ones before): "
            + "; ".join(
                f"**`{e['effect']}`** {e['reduction']:.3f} dB (p = {e['p_value']:.2g}, "
                f"confidence {e['confidence']:.2f}; fitted shape: "
                f"{e.get('shape_summary') or 'n/a'})"
                for e in found
            )
            + "."
        )
    if v["effect"] != "none":
        c = next(c for c in cands if c["effect"] == v["effect"])
        # a trend over time cannot be learned across blocked folds: drift may be decided on
        # interleaved ones, where the blocked reduction shown can be nil
        interleaved = (
            " on blocked folds; decided on interleaved ones, where a trend over time is learnt"
            if c.get("decided_by") == "interleaved"
            else ""
        )
        return (
            f"**Which:** the unmodelled effect is **`{v['effect']}`** "
            f"(held-out reduction {c['reduction']:.3f} dB "
            f"beyond the velocity-only baseline{interleaved}, p = {c['p_value']:.2g}, "
            f"confidence {v['confidence']:.2f}; no other effect is significant on top of it). "
            f"Fitted shape: {c.get('shape_summary') or 'n/a'}."
        )
    best = cands[0] if cands else None
    return (
        "**Which:** **no effect** (`none`): beyond the velocity-only baseline "
        "no candidate effect lowers the held-out gap significantly"
        + (
            f" (the best, `{best['effect']}`: held-out reduction {best['reduction']:+.3f} dB, p = "
            f"{best['p_value']:.2g}; an effect is named only where p < {ALPHA:g}/{len(cands)}, "
            f"the held-out deviance falls by {MIN_DEVIANCE_GAIN:g} per block and bin or more and "
            "the held-out gap shrinks)."
            if best
            else "."
        )
    )


def _how_far_line(report: dict) -> str:
    g = report["gap"]
    return (
        f"**How far:** held-out gap {g['sim_as_is']:.2f} dB (sim as-is) -> "
        f"{g['after_refit']:.2f} dB "
        "(velocity-only baseline fitted on this recording) -> "
        f"**{g['after_effect']:.2f} dB** (refit + "
        + (
            " + ".join(e["effect"] for e in report["verdict"].get("effects") or [])
            or report["verdict"]["effect"]
        )
        + "), "
        f"floor {g['floor']:.2f} dB. "
        f"Residual no-contact noise after denoising held-out data: "
        + ", ".join(
            f"{k} {val:.2f} dB" for k, val in report["residual_noise_db"].items() if k != "raw"
        )
        + " (relative to the raw signal)."
    )


def _metric_lines(report: dict) -> list[str]:
    return [
        "",
        "## Metric",
        "",
        f"{report['metric']['name']} [{report['metric']['unit']}]: "
        f"{report['metric']['definition']}",
        "",
        f"Split: {report['split']['method']} (train {report['split']['train_s']:.1f} s, held out "
        f"{report['split']['heldout_s']:.1f} s). Blocks: {_blocks_text(report['blocks'])}.",
    ]


def _candidate_lines(report: dict) -> list[str]:
    """The ranked candidates, their fitted shapes and the transients."""
    cands = report["candidates"]
    lines = [
        "",
        "## Candidates (held-out, ranked)",
        "",
        "| effect | held-out gap [dB] | reduction vs refit [dB] | p-value "
        "| share of excess removed |",
        "|---|---|---|---|---|",
    ]
    for c in cands:
        lines.append(
            f"| {c['effect']} | {c['heldout_gap']:.3f} | {c['reduction']:+.3f} | "
            f"{c['p_value']:.2g} | {c['excess_removed']:.2f} |"
        )
    lines += ["", "Fitted shapes of every candidate (which_effect_shapes.png): "]
    for c in cands:
        lines.append(f"- {c['effect']}: {c.get('shape_summary') or 'n/a'}")
    tr = report.get("transients", {})
    if tr.get("onsets"):
        lines += [
            "",
            f"Transients (contact-like outliers): {tr['onsets']} onsets, "
            f"{tr['near_reversal']} within "
            f"{tr.get('window_s')} s of a joint reversal (chance: {tr['expected_near']}), "
            f"p = {tr['p_value']:.2g}; "
            + (
                f"{tr['returned_blocks']} blocks of reversal-locked transients returned to the "
                "data as ego-vibration."
                if tr.get("returned_blocks")
                else "treated as contacts."
            ),
        ]
    return lines


def _effect_and_region_lines(report: dict) -> list[str]:
    """The baseline, the verdict rule, the added effect, the ranked regions, the covariates."""
    lines = [
        "",
        f"Baseline: {report['baseline']['definition']}",
        "",
        f"Verdict rule: {report['verdict']['rule']}.",
        "",
        "## Added effect",
        "",
        "Fitted term (log gain per regressor, dB averaged over bins) and, with --write-back, "
        "the simulator strength that reproduces it:",
        "",
        "```json",
        json.dumps(report["added_effect"], indent=1),
        "```",
        "",
        "## Ranked regions (sim as-is)",
        "",
    ]
    for r in report["ranked_regions"][:10]:
        lines.append(f"- {_describe_region(r)}")
    lines += ["", "## Covariates (held-out bias after refit, dB per bin)", ""]
    for name, cov in report["where"]["covariates"].items():
        if name == "stream_lag":
            reference = report["baseline"].get("reference_joint_lag_s", 0.0)
            lines.append(
                f"- stream lag: fitted joint lag {cov['fitted_joint_lag_s'] * 1000:+.1f} ms "
                f"against the reference {reference * 1000:+.1f} ms (--reference-lag, else the "
                "model's own lag: docs/gap.md; training residual scan in report.json)"
            )
        else:
            lines.append(
                f"- {name} [{cov['unit']}]: spread {cov['spread_db_after_refit']} dB; bins "
                + ", ".join("-" if b is None else f"{b:+.2f}" for b in cov["bias_db_after_refit"])
            )
    return lines


def make_figures(diag: Diagnosis, report: dict, out_dir: Path) -> dict[str, str]:
    """Heat maps by frequency x velocity cell and on the velocity grid,
    covariate profiles, candidates: {caption: file name in out_dir}."""
    return {
        "where: frequency x velocity cell": frequency_velocity_figure(
            diag, out_dir / "where_frequency_velocity.png"
        ),
        "where: covariates": covariate_figure(report, out_dir / "where_covariates.png"),
        "which: candidates": candidate_figure(report, out_dir / "which_candidates.png"),
        "which: fitted effect shapes": shape_figure(report, out_dir / "which_effect_shapes.png"),
    }


def frequency_velocity_figure(diag: Diagnosis, path: Path) -> str:
    """Held-out error of sim as-is per frequency bin x velocity cell (cells ordered by speed),
    beside the band-summed bias on the velocity grid (two joints)."""
    plt = pyplot()
    t = diag.table
    wv = _window_means(diag, t.velocity)
    cell, grid = velocity_cells(diag, wv)
    shape = tuple(len(g) for g in grid)
    used = np.unique(cell)
    e = diag.errors["sim_as_is"]
    mat = np.array([np.mean(e[cell == c], axis=0) for c in used]).T
    labels = ["/".join(map(str, _percent_of_max(grid, np.unravel_index(c, shape)))) for c in used]
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5), gridspec_kw={"width_ratios": [2.2, 1]})
    lim = max(1.0, float(np.nanmax(np.abs(mat))))
    im = axes[0].imshow(
        mat,
        aspect="auto",
        origin="lower",
        cmap="RdBu_r",
        vmin=-lim,
        vmax=lim,
        extent=[-0.5, len(used) - 0.5, t.freqs_hz[0] - 23, t.freqs_hz[-1] + 23],
    )
    step = max(1, len(used) // 30)
    axes[0].set_xticks(range(0, len(used), step))
    axes[0].set_xticklabels(labels[::step], rotation=90, fontsize=6)
    axes[0].set_xlabel("velocity cell (% of max speed, " + "/".join(t.joint_names) + ")")
    axes[0].set_ylabel("frequency [Hz]")
    axes[0].set_title("held-out error of sim as-is, dB (red: real louder)")
    fig.colorbar(im, ax=axes[0])
    # velocity grid map of the band-averaged bias
    bias, counts = metric.grouped_bias_db(
        t.magnitude[diag.heldout_rows],
        t.base_mean[diag.heldout_rows],
        velocity_cells(diag, t.velocity[diag.heldout_rows])[0],
        int(np.prod(shape)),
    )
    bias = np.where(counts >= 5, bias, np.nan).reshape(shape)
    if len(shape) == 2:
        im2 = axes[1].imshow(
            bias.T,
            origin="lower",
            cmap="RdBu_r",
            vmin=-lim,
            vmax=lim,
            aspect="auto",
            extent=[-105, 105, -105, 105],
        )
        axes[1].set_xlabel(f"{t.joint_names[0]} [% max]")
        axes[1].set_ylabel(f"{t.joint_names[1]} [% max]")
        axes[1].set_title("band-summed bias per velocity cell, dB")
        fig.colorbar(im2, ax=axes[1])
    return save_figure(fig, path).name


def covariate_figure(report: dict, path: Path) -> str:
    """Held-out bias per covariate bin, sim as-is and after refit; the stream-lag scan."""
    plt = pyplot()
    covs = report["where"]["covariates"]
    names = list(covs)
    fig, axes = plt.subplots(1, len(names), figsize=(3.2 * len(names), 3.2))
    for ax, name in zip(np.atleast_1d(axes), names):
        c = covs[name]
        if name == "stream_lag":
            ax.plot(np.array(c["joint_lag_s"]) * 1000, c["train_log_residual"], "k.-")
            ax.axvline(c["fitted_joint_lag_s"] * 1000, color="r")
            ax.set_xlabel("joint lag [ms] (vibration trails joint states)")
            ax.set_title("stream lag: refit residual", fontsize=9)
            continue
        edges = np.array(c["bin_edges"], dtype=float)
        mid = 0.5 * (edges[1:] + edges[:-1])
        for key, color, label in (
            ("sim_as_is", "0.6", "sim as-is"),
            ("after_refit", "C3", "after refit"),
        ):
            ax.plot(mid, np.array(c[f"bias_db_{key}"], dtype=float), "o-", color=color, label=label)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel(c["unit"], fontsize=8)
    np.atleast_1d(axes)[0].set_ylabel("held-out bias [dB]")
    np.atleast_1d(axes)[0].legend(fontsize=7)
    return save_figure(fig, path).name


def candidate_figure(report: dict, path: Path) -> str:
    """Held-out gap of sim as-is, the baseline and every candidate; the verdict's in red."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.5))
    labels = ["sim as-is", "baseline"] + [c["effect"] for c in report["candidates"]]
    values = [report["gap"]["sim_as_is"], report["gap"]["after_refit"]] + [
        c["heldout_gap"] for c in report["candidates"]
    ]
    colors = ["0.6", "0.3"] + [
        "C3" if c["effect"] == report["verdict"]["effect"] else "C0" for c in report["candidates"]
    ]
    ax.bar(labels, values, color=colors)
    ax.axhline(report["gap"]["floor"], color="k", ls="--", label="floor")
    ax.set_ylabel("held-out gap [dB]")
    ax.set_title(f"which effect: verdict {report['verdict']['effect']}")
    ax.legend()
    return save_figure(fig, path).name


def shape_figure(report: dict, path: Path) -> str:
    """One panel per fitted shape of every candidate (broadband gain, dB); the verdict's in red."""
    plt = pyplot()
    panels = [
        (c["effect"], name, sh)
        for c in report["candidates"]
        for name, sh in c.get("shape", {}).items()
    ]
    n = max(len(panels), 1)
    cols = min(n, 4)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.0 * rows), squeeze=False)
    verdict = report["verdict"]["effect"]
    for ax, (effect, name, sh) in zip(axes.ravel(), panels):
        color = "C3" if effect == verdict else "C0"
        if name.startswith("coupling:"):
            g = np.asarray(sh["gain_db"], float)
            sp = sh["speed_fraction"]
            lim = max(float(np.max(np.abs(g))), 0.1)
            im = ax.imshow(
                g.T,
                origin="lower",
                extent=[sp[0], sp[-1], sp[0], sp[-1]],
                cmap="RdBu_r",
                vmin=-lim,
                vmax=lim,
                aspect="auto",
            )
            fig.colorbar(im, ax=ax, label="dB")
            a, b = sh["joints"]
            ax.set_xlabel(f"|v| / max: {a}", fontsize=7)
            ax.set_ylabel(f"|v| / max: {b}", fontsize=7)
        elif name.startswith("timing:"):
            x = np.asarray(sh["x"], float) * 1000
            ax.plot(x, sh["train_log_residual"], ".-", color=color)
            lo, hi = sh["in_sync_band_s"]
            ax.axvspan(lo * 1000, hi * 1000, color="0.85")
            ax.axvline(sh.get("fitted_joint_lag_s", 0.0) * 1000, color=color, ls="--")
            ax.set_xlabel("joint lag [ms] (grey: in sync)", fontsize=7)
            ax.set_ylabel("baseline log residual", fontsize=7)
        else:
            x = np.asarray(sh["x"], float)
            ax.plot(x, sh["gain_db"], "-", color=color)
            ax.axhline(0, color="k", lw=0.5)
            if "train_end_s" in sh:
                ax.axvline(sh["train_end_s"], color="0.6", ls=":")
            ax.set_xlabel(sh.get("unit", ""), fontsize=7)
            ax.set_ylabel("gain [dB]", fontsize=7)
        ax.set_title(f"{effect}: {name.split(':', 1)[1]}", fontsize=8, color=color)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(panels) :]:
        ax.axis("off")
    fig.suptitle(
        f"fitted candidate terms (broadband gain over the band); verdict {verdict} in red",
        fontsize=9,
    )
    return save_figure(fig, path, dpi=100).name
