"""Every writing command SIGKILLed at random moments leaves the workspace as before or as after.

For each writing command a workspace is prepared in the state the command starts from
("before"), the command is run once uninterrupted from there ("after"), and then it is run
again and again and SIGKILLed at a random moment of its measured duration: the main pid
alone (its worker processes must die with it) or its whole process group (a job killed by
a scheduler). After each kill:

* ``status`` succeeds (exit code 0 or 3), whatever the kill left;
* the next writing command's first step (the lock, taken without ``--wait``, then
  ``recover``) succeeds: no lock outlives a killed holder;
* the workspace is then either exactly as before (every file byte-for-byte, ``tree_hash``)
  or the same as after the uninterrupted run, never in between; the observation log of
  "before" is the first rows of the log found;
* a killed run that left "before" is followed by the next kill on the same workspace, and
  every such chain (at most ``chain`` kills) ends with a run that is not killed and must
  succeed and reach "after".

A run that ends before its kill lands does not count as a kill, and the next kills aim
earlier; the kill counts printed are of runs that died by SIGKILL.

"The same as after" compares every file's content with its timestamps masked: Parquet
files by their rows and their key-value metadata, JSON, CSV, TOML, Markdown and HTML by
their text, ``.npz`` by their arrays. Timestamps (``written_at``, ``ingested_at``,
``abandoned_at``, the report's date) are the only thing a re-run may change; each command
runs at the same path as its reference run, so the command lines they record are equal.

The fast test starts each killed run as ``python -m bams_cli`` (3 kills per command; its
``status`` and re-runs, which are not killed, go through the fork server below). The slow
campaign (>= 50 kills per command) starts them from a fork server that has imported
bams_cli once, so its time goes to killing the commands' work rather than the ~1 s of
imports before it; the child calls ``setsid`` as ``start_new_session=True`` would.
"""

from __future__ import annotations

import csv
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from bams_cli.state.io import journal_in, recover
from bams_cli.state.lock import workspace_lock
from tests.conftest import STAGED_PLAN, tree_hash, write_toy

# ---- starting a command --------------------------------------------------------------------
SERVER = r"""
import json, os, sys
import bams_cli.cli

for line in sys.stdin:
    req = json.loads(line)
    pid = os.fork()
    if pid == 0:
        os.setsid()
        out = os.open(req["out"] or os.devnull, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
        os.dup2(out, 1)
        os.dup2(out, 2)
        sys.argv = [req["argv0"], *req["argv"]]
        code = 1
        try:
            bams_cli.cli.main()
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    print(pid, flush=True)
    _, status = os.waitpid(pid, 0)
    print(-os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status), flush=True)
"""


#: What ``python -m bams_cli`` has as ``sys.argv[0]``: the command line every written file
#: records is then the same whichever way a command was started.
ARGV0 = str(Path(__file__).resolve().parents[1] / "bams_cli" / "__main__.py")


class Started:
    """A running command: its pid (also its process group) and a way to wait for it."""

    def __init__(self, pid: int, wait: Callable[[], int]) -> None:
        self.pid = pid
        self.wait = wait


