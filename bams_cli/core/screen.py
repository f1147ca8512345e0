"""The screened (two-phase) rate estimate: a cheap-level screen, then level-0 confirmation.

A study with a cheap simulator level can spend part of the estimate's budget K on it.
Phase 1 draws a Poisson sample S1 of U (the segments without a level-0 result) with
inclusion probabilities pi1, chosen from the model as an estimate stage is
(``design.choose_design``), and runs the cheap level on it at ``cost`` per run. The model
refitted on those results gives p2 over S1, now informed by each segment's own cheap run.
Phase 2 draws a Poisson sample S2 of S1 with probabilities pi2 chosen from p2 and runs
level 0 on it, with what is left of K:

    K2 = K - cost |S1|.

The estimate of the failures in U (Sarndal, Swensson & Wretman 1992, ch. 9, two-phase
sampling) is

    T = sum_{S2} y / (pi1 pi2),

unbiased whatever rule chose pi2 from phase 1's outcomes, as long as it was fixed before
phase 2's: E[T | S1] = sum_{S1} y / pi1, whose mean is sum_U y. Its variance splits as

    Var T = sum_U y (1 - pi1) / pi1  +  E[ sum_{S1} y (1 - pi2) / (pi1^2 pi2) ]

(``phase1_variance``, ``phase2_variance``), and

    v = sum_{S2} y (1 - pi1 pi2) / (pi1 pi2)^2

estimates it without bias: term by term, (1 - pi1)/(pi1^2 pi2) + (1 - pi2)/(pi1 pi2)^2 =
(1 - pi1 pi2)/(pi1 pi2)^2. That is the one-phase Poisson form at pi = pi1 pi2, so
``estimate.estimate_from_sample`` estimates a screened sample as it stands
(``confirmed_pi``).

Why: the model ranks failures by its p_n, which on a problem it knows poorly ranks them
little better than chance (digits, weak_cheap). A cheap run on the segment itself is
evidence p_n does not have. Measured through the tool on the suite
(docs/suite/screen_design.md).

Open leads (segments whose cheap run already failed and that have no level-0 result,
``pipeline.estimation.open_leads``) are in the screen with certainty: pi1 = pi2 = 1. Their
cheap run is in the log, so phase 1 costs nothing for them; phase 2 confirms each out of
K2 and the rest of K2 goes to the other screened segments. Both phases' designs are fixed
before any outcome they weigh is seen, so T stays unbiased, and a lead adds no variance
where the model, which shrinks one cheap run towards its smooth surroundings, would have
confirmed it at a small pi2 (weight 1/(pi1 pi2)).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bams_cli import defaults
from bams_cli.core.design import DesignChoice, RiskPosterior, choose_design, predicted_variance

FloatArray = NDArray[np.float64]


def screen_size(K: float, cost: float, share: float, n_unknown: int) -> float:
    """Expected number of cheap runs of the screen: ``share`` of K spent at ``cost`` each,
    at most one per segment of U.

    Parameters
    ----------
    K : float
        The estimate's budget in level-0 runs.
    cost : float
        One cheap run's cost in level-0 runs, in (0, 1).
    share : float
        Share of K spent on the screen, in (0, 1).
    n_unknown : int
        |U|.
    """
    if not (K > 0 and math.isfinite(K)):
        raise ValueError(f"K must be a positive number, got {K!r}")
    if not 0 < cost < 1:
        raise ValueError(f"the cheap level's cost must lie in (0, 1), got {cost!r}")
    if not 0 < share < 1:
        raise ValueError(f"the screen's share of K must lie in (0, 1), got {share!r}")
    return float(min(share * K / cost, n_unknown))


def screen_design(
    p: ArrayLike,
    *,
    K: float,
    cost: float,
    share: float,
    posterior: RiskPosterior,
    leads: ArrayLike | None = None,
) -> DesignChoice:
    """Phase 1: pi1 over U, the estimate's own design choice at the screen's size.

    Parameters
    ----------
    p : array_like of shape (n_unknown,)
        p_n over U.
    K, cost, share : float
        As in ``screen_size``.
    posterior : RiskPosterior
        How far p_n is trusted (``design.risk_posterior``).
    leads : bool array_like of shape (n_unknown,), optional
        Open leads (module docstring): pi1 = 1 there, at no cost (their cheap run is in
        the log); the design over the other segments keeps the screen's size.
    """
    p = np.asarray(p, dtype=np.float64)
    lead = _mask(leads, p.size)
    n_rest = p.size - int(lead.sum())
    return _with_leads(p, lead, screen_size(K, cost, share, max(n_rest, 1)), posterior)


def lead_budget(K: float, share: float) -> float:
    """The level-0 runs a screen's confirmation expects to have, K (1 - share): the budget
    whose ``defaults.LEAD_SHARE`` the certain leads may take (``design.certain_leads``)."""
    return float(K) * (1.0 - float(share))


def _with_leads(
    p: FloatArray, lead: NDArray[np.bool_], k: float, posterior: RiskPosterior
) -> DesignChoice:
    """pi = 1 on the leads and the estimate's design choice at expected size ``k`` over the
    other segments (all of them, without leads)."""
    if not lead.any():
        return choose_design(p, K=k, posterior=posterior)
    rest = ~lead
    pi = np.ones(p.size)
    risk = np.zeros(p.size)
    if not rest.any():
        return DesignChoice(name="leads", pi=pi, risk=risk, predicted={})
    c = choose_design(p[rest], K=k, posterior=posterior)
    pi[rest] = c.pi
    risk[rest] = c.risk
    return replace(c, pi=pi, risk=risk)


def _mask(leads: ArrayLike | None, n: int) -> NDArray[np.bool_]:
    if leads is None:
        return np.zeros(n, bool)
    lead = np.asarray(leads, dtype=bool)
    if lead.shape != (n,):
        raise ValueError(f"leads has shape {lead.shape}; expected ({n},), one per segment")
    return lead


def confirm_budget(K: float, cost: float, n_screened: int) -> float:
    """K2 = K - cost |S1|: the level-0 runs left once the screen's cheap runs are paid.

    At least one: every screened segment must keep pi2 > 0 for T to stay unbiased, so a
    screen drawn far larger than expected (its size is random) overspends K a little
    rather than leave it unconfirmed.
    """
    return max(1.0, float(K) - float(cost) * int(n_screened))


def confirm_design(
    p2: ArrayLike, *, K2: float, posterior: RiskPosterior, leads: ArrayLike | None = None
) -> DesignChoice:
    """Phase 2: pi2 over S1 from the refitted model's p2, expected size min(K2, |S1|).

    A weight 1/pi1^2 in the risk would minimise the predicted variance, but it draws the
    budget towards segments phase 1 took at small pi1, most of them passing ones, and
    measured worse on the suite wherever p2 is good (docs/suite/screen_design.md).

    ``leads`` (bool over S1): the open leads, confirmed with certainty (pi2 = 1) out of
    K2; the rest of K2 goes to the other screened segments, at least one run's worth
    where any remain (every screened segment keeps pi2 > 0, as ``confirm_budget`` says).

    An empty screen (S1 is random, and may be empty) has nothing to confirm: T = 0, which
    is E[T | S1] for it; the design returned is empty.
    """
    p2 = np.asarray(p2, dtype=np.float64)
    if p2.size == 0:
        return DesignChoice(name="uniform", pi=np.zeros(0), risk=np.zeros(0), predicted={})
    if not K2 > 0:
        raise ValueError(f"no level-0 budget is left to confirm the screen (K2 = {K2!r})")
    lead = _mask(leads, p2.size)
    n_lead = int(lead.sum())
    return _with_leads(p2, lead, confirm_size(K2, n_lead, p2.size) - n_lead, posterior)


def screen_leads(
    cheap: ArrayLike,
    K2: float,
    *,
    share: float | None = None,
    taken: ArrayLike | None = None,
) -> NDArray[np.bool_]:
    """The screen's own leads: the screened segments whose cheap result ranks among the
    lowest ``share`` x K2 of the screen's, confirmed with certainty (pi2 = 1) beside the
    open leads ``taken``, which count against the same share.

    A model that reads the cheap level as weak shrinks each cheap run towards its
    surroundings, so its p2 confirms a low cheap result little more often than any other;
    the cheap result itself ranks failures far better than chance on every problem
    measured (docs/suite/screen_frontier.md). The rule needs no model and no rate: the
    ranking is fixed by phase 1's outcomes before phase 2 draws, so T stays unbiased.

    Parameters
    ----------
    cheap : array_like of shape (n_screened,)
        Each screened segment's cheap result (its mean where it has several); NaN where it
        has none (its cheap run abandoned): never a lead.
    K2 : float
        The confirmation's level-0 budget (``confirm_budget``).
    share : float, optional
        The share of K2 the leads may take, in [0, 1); default
        ``defaults.SCREEN_LEAD_SHARE``.
    taken : bool array_like of shape (n_screened,), optional
        The open leads already confirmed with certainty.

    Returns
    -------
    bool ndarray of shape (n_screened,)
        The screen's leads, none of them in ``taken``; ties at the cut are broken by
        position, so the rule is a function of S1 and its cheap results alone.
    """
    share = defaults.SCREEN_LEAD_SHARE if share is None else float(share)
    v = np.asarray(cheap, dtype=np.float64)
    if v.ndim != 1:
        raise ValueError(f"cheap must be 1-d, one result per screened segment, got {v.shape}")
    if not 0.0 <= share < 1.0:
        raise ValueError(f"the screen leads' share of K2 must lie in [0, 1), got {share!r}")
    tk = _mask(taken, v.size)
    out = np.zeros(v.size, bool)
    room = int(math.floor(share * max(float(K2), 0.0) + 1e-9)) - int(tk.sum())
    candidates = np.flatnonzero(np.isfinite(v) & ~tk)
    if room <= 0 or candidates.size == 0:
        return out
    order = candidates[np.argsort(v[candidates], kind="stable")]
    out[order[:room]] = True
    return out


def confirm_size(K2: float, n_lead: int, n_screened: int) -> float:
    """The confirmation's expected number of level-0 runs (``confirm_design``): K2 where
    the leads leave room in it, else the leads plus one run's worth over the other screened
    segments, never more than |S1|.

    It exceeds K2 only where the open leads alone use K2 up; the plan records it as its
    ``samples``, which is what the simulation team is asked to run on average.
    """
    if not n_lead:
        return min(float(K2), float(n_screened))
    return n_lead + min(max(float(K2) - n_lead, 1.0), float(n_screened - n_lead))


def confirmed_pi(pi1: ArrayLike, pi2: ArrayLike) -> FloatArray:
    """pi = pi1 pi2 of each segment of S1: what its level-0 result is weighted by."""
    pi1 = np.asarray(pi1, dtype=np.float64)
    pi2 = np.asarray(pi2, dtype=np.float64)
    if pi1.shape != pi2.shape:
        raise ValueError(
            f"pi1 has shape {pi1.shape}, pi2 {pi2.shape}: one each per screened segment"
        )
    for name, a in (("pi1", pi1), ("pi2", pi2)):
        if a.size and not (np.all(a > 0) and np.all(a <= 1)):
            raise ValueError(f"{name} must lie in (0, 1]")
    return pi1 * pi2


def allowance_pi(
    pi1: ArrayLike, screened: ArrayLike, pi2: ArrayLike, risk: ArrayLike
) -> FloatArray:
    """pi over U for the interval's allowance for a failure no run has seen
    (``design.unseen_failure_weight``): pi1 pi2 on S1, and outside it pi1 times the
    screen's mean pi2 weighted by ``risk`` (a failure the screen missed would have been
    confirmed as often as a screened segment of its risk is on average: the "mean"
    allowance of docs/suite/screen_design.md). An empty screen prices every segment at pi1.

    The mean is over S1 as drawn, not reweighted by 1/pi1 to stand for all of U: S1 holds
    more of the segments phase 1 favoured, whose pi2 is larger, so this stand-in is larger
    than U's risk-weighted mean pi2 would be (a narrower interval). It is the form
    measured below; the reweighted one lies between it and the min and is not measured.

    Why the mean and not the screen's smallest pi2 (the "min" allowance, shipped until
    2026-11-27): over every suite problem and the held-out instances of the screened ones
    the two gave the same coverage where ``--screen auto`` screens (toy2d 0.973, av_like
    1.000, gap_sim 0.982; no interval wholly below the rate under either), and the mean's
    interval is 1.3 to 3.5 times narrower (toy2d 1.8 against 6.2 times the rate). Where
    the cheap level is weak (weak_cheap, an explicit ``--screen``) the mean's intervals lay
    wholly below the rate in 3.9% of draws against 1.9% (coverage 0.927 against 0.948).

    Parameters
    ----------
    pi1 : array_like of shape (n_unknown,)
    screened : bool array_like of shape (n_unknown,)
        S1.
    pi2 : array_like of shape (|S1|,)
        The confirmation's probabilities, in S1's order.
    risk : array_like of shape (n_unknown,)
        The allowance's relative risk over U (``RiskPosterior.allowance_risk``): where an
        unseen failure is put.
    """
    pi1 = np.asarray(pi1, dtype=np.float64)
    s1 = np.asarray(screened, dtype=bool)
    pi2 = np.asarray(pi2, dtype=np.float64)
    r = np.asarray(risk, dtype=np.float64)
    if not (pi1.shape == s1.shape == r.shape) or pi2.shape != (int(s1.sum()),):
        raise ValueError(
            f"pi1 {pi1.shape}, screened {s1.shape} and risk {r.shape} are over U; pi2 "
            f"{pi2.shape} over S1 ({int(s1.sum())} segments)"
        )
    if not (np.all(np.isfinite(r)) and np.all(r >= 0)):
        raise ValueError("the allowance's risk must be finite and >= 0")
    w = r[s1]
    if pi2.size == 0:
        stand_in = 1.0
    else:
        stand_in = float(w @ pi2 / w.sum()) if w.sum() > 0 else float(pi2.mean())
    out = pi1 * stand_in
    out[s1] = pi1[s1] * pi2
    return out


def min_allowance_pi(pi1: ArrayLike, screened: ArrayLike, pi2: ArrayLike) -> FloatArray:
    """pi1 pi2 on S1 and pi1 times the screen's smallest pi2 outside it: the smallest pi
    a segment of U could have been confirmed at, whose (1 - pi)/pi bounds any failure's
    weight (``estimate.poisson_max_weight``, the ``fay-feuer`` interval's w_max)."""
    pi1 = np.asarray(pi1, dtype=np.float64)
    s1 = np.asarray(screened, dtype=bool)
    pi2 = np.asarray(pi2, dtype=np.float64)
    out = pi1 * float(pi2.min(initial=1.0))
    out[s1] = pi1[s1] * pi2
    return out


def predicted_vs_uniform(
    risk: ArrayLike, pi1: ArrayLike, screened: ArrayLike, pi2: ArrayLike, K: float
) -> float:
    """The confirmed design's variance over a uniform Poisson design's of K level-0 runs
    over U, both predicted from ``risk`` (the checked model's relative risk over U,
    ``RiskPosterior.risk``) as ``design.predicted_variance`` predicts a stage's: phase 1's
    term sum_U r (1 - pi1)/pi1, and phase 2's given the screen as drawn,
    sum_{S1} r (1 - pi2)/(pi1^2 pi2) (``phase1_variance``, ``phase2_variance``). NaN when
    the uniform design would be exact (K >= |U|)."""
    r = np.asarray(risk, dtype=np.float64)
    a = np.asarray(pi1, dtype=np.float64)
    s1 = np.asarray(screened, dtype=bool)
    b = np.asarray(pi2, dtype=np.float64)
    k = min(float(K), float(r.size))
    uniform = predicted_variance(np.full(r.size, k / r.size), r) if r.size else 0.0
    if not uniform > 0:
        return math.nan
    rs, a_s = r[s1], a[s1]
    with np.errstate(divide="ignore", invalid="ignore"):
        two = float(np.where(b >= 1.0, 0.0, rs * (1.0 - b) / (a_s * a_s * b)).sum())
    return (predicted_variance(a, r) + two) / uniform


def phase1_variance(failures: ArrayLike, pi1: ArrayLike) -> float:
    """sum_U y (1 - pi1)/pi1: the variance T would have if S1's level-0 values were seen
    (``design.predicted_variance`` with the failures as the risk)."""
    return predicted_variance(pi1, np.asarray(failures, dtype=np.float64))


def phase2_variance(failures: ArrayLike, pi1: ArrayLike, pi2: ArrayLike) -> float:
    """sum_{S1} y (1 - pi2)/(pi1^2 pi2): Var(T | S1), over the screened segments."""
    y = np.asarray(failures, dtype=bool)
    a = np.asarray(pi1, dtype=np.float64)[y]
    b = np.asarray(pi2, dtype=np.float64)[y]
    return float(((1.0 - b) / (a * a * b)).sum())
