"""The most recall an estimate design can hold at issue 12's variance bound, with hindsight.

    .venv/bin/python docs/suite/recall_bound.py run FOLDER [--trials 50] [--out docs/suite]
    .venv/bin/python docs/suite/recall_bound.py check
    .venv/bin/python docs/suite/recall_bound.py table docs/suite/recall_bound.json

FOLDER holds the suite's saved runs, one subfolder per problem, from
``bams-cli benchmark --protocol PROBLEM --seeds 10 --strategies bams,mc --save-arrays
--out FOLDER/PROBLEM`` (or ``--protocol suite``): per run the model's p_n after discovery,
the known stratum, and the truth.

For each BAMS run the estimate's K level-0 runs are spread over the segments not yet run at
level 0 (U). Among one-stage Poisson designs whose inclusion probability is nondecreasing
in the model's p_n after discovery, chosen *knowing which segments fail*, ``bound`` finds
the largest expected recall

    (failures known + sum over U's failures of pi) / F

subject to sum_U pi = K and the Horvitz-Thompson variance sum over U's failures of
(1 - pi)/pi at most 1.2 times a uniform design's of the same expected size (issue 12,
point 2). Monotone and with hindsight, a segment ranked below the lowest failure costs
nothing (pi -> 0) and the segments between one failure and the next take the lower one's
pi, so the problem is one pi_j per failure j, nondecreasing in j, paying for n_j segments.
Its optimum is pi_j = min(1, sqrt(mu / (nu nbar_j - 1))) with nbar the nonincreasing
isotonic fit of n (the generalised isotonic regression theorem), mu spending exactly K and
nu the least value at which the variance bound holds. ``check`` compares this closed form
with SLSQP on the same reduced problem (12 random pools).

The bound is for designs that rank by one p_n; the tool's default refits the model on
stage 1's outcomes and draws stage 2 from the refitted p_n, which a bound on the discovery
model's ranking does not cover. Plain MC's recall is that of the same seed's MC run
(uniform level-0 batches and a uniform estimate of the same K, at equal cost); the
default's is the tool's staged design drawn ``--trials`` times from the truth
(``core.evaluate.staged_trials``, on the discovery p_n as ``estimate_design.py``), with its
exact variance over uniform's.

Writes ``recall_bound.json`` and ``recall_bound.md`` to ``--out``.
"""

from __future__ import annotations

import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

PROBLEMS = ("toy2d", "av_like", "weak_cheap", "digits", "rare_regions", "gap_sim")
#: Issue 12's bound on the default design's variance, over a uniform design's.
RATIO = 1.2
#: Issue 11's recall over plain MC: 5x where the model is informative, else 2x.
ASKED = {"toy2d": 5, "av_like": 5, "rare_regions": 5}


def _design(nbar: np.ndarray, K: float, nu: float) -> np.ndarray:
    """x_j = min(1, sqrt(mu / (nu nbar_j - 1))) (1 where nu nbar_j <= 1), mu set by
    bisection so that sum nbar_j x_j = K (the blocks' costs; nbar averages n over a block)."""
    room = nu * nbar - 1.0
    lo, hi = -700.0, 700.0  # log mu
    x = np.ones_like(nbar)
    for _ in range(200):
        mu = np.exp(0.5 * (lo + hi))
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(room > 0, np.minimum(1.0, np.sqrt(mu / room)), 1.0)
        if (nbar * x).sum() > K:
            hi = 0.5 * (lo + hi)
        else:
            lo = 0.5 * (lo + hi)
        if hi - lo < 1e-12:
            break
    return x


