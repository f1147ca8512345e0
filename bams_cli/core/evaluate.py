"""Evaluation against ground truth (paper section 4, "Evaluation criteria"; DESIGN.md, "Evaluation").

Only meaningful where every segment's level-0 outcome is known (sample data, the paper's
synthetic protocol): retention-recall curves, the recall of an importance-sampling plan, the
mean metric of each batch's picks (paper Table 1), and a DPP pick of a few diverse likely
failures for display (paper Figure 3).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import threadpool_limits

from bams_cli import defaults
from bams_cli.core.design import RiskPosterior, certain_leads
from bams_cli.core.estimate import DESIGNS, Design, RateEstimates, SamplePlan, _as_columns

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def retention_recall(
    scores: ArrayLike,
    is_failure: ArrayLike,
    retention_grid: ArrayLike,
    *,
    rate: float | None = None,
) -> FloatArray:
    """Recall of the top-scored segments at retention r p N (paper section 4, retention-recall).

    Segments are ranked by score, highest first. Retention is measured in units of p N (the
    number of failures), so r = 1 keeps the p N highest-scoring segments and recall 1 at
    r = 2 means precision 0.5. At retention r the top floor(r p N) segments are kept (the
    retained count never exceeds the budget; a relative 1e-9 slack absorbs rounding in r p N).

    Ties are broken by a stable sort: among equal scores the lower pool index ranks first.
    Scores with many ties (e.g. p_n saturated at 0 or 1) therefore make the curve depend on
    pool order; for a random-order baseline (MC) pass random scores.

    Parameters
    ----------
    scores : array_like of shape (n_pool,)
        Ranking score, e.g. p_n; finite.
    is_failure : array_like of bool, shape (n_pool,)
        True level-0 failure indicator.
    retention_grid : array_like of shape (n_r,)
        Retention levels r >= 0 in units of p N.
    rate : float, optional
        p; default the true rate mean(is_failure).

    Returns
    -------
    recall : ndarray of shape (n_r,)
        Fraction of all failures among the retained segments.
    """
    scores = np.asarray(scores, dtype=np.float64)
    fail = np.asarray(is_failure, dtype=bool)
    grid = np.asarray(retention_grid, dtype=np.float64)
    if scores.shape != fail.shape or scores.ndim != 1:
        raise ValueError(
            f"scores and is_failure must be 1-d of equal length; got {scores.shape}, {fail.shape}"
        )
    if not np.all(np.isfinite(scores)):
        raise ValueError("scores must be finite; got NaN or inf")
    if np.any(grid < 0):
        raise ValueError("retention_grid must be >= 0")
    n = scores.size
    F = int(fail.sum())
    if F == 0:
        raise ValueError("is_failure has no failures: recall is undefined")
    p = F / n if rate is None else float(rate)
    order = np.argsort(-scores, kind="stable")
    hits = np.concatenate(([0], np.cumsum(fail[order])))
    x = grid * p * n
    n_keep = np.minimum(np.floor(x * (1.0 + 1e-9)).astype(np.int64), n)
    return hits[n_keep] / F


def _pool_failures(plan: SamplePlan, is_failure: ArrayLike) -> NDArray[np.bool_]:
    fail = np.asarray(is_failure, dtype=bool)
    if fail.ndim == 1:
        fail = fail[:, None]
    if fail.shape[0] != plan.n_pool:
        raise ValueError(f"is_failure must have {plan.n_pool} rows (the pool); got {fail.shape}")
    return fail


def is_recall(plan: SamplePlan, is_failure: ArrayLike) -> FloatArray:
    """Realised IS recall: fraction of all failures that are known or in the sample.

    Parameters
    ----------
    plan : SamplePlan
    is_failure : array_like of bool, shape (n_pool,) or (n_pool, m)
        True failure indicator over the whole pool, one column per gamma.

    Returns
    -------
    recall : ndarray of shape (m,)
    """
    fail = _pool_failures(plan, is_failure)
    in_hand = np.ones(plan.n_pool, bool)
    in_hand[plan.unknown] = False  # known stratum stays True
    in_hand[plan.sampled_pool_index] = True
    F = fail.sum(axis=0)
    return (fail & in_hand[:, None]).sum(axis=0) / np.where(F > 0, F, np.nan)


def expected_is_recall(plan: SamplePlan, is_failure: ArrayLike) -> FloatArray:
    """E[IS recall] over the design: (known failures + sum_{failures in U} pi_i) / F.

    Exact for every design, since ``plan.pi`` is each segment's probability of being in the
    sample: pi for poisson and fixed, 1 - (1 - q)^K with replacement (so even a perfect q
    reaches only 1 - (1 - 1/F)^K at K draws over F failures; DESIGN.md).

    Parameters
    ----------
    plan : SamplePlan
    is_failure : array_like of bool, shape (n_pool,) or (n_pool, m)

    Returns
    -------
    recall : ndarray of shape (m,)
    """
    fail = _pool_failures(plan, is_failure)
    prob = np.ones(plan.n_pool)
    prob[plan.unknown] = plan.pi
    F = fail.sum(axis=0)
    return (prob @ fail) / np.where(F > 0, F, np.nan)


def _median_distance(X: FloatArray, max_points: int = 2000) -> float:
    """Median pairwise Euclidean distance over (at most) the first ``max_points`` rows."""
    Y = X[:max_points]
    sq = np.sum(Y**2, axis=1)
    d2 = np.maximum(sq[:, None] + sq[None, :] - 2.0 * Y @ Y.T, 0.0)
    iu = np.triu_indices(Y.shape[0], k=1)
    med = float(np.sqrt(np.median(d2[iu]))) if iu[0].size else 1.0
    return med if med > 0 else 1.0


def dpp_diverse(
    features: ArrayLike,
    quality: ArrayLike,
    k: int,
    *,
    lengthscale: float | None = None,
) -> IntArray:
    """k diverse, likely failures: greedy MAP of a DPP with L = diag(q) S diag(q).

    S_ij = exp(-|x_i - x_j|^2 / (2 l^2)) is an RBF similarity; q is the quality (e.g. p_n).
    det(L_Y) = prod(q_Y^2) det(S_Y) rewards quality and penalises near-duplicates. The greedy
    MAP is Chen, Zhang & Zhou (2018, NeurIPS), Algorithm 1: keep for every candidate i the
    Cholesky row c_i of L restricted to the picked set and d_i^2, the Schur complement of
    L_ii (the gain in log det from adding i); pick argmax d_i^2, then for every i

        e_i = (L_ji - <c_j, c_i>) / d_j,   c_i <- [c_i, e_i],   d_i^2 <- d_i^2 - e_i^2.

    O(n k^2) time, O(n k) memory; L is never formed, only one row per pick.

    Deterministic: ties go to the lowest index. If fewer than k items have a positive gain
    (e.g. only a few distinct points, or zero quality), the remaining picks continue by the
    same rule with gain ~0, so exactly k distinct indices are returned whenever k <= n.

    Parameters
    ----------
    features : array_like of shape (n, d)
    quality : array_like of shape (n,)
        Non-negative quality per item.
    k : int
        Number of items to pick, 1 <= k <= n.
    lengthscale : float, optional
        RBF lengthscale l; default the median pairwise distance.

    Returns
    -------
    picked : int ndarray of shape (k,)
        Indices in pick order.
    """
    X = np.asarray(features, dtype=np.float64)
    q = np.asarray(quality, dtype=np.float64)
    if X.ndim != 2 or q.shape != (X.shape[0],):
        raise ValueError(f"features must be (n, d) and quality (n,); got {X.shape}, {q.shape}")
    n = X.shape[0]
    if not 1 <= k <= n:
        raise ValueError(f"k must lie in [1, {n}]; got {k}")
    if np.any(q < 0) or not np.all(np.isfinite(q)):
        raise ValueError("quality must be finite and >= 0")
    ell = _median_distance(X) if lengthscale is None else float(lengthscale)
    sq = np.sum(X**2, axis=1)
    C = np.zeros((k, n))  # row t: the t-th Cholesky coordinate of every candidate
    d2 = q**2  # L_ii = q_i^2 S_ii = q_i^2
    picked = np.empty(k, np.int64)
    free = np.ones(n, bool)
    for t in range(k):
        gain = np.where(free, d2, -np.inf)
        j = int(np.argmax(gain))  # first maximum: lowest index wins ties
        picked[t] = j
        free[j] = False
        dj = np.sqrt(max(d2[j], 0.0))
        if t == k - 1:
            break
        if dj <= 1e-12 * max(1.0, float(q.max()) ** 2):
            # No gain left at j: its Cholesky coordinate is undefined; leave the others as
            # they are so the remaining picks still follow their own gains.
            continue
        # Row j of L: q_j q_i exp(-|x_j - x_i|^2 / (2 l^2)).
        dist2 = np.maximum(sq + sq[j] - 2.0 * X @ X[j], 0.0)
        Lj = q[j] * q * np.exp(-dist2 / (2.0 * ell**2))
        e = (Lj - C[:t, j] @ C[:t]) / dj
        C[t] = e
        d2 = d2 - e**2
    return picked


def batch_mean_f(values_per_batch: Sequence[ArrayLike]) -> tuple[FloatArray, FloatArray]:
    """Mean level-0 metric f of each batch's picks and its standard error (paper Table 1).

    The SE is the sample standard deviation (ddof = 1) over sqrt(n). Pass each batch's picks
    to get the SE over picks, or each seed's batch mean to get the paper's SE over seeds.

    Parameters
    ----------
    values_per_batch : sequence of array_like, each of shape (n_b,)

    Returns
    -------
    mean : ndarray of shape (n_batches,)
    se : ndarray of shape (n_batches,)
        NaN for a batch with fewer than 2 values.

    A batch with no values (none of its picks has a known level-0 value yet: its results
    are pending, or it picked only cheap levels) has mean NaN: it has no mean, and the
    batches after it still have theirs.
    """
    means = np.empty(len(values_per_batch))
    ses = np.empty(len(values_per_batch))
    for b, vals in enumerate(values_per_batch):
        v = np.asarray(vals, dtype=np.float64).ravel()
        means[b] = v.mean() if v.size else np.nan
        ses[b] = v.std(ddof=1) / np.sqrt(v.size) if v.size > 1 else np.nan
    return means, ses


@dataclass(frozen=True)
class StagedTrials:
    """Repeated draws of the staged estimate design from a known truth (``staged_trials``).

    Attributes
    ----------
    p_hat, ci_low, ci_high : ndarray of shape (n_trials,)
        The combined estimate and its interval in each trial.
    p_hat_unbiased : ndarray of shape (n_trials,)
        The stages' weighted sum, p_hat before it is held between the failures found and
        the cap (``core.design.combine_stages``): exactly unbiased.
    lam : ndarray of shape (n_trials,)
        The uniform share the last stage used (posterior mean after the stages before).
    stage2_design : list of str
        The design the last stage chose in each trial (stage 2 of two).
    recall : ndarray of shape (n_trials,)
        The share of the pool's true failures in hand after the estimate: those known
        before it, the earlier stages' sampled ones, and the expected number the last
        stage samples given them (its design's pi summed over the failures left), over all
        failures.
    var : float
        The design's variance of p_hat: sum_s w_s^2 E[Var(T_s | the stages before)] / N^2,
        exact for stage 1 and averaged over the trials' earlier draws for the later ones.
    var_uniform : float
        Variance of the uniform Poisson design of the same expected size K over U.
    stage1_design : str
    rate : float
        True failure rate.
    """

    p_hat: FloatArray
    ci_low: FloatArray
    ci_high: FloatArray
    lam: FloatArray
    stage2_design: list[str]
    recall: FloatArray
    var: float
    var_uniform: float
    stage1_design: str
    rate: float
    p_hat_unbiased: FloatArray

    @property
    def coverage(self) -> float:
        """Share of trials whose interval holds the true rate."""
        return float(np.mean((self.ci_low <= self.rate) & (self.rate <= self.ci_high)))

    @property
    def below(self) -> float:
        """Share of trials whose interval lies wholly below the true rate."""
        return float(np.mean(self.ci_high < self.rate))

    @property
    def above(self) -> float:
        """Share of trials whose interval lies wholly above the true rate."""
        return float(np.mean(self.ci_low > self.rate))


def staged_trials(
    p: ArrayLike,
    is_failure: ArrayLike,
    *,
    K: float,
    known: ArrayLike | None = None,
    share: float | None = None,
    prior: tuple[float, float] | None = None,
    anchor_sd: float | None = defaults.RISK_ANCHOR_SD,
    confidence: float = 0.9,
    n_trials: int = 1000,
    rng: np.random.Generator,
    reference: bool = False,
    leads: ArrayLike | None = None,
    lead_share: float = defaults.LEAD_SHARE,
    stages: int = defaults.STAGES,
) -> StagedTrials:
    """Draw the default staged estimate design ``n_trials`` times from a known truth.

    Each trial draws stage 1 (the calibrated design at the prior mean of lam, K_1 =
    share K), updates lam from where its sampled failures fell, plans stage 2 over what is
    left as ``estimate --plan`` does, draws it, and so on for each later stage (they share
    K - K_1 equally), and combines the stages' estimates (``core.design.combine_stages``).
    Later stages keep stage 1's p_n: the real loop refits the model on each stage's
    results first, which the evaluation cannot afford a thousand times; the design is
    otherwise exactly the tool's.

    Parameters
    ----------
    p : array_like of shape (n_pool,)
        p_n after discovery (ones for a strategy without a model: uniform designs).
    is_failure : bool array_like of shape (n_pool,)
        True level-0 outcomes.
    K : float
        Total expected sample size over all stages, below |U|: at |U| or above,
        ``estimate --plan`` plans one stage, a census, which this does not draw.
    known : bool array_like of shape (n_pool,), optional
        The known stratum after discovery.
    share : float, optional
        Stage 1's share of K; default ``defaults.STAGE1_SHARE``.
    prior : (float, float), optional
        Beta prior on lam; default ``defaults.RISK_MIX_PRIOR``.
    anchor_sd : float or None
        ``core.design.risk_posterior``'s: how far the failure count may stray from p_n's
        prediction (None: where the failures fell only).
    confidence : float
    n_trials : int
    rng : numpy.random.Generator
    reference : bool
        Run each trial through the tool's own functions (``choose_design``,
        ``estimate_from_sample``, ``combine_stages``) instead of the evaluation's fast path
        (``_staged_trials_fast``): the same draws and, to rounding, the same numbers, at
        several times the cost on a large U.
    leads : bool array_like of shape (n_pool,), optional
        The open cheap-level leads after discovery (``pipeline.estimation.open_leads``),
        which ``estimate --plan`` samples with certainty out of K (at most ``lead_share``
        of it, the highest p first): they join the known stratum and the stages share the
        rest of K, as the tool plans them. ``var_uniform`` stays that of a uniform design
        of K over the whole of U.
    lead_share : float
        The leads' largest share of K (``core.design.lead_share`` of the study's evidence).
    stages : int
        How many stages K is spent in (``estimate --plan --stages``), at least 2.

    Returns
    -------
    StagedTrials
    """
    if stages < 2:
        raise ValueError(f"staged_trials draws two stages or more, not {stages}")
    known_m = np.zeros(np.asarray(p).size, bool) if known is None else np.asarray(known, bool)
    lead_m = certain_leads(p, known_m, leads, K, lead_share)
    if lead_m.any():
        fail = np.asarray(is_failure, dtype=bool)
        n_u = int((~known_m).sum())
        var_u = int(fail[~known_m].sum()) * (n_u - K) / K / fail.size**2
        out = staged_trials(
            p, is_failure, K=K - int(lead_m.sum()), known=known_m | lead_m, share=share,
            prior=prior, anchor_sd=anchor_sd, confidence=confidence, n_trials=n_trials,
            rng=rng, reference=reference, stages=stages,
        )  # fmt: skip
        return dataclasses.replace(out, var_uniform=var_u)
    # Every trial's dot products are over one U (a few 1e4 terms): BLAS threads only
    # contend there (measured: twice the CPU time on 2 busy cores), and their split sums
    # make the last digits depend on the thread count. One thread: same numbers anywhere.
    with threadpool_limits(limits=1, user_api="blas"):
        if reference:
            return _multi_stage_trials(
                p, is_failure, K=K, known=known, share=share, stages=stages, prior=prior,
                anchor_sd=anchor_sd, confidence=confidence, n_trials=n_trials, rng=rng,
            )  # fmt: skip
        return _staged_trials_fast(
            p, is_failure, K=K, known=known, share=share, prior=prior, anchor_sd=anchor_sd,
            confidence=confidence, n_trials=n_trials, rng=rng, stages=stages,
        )  # fmt: skip


@dataclass(frozen=True)
class _Stage1:
    """What every trial of ``staged_trials`` shares: U, the split of K over the stages and
    their weights, stage 1's design."""

    N: int
    n1: int
    known_f: int
    K: float
    shares: list[float]
    weights: FloatArray
    p1: FloatArray
    f1: NDArray[np.bool_]
    u1: FloatArray
    norms1: FloatArray
    order1: NDArray[np.intp]
    name1: str
    pi1: FloatArray
    wm1: float
    V1: float
    rate: float
    n_fail: int

    def result(
        self, p_hat: FloatArray, lo: FloatArray, hi: FloatArray, lam: FloatArray,
        names: list[str], V: FloatArray, in_hand: FloatArray, unbiased: FloatArray,
    ) -> StagedTrials:  # fmt: skip
        """The trials' figures with the design's variance against uniform's. ``V``: each
        trial's exact variance per stage given the stages before, (n_trials, stages);
        ``in_hand``: each trial's failures in hand (``StagedTrials.recall`` before dividing
        by F); ``unbiased``: each trial's p_hat before it was held between the failures
        found and the cap."""
        N, K = self.N, self.K
        var = float((self.weights**2 * V.mean(axis=0)).sum()) / N**2
        var_u = int(self.f1.sum()) * (self.n1 - K) / K / N**2 if K > 0 else math.inf
        recall = in_hand / self.n_fail if self.n_fail > 0 else np.full(in_hand.shape, np.nan)
        return StagedTrials(
            p_hat=p_hat, ci_low=lo, ci_high=hi, lam=lam, stage2_design=names, recall=recall,
            var=var, var_uniform=var_u, stage1_design=self.name1, rate=self.rate,
            p_hat_unbiased=unbiased,
        )  # fmt: skip


