"""``bams-cli status``: where a study stands and the one command to run next.

Pure reading: batches and estimate plans with the picks still awaiting results, whether the
model was fitted on the current observation log, the latest estimate. It takes no lock and
writes nothing, so it runs beside any other command; run during another command's commit,
it shows the state just before or just after it.

The next step follows the loop: a pool (``embed-reduce``), a first batch
(``Workspace.first_batch_command``: random, at every level), its results
(``ingest-results``), a model of them (``fit``), the next batch (``select``) ... Once an
estimate plan is newer than the newest batch the study is estimating: results for the plan,
``estimate``, a ``fit`` that includes them, ``report``; then nothing is left to do.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import re
import shlex
import sys
from pathlib import Path
from typing import Any

import polars as pl

from bams_cli import defaults
from bams_cli.errors import EXIT_OK, EXIT_PENDING, SchemaError, StaleStateError
from bams_cli.settings import Settings
from bams_cli.stages import estimate_again, plan_numbers
from bams_cli.state import schemas
from bams_cli.state.handoff import handoff_path
from bams_cli.state.io import JOURNAL_NAME, read_metadata, read_metadata_json, recovered_note
from bams_cli.state.pending import to_simulate
from bams_cli.state.workspace import Workspace, stale_log

#: Version of the ``status --json`` object; bump it when a key changes meaning or goes away.
STATUS_SCHEMA_VERSION = 1

SID = schemas.SEGMENT_ID


def batch_handoff(ws: Workspace, n: int) -> Path:
    """The CSV hand-off list of batch ``n``."""
    return handoff_path(ws.root, "batch", n)


def plan_handoff(ws: Workspace, k: int) -> Path:
    """The CSV hand-off list of estimate plan ``k``."""
    return handoff_path(ws.root, "plan", k)


def pending_handoffs(ws: Workspace, pending: pl.DataFrame) -> list[str]:
    """The lists to simulate for the picks ``Workspace.pending()`` lists, batches first:
    each hand-off list, or the list of its pending requests alone where some have results
    (``state.pending.to_simulate``)."""
    batches = sorted(set(pending["batch"].drop_nulls().to_list()))
    plans = sorted(set(pending["plan"].drop_nulls().to_list()))
    return [str(to_simulate(ws, "batch", b)) for b in batches] + [
        str(to_simulate(ws, "plan", k)) for k in plans
    ]


def status(root: Path) -> dict[str, Any]:
    """Where the study in ``root`` stands, and the next command (``next``) to run.

    ``exit_code`` is 3 (waiting on results) when a batch or plan has picks without
    results, else 0. Reads only, and takes no lock (so it has no ``wait``), except to
    complete a commit a killed command left half done, as every writing command does first
    (``finished_interrupted_commit``: the files it renamed into place).

    Parameters
    ----------
    root : Path
        The workspace folder (``--workspace``/``-w``).

    Returns
    -------
    dict
        The summary ``--json`` prints: ``workspace``, ``gammas``, ``levels``,
        ``pool_size``, ``observations``, ``observations_per_level``, ``batches``,
        ``plans``, ``pending``, ``model``, ``estimates``, ``phase`` ("setup": no pool yet,
        "discovery", "estimate": an estimate plan is newer than the newest batch, "done"),
        ``next`` (``step``, ``command``, ``text``, ``alternatives``: the other commands the
        text names, each ``step`` and ``command``) and ``exit_code``.

    Raises
    ------
    WorkspaceError
        No workspace at ``root``.
    """
    ws = Workspace(Path(root))
    settings = ws.require_initialised()
    finished = _finish_interrupted_commit(ws.root)
    if finished:
        sys.stderr.write(recovered_note(root, finished))
    has_pool = ws.segments_path.exists()
    obs = ws.read_observations()
    observed = obs.select(SID, "fidelity").unique()
    batches = _batches(ws, observed)
    plans = _plans(ws, observed)
    model = _model(ws, obs) if has_pool else None
    latest = latest_estimate(ws)
    estimating = _estimating(ws, plans, batches)
    step = _next_step(
        ws, settings, has_pool, batches, plans, model, estimating, has_results=obs.height > 0,
        out_of_date=bool(latest and latest["out_of_date"]),
    )  # fmt: skip
    waiting = step["step"] == "ingest-results"
    if not has_pool:
        phase = "setup"
    elif step["step"] == "done":
        phase = "done"
    else:
        phase = "estimate" if estimating else "discovery"
    return {
        "schema_version": STATUS_SCHEMA_VERSION,
        "workspace": str(ws.root),
        "gammas": list(settings.gammas),
        "levels": [lv.name for lv in settings.levels],
        "pool_size": ws.read_segments([SID]).num_rows if has_pool else None,
        "observations": obs.height,
        "observations_per_level": [
            int((obs["fidelity"] == lv).sum()) for lv in range(settings.n_levels)
        ],
        "batches": batches,
        "plans": plans,
        "pending": sum(b["pending"] for b in batches) + sum(p["pending"] for p in plans),
        "abandoned": sum(b["abandoned"] for b in batches) + sum(p["abandoned"] for p in plans),
        "model": model,
        "latest_estimate": latest,
        "commit_in_progress": (ws.root / JOURNAL_NAME).exists(),
        "finished_interrupted_commit": finished,
        "waiting_on_results": waiting,
        "phase": phase,
        "next": step,
        "exit_code": EXIT_PENDING if waiting else EXIT_OK,
    }


def _finish_interrupted_commit(root: Path) -> int:
    """Complete a commit a killed command left half done, as the next writing command would,
    so that the state reported is the one that command had committed to; returns the files
    renamed into place. Nothing at all without a journal (status takes no lock then); with
    one whose command is still running (the lock is held), nothing: ``commit_in_progress``
    says so. Before, status reported the state before the commit, and named the killed
    command (``select``) as the next step though its batch was already decided."""
    from bams_cli.errors import WorkspaceLockedError
    from bams_cli.state.io import journal_in, recover
    from bams_cli.state.lock import held_by_a_live_command, workspace_lock

    # The holder first, then the journal: a command that finished its commit removed its
    # journal before letting go, so a journal seen after a dead or absent holder is left
    # over (a live command's commit is never touched, and no lock is taken for nothing).
    if held_by_a_live_command(root) or not (root / JOURNAL_NAME).exists():
        return 0
    try:
        with workspace_lock(root, wait=False), journal_in(root):
            return recover(root)
    except (WorkspaceLockedError, OSError):
        # Taken meanwhile, or a workspace this user cannot write (a colleague's, a
        # read-only mount): reported as it stands, commit_in_progress true.
        return 0


def _batches(ws: Workspace, observed: pl.DataFrame) -> list[dict[str, Any]]:
    out = []
    for n in ws.batch_numbers():
        df = ws.read_batch(n)
        gone = ws.abandoned_open("batch", n)
        open_ = df.join(observed, on=[SID, "fidelity"], how="anti")
        pending = open_.join(gone, on=[SID, "fidelity"], how="anti").height
        meta = read_metadata(schemas.batch_path(ws.root, n))
        options = _json(meta.get("options"))
        # Partly answered: the list of the pending requests alone, while it is current.
        simulate = to_simulate(ws, "batch", n) if 0 < pending < df.height else None
        out.append(
            {
                "batch": n,
                "strategy": df["strategy"][0] if df.height else None,
                "picks": df.height,
                "cost": math.fsum(df["cost"].to_list()),  # 200 x 0.1 is 20, not 19.999999999999986
                "budget": options.get("budget") if isinstance(options, dict) else None,
                "pending": pending,
                "abandoned": gone.height,
                "handoff": str(batch_handoff(ws, n)),
                "pending_handoff": _pending_list(simulate, batch_handoff(ws, n)),
                "written_at": meta.get("written_at"),
            }
        )
    return out


def _plans(ws: Workspace, observed: pl.DataFrame) -> list[dict[str, Any]]:
    picks = ws.read_plan_picks()
    level0 = observed.filter(pl.col("fidelity") == 0).select(SID)
    out = []
    for k in plan_numbers(ws):
        sampled = picks.filter(pl.col("plan") == k).select(SID)
        gone = ws.abandoned_open("plan", k).select(SID)
        estimate = ws.estimates_dir / f"estimate-{k:04d}.json"
        try:
            meta = read_metadata_json(ws.estimates_dir / f"plan-{k:04d}.parquet")
        except (OSError, ValueError):  # status reads what it can: a damaged plan shows as 1 of 1
            meta = {}
        pending = sampled.join(level0, on=SID, how="anti").join(gone, on=SID, how="anti").height
        simulate = to_simulate(ws, "plan", k) if 0 < pending < sampled.height else None
        out.append(
            {
                "plan": k,
                "stage": int(meta.get("stage") or 1),
                "stages": int(meta.get("stages") or 1),
                "sampled": sampled.height,
                "pending": pending,
                "abandoned": gone.height,
                "handoff": str(plan_handoff(ws, k)),
                "pending_handoff": _pending_list(simulate, plan_handoff(ws, k)),
                "estimate": str(estimate) if estimate.exists() else None,
                "written_at": meta.get("written_at"),
            }
        )
    return out


def _pending_list(simulate: Path | None, handoff: Path) -> str | None:
    """The pending-only list to name, or None: not partly answered, or no current list."""
    return None if simulate is None or simulate == handoff else str(simulate)


def _model(ws: Workspace, obs: pl.DataFrame) -> dict[str, Any] | None:
    """Whether ``model.json`` was fitted on the current log and pool, as ``select`` decides."""
    if not ws.model_path.exists():
        return None
    try:
        model = ws.require_model(allow_newer_observations=True)
    except (StaleStateError, SchemaError) as exc:  # damaged, another pool, scores of another fit
        # The error's own "run `bams-cli fit`" goes: ``next`` names the command once.
        reason = re.sub(r"[;:] run `bams-cli fit -w [^`]*`( to write it again)?$", "", str(exc))
        return {"fresh": False, "fitted_on": None, "fitted_at": None, "reason": reason}
    fitted = int(sum(model.get("n_observations_per_level", [])))
    return {
        "fresh": bool(model["fresh"]),
        "fitted_on": fitted,
        "fitted_at": model.get("fitted_at"),
        "reason": None if model["fresh"] else stale_log(fitted, obs.height),
    }


def _estimate_out_of_date(ws: Workspace, k: int, doc: dict[str, Any]) -> bool:
    """``Workspace.estimate_out_of_date``, False where the file cannot be read (status
    reads what it can; ``report`` names a damaged file)."""
    try:
        return ws.estimate_out_of_date(k, doc)
    except (StaleStateError, SchemaError, OSError, ValueError, TypeError, KeyError):
        return False


def latest_estimate(ws: Workspace) -> dict[str, Any] | None:
    """The newest estimate file's headline (``status --json`` ``latest_estimate``, ``loop
    --json`` ``estimate``): ``plan``, ``file``, ``stages_done``, ``stages`` and per gamma
    ``gamma``, ``p_hat``, ``se``, ``ci_low``, ``ci_high``, ``confidence`` (and
    ``p_hat_low``, ``p_hat_high`` under ``--failed-as bounds``); None before any."""
    files = sorted(ws.estimates_dir.glob("estimate-[0-9][0-9][0-9][0-9].json"))
    if not files:
        return None
    path = files[-1]
    doc = ws.read_estimate(int(path.stem[len("estimate-") :]))
    keys = ("gamma", "p_hat", "se", "ci_low", "ci_high", "confidence")
    # Under --failed-as bounds p_hat is the all-failing end of a range (p_hat_low to
    # p_hat_high), not a rate: the range goes with it. A staged estimate says how many of
    # its stages it rests on.
    ranged = ("p_hat_low", "p_hat_high")
    staging = doc.get("staging") or {}
    return {
        "plan": doc.get("plan"),
        "file": str(path),
        "stages_done": staging.get("stages_done", 1),
        "stages": staging.get("stages", 1),
        # An outcome it read changed since (``Workspace.estimate_out_of_date``).
        "out_of_date": _estimate_out_of_date(ws, int(path.stem[len("estimate-") :]), doc),
        "estimates": [
            {k: e.get(k) for k in keys} | {k: e[k] for k in ranged if e.get(k) is not None}
            for e in doc["estimates"]
        ],
    }


def _estimating(ws: Workspace, plans: list[dict[str, Any]], batches: list[dict[str, Any]]) -> bool:
    """Whether the study is estimating: an estimate plan is newer than the newest batch.

    By the times the files record (``written_at``), which a copy keeps: a workspace
    copied with ``cp -r`` or restored from a CI artifact has every file's modification
    time reset, and status then took a finished estimate for discovery. Files of an older
    bams-cli without the record are ordered by modification time, as before."""
    if not plans:
        return False
    plan_at, batch_at = _written(plans), _written(batches)
    if plan_at is not None and batch_at is not None:
        last_plan, last_batch = max(plan_at, default=_EPOCH), max(batch_at, default=_EPOCH)
        # Equal records (an older bams-cli's, to the second, in one loop's second) say
        # nothing of which came last: the modification times, to the nanosecond, do.
        if last_plan != last_batch:
            return last_plan > last_batch
    return _newest(ws, "estimates/plan-*.parquet") >= _newest(ws, "batches/batch-*.parquet")


_EPOCH = dt.datetime.min.replace(tzinfo=dt.UTC)


def _written(lists: list[dict[str, Any]]) -> list[dt.datetime] | None:
    """Each batch's or plan's recorded ``written_at`` (``_batches``, ``_plans``); None if
    any lacks it, or it is not a time with a zone (not one this tool wrote)."""
    out = []
    for entry in lists:
        at = entry.get("written_at")
        try:
            when = dt.datetime.fromisoformat(at) if isinstance(at, str) else None
        except ValueError:
            return None
        if when is None or when.tzinfo is None:
            return None
        out.append(when)
    return out


def _next_step(
    ws: Workspace,
    settings: Settings,
    has_pool: bool,
    batches: list[dict[str, Any]],
    plans: list[dict[str, Any]],
    model: dict[str, Any] | None,
    estimating: bool,
    has_results: bool = True,
    out_of_date: bool = False,
) -> dict[str, Any]:
    """The step the loop needs next: ``step`` (a command name, or "done"), the exact
    ``command``, ``text`` saying why, for a person, and ``alternatives``, the other
    commands that text names. ``out_of_date``: the newest estimate (``latest_estimate``)
    read outcomes the log no longer holds."""
    w = shlex.quote(str(ws.root))
    new_plan = {"step": "estimate", "command": f"bams-cli estimate -w {w} --plan"}

    def step(
        name: str,
        command: str | None,
        text: str,
        alternatives: tuple[dict[str, str], ...] = (),
        **extra: Any,
    ) -> dict[str, Any]:
        return {
            "step": name,
            "command": command,
            "text": text,
            "alternatives": list(alternatives),
            **extra,
        }

    if not has_pool:
        cmd = f"bams-cli embed-reduce -w {w} SEGMENTS.parquet"
        return step("embed-reduce", cmd, f"no segment pool yet: run `{cmd}`")
    lists = [b for b in batches if b["pending"]] + [p for p in plans if p["pending"]]
    if lists:
        # A list partly answered is simulated from its pending requests alone: the whole
        # list again would ask a noisy simulator for values the log holds, and ingesting
        # those would be refused as conflicts.
        waiting = [e["pending_handoff"] or e["handoff"] for e in lists]
        cmd = f"bams-cli ingest-results -w {w} RESULTS.parquet"
        n = sum(b["pending"] for b in batches) + sum(p["pending"] for p in plans)
        # A list partly answered may hold runs that will never come back (a simulator that
        # fails for good): abandoning them lets the study go on. A list with no result yet
        # is simply waiting for its simulation.
        gone = tuple(
            {
                "step": "abandon",
                "command": f"bams-cli abandon -w {w} "
                + (f"--batch {e['batch']}" if "batch" in e else f"--plan {e['plan']}")
                + " --reason WHY",
            }
            for e in lists
            if e["pending"] < _requests(e)
        )
        return step(
            "ingest-results",
            cmd,
            f"{n} {'pick awaits' if n == 1 else 'picks await'} results: simulate "
            f"{' and '.join(map(_to_simulate, lists))} and run `{cmd}` (RESULTS.parquet: "
            "the results file, Parquet or CSV)"
            + (f"; runs that can never be simulated: `{gone[0]['command']}`" if gone else ""),
            gone,
            handoffs=waiting,
        )
    fit = f"bams-cli fit -w {w}"
    stale = model is None or not model["fresh"]
    why_fit = "no model yet" if model is None else f"the model is stale: {model['reason']}"
    if not batches and not plans or not has_results:
        # No result at all and none awaited (every request of the batches so far was
        # abandoned): nothing to fit, so a new random batch, as at the start. "run fit"
        # here sent a study whose first batch was lost round in a circle.
        cmd = ws.first_batch_command()
        why = "no batch yet" if not batches and not plans else "no result yet (none awaited)"
        return step("select", cmd, f"{why}: run `{cmd}` for a random first batch")
    screen_for = (plans[-1]["plan"] if plans else 0) + 1
    if (ws.root / schemas.SCREEN.relpath.format(n=screen_for)).exists():
        # A screened estimate (`estimate --plan --screen`) whose screen has its results:
        # the confirmation is drawn from the model refitted on them.
        if stale:
            return step(
                "fit", fit, f"{why_fit}; run `{fit}` before the screen's level-0 confirmation"
            )
        cmd = f"bams-cli estimate -w {w} --plan"
        return step(
            "estimate",
            cmd,
            f"the screen for estimate plan {screen_for} has its results: run `{cmd}` to draw "
            "the level-0 confirmation within it",
        )
    if estimating:
        k = plans[-1]["plan"]
        if plans[-1]["estimate"] is None and plans[-1]["abandoned"]:
            cmd = f"bams-cli estimate -w {w} --failed-as bounds"
            return step(
                "estimate",
                cmd,
                f"estimate plan {k} has its results but {plans[-1]['abandoned']} of its "
                f"segments were abandoned: run `{cmd}` for the worst-case interval over them, "
                "or simulate them again and ingest the results",
            )
        stage, stages = plans[-1]["stage"], plans[-1]["stages"]
        if stage < stages:
            # A staged estimate: the next stage is drawn from the model refitted on this
            # stage's results (``core.design``).
            if stale:
                return step(
                    "fit", fit, f"{why_fit}; run `{fit}` before stage {stage + 1} of the estimate"
                )
            cmd = f"bams-cli estimate -w {w} --plan"
            return step(
                "estimate",
                cmd,
                f"stage {stage} of {stages} of the estimate has its results: run `{cmd}` "
                f"for stage {stage + 1}",
            )
        if plans[-1]["estimate"] is None:
            cmd = f"bams-cli estimate -w {w}"
            return step("estimate", cmd, f"estimate plan {k} has all its results: run `{cmd}`")
        if out_of_date:  # the newest estimate is plan k's, the latest plan's
            cmd = estimate_again(ws, k)
            return step(
                "estimate",
                cmd,
                f"plan {k}'s estimate is out of date: results it rests on changed since it "
                "was computed (a result corrected across a gamma, or an abandoned run "
                f"simulated after all); run `{cmd}` again (the earlier one is kept)",
            )
        if stale:
            return step("fit", fit, f"{why_fit}; run `{fit}` so the report shows the current model")
        report = ws.report_dir / "summary.json"
        current = _report_current(ws, Path(plans[-1]["estimate"]))
        if current is None:  # a report or model of an older bams-cli: by modification time
            current = _mtime(report) >= max(
                _mtime(Path(plans[-1]["estimate"])), _mtime(ws.model_path)
            )
        if not current:
            cmd = f"bams-cli report -w {w}"
            return step("report", cmd, f"plan {k}'s estimate is computed: run `{cmd}`")
        return step(
            "done",
            None,
            f"nothing to do: plan {k}'s estimate is computed and reported; for more, "
            f"`bams-cli select -w {w}` (discovery) or `bams-cli estimate -w {w} --plan` "
            "(a new sample)",
            ({"step": "select", "command": f"bams-cli select -w {w}"}, new_plan),
        )
    if stale:
        return step("fit", fit, f"{why_fit}; run `{fit}`")
    budget = batches[-1]["budget"] or defaults.BUDGET
    cmd = f"bams-cli select -w {w} --budget {budget:g}"
    return step(
        "select",
        cmd,
        f"the model is up to date: run `{cmd}` for the next batch, or, when discovery is "
        f"done, `bams-cli estimate -w {w} --plan`",
        (new_plan,),
    )


def _requests(entry: dict[str, Any]) -> int:
    """How many requests a batch (its picks) or plan (its sampled segments) made."""
    return int(entry["picks"] if "batch" in entry else entry["sampled"])


def _to_simulate(entry: dict[str, Any]) -> str:
    """What of a batch or plan awaiting results to simulate: its hand-off list, or, once
    some of its requests have results, the others alone."""
    total = _requests(entry)
    if entry["pending"] == total:
        return str(entry["handoff"])
    those = f"the {entry['pending']} of the {total} requests of"
    if entry["pending_handoff"]:
        name = Path(entry["handoff"]).name
        return f"{entry['pending_handoff']} ({those} {name} without a result)"
    # No current list of them (a workspace an older bams-cli wrote): say which.
    return f"{those} {entry['handoff']} without a result"


def _report_current(ws: Workspace, estimate: Path) -> bool | None:
    """Whether the report shows the current model and ``estimate``, by what the files
    record (which a copy keeps, unlike modification times): the model's fit time and
    observations, and the estimate's plan, gammas, rates and intervals. None when a file
    does not say (missing, unreadable, or written without those records)."""
    try:
        summary = json.loads((ws.report_dir / "summary.json").read_text())
        model = json.loads(ws.model_path.read_text())
        est = json.loads(estimate.read_text())
    except (OSError, ValueError):
        return None
    if not all(isinstance(d, dict) for d in (summary, model, est)):
        return None
    fit = ("fitted_at", "observations_hash")
    shown_model = summary.get("model")
    if not isinstance(shown_model, dict) or any(
        k not in shown_model or k not in model for k in fit
    ):
        return None
    if any(shown_model[k] != model[k] for k in fit):
        return False
    keys = ("gamma", "p_hat", "ci_low", "ci_high", "confidence")
    shown, latest = summary.get("estimates"), est.get("estimates")
    if not (isinstance(shown, list) and isinstance(latest, list)):
        return None
    if not all(isinstance(e, dict) and "plan" in e for e in shown):
        return None
    return [(e["plan"], *(e.get(k) for k in keys)) for e in shown] == [
        (est.get("plan"), *(e.get(k) for k in keys)) for e in latest if isinstance(e, dict)
    ]


def _mtime(path: Path) -> int:
    return path.stat().st_mtime_ns if path.exists() else -1


def _newest(ws: Workspace, pattern: str) -> int:
    """Modification time of the newest file matching ``pattern``: which came last."""
    return max((_mtime(p) for p in ws.root.glob(pattern)), default=-1)


def _json(text: str | None) -> Any:
    try:
        return json.loads(text) if text is not None else None
    except ValueError:
        return None
