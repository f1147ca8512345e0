"""Benchmark the commands end to end, as a user runs them, on a large pool.

    .venv/bin/python bench/bench_pipeline.py                  # N = 1,000,000 toy2d segments
    .venv/bin/python bench/bench_pipeline.py --n 200000 --keep /tmp/ws

Each step is one ``bams-cli`` process (start-up, Parquet I/O and all): init, embed-reduce
(identity on 2 columns), a random mixed-fidelity first batch, simulate, ingest-results,
fit (scoring all N segments), estimate --plan (K = 5 x the GP's p N; where the default
--screen auto screens, the screen's cheap runs simulated, ingested and fitted, then
estimate --plan again for the level-0 confirmation), simulate, ingest, estimate (no refit:
the plan carries the GP's estimate), report. ``select --strategy bams``
is left out: its cost grows with the cluster size and is measured by bench_select.py.
Prints wall seconds and the largest resident set of any step.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pyarrow.parquet as pq

from bams_cli.benchmark import PROTOCOLS, prepare_data

BIN = Path(sys.executable).parent / "bams-cli"


def run(args: list[object], log: Path) -> tuple[float, float]:
    """Wall seconds and peak RSS (MB) of one bams-cli process."""
    t0 = time.perf_counter()
    with log.open("w") as out:
        proc = subprocess.Popen([str(BIN), *map(str, args)], stdout=out, stderr=out)
        _, status, usage = os.wait4(proc.pid, 0)  # this child's own rusage
    dt = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        sys.exit(f"bams-cli {' '.join(map(str, args))} failed:\n{log.read_text()}")
    return dt, usage.ru_maxrss / 1024


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--keep", type=Path, help="Keep the workspace here instead of a temp dir.")
    a = ap.parse_args()

    with tempfile.TemporaryDirectory(prefix="bams-bench-") as tmp:
        root = a.keep or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        data = prepare_data(PROTOCOLS["toy2d"], a.n, root)  # the benchmark harness's pool
        seg, truth = data / "segments.parquet", data / "truth.parquet"
        ws = root / "ws"
        batch = ws / "batches" / "batch-0001.parquet"
        plan = ws / "estimates" / "plan-0001-handoff.csv"
        steps: list[tuple[str, list[object]]] = [
            ("init", ["init", "-w", ws, "--settings-from", data / "settings.toml"]),
            ("embed-reduce", ["embed-reduce", "-w", ws, seg, "--columns", "x*",
                              "--method", "identity", "--no-standardize"]),
            ("select random", ["select", "-w", ws, "--strategy", "random", "--mixed-fidelity",
                               "--budget", "20"]),
            ("simulate batch", ["simulate", batch, "--truth", truth, "-o", root / "r1.parquet"]),
            ("ingest batch", ["ingest-results", "-w", ws, root / "r1.parquet"]),
            ("fit", ["fit", "-w", ws, "--restarts", "4"]),
            ("estimate --plan", ["estimate", "-w", ws, "--plan"]),
        ]  # fmt: skip
        # Where the default (--screen auto) screened, the screen's cheap runs are batch 2:
        # simulated, ingested and fitted before the level-0 confirmation is planned.
        screen = [
            ("simulate screen", ["simulate", ws / "batches" / "batch-0002.parquet",
                                 "--truth", truth, "-o", root / "s1.parquet"]),
            ("ingest screen", ["ingest-results", "-w", ws, root / "s1.parquet"]),
            ("fit", ["fit", "-w", ws, "--restarts", "4"]),
            ("estimate --plan", ["estimate", "-w", ws, "--plan"]),
        ]  # fmt: skip
        rest = [
            ("simulate plan", ["simulate", plan, "--truth", truth, "-o", root / "e1.parquet"]),
            ("ingest plan", ["ingest-results", "-w", ws, root / "e1.parquet"]),
            ("estimate", ["estimate", "-w", ws]),
            ("report", ["report", "-w", ws, "--truth", truth]),
        ]  # fmt: skip
        print(f"N = {a.n:,} segments (toy2d), one bams-cli process per step")
        print(f"{'step':<18}{'seconds':>9}{'peak RSS MB':>13}")
        total = 0.0

        def do(todo: list[tuple[str, list[object]]]) -> None:
            nonlocal total
            for name, args in todo:
                dt, rss = run(args, root / "step.log")
                total += dt
                print(f"{name:<18}{dt:>9.2f}{rss:>13.0f}", flush=True)

        do(steps)
        if (ws / "estimates" / "screen-0001.parquet").exists():
            do(screen)
        do(rest)
        plan_rows = pq.read_metadata(ws / "estimates" / "plan-0001.parquet").num_rows
        print(f"{'total':<18}{total:>9.2f}   (plan: {plan_rows:,} rows)")


if __name__ == "__main__":
    main()
