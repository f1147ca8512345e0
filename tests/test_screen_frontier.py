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