def _stage1(
    p: ArrayLike,
    is_failure: ArrayLike,
    K: float,
    known: ArrayLike | None,
    share: float,
    prior: tuple[float, float],
    stages: int,
) -> _Stage1:
    from bams_cli.core import design as dz

    p = np.asarray(p, dtype=np.float64)
    fail = np.asarray(is_failure, dtype=bool)
    N = p.size
    known_m = np.zeros(N, bool) if known is None else np.asarray(known, dtype=bool)
    U1 = np.flatnonzero(~known_m)
    n1 = U1.size
    K = min(float(K), float(n1))
    p1, f1 = p[U1], fail[U1]
    u1 = dz.relative_risk(p1)
    # One sort of U by p_n serves every trial: a later stage's U is U minus the earlier samples, and
    # dropping segments from a sorted list leaves it sorted (``choose_design``'s order).
    order1 = np.argsort(-p1, kind="stable")
    post1 = dz.risk_posterior([], prior=prior)
    c1 = dz.choose_design(p1, K=share * K, posterior=post1, order=order1)
    pi1 = c1.pi
    # Stage 1 spends ``share`` of K, each later stage an equal part of the rest.
    shares = [share, *([(1.0 - share) / (stages - 1)] * (stages - 1))]
    return _Stage1(
        N=N, n1=n1, known_f=int(fail[known_m].sum()), K=K, shares=shares,
        weights=np.asarray(dz.stage_weights(shares, K, n1), dtype=np.float64), p1=p1, f1=f1,
        u1=u1,
        norms1=dz.risk_norms(u1),
        order1=order1, name1=c1.name, pi1=pi1, wm1=dz.unseen_failure_weight(post1.allowance_risk(p1), pi1),
        V1=float(((1.0 - pi1[f1]) / pi1[f1]).sum()), rate=float(fail.mean()),
        n_fail=int(fail.sum()),
    )  # fmt: skip


