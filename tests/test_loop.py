"""The whole loop through the CLI on a small toy2d pool, and the report in a real browser."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow.parquet as pq
import pytest

from bams_cli.report import SUMMARY_KEYS
from bams_cli.state.io import read_metadata
from bams_cli.state.workspace import Workspace
from tests.conftest import STAGED_PLAN, invoke, ok, tree_hash, write_toy


@pytest.fixture(scope="module")
def loop_ws(tmp_path_factory):
    """A study after a random batch, two BAMS batches and one estimate (module-scoped: slow-ish)."""
    from typer.testing import CliRunner

    runner = CliRunner()
    tmp = tmp_path_factory.mktemp("loop")
    seg, truth = write_toy(tmp / "data", n=1500, seed=4)
    ws = tmp / "ws"
    ok(
        runner,
        "init",
        "-w",
        ws,
        "--gamma",
        "0.56,1.0",
        "--costs",
        "1,0.1",
        "--dim",
        "2",
        "--seed",
        "3",
    )
    ok(
        runner,
        "embed-reduce",
        "-w",
        ws,
        seg,
        "--columns",
        "x*",
        "--method",
        "identity",
        "--no-standardize",
    )
    ok(runner, "select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", "8")
    for b in (1, 2, 3):
        if b > 1:
            ok(runner, "select", "-w", ws, "--budget", "3", "--clusters", "2", "--workers", "1")
        res = tmp / f"r{b}.parquet"
        ok(
            runner,
            "simulate",
            ws / "batches" / f"batch-{b:04d}.parquet",
            "--truth",
            truth,
            "-o",
            res,
        )
        ok(runner, "ingest-results", "-w", ws, res)
        ok(runner, "fit", "-w", ws, "--restarts", "2")
    plan = json.loads(
        ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "60", "--json").stdout
    )
    res = tmp / "est.parquet"
    ok(runner, "simulate", ws / "estimates" / "plan-0001-handoff.csv", "--truth", truth, "-o", res)
    ok(runner, "ingest-results", "-w", ws, res)
    # The model predates the plan's results. The IS estimate needs no model, and the GP's
    # own estimate is the one stored with the plan; only --exact-variance needs a refit.
    before = tree_hash(ws)
    r = invoke(runner, "estimate", "-w", ws, "--exact-variance")
    assert r.exit_code == 1 and "--exact-variance needs a model of the current one" in r.stderr
    assert "the observation log changed after the last fit (fitted on " in r.stderr
    assert "--fixed-hyperparameters" in r.stderr and tree_hash(ws) == before
    stale = json.loads(ok(runner, "estimate", "-w", ws, "--json").stdout)
    assert stale["gp_model"] == "as of the plan"
    widest = max(stale["gp"], key=lambda g: g["gamma"])  # the gamma the plan was drawn on
    assert widest["gp_p_hat"] == pytest.approx(plan["gp_rate_estimate"], rel=1e-12)
    ok(runner, "report", "-w", ws)  # a model older than the log is shown, under a banner
    html = (ws / "report" / "report.html").read_text()
    assert html.index("class='banner warning' role='alert' data-kind='stale_model'") < html.index(
        "<h2>"
    )
    ok(runner, "fit", "-w", ws, "--restarts", "2")
    fresh = json.loads(ok(runner, "estimate", "-w", ws, "--exact-variance", "--json").stdout)
    assert fresh["gp_model"] == "current"
    assert fresh["estimates"] == stale["estimates"]  # same plan, same results
    ok(runner, "report", "-w", ws, "--truth", truth)
    assert "model up to date" in (ws / "report" / "report.html").read_text()
    return ws, truth


def test_batches_respect_budget_and_record_options(loop_ws):
    ws, _ = loop_ws
    w = Workspace(ws)
    assert w.batch_numbers() == [1, 2, 3]
    b1 = w.read_batch(1)
    assert b1["cost"].sum() <= 8 + 1e-12 and set(b1["fidelity"]) == {0, 1}
    for b in (2, 3):
        df = w.read_batch(b)
        assert df["cost"].sum() <= 3 + 1e-12
        assert (df["strategy"] == "bams").all()
        # one level-0 confirmation run (default share 0.2 of a budget of 3, at least one),
        # then the greedy's picks, each with its decrease of J
        confirm = df.filter(df["purpose"] != "discover")
        assert confirm.height == 1 and confirm["fidelity"].to_list() == [0]
        assert confirm["delta_j"].is_nan().all()
        assert df.filter(df["purpose"] == "discover")["delta_j"].is_not_nan().all()
        meta = read_metadata(ws / "batches" / f"batch-{b:04d}.parquet")
        assert json.loads(meta["options"])["budget"] == 3 and meta["model_hash"]
        assert (ws / "batches" / f"batch-{b:04d}.csv").exists()
    # no level-0 pair is picked twice across batches
    picks = w.read_batches().filter(w.read_batches()["fidelity"] == 0)
    assert picks["segment_id"].is_unique().all()


def test_snapshots_are_per_batch_and_survive_the_estimate_refit(loop_ws):
    ws, _ = loop_ws
    snaps = sorted(p.name for p in (ws / "history").glob("*.parquet"))
    assert snaps == [f"scores-after-batch-{b:04d}.parquet" for b in (1, 2, 3)]
    # the last fit (after the plan's results) is not the batch-3 snapshot
    final = json.loads((ws / "model.json").read_text())["observations_hash"]
    assert (
        read_metadata(ws / "history" / "scores-after-batch-0003.parquet")["observations_hash"]
        != final
    )


def test_estimate_is_consistent_with_the_plan(loop_ws):
    ws, truth = loop_ws
    doc = json.loads((ws / "estimates" / "estimate-0001.json").read_text())
    plan = pq.read_table(ws / "estimates" / "plan-0001.parquet").to_pylist()
    sampled = [r for r in plan if r["stratum"] == "sampled"]
    t = {r["segment_id"]: r["value_0"] for r in pq.read_table(truth).to_pylist()}
    for g, est in zip((0.56, 1.0), doc["estimates"], strict=True):
        known_f = sum(t[r["segment_id"]] <= g for r in plan if r["stratum"] == "known")
        ht = sum(1 / r["pi"] for r in sampled if t[r["segment_id"]] <= g)
        assert est["p_hat"] == pytest.approx((known_f + ht) / 1500, rel=1e-12)
        assert est["ci_low"] <= est["p_hat"] <= est["ci_high"]
    # the GP's exact variance lies below its Proposition-1 bound
    for g in doc["gp"]:
        assert 0 <= g["gp_var_exact"] <= g["gp_var_bound"] + 1e-15
    # one sample serves both gammas: the larger gamma finds at least as many failures
    assert (
        doc["estimates"][1]["distinct_failures_found"]
        >= doc["estimates"][0]["distinct_failures_found"]
    )


def test_summary_json_has_its_documented_keys(loop_ws):
    ws, _ = loop_ws
    summary = json.loads((ws / "report" / "summary.json").read_text())
    assert tuple(summary) == SUMMARY_KEYS
    # Two gammas: the per-gamma estimate plot; --truth: its comparison and recall plots.
    assert set(summary["figures"]) == {
        "rate_band",
        "predicted",
        "p_distribution",
        "groups",
        "pool_map",
        "rate",
        "rate_truth",
        "recall",
    }
    assert [b["batch"] for b in summary["batches"]] == [1, 2, 3]
    assert summary["truth"]["failures"][0] == round(summary["truth"]["rate"][0] * 1500)
    assert len(summary["diverse_failures"]) == 5
    md = (ws / "report" / "summary.md").read_text()
    assert "| gamma | p_hat |" in md


NO_BROWSER = (
    "no chromium on PATH: the report's browser test needs Debian's chromium "
    "(apt-get install chromium; .ci/run installs it)"
)


@pytest.fixture(scope="session")
def chromium() -> str:
    """Headless Chromium, or a skip; in CI (CI or BAMS_REQUIRE_BROWSER set) a failure.

    Session-scoped and listed first, so a skip comes before the loop is built.
    """
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path:
        return path
    if os.environ.get("CI") or os.environ.get("BAMS_REQUIRE_BROWSER"):
        pytest.fail(f"{NO_BROWSER}; CI must run this test", pytrace=False)
    pytest.skip(NO_BROWSER)


def test_report_renders_in_headless_chromium_with_every_image(chromium, loop_ws):
    ws, _ = loop_ws
    html = ws / "report" / "report.html"
    flags = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
    ]
    with tempfile.TemporaryDirectory() as profile:
        dom = subprocess.run(
            [
                chromium,
                *flags,
                f"--user-data-dir={profile}",
                "--virtual-time-budget=5000",
                "--window-size=1280,720",  # a laptop's first screen
                "--dump-dom",
                html.as_uri(),
            ],
            capture_output=True,
            text=True,
            timeout=120,
        ).stdout
    n_img = dom.count("<img ")
    figures = json.loads((ws / "report" / "summary.json").read_text())["figures"]
    assert n_img == len(figures) >= 3
    assert f"<title>images-ok {n_img}/{n_img} headline-in-first-screen fits-width " in dom
    with tempfile.TemporaryDirectory() as profile:
        shot = ws / "report" / "screenshot.png"
        subprocess.run(
            [
                chromium,
                *flags,
                f"--user-data-dir={profile}",
                "--window-size=1200,3000",
                f"--screenshot={shot}",
                html.as_uri(),
            ],
            capture_output=True,
            timeout=120,
        )
    assert shot.stat().st_size > 50_000  # a page with its plots, not a blank one


def test_pending_batch_blocks_select(loop_ws, tmp_path):
    from typer.testing import CliRunner

    ws, _ = loop_ws
    copy = tmp_path / "ws"
    shutil.copytree(ws, copy)
    runner = CliRunner()
    ok(runner, "select", "-w", copy, "--strategy", "random", "--budget", "2")
    before = tree_hash(copy)
    r = invoke(runner, "select", "-w", copy, "--strategy", "random", "--budget", "2")
    assert r.exit_code == 3 and "have no results yet" in r.stderr and "--allow-pending" in r.stderr
    assert tree_hash(copy) == before
    ok(runner, "select", "-w", copy, "--strategy", "random", "--budget", "2", "--allow-pending")


def test_estimate_refuses_a_missing_result(loop_ws, tmp_path):
    from typer.testing import CliRunner

    ws, _ = loop_ws
    copy = tmp_path / "ws"
    shutil.copytree(ws, copy)
    runner = CliRunner()
    ok(runner, "fit", "-w", copy, "--restarts", "1")
    ok(runner, "estimate", "-w", copy, *STAGED_PLAN, "--samples", "40", "--new-series")
    before = tree_hash(copy)
    r = invoke(runner, "estimate", "-w", copy)
    assert r.exit_code == 3 and "planned segments have no level-0 result" in r.stderr
    assert tree_hash(copy) == before


@pytest.mark.parametrize("strategy", ["mc-gp", "mcm-gp", "ce", "bas"])
def test_other_strategies_write_a_batch(loop_ws, tmp_path, strategy):
    from typer.testing import CliRunner

    ws, _ = loop_ws
    copy = tmp_path / "ws"
    shutil.copytree(ws, copy)
    runner = CliRunner()
    ok(runner, "fit", "-w", copy, "--restarts", "1")
    r = ok(
        runner,
        "select",
        "-w",
        copy,
        "--strategy",
        strategy,
        "--budget",
        "2",
        "--clusters",
        "2",
        "--workers",
        "1",
        "--json",
    )
    summary = json.loads(r.stdout)
    assert summary["total_cost"] <= 2 + 1e-12 and summary["picks"] >= 1
    df = Workspace(copy).read_batch(summary["batch"])
    if strategy in ("bas", "mc-gp", "ce"):
        assert set(df["fidelity"]) == {0}
    assert np.all(df["strategy"].to_numpy() == strategy)


@pytest.mark.parametrize(
    ("args", "code", "needle"),
    [
        (["select", "--clusters", "0"], 2, "--clusters 0: must be >= 1"),
        (["select", "--overbudget", "0.5"], 2, "--overbudget 0.5: must be a finite number >= 1"),
        (["select", "--budget", "inf"], 2, "--budget inf: must be a finite number > 0"),
        (
            ["select", "--strategy", "random", "--budget", "1e12"],
            1,
            "buys more simulations than the pool has",
        ),
        (
            ["select", "--strategy", "random", "--mixed-fidelity", "--level0-share", "1.5"],
            2,
            "--level0-share 1.5",
        ),
        (
            ["estimate", *STAGED_PLAN, "--samples", "nan"],
            2,
            "--samples nan: must be a finite number",
        ),
        (
            ["estimate", *STAGED_PLAN, "--alpha", "nan"],
            2,
            "--alpha nan: must be a finite number >= 0",
        ),
        (["fit", "--chunk-size", "0"], 2, "--chunk-size 0: must be >= 1"),
        (["fit", "--restarts", "-2"], 2, "--restarts -2: must be >= 1"),
        (["report", "--diverse", "-1"], 2, "--diverse -1: must be >= 0"),
        (["embed-reduce", "x.parquet", "--batch-size", "0"], 2, "--batch-size 0: must be >= 1"),
        (["init", "--gamma", ",", "--force"], 2, "--gamma ',': expected comma-separated numbers"),
    ],
)
def test_bad_options_fail_in_one_line(loop_ws, tmp_path, args, code, needle):
    from typer.testing import CliRunner

    ws, _ = loop_ws
    copy = tmp_path / "ws"
    shutil.copytree(ws, copy)
    before = tree_hash(copy)
    r = invoke(CliRunner(), args[0], "-w", copy, *args[1:])
    assert r.exit_code == code and needle in r.stderr, r.stderr
    assert r.stderr.count("\n") == 1
    assert tree_hash(copy) == before


def test_dask_scheduler_gives_the_same_batch_as_local_processes(loop_ws, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    from typer.testing import CliRunner

    ws, _ = loop_ws
    runner = CliRunner()
    picks = {}
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False) as cluster:
        for name, extra in (
            ("local", ["--workers", "2"]),
            ("dask", ["--scheduler", cluster.scheduler_address]),
        ):
            copy = tmp_path / name
            shutil.copytree(ws, copy)
            ok(runner, "fit", "-w", copy, "--restarts", "1")
            r = ok(
                runner, "select", "-w", copy, "--budget", "3", "--clusters", "2", *extra, "--json"
            )
            summary = json.loads(r.stdout)
            batch = Workspace(copy).read_batch(summary["batch"])
            if name == "dask":  # --json says where the greedies ran
                assert summary["selection_plan"]["scheduler"] == cluster.scheduler_address
            # confirmation picks carry delta_j NaN, which never equals itself
            picks[name] = batch.select(
                "segment_id", "fidelity", pl.col("delta_j").fill_nan(None)
            ).rows()
    assert picks["local"] == picks["dask"] and len(picks["local"]) > 0


def test_a_scheduler_without_workers_is_a_one_line_error(loop_ws, tmp_path, monkeypatch):
    distributed = pytest.importorskip("dask.distributed")
    from typer.testing import CliRunner

    ws, _ = loop_ws
    copy = tmp_path / "ws"
    shutil.copytree(ws, copy)
    ok(CliRunner(), "fit", "-w", copy, "--restarts", "1")
    before = tree_hash(copy)
    real = distributed.Client.wait_for_workers

    def brief(self, n_workers=1, timeout=None):  # the 30 s the command waits, in 1 s
        return real(self, n_workers, timeout=1)

    monkeypatch.setattr(distributed.Client, "wait_for_workers", brief)
    with distributed.LocalCluster(n_workers=0, processes=False) as cluster:
        r = invoke(
            CliRunner(), "select", "-w", copy, "--budget", "3", "--scheduler",
            cluster.scheduler_address,
        )  # fmt: skip
    assert r.exit_code == 1
    assert r.stderr.count("\n") == 1 and "the scheduler has no worker" in r.stderr, r.stderr
    assert tree_hash(copy) == before


def test_the_next_command_completes_a_commit_a_crash_interrupted(toy_ws, runner):
    # As if a command died after renaming some of its files: the rest wait, staged, and the
    # journal lists every rename. The next command that takes the lock finishes the job.
    staged = toy_ws / "batches" / ".tmp-batch-0009.csv-123-1"
    staged.parent.mkdir(exist_ok=True)
    staged.write_text("segment_id,fidelity\nt000001,0\n")
    target = toy_ws / "batches" / "batch-0009.csv"
    pairs = [[str(staged), str(target)], [str(toy_ws / ".tmp-gone-123-0"), str(toy_ws / "x")]]
    (toy_ws / ".bams-journal.json").write_text(json.dumps({"renames": pairs}))
    stray = toy_ws / ".tmp-scores.parquet-456-0"  # staged by a command that never committed
    stray.write_text("partial")
    r = ok(runner, "select", "-w", toy_ws, "--strategy", "random", "--budget", "2")
    assert "finished an interrupted command's commit (1 file renamed" in r.stderr
    assert target.read_text().startswith("segment_id,fidelity")
    assert not (toy_ws / ".bams-journal.json").exists() and not stray.exists()
    assert not (toy_ws / "x").exists()


def test_status_finishes_a_commit_a_killed_select_left_and_reports_its_batch(toy_ws, runner):
    # As if `select` was killed among its renames: its files wait staged, the journal lists
    # them. status completes the commit (as the next writing command would) and reports the
    # batch awaiting results, not "run select" (a trial killed select at its journal).
    staged = _journal_of_a_killed_select(toy_ws, runner)
    r = invoke(runner, "status", "-w", toy_ws, "--json")
    assert r.exit_code == 3, r.output
    summary = json.loads(r.stdout)
    assert summary["next"]["step"] == "ingest-results"
    assert summary["finished_interrupted_commit"] == staged
    assert not summary["commit_in_progress"] and not (toy_ws / ".bams-journal.json").exists()
    assert "finished an interrupted command's commit" in r.stderr
    assert tree_hash(toy_ws) == tree_hash(toy_ws.parent / f"{toy_ws.name}-after")


def _journal_of_a_killed_select(ws: Path, runner) -> int:
    """Stage a random select's files in ``ws`` and journal them, as a kill among its
    renames leaves them; returns the number of files staged."""
    copy = ws.parent / f"{ws.name}-after"
    shutil.copytree(ws, copy)
    ok(runner, "select", "-w", copy, "--strategy", "random", "--budget", "2")
    pairs = []
    for path in sorted(p for p in copy.rglob("*") if p.is_file() and ".lock" not in p.name):
        rel = path.relative_to(copy)
        target = ws / rel
        if target.exists() and target.read_bytes() == path.read_bytes():
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        staged = target.parent / f".tmp-{target.name}-999-{len(pairs)}"
        staged.write_bytes(path.read_bytes())
        pairs.append([str(staged.relative_to(ws)), rel.as_posix()])
    (ws / ".bams-journal.json").write_text(json.dumps({"renames": pairs}))
    return len(pairs)


def test_status_leaves_a_running_command_s_commit_alone(toy_ws, runner, monkeypatch):
    # The journal of a command still holding the lock is its commit under way: status
    # neither completes it nor takes the lock; and where it cannot take the lock (a
    # workspace it may not write), it reports the workspace as it stands.
    from bams_cli.state import lock

    _journal_of_a_killed_select(toy_ws, runner)
    before = tree_hash(toy_ws)
    with lock.workspace_lock(toy_ws):  # this process: alive, holding the lock
        r = invoke(runner, "status", "-w", toy_ws, "--json")
    summary = json.loads(r.stdout)
    assert summary["commit_in_progress"] and summary["finished_interrupted_commit"] == 0
    assert tree_hash(toy_ws) == before

    def refused(*args, **kwargs):
        raise PermissionError(13, "Permission denied", str(toy_ws / ".bams.lock"))

    monkeypatch.setattr(lock, "workspace_lock", refused)
    r = invoke(runner, "status", "-w", toy_ws, "--json")
    assert r.exit_code == 0, r.output  # as before the commit began: a first batch to select
    assert json.loads(r.stdout)["commit_in_progress"] and tree_hash(toy_ws) == before


def test_a_budget_is_refused_only_beyond_what_the_whole_pool_costs(toy_ws, runner):
    # 400 segments at levels costing 1 and 0.1 cost 440 in all: 100 level-0 runs are a
    # batch (the bound was budget / the cheapest cost, 1,000 > 800 runs: refused), 441 not.
    ok(runner, "select", "-w", toy_ws, "--strategy", "random", "--budget", "100")
    before = tree_hash(toy_ws)
    r = invoke(runner, "select", "-w", toy_ws, "--strategy", "random", "--budget", "441")
    assert r.exit_code == 1 and "(400 segments x 2 levels cost 440)" in r.stderr, r.stderr
    assert tree_hash(toy_ws) == before
