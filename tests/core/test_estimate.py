"""Tests for bams_cli.core.estimate: inclusion probabilities, designs, HT estimates, CIs, GP variance.

Repeated-sampling tests draw each sample with the real ``draw_*`` function, stack the
samples as a (|U|, repeats) count matrix and estimate all repeats in one vectorised call of
``estimate_from_sample`` (rows with count 0 contribute nothing).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import ndtr
from scipy.stats import gamma as gamma_dist
from scipy.stats import multivariate_normal

from bams_cli.core.estimate import (
    RateEstimate,
    ZeroInclusionWarning,
    _gamma_interval,
    bvn_cov,
    draw_poisson,
    draw_systematic,
    draw_with_replacement,
    estimate_from_sample,
    estimate_rate,
    gp_estimate,
    gp_variance_exact,
    inclusion_probabilities,
    log_selection_distribution,
    model_weight,
    plan_sample,
    selection_distribution,
)
from bams_cli.core.evaluate import exact_relative_variance, exact_variance

DESIGNS = ["poisson", "fixed", "with-replacement"]


# --------------------------------------------------------------------------------------------
# Test pools
# --------------------------------------------------------------------------------------------


def make_pool(
    N: int = 5000, F: int = 50, *, n_wrong: int = 3, wrong_p: float = 1e-4, shift: float = 2.5
) -> tuple[np.ndarray, np.ndarray]:
    """N segments, F failures; p_n a noisy informative score, n_wrong failures given wrong_p.

    z = noise + shift [failure] - 3, p_n = Phi(z): failures have median p_n ~ 0.35 at
    shift 2.5, passes ~ 0.001 with a tail to 0.25. Fixed seed: the pool is part of the test.
    """
    rng = np.random.default_rng(20240601)
    fail = np.zeros(N, bool)
    fail[rng.choice(N, F, replace=False)] = True
    p = ndtr(rng.normal(size=N) + np.where(fail, shift, 0.0) - 3.0)
    p[np.flatnonzero(fail)[:n_wrong]] = wrong_p
    return p, fail


def calibrated_pool(
    seed: int, N: int = 5000, mu_z: float = -3.5, sd_z: float = 1.5
) -> tuple[np.ndarray, np.ndarray]:
    """A pool on which p_n is calibrated: p = Phi(z), z ~ N(mu_z, sd_z), fail ~ Bernoulli(p).

    Failures at low p_n occur at the rate p_n says, so the sampler meets "confidently wrong"
    failures as often as a calibrated GP would.
    """
    rng = np.random.default_rng(seed)
    p = ndtr(rng.normal(mu_z, sd_z, N))
    return p, rng.random(N) < p


def repeat_counts(design, prob, K, R, rng):
    """(|U|, R) count matrix of R independent samples drawn by the real draw functions."""
    C = np.zeros((prob.size, R), np.int64)
    for r in range(R):
        if design == "poisson":
            C[draw_poisson(prob, rng), r] = 1
        elif design == "fixed":
            C[draw_systematic(prob, rng), r] = 1
        else:
            s, c = draw_with_replacement(prob, K, rng)
            C[s, r] = c
    return C


def simulate(p, fail, *, design, K, alpha, defensive, R, rng, known=None, **kw):
    """Estimates of R independent repeats and the design's exact (fixed: Hajek) variance."""
    N = p.size
    known = np.zeros(N, bool) if known is None else known
    U = np.flatnonzero(~known)
    if design == "with-replacement":
        prob = selection_distribution(p[U], alpha=alpha, defensive=defensive)
    else:
        prob = inclusion_probabilities(p[U], alpha=alpha, defensive=defensive, K=K)
    C = repeat_counts(design, prob, K, R, rng)
    kw.setdefault("w_model", model_weight(p[U], prob, design=design, K=K))
    est = estimate_from_sample(
        prob,
        fail[U],
        design=design,
        n_pool=N,
        n_unknown=U.size,
        budget=K,
        counts=C,
        known_failures=int(fail[known].sum()),
        **kw,
    )
    var = float(exact_variance(prob, fail[U], design=design, n_pool=N, budget=K)[0])
    return est, var


# --------------------------------------------------------------------------------------------
# Inclusion probabilities
# --------------------------------------------------------------------------------------------


def test_inclusion_probabilities_hand_example():
    # q = p (alpha 1, eps 0). K = 1.5: lam = 1.5 would give 1.05 to the largest, so it is
    # capped and the other two share 0.5 in proportion 1 : 2.
    pi = inclusion_probabilities([0.1, 0.2, 0.7], alpha=1.0, defensive=0.0, K=1.5)
    np.testing.assert_allclose(pi, [1 / 6, 1 / 3, 1.0], rtol=1e-15)
    # eps = 0.5 mixes in 0.5/3 each: q = [0.2167, 0.2667, 0.5167]; K = 1 is uncapped.
    pi = inclusion_probabilities([0.1, 0.2, 0.7], alpha=1.0, defensive=0.5, K=1.0)
    np.testing.assert_allclose(pi, [0.05 + 1 / 6, 0.1 + 1 / 6, 0.35 + 1 / 6], rtol=1e-14)


@pytest.mark.parametrize("alpha", [0.0, 0.5, 1.0, 2.5])
@pytest.mark.parametrize("defensive", [0.0, 0.1, 1.0])
@pytest.mark.parametrize("K", [1.0, 37.5, 250.0, 2000.0, 4999.0, 5000.0, 7000.0])
def test_inclusion_probabilities_sum_cap_monotone(alpha, defensive, K):
    rng = np.random.default_rng(1)
    p = rng.random(5000) ** 4
    p[:50] = p[50:100]  # ties
    pi = inclusion_probabilities(p, alpha=alpha, defensive=defensive, K=K)
    assert np.all((pi >= 0) & (pi <= 1))
    assert math.isclose(pi.sum(), min(K, p.size), rel_tol=1e-12)
    order = np.argsort(p, kind="stable")
    assert np.all(np.diff(pi[order]) >= -1e-15)
    # The uncapped share one lam: pi = lam q.
    q = selection_distribution(p, alpha=alpha, defensive=defensive)
    unc = pi < 1
    if np.any(unc):
        lam = pi[unc] / q[unc]
        np.testing.assert_allclose(lam, lam[0], rtol=1e-12)
        # ... and the capped would exceed 1 at that lam.
        assert np.all(lam[0] * q[~unc] >= 1 - 1e-12)


