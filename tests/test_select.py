"""select through the CLI: BAMS batches confirm cheap-level leads at level 0."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from bams_cli import defaults
from bams_cli.state.workspace import Workspace
from tests.conftest import STAGED_PLAN, default_signals, invoke, ok, tree_hash, write_batch


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


def test_bams_on_a_new_study_says_how_to_get_a_first_model(toy_ws, runner):
    # No results yet: "run fit" would send the user to a fit that needs results first. And
    # every command names the same first batch: select and fit said `--strategy random`, a
    # level-0 batch without the pairs the first model learns the cheap level from, while
    # status said `--strategy random --mixed-fidelity --budget 5`.
    first = f"bams-cli select -w {toy_ws} --strategy random --mixed-fidelity --budget 5"
    r = invoke(runner, "select", "-w", toy_ws, "--budget", "3")
    assert r.exit_code == 1
    assert r.stderr.splitlines() == [
        f"error: {toy_ws / 'model.json'}: no fitted model; select a first batch "
        f"(`{first}`), simulate it and ingest the results, then fit"
    ]
    r = invoke(runner, "fit", "-w", toy_ws)
    assert r.exit_code == 1 and f"(`{first}`)" in r.stderr
    status = json.loads(invoke(runner, "status", "-w", toy_ws, "--json").stdout)
    assert status["next"]["command"] == first
    # A command to run as it stands: a folder with a space is quoted.
    spaced = toy_ws.parent / "my study"
    shutil.copytree(toy_ws, spaced)
    status = json.loads(invoke(runner, "status", "-w", spaced, "--json").stdout)
    assert status["next"]["command"] == (
        f"bams-cli select -w '{spaced}' --strategy random --mixed-fidelity --budget 5"
    )


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


def test_select_batch_is_a_stable_make_target(lead_ws, runner):
    from bams_cli import schemas_json
    from tests.jsonschema_subset import errors

    # batch 1 is the hand-made one; --batch 2 makes batch 2 ...
    first, batch = _select(runner, lead_ws, "--batch", "2")
    assert first["batch"] == 2 and "unchanged" not in first
    before = tree_hash(lead_ws)
    # ... and again is a no-op with the same summary, even while its results are pending.
    again, _ = _select(runner, lead_ws, "--batch", "2")
    assert again["unchanged"] is True and tree_hash(lead_ws) == before
    for key in ("batch", "handoff_csv", "picks", "total_cost", "confirm_picks"):
        assert again[key] == first[key], key
    assert errors({"schema_version": 1, **again}, schemas_json.schema("select")) == []
    # Other options for an existing batch, or a number that is not next: one-line errors.
    r = invoke(runner, "select", "-w", lead_ws, "--batch", "2", "--budget", "4")
    assert (
        r.exit_code == 1
        and "batch 2 exists with other options (budget 5.0 there, 4.0 asked;" in r.stderr
    )
    # Batch 2 awaits results: the new batch the error offers needs --allow-pending (the
    # command it named was refused, exit 3).
    says = "or --batch 3 --allow-pending for a new batch beside the picks awaiting results"
    assert says in " ".join(r.stderr.split())
    r = invoke(runner, "select", "-w", lead_ws, "--batch", "2", "--budget", "4", "--allow-pending")
    assert r.exit_code == 1 and "or --batch 3 for a new batch" in " ".join(r.stderr.split())
    r = invoke(runner, "select", "-w", lead_ws, "--batch", "5")
    assert r.exit_code == 1 and "--batch 5: the next batch is 3" in r.stderr
    assert tree_hash(lead_ws) == before


@pytest.mark.parametrize(
    ("edit", "needle"),
    [
        (lambda hp: hp.pop("noise"), "damaged hyperparameters (missing key 'noise')"),
        (lambda hp: hp.clear(), "damaged hyperparameters (missing key"),
        (lambda hp: hp.update(lengthscales0=[-1.0, -1.0]), "lengthscales0 must be finite and > 0"),
        (lambda hp: hp["noise"].__setitem__(0, float("nan")), "noise must be finite and >= 0"),
        (lambda hp: hp.update(lengthscales0=[1.0] * 5), "cannot reshape"),
        (lambda hp: hp.update(mean="abc"), "could not convert string to float"),
        (lambda hp: hp.update(mean=1e308), "mean must be finite and within +-1e+150"),
    ],
)
def test_a_hand_edited_model_is_named_with_the_command_that_rewrites_it(
    lead_ws, runner, edit, needle
):
    path = lead_ws / "model.json"
    doc = json.loads(path.read_text())
    edit(doc["hyperparameters"])
    path.write_text(json.dumps(doc))
    before = tree_hash(lead_ws)
    r = invoke(runner, "select", "-w", lead_ws, "--budget", "2", "--clusters", "2")
    assert r.exit_code == 1 and len(r.stderr.strip().splitlines()) == 1
    assert "model.json" in r.stderr and needle in r.stderr
    assert r.stderr.strip().endswith(f"run `bams-cli fit -w {lead_ws}` to write it again")
    assert "unexpected" not in r.stderr and tree_hash(lead_ws) == before


def test_a_cluster_too_large_for_exact_selection_is_selected_approximately(
    lead_ws, runner, monkeypatch
):
    import bams_cli.core.select as core_select

    # 256 KiB: one exact cluster of the whole pool does not fit, the approximate plan does
    # (64 rows x 512 candidates).
    monkeypatch.setattr(core_select, "MAX_CLUSTER_BYTES", 2**18)
    summary, batch = _select(runner, lead_ws, "--clusters", "1")
    plan = summary["selection_plan"]
    assert plan["exact"] is False and "GiB" in plan["reason"] and plan["clusters"] == 1
    assert plan["max_rows_per_cluster"] * plan["max_candidates_per_cluster"] * 8 <= 2**18
    assert plan["screen_rounds"] == defaults.SELECT_SCREEN_ROUNDS
    assert 0 < plan["candidates_per_round"] <= plan["max_candidates_per_cluster"]
    assert plan["candidates_per_round"] <= plan["candidates_kept"] <= plan["candidates_offered"]
    assert summary["picks"] == len(batch["segment_id"]) > 0


def test_select_json_says_the_small_pool_ran_exactly(lead_ws, runner):
    summary, _ = _select(runner, lead_ws)
    assert summary["selection_plan"]["exact"] is True
    assert summary["selection_plan"]["clusters"] == 2
    assert summary["warnings"] == []  # the model expects failures: nothing to warn about


def test_select_warns_when_the_model_rules_failure_out_everywhere(toy_ws, runner, tmp_path):
    # A trial's first fit after a random batch without a failure put J at 2.5e-30 and
    # BAMS picked on rounding without a word. Here: level-0 values far above gamma 0.56
    # and a model sure of them (sd 0.1 about 3).
    import json as _json

    ids = [f"t{i:06d}" for i in range(0, 400, 40)][:5]
    write_batch(toy_ws, 1, ids, [0] * 5)
    res = tmp_path / "r1.parquet"
    values = [3.1, 2.9, 3.0, 3.2, 3.3]
    pq.write_table(pa.table({"segment_id": ids, "fidelity": [0] * 5, "value": values}), res)
    ok(runner, "ingest-results", "-w", toy_ws, res)
    hp = {"mean": 3.0, "outputscale0": 0.01, "lengthscales0": [1.0, 1.0], "outputscales": [0.01],
          "lengthscales": [[1.0, 1.0]], "noise": [1e-4, 1e-4]}  # fmt: skip
    saved = tmp_path / "hp.json"
    saved.write_text(_json.dumps(hp))
    ok(runner, "fit", "-w", toy_ws, "--fixed-hyperparameters", saved)
    r = ok(runner, "select", "-w", toy_ws, "--budget", "2", "--clusters", "1", "--workers", "1",
           "--json")  # fmt: skip
    summary = _json.loads(r.stdout)
    expected = summary["j_before"] * 400
    assert expected < defaults.SELECT_NEGLIGIBLE_FAILURES
    [w] = summary["warnings"]
    assert f"expects {expected:.2g} failures in the whole pool" in w and "--strategy random" in w
    assert [_json.loads(line) for line in r.stderr.splitlines()] == [{"warning": w}]


def test_select_greedy_forces_the_plan_and_a_batch_rerun_must_ask_for_the_same(lead_ws, runner):
    summary, batch = _select(runner, lead_ws, "--greedy", "approximate", "--batch", "2")
    plan = summary["selection_plan"]
    assert plan["exact"] is False and plan["reason"] == "approximate: asked for"
    assert plan["max_rows_per_cluster"] == defaults.SELECT_MAX_ROWS
    assert summary["picks"] == len(batch["segment_id"]) > 0
    before = tree_hash(lead_ws)
    r = invoke(runner, "select", "-w", lead_ws, "--batch", "2", "--greedy", "exact")
    assert r.exit_code == 1 and "greedy 'approximate' there, 'exact' asked" in r.stderr
    r = invoke(runner, "select", "-w", lead_ws, "--greedy", "fast")
    assert r.exit_code == 2 and "fast" in r.stderr
    assert tree_hash(lead_ws) == before


def test_an_exact_greedy_too_large_for_memory_names_the_flag_that_forced_it(
    lead_ws, runner, monkeypatch
):
    import bams_cli.core.select as core_select

    monkeypatch.setattr(core_select, "MAX_CLUSTER_BYTES", 2**18)  # auto: approximate
    before = tree_hash(lead_ws)
    r = invoke(runner, "select", "-w", lead_ws, "--clusters", "1", "--greedy", "exact")
    assert r.exit_code == 1 and len(r.stderr.strip().splitlines()) == 1
    assert "raise --clusters" in r.stderr and "leave out --greedy exact" in r.stderr
    assert tree_hash(lead_ws) == before


def test_a_tight_memory_ceiling_runs_fewer_workers_and_says_so(lead_ws, runner, monkeypatch):
    from bams_cli import memory
    from bams_cli.pipeline import selection

    # 500 MiB of room: two workers would start (200 MiB each) but leave each cluster less
    # than the full plan's 4,096 x 1,024 covariance (twice 32 MiB); one worker keeps it.
    monkeypatch.setattr(memory, "tree_rss", lambda *_: 100 * 2**20)
    monkeypatch.setattr(selection.os, "cpu_count", lambda: 2)
    r = ok(runner, "select", "-w", lead_ws, "--budget", "5", "--clusters", "2", "--json",
           "--max-memory", "600M")  # fmt: skip
    plan = json.loads(r.stdout)["selection_plan"]
    assert plan["workers"] == 1
    assert "leaves room for 1 of 2 worker processes" in plan["workers_reason"]
    assert json.loads(r.stderr.strip().splitlines()[-1])["warning"] == plan["workers_reason"]
    # Asked for, the workers are what was asked (and the ceiling's check refuses two).
    before = tree_hash(lead_ws)
    r = invoke(runner, "select", "-w", lead_ws, "--budget", "5", "--workers", "2",
               "--allow-pending", "--max-memory", "350M")  # fmt: skip
    assert r.exit_code == 1 and "leaves no room for 2 worker processes" in r.stderr
    assert tree_hash(lead_ws) == before


def test_no_plan_fitting_memory_is_a_one_line_error(lead_ws, runner, monkeypatch):
    import bams_cli.core.select as core_select

    monkeypatch.setattr(core_select, "MAX_CLUSTER_BYTES", 1)
    r = invoke(runner, "select", "-w", lead_ws, "--budget", "2", "--clusters", "1")
    assert r.exit_code == 1 and len(r.stderr.strip().splitlines()) == 1
    assert "approximate plan needs" in r.stderr and "unexpected" not in r.stderr


def test_select_out_writes_the_handoff_and_a_no_op_rerun_restores_it(lead_ws, runner, tmp_path):
    out = tmp_path / "make" / "next.csv"
    first, _ = _select(runner, lead_ws, "--batch", "2", "--out", out)
    csv = lead_ws / "batches" / "batch-0002.csv"
    assert first["out"] == str(out) and out.read_bytes() == csv.read_bytes()
    assert "segment_id" in out.read_text().splitlines()[0]
    # An identical PATH is left alone (Make sees the target up to date) ...
    stamp = out.stat().st_mtime_ns
    before = tree_hash(lead_ws)
    again, _ = _select(runner, lead_ws, "--batch", "2", "--out", out)
    assert again["unchanged"] is True and again["out"] == str(out)
    assert out.stat().st_mtime_ns == stamp and tree_hash(lead_ws) == before
    # ... a lost or hand-edited one is written again, the workspace untouched.
    out.unlink()
    _select(runner, lead_ws, "--batch", "2", "--out", out)
    assert out.read_bytes() == csv.read_bytes()
    out.write_text("segment_id\nedited\n")
    _select(runner, lead_ws, "--batch", "2", "--out", out)
    assert out.read_bytes() == csv.read_bytes() and tree_hash(lead_ws) == before
    # A folder is not a file name.
    r = invoke(runner, "select", "-w", lead_ws, "--batch", "2", "--out", tmp_path)
    assert r.exit_code == 1 and f"--out {tmp_path}: is a folder" in r.stderr


KILLED_SELECT = """
import os, sys
from bams_cli.state import io

