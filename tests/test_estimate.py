"""The estimate command end to end: defaults read from one place, NaN-free JSON, --seed."""

from __future__ import annotations

import inspect
import json
import math
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from bams_cli import cli, console, defaults, pipeline
from bams_cli.core import design as dz
from bams_cli.core import estimate as core_estimate
from bams_cli.state.io import read_metadata_json, stamp
from bams_cli.state.schemas import SEGMENT_ID as SID
from tests.conftest import STAGED_PLAN, default_shares, fitted_toy_study, invoke, ok, write_toy


@pytest.mark.parametrize(
    "name, value", [("alpha", defaults.ALPHA), ("defensive", defaults.DEFENSIVE)]
)
def test_alpha_and_defensive_have_one_definition(name, value):
    # Issue 12: the CLI said alpha 0.75 and core 1.0. Every layer now reads bams_cli.defaults.
    assert (defaults.ALPHA, defaults.DEFENSIVE) == (0.75, 0.1)
    for fn in (core_estimate.plan_sample, pipeline.estimate_plan.__wrapped__, cli.estimate):
        assert inspect.signature(fn).parameters[name].default == value, fn.__qualname__


def strict_json(text: str):
    """json.loads that refuses NaN / Infinity (which Python's parser accepts by default)."""

    def refuse(token: str):
        raise AssertionError(f"bare {token} in JSON output")

    return json.loads(text, parse_constant=refuse)


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_json_writers_refuse_nan(value, capsys):
    # The guard itself: --json output and state-file metadata raise rather than write NaN.
    with pytest.raises(ValueError, match="JSON compliant"):
        console.print_json({"rel_var": value})
    import pyarrow as pa

    with pytest.raises(ValueError, match="JSON compliant"):
        stamp(pa.table({"a": [1]}), 1, {"w_model": [value]})


STUDY_SEED = 5


@pytest.fixture(scope="module")
def fitted_ws(tmp_path_factory):
    """400 toy2d segments, one random level-0 batch of 25, fitted; gamma 0.05 has no failure
    anywhere (f >= 0.094), so its estimate is p_hat = 0 and its relative variance undefined."""
    from typer.testing import CliRunner

    return _toy_study(CliRunner(), tmp_path_factory.mktemp("est"), "0.05,0.56")


def _toy_study(runner, tmp: Path, gammas: str) -> tuple[Path, Path]:
    """400 toy2d segments at ``gammas``, one random level-0 batch of 25, fitted:
    (workspace, truth)."""
    seg, truth = write_toy(tmp / "data", n=400, seed=0)
    ws = tmp / "ws"
    ok(runner, "init", "-w", ws, "--gamma", gammas, "--costs", "1,0.1", "--dim", "2",
       "--seed", str(STUDY_SEED))  # fmt: skip
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize")  # fmt: skip
    ok(runner, "select", "-w", ws, "--strategy", "random", "--budget", "25")
    res = tmp / "r1.parquet"
    ok(runner, "simulate", ws / "batches" / "batch-0001.parquet", "--truth", truth, "-o", res)
    ok(runner, "ingest-results", "-w", ws, res)
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    return ws, truth


def test_estimate_outputs_are_strict_json_with_null_and_reason(fitted_ws, tmp_path):
    from typer.testing import CliRunner

    ws, truth = _copy(fitted_ws, tmp_path)
    runner = CliRunner()
    strict_json(ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "30", "--json").stdout)
    res = tmp_path / "plan.parquet"
    ok(runner, "simulate", ws / "estimates" / "plan-0001-handoff.csv", "--truth", truth, "-o", res)
    ok(runner, "ingest-results", "-w", ws, res)
    out = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    on_disk = strict_json((ws / "estimates" / "estimate-0001.json").read_text())
    assert on_disk["estimates"] == out["estimates"]
    none, some = out["estimates"]
    # gamma 0.05: nothing fails, p_hat = 0, so se^2 / p_hat^2 is null with its reason; se
    # is not 0 either (failures could hide among the pi < 1 segments), and says so.
    assert none["p_hat"] == 0 and none["rel_var"] is None
    assert "p_hat = 0" in none["rel_var_note"]
    assert none["se"] > 0 and "HT variance estimate is 0" in none["variance_note"]
    assert set(some) >= {"se", "variance_note", "rel_var", "rel_var_note"}
    # The report carries the nulls through to summary.json, strictly, and says why.
    ok(runner, "report", "-w", ws)
    summary = strict_json((ws / "report" / "summary.json").read_text())
    assert summary["estimates"][0]["rel_var"] is None
    assert "p_hat = 0" in (ws / "report" / "summary.md").read_text()
    # The plan's metadata is strict JSON too (w_model is null where p_n puts no mass).
    meta = pq.read_schema(ws / "estimates" / "plan-0001.parquet").metadata
    for key, value in meta.items():
        if key.startswith(b"bams"):
            try:
                strict_json(value.decode())
            except json.JSONDecodeError:
                pass  # plain strings (command line, tool version) are not JSON documents


def _copy(fitted_ws, tmp_path) -> tuple[Path, Path]:
    """A fresh copy of the fitted study for one test to change: (workspace, truth)."""
    src, truth = fitted_ws
    shutil.copytree(src, tmp_path / "ws")
    return tmp_path / "ws", truth


def _plan_ids(ws, number: int) -> list[str]:
    t = pq.read_table(ws / "estimates" / f"plan-{number:04d}.parquet")
    return sorted(t.filter(pc.equal(t["stratum"], "sampled"))["segment_id"].to_pylist())


