"""--max-memory: sizes as users write them, the planning share, and the watchdog's stop."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from typer.testing import CliRunner

from bams_cli import defaults, memory
from bams_cli.errors import BamsError, OptionError
from bams_cli.pipeline.selection import cluster_bytes

from .conftest import invoke, ok, simulate_and_ingest, tree_hash

GiB, MiB = 2**30, 2**20


@pytest.mark.parametrize(
    ("text", "size"),
    [
        ("12G", 12 * GiB),
        ("12GiB", 12 * GiB),
        ("12gb", 12 * GiB),
        ("1.5G", 3 * GiB // 2),
        ("800M", 800 * MiB),
        (" 512 MiB ", 512 * MiB),
        ("1T", 2**40),
        (str(3 * GiB), 3 * GiB),
        ("1048576k", GiB),
    ],
)
def test_sizes_are_read_in_binary_units(text: str, size: int) -> None:
    assert memory.parse_size(text) == size


def test_a_percentage_is_of_the_machines_ram() -> None:
    assert memory.parse_size("40%") == int(0.4 * memory.total_ram())
    assert memory.default_budget() == int(defaults.MAX_MEMORY_FRACTION * memory.total_ram())


@pytest.mark.parametrize("text", ["", "G", "12X", "-1G", "0%", "150%", "12 G B", "100M", "1e9"])
def test_bad_sizes_are_one_line_errors_naming_the_flag(text: str) -> None:
    with pytest.raises(BamsError) as err:
        memory.parse_size(text)
    assert "--max-memory" in str(err.value) and "\n" not in str(err.value)
    assert err.value.exit_code == 2  # a malformed option value: usage, as --budget -5


@given(st.integers(min_value=256 * MiB, max_value=2**44))
def test_a_byte_count_reads_back_exactly(n: int) -> None:
    assert memory.parse_size(str(n)) == n
    assert memory.parse_size(f"{n / GiB!r}G") == pytest.approx(n, rel=1e-12, abs=1)


@given(st.text(max_size=12))
def test_any_text_is_a_size_or_a_one_line_error(text: str) -> None:
    try:
        size = memory.parse_size(text)
    except BamsError as exc:
        assert "\n" not in str(exc)
    else:
        assert size >= 256 * MiB


def uses(monkeypatch: pytest.MonkeyPatch, n: int) -> None:
    """The process tree holds n bytes, however it is read."""
    monkeypatch.setattr(memory, "tree_rss", lambda proc=None, children=None: n)
    monkeypatch.setattr(memory, "tree_pss", lambda proc=None, children=None: n)


def test_the_watchdog_stops_a_command_over_its_ceiling(monkeypatch: pytest.MonkeyPatch) -> None:
    uses(monkeypatch, 400 * MiB)
    t0 = time.monotonic()
    with pytest.raises(memory.MemoryCeilingError) as err:
        with memory.ceiling(300 * MiB, "bams-cli fit") as watch:
            assert memory.budget() == 300 * MiB
            while time.monotonic() - t0 < 10:
                time.sleep(0.01)
    assert time.monotonic() - t0 < 2  # stopped at the first reads, not at the loop's end
    assert watch.fired and watch.peak == 400 * MiB
    text = str(err.value)
    assert "bams-cli fit reached 400.0 MiB of memory" in text and "--max-memory 300.0 MiB" in text
    assert memory.budget() == memory.default_budget()  # the ceiling ends with its command


def test_the_watchdog_stops_a_command_started_with_ctrl_c_ignored() -> None:
    """nohup, a script's background job or a CI runner start a process with SIGINT
    ignored; the watchdog's interrupt must still stop the command with its one line, not
    leave the grace period to end the whole process."""
    import signal
    import subprocess
    import sys

    code = (
        "import time\n"
        "from bams_cli import memory\n"
        "memory.tree_rss = memory.tree_pss = lambda *a: 400 * 2**20\n"
        "try:\n"
        "    with memory.ceiling(300 * 2**20, 'bams-cli fit'):\n"
        "        t0 = time.monotonic()\n"
        "        while time.monotonic() - t0 < 10:\n"
        "            time.sleep(0.01)\n"
        "except memory.MemoryCeilingError as exc:\n"
        "    print('stopped:', exc)\n"
        "import signal\n"
        "print('afterwards', signal.getsignal(signal.SIGINT) == signal.SIG_IGN)\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", code],
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert "stopped: bams-cli fit reached 400.0 MiB of memory" in r.stdout
    assert "afterwards True" in r.stdout  # the process's own choice is restored


def test_under_the_ceiling_nothing_fires(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(memory, "tree_rss", lambda proc=None, children=None: 200 * MiB)
    with memory.ceiling(300 * MiB, "bams-cli fit") as watch:
        time.sleep(0.3)
    assert not watch.fired and watch.peak == 200 * MiB


def test_the_real_process_tree_is_read() -> None:
    rss = memory.tree_rss()
    assert 20 * MiB < rss < memory.total_ram()


def test_pages_forked_workers_share_with_the_command_count_once() -> None:
    """Two forked workers map the command's 300 MB: the resident sum counts it three
    times, the proportional set size once, and the watchdog goes by the latter."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    held = np.ones(300 * MiB // 8)
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("fork")) as pool:
        naps = [pool.submit(time.sleep, 2.0) for _ in range(2)]
        time.sleep(0.5)
        rss, pss = memory.tree_rss(), memory.tree_pss()
        assert rss > pss + 500 * MiB, (rss, pss)
        limit = pss + 100 * MiB  # the tree holds less, its resident sum is far more
        with memory.ceiling(limit, "bams-cli select") as watch:
            time.sleep(0.6)
        assert not watch.fired and watch.peak <= limit
        for nap in naps:
            nap.result()
    assert held.sum() == held.size


