"""State files: schema conformance, metadata, atomic writes, round trips (also Hypothesis)."""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bams_cli import __version__
from bams_cli.core.reduce import Reducer
from bams_cli.errors import SchemaError, SettingsError
from bams_cli.settings import Level, Settings
from bams_cli.state import io, schemas
from bams_cli.state.io import read_metadata, transaction

ids = st.text(min_size=1, max_size=12)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


def _rows(schema: pa.Schema, draw) -> dict:
    gen = {
        pa.string(): ids,
        pa.int64(): st.integers(-(2**40), 2**40),
        pa.float64(): finite,
        pa.bool_(): st.booleans(),
    }
    n = draw(st.integers(0, 6))
    return {f.name: draw(st.lists(gen[f.type], min_size=n, max_size=n)) for f in schema}


@pytest.mark.parametrize("state", schemas.ALL, ids=lambda s: s.name)
@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.data())
def test_every_state_file_round_trips(tmp_path: Path, state, data):
    cols = _rows(state.schema, data.draw)
    table = pa.table(cols, schema=state.schema)
    path = tmp_path / "f.parquet"
    with transaction() as tx:
        tx.write_parquet(path, state.conform(table, {"seed": 7}))
    back = state.check(pq.read_table(path), path)
    assert back.select(state.schema.names).to_pylist() == table.to_pylist()
    meta = read_metadata(path)
    assert meta["schema_version"] == str(state.version)
    assert meta["tool_version"] == __version__
    assert meta["seed"] == "7" and "command" in meta and "written_at" in meta


def test_conform_names_the_missing_column():
    with pytest.raises(SchemaError, match="observations.parquet: column 'fidelity'"):
        schemas.OBSERVATIONS.conform(pa.table({"segment_id": ["a"], "value": [1.0]}))


def test_check_names_a_wrong_type(tmp_path):
    p = tmp_path / "o.parquet"
    pq.write_table(pa.table({"segment_id": [1], "mu": [1.0], "sd": [1.0]}), p)
    with pytest.raises(SchemaError, match="column 'segment_id': expected type string, got int64"):
        schemas.SCORES.check(pq.read_table(p), p)


def test_failed_transaction_leaves_no_file_and_keeps_the_old_one(tmp_path):
    target = tmp_path / "x.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), transaction() as tx:
        tx.write_text(target, "new")
        tx.write_text(tmp_path / "y.txt", "other")
        raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.txt"]


@settings(max_examples=50, deadline=None)
@given(
    gammas=st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=1, max_size=4, unique=True),
    costs=st.lists(st.floats(1e-4, 10, allow_nan=False), min_size=0, max_size=3),
    seed=st.integers(0, 2**31),
    dim=st.integers(1, 64),
)
def test_settings_round_trip(gammas, costs, seed, dim):
    levels = (Level("high", 1.0), *(Level(f"low{i}", c) for i, c in enumerate(costs, 1)))
    s = Settings(gammas=tuple(gammas), levels=levels, seed=seed, embedding_dim=dim).validate()
    back = Settings.from_toml(s.to_toml())
    assert back == s
    assert all(math.isfinite(g) for g in back.gammas)


@settings(max_examples=50, deadline=None)
@given(
    gammas=st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=1, max_size=4, unique=True),
    data=st.data(),
)
def test_settings_refuse_a_repeated_gamma_by_its_value(gammas, data):
    again = data.draw(st.sampled_from(gammas))
    at = data.draw(st.integers(0, len(gammas)))
    text = Settings(gammas=(*gammas[:at], again, *gammas[at:])).to_toml()
    with pytest.raises(SettingsError) as info:
        Settings.from_toml(text, source="ws/settings.toml")
    assert str(info.value) == (
        f"ws/settings.toml: gamma {again:g} is given more than once; give each failure "
        "threshold once"
    )


