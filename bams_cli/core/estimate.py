"""Unbiased failure-rate estimation by importance sampling over the pool, and the GP's own.

Paper section 4.1 ("Rate estimation and discovery via IS") in the sharper form DESIGN.md
("Rate estimate") settles. The pool of N segments splits into

* the known stratum: segments whose level-0 value is already known (from discovery), counted
  exactly, and
* the unknown rest U, over which segment i gets an inclusion probability
  pi_i = min(1, lam q_i), q_i = (1 - eps) p_i^alpha / sum_U p^alpha + eps / |U|, with lam set
  so that sum_U pi = K, the simulation budget (``inclusion_probabilities``).

Three designs draw the sample from U (``plan_sample``):

``"poisson"`` (default)
    Each segment in independently with probability pi_i. Horvitz-Thompson (HT) estimate
    p_hat = (1/N) [#known failures + sum over sampled failures of 1/pi_i], variance estimate
    (1/N^2) sum over sampled failures of (1 - pi_i)/pi_i^2, both unbiased.
``"fixed"``
    K segments (floor or ceil when K is fractional), by *randomised systematic sampling*
    (random permutation of U,
    then systematic sampling with a random start along the cumulated pi). Same pi, same HT
    estimate. No unbiased variance estimator exists for systematic sampling; we use Deville's
    (1999) form of the Hajek approximation, which treats the design as maximum-entropy
    (conditional Poisson); the random permutation is what makes that approximation hold.
``"with-replacement"``
    The paper's sampler: K draws i.i.d. from q. The total over U is estimated by
    (1/K) sum over draws of 1{f_i <= gamma}/q_i, its variance by the sample variance of the K
    terms divided by K. Kept to reproduce the paper: it cannot reach recall 1 and a segment
    drawn twice wastes a simulation (DESIGN.md).

One sample serves every gamma: the estimators take a failure matrix of shape
(n_sampled, n_gammas).

Confidence interval (``interval="gamma"``, the default). A normal interval fails badly with
few failures: the HT total is a weighted count with a long right tail (measured coverage
0.72-0.74 at nominal 0.90 with ~2 failures sampled). We use the gamma interval that Fay &
Feuer (1997, Stat. Med. 16:791) built for weighted sums of rare counts. Split the estimated
total into its deterministic part D (known failures, sampled failures with pi = 1) and its
random part R with variance estimate v. With G(q; M, V) the q-quantile of the Gamma with
mean M and variance V (shape M^2/V, scale V/M),

    lower = D + G(a/2; R, v),    upper = D + G(1 - a/2; R + w, v + w^2),    a = 1 - confidence,

where w is the weight (variance-to-mean ratio, ``failure_weights``: (1 - pi)/pi) of one more
failure that the upper limit allows for. With equal weights and small pi this is Garwood's
exact Poisson interval, scaled; with fewer than ~5 failures sampled it is therefore
conservative (measured 0.97-0.98), the price of never under-covering there. The choice of w:

* Fay and Feuer's own, the largest weight in U (``interval="fay-feuer"``), guarantees
  coverage, but defensive sampling leaves pi ~ eps K / |U| somewhere, so the interval is
  1-90 times the rate wide (30 at eps = 0).
* The heaviest *sampled* failure works when weights are alike, but under-covers (0.70-0.85
  measured) when a few failures that the design gave a small pi carry most of the variance:
  samples that miss them show a small total *and* a small v.
* So w = max(heaviest sampled failure, w_model), with w_model = sum_U p_n w / sum_U p_n
  (``model_weight``, stored in the plan): the weight a failure carries on average if
  failures are spread over U as p_n says. The point estimate stays design-unbiased whatever
  p_n is; only the upper limit leans on the model, and a model that puts too much failure
  mass where pi is small only widens it (miscalibrated pool below: 0.996-0.999).
  Without a model weight and with no failure sampled, w is the design's mean segment weight
  (|U_r| - K_r)/K_r over the segments with pi < 1, so that the upper limit is the rule of
  three, -ln(a/2)(1 - pi)/pi, under uniform sampling.

Finally the interval is intersected with what is certain: at least the failures in hand, at
most the segments not seen to pass. HT totals are not range-respecting, so in a rare sample
the sum exceeds that cap, and a with-replacement sum can fall below the failures in hand;
p_hat is then held to the limit it crossed (the truth lies within them, so this only moves
p_hat nearer), and ``p_hat_unbiased`` keeps the sum.

The standard error follows the same reasoning. The HT variance estimate sums over the
sampled failures with pi < 1, so it is 0 whenever none was sampled, even when failures
sampled with certainty (pi = 1) make p_hat > 0. The design is still random there (failures
may hide among the pi < 1 segments), so ``se`` is then that of one failure of the weight w
the upper limit allows for, sqrt(w)/N, and ``variance_note`` says so; ``var_hat`` stays the
HT estimate. se = 0 is reported only for a census of U, which is exact.

Measured coverage (``bench/bench_estimate.py --coverage``, 2,000 repeats, N = 5,000,
nominal 0.90; poisson / fixed / with-replacement): calibrated p_n, alpha 1, eps 0.1,
K = 5 F: 0.885 / 0.905 / 0.921; alpha 2.5: 0.926 / 0.925 / 0.873; eps 0: 0.996 / 0.998 /
0.949; K = F / 2 (~2 failures sampled): 0.975 / 0.978 / 0.974; p_n over-predicting failures
2x with three at p_n = 1e-4: 0.999 / 0.996 / 0.998.

Known limitation, shared by every design-based interval: failures that the design gives a
tiny pi and that the model also rules out (a GP confidently wrong about them) are almost
never sampled, and nothing computed from the sample or the model can see them. With eps = 0
and p_n = 0 at a failure, pi = 0 and the estimator is biased low (``ZeroInclusionWarning``);
with p_n ~ 1e-28 it is unbiased but its variance is astronomically large (DESIGN.md:
~1/(N^2 p^2 pi) of relative variance per such failure). Keep eps > 0.

The GP's own estimate (paper section 3 and appendix B.1): p_hat_GP = mean(p_n), with
Var(p_hat_GP) = (1/N^2) sum_ij [Phi2(s_i, s_j; r_ij) - p_i p_j] (``gp_variance_exact``) and
the bound Var <= mean(p_n (1 - p_n)) (Proposition 1, ``gp_estimate``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import gammaincinv, ndtri

from bams_cli.core.sampling import (  # noqa: F401  (the design, re-exported)
    DESIGNS,
    Design,
    SamplePlan,
    ZeroInclusionWarning,
    draw_poisson,
    draw_systematic,
    draw_with_replacement,
    failure_weights,
    inclusion_probabilities,
    log_selection_distribution,
    model_weight,
    plan_sample,
    selection_distribution,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

Interval = Literal["gamma", "fay-feuer", "wald"]
INTERVALS: tuple[str, ...] = ("gamma", "fay-feuer", "wald")


# --------------------------------------------------------------------------------------------
# Estimation
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RateEstimate:
    """The rate estimate for one gamma.

    Attributes
    ----------
    p_hat : float
        Unbiased estimate of the failure rate over the pool.
    se : float
        Estimated standard error: sqrt(var_hat), except where var_hat = 0 while failures
        could still hide among the segments sampled with pi < 1: then the standard error of
        one such failure of the weight the upper limit allows for (``variance_note`` says
        so). 0 only for a census of U; inf when undefined (one draw with replacement).
    var_hat : float
        Variance estimate (unbiased for poisson and with-replacement; approximate for fixed).
    ci_low, ci_high : float
        Confidence interval (gamma interval unless asked otherwise; see the module docstring).
    confidence : float
    rel_var : float
        Estimated relative variance se^2 / p_hat^2 (NaN when p_hat = 0; ``rel_var_note``).
    n_sampled : int
        Distinct segments simulated.
    n_failures_sampled : int
        Distinct sampled segments that fail.
    n_known_failures : int
        Failures in the known stratum.
    n_failures_found : int
        Distinct failures in hand: known + sampled.
    n_eff : float
        Effective number of failures in the random part, R^2 / v (inf when it has no
        variance, 0 when none was sampled).
    design : str
    variance_note : str or None
        What ``se`` rests on when it is not sqrt(var_hat) (``variance_note``); None when it
        is the design's variance estimate.
    rel_var_note : str or None
        Why ``rel_var`` is undefined (NaN), else None.
    """

    p_hat: float
    se: float
    var_hat: float
    ci_low: float
    ci_high: float
    confidence: float
    rel_var: float
    n_sampled: int
    n_failures_sampled: int
    n_known_failures: int
    n_failures_found: int
    n_eff: float
    design: str
    variance_note: str | None = None
    rel_var_note: str | None = None


@dataclass(frozen=True)
class RateEstimates:
    """``RateEstimate`` for m columns (gammas, or repeats in a simulation), as arrays.

    Every field but ``confidence`` and ``design`` is an ndarray of shape (m,), with the
    meaning of the ``RateEstimate`` field of the same name, and four more: ``variance_basis``
    (int8, a ``BASIS_*`` code: what ``se`` rests on), ``w_allow`` (the weight of the one
    more failure the gamma upper limit allows for), ``certain`` (the part of p_hat that is
    not random: known failures and those sampled with pi = 1) and ``cap`` (the largest rate
    the sample allows: every segment not seen to pass failing); the last two let
    ``core.design.combine_stages`` combine stages. Index it (``est[j]``) or call
    ``to_list()`` for per-gamma ``RateEstimate`` objects, whose notes spell these out.
    """

    p_hat: FloatArray
    se: FloatArray
    var_hat: FloatArray
    ci_low: FloatArray
    ci_high: FloatArray
    rel_var: FloatArray
    n_sampled: IntArray
    n_failures_sampled: IntArray
    n_known_failures: IntArray
    n_failures_found: IntArray
    n_eff: FloatArray
    variance_basis: NDArray[np.int8]
    w_allow: FloatArray
    confidence: float
    design: str
    certain: FloatArray | None = None
    cap: FloatArray | None = None
    #: The design-unbiased total over N (one stage's Horvitz-Thompson or Hansen-Hurwitz
    #: sum, or the stages' weighted sum), before p_hat is held within what the sample
    #: allows: at least the failures found, at most ``cap``. p_hat equals it but in rare
    #: samples. None where no such sum exists (a bound, a GP's estimate).
    p_hat_unbiased: FloatArray | None = None

    def __len__(self) -> int:
        return int(self.p_hat.size)

    def __getitem__(self, j: int) -> RateEstimate:
        kw: dict[str, float | int] = {}
        for name in _ESTIMATE_FIELDS:
            v = getattr(self, name)[j]
            kw[name] = int(v) if np.issubdtype(np.asarray(v).dtype, np.integer) else float(v)
        basis = int(self.variance_basis[j])
        return RateEstimate(
            confidence=self.confidence,
            design=self.design,
            variance_note=variance_note(basis, float(self.w_allow[j])),
            rel_var_note=rel_var_note(float(kw["p_hat"]), float(kw["se"])),
            **kw,  # type: ignore[arg-type]
        )

    def to_list(self) -> list[RateEstimate]:
        """One ``RateEstimate`` per column (gamma)."""
        return [self[j] for j in range(len(self))]


# What a reported se rests on (``RateEstimates.variance_basis``).
#: The design's variance estimate v: se = sqrt(var_hat).
BASIS_HT = 0
#: v = 0 because every sampled failure had pi = 1; se allows for one failure among pi < 1.
BASIS_CERTAIN_FAILURES = 1
#: v = 0 because no failure was sampled; se allows for one failure among pi < 1.
BASIS_NO_FAILURE = 2
#: The sampled terms show no spread (with replacement: every draw a failure of one weight;
#: fixed: one sampled failure with pi < 1 and no other sampled segment with pi < 1).
BASIS_NO_SPREAD = 3
#: Every segment of U was simulated: the estimate is exact, se = 0.
BASIS_CENSUS = 4
#: One draw with replacement: no sample variance, se undefined (inf).
BASIS_SINGLE_DRAW = 5


def variance_note(basis: int, w_allow: float) -> str | None:
    """What a reported se rests on, in words, when it is not the design's variance estimate.

    Parameters
    ----------
    basis : int
        A ``BASIS_*`` code (``RateEstimates.variance_basis``).
    w_allow : float
        Weight (variance-to-mean ratio, (1 - pi)/pi) of the one more failure that the
        interval's upper limit allows for.

    Returns
    -------
    note : str or None
        None for ``BASIS_HT``.
    """
    allow = (
        f"se is that of one failure of weight {w_allow:.4g} among them, the same allowance "
        "the interval's upper limit makes"
    )
    if basis == BASIS_CERTAIN_FAILURES:
        return (
            "every sampled failure was included with certainty (pi = 1), so the HT variance "
            "estimate is 0; the variance comes from the segments sampled with pi < 1, none of "
            f"which failed: {allow}"
        )
    if basis == BASIS_NO_FAILURE:
        return (
            "no failure was sampled, so the HT variance estimate is 0; the variance comes from "
            f"the segments sampled with pi < 1, none of which failed: {allow}"
        )
    if basis == BASIS_NO_SPREAD:
        return (
            "the sampled terms y/pi (with replacement: the draws' y/(K q)) show no spread, so the "
            "variance estimate is 0; failures may remain among the segments with pi < 1 not "
            f"sampled: {allow}"
        )
    if basis == BASIS_CENSUS:
        return "every segment of U was simulated (pi = 1): the estimate is exact and se = 0"
    if basis == BASIS_SINGLE_DRAW:
        return "one draw (K = 1): a sample variance needs at least two, so se is undefined"
    return None


def rel_var_note(p_hat: float, se: float) -> str | None:
    """Why the relative variance se^2 / p_hat^2 is undefined, or None when it is defined."""
    if not math.isfinite(se):
        return "se is undefined (see variance_note), and so is se^2 / p_hat^2"
    if p_hat <= 0:
        return "p_hat = 0: the relative variance se^2 / p_hat^2 is undefined"
    return None


_ESTIMATE_FIELDS = (
    "p_hat",
    "se",
    "var_hat",
    "ci_low",
    "ci_high",
    "rel_var",
    "n_sampled",
    "n_failures_sampled",
    "n_known_failures",
    "n_failures_found",
    "n_eff",
)


def _as_columns(a: ArrayLike, n: int, name: str) -> NDArray:
    a = np.asarray(a)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[0] != n:
        raise ValueError(f"{name} must have shape ({n},) or ({n}, m); got {a.shape}")
    return a


def estimate_from_sample(
    prob: ArrayLike,
    failures: ArrayLike,
    *,
    design: Design,
    n_pool: int,
    n_unknown: int,
    budget: float,
    counts: ArrayLike | None = None,
    known_failures: ArrayLike = 0,
    confidence: float = 0.9,
    interval: Interval = "gamma",
    w_model: ArrayLike | None = None,
    w_max: float | None = None,
) -> RateEstimates:
    """HT / importance-sampling estimate of the failure rate, vectorised over columns.

    Rows are units of U; a row with count 0 contributes nothing, so a caller may pass all of
    U with a 0/1 (or draw-count) matrix in ``counts``, one column per repeat: that is how the
    tests run thousands of repeats at once.

    Total over U (T_U) and its variance estimate v, per design (paper section 4.1; Sarndal,
    Swensson & Wretman 1992 for the HT forms):

    * poisson:  T_hat = sum_s y/pi,  v = sum_s y (1 - pi)/pi^2  (unbiased).
    * fixed:    T_hat as poisson; v = n/(n - 1) sum_s (1 - pi)(y/pi - A)^2 with
      A = sum_s (1 - pi) y/pi / sum_s (1 - pi), over the n sampled units with pi < 1
      (Deville 1999 form of the Hajek approximation; approximate, see ``draw_systematic``).
    * with-replacement:  T_hat = (1/K) sum_draws y/q,  v = s^2 / K with s^2 the sample
      variance of the K terms y/q (unbiased).

    p_hat = (known failures + T_hat) / N and var_hat = v / N^2.

    Parameters
    ----------
    prob : array_like of shape (n_rows,)
        pi of each row (poisson, fixed) or q (with-replacement); > 0 where counts > 0.
    failures : array_like of bool, shape (n_rows,) or (n_rows, m)
        1{f_0(x) <= gamma} per row, one column per gamma. A single column broadcasts
        against a multi-column ``counts``.
    design : {"poisson", "fixed", "with-replacement"}
    n_pool : int
        N.
    n_unknown : int
        |U|.
    budget : float
        K as in ``SamplePlan.budget`` (needed for with-replacement and for the zero-failure
        upper limit).
    counts : array_like of int, shape (n_rows,) or (n_rows, m), optional
        Draws per row; default 1 each (every row sampled once).
    known_failures : int or array_like of shape (m,)
        Failures in the known stratum, per column.
    confidence : float
        Two-sided confidence level of the interval, in (0, 1).
    interval : {"gamma", "fay-feuer", "wald"}
        "gamma" (default) and "fay-feuer": the gamma intervals of the module docstring.
        "wald": p_hat +- z se, for comparison only: it under-covers badly with few failures.
    w_model : float or array_like of shape (m,), optional
        ``model_weight`` per column; widens the gamma upper limit (module docstring).
        None: design-only weights.
    w_max : float, optional
        Largest failure weight in U (``max_failure_weight``); required for "fay-feuer".

    Returns
    -------
    RateEstimates
        Arrays of shape (m,).
    """
    if design not in DESIGNS:
        raise ValueError(f"design must be one of {DESIGNS}; got {design!r}")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must lie in (0, 1); got {confidence}")
    prob = np.asarray(prob, dtype=np.float64)
    n_rows = prob.size
    y_all = _as_columns(failures, n_rows, "failures").astype(bool)
    c_all = (
        np.ones((n_rows, 1), np.int64)
        if counts is None
        else _as_columns(counts, n_rows, "counts").astype(np.int64)
    )
    m = max(y_all.shape[1], c_all.shape[1])
    if y_all.shape[1] not in (1, m) or c_all.shape[1] not in (1, m):
        raise ValueError(
            f"failures and counts have incompatible columns: {y_all.shape}, {c_all.shape}"
        )
    in_s_all = c_all > 0
    if np.any(in_s_all.any(axis=1) & ~(prob > 0)):
        raise ValueError("a sampled row has prob <= 0; pi (or q) must be > 0 where sampled")
    known = np.broadcast_to(np.asarray(known_failures, dtype=np.float64), (m,)).copy()
    n_sampled = np.broadcast_to(np.count_nonzero(in_s_all, axis=0), (m,)).astype(np.int64)
    # Only rows that fail in some column carry the estimate; the others matter only through
    # the sample size (and, for "fixed", the Hajek centring). Cutting to them first keeps a
    # (|U|, repeats) count matrix cheap.
    fr = np.flatnonzero(y_all.any(axis=1))
    pf = prob[fr]
    inv = 1.0 / np.where(pf > 0, pf, 1.0)
    c = c_all[fr].astype(np.float64)
    y = y_all[fr].astype(np.float64)
    yf = y * (c > 0)  # sampled-failure indicator (distinct units), (n_fail_rows, m)
    if yf.shape[1] != m:
        yf = np.broadcast_to(yf, (fr.size, m))
    n_fail_s = yf.sum(axis=0).astype(np.int64)
    n_pass_s = n_sampled - n_fail_s

    # One estimator per design: Hansen-Hurwitz with replacement, Horvitz-Thompson else.
    if design == "with-replacement":
        est = _with_replacement_sum(
            pf, inv, y, c, yf, n_fail_s, K=float(budget), n_unknown=n_unknown, m=m
        )
    else:
        est = _ht_sum(
            pf, inv, yf, prob, in_s_all, design=design, budget=float(budget),
            n_unknown=n_unknown, m=m,
        )  # fmt: skip
    D, R, v, n_rand_fail = est.D, est.R, est.v, est.n_rand_fail

    # HT totals are not range-respecting: in a rare sample (failures drawn at small pi from
    # a small pool) the sum exceeds every segment not seen to pass, which cannot all fail;
    # a with-replacement (Hansen-Hurwitz) sum can also fall below the distinct failures in
    # hand. p_hat is held between the two (only nearer the truth, which lies between them);
    # p_hat_unbiased keeps the sum, which stages combine (``core.design.combine_stages``)
    # and pooling uses.
    unbiased = known + D + R
    found = known + D + n_rand_fail
    hi_cap = known + n_unknown - n_pass_s
    total = np.minimum(np.maximum(unbiased, found), hi_cap)
    N = float(n_pool)
    p_hat = total / N
    var_hat = v / N**2

    w_allow = _allowance_weight(est, w_model, m)
    basis = _variance_basis(est, design=design, budget=float(budget), n_unknown=n_unknown)
    # v sums over the sampled failures with pi < 1 (with replacement: the spread of the
    # draws), so it is 0 when none was sampled, even when failures sampled with pi = 1
    # carry p_hat. se = 0 would then claim a certainty the design does not have: failures
    # may sit among the pi < 1 segments unseen. So se is that of one such failure, of the
    # weight w_allow the upper limit allows for (the rule of three's reasoning, applied to
    # the se), and ``variance_basis`` records why. Only a census of U is exact.
    floor = np.isin(basis, (BASIS_CERTAIN_FAILURES, BASIS_NO_FAILURE, BASIS_NO_SPREAD))
    se = np.where(floor, np.sqrt(w_allow) / N, np.sqrt(var_hat))
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_var = np.where((p_hat > 0) & np.isfinite(se), se**2 / p_hat**2, np.nan)
        n_eff = np.where(R > 0, np.where(v > 0, R**2 / np.where(v > 0, v, 1.0), np.inf), 0.0)

    lo, hi = _interval(
        est, total, known=known, w_allow=w_allow, interval=interval, w_max=w_max,
        a=1.0 - confidence,
    )  # fmt: skip
    # Intersect with the feasible range: the failures in hand are a sure lower bound, and
    # segments seen to pass cannot fail (p_hat is within it, above).
    hi = np.minimum(np.maximum(hi, total), hi_cap)
    lo = np.minimum(np.maximum(lo, found), np.minimum(total, hi))
    return RateEstimates(
        p_hat=p_hat,
        se=se,
        var_hat=var_hat,
        ci_low=lo / N,
        ci_high=hi / N,
        rel_var=rel_var,
        n_sampled=n_sampled,
        n_failures_sampled=n_fail_s,
        n_known_failures=known.astype(np.int64),
        n_failures_found=found.astype(np.int64),
        n_eff=n_eff,
        variance_basis=basis,
        w_allow=w_allow,
        confidence=confidence,
        design=design,
        certain=(known + D) / N,
        cap=hi_cap / N,
        p_hat_unbiased=unbiased / N,
    )


@dataclass(frozen=True)
class _Sum:
    """What one design's estimator makes of a sample, per column (``estimate_from_sample``).

    Attributes
    ----------
    D : ndarray of shape (m,)
        The deterministic part of the total over U: failures sampled with pi = 1.
    R : ndarray of shape (m,)
        The random part, and ``v`` its variance estimate.
    v : ndarray of shape (m,)
    yr : ndarray of shape (n_failure_rows, m)
        The sampled failures that carry R.
    n_rand_fail : ndarray of int, shape (m,)
        Distinct failures among them.
    wt : ndarray of shape (n_failure_rows,)
        Each failure row's weight, its variance-to-mean ratio (``failure_weights``).
    w0 : float
        The weight of a typical segment of U_r, which the upper limit allows for when no
        failure was sampled and no model says otherwise.
    n_certain : int
        Segments of U with pi = 1 (0 with replacement).
    """

    D: FloatArray
    R: FloatArray
    v: FloatArray
    yr: FloatArray
    n_rand_fail: IntArray
    wt: FloatArray
    w0: float
    n_certain: int


def _with_replacement_sum(
    q: FloatArray,
    inv: FloatArray,
    y: FloatArray,
    c: FloatArray,
    yf: FloatArray,
    n_fail_s: IntArray,
    *,
    K: float,
    n_unknown: int,
    m: int,
) -> _Sum:
    """Hansen-Hurwitz: T = (1/K) sum_draws y/q, v = s^2 / K with s^2 the sample variance of
    the K terms y/q, over the failure rows (q, 1/q, y, draw counts c)."""
    yc = np.broadcast_to(y * c, (q.size, m))
    T = (inv @ yc) / K
    # Two passes: the squared deviations from T, the failure draws' (1/q - T)^2 and T^2
    # for each of the other draws. The one-pass sum Y^2 - K T^2 cancels when every draw is
    # a failure of similar weight (terms 1e9 +- 1: every digit lost, v = 0); these terms
    # are all >= 0.
    n_zero_draws = K - yc.sum(axis=0)
    ss = ((inv[:, None] - T[None, :]) ** 2 * yc).sum(axis=0) + n_zero_draws * T**2
    v = ss / (K * (K - 1.0)) if K > 1 else np.full(m, np.inf)
    return _Sum(
        D=np.zeros(m),
        R=T,
        v=v,
        yr=yf,
        n_rand_fail=n_fail_s,
        wt=failure_weights(np.where(q > 0, q, 1.0), design="with-replacement", K=K),
        w0=(n_unknown - 1.0) / K,  # the weight at uniform q = 1/|U|
        n_certain=0,
    )


def _ht_sum(
    pf: FloatArray,
    inv: FloatArray,
    yf: FloatArray,
    prob: FloatArray,
    in_s_all: BoolArray,
    *,
    design: str,
    budget: float,
    n_unknown: int,
    m: int,
) -> _Sum:
    """Horvitz-Thompson over the failure rows (pi, 1/pi, sampled failures): failures at
    pi = 1 are certain (D), the rest R = sum y/pi with the design's variance estimate
    (``_poisson_variance``, ``_deville_variance``)."""
    certain = pf >= 1.0
    rand = ~certain
    yr = yf * rand[:, None]
    one_m = (1.0 - pf) * rand
    v = (
        _poisson_variance(one_m, inv, yr)
        if design == "poisson"
        else _deville_variance(prob, in_s_all, one_m, inv, yr, m)
    )
    n_certain = int(np.count_nonzero(prob >= 1.0))
    K_r = budget - n_certain
    return _Sum(
        D=(certain @ yf).astype(np.float64),
        R=inv @ yr,
        v=v,
        yr=yr,
        n_rand_fail=yr.sum(axis=0).astype(np.int64),
        wt=one_m * inv,  # failure_weights: (1 - pi)/pi, 0 at pi = 1
        # The weight of a segment of U_r at its mean inclusion probability K_r / |U_r|.
        w0=(n_unknown - n_certain - K_r) / K_r if K_r > 0 else 0.0,
        n_certain=n_certain,
    )


def _poisson_variance(one_m: FloatArray, inv: FloatArray, yr: FloatArray) -> FloatArray:
    """v = sum_s y (1 - pi)/pi^2 over the sampled failures with pi < 1 (unbiased)."""
    return (one_m * inv**2) @ yr


def _deville_variance(
    prob: FloatArray,
    in_s_all: BoolArray,
    one_m: FloatArray,
    inv: FloatArray,
    yr: FloatArray,
    m: int,
) -> FloatArray:
    """Deville (1999): n/(n-1) sum_s c_i (e_i - A)^2 with c_i = 1 - pi_i, e_i = y_i/pi_i,
    over the sampled units with pi < 1 (failures or not); A = sum_s c e / sum_s c."""
    rand_all = prob < 1.0
    n_r = np.count_nonzero(in_s_all & rand_all[:, None], axis=0).astype(np.float64)
    n_r = np.broadcast_to(n_r, (m,))
    sum_c = np.broadcast_to(((1.0 - prob) * rand_all) @ in_s_all, (m,))
    sum_ce = (one_m * inv) @ yr
    sum_ce2 = (one_m * inv**2) @ yr
    with np.errstate(divide="ignore", invalid="ignore"):
        A2 = np.where(sum_c > 0, sum_ce**2 / np.where(sum_c > 0, sum_c, 1.0), 0.0)
        fac = np.where(n_r > 1, n_r / (n_r - 1.0), 1.0)
    return np.maximum(fac * (sum_ce2 - A2), 0.0)


def _allowance_weight(est: _Sum, w_model: ArrayLike | None, m: int) -> FloatArray:
    """The weight of the one more failure the gamma upper limit allows for: the heaviest
    failure seen, or the model's typical failure if heavier; with no model, the design's
    typical segment when no failure was seen."""
    w_seen = np.where(est.yr > 0, est.wt[:, None], 0.0).max(axis=0, initial=0.0)
    wm = (
        np.full(m, np.nan)
        if w_model is None
        else np.broadcast_to(np.asarray(w_model, dtype=np.float64), (m,))
    )
    return np.where(
        np.isnan(wm), np.where(est.n_rand_fail > 0, w_seen, est.w0), np.maximum(w_seen, wm)
    )


def _variance_basis(est: _Sum, *, design: str, budget: float, n_unknown: int) -> NDArray:
    """What se rests on per column, a ``BASIS_*`` code (``variance_note``)."""
    m = est.v.size
    basis = np.full(m, BASIS_HT, np.int8)
    if design == "with-replacement":
        has_random = n_unknown > 1
        if not budget > 1:
            basis[:] = BASIS_SINGLE_DRAW
    else:
        has_random = n_unknown - est.n_certain > 0
    no_var = (est.v <= 0) & (basis == BASIS_HT)
    if not has_random:
        basis[no_var] = BASIS_CENSUS
    else:
        basis[no_var] = np.where(
            est.R > 0,
            BASIS_NO_SPREAD,
            np.where(est.D > 0, BASIS_CERTAIN_FAILURES, BASIS_NO_FAILURE),
        )[no_var]
    return basis


def _interval(
    est: _Sum,
    total: FloatArray,
    *,
    known: FloatArray,
    w_allow: FloatArray,
    interval: str,
    w_max: float | None,
    a: float,
) -> tuple[FloatArray, FloatArray]:
    """The interval's limits on the total over the pool, before the feasible range."""
    if interval in ("gamma", "fay-feuer"):
        if interval == "gamma":
            w_next = w_allow
        else:
            if w_max is None:
                raise ValueError("interval='fay-feuer' needs w_max (estimate_rate computes it)")
            w_next = np.full(est.v.size, float(w_max))
        lo_r, hi_r = _gamma_interval(est.R, est.v, w_next, a)
        lo = known + est.D + lo_r
        hi = known + est.D + hi_r
    elif interval == "wald":
        z = float(ndtri(1.0 - a / 2.0))
        lo = total - z * np.sqrt(est.v)
        hi = total + z * np.sqrt(est.v)
    else:
        raise ValueError(f"interval must be one of {INTERVALS}; got {interval!r}")
    # No variance estimate (one draw with replacement): nothing narrower than the feasible
    # range can be claimed.
    lo = np.where(np.isfinite(est.v), lo, -np.inf)
    hi = np.where(np.isfinite(est.v), hi, np.inf)
    return lo, hi


