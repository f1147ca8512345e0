"""Benchmark ``select_batch`` at the paper's AV scale (DESIGN.md "Where the time goes").

Setting: the av_like sample data (``bams_cli.core.synthetic.av_like``) at N in {5k, 20k,
45k}, its 512-d embeddings reduced to d = 12 by PCA; two levels with costs [1, 5/32];
budget m = 15; S = 6 clusters; 30 observations (20 at level 0, 10 at level 1) at random
pool points, with the data set's true values; gamma is its 1% quantile. The GP is
``bams_cli.core.gp.MFGP`` with hyperparameters fitted once by MAP on the 30 observations
and then held fixed for every N (falls back to the dense test posterior if gp.py is
missing). Per-cluster greedies run in a 2-process pool.

    .venv/bin/python bench/bench_select.py                 # 5k, 20k (3 runs), 45k (2 runs)
    .venv/bin/python bench/bench_select.py --sizes 5000 --runs 1
    .venv/bin/python bench/bench_select.py --hyper flat   # worst case: few rows can be dropped

Prints the median wall time per N and each phase's share of it. The "greedy.*" lines are
seconds summed over clusters (they overlap in time across the two processes); "greedy CPU"
is their CPU time, which on a shared machine is below their wall time.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from bams_cli.core.select import select_batch  # noqa: E402

D = 12
COSTS = [1.0, 5 / 32]
BUDGET = 15.0


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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[5000, 20000, 45000])
    ap.add_argument("--runs", type=int, nargs="+", default=None, help="runs per size")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--hyper",
        choices=["map", "flat"],
        default="map",
        help="map: fitted once on the 30 observations; flat: the worst case (see FLAT)",
    )
    ap.add_argument("--row-drop-rtol", type=float, default=1e-4)
    args = ap.parse_args()
    runs = args.runs or [3 if n < 40000 else 2 for n in args.sizes]
    if len(runs) == 1:
        runs = runs * len(args.sizes)

    X, obs, lev, y, gamma = make_pool(2000)
    _, hp = make_posterior(X, obs, lev, y, hyper=args.hyper)
    print(f"hyperparameters ({args.hyper}; fitted at N = 2000 for map), held fixed: {hp}")
    print(f"machine: {os.cpu_count()} cpus, load average {os.getloadavg()}")

    with ProcessPoolExecutor(max_workers=args.workers) as ex:
        # warm-up: import + load numba's cached kernel in every worker
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
        for n, r in zip(args.sizes, runs, strict=True):
            X, obs, lev, y, gamma = make_pool(n)
            post, _ = make_posterior(X, obs, lev, y, hp)
            obs0 = np.zeros(n, dtype=bool)
            obs0[obs[lev == 0]] = True
            totals, results = [], []
            for k in range(r):
                t0 = time.perf_counter()
                res = select_batch(
                    post,
                    X,
                    gamma=gamma,
                    costs=COSTS,
                    budget=BUDGET,
                    n_clusters=6,
                    observed_level0_mask=obs0,
                    row_drop_rtol=args.row_drop_rtol,
                    executor=ex,
                    rng=np.random.default_rng(k),
                )
                totals.append(time.perf_counter() - t0)
                results.append(res)
            med = statistics.median(totals)
            k_med = int(np.argsort(totals)[len(totals) // 2])
            res = results[k_med]
            print(
                f"\nN = {n}: median {med:.1f} s over {r} run(s) "
                f"(all: {', '.join(f'{t:.1f}' for t in totals)}); load {os.getloadavg()[0]:.2f}"
            )
            print(f"  phases of run {k_med + 1} ({totals[k_med]:.1f} s):")
            for phase in ("predict", "cluster", "greedy", "pool", "j_after"):
                v = res.timings[phase]
                print(f"  {phase:<14} {v:7.2f} s  {100 * v / res.timings['total']:5.1f} %")
            g = sum(res.timings[f"greedy.{p}"] for p in ("build", "screen", "exact", "update"))
            print(
                f"  greedy CPU     {res.timings['greedy.cpu']:7.2f} s  summed over clusters "
                f"(wall summed {g:.2f} s: the rest is waiting for a shared core)"
            )
            for p in ("build", "screen", "exact", "update"):
                v = res.timings[f"greedy.{p}"]
                print(f"  greedy.{p:<7} {v:7.2f} s  {100 * v / g:5.1f} % of summed greedy")
            n_lev = np.bincount(res.level, minlength=2)
            print(
                f"  picks: {len(res.index)} ({n_lev[0]} at level 0, {n_lev[1]} at level 1), "
                f"cost {res.total_cost:g}; planned {res.stats['picks_planned']}; "
                f"J {res.j_before:.3e} -> {res.j_after:.3e}"
            )
            print(
                f"  rows screened {res.stats['rows_screened']}, dropped "
                f"{res.stats['rows_dropped']}; candidates {res.stats['candidates']}; "
                f"exact evaluations {res.stats['exact_evaluations']}"
            )


if __name__ == "__main__":
    main()
