"""init: a failure threshold is required; --exist-ok makes a re-run of the same init a no-op."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bams_cli.settings import Settings
from tests.conftest import invoke, ok, tree_hash

ROOT = Path(__file__).resolve().parents[1]
TOY = ROOT / "sample_data" / "toy2d" / "settings.toml"
FLAGS = ["--gamma", "0.56", "--costs", "1,0.1", "--dim", "2", "--seed", "4"]


@pytest.mark.parametrize("flags", [[], ["--costs", "1,0.1", "--seed", "2"]])
def test_init_without_a_threshold_names_the_flag(runner, tmp_path, flags):
    r = invoke(runner, "init", "-w", tmp_path / "ws", *flags)
    assert r.exit_code == 1 and "pass --gamma" in r.stderr and "--settings-from" in r.stderr
    assert r.stderr.count("\n") == 1 and not (tmp_path / "ws").exists()


@pytest.mark.parametrize("source", [FLAGS, ["--settings-from", str(TOY)]])
def test_exist_ok_rerun_of_the_same_init_changes_nothing(runner, tmp_path, source):
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, *source, "--exist-ok")  # a new workspace: created
    before, mtime = tree_hash(ws), (ws / "settings.toml").stat().st_mtime_ns
    r = ok(runner, "init", "-w", ws, *source, "--exist-ok")
    assert "already holds these settings; nothing changed" in r.stdout
    summary = json.loads(ok(runner, "init", "-w", ws, *source, "--exist-ok", "--json").stdout)
    assert summary["unchanged"] is True
    assert tree_hash(ws) == before and (ws / "settings.toml").stat().st_mtime_ns == mtime
    r = invoke(runner, "init", "-w", ws, *source)  # without --exist-ok it still refuses
    assert r.exit_code == 1 and "already exists" in r.stderr and "--exist-ok" in r.stderr


@pytest.mark.parametrize(
    ("flags", "needle"),
    [
        (["--gamma", "0.5", "--costs", "1,0.1", "--dim", "2", "--seed", "4"],
         "gammas: 0.56 in the file, 0.5 requested"),
        (["--gamma", "0.56", "--dim", "2", "--seed", "4"],
         "levels (costs): high 1, low1 0.1 in the file, high 1 requested"),
        (["--gamma", "0.56", "--costs", "1,0.1", "--dim", "2"], "seed: 4 in the file, 0 requested"),
    ],
)  # fmt: skip
def test_exist_ok_with_other_settings_names_the_difference(runner, tmp_path, flags, needle):
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, *FLAGS)
    before = tree_hash(ws)
    r = invoke(runner, "init", "-w", ws, *flags, "--exist-ok")
    assert r.exit_code == 1 and needle in r.stderr and "--force" in r.stderr, r.stderr
    assert r.stderr.count("\n") == 1 and tree_hash(ws) == before


def test_force_and_exist_ok_contradict(runner, tmp_path):
    r = invoke(runner, "init", "-w", tmp_path / "ws", *FLAGS, "--force", "--exist-ok")
    assert r.exit_code == 1 and "pass one of them" in r.stderr
    assert not (tmp_path / "ws").exists()


@pytest.mark.parametrize("gammas", ["0.5,0.5", "0.5,0.3,0.5", "0.5,0.50"])
def test_a_repeated_gamma_is_a_usage_error_naming_it(runner, tmp_path, gammas):
    r = invoke(runner, "init", "-w", tmp_path / "ws", "--gamma", gammas)
    assert r.exit_code == 2, r.output
    assert r.stderr.splitlines() == [
        f"error: --gamma {gammas.replace('0.50', '0.5')}: gamma 0.5 is given more than once; "
        "give each failure threshold once"
    ]
    assert not (tmp_path / "ws").exists()


def test_a_repeated_gamma_in_a_settings_file_names_the_file(runner, tmp_path):
    source = tmp_path / "settings.toml"
    source.write_text("[study]\ngammas = [0.5, 0.3, 0.3]\n")
    r = invoke(runner, "init", "-w", tmp_path / "ws", "--settings-from", source)
    assert r.exit_code == 1 and r.stderr.splitlines() == [
        f"error: {source}: gamma 0.3 is given more than once; give each failure threshold once"
    ]
    assert not (tmp_path / "ws").exists()


def test_gammas_keep_the_order_given(runner, tmp_path):
    # Not sorted: the first drives selection, as the settings file's header says.
    summary = json.loads(
        ok(runner, "init", "-w", tmp_path / "ws", "--gamma", "0.7,0.3", "--json").stdout
    )
    assert summary["gammas"] == [0.7, 0.3]
    assert "gammas = [\n    0.7,\n    0.3,\n]" in (tmp_path / "ws" / "settings.toml").read_text()


@pytest.mark.parametrize(
    ("flags", "line"),
    [
        (["--costs", "1,0"], "--costs 1,0: level 1 cost must be a finite number > 0, got 0"),
        (["--costs", "1,-0.1"], "--costs 1,-0.1: level 1 cost must be a finite number > 0"),
        (["--costs", "1,nan"], "--costs 1,nan: level 1 cost must be a finite number > 0, got nan"),
        (["--costs", "1,inf"], "--costs 1,inf: level 1 cost must be a finite number > 0, got inf"),
        (["--costs", "2,1"], "--costs 2,1: level 0 must cost 1 (costs are in units of one"),
        (["--gamma", "nan"], "--gamma nan: gammas must be finite numbers, got [nan]"),
        (["--gamma", "abc"], "--gamma 'abc': expected comma-separated numbers"),
        (["--costs", "1,"], "--costs '1,': expected comma-separated numbers"),  # not one level
        (["--costs", "1,,0.1"], "--costs '1,,0.1': expected comma-separated numbers"),
        (["--seed", "-1"], "--seed -1: seed must be an integer >= 0, got -1"),
        (["--dim", "0"], "--dim 0: embedding_dim must be >= 1 or \"auto\", got 0"),
        (["--dim", "twelve"], "--dim 'twelve': expected a whole number or 'auto'"),
        (["--costs", "1,0.1", "--level-names", "a"], "--level-names has 1 names for 2 costs"),
        (["--costs", "1,0.1", "--level-names", "lr,lr"],
         "--level-names lr,lr: level name 'lr' is given to more than one level"),
        (["--costs", "1,0.1", "--level-names", "1,0"],
         "--level-names 1,0: level 0 is named '1', the number of another level"),
        (["--costs", "1,0.1", "--level-names", "a,0.0"],  # results read "0.0" as level 0
         "--level-names a,0.0: level 1 is named '0.0', the number of another level"),
    ],
)  # fmt: skip
def test_a_flag_out_of_range_is_a_usage_error_naming_it(runner, tmp_path, flags, line):
    r = invoke(runner, "init", "-w", tmp_path / "ws", "--gamma", "0.5", *flags)
    assert r.exit_code == 2, r.output
    [error] = r.stderr.splitlines()
    assert error.startswith(f"error: {line}"), error
    assert not (tmp_path / "ws").exists()


DEAR = (
    "no less than a level-0 run (costs are in units of one level-0 run; a cheaper simulator "
    "costs a fraction of 1): select will seldom pick it, while random mixed-fidelity batches "
    "spend budget on it"
)


@pytest.mark.parametrize("costs", ["1,1", "1,1.5", "1,0.1,2"])
def test_a_cheap_level_costing_as_much_as_level_0_is_warned_once(runner, tmp_path, costs):
    # Legal (a run of it is still a run), but select's greedy all but never picks it.
    level, cost = next((i, c) for i, c in enumerate(costs.split(",")) if i and float(c) >= 1)
    expected = f"--costs {costs}: level {level} (low{level}) costs {cost}, {DEAR}"
    r = ok(runner, "init", "-w", tmp_path / "ws", "--gamma", "0.5", "--costs", costs)
    assert r.stderr.splitlines() == [f"warning: {expected}"]
    r = ok(runner, "init", "-w", tmp_path / "js", "--gamma", "0.5", "--costs", costs, "--json")
    assert [json.loads(line) for line in r.stderr.splitlines()] == [{"warning": expected}]
    assert json.loads(r.stdout)["warnings"] == [expected]
    r = ok(runner, "init", "-w", tmp_path / "ws", "--gamma", "0.5", "--costs", costs, "--exist-ok")
    assert r.stderr == ""  # a no-op re-run does not repeat it


def test_a_dear_cheap_level_from_a_settings_file_names_the_file(runner, tmp_path):
    source = tmp_path / "settings.toml"
    source.write_text(
        "levels = [{name = 'high', cost = 1.0}, {name = 'sim2', cost = 1.0}]\n"
        "[study]\ngammas = [0.5]\n"
    )
    r = ok(runner, "init", "-w", tmp_path / "ws", "--settings-from", source)
    assert r.stderr.splitlines() == [f"warning: {source}: level 1 (sim2) costs 1, {DEAR}"]


def test_cheap_levels_below_level_0_are_not_warned(runner, tmp_path):
    r = ok(runner, "init", "-w", tmp_path / "ws", "--gamma", "0.5", "--costs", "1,0.99,0.1")
    assert r.stderr == ""


def test_level_names_without_costs_name_the_levels_the_study_has(runner, tmp_path):
    # --level-names alone was dropped without a word: it names the settings file's levels
    # (or level 0 alone), and a count that does not match is refused naming both.
    from bams_cli.settings import load_settings

    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--settings-from", TOY, "--level-names", "sim,fast")
    levels = load_settings(ws).levels
    assert [(lv.name, lv.cost) for lv in levels] == [("sim", 1.0), ("fast", 0.1)]
    r = invoke(runner, "init", "-w", tmp_path / "w2", "--gamma", "0.5", "--level-names", "a,b")
    assert (
        r.exit_code == 2
        and "--level-names has 2 names for the study's 1 level (level 0 alone); pass --costs"
        in r.stderr
    )
    assert not (tmp_path / "w2").exists()


def test_level_names_are_stripped_and_a_name_no_number_reads_is_kept(runner, tmp_path):
    # "high, low1": results say "low1"; "²" is not a number a results file would read.
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.5", "--costs", "1,0.1,0.05",
       "--level-names", "high, low1,²")  # fmt: skip
    names = [lv.name for lv in Settings.from_file(ws / "settings.toml").levels]
    assert names == ["high", "low1", "²"]


@settings(max_examples=60, deadline=None)
@given(text=st.text(max_size=6) | st.integers(min_value=-3, max_value=40).map(str))
def test_any_dim_text_is_a_dimension_or_a_one_line_usage_error(tmp_path_factory, text):
    # init --dim TEXT: a dimension the settings keep, or exit 2 naming the flag.
    from typer.testing import CliRunner

    ws = tmp_path_factory.mktemp("dim") / "ws"
    r = invoke(CliRunner(), "init", "-w", ws, "--gamma", "0.5", "--dim", text)
    if r.exit_code == 0:
        kept = Settings.from_file(ws / "settings.toml").embedding_dim
        assert kept == "auto" if text.strip() == "auto" else kept == int(text) >= 1
        assert text.strip() == "auto" or text.strip().lstrip("-").isascii()
    else:
        assert r.exit_code == 2, r.output
        [line] = r.stderr.strip().splitlines()
        assert line.startswith("error: --dim"), line
        assert not ws.exists()


@given(
    st.one_of(
        st.integers(min_value=-5, max_value=5000),
        st.floats(allow_nan=False, allow_infinity=False),
        st.text(max_size=6),
        st.booleans(),
    )
)
def test_any_embedding_dim_in_the_file_loads_or_is_refused_naming_it(value):
    import tomli_w

    from bams_cli.errors import SettingsError
    from bams_cli.settings import Settings

    text = tomli_w.dumps(
        {
            "study": {"gammas": [0.5], "embedding_dim": value},
            "levels": [{"name": "high", "cost": 1.0}],
        }
    )
    try:
        dim = Settings.from_toml(text).embedding_dim
    except SettingsError as exc:
        assert exc.setting == "embedding_dim" and "\n" not in str(exc)
        assert value != "auto" and not (
            isinstance(value, int) and not isinstance(value, bool) and value >= 1
        )
    else:
        assert dim == value and (dim == "auto" or dim >= 1)


def test_rerunning_the_init_of_a_workspace_made_before_auto_changes_nothing(runner, tmp_path):
    # Older inits wrote embedding_dim = 12; the same init line with --exist-ok (a Makefile's)
    # now asks for the default "auto" and must still be a no-op, not "other settings".
    ws = tmp_path / "ws"
    ok(runner, "init", "-w", ws, "--gamma", "0.5", "--costs", "1,0.1")
    path = ws / "settings.toml"
    path.write_text(path.read_text().replace('embedding_dim = "auto"', "embedding_dim = 12"))
    before = tree_hash(ws)
    r = ok(runner, "init", "-w", ws, "--gamma", "0.5", "--costs", "1,0.1", "--exist-ok", "--json")
    assert json.loads(r.stdout)["unchanged"] is True and json.loads(r.stdout)["embedding_dim"] == 12
    assert tree_hash(ws) == before
    # Asking for another dimension is still a difference.
    r = invoke(
        runner,
        "init",
        "-w",
        ws,
        "--gamma",
        "0.5",
        "--costs",
        "1,0.1",
        "--exist-ok",
        "--dim",
        "auto",
    )
    assert r.exit_code != 0 and "embedding_dim: 12 in the file, auto requested" in r.stderr
