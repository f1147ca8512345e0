"""One function per subcommand: load state -> call core -> write state.

Every function validates everything it reads before it writes anything, stages its
outputs in one ``transaction`` and returns a JSON-serialisable summary (what the CLI prints
as a table, or as-is under ``--json``). Progress is reported through an optional
``progress(phase, done, total)`` callable, so this layer never imports rich.
"""

from __future__ import annotations

import datetime as dt
import fnmatch
import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from bams_cli.core.reduce import Reducer, fit_reducer
from bams_cli.errors import (
    ConflictError,
    DuplicateError,
    InputError,
    SchemaError,
    WorkspaceError,
)
from bams_cli.settings import Settings, levels_from_costs
from bams_cli.state import schemas
from bams_cli.state.io import file_sha256, read_table, require_columns, transaction
from bams_cli.state.lock import workspace_lock
from bams_cli.state.workspace import Workspace

Progress = Callable[[str, int, int], None]
SID = schemas.SEGMENT_ID


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
    wait: bool = False,
) -> dict[str, Any]:
    """Create a workspace and its settings file (flags > --settings-from file > defaults)."""
    ws = Workspace(root)
    if ws.settings_path.exists() and not force:
        raise WorkspaceError(
            f"{ws.settings_path}: already exists; edit it, or pass --force to overwrite it"
        )
    base = Settings()
    if settings_from is not None:
        if not settings_from.exists():
            raise InputError(settings_from, "settings file not found")
        base = Settings.from_toml(settings_from.read_text(), source=str(settings_from))
    levels = levels_from_costs(costs, level_names) if costs else None
    settings = base.with_overrides(
        gammas=tuple(gammas) if gammas else None, levels=levels, seed=seed, embedding_dim=dim
    )
    with workspace_lock(root, wait=wait), transaction() as tx:
        tx.write_text(ws.settings_path, settings.to_toml())
    return {
        "workspace": str(root),
        "settings": str(ws.settings_path),
        **_settings_summary(settings),
    }


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
) -> tuple[str | None, list[str]]:
    """Which column(s) hold the embedding: (list column, []) or (None, numeric columns)."""
    if id_column not in schema.names:
        raise SchemaError(
            source,
            f"no id column {id_column!r}; found {', '.join(schema.names)} (choose it with --id-column)",
            column=id_column,
        )
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
        mats.append(v)
    return np.column_stack(mats) if mats else np.empty((batch.num_rows, 0))


class _EmbeddingStream:
    """Restartable stream of embedding batches from one Parquet file, row groups at a time."""

    def __init__(self, path: Path, list_col: str | None, cols: list[str], batch_size: int):
        self.path, self.list_col, self.cols, self.batch_size = path, list_col, cols, batch_size
        self.read_columns = [list_col] if list_col else cols

    def __call__(self) -> Iterator[np.ndarray]:
        offset = 0
        pf = pq.ParquetFile(self.path)
        for batch in pf.iter_batches(batch_size=self.batch_size, columns=self.read_columns):
            yield _batch_matrix(batch, self.list_col, self.cols, self.path, offset)
            offset += batch.num_rows


