"""The diagnosis: split in time, refit, add each candidate effect, test, rank, explain.

`diagnose(table)` returns a `Diagnosis` holding everything report.json / report.md and
the figures need.  All gap figures are computed on the held-out (later) part of the
recording; every fit uses only the training (earlier) part.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage, stats

from egovib_ros.errors import ConfigError, GapDataError
from egovib_ros.gap import metric
from egovib_ros.gap.baseline import fit_baseline, simulator_cells
from egovib_ros.gap.chain import ALL, ChainFits, CrossFitted, Split
from egovib_ros.gap.effects import (
    DB_PER_NEPER,
    EFFECTS,
    LAG_TOLERANCE_S,
    FittedModel,
    lag_scan,
    place_lag,
    refine_lag,
    shape_curve,
    time_hats,
)
from egovib_ros.gap.features import BlockTable, detect_contacts

TRAIN_FRACTION = 0.6
#: Each training split must hold at least this many no-contact blocks (the candidates' fits).
MIN_TRAIN_BLOCKS = 200
#: ... so a diagnosis needs at least this many, the forward split's 60 % holding them (it
#: was 400, which refused an 8.5 s flight part whose effect its own fits could take:
#: docs/gap_validation_real.md).
MIN_BLOCKS = int(np.ceil(MIN_TRAIN_BLOCKS / TRAIN_FRACTION))
#: Blocked cross-validation in time: this many contiguous folds.
N_FOLDS = 5
#: Significance level of the verdict (Bonferroni-corrected over the candidates). It was 0.01
#: while timing was judged against 0: at 0.05 the real flight's own motor lag was named,
#: with advice that cost noise reduction (docs/gap.md, "The significance level").
ALPHA = 0.05
#: A significant candidate must also lower the held-out Gamma deviance of the expected
#: power by at least this much per block and bin (~0.7 % of the deviance of noise-like
#: bins): twice the largest of 30 effect-free bags of three generators (0.00106, the third
#: hand's); 0.004 missed true effects at 0.0025-0.0035 (docs/gap.md, "The minimum gain").
MIN_DEVIANCE_GAIN = 0.002
#: ... and from the second step of the forward selection on this much: a fitted term leaves
#: structured misfit behind, which another flexible term can take a little of (docs/gap.md).
MIN_DEVIANCE_GAIN_LATER = 0.008
#: The deviance compares power summed over this many consecutive tested blocks.
DEVIANCE_RUN = 4
#: Length of the contiguous held-out segments the permutation test flips (s).
SEGMENT_S = 0.5
N_BOOTSTRAP = 2000
#: Interleaved split of the drift check: chunks of this length, every INTERLEAVE_PERIOD-th held out.
INTERLEAVE_CHUNK_S = 4.0
INTERLEAVE_PERIOD = 3
#: Knot spacing (s) of the in-sample time trend checked on interleaved blocks (at most 12 knots).
INTERLEAVE_KNOT_S = 10.0
#: ... but at least this many chunks and knot intervals over the recording (short ones).
INTERLEAVE_MIN_CHUNKS = 10
INTERLEAVE_MIN_KNOTS = 8
#: ... and knots never closer than this many chunk lengths: a held-out chunk is then
#: predicted by a trend spanning several training chunks, not by its neighbours' level.
INTERLEAVE_KNOT_CHUNKS = 2.5
#: A transient (detected like a contact) counts as reversal-locked if it starts within this
#: window around a joint reversal (s after, s before).
LOCK_AFTER_S, LOCK_BEFORE_S = 0.08, 0.03
#: Significance needed (on training data) to treat reversal-locked transients as ego-vibration.
LOCK_ALPHA = 1e-4
LOCK_MIN_EVENTS = 5

METRIC_NAME = "windowed log-spectral distance"
METRIC_DEFINITION = (
    "gap = sqrt(mean over held-out windows w and in-band DFT bins f of e[w,f]^2), "
    "e[w,f] = 20*log10(sum_b |Y_b(f)| / sum_b m_b(f)) over the no-contact blocks b of window w "
    "({w} consecutive blocks, {ws:.2f} s); |Y_b| observed magnitude spectrum "
    "(band-passed sum of axes, model window), m_b the model's expected magnitude "
    "(mean spectrum, no +sd). gap^2 is additive over bins, windows and window labels "
    "(velocity cell, covariate bin). floor = the score of a model equal to the real process, "
    "i.e. the scatter of window means alone, estimated around the best held-out model in two "
    "ways and the smaller reported: from the blocks' ratios |Y|/m (lag-0 and lag-1 "
    "covariances minus the covariance 4 blocks apart, which removes slowly varying model "
    "error) and from the window errors e[w,f] (their variance minus the covariance of windows "
    "two apart)."
)


@dataclass
class Diagnosis:
    table: BlockTable
    train: np.ndarray
    heldout: np.ndarray
    heldout_rows: np.ndarray
    windows: metric.Windows
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
    sync_lag_s: float = 0.0
    lag_scan: dict = field(default_factory=dict)
    interleaved: dict = field(default_factory=dict)
    transients: dict = field(default_factory=dict)
    split_info: dict = field(default_factory=dict)
    floor_estimates: dict = field(default_factory=dict)
    #: the effects found by the forward selection, in order (the first is `verdict`): each
    #: with its held-out reduction given the ones before, test, confidence and parameters
    effects: list[dict] = field(default_factory=list)
    #: their terms, each fitted on every clean block on top of the ones before it
    effect_models: list[FittedModel] = field(default_factory=list)
    #: every forward-selection step: the candidates tested on top of the effects before
    steps: list[dict] = field(default_factory=list)


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


def _segments(t: np.ndarray, rows: np.ndarray, origin: float) -> np.ndarray:
    """Contiguous SEGMENT_S segments of held-out rows (renumbered from 0)."""
    seg = np.floor((t[rows] - origin) / SEGMENT_S).astype(np.int64)
    _, seg = np.unique(seg, return_inverse=True)
    return seg


def _block_loss(
    observed: np.ndarray, predicted: np.ndarray, rows: np.ndarray, offset: np.ndarray
) -> np.ndarray:
    return np.sum((metric.block_log_errors(observed[rows], predicted[rows]) - offset) ** 2, axis=1)


def reversal_locked_transients(
    table: BlockTable, raw: np.ndarray, flagged: np.ndarray
) -> tuple[np.ndarray, dict]:
    """Transients that start at joint reversals are the robot's own (backlash, clunks),
    not contacts.

    Contacts are external: their onsets fall near a reversal only as often as reversal
    windows cover the time. If transient onsets cluster there far more often (one-sided
    binomial test, LOCK_ALPHA), the transients starting near a reversal are returned to
    the data as ego-vibration (for every model). Returns the new contact mask and a summary.
    """
    info = {
        "onsets": 0,
        "near_reversal": 0,
        "expected_near": 0.0,
        "p_value": 1.0,
        "returned_blocks": 0,
    }
    if not raw.any():
        return flagged, info
    near = (
        (table.reversal_after_s <= LOCK_AFTER_S) | (table.reversal_before_s <= LOCK_BEFORE_S)
    ).any(axis=1)
    onset = raw & ~np.concatenate([[False], raw[:-1]])
    n, k = int(onset.sum()), int((onset & near).sum())
    share = float(near.mean())
    p = (
        float(stats.binomtest(k, n, share, alternative="greater").pvalue)
        if n and 0 < share < 1
        else 1.0
    )
    info.update(
        {
            "onsets": n,
            "near_reversal": k,
            "expected_near": round(n * share, 2),
            "p_value": p,
            "window_s": [-LOCK_BEFORE_S, LOCK_AFTER_S],
        }
    )
    if p >= LOCK_ALPHA or k < LOCK_MIN_EVENTS:
        return flagged, info
    labels, _ = ndimage.label(flagged)
    locked = np.unique(labels[onset & near])
    locked = locked[locked > 0]
    back = np.isin(labels, locked)
    info["returned_blocks"] = int(back.sum())
    return flagged & ~back, info


def fold_index(t: np.ndarray, n_folds: int) -> np.ndarray:
    """Each time's contiguous fold (0 .. n_folds - 1) over the span of `t`."""
    return np.minimum(
        ((t - t[0]) / max(t[-1] - t[0], 1e-9) * n_folds).astype(np.int64), n_folds - 1
    )


