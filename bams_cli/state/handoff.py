"""The hand-off contract: what a simulation team receives, and what it sends back.

Every batch (``select``) and estimate plan (``estimate --plan``) writes one hand-off list
as CSV, in one column layout whichever command wrote it, and a results template beside it:

```
batches/batch-0003.csv                       estimates/plan-0001-handoff.csv
batches/batch-0003.results-template.csv      estimates/plan-0001.results-template.csv
```

Once some of a list's requests have results and others not, a list of the others alone
lies beside it (``batch-0003.pending.csv``, ``plan-0001-handoff.pending.csv``; written by
``state.pending``).

A hand-off row is one request: simulate ``segment_id`` at level ``fidelity`` (its name in
settings is ``fidelity_name``). Its ``request_id`` (``b0003-0007``: batch 3, row 7;
``p0001-0042``: plan 1, row 42) is unique within the study, so results keyed by it alone
are enough. The columns, in order:

    request_id, source, segment_id, fidelity, fidelity_name, cost, purpose, pass-through...

``source`` is ``batch 3`` or ``plan 1``; ``purpose`` says why the run matters (``confirm
lead``, ``confirm likely``, ``discover``, ``estimate``); pass-through columns are the
pool's own (scenario tags, a difficulty score). Internal columns (a batch's ``delta_j``,
``cluster``, ``rank``, ``strategy``; a plan's ``stratum``, ``pi``, ``draws``, ...) stay in
the Parquet state file and reach the CSV only on request (``--handoff-internal``).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np
import polars as pl
import pyarrow as pa

from bams_cli.errors import InputError, shown
from bams_cli.settings import Settings
from bams_cli.state.schemas import SEGMENT_ID, batch_path

#: Version of the hand-off layout; bump it when a column changes meaning or goes away.
HANDOFF_VERSION = 1

REQUEST_ID = "request_id"
#: The contract's columns, in the order every hand-off CSV carries them.
HANDOFF_COLUMNS = (
    REQUEST_ID,
    "source",
    SEGMENT_ID,
    "fidelity",
    "fidelity_name",
    "cost",
    "purpose",
)
#: What the simulation team sends back: a template with these columns, value and status empty.
TEMPLATE_COLUMNS = (REQUEST_ID, SEGMENT_ID, "fidelity", "value", "status")
#: A result's status when the run produced its value; anything else says why it did not.
STATUS_OK = ("", "ok")

Kind = Literal["batch", "plan"]
_PREFIX = {"batch": "b", "plan": "p"}
_REQUEST = re.compile(r"^([bp])(\d+)-(\d+)$")


def request_ids(kind: Kind, number: int, k: int) -> list[str]:
    """Request ids of a hand-off list's k rows: ``b0003-0001`` ... (rows count from 1).

    Row numbers are zero-padded to at least four digits, wider for longer lists, so the
    ids of one list sort in row order.
    """
    width = max(4, len(str(k)))
    return [f"{_PREFIX[kind]}{number:04d}-{i:0{width}d}" for i in range(1, k + 1)]


def source_label(kind: Kind, number: int) -> str:
    """``batch 3`` or ``plan 1``: the hand-off list a request belongs to."""
    return f"{kind} {number}"


def parse_request_id(text: str) -> tuple[Kind, int, int] | None:
    """(kind, list number, row) of a well-formed request id, else None."""
    m = _REQUEST.match(text.strip())
    if not m:
        return None
    kind: Kind = "batch" if m.group(1) == "b" else "plan"
    return kind, int(m.group(2)), int(m.group(3))


def handoff_path(workspace: Path, kind: Kind, number: int) -> Path:
    """The CSV hand-off list of batch or plan ``number``: ``batches/batch-0003.csv``,
    ``estimates/plan-0001-handoff.csv``."""
    if kind == "batch":
        return batch_path(workspace, number).with_suffix(".csv")
    return workspace / "estimates" / f"plan-{number:04d}-handoff.csv"


def pending_path(handoff_csv: Path) -> Path:
    """The list of a hand-off list's requests still without a result, beside it:
    ``batch-0003.pending.csv``, ``plan-0001-handoff.pending.csv`` (``state.pending``)."""
    return handoff_csv.with_name(f"{handoff_csv.stem}.pending.csv")


def template_path(handoff_csv: Path) -> Path:
    """The results template beside a hand-off list: ``batch-0003.results-template.csv``,
    ``plan-0001.results-template.csv`` (beside ``plan-0001-handoff.csv``)."""
    stem = handoff_csv.stem.removesuffix("-handoff")
    return handoff_csv.with_name(f"{stem}.results-template.csv")


def contract_columns(
    kind: Kind,
    number: int,
    segment_ids: Sequence[str] | np.ndarray,
    levels: np.ndarray,
    settings: Settings,
    purpose: Sequence[str],
) -> dict[str, pa.Array]:
    """The contract's columns for k requests, as Arrow arrays in contract order."""
    k = len(levels)
    levels = np.asarray(levels, np.int64)
    names = [lv.name for lv in settings.levels]
    costs = np.asarray(settings.costs, np.float64)
    return {
        REQUEST_ID: pa.array(request_ids(kind, number, k), pa.string()),
        "source": pa.array([source_label(kind, number)] * k, pa.string()),
        SEGMENT_ID: pa.array(np.asarray(segment_ids).astype(str), pa.string()),
        "fidelity": pa.array(levels, pa.int64()),
        "fidelity_name": pa.array([names[lv] for lv in levels], pa.string()),
        "cost": pa.array(costs[levels], pa.float64()),
        "purpose": pa.array(list(purpose), pa.string()),
    }


