"""User-facing defaults that the CLI, the pipeline and the benchmark read from one place.

Each was chosen on the project's problem suite; README, "Defaults, and why", shows the
evidence and says when another value is the better bet.
"""

from __future__ import annotations

#: Share of a BAMS batch's budget spent on level-0 runs that confirm cheap-level leads
#: (or, without leads, the likeliest unconfirmed failures); ``core.confirm``.
CONFIRM_SHARE = 0.2

#: Output transform of ``fit``: "auto" chooses by evidence between the metric itself and
#: asinh compressions of it far from gamma (``core.gp.transform``); "none" keeps the metric.
TRANSFORM = "auto"

#: Budget of ``select`` in cost units (a level-0 run costs 1), and of the first batch that
#: ``status`` suggests.
BUDGET = 5.0
