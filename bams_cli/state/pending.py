"""Pending-only hand-off lists: what is left of a batch or an estimate plan to simulate.

When some requests of a hand-off list have results and others do not (runs that crashed,
results that came back in parts), simulating the whole list again asks a simulator with
run-to-run noise for values the log already holds, and ``ingest-results`` refuses those
as conflicts. So the commands that change which requests are pending (``ingest-results``,
``abandon``) keep, beside each list that is partly answered, its pending rows alone, in
the hand-off list's own columns:

```
batches/batch-0003.csv            batches/batch-0003.pending.csv
estimates/plan-0001-handoff.csv   estimates/plan-0001-handoff.pending.csv
```

written in the command's own transaction (``stage``), and removed in it once nothing of
the list is pending or nothing of it has a result. ``status`` and the refusals of ``fit``
and ``estimate`` name it only while it holds exactly the requests still pending
(``to_simulate``); ``loop`` hands its simulator the same rows (``pending_rows``).

A request is pending for its list while its (segment, level) pair has no active result
and was not abandoned for that list: what ``status`` counts as the list's pending picks.
"""

from __future__ import annotations

from pathlib import Path

import polars as pl

from bams_cli.state.handoff import REQUEST_ID, Kind, handoff_path, pending_path
from bams_cli.state.io import Transaction
from bams_cli.state.schemas import SEGMENT_ID as SID
from bams_cli.state.workspace import Workspace

KEYS = [SID, "fidelity"]


def lists(ws: Workspace) -> list[tuple[Kind, int]]:
    """Every hand-off list of the study that made requests: its batches, then its
    estimate plans."""
    plans = sorted(set(ws.read_plan_picks()["plan"].to_list()))
    batches: list[tuple[Kind, int]] = [("batch", n) for n in ws.batch_numbers()]
    return batches + [("plan", int(k)) for k in plans]


def in_play(ws: Workspace) -> list[tuple[Kind, int]]:
    """The lists a pending-only list can concern: those with a request pending now, and
    those with such a list on disk (it may have to go). Results and abandonment only ever
    end requests, so no other list can become partly answered by a command's commit. Only
    these are read again: every batch file twice per ingest took 3.6 s at 301 batches."""
    pend = ws.pending()
    live = {(kind, int(n)) for kind in ("batch", "plan") for n in pend[kind].drop_nulls().unique()}
    return [
        (kind, number)
        for kind, number in lists(ws)
        if (kind, number) in live or pending_path(handoff_path(ws.root, kind, number)).exists()
    ]


def open_requests(
    ws: Workspace,
    kind: Kind,
    number: int,
    *,
    observed: pl.DataFrame | None = None,
    abandoned: pl.DataFrame | None = None,
) -> tuple[pl.DataFrame, int]:
    """The requests of batch or plan ``number`` still pending, and how many it made.

    Parameters
    ----------
    observed : DataFrame, optional
        (segment_id, fidelity) pairs with an active result (default: the log's); a
        command passes the log it is about to commit.
    abandoned : DataFrame, optional
        The abandoned log (default: ``abandoned.parquet``), likewise.

    Returns
    -------
    requests : DataFrame
        ``request_id``, ``segment_id``, ``fidelity`` of the pending requests.
    total : int
        The requests the list made.
    """
    if kind == "batch":
        made = ws.read_batch(number)
    else:
        made = ws.read_plan_picks().filter(pl.col("plan") == number)
    made = made.select(REQUEST_ID, SID, "fidelity")
    if observed is None:
        observed = ws.read_observations()
    if abandoned is None:
        abandoned = ws.read_abandoned()
    gone = abandoned.filter(pl.col(kind) == number).select(KEYS).unique()
    left = made.join(observed.select(KEYS).unique(), on=KEYS, how="anti")
    return left.join(gone, on=KEYS, how="anti"), made.height


def pending_rows(
    ws: Workspace,
    kind: Kind,
    number: int,
    *,
    observed: pl.DataFrame | None = None,
    abandoned: pl.DataFrame | None = None,
) -> pl.DataFrame | None:
    """The hand-off list's rows (as text, in its order) of the requests still pending, or
    None when there is no such list to make: every request is pending (the hand-off list
    itself is the one to simulate), none is, or the hand-off list is gone.
    ``observed`` and ``abandoned`` as ``open_requests``."""
    left, total = open_requests(ws, kind, number, observed=observed, abandoned=abandoned)
    return _rows_of(handoff_path(ws.root, kind, number), left, total)


