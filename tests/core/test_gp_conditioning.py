"""Conditioning within a memory budget: exact below it, an exact subset above it."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.decomposition import PCA

from bams_cli import defaults
from bams_cli.core.gp import MFGP, fit_mfgp
from bams_cli.core.gp.fit import (
    BYTES_PER_ENTRY,
    condition,
    conditioning_subset,
    max_conditioned,
)
from bams_cli.core.synthetic import av_like


@pytest.fixture(scope="module")
def av_fit():
    """1,500 av_like observations (60% level 1) on a 4,000-segment pool, PCA to d = 12."""
    pool = av_like(4000, seed=0)
    X = PCA(12, random_state=0).fit_transform(pool.features)
    rng = np.random.default_rng(1)
    obs = rng.choice(4000, 1500, replace=False)
    lv = (rng.random(1500) < 0.6).astype(np.int64)
    y = pool.truth[obs, lv]
    exact = fit_mfgp(X[obs], lv, y, 2, rng=np.random.default_rng(0), restarts=2)
    return X, X[obs], lv, y, exact


def test_max_conditioned_is_the_square_root_of_the_budget():
    assert max_conditioned(None) is None
    assert max_conditioned(BYTES_PER_ENTRY * 1000 * 1000) == 1000
    assert max_conditioned(BYTES_PER_ENTRY * 1000 * 1000 - 1) == 999
    assert max_conditioned(0) == 1
    assert max_conditioned(defaults.FIT_CONDITION_MEMORY) == 10_362


def test_conditioning_subset_takes_level0_first_and_is_deterministic():
    levels = np.array([1, 0, 1, 1, 0, 2, 2, 1, 0, 1] * 10)
    assert conditioning_subset(levels, 3, None) is None
    assert conditioning_subset(levels, 3, 100) is None
    rows = conditioning_subset(levels, 3, 50)
    assert rows is not None and rows.size == 50 and np.all(np.diff(rows) > 0)
    assert set(np.flatnonzero(levels == 0)) <= set(rows.tolist())  # all 30 level-0 kept
    np.testing.assert_array_equal(rows, conditioning_subset(levels, 3, 50))
    few = conditioning_subset(levels, 3, 20)
    assert few is not None and few.size == 20 and np.all(levels[few] == 0)


def test_below_the_budget_conditioning_is_the_exact_posterior_bit_for_bit(av_fit):
    X, Xo, lv, y, exact = av_fit
    assert exact.conditioning["method"] == "exact" and exact.conditioned_rows is None
    plain = MFGP(Xo, lv, y, 2, exact.hyperparameters)
    for a, b in zip(exact.predict_theta0(X), plain.predict_theta0(X), strict=True):
        np.testing.assert_array_equal(a, b)


def test_above_the_budget_the_subset_posterior_is_cautious_and_measured(av_fit):
    """Forced subset (1,000 of 1,500): sd never below exact; errors as measured.

    Conditioning on fewer observations cannot lower a Gaussian's variance, so the subset's
    sd is >= the exact sd at every point (up to rounding). The subset is *not* within 1%
    of the exact posterior on av_like (its fitted noise is tiny and its lengthscales long,
    so every observation matters): measured over the 4,000 pool points, the median mean
    error is 0.31 exact sds and the median sd excess 8% (bench_fit.py --accuracy gives the
    same numbers at larger sizes). The bounds below are those numbers with a margin, so a
    worse subset or a wrong conditioning breaks them.
    """
    X, Xo, lv, y, exact = av_fit
    budget = BYTES_PER_ENTRY * 1000 * 1000
    sub = condition(Xo, lv, y, 2, exact.hyperparameters, max_memory=budget)
    assert sub.conditioning == {
        "method": "exact_subset",
        "conditioned_on": 1000,
        "observations": 1500,
        "memory_budget_bytes": budget,
    }
    assert sub.conditioned_rows is not None and sub.conditioned_rows.size == 1000
    assert np.sum(sub.levels_train == 0) == np.sum(lv == 0)  # every level-0 result kept
    assert any("conditions on 1,000 of the 1,500" in note for note in sub.notes)
    mu_e, s2_e = exact.predict_theta0(X)
    mu, s2 = sub.predict_theta0(X)
    sd_e, sd = np.sqrt(s2_e), np.sqrt(s2)
    assert np.all(sd >= sd_e - 1e-9)
    mean_err = np.abs(mu - mu_e) / sd_e
    sd_err = (sd - sd_e) / sd_e
    assert np.median(mean_err) < 0.5 and np.median(sd_err) < 0.15
    # ... and a real subset, not the exact posterior under another name.
    assert np.median(sd_err) > 0.01


def test_fixed_hyperparameters_condition_like_the_fit(av_fit):
    """select rebuilds the posterior with fixed hyperparameters: same subset, same numbers."""
    X, Xo, lv, y, exact = av_fit
    budget = BYTES_PER_ENTRY * 900 * 900
    a = condition(Xo, lv, y, 2, exact.hyperparameters, max_memory=budget)
    b = fit_mfgp(
        Xo, lv, y, 2, rng=np.random.default_rng(5), fixed=exact.hyperparameters, max_memory=budget
    )
    np.testing.assert_array_equal(a.conditioned_rows, b.conditioned_rows)
    np.testing.assert_array_equal(a.predict_theta0(X[:200])[1], b.predict_theta0(X[:200])[1])
