"""Failed runs, as a study without truth meets them: results that say `crashed`, requests
recorded as abandoned (`ingest-results --abandon-failed`, `abandon`), a study that goes on
without them, and an estimate that refuses them or bounds them (`--failed-as bounds`)."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import polars as pl
import pytest
from typer.testing import CliRunner

from bams_cli import abandon
from bams_cli.state.io import journal_in, recover
from bams_cli.state.lock import workspace_lock
from bams_cli.state.workspace import Workspace
from tests.conftest import STAGED_PLAN, answer_handoff, invoke, ok, tree_hash, write_toy


def _status(runner, ws):
    r = invoke(runner, "status", "-w", ws, "--json")
    return r.exit_code, json.loads(r.stdout)


@pytest.fixture
def study(tmp_path):
    """A 400-segment toy2d study with a random level-0 batch of 10 whose first three
    requests crashed."""
    runner = CliRunner()
    seg, truth = write_toy(tmp_path / "data", n=400, seed=5)
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.56", "--costs", "1,0.5", "--dim", "2", "--seed", "1")
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize")  # fmt: skip
    ok(runner, "select", "-w", ws, "--strategy", "random", "--budget", "10")
    crashed = {"b0001-0001", "b0001-0002", "b0001-0003"}
    res = answer_handoff(
        runner, ws / "batches" / "batch-0001.csv", truth, tmp_path / "r1.csv", crashed
    )
    return runner, ws, truth, res, crashed


def test_crashed_rows_block_until_abandoned_then_the_study_goes_on(study, tmp_path):
    runner, ws, _, res, crashed = study
    ok(runner, "ingest-results", "-w", ws, res)
    code, s = _status(runner, ws)
    assert code == 3 and s["pending"] == 3 and s["abandoned"] == 0
    assert (
        invoke(runner, "select", "-w", ws, "--strategy", "random", "--budget", "5").exit_code == 3
    )

    r = ok(runner, "ingest-results", "-w", ws, res, "--abandon-failed", "--json")
    out = json.loads(r.stdout)
    assert out["abandoned"]["abandoned"] == 3 and out["pending"]["count"] == 0
    code, s = _status(runner, ws)
    assert code == 0 and s["pending"] == 0 and s["abandoned"] == 3
    assert s["batches"][0]["abandoned"] == 3 and s["next"]["step"] == "fit"
    log = Workspace(ws).read_abandoned()
    assert sorted(log["request_id"]) == sorted(crashed)
    assert set(log["reason"]) == {"status 'crashed' in r1.csv"}

    before = tree_hash(ws)  # a repeat changes nothing, by either command
    r = ok(runner, "ingest-results", "-w", ws, res, "--abandon-failed")
    # Nothing is pending because the failed requests were abandoned, not answered.
    assert "nothing pending: every selected segment has a result or is abandoned" in r.stdout
    r = ok(runner, "abandon", "-w", ws, "--batch", "1", "--json")
    assert json.loads(r.stdout)["unchanged"] is True
    assert tree_hash(ws) == before


def test_abandoned_pairs_are_never_picked_again_unless_asked(study):
    runner, ws, _, res, _ = study
    ok(runner, "ingest-results", "-w", ws, res, "--abandon-failed")
    gone = set(Workspace(ws).read_abandoned()["segment_id"])
    # 400 segments: 7 observed at level 0 and 3 abandoned leave exactly 390 to pick.
    ws2 = ws.parent / "ws2"
    shutil.copytree(ws, ws2)
    ok(runner, "select", "-w", ws, "--strategy", "random", "--budget", "390")
    picked = set(Workspace(ws).read_batch(2)["segment_id"])
    assert len(picked) == 390 and not picked & gone
    r = invoke(runner, "select", "-w", ws2, "--strategy", "random", "--budget", "393",
               "--retry-abandoned")  # fmt: skip
    assert r.exit_code == 0, r.output
    assert gone <= set(Workspace(ws2).read_batch(2)["segment_id"])


def test_bams_select_never_offers_an_abandoned_pair(study):
    runner, ws, *_ = study
    runner, ws, truth, res, _ = study
    ok(runner, "ingest-results", "-w", ws, res, "--abandon-failed")
    # Batch 2 asks for level 1 of 300 of the 400 segments; all of it is lost.
    ok(runner, "select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", "150",
       "--level0-share", "0")  # fmt: skip
    ok(runner, "abandon", "-w", ws, "--batch", "2", "--fidelity", "low1")
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    r = ok(runner, "select", "-w", ws, "--budget", "4", "--clusters", "2", "--workers", "1",
           "--json")  # fmt: skip
    assert json.loads(r.stdout)["picks"] > 0
    gone = Workspace(ws).read_abandoned().select("segment_id", "fidelity")
    assert gone.height == 303
    picked = Workspace(ws).read_batch(3).select("segment_id", "fidelity")
    assert picked.join(gone, on=["segment_id", "fidelity"], how="semi").height == 0


def _plan_study(runner, ws, truth, tmp: Path, n_lost: int = 3):
    """From the fixture's study: batches in, a plan drawn, its results in but for the
    first ``n_lost`` requests, which are abandoned. Returns their request ids."""
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "40")
    handoff = ws / "estimates" / "plan-0001-handoff.csv"
    rids = [r["request_id"] for r in csv.DictReader(handoff.open())][:n_lost]
    res = answer_handoff(runner, handoff, truth, tmp / "p1.csv", set(rids))
    ok(runner, "ingest-results", "-w", ws, res)
    return rids, res


def test_estimate_refuses_abandoned_planned_segments_then_bounds_them(study, tmp_path, monkeypatch):
    runner, ws, truth, res, _ = study
    ok(runner, "ingest-results", "-w", ws, res, "--abandon-failed")
    rids, _ = _plan_study(runner, ws, truth, tmp_path)
    code, s = _status(runner, ws)
    assert code == 3 and s["plans"][0]["pending"] == 3  # not abandoned yet: waiting
    lost = tmp_path / "lost.csv"
    lost.write_text("request_id\n" + "\n".join(rids) + "\n")
    ok(runner, "abandon", "-w", ws, "--segments", lost, "--reason", "simulator crash")
    code, s = _status(runner, ws)
    assert code == 0 and s["plans"][0]["abandoned"] == 3
    assert s["next"]["command"].endswith("--failed-as bounds")

    plan = pl.read_parquet(ws / "estimates" / "plan-0001.parquet")
    ids = plan.filter(pl.col("request_id").is_in(rids))["segment_id"].to_list()
    before = tree_hash(ws)
    r = invoke(runner, "estimate", "-w", ws)
    assert r.exit_code == 1 and "3 planned segments were abandoned" in r.stderr
    assert ids[0] in r.stderr and "--failed-as bounds" in r.stderr
    assert tree_hash(ws) == before

    # The printed note gives the range, not only that there is one.
    printed = ok(runner, "estimate", "-w", ws, "--failed-as", "bounds").stderr.splitlines()
    bounded = json.loads(ok(runner, "estimate", "-w", ws, "--failed-as", "bounds", "--json").stdout)
    row = bounded["estimates"][0]
    assert (
        f"gamma 0.56, relative variance: undefined: p_hat is a range, {row['p_hat_low']:.4g} "
        f"(the 3 abandoned segments all passing) to {row['p_hat_high']:.4g} (all failing)"
    ) in printed
    assert bounded["abandoned"]["count"] == 3 and sorted(
        bounded["abandoned"]["segments"]
    ) == sorted(ids)

    # A note on a p_hat held within what the sample allows speaks of the estimate as
    # reported, the all-failing case, not of the one before the bounds.
    real = abandon.bound_estimates

    def held_high(*args, **kwargs):
        high = real(*args, **kwargs)
        return dataclasses.replace(high, p_hat_unbiased=high.p_hat * 2.0)

    monkeypatch.setattr(abandon, "bound_estimates", held_high)
    held = json.loads(ok(runner, "estimate", "-w", ws, "--failed-as", "bounds", "--json").stdout)
    monkeypatch.undo()
    notes = [n for n in held["notes"] if "not seen to pass" in n]
    assert len(notes) == len(held["estimates"]) and not [n for n in bounded["notes"] if "sum" in n]
    assert f"so p_hat is that share ({held['estimates'][0]['p_hat']:.4g})" in notes[0]
    assert notes[0].startswith("gamma 0.56, with the 3 abandoned segments all failing: ")

    # The bounds are the estimator run on the plan with the lost runs all passing and all
    # failing: what results saying exactly that would give.
    cases = {}
    for name, value in (("pass", 9.0), ("fail", -9.0)):
        copy = tmp_path / f"ws-{name}"
        shutil.copytree(ws, copy)
        filled = tmp_path / f"{name}.csv"
        filled.write_text("request_id,value\n" + "".join(f"{rid},{value}\n" for rid in rids))
        ok(runner, "ingest-results", "-w", copy, filled)
        cases[name] = json.loads(ok(runner, "estimate", "-w", copy, "--json").stdout)
    for row, lo, hi in zip(bounded["estimates"], cases["pass"]["estimates"],
                           cases["fail"]["estimates"], strict=True):  # fmt: skip
        assert row["ci_low"] == pytest.approx(lo["ci_low"])
        assert row["ci_high"] == pytest.approx(hi["ci_high"])
        assert row["p_hat_low"] == pytest.approx(lo["p_hat"])
        assert row["p_hat_high"] == pytest.approx(hi["p_hat"]) == pytest.approx(row["p_hat"])
        assert row["p_hat_low"] < row["p_hat_high"]
        assert row["n_sampled"] == lo["n_sampled"]  # never a smaller sample
        assert row["se"] is None and "abandoned" in row["variance_note"]

    # status says the estimate is a range, not the all-failing end of it as a rate.
    code, s = _status(runner, ws)
    row = s["latest_estimate"]["estimates"][0]
    assert row["p_hat_low"] == pytest.approx(bounded["estimates"][0]["p_hat_low"])
    text = invoke(runner, "status", "-w", ws).stdout
    assert "p_hat between " in text and "(abandoned segments passing, then failing)" in text

    # The report shows the bounded estimate and the abandoned counts, without truth; its
    # headline gives the range.
    ok(runner, "report", "-w", ws)
    md = (ws / "report" / "summary.md").read_text()
    assert "3 planned segments abandoned" in md
    summary = json.loads((ws / "report" / "summary.json").read_text())
    assert summary["headline"]["text"].startswith("failure rate between ")
    summary = json.loads((ws / "report" / "summary.json").read_text())
    assert summary["batches"][0]["abandoned"] == 3


def test_a_late_result_outranks_the_abandonment(study, tmp_path):
    runner, ws, truth, res, crashed = study
    ok(runner, "ingest-results", "-w", ws, res, "--abandon-failed")
    late = tmp_path / "late.csv"
    late.write_text("request_id,value\nb0001-0001,1.5\n")
    ok(runner, "ingest-results", "-w", ws, late)
    code, s = _status(runner, ws)
    assert code == 0 and s["batches"][0]["abandoned"] == 2
    assert Workspace(ws).read_abandoned().height == 3  # the log keeps the record


@pytest.mark.parametrize(
    ("args", "code", "needle"),
    [
        # No request named: a usage error, exit 2, as a missing argument is.
        ((), 2, "say which requests: --batch N, --plan N or --segments FILE"),
        # Requests the study does not have: exit 1.
        (("--batch", "7"), 1, "--batch 7: no such batch (batches: 1)"),
        (("--plan", "1"), 1, "--plan 1: no such estimate plan (plans: none yet)"),
        (("--batch", "1", "--fidelity", "medium"), 1, "--fidelity 'medium': not a level"),
    ],
)
def test_abandon_usage_errors_change_nothing(study, args, code, needle):
    runner, ws, *_ = study
    before = tree_hash(ws)
    r = invoke(runner, "abandon", "-w", ws, *args)
    assert r.exit_code == code and needle in r.stderr, r.stderr
    assert tree_hash(ws) == before


def test_abandoning_a_run_that_has_a_result_is_an_error(study, tmp_path):
    runner, ws, _, res, _ = study
    ok(runner, "ingest-results", "-w", ws, res)
    lost = tmp_path / "lost.csv"
    lost.write_text("request_id\nb0001-0002\nb0001-0009\n")
    r = invoke(runner, "abandon", "-w", ws, "--segments", lost)
    assert r.exit_code == 1 and "lost.csv: column 'request_id', row 2" in r.stderr
    assert "already has a result" in r.stderr


# ---- killed at any moment: the logs hold all of a command's writes or none -----------------
def _content(ws: Path) -> tuple:
    w = Workspace(ws)
    obs = w.read_observations(active_only=False).select("segment_id", "fidelity", "value")
    return (
        sorted(obs.iter_rows()),
        sorted(w.read_abandoned()["request_id"].to_list()),
    )


@pytest.mark.parametrize("command", ["ingest", "abandon"])
def test_a_killed_writing_command_leaves_all_or_nothing(study, tmp_path, command):
    runner, ws, _, res, _ = study
    args = (
        ["ingest-results", "-w", str(ws), str(res), "--abandon-failed"]
        if command == "ingest"
        else ["abandon", "-w", str(ws), "--batch", "1", "--reason", "gone"]
    )
    if command == "abandon":
        ok(runner, "ingest-results", "-w", ws, res)
    before = _content(ws)
    done = tmp_path / "done"
    shutil.copytree(ws, done)
    ok(runner, *[done if a == str(ws) else a for a in args])
    after = _content(done)
    assert after != before
    rng = random.Random(0)
    for i in range(4):
        copy = tmp_path / f"k{i}"
        shutil.copytree(ws, copy)
        proc = subprocess.Popen(
            [sys.executable, "-m", "bams_cli", *[str(copy) if a == str(ws) else a for a in args]],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        time.sleep(rng.uniform(0.3, 2.5))
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        with workspace_lock(copy), journal_in(copy):  # what the next command does first
            recover(copy)
        assert _content(copy) in (before, after)
        assert not list(copy.rglob(".tmp-*"))
