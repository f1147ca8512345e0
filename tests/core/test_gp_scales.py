"""A cheap level on its own scale: y_l = rho_l (theta0 + delta_l + eps_l) + b_l.

The model is checked against the Kennedy-O'Hagan covariance written out densely and
scipy's multivariate normal, its gradient against central differences, and its fit
against data whose cheap level is a known multiple of level 0.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from bams_cli.core.gp import MFGP, Hyperparameters, fit_mfgp
from bams_cli.core.gp._numerics import standardise
from bams_cli.core.gp.checks import check_model, fitted_discrepancy_sd
from bams_cli.core.gp.objective import _MAPObjective
from bams_cli.core.gp.priors import (
    PriorSpec,
    _Priors,
    pair_evidence,
    pair_scales,
    shows_scale,
    with_pair_modes,
)
from tests.core.test_gp import assert_gradient_matches, mf_data, random_hp, ref_matern52


def koh_cov(A, la, B, lb, hp):
    """Cov(y_a(x), y_b(x')) without noise: rho_a rho_b k0 + [a == b >= 1] rho_a^2 k_a."""
    rho = np.r_[1.0, hp.scales]
    K = rho[la][:, None] * rho[lb][None, :] * ref_matern52(A, B, hp.lengthscales0, hp.outputscale0)
    for i in range(len(A)):
        for j in range(len(B)):
            if la[i] == lb[j] and la[i] >= 1:
                lv = la[i]
                K[i, j] += (
                    rho[lv] ** 2
                    * ref_matern52(
                        A[i : i + 1], B[j : j + 1], hp.lengthscales[lv - 1], hp.outputscales[lv - 1]
                    )[0, 0]
                )
    return K


@pytest.mark.parametrize("n_levels", [2, 3])
def test_scaled_levels_posterior_and_likelihood_equal_the_dense_koh_model(n_levels):
    rng = np.random.default_rng(40 + n_levels)
    d = 2
    X, levels, y = mf_data(rng, d, n_levels)
    hp = dataclasses.replace(
        random_hp(rng, d, n_levels), scales=rng.uniform(0.4, 3.0, n_levels - 1)
    )
    rho = np.r_[1.0, hp.scales]
    y = y * rho[levels]  # the cheap levels on their own scales
    model = fit_mfgp(X, levels, y, n_levels, rng=rng, fixed=hp)

    K = koh_cov(X, levels, X, levels, hp) + np.diag(rho[levels] ** 2 * hp.noise[levels])
    mean = rho[levels] * hp.mean + np.r_[0.0, hp.offsets][levels]
    Xp = rng.normal(size=(6, d))
    k0_p = ref_matern52(Xp, X, hp.lengthscales0, hp.outputscale0) * rho[levels][None, :]
    mu_ref = hp.mean + k0_p @ np.linalg.solve(K, y - mean)
    cov_ref = ref_matern52(Xp, Xp, hp.lengthscales0, hp.outputscale0) - k0_p @ np.linalg.solve(
        K, k0_p.T
    )
    mu, var = model.predict_theta0(Xp)
    np.testing.assert_allclose(mu, mu_ref, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(var, np.diag(cov_ref), rtol=1e-8, atol=1e-10)
    assert model.log_marginal_likelihood == pytest.approx(
        multivariate_normal(mean, K).logpdf(y), rel=1e-10
    )
    # A candidate observation's covariance is in level 0's units, (y_l - b_l) / rho_l:
    # the information it carries about theta0 is the same at any scale.
    Xc, lc = rng.normal(size=(4, d)), np.arange(4) % n_levels
    kc = koh_cov(X, levels, Xc, lc, hp)
    cov_cc = koh_cov(Xc, lc, Xc, lc, hp) + np.diag(rho[lc] ** 2 * hp.noise[lc])
    cov_cc -= kc.T @ np.linalg.solve(K, kc)
    np.testing.assert_allclose(
        model.cov_obs_obs(Xc, lc, Xc, lc),
        cov_cc / np.outer(rho[lc], rho[lc]),
        rtol=1e-8,
        atol=1e-10,
    )


@pytest.mark.parametrize("n_levels", [2, 3])
def test_gradient_in_the_scales_matches_central_differences(n_levels):
    rng = np.random.default_rng(7 + n_levels)
    d = 3
    X, levels, y = mf_data(rng, d, n_levels, n=30)
    ybar, ystd = standardise(y)
    priors = _Priors.for_data(X, n_levels)
    objective = _MAPObjective(X, levels, (y - ybar) / ystd, n_levels, priors)
    for _ in range(3):
        theta = priors.sample_start(rng)
        theta[-(n_levels - 1) :] = rng.normal(0.0, 0.6, n_levels - 1)
        assert_gradient_matches(objective, theta)


def test_gradient_with_the_pairs_prior_matches_central_differences():
    """With pairs, the discrepancy's prior mode moves with rho; its derivative is in the
    scale's gradient."""
    X, levels, y, _ = scaled_study(5, n_pairs=10)
    ybar, ystd = standardise(y)
    ys = (y - ybar) / ystd
    spec = with_pair_modes(None, X, levels, ys, 2)
    assert spec.pair_moments[0] is not None
    priors = _Priors.for_data(X, 2, spec)
    objective = _MAPObjective(X, levels, ys, 2, priors)
    rng = np.random.default_rng(1)
    for log_rho in (-0.3, 0.4, 0.9):
        theta = priors.sample_start(rng)
        theta[-1] = log_rho
        assert_gradient_matches(objective, theta)


def test_the_pairs_prior_mode_is_their_variance_at_the_scale():
    """At rho the mode is var(y1 - rho y0) / rho^2 over the pairs (level 0's units), the
    fixed floor where that is smaller."""
    X, levels, y, _ = scaled_study(6, n_pairs=9)
    spec = with_pair_modes(None, X, levels, y, 2)
    priors = _Priors.for_data(X, 2, spec)
    y0, y1 = y[:9], y[20:29]
    theta = priors.mode.copy()
    for rho in (0.7, 1.0, 2.5):
        theta[-1] = math.log(rho)
        # the density's log at theta is largest in the discrepancy where it sits at the mode
        v = max(np.var(y1 - rho * y0, ddof=1) / rho**2, 0.01)
        grid = np.log(v) + np.linspace(-0.5, 0.5, 101)
        values = []
        for g in grid:
            theta[1] = g
            values.append(priors.log_prior(theta)[0])
        assert grid[int(np.argmax(values))] == pytest.approx(np.log(v), abs=0.011)
    assert spec.discrepancy_modes[0] == pytest.approx(max(np.var(y1 - y0, ddof=1), 0.01))


def scaled_study(seed, rho=2.5, n_pairs=12, n0=20, n1=120, d=3, noise=0.02):
    """Level 1 = rho x level 0 + 1 + a small discrepancy + noise of sd ``noise``;
    ``n_pairs`` segments at both."""
    rng = np.random.default_rng(seed)
    f0 = lambda Z: np.sin(2.0 * Z[:, 0]) + Z[:, 1] ** 2 - 0.5 * Z[:, 2]  # noqa: E731
    X0 = rng.uniform(-1, 1, (n0, d))
    X1 = np.vstack([X0[:n_pairs], rng.uniform(-1, 1, (n1 - n_pairs, d))])
    y0 = f0(X0) + 0.01 * rng.normal(size=n0)
    y1 = rho * f0(X1) + 1.0 + 0.3 * np.cos(3 * X1[:, 2]) + noise * rng.normal(size=n1)
    X = np.vstack([X0, X1])
    levels = np.r_[np.zeros(n0, int), np.ones(n1, int)]
    return X, levels, np.r_[y0, y1], f0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_cheap_level_on_another_scale_is_fitted_with_its_scale_and_trusted(seed):
    X, levels, y, f0 = scaled_study(seed)
    model = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(seed), restarts=4)
    hp = model.hyperparameters
    assert hp.scales[0] == pytest.approx(2.5, rel=0.1)
    # The discrepancy left is small against theta0's variation: the level is trusted.
    assert math.sqrt(hp.outputscales[0] / hp.outputscale0) < 0.15
    # What the model says of y1 - rho y0 is what the pool shows at that rho.
    Z = np.random.default_rng(9).uniform(-1, 1, (5000, 3))
    rho = hp.scales[0]
    truth = float(np.std((2.5 - rho) * f0(Z) + 0.3 * np.cos(3 * Z[:, 2])))
    assert 0.5 < fitted_discrepancy_sd(hp) / truth < 2.0
    # Its pairs, scaled, are what the model allows: no warning.
    seg = np.unique(X, axis=0, return_inverse=True)[1].ravel()
    checks = check_model(model, seg)
    assert not [w for w in checks.warnings if "differs from level 0" in w]
    # Level 0 is predicted better than by level 0's runs alone.
    alone = fit_mfgp(X[levels == 0], levels[levels == 0], y[levels == 0], 1,
                     rng=np.random.default_rng(seed), restarts=4)  # fmt: skip
    err = lambda m: float(np.sqrt(np.mean((m.predict_theta0(Z)[0] - f0(Z)) ** 2)))  # noqa: E731
    assert err(model) < 0.5 * err(alone)


def test_held_at_one_the_same_level_looks_weak_and_predicts_worse():
    """The additive model (the scale held at 1 by a prior of no width) reads 1.5 theta0 as
    discrepancy: the level looks weak, and level 0 is predicted worse than with the scale."""
    X, levels, y, f0 = scaled_study(0)
    Z = np.random.default_rng(9).uniform(-1, 1, (5000, 3))
    err = lambda m: float(np.sqrt(np.mean((m.predict_theta0(Z)[0] - f0(Z)) ** 2)))  # noqa: E731
    scaled = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0), restarts=4)
    additive = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0), restarts=4,
                        priors=PriorSpec(level_scale=(1.0, 1e-4), scale_from_pairs=False))  # fmt: skip
    assert additive.hyperparameters.scales[0] == pytest.approx(1.0, abs=1e-3)
    ratio = lambda hp: math.sqrt(hp.outputscales[0] / hp.outputscale0)  # noqa: E731
    assert ratio(additive.hyperparameters) > 0.5 > 0.15 > ratio(scaled.hyperparameters)
    assert err(scaled) < 0.5 * err(additive)


