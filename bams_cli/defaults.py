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

#: Sharpening exponent of the rate-estimation sample: segments are sampled in proportion to
#: p_n^alpha (``core.estimate.selection_distribution``). DESIGN.md ("Rate estimate"):
#: alpha = 2.5 (the paper's) was worse than 1 or 0.5 for every strategy; with a calibrated
#: p_n, 1/2 minimises the Poisson design's variance.
ALPHA = 0.75

#: Defensive uniform share eps mixed into the sampling distribution: it bounds every
#: inclusion probability below by ~eps K / |U|, so a failure the GP rules out with
#: confidence costs a bounded, not an astronomical, variance (DESIGN.md, "Rate estimate").
DEFENSIVE = 0.1

#: The rate estimate runs in stages (``estimate --plan`` once per stage): stage 1 spends
#: this share of the budget K, and its level-0 outcomes check the model before the later
#: stages spend the rest (``core.design``).
STAGES = 2
STAGE1_SHARE = 0.5

#: Beta prior on lam, the share of the failure mass the model does not explain
#: (``core.design.risk_mix_posterior``); its mean is the trust the first stage places in p_n.
RISK_MIX_PRIOR = (1.0, 1.0)

#: Posterior quantile of lam at which the interval's allowance for an unseen failure is
#: computed: the least trust in p_n that the earlier stages cannot rule out.
RISK_MIX_UPPER = 0.9

#: How far (log-sd) the failure rate of what the model explains may stray from its own
#: mean p_n before the count of failures an estimate stage finds says "the model misses
#: failures" (``core.design.risk_posterior``).
RISK_ANCHOR_SD = 1.0

#: ``select`` runs the exact greedy (every row, every candidate; picks identical to the
#: brute-force greedy) on pools up to this many segments. Larger pools get an approximate
#: plan (``core.select.plan_selection``) whose batch keeps >= 99% of the exact greedy's J
#: decrease where both can be run (``bench/bench_select.py``, tests/core/test_select.py).
SELECT_EXACT_MAX_POOL = 45_000

#: Approximate plan of ``select``: the pool is cut into clusters of about this many
#: segments (never fewer clusters than asked) ...
SELECT_CLUSTER_ROWS = 25_000
#: ... each cluster's J is summed over at most this many of its rows (those where the
#: model is least sure, largest p_n (1 - p_n)) ...
SELECT_MAX_ROWS = 4_096
#: ... and the greedy chooses among at most this many candidates: the best first picks
#: (``core.select.screen_candidates``), plus a uniform random share of the rest. On av_like
#: pools the candidate limit costs more of the J decrease than the row limit does.
SELECT_MAX_CANDIDATES = 4_096
SELECT_RANDOM_SHARE = 0.1
#: ... and K-means with the merge loop runs on a sample of this many segments.
SELECT_CLUSTER_FIT_MAX = 50_000
