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
    return {"timing": ("timing",), "drift": (LEVEL,)}.get(effect, (effect, effect + CHANGED))


def _step(ctx: dict, prefix: tuple[str, ...], remaining: tuple[str, ...], number: int) -> dict:
    """Every remaining change tested on top of the changes taken (`prefix`)."""
    chains, observed = ctx["chains"], ctx["observed"]
    cands, gains = [], {}
    for effect in remaining:
        alt = prefix + _chosen_terms(effect)  # with the change; the null: without its last term
        null = alt[:-1]
        chains.keep(null)
        cf = chains.cross({"refit": null, effect: alt}, offset_of="refit")
        res = _test(observed, cf, effect, ctx["segments"], ctx["rng"])
        gap_null = metric.gap_db(
            heldout_errors(cf.predicted["refit"], observed, cf.rows, ctx["windows"])
        )
        gap_alt = metric.gap_db(
            heldout_errors(cf.predicted[effect], observed, cf.rows, ctx["windows"])
        )
        gains[effect] = res["gain"]
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
    chosen, confidence = _verdict(
        cands, gains, ctx["alpha"], ctx["segments"], ctx["rng"], gap_key="reduction"
    )
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
