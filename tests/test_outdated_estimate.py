"""An estimate whose results were replaced after it was computed is not shown as current.

A simulation team that finds a bad run among an estimate plan's results sends the
corrected value with `ingest-results --replace`. The estimate computed before still reads
the old value: `status` names `estimate` as the next command, `report` says so above the
headline, `loop` computes it again, and a new `estimate` keeps the earlier one beside it.
A discovery result or a cheap-level result the estimate does not read leaves it current.
"""

from __future__ import annotations

import json
from pathlib import Path

import polars as pl
import pytest
from typer.testing import CliRunner

from bams_cli.state.workspace import Workspace
from tests.conftest import STAGED_PLAN, fitted_toy_study, invoke, ok, simulate_and_ingest


def _status(runner: CliRunner, ws: Path) -> dict:
    return json.loads(invoke(runner, "status", "-w", ws, "--json").stdout)


def _notices(runner: CliRunner, ws: Path) -> list[dict]:
    ok(runner, "report", "-w", ws)
    return json.loads((ws / "report" / "summary.json").read_text())["notices"]


@pytest.fixture(scope="module")
def estimated(tmp_path_factory) -> tuple[CliRunner, Path, Path, Path]:
    """A toy study with one one-stage plan of 60 runs, ingested and estimated."""
    runner = CliRunner()
    folder = tmp_path_factory.mktemp("outdated")
    ws, truth = fitted_toy_study(runner, folder)
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--stages", "1", "--samples", "60")
    simulate_and_ingest(
        runner, ws, ws / "estimates" / "plan-0001-handoff.csv", truth, folder / "plan-1.parquet"
    )
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    ok(runner, "estimate", "-w", ws)
    ok(runner, "report", "-w", ws)
    return runner, ws, truth, folder


