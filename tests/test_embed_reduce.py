"""embed-reduce: layouts, methods, --apply, and bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from scipy.linalg import subspace_angles
from sklearn.decomposition import PCA

from bams_cli.core import synthetic
from bams_cli.state.io import read_metadata
from bams_cli.state.workspace import Workspace
from tests.conftest import STAGED_PLAN, invoke, ok, tree_hash, write_batch


def _av_files(folder: Path, n: int = 600, layout: str = "list") -> Path:
    pool = synthetic.av_like(n, seed=3)
    folder.mkdir(parents=True, exist_ok=True)
    E = pool.features[:, :40]  # keep tests quick: 40 embedding columns
    cols: dict = {"segment_id": pool.ids}
    if layout == "list":
        cols["emb"] = pa.FixedSizeListArray.from_arrays(pa.array(E.ravel()), E.shape[1])
    else:
        for j in range(E.shape[1]):
            cols[f"emb_{j:03d}"] = E[:, j]
    cols["difficulty"] = pool.extra["difficulty"]
    cols["scenario"] = ["intersection" if i % 3 else "highway" for i in range(n)]
    path = folder / f"segments-{layout}.parquet"
    pq.write_table(pa.table(cols), path, row_group_size=128)
    return path


@pytest.fixture
def av_ws(tmp_path, runner) -> Path:
    ws = tmp_path / "ws"
    assert (
        invoke(
            runner, "init", "-w", ws, "--gamma", "0.3", "--costs", "1,0.15625", "--dim", "6"
        ).exit_code
        == 0
    )
    return ws


@pytest.mark.parametrize("layout", ["list", "columns"])
def test_pca_matches_batch_pca_and_passes_columns_through(av_ws, runner, tmp_path, layout):
    seg = _av_files(tmp_path / "d", layout=layout)
    args = ["--columns", "emb_*"] if layout == "columns" else []
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--batch-size", "100", *args)
    assert r.exit_code == 0, r.output
    ws = Workspace(av_ws)
    ids, Z = ws.read_pool()
    assert Z.shape == (600, 6) and ids[0] == "seg-000000"
    table = ws.read_segments()
    assert table.column("scenario").to_pylist()[:3] == ["highway", "intersection", "intersection"]
    assert read_metadata(ws.segments_path)["schema_version"] == "1"
    # Streaming exact PCA (batches of 100 rows, row groups of 128) is full-batch PCA of the
    # standardised columns, up to one sign per component.
    E = synthetic.av_like(600, seed=3).features[:, :40]
    S = (E - E.mean(0)) / E.std(0, ddof=1)
    ref = PCA(6, svd_solver="full").fit(S)
    Zref = ref.transform(S)
    sign = np.sign(np.sum(Z * Zref, axis=0))
    np.testing.assert_allclose(Z, sign * Zref, rtol=0, atol=1e-9)
    # the sign is the reducer's own: each component's largest loading is positive
    with np.load(ws.reducer_path) as saved:
        W = saved["W0"]
        np.testing.assert_allclose(saved["explained_variance"], ref.explained_variance_, rtol=1e-9)
    assert np.all(W[np.argmax(np.abs(W), axis=0), np.arange(6)] > 0)


@pytest.mark.slow
def test_ipca_is_kept_for_comparison(av_ws, runner, tmp_path):
    seg = _av_files(tmp_path / "d")
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--method", "ipca", "--json")
    assert r.exit_code == 0, r.output
    _, Z = Workspace(av_ws).read_pool()
    E = synthetic.av_like(600, seed=3).features[:, :40]
    S = (E - E.mean(0)) / E.std(0, ddof=1)
    ref = PCA(6).fit(S)
    W = np.linalg.lstsq(S, Z, rcond=None)[0]  # the linear map the reducer applied
    # IncrementalPCA in batches of 8192 rows sees all 600 at once: the same subspace
    assert np.max(subspace_angles(W, ref.components_.T)) < 1e-6


def test_apply_maps_fitted_segments_identically(av_ws, runner, tmp_path):
    seg = _av_files(tmp_path / "d")
    assert invoke(runner, "embed-reduce", "-w", av_ws, seg).exit_code == 0
    ws = Workspace(av_ws)
    ids, Z = ws.read_pool()
    # re-apply to the same rows under new ids: identical coordinates
    t = pq.read_table(seg)
    new_ids = pa.array([f"new-{i}" for i in range(t.num_rows)])
    again = tmp_path / "again.parquet"
    pq.write_table(t.set_column(0, "segment_id", new_ids), again)
    r = invoke(runner, "embed-reduce", "-w", av_ws, again, "--apply")
    assert r.exit_code == 0, r.output
    ids2, Z2 = ws.read_pool()
    assert len(ids2) == 1200
    np.testing.assert_array_equal(Z2[600:], Z)
    # Make runs each step again: the same --apply, and the step that made the pool, are
    # no-ops (the --apply one was refused: its ids are in the pool, by itself).
    for args in ([again, "--apply"], [seg]):
        before = tree_hash(av_ws)
        r = invoke(runner, "embed-reduce", "-w", av_ws, *args, "--json")
        assert r.exit_code == 0, r.output
        out = json.loads(r.stdout)
        assert out["unchanged"] is True and out["added"] == 0 and out["pool_size"] == 1200
        assert tree_hash(av_ws) == before
    # A different file whose ids are in the pool is still refused.
    other = tmp_path / "other.parquet"
    pq.write_table(pq.read_table(again).slice(0, 5), other)
    r = invoke(runner, "embed-reduce", "-w", av_ws, other, "--apply")
    assert r.exit_code == 1 and "is already in the pool" in r.stderr


def test_apply_rejects_ids_already_in_pool(av_ws, runner, tmp_path):
    seg = _av_files(tmp_path / "d")
    assert invoke(runner, "embed-reduce", "-w", av_ws, seg).exit_code == 0
    before = tree_hash(av_ws)
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--apply")
    assert r.exit_code == 1
    assert "column 'segment_id', row 1: segment id 'seg-000000' is already in the pool" in r.stderr
    assert tree_hash(av_ws) == before


@pytest.mark.slow
def test_autoencoder_reports_error_beside_pca(av_ws, runner, tmp_path):
    seg = _av_files(tmp_path / "d", n=400)
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--method", "autoencoder", "--json")
    assert r.exit_code == 0, r.output
    import json

    summary = json.loads(r.stdout)
    err = summary["reconstruction_error"]
    assert {"pca", "pca_heldout", "autoencoder_heldout"} <= set(err)
    assert 0 < err["autoencoder_heldout"] < 1.0  # standardised units: far below the variance, 1
    _, Z = Workspace(av_ws).read_pool()
    assert Z.shape == (400, 6) and np.all(np.abs(Z) <= 1)  # tanh bottleneck


def _write(path: Path, cols: dict) -> Path:
    pq.write_table(pa.table(cols), path)
    return path


@pytest.mark.parametrize(
    ("cols", "args", "needle"),
    [
        (
            {"segment_id": ["a", "b", "a"], "e0": [1.0, 2, 3], "e1": [1.0, 0, 1]},
            ["--columns", "e*"],
            "column 'segment_id', row 3: segment id 'a' appears again (first at row 1)",
        ),
        (
            {"segment_id": ["a", "b", "c"], "e0": [1.0, float("nan"), 3], "e1": [1.0, 0, 1]},
            ["--columns", "e*"],
            "column 'e0', row 2: non-finite or missing value",
        ),
        (
            {"segment_id": ["a", "b", "c"], "e0": [1.0, 2, 3], "e1": [1.0, 1e308, 1]},
            ["--columns", "e*"],
            "column 'e1', row 2: embedding value 1e+308 is beyond +-1e+100",
        ),
        (
            {"segment_id": ["a", "b", "c"], "emb": [[1.0, 2.0], [0.5, 0.1], [-3e200, 1.0]]},
            [],
            "column 'emb', row 3: embedding value -3e+200 is beyond +-1e+100",
        ),
        (
            {"id": ["a", "b", "c"], "e0": [1.0, 2, 3]},
            ["--columns", "e*"],
            "column 'segment_id': no id column 'segment_id'",
        ),
        (
            {"segment_id": ["a", "b", "c"], "e0": [1.0, 2, 3]},
            ["--columns", "z*"],
            "--columns 'z*' matches no column",
        ),
        (
            {"segment_id": ["a", "b", "c"], "e0": [1.0, 2, 3]},
            [],
            "cannot tell which column holds the embedding",
        ),
        (
            {"segment_id": ["a", "b", "c"], "emb": [[1.0, 2.0], [1.0], [0.0, 1.0]]},
            [],
            "column 'emb', row 2: embedding has 1 values, expected 2",
        ),
    ],
)
def test_bad_segments_fail_cleanly(av_ws, runner, tmp_path, cols, args, needle):
    src = _write(tmp_path / "bad.parquet", cols)
    before = tree_hash(av_ws)
    r = invoke(runner, "embed-reduce", "-w", av_ws, src, "--dim", "1", *args)
    assert r.exit_code == 1
    assert needle in r.stderr, r.stderr
    assert tree_hash(av_ws) == before


def test_integer_ids_are_accepted_as_strings(av_ws, runner, tmp_path):
    src = _write(
        tmp_path / "ints.parquet",
        {"segment_id": [10, 11, 12], "e0": [1.0, 2, 4], "e1": [0.0, 1, 1]},
    )
    r = invoke(runner, "embed-reduce", "-w", av_ws, src, "--columns", "e*", "--dim", "1")
    assert r.exit_code == 0, r.output
    ids, _ = Workspace(av_ws).read_pool()
    assert list(ids) == ["10", "11", "12"]


def test_rerun_is_a_no_op_and_a_refit_needs_force(av_ws, runner, tmp_path):
    seg = _av_files(tmp_path / "d")
    assert invoke(runner, "embed-reduce", "-w", av_ws, seg).exit_code == 0
    before = tree_hash(av_ws)
    # The same file with the same options (a Makefile re-run): nothing to do, exit 0.
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--json")
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert doc["unchanged"] is True and doc["added"] == 0 and doc["pool_size"] > 0
    assert tree_hash(av_ws) == before
    # Other options, or another file: a refit, which needs --force.
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--dim", "3")
    assert r.exit_code == 1 and "--force" in r.stderr
    other = tmp_path / "other.parquet"
    pq.write_table(pq.read_table(seg).slice(0, 50), other)
    r = invoke(runner, "embed-reduce", "-w", av_ws, other)
    assert r.exit_code == 1 and "--force" in r.stderr
    assert tree_hash(av_ws) == before
    assert invoke(runner, "embed-reduce", "-w", av_ws, seg, "--force", "--dim", "3").exit_code == 0


def test_uninitialised_workspace_is_not_created(runner, tmp_path):
    ws = tmp_path / "nothing-here"
    r = invoke(runner, "embed-reduce", "-w", ws, tmp_path / "x.parquet")
    assert r.exit_code == 1 and "no such workspace" in r.stderr
    assert not ws.exists()


def test_apply_takes_the_fitted_columns_by_name_in_any_order(av_ws, runner, tmp_path):
    seg = _av_files(tmp_path / "d", n=200, layout="columns")
    assert invoke(runner, "embed-reduce", "-w", av_ws, seg, "--columns", "emb_*").exit_code == 0
    _, Z = Workspace(av_ws).read_pool()
    t = pq.read_table(seg)
    emb = [c for c in t.column_names if c.startswith("emb_")]
    shuffled = t.select(["segment_id", *reversed(emb), "difficulty", "scenario"])
    shuffled = shuffled.set_column(0, "segment_id", pa.array([f"n{i}" for i in range(200)]))
    path = tmp_path / "reordered.parquet"
    pq.write_table(shuffled, path)
    r = invoke(runner, "embed-reduce", "-w", av_ws, path, "--apply")  # no --columns needed
    assert r.exit_code == 0, r.output
    _, Z2 = Workspace(av_ws).read_pool()
    np.testing.assert_array_equal(Z2[200:], Z)
    missing = tmp_path / "missing.parquet"
    pq.write_table(shuffled.drop_columns(["emb_007"]), missing)
    r = invoke(runner, "embed-reduce", "-w", av_ws, missing, "--apply")
    assert (
        r.exit_code == 1
        and "column 'emb_007': embedding column the reducer was fitted on is missing" in r.stderr
    )


def _fit_ten(ws, runner, truth, tmp_path):
    """Ten level-0 results, ingested and fitted: a workspace with a model."""
    write_batch(ws, 1, [f"t{i:06d}" for i in range(0, 40, 4)], [0] * 10)
    res = tmp_path / "r.parquet"
    invoke(runner, "simulate", ws / "batches" / "batch-0001.parquet", "--truth", truth, "-o", res)
    assert invoke(runner, "ingest-results", "-w", ws, res).exit_code == 0
    assert invoke(runner, "fit", "-w", ws, "--restarts", "1").exit_code == 0


def test_model_is_stale_after_the_pool_grows(toy_ws, runner, toy_files, tmp_path):
    _fit_ten(toy_ws, runner, toy_files[1], tmp_path)
    more = tmp_path / "more.parquet"
    pq.write_table(
        pa.table({"segment_id": ["new-1", "new-2"], "x0": [0.1, 0.2], "x1": [1.0, 2.0]}), more
    )
    assert invoke(runner, "embed-reduce", "-w", toy_ws, more, "--apply").exit_code == 0
    r = invoke(runner, "estimate", "-w", toy_ws, *STAGED_PLAN, "--samples", "5")
    assert r.exit_code == 1 and "fitted on a different segment pool" in r.stderr


def test_model_is_stale_after_the_same_segments_are_reduced_again(
    toy_ws, runner, toy_files, tmp_path
):
    # Same ids, new coordinates (PCA instead of identity): the scores no longer line up.
    seg, truth = toy_files
    _fit_ten(toy_ws, runner, truth, tmp_path)
    r = invoke(runner, "embed-reduce", "-w", toy_ws, seg, "--columns", "x*", "--force")
    assert r.exit_code == 0, r.output
    r = invoke(runner, "select", "-w", toy_ws, "--budget", "2", "--clusters", "1", "--workers", "1")
    assert r.exit_code == 1 and "fitted on a different segment pool" in r.stderr
    # The report still renders, the stale model a banner at the top and its scores unused.
    r = invoke(runner, "report", "-w", toy_ws)
    assert r.exit_code == 0, r.output
    summary = (toy_ws / "report" / "summary.md").read_text()
    assert "fitted on a different segment pool" in summary.split("\n## ")[0]


def test_a_damaged_reducer_is_a_one_line_error(toy_ws, runner, tmp_path):
    (toy_ws / "reducer.npz").write_bytes(b"PK\x03\x04 truncated")
    more = tmp_path / "more.parquet"
    pq.write_table(pa.table({"segment_id": ["new-1"], "x0": [0.1], "x1": [1.0]}), more)
    before = tree_hash(toy_ws)
    r = invoke(runner, "embed-reduce", "-w", toy_ws, more, "--apply")
    assert r.exit_code == 1 and len(r.stderr.strip().splitlines()) == 1
    assert "reducer.npz: damaged state file" in r.stderr and tree_hash(toy_ws) == before


def test_embedding_column_must_be_a_list_column(toy_ws, runner, toy_files):
    seg, _ = toy_files
    before = tree_hash(toy_ws)
    r = invoke(runner, "embed-reduce", "-w", toy_ws, seg, "--embedding-column", "x0", "--force")
    assert r.exit_code == 1
    assert "column 'x0': --embedding-column must name a list column, got type double" in r.stderr
    assert tree_hash(toy_ws) == before


DEAD = "a constant embedding dimension carries no information: drop it"


@pytest.mark.parametrize(
    ("layout", "dead", "where"),
    [
        ("columns", [7], "column 'emb_007': one value in all 600 rows"),
        ("columns", [3, 30], "2 embedding columns hold one value each in all 600 rows "
         "('emb_003', 'emb_030')"),
        ("list", [7], "column 'emb': embedding position 8 (of 40) holds one value in all 600 rows"),
        ("list", [0, 1, 2, 3, 4, 5], "column 'emb': embedding positions 1, 2, 3, 4, 5 ... "
         "(of 40) hold one value in all 600 rows"),
    ],
)  # fmt: skip
@pytest.mark.parametrize("method", ["pca", "identity"])
def test_a_constant_embedding_column_is_one_warning_naming_it(
    av_ws, runner, tmp_path, layout, dead, where, method
):
    seg = _av_files(tmp_path / "d", layout=layout)
    table = pq.read_table(seg)
    if layout == "columns":
        for j in dead:
            name = f"emb_{j:03d}"
            table = table.set_column(table.column_names.index(name), name, pa.array([0.1] * 600))
    else:
        E = np.array(table.column("emb").to_pylist())
        E[:, dead] = 0.1
        emb = pa.FixedSizeListArray.from_arrays(pa.array(E.ravel()), E.shape[1])
        table = table.set_column(table.column_names.index("emb"), "emb", emb)
    pq.write_table(table, seg, row_group_size=128)
    args = ["--columns", "emb_*"] if layout == "columns" else []
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--method", method, "--json", *args)
    assert r.exit_code == 0, r.output
    expected = f"{seg}: {where}; {DEAD}"
    assert [json.loads(line) for line in r.stderr.splitlines()] == [{"warning": expected}]
    assert json.loads(r.stdout)["warnings"] == [expected]
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--method", method, "--force", *args)
    assert r.exit_code == 0 and f"warning: {expected}" in r.stderr.splitlines()
    # a no-op re-run does not repeat it
    assert invoke(runner, "embed-reduce", "-w", av_ws, seg, "--method", method, *args).stderr == ""


def test_a_pool_without_a_constant_column_has_no_warning(av_ws, runner, tmp_path):
    seg = _av_files(tmp_path / "d")
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--json")
    assert r.exit_code == 0 and r.stderr == "" and json.loads(r.stdout)["warnings"] == []


@pytest.mark.parametrize(
    ("rank", "where"),
    [
        (3, "3 of the 6 principal components carry no variance (the embedding spans only 3 "
         "dimensions), so z3..z5 are constant in every row and carry no information: "
         "pass --dim 3"),
        (5, "1 of the 6 principal components carries no variance (the embedding spans only 5 "
         "dimensions), so z5 is constant in every row and carries no information: "
         "pass --dim 5"),
    ],
)  # fmt: skip
@pytest.mark.parametrize("method", ["pca", "ipca"])
def test_more_components_than_the_embedding_s_rank_is_one_warning_saying_how_many(
    av_ws, runner, tmp_path, rank, where, method
):
    # --dim 6 on an embedding of rank 3 gave constant coordinates z3..z5, without a word.
    seg = _av_files(tmp_path / "d")
    table = pq.read_table(seg)
    E = np.array(table.column("emb").to_pylist())
    rng = np.random.default_rng(0)
    E = (E - E.mean(axis=0))[:, :rank] @ rng.normal(size=(rank, E.shape[1]))  # rank `rank`
    emb = pa.FixedSizeListArray.from_arrays(pa.array(E.ravel()), E.shape[1])
    pq.write_table(table.set_column(table.column_names.index("emb"), "emb", emb), seg,
                   row_group_size=128)  # fmt: skip
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--method", method, "--json")
    assert r.exit_code == 0, r.output
    expected = f"{seg}: {where}"
    assert [json.loads(line) for line in r.stderr.splitlines()] == [{"warning": expected}]
    assert json.loads(r.stdout)["warnings"] == [expected]
    _, Z = Workspace(av_ws).read_pool()
    spread = Z.std(axis=0)
    assert (spread[rank:] < 1e-6 * spread[0]).all() and (spread[:rank] > 1e-3 * spread[0]).all()
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--method", method, "--force")
    assert r.exit_code == 0 and f"warning: {expected}" in r.stderr.splitlines()
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--method", method, "--force",
               "--dim", rank, "--json")  # fmt: skip
    assert r.exit_code == 0 and r.stderr == "" and json.loads(r.stdout)["warnings"] == []


def test_an_ipca_that_fails_to_converge_is_one_line_pointing_to_pca(
    av_ws, runner, tmp_path, monkeypatch
):
    # scikit-learn's IncrementalPCA can stop with "SVD did not converge" (seen on an
    # embedding of rank 40 of 64 columns): one line that names the exact method, exit 1,
    # and the workspace as it was.
    from sklearn.decomposition import IncrementalPCA

    def fails(self, X, y=None, check_input=True):
        raise np.linalg.LinAlgError("SVD did not converge")

    monkeypatch.setattr(IncrementalPCA, "partial_fit", fails)
    seg = _av_files(tmp_path / "d")
    before = sorted(p.name for p in Path(av_ws).iterdir())
    r = invoke(runner, "embed-reduce", "-w", av_ws, seg, "--method", "ipca")
    assert r.exit_code != 0
    line = r.output.strip()
    assert "\n" not in line and "SVD did not converge" in line and "--method pca" in line
    assert sorted(p.name for p in Path(av_ws).iterdir()) == before


def test_an_embedding_list_of_decimals_is_read_as_numbers(tmp_path, runner):
    # Decimals are numbers: refusing lists of text and booleans must not refuse them.
    import decimal

    values = [[decimal.Decimal(f"{i * 0.1 + j:.3f}") for j in range(3)] for i in range(8)]
    emb = pa.array(values, type=pa.list_(pa.decimal128(6, 3)))
    pq.write_table(
        pa.table({"segment_id": [f"s{i}" for i in range(8)], "emb": emb}), tmp_path / "d.parquet"
    )
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.5", "--costs", "1,0.1", "--dim", "2")
    ok(runner, "embed-reduce", "-w", ws, tmp_path / "d.parquet", "--method", "pca")


def test_the_default_dimension_is_where_the_spectrum_drops(runner, tmp_path):
    # A new study reduces by the embedding's spectrum: 20 factors in 60 columns give 20
    # coordinates, and the summary, --json and the pool's metadata say why.
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.3")
    assert 'embedding_dim = "auto"' in (ws / "settings.toml").read_text()
    rng = np.random.default_rng(0)
    E = rng.normal(size=(800, 20)) @ rng.normal(size=(20, 60)) + 0.05 * rng.normal(size=(800, 60))
    seg = tmp_path / "seg.parquet"
    flat = pa.FixedSizeListArray.from_arrays(pa.array(E.ravel()), 60)
    pq.write_table(pa.table({"segment_id": [f"s{i}" for i in range(800)], "emb": flat}), seg)
    r = ok(runner, "embed-reduce", "-w", ws, seg)
    assert "pca 60 -> 20 dimensions" in r.stdout
    text = " ".join(r.stdout.split())
    assert "dimensions 20, chosen: the spectrum drops" in text and "after component 20" in text
    assert Workspace(ws).read_pool()[1].shape == (800, 20)
    assert "after component 20" in read_metadata(Workspace(ws).segments_path)["dim_choice"]
    # A number on the command line or in the settings is kept as it is.
    again = ok(runner, "embed-reduce", "-w", ws, seg, "--dim", "3", "--force", "--json")
    assert json.loads(again.stdout)["dim"] == 3 and json.loads(again.stdout)["dim_choice"] is None
    settings = (ws / "settings.toml").read_text()
    (ws / "settings.toml").write_text(
        settings.replace('embedding_dim = "auto"', "embedding_dim = 7")
    )
    seven = ok(runner, "embed-reduce", "-w", ws, seg, "--force", "--json")
    assert json.loads(seven.stdout)["dim"] == 7
    (ws / "settings.toml").write_text(settings)
    auto = ok(runner, "embed-reduce", "-w", ws, seg, "--dim", "auto", "--force", "--json")
    assert json.loads(auto.stdout)["dim"] == 20
    # Fewer factors than 12: 12 are kept all the same.
    E5 = E[:, :5] @ rng.normal(size=(5, 60)) + 0.05 * rng.normal(size=(800, 60))
    flat5 = pa.FixedSizeListArray.from_arrays(pa.array(E5.ravel()), 60)
    pq.write_table(pa.table({"segment_id": [f"s{i}" for i in range(800)], "emb": flat5}), seg)
    five = json.loads(ok(runner, "embed-reduce", "-w", ws, seg, "--force", "--json").stdout)
    assert five["dim"] == 12 and "the least auto keeps" in five["dim_choice"]


def test_settings_take_auto_or_a_number_for_embedding_dim(tmp_path):
    from bams_cli.errors import SettingsError
    from bams_cli.settings import Settings

    base = '[[levels]]\nname = "high"\ncost = 1.0\n\n[study]\ngammas = [0.3]\n'
    # A file without the key was written before "auto": it meant 12, and still does.
    assert Settings.from_toml(base).embedding_dim == 12
    assert Settings.from_toml(base + 'embedding_dim = "auto"\n').embedding_dim == "auto"
    assert Settings.from_toml(base + "embedding_dim = 12\n").embedding_dim == 12
    with pytest.raises(SettingsError, match='embedding_dim must be a whole number or "auto", got'):
        Settings.from_toml(base + 'embedding_dim = "twelve"\n')
