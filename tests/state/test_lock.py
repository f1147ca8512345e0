"""The workspace lock: a second writer fails at once naming the holder, or waits; the lock
never outlives its holder (no child keeps it, a dead holder is recognised)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from bams_cli.errors import WorkspaceLockedError
from bams_cli.state import lock
from bams_cli.state.lock import LOCK_FILE, workspace_lock
from tests.conftest import process_gone

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")

HOLD = """
import sys, time
from pathlib import Path
from bams_cli.state.lock import workspace_lock
with workspace_lock(Path(sys.argv[1])):
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
"""


def _hold(ws, seconds):
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(ws), str(seconds)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def _lock_files_open(pid: int | str = "self") -> list[str]:
    fds = Path(f"/proc/{pid}/fd")
    names = []
    for fd in fds.iterdir():
        try:
            names.append(os.readlink(fd))
        except OSError:
            pass
    return [n for n in names if Path(n).name.startswith(LOCK_FILE)]


def test_second_writer_fails_naming_the_holder(tmp_path):
    proc = _hold(tmp_path, 30)
    try:
        with pytest.raises(
            WorkspaceLockedError, match=rf"locked by pid {proc.pid} on .*pass --wait"
        ):
            with workspace_lock(tmp_path):
                pass
    finally:
        proc.kill()
        proc.wait()
    with workspace_lock(tmp_path):  # the kernel released the dead holder's lock
        pass


def test_wait_blocks_until_free(tmp_path):
    proc = _hold(tmp_path, 1.0)
    start = time.monotonic()
    with workspace_lock(tmp_path, wait=True, timeout=20):
        waited = time.monotonic() - start
    proc.wait()
    assert waited > 0.3


# ---- no child holds the lock -------------------------------------------------------------
@linux_only
def test_forked_child_does_not_hold_the_lock(tmp_path):
    with workspace_lock(tmp_path):
        assert len(_lock_files_open()) == 1
        read, write = os.pipe()
        pid = os.fork()
        if pid == 0:  # child: report which lock files it still has open, then leave at once
            os.write(write, json.dumps(_lock_files_open()).encode())
            os._exit(0)
        os.close(write)
        os.waitpid(pid, 0)
        assert json.loads(os.read(read, 4096)) == []
        os.close(read)
        # ... and the parent still holds it: the child closed its copy, it did not unlock.
        with pytest.raises(WorkspaceLockedError, match=rf"locked by pid {os.getpid()} on "):
            with workspace_lock(tmp_path):
                pass
    assert _lock_files_open() == []


@linux_only
def test_executed_child_does_not_inherit_the_lock(tmp_path):
    with workspace_lock(tmp_path):
        out = subprocess.run(
            ["ls", "-l", "/proc/self/fd/"], close_fds=False, capture_output=True, text=True
        ).stdout
    assert LOCK_FILE not in out


POOL = """
import json, os, sys, time
from pathlib import Path
from bams_cli.parallel import executor
from bams_cli.state.lock import workspace_lock

def report(_):
    time.sleep(0.1)
    fds = [os.readlink(f"/proc/self/fd/{n}") for n in os.listdir("/proc/self/fd")
           if os.path.exists(f"/proc/self/fd/{n}")]
    return os.getpid(), [f for f in fds if ".bams.lock" in f]

with workspace_lock(Path(sys.argv[1])):
    with executor(workers=2) as pool:
        seen = {}
        while len(seen) < 2:  # until both workers have answered
            seen.update(pool.map(report, range(4)))
        print(json.dumps(list(seen.items())), flush=True)
        pool.submit(time.sleep, 60)  # one worker busy, one idle, as in a killed select
        time.sleep(60)
