"""fit: the model file, the scores, fixed hyperparameters, stale-state detection."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from scipy.special import ndtr

from bams_cli.state.io import read_metadata
from bams_cli.state.workspace import Workspace
from tests.conftest import STAGED_PLAN, invoke, ok, tree_hash, write_batch


@pytest.fixture
def fitted_ws(toy_ws, runner, toy_files, tmp_path):
    _, truth = toy_files
    ids = [f"t{i:06d}" for i in range(0, 400, 20)]
    levels = [0] * 8 + [1] * 12
    write_batch(toy_ws, 1, ids, levels)
    res = tmp_path / "r1.parquet"
    assert (
        invoke(
            runner,
            "simulate",
            toy_ws / "batches" / "batch-0001.parquet",
            "--truth",
            truth,
            "-o",
            res,
        ).exit_code
        == 0
    )
    assert invoke(runner, "ingest-results", "-w", toy_ws, res).exit_code == 0
    r = invoke(runner, "fit", "-w", toy_ws, "--restarts", "2", "--json")
    assert r.exit_code == 0, r.output
    return toy_ws


def test_fit_writes_model_and_scores(fitted_ws):
    ws = Workspace(fitted_ws)
    model = json.loads(ws.model_path.read_text())
    hp = model["hyperparameters"]
    assert len(hp["lengthscales0"]) == 2 and len(hp["noise"]) == 2
    assert model["n_observations_per_level"] == [8, 12]
    assert model["observations_hash"] == ws.observations_hash()
    assert np.isfinite(model["log_marginal_likelihood"]) and np.isfinite(model["log_posterior"])
    scores = pq.read_table(ws.scores_path)
    mu = scores.column("mu").to_numpy()
    sd = scores.column("sd").to_numpy()
    p = scores.column("p_0").to_numpy()
    assert scores.num_rows == 400
    np.testing.assert_allclose(p, ndtr((0.56 - mu) / sd), rtol=1e-12, atol=1e-300)
    assert read_metadata(ws.scores_path)["observations_hash"] == ws.observations_hash()


def test_fixed_hyperparameters_reproduce_the_model(fitted_ws, runner, tmp_path):
    ws = Workspace(fitted_ws)
    saved = tmp_path / "model.json"
    saved.write_text(ws.model_path.read_text())
    before = pq.read_table(ws.scores_path).column("mu").to_numpy()
    r = invoke(runner, "fit", "-w", fitted_ws, "--fixed-hyperparameters", saved, "--json")
    assert r.exit_code == 0, r.output
    after = pq.read_table(ws.scores_path).column("mu").to_numpy()
    np.testing.assert_allclose(after, before, rtol=1e-10)
    assert json.loads(ws.model_path.read_text())["trained"] is False


def test_bad_fixed_hyperparameters(fitted_ws, runner, tmp_path):
    bad = tmp_path / "hp.json"
    bad.write_text(json.dumps({"mean": 0}))
    before = tree_hash(fitted_ws)
    r = invoke(runner, "fit", "-w", fitted_ws, "--fixed-hyperparameters", bad)
    assert r.exit_code == 1 and "hp.json: not a hyperparameter file" in r.stderr
    assert tree_hash(fitted_ws) == before


def test_fit_without_observations_names_the_next_step(toy_ws, runner):
    r = invoke(runner, "fit", "-w", toy_ws)
    assert (
        r.exit_code == 1 and "no observations yet" in r.stderr and "--strategy random" in r.stderr
    )


def test_model_is_stale_after_new_results(fitted_ws, runner, toy_files, tmp_path):
    _, truth = toy_files
    write_batch(fitted_ws, 2, ["t000001"], [0])
    res = tmp_path / "r2.parquet"
    invoke(
        runner,
        "simulate",
        fitted_ws / "batches" / "batch-0002.parquet",
        "--truth",
        truth,
        "-o",
        res,
    )
    assert invoke(runner, "ingest-results", "-w", fitted_ws, res).exit_code == 0
    r = invoke(
        runner, "select", "-w", fitted_ws, "--budget", "2", "--clusters", "1", "--workers", "1"
    )
    assert r.exit_code == 1
    # In counts, as status words it (the message gave the logs' two hashes).
    fitted = sum(json.loads((fitted_ws / "model.json").read_text())["n_observations_per_level"])
    assert r.stderr.splitlines() == [
        f"error: {fitted_ws / 'model.json'}: the observation log changed after the last fit "
        f"(fitted on {fitted} results, the log now holds {fitted + 1}); "
        f"run `bams-cli fit -w {fitted_ws}`"
    ]


def test_a_model_stale_by_a_replaced_value_says_so(fitted_ws, runner, tmp_path):
    # After `ingest-results --replace`, status said "fitted on 20 results, the log now
    # holds 20": a reason that reads as none.
    row = Workspace(fitted_ws).read_observations().row(0, named=True)
    res = tmp_path / "fix.parquet"
    pq.write_table(pa.table({"segment_id": [row["segment_id"]], "fidelity": [row["fidelity"]],
                             "value": [row["value"] + 0.5]}), res)  # fmt: skip
    ok(runner, "ingest-results", "-w", fitted_ws, res, "--replace")
    s = json.loads(invoke(runner, "status", "-w", fitted_ws, "--json").stdout)
    assert s["model"]["reason"] == (
        "the observation log changed after the last fit (results replaced since: fitted on "
        "20 results, the log holds as many, not all the same)"
    )
    ok(runner, "report", "-w", fitted_ws)
    notices = json.loads((fitted_ws / "report" / "summary.json").read_text())["notices"]
    [text] = [n["text"] for n in notices if n["kind"] == "stale_model"]
    assert text.startswith("Stale model: the observation log changed after the last fit (results")


def _fit_with(ws, runner, tmp_path, values, noise0, outputscale0=0.25):
    """Level-0 results with the given values, fitted with fixed hyperparameters."""
    ids = [f"t{i:06d}" for i in range(0, 400, 40)][: len(values)]
    write_batch(ws, 1, ids, [0] * len(ids))
    res = tmp_path / "r1.parquet"
    pq.write_table(pa.table({"segment_id": ids, "fidelity": [0] * len(ids), "value": values}), res)
    assert invoke(runner, "ingest-results", "-w", ws, res).exit_code == 0
    hp = {
        "mean": 3.0,
        "outputscale0": outputscale0,
        "lengthscales0": [1.0, 1.0],
        "outputscales": [0.01],
        "lengthscales": [[1.0, 1.0]],
        "noise": [noise0, 1e-4],
    }
    saved = tmp_path / "hp.json"
    saved.write_text(json.dumps(hp))
    return invoke(runner, "fit", "-w", ws, "--fixed-hyperparameters", saved), ids


def test_fit_on_cheap_level_results_alone_warns_that_level_0_is_unmeasured(
    toy_ws, runner, toy_files, tmp_path
):
    # A trial study fitted 20 level-1 results with none at level 0 (late): no warning, the
    # cheap level's bias silently 0 and "level 0 noise sd 0.0093" measured by nothing.
    _, truth = toy_files
    ids = [f"t{i:06d}" for i in range(0, 400, 20)]
    write_batch(toy_ws, 1, ids, [1] * len(ids))
    res = tmp_path / "r1.parquet"
    ok(runner, "simulate", toy_ws / "batches" / "batch-0001.parquet", "--truth", truth, "-o", res)
    ok(runner, "ingest-results", "-w", toy_ws, res)
    r = invoke(runner, "fit", "-w", toy_ws, "--restarts", "1")
    assert r.exit_code == 0, r.output
    [line] = [s for s in r.stderr.splitlines() if "no level-0 result" in s]
    assert line.startswith("warning: no level-0 result yet (20 cheap-level results)")
    assert "bias against level 0" in line
    model = json.loads(Workspace(toy_ws).model_path.read_text())
    assert any(w.startswith("no level-0 result yet") for w in model["warnings"])


def test_fit_warns_when_the_model_explains_an_observed_failure_as_noise(toy_ws, runner, tmp_path):
    # Level-0 noise variance 100: the failure at 0.3 barely moves the mean off 3, so
    # p_n there is ndtr((0.56 - ~3) / ~0.5) ~ 1e-6 although the segment was seen failing.
    r, ids = _fit_with(toy_ws, runner, tmp_path, [0.3, 3.1, 2.9, 3.0, 3.2], noise0=100.0)
    assert r.exit_code == 0, r.output
    line, rate = [s for s in r.stderr.splitlines() if s.startswith("warning:")]
    assert "1 of 1 segments observed failing" in line and repr(ids[0]) in line
    # The pool's p_n sum to less than the one failure seen: the model's own rate is wrong.
    assert "is below the 1 failure already confirmed at level 0" in rate
    model = json.loads(Workspace(toy_ws).model_path.read_text())
    assert len(model["warnings"]) == 2
    p = pq.read_table(Workspace(toy_ws).scores_path).column("p_0").to_numpy()
    assert p[0] < 0.01  # t000000 is row 0: the contradiction the warning names
    # The report carries it too.
    assert invoke(runner, "report", "-w", toy_ws).exit_code == 0
    page = (toy_ws / "report" / "report.html").read_text()
    assert page.count("fit warning: gamma 0.56: 1 of 1 segments observed failing") == 1


def test_fit_does_not_warn_when_the_model_follows_the_data(toy_ws, runner, tmp_path):
    # Output sd 3: a 0.3 among values near 3 is a 0.9-sd event, which the leave-one-out
    # check accepts (with sd 0.5 it would be 5.4 sd and rightly flagged as overconfident).
    r, _ = _fit_with(
        toy_ws, runner, tmp_path, [0.3, 3.1, 2.9, 3.0, 3.2], noise0=1e-4, outputscale0=9.0
    )
    assert r.exit_code == 0, r.output
    assert "warning:" not in r.stderr
    assert json.loads(Workspace(toy_ws).model_path.read_text())["warnings"] == []
    p = pq.read_table(Workspace(toy_ws).scores_path).column("p_0").to_numpy()
    assert p[0] > 0.99


def test_fit_warns_when_level0_runs_surprise_the_model(toy_ws, runner, tmp_path):
    # The same data with output sd 0.5: leave-one-out, the 0.3 is 5.4 sd from its
    # prediction. The warning and model.json's checks say so with the evidence.
    r, _ = _fit_with(toy_ws, runner, tmp_path, [0.3, 3.1, 2.9, 3.0, 3.2], noise0=1e-4)
    assert r.exit_code == 0, r.output
    [line] = [s for s in r.stderr.splitlines() if s.startswith("warning:")]
    assert "overconfident at level 0" in line and "5 level-0 runs" in line
    model = json.loads(Workspace(toy_ws).model_path.read_text())
    assert model["checks"]["loo_level0"]["n"] == 5
    assert model["checks"]["loo_level0"]["mean_z2"] > 5
    assert model["jitter"] == 0.0


def test_fit_s_warnings_reach_stderr_as_json_lines_under_json(toy_ws, runner, tmp_path):
    # The README's contract: under --json every warning is one {"warning": ...} line on
    # stderr, the model's self-check included (it was only inside the JSON on stdout).
    _, _ = _fit_with(toy_ws, runner, tmp_path, [0.3, 3.1, 2.9, 3.0, 3.2], noise0=1e-4)
    saved = tmp_path / "hp.json"
    r = invoke(runner, "fit", "-w", toy_ws, "--fixed-hyperparameters", saved, "--json", "--force")
    assert r.exit_code == 0, r.output
    lines = [json.loads(line) for line in r.stderr.splitlines()]
    summary = json.loads(r.stdout)
    assert summary["warnings"] and lines == [{"warning": w} for w in summary["warnings"]]
    assert "overconfident at level 0" in lines[0]["warning"]


def test_fit_records_its_output_transform_and_fixed_hyperparameters_reuse_it(
    fitted_ws, runner, tmp_path
):
    model = json.loads(Workspace(fitted_ws).model_path.read_text())
    assert model["transform"]["kind"] in ("identity", "asinh")
    assert len(model["transform_evidence"]) == 3  # the identity and two asinh scales
    best = max(model["transform_evidence"], key=lambda e: e["log_evidence"])
    assert (best["scale"] is None) == (model["transform"]["kind"] == "identity")
    # A hand-made transform in a saved model is what a conditioning-only fit uses.
    model["transform"] = {"kind": "asinh", "centre": 0.56, "scale": 0.7}
    saved = tmp_path / "model.json"
    saved.write_text(json.dumps(model))
    r = invoke(runner, "fit", "-w", fitted_ws, "--fixed-hyperparameters", saved, "--json")
    assert r.exit_code == 0, r.output
    assert json.loads(r.stdout)["transform"] == model["transform"]
    # Scores are in the model's units: p_n = Phi((g(gamma) - mu) / sd), g(0.56) = 0.56.
    t = pq.read_table(Workspace(fitted_ws).scores_path)
    mu, sd, p = (t.column(c).to_numpy() for c in ("mu", "sd", "p_0"))
    np.testing.assert_allclose(p, ndtr((0.56 - mu) / sd), rtol=1e-9, atol=1e-12)


def test_fit_transform_none_models_the_metric_itself(fitted_ws, runner):
    r = invoke(runner, "fit", "-w", fitted_ws, "--transform", "none", "--json", "--restarts", "2")
    assert r.exit_code == 0, r.output
    doc = json.loads(Workspace(fitted_ws).model_path.read_text())
    assert doc["transform"] == {"kind": "identity"} and len(doc["transform_evidence"]) == 1
    r = invoke(runner, "fit", "-w", fitted_ws, "--transform", "log")
    unboxed = " ".join(r.stderr.replace("│", " ").split())  # click's usage box wraps
    assert r.exit_code == 2 and "'log' is not one of 'auto', 'none'" in unboxed


def test_fit_is_a_no_op_when_the_model_is_up_to_date(fitted_ws, runner):
    ws = Workspace(fitted_ws)
    before, mtime = tree_hash(fitted_ws), ws.model_path.stat().st_mtime_ns
    r = invoke(runner, "fit", "-w", fitted_ws, "--restarts", "2")
    assert r.exit_code == 0
    assert "model is up to date (fitted on 20 observations); nothing to do" in r.stdout
    assert tree_hash(fitted_ws) == before and ws.model_path.stat().st_mtime_ns == mtime
    summary = json.loads(invoke(runner, "fit", "-w", fitted_ws, "--restarts", "2", "--json").stdout)
    model = json.loads(ws.model_path.read_text())
    assert summary["up_to_date"] is True and summary["observations"] == 20
    assert summary["hyperparameters"] == model["hyperparameters"]
    assert tree_hash(fitted_ws) == before


def test_fit_force_and_other_options_fit_again(fitted_ws, runner):
    ws = Workspace(fitted_ws)
    mtime = ws.model_path.stat().st_mtime_ns
    r = invoke(runner, "fit", "-w", fitted_ws, "--restarts", "2", "--force")
    assert r.exit_code == 0 and "up to date" not in r.stdout
    assert ws.model_path.stat().st_mtime_ns > mtime
    # the default fit (8 restarts) is another fit than --restarts 2; then it is up to date
    r = invoke(runner, "fit", "-w", fitted_ws)
    assert r.exit_code == 0 and "up to date" not in r.stdout
    assert json.loads(ws.model_path.read_text())["restarts"] == 8
    r = invoke(runner, "fit", "-w", fitted_ws)
    assert r.exit_code == 0 and "model is up to date" in r.stdout
    # edited settings (another gamma) ask for other scores
    text = ws.settings_path.read_text().replace("0.56", "0.5")
    ws.settings_path.write_text(text)
    r = invoke(runner, "fit", "-w", fitted_ws, "--json")
    assert r.exit_code == 0 and "up_to_date" not in json.loads(r.stdout)
    assert json.loads(ws.model_path.read_text())["gammas"] == [0.5]


def test_edited_gammas_make_the_model_stale_for_every_command(fitted_ws, runner):
    """settings.toml says "edit by hand": after a gamma edit the scores' p_<k> columns
    answer for the old thresholds, so select and estimate --plan refuse and name fit,
    status says fit, and report still renders."""
    ws = Workspace(fitted_ws)
    text = ws.settings_path.read_text()
    assert "0.56" in text
    ws.settings_path.write_text(text.replace("0.56", "0.6"))
    for args in (["select", "--budget", "2", "--clusters", "1"], ["estimate", *STAGED_PLAN]):
        r = invoke(runner, *args, "-w", fitted_ws)
        assert r.exit_code == 1
        assert "fitted for gammas [0.56]" in r.stderr and "bams-cli fit" in r.stderr
    r = invoke(runner, "status", "-w", fitted_ws, "--json")
    assert json.loads(r.stdout)["next"]["step"] == "fit"
    assert invoke(runner, "report", "-w", fitted_ws).exit_code == 0
    assert invoke(runner, "fit", "-w", fitted_ws, "--restarts", "2").exit_code == 0
    assert (
        invoke(runner, "select", "-w", fitted_ws, "--budget", "2", "--clusters", "1").exit_code == 0
    )


def test_fit_records_its_conditioning_and_select_uses_the_same_posterior(fitted_ws, runner):
    """Exact on all 20 below the budget; over it (15 of 20), an exact subset that model.json,
    --json and the human summary name, and that select's posterior reproduces."""
    from bams_cli import pipeline
    from bams_cli.core.gp.fit import BYTES_PER_ENTRY

    ws = Workspace(fitted_ws)
    model = json.loads(ws.model_path.read_text())
    assert model["conditioning"]["method"] == "exact"
    assert model["conditioning"]["conditioned_on"] == model["conditioning"]["observations"] == 20
    assert model["conditioning"]["note"] == "exact posterior: conditioned on all 20 observations"

    budget = BYTES_PER_ENTRY * 15 * 15
    summary = pipeline.fit(fitted_ws, restarts=2, max_memory=budget, force=True)
    c = summary["conditioning"]
    assert (c["method"], c["conditioned_on"], c["observations"]) == ("exact_subset", 15, 20)
    assert c["memory_budget_bytes"] == budget and "15 of 20 observations" in c["note"]
    model = json.loads(ws.model_path.read_text())
    assert model["conditioning"] == c
    assert model["n_observations_per_level"] == [8, 12]  # the log, not the subset
    settings = ws.require_initialised()
    ids, X = ws.read_pool()
    post, _ = pipeline.load_posterior(ws, settings, ids, X)
    assert post.conditioning["conditioned_on"] == 15
    g = pipeline.fitting.model_transform(ws, model)
    _, sd, _ = post.score(X, g.forward(np.asarray(settings.gammas, dtype=float)))
    np.testing.assert_allclose(sd, pq.read_table(ws.scores_path).column("sd").to_numpy())
    # The same budget again: up to date; the default budget holds all 20, so it refits.
    assert pipeline.fit(fitted_ws, restarts=2, max_memory=budget)["up_to_date"] is True
    assert "up_to_date" not in pipeline.fit(fitted_ws, restarts=2)
    pipeline.fit(fitted_ws, restarts=2, max_memory=budget, force=True)
    r = invoke(runner, "select", "-w", fitted_ws, "--budget", "2", "--clusters", "1", "--json")
    assert r.exit_code == 0, r.output
    r = invoke(runner, "fit", "-w", fitted_ws, "--restarts", "2", "--force")
    assert r.exit_code == 0 and "conditioning" in r.output and "exact posterior" in r.output


