"""The Executor seam: where per-cluster work runs.

Per-cluster selection is independent work. It goes through a
``concurrent.futures.Executor``: a local process pool by default, an in-process runner for
``--workers 1``, or a ``dask.distributed`` cluster when the user names a scheduler
(``client.get_executor()``). One code path either way, and the same answer.

Local workers die with the command that started them: a worker outliving a killed command
would sit idle forever (it waits on a queue whose other end it holds itself) and, before
the lock closed its descriptor in forked children, kept the workspace locked.
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager
from typing import Any

from bams_cli.errors import BamsError


class InlineExecutor(Executor):
    """Runs each task at submit time, in this process (no pickling, easy to debug)."""

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # handed to the caller through the future
            future.set_exception(exc)
        return future


PR_SET_PDEATHSIG = 1  # <linux/prctl.h>


def _watch_parent(parent: int, interval: float = 0.5) -> None:
    """Exit as soon as this process's parent is no longer ``parent`` (it died)."""
    while os.getppid() == parent:
        time.sleep(interval)
    os._exit(1)


def _die_with_parent(parent: int) -> None:
    """Worker initializer: end this worker when ``parent`` (the command) dies.

    On Linux the kernel sends SIGKILL at the parent's death (``PR_SET_PDEATHSIG``), even to
    a worker busy in C code; elsewhere a thread polls ``getppid``. Either way the parent
    may have died before this ran, so check once by hand.
    """
    armed = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            armed = libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
        except (OSError, AttributeError):
            armed = False
    if os.getppid() != parent:
        os._exit(1)
    if not armed:
        threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()


def _pool_context() -> multiprocessing.context.BaseContext:
    """Fork on Linux (fast; the lock's at-fork hook keeps the lock out of workers); the
    platform's default elsewhere. Named, not left to the default, because workers must be
    children of this process for ``_die_with_parent`` (a forkserver's would not be)."""
    if sys.platform.startswith("linux"):
        return multiprocessing.get_context("fork")
    return multiprocessing.get_context("spawn")


@contextmanager
def executor(workers: int | None = None, scheduler: str | None = None) -> Iterator[Executor]:
    """Yield the executor a command should use.

    Parameters
    ----------
    workers : int, optional
        Local worker processes (default: the machine's cores); 1 runs inline.
    scheduler : str, optional
        Address of a ``dask.distributed`` scheduler, e.g. ``tcp://10.0.0.5:8786``.
    """
    if scheduler:
        try:
            from dask.distributed import Client
        except ImportError:
            raise BamsError(
                "--scheduler needs dask.distributed; install it with pip install 'bams-cli[dask]'"
            ) from None
        try:
            client = Client(scheduler, timeout=30)
        except OSError as exc:
            raise BamsError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
        try:
            yield client.get_executor()
        finally:
            client.close()
        return
    if workers is not None and workers < 1:
        raise BamsError(f"--workers {workers}: must be >= 1 (leave it out for one per core)")
    n = workers or os.cpu_count() or 1
    if n <= 1:
        yield InlineExecutor()
        return
    with ProcessPoolExecutor(
        max_workers=n,
        mp_context=_pool_context(),
        initializer=_die_with_parent,
        initargs=(os.getpid(),),
    ) as pool:
        yield pool
