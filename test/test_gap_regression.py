"""gap.regression: the per-bin ridge term and the power GLM recover known coefficients."""

from __future__ import annotations

import numpy as np

from egovib_ros.gap.regression import fit_power_term, fit_term


def test_the_ridge_term_recovers_known_coefficients_and_shrinks_noise():
    """z = a(f) + b(f) x0 + noise, with a second column x1 of pure noise: fit_term finds a
    and b per bin (broadband part + per-bin deviations) and leaves x1 near zero."""
    rng = np.random.default_rng(0)
    n, a, b = 3000, np.array([0.2, -0.1, 0.0, 0.3]), np.array([0.5, 0.6, 0.4, 0.7])
    x = rng.uniform(0.0, 1.0, (n, 2))
    z = a + x[:, :1] * b + rng.normal(0.0, 0.1, (n, len(a)))
    coef, ridge = fit_term(x, z)
    assert coef.shape == (3, len(a))
    np.testing.assert_allclose(coef[0], a, atol=0.05)
    np.testing.assert_allclose(coef[1], b, atol=0.03)
    assert np.abs(coef[2]).max() < 0.05
    assert set(ridge) == {"ridge_broadband", "ridge_per_bin"}


def test_the_power_glm_finds_the_log_gain_of_exponential_power():
    """|Y|^2 of Rayleigh scatter is exponential: ratio ~ Exp(mean exp(2 (a + b x))); the GLM
    returns (a, b) on the magnitude scale, where a log-least-squares fit would be off by
    Euler's gamma / 2."""
    rng = np.random.default_rng(1)
    n, a, b = 6000, np.array([0.1, -0.2]), np.array([0.8, 0.4])
    x = rng.uniform(0.0, 1.0, (n, 1))
    ratio = rng.exponential(np.exp(2.0 * (a + x * b)))
    coef, _ = fit_power_term(x, ratio, np.ones(n, bool))
    np.testing.assert_allclose(coef[0], a, atol=0.05)
    np.testing.assert_allclose(coef[1], b, atol=0.08)
    # no regressors: the log mean power ratio / 2
    only, _ = fit_power_term(np.zeros((n, 0)), ratio, np.ones(n, bool))
    np.testing.assert_allclose(only[0], 0.5 * np.log(ratio.mean(axis=0)), atol=0.01)
    # only the training rows count
    wild = ratio.copy()
    wild[n // 2 :] *= np.exp(10.0 * x[n // 2 :])
    first_half = np.arange(n) < n // 2
    np.testing.assert_array_equal(
        fit_power_term(x, wild, first_half)[0], fit_power_term(x, ratio, first_half)[0]
    )