@pytest.mark.parametrize("values, failed", [([3.1, 2.9, 3.0, 3.2, 3.3], 0), ([0.3, 3.1, 2.9], 1)])
def test_fit_says_when_no_level0_failure_has_checked_the_model_s_rate(
    toy_ws, runner, tmp_path, values, failed
):
    # A trial study's model put its rate at 1.9e-6 against a true 0.0057 before any
    # level-0 failure: the printed rate says it is the model's own and unchecked.
    r, ids = _fit_with(toy_ws, runner, tmp_path, values, noise0=1e-4)
    assert r.exit_code == 0, r.output
    [line] = [s for s in r.stdout.splitlines() if "GP rate estimate" in s]
    assert ("no level-0 failure has checked it yet" in line) == (failed == 0)
    # Level-0 results only: level 1's numbers were fitted by nothing, and say so.
    [lv1] = [s for s in r.stdout.splitlines() if s.split()[:2] == ["level", "1"]]
    assert lv1.endswith("(no level-1 result yet: no data fitted these)")
    saved = tmp_path / "hp.json"
    r = invoke(runner, "fit", "-w", toy_ws, "--fixed-hyperparameters", saved, "--json", "--force")
    assert json.loads(r.stdout)["level0_failures"] == {"0.56": failed}


def test_a_model_rate_below_the_failures_already_confirmed_is_warned():
    from bams_cli.pipeline.fitting import _contradicted_outcomes

    ids = np.array([f"s{i}" for i in range(10)])
    idx = np.array([0, 1, 2, 3])
    lv = np.zeros(4, dtype=np.int64)
    y = np.array([-1.0, -0.5, 0.8, -0.2])  # three level-0 failures at gamma 0
    p = np.full((10, 1), 0.05)
    p[[0, 1, 3], 0] = 0.5  # sure enough of each (no contradiction), 1.85 expected in all
    [line] = _contradicted_outcomes(ids, idx, lv, y, p, [0.0])
    assert "the model's own failure rate 0.185 (1.85 failures expected" in line
    assert "below the 3 failures already confirmed at level 0 (0.3 of the pool)" in line
    p[2, 0] = 0.02
    p[4:, 0] = 0.3  # 3.32 expected: no longer below what was seen
    assert _contradicted_outcomes(ids, idx, lv, y, p, [0.0]) == []


