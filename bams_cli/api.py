"""The Python API: every ``bams-cli`` command as a function, for notebooks and scripts.

Each function is the one the command calls, with the same parameters (a flag
``--level0-share`` is the keyword ``level0_share``, ``--workspace``/``-w`` is the first
argument ``root``) and the same defaults, defined once. Each returns the summary dict the
command prints under ``--json`` (without its ``schema_version``); ``help(api.select)``
lists the parameters and the summary's keys.

- ``init``: ``bams-cli init``, create a workspace and its settings file;
- ``embed_reduce``: ``bams-cli embed-reduce``, reduce embeddings into the pool;
- ``select``: ``bams-cli select``, pick the next batch and write its hand-off list;
- ``ingest_results``: ``bams-cli ingest-results``, append results to the observation log
  (``ingest_results_abandoning_failed``: with ``--abandon-failed``);
- ``fit``: ``bams-cli fit``, fit the multifidelity GP and score the pool;
- ``estimate_plan``: ``bams-cli estimate --plan``, draw one stage's importance sample;
- ``estimate_compute``: ``bams-cli estimate``, the rate estimate from an ingested plan;
- ``report``: ``bams-cli report``, report.html, summary.json and summary.md;
- ``status``: ``bams-cli status``, where the study stands and what to run next;
- ``abandon``: ``bams-cli abandon``, record requests that will never come back;
- ``loop``: ``bams-cli loop``, fit, select, simulate and ingest until done;
- ``simulate``: ``bams-cli simulate``, sample data only: answer a hand-off list from
  ground truth.

Errors are those of the CLI: a problem the user can fix raises a subclass of
``BamsError`` (``InputError``, ``WorkspaceError``, ``PendingResultsError`` ...) whose
message is the one line the command prints and whose ``exit_code`` is the command's (1;
3 for ``PendingResultsError``, picks awaiting results). A message names the flag that
fixes it (``--restarts 0 ...``): the keyword of the same name (``restarts``). ``status``
raises nothing for a study that waits on results: its summary's ``exit_code`` says 3.

Writes are atomic: a function stages its files and renames them into place at the end,
so one that raises (or is interrupted) leaves the workspace as it was. Every function
that touches a workspace, except ``status`` (which only reads), holds the workspace lock
from its first read to its commit; while another command or notebook holds it the call
raises ``WorkspaceLockedError`` at once, and ``wait=True`` blocks until the lock is free.

``--max-memory`` is a context manager in the API: ``with memory.ceiling(8 * 2**30,
"select"): api.select(ws)`` plans ``select``'s clusters (and ``fit``'s conditioning) within
8 GiB and stops the call with ``MemoryCeilingError`` when the notebook's process tree
goes over it (``from bams_cli import memory``). Without it the functions plan within
``defaults.MAX_MEMORY_FRACTION`` of the machine's RAM and nothing watches.

Functions taking ``progress`` (``embed_reduce``, ``fit``, ``select``,
``estimate_compute``) call it as ``progress(phase, done, total)``; ``loop`` takes
``on_step(description, done, total)``.

Example: a study on the toy2d sample data, its first batch random at both fidelities::

    from pathlib import Path
    from bams_cli import api

    ws, data = Path("study"), Path("sample_data/toy2d")
    truth = data / "truth.parquet"  # sample data only: stands in for a simulator
    api.init(ws, gammas=[0.56], costs=[1, 0.1], seed=0)
    segments = data / "segments.parquet"  # segment_id, x0, x1: a 2-d embedding
    api.embed_reduce(ws, segments, columns="x*", method="identity", standardize=False)
    batch = api.select(ws, strategy="random", mixed_fidelity=True, budget=8)
    for b in (1, 2, 3):
        if b > 1:
            api.fit(ws)
            batch = api.select(ws, budget=5)
        results = Path(f"results-{b}.csv")
        api.simulate(Path(batch["handoff_csv"]), truth, results)
        api.ingest_results(ws, results)
    api.fit(ws)
    plan = api.estimate_plan(ws, samples=100, stages=1, screen="off")  # one stage, no screen
    api.simulate(Path(plan["handoff"]), truth, Path("results-estimate.csv"))
    api.ingest_results(ws, Path("results-estimate.csv"))
    estimate = api.estimate_compute(ws)
    print(estimate["estimates"][0])  # p_hat, se, ci_low, ci_high ... for the first gamma
    api.report(ws, truth=truth)

    try:
        api.fit(ws, restarts=0)
    except api.BamsError as exc:  # what the CLI prints, and its exit code
        print(exc, exc.exit_code)
"""

from __future__ import annotations

from bams_cli.abandon import abandon, ingest_results_abandoning_failed
from bams_cli.errors import (
    AbandonedRunsError,
    BamsError,
    ConflictError,
    DuplicateError,
    InputError,
    OptionError,
    OptionValueError,
    PendingResultsError,
    SchemaError,
    SettingsError,
    StaleStateError,
    WorkspaceError,
    WorkspaceLockedError,
)
from bams_cli.loop import LoopError, loop
from bams_cli.pipeline import (
    embed_reduce,
    estimate_compute,
    estimate_plan,
    fit,
    ingest_results,
    init,
    report,
    select,
    simulate,
)
from bams_cli.status import status

__all__ = [
    "AbandonedRunsError",
    "BamsError",
    "ConflictError",
    "DuplicateError",
    "InputError",
    "LoopError",
    "OptionError",
    "OptionValueError",
    "PendingResultsError",
    "SchemaError",
    "SettingsError",
    "StaleStateError",
    "WorkspaceError",
    "WorkspaceLockedError",
    "abandon",
    "embed_reduce",
    "estimate_compute",
    "estimate_plan",
    "fit",
    "ingest_results",
    "ingest_results_abandoning_failed",
    "init",
    "loop",
    "report",
    "select",
    "simulate",
    "status",
]
