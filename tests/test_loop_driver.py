"""`bams-cli loop`: the whole study against a simulator command, without truth in the
workspace; killed at random points and run again, it ends where an uninterrupted run ends;
run again once finished, it does nothing."""

from __future__ import annotations

import contextlib
import json
import os
import random
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from bams_cli import defaults, schemas_json
from bams_cli.state.io import read_metadata_json
from bams_cli.state.lock import LOCK_FILE
from bams_cli.state.workspace import Workspace
from tests.conftest import process_gone, tree_hash, write_toy
from tests.jsonschema_subset import errors

BAMS = [sys.executable, "-m", "bams_cli"]


def _study(tmp: Path, name: str, seg: Path, gamma: str = "0.56", costs: str = "1,0.1") -> Path:
    ws = tmp / name
    for args in _study_args(ws, seg, gamma, costs):
        subprocess.run([*BAMS, *map(str, args)], check=True, capture_output=True)
    return ws


def _study_args(
    ws: Path, seg: Path, gamma: str = "0.56", costs: str = "1,0.1"
) -> list[list[object]]:
    return [
        ["init", "-w", ws, "--gamma", gamma, "--costs", costs, "--dim", "2", "--seed", "4"],
        ["embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
         "--no-standardize"],
    ]  # fmt: skip


def _loop_args(ws: Path, truth: Path, screen: str | None = "off") -> list[str]:
    """The loop to an estimate; ``screen``: its --screen (None: the default, auto), off
    here so the estimate is the staged one whatever the toy's cheap level looks like."""
    # The simulation team's command: the sample simulator answering from its own table.
    sim = (
        f"{shlex.join(BAMS)} simulate {{handoff}} --truth {shlex.quote(str(truth))} -o {{results}}"
    )
    return [*BAMS, "loop", "-w", str(ws), "--simulator", sim, "--batches", "3",
            "--budget", "2", "--first-budget", "4", "--then-estimate", "--samples", "15",
            "--clusters", "2", "--workers", "1",
            *(() if screen is None else ("--screen", screen))]  # fmt: skip


#: The last plan of a default staged estimate: one per stage.
LAST = defaults.STAGES