def _gamma_interval(
    R: FloatArray, v: FloatArray, w_next: FloatArray, a: float
) -> tuple[FloatArray, FloatArray]:
    """Fay-Feuer gamma interval on the random part R of the HT total (module docstring).

    lower = Gamma quantile a/2 with mean R and variance v;
    upper = Gamma quantile 1 - a/2 with mean R + w and variance v + w^2, w = ``w_next``.
    A Gamma with mean M and variance V has shape M^2/V and scale V/M; with R = 0 the upper
    limit is w (-ln(a/2)), the rule of three. With v = 0 and w = 0 both limits are R.

    Parameters
    ----------
    R, v : ndarray of shape (m,)
        Estimate of the random part of the total and its variance estimate.
    w_next : ndarray of shape (m,)
        Variance-to-mean ratio of the one extra failure the upper limit allows for.
    a : float
        1 - confidence.

    Returns
    -------
    lo, hi : ndarray of shape (m,)
    """
    lo = np.zeros_like(R)
    pos = (R > 0) & (v > 0)
    # R > 0 with v = 0 (e.g. every with-replacement draw a failure of equal weight): exact.
    lo[(R > 0) & (v <= 0)] = R[(R > 0) & (v <= 0)]
    if np.any(pos):
        lo[pos] = (v[pos] / R[pos]) * gammaincinv(R[pos] ** 2 / v[pos], a / 2.0)
    M = R + w_next
    V = v + w_next**2
    # V = 0 (no variance and no extra failure allowed for, w = 0: every segment of U_r has
    # pi = 1, or with replacement q = 1) is a point mass at M; the Gamma's shape M^2/V
    # would be inf and its scale 0, and their product NaN.
    hi = M.copy()
    ok = (M > 0) & (V > 0)
    # P(Gamma(k) <= x) = 1 - a/2  <=>  x = gammaincinv(k, 1 - a/2).
    hi[ok] = (V[ok] / M[ok]) * gammaincinv(M[ok] ** 2 / V[ok], 1.0 - a / 2.0)
    return lo, hi


