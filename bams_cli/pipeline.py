"""One function per subcommand: load state -> call core -> write state.

Every function validates everything it reads before it writes anything, stages its
outputs in one ``transaction`` and returns a JSON-serialisable summary (what the CLI prints
as a table, or as-is under ``--json``). Progress is reported through an optional
``progress(phase, done, total)`` callable, so this layer never imports rich.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as dt
import fnmatch
import functools
import json
import math
import sys
import zipfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from bams_cli import defaults, schemas_json
from bams_cli import stages as stages_mod
from bams_cli.errors import (
    ConflictError,
    DuplicateError,
    InputError,
    OptionError,
    PendingResultsError,
    SchemaError,
    SettingsError,
    StaleStateError,
    WorkspaceError,
    shown,
)
from bams_cli.settings import SETTINGS_FILE, Settings, levels_from_costs
from bams_cli.state import handoff as contract
from bams_cli.state import schemas
from bams_cli.state.io import (
    file_sha256,
    first_valid,
    journal_in,
    read_metadata_json,
    read_state,
    read_state_schema,
    read_table,
    recover,
    require_columns,
    require_id_column,
    stamp,
    transaction,
)
from bams_cli.state.lock import workspace_lock
from bams_cli.state.workspace import Workspace
from bams_cli.status import pending_handoffs

Progress = Callable[[str, int, int], None]
SID = schemas.SEGMENT_ID


def locked(fn: Callable[..., dict[str, Any]]) -> Callable[..., dict[str, Any]]:
    """Hold the workspace lock for the whole command: from the first read to the commit.

    A command that read the log, then waited for the lock only to write, could overwrite
    what another command appended in between; holding it throughout makes the second
    command fail at once (or wait, with ``wait=True``) before it reads anything.
    """

    @functools.wraps(fn)
    def run(root: Path, *args: Any, wait: bool = False, **kwargs: Any) -> dict[str, Any]:
        if not (Path(root) / SETTINGS_FILE).exists():
            return fn(root, *args, **kwargs)  # raises "no such workspace" without creating it
        with workspace_lock(Path(root), wait=wait), journal_in(Path(root)):
            moved = recover(Path(root))
            if moved:
                sys.stderr.write(
                    f"note: {root}: finished an interrupted command's commit ({moved} "
                    f"file{'s' if moved != 1 else ''} renamed into place)\n"
                )
            return fn(root, *args, **kwargs)

    return run


# ---------------------------------------------------------------------------------------
# init
# ---------------------------------------------------------------------------------------
def init(
    root: Path,
    *,
    gammas: list[float] | None = None,
    costs: list[float] | None = None,
    level_names: list[str] | None = None,
    seed: int | None = None,
    dim: int | None = None,
    settings_from: Path | None = None,
    force: bool = False,
    exist_ok: bool = False,
    wait: bool = False,
) -> dict[str, Any]:
    """Create a workspace and its settings file (flags > --settings-from file > defaults).

    A failure threshold is required: ``gammas`` or a ``settings_from`` file. The settings
    are built (and checked) first, so bad flags create nothing; whether the workspace
    exists is checked holding the lock, so of two concurrent inits one creates it and the
    other finds it there. With ``exist_ok`` an existing settings file holding exactly the
    requested settings is kept (``unchanged`` in the summary); one holding others is an
    error naming the differences.
    """
    if force and exist_ok:
        raise OptionError(
            "init: --force overwrites settings.toml and --exist-ok keeps it; pass one of them"
        )
    if not gammas and settings_from is None:
        raise OptionError(
            "init: no failure threshold given; pass --gamma (e.g. --gamma 0.5, comma-separated "
            "for several) or --settings-from FILE"
        )
    if Path(root).exists() and not Path(root).is_dir():
        raise WorkspaceError(f"{root}: is a file; a workspace is a folder, choose another -w")
    ws = Workspace(root)
    base = Settings()
    if settings_from is not None:
        if not settings_from.exists():
            raise InputError(settings_from, "settings file not found")
        base = Settings.from_file(settings_from)
    levels = levels_from_costs(costs, level_names) if costs else None
    settings = base.with_overrides(
        gammas=tuple(gammas) if gammas else None, levels=levels, seed=seed, embedding_dim=dim
    )
    with workspace_lock(root, wait=wait), transaction() as tx:
        if ws.settings_path.exists() and exist_ok:
            differences = _settings_differences(Settings.from_file(ws.settings_path), settings)
            if differences:
                raise SettingsError(
                    f"{ws.settings_path}: already exists with other settings "
                    f"({'; '.join(differences)}); pass the same flags as before, or --force "
                    "to overwrite it"
                )
            return {
                "workspace": str(root),
                "settings": str(ws.settings_path),
                "unchanged": True,
                **_settings_summary(settings),
            }
        if ws.settings_path.exists() and not force:
            raise WorkspaceError(
                f"{ws.settings_path}: already exists; edit it, pass --force to overwrite it, "
                "or --exist-ok to keep it when it holds these settings"
            )
        tx.write_text(ws.settings_path, settings.to_toml())
    return {
        "workspace": str(root),
        "settings": str(ws.settings_path),
        **_settings_summary(settings),
    }


def _settings_differences(existing: Settings, requested: Settings) -> list[str]:
    """Each setting that differs, as "name: X in the file, Y requested"."""

    def levels(s: Settings) -> str:
        return ", ".join(f"{lv.name} {lv.cost:g}" for lv in s.levels)

    shown = {
        "gammas": lambda s: ", ".join(f"{g:g}" for g in s.gammas),
        "levels (costs)": levels,
        "seed": lambda s: str(s.seed),
        "embedding_dim": lambda s: str(s.embedding_dim),
        "id_column": lambda s: s.id_column,
        "extra": lambda s: json.dumps(s.extra, sort_keys=True),
    }
    return [
        f"{name}: {show(existing)} in the file, {show(requested)} requested"
        for name, show in shown.items()
        if show(existing) != show(requested)
    ]


def _settings_summary(s: Settings) -> dict[str, Any]:
    return {
        "gammas": list(s.gammas),
        "levels": [{"name": lv.name, "cost": lv.cost} for lv in s.levels],
        "seed": s.seed,
        "embedding_dim": s.embedding_dim,
    }


# ---------------------------------------------------------------------------------------
# embed-reduce
# ---------------------------------------------------------------------------------------
def _embedding_layout(
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
            f"no id column {id_column!r}; found {', '.join(schema.names)} (choose it with --id-column)",
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
        return embedding_column, []
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
    return lists[0], []


def _batch_matrix(
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
        _refuse_huge(M, source, list_col, offset)
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
        _refuse_huge(v[:, None], source, name, offset)
        mats.append(v)
    return np.column_stack(mats) if mats else np.empty((batch.num_rows, 0))


#: Largest magnitude accepted for an observed value: the model's variances are squares of
#: the values' spread, which overflow float64 beyond ~1.3e154 (``core.gp`` refuses a
#: spread above 1e150 too).
MAX_VALUE = 1e150
#: Largest magnitude accepted for an embedding entry: the reducer's covariance sums
#: squares over every row, so millions of rows need room below the float64 limit.
MAX_EMBEDDING = 1e100


def _refuse_huge(M: np.ndarray, source: Path, column: str, offset: int) -> None:
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


class _EmbeddingStream:
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
            yield _batch_matrix(batch, self.list_col, self.cols, self.path, offset)
            offset += batch.num_rows


def _read_ids(path: Path, id_column: str) -> pa.Array:
    table = pq.read_table(path, columns=[id_column])
    require_id_column(table, id_column, path, "segment id")
    ids = table.column(id_column).combine_chunks()
    if pa.types.is_dictionary(ids.type):
        ids = ids.dictionary_decode()
    if ids.null_count:
        row = int(np.flatnonzero(ids.is_null().to_numpy(zero_copy_only=False))[0]) + 1
        raise InputError(path, "segment id is missing", column=id_column, row=row)
    ids = ids.cast(pa.string())
    _check_unique(ids, path, id_column)
    return ids


def _check_unique(ids: pa.Array, source: object, column: str, what: str = "segment id") -> None:
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


@locked
def embed_reduce(
    root: Path,
    source: Path,
    *,
    apply: bool = False,
    method: str = "pca",
    dim: int | None = None,
    standardize: bool = True,
    columns: str | None = None,
    embedding_column: str | None = None,
    id_column: str | None = None,
    batch_size: int = 8192,
    sample_size: int = 20_000,
    force: bool = False,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Reduce segment embeddings into the workspace pool (or, with ``apply``, add to it)."""
    from bams_cli.core.reduce import Reducer, fit_reducer  # sklearn: ~1 s to import

    if batch_size < 1 or sample_size < 1 or (dim is not None and dim < 1):
        raise WorkspaceError(
            f"--batch-size {batch_size}, --sample-size {sample_size} and --dim {dim} must be >= 1"
        )
    ws = Workspace(root)
    settings = ws.require_initialised()
    id_column = id_column or settings.id_column
    if not source.exists():
        raise InputError(source, "segments file not found")
    if source.is_dir():
        raise InputError(source, "is a folder; give the segments file itself")
    try:
        schema = pq.read_schema(source)
    except (pa.ArrowInvalid, OSError) as exc:
        raise InputError(source, f"cannot read as Parquet ({str(exc).splitlines()[0]})") from None
    request = {
        "source_sha256": file_sha256(source),
        "reduce_options": {
            "method": method,
            "dim": settings.embedding_dim if dim is None else dim,
            "standardize": standardize,
            "columns": columns,
            "embedding_column": embedding_column,
            "id_column": id_column,
        },
    }
    if not apply and not force and ws.segments_path.exists():
        # A re-run of the step that made the pool (a Makefile target, a CI retry) is a
        # no-op; a different file or other options need --force or --apply.
        made = read_metadata_json(ws.segments_path)
        if all(made.get(k) == v for k, v in request.items()):
            names = pq.read_schema(ws.segments_path).names
            return {
                "segments": str(ws.segments_path),
                "added": 0,
                "pool_size": int(pq.read_metadata(ws.segments_path).num_rows),
                "method": made.get("method"),
                "dim": made.get("dim"),
                "passthrough_columns": [
                    c for c in names if c != SID and not (c[:1] == "z" and c[1:].isdigit())
                ],
                "unchanged": True,
                "note": "the pool was already reduced from this file with these options",
            }
    layout: dict[str, Any] | None = None
    if apply:
        if not ws.reducer_path.exists():
            raise WorkspaceError(
                f"{ws.reducer_path}: no fitted reducer; run embed-reduce without --apply first"
            )
        try:
            with np.load(ws.reducer_path) as saved:
                arrays = dict(saved)
        except (OSError, ValueError, zipfile.BadZipFile) as exc:
            raise SchemaError(
                ws.reducer_path,
                f"damaged state file ({' '.join(str(exc).split())}); run embed-reduce "
                "without --apply to fit the reducer again",
            ) from None
        layout = {
            "list": str(arrays.get("layout_list", "")) or None,
            "columns": [str(c) for c in arrays.get("layout_columns", np.array([], dtype=str))],
        }
    list_col, cols = _embedding_layout(
        schema,
        source,
        id_column=id_column,
        columns=columns,
        embedding_column=embedding_column or (layout["list"] if layout else None),
        fitted_columns=layout["columns"] if layout and not layout["list"] else None,
    )
    ids = _read_ids(source, id_column)
    stream = _EmbeddingStream(source, list_col, cols, batch_size)
    n = len(ids)
    if n == 0:
        raise InputError(source, "has no rows")
    rng = np.random.default_rng(settings.seed)

    existing: pa.Table | None = None
    if apply:
        reducer = Reducer.from_arrays(arrays)
        existing = ws.read_segments()
        clash = pc.is_in(ids, value_set=existing.column(SID).combine_chunks())
        if pc.any(clash).as_py():
            row = int(np.flatnonzero(clash.to_numpy(zero_copy_only=False))[0]) + 1
            raise DuplicateError(
                source,
                f"segment id {shown(ids[row - 1].as_py())} is already in the pool",
                column=id_column,
                row=row,
            )
    else:
        if ws.segments_path.exists() and not force:
            raise WorkspaceError(
                f"{ws.segments_path}: the pool is already reduced; use --apply to add segments, "
                f"or --force to refit the reducer (coordinates change; refit the model after)"
            )
        dim = settings.embedding_dim if dim is None else dim
        # A random sample of rows (streamed, never the whole pool) trains the autoencoder
        # and measures ipca's reconstruction error. Exact PCA takes its error from the
        # eigenvalues, so it skips this pass: it reads the file twice (fit, transform).
        sample = None
        if method in ("autoencoder", "ipca"):
            take = np.sort(rng.choice(n, size=min(sample_size, n), replace=False))
            sample = _sample_rows(stream, take)
        try:
            reducer = fit_reducer(
                stream,
                method=method,  # type: ignore[arg-type]  # checked by the CLI
                dim=dim,
                standardize=standardize,
                sample=sample,
                rng=rng,
                progress=progress,  # type: ignore[arg-type]
                n_rows=n,
            )
        except ValueError as exc:
            raise InputError(source, str(exc)) from None

    expected = reducer.mean.shape[0]
    Z_parts = []
    done = 0
    for M in stream():
        if M.shape[1] != expected:
            raise InputError(
                source,
                f"embedding has {M.shape[1]} values, the reducer expects {expected}",
                column=list_col or cols[0],
            )
        Z_parts.append(reducer.transform(M))
        done += M.shape[0]
        if progress:
            progress("transform", done, n)
    Z = np.vstack(Z_parts)

    passthrough = [c for c in schema.names if c not in {id_column, list_col, *cols}]
    rest = pq.read_table(source, columns=passthrough) if passthrough else None
    out_cols: dict[str, Any] = {SID: ids}
    for j in range(Z.shape[1]):
        out_cols[f"z{j}"] = pa.array(Z[:, j])
    if rest is not None:
        for name in passthrough:
            if name in out_cols:
                raise SchemaError(
                    source, "column name is reserved for reduced coordinates", column=name
                )
            out_cols[name] = rest.column(name)
    table = pa.table(out_cols)
    if existing is not None:
        table = pa.concat_tables(
            [existing.replace_schema_metadata(None), table], promote_options="permissive"
        )
    meta = {
        "method": reducer.method,
        "dim": reducer.dim,
        "source": str(source),
        "seed": settings.seed,
        "reconstruction_error": reducer.reconstruction_error,
        **({} if apply else request),
    }
    with transaction() as tx:
        if not apply:
            saved_layout = {
                "layout_list": np.array(list_col or ""),
                "layout_columns": np.array(cols, dtype=str),
            }
            tx.write_with(ws.reducer_path, lambda p: _savez(p, reducer.to_arrays() | saved_layout))
        tx.write_parquet(ws.segments_path, schemas.SEGMENTS.conform(table, meta))
    return {
        "segments": str(ws.segments_path),
        "added": n,
        "pool_size": table.num_rows,
        "method": reducer.method,
        "dim": reducer.dim,
        "input_dim": int(expected),
        "reconstruction_error": reducer.reconstruction_error,
        "passthrough_columns": passthrough,
    }


