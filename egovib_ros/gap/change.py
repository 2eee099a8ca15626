"""What changed between two recordings of the same robot (`egovib gap --reference A`).

The two recordings' blocks are joined into one table (`features.join_tables`: the
reference's, then the recording's), and a velocity-only baseline is fitted on both: what
the two share. Each effect's change is a term that acts on the recording's blocks only,
tested on held-out blocks of both (blocked folds within each recording: every training set
holds parts of both) against a model that already has what both share of that effect:

| change | null model | with the change |
|---|---|---|
| `timing` | both recordings' joint states at the reference's lag | the recording's at its own |
| `drift` | the baseline | times a level on the recording's blocks (per bin and broadband: dB) |
| `position`, `coupling`, `acceleration` | times the effect's term on both | times the
  same term again, on the recording's blocks only |

Forward selection as in `diagnose`: each step tests every remaining change on top of the
changes taken (with the rule of the single diagnosis: p < alpha / candidates of the step,
Gamma deviance gain >= MIN_DEVIANCE_GAIN, a smaller held-out gap), the largest gain is
taken, until none qualifies. Parameters: a lag shift in ms (joint-lag convention), a level
change in dB, the changed term's fitted shape (a new interaction, a new position
dependence).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from egovib_ros.errors import GapDataError
from egovib_ros.gap import metric
from egovib_ros.gap.baseline import simulator_cells
from egovib_ros.gap.chain import ALL, CHANGED, ChainFits, Split
from egovib_ros.gap.diagnose import (
    DB_PER_NEPER,
    MIN_DEVIANCE_GAIN,
    N_BOOTSTRAP,
    Diagnosis,
    DiagnosisOptions,
    _align,
    _segments,
    _test,
    heldout_errors,
)
from egovib_ros.gap.effects import EFFECTS
from egovib_ros.gap.features import BlockTable, join_tables

#: The change of a level (drift between two recordings) is one custom term.
LEVEL = "drift" + CHANGED


@dataclass
class ChangeDiagnosis:
    """The changes found, in order, and what the diagnosis of them rests on."""

    effects: list[dict]  # {"effect", "reduction", "p_value", "confidence", "parameters", ...}
    steps: list[dict]
    lags: dict  # the two recordings' joint-state lags (internal convention: stamped late)
    gaps: dict  # held-out gaps of the joined table: baseline, with every change, floor
    blocks: dict
    models: list = field(default_factory=list)  # each change's term fitted on every clean block


def _level_term(table: BlockTable, scales) -> tuple[np.ndarray, list[str]]:
    return np.asarray(table.recording, float)[:, None], ["recording"]


def change_folds(table: BlockTable, n_folds: int) -> list[Split]:
    """Contiguous folds within each recording; fold k holds the k-th part of both."""
    t = table.t_mid_s
    fold = np.zeros(table.n_blocks, np.int64)
    for r in (0, 1):
        sel = table.recording == r
        ts = t[sel]
        fold[sel] = np.minimum(
            ((ts - ts[0]) / max(ts[-1] - ts[0], 1e-9) * n_folds).astype(np.int64), n_folds - 1
        )
    clean = ~table.contact
    return [Split(clean & (fold != k), clean & (fold == k)) for k in range(n_folds)]


def _pair(effect: str, prefix: tuple[str, ...]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(null chain, chain with the change) of one candidate change on top of `prefix`."""
    if effect == "timing":
        return prefix, prefix + ("timing",)
    if effect == "drift":
        return prefix, prefix + (LEVEL,)
    return prefix + (effect,), prefix + (effect, effect + CHANGED)


def _chosen_terms(effect: str) -> tuple[str, ...]:
    """What a change taken adds to the chain."""
    return {"timing": ("timing",), "drift": (LEVEL,)}.get(effect, (effect, effect + CHANGED))


