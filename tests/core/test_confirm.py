"""Confirmation picks: leads first by p_n, then the likeliest unconfirmed failures."""

from __future__ import annotations

import numpy as np
import pytest

from bams_cli.core.confirm import confirmation_picks, n_confirmations


@pytest.mark.parametrize(
    ("budget", "cost0", "share", "expected"),
    [
        (5.0, 1.0, 0.2, 1),
        (5.0, 1.0, 0.4, 2),
        (10.0, 1.0, 0.2, 2),
        (5.0, 1.0, 0.0, 0),  # off
        (0.9, 1.0, 0.5, 0),  # cannot afford level 0
        (1.5, 1.0, 0.2, 0),  # one level-0 run would be the whole batch
        (3.0, 1.0, 0.1, 1),  # at least one when the batch affords level 0 and more
        (2.0, 1.0, 1.0, 2),  # never more than the budget buys
        (15.0, 1.0, 0.2, 3),  # floor(0.2 x 15) = 3 exactly, despite rounding
    ],
)
def test_number_of_confirmations(budget, cost0, share, expected):
    assert n_confirmations(budget, cost0, share) == expected


def test_leads_come_first_by_p_then_likeliest_unconfirmed():
    p = np.array([0.9, 0.1, 0.5, 0.8, 0.3, 0.5, 0.7])
    lead = np.array([False, True, True, False, True, False, False])
    known = np.array([False, False, False, True, True, False, False])
    idx, is_lead = confirmation_picks(p, lead, known, 5)
    # leads 2 (p .5) and 1 (p .1); lead 4 is known at level 0. Then 0 (.9), 6 (.7),
    # and 5 (.5) — segment 3 (.8) is known.
    assert idx.tolist() == [2, 1, 0, 6, 5]
    assert is_lead.tolist() == [True, True, False, False, False]


def test_ties_break_by_lower_index_and_k_caps():
    p = np.full(6, 0.4)
    idx, is_lead = confirmation_picks(p, np.zeros(6, bool), np.zeros(6, bool), 3)
    assert idx.tolist() == [0, 1, 2] and not is_lead.any()
    idx, _ = confirmation_picks(p, np.zeros(6, bool), np.ones(6, bool), 3)
    assert idx.size == 0
