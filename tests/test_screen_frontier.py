"""docs/suite/screen_frontier.py: the screen's cost, recall and variance against brute force."""

from __future__ import annotations

import importlib.util
import itertools
from pathlib import Path

import numpy as np
import pytest

_PATH = Path(__file__).resolve().parents[1] / "docs" / "suite" / "screen_frontier.py"
_spec = importlib.util.spec_from_file_location("screen_frontier", _PATH)
assert _spec and _spec.loader
sf = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(sf)


def _enumerate(f0, f1, gamma, c1, K, share, t):
    """E[T], Var[T] and the expected cost of the two-phase design by enumerating every
    segment's three outcomes (not screened; screened, not confirmed; confirmed)."""
    n = f0.size
    pi1 = share * K / (c1 * n)
    lead = f1 <= t
    rest = K - n * pi1 * c1 - pi1 * lead.sum()
    pi2 = np.where(lead, 1.0, rest / (pi1 * (~lead).sum()))
    y = (f0 <= gamma).astype(float)
    mean = second = cost = 0.0
    for states in itertools.product(range(3), repeat=n):
        s = np.array(states)
        prob = np.prod(np.where(s == 0, 1 - pi1, np.where(s == 1, pi1 * (1 - pi2), pi1 * pi2)))
        T = float(np.sum(y * (s == 2) / (pi1 * pi2)))
        mean += prob * T
        second += prob * T * T
        cost += prob * (c1 * np.sum(s >= 1) + np.sum(s == 2))
    return mean, second - mean * mean, cost, pi1 * pi2


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_screens_variance_and_cost_are_what_brute_force_says(seed):
    rng = np.random.default_rng(seed)
    f0 = rng.standard_normal(7)
    f1 = f0 + 0.5 * rng.standard_normal(7)
    gamma, c1, K, share = float(np.sort(f0)[2]), 0.2, 3.0, 0.3
    t = float(np.sort(f1)[1])
    recall, var, pi2 = sf.design(f0, f1, gamma, c1, K, share, t)
    mean, exact_var, cost, pi = _enumerate(f0, f1, gamma, c1, K, share, t)
    fail = f0 <= gamma
    F = fail.sum()
    assert mean == pytest.approx(F)  # unbiased
    assert cost == pytest.approx(K)  # spends K exactly, in expectation
    assert var * F * (f0.size / K - 1) == pytest.approx(exact_var)
    assert recall * K / f0.size == pytest.approx(pi[fail].mean())


def test_recall_never_exceeds_the_screens_share_over_its_cost():
    rng = np.random.default_rng(3)
    f0 = rng.standard_normal(2_000)
    f1 = f0 + 0.3 * rng.standard_normal(2_000)
    for share in (0.2, 0.5, 0.8):
        for q in (0.005, 0.05):
            r = sf.design(f0, f1, -2.0, 0.1, 60.0, share, float(np.quantile(f1, q)))
            if r is not None:
                assert r[0] <= share / 0.1 + 1e-9


def test_leads_that_cost_more_than_K_make_no_design():
    f0 = np.linspace(-1, 1, 100)
    assert sf.design(f0, f0, 0.0, 0.1, 5.0, 0.5, 10.0) is None


def test_a_screen_on_an_unrelated_cheap_level_costs_what_the_closed_form_says():
    """With f1 independent of f0 the leads are a random L of S1's A segments, so a failure
    is confirmed at pi1 with chance L/A and at pi1 pi2 otherwise, pi2 = (K2 - L)/(A - L):
    Var / uniform ~ (K/A) (1 + (A - L)(A - K2) / (A (K2 - L))), about 2.2 at the shipped
    share 0.3 and lead share 0.5 with cheap runs at 0.1 (docs/suite/unrelated_cheap.md).
    The design with leads taken at random must cost that, and more than without leads."""
    rng = np.random.default_rng(3)
    n, c1, s, h = 400_000, 0.1, 0.3, 0.5
    f0 = rng.standard_normal(n)
    gamma = float(np.quantile(f0, 0.01))
    f1 = rng.permutation(f0)
    K = 2.0 * float(np.sum(f0 <= gamma))
    A, K2 = s * K / c1, (1 - s) * K
    L = h * K2
    r = sf._at_quantile(f0, f1, gamma, c1, K, s, h * (1 - s) * c1 / s)  # L leads in S1
    closed = (K / A) * (1 + (A - L) * (A - K2) / (A * (K2 - L)))
    assert closed == pytest.approx(2.2, abs=0.1)
    assert r["var"] == pytest.approx(closed, rel=0.05)
    no_leads = sf.design(f0, f1, gamma, c1, K, s, -np.inf)
    assert no_leads[1] == pytest.approx(K / K2, rel=0.05)  # 1 / (1 - s): the cheap runs' cost
    assert r["var"] > 1.4 * no_leads[1]


def test_the_unrelated_cheap_levels_are_what_they_say():
    path = Path(__file__).resolve().parents[1] / "docs" / "suite" / "unrelated_cheap.py"
    spec = importlib.util.spec_from_file_location("unrelated_cheap", path)
    assert spec and spec.loader
    uc = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(uc)
    f0 = np.random.default_rng(0).gamma(2.0, 3.0, 50_000)
    perm = uc.cheap_variant(f0, "perm", np.random.default_rng(1))
    assert np.array_equal(np.sort(perm), np.sort(f0))
    assert abs(np.corrcoef(f0, perm)[0, 1]) < 0.02
    c30 = uc.cheap_variant(f0, "c30", np.random.default_rng(1))
    assert np.corrcoef(f0, c30)[0, 1] == pytest.approx(0.3, abs=0.02)
    assert c30.std() == pytest.approx(f0.std(), rel=0.02)
    with pytest.raises(ValueError, match="unknown variant"):
        uc.cheap_variant(f0, "c50", np.random.default_rng(1))