def _final(ws: Path) -> dict:
    """What a study's outcome is made of (not when it was written)."""
    w = Workspace(ws)
    batches = [
        sorted(w.read_batch(n).select("segment_id", "fidelity").iter_rows())
        for n in w.batch_numbers()
    ]
    obs = w.read_observations(active_only=False).select("segment_id", "fidelity", "value")
    plan = pl.concat(
        [pl.read_parquet(ws / "estimates" / f"plan-{k:04d}.parquet") for k in range(1, LAST + 1)]
    )
    est = json.loads((ws / "estimates" / f"estimate-{LAST:04d}.json").read_text())
    model = json.loads(w.model_path.read_text())
    return {
        "batches": batches,
        "observations": sorted(obs.iter_rows()),
        "plan": sorted(plan["segment_id"].to_list()),
        "estimates": est["estimates"],
        "model": model["observations_hash"],
    }


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("loop")
    seg, truth = write_toy(tmp / "data", n=300, seed=2)
    ws = _study(tmp, "ws", seg)
    done = subprocess.run(
        [*_loop_args(ws, truth), "--json"], capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stderr
    return tmp, seg, truth, ws, json.loads(done.stdout)


def test_loop_runs_the_study_to_an_estimate(data):
    _, _, _, ws, out = data
    steps = [(s["step"], s["list"]) for s in out["steps"]]
    assert steps[:4] == [
        ("select", "batch 1"),
        ("simulate", "batch 1"),
        ("ingest-results", "batch 1"),
        ("fit", None),
    ]
    # The estimate's stages, a refit between each two, then the combined estimate.
    at = [steps.index(("estimate --plan", f"plan {k}")) for k in range(1, LAST + 1)]
    assert all(("fit", None) in steps[a:b] for a, b in zip(at, at[1:], strict=False))
    assert ("estimate", f"plan {LAST}") in steps[at[-1] :]
    assert steps[-1] == ("fit", None)  # the model includes the plan's results
    assert out["batches"] == 3 and out["plans"] == LAST and out["estimate_file"]
    # The output of a loop that did the work validates against its schema, every field a
    # step carried included (the schema test's own study runs a loop with nothing to do).
    assert errors(out, schemas_json.schema("loop")) == []
    carried = {k for s in out["steps"] for k in s}
    assert {"picks", "results", "ingested", "to_simulate", "estimate_file"} <= carried
    described = schemas_json.schema("loop")["properties"]["steps"]["items"]["properties"]
    assert carried <= set(described), sorted(carried - set(described))  # schemas stay open
    status = subprocess.run([*BAMS, "status", "-w", str(ws), "--json"], capture_output=True,
                            text=True)  # fmt: skip
    s = json.loads(status.stdout)
    assert status.returncode == 0 and s["pending"] == 0 and s["model"]["fresh"]
    assert s["next"]["step"] == "report"
    assert s["batches"][1]["strategy"] == "bams"


def _headline(ws: Path, plan: int) -> list[str]:
    """The lines `status` gives the estimate of ``plan``, from its file."""
    doc = json.loads((ws / "estimates" / f"estimate-{plan:04d}.json").read_text())
    return [
        f"estimate (plan {plan}): gamma {e['gamma']:g}: p_hat {e['p_hat']:.4g}, "
        f"{round(100 * e['confidence'])}% interval [{e['ci_low']:.4g}, {e['ci_high']:.4g}]"
        for e in doc["estimates"]
    ]


def test_a_screened_loop_screens_refits_confirms_and_estimates(data, tmp_path):
    # `loop --then-estimate` at its default, --screen auto, on a toy whose fitted cheap
    # level tracks level 0: the screen's cheap runs as a batch, simulated and ingested as
    # any, a refit, the level-0 confirmation (plan 1), its results, the estimate.
    _, seg, truth, _, _ = data
    ws = _study(tmp_path, "screened", seg)
    done = subprocess.run(
        [*_loop_args(ws, truth, screen=None), "--json"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert errors(out, schemas_json.schema("loop")) == []
    steps = [(s["step"], s["list"]) for s in out["steps"]]
    first = steps.index(("estimate --plan", "plan 1"))
    assert steps[first + 1 : first + 4] == [
        ("simulate", "batch 4"),
        ("ingest-results", "batch 4"),
        ("fit", None),
    ]
    assert steps[first + 4 : first + 8] == [
        ("estimate --plan", "plan 1"),
        ("simulate", "plan 1"),
        ("ingest-results", "plan 1"),
        ("estimate", "plan 1"),
    ]
    batch = Workspace(ws).read_batch(4)
    assert (batch["strategy"] == "screen").all() and (batch["fidelity"] == 1).all()
    assert out["steps"][first]["to_simulate"] == batch.height
    meta = read_metadata_json(ws / "estimates" / "plan-0001.parquet")
    assert meta["weighting"] == "screen" and meta["screen"]["batch"] == 4
    assert out["plans"] == 1 and out["estimate_file"].endswith("estimate-0001.json")
    assert out["batches"] == 3  # discovery batches, as --batches counts them: not the screen
    # Run again, it has nothing left to do: the screen is neither drawn nor confirmed again.
    again = subprocess.run(
        [*_loop_args(ws, truth, screen=None), "--json"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert again.returncode == 0, again.stderr
    assert [s["step"] for s in json.loads(again.stdout)["steps"]] == []
    # The screen's batch is the estimate's, not a discovery batch: a fourth discovery
    # batch is a new BAMS batch (5), not the screen counted as one.
    more = [*_loop_args(ws, truth, screen=None), "--json"]
    more[more.index("--batches") + 1] = "4"
    more.remove("--then-estimate")
    fourth = subprocess.run(more, capture_output=True, text=True, check=False)
    assert fourth.returncode == 0, fourth.stderr
    assert ("select", "batch 5") in [
        (s["step"], s["list"]) for s in json.loads(fourth.stdout)["steps"]
    ]
    assert set(Workspace(ws).read_batch(5)["strategy"].to_list()) == {"bams"}


def test_loop_draws_no_discovery_batch_inside_an_open_screen(data, tmp_path):
    # A study that drew its screen by hand (`estimate --plan`, --screen auto) and then asks
    # the loop for a fourth discovery batch: its level-0 picks would land among the
    # segments the screen counted as unknown, and the confirmation would refuse them, so
    # the loop refuses first (exit 1, nothing written) and names the way on; with the
    # discovery it has, it confirms the screen and estimates.
    _, seg, truth, _, _ = data
    ws = _study(tmp_path, "open-screen", seg)
    three = [a for a in _loop_args(ws, truth, screen=None) if a != "--then-estimate"]
    subprocess.run(three, check=True, capture_output=True)
    drawn = subprocess.run(
        [*BAMS, "estimate", "-w", str(ws), "--plan", "--samples", "15", "--json"],
        capture_output=True, text=True, check=True,
    )  # fmt: skip
    assert "screen_file" in json.loads(drawn.stdout)  # the toy's cheap level tracks level 0
    more = _loop_args(ws, truth, screen=None)
    more[more.index("--batches") + 1] = "4"
    before = tree_hash(ws)
    r = subprocess.run(more, capture_output=True, text=True, check=False)
    assert r.returncode == 1, r.stderr
    assert "screen-0001.parquet awaits its level-0 confirmation" in r.stderr
    assert "--batches 3 --then-estimate" in r.stderr
    assert tree_hash(ws) == before
    done = subprocess.run(
        [*_loop_args(ws, truth, screen=None), "--json"], capture_output=True, text=True,
        check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    steps = [(s["step"], s["list"]) for s in json.loads(done.stdout)["steps"]]
    assert ("select", "batch 5") not in steps and ("estimate", "plan 1") in steps
    meta = read_metadata_json(ws / "estimates" / "plan-0001.parquet")
    assert meta["weighting"] == "screen" and meta["screen"]["batch"] == 4


def test_loop_refuses_a_screen_it_cannot_draw_before_any_batch(data, tmp_path):
    _, seg, truth, _, _ = data
    ws = _study(tmp_path, "refused", seg)
    before = tree_hash(ws)
    for extra, needle in (
        (["--screen", "1.2"], "must lie in (0, 1)"),
        (["--screen", "half"], "auto, or off"),
        (["--screen", "0.3"], "pass --then-estimate"),
        (["--screen", "auto"], "pass --then-estimate"),
    ):
        args = (
            [a for a in _loop_args(ws, truth) if a != "--then-estimate"]
            if needle.startswith("pass")
            else _loop_args(ws, truth)
        )
        r = subprocess.run([*args, *extra], capture_output=True, text=True, check=False)
        assert r.returncode == 2 and needle in r.stderr, r.stderr
    assert tree_hash(ws) == before


def test_a_loop_that_ends_with_the_estimate_prints_it(data, tmp_path):
    # A loop whose last step was `estimate` ended on "estimate  .../estimate-000N.json":
    # the rate itself took a `report` or `status`.
    tmp, _, truth, ws, out = data
    copy = tmp_path / "ws"
    shutil.copytree(ws, copy)
    (copy / "estimates" / f"estimate-{LAST:04d}.json").unlink()  # stopped before its estimate
    args = [*_loop_args(copy, truth)]
    done = subprocess.run(args, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stderr.splitlines() == [f"loop [3/4]: plan {LAST}: estimate"]  # its one step
    lines = _headline(copy, LAST)
    assert len(lines) == 1 and lines[0] in done.stdout.splitlines()
    # --json: the same headline, as `status --json` gives it (latest_estimate)
    assert out["estimate"]["plan"] == LAST and out["estimate"]["file"] == out["estimate_file"]
    got = out["estimate"]["estimates"][0]
    doc = json.loads((ws / "estimates" / f"estimate-{LAST:04d}.json").read_text())["estimates"][0]
    assert {k: got[k] for k in ("gamma", "p_hat", "ci_low", "ci_high", "confidence")} == {
        k: doc[k] for k in ("gamma", "p_hat", "ci_low", "ci_high", "confidence")
    }
    # Run again, it has nothing to do and says what the estimate is.
    again = subprocess.run(args, capture_output=True, text=True)
    assert again.returncode == 0 and "nothing to do" in again.stderr
    assert lines[0] in again.stdout.splitlines()


@pytest.mark.parametrize(
    "screen",
    [None, pytest.param("off", marks=pytest.mark.slow)],  # 40-50 s each under load
    ids=["screen-auto", "screen-off"],
)
def test_a_three_level_study_runs_to_an_estimate(data, tmp_path, screen):
    """Two cheap simulators beside level 0 (costs 1, 0.3, 0.05): the loop's mixed-fidelity
    first batch, BAMS batches, the estimate (screened or staged) and its files, the model
    with a discrepancy for each cheap level, and `status` and `report` reading them."""
    _, seg, truth2, _, _ = data
    rng = np.random.default_rng(0)
    two = pl.read_parquet(truth2)
    f0 = two["value_0"].to_numpy()
    truth = tmp_path / "truth3.parquet"
    two.with_columns(  # level 2 biased by 0.3 and noisier than level 1
        value_2=pl.Series(f0 + 0.3 + 0.2 * rng.standard_normal(len(f0)))
    ).write_parquet(truth)
    ws = _study(tmp_path, "three", seg, costs="1,0.3,0.05")
    done = subprocess.run(
        [*_loop_args(ws, truth, screen=screen), "--json"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout)
    assert errors(out, schemas_json.schema("loop")) == []
    w = Workspace(ws)
    picked = pl.concat([w.read_batch(n) for n in w.batch_numbers()])
    assert set(picked["fidelity"].to_list()) == {0, 1, 2}
    model = json.loads(w.model_path.read_text())
    assert len(model["hyperparameters"]["offsets"]) == 2  # one discrepancy per cheap level
    r = subprocess.run([*BAMS, "estimate", "-w", str(ws), "--json"], capture_output=True,
                       text=True)  # fmt: skip
    assert r.returncode == 0, r.stderr
    est = json.loads(r.stdout)
    assert errors(est, schemas_json.schema("estimate")) == []
    (e,) = est["estimates"]
    assert 0 <= e["ci_low"] <= e["p_hat"] <= e["ci_high"] <= 1
    weighting = read_metadata_json(ws / "estimates" / "plan-0001.parquet")["weighting"]
    if screen is None:  # level 1 tracks level 0 on the toy: --screen auto screens with it
        assert weighting == "screen"
        assert (w.read_batch(4)["fidelity"] == 1).all()
    else:
        assert weighting != "screen" and out["plans"] == LAST
    for cmd in (["status", "-w", ws, "--json"], ["report", "-w", ws, "--json"]):
        r = subprocess.run([*BAMS, *map(str, cmd)], capture_output=True, text=True)
        assert r.returncode == 0, r.stderr


def test_a_finished_loop_does_nothing(data):
    _, _, truth, ws, _ = data
    before = tree_hash(ws)
    again = subprocess.run([*_loop_args(ws, truth), "--json"], capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    assert json.loads(again.stdout)["unchanged"] is True
    assert tree_hash(ws) == before


@pytest.mark.slow  # about a minute; make test was near its 10-minute budget
def test_a_loop_killed_at_random_points_ends_where_an_uninterrupted_one_does(data):
    tmp, seg, truth, ws, _ = data
    resumed = _study(tmp, "killed", seg)
    rng = random.Random(13)
    for _ in range(4):
        proc = subprocess.Popen(
            _loop_args(resumed, truth),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,  # its simulator and workers die with it, as in a job kill
        )
        time.sleep(rng.uniform(1.0, 6.0))
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    done = subprocess.run(_loop_args(resumed, truth), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert _final(resumed) == _final(ws)


def test_a_failing_simulator_stops_the_loop_naming_it(data, tmp_path):
    tmp, seg, _, _, _ = data
    ws = _study(tmp_path, "ws", seg)
    # It writes part of its file, then fails: what it wrote is not kept.
    args = [*BAMS, "loop", "-w", str(ws), "--simulator", "echo x > {results}; exit 7 # {handoff}",
            "--batches", "2", "--budget", "2"]  # fmt: skip
    r = subprocess.run(args, capture_output=True, text=True)
    assert r.returncode == 1 and "exited with 7" in r.stderr and "batch-0001.csv" in r.stderr
    assert not list((ws / "loop-results").glob(".partial-*"))
    s = subprocess.run([*BAMS, "status", "-w", str(ws), "--json"], capture_output=True, text=True)
    assert s.returncode == 3  # batch 1 drawn, waiting for its results: resumable
    r = subprocess.run([*BAMS, "loop", "-w", str(ws), "--simulator", "true", "--batches", "2"],
                       capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 2 and "must name {handoff}" in r.stderr
    # With --retries 1 the failed run is a try of its own, noted on disk, and the list is
    # simulated once more before the loop stops, saying the retries are spent.
    r = subprocess.run([*args, "--retries", "1"], capture_output=True, text=True)
    assert r.returncode == 1, r.stderr
    assert "batch 1: simulate: the simulator exited with 7" in r.stderr
    assert "retry 1 of 1" in r.stderr and "its --retries 1 spent; fix it" in r.stderr
    [note] = (ws / "loop-results").glob("retried-*")
    assert note.name == "retried-1-batch-0001.failed.txt" and "exited with 7" in note.read_text()


FLAKY = """
import os, subprocess, sys
count, truth, handoff, results = sys.argv[1:]
n = int(open(count).read()) + 1 if os.path.exists(count) else 1
open(count, "w").write(str(n))
if n % 2:  # every other run: a licence server that did not answer
    sys.exit("licence server unavailable")
subprocess.run([*BAMS, "simulate", handoff, "--truth", truth, "-o", results], check=True)
"""


def test_with_retries_a_simulator_that_fails_now_and_then_is_run_again(data, tmp_path):
    # A simulator failing one run in three stopped the loop at every failure, --retries 3
    # or not: a trial study took 11 runs of the same loop to finish.
    tmp, seg, truth, _, _ = data
    ws, args = _scripted_loop(tmp_path, seg, truth, FLAKY, "runs", "--retries", "1", "--json")
    count = tmp_path / "runs"
    r = subprocess.run(args, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert count.read_text() == "2" and Workspace(ws).pending().height == 0
    assert "the simulator exited with 1" in r.stderr and "retry 1 of 1" in r.stderr
    out = json.loads(r.stdout)
    steps = out["steps"]
    assert [s["step"] for s in steps] == ["select", "simulate", "simulate", "ingest-results", "fit"]
    assert steps[1]["failed"] == 1 and "results" in steps[2]
    assert errors(out, schemas_json.schema("loop")) == []  # a failed step's fields too
    described = schemas_json.schema("loop")["properties"]["steps"]["items"]["properties"]
    assert {k for s in steps for k in s} <= set(described)


@pytest.mark.slow  # about a minute: make test ran 14 min (budget 10)
def test_a_second_loop_is_refused_naming_the_first_then_waits_for_it(data, tmp_path):
    """One loop drives a workspace at a time: while the first waits on its simulator (no
    command lock held then), a second is refused naming it; with --wait it runs once the
    first has finished and finds nothing left to do."""
    tmp, seg, truth, ws, _ = data
    study = _study(tmp_path, "ws", seg)
    gate = tmp_path / "gate"
    args = _loop_args(study, truth)
    sim = args[args.index("--simulator") + 1]
    gated = f"while [ ! -e {shlex.quote(str(gate))} ]; do sleep 0.05; done; {sim}"
    args[args.index("--simulator") + 1] = gated
    first = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    handoff = study / "batches" / "batch-0001.csv"
    deadline = time.monotonic() + 120
    while not handoff.exists() and first.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert handoff.exists(), first.stderr.read() if first.poll() is not None else "no batch 1"
    try:  # without the loop lock it would simulate batch 1 too, and wait at the gate
        second = subprocess.run(args, capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        gate.touch()
        first.wait(timeout=600)
        raise
    assert second.returncode == 1
    assert f"another `bams-cli loop` runs here: pid {first.pid}" in second.stderr
    assert len(second.stderr.strip().splitlines()) == 1
    waiting = subprocess.Popen(
        [*args, "--wait", "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    time.sleep(1.0)
    assert waiting.poll() is None  # still waiting for the first loop
    gate.touch()
    assert first.wait(timeout=600) == 0, first.stderr.read()
    out, err = waiting.communicate(timeout=600)
    assert waiting.returncode == 0, err
    assert json.loads(out)["unchanged"] is True
    assert _final(study) == _final(ws)


@pytest.mark.slow  # about a minute: make test ran 14 min (budget 10)
def test_a_loop_killed_inside_a_step_is_noted_once_by_the_next(data, tmp_path):
    """Killed while a step held the command lock, a loop leaves both its locks to the next
    loop, which takes them over saying so in one note, not one per lock."""
    tmp, seg, truth, _, _ = data
    ws = _study(tmp_path, "ws", seg)
    args = _loop_args(ws, truth)
    proc = subprocess.Popen(
        args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    holder = None
    deadline = time.monotonic() + 120
    while holder != proc.pid and proc.poll() is None and time.monotonic() < deadline:
        try:  # a step (select, fit) holds the command lock: its record names the loop
            holder = json.loads((ws / LOCK_FILE).read_text() or "{}").get("pid")
        except (OSError, ValueError):
            pass
        time.sleep(0.01)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert holder == proc.pid
    again = subprocess.run(args, capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    notes = [line for line in again.stderr.splitlines() if "died holding the lock" in line]
    assert len(notes) == 1 and notes[0].startswith(f"note: {ws}: pid {proc.pid} on ")


# A simulator that hands its work to a child process and waits, as a wrapper script does;
# it records both pids next to the file named by its first argument.
SLEEPER = """#!/bin/sh
echo $$ > "$1.shell"
sleep 300 &
echo $! > "$1.child"
wait
"""


def _start_sleeper_loop(tmp_path, seg, **popen):
    """A loop whose simulator is SLEEPER, started and waited for until the simulator's
    shell and child have written their pids: (the loop's Popen, [shell pid, child pid])."""
    ws = _study(tmp_path, "ws", seg)
    sim = tmp_path / "sleeper.sh"
    sim.write_text(SLEEPER)
    sim.chmod(0o755)
    pids = tmp_path / "sim"
    args = [*BAMS, "loop", "-w", str(ws), "--simulator", f"{sim} {pids} {{handoff}} {{results}}",
            "--batches", "1", "--budget", "2"]  # fmt: skip
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            **popen)  # fmt: skip
    child = pids.with_suffix(".child")

    def written() -> bool:  # the pid and its newline, not a file just created
        return child.exists() and child.read_text().endswith("\n")

    deadline = time.monotonic() + 120
    while not written() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    return proc, [int(pids.with_suffix(s).read_text()) for s in (".shell", ".child")]


def _end_leftovers(started: list[int]) -> None:
    """SIGKILL whatever of the simulator a failing test left running."""
    for pid in started:
        if not process_gone(pid):
            os.kill(pid, signal.SIGKILL)


@pytest.mark.slow  # 5-10 s each: make test ran 625 s on a clean clone (budget 600)
@pytest.mark.parametrize(
    "signum, code", [(signal.SIGINT, 128 + signal.SIGINT), (signal.SIGKILL, -signal.SIGKILL)],
    ids=["INT", "KILL"],
)  # fmt: skip
def test_a_signal_to_the_loop_s_whole_job_ends_the_simulator_and_its_children(
    data, tmp_path, signum, code
):
    # The whole job's process group gets the signal: Ctrl-C in a terminal (SIGINT), a CI
    # runner's timeout or `kill -9 -- -PGID` (SIGKILL, which the loop cannot catch).
    # - INT: the simulator's shell dies with the loop's handler running, and its background
    #   child (started with SIGINT ignored by a non-interactive shell) was re-parented to
    #   init before the loop listed the tree, and kept running while the loop said every
    #   process was ended.
    # - KILL: the simulator must be in the group to end with it (in a session of its own
    #   it kept running).
    tmp, seg, truth, _, _ = data
    proc, started = _start_sleeper_loop(tmp_path, seg, start_new_session=True)
    try:
        os.killpg(proc.pid, signum)
        proc.wait(timeout=60)
        deadline = time.monotonic() + 10
        while not all(process_gone(p) for p in started) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert [p for p in started if not process_gone(p)] == []
    finally:
        _end_leftovers(started)
        err = proc.communicate()[1]
    assert proc.returncode == code, err


@pytest.mark.slow  # 20-40 s each: make test ran 812 s on a clean clone (budget 600)
def test_a_loop_started_under_nohup_outlives_its_terminal(data, tmp_path):
    # nohup ignores SIGHUP for the command; the loop's own handler had replaced that, so a
    # closed terminal or SSH session stopped a loop that was meant to outlive it.
    tmp, seg, truth, _, _ = data
    proc, started = _start_sleeper_loop(
        tmp_path, seg, preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN)
    )
    try:
        proc.send_signal(signal.SIGHUP)
        time.sleep(1.0)
        assert proc.poll() is None and not any(process_gone(p) for p in started)
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    finally:
        _end_leftovers(started)
        proc.kill()
        proc.communicate()
    assert proc.returncode == 128 + signal.SIGTERM


@pytest.mark.slow  # 20-40 s each: make test ran 812 s on a clean clone (budget 600)
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["TERM", "INT"])
def test_a_stopped_loop_ends_its_simulator_and_resumes(data, tmp_path, signum):
    """`kill -TERM` (or -INT) of a loop waiting on its simulator ends the simulator and what
    it started, exits 128 + the signal, and leaves the batch pending: run again, the loop
    simulates it and goes on."""
    tmp, seg, truth, _, _ = data
    proc, started = _start_sleeper_loop(tmp_path, seg)
    ws, args = tmp_path / "ws", proc.args
    try:
        proc.send_signal(signum)
        proc.wait(timeout=60)
        assert [p for p in started if not process_gone(p)] == []  # gone as the loop exits
    finally:
        _end_leftovers(started)
        proc.kill()
        err = proc.communicate()[1]
    assert proc.returncode == 128 + signum
    name = signal.Signals(signum).name
    assert err.strip().splitlines()[-1] == (
        f"error: stopped by {name} while the simulator ran on batch 1: the simulator and every "
        "process it started were ended, and batch 1 still awaits results; run the same "
        "`bams-cli loop` again to resume"
    )
    assert not list((ws / "loop-results").iterdir())  # no partial results left behind
    status = subprocess.run([*BAMS, "status", "-w", str(ws), "--json"], capture_output=True,
                            text=True)  # fmt: skip
    s = json.loads(status.stdout)
    assert status.returncode == 3 and s["batches"][0]["pending"] == s["batches"][0]["picks"]
    real = _loop_args(ws, truth)
    args[args.index("--simulator") + 1] = real[real.index("--simulator") + 1]
    again = subprocess.run([*args, "--json"], capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    assert "died holding the lock" not in again.stderr  # the stopped loop let go of its lock
    steps = [(s["step"], s["list"]) for s in json.loads(again.stdout)["steps"]]
    assert steps == [("simulate", "batch 1"), ("ingest-results", "batch 1"), ("fit", None)]


@pytest.mark.slow  # 20-40 s each: make test ran 812 s on a clean clone (budget 600)
def test_a_loop_started_while_a_killed_loop_s_simulator_runs_refuses_naming_it(data, tmp_path):
    # SIGKILL of the loop alone leaves its simulator running; a loop started then ran a
    # second simulator on the same list, both writing the same results file.
    tmp, seg, truth, _, _ = data
    proc, started = _start_sleeper_loop(tmp_path, seg)
    ws, args = tmp_path / "ws", proc.args
    # The loop notes its simulator before starting it (a loop killed between the start
    # and a later note left one that no loop could know of: test_the_note_of_a_simulator_
    # finds_it_before_its_pid_is_known).
    record = ws / "loop-results" / ".simulator-batch-0001.csv.json"
    try:
        assert record.exists(), "the loop never noted its simulator"
        proc.kill()  # the loop alone
        proc.wait(timeout=60)  # (its stderr stays open: the simulator holds it)
        assert not process_gone(started[0])
        refused = subprocess.run(args, capture_output=True, text=True)
        assert refused.returncode == 1, refused.stderr
        [line] = [x for x in refused.stderr.splitlines() if x.startswith("error:")]
        assert line.startswith(
            "error: batch 1: the simulator an earlier `bams-cli loop` started on it is still "
            "running (`"
        ), line
        # The whole tree, named to be ended: the `sh -c` the loop started, the simulator's
        # shell and its child.
        named = [int(x) for x in line.split("`kill ")[1].split("`")[0].split()]
        assert set(started) <= set(named) and len(named) == 3, line
    finally:
        _end_leftovers(started)
        proc.stderr.close()
    deadline = time.monotonic() + 30
    while not process_gone(started[0]) and time.monotonic() < deadline:
        time.sleep(0.05)
    real = _loop_args(ws, truth)
    args[args.index("--simulator") + 1] = real[real.index("--simulator") + 1]
    again = subprocess.run([*args, "--json"], capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    steps = [(s["step"], s["list"]) for s in json.loads(again.stdout)["steps"]]
    assert steps == [("simulate", "batch 1"), ("ingest-results", "batch 1"), ("fit", None)]
    assert not list((ws / "loop-results").glob(".simulator-*"))  # the note of it is gone


def test_the_note_of_a_simulator_finds_it_before_its_pid_is_known(tmp_path):
    """A loop killed by SIGKILL just after starting its simulator, before it could learn
    the pid, leaves only the note it wrote first: a later loop finds the simulator and what
    it started by the token in their environment, refuses naming them all, and goes on
    once they are gone."""
    from bams_cli import loop

    record = tmp_path / ".simulator-batch-0001.csv.json"
    loop._record_simulator(record, "t0k3n", "sim {handoff}")
    env = {**os.environ, loop.SIMULATOR_TOKEN_ENV: "t0k3n"}
    pids = tmp_path / "pids"
    # A shell that starts a child, as a simulator script does; both inherit the token.
    tree = subprocess.Popen(["sh", "-c", f"sleep 60 & echo $$ $! > {pids}; wait"], env=env)
    other = subprocess.Popen(  # another study's simulator: its token is not this one's
        ["sleep", "60"], env={**os.environ, loop.SIMULATOR_TOKEN_ENV: "another"}
    )
    expected: list[int] = []
    try:
        deadline = time.monotonic() + 30
        while not (pids.exists() and len(pids.read_text().split()) == 2):
            assert time.monotonic() < deadline
            time.sleep(0.02)
        expected = sorted(int(x) for x in pids.read_text().split())
        with pytest.raises(loop.LoopError) as exc:
            loop._refuse_an_earlier_loops_simulator(record, "batch", 1)
        named = [int(x) for x in str(exc.value).split("`kill ")[1].split("`")[0].split()]
        assert named == expected and other.pid not in named
        assert "(`sim {handoff}`, pid" in str(exc.value) and record.exists()
    finally:
        for p in expected:
            with contextlib.suppress(ProcessLookupError):
                os.kill(p, signal.SIGKILL)
        tree.wait(timeout=30)
        other.kill()
        other.wait(timeout=30)
    deadline = time.monotonic() + 30
    while not all(process_gone(p) for p in expected):
        assert time.monotonic() < deadline
        time.sleep(0.02)
    loop._refuse_an_earlier_loops_simulator(record, "batch", 1)  # nothing runs: goes on
    assert not record.exists()
    record.write_text('{"pid": 1, "sta')  # written by a loop killed mid-write
    loop._refuse_an_earlier_loops_simulator(record, "batch", 1)
    assert not record.exists()


@pytest.mark.slow  # 5-10 s each: make test ran 625 s on a clean clone (budget 600)
def test_a_simulator_s_memory_is_not_held_against_the_loop(data, tmp_path):
    # Every command runs under a memory ceiling (BAMS_MAX_MEMORY here), counted over the
    # command's process tree; the loop's simulator is the user's program, and one that
    # took more than the ceiling had the loop stopped (and the simulator killed).
    tmp, seg, truth, _, _ = data
    ws = _study(tmp_path, "ws", seg)
    hog = tmp_path / "hog.py"  # 600 MiB, every page touched, held for 2.5 s
    hog.write_text("import time\nb = bytearray(600 * 2**20)\nb[::4096] = b'x' * (len(b) // 4096)\n"
                   "time.sleep(2.5)\n")  # fmt: skip
    big = tmp_path / "big-sim.sh"
    big.write_text(
        f"#!/bin/sh\n{shlex.quote(sys.executable)} {shlex.quote(str(hog))}\n"
        f'exec {shlex.join(BAMS)} simulate "$1" --truth {shlex.quote(str(truth))} -o "$2"\n'
    )
    big.chmod(0o755)
    args = [*BAMS, "loop", "-w", str(ws), "--simulator", f"{big} {{handoff}} {{results}}",
            "--batches", "1", "--budget", "2", "--workers", "1"]  # fmt: skip
    env = os.environ | {"BAMS_MAX_MEMORY": "500M"}
    done = subprocess.run(args, capture_output=True, text=True, env=env)
    assert done.returncode == 0, done.stderr
    assert Workspace(ws).read_observations().height > 0


@pytest.mark.slow  # about a minute: make test ran 14 min (budget 10)
def test_the_loop_shows_the_warnings_its_steps_give(data, tmp_path):
    # Run by hand, fit, select and estimate --plan each print their warnings; the loop ran
    # the same steps and printed none (a trial's fit warned twice that the model was
    # overconfident, and its loop logs held no warning at all).
    tmp, seg, truth, _, _ = data
    ws = _study(tmp_path, "ws", seg, gamma="0.05")  # no segment fails: nothing checks p_n
    args = _loop_args(ws, truth)
    args[args.index("--batches") + 1] = "1"
    del args[args.index("--samples") : args.index("--samples") + 2]  # the default K warns
    done = subprocess.run(args, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    plan = [line for line in done.stderr.splitlines() if line.startswith("warning: plan 1: ")]
    assert len(plan) == 1 and "estimate --plan: no level-0 failure is known" in plan[0]


# A simulator with run-to-run noise (every call answers a little differently) whose first
# call crashes on the first two requests: argv = flag file, truth, hand-off, results.
NOISY = """
import csv, random, subprocess, sys
from pathlib import Path
flag, truth, handoff, results = sys.argv[1:5]
raw = results + ".raw.csv"
subprocess.run([*BAMS, "simulate", handoff, "--truth", truth, "-o", raw], check=True)
rows = list(csv.DictReader(open(raw)))
first = not Path(flag).exists() or sys.argv[5:] == ["always"]  # crash once, or every time
Path(flag).touch()
for i, r in enumerate(rows):
    r["value"], r["status"] = str(float(r["value"]) + random.uniform(-0.01, 0.01)), "ok"
    if first and i < 2:
        r["value"], r["status"] = "", "crashed"
with open(results, "w", newline="") as fh:
    w = csv.DictWriter(fh, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
"""


def test_a_rerun_after_crashed_runs_simulates_only_what_has_no_result(data, tmp_path):
    # The loop stops when runs crashed and says: move the results file aside to run the
    # simulator again. It then handed the whole list to the simulator once more, and a
    # simulator with run-to-run noise answered the runs already logged with other values,
    # which ingesting refused as conflicts, again on every rerun.
    tmp, seg, truth, _, _ = data
    ws, args = _scripted_loop(tmp_path, seg, truth, NOISY, "crashed-once")
    first = subprocess.run(args, capture_output=True, text=True)
    assert first.returncode == 1 and "2 requests of batch 1 still have no result" in first.stderr
    assert (
        "move the file aside (its results are in the workspace) to run the simulator "
        "again on those requests alone" in first.stderr
    )
    assert first.stderr.count("batch 1: ingest-results") == 1  # one step, one progress line
    results = ws / "loop-results" / "batch-0001.csv"
    results.rename(results.with_name("first-try-batch-0001.csv"))  # as the message says
    again = subprocess.run([*args, "--json"], capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    assert len(pl.read_csv(results)) == 2  # the two crashed requests were simulated, no more
    assert Workspace(ws).pending().height == 0
    # --batches 1 ends, as every loop does, with the model of all the results: `fit`
    # was left to the user, and the next `select` refused the stale model.
    assert [s["step"] for s in json.loads(again.stdout)["steps"]][-1] == "fit"
    Workspace(ws).require_fresh_model()
    # The pending-only list it simulated goes once the batch is answered.
    assert not (ws / "loop-results" / "batch-0001.pending.csv").exists()


BAD_LEVEL = """
import subprocess, sys
flag, truth, handoff, results = sys.argv[1:]
subprocess.run([*BAMS, "simulate", handoff, "--truth", truth, "-o", results], check=True)
if not __import__("os").path.exists(flag):  # the first time: a bug writes level 3
    open(flag, "w").close()
    lines = open(results).read().splitlines()
    head = lines[0].split(",")
    row = lines[1].split(",")
    row[head.index("fidelity")] = "3"
    open(results, "w").write("\\n".join([lines[0], ",".join(row), *lines[2:]]) + "\\n")
"""


def _scripted_loop(tmp_path: Path, seg: Path, truth: Path, script: str, state: str, *extra: str):
    """A study and the loop arguments (one batch of budget 3, then ``extra``) whose simulator
    is ``script``, a Python program run as ``simulator.py STATE TRUTH HANDOFF RESULTS`` with
    ``BAMS`` defined, STATE the file ``tmp_path / state``: (workspace, argv)."""
    ws = _study(tmp_path, "ws", seg)
    sim = tmp_path / "simulator.py"
    sim.write_text(f"BAMS = {BAMS!r}\n" + script)
    command = f"{sys.executable} {sim} {tmp_path / state} {truth} {{handoff}} {{results}}"
    args = [*BAMS, "loop", "-w", str(ws), "--simulator", command, "--batches", "1",
            "--budget", "3", *extra]  # fmt: skip
    return ws, args


@pytest.mark.slow  # 5-10 s each: make test ran 625 s on a clean clone (budget 600)
def test_results_the_loop_s_simulator_wrote_wrong_are_moved_aside_and_simulated_again(
    data, tmp_path
):
    # A simulator that exits 0 with a file ingest-results refuses: the loop kept the file,
    # and every rerun ingested it again and failed the same way, the simulator fixed or not.
    tmp, seg, truth, _, _ = data
    ws, args = _scripted_loop(tmp_path, seg, truth, BAD_LEVEL, "wrote-once")
    first = subprocess.run(args, capture_output=True, text=True)
    results = ws / "loop-results" / "batch-0001.csv"
    rejected = ws / "loop-results" / "rejected-batch-0001.csv"
    assert first.returncode == 1
    [line] = [x for x in first.stderr.splitlines() if x.startswith("error:")]
    assert line.startswith(f"error: {results}: column 'fidelity', row 1: fidelity 3"), line
    assert f"moved to {rejected}" in line and "simulates the list again" in line
    assert rejected.exists() and not results.exists()  # kept for the user to read
    assert len(Workspace(ws).read_observations()) == 0  # nothing of it ingested
    again = subprocess.run(args, capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    assert Workspace(ws).pending().height == 0 and len(Workspace(ws).read_observations()) > 0


@pytest.mark.slow  # 20-40 s each: make test ran 812 s on a clean clone (budget 600)
def test_with_retries_left_a_refused_results_file_is_a_try_and_the_list_is_simulated_again(
    data, tmp_path
):
    # --retries covered failed rows only: a refused file stopped the loop with tries left.
    tmp, seg, truth, _, _ = data
    ws, args = _scripted_loop(tmp_path, seg, truth, BAD_LEVEL, "wrote-once", "--retries", "1")
    r = subprocess.run(args, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    folder = ws / "loop-results"
    [warning] = [x for x in r.stderr.splitlines() if "retry 1 of 1" in x]
    assert "column 'fidelity', row 1: fidelity 3" in warning
    assert f"kept as {folder / 'retried-1-batch-0001.csv'}" in warning
    assert (folder / "retried-1-batch-0001.csv").exists()
    assert Workspace(ws).pending().height == 0 and len(Workspace(ws).read_observations()) > 0
    # A simulator that writes a refused file every time: one retry, then the loop stops,
    # and a second loop with the same --retries counts the kept files and tries no more.
    always = tmp_path / "always_bad.py"
    always.write_text(
        f"BAMS = {BAMS!r}\n" + BAD_LEVEL.replace("if not __import__", "if 1 or not __import__")
    )
    ws2 = _study(tmp_path, "ws2", seg)
    args2 = [*BAMS, "loop", "-w", str(ws2), "--simulator",
             f"{sys.executable} {always} {tmp_path / 'flag2'} {truth} {{handoff}} {{results}}",
             "--batches", "1", "--budget", "3", "--retries", "1"]  # fmt: skip
    folder2 = ws2 / "loop-results"
    stuck = subprocess.run(args2, capture_output=True, text=True)
    assert stuck.returncode == 1 and stuck.stderr.count("retry 1 of 1") == 1, stuck.stderr
    assert (folder2 / "retried-1-batch-0001.csv").exists()  # the try a retry followed
    assert f"moved to {folder2 / 'rejected-batch-0001.csv'}" in stuck.stderr  # the last
    again = subprocess.run(args2, capture_output=True, text=True)
    assert again.returncode == 1 and "retry" not in again.stderr, again.stderr
    assert f"moved to {folder2 / 'rejected-2-batch-0001.csv'}" in again.stderr
    assert len(Workspace(ws2).read_observations()) == 0


@pytest.mark.slow  # 20-40 s each: make test ran 812 s on a clean clone (budget 600)
@pytest.mark.parametrize("crashes", ["once", "always"])
def test_retries_simulate_what_has_no_result_again_then_abandon_it(data, tmp_path, crashes):
    # --retries N reruns the simulator on the requests still without a result by itself,
    # keeping each try's results file; with --abandon-failed, what still fails after the
    # last try is abandoned and the loop goes on.
    tmp, seg, truth, _, _ = data
    ws = _study(tmp_path, "ws", seg)
    sim = tmp_path / "noisy.py"
    sim.write_text(f"BAMS = {BAMS!r}\n" + NOISY)
    command = (
        f"{sys.executable} {sim} {tmp_path / 'flag'} {truth} {{handoff}} {{results}} {crashes}"
    )
    args = [*BAMS, "loop", "-w", str(ws), "--simulator", command, "--batches", "1",
            "--budget", "3", "--retries", "2"]  # fmt: skip
    if crashes == "always":
        stuck = subprocess.run(args, capture_output=True, text=True)
        assert (
            stuck.returncode == 1 and "2 requests of batch 1 still have no result" in stuck.stderr
        )
        assert stuck.stderr.count("simulating them again (retry") == 2  # then it stops
        # The list the retries simulated is not kept: it would go stale as results come in.
        assert not (ws / "loop-results" / "batch-0001.pending.csv").exists()
        # Run again as its message says, with --abandon-failed: the two retries are spent
        # (counted from the files kept), so it abandons at once, simulating nothing more.
        args.append("--abandon-failed")
    r = subprocess.run(args, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    tries = 1 if crashes == "once" else 2
    folder = ws / "loop-results"
    if crashes == "always":
        assert "retry" not in r.stderr and ": simulate" not in r.stderr, r.stderr
    else:
        assert "2 requests still without a result: simulating them again (retry 1 of 2" in r.stderr
    for t in range(1, tries + 1):
        assert (folder / f"retried-{t}-batch-0001.csv").exists()  # each try's results kept
    assert not (folder / f"retried-{tries + 1}-batch-0001.csv").exists()
    w = Workspace(ws)
    assert w.pending().height == 0
    assert len(pl.read_csv(folder / "batch-0001.csv")) == 2  # the crashed two were simulated alone
    assert not (folder / "batch-0001.pending.csv").exists()  # nothing left to simulate
    assert w.read_abandoned().height == (0 if crashes == "once" else 2)


def test_a_damaged_workspace_file_during_ingest_is_not_blamed_on_the_simulator(
    data, tmp_path, monkeypatch
):
    # Only the results file itself is set aside as the simulator's fault: an error naming
    # a workspace file leaves the (good) results where they are, for the next loop.
    from bams_cli import loop as study_loop
    from bams_cli.errors import SchemaError
    from bams_cli.loop import LoopError

    tmp, seg, truth, _, _ = data
    ws = _study(tmp_path, "ws", seg)
    damaged = SchemaError(ws / "segments.parquet", "damaged (not a Parquet file)")

    def ingest(*args, **kwargs):
        raise damaged

    monkeypatch.setattr(study_loop.pipeline, "ingest_results", ingest)
    sim = (
        f"{shlex.join(BAMS)} simulate {{handoff}} --truth {shlex.quote(str(truth))} -o {{results}}"
    )
    with pytest.raises(SchemaError) as got:
        study_loop.loop(ws, simulator=sim, batches=1, budget=3, workers=1)
    assert got.value is damaged and not isinstance(got.value, LoopError)
    assert (ws / "loop-results" / "batch-0001.csv").exists()
    assert not list((ws / "loop-results").glob("rejected-*"))


CRASH_ALL = """
import csv, subprocess, sys
handoff, results = sys.argv[1:3]
raw = results + ".raw.csv"
subprocess.run([*BAMS, "simulate", handoff, "--truth", sys.argv[3], "-o", raw], check=True)
rows = list(csv.DictReader(open(raw)))
for r in rows:
    r["value"], r["status"] = "", "crashed"
with open(results, "w", newline="") as fh:
    w = csv.DictWriter(fh, fieldnames=list(rows[0]))
    w.writeheader()
    w.writerows(rows)
"""


@pytest.mark.slow  # 20-40 s each: make test ran 812 s on a clean clone (budget 600)
def test_a_simulator_that_fails_every_run_stops_the_loop_after_one_batch(data, tmp_path):
    # With --abandon-failed, a batch whose every run failed was abandoned whole and, the
    # study still without a result, the loop drew a new random batch, for ever (42 batches
    # in a minute in a trial study).
    tmp, seg, truth, _, _ = data
    ws = _study(tmp_path, "ws", seg)
    sim = tmp_path / "crash_all.py"
    sim.write_text(f"BAMS = {BAMS!r}\n" + CRASH_ALL)
    args = [*BAMS, "loop", "-w", str(ws), "--simulator",
            f"{sys.executable} {sim} {{handoff}} {{results}} {truth}", "--batches", "2",
            "--budget", "3", "--abandon-failed"]  # fmt: skip
    r = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert r.returncode == 1, r.stderr
    assert r.stderr.strip().splitlines()[-1] == (
        "error: every request of batch 1 failed and was abandoned, and the study has no result "
        f"yet: check the simulator on {ws / 'batches' / 'batch-0001.csv'}, then run the same "
        "`bams-cli loop` again (it draws a new random batch)"
    )
    [warning] = [x for x in r.stderr.splitlines() if "abandoned (--abandon-failed)" in x]
    n = len(pl.read_csv(ws / "batches" / "batch-0001.csv"))
    assert f"batch 1: ingest-results: {n} failed requests abandoned" in warning
    assert Workspace(ws).batch_numbers() == [1]
    # The simulator fixed, the same loop goes on with a new random batch.
    real = _loop_args(ws, truth)
    args[args.index("--simulator") + 1] = real[real.index("--simulator") + 1]
    again = subprocess.run([*args, "--json"], capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert Workspace(ws).batch_numbers()[:2] == [1, 2]
    assert len(Workspace(ws).read_observations()) > 0


def test_a_results_dir_that_is_a_workspace_folder_is_refused(data, tmp_path):
    # --results-dir WS/batches: the results file batch-0001.csv was the hand-off list
    # itself, ingested as results and set aside, and the study was broken.
    tmp, seg, truth, _, _ = data
    ws = _study(tmp_path, "ws", seg)
    for folder in (ws / "batches", ws, ws / "estimates"):
        args = _loop_args(ws, truth) + ["--results-dir", str(folder)]
        r = subprocess.run(args, capture_output=True, text=True)
        assert r.returncode == 2, r.stderr
        assert f"--results-dir {folder}: is the workspace's own folder" in r.stderr
    assert Workspace(ws).batch_numbers() == []  # refused before any step


def test_a_budget_that_buys_no_run_is_refused_before_any_step(data, tmp_path):
    # --budget 0.05 with a cheapest level of 0.1: batch 1 (--first-budget) was drawn and
    # simulated, and only batch 2's select refused the budget.
    tmp, seg, truth, _, _ = data
    ws = _study(tmp_path, "ws", seg)
    before = tree_hash(ws)
    for flag in ("--budget", "--first-budget"):
        args = _loop_args(ws, truth)
        args[args.index(flag) + 1] = "0.05"
        r = subprocess.run(args, capture_output=True, text=True)
        assert r.returncode == 1, r.stderr
        assert r.stderr.strip() == f"error: {flag} 0.05: buys no run; the cheapest level costs 0.1"
    assert tree_hash(ws) == before


def test_a_results_dir_that_cannot_be_made_is_refused_before_any_step(data, tmp_path):
    # A folder under a file (as under a missing or read-only mount) got the catch-all
    # "unexpected" error, and only once the first batch had been drawn.
    tmp, seg, truth, _, _ = data
    ws = _study(tmp_path, "ws", seg)
    (tmp_path / "a-file").write_text("x")
    (tmp_path / "a-link").symlink_to(tmp_path / "nowhere" / "results")
    before = tree_hash(ws)
    for folder in (tmp_path / "a-file" / "results", tmp_path / "a-file", tmp_path / "a-link"):
        r = subprocess.run(_loop_args(ws, truth) + ["--results-dir", str(folder)],
                           capture_output=True, text=True)  # fmt: skip
        assert r.returncode == 2, r.stderr
        [line] = r.stderr.strip().splitlines()
        assert line.startswith(f"error: --results-dir {folder}:"), line
        assert "unexpected" not in line
    assert "a-link: a link to " in line and "which does not exist" in line
    assert tree_hash(ws) == before and not (tmp_path / "nowhere").exists()


def test_a_loop_refused_by_the_loop_lock_does_not_touch_its_results_dir(data, tmp_path):
    # The folder check makes (and removes) the folder to probe it: under the lock, so a
    # second loop cannot remove the folder the running one has just made.
    from bams_cli.state.lock import LOOP_LOCK_FILE, workspace_lock

    tmp, seg, truth, _, _ = data
    ws = _study(tmp_path, "ws", seg)
    (tmp_path / "a-file").write_text("x")
    with workspace_lock(ws, lock_file=LOOP_LOCK_FILE):
        r = subprocess.run(
            _loop_args(ws, truth) + ["--results-dir", str(tmp_path / "a-file" / "results")],
            capture_output=True, text=True,
        )  # fmt: skip
    assert r.returncode == 1, r.stderr
    [line] = r.stderr.strip().splitlines()
    assert "another `bams-cli loop` runs here" in line, line


@pytest.mark.slow  # 20-40 s each: make test ran 812 s on a clean clone (budget 600)
def test_a_results_file_older_than_its_hand_off_list_is_refused_and_left_alone(data, tmp_path):
    # A --results-dir kept from an earlier study (or shared): the new study, drawn from the
    # same seed, ingested the old study's results as its own without running its simulator.
    tmp, seg, truth, _, _ = data
    shared = tmp_path / "results"
    first = _study(tmp_path, "first", seg)
    full = _loop_args(first, truth)
    sim = full[full.index("--simulator") + 1]
    args = [*BAMS, "loop", "-w", str(first), "--simulator", sim, "--batches", "1",
            "--budget", "2", "--results-dir", str(shared)]  # fmt: skip
    assert subprocess.run(args, capture_output=True, text=True).returncode == 0
    old = shared / "batch-0001.csv"
    an_hour_ago = time.time() - 3600
    os.utime(old, (an_hour_ago, an_hour_ago))  # the earlier study's
    before = old.read_bytes()
    second = _study(tmp_path, "second", seg)  # the same settings and seed: the same batch
    args[args.index("-w") + 1] = str(second)
    r = subprocess.run(args, capture_output=True, text=True)
    assert r.returncode == 1, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith(
        f"error: {old}: older than the hand-off list it would answer "
        f"({second / 'batches' / 'batch-0001.csv'}), so not written for it"
    ), last
    assert old.read_bytes() == before  # left where it is, as it was
    assert len(Workspace(second).read_observations()) == 0
    os.utime(old)  # `touch`: taken as this study's results
    again = subprocess.run([*args, "--json"], capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    steps = [(s["step"], s["list"]) for s in json.loads(again.stdout)["steps"]]
    assert steps[0] == ("ingest-results", "batch 1")


def test_the_simulator_command_quotes_the_paths_unless_the_user_did():
    # A quoted placeholder got a quoted path inside the user's quotes: with a space in the
    # workspace's path the simulator was handed part of it.
    from bams_cli.loop import fill_simulator

    h, r = Path("/tmp/my study/batches/batch-0001.csv"), Path("/tmp/out dir/batch-0001.csv")
    plain = fill_simulator("sim {handoff} -o {results}", h, r)
    assert shlex.split(plain) == ["sim", str(h), "-o", str(r)]
    quoted = fill_simulator("sim '{handoff}' -o \"{results}\"", h, r)
    assert shlex.split(quoted) == ["sim", str(h), "-o", str(r)]
    inline = fill_simulator('python -c \'run("{handoff}", "{results}")\'', h, r)
    assert shlex.split(inline) == ["python", "-c", f'run("{h}", "{r}")']
    # Other braces (R or Python code in the command) are left as they are.
    assert fill_simulator("sim {handoff} {results} --opt {x}", h, r).endswith(" --opt {x}")


def test_a_kept_model_s_warnings_about_the_settings_reach_the_loop(tmp_path, monkeypatch):
    # fit's no-op re-run repeats none of its stored warnings, but what it says of the
    # settings as they are now (an edited embedding_dim not applied) is new: the loop says it.
    from bams_cli import loop, pipeline

    kept = {"up_to_date": True, "warnings": ["old", "now"], "settings_warnings": ["now"]}
    monkeypatch.setattr(pipeline, "fit", lambda root, wait: kept)
    said: list[str] = []
    ws = Workspace(tmp_path)
    opts = loop.Options(
        simulator="true", batches=1, budget=1.0, first_budget=1.0, then_estimate=False,
        samples=None, results_dir=tmp_path, abandon_failed=False, retries=0, clusters=1,
        workers=None, wait=False,
    )  # fmt: skip
    record = loop._run(ws, opts, "fit", None, None, set(), on_warning=said.append)
    assert record["up_to_date"] is True and said == ["fit: now"]
    kept = {"warnings": ["fresh"]}  # a fit that did the work: all its warnings
    said.clear()
    loop._run(ws, opts, "fit", None, None, set(), on_warning=said.append)
    assert said == ["fit: fresh"]
