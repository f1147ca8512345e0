"""The evidence behind the defaults the problem suite chose (README, "Defaults, and why").

    .venv/bin/python docs/suite/evidence.py                 # every study, ~2 h on 2 cores
    .venv/bin/python docs/suite/evidence.py confirm          # some studies only

Each study runs BAMS on every problem of the suite (``bams-cli benchmark --protocol
suite``: the four problems of ``core.suite`` and toy2d; ``benchmark.run_one``, the real
select, simulate, ingest-results and fit path) for several settings over the same seeds,
and tabulates per problem: the default estimator design's exact recall and 100 x relative
variance (``benchmark.design_stats``), the fitted level-1 discrepancy sd over the true one
in the model's units, level-0 picks per batch, and the GP's own estimate over the true
rate. A setting that differs from the shipped defaults is applied in each worker process
before it runs (GP priors replace ``core.gp.priors.DEFAULT_PRIORS``; select options are
passed to ``pipeline.select`` for BAMS batches). Nothing here changes the shipped
defaults; it shows what the alternatives did.

Studies:
  discrepancy  the discrepancy prior: shipped (mode 0.01, log-sd 1.0) vs (0.1, 1.5)
  discrepancy-width  the shipped mode with a wider log-sd (1.25, 1.5); with av_like
  confirm      select --confirm-share 0 (the plain greedy), 0.2 (shipped), 0.4
  discrepancy-pairs  the discrepancy prior's mode at the pairs' variance (shipped since
               2026-11-25) vs held at 0.01 whatever the pairs show

Writes docs/suite/evidence.md (tables) and evidence.json (per-seed numbers).
"""

from __future__ import annotations

import dataclasses
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
PROBLEMS = ("weak_cheap", "digits", "rare_regions", "gap_sim", "toy2d", "av_like")
SEEDS = range(10)
STUDIES: dict[str, dict[str, tuple[dict[str, Any], dict[str, Any]]]] = {
    # setting name -> (GP prior overrides, BAMS select options)
    "discrepancy": {
        "shipped": ({}, {}),
        "discrepancy prior (0.1, 1.5)": ({"discrepancy": (0.1, 1.5)}, {}),
    },
    "discrepancy-width": {
        "shipped": ({}, {}),
        "discrepancy prior (0.01, 1.25)": ({"discrepancy": (0.01, 1.25)}, {}),
        "discrepancy prior (0.01, 1.5)": ({"discrepancy": (0.01, 1.5)}, {}),
    },
    "discrepancy-pairs": {
        # Explicit flags, so neither setting is taken for an older study's "shipped" run.
        "mode fixed at 0.01": ({"discrepancy_from_pairs": False}, {}),
        "mode from pairs (shipped)": ({"discrepancy_from_pairs": True}, {}),
    },
    "confirm": {
        "confirm-share 0": ({}, {"confirm_share": 0.0}),
        "confirm-share 0.2 (shipped)": ({}, {}),
        "confirm-share 0.4": ({}, {"confirm_share": 0.4}),
    },
}