def _savez(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)  # type: ignore[arg-type]


def _sample_rows(stream: _EmbeddingStream, take: np.ndarray) -> np.ndarray:
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
def _read_results(
    path: Path, settings: Settings, ws: Workspace
) -> tuple[pl.DataFrame, pl.DataFrame]:
    """A results file as rows to ingest and rows the team marked as not run.

    Rows to ingest: ``_row``, segment_id, fidelity (a level number, resolved from a number
    or a level name), value, extra (the file's other columns as JSON), ``_keyed`` (the row
    names a request) and that request's ``_req_batch`` / ``_req_plan``. A row is keyed by
    ``request_id`` (segment_id and fidelity may then be left out, and must agree with the
    request when given) or by segment_id and fidelity. Rows whose ``status`` is neither
    empty nor ``ok`` (``crashed``, ``skipped``) say why there is no value: they are set
    aside, and their requests stay pending. Every bad row is named.
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
            f"request_id (from the hand-off list), or by segment_id and fidelity",
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
    if df.filter(pl.col(rid_col).is_not_null()).select(rid_col).is_duplicated().any():
        rows = df.filter(pl.col(rid_col).is_not_null())
        twice = rows.filter(rows.select(rid_col).is_duplicated())
        raise DuplicateError(
            path,
            f"request_id {shown(twice[rid_col][0])} appears again (first at row {twice['_row'][0]})",
            column=rid_col,
            row=int(twice["_row"][1]),
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
        hint = (
            "; fill it in, or say why there is none in the status column (e.g. crashed)"
            if got is None or str(got).strip() == ""
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

    dup = df.select(SID, "fidelity").is_duplicated()
    if dup.any():
        rows = df.filter(dup)
        first = rows.row(0, named=True)
        again = int(rows["_row"][1])
        raise DuplicateError(
            path,
            f"({shown(first[SID])}, fidelity {first['fidelity']}) appears again (first at row {first['_row']})",
            column=SID,
            row=again,
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


@locked
def ingest_results(
    root: Path,
    source: Path,
    *,
    replace: bool = False,
    allow_unselected: bool = False,
) -> dict[str, Any]:
    """Append a simulation team's results to the observation log."""
    ws = Workspace(root)
    settings = ws.require_initialised()
    ws.require_segments()
    results, not_run = _read_results(source, settings, ws)
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
            f"; {changed.height} of its values were replaced since: pass --replace to restore them"
            if changed.height
            else ""
        )
        return {
            "ingested": 0,
            "already_ingested": True,
            "message": f"{source} was already ingested (sha256 {digest[:12]}); nothing changed"
            + since,
            "pending": _pending_summary(ws),
            "not_run": _not_run_summary(not_run),
        }

    if results.height == 0:
        return {
            "ingested": 0,
            "already_ingested": False,
            "message": f"{source}: every row's status says it was not run; nothing ingested, "
            f"those requests stay pending",
            "pending": _pending_summary(ws),
            "not_run": _not_run_summary(not_run),
        }
    pool_ids = pl.from_arrow(ws.read_segments([SID]).column(SID)).alias(SID)  # type: ignore[union-attr]
    unknown = results.filter(~pl.col(SID).is_in(pool_ids.implode()))
    if unknown.height:
        first = unknown.row(0, named=True)
        raise InputError(
            source,
            f"segment id {shown(first[SID])} is not in the pool ({unknown.height} unknown in all); "
            f"add segments with `bams-cli embed-reduce --apply`",
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
            "pending": _pending_summary(ws),
            "not_run": _not_run_summary(not_run),
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
    return {
        "ingested": new.height,
        "replaced": conflicts.height,
        "already_known": same.height,
        "already_ingested": False,
        "observations": str(ws.observations_path),
        "log_rows": combined.height,
        "by_fidelity": {int(k): int(v) for k, v in new.group_by("fidelity").len().iter_rows()},
        "pending": _pending_summary(ws),
        "not_run": _not_run_summary(not_run),
    }


def _not_run_summary(not_run: pl.DataFrame, limit: int = 20) -> dict[str, Any]:
    """Rows a results file marked as not run (a status other than ok): they stay pending."""
    return {
        "count": not_run.height,
        "first": not_run.head(limit).drop("_row").to_dicts(),
    }


def _pending_summary(ws: Workspace, limit: int = 20) -> dict[str, Any]:
    pend = ws.pending()

    def per(key: str) -> dict[int, int]:  # a plan's picks have no batch, and vice versa
        rows = pend.filter(pl.col(key).is_not_null()).group_by(key).len().sort(key)
        return {int(k): int(v) for k, v in rows.iter_rows()}

    return {
        "count": pend.height,
        "by_batch": per("batch"),
        "by_plan": per("plan"),
        "first": pend.head(limit).select(SID, "fidelity", "batch", "plan").to_dicts(),
    }


# ---------------------------------------------------------------------------------------
# simulate (sample data only)
# ---------------------------------------------------------------------------------------
def simulate(handoff: Path, truth: Path, output: Path) -> dict[str, Any]:
    """Answer a hand-off list from a ground-truth table, as a simulation team would.

    For sample data and demos only: real results come from real simulators.
    """
    dest = Path(output).resolve()
    in_state = any(Workspace(d).holds_state(dest) for d in (dest.parent, dest.parent.parent))
    if dest in (Path(handoff).resolve(), Path(truth).resolve()) or in_state:
        raise InputError(
            output, "would overwrite an input or a workspace's state; choose another -o"
        )
    picks = read_table(handoff, what="hand-off")
    require_columns(picks, [SID, "fidelity"], handoff)
    truth_t = read_table(truth, what="truth")
    require_columns(truth_t, [SID], truth)
    p = pl.from_arrow(picks)
    t = pl.from_arrow(truth_t)
    assert isinstance(p, pl.DataFrame) and isinstance(t, pl.DataFrame)
    p = p.with_row_index("_row", offset=1).with_columns(
        pl.col(SID).cast(pl.String), pl.col("fidelity").cast(pl.Int64)
    )
    t = t.with_columns(pl.col(SID).cast(pl.String))
    levels = sorted(
        int(c.split("_")[1]) for c in t.columns if c.startswith("value_") and c[6:].isdigit()
    )
    bad = p.filter(~pl.col("fidelity").is_in(levels))
    if bad.height:
        raise InputError(
            handoff,
            f"fidelity {bad['fidelity'][0]} has no value_{bad['fidelity'][0]} column in {truth}",
            column="fidelity",
            row=int(bad["_row"][0]),
        )
    long = t.unpivot(
        index=SID, on=[f"value_{lv}" for lv in levels], variable_name="fidelity", value_name="value"
    ).with_columns(pl.col("fidelity").str.slice(6).cast(pl.Int64))
    out = p.join(long, on=[SID, "fidelity"], how="left")
    missing = out.filter(pl.col("value").is_null())
    if missing.height:
        raise InputError(
            handoff,
            f"segment id {missing[SID][0]!r} is not in {truth}",
            column=SID,
            row=int(missing["_row"][0]),
        )
    # A hand-off list with request ids (state.handoff) is answered by request id too.
    keys = [contract.REQUEST_ID] if contract.REQUEST_ID in out.columns else []
    result = out.sort("_row").select(*keys, SID, "fidelity", "value")
    with transaction() as tx:
        if output.suffix.lower() == ".csv":
            tx.write_with(output, lambda path: result.write_csv(path))
        else:
            tx.write_parquet(output, result.to_arrow())
    return {
        "results": str(output),
        "rows": result.height,
        "note": "simulated from ground truth (sample data only)",
    }


# ---------------------------------------------------------------------------------------
# fit
# ---------------------------------------------------------------------------------------
def _training_data(
    ws: Workspace, ids: np.ndarray, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Active observations as (pool index, level, value) arrays."""
    obs = ws.read_observations()
    pend = ws.pending() if obs.height == 0 else None
    if pend is not None and pend.height:
        raise PendingResultsError(
            f"{ws.observations_path}: no observations yet, {pend.height} picks await results; "
            f"simulate {' and '.join(pending_handoffs(ws, pend))} and run "
            f"`bams-cli ingest-results -w {ws.root} RESULTS.parquet`, then fit"
        )
    if obs.height == 0:
        raise WorkspaceError(
            f"{ws.observations_path}: no observations yet; select a first batch "
            f"(`bams-cli select -w {ws.root} --strategy random`), simulate it and ingest the results"
        )
    index = pl.DataFrame({SID: ids, "_idx": np.arange(len(ids))})
    joined = obs.join(index, on=SID, how="left")
    missing = joined.filter(pl.col("_idx").is_null())
    if missing.height:
        raise WorkspaceError(
            f"{ws.observations_path}: segment {missing[SID][0]!r} is no longer in the pool "
            f"({missing.height} observations in all); re-add it with `embed-reduce --apply`"
        )
    return (
        joined["_idx"].to_numpy().astype(np.int64),
        joined["fidelity"].to_numpy().astype(np.int64),
        joined["value"].to_numpy().astype(np.float64),
    )


def load_posterior(ws: Workspace, settings: Settings, ids: np.ndarray, X: np.ndarray):  # noqa: ANN201
    """The fitted model, conditioned again on the log it was fitted on (cheap: one Cholesky).

    The posterior is of the transformed metric g(y) (model.json's ``transform``); g maps
    the first gamma to itself, so ``select`` compares against it unchanged.
    """
    from bams_cli.core.gp import Hyperparameters, fit_mfgp

    model = ws.require_fresh_model()
    idx, lv, y = _training_data(ws, ids, X)
    try:
        hp = Hyperparameters.from_dict(model["hyperparameters"])
        if hp.n_levels != settings.n_levels or hp.d != X.shape[1]:
            raise ValueError(
                f"they are for {hp.n_levels} levels and d = {hp.d}, the study has "
                f"{settings.n_levels} levels and d = {X.shape[1]}"
            )
    except (KeyError, ValueError, TypeError) as exc:
        what = f"missing key {exc}" if isinstance(exc, KeyError) else str(exc)
        raise InputError(
            ws.model_path,
            f"hyperparameters: {what.removeprefix('Hyperparameters: ')}; rewrite it with "
            f"`bams-cli fit -w {ws.root} --force`",
        ) from None
    g = _model_transform(ws, model)
    return fit_mfgp(
        X[idx], lv, g.forward(y), settings.n_levels, rng=np.random.default_rng(settings.seed),
        fixed=hp,
    ), model  # fmt: skip


def _model_transform(ws: Workspace, model: dict[str, Any]):  # noqa: ANN202
    """The output transform a model.json records (the identity for older models)."""
    from bams_cli.core.gp import OutputTransform

    try:
        return OutputTransform.from_dict(model.get("transform"))
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(
            ws.model_path, f"transform: {exc}; rewrite it with `bams-cli fit -w {ws.root}`"
        ) from None


@locked
def fit(
    root: Path,
    *,
    fixed_hyperparameters: Path | None = None,
    restarts: int = 8,
    chunk_size: int = 50_000,
    transform: str = defaults.TRANSFORM,
    force: bool = False,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Train the multifidelity GP on the observation log and score every pool segment.

    ``transform`` is "auto" (model g(y) = c + s asinh((y - c)/s), c the first gamma, with
    s chosen by evidence among the identity and a few scales: ``core.gp.transform``) or
    "none". With ``fixed_hyperparameters`` the file's own transform is used.

    A model already fitted the same way on the same log is kept, and nothing is written
    (``up_to_date`` in the summary; ``_fit_up_to_date``), unless ``force``.
    """
    from bams_cli.core.gp import GPFitError, Hyperparameters, OutputTransform, fit_transformed
    from bams_cli.core.gp.checks import check_model

    if restarts < 1 or chunk_size < 1:
        raise WorkspaceError(f"--restarts {restarts} and --chunk-size {chunk_size} must be >= 1")
    if transform not in TRANSFORMS:
        raise WorkspaceError(f"--transform {transform!r}: choose one of {', '.join(TRANSFORMS)}")
    chosen = None if transform == "auto" else OutputTransform()
    ws = Workspace(root)
    settings = ws.require_initialised()
    if not force and fixed_hyperparameters is None:
        kept = _fit_up_to_date(ws, settings, restarts=restarts, transform=transform)
        if kept is not None:
            return kept
    ids, X = ws.read_pool()
    idx, lv, y = _training_data(ws, ids, X)
    fixed = None
    if fixed_hyperparameters is not None:
        try:
            doc = json.loads(Path(fixed_hyperparameters).read_text())
            fixed = Hyperparameters.from_dict(doc.get("hyperparameters", doc))
            chosen = OutputTransform.from_dict(doc.get("transform"))
        except FileNotFoundError:
            raise InputError(fixed_hyperparameters, "hyperparameter file not found") from None
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise InputError(fixed_hyperparameters, f"not a hyperparameter file ({exc})") from None
        if fixed.lengthscales0.shape[0] != X.shape[1] or fixed.noise.shape[0] != settings.n_levels:
            raise InputError(
                fixed_hyperparameters,
                f"hyperparameters are for d = {fixed.lengthscales0.shape[0]}, {fixed.noise.shape[0]} "
                f"levels; the study has d = {X.shape[1]}, {settings.n_levels} levels",
            )
    rng = np.random.default_rng(settings.seed)
    if progress:
        progress("fit", 0, 1)
    try:
        model, g, evidence = fit_transformed(
            X[idx], lv, y, settings.n_levels, centre=float(settings.gammas[0]), rng=rng,
            restarts=restarts, transform=chosen, fixed=fixed,
        )  # fmt: skip
    except GPFitError as exc:
        raise WorkspaceError(f"fit: {exc}") from None
    model_gammas = g.forward(np.asarray(settings.gammas, dtype=np.float64))
    if progress:
        progress("fit", 1, 1)

    n = len(ids)
    mu = np.empty(n)
    sd = np.empty(n)
    p = np.empty((n, len(settings.gammas)))
    for start in range(0, n, chunk_size):
        stop = min(start + chunk_size, n)
        mu[start:stop], sd[start:stop], p[start:stop] = model.score(
            X[start:stop], model_gammas, chunk_size
        )
        if progress:
            progress("score pool", stop, n)

    checks = check_model(model, idx)
    warnings = [
        *model.notes,
        *checks.warnings,
        *_contradicted_outcomes(ids, idx, lv, y, p, settings.gammas),
    ]
    obs_hash = ws.observations_hash()
    hp = model.hyperparameters
    doc = {
        "hyperparameters": hp.to_dict(),
        "log_marginal_likelihood": float(model.log_marginal_likelihood),
        "log_posterior": float(model.log_posterior),
        "n_observations_per_level": [int(c) for c in model.n_obs_per_level],
        "observations_hash": obs_hash,
        "pool": ws.pool_fingerprint(),
        "units": "outputscale0, outputscales and noise are variances; lengthscales and mean in the metric's units",
        "trained": fixed is None,
        "restarts": restarts,
        "seed": settings.seed,
        "gammas": list(settings.gammas),
        "fitted_at": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "jitter": float(model.jitter),
        "transform": g.to_dict(),
        "transform_option": transform,
        "transform_evidence": [
            {
                "scale": None if math.isinf(e["scale"]) else e["scale"],
                "log_evidence": e["log_evidence"],
            }
            for e in evidence
        ],
        "checks": checks.to_dict(),
        "warnings": warnings,
    }
    cols: dict[str, Any] = {SID: pa.array(ids, pa.string()), "mu": mu, "sd": sd}
    for j in range(p.shape[1]):
        cols[f"p_{j}"] = p[:, j]
    meta = {"observations_hash": obs_hash, "gammas": list(settings.gammas), "seed": settings.seed}
    # A snapshot of p_n after every batch feeds the report's per-batch retention-recall.
    # It is taken only when the newest results belong to a batch: a refit after ingesting
    # an estimate plan's results must not pass for the model "after batch b".
    log = ws.read_observations(active_only=False)  # append-only: the last rows are the newest
    newest = log.filter(pl.col("source_sha256") == log["source_sha256"][-1])["batch"]
    snapshot_batch = None
    if newest.len() and newest.null_count() == 0:
        snapshot_batch = int(newest.max())  # type: ignore[arg-type]
    history = pa.table({f"p_{g}": p[:, g] for g in range(p.shape[1])})
    with transaction() as tx:
        tx.write_text(ws.model_path, json.dumps(doc, indent=2) + "\n")
        tx.write_parquet(ws.scores_path, schemas.SCORES.conform(pa.table(cols), meta))
        if snapshot_batch is not None:
            snapshot = ws.history_dir / f"scores-after-batch-{snapshot_batch:04d}.parquet"
            tx.write_parquet(snapshot, stamp(history, schemas.SCORES.version, meta))
    return {
        "model": str(ws.model_path),
        "scores": str(ws.scores_path),
        "observations": int(len(y)),
        "n_observations_per_level": doc["n_observations_per_level"],
        "log_marginal_likelihood": doc["log_marginal_likelihood"],
        "log_posterior": doc["log_posterior"],
        "hyperparameters": doc["hyperparameters"],
        "checks": doc["checks"],
        "jitter": doc["jitter"],
        "transform": doc["transform"],
        "gp_rate_estimate": {str(g): float(p[:, i].mean()) for i, g in enumerate(settings.gammas)},
        "warnings": warnings,
    }


def _fit_up_to_date(
    ws: Workspace, settings: Settings, *, restarts: int, transform: str
) -> dict[str, Any] | None:
    """The summary of the model in ``model.json`` if fitting now would redo it, else None.

    Redoing it means: trained (not ``--fixed-hyperparameters``) on the current observation
    log and pool, with scores from that fit (``Workspace.require_model``), for the same
    gammas, seed and number of levels, with the same ``--restarts`` and ``--transform``.
    ``--chunk-size`` only bounds memory, so it does not count.
    """
    if not ws.model_path.exists() or not ws.segments_path.exists():
        return None
    try:
        model = ws.require_model(allow_newer_observations=True)
    except (StaleStateError, SchemaError):  # damaged, another pool, scores from another fit
        return None
    n_obs = model.get("n_observations_per_level")
    same = (
        model["fresh"]
        and model.get("trained") is True
        and model.get("restarts") == restarts
        and model.get("transform_option") == transform
        and model.get("gammas") == list(settings.gammas)
        and model.get("seed") == settings.seed
        and isinstance(n_obs, list)
        and len(n_obs) == settings.n_levels
    )
    if not same:
        return None
    _, _, _, p = _read_scores(ws, len(settings.gammas))
    n = int(np.sum(n_obs or []))
    return {
        "up_to_date": True,
        "message": f"model is up to date (fitted on {n} observations); nothing to do "
        f"(pass --force to fit again)",
        "model": str(ws.model_path),
        "scores": str(ws.scores_path),
        "observations": n,
        **{
            k: model.get(k)
            for k in (
                "n_observations_per_level",
                "log_marginal_likelihood",
                "log_posterior",
                "hyperparameters",
                "checks",
                "jitter",
                "transform",
            )
        },
        "gp_rate_estimate": {str(g): float(p[:, i].mean()) for i, g in enumerate(settings.gammas)},
        "warnings": model.get("warnings", []),
    }


#: Output transforms ``fit --transform`` accepts.
TRANSFORMS = ("auto", "none")


#: p_n below this at an observed level-0 failure (or 1 - p_n below it at an observed
#: non-failure) means the model contradicts what was measured.
CONTRADICTION = 0.01


def _contradicted_outcomes(
    ids: np.ndarray,
    idx: np.ndarray,
    lv: np.ndarray,
    y: np.ndarray,
    p: np.ndarray,
    gammas: Sequence[float],
) -> list[str]:
    """Observed level-0 outcomes the fitted model is nearly sure did not happen.

    A fit that explains level-0 results as noise (large level-0 noise, or the data handed to
    the discrepancy) gives p_n ~ 0 at segments seen failing. The rate estimate then samples
    the failures like them with tiny probability and its variance explodes, so say so.
    """
    out = []
    level0 = lv == 0
    for g, gamma in enumerate(gammas):
        pn = p[idx[level0], g]
        val = y[level0]
        for failed, doubt, what in (
            (val <= gamma, pn, "failing"),
            (val > gamma, 1.0 - pn, "not failing"),
        ):
            bad = np.flatnonzero(failed & (doubt < CONTRADICTION))
            if bad.size == 0:
                continue
            worst = bad[np.argmin(doubt[bad])]
            out.append(
                f"gamma {gamma:g}: {bad.size} of {int(failed.sum())} segments observed "
                f"{what} at level 0 get probability < {CONTRADICTION:g} of that outcome "
                f"(worst {ids[idx[level0][worst]]!r}: value {val[worst]:.4g}, "
                f"p_n {pn[worst]:.2g}); the model explains them as noise, so the estimate's "
                "variance may be large. Check the level-0 noise in the hyperparameter table; "
                "more level-0 runs near them help"
            )
    return out


# ---------------------------------------------------------------------------------------
# select
# ---------------------------------------------------------------------------------------
MODEL_STRATEGIES = ("bams", "bas")
STRATEGIES = ("bams", "bas", "random", "mc-gp", "mcm-gp", "ds", "ds-gp", "ce")


@contextlib.contextmanager
def _memory_limit_is_an_option() -> Iterator[None]:
    """select_batch's refusal of a cluster too large for memory, as a one-line error."""
    try:
        yield
    except ValueError as exc:
        if "GiB" not in str(exc):
            raise
        raise OptionError(f"select: {str(exc).replace('n_clusters', '--clusters')}") from None


def _existing_batch(
    ws: Workspace, batch: int, asked: dict[str, Any], n_levels: int
) -> dict[str, Any] | None:
    """``select --batch N``: N's summary if it exists with these options, None if N is next."""
    from bams_cli.state.handoff import template_path

    numbers = ws.batch_numbers()
    following = (numbers or [0])[-1] + 1
    if batch not in numbers:
        if batch != following:
            raise OptionError(
                f"--batch {batch}: the next batch is {following}"
                + (f" (batches {numbers[0]}..{numbers[-1]} exist)" if numbers else "")
            )
        return None
    path = schemas.batch_path(ws.root, batch)
    made = read_metadata_json(path).get("options") or {}
    differ = [
        f"{k} {made[k]!r} there, {v!r} asked"
        for k, v in asked.items()
        if k in made and made[k] != v
    ]
    if differ:
        raise OptionError(
            f"{path}: batch {batch} exists with other options ({'; '.join(differ)}); "
            f"pass the same options, or --batch {following} for a new batch"
        )
    df = ws.read_batch(batch)
    level = df["fidelity"].to_numpy()
    purpose = df["purpose"].to_list() if "purpose" in df.columns else ["discover"] * df.height
    csv = path.with_suffix(".csv")
    return {
        "batch": batch,
        "handoff": str(path),
        "handoff_csv": str(csv),
        "results_template": str(template_path(csv)),
        "strategy": str(made.get("strategy", asked["strategy"])),
        "picks": df.height,
        "total_cost": math.fsum(df["cost"].to_list()),
        "budget": float(made.get("budget", asked["budget"])),
        "picks_per_level": {lv: int((level == lv).sum()) for lv in range(n_levels)},
        "picks_per_cluster": {
            int(c): int((df["cluster"] == c).sum()) for c in df["cluster"].unique().sort()
        },
        "confirm_picks": sum(p != "discover" for p in purpose),
        "confirm_leads": sum(p == "confirm lead" for p in purpose),
        "j_before": None,
        "j_after": None,
        "timings_s": {},
        "unchanged": True,
    }


def _cheap_leads(ws: Workspace, ids: np.ndarray, gamma: float) -> np.ndarray:
    """Segments seen at or below gamma at some cheap level (a lead until level 0 confirms)."""
    obs = ws.read_observations().filter((pl.col("fidelity") > 0) & (pl.col("value") <= gamma))
    return np.isin(ids, obs[SID].to_numpy())


def _observed_level0(ws: Workspace, ids: np.ndarray) -> np.ndarray:
    obs = ws.read_observations().filter(pl.col("fidelity") == 0)
    return np.isin(ids, obs[SID].to_numpy())


# Columns of the state files that only bams-cli reads: the CSV hand-off leaves them out.
BATCH_INTERNAL = ("delta_j", "cluster", "rank", "strategy")
PLAN_INTERNAL = ("stratum", "pi", "draws", "q", "prob", "p_n")


def _passthrough_columns(ws: Workspace, index: np.ndarray, taken: dict[str, Any]) -> dict[str, Any]:
    """The pool's pass-through columns (scenario tags ...) for the picked rows. A column
    named like one of the hand-off's own, or the results' (value, status), is left out:
    the contract's meaning wins."""
    reserved = {SID, *taken, *BATCH_INTERNAL, *PLAN_INTERNAL, *contract.TEMPLATE_COLUMNS}
    coords = set(ws.coordinate_columns())
    names = [
        c
        for c in read_state_schema(ws.segments_path).names
        if c not in coords and c not in reserved
    ]
    if not names:
        return {}
    rows = ws.read_segments([SID, *names]).take(pa.array(np.asarray(index, np.int64)))
    return {name: rows.column(name) for name in names}


def _write_handoff(
    tx: Any, table: pa.Table, csv: Path, internal: tuple[str, ...], with_internal: bool
) -> tuple[Path, Path]:
    """Stage a hand-off CSV and its results template (``state.handoff``) in ``tx``."""
    frame = contract.handoff_frame(table, internal, with_internal=with_internal)
    template = contract.template_path(csv)
    tx.write_with(csv, lambda p: frame.write_csv(p))
    tx.write_with(template, lambda p: contract.template_frame(frame).write_csv(p))
    return csv, template


def _check_out(out: Path) -> Path:
    """``select --out PATH``: a file path outside the workspace's own state files."""
    out = Path(out)
    if out.is_dir():
        raise OptionError(f"--out {out}: is a folder; give a file name such as {out / 'batch.csv'}")
    return out


def _pending_mask(ws: Workspace, ids: np.ndarray, n_levels: int, pend: pl.DataFrame) -> np.ndarray:
    """bool (N, n_levels): True at the pool's (segment, level) pairs awaiting results."""
    out = np.zeros((len(ids), n_levels), bool)
    if pend.height:
        pos = pl.DataFrame({SID: ids, "_i": np.arange(len(ids))})
        rows = pend.join(pos, on=SID).filter(pl.col("fidelity") < n_levels)
        out[rows["_i"].to_numpy(), rows["fidelity"].to_numpy()] = True
    return out


def _copy_handoff_if_needed(csv: Path, out: Path) -> bool:
    """``select --batch N --out PATH`` re-run: (re)write PATH as a copy of batch N's hand-off
    when it is missing or differs; an identical PATH is left alone (Make sees it up to
    date). Returns whether PATH was written."""
    data = csv.read_bytes()
    if out.exists() and out.read_bytes() == data:
        return False
    with transaction() as tx:
        tx.write_bytes(out, data)
    return True


@locked
def select(
    root: Path,
    *,
    strategy: str = "bams",
    budget: float = 5.0,
    clusters: int = 6,
    overbudget: float = 2.0,
    pooling: str = "global",
    mixed_fidelity: bool = False,
    level0_share: float = 0.5,
    confirm_share: float = defaults.CONFIRM_SHARE,
    difficulty_column: str = "difficulty",
    allow_pending: bool = False,
    include_observed: bool = False,
    workers: int | None = None,
    scheduler: str | None = None,
    handoff_internal: bool = False,
    batch: int | None = None,
    retry_abandoned: bool = False,
    out: Path | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Pick the next batch of (segment, fidelity) simulations and write the hand-off list.

    ``batch`` names the batch this call makes, a stable target for Make: when it exists
    already with the same options the call is a no-op (``unchanged``); when it exists with
    other options, or is not the next number, it is an error naming the next one.

    ``out`` is a second, stable path for the batch's CSV hand-off (byte for byte the one in
    ``batches/``), written in the same transaction; a no-op ``batch`` re-run rewrites it
    when it is missing or differs.

    The Parquet state file holds every column; the CSV hand-off and its results template
    follow the contract in ``state.handoff`` (internal columns only with
    ``handoff_internal``).

    For ``strategy="bams"`` in a study with cheap levels, ``confirm_share`` of the budget
    first buys level-0 runs of unconfirmed cheap-level failures (leads), then of the
    likeliest failures whose level 0 is unknown (``core.confirm``); the greedy spends the
    rest.
    """
    from bams_cli.core import baselines
    from bams_cli.core.confirm import confirmation_picks, n_confirmations
    from bams_cli.core.select import select_batch
    from bams_cli.parallel import executor

    if strategy not in STRATEGIES:
        raise WorkspaceError(f"--strategy {strategy!r}: choose one of {', '.join(STRATEGIES)}")
    if pooling not in ("global", "raw"):
        raise WorkspaceError(f"--pooling {pooling!r}: choose global or raw")
    if clusters < 1 or not overbudget >= 1:
        raise WorkspaceError(
            f"--clusters {clusters} must be >= 1 and --overbudget {overbudget} >= 1"
        )
    if not 0 <= level0_share <= 1:
        raise WorkspaceError(f"--level0-share {level0_share}: must lie in [0, 1]")
    if not 0 <= confirm_share <= 1:
        raise WorkspaceError(f"--confirm-share {confirm_share}: must lie in [0, 1]")
    if not (budget > 0 and np.isfinite(budget)):
        raise WorkspaceError(
            f"--budget {budget}: must be > 0 (cost units; one level-0 run costs 1)"
        )
    ws = Workspace(root)
    settings = ws.require_initialised()
    ids, X = ws.read_pool()
    if budget / min(settings.costs) > len(ids) * settings.n_levels:
        raise WorkspaceError(
            f"--budget {budget}: buys more simulations than the pool has "
            f"({len(ids)} segments x {settings.n_levels} levels)"
        )
    # The options that decide the picks: recorded in the batch, compared by --batch.
    asked = {
        "strategy": strategy,
        "budget": budget,
        "clusters": clusters,
        "overbudget": overbudget,
        "pooling": pooling,
        "mixed_fidelity": mixed_fidelity,
        "level0_share": level0_share,
        "confirm_share": confirm_share,
    }
    if out is not None:
        out = _check_out(out)
    if batch is not None:
        done = _existing_batch(ws, batch, asked, settings.n_levels)
        if done is not None:
            if out is not None:
                _copy_handoff_if_needed(Path(done["handoff_csv"]), out)
                done["out"] = str(out)
            return done
    pend = ws.pending()
    if pend.height and not allow_pending:
        where = [f"batch {b}" for b in sorted(set(pend["batch"].drop_nulls().to_list()))]
        where += [f"estimate plan {p}" for p in sorted(set(pend["plan"].drop_nulls().to_list()))]
        raise PendingResultsError(
            f"{ws.root}: {pend.height} picks of {', '.join(where)} have no results yet; "
            f"ingest them with `bams-cli ingest-results`, or pass --allow-pending"
        )
    number = (ws.batch_numbers() or [0])[-1] + 1
    rng = np.random.default_rng([settings.seed, number])
    costs = np.asarray(settings.costs)
    observed0 = _observed_level0(ws, ids)
    exclude = np.zeros(len(ids), bool) if include_observed else observed0
    # Abandoned runs (bams_cli.abandon) are done: never offered again unless asked.
    gone = np.zeros((len(ids), settings.n_levels), bool)
    if not retry_abandoned:
        from bams_cli.abandon import abandoned_mask

        gone = abandoned_mask(ws, ids, settings.n_levels)
    # Pending picks (--allow-pending) are in the batch already: never picked again, and the
    # BAMS greedy is conditioned on them. Their results land under the batch that asked.
    waiting = _pending_mask(ws, ids, settings.n_levels, pend)
    exclude = exclude | gone[:, 0] | waiting[:, 0]
    model_hash = None
    j_before = j_after = None
    timings: dict[str, float] = {}
    selection_plan: dict[str, Any] | None = None  # core.select.plan_selection, as taken

    purpose: np.ndarray | None = None
    if strategy in MODEL_STRATEGIES:
        posterior, model = load_posterior(ws, settings, ids, X)
        model_hash = model["observations_hash"]
        confirm, is_lead = np.zeros(0, np.int64), np.zeros(0, bool)
        if strategy == "bams" and settings.n_levels > 1:
            k = n_confirmations(budget, float(costs[0]), confirm_share)
            if k:
                _, _, _, p_all = _read_scores(ws, len(settings.gammas))
                confirm, is_lead = confirmation_picks(
                    p_all[:, 0], _cheap_leads(ws, ids, settings.gammas[0]), exclude, k
                )
        rest = budget - float(costs[0]) * len(confirm)
        taken0 = observed0.copy()
        taken0[confirm] = True
        result = None
        if rest >= costs.min() - 1e-12:
            with executor(workers, scheduler) as pool, _memory_limit_is_an_option():
                result = select_batch(
                    posterior,
                    X,
                    gamma=settings.gammas[0],
                    costs=list(settings.costs),
                    budget=rest,
                    n_clusters=clusters,
                    overbudget=overbudget,
                    observed_level0_mask=taken0,
                    pooling=pooling,  # type: ignore[arg-type]
                    executor=pool,
                    rng=rng,
                    progress=progress,
                    levels=[0] if strategy == "bas" else None,
                    reobserve_level0=include_observed,
                    excluded_pairs=gone,
                    pending_pairs=waiting if waiting.any() else None,
                )
        n_greedy = 0 if result is None else len(result.index)
        picks = {
            "index": np.concatenate([confirm, result.index if result else []]).astype(np.int64),
            "level": np.concatenate(
                [np.zeros(len(confirm)), result.level if result else []]
            ).astype(np.int64),
            "delta_j": np.concatenate(
                [np.full(len(confirm), np.nan), result.delta_j if result else []]
            ),
            "cluster": np.concatenate(
                [np.full(len(confirm), -1), result.cluster if result else []]
            ).astype(np.int64),
        }
        purpose = np.array(
            [("confirm lead" if lead else "confirm likely") for lead in is_lead]
            + ["discover"] * n_greedy,
            dtype=object,
        )
        if result is not None:
            j_before, j_after = float(result.j_before), float(result.j_after)
            timings = {k: round(float(v), 3) for k, v in result.timings.items()}
            selection_plan = result.plan
    else:
        multi = strategy == "mcm-gp" or (strategy == "random" and mixed_fidelity)
        n_rest = settings.n_levels - 1
        shares = [level0_share] + [(1 - level0_share) / n_rest] * n_rest if n_rest else None
        if strategy in ("random", "mc-gp", "mcm-gp"):
            index, level = baselines.pick_uniform(
                len(ids),
                list(settings.costs),
                budget,
                rng=rng,
                mixed=multi and n_rest > 0,
                observed_level0_mask=exclude,
                level_shares=shares,
            )
        elif strategy in ("ds", "ds-gp"):
            table = ws.read_segments()
            if difficulty_column not in table.column_names:
                raise WorkspaceError(
                    f"{ws.segments_path}: --strategy {strategy} needs a difficulty column "
                    f"{difficulty_column!r} (pass it through embed-reduce, or name it with --difficulty-column)"
                )
            difficulty = (
                table.column(difficulty_column).to_numpy(zero_copy_only=False).astype(np.float64)
            )
            if not np.isfinite(difficulty).all():
                row = int(np.flatnonzero(~np.isfinite(difficulty))[0]) + 1
                raise InputError(
                    ws.segments_path, "difficulty must be finite", column=difficulty_column, row=row
                )
            index, level = baselines.pick_difficulty(
                difficulty, list(settings.costs), budget, rng=rng, observed_level0_mask=exclude
            )
        else:  # ce
            obs = ws.read_observations().filter(pl.col("fidelity") == 0)
            pos = pl.DataFrame({SID: ids, "_i": np.arange(len(ids))})
            o = obs.join(pos, on=SID).select("_i", "value")
            index, level = baselines.pick_cross_entropy(
                X, o["_i"].to_numpy(), o["value"].to_numpy(), list(settings.costs), budget, rng=rng
            )
        keep = ~(gone | waiting)[np.asarray(index, np.int64), np.asarray(level, np.int64)]
        index, level = np.asarray(index)[keep], np.asarray(level)[keep]
        picks = {
            "index": np.asarray(index, np.int64),
            "level": np.asarray(level, np.int64),
            "delta_j": np.full(len(index), np.nan),
            "cluster": np.zeros(len(index), np.int64),
        }

    k = len(picks["index"])
    if k == 0:
        raise WorkspaceError(
            f"select: nothing fits budget {budget} (cheapest level costs {costs.min():g}); raise --budget"
        )
    cols: dict[str, Any] = contract.contract_columns(
        "batch",
        number,
        ids[picks["index"]],
        picks["level"],
        settings,
        list(purpose) if purpose is not None else ["discover"] * k,
    )
    cols |= {
        "delta_j": picks["delta_j"],
        "cluster": picks["cluster"],
        "rank": np.arange(k, dtype=np.int64),
        "strategy": [strategy] * k,
    }
    cols |= _passthrough_columns(ws, picks["index"], taken=cols)
    options = {
        **asked,
        "include_observed": include_observed,
        "allow_pending": allow_pending,
        "retry_abandoned": retry_abandoned,
        "difficulty_column": difficulty_column,
        "workers": workers,
        "scheduler": scheduler,
        "gamma": settings.gammas[0],
    }
    meta = {
        "batch": number,
        "seed": settings.seed,
        "model_hash": model_hash or "",
        "options": options,
    }
    table = schemas.BATCH.conform(pa.table(cols), meta)
    path = schemas.batch_path(ws.root, number)
    with transaction() as tx:
        tx.write_parquet(path, table)
        csv, template = _write_handoff(
            tx, table, path.with_suffix(".csv"), BATCH_INTERNAL, handoff_internal
        )
        if out is not None:
            frame = contract.handoff_frame(table, BATCH_INTERNAL, with_internal=handoff_internal)
            tx.write_with(out, lambda p: frame.write_csv(p))
    per_level = {int(lv): int((picks["level"] == lv).sum()) for lv in range(settings.n_levels)}
    per_cluster = {int(c): int((picks["cluster"] == c).sum()) for c in np.unique(picks["cluster"])}
    return {
        "batch": number,
        "handoff": str(path),
        "handoff_csv": str(csv),
        "results_template": str(template),
        "strategy": strategy,
        "picks": k,
        "total_cost": math.fsum(costs[picks["level"]].tolist()),
        "budget": budget,
        "picks_per_level": per_level,
        "picks_per_cluster": per_cluster,
        "confirm_picks": int(np.sum(purpose != "discover")) if purpose is not None else 0,
        "confirm_leads": int(np.sum(purpose == "confirm lead")) if purpose is not None else 0,
        "j_before": j_before,
        "j_after": j_after,
        "timings_s": timings,
        **({"selection_plan": selection_plan} if selection_plan is not None else {}),
        **({"out": str(out)} if out is not None else {}),
    }


# ---------------------------------------------------------------------------------------
# estimate (plan -> simulate -> compute)
# ---------------------------------------------------------------------------------------
_plan_numbers = stages_mod.plan_numbers


def _read_scores(
    ws: Workspace, n_gammas: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    t = schemas.SCORES.check(read_state(ws.scores_path), ws.scores_path)
    p = np.column_stack([t.column(f"p_{g}").to_numpy() for g in range(n_gammas)])
    ids = t.column(SID).to_numpy(zero_copy_only=False)
    return ids, t.column("mu").to_numpy(), t.column("sd").to_numpy(), p


@locked
def estimate_plan(
    root: Path,
    *,
    samples: float | None = None,
    alpha: float = defaults.ALPHA,
    defensive: float = defaults.DEFENSIVE,
    design: str = "poisson",
    weighting: str = "auto",
    stages: int = defaults.STAGES,
    stage1_share: float = defaults.STAGE1_SHARE,
    new_series: bool = False,
    seed: int | None = None,
    handoff_internal: bool = False,
    allow_pending: bool = False,
) -> dict[str, Any]:
    """Plan one stage of the rate-estimation sample: inclusion probabilities and the hand-off.

    The estimate runs in ``stages`` stages (``core.design``, ``stages``): the first plan of
    a series fixes the total budget K (``samples``) and the stages' weights, and spends
    ``stage1_share`` of K; each later call, once the previous stage's results are in and
    the model refitted on them, draws the next stage with the rest. Every stage's design
    comes from the model checked against the level-0 outcomes of every finished plan
    (``weighting="auto"``): the candidate with the smallest predicted variance among
    uniform, the calibrated design and the paper's p^alpha form. ``weighting`` "uniform"
    or "p-alpha" (with ``alpha``, ``defensive``) forces one; designs "fixed" and
    "with-replacement" are single-stage p^alpha plans, as the paper's.

    While an earlier plan awaits results this refuses (exit code 3, so a Makefile re-run
    does not draw a second plan); ``allow_pending`` draws another anyway.

    The draw is seeded by the study seed and the plan's number (so re-running a study
    reproduces its plans), or by ``seed`` alone when given: the same seed then gives the
    same plan from the same scores, and another seed a fresh one, without editing the
    settings. The seed and the random stream are recorded in the plan's metadata.
    """
    st = stages_mod  # the series and the evidence of finished plans
    from bams_cli.core import design as dz
    from bams_cli.core.estimate import (
        DESIGNS,
        gp_estimate,
        inclusion_probabilities,
        max_failure_weight,
        model_weight,
        plan_sample,
    )

    if design not in DESIGNS:
        raise WorkspaceError(f"--design {design!r}: choose one of {', '.join(DESIGNS)}")
    if weighting not in WEIGHTINGS:
        raise WorkspaceError(f"--weighting {weighting!r}: choose one of {', '.join(WEIGHTINGS)}")
    if not (0 <= alpha < np.inf) or not 0 <= defensive <= 1:
        raise WorkspaceError(f"--alpha {alpha} must be >= 0 and --defensive {defensive} in [0, 1]")
    if samples is not None and not (1 <= samples < np.inf):
        raise WorkspaceError(f"--samples {samples}: must be a number >= 1 (simulations to plan)")
    if not 1 <= stages <= 10:
        raise WorkspaceError(f"--stages {stages}: must be between 1 and 10")
    if not 0 < stage1_share < 1:
        raise WorkspaceError(f"--stage1-share {stage1_share}: must lie in (0, 1), e.g. 0.5")
    ws = Workspace(root)
    settings = ws.require_initialised()
    pend = ws.pending()
    waiting = sorted(set(pend["plan"].drop_nulls().to_list())) if pend.height else []
    if waiting and not allow_pending:
        # A second plan while the first awaits results would be drawn from the same scores
        # and double-count the rate's sample; Make re-running a target must not do that.
        raise PendingResultsError(
            f"{ws.root}: estimate plan {waiting[-1]} awaits results for "
            f"{int(pend['plan'].is_in(waiting).sum())} picks; simulate its hand-off list, "
            "ingest the results and run `bams-cli estimate`, or pass --allow-pending to "
            "draw another plan beside it"
        )
    model = ws.require_fresh_model()
    ids, _, _, p_all = _read_scores(ws, len(settings.gammas))
    # The largest gamma's p_n bounds every other gamma's (f <= g_small implies f <= g_large),
    # so one sample planned on it serves every configured gamma.
    g_plan = int(np.argmax(settings.gammas))
    p = p_all[:, g_plan]
    known = _observed_level0(ws, ids)
    n = len(ids)
    gp_rate, _ = gp_estimate(p)
    n_unknown = int((~known).sum())
    number = (_plan_numbers(ws) or [0])[-1] + 1

    # Which stage is this? The next stage of an unfinished series, or stage 1 of a new one.
    staged = design == "poisson"
    prev = st.plan_info(ws, number - 1) if number > 1 else None
    # A stage is drawn from the model checked on the previous stage's outcomes, so a plan
    # drawn beside a pending one (--allow-pending) starts a new estimate instead.
    continuing = (
        staged
        and not new_series
        and prev is not None
        and prev.stage < prev.stages
        and st.plan_complete(ws, prev.number)
    )
    if continuing:
        assert prev is not None
        if samples is not None and not math.isclose(samples, prev.series_K, rel_tol=1e-9):
            raise WorkspaceError(
                f"--samples: plan {prev.number} is stage {prev.stage} of {prev.stages} of an "
                f"estimate with K = {prev.series_K:g} fixed at its stage 1; this plan is its "
                "next stage and spends the rest (drop --samples, or pass the same K); pass "
                "--new-series to start a new estimate instead"
            )
        series, stage, n_stages = prev.series, prev.stage + 1, prev.stages
        series_K, weights = prev.series_K, prev.weights
        K_stage = series_K * weights[stage - 1]
    else:
        if samples is None:
            # The paper's K = 5 p N with the GP's own p; a GP that explains failures away
            # can put p N near 0, so the failures already seen at level 0 set a floor.
            obs0 = ws.read_observations().filter(pl.col("fidelity") == 0)
            seen = int((obs0["value"] <= settings.gammas[g_plan]).sum())
            samples = float(round(5 * max(gp_rate * n, seen + 1)))
        if design == "with-replacement":
            samples = float(round(samples))
        if design != "with-replacement":
            samples = min(samples, float(n_unknown))
        n_stages = stages if staged and samples >= 2 * stages else 1
        series, stage, series_K = number, 1, float(samples)
        rest = (1.0 - stage1_share) / (n_stages - 1) if n_stages > 1 else 0.0
        weights = [stage1_share, *([rest] * (n_stages - 1))] if n_stages > 1 else [1.0]
        K_stage = series_K * weights[0]
    K_stage = min(K_stage, float(n_unknown))
    stream = [settings.seed, 10_000 + number] if seed is None else [int(seed), 10_000]
    rng = np.random.default_rng(stream)
    unknown = np.flatnonzero(~known)
    pu = p[unknown]
    # What the finished plans say about trusting p_n (lam: the share of failure mass it
    # does not explain); the prior alone before any plan has results.
    evidence, evidence_plans = st.mix_evidence(ws, settings.gammas[g_plan])
    post = dz.risk_posterior(evidence)
    choice = None
    if staged:
        with np.errstate(divide="ignore"):
            if unknown.size == 0:  # every level-0 value is known: a census, nothing to draw
                pi_u = np.zeros(0)
            elif weighting == "auto":
                choice = dz.choose_design(
                    pu, K=K_stage, posterior=post, alpha=alpha, defensive=defensive
                )
                pi_u = choice.pi
            elif weighting == "uniform":
                pi_u = np.full(unknown.size, K_stage / max(unknown.size, 1))
            else:
                pi_u = inclusion_probabilities(pu, alpha=alpha, defensive=defensive, K=K_stage)
        from bams_cli.core.estimate import SamplePlan, draw_poisson

        sampled = draw_poisson(pi_u, rng)
        plan = SamplePlan(
            "poisson", n, unknown.astype(np.int64), pi_u / max(K_stage, 1e-300), pi_u,
            K_stage, sampled, np.ones(sampled.size, np.int64),
        )  # fmt: skip
        # The interval's allowance for a failure no stage has seen, per gamma: where the
        # least-trusted calibrated model the evidence allows puts failures.
        w_model = [
            dz.unseen_failure_weight(post.risk(p_all[unknown, g]), pi_u)
            for g in range(len(settings.gammas))
        ]
    else:
        with np.errstate(divide="ignore"):
            plan = plan_sample(
                p, K=K_stage, rng=rng, known=known, alpha=alpha, defensive=defensive,
                design=design,  # type: ignore[arg-type]
            )  # fmt: skip
        prob_u = plan.q if design == "with-replacement" else plan.pi
        w_model = [
            model_weight(p_all[plan.unknown, g], prob_u, design=design, K=plan.budget)  # type: ignore[arg-type]
            for g in range(len(settings.gammas))
        ]
    # What the known stratum saved: the inclusion probability its segments would have had.
    saved = 0.0
    if known.any() and design != "with-replacement":
        full = inclusion_probabilities(p, alpha=alpha, defensive=defensive, K=min(K_stage, n))
        saved = float(full[known].sum())
    sampled_idx = plan.sampled_pool_index
    known_idx = np.flatnonzero(known)
    prob = plan.sampled_prob
    # The sampled rows are the plan's requests (level 0, in hand-off order); the known
    # stratum's rows follow with the contract's columns null: nothing to simulate there.
    requests = contract.contract_columns(
        "plan",
        number,
        ids[sampled_idx],
        np.zeros(len(sampled_idx), np.int64),
        settings,
        ["estimate"] * len(sampled_idx),
    )
    n_known = len(known_idx)
    cols: dict[str, Any] = {
        name: pa.concat_arrays([arr, pa.nulls(n_known, arr.type)])
        for name, arr in requests.items()
        if name != SID
    }
    cols = {
        SID: pa.array(np.concatenate([ids[sampled_idx], ids[known_idx]]).astype(str), pa.string()),
        "stratum": ["sampled"] * len(sampled_idx) + ["known"] * n_known,
        "pi": np.concatenate([plan.pi[plan.sampled], np.ones(n_known)]),
        "draws": np.concatenate([plan.counts, np.zeros(n_known, np.int64)]),
        "q": np.concatenate([plan.q[plan.sampled], np.zeros(n_known)]),
        "prob": np.concatenate([prob, np.ones(n_known)]),
        "p_n": np.concatenate([p[sampled_idx], p[known_idx]]),
        **cols,
    }
    cols |= _passthrough_columns(ws, np.concatenate([sampled_idx, known_idx]), taken=cols)
    table = pa.table(cols)
    predicted = (
        {k: round(v, 6) for k, v in choice.predicted.items()} if choice is not None else None
    )
    weighting_used = (
        choice.name if choice is not None else ("p^alpha" if weighting != "uniform" else "uniform")
    )
    stage_info = {
        "series": series,
        "stage": stage,
        "stages": n_stages,
        "series_K": series_K,
        "stage_weights": weights,
    }
    check = {**post.summary(), "plans": evidence_plans}
    meta = {
        "plan": number,
        "design": design,
        "samples": K_stage,
        "alpha": alpha,
        "defensive": defensive,
        "weighting": weighting_used,
        "weighting_option": weighting,
        "predicted_vs_uniform": predicted,
        "model_check": check,
        **stage_info,
        "n_pool": n,
        "n_unknown": n_unknown,
        "p_mean_unknown": float(pu.mean()) if pu.size else None,
        "risk_norms": dz.risk_norms(dz.relative_risk(pu)).tolist(),
        # Undefined weights (no segment with pi < 1; p_n = 0 over U) are null, never a
        # bare NaN/Infinity in the metadata's JSON; reading them back gives NaN again.
        "w_max": _finite_or_none(max_failure_weight(plan)),
        "w_model": [_finite_or_none(w) for w in w_model],
        "plan_gamma": settings.gammas[g_plan],
        "model_hash": model["observations_hash"],
        # The GP's own estimate (mean p_n, variance bound) per gamma, as of this plan:
        # `estimate` reports it when the plan's results have not been fitted yet.
        "gp_at_plan": [list(gp_estimate(p_all[:, g])) for g in range(len(settings.gammas))],
        "seed": stream[0],
        "seed_source": "study settings" if seed is None else "--seed",
        "rng_stream": stream,
    }
    path = ws.estimates_dir / f"plan-{number:04d}.parquet"
    handoff_path = ws.estimates_dir / f"plan-{number:04d}-handoff.csv"
    state = schemas.PLAN.conform(table, meta)
    with transaction() as tx:
        tx.write_parquet(path, state)
        _, template = _write_handoff(
            tx, state.slice(0, len(sampled_idx)), handoff_path, PLAN_INTERNAL, handoff_internal
        )
    notes = [n for n in [_design_note(meta)] if n]
    return {
        "plan": number,
        "plan_file": str(path),
        "handoff": str(handoff_path),
        "results_template": str(template),
        "design": design,
        "samples_K": K_stage,
        **stage_info,
        "weighting": weighting_used,
        "predicted_vs_uniform": predicted,
        "model_check": check,
        "to_simulate": len(sampled_idx),
        "simulations_certain": int((plan.pi[plan.sampled] >= 1.0).sum()),
        "known_stratum": int(len(known_idx)),
        "simulations_saved_by_known_stratum": round(saved, 3),
        "gp_rate_estimate": gp_rate,
        "alpha": alpha,
        "defensive": defensive,
        "seed": stream[0],
        "seed_source": meta["seed_source"],
        "notes": notes,
    }


def _design_note(meta: dict[str, Any]) -> str | None:
    """One line when a plan's design was predicted to do no better than uniform sampling."""
    predicted = meta.get("predicted_vs_uniform") or {}
    chosen = predicted.get(meta.get("weighting"))
    if chosen is None or chosen <= UNIFORM_NOTE_RATIO:
        return None
    return (
        f"plan {meta['plan']}: the checked model predicted no design much better than "
        f"uniform sampling ({meta['weighting']}, {chosen:.2f}x uniform's variance); the "
        "estimate rests on the sample, not the model"
    )


#: ``estimate --plan --weighting``: "auto" picks the design with the smallest predicted
#: variance under the checked model; the others force one.
WEIGHTINGS = ("auto", "uniform", "p-alpha")

#: A chosen design predicted to reach at most this fraction of uniform's variance saving
#: gets a note: the model does not help the estimate.
UNIFORM_NOTE_RATIO = 0.9


def _finite_or_none(x: float) -> float | None:
    """x as a JSON number, or None (JSON null) when it is NaN or infinite."""
    x = float(x)
    return x if math.isfinite(x) else None


@dataclasses.dataclass(frozen=True)
class _PlanSample:
    """One plan's sample with its level-0 outcomes, ready for the estimator."""

    sampled_ids: np.ndarray
    fails: np.ndarray
    lost: list[str]
    estimate_with: Callable[[np.ndarray], Any]


def _plan_sample(
    ws: Workspace, number: int, gammas: np.ndarray, confidence: float, failed_as: str | None
) -> _PlanSample:
    """Plan ``number``'s sample, outcomes and estimator (``estimate_with(fails)``).

    Abandoned planned segments are refused, or kept for the bounds (``bams_cli.abandon``).
    """
    from bams_cli import abandon
    from bams_cli.core.estimate import estimate_from_sample

    path = ws.estimates_dir / f"plan-{number:04d}.parquet"
    meta = read_metadata_json(path)
    plan = pl.from_arrow(schemas.PLAN.check(read_state(path), path))
    assert isinstance(plan, pl.DataFrame)
    obs = ws.read_observations().filter(pl.col("fidelity") == 0).select(SID, "value")
    joined = plan.join(obs, on=SID, how="left")
    lost = abandon.planned_abandoned(ws, number, path, joined, failed_as)
    missing = joined.filter(pl.col("value").is_null() & ~pl.col(SID).is_in(lost))
    if missing.height:
        names = ", ".join(missing[SID].head(3).to_list())
        raise PendingResultsError(
            f"{path}: {missing.height} planned segments have no level-0 result ({names}"
            f"{', ...' if missing.height > 3 else ''}); simulate "
            f"{ws.estimates_dir / f'plan-{number:04d}-handoff.csv'} and ingest the results"
        )
    sampled = joined.filter(pl.col("stratum") == "sampled")
    known = joined.filter(pl.col("stratum") == "known")
    fails = sampled["value"].to_numpy()[:, None] <= gammas[None, :]
    known_fails = (known["value"].to_numpy()[:, None] <= gammas[None, :]).sum(axis=0)

    def estimate_with(fails: np.ndarray) -> Any:
        return estimate_from_sample(
            sampled["prob"].to_numpy(),
            fails,
            design=meta["design"],
            n_pool=int(meta["n_pool"]),
            n_unknown=int(meta["n_unknown"]),
            budget=float(meta["samples"]),
            counts=sampled["draws"].to_numpy(),
            known_failures=known_fails,
            confidence=confidence,
            w_model=np.asarray(meta["w_model"], dtype=np.float64),  # null -> NaN: design weights
        )

    return _PlanSample(sampled[SID].to_numpy(), fails, lost, estimate_with)


def _plan_estimate(ws: Workspace, number: int, gammas: np.ndarray, confidence: float):  # noqa: ANN202
    """The HT estimate of one plan from its ingested level-0 results, per gamma."""
    sample = _plan_sample(ws, number, gammas, confidence, None)
    return sample.estimate_with(sample.fails)


@locked
def estimate_compute(
    root: Path,
    *,
    plan_number: int | None = None,
    confidence: float = 0.9,
    exact_variance: bool = False,
    failed_as: str | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Compute the rate estimate from an ingested plan, for every configured gamma.

    A plan that is a later stage of a staged estimate is combined with its earlier stages
    (``core.design.combine_stages``); while stages remain, the estimate rests on the
    stages so far and says so. Planned segments abandoned for good (``bams-cli abandon``)
    are refused, unless ``failed_as="bounds"`` asks for the worst case over them
    (``bams_cli.abandon``).
    """
    from bams_cli import abandon
    from bams_cli.core.design import combine_stages
    from bams_cli.core.estimate import gp_estimate

    if not 0 < confidence < 1:
        raise WorkspaceError(f"--confidence {confidence}: must lie in (0, 1), e.g. 0.9")
    ws = Workspace(root)
    settings = ws.require_initialised()
    plans = _plan_numbers(ws)
    if not plans:
        raise WorkspaceError(
            f"{ws.root}: no estimate plan; run `bams-cli estimate --plan -w {ws.root}` first"
        )
    number = plans[-1] if plan_number is None else plan_number
    path = ws.estimates_dir / f"plan-{number:04d}.parquet"
    if not path.exists():
        raise WorkspaceError(f"{path}: no such plan (plans: {', '.join(map(str, plans))})")
    gammas = np.asarray(settings.gammas)
    # A staged estimate combines its series' stages up to this plan, with the weights
    # fixed at stage 1 (renormalised while later stages are still to come).
    series = stages_mod.series_plans(ws, number)
    samples = [_plan_sample(ws, k.number, gammas, confidence, failed_as) for k in series]
    meta = series[-1].meta
    weights = np.asarray([series[-1].weights[k.stage - 1] for k in series], np.float64)
    weights /= weights.sum()
    splits = np.cumsum([len(x.sampled_ids) for x in samples])[:-1]
    fails = np.concatenate([x.fails for x in samples])
    lost = [i for x in samples for i in x.lost]

    def estimate_with(fails: np.ndarray) -> Any:
        parts = np.split(fails, splits)
        stage_est = [x.estimate_with(f) for x, f in zip(samples, parts, strict=True)]
        return combine_stages(stage_est, weights, n_pool=int(meta["n_pool"]))

    est = estimate_with(fails)
    remaining = series[-1].stages - series[-1].stage
    rows = []
    gp_rows = []
    # The IS estimate needs no model. Beside it goes the GP's own estimate: from the
    # current model when it has been fitted on the plan's results, else the model's as of
    # the plan (stored with it), so a large K never forces a refit just to get the number.
    model = ws.require_model(allow_newer_observations=True)
    at_plan = meta.get("gp_at_plan")
    if not model["fresh"] and (exact_variance or at_plan is None):
        why = "--exact-variance" if exact_variance else f"{path} (made by an older version)"
        raise StaleStateError(
            f"{ws.model_path}: fitted on an older observation log and {why} needs the current "
            f"one; run `bams-cli fit -w {ws.root}` (or, faster, `bams-cli fit -w {ws.root} "
            f"--fixed-hyperparameters {ws.model_path}`: condition only, no training)"
        )
    if model["fresh"]:
        _, mu, sd, p_all = _read_scores(ws, len(gammas))
        gp_values = [gp_estimate(p_all[:, g]) for g in range(len(gammas))]
    else:
        gp_values = [(float(m), float(b)) for m, b in at_plan or []]
    for g, gamma in enumerate(gammas):
        e = est[g]
        rows.append(
            {
                "gamma": float(gamma),
                "p_hat": e.p_hat,
                # Undefined numbers are null beside a note saying why, never NaN (issue 12):
                # the note says what se rests on when it is not the HT variance estimate.
                "se": _finite_or_none(e.se),
                "variance_note": e.variance_note,
                "ci_low": e.ci_low,
                "ci_high": e.ci_high,
                "confidence": confidence,
                "rel_var": _finite_or_none(e.rel_var),
                "rel_var_note": e.rel_var_note,
                "n_sampled": e.n_sampled,
                "failures_sampled": e.n_failures_sampled,
                "failures_known": e.n_known_failures,
                "distinct_failures_found": e.n_failures_found,
            }
        )
        gp_mean, gp_bound = gp_values[g]
        gp_row = {"gamma": float(gamma), "gp_p_hat": gp_mean, "gp_var_bound": gp_bound}
        if exact_variance:
            g_model = float(_model_transform(ws, model).forward(float(gamma)))
            gp_row["gp_var_exact"] = _gp_exact_variance(ws, settings, mu, sd, g_model, progress)
        gp_rows.append(gp_row)
    staging = {
        "series": series[-1].series,
        "plans": [k.number for k in series],
        "stages_done": len(series),
        "stages": series[-1].stages,
        "weights": [round(float(w), 12) for w in weights],
        "series_K": series[-1].series_K,
        "note": (
            f"{remaining} more stage{'s' if remaining > 1 else ''} of this estimate "
            f"{'are' if remaining > 1 else 'is'} planned: refit on these results and run "
            f"`bams-cli estimate --plan -w {ws.root}`; until then the estimate rests on "
            f"{len(series)} of {series[-1].stages} stages"
            if remaining
            else None
        ),
    }
    summary = {
        "plan": number,
        "design": meta["design"] if len(series) == 1 else "staged",
        "samples_K": sum(float(k.meta["samples"]) for k in series),
        "staging": staging,
        "estimates": rows,
        "gp": gp_rows,
        "gp_model": "current" if model["fresh"] else "as of the plan",
        "notes": [n for n in (_design_note(k.meta) for k in series) if n],
    }
    # Hook: with failed_as="bounds", the worst case over abandoned segments (bams_cli.abandon).
    abandon.bound_estimates(
        summary, lost=lost, sampled_ids=np.concatenate([x.sampled_ids for x in samples]),
        fails=fails, estimate_with=estimate_with,
    )  # fmt: skip
    out = ws.estimates_dir / f"estimate-{number:04d}.json"
    with transaction() as tx:
        tx.write_text(out, json.dumps(summary, indent=2, allow_nan=False) + "\n")
    summary["estimate_file"] = str(out)
    return summary


def _gp_exact_variance(
    ws: Workspace,
    settings: Settings,
    mu: np.ndarray,
    sd: np.ndarray,
    gamma: float,
    progress: Progress | None,
) -> float:
    from bams_cli.core.estimate import gp_variance_exact

    ids, X = ws.read_pool()
    if len(ids) > 50_000:
        raise WorkspaceError(
            f"--exact-variance: the pool has {len(ids)} segments; the O(N^2) sum is limited to 50,000"
        )
    posterior, _ = load_posterior(ws, settings, ids, X)
    res = gp_variance_exact(
        mu,
        sd**2,
        lambda r, c: posterior.cov_theta0(X[r], X[c]),
        gamma,
        progress=(lambda done, total: progress("exact variance", done, total))
        if progress
        else None,
    )
    return float(res.var)


# ---------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------
@locked
def report(
    root: Path,
    *,
    truth: Path | None = None,
    n_diverse: int = 5,
    max_points: int = 50_000,
) -> dict[str, Any]:
    """Write report/report.html, summary.json and summary.md for the study."""
    from sklearn.decomposition import PCA

    from bams_cli import __version__
    from bams_cli import report as rep
    from bams_cli.core.evaluate import batch_mean_f, dpp_diverse, retention_recall

    ws = Workspace(root)
    settings = ws.require_initialised()
    ids, X = ws.read_pool()
    n = len(ids)
    gammas = list(settings.gammas)
    log = ws.read_observations(active_only=False)
    active = log.filter(pl.col("active"))
    costs = settings.costs

    truth_f0 = None
    if truth is not None:
        tt = read_table(truth, what="truth")
        require_columns(tt, [SID, "value_0"], truth)
        tdf = pl.from_arrow(tt.select([SID, "value_0"]))
        assert isinstance(tdf, pl.DataFrame)
        tdf = tdf.with_columns(pl.col(SID).cast(pl.String))
        aligned = pl.DataFrame({SID: ids}).join(tdf, on=SID, how="left", maintain_order="left")
        if aligned["value_0"].null_count():
            first = aligned.filter(pl.col("value_0").is_null())[SID][0]
            raise InputError(truth, f"no ground truth for pool segment {first!r}", column=SID)
        truth_f0 = aligned["value_0"].to_numpy()

    per_level = {}
    for lv in range(settings.n_levels):
        count = int((log["fidelity"] == lv).sum())
        per_level[str(lv)] = {"count": count, "cost": count * costs[lv]}
    spent = {
        "per_level": per_level,
        "count": int(log.height),
        "cost": float(sum(v["cost"] for v in per_level.values())),
    }

    model_doc = None
    unusable = None
    if ws.model_path.exists():
        # A model fitted before the latest results still describes the pool; the report
        # shows it marked stale rather than refusing (the estimate needs no refit either).
        # One fitted for other gammas does not: its p columns answer other thresholds.
        try:
            model_doc = ws.require_model(allow_newer_observations=True)
        except StaleStateError as exc:
            unusable = str(exc)
    notices = _report_model_notices(ws, model_doc, active)
    if unusable is not None:
        notices = [{"kind": "stale_model", "severity": "warning", "text": unusable}]

    pos = {sid: i for i, sid in enumerate(ids)}
    obs0 = dict(active.filter(pl.col("fidelity") == 0).select(SID, "value").iter_rows())
    observed_pairs = active.select(SID, "fidelity").unique()
    batch_rows, batch_picks, per_batch_f = [], [], []
    waiting = []
    for b in ws.batch_numbers():
        df = ws.read_batch(b)
        gone = ws.abandoned_open("batch", b)  # requests that will never come back
        open_ = df.join(observed_pairs, on=[SID, "fidelity"], how="anti")
        pending = open_.join(gone, on=[SID, "fidelity"], how="anti").height
        if pending:
            waiting.append(f"batch {b} ({pending} of {df.height} picks, batches/batch-{b:04d}.csv)")
        idx = np.array([pos[s] for s in df[SID].to_list() if s in pos], dtype=np.int64)
        if truth_f0 is not None:
            f0 = truth_f0[idx]
        else:
            f0 = np.array([obs0[s] for s in df[SID].to_list() if s in obs0])
        per_batch_f.append(f0)
        batch_picks.append((b, idx))
        batch_rows.append(
            {
                "batch": b,
                "strategy": df["strategy"][0] if df.height else "",
                "picks": df.height,
                "picks_per_level": {
                    str(k): int(v)
                    for k, v in df.group_by("fidelity").len().sort("fidelity").iter_rows()
                },
                "picks_per_cluster": {
                    str(k): int(v)
                    for k, v in df.group_by("cluster").len().sort("cluster").iter_rows()
                },
                "cost": float(df["cost"].sum()),
                "n_f0": int(len(f0)),
                "pending": pending,
                "abandoned": gone.height,
            }
        )
    if waiting:
        notices.append(
            {
                "kind": "pending_batches",
                "severity": "info",
                "text": f"Results pending for {'; '.join(waiting)}: simulate the hand-off "
                f"list and run `bams-cli ingest-results -w {root}`. A batch's mean level-0 f "
                "counts only the picks whose level-0 value is known.",
            }
        )
    if per_batch_f:
        means, ses = batch_mean_f(per_batch_f)
        for row, m, se in zip(batch_rows, means, ses, strict=True):
            row["mean_f0"] = None if not np.isfinite(m) else float(m)
            row["mean_f0_se"] = None if not np.isfinite(se) else float(se)

    scores = None
    if ws.scores_path.exists() and unusable is None:
        _, mu, sd, p_all = _read_scores(ws, len(gammas))
        scores = (mu, sd, p_all)

    estimates, gp_rows = [], []
    plans = _plan_numbers(ws)
    shown_plan = next((k for k in reversed(plans) if ws.estimate_path(k).exists()), None)
    notices += _report_plan_notices(ws, plans, shown_plan, set(obs0))
    if shown_plan is not None:
        doc = ws.read_estimate(shown_plan)  # a damaged file is named, with its fix
        estimates = [{**e, "plan": shown_plan} for e in doc["estimates"]]
        gp_rows = doc["gp"]
    elif scores is not None:
        from bams_cli.core.estimate import gp_estimate

        for g, gamma in enumerate(gammas):
            m, bound = gp_estimate(scores[2][:, g])
            gp_rows.append({"gamma": gamma, "gp_p_hat": m, "gp_var_bound": bound})

    figures: dict[str, str] = {}
    rng = np.random.default_rng(settings.seed)
    diverse = []
    if n_diverse < 0 or max_points < 1:
        raise WorkspaceError(f"--diverse {n_diverse}: must be >= 0")
    if scores is not None:
        p0 = scores[2][:, 0]
        if X.shape[1] == 2:
            XY, projected = X, False
        else:
            fit_rows = rng.choice(n, size=min(n, max_points), replace=False)
            XY, projected = PCA(2).fit(X[fit_rows]).transform(X), True
        show = np.sort(rng.choice(n, size=min(n, max_points), replace=False))
        shown = np.zeros(n, bool)
        shown[show] = True
        for _, idx in batch_picks:
            shown[idx] = True
        keep = np.flatnonzero(shown)
        remap = np.full(n, -1)
        remap[keep] = np.arange(len(keep))
        figures["pool_map"] = rep.pool_map(
            XY[keep],
            p0[keep],
            [(b, remap[idx]) for b, idx in batch_picks],
            projected=projected,
            gamma=gammas[0],
        )
        # A likely failure is a guess about a segment's level-0 value, so a segment whose
        # level-0 value is known is never one: observed failing it is a confirmed failure
        # (listed apart), observed above every gamma it passed, whatever a model fitted
        # before that result still says.
        known0 = np.zeros(n, bool)
        known0[[pos[s] for s in obs0 if s in pos]] = True
        unknown = np.flatnonzero(~known0)
        top = unknown[np.argsort(-p0[unknown], kind="stable")[:500]]
        chosen = (
            top[dpp_diverse(X[top], p0[top], min(n_diverse, len(top)))] if n_diverse else top[:0]
        )
        cheap = active.filter(pl.col("fidelity") > 0).sort("fidelity")
        leads: dict[str, dict[str, float]] = {}
        for sid, lv, value in cheap.select(SID, "fidelity", "value").iter_rows():
            leads.setdefault(sid, {})[f"observed_f{lv}"] = float(value)
        for i, more in zip(chosen, _passthrough_rows(ws, chosen), strict=True):
            row = {SID: str(ids[i]), "p_n": float(p0[i]), "mu": float(scores[0][i])}
            row.update(leads.get(str(ids[i]), {}))
            row.update(more)
            diverse.append(row)
        diverse = _uniform_rows(diverse)

    # Failures seen at level 0: findings, not guesses. Those the estimate plan sampled are
    # here too; the list holds every one (it is bounded by the level-0 runs).
    confirmed = []
    fails_at = {sid: [g for g in gammas if value <= g] for sid, value in obs0.items() if sid in pos}
    failed = sorted((s for s in fails_at if fails_at[s]), key=lambda s: (obs0[s], s))
    rows_failed = np.array([pos[s] for s in failed], dtype=np.int64)
    for sid, more in zip(failed, _passthrough_rows(ws, rows_failed), strict=True):
        row = {SID: sid, "observed_f0": float(obs0[sid]), "fails_at_gamma": fails_at[sid]}
        if scores is not None:
            row["p_n"] = float(scores[2][pos[sid], 0])
        row.update(more)
        confirmed.append(row)
    confirmed = _uniform_rows(confirmed)

    truth_doc = None
    if truth_f0 is not None:
        fails = truth_f0[:, None] <= np.asarray(gammas)[None, :]
        counts = fails.sum(axis=0)
        est_recall: list[float | None] = [None] * len(gammas)
        for e in estimates:  # by gamma: the estimate may answer gammas edited since
            if e["gamma"] in gammas and counts[gammas.index(e["gamma"])]:
                g = gammas.index(e["gamma"])
                est_recall[g] = e["distinct_failures_found"] / float(counts[g])
        grid = np.linspace(0, 10, 101)
        curves = {}
        if counts[0]:
            for snap in sorted(ws.history_dir.glob("scores-after-batch-*.parquet")):
                batch = int(snap.stem.rsplit("-", 1)[1])
                p_snap = read_state(snap, columns=["p_0"]).column("p_0").to_numpy()
                if len(p_snap) == n:
                    curves[batch] = retention_recall(p_snap, fails[:, 0], grid)
        if curves:
            figures["recall"] = rep.recall_plot(curves, grid)
        truth_doc = {
            "rate": [float(c) / n for c in counts],
            "failures": [int(c) for c in counts],
            "estimate_recall": est_recall,
            "retention_recall": {
                str(b): {f"{r:g}": float(v) for r, v in zip(grid[::10], c[::10], strict=True)}
                for b, c in curves.items()
            },
        }
    if estimates:
        truth_rates = None
        if truth_doc is not None:  # by gamma, as the recall above
            rate = dict(zip(gammas, truth_doc["rate"], strict=True))  # type: ignore[call-overload]
            truth_rates = [rate.get(e["gamma"], float("nan")) for e in estimates]
        figures["rate"] = rep.rate_plot(estimates, truth_rates)

    summary: dict[str, Any] = {
        "schema_version": schemas_json.version("summary.json"),
        "tool_version": __version__,
        "generated_at": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "workspace": str(root),
        "notices": notices,
        "study": {**_settings_summary(settings), "pool_size": n, "dim": int(X.shape[1])},
        "simulation_spent": spent,
        "model": model_doc,
        "batches": batch_rows,
        "estimates": estimates,
        "gp_estimate": gp_rows,
        "confirmed_failures": confirmed,
        "diverse_failures": diverse,
        "truth": truth_doc,
        "figures": sorted(figures),
    }
    out = ws.report_dir
    with transaction() as tx:
        tx.write_text(out / "report.html", rep.render_html(summary, figures))
        tx.write_text(
            out / "summary.json",
            json.dumps(summary, indent=2, default=str, allow_nan=False) + "\n",
        )
        tx.write_text(out / "summary.md", rep.render_markdown(summary))
    return {
        "report": str(out / "report.html"),
        "summary_json": str(out / "summary.json"),
        "summary_md": str(out / "summary.md"),
        "figures": sorted(figures),
        "notices": [n["text"] for n in notices],
        "estimates": [
            {k: e[k] for k in ("gamma", "p_hat", "ci_low", "ci_high")} for e in estimates
        ],
    }


def _report_model_notices(
    ws: Workspace, model: dict[str, Any] | None, active: pl.DataFrame
) -> list[dict[str, str]]:
    """What the report must say first about the model: missing, or older than the log."""
    fit = f"`bams-cli fit -w {ws.root}`"
    if model is None:
        return [
            {
                "kind": "no_model",
                "severity": "info",
                "text": f"No model yet: once results are ingested, run {fit} for failure "
                "probabilities, the pool map and the likely failures.",
            }
        ]
    if model["fresh"]:
        return []
    fitted = int(sum(model.get("n_observations_per_level", [])))
    return [
        {
            "kind": "stale_model",
            "severity": "warning",
            "text": f"Stale model: the observation log changed after the last fit (fitted on "
            f"{fitted} results, the log now holds {active.height}). Failure probabilities, "
            "the pool map, the likely failures' ranking and the GP's estimate are that "
            f"fit's and miss the newer results; run {fit} to bring them up to date.",
        }
    ]


def _report_plan_notices(
    ws: Workspace, plans: list[int], shown: int | None, known0: set[str]
) -> list[dict[str, str]]:
    """One notice per estimate plan newer than the estimate shown: results or compute due."""
    out = []
    picks = ws.read_plan_picks()
    for k in plans:
        if shown is not None and k <= shown:
            continue
        sampled = picks.filter(pl.col("plan") == k)[SID].to_list()
        gone = set(ws.abandoned_open("plan", k)[SID].to_list())
        missing = sum(s not in known0 and s not in gone for s in sampled)
        shown_text = (
            "no estimate is shown yet" if shown is None else f"the estimate shown is plan {shown}'s"
        )
        if missing:
            text = (
                f"Estimate plan {k} awaits level-0 results for {missing} of its {len(sampled)} "
                f"sampled segments (estimates/plan-{k:04d}-handoff.csv); {shown_text}."
            )
        elif gone:
            text = (
                f"Estimate plan {k} has its results but {len(gone)} of its sampled segments "
                f"were abandoned: run `bams-cli estimate -w {ws.root} --failed-as bounds` for "
                f"the worst-case interval over them; {shown_text}."
            )
        else:
            text = (
                f"Estimate plan {k} has all its results: run `bams-cli estimate -w {ws.root}` "
                f"to compute it; {shown_text}."
            )
        out.append({"kind": "pending_plan", "severity": "info", "text": text})
    for k in plans[-1:]:
        note = _design_note(read_metadata_json(ws.estimates_dir / f"plan-{k:04d}.parquet"))
        if note:
            out.append({"kind": "design_like_uniform", "severity": "info", "text": note + "."})
    return out


def _passthrough_rows(ws: Workspace, rows: np.ndarray) -> list[dict[str, Any]]:
    """The pool's pass-through columns (scenario tags, difficulty ...) of some pool rows."""
    segs = ws.read_segments()
    cols = [c for c in segs.column_names if c != SID and c not in ws.coordinate_columns(segs)]
    if not cols:
        return [{} for _ in rows]
    return [
        {k: (round(v, 6) if isinstance(v, float) else v) for k, v in r.items()}
        for r in segs.select(cols).take(pa.array(rows, type=pa.int64())).to_pylist()
    ]


def _uniform_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Rows with one key set (segment_id first, then sorted), blanks where a row lacks one."""
    keys = sorted({k for r in rows for k in r}, key=lambda k: (k != SID, k))
    return [{k: r.get(k, "") for k in keys} for r in rows]
