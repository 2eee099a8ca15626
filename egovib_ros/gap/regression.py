"""The per-bin log-gain fits of the gap diagnosis, shared by the baseline's velocity stage
(`baseline.velocity_stage`) and the candidate effect terms (`effects.fit_variant`):
coefficients per frequency bin = a broadband part shared by all bins plus per-bin
deviations, each ridge-shrunk with its own weight chosen by generalised cross-validation
on the training rows (`fit_term`), inside a log-link Gamma GLM of the power ratio
(`fit_power_term`)."""

from __future__ import annotations

import numpy as np

#: Ridge weights tried by the generalised cross-validation (multiples of the training rows).
RIDGE_GRID = np.array([1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0])
#: Overlapping blocks are not independent: GCV counts half the rows as effective.
EFFECTIVE_ROW_SHARE = 0.5
#: An effect term never moves a prediction by more than this (nepers, ~26 dB).
MAX_LOG_GAIN = 3.0
#: Iterations of the Gamma GLM (IRLS) of a candidate term; working residuals clipped here
#: (a block 20x above its mean power is an outlier, not information about a smooth term).
GLM_ITERATIONS = 4
WORKING_CLIP = 20.0
EULER_GAMMA = 0.5772156649


def gram_decomposition(gram: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Singular values s and right singular vectors V (R, r) of x (n, R) from its Gram matrix
    x^T x: the same numbers as a thin SVD without forming U (n x R), which cost most of a
    diagnosis's time. Directions below 1e-6 of the largest singular value are dropped (the
    ridge shrinks them to nothing anyway)."""
    evals, v = np.linalg.eigh(gram)
    order = np.argsort(evals)[::-1]
    s = np.sqrt(np.maximum(evals[order], 0.0))
    keep = s > (s[0] * 1e-6 if len(s) else 0.0)
    return s[keep], v[:, order][:, keep]


def _gcv_lambda(s: np.ndarray, uy: np.ndarray, yy: float, n: int, n_eff: float) -> float:
    """The ridge weight of RIDGE_GRID * n with the smallest generalised cross-validation
    score (`uy`: the target's coordinates along the singular directions over s, (r, T);
    `yy`: its sum of squares; `n_eff`: the effective rows). Every weight at once: the
    diagnosis calls this some ten thousand times."""
    lam = RIDGE_GRID * n
    d = s[None, :] ** 2 / (s[None, :] ** 2 + lam[:, None])  # (weights, r)
    rss = yy - (2 * d - d * d) @ np.sum(uy**2, axis=1)
    dof = d.sum(axis=1)
    fits = dof < n_eff
    if not fits.any():
        return float(lam[-1])
    score = np.full(len(lam), np.inf)
    score[fits] = rss[fits] / (1.0 - dof[fits] / n_eff) ** 2
    return float(lam[int(np.argmin(score))])


def _gcv_ridge(
    xty: np.ndarray, yy: float, n: int, decomposition: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, float]:
    """Ridge coefficients (R, T) for centred x (n, R) and y (n, T), weight by GCV, from
    x^T y (R, T) and the sum of squares of y."""
    s, v = decomposition
    uy = (v.T @ xty) / s[:, None]
    best_lam = _gcv_lambda(s, uy, yy, n, EFFECTIVE_ROW_SHARE * n)
    d = s / (s**2 + best_lam)
    return v @ (d[:, None] * uy), float(best_lam / n)


def fit_term(xt: np.ndarray, zt: np.ndarray, cache: dict | None = None) -> tuple[np.ndarray, dict]:
    """Per-bin log-gain coefficients of z on x, both on the training rows only: (1 + R, F) =
    [intercept; beta], broadband + per-bin parts by GCV ridge. `cache`: keeps the
    decomposition of the columns between calls with the same x (the GLM's iterations)."""
    n_bins = zt.shape[1]
    z_mean = zt.mean(axis=0)
    if xt.shape[1] == 0:
        return z_mean[None, :], {}
    cache = {} if cache is None else cache
    if "xs" not in cache:
        # Columns are only centred, never scaled to unit variance: every regressor is built
        # on a natural range of about [0, 1] (hats, kernels, harmonics), so a column that is
        # non-zero on few training blocks keeps a small norm and is shrunk hard, instead of
        # being blown up and extrapolated wildly on held-out blocks.
        mu = xt.mean(axis=0)
        live = np.ptp(xt, axis=0) > 1e-12
        xs = xt[:, live] - mu[live]
        dec = gram_decomposition(xs.T @ xs) if live.any() else None
        cache.update(mu=mu, live=live, xs=xs, dec=dec)
    mu, live, xs = cache["mu"], cache["live"], cache["xs"]
    beta = np.zeros((xt.shape[1], n_bins))
    info = {}
    if live.any():
        # the broadband target is each row's mean over bins, the per-bin one the rest: one
        # product x^T zc serves both
        zc = zt - z_mean
        broad = zc.mean(axis=1)
        xtz = xs.T @ zc
        xtb = xtz.mean(axis=1, keepdims=True)
        n, yy_broad = len(zc), float(broad @ broad)
        b, lam_b = _gcv_ridge(xtb, yy_broad, n, cache["dec"])
        yy_dev = float(np.sum(zc * zc)) - n_bins * yy_broad
        dev, lam_d = _gcv_ridge(xtz - xtb, yy_dev, n, cache["dec"])
        beta[live] = b + dev
        info = {"ridge_broadband": lam_b, "ridge_per_bin": lam_d}
    intercept = z_mean - mu @ beta
    return np.vstack([intercept[None, :], beta]), info


def fit_power_term(
    x: np.ndarray, ratio: np.ndarray, train: np.ndarray, cache: dict | None = None
) -> tuple[np.ndarray, dict]:
    """Log-link Gamma GLM of the power ratio |Y|^2 / baseline power on the training rows:
    E[ratio] = exp(2 (a(f) + x beta(f))).

    Targets the *mean* power (what adds over independent sources and what the held-out
    deviance judges), by IRLS: for a log link and Gamma variance the working weights are
    constant, so each step is the same GCV ridge fit (`fit_term`) on the working response
    eta + (ratio - mu) / mu, from the least-squares fit of log ratio. Returns coefficients
    on the magnitude scale (half the power exponent), (1 + R, F); `cache`: as `fit_term`'s
    (calls with the same x and rows).
    """
    xt, ratio = x[train], ratio[train]
    log_ratio = np.log(np.maximum(ratio, 1e-300))
    cache = {} if cache is None else cache
    coef, ridge = fit_term(xt, log_ratio, cache)
    coef[0] += EULER_GAMMA  # E log of an exponential variable = log mean - gamma
    for _ in range(GLM_ITERATIONS):
        eta = coef[0][None, :] + (
            np.clip(xt @ coef[1:], -2 * MAX_LOG_GAIN, 2 * MAX_LOG_GAIN) if xt.shape[1] else 0.0
        )
        mu = np.exp(eta)
        work = eta + np.clip((ratio - mu) / mu, -1.0, WORKING_CLIP)
        coef, ridge = fit_term(xt, work, cache)
    return coef / 2.0, ridge


class SharedDesign:
    """Columns z_s(b, f) = share[owner_s, b, f] * w[b, s] that differ from bin to bin, with
    coefficients shared by every bin: a joint's share of each bin's power (where its lines
    are) times a function of another joint's speed, so a gain acts on that joint's lines
    wherever they are. Never held as (B, F, S): its sums over bins are taken joint by joint
    (sum_f z_s z_t = w_s w_t sum_f share[owner_s] share[owner_t])."""

    def __init__(self, share: np.ndarray, w: np.ndarray, owner: np.ndarray):
        self.share = share  # (J, B, F)
        self.w = w  # (B, S)
        self.owner = np.asarray(owner, dtype=np.intp)  # (S,)

    @property
    def n_columns(self) -> int:
        return self.w.shape[1]

    def columns_of(self) -> list[tuple[int, np.ndarray]]:
        """(joint, its columns) for each joint that owns some."""
        return [(int(j), np.flatnonzero(self.owner == j)) for j in np.unique(self.owner)]

    def predict(self, gamma: np.ndarray) -> np.ndarray:
        """sum_s gamma_s z_s(b, f), (B, F)."""
        out = np.zeros(self.share.shape[1:])
        for j, cols in self.columns_of():
            out += self.share[j] * (self.w[:, cols] @ gamma[cols])[:, None]
        return out


def _shared_gram(design: SharedDesign, train: np.ndarray) -> dict:
    """Per-bin column means on the training rows (F, S) and the centred Gram matrix summed
    over bins, decomposed once (the GLM's iterations reuse it)."""
    rows = np.flatnonzero(train)
    share, w = design.share[:, rows, :], design.w[rows]  # (J, n, F), (n, S)
    owned = design.columns_of()
    mu = np.zeros((share.shape[2], design.n_columns))
    gram = np.zeros((design.n_columns, design.n_columns))
    for j, cols in owned:
        mu[:, cols] = share[j].T @ w[:, cols] / len(rows)
        for k, other in owned:
            overlap = np.einsum("bf,bf->b", share[j], share[k])  # sum over bins, per row
            gram[np.ix_(cols, other)] = w[:, cols].T @ (overlap[:, None] * w[:, other])
    gram -= len(rows) * mu.T @ mu  # centred: sum_f sum_b (z - mu)(z - mu)
    return {"rows": rows, "share": share, "mu": mu, "dec": gram_decomposition(gram)}


def fit_shared_term(
    design: SharedDesign, y: np.ndarray, train: np.ndarray, cache: dict | None = None
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Per-bin intercepts a(f) (F,) and coefficients gamma (S,) shared by every bin of
    y(b, f) ~ a(f) + sum_s gamma_s z_s(b, f) (`SharedDesign`), GCV ridge on the training
    rows (the effective rows counted as EFFECTIVE_ROW_SHARE of the *blocks*: the bins of
    one block are not independent observations of a shared coefficient)."""
    cache = {} if cache is None else cache
    if "dec" not in cache:
        cache.update(_shared_gram(design, train))
    rows, mu, (sv, v) = cache["rows"], cache["mu"], cache["dec"]
    yt = y[rows]
    y_mean = yt.mean(axis=0)
    gamma = np.zeros(design.n_columns)
    info: dict = {}
    if len(sv):
        yc = yt - y_mean
        w = design.w[rows]
        zy = -(mu.T @ yc.sum(axis=0))  # sum_f sum_b (z - mu) yc, joint by joint below
        for j, cols in design.columns_of():
            zy[cols] += w[:, cols].T @ np.einsum("bf,bf->b", cache["share"][j], yc)
        uy = (v.T @ zy) / sv
        n_rows = len(rows) * y.shape[1]
        yy = float(np.sum(yc * yc))
        best_lam = _gcv_lambda(sv, uy[:, None], yy, n_rows, EFFECTIVE_ROW_SHARE * len(rows))
        gamma = v @ (sv / (sv**2 + best_lam) * uy)
        info = {"ridge_shared": float(best_lam / n_rows)}
    return y_mean - mu @ gamma, gamma, info


def fit_shared_power_term(
    design: SharedDesign, ratio: np.ndarray, train: np.ndarray
) -> tuple[np.ndarray, np.ndarray, dict]:
    """`fit_power_term` for a `SharedDesign`: a log-link Gamma GLM of the power ratio by
    IRLS; returns (intercept (F,), gamma (S,), ridge) on the magnitude scale (half the
    power exponent)."""
    log_ratio = np.log(np.maximum(ratio, 1e-300))
    cache: dict = {}
    a, gamma, ridge = fit_shared_term(design, log_ratio, train, cache)
    a = a + EULER_GAMMA
    for _ in range(GLM_ITERATIONS):
        eta = a[None, :] + np.clip(design.predict(gamma), -2 * MAX_LOG_GAIN, 2 * MAX_LOG_GAIN)
        mu = np.exp(eta)
        work = eta + np.clip((ratio - mu) / mu, -1.0, WORKING_CLIP)
        a, gamma, ridge = fit_shared_term(design, work, train, cache)
    return a / 2.0, gamma / 2.0, ridge
