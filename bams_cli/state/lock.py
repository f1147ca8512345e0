"""One writer per workspace.

The lock is an advisory ``flock`` on ``<workspace>/.bams.lock``. The file also holds a
record of who holds the lock (pid, host, the process's start time, the command), so a
refused command can name the holder.

Three rules keep the lock from outliving its holder:

* No child process holds it. ``flock`` belongs to the open file, and ``fork`` copies
  open files: a forked pool worker kept the lock after its parent was killed. The lock's
  descriptor is opened close-on-exec (``subprocess``, spawned workers never see it) and an
  ``os.register_at_fork`` hook closes it in every forked child (``close``, never
  ``LOCK_UN``, which would release the parent's lock too).
* A holder that died is recognised by its record: same host, and the pid either gone or now
  a different process (its start time differs, so a reused pid is not taken for the
  holder). If something still holds the ``flock`` (e.g. workers left by an older version),
  the lock file is unlinked and made afresh; a taker always checks that the file it locked
  is still the one at the path.
* The record is read and written only under a second, short-held lock
  (``.bams.lock-guard``, held for microseconds, never across a command), together with
  taking or dropping the ``flock``: a reader never sees the lock held with no record, or
  the record of a holder that has just let go.
"""

from __future__ import annotations

import datetime as dt
import fcntl
import json
import os
import socket
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bams_cli.errors import WorkspaceLockedError
from bams_cli.state.io import command_line

LOCK_FILE = ".bams.lock"
#: Held by ``bams-cli loop`` for its whole run, beside the per-command lock: one loop drives a
#: workspace at a time (its simulator runs outside any command, where the command lock is free).
LOOP_LOCK_FILE = ".bams.lock-loop"
GUARD_FILE = ".bams.lock-guard"
#: The record is one write of this many bytes at offset 0 (padded with spaces): it never
#: shrinks or grows, so there is no truncated moment for a reader to see.
RECORD_SIZE = 1024
POLL = 0.2  # seconds between tries with --wait
GUARD_TIMEOUT = 5.0  # the guard is held for microseconds; this long means something is wrong

# Descriptors this process locks through; a forked child closes them at once. A fork waits
# for _opening, so no child is forked between an open (or a close) and the update of _held.
_held: set[int] = set()
_opening = threading.Lock()


def _open_held(path: Path) -> int:
    with _opening:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        _held.add(fd)
    return fd


def _close_held(fd: int) -> None:
    with _opening:
        _held.discard(fd)
        os.close(fd)


def _close_in_child() -> None:
    _opening.release()
    for fd in _held:
        try:
            os.close(fd)
        except OSError:
            pass
    _held.clear()


os.register_at_fork(
    before=_opening.acquire, after_in_parent=_opening.release, after_in_child=_close_in_child
)


# ---- process identity ----------------------------------------------------------------------
def _read(path: str) -> str | None:
    try:
        with open(path) as fh:
            return fh.read().strip()
    except OSError:
        return None


def _proc_stat(pid: int) -> tuple[str, str] | None:
    """(state letter, start time in clock ticks since boot) from /proc, or None."""
    text = _read(f"/proc/{pid}/stat")
    if text is None:
        return None
    # The command name (field 2) may hold spaces and parentheses: split after the last ')'.
    fields = text[text.rfind(")") + 2 :].split()
    return fields[0], fields[19]  # fields 3 (state) and 22 (starttime), proc(5)


def _pid_namespace() -> str | None:
    try:
        return os.readlink("/proc/self/ns/pid")
    except OSError:
        return None


def _identity() -> dict[str, Any]:
    """What tells this process apart from any other, now or later, on this host."""
    stat = _proc_stat(os.getpid())
    return {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "boot_id": _read("/proc/sys/kernel/random/boot_id"),
        "pid_ns": _pid_namespace(),
        "start": stat[1] if stat else None,
    }


def _dead(record: dict[str, Any]) -> bool:
    """Whether the process a record names has certainly exited.

    Only a process on this host, booted kernel and pid namespace can be checked; any other
    counts as alive (the lock then waits for the kernel to drop it).
    """
    pid = record.get("pid")
    if not isinstance(pid, int) or pid <= 0 or record.get("host") != socket.gethostname():
        return False
    me = _identity()
    for key in ("boot_id", "pid_ns"):
        if record.get(key) is not None and me[key] is not None and record[key] != me[key]:
            return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        pass  # alive, another user's
    stat = _proc_stat(pid)
    if stat is None:
        return False  # no /proc (macOS): the pid exists, so take it for the holder
    state, start = stat
    # A zombie has closed its files; a different start time is a new process on a reused pid.
    return state == "Z" or (record.get("start") is not None and record["start"] != start)


# ---- the record ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Holder:
    """The record in the lock file; ``held`` is false once its writer let go."""

    info: dict[str, Any]

    @property
    def held(self) -> bool:
        return bool(self.info.get("pid"))

    def describe(self) -> str:
        i = self.info
        return (
            f"pid {i.get('pid', '?')} on {i.get('host', '?')} "
            f"({i.get('command', '?')!r}, since {i.get('since', '?')})"
        )


def _read_record(fd: int) -> Holder:
    # Records of older versions were written truncate-then-write: retry a torn read briefly.
    for _ in range(10):
        raw = os.pread(fd, 1 << 16, 0).decode(errors="replace").strip()
        try:
            info = json.loads(raw) if raw else {}
        except ValueError:
            time.sleep(0.02)
            continue
        if isinstance(info, dict):
            return Holder(info)
    return Holder({})


