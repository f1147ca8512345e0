"""Tests of the baseline pick functions (bams_cli.core.baselines)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bams_cli.core.baselines import (
    STRATEGIES,
    difficulty_weights,
    level_split,
    pick_baseline,
    pick_cross_entropy,
    pick_difficulty,
    pick_uniform,
)

N = 400


def _inputs(seed):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(N, 3))
    f = np.linalg.norm(X - [1.5, 0.0, 0.0], axis=1)  # dangerous near (1.5, 0, 0)
    obs = rng.choice(N, size=12, replace=False)
    mask = np.zeros(N, dtype=bool)
    mask[obs] = True
    difficulty = -f + 0.1 * rng.normal(size=N)
    return X, f, obs, mask, difficulty


@settings(max_examples=60, deadline=None)
@given(
    strategy=st.sampled_from(STRATEGIES),
    costs=st.sampled_from([[1.0], [1.0, 5 / 32], [1.0, 0.1], [1.0, 0.3, 0.07]]),
    budget=st.sampled_from([0.5, 1.0, 2.7, 15.0, 40.0]),
    seed=st.integers(0, 2**32 - 1),
)
def test_budget_respected_and_no_duplicates(strategy, costs, budget, seed):
    X, f, obs, mask, difficulty = _inputs(seed % 7)
    idx, lev = pick_baseline(
        strategy,
        n_pool=N,
        costs=costs,
        budget=budget,
        rng=np.random.default_rng(seed),
        observed_level0_mask=mask,
        difficulty=difficulty,
        X=X,
        observed_index=obs,
        observed_value=f[obs],
    )
    assert idx.dtype == np.int64 and lev.dtype == np.int64 and len(idx) == len(lev)
    assert math.fsum(np.asarray(costs)[lev].tolist()) <= budget
    assert len(set(zip(idx.tolist(), lev.tolist(), strict=True))) == len(idx)  # no pair twice
    assert np.all((idx >= 0) & (idx < N))
    assert not np.any(mask[idx[lev == 0]])  # level 0 never re-simulated
    if strategy != "mcm-gp":
        assert np.all(lev == 0)
        assert len(idx) == int(budget // 1.0)  # every affordable level-0 pick is made


def test_level_split_spreads_budget_by_cost():
    assert level_split([1.0, 5 / 32], 15.0).tolist() == [7, 51]
    assert level_split([1.0, 0.25], 4.0, shares=[1, 0]).tolist() == [4, 0]
    counts = level_split([1.0, 0.3, 0.07], 10.0)
    used = math.fsum(c * k for c, k in zip([1.0, 0.3, 0.07], counts, strict=True))
    assert used <= 10.0 and 10.0 - used < 0.07


def test_level_split_gives_a_full_level_s_share_to_the_levels_that_can_still_run():
    # Every cheap run made (capacity 0 at level 1): the whole budget goes to level 0. The
    # split gave level 0 its half and nothing else, and at budget 1 nothing at all.
    assert level_split([1.0, 0.1], 4.0, capacity=[100, 0]).tolist() == [4, 0]
    assert level_split([1.0, 0.1], 1.0, capacity=[100, 0]).tolist() == [1, 0]
    # Level 0 has one segment left: the rest of its share buys cheap runs.
    assert level_split([1.0, 0.25], 4.0, capacity=[1, 100]).tolist() == [1, 12]
    # A cap that does not bind changes nothing.
    assert level_split([1.0, 5 / 32], 15.0, capacity=[7, 51]).tolist() == [7, 51]
    with pytest.raises(ValueError, match="capacity"):
        level_split([1.0, 0.1], 4.0, capacity=[-1, 3])


def test_level_split_gives_a_level_with_no_share_nothing():
    # --level0-share 1 asks for level 0 only: a full level 0 leaves the rest unspent rather
    # than spending it on the cheap level.
    assert level_split([1.0, 0.1], 5.0, shares=[1, 0], capacity=[2, 100]).tolist() == [2, 0]
    assert level_split([1.0, 0.25], 4.5, shares=[1, 0]).tolist() == [4, 0]


def test_mixed_uniform_spends_what_a_shared_cheap_pool_could_not_take():
    # Two cheap levels free on the same 20 segments: the split gave each 20 picks, the
    # second drew none (its unpaired segments were the first's), and a level-0 run went
    # unbought (cost 4 of budget 5).
    n, costs = 400, np.array([1.0, 0.1, 0.05])
    excluded = np.zeros((n, 3), dtype=bool)
    excluded[20:, 1:] = True
    idx, lev = pick_uniform(
        n, costs, 5.0, rng=np.random.default_rng(0), mixed=True, excluded_pairs=excluded
    )
    assert math.fsum(costs[lev]) <= 5.0 and 5.0 - math.fsum(costs[lev]) < costs.min()
    assert not excluded[idx, lev].any()
    for level in range(3):  # no segment twice at one level
        assert len(set(idx[lev == level])) == (lev == level).sum()
    # Where every level drew its count, nothing more: the split's own counts.
    _, lev = pick_uniform(n, [1.0, 0.1], 5.0, rng=np.random.default_rng(1), mixed=True)
    assert np.bincount(lev).tolist() == level_split([1.0, 0.1], 5.0).tolist() == [2, 30]


@settings(max_examples=200, deadline=None)
@given(
    costs=st.lists(st.floats(0.01, 1.0), min_size=1, max_size=3).map(lambda c: [1.0, *c[1:]]),
    budget=st.floats(0.0, 30.0),
    capacity=st.lists(st.integers(0, 20), min_size=3, max_size=3),
    shares=st.lists(st.floats(0.01, 1.0), min_size=3, max_size=3),
)
def test_level_split_respects_capacity_and_leaves_nothing_it_could_spend(
    costs, budget, capacity, shares
):
    cap, w = capacity[: len(costs)], shares[: len(costs)]
    counts = level_split(costs, budget, shares=w, capacity=cap)
    assert np.all(counts >= 0) and np.all(counts <= cap)
    used = math.fsum(c * k for c, k in zip(costs, counts, strict=True))
    assert used <= budget
    # No level with a free segment could take one more run within the budget.
    for c, k, m in zip(costs, counts, cap, strict=True):
        assert k == m or math.fsum([used, c]) > budget


def test_mixed_uniform_uses_all_levels_and_is_uniform():
    counts = np.zeros(N)
    for seed in range(200):
        idx, lev = pick_uniform(N, [1.0, 0.25], 5.0, rng=np.random.default_rng(seed), mixed=True)
        assert (lev == 0).sum() == 2 and (lev == 1).sum() == 12  # 2 + 2.5 + leftover 0.5
        counts[idx] += 1
    # 2800 picks over 400 segments: every segment's count is Binomial-ish around 7;
    # a fixed-index bias (e.g. always the first rows) would put ~0 on most.
    assert (counts == 0).mean() < 0.05


@pytest.mark.parametrize("paired", [True, False])
def test_mixed_uniform_pairs_level0_segments_with_cheap_runs(paired):
    idx, lev = pick_uniform(
        N, [1.0, 0.25], 5.0, rng=np.random.default_rng(1), mixed=True, paired=paired
    )
    zero, cheap = set(idx[lev == 0]), idx[lev == 1]
    assert len(cheap) == len(set(cheap)) == 12  # no (segment, level) twice
    assert len(zero & set(cheap)) == (2 if paired else 0)
    if paired:
        assert set(cheap[:2]) == zero  # the pairs come first


def test_pairs_are_capped_by_the_cheap_level_count():
    # 4 level-0 picks but only 2 cheap ones: both cheap picks pair, none is new.
    idx, lev = pick_uniform(
        N, [1.0, 1.0], 6.0, rng=np.random.default_rng(2), mixed=True, level_shares=[4, 2]
    )
    assert (lev == 0).sum() == 4 and (lev == 1).sum() == 2
    assert set(idx[lev == 1]) <= set(idx[lev == 0])


@pytest.mark.parametrize("seed", range(5))
def test_mixed_uniform_never_picks_an_excluded_pair(seed):
    # (segment, level) pairs observed, pending or abandoned are excluded per level: level 0
    # and level 1 each from their own free segments, the pairs only where both are free, and
    # the level's whole count while free segments last.
    rng = np.random.default_rng(100 + seed)
    excl = np.zeros((N, 2), bool)
    excl[:, 1] = rng.random(N) < 0.9  # 40-odd segments free at level 1
    excl[:, 0] = rng.random(N) < 0.3
    idx, lev = pick_uniform(
        N, [1.0, 0.25], 5.0, rng=np.random.default_rng(seed), mixed=True, excluded_pairs=excl
    )
    assert not excl[idx, lev].any()
    zero, cheap = idx[lev == 0], idx[lev == 1]
    assert zero.size == 2 and cheap.size == 12 and len(set(cheap)) == 12
    paired = [i for i in zero if not excl[i, 1]]
    assert set(paired) <= set(cheap)
    # Level 0 free on 0-19, level 1 on 10-69: a level-0 pick pairs exactly when it is one
    # of 10-19, and the pairs come first among the cheap picks.
    band = np.ones((N, 2), bool)
    band[:20, 0] = False
    band[10:70, 1] = False
    idx, lev = pick_uniform(
        N, [1.0, 0.25], 5.0, rng=np.random.default_rng(seed), mixed=True, excluded_pairs=band
    )
    zero, cheap = idx[lev == 0], idx[lev == 1]
    assert zero.size == 2 and set(zero) <= set(range(20))
    pairs = [i for i in zero if 10 <= i < 20]
    assert cheap[: len(pairs)].tolist() == pairs
    assert cheap.size == 12 and set(cheap) <= set(range(10, 70)) and len(set(cheap)) == 12
    # Only three segments free at level 1: all three, and the pairs among them.
    few = np.ones((N, 2), bool)
    few[:, 0] = False
    few[[5, 9, 11], 1] = False
    idx, lev = pick_uniform(
        N, [1.0, 0.25], 5.0, rng=np.random.default_rng(seed), mixed=True, excluded_pairs=few
    )
    assert sorted(idx[lev == 1].tolist()) == [5, 9, 11]
    with pytest.raises(ValueError, match="excluded_pairs must have shape"):
        pick_uniform(N, [1.0, 0.25], 5.0, rng=rng, mixed=True, excluded_pairs=excl[:, :1])


def test_difficulty_weights_transforms():
    d = np.array([0.0, 1.0, 3.0])
    w = difficulty_weights(d)
    np.testing.assert_allclose(w * w.sum() / w[0], [1.0, 1.0 + 1 / 0.003, 1 + 3 / 0.003])
    np.testing.assert_allclose(difficulty_weights(d, transform="rank"), [1 / 6, 2 / 6, 3 / 6])
    np.testing.assert_allclose(difficulty_weights(np.ones(4)), 0.25)
    with pytest.raises(ValueError, match="non-finite"):
        difficulty_weights(np.array([0.0, np.nan]))


@pytest.mark.parametrize("seed", range(10))
def test_ds_favours_high_difficulty(seed):
    # 50 hard segments (weight ~1) among 950 easy ones (weight ~1e-3): an easy pick has
    # probability < 950e-3 / 50 ~ 2% per draw, so 20 draws take >= 15 hard ones except with
    # probability < 1e-7, for any seed.
    difficulty = np.zeros(1000)
    hard = np.random.default_rng(seed).choice(1000, size=50, replace=False)
    difficulty[hard] = 1.0
    idx, lev = pick_difficulty(difficulty, [1.0], 20.0, rng=np.random.default_rng(seed))
    assert len(idx) == 20 and np.all(lev == 0)
    assert np.isin(idx, hard).sum() >= 15


@pytest.mark.parametrize("seed", range(5))
def test_ce_samples_near_the_elite(seed):
    X, f, obs, mask, _ = _inputs(seed)
    idx, lev = pick_cross_entropy(X, obs, f[obs], [1.0], 10.0, rng=np.random.default_rng(seed))
    assert len(idx) == 10 and np.all(lev == 0)
    assert np.all((idx >= 0) & (idx < N)) and not np.any(mask[idx])
    elite = obs[np.argsort(f[obs])[:5]]
    centre = X[elite].mean(axis=0)
    # CE picks sit closer to the elite mean than the pool does on average
    assert (
        np.linalg.norm(X[idx] - centre, axis=1).mean() < np.linalg.norm(X - centre, axis=1).mean()
    )


def test_ce_without_data_falls_back_to_uniform():
    X, *_ = _inputs(0)
    idx, lev = pick_cross_entropy(
        X, np.array([3]), np.array([0.1]), [1.0], 4.0, rng=np.random.default_rng(0)
    )
    assert len(idx) == 4 and 3 not in idx


def test_unknown_strategy_and_missing_inputs():
    with pytest.raises(ValueError, match="unknown strategy"):
        pick_baseline("bams", n_pool=N, costs=[1.0], budget=3, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="difficulty"):
        pick_baseline("ds", n_pool=N, costs=[1.0], budget=3, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="observed_value"):
        pick_baseline("ce", n_pool=N, costs=[1.0], budget=3, rng=np.random.default_rng(0))