@settings(max_examples=20, deadline=None)
@given(
    D=st.integers(1, 8),
    d=st.integers(1, 4),
    method=st.sampled_from(["pca", "autoencoder", "identity"]),
)
def test_reducer_round_trip(D, d, method):
    rng = np.random.default_rng(0)
    layers = {"pca": 1, "autoencoder": 2, "identity": 0}[method]
    shapes = [(D, d)] if layers == 1 else [(D, 5), (5, d)][:layers]
    r = Reducer(
        method,
        rng.standard_normal(D),
        rng.random(D) + 0.5,
        weights=[rng.standard_normal(s) for s in shapes],
        biases=[rng.standard_normal(s[1]) for s in shapes],
        reconstruction_error={"pca": 0.25},
    )
    back = Reducer.from_arrays(r.to_arrays())
    E = rng.standard_normal((7, D))
    np.testing.assert_array_equal(back.transform(E), r.transform(E))
    assert back.reconstruction_error == {"pca": 0.25}


CRASH = """
import os, sys
from pathlib import Path
from bams_cli.state import io

ws, crash_after = Path(sys.argv[1]), int(sys.argv[2])
real, renamed = os.replace, []

def replace(src, dst):
    # Die like kill -9 (no cleanup, no finally) after `crash_after` target renames.
    if len(renamed) == crash_after and ".bams-journal" not in str(dst):
        os._exit(9)
    real(src, dst)
    if ".bams-journal" not in str(dst):
        renamed.append(dst)

io.os.replace = replace
with io.journal_in(ws), io.transaction() as tx:
    for name in ("a", "b", "c"):
        tx.write_text(ws / "sub" / name, "new " + name)
"""


@pytest.mark.parametrize("crash_after", [0, 1, 2])
def test_a_commit_killed_among_its_renames_is_completed_by_recover(tmp_path, crash_after):
    ws = tmp_path / "ws"
    (ws / "sub").mkdir(parents=True)
    for name in "abc":
        (ws / "sub" / name).write_text("old " + name)
    out = subprocess.run([sys.executable, "-c", CRASH, str(ws), str(crash_after)])
    assert out.returncode == 9
    # Killed mid-commit: some files new, some old, the journal names all three.
    texts = [(ws / "sub" / n).read_text() for n in "abc"]
    assert texts == [f"new {n}" for n in "abc"[:crash_after]] + [
        f"old {n}" for n in "abc"[crash_after:]
    ]
    assert (ws / io.JOURNAL_NAME).exists()
    assert io.recover(ws) == 3 - crash_after
    assert [(ws / "sub" / n).read_text() for n in "abc"] == [f"new {n}" for n in "abc"]
    assert not (ws / io.JOURNAL_NAME).exists()
    assert not list(ws.rglob(".tmp-*"))
    assert io.recover(ws) == 0  # idempotent


@pytest.mark.parametrize("how", ["copied", "moved"])
def test_a_killed_commit_in_a_copied_workspace_is_completed_in_the_copy_alone(tmp_path, how):
    # A user copies (or moves) a workspace whose last command was killed mid-commit, then
    # runs the next command in the copy: its own staged files land, and nothing outside it
    # (the original's files, or files at the old path) is renamed or removed.
    ws = tmp_path / "ws"
    (ws / "sub").mkdir(parents=True)
    for name in "abc":
        (ws / "sub" / name).write_text("old " + name)
    assert subprocess.run([sys.executable, "-c", CRASH, str(ws), "1"]).returncode == 9
    copy = tmp_path / "copy"
    shutil.copytree(ws, copy) if how == "copied" else ws.rename(copy)
    before = {
        p: p.read_text() for p in tmp_path.rglob("*") if p.is_file() and copy not in p.parents
    }
    assert io.recover(copy) == 2
    assert [(copy / "sub" / n).read_text() for n in "abc"] == [f"new {n}" for n in "abc"]
    assert not list(copy.rglob(".tmp-*")) and not (copy / io.JOURNAL_NAME).exists()
    after = {p: p.read_text() for p in tmp_path.rglob("*") if p.is_file() and copy not in p.parents}
    assert after == before  # the original (when copied) exactly as the crash left it


