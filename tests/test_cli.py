"""The command line as a user meets it: --help, choices, --quiet, --json errors, BAMS_*
environment variables, output in logs, progress lines, the short human summaries."""

from __future__ import annotations

import enum
import inspect
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from typer.main import get_command

from bams_cli import benchmark, cli, console, defaults, pipeline, schemas_json
from bams_cli.cli import app
from bams_cli.core import estimate as core_estimate
from tests.conftest import invoke, ok, write_batch

COMMANDS = sorted(get_command(app).commands)  # type: ignore[attr-defined]


#: Options whose absence means "none" (nothing to abandon by, no truth, no scheduler ...):
#: every other option shows its default in --help.
OFF_UNLESS_GIVEN = {
    ("abandon", "--batch"),
    ("abandon", "--plan"),
    ("abandon", "--segments"),
    ("abandon", "--fidelity"),
    ("abandon", "--reason"),
    ("fit", "--fixed-hyperparameters"),
    ("init", "--gamma"),
    ("init", "--settings-from"),
    ("report", "--truth"),
    ("select", "--scheduler"),
    ("select", "--batch"),
    ("select", "--out"),
}


def help_text(runner, *args: str, monkeypatch) -> str:
    monkeypatch.setenv("COLUMNS", "400")  # one line per option
    return ok(runner, *args, "--help").stdout


@pytest.mark.parametrize("name", COMMANDS)
def test_help_has_no_bool_metavar_and_shows_every_default(runner, name, monkeypatch):
    text = help_text(runner, name, monkeypatch=monkeypatch)
    assert "<bool>" not in text
    command = get_command(app).commands[name]  # type: ignore[attr-defined]
    rows = [line for line in text.splitlines() if re.match(r"│\s+(\*\s+)?-", line)]
    for param in command.params:
        if param.param_type_name != "option" or param.is_flag or param.required:
            continue
        if param.default is None and (name, param.opts[0]) in OFF_UNLESS_GIVEN:
            continue
        row = next(r for r in rows if param.opts[0] in r.split()[1:4])
        assert "[default: " in row, f"{name} {param.opts[0]}: default not shown"


@pytest.mark.parametrize(
    ("name", "choices"),
    [
        ("select", "<bams|bas|random|mc-gp|mcm-gp|ds|ds-gp|ce>"),
        ("select", "<global|raw>"),
        ("select", "<auto|exact|approximate>"),
        ("benchmark", "<auto|exact|approximate>"),
        ("estimate", "<poisson|fixed|with-replacement>"),
        ("estimate", "<auto|uniform|p-alpha>"),
        ("estimate", "<gamma|fay-feuer>"),
        ("estimate", "<bounds>"),
        ("fit", "<auto|none>"),
        ("embed-reduce", "<pca|autoencoder|identity|ipca>"),
        ("benchmark", "<toy2d|av_like|weak_cheap|digits|rare_regions|gap_sim|suite>"),
    ],
)
def test_help_lists_the_choices(runner, name, choices, monkeypatch):
    assert choices in help_text(runner, name, monkeypatch=monkeypatch)


@pytest.mark.parametrize(
    ("args", "valid"),
    [
        (["select", "--strategy", "bmas"], "'bams', 'bas', 'random'"),
        (["select", "--pooling", "local"], "'global', 'raw'"),
        (["estimate", "--design", "srs"], "'poisson', 'fixed', 'with-replacement'"),
        (["estimate", "--weighting", "p^alpha"], "'auto', 'uniform', 'p-alpha'"),
        (["estimate", "--interval", "wald"], "'gamma', 'fay-feuer'"),
        (["estimate", "--failed-as", "pass"], "'bounds'"),
        (["fit", "--transform", "log"], "'auto', 'none'"),
        (["embed-reduce", "x.parquet", "--method", "umap"], "'pca', 'autoencoder'"),
        (["benchmark", "--protocol", "nope"], "'toy2d', 'av_like'"),
        (["schema", "nope"], "'init', 'embed-reduce'"),
    ],
)
def test_an_invalid_choice_is_a_usage_error_naming_the_valid_ones(runner, tmp_path, args, valid):
    r = invoke(runner, *args)
    assert r.exit_code == 2, r.output
    # Off a terminal (as here) click's plain lines, the error whole on one of them.
    [error] = [line for line in r.stderr.splitlines() if line.startswith("Error: ")]
    assert "is not one of" in error and valid in error, r.stderr
    assert "Value error" not in error, error  # typer's pydantic prefix is not the tool's
    assert not list(tmp_path.iterdir())


