"""The velocity-only baseline, estimated from the real recording's training split itself.

The paper's table re-estimated on the real data, in the structure the paper assumes:
velocity only, joints adding (in *power*), stationary, in sync. Per in-band bin f:

    E|Y_b(f)|^2 = c(f) + sum_j sum_k a_jk(f) H_bjk

H_bjk = the block's window-weighted mean of the hat function of joint j's velocity at
cell k (its trajectory within the block, `features.motion_features`); rest is carried by
c(f), so a_j0 = 0. The cells a_jk(f) >= 0 are free: the baseline can put power at any
frequency and speed, whatever the simulator's spectra look like.

Estimated in two resolutions (the penalties count in equivalent blocks at the cell's own
power level, so they matter only where real data are thin): on the model's grid by
weighted least squares (weights 1/E^2; one reweighting) with a curvature penalty along the
cells (SMOOTH_BLOCKS) and a pull towards the simulator's single-joint power, scaled to this
recording per bin (PRIOR_BLOCKS); then on the fine cells (`features.KNOT_REFINE`: gear
lines sweep a DFT bin within a fraction of a grid step), pulled towards the coarse fit;
cells clipped at 0. Then a log-domain mean/rms correction per joint and coarse cell and a
per-bin log-gain in each joint's velocity (`velocity_stage`), both on that joint's share
of the bin's power; the mean magnitude re-levelled per bin on train.

It cannot represent anything that is not a sum over joints of a function of that joint's
velocity: interactions, position, acceleration, time, lag (the five effects).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import sparse

from egovib_ros.gap.features import BlockTable, hat_matrix, motion_features
from egovib_ros.gap.regression import MAX_LOG_GAIN, fit_power_term

#: Knots (signed speed fraction) of the baseline's velocity-only log-gain stage
#: (`fit_baseline`): a second, per-bin look at each joint's velocity on top of the
#: cell table, shared by every candidate, so that no candidate wins by absorbing
#: velocity-only misfit.
VELOCITY_KNOTS = (-1.0, -0.75, -0.5, -0.25, -0.1, 0.0, 0.1, 0.25, 0.5, 0.75, 1.0)

#: Prior weight of the simulator's power at a coarse cell, in equivalent blocks.
PRIOR_BLOCKS = 0.3
#: Prior weight of the coarse fit at a fine cell, in equivalent blocks.
COARSE_PRIOR_BLOCKS = 1.0
#: Curvature penalty along the velocity cells, in equivalent blocks.
SMOOTH_BLOCKS = 20.0
#: A cell's power scale is never taken below this share of the bin's mean power.
SCALE_FLOOR = 0.02
#: Ridge of the log-domain mean/rms stage.
RIDGE_RATIO = 10.0


@dataclass
class Baseline:
    """A fitted velocity-only baseline."""

    magnitude: np.ndarray  # (B, F) predicted expected magnitude
    power: np.ndarray  # (B, F) predicted mean power
    rest_power: np.ndarray  # (F,) c(f)
    cell_power: np.ndarray  # (J, K, F) a_jk(f) at the fine cells (0 at rest)
    info: dict = field(default_factory=dict)


def coarse_knots(table: BlockTable) -> tuple[np.ndarray, ...]:
    return tuple(np.asarray(g, float) for g in table.model.grid)


def coarse_hats(table: BlockTable, hats: np.ndarray) -> np.ndarray:
    """Hats (B, J, K_fine) of the table's fine knots re-expressed on the model grid
    (B, J, K_coarse)."""
    cknots = coarse_knots(table)
    # hat_matrix(fine, coarse) (K_fine, K_coarse): the hat functions on the coarse knots as
    # combinations of those on the fine knots; exact, as every coarse knot is a fine knot (a
    # piecewise-linear function on the coarse knots is piecewise linear on the fine ones).
    out = np.zeros((hats.shape[0], len(cknots), max(len(g) for g in cknots)))
    for j, (f, c) in enumerate(zip(table.knots, cknots)):
        out[:, j, : len(c)] = hats[:, j, : len(f)] @ hat_matrix(f, c)
    return out


def design(
    hats: np.ndarray, knots: tuple[np.ndarray, ...]
) -> tuple[sparse.csr_matrix, list[tuple[int, int]]]:
    """Sparse columns [1, H_bjk for every joint j and non-rest cell k];
    also the (j, k) of each H column."""
    # Built joint by joint as sparse: the dense (B, P) matrix would be the peak memory.
    cols, where = [sparse.csr_matrix(np.ones((hats.shape[0], 1)))], []
    for j, g in enumerate(knots):
        moving = [k for k in range(len(g)) if g[k] != 0.0]
        cols.append(sparse.csr_matrix(hats[:, j, : len(g)])[:, moving])
        where.extend((j, k) for k in moving)
    return sparse.hstack(cols, format="csr"), where


def simulator_cells(
    table: BlockTable, knots: tuple[np.ndarray, ...] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The simulator model's power at rest (F,) and with one joint at each cell (J, K, F),
    minus rest."""
    model = table.model
    knots = coarse_knots(table) if knots is None else knots
    ch = model.channel_indices(("combined",))
    n_joints = len(knots)
    zero, _ = model.estimate(np.zeros((1, n_joints)), ch, include_std=False)
    rest = zero[0, 0, table.freq_index] ** 2
    cells = np.zeros((n_joints, max(len(g) for g in knots), len(table.freq_index)))
    for j, g in enumerate(knots):
        v = np.zeros((len(g), n_joints))
        v[:, j] = g
        m, _ = model.estimate(v, ch, include_std=False)
        cells[j, : len(g)] = m[:, 0, table.freq_index] ** 2 - rest[None, :]
    return rest, cells


