"""``bams-cli embed-reduce``: the pool's embeddings, reduced to the model's inputs."""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from bams_cli.errors import (
    DuplicateError,
    InputError,
    OptionValueError,
    SchemaError,
    WorkspaceError,
    shown,
)
from bams_cli.pipeline._common import SID, Progress, locked, savez
from bams_cli.state import schemas
from bams_cli.state.inputs import EmbeddingStream, embedding_layout, read_ids, sample_rows
from bams_cli.state.io import (
    file_sha256,
    read_metadata_json,
    transaction,
)
from bams_cli.state.workspace import Workspace

if TYPE_CHECKING:
    from bams_cli.core.reduce import Reducer


@locked
def embed_reduce(
    root: Path,
    source: Path,
    *,
    apply: bool = False,
    method: str = "pca",
    dim: int | Literal["auto"] | None = None,
    standardize: bool = True,
    columns: str | None = None,
    embedding_column: str | None = None,
    id_column: str | None = None,
    batch_size: int = 8192,
    sample_size: int = 20_000,
    force: bool = False,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Reduce segment embeddings into the workspace pool (or, with ``apply``, add to it).

    Without ``apply`` this fits the reducer and stores the pool; with ``apply`` it maps new
    segments with the saved reducer and adds them.

    Parameters
    ----------
    root : Path
        The workspace folder (``--workspace``/``-w``).
    source : Path
        Parquet file of segments: ``segment_id`` and the embedding (a list column or
        numeric columns); other columns pass through to the pool.
    apply : bool, default False
        Map new segments with the saved reducer and add them to the pool.
    method : {"pca", "autoencoder", "identity", "ipca"}, default "pca"
        The reducer: exact streaming PCA, an autoencoder, none, or the older
        IncrementalPCA (for comparison).
    dim : int or "auto", optional
        Reduced dimension (default: the settings', "auto": ``core.reduce.choose_dim``).
    standardize : bool, default True
        Scale each input column to unit variance.
    columns : str, optional
        Glob of numeric embedding columns, e.g. ``"emb_*"``.
    embedding_column : str, optional
        The list column holding the embedding.
    id_column : str, optional
        The segment id column (default ``segment_id``).
    batch_size : int, default 8192
        Rows read per batch.
    sample_size : int, default 20000
        Rows sampled to train the autoencoder and measure the reconstruction error.
    force : bool, default False
        Refit the reducer over an existing pool.
    progress : callable ``(phase, done, total) -> None``, optional
        Called as the work advances (the CLI draws its progress bar with it).
    wait : bool, default False
        Wait for another command's workspace lock instead of failing at once
        (``WorkspaceLockedError``).

    Returns
    -------
    dict
        The summary ``--json`` prints: ``segments`` (rows read), ``added``, ``pool_size``,
        ``method``, ``dim``, ``dim_choice`` (why, after --dim auto), ``input_dim``, ``reconstruction_error``,
        ``passthrough_columns``, ``warnings`` (embedding columns holding one value in
        every row, and principal components carrying no variance, when the reducer is
        fitted).

    Raises
    ------
    InputError
        The segments file has a bad value (``SchemaError``: a missing or mistyped column;
        ``DuplicateError``: a repeated segment id); the message names file, column and row.
    OptionValueError
        A size below 1; exit code 2.
    WorkspaceError
        No workspace at ``root``, a pool exists already (without ``force``), or there is no
        saved reducer to ``apply``.
    WorkspaceLockedError
        Another command holds the lock and ``wait`` is False.
    """
    from bams_cli.core.reduce import Reducer, fit_reducer  # sklearn: ~1 s to import

    if isinstance(dim, str) and dim != "auto":
        raise OptionValueError(f"--dim {dim!r}: expected a whole number or 'auto'")
    for flag, value in (
        ("--batch-size", batch_size),
        ("--sample-size", sample_size),
        ("--dim", None if dim == "auto" else dim),
    ):
        if value is not None and value < 1:
            raise OptionValueError(f"{flag} {value}: must be >= 1")
    ws = Workspace(root)
    settings = ws.require_initialised()
    dim_given = dim
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
    made = read_metadata_json(ws.segments_path) if ws.segments_path.exists() else {}
    # A re-run of a step that made or grew the pool (a Makefile target, a CI retry) is a
    # no-op: the same file with the same options, or the same file --apply'd already. A
    # different file or other options need --force or --apply.
    again = (
        request["source_sha256"] in (made.get("applied_sha256") or [])
        if apply
        else all(made.get(k) == v for k, v in request.items())
    )
    if not force and ws.segments_path.exists():
        if again:
            names = pq.read_schema(ws.segments_path).names
            return {
                "segments": str(ws.segments_path),
                "added": 0,
                "pool_size": int(pq.read_metadata(ws.segments_path).num_rows),
                "method": made.get("method"),
                "dim": made.get("dim"),
                "dim_choice": made.get("dim_choice"),
                "passthrough_columns": [
                    c for c in names if c != SID and not (c[:1] == "z" and c[1:].isdigit())
                ],
                "unchanged": True,
                "note": "the pool already holds this file's segments, added by --apply"
                if apply
                else "the pool was already reduced from this file with these options",
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
    list_col, cols = embedding_layout(
        schema,
        source,
        id_column=id_column,
        columns=columns,
        embedding_column=embedding_column or (layout["list"] if layout else None),
        fitted_columns=layout["columns"] if layout and not layout["list"] else None,
    )
    ids = read_ids(source, id_column)
    stream = EmbeddingStream(source, list_col, cols, batch_size)
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
            sample = sample_rows(stream, take)
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
    # Why this many (--dim auto); --apply keeps the fit's.
    dim_choice = made.get("dim_choice") if apply else reducer.dim_choice
    meta = {
        "method": reducer.method,
        "dim": reducer.dim,
        "dim_choice": dim_choice,
        "source": str(source),
        "seed": settings.seed,
        "reconstruction_error": reducer.reconstruction_error,
        # --apply keeps what made the pool (its re-run stays a no-op) and adds its file.
        **({k: made.get(k) for k in request} if apply else request),
        "applied_sha256": [*(made.get("applied_sha256") or []), request["source_sha256"]]
        if apply
        else [],
        # Whether the count is the settings' embedding_dim (no --dim), so that `fit` can say
        # when settings.toml has been edited since and the pool does not follow it.
        "dim_from_settings": made.get("dim_from_settings") if apply else dim_given is None,
    }
    warnings = (
        []
        if apply
        else [
            *_constant_columns(source, list_col, cols, reducer.constant, n),
            *_null_components(source, reducer, n),
        ]
    )
    with transaction() as tx:
        if not apply:
            saved_layout = {
                "layout_list": np.array(list_col or ""),
                "layout_columns": np.array(cols, dtype=str),
            }
            tx.write_with(ws.reducer_path, lambda p: savez(p, reducer.to_arrays() | saved_layout))
        tx.write_parquet(ws.segments_path, schemas.SEGMENTS.conform(table, meta))
    return {
        "segments": str(ws.segments_path),
        "added": n,
        "pool_size": table.num_rows,
        "method": reducer.method,
        "dim": reducer.dim,
        "dim_choice": dim_choice,
        "input_dim": int(expected),
        "reconstruction_error": reducer.reconstruction_error,
        "passthrough_columns": passthrough,
        "warnings": warnings,
    }


def _null_components(source: Path, reducer: Reducer, n: int) -> list[str]:
    """A warning saying how many of the principal components carry no variance: a
    ``--dim`` above the embedding's rank (none for the identity and the autoencoder, nor
    for a single row, which spans nothing).

    Legal, like a constant column, but the surplus coordinates are constant: the model
    gets coordinates whose lengthscales no data can inform (only their prior sets them).
    """
    from bams_cli.core.reduce import null_components

    if reducer.method not in ("pca", "ipca") or n < 2:
        return []
    null = null_components(reducer.explained_variance, reducer.constant)
    k, dim = int(null.sum()), len(null)
    if not k:
        return []
    rank = dim - k
    coords = f"z{rank} is" if k == 1 else f"z{rank}..z{dim - 1} are"
    spans = (
        f"the embedding spans only {rank} dimension{'s' * (rank != 1)}"
        if rank
        else "every row is the same point"
    )
    fix = f": pass --dim {rank}" if rank else ""
    return [
        f"{source}: {k} of the {dim} principal components carr{'ies' if k == 1 else 'y'} no "
        f"variance ({spans}), so "
        f"{coords} constant in every row and carr{'ies' if k == 1 else 'y'} no "
        f"information{fix}"
    ]


def _constant_columns(
    source: Path, list_col: str | None, cols: list[str], constant: np.ndarray, n: int
) -> list[str]:
    """A warning naming the embedding columns that hold one value in every row (none for
    a single row, where every column does).

    Legal, but a constant column carries no information: most likely a broken export or
    a dead feature. With --method identity it reaches the model as a coordinate whose ARD
    lengthscale no data can inform (only its prior sets it); PCA gives it no weight.
    """
    where = np.flatnonzero(constant)
    if n < 2 or not len(where):
        return []
    first = ", ".join(str(j + 1) if list_col else shown(cols[j], 40) for j in where[:5]) + (
        " ..." if len(where) > 5 else ""
    )
    if list_col:
        what = (
            f"column {shown(list_col)}: embedding position{'s' * (len(where) > 1)} {first} "
            f"(of {len(constant)}) hold{'s' * (len(where) == 1)} one value in all "
            f"{n} rows"
        )
    elif len(where) == 1:
        what = f"column {first}: one value in all {n} rows"
    else:
        what = f"{len(where)} embedding columns hold one value each in all {n} rows ({first})"
    return [f"{source}: {what}; a constant embedding dimension carries no information: drop it"]
