"""The Executor seam: where per-cluster work runs.

Per-cluster selection is independent work. It goes through a
``concurrent.futures.Executor``: a local process pool by default, an in-process runner for
``--workers 1``, or a ``dask.distributed`` cluster when the user names a scheduler
(``DaskExecutor``). One code path either way, and the same answer.

On dask, nothing large goes through the scheduler: a task's array arguments, when they
add up to ``SCATTER_MIN_BYTES`` or more, go straight to a worker
(``Client.scatter(direct=True)``), and
an object shared by every task (the fitted model) goes to every worker once
(``broadcast=True``); the task the scheduler sees holds only references to them.

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

import numpy as np

from bams_cli.errors import BamsError

#: A task's array arguments, together at least this large, go to a dask worker directly.
SCATTER_MIN_BYTES = 64 * 1024

#: Arguments sent inside a dask task as they are.
_PLAIN = (int, float, bool, str, bytes, type(None), np.generic)


class InlineExecutor(Executor):
    """Runs each task at submit time, in this process (no pickling, easy to debug)."""

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # handed to the caller through the future
            future.set_exception(exc)
        return future


class DaskExecutor(Executor):
    """A ``dask.distributed`` client as an Executor that keeps large data off the scheduler.

    ``submit(fn, *args, **kwargs)`` sends ``fn`` with small arguments inside the task.
    The task's ndarrays, when they add up to ``SCATTER_MIN_BYTES`` or more, are scattered
    to one worker first (the scheduler then runs the task there); any other object (the fitted model every cluster's
    greedy needs) is broadcast to every worker, once per object however many tasks use it.
    """

    def __init__(self, client: Any, min_bytes: int | None = None) -> None:
        self._client = client
        self._inner = client.get_executor()
        self._min_bytes = SCATTER_MIN_BYTES if min_bytes is None else min_bytes
        self._turn = -1
        self._workers: list[str] | None = None  # listed once, at the first large task
        # id -> (object, its future): the object is held so that its id stays its own.
        self._shared: dict[int, tuple[Any, Any]] = {}

    def _shared_future(self, obj: Any) -> Any:
        if id(obj) not in self._shared:
            fut = self._client.scatter(obj, direct=True, broadcast=True, hash=False)
            self._shared[id(obj)] = (obj, fut)
        return self._shared[id(obj)][1]

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> Future:
        values: dict[Any, Any] = dict(enumerate(args)) | kwargs
        big = [k for k, v in values.items() if isinstance(v, np.ndarray)]
        if sum(values[k].nbytes for k in big) >= self._min_bytes:
            # One task's arrays to one worker, workers in turn: the task runs where its
            # data is, and the tasks spread over the workers.
            if self._workers is None:
                self._workers = sorted(self._client.scheduler_info()["workers"])
            workers = self._workers
            self._turn += 1
            where = [workers[self._turn % len(workers)]] if workers else None
            futs = self._client.scatter(
                [values[k] for k in big], direct=True, hash=False, workers=where
            )
            values |= dict(zip(big, futs, strict=True))
        for k, v in values.items():
            if not isinstance(v, (*_PLAIN, np.ndarray)) and not _is_future(v):
                values[k] = self._shared_future(v)
        n = len(args)
        shipped = [values[i] for i in range(n)]
        return self._inner.submit(fn, *shipped, **{k: values[k] for k in kwargs})

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._inner.shutdown(wait=wait)
        self._shared.clear()


def _is_future(obj: Any) -> bool:
    from dask.distributed import Future as DaskFuture

    return isinstance(obj, DaskFuture)


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

    A forked worker inherits the command's handlers for SIGTERM and SIGHUP (``cli``,
    ``loop``), which raise to unwind the command: in a worker they printed a traceback at
    ``terminate()`` and kept a worker busy in C code alive. Workers take the default back,
    and ignore SIGINT: Ctrl-C reaches the whole process group, and the command, stopped by
    it, ends its workers itself.

    A worker's kernels run on one thread (``core.kernels.set_kernel_threads``): its
    siblings hold the other cores.
    """
    from bams_cli.core.kernels import set_kernel_threads

    set_kernel_threads(1)
    for s in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
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


def _let_wind_down(manager: threading.Thread | None, timeout: float = 5.0) -> None:
    """Wait (a little) for a stopped pool's manager thread to see its workers gone and
    close its pipes. A command stopped at once left it closing them while the interpreter
    exited, and ``concurrent.futures``' exit hook then wrote to a closed pipe: a 15-line
    "Exception ignored" traceback after the command's one line."""
    if manager is not None and manager is not threading.current_thread():
        manager.join(timeout)


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
            # A scheduler with no worker would leave every task queued; dask's own
            # "No valid workers found" surfaced as an unexpected TimeoutError.
            client.wait_for_workers(1, timeout=30)
        except (TimeoutError, OSError):
            client.close()
            raise BamsError(
                f"--scheduler {scheduler}: the scheduler has no worker after 30 s; start some "
                f"with `dask worker {scheduler}`"
            ) from None
        try:
            yield DaskExecutor(client)
        finally:
            client.close()
        return
    if workers is not None and workers < 1:
        raise BamsError(f"--workers {workers}: must be >= 1 (leave it out for one per core)")
    n = workers or os.cpu_count() or 1
    if n <= 1:
        yield InlineExecutor()
        return
    pool = ProcessPoolExecutor(
        max_workers=n,
        mp_context=_pool_context(),
        initializer=_die_with_parent,
        initargs=(os.getpid(),),
    )
    try:
        yield pool
    except BaseException:
        # Stopped (Ctrl-C, a loop's SIGTERM, an error): the queued clusters are not waited
        # for (a select's greedies can run for minutes), and the workers end now.
        manager = getattr(pool, "_executor_manager_thread", None)  # shutdown() forgets it
        pool.shutdown(wait=False, cancel_futures=True)
        for worker in multiprocessing.active_children():
            worker.terminate()
        _let_wind_down(manager)
        raise
    pool.shutdown(wait=True)
