"""status: where a study stands and the next command, at every stage of the loop; the
documented exit codes (0 done, 1 error, 2 usage, 3 waiting on results)."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import polars as pl
import pytest
from typer.testing import CliRunner

from bams_cli.state.workspace import Workspace
from tests.conftest import STAGED_PLAN, invoke, ok, simulate_and_ingest, tree_hash, write_toy


class Study:
    """Runs the loop on a small toy2d pool and keeps `status --json` (and its exit code,
    and the human output) after each stage."""

    def __init__(self, tmp: Path):
        self.runner = CliRunner()
        self.tmp = tmp
        self.seg, self.truth = write_toy(tmp / "data", n=400, seed=1)
        self.ws = tmp / "ws"
        self.stages: dict[str, dict] = {}
        self.copies: dict[str, Path] = {}

    def run(self, *args: object):
        return ok(self.runner, *args)

    def ingest(self, handoff: Path) -> None:
        res = self.tmp / f"res-{handoff.stem}.parquet"
        simulate_and_ingest(self.runner, self.ws, handoff, self.truth, res)

    def status(self, stage: str, *, keep: bool = False) -> None:
        r = invoke(self.runner, "status", "-w", self.ws, "--json")
        human = invoke(self.runner, "status", "-w", self.ws)
        assert human.exit_code == r.exit_code
        self.stages[stage] = {
            "code": r.exit_code,
            "json": json.loads(r.stdout),
            "text": human.stdout,
        }
        if keep:  # a copy of the workspace at this stage, for refusals tested later
            self.copies[stage] = self.tmp / stage.replace(" ", "-")
            shutil.copytree(self.ws, self.copies[stage])


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> Study:
    s = Study(tmp_path_factory.mktemp("status"))
    ws = s.ws
    s.run("init", "-w", ws, "--gamma", "0.56", "--costs", "1,0.1", "--dim", "2", "--seed", "2")
    s.status("initialised")
    s.run("embed-reduce", "-w", ws, s.seg, "--columns", "x*", "--method", "identity",
          "--no-standardize")  # fmt: skip
    s.status("pool")
    s.run("select", "-w", ws, "--strategy", "random", "--mixed-fidelity", "--budget", "8")
    s.status("batch 1 pending", keep=True)
    s.ingest(ws / "batches" / "batch-0001.parquet")
    s.status("batch 1 in")
    s.run("fit", "-w", ws, "--restarts", "1")
    s.status("fitted")
    s.run("select", "-w", ws, "--budget", "2", "--clusters", "1", "--workers", "1")
    s.status("batch 2 pending", keep=True)
    s.ingest(ws / "batches" / "batch-0002.parquet")
    s.status("batch 2 in")
    s.run("fit", "-w", ws, "--restarts", "1")
    s.status("refitted")
    # Two stages, to keep the walk short: the default three are walked by
    # tests/test_estimate.py and, through `loop`, by tests/test_loop_driver.py.
    s.run("estimate", "-w", ws, *STAGED_PLAN, "--stages", "2", "--samples", "20")
    s.status("plan pending", keep=True)
    s.ingest(ws / "estimates" / "plan-0001-handoff.csv")
    s.status("plan in")
    s.run("fit", "-w", ws, "--restarts", "1")
    s.status("stage 1 in, fitted")
    s.run("estimate", "-w", ws, *STAGED_PLAN)
    s.status("stage 2 pending")
    s.ingest(ws / "estimates" / "plan-0002-handoff.csv")
    s.status("stage 2 in")
    s.run("estimate", "-w", ws)
    s.status("estimated")
    s.run("fit", "-w", ws, "--restarts", "1")
    s.status("estimated, fitted")
    s.run("report", "-w", ws)
    s.status("done")
    return s


# stage -> exit code, the next step, and a piece of the command it names
NEXT = {
    "initialised": (0, "embed-reduce", "bams-cli embed-reduce -w {ws} SEGMENTS.parquet"),
    "pool": (0, "select", "bams-cli select -w {ws} --strategy random --mixed-fidelity --budget 5"),
    "batch 1 pending": (3, "ingest-results", "bams-cli ingest-results -w {ws} RESULTS.parquet"),
    "batch 1 in": (0, "fit", "bams-cli fit -w {ws}"),
    "fitted": (0, "select", "bams-cli select -w {ws} --budget 8"),
    "batch 2 pending": (3, "ingest-results", "bams-cli ingest-results -w {ws} RESULTS.parquet"),
    "batch 2 in": (0, "fit", "bams-cli fit -w {ws}"),
    "refitted": (0, "select", "bams-cli select -w {ws} --budget 2"),
    "plan pending": (3, "ingest-results", "bams-cli ingest-results -w {ws} RESULTS.parquet"),
    "plan in": (0, "fit", "bams-cli fit -w {ws}"),
    "stage 1 in, fitted": (0, "estimate", "bams-cli estimate -w {ws} --plan"),
    "stage 2 pending": (3, "ingest-results", "bams-cli ingest-results -w {ws} RESULTS.parquet"),
    "stage 2 in": (0, "estimate", "bams-cli estimate -w {ws}"),
    "estimated": (0, "fit", "bams-cli fit -w {ws}"),
    "estimated, fitted": (0, "report", "bams-cli report -w {ws}"),
    "done": (0, "done", None),
}


@pytest.mark.parametrize("stage", list(NEXT))
def test_status_names_the_next_command_at_every_stage(study, stage):
    code, step, command = NEXT[stage]
    got = study.stages[stage]
    assert got["code"] == code == got["json"]["exit_code"]
    assert got["json"]["schema_version"] == 1
    assert got["json"]["next"]["step"] == step
    assert got["json"]["waiting_on_results"] is (code == 3)
    if command is None:
        assert got["json"]["next"]["command"] is None
        assert "nothing to do" in got["text"]
    else:
        assert got["json"]["next"]["command"] == command.format(ws=study.ws)
        assert command.format(ws=study.ws) in got["text"].replace("\n", " ")


# stage -> the phase `status --json` names, and the other commands its text offers
PHASES = {
    "initialised": ("setup", []),
    "pool": ("discovery", []),
    "batch 1 pending": ("discovery", []),
    "batch 1 in": ("discovery", []),
    "fitted": ("discovery", ["bams-cli estimate -w {ws} --plan"]),
    "batch 2 pending": ("discovery", []),
    "batch 2 in": ("discovery", []),
    "refitted": ("discovery", ["bams-cli estimate -w {ws} --plan"]),
    "plan pending": ("estimate", []),
    "plan in": ("estimate", []),
    "stage 1 in, fitted": ("estimate", []),
    "stage 2 pending": ("estimate", []),
    "stage 2 in": ("estimate", []),
    "estimated": ("estimate", []),
    "estimated, fitted": ("estimate", []),
    "done": ("done", ["bams-cli select -w {ws}", "bams-cli estimate -w {ws} --plan"]),
}


@pytest.mark.parametrize("stage", list(PHASES))
def test_status_json_names_the_phase_and_every_command_its_text_offers(study, stage):
    # A Makefile reads where the study is (discovery over: "estimate"; nothing left:
    # "done") and the commands a person reads in `next:`, without parsing the text.
    phase, alternatives = PHASES[stage]
    got = study.stages[stage]
    assert got["json"]["phase"] == phase
    commands = [a["command"] for a in got["json"]["next"]["alternatives"]]
    assert commands == [c.format(ws=study.ws) for c in alternatives]
    for command in commands:
        assert command in got["text"].replace("\n", " ")


@pytest.mark.parametrize(
    ("stage", "handoff"),
    [
        ("batch 1 pending", "batches/batch-0001.csv"),
        ("batch 2 pending", "batches/batch-0002.csv"),
        ("plan pending", "estimates/plan-0001-handoff.csv"),
    ],
)
def test_pending_picks_name_their_hand_off_list(study, stage, handoff):
    got = study.stages[stage]["json"]
    assert got["next"]["handoffs"] == [str(study.ws / handoff)]
    assert f"simulate {study.ws / handoff} and run" in study.stages[stage]["text"]
    rows = got["plans"] if "plan" in stage else got["batches"]
    assert rows[-1]["pending"] == got["pending"] > 0
    n = got["pending"]
    says = f"{n} pick awaits results" if n == 1 else f"{n} picks await results"
    assert says in got["next"]["text"]
    assert all(r["pending"] == 0 for r in rows[:-1])


def test_status_reports_batches_plans_model_and_estimate(study):
    fresh = study.stages["fitted"]["json"]
    assert fresh["model"]["fresh"] is True and fresh["model"]["fitted_on"] == fresh["observations"]
    assert [b["budget"] for b in fresh["batches"]] == [8.0]
    stale = study.stages["batch 2 in"]["json"]
    assert (
        stale["model"]["fresh"] is False
        and "changed after the last fit" in stale["model"]["reason"]
    )
    assert "model: stale" in study.stages["batch 2 in"]["text"]
    assert study.stages["plan in"]["json"]["plans"][0]["estimate"] is None
    done = study.stages["done"]["json"]
    # The estimate combines both stages; it is filed under the last one's plan.
    assert [(p["stage"], p["stages"]) for p in done["plans"]] == [(1, 2), (2, 2)]
    assert done["plans"][1]["estimate"] == str(study.ws / "estimates" / "estimate-0002.json")
    est = done["latest_estimate"]
    assert est["plan"] == 2 and est["estimates"][0]["gamma"] == 0.56
    assert (
        est["estimates"][0]["ci_low"]
        <= est["estimates"][0]["p_hat"]
        <= est["estimates"][0]["ci_high"]
    )
    assert study.stages["initialised"]["json"]["model"] is None
    assert study.stages["initialised"]["json"]["pool_size"] is None
    assert done["pool_size"] == 400 and done["pending"] == 0


def test_a_copied_study_whose_files_lost_their_times_is_still_where_it_was(study, tmp_path):
    # A workspace copied with `cp -r` or restored from a CI artifact: every file's
    # modification time is the copy's, so the batches can look newer than the estimate
    # plans. Status orders them by the times the files record and still says "done".
    import os
    import time

    copy = tmp_path / "ws"
    shutil.copytree(study.ws, copy)
    later = time.time() + 60
    for path in (copy / "batches").iterdir():
        os.utime(path, (later, later))
    # and the report's older than the estimate and the model it shows
    for path in (copy / "estimates").iterdir():
        os.utime(path, (later, later))
    os.utime(copy / "model.json", (later, later))
    r = invoke(study.runner, "status", "-w", copy, "--json")
    got = json.loads(r.stdout)
    assert (got["phase"], got["next"]["step"]) == ("done", "done")


def test_a_report_that_no_longer_shows_the_estimate_is_stale_whatever_its_time(study, tmp_path):
    # The estimate recomputed at another confidence after the report: the report shows
    # the old interval, so `report` is next, though its file is the newest in the copy.
    import os
    import time

    copy = tmp_path / "ws"
    shutil.copytree(study.ws, copy)
    assert invoke(study.runner, "estimate", "-w", copy, "--confidence", "0.8").exit_code == 0
    later = time.time() + 60
    os.utime(copy / "report" / "summary.json", (later, later))
    got = json.loads(invoke(study.runner, "status", "-w", copy, "--json").stdout)
    assert got["next"]["step"] == "report"


def test_status_reads_only(study, tmp_path):
    copy = tmp_path / "ws"
    shutil.copytree(study.copies["batch 1 pending"], copy)
    lock = copy / ".bams.lock"
    before, lock_before = tree_hash(copy), lock.stat().st_mtime_ns
    assert invoke(study.runner, "status", "-w", copy).exit_code == 3
    assert tree_hash(copy) == before and lock.stat().st_mtime_ns == lock_before


def test_a_model_stale_after_a_gamma_edit_is_told_to_fit_once(study, tmp_path):
    # The staleness error carries its own "run `bams-cli fit`", and next added another.
    copy = tmp_path / "ws"
    shutil.copytree(study.ws, copy)
    settings = copy / "settings.toml"
    settings.write_text(settings.read_text().replace("gammas = [", "gammas = [\n    9.5,", 1))
    r = invoke(study.runner, "status", "-w", copy, "--json")
    text = json.loads(r.stdout)["next"]["text"]
    assert "fitted for gammas" in text and text.count("bams-cli fit") == 1, text


@pytest.mark.parametrize(
    ("stage", "args", "needle"),
    [
        ("batch 1 pending", ["select", "--strategy", "random", "--budget", "2"], "--allow-pending"),
        ("batch 1 pending", ["fit", "--restarts", "1"], "batch-0001.csv"),
        ("plan pending", ["select", "--budget", "2", "--clusters", "1"], "estimate plan 1"),
        ("plan pending", ["estimate"], "planned segments have no level-0 result"),
        # A plan drawn beside a pending batch would miss its results, as select refuses.
        (
            "batch 2 pending",
            ["estimate", *STAGED_PLAN, "--samples", "10"],
            "batch 2 awaits results",
        ),
    ],
)
def test_commands_refusing_for_pending_results_exit_3(study, tmp_path, stage, args, needle):
    copy = tmp_path / "ws"
    shutil.copytree(study.copies[stage], copy)
    before = tree_hash(copy)
    r = invoke(study.runner, args[0], "-w", copy, *args[1:])
    assert r.exit_code == 3 and needle in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert tree_hash(copy) == before


def test_a_usage_error_exits_2(study):
    r = invoke(study.runner, "status", "-w", study.ws, "--no-such-flag")
    assert r.exit_code == 2 and "No such option" in r.output
    assert invoke(study.runner, "select", "-w", study.ws, "--budget", "lots").exit_code == 2


def test_a_bad_input_exits_1(study, tmp_path):
    r = invoke(study.runner, "status", "-w", tmp_path / "nowhere")
    assert r.exit_code == 1 and "no such workspace" in r.stderr
    bad = tmp_path / "bad.csv"
    bad.write_text("segment_id,fidelity,value\nt000001,0,oops\n")
    r = invoke(study.runner, "ingest-results", "-w", study.ws, bad)
    assert r.exit_code == 1 and "bad.csv" in r.stderr


def _nan_lengthscale(text: str) -> str:
    doc = json.loads(text)
    doc["hyperparameters"]["lengthscales0"][0] = float("nan")
    return json.dumps(doc)


@pytest.mark.parametrize("damage", [lambda _: "{not json", _nan_lengthscale], ids=["json", "nan"])
def test_a_damaged_model_makes_fit_the_next_step(study, tmp_path, damage):
    copy = tmp_path / "ws"
    shutil.copytree(study.ws, copy)
    (copy / "model.json").write_text(damage((copy / "model.json").read_text()))
    r = invoke(study.runner, "status", "-w", copy, "--json")
    got = json.loads(r.stdout)
    assert r.exit_code == 0 and got["next"]["step"] == "fit"
    assert got["model"]["fresh"] is False and "damaged" in got["model"]["reason"]
    assert "bams-cli fit" not in got["model"]["reason"]  # named once, as the next step
    text = invoke(study.runner, "status", "-w", copy).stdout
    assert " ".join(text.split()).count("bams-cli fit -w") == 1, text


def test_a_batch_s_cost_is_summed_without_rounding_error(tmp_path):
    # 200 cheap runs at cost 0.1 cost 20: a float sum said 19.999999999999986.
    seg, _ = write_toy(tmp_path / "data", n=300, seed=3)
    ws = tmp_path / "ws"
    runner = CliRunner()
    ok(runner, "init", "-w", ws, "--gamma", "0.56", "--costs", "1,0.1", "--dim", "2")
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize")  # fmt: skip
    ok(runner, "select", "-w", ws, "--strategy", "random", "--mixed-fidelity",
       "--level0-share", "0", "--budget", "20")  # fmt: skip
    r = invoke(runner, "status", "-w", ws, "--json")
    [batch] = json.loads(r.stdout)["batches"]
    assert (batch["picks"], batch["cost"]) == (200, 20.0)


@pytest.mark.parametrize(
    ("n", "costs"), [(4, "1,0.1"), (4, "1"), (3, "1,0.3,0.07"), (3, "1,0.2"), (2, "1,0.01")]
)
def test_the_first_batch_command_runs_on_a_pool_smaller_than_its_budget(tmp_path, n, costs):
    # Four segments at levels of cost 1 and 0.1 buy 4.4: the named `--budget 5` was refused
    # ("buys more simulations than the pool has").
    seg, _ = write_toy(tmp_path / "data", n=n, seed=1)
    ws = tmp_path / "ws"
    runner = CliRunner()
    ok(runner, "init", "-w", ws, "--gamma", "0.56", "--costs", costs, "--dim", "2")
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize")  # fmt: skip
    command = json.loads(invoke(runner, "status", "-w", ws, "--json").stdout)["next"]["command"]
    everything = n * sum(float(c) for c in costs.split(","))
    assert command.endswith(f"--budget {everything:g}")
    args = command.split()[1:]
    batch = json.loads(ok(runner, *args, "--json").stdout)
    assert batch["picks"] == n * len(costs.split(","))


def test_a_partly_answered_list_offers_abandon_for_runs_that_never_come_back(study, tmp_path):
    # Runs that crashed for good stop the study until they are abandoned; a list with no
    # result yet is only waiting, and abandoning it is not offered.
    copy = tmp_path / "ws"
    shutil.copytree(study.copies["batch 2 pending"], copy)
    handoff = pl.read_csv(copy / "batches" / "batch-0002.csv")
    part = tmp_path / "part.csv"
    handoff.head(1).write_csv(part)
    res = tmp_path / "res.parquet"
    simulate_and_ingest(study.runner, copy, part, study.truth, res)
    r = invoke(study.runner, "status", "-w", copy, "--json")
    nxt = json.loads(r.stdout)["next"]
    command = f"bams-cli abandon -w {copy} --batch 2 --reason WHY"
    assert [a["command"] for a in nxt["alternatives"]] == [command]
    assert f"runs that can never be simulated: `{command}`" in nxt["text"]


def test_a_study_whose_every_request_was_abandoned_selects_a_new_random_batch(
    toy_ws, runner, tmp_path
):
    # Nothing to fit and nothing awaited: the way on is a new random batch, for status and
    # for the loop alike ("run fit" sent such a study round in a circle: fit refuses).
    from bams_cli import loop

    ok(runner, "select", "-w", toy_ws, "--strategy", "random", "--budget", "3")
    ok(runner, "abandon", "-w", toy_ws, "--batch", "1", "--reason", "simulator lost them")
    r = invoke(runner, "status", "-w", toy_ws, "--json")
    assert r.exit_code == 0, r.output
    nxt = json.loads(r.stdout)["next"]
    assert nxt["step"] == "select" and "--strategy random" in nxt["command"]
    assert "no result yet" in nxt["text"]
    opts = loop.Options(
        simulator="true", batches=2, budget=3, first_budget=3, then_estimate=False,
        samples=None, results_dir=tmp_path, abandon_failed=False, retries=0, clusters=2,
        workers=1, wait=False,
    )  # fmt: skip
    assert loop._next_step(Workspace(toy_ws), opts) == ("select", "batch", 2)
    # ... also once --batches is used up by batches that brought nothing.
    one = dataclasses.replace(opts, batches=1, then_estimate=True)
    assert loop._next_step(Workspace(toy_ws), one) == ("select", "batch", 2)
    record = loop._run(Workspace(toy_ws), opts, "select", "batch", 2, set())
    assert record["picks"] > 0  # a random batch: BAMS would need a model
    assert Workspace(toy_ws).read_batch(2)["strategy"].unique().to_list() == ["random"]


def _list_file(path: Path, written_at: str | None, mtime: float) -> None:
    import os

    import pyarrow as pa
    import pyarrow.parquet as pq

    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {} if written_at is None else {b"bams.written_at": written_at.encode()}
    pq.write_table(pa.table({"x": [1]}).replace_schema_metadata(meta), path)
    os.utime(path, (mtime, mtime))


@pytest.mark.parametrize(
    ("plan_at", "batch_at", "plan_newer_on_disk", "estimating"),
    [
        # the records decide, whatever the copy did to the modification times
        ("2026-11-29T09:20:22.500000+00:00", "2026-11-29T09:20:22.100000+00:00", False, True),
        ("2026-11-29T09:20:22.100000+00:00", "2026-11-29T09:20:22.500000+00:00", True, False),
        # an older bams-cli's record (to the second) against a newer one's
        ("2026-11-29T09:20:23.000001+00:00", "2026-11-29T09:20:23+00:00", False, True),
        # equal records, a record without a time zone, or none: the modification times
        ("2026-11-29T09:20:22+00:00", "2026-11-29T09:20:22+00:00", False, False),
        ("2026-11-29T09:20:22+00:00", "2026-11-29T09:20:22+00:00", True, True),
        ("2026-11-29T09:20:25", "2026-11-29T09:20:22+00:00", False, False),
        (None, "2026-11-29T09:20:22+00:00", True, True),
    ],
)  # fmt: skip
def test_plans_and_batches_are_ordered_by_their_records_then_their_times(
    tmp_path, plan_at, batch_at, plan_newer_on_disk, estimating
):
    from bams_cli import status as status_mod
    from bams_cli.state.workspace import Workspace

    t0 = 1_800_000_000.0
    _list_file(tmp_path / "estimates" / "plan-0001.parquet", plan_at, t0 + plan_newer_on_disk)
    _list_file(tmp_path / "batches" / "batch-0001.parquet", batch_at, t0 + 0.5)
    plans, batches = [{"plan": 1, "written_at": plan_at}], [{"batch": 1, "written_at": batch_at}]
    assert status_mod._estimating(Workspace(tmp_path), plans, batches) is estimating
