"""Tests for bams_cli.core.evaluate: retention-recall, IS recall, DPP picks, batch means."""

from __future__ import annotations

import inspect
import math

import numpy as np
import pytest

from bams_cli.core.estimate import plan_sample
from bams_cli.core.evaluate import (
    batch_mean_f,
    dpp_diverse,
    expected_is_recall,
    is_recall,
    retention_recall,
)

# --------------------------------------------------------------------------------------------
# Retention-recall
# --------------------------------------------------------------------------------------------

SCORES = np.array([0.9, 0.1, 0.8, 0.8, 0.3, 0.0, 0.7, 0.2, 0.6, 0.5])
GRID = np.array([0.0, 0.25, 0.5, 1.0, 1.5, 2.0, 2.5])


def test_retention_recall_hand_example():
    # N = 10, failures {2, 5, 6, 9}: F = 4 = p N. Ranking (stable on the 0.8 tie):
    #   index  0  2  3  6  8  9  4  7  1  5
    #   fail   0  1  0  1  0  1  0  0  0  1
    # kept = floor(r * 4) = 0, 1, 2, 4, 6, 8, 10  ->  hits 0, 0, 1, 2, 3, 3, 4.
    fail = np.zeros(10, bool)
    fail[[2, 5, 6, 9]] = True
    got = retention_recall(SCORES, fail, GRID)
    np.testing.assert_array_equal(got, [0, 0, 0.25, 0.5, 0.75, 0.75, 1.0])


def test_retention_recall_ties_are_stable():
    # Same scores, failure at 3 instead of 2: index 2 (tied, lower index) ranks first, so at
    # 2 kept the failure at 3 is not yet in.
    fail = np.zeros(10, bool)
    fail[[3, 5, 6, 9]] = True
    got = retention_recall(SCORES, fail, [0.5, 0.75])
    np.testing.assert_array_equal(got, [0.0, 0.25])


def test_retention_recall_rate_override_and_errors():
    fail = np.zeros(10, bool)
    fail[[2, 5, 6, 9]] = True
    # With p = 0.2 given, r = 1 keeps 2 segments: ranks 0, 2 -> one failure of four.
    assert retention_recall(SCORES, fail, [1.0], rate=0.2)[0] == 0.25
    with pytest.raises(ValueError, match="no failures"):
        retention_recall(SCORES, np.zeros(10, bool), GRID)
    with pytest.raises(ValueError, match="finite"):
        retention_recall(np.r_[SCORES[:-1], np.nan], fail, GRID)


# --------------------------------------------------------------------------------------------
# IS recall
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("design", ["poisson", "fixed", "with-replacement"])
def test_is_recall_expected_matches_repeats(design):
    rng = np.random.default_rng(0)
    N = 400
    fail = np.zeros(N, bool)
    fail[rng.choice(N, 12, replace=False)] = True
    p = np.clip(0.6 * fail + 0.1 * rng.random(N), 1e-3, 1)
    known = np.zeros(N, bool)
    known[np.flatnonzero(fail)[:2]] = True  # two failures already known
    known[rng.choice(np.flatnonzero(~fail), 20, replace=False)] = True
    plans = [
        plan_sample(p, K=30, rng=rng, known=known, alpha=1.0, defensive=0.1, design=design)
        for _ in range(2000)
    ]
    got = np.array([is_recall(pl, fail)[0] for pl in plans])
    exp = expected_is_recall(plans[0], fail)[0]
    assert got.min() >= 2 / 12  # the known failures always count
    assert abs(got.mean() - exp) <= 4 * got.std() / math.sqrt(got.size)
    # Hand formula: (known failures + sum of inclusion probabilities of U's failures) / F.
    pl = plans[0]
    pi_fail = pl.pi[fail[pl.unknown]]
    if design == "with-replacement":
        np.testing.assert_allclose(pl.pi, 1 - (1 - pl.q) ** 30, rtol=1e-12)
    assert math.isclose(exp, (2 + pi_fail.sum()) / 12, rel_tol=1e-12)


def test_is_recall_with_replacement_perfect_sampler_ceiling():
    # DESIGN.md: even q uniform over exactly the F failures finds 1 - (1 - 1/F)^K of them.
    N, F = 1000, 50
    fail = np.zeros(N, bool)
    fail[:F] = True
    p = fail.astype(float)
    plan = plan_sample(
        p, K=2 * F, rng=np.random.default_rng(1), alpha=1.0, defensive=0.0,
        design="with-replacement",
    )  # fmt: skip
    assert math.isclose(expected_is_recall(plan, fail)[0], 1 - (1 - 1 / F) ** (2 * F))
    assert abs(expected_is_recall(plan, fail)[0] - 0.867) < 1e-3


