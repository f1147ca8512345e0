"""The suite's problems: deterministic in their seed, and each has the properties it claims."""

from __future__ import annotations

import numpy as np
import pytest

from bams_cli.core import suite

SEEDS = [0, pytest.param(1, marks=pytest.mark.slow)]
FAST = {"weak_cheap": 4_000, "rare_regions": 4_000, "gap_sim": 4_000}


def _failures(pool):
    return pool.truth[:, 0] <= pool.gamma


@pytest.mark.parametrize("name", sorted(FAST))
def test_generators_are_pure_functions_of_n_and_seed(name):
    make = getattr(suite, name)
    a, b, c = make(FAST[name], 3), make(FAST[name], 3), make(FAST[name], 4)
    assert a.ids == b.ids
    np.testing.assert_array_equal(a.features, b.features)
    np.testing.assert_array_equal(a.truth, b.truth)
    assert not np.array_equal(a.truth, c.truth)
    assert a.gamma == c.gamma  # fixed per problem
    assert a.truth.shape == (FAST[name], 2) and a.costs[0] == 1.0 and 0.1 <= a.costs[1] <= 0.2


@pytest.mark.parametrize("name", sorted(FAST))
def test_gamma_and_rate_do_not_move_with_n(name):
    make = getattr(suite, name)
    small, large = make(FAST[name], 0), make(4 * FAST[name], 0)
    assert small.gamma == large.gamma


@pytest.mark.parametrize("seed", SEEDS)
def test_weak_cheap_level_is_weak_biased_and_blind_to_a_mode(seed):
    pool = suite.weak_cheap(seed=seed)
    f0, f1 = pool.truth.T
    fail = _failures(pool)
    assert 0.5 <= np.corrcoef(f0, f1)[0, 1] <= 0.8
    assert 0.01 <= fail.mean() <= 0.02
    assert np.mean(f1[fail] > pool.gamma) >= 0.3  # failures the cheap level does not see
    # The bias depends on x: its mean differs by far more than its noise between halves
    # of the latent's u4 axis, and a constant shift leaves most of its spread.
    d, U = f1 - f0, pool.latent
    assert d[U[:, 4] > 1].mean() - d[U[:, 4] < -1].mean() > 0.8
    assert np.std(d - d.mean()) > 2 * 0.3
    assert pool.latent.shape[1] in range(6, 9) and pool.features.shape[1] == 32


@pytest.fixture(scope="module")
def digits_pool():
    return suite.digits(seed=0)


def test_label_margin_is_true_minus_best_other():
    P = np.array([[0.7, 0.2, 0.1], [0.3, 0.5, 0.2], [0.4, 0.4, 0.2]])
    y = np.array([0, 0, 1])
    np.testing.assert_allclose(suite.label_margin(P, y), [0.5, -0.2, 0.0])


def test_digits_is_real_data_with_a_moderate_cheap_level(digits_pool):
    pool = digits_pool
    f0, f1 = pool.truth.T
    fail = _failures(pool)
    assert pool.features.shape == (1797, 64) and pool.gamma == 0.0
    assert 0.015 <= fail.mean() <= 0.03
    assert 0.6 <= np.corrcoef(f0, f1)[0, 1] <= 0.8
    assert np.mean(f1[fail] > 0) >= 0.25
    assert np.all(np.abs(pool.truth) <= 1.0)


def test_digits_subset_keeps_the_full_pools_margins(digits_pool):
    small = suite.digits(300, seed=0)
    pos = {s: i for i, s in enumerate(digits_pool.ids)}
    rows = [pos[s] for s in small.ids]
    np.testing.assert_array_equal(small.truth, digits_pool.truth[rows])
    with pytest.raises(ValueError, match="1797 images"):
        suite.digits(1798)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_digits_fails_exactly_where_the_out_of_fold_prediction_is_wrong(seed):
    from sklearn.datasets import load_digits
    from sklearn.model_selection import cross_val_predict

    pool = suite.digits(seed=seed)
    suite._digits_margins.cache_clear()
    assert np.array_equal(pool.truth, suite.digits(seed=seed).truth)  # deterministic
    X, y = load_digits(return_X_y=True)
    expensive, _, folds = suite.digits_models(seed)
    P = cross_val_predict(expensive, X, y, cv=folds, method="predict_proba")
    wrong = P.argmax(axis=1) != y
    f0 = pool.truth[:, 0]
    tie = f0 == 0  # argmax picks the lower class on a tie; the margin calls a tie a miss
    np.testing.assert_array_equal((f0 <= 0)[~tie], wrong[~tie])
    assert np.all((f0 <= 0)[tie])


@pytest.mark.parametrize("seed", SEEDS)
def test_rare_regions_are_rare_small_and_separated(seed):
    pool = suite.rare_regions(seed=seed)
    f0, f1 = pool.truth.T
    fail = _failures(pool)
    assert len(f0) == 20_000
    assert 0.001 <= fail.mean() <= 0.005
    assert pool.latent.shape[1] >= 20 and pool.features.shape[1] > pool.latent.shape[1]
    region, dist = suite.rare_region_of(pool.latent[fail])
    assert set(region) == set(range(suite.RARE_REGIONS)) and 4 <= suite.RARE_REGIONS <= 6
    C = suite.rare_region_centers()
    gaps = np.linalg.norm(C[:, None] - C[None], axis=-1)[np.triu_indices(len(C), 1)]
    # Every failure lies within 1.1 of its region's centre; centres are 3 or more apart.
    assert dist.max() < 1.1 and gaps.min() > 3.0
    assert 0.7 <= np.corrcoef(f0, f1)[0, 1] <= 0.85


@pytest.mark.parametrize("seed", SEEDS)
def test_gap_sim_has_a_wide_dynamic_range_and_a_stressed_bias(seed):
    pool = suite.gap_sim(seed=seed)
    f0, f1 = pool.truth.T
    fail = _failures(pool)
    assert len(f0) == 30_000 and pool.features.shape[1] == 16
    assert 0.005 <= fail.mean() <= 0.01
    assert f0[~fail].std() > 10 * pool.gamma
    # At failure it varies by fractions of a metre: collisions stop at contact (gap 0).
    assert f0.min() == 0.0 and np.ptp(f0[fail]) <= pool.gamma
    hard = pool.latent[:, 3] > suite.GAP_HARD_BRAKING
    bias = f1 - f0
    assert np.mean(np.abs(bias[hard])) > 3 * np.mean(np.abs(bias[~hard]))
    assert bias[hard].mean() > 0  # overestimates the gap under hard braking
    assert np.mean(f1[fail] <= pool.gamma) >= 0.6  # still sees most failures


def test_min_gap_matches_the_closed_form_when_both_cars_stop():
    """Lead stops, ego reacts then stops: the final gap is d0 + v_l^2/2b_l - v_e t_r - v_e^2/2b_e."""
    S = np.array([[20.0, 20.0, 60.0, 8.0, 1.0, 6.0], [25.0, 15.0, 40.0, 3.0, 0.5, 8.0]])
    v_e, v_l, d0, b_l, t_r, b_e = S.T
    final = d0 + v_l**2 / (2 * b_l) - v_e * t_r - v_e**2 / (2 * b_e)
    g = suite.min_gap(S, dt=0.01)
    assert np.all(g <= final + 1e-9)
    # The first scenario closes monotonically (ego always faster once the lead brakes).
    assert g[0] == pytest.approx(final[0], abs=1e-6)