def blocked_folds(table: BlockTable, n_folds: int) -> list[Split]:
    """Contiguous time folds: each held out once, fitted on the others
    (no contact blocks anywhere)."""
    fold = fold_index(table.t_mid_s, n_folds)
    clean = ~table.contact
    return [Split(clean & (fold != k), clean & (fold == k)) for k in range(n_folds)]


def forward_split(table: BlockTable, train_fraction: float) -> list[Split]:
    train, held, _ = time_split(table, train_fraction)
    return [Split(train, held)]


def interleaved_splits(table: BlockTable, chunk_s: float = INTERLEAVE_CHUNK_S) -> list[Split]:
    """Chunks of `chunk_s`; rotation r holds out every INTERLEAVE_PERIOD-th chunk from r on."""
    t = table.t_mid_s
    chunk = np.floor((t - t[0]) / chunk_s).astype(np.int64) % INTERLEAVE_PERIOD
    clean = ~table.contact
    return [Split(clean & (chunk != r), clean & (chunk == r)) for r in range(INTERLEAVE_PERIOD)]


def combined_floor(floors: dict[str, float]) -> float:
    """The smaller of the two floor estimates.

    Both are unbiased for a model equal to the process; each is inflated by something
    else: the block-ratio estimate by heavy-tailed ratios (a few loud blocks: it linearises
    the log), the window estimate by model error that changes within ~170 ms (it counts
    it as scatter).  Measured on bags where one of them exceeded the best model's own
    held-out gap (timing, effect-free alternate reality), the other did not.
    """
    values = [v for v in floors.values() if np.isfinite(v)]
    return float(min(values)) if values else float("nan")


def candidate_chains(prefix: tuple[str, ...], effects) -> dict[str, tuple[str, ...]]:
    """The chains a forward-selection step compares: "refit" = the effects selected so far
    (`prefix`; none: the velocity-only baseline), and each remaining candidate on top."""
    return {"refit": tuple(prefix), **{e: tuple(prefix) + (e,) for e in effects}}


