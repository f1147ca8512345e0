"""Project-level promises: README documents every command, core stays free of I/O libraries."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.main import get_command

import bams_cli
from bams_cli.cli import app
from tests.conftest import invoke, ok, tree_hash

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = sorted(get_command(app).commands)  # type: ignore[attr-defined]


def test_readme_opens_with_the_two_commands_and_documents_every_command():
    readme = (ROOT / "README.md").read_text()
    first_block = re.search(r"```(?:bash|sh)?\n(.*?)```", readme, re.S)
    assert first_block is not None
    assert [line.strip() for line in first_block.group(1).strip().splitlines()] == [
        "make demo",
        "make test",
    ]
    for name in COMMANDS:
        assert re.search(rf"^#+ .*`{name}`", readme, re.M), f"README has no section for `{name}`"
        assert f"bams-cli {name}" in readme, f"README has no example of `bams-cli {name}`"


@pytest.mark.parametrize("name", COMMANDS)
def test_every_command_help_has_a_runnable_example(runner, name):
    r = invoke(runner, name, "--help")
    assert r.exit_code == 0
    assert "Example" in r.stdout and f"bams-cli {name}" in r.stdout


def test_top_level_help_lists_every_command(runner):
    r = invoke(runner, "--help")
    for name in COMMANDS:
        assert name in r.stdout


CORE = sorted(p.stem for p in (ROOT / "bams_cli" / "core").glob("*.py") if p.stem != "__init__")


BLOCK = """
import importlib.abc, sys
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in {'polars', 'pyarrow', 'typer', 'rich'}:
            raise ModuleNotFoundError(name)
