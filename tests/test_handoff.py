"""The hand-off contract (issue 13.4): one CSV layout for batches and plans, request ids,
results templates, and results keyed by request id or by (segment, level number or name)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from bams_cli.core import synthetic
from bams_cli.state.handoff import HANDOFF_COLUMNS, TEMPLATE_COLUMNS, request_ids
from bams_cli.state.workspace import Workspace
from tests.conftest import STAGED_PLAN, invoke, ok, tree_hash, write_batch

LEVELS = ["full", "quick"]  # the study's names for level 0 and level 1


@pytest.fixture
def named_ws(tmp_path: Path, runner) -> tuple[Path, Path]:
    """A 300-segment toy2d study whose levels are named, with a pass-through column."""
    pool = synthetic.toy2d(300, 1)
    seg, truth = tmp_path / "segments.parquet", tmp_path / "truth.parquet"
    scenario = np.where(pool.features[:, 0] > 0, "highway", "urban")
    pq.write_table(
        pa.table(
            {
                "segment_id": pool.ids,
                "x0": pool.features[:, 0],
                "x1": pool.features[:, 1],
                "scenario": scenario,
            }
        ),
        seg,
    )
    pq.write_table(
        pa.table(
            {"segment_id": pool.ids, "value_0": pool.truth[:, 0], "value_1": pool.truth[:, 1]}
        ),
        truth,
    )
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.56", "--costs", "1,0.1", "--level-names", ",".join(LEVELS), "--dim", "2")  # fmt: skip
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity", "--no-standardize")  # fmt: skip
    return ws, truth


def _select(runner, ws: Path, *extra: object) -> dict:
    r = ok(runner, "select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", 2, "--json", *extra)  # fmt: skip
    return json.loads(r.stdout)


def _csv(path: Path) -> pl.DataFrame:
    return pl.read_csv(path, infer_schema_length=0)  # every column as text, as a team sees it


def test_batch_and_plan_handoffs_share_one_layout(named_ws, runner, tmp_path):
    ws, truth = named_ws
    batch = _select(runner, ws)
    res = tmp_path / "r1.parquet"
    ok(runner, "simulate", batch["handoff_csv"], "--truth", truth, "-o", res)
    ok(runner, "ingest-results", "-w", ws, res)
    ok(runner, "fit", "-w", ws, "--restarts", 2)
    plan = json.loads(
        ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", 8, "--json").stdout
    )

    b = _csv(Path(batch["handoff_csv"]))
    p = _csv(Path(plan["handoff"]))
    # The contract's columns in order, then the pool's pass-through column; nothing internal.
    assert b.columns == p.columns == [*HANDOFF_COLUMNS, "scenario"]
    assert b["request_id"].to_list() == request_ids("batch", 1, b.height)
    assert b["request_id"][0] == "b0001-0001"
    assert p["request_id"].to_list() == request_ids("plan", 1, p.height)
    assert set(b["source"]) == {"batch 1"} and set(p["source"]) == {"plan 1"}
    assert set(b["fidelity"]) == {"0", "1"} and set(p["fidelity"]) == {"0"}
    names = dict(zip(b["fidelity"], b["fidelity_name"], strict=True))
    assert names == {"0": "full", "1": "quick"} and set(p["fidelity_name"]) == {"full"}
    assert set(b["purpose"]) == {"discover"} and set(p["purpose"]) == {"estimate"}
    assert set(b["cost"].cast(float)) == {1.0, 0.1}

    # The Parquet state keeps every internal column, and the request ids.
    state = pq.read_table(batch["handoff"]).column_names
    for col in ("delta_j", "cluster", "rank", "strategy", "request_id", "fidelity_name"):
        assert col in state
    plan_state = pl.read_parquet(plan["plan_file"])
    for col in ("stratum", "pi", "draws", "request_id"):
        assert col in plan_state.columns
    assert (
        plan_state.filter(pl.col("stratum") == "known")["request_id"].null_count()
        == (plan_state["stratum"] == "known").sum()
    )

    # A results template beside each list: the requests, value and status left empty.
    for handoff, template in ((b, batch["results_template"]), (p, plan["results_template"])):
        t = _csv(Path(template))
        assert t.columns == list(TEMPLATE_COLUMNS)
        assert t["request_id"].to_list() == handoff["request_id"].to_list()
        assert t["value"].null_count() == t["status"].null_count() == t.height
    assert Path(batch["results_template"]).name == "batch-0001.results-template.csv"
    assert Path(plan["results_template"]).name == "plan-0001.results-template.csv"


def test_handoff_internal_adds_internal_columns_to_the_csv(named_ws, runner):
    ws, _ = named_ws
    batch = _select(runner, ws, "--handoff-internal")
    cols = _csv(Path(batch["handoff_csv"])).columns
    assert cols[: len(HANDOFF_COLUMNS)] == list(HANDOFF_COLUMNS)
    assert cols[len(HANDOFF_COLUMNS) :] == ["delta_j", "cluster", "rank", "strategy", "scenario"]


def _fill_template(batch: dict, truth: Path, out: Path, keep: list[str]) -> pl.DataFrame:
    """The team's answer: the template with its values filled in, keeping some columns."""
    t = pl.read_csv(batch["results_template"], schema_overrides={"segment_id": pl.String})
    tr = pl.read_parquet(truth)
    values = [
        tr.filter(pl.col("segment_id") == s)[f"value_{lv}"][0]
        for s, lv in zip(t["segment_id"], t["fidelity"], strict=True)
    ]
    t = t.with_columns(pl.Series("value", values), pl.lit("ok").alias("status")).select(keep)
    t.write_csv(out)
    return t