# --------------------------------------------------------------------------------------------
# DPP
# --------------------------------------------------------------------------------------------


def clustered_points(seed: int = 0):
    """5 well-separated clusters; each holds one point and 3 exact copies of it, plus jitter."""
    rng = np.random.default_rng(seed)
    centres = np.array([[0, 0], [10, 0], [0, 10], [10, 10], [5, 5]], float)
    X = (
        np.repeat(centres, 4, axis=0)
        + rng.normal(0, 0.01, (20, 2)) * (np.arange(20) % 4 == 3)[:, None]
    )
    return X


def test_dpp_returns_k_distinct_diverse_indices():
    X = clustered_points()
    q = np.full(20, 0.5)
    picked = dpp_diverse(X, q, 5, lengthscale=2.0)
    assert picked.size == 5 and np.unique(picked).size == 5
    # One per cluster: duplicates never picked together.
    assert np.unique(picked // 4).size == 5


def test_dpp_prefers_quality_but_not_duplicates():
    X = clustered_points()
    q = np.full(20, 0.2)
    q[0:4] = 0.9  # cluster 0: all four copies high quality
    q[17] = 0.6  # one point of cluster 4 moderately good
    picked = dpp_diverse(X, q, 3, lengthscale=2.0)
    assert picked[0] == 0  # highest quality, lowest index among ties
    assert picked[1] == 17  # next-best quality elsewhere beats a copy of the first
    assert not np.any(np.isin(picked[1:], [1, 2, 3]))
    # Deterministic: it takes no random generator at all.
    np.testing.assert_array_equal(picked, dpp_diverse(X, q, 3, lengthscale=2.0))
    assert "rng" not in inspect.signature(dpp_diverse).parameters


def test_dpp_more_picks_than_distinct_points():
    X = np.repeat(np.array([[0.0, 0.0], [5.0, 5.0]]), 3, axis=0)
    picked = dpp_diverse(X, np.ones(6), 4)
    assert np.unique(picked).size == 4
    assert set(picked[:2] // 3) == {0, 1}  # the two distinct points first


def test_dpp_matches_brute_force_greedy():
    # Greedy log-det on the explicit L: same picks as the Cholesky-update version.
    rng = np.random.default_rng(2)
    X = rng.normal(size=(30, 3))
    q = rng.random(30)
    ell = 1.3
    d2 = ((X[:, None] - X[None]) ** 2).sum(-1)
    L = q[:, None] * q[None] * np.exp(-d2 / (2 * ell**2))
    chosen: list[int] = []
    for _ in range(6):
        best, best_val = -1, -np.inf
        for i in range(30):
            if i in chosen:
                continue
            idx = [*chosen, i]
            val = np.linalg.slogdet(L[np.ix_(idx, idx)])[1]
            if val > best_val + 1e-12:
                best, best_val = i, val
        chosen.append(best)
    np.testing.assert_array_equal(dpp_diverse(X, q, 6, lengthscale=ell), chosen)


# --------------------------------------------------------------------------------------------
# Batch mean f
# --------------------------------------------------------------------------------------------


def test_batch_mean_f_hand_example():
    mean, se = batch_mean_f([[1.0, 2.0, 3.0, 6.0], [4.0, 4.0], [7.0]])
    # Batch 1: mean 3, sd = sqrt(((-2)^2 + 1 + 0 + 9) / 3) = sqrt(14/3), SE = sd / 2.
    np.testing.assert_allclose(mean, [3.0, 4.0, 7.0])
    np.testing.assert_allclose(se[:2], [math.sqrt(14 / 3) / 2, 0.0])
    assert math.isnan(se[2])


def test_batch_mean_f_of_a_batch_without_values_is_nan_and_the_rest_keep_theirs():
    # A batch whose picks were all cheap-level, or whose results are pending, has no
    # level-0 value: no mean, and no error for the study's report.
    mean, se = batch_mean_f([[1.0, 3.0], [], [5.0]])
    assert mean[0] == 2.0 and math.isnan(mean[1]) and mean[2] == 5.0
    assert se[0] == 1.0 and math.isnan(se[1]) and math.isnan(se[2])
