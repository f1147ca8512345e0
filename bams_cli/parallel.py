"""The Executor seam: where per-cluster work runs.

Per-cluster selection is independent work. It goes through a
``concurrent.futures.Executor``: a local process pool by default, an in-process runner for
``--workers 1``, or a ``dask.distributed`` cluster when the user names a scheduler
(``client.get_executor()``). One code path either way, and the same answer.
"""

from __future__ import annotations

import os
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
    n = workers or os.cpu_count() or 1
    if n <= 1:
        yield InlineExecutor()
        return
    with ProcessPoolExecutor(max_workers=n) as pool:
        yield pool
