"""Every bad input, one table: a one-line error naming what is wrong, and nothing changed.

Each case starts from a copy of one study (a reduced toy2d pool, a batch ingested and
fitted, an estimate computed, a second batch awaiting results), damages an input or a
state file, runs one command through the CLI and asserts:

* exit code 1, or 2 for an option out of range (a usage error, as click's own);
* stderr is exactly one line, ``error: <file>: [column 'c'[, row r]: ]<what>``, with the
  file, column and row of the case and its expected text;
* no traceback and no ``(unexpected`` catch-all text (kept for true bugs);
* every file of the workspace byte-for-byte as before (``tree_hash``).
"""

from __future__ import annotations

import json
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from bams_cli.errors import shown
from bams_cli.state.workspace import Workspace
from tests.conftest import (
    STAGED_PLAN,
    invoke,
    ok,
    simulate_and_ingest,
    tree_hash,
    write_batch,
    write_toy,
)

#: Picks of batch 2, awaiting results in every case's workspace: results for them are new.
PENDING = ["t000100", "t000101", "t000102", "t000103"]
PENDING_LEVELS = [0, 0, 1, 1]


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    """The study every case copies; built once through the CLI."""
    runner = CliRunner()
    tmp = tmp_path_factory.mktemp("bad-input")
    seg, truth = write_toy(tmp / "data")
    ws = tmp / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.56", "--costs", "1,0.1", "--dim", "2")
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize")  # fmt: skip
    ids = [f"t{i:06d}" for i in range(0, 400, 20)]
    write_batch(ws, 1, ids, [0] * 8 + [1] * 12)
    simulate_and_ingest(
        runner, ws, ws / "batches" / "batch-0001.parquet", truth, tmp / "r1.parquet"
    )
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "4")
    plan = ws / "estimates" / "plan-0001-handoff.csv"
    simulate_and_ingest(runner, ws, plan, truth, tmp / "r-plan.parquet")
    ok(runner, "estimate", "-w", ws)
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    write_batch(ws, 2, PENDING, PENDING_LEVELS)
    return ws


@dataclass
class Case:
    """One bad input: ``setup(ws, tmp)`` damages the study or writes an input file and
    returns the command's arguments; the error must read ``<file>: column 'c', row r:
    <text>`` with ``file`` relative to the workspace (``@`` prefix: to tmp)."""

    id: str
    setup: Callable[[Path, Path], list[object]]
    file: str
    text: str
    column: str | None = None
    row: int | None = None
    fix: str | None = None
    marks: list = field(default_factory=list)
    code: int = 1

    def where(self, ws: Path, tmp: Path) -> str:
        if not self.file:  # an option: the message starts with the flag
            return ""
        path = tmp / self.file[1:] if self.file.startswith("@") else ws / self.file
        out = str(path)
        if self.column is not None:
            out += f": column {shown(self.column)}"
        if self.row is not None:
            out += f", row {self.row}" if self.column is not None else f": row {self.row}"
        return out


# ---- estimate files read by report and status ------------------------------------------
EST = "estimates/estimate-0001.json"


def _edit_estimate(edit: Callable[[dict], object]) -> Callable[[Path, Path], list[object]]:
    def setup(ws: Path, tmp: Path) -> list[object]:
        path = ws / EST
        doc = json.loads(path.read_text())
        edit(doc)
        path.write_text(json.dumps(doc))
        return ["report", "-w", ws]

    return setup


def _write_estimate(text: str, command: str = "report") -> Callable[[Path, Path], list[object]]:
    def setup(ws: Path, tmp: Path) -> list[object]:
        (ws / EST).write_text(text)
        return [command, "-w", ws]

    return setup


def _row0(key: str, value: object) -> Callable[[dict], object]:
    return lambda doc: doc["estimates"][0].__setitem__(key, value)


REWRITE = "run `bams-cli estimate -w {ws} --plan-number 1` to write it again"