crash_after, renamed, real = int(sys.argv[1]), [], os.replace

def replace(src, dst):
    # Die like kill -9 (no cleanup, no finally) after `crash_after` renames of the commit;
    # -1: as the journal is renamed into place, before the commit began.
    journal = ".bams-journal" in str(dst)
    if (crash_after < 0 and journal) or (len(renamed) == crash_after and not journal):
        os._exit(9)
    real(src, dst)
    if ".bams-journal" not in str(dst):
        renamed.append(dst)

io.os.replace = replace
from bams_cli.cli import app
app(sys.argv[2:])
"""


@pytest.mark.parametrize("crash_after", [-1, 0, 1, 2, 3])
def test_select_out_killed_mid_commit_ends_as_an_uninterrupted_run(
    lead_ws, runner, tmp_path, crash_after
):
    import subprocess
    import sys

    out = tmp_path / "next.csv"
    args = ["select", "-w", str(lead_ws), "--budget", "5", "--clusters", "2", "--workers", "1",
            "--batch", "2", "--out", str(out)]  # fmt: skip
    # The commit renames 4 files (batch Parquet, CSV, results template, --out) after its
    # journal: killed before the journal nothing landed; after it the journal names them all.
    proc = subprocess.run([sys.executable, "-c", KILLED_SELECT, str(crash_after), *args])
    assert proc.returncode == 9
    assert not out.exists()
    # It left its staged copy beside PATH, outside the workspace: named by the journal (the
    # next command completes the commit) or, killed before the journal, by nothing.
    assert list(tmp_path.glob(".tmp-next.csv-*"))
    assert (lead_ws / "batches" / "batch-0002.parquet").exists() == (crash_after >= 1)
    # The same command again, as make would run it, ends with batch 2 and PATH its copy:
    # the next command rolls an interrupted commit forward, or draws the batch afresh.
    again = json.loads(ok(runner, *args, "--json").stdout)
    assert again["batch"] == 2 and again.get("unchanged", False) == (crash_after >= 0)
    csv = lead_ws / "batches" / "batch-0002.csv"
    assert out.read_bytes() == csv.read_bytes()
    assert not list(lead_ws.rglob(".tmp-*")) and not (lead_ws / ".bams-journal.json").exists()
    assert not list(tmp_path.glob(".tmp-*"))  # the killed run's staged copy went too


def test_allow_pending_never_repicks_pending_pairs_and_results_land_under_their_batch(
    lead_ws, runner, tmp_path
):
    from bams_cli.state.workspace import Workspace

    first, b2 = _select(runner, lead_ws, "--batch", "2")
    # Batch 2 awaits results; batch 3 is drawn with it in the batch already.
    second, b3 = _select(runner, lead_ws, "--allow-pending", "--batch", "3")
    pairs2 = set(zip(b2["segment_id"], b2["fidelity"], strict=True))
    pairs3 = set(zip(b3["segment_id"], b3["fidelity"], strict=True))
    assert second["batch"] == 3 and pairs3 and not pairs2 & pairs3
    # Its J is the J given batch 2's picks: lower before, and lower after, than batch 2's.
    assert second["j_before"] < first["j_after"] + 1e-12
    assert second["j_after"] < second["j_before"]
    # With both waiting, the estimate's plan is refused naming both hand-off lists, in
    # the order they were drawn (only the last was named).
    r = invoke(runner, "estimate", "-w", lead_ws, *STAGED_PLAN)
    assert r.exit_code == 3, r.stderr
    lists = [str(lead_ws / "batches" / f"batch-000{n}.csv") for n in (2, 3)]
    picks = len(b2["segment_id"]) + len(b3["segment_id"])
    says = f"batches 2, 3 await results for {picks} picks; simulate {lists[0]} and {lists[1]},"
    assert says in " ".join(r.stderr.split())
    # In one order from run to run (tables and pending-only lists show it): by batch, then
    # segment and level; it came in hash-join order.
    pend = Workspace(lead_ws).pending()
    order = pend.sort("batch", "plan", "segment_id", "fidelity", nulls_last=True)
    assert pend.height == picks and pend.rows() == order.rows()
    # A baseline strategy leaves pending pairs out as well (an observed cheap pair may be
    # picked again: it is not pending).
    _, b4 = _select(runner, lead_ws, "--allow-pending", "--strategy", "random",
                    "--mixed-fidelity", "--budget", "20")  # fmt: skip
    pairs4 = set(zip(b4["segment_id"], b4["fidelity"], strict=True))
    known = {
        (r["segment_id"], r["fidelity"]): r["value"]
        for r in Workspace(lead_ws).read_observations().iter_rows(named=True)
    }
    assert pairs4 and not pairs4 & (pairs2 | pairs3) - known.keys()
    ok(runner, "abandon", "-w", lead_ws, "--batch", "4", "--reason", "not run")
    # Results of both, in either order, land under the batch that asked for each pair. (A
    # deterministic simulator answers a cheap pair seen before with the value logged.)
    for n, b in ((3, b3), (2, b2)):
        keys = list(zip(b["segment_id"], b["fidelity"], strict=True))
        res = tmp_path / f"r{n}.parquet"
        values = [known.get(k, 3.0) for k in keys]
        pq.write_table(pa.table({"segment_id": b["segment_id"], "fidelity": b["fidelity"],
                                 "value": values}), res)  # fmt: skip
        ok(runner, "ingest-results", "-w", lead_ws, res)
    obs = Workspace(lead_ws).read_observations()
    for n, pairs in ((2, pairs2), (3, pairs3)):
        got = obs.filter(obs["batch"] == n)
        new_pairs = {k for k in pairs if k not in known}
        assert set(zip(got["segment_id"], got["fidelity"], strict=True)) == new_pairs, n
    assert Workspace(lead_ws).pending().height == 0


def _cheap_level_nearly_full(toy_ws, runner, toy_files, tmp_path) -> list[str]:
    """Batch 1 run and ingested: 396 of the 400 segments at level 1, 4 of them at level 0."""
    _, truth = toy_files
    ids = [f"t{i:06d}" for i in range(400)]
    write_batch(toy_ws, 1, ids[:396] + ids[:4], [1] * 396 + [0] * 4)
    res = tmp_path / "r1.parquet"
    ok(runner, "simulate", toy_ws / "batches" / "batch-0001.parquet", "--truth", truth, "-o", res)
    ok(runner, "ingest-results", "-w", toy_ws, res)
    return ids


def test_bams_never_offers_a_cheap_run_the_log_already_holds(toy_ws, runner, toy_files, tmp_path):
    # A trial's fourth BAMS batch repeated 11 cheap picks of earlier batches: wasted on a
    # deterministic cheap simulator, refused as conflicts from a noisy one. 396 of 400
    # segments have a level-1 result here, so the greedy would otherwise repeat them.
    ids = _cheap_level_nearly_full(toy_ws, runner, toy_files, tmp_path)
    ok(runner, "fit", "-w", toy_ws, "--restarts", "1")
    cheap_seen = set(ids[:396])

    def picks(*extra):
        copy = tmp_path / f"ws{len(extra)}"
        shutil.copytree(toy_ws, copy)
        ok(runner, "select", "-w", copy, "--budget", "1", "--clusters", "1", "--workers", "1",
           *extra)  # fmt: skip
        t = pq.read_table(copy / "batches" / "batch-0002.parquet")
        return list(zip(t["segment_id"].to_pylist(), t["fidelity"].to_pylist(), strict=True))

    assert not [s for s, lv in picks() if lv == 1 and s in cheap_seen]
    assert [s for s, lv in picks("--include-observed") if lv == 1 and s in cheap_seen]


def test_random_mixed_picks_cheap_runs_only_where_the_level_is_free(
    toy_ws, runner, toy_files, tmp_path
):
    # 396 of 400 segments hold a level-1 result. The mixed random batch drew its cheap picks
    # from the whole pool, so a budget of 2 (one level-0 run, ten cheap ones) re-ran
    # segments the log already held, and when every draw was pending select said "nothing
    # fits budget". The picks now come from the pairs free at their level.
    ids = _cheap_level_nearly_full(toy_ws, runner, toy_files, tmp_path)
    r = ok(runner, "select", "-w", toy_ws, "--strategy", "random", "--mixed-fidelity",
           "--budget", "2", "--level0-share", "0.5", "--json")  # fmt: skip
    t = pq.read_table(toy_ws / "batches" / "batch-0002.parquet")
    sid, lev = t["segment_id"].to_pylist(), t["fidelity"].to_pylist()
    cheap = [s for s, lv in zip(sid, lev, strict=True) if lv == 1]
    zero = [s for s, lv in zip(sid, lev, strict=True) if lv == 0]
    assert len(zero) == 1 and zero[0] not in ids[:4]
    # Ten cheap runs asked, four segments free at level 1: all four, none seen before.
    assert sorted(cheap) == ids[396:]
    assert json.loads(r.stdout)["picks_per_level"] == {"0": 1, "1": 4}


def test_random_mixed_spends_a_full_cheap_level_s_share_on_level0(
    toy_ws, runner, toy_files, tmp_path
):
    # Every segment holds a level-1 result. The mixed random batch gave level 0 its share
    # and the cheap level the rest, which bought nothing: budget 3 ran one level-0 segment,
    # and budget 1 was refused as "nothing fits budget 1.0 (cheapest level costs 0.1)".
    _, truth = toy_files
    ids = [f"t{i:06d}" for i in range(400)]
    write_batch(toy_ws, 1, ids + ids[:4], [1] * 400 + [0] * 4)
    res = tmp_path / "r1.parquet"
    ok(runner, "simulate", toy_ws / "batches" / "batch-0001.parquet", "--truth", truth, "-o", res)
    ok(runner, "ingest-results", "-w", toy_ws, res)

    for budget, n in (("1", 1), ("3", 3)):
        copy = tmp_path / f"ws{budget}"
        shutil.copytree(toy_ws, copy)
        r = ok(runner, "select", "-w", copy, "--strategy", "random", "--mixed-fidelity",
               "--budget", budget, "--json")  # fmt: skip
        summary = json.loads(r.stdout)
        assert summary["picks_per_level"] == {"0": n, "1": 0}
        assert summary["total_cost"] == n
        t = pq.read_table(copy / "batches" / "batch-0002.parquet")
        assert not set(t["segment_id"].to_pylist()) & set(ids[:4])

    # A budget that buys only cheap runs, none left: the error says what would help.
    before = tree_hash(toy_ws)
    r = invoke(runner, "select", "-w", toy_ws, "--strategy", "random", "--mixed-fidelity",
               "--budget", "0.5")  # fmt: skip
    assert r.exit_code == 1, r.output
    assert r.stderr.strip() == (
        "error: select: budget 0.5 buys only level 1 (cost 0.1), where no segment is left "
        "to run; level 0 has 396 segments left at cost 1: raise --budget to at least 1"
    )
    assert tree_hash(toy_ws) == before


def test_a_level0_strategy_with_no_segment_left_names_what_would_help(
    toy_ws, runner, toy_files, tmp_path
):
    # Every segment run at level 0: "nothing fits budget 3 (cheapest level costs 0.1); raise
    # --budget" cited a level --strategy random never picks, and no budget would help.
    _, truth = toy_files
    ids = [f"t{i:06d}" for i in range(400)]
    write_batch(toy_ws, 1, ids, [0] * 400)
    res = tmp_path / "r1.parquet"
    ok(runner, "simulate", toy_ws / "batches" / "batch-0001.parquet", "--truth", truth, "-o", res)
    ok(runner, "ingest-results", "-w", toy_ws, res)
    before = tree_hash(toy_ws)
    r = invoke(runner, "select", "-w", toy_ws, "--strategy", "random", "--budget", "3")
    assert r.exit_code == 1, r.output
    assert r.stderr.strip() == (
        "error: select: no segment is left to run at level 0; ingest the pending results, "
        "pass --include-observed to run segments again, --retry-abandoned to offer abandoned "
        "runs, or add segments (embed-reduce --apply)"
    )
    assert tree_hash(toy_ws) == before


def test_a_cheap_level_edited_dear_in_settings_is_warned_by_select(toy_ws, runner):
    # init warns of a cheap level costing a level-0 run or more; a hand edit came unwarned.
    settings = toy_ws / "settings.toml"
    settings.write_text(settings.read_text().replace("cost = 0.1", "cost = 1.5"))
    r = ok(runner, "select", "-w", toy_ws, "--strategy", "random", "--mixed-fidelity",
           "--budget", "4", "--json")  # fmt: skip
    [warning] = json.loads(r.stdout)["warnings"]
    assert warning.startswith(f"{settings}: level 1 (low1) costs 1.5, no less than a level-0 run")


@pytest.mark.parametrize(
    ("strategy", "budget", "says"),
    [
        ("bas", "0.5", "--strategy bas runs level 0 only, at cost 1"),
        ("random", "0.5", "--strategy random runs level 0 only, at cost 1"),
        ("bams", "0.05", "the cheapest level costs 0.1"),
    ],
)  # fmt: skip
def test_a_budget_that_buys_no_run_is_refused_before_the_work(
    toy_ws, runner, strategy, budget, says
):
    # `select --strategy bas --budget 0.5` ran the whole selection (6 s in a trial study),
    # then said "nothing fits budget 0.5 (cheapest level costs 0.15)": bas runs level 0 only.
    before = tree_hash(toy_ws)
    r = invoke(runner, "select", "-w", toy_ws, "--strategy", strategy, "--budget", budget)
    assert r.exit_code == 1, r.output  # the costs are the study's: not a usage error
    assert r.stderr.strip() == f"error: --budget {budget}: buys no run; {says}"
    assert tree_hash(toy_ws) == before
    # A mixed random batch may pick the cheap level: 0.5 buys runs of it.
    ok(
        runner,
        "select",
        "-w",
        toy_ws,
        "--strategy",
        "random",
        "--mixed-fidelity",
        "--budget",
        "0.5",
    )


@pytest.mark.parametrize(
    "command",
    [("select", "--budget", "3"), ("estimate", "--plan"), ("estimate",), ("fit",)],
)
def test_every_step_of_a_study_without_a_pool_names_embed_reduce(runner, tmp_path, command):
    # `estimate --plan` before embed-reduce said "select a first batch", which select then
    # refused for want of a pool.
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.5", "--costs", "1,0.1")
    before = tree_hash(ws)
    r = invoke(runner, command[0], "-w", ws, *command[1:])
    assert r.exit_code == 1, r.output
    assert r.stderr.splitlines() == [
        f"error: {ws / 'segments.parquet'}: no segment pool yet; run "
        f"`bams-cli embed-reduce -w {ws} SEGMENTS.parquet` first"
    ]
    assert tree_hash(ws) == before


STOPPED_POOLED_SELECT = """
import os, signal, sys, time
# A terminal's Ctrl-C: a CI job started in the background ignores SIGINT, and so would this.
signal.signal(signal.SIGINT, signal.default_int_handler)
from bams_cli.core import select as core_select
def greedy_cluster(*args, **kwargs):  # in a worker: a greedy that runs for minutes
    time.sleep(2.0)  # the command has submitted every cluster and waits on them
    signum = int(sys.argv[1])
    if sys.argv[2] == "group":  # as a terminal sends Ctrl-C: to every process of the job
        os.killpg(os.getpgid(0), signum)
    else:  # as kill, a job runner's timeout: to the command alone
        os.kill(os.getppid(), signum)
    time.sleep(60)
