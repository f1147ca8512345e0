"""The screened estimate design (``core.screen``) measured through the tool on the suite.

    .venv/bin/python docs/suite/screen_design.py run PROBLEM [--seeds 0-9] [--trials 4]
    .venv/bin/python docs/suite/screen_design.py coverage PROBLEM [--seeds 0-9] [--trials 8] [--strategy mcm-gp] [--default]
    .venv/bin/python docs/suite/screen_design.py predict PROBLEM [--seeds 0-4]
    .venv/bin/python docs/suite/screen_design.py signals PROBLEM [--seeds 0-9]
    .venv/bin/python docs/suite/screen_design.py table

For every seed the suite's BAMS protocol runs through the tool and stops where it would plan
the estimate (``estimate_refit.workspaces_before_estimate``). From that workspace, for each
screen share of K (0.2, 0.3, 0.4) and each phase-1 design ("uniform": pi1 = n1 / |U|;
"design": ``core.screen.screen_design``, the estimate's own design choice at the screen's
size), ``--trials`` times: phase 1 draws S1, the truth's cheap-level values of S1 are
appended to the observation log (as ingesting the screen's results would), the model is
refitted at the discovery model's hyperparameters (``fit --fixed-hyperparameters``, as the
benchmark refits), and phase 2's pi2 over S1 comes from the refitted p_0 with K2 = K - c |S1|
under two rules: "plain" (``core.screen.confirm_design``) and "weighted" (the risk weighted
by 1/pi1^2, the minimiser of the predicted variance, against uniform).

var = phase1_variance (exact) + mean over the trials' screens of phase2_variance (exact
given S1),
over the variance of a uniform Poisson design of K level-0 runs (the shipped estimate's
comparison); recall = (failures known before the estimate + expected level-0 failures of
phase 2) / all failures, the suite's recall at the same cost (the screen's cheap runs are
paid out of K). "one stage": the estimate's design choice over U at K, no screen, on the
same workspace (the shipped default runs it in stages, three since 2026-11-29, with a refit; its recall is the
same to within the seeds' spread, docs/suite/estimate_refit.md).

``run`` appends one JSON line per seed to docs/suite/screen_design/PROBLEM.jsonl; ``table``
writes docs/suite/screen_design.md from them.
"""

from __future__ import annotations

import json
import shutil
import statistics
import sys
import tempfile
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
OUT = HERE / "screen_design"
sys.path.insert(0, str(HERE))
import estimate_refit as er  # noqa: E402

PROBLEMS = er.PROBLEMS
#: ``--data-seed N``: the problems generated again with data seed N (held-out instances,
#: as docs/suite/heldout_estimate.py makes them); their lines go to data{N}-*.jsonl, and
#: ``run`` measures only the design screen at share 0.3 ("plain") beside no screen.
DATA_SEED = 0
SHARES = (0.2, 0.3, 0.4)
PHASE1 = ("uniform", "design")
RULES = ("plain", "weighted")
#: The suite's plain MC recall at the same cost (README, the suite table), for the ratio.
PLAIN_MC = {
    "toy2d": 0.0093, "av_like": 0.0428, "weak_cheap": 0.0323,
    "digits": 0.0580, "rare_regions": 0.0057, "gap_sim": 0.0138,
}  # fmt: skip


def _append_cheap(root: Path, ids: np.ndarray, values: np.ndarray, batch: int) -> None:
    """The screen's cheap-level results, written into the observation log."""
    from bams_cli.benchmark import append_cheap_results

    append_cheap_results(root, ids, values, batch)


def _weighted(p2: np.ndarray, pi1: np.ndarray, K2: float, posterior) -> np.ndarray:  # noqa: ANN001
    from bams_cli.core import design as dz

    risk = posterior.risk(p2)
    cands = [np.full(p2.size, K2 / p2.size), dz.calibrated_design(risk / pi1**2, K=K2)]
    pv = [float((risk * (1 - q) / (pi1**2 * q)).sum()) for q in cands]
    return cands[int(np.argmin(pv))]


@dataclass
class Setup:
    """A suite problem as every mode reads it: its data, the truth's cheap level by pool
    row, the cheap level's cost and the estimate's prior trust in p_n."""

    problem: str
    prob: er.SuiteProblem
    scratch: Path
    truth1: np.ndarray
    cost: float
    prior: Any


@dataclass
class SeedState:
    """One seed's workspace where it would plan the estimate, in the scores' row order."""

    ids: np.ndarray
    fail: np.ndarray
    cheap: np.ndarray
    known: np.ndarray
    p: np.ndarray
    U: np.ndarray
    next_batch: int

    @property
    def fU(self) -> np.ndarray:
        return self.fail[self.U]

    @property
    def F(self) -> int:
        return int(self.fail.sum())

    @property
    def Fk(self) -> int:
        return int((self.fail & self.known).sum())


def _out(kind: str, problem: str, data_seed: int | None = None) -> Path:
    """Where a mode's lines for ``problem`` go (``kind``: "" for run, "signals-" ...)."""
    seed = DATA_SEED if data_seed is None else data_seed
    return OUT / f"{f'data{seed}-' if seed else ''}{kind}{problem}.jsonl"


