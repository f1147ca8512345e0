"""ingest-results: the append-only log, idempotence, and every bad-input path."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from bams_cli.state.io import JOURNAL_NAME
from bams_cli.state.workspace import Workspace
from tests.conftest import (
    STAGED_PLAN,
    answer_handoff,
    invoke,
    ok,
    tree_hash,
    write_batch,
    write_toy,
)

IDS = ["t000000", "t000001", "t000002", "t000003"]


def _results(path: Path, rows: list[tuple], extra: dict | None = None) -> Path:
    cols = {
        "segment_id": [r[0] for r in rows],
        "fidelity": [r[1] for r in rows],
        "value": [r[2] for r in rows],
    }
    cols.update(extra or {})
    if path.suffix == ".csv":
        import pyarrow.csv as pacsv

        pacsv.write_csv(pa.table(cols), path)
    else:
        pq.write_table(pa.table(cols), path)
    return path


@pytest.fixture
def ws(toy_ws: Path) -> Path:
    write_batch(toy_ws, 1, IDS, [0, 0, 1, 1])
    return toy_ws


def test_ingest_appends_and_keeps_extra_columns(ws, runner, tmp_path):
    res = _results(
        tmp_path / "r1.parquet",
        [(IDS[0], 0, 1.5), (IDS[1], 0, 0.3)],
        extra={"sim_version": ["v7", "v7"]},
    )
    r = invoke(runner, "ingest-results", "-w", ws, res, "--json")
    assert r.exit_code == 0, r.output
    log = Workspace(ws).read_observations()
    assert log.height == 2
    assert log["batch"].to_list() == [1, 1]
    assert log["source_file"].to_list() == ["r1.parquet"] * 2
    assert '"sim_version": "v7"' in log["extra"][0]
    assert '"count": 2' in r.stdout  # two picks of batch 1 still pending


def test_the_still_pending_table_says_how_many_it_leaves_out(toy_ws, runner, tmp_path):
    # "still pending: 27" listed 20 rows and said nothing of the other 7.
    ids = [f"t{i:06d}" for i in range(30)]
    write_batch(toy_ws, 1, ids, [0] * 30)
    res = _results(tmp_path / "r1.parquet", [(i, 0, 1.0) for i in ids[:3]])
    out = " ".join(ok(runner, "ingest-results", "-w", toy_ws, res).stdout.split())
    assert "still pending: 27" in out and "... and 7 more (first 20 shown)" in out
    assert out.count("batch 1") >= 20
    # At 20 or fewer, no caption.
    res = _results(tmp_path / "r2.parquet", [(i, 0, 1.0) for i in ids[3:10]])
    out = " ".join(ok(runner, "ingest-results", "-w", toy_ws, res).stdout.split())
    assert "still pending: 20" in out and "more (first" not in out


def test_reingest_same_file_changes_nothing(ws, runner, tmp_path):
    res = _results(tmp_path / "r1.parquet", [(IDS[0], 0, 1.5)])
    assert invoke(runner, "ingest-results", "-w", ws, res).exit_code == 0
    before = tree_hash(ws)
    r = invoke(runner, "ingest-results", "-w", ws, res)
    assert r.exit_code == 0
    assert "already ingested" in r.stderr
    assert tree_hash(ws) == before


def test_csv_results_are_accepted(ws, runner, tmp_path):
    res = _results(tmp_path / "r.csv", [(IDS[2], 1, 0.7), (IDS[3], 1, 2.0)])
    r = invoke(runner, "ingest-results", "-w", ws, res)
    assert r.exit_code == 0, r.output
    assert Workspace(ws).read_observations()["fidelity"].to_list() == [1, 1]


def test_conflict_needs_replace_and_keeps_history(ws, runner, tmp_path):
    assert (
        invoke(
            runner, "ingest-results", "-w", ws, _results(tmp_path / "a.parquet", [(IDS[0], 0, 1.5)])
        ).exit_code
        == 0
    )
    clash = _results(tmp_path / "b.parquet", [(IDS[0], 0, 9.0)])
    before = tree_hash(ws)
    r = invoke(runner, "ingest-results", "-w", ws, clash)
    assert r.exit_code == 1
    assert "b.parquet: column 'value', row 1" in r.stderr and "--replace" in r.stderr
    assert tree_hash(ws) == before
    r = invoke(runner, "ingest-results", "-w", ws, clash, "--replace")
    assert r.exit_code == 0, r.output
    full = Workspace(ws).read_observations(active_only=False)
    assert full.height == 2  # nothing is lost: the old value stays, inactive
    assert full.filter(full["active"])["value"].to_list() == [9.0]
    # The summary counts the rows fit and status count ("2 rows now" beside their 1 said).
    assert " ".join(r.stdout.split()).startswith(
        f"ingested 1 result into {ws / 'observations.parquet'} (1 row now, 1 superseded kept "
        "beside them)"
    )
    assert "replaced 1" in " ".join(r.stdout.split())
    again = _results(tmp_path / "c.parquet", [(IDS[0], 0, 9.5)])
    out = json.loads(ok(runner, "ingest-results", "-w", ws, again, "--replace", "--json").stdout)
    assert (out["log_rows"], out["log_active"]) == (3, 1)
    # A later ingest that replaces nothing says so: the superseded rows are the log's.
    new = _results(tmp_path / "d.parquet", [(IDS[1], 0, 2.0)])
    text = " ".join(ok(runner, "ingest-results", "-w", ws, new).stdout.split())
    assert "(2 rows now, 2 superseded kept beside them)" in text and "replaced" not in text


@pytest.mark.parametrize(
    ("rows", "needle"),
    [
        (
            [(IDS[0], 0, 1.0), ("nope", 0, 1.0)],
            "column 'segment_id', row 2: segment id 'nope' is not in the pool",
        ),
        (
            [(IDS[0], 0, 1.0), (IDS[1], 2, 1.0)],
            "column 'fidelity', row 2: fidelity 2 is not a configured level",
        ),
        ([(IDS[0], 0, float("nan"))], "column 'value', row 1: value must be a finite number"),
        ([(IDS[0], 0, float("inf"))], "column 'value', row 1: value must be a finite number"),
        (
            [(IDS[0], 0, 1.0), (IDS[1], 0, 1.0), (IDS[0], 0, 1.0)],
            "column 'segment_id', row 3: ('t000000', fidelity 0) appears again",
        ),
        (
            # Two repeated pairs, the later one's copy first: the row named is the first
            # that repeats an earlier one, and "first at" is that pair's own first row.
            [
                (IDS[0], 0, 1.0),
                (IDS[1], 0, 1.0),
                (IDS[2], 0, 1.0),
                (IDS[1], 0, 1.0),
                (IDS[0], 0, 1.0),
            ],
            "column 'segment_id', row 4: ('t000001', fidelity 0) appears again (first at row 2)",
        ),
        ([(IDS[0], 0.5, 1.0)], "column 'fidelity', row 1: fidelity must be an integer level"),
        (
            [("t000009", 0, 1.0)],
            "row 1: 1 (segment_id, fidelity) pairs were never selected (t000009); pass --allow-unselected",
        ),
    ],
)
def test_bad_results_fail_in_one_line_and_change_nothing(ws, runner, tmp_path, rows, needle):
    res = _results(tmp_path / "bad.parquet", rows)
    before = tree_hash(ws)
    r = invoke(runner, "ingest-results", "-w", ws, res)
    assert r.exit_code == 1
    assert needle in r.stderr
    assert r.stderr.count("\n") == 1 and "bad.parquet" in r.stderr
    assert tree_hash(ws) == before


def test_missing_column_and_unreadable_file(ws, runner, tmp_path):
    p = tmp_path / "nocol.parquet"
    pq.write_table(pa.table({"segment_id": [IDS[0]], "value": [1.0]}), p)
    r = invoke(runner, "ingest-results", "-w", ws, p)
    assert r.exit_code == 1 and "missing required column(s) 'fidelity'" in r.stderr
    junk = tmp_path / "junk.parquet"
    junk.write_bytes(b"not parquet")
    r = invoke(runner, "ingest-results", "-w", ws, junk)
    assert r.exit_code == 1 and "junk.parquet: cannot read as Parquet" in r.stderr


def test_allow_unselected(ws, runner, tmp_path):
    res = _results(tmp_path / "u.parquet", [("t000009", 0, 1.0)])
    r = invoke(runner, "ingest-results", "-w", ws, res, "--allow-unselected")
    assert r.exit_code == 0, r.output
    log = Workspace(ws).read_observations()
    assert log["batch"].to_list() == [None]


def test_pending_listed_until_ingested(ws, runner, tmp_path):
    assert Workspace(ws).pending().height == 4
    invoke(
        runner,
        "ingest-results",
        "-w",
        ws,
        _results(tmp_path / "a.parquet", [(IDS[0], 0, 1.0), (IDS[2], 1, 1.0)]),
    )
    pend = Workspace(ws).pending()
    assert sorted(zip(pend["segment_id"], pend["fidelity"], strict=True)) == [
        (IDS[1], 0),
        (IDS[3], 1),
    ]


def test_zero_padded_ids_survive_csv(toy_ws, runner, tmp_path):
    # a pool whose ids look numeric: "007" must not become 7 on the way through CSV
    seg = tmp_path / "padded.parquet"
    pq.write_table(
        pa.table({"segment_id": ["007", "010"], "x0": [0.5, 1.0], "x1": [0.0, 1.0]}), seg
    )
    assert invoke(runner, "embed-reduce", "-w", toy_ws, seg, "--apply").exit_code == 0
    write_batch(toy_ws, 1, ["007", "010"], [0, 1])
    res = _results(tmp_path / "r.csv", [("007", 0, 1.0), ("010", 1, 2.0)])
    r = invoke(runner, "ingest-results", "-w", toy_ws, res)
    assert r.exit_code == 0, r.output
    assert sorted(Workspace(toy_ws).read_observations()["segment_id"]) == ["007", "010"]


def test_error_text_is_printed_as_written(ws, runner, tmp_path):
    res = _results(tmp_path / "m.csv", [("[/a]", 0, 1.0)])
    r = invoke(runner, "ingest-results", "-w", ws, res)
    assert r.exit_code == 1 and "segment id '[/a]' is not in the pool" in r.stderr


@pytest.mark.parametrize(
    ("level", "hint"),
    [(3, "if it is a simulator the study should have, add it to the levels list in settings.toml"),
     (-1, "levels count up from 0")],
)  # fmt: skip
def test_a_level_outside_the_study_gets_the_fix_that_fits_it(ws, runner, tmp_path, level, hint):
    for suffix in ("parquet", "csv"):
        res = _results(tmp_path / f"f.{suffix}", [(IDS[0], level, 1.0)])
        r = invoke(runner, "ingest-results", "-w", ws, res)
        assert r.exit_code == 1 and r.stderr.rstrip().endswith(hint), r.stderr
        assert f"fidelity {level} is not a configured level" in r.stderr


def test_a_command_holds_the_lock_from_first_read(ws, runner, tmp_path):
    from tests.state.test_lock import _hold

    res = _results(tmp_path / "r.parquet", [(IDS[0], 0, 1.5)])
    before = tree_hash(ws)
    proc = _hold(ws, 30)
    try:
        r = invoke(runner, "ingest-results", "-w", ws, res)
    finally:
        proc.kill()
        proc.wait()
    assert r.exit_code == 1 and f"locked by pid {proc.pid}" in r.stderr
    assert tree_hash(ws) == before
    assert invoke(runner, "ingest-results", "-w", ws, res, "--wait").exit_code == 0


@pytest.mark.parametrize(
    ("content", "needle"),
    [
        ("segment_id,fidelity,value\n", "has no rows; nothing to ingest"),
        (
            "segment_id,fidelity,value\nt000000,true,1.0\n",
            "column 'fidelity', row 1: expected a level number or name, got True of type bool",
        ),
        (
            "segment_id,fidelity,value\nt000000,0,abc\n",
            "column 'value', row 1: value must be a finite number",
        ),
        (
            "segment_id,fidelity,value,value\nt000000,0,1.0,2.0\n",
            "bad.csv: column 'value': column appears more than once in the header",
        ),
        (
            "segm\xffent_id,fidelity,value\nt000000,0,1.0\n",
            "bad.csv: the header is not valid UTF-8",
        ),
    ],
)
def test_malformed_csv_results(ws, runner, tmp_path, content, needle):
    res = tmp_path / "bad.csv"
    res.write_bytes(content.encode("latin-1"))
    before = tree_hash(ws)
    r = invoke(runner, "ingest-results", "-w", ws, res)
    assert r.exit_code == 1 and needle in r.stderr, r.stderr
    assert tree_hash(ws) == before


def test_same_values_from_another_file_change_nothing(ws, runner, tmp_path):
    assert (
        invoke(
            runner, "ingest-results", "-w", ws, _results(tmp_path / "a.parquet", [(IDS[0], 0, 1.5)])
        ).exit_code
        == 0
    )
    before = tree_hash(ws)
    r = invoke(runner, "ingest-results", "-w", ws, _results(tmp_path / "b.csv", [(IDS[0], 0, 1.5)]))
    assert r.exit_code == 0 and "already in the log; nothing changed" in r.stderr
    assert tree_hash(ws) == before


@pytest.mark.parametrize("value", [1e308, -1e200, 2e150])
def test_a_value_the_model_cannot_hold_is_refused_naming_its_row(ws, runner, tmp_path, value):
    """1e308 used to be ingested, and then every fit failed from all starts naming no row."""
    res = tmp_path / "r.csv"
    res.write_text(f"segment_id,fidelity,value\n{IDS[0]},0,1.5\n{IDS[1]},0,{value!r}\n")
    before = tree_hash(ws)
    r = invoke(runner, "ingest-results", "-w", ws, res)
    assert r.exit_code == 1 and len(r.stderr.strip().splitlines()) == 1
    assert "column 'value', row 2" in r.stderr and "beyond +-1e+150" in r.stderr
    assert tree_hash(ws) == before


@pytest.mark.parametrize(
    ("fidelity", "needle"),
    [
        ("1e20", "fidelity 1e+20 is not a configured level"),
        ("9223372036854775808", "is not a configured level"),  # 2^63: beyond Int64
        ("-3", "fidelity -3 is not a configured level"),
        ("nan", "fidelity must be an integer level or a level name"),
        ("inf", "fidelity must be an integer level or a level name, got inf"),
    ],
)
def test_a_fidelity_that_is_no_level_is_named_not_a_crash(ws, runner, tmp_path, fidelity, needle):
    res = tmp_path / "r.csv"
    res.write_text(f"segment_id,fidelity,value\n{IDS[0]},{fidelity},1.5\n")
    before = tree_hash(ws)
    r = invoke(runner, "ingest-results", "-w", ws, res)
    assert r.exit_code == 1 and len(r.stderr.strip().splitlines()) == 1
    assert "column 'fidelity', row 1" in r.stderr and needle in r.stderr
    assert "unexpected" not in r.stderr and tree_hash(ws) == before


def test_a_results_column_named_like_the_tools_own_is_refused(ws, runner, tmp_path):
    res = tmp_path / "r.csv"
    res.write_text(f"segment_id,fidelity,value,_row\n{IDS[0]},0,1.5,9\n")
    r = invoke(runner, "ingest-results", "-w", ws, res)
    assert r.exit_code == 1 and "column '_row': this column name is reserved" in r.stderr


def test_decimal_values_and_levels_are_read_as_the_numbers_they_hold(ws, runner, tmp_path):
    # A SQL export writes decimals; they were refused ("expected numbers, got decimal128").
    from decimal import Decimal

    res = tmp_path / "dec.parquet"
    table = pa.table(
        {
            "segment_id": [IDS[0], IDS[2]],
            "fidelity": pa.array([Decimal("0"), Decimal("1.0")], pa.decimal128(4, 1)),
            "value": pa.array([Decimal("1.25"), Decimal("-0.5")], pa.decimal128(10, 2)),
        }
    )
    pq.write_table(table, res)
    r = invoke(runner, "ingest-results", "-w", ws, res)
    assert r.exit_code == 0, r.output
    log = Workspace(ws).read_observations()
    assert log.select("segment_id", "fidelity", "value").rows() == [
        (IDS[0], 0, 1.25),
        (IDS[2], 1, -0.5),
    ]


def test_the_original_file_with_replace_undoes_a_replace(ws, runner, tmp_path):
    original = _results(tmp_path / "a.parquet", [(IDS[0], 0, 1.5), (IDS[1], 0, 0.3)])
    fix = _results(tmp_path / "b.parquet", [(IDS[0], 0, 9.0)])
    assert invoke(runner, "ingest-results", "-w", ws, original).exit_code == 0
    assert invoke(runner, "ingest-results", "-w", ws, fix, "--replace").exit_code == 0

    # Without --replace the original is a no-op, and says what --replace would bring back.
    before = tree_hash(ws)
    r = invoke(runner, "ingest-results", "-w", ws, original)
    assert r.exit_code == 0 and "already ingested" in r.stderr
    assert "1 of its values was replaced since: pass --replace to restore them" in r.stderr
    assert tree_hash(ws) == before

    r = invoke(runner, "ingest-results", "-w", ws, original, "--replace", "--json")
    assert r.exit_code == 0, r.output
    assert '"replaced": 1' in r.stdout and '"already_known": 1' in r.stdout
    full = Workspace(ws).read_observations(active_only=False)
    assert full.height == 4  # 1.5, 0.3, then 9.0, then 1.5 again: nothing is lost
    active = Workspace(ws).read_observations()
    assert dict(active.select("segment_id", "value").rows()) == {IDS[0]: 1.5, IDS[1]: 0.3}
    assert full.filter(full["value"] == 9.0)["active"].to_list() == [False]

    # Once restored, the original is a plain no-op again.
    r = invoke(runner, "ingest-results", "-w", ws, original, "--replace")
    assert r.exit_code == 0 and "already in the log; nothing changed" in r.stderr


# ---- a batch or plan partly answered: the list of its pending requests alone ----------------
def _status(runner, ws: Path) -> tuple[int, dict, str]:
    r = invoke(runner, "status", "-w", ws, "--json")
    return r.exit_code, json.loads(r.stdout), invoke(runner, "status", "-w", ws).stdout


CRASHED = ("b0001-0001", "b0001-0002", "b0001-0003")


@pytest.fixture
def crashed_study(tmp_path, runner):
    """A 400-segment toy2d study with a random level-0 batch of 10 whose first three runs
    crashed: the results file is returned, not yet ingested."""
    seg, truth = write_toy(tmp_path / "data", n=400, seed=5)
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.56", "--costs", "1,0.5", "--dim", "2", "--seed", "1")
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize")  # fmt: skip
    ok(runner, "select", "-w", ws, "--strategy", "random", "--budget", "10")
    handoff = ws / "batches" / "batch-0001.csv"
    res = answer_handoff(runner, handoff, truth, tmp_path / "r1.csv", CRASHED)
    return ws, truth, handoff, res


def test_the_pending_note_counts_the_abandoned_requests_apart(crashed_study, runner, tmp_path):
    # After abandoning part of a batch, the note said of the requests not pending: "the
    # others have results"; some had been abandoned without one.
    ws, _, _, res = crashed_study
    gone = tmp_path / "gone.csv"
    gone.write_text(f"request_id\n{CRASHED[0]}\n")
    ok(runner, "abandon", "-w", ws, "--segments", gone, "--reason", "simulator crash")
    r = ok(runner, "ingest-results", "-w", ws, res)
    assert "batch 1: 2 of its 10 requests still await results" in r.stdout
    assert "(of the others 7 have results, 1 was abandoned)" in " ".join(r.stdout.split())
    out = json.loads(ok(runner, "ingest-results", "-w", ws, res, "--json").stdout)
    assert [(e["pending"], e["abandoned"]) for e in out["pending_lists"]] == [(2, 1)]


def test_a_batch_partly_answered_is_simulated_from_its_pending_requests_alone(
    crashed_study, runner, tmp_path
):
    # A trial's crashed runs stayed pending, and status said to simulate the whole of
    # batches/batch-0001.csv again: a noisy simulator answered the 7 runs already logged
    # with other values, and ingest-results refused them as conflicts.
    ws, truth, handoff, res = crashed_study
    pending = ws / "batches" / "batch-0001.pending.csv"
    r = ok(runner, "ingest-results", "-w", ws, res)
    assert (
        f"batch 1: 3 of its 10 requests still await results; simulate {pending}, which "
        "lists them alone" in r.stdout
    )
    listed = list(csv.DictReader(pending.open()))
    assert [row["request_id"] for row in listed] == list(CRASHED)
    assert pending.read_text().splitlines()[0] == handoff.read_text().splitlines()[0]
    assert pending.read_text().splitlines()[1:] == handoff.read_text().splitlines()[1:4]
    again = json.loads(ok(runner, "ingest-results", "-w", ws, res, "--json").stdout)
    assert again["pending_lists"] == [
        {"list": "batch 1", "pending": 3, "requests": 10, "abandoned": 0,
         "handoff": str(handoff), "pending_handoff": str(pending)}
    ]  # fmt: skip
    assert "which lists them alone (the others have results)" in r.stdout

    code, s, text = _status(runner, ws)
    assert code == 3 and s["next"]["handoffs"] == [str(pending)]
    assert s["batches"][0]["pending_handoff"] == str(pending)
    says = f"simulate {pending} (the 3 of the 10 requests of batch-0001.csv without a result)"
    assert says in s["next"]["text"] and says in text.replace("\n", " ")
    # select's and estimate --plan's refusals name the same list (they named the whole one).
    r = invoke(runner, "select", "-w", ws, "--strategy", "random", "--budget", "2")
    assert r.exit_code == 3 and f"simulate {pending}, ingest the results" in r.stderr, r.stderr
    r = invoke(runner, "estimate", "-w", ws, *STAGED_PLAN)
    assert r.exit_code == 3 and f"simulate {pending}, ingest the results" in r.stderr, r.stderr
    ok(runner, "report", "-w", ws)
    notices = json.loads((ws / "report" / "summary.json").read_text())["notices"]
    [text] = [n["text"] for n in notices if n["kind"] == "pending_batches"]
    assert "batch 1 (3 of 10 picks, batches/batch-0001.pending.csv)" in text, text

    # The whole list from a noisy simulator is what the old advice led to ...
    whole = answer_handoff(runner, handoff, truth, tmp_path / "whole.csv", noise=0.01)
    before = tree_hash(ws)
    r = invoke(runner, "ingest-results", "-w", ws, whole)
    assert r.exit_code == 1 and "pass --replace" in r.stderr and tree_hash(ws) == before
    # ... the pending list alone goes in, and, the batch answered, goes away.
    rest = answer_handoff(runner, pending, truth, tmp_path / "rest.csv", noise=0.01)
    r = ok(runner, "ingest-results", "-w", ws, rest, "--json")
    assert json.loads(r.stdout)["ingested"] == 3 and json.loads(r.stdout)["pending_lists"] == []
    assert not pending.exists() and not list(ws.rglob(".tmp-*"))
    code, s, _ = _status(runner, ws)
    assert code == 0 and s["next"]["step"] == "fit" and s["batches"][0]["pending_handoff"] is None


def test_the_pending_list_follows_later_results_and_abandonment_and_a_stale_one_is_not_named(
    crashed_study, runner, tmp_path
):
    ws, _, handoff, res = crashed_study
    pending = ws / "batches" / "batch-0001.pending.csv"
    ok(runner, "ingest-results", "-w", ws, res)
    three = pending.read_text()

    def listed() -> list[str]:
        return [row["request_id"] for row in csv.DictReader(pending.open())]

    late = tmp_path / "late.csv"
    late.write_text("request_id,value\nb0001-0001,1.5\n")
    ok(runner, "ingest-results", "-w", ws, late)
    assert listed() == ["b0001-0002", "b0001-0003"]
    code, s, _ = _status(runner, ws)
    assert code == 3 and s["next"]["handoffs"] == [str(pending)]
    assert "the 2 of the 10 requests of batch-0001.csv" in s["next"]["text"]

    # A list that no longer holds exactly what is pending is never named.
    pending.write_text(three)
    code, s, _ = _status(runner, ws)
    assert s["next"]["handoffs"] == [str(handoff)] and s["batches"][0]["pending_handoff"] is None
    assert str(pending) not in s["next"]["text"]
    assert f"the 2 of the 10 requests of {handoff} without a result" in s["next"]["text"]

    lost = tmp_path / "lost.csv"
    lost.write_text("request_id\nb0001-0002\n")
    r = ok(runner, "abandon", "-w", ws, "--segments", lost)
    assert listed() == ["b0001-0003"] and f"simulate {pending}" in r.stdout
    code, s, _ = _status(runner, ws)
    assert s["next"]["handoffs"] == [str(pending)]
    ok(runner, "abandon", "-w", ws, "--batch", "1")
    assert not pending.exists()
    code, s, _ = _status(runner, ws)
    assert code == 0 and s["pending"] == 0


@pytest.mark.parametrize("first", ["ingested", "not yet"])
def test_abandoning_the_failed_rows_leaves_no_pending_list(crashed_study, runner, first):
    # --abandon-failed stages the list with the results, then again with the abandonment:
    # the second staging replaces the first in the one commit.
    ws, _, _, res = crashed_study
    if first == "ingested":
        ok(runner, "ingest-results", "-w", ws, res)
        assert (ws / "batches" / "batch-0001.pending.csv").exists()
    out = json.loads(ok(runner, "ingest-results", "-w", ws, res, "--abandon-failed",
                        "--json").stdout)  # fmt: skip
    assert out["abandoned"]["abandoned"] == 3 and out["pending_lists"] == []
    assert not (ws / "batches" / "batch-0001.pending.csv").exists()
    assert not list(ws.rglob(".tmp-*")) and not (ws / JOURNAL_NAME).exists()


def test_an_estimate_plan_partly_answered_is_named_by_status_and_estimate(
    crashed_study, runner, tmp_path
):
    ws, truth, handoff, _ = crashed_study
    ok(
        runner,
        "ingest-results",
        "-w",
        ws,
        answer_handoff(runner, handoff, truth, tmp_path / "r.csv"),
    )
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "40", "--stages", "1")
    plan = ws / "estimates" / "plan-0001-handoff.csv"
    rids = [row["request_id"] for row in csv.DictReader(plan.open())][:2]
    ok(
        runner,
        "ingest-results",
        "-w",
        ws,
        answer_handoff(runner, plan, truth, tmp_path / "p.csv", rids),
    )
    pending = ws / "estimates" / "plan-0001-handoff.pending.csv"
    assert [row["request_id"] for row in csv.DictReader(pending.open())] == rids
    code, s, _ = _status(runner, ws)
    assert code == 3 and s["next"]["handoffs"] == [str(pending)]
    assert s["plans"][0]["pending_handoff"] == str(pending)
    r = invoke(runner, "estimate", "-w", ws)
    assert r.exit_code == 3 and f"simulate {pending} and ingest" in r.stderr
    rest = answer_handoff(runner, pending, truth, tmp_path / "rest.csv", noise=0.01)
    ok(runner, "ingest-results", "-w", ws, rest)
    assert not pending.exists()
    ok(runner, "estimate", "-w", ws)


def test_the_by_level_counts_are_in_level_order(tmp_path, runner):
    # A trial's ingest printed "by level  level 1: 1, level 0: 2": the counts came in the
    # order of a hash grouping, which changes from run to run. Ten files of three levels
    # each: in level order every time.
    seg, _ = write_toy(tmp_path / "data", n=100, seed=2)
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.56", "--costs", "1,0.3,0.1", "--dim", "2")
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize")  # fmt: skip
    ids = [f"t{i:06d}" for i in range(30)]
    write_batch(ws, 1, ids * 3, [2] * 30 + [1] * 30 + [0] * 30)
    for k in range(10):
        part = ids[3 * k : 3 * k + 3]
        rows = [(sid, lv, 1.0 + lv) for lv in (2, 1, 0) for sid in part[: 3 - lv]]
        res = _results(tmp_path / f"r{k}.csv", rows)
        if k % 2:
            out = json.loads(ok(runner, "ingest-results", "-w", ws, res, "--json").stdout)
            assert list(out["by_fidelity"].items()) == [("0", 3), ("1", 2), ("2", 1)]
        else:
            r = ok(runner, "ingest-results", "-w", ws, res)
            by_level = "  by level  level 0 (high): 3, level 1 (low1): 2, level 2 (low2): 1"
            assert by_level in r.stdout.splitlines()


@pytest.mark.parametrize("damage", ["a pending row gone", "unparseable"])
def test_a_hand_edited_handoff_list_makes_no_pending_list_and_blocks_nothing(
    crashed_study, runner, tmp_path, damage
):
    # The pending-only list is cut from the hand-off CSV. One that lost a pending row made
    # a list that status named as all there was to simulate; one that no longer parsed
    # made ingest-results and status fail with a bare polars error. Now neither makes a
    # list: status names the hand-off list whole, and ingest goes on.
    ws, truth, handoff, res = crashed_study
    pending = ws / "batches" / "batch-0001.pending.csv"
    ok(runner, "ingest-results", "-w", ws, res)
    assert pending.exists()
    lines = handoff.read_text().splitlines(keepends=True)
    if damage == "a pending row gone":
        handoff.write_text("".join(lines[:1] + lines[2:]))  # b0001-0001, pending, gone
    else:
        handoff.write_text("".join(lines) + '"unterminated\n')
    one = answer_handoff(runner, pending, truth, tmp_path / "one.csv")
    rows = one.read_text().splitlines()
    one.write_text("\n".join(rows[:1] + rows[-1:]) + "\n")  # one more result: b0001-0003
    ok(runner, "ingest-results", "-w", ws, one)
    assert not pending.exists()
    code, s, _ = _status(runner, ws)
    assert code == 3 and s["next"]["handoffs"] == [str(handoff)]
    assert s["batches"][0]["pending_handoff"] is None
