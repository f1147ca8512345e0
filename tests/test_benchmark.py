"""The reproduction harness: a tiny end-to-end run, and its exact design arithmetic."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from bams_cli import benchmark as B
from bams_cli import defaults
from bams_cli.benchmark import (
    PROTOCOLS,
    SUITE,
    RunResult,
    _run_designs,
    design_stats,
    run_benchmark,
    run_suite,
)
from bams_cli.core.estimate import estimate_from_sample, plan_sample
from tests.conftest import invoke

REQUIRED = ("recall", "recall_se", "rv", "rv_se", "rv_median", "seeds")


def test_tiny_synthetic_run_writes_finite_tables(tmp_path, monkeypatch):
    from bams_cli import pipeline

    calls = []
    asked = []  # select's --greedy in every batch
    real_select = pipeline.select
    monkeypatch.setattr(
        pipeline, "select", lambda *a, **kw: asked.append(kw["greedy"]) or real_select(*a, **kw)
    )
    fits = []  # (workspace folder, fixed hyperparameters given) for every fit
    real_fit = pipeline.fit
    monkeypatch.setattr(
        pipeline,
        "fit",
        lambda root, **kw: (
            fits.append((Path(root).name, kw.get("fixed_hyperparameters"))) or real_fit(root, **kw)
        ),
    )
    res = run_benchmark(
        "toy2d",
        seeds=1,
        quick=True,
        out_dir=tmp_path,
        strategies=["bas", "mc"],
        level0_share=0.5,
        workers=1,
        progress=lambda phase, done, total: calls.append((phase, done, total)),
        n=1500,
        greedy="approximate",
    )
    doc = json.loads((tmp_path / "results.json").read_text())
    assert doc["setup"]["greedy"] == "approximate" and set(asked) == {"approximate"}
    assert len(asked) == 2 * PROTOCOLS["toy2d"].n_batches
    assert (tmp_path / "tables.md").read_text().startswith("# toy2d")
    assert (tmp_path / "retention-recall.png").stat().st_size > 0
    for strategy in ("bas", "mc"):
        entry = doc[strategy]
        assert set(REQUIRED) <= set(entry)
        assert entry["seeds"] == 1
        assert 0.0 <= entry["recall"] <= 1.0
        assert math.isfinite(entry["rv"]) and entry["rv"] >= 0
        assert math.isfinite(entry["rv_median"])
        assert len(entry["table1"]) == PROTOCOLS["toy2d"].n_batches
        assert all(math.isfinite(t["mean_f"]) for t in entry["table1"])
    assert "bams" not in doc  # only what was asked for
    assert doc["setup"]["pool_size"] == 1500 and doc["setup"]["K"] > 0
    assert res["bas"]["recall"] == doc["bas"]["recall"]
    assert ("toy2d all runs", 2, 2) in calls
    # BAS went through estimate --plan, simulate, ingest, fit and estimate; MC did not.
    [realised] = doc["bas"]["realised_estimates"]
    assert 0.0 <= realised["ci_low"] <= realised["p_hat"] <= realised["ci_high"]
    assert realised["n_sampled"] > 0
    assert realised["distinct_failures_found"] <= doc["setup"]["failures"]
    assert "interval covers p" in (tmp_path / "tables.md").read_text()
    assert not any(doc["mc"].get("realised_estimates", []))
    # The run's own workspace is refitted as a study refits it, a plain fit, through the
    # estimate too; only the screen's evaluation copies condition at fixed hyperparameters.
    own = [fixed for name, fixed in fits if name.startswith("bas-")]
    assert len(own) > PROTOCOLS["toy2d"].n_batches and not any(own)
    # BAS's first batch is level 0 only; its picks fill the budget.
    levels = doc["bas"]["picks_per_level"][0]
    assert levels[0] == [10, 0] and sum(levels[1]) == 5


def _pool(seed: int, n: int = 240):
    rng = np.random.default_rng(seed)
    is_failure = rng.random(n) < 0.06
    # A miscalibrated score: informative, with a few failures it is nearly sure about wrongly.
    p = np.clip(np.where(is_failure, rng.beta(4, 2, n), rng.beta(1, 12, n)), 0, 1)
    p[np.flatnonzero(is_failure)[:2]] = 1e-4
    known = np.zeros(n, bool)
    known[rng.choice(n, 12, replace=False)] = True
    return p, is_failure, known


@pytest.mark.parametrize("design", ["poisson", "with-replacement"])
@pytest.mark.parametrize("seed", [0, 1])
def test_exact_variance_and_recall_match_brute_force(design, seed):
    """design_stats' exact RV and recall agree with 40,000 simulated estimates."""
    p, is_failure, known = _pool(seed)
    n = p.size
    F = is_failure.sum()
    K = 30.0
    use_known = known if design == "poisson" else None
    recall, rv = design_stats(
        p, is_failure, K=K, known=use_known, alpha=1.0, defensive=0.1, design=design
    )
    plan = plan_sample(
        p,
        K=K,
        rng=np.random.default_rng(0),
        known=use_known,
        alpha=1.0,
        defensive=0.1,
        design=design,  # type: ignore[arg-type]
    )
    U = plan.unknown
    y = is_failure[U]
    reps = 40_000
    rng = np.random.default_rng(seed + 10)
    if design == "poisson":
        counts = (rng.random((reps, U.size)) < plan.pi).T.astype(np.int64)
        prob = plan.pi
    else:
        counts = rng.multinomial(int(K), plan.q, size=reps).T
        prob = plan.q
    known_fail = int(is_failure[known].sum()) if use_known is not None else 0
    est = estimate_from_sample(
        prob,
        y,
        design=design,  # type: ignore[arg-type]
        n_pool=n,
        n_unknown=U.size,
        budget=K,
        counts=counts,
        known_failures=known_fail,
    )
    rate = F / n
    # The design-unbiased sum (p_hat is it but where held to what the sample allows).
    total = est.p_hat_unbiased
    assert abs(total.mean() - rate) < 5 * total.std() / math.sqrt(reps)  # unbiased
    rv_mc = total.var(ddof=1) / rate**2
    # The variance of a sample variance is heavy-tailed here (a few failures at pi ~ 1e-3);
    # 40,000 repeats pin it to a few per cent.
    assert rv_mc == pytest.approx(rv, rel=0.15)
    found = (known_fail + ((counts > 0) & y[:, None]).sum(axis=0)) / F
    assert found.mean() == pytest.approx(recall, abs=4 * found.std() / math.sqrt(reps) + 1e-12)


