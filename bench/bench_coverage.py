"""How long the default design's coverage takes to compute for the whole suite.

    .venv/bin/bams-cli benchmark --protocol suite --seeds 10 --save-arrays --out /tmp/suite
    .venv/bin/python bench/bench_coverage.py /tmp/suite [--trials 100] [--repeats 3] [--reference]

Issue 12 asks the design's coverage over the suite in under a minute. For every run the
benchmark saved (``runs.npz``: p_n after discovery, the known stratum, the open leads and
their share of K, the truth), ``core.evaluate.staged_trials`` draws the default staged
design ``--trials`` times from the truth, as ``docs/suite/estimate_design.py`` does for the
table, in one process. Prints the median wall and CPU time over ``--repeats`` passes, the
load average, and the coverage it found per problem (all runs' draws pooled).
``--reference``: each pass also draws the same trials through the tool's own functions
(``staged_trials(reference=True)``), alternating with the fast path, and prints the two
medians and their ratio; the coverage counts must agree (the same draws).
"""

from __future__ import annotations

import os
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from bams_cli.benchmark import saved_run_trials

PROBLEMS = ("toy2d", "av_like", "weak_cheap", "digits", "rare_regions", "gap_sim")
STRATEGIES = ("bams", "mcm-gp", "mc")


def _runs(folder: Path) -> list[tuple[str, str, int]]:
    out = []
    for problem in PROBLEMS:
        z = np.load(folder / problem / "runs.npz")
        for key in sorted(z.files):
            head, _, tail = key.rpartition("-")
            if tail == "known" and head.rsplit("-", 1)[0] in STRATEGIES:
                strategy, seed = head.rsplit("-", 1)
                out.append((problem, strategy, int(seed)))
    return out


def one_pass(folder: Path, trials: int, reference: bool = False) -> dict[str, list[int]]:
    """Coverage counts per problem: [covered, below, above, draws]."""
    counts: dict[str, list[int]] = {p: [0, 0, 0, 0] for p in PROBLEMS}
    for problem, strategy, seed in _runs(folder):
        t, *_ = saved_run_trials(
            folder / problem, strategy, seed, n_trials=trials, reference=reference
        )
        c = counts[problem]
        c[0] += int(((t.ci_low <= t.rate) & (t.rate <= t.ci_high)).sum())
        c[1] += int((t.ci_high < t.rate).sum())
        c[2] += int((t.ci_low > t.rate).sum())
        c[3] += trials
    return counts


def main(argv: list[str]) -> None:
    if not argv or argv[0].startswith("-"):
        # `make bench` runs every script bare: this one needs the suite's saved runs.
        print("bench_coverage.py: skipped, it needs the folder of `bams-cli benchmark "
              "--protocol suite --save-arrays` (see its docstring)")  # fmt: skip
        return
    folder = Path(argv[0])
    trials = int(argv[argv.index("--trials") + 1]) if "--trials" in argv else 100
    repeats = int(argv[argv.index("--repeats") + 1]) if "--repeats" in argv else 3
    paths = [False, True] if "--reference" in argv else [False]
    warnings.simplefilter("ignore")
    walls: dict[bool, list[float]] = {r: [] for r in paths}
    cpus: dict[bool, list[float]] = {r: [] for r in paths}
    counts: dict[bool, dict[str, list[int]]] = {}
    load0 = os.getloadavg()[0]
    for _ in range(repeats):
        for ref in paths:
            t0, c0 = time.perf_counter(), time.process_time()
            counts[ref] = one_pass(folder, trials, reference=ref)
            walls[ref].append(time.perf_counter() - t0)
            cpus[ref].append(time.process_time() - c0)
    n_runs = len(_runs(folder))
    for ref in paths:
        path = "reference: the tool's functions" if ref else "fast path"
        print(
            f"coverage of the default design over the suite ({path}): {n_runs} runs x {trials} draws, one process; median of {repeats}: "
            f"{statistics.median(walls[ref]):.1f} s wall, {statistics.median(cpus[ref]):.1f} s "
            f"CPU (load {load0:.1f} -> {os.getloadavg()[0]:.1f})"
        )
    if len(paths) == 2:
        same = "yes" if counts[True] == counts[False] else "NO"
        ratio = statistics.median(walls[False]) / statistics.median(walls[True])
        print(f"  fast / reference, wall: {ratio:.2f}; the same coverage counts: {same}")
    for problem, (cov, lo, hi, n) in counts[False].items():
        print(f"  {problem:13s} coverage {cov / n:.3f}  below {lo / n:.3f}  above {hi / n:.3f}")


if __name__ == "__main__":
    main(sys.argv[1:])
