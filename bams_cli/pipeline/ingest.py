"""``bams-cli ingest-results``: the simulation team's results, logged against what was asked."""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Any

import polars as pl

from bams_cli.errors import (
    ConflictError,
    InputError,
    shown,
)
from bams_cli.pipeline._common import SID, locked, not_run_summary, pending_summary
from bams_cli.settings import Settings
from bams_cli.state import pending, schemas
from bams_cli.state.handoff import REQUEST_ID, _level_of
from bams_cli.state.inputs import read_results
from bams_cli.state.io import (
    file_sha256,
    transaction,
)
from bams_cli.state.workspace import Workspace


@locked
def ingest_results(
    root: Path,
    source: Path,
    *,
    replace: bool = False,
    allow_unselected: bool = False,
) -> dict[str, Any]:
    """Append a simulation team's results to the observation log.

    Each row is keyed by ``request_id`` (from the hand-off list), or by ``segment_id`` and
    ``fidelity`` (the level's number or its name in settings). A row whose status is
    neither empty nor ok (e.g. crashed) is not ingested: its request stays pending
    (``bams_cli.abandon.ingest_results_abandoning_failed`` records it as abandoned
    instead); one that carries a value anyway is refused. Re-ingesting the same file
    changes nothing.

    Parameters
    ----------
    root : Path
        The workspace folder (``--workspace``/``-w``).
    source : Path
        Parquet or CSV results: ``request_id`` or ``segment_id`` + ``fidelity``, ``value``,
        optional ``status`` (extra columns are kept).
    replace : bool, default False
        Supersede logged values that disagree with this file.
    allow_unselected : bool, default False
        Accept results for (segment, fidelity) pairs no batch or plan selected.
    wait : bool, default False
        Wait for another command's workspace lock instead of failing at once
        (``WorkspaceLockedError``).

    Returns
    -------
    dict
        The summary ``--json`` prints: ``ingested``, ``replaced``, ``already_known``,
        ``already_ingested``, ``observations``, ``log_rows``, ``log_active`` (the rows
        not replaced: what ``fit`` and ``status`` count), ``by_fidelity``; ``pending``
        (``count``, ``by_batch``, ``by_plan``, ``first``), ``pending_lists`` (the batches
        and plans partly answered: ``list``, ``pending``, ``requests``, ``handoff``,
        ``pending_handoff``, the list of their pending requests alone,
        ``state.pending``) and ``not_run`` (``count``, ``first``); ``message`` when
        nothing was new.

    Raises
    ------
    InputError
        The results file has a bad value, or names pairs never selected (without
        ``allow_unselected``); the message names file, column and row.
    ConflictError
        A value disagrees with one already logged (without ``replace``).
    WorkspaceError
        No workspace at ``root``, or no pool.
    WorkspaceLockedError
        Another command holds the lock and ``wait`` is False.
    """
    ws = Workspace(root)
    settings = ws.require_initialised()
    ws.require_segments()
    results, not_run = read_results(source, settings, ws)
    digest = file_sha256(source)
    log = ws.read_observations(active_only=False)

    # A file ingested before is a no-op, unless --replace asks for its values back (to
    # undo a later --replace): then it goes through like any file, superseding what differs.
    if digest in set(log["source_sha256"].to_list()) and not replace:
        active = log.filter(pl.col("active")).select(SID, "fidelity", pl.col("value").alias("_k"))
        changed = results.join(active, on=[SID, "fidelity"], how="left").filter(
            pl.col("_k").is_null() | (pl.col("_k") != pl.col("value"))
        )
        since = (
            f"; {changed.height} of its values {'was' if changed.height == 1 else 'were'} "
            "replaced since: pass --replace to restore them"
            if changed.height
            else ""
        )
        return {
            "ingested": 0,
            "already_ingested": True,
            "message": f"{source} was already ingested (sha256 {digest[:12]}); nothing changed"
            + since,
            "pending": pending_summary(ws),
            "pending_lists": pending.summary(ws),
            "not_run": not_run_summary(_still_pending(ws, settings, not_run)),
        }

    if results.height == 0:
        return {
            "ingested": 0,
            "already_ingested": False,
            "message": f"{source}: every row's status says it was not run; nothing ingested, "
            f"those requests stay pending",
            "pending": pending_summary(ws),
            "pending_lists": pending.summary(ws),
            "not_run": not_run_summary(_still_pending(ws, settings, not_run)),
        }
    pool_ids = pl.from_arrow(ws.read_segments([SID]).column(SID)).alias(SID)  # type: ignore[union-attr]
    unknown = results.filter(~pl.col(SID).is_in(pool_ids.implode()))
    if unknown.height:
        first = unknown.row(0, named=True)
        # Ids are exact; one that is a pool id but for spaces or case says so, with the fix.
        sid = str(first[SID])
        like = pool_ids.filter(
            (pool_ids == sid.strip()) | (pool_ids.str.to_lowercase() == sid.strip().lower())
        )
        fix = (
            f"the pool has {shown(like[0])} (ids are exact: write them as in the hand-off list)"
            if like.len()
            else "add segments with `bams-cli embed-reduce --apply`"
        )
        raise InputError(
            source,
            f"segment id {shown(first[SID])} is not in the pool ({unknown.height} unknown in all); "
            + fix,
            column=SID,
            row=int(first["_row"]),
        )

    # A row keyed by request_id belongs to that request's batch or plan; one keyed by
    # (segment_id, fidelity) to the latest batch and plan that selected the pair.
    matched = results.join(ws.selections(), on=[SID, "fidelity"], how="left").with_columns(
        pl.when(pl.col("_keyed"))
        .then(pl.col("_req_batch"))
        .otherwise(pl.col("batch"))
        .alias("batch"),
        pl.when(pl.col("_keyed")).then(pl.col("_req_plan")).otherwise(pl.col("plan")).alias("plan"),
    )
    unselected = matched.filter(pl.col("batch").is_null() & pl.col("plan").is_null())
    if unselected.height and not allow_unselected:
        first3 = unselected[SID].head(3).to_list()
        names = ", ".join(s if len(s) <= 40 else s[:37] + "..." for s in first3)
        more = "" if unselected.height <= 3 else ", ..."
        raise InputError(
            source,
            f"{unselected.height} (segment_id, fidelity) pairs were never selected ({names}{more}); "
            f"pass --allow-unselected to ingest them",
            column=SID,
            row=int(unselected["_row"][0]),
        )

    active = log.filter(pl.col("active")).select(SID, "fidelity", pl.col("value").alias("known"))
    both = matched.join(active, on=[SID, "fidelity"], how="left")
    conflicts = both.filter(pl.col("known").is_not_null() & (pl.col("known") != pl.col("value")))
    if conflicts.height and not replace:
        c = conflicts.row(0, named=True)
        raise ConflictError(
            f"{source}: column 'value', row {c['_row']}: ({shown(c[SID])}, fidelity {c['fidelity']}) "
            f"is already known as {c['known']!r}, got {c['value']!r} "
            f"({conflicts.height} conflicts in all); pass --replace to supersede the logged values"
        )
    same = both.filter(pl.col("known").is_not_null() & (pl.col("known") == pl.col("value")))
    new = both.filter(pl.col("known").is_null() | (pl.col("known") != pl.col("value")))

    if new.height == 0:
        return {
            "ingested": 0,
            "already_known": same.height,
            "already_ingested": False,
            "message": f"{source}: every value is already in the log; nothing changed",
            "pending": pending_summary(ws),
            "pending_lists": pending.summary(ws),
            "not_run": not_run_summary(_still_pending(ws, settings, not_run)),
        }
    now = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    new_rows = new.select(
        pl.col(SID),
        pl.col("fidelity"),
        pl.col("value"),
        pl.col("batch"),
        pl.lit(source.name).alias("source_file"),
        pl.lit(digest).alias("source_sha256"),
        pl.lit(now).alias("ingested_at"),
        pl.lit(True).alias("active"),
        pl.col("extra"),
    )
    superseded = conflicts.select(SID, "fidelity").with_columns(pl.lit(True).alias("_sup"))
    old = (
        log.join(superseded, on=[SID, "fidelity"], how="left")
        .with_columns((pl.col("active") & pl.col("_sup").is_null()).alias("active"))
        .drop("_sup")
    )
    combined = pl.concat([old, new_rows], how="vertical_relaxed")

    with transaction() as tx:
        tx.write_parquet(
            ws.observations_path,
            schemas.OBSERVATIONS.conform(combined.to_arrow(), {"last_source": source.name}),
        )
        # A batch or plan left partly answered gets the list of its other requests beside
        # its hand-off list, in the same commit: simulating the whole list again would ask
        # for values the log now holds.
        pending.stage(ws, tx, observed=combined.filter(pl.col("active")))
    return {
        "ingested": new.height,
        "replaced": conflicts.height,
        "already_known": same.height,
        "already_ingested": False,
        "observations": str(ws.observations_path),
        "log_rows": combined.height,
        "log_active": int(combined["active"].sum()),
        "by_fidelity": {
            int(k): int(v) for k, v in new.group_by("fidelity").len().sort("fidelity").iter_rows()
        },
        "level_names": [lv.name for lv in settings.levels],
        "pending": pending_summary(ws),
        "pending_lists": pending.summary(ws),
        "not_run": not_run_summary(_still_pending(ws, settings, not_run)),
    }


