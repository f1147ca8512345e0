"""Reading the user's input tables: embeddings (``embed-reduce``) and simulation results
(``ingest-results``).

Everything here checks before anything is written: a bad row is an ``InputError`` naming the
file, the column and the row, and values beyond what the model or the reducer can hold are
refused here, not discovered later as an overflow.
"""

from __future__ import annotations

import fnmatch
import json
import shlex
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from bams_cli.errors import (
    DuplicateError,
    InputError,
    SchemaError,
    shown,
)
from bams_cli.settings import Settings
from bams_cli.state import handoff as contract
from bams_cli.state import schemas
from bams_cli.state.io import (
    first_valid,
    near_miss,
    near_misses,
    read_table,
    require_columns,
    require_id_column,
)
from bams_cli.state.workspace import Workspace

SID = schemas.SEGMENT_ID


# ---------------------------------------------------------------------------------------
# embed-reduce
# ---------------------------------------------------------------------------------------
def _id_hint(id_column: str, names: list[str]) -> str:
    """ ", e.g. --id-column 'Segment ID'" when a column looks like the id one."""
    like = near_miss(id_column, names)
    return "" if like is None else f", e.g. --id-column {shlex.quote(like)}"


def embedding_layout(
    schema: pa.Schema,
    source: Path,
    *,
    id_column: str,
    columns: str | None,
    embedding_column: str | None,
    fitted_columns: list[str] | None = None,
) -> tuple[str | None, list[str]]:
    """Which column(s) hold the embedding: (list column, []) or (None, numeric columns).

    ``fitted_columns`` (with --apply) are the numeric columns the reducer was fitted on:
    they are taken by name, in the fitted order, whatever order the new file has.
    """
    if id_column not in schema.names:
        raise SchemaError(
            source,
            f"no id column {id_column!r}; found {', '.join(schema.names)} (choose it with "
            f"--id-column{_id_hint(id_column, schema.names)})",
            column=id_column,
        )
    if fitted_columns:
        missing = [c for c in fitted_columns if c not in schema.names]
        if missing:
            raise SchemaError(
                source, "embedding column the reducer was fitted on is missing", column=missing[0]
            )
        if columns:
            chosen = [n for n in schema.names if n != id_column and fnmatch.fnmatchcase(n, columns)]
            if set(chosen) != set(fitted_columns):
                raise SchemaError(
                    source,
                    f"--columns {columns!r} matches {len(chosen)} columns, the reducer was fitted on "
                    f"{len(fitted_columns)} ({', '.join(fitted_columns[:3])}, ...); drop --columns with --apply",
                )
        return None, list(fitted_columns)
    if columns:
        chosen = [n for n in schema.names if n != id_column and fnmatch.fnmatchcase(n, columns)]
        if not chosen:
            raise SchemaError(source, f"--columns {columns!r} matches no column", column=columns)
        for name in chosen:
            t = schema.field(name).type
            if not (pa.types.is_floating(t) or pa.types.is_integer(t)):
                raise SchemaError(source, f"embedding column has non-numeric type {t}", column=name)
        return None, chosen
    if embedding_column:
        if embedding_column not in schema.names:
            raise SchemaError(
                source, "no such column (see --embedding-column)", column=embedding_column
            )
        t = schema.field(embedding_column).type
        if not (pa.types.is_fixed_size_list(t) or pa.types.is_list(t) or pa.types.is_large_list(t)):
            raise SchemaError(
                source,
                f"--embedding-column must name a list column, got type {t} (numeric columns: --columns)",
                column=embedding_column,
            )
        return _numeric_list(schema, embedding_column, source), []
    lists = [
        f.name
        for f in schema
        if pa.types.is_fixed_size_list(f.type)
        or pa.types.is_list(f.type)
        or pa.types.is_large_list(f.type)
    ]
    if len(lists) != 1:
        raise SchemaError(
            source,
            "cannot tell which column holds the embedding; "
            "name a list column with --embedding-column or numeric columns with --columns 'emb_*'",
        )
    return _numeric_list(schema, lists[0], source), []