def _time_trend_term(n_knots: int):
    """Term maker for the in-sample time trend: piecewise linear in elapsed time over the
    whole span."""

    def term(table: BlockTable, scales) -> tuple[np.ndarray, list[str]]:
        t = table.t_mid_s
        x = time_hats(t, float(t[0]), float(t[-1]), n_knots)
        return x, [f"time_hat{k + 1}" for k in range(x.shape[1])]

    return term


def _test(
    observed: np.ndarray, cf: CrossFitted, name: str, segments: np.ndarray, rng: np.random.Generator
) -> dict:
    """Held-out comparison of one candidate with the baseline on the tested rows.

    Decision: per-block Gamma deviance of the expected power (paired sign-flip test over
    segments, gain per block and bin); reported alongside: the per-block squared log
    error of the expected magnitude (dB^2).
    """
    rows = cf.rows
    # Power summed over short runs of DEVIANCE_RUN consecutive tested blocks (sums of
    # expected powers are expected sums; the ratio of sums has lighter tails than one block's).
    run = np.arange(len(rows)) // DEVIANCE_RUN

    def sums(a):
        return np.stack([np.bincount(run, weights=a[:, f]) for f in range(a.shape[1])], axis=1)

    y = sums(observed[rows] ** 2)
    # each block gets its run's deviance
    dev_base = metric.block_deviance(y, sums(cf.power["refit"][rows]))[run]
    dev_cand = metric.block_deviance(y, sums(cf.power[name][rows]))[run]
    gain = dev_base - dev_cand
    log_base = _block_loss(observed, cf.predicted["refit"], rows, cf.offset[rows])
    log_cand = _block_loss(observed, cf.predicted[name], rows, cf.offset[rows])
    return {
        "p_value": metric.segment_signflip_pvalue(gain, segments, rng),
        "deviance_reduction": float(np.mean(gain)),
        "block_mse_reduction_db2": float(np.mean(log_base - log_cand) / observed.shape[1])
        * DB_PER_NEPER**2,
        "gain": gain,  # per block: what the bootstrap resamples
    }


def _interleaved_drift(
    tables: dict, prior, window_blocks: int, rng: np.random.Generator, prefix: tuple = ()
) -> dict:
    """Drift checked in-sample: a time trend fitted on interleaved chunks, judged on the
    chunks between; on top of the effects selected so far (`prefix`, fitted on the same
    chunks). `tables`: as ChainFits takes them."""
    table = tables["sync"]
    t = table.t_mid_s
    span = float(t[-1] - t[0])
    # A short recording (a real part of a few seconds) gets shorter chunks and knots, so that
    # it still has several chunks per rotation and a warm-up of a few seconds has knots.
    chunk_s = min(INTERLEAVE_CHUNK_S, span / INTERLEAVE_MIN_CHUNKS)
    knot_s = max(
        min(INTERLEAVE_KNOT_S, span / INTERLEAVE_MIN_KNOTS), INTERLEAVE_KNOT_CHUNKS * chunk_s
    )
    splits = interleaved_splits(table, chunk_s=chunk_s)
    if min(s.train.sum() for s in splits) < MIN_TRAIN_BLOCKS:
        return {}
    n_knots = int(np.clip(round(span / knot_s) + 1, 3, 12))
    clean = ~table.contact
    chains = ChainFits(
        tables, splits, prior, clean=clean, custom={"drift_in_sample": _time_trend_term(n_knots)}
    )
    chains.keep(prefix)
    cf = chains.cross(
        {"refit": prefix, "drift_in_sample": prefix + ("drift_in_sample",)}, offset_of="refit"
    )
    rows = cf.rows
    if len(rows) < 4 * window_blocks:
        return {}
    observed = table.magnitude
    segments = _segments(t, rows, float(t[0]))
    res = _test(observed, cf, "drift_in_sample", segments, rng)
    windows = metric.make_windows(len(rows), window_blocks)
    e_base = heldout_errors(cf.predicted["refit"], observed, rows, windows)
    e_drift = heldout_errors(cf.predicted["drift_in_sample"], observed, rows, windows)
    best = "drift_in_sample" if metric.gap_db(e_drift) < metric.gap_db(e_base) else "refit"
    # The fitted shape, on all clean blocks.
    fitted = chains.fit(ALL, prefix + ("drift_in_sample",))
    coef, ridge = fitted.coef, fitted.parameters.get("ridge", {})
    curve_t = np.linspace(float(t[0]), float(t[-1]), 61)
    g = time_hats(curve_t, float(t[0]), float(t[-1]), n_knots) @ coef[1:].mean(axis=1)
    return {
        "p_value": res["p_value"],
        "deviance_reduction": round(res["deviance_reduction"], 6),
        "block_mse_reduction_db2": round(res["block_mse_reduction_db2"], 5),
        "heldout_gap_baseline": round(metric.gap_db(e_base), 4),
        "heldout_gap_drift": round(metric.gap_db(e_drift), 4),
        "floor": round(
            combined_floor(_floors(observed[rows], cf.predicted[best][rows], windows)), 4
        ),
        "split": f"chunks of {chunk_s:.3g} s, every {INTERLEAVE_PERIOD}rd held out "
        f"in turn ({INTERLEAVE_PERIOD} rotations)",
        "knots": n_knots,
        "ridge": {k: round(v, 5) for k, v in ridge.items()},
        "shape": shape_curve(curve_t, "s", g - g.mean(), 2),
    }