def _still_pending(ws: Workspace, settings: Settings, not_run: pl.DataFrame) -> pl.DataFrame:
    """The rows a results file marked as not run whose (segment, level) is still pending.

    A row names its request by request_id, or by segment_id and fidelity (a number or a
    level name); the rows come back with ``fidelity`` as a level number (null where the row
    names no configured level) and ``fidelity_given``, the file's text. One whose run has a result since (its retry ingested first, or this file
    ingested again after it) is not reported as "stays pending": a re-ingest had said "12
    rows not run ... stay pending" beside "nothing pending". A fidelity that names no level
    compares by segment alone.
    """
    if not not_run.height:
        return not_run
    req = {
        r: (sid, int(fid))
        for r, sid, fid in ws.requests().select(REQUEST_ID, SID, "fidelity").iter_rows()
    }
    waiting = ws.pending().select(SID, "fidelity").unique()
    pairs = set(waiting.iter_rows())
    segments = set(waiting[SID].to_list())
    by_name = {lv.name: i for i, lv in enumerate(settings.levels)}
    keep, levels = [], []
    for rid, sid, fid in not_run.select(REQUEST_ID, SID, "fidelity").iter_rows():
        level: int | None
        if rid is not None and rid.strip() in req:
            sid, level = req[rid.strip()]
        else:
            level = _level_of(fid, by_name) if fid is not None else None
            if level is not None and not 0 <= level < len(settings.levels):
                level = None
        keep.append((sid, level) in pairs if level is not None else sid in segments)
        levels.append(level)
    # The level as a number, as every other list of runs gives it (null: none named), and
    # the file's own text beside it, so that a level the study does not have is still seen.
    not_run = not_run.with_columns(
        pl.col("fidelity").alias("fidelity_given"), pl.Series("fidelity", levels, dtype=pl.Int64)
    )
    return not_run.filter(pl.Series(keep, dtype=pl.Boolean))
