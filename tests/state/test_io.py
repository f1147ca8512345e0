"""State files: schema conformance, metadata, atomic writes, round trips (also Hypothesis)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bams_cli import __version__
from bams_cli.core.reduce import Reducer
from bams_cli.errors import SchemaError
from bams_cli.settings import Level, Settings
from bams_cli.state import schemas
from bams_cli.state.io import read_metadata, transaction

ids = st.text(min_size=1, max_size=12)
finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


def _rows(schema: pa.Schema, draw) -> dict:
    gen = {
        pa.string(): ids,
        pa.int64(): st.integers(-(2**40), 2**40),
        pa.float64(): finite,
        pa.bool_(): st.booleans(),
    }
    n = draw(st.integers(0, 6))
    return {f.name: draw(st.lists(gen[f.type], min_size=n, max_size=n)) for f in schema}


@pytest.mark.parametrize("state", schemas.ALL, ids=lambda s: s.name)
@settings(
    max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.data())
def test_every_state_file_round_trips(tmp_path: Path, state, data):
    cols = _rows(state.schema, data.draw)
    table = pa.table(cols, schema=state.schema)
    path = tmp_path / "f.parquet"
    with transaction() as tx:
        tx.write_parquet(path, state.conform(table, {"seed": 7}))
    back = state.check(pq.read_table(path), path)
    assert back.select(state.schema.names).to_pylist() == table.to_pylist()
    meta = read_metadata(path)
    assert meta["schema_version"] == str(state.version)
    assert meta["tool_version"] == __version__
    assert meta["seed"] == "7" and "command" in meta and "written_at" in meta


def test_conform_names_the_missing_column():
    with pytest.raises(SchemaError, match="observations.parquet: column 'fidelity'"):
        schemas.OBSERVATIONS.conform(pa.table({"segment_id": ["a"], "value": [1.0]}))


def test_check_names_a_wrong_type(tmp_path):
    p = tmp_path / "o.parquet"
    pq.write_table(pa.table({"segment_id": [1], "mu": [1.0], "sd": [1.0]}), p)
    with pytest.raises(SchemaError, match="column 'segment_id': expected type string, got int64"):
        schemas.SCORES.check(pq.read_table(p), p)


def test_failed_transaction_leaves_no_file_and_keeps_the_old_one(tmp_path):
    target = tmp_path / "x.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), transaction() as tx:
        tx.write_text(target, "new")
        tx.write_text(tmp_path / "y.txt", "other")
        raise RuntimeError("boom")
    assert target.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.txt"]


@settings(max_examples=50, deadline=None)
@given(
    gammas=st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=1, max_size=4),
    costs=st.lists(st.floats(1e-4, 10, allow_nan=False), min_size=0, max_size=3),
    seed=st.integers(0, 2**31),
    dim=st.integers(1, 64),
)
def test_settings_round_trip(gammas, costs, seed, dim):
    levels = (Level("high", 1.0), *(Level(f"low{i}", c) for i, c in enumerate(costs, 1)))
    s = Settings(gammas=tuple(gammas), levels=levels, seed=seed, embedding_dim=dim).validate()
    back = Settings.from_toml(s.to_toml())
    assert back == s
    assert all(math.isfinite(g) for g in back.gammas)


@settings(max_examples=20, deadline=None)
@given(
    D=st.integers(1, 8),
    d=st.integers(1, 4),
    method=st.sampled_from(["pca", "autoencoder", "identity"]),
)
def test_reducer_round_trip(D, d, method):
    rng = np.random.default_rng(0)
    layers = {"pca": 1, "autoencoder": 2, "identity": 0}[method]
    shapes = [(D, d)] if layers == 1 else [(D, 5), (5, d)][:layers]
    r = Reducer(
        method,
        rng.standard_normal(D),
        rng.random(D) + 0.5,
        weights=[rng.standard_normal(s) for s in shapes],
        biases=[rng.standard_normal(s[1]) for s in shapes],
        reconstruction_error={"pca": 0.25},
    )
    back = Reducer.from_arrays(r.to_arrays())
    E = rng.standard_normal((7, D))
    np.testing.assert_array_equal(back.transform(E), r.transform(E))
    assert back.reconstruction_error == {"pca": 0.25}
