"""MAP training of the multifidelity GP: seeded L-BFGS-B restarts over the log parameters."""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import OptimizeResult, minimize
from threadpoolctl import threadpool_limits

from bams_cli import defaults
from bams_cli.core.conditioning_budget import BYTES_PER_ENTRY, max_conditioned
from bams_cli.core.gp._numerics import (
    FloatArray,
    GPFitError,
    IntArray,
    check_data,
    cholesky,
)
from bams_cli.core.gp.hyperparameters import Hyperparameters, _hyperparameters
from bams_cli.core.gp.model import MFGP
from bams_cli.core.gp.objective import _MAPObjective
from bams_cli.core.gp.priors import (
    PriorSpec,
    _Priors,
    level0_standardise,
    pair_scales,
    with_pair_modes,
)
from bams_cli.core.gp.transform import OutputTransform, candidate_transforms

_SCREEN_ITER = 10  # L-BFGS-B iterations every restart gets
_N_POLISH = 2  # restarts continued to convergence
_MAXITER = 300  # cap on those; converged runs stop well before
#: Seed of the draw that fills a conditioning subset (``conditioning_subset``): fixed, so
#: the same observation log always gives the same subset, and ``select``'s posterior is
#: the one ``fit`` scored with.
_SUBSET_SEED = 20_241_116


def _minimize(
    objective: _MAPObjective, theta: FloatArray, bounds: list, maxiter: int
) -> OptimizeResult:
    return minimize(
        objective, theta, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": maxiter}
    )