def _setup(problem: str, mode: str) -> Setup:
    from bams_cli import benchmark as bm
    from bams_cli.core import design as dz
    from bams_cli.settings import Settings

    warnings.simplefilter("ignore")
    if DATA_SEED:  # a pool generated afresh, not the committed sample data (data seed 0)
        original = bm.GENERATORS[problem]
        bm.GENERATORS[problem] = lambda n, _seed, _g=original: _g(n, DATA_SEED)
        bm.SAMPLE_DATA = Path(tempfile.mkdtemp()) / "no-sample-data"
    scratch = Path(tempfile.mkdtemp(prefix=f"screen-{mode}-{problem}-"))
    prob = er.suite_problem(problem, scratch)
    truth1 = bm._column(prob.data / "truth.parquet", "value_1").astype(float)
    cost = Settings.from_toml((prob.data / "settings.toml").read_text()).costs[1]
    OUT.mkdir(exist_ok=True)
    return Setup(problem, prob, scratch, truth1, cost, dz.risk_posterior([]))


def _level0_known(base: Path, ids: np.ndarray) -> np.ndarray:
    from bams_cli.state.workspace import Workspace

    obs = Workspace(base).read_observations()
    return np.isin(ids, obs.filter(obs["fidelity"] == 0)["segment_id"].to_numpy().astype(str))


def _seed_states(su: Setup, seeds: list[int]) -> Iterator[tuple[int, Path, SeedState]]:
    """(seed, workspace, its state) for each seed; the workspace is removed after."""
    from bams_cli import benchmark as bm
    from bams_cli.state.workspace import Workspace

    for seed, base in er.workspaces_before_estimate(su.problem, su.prob, seeds, su.scratch):
        ids = bm._column(base / "scores.parquet", "segment_id").astype(str)
        rows = np.array([su.prob.pos[s] for s in ids])
        known = _level0_known(base, ids)
        yield seed, base, SeedState(
            ids=ids, fail=su.prob.truth[rows] <= su.prob.gamma, cheap=su.truth1[rows],
            known=known, p=bm._column(base / "scores.parquet", "p_0").astype(float),
            U=np.flatnonzero(~known),
            next_batch=int(Workspace(base).read_observations()["batch"].max()) + 1,
        )  # fmt: skip
        shutil.rmtree(base)
    shutil.rmtree(su.scratch, ignore_errors=True)


def _refit_on_screen(
    base: Path, root: Path, st: SeedState, s1: np.ndarray, have: np.ndarray | None = None
) -> np.ndarray:
    """p_0 over U from a copy of ``base`` refitted with S1's cheap-level results (positions
    in U), at the discovery model's hyperparameters; the copy is removed. ``have`` (bool
    over the pool): segments whose cheap result is in the log already, not run again (as
    ``estimate --plan`` screens them)."""
    from bams_cli import benchmark as bm
    from bams_cli import pipeline

    shutil.copytree(base, root)
    sel = st.U[s1]
    if have is not None:
        sel = sel[~have[sel]]
    _append_cheap(root, st.ids[sel], st.cheap[sel], st.next_batch)
    pipeline.fit(root, fixed_hyperparameters=root / "model.json", **bm.FIT_DEFAULTS)
    p = bm._column(root / "scores.parquet", "p_0").astype(float)[st.U]
    shutil.rmtree(root)
    return p


