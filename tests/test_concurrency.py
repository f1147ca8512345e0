"""Concurrent writers on one workspace: with --wait all succeed, without it each succeeds or
is refused naming the holder (exit code 1); nothing is lost and the state stays usable."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from bams_cli.state.lock import LOCK_FILE
from tests.conftest import ok, write_toy

BAMS = [sys.executable, "-m", "bams_cli"]
REFUSAL = re.compile(r"locked by pid (\d+) on \S+ \(.*\); wait for it to finish or pass --wait")
PARTS = 3  # results files ingested concurrently


@pytest.fixture
def study(tmp_path: Path) -> tuple[Path, list[Path]]:
    """A workspace with batch 1 drawn and part of its results ingested (so `fit` can run),
    and the rest of its results split into PARTS files of disjoint rows."""
    runner = CliRunner()
    seg, truth = write_toy(tmp_path / "data", n=300)
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.56", "--costs", "1,0.1", "--dim", "2")
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize")  # fmt: skip
    ok(runner, "select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", 12)
    results = tmp_path / "results.parquet"
    ok(runner, "simulate", ws / "batches/batch-0001.parquet", "--truth", truth, "-o", results)
    table = pq.read_table(results)
    n = table.num_rows
    cuts = [0, n // 4] + [n // 4 + (n - n // 4) * (k + 1) // PARTS for k in range(PARTS)]
    files = []
    for k in range(PARTS + 1):
        path = tmp_path / f"part-{k}.parquet"
        pq.write_table(table.slice(cuts[k], cuts[k + 1] - cuts[k]), path)
        files.append(path)
    ok(runner, "ingest-results", "-w", ws, files[0])
    return ws, files[1:]


def _writers(ws: Path, parts: list[Path]) -> list[list[str]]:
    w = str(ws)
    return [
        *[["ingest-results", "-w", w, str(p)] for p in parts],
        ["fit", "-w", w],
        ["select", "-w", w, "--strategy", "random", "--budget", "3", "--allow-pending"],
    ]


def _start(argv: list[str]) -> subprocess.Popen:
    return subprocess.Popen([*BAMS, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)  # fmt: skip


def _rows(path: Path) -> set[tuple]:
    t = pq.read_table(path, columns=["segment_id", "fidelity", "value"])
    return set(zip(t["segment_id"].to_pylist(), t["fidelity"].to_pylist(),
                   t["value"].to_pylist(), strict=True))  # fmt: skip


def _consistent(ws: Path) -> None:
    """The state every later command reads: status runs, and a refit succeeds."""
    s = subprocess.run([*BAMS, "status", "-w", str(ws), "--json"], capture_output=True,
                       text=True)  # fmt: skip
    assert s.returncode in (0, 3), s.stderr
    assert not json.loads(s.stdout).get("commit_in_progress")
    assert not list(ws.rglob(".tmp-*")) and not (ws / ".bams-journal.json").exists()
    f = subprocess.run([*BAMS, "fit", "-w", str(ws)], capture_output=True, text=True)
    assert f.returncode == 0, f.stderr


def test_concurrent_writers_with_wait_all_succeed_and_nothing_is_lost(study):
    ws, parts = study
    before = _rows(ws / "observations.parquet")
    procs = [_start([*argv, "--wait"]) for argv in _writers(ws, parts)]
    for proc in procs:
        out, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, f"{proc.args}: {err}"
    got = _rows(ws / "observations.parquet")
    assert before | set().union(*(_rows(p) for p in parts)) == got
    assert (ws / "batches/batch-0002.parquet").exists()
    _consistent(ws)


@pytest.mark.slow  # about 20 s: make test ran 812 s on a clean clone (budget 600)
def test_concurrent_writers_without_wait_succeed_or_name_the_holder(study):
    ws, parts = study
    before = _rows(ws / "observations.parquet")
    writers = _writers(ws, parts)
    procs = [_start(argv) for argv in writers]
    pids = {p.pid for p in procs}
    done = []
    for argv, proc in zip(writers, procs, strict=True):
        out, err = proc.communicate(timeout=300)
        if proc.returncode == 0:
            done.append(argv)
            continue
        assert proc.returncode == 1 and err.count("\n") == 1, f"{argv}: {err}"
        m = REFUSAL.search(err)
        assert m and int(m.group(1)) in pids - {proc.pid}, f"{argv}: {err}"
    assert done, "no writer succeeded"
    print(f"without --wait: {len(done)} of {len(writers)} writers succeeded, the rest refused")
    ingested = [Path(a[3]) for a in done if a[0] == "ingest-results"]
    expected = before | set().union(set(), *(_rows(p) for p in ingested))
    assert _rows(ws / "observations.parquet") == expected  # refused ones added nothing
    # The refused writers, run again, succeed: nothing they would have written is lost.
    for argv in writers:
        if argv not in done:
            r = subprocess.run([*BAMS, *argv], capture_output=True, text=True)
            assert r.returncode == 0, f"{argv}: {r.stderr}"
    assert _rows(ws / "observations.parquet") == before | set().union(*(_rows(p) for p in parts))
    _consistent(ws)


def _holder_pid(ws: Path) -> int | None:
    try:
        record = json.loads((ws / LOCK_FILE).read_text().strip() or "{}")
    except (FileNotFoundError, ValueError):
        return None
    return record.get("pid")


@pytest.mark.slow  # about 20 s: make test ran 812 s on a clean clone (budget 600)
def test_writers_started_while_one_holds_the_lock_are_refused_naming_it_then_wait(study):
    ws, parts = study
    holder = _start(["fit", "-w", str(ws), "--restarts", "40"])  # seconds of work
    deadline = time.monotonic() + 120
    while _holder_pid(ws) != holder.pid:
        assert holder.poll() is None and time.monotonic() < deadline, holder.stderr
        time.sleep(0.05)
    refused = [_start(argv) for argv in _writers(ws, parts)[:-2]]
    waiting = [_start([*argv, "--wait"]) for argv in _writers(ws, parts)[:-2]]
    for proc in refused:
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 1 and f"locked by pid {holder.pid} on " in err, err
    assert holder.poll() is None, "the holder finished before every refusal: raise --restarts"
    for proc in [*waiting, holder]:
        _, err = proc.communicate(timeout=300)
        assert proc.returncode == 0, err
    before_parts = _rows(ws / "observations.parquet")
    assert before_parts >= set().union(*(_rows(p) for p in parts))
    _consistent(ws)