@dataclass(frozen=True, kw_only=True)
class DiagnosisOptions:
    """How `diagnose` splits, tests and aligns (keyword-only, checked when made).

    Held-out predictions come from blocked `folds`-fold cross-validation in time (each
    contiguous fold predicted by models fitted on the others), or with `train_fraction`
    from a single forward split (fit on the leading share, test on the rest).
    `window_blocks`: blocks per window of the gap metric. `alpha`: the significance level a
    candidate must reach. `effects`: the candidates tried. `seed`: the randomisation tests'.
    `reference_lag_s`: the lag the simulator itself shows between joint states and
    vibration (see `simulator_reference_lag`); lags within `lag_tolerance_s` of it count as
    in sync (the baseline and all non-timing candidates use the best of them), timing is a
    lag beyond that.
    """

    folds: int = N_FOLDS
    train_fraction: float | None = None
    window_blocks: int = metric.DEFAULT_WINDOW_BLOCKS
    alpha: float = ALPHA
    effects: tuple[str, ...] = EFFECTS
    seed: int = 0
    reference_lag_s: float = 0.0
    lag_tolerance_s: float = LAG_TOLERANCE_S

    def __post_init__(self):
        def bad(name: str, want: str):
            raise ConfigError(f"gap options: {name} must be {want}, got {getattr(self, name)!r}")

        if not isinstance(self.folds, int) or not 2 <= self.folds <= 50:
            bad("folds", "an integer in [2, 50]")
        if self.train_fraction is not None and not 0.0 < self.train_fraction < 1.0:
            bad("train_fraction", "None or within (0, 1)")
        if not isinstance(self.window_blocks, int) or self.window_blocks < 1:
            bad("window_blocks", "a positive integer")
        if not 0.0 < self.alpha < 1.0:
            bad("alpha", "within (0, 1)")
        if not self.effects or not set(self.effects) <= set(EFFECTS):
            bad("effects", f"a non-empty subset of {EFFECTS}")
        if not np.isfinite(self.reference_lag_s) or abs(self.reference_lag_s) > 1.0:
            bad("reference_lag_s", "finite seconds within +-1")
        if not 0.0 <= self.lag_tolerance_s <= 1.0:
            bad("lag_tolerance_s", "seconds within [0, 1]")
        object.__setattr__(self, "effects", tuple(self.effects))


def diagnose(table: BlockTable, options: DiagnosisOptions | None = None) -> Diagnosis:
    """Run the whole diagnosis on one recording's block table (`options`: DiagnosisOptions,
    the defaults when None).

    The steps: lags and contacts (`_align`), the splits, held-out predictions of the
    baseline and every candidate (`chain.ChainFits`), the fitted terms for the report
    (`_fitted_models`), held-out gaps and the floor (`_heldout_gaps`), each candidate
    tested against the baseline and the first effect (`_step`); then the forward selection
    (`_select_more`): each remaining candidate on top of the effects found so far, tested
    against them, until none is significant.

    One function: it is the order of the steps above, each a function of its own, passing
    the splits, fits and tests along into the Diagnosis.
    """
    o = options or DiagnosisOptions()
    effects, window_blocks = o.effects, o.window_blocks
    rng = np.random.default_rng(o.seed)
    if (~table.contact).sum() < MIN_BLOCKS:
        raise GapDataError(f"too few no-contact blocks ({int((~table.contact).sum())})")
    prior = simulator_cells(table)
    aligned = _align(table, o, prior)
    splits = (
        forward_split(table, o.train_fraction)
        if o.train_fraction is not None
        else blocked_folds(table, o.folds)
    )
    if (
        min(s.train.sum() for s in splits) < MIN_TRAIN_BLOCKS
        or sum(s.test.sum() for s in splits) < 4 * window_blocks
    ):
        raise GapDataError("too few no-contact blocks to fit and test")
    clean = ~aligned.contact
    tables = {"sync": aligned.base_table, "timing": aligned.timing_table}
    chains = ChainFits(tables, splits, prior, clean=clean)
    cf = chains.cross(candidate_chains((), effects), offset_of="refit")
    rows = cf.rows
    windows = metric.make_windows(len(rows), window_blocks)
    models = _fitted_models(table, aligned, effects, chains, cf)
    errors, gaps, floors = _heldout_gaps(table, models, cf, windows)
    floor = combined_floor(floors)
    # The decision uses every held-out block, not window means: per-block squared log
    # residuals (centred by the baseline's training offset of the row's split, the
    # log-of-Rayleigh bias common to all models), paired against the baseline,
    # contiguous SEGMENT_S segments.
    segments = _segments(table.t_mid_s, rows, float(table.t_mid_s[0]))
    context = _SelectionContext(chains, prior, aligned, o, windows, segments, floor, rng)
    first, interleaved = _step(context, (), cf, gaps, 1)
    if "drift" in models and interleaved:
        _add_interleaved_shape(models["drift"], interleaved)
    selection = _select_more(context, first, models, gaps, cf)
    models["combined"] = _held_out_model("combined", selection.predicted, selection.power, table)
    errors["combined"] = heldout_errors(selection.predicted, table.magnitude, rows, windows)
    gaps["combined"] = metric.gap_db(errors["combined"])
    if gaps["combined"] < min(gaps[name] for name in gaps if name != "sim_as_is") - 1e-12:
        # scatter estimated around the best held-out model (the combined one)
        floors = _floors(table.magnitude[rows], selection.predicted[rows], windows)
        floor = combined_floor(floors)
    vm = models["combined"]
    residual = {
        "raw": 0.0,
        "sim_as_is": residual_noise_db(table, table.base_mean, np.ones_like(table.base_mean), rows),
        "after_refit": residual_noise_db(
            table, models["refit"].predicted, models["refit"].std_scale, rows
        ),
        "after_effect": residual_noise_db(table, vm.predicted, vm.std_scale, rows),
    }
    heldout = np.zeros(table.n_blocks, bool)
    heldout[rows] = True
    return Diagnosis(
        reference_lag_s=float(o.reference_lag_s),
        table=table,
        train=clean,
        heldout=heldout,
        heldout_rows=rows,
        windows=windows,
        models=models,
        errors=errors,
        gaps=gaps,
        floor=floor,
        candidates=first["candidates"],
        verdict=first["effect"],
        confidence=first["confidence"],
        residual_noise=residual,
        window_blocks=window_blocks,
        sync_lag_s=float(aligned.sync_lag),
        lag_scan={
            "lag_s": aligned.lags.tolist(),
            "train_log_residual": aligned.curve.tolist(),
            "sync_lag_s": aligned.sync_lag,
            "timing_lag_s": aligned.timing_lag,
        },
        interleaved=interleaved,
        transients=aligned.transients,
        split_info=_split_info(table.t_mid_s, o.folds, o.train_fraction),
        floor_estimates=floors,
        effects=selection.effects,
        effect_models=selection.models,
        steps=selection.steps,
    )