def test_every_choice_enum_matches_what_the_pipeline_accepts():
    from bams_cli import abandon
    from bams_cli.core import estimate as est

    assert tuple(defaults.Strategy) == pipeline.STRATEGIES
    assert tuple(defaults.Transform) == pipeline.TRANSFORMS
    assert tuple(defaults.Design) == est.DESIGNS
    assert tuple(defaults.Weighting) == pipeline.WEIGHTINGS
    assert tuple(defaults.FailedAs) == abandon.FAILED_AS
    assert set(defaults.Interval) <= set(est.INTERVALS)
    assert tuple(defaults.Protocol) == (*benchmark.PROTOCOLS, "suite")
    assert tuple(cli.SchemaName) == schemas_json.NAMES


def _signature_defaults(fn) -> dict[str, object]:
    fn = inspect.unwrap(fn)
    return {k: p.default for k, p in inspect.signature(fn).parameters.items()}


@pytest.mark.parametrize(
    ("fn", "expected"),
    [
        (
            pipeline.select,
            {
                "strategy": defaults.STRATEGY,
                "budget": defaults.BUDGET,
                "clusters": defaults.CLUSTERS,
                "overbudget": defaults.OVERBUDGET,
                "pooling": defaults.POOLING,
                "level0_share": defaults.LEVEL0_SHARE,
                "confirm_share": defaults.CONFIRM_SHARE,
                "difficulty_column": defaults.DIFFICULTY_COLUMN,
            },
        ),
        (
            pipeline.fit,
            {
                "restarts": defaults.RESTARTS,
                "chunk_size": defaults.CHUNK_SIZE,
                "transform": defaults.TRANSFORM,
            },
        ),
        (
            pipeline.estimate_plan,
            {
                "alpha": defaults.ALPHA,
                "defensive": defaults.DEFENSIVE,
                "design": defaults.DESIGN,
                "weighting": defaults.WEIGHTING,
                "stages": defaults.STAGES,
                "stage1_share": defaults.STAGE1_SHARE,
            },
        ),
        (
            pipeline.estimate_compute,
            {"confidence": defaults.CONFIDENCE, "interval": defaults.INTERVAL},
        ),
        (pipeline.embed_reduce, {"method": defaults.METHOD}),
    ],
)
def test_pipeline_defaults_agree_with_the_one_definition(fn, expected):
    # The CLI and the benchmark pass every one of these from bams_cli.defaults; a pipeline
    # function called bare (a notebook) must do what the CLI does.
    got = _signature_defaults(fn)
    assert {k: got[k] for k in expected} == expected


def test_the_benchmark_reads_its_defaults_from_the_one_definition(monkeypatch):
    monkeypatch.setattr(defaults, "ALPHA", 0.123)
    import importlib

    reloaded = importlib.reload(benchmark)
    try:
        assert reloaded.estimate_defaults()["alpha"] == 0.123
        assert reloaded.PLAN_DEFAULTS["design"] == defaults.DESIGN.value
        assert reloaded.SELECT_DEFAULTS["confirm_share"] == defaults.CONFIRM_SHARE
    finally:
        monkeypatch.undo()
        importlib.reload(benchmark)
    assert core_estimate.plan_sample is not None  # core untouched by the reload


def test_completion_options_are_offered(runner, monkeypatch):
    text = help_text(runner, monkeypatch=monkeypatch)
    assert "--install-completion" in text and "--show-completion" in text


@pytest.mark.parametrize("where", ["command", "global", "env"])
def test_quiet_prints_nothing_but_errors(runner, tmp_path, where):
    ws = tmp_path / "ws"
    args = ["init", "-w", ws, "--gamma", "0.5"]
    env = {}
    if where == "command":
        args.append("--quiet")
    elif where == "global":
        args.insert(0, "-q")
    else:
        env["BAMS_QUIET"] = "1"
    r = runner.invoke(app, [str(a) for a in args], env=env, catch_exceptions=False)
    assert r.exit_code == 0 and r.stdout == "" and r.stderr == ""
    assert (ws / "settings.toml").exists()
    r = runner.invoke(app, [str(a) for a in args], env=env, catch_exceptions=False)
    assert r.exit_code == 1 and r.stdout == ""
    assert r.stderr.startswith("error: ") and r.stderr.count("\n") == 1  # errors still print


def test_quiet_does_not_stick_to_the_next_command(runner, tmp_path):
    ok(runner, "-q", "init", "-w", tmp_path / "a", "--gamma", "0.5")
    assert "created" in ok(runner, "init", "-w", tmp_path / "b", "--gamma", "0.5").stdout


