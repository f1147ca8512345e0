"""Benchmark embed-reduce --method pca end to end on a large 512-d embedding file.

    .venv/bin/python bench/bench_embed_reduce.py            # N = 1,000,000 x 512 float32
    .venv/bin/python bench/bench_embed_reduce.py --quick    # N = 200,000
    .venv/bin/python bench/bench_embed_reduce.py --no-ipca  # skip the slow comparison
    .venv/bin/python bench/bench_embed_reduce.py --keep /tmp/b --methods ipca  # reuse file

Writes a Parquet file of N segments (``segment_id`` and a fixed-size-list<float32>[512]
embedding, row groups of 65,536 rows, 2 GB of floats at N = 1M) whose embeddings are a
24-factor model plus noise around a common offset, then runs ``bams-cli embed-reduce
--method pca --dim 12 --force`` as a user does: one ``bams-cli`` process per run
(start-up, Parquet I/O, writing segments.parquet and reducer.npz). Prints the median,
min and max wall seconds over --runs runs and each process's peak resident set
(``os.wait4`` rusage of the child, ru_maxrss) and CPU seconds (user + system: on a loaded
machine wall time exceeds what the process itself spent). ``--method ipca`` (the IncrementalPCA
reducer that was the default before exact PCA) runs once on the same file for the ratio.

Targets (issue 16.4): N = 1,000,000 x 512 in <= 60 s and < 3 GB on the 2-core machine.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

BIN = Path(sys.executable).parent / "bams-cli"
D, FACTORS, ROW_GROUP = 512, 24, 65_536


def write_embeddings(path: Path, n: int, seed: int = 0) -> None:
    """N x 512 float32 embeddings, written a row group at a time (never all in memory)."""
    rng = np.random.default_rng(seed)
    loadings = rng.normal(size=(FACTORS, D)) * np.geomspace(3.0, 0.3, FACTORS)[:, None]
    offset = rng.normal(size=D) * 5.0
    schema = pa.schema([("segment_id", pa.string()), ("embedding", pa.list_(pa.float32(), D))])
    with pq.ParquetWriter(path, schema) as writer:
        for lo in range(0, n, ROW_GROUP):
            b = min(ROW_GROUP, n - lo)
            E = offset + rng.normal(size=(b, FACTORS)) @ loadings + rng.normal(size=(b, D))
            flat = pa.array(E.astype(np.float32).ravel())
            writer.write_table(
                pa.table(
                    {
                        "segment_id": pa.array([f"seg-{i:07d}" for i in range(lo, lo + b)]),
                        "embedding": pa.FixedSizeListArray.from_arrays(flat, D),
                    },
                    schema=schema,
                ),
                row_group_size=ROW_GROUP,
            )


def run(args: list[object], log: Path) -> tuple[float, float, float]:
    """Wall seconds, CPU seconds (user + system) and peak RSS (MB) of one bams-cli process."""
    t0 = time.perf_counter()
    with log.open("w") as out:
        proc = subprocess.Popen([str(BIN), *map(str, args)], stdout=out, stderr=out)
        _, status, usage = os.wait4(proc.pid, 0)  # this child's own rusage
    dt = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        sys.exit(f"bams-cli {' '.join(map(str, args))} failed:\n{log.read_text()}")
    return dt, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024  # KiB on Linux


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="N = 200,000 instead of 1,000,000")
    ap.add_argument("--n", type=int, help="pool size (overrides --quick)")
    ap.add_argument("--runs", type=int, default=3, help="runs of --method pca (median)")
    ap.add_argument("--no-ipca", action="store_true", help="skip the --method ipca run")
    ap.add_argument("--methods", default="pca,ipca", help="comma-separated: pca, ipca")
    ap.add_argument(
        "--keep", type=Path, help="keep the data and workspace here (and reuse its data file)"
    )
    a = ap.parse_args()
    n = a.n or (200_000 if a.quick else 1_000_000)

    with tempfile.TemporaryDirectory(prefix="bams-bench-") as tmp:
        root = a.keep or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        seg, ws, log = root / "embeddings.parquet", root / "ws", root / "step.log"
        t = time.perf_counter()
        if not (seg.exists() and pq.read_metadata(seg).num_rows == n):
            write_embeddings(seg, n)
        size_mb = seg.stat().st_size / 2**20
        print(f"N = {n:,} x {D} float32 ({size_mb:,.0f} MB on disk), written in "
              f"{time.perf_counter() - t:.0f} s; embed-reduce --dim 12, one process per run")  # fmt: skip
        run(["init", "-w", ws, "--gamma", "0", "--dim", "12", "--force"], log)
        reduce = ["embed-reduce", "-w", ws, seg, "--dim", "12", "--force", "--json"]
        methods = a.methods.split(",")
        results: dict[str, list[tuple[float, float, float]]] = {}
        if "pca" in methods:
            results["pca"] = [run([*reduce, "--method", "pca"], log) for _ in range(a.runs)]
            Z = pq.read_table(ws / "segments.parquet", columns=["z11"])
            assert Z.num_rows == n and np.all(np.isfinite(Z.column("z11").to_numpy()))
        if "ipca" in methods and not a.no_ipca:
            results["ipca"] = [run([*reduce, "--method", "ipca"], log)]  # minutes at 1M
        print(f"{'method':<8}{'runs':>5}{'median s':>10}{'min s':>8}{'max s':>8}"
              f"{'CPU s':>8}{'peak RSS MB':>13}")  # fmt: skip
        median = {}
        for name, runs in results.items():
            secs = [r[0] for r in runs]
            median[name] = statistics.median(secs)
            print(f"{name:<8}{len(runs):>5}{median[name]:>10.1f}{min(secs):>8.1f}{max(secs):>8.1f}"
                  f"{statistics.median(r[1] for r in runs):>8.1f}{max(r[2] for r in runs):>13.0f}")  # fmt: skip
        if len(median) == 2:
            print(f"ipca / pca wall time: {median['ipca'] / median['pca']:.1f}x")


if __name__ == "__main__":
    main()
