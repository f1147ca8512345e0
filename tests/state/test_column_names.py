"""A required column the file spells another way: the error names the rename that fixes it,
and never offers a column for a name it does not resemble (Hypothesis)."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from bams_cli.state.io import near_miss, near_misses

REQUIRED = ["segment_id", "fidelity", "value", "request_id"]
WORDS = st.text(alphabet="abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=12)


def _respell(name: str, draw: st.DrawFn) -> str:
    """``name`` as a team might write it: other case, spaces or dashes for underscores."""
    sep = draw(st.sampled_from(["_", " ", "-", ""]))
    case = draw(st.sampled_from([str.lower, str.upper, str.title, str.capitalize]))
    return case(name.replace("_", sep))


@st.composite
def respelt(draw: st.DrawFn) -> tuple[str, str, list[str]]:
    want = draw(st.sampled_from(REQUIRED))
    spelt = _respell(want, draw)
    others = draw(st.lists(st.sampled_from(["x0", "x1", "scenario", "notes", "run"]), unique=True))
    found = draw(st.permutations([spelt, *others]))
    return want, spelt, list(found)


@given(respelt())
def test_a_respelt_required_column_is_named_with_its_rename(case):
    want, spelt, found = case
    if spelt == want:  # spelt as wanted: nothing is missing, nothing to suggest
        assert near_miss(want, found) is None
        return
    assert near_miss(want, found) == spelt
    assert near_misses([want], found) == f"; rename {spelt!r} to {want!r} (column names are exact)"


@given(st.sampled_from(REQUIRED), st.lists(WORDS, unique=True, max_size=6))
def test_a_column_is_offered_only_when_it_resembles_the_name(want, found):
    like = near_miss(want, found)
    if like is None:
        return
    assert like in found and like != want
    plain = "".join(ch for ch in like.lower() if ch.isalnum())
    from difflib import SequenceMatcher

    assert plain == want.replace("_", "") or SequenceMatcher(None, want, like).ratio() >= 0.75


def test_names_that_are_wanted_or_unlike_are_not_offered():
    # 'fidelity' is itself required: it is never offered as the spelling of another column.
    assert near_misses(["value", "fidelity"], ["segment_id", "fidelity", "metric"]) == ""
    assert near_miss("request_id", ["rid", "req"]) is None
    assert near_miss("value", ["val"]) == "val"


def test_a_name_is_never_offered_across_a_number_at_its_end():
    # A truth file without value_0 is not told to rename value_2 (level 2's values), nor a
    # results file to rename value_1 to value.
    assert near_miss("value_0", ["segment_id", "value_1", "value_2"]) is None
    assert near_miss("value", ["segment_id", "fidelity", "value_1"]) is None
    assert near_miss("value_0", ["segment_id", "Value 0"]) == "Value 0"
