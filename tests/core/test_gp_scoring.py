"""Scoring a pool within a flop budget (``MFGP.score(max_work=...)``) against exact scoring.

A million segments against the 12,000 level-0 runs of an estimate stage took ``fit`` over
an hour, nearly all of it the sds' triangular solves (m n^2 flops). Within the budget the
mean stays exact, every sd is an upper bound of the exact one, and the sd is exact where a
threshold is near; p_n elsewhere is 0 or 1 within 1e-17 either way.
"""

from __future__ import annotations

import numpy as np
import pytest

from bams_cli import defaults
from bams_cli.core.gp import MFGP, Hyperparameters
from bams_cli.core.gp.fit import conditioning_subset

N_OBS, M = 800, 4000


@pytest.fixture(scope="module")
def scored():
    rng = np.random.default_rng(7)
    d = 2
    X = rng.uniform(-3, 3, size=(N_OBS, d))
    levels = (rng.uniform(size=N_OBS) < 0.4).astype(np.int64)  # 60% level 0
    y = np.sin(X).sum(1) + 0.4 * levels + 0.05 * rng.normal(size=N_OBS)
    hp = Hyperparameters(
        mean=0.0,
        outputscale0=1.0,
        lengthscales0=np.array([0.8, 1.1]),
        outputscales=np.array([0.1]),
        lengthscales=np.array([[1.5, 1.5]]),
        noise=np.array([1e-3, 1e-2]),
        offsets=np.array([0.4]),
    )
    model = MFGP(X, levels, y, 2, hp)
    pool = rng.uniform(-3.5, 3.5, size=(M, d))
    gammas = np.array([-1.2, -0.6])
    exact = model.score(pool, gammas)
    assert model.scoring["method"] == "exact"
    return model, pool, gammas, exact


