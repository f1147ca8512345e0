"""The rate estimate's sample design: inclusion probabilities and the draw.

``core.estimate`` says what the designs are and why (its module docstring, DESIGN.md "Rate
estimate"); this module computes them. Over the unknown stratum U, segment i gets
pi_i = min(1, lam q_i) with q_i = (1 - eps) p_i^alpha / sum_U p^alpha + eps / |U| and lam
set so that sum_U pi = K (``inclusion_probabilities``, in log space so that tiny p_i^alpha
neither underflow nor overflow), and ``plan_sample`` draws the sample by one of the three
designs: Poisson (independent), fixed size (randomised systematic) or with replacement
(the paper's). ``failure_weights`` and ``model_weight`` are the design's weight of one
failure, which the interval's upper limit allows for.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bams_cli import defaults

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

Design = Literal["poisson", "fixed", "with-replacement"]
DESIGNS: tuple[str, ...] = ("poisson", "fixed", "with-replacement")


class ZeroInclusionWarning(UserWarning):
    """Some segments of U can never be sampled (pi = 0), so the estimate is biased low."""


# --------------------------------------------------------------------------------------------
# Inclusion probabilities
# --------------------------------------------------------------------------------------------


def selection_distribution(p: ArrayLike, *, alpha: float, defensive: float) -> FloatArray:
    """q = (1 - eps) p^alpha / sum(p^alpha) + eps / |U| (paper section 4.1, with DESIGN.md's eps).

    ``exp(log_selection_distribution(...))``: see there for how the extremes are kept.

    Parameters
    ----------
    p : array_like of shape (n_unknown,)
        Failure probabilities p_n over U, in [0, 1].
    alpha : float
        Sharpening exponent, >= 0 (0 gives uniform sampling).
    defensive : float
        Defensive uniform share eps, in [0, 1].

    Returns
    -------
    q : ndarray of shape (n_unknown,)
        Non-negative, sums to 1 (entries below ~1e-308 underflow; their logs do not).
    """
    return np.exp(log_selection_distribution(p, alpha=alpha, defensive=defensive))


def log_selection_distribution(p: ArrayLike, *, alpha: float, defensive: float) -> FloatArray:
    """log q, q = (1 - eps) p^alpha / sum(p^alpha) + eps / |U|, without under- or overflow.

    p^alpha is formed as alpha (log p - max log p), so p_n down to 1e-300 and alpha up to a
    few keep their ratios: at eps = 0 and alpha = 2.5, p_n = 1e-150 gives q ~ 1e-375, which
    no float64 holds but its log does. ``inclusion_probabilities`` works from these logs.

    Parameters
    ----------
    p : array_like of shape (n_unknown,)
        Failure probabilities p_n over U, in [0, 1].
    alpha : float
        Sharpening exponent, >= 0 (0 gives uniform sampling).
    defensive : float
        Defensive uniform share eps, in [0, 1].

    Returns
    -------
    log_q : ndarray of shape (n_unknown,)
        -inf where q = 0 (p = 0 with eps = 0); logsumexp(log_q) = 0.
    """
    p = np.asarray(p, dtype=np.float64)
    if p.ndim != 1 or p.size == 0:
        raise ValueError(f"p must be a non-empty 1-d array; got shape {p.shape}")
    if not np.all((p >= 0.0) & (p <= 1.0)):
        raise ValueError("p must lie in [0, 1]; got values outside (or NaN)")
    if alpha < 0.0:
        raise ValueError(f"alpha must be >= 0; got {alpha}")
    if not 0.0 <= defensive <= 1.0:
        raise ValueError(f"defensive must lie in [0, 1]; got {defensive}")
    n = p.size
    if alpha == 0.0:
        log_base = np.full(n, -math.log(n))
    else:
        pos = p > 0.0
        if not np.any(pos):
            if defensive == 0.0:
                raise ValueError("all p are 0 and defensive = 0: q is undefined; set defensive > 0")
            log_base = np.full(n, -np.inf)
        else:
            a = np.full(n, -np.inf)
            a[pos] = alpha * np.log(p[pos])
            log_base = a - _logsumexp(a[pos])  # shifts by the max: no under/overflow
    if defensive == 0.0:
        return log_base
    if defensive == 1.0:
        return np.full(n, -math.log(n))
    return np.logaddexp(math.log1p(-defensive) + log_base, math.log(defensive / n))


def _logsumexp(a: FloatArray) -> float:
    """log sum exp(a) over a 1-d array with a finite maximum: scipy's, bit for bit, faster.

    ``scipy.special.logsumexp`` (1.15 on) takes the maximal terms out of the sum for
    precision: with M = max a, m = #{a = M} and s = sum over the others of exp(a - M),
    it returns log1p(s / m) + log(m) + M. This is that formula in the same operations and
    the same order (so a design's pi do not move by an ulp), without the array-API
    dispatch, copies and masked assignments that made it ten times one ``exp`` pass at
    |U| = 30,000 (the staged design computes it for every trial of ``staged_trials``).
    ``tests/core/test_estimate.py`` holds it equal to scipy's.
    """
    a_max = a.max(keepdims=True)
    at_max = a == a_max
    m = np.count_nonzero(at_max, keepdims=True).astype(np.float64)
    e = np.exp(a - a_max)
    e[at_max] = 0.0
    s = e.sum(keepdims=True)
    s = np.where(s == 0, s, s / m)
    return float((np.log1p(s) + np.log(m) + a_max)[0])


def inclusion_probabilities(
    p: ArrayLike,
    *,
    alpha: float,
    defensive: float,
    K: float,
    order: ArrayLike | None = None,
) -> FloatArray:
    """pi_i = min(1, lam q_i) with lam such that sum(pi) = K exactly (DESIGN.md, "Rate estimate").

    q is ``selection_distribution(p, alpha=alpha, defensive=defensive)``. The capped set is
    found exactly, not by iteration: sort q descending; if the m largest are capped at 1, the
    rest share K - m, so lam_m = (K - m) / S_m with S_m the sum of the other q, and m is the
    smallest count with lam_m q_(m) <= 1, i.e. with

        K - m <= S_m / q_(m) = sum_{j >= m} q_(j) / q_(m).

    Both sides are formed from log q rescaled by q_(m) (every ratio in [0, 1], the sum in
    [1, n]), never as lam = (K - m) / S_m: at eps = 0 the tail sums S_m of a confident GP
    are subnormal (q ~ 1e-310), and the division overflowed to inf, no m passed, and every
    segment with q > 0 got pi = 1 (sum(pi) 1,541 against K = 1,489, issue 12). The test is
    monotone in m (S_m / q_(m) - (K - m) never decreases), so m is found by testing m = 0,
    then the m that suffix sums of q / q_(0) point to, confirmed by two exact tests
    (``_capped_count``; bisection where they disagree): O(n), three passes over U at
    most, where a bisection took log2 K of them. The uncapped pi
    are then (K - m) r / sum(r), r = q / q_(m), summed pairwise, so sum(pi) = K to
    rounding (~1e-16 relative).

    q is non-decreasing in p, so an ``order`` that sorts p descending also sorts q: callers
    that compute several designs on one p (``core.design.choose_design``), or one design on
    many subsets of a presorted p (``core.evaluate.staged_trials``), pass it and save the
    sort, O(n log n) and the bulk of the time. It is checked (one pass: q[order] must be
    non-increasing, which rounding could in principle break) and ignored when it fails; pi
    is the same either way, bit for bit.

    Segments with q = 0 (p = 0 with eps = 0), or with pi below ~1e-308, get pi = 0 and can
    never be sampled: a failure among them makes the HT estimate biased low, and a
    ``ZeroInclusionWarning`` says so. Tiny but positive pi keep the estimate unbiased at the
    price of a variance that can be astronomically large (a failure with inclusion
    probability pi adds (1 - pi)/(N^2 pi) to Var(p_hat)); the defensive share eps bounds pi
    below by ~eps K / |U|.

    Parameters
    ----------
    p : array_like of shape (n_unknown,)
        Failure probabilities p_n over U.
    alpha : float
        Sharpening exponent (paper: 2.5; DESIGN.md found 1 or 0.5 better).
    defensive : float
        Defensive uniform share eps in [0, 1].
    K : float
        Expected sample size, >= 0. K >= |U| gives all ones.
    order : int array_like of shape (n_unknown,), optional
        A permutation sorting p descending (e.g. ``np.argsort(-p, kind="stable")``); a hint
        that saves the sort, checked before use.

    Returns
    -------
    pi : ndarray of shape (n_unknown,)
        In [0, 1], non-decreasing in p, summing to min(K, |U|) (less only if fewer than K
        segments have q > 0, with a warning).
    """
    log_q = log_selection_distribution(p, alpha=alpha, defensive=defensive)
    n = log_q.size
    if K < 0 or not np.isfinite(K):
        raise ValueError(f"K must be a finite number >= 0; got {K}")
    if K >= n:
        return np.ones(n)
    if K == 0:
        return np.zeros(n)
    ls = None
    if order is not None:
        order = np.asarray(order, dtype=np.intp)
        if order.shape == (n,):
            ls = log_q[order]
            if not np.all(ls[:-1] >= ls[1:]):  # not a descending sort of q: sort afresh
                ls = None
    if ls is None:
        order = np.argsort(-log_q, kind="stable")
        ls = log_q[order]
    assert order is not None
    n_pos = int(np.count_nonzero(ls > -np.inf))
    pi_sorted = np.zeros(n)
    if n_pos <= K:
        # At most K segments have q > 0: every one of them is taken for sure and the rest
        # of the budget cannot be placed (q = 0 means "never sample").
        pi_sorted[:n_pos] = 1.0
    else:
        m, r, r_sum = _capped_count(ls, K)
        pi_sorted[:m] = 1.0
        pi_sorted[m:] = np.minimum(1.0, (K - m) * r / r_sum)
    pi = np.empty(n)
    pi[order] = pi_sorted
    n_zero = int(np.count_nonzero(pi == 0.0))
    if n_zero:
        warnings.warn(
            f"{n_zero} of {n} segments have inclusion probability 0 (p = 0 with defensive = 0, "
            "or p_n so small that pi underflows): failures among them are never sampled and "
            "the rate estimate is biased low; set defensive > 0",
            ZeroInclusionWarning,
            stacklevel=2,
        )
    return pi


def _capped_count(ls: FloatArray, K: float) -> tuple[int, FloatArray, float]:
    """The number m of capped segments, and r = q_(j) / q_(m) for j >= m with its sum.

    ``ls`` is log q sorted descending, with more than K finite entries. m is the smallest
    count with K - m <= sum_{j >= m} q_(j) / q_(m) (``inclusion_probabilities``); the test
    holds at floor(K) and is monotone in m. Each exact test is one exp pass over the tail;
    the search takes one when nothing is capped and three otherwise, where a bisection
    over [0, floor(K)] took log2 K (eight at K = 200). The ratios of m's test are returned,
    not recomputed.
    """
    n = ls.size
    top = min(n - 1, int(math.floor(K)))
    best: tuple[int, FloatArray, float] | None = None  # the smallest m seen to pass

    def ratios(m: int) -> tuple[FloatArray, float]:
        r = np.exp(ls[m:] - ls[m])  # q_(j) / q_(m) for j >= m, in [0, 1]
        return r, float(r.sum())

    def fits(m: int) -> bool:
        nonlocal best
        r, r_sum = ratios(m)
        ok = K - m <= r_sum * (1.0 + 1e-12)
        if ok and (best is None or m < best[0]):
            best = (m, r, r_sum)
        return ok

    r0, r0_sum = ratios(0)
    if K <= r0_sum * (1.0 + 1e-12):
        return 0, r0, r0_sum
    # Some are capped. r0 = q / q_(0) gives every S_m / q_(m) at once as a suffix sum over
    # r0[m]: a guess at m, which two exact tests (m passes, m - 1 does not) confirm. The
    # guess can miss only where r0 underflows or the cumulative sum's rounding (~1e-13)
    # decides, and then a bisection over [1, floor(K)] settles it as before.
    tail = np.cumsum(r0[::-1])[::-1][: top + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        guess_fits = (r0[: top + 1] > 0) & (K - np.arange(top + 1) <= tail / r0[: top + 1])
    guess = int(np.argmax(guess_fits)) if guess_fits.any() else top
    if guess >= 1 and fits(guess) and (guess == 1 or not fits(guess - 1)):
        m = guess
    else:
        lo, hi = 1, top  # fits(0) failed; fits(top) holds
        while lo < hi:
            mid = (lo + hi) // 2
            if fits(mid):
                hi = mid
            else:
                lo = mid + 1
        m = lo
    if best is not None and best[0] == m:
        return best
    return (m, *ratios(m))


# --------------------------------------------------------------------------------------------
# Drawing the sample
# --------------------------------------------------------------------------------------------


def draw_poisson(pi: ArrayLike, rng: np.random.Generator) -> IntArray:
    """Poisson sampling: each unit in independently with probability pi_i.

    Parameters
    ----------
    pi : array_like of shape (n_unknown,)
    rng : numpy.random.Generator

    Returns
    -------
    sampled : int ndarray of shape (n_sampled,)
        Positions into ``pi`` of the sampled units, ascending. E[n_sampled] = sum(pi).
    """
    pi = np.asarray(pi, dtype=np.float64)
    return np.flatnonzero(rng.random(pi.size) < pi).astype(np.int64)


def draw_systematic(pi: ArrayLike, rng: np.random.Generator, *, permute: bool = True) -> IntArray:
    """Systematic pi-ps sampling (Madow 1949), by default after a random permutation.

    Units with pi = 1 are taken outright (rounding in a cumulative sum must not drop them);
    the others are laid end to end in random order, each occupying a length pi_i of the
    line, and a unit is taken when one of the points u, u + 1, u + 2, ... (u ~ U[0, 1)) lands
    in its stretch. Each unit's inclusion probability is exactly pi_i whatever the order; the
    permutation only makes the joint inclusions close to maximum entropy, which the Hajek
    variance estimator (``estimate_from_sample``) assumes. Without it, pairs adjacent in the
    given order are never sampled together, and the variance estimate is no longer
    approximately unbiased.

    Parameters
    ----------
    pi : array_like of shape (n_unknown,)
    rng : numpy.random.Generator
    permute : bool
        Randomise the order first (default). False keeps the given order.

    Returns
    -------
    sampled : int ndarray of shape (n_sampled,)
        Positions into ``pi``, ascending. n_sampled is floor or ceil of sum(pi) (exactly
        sum(pi) when it is an integer).
    """
    pi = np.asarray(pi, dtype=np.float64)
    certain = pi >= 1.0
    idx = np.flatnonzero(~certain & (pi > 0.0))
    if permute:
        idx = rng.permutation(idx)
    cum = np.cumsum(pi[idx])
    u = rng.random()
    # Unit k is hit when floor(cum_k - u) > floor(cum_{k-1} - u).
    hits = np.floor(cum - u)
    prev = np.concatenate(([np.floor(-u)], hits[:-1]))
    chosen = idx[hits > prev]
    return np.sort(np.concatenate((np.flatnonzero(certain), chosen))).astype(np.int64)


def draw_with_replacement(
    q: ArrayLike, K: int, rng: np.random.Generator
) -> tuple[IntArray, IntArray]:
    """K i.i.d. draws from q (the paper's sampler), as distinct units and their draw counts.

    Parameters
    ----------
    q : array_like of shape (n_unknown,)
        Selection distribution, sums to 1.
    K : int
        Number of draws.
    rng : numpy.random.Generator

    Returns
    -------
    sampled : int ndarray of shape (n_sampled,)
        Positions into ``q`` drawn at least once, ascending.
    counts : int ndarray of shape (n_sampled,)
        Times each was drawn; sums to K.
    """
    q = np.asarray(q, dtype=np.float64)
    # Inverse-CDF draws (one cumsum, K binary searches): at |U| ~ 1e6 this beats a
    # multinomial, which walks every category.
    draws = rng.choice(q.size, size=int(K), p=q / q.sum())
    sampled, counts = np.unique(draws, return_counts=True)
    return sampled.astype(np.int64), counts.astype(np.int64)


def failure_weights(prob: ArrayLike, *, design: Design, K: float) -> FloatArray:
    """Variance-to-mean ratio w_i of one failure's term in the estimated total.

    Poisson/fixed: the term is I/pi with I ~ Bernoulli(pi), so w = (1 - pi)/pi (0 at pi = 1).
    With replacement: X/(K q) with X ~ Binomial(K, q), so w = (1 - q)/(K q). A failure
    adds w to Var(T_hat); the gamma interval's upper limit allows for one more of them.

    Parameters
    ----------
    prob : array_like of shape (n,)
        pi (poisson, fixed) or q (with-replacement); > 0.
    design : {"poisson", "fixed", "with-replacement"}
    K : float
        Number of draws (with-replacement only).

    Returns
    -------
    w : ndarray of shape (n,)
    """
    prob = np.asarray(prob, dtype=np.float64)
    with np.errstate(divide="ignore"):
        if design == "with-replacement":
            return (1.0 - prob) / (float(K) * prob)
        return np.where(prob >= 1.0, 0.0, (1.0 - prob) / prob)


def model_weight(p: ArrayLike, prob: ArrayLike, *, design: Design, K: float) -> float:
    """Mean failure weight if failures were spread over U as p_n says: sum p w / sum p.

    The sums run over the random part of U (pi < 1; all of U with replacement). Under a
    calibrated p_n, each failure of U is unit i with probability proportional to p_i, so
    this is the expected variance a failure adds; the gamma interval uses it as the weight
    of the extra failure its upper limit allows for, which keeps the interval honest about
    failures the sample has not seen (module docstring). Returns NaN when sum p = 0.

    Parameters
    ----------
    p : array_like of shape (n_unknown,)
        p_n over U.
    prob : array_like of shape (n_unknown,)
        pi (poisson, fixed) or q (with-replacement) over U.
    design : {"poisson", "fixed", "with-replacement"}
    K : float

    Returns
    -------
    w_model : float
    """
    p = np.asarray(p, dtype=np.float64)
    prob = np.asarray(prob, dtype=np.float64)
    rand = prob > 0 if design == "with-replacement" else (prob > 0) & (prob < 1.0)
    mass = float(p[rand].sum())
    if mass <= 0:
        return math.nan
    w = failure_weights(prob[rand], design=design, K=K)
    return float(p[rand] @ w) / mass


@dataclass(frozen=True)
class SamplePlan:
    """A drawn rate-estimation sample over the pool (DESIGN.md, "Rate estimate").

    Attributes
    ----------
    design : {"poisson", "fixed", "with-replacement"}
    n_pool : int
        N, the pool size; the rate is a fraction of N.
    unknown : int ndarray of shape (n_unknown,)
        Pool indices of U (segments whose level-0 value is not known), ascending.
    q : ndarray of shape (n_unknown,)
        Selection distribution over U.
    pi : ndarray of shape (n_unknown,)
        Inclusion probabilities over U. For "with-replacement", the probability of being
        drawn at least once, 1 - (1 - q)^K (used for recall, not for the estimate).
    budget : float
        K: expected sample size (poisson), sample size (fixed) or number of draws
        (with-replacement).
    sampled : int ndarray of shape (n_sampled,)
        Positions into ``unknown`` of the sampled segments, ascending.
    counts : int ndarray of shape (n_sampled,)
        Draws per sampled segment (all 1 except with replacement).
    w_model : float
        ``model_weight`` of the planning p_n: the weight a failure carries on average if
        failures are spread over U as p_n says. Widens the interval's upper limit (module
        docstring). NaN when unknown.
    """

    design: Design
    n_pool: int
    unknown: IntArray
    q: FloatArray
    pi: FloatArray
    budget: float
    sampled: IntArray
    counts: IntArray
    w_model: float = math.nan

    @property
    def n_unknown(self) -> int:
        """|U|."""
        return int(self.unknown.size)

    @property
    def sampled_pool_index(self) -> IntArray:
        """Pool indices of the sampled segments, shape (n_sampled,): the simulation list."""
        return self.unknown[self.sampled]

    @property
    def sampled_prob(self) -> FloatArray:
        """Per sampled segment, what the estimator divides by: pi, or q with replacement."""
        src = self.q if self.design == "with-replacement" else self.pi
        return src[self.sampled]


def plan_sample(
    p: ArrayLike,
    *,
    K: float,
    rng: np.random.Generator,
    known: ArrayLike | None = None,
    alpha: float = defaults.ALPHA,
    defensive: float = defaults.DEFENSIVE,
    design: Design = "poisson",
    permute: bool = True,
) -> SamplePlan:
    """Plan a rate-estimation sample: inclusion probabilities over U, then one draw.

    Parameters
    ----------
    p : array_like of shape (n_pool,)
        Failure probability p_n of every pool segment (for one gamma; the plan serves all).
    K : float
        Simulation budget (see ``SamplePlan.budget``); an integer for "with-replacement".
    rng : numpy.random.Generator
    known : array_like of bool, shape (n_pool,), optional
        True where the level-0 value is already known: excluded from sampling and counted
        exactly by the estimator.
    alpha, defensive : float
        See ``inclusion_probabilities``; defaults ``defaults.ALPHA`` and
        ``defaults.DEFENSIVE``, the values the CLI uses.
    design : {"poisson", "fixed", "with-replacement"}
    permute : bool
        "fixed" only: randomise the systematic order (see ``draw_systematic``).

    Returns
    -------
    plan : SamplePlan
    """
    if design not in DESIGNS:
        raise ValueError(f"design must be one of {DESIGNS}; got {design!r}")
    p = np.asarray(p, dtype=np.float64)
    n_pool = p.size
    known_mask = np.zeros(n_pool, bool) if known is None else np.asarray(known, dtype=bool)
    if known_mask.shape != p.shape:
        raise ValueError(f"known must have shape {p.shape}; got {known_mask.shape}")
    unknown = np.flatnonzero(~known_mask).astype(np.int64)
    if unknown.size == 0:
        empty = np.zeros(0)
        none = np.zeros(0, np.int64)
        return SamplePlan(design, n_pool, unknown, empty, empty, float(K), none, none)
    pu = p[unknown]
    q = selection_distribution(pu, alpha=alpha, defensive=defensive)
    if design == "with-replacement":
        if K != int(K) or K < 1:
            raise ValueError(f"with-replacement needs an integer number of draws K >= 1; got {K}")
        sampled, counts = draw_with_replacement(q, int(K), rng)
        pi = -np.expm1(K * np.log1p(-np.minimum(q, 1.0)))
    else:
        pi = inclusion_probabilities(pu, alpha=alpha, defensive=defensive, K=K)
        if design == "poisson":
            sampled = draw_poisson(pi, rng)
        else:
            sampled = draw_systematic(pi, rng, permute=permute)
        counts = np.ones(sampled.size, np.int64)
    prob = q if design == "with-replacement" else pi
    w_model = model_weight(pu, prob, design=design, K=K)
    return SamplePlan(design, n_pool, unknown, q, pi, float(K), sampled, counts, w_model)