def _multi_stage_trials(
    p: ArrayLike,
    is_failure: ArrayLike,
    *,
    K: float,
    known: ArrayLike | None,
    share: float | None,
    stages: int,
    prior: tuple[float, float] | None,
    anchor_sd: float | None,
    confidence: float,
    n_trials: int,
    rng: np.random.Generator,
) -> StagedTrials:
    """The reference: each trial runs the tool's own functions (``choose_design``,
    ``estimate_from_sample``, ``combine_stages``) over ``stages`` stages. Stage 1 spends
    ``share`` K, each later stage an equal part of the rest (as ``estimate --plan --stages``
    shares it), planned over what the stages before it left, from the evidence of all of
    them. ``_staged_trials_fast`` gives its numbers to rounding at any number of stages
    (tests/core/test_design.py).

    var: sum_s w_s^2 E[V_s], V_s stage s's exact variance given the stages before it
    (each stage's total is unbiased given them, so the stages' errors are uncorrelated),
    the mean over the trials standing for E beyond stage 1."""
    from bams_cli import defaults
    from bams_cli.core import design as dz
    from bams_cli.core.estimate import estimate_from_sample

    share = defaults.STAGE1_SHARE if share is None else share
    prior = defaults.RISK_MIX_PRIOR if prior is None else prior
    st = _stage1(p, is_failure, K, known, share, prior, stages)
    N, known_f, K, shares = st.N, st.known_f, st.K, st.shares
    out = {k: np.empty(n_trials) for k in ("p_hat", "lo", "hi", "lam", "in_hand", "unbiased")}
    V = np.zeros((n_trials, stages))
    names: list[str] = []
    for t in range(n_trials):
        # Stage 1 is the same in every trial (its design from the prior alone).
        ps, fs, us, norms, pi, wm = st.p1, st.f1, st.u1, st.norms1, st.pi1, st.wm1
        order = st.order1
        found = known_f
        evidence: list[dz.StageEvidence] = []
        ests: list[RateEstimates] = []
        post: dz.RiskPosterior | None = None
        for s in range(stages):
            K_s = min(shares[s] * K, float(ps.size))
            name = st.name1
            if s > 0:
                post = dz.risk_posterior(evidence, prior=prior, anchor_sd=anchor_sd)
                if ps.size:
                    c = dz.choose_design(ps, K=K_s, posterior=post, order=order)
                    name, pi = c.name, c.pi
                    wm = dz.unseen_failure_weight(post.allowance_risk(ps), pi)
                else:  # an earlier stage drew all of U: nothing is left to draw
                    name, pi, wm = "uniform", np.ones(0), math.nan
            take = np.flatnonzero(rng.random(ps.size) < pi)
            ests.append(
                estimate_from_sample(
                    pi[take],
                    fs[take],
                    design="poisson",
                    n_pool=N,
                    n_unknown=ps.size,
                    budget=K_s,
                    known_failures=found,
                    confidence=confidence,
                    w_model=wm,
                )  # fmt: skip
            )
            pf = pi[fs]
            V[t, s] = float(np.where(pf >= 1.0, 0.0, (1.0 - pf) / np.maximum(pf, 1e-300)).sum())
            if s == stages - 1:
                out["in_hand"][t] = found + float(pf.sum())
                names.append(name)
                break
            evidence.append(dz.StageEvidence(us[take], fs[take], norms, p_mean=float(ps.mean())))
            found += int(fs[take].sum())
            rest = np.ones(ps.size, bool)
            rest[take] = False
            # One sort of U serves every stage: dropping segments keeps it sorted.
            order = (np.cumsum(rest) - 1)[order[rest[order]]]
            ps, fs = ps[rest], fs[rest]
            us = dz.relative_risk(ps)
            norms = dz.risk_norms(us)
        comb = dz.combine_stages(ests, st.weights, n_pool=N)
        out["p_hat"][t], out["lo"][t], out["hi"][t] = comb.p_hat[0], comb.ci_low[0], comb.ci_high[0]
        assert comb.p_hat_unbiased is not None
        out["unbiased"][t] = comb.p_hat_unbiased[0]
        out["lam"][t] = post.lam_mean if post is not None else float("nan")
    return st.result(
        out["p_hat"], out["lo"], out["hi"], out["lam"], names, V, out["in_hand"],
        out["unbiased"],
    )  # fmt: skip