def test_a_series_drawn_before_the_weights_left_the_shares_keeps_its_weights(fitted_ws, tmp_path):
    """Stage 1 written by an older bams-cli (its weights were its shares of K, and it has
    no ``stage_shares``): stage 2 spends the rest of K and the estimate combines the stages
    with the weights stage 1 fixed, as that version would have."""
    from typer.testing import CliRunner

    runner = CliRunner()
    ws, truth = _copy(fitted_ws, tmp_path)
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "80", "--stage1-share", "0.3")
    path = ws / "estimates" / "plan-0001.parquet"
    table = pq.read_table(path)
    old = {k: v for k, v in table.schema.metadata.items() if k != b"bams.stage_shares"}
    old[b"bams.stage_weights"] = b"[0.3, 0.7]"
    pq.write_table(table.replace_schema_metadata(old), path)
    assert "stage_shares" not in read_metadata_json(path)
    _simulate_and_ingest(runner, ws, truth, 1, tmp_path)
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    s2 = strict_json(ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--json").stdout)
    assert s2["samples_K"] == pytest.approx(80 * 0.7)
    assert s2["stage_weights"] == [0.3, 0.7] and s2["stage_shares"] == [0.3, 0.7]
    _simulate_and_ingest(runner, ws, truth, 2, tmp_path)
    out = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    assert out["staging"]["weights"] == [0.3, 0.7]


def test_a_default_k_near_a_census_is_said_and_a_given_k_is_not(tmp_path):
    # A common failure (gamma 2.5: 30% of toy2d's 400 segments): the default K, 5 p N,
    # reaches most of the segments without a level-0 result, and the plan says so.
    from typer.testing import CliRunner

    runner = CliRunner()
    ws, _ = _toy_study(runner, tmp_path, "2.5")
    plan = strict_json(ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--json").stdout)
    n_unknown = 400 - 25
    assert plan["series_K"] >= defaults.PLAN_LARGE_SHARE * n_unknown
    (said,) = [w for w in plan["warnings"] if "without a level-0 result" in w]
    assert f"of the {n_unknown:,} segments" in said and "--samples" in said
    again = ["--new-series", "--allow-pending", "--samples", str(plan["series_K"]), "--json"]
    given = strict_json(ok(runner, "estimate", "-w", ws, *STAGED_PLAN, *again).stdout)
    assert not [w for w in given["warnings"] if "without a level-0 result" in w]
    assert (given["stages"], given["stage_weights"]) == (1, [1.0])  # K = |U|: a census
    # The plan's summary names the stages' weights, which K near U sets far from the shares.
    shown = ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--new-series", "--allow-pending",
               "--samples", "150").stdout  # fmt: skip
    (line,) = [x for x in shown.splitlines() if x.lstrip().startswith("stage weights")]
    n, s1 = defaults.STAGES, defaults.STAGE1_SHARE
    w = dz.stage_weights([s1, *[(1 - s1) / (n - 1)] * (n - 1)], 150, n_unknown)
    assert " / ".join(f"{x:.3g}" for x in w) + " in the combined estimate" in line


def test_k_that_takes_every_unknown_segment_is_one_stage_a_census(fitted_ws, tmp_path):
    from typer.testing import CliRunner

    runner = CliRunner()
    ws, truth = _copy(fitted_ws, tmp_path)
    s1 = strict_json(
        ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "375", "--json").stdout
    )
    assert (s1["stages"], s1["stage_weights"], s1["to_simulate"]) == (1, [1.0], 375)
    assert any("one stage, a census" in n for n in s1["notes"])
    _simulate_and_ingest(runner, ws, truth, 1, tmp_path)
    out = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    fails = pq.read_table(truth)["value_0"].to_numpy() <= 0.56
    assert out["estimates"][1]["p_hat"] == pytest.approx(fails.mean(), rel=1e-12)
    assert (
        out["estimates"][1]["se"] == 0
        and out["estimates"][1]["ci_high"] == out["estimates"][1]["p_hat"]
    )


def test_stages_done_that_weigh_nothing_in_the_whole_report_by_their_shares(fitted_ws, tmp_path):
    # Weights fixed at stage 1 can give the stages done so far no weight (a later stage
    # that takes every segment left): the estimate between the stages must not divide 0
    # by 0. (K below |U| cannot make such a stage any more; a plan written so still reads.)
    from typer.testing import CliRunner

    runner = CliRunner()
    ws, truth = _copy(fitted_ws, tmp_path)
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "80")
    path = ws / "estimates" / "plan-0001.parquet"
    table = pq.read_table(path)
    meta = dict(table.schema.metadata)
    meta[b"bams.stage_weights"] = b"[0.0, 1.0]"
    pq.write_table(table.replace_schema_metadata(meta), path)
    _simulate_and_ingest(runner, ws, truth, 1, tmp_path)
    out = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    one = pipeline.plan_estimate(pipeline.Workspace(ws), 1, np.array([0.05, 0.56]), 0.9)
    assert out["staging"]["stages_done"] == 1
    assert out["estimates"][1]["p_hat_unbiased"] == pytest.approx(one.p_hat_unbiased[1])


def test_plan_seed_draws_a_fresh_reproducible_plan(fitted_ws, tmp_path):
    from typer.testing import CliRunner

    ws, truth = _copy(fitted_ws, tmp_path)
    runner = CliRunner()

    def plan(*extra):
        args = ("estimate", "-w", ws, *STAGED_PLAN, "--samples", "60", "--json", *extra)
        return strict_json(ok(runner, *args).stdout)

    default = plan()
    # While plan 1 awaits results a second plan is refused with exit code 3 (waiting) ...
    r = invoke(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "60")
    assert r.exit_code == 3 and "estimate plan 1 awaits results" in r.stderr
    assert not (ws / "estimates" / "plan-0002.parquet").exists()
    # ... unless asked for: fresh plans from one fitted workspace, as a design study wants.
    more = ("--allow-pending", "--seed")
    s7, _, s8 = plan(*more, "7"), plan(*more, "7"), plan(*more, "8")
    assert (default["seed"], default["seed_source"]) == (STUDY_SEED, "study settings")
    assert (s7["seed"], s7["seed_source"], s8["seed"]) == (7, "--seed", 8)
    # Same seed, same plan (plans 2 and 3); another seed, another plan; recorded in the file.
    assert _plan_ids(ws, 2) == _plan_ids(ws, 3)
    assert _plan_ids(ws, 4) != _plan_ids(ws, 2)
    meta = [read_metadata_json(ws / "estimates" / f"plan-{k:04d}.parquet") for k in (2, 4)]
    assert [(m["seed"], m["seed_source"], m["rng_stream"]) for m in meta] == [
        (7, "--seed", [7, 10_000]),
        (8, "--seed", [8, 10_000]),
    ]
    # A later stage draws from its series' --seed, its own stream per stage: fresh plans
    # of one study, each from its own seed, had shared stage 2's draws (a trial study).
    for k in (1, 2, 3, 4):
        ok(runner, "abandon", "-w", ws, "--plan", str(k), "--reason", "next: a series by --seed")
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "60", "--seed", "5", "--new-series")
    _simulate_and_ingest(runner, ws, truth, 5, tmp_path)
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    stage2 = plan()
    assert (stage2["stage"], stage2["seed"], stage2["seed_source"]) == (2, 5, "stage 1's --seed")
    m6 = read_metadata_json(ws / "estimates" / "plan-0006.parquet")
    assert m6["rng_stream"] == [5, 20_002]  # not [5, 10_002]: a seed-5 study's own plan 2
    from bams_cli import schemas_json
    from tests.jsonschema_subset import errors

    assert errors(stage2, schemas_json.schema("estimate-plan")) == []
    # --seed without --plan is a usage error that names the fix.
    r = invoke(runner, "estimate", "-w", ws, "--seed", "7")
    assert r.exit_code == 2 and "pass it with --plan" in r.output + r.stderr


