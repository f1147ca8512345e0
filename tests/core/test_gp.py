"""Tests of the multifidelity GP (bams_cli/core/gp.py).

Reference values come from independent computations written here (a direct Matern
function, dense np.linalg.solve) or from scikit-learn, never from the module under test.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pickle

import numpy as np
import pytest
from scipy.special import ndtr
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel
from threadpoolctl import threadpool_limits

from bams_cli.core.gp import (
    MFGP,
    GPFitError,
    Hyperparameters,
    _failure_probability,
    _MAPObjective,
    _pack,
    _Priors,
    cholesky,
    fit_mfgp,
    standardise,
)

# ----------------------------------------------------------------- reference model


def ref_matern52(A, B, ell, s2):
    """Matern-5/2 ARD written from GPML eq. 4.17 with explicit differences."""
    r = np.sqrt((((A[:, None, :] - B[None, :, :]) / ell) ** 2).sum(-1))
    return s2 * (1 + math.sqrt(5) * r + 5.0 / 3.0 * r**2) * np.exp(-math.sqrt(5) * r)


def ref_kaug(A, la, B, lb, hp):
    """k_aug((x, a), (x', b)) = k0 + [a == b >= 1] k_a, entry by entry."""
    K = ref_matern52(A, B, hp.lengthscales0, hp.outputscale0)
    for i in range(len(A)):
        for j in range(len(B)):
            if la[i] == lb[j] and la[i] >= 1:
                l = la[i]
                K[i, j] += ref_matern52(
                    A[i : i + 1], B[j : j + 1], hp.lengthscales[l - 1], hp.outputscales[l - 1]
                )[0, 0]
    return K


def ref_same(A, la, B, lb):
    return np.array(
        [
            [bool(np.all(A[i] == B[j]) and la[i] == lb[j]) for j in range(len(B))]
            for i in range(len(A))
        ]
    )


def random_hp(rng, d, n_levels):
    L = n_levels - 1
    return Hyperparameters(
        mean=float(rng.normal()),
        outputscale0=float(rng.uniform(0.5, 2.0)),
        lengthscales0=rng.uniform(0.5, 2.0, d),
        outputscales=rng.uniform(0.05, 0.5, L),
        lengthscales=rng.uniform(0.5, 3.0, (L, d)),
        noise=rng.uniform(0.01, 0.1, n_levels),
        offsets=rng.normal(size=L),
    )


def mf_data(rng, d, n_levels, n=24):
    """Observations with repeats of one (x, l) and one x observed at every level."""
    X = rng.normal(size=(n, d))
    levels = rng.integers(0, n_levels, n)
    X[1] = X[0]
    levels[1] = levels[0]  # a repeat: same (x, l), distinct observation
    for l in range(n_levels):
        X[2 + l] = X[0]
        levels[2 + l] = l  # the same x at every level
    y = np.sin(X).sum(1) + 0.3 * levels + 0.1 * rng.normal(size=n)
    return X, levels, y


# -------------------------------------------------- 1. one level against sklearn


@pytest.mark.parametrize("d", [1, 3])
@pytest.mark.parametrize("mean", [0.0, 1.7])
def test_one_level_equals_sklearn(d, mean):
    rng = np.random.default_rng(d)
    X = rng.uniform(-2, 2, (30, d))
    y = np.cos(2 * X).sum(1) + 0.1 * rng.normal(size=30) + mean
    Xt = rng.uniform(-2.5, 2.5, (17, d))
    hp = Hyperparameters(
        mean=mean,
        outputscale0=1.3,
        lengthscales0=rng.uniform(0.3, 1.5, d),
        outputscales=np.zeros(0),
        lengthscales=np.zeros((0, d)),
        noise=np.array([0.05]),
    )
    model = fit_mfgp(X, np.zeros(30, int), y, 1, rng=rng, fixed=hp)

    # sklearn has a zero prior mean: give it y - mean and add the mean back. Its
    # predictive variance includes the WhiteKernel noise; ours is theta0's.
    kernel = ConstantKernel(1.3, "fixed") * Matern(
        length_scale=hp.lengthscales0, length_scale_bounds="fixed", nu=2.5
    ) + WhiteKernel(0.05, "fixed")
    sk = GaussianProcessRegressor(kernel, alpha=0.0, optimizer=None, normalize_y=False)
    sk.fit(X, y - mean)
    sk_mu, sk_cov = sk.predict(Xt, return_cov=True)

    mu, sigma2 = model.predict_theta0(Xt)
    np.testing.assert_allclose(mu, sk_mu + mean, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(sigma2, np.diag(sk_cov) - 0.05, rtol=1e-8)
    np.testing.assert_allclose(
        model.cov_theta0(Xt, Xt), sk_cov - 0.05 * np.eye(17), rtol=1e-8, atol=1e-12
    )
    np.testing.assert_allclose(model.obs_var(Xt, np.zeros(17, int)), np.diag(sk_cov), rtol=1e-8)
    np.testing.assert_allclose(
        model.log_marginal_likelihood, sk.log_marginal_likelihood_value_, rtol=1e-10
    )


# ----------------------------------------- 2. multifidelity against dense algebra


@pytest.mark.parametrize("n_levels", [2, 3])
@pytest.mark.parametrize("d", [1, 2])
def test_multifidelity_posterior_equals_dense(n_levels, d):
    rng = np.random.default_rng(10 * n_levels + d)
    X, levels, y = mf_data(rng, d, n_levels)
    hp = random_hp(rng, d, n_levels)
    model = fit_mfgp(X, levels, y, n_levels, rng=rng, fixed=hp)

    K = ref_kaug(X, levels, X, levels, hp) + np.diag(hp.noise[levels])
    solve = lambda B: np.linalg.solve(K, B)  # noqa: E731
    Xp = np.vstack([rng.normal(size=(5, d)), X[:2]])  # includes an observed point
    Xc = np.vstack([rng.normal(size=(4, d)), X[0], X[0], X[5]])
    lc = np.r_[rng.integers(0, n_levels, 4), levels[0], 1, levels[5]]
    Xc[1], lc[1] = Xc[0], (lc[0] + 1) % n_levels  # same x, another level

    k0_p = ref_matern52(Xp, X, hp.lengthscales0, hp.outputscale0)
    prior_mean = hp.mean + np.r_[0.0, hp.offsets][levels]  # y = m + b_l + theta0 + ...
    mu_ref = hp.mean + k0_p @ solve(y - prior_mean)
    cov_pp = ref_matern52(Xp, Xp, hp.lengthscales0, hp.outputscale0) - k0_p @ solve(k0_p.T)
    kc = ref_kaug(X, levels, Xc, lc, hp)
    cov_pc = ref_matern52(Xp, Xc, hp.lengthscales0, hp.outputscale0) - k0_p @ solve(kc)
    same = ref_same(Xc, lc, Xc, lc)
    cov_cc = ref_kaug(Xc, lc, Xc, lc, hp) + same * hp.noise[lc][:, None] - kc.T @ solve(kc)

    mu, sigma2 = model.predict_theta0(Xp)
    np.testing.assert_allclose(mu, mu_ref, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(sigma2, np.diag(cov_pp), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(model.cov_theta0(Xp, Xp), cov_pp, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(model.cov_theta0_obs(Xp, Xc, lc), cov_pc, rtol=1e-8, atol=1e-10)
    # More than twice as many rows as columns: the data term through K^-1 k_aug(Y_n, c).
    np.testing.assert_allclose(
        model.cov_theta0_obs(Xp, Xc[:3], lc[:3]), cov_pc[:, :3], rtol=1e-8, atol=1e-10
    )
    # Each candidate at its own point: the dense diagonal (select's first screen).
    cov_own = ref_matern52(Xc, Xc, hp.lengthscales0, hp.outputscale0) - ref_matern52(
        Xc, X, hp.lengthscales0, hp.outputscale0
    ) @ solve(kc)
    own_cov, own_var = model.own_point(Xc, lc)
    np.testing.assert_allclose(own_cov, np.diag(cov_own), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(own_var, np.diag(cov_cc), rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(model.cov_obs_obs(Xc, lc, Xc, lc), cov_cc, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(model.obs_var(Xc, lc), np.diag(cov_cc), rtol=1e-8, atol=1e-10)
    # An explicit `same` replaces the default: here no pair is the same observation.
    no_noise = cov_cc - same * hp.noise[lc][:, None]
    np.testing.assert_allclose(
        model.cov_obs_obs(Xc, lc, Xc, lc, same=np.zeros((7, 7), bool)), no_noise, atol=1e-10
    )
    # Rectangular blocks agree with the square one.
    np.testing.assert_allclose(
        model.cov_obs_obs(Xc[:3], lc[:3], Xc[2:], lc[2:]), cov_cc[:3, 2:], rtol=1e-8, atol=1e-10
    )


@pytest.mark.parametrize("n_levels", [2, 3])
def test_a_localised_posterior_answers_as_the_dense_reference(n_levels, monkeypatch):
    # Selection's per-cluster view (MFGP.localised) solves each (point, level) factor once
    # and looks it up afterwards: every answer equals the dense reference, for points of
    # its set, points outside it, a mix, repeats and the same query twice; each factor is
    # solved once; the original is untouched; too little memory means no view.
    from bams_cli.core.gp import model as gp_model

    rng = np.random.default_rng(40 + n_levels)
    d = 2
    X, levels, y = mf_data(rng, d, n_levels)
    hp = random_hp(rng, d, n_levels)
    model = fit_mfgp(X, levels, y, n_levels, rng=rng, fixed=hp)
    K = ref_kaug(X, levels, X, levels, hp) + np.diag(hp.noise[levels])
    solve = lambda B: np.linalg.solve(K, B)  # noqa: E731

    pts = np.vstack([rng.normal(size=(30, d)), X[:3]])  # the view's set, observed points too
    view = model.localised(pts, 2**30)
    assert view is not model and getattr(model, "_local", None) is None
    assert model.localised(pts, 8 * len(X) * len(pts) * n_levels - 1) is model

    solved = []
    real = gp_model.MFGP._solve_L
    monkeypatch.setattr(
        gp_model.MFGP, "_solve_L", lambda self, B: solved.append(B.shape[1]) or real(self, B)
    )
    outside = rng.normal(size=(4, d))
    Xp = np.vstack([pts[[0, 5, 5, 31]], outside[:2]])  # repeats and two points outside
    Xc = np.vstack([pts[[1, 1, 2, 7, 32]], outside[2:]])
    lc = np.r_[0, n_levels - 1, rng.integers(0, n_levels, 3), 1, 0]
    for _ in range(2):  # the second round finds every factor of the set solved
        k0_p = ref_matern52(Xp, X, hp.lengthscales0, hp.outputscale0)
        kc = ref_kaug(X, levels, Xc, lc, hp)
        cov_pc = ref_matern52(Xp, Xc, hp.lengthscales0, hp.outputscale0) - k0_p @ solve(kc)
        cov_pp = ref_matern52(Xp, Xp, hp.lengthscales0, hp.outputscale0) - k0_p @ solve(k0_p.T)
        same = ref_same(Xc, lc, Xc, lc)
        cov_cc = ref_kaug(Xc, lc, Xc, lc, hp) + same * hp.noise[lc][:, None] - kc.T @ solve(kc)
        cov_own = ref_matern52(Xc, Xc, hp.lengthscales0, hp.outputscale0) - ref_matern52(
            Xc, X, hp.lengthscales0, hp.outputscale0
        ) @ solve(kc)
        tol = dict(rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(view.cov_theta0_obs(Xp, Xc, lc), cov_pc, **tol)
        np.testing.assert_allclose(view.cov_theta0(Xp, Xp), cov_pp, **tol)
        np.testing.assert_allclose(view.cov_obs_obs(Xc, lc, Xc, lc), cov_cc, **tol)
        np.testing.assert_allclose(view.obs_var(Xc, lc), np.diag(cov_cc), **tol)
        own_cov, own_var = view.own_point(Xc, lc)
        np.testing.assert_allclose(own_cov, np.diag(cov_own), **tol)
        np.testing.assert_allclose(own_var, np.diag(cov_cc), **tol)
        if _ == 0:
            first = sum(solved)
    # Second round: only the points outside the set were solved again, 2 + 2 columns per
    # query that holds them (cov_theta0_obs: 2 + 2, cov_theta0: 2 + 2, cov_obs_obs: 2, the
    # pairs against themselves from one factor, obs_var: 2, own_point: 2 + 2).
    assert sum(solved) - first == 16
    # First round: at most once per (point, level) of the set, plus the outside points.
    n_set_pairs = len(
        {(tuple(x), 0) for x in Xp[:4]}
        | {(tuple(x), int(l)) for x, l in zip(Xc[:5], lc[:5], strict=True)}
        | {(tuple(x), 0) for x in Xc[:5]}
    )
    assert first <= n_set_pairs + 18


def test_noise_only_on_true_diagonal_of_training_covariance():
    # Two observations of the same (x, 0) are distinct: their covariance is s0, not s0 + tau^2.
    # A model that put noise on every identical pair would shrink toward the repeats' mean
    # differently; check against the dense reference with repeats only.
    rng = np.random.default_rng(3)
    X = np.repeat(rng.normal(size=(3, 2)), 2, axis=0)
    levels = np.zeros(6, int)
    y = rng.normal(size=6)
    hp = random_hp(rng, 2, 1)
    model = MFGP(X, levels, y, 1, hp)
    K = ref_matern52(X, X, hp.lengthscales0, hp.outputscale0) + hp.noise[0] * np.eye(6)
    x = X[:1]
    k = ref_matern52(x, X, hp.lengthscales0, hp.outputscale0)
    np.testing.assert_allclose(
        model.predict_theta0(x)[0], hp.mean + k @ np.linalg.solve(K, y - hp.mean), rtol=1e-10
    )


# ---------------------------------------------------------- 3. analytic gradient


@pytest.mark.parametrize("n_levels", [1, 2, 3])
def test_gradient_matches_central_differences(n_levels):
    rng = np.random.default_rng(n_levels)
    d = 3
    X, levels, y = mf_data(rng, d, n_levels, n=30)
    ybar, ystd = standardise(y)
    priors = _Priors.for_data(X, n_levels)
    objective = _MAPObjective(X, levels, (y - ybar) / ystd, n_levels, priors)
    for _ in range(4):
        assert_gradient_matches(objective, priors.sample_start(rng))


def assert_gradient_matches(objective, theta, h=1e-6):
    """The objective's analytic gradient at theta equals central differences of it."""
    with threadpool_limits(limits=1, user_api="blas"):  # as fit_mfgp runs it; faster
        _, grad = objective(theta)
        fd = np.array(
            [
                (objective(theta + h * e)[0] - objective(theta - h * e)[0]) / (2 * h)
                for e in np.eye(theta.size)
            ]
        )
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-5 * np.abs(fd).max())


def test_uncached_squared_differences_give_same_objective(monkeypatch):
    import bams_cli.core.gp.objective as gp

    rng = np.random.default_rng(0)
    X, levels, y = mf_data(rng, 3, 2)
    priors = _Priors.for_data(X, 2)
    theta = priors.sample_start(rng)
    f_cached, g_cached = _MAPObjective(X, levels, y, 2, priors)(theta)
    monkeypatch.setattr(gp, "_MAX_DIFF_ELEMENTS", 0)
    f_loop, g_loop = _MAPObjective(X, levels, y, 2, priors)(theta)
    assert f_loop == pytest.approx(f_cached, rel=1e-12)
    np.testing.assert_allclose(g_loop, g_cached, rtol=1e-9, atol=1e-12)


# ------------------------------------------------------------------ fit behaviour


def standardised_theta(hp, ystd):
    """The packed parameters of ``hp`` in the units of y / std(y), the objective's."""
    v = ystd**2
    return _pack(
        dataclasses.replace(
            hp,
            outputscale0=hp.outputscale0 / v,
            outputscales=hp.outputscales / v,
            noise=hp.noise / v,
        )
    )


def test_fit_reports_map_objective_and_beats_prior_mode():
    rng = np.random.default_rng(5)
    X, levels, y = mf_data(rng, 2, 2, n=40)
    model = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0), restarts=3)
    ybar, ystd = standardise(y)
    priors = _Priors.for_data(X, 2)
    objective = _MAPObjective(X, levels, (y - ybar) / ystd, 2, priors)
    hp = model.hyperparameters
    theta = standardised_theta(hp, ystd)
    f_fit, grad = objective(theta)
    # log_posterior is the MAP objective in natural units (shift n log std(y)).
    assert model.log_posterior == pytest.approx(-f_fit - len(y) * math.log(ystd), abs=1e-6)
    assert f_fit < objective(priors.mode)[0] - 1.0
    # The GLS mean is what the model uses: refitting the mean cannot raise the likelihood.
    for dm in (-0.05, 0.05):
        shifted = MFGP(X, levels, y, 2, dataclasses.replace(hp, mean=hp.mean + dm))
        assert shifted.log_marginal_likelihood < model.log_marginal_likelihood


def test_fit_is_equivariant_to_output_scale():
    rng = np.random.default_rng(8)
    X, levels, y = mf_data(rng, 2, 2, n=30)
    a = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(1), restarts=3).hyperparameters
    scaled = fit_mfgp(X, levels, 1000.0 * y + 5.0, 2, rng=np.random.default_rng(1), restarts=3)
    b = scaled.hyperparameters
    assert b.mean == pytest.approx(1000.0 * a.mean + 5.0, rel=1e-5)
    assert b.outputscale0 == pytest.approx(1e6 * a.outputscale0, rel=1e-5)
    np.testing.assert_allclose(b.lengthscales0, a.lengthscales0, rtol=1e-5)
    np.testing.assert_allclose(b.noise, 1e6 * a.noise, rtol=1e-4)
    np.testing.assert_allclose(b.outputscales, 1e6 * a.outputscales, rtol=1e-5)


@pytest.mark.parametrize("n_levels", [1, 3])
def test_fit_shapes_and_levels_without_data(n_levels):
    rng = np.random.default_rng(2)
    X = rng.normal(size=(20, 3))
    levels = np.zeros(20, int) if n_levels == 1 else rng.integers(0, 2, 20)  # level 2 unused
    y = np.sin(X).sum(1)
    model = fit_mfgp(X, levels, y, n_levels, rng=rng, restarts=2)
    hp = model.hyperparameters
    L = n_levels - 1
    assert hp.outputscales.shape == (L,)
    assert hp.lengthscales.shape == (L, 3)
    assert hp.noise.shape == (n_levels,)
    assert model.lengthscales0.shape == (3,)
    assert model.n_levels == n_levels
    np.testing.assert_array_equal(model.n_obs_per_level, np.bincount(levels, minlength=n_levels))
    assert np.all(np.isfinite(model.predict_theta0(X)[0]))


def test_fit_is_reproducible_given_rng():
    rng = np.random.default_rng(4)
    X, levels, y = mf_data(rng, 2, 2)
    a = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(7), restarts=3).hyperparameters
    b = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(7), restarts=3).hyperparameters
    assert a == b


# ------------------------------------------------------------- 4. prior recovery


def draw_from_prior(seed, hp, d):
    """n = 200, two levels: 70 level-0 sites (30 observed twice), 100 level-1 obs."""
    rng = np.random.default_rng(seed)
    U = rng.normal(size=(70, d))
    X = np.vstack([U, U[:30], U[:40], rng.normal(size=(60, d))])
    levels = np.r_[np.zeros(100, int), np.ones(100, int)]
    K = ref_kaug(X, levels, X, levels, hp) + np.diag(hp.noise[levels])
    y = hp.mean + np.linalg.cholesky(K) @ rng.normal(size=200)
    return X, levels, y


@pytest.mark.slow
def test_map_recovers_hyperparameters_of_data_drawn_from_the_prior():
    """Fitted theta0 lengthscales and both noise variances land within a factor 2.5 of the
    truth on every seed, and within a factor 1.5 on average over seeds (no bias).

    Repeats at level 0 are part of the design: without them, a level-0 noise of 5% of
    the signal variance is not identifiable from 100 scattered points in 4-d (the
    likelihood is flat over 1e-4..1e-2 and the prior decides), which is the data's
    limit, not the fit's.
    """
    d = 4
    truth = Hyperparameters(
        mean=1.0,
        outputscale0=2.0,
        lengthscales0=np.array([0.8, 1.2, 2.0, 3.0]),
        outputscales=np.array([0.3]),
        lengthscales=np.full((1, d), 2.0),
        noise=np.array([0.05, 0.2]),
    )
    log_err_ell, log_err_noise = [], []
    for seed in range(5):
        X, levels, y = draw_from_prior(seed, truth, d)
        hp = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(seed)).hyperparameters
        log_err_ell.append(np.log(hp.lengthscales0 / truth.lengthscales0))
        # Each level's noise in its own units: a cheap level's is rho^2 tau^2.
        own_units = hp.noise * np.r_[1.0, hp.scales] ** 2
        log_err_noise.append(np.log(own_units / truth.noise))
    err_ell, err_noise = np.array(log_err_ell), np.array(log_err_noise)
    assert np.all(np.abs(err_ell) < math.log(2.5)), np.exp(err_ell)
    assert np.all(np.abs(err_noise) < math.log(2.5)), np.exp(err_noise)
    assert np.all(np.abs(err_ell.mean(0)) < math.log(1.5)), np.exp(err_ell.mean(0))
    assert np.all(np.abs(err_noise.mean(0)) < math.log(1.5)), np.exp(err_noise.mean(0))


def test_prior_modes_are_the_documented_ones():
    """The priors' modes, pinned: a changed default must change this test on purpose.

    d = 12 inputs with unit range, two levels; standardised units. The lengthscale prior
    is BoTorch's dimension-scaled one, mode exp(sqrt2 + log(d)/2 - 3) = 0.2048 sqrt(d).
    """
    from bams_cli.core.gp import DEFAULT_PRIORS

    d = 12
    X = np.vstack([np.zeros(d), np.ones(d)])
    mode = np.exp(_Priors.for_data(X, 2).mode)
    s, ell, noise = mode[:2], mode[2 : 2 + 2 * d].reshape(2, d), mode[2 + 2 * d : 4 + 2 * d]
    rho = mode[4 + 2 * d :]
    np.testing.assert_allclose(ell, math.exp(math.sqrt(2) - 3) * math.sqrt(d), rtol=1e-12)
    assert ell[0, 0] == pytest.approx(0.7094, abs=1e-4)
    np.testing.assert_allclose(s, [1.0, DEFAULT_PRIORS.discrepancy[0]], rtol=1e-12)
    np.testing.assert_allclose(noise, [3e-4, 3e-3], rtol=1e-12)
    np.testing.assert_allclose(rho, [1.0], rtol=1e-12)
    assert DEFAULT_PRIORS.level_scale == (1.0, 0.5)
    assert DEFAULT_PRIORS.noise0 == (3e-4, 1.0) and DEFAULT_PRIORS.lengthscale_dim_scaling
    # Natural units: a dimension twice as wide gets twice the lengthscale.
    X2 = X.copy()
    X2[1, 0] = 2.0
    assert np.exp(_Priors.for_data(X2, 2).mode[2]) == pytest.approx(2 * ell[0, 0])


def test_level0_noise_the_data_cannot_identify_stays_near_the_prior_mode():
    """100 scattered points in 4-d with noise 1% of the signal variance: the likelihood
    hardly tells that noise from roughness, so the prior decides. Measured fitted noise /
    var(y): 4e-4, 1.7e-3, 3e-4 on seeds 0-2 with the shipped prior; with a 100x higher
    mode, 9e-3, 4e-3, 4e-3 (mean 6e-3), which this test rejects."""
    fitted = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        X = rng.normal(size=(100, 4))
        f = np.sin(1.5 * X[:, 0]) + np.cos(1.2 * X[:, 1]) * X[:, 2] + 0.5 * np.sin(2 * X[:, 3])
        y = f + 0.1 * np.std(f) * rng.normal(size=100)
        hp = fit_mfgp(X, np.zeros(100, int), y, 1, rng=np.random.default_rng(0)).hyperparameters
        fitted.append(hp.noise[0] / np.var(y))
    assert max(fitted) < 2.5e-3 and np.mean(fitted) < 1.5e-3, fitted


def test_dimension_scaled_lengthscales_keep_a_12d_fit_from_interpolating():
    """20 points in 12-d from a function of two inputs: the sqrt(d)-scaled prior keeps the
    irrelevant dimensions' lengthscales long (median above the input range); without
    the scaling (prior mode 0.2 x range) the fit makes them short and interpolates."""
    from bams_cli.core.gp import PriorSpec

    rng = np.random.default_rng(1)
    X = rng.uniform(0, 1, (20, 12))
    y = np.sin(4 * X[:, 0]) + X[:, 1]
    fits = {
        scaled: fit_mfgp(
            X, np.zeros(20, int), y, 1, rng=np.random.default_rng(0),
            priors=PriorSpec(lengthscale_dim_scaling=scaled),
        ).hyperparameters.lengthscales0
        for scaled in (True, False)
    }  # fmt: skip
    assert np.median(fits[True][2:]) > 1.0
    assert np.median(fits[True][2:]) > 2.0 * np.median(fits[False][2:])


# -------------------------------------------------------------------- 5. toy2d


def toy_f(X):
    """Paper appendix (synthetic experiments): ||(|x0| - c, x1 - c)||_1, c = 1.95."""
    return np.abs(np.abs(X[:, 0]) - 1.95) + np.abs(X[:, 1] - 1.95)


def test_cheap_level_lowers_heldout_error_on_toy2d():
    ratios = []
    for seed in range(5):
        rng = np.random.default_rng(seed)
        X0, X1, Xt = rng.normal(size=(15, 2)), rng.normal(size=(100, 2)), rng.normal(size=(2000, 2))
        y0, y1 = toy_f(X0), toy_f(X1) + 0.1 * rng.normal(size=100)
        single = fit_mfgp(X0, np.zeros(15, int), y0, 1, rng=np.random.default_rng(seed))
        multi = fit_mfgp(
            np.vstack([X0, X1]),
            np.r_[np.zeros(15, int), np.ones(100, int)],
            np.r_[y0, y1],
            2,
            rng=np.random.default_rng(seed),
        )
        rmse = [
            np.sqrt(np.mean((m.predict_theta0(Xt)[0] - toy_f(Xt)) ** 2)) for m in (single, multi)
        ]
        ratios.append(rmse[1] / rmse[0])
    # Measured ratios 0.26..0.79 (mean 0.5); a GP that ignored level 1, or let its noise
    # swamp level 0, would sit near or above 1.
    assert max(ratios) < 0.95, ratios
    assert np.mean(ratios) < 0.7, ratios


def test_constant_bias_of_a_cheap_level_is_an_offset_not_a_discrepancy():
    """A cheap level reading 2.0 high everywhere: the GLS offset takes the bias, so the
    discrepancy kernel stays small and theta0's mean is not shifted."""
    rng = np.random.default_rng(3)
    X = rng.normal(size=(60, 2))
    f = np.sin(X[:, 0]) + 0.5 * X[:, 1]
    levels = np.r_[np.zeros(20, int), np.ones(40, int)]
    X = np.vstack([X[:20], X[:20], X[20:40]])  # 20 pairs, 20 cheap-only
    f = np.r_[f[:20], f[:20], f[20:40]]
    y = f + 2.0 * levels + 0.01 * rng.normal(size=60)
    model = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0))
    hp = model.hyperparameters
    assert hp.offsets[0] == pytest.approx(2.0, abs=0.1)
    assert hp.outputscales[0] < 0.05 * np.var(y)
    Xt = rng.normal(size=(200, 2))
    mu, _ = model.predict_theta0(Xt)
    assert abs(np.mean(mu - (np.sin(Xt[:, 0]) + 0.5 * Xt[:, 1]))) < 0.1


def test_offset_is_zero_without_level0_data():
    rng = np.random.default_rng(4)
    X = rng.normal(size=(10, 2))
    model = fit_mfgp(X, np.ones(10, int), X.sum(1), 2, rng=rng)
    assert model.hyperparameters.offsets.tolist() == [0.0]


# ------------------------------------------------------- 6. numerical failure


def test_jitter_rescues_duplicates_without_noise():
    rng = np.random.default_rng(0)
    X = np.repeat(rng.normal(size=(5, 2)), 2, axis=0)
    y = np.repeat(rng.normal(size=5), 2)
    hp = dataclasses.replace(random_hp(rng, 2, 1), noise=np.array([0.0]))
    model = MFGP(X, np.zeros(10, int), y, 1, hp)
    assert model.jitter > 0.0
    assert len(model.notes) == 1 and "jitter" in model.notes[0]
    mu, sigma2 = model.predict_theta0(X)
    np.testing.assert_allclose(mu, y, atol=1e-3)
    assert np.all(sigma2 >= 0.0) and np.all(sigma2 < 1e-3)


def test_no_note_when_no_jitter_was_needed():
    rng = np.random.default_rng(0)
    X, levels, y = mf_data(rng, 2, 2)
    assert MFGP(X, levels, y, 2, random_hp(rng, 2, 2)).notes == []


def test_constant_data_is_a_recorded_fact():
    X = np.random.default_rng(0).normal(size=(6, 2))
    model = fit_mfgp(X, np.zeros(6, int), np.full(6, 3.5), 1, rng=np.random.default_rng(0))
    assert any("all 6 observed values equal 3.5" in n for n in model.notes)


def test_values_near_the_float_limit_are_standardised_without_overflow():
    # The plain np.mean of these overflows to inf; scaled first, it does not.
    ybar, ystd = standardise(np.array([1.7e308, 1.7e308]))
    assert ybar == pytest.approx(1.7e308) and ystd == 1.0
    assert standardise(np.array([1e100, 2e100])) == pytest.approx((1.5e100, 0.5e100))
    with pytest.raises(GPFitError, match="too large for a GP"):
        standardise(np.array([1e307, 3e307, 2e307]))
    with pytest.raises(GPFitError, match="too large for a GP"):
        fit_mfgp(
            np.eye(3), np.zeros(3, int), [1e307, 3e307, 2e307], 1, rng=np.random.default_rng(0)
        )


def test_a_spread_too_small_for_float64_variances_is_an_error_not_a_zero_outputscale():
    # Found by the fuzzing of ingest-results: level-0 values 0 and 7e-227 have sd 3.5e-227,
    # whose square underflows, so the fitted outputscale came out 0 (a catch-all error).
    with pytest.raises(GPFitError, match="too small for a GP"):
        standardise(np.array([0.0, 7.052485094062495e-227]))
    with pytest.raises(GPFitError, match="too small for a GP"):
        fit_mfgp(np.eye(2), np.zeros(2, int), [0.0, 7e-227], 1, rng=np.random.default_rng(0))
    # A small spread whose variances are still float64 numbers is fitted as any other.
    assert standardise(np.array([0.0, 2e-100])) == pytest.approx((1e-100, 1e-100))
    model = fit_mfgp(
        np.eye(3), np.zeros(3, int), [0.0, 2e-100, 1e-100], 1, rng=np.random.default_rng(0)
    )
    assert (
        np.isfinite(model.hyperparameters.outputscale0) and model.hyperparameters.outputscale0 > 0
    )


def test_indefinite_matrix_raises_with_remedy():
    with pytest.raises(GPFitError, match="jitter.*noise variance"):
        cholesky(np.array([[1.0, 2.0], [2.0, 1.0]]))


def test_overflowing_inputs_raise_with_remedy():
    X = np.array([[1e160], [-1e160], [0.0]])
    hp = Hyperparameters(0.0, 1.0, np.ones(1), np.zeros(0), np.zeros((0, 1)), np.array([0.1]))
    with pytest.raises(GPFitError, match="non-finite entries.*rescale X"):
        MFGP(X, np.zeros(3, int), np.zeros(3), 1, hp)


@pytest.mark.parametrize(
    ("column", "match"), [("y", "y has 1 non-finite value.*row 3"), ("X", "X has .*row 3")]
)
def test_nonfinite_data_raise_naming_the_row(column, match):
    rng = np.random.default_rng(0)
    X, y = rng.normal(size=(6, 2)), rng.normal(size=6)
    if column == "y":
        y[3] = np.nan
    else:
        X[3, 1] = np.inf
    with pytest.raises(GPFitError, match=match):
        fit_mfgp(X, np.zeros(6, int), y, 1, rng=rng)


def test_levels_out_of_range_raise():
    rng = np.random.default_rng(0)
    with pytest.raises(GPFitError, match=r"levels must lie in \[0, 2\)"):
        fit_mfgp(rng.normal(size=(4, 1)), np.array([0, 1, 2, 0]), np.zeros(4), 2, rng=rng)
    with pytest.raises(ValueError):
        Hyperparameters(0.0, 1.0, np.ones(1), np.ones(1), np.ones((1, 1)), np.array([0.1]))


# ------------------------------------------------------------------ 7. score()


@pytest.mark.parametrize("n_levels", [1, 2])
def test_score_chunked_equals_unchunked_and_p_is_phi(n_levels):
    rng = np.random.default_rng(11)
    X, levels, y = mf_data(rng, 2, n_levels)
    model = MFGP(X, levels, y, n_levels, random_hp(rng, 2, n_levels))
    Xp = rng.normal(size=(103, 2))
    gammas = np.array([-0.5, 0.0, 1.0])
    mu, sd, p = model.score(Xp, gammas, chunk_size=10**6)
    mu7, sd7, p7 = model.score(Xp, gammas, chunk_size=7)
    np.testing.assert_allclose(mu7, mu, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(sd7, sd, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(p7, p, rtol=1e-12, atol=1e-14)
    assert p.shape == (103, 3)
    np.testing.assert_allclose(p, ndtr((gammas[None, :] - mu[:, None]) / sd[:, None]), rtol=1e-14)
    mu_ref, s2_ref = model.predict_theta0(Xp)
    np.testing.assert_allclose(mu, mu_ref, rtol=1e-13)
    np.testing.assert_allclose(sd**2, s2_ref, rtol=1e-12)


def test_failure_probability_with_zero_sd_is_an_indicator():
    mu = np.array([0.0, 1.0, 2.0, 1.0])
    sd = np.array([0.0, 0.0, 0.0, 1.0])
    p = _failure_probability(mu, sd, np.array([1.0]))
    np.testing.assert_array_equal(p[:3, 0], [1.0, 1.0, 0.0])
    assert p[3, 0] == pytest.approx(0.5)
    assert not np.isnan(p).any()


# ------------------------------------------------------------ serialisation


def test_hyperparameters_json_round_trip():
    rng = np.random.default_rng(0)
    for n_levels in (1, 3):
        hp = random_hp(rng, 4, n_levels)
        back = Hyperparameters.from_dict(json.loads(json.dumps(hp.to_dict())))
        assert back == hp
        assert back.lengthscales.shape == (n_levels - 1, 4)


def test_model_pickles():
    rng = np.random.default_rng(0)
    X, levels, y = mf_data(rng, 2, 2)
    model = MFGP(X, levels, y, 2, random_hp(rng, 2, 2))
    clone = pickle.loads(pickle.dumps(model))
    Xp = rng.normal(size=(9, 2))
    np.testing.assert_array_equal(clone.score(Xp, [0.0])[2], model.score(Xp, [0.0])[2])
    np.testing.assert_array_equal(
        clone.cov_obs_obs(Xp, np.ones(9, int), Xp, np.ones(9, int)),
        model.cov_obs_obs(Xp, np.ones(9, int), Xp, np.ones(9, int)),
    )


def test_mfgp_satisfies_posterior_protocol():
    from bams_cli.core.posterior import Posterior

    rng = np.random.default_rng(0)
    X, levels, y = mf_data(rng, 2, 2)
    model = MFGP(X, levels, y, 2, random_hp(rng, 2, 2))
    posterior: Posterior = model  # mypy checks the structural match
    assert posterior.n_levels == 2
    np.testing.assert_array_equal(posterior.lengthscales0, model.hyperparameters.lengthscales0)
    for name in ("predict_theta0", "cov_theta0_obs", "cov_obs_obs", "obs_var"):
        assert callable(getattr(posterior, name))


def test_cov_obs_obs_reuses_the_factor_of_a_repeated_large_candidate_set():
    # Selection asks for one row against the same ~15,000 candidates at every pick; the
    # model remembers their factor. A changed set (same shape) must not get the stale one.
    rng = np.random.default_rng(3)
    X, levels, y = mf_data(rng, 2, 2)
    hp = random_hp(rng, 2, 2)
    model = fit_mfgp(X, levels, y, 2, rng=rng, fixed=hp)
    Xc = rng.normal(size=(1100, 2))
    lc = rng.integers(0, 2, 1100)
    ref = dense_cov_obs_obs(X, levels, hp, Xc[:3], lc[:3], Xc, lc)
    first = model.cov_obs_obs(Xc[:3], lc[:3], Xc, lc)
    again = model.cov_obs_obs(Xc[:3], lc[:3], Xc, lc)
    np.testing.assert_allclose(first, ref, rtol=1e-8, atol=1e-10)
    np.testing.assert_array_equal(again, first)
    Xc2, lc2 = Xc.copy(), lc.copy()
    Xc2[500] += 0.3
    lc2[7] = 1 - lc2[7]
    ref2 = dense_cov_obs_obs(X, levels, hp, Xc2[:3], lc2[:3], Xc2, lc2)
    np.testing.assert_allclose(
        model.cov_obs_obs(Xc2[:3], lc2[:3], Xc2, lc2), ref2, rtol=1e-8, atol=1e-10
    )


def dense_cov_obs_obs(X, levels, hp, Xa, la, Xb, lb):
    K = ref_kaug(X, levels, X, levels, hp) + np.diag(hp.noise[levels])
    ka, kb = ref_kaug(X, levels, Xa, la, hp), ref_kaug(X, levels, Xb, lb, hp)
    same = ref_same(Xa, la, Xb, lb)
    return (
        ref_kaug(Xa, la, Xb, lb, hp) + same * hp.noise[la][:, None] - ka.T @ np.linalg.solve(K, kb)
    )


def test_fit_subset_is_a_level_stratified_sample_drawn_only_when_needed():
    from bams_cli.core.gp.fit import fit_subset

    levels = np.r_[np.zeros(700, np.int64), np.ones(290, np.int64), np.full(10, 2)]
    rng = np.random.default_rng(0)
    assert fit_subset(levels, 3, 1000, rng) is None and fit_subset(levels, 3, None, rng) is None
    assert rng.random() == np.random.default_rng(0).random()  # nothing drawn
    sub = fit_subset(levels, 3, 300, np.random.default_rng(1))
    counts = np.bincount(levels[sub], minlength=3)
    # 300 split 700:290:10 -> 210, 87, 3, and the 10-per-level floor lifts the last to 10.
    assert counts.tolist() == [210, 87, 10]
    assert np.all(np.diff(sub) > 0)  # sorted, no repeats
    again = fit_subset(levels, 3, 300, np.random.default_rng(1))
    assert np.array_equal(sub, again)


def test_hyperparameters_from_a_subset_and_the_model_conditions_on_every_observation():
    rng = np.random.default_rng(3)
    n = 240
    X = rng.uniform(size=(n, 2))
    levels = (rng.random(n) < 0.5).astype(np.int64)
    f = np.sin(6 * X[:, 0]) + X[:, 1]
    y = f + levels * 0.1 + 0.01 * rng.normal(size=n)
    model = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0), restarts=2, max_fit=80)
    assert model.fitted_on == 80 and model.n_obs_per_level.sum() == n
    # Conditioned on all 240: it reproduces the observations the search never saw, to
    # within the noise, exactly as a model given the same hyperparameters and all the data.
    full = MFGP(X, levels, y, 2, model.hyperparameters)
    mu, var = model.predict_theta0(X)
    mu_ref, var_ref = full.predict_theta0(X)
    assert np.allclose(mu, mu_ref) and np.allclose(var, var_ref)
    at0 = levels == 0
    assert np.sqrt(np.mean((mu[at0] - y[at0]) ** 2)) < 0.05
    # A subset model and the all-data MAP model agree on the function to a small share of
    # its spread.
    exact = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0), restarts=2, max_fit=None)
    assert exact.fitted_on == n
    grid = rng.uniform(size=(500, 2))
    m_sub, _ = model.predict_theta0(grid)
    m_all, _ = exact.predict_theta0(grid)
    assert np.sqrt(np.mean((m_sub - m_all) ** 2)) < 0.05 * np.std(m_all)


