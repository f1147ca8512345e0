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

from bams_cli import report as rep
from bams_cli.report import SUMMARY_KEYS
from bams_cli.state import schemas
from bams_cli.state.io import read_metadata
from bams_cli.state.workspace import Workspace
from tests import test_loop
from tests.conftest import STAGED_PLAN, invoke, ok, simulate_and_ingest

#: Headless Chromium, or a skip (in CI a failure): test_loop's fixture.
chromium = test_loop.chromium

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
            **self.stored_models(w),
        }
        return self.reports[stage]

    def stored_models(self, w: Workspace) -> dict:
        """What the workspace holds right now of the models, batches and plans (later steps
        replace scores.parquet and add snapshots): each model's p_0 by the hash of the log it
        was fitted on, the batch each snapshot follows, the batches' and plans' metadata."""
        models, after = {}, {}
        for path in [*sorted((self.ws / "history").glob("*.parquet")), w.scores_path]:
            if path.exists():
                h = read_metadata(path)["observations_hash"]
                models.setdefault(h, pq.read_table(path, columns=["p_0"])["p_0"].to_numpy())
                if path.parent.name == "history":
                    after[int(path.stem[-4:])] = h
        plans = {
            int(path.stem[5:]): {
                "meta": read_metadata(path),
                "sampled": pl.read_parquet(path).filter(pl.col("stratum") == "sampled"),
            }
            for path in sorted((self.ws / "estimates").glob("plan-*.parquet"))
        }
        return {
            "models": models,
            "snapshot_after": after,
            "batch_meta": {
                b: read_metadata(schemas.batch_path(self.ws, b)) for b in w.batch_numbers()
            },
            "plans": plans,
            "ids": w.read_pool()[0],
        }


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
    # Two stages, to keep the walk short: the default three are walked by
    # tests/test_estimate.py and, through `loop`, by tests/test_loop_driver.py.
    s.run("estimate", "-w", ws, *STAGED_PLAN, "--stages", "2", "--samples", "40")
    s.report("plan 1 pending")
    s.simulate_and_ingest(ws / "estimates" / "plan-0001-handoff.csv")
    s.report("plan 1 in, not computed")
    s.run("estimate", "-w", ws)
    s.report("plan 1 computed")
    s.run("fit", "-w", ws, "--restarts", "2")
    s.run("estimate", "-w", ws, *STAGED_PLAN, "--samples", "40")
    s.report("plan 2 pending")
    s.simulate_and_ingest(ws / "estimates" / "plan-0002-handoff.csv")
    s.run("estimate", "-w", ws)
    s.report("plan 2 computed")
    # Discovery again after the estimate: a BAMS batch with level-0 picks, chosen by a
    # model fitted on the plans' results (no snapshot of it: its newest results were a
    # plan's), so the report's prediction for it comes from the current scores.
    s.run("fit", "-w", ws, "--restarts", "2")
    s.run("select", "-w", ws, "--strategy", "bams", "--budget", "4", *bams)
    s.simulate_and_ingest(ws / "batches" / "batch-0004.parquet")
    s.report("discovery after the estimate")
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
    "discovery after the estimate": ["stale_estimate", "stale_model"],
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
    n_batches = len(s["batches"])
    assert f"segments; {n_batches} batch{'' if n_batches == 1 else 'es'};" in md  # not "1 batches"
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
    # Its own picks bring no level-0 value. An estimate sample may have run some of its
    # segments at level 0 since: the mean counts exactly those (a BAMS batch's cheap picks
    # sit where p_n is high, which the estimate's design favours).
    ingested = {"plan 2 computed": (1, 2)}.get(stage, ())
    sampled0: set[str] = set()
    for n in ingested:
        plan = pl.read_parquet(study.ws / "estimates" / f"plan-{n:04d}.parquet")
        sampled0 |= set(plan.filter(pl.col("stratum") == "sampled")["segment_id"].to_list())
    batch_ids = set(
        pq.read_table(study.ws / "batches" / f"batch-{batch:04d}.parquet")["segment_id"].to_pylist()
    )
    n_f0 = len(batch_ids & sampled0)
    assert row["n_f0"] == n_f0
    assert (row["mean_f0"] is None) == (n_f0 == 0)
    assert row["mean_f0_se"] is None or n_f0 > 1
    assert row["pending"] == (row["picks"] if "pending" in stage else 0)
    first = r["summary"]["batches"][0]
    assert first["mean_f0"] is not None  # the other batches keep theirs
    md_row = next(line for line in r["md"].splitlines() if line.startswith(f"| {batch} |"))
    if n_f0 == 0:
        assert md_row.endswith(f"|  | {row['pending']} | {row['abandoned']} |")
    else:
        assert md_row.endswith(
            f"| {row['mean_f0']:.3g}"
            + ("" if row["mean_f0_se"] is None else f" ({row['mean_f0_se']:.2g})")
            + f" | {row['pending']} | {row['abandoned']} |"
        )