def test_a_json_error_is_one_json_line_on_stderr(runner, tmp_path):
    r = invoke(runner, "select", "-w", tmp_path / "missing", "--json")
    assert r.exit_code == 1 and r.stdout == ""
    [line] = r.stderr.splitlines()
    doc = json.loads(line)
    assert doc["exit_code"] == 1 and "no such workspace" in doc["error"]
    # Without --json the same error stays the human line.
    r = invoke(runner, "select", "-w", tmp_path / "missing")
    assert r.stderr.startswith("error: ") and "no such workspace" in r.stderr


@pytest.mark.parametrize(
    ("args", "code", "needle"),
    [
        (["select", "-w", "missing-ws", "--json"], 1, "no such workspace"),
        (["select", "--strategy", "nope", "--json"], 2, "'nope' is not one of 'bams'"),
        (["select", "--bogus", "--json"], 2, "No such option: --bogus"),
        (["select", "--budget", "-5", "--json"], 2, "--budget -5: must be a finite number > 0"),
    ],
)
def test_the_installed_command_prints_json_errors_even_for_usage(tmp_path, args, code, needle):
    out = subprocess.run(
        [sys.executable, "-m", "bams_cli", *args], capture_output=True, text=True, cwd=tmp_path
    )
    assert out.returncode == code and out.stdout == ""
    [line] = out.stderr.splitlines()
    doc = json.loads(line)
    assert doc["exit_code"] == code and needle in doc["error"]
    assert "Value error" not in doc["error"]


def test_json_warnings_are_json_lines(runner):
    import warnings

    @cli.command("warn-json")
    def _warn(json_out: cli.Json = False) -> None:
        """Test-only command.\n\n[bold]Example[/]: bams-cli warn-json"""
        warnings.warn("careful", UserWarning, stacklevel=1)

    try:
        r = invoke(runner, "warn-json", "--json")
    finally:
        app.registered_commands.pop()
    assert [json.loads(line) for line in r.stderr.splitlines()] == [{"warning": "careful"}]


def test_bams_workspace_is_honoured(runner, tmp_path):
    ws = tmp_path / "from-env"
    r = runner.invoke(
        app, ["init", "--gamma", "0.5"], env={"BAMS_WORKSPACE": str(ws)}, catch_exceptions=False
    )
    assert r.exit_code == 0, r.output
    assert (ws / "settings.toml").exists()
    r = runner.invoke(app, ["status", "--json"], env={"BAMS_WORKSPACE": str(ws)})
    assert json.loads(r.stdout)["workspace"] == str(ws)


def test_a_long_path_prints_whole_on_one_line_in_a_log(runner, tmp_path, monkeypatch):
    # CliRunner's stdout is not a terminal, like a CI log; rich used to wrap at 80 columns.
    monkeypatch.delenv("COLUMNS", raising=False)
    ws = tmp_path.joinpath(*(["a-rather-long-folder-name"] * 8), "ws")
    assert len(str(ws)) > 200
    r = ok(runner, "init", "-w", ws, "--gamma", "0.5")
    assert any(line.endswith(str(ws / "settings.toml")) for line in r.stdout.splitlines())
    r = ok(runner, "status", "-w", ws)
    assert any(str(ws) in line for line in r.stdout.splitlines())


def test_select_summary_is_a_few_lines_of_key_facts(toy_ws, runner):
    r = ok(runner, "select", "-w", toy_ws, "--strategy", "random", "--budget", "3")
    lines = r.stdout.splitlines()
    assert lines[0] == "batch 1: 3 picks (3 level-0), strategy random"
    assert any(line.split() == ["cost", "3", "of", "budget", "3"] for line in lines)
    assert any(line.strip().endswith("batch-0001.csv") for line in lines)
    assert "{" not in r.stdout and "timings_s" not in r.stdout and len(lines) <= 8