def test_inclusion_probabilities_zero_p_warns():
    p = np.array([0.0, 0.0, 0.2, 0.5, 0.9])
    with pytest.warns(ZeroInclusionWarning, match="defensive > 0"):
        pi = inclusion_probabilities(p, alpha=1.0, defensive=0.0, K=2.0)
    assert pi[0] == 0 and pi[1] == 0 and math.isclose(pi.sum(), 2.0)
    # K above the number of positive q: all three taken, the rest of the budget unplaceable.
    with pytest.warns(ZeroInclusionWarning):
        pi = inclusion_probabilities(p, alpha=1.0, defensive=0.0, K=4.0)
    np.testing.assert_array_equal(pi, [0, 0, 1, 1, 1])


def test_selection_distribution_survives_tiny_p():
    # p^2.5 underflows for p ~ 1e-200; ratios must survive.
    q = selection_distribution(np.array([1e-200, 2e-200]), alpha=2.5, defensive=0.0)
    np.testing.assert_allclose(q, np.array([1.0, 2**2.5]) / (1 + 2**2.5))


def subnormal_tail_pool() -> np.ndarray:
    # 1,480 likely segments and 61 whose p_n falls from 1e-306 to 1e-315: at eps = 0 their
    # q (p / 740) lies below 2.2e-308, so every tail sum S_m is subnormal and the old
    # lam = (K - m) / S_m overflowed (issue 12: every pi became 1, sum 1,541 vs K).
    return np.concatenate([np.full(1480, 0.5), np.logspace(-306, -315, 61)])


@pytest.mark.parametrize(
    "pool, alpha",
    [
        # q spanning 1e-300..1 log-uniformly (alpha 1: q = p / sum p).
        pytest.param(lambda: np.logspace(0, -300, 1541), 1.0, id="q-1e-300..1"),
        pytest.param(subnormal_tail_pool, 1.0, id="subnormal-tail"),
        # alpha 2.5 takes p = 1e-150 to q ~ 1e-375: no float64 holds it, its log does.
        pytest.param(lambda: np.logspace(0, -150, 1541), 2.5, id="q-below-float64"),
    ],
)
@pytest.mark.parametrize("K", [10.0, 1485.5, 1489.0, 1540.5])
@pytest.mark.filterwarnings("ignore::bams_cli.core.estimate.ZeroInclusionWarning")
def test_inclusion_probabilities_at_the_float_edge(pool, alpha, K):
    p = pool()
    pi = inclusion_probabilities(p, alpha=alpha, defensive=0.0, K=K)
    assert math.isclose(pi.sum(), K, rel_tol=1e-9), (pi.sum(), int((pi == 1).sum()))
    assert np.all((pi >= 0) & (pi <= 1))
    # pi = lam q for the uncapped, checked in logs (q itself underflows): log pi - log q is
    # one constant log lam, and every capped segment would exceed 1 at that lam.
    log_q = log_selection_distribution(p, alpha=alpha, defensive=0.0)
    unc = (pi < 1) & (pi > 1e-300)
    log_lam = np.log(pi[unc]) - log_q[unc]
    np.testing.assert_allclose(log_lam, log_lam[0], rtol=0, atol=1e-9)
    assert np.all(log_lam[0] + log_q[pi == 1] >= -1e-9)
    assert np.count_nonzero(pi == 1) < K  # the budget left for the tail is really placed


