"""Benchmark the memory ceiling (``--max-memory``) of the commands that grow with the pool.

    .venv/bin/python bench/bench_memory.py                      # N = 1,000,000 toy2d segments
    .venv/bin/python bench/bench_memory.py --n 200000 --limits 2G,1G --keep /tmp/bm
    .venv/bin/python bench/bench_memory.py --commands "select bams" --limits 1G,700M
    .venv/bin/python bench/bench_memory.py --protocol av_like --n 45000 \
        --commands "select bams" --limits "" --runs 3      # select timed from outside

Builds a study as a user does, one ``bams-cli`` process per step (the harness's toy2d pool
at N segments, or av_like's 512-d embeddings reduced to 12 by PCA, a random mixed-fidelity
first batch, its simulated results, ``fit``), then runs each command that takes
``--max-memory`` (``embed-reduce``, ``fit``, ``select --strategy bams``, ``report``) once
with no ceiling given (the default, ``defaults.MAX_MEMORY_FRACTION`` of RAM) and once under
each of ``--limits``, on a fresh copy of the study each time (--runs times; the median wall
time of the finished runs is printed). It prints each run's wall seconds and the peak
memory of its whole process tree (the command and its worker processes, read every 20 ms
through psutil) as its proportional set size, the memory it holds (a page shared by forked
workers counts once), beside the sum of the processes' resident sizes (which counts such a
page in every process), and whether the command finished or stopped at its ceiling. The
ceiling holds when every finished run's peak is under its limit; a run that stops at its
ceiling prints the one-line error the user sees. Reading the proportional set size costs
CPU beside the command (about 2 s of 7 at 45,000 av_like segments): time a command
without this script's sampling when the time is what matters.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import psutil

from bams_cli.benchmark import PROTOCOLS, prepare_data
from bams_cli.memory import format_size, parse_size, tree_pss, tree_rss

BIN = Path(sys.executable).parent / "bams-cli"


def run(args: list[object], log: Path) -> tuple[float, int, int, int]:
    """Wall seconds, peak process-tree memory (proportional set size, and resident sum;
    bytes) and exit code of one bams-cli process."""
    t0 = time.perf_counter()
    peak = peak_rss = 0
    with log.open("w") as out:
        proc = subprocess.Popen([str(BIN), *map(str, args)], stdout=out, stderr=out)
        done = threading.Event()

        def sample() -> None:
            nonlocal peak, peak_rss
            me = psutil.Process(proc.pid)
            while not done.wait(0.02):
                try:
                    kids = me.children(recursive=True)
                    peak_rss = max(peak_rss, tree_rss(me, kids))
                    peak = max(peak, tree_pss(me, kids))
                except psutil.NoSuchProcess:
                    return

        t = threading.Thread(target=sample, daemon=True)
        t.start()
        code = proc.wait()
        done.set()
        t.join()
    return time.perf_counter() - t0, peak, peak_rss, code


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--limits", default="2G,1G", help="comma-separated --max-memory values")
    ap.add_argument("--keep", type=Path, help="keep the data and study here")
    ap.add_argument(
        "--commands",
        default="embed-reduce,fit,select bams,report",
        help="comma-separated subset of: embed-reduce, fit, select bams, report",
    )
    ap.add_argument("--protocol", choices=["toy2d", "av_like"], default="toy2d")
    ap.add_argument("--runs", type=int, default=1, help="runs of each command and ceiling")
    a = ap.parse_args()
    limits = [x.strip() for x in a.limits.split(",") if x.strip()]

    with tempfile.TemporaryDirectory(prefix="bams-bench-") as tmp:
        root = a.keep or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        data = prepare_data(PROTOCOLS[a.protocol], a.n, root)
        seg, truth, log = data / "segments.parquet", data / "truth.parquet", root / "step.log"
        base = root / "base"
        shutil.rmtree(base, ignore_errors=True)
        reduce: list[object] = (
            ["embed-reduce", "-w", base, seg, "--columns", "x*", "--method", "identity",
             "--no-standardize"]
            if a.protocol == "toy2d"
            else ["embed-reduce", "-w", base, seg, "--method", "pca", "--dim", "12"]
        )  # fmt: skip
        setup: list[list[object]] = [
            ["init", "-w", base, "--settings-from", data / "settings.toml"],
            reduce,
            ["select", "-w", base, "--strategy", "random", "--mixed-fidelity", "--budget", "20"],
            ["simulate", base / "batches" / "batch-0001.parquet", "--truth", truth,
             "-o", root / "r1.parquet"],
            ["ingest-results", "-w", base, root / "r1.parquet"],
            ["fit", "-w", base, "--restarts", "4"],
        ]  # fmt: skip
        t = time.perf_counter()
        for args in setup:
            if run(args, log)[3] != 0:
                sys.exit(f"bams-cli {' '.join(map(str, args))} failed:\n{log.read_text()}")
        print(f"N = {a.n:,} segments ({a.protocol}), study set up in {time.perf_counter() - t:.0f} s; "
              f"RAM {format_size(psutil.virtual_memory().total)}")  # fmt: skip

        def work(ws: Path) -> dict[str, list[object]]:
            return {
                "embed-reduce": [*reduce[:2], ws, *reduce[3:], "--force"],
                "fit": ["fit", "-w", ws, "--restarts", "4", "--force"],
                "select bams": ["select", "-w", ws, "--strategy", "bams", "--budget", "15"],
                "report": ["report", "-w", ws],
            }  # fmt: skip

        print(f"{'command':<14}{'--max-memory':>14}{'wall s':>9}{'peak PSS':>12}"
              f"{'RSS sum':>12}  outcome")  # fmt: skip
        held = True
        for name in [c.strip() for c in a.commands.split(",")]:
            for limit in [None, *limits]:
                walls = []
                for _ in range(max(1, a.runs)):
                    ws = root / "run"
                    shutil.rmtree(ws, ignore_errors=True)
                    shutil.copytree(base, ws)
                    args = work(ws)[name] + ([] if limit is None else ["--max-memory", limit])
                    dt, peak, peak_rss, code = run(args, log)
                    cap = None if limit is None else parse_size(limit)
                    if code == 0:
                        walls.append(dt)
                        ok = cap is None or peak <= cap
                        held &= ok
                        outcome = "finished" + ("" if ok else "  OVER THE CEILING")
                    else:
                        lines = log.read_text().strip().splitlines()
                        outcome = f"exit {code}: {lines[-1] if lines else ''}"
                    print(f"{name:<14}{limit or 'default':>14}{dt:>9.1f}{format_size(peak):>12}"
                          f"{format_size(peak_rss):>12}  {outcome}", flush=True)  # fmt: skip
                if len(walls) > 1:
                    print(f"{name:<14}{limit or 'default':>14}{statistics.median(walls):>9.1f}"
                          f"  median of the {len(walls)} finished runs", flush=True)  # fmt: skip
        print("every finished run stayed under its ceiling" if held else "A CEILING WAS EXCEEDED")
        sys.exit(0 if held else 1)


if __name__ == "__main__":
    main()