def _simulate_and_ingest(runner, ws, truth, number: int, tmp_path):
    res = tmp_path / f"plan-{number}.parquet"
    handoff = ws / "estimates" / f"plan-{number:04d}-handoff.csv"
    ok(runner, "simulate", handoff, "--truth", truth, "-o", res)
    ok(runner, "ingest-results", "-w", ws, res)


def test_a_staged_estimate_walks_plan_simulate_ingest_fit_plan_and_combines(
    fitted_ws, tmp_path, monkeypatch
):
    # Issue 12, point 1, the way a Makefile drives it: stage 1, its results, a refit, stage 2
    # from the model checked on stage 1's outcomes, its results, the combined estimate.
    from typer.testing import CliRunner

    ws, truth = _copy(fitted_ws, tmp_path)
    runner = CliRunner()
    s1 = strict_json(
        ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "80", "--json").stdout
    )
    n_stages = defaults.STAGES
    assert (s1["stage"], s1["stages"], s1["series"], s1["series_K"]) == (1, n_stages, 1, 80)
    assert s1["samples_K"] == pytest.approx(80 * defaults.STAGE1_SHARE)
    # The estimate's weights are set apart from the budget's shares: 80 of the 375 unknown
    # segments puts a little more weight on the later stages, which sample from fewer.
    shares = default_shares()
    assert s1["stage_shares"] == pytest.approx(shares, rel=1e-12)
    assert s1["stage_weights"] == pytest.approx(dz.stage_weights(shares, 80, 375), rel=1e-12)
    assert s1["stage_weights"][0] < shares[0] - 0.01
    assert sum(s1["stage_weights"]) == pytest.approx(1)
    assert s1["model_check"]["sampled"] == 0  # the prior alone: nothing checked yet
    assert s1["predicted_vs_uniform"]["uniform"] == 1.0
    assert s1["predicted_vs_uniform"][s1["weighting"]] == min(s1["predicted_vs_uniform"].values())
    # Stage 2 waits for stage 1's results (exit code 3) ...
    r = invoke(runner, "estimate", "-w", ws, *STAGED_PLAN)
    assert r.exit_code == 3
    _simulate_and_ingest(runner, ws, truth, 1, tmp_path)
    # ... stage 1 alone is an estimate already, and says that a stage remains ...
    part = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    assert part["staging"]["stages_done"] == 1
    assert f"{n_stages - 1} more stage" in part["staging"]["note"]
    # ... and stage 2 needs the model refitted on stage 1's results; status says so.
    nxt = strict_json(ok(runner, "status", "-w", ws, "--json").stdout)["next"]
    assert nxt["step"] == "fit" and "before stage 2" in nxt["text"]
    r = invoke(runner, "estimate", "-w", ws, *STAGED_PLAN)
    assert r.exit_code != 0 and "fit" in r.stderr
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    nxt = strict_json(ok(runner, "status", "-w", ws, "--json").stdout)["next"]
    assert nxt["command"].endswith("--plan") and "for stage 2" in nxt["text"]
    # A different K for the running estimate is refused, naming the way out.
    r = invoke(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "50")
    assert r.exit_code == 1 and "--new-series" in r.stderr
    s2 = strict_json(
        ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "80", "--json").stdout
    )
    assert (s2["stage"], s2["series"], s2["stage_weights"]) == (2, 1, s1["stage_weights"])
    assert s2["samples_K"] == pytest.approx(80 * shares[1])
    assert s2["model_check"]["plans"] == [1] and s2["model_check"]["sampled"] == s1["to_simulate"]
    # Stage 2 never re-draws what stage 1 simulated: those are known now.
    assert not set(_plan_ids(ws, 1)) & set(_plan_ids(ws, 2))
    _simulate_and_ingest(runner, ws, truth, 2, tmp_path)
    # The later stages, each from the model refitted on every stage before it.
    for k in range(3, n_stages + 1):
        ok(runner, "fit", "-w", ws, "--restarts", "1")
        sk = strict_json(ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--json").stdout)
        assert (sk["stage"], sk["stage_weights"]) == (k, s1["stage_weights"])
        assert sk["samples_K"] == pytest.approx(80 * shares[k - 1])
        assert sk["model_check"]["plans"] == list(range(1, k))
        assert not set(_plan_ids(ws, k)) & {i for j in range(1, k) for i in _plan_ids(ws, j)}
        _simulate_and_ingest(runner, ws, truth, k, tmp_path)
    out = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    assert out["design"] == "staged" and out["staging"]["plans"] == list(range(1, n_stages + 1))
    assert out["staging"]["note"] is None
    # The combined estimate is the weighted sum of the stages' own (computed one by one).
    w = out["staging"]["weights"]
    each = [
        pipeline.plan_estimate(pipeline.Workspace(ws), k, np.array([0.05, 0.56]), 0.9)
        for k in range(1, n_stages + 1)
    ]
    one = each[0]
    n_pool = pq.read_metadata(Path(ws) / "segments.parquet").num_rows
    for g, e in enumerate(out["estimates"]):
        wsum = sum(wk * ek.p_hat_unbiased[g] for wk, ek in zip(w, each, strict=True))
        assert e["p_hat_unbiased"] == pytest.approx(wsum, rel=1e-12)
        # ... raised to the failures found when it falls below them (core.design).
        assert e["p_hat"] == pytest.approx(max(wsum, e["distinct_failures_found"] / n_pool))
        assert e["distinct_failures_found"] / n_pool <= e["ci_low"] <= e["p_hat"] <= e["ci_high"]
        # Failures are counted once: known from outside the samples (here: before stage 1),
        # then sampled by either stage (stage 2's known stratum holds stage 1's).
        assert e["failures_known"] == one.n_known_failures[g]
        assert e["failures_sampled"] == sum(ek.n_failures_sampled[g] for ek in each)
        assert e["failures_known"] + e["failures_sampled"] == e["distinct_failures_found"]
    assert one.n_failures_sampled.max() > 0  # else the double count could not show
    # A weighted sum below the failures found (as if stage 1 had drawn few of those stage 2
    # found) is kept as p_hat_unbiased, and the estimate says p_hat was raised.
    from bams_cli.core import design

    real = design.combine_stages

    def estimate_with_sum(factor):
        """The estimate had the stages' weighted sum been ``factor`` x p_hat."""
        monkeypatch.setattr(
            design, "combine_stages",
            lambda *a, **kw: replace(c := real(*a, **kw), p_hat_unbiased=c.p_hat * factor),
        )  # fmt: skip
        try:
            return strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
        finally:
            monkeypatch.undo()

    low = estimate_with_sum(0.5)
    for e, e_low in zip(out["estimates"], low["estimates"], strict=True):
        assert e_low["p_hat"] == e["p_hat"] and e_low["p_hat_unbiased"] == 0.5 * e["p_hat"]
    raised = [n for n in low["notes"] if "fell below the" in n]
    assert len(raised) == sum(e["p_hat"] > 0 for e in out["estimates"]) > 0
    assert "`p_hat_unbiased` keeps the sum" in raised[0]
    # One above what the sample allows is held to it, and said too.
    high = estimate_with_sum(2.0)
    capped = [n for n in high["notes"] if "not seen to pass" in n]
    assert len(capped) == len(raised) and "the rate is at most that" in capped[0]
    # The next plan starts a new estimate: the series is complete.
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    nxt = strict_json(ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--json").stdout)
    after = n_stages + 1
    assert (nxt["stage"], nxt["series"]) == (1, after)
    assert nxt["model_check"]["plans"] == list(range(1, after))
    # ... and says so: the report's headline will move to it.
    assert not any("new estimate" in n for n in s1["notes"] + s2["notes"])
    earlier = ", ".join(str(k) for k in range(1, after))
    assert nxt["notes"][0].startswith(
        f"plan {after} starts a new estimate; the earlier one (plans {earlier})"
    )


def test_failures_a_discovery_batch_finds_between_stages_are_counted_once(fitted_ws, tmp_path):
    # A team may run a discovery batch while an estimate is half done. Its level-0 failures
    # are known at stage 2's planning: they must count among the known failures, so that
    # known + sampled is every distinct failure found (they had counted in neither).
    from typer.testing import CliRunner

    ws, truth = _copy(fitted_ws, tmp_path)
    runner = CliRunner()
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "10")
    _simulate_and_ingest(runner, ws, truth, 1, tmp_path)
    one = pipeline.plan_estimate(pipeline.Workspace(ws), 1, np.array([0.05, 0.56]), 0.9)
    ok(runner, "select", "-w", ws, "--strategy", "random", "--budget", "60")
    res = tmp_path / "between.parquet"
    ok(runner, "simulate", ws / "batches" / "batch-0002.parquet", "--truth", truth, "-o", res)
    ok(runner, "ingest-results", "-w", ws, res)
    # The batch may miss the few failures a stage of 5 samples leaves (the pool holds 3 at
    # gamma 0.56, where p_n puts them): one more level-0 run outside every list, of a
    # failure no one has run, makes sure some are found between the stages.
    seen = set(pipeline.Workspace(ws).read_observations().filter(pl.col("fidelity") == 0)[SID])
    t = pl.read_parquet(truth)
    extra = t.filter((pl.col("value_0") <= 0.56) & ~pl.col(SID).is_in(list(seen))).head(1)
    assert extra.height == 1
    extra.select(SID, pl.lit(0).alias("fidelity"), pl.col("value_0").alias("value")).write_csv(
        tmp_path / "extra.csv"
    )
    ok(runner, "ingest-results", "-w", ws, tmp_path / "extra.csv", "--allow-unselected")
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "10")
    _simulate_and_ingest(runner, ws, truth, 2, tmp_path)
    out = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    e = out["estimates"][1]  # gamma 0.56
    assert e["failures_known"] + e["failures_sampled"] == e["distinct_failures_found"]
    assert e["failures_known"] > one.n_known_failures[1]  # the batch found some