def test_the_estimate_shown_is_the_latest_computed_plan(study):
    for stage in ("initialised", "fitted", "plan 1 pending", "plan 1 in, not computed"):
        r = study.reports[stage]
        assert r["summary"]["estimates"] == [] and "No estimate yet" in r["html"]
    pending = study.reports["plan 1 pending"]["summary"]["notices"][0]["text"]
    assert "Estimate plan 1 awaits level-0 results for" in pending
    assert "estimates/plan-0001-handoff.csv" in pending and "no estimate is shown yet" in pending
    due = study.reports["plan 1 in, not computed"]["summary"]["notices"][1]["text"]
    assert "Estimate plan 1 has all its results" in due and "bams-cli estimate -w" in due
    shown_by_stage = (
        ("plan 1 computed", 1),
        ("plan 2 pending", 1),
        ("plan 2 computed", 2),
        ("discovery after the estimate", 2),
    )
    for stage, shown in shown_by_stage:
        r = study.reports[stage]
        doc = json.loads((study.ws / "estimates" / f"estimate-{shown:04d}.json").read_text())
        assert [e["plan"] for e in r["summary"]["estimates"]] == [shown]
        assert [e["p_hat"] for e in r["summary"]["estimates"]] == [
            e["p_hat"] for e in doc["estimates"]
        ]
        assert f"From estimate plan {shown}; 90% gamma intervals." in r["html"]
        # One gamma: its estimate is in the trend's plot, beside the model's rate.
        assert "rate_band" in r["summary"]["figures"] and "rate" not in r["summary"]["figures"]
        assert "| gamma | p_hat |" in r["md"]
    text = study.reports["plan 2 pending"]["summary"]["notices"][0]["text"]
    assert "Estimate plan 2 awaits" in text and "the estimate shown is plan 1's" in text


def test_an_estimate_older_than_the_latest_batch_says_so_under_the_headline(study):
    # Batch 4 was selected and its results ingested after plan 2 was drawn: the headline's
    # rate does not count them, and the sentence right under it says so, in both forms.
    r = study.reports["discovery after the estimate"]
    log = r["log"]
    n = log.filter(pl.col("active") & (pl.col("batch") == 4)).height
    text = (
        f"The estimate shown predates the latest discovery: batch 4 was selected and {n} "
        "discovery results were ingested after plan 2, on which it rests, was drawn, and its "
        f"rate does not count them; `bams-cli estimate -w {study.ws} --plan` draws a new "
        "sample that does."
    )
    assert r["summary"]["notices"][0] == {
        "kind": "stale_estimate",
        "severity": "warning",
        "text": text,
    }
    headline, width = r["summary"]["headline"]["text"], r["summary"]["headline"]["width"]
    assert r["md"].split("\n\n")[1:3] == [
        f"**{headline[:1].upper()}{headline[1:]}.** {width}",
        f"> [!WARNING]\n> {text}",
    ]
    html = r["html"]
    start = html.index("<p id='headline'")
    nxt = html.index("<p", start + 1)  # the width note, then the banner
    banner = html.index("<div class='banner warning' role='alert' data-kind='stale_estimate'>")
    assert start < nxt < banner and html.index("<", html.index("</p>", nxt) + 4) == banner
    for stage in ("plan 1 computed", "plan 2 pending", "plan 2 computed"):
        kinds = [x["kind"] for x in study.reports[stage]["summary"]["notices"]]
        assert "stale_estimate" not in kinds


@pytest.mark.parametrize("stage", list(EXPECTED_NOTICES))
def test_likely_failures_are_unknown_at_level_0_and_level_0_failures_are_confirmed(study, stage):
    r = study.reports[stage]
    s, level0 = r["summary"], r["level0"]
    gamma = s["study"]["gammas"][0]
    likely = [row["segment_id"] for row in s["diverse_failures"]]
    assert not set(likely) & set(level0)
    # A value a row lacks (no cheap run: observed_f1) is null, as in failures_found, not "".
    for rows in (s["diverse_failures"], s["confirmed_failures"]):
        assert all(v != "" for row in rows for v in row.values())
    for b in s["batches"]:  # sums of run costs without float dust (0.1 x 200 is 20)
        assert b["cost"] == float(f"{b['cost']:.12g}")
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
    # Which gamma each count is at: the headline's the first, the found list's the largest.
    assert f"confirmed at level 0 (gamma {gammas[0]:g})" in head
    n_any = sum(v <= max(gammas) for v in r["level0"].values())
    assert f"({n_any} confirmed at level 0 at the largest gamma, {max(gammas):g}," in r["md"]
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
        # Between the stages the headline says the estimate rests on stage 1 alone.
        remains = doc["staging"]["stages_done"] < doc["staging"]["stages"]
        assert ("stage 1 of 2 only" in head) == remains
        assert remains == (stage in ("plan 1 computed", "plan 2 pending"))
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
    done = {
        "plan 1 computed": [1],
        "plan 2 pending": [1],
        "plan 2 computed": [1, 2],
        "discovery after the estimate": [1, 2],
    }
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


