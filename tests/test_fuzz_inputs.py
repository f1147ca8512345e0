"""Fuzzed input tables for `ingest-results` and `embed-reduce` (Hypothesis).

For any generated table (columns of random Arrow types, NaN, inf, huge and tiny values,
duplicate and missing rows, renamed, missing and extra columns, empty files, CSV written with
other line endings and quoting) the command either

* succeeds, and the state it wrote is consistent: readable, every value finite and within
  the range the model holds, no (segment, fidelity) pair active twice, no logged row lost,
  the pool's ids unique with finite coordinates, and one warning line naming the embedding
  columns that hold one value in every row, if any; or
* fails with exit code 1 and exactly one line on stderr that names the input file, never
  the catch-all, and leaves every workspace file byte-for-byte as it was.

The fast runs keep the example counts small (``make test``); the ``slow`` variants run many
more examples and also run `fit` on every accepted results file.
"""

from __future__ import annotations

import decimal
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from bams_cli.state.workspace import Workspace
from tests.conftest import invoke, ok, tree_hash, write_batch, write_toy

PICKED = [f"t{i:06d}" for i in range(6)]
MAX_VALUE = 1e150  # pipeline.MAX_VALUE: what the model can hold


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    """A reduced 400-segment toy2d pool, batch 1 (six picks) awaiting results, and one
    result already logged (t000000 at level 0), so conflicts and --replace are reachable."""
    runner = CliRunner()
    tmp = tmp_path_factory.mktemp("fuzz")
    seg, _ = write_toy(tmp / "data")
    ws = tmp / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.56", "--costs", "1,0.1", "--dim", "2")
    ok(runner, "embed-reduce", "-w", ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize")  # fmt: skip
    write_batch(ws, 1, PICKED, [0, 0, 0, 1, 1, 1])
    first = tmp / "first.parquet"
    pq.write_table(pa.table({"segment_id": ["t000000"], "fidelity": [0], "value": [0.7]}), first)
    ok(runner, "ingest-results", "-w", ws, first)
    return ws


# ---- strategies ------------------------------------------------------------------------------
FLOATS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e150, -1e150, 1.0000001e150, 1e308, 5e-324, 0.56]),
    st.floats(-10, 10),
)
IDS = st.sampled_from([*PICKED, "t000399", "nope", "", " t000001", "T000001", "b0001-0001"])
TEXT = st.one_of(IDS, st.text(max_size=8), st.sampled_from(["high", "low1", "ok", "crashed", "1"]))


@st.composite
def column(draw, kind: str, n: int) -> pa.Array:
    """n values of one Arrow type; which type depends on the column's role and chance."""
    choices = ["string", "int64", "float64", "null", "bool", "list", "binary", "decimal",
               "dictionary", "struct", "float16"]  # fmt: skip
    weights = {"segment_id": "string", "request_id": "string", "fidelity": "int64",
               "value": "float64", "status": "string"}  # fmt: skip
    t = draw(st.sampled_from([weights.get(kind, "string")] * 25 + choices))
    maybe = lambda s: st.one_of(st.none(), s) if draw(st.booleans()) else s  # noqa: E731
    if t == "string":
        values = draw(st.lists(maybe(TEXT if kind != "request_id" else st.sampled_from(
            ["b0001-0001", "b0001-0004", "b0001-0009", "p0001-0001", "junk", ""])),
            min_size=n, max_size=n))  # fmt: skip
        return pa.array(values, pa.string())
    if t == "int64":
        ints = st.one_of(st.integers(-2, 3), st.integers(-(2**63), 2**63 - 1))
        return pa.array(draw(st.lists(maybe(ints), min_size=n, max_size=n)), pa.int64())
    if t == "float64":
        return pa.array(draw(st.lists(maybe(FLOATS), min_size=n, max_size=n)), pa.float64())
    if t == "float16":
        values = draw(st.lists(st.floats(-2, 2, width=16), min_size=n, max_size=n))
        return pa.array(np.array(values, np.float16))
    if t == "decimal":
        digits = st.decimals(-1e6, 1e6, places=2, allow_nan=False)
        return pa.array(draw(st.lists(digits, min_size=n, max_size=n)), pa.decimal128(12, 2))
    if t == "null":
        return pa.nulls(n)
    if t == "bool":
        return pa.array(draw(st.lists(st.booleans(), min_size=n, max_size=n)), pa.bool_())
    if t == "list":
        return pa.array(draw(st.lists(st.lists(IDS, max_size=2), min_size=n, max_size=n)))
    if t == "binary":
        values = draw(st.lists(IDS.map(str.encode), min_size=n, max_size=n))
        return pa.array(values, pa.binary())
    if t == "dictionary":
        return pa.array(draw(st.lists(TEXT, min_size=n, max_size=n))).dictionary_encode()
    return pa.array([{"a": v} for v in draw(st.lists(st.integers(0, 1), min_size=n, max_size=n))])


