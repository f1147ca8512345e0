"""Confirmation picks: level-0 runs that turn cheap-level leads into findings.

A failure seen only at a cheap level is a lead, not a finding: the cheap simulator may be
wrong exactly there (DESIGN.md, "Confirmation"). BAMS's greedy values a level-0 run only
for how much it lowers the pool's misclassification variance J, and when the model trusts
the cheap level it may run no level 0 at all for several batches: leads pile up
unconfirmed and the model's view of level 0 rests on the first batch. A share of each
BAMS batch therefore goes to level-0 runs of

1. leads: segments whose cheap-level value is at or below gamma and whose level-0 value is
   unknown, most likely failures first (highest p_n);
2. if there are fewer leads than confirmation runs, the likeliest failures whose level-0
   value is unknown (highest p_n).

The greedy then spends the rest of the budget. The share's default was chosen on the
project's problem suite (README, "Defaults, and why").
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


def n_confirmations(budget: float, cost0: float, share: float) -> int:
    """How many level-0 confirmation runs a batch of ``budget`` reserves.

    floor(share x budget / c_0), and at least one when ``share > 0`` and the budget buys
    a level-0 run and something else besides (budget >= 2 c_0): a batch that can afford
    level 0 never spends everything at the cheap levels.
    """
    if share <= 0.0 or budget < cost0:
        return 0
    k = math.floor(share * budget / cost0 + 1e-9)
    if k == 0 and budget >= 2.0 * cost0:
        k = 1
    return int(min(k, math.floor(budget / cost0 + 1e-9)))


def confirmation_picks(
    p: FloatArray, lead: BoolArray, level0_known: BoolArray, k: int
) -> tuple[IntArray, BoolArray]:
    """The ``k`` segments to run at level 0: leads first, then the likeliest failures.

    Parameters
    ----------
    p : ndarray of shape (N,)
        Failure probability p_n of every segment.
    lead : bool ndarray of shape (N,)
        Seen failing at a cheap level.
    level0_known : bool ndarray of shape (N,)
        Level 0 observed or already selected; never picked.
    k : int

    Returns
    -------
    index : int ndarray of shape (<= k,)
        In pick order. Ties in p break by the lower pool index.
    is_lead : bool ndarray of the same shape
    """
    p = np.asarray(p, dtype=np.float64)
    free = ~np.asarray(level0_known, dtype=bool)
    lead = np.asarray(lead, dtype=bool) & free
    order = np.lexsort((np.arange(p.size), -p))  # p descending, then index ascending
    leads = order[lead[order]]
    others = order[(free & ~lead)[order]]
    index = np.concatenate([leads, others])[: max(int(k), 0)].astype(np.int64)
    return index, lead[index]
