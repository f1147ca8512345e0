"""Every bad input, one table: a one-line error naming what is wrong, and nothing changed.

Each case starts from a copy of one study (a reduced toy2d pool, a batch ingested and
fitted, an estimate computed, a second batch awaiting results), damages an input or a
state file, runs one command through the CLI and asserts:

* exit code 1 (2 for click's own usage errors, none of them here);
* stderr is exactly one line, ``error: <file>: [column 'c'[, row r]: ]<what>``, with the
  file, column and row of the case and its expected text;
* no traceback and no ``(unexpected`` catch-all text (kept for true bugs);
* every file of the workspace byte-for-byte as before (``tree_hash``).
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from typer.testing import CliRunner

from tests.conftest import invoke, ok, simulate_and_ingest, tree_hash, write_batch, write_toy

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
    ok(runner, "estimate", "-w", ws, "--plan", "--samples", "4")
    plan = ws / "estimates" / "plan-0001-handoff.csv"
    simulate_and_ingest(runner, ws, plan, truth, tmp / "r-plan.parquet")
    ok(runner, "estimate", "-w", ws)
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

    def where(self, ws: Path, tmp: Path) -> str:
        path = tmp / self.file[1:] if self.file.startswith("@") else ws / self.file
        out = str(path)
        if self.column is not None:
            out += f": column {self.column!r}"
        if self.row is not None:
            out += f", row {self.row}"
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

CASES = [*ESTIMATE_CASES]


def test_case_ids_are_unique():
    assert len({c.id for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", [pytest.param(c, id=c.id, marks=c.marks) for c in CASES])
def test_bad_input_is_one_line_naming_it_and_changes_nothing(case, template, tmp_path):
    ws = tmp_path / "ws"
    shutil.copytree(template, ws)
    args = case.setup(ws, tmp_path)
    before = tree_hash(ws)
    r = invoke(CliRunner(), *args)
    lines = r.stderr.splitlines()
    assert r.exit_code == 1, (r.exit_code, r.output)
    assert len(lines) == 1, r.stderr
    assert "Traceback" not in r.output and "(unexpected" not in r.stderr
    expected = f"error: {case.where(ws, tmp_path)}: "
    assert lines[0].startswith(expected), f"\n{lines[0]}\n{expected}"
    assert case.text.replace("{ws}", str(ws)) in lines[0], f"\n{lines[0]}\n{case.text}"
    if case.fix is not None:
        assert lines[0].endswith(case.fix.replace("{ws}", str(ws))), lines[0]
    assert tree_hash(ws) == before


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