# ---------------------------------------------------------------------------------------
# Issue 14: the failures found, the plots that read in 12 dimensions, the trend's spend
# and prediction, each number brute-forced from the study's files as they were when the
# report was written
# ---------------------------------------------------------------------------------------
FINAL = "discovery after the estimate"


def _planned(r: dict) -> dict[str, int]:
    """segment -> the first estimate plan that sampled it."""
    out: dict[str, int] = {}
    for k, plan in sorted(r["plans"].items()):
        for sid in plan["sampled"]["segment_id"].to_list():
            out.setdefault(sid, k)
    return out


def _prior(r: dict, kind: str, number: int):
    """The p_0 a model fitted before the results of a batch or plan gave the pool: the
    model that chose it, else (a batch) the snapshot after the latest earlier batch, else
    (a plan drawn at the first gamma) the p_n the plan stored at its own rows."""
    meta = r["batch_meta"][number] if kind == "batch" else r["plans"][number]["meta"]
    if meta.get("model_hash") in r["models"]:
        return r["models"][meta["model_hash"]]
    if kind == "batch":
        earlier = [b for b in r["snapshot_after"] if b < number]
        return r["models"][r["snapshot_after"][max(earlier)]] if earlier else None
    if float(meta["plan_gamma"]) != r["summary"]["study"]["gammas"][0]:
        return None
    pos = {sid: i for i, sid in enumerate(r["ids"])}
    p = np.full(len(pos), np.nan)
    for sid, value in r["plans"][number]["sampled"].select("segment_id", "p_n").iter_rows():
        p[pos[sid]] = value
    return p


@pytest.mark.parametrize("stage", list(EXPECTED_NOTICES))
def test_the_failures_found_table_is_the_head_of_failures_csv(study, stage):
    r = study.reports[stage]
    found = r["summary"]["failures_found"]
    csv = r["failures"]
    assert found["columns"] == csv.columns
    assert (found["confirmed"], found["leads"]) == (
        csv.filter(pl.col("status") == "confirmed").height if csv.height else 0,
        csv.filter(pl.col("status") == "lead").height if csv.height else 0,
    )
    head = csv.head(rep.FAILURES_SHOWN)
    assert len(found["shown"]) == head.height
    for row, want in zip(found["shown"], head.iter_rows(named=True), strict=True):
        assert set(row) == set(want)
        for k, v in want.items():  # the CSV reads "0.2825" back as a number
            if v is None:
                assert row[k] is None
            elif isinstance(v, float):
                assert float(row[k]) == pytest.approx(v)
            else:
                assert str(row[k]) == str(v)
    html = r["html"]
    section = html[html.index("<h2>Failures found</h2>") : html.index("<h2>Trends")]
    if csv.height:
        assert section.count("<tr>") == head.height + 1  # and the header
        for sid in head["segment_id"]:
            assert f">{sid}<" in section
        assert "more</b> in <a href='failures.csv'>" not in section  # all shown
    else:
        assert "None yet" in section
    assert f"Failures found: {csv.height} ({found['confirmed']} confirmed" in r["md"]


def test_a_long_list_shows_its_head_and_counts_the_rest(study, tmp_path, monkeypatch):
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(study.ws, ws)
    csv = study.reports[FINAL]["failures"]
    assert csv.height >= 2  # the study finds more than one
    monkeypatch.setattr(rep, "FAILURES_SHOWN", 1)
    ok(study.runner, "report", "-w", ws)
    html = (ws / "report" / "report.html").read_text()
    section = html[html.index("<h2>Failures found</h2>") : html.index("<h2>Trends")]
    assert section.count("<tr>") == 2
    assert f"<b>{csv.height - 1} more</b> in <a href='failures.csv'>failures.csv</a>" in section
    assert pl.read_csv(ws / "report" / "failures.csv").height == csv.height  # all of them