def _copy(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def _replace(runner: CliRunner, ws: Path, rows: pl.DataFrame, path: Path) -> None:
    rows.select("segment_id", "fidelity", "value").write_parquet(path)
    ok(runner, "ingest-results", "-w", ws, path, "--replace")


def test_a_replaced_plan_result_makes_the_estimate_out_of_date(estimated, tmp_path):
    runner, src, _, _ = estimated
    ws = _copy(src, tmp_path / "ws")
    assert _status(runner, ws)["next"]["step"] == "done"
    before = json.loads((ws / "estimates" / "estimate-0001.json").read_text())
    assert isinstance(before["inputs_hash"], str)
    # One sampled segment's level-0 result corrected: a pass becomes a failure.
    w = Workspace(ws)
    sampled = w.read_plan_picks().filter(pl.col("plan") == 1)["segment_id"]
    obs = w.read_observations().filter(
        (pl.col("fidelity") == 0)
        & pl.col("segment_id").is_in(sampled.to_list())
        & (pl.col("value") > 0.56)
    )
    _replace(runner, ws, obs.head(1).with_columns(pl.lit(-1.0).alias("value")), tmp_path / "r.pq")
    # A stale model is fitted first, as ever; then the estimate.
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    st = _status(runner, ws)
    assert st["latest_estimate"]["out_of_date"] is True
    assert "estimate (plan 1, out of date): gamma 0.56" in invoke(runner, "status", "-w", ws).stdout
    assert st["next"]["step"] == "estimate"
    assert st["next"]["command"] == f"bams-cli estimate -w {ws}"
    assert "plan 1's estimate is out of date" in st["next"]["text"]
    notice = _notices(runner, ws)[0]
    assert notice["kind"] == "outdated_estimate" and notice["severity"] == "warning"
    assert notice["text"].startswith("The estimate shown is out of date: results of plan 1 ")
    summary = json.loads((ws / "report" / "summary.json").read_text())
    assert summary["estimates"][0]["p_hat"] == before["estimates"][0]["p_hat"]  # warned
    # Every result delivered counts as spent, and the headline says one was superseded.
    spent = summary["simulation_spent"]
    assert spent["superseded"] == 1 and spent["count"] == w.read_observations().height + 1
    md = " ".join((ws / "report" / "summary.md").read_text().split())
    assert f"{spent['count']} simulations costing {spent['cost']:g} level-0 runs (1 of " in md
    # Computed again: the failure counts, the earlier estimate is kept, and all is current.
    ok(runner, "estimate", "-w", ws)
    after = json.loads((ws / "estimates" / "estimate-0001.json").read_text())
    kept = json.loads((ws / "estimates" / "estimate-0001.1.json").read_text())
    assert kept["estimates"] == before["estimates"]
    assert after["estimates"][0]["p_hat"] > before["estimates"][0]["p_hat"]
    assert after["inputs_hash"] != before["inputs_hash"]
    assert _status(runner, ws)["next"]["step"] == "report"
    assert _status(runner, ws)["latest_estimate"]["out_of_date"] is False
    assert "outdated_estimate" not in [n["kind"] for n in _notices(runner, ws)]
    assert _status(runner, ws)["next"]["step"] == "done"


def test_loop_computes_an_out_of_date_estimate_again(estimated, tmp_path):
    runner, src, truth, _ = estimated
    ws = _copy(src, tmp_path / "ws")
    w = Workspace(ws)
    sampled = w.read_plan_picks().filter(pl.col("plan") == 1)["segment_id"]
    obs = w.read_observations().filter(
        (pl.col("fidelity") == 0) & pl.col("segment_id").is_in(sampled.to_list())
    )
    flipped = pl.when(pl.col("value") <= 0.56).then(1.0).otherwise(-1.0).alias("value")
    _replace(runner, ws, obs.head(2).with_columns(flipped), tmp_path / "r.pq")
    assert w.estimate_out_of_date(1)
    simulator = f"bams-cli simulate {{handoff}} --truth {truth} -o {{results}}"
    ok(runner, "loop", "-w", ws, "--batches", "1", "--then-estimate", "--simulator", simulator)
    assert not w.estimate_out_of_date(1)
    assert (ws / "estimates" / "estimate-0001.1.json").exists()


def test_results_the_estimate_does_not_read_leave_it_current(estimated, tmp_path):
    runner, src, truth, _ = estimated
    ws = _copy(src, tmp_path / "ws")
    w = Workspace(ws)
    held = w.estimate_inputs_hash([1], [0.56])
    # A cheap-level result replaced, and a new discovery batch with its results.
    cheap = w.read_observations().filter(pl.col("fidelity") == 1).head(1)
    _replace(runner, ws, cheap.with_columns(pl.col("value") + 1.0), tmp_path / "r.pq")
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    ok(runner, "select", "-w", ws, "--strategy", "random", "--budget", "3")
    simulate_and_ingest(
        runner, ws, ws / "batches" / "batch-0002.parquet", truth, tmp_path / "b2.parquet"
    )
    assert w.estimate_inputs_hash([1], [0.56]) == held
    assert not w.estimate_out_of_date(1)
    kinds = [n["kind"] for n in _notices(runner, ws)]
    assert "outdated_estimate" not in kinds and "stale_estimate" in kinds


def test_a_new_plan_beside_an_estimate_never_computed_says_so(estimated, tmp_path):
    runner, src, _, _ = estimated
    ws = _copy(src, tmp_path / "ws")
    (ws / "estimates" / "estimate-0001.json").unlink()  # plan 1's results in, never estimated
    r = ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "30", "--json")
    warned = json.loads(r.stdout)["warnings"]
    assert (
        "plan 1 has all its results but its estimate was never computed: `bams-cli estimate "
        f"-w {ws} --plan-number 1` computes it; this plan, 2, starts a new estimate beside it"
    ) in warned
    # With plan 1 estimated, a new plan says nothing of it.
    ws2 = _copy(src, tmp_path / "ws2")
    r = ok(runner, "estimate", "-w", ws2, *STAGED_PLAN, "--samples", "30", "--json")
    assert not any("never computed" in w for w in json.loads(r.stdout)["warnings"])


def test_a_value_corrected_on_the_same_side_of_gamma_leaves_it_current(estimated, tmp_path):
    runner, src, _, _ = estimated
    ws = _copy(src, tmp_path / "ws")
    w = Workspace(ws)
    sampled = w.read_plan_picks().filter(pl.col("plan") == 1)["segment_id"].to_list()
    obs = w.read_observations().filter(
        (pl.col("fidelity") == 0) & pl.col("segment_id").is_in(sampled) & (pl.col("value") > 0.7)
    )
    # 0.7 -> 0.8 and the like: every gamma's outcome the same, so the estimate is too.
    _replace(runner, ws, obs.head(3).with_columns(pl.col("value") + 0.1), tmp_path / "r.pq")
    assert not w.estimate_out_of_date(1)
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    assert _status(runner, ws)["next"]["step"] == "report"