@dataclass
class _SelectionContext:
    """What every forward-selection step needs."""

    chains: ChainFits
    prior: tuple
    aligned: "_Aligned"
    options: DiagnosisOptions
    windows: metric.Windows
    segments: np.ndarray
    floor: float
    rng: np.random.Generator


@dataclass
class _Selection:
    effects: list[dict]  # the selected effects, in order (report: verdict.effects)
    models: list[FittedModel]  # each one's term fitted on every clean block after the ones before
    steps: list[dict]  # every step: its candidates tested on top of the effects before
    predicted: np.ndarray  # (B, F) held-out expected magnitude of the combined model
    power: np.ndarray  # (B, F) held-out expected power of the combined model


def _effect_entry(step: dict, gap_before: float, model: FittedModel) -> dict:
    """A selected effect: its held-out reduction given the effects before it, test, model."""
    c = next(c for c in step["candidates"] if c["effect"] == step["effect"])
    tested = ("heldout_gap", "reduction", "gap_reduction_decisive", "p_value")
    tested += ("deviance_reduction", "block_mse_reduction_db2", "decided_by")
    return {
        **{k: step[k] for k in ("effect", "step", "confidence")},
        "heldout_gap_before": round(float(gap_before), 4),
        **{k: c[k] for k in tested if k in c},
        "parameters": model.parameters,
    }


def _select_more(
    ctx: _SelectionContext, first: dict, models: dict, gaps: dict, cf: CrossFitted
) -> _Selection:
    """Forward selection on held-out data: the first step's effect, then each remaining
    candidate fitted on top of the effects selected so far (the same folds), tested against
    them with the first step's rule (p < alpha / candidates of the step, deviance gain, a
    smaller held-out gap), the best one taken, until no candidate of a step qualifies."""
    chains = ctx.chains
    observed = chains.tables["sync"].magnitude
    rows = cf.rows
    steps = [first]
    if first["effect"] == "none":
        return _Selection([], [], steps, cf.predicted["refit"], cf.power["refit"])
    selected = [first["effect"]]
    entries = [_effect_entry(first, gaps["refit"], models[first["effect"]])]
    fitted = [models[first["effect"]]]
    predicted, power = cf.predicted[first["effect"]], cf.power[first["effect"]]
    gap_now = gaps[first["effect"]]
    o = ctx.options
    while len(selected) < len(o.effects):
        prefix = tuple(selected)
        remaining = tuple(e for e in o.effects if e not in selected)
        chains.keep(prefix)
        cf_k = chains.cross(candidate_chains(prefix, remaining), offset_of="refit")
        gaps_k = {
            name: metric.gap_db(heldout_errors(cf_k.predicted[name], observed, rows, ctx.windows))
            for name in cf_k.predicted
        }
        step, interleaved = _step(ctx, prefix, cf_k, gaps_k, len(steps) + 1)
        steps.append(step)
        effect = step["effect"]
        if effect == "none":
            break
        model = _chain_model(ctx, prefix, effect, interleaved)
        entries.append(_effect_entry(step, gap_now, model))
        fitted.append(model)
        selected.append(effect)
        predicted, power = cf_k.predicted[effect], cf_k.power[effect]
        gap_now = gaps_k[effect]
    return _Selection(entries, fitted, steps, predicted, power)