def run(problem: str, seeds: list[int], trials: int) -> None:
    from bams_cli.core import design as dz
    from bams_cli.core import screen as sc

    su = _setup(problem, "run")
    K, c, prior = su.prob.K, su.cost, su.prior
    for seed, base, st in _seed_states(su, seeds):
        U, p, fU, F, Fk = st.U, st.p, st.fU, st.F, st.Fk
        var_u = int(fU.sum()) * (U.size - K) / K
        d0 = dz.choose_design(p[U], K=K, posterior=prior).pi
        row: dict = {
            "problem": problem, "seed": seed, "trials": trials, "F": F, "K": K, "cost": c,
            "uniform_recall": (Fk + fU.sum() * K / U.size) / F,
            "one_stage": {
                "recall": (Fk + d0[fU].sum()) / F,
                "var": float(((1 - d0[fU]) / d0[fU]).sum()) / var_u,
            },
        }  # fmt: skip
        for mode in ("design",) if DATA_SEED else PHASE1:
            for share in (COVERAGE_SHARE,) if DATA_SEED else SHARES:
                n1 = sc.screen_size(K, c, share, U.size)
                if mode == "uniform":
                    pi1 = np.full(U.size, n1 / U.size)
                else:
                    pi1 = sc.screen_design(p[U], K=K, cost=c, share=share, posterior=prior).pi
                rng = np.random.default_rng(seed * 100 + 7)
                V2: dict[str, list[float]] = {r: [] for r in RULES}
                found: dict[str, list[float]] = {r: [] for r in RULES}
                for t in range(trials):
                    s1 = np.flatnonzero(rng.random(U.size) < pi1)
                    p2 = _refit_on_screen(base, su.scratch / f"trial-{seed}-{t}", st, s1)[s1]
                    K2 = min(sc.confirm_budget(K, c, s1.size), float(s1.size))
                    for rule in ("plain",) if DATA_SEED else RULES:
                        if rule == "plain":
                            pi2 = sc.confirm_design(p2, K2=K2, posterior=prior).pi
                        else:
                            pi2 = _weighted(p2, pi1[s1], K2, prior)
                        f = fU[s1]
                        V2[rule].append(sc.phase2_variance(f, pi1[s1], pi2))
                        found[rule].append(float(pi2[f].sum()))
                V1 = sc.phase1_variance(fU, pi1)
                for rule in ("plain",) if DATA_SEED else RULES:
                    row[f"{mode}-{rule}-{share}"] = {
                        "recall": (Fk + float(np.mean(found[rule]))) / F,
                        "var": (V1 + float(np.mean(V2[rule]))) / var_u,
                    }
        with open(_out("", problem), "a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)


#: How the interval's allowance for an unseen failure prices a segment outside S1:
#: "min": pi1 times the smallest pi2 of the screen (a failure the screen missed would have
#: been confirmed at most that often); "mean": pi1 times the allowance-risk-weighted mean
#: pi2 of the screen (as often as a screened segment of its risk, on average).
ALLOWANCES = ("min", "mean")


def _allowance_pi(
    pi1: np.ndarray, s1: np.ndarray, pi2: np.ndarray, risk: np.ndarray, how: str
) -> np.ndarray:
    """pi over U for ``design.unseen_failure_weight``: pi1 pi2 on S1, pi1 times a stand-in
    pi2 elsewhere (ALLOWANCES)."""
    if how == "min":
        stand_in = float(pi2.min(initial=1.0))
    else:
        w = risk[s1]
        stand_in = float(w @ pi2 / w.sum()) if s1.size else 1.0
    out = pi1 * stand_in
    out[s1] = pi1[s1] * pi2
    return out


def coverage(
    problem: str, seeds: list[int], trials: int, draws: int, default: bool = False
) -> None:
    """The default 90% interval's coverage under the design screen at COVERAGE_SHARE:
    for each of ``trials`` screens per seed (S1 drawn, the model refitted), ``draws``
    confirmations drawn from the truth (pi2 fixed given S1), under each of ALLOWANCES.

    ``default`` (``--default``): the screen as ``estimate --plan`` draws it since
    2026-11-30: pi1 under the study's prior on lam and pi2 under its confirmation prior
    (``pipeline.screening.risk_prior``, ``confirm_prior``: the seed's fitted model), the
    screen's own lowest cheap results confirmed with certainty
    (``core.screen.screen_leads``) and kept in the allowance's stand-in at their pi2 of 1,
    as the tool keeps them; discovery's open leads taken with certainty in both phases
    (``pipeline.estimation.open_leads``, as ``benchmark.screen_default`` takes them, since
    2026-11-30; before, they were not) and segments with a cheap result already not run
    again, so they cost nothing. Lines go to coverage-default-PROBLEM.jsonl."""
    from bams_cli.core import design as dz
    from bams_cli.core import screen as sc
    from bams_cli.core.estimate import estimate_from_sample
    from bams_cli.pipeline import screening
    from bams_cli.pipeline.estimation import open_leads
    from bams_cli.state.workspace import Workspace

    su = _setup(problem, "cov")
    K, c, prior = su.prob.K, su.cost, su.prior
    for seed, base, st in _seed_states(su, seeds):
        U, fU, N, Fk = st.U, st.fU, st.ids.size, st.Fk
        rate = st.F / N
        confirm = prior
        lead_U = np.zeros(U.size, bool)
        have = None
        if default:
            ws = Workspace(base)
            model, settings = ws.read_model(), ws.require_initialised()
            prior = dz.risk_posterior([], prior=screening.risk_prior(model, settings))
            confirm = dz.risk_posterior([], prior=screening.confirm_prior(model, settings))
            obs = ws.read_observations()
            have = np.isin(st.ids, obs.filter(obs["fidelity"] == 1)["segment_id"].to_numpy())
            leads, _ = open_leads(
                ws, st.ids, st.p, st.known, su.prob.gamma, ws.pending(),
                K=sc.lead_budget(K, COVERAGE_SHARE),
                scales=model["hyperparameters"].get("scales") or (),
            )  # fmt: skip
            lead_U = leads[U]
        pi1 = sc.screen_design(
            st.p[U], K=K, cost=c, share=COVERAGE_SHARE, posterior=prior, leads=lead_U
        ).pi
        rng = np.random.default_rng(seed * 100 + 11)
        tally = {h: np.zeros(5) for h in ALLOWANCES}  # hits, below, above, width, p_hat
        for t in range(trials):
            s1 = np.flatnonzero(rng.random(U.size) < pi1)
            p2_all = _refit_on_screen(base, su.scratch / f"cov-{seed}-{t}", st, s1, have)
            # An empty screen has an empty confirmation: T = 0 in every draw.
            runs = s1.size if have is None else int((~have[U[s1]]).sum())
            K2 = min(sc.confirm_budget(K, c, runs), float(s1.size)) if s1.size else K
            own = lead_U[s1]
            if default and s1.size:
                own = own | sc.screen_leads(st.cheap[U][s1], K2, taken=lead_U[s1])
            pi2 = sc.confirm_design(p2_all[s1], K2=K2, posterior=confirm, leads=own).pi
            counts = (rng.random((s1.size, draws)) < pi2[:, None]).astype(np.int64)
            allow = prior.allowance_risk(p2_all)
            # Over U without the open leads (no unseen failure hides in one), the screen's
            # own leads in the stand-in: as the tool prices it (``pipeline.screening``).
            rest = ~lead_U
            in_s1 = np.zeros(U.size, bool)
            in_s1[s1] = True
            s1_r, pi2_r, allow_r = np.flatnonzero(in_s1[rest]), pi2[rest[s1]], allow[rest]
            for how in ALLOWANCES:
                wm = dz.unseen_failure_weight(
                    allow_r, _allowance_pi(pi1[rest], s1_r, pi2_r, allow_r, how)
                )
                est = estimate_from_sample(
                    sc.confirmed_pi(pi1[s1], pi2), fU[s1], design="poisson", n_pool=N,
                    n_unknown=U.size, budget=K2, counts=counts, known_failures=Fk,
                    confidence=0.9, w_model=wm,
                )  # fmt: skip
                tally[how] += [
                    np.sum((est.ci_low <= rate) & (rate <= est.ci_high)),
                    np.sum(est.ci_high < rate),
                    np.sum(est.ci_low > rate),
                    np.sum(est.ci_high - est.ci_low) / rate,
                    np.sum(est.p_hat_unbiased) / rate,
                ]
        n = trials * draws
        row: dict = {
            "problem": problem, "seed": seed, "trials": trials, "draws": draws,
            "share": COVERAGE_SHARE,
        }  # fmt: skip
        for how, (hits, below, above, width, mean) in tally.items():
            row[how] = {
                "coverage": hits / n, "below": below / n, "above": above / n,
                "width_over_rate": width / n, "mean_over_rate": mean / n,
            }  # fmt: skip
        row["strategy"] = er.STRATEGY
        kind = "coverage-" if er.STRATEGY == "bams" else f"coverage-{er.STRATEGY}-"
        if default:
            row["default"] = True
            kind = kind.replace("coverage-", "coverage-default-")
        with open(_out(kind, problem), "a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)


def predict(problem: str, seeds: list[int], draws: int = 30) -> None:
    """What the discovery model predicts of the design screen at COVERAGE_SHARE, per seed.

    Each segment of U alone: its level-0 posterior N(mu0, sd0^2) and, from
    ``MFGP.own_point``, the covariance of theta_0 with its own cheap run and that run's
    variance give b = cov / sqrt(var); after the run, mu0 moves by b z (z standard normal)
    and sd0^2 drops by b^2, so p2 = Phi((gamma - mu0 - b z) / sqrt(sd0^2 - b^2)). No
    segment's run informs another here (the refit does that). Predicted variances use the
    risk r = (1 - lam) p / mean_U(p) + lam at the prior's mean lam: the screen's
    sum r (1 - pi1)/pi1 + mean over ``draws`` screens of sum_S1 r2 (1 - pi2)/(pi1^2 pi2),
    against the no-screen design's sum r (1 - pi)/pi, both over uniform's.
    """
    from scipy.special import ndtr

    from bams_cli.core import design as dz
    from bams_cli.core import screen as sc
    from bams_cli.pipeline.fitting import load_posterior
    from bams_cli.state.workspace import Workspace

    su = _setup(problem, "pred")
    K, c, gamma, prior = su.prob.K, su.cost, su.prob.gamma, su.prior
    lam = prior.lam_mean
    for seed, base in er.workspaces_before_estimate(problem, su.prob, seeds, su.scratch):
        ws = Workspace(base)
        ids, X = ws.read_pool()
        ids = np.asarray(ids).astype(str)
        post, _ = load_posterior(ws, ws.require_initialised(), ids, X)
        U = np.flatnonzero(~_level0_known(base, ids))
        mu0, sd0, pp = post.score(X[U], [gamma])
        p = pp[:, 0]
        cov, var = post.own_point(X[U], np.ones(U.size, np.int64))
        b = cov / np.sqrt(var)
        s2 = np.sqrt(np.maximum(sd0**2 - b**2, 1e-12))
        r = (1 - lam) * p / p.mean() + lam
        Vu = dz.predicted_variance(np.full(U.size, K / U.size), r)
        Vns = dz.predicted_variance(dz.choose_design(p, K=K, posterior=prior).pi, r)
        pi1 = sc.screen_design(p, K=K, cost=c, share=COVERAGE_SHARE, posterior=prior).pi
        rng = np.random.default_rng(seed)
        V2 = []
        for _ in range(draws):
            s1 = np.flatnonzero(rng.random(U.size) < pi1)
            p2 = ndtr((gamma - mu0[s1] - b[s1] * rng.standard_normal(s1.size)) / s2[s1])
            r2 = (1 - lam) * p2 / p.mean() + lam
            K2 = min(sc.confirm_budget(K, c, s1.size), float(s1.size))
            pi2 = sc.confirm_design(p2, K2=K2, posterior=prior).pi
            V2.append(float((r2 * (1 - pi2) / (pi1[s1] ** 2 * pi2)).sum()))
        row = {
            "problem": problem, "seed": seed, "pred_noscreen": Vns / Vu,
            "pred_screen": (dz.predicted_variance(pi1, r) + float(np.mean(V2))) / Vu,
            "rho2_median": float(np.median(b**2 / np.maximum(sd0**2, 1e-300))),
        }  # fmt: skip
        with open(OUT / f"predict-{problem}.jsonl", "a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)
        shutil.rmtree(base)
    shutil.rmtree(su.scratch, ignore_errors=True)


def signals(problem: str, seeds: list[int]) -> None:
    """What a study can see, before it plans the estimate, of whether its cheap level is
    worth a screen: per seed, from the workspace where the estimate would be planned (no
    truth): the fitted model's discrepancy-plus-cheap-noise sd over its level-0 signal sd
    (``disc_over_signal``), and the pairs' correlation corr(y0, y1) over the segments run at
    both levels (``pairs_corr``, ``n_pairs``). Joined in ``table`` with ``run``'s measured
    variance of the design screen at share 0.3 over the no-screen design's, same seeds."""
    import polars as pl

    from bams_cli.state.workspace import Workspace

    su = _setup(problem, "signals")
    for seed, base, _st in _seed_states(su, seeds):
        hp = json.loads((base / "model.json").read_text())["hyperparameters"]
        disc = float(hp["outputscales"][0]) + float(hp["noise"][1])
        obs = Workspace(base).read_observations()
        y0 = obs.filter(pl.col("fidelity") == 0).group_by("segment_id").agg(pl.col("value").mean())
        y1 = obs.filter(pl.col("fidelity") == 1).group_by("segment_id").agg(pl.col("value").mean())
        pairs = y0.join(y1, on="segment_id", suffix="_1")
        corr = (
            float(np.corrcoef(pairs["value"].to_numpy(), pairs["value_1"].to_numpy())[0, 1])
            if pairs.height >= 3
            else None
        )
        row = {
            "problem": problem, "seed": seed,
            "disc_over_signal": (disc / float(hp["outputscale0"])) ** 0.5,
            "pairs_corr": corr, "n_pairs": pairs.height,
        }  # fmt: skip
        with open(_out("signals-", problem), "a") as fh:
            fh.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)


COVERAGE_SHARE = 0.3
#: The rule the signals table tries: screen where the fitted discrepancy-plus-cheap-noise
#: sd is under this share of the level-0 signal sd.
SIGNAL_THRESHOLD = 0.3


def _signal_lines(data_seed: int = 0) -> list[str]:
    """The fourth table: ``signals`` lines joined with ``run``'s, per problem (on the
    instances of ``data_seed``, the fifth)."""
    rows = []
    for problem in PROBLEMS:
        path, run_path = _out("signals-", problem, data_seed), _out("", problem, data_seed)
        if not path.exists() or not run_path.exists():
            continue
        sig = {r["seed"]: r for x in path.read_text().splitlines() if x and (r := json.loads(x))}
        runs = {
            r["seed"]: r for x in run_path.read_text().splitlines() if x and (r := json.loads(x))
        }
        seeds = sorted(set(sig) & set(runs))
        d = [sig[k]["disc_over_signal"] for k in seeds]
        c = [sig[k]["pairs_corr"] for k in seeds if sig[k]["pairs_corr"] is not None]
        ratio = [runs[k]["design-plain-0.3"]["var"] / runs[k]["one_stage"]["var"] for k in seeds]
        rule = [
            runs[k]["design-plain-0.3" if sig[k]["disc_over_signal"] < SIGNAL_THRESHOLD
                    else "one_stage"]["var"]
            for k in seeds
        ]  # fmt: skip
        screened = sum(sig[k]["disc_over_signal"] < SIGNAL_THRESHOLD for k in seeds)
        rows.append(
            f"| {problem} | {len(seeds)} | {min(d):.2f} - {max(d):.2f} | "
            f"{min(c):.2f} - {max(c):.2f} | {statistics.mean(ratio):.2f} [{min(ratio):.2f}, "
            f"{max(ratio):.2f}] | {sum(x < 1 for x in ratio)} | {screened} | "
            f"{statistics.mean(rule):.2f} [{max(rule):.2f}] |"
        )
    if not rows:
        return []
    if data_seed:
        return [
            "",
            f"The same on held-out instances: every problem generated again with data seed "
            f"{data_seed} (`screen_design.py signals PROBLEM --data-seed {data_seed}` and "
            f"`run PROBLEM --data-seed {data_seed}`, the design screen at share 0.3 only), "
            "the threshold as chosen above.",
            "",
            "| problem | seeds | disc / signal | pairs' corr | screen / no screen, mean "
            f"[range] | screen better | seeds screened at < {SIGNAL_THRESHOLD} | rule: var "
            "[max] |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |",
            *rows,
        ]
    return [
        "",
        "What a study can see of its cheap level before it plans the estimate "
        "(`screen_design.py signals PROBLEM`; its docstring says how; no truth): the fitted "
        "model's discrepancy-plus-cheap-noise sd over its level-0 signal sd (disc / signal) "
        "and the pairs' correlation corr(y0, y1) over segments run at both levels (5 to 27 "
        "pairs), beside the measured variance of the design screen at share 0.3 over the "
        "no-screen design's (the first table's runs, same seeds). rule: screen where disc / "
        f"signal < {SIGNAL_THRESHOLD}; its variance over uniform's, mean [max] over seeds "
        "(the one-stage design where it does not screen). Measured 2026-11-27.",
        "",
        "| problem | seeds | disc / signal | pairs' corr | screen / no screen, mean [range] "
        f"| screen better | seeds screened at < {SIGNAL_THRESHOLD} | rule: var [max] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
        *rows,
    ]


def _cell(rows: list[dict], key: str, problem: str) -> str:
    rec = [r[key]["recall"] for r in rows]
    var = [r[key]["var"] for r in rows]
    return (
        f"{statistics.mean(rec):.4f} ({statistics.mean(rec) / PLAIN_MC[problem]:.1f}x) | "
        f"{statistics.mean(var):.2f} [{max(var):.2f}]"
    )


def _by_problem(kind: str) -> dict[str, list[dict]]:
    """The JSON lines of OUT/{kind}PROBLEM.jsonl, by problem, for the problems that have them."""
    return {
        problem: [json.loads(x) for x in path.read_text().splitlines() if x]
        for problem in PROBLEMS
        if (path := OUT / f"{kind}{problem}.jsonl").exists()
    }


def _allowance_rows(lead: str, rows: list[dict]) -> list[str]:
    """One table row per allowance of ``coverage``'s lines: coverage mean [min] over the
    lines, below, above, width and mean p_hat over the rate; ``lead`` opens the first."""
    out = []
    for i, how in enumerate(ALLOWANCES):
        cov = [r[how]["coverage"] for r in rows]
        first = lead if i == 0 else "|" + " |" * lead.count(" |")
        stats = [f"{statistics.mean(r[how][k] for r in rows):.3f}" for k in ("below", "above")]
        width = statistics.mean(r[how]["width_over_rate"] for r in rows)
        mean = statistics.mean(r[how]["mean_over_rate"] for r in rows)
        out.append(
            f"{first} {how} | {statistics.mean(cov):.3f} [{min(cov):.3f}] | "
            + " | ".join(stats)
            + f" | {width:.1f} | {mean:.3f} |"
        )
    return out


def table() -> None:
    lines = [
        "# A cheap-level screen before the level-0 estimate, measured through the tool",
        "",
        "`docs/suite/screen_design.py` (its docstring says how; `core.screen` holds the "
        "design and its unbiasedness, checked by enumeration in tests/core/test_screen.py). "
        "BAMS runs of the suite protocol; from each run's workspace, part of the estimate's "
        "budget K (the share) buys cheap-level runs on a Poisson sample S1, the model is "
        "refitted on them, and the rest buys level-0 runs on S1. recall: failures confirmed "
        "at level 0 by the end, over all failures, at the same cost as plain MC (x: over the "
        "suite's plain MC recall). var: the estimate's variance over a uniform level-0 "
        "design of K runs (phase 1's term exact, phase 2's exact given S1 and averaged over "
        "the 4 screens per seed, so the [max] is noisy), mean [max] over seeds. no screen: the estimate's design without "
        "a screen, on the same workspaces (it does not depend on the share). uniform / "
        "design screen: phase 1 uniform over U, or the estimate's own design choice at the "
        "screen's size (`core.screen.screen_design`). Phase 2 is "
        '`core.screen.confirm_design` ("plain"). The predicted-variance minimiser that '
        'weights the risk by 1/pi1^2 ("weighted", in the JSON lines) did worse where the '
        "refitted p_n is good (design screen 0.3: av_like var 0.27 against 0.08, toy2d 0.31 "
        "against 0.02) and better where it is weak (digits 0.87 against 1.06, weak_cheap "
        "1.12 against 1.23). 4 screens per seed; measured 2026-11-25 (17:00, the lines were "
        "written by this script's first form, whose draws and numbers it reproduces: "
        "digits seed 0 checked).",
        "",
        "| problem | seeds | design | "
        + " | ".join(f"share {x}: recall (x MC) | var" for x in SHARES)
        + " |",
        "| --- | --- | --- |" + " --- | --- |" * len(SHARES),
    ]
    for problem in PROBLEMS:
        path = OUT / f"{problem}.jsonl"
        if not path.exists():
            continue
        rows = [json.loads(line) for line in path.read_text().splitlines() if line]
        head = f"| {problem} | {len(rows)} |"
        one = _cell(rows, "one_stage", problem)
        lines.append(f"{head} no screen | " + " | ".join([one] * len(SHARES)) + " |")
        for m in PHASE1:
            cells = [_cell(rows, f"{m}-plain-{x}", problem) for x in SHARES]
            lines.append(f"| | | {m} screen | " + " | ".join(cells) + " |")
    cov_rows = _by_problem("coverage-")
    if cov_rows:
        first = next(iter(cov_rows.values()))[0]
        lines += [
            "",
            f"The default 90% interval under the design screen at share {COVERAGE_SHARE} "
            f"(`screen_design.py coverage PROBLEM`): for each seed, {first['trials']} "
            f"screens (S1 drawn, the model refitted) and {first['draws']:,} confirmations "
            "from the truth per screen, estimated by `estimate_from_sample` at pi1 pi2. The "
            "interval's allowance for an unseen failure (`design.unseen_failure_weight`, "
            "the refitted model's allowance risk) needs a pi for segments outside S1: min, "
            "pi1 times the screen's smallest pi2 (a failure the screen missed would have "
            "been confirmed at most that often); mean, pi1 times its risk-weighted mean pi2. "
            "coverage: mean [min] over seeds (each seed's rests on its few screens: a min "
            "near 0.88 can be one screen whose intervals all missed); below / above: the "
            "shares of intervals wholly below / above the rate; width over the rate; mean "
            "p_hat (the unbiased sum) over the rate, whose spread from 1 is that of the few "
            "screens per seed (the enumeration in tests/core/test_screen.py shows it "
            "unbiased). The staged design's widths, for comparison: toy2d 3.05, av_like "
            "6.08, rare_regions 10.85 times the rate (docs/suite/estimate_design.md, BAMS).",
            "",
            "| problem | seeds | allowance | coverage | below | above | width / rate | "
            "mean p_hat / rate |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for problem, rows in cov_rows.items():
            lines += _allowance_rows(f"| {problem} | {len(rows)} |", rows)
    dflt = {
        "BAMS": _by_problem("coverage-default-"),
        "MCM-GP": _by_problem("coverage-default-mcm-gp-"),
    }
    if any(dflt.values()):
        lines += [
            "",
            "The same for the screen as `estimate --plan` draws it since 2026-11-30, when "
            "`--screen auto` began to screen every study with a cheap level "
            "(`screen_design.py coverage PROBLEM --trials 4 --default [--strategy mcm-gp]`, the coverage "
            "docstring says how): the study's priors on lam from the seed's model, the "
            "screen's own lowest cheap results confirmed with certainty and kept in the "
            "allowance's stand-in (at pi2 = 1; left out, 2026-11-30 at 1f89bb4, the widths "
            "were 1.3, 4.0 and 24.7 times the rate and weak_cheap's coverage 0.972 with no "
            "miss below). The three problems it did not screen before, and toy2d; 4 screens "
            "x 1,000 confirmations per seed. The staged design's widths there, for "
            "comparison: rare_regions 10.85 times the rate (above). rare_regions' mean "
            "p_hat far from 1 is phase 1's spread over its 40 screens, each holding about "
            "0.65 of its 57 failures (pi1 about 0.011 over 20,000 segments): the sum is "
            "unbiased over screens (tests/core/test_screen.py), and the width is what pays "
            "for a screen that sampled none. Measured again 2026-11-30 (03:44-04:18 at "
            "a0e4b7c), the rows below, with discovery's open leads taken with certainty in "
            "both phases and cheap results already in the log not run again, as `estimate "
            "--plan` does (the first measurement did neither): BAMS weak_cheap 0.935 -> "
            "0.956 (wholly below the rate 3.7% -> 2.2% of draws), digits 0.981 -> 0.989, "
            "rare_regions 1.000 both, toy2d 1.000 -> 0.900; MCM-GP weak_cheap 0.949 -> "
            "0.956, digits 0.972 -> 0.984, rare_regions 0.925 -> 0.950. toy2d's misses all "
            "lie above the rate: on 4 of its 40 screens S1 drew more failures than pi1 "
            "expects, E[T | S1] lay above the rate by more than the interval reaches, and "
            "every confirmation of those screens missed (a seed's 4 screens move its "
            "coverage in quarters); none lay below.",
            "",
            "| problem | seeds | allowance | coverage | below | above | width / rate | "
            "mean p_hat / rate |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for strategy, by in dflt.items():
            for problem, rows in by.items():
                lines += _allowance_rows(f"| {problem}, {strategy} | {len(rows)} |", rows)
    held = [
        (seed, problem, [json.loads(x) for x in path.read_text().splitlines() if x])
        for seed in (1, 2)
        for problem in PROBLEMS
        if (path := _out("coverage-", problem, seed)).exists()
    ]
    if held:
        lines += [
            "",
            "The same on held-out instances of the problems `--screen auto` screens "
            "(`screen_design.py coverage PROBLEM --data-seed N --seeds 0-4 --trials 4`, "
            "2026-11-27): every problem generated again with data seed 1 or 2, 4 screens x "
            "1,000 confirmations per seed.",
            "",
            "| problem | data seed | seeds | allowance | coverage | below | above | "
            "width / rate | mean p_hat / rate |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for seed, problem, rows in held:
            lines += _allowance_rows(f"| {problem} | {seed} | {len(rows)} |", rows)
    pred_rows = _by_problem("predict-")
    if pred_rows:
        lines += [
            "",
            "Can the discovery model tell where the screen pays? `screen_design.py predict` "
            "(its docstring says how): each segment's own cheap run moves its p_n as the "
            "model's own-point covariance says, no run informing another. Ratios: the design "
            f"screen at share {COVERAGE_SHARE}'s variance over the no-screen design's, "
            "predicted and measured (the table above, same runs), mean over seeds; screen "
            "better: the runs where each says the screen's variance is lower. (Seeds 0-4; the "
            "lines were written by this mode's first form, which it reproduces: digits seed "
            "1 checked.)",
            "",
            "| problem | seeds | predicted ratio | measured ratio | screen better, predicted "
            "| screen better, measured |",
            "| --- | --- | --- | --- | --- | --- |",
        ]
        for problem, rows in pred_rows.items():
            measured = {
                r["seed"]: r["design-plain-0.3"]["var"] / r["one_stage"]["var"]
                for x in (OUT / f"{problem}.jsonl").read_text().splitlines()
                if x and (r := json.loads(x))
            }
            pr = [r["pred_screen"] / r["pred_noscreen"] for r in rows]
            me = [measured[r["seed"]] for r in rows]
            lines.append(
                f"| {problem} | {len(rows)} | {statistics.mean(pr):.2f} | "
                f"{statistics.mean(me):.2f} | {sum(x < 1 for x in pr)} | "
                f"{sum(x < 1 for x in me)} |"
            )
    lines += _signal_lines() + _signal_lines(1)
    lines += [
        "",
        "What it shows (design screen at share 0.3 against no screen):",
        "",
        "- Recall rose on all six problems: toy2d 17.7x -> 39.3x plain MC, av_like 12.0x -> "
        "15.6x, weak_cheap 1.5x -> 1.9x, digits 1.5x -> 2.3x, rare_regions 1.9x -> 3.1x "
        "(4.0x at share 0.4), gap_sim 4.7x -> 6.3x. A cheap run on the segment itself is "
        "evidence the discovery model's p_n lacks, so the screen lies outside the class "
        "docs/suite/recall_bound.md bounds (designs monotone in p_n); on rare_regions it "
        "passes that bound's mean (3.8x) at share 0.4.",
        "- Variance fell on four: toy2d 0.06 -> 0.02, av_like 0.19 -> 0.08 (worst seed 0.27 "
        "-> 0.12: issue 12's 1/5 on every seed), rare_regions 1.06 -> 0.62, gap_sim 0.47 -> "
        "0.39. It rose where the cheap level is weakest: weak_cheap 0.94 -> 1.23 (worst "
        "1.63) and digits' worst seed 1.17 -> 1.60 (mean 1.03 -> 1.06).",
        "- The interval held under it: coverage 0.927 to 1.000 per problem with either "
        "allowance, wholly below the rate in at most 3.9% of draws (weak_cheap with the mean "
        "allowance; 1.9% with the min; none elsewhere but digits' 0.6%). The mean allowance "
        "is narrower than the staged design's interval where the model is right (toy2d "
        "1.8 against 3.05 times the rate, av_like 4.7 against 6.08, rare_regions 8.5 "
        "against 10.85).",
        "- So the screen cannot be spent blindly: a study must screen where it pays. The "
        "discovery model's per-segment prediction (third table) called the screen worse on "
        "every run, while it measured better on most: a cheap run informs the refit beyond "
        "its own segment, which a per-segment prediction misses. What the fitted model says "
        "of the cheap level as a whole does better (fourth table): its discrepancy sd under "
        f"{SIGNAL_THRESHOLD} of its level-0 signal sd picks out toy2d, av_like and gap_sim on "
        "every seed, where the screen never had more than 1.06x the no-screen design's "
        "variance, and no seed of weak_cheap or digits, where it had up to 1.68x; it misses "
        "rare_regions (0.37 to 1.52), where the screen halved the variance on 8 of 10 seeds. "
        "The pairs' correlation separates no better (weak_cheap seed 7: 0.96, digits seeds 5 "
        "and 7: 0.96, all worse under the screen). The threshold was chosen in the gap "
        "between six problems' values; on held-out instances (fifth table, data seed 1, 5 "
        "seeds each) it screened every seed of toy2d, av_like and gap_sim, where the screen "
        "was better on every seed (at most 0.99 of the no-screen variance; av_like 0.14 of "
        "uniform's on average, worst seed 0.21), and no seed of weak_cheap (worse on every "
        "seed, 1.08 to 1.36), digits or rare_regions.",
        "- Shipped as an option, not the default: `estimate --plan --screen SHARE` draws the "
        "screen (its cheap runs as a batch), and the next `estimate --plan`, after their "
        "results and a refit, the confirmation at pi1 pi2 within it, with the min allowance "
        "(README, `estimate`). Since 2026-11-27 it is the default where the fitted cheap "
        "level tracks level 0 (`--screen auto`), and its interval uses the mean allowance: "
        "on every problem `--screen auto` screens, here and on the held-out instances, the "
        "two allowances covered alike to the third digit with no interval wholly below the "
        "rate (the upper limit decided no miss), and the mean's is 1.3 to 3.5 times "
        "narrower (toy2d 1.8 against 6.2 times the rate, held out 1.5 and 2.2 against 5.0 "
        "and 7.5). It costs coverage only where the cheap level is weak, which auto does "
        "not screen (weak_cheap under an explicit screen: 0.927 against 0.948, 3.9% below "
        "against 1.9%).",
    ]
    mcm = _by_problem("coverage-mcm-gp-")
    if mcm:
        lines += [
            "",
            "The default interval under the screen for the other GP strategy, now that "
            "`--screen auto` screens MCM-GP's runs of toy2d, av_like and gap_sim on every "
            "seed (docs/reproduction/suite/suite.md): `screen_design.py coverage PROBLEM "
            "--seeds 0-4 --trials 4 --strategy mcm-gp` (2026-11-27; 4 screens x 1,000 "
            "confirmations per seed; lines in `screen_design/coverage-mcm-gp-*.jsonl`). "
            "Coverage over all 20,000 draws per problem, [the lowest seed's]:",
            "",
            "| problem | seeds | allowance | coverage | below | above | width / rate | "
            "mean p_hat / rate |",
            "| --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for problem, rows in mcm.items():
            lines += _allowance_rows(f"| {problem} | {len(rows)} |", rows)
        lines += [
            "",
            "No interval lay wholly below the rate; toy2d's misses were all above it (its "
            "lowest seed rests on 4 screens).",
        ]
    (HERE / "screen_design.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv: list[str]) -> None:
    global DATA_SEED
    if "--data-seed" in argv:
        DATA_SEED = int(argv[argv.index("--data-seed") + 1])
    if argv[:1] == ["table"]:
        table()
        return
    if argv[:1] not in (["run"], ["coverage"], ["predict"], ["signals"]) or len(argv) < 2:
        raise SystemExit(__doc__)
    if argv[0] == "signals":
        signals(argv[1], er.seeds_and_trials(argv, "0-9", 0)[0])
    elif argv[0] == "predict":
        predict(argv[1], er.seeds_and_trials(argv, "0-4", 0)[0])
    elif argv[0] == "coverage":
        if "--strategy" in argv:  # another discovery strategy's runs (mcm-gp)
            i = argv.index("--strategy")
            er.STRATEGY = argv[i + 1]
            argv = argv[:i] + argv[i + 2 :]
        default = "--default" in argv
        argv = [a for a in argv if a != "--default"]
        coverage(argv[1], *er.seeds_and_trials(argv, "0-9", 8), 1000, default=default)
    else:
        run(argv[1], *er.seeds_and_trials(argv, "0-9", 4))


if __name__ == "__main__":
    main(sys.argv[1:])
