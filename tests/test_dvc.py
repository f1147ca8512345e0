"""examples/dvc.yaml drives the loop of examples/Makefile: its stages chain through their
deps and outs, every command is a bams-cli invocation with options that exist, and run in
the order DVC would run them they carry a study from an empty folder to its report.

DVC itself is not a dependency: the file is read by a reader of the YAML subset it is
written in (checked against PyYAML where that happens to be installed), and the stages
are run by the shell, in file order, as `dvc repro` runs them on a fresh project.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import typer.main
from typer.testing import CliRunner

from bams_cli.cli import app
from bams_cli.settings import Settings, levels_from_costs
from tests.conftest import write_toy

ROOT = Path(__file__).resolve().parent.parent
DVC_YAML = ROOT / "examples" / "dvc.yaml"
BIN = Path(sys.executable).parent

# ---- a reader of the YAML subset dvc.yaml is written in -------------------------------------


def _scalar(text: str) -> Any:
    return int(text) if re.fullmatch(r"-?\d+", text) else text


def _lines(text: str) -> list[tuple[int, str]]:
    out = []
    for raw in text.splitlines():
        if raw.strip() and not raw.lstrip().startswith("#"):
            out.append((len(raw) - len(raw.lstrip(" ")), raw.strip()))
    return out


def _block(lines: list[tuple[int, str]], i: int, indent: int) -> tuple[Any, int]:
    """The mapping or list whose lines start at ``indent``, from line i; (value, next i)."""
    if lines[i][1].startswith("- "):
        items = []
        while i < len(lines) and lines[i][0] == indent and lines[i][1].startswith("- "):
            rest = lines[i][1][2:]
            if re.match(r"^[\w-]+:( |$)", rest):  # an item that is a mapping
                sub = [(indent + 2, rest)]
                j = i + 1
                while j < len(lines) and lines[j][0] > indent:
                    sub.append(lines[j])
                    j += 1
                value, _ = _block(sub, 0, indent + 2)
                items.append(value)
                i = j
            else:
                items.append(_scalar(rest))
                i += 1
        return items, i
    mapping: dict[str, Any] = {}
    while i < len(lines) and lines[i][0] == indent:
        key, _, rest = lines[i][1].partition(":")
        assert key not in mapping, f"{key} twice"
        if rest.strip():
            mapping[key] = _scalar(rest.strip())
            i += 1
        else:
            assert lines[i + 1][0] > indent, f"{key}: empty block"
            mapping[key], i = _block(lines, i + 1, lines[i + 1][0])
    return mapping, i


def read_dvc_yaml(path: Path) -> dict[str, Any]:
    lines = _lines(path.read_text())
    doc, end = _block(lines, 0, 0)
    assert end == len(lines), f"{path}: line {end + 1} not understood: {lines[end][1]}"
    return doc


def _stages(doc: dict[str, Any], **override: Any) -> dict[str, dict[str, list[str]]]:
    """Every stage's cmd, deps and outs as lists, ${var} substituted (``vars`` < override)."""
    values = {k: v for d in doc["vars"] for k, v in d.items()} | override

    def sub(text: str) -> str:
        return re.sub(r"\$\{(\w+)\}", lambda m: str(values[m.group(1)]), text)

    out = {}
    for name, stage in doc["stages"].items():
        assert set(stage) <= {"cmd", "deps", "outs"}, name
        cmd = stage["cmd"] if isinstance(stage["cmd"], list) else [stage["cmd"]]
        out[name] = {key: [sub(v) for v in stage.get(key, [])] for key in ("deps", "outs")}
        out[name]["cmd"] = [sub(c) for c in cmd]
    return out


# ---- the checks -----------------------------------------------------------------------------


def test_the_reader_agrees_with_pyyaml_where_installed():
    yaml = pytest.importorskip("yaml", reason="PyYAML is not a dependency; the reader is")
    assert yaml.safe_load(DVC_YAML.read_text()) == read_dvc_yaml(DVC_YAML)


