"""The Python API (``bams_cli.api``) is the CLI: every command has its function, every flag
its documented parameter, the same study gives the same numbers, and the same bad input
the same error."""

from __future__ import annotations

import inspect
import json
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import polars as pl
import pytest
from typer.testing import CliRunner

from bams_cli import api
from bams_cli.cli import app
from bams_cli.errors import BamsError, PendingResultsError, WorkspaceError
from bams_cli.state.workspace import Workspace
from tests.conftest import STAGED_PLAN, invoke, ok, tree_hash, write_toy

#: Each command that reads or writes a workspace, and the API functions it calls.
COMMANDS: dict[str, list[Callable[..., dict[str, Any]]]] = {
    "init": [api.init],
    "embed-reduce": [api.embed_reduce],
    "ingest-results": [api.ingest_results, api.ingest_results_abandoning_failed],
    "fit": [api.fit],
    "select": [api.select],
    "estimate": [api.estimate_plan, api.estimate_compute],
    "report": [api.report],
    "status": [api.status],
    "abandon": [api.abandon],
    "loop": [api.loop],
    "simulate": [api.simulate],
}
#: Commands with no workspace, hence no API function here.
NO_WORKSPACE = {"schema", "benchmark"}

#: CLI parameters that are no API parameter: how the CLI prints, or which function it calls.
CLI_ONLY: dict[str, set[str]] = {
    "*": {"json_out", "quiet", "max_memory"},  # max_memory: ``with memory.ceiling(...)``
    "estimate": {"plan"},  # --plan: estimate_plan, else estimate_compute
    "ingest-results": {"abandon_failed"},  # ingest_results_abandoning_failed
}
#: CLI parameter names that the API spells otherwise.
RENAMED: dict[str, dict[str, str]] = {
    "*": {"workspace": "root"},
    "init": {"gamma": "gammas"},
    "embed-reduce": {"segments": "source"},
    "ingest-results": {"results": "source"},
    "report": {"diverse": "n_diverse"},
}

LOCKED = [
    api.embed_reduce,
    api.ingest_results,
    api.ingest_results_abandoning_failed,
    api.fit,
    api.select,
    api.estimate_plan,
    api.estimate_compute,
    api.report,
    api.abandon,
]
FUNCTIONS = sorted({f for fs in COMMANDS.values() for f in fs}, key=lambda f: f.__name__)


def _cli_commands() -> dict[str, Callable[..., None]]:
    return {
        c.name or c.callback.__name__.replace("_", "-"): c.callback  # type: ignore[union-attr]
        for c in app.registered_commands
    }


def _sections(doc: str) -> dict[str, list[str]]:
    """A numpy-style docstring's sections: heading -> its lines."""
    lines = doc.splitlines()
    heads = [
        i
        for i in range(len(lines) - 1)
        if lines[i].strip()
        and set(lines[i + 1].strip()) == {"-"}
        and len(lines[i + 1].strip()) == len(lines[i].strip())
    ]
    out = {}
    for k, i in enumerate(heads):
        end = heads[k + 1] if k + 1 < len(heads) else len(lines)
        out[lines[i].strip()] = lines[i + 2 : end]
    return out


def _documented(fn: Callable[..., Any]) -> list[str]:
    """The names the Parameters section documents, in order."""
    doc = inspect.getdoc(fn) or ""
    params = _sections(doc).get("Parameters", [])
    names = []
    for line in params:
        if line and not line[0].isspace():
            m = re.match(r"^(\w+)(\s*:|$)", line)
            assert m, f"{fn.__name__}: unreadable Parameters line {line!r}"
            names.append(m.group(1))
    return names


def test_every_workspace_command_has_its_api_function() -> None:
    assert set(_cli_commands()) == set(COMMANDS) | NO_WORKSPACE
    for name in api.__all__:
        assert hasattr(api, name), name
    for fns in COMMANDS.values():
        for fn in fns:
            assert fn.__name__ in api.__all__


@pytest.mark.parametrize("fn", FUNCTIONS, ids=lambda f: f.__name__)
def test_docstring_documents_every_parameter(fn: Callable[..., Any]) -> None:
    doc = inspect.getdoc(fn) or ""
    summary = doc.splitlines()[0]
    assert summary.strip() and len(summary) <= 100, summary
    sections = _sections(doc)
    assert {"Parameters", "Returns", "Raises"} <= set(sections), (fn.__name__, list(sections))
    params = list(inspect.signature(fn).parameters)
    assert _documented(fn) == params, f"{fn.__name__}: docstring vs signature"