ESTIMATE_CASES = [
    Case("estimate-not-json", _write_estimate("{not json"), EST, "damaged, not valid JSON"),
    Case("estimate-empty", _write_estimate(""), EST, "damaged, not valid JSON"),
    Case("estimate-control-bytes", _write_estimate("\x00\x01"), EST, "damaged, not valid JSON"),
    Case("estimate-a-list", _write_estimate("[1, 2]"), EST, "expected a JSON object, got [1, 2]"),
    Case("estimate-status", _write_estimate("[1, 2]", "status"), EST, "expected a JSON object"),
    Case("estimate-no-rows", _edit_estimate(lambda d: d.pop("estimates")), EST,
         "key 'estimates': expected a non-empty list of objects, got nothing"),
    Case("estimate-rows-empty", _edit_estimate(lambda d: d.update(estimates=[])), EST,
         "key 'estimates': expected a non-empty list of objects, got []"),
    Case("estimate-row-a-number", _edit_estimate(lambda d: d.update(estimates=[3])), EST,
         "key estimates[0]: expected an object, got 3"),
    Case("estimate-p-hat-missing", _edit_estimate(lambda d: d["estimates"][0].pop("p_hat")), EST,
         "key estimates[0].p_hat: missing (expected a number)"),
    Case("estimate-p-hat-text", _edit_estimate(_row0("p_hat", "abc")), EST,
         'key estimates[0].p_hat: expected a number, got "abc"'),
    Case("estimate-p-hat-nan", _write_estimate('{"estimates": [{"gamma": 0.56, "p_hat": NaN}]}'),
         EST, "key estimates[0].p_hat: expected a number, got nan"),
    Case("estimate-ci-bool", _edit_estimate(_row0("ci_low", True)), EST,
         "key estimates[0].ci_low: expected a number, got true"),
    Case("estimate-count-negative", _edit_estimate(_row0("distinct_failures_found", -1)), EST,
         "key estimates[0].distinct_failures_found: expected a count, got -1"),
    Case("estimate-count-float", _edit_estimate(_row0("n_sampled", 2.5)), EST,
         "key estimates[0].n_sampled: expected a count, got 2.5"),
    Case("estimate-note-number", _edit_estimate(_row0("variance_note", 7)), EST,
         "key estimates[0].variance_note: expected a text or null, got 7"),
    Case("estimate-gp-missing", _edit_estimate(lambda d: d.pop("gp")), EST,
         "key 'gp': expected a non-empty list of objects, got nothing"),
    Case("estimate-gp-text", _edit_estimate(lambda d: d["gp"][0].update(gp_p_hat="x" * 500)), EST,
         'key gp[0].gp_p_hat: expected a number, got "' + "x" * 36 + "..."),
]  # fmt: skip


for _case in ESTIMATE_CASES:
    _case.fix = REWRITE


# ---- ingest-results ------------------------------------------------------------------------
def _parquet(cols: dict, *args: object, name: str = "r.parquet"):
    def setup(ws: Path, tmp: Path) -> list[object]:
        pq.write_table(pa.table(cols), tmp / name)
        return ["ingest-results", "-w", ws, tmp / name, *args]

    return setup


def _csv(text: str | bytes, *args: object, name: str = "r.csv"):
    def setup(ws: Path, tmp: Path) -> list[object]:
        data = text.encode() if isinstance(text, str) else text
        (tmp / name).write_bytes(data)
        return ["ingest-results", "-w", ws, tmp / name, *args]

    return setup


def _rows(*rows: tuple, **extra: list) -> dict:
    """Results columns from (segment_id, fidelity, value) rows, plus extra columns."""
    cols = {"segment_id": [r[0] for r in rows], "fidelity": [r[1] for r in rows],
            "value": [r[2] for r in rows]}  # fmt: skip
    return {**cols, **extra}


P0, P1, P2, P3 = PENDING
GOOD = (P0, 0, 1.0)
HEADER = "segment_id,fidelity,value\n"
LONG = "x" * 100_000
R, RC = "@r.parquet", "@r.csv"