def test_uniform_design_gives_the_monte_carlo_formula():
    """alpha = 0 without a known stratum: Poisson RV (1 - K/N)/(p K), WR RV (1 - p)/(p K)."""
    n, K = 5000, 100.0
    is_failure = np.zeros(n, bool)
    is_failure[:40] = True
    p = 40 / n
    _, rv_poisson = design_stats(
        np.ones(n), is_failure, K=K, known=None, alpha=0.0, defensive=0.1, design="poisson"
    )
    recall, rv_wr = design_stats(
        np.ones(n), is_failure, K=K, known=None, alpha=0.0, defensive=0.0,
        design="with-replacement",
    )  # fmt: skip
    assert rv_poisson == pytest.approx((1 - K / n) / (p * K))
    assert rv_wr == pytest.approx((1 - p) / (p * K))
    assert recall == pytest.approx(1 - (1 - 1 / n) ** K)


def test_underflowing_scores_of_non_failures_leave_the_variance_finite():
    """p_n^2.5 ~ 0 on passing segments is harmless; on a failure it is unbounded."""
    n, K = 1000, 50.0
    is_failure = np.zeros(n, bool)
    is_failure[:10] = True
    p = np.full(n, 1e-200)
    p[:10] = np.linspace(0.2, 1.0, 10)
    p[10:60] = 0.1
    recall, rv = design_stats(
        p, is_failure, K=K, known=None, alpha=2.5, defensive=0.0, design="with-replacement"
    )
    q = p**2.5 / np.sum(p[:60] ** 2.5)
    expected = (np.sum(1 / q[:10]) - 100) / (n**2 * K) / (10 / n) ** 2
    assert rv == pytest.approx(expected)
    assert 0 < recall < 1
    p[0] = 1e-200  # now a failure cannot be drawn
    _, rv = design_stats(
        p, is_failure, K=K, known=None, alpha=2.5, defensive=0.0, design="with-replacement"
    )
    assert rv == math.inf


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--seeds", "0"], "--seeds 0: need at least 1"),
        (["--strategies", "bams,foo"], "--strategies foo: not part of the toy2d protocol"),
        (["--level0-share", "2"], "--level0-share 2.0: must lie in (0, 1)"),
        (["--workers", "0"], "--workers 0: must be >= 1"),
    ],
)
def test_bad_benchmark_options_are_one_line_errors(runner, tmp_path, args, message):
    # A value out of range is a usage error (exit code 2), as for every other command.
    r = invoke(runner, "benchmark", "--out", tmp_path / "out", *args)
    assert r.exit_code == 2 and r.stderr.startswith("error: " + message), r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "out").exists()