def test_stages_1_is_a_single_stage_plan(fitted_ws, tmp_path):
    from typer.testing import CliRunner

    ws, truth = _copy(fitted_ws, tmp_path)
    runner = CliRunner()
    args = ("estimate", "-w", ws, *STAGED_PLAN, "--samples", "40", "--stages", "1", "--json")
    s1 = strict_json(ok(runner, *args).stdout)
    assert (s1["stages"], s1["samples_K"], s1["stage_weights"]) == (1, 40, [1.0])
    _simulate_and_ingest(runner, ws, truth, 1, tmp_path)
    out = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    assert out["design"] == "poisson" and out["staging"]["note"] is None


@pytest.mark.parametrize(
    "predicted, weighting, says",
    [
        ({"uniform": 1.0, "calibrated": 0.95, "p^alpha": 3.0}, "calibrated", True),
        ({"uniform": 1.0, "calibrated": 0.4, "p^alpha": 0.5}, "calibrated", False),
        ({"uniform": 1.0, "calibrated": 1.0, "p^alpha": 2.0}, "uniform", True),
        (None, "p^alpha", False),  # a forced design: nothing was predicted
        ({"screen": 1.05}, "screen", True),  # a screen's confirmation
        ({"screen": 0.4}, "screen", False),
    ],
)
def test_a_design_predicted_no_better_than_uniform_is_said_in_one_line(predicted, weighting, says):
    note = pipeline.design_note(
        {"plan": 3, "predicted_vs_uniform": predicted, "weighting": weighting}
    )
    assert (note is not None) is says
    if says:
        assert note.startswith("plan 3:") and "\n" not in note and "uniform" in note