INGEST_CASES = [
    Case("results-id-list", _parquet({**_rows(GOOD, GOOD), "segment_id": [[P0], [P1]]}), R,
         "segment id ['t000100'] is of type list<element: string>; expected text or an integer",
         column="segment_id", row=1),
    Case("results-id-struct", _parquet({**_rows(GOOD), "segment_id": [{"id": P0}]}), R,
         "segment id {'id': 't000100'} is of type struct<id: string>", column="segment_id", row=1),
    Case("results-id-binary", _parquet({**_rows(GOOD), "segment_id": pa.array([b"t"], pa.binary())}),
         R, "segment id b't' is of type binary", column="segment_id", row=1),
    Case("results-id-float", _parquet({**_rows(GOOD, GOOD), "segment_id": [None, 1.5]}), R,
         "segment id 1.5 is of type double", column="segment_id", row=2),
    Case("results-id-map", _parquet({**_rows(GOOD), "segment_id": pa.array([[("a", 1)]], pa.map_(pa.string(), pa.int64()))}),
         R, "is of type map<string, int64", column="segment_id", row=1),
    Case("results-request-id-list", _parquet({**_rows(GOOD), "request_id": [["b0002-0001"]]}), R,
         "request id ['b0002-0001'] is of type list", column="request_id", row=1),
    Case("results-status-list", _parquet({**_rows(GOOD), "status": [["ok"]]}), R,
         "status ['ok'] is of type list<element: string>; expected text such as ok or crashed",
         column="status", row=1),
    Case("results-value-list", _parquet({**_rows(GOOD), "value": [[1.0]]}), R,
         "expected a number, got [1.0] of type list<element: double>", column="value", row=1),
    Case("results-fidelity-struct", _parquet({**_rows(GOOD), "fidelity": [{"level": 0}]}), R,
         "expected a level number or name, got {'level': 0} of type struct", column="fidelity", row=1),
    Case("results-value-nan", _parquet(_rows(GOOD, (P1, 0, float("nan")))), R,
         "value must be a finite number, got nan", column="value", row=2),
    Case("results-value-inf", _parquet(_rows((P0, 0, float("-inf")))), R,
         "value must be a finite number, got -inf", column="value", row=1),
    Case("results-value-huge", _parquet(_rows(GOOD, (P1, 0, 1e308))), R,
         "value 1e+308 is beyond +-1e+150", column="value", row=2),
    Case("results-value-text", _csv(HEADER + f"{P0},0,abc\n"), RC,
         "value must be a finite number, got 'abc'", column="value", row=1),
    # A CSV's "nan" or "NA" is what it says, not an empty field (pyarrow's default reads
    # them as missing, and the message said "got nothing").
    Case("results-value-nan-csv", _csv(HEADER + f"{P0},0,1\n{P1},0,nan\n"), RC,
         "value must be a finite number, got nan; fill it in, or say why there is none in the "
         "status column", column="value", row=2),
    Case("results-value-na-csv", _csv(HEADER + f"{P0},0,NA\n"), RC,
         "value must be a finite number, got 'NA'", column="value", row=1),
    Case("results-value-empty", _csv(HEADER + f"{P0},0,1\n{P1},0,\n"), RC,
         "value must be a finite number, got nothing; fill it in, or say why there is none in the "
         "status column", column="value", row=2),
    Case("results-fidelity-1e20", _csv(HEADER + f"{P0},1e20,1\n"), RC,
         "fidelity 1e+20 is not a configured level", column="fidelity", row=1),
    Case("results-fidelity-negative", _csv(HEADER + f"{P0},0,1\n{P1},-3,1\n"), RC,
         "fidelity -3 is not a configured level (known levels: 0 = 'high', 1 = 'low1')",
         column="fidelity", row=2),
    Case("results-fidelity-2^63", _csv(HEADER + f"{P0},9223372036854775808,1\n"), RC,
         "is not a configured level", column="fidelity", row=1),
    Case("results-fidelity-name", _csv(HEADER + f"{P0},ultra,1\n"), RC,
         "fidelity must be an integer level or a level name, got 'ultra'; known levels: "
         "0 = 'high', 1 = 'low1'", column="fidelity", row=1),
    Case("results-fidelity-name-case", _csv(HEADER + f"{P0},0,1\n{P1},LOW1,1\n"), RC,
         "got 'LOW1'; known levels: 0 = 'high', 1 = 'low1' (names are exact: 'low1')",
         column="fidelity", row=2),
    Case("results-id-spaced-value", _csv(HEADER + f"{P0},0,1\n {P1} ,1,1\n"), RC,
         f"segment id ' {P1} ' is not in the pool (1 unknown in all); the pool has '{P1}' "
         "(ids are exact: write them as in the hand-off list)", column="segment_id", row=2),
    Case("results-fidelity-half", _parquet(_rows((P0, 0.5, 1.0))), R,
         "fidelity must be an integer level or a level name, got 0.5", column="fidelity", row=1),
    Case("results-duplicate-pair", _parquet(_rows(GOOD, (P1, 0, 1.0), GOOD)), R,
         "('t000100', fidelity 0) appears again (first at row 1)", column="segment_id", row=3),
    Case("results-unknown-segment", _parquet(_rows(GOOD, ("nope", 0, 1.0))), R,
         "segment id 'nope' is not in the pool (1 unknown in all)", column="segment_id", row=2),
    Case("results-unselected", _parquet(_rows(("t000399", 0, 1.0))), R,
         "1 (segment_id, fidelity) pairs were never selected (t000399); pass --allow-unselected",
         column="segment_id", row=1),
    Case("results-conflict", _parquet(_rows(("t000000", 0, 123.0))), R,
         "('t000000', fidelity 0) is already known as", column="value", row=1),
    Case("results-missing-id", _parquet({**_rows(GOOD, GOOD), "segment_id": [P0, None]}), R,
         "segment id is missing (give the row's request_id, or its segment_id and fidelity)",
         column="segment_id", row=2),
    Case("results-no-value-column", _parquet({"segment_id": [P0], "fidelity": [0]}), R,
         "missing required column(s) 'value'", column="value"),
    Case("results-no-fidelity-column", _parquet({"segment_id": [P0], "value": [1.0]}), R,
         "missing required column(s) 'fidelity'; key each result by request_id",
         column="fidelity"),
    # A column the file spells another way is named, with the rename that fixes it.
    Case("results-value-capitalised", _csv(f"segment_id,fidelity,Value\n{P0},0,1\n"), RC,
         "found 'segment_id', 'fidelity', 'Value'; rename 'Value' to 'value' (column names "
         "are exact)", column="value"),
    Case("results-id-spaced", _csv(f"segment id,fidelity,value\n{P0},0,1\n"), RC,
         "key each result by request_id (from the hand-off list), or by segment_id and "
         "fidelity; rename 'segment id' to 'segment_id' (column names are exact)",
         column="segment_id"),
    Case("results-header-only", _csv(HEADER), RC, "has no rows; nothing to ingest"),
    Case("results-zero-bytes", _csv(b""), RC, "cannot read as CSV (Empty CSV file"),
    Case("results-junk-parquet", _csv(b"PAR1 junk", name="r.parquet"),
         R, "cannot read as Parquet"),
    Case("results-not-found", lambda ws, tmp: ["ingest-results", "-w", ws, tmp / "nowhere.csv"],
         "@nowhere.csv", "results file not found"),
    Case("results-a-directory", lambda ws, tmp: ["ingest-results", "-w", ws, tmp],
         "@", "is a folder; give the results file itself"),
    Case("results-header-twice", _csv("segment_id,fidelity,value,value\nt000100,0,1,2\n"), RC,
         "column appears more than once in the header", column="value"),
    Case("results-header-not-utf8", _csv(b"segm\xffent_id,fidelity,value\nt000100,0,1\n"), RC,
         "the header is not valid UTF-8 text"),
    Case("results-row-column", _csv("segment_id,fidelity,value,_row\nt000100,0,1,9\n"), RC,
         "this column name is reserved by bams-cli; rename it", column="_row"),
    Case("results-ragged-long", _csv(HEADER + f"{P0},0,1\n{P1},0,2.0,7\n"), RC,
         "has 4 fields, the header 3 ('t000101,0,2.0,7'); quote fields that hold commas", row=2),
    Case("results-ragged-short", _csv(HEADER + f"{P0},0\n"), RC,
         "has 2 fields, the header 3 ('t000100,0'); give every column a field", row=1),
    Case("results-ragged-quoted", _csv(HEADER + f'"{P0}",0,1\n"a,b",0\n'), RC,
         "has 2 fields, the header 3", row=2),
    Case("results-long-id", _parquet(_rows((LONG, 0, 1.0))), R,
         "segment id 'xxxxxxxx", column="segment_id", row=1),
    Case("results-long-column-twice", _csv(f"segment_id,fidelity,value,{LONG},{LONG}\n"), RC,
         "column appears more than once in the header", column=LONG),
    Case("results-long-fidelity", _csv(HEADER + f"{P0},{LONG},1\n"), RC,
         "fidelity must be an integer level or a level name, got 'xxxx", column="fidelity", row=1),
    Case("results-unknown-request", _csv("request_id,value\nb0002-0001,1\nb0009-0001,2\n"), RC,
         "request_id 'b0009-0001' is not in any hand-off list", column="request_id", row=2),
    Case("results-request-twice", _csv("request_id,value\nb0002-0001,1\nb0002-0001,2\n"), RC,
         "request_id 'b0002-0001' appears again (first at row 1)", column="request_id", row=2),
    Case("results-request-other-segment",
         _csv("request_id,segment_id,value\nb0002-0001,t000101,1\n"), RC,
         "request_id 'b0002-0001' is segment 't000100', but this row names 't000101'",
         column="segment_id", row=1),
    Case("results-request-other-level",
         _csv("request_id,fidelity,value\nb0002-0001,1,1\n"), RC,
         "request_id 'b0002-0001' asks for fidelity 0, but this row gives", column="fidelity", row=1),
]  # fmt: skip