def _confidence(gains: dict[str, np.ndarray], segments: np.ndarray, chosen: str, rng) -> float:
    """Share of block-bootstrap resamples (held-out segments) in which the chosen change
    keeps the largest mean deviance gain over its null (at least MIN_DEVIANCE_GAIN); for
    none: in which no change reaches it."""
    names = list(gains)
    n_seg = int(segments.max()) + 1
    seg_len = np.bincount(segments, minlength=n_seg)
    per_seg = np.stack([np.bincount(segments, weights=gains[n], minlength=n_seg) for n in names])
    found = np.zeros(N_BOOTSTRAP, bool)
    for start in range(0, N_BOOTSTRAP, 100):
        picks = rng.integers(0, n_seg, size=(min(100, N_BOOTSTRAP - start), n_seg))
        mean = per_seg[:, picks].sum(axis=2) / np.maximum(seg_len[picks].sum(axis=1), 1)
        best = np.argmax(mean, axis=0)
        top = mean[best, np.arange(mean.shape[1])] >= MIN_DEVIANCE_GAIN
        if chosen == "none":
            found[start : start + len(picks)] = ~np.any(mean >= MIN_DEVIANCE_GAIN, axis=0)
        else:
            found[start : start + len(picks)] = top & (best == names.index(chosen))
    return round(float(found.mean()), 4)


def _step(ctx: dict, prefix: tuple[str, ...], remaining: tuple[str, ...], number: int) -> dict:
    """Every remaining change tested on top of the changes taken (`prefix`)."""
    chains, observed = ctx["chains"], ctx["observed"]
    cands, gains = [], {}
    for effect in remaining:
        null, alt = _pair(effect, prefix)
        chains.keep(null)
        cf = chains.cross({"refit": null, effect: alt}, offset_of="refit")
        res = _test(observed, cf, effect, ctx["segments"], ctx["rng"])
        gap_null = metric.gap_db(
            heldout_errors(cf.predicted["refit"], observed, cf.rows, ctx["windows"])
        )
        gap_alt = metric.gap_db(
            heldout_errors(cf.predicted[effect], observed, cf.rows, ctx["windows"])
        )
        gains[effect] = res["loss_base"] - res["loss_cand"]
        cands.append(
            {
                "effect": effect,
                "heldout_gap_before": round(gap_null, 4),
                "heldout_gap": round(gap_alt, 4),
                "reduction": round(gap_null - gap_alt, 4),
                "p_value": res["p_value"],
                "deviance_reduction": round(res["deviance_reduction"], 6),
                "_predicted": (cf.predicted[effect], cf.power[effect]),
            }
        )
    cands.sort(key=lambda c: -c["deviance_reduction"])
    level = ctx["alpha"] / max(len(cands), 1)
    eligible = [
        c
        for c in cands
        if c["p_value"] < level
        and c["deviance_reduction"] >= MIN_DEVIANCE_GAIN
        and c["reduction"] > 0.0
    ]
    chosen = eligible[0]["effect"] if eligible else "none"
    return {
        "step": number,
        "given": list(prefix),
        "effect": chosen,
        "confidence": _confidence(gains, ctx["segments"], chosen, ctx["rng"]),
        "candidates": cands,
    }


def _parameters(ctx: dict, effect: str, prefix: tuple[str, ...]) -> tuple[dict, object]:
    """A change's parameters (and its term fitted on every clean block, on top of `prefix`)."""
    lags = ctx["lags"]
    if effect == "timing":
        # joint-lag convention: the seconds the vibration trails the joint states
        ref, real = -lags["reference"], -lags["real"]
        return {
            "joint_lag_shift_s": round(real - ref, 5),
            "lag_shift_ms": round(1000.0 * (real - ref), 1),
            "reference_joint_lag_s": round(ref, 5),
            "real_joint_lag_s": round(real, 5),
        }, None
    chain = prefix + _chosen_terms(effect)
    model = ctx["chains"].fit(ALL, chain)
    if effect == "drift":
        level = model.coef[1] * DB_PER_NEPER  # per bin, dB
        return {
            "level_change_db": round(float(level.mean()), 3),
            "level_change_db_per_bin": [round(float(v), 3) for v in level],
            "frequency_hz": [round(float(f), 1) for f in ctx["table"].freqs_hz],
        }, model
    return {"term": model.parameters, "what": f"{effect} term on the recording only"}, model