def bound(p, fail, known, K, ratio: float = RATIO) -> float:
    """The largest expected recall over designs monotone in p_n, chosen knowing which
    segments fail, at <= ``ratio`` x uniform's exact variance (module docstring)."""
    from sklearn.isotonic import IsotonicRegression

    U = np.flatnonzero(~known)
    fu = fail[U][np.argsort(p[U], kind="stable")]
    F, F_known = int(fail.sum()), int((fail & known).sum())
    at = np.flatnonzero(fu)  # ranks of U's failures, ascending p_n
    u = K / U.size
    if at.size == 0 or u >= 1.0:
        return (F_known + at.size * min(u, 1.0)) / F
    # Monotone pi: the segments ranked below the lowest failure cost nothing (pi -> 0), and
    # every segment between a failure and the next takes that failure's pi, the least
    # monotonicity allows: pi_j per failure j, nondecreasing in j, paying for n_j segments.
    # Maximise sum_j pi_j subject to sum_j n_j pi_j = K and sum_j (1 - pi_j)/pi_j <= V.
    # Stationarity gives pi_j = sqrt(mu / (nu n_j - 1)) (capped at 1), decreasing in n_j;
    # under the order constraint n_j is replaced by its nonincreasing isotonic fit (the
    # generalised isotonic regression theorem: Robertson, Wright and Dykstra 1988, 1.5).
    n = np.diff(np.append(at, U.size)).astype(np.float64)
    if n.sum() <= K:  # pi = 1 from the lowest failure up, the rest below it: every failure
        return (F_known + at.size) / F
    j = np.arange(n.size, dtype=np.float64)
    nbar = IsotonicRegression(increasing=False).fit_transform(j, n)
    limit = ratio * at.size * (1.0 - u) / u
    best = (F_known + at.size * u) / F  # uniform is feasible

    def recall(log_nu: float) -> float:
        x = _design(nbar, K, float(np.exp(log_nu)))
        if abs((nbar * x).sum() / K - 1.0) > 1e-6 or x.min() <= 0.0:
            return -1.0  # no mu spends exactly K at this nu
        ok = ((1.0 - x) / x).sum() <= limit * (1.0 + 1e-9)
        return (F_known + x.sum()) / F if ok else -1.0

    # Along the curve (mu spending exactly K at each nu), recall and variance both fall as
    # the budget's price nu rises: the optimum is the least nu at which the design spends
    # K within the variance bound. A log grid finds a feasible nu; bisection, the edge.
    grid = np.linspace(np.log(1.0 / n.max()) - 2.0, np.log(1.0 / nbar.min()) + 12.0, 400)
    vals = np.array([recall(g) for g in grid])
    ok = np.flatnonzero(vals > 0)
    if ok.size:
        best = max(best, float(vals.max()))
        k = int(ok[0])
        if k > 0:
            a, b = grid[k - 1], grid[k]  # infeasible, feasible
            for _ in range(100):
                c = 0.5 * (a + b)
                if recall(c) > 0:
                    b = c
                else:
                    a = c
            best = max(best, recall(b))
    return float(best)


def _bound_by_slsqp(p, fail, K, ratio: float = RATIO) -> float:
    """The same optimum found by a general solver over pi_j = cumsum(d), d >= 0 (small
    pools only: minutes at 300 failures), to check ``bound``."""
    from scipy.optimize import minimize

    fu = fail[np.argsort(p, kind="stable")]
    at = np.flatnonzero(fu)
    u = K / p.size
    n = np.diff(np.append(at, p.size)).astype(np.float64)
    limit = ratio * at.size * (1.0 - u) / u
    tri = np.tril(np.ones((at.size, at.size)))
    cons = [
        {"type": "eq", "fun": lambda d: (n * np.cumsum(d)).sum() / K - 1.0,
         "jac": lambda d: (n @ tri) / K},
        {"type": "ineq", "fun": lambda d: 1.0 - ((1.0 - (x := np.cumsum(d))) / x).sum() / limit,
         "jac": lambda d: ((1.0 / np.cumsum(d) ** 2) @ tri) / limit},
        {"type": "ineq", "fun": lambda d: 1.0 - d.sum(), "jac": lambda d: -np.ones_like(d)},
    ]  # fmt: skip
    d0 = np.zeros(at.size)
    d0[0] = K / n.sum()
    r = minimize(
        lambda d: -np.cumsum(d).sum(), d0, jac=lambda d: -(np.ones(at.size) @ tri),
        method="SLSQP", bounds=[(1e-9, 1.0)] + [(0.0, 1.0)] * (at.size - 1),
        constraints=cons, options={"maxiter": 3000, "ftol": 1e-14},
    )  # fmt: skip
    x = np.cumsum(r.x)
    assert abs((n * x).sum() / K - 1.0) < 1e-6 and ((1 - x) / x).sum() <= limit * (1 + 1e-6)
    return float(x.sum() / at.size)


