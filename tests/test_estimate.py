"""The estimate command end to end: defaults read from one place, NaN-free JSON, --seed."""

from __future__ import annotations

import inspect
import json
import math
import shutil

import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest

from bams_cli import cli, console, defaults, pipeline
from bams_cli.core import estimate as core_estimate
from bams_cli.state.io import stamp
from tests.conftest import invoke, ok, write_toy


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

    runner = CliRunner()
    tmp = tmp_path_factory.mktemp("est")
    seg, truth = write_toy(tmp / "data", n=400, seed=0)
    ws = tmp / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.05,0.56", "--costs", "1,0.1", "--dim", "2",
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

    src, truth = fitted_ws
    ws = tmp_path / "ws"
    shutil.copytree(src, ws)
    runner = CliRunner()
    strict_json(ok(runner, "estimate", "-w", ws, "--plan", "--samples", "30", "--json").stdout)
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


def _plan_ids(ws, number: int) -> list[str]:
    t = pq.read_table(ws / "estimates" / f"plan-{number:04d}.parquet")
    return sorted(t.filter(pc.equal(t["stratum"], "sampled"))["segment_id"].to_pylist())


def test_plan_seed_draws_a_fresh_reproducible_plan(fitted_ws, tmp_path):
    from typer.testing import CliRunner

    src, _ = fitted_ws
    ws = tmp_path / "ws"
    shutil.copytree(src, ws)
    runner = CliRunner()

    def plan(*extra):
        args = ("estimate", "-w", ws, "--plan", "--samples", "60", "--json", *extra)
        return strict_json(ok(runner, *args).stdout)

    default = plan()
    # While plan 1 awaits results a second plan is refused with exit code 3 (waiting) ...
    r = invoke(runner, "estimate", "-w", ws, "--plan", "--samples", "60")
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
    meta = [pipeline.read_metadata_json(ws / "estimates" / f"plan-{k:04d}.parquet") for k in (2, 4)]
    assert [(m["seed"], m["seed_source"], m["rng_stream"]) for m in meta] == [
        (7, "--seed", [7, 10_000]),
        (8, "--seed", [8, 10_000]),
    ]
    # --seed without --plan is a usage error that names the fix.
    r = invoke(runner, "estimate", "-w", ws, "--seed", "7")
    assert r.exit_code != 0 and "pass it with --plan" in r.output + r.stderr