def _step(
    ctx: _SelectionContext, prefix: tuple[str, ...], cf: CrossFitted, gaps: dict, number: int
) -> tuple[dict, dict]:
    """Forward-selection step `number`: every remaining candidate on top of `prefix`
    (cross-fitted in `cf`, held-out `gaps`) tested against it, and the one taken (`none`:
    the selection stops); also the step's interleaved drift check ({} without drift)."""
    o = ctx.options
    remaining = tuple(e for e in o.effects if e not in prefix)
    interleaved = (
        _interleaved_drift(ctx.chains.tables, ctx.prior, o.window_blocks, ctx.rng, prefix)
        if "drift" in remaining
        else {}
    )
    observed = ctx.chains.tables["sync"].magnitude
    cands, gains = _candidates(
        observed, cf, remaining, gaps, ctx.floor, ctx.segments, interleaved, ctx.rng
    )
    min_gain = MIN_DEVIANCE_GAIN_LATER if prefix else MIN_DEVIANCE_GAIN
    effect, confidence = _verdict(cands, gains, o.alpha, ctx.segments, ctx.rng, min_gain=min_gain)
    step = {
        "step": number,
        "prefix": list(prefix),
        "candidates": cands,
        "effect": effect,
        "confidence": confidence,
    }
    return step, interleaved


def _add_interleaved_shape(model: FittedModel, interleaved: dict) -> None:
    """The drift term's shapes with the interleaved check's curve beside them."""
    model.shape = dict(model.shape or {})
    model.shape["drift:elapsed_time (interleaved check)"] = interleaved["shape"]


def _chain_model(
    ctx: _SelectionContext, prefix: tuple[str, ...], effect: str, interleaved: dict
) -> FittedModel:
    """The selected effect's term fitted on every clean block on top of `prefix` (its
    parameters and shape for the report)."""
    chain = prefix + (effect,)
    model = ctx.chains.fit(ALL, chain)
    if effect == "timing":
        scales = ctx.chains.baseline(ALL, ctx.chains.lag_key(chain))[1]
        return _timing_model(model, ctx.aligned, scales)
    if effect == "drift" and interleaved:
        _add_interleaved_shape(model, interleaved)
    return model


def _held_out_model(
    name: str, predicted: np.ndarray, power: np.ndarray, table: BlockTable
) -> FittedModel:
    """A model known by its held-out predictions only (the combined one)."""
    return FittedModel(
        name=name,
        predicted=predicted,
        std_scale=predicted / np.maximum(table.base_mean, 1e-12),
        power=power,
        table=table,
    )


@dataclass
class _Aligned:
    """The lags found and the contacts detected against the recording's own baseline."""

    lags: np.ndarray  # the lags scanned (s)
    curve: np.ndarray  # training log residual of the baseline at each
    sync_lag: float  # best lag within the tolerance of the simulator's own
    timing_lag: float  # best lag anywhere (the timing candidate's)
    sync_band: tuple[float, float]
    reference_lag_s: float  # the options': the simulator's own lag, and the tolerance around it
    tolerance_s: float
    base_table: BlockTable  # the table at the sync lag, contacts detected
    timing_table: BlockTable | None  # at the timing lag, if that differs
    contact: np.ndarray
    transients: dict


def _align(table: BlockTable, o: DiagnosisOptions, prior) -> _Aligned:
    """Lags: one scan of the baseline's residual (a single nuisance parameter, fitted on
    every clean block, +-LAG_RANGE_S around the reference); "in sync" = the best lag within
    the tolerance. Then contacts again, against the baseline fitted to this recording (the
    simulator's spectra may differ in shape), with reversal-locked transients returned to
    the data. Sets table.contact."""
    effects, reference_lag_s = o.effects, o.reference_lag_s
    clean = ~table.contact
    # Centred on the reference: the in-sync band is always inside the grid, and a lag is
    # looked for as far on either side of the robot's own lag.
    lags, curve = lag_scan(table, clean, prior=prior, centre_s=reference_lag_s)
    lo, hi = reference_lag_s - o.lag_tolerance_s, reference_lag_s + o.lag_tolerance_s
    sync_lag = refine_lag(table, clean, lags, curve, lo=lo, hi=hi, prior=prior)
    # Timing is a lag beyond the tolerance: placed by the full baseline (`place_lag`), a
    # lag it puts within the band is the in-sync one (two criteria's optima 1 ms apart
    # must not make a timing term: an effect-free bag was named `timing` for a 1 ms lag).
    timing_lag = sync_lag
    if "timing" in effects:
        placed = place_lag(table, clean, lags, curve, prior=prior)
        timing_lag = sync_lag if lo - 1e-9 <= placed <= hi + 1e-9 else placed
    base_table = table.at_lag(sync_lag)
    base = fit_baseline(base_table, clean, prior=prior)
    flagged, raw = detect_contacts(table.magnitude, base.magnitude, table.t_mid_s)
    contact, transients = reversal_locked_transients(base_table, raw, flagged)
    table.contact = contact
    timing_table = None
    if "timing" in effects and abs(timing_lag - sync_lag) > 1e-4:
        timing_table = replace(table.at_lag(timing_lag), contact=contact)
    return _Aligned(
        lags=lags,
        curve=curve,
        sync_lag=sync_lag,
        timing_lag=timing_lag,
        sync_band=(lo, hi),
        reference_lag_s=reference_lag_s,
        tolerance_s=o.lag_tolerance_s,
        base_table=replace(base_table, contact=contact),
        timing_table=timing_table,
        contact=contact,
        transients=transients,
    )


