"""Benchmark the multifidelity GP: MAP fit time and pool-scoring time and memory.

Run: .venv/bin/python bench/bench_fit.py [--quick]

Fit: n = 50, 200, 500, 1,000 and 5,000 observations, d = 12, two levels (40% level 0, 60%
level 1, a third of the level-1 points at level-0 sites), 8 restarts, median of 3 runs with
different seeds (one run above 1,000; --sizes to choose). Above ``defaults.FIT_SUBSET``
observations the MAP search runs on that many (``core.gp.fit_subset``) and the model
conditions on all; --exact also times the search on all of them, and both fits' level-0
posterior means are compared on 2,000 pool points (RMS difference over the sd of the mean). Score: the n = 200 and n = 500 models on N = 45,000 and 1,000,000 pool
points, three gammas. Memory is the tracemalloc peak during score() (numpy reports its buffers to
tracemalloc; the pool array itself is allocated before and not counted), plus the
process's peak RSS (resource.getrusage ru_maxrss) for context.

Targets: fit n <= 200 under 5 s, 1,000 under 10 s, 5,000 under 60 s; scoring 1,000,000
under 60 s and 2 GB. Wall and CPU seconds are both printed: the machine is shared.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bams_cli.core.gp import MFGP, fit_mfgp  # noqa: E402

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="n <= 200, one repeat, N = 45k")
    parser.add_argument("--sizes", type=str, default=None, help="comma-separated n to fit")
    parser.add_argument("--exact", action="store_true", help="also fit on all observations")
    args = parser.parse_args()
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