#: Where and when the saved runs were made (evidence.json keeps the numbers, not this).
NOTES = """\
These runs (2026-11-23, 2 cores, other work running): the first four (weak_cheap and
digits under both discrepancy settings) at commit a2b71a7, the rest of the discrepancy and
confirm studies at commit 6bbb098, where rare_regions' failure regions got basins; in
between came the lock, `status` and strict-JSON work, which change none of these numbers:
the shipped rows equal the BAMS rows of docs/reproduction/suite/suite.md (made at ec5abc9
and 6bbb098) to the last digit.

discrepancy-width (2026-11-24, commit 81bbf56, 2 workers, other work running; the shipped
rows equal docs/reproduction/suite/suite.md's BAMS rows, made at 3aa36ac, to the last
digit): a wider prior around the same mode lets the pairs of levels pull the discrepancy up
where the shipped prior holds it low (weak_cheap 0.66 -> 0.77 and 0.84 of the truth, median),
and more level-0 picks follow; but the seeds within 2x do not rise overall (57 of 60 shipped,
56 at log-sd 1.25, 55 at 1.5): gap_sim's stationary misfit then goes into the discrepancy
(up to 2.55x and 2.76x the truth), and toy2d's worst seed crosses 2x at 1.25. rare_regions'
recall doubles (0.007 -> 0.013 and 0.014, 2.1x plain MC's 0.0067), a difference of 1.3
and 1.6 standard errors, and its discrepancy stays below 0.5x on one or two seeds whatever
the width.
The shipped (0.01, 1.0) stays.

discrepancy-pairs (2026-11-25, 2 workers): the same prior (0.01, 1.0) with its mode moved
to the pairs' variance once 3 segments are run at both levels (shipped since), against the
mode held at 0.01. The fixed-mode rows ran at commit d78ae39 and equal
docs/reproduction/suite/suite.md's BAMS rows at 3c3c846 to the last digit. The from-pairs
rows ran before d78ae39 was committed, from a working tree whose code was d78ae39's (only
comments and formatting differed), through the same ``run_setting`` driven from a scratch
script, hence no timings; they equal the suite's BAMS rows at b5858e2 to the last digit. Every problem's discrepancy is within 2x on
10 seeds of 10 (weak_cheap 7 and rare_regions 8 with the fixed mode; 60 of 60 against
55); weak_cheap's median ratio rises from 0.67 to 1.05 and it finds more (recall 0.075 ->
0.095, 100 RV 32.5 -> 26.9); av_like's RV falls from 9.4 to 4.0. digits (0.127 -> 0.116)
and rare_regions (0.018 -> 0.016) find less, within one SE; toy2d's median rises from
1.43 to 1.58 (worst seed 1.82 either way); gap_sim's pairs never show more than 0.01 and
its rows are unchanged.
"""


def _worker(spec: B.RunSpec, priors: dict[str, Any], select_kw: dict[str, Any]) -> dict[str, Any]:
    """One BAMS run with the given priors and select options; what the tables need."""
    from bams_cli.core.gp import priors as P

    P.DEFAULT_PRIORS = dataclasses.replace(P.DEFAULT_PRIORS, **priors)
    if select_kw:
        original = pipeline.select

        def select(root, **kw):
            if kw.get("strategy") == "bams":
                kw.update(select_kw)
            return original(root, **kw)

        pipeline.select = select  # benchmark.run_one calls pipeline.select
    r = B.run_one(spec)
    return {
        "seed": r.seed,
        "p": r.p_after[-1],
        "known": r.known,
        "hp": r.hyperparameters[-1],
        "level0": [int((lv == 0).sum()) for _, lv in r.picks],
    }


def run_setting(problem: str, priors: dict[str, Any], select_kw: dict[str, Any]) -> dict:
    proto = B.PROTOCOLS[problem]
    with tempfile.TemporaryDirectory(prefix="bams-suite-evidence-") as tmp:
        data = B.prepare_data(proto, None, Path(tmp))
        f0 = B._column(data / "truth.parquet", "value_0").astype(np.float64)
        f1 = B._column(data / "truth.parquet", "value_1").astype(np.float64)
        gamma = Settings.from_toml((data / "settings.toml").read_text()).gammas[0]
        fail = f0 <= gamma
        K = float(round(proto.k_factor * fail.sum()))
        specs = [B.RunSpec(problem, "bams", s, str(data), tmp, 0.5, 6, K) for s in SEEDS]
        with ProcessPoolExecutor(2, mp_context=mp.get_context("spawn")) as pool:
            runs = list(pool.map(_worker, specs, [priors] * len(specs), [select_kw] * len(specs)))
    est = B.estimate_defaults()
    rows = []
    for r in runs:
        recall, rv = B.design_stats(
            r["p"], fail, K=K, known=r["known"], alpha=est["alpha"],
            defensive=est["defensive"], design=est["design"],
        )  # fmt: skip
        disc = B.discrepancy_sd(r["hp"]) / B.true_discrepancy_sd(
            f0, f1, r["hp"].get("transform"), B.level_scale(r["hp"])
        )
        rows.append(
            {
                "seed": r["seed"],
                "recall": recall,
                "rv100": 100 * rv,
                "disc_ratio": disc,
                "level0": r["level0"],
                "gp_ratio": float(np.mean(r["p"]) / fail.mean()),
                "transform": (r["hp"].get("transform") or {}).get("kind", "identity"),
            }
        )
    return {"K": K, "rate": float(fail.mean()), "runs": rows}


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    rec = np.array([r["recall"] for r in rows])
    rv = np.array([r["rv100"] for r in rows])
    disc = np.array([r["disc_ratio"] for r in rows])
    gp = np.array([r["gp_ratio"] for r in rows])
    level0 = np.array([r["level0"] for r in rows])
    return {
        "recall": float(rec.mean()),
        "recall_se": float(rec.std(ddof=1) / np.sqrt(rec.size)),
        "rv": float(rv.mean()),
        "rv_median": float(np.median(rv)),
        "disc_ratio": [float(disc.min()), float(np.median(disc)), float(disc.max())],
        "disc_within_2x": int(np.sum((disc >= 0.5) & (disc <= 2.0))),
        "level0_per_batch": level0.mean(axis=0).round(2).tolist(),
        "gp_ratio": [float(gp.min()), float(gp.mean()), float(gp.max())],
        "asinh_runs": int(sum(r["transform"] == "asinh" for r in rows)),
        "seeds": len(rows),
    }


