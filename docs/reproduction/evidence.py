"""The evidence behind the defaults the reproduction changed (docs/reproduction/README.md).

    .venv/bin/python docs/reproduction/evidence.py               # everything, ~1 h on 2 cores
    .venv/bin/python docs/reproduction/evidence.py priors alpha  # some studies only

Each study runs the paper's protocol (``bams_cli.benchmark.run_one``: the real select,
simulate, ingest-results and fit path) for several settings over the same seeds, and
tabulates the exact recall and 100 x relative variance of the default estimator design
(``benchmark.design_stats``). A setting that differs from the shipped defaults is applied
in each worker process before it runs: GP prior constants are set on ``bams_cli.core.gp``
and select options are passed to ``pipeline.select`` for the BAMS and BAS batches. Nothing
here changes the shipped defaults; it only shows what the alternatives did.

Studies:
  priors    GP priors before this change (level-0 noise log-sd 1.5, discrepancy mode 0.1
            log-sd 1.5) vs now, toy2d (20 seeds) and av_like (10 seeds)
  eta       select --overbudget 1, 2, 3 (BAMS, BAS), toy2d 20 seeds
  share     the level-0 share of the first mixed batch, 0.3 / 0.5 / 0.7 (BAMS), toy2d
  pooling   select --pooling global vs raw (BAMS), toy2d
  alpha     estimate --alpha / --defensive grid on the shipped-default runs, both protocols

Writes docs/reproduction/evidence.md (tables) and evidence.json (per-seed numbers).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from bams_cli import benchmark as B
from bams_cli import pipeline
from bams_cli.settings import Settings

HERE = Path(__file__).resolve().parent
OLD_PRIORS = {
    "_NOISE0_MODE": 3e-4,
    "_NOISE0_SCALE": 1.5,
    "_DISCREPANCY_MODE": 0.1,
    "_DISCREPANCY_SCALE": 1.5,
}
ALPHAS = (0.5, 0.75, 1.0, 1.5)
EPSILONS = (0.02, 0.05, 0.1, 0.2)


def _worker(spec: B.RunSpec, gp_constants: dict[str, float], select_kw: dict[str, Any]):
    """Run one (strategy, seed) with the given GP constants and BAMS/BAS select options."""
    from bams_cli.core import gp

    for name, value in gp_constants.items():
        setattr(gp, name, value)
    if select_kw:
        original = pipeline.select

        def select(root, **kw):
            if kw.get("strategy") in ("bams", "bas"):
                kw.update(select_kw)
            return original(root, **kw)

        pipeline.select = select  # benchmark.run_one calls pipeline.select
    r = B.run_one(spec)
    return r.strategy, r.seed, r.p_after[-1], r.known


def run_setting(
    protocol: str,
    strategies: list[str],
    seeds: range,
    *,
    gp_constants: dict[str, float] | None = None,
    select_kw: dict[str, Any] | None = None,
    level0_share: float = 0.5,
    workers: int = 2,
) -> dict[str, Any]:
    """Final p_n and known stratum of every (strategy, seed), plus the pool's truth."""
    proto = B.PROTOCOLS[protocol]
    with tempfile.TemporaryDirectory(prefix="bams-evidence-") as tmp:
        data = B.prepare_data(proto, None, Path(tmp))
        f0 = B._column(data / "truth.parquet", "value_0").astype(np.float64)
        gamma = Settings.from_toml((data / "settings.toml").read_text()).gammas[0]
        fail = f0 <= gamma
        K = float(round(proto.k_factor * fail.sum()))
        specs = [
            B.RunSpec(protocol, s, seed, str(data), tmp, level0_share, 6, K)
            for s in strategies
            for seed in seeds
        ]
        with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
            out = list(
                pool.map(
                    _worker,
                    specs,
                    [gp_constants or {}] * len(specs),
                    [select_kw or {}] * len(specs),
                )
            )
    return {"fail": fail, "K": K, "runs": out}


def score(setting: dict[str, Any], alpha: float, eps: float) -> dict[str, dict[str, Any]]:
    """Recall and 100 RV per strategy under the Poisson design with (alpha, eps)."""
    per: dict[str, list[tuple[float, float]]] = {}
    for strategy, _, p, known in setting["runs"]:
        per.setdefault(strategy, []).append(
            B.design_stats(
                p, setting["fail"], K=setting["K"], known=known, alpha=alpha,
                defensive=eps, design="poisson",
            )
        )  # fmt: skip
    out = {}
    for strategy, rows in per.items():
        a = np.array(rows)
        out[strategy] = {
            "recall": float(a[:, 0].mean()),
            "recall_se": float(a[:, 0].std(ddof=1) / np.sqrt(len(a))),
            "rv": float(100 * a[:, 1].mean()),
            "rv_median": float(100 * np.median(a[:, 1])),
            "per_seed_recall": a[:, 0].round(4).tolist(),
            "per_seed_rv": (100 * a[:, 1]).round(3).tolist(),
        }
    return out


