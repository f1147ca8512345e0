"""The default staged estimate design as the tool runs it: stage 2 planned from a model
refitted on stage 1's level-0 results.

    .venv/bin/python docs/suite/estimate_refit.py run PROBLEM [--seeds 0-9] [--trials 8]
    .venv/bin/python docs/suite/estimate_refit.py table

``estimate_design.py`` draws the design a thousand times per run and keeps stage 1's p_n for
stage 2, which the evaluation can afford; the tool refits between the stages
(``estimate --plan`` refuses a stale model), and the refit sees stage 1's level-0 outcomes.
Here, for every seed, the suite's protocol runs through the tool (``benchmark.run_one``: a
random mixed batch of 10, two BAMS batches of 5) and stops where it would plan the estimate.
Then, ``--trials`` times from copies of that workspace: ``estimate --plan`` (stage 1, K =
2 p N, its own ``--seed``), the truth simulated and ingested, ``fit
--fixed-hyperparameters`` (as the benchmark refits, at the discovery model's
hyperparameters), and stage 2's design as ``estimate --plan`` builds it (``choose_design``
on the refitted p_n and the posterior the finished stage gives, ``stages.mix_evidence``).
Stage 1's variance is exact; stage 2's is exact given each stage-1 draw and averaged over
the draws. var / uniform: (w_1^2 V_1 + w_2^2 mean V_2) over a uniform Poisson design's of
the same expected size K; beside it the fixed-p evaluation of the same run
(``core.evaluate.staged_trials``, 200 draws).

``run`` appends one JSON line per seed to docs/suite/estimate_refit/PROBLEM.jsonl;
``table`` writes docs/suite/estimate_refit.md from them.
"""

from __future__ import annotations

import json
import shutil
import statistics
import sys
import tempfile
import time
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "estimate_refit"
PROBLEMS = ("toy2d", "av_like", "weak_cheap", "digits", "rare_regions", "gap_sim")


class _Stop(Exception):
    """Raised in place of the protocol's own estimate, once the workspace is kept."""


@dataclass
class SuiteProblem:
    """A suite problem's data as the protocol runs it: where its files are, the truth at
    level 0 by segment, gamma and the estimate's K = k p N."""

    data: Path
    truth: np.ndarray
    pos: dict[str, int]
    gamma: float
    K: float


def suite_problem(problem: str, scratch: Path) -> SuiteProblem:
    """The problem's data generated in ``scratch``, and its truth."""
    from bams_cli import benchmark as bm
    from bams_cli.settings import Settings

    data = bm.prepare_data(bm.PROTOCOLS[problem], None, scratch)
    truth = bm._column(data / "truth.parquet", "value_0").astype(float)
    pos = {s: i for i, s in enumerate(bm._column(data / "truth.parquet", "segment_id").astype(str))}
    gamma = Settings.from_toml((data / "settings.toml").read_text()).gammas[0]
    K = float(round(bm.PROTOCOLS[problem].k_factor * int((truth <= gamma).sum())))
    return SuiteProblem(data, truth, pos, gamma, K)


#: The discovery strategy whose workspaces ``workspaces_before_estimate`` yields
#: (screen_design.py ``coverage --strategy mcm-gp`` sets it).
STRATEGY = "bams"


def workspaces_before_estimate(
    problem: str, prob: SuiteProblem, seeds: list[int], scratch: Path
) -> Iterator[tuple[int, Path]]:
    """(seed, workspace) for each seed: the suite's protocol (``STRATEGY``) run through the tool
    (``benchmark.run_one``) and stopped where it would plan the estimate, its workspace
    copied into ``scratch`` (the caller may remove it)."""
    from bams_cli import benchmark as bm
    from bams_cli import pipeline

    real_plan = pipeline.estimate_plan
    kept: dict[str, Path] = {}

    def keep(root: Path, **_: object) -> None:
        kept["ws"] = scratch / f"ws-{Path(root).name}"
        shutil.copytree(root, kept["ws"])
        raise _Stop

    for seed in seeds:
        pipeline.estimate_plan = keep
        try:
            spec = bm.RunSpec(problem, STRATEGY, seed, str(prob.data), str(scratch), 0.5, 6, prob.K)
            bm.run_one(spec)
        except _Stop:
            pass
        finally:
            pipeline.estimate_plan = real_plan
        yield seed, kept["ws"]