def test_values_at_the_accepted_limit_give_a_one_line_fit_error(toy_ws, runner, tmp_path):
    # 0 and 1e150 are both accepted by ingest-results (|value| <= 1e150); the level-1
    # offset the fit found lay just past the limit, and fit died with an "unexpected"
    # ValueError (found by test_fuzz_inputs' slow test).
    write_batch(toy_ws, 1, ["t000001", "t000003", "t000005"], [0, 1, 0])
    res = tmp_path / "r.parquet"
    pq.write_table(
        pa.table({"segment_id": ["t000001", "t000003", "t000005"], "fidelity": [0, 1, 0],
                  "value": [0.0, 1e150, 0.7]}),
        res,
    )  # fmt: skip
    assert invoke(runner, "ingest-results", "-w", toy_ws, res).exit_code == 0
    before = tree_hash(toy_ws)
    r = invoke(runner, "fit", "-w", toy_ws, "--restarts", "1")
    assert r.exit_code == 1 and "(unexpected" not in r.stderr, r.stderr
    [line] = r.stderr.splitlines()
    assert "the observed values span 0 to 1e+150); rescale the metric" in line
    assert tree_hash(toy_ws) == before


def test_a_contradicted_value_is_printed_with_the_digits_that_tell_it_from_gamma():
    # "value 1.9, p_n 1" for a segment observed *not* failing at gamma 1.9 (its value was
    # 1.9002) read as a contradiction of the warning itself.
    from bams_cli.pipeline.fitting import _beside, _contradicted_outcomes

    assert _beside(1.9002, 1.9) == "1.9002" and _beside(1.90000001, 1.9) == "1.90000001"
    assert _beside(1.9, 1.9) == "1.9" and _beside(2.5, 1.9) == "2.5"
    # On the value's side of gamma: 1.90016 is not "1.9" beside a gamma of 1.9001.
    assert _beside(1.90016, 1.9001) == "1.9002" and _beside(1.90011, 1.9001) == "1.90011"
    assert _beside(1.90004, 1.9001) == "1.9"
    [line] = _contradicted_outcomes(
        np.array(["a", "b"]), np.array([0, 1]), np.array([0, 0]), np.array([1.9002, 3.0]),
        np.array([[1.0 - 1e-5], [0.0]]), [1.9],
    )  # fmt: skip
    assert "1 of 2 segments observed not failing" in line
    assert "(worst 'a': value 1.9002, probability 1e-05)" in line