def test_a_pool_known_at_level_0_everywhere_plans_nothing_and_is_exact(tmp_path):
    from typer.testing import CliRunner

    runner = CliRunner()
    seg, truth = write_toy(tmp_path / "data", n=24, seed=3)
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.56", "--costs", "1,1", "--dim", "2")
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize")  # fmt: skip
    for batch in (1, 2):  # every segment at level 0, in two random batches of 12
        ok(runner, "select", "-w", ws, "--strategy", "random", "--budget", "12")
        res = tmp_path / f"r{batch}.parquet"
        handoff = ws / "batches" / f"batch-{batch:04d}.parquet"
        ok(runner, "simulate", handoff, "--truth", truth, "-o", res)
        ok(runner, "ingest-results", "-w", ws, res)
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    plan = strict_json(ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--json").stdout)
    assert plan["to_simulate"] == 0 and plan["known_stratum"] == 24
    out = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    e = out["estimates"][0]
    assert e["ci_low"] == e["p_hat"] == e["ci_high"] and e["se"] == 0
    assert e["p_hat"] == pytest.approx((pq.read_table(truth)["value_0"].to_numpy() <= 0.56).mean())


def test_the_fay_feuer_interval_is_a_choice_and_never_narrower(fitted_ws, tmp_path):
    from typer.testing import CliRunner

    ws, truth = _copy(fitted_ws, tmp_path)
    runner = CliRunner()
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "40", "--stages", "1")
    _simulate_and_ingest(runner, ws, truth, 1, tmp_path)
    gamma = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    ff = strict_json(ok(runner, "estimate", "-w", ws, "--interval", "fay-feuer", "--json").stdout)
    assert (gamma["interval"], ff["interval"]) == ("gamma", "fay-feuer")
    pairs = list(zip(gamma["estimates"], ff["estimates"], strict=True))
    assert all(f["p_hat"] == g["p_hat"] and f["se"] == g["se"] for g, f in pairs)
    # w_max, the largest weight in U, is at least the model's allowance: never narrower,
    # and wider here (p_hat = 0 at gamma 0.05: the upper limit is all allowance).
    assert all(f["ci_high"] >= g["ci_high"] for g, f in pairs)
    assert pairs[0][1]["ci_high"] > pairs[0][0]["ci_high"]
    assert "90% fay-feuer interval" in ok(runner, "estimate", "-w", ws, "--interval",
                                          "fay-feuer").stdout  # fmt: skip


def test_another_confidence_keeps_the_earlier_estimate_and_says_where_each_is(fitted_ws, tmp_path):
    # `estimate --confidence 0.95` after the default's estimate replaced its file in silence.
    from typer.testing import CliRunner

    ws, truth = _copy(fitted_ws, tmp_path)
    runner = CliRunner()
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "40", "--stages", "1")
    _simulate_and_ingest(runner, ws, truth, 1, tmp_path)
    path = ws / "estimates" / "estimate-0001.json"
    assert f"estimate written to {path}\n" in ok(runner, "estimate", "-w", ws).stdout
    at_90 = path.read_text()
    # The same estimate again: nothing to keep, nothing else written.
    assert f"estimate written to {path}\n" in ok(runner, "estimate", "-w", ws).stdout
    assert [p.name for p in (ws / "estimates").glob("estimate-*")] == [path.name]
    wider = ok(runner, "estimate", "-w", ws, "--confidence", "0.95").stdout
    kept = path.with_name("estimate-0001.1.json")
    assert (
        f"estimate written to {path}; plan 1's earlier estimate (90% gamma interval) is kept "
        f"as {kept}\n"
    ) in wider
    assert kept.read_text() == at_90
    assert json.loads(path.read_text())["estimates"][0]["confidence"] == 0.95
    back = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    assert back["estimate_file"] == str(path) and path.read_text() == at_90
    assert back["earlier_estimate"] == {
        "file": str(path.with_name("estimate-0001.2.json")),
        "confidence": 0.95,
        "interval": "gamma",
    }
    # status and the report read the plan's estimate, not the kept ones.
    status = strict_json(ok(runner, "status", "-w", ws, "--json").stdout)
    assert status["latest_estimate"]["file"] == str(path)


def test_fay_feuer_refuses_a_combined_staged_estimate(fitted_ws, tmp_path):
    from typer.testing import CliRunner

    ws, truth = _copy(fitted_ws, tmp_path)
    runner = CliRunner()
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "40")
    _simulate_and_ingest(runner, ws, truth, 1, tmp_path)
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN)
    _simulate_and_ingest(runner, ws, truth, 2, tmp_path)
    r = invoke(runner, "estimate", "-w", ws, "--interval", "fay-feuer")
    assert r.exit_code == 1 and "--interval fay-feuer: plan 2 is stage 2" in r.stderr
    assert "--stages 1" in r.stderr and r.stderr.count("\n") == 1


@pytest.mark.parametrize("design", ["poisson", "with-replacement"])
def test_a_plan_stores_pi_and_q_and_no_separate_prob(fitted_ws, tmp_path, design):
    # The estimator divides by pi (q with replacement), read from those columns; a third
    # copy of one of them ("prob") was dead weight.
    from typer.testing import CliRunner

    ws, truth = _copy(fitted_ws, tmp_path)
    runner = CliRunner()
    args = ("estimate", "-w", ws, *STAGED_PLAN, "--samples", "30", "--design", design)
    ok(runner, *args, "--stages", "1")
    plan = pq.read_table(ws / "estimates" / "plan-0001.parquet").to_pylist()
    assert {"pi", "q", "draws"} <= set(plan[0]) and "prob" not in plan[0]
    _simulate_and_ingest(runner, ws, truth, 1, tmp_path)
    out = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)
    assert out["design"] == design
    if design != "poisson":
        return
    # Horvitz-Thompson by hand at gamma 0.56: known failures + sum over sampled failures
    # of 1/pi, over N = 400.
    obs = pq.read_table(ws / "observations.parquet").to_pylist()
    level0 = {r["segment_id"]: r["value"] for r in obs if r["fidelity"] == 0}
    total = sum(
        (1.0 if r["stratum"] == "known" else 1.0 / r["pi"])
        for r in plan
        if level0[r["segment_id"]] <= 0.56
    )
    assert out["estimates"][1]["p_hat"] == pytest.approx(total / 400, rel=1e-12)