def _read_ids(path: Path, id_column: str) -> pa.Array:
    ids = pq.read_table(path, columns=[id_column]).column(id_column).combine_chunks()
    if not (
        pa.types.is_string(ids.type)
        or pa.types.is_large_string(ids.type)
        or pa.types.is_integer(ids.type)
    ):
        raise SchemaError(
            path, f"segment ids must be strings or integers, got {ids.type}", column=id_column
        )
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
            f"{what} {value!r} appears again (first at row {first + 1})",
            column=column,
            row=second + 1,
        )


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
    wait: bool = False,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Reduce segment embeddings into the workspace pool (or, with ``apply``, add to it)."""
    ws = Workspace(root)
    settings = ws.require_initialised()
    id_column = id_column or settings.id_column
    if not source.exists():
        raise InputError(source, "segments file not found")
    try:
        schema = pq.read_schema(source)
    except (pa.ArrowInvalid, OSError) as exc:
        raise InputError(source, f"cannot read as Parquet ({str(exc).splitlines()[0]})") from None
    list_col, cols = _embedding_layout(
        schema, source, id_column=id_column, columns=columns, embedding_column=embedding_column
    )
    ids = _read_ids(source, id_column)
    stream = _EmbeddingStream(source, list_col, cols, batch_size)
    n = len(ids)
    if n == 0:
        raise InputError(source, "has no rows")
    rng = np.random.default_rng(settings.seed)

    existing: pa.Table | None = None
    if apply:
        if not ws.reducer_path.exists():
            raise WorkspaceError(
                f"{ws.reducer_path}: no fitted reducer; run embed-reduce without --apply first"
            )
        with np.load(ws.reducer_path) as arrays:
            reducer = Reducer.from_arrays(dict(arrays))
        existing = ws.read_segments()
        clash = pc.is_in(ids, value_set=existing.column(SID).combine_chunks())
        if pc.any(clash).as_py():
            row = int(np.flatnonzero(clash.to_numpy(zero_copy_only=False))[0]) + 1
            raise DuplicateError(
                source,
                f"segment id {ids[row - 1].as_py()!r} is already in the pool",
                column=id_column,
                row=row,
            )
    else:
        if ws.segments_path.exists() and not force:
            raise WorkspaceError(
                f"{ws.segments_path}: the pool is already reduced; use --apply to add segments, "
                f"or --force to refit the reducer (coordinates change; refit the model after)"
            )
        dim = dim or settings.embedding_dim
        sample = None
        if method == "autoencoder" or n <= 200_000:
            take = np.sort(rng.choice(n, size=min(sample_size, n), replace=False))
            sample = np.vstack(list(stream()))[take] if n <= 200_000 else _sample_rows(stream, take)
        try:
            reducer = fit_reducer(
                stream,
                method=method,
                dim=dim,
                standardize=standardize,
                sample=sample,
                rng=rng,
                progress=progress,  # type: ignore[arg-type]
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
    }
    with workspace_lock(root, wait=wait), transaction() as tx:
        if not apply:
            tx.write_with(ws.reducer_path, lambda p: _savez(p, reducer.to_arrays()))
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
        np.savez(fh, **arrays)


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
def _read_results(path: Path, n_levels: int) -> pl.DataFrame:
    """A results file as (segment_id, fidelity, value, extra), every bad row named."""
    table = read_table(path, what="results")
    require_columns(table, [SID, "fidelity", "value"], path)
    df = pl.from_arrow(table)
    assert isinstance(df, pl.DataFrame)
    df = df.with_row_index("_row", offset=1)

    sid = df[SID]
    if sid.null_count():
        raise InputError(
            path, "segment id is missing", column=SID, row=int(df.filter(sid.is_null())["_row"][0])
        )
    df = df.with_columns(pl.col(SID).cast(pl.String))

    fid = df["fidelity"].cast(pl.Float64, strict=False)
    bad = fid.is_null() | (fid != fid.round(0))
    if bad.any():
        row = int(df.filter(bad)["_row"][0])
        raise InputError(
            path,
            f"fidelity must be an integer level, got {df['fidelity'][row - 1]!r}",
            column="fidelity",
            row=row,
        )
    df = df.with_columns(fid.cast(pl.Int64).alias("fidelity"))
    out = df.filter((pl.col("fidelity") < 0) | (pl.col("fidelity") >= n_levels))
    if out.height:
        raise InputError(
            path,
            f"fidelity {out['fidelity'][0]} is not a configured level (0..{n_levels - 1}); "
            f"add it to settings.toml [[levels]]",
            column="fidelity",
            row=int(out["_row"][0]),
        )

    val = df["value"].cast(pl.Float64, strict=False)
    bad = val.is_null() | ~val.is_finite()
    if bad.any():
        row = int(df.filter(bad)["_row"][0])
        raise InputError(
            path,
            f"value must be a finite number, got {df['value'][row - 1]!r}",
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
            f"({first[SID]!r}, fidelity {first['fidelity']}) appears again (first at row {first['_row']})",
            column=SID,
            row=again,
        )
    extra_cols = [c for c in df.columns if c not in {SID, "fidelity", "value", "_row"}]
    if extra_cols:
        extra = df.select(extra_cols).to_dicts()
        df = df.with_columns(
            pl.Series("extra", [json.dumps(e, default=str) for e in extra], pl.String)
        )
    else:
        df = df.with_columns(pl.lit(None, dtype=pl.String).alias("extra"))
    return df.select("_row", SID, "fidelity", "value", "extra")


def ingest_results(
    root: Path,
    source: Path,
    *,
    replace: bool = False,
    allow_unselected: bool = False,
    wait: bool = False,
) -> dict[str, Any]:
    """Append a simulation team's results to the observation log."""
    ws = Workspace(root)
    settings = ws.require_initialised()
    ws.require_segments()
    results = _read_results(source, settings.n_levels)
    digest = file_sha256(source)
    log = ws.read_observations(active_only=False)

    if digest in set(log["source_sha256"].to_list()):
        return {
            "ingested": 0,
            "already_ingested": True,
            "message": f"{source} was already ingested (sha256 {digest[:12]}); nothing changed",
            "pending": _pending_summary(ws),
        }

    pool_ids = pl.from_arrow(ws.read_segments([SID]).column(SID)).alias(SID)  # type: ignore[union-attr]
    unknown = results.filter(~pl.col(SID).is_in(pool_ids.implode()))
    if unknown.height:
        first = unknown.row(0, named=True)
        raise InputError(
            source,
            f"segment id {first[SID]!r} is not in the pool ({unknown.height} unknown in all); "
            f"add segments with `bams-cli embed-reduce --apply`",
            column=SID,
            row=int(first["_row"]),
        )

    picks = _selections(ws)
    matched = results.join(picks, on=[SID, "fidelity"], how="left").with_columns(
        pl.col("planned").fill_null(False)
    )
    unselected = matched.filter(pl.col("batch").is_null() & ~pl.col("planned"))
    if unselected.height and not allow_unselected:
        names = ", ".join(unselected[SID].head(3).to_list())
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
            f"{source}: column 'value', row {c['_row']}: ({c[SID]!r}, fidelity {c['fidelity']}) "
            f"is already known as {c['known']!r}, got {c['value']!r} "
            f"({conflicts.height} conflicts in all); pass --replace to supersede the logged values"
        )
    same = both.filter(pl.col("known").is_not_null() & (pl.col("known") == pl.col("value")))
    new = both.filter(pl.col("known").is_null() | (pl.col("known") != pl.col("value")))

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

    with workspace_lock(root, wait=wait), transaction() as tx:
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
    }