def _pi_by_bisection(p, *, alpha, defensive, K):
    """The straightforward computation: argsort, then bisect [0, floor(K)] for m."""
    log_q = log_selection_distribution(p, alpha=alpha, defensive=defensive)
    n = log_q.size
    if K >= n:
        return np.ones(n)
    order = np.argsort(-log_q, kind="stable")
    ls = log_q[order]
    n_pos = int(np.count_nonzero(ls > -np.inf))
    pi_sorted = np.zeros(n)
    if n_pos <= K:
        pi_sorted[:n_pos] = 1.0
    else:

        def fits(m):
            return K - m <= float(np.exp(ls[m:] - ls[m]).sum()) * (1.0 + 1e-12)

        lo, hi = 0, min(n - 1, int(math.floor(K)))
        while lo < hi:
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if fits(mid) else (mid + 1, hi)
        r = np.exp(ls[lo:] - ls[lo])
        pi_sorted[:lo] = 1.0
        pi_sorted[lo:] = np.minimum(1.0, (K - lo) * r / r.sum())
    pi = np.empty(n)
    pi[order] = pi_sorted
    return pi


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.filterwarnings("ignore::bams_cli.core.estimate.ZeroInclusionWarning")
def test_inclusion_probabilities_equal_the_bisection_bit_for_bit(seed):
    # The suffix-sum guess at the capped count, and the order hint, must not move pi by an
    # ulp: an estimate --plan file is the same before and after. Pools from flat to heavy
    # capping (m from 0 to hundreds), with ties and zeros.
    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 4000))
    p = rng.random(n) ** rng.choice([1, 4, 12, 40])
    p[rng.integers(0, n, n // 10)] = p[rng.integers(0, n, n // 10)]  # ties
    if seed % 2:
        p[rng.integers(0, n, 5)] = 0.0
    order = np.argsort(-p, kind="stable")
    for alpha, defensive in [(0.75, 0.1), (0.5, 0.0), (1.0, 0.0), (2.5, 0.01)]:
        for K in [0.5, 1.0, 7.3, n / 50, n / 5, n / 2, n - 1.5]:
            ref = _pi_by_bisection(p, alpha=alpha, defensive=defensive, K=K)
            pi = inclusion_probabilities(p, alpha=alpha, defensive=defensive, K=K)
            np.testing.assert_array_equal(pi, ref)
            hinted = inclusion_probabilities(p, alpha=alpha, defensive=defensive, K=K, order=order)
            np.testing.assert_array_equal(hinted, ref)
    # A hint that does not sort p is caught and ignored.
    wrong = rng.permutation(n)
    pi = inclusion_probabilities(p, alpha=0.75, defensive=0.1, K=n / 5, order=wrong)
    np.testing.assert_array_equal(pi, _pi_by_bisection(p, alpha=0.75, defensive=0.1, K=n / 5))


def test_logsumexp_is_scipys_bit_for_bit():
    from scipy.special import logsumexp

    from bams_cli.core.sampling import _logsumexp

    rng = np.random.default_rng(7)
    for i in range(400):
        n = int(rng.integers(1, 5000))
        a = rng.normal(0.0, rng.choice([1e-3, 1.0, 30.0, 300.0]), n)
        if i % 3 == 0:
            a[rng.integers(0, n, int(rng.integers(1, 4)))] = a.max()  # ties at the max
        if i % 5 == 0:
            a = np.round(a, 1)
        assert _logsumexp(a) == float(logsumexp(a))


# --------------------------------------------------------------------------------------------
# Designs: the draws have the inclusion probabilities they claim
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("design", DESIGNS)
def test_draw_inclusion_frequencies(design):
    rng = np.random.default_rng(2)
    p = rng.random(40) ** 2
    K = 8
    R = 6000
    if design == "with-replacement":
        q = selection_distribution(p, alpha=1.0, defensive=0.1)
        prob = -np.expm1(K * np.log1p(-q))
        C = repeat_counts(design, q, K, R, rng)
        np.testing.assert_array_equal(C.sum(axis=0), K)
        np.testing.assert_allclose(C.mean(axis=1), K * q, atol=5 * np.sqrt(K * q / R).max())
    else:
        prob = inclusion_probabilities(p, alpha=1.0, defensive=0.1, K=K)
        C = repeat_counts(design, prob, K, R, rng)
        if design == "fixed":
            np.testing.assert_array_equal(C.sum(axis=0), K)
    freq = (C > 0).mean(axis=1)
    se = np.sqrt(prob * (1 - prob) / R) + 1e-12
    assert np.all(np.abs(freq - prob) <= 4.5 * se)


def test_draw_systematic_non_integer_size():
    rng = np.random.default_rng(3)
    pi = np.full(10, 0.35)  # sum 3.5: sizes 3 or 4, each half the time
    sizes = [draw_systematic(pi, rng).size for _ in range(2000)]
    assert set(sizes) == {3, 4}
    assert abs(np.mean(sizes) - 3.5) < 4.5 * 0.5 / np.sqrt(2000)


# --------------------------------------------------------------------------------------------
# Estimators on hand examples
# --------------------------------------------------------------------------------------------


def test_estimates_hand_example():
    # N = 10, one known failure; sampled pi = [0.5, 0.25, 1], failures [T, T, F].
    kw = dict(n_pool=10, n_unknown=8, budget=3.0, known_failures=1)
    pi = np.array([0.5, 0.25, 1.0])
    f = np.array([True, True, False])
    est = estimate_from_sample(pi, f, design="poisson", **kw)
    assert math.isclose(est.p_hat[0], (1 + 2 + 4) / 10)
    assert math.isclose(est.var_hat[0], (0.5 / 0.25 + 0.75 / 0.0625) / 100)
    assert est.n_failures_found[0] == 3 and est.n_failures_sampled[0] == 2
    # Deville: e = [2, 4], c = [0.5, 0.75], A = (1 + 3)/1.25 = 3.2,
    # v = 2/1 (0.5 * 1.2^2 + 0.75 * 0.8^2) = 2.4.
    est = estimate_from_sample(pi, f, design="fixed", **kw)
    assert math.isclose(est.p_hat[0], 0.7)
    assert math.isclose(est.var_hat[0], 2.4 / 100)
    # With replacement, K = 4 draws, counts [2, 1, 1], q = [0.2, 0.1, 0.3]:
    # terms 5, 5, 10, 0 -> T = 5, s^2 = 50/3, v = s^2/4.
    q = np.array([0.2, 0.1, 0.3])
    est = estimate_from_sample(
        q, f, design="with-replacement", counts=[2, 1, 1], n_pool=10, n_unknown=8, budget=4,
        known_failures=1,
    )  # fmt: skip
    assert math.isclose(est.p_hat[0], 0.6)
    assert math.isclose(est.var_hat[0], 50 / 12 / 100)


def test_with_replacement_variance_keeps_its_digits():
    # K = 4 draws, every one a failure: rows drawn [2, 1, 1] times with 1/q ~ [1e9, 1e9 + 1,
    # 1e9 + 3], terms ~ [1e9, 1e9, 1e9 + 1, 1e9 + 3]: mean 1e9 + 1, deviations [-1, -1, 0, 2],
    # s^2 = 6/3 = 2, v = s^2/K = 0.5. The one-pass sum Y^2 - K T^2 is a difference of two
    # ~4e18 numbers whose spacing is 512: all digits lost.
    q = 1.0 / np.array([1e9, 1e9 + 1, 1e9 + 3])
    counts = np.array([2, 1, 1])
    K = 4
    terms = np.repeat(1.0 / q, counts)  # brute force: the K terms themselves, in fsum
    mean = math.fsum(terms) / K
    brute = math.fsum((t - mean) ** 2 for t in terms) / (K - 1) / K
    assert math.isclose(brute, 0.5, rel_tol=1e-6)
    one_pass = (math.fsum(terms**2) - K * mean**2) / (K - 1) / K
    assert abs(one_pass - brute) > 0.5 * brute  # the case really defeats the one-pass form
    N = 10**10
    est = estimate_from_sample(
        q, np.ones(3, bool), design="with-replacement", counts=counts, n_pool=N,
        n_unknown=10**9, budget=K,
    )  # fmt: skip
    assert math.isclose(est.var_hat[0] * N**2, brute, rel_tol=1e-9)
    # With draws of passing segments too (repeat columns), still the brute-force value.
    counts2 = np.array([[2, 1], [1, 0], [1, 1]])  # column 1: two failure draws, two passes
    est = estimate_from_sample(
        q, np.ones(3, bool), design="with-replacement", counts=counts2, n_pool=N,
        n_unknown=10**9, budget=K,
    )  # fmt: skip
    terms = np.array([1.0 / q[0], 1.0 / q[2], 0.0, 0.0])
    mean = math.fsum(terms) / K
    brute2 = math.fsum((t - mean) ** 2 for t in terms) / (K - 1) / K
    assert math.isclose(est.var_hat[1] * N**2, brute2, rel_tol=1e-12)


def test_estimate_rate_serves_every_gamma():
    rng = np.random.default_rng(4)
    p, fail = make_pool(n_wrong=0)
    known = np.zeros(p.size, bool)
    known[:300] = True
    plan = plan_sample(p, K=250, rng=rng, known=known, alpha=1.0, defensive=0.1)
    # Three nested thresholds: failure sets grow.
    f3 = np.stack([fail & (np.arange(p.size) % 3 == 0), fail, fail | (p > 0.2)], axis=1)
    ests = estimate_rate(plan, f3[plan.sampled_pool_index], known_failures=f3[known].sum(axis=0))
    assert len(ests) == 3 and all(isinstance(e, RateEstimate) for e in ests)
    for j, e in enumerate(ests):
        single = estimate_rate(
            plan, f3[plan.sampled_pool_index, j], known_failures=int(f3[known, j].sum())
        )[0]
        for name in ("p_hat", "se", "ci_low", "ci_high", "n_failures_found", "n_sampled"):
            assert getattr(e, name) == pytest.approx(getattr(single, name), rel=1e-12)
        assert e.ci_low <= e.p_hat <= e.ci_high
        assert e.n_sampled == plan.sampled.size
    assert ests[0].p_hat <= ests[1].p_hat <= ests[2].p_hat


# --------------------------------------------------------------------------------------------
# Unbiasedness, variance, coverage over repeated samples
# --------------------------------------------------------------------------------------------

GRID_SEED = {d: i for i, d in enumerate(DESIGNS)}


def skewness_of_estimate(p, fail, *, design, K, alpha, defensive, known=None) -> float:
    """Exact skewness of one estimate of the total (fixed: the Poisson value, approximately).

    Poisson: sum over failures of independent w I, I ~ Bernoulli(pi), w = 1/pi:
    kappa2 = sum (1 - pi)/pi, kappa3 = sum (1 - pi)(1 - 2 pi)/pi^2.
    With replacement: mean of K i.i.d. Y = 1{fail}/q: skew(Y) / sqrt(K).
    """
    U = np.arange(p.size) if known is None else np.flatnonzero(~known)
    f = fail[U]
    if design == "with-replacement":
        q = selection_distribution(p[U], alpha=alpha, defensive=defensive)[f]
        T = f.sum()
        m2 = (1 / q).sum() - T**2
        m3 = (1 / q**2).sum() - 3 * T * (1 / q).sum() + 2 * T**3
        return m3 / m2**1.5 / math.sqrt(K)
    pi = inclusion_probabilities(p[U], alpha=alpha, defensive=defensive, K=K)[f]
    pi = pi[pi < 1]
    k2 = ((1 - pi) / pi).sum()
    k3 = ((1 - pi) * (1 - 2 * pi) / pi**2).sum()
    return k3 / k2**1.5 if k2 > 0 else 0.0


@pytest.mark.parametrize("design", DESIGNS)
@pytest.mark.parametrize("alpha", [0.5, 1.0, 2.5])
@pytest.mark.parametrize(
    "defensive", [pytest.param(0.0, marks=pytest.mark.slow), pytest.param(0.1)]
)
@pytest.mark.parametrize("with_known", [pytest.param(False, marks=pytest.mark.slow), True])
def test_unbiased(design, alpha, defensive, with_known):
    """Mean of 2,000 estimates within 3 SE of the true rate (skewness-corrected band).

    The pool holds 3 confidently-wrong failures (p_n = 1e-4, strictly positive so that
    eps = 0 stays unbiased; ``test_zero_inclusion_is_biased_and_warned`` covers p_n = 0).
    SE = sqrt(Var / 2000) from the exact variance (Hajek's approximation, or the observed
    spread if larger, for "fixed"). The estimate is right-skewed (rare heavy terms), so the
    mean of 2,000 is too: its upper 3-SE limit moves out by the Cornish-Fisher term
    (z^2 - 1) g / 6 = 4 g / 3, g the exact skewness of the mean, which keeps the false alarm
    rate at ~0.3% where a symmetric band would not. The lower limit stays at -3 SE (a
    right-skewed mean falls below -3 SE less often than a normal one). At eps = 0 the exact variance is
    huge (the confidently-wrong failures get pi ~ 1e-10; DESIGN.md), so there the check is
    weak by construction; at eps = 0.1 it resolves a bias of a few percent of the rate.
    """
    p, fail = make_pool()
    known = None
    if with_known:
        known = np.zeros(p.size, bool)
        known[np.random.default_rng(5).choice(p.size, 500, replace=False)] = True
        known[np.flatnonzero(fail)[10:14]] = True  # some known failures
    seed = 1000 * GRID_SEED[design] + int(10 * alpha) + int(100 * defensive) + 7 * with_known
    R = 2000
    kw = dict(design=design, K=250, alpha=alpha, defensive=defensive, known=known)
    est, var = simulate(p, fail, R=R, rng=np.random.default_rng(seed), **kw)
    if design == "fixed":
        var = max(var, float(est.p_hat.var()))
    z = (est.p_hat.mean() - fail.mean()) / math.sqrt(var / R)
    shift = 4 / 3 * skewness_of_estimate(p, fail, **kw) / math.sqrt(R)
    assert -3 <= z <= 3 + max(shift, 0.0)


def test_zero_inclusion_is_biased_and_warned():
    # A failure with p_n = 0 and eps = 0 gets pi = 0: E[p_hat] misses it exactly.
    p, fail = make_pool(n_wrong=3, wrong_p=0.0)
    with pytest.warns(ZeroInclusionWarning):
        pi = inclusion_probabilities(p, alpha=1.0, defensive=0.0, K=250)
    # E[T_hat] = number of failures with pi > 0, exactly.
    assert (pi[fail] > 0).sum() == fail.sum() - 3
    assert np.isinf(exact_variance(pi, fail, design="poisson", n_pool=p.size)[0])


@pytest.mark.parametrize("design", DESIGNS)
def test_reported_se_and_exact_variance_match_spread(design):
    """Across 4,000 repeats: RMS of reported SEs, and exact SD, within 10% of the spread.

    Pool chosen with failures' pi >= 0.05 (excess kurtosis of the estimate ~1), so the
    spread of 4,000 repeats is itself known to ~1.5%. For "fixed" both the reported
    variance and the "exact" one are Hajek approximations; the test shows they hold.
    """
    p, fail = make_pool(n_wrong=0, shift=3.5)
    est, var = simulate(
        p, fail, design=design, K=250, alpha=0.5, defensive=0.1, R=4000,
        rng=np.random.default_rng(6 + GRID_SEED[design]),
    )  # fmt: skip
    sd = est.p_hat.std(ddof=1)
    assert abs(math.sqrt(est.var_hat.mean()) / sd - 1) < 0.10
    assert abs(math.sqrt(var) / sd - 1) < 0.10
    # Relative variance: estimated and exact agree with the spread too.
    truth = fail.mean()
    assert abs(np.nanmean(est.rel_var) / (sd**2 / truth**2) - 1) < 0.25


def test_exact_relative_variance_hand_example():
    # N = 10, one known failure, U = 9 units with pi = 0.5 (poisson), two failures in U:
    # Var = (1/100) * 2 * (1 - 0.5)/0.5 = 0.02; p = 3/10 -> RV = 0.02 / 0.09.
    known = np.zeros(10, bool)
    known[0] = True
    fail = np.zeros(10, bool)
    fail[[0, 3, 7]] = True
    plan = plan_sample(np.full(10, 0.3), K=4.5, rng=np.random.default_rng(0), known=known)
    np.testing.assert_allclose(plan.pi, 0.5)
    var, rv = exact_relative_variance(plan, fail)
    assert math.isclose(var[0], 0.02) and math.isclose(rv[0], 0.02 / 0.09)


def coverage(est, truth):
    return float(np.mean((est.ci_low <= truth) & (truth <= est.ci_high)))


@pytest.mark.parametrize("design", DESIGNS)
def test_ci_coverage_near_nominal(design):
    """Calibrated p_n, alpha 1, eps 0.1, K = 5 p N (~100 failures sampled): |cov - 0.9| <= 3 pts.

    4,000 repeats (binomial SE of the coverage 0.5 pts). Mean over 6 x 2,000 repeats:
    0.896 (poisson), 0.893 (fixed), 0.918 (with-replacement; 2.6 SE inside the band here).
    """
    p, fail = calibrated_pool(2)
    est, _ = simulate(
        p, fail, design=design, K=5 * int(fail.sum()), alpha=1.0, defensive=0.1, R=4000,
        rng=np.random.default_rng(8 + GRID_SEED[design]),
    )  # fmt: skip
    assert abs(coverage(est, fail.mean()) - 0.9) <= 0.03


@pytest.mark.parametrize("design", DESIGNS)
def test_ci_coverage_few_failures(design):
    """~1.6 failures sampled (< 5 in ~98% of repeats): coverage >= nominal - 3 pts.

    Calibrated pool with 55 failures, K = 27. With so few failures the interval reduces to
    Garwood's exact Poisson interval and is conservative (measured 0.98), which is why this
    case asserts only the lower side; the normal (Wald) interval covers < 0.8 here, which the
    test also asserts, on all repeats and on those with < 5 failures sampled.
    """
    p, fail = calibrated_pool(1, mu_z=-3.2, sd_z=1.0)
    truth = fail.mean()
    kw = dict(design=design, K=int(fail.sum()) // 2, alpha=0.5, defensive=0.1, R=2000)
    seed = 9 + GRID_SEED[design]
    est, _ = simulate(p, fail, rng=np.random.default_rng(seed), **kw)
    few = est.n_failures_sampled < 5
    assert few.mean() > 0.9
    hit = (est.ci_low <= truth) & (truth <= est.ci_high)
    assert hit.mean() >= 0.87 and hit[few].mean() >= 0.87
    wald, _ = simulate(p, fail, rng=np.random.default_rng(seed), interval="wald", **kw)
    wald_hit = (wald.ci_low <= truth) & (truth <= wald.ci_high)
    assert wald_hit.mean() < 0.8 and wald_hit[few].mean() < 0.8


def test_fay_feuer_interval_is_conservative():
    rng = np.random.default_rng(10)
    p, fail = make_pool(n_wrong=3)
    hits = []
    for _ in range(300):
        plan = plan_sample(p, K=250, rng=rng, alpha=1.0, defensive=0.1)
        e = estimate_rate(plan, fail[plan.sampled_pool_index], interval="fay-feuer")[0]
        g = estimate_rate(plan, fail[plan.sampled_pool_index])[0]
        assert e.ci_high >= g.ci_high and e.ci_low == g.ci_low
        hits.append(e.ci_low <= fail.mean() <= e.ci_high)
    assert np.mean(hits) >= 0.95


def test_ci_zero_failures_rule_of_three():
    # Uniform Poisson sampling, nothing found: upper = -ln(0.05)(1 - pi)/pi failures.
    N, K = 1000, 100
    pi = np.full(K, K / N)
    est = estimate_from_sample(pi, np.zeros(K, bool), design="poisson", n_pool=N, n_unknown=N,
                               budget=K)  # fmt: skip
    assert est.p_hat[0] == 0 and est.ci_low[0] == 0
    assert math.isclose(est.ci_high[0], -math.log(0.05) * 9 / N)


@pytest.mark.parametrize("R", [0.0, 3.0])
def test_gamma_interval_without_variance_or_extra_weight(R):
    # v = 0 and w = 0: a point mass at R (the Gamma's shape R^2/0 gave NaN before).
    lo, hi = _gamma_interval(np.array([R]), np.zeros(1), np.zeros(1), 0.1)
    assert lo[0] == hi[0] == R


def test_with_replacement_certain_segment_interval_is_finite():
    # U is one segment with q = 1, drawn K = 3 times, a failure: T = 3/(3 * 1) = 1 failure
    # for sure, v = 0 and its weight (1 - q)/(K q) = 0. Interval [1, 1]/N, not NaN.
    est = estimate_from_sample(
        [1.0], [True], design="with-replacement", counts=[3], n_pool=5, n_unknown=1, budget=3
    )
    assert est.p_hat[0] == est.ci_low[0] == est.ci_high[0] == 0.2


def test_gamma_upper_limit_at_moderate_pi_by_hand():
    # Poisson, N = 100, |U| = 50; sampled pi = [0.5, 0.8, 0.5], failures [T, T, F].
    #   R = 1/0.5 + 1/0.8 = 2 + 1.25 = 3.25 failures
    #   v = (1 - 0.5)/0.5^2 + (1 - 0.8)/0.8^2 = 2 + 0.3125 = 2.3125
    #   failure weights (1 - pi)/pi = [1, 0.25]; no model weight: w = heaviest seen = 1
    #   upper: Gamma with mean M = R + w = 4.25 and variance V = v + w^2 = 3.3125,
    #          shape M^2/V = 18.0625/3.3125 = 5.45283, scale V/M = 0.779412
    #   lower: Gamma with mean 3.25, variance 2.3125 (shape 4.56757, scale 0.711538):
    #          its 5% point (1.21) is below the 2 failures in hand, so lower = 2.
    # Weight 1/pi instead of (1 - pi)/pi would give w = 2, M = 5.25, V = 6.3125.
    kw = dict(design="poisson", n_pool=100, n_unknown=50, budget=10.0)
    pi = np.array([0.5, 0.8, 0.5])
    f = np.array([True, True, False])
    est = estimate_from_sample(pi, f, **kw)
    upper = gamma_dist.ppf(0.95, 18.0625 / 3.3125, scale=3.3125 / 4.25)
    assert math.isclose(upper, 7.6175, rel_tol=1e-4)  # 1/pi weights would give 9.95
    assert math.isclose(est.ci_high[0], upper / 100, rel_tol=1e-10)
    assert est.ci_low[0] == 2 / 100
    assert math.isclose(est.var_hat[0], 2.3125 / 100**2, rel_tol=1e-14)
    assert est.variance_basis[0] == 0 and math.isclose(est.se[0], math.sqrt(2.3125) / 100)
    # A model weight heavier than any failure seen takes over: w = 1.5, M = 4.75,
    # V = 2.3125 + 2.25 = 4.5625.
    est = estimate_from_sample(pi, f, w_model=1.5, **kw)
    upper = gamma_dist.ppf(0.95, 4.75**2 / 4.5625, scale=4.5625 / 4.75)
    assert math.isclose(est.ci_high[0], upper / 100, rel_tol=1e-10)


def test_model_weight_by_hand():
    # U_r = two segments with pi = [0.5, 0.8] and p_n = [0.1, 0.3]; the pi = 1 segment is
    # left out. w = (1 - pi)/pi = [1, 0.25]: (0.1 * 1 + 0.3 * 0.25)/0.4 = 0.175/0.4 = 0.4375
    # (1/pi would give (0.2 + 0.375)/0.4 = 1.4375).
    w = model_weight([0.1, 0.3, 0.9], [0.5, 0.8, 1.0], design="poisson", K=2.3)
    assert math.isclose(w, 0.4375, rel_tol=1e-14)


@pytest.mark.parametrize(
    "w_model, w",
    [
        (2.0, 2.0),  # the plan's model weight
        # No model: the design's typical segment of U_r: |U_r| = 50 - 2 certain = 48 with
        # K_r = 10 - 2 = 8 expected draws, w0 = (48 - 8)/8 = 5 (rule of three at pi = 1/6).
        (None, 5.0),
    ],
)
def test_failures_sampled_with_certainty_keep_a_variance(w_model, w):
    # N = 100, |U| = 50, K = 10; sampled pi = [1, 1, 0.5, 0.5], the two pi = 1 segments fail.
    # The HT variance estimate is 0 (it sums over failures with pi < 1), but failures may
    # hide among the 48 segments with pi < 1: se = sqrt(w)/N, and the upper limit is
    # 2 + w (-ln 0.05) failures, the zero-failure rule of three on top of the two in hand.
    est = estimate_from_sample(
        [1.0, 1.0, 0.5, 0.5], [True, True, False, False], design="poisson", n_pool=100,
        n_unknown=50, budget=10.0, w_model=w_model,
    )[0]  # fmt: skip
    assert est.p_hat == 0.02 and est.var_hat == 0.0
    assert math.isclose(est.se, math.sqrt(w) / 100, rel_tol=1e-14)
    assert math.isclose(est.rel_var, (w / 100**2) / 0.02**2, rel_tol=1e-14)
    assert est.ci_low == 0.02
    assert math.isclose(est.ci_high, (2 + w * -math.log(0.05)) / 100, rel_tol=1e-12)
    assert "included with certainty (pi = 1)" in est.variance_note
    assert f"weight {w:.4g}" in est.variance_note and est.rel_var_note is None


def test_se_is_zero_only_for_a_census():
    # Every segment of U sampled with pi = 1: exact, se = 0, and a note says so.
    est = estimate_from_sample(
        [1.0, 1.0, 1.0], [True, False, False], design="poisson", n_pool=10, n_unknown=3,
        budget=3.0, known_failures=1,
    )[0]  # fmt: skip
    assert est.p_hat == est.ci_low == est.ci_high == 0.2 and est.se == 0
    assert "exact" in est.variance_note
    # Nothing found and p_hat = 0: se allows for one failure, rel_var is undefined, said why.
    est = estimate_from_sample(
        np.full(100, 0.1), np.zeros(100, bool), design="poisson", n_pool=1000, n_unknown=1000,
        budget=100.0,
    )[0]  # fmt: skip
    assert est.p_hat == 0 and math.isclose(est.se, 3 / 1000)  # sqrt(w0 = 900/100) / N
    assert math.isnan(est.rel_var) and "p_hat = 0" in est.rel_var_note


def test_single_draw_with_replacement_is_undefined_not_nan_interval():
    # One draw: no sample variance (se = inf, said why); the interval is the feasible range,
    # [1 failure in hand, 3 segments not seen to pass] / N, not NaN.
    est = estimate_from_sample(
        [0.5], [True], design="with-replacement", counts=[1], n_pool=5, n_unknown=3, budget=1
    )[0]
    assert math.isinf(est.se) and "K = 1" in est.variance_note
    assert (est.ci_low, est.ci_high) == (0.2, 0.6)
    assert math.isnan(est.rel_var) and "undefined" in est.rel_var_note


def test_ci_contains_found_and_excludes_passed():
    # Lower limit never below the failures in hand; upper never above the non-passing count.
    est = estimate_from_sample(
        [0.9, 0.9, 0.9], [True, True, False], design="poisson", n_pool=5, n_unknown=3,
        budget=2.7, known_failures=2,
    )  # fmt: skip
    # 2 known + 2 found = 4 failures for sure; the third unknown passed, so at most 4.
    # The sum (2 + 2/0.9)/5 exceeds that cap (HT is not range-respecting): p_hat is held
    # to it, and p_hat_unbiased keeps the sum.
    assert est.p_hat_unbiased[0] == pytest.approx((2 + 2 / 0.9) / 5, rel=1e-12)
    assert est.ci_low[0] == est.p_hat[0] == est.ci_high[0] == 4 / 5


# --------------------------------------------------------------------------------------------
# GP variance
# --------------------------------------------------------------------------------------------


def gp_posterior(N: int, seed: int, *, n_obs: int = 8):
    """Pool, posterior mean and covariance of an RBF GP conditioned on n_obs noisy points."""
    rng = np.random.default_rng(seed)
    X = rng.uniform(-2, 2, size=(N, 2))
    Xo = rng.uniform(-2, 2, size=(n_obs, 2))

    def k(A, B):
        d2 = ((A[:, None, :] - B[None, :, :]) ** 2).sum(-1)
        return 1.5 * np.exp(-0.5 * d2 / 0.8**2)

    Koo = k(Xo, Xo) + 0.05 * np.eye(n_obs)
    yo = rng.normal(size=n_obs)
    Kxo = k(X, Xo)
    A = np.linalg.solve(Koo, Kxo.T)
    mu = A.T @ yo
    Sigma = k(X, X) - Kxo @ A
    return mu, Sigma


def brute_force_gp_variance(mu, Sigma, gamma):
    sd = np.sqrt(np.diag(Sigma))
    s = (gamma - mu) / sd
    p = ndtr(s)
    total = float(np.sum(p * (1 - p)))
    N = mu.size
    for i in range(N):
        for j in range(i + 1, N):
            r = Sigma[i, j] / (sd[i] * sd[j])
            c = multivariate_normal.cdf([s[i], s[j]], mean=[0, 0], cov=[[1, r], [r, 1]])
            total += 2 * (c - p[i] * p[j])
    return total / N**2


@pytest.mark.parametrize("gamma", [-1.0, 0.0, 0.7])
def test_gp_variance_matches_brute_force(gamma):
    mu, Sigma = gp_posterior(50, seed=int(10 * gamma) + 20)

    def cov_block(rows, cols):
        return Sigma[np.ix_(rows, cols)]

    got = gp_variance_exact(mu, np.diag(Sigma), cov_block, gamma, h_tol=0.0)
    ref = brute_force_gp_variance(mu, Sigma, gamma)
    assert abs(got.var - ref) <= 1e-13
    assert got.skipped_bound == 0.0
    p_hat, bound = gp_estimate(ndtr((gamma - mu) / np.sqrt(np.diag(Sigma))))
    assert got.var <= bound + 1e-15 and math.isclose(got.h_mean, bound, rel_tol=1e-12)
    # Positive posterior correlations: Var well above the independent-units value mean(h)/N.
    assert got.var > 2 * bound / mu.size


def test_gp_variance_tiles_and_skips():
    mu, Sigma = gp_posterior(400, seed=3)
    sigma2 = np.diag(Sigma).copy()
    calls = []

    def cov_block(rows, cols):
        return Sigma[np.ix_(rows, cols)]

    full = gp_variance_exact(mu, sigma2, cov_block, 0.5, tile=10_000, h_tol=0.0)
    tiled = gp_variance_exact(
        mu, sigma2, cov_block, 0.5, tile=37, h_tol=0.0, progress=lambda d, n: calls.append((d, n))
    )
    assert abs(full.var - tiled.var) <= 1e-15
    n_t = math.ceil(400 / 37)
    assert calls[-1] == (n_t * (n_t + 1) // 2,) * 2
    # Skipping units with small h moves Var by no more than the returned bound.
    h = ndtr((0.5 - mu) / np.sqrt(sigma2)) * ndtr(-(0.5 - mu) / np.sqrt(sigma2))
    tol = float(np.quantile(h, 0.3))
    skip = gp_variance_exact(mu, sigma2, cov_block, 0.5, h_tol=tol)
    assert skip.n_kept < 400 and skip.skipped_bound > 0
    assert abs(skip.var - full.var) <= skip.skipped_bound


def test_gp_variance_known_points_and_perfect_correlation():
    # sigma = 0 rows (observed exactly) have h = 0 and are skipped without NaNs;
    # fully correlated duplicates give Var = h (they move together).
    mu = np.array([0.0, 0.0, 5.0])
    sigma2 = np.array([1.0, 1.0, 0.0])
    Sigma = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 0.0]])
    for h_tol in (0.0, 1e-12):
        got = gp_variance_exact(mu, sigma2, lambda r, c: Sigma[np.ix_(r, c)], 0.0, h_tol=h_tol)
        assert math.isclose(got.var, 4 * 0.25 / 9, rel_tol=1e-14) and got.n_kept == 2


@pytest.mark.parametrize("r", [-0.29, -0.05, 0.0, 0.001, 0.1, 0.2999, 0.3, 0.6, 0.95])
def test_gp_variance_two_units_any_correlation(r):
    # Two units: Var = (h1 + h2 + 2 cov) / 4, the pair term from the tetrachoric series
    # (|r| < 0.3) or Genz's quadrature (|r| >= 0.3); both against scipy's bivariate CDF.
    mu = np.array([0.3, -1.1])
    sigma2 = np.array([0.8, 1.7])
    c = r * math.sqrt(sigma2[0] * sigma2[1])
    Sigma = np.array([[sigma2[0], c], [c, sigma2[1]]])
    gamma = -0.4
    s = (gamma - mu) / np.sqrt(sigma2)
    p = ndtr(s)
    both = multivariate_normal.cdf(s, cov=[[1, r], [r, 1]])
    ref = (np.sum(p * (1 - p)) + 2 * (both - p[0] * p[1])) / 4
    got = gp_variance_exact(mu, sigma2, lambda i, j: Sigma[np.ix_(i, j)], gamma, h_tol=0.0)
    assert abs(got.var - ref) <= 1e-16


def test_bvn_cov_special_cases():
    h = np.array([0.0, 0.0, 1.3, -0.4, 2.0, 0.0])
    k = np.array([0.0, 0.7, -0.2, -0.4, 2.0, -1.0])
    for r in [-1.0, -0.95, -0.5, 0.0, 0.2, 0.93, 1.0]:
        got = bvn_cov(h, k, r)
        if abs(r) == 1:
            both = ndtr(np.minimum(h, k)) if r == 1 else np.maximum(ndtr(h) - ndtr(-k), 0)
        else:
            both = np.array(
                [
                    multivariate_normal.cdf([a, b], cov=[[1, r], [r, 1]])
                    for a, b in zip(h, k, strict=True)
                ]
            )
        np.testing.assert_allclose(got, both - ndtr(h) * ndtr(k), atol=2e-15)
    # Plackett at h = k = 0: Phi2 = 1/4 + asin(r)/(2 pi).
    assert math.isclose(bvn_cov(0.0, 0.0, 0.5), math.asin(0.5) / (2 * math.pi), rel_tol=1e-14)


def test_a_horvitz_thompson_sum_above_what_the_sample_allows_is_held_to_it():
    # Ten segments at pi 0.1; the sample holds one failure (weight 10) and two passes. The
    # sum says all ten fail, but two were seen to pass: at most 8 can. p_hat is 8 / 10,
    # the interval holds it, and p_hat_unbiased keeps the sum (the stages combine that).
    pi = np.array([0.1, 0.1, 0.1])
    fails = np.array([True, False, False])
    e = estimate_from_sample(pi, fails, design="poisson", n_pool=10, n_unknown=10, budget=1.0)
    assert e.cap[0] == pytest.approx(0.8)
    assert e.p_hat_unbiased[0] == pytest.approx(1.0, rel=1e-12)
    assert e.p_hat[0] == pytest.approx(0.8, rel=1e-12)
    assert 0.1 - 1e-12 <= e.ci_low[0] <= e.p_hat[0] <= e.ci_high[0] <= 0.8 + 1e-12
    # Below the cap nothing changes: p_hat is the sum.
    few = estimate_from_sample(pi, fails, design="poisson", n_pool=100, n_unknown=100, budget=10.0)
    assert few.p_hat[0] == few.p_hat_unbiased[0]


def test_a_hansen_hurwitz_sum_is_held_between_the_failures_found_and_the_cap():
    # With replacement, T = (1/K) sum over draws of y / q.
    # Above the cap: 10 segments, the failure at q 0.02 drawn once and a pass once (K 2):
    # T = (1/2)(1/0.02) = 25 failures, but one was seen to pass: at most 9.
    hi = estimate_from_sample([0.02, 0.98 / 9], [True, False], design="with-replacement",
                              n_pool=10, n_unknown=10, budget=2.0, counts=[1, 1])  # fmt: skip
    assert hi.p_hat_unbiased[0] == pytest.approx(2.5, rel=1e-12)
    assert hi.p_hat[0] == pytest.approx(0.9, rel=1e-12) == pytest.approx(hi.cap[0])
    assert hi.ci_low[0] <= hi.p_hat[0] <= hi.ci_high[0] <= 0.9 + 1e-12
    # Below the failures in hand: the failure at q 0.5 drawn once, a pass at q 0.25 three
    # times (K 4): T = (1/4)(1/0.5) = 0.5 failures, against 1 found.
    lo = estimate_from_sample([0.5, 0.25], [True, False], design="with-replacement",
                              n_pool=10, n_unknown=10, budget=4.0, counts=[1, 3])  # fmt: skip
    assert lo.p_hat_unbiased[0] == pytest.approx(0.05, rel=1e-12)
    assert lo.p_hat[0] == pytest.approx(0.1, rel=1e-12)  # 1 / 10
    assert 0.1 - 1e-12 <= lo.ci_low[0] <= lo.p_hat[0] <= lo.ci_high[0]