def _rows_of(handoff: Path, left: pl.DataFrame, total: int) -> pl.DataFrame | None:
    """``pending_rows`` given the list's pending requests ``left`` of ``total``."""
    if left.height in (0, total) or not handoff.exists():
        return None
    try:
        rows = pl.read_csv(handoff, infer_schema=False).with_row_index("_order")
        keys = left.select(pl.col(SID).cast(pl.String), pl.col("fidelity").cast(pl.String))
        rows = rows.join(keys, on=KEYS, how="semi").sort("_order").drop("_order")
    except (pl.exceptions.PolarsError, OSError, UnicodeDecodeError):
        return None  # a damaged hand-off list: no list of its rows (status names it whole)
    # A hand-off list that does not hold every pending request (edited by hand) makes no
    # list either: one that lacked a request would be named as all there is to simulate.
    return rows if rows.height == left.height else None


def _current(handoff: Path, want: pl.DataFrame | None) -> Path:
    """The pending-only list beside ``handoff`` if it holds exactly ``want``, else ``handoff``."""
    path = pending_path(handoff)
    if want is not None and path.read_text() == want.write_csv():
        return path
    return handoff


def to_simulate(
    ws: Workspace,
    kind: Kind,
    number: int,
    *,
    observed: pl.DataFrame | None = None,
    abandoned: pl.DataFrame | None = None,
) -> Path:
    """The list to hand the simulation team for batch or plan ``number``: its pending-only
    list while that holds exactly the requests still pending, else the hand-off list.
    ``observed`` and ``abandoned`` as ``open_requests`` (read when left out)."""
    handoff = handoff_path(ws.root, kind, number)
    if not pending_path(handoff).exists():
        return handoff
    return _current(handoff, pending_rows(ws, kind, number, observed=observed, abandoned=abandoned))


def stage(
    ws: Workspace,
    tx: Transaction,
    *,
    observed: pl.DataFrame | None = None,
    abandoned: pl.DataFrame | None = None,
) -> None:
    """Stage in ``tx`` every pending-only list as the logs being committed leave it:
    written where it is missing or differs, removed where no list is wanted.
    ``observed`` and ``abandoned`` as ``open_requests``: what the transaction commits."""
    if observed is None:
        observed = ws.read_observations()
    if abandoned is None:
        abandoned = ws.read_abandoned()
    observed = observed.select(KEYS).unique()
    for kind, number in in_play(ws):
        want = pending_rows(ws, kind, number, observed=observed, abandoned=abandoned)
        path = pending_path(handoff_path(ws.root, kind, number))
        # Staged already in this transaction (ingest-results --abandon-failed stages the
        # lists once more after the abandonment): the later staging must replace it.
        again = tx.staged(path)
        if want is None:
            if again or path.exists():
                tx.remove(path)
            continue
        text = want.write_csv()
        if again or not path.exists() or path.read_text() != text:
            tx.write_text(path, text)


def summary(ws: Workspace) -> list[dict[str, object]]:
    """The lists partly answered, for a command's output: ``list`` ("batch 3"),
    ``pending``, ``requests``, ``abandoned`` (without a result), ``handoff`` and
    ``pending_handoff`` (the list to simulate,
    or null when it is not current: ``status`` then names the whole hand-off list)."""
    observed = ws.read_observations().select(KEYS).unique()
    abandoned = ws.read_abandoned()
    out: list[dict[str, object]] = []
    for kind, number in in_play(ws):
        left, total = open_requests(ws, kind, number, observed=observed, abandoned=abandoned)
        if left.height in (0, total):
            continue
        handoff = handoff_path(ws.root, kind, number)
        # The requests are read once: the list is checked against the rows they give.
        current = (
            _current(handoff, _rows_of(handoff, left, total))
            if pending_path(handoff).exists()
            else handoff
        )
        # The others have results, or were abandoned without one.
        gone = abandoned.filter(pl.col(kind) == number).select(KEYS).unique()
        out.append(
            {
                "list": f"{kind} {number}",
                "pending": left.height,
                "requests": total,
                "abandoned": gone.join(observed, on=KEYS, how="anti").height,
                "handoff": str(handoff),
                "pending_handoff": str(current) if current != handoff else None,
            }
        )
    return out