def _capped(head: FloatArray, rest: float, K: float) -> tuple[int, float]:
    """Capped count m and the scale c of pi = min(1, c g), sum K, for g > 0 (``_capped_count``).

    ``head``: the floor(K) + 1 largest g, descending; ``rest``: the sum of the other g (the
    design is over more than K segments). m is the smallest count with K - m <=
    sum_{j >= m} g_j / g_m; the uncapped share K - m in proportion to g: c = (K - m) /
    sum_{j >= m} g_j. The tail sums add positive terms only, so no digits are lost however
    much of the sum the capped hold.
    """
    tails = rest + np.cumsum(head[::-1])[::-1]  # sum_{j >= m} g_j
    ms = np.arange(head.size)
    ok = (K - ms) * head <= tails
    m = int(np.argmax(ok)) if ok.any() else head.size - 1
    return m, (K - m) / float(tails[m])


def _sum_less(
    x: FloatArray, x_all: float, head: IntArray, kf: FloatArray, cache: dict[str, FloatArray]
) -> float:
    """sum of x over the segments with kf = 1, less ``head`` (x_all: the sum with it).

    By difference, unless the head holds over half of it and the difference would lose
    digits: then summed afresh (the indicator without the head is kept in ``cache``).
    """
    h = float(x[head].sum())
    if h <= 0.5 * x_all:
        return x_all - h
    if "kf" not in cache:
        cache["kf"] = kf.copy()
        cache["kf"][head] = 0.0
    return float(x @ cache["kf"])


