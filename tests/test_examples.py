"""examples/Makefile drives a whole study the way a team's Makefile would: through a
simulation that fails, a re-run that resumes, and a finished study that is up to date."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import polars as pl
import pytest

from bams_cli.settings import Settings, levels_from_costs
from tests.conftest import write_toy

ROOT = Path(__file__).resolve().parent.parent
BAMS = str(Path(sys.executable).with_name("bams-cli"))

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")


def _make(tmp: Path, *extra: str, check: bool = True) -> subprocess.CompletedProcess:
    args = [
        "make", "-f", str(ROOT / "examples" / "Makefile"), f"BAMS={BAMS}",
        f"DATA={tmp / 'data'}", f"WS={tmp / 'study'}", "SAMPLES=30", *extra,
    ]  # fmt: skip
    r = subprocess.run(args, cwd=tmp, capture_output=True, text=True)
    if check:
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return r


def _toy_data(tmp: Path) -> None:
    """400 toy2d segments in tmp/data, with two levels (costs 1 and 0.1) and gamma 0.56."""
    write_toy(tmp / "data", n=400)
    settings = Settings(
        gammas=(0.56,), levels=levels_from_costs([1.0, 0.1]), seed=0, embedding_dim=2
    )
    (tmp / "data" / "settings.toml").write_text(settings.to_toml())


@pytest.mark.slow  # a whole study through make, four times: about a minute and a half
def test_the_example_makefile_runs_resumes_and_is_then_up_to_date(tmp_path):
    _toy_data(tmp_path)

    # The simulation team fails on batch 2: make stops there, nothing half-done.
    failing = "SIMULATE=$(if $(findstring batch-0002,$(1)),false,$(BAMS) simulate $(1) "
    failing += "--truth $(DATA)/truth.parquet -o $(2))"
    r = _make(tmp_path, failing, check=False)
    assert r.returncode != 0
    study = tmp_path / "study"
    assert (study / "batches" / "batch-0002.parquet").exists()
    assert not (study / "batches" / "batch-0003.parquet").exists()
    status = subprocess.run(
        [BAMS, "status", "-w", str(study), "--json"], capture_output=True, text=True
    )
    assert status.returncode == 3  # waiting on results
    assert json.loads(status.stdout)["next"]["step"] == "ingest-results"

    # The next run resumes at batch 2's simulation and finishes the study.
    r = _make(tmp_path)
    assert "select -w" in r.stdout and "--batch 1" not in r.stdout  # batch 1 not redone
    assert "--batch 3" in r.stdout
    doc = json.loads((study / "estimates" / "estimate-0002.json").read_text())
    assert doc["estimates"][0]["p_hat"] >= 0
    assert doc["design"] == "staged" and doc["staging"]["plans"] == [1, 2]
    # Every stage it planned: the estimate is whole, not "stage 2 of 3 only".
    assert doc["staging"]["stages_done"] == doc["staging"]["stages"] == 2
    assert (study / "report" / "summary.md").exists()

    # Finished: nothing to do, and every target is up to date.
    r = _make(tmp_path)
    assert "Nothing to be done" in r.stdout
    assert _make(tmp_path, "-q", check=False).returncode == 0

    # A lost report is rebuilt alone (fit is a no-op on an unchanged log).
    (study / "report" / "summary.md").unlink()
    r = _make(tmp_path)
    assert "report -w" in r.stdout and "select -w" not in r.stdout
    assert "up to date" in r.stdout


CRASHY = """
import subprocess, sys
import polars as pl
bams, handoff, out, truth, log = sys.argv[1:6]
with open(log, "a") as fh:
    fh.write(handoff + "\\n")
asked = open(log).read().split()
raw = out + ".raw.parquet"
subprocess.run([bams, "simulate", handoff, "--truth", truth, "-o", raw], check=True)
df = pl.read_parquet(raw).with_columns(pl.lit("ok").alias("status"))
# Batch 2's first two runs crash when asked for the first and the second time.
if "batch-0002" in handoff and sum("batch-0002" in a for a in asked) <= 2:
    first = pl.int_range(pl.len()) < 2
    df = df.with_columns(
        pl.when(first).then(pl.lit("crashed")).otherwise(pl.col("status")).alias("status"),
        pl.when(first).then(None).otherwise(pl.col("value")).alias("value"),
    )