@pytest.mark.parametrize(
    "what, kw",
    [
        ("4 pairs", {"n_pairs": 4}),
        ("a slope of 1.3 with a discrepancy", {"rho": 1.3}),
        ("pairs correlated at 0.5", {"rho": 2.5, "noise": 1.5}),
    ],
)
def test_scale_is_held_at_one_where_the_pairs_show_none(what, kw):
    """Too few pairs, a slope within 1.5 of 1, or pairs that do not track each other:
    the additive model, exactly (rho 1, not merely near it)."""
    X, levels, y, _ = scaled_study(0, **kw)
    assert math.isnan(pair_scales(X, levels, y, 2)[0]), what
    hp = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0), restarts=3).hyperparameters
    assert hp.scales[0] == 1.0, what


def test_pair_scales_are_the_least_squares_slope_where_pairs_show_a_scale():
    X, levels, y, _ = scaled_study(3, n_pairs=8)
    y0, y1 = y[:8], y[20:28]  # the paired segments, one run each
    ref = np.polyfit(y0, y1, 1)[0]
    assert ref == pytest.approx(2.5, rel=0.1)
    assert pair_scales(X, levels, y, 2)[0] == pytest.approx(ref, rel=1e-10)
    assert shows_scale(5, 2.0, 0.9, 4.0) and shows_scale(5, 0.4, 0.95, 6.0)
    assert not shows_scale(4, 2.5, 0.99, 5.0) and not shows_scale(5, 2.5, 0.99, 3.99)
    assert not shows_scale(5, 2.5, 0.89, 5.0) and not shows_scale(5, -2.5, 0.99, 5.0)
    # Pairs about a line of slope 2: at correlation 0.9 it cuts the sd of the differences
    # by 1.44 (a weak level's few pairs); at 0.99 by 3.65; 4 needs 0.992. Closed form with
    # s = sd(y_l) / sd(y_0) = 2 / corr: sqrt((s^2 - 2 corr s + 1) / (s^2 (1 - corr^2))).
    rng = np.random.default_rng(0)
    for corr, gain in ((0.9, 1.435), (0.99, 3.65)):
        z = rng.standard_normal((2, 200_000))
        y0 = z[0]
        yl = 2.0 * (corr * z[0] + math.sqrt(1 - corr**2) * z[1]) / corr  # slope 2
        k, slope, r, g = pair_evidence(y0, yl)
        assert (k, slope, r) == (
            200_000,
            pytest.approx(2.0, rel=0.01),
            pytest.approx(corr, abs=0.002),
        )
        assert g == pytest.approx(gain, rel=0.02)
    # A cheap level that is level 0 shifted: the differences are a constant, slope 1 fits
    # exactly and there is no scale to show; an exact line of slope 2.5 shows one.
    y0 = rng.standard_normal(12)
    for shift in (3.0, -0.7, 1e4):
        k, slope, r, g = pair_evidence(y0, y0 + shift)
        assert g == 1.0 and slope == pytest.approx(1.0) and not shows_scale(k, slope, r, g)
    k, slope, r, g = pair_evidence(y0, 2.5 * y0 + 1.0)
    assert g > 1e6 and shows_scale(k, slope, r, g)


