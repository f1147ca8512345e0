"""``bams-cli abandon``: requests that will never come back, and what that does downstream.

A simulation that crashed for good, timed out, or was dropped leaves its request pending
forever: ``select`` and ``estimate --plan`` wait for it, ``status`` exits 3. Abandoning it
records (segment, level, batch or plan, why) in ``abandoned.parquet``, an append-only log
like the observation log (nothing is ever removed; a result that arrives later is
ingested as usual and outranks the abandonment). Downstream:

- ``Workspace.pending()`` no longer lists the request, so ``status`` and exit code 3 stop
  waiting on it;
- ``select`` treats the pair as done: never offered again (``select --retry-abandoned``
  offers it);
- ``estimate`` refuses a plan whose sampled segments were abandoned, naming them: an
  estimate on the remaining sample would be a quietly smaller, biased one. With
  ``--failed-as bounds`` it reports the worst case instead: the same estimator on the same
  plan with the abandoned segments taken as all passes (the interval's lower end) and as
  all failures (its upper end).
"""

from __future__ import annotations

import datetime as dt
import inspect
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from bams_cli import pipeline
from bams_cli.errors import AbandonedRunsError, InputError, OptionError, OptionValueError
from bams_cli.settings import Settings
from bams_cli.state import handoff as contract
from bams_cli.state import pending, schemas
from bams_cli.state.inputs import read_results
from bams_cli.state.io import read_table, transaction
from bams_cli.state.workspace import Workspace

SID = schemas.SEGMENT_ID
RID = contract.REQUEST_ID
KEYS = [SID, "fidelity"]
#: How ``estimate`` may treat abandoned planned segments (``--failed-as``).
FAILED_AS = ("bounds",)
#: How many abandoned segments an error message or a summary names.
NAMED = 3


# ---------------------------------------------------------------------------------------
# abandon
# ---------------------------------------------------------------------------------------
@pipeline.locked
def abandon(
    root: Path,
    *,
    batch: int | None = None,
    plan: int | None = None,
    segments: Path | None = None,
    fidelity: Sequence[str] | None = None,
    reason: str | None = None,
) -> dict[str, Any]:
    """Record the pending requests of a batch, a plan or a list as never coming back.

    ``batch`` / ``plan`` take every pending request of that list; ``segments`` (a file with
    ``request_id``, or ``segment_id`` and optionally ``fidelity``: a hand-off list or a
    results file filtered to the lost runs) takes those, within ``batch`` / ``plan`` when
    given; ``fidelity`` (numbers or level names) narrows to those levels. Requests already
    abandoned are left as they are, so a repeat changes nothing (``unchanged``).

    Parameters
    ----------
    root : Path
        The workspace folder (``--workspace``/``-w``).
    batch : int, optional
        Abandon batch N's pending requests.
    plan : int, optional
        Abandon estimate plan N's pending requests.
    segments : Path, optional
        CSV or Parquet naming the requests: ``request_id``, or ``segment_id`` (and
        ``fidelity``).
    fidelity : sequence of str, optional
        Only these levels (numbers or names; an item may be comma-separated).
    reason : str, optional
        Why they will never come back (kept in the log).
    wait : bool, default False
        Wait for another command's workspace lock instead of failing at once
        (``WorkspaceLockedError``).

    Returns
    -------
    dict
        The summary ``--json`` prints: ``abandoned``, ``already_abandoned``,
        ``unchanged``, ``by_source``, ``first``, ``log``, ``log_rows``, ``pending``,
        ``pending_lists`` (as ``ingest_results``'); ``message`` when nothing changed.

    Raises
    ------
    OptionError
        None of ``batch``, ``plan``, ``segments``; both ``batch`` and ``plan``; no such
        batch or plan; an unknown level in ``fidelity``.
    InputError
        ``segments`` lacks the key columns, has no rows or names unknown requests.
    WorkspaceError
        No workspace at ``root``.
    WorkspaceLockedError
        Another command holds the lock and ``wait`` is False.
    """
    if batch is None and plan is None and segments is None:
        raise OptionValueError(
            "abandon: say which requests: --batch N, --plan N or --segments FILE"
        )
    if batch is not None and plan is not None:
        raise OptionError("abandon: --batch and --plan name one list each; pass one of them")
    ws = Workspace(root)
    settings = ws.require_initialised()
    requests = ws.requests()
    if batch is not None:
        known = ws.batch_numbers()
        if batch not in known:
            raise OptionError(f"--batch {batch}: no such batch (batches: {_numbers(known)})")
        requests = requests.filter(pl.col("batch") == batch)
    if plan is not None:
        known = sorted(set(ws.read_plan_picks()["plan"].to_list()))
        if plan not in known:
            raise OptionError(f"--plan {plan}: no such estimate plan (plans: {_numbers(known)})")
        requests = requests.filter(pl.col("plan") == plan)
    if fidelity:
        requests = requests.filter(pl.col("fidelity").is_in(_levels(fidelity, settings)))
    observed = ws.read_observations().select(*KEYS).unique()
    if segments is not None:
        requests = _listed(segments, requests, observed, settings)
    open_ = requests.join(observed, on=KEYS, how="anti")
    gone = ws.read_abandoned()
    already = open_.join(gone.select(RID).unique(), on=RID, how="semi")
    new = open_.join(gone.select(RID).unique(), on=RID, how="anti")
    why = reason or "abandoned by hand"
    summary = _commit(ws, new, already.height, why, "bams-cli abandon")
    summary["pending"] = pipeline.pending_summary(ws)
    summary["pending_lists"] = pending.summary(ws)
    return summary