@st.composite
def plausible_results(draw) -> pa.Table:
    """What a simulation team sends, mostly right: picked segments at their levels, finite
    values; now and then one cell goes wrong (a huge value, a name for a level, a stray id)."""
    rows = draw(st.lists(st.sampled_from(range(len(PICKED))), min_size=1, max_size=6, unique=True))
    ids = [PICKED[i] for i in rows]
    levels: list[object] = [0 if i < 3 else 1 for i in rows]
    values: list[object] = draw(st.lists(st.floats(-5, 5), min_size=len(rows), max_size=len(rows)))
    if draw(st.booleans()):
        k = draw(st.integers(0, len(rows) - 1))
        which = draw(st.sampled_from(["value", "fidelity", "segment_id"]))
        if which == "value":
            values[k] = draw(FLOATS)
        elif which == "fidelity":
            levels = [str(v) for v in levels]
            levels[k] = draw(st.sampled_from(["high", "low1", "2", "-1", "1.0", " 0 ", ""]))
        else:
            ids[k] = draw(IDS)
    cols = {"segment_id": ids, "fidelity": levels, "value": values}
    if draw(st.booleans()):
        cols["status"] = draw(st.lists(st.sampled_from(["", "ok", "OK", "crashed", None]),
                                       min_size=len(rows), max_size=len(rows)))  # fmt: skip
    if draw(st.booleans()):
        cols["sim_version"] = ["v1"] * len(rows)
    return pa.table(cols)


@st.composite
def results_table(draw) -> pa.Table:
    if draw(st.booleans()):
        return draw(plausible_results())
    n = draw(st.integers(0, 6))
    names = ["segment_id", "fidelity", "value"]
    names = [c for c in names if draw(st.integers(0, 9))]  # now and then a column is missing
    names += draw(st.lists(st.sampled_from(["request_id", "status", "note", "Value", "_x"]),
                           max_size=2, unique=True))  # fmt: skip
    cols = {name: draw(column(name, n)) for name in names}
    if n and draw(st.booleans()):  # duplicate rows
        take = draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=n))
        return pa.table(cols).take(pa.array(list(range(n)) + take)) if cols else pa.table({})
    return pa.table(cols)


def _csv_cell(v: object) -> str:
    if v is None:
        return ""
    if isinstance(v, float) and not math.isfinite(v):
        return {True: "nan"}.get(math.isnan(v), "inf" if v > 0 else "-inf")
    text = str(v)
    return '"' + text.replace('"', '""') + '"' if any(c in text for c in ',"\n\r') else text


@st.composite
def csv_bytes(draw, table: pa.Table) -> bytes:
    """A CSV of the table's scalar columns, with chance line endings, quoting and raggedness."""
    cols = [c for c in table.column_names if not pa.types.is_nested(table.schema.field(c).type)]
    end = draw(st.sampled_from(["\n", "\r\n"]))
    rows = [",".join(cols)]
    for i in range(table.num_rows):
        cells = [_csv_cell(table.column(c)[i].as_py()) for c in cols]
        if draw(st.integers(0, 9)) == 0:  # a ragged row
            cells = cells[:-1] if cells and draw(st.booleans()) else [*cells, "7"]
        rows.append(",".join(cells))
    text = end.join(rows) + (end if draw(st.booleans()) else "")
    return (("\ufeff" if draw(st.integers(0, 9)) == 0 else "") + text).encode()