def run(problem: str, seeds: list[int], trials: int) -> None:
    from bams_cli import benchmark as bm
    from bams_cli import defaults, pipeline
    from bams_cli import stages as st
    from bams_cli.core import design as dz
    from bams_cli.core.evaluate import staged_trials
    from bams_cli.state.workspace import Workspace

    warnings.simplefilter("ignore")
    scratch = Path(tempfile.mkdtemp(prefix=f"estimate-refit-{problem}-"))
    prob = suite_problem(problem, scratch)
    data, truth, pos, gamma, K = prob.data, prob.truth, prob.pos, prob.gamma, prob.K
    real_plan = pipeline.estimate_plan

    def level0(ws: Workspace, ids: np.ndarray) -> np.ndarray:
        obs = ws.read_observations()
        return np.isin(ids, obs.filter(obs["fidelity"] == 0)["segment_id"].to_numpy().astype(str))

    OUT.mkdir(exist_ok=True)
    for seed, base in workspaces_before_estimate(problem, prob, seeds, scratch):
        ids = bm._column(base / "scores.parquet", "segment_id").astype(str)
        p = bm._column(base / "scores.parquet", "p_0").astype(float)
        fail = truth[[pos[s] for s in ids]] <= gamma
        known = level0(Workspace(base), ids)
        U1 = np.flatnonzero(~known)
        K1 = defaults.STAGE1_SHARE * K
        pi1 = dz.choose_design(p[U1], K=K1, posterior=dz.risk_posterior([])).pi
        f1 = fail[U1]
        V1 = float(((1 - pi1[f1]) / pi1[f1]).sum())
        V2, lam2 = [], []
        t0 = time.perf_counter()
        for t in range(trials):
            root = scratch / f"trial-{seed}-{t}"
            shutil.copytree(base, root)
            plan = real_plan(root, samples=K, seed=1000 * seed + t, **bm.PLAN_DEFAULTS)
            res = root / "stage-1-results.parquet"
            pipeline.simulate(Path(plan["handoff"]), data / "truth.parquet", res)
            pipeline.ingest_results(root, res)
            pipeline.fit(root, fixed_hyperparameters=root / "model.json", **bm.FIT_DEFAULTS)
            ws2 = Workspace(root)
            p2 = bm._column(root / "scores.parquet", "p_0").astype(float)
            U2 = np.flatnonzero(~level0(ws2, ids))
            post = dz.risk_posterior(st.mix_evidence(ws2, gamma)[0])
            pi2 = dz.choose_design(p2[U2], K=min(K - K1, U2.size), posterior=post).pi
            f2 = fail[U2]
            V2.append(float(((1 - pi2[f2]) / pi2[f2]).sum()))
            lam2.append(post.lam_mean)
            shutil.rmtree(root)
        w1 = defaults.STAGE1_SHARE
        var_u = int(f1.sum()) * (U1.size - K) / K
        fixed = staged_trials(
            p, fail, K=K, known=known, n_trials=200, rng=np.random.default_rng(seed)
        )
        row = {
            "problem": problem, "seed": seed, "trials": trials, "K": K,
            "ratio_refit": (w1**2 * V1 + (1 - w1) ** 2 * float(np.mean(V2))) / var_u,
            "ratio_fixed": fixed.var / fixed.var_uniform,
            "lam2": float(np.mean(lam2)), "seconds_per_trial": (time.perf_counter() - t0) / trials,
        }  # fmt: skip
        with open(OUT / f"{problem}.jsonl", "a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)
        shutil.rmtree(base)
    shutil.rmtree(scratch, ignore_errors=True)


def table() -> None:
    lines = [
        "# The staged estimate design with the tool's refit between stages",
        "",
        "`docs/suite/estimate_refit.py` (its docstring says how): BAMS runs of the suite "
        "protocol, stage 2 planned from the model refitted on stage 1's level-0 results, as "
        "`estimate --plan` does. var / uniform: the design's variance over a uniform Poisson "
        "design's of the same expected size, mean [max] over seeds; fixed p: the same runs "
        "under `estimate_design.py`'s evaluation, which keeps stage 1's p_n for stage 2. lam: "
        "the posterior mean share of failure mass stage 2 leaves to uniform risk. One JSON "
        "line per seed in docs/suite/estimate_refit/PROBLEM.jsonl (measured 2026-11-24 with "
        "a Beta(0.5, 1) prior on lam and shapes tau 0.5 and 1, the defaults since; "
        "gap_sim again on 2026-11-25, its embedding reduced by `embed-reduce --dim auto` "
        "to 12 components; the other five later that day, at `--dim auto` and with the "
        "discrepancy prior centred on the pairs' variance: their discovery models, and so "
        "the hyperparameters the refit keeps, changed).",
        "",
        "| problem | seeds | stage-1 draws per seed | var / uniform, refit | var / uniform, fixed p | lam |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for problem in PROBLEMS:
        path = OUT / f"{problem}.jsonl"
        if not path.exists():
            continue
        rows = [json.loads(line) for line in path.read_text().splitlines() if line]
        a = [r["ratio_refit"] for r in rows]
        b = [r["ratio_fixed"] for r in rows]
        lines.append(
            f"| {problem} | {len(rows)} | {rows[0]['trials']} | {statistics.mean(a):.3f} "
            f"[{max(a):.3f}] | {statistics.mean(b):.3f} [{max(b):.3f}] | "
            f"{statistics.mean(r['lam2'] for r in rows):.2f} |"
        )
    (HERE / "estimate_refit.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def seeds_and_trials(argv: list[str], seeds: str, trials: int) -> tuple[list[int], int]:
    """``--seeds LO-HI`` and ``--trials T`` from ``argv``, else the defaults given."""
    if "--seeds" in argv:
        seeds = argv[argv.index("--seeds") + 1]
    lo, hi = seeds.split("-")
    if "--trials" in argv:
        trials = int(argv[argv.index("--trials") + 1])
    return list(range(int(lo), int(hi) + 1)), trials


def main(argv: list[str]) -> None:
    if argv[:1] == ["table"]:
        table()
        return
    if argv[:1] != ["run"] or len(argv) < 2:
        raise SystemExit(__doc__)
    run(argv[1], *seeds_and_trials(argv, "0-9", 8))


if __name__ == "__main__":
    main(sys.argv[1:])
