"""The local worker pool: stopped, it does not wait for the work still queued."""

from __future__ import annotations

import multiprocessing
import time

import pytest

from bams_cli.parallel import executor


def test_a_stopped_pool_ends_its_workers_without_running_the_queue():
    # A loop stopped by SIGTERM during select unwound into the pool, which waited for every
    # queued cluster (8 tasks of 3 s on 2 workers: 12 s) before the loop could stop.
    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt), executor(2) as pool:
        futures = [pool.submit(time.sleep, 3) for _ in range(8)]
        time.sleep(0.5)
        raise KeyboardInterrupt
    assert time.monotonic() - t0 < 2.5
    # none ran: cancelled, or failed as the pool broke (BrokenProcessPool), never finished
    finished = [f for f in futures[2:] if f.done() and not f.cancelled() and not f.exception()]
    assert finished == []
    deadline = time.monotonic() + 5
    while multiprocessing.active_children() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert multiprocessing.active_children() == []