def _numbers(known: list[int]) -> str:
    return ", ".join(map(str, known)) if known else "none yet"


def _levels(values: Sequence[str], settings: Settings) -> list[int]:
    names = [lv.name for lv in settings.levels]
    out = []
    for text in values:
        for value in (v.strip() for v in str(text).split(",") if v.strip()):
            if value in names:
                out.append(names.index(value))
            elif value.isdigit() and int(value) < len(names):
                out.append(int(value))
            else:
                known = ", ".join(f"{i} = {n!r}" for i, n in enumerate(names))
                raise OptionError(f"--fidelity {value!r}: not a level (known levels: {known})")
    return out


def _listed(
    path: Path, requests: pl.DataFrame, observed: pl.DataFrame, settings: Settings
) -> pl.DataFrame:
    """The requests a ``--segments`` file names; a row naming none is an error."""
    table = read_table(path, what="segments")
    df = pl.from_arrow(table)
    assert isinstance(df, pl.DataFrame)
    df = df.with_row_index("_row", offset=1)
    if RID in df.columns:
        df = df.with_columns(pl.col(RID).cast(pl.String).str.strip_chars())
        on = [RID]
    elif SID in df.columns:
        df = df.with_columns(pl.col(SID).cast(pl.String))
        on = [SID]
        if "fidelity" in df.columns:
            fid = contract.resolve_fidelity(df["fidelity"], df["_row"], settings, path)
            df = df.with_columns(fid.alias("fidelity"))
            on = KEYS
    else:
        raise InputError(
            path, "needs a request_id or a segment_id column (e.g. a filtered hand-off list)"
        )
    if df.height == 0:
        raise InputError(path, "has no rows; nothing to abandon")
    keyed = df.select("_row", *on).join(
        requests.with_columns(pl.lit(True).alias("_hit")), on=on, how="left"
    )
    unmatched = keyed.filter(pl.col("_hit").is_null())
    if unmatched.height:
        first = unmatched.row(0, named=True)
        where = "" if requests.height == 0 else " in the lists asked for"
        raise InputError(
            path,
            f"{on[0]} {first[on[0]]!r} is not a request{where} ({unmatched.height} such rows); "
            "copy request ids or segment ids from the hand-off list",
            column=on[0],
            row=int(first["_row"]),
        )
    done = keyed.join(observed, on=KEYS, how="semi")
    if done.height:
        first = done.row(0, named=True)
        raise InputError(
            path,
            f"({first[SID]!r}, fidelity {first['fidelity']}) already has a result "
            f"({done.height} such rows); nothing to abandon there, drop it from the file",
            column=on[0],
            row=int(first["_row"]),
        )
    return keyed.drop("_row", "_hit").unique(subset=[RID], keep="first")