# ---- embed-reduce ----------------------------------------------------------------------------
S = "@seg.parquet"
IDENTITY = ("--method", "identity", "--no-standardize", "--force")


def _segments(cols: dict, *args: object):
    def setup(ws: Path, tmp: Path) -> list[object]:
        pq.write_table(pa.table(cols), tmp / "seg.parquet")
        return ["embed-reduce", "-w", ws, tmp / "seg.parquet", *args]

    return setup


def _xy(n: int = 3, **over: list) -> dict:
    cols = {"segment_id": [f"s{i}" for i in range(n)], "x0": [float(i) for i in range(n)],
            "x1": [1.0 - i for i in range(n)]}  # fmt: skip
    return {**cols, **over}


COLS = ("--columns", "x*", *IDENTITY)

EMBED_CASES = [
    Case("segments-id-list", _segments(_xy(segment_id=[["a"], ["b"], ["c"]]), *COLS), S,
         "segment id ['a'] is of type list<element: string>; expected text or an integer",
         column="segment_id", row=1),
    Case("segments-id-struct", _segments(_xy(segment_id=[None, {"k": 1}, {"k": 2}]), *COLS), S,
         "segment id {'k': 1} is of type struct<k: int64>", column="segment_id", row=2),
    Case("segments-id-float", _segments(_xy(segment_id=[1.0, 2.0, 3.0]), *COLS), S,
         "segment id 1.0 is of type double", column="segment_id", row=1),
    Case("segments-id-binary", _segments(_xy(segment_id=[b"a", b"b", b"c"]), *COLS), S,
         "segment id b'a' is of type binary", column="segment_id", row=1),
    Case("segments-id-duplicate", _segments(_xy(segment_id=["a", "b", "a"]), *COLS), S,
         "segment id 'a' appears again (first at row 1)", column="segment_id", row=3),
    Case("segments-id-column-spelled-otherwise",
         _segments({"Segment ID": ["a", "b"], "x0": [0.0, 1.0]}, *COLS), S,
         "no id column 'segment_id'; found Segment ID, x0 (choose it with --id-column, e.g. "
         "--id-column 'Segment ID')", column="segment_id"),
    Case("segments-id-null", _segments(_xy(segment_id=["a", None, "c"]), *COLS), S,
         "segment id is missing", column="segment_id", row=2),
    Case("segments-id-long-duplicate", _segments(_xy(segment_id=[LONG, "b", LONG]), *COLS), S,
         "segment id 'xxxxxxxx", column="segment_id", row=3),
    Case("segments-nan", _segments(_xy(x1=[1.0, float("nan"), 0.0]), *COLS), S,
         "non-finite or missing value", column="x1", row=2),
    Case("segments-huge", _segments(_xy(x0=[1.0, 2.0, 1e308]), *COLS), S,
         "embedding value 1e+308 is beyond +-1e+100", column="x0", row=3),
    Case("segments-text-column", _segments(_xy(x1=["a", "b", "c"]), *COLS), S,
         "embedding column has non-numeric type string", column="x1"),
    Case("segments-list-of-text", _segments({"segment_id": ["a", "b"], "emb": [["1", "2"], ["0", "abc"]]},
         *IDENTITY), S, "embedding column holds lists of string, not numbers", column="emb"),
    Case("segments-list-of-bool", _segments({"segment_id": ["a", "b"], "emb": [[True, False], [False, True]]},
         "--embedding-column", "emb", *IDENTITY), S, "embedding column holds lists of bool, not numbers",
         column="emb"),
    Case("segments-list-nan", _segments({"segment_id": ["a", "b"], "emb": [[1.0, float("nan")], [0.0, 1.0]]},
         *IDENTITY), S, "embedding holds a non-finite value", column="emb", row=1),
    Case("segments-list-ragged", _segments({"segment_id": ["a", "b"], "emb": [[1.0, 2.0], [1.0]]},
         *IDENTITY), S, "embedding has 1 values, expected 2", column="emb", row=2),
    Case("segments-list-empty", _segments({"segment_id": ["a", "b"], "emb": [[], []]}, *IDENTITY),
         S, "embedding is empty (0 values)", column="emb", row=1),
    Case("segments-list-null", _segments({"segment_id": ["a", "b"], "emb": [[1.0, 2.0], None]},
         *IDENTITY), S, "embedding is null", column="emb", row=2),
    Case("segments-no-id-column", _segments({"id": ["a"], "x0": [1.0]}, *COLS), S,
         "no id column 'segment_id'; found id, x0 (choose it with --id-column)", column="segment_id"),
    Case("segments-columns-match-nothing", _segments(_xy(), "--columns", "e*", *IDENTITY), S,
         "--columns 'e*' matches no column", column="e*"),
    Case("segments-no-embedding", _segments(_xy(), *IDENTITY), S,
         "cannot tell which column holds the embedding"),
    Case("segments-reserved-name", _segments(_xy(z0=[1, 2, 3]), *COLS), S,
         "column name is reserved for reduced coordinates", column="z0"),
    Case("segments-no-rows", _segments({"segment_id": pa.array([], pa.string()),
         "x0": pa.array([], pa.float64())}, *COLS), S, "has no rows"),
    Case("segments-junk", lambda ws, tmp: (tmp / "seg.parquet").write_bytes(b"junk") and
         ["embed-reduce", "-w", ws, tmp / "seg.parquet", *COLS], S, "cannot read as Parquet"),
    Case("segments-not-found", lambda ws, tmp: ["embed-reduce", "-w", ws, tmp / "seg.parquet"],
         S, "segments file not found"),
    Case("segments-a-directory", lambda ws, tmp: ["embed-reduce", "-w", ws, tmp, *COLS], "@",
         "is a folder; give the segments file itself"),
    Case("segments-apply-in-pool", _segments(_xy(segment_id=["n1", "t000005", "n2"]), "--apply"),
         S, "segment id 't000005' is already in the pool", column="segment_id", row=2),
    Case("segments-apply-missing-column", _segments({"segment_id": ["n1"], "x0": [1.0]}, "--apply"),
         S, "embedding column the reducer was fitted on is missing", column="x1"),
]  # fmt: skip