def _selections(ws: Workspace) -> pl.DataFrame:
    """Every selected (segment, fidelity): batch picks with their batch, plan picks flagged."""
    batches = ws.read_batches().group_by(SID, "fidelity").agg(pl.col("batch").max())
    planned = _planned(ws)
    sel = batches.join(planned, on=[SID, "fidelity"], how="full", coalesce=True)
    return sel.with_columns(pl.col("planned").fill_null(False))


def _planned(ws: Workspace) -> pl.DataFrame:
    frames = []
    if ws.estimates_dir.is_dir():
        for p in sorted(ws.estimates_dir.glob("plan-*.parquet")):
            t = pq.read_table(p, columns=[SID, "stratum"])
            df = pl.from_arrow(t)
            assert isinstance(df, pl.DataFrame)
            frames.append(df.filter(pl.col("stratum") == "sampled").select(SID))
    if not frames:
        return pl.DataFrame(schema={SID: pl.String, "fidelity": pl.Int64, "planned": pl.Boolean})
    return (
        pl.concat(frames)
        .unique()
        .with_columns(pl.lit(0, dtype=pl.Int64).alias("fidelity"), pl.lit(True).alias("planned"))
    )


def _pending_summary(ws: Workspace, limit: int = 20) -> dict[str, Any]:
    pend = ws.pending()
    return {
        "count": pend.height,
        "by_batch": {
            int(k): int(v) for k, v in pend.group_by("batch").len().sort("batch").iter_rows()
        },
        "first": pend.head(limit).select(SID, "fidelity", "batch").to_dicts(),
    }


# ---------------------------------------------------------------------------------------
# simulate (sample data only)
# ---------------------------------------------------------------------------------------
def simulate(handoff: Path, truth: Path, output: Path) -> dict[str, Any]:
    """Answer a hand-off list from a ground-truth table, as a simulation team would.

    For sample data and demos only: real results come from real simulators.
    """
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
    result = out.sort("_row").select(SID, "fidelity", "value")
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
