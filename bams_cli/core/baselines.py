"""Pick functions of the baseline strategies the paper compares BAMS with (section 4).

Each returns the batch as two int arrays (pool index, level), in pick order, whose total
cost fsum(costs[level]) never exceeds the budget m, with no (index, level) pair twice and no
segment twice. They pick; what happens downstream (GP or not, which estimator) is the
caller's business:

========  =====================================================  ========================
strategy  picks                                                  downstream
========  =====================================================  ========================
mc        uniform over segments, level 0                         plain Monte Carlo
random    as mc (``select --strategy random``; mixed on request)  plain Monte Carlo
mc-gp     uniform over segments, level 0                         GP scores the pool
mcm-gp    uniform over segments, levels split by cost            GP scores the pool
ds        without replacement, P ~ difficulty weight, level 0    IS by difficulty
ds-gp     as ds                                                  GP scores the pool
ce        cross-entropy: diagonal Gaussian fitted to the elite,  CE importance scores
          samples mapped to the nearest unobserved segment
========  =====================================================  ========================

(BAS is BAMS restricted to level 0: ``select.select_batch(..., levels=[0])``.)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Literal

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

Strategy = Literal["mc", "random", "mc-gp", "mcm-gp", "ds", "ds-gp", "ce"]
STRATEGIES: tuple[str, ...] = ("mc", "random", "mc-gp", "mcm-gp", "ds", "ds-gp", "ce")

#: The cross-entropy method's elite size and variance floor (share of the pool's variance
#: per dimension); the benchmark's CE rate scores read them here too.
CE_N_ELITE = 5
CE_VAR_FLOOR = 1e-6


def _n_affordable(cost: float, budget: float) -> int:
    """Largest k with fsum([cost] * k) <= budget."""
    k = int(budget // cost)
    while k > 0 and math.fsum([cost] * k) > budget:
        k -= 1
    while math.fsum([cost] * (k + 1)) <= budget:
        k += 1
    return k


def _available(n_pool: int, observed_level0_mask: BoolArray | None) -> BoolArray:
    if observed_level0_mask is None:
        return np.ones(n_pool, dtype=bool)
    mask = np.asarray(observed_level0_mask, dtype=bool)
    if mask.shape != (n_pool,):
        raise ValueError(f"observed_level0_mask must have shape ({n_pool},); got {mask.shape}")
    return ~mask


def level_split(
    costs: Sequence[float],
    budget: float,
    shares: Sequence[float] | None = None,
    capacity: Sequence[int] | None = None,
) -> IntArray:
    """How many picks each level gets in a mixed-fidelity random batch.

    Each level l receives the budget share shares[l] (default: equal shares, 1 / (L + 1)),
    and buys floor(share_l m / c_l) picks, so cheap levels get proportionally more picks.
    The rounding leftover is then spent greedily, one pick at a time, on the most expensive
    level that still fits (level 0 first), so at most min_l c_l of the budget is left.

    With ``capacity``, level l gets at most capacity[l] picks: a level whose segments have
    all been run (a small pool's cheap level, after a few batches) cannot spend its share,
    and what it leaves goes, by the same greedy rule, to the levels that can still be run.
    Without it a batch of budget 1 on a pool whose cheap runs were all made was refused as
    "nothing fits", and a larger one spent only level 0's share. A level whose share is 0
    gets nothing, leftover included.

    Parameters
    ----------
    costs : sequence of float, length L + 1
    budget : float
    shares : sequence of float, length L + 1, optional
        Non-negative; normalised to sum 1.
    capacity : sequence of int, length L + 1, optional
        The most picks each level can take (segments still free at it).

    Returns
    -------
    counts : int ndarray of shape (L + 1,)

    Examples
    --------
    >>> level_split([1.0, 5 / 32], 15.0).tolist()   # 7 at level 0, 51 at level 1
    [7, 51]
    """
    c_arr = np.asarray(costs, dtype=np.float64)
    L1 = len(c_arr)
    w = np.full(L1, 1.0 / L1) if shares is None else np.asarray(shares, dtype=np.float64)
    if w.shape != (L1,) or np.any(w < 0) or w.sum() <= 0:
        raise ValueError(f"shares must be {L1} non-negative numbers, not all 0; got {shares}")
    w = w / w.sum()
    cap = (
        np.full(L1, np.iinfo(np.int64).max)
        if capacity is None
        else np.asarray(capacity, dtype=np.int64)
    )
    if cap.shape != (L1,) or np.any(cap < 0):
        raise ValueError(f"capacity must be {L1} non-negative counts; got {capacity}")
    counts = np.array(
        [
            min(_n_affordable(c, share * budget), int(k))
            for c, share, k in zip(c_arr, w, cap, strict=True)
        ]
    )
    used = [float(c) for c, k in zip(c_arr, counts, strict=True) for _ in range(k)]
    for lev in np.argsort(-c_arr, kind="stable"):
        if w[lev] == 0:  # a level given no share is not run (--level0-share 1: level 0 only)
            continue
        while counts[lev] < cap[lev] and math.fsum([*used, float(c_arr[lev])]) <= budget:
            used.append(float(c_arr[lev]))
            counts[lev] += 1
    return counts


def pick_uniform(
    n_pool: int,
    costs: Sequence[float],
    budget: float,
    *,
    rng: np.random.Generator,
    mixed: bool = False,
    observed_level0_mask: BoolArray | None = None,
    level_shares: Sequence[float] | None = None,
    paired: bool = True,
    excluded_pairs: BoolArray | None = None,
) -> tuple[IntArray, IntArray]:
    """Uniform picks over unobserved segments: MC / MC-GP (level 0) and MCM-GP (mixed).

    Single fidelity: floor(m / c_0) distinct segments with level 0 unobserved, uniformly
    without replacement. Mixed (``mixed=True``): ``level_split`` decides how many picks
    each level gets, drawn uniformly without replacement (level-0 picks only among
    segments whose level 0 is unobserved). With ``paired`` (the default) each cheap level's
    first picks are the level-0 segments themselves, as many as that level's count allows,
    and the rest are other segments; without it every pick is a distinct segment.

    Why pairs: the values of one segment at level 0 and at a cheap level identify the
    cheap level's discrepancy directly (their difference is alpha_l + noise, with theta0
    cancelled). Without pairs the model can only tell the discrepancy from theta0 through
    the kernels' smoothness, and with a handful of level-0 runs it often calls a weak
    cheap level nearly exact (DESIGN.md, "Paired evidence").

    Parameters
    ----------
    n_pool : int
    costs : sequence of float, length L + 1
    budget : float
    rng : numpy.random.Generator
    mixed : bool
    observed_level0_mask : bool ndarray of shape (n_pool,), optional
    level_shares : sequence of float, optional
        Budget shares per level for ``mixed``; default equal.
    paired : bool
    excluded_pairs : bool ndarray of shape (n_pool, L + 1), optional
        (segment, level) pairs that must not be picked: observed, awaiting results or
        abandoned at that level. A cheap level's picks, its pairs with the level-0 picks
        included, come only from segments free at that level, so a batch spends its budget
        on runs that can be made rather than on picks ``select`` would have to drop.

    Returns
    -------
    index : int ndarray of shape (r,)
    level : int ndarray of shape (r,)
    """
    free0 = _available(n_pool, observed_level0_mask)
    c_arr = np.asarray(costs, dtype=np.float64)
    if excluded_pairs is not None:
        excluded_pairs = np.asarray(excluded_pairs, dtype=bool)
        if excluded_pairs.shape != (n_pool, len(c_arr)):
            raise ValueError(
                f"excluded_pairs must have shape {(n_pool, len(c_arr))}; got {excluded_pairs.shape}"
            )
        free0 = free0 & ~excluded_pairs[:, 0]
    # What each level can still take: the segments free at it (with two or more cheap
    # levels an upper bound, as they draw their unpaired picks from one pool).
    capacity = [int(free0.sum())] + [
        n_pool if excluded_pairs is None else int((~excluded_pairs[:, lev]).sum())
        for lev in range(1, len(c_arr))
    ]
    counts = (
        level_split(costs, budget, level_shares, capacity)
        if mixed
        else np.array([_n_affordable(c_arr[0], budget)] + [0] * (len(c_arr) - 1))
    )
    # Level 0 first (it has the narrower pool), then the other levels from what is left.
    taken = np.zeros(n_pool, dtype=bool)
    idx_out: list[IntArray] = []
    lev_out: list[IntArray] = []
    level0 = np.zeros(0, dtype=np.int64)
    for lev, k in enumerate(counts):
        k = int(k)
        if lev == 0:
            free = free0
        elif excluded_pairs is None:
            free = np.ones(n_pool, dtype=bool)
        else:
            free = ~excluded_pairs[:, lev]
        pair = level0[free[level0]][: k if paired and lev > 0 else 0]
        pool = np.flatnonzero(free & ~taken)
        k_new = min(k - len(pair), len(pool))
        new = rng.choice(pool, size=k_new, replace=False) if k_new else np.zeros(0, np.int64)
        taken[new] = True
        pick = np.concatenate([pair, new]).astype(np.int64)
        if lev == 0:
            level0 = pick
        idx_out.append(pick)
        lev_out.append(np.full(len(pick), lev, dtype=np.int64))
    if mixed:
        # Capacity is an upper bound where cheap levels share their unpaired segments: a
        # level may have drawn fewer than it was given. What it left buys runs of the
        # levels with segments still free, most expensive first, as level_split would.
        _top_up(idx_out, lev_out, c_arr, budget, level_shares, free0, excluded_pairs, rng)
    return np.concatenate(idx_out), np.concatenate(lev_out)


def _top_up(
    idx_out: list[IntArray],
    lev_out: list[IntArray],
    c_arr: FloatArray,
    budget: float,
    level_shares: Sequence[float] | None,
    free0: BoolArray,
    excluded_pairs: BoolArray | None,
    rng: np.random.Generator,
) -> None:
    """Spend on free segments what ``pick_uniform``'s levels could not draw (in place).

    A level's new picks may be any segment free at that level and not yet picked at it.
    Draws nothing (and takes nothing from ``rng``) when no level has a free segment the
    leftover buys, the common case, so batches drawn before it existed are drawn again
    unchanged.
    """
    used = [float(c_arr[lev]) for lev_arr in lev_out for lev in lev_arr]
    shares = np.ones(len(c_arr)) if level_shares is None else np.asarray(level_shares, float)
    for lev in np.argsort(-c_arr, kind="stable"):
        if shares[lev] == 0 or math.fsum([*used, float(c_arr[lev])]) > budget:
            continue
        if lev == 0:
            free = free0.copy()
        elif excluded_pairs is None:
            free = np.ones(free0.size, dtype=bool)
        else:
            free = ~excluded_pairs[:, lev]
        for idx, lv in zip(idx_out, lev_out, strict=True):
            free[idx[lv == lev]] = False
        pool = np.flatnonzero(free)
        k = 0
        while k < len(pool) and math.fsum([*used, float(c_arr[lev])]) <= budget:
            used.append(float(c_arr[lev]))
            k += 1
        if k:
            idx_out.append(rng.choice(pool, size=k, replace=False).astype(np.int64))
            lev_out.append(np.full(k, lev, dtype=np.int64))


def difficulty_weights(
    difficulty: FloatArray, *, transform: Literal["linear", "rank"] = "linear", floor: float = 1e-3
) -> FloatArray:
    """Sampling weights from a per-segment difficulty score (higher = more likely to fail).

    - ``transform="linear"`` (default): w = d - min(d) + floor * (max(d) - min(d)), i.e.
      proportional to the score shifted to start at a small positive floor. A score that
      already is a failure probability keeps its proportions (up to the shift by its min).
    - ``transform="rank"``: w = rank(d) / n (ties averaged), for scores on an arbitrary
      scale (logits, negative TTC): only their order matters.

    The floor keeps every segment drawable. Constant scores give uniform weights.

    Parameters
    ----------
    difficulty : ndarray of shape (n,)
    transform : {"linear", "rank"}
    floor : float

    Returns
    -------
    w : ndarray of shape (n,), positive, summing to 1
    """
    d = np.asarray(difficulty, dtype=np.float64)
    if not np.all(np.isfinite(d)):
        bad = np.flatnonzero(~np.isfinite(d))
        raise ValueError(
            f"difficulty has {len(bad)} non-finite values (first at row {bad[0]}); "
            "fill or drop them"
        )
    if transform == "rank":
        from scipy.stats import rankdata

        w = rankdata(d) / len(d)
    elif transform == "linear":
        span = d.max() - d.min() if len(d) else 0.0
        w = np.ones_like(d) if span == 0 else d - d.min() + floor * span
    else:
        raise ValueError(f"transform must be 'linear' or 'rank'; got {transform!r}")
    return w / w.sum()


def pick_difficulty(
    difficulty: FloatArray,
    costs: Sequence[float],
    budget: float,
    *,
    rng: np.random.Generator,
    observed_level0_mask: BoolArray | None = None,
    transform: Literal["linear", "rank"] = "linear",
) -> tuple[IntArray, IntArray]:
    """DS / DS-GP picks: level 0, without replacement, P proportional to difficulty weight.

    Successive sampling: each draw takes an unpicked, level-0-unobserved segment with
    probability proportional to ``difficulty_weights`` among those left.

    Parameters
    ----------
    difficulty : ndarray of shape (n_pool,)
    costs : sequence of float
    budget : float
    rng : numpy.random.Generator
    observed_level0_mask : bool ndarray of shape (n_pool,), optional
    transform : {"linear", "rank"}

    Returns
    -------
    index : int ndarray of shape (r,)
    level : int ndarray of shape (r,)   (all 0)
    """
    difficulty = np.asarray(difficulty, dtype=np.float64)
    free = np.flatnonzero(_available(len(difficulty), observed_level0_mask))
    k = min(_n_affordable(float(costs[0]), budget), len(free))
    if k == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    w = difficulty_weights(difficulty, transform=transform)[free]
    pick = rng.choice(free, size=k, replace=False, p=w / w.sum())
    return pick.astype(np.int64), np.zeros(k, dtype=np.int64)


def pick_cross_entropy(
    X: FloatArray,
    observed_index: IntArray,
    observed_value: FloatArray,
    costs: Sequence[float],
    budget: float,
    *,
    rng: np.random.Generator,
    n_elite: int = CE_N_ELITE,
    var_floor: float = CE_VAR_FLOOR,
) -> tuple[IntArray, IntArray]:
    """CE picks: sample a diagonal Gaussian fitted to the elite, snap to the nearest segment.

    Paper appendix "Setup for the cross-entropy method": the sampling distribution is a
    Gaussian with diagonal covariance over the embedding; its mean and variance are fitted
    to the ``n_elite`` observed level-0 segments with the most dangerous (lowest) metric;
    each sample is mapped to the nearest segment (Euclidean, in X) that is unobserved at
    level 0 and not yet picked. The elite is refitted from all level-0 observations at every
    call, so no state is carried between batches. With fewer than two observations the
    picks are uniform (CE has nothing to fit yet). ``var_floor`` (times the pool's
    per-dimension variance) stops the Gaussian from collapsing onto one point.

    Parameters
    ----------
    X : ndarray of shape (n_pool, d)
    observed_index : int ndarray of shape (n_obs,)
        Pool indices with a level-0 observation.
    observed_value : ndarray of shape (n_obs,)
        Their level-0 metric f.
    costs : sequence of float
    budget : float
    rng : numpy.random.Generator
    n_elite : int
    var_floor : float

    Returns
    -------
    index : int ndarray of shape (r,)
    level : int ndarray of shape (r,)   (all 0)
    """
    X = np.asarray(X, dtype=np.float64)
    n_pool = len(X)
    observed_index = np.asarray(observed_index, dtype=np.int64)
    observed_value = np.asarray(observed_value, dtype=np.float64)
    observed = np.zeros(n_pool, dtype=bool)
    observed[observed_index] = True
    free = np.flatnonzero(~observed)
    k = min(_n_affordable(float(costs[0]), budget), len(free))
    if k == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if len(observed_index) < 2:
        return pick_uniform(n_pool, costs, budget, rng=rng, observed_level0_mask=observed)

    elite = observed_index[np.argsort(observed_value, kind="stable")[: max(n_elite, 2)]]
    mean = X[elite].mean(axis=0)
    var = X[elite].var(axis=0) + var_floor * X.var(axis=0)
    from scipy.spatial import cKDTree

    tree = cKDTree(X[free])
    taken = np.zeros(len(free), dtype=bool)
    out: list[int] = []
    while len(out) < k:
        z = mean + np.sqrt(var) * rng.standard_normal(len(mean))
        # Nearest free segment not taken yet: widen the neighbour query until one is found.
        n_q = 8
        while True:
            _, nn = tree.query(z, k=min(n_q, len(free)))
            nn = np.atleast_1d(nn)
            fresh = nn[~taken[nn]]
            if len(fresh) or n_q >= len(free):
                break
            n_q *= 4
        if not len(fresh):  # every free segment taken (cannot happen while len(out) < k)
            break
        taken[fresh[0]] = True
        out.append(int(free[fresh[0]]))
    return np.array(out, dtype=np.int64), np.zeros(len(out), dtype=np.int64)


def pick_baseline(
    strategy: Strategy,
    *,
    n_pool: int,
    costs: Sequence[float],
    budget: float,
    rng: np.random.Generator,
    observed_level0_mask: BoolArray | None = None,
    difficulty: FloatArray | None = None,
    X: FloatArray | None = None,
    observed_index: IntArray | None = None,
    observed_value: FloatArray | None = None,
    mixed: bool | None = None,
    level_shares: Sequence[float] | None = None,
    excluded_pairs: BoolArray | None = None,
) -> tuple[IntArray, IntArray]:
    """Dispatch to the pick function of ``strategy`` (see the module table).

    ``mixed`` spreads the uniform strategies over the levels (by default only ``mcm-gp``
    does), with ``level_shares`` of the budget per level (``pick_uniform``);
    ``excluded_pairs`` are the (segment, level) pairs they must not pick.

    Returns
    -------
    index : int ndarray of shape (r,)
    level : int ndarray of shape (r,)
    """
    if strategy in ("mc", "random", "mc-gp", "mcm-gp"):
        return pick_uniform(
            n_pool,
            costs,
            budget,
            rng=rng,
            mixed=strategy == "mcm-gp" if mixed is None else mixed,
            observed_level0_mask=observed_level0_mask,
            level_shares=level_shares,
            excluded_pairs=excluded_pairs,
        )
    if strategy in ("ds", "ds-gp"):
        if difficulty is None:
            raise ValueError(f"strategy {strategy!r} needs a difficulty score per segment")
        return pick_difficulty(
            difficulty, costs, budget, rng=rng, observed_level0_mask=observed_level0_mask
        )
    if strategy == "ce":
        if X is None or observed_index is None or observed_value is None:
            raise ValueError("strategy 'ce' needs X, observed_index and observed_value")
        return pick_cross_entropy(X, observed_index, observed_value, costs, budget, rng=rng)
    raise ValueError(f"unknown strategy {strategy!r}; choose one of {', '.join(STRATEGIES)}")