def _commit(
    ws: Workspace,
    new: pl.DataFrame,
    already: int,
    reason: str | pl.Expr,
    source: str,
    observed: pl.DataFrame | None = None,
) -> dict[str, Any]:
    """Append ``new`` requests (request_id, segment_id, fidelity, batch, plan) to the log,
    and bring the pending-only lists (``state.pending``) in line with it in the same
    commit. ``observed``: the (segment_id, fidelity) pairs with a result once the
    transaction commits (default: the log's)."""
    log = ws.read_abandoned()
    new = new.sort(RID)
    if new.height:
        now = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
        reason_expr = reason if isinstance(reason, pl.Expr) else pl.lit(reason)
        rows = new.select(
            pl.col(SID).cast(pl.String),
            pl.col("fidelity").cast(pl.Int64),
            pl.col("batch").cast(pl.Int64),
            pl.col("plan").cast(pl.Int64),
            pl.col(RID).cast(pl.String),
            reason_expr.cast(pl.String).alias("reason"),
            pl.lit(source).alias("source"),
            pl.lit(now).alias("abandoned_at"),
        )
        log = pl.concat([log, rows], how="vertical_relaxed")
        with transaction() as tx:
            tx.write_parquet(ws.abandoned_path, schemas.ABANDONED.conform(log.to_arrow()))
            pending.stage(ws, tx, observed=observed, abandoned=log)
    labels = [
        contract.source_label("batch", int(b)) if b is not None else f"plan {int(p)}"
        for b, p in zip(new["batch"].to_list(), new["plan"].to_list(), strict=True)
    ]
    by_source: dict[str, int] = {}
    for label in labels:
        by_source[label] = by_source.get(label, 0) + 1
    summary: dict[str, Any] = {
        "abandoned": new.height,
        "already_abandoned": already,
        "unchanged": new.height == 0,
        "by_source": by_source,
        "first": new.head(20).select(RID, SID, "fidelity", "batch", "plan").to_dicts(),
        "log": str(ws.abandoned_path),
        "log_rows": log.height,
    }
    if new.height == 0:
        summary["message"] = (
            f"nothing to abandon: {already} of these requests "
            f"{'was' if already == 1 else 'were'} abandoned before, the rest have results"
            if already
            else "nothing to abandon: every request asked for has a result"
        )
    return summary


# ---------------------------------------------------------------------------------------
# ingest-results --abandon-failed
# ---------------------------------------------------------------------------------------
@pipeline.locked
def ingest_results_abandoning_failed(
    root: Path, source: Path, *, replace: bool = False, allow_unselected: bool = False
) -> dict[str, Any]:
    """``ingest-results``, and the rows whose status says the run failed (any status but
    empty or ok) abandoned, in one commit: the observation log and the abandoned log land
    together or not at all. The abandonment's reason is the row's status.

    This is ``bams-cli ingest-results --abandon-failed``.

    Parameters
    ----------
    root : Path
        The workspace folder (``--workspace``/``-w``).
    source : Path
        Parquet or CSV results, as for ``ingest_results``.
    replace : bool, default False
        Supersede logged values that disagree with this file.
    allow_unselected : bool, default False
        Accept results for (segment, fidelity) pairs nothing selected.
    wait : bool, default False
        Wait for another command's workspace lock instead of failing at once
        (``WorkspaceLockedError``).

    Returns
    -------
    dict
        ``ingest_results``' summary with ``abandoned`` (``abandoned``,
        ``already_abandoned``, ...).

    Raises
    ------
    InputError, ConflictError, WorkspaceError
        As ``ingest_results``.
    WorkspaceLockedError
        Another command holds the lock and ``wait`` is False.
    """
    ws = Workspace(root)
    settings = ws.require_initialised()
    ws.require_segments()
    results, not_run = read_results(source, settings, ws)
    ingest = inspect.unwrap(pipeline.ingest_results)  # already holding the lock
    with transaction():
        summary = ingest(root, source, replace=replace, allow_unselected=allow_unselected)
        targets, already = _failed_requests(ws, settings, not_run, results, source)
        # What has a result once this commits: the log's pairs and the file's (the
        # ingest above is staged, not yet on disk).
        observed = pl.concat(
            [ws.read_observations().select(*KEYS), results.select(*KEYS)], how="vertical_relaxed"
        )
        gone = _commit(
            ws,
            targets,
            already,
            pl.format("status '{}' in {}", pl.col("_status"), pl.lit(source.name)),
            f"ingest-results --abandon-failed {source.name}",
            observed=observed,
        )
    summary["abandoned"] = {k: gone[k] for k in ("abandoned", "already_abandoned", "first")}
    if "message" in summary and gone["abandoned"]:
        summary["message"] = summary["message"].replace(
            "nothing changed", f"{gone['abandoned']} failed requests abandoned"
        )
    summary["pending"] = pipeline.pending_summary(ws)  # after the commit
    summary["pending_lists"] = pending.summary(ws)
    return summary