@pytest.mark.parametrize("stage", list(EXPECTED_NOTICES))
def test_each_batch_s_failures_against_what_the_model_predicted_before_them(study, stage):
    r = study.reports[stage]
    s = r["summary"]
    gamma = s["study"]["gammas"][0]
    pos = {sid: i for i, sid in enumerate(r["ids"])}
    log = r["log"]
    level0 = log.filter(pl.col("active") & (pl.col("fidelity") == 0))
    rows = []
    for t in s["trends"]:
        b = t["batch"]
        mine = level0.filter(pl.col("batch") == b)
        runs = dict(log.filter(pl.col("batch") == b).group_by("fidelity").len().iter_rows())
        assert t["runs_per_level"] == {str(k): v for k, v in sorted(runs.items())}
        assert t["level0_results"] == mine.height
        p = _prior(r, "batch", b)
        if p is None or not mine.height:
            assert t["predicted_failures"] is None and t["predicted_by"] is None
            continue
        q = np.array([p[pos[sid]] for sid in mine["segment_id"]])
        assert t["predicted_failures"] == pytest.approx(q.sum())
        assert t["predicted_sd"] == pytest.approx(np.sqrt((q * (1 - q)).sum()))
        assert t["confirmed"] == int((mine["value"] <= gamma).sum())
        rows.append((b, q.sum(), (q * (1 - q)).sum(), t["confirmed"], mine.height))
    pv = s["predicted_vs_found"]
    if not rows:
        assert pv is None and "predicted" not in s["figures"]
        return
    assert pv["batches"] == [row[0] for row in rows]
    assert pv["predicted"] == pytest.approx(sum(row[1] for row in rows))
    assert pv["predicted_sd"] == pytest.approx(np.sqrt(sum(row[2] for row in rows)))
    assert pv["found"] == sum(row[3] for row in rows)
    assert pv["level0_results"] == sum(row[4] for row in rows)
    assert "predicted" in s["figures"] and "Before their results, the model expected" in r["md"]


def test_the_batch_after_the_estimate_is_predicted_by_the_model_that_chose_it(study):
    # Without this, the prediction checks above could pass on no prediction at all.
    t = study.reports[FINAL]["summary"]["trends"][-1]
    assert t["batch"] == 4 and t["level0_results"] > 0
    assert t["predicted_by"] == "the model that chose it" and t["predicted_failures"] > 0


@pytest.mark.parametrize("stage", list(EXPECTED_NOTICES))
def test_discovery_spend_apart_from_estimate_spend(study, stage):
    r = study.reports[stage]
    s = r["summary"]
    costs = [lv["cost"] for lv in s["study"]["levels"]]
    planned = _planned(r)
    parts = {"discovery": [], "estimate": [], "other": []}
    by_plan: dict[int, list] = {}
    for sid, lv, b in r["log"].select("segment_id", "fidelity", "batch").iter_rows():
        if b is not None:
            parts["discovery"].append(lv)
        elif lv == 0 and sid in planned:
            parts["estimate"].append(lv)
            by_plan.setdefault(planned[sid], []).append(sid)
        else:
            parts["other"].append(lv)
    for name, levels in parts.items():
        got = s["spend"][name]
        assert got["count"] == len(levels)
        assert got["cost"] == pytest.approx(sum(costs[lv] for lv in levels))
        for lv in range(len(costs)):
            assert got["per_level"][str(lv)]["count"] == levels.count(lv)
    assert sum(s["spend"][k]["cost"] for k in parts) == pytest.approx(s["simulation_spent"]["cost"])
    written = {b: m["written_at"] for b, m in r["batch_meta"].items()}
    gamma = s["study"]["gammas"][0]
    level0 = dict(
        r["log"]
        .filter(pl.col("active") & (pl.col("fidelity") == 0))
        .select("segment_id", "value")
        .iter_rows()
    )
    assert [p["plan"] for p in s["spend"]["plans"]] == sorted(r["plans"])
    for p in s["spend"]["plans"]:
        at = r["plans"][p["plan"]]["meta"]["written_at"]
        assert p["after_batch"] == max((b for b, w in written.items() if w <= at), default=0)
        sids = by_plan.get(p["plan"], [])
        assert p["count"] == len(sids)
        assert p["confirmed"] == len({sid for sid in sids if level0.get(sid, np.inf) <= gamma})
    for h in s["estimate_history"]:
        assert h["after_batch"] == next(
            p["after_batch"] for p in s["spend"]["plans"] if p["plan"] == h["plan"]
        )
        assert h["interval"] == "gamma"
    assert r["md"].count("Spend (results in): discovery batches ") == 1
    if s["trends"] or s["spend"]["plans"]:
        assert "spend, by purpose" in r["html"]