def _write_record(fd: int, info: dict[str, Any]) -> None:
    data = json.dumps(info)
    if len(data) > RECORD_SIZE:
        info = {**info, "command": str(info.get("command", ""))[:200] + "..."}
        data = json.dumps(info)[:RECORD_SIZE]
    os.pwrite(fd, data.ljust(RECORD_SIZE).encode(), 0)
    os.ftruncate(fd, RECORD_SIZE)  # a longer record of an older version leaves no tail


# ---- the guard -------------------------------------------------------------------------------
@contextmanager
def _guard(workspace: Path) -> Iterator[None]:
    fd = _open_held(workspace / GUARD_FILE)
    try:
        start = time.monotonic()
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() - start > GUARD_TIMEOUT:
                    raise WorkspaceLockedError(
                        f"{workspace / GUARD_FILE}: held for over {GUARD_TIMEOUT:g} s (a stopped "
                        f"bams-cli process?); find it with `fuser {workspace / GUARD_FILE}`"
                    ) from None
                time.sleep(0.002)
        yield
    finally:
        _close_held(fd)


def _same_file(fd: int, path: Path) -> bool:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return False
    mine = os.fstat(fd)
    return (st.st_dev, st.st_ino) == (mine.st_dev, mine.st_ino)


#: Dead holders this process has noted taking over: a loop killed inside a step held both
#: its own lock and the command lock, and the next loop takes over both.
_noted: set[tuple[Any, ...]] = set()


def _note_dead(holder: Holder, message: str) -> None:
    """Say once per process that ``holder`` died holding a lock this process takes over."""
    key = tuple(holder.info.get(k) for k in ("pid", "host", "boot_id", "pid_ns", "start"))
    if key not in _noted:
        _noted.add(key)
        sys.stderr.write(f"note: {message}\n")


#: What one attempt to take the lock can end in, besides success.
RETRY = Holder({"retry": True})


def _try_take(workspace: Path, fd: int, lock_file: str = LOCK_FILE) -> Holder | None:
    """One attempt, under the guard: None once ``fd`` holds the lock, ``RETRY`` to open the
    file again at once (it was replaced, or a dead holder's lock was broken), else the
    record of the holder."""
    path = workspace / lock_file
    with _guard(workspace):
        if not _same_file(fd, path):
            return RETRY  # replaced after we opened it: open the new one
        found = _read_record(fd)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            if not (found.held and _dead(found.info)):
                return found
            # The holder is gone but its flock is not: a process it started kept the
            # descriptor. Nobody can lock this file again; a new one takes its place.
            os.unlink(path)
            _note_dead(
                found,
                f"{workspace}: {found.describe()} died holding the lock (a process it "
                f"started still has {lock_file} open); proceeding",
            )
            return RETRY
        if found.held:
            _note_dead(found, f"{workspace}: {found.describe()} died holding the lock; proceeding")
        _write_record(
            fd,
            {
                **_identity(),
                "command": command_line(),
                "since": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            },
        )
        return None


def held_by_a_live_command(workspace: Path, lock_file: str = LOCK_FILE) -> bool:
    """Whether the lock's record names a command still running, read without taking the
    lock (or writing anything). True where the record cannot be read: a reader that cannot
    tell must leave the workspace alone."""
    try:
        fd = os.open(workspace / lock_file, os.O_RDONLY)
    except FileNotFoundError:
        return False
    except OSError:
        return True
    try:
        holder = _read_record(fd)
    finally:
        os.close(fd)
    return holder.held and not _dead(holder.info)


@contextmanager
def workspace_lock(
    workspace: Path,
    *,
    wait: bool = False,
    timeout: float | None = None,
    lock_file: str = LOCK_FILE,
    refusal: str = "locked by",
) -> Iterator[None]:
    """Hold the workspace's write lock for the duration of the block.

    Parameters
    ----------
    wait : bool
        Block until the lock is free instead of failing at once.
    timeout : float, optional
        With ``wait``, give up after this many seconds.
    lock_file : str
        The lock's file in the workspace: ``LOCK_FILE`` (every writing command) or
        ``LOOP_LOCK_FILE`` (``bams-cli loop``); the same rules hold for both.
    refusal : str
        What the refusal says before naming the holder.
    """
    workspace.mkdir(parents=True, exist_ok=True)
    path = workspace / lock_file
    start = time.monotonic()
    while True:
        fd = _open_held(path)
        try:
            holder = _try_take(workspace, fd, lock_file)
        except BaseException:
            _close_held(fd)
            raise
        if holder is None:
            break
        _close_held(fd)
        if holder is RETRY:
            continue
        if not wait or (timeout is not None and time.monotonic() - start > timeout):
            who = holder.describe() if holder.held else "a process that left no record"
            raise WorkspaceLockedError(
                f"{workspace}: {refusal} {who}; wait for it to finish or pass --wait"
            )
        time.sleep(POLL)
    owner = os.getpid()
    try:
        yield
    finally:
        # A forked child that unwinds through this block has already closed its copy.
        if os.getpid() == owner:
            try:
                with _guard(workspace):
                    _write_record(fd, {})
                    fcntl.flock(fd, fcntl.LOCK_UN)
            finally:
                _close_held(fd)
