"""The default staged estimate design as the tool runs it: stage 2 planned from a model
refitted on stage 1's level-0 results.

    .venv/bin/python docs/suite/estimate_refit.py run PROBLEM [--seeds 0-9] [--trials 8]
    .venv/bin/python docs/suite/estimate_refit.py recall PROBLEM [--optimise]
    .venv/bin/python docs/suite/estimate_refit.py stages PROBLEM [--stages S] [--share1 X] [--optimise]
    .venv/bin/python docs/suite/estimate_refit.py table

(``stages`` without ``--stages`` and ``--share1``: the tool's default stages.)

``estimate_design.py`` draws the design a thousand times per run and keeps stage 1's p_n for
every later stage, which the evaluation can afford; the tool refits between the stages
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


def level0(ws, ids: np.ndarray) -> np.ndarray:  # noqa: ANN001
    """Which of ``ids`` have a level-0 result in the workspace's log."""
    obs = ws.read_observations()
    return np.isin(ids, obs.filter(obs["fidelity"] == 0)["segment_id"].to_numpy().astype(str))


def _start(problem: str, what: str) -> tuple[Path, SuiteProblem]:
    """A scratch folder and the problem's data generated in it, warnings off."""
    warnings.simplefilter("ignore")
    scratch = Path(tempfile.mkdtemp(prefix=f"estimate-{what}-{problem}-"))
    return scratch, suite_problem(problem, scratch)


def _seed_state(base: Path, prob: SuiteProblem) -> tuple[np.ndarray, ...]:
    """A kept workspace's segment ids, p_n, true failures and level-0 knowns, in its order."""
    from bams_cli import benchmark as bm
    from bams_cli.state.workspace import Workspace

    ids = bm._column(base / "scores.parquet", "segment_id").astype(str)
    p = bm._column(base / "scores.parquet", "p_0").astype(float)
    fail = prob.truth[[prob.pos[s] for s in ids]] <= prob.gamma
    return ids, p, fail, level0(Workspace(base), ids)


#: ``run`` and ``recall`` measure the two stages of half K the tool drew until 2026-11-29
#: (``stages`` measures any number).
TWO_STAGES = {"stages": 2, "stage1_share": 0.5}


def _stage1_refitted(
    base: Path, root: Path, prob: SuiteProblem, *, K: float, seed: int, optimise: bool
) -> tuple:
    """A copy of ``base`` with stage 1 (of two halves) planned, simulated, ingested and
    refitted (``optimise``: the MAP search; else at the discovery hyperparameters): its
    workspace and the refitted p_n."""
    from bams_cli import benchmark as bm
    from bams_cli import pipeline
    from bams_cli.state.workspace import Workspace

    shutil.copytree(base, root)
    plan = pipeline.estimate_plan(root, samples=K, seed=seed, **{**bm.PLAN_DEFAULTS, **TWO_STAGES})
    res = root / "stage-1-results.parquet"
    pipeline.simulate(Path(plan["handoff"]), prob.data / "truth.parquet", res)
    pipeline.ingest_results(root, res)
    fixed = None if optimise else root / "model.json"
    pipeline.fit(root, fixed_hyperparameters=fixed, **bm.FIT_DEFAULTS)
    return Workspace(root), bm._column(root / "scores.parquet", "p_0").astype(float)


def run(problem: str, seeds: list[int], trials: int) -> None:
    from bams_cli import stages as st
    from bams_cli.core import design as dz
    from bams_cli.core.evaluate import staged_trials

    scratch, prob = _start(problem, "refit")
    gamma, K = prob.gamma, prob.K

    OUT.mkdir(exist_ok=True)
    for seed, base in workspaces_before_estimate(problem, prob, seeds, scratch):
        ids, p, fail, known = _seed_state(base, prob)
        U1 = np.flatnonzero(~known)
        K1 = TWO_STAGES["stage1_share"] * K
        pi1 = dz.choose_design(p[U1], K=K1, posterior=dz.risk_posterior([])).pi
        f1 = fail[U1]
        V1 = float(((1 - pi1[f1]) / pi1[f1]).sum())
        V2, lam2 = [], []
        t0 = time.perf_counter()
        for t in range(trials):
            root = scratch / f"trial-{seed}-{t}"
            ws2, p2 = _stage1_refitted(
                base, root, prob, K=K, seed=1000 * seed + t, optimise=False
            )  # fmt: skip
            U2 = np.flatnonzero(~level0(ws2, ids))
            post = dz.risk_posterior(st.mix_evidence(ws2, gamma)[0])
            pi2 = dz.choose_design(p2[U2], K=min(K - K1, U2.size), posterior=post).pi
            f2 = fail[U2]
            V2.append(float(((1 - pi2[f2]) / pi2[f2]).sum()))
            lam2.append(post.lam_mean)
            shutil.rmtree(root)
        w1 = TWO_STAGES["stage1_share"]
        var_u = int(f1.sum()) * (U1.size - K) / K
        fixed = staged_trials(
            p, fail, K=K, known=known, n_trials=200, rng=np.random.default_rng(seed),
            stages=2, share=0.5,
        )  # fmt: skip
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