def _fitted_models(
    table: BlockTable, aligned: _Aligned, effects, chains: ChainFits, cf: CrossFitted
) -> dict[str, FittedModel]:
    """The fitted terms (parameters, shapes) for the report, fitted on every clean block;
    their predictions then replaced by the held-out ones (all figures are held out)."""
    models = {
        name: chains.fit(ALL, chain)
        for name, chain in candidate_chains((), [e for e in effects if e != "timing"]).items()
    }
    if "timing" in effects:
        scales = chains.baseline(ALL, "sync")[1]
        models["timing"] = _timing_model(models["refit"], aligned, scales)
    for name, fm in models.items():
        fm.refit_predicted = cf.predicted["refit"]
        fm.predicted = cf.predicted[name]
        fm.std_scale = fm.predicted / np.maximum(table.base_mean, 1e-12)
    return models


def _timing_model(refit: FittedModel, aligned: _Aligned, scales) -> FittedModel:
    """The timing candidate: the refit at the timing lag, with the lag scan as its shape."""
    lo, hi = aligned.sync_band
    reference_lag_s = aligned.reference_lag_s
    fitted = FittedModel(
        name="timing",
        predicted=refit.predicted,
        std_scale=refit.std_scale,
        parameters=dict(refit.parameters),
        table=aligned.timing_table or aligned.base_table,
        scales=scales,
    )
    fitted.parameters.update(
        {
            "lag_s": round(aligned.timing_lag, 5),
            "sync_lag_s": round(aligned.sync_lag, 5),
            "reference_lag_s": round(float(reference_lag_s), 5),
            "lag_vs_simulator_s": round(float(aligned.timing_lag - reference_lag_s), 5),
            "tolerance_s": aligned.tolerance_s,
        }
    )
    fitted.shape = {
        "timing:lag_scan": {
            "x": [round(float(lag), 4) for lag in aligned.lags],
            "unit": "s",
            "train_log_residual": [round(float(c), 6) for c in aligned.curve],
            "in_sync_band_s": [round(lo, 4), round(hi, 4)],
            "fitted_lag_s": round(aligned.timing_lag, 5),
        }
    }
    return fitted


def _heldout_gaps(
    table: BlockTable, models: dict[str, FittedModel], cf: CrossFitted, windows: metric.Windows
) -> tuple[dict[str, np.ndarray], dict[str, float], dict[str, float]]:
    """Held-out window errors and gaps of the simulator as is and of every model, and the two
    floor estimates. Scatter is estimated around the best held-out predictor: a model error
    that varies from block to block (e.g. a wrong lag) would otherwise count as scatter."""
    observed, rows = table.magnitude, cf.rows
    errors = {"sim_as_is": heldout_errors(table.base_mean, observed, rows, windows)}
    for name in models:
        errors[name] = heldout_errors(cf.predicted[name], observed, rows, windows)
    gaps = {name: metric.gap_db(e) for name, e in errors.items()}
    best = min(models, key=lambda name: gaps[name])
    return errors, gaps, _floors(observed[rows], cf.predicted[best][rows], windows)


def _floors(observed: np.ndarray, predicted: np.ndarray, windows: metric.Windows) -> dict:
    """The two floor estimates (see `combined_floor`) of held-out rows around `predicted`."""
    return {
        "block_ratio": metric.floor_db(observed, predicted, windows),
        "window": metric.floor_window_db(observed, predicted, windows),
    }


def _candidates(
    observed: np.ndarray,
    cf: CrossFitted,
    effects,
    gaps: dict[str, float],
    floor: float,
    segments: np.ndarray,
    interleaved: dict,
    rng: np.random.Generator,
) -> tuple[list[dict], dict[str, np.ndarray]]:
    """Each candidate tested against the baseline on the held-out blocks, sorted by its
    deviance reduction; and (in that order) the per-block gains the bootstrap resamples."""
    excess_refit = max(gaps["refit"] ** 2 - floor**2, 1e-12)
    gains = {}
    candidates = []
    for effect in effects:
        res = _test(observed, cf, effect, segments, rng)
        gains[effect] = res["gain"]
        removed = float(
            np.clip((gaps["refit"] ** 2 - gaps[effect] ** 2) / excess_refit, -9.99, 1.0)
        )
        entry = {
            "effect": effect,
            "heldout_gap": round(gaps[effect], 4),
            "reduction": round(gaps["refit"] - gaps[effect], 4),
            "p_value": res["p_value"],
            "excess_removed": round(removed, 4),
            "deviance_reduction": round(res["deviance_reduction"], 6),
            "block_mse_reduction_db2": round(res["block_mse_reduction_db2"], 5),
        }
        if effect == "drift" and interleaved:
            _two_looks_at_drift(entry, interleaved)
        entry.setdefault("gap_reduction_decisive", entry["reduction"])
        candidates.append(entry)
    candidates.sort(key=lambda c: -c["deviance_reduction"])
    return candidates, {c["effect"]: gains[c["effect"]] for c in candidates}


