"""The diagnosis: split in time, refit, add each candidate effect, test, rank, explain.

`diagnose(table)` returns a `Diagnosis` holding everything report.json / report.md and
the figures need.  All gap figures are computed on the held-out (later) part of the
recording; every fit uses only the training (earlier) part.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from egovib_ros.gap import metric
from egovib_ros.gap.effects import EFFECTS, FittedModel, fit_all
from egovib_ros.gap.features import BlockTable

TRAIN_FRACTION = 0.6
#: Significance level of the verdict (Bonferroni-corrected over the candidates).
ALPHA = 0.01
#: A significant candidate must also lower the held-out gap by at least this much.
MIN_REDUCTION_DB = 0.002
N_BOOTSTRAP = 2000

METRIC_NAME = "windowed log-spectral distance"
METRIC_DEFINITION = (
    "gap = sqrt(mean over held-out windows w and in-band DFT bins f of e[w,f]^2), "
    "e[w,f] = 20*log10(sum_b |Y_b(f)| / sum_b m_b(f)) over the no-contact blocks b of window w "
    "({w} consecutive blocks, {ws:.2f} s); |Y_b| observed magnitude spectrum (band-passed sum of axes, "
    "model window), m_b the model's expected magnitude (mean spectrum, no +sd). gap^2 is additive over "
    "bins, windows and window labels (velocity cell, covariate bin). floor = split-half estimate of the "
    "score of a perfect model (interleaved block pairs: sqrt(mean (e_A - e_B)^2 / 4)).")


@dataclass
class Diagnosis:
    table: BlockTable
    train: np.ndarray
    heldout: np.ndarray
    heldout_rows: np.ndarray
    windows: metric.Windows
    split_time_s: float
    models: dict[str, FittedModel]
    errors: dict[str, np.ndarray]            # name -> (n_windows, F) held-out window errors [dB]
    gaps: dict[str, float]
    floor: float
    candidates: list[dict]
    verdict: str
    confidence: float
    residual_noise: dict[str, float] = field(default_factory=dict)
    window_blocks: int = metric.DEFAULT_WINDOW_BLOCKS

    @property
    def verdict_model(self) -> FittedModel:
        return self.models[self.verdict] if self.verdict != "none" else self.models["refit"]


def time_split(table: BlockTable, train_fraction: float = TRAIN_FRACTION) -> tuple[np.ndarray, np.ndarray, float]:
    """Train = no-contact blocks in the first `train_fraction` of the time span, held out = the rest."""
    t = table.t_mid_s
    split = float(t[0] + train_fraction * (t[-1] - t[0]))
    clean = ~table.contact
    return clean & (t < split), clean & (t >= split), split


def heldout_errors(model_pred: np.ndarray, observed: np.ndarray, rows: np.ndarray,
                   windows: metric.Windows) -> np.ndarray:
    return metric.window_errors_db(observed[rows], model_pred[rows], windows)


def residual_noise_db(table: BlockTable, predicted: np.ndarray, std_scale: np.ndarray, rows: np.ndarray) -> float:
    """Mean no-contact magnitude left after spectral subtraction (Eq. 3 with Eq. 5 noise), relative to raw [dB].

    The noise estimate is the variant's mean plus the calibrated std scaled by the same
    gain: |X| = max(|Y| - (m + g*sd), 0), summed over in-band bins and held-out blocks.
    """
    y = table.magnitude[rows]
    noise = predicted[rows] + table.base_std[rows] * std_scale[rows]
    left = np.maximum(y - noise, 0.0).sum()
    return float(20.0 * np.log10(max(left, 1e-300) / max(y.sum(), 1e-300)))


def diagnose(table: BlockTable, *, train_fraction: float = TRAIN_FRACTION,
             window_blocks: int = metric.DEFAULT_WINDOW_BLOCKS, alpha: float = ALPHA,
             effects: tuple[str, ...] = EFFECTS, seed: int = 0) -> Diagnosis:
    """Run the whole diagnosis on one recording's block table."""
    train, heldout, split = time_split(table, train_fraction)
    if train.sum() < 200 or heldout.sum() < 4 * window_blocks:
        raise ValueError(f"too few no-contact blocks ({int(train.sum())} train, {int(heldout.sum())} held out)")
    rows = np.flatnonzero(heldout)
    windows = metric.make_windows(len(rows), window_blocks)
    models = fit_all(table, train, effects)
    observed = table.magnitude
    errors = {"sim_as_is": heldout_errors(table.base_mean, observed, rows, windows)}
    for name, fitted in models.items():
        errors[name] = heldout_errors(fitted.predicted, fitted.table.magnitude, rows, windows)
    gaps = {name: metric.gap_db(e) for name, e in errors.items()}
    floor = metric.floor_db(observed[rows], models["refit"].predicted[rows], windows)

    rng = np.random.default_rng(seed)
    base = errors["refit"]
    excess_refit = max(gaps["refit"] ** 2 - floor ** 2, 1e-12)
    candidates = []
    for effect in effects:
        if effect not in errors:
            continue
        p = metric.paired_signflip_pvalue(base, errors[effect], rng=rng)
        removed = float(np.clip((gaps["refit"] ** 2 - gaps[effect] ** 2) / excess_refit, -9.99, 1.0))
        candidates.append({"effect": effect, "heldout_gap": round(gaps[effect], 4),
                           "reduction": round(gaps["refit"] - gaps[effect], 4), "p_value": p,
                           "excess_removed": round(float(removed), 4)})
    candidates.sort(key=lambda c: -c["reduction"])
    level = alpha / max(len(candidates), 1)
    eligible = [c for c in candidates if c["p_value"] < level and c["reduction"] >= MIN_REDUCTION_DB]
    verdict = eligible[0]["effect"] if eligible else "none"
    confidence = _bootstrap_confidence(errors, [c["effect"] for c in candidates], verdict, floor, rng)

    residual = {"raw": 0.0}
    residual["sim_as_is"] = residual_noise_db(table, table.base_mean, np.ones_like(table.base_mean), rows)
    residual["after_refit"] = residual_noise_db(table, models["refit"].predicted, models["refit"].std_scale, rows)
    vm = models[verdict] if verdict != "none" else models["refit"]
    residual["after_effect"] = residual_noise_db(vm.table, vm.predicted, vm.std_scale, rows)
    return Diagnosis(table=table, train=train, heldout=heldout, heldout_rows=rows, windows=windows,
                     split_time_s=split, models=models, errors=errors, gaps=gaps, floor=floor,
                     candidates=candidates, verdict=verdict, confidence=confidence,
                     residual_noise=residual, window_blocks=window_blocks)


