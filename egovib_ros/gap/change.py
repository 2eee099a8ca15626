"""What changed between two recordings of the same robot (`egovib gap --reference A`).

The two recordings' blocks are joined into one table (`features.join_tables`: the
reference's, then the recording's), and a velocity-only baseline is fitted on both: what
the two share. Each effect's change is a term that acts on the recording's blocks only,
tested on held-out blocks of both (blocked folds within each recording: every training set
holds parts of both) against the changes taken so far and against every model that would
explain the data without that change:

- `timing`: the recording's joint states at its own lag instead of the reference's;
- `drift`: a level on the recording's blocks (per bin and broadband: dB);
- `coupling`: the effect's term on both, then again on the recording's blocks only; it
  must also beat the term on both;
- `position`, `acceleration`: the effect's term on the recording's blocks only, fitted
  with their level; it must also beat the term on both, and the level alone.

Forward selection as in `diagnose`: each step tests every remaining change on top of the
changes taken (with the rule of the single diagnosis, against each model above: p < alpha
/ candidates of the step, Gamma deviance gain >= MIN_DEVIANCE_GAIN, a smaller held-out
gap), the largest gain over the changes taken is taken, until none qualifies. A position or
acceleration change whose shape adds nothing to its level once the other changes are taken
(a lag shift taken later explains it) is struck, and the selection run again without it:
its level is then a drift. Parameters: a lag shift in ms (joint-lag convention), a level
change in dB, the changed term's fitted shape (a new interaction, a new position
dependence) and the level it brings.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from egovib_ros.errors import GapDataError
from egovib_ros.gap import metric
from egovib_ros.gap.baseline import simulator_cells
from egovib_ros.gap.chain import ALL, ALONE, CHANGED, ChainFits, CrossFitted, Split
from egovib_ros.gap.diagnose import (
    MIN_BLOCKS,
    MIN_TRAIN_BLOCKS,
    Diagnosis,
    DiagnosisOptions,
    _align,
    _floors,
    _segments,
    _test,
    _verdict,
    combined_floor,
    fold_index,
    heldout_errors,
)
from egovib_ros.gap.effects import DB_PER_NEPER, EFFECTS
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


#: Effects whose change is their term on the recording's blocks only, fitted together with
#: that recording's level (chain.ALONE). In two stages (the term, then a level), the term's
#: columns carry the level and extrapolate wildly: on a real flight a new position dependence
#: predicted held-out blocks worse than no change at all.
SHAPES = ("position", "acceleration")


def change_folds(table: BlockTable, n_folds: int) -> list[Split]:
    """Contiguous folds within each recording; fold k holds the k-th part of both."""
    fold = np.zeros(table.n_blocks, np.int64)
    for r in (0, 1):
        sel = table.recording == r
        fold[sel] = fold_index(table.t_mid_s[sel], n_folds)
    clean = ~table.contact
    return [Split(clean & (fold != k), clean & (fold == k)) for k in range(n_folds)]


def _chosen_terms(effect: str) -> tuple[str, ...]:
    """What a change taken adds to the chain."""
    if effect in SHAPES:
        return (effect + ALONE,)
    return {"timing": ("timing",), "drift": (LEVEL,)}.get(effect, (effect, effect + CHANGED))


def _nulls(effect: str, prefix: tuple[str, ...]) -> tuple[tuple[str, ...], ...]:
    """What a change must beat besides the changes taken: an effect both recordings share
    (its term on both, for an effect with such a term), and for a shape change, which
    carries the recording's level, that level alone."""
    if effect == "coupling":
        return (prefix + (effect,),)
    if effect in SHAPES:
        return prefix + (effect,), prefix + (LEVEL,)
    return ()


def _gap(ctx: dict, predicted: np.ndarray) -> float:
    """Held-out gap (dB) of a prediction on the tested rows."""
    return metric.gap_db(heldout_errors(predicted, ctx["observed"], ctx["rows"], ctx["windows"]))