def _smoothness_rows(
    knots: tuple[np.ndarray, ...], where: list[tuple[int, int]], n_par: int
) -> tuple[np.ndarray, np.ndarray]:
    """Second differences along each joint's cells (the rest cell counts as a fixed 0), and the
    (up to three) columns each row involves, (R, 3) with -1 where the rest cell stands."""
    col = {jk: 1 + i for i, jk in enumerate(where)}
    rows, members = [], []
    for j, g in enumerate(knots):
        for k in range(1, len(g) - 1):
            r = np.zeros(n_par)
            m = []
            for kk, c in ((k - 1, 1.0), (k, -2.0), (k + 1, 1.0)):
                if (j, kk) in col:
                    r[col[(j, kk)]] = c
                m.append(col.get((j, kk), -1))
            rows.append(r)
            members.append(m)
    if not rows:
        return np.zeros((0, n_par)), np.zeros((0, 3), int)
    return np.array(rows), np.array(members)


def _row_products(xt: sparse.csr_matrix) -> sparse.csr_matrix:
    """(P*P, B): column b holds the outer product of row b of `xt` with itself, so that
    `_row_products(xt) @ w` is every weighting's Gram matrix sum_b w_b x_b x_b^T at once,
    flattened (a design row has a few non-zeros: a few dozen products)."""
    xt = sparse.csr_matrix(xt, copy=True)
    xt.sum_duplicates()
    n_par = xt.shape[1]
    counts = np.diff(xt.indptr)
    row = np.repeat(np.arange(xt.shape[0]), counts)  # of each stored entry
    each = counts[row]  # the entries in its row
    entry = np.repeat(np.arange(len(row)), each)  # each entry, once per entry of its row
    start = np.repeat(np.cumsum(each) - each, each)
    partner = xt.indptr[row[entry]] + np.arange(len(entry)) - start
    products = sparse.csr_matrix(
        (
            xt.data[entry] * xt.data[partner],
            (row[entry], xt.indices[entry] * n_par + xt.indices[partner]),
        ),
        shape=(xt.shape[0], n_par * n_par),
    )
    return products.T.tocsr()


