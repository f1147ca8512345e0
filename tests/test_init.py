"""init: a failure threshold is required; --exist-ok makes a re-run of the same init a no-op."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.conftest import invoke, ok, tree_hash

ROOT = Path(__file__).resolve().parents[1]
TOY = ROOT / "sample_data" / "toy2d" / "settings.toml"
FLAGS = ["--gamma", "0.56", "--costs", "1,0.1", "--dim", "2", "--seed", "4"]


@pytest.mark.parametrize("flags", [[], ["--costs", "1,0.1", "--seed", "2"]])
def test_init_without_a_threshold_names_the_flag(runner, tmp_path, flags):
    r = invoke(runner, "init", "-w", tmp_path / "ws", *flags)
    assert r.exit_code == 1 and "pass --gamma" in r.stderr and "--settings-from" in r.stderr
    assert r.stderr.count("\n") == 1 and not (tmp_path / "ws").exists()


@pytest.mark.parametrize("source", [FLAGS, ["--settings-from", str(TOY)]])
def test_exist_ok_rerun_of_the_same_init_changes_nothing(runner, tmp_path, source):
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, *source, "--exist-ok")  # a new workspace: created
    before, mtime = tree_hash(ws), (ws / "settings.toml").stat().st_mtime_ns
    r = ok(runner, "init", "-w", ws, *source, "--exist-ok")
    assert "already holds these settings; nothing changed" in r.stdout
    summary = json.loads(ok(runner, "init", "-w", ws, *source, "--exist-ok", "--json").stdout)
    assert summary["unchanged"] is True
    assert tree_hash(ws) == before and (ws / "settings.toml").stat().st_mtime_ns == mtime
    r = invoke(runner, "init", "-w", ws, *source)  # without --exist-ok it still refuses
    assert r.exit_code == 1 and "already exists" in r.stderr and "--exist-ok" in r.stderr


@pytest.mark.parametrize(
    ("flags", "needle"),
    [
        (["--gamma", "0.5", "--costs", "1,0.1", "--dim", "2", "--seed", "4"],
         "gammas: 0.56 in the file, 0.5 requested"),
        (["--gamma", "0.56", "--dim", "2", "--seed", "4"],
         "levels (costs): high 1, low1 0.1 in the file, high 1 requested"),
        (["--gamma", "0.56", "--costs", "1,0.1", "--dim", "2"], "seed: 4 in the file, 0 requested"),
    ],
)  # fmt: skip
def test_exist_ok_with_other_settings_names_the_difference(runner, tmp_path, flags, needle):
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, *FLAGS)
    before = tree_hash(ws)
    r = invoke(runner, "init", "-w", ws, *flags, "--exist-ok")
    assert r.exit_code == 1 and needle in r.stderr and "--force" in r.stderr, r.stderr
    assert r.stderr.count("\n") == 1 and tree_hash(ws) == before


def test_force_and_exist_ok_contradict(runner, tmp_path):
    r = invoke(runner, "init", "-w", tmp_path / "ws", *FLAGS, "--force", "--exist-ok")
    assert r.exit_code == 1 and "pass one of them" in r.stderr
    assert not (tmp_path / "ws").exists()
