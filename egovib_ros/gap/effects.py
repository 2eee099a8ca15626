"""Refit and candidate effect models: multiplicative (log-linear) corrections to the noise model.

Every model predicts the expected magnitude of block b in bin f as

    m_b(f) = mu(f, v_b) * exp( sum_k beta_k(f) x_k(b) )

where mu is the calibrated model's mean spectrum at the block's velocity and x_k are
regressors; beta are fitted per frequency bin by ridge least squares on the log ratio
ln |Y_b(f)| / mu(f, v_b) of the *training* blocks, then the intercept is re-levelled so
that the predicted *mean* magnitude matches (the log of a Rayleigh-like magnitude is
biased low; slopes are not).

- refit (the model's own structure: velocity only, separable per joint, stationary,
  synchronous): an intercept per bin plus, per joint, piecewise-linear gains over the
  model's velocity grid (hat functions) -- fixes a mis-calibrated level or velocity
  dependence without being able to express any effect below.
- position: refit + cos/sin of the first two harmonics of continuous (revolute) joint
  angles, linear + quadratic terms of the others (e.g. gripper gap).
- coupling: refit + |v_i||v_j| (and its square) per joint pair, speeds as fractions of
  the grid maximum: exactly the interaction that separable (Eq. 6) structure lacks.
- acceleration: refit + |a_j| and |a_j|^2, accelerations scaled by their training 95th
  percentile.
- drift: refit + elapsed time (minutes): a level trend extrapolated to held-out time.
- timing: refit after re-matching joint states with a lag fitted on the training split
  (grid search, then refinement).
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
    predicted: np.ndarray                 # (B, F) expected magnitude, all blocks
    std_scale: np.ndarray                 # (B, F) multiplicative gain applied to the model std too
    parameters: dict = field(default_factory=dict)
    table: BlockTable | None = field(default=None, repr=False)   # the table it predicts (lag!)


def log_ratio(table: BlockTable) -> np.ndarray:
    tiny = 1e-12
    return np.log(np.maximum(table.magnitude, tiny)) - np.log(np.maximum(table.base_mean, tiny))


def refit_basis(velocity: np.ndarray, vmax: np.ndarray, n_knots: int = 11) -> np.ndarray:
    """Per-joint hat functions over signed speed fractions (knot at 0 dropped: the intercept)."""
    knots = np.linspace(-1.0, 1.0, n_knots)
    step = knots[1] - knots[0]
    cols = []
    for j in range(velocity.shape[1]):
        frac = np.clip(velocity[:, j] / vmax[j], -1.0, 1.0)
        hats = np.maximum(0.0, 1.0 - np.abs(frac[:, None] - knots[None, :]) / step)
        cols.append(np.delete(hats, n_knots // 2, axis=1))
    return np.concatenate(cols, axis=1)


@dataclass
class Scales:
    """Regressor scalings fixed on the training split (so held-out data are not peeked at)."""

    periodic: np.ndarray        # (J,) bool: joint angle wraps (continuous revolute)
    pos_centre: np.ndarray      # (J,)
    pos_half: np.ndarray        # (J,)
    acc_scale: np.ndarray       # (J,)
    t_ref_s: float


def fit_scales(table: BlockTable, train: np.ndarray) -> Scales:
    pos = table.position[train]
    span = pos.max(axis=0) - pos.min(axis=0)
    # An angle: a joint that turns through more than half a revolution in the data, or
    # is named as a roll/continuous joint (its harmonics then extrapolate boundedly).
    named = np.array([any(k in n.lower() for k in ("roll", "continuous")) for n in table.joint_names])
    periodic = (span > np.pi) | named
    lo, hi = np.percentile(pos, 1, axis=0), np.percentile(pos, 99, axis=0)
    acc = np.percentile(table.acceleration[train], 95, axis=0)
    return Scales(periodic=periodic, pos_centre=0.5 * (lo + hi), pos_half=np.maximum(0.5 * (hi - lo), 1e-9),
                  acc_scale=np.maximum(acc, 1e-9), t_ref_s=float(table.t_mid_s[train].min()))


def effect_regressors(effect: str, table: BlockTable, scales: Scales) -> tuple[np.ndarray, list[str]]:
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
                cols += [z, z ** 2]
                names += [f"lin({name})", f"quad({name})"]
    elif effect == "coupling":
        speed = np.abs(table.velocity) / table.vmax
        for i in range(speed.shape[1]):
            for j in range(i + 1, speed.shape[1]):
                prod = speed[:, i] * speed[:, j]
                cols += [prod, prod ** 2]
                names += [f"|v_{i}||v_{j}|", f"(|v_{i}||v_{j}|)^2"]
    elif effect == "acceleration":
        acc = np.clip(table.acceleration / scales.acc_scale, 0.0, 4.0)
        for j, name in enumerate(table.joint_names):
            cols += [acc[:, j], acc[:, j] ** 2]
            names += [f"|a|({name})", f"|a|^2({name})"]
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


def fit_variant(table: BlockTable, train: np.ndarray, effect: str, scales: Scales) -> FittedModel:
    """Fit refit (+ one effect's regressors) on the training rows; predict every block."""
    basis = refit_basis(table.velocity, table.vmax)
    extra, names = effect_regressors(effect, table, scales)
    x = np.concatenate([np.ones((table.n_blocks, 1)), basis, extra], axis=1)
    penalties = np.concatenate([[0.0], np.full(basis.shape[1], RIDGE_REFIT), np.full(extra.shape[1], RIDGE_EFFECT)])
    z = log_ratio(table)
    beta = _ridge_fit(x[train], z[train], penalties)
    gain = np.exp(x @ beta)
    predicted = table.base_mean * gain
    # Re-level: the mean magnitude (not the geometric mean) must match on training blocks.
    level = table.magnitude[train].sum(axis=0) / np.maximum(predicted[train].sum(axis=0), 1e-300)
    gain *= level
    beta[0] += np.log(level)
    params = {"n_parameters": int(x.shape[1] * z.shape[1]),
              "level_db": _db_summary(beta[0])}
    if names:
        params["terms"] = {n: _db_summary(beta[1 + basis.shape[1] + k]) for k, n in enumerate(names)}
        params["coefficients_per_bin"] = {n: [round(float(c), 5) for c in beta[1 + basis.shape[1] + k]]
                                          for k, n in enumerate(names)}
    params.update(_effect_summary(effect, names, beta[1 + basis.shape[1]:], scales))
    return FittedModel(name=effect, predicted=table.base_mean * gain, std_scale=gain,
                       parameters=params, table=table)


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
                out[joint] = {"relative_amplitude": round(amp, 4),
                              "phase_rad": round(float(np.arctan2(c[k + 1], c[k])), 4)}
            if name.startswith("lin("):
                joint = name[4:-1]
                # log gain per half of the joint's travel (position scaled to [-1, 1])
                out[joint] = {"relative_slope": round(float(c[k]), 4),
                              "relative_curvature": round(float(c[k + 1]), 4)}
            k += 1
    elif effect == "coupling":
        out["log_gain_at_full_speeds"] = round(float(c[0] + c[1]), 4)
    elif effect == "acceleration":
        out["acc_scale"] = [round(float(a), 5) for a in scales.acc_scale]
        out["log_gain_per_scale"] = [round(float(c[2 * j]), 4) for j in range(len(c) // 2)]
    elif effect == "drift":
        out["log_gain_per_minute"] = round(float(c[0]), 5)
    return out


def fit_lag(table: BlockTable, train: np.ndarray, scales: Scales, *,
            lag_range_s: float = LAG_RANGE_S) -> tuple[float, np.ndarray, np.ndarray]:
    """Lag (s) minimising the training residual of the refit; also (lags, residual curve)."""

    def residual(lag: float) -> float:
        t = table.at_lag(lag)
        fitted = fit_variant(t, train, "refit", scales)
        z = log_ratio(t)[train] - np.log(np.maximum(fitted.std_scale[train], 1e-300))
        return float(np.mean((z - z.mean(axis=0)) ** 2))

    coarse = np.arange(-lag_range_s, lag_range_s + 1e-12, LAG_COARSE_S)
    curve = np.array([residual(l) for l in coarse])
    best = coarse[int(np.argmin(curve))]
    fine = np.arange(best - LAG_COARSE_S, best + LAG_COARSE_S + 1e-12, LAG_FINE_S)
    fine_curve = np.array([residual(l) for l in fine])
    lag = float(fine[int(np.argmin(fine_curve))])
    return lag, coarse, curve


def fit_timing(table: BlockTable, train: np.ndarray, scales: Scales) -> FittedModel:
    lag, lags, curve = fit_lag(table, train, scales)
    lagged = table.at_lag(lag)
    fitted = fit_variant(lagged, train, "refit", scales)
    fitted.name = "timing"
    fitted.parameters["lag_s"] = round(lag, 5)
    fitted.parameters["lag_scan"] = {"lag_s": [round(float(l), 4) for l in lags],
                                     "train_log_residual": [round(float(c), 6) for c in curve]}
    return fitted


def fit_all(table: BlockTable, train: np.ndarray, effects: tuple[str, ...] = EFFECTS) -> dict[str, FittedModel]:
    """Refit plus every candidate effect, all fitted on `train` rows only."""
    scales = fit_scales(table, train)
    out = {"refit": fit_variant(table, train, "refit", scales)}
    for effect in effects:
        if effect == "timing":
            out[effect] = fit_timing(table, train, scales) if table.joints is not None else None
        else:
            out[effect] = fit_variant(table, train, effect, scales)
    return {k: v for k, v in out.items() if v is not None}
