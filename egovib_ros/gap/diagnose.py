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
#: A significant candidate must also lower the held-out per-block mean squared log
#: error by at least this much (dB^2 per block and bin).
MIN_BLOCK_GAIN_DB2 = 0.01
#: Length of the contiguous held-out segments the permutation test flips (s).
SEGMENT_S = 0.5
DB_PER_NEPER = 20.0 / np.log(10.0)
N_BOOTSTRAP = 2000

METRIC_NAME = "windowed log-spectral distance"
METRIC_DEFINITION = (
    "gap = sqrt(mean over held-out windows w and in-band DFT bins f of e[w,f]^2), "
    "e[w,f] = 20*log10(sum_b |Y_b(f)| / sum_b m_b(f)) over the no-contact blocks b of window w "
    "({w} consecutive blocks, {ws:.2f} s); |Y_b| observed magnitude spectrum (band-passed sum of "
    "axes, model window), m_b the model's expected magnitude (mean spectrum, no +sd). gap^2 is "
    "additive over bins, windows and window labels (velocity cell, covariate bin). floor = the "
    "score of a model equal to the real process, i.e. the scatter of window means alone, "
    "estimated from the held-out blocks' own ratio |Y|/m: its lag-0 and lag-1 (overlapping "
    "blocks) covariances minus the covariance 4 blocks apart, which removes slowly varying model "
    "error."
)


@dataclass
class Diagnosis:
    table: BlockTable
    train: np.ndarray
    heldout: np.ndarray
    heldout_rows: np.ndarray
    windows: metric.Windows
    split_time_s: float
    models: dict[str, FittedModel]
    errors: dict[str, np.ndarray]  # name -> (n_windows, F) held-out window errors [dB]
    gaps: dict[str, float]
    floor: float
    candidates: list[dict]
    verdict: str
    confidence: float
    residual_noise: dict[str, float] = field(default_factory=dict)
    window_blocks: int = metric.DEFAULT_WINDOW_BLOCKS
    reference_lag_s: float = 0.0

    @property
    def verdict_model(self) -> FittedModel:
        return self.models[self.verdict] if self.verdict != "none" else self.models["refit"]


def time_split(
    table: BlockTable, train_fraction: float = TRAIN_FRACTION
) -> tuple[np.ndarray, np.ndarray, float]:
    """Train = no-contact blocks in the first `train_fraction` of the time span,
    held out = the rest."""
    t = table.t_mid_s
    split = float(t[0] + train_fraction * (t[-1] - t[0]))
    clean = ~table.contact
    return clean & (t < split), clean & (t >= split), split


def heldout_errors(
    model_pred: np.ndarray, observed: np.ndarray, rows: np.ndarray, windows: metric.Windows
) -> np.ndarray:
    return metric.window_errors_db(observed[rows], model_pred[rows], windows)


def residual_noise_db(
    table: BlockTable, predicted: np.ndarray, std_scale: np.ndarray, rows: np.ndarray
) -> float:
    """Mean no-contact magnitude left after spectral subtraction (Eq. 3 with Eq. 5 noise),
    relative to raw [dB].

    The noise estimate is the variant's mean plus the calibrated std scaled by the same
    gain: |X| = max(|Y| - (m + g*sd), 0), summed over in-band bins and held-out blocks.
    """
    y = table.magnitude[rows]
    noise = predicted[rows] + table.base_std[rows] * std_scale[rows]
    left = np.maximum(y - noise, 0.0).sum()
    return float(20.0 * np.log10(max(left, 1e-300) / max(y.sum(), 1e-300)))


