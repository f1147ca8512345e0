"""Evaluation against ground truth (paper section 4, "Evaluation criteria"; DESIGN.md, "Evaluation").

Only meaningful where every segment's level-0 outcome is known (sample data, the paper's
synthetic protocol): retention-recall curves, the recall of an importance-sampling plan, the
mean metric of each batch's picks (paper Table 1), and a DPP pick of a few diverse likely
failures for display (paper Figure 3).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from bams_cli.core.estimate import SamplePlan

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
    rng: np.random.Generator | None = None,
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
    rng : numpy.random.Generator, optional
        Unused: the greedy MAP is deterministic. Accepted so that callers can pass their
        generator uniformly with the other evaluation helpers.
    lengthscale : float, optional
        RBF lengthscale l; default the median pairwise distance.

    Returns
    -------
    picked : int ndarray of shape (k,)
        Indices in pick order.
    """
    del rng
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