def _bootstrap_confidence(errors: dict[str, np.ndarray], names: list[str], verdict: str, floor: float,
                          rng: np.random.Generator, segment_windows: int = 2) -> float:
    """Share of block-bootstrap resamples of held-out segments that reach the same decision.

    For an effect: it has the largest held-out reduction (and at least MIN_REDUCTION_DB).
    For `none`: no candidate reduces the gap by MIN_REDUCTION_DB.
    """
    if not names:
        return 1.0
    sq = {n: np.mean(np.square(errors[n]), axis=1) for n in ["refit"] + names}
    n_w = len(sq["refit"])
    n_seg = max(n_w // segment_windows, 1)
    seg = np.minimum(np.arange(n_w) // segment_windows, n_seg - 1)
    seg_sum = {n: np.bincount(seg, weights=v, minlength=n_seg) for n, v in sq.items()}
    seg_len = np.bincount(seg, minlength=n_seg)
    picks = rng.integers(0, n_seg, size=(N_BOOTSTRAP, n_seg))
    n_picked = seg_len[picks].sum(axis=1)
    mean_sq = {n: s[picks].sum(axis=1) / n_picked for n, s in seg_sum.items()}
    gap_refit = np.sqrt(mean_sq["refit"])
    reduction = np.stack([gap_refit - np.sqrt(mean_sq[n]) for n in names])
    best = np.argmax(reduction, axis=0)
    found = reduction[best, np.arange(N_BOOTSTRAP)] >= MIN_REDUCTION_DB
    if verdict == "none":
        return round(float(np.mean(~found)), 4)
    return round(float(np.mean(found & (best == names.index(verdict)))), 4)