def _step(ctx: dict, prefix: tuple[str, ...], remaining: tuple[str, ...], number: int) -> dict:
    """Every remaining change tested on top of the changes taken (`prefix`): its gain over
    them ranks it; it is significant only if it also beats each of its `_nulls`."""
    chains, observed = ctx["chains"], ctx["observed"]
    chains.keep(prefix)
    # every chain of the step in one pass (each term fitted once), then compared in pairs
    named = {"refit": prefix}
    nulls = {effect: _nulls(effect, prefix) for effect in remaining}
    for effect in remaining:
        named[effect] = prefix + _chosen_terms(effect)
        named.update({f"{effect}#{i}": null for i, null in enumerate(nulls[effect])})
    every = chains.cross(named, offset_of="refit")

    def pair(null: str, effect: str) -> CrossFitted:
        return replace(
            every,
            predicted={"refit": every.predicted[null], effect: every.predicted[effect]},
            power={"refit": every.power[null], effect: every.power[effect]},
        )

    cands, gains = [], {}
    for effect in remaining:
        cf = pair("refit", effect)
        res = _test(observed, cf, effect, ctx["segments"], ctx["rng"])
        gap_null, gap_alt = (_gap(ctx, cf.predicted[k]) for k in ("refit", effect))
        p_value, decisive = res["p_value"], gap_null - gap_alt
        for i in range(len(nulls[effect])):
            other = pair(f"{effect}#{i}", effect)
            tested = _test(observed, other, effect, ctx["segments"], ctx["rng"])
            p_value = max(p_value, tested["p_value"])
            decisive = min(decisive, _gap(ctx, other.predicted["refit"]) - gap_alt)
        gains[effect] = res["gain"]
        cands.append(
            {
                "effect": effect,
                "heldout_gap_before": round(gap_null, 4),
                "heldout_gap": round(gap_alt, 4),
                "reduction": round(gap_null - gap_alt, 4),
                "gap_reduction_decisive": round(decisive, 4),
                "p_value": p_value,
                "deviance_reduction": round(res["deviance_reduction"], 6),
                "_predicted": (cf.predicted[effect], cf.power[effect]),
            }
        )
    cands.sort(key=lambda c: -c["deviance_reduction"])
    chosen, confidence = _verdict(cands, gains, ctx["alpha"], ctx["segments"], ctx["rng"])
    return {
        "step": number,
        "given": list(prefix),
        "effect": chosen,
        "confidence": confidence,
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
    params = {"term": model.parameters, "what": f"{effect} term on the recording only"}
    if effect in SHAPES:  # the level it brings: the term's mean over the recording's blocks
        rows = ctx["chains"].clean & (ctx["table"].recording == 1)
        gain = np.log(model.predicted[rows] / np.maximum(model.refit_predicted[rows], 1e-300))
        params["what"] += ", with its level"
        params["level_change_db"] = round(float(gain.mean()) * DB_PER_NEPER, 3)
    return params, model


def _select(ctx: dict, candidates: tuple[str, ...], predicted: np.ndarray) -> tuple:
    """Forward selection over `candidates`: (effects, steps, their models, the held-out
    prediction with every change taken; `predicted`: the baseline's)."""
    prefix: tuple[str, ...] = ()
    effects, steps, models = [], [], []
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
                **{k: c[k] for k in ("effect", "reduction", "p_value", "heldout_gap_before")},
                "heldout_gap": c["heldout_gap"],
                "deviance_reduction": c["deviance_reduction"],
                "confidence": step["confidence"],
                "step": step["step"],
                "parameters": params,
            }
        )
        models.append(model)
        prefix = prefix + _chosen_terms(step["effect"])
        predicted = c["_predicted"][0]
    for step in steps:
        for c in step["candidates"]:
            c.pop("_predicted", None)
    return effects, steps, models, predicted


def _level_only_shape(ctx: dict, selected: list[str], n_candidates: int) -> str | None:
    """The first shape change taken whose shape, given every other change taken, adds
    nothing significant to the level it carries (a lag shift taken later explains it: its
    level is a drift); None if there is none."""
    significant = ctx["alpha"] / max(n_candidates, 1)
    for effect in selected:
        if effect not in SHAPES or len(selected) < 2:
            continue
        others = tuple(t for e in selected if e != effect for t in _chosen_terms(e))
        cf = ctx["chains"].cross(
            {"refit": others + (LEVEL,), effect: others + _chosen_terms(effect)},
            offset_of="refit",
        )
        p_value = _test(ctx["observed"], cf, effect, ctx["segments"], ctx["rng"])["p_value"]
        if p_value >= significant:
            return effect
    return None


def diagnose_change(
    reference: BlockTable, real_diag: Diagnosis, options: DiagnosisOptions | None = None
) -> ChangeDiagnosis:
    """What changed from the `reference` recording's table to the recording `real_diag`
    diagnosed (its lags and contacts are reused): see the module's docstring."""
    o = options or DiagnosisOptions()
    rng = np.random.default_rng(o.seed + 1)
    if (~reference.contact).sum() < MIN_BLOCKS:
        raise GapDataError(f"too few no-contact blocks ({int((~reference.contact).sum())})")
    prior = simulator_cells(reference)
    aligned = _align(reference, o, prior)
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
    if min(s.train.sum() for s in splits) < MIN_TRAIN_BLOCKS:
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
        "rows": rows,
        "lags": {"reference": lag_ref, "real": lag_real},
        "table": null,
    }
    base = chains.cross({"refit": ()}, offset_of="refit")
    gap_base = metric.gap_db(
        heldout_errors(base.predicted["refit"], null.magnitude, rows, ctx["windows"])
    )
    candidates = tuple(e for e in EFFECTS if e in o.effects)
    while True:
        effects, steps, models, predicted = _select(ctx, candidates, base.predicted["refit"])
        unsupported = _level_only_shape(ctx, [e["effect"] for e in effects], len(candidates))
        if unsupported is None:
            break
        candidates = tuple(e for e in candidates if e != unsupported)
    errors = heldout_errors(predicted, null.magnitude, rows, ctx["windows"])
    floor = combined_floor(_floors(null.magnitude[rows], predicted[rows], ctx["windows"]))
    return ChangeDiagnosis(
        effects=effects,
        steps=steps,
        lags={"reference": lag_ref, "real": lag_real},
        gaps={
            "baseline": round(gap_base, 4),
            "after_changes": round(metric.gap_db(errors), 4),
            "floor": round(floor, 4) if np.isfinite(floor) else None,
        },
        blocks={
            "reference": int(reference.n_blocks),
            "real": int(real_table.n_blocks),
            "heldout": int(len(rows)),
        },
        models=models,
    )