def test_models_written_before_scales_read_as_additive():
    hp = random_hp(np.random.default_rng(0), 2, 3)
    d = hp.to_dict()
    assert d["scales"] == [1.0, 1.0]
    del d["scales"]
    assert Hyperparameters.from_dict(d) == hp
    with pytest.raises(ValueError, match="scales must be 2 finite numbers > 0"):
        Hyperparameters.from_dict({**d, "scales": [1.0, -2.0]})


def few_level0_runs(seed, d=12, n0=8, n_pairs=7, n1=120, rho=2.5):
    """A discovery loop's data after three batches: 8 level-0 runs (7 of them paired),
    113 cheap-only runs in 12-d, the cheap level 2.5 x level 0 + 1 + a small bias."""
    rng = np.random.default_rng(seed)
    W = rng.normal(size=(3, d)) / math.sqrt(d)

    def f0(Z):
        return np.sin(Z @ W[0]) + 0.5 * (Z @ W[1]) ** 2 - 0.7 * (Z @ W[2])

    X0 = rng.normal(size=(n0, d))
    X1 = np.vstack([X0[:n_pairs], rng.normal(size=(n1 - n_pairs, d))])
    y0 = f0(X0) + 0.01 * rng.normal(size=n0)
    y1 = rho * f0(X1) + 1.0 + 0.2 * np.tanh(X1[:, 0]) + 0.05 * rng.normal(size=n1)
    X = np.vstack([X0, X1])
    return X, np.r_[np.zeros(n0, int), np.ones(n1, int)], np.r_[y0, y1]