@pytest.mark.parametrize("stage", list(EXPECTED_NOTICES))
def test_the_p_n_distribution_counts_the_pool_and_where_the_runs_went(study, stage):
    r = study.reports[stage]
    s = r["summary"]
    d = s["p_distribution"]
    if r["scores"] is None or s["model"] is None:
        assert d is None and "p_distribution" not in s["figures"]
        return
    gamma = s["study"]["gammas"][0]
    edges = np.array(d["edges"])
    assert edges[0] == 0 and edges[-1] == 1 and np.all(np.diff(edges) > 0)

    def bin_of(p: float) -> int:  # [edges[i], edges[i+1]), the last bin closed
        return min(int(np.flatnonzero(edges <= p)[-1]), len(edges) - 2)

    p0 = dict(r["scores"].select("segment_id", "p_0").iter_rows())
    known = set(r["level0"])
    pool, unknown = np.zeros(len(edges) - 1), np.zeros(len(edges) - 1)
    expected = np.zeros(len(edges) - 1)
    for sid, p in p0.items():
        pool[bin_of(p)] += 1
        if sid not in known:
            unknown[bin_of(p)] += 1
            expected[bin_of(p)] += p
    assert d["pool"] == pool.tolist() and d["unknown"] == unknown.tolist()
    assert d["expected_failures"] == pytest.approx(expected.tolist())
    pos = {sid: i for i, sid in enumerate(r["ids"])}
    planned = _planned(r)
    runs, failed, without = np.zeros(len(edges) - 1), np.zeros(len(edges) - 1), 0
    level0 = r["log"].filter(pl.col("active") & (pl.col("fidelity") == 0))
    for sid, value, b in level0.select("segment_id", "value", "batch").iter_rows():
        kind, number = ("batch", b) if b is not None else ("plan", planned.get(sid))
        prior = None if number is None else _prior(r, kind, number)
        if prior is None:
            without += 1
            continue
        runs[bin_of(prior[pos[sid]])] += 1
        failed[bin_of(prior[pos[sid]])] += value <= gamma
    assert d["runs"] == runs.tolist() and d["runs_failed"] == failed.tolist()
    assert d["runs_without_prior"] == without
    assert "p_distribution" in s["figures"]
    if stage == FINAL:  # only batch 1, chosen at random before any model, has none
        assert without == level0.filter(pl.col("batch") == 1).height > 0


@pytest.mark.parametrize("stage", list(EXPECTED_NOTICES))
def test_the_breakdown_by_cluster_adds_up_to_the_study(study, stage):
    r = study.reports[stage]
    s = r["summary"]
    g = s["groups"]
    if s["model"] is None:
        assert g is None and "groups" not in s["figures"]
        return
    gamma = s["study"]["gammas"][0]
    rows = g["rows"]
    assert g["by"] == "cluster" and g["kind"] == "clusters" and len(rows) >= 1
    # The latest BAMS batch's --clusters, else the default.
    bams = [
        m
        for b, m in sorted(r["batch_meta"].items())
        if json.loads(m["options"])["strategy"] == "bams"
    ]
    want = json.loads(bams[-1]["options"])["clusters"] if bams else 6
    assert len(rows) == want
    if bams:  # what select ran on is recorded with the batch
        assert json.loads(bams[-1]["selection_plan"])["clusters"] == want
    assert sum(row["size"] for row in rows) == s["study"]["pool_size"]
    if r["scores"] is not None:
        p = r["scores"]["p_0"].to_numpy()
        assert sum(row["expected_failures"] for row in rows) == pytest.approx(p.sum())
    log = r["log"]
    for lv in range(len(s["study"]["levels"])):
        assert (
            sum(row["runs_per_level"][str(lv)] for row in rows)
            == log.filter(pl.col("fidelity") == lv).height
        )
    assert sum(row["confirmed"] for row in rows) == sum(v <= gamma for v in r["level0"].values())
    csv = r["failures"]
    leads = csv.filter(pl.col("status") == "lead").height if csv.height else 0
    assert sum(row["leads"] for row in rows) == leads
    assert "<h3>By cluster</h3>" in r["html"] and "By cluster: " in r["md"]


def test_the_cluster_view_has_the_clusters_the_batch_s_greedy_ran_on(study, tmp_path):
    """On a large pool the approximate plan runs on more clusters than --clusters; the
    batch records the plan it took, and the report's cluster view follows it."""
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(study.ws, ws)
    path = ws / "batches" / "batch-0004.parquet"
    table = pq.read_table(path)
    meta = dict(table.schema.metadata)
    assert json.loads(meta[b"bams.options"])["clusters"] == 2
    plan = json.loads(meta[b"bams.selection_plan"])
    plan["clusters"] = 3  # as the approximate plan on a large pool records it
    meta[b"bams.selection_plan"] = json.dumps(plan).encode()
    pq.write_table(table.replace_schema_metadata(meta), path)
    ok(study.runner, "report", "-w", ws)
    g = json.loads((ws / "report" / "summary.json").read_text())["groups"]
    assert g["kind"] == "clusters" and len(g["rows"]) == 3
    assert (
        sum(row["size"] for row in g["rows"])
        == study.reports[FINAL]["summary"]["study"]["pool_size"]
    )