def test_a_journaled_removal_in_a_copied_workspace_removes_the_copy_s_file(tmp_path, monkeypatch):
    ws, copy = tmp_path / "ws", tmp_path / "copy"
    ws.mkdir()
    (ws / "gone").write_text("old")
    real = io.os.replace

    def killed(src, dst):  # the journal lands; the first rename of the commit is "killed"
        if io.JOURNAL_NAME not in str(dst):
            raise KeyboardInterrupt
        real(src, dst)

    with io.journal_in(ws):
        tx = io.Transaction()
        tx.write_text(ws / "a", "new")
        tx.remove(ws / "gone")
        monkeypatch.setattr(io.os, "replace", killed)
        with pytest.raises(KeyboardInterrupt):
            tx.commit()
        monkeypatch.setattr(io.os, "replace", real)
    shutil.copytree(ws, copy)
    assert json.loads((copy / io.JOURNAL_NAME).read_text())["renames"][1] == [None, "gone"]
    assert io.recover(copy) == 1
    assert (copy / "a").read_text() == "new" and not (copy / "gone").exists()
    assert (ws / "gone").read_text() == "old" and not (ws / "a").exists()


def test_recover_removes_files_staged_by_a_transaction_that_never_committed(tmp_path):
    ws = tmp_path / "ws"
    (ws / "sub").mkdir(parents=True)
    (ws / "sub" / "a").write_text("old")
    tx = io.Transaction()
    tx.write_text(ws / "sub" / "a", "new")
    tx.write_text(ws / "b", "new")  # ... and the process died before commit
    assert len(list(ws.rglob(".tmp-*"))) == 2
    assert io.recover(ws) == 0
    assert (ws / "sub" / "a").read_text() == "old" and not (ws / "b").exists()
    assert not list(ws.rglob(".tmp-*"))


def test_a_staged_removal_lands_with_the_writes_and_the_last_staging_of_a_file_wins(tmp_path):
    for name in ("b", "c"):
        (tmp_path / name).write_text("old")
    with io.journal_in(tmp_path), transaction() as tx:
        tx.write_text(tmp_path / "a", "first")
        tx.write_text(tmp_path / "a", "second")
        tx.write_text(tmp_path / "b", "new")
        tx.remove(tmp_path / "b")
        tx.remove(tmp_path / "c")
        tx.write_text(tmp_path / "c", "new")
        tx.remove(tmp_path / "nowhere")  # nothing to remove: nothing happens
        assert tx.staged(tmp_path / "b") and not tx.staged(tmp_path / "d")
        assert (tmp_path / "b").read_text() == "old"  # nothing lands before the commit
    assert (tmp_path / "a").read_text() == "second" and (tmp_path / "c").read_text() == "new"
    assert not (tmp_path / "b").exists() and not (tmp_path / "nowhere").exists()
    assert not list(tmp_path.rglob(".tmp-*")) and not (tmp_path / io.JOURNAL_NAME).exists()


def test_a_journaled_removal_is_completed_by_recover(tmp_path):
    (tmp_path / "gone").write_text("old")
    tx = io.Transaction()
    tx.write_text(tmp_path / "a", "new")
    tx.remove(tmp_path / "gone")
    pairs = [[None if tmp is None else str(tmp), str(target)] for tmp, target in tx._staged]
    (tmp_path / io.JOURNAL_NAME).write_text(json.dumps({"renames": pairs}))  # then: killed
    assert io.recover(tmp_path) == 1
    assert (tmp_path / "a").read_text() == "new" and not (tmp_path / "gone").exists()
    assert not (tmp_path / io.JOURNAL_NAME).exists() and not list(tmp_path.rglob(".tmp-*"))


def test_a_single_file_commit_needs_no_journal(tmp_path, monkeypatch):
    seen = []
    real = io.os.replace
    monkeypatch.setattr(io.os, "replace", lambda s, d: (seen.append(Path(d).name), real(s, d)))
    with io.journal_in(tmp_path), io.transaction() as tx:
        tx.write_text(tmp_path / "a", "x")
    assert seen == ["a"]