sys.meta_path.insert(0, Block())
"""


@pytest.mark.parametrize("module", CORE)
def test_core_modules_work_without_io_or_cli_libraries(module):
    # scikit-learn picks up rich on its own when it is installed; blocking the libraries
    # outright proves core neither imports them nor needs them.
    code = BLOCK + f"import bams_cli.core.{module}\nprint('ok')"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.strip() == "ok", (
        f"bams_cli.core.{module}: {out.stderr.strip().splitlines()[-1:]}"
    )


def test_cli_starts_without_the_numerical_stack():
    # Every command pays the CLI's import time; scikit-learn and SciPy alone took ~2-5 s.
    # They load inside the commands that use them.
    code = (
        "import sys, bams_cli.cli\n"
        "heavy = {'sklearn', 'scipy', 'matplotlib', 'numba', 'dask', 'distributed'}\n"
        "print(sorted(heavy & {m.split('.')[0] for m in sys.modules}))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


@pytest.mark.parametrize("flag", ["--version", "-V"])
def test_python_dash_m_runs(tmp_path, flag):
    out = subprocess.run([sys.executable, "-m", "bams_cli", flag], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == f"bams-cli {bams_cli.__version__}"


def test_sample_data_generator_is_deterministic(tmp_path):
    for run in ("a", "b"):
        subprocess.run(
            [
                sys.executable,
                str(ROOT / "sample_data" / "generate.py"),
                "toy2d",
                "--n",
                "300",
                "--out",
                str(tmp_path / run),
            ],
            check=True,
            capture_output=True,
        )
    for name in ("segments.parquet", "truth.parquet"):
        assert pq.read_table(tmp_path / "a" / name).equals(pq.read_table(tmp_path / "b" / name))
    # the committed toy2d files are what the generator makes
    committed = pq.read_table(ROOT / "sample_data" / "toy2d" / "truth.parquet")
    assert committed.num_rows == 20_000
    rate = float(np.mean(committed.column("value_0").to_numpy() <= 0.56))
    assert 0.003 < rate < 0.007


def test_simulate_answers_a_handoff_from_truth(runner, toy_files, tmp_path):
    import pyarrow as pa

    _, truth = toy_files
    handoff = tmp_path / "h.csv"
    handoff.write_text("segment_id,fidelity\nt000003,1\nt000001,0\n")
    out = tmp_path / "res.parquet"
    r = invoke(runner, "simulate", handoff, "--truth", truth, "-o", out)
    assert r.exit_code == 0, r.output
    res = pq.read_table(out).to_pylist()
    t = pq.read_table(truth).to_pylist()
    assert res == [
        {"segment_id": "t000003", "fidelity": 1, "value": t[3]["value_1"]},
        {"segment_id": "t000001", "fidelity": 0, "value": t[1]["value_0"]},
    ]
    bad = tmp_path / "bad.parquet"
    pq.write_table(pa.table({"segment_id": ["zzz"], "fidelity": [0]}), bad)
    r = invoke(runner, "simulate", bad, "--truth", truth, "-o", tmp_path / "o.parquet")
    assert r.exit_code == 1 and "column 'segment_id', row 1: segment id 'zzz' is not in" in r.stderr
    assert not (tmp_path / "o.parquet").exists()
    for target in (handoff, truth):  # answering into an input would destroy it
        before = target.read_bytes()
        r = invoke(runner, "simulate", handoff, "--truth", truth, "-o", target)
        assert r.exit_code == 1 and "would overwrite an input" in r.stderr
        assert target.read_bytes() == before


def test_simulate_refuses_to_write_over_workspace_state(toy_ws, runner, toy_files):
    _, truth = toy_files
    handoff = toy_ws.parent / "h.csv"
    handoff.write_text("segment_id,fidelity\nt000001,0\n")
    before = tree_hash(toy_ws)
    for target in (toy_ws / "segments.parquet", toy_ws / "batches" / "batch-0001.parquet"):
        r = invoke(runner, "simulate", handoff, "--truth", truth, "-o", target)
        assert r.exit_code == 1 and "a workspace's state" in r.stderr
    assert tree_hash(toy_ws) == before
    ok(runner, "simulate", handoff, "--truth", truth, "-o", toy_ws / "results" / "r.parquet")


def test_a_damaged_state_file_is_a_one_line_error_naming_it(toy_ws, runner):
    (toy_ws / "segments.parquet").write_bytes(b"PAR1 not really")
    before = tree_hash(toy_ws)
    r = invoke(runner, "select", "-w", toy_ws, "--strategy", "random", "--budget", "2")
    assert r.exit_code == 1 and len(r.stderr.strip().splitlines()) == 1
    assert "segments.parquet: damaged state file, not readable as Parquet" in r.stderr
    assert tree_hash(toy_ws) == before


def test_unexpected_errors_are_one_line_unless_debugging(toy_ws, runner, monkeypatch):
    from bams_cli import pipeline

    def broken(*args, **kwargs):
        raise ZeroDivisionError("float division\nby zero")

    monkeypatch.setattr(pipeline, "select", broken)
    r = invoke(runner, "select", "-w", toy_ws, "--strategy", "random", "--budget", "2")
    assert r.exit_code == 1
    assert r.stderr.splitlines() == [
        "error: ZeroDivisionError: float division by zero (unexpected: a damaged or "
        "hand-edited state file? rerun with BAMS_DEBUG=1 for the traceback)"
    ]
    monkeypatch.setenv("BAMS_DEBUG", "1")  # developers get the traceback
    with pytest.raises(ZeroDivisionError):
        invoke(runner, "select", "-w", toy_ws, "--strategy", "random", "--budget", "2")


def test_a_damaged_model_file_names_the_fix(toy_ws, runner):
    (toy_ws / "model.json").write_text("{not json")
    r = invoke(runner, "select", "-w", toy_ws, "--budget", "2")
    assert r.exit_code == 1
    assert "model.json: damaged (not a model written by fit); run `bams-cli fit" in r.stderr


def test_warnings_print_as_one_line_each(toy_ws, runner):
    import warnings

    from bams_cli import cli

    @cli.command("warn-twice")
    def _warn_twice() -> None:
        """Test-only command.\n\n[bold]Example[/]: bams-cli warn-twice"""
        warnings.warn("first\nhalf", RuntimeWarning, stacklevel=1)
        warnings.warn("second", UserWarning, stacklevel=1)

    try:
        r = invoke(runner, "warn-twice")
    finally:
        app.registered_commands.pop()
    assert r.exit_code == 0
    assert r.stderr.splitlines() == ["warning: first half", "warning: second"]


def test_a_negative_seed_is_refused(tmp_path, runner):
    r = invoke(runner, "init", "-w", tmp_path / "ws", "--gamma", "0.5", "--seed", "-1")
    assert r.exit_code == 2 and "--seed -1: seed must be an integer >= 0, got -1" in r.stderr
    assert not (tmp_path / "ws" / "settings.toml").exists()


@pytest.mark.parametrize("name", COMMANDS)
def test_help_paragraphs_come_out_whole_on_a_wide_terminal(runner, name, monkeypatch):
    # Rich help keeps a docstring's single newlines; wrapped source lines would break
    # every sentence at the source's width whatever the terminal's.
    monkeypatch.setenv("COLUMNS", "400")
    r = invoke(runner, name, "--help")
    doc = get_command(app).commands[name].help
    lines = [line.strip() for line in r.stdout.splitlines()]
    for paragraph in doc.split("\n\n"):
        plain = re.sub(r"\[/?[a-z ]*\]", "", paragraph)  # rich markup such as [bold]
        assert plain in lines, f"{name}: {plain[:60]!r} is not one line"


@pytest.mark.parametrize(
    ("name", "hint"),
    [
        ("benchmark", "[default: the committed sample data]"),
        ("benchmark", "[default: all]"),
        ("estimate", "[default: 5 x the GP's p x N, at least 100]"),
        ("estimate", "[default: the latest]"),
        ("select", "[default: all cores]"),
        ("embed-reduce", "[default: settings, auto]"),
    ],
)
def test_help_shows_bracketed_defaults_verbatim(runner, name, hint, monkeypatch):
    monkeypatch.setenv("COLUMNS", "400")  # rich would read them as markup tags
    assert hint in invoke(runner, name, "--help").stdout


def test_settings_errors_name_the_file(toy_ws, runner, toy_files):
    settings = toy_ws / "settings.toml"
    settings.write_text(settings.read_text().replace("seed = 0", "seed = -3"))
    r = invoke(runner, "select", "-w", toy_ws, "--strategy", "random", "--budget", "2")
    assert r.exit_code == 1
    assert r.stderr.strip() == f"error: {settings}: seed must be an integer >= 0, got -3"
    seg, _ = toy_files  # a binary file handed over as settings
    r = invoke(runner, "init", "-w", toy_ws.parent / "w2", "--settings-from", seg)
    assert r.exit_code == 1 and f"{seg}: not a TOML text file" in r.stderr


BROWSER_TEST = "tests/test_loop.py::test_report_renders_in_headless_chromium_with_every_image"


@pytest.mark.parametrize(
    ("require", "outcome"),
    [({}, "1 skipped"), ({"BAMS_REQUIRE_BROWSER": "1"}, "1 error"), ({"CI": "true"}, "1 error")],
)
def test_without_chromium_the_browser_test_skips_and_in_ci_fails(tmp_path, require, outcome):
    # `make test` installs nothing: on a machine without Chromium the browser test skips
    # with its reason (and before building the study it would render); CI must run it.
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "BAMS_REQUIRE_BROWSER", "PATH")}
    env.update(PATH=str(tmp_path), **require)  # an empty folder: no chromium on PATH
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", BROWSER_TEST],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert outcome in r.stdout, r.stdout + r.stderr
    assert "no chromium on PATH: the report's browser test needs Debian's chromium" in r.stdout
    assert ("CI must run this test" in r.stdout) == bool(require)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        (
            "study = 5\nlevels = [{name = 'high', cost = 1.0}]\n",
            "'study' must be a [study] table, got int 5",
        ),
        ("levels = 3\n[study]\ngammas = [0.5]\n", "'levels' must be a list of {name, cost} tables"),
        ("extra = 1\n[study]\ngammas = [0.5]\n", "'extra' must be an [extra] table"),
    ],
)
def test_a_settings_section_of_the_wrong_kind_is_named(text, needle):
    from bams_cli.errors import SettingsError
    from bams_cli.settings import Settings

    with pytest.raises(SettingsError, match=re.escape(needle)):
        Settings.from_toml(text, source="ws/settings.toml")


def test_the_workspace_promises_name_tests_that_exist():
    readme = (ROOT / "README.md").read_text()
    section = readme.split("### What the workspace promises", 1)[1].split("\n## ", 1)[0]
    named = re.findall(r"`(tests/[\w/]+\.py)(?:::(\w+))?`", section)
    assert len(named) >= 6
    for path, test in named:
        assert (ROOT / path).is_file(), path
        assert not test or f"def {test}(" in (ROOT / path).read_text(), (path, test)