def _failed_requests(
    ws: Workspace,
    settings: Settings,
    not_run: pl.DataFrame,
    results: pl.DataFrame,
    path: Path,
) -> tuple[pl.DataFrame, int]:
    """The open requests that a results file's not-run rows answer, and how many of them
    were abandoned before. A row keyed by request_id is that request; one keyed by
    (segment_id, fidelity) is the pair's pending request."""
    empty = ws.requests().head(0).with_columns(pl.lit(None, pl.String).alias("_status"))
    if not_run.height == 0:
        return empty, 0
    by_id = not_run.filter(pl.col(RID).is_not_null() & (pl.col(RID).str.strip_chars() != ""))
    by_pair = not_run.join(by_id.select("_row"), on="_row", how="anti")
    frames = []
    if by_id.height:
        req = by_id.select("_row", pl.col(RID).str.strip_chars(), pl.col("status").alias("_status"))
        req = req.join(ws.requests(), on=RID, how="left")
        unknown = req.filter(pl.col(SID).is_null())
        if unknown.height:
            first = unknown.row(0, named=True)
            raise InputError(
                path,
                f"request_id {first[RID]!r} is not in any hand-off list",
                column=RID,
                row=int(first["_row"]),
            )
        frames.append(req.drop("_row"))
    if by_pair.height:
        fid = contract.resolve_fidelity(by_pair["fidelity"], by_pair["_row"], settings, path)
        pairs = by_pair.select(SID, pl.col("status").alias("_status")).with_columns(
            fid.alias("fidelity")
        )
        pend = ws.pending()
        for key, kind in (("batch", "batch"), ("plan", "plan")):
            hit = pairs.join(pend.filter(pl.col(key).is_not_null()), on=KEYS, how="inner")
            if hit.height:
                ids = ws.requests().filter(pl.col(key).is_not_null())
                hit = hit.select(*KEYS, key, "_status").join(
                    ids.select(RID, *KEYS, key), on=[*KEYS, key], how="inner"
                )
                other = "plan" if kind == "batch" else "batch"
                frames.append(hit.with_columns(pl.lit(None, pl.Int64).alias(other)))
    if not frames:
        return empty, 0
    cols = [RID, SID, "fidelity", "batch", "plan", "_status"]
    found = pl.concat([f.select(cols) for f in frames], how="vertical_relaxed")
    found = found.unique(subset=[RID], keep="first")
    # A pair this very file (or the log) gives a value is answered, not lost.
    answered = pl.concat(
        [ws.read_observations().select(*KEYS), results.select(*KEYS)], how="vertical_relaxed"
    ).unique()
    found = found.join(answered, on=KEYS, how="anti")
    gone = ws.read_abandoned().select(RID).unique()
    already = found.join(gone, on=RID, how="semi").height
    return found.join(gone, on=RID, how="anti"), already


# ---------------------------------------------------------------------------------------
# what the other commands ask
# ---------------------------------------------------------------------------------------
def abandoned_mask(ws: Workspace, ids: np.ndarray, n_levels: int) -> np.ndarray:
    """True at (segment, level) pairs some request of which was abandoned and that have no
    result: ``select`` treats them as done. Shape (N, n_levels)."""
    mask = np.zeros((len(ids), n_levels), dtype=bool)
    gone = ws.read_abandoned().select(*KEYS).unique()
    if gone.height == 0:
        return mask
    gone = gone.join(ws.read_observations().select(*KEYS).unique(), on=KEYS, how="anti")
    pos = pl.DataFrame({SID: ids.astype(str), "_i": np.arange(len(ids))})
    hit = gone.join(pos, on=SID, how="inner").filter(pl.col("fidelity") < n_levels)
    mask[hit["_i"].to_numpy(), hit["fidelity"].to_numpy()] = True
    return mask


