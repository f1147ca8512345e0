"""Benchmark the rate-estimation math (bams_cli.core.estimate).

    .venv/bin/python bench/bench_estimate.py            # plan/compute at N = 1e6, GP at 5k, 20k
    .venv/bin/python bench/bench_estimate.py --gp-n 5000 20000 50000
    .venv/bin/python bench/bench_estimate.py --coverage     # CI coverage table only

* plan: inclusion probabilities over U plus one Poisson draw (``plan_sample``), N = 1e6;
* compute: HT estimate + gamma interval for 3 gammas (``estimate_rate``);
* gp_variance_exact on a 12-d Matern-5/2 GP posterior conditioned on 60 observations, all
  pairs computed (h_tol = 0, the worst case) and with the default skip tolerance.

Each timing is the median of --repeats runs (GP: one run; it is the long one).

``--coverage`` instead prints the confidence-interval coverage table quoted in
``bams_cli/core/estimate.py``: 2,000 repeated samples per scenario, nominal 0.90.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from typing import TypeVar

import numpy as np
from scipy.special import ndtr

from bams_cli.core.estimate import (
    Interval,
    draw_poisson,
    draw_systematic,
    draw_with_replacement,
    estimate_from_sample,
    estimate_rate,
    gp_variance_exact,
    inclusion_probabilities,
    model_weight,
    plan_sample,
    selection_distribution,
)

T = TypeVar("T")


def median_time(fn: Callable[[], T], repeats: int) -> tuple[float, T]:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def bench_plan_compute(N: int, repeats: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    # Calibrated synthetic scores: rate ~1%, failures ~ Bernoulli(p).
    z = rng.normal(-4.2, 1.5, N)
    p = ndtr(z)
    u = rng.random(N)
    gammas_fail = np.stack([u < p, u < 2 * p, u < 0.5 * p], axis=1)  # 3 nested thresholds
    known = np.zeros(N, bool)
    known[rng.choice(N, N // 100, replace=False)] = True
    K = 5 * int(gammas_fail[:, 0].sum())

    t_plan, plan = median_time(
        lambda: plan_sample(p, K=K, rng=rng, known=known, alpha=1.0, defensive=0.1), repeats
    )
    f_s = gammas_fail[plan.sampled_pool_index]
    known_f = gammas_fail[known].sum(axis=0)
    t_comp, ests = median_time(lambda: estimate_rate(plan, f_s, known_failures=known_f), repeats)
    print(f"N = {N:,}  |U| = {plan.n_unknown:,}  K = {K:,}  sampled = {plan.sampled.size:,}")
    print(f"plan    (inclusion probabilities + Poisson draw): median {t_plan:.3f} s")
    print(f"compute (HT + gamma CI, 3 gammas):                median {t_comp:.3f} s")
    for g, e in enumerate(ests):
        truth = gammas_fail[:, g].mean()
        print(
            f"  gamma {g}: truth {truth:.5f}  p_hat {e.p_hat:.5f}  se {e.se:.2e}  "
            f"CI [{e.ci_low:.5f}, {e.ci_high:.5f}]  failures sampled {e.n_failures_sampled}"
        )


def matern52(A: np.ndarray, B: np.ndarray, ell: float, s2: float) -> np.ndarray:
    sq = (A**2).sum(1)[:, None] + (B**2).sum(1)[None, :] - 2.0 * A @ B.T
    r = np.sqrt(np.maximum(sq, 0.0)) / ell
    z = math.sqrt(5.0) * r
    return s2 * (1.0 + z + z * z / 3.0) * np.exp(-z)


def gp_problem(N: int, seed: int, d: int = 12, n_obs: int = 60):
    """A 12-d GP posterior at N pool points; returns mu, sigma2, cov_block, gamma."""
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(N, d))
    Xo = X[rng.choice(N, n_obs, replace=False)]
    ell, s2, noise = 2.0 * math.sqrt(d) / 2, 1.0, 1e-2
    f = lambda A: np.sin(A[:, 0]) + 0.5 * A[:, 1]  # noqa: E731
    Koo = matern52(Xo, Xo, ell, s2) + noise * np.eye(n_obs)
    Lc = np.linalg.cholesky(Koo)
    alpha = np.linalg.solve(Lc.T, np.linalg.solve(Lc, f(Xo)))

    def cross(A):  # L^-1 k(Xo, A)
        return np.linalg.solve(Lc, matern52(Xo, A, ell, s2))

    mu = matern52(X, Xo, ell, s2) @ alpha
    V = cross(X)
    sigma2 = s2 - (V**2).sum(0)

    def cov_block(rows, cols):
        return matern52(X[rows], X[cols], ell, s2) - V[:, rows].T @ V[:, cols]

    gamma = float(np.quantile(mu, 0.05))
    return mu, sigma2, cov_block, gamma


def bench_gp(N: int, seed: int) -> None:
    mu, sigma2, cov_block, gamma = gp_problem(N, seed)
    for h_tol in (0.0, 1e-12):
        t0 = time.perf_counter()
        res = gp_variance_exact(mu, sigma2, cov_block, gamma, h_tol=h_tol)
        dt = time.perf_counter() - t0
        pairs = res.n_kept * (res.n_kept + 1) / 2
        print(
            f"gp_variance_exact N = {N:,} h_tol = {h_tol:g}: {dt:.2f} s  "
            f"(kept {res.n_kept:,}, {pairs / dt / 1e6:.1f} M pairs/s)  var {res.var:.3e}  "
            f"bound mean(h) {res.h_mean:.3e}  skipped <= {res.skipped_bound:.1e}"
        )


def calibrated_pool(seed: int, mu_z: float, sd_z: float, N: int = 5000):
    """p = Phi(z), z ~ N(mu_z, sd_z); failures ~ Bernoulli(p): p_n is calibrated."""
    rng = np.random.default_rng(seed)
    p = ndtr(rng.normal(mu_z, sd_z, N))
    return p, rng.random(N) < p


def miscalibrated_pool(N: int = 5000, F: int = 50, n_wrong: int = 3):
    """F fixed failures; p_n = Phi(noise + 2.5 [failure] - 3): over-predicts failures ~2x
    and puts three failures at p_n = 1e-4 (the tests' ``make_pool``)."""
    rng = np.random.default_rng(20240601)
    fail = np.zeros(N, bool)
    fail[rng.choice(N, F, replace=False)] = True
    p = ndtr(rng.normal(size=N) + np.where(fail, 2.5, 0.0) - 3.0)
    p[np.flatnonzero(fail)[:n_wrong]] = 1e-4
    return p, fail


def coverage_table(R: int = 2000, seed: int = 0) -> None:
    pools = {
        "calibrated A": calibrated_pool(2, -3.5, 1.5),
        "calibrated B": calibrated_pool(1, -3.2, 1.0),
        "miscalibrated": miscalibrated_pool(),
    }
    scenarios = [
        ("calibrated A", 5.0, 1.0, 0.1),
        ("calibrated A", 5.0, 2.5, 0.1),
        ("calibrated A", 5.0, 1.0, 0.0),
        ("calibrated B", 5.0, 0.5, 0.1),
        ("calibrated B", 0.5, 0.5, 0.1),
        ("miscalibrated", 5.0, 1.0, 0.1),
    ]
    intervals: list[tuple[Interval, bool]] = [
        ("gamma", True),
        ("gamma", False),
        ("fay-feuer", True),
        ("wald", True),
    ]
    print(f"coverage of nominal 0.90 intervals, {R} repeats; width = median (hi - lo) / p")
    print("gamma* = gamma without the model weight (design-only)")
    head = f"{'pool':14s} {'K/F':>4s} {'alpha':>5s} {'eps':>4s} {'design':17s} {'fails':>6s}"
    names = ["gamma", "gamma*", "fay-feuer", "wald"]
    print(head + "".join(f" {n:>16s}" for n in names))
    rng = np.random.default_rng(seed)
    for pool, kf, alpha, eps in scenarios:
        p, fail = pools[pool]
        truth = fail.mean()
        K = max(1, int(round(kf * fail.sum())))
        for design in ("poisson", "fixed", "with-replacement"):
            if design == "with-replacement":
                prob = selection_distribution(p, alpha=alpha, defensive=eps)
            else:
                prob = inclusion_probabilities(p, alpha=alpha, defensive=eps, K=K)
            C = np.zeros((p.size, R), np.int64)
            for r in range(R):
                if design == "poisson":
                    C[draw_poisson(prob, rng), r] = 1
                elif design == "fixed":
                    C[draw_systematic(prob, rng), r] = 1
                else:
                    s, c = draw_with_replacement(prob, K, rng)
                    C[s, r] = c
            w_model = model_weight(p, prob, design=design, K=K)
            wf = (
                ((1 - prob) / (K * prob)).max()
                if design == "with-replacement"
                else (((1 - prob) / prob)[prob < 1].max())
            )
            cells = []
            for interval, with_model in intervals:
                est = estimate_from_sample(
                    prob, fail, design=design, n_pool=p.size, n_unknown=p.size, budget=K,
                    counts=C, interval=interval, w_model=w_model if with_model else None,
                    w_max=wf,
                )  # fmt: skip
                cov = np.mean((est.ci_low <= truth) & (truth <= est.ci_high))
                width = np.median(est.ci_high - est.ci_low) / truth
                cells.append(f" {cov:8.3f} ({width:5.2f})")
            fails = est.n_failures_sampled.mean()
            print(
                f"{pool:14s} {kf:4.1f} {alpha:5.1f} {eps:4.1f} {design:17s} {fails:6.1f}"
                + "".join(cells)
            )


def bench_staged(N: int, repeats: int, seed: int) -> None:
    """One stage of the default staged design at pool size N: the posterior over the
    calibration from a finished stage, the design choice (three candidates' inclusion
    probabilities and predicted variances), the draw; and the combined estimate."""
    from bams_cli.core import design as dz

    rng = np.random.default_rng(seed)
    p = ndtr(rng.normal(-4.2, 1.5, N))
    fail = rng.random(N) < p
    K = 5 * int(fail.sum())
    u = dz.relative_risk(p)
    norms = dz.risk_norms(u)

    def stage1():
        choice = dz.choose_design(p, K=K / 2, posterior=dz.risk_posterior([]))
        return choice, draw_poisson(choice.pi, rng)

    t_stage1, (c1, s1) = median_time(stage1, repeats)
    ev = dz.StageEvidence(u[s1], fail[s1], norms, p_mean=float(p.mean()))

    def stage2():
        post = dz.risk_posterior([ev])
        choice = dz.choose_design(p, K=K / 2, posterior=post)
        return choice, draw_poisson(choice.pi, rng)

    t_stage, (choice, s2) = median_time(stage2, repeats)

    def combined():
        e1 = estimate_from_sample(c1.pi[s1], fail[s1], design="poisson", n_pool=N,
                                  n_unknown=N, budget=K / 2)  # fmt: skip
        e2 = estimate_from_sample(choice.pi[s2], fail[s2], design="poisson", n_pool=N,
                                  n_unknown=N, budget=K / 2)  # fmt: skip
        return dz.combine_stages([e1, e2], [0.5, 0.5], n_pool=N)

    t_comb, est = median_time(combined, repeats)
    budget = 5.0  # issue 12: estimate --plan stays under 5 s per stage at N = 1e6
    print(
        f"staged, N = {N:,}, K = {K:,}: stage 1's plan (prior, design choice, draw) median "
        f"{t_stage1:.3f} s; each stage under {budget:.0f} s: "
        f"{'yes' if max(t_stage1, t_stage) < budget else 'NO'}"
    )
    print(
        f"staged, N = {N:,}, K = {K:,}: a later stage's plan (posterior + design choice + "
        f"draw) median {t_stage:.3f} s ({choice.name}, predicted "
        f"{choice.predicted[choice.name]:.3f}x uniform); combining two stages median "
        f"{t_comb:.3f} s; p_hat {est.p_hat[0]:.5f} (truth {fail.mean():.5f})"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--gp-n", type=int, nargs="*", default=[5_000, 20_000])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--coverage", action="store_true", help="print the CI coverage table only")
    args = ap.parse_args()
    if args.coverage:
        coverage_table(seed=args.seed)
        return
    bench_plan_compute(args.n, args.repeats, args.seed)
    bench_staged(args.n, args.repeats, args.seed)
    # Warm the numba kernels (compile or load from cache) outside the timings.
    mu, sigma2, cov_block, gamma = gp_problem(300, args.seed)
    gp_variance_exact(mu, sigma2, cov_block, gamma)
    for n in args.gp_n:
        bench_gp(n, args.seed)


if __name__ == "__main__":
    main()