def test_benchmark_out_must_be_a_folder(runner, tmp_path):
    (tmp_path / "file").write_text("x")
    r = invoke(runner, "benchmark", "--seeds", "1", "--out", tmp_path / "file")
    assert r.exit_code == 1 and "--out" in r.stderr and "is a file" in r.stderr


def test_init_on_a_file_is_a_one_line_error(runner, tmp_path):
    (tmp_path / "w").write_text("x")
    r = invoke(runner, "init", "-w", tmp_path / "w", "--gamma", "0.5")
    assert r.exit_code == 1 and "w: is a file; a workspace is a folder" in r.stderr


def test_a_suite_problem_runs_end_to_end_into_the_suite_table(tmp_path):
    """gap_sim, one seed, small pool: its folder, tables without paper columns, suite.md."""
    results = run_suite(
        seeds=1,
        quick=True,
        out_dir=tmp_path,
        strategies=["mcm-gp", "mc"],
        level0_share=0.5,
        workers=1,
        progress=None,
        n=1200,
        problems=["gap_sim"],
    )
    doc = json.loads((tmp_path / "gap_sim" / "results.json").read_text())
    assert doc["setup"]["pool_size"] == 1200 and doc["paper"] == {}
    assert doc["setup"]["true_discrepancy_sd"] > 0
    tables = (tmp_path / "gap_sim" / "tables.md").read_text()
    assert tables.startswith("# gap_sim") and "paper recall" not in tables
    gp, mc = doc["mcm-gp"], doc["mc"]
    [fitted] = gp["discrepancy_sd_fitted"]
    [ratio] = gp["gp_rate_ratio"]
    assert fitted > 0 and ratio > 0
    assert mc["discrepancy_sd_fitted"] == [] and mc["gp_rate_ratio"] == []
    assert mc["level0_per_batch"] == [10, 5, 5]  # plain MC: level 0 only
    assert sum(gp["level0_per_batch"]) < 20  # MCM-GP buys cheap runs too
    md = (tmp_path / "suite.md").read_text()
    header = next(line for line in md.splitlines() if line.startswith("| problem"))
    for column in ("recall, default", "var / uniform, default", "screened", "recall, p^alpha",
                   "100 RV", "disc. sd fitted", "true sd(f1 - f0)", "level-0 picks per batch",
                   "GP / p"):  # fmt: skip
        assert column in header
    # The default (staged) design's recall: MC's model says nothing, so both its stages
    # sample U uniformly and the recall is, in expectation, the uniform single-stage
    # design's, which the p^alpha column gives exactly for MC (alpha 0). About 8 failures
    # and 100 draws: up to a quarter either way (measured 0.0297 against 0.0237).
    [mc_seed] = mc["per_seed_recall_staged"]
    assert mc_seed == pytest.approx(mc["recall"], rel=0.35)
    assert 0 < gp["recall_staged"] <= 1
    # The default estimate: MC has no model to screen with, so its default is the staged
    # design; MCM-GP's is the screen where its fitted cheap level tracks level 0.
    assert mc["screened_seeds"] == 0 and mc["screens"] == [None]
    assert mc["per_seed_recall_default"] == mc["per_seed_recall_staged"]
    assert mc["per_seed_var_default"][0] == pytest.approx(1.0, abs=0.35)  # uniform in every stage
    [screen] = gp["screens"]
    assert gp["screened_seeds"] == (screen is not None)
    if screen is not None:
        assert screen["share"] == defaults.SCREEN_HINT_SHARE and screen["trials"] == B.SCREEN_TRIALS
        assert gp["per_seed_recall_default"] == [screen["recall"]]
        assert gp["per_seed_var_default"] == [screen["var_ratio"]]
    # The default design's recall, as drawn and as run, its variance and screened seeds
    # come first in a row, then p^alpha's.
    cells = [c.strip() for c in header.split("|")]
    at = cells.index("recall, default")
    assert cells[at + 1 : at + 5] == [
        "recall, as run (x MC)", "var / uniform, default", "screened", "recall, p^alpha",
    ]  # fmt: skip
    mc_row = next(line for line in md.splitlines() if "| MC |" in line).split("|")
    assert mc_row[at].strip().startswith(f"{mc['recall_default']:.3f}")
    assert mc_row[at + 1].strip() == "-"  # plain MC runs no realised estimate
    var = mc["per_seed_var_default"][0]
    assert mc_row[at + 2].strip() == f"{var:.2f} [{var:.2f}]" and mc_row[at + 3].strip() == "0"
    assert mc_row[at + 4].strip().startswith(f"{mc['recall']:.3f}")
    # As run: the failures the realised estimate had in hand, over the pool's, and that
    # over plain MC's recall.
    [realised] = gp["realised_estimates"]
    as_run = realised["distinct_failures_found"] / doc["setup"]["failures"]
    gp_row = next(line for line in md.splitlines() if "| MCM-GP |" in line).split("|")
    assert gp_row[at + 1].strip() == f"{as_run:.3f} ({as_run / mc['recall_default']:.1f}x)"
    assert condensed_row(tmp_path, "mcm-gp")["recall_realised"] == pytest.approx(as_run)
    row = next(line for line in md.splitlines() if line.startswith("| gap_sim"))
    assert f"{fitted:.3g}" in row and "10 / 5 / 5" in md
    condensed = json.loads((tmp_path / "suite.json").read_text())
    assert set(condensed) == {"gap_sim"} and set(results) == {"gap_sim"}
    assert condensed["gap_sim"]["strategies"]["mc"]["gp_rate_ratio"] is None