def test_every_stage_command_is_a_bams_cli_call_with_options_that_exist():
    stages = _stages(read_dvc_yaml(DVC_YAML))
    commands = typer.main.get_command(app).commands  # type: ignore[attr-defined]
    runner = CliRunner()
    used = set()
    for name, stage in stages.items():
        for cmd in stage["cmd"]:
            argv = shlex.split(cmd)
            if ">" in argv:  # the --json summary, written as the stage's stamp
                k = argv.index(">")
                assert argv[k + 1] in stage["outs"] and "--json" in argv, cmd
                argv = argv[:k]
            if argv[:2] == ["mkdir", "-p"]:  # the folder the stamps go to
                continue
            assert argv[0] == "bams-cli", f"{name}: {cmd}"
            sub = argv[1]
            assert sub in commands, f"{name}: no subcommand {sub!r}"
            options = {o for p in commands[sub].params for o in p.opts + p.secondary_opts}
            for token in argv[2:]:
                if token.startswith("-"):
                    assert token.split("=")[0] in options, f"{name}: {sub} has no {token}"
            used.add(sub)
    for sub in used:
        r = runner.invoke(app, [sub, "--help"])
        assert r.exit_code == 0 and "Usage" in r.stdout, sub
    # The Makefile's loop: every step of it has its stage.
    assert used == {"init", "embed-reduce", "select", "simulate", "ingest-results", "fit",
                    "estimate", "report"}  # fmt: skip
    assert sum("--plan" in c for s in stages.values() for c in s["cmd"]) == 2  # two stages


def test_stages_chain_through_their_deps_and_outs():
    stages = _stages(read_dvc_yaml(DVC_YAML))
    made: dict[str, str] = {}
    for name, stage in stages.items():  # in file order, which is an order DVC may run
        for dep in stage["deps"]:
            assert dep in made or dep.startswith("sample_data/"), f"{name}: {dep} from nowhere"
        assert name == "init" or any(dep in made for dep in stage["deps"]), name
        for out in stage["outs"]:
            assert out not in made, f"{out}: out of {made.get(out)} and {name}"
            # Outputs live outside the workspace: DVC deletes a stage's outs before it
            # runs, and bams-cli owns (and atomically rewrites) everything in the workspace.
            assert out.startswith("study-sim/"), f"{name}: {out}"
            made[out] = name
        # A file a command writes (--out, -o, > ...) is declared as one of the stage's outs.
        for cmd in stage["cmd"]:
            argv = shlex.split(cmd)
            for flag in ("--out", "-o", ">"):
                if flag in argv:
                    assert argv[argv.index(flag) + 1] in stage["outs"], f"{name}: {cmd}"
    assert list(stages)[-1] == "report"


@pytest.mark.slow
def test_the_stages_run_in_order_carry_a_study_to_its_report(tmp_path):
    write_toy(tmp_path / "data", n=400)
    settings = Settings(
        gammas=(0.56,), levels=levels_from_costs([1.0, 0.1]), seed=0, embedding_dim=2
    )
    (tmp_path / "data" / "settings.toml").write_text(settings.to_toml())
    stages = _stages(read_dvc_yaml(DVC_YAML), data="data", samples=30)
    env = os.environ | {"PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}"}
    for name, stage in stages.items():
        for cmd in stage["cmd"]:
            r = subprocess.run(
                cmd, shell=True, cwd=tmp_path, env=env, capture_output=True, text=True
            )
            assert r.returncode == 0, f"{name}: {cmd}\n{r.stdout[-2000:]}{r.stderr[-2000:]}"
        for out in stage["outs"]:
            assert (tmp_path / out).stat().st_size > 0, f"{name}: {out}"
    sim = tmp_path / "study-sim"
    for n in (1, 2, 3):  # the stable --out targets are the batches' hand-offs
        csv = tmp_path / "study" / "batches" / f"batch-000{n}.csv"
        assert (sim / f"batch-000{n}.csv").read_bytes() == csv.read_bytes()
    estimate = json.loads((sim / "estimate.json").read_text())
    doc = json.loads((tmp_path / "study" / "estimates" / "estimate-0002.json").read_text())
    assert doc["design"] == "staged" and doc["staging"]["plans"] == [1, 2]
    assert doc["staging"]["stages_done"] == doc["staging"]["stages"] == 2  # the whole estimate
    assert estimate["estimates"][0]["p_hat"] == doc["estimates"][0]["p_hat"] >= 0
    assert (tmp_path / "study" / "report" / "summary.md").exists()