def planned_abandoned(
    ws: Workspace, number: int, path: Path, joined: pl.DataFrame, failed_as: str | None
) -> list[str]:
    """``estimate``'s check: plan ``number``'s sampled segments that were abandoned and
    have no level-0 result. Refused unless ``failed_as`` says how to count them."""
    gone = ws.read_abandoned().filter((pl.col("plan") == number) & (pl.col("fidelity") == 0))
    if gone.height == 0:
        return []
    lost = joined.filter(
        (pl.col("stratum") == "sampled")
        & pl.col("value").is_null()
        & pl.col(SID).is_in(gone[SID].implode())
    )[SID].to_list()
    if lost and failed_as is None:
        names = ", ".join(map(str, lost[:NAMED])) + (", ..." if len(lost) > NAMED else "")
        raise AbandonedRunsError(
            f"{path}: {len(lost)} planned segment{' was' if len(lost) == 1 else 's were'} "
            f"abandoned ({names}); an estimate "
            "without them would rest on a smaller sample than planned, biased toward "
            "whatever made them fail. Pass --failed-as bounds for the worst-case interval "
            "(abandoned taken as all failures and as all passes), or simulate them again "
            "and ingest the results"
        )
    if failed_as is not None and failed_as not in FAILED_AS:
        raise OptionError(f"--failed-as {failed_as!r}: choose {', '.join(FAILED_AS)}")
    return lost


def bound_estimates(
    summary: dict[str, Any],
    *,
    lost: list[str],
    sampled_ids: np.ndarray,
    fails: np.ndarray,
    estimate_with: Callable[[np.ndarray], Any],
) -> Any:
    """``estimate --failed-as bounds``: the estimate over every abandoned case, in place.
    Returns the all-failing case's estimates (``core.estimate.RateEstimates``: what p_hat
    now reports), or None when nothing was abandoned.

    The plan's estimator runs twice on the same sample: abandoned segments taken as all
    passes and as all failures. The rate is reported as the range of the two p_hat
    (``p_hat_low`` .. ``p_hat_high``; ``p_hat`` is the upper end, the worst case), the
    interval from the all-pass case's lower limit to the all-fail case's upper limit. No
    single standard error describes that, so ``se`` and ``rel_var`` are null with a note.

    fails : bool ndarray of shape (n_sampled, n_gammas), abandoned rows' entries ignored.
    """
    if not lost:
        return None
    gone = np.isin(np.asarray(sampled_ids).astype(str), np.asarray(lost, dtype=str))
    as_pass, as_fail = fails.copy(), fails.copy()
    as_pass[gone], as_fail[gone] = False, True
    low, high = estimate_with(as_pass), estimate_with(as_fail)
    k = int(gone.sum())
    note = (
        f"{k} planned segments abandoned: the interval runs from the lower limit with them "
        "all passing to the upper limit with them all failing; p_hat is the all-failing case"
    )
    for g, row in enumerate(summary["estimates"]):
        lo, hi = low[g], high[g]
        row.update(
            p_hat=hi.p_hat,
            p_hat_low=lo.p_hat,
            p_hat_high=hi.p_hat,
            se=None,
            variance_note=note,
            ci_low=lo.ci_low,
            ci_high=hi.ci_high,
            rel_var=None,
            rel_var_note=f"undefined: p_hat is a range, {lo.p_hat:.4g} (the {k} abandoned "
            f"segments all passing) to {hi.p_hat:.4g} (all failing)",
            failures_sampled=lo.n_failures_sampled,
            abandoned=k,
        )
        if "p_hat_unbiased" in row:  # the all-failing case's, as p_hat
            row["p_hat_unbiased"] = float(high.p_hat_unbiased[g])
    summary["abandoned"] = {
        "count": k,
        "failed_as": "bounds",
        "segments": [str(s) for s in lost[:20]],
        "note": note,
    }
    return high