def _partial(runner, ws, handoff, truth, path, drop: int) -> list[str]:
    """Simulate a hand-off list and ingest all but its last ``drop`` results; their ids."""
    full = path.with_name(path.stem + "-all.parquet")
    ok(runner, "simulate", handoff, "--truth", truth, "-o", full)
    rows = pl.read_parquet(full)
    rows.head(rows.height - drop).write_parquet(path)
    ok(runner, "ingest-results", "-w", ws, path)
    rows.tail(drop).write_parquet(path.with_name(path.stem + "-rest.parquet"))
    return rows.tail(drop)["segment_id"].to_list()


def test_an_estimate_over_abandoned_runs_is_computed_again_with_its_bounds(tmp_path):
    runner = CliRunner()
    ws, truth = fitted_toy_study(runner, tmp_path)
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--stages", "1", "--samples", "40")
    handoff = ws / "estimates" / "plan-0001-handoff.csv"
    _partial(runner, ws, handoff, truth, tmp_path / "p1.parquet", drop=2)
    ok(runner, "abandon", "-w", ws, "--plan", "1", "--reason", "simulator crash")
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    ok(runner, "estimate", "-w", ws, "--failed-as", "bounds")
    assert _status(runner, ws)["next"]["step"] == "report"
    # One abandoned run is simulated after all: a result the estimate's bounds did not have.
    rest = pl.read_parquet(tmp_path / "p1-rest.parquet")
    rest.head(1).write_parquet(tmp_path / "late.parquet")
    ok(runner, "ingest-results", "-w", ws, tmp_path / "late.parquet", "--allow-unselected")
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    st = _status(runner, ws)
    assert st["next"]["command"] == f"bams-cli estimate -w {ws} --failed-as bounds"
    assert f"`bams-cli estimate -w {ws} --failed-as bounds`" in _notices(runner, ws)[0]["text"]
    simulator = f"bams-cli simulate {{handoff}} --truth {truth} -o {{results}}"
    ok(runner, "loop", "-w", ws, "--batches", "1", "--then-estimate", "--simulator", simulator)
    assert not Workspace(ws).estimate_out_of_date(1)


def test_a_staged_estimate_reads_every_stage_and_the_known_stratum(tmp_path):
    runner = CliRunner()
    ws, truth = fitted_toy_study(runner, tmp_path)
    w = Workspace(ws)
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--stages", "2", "--samples", "40")
    simulate_and_ingest(
        runner, ws, ws / "estimates" / "plan-0001-handoff.csv", truth, tmp_path / "p1.parquet"
    )
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    ok(runner, "estimate", "-w", ws)  # stage 1 of 2, so far
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN)  # stage 2, its results out
    # A stage-1 result corrected while stage 2 is out: the estimate shown is plan 1's, and
    # the command that computes it again names it.
    sampled = w.read_plan_picks().filter(pl.col("plan") == 1)["segment_id"].to_list()
    one = w.read_observations().filter(
        (pl.col("fidelity") == 0) & pl.col("segment_id").is_in(sampled) & (pl.col("value") > 0.56)
    )
    _replace(runner, ws, one.head(1).with_columns(pl.lit(-1.0).alias("value")), tmp_path / "a.pq")
    notice = _notices(runner, ws)
    assert notice[0]["kind"] == "outdated_estimate"
    assert f"`bams-cli estimate -w {ws} --plan-number 1`" in notice[0]["text"]
    ok(runner, "estimate", "-w", ws, "--plan-number", "1")
    assert not w.estimate_out_of_date(1)
    # Stage 2 in and the estimate of both: current, though it reads two plans.
    simulate_and_ingest(
        runner, ws, ws / "estimates" / "plan-0002-handoff.csv", truth, tmp_path / "p2.parquet"
    )
    ok(runner, "estimate", "-w", ws)
    doc = json.loads((ws / "estimates" / "estimate-0002.json").read_text())
    assert doc["staging"]["plans"] == [1, 2] and not w.estimate_out_of_date(2)
    # A result of the known stratum (run before plan 1 was drawn) corrected across gamma.
    known = (
        pl.read_parquet(ws / "estimates" / "plan-0001.parquet")
        .filter(pl.col("stratum") == "known")["segment_id"]
        .to_list()
    )
    old = (
        w.read_observations()
        .filter((pl.col("fidelity") == 0) & pl.col("segment_id").is_in(known))
        .head(1)
    )
    flipped = pl.when(pl.col("value") <= 0.56).then(1.0).otherwise(-1.0).alias("value")
    _replace(runner, ws, old.with_columns(flipped), tmp_path / "k.pq")
    assert w.estimate_out_of_date(2) and w.estimate_out_of_date(1)
    assert _status(runner, ws)["latest_estimate"]["out_of_date"] is True
