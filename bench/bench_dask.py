"""``select`` on a dask.distributed cluster against local worker processes (issue 16, point 3).

    .venv/bin/python bench/bench_dask.py                          # 45k and 200k, 2 workers
    .venv/bin/python bench/bench_dask.py --sizes 200000 --pool-cache /tmp/bams-pools

The pool and model are ``bench_select``'s (av_like, d = 12, two levels, budget 15, 30
observations, hyperparameters fitted once at N = 2,000). For every N, ``select_batch`` runs
with the same seed on a local process pool of --workers processes and on a loopback
``dask.distributed.LocalCluster`` of --workers single-threaded worker processes, reached
through ``bams_cli.parallel.executor(scheduler=...)`` as ``select --scheduler`` does. It
prints whether the two batches are identical, each run's wall time, and what went through
the scheduler: the largest task the client sent it (dask's own measure, the pickled size
of each submitted graph) against the largest cluster's points.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

from bench_select import BUDGET, COSTS, cached_pool, make_pool, make_posterior  # noqa: E402

from bams_cli.core.select import select_batch  # noqa: E402
from bams_cli.parallel import executor  # noqa: E402

_UNITS = {"B": 1, "kiB": 2**10, "MiB": 2**20, "GiB": 2**30}


def _size(message: str) -> float:
    m = re.search(r"Sending large graph of size ([\d.]+) (\w+)", message)
    return float(m.group(1)) * _UNITS.get(m.group(2), 1) if m else 0.0


def run(post, X, obs0, gamma, ex, clusters: int):
    t0 = time.perf_counter()
    res = select_batch(
        post,
        X,
        gamma=gamma,
        costs=COSTS,
        budget=BUDGET,
        n_clusters=clusters,
        observed_level0_mask=obs0,
        executor=ex,
        rng=np.random.default_rng(0),
    )
    return res, time.perf_counter() - t0


def main() -> None:
    import dask
    import distributed

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[45000, 200000])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--clusters", type=int, default=6)
    ap.add_argument("--pool-cache", default=None)
    args = ap.parse_args()

    X, obs, lev, y, _ = make_pool(2000)
    _, hp = make_posterior(X, obs, lev, y)
    print(f"machine: {os.cpu_count()} cpus, load average {os.getloadavg()}")
    with (
        distributed.LocalCluster(
            n_workers=args.workers, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        ProcessPoolExecutor(args.workers) as local,
    ):
        for n in args.sizes:
            X, obs, lev, y, gamma = cached_pool(n, args.pool_cache)
            post, _ = make_posterior(X, obs, lev, y, hp)
            obs0 = np.zeros(n, dtype=bool)
            obs0[obs[lev == 0]] = True
            a, t_local = run(post, X, obs0, gamma, local, args.clusters)
            # Every graph the client sends is measured: dask warns with its pickled size
            # above the threshold, here 0 bytes.
            with (
                dask.config.set({"distributed.admin.large-graph-warning-threshold": "0B"}),
                warnings.catch_warnings(record=True) as sent,
                executor(scheduler=cluster.scheduler_address) as remote,
            ):
                warnings.simplefilter("always")
                b, t_dask = run(post, X, obs0, gamma, remote, args.clusters)
            sizes = [_size(str(w.message)) for w in sent]
            sizes = [s for s in sizes if s > 0]
            biggest = max(np.bincount(a.labels)) * X.shape[1] * 8
            same = np.array_equal(a.index, b.index) and np.array_equal(a.level, b.level)
            print(
                f"N = {n}: plan {'exact' if a.plan['exact'] else 'approximate'}, "
                f"{a.plan['clusters']} clusters; local {t_local:.1f} s, dask {t_dask:.1f} s; "
                f"identical batch: {same} ({len(a.index)} picks); {len(sizes)} tasks sent to "
                f"the scheduler, the largest {max(sizes, default=0) / 1024:.1f} KiB, against "
                f"{biggest / 2**20:.1f} MiB of points in the largest cluster"
            )


if __name__ == "__main__":
    main()