def handoff_frame(table: pa.Table, internal: Sequence[str], *, with_internal: bool) -> pl.DataFrame:
    """The CSV a team receives: the contract's columns, internal ones on request, then the
    pass-through columns (everything else the state file holds)."""
    passthrough = [c for c in table.column_names if c not in HANDOFF_COLUMNS and c not in internal]
    cols = list(HANDOFF_COLUMNS)
    if with_internal:
        cols += [c for c in internal if c in table.column_names]
    frame = pl.from_arrow(table.select(cols + passthrough))
    assert isinstance(frame, pl.DataFrame)
    return frame


def template_frame(handoff: pl.DataFrame) -> pl.DataFrame:
    """The results template: one row per request, value and status left for the team."""
    return handoff.select(
        REQUEST_ID,
        SEGMENT_ID,
        "fidelity",
        pl.lit(None, dtype=pl.Float64).alias("value"),
        pl.lit(None, dtype=pl.String).alias("status"),
    )


def _add_level_hint(level: int) -> str:
    """The fix a level outside the study's suggests: a level above them may be a simulator
    the settings do not list yet; a negative one is a mistake in the file."""
    if level < 0:
        return "; levels count up from 0"
    return (
        "; if it is a simulator the study should have, add it to the levels list in settings.toml"
    )


def resolve_fidelity(
    values: pl.Series, rows: pl.Series, settings: Settings, path: Path
) -> pl.Series:
    """A results file's fidelity column as level numbers: each value may be the level's
    number (``1``, ``1.0``, ``"1"``) or its name in settings (``low1``); mixed is fine.

    A missing value, an unknown name or a number outside the configured levels is an
    InputError naming the file, the column, the row and the known levels.
    """
    names = [lv.name for lv in settings.levels]
    known = ", ".join(f"{i} = {n!r}" for i, n in enumerate(names))
    if values.dtype.is_integer() and not values.null_count():  # the common case, vectorised
        levels = values.cast(pl.Int64)
    else:
        by_name = {n: i for i, n in enumerate(names)}
        found = [_level_of(v, by_name) for v in values.to_list()]
        for value, level, row in zip(values.to_list(), found, rows.to_list(), strict=True):
            if level is None:
                got = "nothing" if value is None or str(value).strip() == "" else shown(value)
                like = [n for n in names if n.lower() == str(value).strip().lower()]
                exact = f" (names are exact: {like[0]!r})" if like and value is not None else ""
                raise InputError(
                    path,
                    f"fidelity must be an integer level or a level name, got {got}; "
                    f"known levels: {known}{exact}",
                    column="fidelity",
                    row=int(row),
                )
            if not 0 <= level < len(names):  # before an Int64 column could overflow
                raise InputError(
                    path,
                    f"fidelity {shown(value)} is not a configured level (known levels: {known})"
                    + _add_level_hint(level),
                    column="fidelity",
                    row=int(row),
                )
        levels = pl.Series("fidelity", found, pl.Int64)
    outside = (levels < 0) | (levels >= len(names))
    if outside.any():
        i = int(outside.arg_true()[0])
        raise InputError(
            path,
            f"fidelity {levels[i]} is not a configured level (known levels: {known})"
            + _add_level_hint(int(levels[i])),
            column="fidelity",
            row=int(rows[i]),
        )
    return levels.alias("fidelity")


def _level_of(value: object, by_name: dict[str, int]) -> int | None:
    if value is None or isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        return int(value) if np.isfinite(value) and value == round(value) else None
    text = str(value).strip()
    if text in by_name:  # a name wins over a number: settings may name a level "1"
        return by_name[text]
    try:
        number = float(text)
    except ValueError:
        return None
    return int(number) if np.isfinite(number) and number == round(number) else None