def _numeric_list(schema: pa.Schema, name: str, source: Path) -> str:
    """``name``, a list column, if its values are numbers; else a one-line SchemaError.

    Strings such as "0.25" were parsed as numbers (ten times slower, and a bad one gave an
    error naming no column or row) and booleans read as 0 and 1. Decimals stay accepted."""
    value = schema.field(name).type.value_type
    # null: every list empty or null, which the row checks name ("embedding is empty");
    # decimals are numbers, read as floats.
    if not (
        pa.types.is_floating(value)
        or pa.types.is_integer(value)
        or pa.types.is_decimal(value)
        or pa.types.is_null(value)
    ):
        raise SchemaError(
            source, f"embedding column holds lists of {value}, not numbers", column=name
        )
    return name


def batch_matrix(
    batch: pa.RecordBatch, list_col: str | None, cols: list[str], source: Path, offset: int
) -> np.ndarray:
    """Embedding rows of one record batch as float64, with bad values named by row."""
    if list_col is not None:
        arr = batch.column(list_col)
        if arr.null_count:
            row = offset + int(np.flatnonzero(arr.is_null().to_numpy(zero_copy_only=False))[0]) + 1
            raise InputError(source, "embedding is null", column=list_col, row=row)
        lengths = pc.list_value_length(arr).to_numpy(zero_copy_only=False)
        if len(lengths) and lengths[0] == 0:  # a pool with no coordinates: nothing could use it
            raise InputError(
                source, "embedding is empty (0 values)", column=list_col, row=offset + 1
            )
        if len(lengths) and (lengths != lengths[0]).any():
            row = offset + int(np.flatnonzero(lengths != lengths[0])[0]) + 1
            raise InputError(
                source,
                f"embedding has {lengths[row - offset - 1]} values, expected {lengths[0]}",
                column=list_col,
                row=row,
            )
        flat = pc.list_flatten(arr).to_numpy(zero_copy_only=False).astype(np.float64)
        M = flat.reshape(len(arr), -1) if len(arr) else np.empty((0, 0))
        bad = ~np.isfinite(M)
        if bad.any():
            r = int(np.flatnonzero(bad.any(axis=1))[0])
            raise InputError(
                source, "embedding holds a non-finite value", column=list_col, row=offset + r + 1
            )
        refuse_huge(M, source, list_col, offset)
        return M
    mats = []
    for name in cols:
        a = batch.column(name)
        v = a.to_numpy(zero_copy_only=False).astype(np.float64)
        bad = ~np.isfinite(v)
        if bad.any():
            raise InputError(
                source,
                "non-finite or missing value",
                column=name,
                row=offset + int(np.flatnonzero(bad)[0]) + 1,
            )
        refuse_huge(v[:, None], source, name, offset)
        mats.append(v)
    return np.column_stack(mats) if mats else np.empty((batch.num_rows, 0))


#: Largest magnitude accepted for an observed value: the model's variances are squares of
#: the values' spread, which overflow float64 beyond ~1.3e154 (``core.gp`` refuses a
#: spread above 1e150 too).
MAX_VALUE = 1e150
#: Largest magnitude accepted for an embedding entry: the reducer's covariance sums
#: squares over every row, so millions of rows need room below the float64 limit.
MAX_EMBEDDING = 1e100


def refuse_huge(M: np.ndarray, source: Path, column: str, offset: int) -> None:
    """InputError naming the first row with an entry beyond +-MAX_EMBEDDING."""
    huge = np.abs(M) > MAX_EMBEDDING
    if huge.any():
        r = int(np.flatnonzero(huge.any(axis=1))[0])
        raise InputError(
            source,
            f"embedding value {M[r][huge[r]][0]:.3g} is beyond +-{MAX_EMBEDDING:g}: its square "
            "overflows the reducer's covariance; rescale the embedding",
            column=column,
            row=offset + r + 1,
        )


class EmbeddingStream:
    """Restartable stream of embedding batches from one Parquet file, row groups at a time."""

    def __init__(self, path: Path, list_col: str | None, cols: list[str], batch_size: int):
        self.path, self.list_col, self.cols, self.batch_size = path, list_col, cols, batch_size
        self.read_columns = [list_col] if list_col else cols

    def __call__(self) -> Iterator[np.ndarray]:
        offset = 0
        # Read column chunks through a small buffer, without pre-buffering: by default
        # pyarrow pre-reads whole row groups' chunks ahead, and its pool grew to the size
        # of the file (2 GB for 1M x 512 float32) during one pass.
        pf = pq.ParquetFile(self.path, buffer_size=1 << 22, pre_buffer=False)
        for batch in pf.iter_batches(batch_size=self.batch_size, columns=self.read_columns):
            yield batch_matrix(batch, self.list_col, self.cols, self.path, offset)
            offset += batch.num_rows