core_select.greedy_cluster = greedy_cluster
from bams_cli.cli import app
app(sys.argv[3:])
"""


@pytest.mark.parametrize(
    ("signum", "to"),
    [(2, "pid"), (2, "group"), (15, "pid"), (1, "pid")],
    ids=["INT", "INT-group", "TERM", "HUP"],
)
def test_a_pooled_select_stopped_by_a_signal_ends_in_one_line_at_once(lead_ws, signum, to):
    # Forked workers inherited the command's SIGTERM handler: at terminate() each idle one
    # (4 workers, 2 clusters) printed a traceback, and one busy in C code kept it waiting.
    # SIGINT to the command alone went unseen until the workers finished: importing polars
    # replaces Python's C-level SIGINT handler with one under which a wait is not
    # interrupted. Ctrl-C to the whole group sometimes ended in a 15-line traceback from
    # concurrent.futures' exit hook.
    import subprocess
    import sys
    import time

    before = tree_hash(lead_ws)
    args = ["select", "-w", str(lead_ws), "--budget", "5", "--clusters", "2", "--workers", "4"]
    start = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-c", STOPPED_POOLED_SELECT, str(signum), to, *args],
        capture_output=True, text=True, timeout=50, start_new_session=True,
        preexec_fn=default_signals,
    )  # fmt: skip
    assert time.monotonic() - start < 45  # not the workers' 60 s
    assert proc.returncode == 128 + signum, proc.stderr
    assert len(proc.stderr.splitlines()) == 1, proc.stderr
    assert proc.stderr.startswith("error: ")
    assert tree_hash(lead_ws) == before


def test_select_past_its_scoring_budget_bounds_the_pool_s_sds_and_says_so(
    lead_ws, runner, monkeypatch, tmp_path
):
    """Pool size x n^2 over ``SCORE_MAX_WORK`` (a million segments after an estimate
    stage: the pool's sds alone took over an hour): select takes the means and sds fit
    wrote, which are what it would compute (bounded as fit bounds them), says how in
    --json, and warns when segments near gamma kept the bound."""
    from bams_cli import schemas_json
    from bams_cli.core.select import _predict
    from bams_cli.pipeline.fitting import load_posterior
    from bams_cli.settings import load_settings
    from tests.jsonschema_subset import errors

    exact, _ = _select(runner, shutil.copytree(lead_ws, tmp_path / "copy"))
    assert exact["selection_plan"]["pool_sds"] == {"method": "exact", "rows": 400}
    # 400 segments, 36 results: the bound on 35 of them, then 7 exact sds
    max_work = 400 * 35**2 + 7 * 36**2
    monkeypatch.setattr(defaults, "SCORE_MAX_WORK", max_work)
    ws = Workspace(lead_ws)
    saved = tmp_path / "model.json"
    saved.write_text(ws.model_path.read_text())
    ok(runner, "fit", "-w", lead_ws, "--fixed-hyperparameters", saved)
    scoring = json.loads(ws.model_path.read_text())["scoring"]
    summary, batch = _select(runner, lead_ws)
    assert errors(summary, schemas_json.schema("select")) == []
    s = summary["selection_plan"]["pool_sds"]
    assert s == {k: v for k, v in scoring.items() if k != "note"}
    assert s["method"] == "bounded" and s["rows"] == 400 and s["bound_observations"] == 35
    assert s["exact_sd_rows"] == 7 < s["near_thresholds"]  # the rest of them kept the bound
    [warned] = summary["warnings"]
    assert warned.startswith("the pool's posterior: means exact; sds exact on the 7 segments")
    assert summary["picks"] == len(batch["segment_id"]) > 0
    # what select took from scores.parquet is what it would have computed
    settings = load_settings(lead_ws)
    ids, X = ws.read_pool()
    posterior, _ = load_posterior(ws, settings, ids, X)
    mu, sigma2, how = _predict(posterior, X, settings.gammas[0], max_work)
    scores = pq.read_table(ws.scores_path)
    np.testing.assert_allclose(scores["mu"].to_numpy(), mu, rtol=0, atol=1e-12)
    np.testing.assert_allclose(scores["sd"].to_numpy() ** 2, sigma2, rtol=1e-12, atol=1e-15)
    assert how == s


def test_select_past_local_obs_says_its_greedies_used_the_nearest_observations(
    lead_ws, runner, monkeypatch
):
    """Past ``SELECT_LOCAL_OBS`` observations the approximate plan's greedies condition on
    the nearest to their cluster (a million segments after an estimate stage took hours
    without it); the exact plan never does."""
    from bams_cli import schemas_json
    from tests.jsonschema_subset import errors

    monkeypatch.setattr(defaults, "SELECT_LOCAL_OBS", 20)  # lead_ws has 36 results
    # and a screen whose factors (candidates x 36^2 flops) are "out of reach"
    monkeypatch.setattr(defaults, "SCORE_MAX_WORK", 1e3)
    summary, batch = _select(runner, lead_ws, "--greedy", "approximate")
    assert errors(summary, schemas_json.schema("select")) == []
    assert summary["selection_plan"]["local_observations"] == 20
    assert summary["picks"] == len(batch["segment_id"]) > 0
    exact, _ = _select(runner, lead_ws, "--greedy", "exact", "--allow-pending")
    assert exact["selection_plan"]["local_observations"] is None