def test_results_keyed_by_request_id_alone(named_ws, runner, tmp_path):
    ws, truth = named_ws
    batch = _select(runner, ws)
    answer = _fill_template(batch, truth, tmp_path / "r.csv", ["request_id", "value", "status"])
    r = ok(runner, "ingest-results", "-w", ws, tmp_path / "r.csv", "--json")
    assert json.loads(r.stdout)["pending"]["count"] == 0
    log = Workspace(ws).read_observations()
    assert log.height == answer.height
    assert set(log["batch"]) == {1}
    handoff = _csv(Path(batch["handoff_csv"]))
    # Each value landed on its request's segment and level; the request id is kept.
    got = {json.loads(e)["request_id"]: (s, f) for s, f, e in log.select("segment_id", "fidelity", "extra").iter_rows()}  # fmt: skip
    want = {r: (s, int(f)) for r, s, f in handoff.select("request_id", "segment_id", "fidelity").iter_rows()}  # fmt: skip
    assert got == want


def test_fidelity_by_number_or_name_mixed(named_ws, runner, tmp_path):
    ws, truth = named_ws
    batch = _select(runner, ws)
    t = _fill_template(batch, truth, tmp_path / "r.csv", ["segment_id", "fidelity", "value"])
    mixed = [LEVELS[f] if i % 2 else str(f) for i, f in enumerate(t["fidelity"])]
    t.with_columns(pl.Series("fidelity", mixed)).write_csv(tmp_path / "r.csv")
    ok(runner, "ingest-results", "-w", ws, tmp_path / "r.csv")
    log = Workspace(ws).read_observations().sort("segment_id", "fidelity")
    assert log.select("segment_id", "fidelity").rows() == t.sort("segment_id", "fidelity").select("segment_id", "fidelity").rows()  # fmt: skip