@pytest.mark.parametrize(
    "values, warned", [([3.1, 2.9, 3.0, 3.2, 3.3], True), ([0.3, 3.1, 2.9, 3.0, 3.2], False)]
)
def test_the_default_k_has_a_floor_and_says_when_no_level0_failure_checked_the_rate(
    toy_ws, runner, tmp_path, values, warned
):
    """A GP that has seen no level-0 failure can put its rate near 0 and K = 5 p N at 5,
    an estimate of "0, at most 0.5": the default K is at least defaults.PLAN_MIN_SAMPLES,
    and with no level-0 failure known the plan says so, on stderr as a JSON line under
    --json, with the model's rate and how to size K."""
    import pyarrow as pa

    from tests.conftest import write_batch

    ids = [f"t{i:06d}" for i in range(0, 400, 40)][: len(values)]
    write_batch(toy_ws, 1, ids, [0] * len(ids))
    res = tmp_path / "r1.parquet"
    pq.write_table(pa.table({"segment_id": ids, "fidelity": [0] * len(ids), "value": values}), res)
    ok(runner, "ingest-results", "-w", toy_ws, res)
    hp = {
        "mean": 3.0,
        "outputscale0": 0.25,
        "lengthscales0": [1.0, 1.0],
        "outputscales": [0.01],
        "lengthscales": [[1.0, 1.0]],
        "noise": [1e-4, 1e-4],
    }
    saved = tmp_path / "hp.json"
    saved.write_text(json.dumps(hp))
    ok(runner, "fit", "-w", toy_ws, "--fixed-hyperparameters", saved)
    r = invoke(runner, "estimate", "-w", toy_ws, *STAGED_PLAN, "--json")
    assert r.exit_code == 0, r.output
    s = json.loads(r.stdout)
    n_unknown = 400 - len(ids)
    paper = 5 * max(s["gp_rate_estimate"] * 400, (0 if warned else 1) + 1)
    assert s["series_K"] == min(round(max(paper, defaults.PLAN_MIN_SAMPLES)), n_unknown)
    if warned:  # the model's rate alone would have planned a handful of runs
        assert paper < 10 and s["series_K"] == defaults.PLAN_MIN_SAMPLES
    lines = [json.loads(line)["warning"] for line in r.stderr.splitlines()]
    assert lines == s["warnings"]
    if warned:
        [w] = s["warnings"]
        assert "no level-0 failure is known" in w and f"{s['gp_rate_estimate']:.2g}" in w
        assert "--samples" in w and "K = 100 is the default's floor" in w and "3.0/K" in w
    else:  # one failure checked the rate: nothing to say of it, only of a K near a census
        near = s["series_K"] >= defaults.PLAN_LARGE_SHARE * n_unknown
        assert [w for w in s["warnings"] if "without a level-0 result" not in w] == []
        assert len(s["warnings"]) == int(near)


def test_the_interval_s_allowance_trusts_p_n_as_little_as_the_evidence_allows(fitted_ws, tmp_path):
    """The weight of the unseen failure the interval allows for is the mean (1 - pi)/pi
    under the risk with lam at its RISK_MIX_UPPER posterior quantile, not its mean (which
    put the allowance where the model is trusted and let intervals lie below the rate);
    recomputed by hand from the scores and the stage-1 design."""
    from typer.testing import CliRunner

    from bams_cli.core import design as dz

    ws, _ = _copy(fitted_ws, tmp_path)
    s = strict_json(
        ok(CliRunner(), "estimate", "-w", ws, *STAGED_PLAN, "--samples", "80", "--json").stdout
    )
    meta = read_metadata_json(ws / "estimates" / "plan-0001.parquet")
    plan = pq.read_table(ws / "estimates" / "plan-0001.parquet")
    known = set(pc.filter(plan["segment_id"], pc.equal(plan["stratum"], "known")).to_pylist())
    scores = pq.read_table(ws / "scores.parquet")
    unknown = np.array([sid not in known for sid in scores["segment_id"].to_pylist()])
    p = scores["p_1"].to_numpy()[unknown]  # gamma 0.56, the plan's (the largest)
    assert meta["plan_gamma"] == 0.56
    post = dz.risk_posterior([])  # stage 1: the prior alone
    pi = dz.choose_design(p, K=s["samples_K"], posterior=post).pi
    lam_q = post.lam_quantile(defaults.RISK_MIX_UPPER)
    assert lam_q > post.lam_mean + 0.2
    w_tau = post.weights.sum(axis=1)
    shaped = sum(
        w * p**tau / np.mean(p**tau) for w, tau in zip(w_tau, post.taus, strict=True) if w > 0
    )
    r = lam_q + (1 - lam_q) * shaped
    rand = (pi > 0) & (pi < 1)
    by_hand = float((r[rand] * (1 - pi[rand]) / pi[rand]).sum() / r[rand].sum())
    r_mean = post.risk(p)
    at_mean = float((r_mean[rand] * (1 - pi[rand]) / pi[rand]).sum() / r_mean[rand].sum())
    assert meta["w_model"][1] == pytest.approx(by_hand, rel=1e-9)
    assert meta["w_model"][1] > 1.1 * at_mean  # the mean trust allowed for less


def test_the_plan_names_the_gamma_its_gp_rate_and_design_are_for(fitted_ws, tmp_path):
    # A two-gamma study's plan is drawn for the largest gamma; its summary printed the GP's
    # rate at that gamma without naming it, which a trial read as the first gamma's.
    from typer.testing import CliRunner

    ws, _ = _copy(fitted_ws, tmp_path)
    r = ok(CliRunner(), "estimate", "-w", ws, *STAGED_PLAN, "--samples", "40")
    [line] = [s for s in r.stdout.splitlines() if "GP rate estimate" in s]
    assert line.rstrip().endswith("at gamma 0.56, the largest, which the plan is drawn for")
    # The threshold as the study set it: 0.5612 was printed "0.561".
    ws, _ = _copy(fitted_ws, tmp_path / "other")
    settings = ws / "settings.toml"
    settings.write_text(settings.read_text().replace("0.56", "0.5612"))
    ok(CliRunner(), "fit", "-w", ws, "--restarts", "1")
    r = ok(CliRunner(), "estimate", "-w", ws, *STAGED_PLAN, "--samples", "40")
    [line] = [s for s in r.stdout.splitlines() if "GP rate estimate" in s]
    assert "at gamma 0.5612, the largest" in line


def test_a_stage_planned_by_an_older_version_still_checks_the_model(fitted_ws, tmp_path):
    # Plans record which calibration shape each risk norm belongs to (risk_taus). A plan
    # from before that record weighed tau 0.5, 1, 1.5 and 2 in that order: its evidence is
    # read by shape, not dropped, so a study upgraded between its stages keeps stage 1's.
    from typer.testing import CliRunner

    from bams_cli import stages
    from bams_cli.core import design as dz

    ws, truth = _copy(fitted_ws, tmp_path)
    runner = CliRunner()
    ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", "80")
    _simulate_and_ingest(runner, ws, truth, 1, tmp_path)
    now, used = stages.mix_evidence(pipeline.Workspace(ws), 0.56)
    assert used == [1] and now[0].failed.any()
    path = ws / "estimates" / "plan-0001.parquet"
    t = pq.read_table(path)
    meta = dict(t.schema.metadata)
    assert json.loads(meta.pop(b"bams.risk_taus")) == list(dz.TAUS)
    norms = dict(zip(dz.TAUS, json.loads(meta[b"bams.risk_norms"]), strict=True))
    old = [norms[0.5], norms[1.0], 7.0, 9.0]  # tau 1.5 and 2's norms: not read
    meta[b"bams.risk_norms"] = json.dumps(old).encode()
    pq.write_table(t.replace_schema_metadata(meta), path)
    then, used = stages.mix_evidence(pipeline.Workspace(ws), 0.56)
    assert used == [1]
    np.testing.assert_array_equal(then[0].u, now[0].u)
    np.testing.assert_array_equal(then[0].failed, now[0].failed)
    np.testing.assert_array_equal(then[0].norms, now[0].norms)
    # A record the shapes cannot be read from (three norms, no taus) is skipped, not misread.
    meta[b"bams.risk_norms"] = json.dumps(old[:3]).encode()
    pq.write_table(t.replace_schema_metadata(meta), path)
    assert stages.mix_evidence(pipeline.Workspace(ws), 0.56) == ([], [])