# ---- state files and other inputs ----------------------------------------------------------
def _edit_file(rel: str, data: bytes, *command: str):
    def setup(ws: Path, tmp: Path) -> list[object]:
        (ws / rel).write_bytes(data)
        return [*command[:1], "-w", ws, *command[1:]]

    return setup


def _edit_settings(pattern: str, replacement: str, *command: str):
    """A hand edit of settings.toml: the first match of ``pattern`` replaced."""

    def setup(ws: Path, tmp: Path) -> list[object]:
        text = (ws / "settings.toml").read_text()
        edited = re.sub(pattern, replacement, text, count=1, flags=re.M)
        assert edited != text, pattern
        (ws / "settings.toml").write_text(edited)
        return [*command[:1], "-w", ws, *command[1:]]

    return setup


def _edit_model(edit: Callable[[dict], object], *command: str):
    def setup(ws: Path, tmp: Path) -> list[object]:
        doc = json.loads((ws / "model.json").read_text())
        edit(doc["hyperparameters"])
        (ws / "model.json").write_text(json.dumps(doc))
        return [*command[:1], "-w", ws, *command[1:]]

    return setup


def _fixed(edit: Callable[[dict], object]):
    def setup(ws: Path, tmp: Path) -> list[object]:
        doc = json.loads((ws / "model.json").read_text())
        edit(doc["hyperparameters"])
        (tmp / "hp.json").write_text(json.dumps(doc))
        return ["fit", "-w", ws, "--fixed-hyperparameters", tmp / "hp.json"]

    return setup