class Subprocesses:
    """Each command a fresh ``python -m bams_cli`` in its own session."""

    def start(self, argv: list[str], out: Path | None = None) -> Started:
        sink = open(out, "w") if out else subprocess.DEVNULL
        proc = subprocess.Popen(
            [sys.executable, "-m", "bams_cli", *argv],
            stdout=sink,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        if out:
            sink.close()  # type: ignore[union-attr]
        return Started(proc.pid, proc.wait)

    def close(self) -> None:
        pass


class ForkServer:
    """Each command a child forked (then ``setsid``) from a process that imported bams_cli."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", SERVER], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
        )

    def start(self, argv: list[str], out: Path | None = None) -> Started:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(
            json.dumps({"argv0": ARGV0, "argv": argv, "out": str(out) if out else None}) + "\n"
        )
        self.proc.stdin.flush()
        pid = int(self.proc.stdout.readline())
        stdout = self.proc.stdout
        return Started(pid, lambda: int(stdout.readline()))

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        self.proc.wait(timeout=30)


def run(launcher, argv: list[str], out: Path) -> tuple[int, str]:
    rc = launcher.start(argv, out).wait()
    return rc, out.read_text()


# ---- what "the same state" means -----------------------------------------------------------
TIME = re.compile(r"\d{4}-\d\d-\d\d[T ]\d\d:\d\d(:\d\d(\.\d+)?)?([+-]\d\d:?\d\d|Z| ?UTC)?")


def _masked(text: str) -> str:
    return TIME.sub("<time>", text)


def _content(path: Path) -> str:
    """A file's content with its timestamps masked (see the module docstring)."""
    if path.suffix == ".parquet":
        table = pq.read_table(path)
        meta = {k.decode(): v.decode() for k, v in (table.schema.metadata or {}).items()}
        rows = table.replace_schema_metadata(None).to_pylist()
        return _masked(json.dumps([str(table.schema), meta, rows], default=str))
    if path.suffix == ".npz":
        with np.load(path) as npz:
            return json.dumps({k: npz[k].tobytes().hex() for k in sorted(npz.files)})
    return _masked(path.read_text())


def snapshot(ws: Path) -> dict[str, str]:
    """Every file's masked content (the lock files left out, as in ``tree_hash``)."""
    if not ws.exists():
        return {}
    return {
        str(p.relative_to(ws)): _content(p)
        for p in sorted(ws.rglob("*"))
        if p.is_file() and not p.name.startswith(".bams.lock")
    }


def observation_rows(ws: Path) -> list[tuple]:
    path = ws / "observations.parquet"
    if not path.exists():
        return []
    t = pq.read_table(path, columns=["segment_id", "fidelity", "value", "source_sha256"])
    return list(zip(*(t[c].to_pylist() for c in t.column_names), strict=True))


# ---- the workspaces each command starts from -----------------------------------------------
@dataclass
class Case:
    name: str
    before: Path  # the workspace the command starts from (absent for init)
    argv: Callable[[Path], list[str]]  # the command line, given the workspace it runs on


def _ok(launcher, argv: list[str], log: Path) -> None:
    rc, out = run(launcher, argv, log)
    assert rc == 0, f"{argv}: {out}"


def prepare(base: Path, launcher) -> list[Case]:
    """The discovery loop on a 300-segment toy pool, keeping the workspace before each step."""
    data = base / "data"
    seg, truth = write_toy(data, n=300)
    ws = base / "ws"
    log = base / "prep.log"
    keep: dict[str, Path] = {}

    def step(name: str, argv: list[str]) -> None:
        if name:
            keep[name] = base / f"before-{name}"
            shutil.copytree(ws, keep[name], symlinks=True)
        _ok(launcher, argv, log)

    def cli(*args: object) -> list[str]:
        return [str(a) for a in args]

    init = cli("--gamma", "0.56", "--costs", "1,0.1", "--dim", "2")
    embed = cli(seg, "--columns", "x*", "--method", "identity", "--no-standardize")
    pool = cli("--clusters", 3, "--workers", 2)  # a worker pool, for the kills of its pid alone
    r1, p1, part = base / "r1.parquet", base / "p1.parquet", base / "r1-part.csv"
    _ok(launcher, cli("init", "-w", ws, *init), log)
    step("embed-reduce", cli("embed-reduce", "-w", ws, *embed))
    step("", cli("select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", 10))
    _ok(
        launcher,
        cli("simulate", ws / "batches/batch-0001.parquet", "--truth", truth, "-o", r1),
        log,
    )
    # Results that leave runs pending: the commit also writes the pending-only list.
    _ok(launcher, cli("simulate", ws / "batches/batch-0001.csv", "--truth", truth, "-o",
                      part), log)  # fmt: skip
    rows = list(csv.DictReader(part.open()))
    for i, row in enumerate(rows):
        row["value"], row["status"] = (row["value"], "ok") if i >= 2 else ("", "crashed")
    with part.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    keep["ingest-results, part"] = keep["ingest-results"] = base / "before-ingest-results"
    shutil.copytree(ws, keep["ingest-results"], symlinks=True)
    _ok(launcher, cli("ingest-results", "-w", ws, r1), log)
    step("fit", cli("fit", "-w", ws))
    fitted = base / "fitted"
    shutil.copytree(ws, fitted, symlinks=True)
    screened = base / "screened"  # a screened estimate: the screen, then its confirmation
    shutil.copytree(ws, screened, symlinks=True)
    step("select", cli("select", "-w", ws, "--strategy", "bams", "--budget", 5, *pool))
    step("abandon", cli("abandon", "-w", ws, "--batch", 2, "--reason", "gone"))
    ws = fitted
    plan = cli(*STAGED_PLAN, "--samples", 40, "--stages", 1)
    step("estimate --plan", cli("estimate", "-w", ws, *plan))
    handoff = ws / "estimates/plan-0001-handoff.csv"
    _ok(launcher, cli("simulate", handoff, "--truth", truth, "-o", p1), log)
    _ok(launcher, cli("ingest-results", "-w", ws, p1), log)
    step("estimate", cli("estimate", "-w", ws))
    step("report", cli("report", "-w", ws, "--truth", truth))
    ws = screened
    screen = cli("--plan", "--screen", 0.3, "--samples", 40)
    step("estimate --plan --screen", cli("estimate", "-w", ws, *screen))
    s1 = base / "s1.parquet"
    _ok(launcher, cli("simulate", ws / "batches/batch-0002.csv", "--truth", truth, "-o", s1),
        log)  # fmt: skip
    _ok(launcher, cli("ingest-results", "-w", ws, s1), log)
    _ok(launcher, cli("fit", "-w", ws), log)
    step("estimate --plan, confirming", cli("estimate", "-w", ws, *STAGED_PLAN))

    args: dict[str, Callable[[Path], list[str]]] = {
        "init": lambda w: cli("init", "-w", w, *init),
        "embed-reduce": lambda w: cli("embed-reduce", "-w", w, *embed),
        "ingest-results": lambda w: cli("ingest-results", "-w", w, r1),
        "ingest-results, part": lambda w: cli("ingest-results", "-w", w, part),
        "fit": lambda w: cli("fit", "-w", w),
        "select": lambda w: cli("select", "-w", w, "--strategy", "bams", "--budget", 5, *pool),
        "abandon": lambda w: cli("abandon", "-w", w, "--batch", 2, "--reason", "gone"),
        "estimate --plan": lambda w: cli("estimate", "-w", w, *plan),
        "estimate": lambda w: cli("estimate", "-w", w),
        "report": lambda w: cli("report", "-w", w, "--truth", truth),
        "estimate --plan --screen": lambda w: cli("estimate", "-w", w, *screen),
        "estimate --plan, confirming": lambda w: cli("estimate", "-w", w, *STAGED_PLAN),
    }
    keep["init"] = base / "before-init"  # never created: init starts from nothing
    return [Case(name, keep[name], args[name]) for name in args]


# ---- the campaign --------------------------------------------------------------------------
def _reset(case: Case, ws: Path) -> None:
    shutil.rmtree(ws, ignore_errors=True)
    if case.before.exists():
        shutil.copytree(case.before, ws, symlinks=True)


def _killpg(pid: int) -> None:
    try:
        os.killpg(pid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def campaign(
    case: Case, work: Path, killed, launcher, kills: int, seed: int, chain: int
) -> Counter:
    """Kill ``case``'s command ``kills`` times; returns how each kill ended.

    ``killed`` starts the runs that are killed (and the reference run, whose duration the
    kill times spread over); ``launcher`` the rest (``status``, the re-runs).
    """
    ws = work / "ws"
    log = work / "out.log"
    argv = case.argv(ws)
    before_hash = tree_hash(case.before) if case.before.exists() else {}
    before_rows = observation_rows(case.before)

    _reset(case, ws)
    start = time.monotonic()
    _ok(killed, argv, log)
    duration = reference = time.monotonic() - start
    after = snapshot(ws)
    assert after != snapshot(case.before), f"{case.name}: the reference run changed nothing"

    rng = random.Random(seed)
    outcomes: Counter = Counter()
    _reset(case, ws)
    in_chain = 0
    i = 0
    while outcomes["landed"] < kills:  # a run that ended before its kill does not count
        assert i < 3 * kills, f"{case.name}: {i} runs, {outcomes['landed']} killed"
        group = i % 2 == 1
        started = killed.start(argv)
        time.sleep(rng.uniform(0.0, 0.9 * duration))
        if group:
            _killpg(started.pid)
        else:
            try:
                os.kill(started.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        rc = started.wait()
        if rc == 0:  # the reference run was slow (a cold start, a busy machine): aim earlier
            duration *= 0.8
        what = f"{case.name}, kill {i} ({'group' if group else 'pid'}, rc {rc})"
        assert rc in (0, -signal.SIGKILL), f"{what}: failed by itself"
        if (ws / "settings.toml").exists():
            src, out = run(launcher, ["status", "-w", str(ws)], log)
            assert src in (0, 3), f"{what}: status exited {src}: {out}"
        if ws.exists():
            # What the next writing command does first; no --wait: the lock must be free.
            with workspace_lock(ws), journal_in(ws):
                recover(ws)
        _killpg(started.pid)  # any worker the main pid's death left (there should be none)
        assert not list(ws.rglob(".tmp-*")) if ws.exists() else True
        assert observation_rows(ws)[: len(before_rows)] == before_rows, f"{what}: rows lost"
        if (tree_hash(ws) if ws.exists() else {}) == before_hash:
            state = "before"
        else:
            found = snapshot(ws)
            assert found == after, f"{what}: in between: {_diff(found, after)}"
            state = "after"
        outcomes[("finished" if rc == 0 else "killed") + f", {state}"] += 1
        outcomes["landed"] += rc != 0
        i += 1
        if state == "before":
            in_chain += 1
            if in_chain < chain and outcomes["landed"] < kills:
                continue  # the next kill runs on what this one left
            rrc, out = run(launcher, argv, log)
            assert rrc == 0, f"{what}: the re-run failed: {out}"
            assert snapshot(ws) == after, (
                f"{what}: the re-run differs: {_diff(snapshot(ws), after)}"
            )
            outcomes["re-runs reaching after"] += 1
        in_chain = 0
        _reset(case, ws)
    outcomes["reference run, ms"] = round(1000 * reference)
    return outcomes


def _diff(found: dict[str, str], want: dict[str, str]) -> str:
    names = sorted(set(found) | set(want))
    return ", ".join(
        f"{n} ({'missing' if n not in found else 'extra' if n not in want else 'differs'})"
        for n in names
        if found.get(n) != want.get(n)
    )


def _run_all(tmp_path: Path, subprocesses: bool, kills: int, chain: int, threads: int) -> None:
    lock = threading.Lock()
    servers: list[ForkServer] = []
    local = threading.local()

    def one(args: tuple[int, Case]) -> tuple[str, Counter]:
        k, case = args
        if not hasattr(local, "server"):
            local.server = ForkServer()
            with lock:
                servers.append(local.server)
        killed = Subprocesses() if subprocesses else local.server
        work = tmp_path / f"run-{k}"
        work.mkdir()
        outcomes = campaign(case, work, killed, local.server, kills, seed=k, chain=chain)
        return case.name, outcomes

    try:
        server = ForkServer()  # the preparation needs no kills: imports once
        servers.append(server)
        cases = prepare(tmp_path / "prep", server)
        with ThreadPoolExecutor(threads) as pool:
            results = list(pool.map(one, enumerate(cases)))
    finally:
        for server in servers:
            server.close()
    for name, outcomes in results:
        print(f"{name}: {kills} kills: {dict(sorted(outcomes.items()))}")
        assert outcomes["landed"] == kills


def test_each_writing_command_killed_once(tmp_path):
    """A kill of each command started as ``python -m bams_cli`` (its pid). The slow set
    kills each three times (pid, group, pid) and 50 times in-process."""
    _run_all(tmp_path, subprocesses=True, kills=1, chain=1, threads=2)


@pytest.mark.slow
def test_each_writing_command_killed_a_few_times(tmp_path):
    """3 kills of each command started as ``python -m bams_cli``: pid, group, pid."""
    _run_all(tmp_path, subprocesses=True, kills=3, chain=3, threads=2)


@pytest.mark.slow
def test_each_writing_command_killed_at_50_random_moments(tmp_path):
    _run_all(tmp_path, subprocesses=False, kills=50, chain=20, threads=3)
