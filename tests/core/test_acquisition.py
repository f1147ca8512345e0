"""Tests of beta, h and J (bams_cli.core.acquisition)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtr
from scipy.stats import multivariate_normal

from bams_cli.core.acquisition import (
    acquisition_j,
    beta,
    beta_poly,
    eval_beta_poly,
    margin,
    point_variance,
    remaining_fraction,
)
from tests.core.dense_posterior import make_problem

S_GRID = [-6.0, -3.0, -1.0, -0.2, 0.0, 0.7, 2.0, 4.0, 7.5]
T_GRID = [0.0, 1e-8, 1e-3, 0.1, 0.3, 0.5, 0.9, 0.999, 1.0]


@pytest.mark.parametrize("s", S_GRID)
@pytest.mark.parametrize("t", T_GRID)
def test_beta_is_bivariate_normal_probability(s, t):
    # beta = Phi2(s, -s; rho = t - 1) (appendix A.2); scipy's integrator is good to ~1e-13
    # absolute, and degrades to ~1e-9 relative as rho -> -1.
    rho = t - 1.0
    ref = multivariate_normal.cdf(
        [s, -s],
        mean=[0.0, 0.0],
        cov=[[1.0, rho], [rho, 1.0]],
        allow_singular=True,
        abseps=1e-14,
        releps=1e-14,
    )
    assert beta(s, t) == pytest.approx(ref, rel=1e-8, abs=1e-12)


@pytest.mark.parametrize("s", S_GRID)
def test_beta_endpoints(s):
    p = ndtr(s)
    assert beta(s, 1.0) == pytest.approx(p * ndtr(-s), rel=1e-13, abs=1e-300)
    assert beta(s, 0.0) == 0.0
    # t is clipped into [0, 1]: rounding may push it just outside.
    assert beta(s, 1.0 + 1e-12) == beta(s, 1.0)
    assert beta(s, -1e-12) == 0.0


@pytest.mark.parametrize("s", S_GRID)
def test_beta_increasing_and_concave_in_t(s):
    t = np.linspace(0.0, 1.0, 4001)
    b = beta(s, t)
    db = np.diff(b)
    assert np.all(db >= -1e-13 * b.max())  # at s = 7.5 increments of 1e-29 meet rounding
    # concavity: successive increments shrink (up to rounding of b)
    assert np.all(np.diff(db) <= 1e-13 * b.max())
    # and the closed-form slope exp(-s^2 / (2 - t)) / (2 pi sqrt(t (2 - t))) matches
    # (away from t = 0, where beta ~ sqrt(t) makes the secant a poor slope estimate)
    tm = 0.5 * (t[1:] + t[:-1])
    slope = np.exp(-(s**2) / (2 - tm)) / (2 * np.pi * np.sqrt(tm * (2 - tm)))
    far = tm > 0.01
    np.testing.assert_allclose(
        (db / np.diff(t))[far], slope[far], rtol=1e-4, atol=1e-9 * slope.max()
    )


def test_point_variance_and_margin():
    mu = np.array([0.0, 1.0, -2.0, 5.0, 0.3])
    sigma2 = np.array([1.0, 4.0, 0.25, 0.0, 0.0])
    s = margin(mu, sigma2, gamma=0.3)
    np.testing.assert_allclose(s[:3], [0.3, -0.35, 4.6])
    assert s[3] == -np.inf and s[4] == np.inf  # known theta0: p = 0 above gamma, 1 at it
    h = point_variance(s)
    p = ndtr(s[:3])
    np.testing.assert_allclose(h[:3], p * ndtr(-s[:3]), rtol=1e-14)
    assert np.all(h[3:] == 0) and np.all(beta(s[3:], 0.5) == 0)


def test_j_empty_is_mean_point_variance():
    rng = np.random.default_rng(3)
    s = rng.normal(0, 2, size=500)
    h = ndtr(s) * (1 - ndtr(s))
    assert acquisition_j(s) == pytest.approx(h.mean(), rel=1e-13)
    assert acquisition_j(s, np.ones(500)) == pytest.approx(h.mean(), rel=1e-13)
    assert acquisition_j(s, np.zeros(500)) == 0.0


def test_remaining_fraction():
    t = remaining_fraction([1.0, 2.0, 0.0, 1.0], [0.25, 2.0000001, 0.0, -1e-17])
    np.testing.assert_allclose(t, [0.25, 1.0, 1.0, 0.0])


@pytest.mark.parametrize("s", [0.0, 0.4, -1.3, 2.5, -3.7, 5.0, 6.5, -8.0, 12.0, 30.0])
def test_beta_poly_error_bound_holds(s):
    # The screening polynomial's bound must hold everywhere on [0, 1], including t -> 0
    # where beta ~ sqrt(t), and be small relative to h for moderate s.
    m, err = beta_poly(np.array([s]))
    t = np.concatenate([np.linspace(0, 1, 200_001), np.geomspace(1e-16, 1e-2, 2001)])
    approx = eval_beta_poly(m, t[None, :])[0]
    exact = beta(s, t)
    assert np.max(np.abs(approx - exact)) <= err[0]
    if abs(s) <= 3:
        assert err[0] <= 1e-7 * point_variance(s)


def test_single_point_j_matches_monte_carlo():
    """J({c}) is E[ mean_x h_{n+1}(x) ] over the future outcome y_c (paper eq. (3)).

    Simulate the innovation y_c - E y_c ~ N(0, V(c)), update mu and sigma2 at every pool
    point, average h. Pass for any seed: tolerance is 5 Monte Carlo standard errors.
    """
    prob = make_problem(n_pool=80, n_obs=6, n_levels=2, d=2, seed=11)
    post, X, gamma = prob.posterior, prob.X, prob.gamma
    mu, sigma2 = post.predict_theta0(X)
    s = margin(mu, sigma2, gamma)
    rng = np.random.default_rng(12345)
    for c_idx, c_lev in [(5, 0), (17, 1), (40, 0)]:
        Xc = X[c_idx : c_idx + 1]
        lc = np.array([c_lev])
        C = post.cov_theta0_obs(X, Xc, lc)[:, 0]
        V = post.obs_var(Xc, lc)[0]
        sigma2_after = sigma2 - C**2 / V
        j_exact = acquisition_j(s, remaining_fraction(sigma2, sigma2_after))

        eps = rng.normal(0.0, np.sqrt(V), size=20_000)
        mu_after = mu[None, :] + (C / V)[None, :] * eps[:, None]
        s_after = (gamma - mu_after) / np.sqrt(np.maximum(sigma2_after, 1e-300))[None, :]
        j_samples = (ndtr(s_after) * ndtr(-s_after)).mean(axis=1)
        se = j_samples.std(ddof=1) / np.sqrt(len(j_samples))
        assert abs(j_samples.mean() - j_exact) <= 5 * se + 1e-12
        assert j_exact < acquisition_j(s)  # an observation never raises J in expectation
