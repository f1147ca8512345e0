"""One writer per workspace.

The lock is an advisory ``flock`` on ``<workspace>/.bams.lock``: the kernel drops it when
the holding process dies, so a crashed command never leaves a stale lock behind. The file
itself records who holds it, so a refused command can name the holder.
"""

from __future__ import annotations

import datetime as dt
import fcntl
import json
import os
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from bams_cli.errors import WorkspaceLockedError
from bams_cli.state.io import command_line

LOCK_FILE = ".bams.lock"


def _holder(fd: int) -> str:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        info = json.loads(os.read(fd, 4096).decode() or "{}")
    except (OSError, ValueError):
        return "an unknown process"
    return (
        f"pid {info.get('pid', '?')} on {info.get('host', '?')} "
        f"({info.get('command', '?')!r}, since {info.get('since', '?')})"
    )


@contextmanager
def workspace_lock(
    workspace: Path, *, wait: bool = False, timeout: float | None = None
) -> Iterator[None]:
    """Hold the workspace's write lock for the duration of the block.

    Parameters
    ----------
    wait : bool
        Block until the lock is free instead of failing at once.
    timeout : float, optional
        With ``wait``, give up after this many seconds.
    """
    workspace.mkdir(parents=True, exist_ok=True)
    fd = os.open(workspace / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        start = time.monotonic()
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if not wait or (timeout is not None and time.monotonic() - start > timeout):
                    raise WorkspaceLockedError(
                        f"{workspace}: locked by {_holder(fd)}; wait for it to finish or "
                        f"pass --wait"
                    ) from None
                time.sleep(0.2)
        info = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "command": command_line(),
            "since": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        }
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, json.dumps(info).encode())
        try:
            yield
        finally:
            os.ftruncate(fd, 0)
            fcntl.flock(fd, fcntl.LOCK_UN)
    finally:
        os.close(fd)
