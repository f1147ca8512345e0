"""What any method can reach on rare_regions at the suite's budget: bounds on recall.

    .venv/bin/python docs/suite/rare_regions_bound.py          # ~5 min on one core

Issue 11 asks BAMS for 5x plain MC's recall on rare_regions (level-0 failures in hand
after discovery, 10 + 5 + 5 cost units, plus the estimate's K = 2 p N samples). This script
asks how much of that the data allow, whatever the method:

1. **What the model sees.** The pipeline reduces the 96-d embedding to a few PCA
   components (the protocol's ``embed-reduce``: 24 by ``--dim auto`` since 2026-11-25, 12
   before), exactly as the benchmark does. A learner given the
   level-0 value of *every* segment (5-fold cross-validation over all 20,000, so 16,000
   labels per fit: ~100x what discovery buys) predicts f0 from those features; we count
   the true failures among its K lowest predictions, and the recall of the default
   estimate design (q proportional to score^alpha with the defensive share) built from it.
   The same learner on the full 96-d embedding shows what the reduction throws away.
2. **What the budget buys.** With no way to aim (point 1), every cheap run is a draw from
   the pool; 20 units buy at most 20 / c_1 cheap runs, and a lead is a true failure only
   where f1 and f0 agree. Expected true failures among the leads of that many runs.
3. **The oracle that knows every cheap value** (for free) and spends the 20 discovery runs
   and the K estimate samples at level 0 on the lowest f1: what the cheap level is worth
   when it is seen everywhere, which the budget never allows.

Writes docs/suite/rare_regions_bound.md.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.stats import norm
from sklearn.ensemble import HistGradientBoostingRegressor
from sklearn.model_selection import KFold

from bams_cli import benchmark, defaults, pipeline
from bams_cli.core import suite
from bams_cli.state.workspace import Workspace

OUT = Path(__file__).with_name("rare_regions_bound.md")


def cv_predictions(Z: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Out-of-fold predictions of y from Z (5 folds, gradient-boosted trees)."""
    pred = np.empty_like(y)
    for train, test in KFold(5, shuffle=True, random_state=0).split(Z):
        model = HistGradientBoostingRegressor(max_iter=300, random_state=0)
        pred[test] = model.fit(Z[train], y[train]).predict(Z[test])
    return pred


def design_recall(score: np.ndarray, fail: np.ndarray, K: float) -> float:
    """Expected recall of the default Poisson design built from a failure score."""
    recall, _ = benchmark.design_stats(
        score, fail, K=K, known=None, alpha=defaults.ALPHA, defensive=defaults.DEFENSIVE,
        design="poisson",
    )  # fmt: skip
    return recall


def main() -> None:
    proto = benchmark.PROTOCOLS["rare_regions"]
    with tempfile.TemporaryDirectory() as tmp:
        data = benchmark.prepare_data(proto, None, Path(tmp))
        root = Path(tmp) / "ws"
        pipeline.init(root, settings_from=data / "settings.toml", seed=0)
        pipeline.embed_reduce(root, data / "segments.parquet", **proto.reduce)
        ids, X = Workspace(root).read_pool()
    pool = suite.rare_regions()
    pos = {s: i for i, s in enumerate(pool.ids)}
    order = np.array([pos[str(s)] for s in ids])
    E, f0, f1 = pool.features[order], pool.truth[order, 0], pool.truth[order, 1]
    fail = f0 <= pool.gamma
    N, F = f0.size, int(fail.sum())
    K = float(round(proto.k_factor * F))
    budget = proto.m1 + (proto.n_batches - 1) * proto.mb
    c1 = pool.costs[1]

    rows = []
    seen = f"{X.shape[1]} PCA components (what the model sees)"
    for name, Z in ((seen, X), ("96-d embedding", E)):
        pred = cv_predictions(Z, f0)
        r2 = 1.0 - np.mean((pred - f0) ** 2) / f0.var()
        low = np.argsort(pred)
        # A failure score from the prediction: Phi((gamma - pred) / residual sd).
        score = norm.cdf((pool.gamma - pred) / np.std(pred - f0))
        rows.append(
            f"| {name} | {r2:.2f} | {int(fail[low[: int(K)]].sum())} of {F} "
            f"(chance {K * F / N:.1f}) | {design_recall(score, fail, K):.4f} |"
        )
    mc = (budget + K) / N  # uniform level 0: budget runs in discovery, K in the estimate
    runs1 = budget / c1
    leads_true = runs1 * float((fail & (f1 <= pool.gamma)).mean())
    oracle = np.argsort(f1)[: int(budget + K)]
    bound = leads_true / F + float(rows[0].split("|")[-2])
    text = "\n".join(
        [
            "# rare_regions: what the budget and the features allow",
            "",
            f"Pool N = {N:,}, failures F = {F} (rate {F / N:.4f}), K = {K:.0f}, discovery "
            f"budget {budget:g} units, cheap run cost {c1}. Plain MC's recall "
            f"(budget + K) / N = {mc:.4f}; 2x = {2 * mc:.4f}, 5x = {5 * mc:.4f} "
            f"({5 * mc * F:.1f} failures in hand per run).",
            "",
            "1. A learner given the level-0 value of every segment (5-fold CV over the whole "
            "pool, 16,000 labels per fit), gradient-boosted trees:",
            "",
            "| features | CV R^2 of f0 | failures among its K lowest predictions "
            "| recall of the default design from it |",
            "| --- | --- | --- | --- |",
            *rows,
            "",
            f"2. All {budget:g} units at the cheap level buy {runs1:.0f} runs; aimed no "
            f"better than chance (1.), they hold {runs1 * float((f1 <= pool.gamma).mean()):.2f} "
            f"cheap-level failures, of which {leads_true:.2f} fail at level 0 "
            f"(recall {leads_true / F:.4f} if every one were confirmed).",
            "",
            f"   Upper bound, 1. ({X.shape[1]} PCA) + 2.: recall <= {bound:.4f} = "
            f"{bound / mc:.1f}x MC (target 5x = {5 * mc:.4f}).",
            "",
            f"3. Oracle that knows f1 everywhere, runs the {budget + K:.0f} lowest at level 0: "
            f"{int(fail[oracle].sum())} of {F} (recall {fail[oracle].sum() / F:.2f}).",
            "",
            f"Command: `.venv/bin/python docs/suite/rare_regions_bound.py` ({sys.version.split()[0]}).",
            "",
        ]
    )
    OUT.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