def table(title: str, rows: dict[str, dict[str, dict[str, Any]]]) -> list[str]:
    """Markdown: one row per (setting, strategy)."""
    lines = [
        f"### {title}",
        "",
        "| setting | strategy | recall ± SE | 100 RV mean | 100 RV median |",
        "| --- | --- | --- | --- | --- |",
    ]
    for setting, per in rows.items():
        for strategy, e in per.items():
            lines.append(
                f"| {setting} | {B.NAMES[strategy]} | {e['recall']:.3f} ± {e['recall_se']:.3f} "
                f"| {e['rv']:.2f} | {e['rv_median']:.2f} |"
            )
    return [*lines, ""]


def main(studies: list[str]) -> None:
    est = B.estimate_defaults()
    a0, e0 = est["alpha"], est["defensive"]
    md = [
        "# Evidence for the reproduction defaults",
        "",
        f"Generated by `docs/reproduction/evidence.py {' '.join(studies)}`. Recall and 100 RV "
        f"are exact design quantities of the default estimator (Poisson, alpha {a0:g}, "
        f"defensive {e0:g}) after batch 3, over seeds (toy2d: K = 2 p N; av_like: K = 5 p N).",
        "",
    ]
    doc: dict[str, Any] = {}
    t0 = time.perf_counter()
    toy_seeds, av_seeds = range(20), range(10)
    gp_strats = ["bams", "bas", "mcm-gp", "mc-gp"]
    shipped: dict[str, dict[str, Any]] = {}

    def shipped_runs(protocol: str) -> dict[str, Any]:
        if protocol not in shipped:
            seeds = toy_seeds if protocol == "toy2d" else av_seeds
            shipped[protocol] = run_setting(protocol, gp_strats, seeds)
        return shipped[protocol]

    if "priors" in studies:
        for protocol, seeds in (("toy2d", toy_seeds), ("av_like", av_seeds)):
            old = run_setting(protocol, gp_strats, seeds, gp_constants=OLD_PRIORS)
            rows = {
                "old priors": score(old, a0, e0),
                "new priors": score(shipped_runs(protocol), a0, e0),
            }
            doc[f"priors/{protocol}"] = rows
            md += table(f"GP priors, {protocol} ({len(seeds)} seeds)", rows)
    if "eta" in studies:
        rows = {}
        for eta in (1.0, 2.0, 3.0):
            s = run_setting("toy2d", ["bams", "bas"], toy_seeds, select_kw={"overbudget": eta})
            rows[f"overbudget {eta:g}"] = score(s, a0, e0)
        doc["eta/toy2d"] = rows
        md += table("select --overbudget, toy2d (20 seeds)", rows)
    if "share" in studies:
        rows = {}
        for share in (0.3, 0.5, 0.7):
            s = run_setting("toy2d", ["bams"], toy_seeds, level0_share=share)
            rows[f"level-0 share {share:g}"] = score(s, a0, e0)
        doc["share/toy2d"] = rows
        md += table("Level-0 share of the first (random, mixed) batch, toy2d (20 seeds)", rows)
    if "pooling" in studies:
        rows = {}
        for pooling in ("global", "raw"):
            s = run_setting("toy2d", ["bams"], toy_seeds, select_kw={"pooling": pooling})
            rows[f"pooling {pooling}"] = score(s, a0, e0)
        doc["pooling/toy2d"] = rows
        md += table("select --pooling, toy2d (20 seeds)", rows)
    if "alpha" in studies:
        for protocol in ("toy2d", "av_like"):
            s = shipped_runs(protocol)
            rows = {f"alpha {a:g}, eps {e:g}": score(s, a, e) for a in ALPHAS for e in EPSILONS}
            doc[f"alpha/{protocol}"] = rows
            md += table(f"estimate --alpha / --defensive, {protocol}", rows)
    md.append(f"Wall time {time.perf_counter() - t0:.0f} s.")
    (HERE / "evidence.md").write_text("\n".join(md) + "\n")
    (HERE / "evidence.json").write_text(json.dumps(doc, indent=1) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main(sys.argv[1:] or ["priors", "eta", "share", "pooling", "alpha"])