def test_a_cluster_gets_its_share_of_what_is_left(monkeypatch: pytest.MonkeyPatch) -> None:
    from bams_cli.core.select import MAX_CLUSTER_BYTES

    uses(monkeypatch, 500 * MiB)
    monkeypatch.setattr(memory, "_budget", 2 * GiB)
    # (2 GiB - 500 MiB) over 2 workers, less a worker's own start-up, 4/9 of it for C (as
    # much again for the greedy's temporaries, a quarter for the posterior's factors).
    share = (2048 - 500) * MiB / 2 - memory.WORKER_BASE_BYTES
    assert cluster_bytes(2, None) == int(share * 4 / 9)
    assert cluster_bytes(1, None) == int(((2048 - 500) * MiB - memory.WORKER_BASE_BYTES) * 4 / 9)
    assert cluster_bytes(2, "tcp://elsewhere:8786") == MAX_CLUSTER_BYTES  # not our memory
    monkeypatch.setattr(memory, "_budget", 64 * GiB)
    assert cluster_bytes(2, None) == MAX_CLUSTER_BYTES  # never above select's own limit
    monkeypatch.setattr(memory, "_budget", 800 * MiB)  # 150 MiB a worker: not enough
    with pytest.raises(OptionError, match=r"holds 500.0 MiB already .* --workers 1$"):
        cluster_bytes(2, None)
    assert cluster_bytes(1, None) == int((300 * MiB - memory.WORKER_BASE_BYTES) * 4 / 9)