def max_failure_weight(plan: SamplePlan) -> float:
    """Largest variance-to-mean ratio a failure of U could have: Fay and Feuer's w_M.

    (1 - pi)/pi over the segments of U with pi < 1, or (1 - q)/(K q) with replacement;
    +inf if some segment can never be sampled.
    """
    if plan.n_unknown == 0:
        return 0.0
    if plan.design == "with-replacement":
        qmin = float(plan.q.min())
        return math.inf if qmin <= 0 else (1.0 - qmin) / (plan.budget * qmin)
    return poisson_max_weight(plan.pi)


def poisson_max_weight(pi: ArrayLike) -> float:
    """(1 - pi)/pi at the smallest pi < 1 of a Poisson design over U: 0 when every pi is 1,
    +inf when some segment can never be sampled (``max_failure_weight``'s w_M)."""
    pi = np.asarray(pi, dtype=np.float64)
    rand = pi[pi < 1.0]
    if rand.size == 0:
        return 0.0
    pmin = float(rand.min())
    return math.inf if pmin <= 0 else (1.0 - pmin) / pmin


def estimate_rate(
    plan: SamplePlan,
    failures: ArrayLike,
    *,
    known_failures: ArrayLike = 0,
    confidence: float = 0.9,
    interval: Interval = "gamma",
    w_model: ArrayLike | None = None,
) -> list[RateEstimate]:
    """Rate estimate per gamma from a drawn plan and the simulated outcomes.

    Parameters
    ----------
    plan : SamplePlan
    failures : array_like of bool, shape (n_sampled,) or (n_sampled, n_gammas)
        1{f_0 <= gamma} of the sampled segments, in ``plan.sampled`` order.
    known_failures : int or array_like of int, shape (n_gammas,)
        Failures in the known stratum per gamma.
    confidence : float
    interval : {"gamma", "fay-feuer", "wald"}
        See ``estimate_from_sample``.
    w_model : float or array_like of shape (n_gammas,), optional
        Model weight per gamma; default ``plan.w_model`` (from the planning p_n). Pass
        ``model_weight(p_gamma[plan.unknown], prob, ...)`` per gamma when p_n at the other
        gammas is at hand.

    Returns
    -------
    estimates : list of RateEstimate, length n_gammas
    """
    w_max = max_failure_weight(plan) if interval == "fay-feuer" else None
    est = estimate_from_sample(
        plan.sampled_prob,
        failures,
        design=plan.design,
        n_pool=plan.n_pool,
        n_unknown=plan.n_unknown,
        budget=plan.budget,
        counts=plan.counts,
        known_failures=known_failures,
        confidence=confidence,
        interval=interval,
        w_model=plan.w_model if w_model is None else w_model,
        w_max=w_max,
    )
    return est.to_list()


# The GP's own estimate and its exact variance live in ``core.gp_rate``; re-exported here.
from bams_cli.core.gp_rate import (  # noqa: E402, F401
    GPVariance,
    bvn_cov,
    gp_estimate,
    gp_variance_exact,
)