def diagnose(
    table: BlockTable,
    *,
    train_fraction: float = TRAIN_FRACTION,
    window_blocks: int = metric.DEFAULT_WINDOW_BLOCKS,
    alpha: float = ALPHA,
    effects: tuple[str, ...] = EFFECTS,
    seed: int = 0,
    reference_lag_s: float = 0.0,
) -> Diagnosis:
    """Run the whole diagnosis on one recording's block table.

    `reference_lag_s`: the lag the simulator itself shows between joint states and
    vibration (see `simulator_reference_lag`); timing is judged relative to it.
    """
    train, heldout, split = time_split(table, train_fraction)
    if train.sum() < 200 or heldout.sum() < 4 * window_blocks:
        raise ValueError(
            f"too few no-contact blocks ({int(train.sum())} train, {int(heldout.sum())} held out)"
        )
    rows = np.flatnonzero(heldout)
    windows = metric.make_windows(len(rows), window_blocks)
    # "Synchronous" means in sync the way the simulator is: its vibration envelope trails
    # the joint velocity by the structural and band-pass group delay (a few ms), so the
    # refit and all non-timing candidates use the simulator's reference lag; the timing
    # candidate fits its own.
    fit_table = table.at_lag(reference_lag_s) if reference_lag_s else table
    models = fit_all(fit_table, train, effects)
    if "timing" in models:
        lag = models["timing"].parameters["lag_s"]
        models["timing"].parameters["reference_lag_s"] = round(float(reference_lag_s), 5)
        models["timing"].parameters["lag_vs_simulator_s"] = round(float(lag - reference_lag_s), 5)
    observed = table.magnitude
    errors = {"sim_as_is": heldout_errors(table.base_mean, observed, rows, windows)}
    for name, fitted in models.items():
        errors[name] = heldout_errors(fitted.predicted, observed, rows, windows)
    gaps = {name: metric.gap_db(e) for name, e in errors.items()}

    rng = np.random.default_rng(seed)
    # Scatter is estimated around the best held-out predictor: a model error that varies
    # from block to block (e.g. a wrong lag) would otherwise count as scatter.
    best = min(models, key=lambda name: gaps[name])
    floor = metric.floor_db(observed[rows], models[best].predicted[rows], windows)
    # The decision uses every held-out block, not window means: per-block squared log
    # residuals (centred by the refit's training offset, the log-of-Rayleigh bias common
    # to all models), paired against the refit, contiguous SEGMENT_S segments.
    offset = np.mean(
        metric.block_log_errors(observed[train], models["refit"].predicted[train]), axis=0
    )
    loss = {
        name: np.sum(
            (metric.block_log_errors(observed[rows], f.predicted[rows]) - offset) ** 2, axis=1
        )
        for name, f in models.items()
    }
    segments = np.floor((table.t_mid_s[rows] - split) / SEGMENT_S).astype(np.int64)
    segments -= segments.min()
    n_bins = observed.shape[1]
    excess_refit = max(gaps["refit"] ** 2 - floor**2, 1e-12)
    candidates = []
    for effect in effects:
        if effect not in errors:
            continue
        p = metric.segment_signflip_pvalue(loss["refit"], loss[effect], segments, rng=rng)
        removed = float(
            np.clip((gaps["refit"] ** 2 - gaps[effect] ** 2) / excess_refit, -9.99, 1.0)
        )
        block_gain = float(np.mean(loss["refit"] - loss[effect]) / n_bins) * DB_PER_NEPER**2
        candidates.append(
            {
                "effect": effect,
                "heldout_gap": round(gaps[effect], 4),
                "reduction": round(gaps["refit"] - gaps[effect], 4),
                "p_value": p,
                "excess_removed": round(removed, 4),
                "block_mse_reduction_db2": round(float(block_gain), 5),
            }
        )
    candidates.sort(key=lambda c: -c["block_mse_reduction_db2"])
    level = alpha / max(len(candidates), 1)
    eligible = [
        c
        for c in candidates
        if c["p_value"] < level and c["block_mse_reduction_db2"] >= MIN_BLOCK_GAIN_DB2
    ]
    verdict = eligible[0]["effect"] if eligible else "none"
    if verdict == "none":
        # How far the strongest candidate is from being named: 1 - its Bonferroni-adjusted p.
        best_p = min([c["p_value"] for c in candidates], default=1.0)
        confidence = round(float(1.0 - min(1.0, best_p * max(len(candidates), 1))), 4)
    else:
        confidence = _bootstrap_confidence(
            loss, [c["effect"] for c in candidates], verdict, segments, n_bins, rng
        )

    residual = {"raw": 0.0}
    residual["sim_as_is"] = residual_noise_db(
        table, table.base_mean, np.ones_like(table.base_mean), rows
    )
    residual["after_refit"] = residual_noise_db(
        models["refit"].table, models["refit"].predicted, models["refit"].std_scale, rows
    )
    vm = models[verdict] if verdict != "none" else models["refit"]
    residual["after_effect"] = residual_noise_db(vm.table, vm.predicted, vm.std_scale, rows)
    return Diagnosis(
        reference_lag_s=float(reference_lag_s),
        table=table,
        train=train,
        heldout=heldout,
        heldout_rows=rows,
        windows=windows,
        split_time_s=split,
        models=models,
        errors=errors,
        gaps=gaps,
        floor=floor,
        candidates=candidates,
        verdict=verdict,
        confidence=confidence,
        residual_noise=residual,
        window_blocks=window_blocks,
    )


def _bootstrap_confidence(
    loss: dict[str, np.ndarray],
    names: list[str],
    verdict: str,
    segments: np.ndarray,
    n_bins: int,
    rng: np.random.Generator,
) -> float:
    """Share of block-bootstrap resamples (held-out segments drawn with replacement) in which
    the verdict's effect has the largest held-out per-block gain over the refit (at least
    MIN_BLOCK_GAIN_DB2).
    """
    if not names:
        return 1.0
    n_seg = int(segments.max()) + 1
    seg_len = np.bincount(segments, minlength=n_seg)
    gain = np.stack(
        [np.bincount(segments, weights=loss["refit"] - loss[n], minlength=n_seg) for n in names]
    )
    picks = rng.integers(0, n_seg, size=(N_BOOTSTRAP, n_seg))
    n_picked = np.maximum(seg_len[picks].sum(axis=1), 1)
    mean_gain = gain[:, picks].sum(axis=2) / n_picked / n_bins * DB_PER_NEPER**2  # (K, N_BOOTSTRAP)
    best = np.argmax(mean_gain, axis=0)
    found = mean_gain[best, np.arange(N_BOOTSTRAP)] >= MIN_BLOCK_GAIN_DB2
    return round(float(np.mean(found & (best == names.index(verdict)))), 4)
