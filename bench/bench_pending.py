"""Benchmark ``select`` with thousands of pending picks: J given an estimate stage's pairs.

A team runs ``select --allow-pending`` while an estimate stage's level-0 runs are out: the
batch is conditioned on every pending pair (``core.select._Given``). At a million segments
after a two-stage estimate (14,654 observations, 11,782 pending picks) J before the batch
was still running after 7 minutes: each block of 8,192 pool rows solved the pairs' data
term K^-1 k(Y_n, pairs) again (n^2 x pairs flops a block), and every row near gamma was
conditioned on every pair (rows x n x pairs).

Setting: a GP on n observations (60% level 0) of a smooth function in d = 4 (--dim), hyperparameters
fixed; a pool of N uniform points; G pending level-0 pairs drawn uniformly from the pool;
gamma the pool mean's 2% quantile. Timed, each --runs times (median):

* ``joint, per block``: J given the G pairs jointly, the pairs' data term solved for every
  block (``cov_theta0_obs``; how ``select`` did it before);
* ``joint``: the same J with the data term solved once (``MFGP.cov_theta0_obs_to``);
* ``by cluster``: each cluster's rows conditioned on its own pairs (``_j_given(labels=)``,
  what ``select`` does once rows x pairs x (n + pairs) exceeds ``defaults.SCORE_MAX_WORK``), with the
  ratio of its J to the joint one (>= 1: an upper bound);
* J before and after a batch of 100 level-1 picks, by cluster: two passes (``_j_given``
  twice, as ``select`` did before 2026-11-29) against one conditioning on the pending pairs
  and the picks together (``_j_nested``: Cholesky whitening is nested);
* with ``--select`` (``--select-only``: it alone), the whole ``select_batch``, budget 10,
  its greedies inline in one process (``select`` runs them on the cores' worker
  processes), each phase printed with its time as it ends. ``--moments FILE`` keeps the
  pool's moments between runs (at a million segments and 14,000 observations they take
  minutes). Each cluster's greedy starts conditioned on its pending pairs, in blocks of
  up to 64 (``core.select.FORCED_CHUNK_ELEMENTS``); one pair at a time, a million
  segments with 12,000 pending did not leave the greedies in 35 minutes.

    .venv/bin/python bench/bench_pending.py                         # N 200k, n 4,000, G 3,000, d 4
    .venv/bin/python bench/bench_pending.py --pool 1000000 --obs 14000 --pending 12000 \
        --runs 1 --select-only --moments /tmp/moments-1m.npz
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from bams_cli import defaults
from bams_cli.core.acquisition import margin
from bams_cli.core.cluster import cluster_pool
from bams_cli.core.gp import MFGP, Hyperparameters
from bams_cli.core.select import _j_given, _j_nested, select_batch

T = TypeVar("T")
_PHASE = {"j_after": "J before and after"}  # select_batch's one pass for both


class _PerBlock:
    """The posterior without ``cov_theta0_obs_to``: ``_Given`` solves per block."""

    def __init__(self, model: MFGP) -> None:
        self._m = model

    def __getattr__(self, name: str):  # type: ignore[no-untyped-def]
        if name == "cov_theta0_obs_to":
            raise AttributeError(name)
        return getattr(self._m, name)


def _problem(N: int, n: int, G: int, d: int, seed: int):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(seed)
    f = lambda X: np.sin(X).sum(1) + 0.3 * X[:, 0] * X[:, 1]  # noqa: E731
    X = rng.uniform(-3, 3, size=(n, d))
    levels = (rng.uniform(size=n) < 0.4).astype(np.int64)
    y = f(X) + 0.3 * levels + 0.05 * rng.normal(size=n)
    hp = Hyperparameters(
        mean=0.0,
        outputscale0=1.0,
        lengthscales0=np.full(d, 1.5),
        outputscales=np.array([0.1]),
        lengthscales=np.full((1, d), 2.0),
        noise=np.array([1e-3, 1e-2]),
        offsets=np.array([0.3]),
    )
    model = MFGP(X, levels, y, 2, hp)
    pool = rng.uniform(-3.2, 3.2, size=(N, d))
    pend = np.zeros((N, 2), bool)
    pend[rng.choice(N, G, replace=False), 0] = True
    return model, pool, pend


def _timed(fn: Callable[[], T], runs: int) -> tuple[float, T]:
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pool", type=int, default=200_000)
    ap.add_argument("--obs", type=int, default=4_000)
    ap.add_argument("--pending", type=int, default=3_000)
    ap.add_argument("--dim", type=int, default=4)
    ap.add_argument("--clusters", type=int, default=40, help="clusters of the by-cluster J")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-per-block", action="store_true", help="skip the slowest variant")
    ap.add_argument(
        "--skip-joint", action="store_true", help="by cluster only (at a million segments)"
    )
    ap.add_argument("--select", action="store_true", help="also time the whole select_batch")
    ap.add_argument("--select-only", action="store_true", help="time select_batch alone")
    ap.add_argument("--moments", type=Path, help="an .npz keeping the pool's moments between runs")
    a = ap.parse_args()

    model, pool, pend = _problem(a.pool, a.obs, a.pending, a.dim, a.seed)
    # gamma from a sample; the pool's moments as select gets them (bounded past the budget)
    gamma = float(np.quantile(model.predict_theta0(pool[:5000])[0], 0.02))
    t = time.perf_counter()
    problem = json.dumps([a.pool, a.obs, a.pending, a.dim, a.seed])
    if a.moments is not None and a.moments.exists():
        kept = np.load(a.moments, allow_pickle=False)
        if "problem" not in kept.files or str(kept["problem"]) != problem:
            raise SystemExit(
                f"{a.moments} does not hold the moments of --pool --obs --pending --dim "
                f"--seed {problem}: remove it or name another file"
            )
        mu, sigma2, how = kept["mu"], kept["sigma2"], json.loads(str(kept["how"]))
        print(f"pool moments: read from {a.moments}")
    else:
        mu, sigma2, _ = model.moments(pool, [gamma], max_work=defaults.SCORE_MAX_WORK)
        how = dict(model.scoring)
        print(f"pool moments: {time.perf_counter() - t:.1f} s ({how['method']})")
        if a.moments is not None:
            np.savez(a.moments, mu=mu, sigma2=sigma2, how=json.dumps(how), problem=problem)
    s = margin(mu, sigma2, gamma)
    z = defaults.SCORE_DECIDED_Z
    near = int(np.count_nonzero(np.abs(s) < z))
    idx, lev = (v.astype(np.int64) for v in np.nonzero(pend))
    print(
        f"N {a.pool:,}, n {a.obs:,}, pending {a.pending:,}, d {a.dim}; rows near gamma "
        f"{near:,}; rows x pairs x (n + pairs) {near * a.pending * (a.obs + a.pending):.2g} "
        f"(SCORE_MAX_WORK {defaults.SCORE_MAX_WORK:.0e}); load {os.getloadavg()[0]:.1f}"
    )
    if not a.select_only:
        _j_variants(a, model, pool, s, sigma2, idx, lev, z)
    if a.select or a.select_only:
        _select(model, pool, gamma, pend, mu, sigma2, how)


def _j_variants(a, model, pool, s, sigma2, idx, lev, z) -> None:  # type: ignore[no-untyped-def]
    res: dict[str, float] = {}
    per_block = not (a.skip_per_block or a.skip_joint)
    if per_block:
        res["joint, per block"], j_old = _timed(
            lambda: _j_given(_PerBlock(model), pool, s, sigma2, idx, lev, z), a.runs
        )
    if not a.skip_joint:
        res["joint"], j_joint = _timed(
            lambda: _j_given(model, pool, s, sigma2, idx, lev, z), a.runs
        )
    labels = cluster_pool(pool, model.lengthscales0, a.clusters, rng=np.random.default_rng(0))
    res["by cluster"], j_split = _timed(
        lambda: _j_given(model, pool, s, sigma2, idx, lev, z, labels), a.runs
    )
    for k, v in res.items():
        ratio = f"  ({v / res['joint']:.2f}x joint)" if k != "joint" and "joint" in res else ""
        print(f"{k:>18}: {v:8.1f} s{ratio}", flush=True)
    if per_block:
        print(f"J joint per block {j_old:.6g} vs joint {j_joint:.6g} (the same J)")
    if a.skip_joint:
        print(f"J by cluster {j_split:.6g}", flush=True)
    else:
        print(f"J by cluster / joint: {j_split / j_joint:.4f} (an upper bound: >= 1)", flush=True)
    # J before and after a batch of 100 level-1 picks, by cluster: two passes (before
    # 2026-11-29) against one conditioning on the pending pairs and the picks
    rng = np.random.default_rng(a.seed + 1)
    picks = rng.choice(np.setdiff1d(np.arange(len(pool)), idx), 100, replace=False)
    b_idx, b_lev = np.concatenate([idx, picks]), np.concatenate([lev, np.ones(100, np.int64)])
    two, (jb2, ja2) = _timed(
        lambda: (
            _j_given(model, pool, s, sigma2, idx, lev, z, labels),
            _j_given(model, pool, s, sigma2, b_idx, b_lev, z, labels),
        ),
        a.runs,
    )
    one, (jb1, ja1) = _timed(
        lambda: _j_nested(model, pool, s, sigma2, b_idx, b_lev, len(idx), z, labels), a.runs
    )
    print(
        f"J before and after 100 picks, by cluster: two passes {two:.1f} s, one pass "
        f"{one:.1f} s ({one / two:.2f}x); J {jb1:.6g} -> {ja1:.6g} (two passes "
        f"{jb2:.6g} -> {ja2:.6g})",
        flush=True,
    )


def _select(model, pool, gamma, pend, mu, sigma2, how) -> None:  # type: ignore[no-untyped-def]
    t = time.perf_counter()
    shown: dict[str, int] = {}

    def progress(phase: str, done: int, total: int) -> None:
        """Each phase's start and end, and every tenth of the greedies, with the time."""
        step = max(1, total // 10) if phase == "greedy" else total
        if done in (0, total) or done // step > shown.get(phase, -1):
            shown[phase] = done // step
            print(f"  {time.perf_counter() - t:7.1f} s  {phase} {done}/{total}", flush=True)

    r = select_batch(
        model, pool, gamma=gamma, costs=[1.0, 0.1], budget=10.0, pending_pairs=pend,
        rng=np.random.default_rng(1), max_work=defaults.SCORE_MAX_WORK,
        moments=(mu, sigma2, how), progress=progress,
    )  # fmt: skip
    print(
        f"select_batch (greedies inline, one process): {time.perf_counter() - t:.1f} s, "
        f"{len(r.index)} picks, J {r.j_before:.4g} -> {r.j_after:.4g}, j_by_cluster "
        f"{r.plan['j_by_cluster']}; "
        + ", ".join(f"{_PHASE.get(k, k)} {v:.1f}" for k, v in r.timings.items() if "." not in k)
    )


if __name__ == "__main__":
    main()