def _durable_order(monkeypatch):
    """Record every fsync (of which file or folder) and every rename, in call order."""
    events: list[tuple] = []
    real_fsync, real_replace, real_rename = io.os.fsync, io.os.replace, io.os.rename

    def ident(st):
        return (st.st_dev, st.st_ino)

    def fsync(fd):
        events.append(("fsync", ident(os.fstat(fd))))
        real_fsync(fd)

    def rename_with(real):
        def move(src, dst):
            events.append(("rename", ident(os.stat(src)), Path(dst)))
            real(src, dst)

        return move

    monkeypatch.setattr(io.os, "fsync", fsync)
    monkeypatch.setattr(io.os, "replace", rename_with(real_replace))
    monkeypatch.setattr(io.os, "rename", rename_with(real_rename))
    return events


def _assert_fsync_rename_fsync(events, renamed: int) -> None:
    """Each renamed file was fsynced before its rename, and its folder after it."""
    moves = [(i, e[1], e[2]) for i, e in enumerate(events) if e[0] == "rename"]
    assert len(moves) == renamed
    for at, file, target in moves:
        folder = os.stat(target.parent)
        synced = [i for i, e in enumerate(events) if e[0] == "fsync" and e[1] == file]
        assert synced and synced[0] < at, f"{target.name}: renamed before its data was fsynced"
        dir_synced = [
            i
            for i, e in enumerate(events)
            if e[0] == "fsync" and e[1] == (folder.st_dev, folder.st_ino)
        ]
        assert any(i > at for i in dir_synced), f"{target.name}: folder not fsynced after rename"


WRITERS = {
    "parquet": lambda tx, p: tx.write_parquet(p, pa.table({"a": [1, 2]})),
    "bytes": lambda tx, p: tx.write_bytes(p, b"x"),
    "text": lambda tx, p: tx.write_text(p, "x"),
    "with": lambda tx, p: tx.write_with(p, lambda tmp: Path(tmp).write_bytes(b"x")),
}


@pytest.mark.parametrize("how", WRITERS)
@pytest.mark.parametrize("journal", [False, True])
def test_every_file_is_fsynced_before_its_rename_and_its_folder_after(
    tmp_path, monkeypatch, how, journal
):
    # Three files in two folders: with the journal that is four renames (journal included).
    targets = [tmp_path / "a", tmp_path / "sub" / "b", tmp_path / "sub" / "c"]
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "b").write_text("old")
    events = _durable_order(monkeypatch)
    with io.journal_in(tmp_path) if journal else contextlib.nullcontext():
        with transaction() as tx:
            for target in targets:
                WRITERS[how](tx, target)
    _assert_fsync_rename_fsync(events, renamed=len(targets) + journal)
    assert all(t.exists() for t in targets) and not list(tmp_path.rglob(".tmp-*"))


def test_recover_fsyncs_the_folders_it_renames_into(tmp_path, monkeypatch):
    (tmp_path / "sub").mkdir()
    events = _durable_order(monkeypatch)
    tx = io.Transaction()
    tx.write_text(tmp_path / "a", "new")
    tx.write_text(tmp_path / "sub" / "b", "new")
    pairs = [[str(tmp), str(target)] for tmp, target in tx._staged]
    (tmp_path / io.JOURNAL_NAME).write_text(json.dumps({"renames": pairs}))  # then: killed
    assert io.recover(tmp_path) == 2
    _assert_fsync_rename_fsync(events, renamed=2)


def test_remove_strays_takes_only_dead_processes_files_for_that_target(tmp_path):
    import subprocess
    import sys

    from bams_cli.state.io import remove_strays

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    pid = int(dead.stdout)
    target = tmp_path / "next.csv"
    gone = tmp_path / f".tmp-next.csv-{pid}-0"
    mine = tmp_path / f".tmp-next.csv-{os.getpid()}-0"  # a live writer's: kept
    other = tmp_path / f".tmp-other.csv-{pid}-0"  # another target's: kept
    for p in (gone, mine, other):
        p.write_text("x")
    assert remove_strays(target) == 1
    assert not gone.exists() and mine.exists() and other.exists()
