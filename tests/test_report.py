"""`report` without --truth, at every state a real study passes through.

The loop runs on the av_like sample data through the CLI, with `bams-cli simulate` as the
simulation team, and `report` runs after every step: before any model, with a batch
pending, after batches that picked only cheap-level runs (mcm-gp with --level0-share 0, and
BAMS with a budget below one level-0 run), with an estimate plan pending, with its results
in but not computed, and with two plans. The second part hands a stale model results that
contradict its likely failures.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from bams_cli.report import SUMMARY_KEYS
from bams_cli.state.workspace import Workspace
from tests.conftest import ok, simulate_and_ingest

SAMPLE = Path(__file__).resolve().parents[1] / "sample_data"
AV = SAMPLE / "av_like"
TOY = SAMPLE / "toy2d"


class Study:
    """A workspace driven through the CLI, keeping the report written after each step."""

    def __init__(self, tmp: Path, data: Path):
        self.runner = CliRunner()
        self.tmp, self.data, self.ws = tmp, data, tmp / "ws"
        self.truth = data / "truth.parquet"
        self.reports: dict[str, dict] = {}

    def run(self, *args: object):
        return ok(self.runner, *args)

    def simulate_and_ingest(self, handoff: Path) -> None:
        res = self.tmp / f"results-{handoff.stem}.parquet"
        simulate_and_ingest(self.runner, self.ws, handoff, self.truth, res)

    def report(self, stage: str) -> dict:
        self.run("report", "-w", self.ws)  # no --truth: what a real study has
        out = self.ws / "report"
        w = Workspace(self.ws)
        active = w.read_observations()
        level0 = active.filter(pl.col("fidelity") == 0)
        self.reports[stage] = {
            "summary": json.loads((out / "summary.json").read_text()),
            "md": (out / "summary.md").read_text(),
            "html": (out / "report.html").read_text(),
            "level0": dict(level0.select("segment_id", "value").iter_rows()),
            "level0_batch": dict(level0.select("segment_id", "batch").iter_rows()),
            "cheap": active.filter(pl.col("fidelity") > 0),
            "runs0": w.read_observations(active_only=False).filter(pl.col("fidelity") == 0).height,
            "failures": pl.read_csv(out / "failures.csv", infer_schema_length=None),
            "log": w.read_observations(active_only=False),
            "scores": pl.read_parquet(w.scores_path) if w.scores_path.exists() else None,
        }
        return self.reports[stage]


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> Study:
    s = Study(tmp_path_factory.mktemp("report-states"), AV)
    ws = s.ws
    s.run("init", "-w", ws, "--settings-from", AV / "settings.toml")
    s.run("embed-reduce", "-w", ws, AV / "segments.parquet", "--dim", "12")
    s.report("initialised")
    s.run("select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", "6")
    s.report("first batch pending")
    s.simulate_and_ingest(ws / "batches" / "batch-0001.parquet")
    s.report("first results, no fit")
    s.run("fit", "-w", ws, "--restarts", "2")
    s.report("fitted")
    s.run("select", "-w", ws, "--strategy", "mcm-gp", "--level0-share", "0", "--budget", "1")
    s.report("cheap-only batch pending")
    s.simulate_and_ingest(ws / "batches" / "batch-0002.parquet")
    s.report("cheap-only batch in, not fitted")
    s.run("fit", "-w", ws, "--restarts", "2")
    bams = ("--clusters", "2", "--workers", "1")
    s.run("select", "-w", ws, "--strategy", "bams", "--budget", "0.5", *bams)
    s.report("cheap-only bams batch pending")
    s.simulate_and_ingest(ws / "batches" / "batch-0003.parquet")
    s.run("fit", "-w", ws, "--restarts", "2")
    s.report("cheap-only bams batch fitted")
    s.run("estimate", "-w", ws, "--plan", "--samples", "40")
    s.report("plan 1 pending")
    s.simulate_and_ingest(ws / "estimates" / "plan-0001-handoff.csv")
    s.report("plan 1 in, not computed")
    s.run("estimate", "-w", ws)
    s.report("plan 1 computed")
    s.run("fit", "-w", ws, "--restarts", "2")
    s.run("estimate", "-w", ws, "--plan", "--samples", "40")
    s.report("plan 2 pending")
    s.simulate_and_ingest(ws / "estimates" / "plan-0002-handoff.csv")
    s.run("estimate", "-w", ws)
    s.report("plan 2 computed")
    return s


# stage -> the notices the report must open with, in order
EXPECTED_NOTICES = {
    "initialised": ["no_model"],
    "first batch pending": ["no_model", "pending_batches"],
    "first results, no fit": ["no_model"],
    "fitted": [],
    "cheap-only batch pending": ["pending_batches"],
    "cheap-only batch in, not fitted": ["stale_model"],
    "cheap-only bams batch pending": ["pending_batches"],
    "cheap-only bams batch fitted": [],
    "plan 1 pending": ["pending_plan"],
    "plan 1 in, not computed": ["stale_model", "pending_plan"],
    "plan 1 computed": ["stale_model"],
    "plan 2 pending": ["pending_plan"],
    "plan 2 computed": ["stale_model"],
}


@pytest.mark.parametrize("stage", list(EXPECTED_NOTICES))
def test_report_says_first_what_state_the_study_is_in(study, stage):
    r = study.reports[stage]
    s = r["summary"]
    assert tuple(s) == SUMMARY_KEYS and s["truth"] is None
    assert [n["kind"] for n in s["notices"]] == EXPECTED_NOTICES[stage]
    # Banners come first: in the HTML right under the title, in summary.md right under
    # its heading, in the same order as in summary.json.
    html, md = r["html"], r["md"]
    body = html[html.index("<h1>") : html.index("<h2>")]
    assert body.count("class='banner") == len(s["notices"])
    head = md.split("\nPool of ")[0]
    for n in s["notices"]:
        assert f"data-kind='{n['kind']}'" in body
        assert f"> {n['text']}" in head
    if "stale_model" in EXPECTED_NOTICES[stage]:
        assert "class='banner warning'" in body and "> [!WARNING]" in head
        assert "Stale model" in body and f"bams-cli fit -w {study.ws}" in head
        assert "model stale (see the top of the report)" in html
    elif s["model"] is not None:
        assert "model up to date" in html


def test_a_pending_batch_names_its_hand_off_list_and_has_no_mean_yet(study):
    s = study.reports["first batch pending"]["summary"]
    (b1,) = s["batches"]
    assert b1["pending"] == b1["picks"] and b1["mean_f0"] is None and b1["n_f0"] == 0
    text = s["notices"][1]["text"]
    assert f"batch 1 ({b1['picks']} of {b1['picks']} picks, batches/batch-0001.csv)" in text
    assert "bams-cli ingest-results" in text
    after = study.reports["first results, no fit"]["summary"]["batches"][0]
    assert after["pending"] == 0 and after["mean_f0"] is not None and after["n_f0"] > 0


@pytest.mark.parametrize(
    ("stage", "batch", "strategy"),
    [
        ("cheap-only batch pending", 2, "mcm-gp"),
        ("cheap-only batch in, not fitted", 2, "mcm-gp"),
        ("cheap-only bams batch pending", 3, "bams"),
        ("cheap-only bams batch fitted", 3, "bams"),
        ("plan 2 computed", 3, "bams"),
    ],
)
def test_a_batch_of_cheap_level_picks_only_has_a_blank_mean(study, stage, batch, strategy):
    r = study.reports[stage]
    row = r["summary"]["batches"][batch - 1]
    assert row["batch"] == batch and row["strategy"] == strategy
    assert set(row["picks_per_level"]) == {"1"} and row["picks"] > 0
    assert row["mean_f0"] is None and row["mean_f0_se"] is None and row["n_f0"] == 0
    assert row["pending"] == (row["picks"] if "pending" in stage else 0)
    first = r["summary"]["batches"][0]
    assert first["mean_f0"] is not None  # the other batches keep theirs
    md_row = next(line for line in r["md"].splitlines() if line.startswith(f"| {batch} |"))
    assert md_row.endswith(f"|  | {row['pending']} | {row['abandoned']} |")


def test_the_estimate_shown_is_the_latest_computed_plan(study):
    for stage in ("initialised", "fitted", "plan 1 pending", "plan 1 in, not computed"):
        r = study.reports[stage]
        assert r["summary"]["estimates"] == [] and "No estimate yet" in r["html"]
    pending = study.reports["plan 1 pending"]["summary"]["notices"][0]["text"]
    assert "Estimate plan 1 awaits level-0 results for" in pending
    assert "estimates/plan-0001-handoff.csv" in pending and "no estimate is shown yet" in pending
    due = study.reports["plan 1 in, not computed"]["summary"]["notices"][1]["text"]
    assert "Estimate plan 1 has all its results" in due and "bams-cli estimate -w" in due
    for stage, shown in (("plan 1 computed", 1), ("plan 2 pending", 1), ("plan 2 computed", 2)):
        r = study.reports[stage]
        doc = json.loads((study.ws / "estimates" / f"estimate-{shown:04d}.json").read_text())
        assert [e["plan"] for e in r["summary"]["estimates"]] == [shown]
        assert [e["p_hat"] for e in r["summary"]["estimates"]] == [
            e["p_hat"] for e in doc["estimates"]
        ]
        assert f"From estimate plan {shown}." in r["html"] and "rate" in r["summary"]["figures"]
        assert "| gamma | p_hat |" in r["md"]
    text = study.reports["plan 2 pending"]["summary"]["notices"][0]["text"]
    assert "Estimate plan 2 awaits" in text and "the estimate shown is plan 1's" in text


@pytest.mark.parametrize("stage", list(EXPECTED_NOTICES))
def test_likely_failures_are_unknown_at_level_0_and_level_0_failures_are_confirmed(study, stage):
    r = study.reports[stage]
    s, level0 = r["summary"], r["level0"]
    gamma = s["study"]["gammas"][0]
    likely = [row["segment_id"] for row in s["diverse_failures"]]
    assert not set(likely) & set(level0)
    if s["model"] is not None:
        assert len(likely) == 5 and "pool_map" in s["figures"]
    else:
        assert likely == [] and s["figures"] == []
    failed = sorted((v, sid) for sid, v in level0.items() if v <= gamma)
    confirmed = s["confirmed_failures"]
    assert [(row["observed_f0"], row["segment_id"]) for row in confirmed] == failed
    assert all(row["fails_at_gamma"] == [gamma] and "difficulty" in row for row in confirmed)
    assert f"Confirmed failures (level 0, f <= a gamma): {len(failed)}" in r["md"]
    for sid in likely[:1] + [row["segment_id"] for row in confirmed[:1]]:
        assert f">{sid}<" in r["html"]


def test_the_plans_find_failures_the_report_confirms(study):
    # Without this, the confirmed-failure checks above could pass on empty lists.
    assert study.reports["plan 2 computed"]["summary"]["confirmed_failures"]


# ---------------------------------------------------------------------------------------
# A stale model contradicted by results ingested after it (issue 13, point 7)
# ---------------------------------------------------------------------------------------
def test_a_stale_model_is_a_banner_and_results_since_overrule_its_likely_failures(tmp_path):
    s = Study(tmp_path, TOY)
    ws = s.ws
    s.run("init", "-w", ws, "--settings-from", TOY / "settings.toml")
    identity = ("--columns", "x*", "--method", "identity", "--no-standardize")
    s.run("embed-reduce", "-w", ws, TOY / "segments.parquet", *identity)
    s.run("select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", "6")
    s.simulate_and_ingest(ws / "batches" / "batch-0001.parquet")
    s.run("fit", "-w", ws, "--restarts", "2")
    fresh = s.report("fresh")["summary"]
    gamma = fresh["study"]["gammas"][0]
    assert fresh["notices"] == [] and len(fresh["diverse_failures"]) == 5
    # The simulation team then reports, at level 0, that the first likely failure passed
    # (a value above every gamma) and the second failed, and nobody refits.
    passed, failed = (row["segment_id"] for row in fresh["diverse_failures"][:2])
    p_passed = fresh["diverse_failures"][0]["p_n"]
    results = tmp_path / "hand-run.parquet"
    pq.write_table(
        pa.table(
            {
                "segment_id": [passed, failed],
                "fidelity": [0, 0],
                "value": [gamma + 0.2, gamma - 0.1],
            }
        ),
        results,
    )
    s.run("ingest-results", "-w", ws, results, "--allow-unselected")
    stale = s.report("stale")
    summary = stale["summary"]
    assert [n["kind"] for n in summary["notices"]] == ["stale_model"]
    assert summary["model"]["fresh"] is False
    # The banner opens the HTML and summary.md, not a caption further down.
    html = stale["html"]
    assert html.index("class='banner warning'") < html.index("<h2>")
    # summary.md: the title, the headline, then the banner, before any table.
    md = stale["md"].splitlines()
    assert md[2].startswith("**No failure-rate estimate yet; ")
    assert md[4:6] == ["> [!WARNING]", f"> {summary['notices'][0]['text']}"]
    likely = {row["segment_id"] for row in summary["diverse_failures"]}
    assert passed not in likely and failed not in likely and len(likely) == 5
    (confirmed,) = summary["confirmed_failures"]
    assert confirmed["segment_id"] == failed and confirmed["observed_f0"] == gamma - 0.1
    # The segment seen passing is nowhere listed as a failure, though the model still
    # gives it a high failure probability.
    assert p_passed > 0.3
    assert f">{passed}<" not in html and passed not in stale["md"]
    s.run("fit", "-w", ws, "--restarts", "2")
    refit = s.report("refit")["summary"]
    assert refit["notices"] == []
    assert passed not in {row["segment_id"] for row in refit["diverse_failures"]}
    assert [row["segment_id"] for row in refit["confirmed_failures"]] == [failed]


@pytest.mark.parametrize("stage", list(EXPECTED_NOTICES))
def test_the_headline_and_failures_csv_say_what_the_log_says(study, stage):
    r = study.reports[stage]
    s = r["summary"]
    gammas = s["study"]["gammas"]
    # Brute force from the observation log: confirmed = a level-0 value at or below a
    # gamma; a lead = no level-0 value and a cheaper level at or below the first gamma.
    confirmed = {sid for sid, v in r["level0"].items() if v <= max(gammas)}
    cheap = r["cheap"].filter(pl.col("value") <= gammas[0])
    leads = set(cheap["segment_id"].to_list()) - set(r["level0"])
    csv = r["failures"]
    assert csv.height == s["failures_found"]["count"] == len(confirmed) + len(leads)
    if csv.height:
        by_status = dict(csv.group_by("status").agg(pl.col("segment_id")).iter_rows())
        assert set(by_status.get("confirmed", [])) == confirmed
        assert set(by_status.get("lead", [])) == leads
        for sid, status, found_by in csv.select("segment_id", "status", "found_by").iter_rows():
            if status == "confirmed":
                batch = r["level0_batch"][sid]
                assert found_by == (f"batch {batch}" if batch is not None else found_by)
                assert batch is not None or found_by.startswith("plan ")
                assert csv.filter(pl.col("segment_id") == sid)["value_0"][0] == r["level0"][sid]
    head = s["headline"]["text"]
    n_conf = sum(v <= gammas[0] for v in r["level0"].values())
    assert f"; {n_conf} failure{'s' if n_conf != 1 else ''} confirmed at level 0" in head
    assert f"; {r['runs0']} level-0" in head
    if s["estimates"]:
        e = next(e for e in s["estimates"] if e["gamma"] == gammas[0])
        assert head.startswith("failure rate ") and f"{100 * e['confidence']:g}% interval" in head
        doc = json.loads((study.ws / "estimates" / f"estimate-{e['plan']:04d}.json").read_text())
        made_of = doc["staging"]["plans"] if doc.get("staging") else [e["plan"]]
        by = f"plan {made_of[0]}" if len(made_of) == 1 else f"plans {made_of[0]}"
        assert f"among {e['n_sampled']} segments sampled by {by}" in s["headline"]["width"]
        if stage == "plan 2 computed":  # the second stage of a two-stage estimate
            assert made_of == [1, 2] and "sampled by plans 1 and 2" in s["headline"]["width"]
    else:
        assert head.startswith("no failure-rate estimate yet")
    # It leads summary.md and the HTML, above every table.
    assert r["md"].splitlines()[2].startswith(f"**{head[:1].upper()}{head[1:]}.**")
    assert r["html"].index("id='headline'") < r["html"].index("<h2>")


@pytest.mark.parametrize("stage", list(EXPECTED_NOTICES))
def test_trends_every_estimate_and_the_stopping_signal(study, stage):
    r = study.reports[stage]
    s = r["summary"]
    gamma = s["study"]["gammas"][0]
    log = r["log"].filter(pl.col("active"))
    trends = s["trends"]
    assert [t["batch"] for t in trends] == [b["batch"] for b in s["batches"]]
    so_far = set()
    for t, b in zip(trends, s["batches"], strict=True):
        found = log.filter(
            (pl.col("fidelity") == 0) & (pl.col("batch") == t["batch"]) & (pl.col("value") <= gamma)
        )["segment_id"].unique()
        so_far |= set(found.to_list())
        assert (t["confirmed"], t["confirmed_so_far"]) == (found.len(), len(so_far))
        assert t["cost"] == pytest.approx(b["cost"])
        assert sum(t["cost_per_level"].values()) == pytest.approx(b["cost"])
        if b["strategy"] == "bams":  # a model-driven batch stores J before and after
            assert t["j_after"] < t["j_before"]
            assert t["j_decrease_per_cost"] == pytest.approx(
                (t["j_before"] - t["j_after"]) / t["cost"]
            )
        else:
            assert t["j_before"] is None and t["j_decrease_per_cost"] is None
    history = s["estimate_history"]
    made = sorted(int(p.stem[9:]) for p in (study.ws / "estimates").glob("estimate-*.json"))
    done = {"plan 1 computed": [1], "plan 2 pending": [1], "plan 2 computed": [1, 2]}
    assert [h["plan"] for h in history] == done.get(stage, [])
    assert made[: len(history)] == [h["plan"] for h in history] or stage != "plan 2 computed"
    stop = s["stopping"]
    last = [t["j_decrease_per_cost"] for t in trends[-3:] if t["j_decrease_per_cost"] is not None]
    assert stop["j_decrease_per_cost_last_batches"] == pytest.approx(last)
    if r["scores"] is not None and s["model"] is not None:
        known = set(r["level0"])
        p0 = r["scores"].filter(~pl.col("segment_id").is_in(list(known)))["p_0"].to_numpy()
        top = np.sort(p0)[::-1][: stop["next_batch_level0_runs"]].sum()
        assert stop["expected_failures_next_batch"] == pytest.approx(top)
    if history:
        h = history[-1]
        want = np.ceil(h["samples_K"] * ((h["ci_high"] - h["ci_low"]) / h["p_hat"]) ** 2)
        assert stop["samples_for_width_equal_to_rate"] == want
        assert "An interval as wide as the rate itself would need about" in r["md"]
    else:
        assert stop["samples_for_width_equal_to_rate"] is None