def fit_mfgp(
    X: FloatArray,
    levels: IntArray,
    y: FloatArray,
    n_levels: int,
    *,
    rng: np.random.Generator,
    restarts: int = 8,
    fixed: Hyperparameters | None = None,
    priors: PriorSpec | None = None,
    max_fit: int | None = defaults.FIT_SUBSET,
    max_memory: int | None = defaults.FIT_CONDITION_MEMORY,
) -> MFGP:
    """Fit the multifidelity GP by MAP and condition it on the data.

    With more than ``max_fit`` observations the hyperparameters come from a random subset
    of ``max_fit`` of them (``fit_subset``: stratified by level), and the returned model
    conditions on every observation with them; ``model.fitted_on`` says how many the
    search saw.

    Conditioning is exact on every observation while its covariance fits ``max_memory``
    bytes (``max_conditioned``: 14,654 observations at the default 2 GiB). Above that the
    model conditions exactly on a subset of that many (``conditioning_subset``: level 0
    first); ``model.conditioning`` records which. A subset's posterior variance is never
    below the exact one (conditioning on fewer observations cannot lower a Gaussian's
    variance), so its sd errs on the cautious side; how far its mean and sd are from the
    exact posterior is measured in bench/bench_fit.py --accuracy.

    Parameters
    ----------
    X : ndarray of shape (n, d)
        Inputs (reduced embeddings). Repeats and several levels at one x are fine.
    levels : int ndarray of shape (n,)
        Fidelity level of each observation, in [0, n_levels).
    y : ndarray of shape (n,)
        Observed metric.
    n_levels : int
        L + 1. Levels without observations keep their prior-mode hyperparameters.
    rng : numpy.random.Generator
        Draws the restart points; the only source of randomness.
    restarts : int
        Number of L-BFGS-B starts: one from the prior mode, ``restarts - 1`` from
        ``_Priors.sample_start``. Each runs 30 iterations; the best two then run to
        convergence, and the best MAP objective wins.
    fixed : Hyperparameters, optional
        If given, no training: the returned GP conditions on the data with these.
    priors : PriorSpec, optional
        Hyperparameter priors; ``priors.DEFAULT_PRIORS`` when omitted.
    max_fit : int, optional
        Most observations the hyperparameter search runs on (None: all).
    max_memory : int, optional
        Byte budget of the conditioning (None: exact on all, whatever it costs).

    Returns
    -------
    MFGP

    Raises
    ------
    GPFitError
        Bad data (message names the row), or no restart reached a finite objective.
    """
    if n_levels < 1:
        raise GPFitError(f"n_levels must be >= 1, got {n_levels}")
    X, levels, y = check_data(X, levels, y, n_levels)
    if fixed is not None:
        return condition(X, levels, y, n_levels, fixed, priors=priors, max_memory=max_memory)
    if restarts < 1:
        raise GPFitError(f"restarts must be >= 1, got {restarts}")

    ybar, ystd = level0_standardise(X, levels, y, n_levels)
    priors = with_pair_modes(priors, X, levels, (y - ybar) / ystd, n_levels)
    prior = _Priors.for_data(X, n_levels, priors)
    sub = fit_subset(levels, n_levels, max_fit, rng)
    Xf, lf, yf = (X, levels, y) if sub is None else (X[sub], levels[sub], y[sub])
    objective = _MAPObjective(Xf, lf, (yf - ybar) / ystd, n_levels, prior)
    bounds = list(zip(prior.lower, prior.upper, strict=True))
    # The search runs with every cheap level's scale held at 1 (the additive model), then
    # frees the scales that pairs show (``priors.shows_scale``) and continues from its
    # best point, and from there with each scale at its pairs' slope. The additive search
    # is thus the one a model without scales runs (its restarts, its optimum), and the
    # scaled one can only improve on it.
    first_scale = n_levels * (X.shape[1] + 2)
    held = [(0.0, 0.0) if i >= first_scale else b for i, b in enumerate(bounds)]
    slopes = pair_scales(X, levels, y, n_levels)
    free = [i for i, sl in enumerate(slopes) if math.isfinite(sl)]
    starts = [prior.mode] + [prior.sample_start(rng) for _ in range(restarts - 1)]
    starts = [np.clip(t, *np.transpose(held)) for t in starts]

    # Restarts in two stages: every start gets a short L-BFGS-B run, then the best
    # _N_POLISH of them continue to convergence. All `restarts` starts still compete for
    # the basin; the expensive tail of the optimisation is spent only on the leaders.
    # (Measured at n = 200, d = 12: full runs take ~140 evaluations each and nearly all
    # end in the same optimum, so this halves the fit time at no cost in objective.)
    # One BLAS thread: the matrices are a few hundred wide, where OpenBLAS threads only
    # add synchronisation (measured 30x slower Cholesky at n = 200 on a busy 2-core box).
    with threadpool_limits(limits=1, user_api="blas"):
        screened = [_minimize(objective, t, held, _SCREEN_ITER) for t in starts]
        finite = [r for r in screened if np.isfinite(r.fun)]
        finite.sort(key=lambda r: float(r.fun))
        polished = [_minimize(objective, r.x, held, _MAXITER) for r in finite[:_N_POLISH]]
        results = finite + polished
        if free and results:
            scaled = [b if i < first_scale or i - first_scale in free else (0.0, 0.0)
                      for i, b in enumerate(bounds)]  # fmt: skip
            base = min(results, key=lambda r: float(r.fun)).x
            # At a scale far from 1 the additive optimum's discrepancy (which took the
            # scale's share) pulls back towards 1: the starts at the pairs' slopes have
            # the discrepancy at its prior mode there, from the additive optimum and
            # from the prior's mode.
            at_slopes = [base.copy(), prior.mode.copy()]
            for t in at_slopes:
                for i in free:
                    lo, hi = scaled[first_scale + i]
                    rho = float(np.exp(np.clip(math.log(slopes[i]), lo, hi)))
                    t[first_scale + i] = math.log(rho)
                    t[1 + i] = math.log(prior.discrepancy_mode_at(i, rho))
            results += [
                _minimize(objective, np.clip(t, *np.transpose(scaled)), scaled, _MAXITER)
                for t in [base, *at_slopes]
            ]
    best_theta, best_f = None, math.inf
    for res in results:
        if np.isfinite(res.fun) and res.fun < best_f:
            best_theta, best_f = res.x, float(res.fun)
    if best_theta is None:
        raise GPFitError(
            f"MAP training failed from all {restarts} starts (non-finite objective); "
            "check X and y for extreme values or pass fixed hyperparameters"
        )

    K, _, _ = objective.covariance(best_theta)
    L, _ = cholesky(K)
    beta, _ = objective.gls_mean(L, objective.scaled_y(best_theta))
    try:
        hp = _hyperparameters(best_theta, beta, X.shape[1], n_levels, ybar, ystd)
    except ValueError as exc:
        # Values near the accepted limit (1e150) give a level offset or mean just past it.
        raise GPFitError(
            f"{str(exc).removeprefix('Hyperparameters: ')} in natural units (the observed "
            f"values span {float(np.min(y)):.3g} to {float(np.max(y)):.3g}); rescale the "
            "metric, e.g. to units where failures are within a few units of gamma"
        ) from None
    model = condition(X, levels, y, n_levels, hp, priors=priors, max_memory=max_memory)
    model.fitted_on = y.size if sub is None else sub.size
    if np.ptp(y) == 0.0:
        model.notes.append(
            f"all {y.size} observed values equal {y[0]:.6g}: the model is flat, and its "
            "failure probabilities rest on the priors alone"
        )
    return model