def _two_looks_at_drift(entry: dict, interleaved: dict) -> None:
    """Drift is looked at twice (a trend over the folds; in-sample on interleaved chunks):
    Bonferroni over the two, the gain of the look that decides."""
    p = entry["p_value"]
    entry["folds"] = {
        k: entry[k] for k in ("p_value", "deviance_reduction", "block_mse_reduction_db2")
    }
    entry["interleaved"] = {k: v for k, v in interleaved.items() if k != "shape"}
    decided = "interleaved" if interleaved["p_value"] < p else "folds"
    entry["p_value"] = min(1.0, 2.0 * min(p, interleaved["p_value"]))
    entry["decided_by"] = decided
    if decided == "interleaved":
        entry["deviance_reduction"] = interleaved["deviance_reduction"]
        entry["block_mse_reduction_db2"] = interleaved["block_mse_reduction_db2"]
        entry["gap_reduction_decisive"] = round(
            interleaved["heldout_gap_baseline"] - interleaved["heldout_gap_drift"], 4
        )


def _verdict(
    candidates: list[dict],
    gains: dict[str, np.ndarray],
    alpha: float,
    segments: np.ndarray,
    rng: np.random.Generator,
    *,
    min_gain: float = MIN_DEVIANCE_GAIN,
    gap_key: str = "gap_reduction_decisive",
) -> tuple[str, float]:
    """The effect named (the first of `candidates`, sorted, that qualifies; `none`) and its
    confidence (`_bootstrap_confidence` of the per-block `gains`).

    Named only if significant (p < alpha / candidates), large enough (`min_gain`), and the
    held-out gap (`gap_key`: the metric the report shows) actually shrinks: a term that
    improves the power deviance but worsens the magnitude gap is explaining something else
    (measured: the coupling term on weak timing and acceleration bags of the simulator)."""
    level = alpha / max(len(candidates), 1)
    eligible = [
        c
        for c in candidates
        if c["p_value"] < level and c["deviance_reduction"] >= min_gain and c[gap_key] > 0.0
    ]
    verdict = eligible[0]["effect"] if eligible else "none"
    interleaved = any(c.get("decided_by") == "interleaved" for c in candidates)  # drift's
    return verdict, _bootstrap_confidence(
        gains, verdict, segments, rng, others_only=interleaved and verdict == "drift"
    )


def _split_info(t: np.ndarray, folds: int, train_fraction: float | None) -> dict:
    """How the recording was split, for the report."""
    if train_fraction is not None:
        info = {
            "method": f"by time: first {100 * train_fraction:.0f} % of the recording "
            "fits (train), the rest is held out",
            "train_s": float(train_fraction * (t[-1] - t[0])),
            "heldout_s": float((1 - train_fraction) * (t[-1] - t[0])),
        }
    else:
        info = {
            "method": f"blocked {folds}-fold cross-validation in time: the recording is cut "
            f"into {folds} contiguous folds, each predicted by models fitted on the other "
            "folds, so every block is held out once",
            "train_s": float((folds - 1) / folds * (t[-1] - t[0])),
            "heldout_s": float(t[-1] - t[0]),
            "folds": folds,
        }
    info["method"] += (
        "; contact blocks detected from the data (top-3-bin log-ratio outliers against the "
        "baseline) are excluded"
    )
    return info


def _bootstrap_confidence(
    gains: dict[str, np.ndarray],
    verdict: str,
    segments: np.ndarray,
    rng: np.random.Generator,
    *,
    others_only: bool = False,
) -> float:
    """Share of block-bootstrap resamples (held-out segments drawn with replacement) in which
    the verdict has the largest mean per-block gain of `gains` (deviance reduction over its
    null, at least MIN_DEVIANCE_GAIN); for `none`, the share in which no candidate reaches
    it, i.e. low beside a large gain that just misses significance. `others_only` (a drift
    verdict decided on the interleaved split, not comparable segment by segment): the share
    in which no other candidate reaches it.
    """
    names = list(gains)
    if not names:
        return 1.0
    n_seg = int(segments.max()) + 1
    seg_len = np.bincount(segments, minlength=n_seg)
    gain = np.stack([np.bincount(segments, weights=gains[n], minlength=n_seg) for n in names])
    mean_gain = np.empty((len(names), N_BOOTSTRAP))  # (K, N_BOOTSTRAP)
    batch = 100  # resamples per draw: the same stream as one draw, in bounded memory
    for start in range(0, N_BOOTSTRAP, batch):
        picks = rng.integers(0, n_seg, size=(min(batch, N_BOOTSTRAP - start), n_seg))
        n_picked = np.maximum(seg_len[picks].sum(axis=1), 1)
        mean_gain[:, start : start + len(picks)] = gain[:, picks].sum(axis=2) / n_picked
    if verdict == "none":
        return round(float(np.mean(np.max(mean_gain, axis=0) < MIN_DEVIANCE_GAIN)), 4)
    if others_only:
        others = [i for i, n in enumerate(names) if n != "drift"]
        if not others:
            return 1.0
        return round(float(np.mean(np.max(mean_gain[others], axis=0) < MIN_DEVIANCE_GAIN)), 4)
    best = np.argmax(mean_gain, axis=0)
    found = mean_gain[best, np.arange(N_BOOTSTRAP)] >= MIN_DEVIANCE_GAIN
    return round(float(np.mean(found & (best == names.index(verdict)))), 4)