df.write_parquet(out)
"""


@pytest.mark.slow  # a whole study through make, with retries: about a minute
def test_runs_that_crash_are_simulated_again_alone_and_make_goes_on_after_a_hand_fix(tmp_path):
    # Two runs of batch 2 crash: ingest keeps their requests pending and lists them alone;
    # make's ingest step simulates that list (they crash again) and stops, with status
    # naming the list. The user simulates and ingests it by hand; the next make asks for
    # nothing more of batch 2 and finishes the study.
    _toy_data(tmp_path)
    (tmp_path / "crashy.py").write_text(CRASHY)
    log = tmp_path / "asked.txt"
    sim = (
        f"SIMULATE={sys.executable} {tmp_path / 'crashy.py'} {BAMS} $(1) $(2) "
        f"$(DATA)/truth.parquet {log}"
    )
    r = _make(tmp_path, sim, check=False)
    assert r.returncode != 0 and "runs still pending" in r.stdout
    study = tmp_path / "study"
    whole = study / "batches" / "batch-0002.csv"
    pending = study / "batches" / "batch-0002.pending.csv"
    assert log.read_text().split() == [
        str(study / "batches" / "batch-0001.csv"), str(whole), str(pending)
    ]  # fmt: skip
    assert len(pending.read_text().strip().splitlines()) == 1 + 2
    assert not (tmp_path / "study-sim" / "ingested-0002").exists()
    status = subprocess.run(
        [BAMS, "status", "-w", str(study), "--json"], capture_output=True, text=True
    )
    assert status.returncode == 3 and str(pending) in status.stdout

    by_hand = tmp_path / "by-hand.parquet"
    for args in (
        ["simulate", str(pending), "--truth", str(tmp_path / "data" / "truth.parquet"),
         "-o", str(by_hand)],
        ["ingest-results", "-w", str(study), str(by_hand)],
    ):  # fmt: skip
        assert subprocess.run([BAMS, *args], capture_output=True).returncode == 0
    assert not pending.exists()

    _make(tmp_path, sim)
    asked = log.read_text().split()
    assert asked.count(str(whole)) == 1 and asked.count(str(pending)) == 1
    assert (study / "report" / "summary.md").exists()
    assert _make(tmp_path, sim, "-q", check=False).returncode == 0


BROKEN = """
import subprocess, sys
from pathlib import Path
bams, handoff, out, truth, log = sys.argv[1:6]
with open(log, "a") as fh:
    fh.write(handoff + "\\n")
n = sum("batch-0002" in a for a in open(log).read().split())
if "batch-0002" in handoff and n == 1:  # writes half a file, then fails
    Path(out).write_bytes(b"PAR1 half")
    sys.exit(1)
if "batch-0002" in handoff and n == 2:  # succeeds, with a file cut short
    Path(out).write_bytes(b"PAR1 cut short")
    sys.exit(0)
subprocess.run([bams, "simulate", handoff, "--truth", truth, "-o", out], check=True)
"""


@pytest.mark.slow  # a whole study through make, three times: about a minute
def test_a_failed_or_malformed_simulation_is_simulated_again_by_the_next_make(tmp_path):
    # A simulator that fails after writing part of its file leaves nothing make would take
    # for done (.DELETE_ON_ERROR); a results file ingest-results refuses is set aside, so
    # the next make simulates the list again instead of failing on that file for ever.
    _toy_data(tmp_path)
    (tmp_path / "broken.py").write_text(BROKEN)
    sim = (
        f"SIMULATE={sys.executable} {tmp_path / 'broken.py'} {BAMS} $(1) $(2) "
        f"$(DATA)/truth.parquet {tmp_path / 'asked.log'}"
    )
    # Spelled with a double slash, which the error names normalised: set aside all the same.
    sim = [sim, f"SIM={tmp_path}//study-sim"]
    results = tmp_path / "study-sim" / "results-0002.parquet"
    r = _make(tmp_path, *sim, check=False)
    assert r.returncode != 0 and not results.exists()  # the half-written file is gone
    r = _make(tmp_path, *sim, check=False)
    assert r.returncode != 0 and not results.exists()
    [rejected] = (tmp_path / "study-sim").glob("rejected-*-results-0002.parquet")
    assert rejected.read_bytes() == b"PAR1 cut short"  # kept for the user to read
    assert "set aside as rejected" in r.stderr
    # A value that conflicts with one logged is not the file's fault: it stays, make stops.
    conflict = tmp_path / "study-sim" / "results-0001.parquet"
    saved = conflict.read_bytes()
    t = pl.read_parquet(conflict)
    t.with_columns(pl.col("value") + 1.0).write_parquet(conflict)
    (tmp_path / "study-sim" / "ingested-0001").unlink()
    r = _make(tmp_path, *sim, check=False)
    assert r.returncode != 0 and "is already known as" in r.stderr and conflict.exists()
    assert "set aside" not in r.stderr
    conflict.write_bytes(saved)  # put right by hand: make goes on
    _make(tmp_path, *sim)  # batch 2 simulated a third time, and the study finishes
    assert (tmp_path / "study" / "report" / "summary.md").exists()
    assert open(tmp_path / "asked.log").read().count("batch-0002") == 3
