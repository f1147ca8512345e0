"""Signals that stop a command where it stands.

SIGINT (Ctrl-C, or ``kill -INT`` from a job runner), SIGTERM (``kill``'s default, a CI job's
timeout) and SIGHUP (a closed terminal) raise :class:`Stopped` in the main thread, so the
command unwinds as Ctrl-C does: files being written are discarded, the workspace lock is
released, and the command ends with one line and exit code 128 + the signal. Python's
default for SIGTERM and SIGHUP ends the process on the spot instead, lock left behind.

A handler is installed only where ``take(current_handler)`` says so: a signal ignored when
the command started stays ignored (``nohup``), and a handler someone else installed (a
loop around the command, a test harness) is left alone.

Installing Python's handler again for SIGINT matters beyond the message: importing polars
replaces the C-level SIGINT handler with one that restarts interrupted system calls, so a
command blocked waiting on its worker pool never saw ``kill -INT`` until every worker
had finished (minutes, for a select's greedies).
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any


class Stopped(KeyboardInterrupt):
    """A signal stopped a command; ``exit_code`` is 128 + its number, as a shell reports it."""

    def __init__(self, signum: int, message: str = "") -> None:
        if not message:
            said = "interrupted" if signum == signal.SIGINT else f"stopped by {_name(signum)}"
            message = f"{said}; files being written were discarded"
        super().__init__(message)
        self.signum = signum
        self.exit_code = 128 + signum


def _name(signum: int) -> str:
    return signal.Signals(signum).name


def is_default(handler: Any) -> bool:
    """The handler Python starts with: ``SIG_DFL``, or ``default_int_handler`` for SIGINT."""
    return handler is signal.default_int_handler or handler == signal.SIG_DFL


def not_ignored(handler: Any) -> bool:
    return handler != signal.SIG_IGN


@contextmanager
def raising(
    signums: Sequence[int],
    stopped: Callable[[int], BaseException] = Stopped,
    take: Callable[[Any], bool] = is_default,
) -> Iterator[None]:
    """For the block's time, each of ``signums`` whose handler ``take`` accepts raises
    ``stopped(signum)`` in the main thread, once: a second signal while the first unwinds
    (a rollback, a simulator being ended) changes nothing. A forked child that kept the
    handler dies by the signal as by default. Outside the main thread nothing is installed
    (Python allows handlers only there)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    me = os.getpid()
    stopping = False

    def stop(signum: int, _frame: Any) -> None:
        nonlocal stopping
        if os.getpid() != me:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)
            return
        if not stopping:
            stopping = True
            raise stopped(signum)

    previous = {s: signal.getsignal(s) for s in signums}
    taken = {s: h for s, h in previous.items() if take(h)}
    for s in taken:
        signal.signal(s, stop)
    try:
        yield
    finally:
        for s, handler in taken.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
