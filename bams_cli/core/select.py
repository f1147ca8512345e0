"""Batch selection: per-cluster greedy on the acquisition J, then Algorithm 1's pooling.

Paper section 3 ("Sequential selection", "Multifidelity sampling"), appendix A.1-A.4 and
DESIGN.md ("Greedy selection without re-inverting anything", "Where the time goes").

Within a cluster with rows R (pool points) and candidates c = (x, l), x in R, every allowed
level l, the greedy keeps

    C(x, c) = cov(theta0(x), y_c | data, S)     rows x candidates
    V(c)    = var(y_c | data, S)                candidates
    G(s_k, .) = cov(y_{s_k}, y_. | data, S_{k-1})  one row per pick so far

and picking s is one rank-1 conditioning step (the paper's block-inverse recursion, appendix
A.3, written as conditioning):

    C <- C - C[:, s] G(s, :) / V(s),   V <- V - G(s, :)^2 / V(s),
    sigma_{n+S}^2(x) <- sigma_{n+S}^2(x) - C(x, s)^2 / V(s).

A candidate's score is the cost-normalised decrease (paper eq. (5))

    (J(S) - J(S + c)) / c_l,   t_c(x) = t_S(x) - C(x, c)^2 / (V(c) sigma_n^2(x)).

Where the time goes is beta over rows x candidates (1.1e8 values per pick at N = 45k). The
pick is nevertheless exact; three devices make it cheap, none of which changes the answer:

1. Rows whose point variance h_n is negligible (the smallest h_n summing to at most
   ``row_drop_rtol`` of the total) are left out of the screening pass. They cannot move J by
   more than R = sum of their current beta, because 0 <= beta <= h_n.
2. The screening pass evaluates beta(s_x, .) through a per-row degree-8 polynomial
   (``acquisition.beta_poly``) in a compiled loop, with a rigorous bound err_x on its error.
   The loop computes t with exactly the same floating-point operations as the exact path,
   so the bound covers everything but the polynomial.
3. Every candidate gets an interval [lower, upper] for its score from the screened value,
   sum err_x, R and the summation rounding. Only candidates whose upper end reaches the best
   lower end can win; those "contenders" are evaluated exactly (``scipy.special.owens_t``
   over every row, dropped ones included), best upper bound first, stopping as soon as the
   next upper bound falls below the best exact score. The pick and its Delta J are exact.
4. Candidates that can never be picked again (picked, determined, or a level the shrinking
   budget no longer buys) are dropped from C once they are a quarter of its columns
   (``_compact_columns``, in place): at N = 45k the cheap level outlives level 0 for the
   last third of a cluster's picks, and the screen no longer streams those columns.

Multiple thresholds: J is defined for one gamma. ``select_batch`` takes one; the pipeline
passes the first configured gamma (the others are scored by the same GP afterwards).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numba import njit
from numpy.typing import NDArray
from scipy.linalg import cho_factor, eigh, solve_triangular
from threadpoolctl import threadpool_limits

from bams_cli import defaults

from .acquisition import CHEB_DEGREE, beta, beta_poly, margin, point_variance
from .cluster import cluster_pool
from .kernels import kernel_threads
from .posterior import Posterior

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]
ProgressFn = Callable[[str, int, int], None]

#: A candidate whose conditional variance is below this fraction of the largest starting
#: candidate variance in its cluster is determined already (a noise-free repeat of data or of
#: a pick): it can teach nothing, and C / V would be 0 / 0 in rounding noise.
V_TINY_REL = 1e-12
#: Floats of each of the three blocks (rows x pairs, dropped rows x pairs, pairs x
#: candidates) in which the greedy conditions on the pairs already in the batch (at most 64
#: pairs a block).
FORCED_CHUNK_ELEMENTS = 2**22
#: Bytes of rows x candidates float64 one cluster may hold before ``select_batch`` refuses.
MAX_CLUSTER_BYTES = 4 * 2**30
#: Per cluster, the most the posterior may keep of its points' whitened factors
#: (``MFGP.localised``): with thousands of observations they are most of select's work.
FACTOR_CACHE_BYTES = 2 * 2**30
#: ``_pool_blas_threads``: from this many observations the whole-pool steps use every core.
POOL_THREADED_FROM = 500
_EPS = float(np.finfo(np.float64).eps)
#: Compact C once fewer than this fraction of its columns can still be picked.
COMPACT_BELOW = 0.75
_PREDICT_BLOCK = 8192
#: Rows (largest h_n) the candidate screen's first-pick score sums over (``screen_candidates``).
SCREEN_ROWS = 1024
#: Of those, rows the first stage of the screen sums over for every candidate.
SCREEN_ROWS_FIRST = 128
#: Stage 2 of the screen scores this many times ``max_candidates`` candidates.
SCREEN_PRESCREEN = 2


@dataclass
class ClusterQueue:
    """One cluster's greedy picks, in the order the greedy made them (Algorithm 1, Queue_s).

    Attributes
    ----------
    cluster : int
    n_rows : int
        N_s, the cluster's number of pool points.
    index : int ndarray of shape (q,)
        Pool indices of the picks.
    level : int ndarray of shape (q,)
    delta_j : ndarray of shape (q,)
        J_s(S) - J_s(S + c) >= 0, the decrease of the cluster's own J (mean over its rows).
    cost : ndarray of shape (q,)
    timings : dict of str -> float
        Wall seconds spent in "build", "screen", "exact" and "update"; "cpu" is the process
        CPU time of the whole call (below the wall time when the machine is shared).
    stats : dict of str -> int
        "rows_screened", "rows_dropped", "candidates", "exact_evaluations".
    """

    cluster: int
    n_rows: int
    index: IntArray
    level: IntArray
    delta_j: FloatArray
    cost: FloatArray
    timings: dict[str, float] = field(default_factory=dict)
    stats: dict[str, int] = field(default_factory=dict)


@dataclass
class SelectionResult:
    """A selected batch, in pooling order.

    Attributes
    ----------
    index : int ndarray of shape (r,)
        Pool indices of the picks.
    level : int ndarray of shape (r,)
        Fidelity level of each pick (0 = high fidelity).
    delta_j : ndarray of shape (r,)
        The decrease of the whole pool's J the pick was chosen for: (N_s / N) times the
        cluster greedy's Delta J_s, conditional on the cluster's earlier picks. Their sum
        approximates ``j_before - j_after`` (exactly so for one cluster and no skipped picks).
    cost : ndarray of shape (r,)
    cluster : int ndarray of shape (r,)
    rank : int ndarray of shape (r,)
        0, 1, ...: the order in which pooling took the picks.
    score : ndarray of shape (r,)
        The pooling key: delta_j / cost for pooling="global", Delta J_s for "raw".
    j_before, j_after : float
        J of the whole pool before the batch and after it, given the pending pairs: all
        pairs conditioned on jointly, computed exactly (past ``max_work``, to 1e-17 a row
        where the sds are exact, see ``plan["pool_sds"]``); or, where the pending pairs
        and the picks together are past ``max_work``, each cluster on its own pairs, an
        upper bound (``plan["j_by_cluster"]``).
    gamma : float
        The threshold J was computed for.
    labels : int ndarray of shape (N,)
        Cluster of every pool point.
    timings : dict of str -> float
        Wall seconds per phase ("predict", "cluster", "greedy", "pool", "j_after": J
        before and after the batch, "total")
        plus seconds summed over clusters inside the greedy ("greedy.build", "greedy.screen",
        "greedy.exact", "greedy.update", and "greedy.cpu", their CPU time).
    stats : dict of str -> int
    queues : list of ClusterQueue
        Every cluster's greedy queue, including the picks pooling did not take.
    plan : dict
        The plan taken (``plan_selection``) and what it kept: "exact", "reason",
        "clusters", "max_rows_per_cluster", "max_candidates_per_cluster", "random_share",
        "screen_rounds", "candidates_offered", "candidates_kept" (over all screening rounds),
        "candidates_per_round" (most in one cluster's round: the columns its greedy holds),
        "rows_live" (rows with p_n (1 - p_n) > 0),
        "rows_in_j" (rows J is averaged over, each cluster's largest p_n (1 - p_n)) (None
        where the exact plan has no such limit).
    """

    index: IntArray
    level: IntArray
    delta_j: FloatArray
    cost: FloatArray
    cluster: IntArray
    rank: IntArray
    score: FloatArray
    j_before: float
    j_after: float
    gamma: float
    labels: IntArray
    timings: dict[str, float]
    stats: dict[str, int]
    queues: list[ClusterQueue] = field(default_factory=list)
    plan: dict[str, Any] = field(default_factory=dict)

    @property
    def total_cost(self) -> float:
        """Sum of the picks' costs (correctly rounded)."""
        return math.fsum(self.cost.tolist())


# --------------------------------------------------------------------------------------
# The compiled screening pass
# --------------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _update_and_screen(C, a, g, inv_sig2, tS, b, M, invV, acc):  # pragma: no cover
    """Apply the pending rank-1 step to C and sum the screened decreases per candidate.

    C : (n_rows, n_c), updated in place: C -= outer(a, g) (a = 0 when nothing is pending;
    x - 0 * y == x exactly).
    acc : (n_c,), out: acc[c] = sum_x b_x - sqrt(t) P_x(2 t - 1), t = t_c(x).

    One pass over C per pick: the loop streams ~1e8 doubles, so the update and the
    screening share it. No fast-math: t must come out bit for bit as in the numpy exact
    path, t = tS_x - ((C * C) * invV) * inv_sig2 clipped at 0. Estrin's scheme keeps the
    dependency chain short (Horner or Clenshaw would be latency-bound).
    """
    n_rows, n_c = C.shape
    for j in range(n_c):
        acc[j] = 0.0
    for i in range(n_rows):
        row = C[i]
        ai = a[i]
        si = inv_sig2[i]
        ti = tS[i]
        bi = b[i]
        mi = M[i]
        m0, m1, m2 = mi[0], mi[1], mi[2]
        m3, m4, m5 = mi[3], mi[4], mi[5]
        m6, m7, m8 = mi[6], mi[7], mi[8]
        for j in range(n_c):
            cij = row[j] - ai * g[j]
            row[j] = cij
            t = ti - cij * cij * invV[j] * si
            t = t if t > 0.0 else 0.0
            z = 2.0 * t - 1.0
            z2 = z * z
            z4 = z2 * z2
            q0 = (m0 + m1 * z) + (m2 + m3 * z) * z2
            q1 = (m4 + m5 * z) + (m6 + m7 * z) * z2
            v = q0 + (q1 + m8 * z4) * z4
            acc[j] += bi - math.sqrt(t) * v


@njit(cache=True)
def _compact_rows_in_place(flat, n_rows, n_c, keep):  # pragma: no cover
    k = keep.shape[0]
    for i in range(n_rows):
        src = i * n_c
        dst = i * k
        for jj in range(k):
            flat[dst + jj] = flat[src + keep[jj]]


def _compact_columns(C: FloatArray, keep: IntArray) -> FloatArray:
    """C[:, keep] for ascending ``keep``, written over C's own memory (no second copy).

    Row i of the result starts at i * len(keep) <= i * n_c and keep[jj] >= jj, so every
    element is read before anything overwrites it.
    """
    n_rows, n_c = C.shape
    flat = C.reshape(-1)
    _compact_rows_in_place(flat, n_rows, n_c, np.ascontiguousarray(keep, dtype=np.int64))
    return flat[: n_rows * len(keep)].reshape(n_rows, len(keep))


def _room(a: FloatArray, k: int) -> FloatArray:
    """``a`` (of whose rows the first k are in use) with room for row k: the capacity is
    doubled when full, so appending n rows one at a time copies O(n) rows in all."""
    if k < len(a):
        return a
    out = np.empty((max(2 * len(a), 8), *a.shape[1:]))
    out[:k] = a[:k]
    return out


# --------------------------------------------------------------------------------------
# Per-cluster greedy
# --------------------------------------------------------------------------------------


def _level_fits(used: list[float], costs: FloatArray, budget: float) -> BoolArray:
    """Which levels still fit: fsum(used + [c_l]) <= budget, correctly rounded."""
    return np.array([math.fsum([*used, float(c)]) <= budget for c in costs])


def greedy_cluster(
    posterior: Posterior,
    X: FloatArray,
    rows: IntArray,
    mu: FloatArray,
    sigma2: FloatArray,
    candidate_mask: BoolArray,
    *,
    gamma: float,
    costs: FloatArray,
    budget: float,
    cluster: int = 0,
    row_drop_rtol: float = 1e-4,
    forced_mask: BoolArray | None = None,
    max_rows: int | None = None,
    max_candidates: int | None = None,
    random_share: float = 0.1,
    seed: int = 0,
    screen_rounds: int = 1,
    factor_bytes: int = FACTOR_CACHE_BYTES,
    sds_from_posterior: bool = False,
) -> ClusterQueue:
    """Greedy selection in one cluster until its budget is spent (Algorithm 1, inner loop).

    Each step picks argmax_c (J_s(S) - J_s(S + c)) / c_l over the candidates that still fit
    (cost + c_l <= budget), ties to the lowest pool index, then the lowest level. A picked
    (x, l) is masked afterwards, and so is any candidate whose conditional variance has
    vanished. The loop stops when no candidate fits. J_s is the mean over the cluster's rows.

    A top-level function of plain arrays and the (picklable) posterior, so that an Executor
    can run it in another process.

    Parameters
    ----------
    posterior : Posterior
    X : ndarray of shape (n_s, d)
        The cluster's pool points.
    rows : int ndarray of shape (n_s,)
        Their pool indices, ascending.
    mu, sigma2 : ndarray of shape (n_s,)
        Posterior mean and variance of theta0 at X.
    candidate_mask : bool ndarray of shape (n_s, n_levels)
        [i, l] True when (X[i], l) is a candidate.
    gamma : float
    costs : ndarray of shape (n_levels,)
    budget : float
        ceil(eta m N_s / N) in cost units.
    cluster : int
        Label, carried into the result.
    row_drop_rtol : float
        Rows with the smallest h_n, up to this fraction of sum h_n, skip the screening pass
        (exactness is kept, see the module docstring). 0 screens every row.
    forced_mask : bool ndarray of shape (n_s, n_levels), optional
        [i, l] True when (X[i], l) is in the batch already (picks of an earlier batch still
        awaiting results). The greedy starts from S = these pairs: each is one conditioning
        step like a pick's (J needs only their covariances, not their values), costs
        nothing, is never picked again and is not part of the returned queue; every
        Delta J_s is then J_s(forced + S) - J_s(forced + S + c).
    max_rows, max_candidates : int, optional
        The approximate plan (``plan_selection``): J_s is summed over the ``max_rows``
        rows with the largest h_n only, and the greedy chooses among at most
        ``max_candidates`` candidates (``_approximate_cluster``). None (both, the default)
        is the exact greedy.
    random_share : float
        Share of ``max_candidates`` drawn uniformly from the candidates the screen passed over.
    seed : int
        Seeds the random share of candidates (with ``cluster``).
    screen_rounds : int
        Approximate plan: the candidates are screened anew this many times as the greedy
        spends the budget, given the picks so far (``_approximate_cluster``).
    factor_bytes : int
        Memory the posterior may keep the cluster's whitened factors in (a posterior with
        ``localised``, as ``MFGP``); over it, every factor is solved when asked for.
    sds_from_posterior : bool
        Replace sigma2 by the posterior's own variances at X, keeping mu: for a local
        posterior (``select_batch``'s ``local_obs``), whose variances are not the ones
        given, so that sigma_{n+S}^2 / sigma_n^2 stays in [0, 1].

    Returns
    -------
    ClusterQueue
    """
    kwargs: dict[str, Any] = dict(
        gamma=gamma,
        costs=costs,
        budget=budget,
        cluster=cluster,
        row_drop_rtol=row_drop_rtol,
        forced_mask=forced_mask,
    )
    # One BLAS thread: the posterior's matrices here are (rows or candidates) x n_obs with
    # n_obs ~ 30, where OpenBLAS threads only add synchronisation; and clusters already run
    # in parallel processes. Measured on the busy 2-core box: update and exact phases 10x
    # faster, the covariance build 4x. The kernels' threads likewise (core.kernels).
    with threadpool_limits(limits=1, user_api="blas"), kernel_threads(1):
        if sds_from_posterior:
            sigma2 = np.maximum(posterior.predict_theta0(X)[1], 0.0)
        localised = getattr(posterior, "localised", None)
        if localised is not None:
            posterior = localised(X, factor_bytes)
        args = (posterior, X, rows, mu, sigma2, candidate_mask)
        if max_rows is not None or max_candidates is not None:
            return _approximate_cluster(
                *args,
                **kwargs,
                max_rows=max_rows,
                max_candidates=max_candidates,
                random_share=random_share,
                seed=seed,
                screen_rounds=screen_rounds,
            )
        return _greedy_cluster(*args, **kwargs)


def _greedy_cluster(
    posterior: Posterior,
    X: FloatArray,
    rows: IntArray,
    mu: FloatArray,
    sigma2: FloatArray,
    candidate_mask: BoolArray,
    *,
    gamma: float,
    costs: FloatArray,
    budget: float,
    cluster: int,
    row_drop_rtol: float,
    forced_mask: BoolArray | None = None,
    j_mask: BoolArray | None = None,
    n_norm: float | None = None,
    n_rows: int | None = None,
    timings: dict[str, float] | None = None,
    cpu0: float | None = None,
    stats: dict[str, int] | None = None,
    spent: list[float] | None = None,
    stop_cost: float | None = None,
) -> ClusterQueue:
    """The greedy itself. ``j_mask`` (default all) marks the rows J is summed over;
    a pick's Delta J is that sum divided by ``n_norm`` (default len(rows)). The
    approximate plan passes its kept rows and candidates this way (``_approximate_cluster``).
    ``spent``: costs of picks made before this call (conditioned on as ``forced_mask``),
    counted against ``budget``; ``stop_cost``: stop once the picks' costs with ``spent``
    reach it (the picks up to there are those of the greedy with no stop)."""
    spent = [] if spent is None else list(spent)
    timings = {"build": 0.0, "screen": 0.0, "exact": 0.0, "update": 0.0} | (timings or {})
    cpu0 = time.process_time() if cpu0 is None else cpu0
    t0 = time.perf_counter()
    X = np.asarray(X, dtype=np.float64)
    rows = np.asarray(rows, dtype=np.int64)
    costs = np.asarray(costs, dtype=np.float64)
    n_s = float(len(rows)) if n_norm is None else float(n_norm)
    s_all = margin(mu, sigma2, gamma)
    h = point_variance(s_all)

    # Rows with h = 0 have beta = 0 whatever we pick; the rest split into screened rows K
    # and dropped rows D (smallest h, summing to <= row_drop_rtol * sum h).
    live = np.flatnonzero((h > 0.0) if j_mask is None else (h > 0.0) & j_mask)
    order = live[np.argsort(h[live], kind="stable")]
    csum = np.cumsum(h[order])
    n_drop = int(np.searchsorted(csum, row_drop_rtol * csum[-1], side="right")) if len(csum) else 0
    D = np.sort(order[:n_drop])
    K = np.sort(order[n_drop:])

    # Forced pairs are columns like the candidates (conditioning needs their C and G), are
    # conditioned on first, in pool-index order, and are never eligible afterwards.
    forced_mask = (
        np.zeros_like(candidate_mask, dtype=bool)
        if forced_mask is None
        else np.asarray(forced_mask, dtype=bool)
    )
    columns = np.asarray(candidate_mask, dtype=bool) | forced_mask
    cand_row, cand_level = np.nonzero(columns)  # row-major: by pool index, then level
    forced_cols = np.flatnonzero(forced_mask[cand_row, cand_level]).astype(np.int64)
    cand_level = cand_level.astype(np.int64)
    n_c = n_c0 = len(cand_row)
    Xc = np.ascontiguousarray(X[cand_row])
    cc = costs[cand_level]

    # Screened rows: C(K, candidates) built in row blocks of ~64 MB.
    C = np.empty((len(K), n_c))
    blk = max(1, (8 * 2**20) // max(n_c, 1))
    for i0 in range(0, len(K), blk):
        C[i0 : i0 + blk] = posterior.cov_theta0_obs(X[K[i0 : i0 + blk]], Xc, cand_level)
    V = np.array(posterior.obs_var(Xc, cand_level), dtype=np.float64) if n_c else np.zeros(0)
    v_floor = V_TINY_REL * (float(V.max()) if n_c else 0.0)
    alive = V > v_floor
    picked = np.zeros(n_c, dtype=bool)

    s_K = s_all[K]
    sig2_K = np.asarray(sigma2, dtype=np.float64)[K]
    inv_sig2_K = 1.0 / sig2_K
    sS_K = sig2_K.copy()  # sigma_{n+S}^2
    tS_K = np.ones(len(K))
    b_K = beta(s_K, tS_K)
    M_K, err_K = beta_poly(s_K)
    assert M_K.shape[1] == CHEB_DEGREE + 1 == 9  # the compiled loop is written for 9
    # Screened sum error: polynomial bounds + rounding of the n_K-term sum of terms of size
    # <= b_x + err_x and of each subtraction b_x - approx.
    E = float(err_K.sum() + (len(K) + 2) * 2.0 * _EPS * (b_K + err_K).sum())

    s_D = s_all[D]
    sig2_D = np.asarray(sigma2, dtype=np.float64)[D]
    inv_sig2_D = 1.0 / sig2_D
    sS_D = sig2_D.copy()
    tS_D = np.ones(len(D))
    b_D = beta(s_D, tS_D)
    XD = X[D]

    # The rank-1 steps so far, k of them, step j conditioning on pair s_j: rows of G_rows are
    # G_{j-1}(s_j, .), V_steps the V_{j-1}(s_j), rows of A_D C_{j-1}(D, s_j), and rows of A_K
    # C_{j-1}(K, s_j) / V_{j-1}(s_j) for the forced pairs, whose steps reach C only when
    # the picking starts (one matrix product for all of them instead of one pass over C each).
    k = 0
    G_rows = np.empty((0, n_c))
    V_steps = np.empty(0)
    A_D = np.empty((0, len(D)))
    A_K = np.empty((0, len(K)))
    n_forced = 0  # steps of forced pairs, all before the first pick's
    out_idx: list[int] = []
    out_lev: list[int] = []
    out_dj: list[float] = []
    out_cost: list[float] = []
    used: list[float] = []
    a_vec = np.zeros(len(K))
    g_vec = np.zeros(n_c)
    acc = np.zeros(n_c)
    n_exact = 0
    arange_c = np.arange(n_c)
    # Forced pairs come in chunks: each chunk's columns of C(K, .), C(D, .) and G(., all)
    # are computed and brought up to date with the steps before it in three products; in the
    # chunk, each pair needs only the steps taken since. (One pair at a time, the work and
    # the copying grew with the square of a cluster's pending pairs.)
    chunk = int(np.clip(FORCED_CHUNK_ELEMENTS // max(len(K), len(D), n_c, 1), 1, 64))
    fi = chunk_start = chunk_end = k0 = 0
    CKF = CDF = GF = np.empty((0, 0))
    timings["build"] += time.perf_counter() - t0

    def dropped_columns(B: IntArray) -> FloatArray:
        """C_S(D, B): the data-conditioned covariance minus the steps' rank-1 terms."""
        CD = np.asarray(posterior.cov_theta0_obs(XD, Xc[B], cand_level[B]), dtype=np.float64)
        if k:
            CD = CD - A_D[:k].T @ (G_rows[:k][:, B] / V_steps[:k, None])
        return CD

    def exact_decrease(B: IntArray, invV: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Exact sum over all rows of beta(t_S) - beta(t_c) for candidates B; also C_S(D, B)."""
        CK = C[:, B]
        # Same operations, same order as the compiled loop: bit-identical t.
        tK = np.maximum(tS_K[:, None] - CK * CK * invV[B][None, :] * inv_sig2_K[:, None], 0.0)
        dec = (b_K[:, None] - beta(s_K[:, None], tK)).sum(axis=0)
        CD = np.zeros((0, len(B)))
        if len(D):
            CD = dropped_columns(B)
            tD = np.maximum(tS_D[:, None] - CD * CD * invV[B][None, :] * inv_sig2_D[:, None], 0.0)
            dec = dec + (b_D[:, None] - beta(s_D[:, None], tD)).sum(axis=0)
        return dec, CD

    while True:
        t3 = time.perf_counter()
        if fi < len(forced_cols):
            # A pair already in the batch: condition on it.
            if fi == chunk_end:  # a new chunk: its columns, up to date with the steps so far
                chunk_start, chunk_end, k0 = fi, min(fi + chunk, len(forced_cols)), k
                f_chunk = forced_cols[chunk_start:chunk_end]
                Gf = G_rows[:k][:, f_chunk]
                CKF = C[:, f_chunk] - A_K[:k].T @ Gf
                CDF = dropped_columns(f_chunk) if len(D) else np.zeros((0, len(f_chunk)))
                GF = np.asarray(
                    posterior.cov_obs_obs(
                        Xc[f_chunk], cand_level[f_chunk], Xc, cand_level,
                        same=arange_c[None, :] == f_chunk[:, None],
                    ),
                    dtype=np.float64,
                ) - (Gf / V_steps[:k, None]).T @ G_rows[:k]  # fmt: skip
            s, j = int(forced_cols[fi]), fi - chunk_start
            fi += 1
            if not alive[s]:  # determined already: conditioning on it changes nothing
                picked[s] = True
                continue
            w = G_rows[k0:k, s] / V_steps[k0:k]
            colK = CKF[:, j] - A_K[k0:k].T @ G_rows[k0:k, s]
            best_CD = CDF[:, j] - A_D[k0:k].T @ w if len(D) else np.zeros(0)
            g = GF[j] - w @ G_rows[k0:k]
            pair_forced = True
        else:
            pair_forced = False
            if stop_cost is not None and math.fsum([*spent, *used]) >= stop_cost:
                break
            if n_forced:  # the forced pairs' steps, in row blocks
                t1 = time.perf_counter()
                for i0 in range(0, len(K), blk):
                    C[i0 : i0 + blk] -= A_K[:n_forced, i0 : i0 + blk].T @ G_rows[:n_forced]
                n_forced = 0
                A_K = np.empty((0, len(K)))
                CKF = CDF = GF = np.empty((0, 0))
                timings["update"] += time.perf_counter() - t1
            eligible = alive & ~picked & _level_fits([*spent, *used], costs, budget)[cand_level]
            if not eligible.any():
                break
            if eligible.sum() < COMPACT_BELOW * n_c:
                # Picked, determined and unaffordable candidates are out for good (the remaining
                # budget only shrinks and V only decreases), but the screen streams every column
                # of C at every pick: drop them. Column order is kept, so index ties break as
                # before. The pending rank-1 step (a_vec, g_vec) applies column by column.
                keep = np.flatnonzero(eligible)
                t1 = time.perf_counter()
                C = _compact_columns(C, keep)
                cand_row, cand_level, Xc, cc = cand_row[keep], cand_level[keep], Xc[keep], cc[keep]
                V, alive, picked, g_vec = V[keep], alive[keep], picked[keep], g_vec[keep]
                G_rows = G_rows[:k][:, keep]
                eligible = eligible[keep]
                n_c = len(keep)
                acc = np.zeros(n_c)
                arange_c = np.arange(n_c)
                timings["update"] += time.perf_counter() - t1
            t1 = time.perf_counter()
            invV = np.zeros(n_c)
            np.divide(1.0, V, out=invV, where=alive & ~picked)
            _update_and_screen(C, a_vec, g_vec, inv_sig2_K, tS_K, b_K, M_K, invV, acc)
            t2 = time.perf_counter()
            timings["screen"] += t2 - t1

            # Score intervals (the n_s c_l normalisation is common to J_s and the bounds).
            R = float(b_D.sum()) * (1.0 + 1e-12)
            norm = n_s * cc
            lower = np.where(eligible, (acc - E) / norm, -np.inf)
            upper = np.where(eligible, (acc + E + R) / norm, -np.inf)
            lb_star = lower.max()
            cont = np.flatnonzero(upper >= lb_star)
            cont = cont[np.lexsort((cont, -upper[cont]))]  # best upper first, then lowest index
            best, best_score, best_dec, best_CD = -1, -np.inf, 0.0, np.zeros(0)
            pos, nb = 0, 4
            while pos < len(cont):
                u = upper[cont[pos]]
                if u < best_score or (u == best_score and cont[pos] > best):
                    break
                B = cont[pos : pos + nb]
                dec, CD = exact_decrease(B, invV)
                n_exact += len(B)
                sc = dec / norm[B]
                for kk, c in enumerate(B):
                    if sc[kk] > best_score or (sc[kk] == best_score and c < best):
                        best, best_score, best_dec, best_CD = int(c), sc[kk], dec[kk], CD[:, kk]
                pos += len(B)
                nb = min(2 * nb, 64)
            t3 = time.perf_counter()
            timings["exact"] += t3 - t2

            s = best
            out_idx.append(int(rows[cand_row[s]]))
            out_lev.append(int(cand_level[s]))
            out_dj.append(float(best_dec) / n_s)
            out_cost.append(float(cc[s]))
            used.append(float(cc[s]))
            colK = C[:, s].copy()
            g = np.asarray(
                posterior.cov_obs_obs(
                    Xc[s : s + 1], cand_level[s : s + 1], Xc, cand_level,
                    same=(arange_c == s)[None, :],
                ),
                dtype=np.float64,
            )[0] - (G_rows[:k, s] / V_steps[:k]) @ G_rows[:k]  # fmt: skip

        # Conditioning on y_s: one rank-1 step for everything we keep. g is G_S(s, .),
        # conditional on the earlier steps.
        Vs = V[s]
        G_rows, V_steps = _room(G_rows, k), _room(V_steps, k)
        G_rows[k], V_steps[k] = g, Vs
        sS_K = sS_K - colK**2 / Vs
        tS_K = np.clip(sS_K * inv_sig2_K, 0.0, 1.0)
        b_K = beta(s_K, tS_K)
        E = float(err_K.sum() + (len(K) + 2) * 2.0 * _EPS * (b_K + err_K).sum())
        if len(D):
            A_D = _room(A_D, k)
            A_D[k] = best_CD
            sS_D = sS_D - best_CD**2 / Vs
            tS_D = np.clip(sS_D * inv_sig2_D, 0.0, 1.0)
            b_D = beta(s_D, tS_D)
        if pair_forced:  # its step reaches C when the picking starts
            A_K = _room(A_K, k)
            A_K[k] = colK / Vs
            n_forced = k + 1
        else:
            a_vec, g_vec = colK / Vs, g
        k += 1
        V = V - g**2 / Vs
        picked[s] = True
        alive &= V > v_floor
        timings["update"] += time.perf_counter() - t3

    timings["cpu"] = time.process_time() - cpu0
    return ClusterQueue(
        cluster=cluster,
        n_rows=len(rows) if n_rows is None else n_rows,
        index=np.array(out_idx, dtype=np.int64),
        level=np.array(out_lev, dtype=np.int64),
        delta_j=np.array(out_dj, dtype=np.float64),
        cost=np.array(out_cost, dtype=np.float64),
        timings=timings,
        stats={
            "rows_screened": len(K),
            "rows_dropped": len(D),
            "candidates": n_c0,
            "exact_evaluations": n_exact,
        }
        | (stats or {}),
    )


# --------------------------------------------------------------------------------------
# The approximate plan: J on the rows of largest h_n, a screened candidate subset
# --------------------------------------------------------------------------------------


def _own_point(
    posterior: Posterior, Xc: FloatArray, levels: IntArray
) -> tuple[FloatArray, FloatArray]:
    """cov_n(theta0(x_c), y_c) and var_n(y_c) for every candidate c at its own point.

    The posterior's own (``Posterior``'s optional ``own_point``, which ``MFGP`` has) where
    it has one: the blocks of 128 of ``cov_theta0_obs`` otherwise needed cost 128 kernel
    values per candidate instead of one, and the approximate plan at 45,000 av_like
    segments took 8.2-8.5 CPU s with them against 6.4-6.8 without. Blocks of 32 cost three
    times the CPU of 128 (per-call overhead; 3.3 s vs 1.2 s for 10,000 candidates).
    """
    own = getattr(posterior, "own_point", None)
    if own is not None:
        cov, var = own(Xc, levels)
        return np.asarray(cov, dtype=np.float64), np.asarray(var, dtype=np.float64)
    out = np.empty(len(Xc))
    blk = 128
    for i0 in range(0, len(Xc), blk):
        Cb = posterior.cov_theta0_obs(Xc[i0 : i0 + blk], Xc[i0 : i0 + blk], levels[i0 : i0 + blk])
        out[i0 : i0 + blk] = np.diagonal(np.asarray(Cb, dtype=np.float64))
    return out, np.asarray(posterior.obs_var(Xc, levels), dtype=np.float64)


class _Given:
    """Conditioning on pairs already in the batch: for the screen's scores outside the
    greedy's C, and for ``batch_variance``.

    With Sigma = cov_n(y_G, y_G) (noise on the diagonal) = L L^T, anything's covariance
    given y_G is its covariance given the data minus w_a^T w_b, w = L^-1 cov_n(y_G, .).
    A singular Sigma (a noise-free pair repeated) keeps only the directions it resolves:
    the others carry no information.
    """

    def __init__(self, posterior: Posterior, Xg: FloatArray, levels: IntArray) -> None:
        self.posterior, self.Xg, self.levels = posterior, Xg, levels
        S = np.asarray(
            posterior.cov_obs_obs(Xg, levels, Xg, levels, same=np.eye(len(Xg), dtype=bool)),
            dtype=np.float64,
        )
        S = 0.5 * (S + S.T)
        # Cholesky whitening is nested: the first g rows of L^-1 cov_n(y_G, .) whiten
        # against G's first g pairs alone (L's leading block is their factor).
        self.nested = True
        try:
            L, _ = cho_factor(S, lower=True)
            L = np.tril(L)
            self._whiten = lambda K: solve_triangular(L, K, lower=True)
        except np.linalg.LinAlgError:
            self.nested = False
            lam, Q = eigh(S)
            keep = lam > 1e-12 * max(lam.max(), 0.0)
            P = Q[:, keep] / np.sqrt(lam[keep])
            self._whiten = lambda K: P.T @ K
        # The pairs' data term solved once for every block of rows asked about (an MFGP's
        # ``cov_theta0_obs_to``): 11,782 pending picks against 14,654 observations solved
        # it again for each of a million-segment pool's blocks.
        self._cov_theta0: Callable[[FloatArray], FloatArray] | None = None
        self._to = getattr(posterior, "cov_theta0_obs_to", None)
        # Likewise against candidates (an MFGP's ``cov_obs_obs_from``): the screen asks
        # about every candidate of a cluster, in blocks.
        self._cov_obs: Callable[[FloatArray, IntArray], FloatArray] | None = None
        self._from = getattr(posterior, "cov_obs_obs_from", None)

    def w_theta0(self, X: FloatArray) -> FloatArray:
        """L^-1 cov_n(y_G, theta0(X)), shape (|G|, len(X))."""
        if self._to is not None:  # first call: solve the pairs' data term, or learn it can't
            self._cov_theta0, self._to = self._to(self.Xg, self.levels), None
        if self._cov_theta0 is not None:
            K = self._cov_theta0(X)
        else:
            K = self.posterior.cov_theta0_obs(X, self.Xg, self.levels)
        return self._whiten(np.asarray(K, dtype=np.float64).T)

    def w_obs(self, Xc: FloatArray, levels: IntArray) -> FloatArray:
        """L^-1 cov_n(y_G, y_c), shape (|G|, len(Xc)); no c is one of G's observations."""
        if self._from is not None:  # first call: solve the pairs' data term, or learn it can't
            self._cov_obs, self._from = self._from(self.Xg, self.levels), None
        if self._cov_obs is not None:
            K = self._cov_obs(Xc, levels)
        else:
            K = self.posterior.cov_obs_obs(
                self.Xg, self.levels, Xc, levels,
                same=np.zeros((len(self.Xg), len(Xc)), dtype=bool),
            )  # fmt: skip
        return self._whiten(np.asarray(K, dtype=np.float64))


def screen_candidates(
    posterior: Posterior,
    X: FloatArray,
    mu: FloatArray,
    sigma2: FloatArray,
    candidate_mask: BoolArray,
    *,
    gamma: float,
    costs: FloatArray,
    max_candidates: int,
    random_share: float,
    rng: np.random.Generator,
    j_rows: IntArray | None = None,
    prescreen: int | None = None,
    given: tuple[FloatArray, IntArray] | None = None,
    own: tuple[FloatArray, FloatArray] | None = None,
) -> BoolArray:
    """Keep at most ``max_candidates`` candidates: the best next picks, plus a random share.

    Two stages, each a restriction of the greedy's next step (paper eq. (5)) given the
    pairs ``given`` already in the batch (none: the first step):

    1. Own point: c = (x_c, l) scored by the decrease it causes at x_c alone, per cost,
       [beta(s_c, t_S) - beta(s_c, t_c)] / c_l with t_c = t_S - C_S(x_c, c)^2 /
       (V_S(c) sigma_n^2(x_c)), t_S = sigma_{n+S}^2(x_c) / sigma_n^2(x_c).
       The ``prescreen`` x ``max_candidates`` best go on.
    2. Next pick: those are scored by the decrease they cause summed over ``j_rows`` (the
       rows the approximate greedy sums J over; the ``SCREEN_ROWS`` of them with the
       largest beta(s, t_S), i.e. h_n when nothing is given), the greedy's own score, in
       the compiled screening loop.

    The best ``(1 - random_share) max_candidates`` of stage 2 are kept, plus a uniform draw
    from all the others: stage 1 misses candidates whose value lies in their neighbours,
    and the draw keeps every region of the cluster reachable.

    Parameters
    ----------
    X : ndarray of shape (n_s, d)
    mu, sigma2 : ndarray of shape (n_s,)
    candidate_mask : bool ndarray of shape (n_s, n_levels)
    j_rows : int ndarray, optional
        Indices into X of the rows stage 2 sums over; default all.
    given : (ndarray of shape (g, d), int ndarray of shape (g,)), optional
        Points and levels of the pairs the scores are conditional on (the greedy's picks
        so far, pairs of an earlier batch); none of them may be a candidate.
    own : (ndarray, ndarray) of shape (n_s, n_levels) each, optional
        cov_n(theta0(x_c), y_c) and var_n(y_c) of every candidate, given the data only,
        filled in here where NaN: a caller screening the same cluster again passes the
        same arrays (they do not depend on ``given``).

    Returns
    -------
    keep : bool ndarray of shape (n_s, n_levels)
        A subset of ``candidate_mask``.
    """
    cand_row, cand_level = np.nonzero(candidate_mask)
    n_c = len(cand_row)
    if n_c <= max_candidates:
        return np.asarray(candidate_mask, dtype=bool).copy()
    cand_level = cand_level.astype(np.int64)
    sig2_all = np.asarray(sigma2, dtype=np.float64)
    s_all = margin(mu, sig2_all, gamma)
    cond = None if given is None or len(given[0]) == 0 else _Given(posterior, *given)

    def remaining(idx: IntArray) -> tuple[FloatArray, FloatArray | None]:
        """t_S = sigma_{n+S}^2 / sigma_n^2 at rows idx, and their w (None: nothing given)."""
        if cond is None:
            return np.ones(len(idx)), None
        w = cond.w_theta0(np.ascontiguousarray(X[idx]))
        sg = sig2_all[idx]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(sg > 0, (sg - (w * w).sum(axis=0)) / np.where(sg > 0, sg, 1.0), 1.0)
        return np.clip(t, 0.0, 1.0), w

    sig2 = sig2_all[cand_row]
    s_c = s_all[cand_row]
    u_row, u_inv = np.unique(cand_row, return_inverse=True)
    tS_u, w_u = remaining(u_row)
    tS_c = tS_u[u_inv]
    b_c = beta(s_c, tS_c)
    n_rand = int(round(random_share * max_candidates))
    n_top = max_candidates - n_rand
    n_pre = min(n_c, (SCREEN_PRESCREEN if prescreen is None else prescreen) * max_candidates)

    # The rows the scores sum over: of the J rows, the SCREEN_ROWS with the largest
    # beta(s, t_S) (stage 2), and the SCREEN_ROWS_FIRST largest of those (stage 1). At 1M
    # segments stage 2 on all 4,096 J rows was three quarters of select's time (351 of
    # 461 s summed over clusters).
    rows_j = np.arange(len(X)) if j_rows is None else np.asarray(j_rows, dtype=np.int64)
    rows_j = rows_j[sig2_all[rows_j] > 0]
    tS_r, w_r = remaining(rows_j)
    s_r = s_all[rows_j]
    b_r = beta(s_r, tS_r)
    by_b = np.lexsort((rows_j, -b_r))
    if len(rows_j) > SCREEN_ROWS:
        top_h = np.sort(by_b[:SCREEN_ROWS])
        rows_j, s_r, tS_r, b_r = rows_j[top_h], s_r[top_h], tS_r[top_h], b_r[top_h]
        w_r = None if w_r is None else np.ascontiguousarray(w_r[:, top_h])
        by_b = np.lexsort((rows_j, -b_r))
    inv_sig2 = 1.0 / sig2_all[rows_j]
    M_r, _ = beta_poly(s_r)
    Xr = np.ascontiguousarray(X[rows_j])

    solve_rows = getattr(posterior, "cov_obs_obs_from", None)

    def rows_cov(r: IntArray) -> Callable[[FloatArray, IntArray], FloatArray]:
        """(Xc, levels) -> cov_n(theta0(Xr[r]), y_c): the rows' data term solved once
        where the posterior can (``MFGP.cov_obs_obs_from`` at level 0, not localised),
        since stage 1 asks about the same rows for every block of candidates."""
        Xr_r = np.ascontiguousarray(Xr[r])
        level0 = np.zeros(len(r), dtype=np.int64)
        solved = None if solve_rows is None else solve_rows(Xr_r, level0)
        if solved is not None:
            return solved
        return lambda Xc, lc: posterior.cov_theta0_obs(Xr_r, Xc, lc)

    def decrease(
        r: IntArray,
        cov_r: Callable[[FloatArray, IntArray], FloatArray],
        Xb: FloatArray,
        lb: IntArray,
        invV: FloatArray,
        wb: Any,
    ) -> FloatArray:
        """Screened sum over rows r (indices into rows_j; ``cov_r`` their covariances)
        of the decrease each of Xb, lb causes, given the pairs (w_r, wb); blocks of ~64 MB
        of C."""
        out = np.zeros(len(Xb))
        wr = None if w_r is None else np.ascontiguousarray(w_r[:, r])
        cblk = max(1, (8 * 2**20) // max(len(r), 1))
        for j0 in range(0, len(Xb), cblk):
            J = slice(j0, j0 + cblk)
            Cb = np.ascontiguousarray(cov_r(Xb[J], lb[J]), dtype=np.float64)
            if wr is not None and wb is not None:
                Cb -= wr.T @ wb[:, J]
            acc = np.zeros(Cb.shape[1])
            _update_and_screen(
                Cb,
                np.zeros(len(r)),
                np.zeros(Cb.shape[1]),
                np.ascontiguousarray(inv_sig2[r]),
                np.ascontiguousarray(tS_r[r]),
                np.ascontiguousarray(b_r[r]),
                np.ascontiguousarray(M_r[r]),
                np.ascontiguousarray(invV[J]),
                acc,
            )
            out[J] = acc
        return out

    # Stage 1, every candidate: the decrease at its own point plus that over the
    # SCREEN_ROWS_FIRST rows of largest beta(s, t_S). The own point alone misses a
    # candidate where the model is sure (p_n (1 - p_n) = 0) between unsure rows: at 45,000
    # av_like segments the exact greedy picks such candidates.
    r1 = np.sort(by_b[:SCREEN_ROWS_FIRST])
    cov_r1 = rows_cov(r1)
    score = np.empty(n_c)
    v_data = np.empty(n_c)  # var_n(y_c) given the data only; stage 2 reads it too
    blk = 8192
    for i0 in range(0, n_c, blk):
        B = np.arange(i0, min(i0 + blk, n_c))
        Xb = np.ascontiguousarray(X[cand_row[B]])
        rb, lb = cand_row[B], cand_level[B]
        if own is None or np.isnan(own[0][rb, lb]).any():
            c_own, V0 = _own_point(posterior, Xb, lb)
            if own is not None:
                own[0][rb, lb], own[1][rb, lb] = c_own, V0
        else:
            c_own, V0 = own[0][rb, lb], own[1][rb, lb]
        v_data[B] = V0
        V = V0
        ok = (V > 0) & (sig2[B] > 0)
        wc = None
        if cond is not None and w_u is not None:
            wc = cond.w_obs(Xb, cand_level[B])
            c_own = c_own - (w_u[:, u_inv[B]] * wc).sum(axis=0)
            V = V0 - (wc * wc).sum(axis=0)
            ok &= V > V_TINY_REL * V0
        with np.errstate(divide="ignore", invalid="ignore"):
            t_b = np.where(ok, tS_c[B] - c_own**2 / (V * sig2[B]), tS_c[B])
        at_own = b_c[B] - beta(s_c[B], np.clip(t_b, 0.0, 1.0))
        invV = np.zeros(len(B))
        np.divide(1.0, V, out=invV, where=ok)
        near = decrease(r1, cov_r1, Xb, cand_level[B], invV, wc)
        score[B] = (at_own + near) / costs[cand_level[B]]
    pre = np.lexsort((np.arange(n_c), -score))[:n_pre]  # best first, then lowest index

    # Stage 2: the next-step decrease over the SCREEN_ROWS rows, screened like the
    # greedy's picks.
    Xp = np.ascontiguousarray(X[cand_row[pre]])
    lp = cand_level[pre]
    Vp = v_data[pre]
    floor = np.zeros(n_pre)
    w_p = None
    if cond is not None:
        w_p = cond.w_obs(Xp, lp)
        floor = V_TINY_REL * Vp
        Vp = Vp - (w_p * w_p).sum(axis=0)
    invV = np.zeros(n_pre)
    np.divide(1.0, Vp, out=invV, where=Vp > floor)
    all_r = np.arange(len(rows_j))
    first = decrease(all_r, rows_cov(all_r), Xp, lp, invV, w_p) / costs[lp]
    top = pre[np.lexsort((pre, -first))[:n_top]]
    others = np.setdiff1d(np.arange(n_c), top)
    chosen = np.concatenate([top, rng.choice(others, size=min(n_rand, len(others)), replace=False)])
    keep = np.zeros_like(candidate_mask, dtype=bool)
    keep[cand_row[chosen], cand_level[chosen]] = True
    return keep


def _approximate_cluster(
    posterior: Posterior,
    X: FloatArray,
    rows: IntArray,
    mu: FloatArray,
    sigma2: FloatArray,
    candidate_mask: BoolArray,
    *,
    gamma: float,
    costs: FloatArray,
    budget: float,
    cluster: int,
    row_drop_rtol: float,
    forced_mask: BoolArray | None,
    max_rows: int | None,
    max_candidates: int | None,
    random_share: float,
    seed: int,
    screen_rounds: int = 1,
) -> ClusterQueue:
    """The greedy on the rows that matter most and a candidate subset of one cluster.

    J_s = (1/N_s) sum_x beta(x) is summed over the ``max_rows`` rows with the largest
    h_n = p_n (1 - p_n) only. Since 0 <= beta <= h_n, the rows left out change any Delta J_s
    by at most (1/N_s) times the sum of their h_n; the share of sum h_n left out is in the
    stats ("h_left_out_ppb", parts per billion). The candidates are those of
    ``screen_candidates``; the conditioning steps are exact on that subset.

    ``screen_rounds`` R > 1 screens again as the greedy goes: round r (1..R) runs the greedy
    until the cluster has spent r/R of its budget (the picks are those the greedy would make
    on that round's candidates with the whole budget), then the candidates are screened
    anew given every pick so far, and the next round continues the same greedy (its picks
    conditioned on, as ``forced_mask`` pairs) on them. One screen, from the first-step
    score, keeps candidates near the first picks and misses those that become the best
    once the region around the first picks is resolved.
    Memory: (kept rows) x (kept candidates) floats instead of N_s x (L + 1) N_s.
    """
    timings = {"build": 0.0, "screen": 0.0, "exact": 0.0, "update": 0.0, "plan": 0.0}
    cpu0 = time.process_time()
    t0 = time.perf_counter()
    rng = np.random.default_rng([seed, cluster])
    X = np.asarray(X, dtype=np.float64)
    rows = np.asarray(rows, dtype=np.int64)
    costs = np.asarray(costs, dtype=np.float64)
    n_s = len(rows)
    forced = (
        np.zeros_like(candidate_mask, dtype=bool)
        if forced_mask is None
        else np.asarray(forced_mask, dtype=bool)
    )
    h = point_variance(margin(mu, sigma2, gamma))
    live = np.flatnonzero(h > 0.0)
    j_rows = live
    if max_rows is not None and len(live) > max_rows:
        # The rows that can matter: a row's beta, and so anything a pick can take off it,
        # is at most h_n. Keeping the largest h_n leaves out at most the sum of the rest
        # (reported as "h_left_out"); a uniform sample instead spent most of its rows where
        # the model is sure, and kept 70% of the exact decrease where this keeps 99%.
        by_h = live[np.lexsort((live, -h[live]))]
        j_rows = np.sort(by_h[:max_rows])
    cand0 = np.asarray(candidate_mask, dtype=bool)
    screened = max_candidates is not None and np.count_nonzero(cand0) > max_candidates
    n_rounds = max(1, int(screen_rounds)) if screened else 1
    j_mask = np.zeros(n_s, dtype=bool)
    j_mask[j_rows] = True
    h_total = float(h.sum())
    h_out = h_total - float(h[j_rows].sum())
    in_batch = forced.copy()  # pairs the round's greedy starts conditioned on
    kept = np.zeros_like(cand0)
    most = 0  # most candidates in one round: the greedy's C has this many columns
    own = (np.full(cand0.shape, np.nan), np.full(cand0.shape, np.nan))  # screen's cache
    spent: list[float] = []
    parts: list[ClusterQueue] = []
    n_exact = 0
    timings["plan"] = time.perf_counter() - t0
    for r in range(n_rounds):
        stop = budget * (r + 1) / n_rounds if r + 1 < n_rounds else None
        if r > 0 and not _level_fits(spent, costs, budget).any():
            break  # the budget is spent
        if stop is not None and math.fsum(spent) >= stop:
            continue  # one expensive pick took this round's share too
        t0 = time.perf_counter()
        cand = cand0 & ~in_batch
        if screened and max_candidates is not None:
            gi, gl = np.nonzero(in_batch)
            cand = screen_candidates(
                posterior,
                X,
                mu,
                sigma2,
                cand,
                gamma=gamma,
                costs=costs,
                max_candidates=max_candidates,
                random_share=random_share,
                rng=rng,
                j_rows=j_rows,
                given=(np.ascontiguousarray(X[gi]), gl.astype(np.int64)) if len(gi) else None,
                own=own,
            )
        kept |= cand
        most = max(most, int(np.count_nonzero(cand)))
        # Points the sub-problem needs: the rows of J, the candidates' and the pairs in
        # the batch's own points, in pool order so ties still break to the lowest index.
        sub = np.flatnonzero(j_mask | (cand | in_batch).any(axis=1))
        timings["plan"] += time.perf_counter() - t0
        q = _greedy_cluster(
            posterior,
            X[sub],
            rows[sub],
            np.asarray(mu)[sub],
            np.asarray(sigma2)[sub],
            cand[sub],
            gamma=gamma,
            costs=costs,
            budget=budget,
            cluster=cluster,
            row_drop_rtol=row_drop_rtol,
            forced_mask=in_batch[sub] if in_batch.any() else None,
            j_mask=j_mask[sub],
            n_norm=float(n_s),
            n_rows=n_s,
            timings=timings,
            cpu0=cpu0,
            spent=spent,
            stop_cost=stop,
        )
        timings = q.timings
        parts.append(q)
        n_exact += q.stats["exact_evaluations"]
        in_batch[np.searchsorted(rows, q.index), q.level] = True
        spent += q.cost.tolist()
    return ClusterQueue(
        cluster=cluster,
        n_rows=n_s,
        index=np.concatenate([q.index for q in parts]),
        level=np.concatenate([q.level for q in parts]),
        delta_j=np.concatenate([q.delta_j for q in parts]),
        cost=np.concatenate([q.cost for q in parts]),
        timings=timings,
        stats={
            "rows_screened": parts[-1].stats["rows_screened"],
            "rows_dropped": parts[-1].stats["rows_dropped"],
            "candidates": int(np.count_nonzero(kept)),
            "candidates_per_round": most,
            "exact_evaluations": n_exact,
            "screen_rounds": len(parts),
            "rows_in_j": len(j_rows),
            "rows_live": len(live),
            "h_left_out_ppb": int(round(1e9 * h_out / h_total)) if h_total > 0 else 0,
            "candidates_offered": int(np.count_nonzero(candidate_mask)),
        },
    )


# --------------------------------------------------------------------------------------
# Pooling (Algorithm 1, outer loop)
# --------------------------------------------------------------------------------------


def pool_queues(
    costs: Sequence[FloatArray],
    keys: Sequence[FloatArray],
    index: Sequence[IntArray],
    level: Sequence[IntArray],
    budget: float,
) -> tuple[IntArray, IntArray]:
    """Merge cluster queues into one batch within the budget (Algorithm 1, second loop).

    Repeatedly: a queue whose head does not fit (fsum(costs so far) + c > budget) skips that
    head and moves on; among the heads that fit, take the largest key (ties: lowest
    cluster, then lowest pool index, then lowest level). Stops when every queue is empty.
    The paper's strict ``cost_g + c < m`` would leave a whole unit unused; DESIGN.md settles
    on <=.

    Parameters
    ----------
    costs, keys, index, level : sequences (one per cluster) of ndarrays of shape (q_s,)
    budget : float
        m, in cost units.

    Returns
    -------
    cluster : int ndarray of shape (r,)
    position : int ndarray of shape (r,)
        The taken items, in order, as (cluster, position in its queue).
    """
    n_q = len(costs)
    head = [0] * n_q
    used: list[float] = []
    taken_c: list[int] = []
    taken_p: list[int] = []
    while True:
        best = None
        for q in range(n_q):
            while head[q] < len(costs[q]) and math.fsum([*used, float(costs[q][head[q]])]) > budget:
                head[q] += 1  # does not fit: skipped, the queue moves on
            if head[q] < len(costs[q]):
                p = head[q]
                rank_key = (-float(keys[q][p]), q, int(index[q][p]), int(level[q][p]))
                if best is None or rank_key < best[0]:
                    best = (rank_key, q, p)
        if best is None:
            break
        _, q, p = best
        used.append(float(costs[q][p]))
        taken_c.append(q)
        taken_p.append(p)
        head[q] += 1
    return np.array(taken_c, dtype=np.int64), np.array(taken_p, dtype=np.int64)


# --------------------------------------------------------------------------------------
# Whole-pool quantities
# --------------------------------------------------------------------------------------


def _n_obs(posterior: Posterior) -> int:
    """Observations the posterior is conditioned on (0 for one that does not say)."""
    return len(getattr(posterior, "X_train", ()))


def _pool_blas_threads(posterior: Posterior) -> int | None:
    """BLAS threads for the whole-pool steps in the command's own process (the posterior at
    the pool, J after the batch): one for a posterior on a few dozen observations (see
    ``greedy_cluster``), every core from ``POOL_THREADED_FROM`` on, where each step is a
    triangular solve of n_obs x pool (at 3,700 observations and 12,000 segments, 4.4 s and
    5.5 s on one core) and the workers are idle."""
    return None if _n_obs(posterior) >= POOL_THREADED_FROM else 1


def _predict(
    posterior: Posterior,
    X: FloatArray,
    gamma: float | None = None,
    max_work: float | None = None,
    progress: ProgressFn | None = None,
) -> tuple[FloatArray, FloatArray, dict[str, Any] | None]:
    """mu_n and sigma_n^2 at every pool point, and how the sds were got (None: exactly).

    Exact sds cost pool size x n^2 flops. Past ``max_work`` (a million segments after an
    estimate stage's 12,000 level-0 runs: over an hour) a posterior that can
    (``MFGP.moments``) keeps the mean exact and bounds each sd from above, exact where
    gamma lies within ``SCORE_DECIDED_Z`` bound-sds of the mean, nearest first, as far as
    the budget goes. Elsewhere |s| exceeds that with either sd, so h_n and every beta
    there are below Phi(-8.5) < 1e-17. Near rows the budget did not reach keep the bound
    (the dict's ``exact_sd_rows`` < ``near_thresholds``; ``select`` warns as ``fit`` does): their h_n and
    the greedy's decreases there are those of a less certain model.
    """
    moments = getattr(posterior, "moments", None)
    bounded = getattr(posterior, "bounded_scoring", None)
    if (
        gamma is not None
        and moments is not None
        and bounded is not None
        and bounded(len(X), max_work)
    ):
        mu, sigma2, _ = moments(X, [gamma], _PREDICT_BLOCK, max_work=max_work, progress=progress)
        return mu, sigma2, dict(posterior.scoring)  # type: ignore[attr-defined]
    mu = np.empty(len(X))
    sigma2 = np.empty(len(X))
    for i0 in range(0, len(X), _PREDICT_BLOCK):
        m, v = posterior.predict_theta0(X[i0 : i0 + _PREDICT_BLOCK])
        mu[i0 : i0 + _PREDICT_BLOCK] = m
        sigma2[i0 : i0 + _PREDICT_BLOCK] = np.maximum(v, 0.0)
        if progress is not None:
            progress("predict", min(i0 + _PREDICT_BLOCK, len(X)), len(X))
    return mu, sigma2, None


def batch_variance(
    posterior: Posterior,
    X: FloatArray,
    sigma2: FloatArray,
    index: IntArray,
    level: IntArray,
    at: IntArray | None = None,
) -> FloatArray:
    """sigma_{n+B}^2 at every pool point (or the rows ``at``) after conditioning on the
    whole batch B jointly.

    sigma_{n+B}^2(x) = sigma_n^2(x) - c_B(x)^T Sigma_B^-1 c_B(x), with
    c_B(x) = cov_n(theta0(x), y_B) and Sigma_B = cov_n(y_B, y_B) (noise on the diagonal:
    every pick is its own future observation). If Sigma_B is singular (a noise-free pick
    repeated), the directions it cannot resolve carry no information and are dropped.

    Parameters
    ----------
    posterior : Posterior
    X : ndarray of shape (N, d)
    sigma2 : ndarray of shape (N,)
    index, level : int ndarray of shape (r,)

    at : int ndarray, optional
        Pool rows to compute it at; default all.

    Returns
    -------
    sigma2_after : ndarray of shape (N,), or (len(at),)
    """
    return _variances_given(posterior, X, sigma2, index, level, at, 0)[1]


def _variances_given(
    posterior: Posterior,
    X: FloatArray,
    sigma2: FloatArray,
    index: IntArray,
    level: IntArray,
    at: IntArray | None,
    first: int,
) -> tuple[FloatArray, FloatArray]:
    """``batch_variance`` given B's ``first`` pairs and given all of B, from one
    conditioning on B where its whitening is nested (``_Given.nested``): J before and
    after a batch given thousands of pending pairs cost one pass, not two."""
    rows = np.arange(len(X)) if at is None else np.asarray(at, dtype=np.int64)
    if len(index) == 0:
        return sigma2[rows].copy(), sigma2[rows].copy()
    given = _Given(posterior, X[index], level)
    # J before from the leading rows of the whitened covariances, unless nothing precedes
    # the picks or the whitening is not nested (then J before is conditioned on its own;
    # with nothing picked, W[:first] is all of W either way)
    from_rows = first > 0 and (given.nested or first == len(index))
    if first == 0:
        before = sigma2[rows].copy()
    elif from_rows:
        before = np.empty(len(rows))
    else:
        before = _variances_given(posterior, X, sigma2, index[:first], level[:first], rows, 0)[1]
    after = np.empty(len(rows))
    for i0 in range(0, len(rows), _PREDICT_BLOCK):
        r = rows[i0 : i0 + _PREDICT_BLOCK]
        W2 = given.w_theta0(X[r]) ** 2
        after[i0 : i0 + _PREDICT_BLOCK] = sigma2[r] - W2.sum(axis=0)
        if from_rows:
            before[i0 : i0 + _PREDICT_BLOCK] = sigma2[r] - W2[:first].sum(axis=0)
    return np.maximum(before, 0.0), np.maximum(after, 0.0)


def _j_given(
    posterior: Posterior,
    X: FloatArray,
    s: FloatArray,
    sigma2: FloatArray,
    index: IntArray,
    level: IntArray,
    decided_z: float | None = None,
    labels: IntArray | None = None,
) -> float:
    """J(B) = mean_x beta(s(x), t_B(x)): B conditioned on jointly, or per cluster (``labels``).

    ``decided_z``: rows with |s| at or past it keep beta(s, 1) = h_n, which no batch can
    raise (beta(s, t) <= beta(s, 1) for t <= 1), below Phi(-z) each; the pool-wide
    conditioning (N x n kernel evaluations) is then done on the other rows only.

    ``labels`` (the pool's clusters): each cluster's rows conditioned on the pairs of B in
    that cluster only. Conditioning on fewer pairs never lowers a variance, and beta rises
    with t, so this J is at least the joint one: an upper bound, for a B of thousands of
    pairs (an estimate stage's pending picks) where the joint one costs rows x n x |B|.
    """
    return _j_nested(posterior, X, s, sigma2, index, level, 0, decided_z, labels)[1]


def _j_nested(
    posterior: Posterior,
    X: FloatArray,
    s: FloatArray,
    sigma2: FloatArray,
    index: IntArray,
    level: IntArray,
    first: int,
    decided_z: float | None = None,
    labels: IntArray | None = None,
) -> tuple[float, float]:
    """``_j_given`` of B's ``first`` pairs and of all of B (J before and after a batch:
    the pending pairs first, then the picks), from one conditioning on B per group of rows
    (``_variances_given``)."""
    at = np.arange(len(X)) if decided_z is None else np.flatnonzero(np.abs(s) < decided_z)
    t_first, t_all = np.ones(len(X)), np.ones(len(X))
    if labels is None:
        groups = [(at, index, level, first)]
    else:
        groups = []
        for k in np.unique(labels[index]):
            mine = labels[index] == k  # keeps B's order: a cluster's first pairs lead
            groups.append((at[labels[at] == k], index[mine], level[mine], int(mine[:first].sum())))
    with threadpool_limits(limits=_pool_blas_threads(posterior), user_api="blas"):
        for rows, idx, lev, g in groups:
            if len(rows) == 0:
                continue
            sig2 = sigma2[rows]
            ok = sig2 > 0
            for t, v in zip(
                (t_first, t_all),
                _variances_given(posterior, X, sigma2, idx, lev, rows, g),
                strict=True,
            ):
                with np.errstate(divide="ignore", invalid="ignore"):
                    t[rows] = np.where(ok, v / np.where(ok, sig2, 1.0), 1.0)
    return float(beta(s, t_first).mean()), float(beta(s, t_all).mean())


def _j_by_cluster(
    posterior: Posterior,
    s: FloatArray,
    n_given: int,
    decided_z: float | None,
    max_work: float | None,
) -> bool:
    """Whether ``_j_given`` conditions cluster by cluster: when conditioning every row J
    sums over on all ``n_given`` pairs jointly is over ``max_work`` flops, a row's
    covariances with the pairs costing n x pairs and their whitening pairs^2."""
    if max_work is None or n_given == 0:
        return False
    rows = len(s) if decided_z is None else int(np.count_nonzero(np.abs(s) < decided_z))
    return float(rows) * n_given * (_n_obs(posterior) + n_given) > max_work


# --------------------------------------------------------------------------------------
# The plan: exact, or approximate at a size that fits memory and time
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SelectionPlan:
    """How ``select_batch`` runs the greedy on a pool of a given size.

    Attributes
    ----------
    exact : bool
        Every row and every candidate of every cluster (picks identical to brute force).
    n_clusters : int
        S, the number of clusters Algorithm 2 makes.
    max_rows, max_candidates : int or None
        Approximate plan only: per cluster, J is averaged over the at most ``max_rows``
        rows of largest h_n = p_n (1 - p_n) (chosen, not sampled), and the greedy chooses
        among at most ``max_candidates`` candidates (``screen_candidates``). None when
        exact.
    random_share : float
        Share of the kept candidates drawn uniformly (approximate plan).
    reason : str
        Why this plan, in one sentence.
    cluster_fit_max : int or None
        Approximate plan: K-means and the merge loop run on a sample of this many points
        (``cluster.cluster_pool``'s ``fit_max``). None: on every point.
    screen_rounds : int
        Approximate plan: how many times each cluster's candidates are screened as its
        greedy spends the budget (``_approximate_cluster``); 1 when exact.
    """

    exact: bool
    n_clusters: int
    max_rows: int | None
    max_candidates: int | None
    random_share: float
    reason: str
    cluster_fit_max: int | None = None
    screen_rounds: int = 1

    def describe(self) -> str:
        """One line for the progress display."""
        if self.exact:
            return f"exact greedy, {self.n_clusters} clusters"
        return (
            f"approximate greedy, {self.n_clusters} clusters, <= {self.max_candidates} "
            f"candidates and <= {self.max_rows} rows of J each"
        )


def plan_selection(
    n_pool: int,
    n_levels: int,
    n_clusters: int,
    *,
    approximate: Literal["auto", "never", "always"] = "auto",
    exact_max_pool: int = defaults.SELECT_EXACT_MAX_POOL,
    cluster_rows: int = defaults.SELECT_CLUSTER_ROWS,
    max_rows: int = defaults.SELECT_MAX_ROWS,
    max_candidates: int = defaults.SELECT_MAX_CANDIDATES,
    random_share: float = defaults.SELECT_RANDOM_SHARE,
    cluster_fit_max: int = defaults.SELECT_CLUSTER_FIT_MAX,
    max_cluster_bytes: int | None = None,
    screen_rounds: int = defaults.SELECT_SCREEN_ROUNDS,
) -> SelectionPlan:
    """Choose exact or approximate selection for a pool of ``n_pool`` points.

    "auto": exact up to ``exact_max_pool`` points; above, approximate with
    S = max(n_clusters, ceil(n_pool / cluster_rows)) clusters, so per-cluster work
    (picks x rows x candidates, picks ~ budget share ~ 1/S) and memory
    (``max_rows`` x ``max_candidates`` floats) stay bounded whatever the pool size.
    "never" forces exact (``select_batch`` refuses a cluster over ``MAX_CLUSTER_BYTES``);
    "always" forces the approximate plan (how the tests compare it with exact).
    Memory per cluster of the approximate plan is capped at ``max_cluster_bytes``
    (default ``MAX_CLUSTER_BYTES``) by shrinking ``max_rows``, down to 64, then
    ``max_candidates``.
    """
    if approximate not in ("auto", "never", "always"):
        raise ValueError(f"approximate must be 'auto', 'never' or 'always'; got {approximate!r}")
    limit = MAX_CLUSTER_BYTES if max_cluster_bytes is None else max_cluster_bytes
    if approximate == "never" or (approximate == "auto" and n_pool <= exact_max_pool):
        why = (
            "asked for"
            if approximate == "never"
            else f"pool of {n_pool} <= {exact_max_pool} segments"
        )
        return SelectionPlan(True, n_clusters, None, None, 0.0, f"exact: {why}")
    rows_fit = limit // (8 * max(max_candidates, 1))
    if rows_fit < 64:  # rows matter less than candidates, but 64 is the least we go to
        max_candidates, rows_fit = limit // (8 * 64), 64
    if max_candidates < 1:
        raise ValueError(
            f"the approximate plan needs {64 * 8 / 2**30:.2g} GiB per cluster at least "
            f"(64 rows x 1 candidate); the limit is {limit / 2**30:.2g} GiB"
        )
    s = max(n_clusters, math.ceil(n_pool / max(cluster_rows, 1)))
    return SelectionPlan(
        False,
        s,
        min(max_rows, rows_fit),
        max_candidates,
        random_share,
        f"approximate: pool of {n_pool} > {exact_max_pool} segments"
        if approximate == "auto"
        else "approximate: asked for",
        cluster_fit_max,
        max(1, int(screen_rounds)),
    )


# --------------------------------------------------------------------------------------
# Entry point
# --------------------------------------------------------------------------------------


def select_batch(
    posterior: Posterior,
    X: FloatArray,
    *,
    gamma: float,
    costs: Sequence[float],
    budget: float,
    n_clusters: int = 6,
    overbudget: float = 1.0,
    observed_level0_mask: BoolArray | None = None,
    pooling: Literal["global", "raw"] = "global",
    executor: Executor | None = None,
    rng: np.random.Generator,
    progress: ProgressFn | None = None,
    levels: Sequence[int] | None = None,
    reobserve_level0: bool = False,
    n_init_clusters: int | None = None,
    row_drop_rtol: float = 1e-4,
    excluded_pairs: BoolArray | None = None,
    pending_pairs: BoolArray | None = None,
    approximate: Literal["auto", "never", "always"] = "auto",
    plan_options: dict[str, Any] | None = None,
    max_work: float | None = defaults.SCORE_MAX_WORK,
    local_obs: int | None = defaults.SELECT_LOCAL_OBS,
    moments: tuple[FloatArray, FloatArray, dict[str, Any]] | None = None,
) -> SelectionResult:
    """Select the next batch of (segment, level) simulations (paper Algorithm 1).

    1. Cluster the pool (Algorithm 2, ``cluster.cluster_pool``).
    2. In every cluster s, run the greedy on its own rows and candidates with budget
       ceil(eta m N_s / N) (``greedy_cluster``), through ``executor`` when given.
    3. Pool the cluster queues within the budget m (``pool_queues``), comparing
       - pooling="global" (default): (N_s / N) Delta J_s / c_l, the cost-normalised
         decrease of the whole pool's J (J is the N_s/N-weighted sum of the clusters' J);
       - pooling="raw": Delta J_s as in the paper's Algorithm 1.
    4. Recompute J before and after the chosen batch, given the pending pairs: exactly,
       all pairs conditioned on jointly, or past ``max_work`` each cluster on its own
       pairs, an upper bound (``plan["j_by_cluster"]``).

    Parameters
    ----------
    posterior : Posterior
    X : ndarray of shape (N, d)
        The pool, in the coordinates the posterior was fitted in.
    gamma : float
        The failure threshold J is computed for (one; see the module docstring).
    costs : sequence of float, length n_levels
        Cost c_l of one simulation at each level, c_0 = 1 by convention.
    budget : float
        m, the batch budget in cost units.
    n_clusters : int
        S; 1 runs a single greedy over the whole pool (memory grows as N^2).
    overbudget : float
        eta >= 1: each cluster plans ceil(eta m N_s / N) so pooling has spare picks.
    observed_level0_mask : bool ndarray of shape (N,), optional
        True where level 0 is already observed; those (x, 0) are not candidates unless
        ``reobserve_level0``.
    pooling : {"global", "raw"}
    executor : concurrent.futures.Executor, optional
        Runs the per-cluster greedies; None runs them inline. Same answer either way.
    rng : numpy.random.Generator
        Seeds K-means; nothing else is random.
    progress : callable(phase, done, total), optional
    levels : sequence of int, optional
        Levels that may be selected; default all. ``levels=[0]`` is BAS.
    reobserve_level0 : bool
        Allow (x, 0) candidates where level 0 is already observed.
    n_init_clusters : int, optional
        S_hat for Algorithm 2; default 2 S.
    row_drop_rtol : float
        Speed knob of the exact screening (``greedy_cluster``); never changes the result.
    excluded_pairs : bool ndarray of shape (N, n_levels), optional
        True at (x, l) pairs that are never candidates (runs abandoned for good).
    pending_pairs : bool ndarray of shape (N, n_levels), optional
        True at (x, l) pairs an earlier batch picked whose results are still out. They
        are in the batch already: never candidates, and every cluster's greedy starts
        conditioned on its own (``greedy_cluster``'s ``forced_mask``), as a batch's earlier
        picks condition its later ones. J needs only their covariances, so this is exact;
        ``j_before`` is J given them and ``j_after`` J given them and the batch.
    approximate : {"auto", "never", "always"}
        Exact or approximate greedy (``plan_selection``): "auto" is exact up to
        ``defaults.SELECT_EXACT_MAX_POOL`` points, and also falls back to the approximate
        plan when an exact cluster would exceed ``MAX_CLUSTER_BYTES``. The plan taken is
        in ``SelectionResult.plan``.
    plan_options : dict, optional
        Keyword arguments for ``plan_selection`` (exact_max_pool, cluster_rows, max_rows,
        max_candidates, random_share).
    max_work : float, optional
        Flops the pool's posterior sds may take (N n^2 exactly); past it they are bounded
        where |s| >= ``SCORE_DECIDED_Z`` (``_predict``), and J's pool-wide conditioning
        skips those rows. None: exact whatever it costs. ``plan["pool_sds"]`` says which.
    local_obs : int, optional
        The approximate plan's greedies, past this many observations and where the
        candidates' factors (candidates x n^2 flops) exceed ``max_work``, work on the GP
        conditioned on the ``local_obs`` observations nearest their cluster (a posterior
        with ``nearest``), with its variances (``greedy_cluster``'s
        ``sds_from_posterior``) and the whole model's means. Every candidate's factor then
        costs local_obs^2 instead of n^2: a million segments after an estimate stage
        (14,654 observations, two million candidates) took hours without it.
        ``plan["local_observations"]`` says so. None: on the whole posterior.
    moments : (mu, sigma2, how), optional
        The pool's posterior means and variances when known already, and how they were
        got (``_predict``'s third value, ``"method"`` "exact" or "bounded"): ``select``
        passes the scores ``fit`` wrote for the same posterior at a scale where computing
        them again costs minutes.

    Returns
    -------
    SelectionResult
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    X = np.ascontiguousarray(X, dtype=np.float64)
    if X.ndim != 2:
        raise ValueError(f"X must be 2-d (N, d); got shape {X.shape}")
    N = len(X)
    n_levels = int(posterior.n_levels)
    costs_arr = np.asarray(costs, dtype=np.float64)
    if costs_arr.shape != (n_levels,):
        raise ValueError(
            f"costs must give one cost per fidelity level: the posterior has {n_levels} "
            f"levels, got {costs_arr.shape[0] if costs_arr.ndim else 'a scalar'}"
        )
    if not np.all(costs_arr > 0):
        raise ValueError(f"costs must be positive; got {costs_arr.tolist()}")
    if not budget > 0:
        raise ValueError(f"budget must be positive; got {budget}")
    if overbudget < 1:
        raise ValueError(f"overbudget (eta) must be >= 1; got {overbudget}")
    if pooling not in ("global", "raw"):
        raise ValueError(f"pooling must be 'global' or 'raw'; got {pooling!r}")
    allowed = np.zeros(n_levels, dtype=bool)
    chosen = list(range(n_levels)) if levels is None else [int(lev) for lev in levels]
    if not chosen or any(not 0 <= lev < n_levels for lev in chosen):
        raise ValueError(f"levels must be a non-empty subset of 0..{n_levels - 1}; got {levels}")
    allowed[chosen] = True
    cand = np.broadcast_to(allowed, (N, n_levels)).copy()
    if observed_level0_mask is not None:
        obs0 = np.asarray(observed_level0_mask, dtype=bool)
        if obs0.shape != (N,):
            raise ValueError(f"observed_level0_mask must have shape ({N},); got {obs0.shape}")
        if not reobserve_level0:
            cand[obs0, 0] = False
    if excluded_pairs is not None:
        gone = np.asarray(excluded_pairs, dtype=bool)
        if gone.shape != (N, n_levels):
            raise ValueError(f"excluded_pairs must have shape ({N}, {n_levels}); got {gone.shape}")
        cand &= ~gone
    pending = np.zeros((N, n_levels), dtype=bool)
    if pending_pairs is not None:
        pending = np.asarray(pending_pairs, dtype=bool)
        if pending.shape != (N, n_levels):
            raise ValueError(
                f"pending_pairs must have shape ({N}, {n_levels}); got {pending.shape}"
            )
        cand &= ~pending
    p_idx, p_lev = (a.astype(np.int64) for a in np.nonzero(pending))

    def report(phase: str, done: int, total: int) -> None:
        if progress is not None:
            progress(phase, done, total)

    # Posterior at the pool.
    t = time.perf_counter()
    report("predict", 0, 1)
    pool_sds: dict[str, Any] | None
    if moments is not None:
        mu, sigma2, pool_sds = moments
        if mu.shape != (N,) or sigma2.shape != (N,):
            raise ValueError(f"moments must hold two arrays of shape ({N},)")
    else:
        with threadpool_limits(limits=_pool_blas_threads(posterior), user_api="blas"):
            mu, sigma2, pool_sds = _predict(posterior, X, gamma, max_work, report)
    s = margin(mu, sigma2, gamma)
    bounded = pool_sds is not None and pool_sds.get("method") == "bounded"
    decided_z = defaults.SCORE_DECIDED_Z if bounded else None
    report("predict", 1, 1)
    timings["predict"] = time.perf_counter() - t

    plan = plan_selection(N, n_levels, n_clusters, approximate=approximate, **(plan_options or {}))

    # Algorithm 2.
    t = time.perf_counter()
    report("cluster", 0, 1)
    labels = cluster_pool(
        X,
        posterior.lengthscales0,
        plan.n_clusters,
        n_init_clusters=n_init_clusters,
        rng=rng,
        fit_max=plan.cluster_fit_max,
    )
    n_cl = int(labels.max()) + 1 if N else 0
    members = [np.flatnonzero(labels == k) for k in range(n_cl)]
    report("cluster", 1, 1)
    timings["cluster"] = time.perf_counter() - t

    biggest = max((len(r) * int((cand | pending)[r].sum()) * 8 for r in members), default=0)
    limit = (plan_options or {}).get("max_cluster_bytes")
    limit = MAX_CLUSTER_BYTES if limit is None else limit
    if plan.exact and biggest > limit:
        if approximate == "never":
            raise ValueError(
                f"the largest cluster needs {biggest / 2**30:.1f} GiB for its rows x candidates "
                f"covariance (limit {limit / 2**30:.2g} GiB); raise n_clusters"
            )
        # Too big for exact even on a small pool (few clusters asked): the same clusters,
        # approximately.
        approx = plan_selection(N, n_levels, n_cl, approximate="always", **(plan_options or {}))
        plan = SelectionPlan(
            False,
            n_cl,
            approx.max_rows,
            approx.max_candidates,
            approx.random_share,
            f"approximate: the exact greedy's largest cluster needs {biggest / 2**30:.1f} GiB "
            f"(limit {limit / 2**30:.2g} GiB)",
            screen_rounds=approx.screen_rounds,
        )
    report(f"plan: {plan.describe()}", 1, 1)

    # Algorithm 1, first loop: one greedy per cluster.
    t = time.perf_counter()
    # Local models only where the whole one's screen is out of reach: every candidate's
    # factor costs n^2, and past max_work that is hours (a million segments, 14,654
    # observations: 4e14). Below it the whole model is kept: on a 10,000-segment sample of
    # that study the local greedies (2,000 or 4,000 observations) took 78% of the whole
    # model's J decrease, all of it at the cheap level.
    n_obs = _n_obs(posterior)
    local = (
        not plan.exact
        and local_obs is not None
        and max_work is not None
        and hasattr(posterior, "nearest")
        and n_obs > local_obs
        and float(np.count_nonzero(cand)) * n_obs * n_obs > max_work
    )
    plan_seed = int(rng.integers(2**31 - 1)) if not plan.exact else 0
    # A worker's share is 9/4 of the covariance limit (``pipeline.selection.cluster_bytes``):
    # the covariance, as much again in temporaries, a quarter for the posterior's factors.
    # The approximate plan's covariance is its rows x candidates only, and the factors
    # (a cluster's every point, at thousands of observations) may take the rest.
    held = limit if plan.exact else 8 * (plan.max_rows or 0) * (plan.max_candidates or 0)
    factor_bytes = int(min(FACTOR_CACHE_BYTES, 9 * limit / 4 - 2 * held))
    jobs = []
    for k, r in enumerate(members):
        # ceil(eta m N_s / N); the 1e-9 stops float error from lifting an exact integer
        # (15 * 10000 / 30000 = 5) to the next one.
        b_k = float(math.ceil(overbudget * budget * len(r) / N - 1e-9))
        # A local posterior is made here, not in the worker: a worker is sent the small
        # model only (the whole one's factor was 1.7 GB a task at 14,654 observations).
        post_k = posterior
        if local:
            post_k = posterior.nearest(X[r], local_obs)  # type: ignore[attr-defined]
            report("local models", k + 1, n_cl)
        args = (post_k, X[r], r, mu[r], sigma2[r], cand[r])
        kwargs: dict[str, Any] = dict(
            gamma=gamma,
            costs=costs_arr,
            budget=b_k,
            cluster=k,
            row_drop_rtol=row_drop_rtol,
            forced_mask=pending[r] if len(p_idx) else None,
            factor_bytes=factor_bytes,
        )
        if not plan.exact:
            kwargs |= dict(
                max_rows=plan.max_rows,
                max_candidates=plan.max_candidates,
                random_share=plan.random_share,
                seed=plan_seed,
                screen_rounds=plan.screen_rounds,
                sds_from_posterior=local,
            )
        jobs.append((args, kwargs))
    report("greedy", 0, n_cl)
    queues: list[ClusterQueue] = []
    if executor is None:
        for i, (args, kwargs) in enumerate(jobs):
            queues.append(greedy_cluster(*args, **kwargs))
            report("greedy", i + 1, n_cl)
    else:
        # Largest clusters first: with fewer workers than clusters this evens out the tail.
        order = sorted(range(n_cl), key=lambda k: -len(members[k]))
        futures: dict[int, Any] = {}
        shown = 0
        for k in order:
            futures[k] = executor.submit(greedy_cluster, *jobs[k][0], **jobs[k][1])
            done = sum(f.done() for f in futures.values())  # an inline executor: all
            if done > shown:
                shown = done
                report("greedy", shown, n_cl)
        for i, k in enumerate(order):
            futures[k].result()
            if i + 1 > shown:
                shown = i + 1
                report("greedy", shown, n_cl)
        queues = [futures[k].result() for k in range(n_cl)]
    timings["greedy"] = time.perf_counter() - t
    for phase in ("build", "screen", "exact", "update", "plan", "cpu"):
        timings[f"greedy.{phase}"] = sum(q.timings.get(phase, 0.0) for q in queues)

    # Algorithm 1, second loop.
    t = time.perf_counter()
    report("pool", 0, 1)
    weights = [q.n_rows / N for q in queues]
    global_dj = [w * q.delta_j for w, q in zip(weights, queues, strict=True)]
    if pooling == "global":
        keys = [dj / q.cost for dj, q in zip(global_dj, queues, strict=True)]
    else:
        keys = [q.delta_j for q in queues]
    q_idx, q_pos = pool_queues(
        [q.cost for q in queues],
        keys,
        [q.index for q in queues],
        [q.level for q in queues],
        float(budget),
    )
    index = np.array(
        [queues[c].index[p] for c, p in zip(q_idx, q_pos, strict=True)], dtype=np.int64
    )
    level = np.array(
        [queues[c].level[p] for c, p in zip(q_idx, q_pos, strict=True)], dtype=np.int64
    )
    delta_j = np.array(
        [global_dj[c][p] for c, p in zip(q_idx, q_pos, strict=True)], dtype=np.float64
    )
    cost = np.array(
        [queues[c].cost[p] for c, p in zip(q_idx, q_pos, strict=True)], dtype=np.float64
    )
    score = np.array([keys[c][p] for c, p in zip(q_idx, q_pos, strict=True)], dtype=np.float64)
    report("pool", 1, 1)
    timings["pool"] = time.perf_counter() - t

    # J before and after the batch, given the pending pairs: exact, or past max_work (an
    # estimate stage's thousands of pending picks at a million segments) conditioned
    # cluster by cluster, an upper bound, both the same way so that they compare.
    # Decided on the pairs actually given, once the batch is known.
    after_idx = np.concatenate([p_idx, index])
    after_lev = np.concatenate([p_lev, level])
    j_by_cluster = _j_by_cluster(posterior, s, len(after_idx), decided_z, max_work)
    by = labels if j_by_cluster else None
    t = time.perf_counter()
    report("j_after", 0, 1)
    j_before, j_after = _j_nested(
        posterior, X, s, sigma2, after_idx, after_lev, len(p_idx), decided_z, by
    )
    if not len(p_idx):  # J given nothing: h_n itself, as select has always reported it
        j_before = float(point_variance(s).mean())
    report("j_after", 1, 1)
    timings["j_after"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_start

    stats: dict[str, int] = {"clusters": n_cl, "picks_planned": sum(len(q.index) for q in queues)}
    for key in ("rows_screened", "rows_dropped", "candidates", "exact_evaluations"):
        stats[key] = sum(q.stats.get(key, 0) for q in queues)
    plan_summary: dict[str, Any] = {
        "exact": plan.exact,
        "reason": plan.reason,
        "clusters": n_cl,
        "max_rows_per_cluster": plan.max_rows,
        "max_candidates_per_cluster": plan.max_candidates,
        "random_share": plan.random_share if not plan.exact else None,
        "screen_rounds": plan.screen_rounds if not plan.exact else None,
        "cluster_fit_sample": plan.cluster_fit_max
        if plan.cluster_fit_max is not None and plan.cluster_fit_max < N
        else None,
        "candidates_offered": int(sum(q.stats.get("candidates_offered", 0) for q in queues))
        if not plan.exact
        else stats["candidates"],
        "candidates_kept": stats["candidates"],
        "candidates_per_round": max(
            (q.stats.get("candidates_per_round", 0) for q in queues), default=0
        )
        if not plan.exact
        else None,
        "rows_live": int(sum(q.stats.get("rows_live", 0) for q in queues))
        if not plan.exact
        else None,
        "rows_in_j": int(sum(q.stats.get("rows_in_j", 0) for q in queues))
        if not plan.exact
        else None,
        # Largest share of a cluster's sum h_n on rows left out of its J: a bound on how
        # much of any Delta J_s the approximation can miss through rows.
        "h_left_out": max((q.stats.get("h_left_out_ppb", 0) for q in queues), default=0) / 1e9
        if not plan.exact
        else None,
        # How the pool's sds were got: exact, or bounded where gamma is decided (_predict).
        "pool_sds": pool_sds or {"method": "exact", "rows": N},
        # The observations each cluster's greedy conditioned on, when fewer than all.
        "local_observations": local_obs if local else None,
        # J before and after conditioned cluster by cluster (an upper bound, _j_given).
        "j_by_cluster": j_by_cluster,
    }

    return SelectionResult(
        index=index,
        level=level,
        delta_j=delta_j,
        cost=cost,
        cluster=q_idx,
        rank=np.arange(len(index), dtype=np.int64),
        score=score,
        j_before=j_before,
        j_after=j_after,
        gamma=float(gamma),
        labels=labels,
        timings=timings,
        stats=stats,
        queues=queues,
        plan=plan_summary,
    )