def _stage_terms(
    pf: FloatArray, n_sampled: int, n_certain: int, *, n_unknown: int, budget: float,
    known: float, w_model: float,
) -> tuple[float, float, float, float, float, float]:  # fmt: skip
    """What ``combine_stages`` takes from a poisson stage's ``estimate_from_sample``.

    ``pf``: the inclusion probabilities of the stage's sampled failures; ``n_certain``: its
    sampled segments with pi = 1. Returns (total, certain, v, w_allow, found, hi_cap),
    totals over U, formed as that function forms them.
    """
    rand = pf < 1.0
    pr = pf[rand]
    inv = 1.0 / pr
    D = float(pf.size - pr.size)
    R = float(inv.sum())
    v = float(((1.0 - pr) * inv**2).sum())
    w_seen = float(((1.0 - pr) * inv).max(initial=0.0))
    if math.isnan(w_model):
        K_r = budget - n_certain
        w0 = (n_unknown - n_certain - K_r) / K_r if K_r > 0 else 0.0
        w_allow = w_seen if pr.size else w0
    else:
        w_allow = max(w_seen, w_model)
    found = known + D + pr.size
    hi_cap = known + n_unknown - (n_sampled - pf.size)
    return known + D + R, known + D, v, w_allow, found, hi_cap


def _staged_trials_fast(
    p: ArrayLike,
    is_failure: ArrayLike,
    *,
    K: float,
    known: ArrayLike | None,
    share: float | None,
    prior: tuple[float, float] | None,
    anchor_sd: float | None,
    confidence: float,
    n_trials: int,
    rng: np.random.Generator,
    stages: int = 2,
) -> StagedTrials:
    """``_multi_stage_trials``' numbers from per-run precomputations, for any number of
    stages.

    A later stage's design over U_s = U minus the earlier stages' samples needs no sort, exp
    or log per trial:

    * the posterior risk u^tau / mean_Us(u^tau) is p^tau / mean_Us(p^tau) whatever
      mean_Us(p) is, so r = lam + sum_tau b_tau p^tau with p^tau computed once, and every
      sum over U_s is a dot product with U_s's indicator, or the last one's less the
      sample;
    * each weighted candidate is pi = min(1, c g) (g = sqrt(r), or q of the p^alpha form):
      its capped count m needs only the floor(K_s) + 1 segments of U_s with the largest
      p_n (one sort of U serves every trial and stage) and the sum of g over U_s;
    * its predicted variance sum_{pi < 1} r (1 - pi)/pi is sum_{j >= m} r_j / (c g_j) less
      sum_{j >= m} r_j: for the calibrated design T_m / c (r / g = g), for p^alpha one dot
      product; only the chosen design's pi is formed, for the draw;
    * a stage's estimate needs only its sampled failures, and ``combine_stages``'s interval
      is computed for every trial at once.

    The draws are the reference's, from the same stream in the same order, and each
    finished stage's evidence (``StageEvidence``) is formed as the reference forms it, so
    the posteriors are its own. A candidate whose g is constant over U_s has the uniform
    design's pi and predicted variance exactly, as in the reference (where a tie goes to
    uniform): so a p_n constant over U_s gives uniform without a comparison that rounding
    could tip. Equal to ``_multi_stage_trials`` to rounding (tests/core/test_design.py).
    """
    from bams_cli import defaults
    from bams_cli.core import design as dz
    from bams_cli.core.estimate import _gamma_interval

    share = defaults.STAGE1_SHARE if share is None else share
    prior = defaults.RISK_MIX_PRIOR if prior is None else prior
    st = _stage1(p, is_failure, K, known, share, prior, stages)
    if not (st.K > 0 and 0 < share < 1 and defaults.DEFENSIVE > 0):
        # Nothing to sample, or a single stage: the reference handles (or rejects) it.
        return _multi_stage_trials(
            p, is_failure, K=K, known=known, share=share, stages=stages, prior=prior,
            anchor_sd=anchor_sd, confidence=confidence, n_trials=n_trials, rng=rng,
        )  # fmt: skip
    N, n1, known_f, K, shares = st.N, st.n1, st.known_f, st.K, st.shares
    p1, f1 = st.p1, st.f1
    p_mean1 = float(p1.mean())
    n_certain1 = int(np.count_nonzero(st.pi1 >= 1.0))
    taus = np.asarray(dz.TAUS, dtype=np.float64)
    pos = p1 > 0
    # Rows: p^tau for each tau (the risk), p^alpha (the paper-form candidate), over U.
    powers = np.zeros((taus.size + 1, n1))
    for i, tau in enumerate(taus):
        powers[i] = p1**tau
    powers[-1, pos] = p1[pos] ** defaults.ALPHA
    sums1 = powers.sum(axis=1)  # over U; a trial's sums over U_s drop the earlier samples
    n_pos1 = int(np.count_nonzero(pos))
    est = np.empty((stages, 4, n_trials))  # per stage: total, certain, v, w_allow
    found_last = np.empty(n_trials)
    cap_last = np.empty(n_trials)
    lam = np.full(n_trials, np.nan)
    V = np.zeros((n_trials, stages))
    V[:, 0] = st.V1
    in_hand = np.empty(n_trials)
    names: list[str] = []
    for t in range(n_trials):
        kept = np.ones(n1, bool)  # U_s over U
        sums, n_pos, found, n_s = sums1, n_pos1, known_f, n1
        evidence: list[dz.StageEvidence] = []
        for s in range(stages):
            K_s = min(shares[s] * K, float(n_s))
            if s == 0:
                name, pi_s, wm = st.name1, st.pi1, st.wm1
                f_s, n_certain = f1, n_certain1
            else:
                post = dz.risk_posterior(evidence, prior=prior, anchor_sd=anchor_sd)
                lam[t] = post.lam_mean
                name, pi_u, wm = _later_stage_design(
                    post, p1, powers, sums, kept, n_s, K_s, positive=n_pos > 0, order=st.order1
                )
                pi_s, f_s = pi_u[kept], f1[kept]
                n_certain = int(np.count_nonzero(pi_s >= 1.0))
            take = rng.random(n_s) < pi_s
            *est[s, :, t], found_s, cap_s = _stage_terms(
                pi_s[take & f_s], int(np.count_nonzero(take)), n_certain, n_unknown=n_s,
                budget=K_s, known=found, w_model=wm,
            )  # fmt: skip
            pf = pi_s[f_s]
            if s:
                V[t, s] = float(np.where(pf >= 1.0, 0.0, (1.0 - pf) / np.maximum(pf, 1e-300)).sum())
            if s == stages - 1:
                found_last[t], cap_last[t] = found_s, cap_s
                in_hand[t] = found + float(pf.sum())
                names.append(name)
                break
            # The finished stage's evidence, formed as the reference forms it.
            if s == 0:
                us, norms, p_mean = st.u1, st.norms1, p_mean1
            else:
                ps = p1[kept]
                us = dz.relative_risk(ps)
                norms, p_mean = dz.risk_norms(us), float(ps.mean())
            evidence.append(dz.StageEvidence(us[take], f_s[take], norms, p_mean=p_mean))
            found += int(f_s[take].sum())
            gone_idx = np.flatnonzero(kept)[take] if s else np.flatnonzero(take)
            kept[gone_idx] = False
            n_s -= gone_idx.size
            n_pos -= int(np.count_nonzero(pos[gone_idx]))
            gone = powers[:, gone_idx].sum(axis=1)
            # By difference, unless the sample holds over half of a sum (digits would go).
            sums = sums - gone if np.all(gone <= 0.5 * sums) else powers @ kept.astype(np.float64)
    # ``combine_stages`` on every trial's stage figures, in its order of operations.
    Nf = float(N)
    w = st.weights
    total, certain, v, w_next = (np.zeros(n_trials) for _ in range(4))
    for s in range(stages):
        total = total + w[s] * (est[s, 0] / Nf)
        certain = certain + w[s] * (est[s, 1] / Nf)
        v = v + w[s] ** 2 * (est[s, 2] / Nf**2)
        w_next = w_next + w[s] ** 2 * est[s, 3]
    total, certain, v = total * Nf, certain * Nf, v * Nf**2
    lo_r, hi_r = _gamma_interval(np.maximum(total - certain, 0.0), v, w_next, 1.0 - confidence)
    unbiased = total
    cap = cap_last / Nf * Nf
    total = np.minimum(np.maximum(total, found_last), cap)
    hi = np.minimum(np.maximum(certain + hi_r, total), cap)
    lo = np.minimum(np.maximum(certain + lo_r, found_last), np.minimum(total, hi))
    return st.result(total / Nf, lo / Nf, hi / Nf, lam, names, V, in_hand, unbiased / Nf)


