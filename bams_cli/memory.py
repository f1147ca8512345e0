"""A memory ceiling for the commands that grow with the pool: ``--max-memory``.

``select``, ``fit``, ``embed-reduce`` and ``report`` take ``--max-memory SIZE`` (``12G``,
``800M``, ``40%`` of the machine's RAM; default ``defaults.MAX_MEMORY_FRACTION`` of it).
The ceiling works in two ways:

* planning: a command that sizes its work (``select``'s clusters and its rows x candidates
  covariance, ``embed-reduce``'s row batches, ``fit``'s exact conditioning) asks
  ``budget()`` and plans to stay within a share of it;
* a watchdog: while the command runs, a thread reads the resident memory of the process
  and its worker processes every ``POLL_S`` seconds. Their resident sizes summed count a
  page a forked worker shares with the command once per process (three times over with two
  workers); while that sum is over the ceiling, the watchdog reads what the tree really
  holds, its proportional set size (each page once, ``tree_pss``), at most every ``PSS_S``
  seconds since that read costs milliseconds. Past the ceiling it stops the command
  the way Ctrl-C does: files being written are discarded (every write is atomic), and the
  command ends with one line naming the ceiling and what it reached, exit code 1. If the
  command cannot be interrupted within ``GRACE_S`` (a long call in compiled code) while
  still over the ceiling, the watchdog prints the same line and ends the process tree
  (exit code 1); the workspace is then as a kill leaves it
  (``tests/test_crash_campaign.py``): as before, or as after the step's atomic commit.
"""

from __future__ import annotations

import _thread
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import psutil

from bams_cli import defaults
from bams_cli.errors import BamsError, OptionValueError

#: Seconds between two reads of the process tree's resident memory.
POLL_S = 0.05
#: Seconds between two listings of the worker processes (a listing reads every process's
#: /proc entry: 2.4 ms of CPU with 63 processes, too much to repeat every ``POLL_S``).
LIST_S = 1.0
#: Seconds between two reads of the tree's proportional set size, made only while the
#: cheap resident sum is over the ceiling (a read costs about 5 ms per 500 MB a process holds).
PSS_S = 0.2
#: Resident bytes of a worker process before it holds any work (Python, numpy, numba).
WORKER_BASE_BYTES = 200 * 2**20
#: Seconds the command has to stop after an interrupt before the watchdog ends it.
GRACE_S = 1.0