def _bad(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "bad.csv"
    path.write_text(text)
    return path


@pytest.mark.parametrize(
    "rows, needle",
    [
        (
            "segment_id,fidelity,value\n{s0},{f0},1.0\n{s1},medium,1.0\n",
            "column 'fidelity', row 2: fidelity must be an integer level or a level name, "
            "got 'medium'; known levels: 0 = 'full', 1 = 'quick'",
        ),
        (
            "request_id,value\n{r0},1.0\nb0001-0999,2.0\n",
            "column 'request_id', row 2: request_id 'b0001-0999' is not in any hand-off list",
        ),
        (
            "request_id,value\n{r0},1.0\n{r0},1.0\n",
            "column 'request_id', row 2: request_id '{r0}' appears again (first at row 1)",
        ),
        (
            "request_id,value\n{r0},1.0\n{r1},1.0\n{r2},1.0\n{r1},1.0\n{r0},1.0\n",
            "column 'request_id', row 4: request_id '{r1}' appears again (first at row 2)",
        ),
        (
            "request_id,segment_id,value\n{r0},{s1},1.0\n",
            "column 'segment_id', row 1: request_id '{r0}' is segment '{s0}', but this row names '{s1}'",
        ),
        (
            "request_id,value,status\n{r0},,\n",
            "column 'value', row 1: value must be a finite number, got nothing; fill it in, or say "
            "why there is none in the status column",
        ),
        (
            "value\n1.0\n",
            "missing required column(s) 'segment_id', 'fidelity'; key each result by request_id",
        ),
    ],
)
def test_bad_keys_fail_in_one_line_and_change_nothing(named_ws, runner, tmp_path, rows, needle):
    ws, _ = named_ws
    batch = _select(runner, ws)
    h = _csv(Path(batch["handoff_csv"]))
    keys = {"r0": h["request_id"][0], "s0": h["segment_id"][0], "f0": h["fidelity"][0],
            "s1": h["segment_id"][2], "r1": h["request_id"][1], "r2": h["request_id"][2]}  # fmt: skip
    before = tree_hash(ws)
    r = invoke(runner, "ingest-results", "-w", ws, _bad(tmp_path, rows.format(**keys)))
    assert r.exit_code == 1
    assert r.stderr.count("\n") == 1 and r.stderr.startswith(f"error: {tmp_path / 'bad.csv'}: ")
    assert needle.format(**keys) in r.stderr
    assert tree_hash(ws) == before


def test_rows_marked_not_run_stay_pending(named_ws, runner, tmp_path):
    ws, truth = named_ws
    batch = _select(runner, ws)
    t = _fill_template(batch, truth, tmp_path / "r.csv", list(TEMPLATE_COLUMNS))
    status = ["crashed"] + ["ok"] * (t.height - 1)
    value = [None, *t["value"][1:]]
    t.with_columns(pl.Series("status", status), pl.Series("value", value)).write_csv(
        tmp_path / "r.csv"
    )
    r = ok(runner, "ingest-results", "-w", ws, tmp_path / "r.csv", "--json")
    summary = json.loads(r.stdout)
    assert summary["ingested"] == t.height - 1
    assert summary["not_run"]["count"] == 1
    assert summary["not_run"]["first"][0]["request_id"] == t["request_id"][0]
    assert summary["not_run"]["first"][0]["status"] == "crashed"
    # The level as a number, as every other list of runs in --json gives it (was "1").
    assert summary["not_run"]["first"][0]["fidelity"] == t["fidelity"][0]
    assert summary["pending"]["count"] == 1
    # The same file again is a no-op that still names the run as not run, while it is...
    again = json.loads(ok(runner, "ingest-results", "-w", ws, tmp_path / "r.csv", "--json").stdout)
    assert again["already_ingested"] and again["not_run"]["count"] == 1
    # ... but not once its retry has a result: nothing of it stays pending.
    retry = tmp_path / "retry.csv"
    t.head(1).select("request_id", "value").write_csv(retry)
    ok(runner, "ingest-results", "-w", ws, retry)
    r = ok(runner, "ingest-results", "-w", ws, tmp_path / "r.csv")
    again = json.loads(ok(runner, "ingest-results", "-w", ws, tmp_path / "r.csv", "--json").stdout)
    assert again["already_ingested"] and again["pending"]["count"] == 0
    assert again["not_run"]["count"] == 0
    assert "not run" not in r.stdout + r.stderr


@pytest.mark.parametrize("flags", [(), ("--abandon-failed",)])
@pytest.mark.parametrize("word", ["failed", "PASSED", "crashed"])
def test_a_value_beside_a_not_run_status_is_refused(named_ws, runner, tmp_path, flags, word):
    # A team wrote status "failed" for the system's outcome beside every value. Those rows
    # were set aside as not run with exit 0, and --abandon-failed abandoned the failures.
    ws, truth = named_ws
    batch = _select(runner, ws)
    t = _fill_template(batch, truth, tmp_path / "r.csv", list(TEMPLATE_COLUMNS))
    status = ["ok", word, "ok", word] + ["ok"] * (t.height - 4)
    t.with_columns(pl.Series("status", status)).write_csv(tmp_path / "r.csv")
    before = tree_hash(ws)
    r = invoke(runner, "ingest-results", "-w", ws, tmp_path / "r.csv", *flags)
    assert r.exit_code == 1, r.output
    assert r.stderr.count("\n") == 1
    assert r.stderr.startswith(
        f"error: {tmp_path / 'r.csv'}: column 'status', row 2: status {word!r} says the run "
        f"made no result, but the row has value "
    )
    assert "(2 such rows)" in r.stderr
    assert tree_hash(ws) == before
    # A value the file holds as text (a decimal comma) is a value too.
    text = [str(v) for v in t["value"]]
    text[1] = "0,3"
    t.with_columns(pl.Series("status", status), pl.Series("value", text)).write_csv(
        tmp_path / "r.csv"
    )
    r = invoke(runner, "ingest-results", "-w", ws, tmp_path / "r.csv", *flags)
    assert r.exit_code == 1, r.output
    assert (
        f"row 2: status {word!r} says the run made no result, but the row has value '0,3'"
        in r.stderr
    )
    assert tree_hash(ws) == before
    # Without the values the same statuses say the runs were not made: set aside, pending.
    value = [t["value"][0], None, t["value"][2], None, *t["value"][4:]]
    t.with_columns(pl.Series("status", status), pl.Series("value", value)).write_csv(
        tmp_path / "r.csv"
    )
    summary = json.loads(
        ok(runner, "ingest-results", "-w", ws, tmp_path / "r.csv", "--json").stdout
    )
    assert summary["ingested"] == t.height - 2 and summary["not_run"]["count"] == 2


def test_not_run_rows_keyed_by_segment_give_their_level_as_a_number(named_ws, runner, tmp_path):
    # A team without request ids names each run by segment and level name; the rows it
    # marks as not run come back with the level's number, as every other list gives it.
    ws, truth = named_ws
    batch = _select(runner, ws)
    t = _fill_template(batch, truth, tmp_path / "r.csv", ["segment_id", "fidelity", "value"])
    names = [LEVELS[f] for f in t["fidelity"]]
    status = ["crashed"] + ["ok"] * (t.height - 1)
    value = [None, *t["value"][1:]]
    t.with_columns(
        pl.Series("fidelity", names), pl.Series("status", status), pl.Series("value", value)
    ).write_csv(tmp_path / "r.csv")
    summary = json.loads(
        ok(runner, "ingest-results", "-w", ws, tmp_path / "r.csv", "--json").stdout
    )
    (row,) = summary["not_run"]["first"]
    assert row["segment_id"] == t["segment_id"][0]
    assert row["fidelity"] == t["fidelity"][0] and isinstance(row["fidelity"], int)
    assert row["fidelity_given"] == names[0] and row["request_id"] is None
    # A level the study does not have has no number, but its text is still shown.
    t.with_columns(
        pl.Series("fidelity", ["ultra", *names[1:]]),
        pl.Series("status", status),
        pl.Series("value", value),
    ).write_csv(tmp_path / "r2.csv")
    again = json.loads(ok(runner, "ingest-results", "-w", ws, tmp_path / "r2.csv", "--json").stdout)
    (row,) = again["not_run"]["first"]
    assert row["fidelity"] is None and row["fidelity_given"] == "ultra"


def test_a_not_run_row_whose_retry_came_first_is_not_pending(named_ws, runner, tmp_path):
    # The retry's results ingested before the file that first said "crashed": that file
    # then names no row as not run, since none of its requests waits any more.
    ws, truth = named_ws
    batch = _select(runner, ws)
    t = _fill_template(batch, truth, tmp_path / "r.csv", list(TEMPLATE_COLUMNS))
    status = ["crashed", "crashed"] + ["ok"] * (t.height - 2)
    value = [None, None, *t["value"][2:]]
    t.head(2).select("request_id", "value").write_csv(tmp_path / "retry.csv")
    t.with_columns(pl.Series("status", status), pl.Series("value", value)).write_csv(
        tmp_path / "r.csv"
    )
    ok(runner, "ingest-results", "-w", ws, tmp_path / "retry.csv")
    summary = json.loads(
        ok(runner, "ingest-results", "-w", ws, tmp_path / "r.csv", "--json").stdout
    )
    assert summary["ingested"] == t.height - 2
    assert summary["not_run"]["count"] == 0 and summary["pending"]["count"] == 0


def test_batches_written_before_request_ids_get_them_from_their_rows(toy_ws, runner, tmp_path):
    # conftest.write_batch writes a batch as an older bams-cli did: no request_id column.
    write_batch(toy_ws, 1, ["t000000", "t000001", "t000002"], [0, 0, 1])
    assert Workspace(toy_ws).requests()["request_id"].to_list() == [
        "b0001-0001",
        "b0001-0002",
        "b0001-0003",
    ]
    res = _bad(tmp_path, "request_id,value\nb0001-0003,0.7\n")
    ok(runner, "ingest-results", "-w", toy_ws, res)
    log = Workspace(toy_ws).read_observations()
    assert log.select("segment_id", "fidelity", "batch").rows() == [("t000002", 1, 1)]
