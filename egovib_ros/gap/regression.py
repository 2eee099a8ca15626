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
    `yy`: its sum of squares; `n_eff`: the effective rows)."""
    best, best_lam = np.inf, RIDGE_GRID[-1] * n
    for lam in RIDGE_GRID * n:
        d = s**2 / (s**2 + lam)
        rss = yy - float(np.sum((2 * d - d * d)[:, None] * uy**2))
        dof = float(d.sum())
        if dof >= n_eff:
            continue
        score = rss / (1.0 - dof / n_eff) ** 2
        if score < best:
            best, best_lam = score, lam
    return best_lam


def _gcv_ridge(
    x: np.ndarray, y: np.ndarray, decomposition: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, float]:
    """Ridge coefficients (R, T) for standardised x (n, R) and centred y (n, T), weight by GCV."""
    n = len(x)
    s, v = decomposition
    uy = (v.T @ (x.T @ y)) / s[:, None]
    best_lam = _gcv_lambda(s, uy, float(np.sum(y * y)), n, EFFECTIVE_ROW_SHARE * n)
    d = s / (s**2 + best_lam)
    return v @ (d[:, None] * uy), float(best_lam / n)


def fit_term(
    x: np.ndarray, z: np.ndarray, train: np.ndarray, cache: dict | None = None
) -> tuple[np.ndarray, dict]:
    """Per-bin log-gain coefficients: (1 + R, F) = [intercept; beta],
    broadband + per-bin parts by GCV ridge. `cache`: keeps the decomposition of the
    training columns between calls with the same x and rows (the GLM's iterations)."""
    n_bins = z.shape[1]
    zt = z[train]
    z_mean = zt.mean(axis=0)
    if x.shape[1] == 0:
        return z_mean[None, :], {}
    cache = {} if cache is None else cache
    if "xs" not in cache:
        xt = x[train]
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
    beta = np.zeros((x.shape[1], n_bins))
    info = {}
    if live.any():
        zc = zt - z_mean
        broad = zc.mean(axis=1, keepdims=True)
        b, lam_b = _gcv_ridge(xs, broad, cache["dec"])
        dev, lam_d = _gcv_ridge(xs, zc - broad, cache["dec"])
        beta[live] = b + dev
        info = {"ridge_broadband": lam_b, "ridge_per_bin": lam_d}
    intercept = z_mean - mu @ beta
    return np.vstack([intercept[None, :], beta]), info


def fit_power_term(
    x: np.ndarray, ratio: np.ndarray, train: np.ndarray, cache: dict | None = None
) -> tuple[np.ndarray, dict]:
    """Log-link Gamma GLM of the power ratio |Y|^2 / baseline power:
    E[ratio] = exp(2 (a(f) + x beta(f))).

    Targets the *mean* power (what adds over independent sources and what the held-out
    deviance judges), by IRLS: for a log link and Gamma variance the working weights are
    constant, so each step is the same GCV ridge fit (`fit_term`) on the working response
    eta + (ratio - mu) / mu, from the least-squares fit of log ratio. Returns coefficients
    on the magnitude scale (half the power exponent), (1 + R, F); `cache`: as `fit_term`'s.
    """
    log_ratio = np.log(np.maximum(ratio, 1e-300))
    cache = {} if cache is None else cache
    coef, ridge = fit_term(x, log_ratio, train, cache)
    coef[0] += EULER_GAMMA  # E log of an exponential variable = log mean - gamma
    for _ in range(GLM_ITERATIONS):
        eta = coef[0][None, :] + (
            np.clip(x @ coef[1:], -2 * MAX_LOG_GAIN, 2 * MAX_LOG_GAIN) if x.shape[1] else 0.0
        )
        mu = np.exp(eta)
        work = eta + np.clip((ratio - mu) / mu, -1.0, WORKING_CLIP)
        coef, ridge = fit_term(x, work, train, cache)
    return coef / 2.0, ridge


class SharedDesign:
    """Columns z_s(b, f) = share[owner_s, b, f] * w[b, s] that differ from bin to bin, with
    coefficients shared by every bin: a joint's share of each bin's power (where its lines
    are) times a function of another joint's speed, so a gain acts on that joint's lines
    wherever they are. Never held as (B, F, S): built one bin at a time."""

    def __init__(self, share: np.ndarray, w: np.ndarray, owner: np.ndarray):
        self.share = share  # (J, B, F)
        self.w = w  # (B, S)
        self.owner = np.asarray(owner, dtype=np.intp)  # (S,)

    @property
    def n_columns(self) -> int:
        return self.w.shape[1]

    def bin_columns(self, f: int, rows=slice(None)) -> np.ndarray:
        """z(b, f, :) for the rows, (n, S)."""
        return self.share[:, rows, f][self.owner].T * self.w[rows]

    def predict(self, gamma: np.ndarray) -> np.ndarray:
        """sum_s gamma_s z_s(b, f), (B, F)."""
        out = np.zeros(self.share.shape[1:])
        for j in np.unique(self.owner):
            cols = self.owner == j
            out += self.share[j] * (self.w[:, cols] @ gamma[cols])[:, None]
        return out


def _shared_gram(design: SharedDesign, train: np.ndarray) -> dict:
    """Per-bin column means on the training rows and the centred Gram matrix summed over
    bins, decomposed once (the GLM's iterations reuse it)."""
    rows = np.flatnonzero(train)
    n_bins = design.share.shape[2]
    s = design.n_columns
    mu = np.zeros((n_bins, s))
    gram = np.zeros((s, s))
    for f in range(n_bins):
        zf = design.bin_columns(f, rows)
        mu[f] = zf.mean(axis=0)
        zc = zf - mu[f]
        gram += zc.T @ zc
    return {"rows": rows, "mu": mu, "dec": gram_decomposition(gram)}


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
        zy = np.zeros(design.n_columns)
        yy = 0.0
        for f in range(y.shape[1]):
            yc = yt[:, f] - y_mean[f]
            zy += (design.bin_columns(f, rows) - mu[f]).T @ yc
            yy += float(yc @ yc)
        uy = (v.T @ zy) / sv
        n_rows = len(rows) * y.shape[1]
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