def test_a_batch_without_a_recorded_plan_is_clustered_as_select_would_plan_it(tmp_path):
    """Batches from before the plan was recorded: the plan select makes for the pool size
    (at 1,000,000 segments, one cluster per 25,000 and K-means on a 50,000 sample)."""
    from bams_cli import defaults
    from bams_cli.pipeline.reporting import _select_clustering

    ws = Workspace(tmp_path)
    assert _select_clustering(ws, {}, 1_000_000, 2) == (
        1_000_000 // defaults.SELECT_CLUSTER_ROWS,
        defaults.SELECT_CLUSTER_FIT_MAX,
    )
    assert _select_clustering(ws, {}, 5_000, 2) == (defaults.CLUSTERS, None)


def test_report_by_a_pass_through_column(study, tmp_path):
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(study.ws, ws)
    r = study.reports[FINAL]
    ok(study.runner, "report", "-w", ws, "--by", "difficulty")
    s = json.loads((ws / "report" / "summary.json").read_text())
    g = s["groups"]
    assert g["by"] == "difficulty" and g["kind"] == "column"
    gamma = s["study"]["gammas"][0]
    segs = pl.read_parquet(AV / "segments.parquet", columns=["segment_id", "difficulty"])
    difficulty = dict(segs.iter_rows())
    scores = pl.read_parquet(ws / "scores.parquet")
    p0 = dict(scores.select("segment_id", "p_0").iter_rows())
    log = r["log"]
    csv = r["failures"]
    leads = set(csv.filter(pl.col("status") == "lead")["segment_id"]) if csv.height else set()
    rows = g["rows"]
    assert len(rows) == 5  # a numeric column: quantile bins
    for i, row in enumerate(rows):
        last = i == len(rows) - 1

        def inside(sid, row=row, last=last):
            v = difficulty[sid]
            return row["low"] <= v and (v <= row["high"] if last else v < row["high"])

        members = {sid for sid in difficulty if inside(sid)}
        assert row["size"] == len(members)
        assert row["expected_failures"] == pytest.approx(sum(p0[sid] for sid in members))
        assert row["expected_unconfirmed"] == pytest.approx(
            sum(p0[sid] for sid in members if sid not in r["level0"])
        )
        for lv in range(2):
            runs = log.filter(
                (pl.col("fidelity") == lv) & pl.col("segment_id").is_in(list(members))
            )
            assert row["runs_per_level"][str(lv)] == runs.height
        assert row["confirmed"] == sum(r["level0"].get(sid, np.inf) <= gamma for sid in members)
        assert row["leads"] == len(leads & members)
    assert sum(row["size"] for row in rows) == len(difficulty)
    html = (ws / "report" / "report.html").read_text()
    assert "<h3>By difficulty</h3>" in html and "groups" in s["figures"]
    before = {p.name: p.read_bytes() for p in (ws / "report").iterdir()}
    bad = invoke(study.runner, "report", "-w", ws, "--by", "no_such_column")
    assert bad.exit_code != 0 and "--by 'no_such_column'" in bad.stderr
    assert "it has difficulty" in bad.stderr
    assert {p.name: p.read_bytes() for p in (ws / "report").iterdir()} == before


@pytest.mark.parametrize("stage", list(EXPECTED_NOTICES))
def test_ground_truth_appears_only_with_truth(study, stage):
    r = study.reports[stage]
    s = r["summary"]
    assert s["truth"] is None
    assert "ground truth" not in r["html"].lower() and "data-truth" not in r["html"]
    assert "rate_truth" not in s["figures"] and "recall" not in s["figures"]
    assert "ground truth" not in r["md"].lower()


def test_with_truth_its_section_is_marked_and_last(study, tmp_path):
    import shutil

    ws = tmp_path / "ws"
    shutil.copytree(study.ws, ws)
    ok(study.runner, "report", "-w", ws, "--truth", AV / "truth.parquet")
    s = json.loads((ws / "report" / "summary.json").read_text())
    html = (ws / "report" / "report.html").read_text()
    assert s["truth"] is not None and {"rate_truth", "recall"} <= set(s["figures"])
    start = html.index("<section class='truth' id='ground-truth' data-truth='1'>")
    end = html.index("</section>", start)
    section = html[start:end]
    assert "<h2>Against ground truth (--truth)</h2>" in section
    assert "Only because --truth was given" in section
    assert "<h2>" not in html[end:]  # nothing follows it
    # Its plots sit inside it; outside it, only the batches' mean f says it used the truth.
    assert section.count("<img ") == 2
    outside = html[:start] + html[end:]
    assert outside.lower().count("ground truth") == 2  # that column and its note
    md = (ws / "report" / "summary.md").read_text()
    assert "**Against ground truth (--truth; a real study has none):** true rate" in md
    # summary.md's batch table says so too: its mean of the picks' true values is not the
    # mean of the level-0 runs that the table holds without --truth.
    assert "| mean level-0 f of picks (ground truth) (SE) |" in md


