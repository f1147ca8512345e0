"""Choosing the rate estimate's design from a model that has been checked against level 0.

DESIGN.md ("Rate estimate") and issue 12. The paper samples in proportion to p_n^alpha and
trusts p_n fully; a GP that is confidently wrong then puts a failure at a tiny inclusion
probability, and the estimate's variance is many times that of uniform sampling (measured
on the suite: 2.5-3.8x on weak_cheap, digits and rare_regions). Here p_n is not trusted
blindly; it is mixed with uniform risk by as much as its own track record says:

    r_i(lam) = (1 - lam) u_i + lam,        u_i = p_i / mean_U(p),

the *calibrated relative risk*: lam is the share of the failure mass that the model does not
explain and that is spread evenly over U. The Poisson design that minimises the predicted
Horvitz-Thompson variance sum_U p_i (1 - pi_i) / pi_i under sum pi = K is pi_i proportional
to sqrt(p_i), capped at 1 (Lagrange: d/dpi (p/pi + nu pi) = 0), so the design for a given lam
is pi proportional to sqrt(r(lam)) (``calibrated_design``); lam = 1 is uniform sampling.

How much to trust p_n (``risk_posterior``). Earlier estimate stages are random samples
with known pi, whose level-0 outcomes and planning-time p_n are stored in their plans.
Given which sampled segments failed, where they failed says how good u was: with the count
of failures n_f fixed, a failure falls on sampled segment i with probability
r_i / sum_S r (Poisson process; the sample's own selection depends on p_n only, so it does
not bias this), which gives the likelihood

    L(lam) = prod_{i in S, failed} r_i(lam) / (sum_{j in S} r_j(lam))^n_f,

combined with a Beta prior on lam on a grid (``risk_prior``: ``defaults.RISK_MIX_PRIOR``,
or ``defaults.RISK_MIX_PRIOR_WEAK_CHEAP`` where the fitted cheap level does not track level
0; an estimate keeps the prior of its first step). With no failure
sampled the posterior is the prior; failures at small u push lam towards 1 (uniform),
failures where u is large towards 0.

The estimate is staged (``estimate --plan``, DESIGN.md): stage 1 spends a share of K with the
design at the current posterior mean of lam; once its results are in, the posterior is
updated and the next stage spends its share, and so on (``defaults.STAGES``). Each stage's
HT estimate T_s counts what is known at
its planning exactly and is unbiased given the past, so T = sum_s w_s T_s with weights fixed
when stage 1 is planned is unbiased, and its stages are uncorrelated
(E[(T_1 - T)(T_2 - T)] = E[(T_1 - T) E[T_2 - T | stage 1]] = 0):
Var(T) = sum_s w_s^2 Var(T_s), estimated by sum_s w_s^2 v_s (``combine_stages``). The
weights (``stage_weights``) are those that minimise Var(T) were every stage uniform: w_s
proportional to 1 / (N_s (1 - pi_s) / pi_s), N_s the segments left to stage s and
pi_s = K_s / N_s. While K is a small share of U that is K_s / K to a percent or two; as K
nears U, stage 2 samples most of what stage 1 left, its variance falls towards 0, and
K_s / K would have kept a quarter of stage 1's (a trial study with K = 0.93 |U| measured
3.1x a one-stage uniform design's variance; these weights give exactly uniform's there,
before stage 2's refit gains anything).

The interval's upper limit allows for a failure no stage sampled, of the mean weight
(1 - pi)/pi that a failure placed as the risk says would carry (``unseen_failure_weight``).
That risk is not the posterior mean the design uses but the least trust in p_n the evidence
cannot rule out: lam at its ``defaults.RISK_MIX_UPPER`` (0.9) posterior quantile
(``RiskPosterior.allowance_risk``). Failures the model puts where it is wrong sit at small
pi, and the mean trust put too little weight there: a trial study's model expected 18
failures in a region that held 113, and 2 of 9 intervals lay wholly below the rate.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import betaln

from bams_cli import defaults
from bams_cli.core.estimate import (
    BASIS_CENSUS,
    BASIS_HT,
    BASIS_NO_FAILURE,
    RateEstimates,
    _gamma_interval,
    inclusion_probabilities,
)

FloatArray = NDArray[np.float64]

#: Grid over lam for the posterior: dense near 0 and 1, where the likelihood is steepest.
_LAM_GRID = 0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, 121))

#: Shapes the calibration map may take: r proportional to u^tau (tau 1: p_n as it is;
#: 0.5: flatter, a model whose contrasts are overstated). The sharper shapes tau 1.5 and 2
#: were weighed until 2026-11-24. Dropping them lowered the mean variance on toy2d, av_like,
#: weak_cheap, digits and gap_sim under every prior measured (av_like 0.258 -> 0.245 of
#: uniform's under Beta(1, 1)) and raised it on rare_regions by up to 0.017; some worst
#: seeds rose with it (under Beta(0.5, 1): rare_regions 1.179 -> 1.188, weak_cheap 1.011
#: -> 1.016 and 1.060 -> 1.076, digits' MCM-GP runs 1.123 -> 1.160); docs/suite/risk_prior.md.
#: With stage 1's one or two failures a sharper shape fits them as well as tau 1 and
#: mostly adds weight where the model puts most.
TAUS = (0.5, 1.0)


def relative_risk(p: ArrayLike) -> FloatArray:
    """u = p / mean(p) over U (all ones when p is 0 everywhere: nothing to go on).

    Parameters
    ----------
    p : array_like of shape (n_unknown,)
        p_n over U, in [0, 1].

    Returns
    -------
    u : ndarray of shape (n_unknown,)
        Non-negative, mean 1.
    """
    p = np.asarray(p, dtype=np.float64)
    mean = float(p.mean()) if p.size else 0.0
    if not mean > 0.0:
        return np.ones(p.size)
    return p / mean


def risk_norms(u: ArrayLike, taus: ArrayLike = TAUS) -> FloatArray:
    """mean_U(u^tau) for each tau: what turns u^tau into a relative risk of mean 1."""
    u = np.asarray(u, dtype=np.float64)
    return np.array([float(np.mean(u**t)) if u.size else 1.0 for t in np.asarray(taus)])


@dataclass(frozen=True)
class StageEvidence:
    """One finished stage: its sampled segments' relative risk at planning and outcomes.

    Attributes
    ----------
    u : ndarray of shape (n_sampled,)
        p_n / mean_U(p_n) at the stage's planning.
    failed : bool ndarray of shape (n_sampled,)
    norms : ndarray of shape (len(TAUS),)
        ``risk_norms`` of the stage's U at planning.
    p_mean : float, optional
        mean_U(p_n) at planning: the model's own failure rate over U, which anchors the
        count of failures (``risk_posterior``). None: where the failures fell only.
    """

    u: FloatArray
    failed: NDArray[np.bool_]
    norms: FloatArray
    p_mean: float | None = None


@dataclass(frozen=True)
class RiskPosterior:
    """Posterior over the calibration maps r = (1 - lam) u^tau / mean(u^tau) + lam.

    Attributes
    ----------
    taus : ndarray of shape (n_tau,)
    lams : ndarray of shape (n_lam,)
    weights : ndarray of shape (n_tau, n_lam)
        Posterior probabilities, summing to 1.
    failures, sampled : int
        What the posterior rests on (0 and 0: the prior).
    prior : (float, float)
        The Beta(a, b) prior on lam it was formed from (``risk_prior``).
    """

    taus: FloatArray
    lams: FloatArray
    weights: FloatArray
    failures: int
    sampled: int
    prior: tuple[float, float] = defaults.RISK_MIX_PRIOR

    @property
    def lam_mean(self) -> float:
        """Posterior mean of lam, the share of failure mass the model does not explain."""
        return float(self.weights.sum(axis=0) @ self.lams)

    @property
    def tau_mean(self) -> float:
        """Posterior mean of tau (1: p_n's own shape; > 1 sharper; < 1 flatter)."""
        return float(self.weights.sum(axis=1) @ self.taus)

    def lam_quantile(self, q: float) -> float:
        """The q-quantile of lam's posterior."""
        cdf = np.cumsum(self.weights.sum(axis=0))
        return float(self.lams[min(int(np.searchsorted(cdf, q)), self.lams.size - 1)])

    def _shapes(self, p: ArrayLike) -> list[tuple[int, FloatArray]]:
        """(tau index, u^tau / mean(u^tau)) for every shape tau the posterior weighs."""
        u = relative_risk(p)
        w_tau = self.weights.sum(axis=1)
        # u^tau once per tau, for its norm (``risk_norms``) and its term alike.
        return [
            (t, (u_tau := u**tau) / (float(np.mean(u_tau)) if u.size else 1.0))
            for t, tau in enumerate(self.taus)
            if w_tau[t] > 0
        ]

    def risk(self, p: ArrayLike) -> FloatArray:
        """Posterior mean relative risk over U, mean 1: what the next design is built on.

        The predicted variance sum r (1 - pi)/pi is linear in r, so the posterior mean
        risk gives the posterior mean of every design's predicted variance.
        """
        trust = self.weights @ (1.0 - self.lams)  # sum_l w_tl (1 - lam_l), per tau
        r = np.full(np.asarray(p).size, self.lam_mean)
        for t, shaped in self._shapes(p):
            r += trust[t] * shaped
        return r

    def risk_at(self, p: ArrayLike, lam: float) -> FloatArray:
        """Relative risk over U (mean 1) with the model trusted as little as ``lam`` says:
        r = lam + (1 - lam) sum_tau w_tau u^tau / mean(u^tau), the shapes tau weighted as the
        posterior weighs them. At lam = ``lam_quantile(defaults.RISK_MIX_UPPER)`` it is where
        the interval's allowance puts an unseen failure (``unseen_failure_weight``): the
        least trust in p_n that the evidence cannot rule out, not its mean.
        """
        w_tau = self.weights.sum(axis=1)
        shaped = np.zeros(np.asarray(p).size)
        for t, term in self._shapes(p):
            shaped += w_tau[t] * term
        return float(lam) + (1.0 - float(lam)) * shaped

    def allowance_risk(self, p: ArrayLike) -> FloatArray:
        """``risk_at`` the lam quantile ``defaults.RISK_MIX_UPPER`` (module docstring)."""
        return self.risk_at(p, self.lam_quantile(defaults.RISK_MIX_UPPER))

    def summary(self) -> dict[str, float | int | list[float]]:
        """lam (mean, 90% upper), tau (mean) and the evidence's size, for the plan's record."""
        return {
            "lam": round(self.lam_mean, 6),
            "lam_high": round(self.lam_quantile(defaults.RISK_MIX_UPPER), 6),
            "tau": round(self.tau_mean, 6),
            "failures": self.failures,
            "sampled": self.sampled,
            "prior": [float(self.prior[0]), float(self.prior[1])],
        }


def risk_posterior(
    evidence: list[StageEvidence],
    *,
    prior: tuple[float, float] = defaults.RISK_MIX_PRIOR,
    taus: ArrayLike = TAUS,
    anchor_sd: float | None = defaults.RISK_ANCHOR_SD,
) -> RiskPosterior:
    """Posterior over (tau, lam) given where the earlier stages' sampled failures fell.

    Likelihood of one stage (module docstring): prod over its sampled failures of r_i over
    (sum over its sampled segments of r)^n_f, r = (1 - lam) u^tau / norm_tau + lam.
    Prior: Beta(a, b) on lam, uniform over the tau grid.

    Parameters
    ----------
    evidence : list of StageEvidence
        Finished stages; empty gives the prior.
    prior : (float, float)
        Beta(a, b) on lam.
    taus : array_like
        The tau grid; each stage's ``norms`` must follow it.
    anchor_sd : float or None
        With every stage's ``p_mean`` known: also use how many failures each stage found
        against what p_n predicts, with the model's explained rate c (1 - lam) log-normal
        about mean p_n with this sd. None: only where the failures fell.

    Returns
    -------
    RiskPosterior
    """
    taus = np.asarray(taus, dtype=np.float64)
    a, b = prior
    lam = _LAM_GRID[1:-1]
    log_post = np.broadcast_to(
        (a - 1.0) * np.log(lam) + (b - 1.0) * np.log1p(-lam) - betaln(a, b), (taus.size, lam.size)
    ).copy()
    n_f = n_s = 0
    anchored = anchor_sd is not None and all(ev.p_mean and ev.p_mean > 0 for ev in evidence)
    # log(c / mean_U p_n) on a grid, c the failure rate per unit risk (anchored form only).
    Z, c_z, log_c_z = _Z_GRID, None, None
    ll_z = np.zeros((taus.size, lam.size, Z.size)) if anchored else None
    for ev in evidence:
        u = np.asarray(ev.u, dtype=np.float64)
        failed = np.asarray(ev.failed, dtype=bool)
        if u.shape != failed.shape or u.ndim != 1:
            raise ValueError(
                f"u and failed must be 1-d of one shape; got {u.shape}, {failed.shape}"
            )
        if np.any(~np.isfinite(u)) or np.any(u < 0):
            raise ValueError("u must be finite and >= 0")
        n_s += u.size
        k = int(failed.sum())
        n_f += k
        if not k and not anchored:
            continue
        if anchored:
            assert ev.p_mean is not None
            c_z = ev.p_mean * np.exp(Z)
            log_c_z = k * np.log(c_z)
        for t, tau in enumerate(taus):
            A = u**tau / ev.norms[t]
            log_rf = (
                np.log((1.0 - lam)[:, None] * A[failed][None, :] + lam[:, None]).sum(axis=1)
                if k
                else np.zeros(lam.size)
            )
            sum_r = (1.0 - lam) * A.sum() + lam * u.size
            if anchored:
                # Poisson counts: intensity c r_i per sampled segment, c = p_mean e^z.
                assert ll_z is not None and c_z is not None and log_c_z is not None
                ll_z[t] += log_rf[:, None] + log_c_z[None, :] - sum_r[:, None] * c_z[None, :]
            else:
                # Where the failures fell, given their count (c profiled out).
                log_post[t] += log_rf - k * np.log(sum_r)
    if anchored:
        # The model is taken at its word for the failures it explains, c (1 - lam) =
        # mean p_n, up to a log-normal factor of sd ``anchor_sd``: so a count of failures
        # far above what p_n predicts says the model misses failure mass (lam large).
        assert anchor_sd is not None and ll_z is not None
        total = ll_z  # in place: (tau, lam, z) grids are 46,000 terms, allocated once
        total += _prior_z(float(anchor_sd))[None, :, :]
        top = total.max(axis=2, keepdims=True)
        total -= top
        # Terms below e^-700 are written as e^-700: each row's sum holds e^0 = 1, so they
        # vanish in it as the 0 that exp would give (and np.exp never takes its slow path
        # for results that underflow, 30 times one fast pass over these 46,000 terms).
        np.maximum(total, -700.0, out=total)
        log_post += top[..., 0] + np.log(np.exp(total, out=total).sum(axis=2))
    w = np.exp(log_post - log_post.max()) * np.gradient(lam)[None, :]
    w /= w.sum()
    return RiskPosterior(
        taus=taus, lams=lam, weights=w, failures=n_f, sampled=n_s, prior=(float(a), float(b))
    )


def risk_prior(cheap_discrepancy: float | None) -> tuple[float, float]:
    """The Beta prior on lam for a study whose fitted model has this cheap-level discrepancy.

    ``cheap_discrepancy`` is the level-1 discrepancy-plus-noise sd over the level-0 signal
    sd (``pipeline.screening.cheap_level_discrepancy``; None: no cheap level). Where it is
    at least ``defaults.SCREEN_HINT_DISCREPANCY`` the cheap level does not track level 0,
    the model's p_n rests on its few level-0 runs, and it is trusted less
    (``defaults.RISK_MIX_PRIOR_WEAK_CHEAP``); elsewhere ``defaults.RISK_MIX_PRIOR``.
    """
    if cheap_discrepancy is None or cheap_discrepancy < defaults.SCREEN_HINT_DISCREPANCY:
        return defaults.RISK_MIX_PRIOR
    # A NaN ratio (``pipeline.screening`` passes None for a non-finite fit) is no
    # evidence that the cheap level tracks level 0: the lesser trust.
    return defaults.RISK_MIX_PRIOR_WEAK_CHEAP


def confirm_prior(cheap_discrepancy: float | None) -> tuple[float, float]:
    """The Beta prior on lam of a screen's level-0 confirmation (pi2 over S1).

    Where the cheap level tracks level 0 (``cheap_discrepancy`` under
    ``defaults.SCREEN_HINT_DISCREPANCY``) the refitted p_n over S1 rests on each segment's
    own cheap run and is trusted almost wholly (``defaults.RISK_MIX_PRIOR_CONFIRM``);
    elsewhere the confirmation is planned as the screen was (``risk_prior``).
    """
    if cheap_discrepancy is not None and cheap_discrepancy < defaults.SCREEN_HINT_DISCREPANCY:
        return defaults.RISK_MIX_PRIOR_CONFIRM
    return risk_prior(cheap_discrepancy)


#: The grid over z = log(c / mean_U p_n) of the anchored posterior (``risk_posterior``).
_Z_GRID = np.linspace(-6.0, 6.0, 97)


@functools.lru_cache(maxsize=8)
def _prior_z(anchor_sd: float) -> FloatArray:
    """log prior of z given lam over (lam, z), up to a constant: the same for every call."""
    lam = _LAM_GRID[1:-1]
    out = -0.5 * ((_Z_GRID[None, :] + np.log1p(-lam)[:, None]) / anchor_sd) ** 2
    out.flags.writeable = False
    return out


def calibrated_design(risk: ArrayLike, *, K: float, order: ArrayLike | None = None) -> FloatArray:
    """Inclusion probabilities pi proportional to sqrt(risk), capped at 1, sum K.

    The minimiser of the predicted variance sum r (1 - pi)/pi over designs with sum pi = K
    (module docstring); ``estimate.inclusion_probabilities`` with alpha = 1/2 on r.

    Parameters
    ----------
    risk : array_like of shape (n_unknown,)
        Relative failure risk r > 0 (``RiskPosterior.risk``).
    K : float
        Expected sample size.
    order : int array_like of shape (n_unknown,), optional
        A permutation sorting risk descending: saves the sort (``inclusion_probabilities``).

    Returns
    -------
    pi : ndarray of shape (n_unknown,)
    """
    r = np.asarray(risk, dtype=np.float64)
    top = float(r.max()) if r.size else 1.0
    return inclusion_probabilities(r / top, alpha=0.5, defensive=0.0, K=K, order=order)


def predicted_variance(pi: ArrayLike, risk: ArrayLike) -> float:
    """sum r (1 - pi)/pi: the HT total's variance if failures occur with probability r.

    Proportional to the design's variance under the calibrated model whatever the rate, so
    ratios between designs are what the model predicts.
    """
    pi = np.asarray(pi, dtype=np.float64)
    risk = np.asarray(risk, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = np.where(pi >= 1.0, 0.0, risk * (1.0 - pi) / pi)
    return float(terms.sum())


@dataclass(frozen=True)
class DesignChoice:
    """The design an estimate stage uses, and the candidates it was chosen from.

    Attributes
    ----------
    name : str
        "calibrated" (pi proportional to sqrt(r)), "uniform" or "p^alpha".
    pi : ndarray of shape (n_unknown,)
    risk : ndarray of shape (n_unknown,)
        The posterior mean relative risk the prediction used.
    predicted : dict of str -> float
        Each candidate's predicted variance relative to uniform sampling of the same K.
    """

    name: str
    pi: FloatArray
    risk: FloatArray
    predicted: dict[str, float]


def choose_design(
    p: ArrayLike,
    *,
    K: float,
    posterior: RiskPosterior,
    alpha: float = defaults.ALPHA,
    defensive: float = defaults.DEFENSIVE,
    order: ArrayLike | None = None,
) -> DesignChoice:
    """Predict each candidate design's variance under the posterior risk; take the smallest.

    Candidates: uniform, the calibrated design, and the paper's form p^alpha mixed with a
    defensive share (``estimate.inclusion_probabilities``). Ties go to uniform, which
    needs no model.

    Parameters
    ----------
    p : array_like of shape (n_unknown,)
        p_n over U.
    K : float
        Expected sample size.
    posterior : RiskPosterior
        How far p_n is trusted (``risk_posterior``).
    alpha, defensive : float
        The paper-form candidate's.
    order : int array_like of shape (n_unknown,), optional
        A permutation sorting p descending (``np.argsort(-p, kind="stable")``), when the
        caller has it (``core.evaluate.staged_trials``). Both weighted candidates are
        non-decreasing in p, so this one sort serves both (``inclusion_probabilities``
        checks it); by default it is computed here.

    Returns
    -------
    DesignChoice
    """
    p = np.asarray(p, dtype=np.float64)
    n = p.size
    risk = posterior.risk(p)
    if order is None and n:
        order = np.argsort(-p, kind="stable")
    uniform = np.full(n, min(1.0, K / n)) if n else np.zeros(0)
    cands = {
        "uniform": uniform,
        "calibrated": calibrated_design(risk, K=K, order=order),
        "p^alpha": inclusion_probabilities(p, alpha=alpha, defensive=defensive, K=K, order=order)
        if p.max(initial=0.0) > 0 or defensive > 0
        else uniform,
    }
    base = predicted_variance(uniform, risk)
    predicted = {
        k: (predicted_variance(v, risk) / base if base > 0 else 1.0) for k, v in cands.items()
    }
    best = min(("uniform", "calibrated", "p^alpha"), key=lambda k: (predicted[k], k != "uniform"))
    return DesignChoice(name=best, pi=cands[best], risk=risk, predicted=predicted)


def unseen_failure_weight(risk: ArrayLike, pi: ArrayLike) -> float:
    """Mean weight (1 - pi)/pi of a failure spread over U as ``risk`` says (pi < 1 only).

    ``estimate.model_weight`` with the posterior risk in place of p_n: the interval's
    upper limit allows for one more failure of this weight. NaN when every pi is 1.
    """
    pi = np.asarray(pi, dtype=np.float64)
    risk = np.asarray(risk, dtype=np.float64)
    rand = (pi > 0) & (pi < 1.0)
    r = np.where(rand, risk, 0.0)
    mass = float(r.sum())
    if mass <= 0:
        return math.nan
    return float(r @ ((1.0 - pi) / np.where(rand, pi, 1.0))) / mass


def lead_share(n_pairs: int, n_failed: int) -> float:
    """The share of K the open leads may take, from the study's evidence on leads: of
    ``n_pairs`` segments with a cheap run at or below gamma and a level-0 result,
    ``n_failed`` failed at level 0. ``defaults.LEAD_SHARE`` where (n_failed + 1) /
    (n_pairs + 2), the chance a lead fails under a uniform prior, is at least
    ``defaults.LEAD_HIT_MIN``; ``defaults.LEAD_SHARE_UNPROVEN`` below it."""
    if not 0 <= n_failed <= n_pairs:
        raise ValueError(f"need 0 <= failed <= pairs; got {n_failed} of {n_pairs}")
    hit = (n_failed + 1.0) / (n_pairs + 2.0)
    return defaults.LEAD_SHARE if hit >= defaults.LEAD_HIT_MIN else defaults.LEAD_SHARE_UNPROVEN


def certain_leads(
    p: ArrayLike,
    known: ArrayLike,
    leads: ArrayLike | None,
    K: float,
    share: float = defaults.LEAD_SHARE,
) -> NDArray[np.bool_]:
    """The open leads a new staged estimate samples with certainty out of K: those outside
    the known stratum, at most ``share`` K of them (``lead_share``), the highest p_n first
    (``pipeline.estimation.open_leads``; bool over the pool, all False without leads)."""
    p = np.asarray(p, dtype=np.float64)
    if leads is None:
        return np.zeros(p.size, bool)
    lead = np.asarray(leads, dtype=bool) & ~np.asarray(known, dtype=bool)
    idx = np.flatnonzero(lead)
    cap = max(int(share * K + 1e-9), 0)  # 0.5 x 126 is 63 however K was rounded
    if idx.size > cap:
        lead = np.zeros(p.size, bool)
        lead[idx[np.argsort(-p[idx], kind="stable")[:cap]]] = True
    return lead


def stage_weights(shares: ArrayLike, K: float, n_unknown: float) -> list[float]:
    """The weights of T = sum_s w_s T_s, fixed when stage 1 is planned (module docstring).

    Parameters
    ----------
    shares : array_like of shape (n_stages,)
        Each stage's share of K (summing to 1); stage s spends K_s = share_s K, at most
        the N_s segments left to it (N_1 = ``n_unknown``, N_{s+1} = N_s - K_s, the
        expected size of what a Poisson stage leaves).
    K : float
        The estimate's budget.
    n_unknown : float
        |U| when stage 1 is planned.

    Returns
    -------
    list of float
        w_s proportional to pi_s / (N_s (1 - pi_s)), pi_s = K_s / N_s: inverse to stage s's
        variance were its design uniform (the failure rate, the same in every stage's U,
        cancels). A stage that takes every segment left (pi_s = 1, a census of the rest)
        is exact: it gets weight 1 and the stages before it 0. One stage, or no budget:
        the shares.
    """
    sh = np.asarray(shares, dtype=np.float64)
    if sh.size <= 1 or K <= 0 or n_unknown <= 0:
        return [float(x) for x in sh]
    left, inv = float(n_unknown), np.zeros(sh.size)
    for s, share in enumerate(sh):
        k = min(float(share) * K, left)  # left stays > 0: a census returns below
        if k <= 0:
            continue
        if k >= left * (1.0 - 1e-12):  # a census of what is left: exact
            return [float(s == j) for j in range(sh.size)]
        pi = k / left
        inv[s] = pi / (left * (1.0 - pi))
        left -= k
    if inv.sum() <= 0:
        return [float(x) for x in sh]
    return [float(x) for x in inv / inv.sum()]


def combine_stages(
    stages: list[RateEstimates], weights: ArrayLike, *, n_pool: int
) -> RateEstimates:
    """T = sum_s w_s T_s over estimate stages, its variance and gamma interval.

    Parameters
    ----------
    stages : list of RateEstimates
        One per stage, in order, each from ``estimate.estimate_from_sample`` for that
        stage's plan (its known stratum: everything known at the stage's planning). The
        last stage's failures found and feasible range bound the combined interval.
    weights : array_like of shape (n_stages,)
        Fixed before stage 1 was drawn; summing to 1.
    n_pool : int
        N.

    Returns
    -------
    RateEstimates
        p_hat_unbiased = sum w_s p_hat_unbiased_s, and p_hat = it held between the
        failures found over N and the last stage's cap; var_hat = sum w_s^2 var_hat_s; the gamma interval on the combined
        random part, allowing for one more failure unseen by every stage (mean
        contribution sum w_s = 1, variance sum w_s^2 w_allow_s), never below the failures
        found; design "staged".

    Notes
    -----
    One stage's Horvitz-Thompson total is never below the failures it found (each counts
    1/pi >= 1), but the weighted sum can be: a stage 1 that drew few of the failures
    stage 2 then found (stage 2, planned from the model refitted on stage 1's outcomes,
    finds more of them at large pi) pulls it under the count in hand. In trials of the
    tool's whole path (refit between the stages) on a problem with a 1% rate, 1 draw of
    7 gave 87.3 failures against 88 found. The rate cannot be below what was found, so
    p_hat is raised to it: never farther from the truth than the weighted sum, biased only
    upwards, and by E[(found - sum)+], rare and small (``p_hat_unbiased`` keeps the sum for
    pooling estimates across studies, where that bias would add up).
    """
    w = np.asarray(weights, dtype=np.float64)
    if len(stages) != w.size or not len(stages):
        raise ValueError(f"need one weight per stage; got {w.size} for {len(stages)}")
    if not math.isclose(float(w.sum()), 1.0, rel_tol=1e-9) or np.any(w < 0):
        raise ValueError(f"stage weights must be >= 0 and sum to 1; got {w.tolist()}")
    if len(stages) == 1:
        return stages[0]
    N = float(n_pool)
    last = stages[-1]
    if any(s.certain is None or s.cap is None or s.p_hat_unbiased is None for s in stages):
        raise ValueError(
            "stages must come from estimate_from_sample (certain, cap and p_hat_unbiased set)"
        )
    assert last.cap is not None
    # Each stage's own sum, not its p_hat held under its cap: the weighted sum of those
    # would no longer be unbiased.
    total = sum(ws * np.asarray(s.p_hat_unbiased) for ws, s in zip(w, stages, strict=True)) * N
    certain = sum(ws * np.asarray(s.certain) for ws, s in zip(w, stages, strict=True)) * N
    v = sum(ws**2 * s.var_hat for ws, s in zip(w, stages, strict=True)) * N**2
    w_next = sum(ws**2 * s.w_allow for ws, s in zip(w, stages, strict=True))
    R = total - certain
    conf = last.confidence
    lo_r, hi_r = _gamma_interval(np.maximum(R, 0.0), v, w_next, 1.0 - conf)
    found = last.n_failures_found.astype(np.float64)
    unbiased = total
    cap = last.cap * N
    total = np.minimum(np.maximum(total, found), cap)
    hi = np.minimum(np.maximum(certain + hi_r, total), cap)
    lo = np.minimum(np.maximum(certain + lo_r, found), np.minimum(total, hi))
    var_hat = v / N**2
    census = last.variance_basis == BASIS_CENSUS
    floor = (v <= 0) & ~census
    se = np.where(census, 0.0, np.where(floor, np.sqrt(w_next) / N, np.sqrt(var_hat)))
    p_hat = total / N
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_var = np.where(p_hat > 0, se**2 / p_hat**2, np.nan)
        n_eff = np.where(R > 0, np.where(v > 0, R**2 / np.where(v > 0, v, 1.0), np.inf), 0.0)
    basis = np.where(census, BASIS_CENSUS, np.where(floor, BASIS_NO_FAILURE, BASIS_HT))
    sampled = np.sum([s.n_failures_sampled for s in stages], axis=0)
    return replace(
        last,
        p_hat=p_hat,
        se=se,
        var_hat=var_hat,
        ci_low=lo / N,
        ci_high=hi / N,
        rel_var=rel_var,
        n_sampled=np.sum([s.n_sampled for s in stages], axis=0),
        n_failures_sampled=sampled,
        # Known from level-0 runs outside the estimate's samples: the last stage's distinct
        # failures less every stage's sampled ones (a later stage's known stratum holds the
        # earlier stages' sampled failures, and a discovery batch's between the stages).
        n_known_failures=(last.n_failures_found - sampled).astype(np.int64),
        n_eff=n_eff,
        variance_basis=basis.astype(np.int8),
        w_allow=w_next,
        certain=certain / N,
        design="staged",
        p_hat_unbiased=unbiased / N,
    )


__all__ = [
    "TAUS",
    "DesignChoice",
    "RiskPosterior",
    "StageEvidence",
    "calibrated_design",
    "risk_norms",
    "choose_design",
    "combine_stages",
    "lead_share",
    "predicted_variance",
    "relative_risk",
    "stage_weights",
    "risk_posterior",
    "unseen_failure_weight",
]
