"""The estimate command end to end: defaults read from one place, NaN-free JSON, --seed."""

from __future__ import annotations

import inspect

import pytest

from bams_cli import cli, defaults, pipeline
from bams_cli.core import estimate as core_estimate


@pytest.mark.parametrize(
    "name, value", [("alpha", defaults.ALPHA), ("defensive", defaults.DEFENSIVE)]
)
def test_alpha_and_defensive_have_one_definition(name, value):
    # Issue 12: the CLI said alpha 0.75 and core 1.0. Every layer now reads bams_cli.defaults.
    assert (defaults.ALPHA, defaults.DEFENSIVE) == (0.75, 0.1)
    for fn in (core_estimate.plan_sample, pipeline.estimate_plan.__wrapped__, cli.estimate):
        assert inspect.signature(fn).parameters[name].default == value, fn.__qualname__
