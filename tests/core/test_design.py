"""The estimate's design: calibrated risk, its posterior, the design choice, staged estimates.

References: scipy.optimize for the variance-minimising design, numerical integration for the
posterior, Monte Carlo over repeated draws for unbiasedness, variance and coverage.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate, optimize, special, stats

from bams_cli import defaults
from bams_cli.core import design as dz
from bams_cli.core import screen as sc
from bams_cli.core.estimate import estimate_from_sample
from bams_cli.core.evaluate import _capped, staged_trials
from bams_cli.core.sampling import inclusion_probabilities


def _evidence(u: np.ndarray, failed: np.ndarray, pool_u: np.ndarray) -> dz.StageEvidence:
    return dz.StageEvidence(u, failed, dz.risk_norms(pool_u))


def test_calibrated_design_minimises_the_predicted_variance():
    # Brute force: minimise sum r (1 - pi)/pi subject to sum pi = K, 0 < pi <= 1 with SLSQP.
    rng = np.random.default_rng(3)
    r = rng.gamma(0.4, size=9) + 1e-3
    r = r / r.mean()
    K = 3.0
    pi = dz.calibrated_design(r, K=K)
    assert pi.sum() == pytest.approx(K, rel=1e-12)
    res = optimize.minimize(
        lambda x: np.sum(r * (1 - x) / x),
        np.full(r.size, K / r.size),
        method="SLSQP",
        bounds=[(1e-6, 1.0)] * r.size,
        constraints=[{"type": "eq", "fun": lambda x: x.sum() - K}],
        options={"ftol": 1e-14, "maxiter": 500},
    )
    assert res.success
    assert dz.predicted_variance(pi, r) == pytest.approx(res.fun, rel=1e-6)
    np.testing.assert_allclose(pi, res.x, atol=1e-4)


def test_calibrated_design_is_proportional_to_sqrt_risk_below_the_cap():
    r = np.array([0.25, 1.0, 4.0, 16.0])
    pi = dz.calibrated_design(r, K=0.5)
    np.testing.assert_allclose(pi / pi[0], np.sqrt(r / r[0]), rtol=1e-12)


def test_predicted_variance_is_the_ht_variance_when_failures_follow_the_risk():
    # Monte Carlo: failures ~ Bernoulli(p), Poisson sample with pi; Var(T_hat - T) = sum p (1-pi)/pi.
    rng = np.random.default_rng(7)
    n = 40
    p = rng.uniform(0.01, 0.3, n)
    pi = rng.uniform(0.1, 0.9, n)
    reps = 200_000
    fail = rng.random((reps, n)) < p
    take = rng.random((reps, n)) < pi
    err = (fail * take / pi).sum(axis=1) - fail.sum(axis=1)
    assert err.var() == pytest.approx(dz.predicted_variance(pi, p), rel=0.02)


def test_the_prior_alone_before_any_stage_has_results():
    post = dz.risk_posterior([], prior=(2.0, 5.0))
    assert post.lam_mean == pytest.approx(2 / 7, abs=2e-3)
    assert post.lam_quantile(0.9) == pytest.approx(stats.beta(2, 5).ppf(0.9), abs=0.02)
    # tau uniform over the grid
    np.testing.assert_allclose(post.weights.sum(axis=1), 1 / len(dz.TAUS), rtol=1e-9)
    assert post.failures == post.sampled == 0


def test_lam_posterior_matches_numerical_integration():
    # One tau: the posterior mean of lam by quad over the same likelihood and prior.
    rng = np.random.default_rng(11)
    pool = rng.gamma(0.3, size=500)
    pool = pool / pool.mean()
    s = rng.choice(500, 60, replace=False)
    failed = np.zeros(60, bool)
    failed[[0, 5, 9]] = True
    ev = dz.StageEvidence(pool[s], failed, dz.risk_norms(pool, taus=[1.0]))
    post = dz.risk_posterior([ev], prior=(1.5, 2.0), taus=[1.0])
    u = pool[s]

    def density(lam: float) -> float:
        r = (1 - lam) * u + lam
        like = np.prod(r[failed]) / r.sum() ** failed.sum()
        return like * stats.beta(1.5, 2.0).pdf(lam)

    z = integrate.quad(density, 0, 1, limit=200)[0]
    mean = integrate.quad(lambda x: x * density(x), 0, 1, limit=200)[0] / z
    assert post.lam_mean == pytest.approx(mean, abs=5e-3)


def test_failures_where_the_model_is_sure_raise_trust_and_elsewhere_lower_it():
    rng = np.random.default_rng(5)
    pool = rng.gamma(0.2, size=2000)
    pool = pool / pool.mean()
    s = rng.choice(2000, 200, replace=False)
    u = pool[s]
    order = np.argsort(u)
    high = np.zeros(200, bool)
    high[order[-5:]] = True  # failures at the largest u sampled
    low = np.zeros(200, bool)
    low[order[:5]] = True  # failures where the model sees nothing
    prior = dz.risk_posterior([])
    trusted = dz.risk_posterior([_evidence(u, high, pool)])
    doubted = dz.risk_posterior([_evidence(u, low, pool)])
    assert trusted.lam_mean < prior.lam_mean < doubted.lam_mean
    assert doubted.lam_mean > 0.8


def test_lam_is_recovered_from_many_failures():
    # Failures drawn from r = (1 - lam) u + lam: the posterior concentrates near lam.
    rng = np.random.default_rng(2)
    pool = rng.gamma(0.3, size=20_000)
    pool = pool / pool.mean()
    for lam in (0.1, 0.6):
        r = (1 - lam) * pool + lam
        failed = rng.random(pool.size) < 0.02 * r
        post = dz.risk_posterior([_evidence(pool, failed, pool)])
        assert post.lam_mean == pytest.approx(lam, abs=0.08)
        assert post.tau_mean == pytest.approx(1.0, abs=0.3)


def test_posterior_risk_has_mean_one_and_a_floor():
    rng = np.random.default_rng(0)
    p = rng.beta(0.1, 30, 1000)
    post = dz.risk_posterior([])
    r = post.risk(p)
    assert r.mean() == pytest.approx(1.0, rel=1e-9)
    assert r.min() >= post.lam_mean * (1 - 1e-12)


def test_choose_design_takes_uniform_when_the_model_says_nothing():
    choice = dz.choose_design(np.full(100, 0.01), K=10, posterior=dz.risk_posterior([]))
    assert choice.name == "uniform"
    np.testing.assert_allclose(choice.pi, 0.1)
    assert choice.predicted["uniform"] == 1.0


def test_choose_design_predicts_each_candidate_and_takes_the_smallest():
    rng = np.random.default_rng(1)
    p = rng.beta(0.05, 10, 5000)
    choice = dz.choose_design(p, K=100, posterior=dz.risk_posterior([]))
    assert choice.predicted[choice.name] == min(choice.predicted.values())
    assert choice.name == "calibrated" and choice.predicted["calibrated"] < 1.0
    assert choice.pi.sum() == pytest.approx(100, rel=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_choose_design_with_a_presorted_subset_equals_the_plain_call(seed):
    # staged_trials sorts U once and hands each trial's stage 2 the order of U minus stage
    # 1's sample; the choice must be the plain call's, bit for bit.
    rng = np.random.default_rng(seed)
    n = 3000
    p = rng.beta(0.05, 10, n)
    p[:300] = p[300:600]  # ties
    fail = rng.random(n) < p
    order = np.argsort(-p, kind="stable")
    s = rng.choice(n, 150, replace=False)
    u = dz.relative_risk(p)
    post = dz.risk_posterior([dz.StageEvidence(u[s], fail[s], dz.risk_norms(u), p.mean())])
    rest = np.ones(n, bool)
    rest[s] = False
    order2 = (np.cumsum(rest) - 1)[order[rest[order]]]
    for K in (30.0, 300.0, 1500.0):
        plain = dz.choose_design(p[rest], K=K, posterior=post)
        hinted = dz.choose_design(p[rest], K=K, posterior=post, order=order2)
        assert hinted.name == plain.name and hinted.predicted == plain.predicted
        np.testing.assert_array_equal(hinted.pi, plain.pi)
        np.testing.assert_array_equal(hinted.risk, plain.risk)


def _posterior_plain(evidence, prior=(1.0, 1.0), anchor_sd=1.0):
    # risk_posterior's anchored form written out directly: the grids allocated afresh, the
    # log-sum-exp over z with numpy's own exp.
    taus = np.asarray(dz.TAUS)
    lam = dz._LAM_GRID[1:-1]
    a, b = prior
    log_post = np.broadcast_to(
        (a - 1.0) * np.log(lam) + (b - 1.0) * np.log1p(-lam) - special.betaln(a, b),
        (taus.size, lam.size),
    ).copy()
    Z = np.linspace(-6.0, 6.0, 97)
    ll_z = np.zeros((taus.size, lam.size, Z.size))
    for ev in evidence:
        k = int(ev.failed.sum())
        for t, tau in enumerate(taus):
            A = ev.u**tau / ev.norms[t]
            log_rf = (
                np.log((1.0 - lam)[:, None] * A[ev.failed][None, :] + lam[:, None]).sum(axis=1)
                if k
                else np.zeros(lam.size)
            )
            sum_r = (1.0 - lam) * A.sum() + lam * ev.u.size
            c = ev.p_mean * np.exp(Z)
            ll_z[t] += log_rf[:, None] + k * np.log(c)[None, :] - sum_r[:, None] * c[None, :]
    prior_z = -0.5 * ((Z[None, :] + np.log1p(-lam)[:, None]) / anchor_sd) ** 2
    total = ll_z + prior_z[None, :, :]
    top = total.max(axis=2, keepdims=True)
    log_post += top[..., 0] + np.log(np.exp(total - top).sum(axis=2))
    w = np.exp(log_post - log_post.max()) * np.gradient(lam)[None, :]
    return w / w.sum()


@pytest.mark.parametrize("case", ["one stage", "two stages", "no failure", "many failures"])
def test_anchored_posterior_equals_its_plain_form_bit_for_bit(case):
    # risk_posterior sums exp over z in place and writes terms below e^-700 as e^-700 (they
    # vanish beside the row's e^0 = 1); the weights must be the plain form's, bit for bit.
    rng = np.random.default_rng(len(case))
    pool = rng.gamma(0.3, size=4000)
    pool = pool / pool.mean()
    p_mean = 0.004 if case != "many failures" else 0.0001

    def stage(n_s, n_f):
        s = rng.choice(pool.size, n_s, replace=False)
        failed = np.zeros(n_s, bool)
        failed[np.argsort(-pool[s])[:n_f]] = True
        return dz.StageEvidence(pool[s], failed, dz.risk_norms(pool), p_mean=p_mean)

    evidence = {
        "one stage": [stage(200, 3)],
        "two stages": [stage(200, 3), stage(150, 1)],
        "no failure": [stage(300, 0)],
        "many failures": [stage(500, 60)],
    }[case]
    for prior in ((1.0, 1.0), (2.0, 5.0)):
        got = dz.risk_posterior(evidence, prior=prior).weights
        np.testing.assert_array_equal(got, _posterior_plain(evidence, prior=prior))


def _stage(pi, fail, take, *, n_pool, known_failures=0):
    s = np.flatnonzero(take)
    return estimate_from_sample(
        pi[s], fail[s], design="poisson", n_pool=n_pool, n_unknown=pi.size,
        budget=float(pi.sum()), known_failures=known_failures,
    )  # fmt: skip


def test_combine_stages_is_the_weighted_sum_with_weighted_variance():
    rng = np.random.default_rng(4)
    n = 300
    fail = rng.random(n) < 0.05
    pi1 = rng.uniform(0.05, 0.5, n)
    pi2 = rng.uniform(0.05, 0.5, n)
    e1 = _stage(pi1, fail, rng.random(n) < pi1, n_pool=n)
    e2 = _stage(pi2, fail, rng.random(n) < pi2, n_pool=n)
    c = dz.combine_stages([e1, e2], [0.3, 0.7], n_pool=n)
    assert c.p_hat[0] == pytest.approx(0.3 * e1.p_hat[0] + 0.7 * e2.p_hat[0], rel=1e-12)
    assert c.var_hat[0] == pytest.approx(0.09 * e1.var_hat[0] + 0.49 * e2.var_hat[0], rel=1e-12)
    assert c.ci_low[0] <= c.p_hat[0] <= c.ci_high[0]
    assert c.design == "staged"
    with pytest.raises(ValueError, match="sum to 1"):
        dz.combine_stages([e1, e2], [0.5, 0.6], n_pool=n)
    assert dz.combine_stages([e1], [1.0], n_pool=n) is e1


def test_a_weighted_sum_below_the_failures_found_is_raised_to_them():
    # Stage 1 draws none of the 10 failures of 100 (all at pi 0.1); stage 2, planned from
    # a model that learned where they are, takes them all at pi = 1. The weighted sum,
    # 0.5 x 0 + 0.5 x 10 = 5 failures, is below the 10 in hand; the rate cannot be.
    n = 100
    fail = np.zeros(n, bool)
    fail[:10] = True
    pi1 = np.full(n, 0.1)
    take1 = np.zeros(n, bool)
    take1[50:60] = True  # ten passes
    e1 = _stage(pi1, fail, take1, n_pool=n)
    rest = ~take1
    pi2 = np.where(fail[rest], 1.0, 0.05)
    take2 = fail[rest].copy()
    e2 = _stage(pi2, fail[rest], take2, n_pool=n)
    c = dz.combine_stages([e1, e2], [0.5, 0.5], n_pool=n)
    assert e1.p_hat[0] == 0.0 and e2.p_hat[0] == pytest.approx(0.10, rel=1e-12)
    assert c.p_hat_unbiased[0] == pytest.approx(0.05, rel=1e-12)
    assert c.n_failures_found[0] == 10
    assert c.p_hat[0] == pytest.approx(0.10, rel=1e-12)  # 10 / 100
    assert 0.10 - 1e-12 <= c.ci_low[0] <= c.p_hat[0] <= c.ci_high[0]
    # Between the count and the cap the sum is p_hat itself; over random stages, p_hat is
    # always the sum held between them, and the interval holds it.
    rng = np.random.default_rng(3)
    raised = capped = 0
    for _ in range(200):
        f = rng.random(n) < 0.08
        a, b = rng.uniform(0.02, 0.6, n), rng.uniform(0.02, 1.0, n)
        t1 = rng.random(n) < a
        r = ~t1
        t2 = rng.random(r.sum()) < b[r]
        s1 = _stage(a, f, t1, n_pool=n)
        s2 = _stage(b[r], f[r], t2, n_pool=n, known_failures=int((f & t1).sum()))
        w = rng.uniform(0.1, 0.9)
        cc = dz.combine_stages([s1, s2], [w, 1 - w], n_pool=n)
        # Each stage's own Horvitz-Thompson sum (1/pi per sampled failure), not its p_hat,
        # which a stage's cap may hold below it.
        ht1 = float((1.0 / a[f & t1]).sum())
        ht2 = int((f & t1).sum()) + float((1.0 / b[r][f[r] & t2]).sum())
        assert s1.p_hat_unbiased[0] * n == pytest.approx(ht1, rel=1e-12, abs=1e-12)
        assert s2.p_hat_unbiased[0] * n == pytest.approx(ht2, rel=1e-12, abs=1e-12)
        wsum = (w * ht1 + (1 - w) * ht2) / n
        assert cc.p_hat_unbiased[0] == pytest.approx(wsum, rel=1e-12, abs=1e-15)
        found, cap = cc.n_failures_found[0] / n, cc.cap[0]
        assert cc.p_hat[0] == pytest.approx(min(max(wsum, found), cap), rel=1e-12)
        assert found - 1e-12 <= cc.ci_low[0] <= cc.p_hat[0] <= cc.ci_high[0] <= cap + 1e-12
        raised += cc.p_hat[0] > cc.p_hat_unbiased[0]
        capped += cc.p_hat[0] < cc.p_hat_unbiased[0]
    assert raised > 0 and capped > 0  # the random stages reach both cases


@pytest.mark.parametrize("stages", [2, 3])
@pytest.mark.parametrize("model", ["calibrated", "useless"])
def test_staged_design_is_unbiased_and_its_variance_is_what_it_says(model, stages):
    # Repeated draws of the whole staged design from a known truth: the mean of p_hat is
    # the rate within 3 SE, and its spread matches the design's stated variance (for three
    # stages sum_s w_s^2 E[V_s], which holds only if the stages' errors are uncorrelated).
    rng = np.random.default_rng(9)
    N = 1000
    p = rng.beta(0.3, 8, N)
    fail = rng.random(N) < p
    if model == "useless":
        p = rng.permutation(p)
    # 2,000 draws: a useless model puts failures at small pi, whose weights make p_hat's
    # spread heavy-tailed, and 400 draws put the mean 3.2 SE off once (20,000: 1.1 SE).
    res = staged_trials(p, fail, K=4.0 * fail.sum(), n_trials=2000, rng=rng, stages=stages)
    se = res.p_hat_unbiased.std(ddof=1) / np.sqrt(res.p_hat_unbiased.size)
    assert abs(res.p_hat_unbiased.mean() - res.rate) < 3 * se
    assert res.p_hat_unbiased.var(ddof=1) == pytest.approx(res.var, rel=0.15)
    assert res.coverage >= 0.85
    # p_hat is the sum raised to the failures found: never lower, and on the mean within
    # the same 3 SE of the rate (it is raised only in the rare draws below the count).
    assert np.all(res.p_hat >= res.p_hat_unbiased)
    assert abs(res.p_hat.mean() - res.rate) < 3 * se


@pytest.mark.parametrize("stages", [2, 3, 4])
def test_the_fast_path_draws_what_the_many_stage_loop_draws(stages):
    # _multi_stage_trials plans, draws and combines each stage through the tool's own
    # functions; the fast path draws the same numbers, to rounding, at any number of stages.
    from bams_cli.core.evaluate import _multi_stage_trials, _staged_trials_fast

    rng = np.random.default_rng(4)
    p = rng.beta(0.3, 20, 2500)
    fail = rng.random(p.size) < np.clip(1.5 * p, 0, 1)
    known = rng.random(p.size) < 0.01
    kw = {"K": 120.0, "known": known, "share": 1.0 / stages, "prior": None, "anchor_sd": 0.5,
          "confidence": 0.9, "n_trials": 40}  # fmt: skip
    a = _staged_trials_fast(p, fail, stages=stages, rng=np.random.default_rng(7), **kw)
    b = _multi_stage_trials(p, fail, stages=stages, rng=np.random.default_rng(7), **kw)
    for name in ("p_hat", "ci_low", "ci_high", "recall", "p_hat_unbiased", "lam"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=1e-9, atol=1e-15)
    assert a.var == pytest.approx(b.var, rel=1e-9) and a.stage2_design == b.stage2_design
    # The later stages' posteriors moved with the draws, and the estimates with them.
    assert np.unique(a.lam).size > 10 and np.unique(a.p_hat).size > 20
    with pytest.raises(ValueError, match="two stages or more"):
        staged_trials(p, fail, K=120.0, n_trials=1, rng=rng, stages=1)


@pytest.mark.parametrize("seed, stages", [(1, 3), (3, 3), (7, 5), (186, 4), (214, 4)])
def test_fast_path_and_reference_agree_near_a_census(seed, stages):
    # K at or just under |U| in several stages. Where a stage draws all that is left, the
    # next has nothing to draw (the reference had raised, "p must be a non-empty 1-d
    # array": seeds 186 and 214 at four stages). Where p_n takes a few values, the capped
    # segments and a flat rest make the calibrated and p^alpha designs one; both paths
    # name it calibrated (the fast path's rounding had named it p^alpha: seeds 1, 3, 7).
    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 300))
    p = rng.choice([0.0, 0.01, 0.1, 0.5], n) if seed % 2 else rng.beta(0.3, 5, n)
    fail = rng.random(n) < p
    K = float(n) if seed % 3 == 0 else float(rng.uniform(0.97, 0.9999) * n)
    kw = {"K": K, "n_trials": 10, "stages": stages}
    ref = staged_trials(p, fail, rng=np.random.default_rng(seed), reference=True, **kw)
    fast = staged_trials(p, fail, rng=np.random.default_rng(seed), **kw)
    assert fast.stage2_design == ref.stage2_design
    for name in ("p_hat", "ci_low", "ci_high", "recall", "p_hat_unbiased"):
        np.testing.assert_allclose(getattr(fast, name), getattr(ref, name), rtol=1e-9, atol=1e-15)
    assert fast.var == pytest.approx(ref.var, rel=1e-9, abs=1e-300)


def test_the_staged_design_near_a_census_is_as_precise_as_one_uniform_sample():
    # A model that says nothing (p_n flat: both stages uniform) and K = 0.9 of U: the
    # design the benchmark draws has one uniform sample's variance (the stages' weights,
    # core.design.stage_weights), where weighting them by their shares of K gave ~2.7x.
    rng = np.random.default_rng(4)
    N = 2000
    fail = rng.random(N) < 0.05
    res = staged_trials(np.full(N, 0.05), fail, K=0.9 * N, n_trials=400, rng=rng)
    assert res.var / res.var_uniform == pytest.approx(1.0, abs=0.08)
    assert abs(res.p_hat_unbiased.mean() - res.rate) < 3 * res.p_hat_unbiased.std() / 20


def _pool(rng, n, kind):
    p = rng.beta(0.05, 10, n)
    p[: n // 8] = p[n // 8 : n // 4]  # ties
    p[n // 4 : n // 4 + n // 20] = 0.0  # zeros
    if kind == "constant":
        p = np.full(n, 0.3)
    elif kind == "zeros":
        p = np.zeros(n)
    elif kind == "extreme":
        p = np.where(rng.random(n) < 0.02, 1.0, 1e-12)
    return p


@pytest.mark.parametrize("stages", [2, 3])
@pytest.mark.parametrize(
    "kind, K, known_share, no_failures, share, anchor_sd",
    [
        ("beta", 100.0, 0.1, False, None, 1.0),
        ("beta", 100.0, 0.1, True, None, 1.0),  # zero failures: every stage samples none
        ("beta", 1.5, 0.0, False, None, 1.0),  # K below 2: stage 2 has floor(K_2) = 0
        ("beta", 5000.0, 0.1, False, None, 1.0),  # K >= |U|: stage 2 takes all that is left
        ("beta", 0.9 * 1800, 0.1, False, None, 1.0),  # K_2 >= |U_2| in most trials
        ("beta", 4.0, 0.995, False, None, 1.0),  # |U| = 10
        ("beta", 100.0, 0.1, False, 0.2, 1.0),
        ("constant", 100.0, 0.1, False, None, 1.0),  # every candidate ties uniform
        ("zeros", 100.0, 0.1, False, None, 1.0),
        ("extreme", 60.0, 0.0, False, None, 1.0),  # the capped carry most of the mass
        ("beta", 100.0, 0.1, False, None, None),  # where the failures fell only
        ("beta", 100.0, 0.1, False, 0.3, 0.4),
    ],
)
def test_staged_trials_fast_path_equals_the_tools_functions(
    kind, K, known_share, no_failures, share, anchor_sd, stages
):
    # The evaluation's fast path against the reference, which runs each trial through
    # choose_design, estimate_from_sample and combine_stages: the same draws (so the same
    # later-stage designs and lam, exactly) and the same numbers to 1e-12.
    rng = np.random.default_rng(int(K) + len(kind))
    n = 2000
    p = _pool(rng, n, kind)
    fail = (rng.random(n) < np.clip(3.0 * p, 0.01, 1.0)) & (not no_failures)
    known = np.zeros(n, bool)
    known[: int(known_share * n)] = True
    known = rng.permutation(known)
    kw = dict(K=K, known=known, share=share, anchor_sd=anchor_sd, n_trials=25, stages=stages)
    fast = staged_trials(p, fail, rng=np.random.default_rng(5), **kw)
    ref = staged_trials(p, fail, rng=np.random.default_rng(5), reference=True, **kw)
    assert fast.stage2_design == ref.stage2_design
    assert fast.stage1_design == ref.stage1_design
    np.testing.assert_array_equal(fast.lam, ref.lam)
    for name in ("p_hat", "ci_low", "ci_high", "recall"):
        np.testing.assert_allclose(getattr(fast, name), getattr(ref, name), rtol=1e-12, atol=0)
    assert fast.var == pytest.approx(ref.var, rel=1e-12, abs=0)
    assert fast.var_uniform == ref.var_uniform and fast.rate == ref.rate


@pytest.mark.parametrize("reference", [False, True])
def test_staged_trials_recall_of_uniform_sampling(reference):
    # p_n constant: both stages sample U uniformly, so the failures in hand are the known
    # ones plus, in expectation, F_U K / |U| (stage 1 takes F_U K_1/|U|; stage 2 the rest's
    # share K_2/|U_2| of the F_U (1 - K_1/|U|) left, |U_2| about |U| - K_1).
    rng = np.random.default_rng(11)
    n = 3000
    fail = rng.random(n) < 0.03
    known = np.zeros(n, bool)
    known[:300] = True
    F, known_f, F_U = fail.sum(), fail[known].sum(), fail[~known].sum()
    K = 270.0
    r = staged_trials(
        np.full(n, 0.2), fail, K=K, known=known, n_trials=400 if not reference else 60,
        rng=np.random.default_rng(3), reference=reference,
    )  # fmt: skip
    expected = (known_f + F_U * K / (n - 300)) / F
    # Per trial: Binomial-like stage-1 count, sd about sqrt(F_U K_1/|U|) ~ 2.8 failures.
    se = r.recall.std(ddof=1) / np.sqrt(r.recall.size)
    assert abs(r.recall.mean() - expected) < 4 * se + 1e-3
    assert np.all(r.recall >= known_f / F) and np.all(r.recall <= 1.0)


def test_staged_trials_with_all_of_U_known_fails_as_the_tool_does():
    p = np.full(50, 0.1)
    fail = np.arange(50) < 5
    for reference in (False, True):
        with pytest.raises(ValueError, match="non-empty"):
            staged_trials(
                p, fail, K=10.0, known=np.ones(50, bool), n_trials=3,
                rng=np.random.default_rng(0), reference=reference,
            )  # fmt: skip


@pytest.mark.parametrize("seed", range(6))
def test_capped_scale_gives_inclusion_probabilities_pi(seed):
    # pi = min(1, c g), the m largest capped, against inclusion_probabilities on g^2 with
    # alpha = 1/2 (pi proportional to g): ties, a few large g, K near |U|.
    rng = np.random.default_rng(seed)
    n = 500
    g = rng.gamma(0.3, size=n) + 1e-9
    g[:50] = g[50:100]
    g[rng.choice(n, 5)] *= 1e4
    order = np.argsort(-g, kind="stable")
    for K in (0.5, 3.0, 40.0, 250.7, 499.0):
        top = min(n - 1, int(np.floor(K)))
        head = order[: top + 1]
        m, c = _capped(g[head], float(np.delete(g, head).sum()), K)
        pi = np.minimum(1.0, c * g)
        if m:
            pi[g >= g[order[m - 1]]] = 1.0
        want = inclusion_probabilities(g**2 / (g**2).max(), alpha=0.5, defensive=0.0, K=K)
        np.testing.assert_allclose(pi, want, rtol=1e-12, atol=0)
        assert int(np.count_nonzero(pi >= 1.0)) == int(np.count_nonzero(want >= 1.0)) == m


@pytest.mark.slow
def test_default_design_drawn_ten_thousand_times_is_unbiased_and_covers():
    # Issue 12: >= 10,000 draws of the default design from a known truth.
    rng = np.random.default_rng(12)
    N = 2000
    p = rng.beta(0.05, 10, N)
    fail = rng.random(N) < np.clip(p * 1.5, 0, 1)  # the model under-predicts
    known = np.zeros(N, bool)
    known[rng.choice(N, 40, replace=False)] = True
    res = staged_trials(p, fail, K=5.0 * fail.sum() * 0.6, known=known, n_trials=10_000, rng=rng)
    se = res.p_hat.std(ddof=1) / np.sqrt(res.p_hat.size)
    assert abs(res.p_hat.mean() - res.rate) < 3 * se
    assert abs(res.p_hat_unbiased.mean() - res.rate) < 3 * se
    assert res.coverage >= 0.88
    assert res.var <= 1.2 * res.var_uniform


def test_a_count_far_above_what_p_n_predicts_says_the_model_misses_failures():
    # p_n predicts 0.5 failures among 500 sampled segments; 30 were found. Where they fell
    # says little (at random), how many says the model misses most of the failure mass.
    rng = np.random.default_rng(8)
    pool = rng.gamma(0.3, size=5000)
    pool = pool / pool.mean()
    s = rng.choice(5000, 500, replace=False)
    failed = np.zeros(500, bool)
    failed[rng.choice(500, 30, replace=False)] = True
    ev = dz.StageEvidence(pool[s], failed, dz.risk_norms(pool), p_mean=0.001)
    anchored = dz.risk_posterior([ev])
    where_only = dz.risk_posterior([ev], anchor_sd=None)
    assert anchored.lam_mean > 0.9 > where_only.lam_mean
    # ... and a count in line with p_n leaves trust where where-they-fell puts it.
    calm = dz.StageEvidence(pool[s], failed, dz.risk_norms(pool), p_mean=30 / pool[s].sum())
    assert dz.risk_posterior([calm]).lam_mean < anchored.lam_mean - 0.2


def test_a_screens_confirmation_trusts_the_refitted_p_n_only_where_the_cheap_level_tracks():
    t = defaults.SCREEN_HINT_DISCREPANCY
    assert dz.confirm_prior(0.0) == dz.confirm_prior(t * 0.999) == defaults.RISK_MIX_PRIOR_CONFIRM
    # Where the cheap level does not track level 0 (an explicit --screen), or there is no
    # evidence that it does, the confirmation is planned as the screen was.
    for ratio in (t, 5.0, float("nan"), None):
        assert dz.confirm_prior(ratio) == dz.risk_prior(ratio)
    # More trust than the screen's own prior: a smaller posterior mean of lam, so pi2
    # follows the refitted p_n more closely (a failure p_n puts at high risk gets a larger
    # pi2, one at low risk a smaller).
    confirm = dz.risk_posterior([], prior=defaults.RISK_MIX_PRIOR_CONFIRM)
    screen = dz.risk_posterior([], prior=defaults.RISK_MIX_PRIOR)
    assert confirm.lam_mean < 0.05 < 0.25 < screen.lam_mean
    p2 = np.r_[np.full(5, 0.5), np.full(195, 1e-4)]
    pi_c = sc.confirm_design(p2, K2=20.0, posterior=confirm).pi
    pi_s = sc.confirm_design(p2, K2=20.0, posterior=screen).pi
    assert pi_c.sum() == pytest.approx(20.0) and pi_s.sum() == pytest.approx(20.0)
    assert pi_c[0] >= pi_s[0] and pi_c[-1] < pi_s[-1]


def test_the_prior_on_lam_trusts_p_n_less_where_the_cheap_level_does_not_track_level0():
    t = defaults.SCREEN_HINT_DISCREPANCY
    assert dz.risk_prior(None) == defaults.RISK_MIX_PRIOR  # no cheap level
    assert dz.risk_prior(0.0) == dz.risk_prior(t * 0.999) == defaults.RISK_MIX_PRIOR
    assert dz.risk_prior(t) == dz.risk_prior(5.0) == defaults.RISK_MIX_PRIOR_WEAK_CHEAP
    assert dz.risk_prior(float("nan")) == defaults.RISK_MIX_PRIOR_WEAK_CHEAP
    # Less trust: a larger prior mean of lam, and a wider allowance quantile.
    strong = dz.risk_posterior([], prior=defaults.RISK_MIX_PRIOR)
    weak = dz.risk_posterior([], prior=defaults.RISK_MIX_PRIOR_WEAK_CHEAP)
    a, b = defaults.RISK_MIX_PRIOR_WEAK_CHEAP
    # The prior's mean a / (a + b), on the posterior's lam grid (its density is unbounded at 1).
    assert weak.lam_mean == pytest.approx(a / (a + b), abs=0.03)
    assert weak.lam_mean > strong.lam_mean + 0.2
    assert weak.summary()["prior"] == [a, b]


@pytest.mark.parametrize(
    ("n", "K", "shares"),
    [(10, 9, [0.5, 0.5]), (20_000, 200, [0.5, 0.5]), (5_000, 4_600, [0.3, 0.7]),
     (1_000, 600, [0.5, 0.25, 0.25])],
)  # fmt: skip
def test_stage_weights_make_uniform_stages_as_precise_as_one_uniform_sample(n, K, shares):
    # Uniform stages: stage s samples pi_s = K_s / N_s of the N_s segments left, its HT
    # variance per failure (1 - pi_s) / pi_s over N_s. Weighted inversely, the stages add
    # up to one uniform Poisson sample of K: 1 / sum_s (1 / V_s) = n (1 - K/n) / (K/n).
    w = np.asarray(dz.stage_weights(shares, K, n))
    left, V = float(n), []
    for sh in shares:
        k = sh * K
        V.append(left * (1 - k / left) / (k / left))
        left -= k
    assert w.sum() == pytest.approx(1.0, rel=1e-12)
    assert float(w**2 @ V) == pytest.approx(n * (1 - K / n) / (K / n), rel=1e-9)
    # and no other weights do better (Cauchy-Schwarz): the shares are worse or equal
    assert float(w**2 @ V) <= float(np.asarray(shares) ** 2 @ V) * (1 + 1e-12)


def test_stage_weights_a_census_of_the_rest_takes_all_the_weight():
    assert dz.stage_weights([0.5, 0.5], 100, 100) == [0.0, 1.0]  # stage 2 takes all 50 left
    assert dz.stage_weights([0.5, 0.5], 250, 100) == [1.0, 0.0]  # stage 1 takes all 100
    assert dz.stage_weights([1.0], 50, 100) == [1.0]
    assert dz.stage_weights([0.5, 0.5], 0, 100) == [0.5, 0.5]


def test_staged_uniform_draws_with_these_weights_match_one_uniform_sample():
    # Monte Carlo over the real two-stage draw (stage 2's pi over the U it actually
    # leaves), K = 0.9 of the pool: the weighted HT sum is unbiased, its variance is one
    # uniform sample's, and the shares' weights (K_s / K) give about 3x it.
    rng = np.random.default_rng(11)
    n, K, reps = 400, 360.0, 40_000
    fail = np.zeros(n, bool)
    fail[:40] = True
    w = dz.stage_weights([0.5, 0.5], K, n)
    T = np.empty((reps, 2))
    for r in range(reps):
        s1 = rng.random(n) < 0.5 * K / n
        t1 = fail[s1].sum() / (0.5 * K / n)
        u2 = ~s1
        pi2 = min(1.0, 0.5 * K / u2.sum())
        s2 = u2 & (rng.random(n) < pi2)
        t2 = fail[s1].sum() + fail[s2].sum() / pi2
        T[r] = (t1, t2)
    est = T @ np.asarray(w)
    var_one = 40 * (1 - K / n) / (K / n)
    assert abs(est.mean() - 40) < 4 * est.std() / np.sqrt(reps)
    assert est.var() == pytest.approx(var_one, rel=0.1)
    assert (T @ np.array([0.5, 0.5])).var() > 2.5 * var_one


def test_leads_sampled_with_certainty_keep_the_staged_estimate_unbiased_and_in_hand():
    """``estimate --plan`` samples the open cheap-level leads with pi = 1 out of K
    (``staged_trials(leads=...)`` draws that design). Drawn 2,000 times from a truth whose
    leads are enriched in failures whatever p says: unbiased, its variance what the trials
    show, the leads' failures in hand in every trial, more recall than without them, and
    the variance set beside a uniform design of the whole K over the whole of U. More
    leads than defaults.LEAD_SHARE K: the highest p first."""
    rng = np.random.default_rng(11)
    N = 3000
    p = rng.beta(0.3, 20, N)
    fail = rng.random(N) < p
    leads = rng.random(N) < np.where(fail, 0.3, 0.004)
    K = 200.0
    assert 0 < leads.sum() < defaults.LEAD_SHARE * K
    t = staged_trials(p, fail, K=K, leads=leads, n_trials=2000, rng=np.random.default_rng(1))
    se = t.p_hat_unbiased.std(ddof=1) / np.sqrt(t.p_hat_unbiased.size)
    assert abs(t.p_hat_unbiased.mean() - t.rate) < 3 * se
    assert t.p_hat_unbiased.var(ddof=1) == pytest.approx(t.var, rel=0.15)
    assert t.var_uniform == pytest.approx(fail.sum() * (N - K) / K / N**2, rel=1e-12)
    assert np.all(t.recall >= fail[leads].sum() / fail.sum())
    none = staged_trials(p, fail, K=K, n_trials=2000, rng=np.random.default_rng(1))
    assert t.recall.mean() > none.recall.mean() + 0.5 * fail[leads].sum() / fail.sum()
    # The cap, against a brute-force ranking: every segment a lead, known ones excluded.
    known = np.zeros(N, bool)
    known[:10] = True
    cap = int(defaults.LEAD_SHARE * K)
    want = np.zeros(N, bool)
    want[[i for i in sorted(range(N), key=lambda i: -p[i]) if not known[i]][:cap]] = True
    np.testing.assert_array_equal(dz.certain_leads(p, known, np.ones(N, bool), K), want)
    small = dz.certain_leads(p, known, np.ones(N, bool), K, defaults.LEAD_SHARE_UNPROVEN)
    assert small.sum() == int(defaults.LEAD_SHARE_UNPROVEN * K) and not (small & ~want).any()


@pytest.mark.parametrize(
    ("pairs", "failed", "share"),
    [
        (0, 0, defaults.LEAD_SHARE),  # no evidence: the uniform prior's 1/2
        (3, 0, defaults.LEAD_SHARE),  # 1/5: at the threshold
        (4, 0, defaults.LEAD_SHARE_UNPROVEN),  # 1/6
        (12, 1, defaults.LEAD_SHARE_UNPROVEN),  # 1/7
        (5, 1, defaults.LEAD_SHARE),  # 2/7
    ],
)
def test_the_leads_share_of_K_follows_how_often_the_studys_leads_failed(pairs, failed, share):
    assert defaults.LEAD_HIT_MIN == 0.2  # the thresholds above are 1/5
    assert dz.lead_share(pairs, failed) == share


def test_leads_that_rarely_fail_take_little_of_K_and_keep_the_variance_near_uniforms():
    # A study at K = 1.2 F (K at its floor under a model that saw no failure): leads that
    # fail 7% of the time, half of K of them, raise the variance above uniform's; a tenth
    # of K raises it by at most 1/0.9. The rule's threshold, F/K, by the exact variance.
    from bams_cli.core.evaluate import staged_trials

    rng = np.random.default_rng(5)
    N, K = 6000, 100.0
    fail = rng.random(N) < 0.02
    p = np.full(N, 1e-4)
    leads = np.zeros(N, bool)
    leads[rng.choice(np.flatnonzero(~fail), 47, replace=False)] = True
    leads[rng.choice(np.flatnonzero(fail), 3, replace=False)] = True
    ratio = {}
    for share in (defaults.LEAD_SHARE, defaults.LEAD_SHARE_UNPROVEN):
        t = staged_trials(
            p, fail, K=K, leads=leads, lead_share=share, n_trials=200,
            rng=np.random.default_rng(1),
        )  # fmt: skip
        ratio[share] = t.var / t.var_uniform
    assert ratio[defaults.LEAD_SHARE] > 1.3
    assert ratio[defaults.LEAD_SHARE_UNPROVEN] < 1.0 / 0.9 + 0.03
