"""The CLI end to end on the committed av_like sample data (512-d embeddings, 2 levels)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from bams_cli.state.workspace import Workspace
from tests.conftest import invoke, ok

DATA = Path(__file__).resolve().parents[1] / "sample_data" / "av_like"


def _round(runner, ws: Path, tmp: Path, *select_args: str) -> dict:
    summary = json.loads(ok(runner, "select", "-w", ws, *select_args, "--json").stdout)
    n = summary["batch"]
    res = tmp / f"r{n}.csv"
    ok(runner, "simulate", summary["handoff_csv"], "--truth", DATA / "truth.parquet", "-o", res)
    ok(runner, "ingest-results", "-w", ws, res)
    ok(runner, "fit", "-w", ws, "--restarts", "2")
    return summary


def test_av_like_loop_with_pca_difficulty_and_bams(runner, tmp_path):
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--settings-from", DATA / "settings.toml")
    r = ok(runner, "embed-reduce", "-w", ws, DATA / "segments.parquet", "--json")
    assert json.loads(r.stdout)["input_dim"] == 512
    w = Workspace(ws)
    ids, X = w.read_pool()
    assert X.shape == (2000, 12)
    assert "difficulty" in w.read_segments().column_names

    first = _round(
        runner, ws, tmp_path, "--strategy", "random", "--mixed-fidelity", "--budget", "20"
    )
    assert first["total_cost"] <= 20 and all(v > 0 for v in first["picks_per_level"].values())
    ds = _round(runner, ws, tmp_path, "--strategy", "ds", "--budget", "4")
    batch = pq.read_table(ds["handoff"]).to_pylist()
    assert all(row["fidelity"] == 0 for row in batch) and "difficulty" in batch[0]
    # DS draws towards difficult segments: its picks beat the pool's median difficulty
    pool_diff = np.median(w.read_segments().column("difficulty").to_numpy())
    assert np.mean([row["difficulty"] for row in batch]) > pool_diff
    bams = _round(runner, ws, tmp_path, "--budget", "3", "--clusters", "2", "--workers", "1")
    assert bams["j_after"] < bams["j_before"] and bams["total_cost"] <= 3
    model = json.loads((ws / "model.json").read_text())
    assert len(model["hyperparameters"]["lengthscales0"]) == 12
    assert sum(model["n_observations_per_level"]) == first["picks"] + ds["picks"] + bams["picks"]


def test_difficulty_strategy_without_the_column_names_the_fix(runner, toy_ws):
    r = invoke(runner, "select", "-w", toy_ws, "--strategy", "ds", "--budget", "2")
    assert r.exit_code == 1 and "needs a difficulty column 'difficulty'" in r.stderr