@pytest.mark.parametrize("seed", [0, 4])
def test_the_scale_is_found_when_the_additive_optimum_holds_it_back(seed):
    """From the additive optimum, whose discrepancy took the scale's share, a search that
    only moved rho to the pairs' slope went back to rho 1.1 on seed 4 (the level then
    looked as far from level 0 as level 0 varies); the starts with the discrepancy at its
    mode for that slope find 2.4."""
    X, levels, y = few_level0_runs(seed)
    hp = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(seed)).hyperparameters
    assert hp.scales[0] == pytest.approx(2.5, rel=0.05)
    assert math.sqrt(hp.outputscales[0] / hp.outputscale0) < 0.1


@pytest.mark.parametrize("seed", [0, 1])
def test_a_cheap_level_in_other_units_is_fitted_as_in_level_0_s(seed):
    """A cheap level reporting other units (its values times 1/50, 8 or 40: scales 0.05,
    20 and 100) is the same model: the scale follows the units, the discrepancy and level
    0's posterior do not move. Until the data were standardised in level 0's units and the
    scale's prior centred on the pairs' slope, the priors were in the pooled units, and a
    20x level was fitted at rho 1.1 with a discrepancy 25 times theta0's signal."""
    X, levels, y = few_level0_runs(seed)
    Z = np.random.default_rng(9).normal(size=(2000, 12))
    fits = {}
    for c in (1.0, 1 / 50, 8.0, 40.0):
        yc = np.where(levels == 1, c * y, y)
        model = fit_mfgp(X, levels, yc, 2, rng=np.random.default_rng(seed))
        fits[c] = (model.hyperparameters, *model.predict_theta0(Z))
    hp1, mu1, sd1 = fits[1.0]
    assert hp1.scales[0] == pytest.approx(2.5, rel=0.05)
    for c, (hp, mu, sd) in fits.items():
        assert hp.scales[0] == pytest.approx(c * hp1.scales[0], rel=1e-3), c
        assert hp.outputscales[0] == pytest.approx(hp1.outputscales[0], rel=0.02), c
        assert hp.offsets[0] == pytest.approx(c * hp1.offsets[0], rel=0.01, abs=1e-3 * c), c
        assert float(np.max(np.abs(mu - mu1) / sd1)) < 0.15, c
        assert float(np.max(np.abs(sd / sd1 - 1.0))) < 0.01, c