def test_select_starts_the_workers_the_ceiling_leaves_room_for(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from bams_cli.pipeline import selection

    need = memory.WORKER_BASE_BYTES + 2 * 8 * 4096 * 1024  # start-up, twice the full plan's C
    monkeypatch.setattr(selection.os, "cpu_count", lambda: 4)
    uses(monkeypatch, 500 * MiB)
    for room, expected in [(4 * need, None), (3 * need + MiB, 3), (need, 1)]:
        monkeypatch.setattr(memory, "_budget", 500 * MiB + room)
        n, why = selection.workers_within_memory(None, None)
        assert n == expected, (room, n)
        assert (f"room for {n} of 4 worker processes" in why) if n else why == ""
    # Not even one at the full plan: one, in the command, on a smaller plan, and said so
    # (one per core had been kept, and refused where --workers 1 ran).
    monkeypatch.setattr(memory, "_budget", 500 * MiB + need - MiB)
    n, why = selection.workers_within_memory(None, None)
    assert n == 1 and "leaves no room for a worker process at the full plan" in why
    assert selection.workers_within_memory(3, None) == (3, "")  # asked for: kept
    assert selection.workers_within_memory(None, "tcp://elsewhere:8786") == (None, "")


def fitted(runner: CliRunner, ws: Path, truth: Path) -> None:
    ok(runner, "select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", "10")
    handoff = ws / "batches" / "batch-0001.parquet"
    simulate_and_ingest(runner, ws, handoff, truth, ws.parent / "r1.parquet")
    ok(runner, "fit", "-w", ws, "--restarts", "2")


@pytest.mark.parametrize(
    "args",
    [
        ["fit", "--force"],
        ["select", "--strategy", "bams", "--budget", "5"],
        ["report"],
    ],
)
def test_a_command_stopped_at_its_ceiling_leaves_the_workspace_as_it_was(
    runner: CliRunner,
    toy_ws: Path,
    toy_files: tuple[Path, Path],
    monkeypatch: pytest.MonkeyPatch,
    args: list[str],
) -> None:
    fitted(runner, toy_ws, toy_files[1])
    before = tree_hash(toy_ws)
    uses(monkeypatch, 3 * GiB)
    monkeypatch.setattr(memory, "POLL_S", 0.001)  # first read before the command's work
    r = invoke(runner, *args[:1], "-w", toy_ws, *args[1:], "--max-memory", "2G")
    assert r.exit_code == 1, r.output
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "over --max-memory 2.0 GiB" in lines[0], r.stderr
    assert tree_hash(toy_ws) == before


def test_the_ceiling_comes_from_the_environment_too(
    runner: CliRunner, toy_ws: Path, toy_files: tuple[Path, Path], monkeypatch: pytest.MonkeyPatch
) -> None:
    fitted(runner, toy_ws, toy_files[1])
    monkeypatch.setenv("BAMS_MAX_MEMORY", "12X")
    r = invoke(runner, "fit", "-w", toy_ws, "--force")
    assert r.exit_code == 2 and "--max-memory '12X'" in r.stderr  # a usage error, as --budget -5
    monkeypatch.setenv("BAMS_MAX_MEMORY", "4G")
    ok(runner, "fit", "-w", toy_ws, "--force")


def test_nothing_is_committed_once_the_ceiling_was_reached(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A library that handles Ctrl-C itself can swallow the watchdog's interrupt; the
    commit still refuses, and the staged files go."""
    from bams_cli.state.io import transaction

    target = tmp_path / "out.txt"
    with transaction() as tx:  # no ceiling: commits
        tx.write_text(target, "before")
    watch = memory.Watch(limit=300 * MiB, command="bams-cli fit", peak=400 * MiB, fired=True)
    monkeypatch.setattr(memory, "_watch", watch)
    with pytest.raises(memory.MemoryCeilingError, match="over --max-memory 300.0 MiB"):
        with transaction() as tx:
            tx.write_text(target, "after")
    assert target.read_text() == "before" and sorted(tmp_path.iterdir()) == [target]


def test_fit_conditions_within_half_the_ceiling(monkeypatch: pytest.MonkeyPatch) -> None:
    from bams_cli.core.gp.fit import max_conditioned
    from bams_cli.pipeline.fitting import condition_budget

    assert condition_budget(123 * MiB) == 123 * MiB  # the API's explicit budget wins
    monkeypatch.setattr(memory, "_budget", 64 * GiB)
    assert condition_budget() == defaults.FIT_CONDITION_MEMORY
    monkeypatch.setattr(memory, "_budget", 2 * GiB)
    assert condition_budget() == GiB
    cap = max_conditioned(condition_budget())
    assert cap is not None and cap < max_conditioned(defaults.FIT_CONDITION_MEMORY)


def test_a_command_deaf_to_the_interrupt_is_ended_with_the_same_line() -> None:
    """Blocked in a system call the interrupt cannot break, the command is ended by the
    watchdog after ``GRACE_S``: the one line, exit code 1, not a hang."""
    import subprocess
    import sys

    code = (
        "import os\n"
        "from bams_cli import memory as m\n"
        "m.tree_rss = m.tree_pss = lambda proc=None, children=None: 3 * 2**30\n"
        "with m.ceiling(2 * 2**30, 'bams-cli select'):\n"
        "    r, w = os.pipe()\n"
        "    os.read(r, 1)\n"
    )
    t0 = time.monotonic()
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 1, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "bams-cli select reached 3.0 GiB" in lines[0], done.stderr
    assert time.monotonic() - t0 < 30