BROWSER_SIZES = [(1280, 720), (1920, 1080), (390, 844)]


@pytest.mark.parametrize(("width", "height"), BROWSER_SIZES)
def test_the_report_reads_in_a_browser_at_every_size(chromium, study, tmp_path, width, height):
    import subprocess
    import tempfile

    r = study.reports[FINAL]
    page = tmp_path / "report.html"
    page.write_text(r["html"])
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--hide-scrollbars", f"--window-size={width},{height}"]  # fmt: skip
    with tempfile.TemporaryDirectory() as profile:
        dom = subprocess.run(
            [chromium, *flags, f"--user-data-dir={profile}", "--virtual-time-budget=5000",
             "--dump-dom", page.as_uri()],
            capture_output=True, text=True, timeout=120,
        ).stdout  # fmt: skip
        shot = tmp_path / f"screen-{width}x{height}.png"
        subprocess.run(
            [chromium, *flags, f"--user-data-dir={profile}", f"--screenshot={shot}", page.as_uri()],
            capture_output=True, timeout=120,
        )  # fmt: skip
    n_img = len(r["summary"]["figures"])
    assert n_img >= 5 and dom.count("<img ") == n_img
    title = dom[dom.index("<title>") + 7 : dom.index("</title>")]
    assert title.startswith(f"images-ok {n_img}/{n_img} headline-in-first-screen "), title
    # The page never scrolls sideways: wide tables scroll within their own box.
    assert " fits-width " in title, title
    assert shot.stat().st_size > 10_000  # the first screen, drawn


def test_estimate_and_the_report_name_the_interval_s_kind(tmp_path):
    s = Study(tmp_path, TOY)
    ws = s.ws
    s.run("init", "-w", ws, "--settings-from", TOY / "settings.toml")
    identity = ("--columns", "x*", "--method", "identity", "--no-standardize")
    s.run("embed-reduce", "-w", ws, TOY / "segments.parquet", *identity)
    s.run("select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", "6")
    s.simulate_and_ingest(ws / "batches" / "batch-0001.parquet")
    s.run("fit", "-w", ws, "--restarts", "2")
    s.run("estimate", "-w", ws, *STAGED_PLAN, "--stages", "1", "--samples", "30")
    s.simulate_and_ingest(ws / "estimates" / "plan-0001-handoff.csv")
    out = s.run("estimate", "-w", ws).stdout
    assert "90% gamma interval)" in out  # the table's title
    assert "interval: 90% gamma interval, allowing for one failure the sample may" in out
    head = s.report("gamma")["summary"]["headline"]["width"]
    assert "it is a gamma interval" in head
    out = s.run("estimate", "-w", ws, "--interval", "fay-feuer", "--confidence", "0.8").stdout
    # (the last line may name the gamma interval of the estimate this one replaced)
    table = out.split("\nestimate written to ")[0]
    assert "80% fay-feuer interval)" in table and "gamma interval" not in table
    assert "interval: 80% fay-feuer interval, Fay and Feuer's, allowing for one missed" in out
    r = s.report("fay-feuer")
    assert "it is Fay and Feuer's interval" in r["summary"]["headline"]["width"]
    assert "80% Fay-Feuer intervals." in r["html"]
    assert r["summary"]["estimate_history"][-1]["interval"] == "fay-feuer"


def _estimate_row(**over):
    row = {
        "gamma": 0.0,
        "p_hat": 0.0,
        "ci_low": 0.0,
        "ci_high": 0.49,
        "confidence": 0.9,
        "failures_sampled": 0,
        "failures_known": 0,
        "n_sampled": 3,
        "plan": 1,
        "plans": [1],
        "interval": "gamma",
        "stages_done": 1,
        "stages": 1,
    }
    return row | over


SPENT = {"per_level": {"0": {"count": 20}, "1": {"count": 40}}}


def test_a_headline_with_no_failure_sampled_is_an_upper_limit_not_a_rate_of_zero():
    h = rep.headline([_estimate_row()], [], [], SPENT, 0.0)
    assert h["text"].startswith(
        "failure rate at most 0.49 per segment (no failure in the estimate's sample; "
        "90% interval 0 to 0.49); 0 failures confirmed at level 0"
    )
    assert "0.0e+00" not in h["text"]


def test_a_headline_interval_keeps_three_significant_digits():
    # A user's [0.01049, 0.0143] read "0.01 to 0.014": the lower end lost a twentieth.
    e = _estimate_row(p_hat=0.01184, ci_low=0.01049, ci_high=0.0143, failures_sampled=40)
    h = rep.headline([e], [], [], SPENT, 0.0)
    assert "90% interval 0.0105 to 0.0143" in h["text"]


