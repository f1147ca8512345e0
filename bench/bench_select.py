"""Benchmark ``select_batch`` at the paper's AV scale and at fleet scale.

DESIGN.md, "Where the time goes"; issue 16.

Setting: the av_like sample data (``bams_cli.core.synthetic.av_like``) at N in {45k, 200k}
(and 1M with --million), its 512-d embeddings reduced to d = 12 by PCA; two levels with
costs [1, 5/32]; budget m = 15; S = 6 clusters asked and eta = 2, as ``bams-cli select``
runs by default; 30 observations (20 at level 0, 10 at level 1) at random pool points, with
the data set's true values; gamma is its 1% quantile. The GP is ``bams_cli.core.gp.MFGP``
with hyperparameters fitted once by MAP on the 30 observations at N = 2000 and then held
fixed for every N. Per-cluster greedies run in a 2-process pool, as ``bams-cli select``
runs them. ``select_batch`` chooses its plan itself (``core.select.plan_selection``): exact
up to ``defaults.SELECT_EXACT_MAX_POOL`` (20,000) segments, approximate above.

    .venv/bin/python bench/bench_select.py                       # 45k and 200k, 3 runs each
    nice .venv/bin/python bench/bench_select.py --million --pool-cache /tmp/bams-pools
    .venv/bin/python bench/bench_select.py --sizes 45000 --hyper flat   # worst case
    .venv/bin/python bench/bench_select.py --sweep --sizes 10000 25000 45000 \
        --pool-cache /tmp/bams-pools --caps 1024:1024:3 1024:1024:1   # J ratio per problem

For every N it prints the plan taken, the median wall time over --runs runs, the peak
resident memory of the process tree (this process plus the pool's workers, sampled every
20 ms from /proc), each phase's share of one run, and the load average (the machine is
shared: CPU seconds are the steadier number). "greedy.*" lines are seconds summed over
clusters (they overlap in time across the two processes).

--sweep's --caps are ROWS:CANDIDATES[:ROUNDS] per cluster, ROUNDS the times the candidates
are screened as the greedy spends the budget (``plan_selection``'s ``screen_rounds``;
default ``defaults.SELECT_SCREEN_ROUNDS``). Measured 2026-11-23 (load 6-10, README
"Performance"): 1024:1024:3, the default plan, kept >= 99.3% of the exact greedy's J
decrease on av_like, toy2d, weak_cheap and gap_sim at 10k, 25k and 45k, in 5.1-5.4 CPU s at
45k; 1024:1024:1 kept 95.8% (toy2d, 45k) to 100%.

J ratio (--j-ratio, on by default): where the exact greedy is feasible (N <= 45k), the same
pool and clusters are selected again with the other plan forced (the approximate one,
``approximate="always"``, where the default ran exactly; the exact greedy,
``approximate="never"``, where it did not), and the ratio of the two batches' exact J
decreases (J before minus J after, all picks conditioned on jointly) is printed. The
approximation's promise is a ratio >= 0.99.

Reference (--reference, on by default): the exact greedy written densely in numpy with
``scipy.special.owens_t`` (``reference_greedy``: beta for every row and candidate at every
pick, no screening, no compiled code) on one cluster of the first N, timed against
``greedy_cluster`` on the same cluster in the same process. It reports the time ratio,
whether the picks are identical, and the ratio of the two greedies' J decreases (1 for
an exact method). A cluster of the approximate plans (25k rows x 50k candidates) would
need a 10 GB dense covariance, so the reference runs on the first N only.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np
from scipy.special import owens_t

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from bams_cli.core.select import (  # noqa: E402
    V_TINY_REL,
    _predict,
    greedy_cluster,
    select_batch,
)

D = 12
COSTS = [1.0, 5 / 32]
BUDGET = 15.0
#: The exact greedy runs within minutes up to here (the paper's pool); --j-ratio compares.
EXACT_FEASIBLE = 45_000


def cached_pool(n: int, cache: str | None, seed: int = 0):
    """``make_pool(n)``, kept as .npz in ``cache`` when given (1M takes ~2 min to make)."""
    if cache is None:
        return make_pool(n, seed)
    path = os.path.join(cache, f"av_like-{n}-{seed}.npz")
    if not os.path.exists(path):
        os.makedirs(cache, exist_ok=True)
        X, obs, lev, y, gamma = make_pool(n, seed)
        np.savez(path, X=X, obs=obs, lev=lev, y=y, gamma=gamma)
    f = np.load(path)
    return f["X"], f["obs"], f["lev"], f["y"], float(f["gamma"])


def make_pool(n: int, seed: int = 0):
    """The av_like sample data at size n: 512-d embeddings reduced to 12-d by PCA."""
    from sklearn.decomposition import PCA

    from bams_cli.core.synthetic import av_like

    pool = av_like(n, seed)
    E = pool.features
    X = PCA(D, random_state=0).fit_transform((E - E.mean(0)) / E.std(0))
    rng = np.random.default_rng([seed, n])
    obs = rng.choice(n, size=30, replace=False)
    lev = np.r_[np.zeros(20, dtype=np.int64), np.ones(10, dtype=np.int64)]
    y = pool.truth[obs, lev]  # level 1: the 25th percentile of 5 of the 32 rollouts
    return X, obs, lev, y, pool.gamma


# "flat": hand-set hyperparameters under which the GP is unsure almost everywhere (isotropic
# lengthscale 3, output variance 0.5), so no row can be left out of the screening: the
# worst case for the selection loop.
FLAT = dict(mean=3.0, outputscale0=0.5, ell0=3.0, outputscale1=0.02, ell1=4.0, noise=(1e-3, 0.02))


def make_posterior(X, obs, lev, y, hp=None, hyper="map"):
    try:
        from bams_cli.core.gp import Hyperparameters, fit_mfgp
    except ImportError:  # gp.py not there: the dense test posterior, flat hyperparameters
        from tests.core.dense_posterior import DensePosterior

        ell = np.vstack([np.full(D, FLAT["ell0"]), np.full(D, FLAT["ell1"])])
        scales = np.array([FLAT["outputscale0"], FLAT["outputscale1"]])
        post = DensePosterior(X[obs], lev, y, ell, scales, np.array(FLAT["noise"]), FLAT["mean"])
        return post, None
    if hp is None and hyper == "flat":
        hp = Hyperparameters(
            mean=FLAT["mean"],
            outputscale0=FLAT["outputscale0"],
            lengthscales0=np.full(D, FLAT["ell0"]),
            outputscales=np.array([FLAT["outputscale1"]]),
            lengthscales=np.full((1, D), FLAT["ell1"]),
            noise=np.array(FLAT["noise"]),
        )
    if hp is None:
        post = fit_mfgp(X[obs], lev, y, 2, rng=np.random.default_rng(0), restarts=4)
        return post, post.hyperparameters
    return fit_mfgp(X[obs], lev, y, 2, rng=np.random.default_rng(0), fixed=hp), hp


def problem_pool(name: str, n: int, cache: str | None = None, seed: int = 0):
    """A pool of ``name`` at size n, as the J-ratio sweep uses it (``--sweep``).

    av_like as ``make_pool``; toy2d (2-d) as it is; the suite problems (``core.suite``)
    reduced to at most D dimensions by PCA like av_like. 30 observations (20 at level 0,
    10 at level 1) at random pool points with the problem's true values. Returns
    X, obs, lev, y, gamma, costs.
    """
    from sklearn.decomposition import PCA

    from bams_cli.core import suite, synthetic

    if name == "av_like":
        X, obs, lev, y, gamma = cached_pool(n, cache, seed)
        return X, obs, lev, y, gamma, COSTS
    gen = synthetic.toy2d if name == "toy2d" else getattr(suite, name)
    pool = gen(n, seed)
    E = pool.features
    if E.shape[1] > D:
        E = PCA(D, random_state=0).fit_transform((E - E.mean(0)) / E.std(0))
    rng = np.random.default_rng([seed, n])
    obs = rng.choice(n, size=30, replace=False)
    lev = np.r_[np.zeros(20, dtype=np.int64), np.ones(10, dtype=np.int64)]
    return np.ascontiguousarray(E), obs, lev, pool.truth[obs, lev], pool.gamma, pool.costs


def sweep(args, ex) -> None:
    """J ratio and time of the approximate plan against the exact greedy, per pool and caps.

    For every problem and size: the GP fitted by MAP on the pool's 30 observations, the
    exact greedy's batch, then the approximate plan forced with each --caps ROWS:CANDIDATES
    (same rng seed: same clusters at these sizes), its batch's exact J decrease over the
    exact greedy's, its wall and CPU seconds (median over --runs) and the load.
    """
    from bams_cli.core.gp import fit_mfgp

    print("problem      N       plan          J ratio  wall s  CPU s  load")
    for name in args.problems:
        for n in args.sizes:
            X, obs, lev, y, gamma, costs = problem_pool(name, n, args.pool_cache)
            post = fit_mfgp(X[obs], lev, y, 2, rng=np.random.default_rng(0), restarts=2)
            obs0 = np.zeros(n, dtype=bool)
            obs0[obs[lev == 0]] = True

            def run(approximate, opts=None, X=X, post=post, obs0=obs0, gamma=gamma, costs=costs):
                load = os.getloadavg()[0]
                c0, t0 = time.process_time(), time.perf_counter()
                res = select_batch(
                    post,
                    X,
                    gamma=gamma,
                    costs=costs,
                    budget=BUDGET,
                    n_clusters=args.clusters,
                    overbudget=args.overbudget,
                    observed_level0_mask=obs0,
                    executor=ex,
                    rng=np.random.default_rng(0),
                    approximate=approximate,
                    plan_options=opts,
                )
                wall = time.perf_counter() - t0
                return res, wall, time.process_time() - c0 + res.timings["greedy.cpu"], load

            # The exact greedy's batch is kept with --pool-cache (45k takes minutes on a
            # busy machine); its decrease does not depend on the approximate plans swept.
            key = f"exact-{name}-{n}-S{args.clusters}-eta{args.overbudget:g}.json"
            path = os.path.join(args.pool_cache, key) if args.pool_cache else None
            if path and os.path.exists(path):
                with open(path) as f:
                    dec, wall, cpu, load = json.load(f)
            else:
                exact, wall, cpu, load = run("never")
                dec = exact.j_before - exact.j_after
                if path:
                    os.makedirs(args.pool_cache, exist_ok=True)
                    with open(path, "w") as f:
                        json.dump([dec, wall, cpu, load], f)
            print(f"{name:<12} {n:<7} exact         1.0000  {wall:6.1f} {cpu:6.1f}  {load:.2f}")
            for cap in args.caps:
                r, c, *rounds = (int(v) for v in cap.split(":"))
                opts = dict(max_rows=r, max_candidates=c)
                if rounds:
                    opts["screen_rounds"] = rounds[0]
                if args.cluster_fit_max:
                    opts["cluster_fit_max"] = args.cluster_fit_max
                runs = [run("always", opts) for _ in range(args.runs)]
                res = runs[0][0]
                ratio = (res.j_before - res.j_after) / dec
                med = statistics.median(w for _, w, _, _ in runs)
                cpus = statistics.median(c for _, _, c, _ in runs)
                print(
                    f"{name:<12} {n:<7} {cap:<13} {ratio:7.4f}  {med:6.1f} {cpus:6.1f}  "
                    f"{runs[0][3]:.2f}",
                    flush=True,
                )


class PeakRSS:
    """Peak resident memory (MB) of this process and all its descendants, sampled from /proc.

    ru_maxrss gives one process's peak; the workers of a process pool hold their clusters'
    matrices at the same time as the parent holds the pool, so the sum is what the machine
    must have.
    """

    def __init__(self, interval: float = 0.02) -> None:
        self.interval, self.peak, self._stop = interval, 0.0, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def _tree(pid: int) -> list[int]:
        out, todo = [], [pid]
        while todo:
            p = todo.pop()
            out.append(p)
            try:
                for task in os.listdir(f"/proc/{p}/task"):
                    with open(f"/proc/{p}/task/{task}/children") as f:
                        todo += [int(c) for c in f.read().split()]
            except OSError:
                pass
        return out

    @staticmethod
    def _rss_mb(pid: int) -> float:
        try:
            with open(f"/proc/{pid}/statm") as f:
                return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
        except OSError:
            return 0.0

    def _run(self) -> None:
        while not self._stop.is_set():
            total = sum(self._rss_mb(p) for p in self._tree(os.getpid()))
            self.peak = max(self.peak, total)
            self._stop.wait(self.interval)

    def __enter__(self) -> PeakRSS:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


def reference_greedy(post, X, rows, mu, sigma2, cand, gamma, costs, budget, block=256):
    """The exact per-cluster greedy, densely: every row x every candidate through owens_t.

    Written from DESIGN.md alone (no code shared with ``select``): C = cov(theta0(rows),
    y_cands), V = var(y_cands); at each pick, for every candidate c,
    t_c(x) = t_S(x) - C(x, c)^2 / (V(c) sigma_n^2(x)) and
    Delta_c = sum_x beta(s_x, t_S(x)) - beta(s_x, t_c(x)), beta = 2 T(s, sqrt(t / (2 - t)));
    take the best Delta_c / c_l among candidates that fit (ties: lowest candidate index),
    then condition everything on it by one rank-1 step. Candidates are processed in
    column blocks so memory stays at C plus a rows x block temporary.

    Returns pool indices, levels and the picks' Delta J (mean over the cluster's rows).
    """
    cr, cl = np.nonzero(cand)
    Xc = X[cr]
    n_s = len(rows)
    C = post.cov_theta0_obs(X, Xc, cl)  # rows x candidates, dense
    V = post.obs_var(Xc, cl).astype(np.float64)
    alive = V > V_TINY_REL * V.max()
    picked = np.zeros(len(cr), bool)
    live = sigma2 > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(live, (gamma - mu) / np.sqrt(np.where(live, sigma2, 1.0)), 0.0)
    s, sig2 = s[live], sigma2[live]
    C = C[live]
    tS = np.ones(len(s))

    def b(t):
        t = np.clip(t, 0.0, 1.0)
        return 2.0 * owens_t(s[:, None] if t.ndim == 2 else s, np.sqrt(t / (2.0 - t)))

    v_floor = V_TINY_REL * V.max()
    used: list[float] = []
    G_hist: list[np.ndarray] = []
    V_hist: list[float] = []
    out_i, out_l, out_dj = [], [], []
    while True:
        fits = np.array([math.fsum([*used, c]) <= budget for c in costs])[cl]
        elig = np.flatnonzero(alive & ~picked & fits)
        if not len(elig):
            break
        bS = b(tS)
        best, best_sc, best_dec = -1, -np.inf, 0.0
        for j0 in range(0, len(elig), block):
            B = elig[j0 : j0 + block]
            t = tS[:, None] - C[:, B] ** 2 / (V[B][None, :] * sig2[:, None])
            dec = (bS[:, None] - b(t)).sum(axis=0)
            sc = dec / costs[cl[B]]
            k = int(np.argmax(sc))  # first maximum: lowest index within the block
            if sc[k] > best_sc:
                best, best_sc, best_dec = int(B[k]), float(sc[k]), float(dec[k])
        out_i.append(int(rows[cr[best]]))
        out_l.append(int(cl[best]))
        out_dj.append(best_dec / n_s)
        used.append(float(costs[cl[best]]))
        g = post.cov_obs_obs(
            Xc[best : best + 1],
            cl[best : best + 1],
            Xc,
            cl,
            same=(np.arange(len(cr)) == best)[None],
        )[0]
        picked[best] = True
        Vs, col = V[best], C[:, best].copy()
        for gk, vk in zip(G_hist, V_hist, strict=True):  # g conditional on earlier picks
            g = g - (gk[best] / vk) * gk
        G_hist.append(g)
        V_hist.append(float(Vs))
        tS = np.clip(tS - col**2 / (Vs * sig2), 0.0, 1.0)
        for i0 in range(0, len(C), block):
            C[i0 : i0 + block] -= np.outer(col[i0 : i0 + block] / Vs, g)
        V = V - g**2 / Vs
        alive &= V > v_floor
    return np.array(out_i), np.array(out_l), np.array(out_dj)


def run_reference(post, X, obs0, gamma, labels, which: str) -> None:
    """Time greedy_cluster and reference_greedy on one cluster; compare their picks."""
    sizes = np.bincount(labels)
    k = int(np.argmin(sizes) if which == "smallest" else np.argmax(sizes))
    rows = np.flatnonzero(labels == k)
    costs = np.asarray(COSTS)
    budget = float(math.ceil(BUDGET * len(rows) / len(X) - 1e-9))  # as select_batch, eta = 1
    cand = np.ones((len(rows), 2), dtype=bool)
    cand[obs0[rows], 0] = False
    mu, sigma2, _ = _predict(post, X[rows])
    args = (post, X[rows], rows, mu, sigma2, cand)
    t0, c0 = time.perf_counter(), time.process_time()
    q = greedy_cluster(*args, gamma=gamma, costs=costs, budget=budget)
    t_fast, c_fast = time.perf_counter() - t0, time.process_time() - c0
    t0, c0 = time.perf_counter(), time.process_time()
    idx, lev, dj = reference_greedy(post, X[rows], rows, mu, sigma2, cand, gamma, costs, budget)
    t_ref, c_ref = time.perf_counter() - t0, time.process_time() - c0
    same = np.array_equal(q.index, idx) and np.array_equal(q.level, lev)
    print(
        f"\nreference on cluster {k} ({which}: {len(rows)} rows, {int(cand.sum())} candidates, "
        f"budget {budget:g}, {len(idx)} picks); load {os.getloadavg()[0]:.2f}"
    )
    print(f"  greedy_cluster      {t_fast:8.2f} s wall {c_fast:8.2f} s CPU")
    print(f"  dense numpy+owens_t {t_ref:8.2f} s wall {c_ref:8.2f} s CPU")
    print(
        f"  ratio (reference / greedy_cluster): {t_ref / t_fast:.1f}x wall, {c_ref / c_fast:.1f}x CPU"
    )
    print(
        f"  picks identical: {same}; J-decrease ratio (greedy_cluster / reference): "
        f"{math.fsum(q.delta_j.tolist()) / math.fsum(dj.tolist()):.12f}"
    )


def select(post, X, obs0, gamma, args, ex, seed, approximate="auto"):
    return select_batch(
        post,
        X,
        gamma=gamma,
        costs=COSTS,
        budget=BUDGET,
        n_clusters=args.clusters,
        overbudget=args.overbudget,
        observed_level0_mask=obs0,
        row_drop_rtol=args.row_drop_rtol,
        executor=ex,
        rng=np.random.default_rng(seed),
        approximate=approximate,
    )


def report_run(n, args, totals, cpus, peaks, loads, results) -> None:
    med = statistics.median(totals)
    k_med = int(np.argsort(totals)[len(totals) // 2])
    res = results[k_med]
    plan = res.plan
    print(
        f"\nN = {n}: median {med:.1f} s over {len(totals)} run(s) "
        f"(all: {', '.join(f'{t:.1f}' for t in totals)}); CPU s (parent + workers' "
        f"greedy): {', '.join(f'{c:.1f}' for c in cpus)}; peak RSS of the process "
        f"tree {max(peaks):.0f} MB; load average at each start: "
        f"{', '.join(f'{v:.2f}' for v in loads)}"
    )
    print(f"  plan: {'exact' if plan['exact'] else 'approximate'} ({plan['reason']}), {plan}")
    same = all(
        np.array_equal(r.index, results[0].index) and np.array_equal(r.level, results[0].level)
        for r in results
    )
    print(
        "  every run gave the same batch"
        if same
        else "  runs differ in their batch (K-means seeds differ per run)"
    )
    print(f"  phases of run {k_med + 1} ({totals[k_med]:.1f} s):")
    for phase in ("predict", "cluster", "greedy", "pool", "j_after"):
        v = res.timings[phase]
        name = "J before+after" if phase == "j_after" else phase  # one pass for both
        print(f"  {name:<14} {v:7.2f} s  {100 * v / res.timings['total']:5.1f} %")
    g = sum(res.timings[f"greedy.{p}"] for p in ("build", "screen", "exact", "update", "plan"))
    print(
        f"  greedy CPU     {res.timings['greedy.cpu']:7.2f} s  summed over clusters "
        f"(wall summed {g:.2f} s: the rest is waiting for a shared core)"
    )
    for p in ("plan", "build", "screen", "exact", "update"):
        v = res.timings[f"greedy.{p}"]
        print(f"  greedy.{p:<7} {v:7.2f} s  {100 * v / g:5.1f} % of summed greedy")
    n_lev = np.bincount(res.level, minlength=2)
    print(
        f"  picks: {len(res.index)} ({n_lev[0]} at level 0, {n_lev[1]} at level 1), "
        f"cost {res.total_cost:g}; planned {res.stats['picks_planned']}; "
        f"J {res.j_before:.4e} -> {res.j_after:.4e}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[45000, 200000])
    ap.add_argument("--million", action="store_true", help="also N = 1,000,000")
    ap.add_argument("--runs", type=int, default=3, help="runs per size (median reported)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--clusters", type=int, default=6, help="S asked (the plan may use more)")
    ap.add_argument("--overbudget", type=float, default=2.0, help="eta (bams-cli select: 2)")
    ap.add_argument(
        "--hyper",
        choices=["map", "flat"],
        default="map",
        help="map: fitted once on the 30 observations; flat: the worst case (see FLAT)",
    )
    ap.add_argument("--row-drop-rtol", type=float, default=1e-4)
    ap.add_argument("--pool-cache", default=None, help="folder to keep the made pools in")
    ap.add_argument("--no-reference", dest="reference", action="store_false")
    ap.add_argument("--no-j-ratio", dest="j_ratio", action="store_false")
    ap.add_argument("--reference-cluster", choices=["smallest", "largest"], default="smallest")
    ap.add_argument(
        "--sweep",
        action="store_true",
        help="J ratio and time of the approximate plan per --problems, --sizes and --caps",
    )
    ap.add_argument(
        "--problems",
        nargs="+",
        default=["av_like", "toy2d", "weak_cheap", "gap_sim"],
        help="--sweep: av_like, toy2d or a core.suite problem",
    )
    ap.add_argument(
        "--caps",
        nargs="+",
        default=["1024:1024:3", "1024:1024:1", "2048:2048:3"],
        help="--sweep: approximate plans as ROWS:CANDIDATES[:SCREEN_ROUNDS] per cluster",
    )
    ap.add_argument(
        "--cluster-fit-max", type=int, default=None, help="--sweep: plan's cluster_fit_max"
    )
    args = ap.parse_args()
    if args.sweep:
        with ProcessPoolExecutor(max_workers=args.workers) as ex:
            sweep(args, ex)
        return
    sizes = [*args.sizes, *([1_000_000] if args.million else [])]

    X, obs, lev, y, gamma = make_pool(2000)
    _, hp = make_posterior(X, obs, lev, y, hyper=args.hyper)
    print(f"hyperparameters ({args.hyper}; fitted at N = 2000 for map), held fixed: {hp}")
    print(f"machine: {os.cpu_count()} cpus, load average {os.getloadavg()}")

    first = None
    with ProcessPoolExecutor(max_workers=args.workers) as ex:
        # warm-up: import + load numba's cached kernels in every worker
        post, _ = make_posterior(X, obs, lev, y, hp)
        select_batch(
            post,
            X,
            gamma=gamma,
            costs=COSTS,
            budget=2.0,
            n_clusters=args.workers,
            executor=ex,
            rng=np.random.default_rng(0),
        )
        for n in sizes:
            X, obs, lev, y, gamma = cached_pool(n, args.pool_cache)
            post, _ = make_posterior(X, obs, lev, y, hp)
            obs0 = np.zeros(n, dtype=bool)
            obs0[obs[lev == 0]] = True
            totals, cpus, peaks, loads, results = [], [], [], [], []
            for k in range(args.runs):
                loads.append(os.getloadavg()[0])
                c0 = time.process_time()
                with PeakRSS() as mem:
                    t0 = time.perf_counter()
                    res = select(post, X, obs0, gamma, args, ex, k)
                    totals.append(time.perf_counter() - t0)
                cpus.append(time.process_time() - c0 + res.timings["greedy.cpu"])
                peaks.append(mem.peak)
                results.append(res)
            if first is None:
                first = (post, X, obs0, gamma, results[0].labels)
            report_run(n, args, totals, cpus, peaks, loads, results)
            if args.j_ratio and (results[0].plan["exact"] or n <= EXACT_FEASIBLE):
                # The other plan on the same pool and seed: the approximate one forced where
                # the default ran exactly, the exact greedy where it did not.
                other = "always" if results[0].plan["exact"] else "never"
                load = os.getloadavg()[0]
                with PeakRSS() as mem:
                    t0 = time.perf_counter()
                    forced = select(post, X, obs0, gamma, args, ex, 0, approximate=other)
                    t_forced = time.perf_counter() - t0
                exact, approx = (results[0], forced) if other == "always" else (forced, results[0])
                ratio = (approx.j_before - approx.j_after) / (exact.j_before - exact.j_after)
                print(
                    f"  J ratio: the {'approximate plan' if other == 'always' else 'exact greedy'}"
                    f" forced on this pool (run 1's clusters: "
                    f"{np.array_equal(approx.labels, exact.labels)}; {forced.plan}) took "
                    f"{t_forced:.1f} s, peak RSS {mem.peak:.0f} MB, load {load:.2f}; "
                    f"approximate batch's exact J decrease {approx.j_before - approx.j_after:.4e}"
                    f" vs the exact greedy's {exact.j_before - exact.j_after:.4e}: "
                    f"ratio {ratio:.4f}"
                )
    if args.reference and first is not None:
        run_reference(*first, args.reference_cluster)


if __name__ == "__main__":
    main()