_UNITS = {"": 1, "k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40}
_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*([kmgt]?)(i?b)?\s*$", re.IGNORECASE)
_PERCENT = re.compile(r"^\s*([0-9]*\.?[0-9]+)\s*%\s*$")


class MemoryCeilingError(BamsError):
    """A command reached its ``--max-memory`` ceiling and was stopped."""


def total_ram() -> int:
    """Bytes of physical memory on this machine."""
    return int(psutil.virtual_memory().total)


def default_budget() -> int:
    """``defaults.MAX_MEMORY_FRACTION`` of the machine's RAM, in bytes."""
    return int(defaults.MAX_MEMORY_FRACTION * total_ram())


def parse_size(text: str, flag: str = "--max-memory") -> int:
    """Bytes from ``12G``, ``12GiB``, ``12GB``, ``800M``, ``512k``, ``1000000`` or ``40%``.

    Units are binary (``G`` = ``GB`` = ``GiB`` = 2**30 bytes); a percentage is of the
    machine's RAM. Anything else, zero, or a size under 256 MiB is a one-line usage error
    (exit code 2, as for any malformed option value).
    """
    percent = _PERCENT.match(text)
    if percent:
        share = float(percent.group(1)) / 100.0
        if not 0.0 < share <= 1.0:
            raise OptionValueError(f"{flag} {text!r}: a percentage of RAM must be in (0%, 100%]")
        size = int(share * total_ram())
    else:
        match = _SIZE.match(text)
        if not match:
            raise OptionValueError(
                f"{flag} {text!r}: expected a size such as 12G, 800M or 40% (of RAM)"
            )
        size = int(float(match.group(1)) * _UNITS[match.group(2).lower()])
    if size < 256 * 2**20:
        raise OptionValueError(
            f"{flag} {text!r}: below 256M, less than a command needs to start (Python, numpy, numba)"
        )
    return size


def format_size(n: float) -> str:
    """``1.5 GiB``, ``800 MiB``: the unit that keeps the number between 1 and 1024."""
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024:
            return f"{n:.0f} {unit}" if unit in ("B", "KiB") else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


def _tree_sum(
    read: Callable[[psutil.Process], int],
    proc: psutil.Process | None,
    children: list[psutil.Process] | None,
) -> int:
    """``read`` summed over a process and its descendants (``children``: as last listed,
    which spares the scan of every process on the machine that listing costs)."""
    proc = proc or psutil.Process()
    if children is None:
        children = proc.children(recursive=True)
    total = 0
    for p in [proc, *children]:
        try:
            total += read(p)
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            pass
    return total


def tree_rss(
    proc: psutil.Process | None = None, children: list[psutil.Process] | None = None
) -> int:
    """Resident bytes of a process and all its descendants (pages they share count
    once per process, so this never under-counts). Microseconds per process."""
    return _tree_sum(lambda p: p.memory_info().rss, proc, children)


def tree_pss(
    proc: psutil.Process | None = None, children: list[psutil.Process] | None = None
) -> int:
    """Proportional set size of a process and its descendants: the memory the tree holds.

    A page shared by k processes counts 1/k in each, so a forked worker's pages that are
    still its parent's count once in the total, where ``tree_rss`` counts them in every
    process. Reads /proc/PID/smaps_rollup: milliseconds per process, not microseconds.
    """
    return _tree_sum(lambda p: p.memory_full_info().pss, proc, children)


_budget: int | None = None
_watch: Watch | None = None
#: Child processes that are not the command's memory, with everything they start: the
#: user's simulator that ``loop`` runs (``outside``).
_outside: set[int] = set()


@contextmanager
def outside(pid: int) -> Iterator[None]:
    """While inside, the watchdog leaves process ``pid`` and its descendants out of the
    command's memory: ``loop``'s simulator is the user's program, and a large one would
    otherwise stop the loop under a ceiling meant for bams-cli's own steps."""
    _outside.add(pid)
    try:
        yield
    finally:
        _outside.discard(pid)


def _own_children(me: psutil.Process) -> list[psutil.Process]:
    """``me``'s descendants, less those under ``outside``."""
    children = me.children(recursive=True)
    if not _outside:
        return children
    skip: set[int] = set()
    for p in children:
        if p.pid in _outside:
            skip.add(p.pid)
            try:
                skip.update(c.pid for c in p.children(recursive=True))
            except psutil.NoSuchProcess:
                pass
    return [p for p in children if p.pid not in skip]


def budget() -> int:
    """The ceiling of the running command, in bytes (``default_budget()`` outside one)."""
    return default_budget() if _budget is None else _budget


def share(fraction: float) -> int:
    """``fraction`` of the running command's ceiling, in bytes: what one part of its work
    (one cluster's covariance, one batch of rows) may plan to hold."""
    return int(fraction * budget())


@dataclass
class Watch:
    """What the watchdog saw: the ceiling, the most memory it read the tree holding (its
    resident sum, or its proportional set size where that sum was over the ceiling), and
    whether it fired."""

    limit: int
    command: str
    peak: int = 0
    fired: bool = False
    _stop: threading.Event = field(default_factory=threading.Event)

    def message(self) -> str:
        return (
            f"{self.command} reached {format_size(self.peak)} of memory, over --max-memory "
            f"{format_size(self.limit)} and was stopped (writes are atomic: nothing half-written "
            "is left); raise --max-memory (or BAMS_MAX_MEMORY) or free memory on this machine"
        )

    def _run(self) -> None:
        me = psutil.Process()
        fired_at = listed_at = pss_at = 0.0
        pss = 0
        children: list[psutil.Process] = []
        while not self._stop.wait(POLL_S):
            now = time.monotonic()
            if now - listed_at > LIST_S:  # listing scans all of /proc
                children, listed_at = _own_children(me), now
            used = tree_rss(me, children)  # never less than what the tree holds
            if used > self.limit:
                if now - pss_at >= PSS_S:
                    pss, pss_at = tree_pss(me, children), now
                used = min(used, pss)
            self.peak = max(self.peak, used)
            if used <= self.limit:
                continue
            if not self.fired:
                self.fired, fired_at = True, time.monotonic()
                _thread.interrupt_main()
            elif time.monotonic() - fired_at > GRACE_S:
                self._end_tree(me)

    def _end_tree(self, me: psutil.Process) -> None:
        """The command did not stop after the interrupt: say why, then end it and its workers."""
        from bams_cli import console

        console.error(self.message())
        sys.stderr.flush()
        for child in me.children(recursive=True):
            try:
                child.kill()
            except psutil.NoSuchProcess:
                pass
        os._exit(1)  # no cleanup: a kill's state (tests/test_crash_campaign.py)


def check() -> None:
    """Raise ``MemoryCeilingError`` when the running command has gone over its ceiling.

    Every atomic commit calls it (``state.io.transaction``): the watchdog's interrupt can be
    swallowed by a library that handles Ctrl-C itself, but nothing is committed after the
    ceiling was reached.
    """
    if _watch is not None and _watch.fired:
        raise MemoryCeilingError(_watch.message())


@contextmanager
def ceiling(limit: int | None, command: str) -> Iterator[Watch]:
    """Run a command under a ceiling of ``limit`` bytes (None: ``default_budget()``).

    ``budget()`` returns the limit inside. A watchdog interrupt becomes
    ``MemoryCeilingError`` with the watch's one-line message.
    """
    global _budget, _watch
    watch = Watch(limit=default_budget() if limit is None else int(limit), command=command)
    previous, _budget = _budget, watch.limit
    previous_watch, _watch = _watch, watch
    thread = threading.Thread(target=watch._run, name="bams-max-memory", daemon=True)
    # Started with Ctrl-C ignored (nohup, a script's background job, some CI runners),
    # Python has no SIGINT handler and the watchdog's interrupt would do nothing: the
    # grace period would then end the whole process. Handle it for the command's time.
    ignored = None
    if threading.current_thread() is threading.main_thread():
        handler = signal.getsignal(signal.SIGINT)
        if handler in (signal.SIG_IGN, signal.SIG_DFL, None):
            ignored = handler
            signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        thread.start()  # inside: the first read may fire before start() returns
        yield watch
    except KeyboardInterrupt:
        if watch.fired:
            raise MemoryCeilingError(watch.message()) from None
        raise
    finally:
        try:
            watch._stop.set()
            if thread.ident is not None:
                thread.join()
        except KeyboardInterrupt:
            # Fired as the command ended: its commit was refused (``check``), or it had
            # committed before the ceiling was reached; either way it is raising or done.
            if not watch.fired:
                raise
        finally:
            _budget, _watch = previous, previous_watch
            if ignored is not None:
                signal.signal(signal.SIGINT, ignored)