def condensed_row(folder, strategy):
    return json.loads((folder / "suite.json").read_text())["gap_sim"]["strategies"][strategy]


def test_staged_recall_is_the_staged_design_drawn_from_the_runs_own_model():
    # The suite's "recall, default" for one run: staged_trials on its final p_n and known
    # stratum (its own stream); a run without a model plans from a constant p_n; DS and CE
    # (scores, not probabilities) have none.
    from types import SimpleNamespace

    from bams_cli import benchmark as B
    from bams_cli.core.evaluate import staged_trials

    rng = np.random.default_rng(0)
    n = 3000
    p = rng.beta(0.3, 8.0, n)
    fail = rng.random(n) < p
    known = np.zeros(n, bool)
    known[np.argsort(-p)[:30]] = True  # discovery ran the riskiest segments
    # The last fit's cheap level tracks level 0 (discrepancy sd 0.1 of the signal's).
    close = {"outputscale0": 1.0, "outputscales": [0.005], "noise": [1e-4, 0.005]}
    run = SimpleNamespace(p_after=[None, p], scores=None, known=known, seed=7,
                          hyperparameters=[None, close])  # fmt: skip
    want = staged_trials(
        p,
        fail,
        K=120.0,
        known=known,
        n_trials=B.STAGED_TRIALS,
        rng=np.random.default_rng([7, 2026]),
    ).recall.mean()
    t = staged_trials(
        p, fail, K=120.0, known=known, n_trials=B.STAGED_TRIALS,
        rng=np.random.default_rng([7, 2026]),
    )  # fmt: skip
    assert B._staged_design(run, fail, 120.0) == pytest.approx(
        (want, t.var / t.var_uniform), rel=1e-12
    )
    # The known stratum's failures are in hand whatever the design.
    assert want >= fail[known].sum() / fail.sum()
    flat = staged_trials(
        np.ones(n), fail, K=120.0, known=known, n_trials=B.STAGED_TRIALS,
        rng=np.random.default_rng([7, 2026]),
    ).recall.mean()  # fmt: skip
    assert want > flat  # this p_n ranks the failures: its design holds more of them
    # A cheap level that does not track level 0 (sd 0.5 of the signal's): p_n is trusted
    # less, as estimate --plan trusts it (core.design.risk_prior).
    far = {"outputscale0": 1.0, "outputscales": [0.2], "noise": [1e-4, 0.05]}
    weak_run = SimpleNamespace(**{**vars(run), "hyperparameters": [None, far]})
    t_weak = staged_trials(
        p, fail, K=120.0, known=known, n_trials=B.STAGED_TRIALS,
        prior=defaults.RISK_MIX_PRIOR_WEAK_CHEAP, rng=np.random.default_rng([7, 2026]),
    )  # fmt: skip
    got = B._staged_design(weak_run, fail, 120.0)
    assert got == pytest.approx((t_weak.recall.mean(), t_weak.var / t_weak.var_uniform), rel=1e-12)
    assert got[1] != pytest.approx(t.var / t.var_uniform, rel=1e-3)
    mc = SimpleNamespace(p_after=[None], scores=None, known=known, seed=7, hyperparameters=[None])
    assert B._staged_design(mc, fail, 120.0)[0] == pytest.approx(flat, rel=1e-12)
    ds = SimpleNamespace(p_after=[None], scores=np.ones(n), known=known, seed=7,
                         hyperparameters=[None])  # fmt: skip
    assert B._staged_design(ds, fail, 120.0) is None