def _truth(cols: dict | None):
    def setup(ws: Path, tmp: Path) -> list[object]:
        path = tmp / "truth.parquet"
        if cols is None:
            path.write_bytes(b"not parquet")
        else:
            pq.write_table(pa.table(cols), path)
        return ["report", "-w", ws, "--truth", path]

    return setup


def _damaged_reducer(ws: Path, tmp: Path) -> list[object]:
    (ws / "reducer.npz").write_bytes(b"junk")
    return _segments(_xy(), "--apply")(ws, tmp)


SELECT = ("select", "--budget", "2", "--clusters", "2", "--allow-pending", "--workers", "1")


def _nan_at(key: str):
    def edit(hp: dict) -> None:
        hp[key] = [float("nan"), *hp[key][1:]]

    return edit


# A hand-edited model.json is refused by every command that reads the model, not only by
# select: estimate --plan drew a plan from a NaN lengthscale, and report reached the
# catch-all (a NaN outputscale even made --screen auto decide there was no cheap level).
MODEL_EDITS = {
    "nan-lengthscale": (_nan_at("lengthscales0"), "lengthscales0 must be finite and > 0, got [nan, "),
    "nan-outputscale": (_nan_at("outputscales"), "outputscales must be finite and > 0, got [nan]"),
    "negative-noise": (lambda hp: hp.update(noise=[-1.0, *hp["noise"][1:]]),
                       "noise must be finite and >= 0, got [-1, "),
    "mean-text": (lambda hp: hp.update(mean="abc"), "could not convert string to float: 'abc'"),
    "mean-huge-integer": (lambda hp: hp.update(mean=10**400), "int too large to convert to float"),
    "lengthscales-for-another-d": (
        lambda hp: hp.update(lengthscales0=[1.0, 1.0, 1.0],
                             lengthscales=[[1.0, 1.0, 1.0] for _ in hp["outputscales"]]),
        "they are for d = 3, the pool has d = 2"),
}  # fmt: skip
MODEL_READERS = {
    "estimate-plan": ("estimate", *STAGED_PLAN, "--allow-pending"),
    "estimate-screen": ("estimate", "--plan", "--screen", "0.3", "--allow-pending"),
    "select": SELECT,
}
MODEL_CASES = [
    Case(f"model-{edit}-{reader}", _edit_model(change, *command), "model.json",
         f"damaged hyperparameters ({text}", fix="run `bams-cli fit -w {ws}` to write it again")
    for edit, (change, text) in MODEL_EDITS.items()
    for reader, command in MODEL_READERS.items()
]  # fmt: skip

