"""MAP training of the multifidelity GP: seeded L-BFGS-B restarts over the log parameters."""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import OptimizeResult, minimize
from threadpoolctl import threadpool_limits

from bams_cli import defaults
from bams_cli.core.gp._numerics import (
    FloatArray,
    GPFitError,
    IntArray,
    check_data,
    cholesky,
    standardise,
)
from bams_cli.core.gp.hyperparameters import Hyperparameters, _hyperparameters
from bams_cli.core.gp.model import MFGP
from bams_cli.core.gp.objective import _MAPObjective
from bams_cli.core.gp.priors import PriorSpec, _Priors
from bams_cli.core.gp.transform import OutputTransform, candidate_transforms

_SCREEN_ITER = 10  # L-BFGS-B iterations every restart gets
_N_POLISH = 2  # restarts continued to convergence
_MAXITER = 300  # cap on those; converged runs stop well before


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
) -> MFGP:
    """Fit the multifidelity GP by MAP and condition it on the data.

    With more than ``max_fit`` observations the hyperparameters come from a random subset
    of ``max_fit`` of them (``fit_subset``: stratified by level), and the returned model
    conditions on every observation with them; ``model.fitted_on`` says how many the
    search saw.

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
        return MFGP(X, levels, y, n_levels, fixed, priors=priors)
    if restarts < 1:
        raise GPFitError(f"restarts must be >= 1, got {restarts}")

    ybar, ystd = standardise(y)
    prior = _Priors.for_data(X, n_levels, priors)
    sub = fit_subset(levels, n_levels, max_fit, rng)
    Xf, lf, yf = (X, levels, y) if sub is None else (X[sub], levels[sub], y[sub])
    objective = _MAPObjective(Xf, lf, (yf - ybar) / ystd, n_levels, prior)
    bounds = list(zip(prior.lower, prior.upper, strict=True))
    starts = [prior.mode] + [prior.sample_start(rng) for _ in range(restarts - 1)]

    # Restarts in two stages: every start gets a short L-BFGS-B run, then the best
    # _N_POLISH of them continue to convergence. All `restarts` starts still compete for
    # the basin; the expensive tail of the optimisation is spent only on the leaders.
    # (Measured at n = 200, d = 12: full runs take ~140 evaluations each and nearly all
    # end in the same optimum, so this halves the fit time at no cost in objective.)
    # One BLAS thread: the matrices are a few hundred wide, where OpenBLAS threads only
    # add synchronisation (measured 30x slower Cholesky at n = 200 on a busy 2-core box).
    with threadpool_limits(limits=1, user_api="blas"):
        screened = [_minimize(objective, t, bounds, _SCREEN_ITER) for t in starts]
        finite = [r for r in screened if np.isfinite(r.fun)]
        finite.sort(key=lambda r: float(r.fun))
        polished = [_minimize(objective, r.x, bounds, _MAXITER) for r in finite[:_N_POLISH]]
    best_theta, best_f = None, math.inf
    for res in finite + polished:
        if np.isfinite(res.fun) and res.fun < best_f:
            best_theta, best_f = res.x, float(res.fun)
    if best_theta is None:
        raise GPFitError(
            f"MAP training failed from all {restarts} starts (non-finite objective); "
            "check X and y for extreme values or pass fixed hyperparameters"
        )

    K, _, _ = objective.covariance(best_theta)
    L, _ = cholesky(K)
    beta, _ = objective.gls_mean(L)
    hp = _hyperparameters(best_theta, beta, X.shape[1], n_levels, ybar, ystd)
    model = MFGP(X, levels, y, n_levels, hp, priors=priors)
    model.fitted_on = y.size if sub is None else sub.size
    if np.ptp(y) == 0.0:
        model.notes.append(
            f"all {y.size} observed values equal {y[0]:.6g}: the model is flat, and its "
            "failure probabilities rest on the priors alone"
        )
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
) -> tuple[MFGP, OutputTransform, list[dict[str, float]]]:
    """Fit the GP to g(y), choosing the output transform g by evidence (``transform``).

    Parameters
    ----------
    X, levels, y, n_levels, rng, restarts, fixed, priors
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
    best: tuple[float, MFGP, OutputTransform] | None = None
    evidence = []
    for g in candidates:
        model = fit_mfgp(
            X, levels, g.forward(y), n_levels, rng=np.random.default_rng(seed),
            restarts=restarts, fixed=fixed, priors=priors,
        )  # fmt: skip
        score = model.log_posterior + g.log_jacobian(y)
        evidence.append({"scale": g.scale, "log_evidence": float(score)})
        if best is None or score > best[0]:
            best = (score, model, g)
    assert best is not None
    return best[1], best[2], evidence