def _solve(
    xt: sparse.csr_matrix,
    products: sparse.csr_matrix,
    yn: np.ndarray,
    weights: np.ndarray,
    prior: np.ndarray,
    prior_blocks: float,
    scale: np.ndarray,
    d2: np.ndarray,
    centres: np.ndarray,
) -> np.ndarray:
    """Penalised weighted least squares per bin, every bin at once (`products`:
    `_row_products(xt)`); all quantities in units of the bin's mean power."""
    n_par, n_bins = xt.shape[1], yn.shape[1]
    lhs = (products @ weights).T.reshape(n_bins, n_par, n_par)
    pen = prior_blocks / scale**2  # (F, P)
    lhs[:, np.arange(n_par), np.arange(n_par)] += pen
    rhs = (xt.T @ (weights * yn)).T + pen * prior
    if len(d2):
        # Curvature relative to the largest of the three cells involved: a sharp line
        # (one loud cell between quiet ones) is not crushed by its quiet neighbours' scale.
        local = np.max(np.where(centres >= 0, scale[:, np.maximum(centres, 0)], 0.0), axis=2)
        ds = d2[None] / np.maximum(local, SCALE_FLOOR)[:, :, None]  # (F, R, P)
        lhs += SMOOTH_BLOCKS * np.matmul(ds.transpose(0, 2, 1), ds)
    return np.linalg.solve(lhs, rhs[..., None])[..., 0]


def _prior_matrix(where, rest: np.ndarray, cells: np.ndarray) -> np.ndarray:
    prior = np.zeros((len(rest), 1 + len(where)))
    prior[:, 0] = rest
    for i, (j, k) in enumerate(where):
        prior[:, 1 + i] = cells[j, k]
    return prior


def fit_coarse(
    hats_c: np.ndarray,
    knots_c: tuple[np.ndarray, ...],
    power: np.ndarray,
    train: np.ndarray,
    prior_rest: np.ndarray,
    prior_cells: np.ndarray,
):
    """Coarse-cell power model: coefficients (F, P) in units of the bin's training mean
    power, etc."""
    x, where = design(hats_c, knots_c)
    xt = x[np.flatnonzero(train)]
    yn_level = np.maximum(power[train].mean(axis=0), 1e-300)
    yn = power[train] / yn_level
    prior = _prior_matrix(where, prior_rest, prior_cells)
    sim_mean = np.maximum(np.asarray(xt @ prior.T), 0.0).mean(axis=0)
    # simulator at this level
    prior = np.maximum(prior / np.maximum(sim_mean, 1e-300)[:, None], 0.0)
    d2, centres = _smoothness_rows(knots_c, where, x.shape[1])
    scale = np.ones_like(prior)
    weights = np.ones_like(yn)
    products = _row_products(xt)
    for _ in range(2):
        coef = _solve(xt, products, yn, weights, prior, PRIOR_BLOCKS, scale, d2, centres)
        coef[:, 1:] = np.maximum(coef[:, 1:], 0.0)
        coef[:, 0] = np.maximum(coef[:, 0], SCALE_FLOOR * 0.1)
        fitted = np.maximum(np.asarray(xt @ coef.T), SCALE_FLOOR)
        weights = 1.0 / fitted**2
        scale = np.maximum(np.maximum(coef, prior), SCALE_FLOOR)
    return coef, x, where, yn_level, weights