@pytest.mark.parametrize("fn", LOCKED, ids=lambda f: f.__name__)
def test_locked_functions_show_wait(fn: Callable[..., Any]) -> None:
    """``@locked`` adds ``wait``; the signature (and so ``help()``) must say so."""
    wait = inspect.signature(fn).parameters["wait"]
    assert wait.kind is inspect.Parameter.KEYWORD_ONLY
    assert wait.default is False
    assert "wait" in _documented(fn)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_cli_option_is_an_api_parameter(command: str) -> None:
    callback = _cli_commands()[command]
    cli_params = inspect.signature(callback).parameters
    api_params = set().union(*(inspect.signature(f).parameters for f in COMMANDS[command]))
    skip = CLI_ONLY["*"] | CLI_ONLY.get(command, set())
    renamed = RENAMED["*"] | RENAMED.get(command, {})
    for name in cli_params:
        if name in skip:
            continue
        assert renamed.get(name, name) in api_params, f"{command}: --{name} has no API parameter"


# ---------------------------------------------------------------------------------------
# the same study through the API and through the CLI
# ---------------------------------------------------------------------------------------
def _cli_study(runner: CliRunner, ws: Path, seg: Path, truth: Path, tmp: Path) -> dict[str, Any]:
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
    ok(runner, "select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", "6")
    for b in (1, 2):
        if b > 1:
            ok(runner, "select", "-w", ws, "--budget", "3", "--clusters", "2", "--workers", "1")
        res = tmp / f"cli-r{b}.parquet"
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
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "40", "--stages", "1")
    res = tmp / "cli-est.parquet"
    ok(runner, "simulate", ws / "estimates" / "plan-0001-handoff.csv", "--truth", truth, "-o", res)
    ok(runner, "ingest-results", "-w", ws, res)
    out = ok(runner, "estimate", "-w", ws, "--json").stdout
    return json.loads(out)


def _api_study(ws: Path, seg: Path, truth: Path, tmp: Path) -> dict[str, Any]:
    api.init(ws, gammas=[0.56, 1.0], costs=[1, 0.1], dim=2, seed=3)
    api.embed_reduce(ws, seg, columns="x*", method="identity", standardize=False)
    api.select(ws, strategy="random", mixed_fidelity=True, budget=6)
    for b in (1, 2):
        if b > 1:
            api.select(ws, budget=3, clusters=2, workers=1)
        res = tmp / f"api-r{b}.parquet"
        api.simulate(ws / "batches" / f"batch-{b:04d}.parquet", truth, res)
        api.ingest_results(ws, res)
        api.fit(ws, restarts=2, wait=True)
    plan = api.estimate_plan(ws, samples=40, stages=1, screen="off")
    res = tmp / "api-est.parquet"
    api.simulate(Path(plan["handoff"]), truth, res)
    api.ingest_results(ws, res)
    return api.estimate_compute(ws)


def _picks(ws: Path) -> list[list[tuple[str, int]]]:
    w = Workspace(ws)
    return [
        list(
            pl.read_parquet(w.batches_dir / f"batch-{b:04d}.parquet")
            .select("segment_id", "fidelity")
            .iter_rows()
        )
        for b in w.batch_numbers()
    ]


def test_api_study_equals_cli_study(tmp_path: Path) -> None:
    seg, truth = write_toy(tmp_path / "data", n=300, seed=4)
    cli_ws, api_ws = tmp_path / "cli", tmp_path / "api"
    cli_est = _cli_study(CliRunner(), cli_ws, seg, truth, tmp_path)
    api_est = _api_study(api_ws, seg, truth, tmp_path)

    assert len(_picks(cli_ws)) == 2
    assert _picks(api_ws) == _picks(cli_ws)
    model = [json.loads((w / "model.json").read_text()) for w in (api_ws, cli_ws)]
    assert model[0]["observations_hash"] == model[1]["observations_hash"]
    assert model[0]["hyperparameters"] == model[1]["hyperparameters"]
    plans = [
        pl.read_parquet(w / "estimates" / "plan-0001.parquet").sort("segment_id")
        for w in (api_ws, cli_ws)
    ]
    assert plans[0].equals(plans[1])
    assert cli_est.pop("schema_version")
    for key in ("estimates", "gp", "plan", "design", "samples_K", "staging", "notes"):
        assert api_est[key] == cli_est[key], key
    assert {k for k in api_est if k != "estimate_file"} == {
        k for k in cli_est if k != "estimate_file"
    }
    assert api.status(api_ws)["next"]["step"] == api.status(cli_ws)["next"]["step"]