def read_ids(path: Path, id_column: str) -> pa.Array:
    table = pq.read_table(path, columns=[id_column])
    require_id_column(table, id_column, path, "segment id")
    ids = table.column(id_column).combine_chunks()
    if pa.types.is_dictionary(ids.type):
        ids = ids.dictionary_decode()
    if ids.null_count:
        row = int(np.flatnonzero(ids.is_null().to_numpy(zero_copy_only=False))[0]) + 1
        raise InputError(path, "segment id is missing", column=id_column, row=row)
    ids = ids.cast(pa.string())
    check_unique(ids, path, id_column)
    return ids


def check_unique(ids: pa.Array, source: object, column: str, what: str = "segment id") -> None:
    s = pl.Series(ids)
    dup = s.is_duplicated()
    if dup.any():
        first = int(dup.arg_true()[0])
        value = s[first]
        second = int((s == value).arg_true()[1])
        raise DuplicateError(
            source,
            f"{what} {shown(value)} appears again (first at row {first + 1})",
            column=column,
            row=second + 1,
        )


def _first_repeat(df: pl.DataFrame, key: list[str]) -> tuple[dict, int] | None:
    """The first row (in file order, ``_row``) whose ``key`` an earlier row already has, and
    that earlier row's number; None when every key is distinct."""
    df = df.sort("_row")
    again = df.filter(~pl.struct(key).is_first_distinct())
    if not again.height:
        return None
    row = again.row(0, named=True)
    first = df.filter(pl.all_horizontal([pl.col(c) == row[c] for c in key]))["_row"][0]
    return row, int(first)


def sample_rows(stream: EmbeddingStream, take: np.ndarray) -> np.ndarray:
    """Rows ``take`` (sorted) of a stream, without holding the whole stream in memory."""
    out, offset = [], 0
    for M in stream():
        lo, hi = np.searchsorted(take, [offset, offset + len(M)])
        out.append(M[take[lo:hi] - offset])
        offset += len(M)
    return np.vstack(out)