def fit_baseline(
    table: BlockTable, train: np.ndarray, *, prior: tuple[np.ndarray, np.ndarray] | None = None
) -> Baseline:
    """Velocity-only baseline fitted on the `train` rows, predicting every block (`prior`:
    `simulator_cells`, computed when None)."""
    hats = table.hats
    knots_c = coarse_knots(table)
    hats_c = coarse_hats(table, hats)
    prior_rest, prior_cells = simulator_cells(table) if prior is None else prior
    power = table.magnitude**2
    coef_c, x_c, where_c, level, weights = fit_coarse(
        hats_c, knots_c, power, train, prior_rest, prior_cells
    )
    # Fine cells: prior = the coarse fit interpolated to them.
    x, where = design(hats, table.knots)
    cells_c = np.zeros((len(knots_c), max(len(g) for g in knots_c), len(level)))
    for i, (j, k) in enumerate(where_c):
        cells_c[j, k] = coef_c[:, 1 + i]
    cells_f = np.zeros((len(table.knots), hats.shape[2], len(level)))
    for j, (f, c) in enumerate(zip(table.knots, knots_c)):
        cells_f[j, : len(f)] = hat_matrix(f, c) @ cells_c[j, : len(c)]  # see coarse_hats
    prior_f = _prior_matrix(where, coef_c[:, 0], cells_f)
    d2, centres = _smoothness_rows(table.knots, where, x.shape[1])
    scale = np.maximum(prior_f, SCALE_FLOOR)
    rows = np.flatnonzero(train)
    xt = x[rows]
    coef = _solve(
        xt,
        _row_products(xt),
        power[train] / level,
        weights,
        prior_f,
        COARSE_PRIOR_BLOCKS,
        scale,
        d2,
        centres,
    )
    coef[:, 1:] = np.maximum(coef[:, 1:], 0.0)
    coef[:, 0] = np.maximum(coef[:, 0], SCALE_FLOOR * 0.1)
    coef = coef * level[:, None]
    predicted = np.maximum(np.asarray(x @ coef.T), SCALE_FLOOR * 0.1 * level)  # (B, F)
    magnitude = np.sqrt(predicted)
    # Mean/rms ratio per joint and coarse cell, on that joint's share of the bin's power.
    per_joint = np.zeros((len(table.knots),) + predicted.shape)
    for j in range(len(table.knots)):  # sparse products: x is (B, P), dense it is the peak
        cols = [1 + i for i, (jj, _) in enumerate(where) if jj == j]
        if cols:
            per_joint[j] = np.asarray(x[:, cols] @ coef[:, cols].T)
    share = np.clip(per_joint / predicted[None], 0.0, 1.0)  # (J, B, F)
    xc = x_c.toarray()
    cols_j = [
        np.array([1 + i for i, (jj, _) in enumerate(where_c) if jj == j])
        for j in range(len(knots_c))
    ]
    z = np.log(np.maximum(table.magnitude, 1e-300)) - np.log(magnitude)
    ratio = np.zeros_like(z)
    for f in range(z.shape[1]):
        sep = np.concatenate(
            [np.ones((len(z), 1))]
            + [xc[:, c] * share[j, :, f, None] for j, c in enumerate(cols_j)],
            axis=1,
        )
        a = sep[rows]
        pen = np.full(sep.shape[1], RIDGE_RATIO)
        pen[0] = 0.0
        beta = np.linalg.solve(a.T @ a + np.diag(pen), a.T @ z[rows, f])
        beta[0] = 0.0  # the level is set below
        ratio[:, f] = sep @ beta
    magnitude = magnitude * np.exp(ratio)
    magnitude = magnitude * relevel(table.magnitude, magnitude, train)
    cells = np.zeros((len(table.knots), hats.shape[2], len(level)))
    for i, (j, k) in enumerate(where):
        cells[j, k] = coef[:, 1 + i]
    info = {
        "n_parameters": int(coef.size + len(level) * sum(len(c) for c in cols_j)),
        "structure": "power-additive over joints, free per velocity cell and bin, "
        "then a per-bin log-gain in each joint's signed velocity",
        "cells_per_joint": [len(g) for g in table.knots],
    }
    base = Baseline(
        magnitude=magnitude, power=predicted, rest_power=coef[:, 0], cell_power=cells, info=info
    )
    return velocity_stage(table, train, base, share)


def velocity_regressors(table: BlockTable) -> tuple[np.ndarray, list[str]]:
    """The baseline's velocity-only log-gain columns (hats of the signed speed fraction per
    joint, rest dropped: the intercept holds it)."""
    frac = table.velocity / table.vmax
    knots = np.asarray(VELOCITY_KNOTS)
    rest = int(np.flatnonzero(knots == 0.0)[0])
    cols, names = [], []
    for j, name in enumerate(table.joint_names):
        h = np.delete(hat_matrix(frac[:, j], knots), rest, axis=1)
        cols.append(h)
        names += [f"v={k:g}({name})" for k in np.delete(knots, rest)]
    return np.concatenate(cols, axis=1), names