def render(results: dict[str, dict[str, dict[str, Any]]]) -> str:
    lines = [
        "# The suite's evidence for the defaults",
        "",
        "BAMS on each suite problem, seeds 0-9, the protocol of `bams-cli benchmark "
        "--protocol suite` (random mixed batch of 10, then 2 x 5 by BAMS, K = 2 p N). "
        "recall and 100 RV: the default estimator design, exact. disc. fitted / true: the "
        "final model's level-1 discrepancy sd over the true sd(g(f1) - g(f0)), "
        "min / median / max over seeds and the seeds within a factor 2. GP / p: mean(p_n) "
        "over the true rate, min / mean / max. Regenerate with "
        "`.venv/bin/python docs/suite/evidence.py`.",
        "",
    ]
    for study, settings in results.items():
        lines += [
            f"## {study}",
            "",
            "| problem | setting | recall ± SE | 100 RV mean (median) | disc. fitted / true "
            "(within 2x) | level-0 picks per batch | GP / p | asinh fits |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for problem in PROBLEMS:
            for name, per in settings.items():
                s = per.get(problem)
                if s is None:
                    continue
                d, g = s["disc_ratio"], s["gp_ratio"]
                lines.append(
                    f"| {problem} | {name} | {s['recall']:.3f} ± {s['recall_se']:.3f} | "
                    f"{s['rv']:.3g} ({s['rv_median']:.3g}) | {d[0]:.2f} / {d[1]:.2f} / "
                    f"{d[2]:.2f} ({s['disc_within_2x']}/{s['seeds']}) | "
                    f"{' / '.join(f'{v:g}' for v in s['level0_per_batch'])} | "
                    f"{g[0]:.2f} / {g[1]:.2f} / {g[2]:.2f} | {s['asinh_runs']}/{s['seeds']} |"
                )
        lines.append("")
    return "\n".join(lines) + "\n" + NOTES


def _same_setting(
    saved: dict[str, Any], priors: dict[str, Any], select_kw: dict[str, Any], problem: str
) -> str | None:
    """The key of a finished run of the same (priors, select options) on ``problem``."""
    for study, settings in STUDIES.items():
        for name, (p, s) in settings.items():
            key = f"{study}/{name}/{problem}"
            if key in saved and p == priors and s == select_kw:
                return key
    return None


def main(argv: list[str]) -> None:
    studies = argv or list(STUDIES)
    path = HERE / "evidence.json"
    saved = json.loads(path.read_text()) if path.exists() else {}
    for study in studies:
        for name, (priors, select_kw) in STUDIES[study].items():
            for problem in PROBLEMS:
                key = f"{study}/{name}/{problem}"
                if key in saved:  # resumable: a finished setting is not rerun
                    continue
                same = _same_setting(saved, priors, select_kw, problem)
                if same is not None:  # e.g. "shipped" in two studies: run once
                    saved[key] = saved[same]
                    continue
                t0 = time.perf_counter()
                out = run_setting(problem, priors, select_kw)
                out["summary"] = summarise(out["runs"])
                out["seconds"] = round(time.perf_counter() - t0, 1)
                saved[key] = out
                path.write_text(json.dumps(saved, indent=1) + "\n")
                print(f"{key}: {out['summary']['recall']:.3f} in {out['seconds']} s", flush=True)
    results: dict[str, dict[str, dict[str, Any]]] = {}
    for key, out in saved.items():
        study, name, problem = key.split("/")
        results.setdefault(study, {}).setdefault(name, {})[problem] = out["summary"]
    (HERE / "evidence.md").write_text(render(results))


if __name__ == "__main__":
    main(sys.argv[1:])
