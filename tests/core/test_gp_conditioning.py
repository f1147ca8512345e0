"""Conditioning within a memory budget: exact below it, an exact subset above it."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from sklearn.decomposition import PCA

from bams_cli import defaults
from bams_cli.core.gp import MFGP, fit_mfgp
from bams_cli.core.gp._numerics import JITTERS, GPFitError, cholesky, cholesky_inplace
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
    assert max_conditioned(defaults.FIT_CONDITION_MEMORY) == 14_654


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


def test_exact_conditioning_holds_one_covariance_at_its_peak(av_fit):
    """The budget's bytes per entry are real: K is built and factorised in place.

    tracemalloc sees every numpy and scipy allocation; building K, then copying it for the
    factor (or holding the kernel's temporaries) would need 16 to 24 bytes per entry.
    """
    _, Xo, lv, y, exact = av_fit
    n = y.size
    MFGP(Xo[:50], lv[:50], y[:50], 2, exact.hyperparameters)  # compiled, imported
    tracemalloc.start()
    model = MFGP(Xo, lv, y, 2, exact.hyperparameters)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert 8 * n * n <= peak < 1.25 * 8 * n * n <= BYTES_PER_ENTRY * n * n
    assert model._L.flags.f_contiguous and model._L.shape == (n, n)


@pytest.mark.parametrize("noise", [0.0, 0.3])
def test_inplace_cholesky_is_the_copying_one(noise):
    """Same factor and jitter as ``cholesky`` (a copy, never overwritten); with zero noise
    the repeated rows need the jitter ladder, whose rungs rebuild K first."""
    rng = np.random.default_rng(4)
    A = np.repeat(rng.normal(size=(6, 2)), 2, axis=0)
    K0 = np.exp(-0.5 * ((A[:, None, :] - A[None, :, :]) ** 2).sum(-1)) + noise * np.eye(12)
    want, jitter = cholesky(K0)
    K = np.asfortranarray(K0)
    rebuilds = []

    def rebuild():
        rebuilds.append(1)
        K[...] = K0

    L, got_jitter = cholesky_inplace(K, rebuild)
    assert L is K and got_jitter == jitter and (jitter > 0) == (noise == 0.0)
    scale = float(np.mean(np.diag(K0)))
    assert len(rebuilds) == JITTERS.index(jitter / scale)  # one rebuild per failed rung
    np.testing.assert_allclose(np.tril(L), np.tril(want), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.tril(L) @ np.tril(L).T, K0 + jitter * np.eye(12), atol=1e-9)


def test_inplace_cholesky_rejects_what_cholesky_rejects():
    with pytest.raises(GPFitError, match="non-finite"):
        cholesky_inplace(np.asfortranarray([[1.0, 0.0], [np.inf, 1.0]]), lambda: None)
    bad = np.array([[1.0, 2.0], [2.0, 1.0]])
    K = np.asfortranarray(bad)
    with pytest.raises(GPFitError, match="jitter.*noise variance"):
        cholesky_inplace(K, lambda: K.__setitem__(Ellipsis, bad))