def diagnose_change(
    reference: BlockTable, real_diag: Diagnosis, options: DiagnosisOptions | None = None
) -> ChangeDiagnosis:
    """What changed from the `reference` recording's table to the recording `real_diag`
    diagnosed (its lags and contacts are reused): see the module's docstring."""
    o = options or DiagnosisOptions()
    rng = np.random.default_rng(o.seed + 1)
    if (~reference.contact).sum() < 400:
        raise GapDataError(f"too few no-contact blocks ({int((~reference.contact).sum())})")
    prior = simulator_cells(reference)
    aligned = _align(reference, o.effects, prior, o.reference_lag_s, o.lag_tolerance_s)
    lag_ref = float(aligned.timing_lag)
    lag_real = float(real_diag.lag_scan.get("timing_lag_s", real_diag.sync_lag_s))
    real_table = real_diag.table
    ref_at = replace(reference.at_lag(lag_ref), contact=aligned.contact)
    null = join_tables(ref_at, replace(real_table.at_lag(lag_ref), contact=real_table.contact))
    moved = None
    if abs(lag_real - lag_ref) > 1e-4:
        moved = join_tables(
            ref_at, replace(real_table.at_lag(lag_real), contact=real_table.contact)
        )
    splits = change_folds(null, o.folds)
    if min(s.train.sum() for s in splits) < 200:
        raise GapDataError("too few no-contact blocks to fit and test the change")
    chains = ChainFits(
        {"sync": null, "timing": moved},
        splits,
        prior,
        clean=~null.contact,
        custom={LEVEL: _level_term},
    )
    rows = np.flatnonzero(np.any([s.test for s in splits], axis=0))
    ctx = {
        "chains": chains,
        "observed": null.magnitude,
        "segments": _segments(null.t_mid_s, rows, float(null.t_mid_s[0])),
        "windows": metric.make_windows(len(rows), o.window_blocks),
        "alpha": o.alpha,
        "rng": rng,
        "lags": {"reference": lag_ref, "real": lag_real},
        "table": null,
    }
    candidates = tuple(e for e in EFFECTS if e in o.effects)
    prefix: tuple[str, ...] = ()
    effects, steps, models = [], [], []
    base = chains.cross({"refit": ()}, offset_of="refit")
    predicted = base.predicted["refit"]
    gap_base = metric.gap_db(heldout_errors(predicted, null.magnitude, rows, ctx["windows"]))
    while len(effects) < len(candidates):
        taken = {e["effect"] for e in effects}
        step = _step(ctx, prefix, tuple(e for e in candidates if e not in taken), len(steps) + 1)
        steps.append(step)
        if step["effect"] == "none":
            break
        c = next(c for c in step["candidates"] if c["effect"] == step["effect"])
        params, model = _parameters(ctx, step["effect"], prefix)
        effects.append(
            {
                "effect": step["effect"],
                "reduction": c["reduction"],
                "p_value": c["p_value"],
                "confidence": step["confidence"],
                "parameters": params,
                "heldout_gap_before": c["heldout_gap_before"],
                "heldout_gap": c["heldout_gap"],
                "deviance_reduction": c["deviance_reduction"],
                "step": step["step"],
            }
        )
        models.append(model)
        prefix = prefix + _chosen_terms(step["effect"])
        predicted = c["_predicted"][0]
    for step in steps:
        for c in step["candidates"]:
            c.pop("_predicted", None)
    errors = heldout_errors(predicted, null.magnitude, rows, ctx["windows"])
    floors = {
        "block_ratio": metric.floor_db(null.magnitude[rows], predicted[rows], ctx["windows"]),
        "window": metric.floor_window_db(null.magnitude[rows], predicted[rows], ctx["windows"]),
    }
    finite = [v for v in floors.values() if np.isfinite(v)]
    return ChangeDiagnosis(
        effects=effects,
        steps=steps,
        lags={"reference": lag_ref, "real": lag_real},
        gaps={
            "baseline": round(gap_base, 4),
            "after_changes": round(metric.gap_db(errors), 4),
            "floor": round(float(min(finite)), 4) if finite else None,
        },
        blocks={
            "reference": int(reference.n_blocks),
            "real": int(real_table.n_blocks),
            "heldout": int(len(rows)),
        },
        models=models,
    )
