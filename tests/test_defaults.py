"""Every default of the Python API is the one in bams_cli.defaults (issue 14, point 3).

A notebook calling ``bams_cli.api.select(ws)`` must do what ``bams-cli select -w ws`` does,
and the CLI and the benchmark read their defaults from ``bams_cli.defaults``. So every
parameter of a public pipeline or API function with a default other than None or a flag
(True/False) is found in ``defaults`` by its name (``budget`` -> ``BUDGET``, or an alias
below) and must equal it: a literal that drifts from the constant fails here. A parameter
with no constant must be listed in ``NOT_A_STUDY_DEFAULT`` with why.
"""

from __future__ import annotations

import inspect

import pytest

from bams_cli import api, defaults, pipeline

#: Parameters whose constant has another name.
ALIASES = {"n_diverse": "DIVERSE"}

#: Defaults that are not study settings, so not in bams_cli.defaults.
NOT_A_STUDY_DEFAULT = {
    ("report", "max_points"): "how many pool points the 2-D pool map draws, a drawing limit",
    ("pending_summary", "limit"): "how many pending picks a message lists, a display limit",
}


def _public_functions() -> dict[str, object]:
    out = {}
    for module in (api, pipeline):
        for name in module.__all__:
            fn = getattr(module, name)
            if inspect.isfunction(inspect.unwrap(fn)):
                out[name] = fn
    return out


def _checked_defaults() -> list[tuple[str, str, object]]:
    """(function, parameter, default) for every default that must be a defaults constant."""
    rows = []
    for name, fn in sorted(_public_functions().items()):
        for param in inspect.signature(inspect.unwrap(fn)).parameters.values():
            value = param.default
            if value is inspect.Parameter.empty or value is None or isinstance(value, bool):
                continue
            rows.append((name, param.name, value))
    return rows


CHECKED = _checked_defaults()


def test_the_check_covers_the_api():
    # Not vacuous: select's, fit's, estimate's, embed-reduce's, loop's and report's
    # defaults are all among those compared.
    functions = {fn for fn, _, _ in CHECKED}
    assert {"select", "fit", "estimate_plan", "estimate_compute", "embed_reduce", "loop",
            "report"} <= functions  # fmt: skip
    assert len(CHECKED) >= 25


@pytest.mark.parametrize(("fn", "param", "value"), CHECKED, ids=[f"{f}.{p}" for f, p, _ in CHECKED])
def test_every_api_default_is_the_one_in_defaults(fn, param, value):
    if (fn, param) in NOT_A_STUDY_DEFAULT:
        assert not hasattr(defaults, ALIASES.get(param, param.upper()))
        return
    constant = ALIASES.get(param, param.upper())
    assert hasattr(defaults, constant), (
        f"{fn}({param}={value!r}): no bams_cli.defaults.{constant}; define the default there "
        "(or list the parameter in NOT_A_STUDY_DEFAULT with why)"
    )
    want = getattr(defaults, constant)
    assert value == want and type(value) in (type(want), *type(want).__mro__), (
        f"{fn}({param}={value!r}) drifted from bams_cli.defaults.{constant} = {want!r}"
    )