def test_open_leads_are_sampled_with_certainty_out_of_k_and_left_out_of_the_evidence(tmp_path):
    """A segment whose cheap run failed and that has no level-0 result is a lead: stage 1
    of a new estimate samples it with pi = 1 out of K, the stages share the rest of K over
    the other segments with the design the tool would draw there, and the leads' outcomes
    do not enter the evidence on p_n (their selection was the cheap run's, not p_n's)."""
    from typer.testing import CliRunner

    runner = CliRunner()
    ws, truth, t = _lead_study(runner, tmp_path)
    level0, leads = _leads(ws)
    assert 3 <= len(leads) <= 30, len(leads)
    K = 60
    s1 = strict_json(
        ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", str(K), "--json").stdout
    )
    n_l = len(leads)
    assert s1["leads_certain"] == s1["series_leads"] == n_l
    assert f"{n_l} open leads (a cheap run at or below gamma" in " ".join(s1["notes"])
    share = defaults.STAGE1_SHARE
    assert s1["samples_K"] == pytest.approx(n_l + share * (K - n_l))
    n_unknown = 400 - len(level0)
    assert s1["stage_weights"] == pytest.approx(
        dz.stage_weights(default_shares(), K - n_l, n_unknown - n_l), rel=1e-12
    )
    plan = pl.read_parquet(ws / "estimates" / "plan-0001.parquet")
    sampled = plan.filter(pl.col("stratum") == "sampled")
    at_leads = sampled.filter(pl.col(SID).is_in(leads))
    assert at_leads.height == n_l and (at_leads["pi"] == 1.0).all()
    # The rest: the design choose_design draws over U without the leads, at their share.
    scores = pl.read_parquet(ws / "scores.parquet").select(SID, "p_0")
    rest = scores.filter(~pl.col(SID).is_in(sorted(level0) + leads))
    want = dz.choose_design(
        rest["p_0"].to_numpy(), K=share * (K - n_l), posterior=dz.risk_posterior([])
    )
    got = rest.with_columns(pl.Series("want", want.pi)).join(
        sampled.select(SID, "pi"), on=SID, how="inner"
    )
    assert got.height > 0
    np.testing.assert_allclose(got["pi"], got["want"], rtol=1e-12)
    assert sorted(read_metadata_json(ws / "estimates" / "plan-0001.parquet")["lead_ids"]) == leads
    # Stage 1's results in and fitted: the evidence is its sampled segments but the leads,
    # and stage 2 spends the rest of what the leads left.
    _simulate_and_ingest(runner, ws, truth, 1, tmp_path)
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    s2 = strict_json(ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--json").stdout)
    assert (s2["stage"], s2["series_leads"], s2["leads_certain"]) == (2, n_l, 0)
    assert s2["samples_K"] == pytest.approx(default_shares()[1] * (K - n_l))
    assert s2["model_check"]["sampled"] == sampled.height - n_l
    _simulate_and_ingest(runner, ws, truth, 2, tmp_path)
    est = strict_json(ok(runner, "estimate", "-w", ws, "--json").stdout)["estimates"][0]
    # Every lead's level-0 outcome is in hand: the failures found count them.
    lead_fails = int(t.filter(pl.col(SID).is_in(leads))["value_0"].le(0.56).sum())
    assert est["distinct_failures_found"] >= lead_fails


def _lead_study(runner, tmp_path: Path) -> tuple[Path, Path, pl.DataFrame]:
    """400 toy2d segments whose cheap level reads 0.6 low (it fails wherever level 0 is
    under 1.16), one random mixed-fidelity batch of budget 12, fitted: (workspace, truth,
    the truth table)."""
    ws, truth = fitted_toy_study(runner, tmp_path, cheap_offsets={1: 0.6})
    return ws, truth, pl.read_parquet(truth)


def _leads(ws: Path) -> tuple[set[str], list[str]]:
    """(the segments with a level-0 result, the open leads at gamma 0.56), by hand."""
    obs = pl.read_parquet(ws / "observations.parquet")
    level0 = set(obs.filter(pl.col("fidelity") == 0)[SID])
    cheap_fail = set(obs.filter((pl.col("fidelity") == 1) & (pl.col("value") <= 0.56))[SID])
    return level0, sorted(cheap_fail - level0)


def test_open_leads_keep_the_highest_p_n_within_the_cap_and_skip_abandoned_and_scaled(tmp_path):
    """More leads than the cap: the highest p_n. A lead whose level-0 run was abandoned
    (it failed for good) is not asked for again. A cheap level the model fits with a scale
    other than 1 reports other units: its runs are no leads at gamma."""
    from typer.testing import CliRunner

    from bams_cli.pipeline.estimation import open_leads
    from bams_cli.state.workspace import Workspace

    runner = CliRunner()
    ws, _, _ = _lead_study(runner, tmp_path)
    level0, leads = _leads(ws)
    w = Workspace(ws)
    scores = pl.read_parquet(ws / "scores.parquet")
    ids, p = scores[SID].to_numpy(), scores["p_0"].to_numpy()
    known = np.isin(ids, sorted(level0))

    def chosen(**kw) -> list[str]:
        kw.setdefault("K", 2000.0)
        return sorted(ids[open_leads(w, ids, p, known, 0.56, w.pending(), **kw)[0]])

    assert chosen() == leads
    by_p = sorted(leads, key=lambda s: -p[ids == s][0])
    assert chosen(K=2 / defaults.LEAD_SHARE) == sorted(by_p[:2])  # a cap of 2
    assert chosen(scales=[2.5]) == [] == chosen(scales=[0.6])
    assert chosen(scales=[1.0]) == leads == chosen(scales=[1.4])
    # A BAMS batch whose level-0 runs crash for good (abandoned): none of them is a lead.
    ok(runner, "select", "-w", ws, "--budget", "6")
    b2 = pl.read_parquet(ws / "batches" / "batch-0002.parquet")
    asked = set(b2.filter(pl.col("fidelity") == 0)[SID]) & set(leads)
    assert asked, "the batch confirms no lead: the test has nothing to check"
    assert not set(chosen()) & asked  # awaited
    ok(runner, "abandon", "-w", ws, "--batch", "2", "--fidelity", "0", "--reason", "crash")
    assert not set(chosen()) & asked  # abandoned
    assert set(chosen()) == set(leads) - asked


def test_the_leads_share_of_k_follows_the_leads_the_study_ran_at_level0(tmp_path, monkeypatch):
    """The evidence (cheap failures with a level-0 result, how many failed there) is read
    from the log; where it says leads fail rarely, they take a tenth of K, and the plan
    says how many were left to the design and why."""
    from typer.testing import CliRunner

    from bams_cli.pipeline.estimation import open_leads
    from bams_cli.state.workspace import Workspace

    runner = CliRunner()
    ws, truth, _ = _lead_study(runner, tmp_path)
    # A BAMS batch confirms some leads at level 0: the evidence.
    ok(runner, "select", "-w", ws, "--budget", "6")
    _simulate_batch(runner, ws, truth, 2, tmp_path)
    ok(runner, "fit", "-w", ws, "--restarts", "1")
    level0, leads = _leads(ws)
    obs = pl.read_parquet(ws / "observations.parquet")
    cheap_fail = set(obs.filter((pl.col("fidelity") == 1) & (pl.col("value") <= 0.56))[SID])
    ran0 = obs.filter(pl.col("fidelity") == 0)
    pairs = cheap_fail & set(ran0[SID])
    failed = cheap_fail & set(ran0.filter(pl.col("value") <= 0.56)[SID])
    assert pairs, "no cheap failure was run at level 0: nothing to count"
    w = Workspace(ws)
    scores = pl.read_parquet(ws / "scores.parquet")
    ids, p = scores[SID].to_numpy(), scores["p_0"].to_numpy()
    known = np.isin(ids, sorted(level0))
    _, facts = open_leads(w, ids, p, known, 0.56, w.pending(), K=2000.0)
    assert facts == {
        "open": len(leads), "pairs": len(pairs), "failed": len(failed),
        "share": dz.lead_share(len(pairs), len(failed)),
    }  # fmt: skip
    # Evidence that leads fail less often than the threshold: a tenth of K.
    monkeypatch.setattr(defaults, "LEAD_HIT_MIN", 0.999)
    K = 10 * (len(leads) - 1) / 1.0
    cap = int(defaults.LEAD_SHARE_UNPROVEN * K)
    assert 0 < cap < len(leads)
    mask, facts = open_leads(w, ids, p, known, 0.56, w.pending(), K=K)
    assert facts["share"] == defaults.LEAD_SHARE_UNPROVEN and mask.sum() == cap
    s1 = strict_json(
        ok(runner, "estimate", "-w", ws, *STAGED_PLAN, "--samples", str(K), "--json").stdout
    )
    assert s1["leads_certain"] == cap
    assert f"; {len(leads) - cap} more are left to the design" in " ".join(s1["notes"])
    meta = read_metadata_json(ws / "estimates" / "plan-0001.parquet")
    assert meta["lead_evidence"]["share"] == defaults.LEAD_SHARE_UNPROVEN


def test_the_benchmark_reads_leads_and_their_evidence_as_the_pipeline_does(tmp_path):
    """The benchmark evaluates the estimate from a run's picks and the truth; the tool
    reads the same study's observation log. Both must find the same open leads and the
    same evidence on them, or the suite measures another design than the one shipped."""
    from typer.testing import CliRunner

    from bams_cli.benchmark import RunResult, run_lead_evidence
    from bams_cli.benchmark import open_leads as run_open_leads
    from bams_cli.pipeline._handoff import cheap_failures, lead_evidence
    from bams_cli.state.workspace import Workspace

    runner = CliRunner()
    ws, truth, t = _lead_study(runner, tmp_path)
    ok(runner, "select", "-w", ws, "--budget", "6")  # confirms some leads at level 0
    _simulate_batch(runner, ws, truth, 2, tmp_path)
    ids = t[SID].to_numpy().astype(str)  # the truth file's order, the benchmark's
    row = {sid: i for i, sid in enumerate(ids)}
    obs = pl.read_parquet(ws / "observations.parquet")
    picks = [
        (np.array([row[x] for x in b[SID].to_list()]), b["fidelity"].to_numpy())
        for _, b in obs.group_by("batch", maintain_order=True)
    ]
    known = np.isin(ids, obs.filter(pl.col("fidelity") == 0)[SID].to_list())
    r = RunResult(
        strategy="bams", seed=0, picks=picks, p_after=[None], scores=None, known=known,
        hyperparameters=[None], realised=None, seconds={},
    )  # fmt: skip
    f1, fail = t["value_1"].to_numpy(), t["value_0"].to_numpy() <= 0.56
    w = Workspace(ws)
    evidence = lead_evidence(w, ids, cheap_failures(w, ids, 0.56), 0.56)
    assert evidence[0] > 0, "no lead was run at level 0: nothing to compare"
    assert run_lead_evidence(r, f1, fail, 0.56) == evidence
    leads = cheap_failures(w, ids, 0.56) & ~known
    assert leads.any()
    np.testing.assert_array_equal(run_open_leads(r, f1, 0.56), leads)


def _simulate_batch(runner, ws, truth, number: int, tmp_path):
    res = tmp_path / f"batch-{number}.parquet"
    ok(runner, "simulate", ws / "batches" / f"batch-{number:04d}.parquet", "--truth", truth,
       "-o", res)  # fmt: skip
    ok(runner, "ingest-results", "-w", ws, res)


def test_a_staged_plan_says_its_k_is_this_stage_s_share_of_the_estimate_s():
    # "K 153 of 444 for the estimate" read as if 444 were the pool; a stage says whose K.
    from bams_cli.console import _plan_budget

    staged = {"samples_K": 153.0, "series_K": 444.0, "stages": 3}
    assert _plan_budget(staged) == "K 153 this stage, of 444 over the estimate's 3 stages"
    one = {"samples_K": 200.0, "series_K": 200.0, "stages": 1}
    assert _plan_budget(one) == "K 200 of 200 for the estimate"