def test_every_suite_problem_has_a_protocol_without_paper_numbers():
    for name in SUITE[2:]:
        proto = PROTOCOLS[name]
        assert (proto.m1, proto.mb, proto.n_batches, proto.k_factor) == (10, 5, 3, 2.0)
        assert proto.paper == {} and proto.strategies == ("bams", "mcm-gp", "mc")
        # Reduced as a new study is, by embed-reduce's defaults (--dim auto).
        assert proto.reduce == {"method": "pca"}


def test_mc_estimates_uniformly_and_mc_gp_by_its_gp():
    """Same uniform picks; MC's design is uniform over U, MC-GP's follows p_n."""
    rng = np.random.default_rng(0)
    n, K = 2000, 60.0
    is_failure = rng.random(n) < 0.02
    known = np.zeros(n, bool)
    known[rng.choice(n, 20, replace=False)] = True
    picks = [(np.flatnonzero(known)[:10], np.zeros(10, np.int64))]
    est = {"alpha": 0.75, "defensive": 0.1, "design": "poisson"}

    def run(strategy, p):
        return RunResult(strategy, 0, picks, [p], None, known, [None], None, {})

    recall, rv = _run_designs(run("mc", None), is_failure, K, est)["default"]
    U = ~known
    pi = K / U.sum()  # every unknown segment equally likely
    fails_u = int((is_failure & U).sum())
    assert rv == pytest.approx(fails_u * (1 - pi) / pi / n**2 / is_failure.mean() ** 2)
    assert recall == pytest.approx((is_failure[known].sum() + pi * fails_u) / is_failure.sum())
    p_n = np.where(is_failure, 0.5, 0.01)
    _, rv_gp = _run_designs(run("mc-gp", p_n), is_failure, K, est)["default"]
    assert rv_gp < rv / 5


def test_benchmark_json_writes_undefined_numbers_as_null():
    """results.json and suite.json are strict JSON: NaN and inf, bare or inside numpy
    values and arrays, become null (a bare NaN is not JSON)."""
    import json as _json

    from bams_cli.benchmark import _strict_json

    doc = {
        "ratio": float("nan"),
        "rows": [1.5, np.float64("inf"), np.array([0.25, np.nan])],
        "seeds": (np.int64(3), -np.inf),
        "ok": {"x": np.float32(0.5)},
    }

    def refuse(name):
        raise ValueError(f"bare {name} in the JSON")

    got = _json.loads(_strict_json(doc), parse_constant=refuse)
    assert got == {
        "ratio": None,
        "rows": [1.5, None, [0.25, None]],
        "seeds": [3, None],
        "ok": {"x": 0.5},
    }
