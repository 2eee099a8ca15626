"""Refit and candidate effect models of the gap diagnosis.

Refit (the model's own structure: velocity only, joints adding, stationary, in sync),
fitted on the training split only (`fit_refit_additive`):

    E|Y_b(f)|^2 = c(f) S_0(f) + sum_j g_j(f, v_j) [S(f, v_j alone) - S_0(f)],   S = mu^2

(independent sources add in power; g_j piecewise linear over the velocity grid), then
a per-joint (separable) log-domain speed correction.  It absorbs any mis-calibrated
level per joint, speed and frequency, but no interaction, position, acceleration,
time or lag dependence.

Each candidate multiplies the refit by a log-linear term fitted per frequency bin by
ridge least squares on ln |Y| / m_refit of the training blocks, then re-levelled so the
predicted *mean* magnitude matches (the log of a Rayleigh-like magnitude is biased):

- position: cos/sin of the first two harmonics of continuous (revolute) joint angles,
  linear + quadratic terms of the others (e.g. gripper gap).
- coupling: |v_i||v_j|, its square, and its square relative to the modelled band power
  (an interaction that *adds* vibration) per joint pair, speeds as fractions of the
  grid maximum: exactly the interaction that the additive structure lacks.
- acceleration: log1p|a_j|, |a_j|, |a_j|^2 and |a_j|^2 relative to the modelled band
  power, accelerations scaled by their training 95th percentile.
- drift: elapsed time (minutes): a level trend extrapolated to held-out time.
- timing: the refit after re-matching joint states with a lag fitted on the training
  split (grid search, then refinement).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from egovib_ros.gap.features import BlockTable

EFFECTS = ("position", "coupling", "acceleration", "timing", "drift")
#: Ridge weight of the refit's velocity gains: cells with only a few blocks stay near
#: the calibrated model instead of chasing noise.
RIDGE_REFIT = 10.0
RIDGE_EFFECT = 1.0
#: Lag search (s): coarse grid, then +-1 coarse step at the fine step.
LAG_RANGE_S = 0.1
LAG_COARSE_S = 0.005
LAG_FINE_S = 0.001


@dataclass
class FittedModel:
    """A fitted variant of the noise model: predictions for every block of a table."""

    name: str
    predicted: np.ndarray  # (B, F) expected magnitude, all blocks
    std_scale: np.ndarray  # (B, F) multiplicative gain applied to the model std too
    parameters: dict = field(default_factory=dict)
    table: BlockTable | None = field(default=None, repr=False)  # the table it predicts (lag!)
    coef: np.ndarray | None = field(default=None, repr=False)  # (1 + R, F) log-gain coefficients
    refit_predicted: np.ndarray | None = field(
        default=None, repr=False
    )  # (B, F) before the effect term
    scales: "Scales | None" = field(default=None, repr=False)


@dataclass
class Scales:
    """Regressor scalings fixed on the training split (so held-out data are not peeked at)."""

    periodic: np.ndarray  # (J,) bool: joint angle wraps (continuous revolute)
    pos_centre: np.ndarray  # (J,)
    pos_half: np.ndarray  # (J,)
    acc_scale: np.ndarray  # (J,)
    t_ref_s: float
    power_ref: float = 1.0  # median modelled band power (train)


def fit_scales(table: BlockTable, train: np.ndarray) -> Scales:
    pos = table.position[train]
    span = pos.max(axis=0) - pos.min(axis=0)
    # An angle: a joint that turns through more than half a revolution in the data, or
    # is named as a roll/continuous joint (its harmonics then extrapolate boundedly).
    named = np.array(
        [any(k in n.lower() for k in ("roll", "continuous")) for n in table.joint_names]
    )
    periodic = (span > np.pi) | named
    lo, hi = np.percentile(pos, 1, axis=0), np.percentile(pos, 99, axis=0)
    acc = np.percentile(table.acceleration[train], 95, axis=0)
    return Scales(
        periodic=periodic,
        pos_centre=0.5 * (lo + hi),
        pos_half=np.maximum(0.5 * (hi - lo), 1e-9),
        acc_scale=np.maximum(acc, 1e-9),
        t_ref_s=float(table.t_mid_s[train].min()),
        power_ref=float(np.median(np.mean(table.base_mean[train] ** 2, axis=1))),
    )


def relative_power(table: BlockTable, scales: Scales) -> np.ndarray:
    """Reference power / modelled band power of each block.

    An effect that *adds* vibration of a given power raises the log magnitude by about
    log(1 + added / modelled): relatively more where the model is quiet.  Multiplying a
    regressor's square by this ratio gives the additive (power) form of the term.
    """
    power = np.mean(table.base_mean**2, axis=1)
    return scales.power_ref / np.maximum(power, 1e-6 * scales.power_ref)


def effect_regressors(
    effect: str, table: BlockTable, scales: Scales
) -> tuple[np.ndarray, list[str]]:
    """Regressor columns (B, R) of one candidate effect, with their names."""
    cols, names = [], []
    if effect == "position":
        for j, name in enumerate(table.joint_names):
            p = table.position[:, j]
            if scales.periodic[j]:
                for k in (1, 2):
                    cols += [np.cos(k * p), np.sin(k * p)]
                    names += [f"cos{k}({name})", f"sin{k}({name})"]
            else:
                z = np.clip((p - scales.pos_centre[j]) / scales.pos_half[j], -1.5, 1.5)
                cols += [z, z**2]
                names += [f"lin({name})", f"quad({name})"]
    elif effect == "coupling":
        speed = np.abs(table.velocity) / table.vmax
        rel = relative_power(table, scales)
        for i in range(speed.shape[1]):
            for j in range(i + 1, speed.shape[1]):
                prod = speed[:, i] * speed[:, j]
                cols += [prod, prod**2, np.minimum(prod**2 * rel, 25.0)]
                names += [f"|v_{i}||v_{j}|", f"(|v_{i}||v_{j}|)^2", f"(|v_{i}||v_{j}|)^2/P"]
    elif effect == "acceleration":
        # Reversals and clunks reach 10-20x the typical (95th percentile) acceleration:
        # keep that range (clip at 40x) and let log1p carry the bulk.
        acc = np.clip(table.acceleration / scales.acc_scale, 0.0, 40.0)
        rel = relative_power(table, scales)
        for j, name in enumerate(table.joint_names):
            u = acc[:, j] / 10.0
            cols += [np.log1p(acc[:, j]), u, u**2, np.minimum(u**2 * rel, 25.0)]
            names += [f"log1p|a|({name})", f"|a|({name})", f"|a|^2({name})", f"|a|^2/P({name})"]
    elif effect == "drift":
        cols = [(table.t_mid_s - scales.t_ref_s) / 60.0]
        names = ["t_min"]
    elif effect in ("refit", "timing"):
        pass
    else:
        raise ValueError(f"unknown effect {effect!r}")
    if not cols:
        return np.zeros((table.n_blocks, 0)), []
    return np.stack(cols, axis=1), names


def _ridge_fit(x: np.ndarray, z: np.ndarray, penalties: np.ndarray) -> np.ndarray:
    """Ridge least squares with per-column penalties (multiple right-hand sides)."""
    xtx = x.T @ x + np.diag(penalties)
    return np.linalg.solve(xtx, x.T @ z)


def fit_refit_additive(table: BlockTable, train: np.ndarray) -> tuple[np.ndarray, dict]:
    """The model's own structure refitted: velocity only, joints adding (Eq. 6), stationary,
    in sync.

    Independent sources add in power, so the refit works on mean-square spectra:

        E|Y_b(f)|^2 = c(f) S_0(f) + sum_j g_j(f, v_j) [S(f, v_j alone) - S_0(f)],   S = mu^2

    with g_j piecewise linear over the velocity grid (hat functions, 20 % steps) and c
    per bin, fitted by ridge-weighted least squares (weights 1/S^2: the scatter of a
    power grows with its mean) and shrunk towards the calibrated model (c = g = 1).
    A vibration level that is wrong by any factor per joint, speed and frequency is
    representable; an interaction between joints, or a dependence on anything but
    velocity, is not.  Returns (predicted magnitude sqrt(S) (B, F), summary).
    """
    hats = np.concatenate(
        [refit_hats(table.velocity[:, j], table.vmax[j]) for j in range(table.velocity.shape[1])],
        axis=1,
    )  # (B, J*K)
    joint_of = np.repeat(
        np.arange(table.velocity.shape[1]), hats.shape[1] // table.velocity.shape[1]
    )
    s0 = table.zero_mean**2
    diff = table.axis_mean**2 - s0[None, None, :]  # (B, J, F)
    base = s0[None, :] + diff.sum(axis=1)  # Eq. 6 in power, model as is
    base = np.maximum(base, 1e-6 * np.max(base))
    n_bins = base.shape[1]
    # Design per bin, all bins at once: (F, B, P) with P = 1 + J*K.
    x = np.concatenate(
        [
            np.broadcast_to(s0[:, None, None], (n_bins, table.n_blocks, 1)),
            hats[None, :, :] * diff.transpose(2, 0, 1)[:, :, joint_of],
        ],
        axis=2,
    )
    w = (1.0 / base).T  # (F, B)
    delta = _batched_ridge(
        x[:, train] * w[:, train, None],
        ((table.magnitude[train] ** 2 - base[train]).T * w[:, train]),
        RIDGE_REFIT,
        penalise_first=True,
    )
    predicted = np.maximum(base + np.einsum("fbp,fp->bf", x, delta), 0.01 * base)
    gains = 1.0 + delta  # (F, P)
    magnitude = np.sqrt(predicted)
    # Second stage, log domain, still separable per joint: the mean/rms ratio of a
    # magnitude depends on how tonal the bin is (hum and gear lines vs. broadband), which
    # changes with speed, so a per-joint speed correction of the magnitude completes the refit.
    # Each joint's correction acts only on its own share of the bin's power, so it
    # cannot carry one joint's speed into another joint's band (that is coupling).
    z = np.log(np.maximum(table.magnitude, 1e-12)) - np.log(np.maximum(magnitude, 1e-12))
    share = np.clip(diff / np.maximum(predicted, 1e-300)[:, None, :], 0.0, 1.0)  # (B, J, F)
    sep = np.concatenate(
        [
            np.ones((n_bins, table.n_blocks, 1)),
            hats[None, :, :] * share.transpose(2, 0, 1)[:, :, joint_of],
        ],
        axis=2,
    )
    beta = _batched_ridge(sep[:, train], z[train].T, RIDGE_REFIT, penalise_first=False)
    beta[:, 0] = 0.0  # the overall level is set later (re-levelling)
    magnitude = magnitude * np.exp(np.einsum("fbp,fp->bf", sep, beta))
    return magnitude, {
        "rest_gain_db": round(float(10 * np.log10(max(np.mean(gains[:, 0]), 1e-6))), 4),
        "n_parameters": int(gains.size + beta.size),
    }


def _batched_ridge(
    x: np.ndarray, y: np.ndarray, ridge: float, *, penalise_first: bool
) -> np.ndarray:
    """Per-bin ridge least squares: x (F, B, P), y (F, B) -> coefficients (F, P)."""
    n_par = x.shape[2]
    penalty = np.full(n_par, ridge)
    if not penalise_first:
        penalty[0] = 0.0
    xt = x.transpose(0, 2, 1)
    return np.linalg.solve(xt @ x + np.diag(penalty)[None], (xt @ y[:, :, None]))[:, :, 0]


def refit_hats(velocity: np.ndarray, vmax: float, n_knots: int = 11) -> np.ndarray:
    """Hat functions over signed speed fractions -1..1 (knot at rest dropped: c carries it)."""
    knots = np.linspace(-1.0, 1.0, n_knots)
    step = knots[1] - knots[0]
    frac = np.clip(velocity / vmax, -1.0, 1.0)
    hats = np.maximum(0.0, 1.0 - np.abs(frac[:, None] - knots[None, :]) / step)
    return np.delete(hats, n_knots // 2, axis=1)


def fit_variant(
    table: BlockTable,
    train: np.ndarray,
    effect: str,
    scales: Scales,
    refit: tuple[np.ndarray, dict] | None = None,
) -> FittedModel:
    """Refit, then one effect's regressors on top of it (log domain),
    fitted on the training rows."""
    refit_pred, refit_info = refit if refit is not None else fit_refit_additive(table, train)
    extra, names = effect_regressors(effect, table, scales)
    x = np.concatenate([np.ones((table.n_blocks, 1)), extra], axis=1)
    penalties = np.concatenate([[0.0], np.full(extra.shape[1], RIDGE_EFFECT)])
    tiny = 1e-12
    z = np.log(np.maximum(table.magnitude, tiny)) - np.log(np.maximum(refit_pred, tiny))
    beta = _ridge_fit(x[train], z[train], penalties)
    gain = np.exp(x @ beta)
    predicted = refit_pred * gain
    # Re-level: the mean magnitude (not the geometric mean) must match on training blocks.
    level = table.magnitude[train].sum(axis=0) / np.maximum(predicted[train].sum(axis=0), 1e-300)
    gain *= level
    beta[0] += np.log(level)
    params = {
        "n_parameters": int(refit_info["n_parameters"] + x.shape[1] * z.shape[1]),
        "refit_rest_gain_db": refit_info["rest_gain_db"],
    }
    if names:
        params["terms_db"] = {n: _db_summary(beta[1 + k]) for k, n in enumerate(names)}
        params["coefficients_per_bin"] = {
            n: [round(float(c), 5) for c in beta[1 + k]] for k, n in enumerate(names)
        }
    params.update(_effect_summary(effect, names, beta[1:], scales))
    predicted = refit_pred * gain
    std_scale = predicted / np.maximum(table.base_mean, 1e-12)
    return FittedModel(
        name=effect,
        predicted=predicted,
        std_scale=std_scale,
        parameters=params,
        table=table,
        coef=beta,
        refit_predicted=refit_pred,
        scales=scales,
    )


def apply_effect_term(
    table: BlockTable,
    train: np.ndarray,
    refit_predicted: np.ndarray,
    effect: str,
    coef: np.ndarray,
    scales: Scales,
) -> np.ndarray:
    """Predictions with a given (e.g. simulator-derived) effect term on top of a refit,
    re-levelled on train."""
    extra, _ = effect_regressors(effect, table, scales)
    gain = np.exp(extra @ coef[1:]) if extra.shape[1] else np.ones_like(refit_predicted)
    predicted = refit_predicted * gain
    level = table.magnitude[train].sum(axis=0) / np.maximum(predicted[train].sum(axis=0), 1e-300)
    return predicted * level


def _db_summary(log_gain: np.ndarray) -> float:
    """Broadband size of a per-bin log gain, in dB (mean over bins)."""
    return round(float(np.mean(log_gain) * 20.0 / np.log(10.0)), 4)


def _effect_summary(effect: str, names: list[str], coef: np.ndarray, scales: Scales) -> dict:
    """Physically readable effect parameters (broadband, averaged over bins)."""
    c = coef.mean(axis=1) if len(coef) else coef
    out: dict = {}
    if effect == "position":
        k = 0
        for name in names:
            if name.startswith("cos1("):
                joint = name[5:-1]
                amp = float(np.hypot(c[k], c[k + 1]))
                out[joint] = {
                    "relative_amplitude": round(amp, 4),
                    "phase_rad": round(float(np.arctan2(c[k + 1], c[k])), 4),
                }
            if name.startswith("lin("):
                joint = name[4:-1]
                # log gain per half of the joint's travel (position scaled to [-1, 1])
                out[joint] = {
                    "relative_slope": round(float(c[k]), 4),
                    "relative_curvature": round(float(c[k + 1]), 4),
                }
            k += 1
    elif effect == "coupling":
        out["log_gain_at_full_speeds"] = round(float(c[0] + c[1]), 4)
        out["relative_power_coefficient"] = round(float(c[2]), 5)
    elif effect == "acceleration":
        out["acc_scale"] = [round(float(a), 5) for a in scales.acc_scale]
        out["log1p_coefficient"] = [round(float(c[4 * j]), 4) for j in range(len(c) // 4)]
        out["relative_power_coefficient"] = [
            round(float(c[4 * j + 3]), 5) for j in range(len(c) // 4)
        ]
    elif effect == "drift":
        out["log_gain_per_minute"] = round(float(c[0]), 5)
    return out


def fit_lag(
    table: BlockTable, train: np.ndarray, scales: Scales, *, lag_range_s: float = LAG_RANGE_S
) -> tuple[float, np.ndarray, np.ndarray]:
    """Lag (s) minimising the training residual of the refit; also (lags, residual curve)."""

    # The scan only needs training blocks; every other one (overlapping neighbours carry
    # little extra information) halves its cost.
    sub = table.subset(np.flatnonzero(train)[::2])
    every = np.ones(sub.n_blocks, dtype=bool)

    def residual(lag: float) -> float:
        t = sub.at_lag(lag)
        predicted, _ = fit_refit_additive(t, every)
        z = np.log(np.maximum(t.magnitude, 1e-12)) - np.log(np.maximum(predicted, 1e-12))
        return float(np.mean((z - z.mean(axis=0)) ** 2))

    coarse = np.arange(-lag_range_s, lag_range_s + 1e-12, LAG_COARSE_S)
    curve = np.array([residual(lag) for lag in coarse])
    best = coarse[int(np.argmin(curve))]
    fine = np.arange(best - LAG_COARSE_S, best + LAG_COARSE_S + 1e-12, LAG_FINE_S)
    fine_curve = np.array([residual(lag) for lag in fine])
    lag = float(fine[int(np.argmin(fine_curve))])
    return lag, coarse, curve


def fit_timing(table: BlockTable, train: np.ndarray, scales: Scales) -> FittedModel:
    lag, lags, curve = fit_lag(table, train, scales)
    lagged = table.at_lag(lag)
    fitted = fit_variant(lagged, train, "refit", scales)
    fitted.name = "timing"
    fitted.parameters["lag_s"] = round(lag, 5)
    fitted.parameters["lag_scan"] = {
        "lag_s": [round(float(lag), 4) for lag in lags],
        "train_log_residual": [round(float(c), 6) for c in curve],
    }
    return fitted


def fit_all(
    table: BlockTable, train: np.ndarray, effects: tuple[str, ...] = EFFECTS
) -> dict[str, FittedModel]:
    """Refit plus every candidate effect, all fitted on `train` rows only."""
    scales = fit_scales(table, train)
    refit = fit_refit_additive(table, train)
    out = {"refit": fit_variant(table, train, "refit", scales, refit)}
    for effect in effects:
        if effect == "timing":
            out[effect] = fit_timing(table, train, scales) if table.joints is not None else None
        else:
            out[effect] = fit_variant(table, train, effect, scales, refit)
    return {k: v for k, v in out.items() if v is not None}
