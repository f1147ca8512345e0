"""Benchmark the multifidelity GP: fit time, peak memory, scoring, and accuracy of conditioning.

Run: .venv/bin/python bench/bench_fit.py [--quick] [--sizes 1000,5000,20000,50000]
     .venv/bin/python bench/bench_fit.py --accuracy 5000 --keep 2500,3750

Fit: n observations, d = 12, two levels (40% level 0, 60% level 1, a third of the level-1
points at level-0 sites), 8 restarts. Each size runs in a fresh child process, so its peak
RSS (resource.getrusage ru_maxrss) is its own; wall and CPU seconds of the fit, then of
scoring a 45,000-point pool (three gammas). Above ``defaults.FIT_SUBSET`` observations the
MAP search runs on that many (``core.gp.fit_subset``); the model conditions exactly on all
of them while they fit ``defaults.FIT_CONDITION_MEMORY`` (14,654 observations), else
exactly on a subset of that many (``core.gp.fit.condition``): the "conditioned" column.
--exact also times the MAP search on all observations (sizes up to a few thousand).

--accuracy N: N av_like observations (60% level 1, PCA to d = 12 as embed-reduce does),
the exact posterior against the subset posterior that a budget for --keep observations
gives, at 4,000 pool points: |mean error| and sd excess in units of the exact sd, and the
factor sqrt(1 + T) by which a certificate could bound the subset's sd above the exact one
(T: the dropped observations' subset-posterior latent variances over their noise): 1.01
would certify the issue's 1%. With --local BLOCKS: each of BLOCKS k-means blocks of the pool
points conditioned on its own --keep most correlated observations instead, and how many
eigenvalues of the observations' prior covariance exceed 1, 0.1, 0.01 and 0.001 (the rank
a low-rank model would need).

Score (default run): the n = 200 and n = 500 models on N = 45,000 and 1,000,000 pool
points. Memory is the tracemalloc peak during score() plus the process's peak RSS.

--score-budget N_OBS,POOL: ``fit``'s scoring of a POOL-point pool against N_OBS observations
within ``defaults.SCORE_MAX_WORK`` (a million segments after an estimate stage's 12,000
level-0 runs: 12000,1000000): wall time, how it scored (``MFGP.score``'s ``scoring``), and
against the exact posterior on 2,000 pool points drawn at random and on the 2,000 whose mean
is nearest a threshold: the largest |p_n difference| and the sd's ratio to the exact one.

Targets: fit n <= 200 under 5 s, 1,000 under 10 s, 5,000 under 60 s, 50,000 under 5 min;
scoring 1,000,000 under 60 s and 2 GB. Wall and CPU seconds are both printed: the machine
is shared.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
import tracemalloc
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bams_cli.core.gp import MFGP, fit_mfgp  # noqa: E402
from bams_cli.core.gp.fit import BYTES_PER_ENTRY, condition  # noqa: E402

D = 12


def synthetic(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smooth level-0 metric plus a small smooth discrepancy and noise at level 1."""
    n0 = int(0.4 * n)
    X0 = rng.normal(size=(n0, D))
    n_shared = (n - n0) // 3
    X1 = np.vstack([X0[:n_shared], rng.normal(size=(n - n0 - n_shared, D))])
    X = np.vstack([X0, X1])
    levels = np.r_[np.zeros(n0, np.int64), np.ones(n - n0, np.int64)]
    w = np.linspace(1.0, 0.1, D)
    f = np.sin(X @ w / 2.0) + 0.3 * X[:, 0] ** 2
    y = f + levels * (0.2 * np.cos(X[:, 1]) + 0.1 * rng.normal(size=n))
    return X, levels, y