# ---- the property ----------------------------------------------------------------------------
def _refused_cleanly(r, source: Path, before: dict, ws: Path) -> None:
    lines = r.stderr.splitlines()
    assert r.exit_code == 1, (r.exit_code, r.output)
    assert len(lines) == 1 and lines[0].startswith(f"error: {source}"), r.stderr
    assert "(unexpected" not in r.stderr and "Traceback" not in r.output
    assert tree_hash(ws) == before


def _log_is_consistent(ws: Path, old: pl.DataFrame, replace: bool) -> pl.DataFrame:
    log = Workspace(ws).read_observations(active_only=False)
    # Nothing lost: the old log is the new one's first rows; a --replace only deactivates.
    head = log.head(old.height)
    keep = ["segment_id", "fidelity", "value", "source_sha256"]
    assert head.select(keep).equals(old.select(keep))
    if replace:
        assert (~head["active"] | old["active"]).all()
    else:
        assert head["active"].equals(old["active"])
    active = log.filter(pl.col("active"))
    assert not active.select("segment_id", "fidelity").is_duplicated().any()
    assert active["value"].is_finite().all() and (active["value"].abs() <= MAX_VALUE).all()
    assert active["fidelity"].is_in([0, 1]).all()
    pool, _ = Workspace(ws).read_pool()
    assert active["segment_id"].is_in(list(pool)).all()
    return log


def _check_ingest(template: Path, table: pa.Table, as_csv: bytes | None, flags: list[str],
                  then_fit: bool = False) -> None:  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        ws = Path(tmp) / "ws"
        shutil.copytree(template, ws)
        source = Path(tmp) / ("r.csv" if as_csv is not None else "r.parquet")
        if as_csv is not None:
            source.write_bytes(as_csv)
        else:
            pq.write_table(table, source)
        old = Workspace(ws).read_observations(active_only=False)
        before = tree_hash(ws)
        r = invoke(CliRunner(), "ingest-results", "-w", ws, source, *flags)
        event("refused" if r.exit_code else "accepted")  # --hypothesis-show-statistics
        if r.exit_code != 0:
            _refused_cleanly(r, source, before, ws)
            return
        log = _log_is_consistent(ws, old, "--replace" in flags)
        if then_fit and log.filter(pl.col("active") & (pl.col("fidelity") == 0)).height >= 2:
            fit = invoke(CliRunner(), "fit", "-w", ws, "--restarts", "1")
            assert fit.exit_code in (0, 1) and "(unexpected" not in fit.stderr, fit.output