STATE_CASES = [
    Case("settings-study-a-number", _edit_file("settings.toml", b"study = 5\n", "fit"),
         "settings.toml", "'study' must be a [study] table, got int 5"),
    Case("settings-not-toml", _edit_file("settings.toml", b"[study\n", "report"),
         "settings.toml", "not valid TOML"),
    # A typo or a stray type would be ignored: the study would run with the default seed.
    Case("settings-misspelt-seed", _edit_settings(r"^seed = ", "sedd = ", "fit"),
         "settings.toml", "unknown key 'sedd' in [study]; did you mean 'seed'?"),
    Case("settings-seed-not-whole", _edit_settings(r"^seed = .*$", "seed = 7.5", "status"),
         "settings.toml", "seed must be a whole number, got 7.5"),
    Case("settings-level-key-misspelt", _edit_settings(r"cost = 0", "costt = 0", "fit"),
         "settings.toml", "unknown key 'costt' in levels entry 1; did you mean 'cost'?"),
    # A value of the wrong type was "malformed entry (could not convert string to float:
    # 'cheap')", naming no key.
    Case("settings-level-cost-a-word", _edit_settings(r"cost = 0\.[0-9]+", 'cost = "cheap"',
                                                      "status"),
         "settings.toml", "levels entry 1 ('low1'): cost must be a number, got 'cheap'"),
    Case("settings-level-without-cost", _edit_settings(r", cost = 0\.[0-9]+", "", "fit"),
         "settings.toml", "levels entry 1 has no 'cost'"),
    Case("settings-gamma-a-word", _edit_settings(r"^gammas = \[\n\s*[0-9.]+,", 'gammas = ["x",',
                                                 "fit"),
         "settings.toml", "gammas must be a list of numbers, got ['x']"),
    Case("settings-id-column-a-number", _edit_settings(r'^id_column = .*$', "id_column = 3",
                                                       "status"),
         "settings.toml", "id_column must be a column name, got 3"),
    # Results that name their level by a name two levels share would land at the wrong one.
    # A level deleted by hand while the log holds its results: fit names both files.
    Case("settings-level-removed", _edit_settings(r'^\s*\{ name = "[^"]*", cost = 0\..*\n', "", "fit"),
         "observations.parquet", "settings.toml declares 1 level(s); restore the levels"),
    Case("settings-level-names-repeated",
         _edit_settings(r'(name = )"[^"]*"(.*\n.*name = )"[^"]*"', r'\1"x"\2"x"', "fit"),
         "settings.toml", "level name 'x' is given to more than one level"),
    Case("model-not-json", _edit_file("model.json", b"{oops", *SELECT), "model.json",
         "damaged (not a model written by fit)"),
    Case("model-mean-1e308", _edit_model(lambda hp: hp.update(mean=1e308), *SELECT), "model.json",
         "mean must be finite and within +-1e+150"),
    Case("model-negative-lengthscale",
         _edit_model(lambda hp: hp.update(lengthscales0=[-1.0, -1.0]), *SELECT), "model.json",
         "lengthscales0 must be finite and > 0"),
    Case("fixed-hyperparameters-mean-1e308", _fixed(lambda hp: hp.update(mean=1e308)), "@hp.json",
         "mean must be finite and within +-1e+150"),
    Case("fixed-hyperparameters-missing-key", _fixed(lambda hp: hp.pop("noise")), "@hp.json",
         "not a hyperparameter file"),
    Case("segments-state-damaged", _edit_file("segments.parquet", b"PAR1", "fit"),
         "segments.parquet", "damaged state file, not readable as Parquet"),
    Case("observations-state-damaged",
         _edit_file("observations.parquet", b"junk", "fit"),
         "observations.parquet", "damaged state file, not readable as Parquet"),
    Case("reducer-damaged", _damaged_reducer, "reducer.npz", "damaged state file"),
    Case("truth-junk", _truth(None), "@truth.parquet", "cannot read as Parquet"),
    Case("truth-no-value-column", _truth({"segment_id": ["t000000"]}), "@truth.parquet",
         "missing required column(s) 'value_0'", column="value_0"),
]  # fmt: skip


# ---- options: no file to name, the flag instead ----------------------------------------------
def _options(*args: object):
    return lambda ws, tmp: [args[0], "-w", ws, *args[1:]]


PLAN = ("estimate", *STAGED_PLAN, "--allow-pending")
#: Checked before the loop takes a step: the pending batch 2 would be simulated first.
LOOP = ("loop", "--simulator", "true {handoff} {results}", "--batches", "3")
BUDGET = "must be a finite number > 0 (cost units; one level-0 run costs 1)"

OPTION_CASES = [
    Case("workers-negative", _options(*SELECT, "--workers", "-3"), "",
         "--workers -3: must be >= 1", code=2),
    Case("workers-zero", _options(*SELECT, "--workers", "0"), "", "--workers 0: must be >= 1",
         code=2),
    Case("budget-negative", _options("select", "--budget", "-5", "--allow-pending"), "",
         f"--budget -5: {BUDGET}", code=2),
    Case("budget-zero", _options("select", "--budget", "0", "--allow-pending"), "",
         f"--budget 0: {BUDGET}", code=2),
    Case("budget-nan", _options("select", "--budget", "nan", "--allow-pending"), "",
         f"--budget nan: {BUDGET}", code=2),
    Case("clusters-zero", _options("select", "--clusters", "0", "--allow-pending"), "",
         "--clusters 0: must be >= 1", code=2),
    Case("overbudget-inf", _options("select", "--overbudget", "inf", "--allow-pending"), "",
         "--overbudget inf: must be a finite number >= 1", code=2),
    Case("level0-share-nan", _options("select", "--level0-share", "nan", "--allow-pending"), "",
         "--level0-share nan: must lie in [0, 1]", code=2),
    Case("samples-zero", _options(*PLAN, "--samples", "0"), "",
         "--samples 0: must be a finite number >= 1 (simulations to plan)", code=2),
    Case("samples-inf", _options(*PLAN, "--samples", "inf"), "", "--samples inf: must be a finite",
         code=2),
    Case("defensive-nan", _options(*PLAN, "--defensive", "nan"), "",
         "--defensive nan: must lie in [0, 1]", code=2),
    Case("alpha-negative", _options(*PLAN, "--alpha", "-1"), "",
         "--alpha -1: must be a finite number >= 0", code=2),
    Case("stage1-share-one", _options(*PLAN, "--stage1-share", "1"), "",
         "--stage1-share 1: must lie in (0, 1)", code=2),
    Case("plan-seed-negative", _options(*PLAN, "--seed", "-1"), "",
         "--seed -1: must be an integer >= 0", code=2),
    Case("confidence-nan", _options("estimate", "--confidence", "nan"), "",
         "--confidence nan: must lie in (0, 1)", code=2),
    Case("loop-budget-negative", _options(*LOOP, "--budget", "-5"), "", f"--budget -5: {BUDGET}",
         code=2),
    Case("loop-first-budget-zero", _options(*LOOP, "--first-budget", "0"), "",
         f"--first-budget 0: {BUDGET}", code=2),
    Case("loop-samples-negative", _options(*LOOP, "--then-estimate", "--samples", "-1"), "",
         "--samples -1: must be a finite number >= 1", code=2),
    Case("loop-clusters-zero", _options(*LOOP, "--clusters", "0"), "",
         "--clusters 0: must be >= 1", code=2),
    Case("loop-batches-zero", _options("loop", "--simulator", "true {handoff} {results}",
         "--batches", "0"), "", "--batches 0: must be >= 1", code=2),
]  # fmt: skip