def _later_stage_design(
    post: RiskPosterior,
    p1: FloatArray,
    powers: FloatArray,
    sums: FloatArray,
    kept: NDArray[np.bool_],
    n_s: int,
    K_s: float,
    *,
    positive: bool,
    order: NDArray[np.intp],
) -> tuple[str, FloatArray, float]:
    """A later stage's design over U_s (``kept``, over U) as ``choose_design`` picks it,
    and the interval's allowance weight (``unseen_failure_weight``), from p_n's powers
    over U (``powers``: p^tau per tau, then p^alpha) and their sums over U_s (``sums``).
    ``positive``: some p_n over U_s is above 0; ``order``: U by p_n, descending. Returns
    (design name, pi over U (read on ``kept``), allowance weight)."""
    from bams_cli import defaults
    from bams_cli.core import design as dz

    n1 = p1.size
    if K_s >= n_s:
        return "uniform", np.ones(n1), math.nan
    eps = defaults.DEFENSIVE
    taus = np.asarray(dz.TAUS, dtype=np.float64)
    kf = kept.astype(np.float64)
    n_gone = n1 - n_s
    # ``RiskPosterior.risk`` over U_s, as lam + sum_tau b_tau p^tau.
    w_tau = post.weights.sum(axis=1)
    trust = post.weights @ (1.0 - post.lams)
    coef = np.zeros(taus.size)
    for i in range(taus.size):
        if w_tau[i] > 0:
            coef[i] = trust[i] / (sums[i] / n_s) if positive else 0.0
    r = coef @ powers[:-1] + (
        post.lam_mean if positive else post.lam_mean + float(trust[w_tau > 0].sum())
    )
    top = min(n_s - 1, int(math.floor(K_s)))
    head = order[: top + 1 + n_gone]
    head = head[kept[head]][: top + 1]  # U_s's top + 1 largest p_n, descending
    tail = order[::-1][: n_gone + 1]
    low = int(tail[kept[tail]][0])  # U_s's smallest p_n
    R_all = float(r @ kf)
    pu = K_s / n_s
    pv = {"uniform": R_all * (1.0 - pu) / pu}
    scale: dict[str, tuple[float, float, float]] = {}
    capped: dict[str, int] = {}
    g = np.sqrt(r)
    q = (
        (1.0 - eps) * powers[-1] / float(sums[-1]) + eps / n_s
        if positive
        else np.full(n1, 1.0 / n_s)
    )
    cache: dict[str, FloatArray] = {}
    rest_r = _sum_less(r, R_all, head, kf, cache)
    flat = p1[head[0]] == p1[low]  # p_n constant over U_s: every candidate is uniform
    for cand, gg in (("calibrated", g), ("p^alpha", q)):
        if flat:
            pv[cand] = pv["uniform"]
            continue
        g_rest = _sum_less(gg, float(gg @ kf), head, kf, cache)
        m, c = _capped(gg[head], g_rest, K_s)
        r_m = rest_r + float(r[head[m:]].sum())
        if cand == "calibrated":  # r / pi = g / c where pi < 1
            rq_m = g_rest + float(g[head[m:]].sum())
        else:  # r / pi = (r / q) / c
            rq = r / q
            rq_m = _sum_less(rq, float(rq @ kf), head, kf, cache) + float(rq[head[m:]].sum())
        pv[cand] = rq_m / c - r_m
        scale[cand] = (c, float(gg[head[m - 1]]) if m else math.inf, r_m)
        capped[cand] = m
    m = capped.get("calibrated", -1)
    if m == capped.get("p^alpha") and m < head.size and p1[head[m]] == p1[low]:
        # The same segments capped and p_n constant over the rest: the two designs are one
        # (pi = 1 on the capped, the rest of K shared equally), and the reference's equal
        # predicted variances give the first, calibrated; here rounding could tip them.
        pv["p^alpha"] = pv["calibrated"]
    base = pv["uniform"]
    pred = {k: (v / base if base > 0 else 1.0) for k, v in pv.items()}
    name = min(pred, key=lambda k: (pred[k], k != "uniform"))
    if name == "uniform":
        pi_u = np.full(n1, pu)
    else:
        gg = g if name == "calibrated" else q
        c, thr, _ = scale[name]
        pi_u = np.minimum(1.0, c * gg)
        if thr < math.inf:
            pi_u[gg >= thr] = 1.0
    # The allowance's risk (``RiskPosterior.allowance_risk`` over U_s): lam at its upper
    # quantile, the shapes as the posterior weighs them; u^tau / mean(u^tau) is
    # p^tau / mean(p^tau), and all ones where p_n is 0 over U_s.
    lam_q = post.lam_quantile(defaults.RISK_MIX_UPPER)
    shaped = np.zeros(n1)
    for i in range(taus.size):
        if w_tau[i] > 0:
            shaped += w_tau[i] * (powers[i] / (sums[i] / n_s) if positive else 1.0)
    r_q = lam_q + (1.0 - lam_q) * shaped
    rand = kept & (pi_u > 0.0) & (pi_u < 1.0)
    mass_q = float(r_q[rand].sum())
    wm = float(r_q[rand] @ ((1.0 - pi_u[rand]) / pi_u[rand])) / mass_q if mass_q > 0 else math.nan
    return name, pi_u, wm