"""


@linux_only
def test_killed_command_leaves_no_lock_and_no_workers(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-c", POOL, str(tmp_path)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None
    workers = json.loads(proc.stdout.readline())
    pids = [pid for pid, _ in workers]
    assert len(set(pids)) == 2 and all(fds == [] for _, fds in workers), workers
    proc.send_signal(signal.SIGKILL)
    start = time.monotonic()
    with workspace_lock(tmp_path, wait=True, timeout=20):
        assert time.monotonic() - start < 3
    proc.wait()
    deadline = time.monotonic() + 3
    while not all(map(process_gone, pids)) and time.monotonic() < deadline:
        time.sleep(0.05)
    survivors = [pid for pid in pids if not process_gone(pid)]
    for pid in survivors:  # do not leave them behind when the test fails
        os.kill(pid, signal.SIGKILL)
    assert survivors == []


@linux_only
def test_worker_watchdog_exits_when_its_parent_dies(tmp_path):
    # Where PR_SET_PDEATHSIG is missing, a thread polling getppid ends the worker.
    program = """
import os, sys, threading, time
from bams_cli.parallel import _watch_parent
parent = os.getpid()  # not getppid() in the child: the parent may be dead by then
pid = os.fork()
if pid == 0:
    threading.Thread(target=_watch_parent, args=(parent, 0.05), daemon=True).start()
    time.sleep(60)
    os._exit(0)
print(pid, flush=True)
time.sleep(60)
"""
    proc = subprocess.Popen([sys.executable, "-c", program], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    child = int(proc.stdout.readline())
    proc.kill()
    proc.wait()
    deadline = time.monotonic() + 3
    while not process_gone(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    if not process_gone(child):
        os.kill(child, signal.SIGKILL)
        pytest.fail("the worker outlived its parent")


# ---- a dead holder is recognised -------------------------------------------------------------
def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_holder_that_died_is_noted_in_one_line(tmp_path, capfd):
    proc = _hold(tmp_path, 30)
    proc.kill()
    proc.wait()
    with workspace_lock(tmp_path, wait=True, timeout=5):
        pass
    err = capfd.readouterr().err
    assert err.count("\n") == 1
    assert f"pid {proc.pid} on {socket.gethostname()}" in err and "died holding the lock" in err
    with workspace_lock(tmp_path):  # released properly this time: nothing to say
        pass
    assert capfd.readouterr().err == ""


def test_long_record_of_an_older_version_is_replaced_whole(tmp_path, capfd):
    # Older versions wrote the record at its own length; a killed one left it behind.
    old = {"pid": _dead_pid(), "host": socket.gethostname(), "command": "bams-cli " + "x" * 6000}
    (tmp_path / LOCK_FILE).write_text(json.dumps(old))
    with workspace_lock(tmp_path):
        pass
    assert f"pid {old['pid']} on" in capfd.readouterr().err
    proc = _hold(tmp_path, 30)
    try:
        with pytest.raises(WorkspaceLockedError, match=rf"locked by pid {proc.pid} on "):
            with workspace_lock(tmp_path):
                pass
    finally:
        proc.kill()
        proc.wait()


ORPHAN = """
import fcntl, json, os, sys, time
fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)
fcntl.flock(fd, fcntl.LOCK_EX)
os.pwrite(fd, sys.argv[2].encode().ljust(1024), 0)
print("held", flush=True)
time.sleep(30)
"""


def _orphan(ws: Path, record: dict) -> subprocess.Popen:
    """A process holding the flock under a record that names someone else (as a pool worker
    of an older version did after its command was killed)."""
    proc = subprocess.Popen(
        [sys.executable, "-c", ORPHAN, str(ws / LOCK_FILE), json.dumps(record)],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "held"
    return proc


def _record(pid: int, **changes) -> dict:
    me = lock._identity()
    stat = lock._proc_stat(pid)
    base = {**me, "pid": pid, "start": stat[1] if stat else None, "command": "bams-cli select"}
    return {**base, **changes}


@pytest.mark.parametrize(
    "case",
    [
        "dead pid",
        pytest.param("reused pid", marks=linux_only),  # alive, but started after the record
        "old record",  # written by an older version: pid and host only
    ],
)
def test_lock_kept_by_a_dead_holders_child_is_taken_over(tmp_path, capfd, case):
    if case == "dead pid":
        record = _record(_dead_pid())
    elif case == "reused pid":
        record = _record(os.getpid(), start="1")
    else:
        record = {"pid": _dead_pid(), "host": socket.gethostname(), "command": "bams-cli fit"}
    orphan = _orphan(tmp_path, record)
    try:
        start = time.monotonic()
        with workspace_lock(tmp_path):
            assert time.monotonic() - start < 1
        err = capfd.readouterr().err
        assert err.count("\n") == 1 and f"pid {record['pid']} on" in err
        assert "still has .bams.lock open); proceeding" in err
        with workspace_lock(tmp_path):  # the new lock file is an ordinary one
            pass
        assert capfd.readouterr().err == ""
    finally:
        orphan.kill()
        orphan.wait()


@pytest.mark.parametrize("where", ["here", "another host"])
def test_live_holder_is_never_taken_over(tmp_path, where):
    record = _record(os.getpid())  # this very process: alive, same start time
    if where == "another host":
        record = _record(_dead_pid(), host="elsewhere")  # cannot be checked: counts as alive
    orphan = _orphan(tmp_path, record)
    try:
        with pytest.raises(WorkspaceLockedError, match=rf"locked by pid {record['pid']} on "):
            with workspace_lock(tmp_path):
                pass
    finally:
        orphan.kill()
        orphan.wait()


CHURN = """
import sys, time
from pathlib import Path
from bams_cli.state.lock import workspace_lock
stop = Path(sys.argv[2])
end = time.monotonic() + 60.0
print("go", flush=True)
while not stop.exists() and time.monotonic() < end:
    with workspace_lock(Path(sys.argv[1]), wait=True):
        pass
