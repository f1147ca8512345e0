"""Every command's --json output (and report/summary.json) validates against the schema
``bams-cli schema`` prints: a whole study is run once, each output checked on the way."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bams_cli import schemas_json
from tests.conftest import STAGED_PLAN, invoke, ok, write_toy
from tests.jsonschema_subset import check_schema, errors


def _run(runner: CliRunner, *args: object, code: int = 0) -> dict:
    r = invoke(runner, *args, "--json")
    assert r.exit_code == code, f"{args}: {r.output}"
    return json.loads(r.stdout)


@pytest.fixture(scope="module")
def outputs(tmp_path_factory) -> dict[str, list[dict]]:
    """Each schema's name -> the outputs of a small study's commands (several per name
    where a command answers in more than one shape)."""
    runner = CliRunner()
    tmp = tmp_path_factory.mktemp("schemas")
    seg, truth = write_toy(tmp / "data", n=300)
    ws = tmp / "ws"
    out: dict[str, list[dict]] = {name: [] for name in schemas_json.NAMES}

    def run(name: str, *args: object, code: int = 0) -> dict:
        doc = _run(runner, *args, code=code)
        out[name].append(doc)
        return doc

    def answer(handoff: str, n: int) -> Path:
        res = tmp / f"r{n}.csv"
        run("simulate", "simulate", handoff, "--truth", truth, "-o", res)
        return res

    run("init", "init", "-w", ws, "--gamma", "0.56", "--costs", "1,0.1", "--dim", "2")
    run("init", "init", "-w", ws, "--gamma", "0.56", "--costs", "1,0.1", "--dim", "2", "--exist-ok")  # fmt: skip
    run("status", "status", "-w", ws)  # no pool yet
    run("embed-reduce", "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity", "--no-standardize")  # fmt: skip
    b1 = run("select", "select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", 3)  # fmt: skip
    run("status", "status", "-w", ws, code=3)  # waiting on results
    res = answer(b1["handoff_csv"], 1)
    run("ingest-results", "ingest-results", "-w", ws, res)
    run("ingest-results", "ingest-results", "-w", ws, res)  # already ingested
    run("fit", "fit", "-w", ws, "--restarts", 2)
    run("fit", "fit", "-w", ws, "--restarts", 2)  # up to date
    b2 = run("select", "select", "-w", ws, "--budget", 2, "--clusters", 2, "--workers", 1)
    # The results template with one run that crashed: not ingested, still pending.
    template = (Path(b2["results_template"])).read_text().splitlines()
    lines = [template[0], template[1].rstrip(",") + ",,crashed"]
    (tmp / "crashed.csv").write_text("\n".join(lines) + "\n")
    run("ingest-results", "ingest-results", "-w", ws, tmp / "crashed.csv")
    # Given up on: the crashed run abandoned, then the rest of the batch; late results count.
    run("ingest-results", "ingest-results", "-w", ws, tmp / "crashed.csv", "--abandon-failed")
    run("abandon", "abandon", "-w", ws, "--batch", 2, "--reason", "cluster down")
    run("abandon", "abandon", "-w", ws, "--batch", 2)  # nothing left to abandon
    run("ingest-results", "ingest-results", "-w", ws, answer(b2["handoff_csv"], 2))
    run("fit", "fit", "-w", ws, "--restarts", 2)
    run("report", "report", "-w", ws)  # no estimate yet
    out["summary.json"].append(json.loads((ws / "report" / "summary.json").read_text()))
    plan = run("estimate-plan", "estimate", "-w", ws, *STAGED_PLAN, "--samples", 10)
    run("status", "status", "-w", ws, code=3)
    run("ingest-results", "ingest-results", "-w", ws, answer(plan["handoff"], 3))
    run("estimate", "estimate", "-w", ws)
    # A screened estimate: the screen (a cheap batch), its results, a refit, the confirmation.
    run("fit", "fit", "-w", ws, "--restarts", 2)
    screen = run("estimate-screen", "estimate", "-w", ws, "--plan", "--screen", 0.3,
                 "--samples", 10, "--new-series")  # fmt: skip
    run("ingest-results", "ingest-results", "-w", ws, answer(screen["handoff"], 4))
    run("fit", "fit", "-w", ws, "--restarts", 2)
    confirm = run("estimate-plan", "estimate", "-w", ws, *STAGED_PLAN)
    assert confirm["weighting"] == "screen"
    run("ingest-results", "ingest-results", "-w", ws, answer(confirm["handoff"], 5))
    run("estimate", "estimate", "-w", ws)
    run("report", "report", "-w", ws, "--truth", truth)
    out["summary.json"].append(json.loads((ws / "report" / "summary.json").read_text()))
    run("status", "status", "-w", ws)
    sim = f"{sys.executable} -m bams_cli simulate {{handoff}} --truth {truth} -o {{results}}"
    run("loop", "loop", "-w", ws, "--simulator", sim, "--batches", 2)  # nothing left to do
    return out


@pytest.mark.parametrize("name", schemas_json.NAMES)
def test_each_output_validates_against_its_schema(outputs, name):
    schema = schemas_json.schema(name)
    check_schema(schema)
    assert outputs[name], f"the study ran no command printing {name}"
    for doc in outputs[name]:
        assert doc["schema_version"] == schemas_json.VERSIONS[name]
        assert errors(doc, schema) == [], name


def test_the_shapes_the_study_went_through(outputs):
    # The study above reached each answer the schemas describe more than one way.
    assert any(d.get("up_to_date") for d in outputs["fit"])
    assert any(d["already_ingested"] for d in outputs["ingest-results"])
    assert any(d["not_run"]["count"] == 1 for d in outputs["ingest-results"])
    assert {d["exit_code"] for d in outputs["status"]} == {0, 3}
    assert [d["truth"] is None for d in outputs["summary.json"]] == [True, False]
    assert outputs["status"][0]["model"] is None


@pytest.mark.parametrize(
    "name, break_it, needle",
    [
        ("select", lambda d: d.pop("results_template"), "missing required key 'results_template'"),
        ("select", lambda d: d.update(picks="11"), "$.picks: expected integer"),
        ("status", lambda d: d["next"].update(text=None), "$.next.text: expected string"),
        ("estimate", lambda d: d["estimates"][0].update(p_hat=None), "$.estimates[0].p_hat"),
        ("summary.json", lambda d: d.update(schema_version=99), "$.schema_version: expected 1"),
    ],
)
def test_the_validator_catches_a_broken_output(outputs, name, break_it, needle):
    doc = json.loads(json.dumps(outputs[name][-1]))
    break_it(doc)
    found = errors(doc, schemas_json.schema(name))
    assert any(needle in e for e in found), found


def test_schema_command_prints_each_schema(runner):
    every = json.loads(ok(runner, "schema").stdout)
    assert list(every) == list(schemas_json.NAMES)
    for name in ("select", "ingest-results", "fit", "estimate", "status", "summary.json"):
        one = json.loads(ok(runner, "schema", name).stdout)
        assert one == every[name] == schemas_json.schema(name)
        assert one["properties"]["schema_version"] == {"const": schemas_json.VERSIONS[name]}
        assert one["required"][0] == "schema_version"
    r = invoke(runner, "schema", "nope")
    unboxed = " ".join(r.stderr.replace("│", " ").split())  # click's usage box wraps
    assert r.exit_code == 2 and "'nope' is not one of 'init', 'embed-reduce'" in unboxed


def test_every_notice_the_report_can_write_is_in_the_summary_schema():
    # A notice kind written in one place and missing from the schema makes summary.json
    # fail its own schema only in the study that meets that notice (design_like_uniform did).
    import re

    from bams_cli.pipeline import reporting

    source = Path(reporting.__file__).read_text()
    written = set(re.findall(r'"kind": "([a-z_]+)"', source))
    kinds = schemas_json.schema("summary.json")["properties"]["notices"]["items"]
    assert written and written <= set(kinds["properties"]["kind"]["enum"])


def test_every_field_a_loop_step_can_carry_is_in_the_loop_schema():
    # The study above runs loop with nothing left to do, so its steps carry no fields; a
    # field written by ``loop._run`` and missing from the schema went unseen (``failed``).
    import re

    from bams_cli import loop

    source = Path(loop.__file__).read_text()
    written = set(re.findall(r'record\["([a-z_]+)"\]', source))
    step = schemas_json.schema("loop")["properties"]["steps"]["items"]["properties"]
    assert written and written <= set(step), sorted(written - set(step))


def test_schema_takes_json_as_every_command_does(runner):
    # `bams-cli schema estimate --json` was a usage error (exit 2).
    plain = ok(runner, "schema", "estimate").stdout
    assert ok(runner, "schema", "estimate", "--json").stdout == plain
    assert json.loads(plain)["$id"].startswith("bams-cli/estimate/")