def exact_variance(
    plan_or_prob: SamplePlan | ArrayLike,
    is_failure: ArrayLike,
    *,
    design: Design | None = None,
    n_pool: int | None = None,
    budget: float | None = None,
) -> FloatArray:
    """True Var(p_hat) of the design when the failures of U are known (evaluation only).

    * poisson: (1/N^2) sum_{failures in U} (1 - pi)/pi (exact).
    * with-replacement: (1/(N^2 K)) (sum_{failures} 1/q - T_U^2) (exact).
    * fixed: Hajek's approximation (1/N^2) sum_U pi (1 - pi)(y/pi - A)^2 with
      A = sum_U (1 - pi) y / sum_U pi (1 - pi), over units with pi < 1 (approximate, like the
      estimator; exact systematic variances depend on the order).

    A failure with pi = 0 makes the variance finite but the estimator biased; one with q = 0
    with replacement, likewise. Both are reported as +inf here so that nobody mistakes the
    design for a good one.

    Parameters
    ----------
    plan_or_prob : SamplePlan or array_like of shape (n_unknown,)
        A plan, or pi (q for with-replacement) over U together with the keywords.
    is_failure : array_like of bool, shape (n_unknown,) or (n_unknown, m)
        Failure indicator over U (in ``plan.unknown`` order).
    design, n_pool, budget
        Needed when ``plan_or_prob`` is an array.

    Returns
    -------
    var : ndarray of shape (m,)
    """
    if isinstance(plan_or_prob, SamplePlan):
        plan = plan_or_prob
        design = plan.design
        n_pool = plan.n_pool
        budget = plan.budget
        prob = plan.q if design == "with-replacement" else plan.pi
    else:
        prob = np.asarray(plan_or_prob, dtype=np.float64)
        if design is None or n_pool is None:
            raise ValueError("design and n_pool are required when passing probabilities")
    y = _as_columns(is_failure, prob.size, "is_failure").astype(np.float64)
    N2 = float(n_pool) ** 2
    zero = prob <= 0
    bad = (zero[:, None] * y).sum(axis=0) > 0
    safe = np.where(zero, 1.0, prob)
    if design == "poisson":
        var = (((1.0 - prob) / safe) * ~zero) @ y / N2
    elif design == "with-replacement":
        if budget is None:
            raise ValueError("budget (K draws) is required for with-replacement")
        T = y.sum(axis=0)
        var = ((~zero / safe) @ y - T**2) / (float(budget) * N2)
    elif design == "fixed":
        r = (prob < 1.0) & ~zero
        d = prob * (1.0 - prob) * r
        A = ((1.0 - prob) * r) @ y / d.sum() if d.sum() > 0 else np.zeros(y.shape[1])
        e = y / safe[:, None] - A[None, :]
        var = (d[:, None] * e**2 * r[:, None]).sum(axis=0) / N2
    else:
        raise ValueError(f"design must be one of {DESIGNS}; got {design!r}")
    return np.where(bad, np.inf, var)