def test_fit_summary_has_no_raw_json(toy_ws, runner, toy_files, tmp_path):
    _, truth = toy_files
    ids = [f"t{i:06d}" for i in range(0, 400, 20)]
    write_batch(toy_ws, 1, ids, [0] * 8 + [1] * 12)
    res = tmp_path / "r1.parquet"
    ok(runner, "simulate", toy_ws / "batches" / "batch-0001.parquet", "--truth", truth, "-o", res)
    ok(runner, "ingest-results", "-w", toy_ws, res)
    r = ok(runner, "fit", "-w", toy_ws, "--restarts", "1")
    lines = r.stdout.splitlines()
    assert lines[0] == "model fitted on 20 results (level 0: 8, level 1: 12)"
    assert any("GP rate estimate" in line and "gamma 0.56:" in line for line in lines)
    assert any(line.split()[:2] == ["level", "1"] and "discrepancy sd" in line for line in lines)
    assert "{" not in r.stdout and "[" not in r.stdout


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_plain_progress_is_silent_for_a_quick_command(capsys):
    clock = FakeClock()
    update = console.plain_progress("fit: ", after_s=3, clock=clock)
    for done in range(5):
        clock.now = done * 0.5
        update("score pool", done, 4)
    assert capsys.readouterr().err == ""


def test_plain_progress_prints_a_few_lines_with_an_eta(capsys):
    clock = FakeClock()
    update = console.plain_progress("select: ", after_s=3, every_s=30, clock=clock)
    update("predict", 0, 1)
    clock.now = 1.0
    update("predict", 1, 1)
    for i in range(101):  # 100 steps of 1 s each
        clock.now = 1.0 + i
        update("greedy", i, 100)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "select: greedy: 2/100, 3 s elapsed, about 98 s left"
    assert lines[-1] == "select: greedy: 100/100, 101 s elapsed"
    assert 3 <= len(lines) <= 6  # a few lines, not one per step
    assert not any("predict" in line for line in lines)  # it ended before the threshold


def test_plain_progress_names_a_phase_that_is_the_command_once(capsys):
    clock = FakeClock()
    update = console.plain_progress("fit: ", after_s=3, clock=clock)
    update("fit", 0, 1)
    clock.now = 4.0
    update("fit", 1, 1)
    assert capsys.readouterr().err.splitlines() == ["fit: 1/1, 4 s elapsed"]  # not "fit: fit:"


def test_progress_is_plain_lines_off_a_terminal_and_nothing_when_quiet(capsys):
    with console.progress(True, "fit") as bar:
        assert bar is not None and bar.__qualname__.startswith("plain_progress")
    console.set_mode(quiet=True, json_out=False)
    try:
        with console.progress(True, "fit") as bar:
            assert bar is None
    finally:
        console.set_mode(quiet=False, json_out=False)


def test_enums_are_their_values_wherever_a_string_goes():
    assert defaults.Strategy.MCM_GP == "mcm-gp" and f"{defaults.Design.WITH_REPLACEMENT}" == (
        "with-replacement"
    )
    assert json.dumps({"s": defaults.STRATEGY}) == '{"s": "bams"}'
    assert all(
        issubclass(e, enum.StrEnum) for e in (defaults.Interval, defaults.Pooling, defaults.Greedy)
    )


def test_readme_documents_the_environment_variables():
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    used = set()
    for command in get_command(app).commands.values():  # type: ignore[attr-defined]
        for param in command.params:
            envvar = getattr(param, "envvar", None)
            if envvar:
                used.add(envvar)
    assert used >= {"BAMS_WORKSPACE", "BAMS_QUIET"}
    for name in sorted(used):
        assert name in readme, f"{name} is not in README.md"


TERMINATED_SELECT = """
import os, signal, sys
from bams_cli.state import workspace
real = workspace.Workspace.read_pool
def read_pool(self):  # a CI job's timeout arrives while the command works
    os.kill(os.getpid(), int(sys.argv[1]))
    return real(self)
workspace.Workspace.read_pool = read_pool
from bams_cli.cli import app
app(sys.argv[2:])
"""


@pytest.mark.parametrize("signum", [15, 1], ids=["TERM", "HUP"])
def test_sigterm_and_sighup_end_a_command_as_ctrl_c_does(toy_ws, runner, signum):
    # Python's default ended the process on the spot: no line said, exit -15, and the
    # workspace lock left for the next command to take over with a note.
    from tests.conftest import default_signals, tree_hash

    before = tree_hash(toy_ws)
    args = ["select", "-w", str(toy_ws), "--strategy", "random", "--budget", "2"]
    proc = subprocess.run(
        [sys.executable, "-c", TERMINATED_SELECT, str(signum), *args],
        capture_output=True,
        text=True,
        preexec_fn=default_signals,
    )
    name = {15: "SIGTERM", 1: "SIGHUP"}[signum]
    assert proc.returncode == 128 + signum, proc.stderr
    assert proc.stderr == f"error: stopped by {name}; files being written were discarded\n"
    assert tree_hash(toy_ws) == before
    r = ok(runner, *args)  # the lock was released: no note of a stale one taken over
    assert "lock" not in r.stderr