def test_a_fit_with_nothing_to_do_does_not_load_the_numerical_stack(fitted_ws):
    # A Makefile runs `fit` after every ingest; with the model up to date it took 3-7 s,
    # nearly all of it importing the GP and scipy.stats before finding nothing to do.
    import subprocess
    import sys

    code = (
        "import sys; from pathlib import Path; from bams_cli.pipeline import fit; "
        f"out = fit(Path({str(fitted_ws)!r}), restarts=2); "
        "print(out.get('up_to_date'), 'bams_cli.core.gp' in sys.modules)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert r.stdout.split() == ["True", "False"]


def test_fit_says_when_an_edited_embedding_dim_has_not_been_applied(fitted_ws, runner, toy_files):
    # settings.toml says "edit by hand", but a new embedding_dim changes nothing until the
    # pool is reduced again: fit (kept or refitted) says so, and says it only while true.
    ws = Workspace(fitted_ws)
    text = ws.settings_path.read_text()
    assert "embedding_dim = 2" in text
    ws.settings_path.write_text(text.replace("embedding_dim = 2", "embedding_dim = 5"))

    def stale(*args):
        r = invoke(runner, "fit", "-w", fitted_ws, "--restarts", "2", *args)
        assert r.exit_code == 0, r.output
        return [s for s in r.stderr.splitlines() if "embedding_dim" in s]

    [line] = stale()  # the model is up to date: the warning is still said
    assert line.startswith(f"warning: {ws.settings_path}: embedding_dim is 5, but the pool was ")
    assert "reduced with 2 (2 components)" in line and "embed-reduce --force" in line
    assert len(stale("--force")) == 1
    assert not any("embedding_dim" in w for w in json.loads(ws.model_path.read_text())["warnings"])
    ws.settings_path.write_text(text)
    assert stale() == []
    # A pool reduced with an explicit --dim follows the flag, not the setting.
    seg, _ = toy_files
    ok(runner, "embed-reduce", "-w", fitted_ws, seg, "--columns", "x*", "--method", "identity",
       "--no-standardize", "--dim", "2", "--force")  # fmt: skip
    ws.settings_path.write_text(text.replace("embedding_dim = 2", "embedding_dim = 5"))
    assert stale("--force") == []


def test_fit_over_its_scoring_budget_keeps_means_exact_and_says_so(
    fitted_ws, runner, tmp_path, monkeypatch
):
    """Pool size x n^2 over ``SCORE_MAX_WORK`` (a million segments after an estimate stage's
    12,000 level-0 runs took over an hour): means exact, sds never below the exact ones,
    p_n from them, and model.json, --json and the summary say how."""
    from bams_cli import defaults, schemas_json
    from tests.jsonschema_subset import errors

    ws = Workspace(fitted_ws)
    saved = tmp_path / "model.json"
    saved.write_text(ws.model_path.read_text())
    assert json.loads(saved.read_text())["scoring"]["method"] == "exact"
    exact = pq.read_table(ws.scores_path)
    monkeypatch.setattr(defaults, "SCORE_MAX_WORK", 400 * 20 * 20 - 1)  # 400 segments, 20 obs
    r = invoke(runner, "fit", "-w", fitted_ws, "--fixed-hyperparameters", saved, "--json")
    assert r.exit_code == 0, r.output
    summary = json.loads(r.stdout)
    assert errors(summary, schemas_json.schema("fit")) == []
    s = summary["scoring"]
    assert s["method"] == "bounded" and s["rows"] == 400 and s["bound_observations"] == 19
    assert json.loads(ws.model_path.read_text())["scoring"] == s
    # the bound costs 19^2 x 400; the rest buys (159,999 - 144,400) // 20^2 exact sds
    assert s["exact_sd_rows"] == 38
    assert s["near_thresholds"] > 38, s  # the others kept the bound
    p0 = pq.read_table(ws.scores_path)["p_0"].to_numpy()
    assert s["p_sum"] == pytest.approx([p0.sum()], rel=1e-12)
    # the rows that kept the bound moved the pool's sum of p_n by no more than it says
    moved = abs(p0.sum() - exact["p_0"].to_numpy().sum())
    assert 0 < moved <= s["kept_bound_error"][0] * (1 + 1e-9)
    warned = any(w.startswith("scoring: means exact") for w in summary["warnings"])
    assert warned == (s["kept_bound_error"][0] > 0.01 * s["p_sum"][0])
    bounded = pq.read_table(ws.scores_path)
    np.testing.assert_allclose(bounded["mu"].to_numpy(), exact["mu"].to_numpy(), atol=1e-10)
    assert np.all(bounded["sd"].to_numpy() >= exact["sd"].to_numpy() - 1e-12)
    assert np.any(bounded["sd"].to_numpy() > exact["sd"].to_numpy() * 1.01)
    mu, sd = bounded["mu"].to_numpy(), bounded["sd"].to_numpy()
    np.testing.assert_allclose(bounded["p_0"].to_numpy(), ndtr((0.56 - mu) / sd), rtol=1e-12)
    # sd_exact says which sds are exact: the 38 rows the budget bought, and no other
    flag = bounded["sd_exact"].to_numpy(zero_copy_only=False)
    assert flag.sum() == 38 and exact["sd_exact"].to_numpy(zero_copy_only=False).all()
    np.testing.assert_allclose(sd[flag], exact["sd"].to_numpy()[flag], rtol=1e-9)
    assert np.all(sd[~flag] > exact["sd"].to_numpy()[~flag] * (1 + 1e-9))
    r = invoke(runner, "fit", "-w", fitted_ws, "--fixed-hyperparameters", saved)
    assert r.exit_code == 0 and "scoring" in r.output and "upper bound" in r.output


@pytest.mark.parametrize(("kept", "warned"), [(0.9, False), (1.1, True)])
def test_fit_warns_when_bound_sds_can_move_the_model_s_expected_failures_over_1_percent(
    kept, warned
):
    from bams_cli.pipeline.fitting import scoring_fell_short

    s = {
        "method": "bounded", "rows": 10**6, "max_work": 5e12, "bound_observations": 1581,
        "near_thresholds": 64_368, "exact_sd_rows": 16_893, "decided_z": 8.5,
        "p_sum": [4_800.0, 100.0], "kept_bound_error": [3.0, kept],
    }  # fmt: skip
    lines = scoring_fell_short(s)
    assert bool(lines) == warned
    if warned:
        assert lines == [
            "scoring: means exact; sds exact on the 16,893 segments nearest a threshold (within "
            "8.5 sds), elsewhere an upper bound from 1,581 observations, where p_n is 0 or 1 "
            "within 1e-17; 47,475 more near them kept the bound, their p_n leaning toward 1/2 "
            "(it can move the pool's sum of p_n by up to 1.10%): exact sds on all 1,000,000 "
            "would cost over 5e+12 flops"
        ]