def test_score_of_a_large_threaded_model_equals_a_dense_scipy_posterior():
    """From 2,000 observations the training covariance is built by the compiled kernel in
    place and factorised with every BLAS thread; score's pool block comes from the compiled
    cross kernel. Reference: the covariance from scipy's cdist and GPML eq. 4.17, scipy's
    Cholesky, GPML Alg. 2.1, at new points and at observed ones (sd near 0 there: the
    noise is small, as fitted level-0 noise usually is)."""
    from scipy.linalg import cho_factor, cho_solve
    from scipy.spatial.distance import cdist

    rng = np.random.default_rng(21)
    d, n_levels, n = 12, 3, 2100
    X = rng.normal(size=(n, d))
    levels = rng.integers(0, n_levels, n)
    X[n // 2 :: 7] = X[: len(X[n // 2 :: 7])]  # sites observed at two levels or twice
    y = np.sin(X[:, :3]).sum(1) + 0.2 * levels + 0.01 * rng.normal(size=n)
    hp = dataclasses.replace(random_hp(rng, d, n_levels), noise=np.array([1e-4, 1e-3, 1e-3]))
    hp = dataclasses.replace(hp, lengthscales0=rng.uniform(2.0, 6.0, d))
    model = MFGP(X, levels, y, n_levels, hp)

    def k(A, B, ell, s2):
        r = math.sqrt(5) * cdist(A / ell, B / ell)
        return s2 * (1 + r + r**2 / 3) * np.exp(-r)

    K = k(X, X, hp.lengthscales0, hp.outputscale0) + np.diag(hp.noise[levels])
    for lv in range(1, n_levels):
        m = levels == lv
        K[np.ix_(m, m)] += k(X[m], X[m], hp.lengthscales[lv - 1], hp.outputscales[lv - 1])
    c = cho_factor(K, lower=True)
    Xp = np.vstack([rng.normal(size=(300, d)), X[levels == 0][:100]])
    kp = k(Xp, X, hp.lengthscales0, hp.outputscale0)
    mu_ref = hp.mean + kp @ cho_solve(c, y - hp.mean - np.r_[0.0, hp.offsets][levels])
    s2_ref = hp.outputscale0 - np.einsum("ij,ji->i", kp, cho_solve(c, kp.T))
    mu, sd, _ = model.score(Xp, np.array([0.0]), chunk_size=150)  # three chunks
    prior_sd = math.sqrt(hp.outputscale0)
    assert sd[300:].max() < 0.02 * prior_sd  # observed level 0: strong cancellation
    np.testing.assert_allclose(mu, mu_ref, rtol=0, atol=1e-9 * prior_sd)
    np.testing.assert_allclose(sd, np.sqrt(np.maximum(s2_ref, 0)), rtol=0, atol=1e-9 * prior_sd)
    assert model.log_marginal_likelihood == pytest.approx(
        -0.5
        * (y - hp.mean - np.r_[0.0, hp.offsets][levels])
        @ cho_solve(c, y - hp.mean - np.r_[0.0, hp.offsets][levels])
        - np.log(np.diag(c[0])).sum()
        - 0.5 * n * math.log(2 * math.pi),
        rel=1e-10,
    )


# ------------------------------------------------------- discrepancy prior from pairs


def pair_variances(X, levels, y, n_levels):
    """(pairs, unbiased variance of y_l - y_0 over them) per cheap level, from the pairs'
    moments the discrepancy prior is built from."""
    from bams_cli.core.gp.priors import pair_moments, paired_differences

    seg = np.unique(X, axis=0, return_inverse=True)[1].ravel()
    out = []
    for lv in range(1, n_levels):
        d = paired_differences(seg, levels, y, lv)
        mom = pair_moments(X, levels, y, n_levels)[lv - 1]
        out.append((d.size, math.nan if mom is None else mom[0] - 2 * mom[2] + mom[1]))
    return out


def test_pair_variances_equal_a_brute_force_count():
    """Pairs are inputs seen at level 0 and at the cheap level, repeats averaged first."""
    rng = np.random.default_rng(7)
    sites = rng.normal(size=(9, 3))
    which = rng.integers(0, 9, size=60)
    levels = rng.integers(0, 3, size=60)
    X, y = sites[which], rng.normal(size=60)
    got = pair_variances(X, levels, y, 3)
    for lv in (1, 2):
        diffs = []
        for s in range(9):
            a = y[(which == s) & (levels == 0)]
            b = y[(which == s) & (levels == lv)]
            if a.size and b.size:
                diffs.append(b.mean() - a.mean())
        assert got[lv - 1][0] == len(diffs)
        assert got[lv - 1][1] == pytest.approx(np.var(diffs, ddof=1), rel=1e-12)


def test_discrepancy_prior_mode_follows_the_pairs_only_when_they_show_more():
    """Mode at the pairs' variance (standardised) from MIN_PAIRS pairs on, never below the
    spec's mode, and not at all with ``discrepancy_from_pairs`` off."""
    from bams_cli.core.gp import DEFAULT_PRIORS, PriorSpec
    from bams_cli.core.gp.priors import MIN_PAIRS, with_pair_modes

    rng = np.random.default_rng(1)
    U = rng.normal(size=(8, 2))
    d = np.array([0.9, -0.4, 0.3, -1.1, 0.6, 0.0, 0.8, -0.2])
    f = rng.normal(size=8)

    def disc_mode(k, scale=1.0, spec=None):
        X = np.vstack([U, U[:k]])
        levels = np.r_[np.zeros(8, int), np.ones(k, int)]
        y = np.r_[f, f[:k] + scale * d[:k]]
        return np.exp(_Priors.for_data(X, 2, with_pair_modes(spec, X, levels, y, 2)).mode[1])

    assert disc_mode(8) == pytest.approx(np.var(d, ddof=1), rel=1e-9)
    assert disc_mode(MIN_PAIRS) == pytest.approx(np.var(d[:MIN_PAIRS], ddof=1), rel=1e-9)
    floor = DEFAULT_PRIORS.discrepancy[0]
    assert disc_mode(MIN_PAIRS - 1) == pytest.approx(floor, rel=1e-9)
    assert disc_mode(8, scale=0.01) == pytest.approx(floor, rel=1e-9)
    off = PriorSpec(discrepancy_from_pairs=False)
    assert disc_mode(8, spec=off) == pytest.approx(floor, rel=1e-9)


def weak_cheap_level(seed, d=12, n_pairs=5):
    """f1 = f0 + 0.8 x an independent function as smooth as f0: corr(f0, f1) ~ 0.75.

    7 level-0 runs (n_pairs of them also run cheap) and 80 cheap-only runs in 12-d, the
    shape of a discovery loop's data after three batches.
    """
    rng = np.random.default_rng(seed)
    w0, w1 = rng.normal(size=(2, d))
    b0, b1 = rng.uniform(0, 2 * np.pi, size=2)

    def f0(X):
        return np.sin(X @ w0 / 2 + b0)

    def f1(X):
        return f0(X) + 0.8 * np.sin(X @ w1 / 2 + b1)

    X0 = rng.normal(size=(7, d))
    Xc = rng.normal(size=(80, d))
    X = np.vstack([X0, X0[:n_pairs], Xc])
    levels = np.r_[np.zeros(7, int), np.ones(n_pairs + 80, int)]
    y = np.r_[f0(X0), f1(X0[:n_pairs]), f1(Xc)] + 0.01 * rng.normal(size=levels.size)
    Xt = rng.normal(size=(4000, d))

    def true_sd(rho=1.0):
        """sd(f1 - rho f0) over the inputs' distribution."""
        return float(np.std(f1(Xt) - rho * f0(Xt)))

    return X, levels, y, true_sd


def test_a_weak_cheap_level_is_not_trusted_beyond_what_its_pairs_show():
    """Over 8 seeds the fitted sd of y1 - y0 is unbiased for the true sd(f1 - f0): their
    geometric mean ratio within 1.33x of 1, every seed within 2.5x. With the discrepancy
    prior held at its fixed mode (``discrepancy_from_pairs=False``) the geometric mean is
    0.60: the cheap level looks twice as good as it is, as the suite's weak_cheap
    did (on average 0.69 of the truth, seeds down to 0.48; docs/suite/evidence.md)."""
    from bams_cli.core.gp.checks import fitted_discrepancy_sd

    log_ratio = []
    for seed in range(8):
        X, levels, y, true_sd = weak_cheap_level(seed)
        hp = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(seed)).hyperparameters
        log_ratio.append(math.log(fitted_discrepancy_sd(hp) / true_sd(hp.scales[0])))
    ratios = np.round(np.exp(log_ratio), 2)
    assert abs(np.mean(log_ratio)) < math.log(1.33), ratios
    assert np.all(np.abs(log_ratio) < math.log(2.5)), ratios