"""


def test_refusal_names_the_holder_even_while_it_takes_and_releases(tmp_path):
    stop = tmp_path / "stop"
    proc = subprocess.Popen(
        [sys.executable, "-c", CHURN, str(tmp_path), str(stop)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "go"
    refusals: list[str] = []
    # Until 50 refusals are seen (or 30 s pass: a loaded machine). After each success
    # pause a moment, so the other process, which waits for the lock, gets its turn.
    deadline = time.monotonic() + 30.0
    try:
        while len(refusals) < 50 and time.monotonic() < deadline:
            try:
                with workspace_lock(tmp_path):
                    pass
                time.sleep(0.001)
            except WorkspaceLockedError as exc:
                refusals.append(str(exc))
    finally:
        stop.touch()
        proc.wait(timeout=30)
    assert refusals, "never caught the other process holding the lock"
    nameless = [r for r in refusals if f"locked by pid {proc.pid} on " not in r]
    assert nameless == [], f"{len(nameless)} of {len(refusals)}: {nameless[0]}"


# ---- init under the lock -------------------------------------------------------------------
INIT = """
import sys, time
from pathlib import Path
go = Path(sys.argv[1])
from bams_cli.cli import main  # import first, so that all start together
from bams_cli.settings import Settings

# A slow machine: a long moment between looking at the folder and taking the lock.
build = Settings.with_overrides
Settings.with_overrides = lambda self, **kw: time.sleep(0.3) or build(self, **kw)
print("ready", flush=True)
while not go.exists():
    time.sleep(0.002)
sys.argv = ["bams-cli", "init", *sys.argv[2:]]
main()
"""


def test_concurrent_inits_one_wins_the_rest_fail(tmp_path):
    """Two of four wait for the lock: they must then find the workspace made, not remake it."""
    ws, go = tmp_path / "ws", tmp_path / "go"
    waits = [False, True, False, True]
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-c",
                INIT,
                str(go),
                "-w",
                str(ws),
                "--seed",
                str(seed),
                "--gamma",
                "0.5",
            ]
            + ["--wait"] * wait,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for seed, wait in enumerate(waits)
    ]
    for p in procs:
        assert p.stdout is not None and p.stdout.readline().strip() == "ready"
    go.touch()
    results = [(p.wait(timeout=60), *p.communicate()) for p in procs]
    winners = [seed for seed, (code, _, _) in enumerate(results) if code == 0]
    assert len(winners) == 1, results
    for (code, _, err), wait in zip(results, waits, strict=True):
        if code != 0:
            assert code == 1 and err.count("\n") == 1, err
            assert "settings.toml: already exists; edit it, pass --force" in err or (
                not wait and "locked by pid" in err
            ), err
    settings = tomllib.loads((ws / "settings.toml").read_text())
    assert settings["study"]["seed"] == winners[0]
