"""select through the CLI: BAMS batches confirm cheap-level leads at level 0."""

from __future__ import annotations

import json

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from tests.conftest import invoke, ok, write_batch


@pytest.fixture
def lead_ws(toy_ws, runner, tmp_path):
    """Level 0 on 6 segments, level 1 on 30; two cheap-level values at or below gamma
    (0.56) on segments whose level 0 is unknown: two leads."""
    ids0 = [f"t{i:06d}" for i in range(0, 60, 10)]
    ids1 = [f"t{i:06d}" for i in range(100, 400, 10)]
    write_batch(toy_ws, 1, ids0 + ids1, [0] * 6 + [1] * 30)
    values = [3.0, 2.5, 2.8, 3.3, 2.2, 2.9] + [2.0 + 0.05 * i for i in range(30)]
    values[6 + 7], values[6 + 20] = 0.4, 0.5  # t000170 and t000300 fail at level 1
    res = tmp_path / "r1.parquet"
    pq.write_table(
        pa.table({"segment_id": ids0 + ids1, "fidelity": [0] * 6 + [1] * 30, "value": values}), res
    )
    ok(runner, "ingest-results", "-w", toy_ws, res)
    ok(runner, "fit", "-w", toy_ws, "--restarts", "2")
    return toy_ws


def _select(runner, ws, *extra):
    r = ok(runner, "select", "-w", ws, "--budget", "5", "--clusters", "2", "--workers", "1",
           "--json", *extra)  # fmt: skip
    summary = json.loads(r.stdout)
    batch = pq.read_table(summary["handoff"]).to_pydict()
    return summary, batch


def test_bams_batch_confirms_leads_at_level0_first(lead_ws, runner):
    summary, batch = _select(runner, lead_ws, "--confirm-share", "0.4")
    assert summary["confirm_picks"] == 2 and summary["confirm_leads"] == 2
    assert batch["purpose"][:2] == ["confirm lead", "confirm lead"]
    assert sorted(batch["segment_id"][:2]) == ["t000170", "t000300"]
    assert batch["fidelity"][:2] == [0, 0]
    assert set(batch["purpose"][2:]) <= {"discover"}
    # The greedy spent the rest and never re-picked a confirmed segment at level 0.
    assert sum(batch["cost"]) <= 5.0 + 1e-9
    level0 = [s for s, f in zip(batch["segment_id"], batch["fidelity"], strict=True) if f == 0]
    assert len(level0) == len(set(level0))


def test_without_leads_the_likeliest_unconfirmed_failure_is_run_at_level0(
    lead_ws, runner, tmp_path
):
    summary, batch = _select(runner, lead_ws, "--confirm-share", "0.6")
    assert summary["confirm_picks"] == 3 and summary["confirm_leads"] == 2
    assert batch["purpose"][2] == "confirm likely" and batch["fidelity"][2] == 0


def test_confirm_share_zero_is_the_plain_greedy(lead_ws, runner):
    summary, batch = _select(runner, lead_ws, "--confirm-share", "0")
    assert summary["confirm_picks"] == 0
    assert set(batch["purpose"]) == {"discover"}


def test_confirm_share_out_of_range_is_refused(lead_ws, runner):
    r = invoke(runner, "select", "-w", lead_ws, "--confirm-share", "1.5")
    assert r.exit_code != 0 and "--confirm-share 1.5: must lie in [0, 1]" in r.stderr
