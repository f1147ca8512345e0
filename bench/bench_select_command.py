"""Time ``bams-cli select`` as a user runs it: one process, start-up and Parquet I/O included.

    .venv/bin/python bench/bench_select_command.py                     # 45,000 av_like segments
    .venv/bin/python bench/bench_select_command.py --keep /tmp/sel45   # keep the fitted study
    .venv/bin/python bench/bench_select_command.py --study /tmp/sel45/ws --runs 5
    .venv/bin/python bench/bench_select_command.py --n 12000 --first-budget 1000 --runs 1
                                        # a study with ~3,700 observations

The study is what ``select`` meets after a first batch: the benchmark's av_like pool
(``benchmark.prepare_data``), init, embed-reduce (PCA to d = 12, as the protocol), a
random mixed-fidelity batch of budget 20 (``--first-budget``), its results, fit. Each run copies that workspace afresh and times
``bams-cli select --budget 15`` twice, alternating: the default plan (approximate at this
size) and ``--greedy exact``. Prints every run, the medians and the largest resident set of
any process of the command (the command and the workers it waited for). The machine is shared: compare
medians from one run of this script, and quote the load it prints.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bams_cli.benchmark import PROTOCOLS, prepare_data

BIN = Path(sys.executable).parent / "bams-cli"


def run(args: list[object]) -> tuple[float, float]:
    """Wall seconds and peak RSS (MB) of one bams-cli process: its own largest resident
    set and its workers' (``wait4``'s rusage of that child, which covers the processes it
    waited for), not the study's earlier steps'."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen([str(BIN), *map(str, args)], stdout=subprocess.DEVNULL,
                                stderr=err)  # fmt: skip
        _, status, usage = os.wait4(proc.pid, 0)
        dt = time.perf_counter() - t0
        if os.waitstatus_to_exitcode(status) != 0:
            err.seek(0)
            sys.exit(f"bams-cli {' '.join(map(str, args))} failed:\n{err.read().decode()}")
    return dt, usage.ru_maxrss / 1024


def make_study(root: Path, n: int, first_budget: float = 20) -> Path:
    data = prepare_data(PROTOCOLS["av_like"], n, root)
    seg, truth = data / "segments.parquet", data / "truth.parquet"
    ws = root / "ws"
    for args in (
        ["init", "-w", ws, "--settings-from", data / "settings.toml"],
        # As the av_like protocol: its 512-d embeddings reduced to d = 12 by PCA.
        ["embed-reduce", "-w", ws, seg, "--method", "pca", "--dim", 12],
        ["select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", first_budget],
        ["simulate", ws / "batches" / "batch-0001.parquet", "--truth", truth,
         "-o", root / "r1.parquet"],
        ["ingest-results", "-w", ws, root / "r1.parquet"],
        ["fit", "-w", ws, "--restarts", "4"],
    ):  # fmt: skip
        run(args)
    return ws


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=45_000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--first-budget", type=float, default=20,
                    help="Budget of the random first batch; raise it for a study with thousands "
                    "of observations (1,000 gives ~3,000 on av_like).")  # fmt: skip
    ap.add_argument("--study", type=Path, help="A fitted workspace to time select on.")
    ap.add_argument("--keep", type=Path, help="Make the study here and keep it.")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bams-bench-") as tmp:
        ws = a.study
        if ws is None:
            root = a.keep or Path(tmp)
            root.mkdir(parents=True, exist_ok=True)
            ws = make_study(root, a.n, a.first_budget)
        print(f"study {ws}; {os.cpu_count()} cpus, load average {os.getloadavg()}")
        plans = {"default": [], "--greedy exact": []}
        peak = 0.0
        for i in range(a.runs):
            for name, extra in (("default", []), ("--greedy exact", ["--greedy", "exact"])):
                copy = Path(tmp) / "run"
                shutil.rmtree(copy, ignore_errors=True)
                shutil.copytree(ws, copy)
                dt, rss = run(["select", "-w", copy, "--budget", "15", "--quiet", *extra])
                plans[name].append(dt)
                peak = max(peak, rss)
                print(f"run {i + 1} {name:<15} {dt:6.2f} s", flush=True)
        for name, times in plans.items():
            print(f"{name:<15} median {statistics.median(times):.2f} s "
                  f"({', '.join(f'{t:.2f}' for t in times)})")  # fmt: skip
        print(f"peak RSS of any select process {peak:.0f} MB; load average {os.getloadavg()}")


if __name__ == "__main__":
    main()
