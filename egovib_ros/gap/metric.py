"""The gap metric: windowed log-spectral distance between observed and predicted magnitudes.

    e[w, f] = 20 log10( sum_{b in w} |Y_b(f)| / sum_{b in w} m_b(f) )
    gap     = sqrt( mean_{w, f} e[w, f]^2 )                        [dB]

b runs over the no-contact blocks of a window w (W consecutive held-out blocks), f over
the in-band bins; m_b is the model's *expected* magnitude (no +sd term). Averaging within
a window before the log keeps the per-block Rayleigh-like scatter (several dB) from
swamping model errors, while a window is short enough that position, acceleration, time
and lag still vary between windows. gap^2 splits additively over bins, windows and
window labels (`contributions`). A model equal to the real process still scores the
scatter of the window means: the floor (`floor_db`, `floor_window_db`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DEFAULT_WINDOW_BLOCKS = 8
#: Largest contribution of one bin of one block to the Gamma deviance (y/mu ~ 11).
DEVIANCE_CAP = 8.0


@dataclass
class Windows:
    """Assignment of (held-out) blocks to consecutive windows."""

    index: np.ndarray  # (B,) window id of each block, -1 = unused tail
    n_windows: int

    def members(self) -> np.ndarray:
        return self.index >= 0


def make_windows(n_blocks: int, window_blocks: int = DEFAULT_WINDOW_BLOCKS) -> Windows:
    """Cut `n_blocks` consecutive blocks into windows of `window_blocks`
    (the remainder is dropped)."""
    n_windows = n_blocks // window_blocks
    index = np.full(n_blocks, -1, dtype=np.int64)
    used = n_windows * window_blocks
    index[:used] = np.arange(used) // window_blocks
    return Windows(index=index, n_windows=int(n_windows))


def window_sums(values: np.ndarray, windows: Windows) -> np.ndarray:
    """Sum (B, F) values per window -> (n_windows, F)."""
    keep = windows.members()
    out = np.zeros((windows.n_windows, values.shape[1]))
    np.add.at(out, windows.index[keep], values[keep])
    return out


def window_errors_db(observed: np.ndarray, predicted: np.ndarray, windows: Windows) -> np.ndarray:
    """e[w, f] in dB: log ratio of window sums of observed vs predicted magnitudes."""
    obs = window_sums(observed, windows)
    pred = window_sums(predicted, windows)
    tiny = np.finfo(float).tiny
    return 20.0 * np.log10(np.maximum(obs, tiny) / np.maximum(pred, tiny))


def gap_db(errors_db: np.ndarray) -> float:
    """RMS of window errors (the gap)."""
    return float(np.sqrt(np.mean(np.square(errors_db)))) if errors_db.size else float("nan")


def floor_db(
    observed: np.ndarray, predicted: np.ndarray, windows: Windows, *, far_lag: int = 4
) -> float:
    """Estimate of the gap a perfect model would score on these windows (scatter only).

    The scatter of a window mean comes from the block-to-block scatter of the ratio
    r_b = |Y_b| / m_b, which is correlated only between overlapping neighbours (lag 1).
    A model error varies slowly, adding about the same covariance at every short lag,
    so the scatter's own covariances are C_k - C_far (k = 0, 1; far = 4 blocks apart);
    then var(window mean) = (W c_0 + 2 (W - 1) c_1) / W^2 and e ~ 20/ln10 * sd.
    """
    keep = windows.members()
    if not keep.any():
        return float("nan")
    r = observed[keep] / np.maximum(predicted[keep], 1e-300)
    r = r / r.mean(axis=0) - 1.0
    n = len(r)
    if n <= far_lag + 1:
        return float("nan")

    def cov(k: int) -> np.ndarray:
        return np.mean(r[k:] * r[: n - k], axis=0) if k else np.mean(r * r, axis=0)

    c_far = cov(far_lag)
    c0, c1 = cov(0) - c_far, np.maximum(cov(1) - c_far, 0.0)
    w = np.bincount(windows.index[keep]).mean()
    var = (w * c0 + 2 * (w - 1) * c1) / w**2
    return float(20.0 / np.log(10.0) * np.sqrt(np.mean(np.maximum(var, 0.0))))


def floor_window_db(
    observed: np.ndarray, predicted: np.ndarray, windows: Windows, *, far_lag: int = 2
) -> float:
    """The floor estimated in the metric's own (log, window) domain.

    e[w, f] = scatter + model error; the scatter of windows `far_lag` apart is independent
    (no shared blocks), a slowly varying model error is shared: var(e) - cov(e_w, e_w+far)
    estimates the scatter's variance.  Unlike `floor_db` it needs no linearisation of the
    log, so a heavy-tailed ratio |Y|/m (a few loud blocks) does not inflate it.
    """
    e = window_errors_db(observed, predicted, windows)
    if len(e) <= far_lag + 1:
        return float("nan")
    e = e - e.mean(axis=0)
    var = np.mean(e * e, axis=0)
    cov = np.mean(e[far_lag:] * e[:-far_lag], axis=0)
    return float(np.sqrt(np.mean(np.maximum(var - np.maximum(cov, 0.0), 0.0))))


def contributions(
    errors_db: np.ndarray, labels: np.ndarray, n_labels: int
) -> tuple[np.ndarray, np.ndarray]:
    """Split gap^2 over window labels:
    (share of gap^2 [dB^2] per label and bin, window count per label).

    share[k, f] = sum_{w: label w = k} e[w,f]^2 / (n_windows * n_bins); summing share over
    k and f gives gap^2 exactly.  Windows with label < 0 are not counted in any label.
    """
    n_windows, n_bins = errors_db.shape
    share = np.zeros((n_labels, n_bins))
    counts = np.zeros(n_labels, dtype=np.int64)
    ok = labels >= 0
    np.add.at(share, labels[ok], np.square(errors_db[ok]) / (n_windows * n_bins))
    np.add.at(counts, labels[ok], 1)
    return share, counts


def grouped_bias_db(
    observed: np.ndarray, predicted: np.ndarray, labels: np.ndarray, n_labels: int
) -> tuple[np.ndarray, np.ndarray]:
    """Band-summed observed/predicted ratio in dB per label group of blocks
    (for covariate profiles).

    Returns (bias_db (n_labels,), block counts); groups without blocks give NaN.
    """
    ok = labels >= 0
    obs = np.bincount(labels[ok], weights=observed[ok].sum(axis=1), minlength=n_labels)
    pred = np.bincount(labels[ok], weights=predicted[ok].sum(axis=1), minlength=n_labels)
    counts = np.bincount(labels[ok], minlength=n_labels)
    with np.errstate(divide="ignore", invalid="ignore"):
        bias = np.where(counts > 0, 20.0 * np.log10(obs / pred), np.nan)
    return bias, counts


def block_log_errors(observed: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """Per-block, per-bin natural-log residuals ln |Y| - ln m
    (squared and summed, the test's loss)."""
    tiny = 1e-300
    return np.log(np.maximum(observed, tiny)) - np.log(np.maximum(predicted, tiny))


def block_deviance(observed_power: np.ndarray, predicted_power: np.ndarray) -> np.ndarray:
    """Per-block Gamma deviance y/mu - ln(y/mu) - 1, averaged over bins
    (y = |Y|^2, mu = expected power).

    Minimised in expectation by mu = E[y], whatever the distribution of y: the right loss
    for a model of expected *power* (independent sources add in power, not in mean
    magnitude, so a mean-magnitude or log loss would reward fitting how the shape of the
    magnitude distribution changes with the mixture, e.g. two tones in one bin).
    """
    ratio = np.maximum(observed_power, 1e-300) / np.maximum(predicted_power, 1e-300)
    # Capped per bin: one block whose power a model of thin cells under-predicts 100-fold
    # would otherwise outweigh thousands (the deviance grows linearly in y/mu).
    return np.mean(np.minimum(ratio - np.log(ratio) - 1.0, DEVIANCE_CAP), axis=1)


def segment_signflip_pvalue(
    gain: np.ndarray, segments: np.ndarray, rng: np.random.Generator
) -> float:
    """One-sided paired sign-flip test of per-block loss reductions (base minus candidate)
    grouped in contiguous time segments.

    Under H0 (the candidate predicts held-out blocks no better than the base) each
    segment's summed loss difference is symmetric about zero.
    """
    d_s = np.bincount(segments, weights=gain)
    d_s = d_s[np.bincount(segments) > 0]
    n_seg = len(d_s)
    observed = d_s.mean()
    if n_seg <= 16:
        signs = 1 - 2 * ((np.arange(2**n_seg)[:, None] >> np.arange(n_seg)) & 1)
        return float(np.mean((signs * d_s).mean(axis=1) >= observed - 1e-12))
    return _signflip_tail(d_s, observed, rng)


#: Sign patterns drawn (more than 16 segments), PERMUTATION_BATCH at a time: the same random
#: stream as one draw of all of them (int64 draws are not buffered), in bounded memory.
N_PERMUTATIONS = 20000
PERMUTATION_BATCH = 1000


def _signflip_tail(d_s: np.ndarray, observed: float, rng: np.random.Generator) -> float:
    """(1 + #{null mean >= observed}) / (1 + N_PERMUTATIONS), signs drawn in batches."""
    at_least = 0
    for start in range(0, N_PERMUTATIONS, PERMUTATION_BATCH):
        signs = rng.choice(
            np.array([-1.0, 1.0]), size=(min(PERMUTATION_BATCH, N_PERMUTATIONS - start), len(d_s))
        )
        at_least += int(np.sum((signs * d_s).mean(axis=1) >= observed - 1e-12))
    return float((1 + at_least) / (1 + N_PERMUTATIONS))