def test_within_budget_the_mean_is_exact_and_every_sd_an_upper_bound(scored):
    model, pool, gammas, (mu0, sd0, p0) = scored
    mu, sd, p = model.score(pool, gammas, max_work=1.5e9)  # exact: M n^2 = 2.6e9
    s = model.scoring
    assert s["method"] == "bounded"
    assert s["bound_observations"] == 500  # isqrt(1.5e9 / 8 / 4000) = 216, at least 500
    np.testing.assert_allclose(mu, mu0, rtol=0, atol=1e-10)
    assert np.all(sd >= sd0 - 1e-9)
    assert np.any(sd > sd0 * 1.5)  # a real bound, not the exact sd everywhere
    # the rest of the budget: (1.5e9 - 500^2 M) // n^2 rows of exact sd
    assert s["exact_sd_rows"] == int((1.5e9 - 500**2 * M) // N_OBS**2) == 781
    assert s["near_thresholds"] > s["exact_sd_rows"]  # some near rows kept the bound


def test_the_exact_sds_go_to_the_rows_nearest_a_threshold(scored):
    model, pool, gammas, (mu0, sd0, p0) = scored
    mu, sd, p = model.score(pool, gammas, max_work=1.5e9)
    # the bound by hand: the same GP on the 500 observations conditioning_subset picks
    rows = conditioning_subset(model.levels_train, 2, 500)
    bound = MFGP(
        model.X_train[rows], model.levels_train[rows], model.y_train[rows], 2,
        model.hyperparameters,
    )  # fmt: skip
    _, sd_b, _ = bound.score(pool, gammas)
    z = np.min(np.abs(gammas[None, :] - mu0[:, None]), axis=1) / sd_b
    refined = np.zeros(M, dtype=bool)
    refined[np.argsort(z, kind="stable")[: model.scoring["exact_sd_rows"]]] = True
    np.testing.assert_allclose(sd[refined], sd0[refined], rtol=1e-9)
    np.testing.assert_allclose(sd[~refined], sd_b[~refined], rtol=1e-9)
    np.testing.assert_allclose(p[refined], p0[refined], rtol=0, atol=1e-12)
    far = z >= defaults.SCORE_DECIDED_Z
    assert far.sum() > M / 3
    # far from every threshold p_n is 0 or 1 to 1e-17 with either sd
    assert np.max(np.abs(p[far] - p0[far])) < 1e-15
    assert set(np.unique(np.round(p0[far]))) <= {0.0, 1.0}


def test_a_budget_that_covers_every_near_row_gives_the_exact_failure_probabilities(scored):
    model, pool, _, _ = scored
    rare = np.array([-1.8])  # few segments near it
    mu0, _, p0 = model.score(pool, rare)
    mu, _, p = model.score(pool, rare, max_work=2.0e9)
    s = model.scoring
    assert s["method"] == "bounded" and 0 < s["exact_sd_rows"] == s["near_thresholds"] < M
    np.testing.assert_allclose(p, p0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(mu, mu0, rtol=0, atol=1e-10)


def test_a_bound_sd_only_leans_p_n_toward_one_half_by_at_most_what_scoring_says(scored):
    # The exact sd is never above the bound, so the exact p_n is on the same side of 1/2
    # and further out: a kept row moves p_n toward 1/2 (up where mu is above gamma, down
    # below it) by at most min(p, 1 - p), and scoring's kept_bound_error sums that.
    model, pool, gammas, (mu0, sd0, p0) = scored
    _, _, p = model.score(pool, gammas, max_work=1.5e9)
    assert np.all(np.sign(p - 0.5) * np.sign(p0 - 0.5) >= 0)
    assert np.all(np.abs(p - 0.5) <= np.abs(p0 - 0.5) + 1e-15)
    moved = np.abs(p.sum(axis=0) - p0.sum(axis=0))
    bound = np.array(model.scoring["kept_bound_error"])
    assert np.all(moved <= bound * (1 + 1e-9)) and np.all(moved > 0)
    below = mu0 < gammas[0]  # predicted to fail: the bound lowers p_n there
    assert np.any(p[below, 0] < p0[below, 0] - 1e-6)


def test_the_bound_carries_the_jitter_the_exact_factor_needed():
    # Level-0 noise 0 (allowed by --fixed-hyperparameters) and repeated segments: the exact
    # model's factorisation adds jitter to every observation. A bound built without it
    # conditioned on less noisy data: its sd fell below the exact one on 88 of 100 rows
    # (up to 1.9x), and a row 9 bound-sds from gamma got p_n 1.0 against 0.9999985.
    rng = np.random.default_rng(1)
    X0 = rng.uniform(-3, 3, (600, 2))
    X = np.vstack([X0, X0[:100], rng.uniform(-3, 3, (300, 2))])
    levels = np.r_[np.zeros(700, np.int64), np.ones(300, np.int64)]
    y = np.sin(X).sum(1) + 0.3 * levels
    hp = Hyperparameters(
        mean=0.0, outputscale0=1.0, lengthscales0=np.array([0.8, 1.1]),
        outputscales=np.array([9.0]), lengthscales=np.array([[1.5, 1.5]]),
        noise=np.array([0.0, 1e-2]), offsets=np.array([0.3]),
    )  # fmt: skip
    model = MFGP(X, levels, y, 2, hp)
    assert model.jitter > 0
    pool = X0[:100].copy()
    _, sd0, _ = model.score(pool, [0.0])
    _, sd, _ = model.score(pool, [0.0], max_work=1.01 * 500**2 * len(pool))
    assert model.scoring["method"] == "bounded" and model.scoring["exact_sd_rows"] == 0
    # variances of ~1e-10 out of an outputscale of 1: equal up to the subtraction's rounding
    assert np.all(sd**2 >= sd0**2 - 1e-13)
    assert np.min(sd / sd0) > 0.999


def test_a_budget_the_bound_alone_would_exhaust_scores_exactly(scored):
    model, pool, gammas, (mu0, sd0, p0) = scored
    mu, sd, p = model.score(pool, gammas, max_work=500**2 * M)  # the bound costs it all
    assert model.scoring["method"] == "exact"
    np.testing.assert_array_equal(sd, sd0)


def test_select_within_a_budget_picks_as_the_exact_posterior_does(scored):
    """select_batch past ``max_work``: the pool's sds bounded where gamma is decided, J's
    pool-wide conditioning on the other rows only. The rows that decide the picks keep
    their exact sds, so the batch is the exact one and J moves by < 1e-17 a row."""
    from bams_cli.core.select import select_batch

    model, pool, gammas, _ = scored
    kw = dict(gamma=-1.2, costs=[1.0, 0.1], budget=3.0, n_clusters=3, overbudget=2.0)
    exact = select_batch(model, pool, rng=np.random.default_rng(3), max_work=None, **kw)
    bounded = select_batch(model, pool, rng=np.random.default_rng(3), max_work=2e9, **kw)
    assert exact.plan["pool_sds"] == {"method": "exact", "rows": M}
    s = bounded.plan["pool_sds"]
    assert s["method"] == "bounded" and s["exact_sd_rows"] == s["near_thresholds"] < M / 2
    np.testing.assert_array_equal(bounded.index, exact.index)
    np.testing.assert_array_equal(bounded.level, exact.level)
    np.testing.assert_allclose(bounded.delta_j, exact.delta_j, rtol=1e-9, atol=1e-17 * M)
    assert exact.j_after < exact.j_before  # a batch that teaches something
    assert abs(bounded.j_before - exact.j_before) < 1e-17
    assert abs(bounded.j_after - exact.j_after) < 1e-17


def test_nearest_conditions_on_the_observations_closest_to_the_points(scored):
    """``MFGP.nearest``: the k observations nearest the points (level 0's lengthscales, by
    brute force here), the same hyperparameters and noise; sds never below the full GP's."""
    model, pool, _, (mu0, sd0, _) = scored
    region = pool[(pool[:, 0] > 1.5) & (pool[:, 1] < -1.0)]
    local = model.nearest(region, 150)
    ell = model.hyperparameters.lengthscales0
    d = np.sqrt((((model.X_train[:, None, :] - region[None]) / ell) ** 2).sum(-1)).min(axis=1)
    want = np.sort(np.argsort(d, kind="stable")[:150])
    np.testing.assert_array_equal(local.X_train, model.X_train[want])
    np.testing.assert_array_equal(local.y_train, model.y_train[want])
    assert local.hyperparameters == model.hyperparameters  # no jitter was needed here
    mu_f, s2_f = model.predict_theta0(region)
    mu_l, s2_l = local.predict_theta0(region)
    assert np.all(s2_l >= s2_f - 1e-12)
    # near its region the local GP is close to the whole one, far from it it is not
    assert np.median(np.sqrt(s2_l / s2_f)) < 1.01 and np.median(np.abs(mu_l - mu_f)) < 0.01
    far = pool[(pool[:, 0] < -2.0) & (pool[:, 1] > 2.0)]
    assert np.median(np.sqrt(local.predict_theta0(far)[1] / model.predict_theta0(far)[1])) > 3
    assert model.nearest(region, N_OBS) is model


def test_select_past_local_obs_runs_each_cluster_on_its_nearest_observations(scored):
    """The approximate plan's greedies on a local GP (``local_obs``): J decreases by as much,
    measured with the whole posterior, as the greedies on the whole GP."""
    from bams_cli.core.acquisition import margin, point_variance
    from bams_cli.core.select import _j_given, select_batch

    model, pool, _, _ = scored
    kw = dict(
        gamma=-1.2, costs=[1.0, 0.1], budget=4.0, n_clusters=4, overbudget=2.0,
        approximate="always", max_work=1.0,  # exact sds; every screen "out of reach"
    )  # fmt: skip
    whole = select_batch(model, pool, rng=np.random.default_rng(3), local_obs=None, **kw)
    local = select_batch(model, pool, rng=np.random.default_rng(3), local_obs=300, **kw)
    assert whole.plan["local_observations"] is None and local.plan["local_observations"] == 300
    mu, sigma2 = model.predict_theta0(pool)
    s = margin(mu, sigma2, -1.2)
    j0 = float(point_variance(s).mean())
    drop = {
        name: j0 - _j_given(model, pool, s, sigma2, r.index, r.level)
        for name, r in (("whole", whole), ("local", local))
    }
    assert drop["whole"] > 0 and drop["local"] >= 0.95 * drop["whole"], drop


def _dense_reference(model):
    """The model's prior k_aug, written with scikit-learn's Matern-5/2, and the Cholesky
    factor of its observations' covariance (noise and jitter on the diagonal)."""
    from scipy.linalg import cho_factor
    from sklearn.gaussian_process.kernels import Matern

    hp = model.hyperparameters

    def k_aug(A, la, B, lb):
        k = hp.outputscale0 * Matern(hp.lengthscales0, nu=2.5)(A, B)
        k1 = hp.outputscales[0] * Matern(hp.lengthscales[0], nu=2.5)(A, B)
        return k + ((la[:, None] == 1) & (lb[None, :] == 1)) * k1

    Xn, ln = model.X_train, model.levels_train
    K = k_aug(Xn, ln, Xn, ln)
    K[np.diag_indices_from(K)] += hp.noise[ln] + model.jitter
    return k_aug, cho_factor(K)


def test_cov_theta0_obs_to_solves_the_columns_once_and_answers_as_cov_theta0_obs(scored):
    """``MFGP.cov_theta0_obs_to``: the same covariances, block after block, as
    ``cov_theta0_obs`` (its many-rows path, to the bit), and as the definition
    k0(x, x_c) - k(x, X_n) K^-1 k_aug(Y_n, c) computed with a dense solve."""
    from scipy.linalg import cho_solve

    model, pool, _, _ = scored
    rng = np.random.default_rng(11)
    cols = pool[rng.choice(M, 40, replace=False)]
    lev = rng.integers(0, 2, 40)
    cov = model.cov_theta0_obs_to(cols, lev)
    assert cov is not None
    for block in (pool[:900], pool[900:2000]):
        np.testing.assert_array_equal(cov(block), model.cov_theta0_obs(block, cols, lev))
    # the definition, densely, with scikit-learn's Matern-5/2 as the prior covariances
    k_aug, Kf = _dense_reference(model)
    Xn, ln = model.X_train, model.levels_train
    x = pool[:300]
    z = np.zeros(len(x), np.int64)
    want = k_aug(x, z, cols, lev) - k_aug(x, z, Xn, ln) @ cho_solve(Kf, k_aug(Xn, ln, cols, lev))
    np.testing.assert_allclose(cov(x), want, atol=1e-9)
    # more columns than observations: still solved once, the same covariances
    many, lev_many = pool[: N_OBS + 50], np.zeros(N_OBS + 50, np.int64)
    x = pool[-200:]
    np.testing.assert_allclose(
        model.cov_theta0_obs_to(many, lev_many)(x),
        model.cov_theta0_obs(x, many, lev_many),
        atol=1e-10,
    )


def test_solved_rows_answer_as_cov_theta0_obs_and_cov_obs_obs(scored):
    """``MFGP.cov_obs_obs_from``, at level 0 the rows' cov_n(theta0, y): the data term solved
    once, then the same covariances as ``cov_theta0_obs`` / ``cov_obs_obs`` for block after
    block of columns at both levels, and as the definitions computed with a dense solve
    (scikit-learn's Matern-5/2 as the prior covariances); None for a localised view."""
    from scipy.linalg import cho_solve

    model, pool, _, _ = scored
    rng = np.random.default_rng(12)
    rows = pool[rng.choice(M, 60, replace=False)]
    lev_rows = rng.integers(0, 2, 60)
    theta0 = model.cov_obs_obs_from(rows, np.zeros(60, np.int64))
    obs = model.cov_obs_obs_from(rows, lev_rows)
    assert theta0 is not None and obs is not None
    k_aug, Kf = _dense_reference(model)
    Xn, ln = model.X_train, model.levels_train
    zeros = np.zeros(60, np.int64)
    for cols in (pool[:500], pool[500:1700]):
        lev = rng.integers(0, 2, len(cols))
        none_same = np.zeros((60, len(cols)), dtype=bool)
        np.testing.assert_allclose(
            theta0(cols, lev), model.cov_theta0_obs(rows, cols, lev), rtol=0, atol=1e-10
        )
        np.testing.assert_allclose(
            obs(cols, lev),
            model.cov_obs_obs(rows, lev_rows, cols, lev, same=none_same),
            rtol=0,
            atol=1e-10,
        )
        want0 = k_aug(rows, zeros, cols, lev) - k_aug(rows, zeros, Xn, ln) @ cho_solve(
            Kf, k_aug(Xn, ln, cols, lev)
        )
        want = k_aug(rows, lev_rows, cols, lev) - k_aug(rows, lev_rows, Xn, ln) @ cho_solve(
            Kf, k_aug(Xn, ln, cols, lev)
        )
        np.testing.assert_allclose(theta0(cols, lev), want0, atol=1e-9)
        np.testing.assert_allclose(obs(cols, lev), want, atol=1e-9)
        # the level-1 rows differ from theta0's: the discrepancy's covariance enters
        assert np.abs(want - want0).max() > 1e-3
    local = model.localised(pool[:200], 2**30)
    assert local is not model
    assert local.cov_obs_obs_from(rows, lev_rows) is None


def test_a_set_of_pairs_against_itself_is_its_covariance_from_one_factor(scored):
    """``cov_obs_obs(A, A)`` (one factor, reused) is the covariance the two-factor path
    gives for the same pairs in another column order, and the dense definition (noise
    on the diagonal, repeated points at both levels)."""
    from scipy.linalg import cho_solve

    model, pool, _, _ = scored
    rng = np.random.default_rng(13)
    A = np.vstack([pool[rng.choice(M, 70, replace=False)], pool[:5]])
    la = np.r_[rng.integers(0, 2, 70), np.ones(5, np.int64)]
    A = np.vstack([A, pool[:5]])  # the same 5 points again, at level 0
    la = np.r_[la, np.zeros(5, np.int64)]
    same = np.eye(len(A), dtype=bool)
    S = model.cov_obs_obs(A, la, A, la, same=same)
    r = rng.permutation(len(A))
    np.testing.assert_allclose(
        S[:, r], model.cov_obs_obs(A, la, A[r], la[r], same=same[:, r]), rtol=0, atol=1e-12
    )
    k_aug, Kf = _dense_reference(model)
    Xn, ln = model.X_train, model.levels_train
    want = k_aug(A, la, A, la) - k_aug(A, la, Xn, ln) @ cho_solve(Kf, k_aug(Xn, ln, A, la))
    want[np.diag_indices_from(want)] += model.hyperparameters.noise[la]
    np.testing.assert_allclose(S, want, atol=1e-9)


def test_j_given_by_cluster_is_each_cluster_on_its_own_pairs_and_bounds_the_joint_j(scored):
    """``_j_given(labels=)``: every cluster's rows conditioned on that cluster's pairs only
    (brute force: one ``_j_given`` per cluster's pairs, its rows kept), never below the J
    conditioned on every pair jointly; one cluster is the joint J itself."""
    from bams_cli.core.acquisition import beta, margin
    from bams_cli.core.select import _j_by_cluster, _j_given, batch_variance

    model, pool, _, _ = scored
    mu, sigma2 = model.predict_theta0(pool)
    s = margin(mu, sigma2, -1.2)
    rng = np.random.default_rng(5)
    # four quadrants and a fifth cluster (a strip at x0 > 3) that holds no pair
    labels = (pool[:, 0] > 0).astype(np.int64) + 2 * (pool[:, 1] > 0)
    labels[pool[:, 0] > 3.0] = 4
    index = rng.choice(np.flatnonzero(labels < 4), 60, replace=False)
    level = rng.integers(0, 2, 60)
    z = defaults.SCORE_DECIDED_Z

    def brute(decided_z):
        t = np.ones(M)  # cluster 4's rows, and decided rows, keep beta(s, 1) = h_n
        for k in range(4):
            rows = np.flatnonzero(labels == k)
            if decided_z is not None:
                rows = rows[np.abs(s[rows]) < decided_z]
            mine = labels[index] == k
            after = batch_variance(model, pool, sigma2, index[mine], level[mine], at=rows)
            t[rows] = after / sigma2[rows]
        return float(beta(s, t).mean())

    assert np.count_nonzero(labels == 4) > 100
    assert 0 < np.count_nonzero(np.abs(s) >= z) < M  # some rows decided, some not
    joint = _j_given(model, pool, s, sigma2, index, level)
    split = _j_given(model, pool, s, sigma2, index, level, labels=labels)
    assert split == pytest.approx(brute(None), rel=1e-12)
    assert split > joint * (1 + 1e-6)  # pairs across the borders taught each other's rows
    same = _j_given(model, pool, s, sigma2, index, level, labels=np.zeros(M, np.int64))
    assert same == pytest.approx(joint, rel=1e-12)
    # decided rows keep h_n, by cluster as jointly
    decided = _j_given(model, pool, s, sigma2, index, level, z, labels)
    assert decided == pytest.approx(brute(z), rel=1e-12)
    assert decided >= _j_given(model, pool, s, sigma2, index, level, z)
    # the choice: rows x pairs x (n + pairs) against the budget
    assert _j_by_cluster(model, s, 60, None, max_work=M * 60 * (N_OBS + 60) - 1)
    assert not _j_by_cluster(model, s, 60, None, max_work=M * 60 * (N_OBS + 60))
    assert not _j_by_cluster(model, s, 60, None, max_work=None)


def test_select_with_many_pending_pairs_conditions_j_by_cluster_past_the_budget(scored):
    """Thousands of pending pairs (an estimate stage's picks) past ``max_work``: the same
    picks as the joint conditioning (the greedies condition on their own cluster's pending
    pairs either way), J before and after from cluster-by-cluster conditioning, each at
    least the joint one, and the plan says so."""
    from bams_cli.core.acquisition import margin, point_variance
    from bams_cli.core.select import select_batch

    model, pool, _, _ = scored
    rng = np.random.default_rng(9)
    pend = np.zeros((M, 2), bool)
    pend[rng.choice(M, 1000, replace=False), 0] = True
    kw = dict(
        gamma=-1.2, costs=[1.0, 0.1], budget=3.0, n_clusters=4, overbudget=2.0,
        pending_pairs=pend,
    )  # fmt: skip
    # sds exact (M n^2 = 2.6e9 is under it), J's joint conditioning M G (n + G) 7.5e9 not
    joint = select_batch(model, pool, rng=np.random.default_rng(3), max_work=None, **kw)
    split = select_batch(model, pool, rng=np.random.default_rng(3), max_work=2.7e9, **kw)
    assert split.plan["pool_sds"]["method"] == "exact"
    assert not joint.plan["j_by_cluster"] and split.plan["j_by_cluster"]
    np.testing.assert_array_equal(split.index, joint.index)
    np.testing.assert_array_equal(split.level, joint.level)
    assert split.j_before > joint.j_before * (1 + 1e-6)
    assert split.j_after > joint.j_after * (1 + 1e-6)
    assert split.j_after < split.j_before
    # the bound still conditions on the pending pairs: below J given nothing pending
    mu, sigma2 = model.predict_theta0(pool)
    h_n = float(point_variance(margin(mu, sigma2, -1.2)).mean())
    assert split.j_before < 0.95 * h_n


def test_j_by_cluster_is_decided_on_the_picks_the_batch_made(scored):
    """Nothing pending: J is conditioned by cluster only when the batch's own picks are
    past the budget, not when the most picks the budget could buy would be (7 at level 1's
    cost 0.7, where the batch mixed levels and made 5)."""
    from bams_cli.core.select import select_batch

    model, pool, _, _ = scored
    kw = dict(gamma=-1.2, costs=[1.0, 0.7], budget=5.0, n_clusters=4)
    exact = select_batch(model, pool, rng=np.random.default_rng(3), max_work=None, **kw)
    made = len(exact.index)
    assert made == 5 and set(exact.level) == {0, 1}
    work = M * made * (N_OBS + made)  # 1.6e7 flops; 7 picks would be 2.3e7
    under = select_batch(model, pool, rng=np.random.default_rng(3), max_work=work, **kw)
    over = select_batch(model, pool, rng=np.random.default_rng(3), max_work=work - 1, **kw)
    for r in (under, over):
        assert r.plan["pool_sds"]["method"] == "exact"
        np.testing.assert_array_equal(r.index, exact.index)
    assert not under.plan["j_by_cluster"] and over.plan["j_by_cluster"]
    assert under.j_after == pytest.approx(exact.j_after, rel=1e-12)
    assert over.j_after > exact.j_after * (1 + 1e-6)
    assert under.j_before == over.j_before == exact.j_before  # nothing pending: h_n


@pytest.mark.parametrize("whitening", ["cholesky", "eigh"])
def test_j_before_and_after_from_one_conditioning_equal_each_conditioned_alone(
    scored, whitening, monkeypatch
):
    """``_j_nested``: J given B's first pairs (the pending ones) and J given all of B, from
    one conditioning on B (Cholesky whitening is nested), equal ``_j_given`` of each, joint
    and by cluster, with decided rows; through the eigh whitening (a singular Sigma_B) the
    first J is conditioned on its own."""
    import bams_cli.core.select as sel
    from bams_cli.core.acquisition import margin

    model, pool, _, _ = scored
    mu, sigma2 = model.predict_theta0(pool)
    s = margin(mu, sigma2, -1.2)
    rng = np.random.default_rng(12)
    labels = (pool[:, 0] > 0).astype(np.int64) + 2 * (pool[:, 1] > 0)
    # 70 pending pairs outside cluster 3, then 20 picks outside cluster 0: one cluster
    # holds pending pairs only, one picks only
    first = 70
    pending = rng.choice(np.flatnonzero(labels != 3), first, replace=False)
    rest = np.setdiff1d(np.flatnonzero(labels != 0), pending)
    index = np.concatenate([pending, rng.choice(rest, 20, replace=False)])
    level = rng.integers(0, 2, 90)
    if whitening == "eigh":

        def singular(*a, **k):
            raise np.linalg.LinAlgError("as for a repeated noise-free pair")

        monkeypatch.setattr(sel, "cho_factor", singular)
    dz = defaults.SCORE_DECIDED_Z
    for z, by in ((None, None), (dz, None), (None, labels), (dz, labels)):
        before, after = sel._j_nested(model, pool, s, sigma2, index, level, first, z, by)
        assert before == pytest.approx(
            sel._j_given(model, pool, s, sigma2, index[:first], level[:first], z, by), rel=1e-10
        )
        assert after == pytest.approx(
            sel._j_given(model, pool, s, sigma2, index, level, z, by), rel=1e-10
        )
        assert after < before
        # nothing picked: before is after
        both = sel._j_nested(model, pool, s, sigma2, index, level, len(index), z, by)
        assert both[0] == pytest.approx(both[1], rel=1e-12)
        assert both[1] == pytest.approx(after, rel=1e-12)