def test_a_headline_over_abandoned_segments_is_a_range_and_says_a_stage_remains():
    note = "1 planned segments abandoned: the interval runs from ..."
    e = _estimate_row(
        p_hat=0.1546, p_hat_low=6.67e-5, p_hat_high=0.1546, ci_low=6.67e-5, ci_high=0.733,
        abandoned=1, failures_known=1, stages_done=1, stages=2, variance_note=note,
    )  # fmt: skip
    h = rep.headline([e], [], [], SPENT, 0.0)
    assert h["text"].startswith(
        "failure rate between 6.67e-05 and 0.155 per segment (the 1 abandoned segment all "
        "passing, then all failing); 90% interval 6.67e-05 to 0.733; stage 1 of 2 only: the "
        "next `estimate --plan` draws the rest; "
    )
    assert "among 3 segments sampled by plan 1 (1 of them abandoned)" in h["width"]
    # Stage 1 of three: the next plan draws stage 2, not the rest.
    h3 = rep.headline([{**e, "stages": 3}], [], [], SPENT, 0.0)
    assert "stage 1 of 3 only: the next `estimate --plan` draws stage 2; " in h3["text"]
    assert "narrow it. 1 planned" in h["width"]  # a sentence of its own, capitalised
    # One stage of one: nothing remains, and a sampled failure gives a rate.
    h = rep.headline([_estimate_row(p_hat=0.002, failures_sampled=2)], [], [], SPENT, 0.0)
    assert h["text"].startswith("failure rate 0.002 per segment (about 1 in 500); 90% interval")
    assert "stage" not in h["text"]


def test_a_breakdown_whose_model_disagrees_with_the_estimate_says_so():
    # A trial's --by breakdown put 0.6 unconfirmed failures in a group that held 54, beside
    # a headline estimate that was right: the model's per-group numbers carry a caveat when
    # its total lies outside the estimate's interval, and none when inside.
    from bams_cli.pipeline.reporting import _model_against_estimate
    from bams_cli.report import group_lines

    def groups(*expected):
        rows = [{"group": f"g{i}", "size": 100, "expected_failures": x,
                 "expected_unconfirmed": x, "runs_per_level": {"0": 1}, "confirmed": 0,
                 "leads": 0} for i, x in enumerate(expected)]  # fmt: skip
        return {"by": "kind", "how": "each value of kind", "rows": rows}

    est = [{"gamma": -0.5, "p_hat": 0.012, "ci_low": 0.008, "ci_high": 0.018}]
    low = groups(8.6, 7.4)  # 16 in the pool against 144 [96, 216]
    _model_against_estimate(low, est, -0.5, 12_000)
    assert low["caveat"].startswith("The model expects 16 failures in the pool, below the ")
    assert any(line == f"**{low['caveat']}.**" for line in group_lines(low))
    inside = groups(80.0, 70.0)
    _model_against_estimate(inside, est, -0.5, 12_000)
    assert "caveat" not in inside and not any(line.startswith("**") for line in group_lines(inside))
    other = groups(8.6, 7.4)  # an estimate at another gamma says nothing about this one
    _model_against_estimate(other, est, 0.0, 12_000)
    assert "caveat" not in other


def test_a_stored_model_is_read_at_its_own_column_for_a_gamma(tmp_path):
    # Snapshots keep the gammas of their fit; after settings.toml reorders them, the report
    # read p_0 by position and showed another gamma's rate beside this one's failures.
    from bams_cli.pipeline.reporting import _snapshot_p
    from bams_cli.state import schemas
    from bams_cli.state.io import stamp

    table = pa.table({"p_0": [0.1, 0.2], "p_1": [0.7, 0.9]})
    path = tmp_path / "scores-after-batch-0001.parquet"
    pq.write_table(stamp(table, schemas.SCORES.version, {"gammas": [-0.5, 0.5]}), path)
    np.testing.assert_array_equal(_snapshot_p(path, 0.5), [0.7, 0.9])
    np.testing.assert_array_equal(_snapshot_p(path, -0.5), [0.1, 0.2])
    assert _snapshot_p(path, 0.25) is None  # a gamma added since: that model never had it
    old = tmp_path / "scores-after-batch-0002.parquet"  # written before gammas were recorded
    pq.write_table(stamp(table, schemas.SCORES.version), old)
    np.testing.assert_array_equal(_snapshot_p(old, 0.5), [0.1, 0.2])


def test_run_costs_are_summed_without_float_dust():
    from bams_cli.pipeline.reporting import _cost

    assert sum([0.1] * 200) != 20.0 and _cost(sum([0.1] * 200)) == 20.0
    assert _cost(sum([0.05] * 3)) == 0.15 and _cost(1e-7 / 3) == float(f"{1e-7 / 3:.12g}")