CASES = [*ESTIMATE_CASES, *INGEST_CASES, *EMBED_CASES, *STATE_CASES, *MODEL_CASES, *OPTION_CASES]


def test_the_table_is_large_and_its_ids_unique():
    assert len(CASES) >= 60
    assert len({c.id for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", [pytest.param(c, id=c.id, marks=c.marks) for c in CASES])
def test_bad_input_is_one_line_naming_it_and_changes_nothing(case, template, tmp_path):
    ws = tmp_path / "ws"
    shutil.copytree(template, ws)
    args = case.setup(ws, tmp_path)
    before = tree_hash(ws)
    r = invoke(CliRunner(), *args)
    lines = r.stderr.splitlines()
    assert r.exit_code == case.code, (r.exit_code, r.output)
    assert len(lines) == 1, r.stderr
    assert len(lines[0]) < 400 + len(str(tmp_path)) * 3, lines[0][:1000]  # nothing echoed whole
    assert "Traceback" not in r.output and "(unexpected" not in r.stderr
    where = case.where(ws, tmp_path)
    expected = f"error: {where}: " if where else "error: "
    assert lines[0].startswith(expected), f"\n{lines[0]}\n{expected}"
    assert case.text.replace("{ws}", str(ws)) in lines[0], f"\n{lines[0]}\n{case.text}"
    if case.fix is not None:
        assert lines[0].endswith(case.fix.replace("{ws}", str(ws))), lines[0]
    assert tree_hash(ws) == before


@pytest.mark.parametrize("edit", list(MODEL_EDITS))
def test_a_report_shows_a_damaged_model_as_unusable(template, tmp_path, edit):
    # The report does not need the model (its estimate does not): it is written, opening
    # with the model's damage and the command that mends it. It reached the catch-all
    # ("Input X contains NaN"), or with a negative noise drew the model's picture from it.
    ws = tmp_path / "ws"
    shutil.copytree(template, ws)
    change, text = MODEL_EDITS[edit]
    _edit_model(change, "report")(ws, tmp_path)
    r = invoke(CliRunner(), "report", "-w", ws)
    assert r.exit_code == 0, r.output
    assert "(unexpected" not in r.stderr and "Traceback" not in r.output
    summary = json.loads((ws / "report" / "summary.json").read_text())
    [notice] = [n for n in summary["notices"] if n["kind"] == "stale_model"]
    assert f"damaged hyperparameters ({text}" in notice["text"]
    assert notice["text"].endswith(f"run `bams-cli fit -w {ws}` to write it again")


def test_fit_rewrites_a_model_whose_hyperparameters_were_damaged(template, tmp_path):
    # The command every refusal names: a damaged model is not "up to date", whatever
    # the log it says it was fitted on.
    ws = tmp_path / "ws"
    shutil.copytree(template, ws)
    change, _ = MODEL_EDITS["nan-lengthscale"]
    _edit_model(change, "fit")(ws, tmp_path)
    r = ok(CliRunner(), "fit", "-w", ws, "--restarts", "1", "--json")
    assert not json.loads(r.stdout).get("up_to_date")
    Workspace(ws).require_fresh_model()  # readable again: no error


def test_an_estimate_of_gammas_edited_since_is_reported_by_its_own_gamma(template, tmp_path):
    # The estimate's rows carry their gamma: recall is matched by it, not by position.
    ws = tmp_path / "ws"
    shutil.copytree(template, ws)
    path = ws / EST
    doc = json.loads(path.read_text())
    doc["estimates"].insert(0, {**doc["estimates"][0], "gamma": 0.3})
    doc["gp"].insert(0, {**doc["gp"][0], "gamma": 0.3})
    path.write_text(json.dumps(doc))
    truth = template.parent / "data" / "truth.parquet"
    ok(CliRunner(), "report", "-w", ws, "--truth", truth)
    summary = json.loads((ws / "report" / "summary.json").read_text())
    assert [e["gamma"] for e in summary["estimates"]] == [0.3, 0.56]
    found = doc["estimates"][1]["distinct_failures_found"]
    assert summary["truth"]["estimate_recall"] == [found / summary["truth"]["failures"][0]]
