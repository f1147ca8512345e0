"""A screened estimate through the CLI, as a Makefile drives it: ``estimate --plan --screen``
(cheap-level runs as a batch), their results, a refit, ``estimate --plan`` (the level-0
confirmation within the screen), its results, ``estimate``.

``core.screen``'s unbiasedness is shown by enumeration in tests/core/test_screen.py; here
the wiring: what the screen records is what the confirmation and the estimate use, and the
estimate is the two-phase Horvitz-Thompson sum computed by hand from the files and truth.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import polars as pl
import pyarrow.parquet as pq
import pytest

from bams_cli import defaults, schemas_json
from bams_cli.core import design as dz
from bams_cli.core import screen as sc
from bams_cli.pipeline import screening
from bams_cli.settings import Settings
from bams_cli.state.io import read_metadata_json
from bams_cli.state.schemas import SEGMENT_ID as SID
from bams_cli.state.workspace import Workspace
from tests.conftest import fitted_toy_study, invoke, ok, tree_hash, write_toy
from tests.jsonschema_subset import errors
from tests.test_estimate import strict_json

K = 60.0
SHARE = 0.3


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """400 toy2d segments (two levels, the cheap one at cost 0.1), a random mixed batch with
    level-0 and cheap runs, fitted."""
    from typer.testing import CliRunner

    runner = CliRunner()
    tmp = tmp_path_factory.mktemp("screen")
    return fitted_toy_study(runner, tmp, gammas="0.05,0.56", budget=20)


def _copy(fitted, tmp_path):
    src, truth = fitted
    shutil.copytree(src, tmp_path / "ws")
    return tmp_path / "ws", truth


def _plain_plan(runner, ws, samples):
    """`estimate --plan --screen off --samples S --json`: an unscreened stage 1, its summary."""
    args = ["estimate", "-w", ws, "--plan", "--screen", "off", "--samples", samples, "--json"]
    return strict_json(ok(runner, *args).stdout)


def _sim(runner, handoff, truth, out):
    ok(runner, "simulate", handoff, "--truth", truth, "-o", out)
    return out


def _own_leads_by_hand(ws, s1, leads, K2):
    """The screen's own leads, by hand: the screened segments (open leads aside) with the
    lowest cheap results in the log (ties by the screen's row order), floor(
    SCREEN_LEAD_SHARE K2) of them less the open leads (``core.screen.screen_leads``)."""
    cheap_now = (
        pl.read_parquet(ws / "observations.parquet")
        .filter(pl.col("fidelity") == 1)
        .group_by(SID)
        .agg(pl.col("value").mean())
    )
    ranked = (
        s1.select(SID)
        .with_row_index("_r")
        .join(cheap_now, on=SID, how="left")
        .filter(~pl.col(SID).is_in(sorted(leads)) & pl.col("value").is_not_null())
        .sort("value", "_r")
    )
    n_own = int(defaults.SCREEN_LEAD_SHARE * K2) - len(leads)
    assert 0 < n_own < ranked.height, "the toy takes no screen lead: nothing to check"
    return set(ranked[SID].head(n_own))


def test_a_screened_estimate_walks_screen_results_fit_confirm_results_estimate(fitted, tmp_path):
    from typer.testing import CliRunner

    ws, truth = _copy(fitted, tmp_path)
    runner = CliRunner()
    cheap_before = pl.read_parquet(ws / "observations.parquet").filter(pl.col("fidelity") == 1)
    model_at_screen = json.loads((ws / "model.json").read_text())
    scr = strict_json(
        ok(
            runner, "estimate", "-w", ws, "--plan", "--screen", SHARE, "--samples", K, "--json"
        ).stdout  # fmt: skip
    )
    assert errors(scr, schemas_json.schema("estimate-screen")) == []
    assert (scr["plan"], scr["batch"], scr["samples_K"], scr["screen_level"]) == (1, 2, K, 1)
    # The open leads (a cheap run at or below the largest gamma, no level-0 result), by hand:
    # in the screen with certainty, at no cost; the rest of the screen keeps its expected
    # size, its share of K at the cheap level's cost.
    obs0 = pl.read_parquet(ws / "observations.parquet")
    leads = set(cheap_before.filter(pl.col("value") <= 0.56)[SID]) - set(
        obs0.filter(pl.col("fidelity") == 0)[SID]
    )
    assert leads, "the batch left no open lead: the test has nothing to check"
    assert scr["leads_certain"] == len(leads)
    assert scr["screen_expected"] == pytest.approx(SHARE * K / 0.1 + len(leads))
    screen = pl.read_parquet(ws / "estimates" / "screen-0001.parquet")
    smeta = read_metadata_json(ws / "estimates" / "screen-0001.parquet")
    assert screen.height == 400 and smeta["series_K"] == K
    assert set(smeta["lead_ids"]) == leads
    s1 = screen.filter(pl.col("screened"))
    assert s1.height == scr["screened"] and (s1["stratum"] == "unknown").all()
    assert (screen.filter(pl.col(SID).is_in(sorted(leads)))["pi1"] == 1.0).all()
    assert leads <= set(s1[SID])
    # The batch runs the cheap level on S1 but for what the log already holds.
    batch = pl.read_parquet(ws / "batches" / "batch-0002.parquet")
    assert (batch["fidelity"] == 1).all() and (batch["strategy"] == "screen").all()
    held = set(cheap_before[SID]) & set(s1[SID])
    assert set(batch[SID]) == set(s1[SID]) - held
    assert scr["cheap_in_log"] == len(held) and scr["cheap_runs"] == batch.height
    assert scr["level0_left"] == pytest.approx(K - 0.1 * batch.height)
    assert not list((ws / "estimates").glob("plan-*.parquet"))  # no plan until confirmed
    # `estimate` before the confirmation names the steps still to come, and writes nothing.
    before = tree_hash(ws)
    r = invoke(runner, "estimate", "-w", ws)
    assert r.exit_code == 1 and "screen-0001.parquet awaits its level-0 confirmation" in r.stderr
    assert "batch 2" in r.stderr and "fit" in r.stderr and "--plan" in r.stderr
    assert tree_hash(ws) == before
    # The confirmation waits for the screen's results (exit code 3) and for the refit.
    r = invoke(runner, "estimate", "-w", ws, "--plan")
    assert r.exit_code == 3 and "batch 2 awaits results" in r.stderr
    ok(runner, "ingest-results", "-w", ws,
       _sim(runner, ws / "batches" / "batch-0002.csv", truth, tmp_path / "s.parquet"))  # fmt: skip
    r = invoke(runner, "estimate", "-w", ws, "--plan")
    assert r.exit_code != 0 and "fit" in r.stderr
    r = invoke(runner, "estimate", "-w", ws)  # the cheap runs are in: fit, then --plan
    assert r.exit_code == 1 and "awaits its level-0 confirmation" in r.stderr
    assert "batch 2" not in r.stderr and "fit" in r.stderr
    nxt = strict_json(ok(runner, "status", "-w", ws, "--json").stdout)["next"]
    assert nxt["step"] == "fit" and "confirmation" in nxt["text"]
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    nxt = strict_json(ok(runner, "status", "-w", ws, "--json").stdout)["next"]
    assert nxt["command"].endswith("--plan") and "screen for estimate plan 1" in nxt["text"]
    # A different K than the screen's is refused, naming the way out.
    r = invoke(runner, "estimate", "-w", ws, "--plan", "--samples", "80")
    assert r.exit_code == 1 and "--new-series" in r.stderr
    plan = strict_json(ok(runner, "estimate", "-w", ws, "--plan", "--json").stdout)
    assert errors(plan, schemas_json.schema("estimate-plan")) == []
    assert (plan["plan"], plan["weighting"], plan["stages"]) == (1, "screen", 1)
    # pi2 over S1, recomputed from the refitted scores: the plan's pi is pi1 pi2.
    scores = pl.read_parquet(ws / "scores.parquet")
    p_col = [c for c in scores.columns if c.startswith("p_")][-1]  # the largest gamma's
    s1p = s1.join(scores.select(SID, p_col), on=SID, how="left")
    K2 = min(sc.confirm_budget(K, 0.1, scr["cheap_runs"]), float(s1.height))
    # Under the prior the screen recorded for it, from the model the screen was drawn on:
    # this toy's cheap level tracks level 0, so near-full trust in the refitted p_n.
    ratio = screening.cheap_level_discrepancy(model_at_screen)
    assert ratio is not None and ratio < defaults.SCREEN_HINT_DISCREPANCY
    assert smeta["confirm_prior"] == list(defaults.RISK_MIX_PRIOR_CONFIRM)
    assert smeta["risk_prior"] == list(defaults.RISK_MIX_PRIOR)
    assert plan["screen"]["confirm_prior"] == smeta["confirm_prior"]
    post2 = dz.risk_posterior([], prior=defaults.RISK_MIX_PRIOR_CONFIRM)
    own = _own_leads_by_hand(ws, s1p, leads, K2)
    assert plan["screen"]["screen_leads"] == len(own)
    is_lead = s1p[SID].is_in(sorted(leads | own)).to_numpy()
    pi2 = sc.confirm_design(s1p[p_col].to_numpy(), K2=K2, posterior=post2, leads=is_lead).pi
    # The leads confirmed with certainty, the rest of K2 over the other screened segments.
    assert (pi2[is_lead] == 1).all() and plan["screen"]["leads_certain"] == len(leads)
    # What the checked model predicts of the confirmed design against uniform sampling of
    # K, by hand: phase 1's term over U and phase 2's over the screen as drawn.
    unk_p = screen.filter(pl.col("stratum") == "unknown").join(
        scores.select(SID, p_col), on=SID, how="left"
    )
    r = post2.risk(unk_p[p_col].to_numpy())
    a, s1_mask = unk_p["pi1"].to_numpy(), unk_p["screened"].to_numpy()
    b = np.ones(unk_p.height)
    by_id = dict(zip(s1p[SID].to_list(), pi2.tolist(), strict=True))
    b[s1_mask] = [by_id[x] for x in unk_p[SID].filter(s1_mask).to_list()]
    one = np.where(a >= 1, 0.0, r * (1 - a) / a).sum()
    two = np.where(b >= 1, 0.0, r * (1 - b) / (a * a * b))[s1_mask].sum()
    uni = (r * (1 - K / r.size) / (K / r.size)).sum()
    assert plan["predicted_vs_uniform"]["screen"] == pytest.approx((one + two) / uni, abs=1e-6)
    assert pi2[~is_lead].sum() == pytest.approx(K2 - len(leads | own), rel=1e-9)
    assert plan["samples_K"] == pytest.approx(K2) == pytest.approx(pi2.sum(), rel=1e-9)
    pi_by_id = dict(zip(s1[SID].to_list(), (s1["pi1"].to_numpy() * pi2).tolist(), strict=True))
    planned = pl.read_parquet(ws / "estimates" / "plan-0001.parquet")
    sampled = planned.filter(pl.col("stratum") == "sampled")
    assert set(sampled[SID]) <= set(s1[SID]) and sampled.height == plan["to_simulate"]
    assert leads | own <= set(sampled[SID])
    for sid, pi in zip(sampled[SID].to_list(), sampled["pi"].to_list(), strict=True):
        assert pi == pytest.approx(pi_by_id[sid], rel=1e-12)
    # The known stratum is the screen's: every segment with a level-0 result at the screen.
    known = planned.filter(pl.col("stratum") == "known")
    assert set(known[SID]) == set(screen.filter(pl.col("stratum") == "known")[SID])
    # The interval's allowance for an unseen failure, per gamma, by hand: the "mean"
    # allowance (pi1 times S1's risk-weighted mean pi2 outside S1), not the "min".
    pmeta = read_metadata_json(ws / "estimates" / "plan-0001.parquet")
    unk = screen.filter(pl.col("stratum") == "unknown").join(scores, on=SID, how="left")
    in_s1, pi1_u = unk["screened"].to_numpy(), unk["pi1"].to_numpy()
    post = dz.risk_posterior([])
    p_cols = sorted((c for c in scores.columns if c.startswith("p_")), key=lambda c: int(c[2:]))
    assert len(pmeta["w_model"]) == len(p_cols) == 2
    unk_lead = unk[SID].is_in(sorted(leads)).to_numpy()
    for g, col in enumerate(p_cols):
        # No unseen failure hides in an open lead, confirmed with certainty; the screen's
        # own leads stay in the stand-in at their pi2 of 1.
        risk = np.where(unk_lead, 0.0, post.allowance_risk(unk[col].to_numpy()))
        stand_in = (risk[in_s1] * pi2).sum() / risk[in_s1].sum()
        allow = np.where(in_s1, 0.0, pi1_u * stand_in)
        allow[in_s1] = pi1_u[in_s1] * pi2
        want = dz.unseen_failure_weight(risk, allow)
        assert pmeta["w_model"][g] == pytest.approx(want, rel=1e-9)
        floor = dz.unseen_failure_weight(risk, sc.min_allowance_pi(pi1_u, in_s1, pi2))
        assert floor > 1.01 * want  # the min allowance would be another number
    # A second plan while the confirmation awaits results is refused, as any plan's.
    assert invoke(runner, "estimate", "-w", ws, "--plan").exit_code == 3
    ok(runner, "ingest-results", "-w", ws,
       _sim(runner, ws / "estimates" / "plan-0001-handoff.csv", truth, tmp_path / "c.parquet"))  # fmt: skip
    out = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    assert errors(out, schemas_json.schema("estimate")) == []
    # The estimate is the two-phase HT sum, by hand from the truth: known failures, plus
    # each confirmed failure weighted by 1 / (pi1 pi2), over N.
    f = pl.read_parquet(truth).select(SID, pl.col("value_0").alias("f0"))
    for e in out["estimates"]:
        g = e["gamma"]
        fails = f.filter(pl.col("f0") <= g)
        n_known = known.join(fails, on=SID).height
        hits = sampled.join(fails, on=SID)
        total = n_known + float((1.0 / hits["pi"].to_numpy()).sum())
        assert e["p_hat_unbiased"] == pytest.approx(total / 400, rel=1e-12)
        assert e["failures_known"] == n_known and e["failures_sampled"] == hits.height
        assert e["ci_low"] <= e["p_hat"] <= e["ci_high"]
    # The design is random: segments confirmed at pi1 pi2 < 1 carry weights above 1 (a
    # wrong weight, 1 / pi2 alone, is caught by the pi check above).
    assert (sampled["pi"].to_numpy() < 1).any()
    # status and report read a study with a screen in it.
    assert invoke(runner, "status", "-w", ws).exit_code in (0, 3)
    ok(runner, "report", "-w", ws)


def test_cheap_results_already_in_the_log_are_not_run_again_and_cost_nothing(fitted, tmp_path):
    from typer.testing import CliRunner

    ws, truth = _copy(fitted, tmp_path)
    runner = CliRunner()
    # A screen at share 0.99 of a large K takes every unknown segment (pi1 = 1): the cheap
    # runs batch 1 already holds are in S1 and must not be asked for again.
    scr = strict_json(
        ok(
            runner, "estimate", "-w", ws, "--plan", "--screen", 0.9, "--samples", 300, "--json"
        ).stdout  # fmt: skip
    )
    cheap = pl.read_parquet(ws / "observations.parquet").filter(pl.col("fidelity") == 1)
    level0 = pl.read_parquet(ws / "observations.parquet").filter(pl.col("fidelity") == 0)
    unknown_cheap = set(cheap[SID]) - set(level0[SID])
    assert unknown_cheap, "batch 1 must hold cheap runs of segments without level 0"
    assert scr["screened"] == 400 - level0[SID].n_unique()  # every unknown segment
    assert scr["cheap_in_log"] == len(unknown_cheap)
    assert scr["cheap_runs"] == scr["screened"] - len(unknown_cheap)
    batch = pl.read_parquet(ws / "batches" / "batch-0002.parquet")
    assert not set(batch[SID]) & unknown_cheap
    assert scr["level0_left"] == pytest.approx(300 - 0.1 * scr["cheap_runs"])


@pytest.mark.parametrize(
    "args, message",
    [
        (["--screen", "1.5"], "must lie in (0, 1)"),
        (["--screen", "0"], "must lie in (0, 1)"),
        (["--screen", "0.3", "--design", "fixed"], "Poisson design"),
    ],
)
def test_a_screen_out_of_range_is_refused_and_changes_nothing(fitted, tmp_path, args, message):
    from typer.testing import CliRunner

    ws, _ = _copy(fitted, tmp_path)
    before = tree_hash(ws)
    r = invoke(CliRunner(), "estimate", "-w", ws, "--plan", *args)
    assert r.exit_code == 2 and message in r.stderr
    assert tree_hash(ws) == before


def _one_level_study(runner, tmp_path):
    """A fitted toy study with level 0 alone (no cheap level to screen with)."""
    seg, truth = write_toy(tmp_path / "data", n=120, seed=1)
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.56", "--dim", "2")
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize")  # fmt: skip
    ok(runner, "select", "-w", ws, "--strategy", "random", "--budget", "15")
    res = _sim(runner, ws / "batches" / "batch-0001.parquet", truth, tmp_path / "r.parquet")
    ok(runner, "ingest-results", "-w", ws, res)
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    return ws


def test_screen_needs_plan_and_a_cheap_level(tmp_path):
    from typer.testing import CliRunner

    runner = CliRunner()
    ws = _one_level_study(runner, tmp_path)
    before = tree_hash(ws)
    r = invoke(runner, "estimate", "-w", ws, "--plan", "--screen", "0.3")
    assert r.exit_code == 2 and "one fidelity level" in r.stderr
    r = invoke(runner, "estimate", "-w", ws, "--screen", "0.3")
    assert r.exit_code == 2 and "pass it with --plan" in r.stderr
    assert tree_hash(ws) == before


def test_new_series_drops_an_open_screen_for_a_plain_plan(fitted, tmp_path):
    from typer.testing import CliRunner

    ws, truth = _copy(fitted, tmp_path)
    runner = CliRunner()
    ok(runner, "estimate", "-w", ws, "--plan", "--screen", SHARE, "--samples", K)
    ok(runner, "abandon", "-w", ws, "--batch", "2", "--reason", "the cheap simulator is down")
    out = strict_json(
        ok(
            runner,
            "estimate",
            "-w",
            ws,
            "--plan",
            "--new-series",
            "--screen",
            "off",
            "--samples",
            "40",
            "--json",
        ).stdout  # fmt: skip
    )
    assert out["weighting"] != "screen" and out["plan"] == 1
    meta = read_metadata_json(ws / "estimates" / "plan-0001.parquet")
    assert "screen" not in meta
    assert pq.read_metadata(ws / "estimates" / "plan-0001.parquet").num_rows > 0
    # The next plan after it is a plain plan again, not a confirmation of the dropped screen.
    ok(runner, "ingest-results", "-w", ws,
       _sim(runner, ws / "estimates" / "plan-0001-handoff.csv", truth, tmp_path / "p.parquet"))  # fmt: skip
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    nxt = strict_json(ok(runner, "estimate", "-w", ws, "--plan", "--json").stdout)
    assert nxt["weighting"] != "screen" and nxt["plan"] == 2
    assert np.isfinite(nxt["samples_K"])


def test_a_screen_awaiting_confirmation_is_not_drawn_again_nor_confirmed_early(fitted, tmp_path):
    # Found in review: --screen again overwrote the open screen (K spent twice), and
    # --allow-pending confirmed before the screen's cheap runs were in.
    from typer.testing import CliRunner

    ws, truth = _copy(fitted, tmp_path)
    runner = CliRunner()
    ok(runner, "estimate", "-w", ws, "--plan", "--screen", SHARE, "--samples", K)
    before = tree_hash(ws)
    r = invoke(runner, "estimate", "-w", ws, "--plan", "--allow-pending")
    assert r.exit_code == 3 and "the screen's cheap runs, awaits" in r.stderr
    ok(runner, "ingest-results", "-w", ws,
       _sim(runner, ws / "batches" / "batch-0002.csv", truth, tmp_path / "s.parquet"))  # fmt: skip
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    before = tree_hash(ws)
    r = invoke(runner, "estimate", "-w", ws, "--plan", "--screen", SHARE)
    assert r.exit_code == 1 and "awaits its confirmation" in r.stderr and "--new-series" in r.stderr
    assert tree_hash(ws) == before
    # A new screen on the first one's results (--new-series) draws from fresh uniforms: on
    # the same ones, S1' = {u < pi1'} with pi1' fitted on S1's cheap runs is biased.
    first = read_metadata_json(ws / "estimates" / "screen-0001.parquet")
    ok(runner, "estimate", "-w", ws, "--plan", "--screen", SHARE, "--samples", K, "--new-series")
    again = read_metadata_json(ws / "estimates" / "screen-0001.parquet")
    assert first["rng_stream"][:2] == again["rng_stream"][:2]
    assert first["rng_stream"] != again["rng_stream"]


def test_a_screen_is_refused_beside_pending_level0_runs(fitted, tmp_path):
    from typer.testing import CliRunner

    ws, _ = _copy(fitted, tmp_path)
    runner = CliRunner()
    ok(
        runner,
        "estimate",
        "-w",
        ws,
        "--plan",
        "--samples",
        "30",
        "--stages",
        "1",
        "--screen",
        "off",
    )
    before = tree_hash(ws)
    r = invoke(runner, "estimate", "-w", ws, "--plan", "--screen", SHARE, "--allow-pending",
               "--new-series")  # fmt: skip
    assert r.exit_code == 3 and "level-0 runs await results" in r.stderr
    assert tree_hash(ws) == before


def test_a_pool_grown_since_the_screen_is_refused(fitted, tmp_path):
    # Found in review: segments added after the screen were in no stratum, never sampled.
    from typer.testing import CliRunner

    from bams_cli.errors import WorkspaceError
    from bams_cli.pipeline import screening
    from bams_cli.state.workspace import Workspace

    ws, _ = _copy(fitted, tmp_path)
    ok(CliRunner(), "estimate", "-w", ws, "--plan", "--screen", SHARE, "--samples", K)
    w = Workspace(ws)
    ids, _ = w.read_pool()
    table, _, index = screening.read_screen(w, 1, ids)
    assert (ids[index] == table[SID].to_numpy()).all()
    with pytest.raises(WorkspaceError, match="1 segments more than when the screen was drawn"):
        screening.read_screen(w, 1, np.append(ids, "new-segment"))
    with pytest.raises(WorkspaceError, match="no longer in the pool"):
        screening.read_screen(w, 1, ids[1:])


def test_a_new_plain_estimate_suggests_a_screen_where_the_cheap_level_tracks_level0(
    fitted, tmp_path
):
    import json
    import math

    from typer.testing import CliRunner

    from bams_cli import defaults
    from bams_cli.pipeline import screening

    ws, _ = _copy(fitted, tmp_path)
    hp = json.loads((ws / "model.json").read_text())["hyperparameters"]
    ratio = math.sqrt((hp["outputscales"][0] + hp["noise"][1]) / hp["outputscale0"])
    assert ratio < defaults.SCREEN_HINT_DISCREPANCY  # toy2d's cheap level is close
    out = _plain_plan(CliRunner(), ws, 40)
    (hint,) = [n for n in out["notes"] if "tracks level 0 closely" in n]
    assert f"{ratio:.2f} of its level-0 signal's" in hint and "--screen 0.3" in hint
    # A weak cheap level (its discrepancy as large as the signal), a one-level model, or
    # one without the hyperparameters: no suggestion.
    weak = {"hyperparameters": {"outputscale0": 1.0, "outputscales": [0.9], "noise": [0, 0.2]}}
    edge = {"hyperparameters": {"outputscale0": 1.0, "outputscales": [0.0], "noise": [0, 0.09]}}
    assert screening.screen_hint(weak, ws) is None
    assert screening.cheap_level_discrepancy(edge) == pytest.approx(0.3)
    assert screening.screen_hint(edge, ws) is None  # the threshold itself does not suggest
    one = {"hyperparameters": {"outputscale0": 1.0, "outputscales": [], "noise": [0.0]}}
    assert screening.screen_hint(one, ws) is None and screening.screen_hint({}, ws) is None


def test_screen_auto_screens_wherever_the_study_has_a_cheap_level(fitted, tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from bams_cli import defaults
    from bams_cli.pipeline import screening

    runner = CliRunner()
    ws, _ = _copy(fitted, tmp_path / "close")
    # toy2d's cheap level tracks level 0 (the hint's test): auto, the default, screens 0.3
    # of K.
    assert defaults.SCREEN == "auto"
    out = strict_json(ok(runner, "estimate", "-w", ws, "--plan", "--samples", K, "--json").stdout)
    assert errors(out, schemas_json.schema("estimate-screen")) == []
    assert out["screen_share"] == defaults.SCREEN_HINT_SHARE
    assert any(n.startswith("--screen auto: screening 0.3 of K") for n in out["notes"])
    # auto again while that screen awaits its confirmation does not draw another (the
    # batch is pending: exit 3, as a plain --plan).
    assert invoke(runner, "estimate", "-w", ws, "--plan", "--screen", "auto").exit_code == 3
    # A weaker cheap level: auto screens too, and says that the confirmation will take the
    # screen's lowest cheap results with certainty rather than the model's ranking; the
    # screen is planned under the lesser trust in p_n.
    ws2, _ = _copy(fitted, tmp_path / "far")
    monkeypatch.setattr(screening, "cheap_level_discrepancy", lambda model: 0.8)
    out = strict_json(
        ok(
            runner, "estimate", "-w", ws2, "--plan", "--screen", "auto", "--samples", K, "--json"
        ).stdout  # fmt: skip
    )
    assert errors(out, schemas_json.schema("estimate-screen")) == []
    assert out["screen_share"] == defaults.SCREEN_HINT_SHARE
    (note,) = [n for n in out["notes"] if n.startswith("--screen auto: screening 0.3 of K")]
    assert "0.80 of its level-0 signal's" in note and "lowest cheap results" in note
    # ... and that a cheap level unrelated to level 0 would make it cost, and the way out.
    assert "unrelated to level 0" in note and "--screen off" in note
    assert out["risk_prior"] == list(defaults.RISK_MIX_PRIOR_WEAK_CHEAP)
    assert out["confirm_prior"] == list(defaults.RISK_MIX_PRIOR_WEAK_CHEAP)
    # A study with one level has nothing to screen with: the staged plan, and why.
    assert screening.auto_share(
        {}, Settings(gammas=(0.5,)), K=50.0, n_unknown=400, n_observations=10
    ) == (  # fmt: skip
        None,
        "--screen auto: no screen (the model has no cheap level to screen with)",
    )
    # A word that is neither a share nor auto is a usage error.
    r = invoke(runner, "estimate", "-w", ws2, "--plan", "--screen", "half")
    assert r.exit_code == 2 and "auto, or off" in r.stderr


@pytest.mark.parametrize("ratio", [0.1, 0.8])
def test_a_plain_plan_trusts_p_n_less_where_the_cheap_level_does_not_track_level0(
    fitted, tmp_path, monkeypatch, ratio
):
    """The prior on lam follows the fitted cheap-level discrepancy (core.design.risk_prior):
    the plan records it, and its inclusion probabilities are the design chosen under it,
    recomputed by hand from the scores (not those of the other prior)."""
    from typer.testing import CliRunner

    from bams_cli import defaults
    from bams_cli.pipeline import screening

    ws, _ = _copy(fitted, tmp_path)
    monkeypatch.setattr(screening, "cheap_level_discrepancy", lambda model: ratio)
    out = _plain_plan(CliRunner(), ws, K)
    weak = ratio >= defaults.SCREEN_HINT_DISCREPANCY
    prior = defaults.RISK_MIX_PRIOR_WEAK_CHEAP if weak else defaults.RISK_MIX_PRIOR
    assert defaults.RISK_MIX_PRIOR_WEAK_CHEAP != defaults.RISK_MIX_PRIOR
    assert out["model_check"]["prior"] == list(prior)
    plan = pq.read_table(ws / "estimates" / "plan-0001.parquet").to_pylist()
    meta = read_metadata_json(ws / "estimates" / "plan-0001.parquet")
    known = {r[SID] for r in plan if r["stratum"] == "known"}
    # The open leads are sampled with certainty out of K (pipeline.estimation.open_leads);
    # the design is chosen over the rest of U with the rest of K.
    leads = set(meta["lead_ids"])
    assert len(leads) == out["leads_certain"]
    scores = pl.read_parquet(ws / "scores.parquet")
    unknown = ~scores[SID].is_in(sorted(known | leads)).to_numpy()
    assert meta["plan_gamma"] == 0.56  # p_1: the plan is drawn for the largest gamma
    p = scores["p_1"].to_numpy()[unknown]
    ids = scores[SID].to_numpy()[unknown]
    by_hand = {
        pr: dict(zip(ids, dz.choose_design(p, K=out["samples_K"] - len(leads),
                                           posterior=dz.risk_posterior([], prior=pr)).pi,
                     strict=True))
        for pr in (defaults.RISK_MIX_PRIOR, defaults.RISK_MIX_PRIOR_WEAK_CHEAP)
    }  # fmt: skip
    assert all(r["pi"] == 1.0 for r in plan if r[SID] in leads)
    sampled = [r for r in plan if r["stratum"] == "sampled" and r[SID] not in leads]
    assert sampled
    got = np.array([r["pi"] for r in sampled])
    want = np.array([by_hand[prior][r[SID]] for r in sampled])
    other = np.array([by_hand[defaults.RISK_MIX_PRIOR if weak else
                              defaults.RISK_MIX_PRIOR_WEAK_CHEAP][r[SID]] for r in sampled])  # fmt: skip
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert np.max(np.abs(got - other) / other) > 0.05
    # Less trust: the lowest-p_n segments get a larger share of K.
    lo = {pr: min(v.values()) for pr, v in by_hand.items()}
    assert lo[defaults.RISK_MIX_PRIOR_WEAK_CHEAP] > lo[defaults.RISK_MIX_PRIOR]
    # The plan's summary says how far p_n is trusted, and under which prior.
    r = ok(CliRunner(), "estimate", "-w", ws, "--plan", "--new-series", "--screen", "off",
           "--allow-pending", "--samples", K)  # fmt: skip
    (line,) = [x for x in r.stdout.splitlines() if x.lstrip().startswith("trust in p_n")]
    assert "of the failure mass unexplained by p_n" in line and "0 failures in 0 runs" in line
    assert line.rstrip().endswith(f"prior Beta({prior[0]:g}, {prior[1]:g})")


def test_an_estimate_keeps_the_prior_of_its_first_step_whatever_the_refit_says(
    fitted, tmp_path, monkeypatch
):
    """A screen drawn where the cheap level does not track level 0 draws pi1 under the
    lesser trust and records it; its confirmation keeps that prior though the refit on its
    cheap runs says the cheap level now tracks. A staged series' stage 2 keeps stage 1's."""
    from typer.testing import CliRunner

    from bams_cli import defaults
    from bams_cli.pipeline import screening

    runner = CliRunner()
    weak, strong = defaults.RISK_MIX_PRIOR_WEAK_CHEAP, defaults.RISK_MIX_PRIOR
    ws, truth = _copy(fitted, tmp_path / "screen")
    monkeypatch.setattr(screening, "cheap_level_discrepancy", lambda model: 0.8)
    ok(runner, "estimate", "-w", ws, "--plan", "--screen", SHARE, "--samples", K)
    screen = pl.read_parquet(ws / "estimates" / "screen-0001.parquet")
    smeta = read_metadata_json(ws / "estimates" / "screen-0001.parquet")
    # An explicit screen where the cheap level does not track: its confirmation is planned
    # as its pi1 was, not at the near-full trust of a tracking cheap level.
    assert smeta["risk_prior"] == smeta["confirm_prior"] == list(weak)
    scores = pl.read_parquet(ws / "scores.parquet")
    unknown = screen.filter(pl.col("stratum") == "unknown").join(
        scores.select(SID, "p_1"), on=SID, how="left"
    )
    is_lead = unknown[SID].is_in(smeta["lead_ids"]).to_numpy()
    pi1 = {
        pr: sc.screen_design(unknown["p_1"].to_numpy(), K=K, cost=0.1, share=SHARE,
                             posterior=dz.risk_posterior([], prior=pr), leads=is_lead).pi
        for pr in (weak, strong)
    }  # fmt: skip
    np.testing.assert_allclose(unknown["pi1"].to_numpy(), pi1[weak], rtol=1e-12)
    assert np.max(np.abs(pi1[weak] - pi1[strong])) > 1e-3
    ok(runner, "ingest-results", "-w", ws,
       _sim(runner, ws / "batches" / "batch-0002.csv", truth, tmp_path / "s.parquet"))  # fmt: skip
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    monkeypatch.setattr(screening, "cheap_level_discrepancy", lambda model: 0.1)
    plan = strict_json(ok(runner, "estimate", "-w", ws, "--plan", "--json").stdout)
    assert plan["weighting"] == "screen" and plan["model_check"]["prior"] == list(weak)
    assert plan["screen"]["confirm_prior"] == list(weak)
    # A screen written before the confirmation had a prior of its own: pi1's plans pi2.
    settings = Workspace(ws).require_initialised()
    for recorded, expected in (
        ({"risk_prior": list(weak)}, weak),
        ({"risk_prior": list(weak), "confirm_prior": [0.1, 10.0]}, (0.1, 10.0)),
    ):
        assert screening.recorded_confirm_prior({}, settings, recorded) == expected
    # Stage 2 of a staged series keeps stage 1's prior.
    ws2, truth = _copy(fitted, tmp_path / "staged")
    monkeypatch.setattr(screening, "cheap_level_discrepancy", lambda model: 0.8)
    one = _plain_plan(runner, ws2, K)
    assert (one["stage"], one["stages"], one["model_check"]["prior"]) == (
        1,
        defaults.STAGES,
        list(weak),
    )
    ok(runner, "ingest-results", "-w", ws2,
       _sim(runner, one["handoff"], truth, tmp_path / "r1.parquet"))  # fmt: skip
    ok(runner, "fit", "-w", ws2, "--restarts", "1")
    monkeypatch.setattr(screening, "cheap_level_discrepancy", lambda model: 0.1)
    two = strict_json(ok(runner, "estimate", "-w", ws2, "--plan", "--json").stdout)
    assert (two["stage"], two["model_check"]["prior"]) == (2, list(weak))
    # A new series takes the current model's.
    new = strict_json(
        ok(
            runner,
            "estimate",
            "-w",
            ws2,
            "--plan",
            "--new-series",
            "--screen",
            "off",
            "--allow-pending",
            "--json",
        ).stdout  # fmt: skip
    )
    assert (new["stage"], new["model_check"]["prior"]) == (1, list(strong))


def test_screen_auto_on_a_one_level_study_plans_plainly(tmp_path):
    from typer.testing import CliRunner

    runner = CliRunner()
    ws = _one_level_study(runner, tmp_path)
    for screen in ("auto", None):  # explicitly, and by default: no screen, and no word of one
        out = strict_json(
            ok(
                runner,
                "estimate",
                "-w",
                ws,
                "--plan",
                "--new-series",
                "--allow-pending",
                *(("--screen", screen) if screen else ()),
                "--json",
            ).stdout  # fmt: skip
        )
        assert "screen_file" not in out and out["weighting"] != "screen"
        assert not any("screen" in n for n in out["notes"]), out["notes"]


def test_screen_auto_does_not_screen_more_than_a_refit_conditions_on(fitted, tmp_path, monkeypatch):
    # At a million segments the default K buys ~28,000 cheap runs: more than fit conditions
    # on exactly (14,654 at its 2 GiB), so the confirmation would rest on a model that has
    # not seen most of them, after minutes of scoring. auto plans the staged estimate there.
    from typer.testing import CliRunner

    from bams_cli import defaults
    from bams_cli.core.conditioning_budget import max_conditioned
    from bams_cli.pipeline import screening

    cap = max_conditioned(defaults.FIT_CONDITION_MEMORY)
    assert cap == 14_654
    assert screening.refit_too_large(cap - 100, 100) is None
    note = screening.refit_too_large(cap - 99, 100)
    assert note is not None and f"{cap:,}" in note and "14,555 expected cheap runs" in note
    ws, _ = _copy(fitted, tmp_path)
    obs = Workspace(ws).read_observations().height
    # This toy's screen at K: 0.3 K / 0.1 cheap runs; a budget one short of holding them.
    n1 = 0.3 * float(K) / 0.1
    monkeypatch.setattr(defaults, "FIT_CONDITION_MEMORY", 10 * int(obs + n1 - 1) ** 2)
    out = strict_json(
        ok(CliRunner(), "estimate", "-w", ws, "--plan", "--samples", K, "--json").stdout
    )
    assert "screen_file" not in out and out["stage"] == 1 and out["stages"] == defaults.STAGES
    assert any("exceed the" in n and "a refit conditions on exactly" in n for n in out["notes"])


def _screened_and_refitted(runner, fitted, tmp_path):
    """A copy of the fitted study with its screen drawn (batch 2), simulated, ingested and
    refitted: what its confirmation is drawn from."""
    ws, truth = _copy(fitted, tmp_path)
    ok(runner, "estimate", "-w", ws, "--plan", "--screen", SHARE, "--samples", K)
    ok(runner, "ingest-results", "-w", ws,
       _sim(runner, ws / "batches" / "batch-0002.csv", truth, tmp_path / "s.parquet"))  # fmt: skip
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    return ws, truth


def test_select_warns_that_level0_picks_void_an_open_screen(fitted, tmp_path):
    # A discovery batch drawn while a screen awaits its confirmation: its level-0 results
    # would fall among the segments the screen counted as unknown, and the confirmation
    # would then refuse the screen. `select` draws it (the study may want it) and says so.
    from typer.testing import CliRunner

    runner = CliRunner()
    ws, truth = _screened_and_refitted(runner, fitted, tmp_path / "level0")
    out = strict_json(
        ok(runner, "select", "-w", ws, "--strategy", "random", "--budget", "3", "--json").stdout
    )
    assert out["picks_per_level"]["0"] == 3
    said = [w for w in out["warnings"] if "screen-0001.parquet awaits" in w]
    assert len(said) == 1 and "--new-series" in said[0] and "3 level-0 picks" in said[0]
    # And it is what happens: once their results are in, the confirmation refuses.
    ok(runner, "ingest-results", "-w", ws,
       _sim(runner, ws / "batches" / "batch-0003.csv", truth, tmp_path / "b.parquet"))  # fmt: skip
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    r = invoke(runner, "estimate", "-w", ws, "--plan")
    assert r.exit_code != 0 and "--new-series" in r.stderr
    # A batch of cheap runs alone leaves the screen be: no warning.
    ws2, _ = _screened_and_refitted(runner, fitted, tmp_path / "cheap")
    none = strict_json(
        ok(
            runner,
            "select",
            "-w",
            ws2,
            "--strategy",
            "random",
            "--mixed-fidelity",
            "--level0-share",
            "0",
            "--budget",
            "0.3",
            "--json",
        ).stdout  # fmt: skip
    )
    assert not any("screen-0001" in w for w in none["warnings"])


def test_a_screen_written_before_the_confirmation_prior_confirms_as_it_did(
    fitted, tmp_path, monkeypatch
):
    """A screen drawn by an older bams-cli (no ``confirm_prior`` in its metadata) is
    confirmed under the prior it drew pi1 with, as that version would have: pi = pi1 pi2
    with pi2 planned under Beta(0.5, 1), not the near-full trust of the new default. (The
    screen's own leads are off: half of K2 in them leaves a rest so small that both priors
    spread it evenly, and the test could not tell them apart.)"""
    from typer.testing import CliRunner

    monkeypatch.setattr(defaults, "SCREEN_LEAD_SHARE", 0.0)
    runner = CliRunner()
    ws, truth = _copy(fitted, tmp_path)
    scr = strict_json(
        ok(
            runner, "estimate", "-w", ws, "--plan", "--screen", SHARE, "--samples", K, "--json"
        ).stdout  # fmt: skip
    )
    path = ws / "estimates" / "screen-0001.parquet"
    table = pq.read_table(path)
    old = {k: v for k, v in table.schema.metadata.items() if k != b"bams.confirm_prior"}
    pq.write_table(table.replace_schema_metadata(old), path)
    assert "confirm_prior" not in read_metadata_json(path)
    ok(runner, "ingest-results", "-w", ws,
       _sim(runner, ws / "batches" / "batch-0002.csv", truth, tmp_path / "s.parquet"))  # fmt: skip
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    r = ok(runner, "estimate", "-w", ws, "--plan")
    (line,) = [x for x in r.stdout.splitlines() if x.lstrip().startswith("confirmation")]
    assert "pi2 within the screen planned under Beta(0.5, 1)" in line
    (line,) = [x for x in r.stdout.splitlines() if x.lstrip().startswith("screen leads")]
    assert "the screen's 0 lowest cheap results confirmed with certainty" in line
    plan_meta = read_metadata_json(ws / "estimates" / "plan-0001.parquet")
    assert plan_meta["screen"]["confirm_prior"] == list(defaults.RISK_MIX_PRIOR)
    s1 = pl.read_parquet(path).filter(pl.col("screened"))
    scores = pl.read_parquet(ws / "scores.parquet")
    p_col = [c for c in scores.columns if c.startswith("p_")][-1]
    p2 = s1.join(scores.select(SID, p_col), on=SID, how="left")[p_col].to_numpy()
    K2 = min(sc.confirm_budget(K, 0.1, scr["cheap_runs"]), float(s1.height))
    lead = s1[SID].is_in(read_metadata_json(path)["lead_ids"]).to_numpy()
    pi2 = {
        pr: sc.confirm_design(p2, K2=K2, posterior=dz.risk_posterior([], prior=pr), leads=lead).pi
        for pr in (defaults.RISK_MIX_PRIOR, defaults.RISK_MIX_PRIOR_CONFIRM)
    }
    assert (
        np.max(np.abs(pi2[defaults.RISK_MIX_PRIOR] - pi2[defaults.RISK_MIX_PRIOR_CONFIRM])) > 0.05
    )
    pi_old = s1["pi1"].to_numpy() * pi2[defaults.RISK_MIX_PRIOR]
    want = dict(zip(s1[SID].to_list(), pi_old.tolist(), strict=True))
    sampled = pl.read_parquet(ws / "estimates" / "plan-0001.parquet").filter(
        pl.col("stratum") == "sampled"
    )
    assert sampled.height > 0
    np.testing.assert_allclose(
        sampled["pi"].to_numpy(), [want[s] for s in sampled[SID].to_list()], rtol=1e-12
    )


def test_a_screen_takes_only_the_leads_run_at_its_own_level(tmp_path):
    """Three levels: the screen runs level 1. A lead seen at level 2 alone would cost the
    screen a level-1 run, so the screen leaves it to the design; the staged plan, which
    runs no cheap level, takes every open lead."""
    from typer.testing import CliRunner

    runner = CliRunner()
    # Level 1 tracks level 0; level 2 reads 0.6 low, so it fails where level 0 is under 1.16.
    ws, truth = fitted_toy_study(runner, tmp_path, costs="1,0.1,0.05", cheap_offsets={2: 0.6})
    obs = pl.read_parquet(ws / "observations.parquet")
    level0 = set(obs.filter(pl.col("fidelity") == 0)[SID])
    ran1 = set(obs.filter(pl.col("fidelity") == 1)[SID])
    cheap_fail = set(obs.filter((pl.col("fidelity") > 0) & (pl.col("value") <= 0.56))[SID])
    leads = cheap_fail - level0
    assert leads - ran1, "no lead seen at level 2 alone: the test has nothing to check"
    plan = ["estimate", "-w", ws, "--plan", "--samples", "200", "--json"]
    scr = strict_json(ok(runner, *plan, "--screen", SHARE).stdout)
    assert scr["leads_certain"] == len(leads & ran1)
    smeta = read_metadata_json(ws / "estimates" / f"screen-{scr['plan']:04d}.parquet")
    assert set(smeta["lead_ids"]) == leads & ran1
    staged = strict_json(
        ok(runner, *plan, "--new-series", "--screen", "off", "--allow-pending").stdout
    )
    assert staged["leads_certain"] == len(leads)
