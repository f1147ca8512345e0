"""The workspace lock: a second writer fails at once naming the holder, or waits."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from bams_cli.errors import WorkspaceLockedError
from bams_cli.state.lock import workspace_lock

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