def test_the_reported_log_posterior_is_the_map_objective_under_the_pairs_prior():
    """On a study with pairs and a metric far from unit scale, ``log_posterior`` is the
    negative MAP objective (natural units) built with the pairs' discrepancy mode, which
    is the standardised pairs' variance: the fit and the model use one prior."""
    from bams_cli.core.gp.priors import with_pair_modes

    X, levels, y0, _ = weak_cheap_level(3)
    y = 40.0 * y0 + 7.0
    model = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0), restarts=3)
    ybar, ystd = standardise(y)
    ys = (y - ybar) / ystd
    [(k, v)] = pair_variances(X, levels, ys, 2)
    assert k == 5 and v > 0.05
    assert model.priors.discrepancy_modes == pytest.approx((v,), rel=1e-12)
    priors = _Priors.for_data(X, 2, with_pair_modes(None, X, levels, ys, 2))
    objective = _MAPObjective(X, levels, ys, 2, priors)
    theta = standardised_theta(model.hyperparameters, ystd)
    assert model.log_posterior == pytest.approx(-objective(theta)[0] - len(y) * math.log(ystd))


def test_a_model_on_a_conditioning_subset_keeps_the_modes_of_every_pair():
    """The conditioning subset keeps level 0 first and few of the cheap runs, so few
    pairs; the model still scores its log posterior under the modes of all of them."""
    from bams_cli.core.conditioning_budget import BYTES_PER_ENTRY
    from bams_cli.core.gp.fit import condition
    from bams_cli.core.gp.priors import with_pair_modes

    X, levels, y, _ = weak_cheap_level(1)
    ybar, ystd = standardise(y)
    full = with_pair_modes(None, X, levels, (y - ybar) / ystd, 2).discrepancy_modes
    hp = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0), restarts=2).hyperparameters
    small = condition(X, levels, y, 2, hp, max_memory=BYTES_PER_ENTRY * 9 * 9)
    assert small.conditioning["method"] == "exact_subset"
    assert small.priors.discrepancy_modes == full
    rows = small.conditioned_rows
    ys, ss = standardise(y[rows])
    own = with_pair_modes(None, X[rows], levels[rows], (y[rows] - ys) / ss, 2)
    assert own.discrepancy_modes != full  # the subset alone would have given another prior


def test_three_levels_get_their_own_pair_modes():
    """Level 1 close to level 0, level 2 far: each cheap level's mode is its own pairs'."""
    from bams_cli.core.gp.priors import with_pair_modes

    rng = np.random.default_rng(4)
    U = rng.normal(size=(6, 2))
    f = rng.normal(size=6)
    X = np.vstack([U, U, U])
    levels = np.repeat([0, 1, 2], 6)
    d1, d2 = 0.02 * rng.normal(size=6), 0.9 * rng.normal(size=6)
    y = np.r_[f, f + d1, f + d2]
    spec = with_pair_modes(None, X, levels, y, 3)
    assert spec.discrepancy_modes[0] == pytest.approx(0.01)  # below the floor
    assert spec.discrepancy_modes[1] == pytest.approx(np.var(d2, ddof=1), rel=1e-9)
    mode = np.exp(_Priors.for_data(X, 3, spec).mode[1:3])
    np.testing.assert_allclose(mode, spec.discrepancy_modes, rtol=1e-9)
    assert with_pair_modes(spec, X[:1], levels[:1], y[:1], 3) is spec  # resolved once