def test_a_scale_the_model_holds_away_from_its_pairs_is_reported_with_their_slope():
    """Hyperparameters held at rho 1 (``--fixed-hyperparameters``) on a level 20x level
    0's: fit's check says what the pairs show. The fitted model says nothing."""
    X, levels, y = few_level0_runs(0, rho=20.0)
    seg = np.unique(X, axis=0, return_inverse=True)[1].ravel()
    fitted = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0))
    assert fitted.hyperparameters.scales[0] == pytest.approx(20.0, rel=0.05)
    assert not [w for w in check_model(fitted, seg).warnings if "times level 0's" in w]
    held = dataclasses.replace(fitted.hyperparameters, scales=np.ones(1))
    model = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0), fixed=held)
    [warning] = [w for w in check_model(model, seg).warnings if "times level 0's" in w]
    assert "level 1's values are 19.9 times level 0's at the 7 segments run at both" in warning
    assert "the model's scale for it is 1 (held fixed" in warning


def test_the_fitted_offset_is_in_the_cheap_level_s_units():
    """b_l = rho_l ystd beta_l + (1 - rho_l) ybar: on data far from 0 (ybar 7 away), the
    fitted offset is the GLS optimum in natural units; moving it lowers the likelihood."""
    X, levels, y, _ = scaled_study(2)
    y = y + 7.0
    model = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(2), restarts=3)
    hp = model.hyperparameters
    assert hp.scales[0] == pytest.approx(2.5, rel=0.1)
    for delta in (-0.05, 0.05):
        moved = MFGP(X, levels, y, 2, dataclasses.replace(hp, offsets=hp.offsets + delta))
        assert moved.log_marginal_likelihood < model.log_marginal_likelihood - 1e-3


def test_a_model_on_a_subset_scores_its_prior_in_the_fit_s_units():
    """Conditioning on a subset (a memory budget) that keeps too few pairs to show the
    scale: the prior is still scored in the units the fit chose on every observation, so
    log_posterior - log_marginal_likelihood is near the full model's: 2 nats off, the
    lengthscale prior's, which follows the subset's input ranges; 57 nats off when the
    subset standardised itself (pooled units, the gate lost)."""
    from bams_cli.core.conditioning_budget import BYTES_PER_ENTRY
    from bams_cli.core.gp.fit import conditioning_subset

    X, levels, y = few_level0_runs(0, rho=20.0)
    full = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0))
    cap = 60
    rows = conditioning_subset(levels, 2, cap)
    assert rows is not None
    assert math.isnan(pair_scales(X[rows], levels[rows], y[rows], 2)[0])  # the gate is lost
    sub = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0),
                   fixed=full.hyperparameters, max_memory=BYTES_PER_ENTRY * cap * cap)  # fmt: skip
    assert sub.conditioning["conditioned_on"] == cap
    prior = lambda m: m.log_posterior - m.log_marginal_likelihood  # noqa: E731
    assert abs(prior(sub) - prior(full)) < 3.0