# ---------------------------------------------------------------------------------------
# ingest-results
# ---------------------------------------------------------------------------------------
def read_results(
    path: Path, settings: Settings, ws: Workspace
) -> tuple[pl.DataFrame, pl.DataFrame]:
    """A results file as rows to ingest and rows the team marked as not run.

    Rows to ingest: ``_row``, segment_id, fidelity (a level number, resolved from a number
    or a level name), value, extra (the file's other columns as JSON), ``_keyed`` (the row
    names a request) and that request's ``_req_batch`` / ``_req_plan``. A row is keyed by
    ``request_id`` (segment_id and fidelity may then be left out, and must agree with the
    request when given) or by segment_id and fidelity. Rows whose ``status`` is neither
    empty nor ``ok`` (``crashed``, ``skipped``) say why there is no value: they are set
    aside, and their requests stay pending; such a row that carries a value anyway is
    refused. Every bad row is named.
    """
    rid_col = contract.REQUEST_ID
    table = read_table(path, what="results")
    keyed_file = rid_col in table.column_names
    if keyed_file:
        require_columns(table, ["value"], path)
    elif "value" in table.column_names and (
        SID not in table.column_names or "fidelity" not in table.column_names
    ):
        missing = [c for c in (SID, "fidelity") if c not in table.column_names]
        raise SchemaError(
            path,
            f"missing required column(s) {', '.join(map(repr, missing))}; key each result by "
            f"request_id (from the hand-off list), or by segment_id and fidelity"
            + near_misses([*missing, rid_col], table.column_names),
            column=missing[0],
        )
    else:
        require_columns(table, [SID, "fidelity", "value"], path)
    require_id_column(table, SID, path, "segment id")
    require_id_column(table, rid_col, path, "request id")
    require_id_column(table, "status", path, "status", "text such as ok or crashed")
    for name in ("fidelity", "value"):
        if name not in table.column_names:
            continue
        t = table.schema.field(name).type
        # Numbers as decimals (a SQL export), half floats, or categories (pandas) are read
        # as the numbers or level names they hold; the checks below see float64 or text.
        if pa.types.is_dictionary(t):
            t = t.value_type
        elif pa.types.is_decimal(t) or pa.types.is_float16(t):
            t = pa.float64()
        if not (
            pa.types.is_integer(t)
            or pa.types.is_floating(t)
            or pa.types.is_string(t)
            or pa.types.is_large_string(t)
            or pa.types.is_null(t)
        ):
            row, value = first_valid(table.column(name))
            raise SchemaError(
                path,
                f"expected {'a number' if name == 'value' else 'a level number or name'}, "
                f"got {shown(value)} of type {t}",
                column=name,
                row=row,
            )
        if t != table.schema.field(name).type:
            i = table.column_names.index(name)
            table = table.set_column(i, name, table.column(name).cast(t))
    if table.num_rows == 0:
        raise InputError(path, "has no rows; nothing to ingest")
    df = pl.from_arrow(table)
    assert isinstance(df, pl.DataFrame)
    if "_row" in df.columns:
        raise SchemaError(
            path, "this column name is reserved by bams-cli; rename it", column="_row"
        )
    df = df.with_row_index("_row", offset=1)
    extra_cols = [c for c in df.columns if c not in {SID, "fidelity", "value", "_row"}]
    for name in (SID, "fidelity", rid_col, "status"):
        if name not in df.columns:
            df = df.with_columns(pl.lit(None, dtype=pl.String).alias(name))

    status = pl.col("status").cast(pl.String).str.strip_chars().str.to_lowercase()
    not_run = status.is_not_null() & ~status.is_in(list(contract.STATUS_OK))
    # A status that says the run made no result beside a value it made is a contradiction,
    # and one a team falls into: "failed" or "passed" written for the system's outcome
    # (a failure is a value at or below gamma). Setting such rows aside as not run lost
    # their values, and --abandon-failed abandoned exactly the failures.
    # (Every file has a value column: keyed by request_id or by segment, it must.)
    if df.schema["value"] == pl.String:  # text: any but blank or a spelling of NaN
        text = pl.col("value").str.strip_chars().str.to_lowercase()
        has_value = text.is_not_null() & ~text.is_in(["", "nan", "-nan", "+nan", "na", "n/a"])
    else:
        value = pl.col("value").cast(pl.Float64, strict=False)
        has_value = value.is_not_null() & value.is_finite()
    both = df.filter(not_run & has_value)
    if both.height:
        first = both.row(0, named=True)
        raise InputError(
            path,
            f"status {shown(first['status'])} says the run made no result, but the row "
            f"has value {shown(first['value'])} ({both.height} such "
            f"{'row' if both.height == 1 else 'rows'}); for a run "
            "that was made leave status empty or write ok (a failure of the system is "
            "a value at or below gamma, not a status), for one that was not leave "
            "value empty",
            column="status",
            row=int(first["_row"]),
        )
    skipped = df.filter(not_run).select(
        "_row", pl.col(rid_col).cast(pl.String), pl.col(SID).cast(pl.String),
        pl.col("fidelity").cast(pl.String), pl.col("status").cast(pl.String),
    )  # fmt: skip
    df = df.filter(~not_run)

    # Requests: a row's request_id names its segment and level (and its batch or plan).
    df = df.with_columns(
        pl.col(rid_col).cast(pl.String).str.strip_chars().replace("", None).alias(rid_col)
    )
    requests = ws.requests().rename(
        {SID: "_req_sid", "fidelity": "_req_fid", "batch": "_req_batch", "plan": "_req_plan"}
    )
    df = df.join(requests, on=rid_col, how="left").sort("_row")
    df = df.with_columns(pl.col(rid_col).is_not_null().alias("_keyed"))
    unknown = df.filter(pl.col("_keyed") & pl.col("_req_sid").is_null())
    if unknown.height:
        first = unknown.row(0, named=True)
        raise InputError(
            path,
            f"request_id {shown(first[rid_col])} is not in any hand-off list ({unknown.height} unknown "
            f"in all); copy request ids from batches/batch-NNNN.csv or estimates/plan-NNNN-handoff.csv",
            column=rid_col,
            row=int(first["_row"]),
        )
    repeat = _first_repeat(df.filter(pl.col(rid_col).is_not_null()), [rid_col])
    if repeat is not None:
        again, first_row = repeat
        raise DuplicateError(
            path,
            f"request_id {shown(again[rid_col])} appears again (first at row {first_row})",
            column=rid_col,
            row=int(again["_row"]),
        )

    given_sid = df[SID].cast(pl.String)
    lacking = given_sid.is_null() & ~df["_keyed"]
    if lacking.any():
        raise InputError(
            path,
            "segment id is missing (give the row's request_id, or its segment_id and fidelity)",
            column=SID,
            row=int(df.filter(lacking)["_row"][0]),
        )
    clash = given_sid.is_not_null() & df["_keyed"] & (given_sid != df["_req_sid"])
    if clash.any():
        c = df.filter(clash).row(0, named=True)
        raise InputError(
            path,
            f"request_id {shown(c[rid_col])} is segment {c['_req_sid']!r}, but this row names "
            f"{shown(str(c[SID]))}; fix the segment_id or the request_id",
            column=SID,
            row=int(c["_row"]),
        )

    given = df["fidelity"]
    if given.dtype == pl.String:
        given = given.str.strip_chars().replace("", None)
    has_fid = given.is_not_null()
    lacking = ~has_fid & ~df["_keyed"]
    if lacking.any():
        contract.resolve_fidelity(  # raises, naming the row and the known levels
            given.filter(lacking), df["_row"].filter(lacking), settings, path
        )
    levels = df["_req_fid"].clone()
    if has_fid.any():
        resolved = contract.resolve_fidelity(
            given.filter(has_fid), df["_row"].filter(has_fid), settings, path
        )
        levels = levels.scatter(has_fid.arg_true(), resolved)
    clash = has_fid & df["_keyed"] & (levels != df["_req_fid"])
    if clash.any():
        c = df.with_columns(levels.alias("_fid")).filter(clash).row(0, named=True)
        raise InputError(
            path,
            f"request_id {shown(c[rid_col])} asks for fidelity {c['_req_fid']}, but this row gives "
            f"{shown(c['fidelity'])} (level {c['_fid']}); fix the fidelity or the request_id",
            column="fidelity",
            row=int(c["_row"]),
        )
    df = df.with_columns(
        pl.coalesce(given_sid, pl.col("_req_sid")).alias(SID), levels.alias("fidelity")
    )

    val = df["value"].cast(pl.Float64, strict=False)
    bad = val.is_null() | ~val.is_finite()
    if bad.any():
        row = int(df.filter(bad)["_row"][0])
        got = df.filter(bad)["value"][0]
        blank = got is None or str(got).strip() == ""
        hint = (
            "; fill it in, or say why there is none in the status column (e.g. crashed)"
            if blank or str(got).strip().lower() in ("nan", "-nan", "+nan")
            else ""
        )
        raise InputError(
            path,
            f"value must be a finite number, got {'nothing' if got is None else shown(got)}{hint}",
            column="value",
            row=row,
        )
    huge = val.abs() > MAX_VALUE
    if huge.any():
        row = int(df.filter(huge)["_row"][0])
        raise InputError(
            path,
            f"value {df.filter(huge)['value'][0]} is beyond +-{MAX_VALUE:g}: the model's "
            "variances (the square of the values' spread) would overflow; report the metric "
            "in larger units, or correct the value",
            column="value",
            row=row,
        )
    df = df.with_columns(val.alias("value"))

    repeat = _first_repeat(df, [SID, "fidelity"])
    if repeat is not None:
        again, first_row = repeat
        raise DuplicateError(
            path,
            f"({shown(again[SID])}, fidelity {again['fidelity']}) appears again (first at row {first_row})",
            column=SID,
            row=int(again["_row"]),
        )
    if extra_cols:
        extra = df.select(extra_cols).to_dicts()
        df = df.with_columns(
            pl.Series("extra", [json.dumps(e, default=str) for e in extra], pl.String)
        )
    else:
        df = df.with_columns(pl.lit(None, dtype=pl.String).alias("extra"))
    keep = ["_row", SID, "fidelity", "value", "extra", "_keyed", "_req_batch", "_req_plan"]
    return df.select(keep), skipped