def conditioning_subset(levels: IntArray, n_levels: int, max_obs: int | None) -> IntArray | None:
    """Indices of the observations the model conditions on; None for all of them.

    Level-0 observations first (they measure theta0 itself; a cheap level's are blurred by
    its discrepancy), a fixed-seed uniform draw among them if they alone are too many; the
    remaining places go to a fixed-seed uniform draw from the cheap levels' observations
    (never more than ``max_obs`` in all: the budget is a ceiling). Measured on av_like (6,000 observations, 60% cheap, a subset of
    4,500): level 0 first kept the largest mean error at pool points to 22 posterior sds
    where a uniform draw reached 92, at the same median. Deterministic in the log (fixed
    seed, ``_SUBSET_SEED``); sorted, so the subset's order is the log's.
    """
    n = levels.size
    if max_obs is None or n <= max_obs:
        return None
    rng = np.random.default_rng(_SUBSET_SEED)
    first = np.flatnonzero(levels == 0)
    if first.size >= max_obs:
        return np.sort(rng.choice(first, size=max_obs, replace=False)).astype(np.int64)
    rest = np.flatnonzero(levels != 0)
    chosen = rng.choice(rest, size=max_obs - first.size, replace=False)
    return np.sort(np.concatenate([first, chosen])).astype(np.int64)


def condition(
    X: FloatArray,
    levels: IntArray,
    y: FloatArray,
    n_levels: int,
    hyperparameters: Hyperparameters,
    *,
    priors: PriorSpec | None = None,
    max_memory: int | None = defaults.FIT_CONDITION_MEMORY,
) -> MFGP:
    """The GP with these hyperparameters conditioned on the data, within ``max_memory``.

    Exact on all observations when they fit the budget (the model is then exactly
    ``MFGP(X, levels, y, n_levels, hyperparameters)``); else exact on
    ``conditioning_subset``. ``model.conditioning`` says which, ``model.conditioned_rows``
    which rows (None: all).
    """
    X, levels, y = check_data(X, levels, y, n_levels)
    n = y.size
    ybar, ystd = level0_standardise(X, levels, y, n_levels)
    priors = with_pair_modes(priors, X, levels, (y - ybar) / ystd, n_levels)
    cap = max_conditioned(max_memory)
    rows = conditioning_subset(levels, n_levels, cap)
    if rows is None:
        model = MFGP(
            X, levels, y, n_levels, hyperparameters, priors=priors, standardisation=(ybar, ystd)
        )
    else:
        model = MFGP(
            X[rows], levels[rows], y[rows], n_levels, hyperparameters, priors=priors,
            standardisation=(ybar, ystd),
        )  # fmt: skip
        model.notes.append(
            f"the model conditions on {rows.size:,} of the {n:,} observations "
            f"({int(np.sum(levels[rows] == 0)):,} of them level 0, taken first): exact "
            f"conditioning on all would need {BYTES_PER_ENTRY * n * n / 2**30:.1f} GiB, over "
            f"the budget of {float(max_memory or 0) / 2**30:.1f} GiB; its sds are never below "
            "the exact posterior's"
        )
    model.conditioned_rows = rows
    model.conditioning = {
        "method": "exact" if rows is None else "exact_subset",
        "conditioned_on": int(n if rows is None else rows.size),
        "observations": int(n),
        "memory_budget_bytes": None if max_memory is None else int(max_memory),
    }
    return model


