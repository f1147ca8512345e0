"""The default estimate design on the suite: variance against uniform, and coverage.

    .venv/bin/bams-cli benchmark --protocol suite --seeds 10 --save-arrays \\
        --out /tmp/suite-arrays                                # the runs (~25 min)
    .venv/bin/python docs/suite/estimate_design.py /tmp/suite-arrays [--trials 100]

For every run the benchmark saved (``runs.npz``: p_n after discovery, the known stratum,
the truth), ``core.evaluate.staged_trials`` draws the default staged design
(``defaults.STAGES`` stages) ``--trials`` times from the truth, as ``estimate --plan``
builds it (the later stages keep stage 1's p_n instead of a refit), and records:

* its variance against a uniform Poisson design of the same expected size K over U
  (stage 1 exact, the later stages averaged over the trials' earlier draws);
* the default 90% interval's coverage of the true rate, the share of intervals wholly
  below and wholly above it, and the mean interval width over the rate.

Beside them: the single-stage p^alpha design that ``estimate --plan`` used before
(alpha ``defaults.ALPHA``, defensive share ``defaults.DEFENSIVE``), exact; and, as the
"uniform" row, the staged design with a model that says nothing (p_n constant), i.e.
uniform sampling in stages, on the BAMS runs' known strata.

Writes docs/suite/estimate_design.md and estimate_design.json.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import resource
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
PROBLEMS = ("toy2d", "av_like", "weak_cheap", "digits", "rare_regions", "gap_sim")
#: The GP strategies, plain MC (its uniform discovery and a uniform estimate), and the
#: "uniform" row (a uniform estimate after BAMS's discovery).
STRATEGIES = ("bams", "mcm-gp", "mc", "uniform")
MODELLED = ("bams", "mcm-gp")


def _old_recall(p: np.ndarray, fail: np.ndarray, known: np.ndarray, K: float) -> float:
    """The single-stage p^alpha design's expected recall (the suite table's)."""
    from bams_cli import benchmark as B

    recall, _ = B.design_stats(p, fail, K=K, known=known, **B.estimate_defaults())
    return float(recall)


def _one(args: tuple[str, str, str, int, int]) -> dict[str, Any]:
    from bams_cli import defaults
    from bams_cli.benchmark import saved_run_trials
    from bams_cli.core.estimate import inclusion_probabilities

    folder, problem, strategy, seed, trials = args
    warnings.simplefilter("ignore")
    K = float(np.load(Path(folder) / problem / "runs.npz")["K"])
    t0, c0 = time.perf_counter(), time.process_time()
    # Plain MC and the uniform row (BAMS's discovery, p_n constant): every stage uniform.
    # The GP strategies' designs take the run's open leads at their evidence's share of K.
    r, fail, known, p, prior = saved_run_trials(
        Path(folder) / problem, "bams" if strategy == "uniform" else strategy, seed,
        n_trials=trials, uniform=strategy == "uniform",
    )  # fmt: skip
    U = np.flatnonzero(~known)
    fu = fail[U]
    with np.errstate(divide="ignore", over="ignore"):
        pi = inclusion_probabilities(
            p[U], alpha=defaults.ALPHA, defensive=defaults.DEFENSIVE, K=min(K, U.size)
        )
        old = float(((1 - pi[fu]) / pi[fu]).sum()) / (fu.sum() * (U.size - K) / K)
    # The difference (doubly robust) form sum_U p_n + sum_s (y - p_n)/pi against HT, both
    # exact, on stage 1's design: Var = sum_U (y - m)^2 (1 - pi)/pi with m = p_n or 0.
    from bams_cli.core import design as dz

    pi1 = dz.choose_design(
        p[U], K=K * defaults.STAGE1_SHARE, posterior=dz.risk_posterior([], prior=prior)
    ).pi
    w1 = (1 - pi1) / pi1
    v_ht = float((fu * w1).sum())
    v_dr = float(((fu - p[U]) ** 2 * w1).sum())
    inside = (r.ci_low <= r.rate) & (r.rate <= r.ci_high)
    return {
        "problem": problem,
        "strategy": strategy,
        "seed": seed,
        "rate": r.rate,
        "K": K,
        "ratio": r.var / r.var_uniform,
        "old_ratio": old,
        "recall": float(r.recall.mean()),
        "old_recall": _old_recall(p, fail, known, K),
        "dr_over_ht": v_dr / v_ht if v_ht > 0 else None,
        "covered": int(inside.sum()),
        "below": int((r.ci_high < r.rate).sum()),
        "above": int((r.ci_low > r.rate).sum()),
        "trials": trials,
        "width": float(np.mean(r.ci_high - r.ci_low) / r.rate),
        "mean_p_hat": float(r.p_hat.mean() / r.rate),
        "lam": float(r.lam.mean()),
        "stage2_uniform": float(np.mean([d == "uniform" for d in r.stage2_design])),
        "seconds": time.perf_counter() - t0,
        "cpu_seconds": time.process_time() - c0,
    }


def main(argv: list[str]) -> None:
    folder = Path(argv[0])
    trials = int(argv[argv.index("--trials") + 1]) if "--trials" in argv else 100
    jobs = []
    for problem in PROBLEMS:
        z = np.load(folder / problem / "runs.npz")
        for strategy in STRATEGIES:
            src = "bams" if strategy == "uniform" else strategy
            for key in sorted(
                k for k in z.files if k.rsplit("-", 2)[0] == src and k.endswith("-known")
            ):
                jobs.append((str(folder), problem, strategy, int(key.split("-")[-2]), trials))
    t0, load0 = time.perf_counter(), os.getloadavg()[0]
    with ProcessPoolExecutor(2, mp_context=mp.get_context("spawn")) as pool:
        rows = list(pool.map(_one, jobs))
    wall, load1 = time.perf_counter() - t0, os.getloadavg()[0]
    cpu_all = sum(
        getattr(resource.getrusage(who), f)
        for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
        for f in ("ru_utime", "ru_stime")
    )
    (HERE / "estimate_design.json").write_text(json.dumps(rows, indent=1) + "\n")
    lines = [
        "# The default estimate design on the suite",
        "",
        f"`docs/suite/estimate_design.py {folder} --trials {trials}`: {trials} draws of the "
        "default staged design (three stages of a third of K since 2026-11-29; two halves before) per run (10 seeds per problem and strategy), from the truth. "
        "var / uniform: the design's variance over a uniform Poisson design's of the same "
        "expected size, mean [max] over seeds; p^alpha / uniform: the same for the "
        "single-stage p^alpha design used before. Coverage of the default 90% interval over "
        "all draws, the shares of intervals wholly below and wholly above the true rate, "
        "and the mean width over the rate. lam: the mean share of failure mass the last stage "
        "leaves to uniform risk. DR / HT: the exact variance of the difference (doubly "
        "robust) form, sum_U p_n + sum_s (y - p_n)/pi, over Horvitz-Thompson's on stage 1's "
        "design, mean [max] over seeds. recall: the share of the true failures in hand after "
        "the estimate (known before it, plus the design's sampled ones), mean over draws and "
        "seeds, for the default design and for p^alpha; the uniform row's is that of a "
        "uniform estimate after BAMS's discovery (BAMS's known strata, p_n constant), so it "
        "counts the failures BAMS's batches found; the mc row is plain MC's: its uniform "
        "level-0 batches, then a uniform estimate of the same K. The GP strategies' designs "
        "sample the run's open cheap-level leads with certainty, up to the share of K the "
        "run's evidence allows (``benchmark.run_leads``), as ``estimate --plan`` does. "
        f"Wall time {wall:.0f} s on 2 workers "
        f"({sum(r['cpu_seconds'] for r in rows):.0f} CPU s in the trials, {cpu_all:.0f} CPU s "
        f"in all with the workers' start; load average {load0:.1f} at the start, "
        f"{load1:.1f} at the end, on 2 cores).",
        "",
        "| problem | strategy | draws | var / uniform | p^alpha / uniform | coverage | below | above | width / rate | mean p_hat / rate | lam | DR / HT | recall | p^alpha recall |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for problem in PROBLEMS:
        for strategy in STRATEGIES:
            rs = [r for r in rows if r["problem"] == problem and r["strategy"] == strategy]
            if not rs:
                continue
            n = sum(r["trials"] for r in rs)
            ratio = [r["ratio"] for r in rs]
            old = [r["old_ratio"] for r in rs]
            lines.append(
                f"| {problem} | {strategy} | {n} | {np.mean(ratio):.3f} [{np.max(ratio):.3f}] | "
                + (f"{np.mean(old):.3f} [{np.max(old):.3f}]" if strategy in MODELLED else "-")
                + f" | {sum(r['covered'] for r in rs) / n:.3f} | {sum(r['below'] for r in rs) / n:.3f}"
                f" | {sum(r['above'] for r in rs) / n:.3f} | {np.mean([r['width'] for r in rs]):.2f}"
                f" | {np.mean([r['mean_p_hat'] for r in rs]):.3f} | {np.mean([r['lam'] for r in rs]):.2f}"
                + (
                    f" | {np.mean(dr):.3f} [{np.max(dr):.3f}] |"
                    if (dr := [r["dr_over_ht"] for r in rs if r["dr_over_ht"] is not None])
                    and strategy in MODELLED
                    else " | - |"
                )
                + f" {np.mean([r['recall'] for r in rs]):.3f} | "
                + (
                    f"{np.mean([r['old_recall'] for r in rs]):.3f} |"
                    if strategy in MODELLED
                    else "- |"
                )
            )
    (HERE / "estimate_design.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main(sys.argv[1:])
