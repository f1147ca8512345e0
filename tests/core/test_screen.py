"""The screened (two-phase) estimate: checked by enumerating every pair of samples.

Reference: on a pool of 7 segments every phase-1 sample S1 and every phase-2 sample S2 of
it (3^7 = 2,187 pairs) is enumerated with its probability, so the estimator's mean,
variance and the variance estimate's mean are exact, not Monte Carlo.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from bams_cli.core import design as dz
from bams_cli.core import screen as sc
from bams_cli.core.estimate import estimate_from_sample

N = 7
FAIL = np.array([1, 0, 1, 0, 0, 1, 0], dtype=bool)
# The cheap level's value: low where level 0 fails, but not always (segment 5 fails
# unseen, segment 3 looks like a failure and is not).
CHEAP = np.array([0.1, 0.9, 0.3, 0.2, 0.8, 0.7, 0.6])
PI1 = np.array([0.9, 0.3, 0.6, 0.5, 0.2, 0.4, 0.7])
K, COST = 3.0, 0.25


def _pi2(s1: np.ndarray, K: float = K, cost: float = COST) -> np.ndarray:
    """Phase 2 as the tool draws it: the design chosen from what the screen showed."""
    p2 = np.clip(1.0 - CHEAP[s1], 0.01, 1.0) ** 2
    K2 = sc.confirm_budget(K, cost, s1.size)
    return sc.confirm_design(p2, K2=K2, posterior=dz.risk_posterior([])).pi


def _enumerate(K: float = K, cost: float = COST):
    """(probability, S1, pi2 over S1, S2 as a mask over S1) for every pair of samples."""
    for bits in itertools.product((0, 1), repeat=N):
        in1 = np.array(bits, dtype=bool)
        P1 = float(np.prod(np.where(in1, PI1, 1.0 - PI1)))
        s1 = np.flatnonzero(in1)
        pi2 = _pi2(s1, K, cost)
        for bits2 in itertools.product((0, 1), repeat=s1.size):
            in2 = np.array(bits2, dtype=bool)
            P2 = float(np.prod(np.where(in2, pi2, 1.0 - pi2))) if s1.size else 1.0
            yield P1 * P2, s1, pi2, in2


# (3.0, 0.25): K2 = 3 - |S1|/4 >= 1.25; (1.5, 0.4): screens of 2 or more reach K2's floor.
@pytest.mark.parametrize(("K", "cost"), [(K, COST), (1.5, 0.4)])
def test_the_screened_estimate_is_unbiased_and_its_variance_splits_by_phase(K, cost):
    mean = second = v_mean = total_p = 0.0
    phase2 = 0.0  # E[Var(T | S1)], accumulated once per S1
    seen_s1: set[tuple[int, ...]] = set()
    for P, s1, pi2, in2 in _enumerate(K, cost):
        total_p += P
        pi = sc.confirmed_pi(PI1[s1], pi2) if s1.size else np.zeros(0)
        y = FAIL[s1]
        T = float(np.sum(y[in2] / pi[in2]))
        v = float(np.sum(y[in2] * (1.0 - pi[in2]) / pi[in2] ** 2))
        mean += P * T
        second += P * T * T
        v_mean += P * v
        key = tuple(s1)
        if key not in seen_s1:
            seen_s1.add(key)
            P1 = float(np.prod(np.where(np.isin(np.arange(N), s1), PI1, 1.0 - PI1)))
            if s1.size:
                phase2 += P1 * sc.phase2_variance(y, PI1[s1], pi2)
    assert total_p == pytest.approx(1.0, abs=1e-12)
    assert mean == pytest.approx(FAIL.sum(), abs=1e-10)
    var = second - mean**2
    assert var == pytest.approx(sc.phase1_variance(FAIL, PI1) + phase2, rel=1e-10)
    # The one-phase Poisson form at pi = pi1 pi2 estimates it without bias.
    assert v_mean == pytest.approx(var, rel=1e-10)
    # Weighting by pi2 alone (forgetting the screen) is biased.
    wrong = sum(
        P * float(np.sum(FAIL[s1][in2] / pi2[in2])) for P, s1, pi2, in2 in _enumerate(K, cost)
    )
    assert abs(wrong - FAIL.sum()) > 0.1


def test_estimate_from_sample_takes_a_screened_sample_at_pi1_pi2():
    # One pair of samples: the HT sum and its variance estimate from the tool's estimator.
    s1 = np.array([0, 2, 3, 5])
    pi2 = _pi2(s1)
    in2 = np.array([True, True, False, True])
    pi = sc.confirmed_pi(PI1[s1], pi2)[in2]
    y = FAIL[s1][in2]
    est = estimate_from_sample(
        pi, y, design="poisson", n_pool=N, n_unknown=N, budget=K, confidence=0.9
    )
    assert est.p_hat_unbiased is not None
    assert est.p_hat_unbiased[0] * N == pytest.approx(float(np.sum(y / pi)), rel=1e-12)
    assert est.var_hat[0] * N**2 == pytest.approx(float(np.sum(y * (1 - pi) / pi**2)), rel=1e-12)


def test_the_confirmation_budget_pays_for_the_screen_and_never_reaches_zero():
    assert sc.screen_size(100.0, 0.1, 0.3, 20_000) == pytest.approx(300.0)
    assert sc.screen_size(100.0, 0.1, 0.3, 250) == 250.0  # one cheap run per segment at most
    assert sc.confirm_budget(100.0, 0.1, 300) == pytest.approx(70.0)
    # A screen drawn larger than expected still leaves a level-0 run to confirm with:
    # every screened segment must keep pi2 > 0 for the estimate to stay unbiased.
    assert sc.confirm_budget(10.0, 0.5, 40) == 1.0
    pi2 = sc.confirm_design(np.full(5, 0.1), K2=1.0, posterior=dz.risk_posterior([])).pi
    assert np.all(pi2 > 0) and pi2.sum() == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("K", "cost", "share", "match"),
    [(0.0, 0.1, 0.3, "K must"), (10.0, 1.0, 0.3, "cost"), (10.0, 0.1, 1.0, "share")],
)
def test_a_screen_out_of_range_is_refused(K, cost, share, match):
    with pytest.raises(ValueError, match=match):
        sc.screen_size(K, cost, share, 100)


def test_confirmed_pi_refuses_probabilities_outside_0_1():
    with pytest.raises(ValueError, match="pi2"):
        sc.confirmed_pi([0.5, 0.5], [0.5, 0.0])
    with pytest.raises(ValueError, match="shape"):
        sc.confirmed_pi([0.5], [0.5, 0.5])


def test_the_screen_spends_its_share_and_draws_likelier_failures_more_often():
    p = np.geomspace(1e-5, 0.3, 400)
    prior = dz.risk_posterior([])
    pi1 = sc.screen_design(p, K=20.0, cost=0.1, share=0.3, posterior=prior).pi
    assert pi1.sum() == pytest.approx(sc.screen_size(20.0, 0.1, 0.3, p.size), rel=1e-9)
    assert pi1.sum() == pytest.approx(60.0, rel=1e-9)  # 0.3 of K at 0.1 per cheap run
    assert np.all(np.diff(pi1) >= -1e-12) and pi1[-1] > 2 * pi1[0]


def test_the_confirmation_follows_the_refitted_model_and_an_empty_screen_confirms_nothing():
    prior = dz.risk_posterior([])
    p2 = np.array([1e-4, 1e-3, 0.01, 0.1, 0.5, 0.9])
    pi2 = sc.confirm_design(p2, K2=2.0, posterior=prior).pi
    assert pi2.sum() == pytest.approx(2.0, rel=1e-9)
    assert np.all(np.diff(pi2) >= -1e-12) and pi2[-1] > 2 * pi2[0] > 0
    empty = sc.confirm_design(np.zeros(0), K2=2.0, posterior=prior)
    assert empty.pi.size == 0


@pytest.mark.parametrize("with_leads", [False, True])
def test_screen_trials_match_a_monte_carlo_of_the_whole_two_phase_design(with_leads):
    # core.evaluate.screen_trials (the benchmark's measure of the screened default) against
    # the design simulated end to end: draw S1, plan pi2 from a refit that sees S1's cheap
    # values, draw S2, sum y / (pi1 pi2). Its variance (phase 1 exact, phase 2 averaged
    # over the trials' screens) and its recall must be the simulation's, and the sum
    # unbiased. A refit that ignored the screen, a variance without phase 1's term, or a
    # K2 that did not pay for the cheap runs would each miss by far more than the tolerance.
    from bams_cli.core.evaluate import screen_trials

    rng = np.random.default_rng(3)
    n = 600
    p = rng.beta(0.4, 6.0, n)
    fail = rng.random(n) < p
    cheap = np.where(fail, 0.7, 0.05) + 0.1 * rng.random(n)  # what a cheap run tells
    known = np.zeros(n, bool)
    known[np.argsort(-p)[:15]] = True
    have = np.zeros(n, bool)
    have[rng.choice(n, 300, replace=False)] = True  # cheap results already in the log
    K, cost, share = 60.0, 0.2, 0.3
    # Open leads: cheap results in hand, no level-0 one, most of them failures the model
    # rates low; taken with certainty in both phases.
    leads = np.zeros(n, bool)
    if with_leads:
        leads[rng.choice(np.flatnonzero(have & ~known & (p < 0.05)), 12, replace=False)] = True

    def refit(s1: np.ndarray) -> np.ndarray:
        return np.clip(0.5 * p[s1] + 0.5 * cheap[s1], 1e-6, 1.0)

    t = screen_trials(
        p, fail, K=K, cost=cost, share=share, refit=refit, known=known, cheap_known=have,
        leads=leads if with_leads else None, n_trials=3000, rng=np.random.default_rng(4),
    )  # fmt: skip
    U = np.flatnonzero(~known)
    post = dz.risk_posterior([])
    pi1 = sc.screen_design(p[U], K=K, cost=cost, share=share, posterior=post, leads=leads[U]).pi
    assert np.all(pi1[leads[U]] == 1.0)
    sims = np.empty(20_000)
    found = np.empty(sims.size)
    mc = np.random.default_rng(5)
    for i in range(sims.size):
        s1 = np.flatnonzero(mc.random(U.size) < pi1)
        runs = int((~have[U[s1]]).sum())
        K2 = min(sc.confirm_budget(K, cost, runs), float(s1.size))
        pi2 = sc.confirm_design(refit(U[s1]), K2=K2, posterior=post, leads=leads[U[s1]]).pi
        s2 = mc.random(s1.size) < pi2
        y = fail[U[s1]] & s2
        sims[i] = float((1.0 / (pi1[s1] * pi2))[y].sum())
        found[i] = float(y.sum())
    F_U = int(fail[U].sum())
    se = sims.std(ddof=1) / np.sqrt(sims.size)
    assert abs(sims.mean() - F_U) < 4 * se  # unbiased
    assert t.var * n**2 == pytest.approx(sims.var(ddof=1), rel=0.06)
    F = int(fail.sum())
    assert t.recall.mean() == pytest.approx((fail[known].sum() + found.mean()) / F, rel=0.03)
    # The uniform comparison: K level-0 runs over U, Poisson.
    k = K / U.size
    assert t.var_uniform * n**2 == pytest.approx(F_U * (1 - k) / k, rel=1e-12)
    assert t.rate == F / n and t.screened.mean() == pytest.approx(pi1.sum(), rel=0.02)


def test_leads_are_screened_and_confirmed_with_certainty_and_the_rest_keeps_its_budget():
    p = np.geomspace(1e-5, 0.3, 400)
    lead = np.zeros(p.size, bool)
    lead[[3, 50, 51, 200]] = True  # leads the model rates low
    prior = dz.risk_posterior([])
    pi1 = sc.screen_design(p, K=20.0, cost=0.1, share=0.3, posterior=prior, leads=lead).pi
    assert np.all(pi1[lead] == 1.0)
    # The other segments keep the screen's size (the leads' cheap runs are in the log).
    assert pi1[~lead].sum() == pytest.approx(60.0, rel=1e-9)
    plain = sc.screen_design(p[~lead], K=20.0, cost=0.1, share=0.3, posterior=prior).pi
    np.testing.assert_allclose(pi1[~lead], plain, rtol=1e-12)
    # Phase 2: the leads out of K2, the rest of K2 over the other screened segments, and
    # never less than one run's worth while any remain.
    p2 = np.geomspace(1e-4, 0.5, 30)
    l2 = np.zeros(p2.size, bool)
    l2[[0, 1, 7]] = True
    pi2 = sc.confirm_design(p2, K2=8.0, posterior=prior, leads=l2).pi
    assert np.all(pi2[l2] == 1.0) and pi2[~l2].sum() == pytest.approx(5.0, rel=1e-9)
    assert sc.confirm_size(8.0, 3, p2.size) == pytest.approx(pi2.sum(), rel=1e-9) == 8.0
    tight = sc.confirm_design(p2, K2=3.5, posterior=prior, leads=l2).pi
    assert np.all(tight[~l2] > 0) and tight[~l2].sum() == pytest.approx(1.0, rel=1e-9)
    # The leads use K2 up: the plan asks for more than K2 runs on average, and says so.
    assert sc.confirm_size(3.5, 3, p2.size) == pytest.approx(tight.sum(), rel=1e-9) == 4.0
    every = sc.confirm_design(p2[l2], K2=2.0, posterior=prior, leads=np.ones(3, bool))
    assert np.all(every.pi == 1.0) and every.name == "leads"
    assert sc.confirm_size(2.0, 3, 3) == 3.0 and sc.confirm_size(40.0, 0, 30) == 30.0
    with pytest.raises(ValueError, match="leads has shape"):
        sc.confirm_design(p2, K2=8.0, posterior=prior, leads=l2[:5])


def _phase2_moments(P1: float, s1: np.ndarray, pi2: np.ndarray, pi: np.ndarray):
    """Given S1 (drawn with probability P1): every S2 enumerated, the sums over them of
    P T, P T^2 and P v (v the Poisson variance estimate at pi = pi1 pi2)."""
    mean = second = v_mean = 0.0
    for bits2 in itertools.product((0, 1), repeat=s1.size):
        in2 = np.array(bits2, dtype=bool)
        P = P1 * float(np.prod(np.where(in2, pi2, 1.0 - pi2)))
        if P == 0.0:
            continue
        y = FAIL[s1] & in2
        T = float(np.sum(1.0 / pi[y]))
        mean += P * T
        second += P * T * T
        v_mean += P * float(np.sum((1.0 - pi[y]) / pi[y] ** 2))
    return mean, second, v_mean


def test_the_screened_estimate_with_certain_leads_is_unbiased_by_enumeration():
    # Segments 0 and 5 are leads (5 fails at level 0 unseen by the cheap level's value
    # here, which the refit reads as a pass): pi1 = pi2 = 1 there, the rest as drawn.
    lead = np.zeros(N, bool)
    lead[[0, 5]] = True
    pi1 = np.where(lead, 1.0, PI1)
    mean = second = v_mean = 0.0
    for bits in itertools.product((0, 1), repeat=N):
        in1 = np.array(bits, dtype=bool)
        P1 = float(np.prod(np.where(in1, pi1, 1.0 - pi1)))
        if P1 == 0.0:
            continue
        s1 = np.flatnonzero(in1)
        p2 = np.clip(1.0 - CHEAP[s1], 0.01, 1.0) ** 2
        K2 = sc.confirm_budget(K, COST, int((~lead[s1]).sum()))
        pi2 = sc.confirm_design(p2, K2=K2, posterior=dz.risk_posterior([]), leads=lead[s1]).pi
        assert np.all(pi2[lead[s1]] == 1.0)
        pi = sc.confirmed_pi(pi1[s1], pi2)
        m, s2, v = _phase2_moments(P1, s1, pi2, pi)
        mean, second, v_mean = mean + m, second + s2, v_mean + v
    assert mean == pytest.approx(FAIL.sum(), abs=1e-10)
    assert v_mean == pytest.approx(second - mean**2, rel=1e-10)


def test_allowance_pi_prices_the_unscreened_at_pi1_times_the_risk_weighted_mean_pi2():
    pi1 = np.array([0.5, 0.2, 0.1, 0.8])
    s1 = np.array([True, False, True, False])
    risk = np.array([3.0, 9.0, 1.0, 9.0])  # S1's risks 3 and 1: mean pi2 (3 0.6 + 0.3)/4
    got = sc.allowance_pi(pi1, s1, np.array([0.6, 0.3]), risk)
    np.testing.assert_allclose(got, [0.3, 0.2 * 0.525, 0.03, 0.8 * 0.525])
    # Not the plain mean (0.45), nor the smallest (0.3): the risk weights it.
    assert not np.allclose(got[1], 0.2 * 0.45) and not np.allclose(got[1], 0.2 * 0.3)
    # An empty screen: pi1 alone.
    np.testing.assert_allclose(
        sc.allowance_pi(pi1, np.zeros(4, bool), np.zeros(0), np.ones(4)), pi1
    )
    # The bound w_max rests on: the smallest pi2.
    np.testing.assert_allclose(
        sc.min_allowance_pi(pi1, s1, np.array([0.6, 0.3])), [0.3, 0.06, 0.03, 0.24]
    )
    with pytest.raises(ValueError, match="over U"):
        sc.allowance_pi(pi1, s1, np.array([0.6]), risk)
    for bad in (np.nan, -1.0):
        with pytest.raises(ValueError, match="finite and >= 0"):
            sc.allowance_pi(pi1, s1, np.array([0.6, 0.3]), np.array([3.0, bad, 1.0, 9.0]))
    # A screen whose risk is all zero: the plain mean of pi2.
    np.testing.assert_allclose(
        sc.allowance_pi(pi1, s1, np.array([0.6, 0.3]), np.zeros(4))[1], 0.2 * 0.45
    )


@pytest.mark.slow
@pytest.mark.parametrize("with_leads", [False, True])
def test_the_screened_default_drawn_ten_thousand_times_is_unbiased_and_covers(with_leads):
    # Issue 12's check for the default estimate where it screens: 100 screens (S1 drawn,
    # pi2 from a refit that sees S1's cheap runs) x 100 confirmations each, from a known
    # truth whose model under-predicts the rate; the estimate and its 90% interval as
    # `estimate` computes them (estimate_from_sample at pi1 pi2, the "mean" allowance).
    from bams_cli.core.estimate import estimate_from_sample

    rng = np.random.default_rng(12)
    N = 2000
    p = rng.beta(0.05, 10, N)
    fail = rng.random(N) < np.clip(p * 1.5, 0, 1)
    cheap_fail = np.where(rng.random(N) < 0.85, fail, ~fail)  # a cheap level that errs
    known = np.zeros(N, bool)
    known[rng.choice(N, 40, replace=False)] = True
    U = np.flatnonzero(~known)
    K, cost, share = 5.0 * fail.sum() * 0.6, 0.1, 0.3
    post = dz.risk_posterior([])
    # Open leads: segments discovery ran at the cheap level, which failed there, taken
    # with certainty in both phases (the cheap level errs, so some of them pass).
    lead = np.zeros(U.size, bool)
    if with_leads:
        seen = cheap_fail[U] & (rng.random(U.size) < 0.3)
        # The cap estimate --plan applies (most of them are cheap-level false alarms).
        lead = dz.certain_leads(p[U], np.zeros(U.size, bool), seen, sc.lead_budget(K, share))
        assert 5 <= lead.sum() < seen.sum()
    pi1 = sc.screen_design(p[U], K=K, cost=cost, share=share, posterior=post, leads=lead).pi
    rate, Fk = fail.mean(), int(fail[known].sum())
    p_hat, lo, hi = [], [], []
    for _ in range(100):
        s1 = rng.random(U.size) < pi1
        idx = np.flatnonzero(s1)
        refit = np.clip(0.3 * p[U] + 0.6 * cheap_fail[U] * s1, 1e-6, 1.0)  # sees S1's runs
        K2 = min(sc.confirm_budget(K, cost, int((s1 & ~lead).sum())), float(idx.size))
        pi2 = sc.confirm_design(refit[idx], K2=K2, posterior=post, leads=lead[idx]).pi
        counts = (rng.random((idx.size, 100)) < pi2[:, None]).astype(np.int64)
        # The allowance over U without the leads, as ``screening.confirm_screen`` takes it.
        rest = ~lead
        allow = post.allowance_risk(refit)[rest]
        w_model = dz.unseen_failure_weight(
            allow, sc.allowance_pi(pi1[rest], s1[rest], pi2[~lead[idx]], allow)
        )
        est = estimate_from_sample(
            sc.confirmed_pi(pi1[idx], pi2), fail[U][idx], design="poisson", n_pool=N,
            n_unknown=U.size, budget=K2, counts=counts, known_failures=Fk, confidence=0.9,
            w_model=w_model,
        )  # fmt: skip
        p_hat.append(est.p_hat_unbiased.ravel())
        lo.append(est.ci_low.ravel())
        hi.append(est.ci_high.ravel())
    ph, lo_, hi_ = (np.concatenate(a) for a in (p_hat, lo, hi))
    assert ph.size == 10_000
    # Draws share their screen 100 at a time: the SE is the screens' spread of their means.
    se = ph.reshape(100, 100).mean(axis=1).std(ddof=1) / 10.0
    assert abs(ph.mean() - rate) < 3 * se
    cover = np.mean((lo_ <= rate) & (rate <= hi_))
    below = np.mean(hi_ < rate)
    assert cover >= 0.88 and below <= 0.05, (cover, below)


def test_screen_trials_plan_pi1_and_pi2_under_their_own_priors(monkeypatch):
    # The benchmark measures the screen as `estimate --plan` draws it: pi1 under the
    # study's prior, pi2 under the confirmation's (``benchmark.screen_default`` passes both).
    from bams_cli import defaults
    from bams_cli.core.evaluate import screen_trials

    seen: dict[str, list[tuple[float, float]]] = {"screen": [], "confirm": []}
    real_s, real_c = sc.screen_design, sc.confirm_design

    def spy_s(*a, posterior, **k):
        seen["screen"].append(tuple(posterior.prior))
        return real_s(*a, posterior=posterior, **k)

    def spy_c(*a, posterior, **k):
        seen["confirm"].append(tuple(posterior.prior))
        return real_c(*a, posterior=posterior, **k)

    monkeypatch.setattr(sc, "screen_design", spy_s)
    monkeypatch.setattr(sc, "confirm_design", spy_c)
    rng = np.random.default_rng(3)
    p = rng.beta(0.4, 6.0, 300)
    fail = rng.random(300) < p
    screen_trials(
        p, fail, K=30.0, cost=0.2, share=0.3, refit=lambda s1: p[s1], n_trials=3,
        prior=defaults.RISK_MIX_PRIOR, confirm_prior=defaults.RISK_MIX_PRIOR_CONFIRM,
        rng=np.random.default_rng(4),
    )  # fmt: skip
    assert set(seen["screen"]) == {defaults.RISK_MIX_PRIOR}
    assert set(seen["confirm"]) == {defaults.RISK_MIX_PRIOR_CONFIRM} and len(seen["confirm"]) == 3


def test_the_screens_own_leads_are_its_lowest_cheap_results_within_their_share():
    cheap = np.array([0.5, 0.1, np.nan, 0.3, 0.1, 0.9, 0.2])
    # floor(0.5 x 6.9) = 3: the three lowest, the tie at 0.1 both in, NaN never.
    got = sc.screen_leads(cheap, 6.9, share=0.5)
    np.testing.assert_array_equal(np.flatnonzero(got), [1, 4, 6])
    # The open leads count against the share and are not returned again.
    taken = np.zeros(cheap.size, bool)
    taken[[0, 5]] = True
    np.testing.assert_array_equal(
        np.flatnonzero(sc.screen_leads(cheap, 6.9, share=0.5, taken=taken)), [1]
    )
    # A tie at the cut goes by position; a share of 0, or too little K2, takes none.
    np.testing.assert_array_equal(np.flatnonzero(sc.screen_leads(cheap, 2.0, share=0.5)), [1])
    assert not sc.screen_leads(cheap, 1.9, share=0.5).any()
    assert not sc.screen_leads(cheap, 100.0, share=0.0).any()
    assert sc.screen_leads(cheap, 100.0, share=0.9).sum() == 6  # every finite result
    with pytest.raises(ValueError, match=r"\[0, 1\)"):
        sc.screen_leads(cheap, 5.0, share=1.0)


def test_the_screened_estimate_with_its_own_leads_is_unbiased_by_enumeration():
    # pi2 depends on which segments S1 drew and on their cheap results (the lowest of them
    # confirmed with certainty, the rest by the model's p2): every pair of samples
    # enumerated, the sum must be unbiased and the Poisson form at pi1 pi2 must estimate
    # its variance without bias; the rule must move pi2 from the model's design.
    mean = second = v_mean = 0.0
    n_leads = 0
    moved = 0.0
    for bits in itertools.product((0, 1), repeat=N):
        in1 = np.array(bits, dtype=bool)
        P1 = float(np.prod(np.where(in1, PI1, 1.0 - PI1)))
        s1 = np.flatnonzero(in1)
        if s1.size == 0:
            continue
        p2 = np.clip(1.0 - CHEAP[s1], 0.01, 1.0) ** 2
        K2 = min(sc.confirm_budget(K, COST, s1.size), float(s1.size))
        own = sc.screen_leads(CHEAP[s1], K2, share=0.5)
        n_leads += int(own.sum())
        post = dz.risk_posterior([])
        pi2 = sc.confirm_design(p2, K2=K2, posterior=post, leads=own).pi
        moved = max(
            moved, float(np.abs(pi2 - sc.confirm_design(p2, K2=K2, posterior=post).pi).max())
        )
        pi = sc.confirmed_pi(PI1[s1], pi2)
        m, s2, v = _phase2_moments(P1, s1, pi2, pi)
        mean, second, v_mean = mean + m, second + s2, v_mean + v
    assert n_leads > 0 and moved > 0.2
    assert mean == pytest.approx(FAIL.sum(), abs=1e-10)
    assert v_mean == pytest.approx(second - mean**2, rel=1e-10)


def test_screen_trials_take_the_screens_own_leads_as_a_monte_carlo_of_the_design_does():
    # screen_trials with the cheap results (the benchmark's measure of the screened
    # default) against the design simulated end to end with the same rule: unbiased, the
    # same variance and recall; and the leads raise recall where the cheap results rank
    # the failures and the refit does not.
    from bams_cli.core.evaluate import screen_trials

    rng = np.random.default_rng(7)
    n = 800
    fail = rng.random(n) < 0.03
    cheap = np.where(fail, 0.0, 1.0) + 0.8 * rng.standard_normal(n)
    p = np.full(n, 0.03)
    K, cost, share = 60.0, 0.2, 0.3

    def refit(s1: np.ndarray) -> np.ndarray:  # a model that reads the cheap level as weak
        return np.full(s1.size, 0.03)

    kw = {"K": K, "cost": cost, "share": share, "refit": refit, "n_trials": 2000}
    t = screen_trials(p, fail, cheap=cheap, rng=np.random.default_rng(8), **kw)
    plain = screen_trials(p, fail, rng=np.random.default_rng(8), **kw)
    post = dz.risk_posterior([])
    pi1 = sc.screen_design(p, K=K, cost=cost, share=share, posterior=post).pi
    sims = np.empty(20_000)
    found = np.empty(sims.size)
    mc = np.random.default_rng(9)
    for i in range(sims.size):
        s1 = np.flatnonzero(mc.random(n) < pi1)
        K2 = min(sc.confirm_budget(K, cost, s1.size), float(s1.size))
        own = sc.screen_leads(cheap[s1], K2)
        pi2 = sc.confirm_design(refit(s1), K2=K2, posterior=post, leads=own).pi
        y = fail[s1] & (mc.random(s1.size) < pi2)
        sims[i] = float((1.0 / (pi1[s1] * pi2))[y].sum())
        found[i] = float(y.sum())
    assert abs(sims.mean() - fail.sum()) < 4 * sims.std(ddof=1) / np.sqrt(sims.size)
    assert t.var * n**2 == pytest.approx(sims.var(ddof=1), rel=0.06)
    assert t.recall.mean() == pytest.approx(found.mean() / fail.sum(), rel=0.03)
    assert t.recall.mean() > 1.5 * plain.recall.mean() and t.var < plain.var