def child(n: int, seed: int) -> None:
    """One fit (and a 45k-pool score) in this process; prints one JSON line."""
    X, levels, y = synthetic(n, np.random.default_rng(seed))
    t, c = time.perf_counter(), time.process_time()
    model = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(seed), restarts=8)
    fit_wall, fit_cpu = time.perf_counter() - t, time.process_time() - c
    pool = np.random.default_rng(0).normal(size=(45_000, D))
    t, c = time.perf_counter(), time.process_time()
    _, sd, p = model.score(pool, np.array([-0.5, 0.0, 0.5]))
    score_wall, score_cpu = time.perf_counter() - t, time.process_time() - c
    assert np.all(np.isfinite(p)) and np.all(sd >= 0)
    out = {
        "n": n,
        "fitted_on": model.fitted_on,
        "conditioned_on": model.conditioning["conditioned_on"],
        "fit_wall": fit_wall,
        "fit_cpu": fit_cpu,
        "score_wall": score_wall,
        "score_cpu": score_cpu,
        "maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    print(json.dumps(out), flush=True)


def bench_sizes(sizes: list[int]) -> None:
    """Every size in a fresh process (its own peak RSS); one run each."""
    print(f"fit (d = {D}, two levels, restarts = 8, one run per size, fresh process each)")
    print(f"load: {os.getloadavg()[0]:.1f} (1-min load average, 2 cores)")
    print(
        f"{'n':>6} {'search on':>9} {'conditioned':>11} {'fit s':>7} {'fit CPU s':>9} "
        f"{'score 45k s':>11} {'score CPU s':>11} {'peak RSS MB':>11}"
    )
    for n in sizes:
        res = subprocess.run(
            [sys.executable, __file__, "--child", str(n)],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        r = json.loads(res.stdout.strip().splitlines()[-1])
        print(
            f"{n:>6} {r['fitted_on']:>9} {r['conditioned_on']:>11} {r['fit_wall']:>7.1f} "
            f"{r['fit_cpu']:>9.1f} {r['score_wall']:>11.1f} {r['score_cpu']:>11.1f} "
            f"{r['maxrss_mb']:>11.0f}",
            flush=True,
        )


@dataclass
class _Study:
    X: np.ndarray  # the pool, PCA coordinates
    Xo: np.ndarray  # the observed points
    lv: np.ndarray
    y: np.ndarray
    exact: MFGP
    seconds: float  # the exact fit's
    Xq: np.ndarray  # 4,000 pool points
    mu_e: np.ndarray
    sd_e: np.ndarray


def _exact_study(n: int) -> _Study:
    """n av_like observations (60% level 1, PCA to d = 12 as embed-reduce does), the GP
    fitted and conditioned exactly on all of them, and its posterior at 4,000 pool points."""
    from sklearn.decomposition import PCA

    from bams_cli.core.synthetic import av_like

    n_pool = max(4 * n, 8000)
    pool = av_like(n_pool, seed=0)
    X = PCA(D, random_state=0).fit_transform(pool.features)
    rng = np.random.default_rng(1)
    obs = rng.choice(n_pool, n, replace=False)
    lv = (rng.random(n) < 0.6).astype(np.int64)
    y = pool.truth[obs, lv]
    t = time.perf_counter()
    exact = fit_mfgp(X[obs], lv, y, 2, rng=np.random.default_rng(0), restarts=8, max_memory=None)
    seconds = time.perf_counter() - t
    Xq = X[rng.choice(n_pool, 4000, replace=False)]
    mu_e, s2_e = exact.predict_theta0(Xq)
    return _Study(X, X[obs], lv, y, exact, seconds, Xq, mu_e, np.sqrt(s2_e))


def bench_accuracy(n: int, keeps: list[int]) -> None:
    """Exact posterior against the budget's subset posterior on av_like (module docstring)."""
    st = _exact_study(n)
    Xo, lv, y, exact, Xq, mu_e, sd_e = st.Xo, st.lv, st.y, st.exact, st.Xq, st.mu_e, st.sd_e
    print(f"av_like, {n} observations ({int(np.sum(lv == 0))} at level 0), exact fit "
          f"{st.seconds:.1f} s; errors at 4,000 pool points in exact sds")  # fmt: skip
    print(
        f"{'kept':>6} {'|mean err| median':>17} {'p90':>6} {'max':>7} "
        f"{'sd excess median':>16} {'p90':>6} {'max':>6} {'min':>9} {'sd bound x':>13}"
    )
    for keep in keeps:
        sub = condition(
            Xo, lv, y, 2, exact.hyperparameters, max_memory=BYTES_PER_ENTRY * keep * keep
        )
        mu, s2 = sub.predict_theta0(Xq)
        em = np.abs(mu - mu_e) / sd_e
        es = (np.sqrt(s2) - sd_e) / sd_e
        # What a guarantee could say: with e_j the subset posterior's variance of dropped
        # observation j's latent and tau_j^2 its noise, var_exact >= var_subset / (1 + T),
        # T = sum_j e_j / tau_j^2 (the dropped block's covariance is >= its noise).
        dropped = np.setdiff1d(np.arange(n), sub.conditioned_rows)
        tau2 = exact.hyperparameters.noise[lv[dropped]]
        T = float(np.sum(sub.obs_var(Xo[dropped], lv[dropped]) / tau2 - 1.0))
        print(
            f"{keep:>6} {np.median(em):>17.3f} {np.quantile(em, 0.9):>6.2f} {em.max():>7.1f} "
            f"{np.median(es):>16.3f} {np.quantile(es, 0.9):>6.2f} {es.max():>6.1f} "
            f"{es.min():>9.1e} {np.sqrt(1.0 + T):>13.3g}",
            flush=True,
        )


def bench_local(n: int, keeps: list[int], blocks: int) -> None:
    """Exact posterior against block-local subsets, and the kernel matrix's spectrum.

    The query points are split into ``blocks`` by k-means; each block conditions exactly
    on the ``keep`` observations of largest prior level-0 covariance with any of its
    points (what a local or nearest-neighbour GP does). Then the eigenvalues of the
    observations' prior covariance: how many exceed a threshold is the rank a low-rank
    (Nystrom, inducing-point) model would need to hold the posterior to that precision.
    """
    from sklearn.cluster import KMeans

    from bams_cli.core.kernels import matern52

    st = _exact_study(n)
    X, Xo, lv, y, Xq, exact = st.X, st.Xo, st.lv, st.y, st.Xq, st.exact
    mu_e, sd_e, hp = st.mu_e, st.sd_e, exact.hyperparameters
    label = KMeans(blocks, n_init=1, random_state=0).fit_predict(Xq)
    print(f"av_like, {n} observations, level-0 noise {hp.noise[0]:.2g}, outputscale "
          f"{hp.outputscale0:.3g}, lengthscales {np.min(hp.lengthscales0):.3g}-"
          f"{np.max(hp.lengthscales0):.3g} (PCA coordinates of sd {X.std(axis=0).min():.2g}-"
          f"{X.std(axis=0).max():.2g}); {blocks} blocks of the 4,000 pool points; errors "
          "in exact sds")  # fmt: skip
    for keep in keeps:
        mu, s2 = np.empty(len(Xq)), np.empty(len(Xq))
        t = time.perf_counter()
        for b in range(blocks):
            q = np.flatnonzero(label == b)
            near = matern52(Xq[q], Xo, hp.lengthscales0, hp.outputscale0).max(axis=0)
            rows = np.argsort(-near)[:keep]
            mu[q], s2[q] = MFGP(Xo[rows], lv[rows], y[rows], 2, hp).predict_theta0(Xq[q])
        em = np.abs(mu - mu_e) / sd_e
        es = (np.sqrt(s2) - sd_e) / sd_e
        print(
            f"local {keep:>6}: |mean err| median {np.median(em):.3f} p90 "
            f"{np.quantile(em, 0.9):.3f} max {em.max():.2f}; sd excess median "
            f"{np.median(es):.4f} p90 {np.quantile(es, 0.9):.4f} max {es.max():.3f} "
            f"({time.perf_counter() - t:.1f} s)",
            flush=True,
        )
    K = exact._L @ exact._L.T
    K[np.diag_indices(n)] -= hp.noise[lv]
    w = np.linalg.eigvalsh(K)
    above = ", ".join(f"{int(np.sum(w > t))} > {t:g}" for t in (1.0, 1e-1, 1e-2, 1e-3))
    print(f"eigenvalues of the {n} x {n} prior covariance: {above}")


def bench_fit(sizes: list[int], repeats: int, exact: bool = False) -> dict[int, MFGP]:
    print(f"fit (d = {D}, two levels, restarts = 8, median of {repeats} up to n = 1,000)")
    print(f"{'n':>6} {'search on':>9} {'median s':>9} {'min s':>7} {'max s':>7} {'CPU s':>7}")
    models = {}
    grid = np.random.default_rng(99).normal(size=(2000, D))
    for n in sizes:
        times, cpu = [], []
        for seed in range(repeats if n <= 1000 else 1):
            X, levels, y = synthetic(n, np.random.default_rng(seed))
            t, c = time.perf_counter(), time.process_time()
            model = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(seed), restarts=8)
            times.append(time.perf_counter() - t)
            cpu.append(time.process_time() - c)
        models[n] = model
        print(
            f"{n:>6} {model.fitted_on:>9} {statistics.median(times):>9.2f} {min(times):>7.2f} "
            f"{max(times):>7.2f} {statistics.median(cpu):>7.2f}",
            flush=True,
        )
        if exact and model.fitted_on < n:
            t, c = time.perf_counter(), time.process_time()
            full = fit_mfgp(
                X, levels, y, 2, rng=np.random.default_rng(seed), restarts=8, max_fit=None
            )
            wall, cpu_s = time.perf_counter() - t, time.process_time() - c
            m_sub, _ = model.predict_theta0(grid)
            m_all, _ = full.predict_theta0(grid)
            diff = float(np.sqrt(np.mean((m_sub - m_all) ** 2)) / np.std(m_all))
            print(
                f"{n:>6} {n:>9} {wall:>9.2f} {'':>7} {'':>7} {cpu_s:>7.2f}"
                f"   subset vs all: RMS mean difference {diff:.3f} of sd(mean)",
                flush=True,
            )
    return models


def bench_score(models: list[MFGP], pools: list[int]) -> None:
    print(f"\nscore (d = {D}, 3 gammas, default chunk_size)")
    print(
        f"{'n_obs':>6} {'N':>10} {'seconds':>8} {'tracemalloc peak MB':>20} "
        f"{'process maxrss MB':>18}"
    )
    gammas = np.array([-0.5, 0.0, 0.5])
    for model in models:
        n_obs = model.X_train.shape[0]
        for N in pools:
            X = np.random.default_rng(0).normal(size=(N, D))
            tracemalloc.start()
            t = time.perf_counter()
            mu, sd, p = model.score(X, gammas)
            elapsed = time.perf_counter() - t
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            maxrss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB
            assert p.shape == (N, 3) and np.all(np.isfinite(p))
            print(f"{n_obs:>6} {N:>10,} {elapsed:>8.2f} {peak / 2**20:>20.0f} {maxrss_mb:>18.0f}")
            del X, mu, sd, p


def bench_score_budget(n_obs: int, N: int) -> None:
    from bams_cli import defaults

    rng = np.random.default_rng(0)
    X, levels, y = synthetic(n_obs, rng)
    model = fit_mfgp(X, levels, y, 2, rng=np.random.default_rng(0), restarts=2)
    pool = rng.normal(size=(N, D))
    gammas = np.quantile(model.predict_theta0(pool[:20_000])[0], [0.005, 0.02])
    t, c = time.perf_counter(), time.process_time()
    mu, sd, p = model.score(pool, gammas, max_work=defaults.SCORE_MAX_WORK)
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    scoring = dict(model.scoring)
    print(f"score {N:,} points against {n_obs:,} observations (d = {D}), gammas {gammas}")
    print(f"  wall {wall:.1f} s, CPU {cpu:.1f} s, exact would cost {N * n_obs**2:.2g} flops")
    print(f"  {json.dumps(scoring)}")
    gap = np.min(np.abs(gammas[None, :] - mu[:, None]), axis=1)
    for what, rows in [
        ("random", rng.choice(N, 2000, replace=False)),
        ("nearest a threshold", np.argsort(gap)[:2000]),
    ]:
        mu0, sd0, p0 = model.score(pool[rows], gammas)
        print(
            f"  {what:>20}: max |mu - exact| {np.max(np.abs(mu[rows] - mu0)):.1e}, "
            f"max |p_n - exact| {np.max(np.abs(p[rows] - p0)):.1e}, sd / exact "
            f"{np.min(sd[rows] / sd0):.4f} to {np.max(sd[rows] / sd0):.3f}",
            flush=True,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="n <= 200, one repeat, N = 45k")
    parser.add_argument("--sizes", type=str, default=None, help="comma-separated n to fit")
    parser.add_argument("--exact", action="store_true", help="also fit on all observations")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--accuracy", type=int, default=None, help="exact vs subset at this n")
    parser.add_argument("--keep", type=str, default=None, help="subset sizes for --accuracy")
    parser.add_argument(
        "--local", type=int, default=None, metavar="BLOCKS",
        help="with --accuracy: block-local subsets of --keep observations, and the spectrum",
    )  # fmt: skip
    parser.add_argument(
        "--score-budget", type=str, default=None, metavar="N_OBS,POOL",
        help="fit's scoring of POOL points against N_OBS observations within its flop budget",
    )  # fmt: skip
    args = parser.parse_args()
    if args.score_budget:
        n_obs, pool = (int(v) for v in args.score_budget.split(","))
        bench_score_budget(n_obs, pool)
        return
    if args.child is not None:
        child(args.child, 0)
        return
    if args.accuracy is not None:
        n = args.accuracy
        keeps = [int(k) for k in args.keep.split(",")] if args.keep else [n // 2, 3 * n // 4]
        if args.local:
            bench_local(n, keeps, args.local)
        else:
            bench_accuracy(n, keeps)
        return
    if args.sizes and not args.exact:
        bench_sizes([int(s) for s in args.sizes.split(",")])
        return
    sizes = [50, 200] if args.quick else [50, 200, 500, 1000, 5000]
    if args.sizes:
        sizes = [int(s) for s in args.sizes.split(",")]
    models = bench_fit(sizes, 1 if args.quick else 3, exact=args.exact)
    if args.sizes:
        return
    if args.quick:
        bench_score([models[200]], [45_000])
    else:
        bench_score([models[200], models[500]], [45_000, 1_000_000])


if __name__ == "__main__":
    main()