def check(n_cases: int = 12) -> list[tuple[float, float]]:
    """``bound`` against ``_bound_by_slsqp`` on small random pools (nothing known)."""
    out = []
    rng = np.random.default_rng(0)
    for _ in range(n_cases):
        N = int(rng.integers(300, 1500))
        p = rng.beta(0.5, 10, N)
        fail = rng.random(N) < np.clip(p * rng.uniform(0.3, 3.0), 0, 1)
        if fail.sum() < 2:
            continue
        K = float(rng.uniform(1.0, 4.0) * fail.sum())
        a = bound(p, fail, np.zeros(N, bool), K)
        b = _bound_by_slsqp(p, fail, K)
        out.append((a, b))
        assert a >= b - 1e-4 and a <= b + 1e-3, (a, b)
    return out


def _mc_recall(z, fail, K: float, seed: int) -> float:
    known = z[f"mc-{seed}-known"]
    U = ~known
    return float(((fail & known).sum() + fail[U].sum() * min(1.0, K / U.sum())) / fail.sum())


def run(folder: Path, trials: int) -> list[dict]:
    from bams_cli.core.evaluate import staged_trials

    rows = []
    for problem in PROBLEMS:
        path = folder / problem / "runs.npz"
        if not path.exists():
            print(f"{problem}: no {path}, skipped", file=sys.stderr)
            continue
        z = np.load(path)
        fail = z["f0"] <= float(z["gamma"])
        K = float(z["K"])
        for seed in range(10):
            if f"bams-{seed}-p" not in z:
                continue
            p, known = z[f"bams-{seed}-p"], z[f"bams-{seed}-known"]
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                r = staged_trials(
                    p, fail, K=K, known=known, n_trials=trials, rng=np.random.default_rng(seed)
                )
            rows.append(
                {
                    "problem": problem,
                    "seed": seed,
                    "N": int(fail.size),
                    "F": int(fail.sum()),
                    "K": K,
                    "mc": _mc_recall(z, fail, K, seed),
                    "default": float(r.recall.mean()),
                    "default_ratio": float(r.var / r.var_uniform),
                    "bound": bound(p, fail, known, K),
                    "seconds": time.perf_counter() - t0,
                }
            )
            print(json.dumps(rows[-1]), file=sys.stderr)
    return rows


def table(rows: list[dict]) -> str:
    out = [
        "| problem | N | failures | K | plain MC recall | asked | default recall | "
        "default var / uniform | bound at 1.2x uniform's var, mean [range over seeds] | "
        "seeds whose bound reaches the ask |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for problem in PROBLEMS:
        rs = [r for r in rows if r["problem"] == problem]
        if not rs:
            continue
        mc = float(np.mean([r["mc"] for r in rs]))
        asked = ASKED.get(problem, 2)
        default = float(np.mean([r["default"] for r in rs]))
        b = np.array([r["bound"] for r in rs])
        x = b / np.array([r["mc"] for r in rs])
        reach = int(np.sum(x >= asked))
        out.append(
            f"| {problem} | {rs[0]['N']:,} | {rs[0]['F']} | {rs[0]['K']:g} | {mc:.4f} | "
            f"{asked}x MC | {default:.4f} ({default / mc:.1f}x) | "
            f"{np.mean([r['default_ratio'] for r in rs]):.2f} | "
            f"{b.mean():.4f} ({b.mean() / mc:.1f}x) [{x.min():.1f}x, {x.max():.1f}x] | "
            f"{reach} of {len(rs)} |"
        )
    return "\n".join(out)


def main(argv: list[str]) -> None:
    if argv and argv[0] == "check":
        for a, b in check():
            print(f"bound {a:.5f}  general solver {b:.5f}")
        return
    if argv and argv[0] == "table":
        print(table(json.loads(Path(argv[1]).read_text())))
        return
    if not argv or argv[0] != "run":
        raise SystemExit(__doc__)
    folder = Path(argv[1])
    trials = int(argv[argv.index("--trials") + 1]) if "--trials" in argv else 50
    out = Path(argv[argv.index("--out") + 1]) if "--out" in argv else Path(__file__).parent
    rows = run(folder, trials)
    (out / "recall_bound.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(table(rows))


if __name__ == "__main__":
    main(sys.argv[1:])