# ---------------------------------------------------------------------------------------
# the same bad input: the same error, and the workspace untouched
# ---------------------------------------------------------------------------------------
def _bad_results(ws: Path) -> Path:
    path = ws.parent / "bad-results.csv"
    path.write_text("segment_id,fidelity,value\nno-such-segment,0,0.3\n")
    return path


BAD: list[tuple[str, list[str], Callable[..., Any], dict[str, Any], type[BamsError]]] = [
    ("fit", ["fit", "--restarts", "0"], api.fit, {"restarts": 0}, api.OptionValueError),
    (
        "select",
        ["select", "--confirm-share", "1.5"],
        api.select,
        {"confirm_share": 1.5},
        api.OptionValueError,
    ),
    (
        "estimate",
        ["estimate", "--confidence", "2.0"],
        api.estimate_compute,
        {"confidence": 2.0},
        api.OptionValueError,
    ),
    (
        "estimate-plan",
        ["estimate", *STAGED_PLAN, "--stages", "0"],
        api.estimate_plan,
        {"stages": 0},
        api.OptionValueError,
    ),
    ("report", ["report", "--diverse", "-1"], api.report, {"n_diverse": -1}, api.OptionValueError),
    ("abandon", ["abandon"], api.abandon, {}, api.OptionValueError),
]


def _cli_error(runner: CliRunner, ws: Path, args: list[object]) -> tuple[int, str]:
    r = invoke(runner, args[0], "-w", ws, *args[1:])
    lines = r.stderr.splitlines()
    assert len(lines) == 1, r.stderr
    assert lines[0].startswith("error: ")
    return r.exit_code, lines[0].removeprefix("error: ")


def _same_error(
    runner: CliRunner, ws: Path, call: Callable[[], Any], args: list[object], cls: type
) -> None:
    before = tree_hash(ws)
    with pytest.raises(BamsError) as info:
        call()
    assert type(info.value) is cls
    assert tree_hash(ws) == before
    code, message = _cli_error(runner, ws, args)
    assert str(info.value) == message
    assert info.value.exit_code == code
    assert tree_hash(ws) == before


@pytest.mark.parametrize(
    ("args", "fn", "kwargs", "cls"), [b[1:] for b in BAD], ids=[b[0] for b in BAD]
)
def test_api_error_is_the_cli_error(
    toy_ws: Path,
    runner: CliRunner,
    args: list[str],
    fn: Callable[..., Any],
    kwargs: dict[str, Any],
    cls: type,
) -> None:
    _same_error(runner, toy_ws, lambda: fn(toy_ws, **kwargs), list(args), cls)


def test_api_input_error_is_the_cli_error(toy_ws: Path, runner: CliRunner) -> None:
    bad = _bad_results(toy_ws)
    _same_error(
        runner,
        toy_ws,
        lambda: api.ingest_results(toy_ws, bad),
        ["ingest-results", bad],
        api.InputError,
    )


def test_api_pending_error_has_exit_code_3(toy_ws: Path, runner: CliRunner) -> None:
    api.select(toy_ws, strategy="random", budget=3)
    _same_error(runner, toy_ws, lambda: api.fit(toy_ws), ["fit"], PendingResultsError)
    assert PendingResultsError("x").exit_code == 3


def test_missing_workspace_is_the_cli_error(tmp_path: Path, runner: CliRunner) -> None:
    ws = tmp_path / "nowhere"
    with pytest.raises(WorkspaceError) as info:
        api.fit(ws)
    code, message = _cli_error(runner, ws, ["fit"])
    assert (str(info.value), info.value.exit_code) == (message, code)
    assert not ws.exists()


def _example() -> str:
    return inspect.cleandoc((api.__doc__ or "").split("::\n", 1)[1])


def test_readme_python_api_example_is_the_docstrings() -> None:
    """The README shows the example that ``test_module_docstring_example_runs`` runs."""
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    section = readme.split("\n## Python API\n", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```python\n(.*?)```", section, re.S)
    assert block is not None
    assert block.group(1).strip() == _example()


@pytest.mark.slow
def test_module_docstring_example_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The example a notebook user copies from ``help(bams_cli.api)`` runs as written."""
    root = Path(__file__).resolve().parents[1]
    (tmp_path / "sample_data").symlink_to(root / "sample_data")
    monkeypatch.chdir(tmp_path)
    exec(compile(_example(), "bams_cli.api example", "exec"), {})
    assert (tmp_path / "study" / "report" / "report.html").is_file()
    assert len(list((tmp_path / "study" / "batches").glob("batch-*.parquet"))) == 3