def exact_relative_variance(
    plan: SamplePlan, is_failure: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """True Var(p_hat) and relative variance Var / p^2 of a plan's design (evaluation only).

    The paper's RV (section 4.1) as the design's exact variance, not the spread of a few
    hundred trials (DESIGN.md). p is the true rate over the pool, known stratum included.

    Parameters
    ----------
    plan : SamplePlan
    is_failure : array_like of bool, shape (n_pool,) or (n_pool, m)
        True failure indicator over the whole pool, one column per gamma.

    Returns
    -------
    var : ndarray of shape (m,)
    rel_var : ndarray of shape (m,)
        NaN where the true rate is 0.
    """
    fail = _as_columns(is_failure, plan.n_pool, "is_failure").astype(bool)
    var = exact_variance(plan, fail[plan.unknown])
    p = fail.mean(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        return var, np.where(p > 0, var / p**2, np.nan)


@dataclass(frozen=True)
class ScreenTrials:
    """Repeated draws of the screened estimate design from a known truth (``screen_trials``).

    Attributes
    ----------
    share : float
        The screen's share of K.
    recall : ndarray of shape (n_trials,)
        The share of the pool's true failures in hand after the estimate: those known
        before it plus the expected number the confirmation samples given the trial's
        screen (its pi2 summed over the screened failures), over all failures.
    screened : ndarray of shape (n_trials,)
        |S1| of each trial.
    var : float
        The design's variance of p_hat: phase 1's term exact, phase 2's exact given S1 and
        averaged over the trials' screens (``core.screen``), over N^2.
    var_uniform : float
        Variance of the uniform Poisson design of K level-0 runs over U.
    rate : float
        True failure rate.
    """

    share: float
    recall: FloatArray
    screened: IntArray
    var: float
    var_uniform: float
    rate: float


def screen_trials(
    p: ArrayLike,
    is_failure: ArrayLike,
    *,
    K: float,
    cost: float,
    share: float,
    refit: Callable[[IntArray], FloatArray],
    known: ArrayLike | None = None,
    cheap_known: ArrayLike | None = None,
    prior: tuple[float, float] | None = None,
    confirm_prior: tuple[float, float] | None = None,
    leads: ArrayLike | None = None,
    cheap: ArrayLike | None = None,
    lead_share: float | None = None,
    n_trials: int,
    rng: np.random.Generator,
) -> ScreenTrials:
    """Draw the screened estimate design (``estimate --plan --screen``) from a known truth.

    Each trial draws S1 with the screen's pi1 (``core.screen.screen_design`` over U), asks
    ``refit`` for the model's p_n over S1 once S1's cheap results are in (the real loop
    ingests them and fits), and plans the confirmation's pi2 from it with what is left of
    K (``core.screen.confirm_design``), as ``estimate --plan`` does. The refit is the
    caller's: it needs the workspace and the cheap level's truth.

    Parameters
    ----------
    p : array_like of shape (n_pool,)
        p_n after discovery.
    is_failure : bool array_like of shape (n_pool,)
        True level-0 outcomes.
    K : float
        The estimate's budget in level-0 runs, the screen's cheap runs included.
    cost : float
        One cheap run's cost in level-0 runs.
    share : float
        The screen's share of K.
    refit : callable
        S1 (pool indices) -> p_n over S1 after a fit that has S1's cheap results.
    known : bool array_like of shape (n_pool,), optional
        The known stratum after discovery.
    cheap_known : bool array_like of shape (n_pool,), optional
        Segments with a cheap result already: the screen does not run them again, and
        they cost nothing.
    prior : (float, float), optional
        Beta prior on lam of the screen's pi1; default ``defaults.RISK_MIX_PRIOR``
        (``estimate --plan`` takes ``core.design.risk_prior`` of the screen's fit).
    confirm_prior : (float, float), optional
        Beta prior on lam of the confirmation's pi2; default ``prior`` (``estimate --plan``
        takes ``core.design.confirm_prior`` of the screen's fit and keeps it).
    leads : bool array_like of shape (n_pool,), optional
        The open leads the screen takes with certainty (pi1 = pi2 = 1, ``core.screen``),
        as ``pipeline.estimation.open_leads`` chooses them; they must hold a cheap result
        (``cheap_known``) and lie outside ``known``.
    cheap : array_like of shape (n_pool,), optional
        The cheap-level result each segment's screen run would return: the confirmation
        takes the screen's lowest with certainty (``core.screen.screen_leads``, at
        ``lead_share`` of K2), as ``estimate --plan`` does. Without it, no screen leads.
    lead_share : float, optional
        ``core.screen.screen_leads``'s share; default ``defaults.SCREEN_LEAD_SHARE``.
    n_trials : int
    rng : numpy.random.Generator

    Returns
    -------
    ScreenTrials
    """
    from bams_cli.core import screen as sc
    from bams_cli.core.design import risk_posterior

    p = np.asarray(p, dtype=np.float64)
    fail = np.asarray(is_failure, dtype=bool)
    n = fail.size
    if p.shape != (n,):
        raise ValueError(f"p has shape {p.shape}; is_failure {fail.shape}: one each per segment")
    kn = np.zeros(n, bool) if known is None else np.asarray(known, dtype=bool)
    have = np.zeros(n, bool) if cheap_known is None else np.asarray(cheap_known, dtype=bool)
    F = int(fail.sum())
    if F == 0:
        raise ValueError("the pool has no failure: recall and variance are undefined")
    U = np.flatnonzero(~kn)
    fU = fail[U]
    in_hand = float((fail & kn).sum())  # the known stratum's failures, found whatever S1
    # A new study: no earlier estimate to mix in.
    posterior = risk_posterior([], prior=defaults.RISK_MIX_PRIOR if prior is None else prior)
    confirm = posterior if confirm_prior is None else risk_posterior([], prior=confirm_prior)
    lead = np.zeros(n, bool) if leads is None else np.asarray(leads, dtype=bool)
    if np.any(lead & (kn | ~have)):
        raise ValueError("a lead must have a cheap result and no level-0 one")
    lead_U = lead[U]
    cheap_U = None if cheap is None else np.asarray(cheap, dtype=np.float64)[U]
    pi1 = sc.screen_design(p[U], K=K, cost=cost, share=share, posterior=posterior, leads=lead_U).pi
    recall = np.empty(n_trials)
    screened = np.empty(n_trials, np.int64)
    v2 = np.empty(n_trials)
    for t in range(n_trials):
        s1 = np.flatnonzero(rng.random(U.size) < pi1)
        screened[t] = s1.size
        if s1.size == 0:  # nothing to confirm: T = 0, E[T | S1]
            recall[t] = in_hand / F
            v2[t] = 0.0
            continue
        p2 = np.asarray(refit(U[s1]), dtype=np.float64)
        runs = int((~have[U[s1]]).sum())
        K2 = min(sc.confirm_budget(K, cost, runs), float(s1.size))
        certain = lead_U[s1]
        if cheap_U is not None:
            certain = certain | sc.screen_leads(cheap_U[s1], K2, share=lead_share, taken=lead_U[s1])
        pi2 = sc.confirm_design(p2, K2=K2, posterior=confirm, leads=certain).pi
        recall[t] = (in_hand + float(pi2[fU[s1]].sum())) / F
        v2[t] = sc.phase2_variance(fU[s1], pi1[s1], pi2)
    N2 = float(n) ** 2
    k = min(float(K), float(U.size))
    return ScreenTrials(
        share=float(share),
        recall=recall,
        screened=screened,
        var=(sc.phase1_variance(fU, pi1) + float(v2.mean())) / N2,
        var_uniform=float(fU.sum()) * (U.size - k) / k / N2,
        rate=F / n,
    )