def velocity_stage(
    table: BlockTable, train: np.ndarray, base: Baseline, share: np.ndarray
) -> Baseline:
    """The table's prediction times a per-bin log-gain in each joint's signed velocity, acting
    on that joint's `share` (J, B, F) of each bin's power (Gamma GLM of the power ratio, GCV
    ridge per bin: `regression.fit_power_term`): what the additive power cells miss of a
    velocity-only spectrum (direction, the shape of the magnitude distribution, a line
    between cells), fitted once and shared by every candidate.

    On the joint's share, not on the whole bin: a gain on the whole bin applies joint j's
    correction to joint k's power too whenever both move, a misfit that depends on both
    speeds, which the coupling candidate then took as an interaction (docs/gap.md, the
    third hand)."""
    x, names = velocity_regressors(table)
    owner = np.repeat(np.arange(len(table.joint_names)), x.shape[1] // len(table.joint_names))
    ratio = table.magnitude**2 / np.maximum(base.power, 1e-300)
    # The expected magnitude gets its own gain, fitted on the magnitude ratio (a log-link GLM
    # of its mean): the square root of the power's gain is not the mean magnitude's where the
    # magnitude distribution changes with speed (a steady line at a held speed: |Y| ~ its
    # rms; noise: 0.89 of it).
    ratio_m = table.magnitude / np.maximum(base.magnitude, 1e-300)
    log_power, log_magnitude = np.zeros_like(ratio), np.zeros_like(ratio)
    for f in range(ratio.shape[1]):
        xf = x * share[owner, :, f].T
        columns: dict = {}  # the bin's training columns, decomposed once for both fits
        for target, out in ((ratio, log_power), (ratio_m, log_magnitude)):
            # fit_power_term's coefficients are on the magnitude scale of its target: x2
            coef, _ = fit_power_term(xf, target[:, f : f + 1], train, columns)
            out[:, f] = 2.0 * (coef[0, 0] + np.clip(xf @ coef[1:, 0], -MAX_LOG_GAIN, MAX_LOG_GAIN))
    power = base.power * np.exp(log_power)
    power = power * relevel(table.magnitude**2, power, train)
    magnitude = base.magnitude * np.exp(log_magnitude)
    magnitude = magnitude * relevel(table.magnitude, magnitude, train)
    info = dict(base.info)
    info["n_parameters"] = int(info.get("n_parameters", 0) + 2 * (1 + len(names)) * ratio.shape[1])
    info["velocity_gain"] = {"regressors": len(names), "on": "each joint's share of the bin"}
    return replace(base, magnitude=magnitude, power=power, info=info)


def relevel(observed: np.ndarray, predicted: np.ndarray, train: np.ndarray) -> np.ndarray:
    """Per-bin factor so that the predicted *mean* (magnitude or power) matches the observed
    one on training blocks."""
    return observed[train].sum(axis=0) / np.maximum(predicted[train].sum(axis=0), 1e-300)


def lag_residual(table: BlockTable, rows: np.ndarray, lag_s: float, prior) -> float:
    """Mean squared centred log residual of the coarse baseline fitted on `rows`
    with joint states at `lag_s`."""
    knots_c = coarse_knots(table)
    hats, _, _ = motion_features(
        table.joints,
        table.t_first_s[rows],
        table.t_last_s[rows],
        lag_s,
        knots_c,
        table.model.window,
    )
    power = table.magnitude[rows] ** 2
    every = np.ones(len(rows), bool)
    coef, x, _, level, _ = fit_coarse(hats, knots_c, power, every, *prior)
    predicted = np.maximum(np.asarray(x @ coef.T), SCALE_FLOOR * 0.1) * level
    z = np.log(np.maximum(table.magnitude[rows], 1e-300)) - 0.5 * np.log(predicted)
    return float(np.mean((z - z.mean(axis=0)) ** 2))


def full_lag_deviance(table: BlockTable, train: np.ndarray, lag_s: float, prior) -> float:
    """Mean Gamma deviance of the observed power against the baseline the diagnosis fits
    (`fit_baseline`, the table's fine knots) on the `train` blocks with joint states at
    `lag_s`, its level per bin matched on them: the likelihood the candidates' tests use,
    at ~10x `lag_residual`'s cost (for the few lags around a scan's minimum). The squared
    log residual would weigh the near-zero powers that a Rayleigh magnitude often has most
    (it put a polled 19 ms lag at 26 ms, where the timing term lost on held-out data)."""
    at_lag = table.at_lag(lag_s)
    base = fit_baseline(at_lag, train, prior=prior)
    ratio = at_lag.magnitude[train] ** 2 / np.maximum(base.power[train], 1e-300)
    ratio = np.maximum(ratio / np.maximum(ratio.mean(axis=0), 1e-300), 1e-300)
    return float(np.mean(2.0 * (ratio - 1.0 - np.log(ratio))))
