"""Shared fixtures: tiny sample pools, initialised workspaces, a CLI runner."""

from __future__ import annotations

import csv
import hashlib
import random
import signal
from collections.abc import Collection
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from bams_cli.cli import app
from bams_cli.core import synthetic
from bams_cli.state import schemas
from bams_cli.state.io import transaction

#: ``estimate --plan`` for the staged estimate whatever the study's cheap level looks like:
#: the tests of the staged plan's mechanics pin ``--screen off``. The default, auto, screens
#: where the fitted cheap level tracks level 0 (tests/test_screen_estimate.py, the loop's
#: screened test and the demo walk that path).
STAGED_PLAN = ("--plan", "--screen", "off")


def default_shares() -> list[float]:
    """Each stage's share of K in a default staged estimate: stage 1's, then the rest in
    equal parts (``estimate --plan --stages``)."""
    from bams_cli import defaults

    n, first = defaults.STAGES, defaults.STAGE1_SHARE
    return [first, *[(1.0 - first) / (n - 1)] * (n - 1)]


@pytest.fixture
def runner() -> CliRunner:
    return CliRunner()


def invoke(runner: CliRunner, *args: object):
    """Run the CLI in-process; returns the click Result (exit_code, stdout, stderr)."""
    return runner.invoke(app, [str(a) for a in args], catch_exceptions=False)


def ok(runner: CliRunner, *args: object):
    """Run the CLI in-process and insist it succeeded."""
    r = invoke(runner, *args)
    assert r.exit_code == 0, f"{args}: {r.output}"
    return r


def simulate_and_ingest(runner: CliRunner, ws: Path, handoff: Path, truth: Path, results: Path):
    """The sample simulator answers a hand-off list; its results are ingested."""
    ok(runner, "simulate", handoff, "--truth", truth, "-o", results)
    return ok(runner, "ingest-results", "-w", ws, results)


def answer_handoff(
    runner: CliRunner,
    handoff: Path,
    truth: Path,
    out: Path,
    crashed: Collection[str] = (),
    noise: float = 0.0,
) -> Path:
    """The simulation team's results for a hand-off list, as CSV: rows whose request id is
    in ``crashed`` come back without a value, status ``crashed``; ``noise`` > 0 plays a
    simulator whose runs differ from run to run (the truth table plays the simulator; the
    workspace never sees it)."""
    raw = out.with_suffix(".raw.csv")
    ok(runner, "simulate", handoff, "--truth", truth, "-o", raw)
    rows = list(csv.DictReader(raw.open()))
    rng = random.Random(str(out))
    for r in rows:
        r["status"] = "ok"
        if noise:
            r["value"] = repr(float(r["value"]) + rng.uniform(-noise, noise))
        if r["request_id"] in crashed:
            r["value"], r["status"] = "", "crashed"
    with out.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return out


def process_gone(pid: int) -> bool:
    """Exited: reaped, or a zombie (it has closed its files and waits to be reaped)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


def default_signals() -> None:
    """``preexec_fn`` for a child a test stops by a signal: SIGINT, SIGTERM and SIGHUP at
    their defaults. The tool leaves an inherited SIG_IGN alone (``nohup`` means it), so a
    test suite run under ``nohup``, or as a background job of a shell (SIGINT ignored),
    would otherwise see the signal ignored and the command finish."""
    for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(s, signal.SIG_DFL)


def tree_hash(root: Path) -> dict[str, str]:
    """Content hash of every file under root, to prove a failing command changed nothing.

    The lock files are left out: they record whoever holds the lock right now, not state.
    """
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and not p.name.startswith(".bams.lock")
    }


def write_toy(folder: Path, n: int = 400, seed: int = 0) -> tuple[Path, Path]:
    pool = synthetic.toy2d(n, seed)
    folder.mkdir(parents=True, exist_ok=True)
    seg = folder / "segments.parquet"
    truth = folder / "truth.parquet"
    pq.write_table(
        pa.table({"segment_id": pool.ids, "x0": pool.features[:, 0], "x1": pool.features[:, 1]}),
        seg,
    )
    pq.write_table(
        pa.table(
            {"segment_id": pool.ids, "value_0": pool.truth[:, 0], "value_1": pool.truth[:, 1]}
        ),
        truth,
    )
    return seg, truth


def fitted_toy_study(
    runner: CliRunner,
    folder: Path,
    *,
    gammas: str = "0.56",
    costs: str = "1,0.1",
    budget: int = 12,
    cheap_offsets: dict[int, float] | None = None,
) -> tuple[Path, Path]:
    """A 400-segment toy2d study through the CLI, as a study starts: ``init`` (seed 3),
    ``embed-reduce``, one random mixed-fidelity batch of ``budget``, its truth simulated
    and ingested, ``fit``. ``cheap_offsets`` {level: c}: that level's truth becomes level
    0's minus c (a cheap level that reads low, so it fails more widely). Returns (workspace,
    truth file)."""
    seg, truth = write_toy(folder / "data", n=400, seed=0)
    if cheap_offsets:
        t = pq.read_table(truth)
        for level, c in cheap_offsets.items():
            col = pa.array(t["value_0"].to_numpy() - c)
            name = f"value_{level}"
            t = (
                t.set_column(t.schema.get_field_index(name), name, col)
                if name in t.column_names
                else t.append_column(name, col)
            )
        pq.write_table(t, truth)
    ws = folder / "ws"
    ok(runner, "init", "-w", ws, "--gamma", gammas, "--costs", costs, "--dim", "2",
       "--seed", "3")  # fmt: skip
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize")  # fmt: skip
    ok(runner, "select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget",
       str(budget))  # fmt: skip
    batch = ws / "batches" / "batch-0001.parquet"
    simulate_and_ingest(runner, ws, batch, truth, folder / "batch-1.parquet")
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    return ws, truth


@pytest.fixture
def toy_files(tmp_path: Path) -> tuple[Path, Path]:
    return write_toy(tmp_path / "data")


@pytest.fixture
def toy_ws(tmp_path: Path, runner: CliRunner, toy_files) -> Path:
    """An initialised workspace with a reduced 400-segment toy2d pool."""
    ws = tmp_path / "ws"
    seg, _ = toy_files
    r = invoke(runner, "init", "-w", ws, "--gamma", "0.56", "--costs", "1,0.1", "--dim", "2")
    assert r.exit_code == 0, r.output
    r = invoke(
        runner,
        "embed-reduce",
        "-w",
        ws,
        seg,
        "--columns",
        "x*",
        "--method",
        "identity",
        "--no-standardize",
    )
    assert r.exit_code == 0, r.output
    return ws


def write_batch(
    ws: Path, n: int, ids: list[str], levels: list[int], strategy: str = "random"
) -> Path:
    """Write a hand-off list as `select` would (for tests of the steps after it)."""
    k = len(ids)
    table = pa.table(
        {
            "segment_id": ids,
            "fidelity": np.asarray(levels, dtype=np.int64),
            "cost": np.where(np.asarray(levels) == 0, 1.0, 0.1),
            "delta_j": np.zeros(k),
            "cluster": np.zeros(k, dtype=np.int64),
            "rank": np.arange(k, dtype=np.int64),
            "strategy": [strategy] * k,
        }
    )
    path = schemas.batch_path(ws, n)
    with transaction() as tx:
        tx.write_parquet(path, schemas.BATCH.conform(table))
    return path