def recall(problem: str, seeds: list[int], trials: int, optimise: bool) -> None:
    """Recall as the tool runs the estimate: stage 1 drawn by ``estimate --plan`` (its open
    leads with certainty), its truth ingested, the model refitted (``--optimise``: the MAP
    search again, as a plain ``fit`` does; else at the discovery model's hyperparameters),
    stage 2's design from the refit (``choose_design`` at the checked posterior, as
    ``estimate --plan`` builds it). recall = (failures at level 0 after stage 1 + the
    failures stage 2's pi sums to) / all failures, averaged over the draws; beside it the
    fixed-p evaluation of the same run with its leads (``staged_trials``, 200 draws)."""
    from bams_cli import stages as st
    from bams_cli.core import design as dz
    from bams_cli.core.evaluate import staged_trials
    from bams_cli.pipeline.estimation import open_leads
    from bams_cli.state.workspace import Workspace

    scratch, prob = _start(problem, "recall")
    truth, gamma, K = prob.truth, prob.gamma, prob.K

    OUT.mkdir(exist_ok=True)
    for seed, base in workspaces_before_estimate(problem, prob, seeds, scratch):
        ids, p, fail, known = _seed_state(base, prob)
        F = int((truth <= gamma).sum())
        got = []
        t0 = time.perf_counter()
        for t in range(trials):
            root = scratch / f"trial-{seed}-{t}"
            ws2, p2 = _stage1_refitted(
                base, root, prob, K=K, seed=1000 * seed + t, optimise=optimise
            )  # fmt: skip
            after1 = level0(ws2, ids)
            U2 = np.flatnonzero(~after1)
            post = dz.risk_posterior(st.mix_evidence(ws2, gamma)[0])
            K2 = min((1 - TWO_STAGES["stage1_share"]) * K, U2.size)
            pi2 = dz.choose_design(p2[U2], K=K2, posterior=post).pi
            got.append((int(fail[after1].sum()) + float(pi2[fail[U2]].sum())) / F)
            shutil.rmtree(root)
        ws = Workspace(base)
        lead_m, facts = open_leads(
            ws, ids, p, known, gamma, ws.pending(), K=K,
            scales=json.loads((base / "model.json").read_text())["hyperparameters"].get("scales")
            or (),
        )  # fmt: skip
        lead_share = facts["share"]
        fx = staged_trials(
            p, fail, K=K, known=known, n_trials=200, rng=np.random.default_rng(seed),
            leads=lead_m, lead_share=lead_share, stages=2, share=0.5,
        )  # fmt: skip
        row = {
            "problem": problem, "seed": seed, "trials": trials, "K": K, "optimise": optimise,
            "recall_refit": float(np.mean(got)), "recall_fixed": float(np.mean(fx.recall)),
            "seconds_per_trial": (time.perf_counter() - t0) / trials,
        }  # fmt: skip
        with open(OUT / f"recall-{problem}.jsonl", "a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)
        shutil.rmtree(base)
    shutil.rmtree(scratch, ignore_errors=True)


def staged_path(
    problem: str, seeds: list[int], trials: int, n_stages: int, share1: float, optimise: bool
) -> None:
    """The staged estimate as the tool runs it, every stage planned by ``estimate --plan``
    from the model refitted on the stages before it (``--optimise``: the MAP search again,
    as a plain ``fit`` does; else at the discovery model's hyperparameters).

    Each stage's inclusion probabilities over its U_s are caught as the plan draws them
    (``core.estimate.draw_poisson``), so its variance given the stages before is exact:
    V_s = sum over the failures of U_s of (1 - pi)/pi. The stages' HT totals are
    conditionally unbiased for the same total, so their errors are uncorrelated and the
    design's variance is sum_s w_s^2 E[V_s], the mean over the draws standing for E.
    var / uniform: over a uniform Poisson design of K level-0 runs over U. recall: the
    failures with a level-0 result after the last stage's draw, in expectation over the
    last draw (its pi summed over the failures left), over all failures."""
    from bams_cli import benchmark as bm
    from bams_cli import pipeline
    from bams_cli.core import estimate as est_mod
    from bams_cli.state.workspace import Workspace

    scratch, prob = _start(problem, "stages")
    data, truth, gamma, K = prob.data, prob.truth, prob.gamma, prob.K
    real_plan, real_draw = pipeline.estimate_plan, est_mod.draw_poisson
    caught: list[np.ndarray] = []

    def catch(pi: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        caught.append(np.asarray(pi, dtype=np.float64).copy())
        return real_draw(pi, rng)

    OUT.mkdir(exist_ok=True)
    opts = {**bm.PLAN_DEFAULTS, "stages": n_stages, "stage1_share": share1, "screen": "off"}
    for seed, base in workspaces_before_estimate(problem, prob, seeds, scratch):
        ids, _, fail, known0 = _seed_state(base, prob)
        F = int((truth <= gamma).sum())
        U0 = int((~known0).sum())
        var_u = int(fail[~known0].sum()) * (U0 - K) / K
        V = np.zeros((trials, n_stages))
        rec, weights = [], None
        t0 = time.perf_counter()
        est_mod.draw_poisson = catch
        try:
            for t in range(trials):
                root = scratch / f"trial-{seed}-{t}"
                shutil.copytree(base, root)
                for s in range(n_stages):
                    known = level0(Workspace(root), ids)
                    caught.clear()
                    plan = real_plan(
                        root, samples=K, seed=1000 * seed + 10 * t + s, **opts
                    )  # fmt: skip
                    pi = caught[-1]
                    if pi.size != int((~known).sum()):
                        raise RuntimeError("the caught design is not over U")
                    fU = fail[~known]
                    V[t, s] = float(((1 - pi[fU]) / pi[fU]).sum())
                    weights = plan["stage_weights"]
                    if s == n_stages - 1:
                        rec.append((int(fail[known].sum()) + float(pi[fU].sum())) / F)
                        break
                    res = root / f"stage-{s + 1}-results.parquet"
                    pipeline.simulate(Path(plan["handoff"]), data / "truth.parquet", res)
                    pipeline.ingest_results(root, res)
                    fixed = None if optimise else root / "model.json"
                    pipeline.fit(root, fixed_hyperparameters=fixed, **bm.FIT_DEFAULTS)
                shutil.rmtree(root)
        finally:
            est_mod.draw_poisson = real_draw
        w = np.asarray(weights, dtype=np.float64)
        row = {
            "problem": problem, "seed": seed, "trials": trials, "K": K, "optimise": optimise,
            "stages": n_stages, "stage1_share": share1, "weights": w.tolist(),
            "var_ratio": float((w**2 * V.mean(axis=0)).sum() / var_u),
            "recall": float(np.mean(rec)), "mc_recall_K": K / U0,
            "seconds_per_trial": (time.perf_counter() - t0) / trials,
        }  # fmt: skip
        with open(OUT / f"stages-{problem}.jsonl", "a") as fh:
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
    lines += _recall_lines() + _stages_lines()
    (HERE / "estimate_refit.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


#: Plain MC's recall at the same cost on the suite (README, the suite table).
PLAIN_MC = {
    "toy2d": 0.0093, "av_like": 0.0428, "weak_cheap": 0.0323,
    "digits": 0.0580, "rare_regions": 0.0057, "gap_sim": 0.0138,
}  # fmt: skip


def _rows(kind: str, problem: str) -> list[dict]:
    path = OUT / f"{kind}-{problem}.jsonl"
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line]


def _x(r: float, problem: str) -> str:
    return f"{r:.4f} ({r / PLAIN_MC[problem]:.1f}x)"


def _recall_lines() -> list[str]:
    out = [
        "",
        "## Recall with the refit between the stages",
        "",
        "`estimate_refit.py recall PROBLEM [--optimise]` (2026-11-29, two stages of half K, "
        "the default until then): the same runs' recall (the share of "
        "all failures with a level-0 result after the estimate, in expectation over stage 2's "
        "draw; x: over the suite's plain MC recall at the same cost), stage 1 drawn by "
        "`estimate --plan` with its open leads, stage 2 planned from the refitted model: at "
        "the discovery model's hyperparameters (fixed hyperparameters), or by the MAP search "
        "again (`--optimise`), as a plain `fit` between the stages does. Beside it the "
        "fixed-p evaluation of the same runs (stage 2 keeping stage 1's p_n, as the suite "
        "table and `estimate_design.md` evaluated the default then). 4 stage-1 draws per seed.",
        "",
        "| problem | seeds | recall, refit at fixed hyperparameters | recall, refit with the MAP search | recall, fixed p |",
        "| --- | --- | --- | --- | --- |",
    ]
    for problem in PROBLEMS:
        rows = _rows("recall", problem)
        if not rows:
            continue
        got = {}
        for opt in (False, True):
            mine = [r["recall_refit"] for r in rows if r["optimise"] == opt]
            got[opt] = _x(statistics.mean(mine), problem) if mine else "-"
        fixed = statistics.mean(r["recall_fixed"] for r in rows if not r["optimise"])
        n = len([r for r in rows if r["optimise"]]) or len(rows)
        out.append(f"| {problem} | {n} | {got[False]} | {got[True]} | {_x(fixed, problem)} |")
    return out


def _stages_lines() -> list[str]:
    from bams_cli import defaults

    default = (defaults.STAGES, round(defaults.STAGE1_SHARE, 2))
    out = [
        "",
        "## Two, three or four stages",
        "",
        "`estimate_refit.py stages PROBLEM --stages S --share1 X --optimise`: the staged "
        "estimate as the tool runs it, every stage planned by `estimate --plan` from the "
        "model refitted (MAP search) on the stages before it; each stage's design caught as "
        "it is drawn, so its variance given the stages before is exact, and the design's "
        "variance sum_s w_s^2 E[V_s] (the stages' errors are uncorrelated) is averaged over "
        "4 draws per seed. var / uniform: mean [max] over seeds. recall as above. Against "
        f"the default ({default[0]} stages, stage 1 {default[1]:.2f} of K): the difference "
        "in recall, mean ± SE over the seeds, paired (every row of a problem on the same "
        "discovery runs). Measured 2026-11-29 (two and three stages 19:16-19:50, four "
        "22:15-22:30); three stages of a third each are the default since.",
        "",
        "| problem | stages | stage 1's share | seeds | var / uniform | recall | recall less "
        "the default's |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for problem in PROBLEMS:
        rows = _rows("stages", problem)
        key_of = lambda r: (r["stages"], round(r["stage1_share"], 2))  # noqa: E731
        base = {r["seed"]: r["recall"] for r in rows if key_of(r) == default}
        for key in sorted({key_of(r) for r in rows}):
            mine = [r for r in rows if key_of(r) == key]
            v = [r["var_ratio"] for r in mine]
            rec = statistics.mean(r["recall"] for r in mine)
            diff = [r["recall"] - base[r["seed"]] for r in mine if r["seed"] in base]
            paired = (
                f"{statistics.mean(diff):+.4f} ± {statistics.stdev(diff) / len(diff) ** 0.5:.4f}"
                if key != default and len(diff) > 1
                else "-"
            )
            out.append(
                f"| {problem} | {key[0]} | {key[1]:.2f} | {len(mine)} | "
                f"{statistics.mean(v):.3f} [{max(v):.3f}] | {_x(rec, problem)} | {paired} |"
            )
    out += [
        "",
        "A fourth stage moved recall by less than its SE on all three problems (weak_cheap "
        "+0.0017 ± 0.0038, digits +0.0023 ± 0.0051, rare_regions -0.0013 ± 0.0019) and the "
        "variance by 0.004-0.04 of uniform's, down; going from two stages to three had moved weak_cheap's "
        "recall by 6.7 SEs and rare_regions' by 1.8. So the default stays at three, a round "
        "of simulation fewer for the study, and four stages are not the way to issue 11's "
        "2x on digits or 5x on rare_regions.",
    ]
    return out


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
    if argv[:1] not in (["run"], ["recall"], ["stages"]) or len(argv) < 2:
        raise SystemExit(__doc__)
    if argv[:1] == ["stages"] and len(argv) >= 2:
        from bams_cli import defaults

        # Without the flags, the tool's default stages.
        n = int(argv[argv.index("--stages") + 1]) if "--stages" in argv else defaults.STAGES
        sh = (
            float(argv[argv.index("--share1") + 1]) if "--share1" in argv else defaults.STAGE1_SHARE
        )
        staged_path(argv[1], *seeds_and_trials(argv, "0-9", 4), n, sh, "--optimise" in argv)
        return
    if argv[:1] == ["recall"] and len(argv) >= 2:
        recall(argv[1], *seeds_and_trials(argv, "0-9", 4), "--optimise" in argv)
        return
    run(argv[1], *seeds_and_trials(argv, "0-9", 8))


if __name__ == "__main__":
    main(sys.argv[1:])