FLAGS = st.lists(st.sampled_from(["--replace", "--allow-unselected"]), unique=True)
FAST = settings(
    max_examples=30,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
SLOW = settings(FAST, max_examples=400)


@FAST
@given(table=results_table(), flags=FLAGS)
def test_ingest_parquet_either_consistent_or_refused_cleanly(template, table, flags):
    _check_ingest(template, table, None, flags)


@FAST
@given(data=st.data(), flags=FLAGS)
def test_ingest_csv_either_consistent_or_refused_cleanly(template, data, flags):
    table = data.draw(results_table())
    _check_ingest(template, table, data.draw(csv_bytes(table)), flags)


@pytest.mark.slow
@SLOW
@given(data=st.data(), flags=FLAGS)
def test_ingest_many_tables_then_fit(template, data, flags):
    table = data.draw(results_table())
    as_csv = data.draw(csv_bytes(table)) if data.draw(st.booleans()) else None
    _check_ingest(template, table, as_csv, flags, then_fit=True)


# ---- embed-reduce ------------------------------------------------------------------------------
@st.composite
def segments_table(draw) -> tuple[pa.Table, list[str]]:
    """A segments file and the embed-reduce options to read it with."""
    n = draw(st.integers(0, 8))
    cols: dict[str, pa.Array] = {}
    if draw(st.integers(0, 9)):
        unique = draw(st.booleans())
        ids = [f"s{i}" for i in range(n)] if unique else draw(
            st.lists(st.sampled_from(["a", "b", "t000001"]), min_size=n, max_size=n))  # fmt: skip
        cols["segment_id"] = pa.array(ids, pa.string())
        if draw(st.integers(0, 3)) == 0:
            cols["segment_id"] = draw(column("segment_id", n))
    layout = draw(st.sampled_from(["columns", "list", "both"]))
    if layout in ("columns", "both"):
        for j in range(draw(st.integers(1, 3))):
            kind = draw(st.sampled_from(["float64"] * 4 + ["int64", "string", "null", "bool"]))
            if kind == "float64":
                cols[f"e{j}"] = pa.array(draw(st.lists(FLOATS, min_size=n, max_size=n)))
            elif kind == "int64":
                cols[f"e{j}"] = pa.array(draw(st.lists(st.integers(-5, 5), min_size=n, max_size=n)))
            else:
                cols[f"e{j}"] = draw(column(kind, n))
    if layout in ("list", "both"):
        width = draw(st.integers(1, 3))
        rows = st.lists(st.one_of(st.floats(-3, 3), FLOATS), min_size=width, max_size=width)
        if draw(st.integers(0, 4)) == 0:
            rows = st.one_of(st.none(), st.lists(FLOATS, max_size=3))  # ragged, null
        cols["emb"] = pa.array(draw(st.lists(rows, min_size=n, max_size=n)), pa.list_(pa.float64()))
    if draw(st.integers(0, 5)) == 0:
        cols[draw(st.sampled_from(["z0", "tag"]))] = pa.array(["x"] * n)
    method = draw(st.sampled_from(["identity", "pca"]))
    args = ["--method", method, "--force", "--dim", str(draw(st.integers(1, 3)))]
    if layout == "columns" or (layout == "both" and draw(st.booleans())):
        args += ["--columns", "e*"]
    if draw(st.booleans()):
        args.append("--no-standardize")
    return pa.table(cols) if cols else pa.table({"x": pa.array([], pa.int64())}), args


def _check_embed(template: Path, table: pa.Table, args: list[str]) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        ws = Path(tmp) / "ws"
        shutil.copytree(template, ws)
        source = Path(tmp) / "seg.parquet"
        pq.write_table(table, source)
        before = tree_hash(ws)
        r = invoke(CliRunner(), "embed-reduce", "-w", ws, source, *args)
        event("refused" if r.exit_code else "accepted")
        if r.exit_code != 0:
            _refused_cleanly(r, source, before, ws)
            return
        ids, X = Workspace(ws).read_pool()
        assert len(ids) == table.num_rows == len(set(ids))
        assert np.isfinite(X).all() and X.shape[1] >= 1
        assert ids.tolist() == [str(v) for v in table.column("segment_id").to_pylist()]
        with np.load(ws / "reducer.npz") as saved:
            assert all(np.isfinite(a).all() for a in saved.values() if a.dtype.kind == "f")
        _constant_columns_are_warned(table, args, r.stderr, source)


def _constant_columns_are_warned(table: pa.Table, args: list[str], stderr: str, source: Path):
    if "--columns" in args:
        names = [c for c in table.column_names if c.startswith("e")]
        E = np.column_stack([np.asarray(table.column(c).to_pylist(), float) for c in names])
        dims = [repr(c) for c in names]
    else:
        E = np.asarray(table.column("emb").to_pylist(), float)
        dims = [str(j + 1) for j in range(E.shape[1])]
    constant = [d for d, col in zip(dims, E.T, strict=True) if (col == col[0]).all()]
    warned = [line for line in stderr.splitlines() if "constant embedding" in line]
    if len(E) < 2 or not constant:  # one row: every column is constant, nothing to say
        assert warned == []
        return
    event("constant column warned")
    [line] = warned
    assert line.startswith(f"warning: {source}: ") and all(d in line for d in constant), line


@FAST
@given(case=segments_table())
def test_embed_reduce_either_consistent_or_refused_cleanly(template, case):
    _check_embed(template, *case)


@pytest.mark.slow
@SLOW
@given(case=segments_table())
def test_embed_reduce_many_tables(template, case):
    _check_embed(template, *case)


def test_decimal_inputs_are_exact_enough(template, tmp_path):
    # A guard on the fuzzer's decimal branch: decimals reach the log as their float value.
    res = tmp_path / "d.parquet"
    value = pa.array([decimal.Decimal("0.25")], pa.decimal128(4, 2))
    pq.write_table(pa.table({"segment_id": [PICKED[1]], "fidelity": [0], "value": value}), res)
    ws = tmp_path / "ws"
    shutil.copytree(template, ws)
    ok(CliRunner(), "ingest-results", "-w", ws, res)
    assert Workspace(ws).read_observations()["value"].to_list() == [0.7, 0.25]