def fit_subset(
    levels: IntArray, n_levels: int, max_fit: int | None, rng: np.random.Generator
) -> IntArray | None:
    """Indices of the observations the hyperparameter search runs on; None for all.

    A uniform random subset of ``max_fit`` (subset of data), stratified by level: each
    level keeps its share of the observations, rounded by largest remainder, and at least
    ``min(n_l, 10)`` of its n_l. Drawn from ``rng`` only when a subset is needed, so small
    studies fit exactly as before. Sorted, so the subset's order is the log's.
    """
    n = levels.size
    if max_fit is None or n <= max_fit:
        return None
    counts = np.bincount(levels, minlength=n_levels)
    share = max_fit * counts / n
    take = np.floor(share).astype(np.int64)
    for lv in np.argsort(-(share - take), kind="stable")[: max_fit - int(take.sum())]:
        take[lv] += 1
    take = np.minimum(counts, np.maximum(take, np.minimum(counts, 10)))
    picked = [
        rng.choice(np.flatnonzero(levels == lv), size=int(take[lv]), replace=False)
        for lv in range(n_levels)
        if take[lv] > 0
    ]
    return np.sort(np.concatenate(picked)).astype(np.int64)


def fit_transformed(
    X: FloatArray,
    levels: IntArray,
    y: FloatArray,
    n_levels: int,
    *,
    centre: float,
    rng: np.random.Generator,
    restarts: int = 8,
    transform: OutputTransform | None = None,
    fixed: Hyperparameters | None = None,
    priors: PriorSpec | None = None,
    max_memory: int | None = defaults.FIT_CONDITION_MEMORY,
) -> tuple[MFGP, OutputTransform, list[dict[str, float]]]:
    """Fit the GP to g(y), choosing the output transform g by evidence (``transform``).

    Parameters
    ----------
    X, levels, y, n_levels, rng, restarts, fixed, priors, max_memory
        As ``fit_mfgp``; y in the metric's units.
    centre : float
        c of the asinh transform (the study's first gamma).
    transform : OutputTransform, optional
        Use this one; None chooses among ``candidate_transforms`` by the log posterior
        density of y (the MAP log posterior of g(y) plus the log Jacobian). Every
        candidate starts from the same seed, so the choice is reproducible.

    Returns
    -------
    model : MFGP
        Conditioned on g(y); its mu and sd are in g's units.
    transform : OutputTransform
    evidence : list of dict
        One row per candidate tried: ``scale`` (inf for the identity) and ``log_evidence``.
    """
    y = np.asarray(y, dtype=np.float64)
    candidates = (
        [transform] if transform is not None else candidate_transforms(y[np.isfinite(y)], centre)
    )
    seed = int(rng.integers(2**63))
    # One conditioned model alive at a time: each holds an n x n factor (1.2 GB at 12,000
    # observations), and keeping the best so far beside the next candidate doubled fit's
    # peak memory. The best is conditioned again at the end unless it was the last.
    best: tuple[float, OutputTransform, Hyperparameters, int, list[str]] | None = None
    evidence = []
    model: MFGP | None = None
    last_is_best = False
    for g in candidates:
        model = None  # frees the previous candidate's factor before this one's is built
        model = fit_mfgp(
            X, levels, g.forward(y), n_levels, rng=np.random.default_rng(seed),
            restarts=restarts, fixed=fixed, priors=priors, max_memory=max_memory,
        )  # fmt: skip
        score = model.log_posterior + g.log_jacobian(y)
        evidence.append({"scale": g.scale, "log_evidence": float(score)})
        last_is_best = best is None or score > best[0]
        if last_is_best:
            best = (score, g, model.hyperparameters, model.fitted_on, list(model.notes))
    assert best is not None and model is not None
    _, g, hp, fitted_on, notes = best
    if not last_is_best:
        model = None
        model = condition(
            X, levels, g.forward(y), n_levels, hp, priors=priors, max_memory=max_memory
        )
        model.fitted_on, model.notes = fitted_on, notes
    return model, g, evidence
