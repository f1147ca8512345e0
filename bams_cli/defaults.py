"""User-facing defaults that the CLI, the pipeline and the benchmark read from one place.

Each was chosen on the project's problem suite; README, "Defaults, and why", shows the
evidence and says when another value is the better bet.
"""

from __future__ import annotations

from enum import StrEnum

# --- choices: each a StrEnum, so a member is its value ("bams") wherever a string goes ---


class Strategy(StrEnum):
    """``select --strategy``: BAMS, its level-0-only variant, and the paper's baselines."""

    BAMS = "bams"
    BAS = "bas"
    RANDOM = "random"
    MC_GP = "mc-gp"
    MCM_GP = "mcm-gp"
    DS = "ds"
    DS_GP = "ds-gp"
    CE = "ce"


class Pooling(StrEnum):
    """``select --pooling``: how the clusters' candidate picks are compared."""

    GLOBAL = "global"
    RAW = "raw"


class Greedy(StrEnum):
    """``select --greedy``: the exact greedy, the approximate plan, or by pool size."""

    AUTO = "auto"
    EXACT = "exact"
    APPROXIMATE = "approximate"


class Method(StrEnum):
    """``embed-reduce --method``."""

    PCA = "pca"
    AUTOENCODER = "autoencoder"
    IDENTITY = "identity"
    IPCA = "ipca"


class Transform(StrEnum):
    """``fit --transform``."""

    AUTO = "auto"
    NONE = "none"


class Design(StrEnum):
    """``estimate --design``: the sampling design of the rate estimate (``core.estimate``)."""

    POISSON = "poisson"
    FIXED = "fixed"
    WITH_REPLACEMENT = "with-replacement"


class Weighting(StrEnum):
    """``estimate --weighting``: how a stage's inclusion probabilities are chosen."""

    AUTO = "auto"
    UNIFORM = "uniform"
    P_ALPHA = "p-alpha"


class Interval(StrEnum):
    """``estimate --interval``: "gamma" allows for one failure of the model's weight that no
    stage has seen; "fay-feuer" for one of the largest weight any segment could carry, which
    Fay and Feuer (1997) prove covers at the nominal level (wider). ``core.estimate``."""

    GAMMA = "gamma"
    FAY_FEUER = "fay-feuer"


class FailedAs(StrEnum):
    """``estimate --failed-as``: how abandoned planned segments are counted."""

    BOUNDS = "bounds"


class Protocol(StrEnum):
    """``benchmark --protocol``: the paper's two protocols, the suite's problems, or all."""

    TOY2D = "toy2d"
    AV_LIKE = "av_like"
    WEAK_CHEAP = "weak_cheap"
    DIGITS = "digits"
    RARE_REGIONS = "rare_regions"
    GAP_SIM = "gap_sim"
    SUITE = "suite"


# --- where a study lives ---

#: ``-w/--workspace`` when neither the flag nor BAMS_WORKSPACE is given.
WORKSPACE = "./bams-workspace"

# --- embed-reduce ---

METHOD = Method.PCA
#: Rows read per Parquet batch, and rows sampled to train the autoencoder and measure error.
BATCH_SIZE = 8192
SAMPLE_SIZE = 20_000

# --- fit ---

#: Seeded L-BFGS-B restarts of the MAP fit, and pool rows scored per chunk.
RESTARTS = 8
CHUNK_SIZE = 50_000

# --- select ---

STRATEGY = Strategy.BAMS
#: Clusters S (1: no clustering), and the overbudget eta of each cluster's plan.
CLUSTERS = 6
OVERBUDGET = 2.0
POOLING = Pooling.GLOBAL
GREEDY = Greedy.AUTO
#: random (mixed fidelity), mcm-gp and the benchmark's random batches: level-0 share.
LEVEL0_SHARE = 0.5
DIFFICULTY_COLUMN = "difficulty"

# --- estimate ---

DESIGN = Design.POISSON
WEIGHTING = Weighting.AUTO
INTERVAL = Interval.GAMMA
#: Two-sided confidence level of the rate interval.
CONFIDENCE = 0.9

# --- report ---

#: Diverse likely failures listed in the report.
DIVERSE = 5

# --- benchmark ---

PROTOCOL = Protocol.TOY2D
SEEDS = 10
BENCHMARK_WORKERS = 2
BENCHMARK_OUT = "docs/reproduction"

#: Share of a BAMS batch's budget spent on level-0 runs that confirm cheap-level leads
#: (or, without leads, the likeliest unconfirmed failures); ``core.confirm``.
CONFIRM_SHARE = 0.2

#: Output transform of ``fit``: "auto" chooses by evidence between the metric itself and
#: asinh compressions of it far from gamma (``core.gp.transform``); "none" keeps the metric.
TRANSFORM = Transform.AUTO

#: Times ``loop`` runs the simulator again on a list's requests still without a result
#: before it stops: none, so a simulator that fails is seen at once (``--retries N``).
RETRIES = 0

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

#: ``select`` warns when the model expects fewer failures than this in the whole pool
#: (N x J, J = mean p_n (1 - p_n)): its greedy then has nothing to aim at.
SELECT_NEGLIGIBLE_FAILURES = 0.01

#: ``estimate --plan``'s default K is 5 x the GP's expected failures (the paper's 5 p N),
#: at least 5 x (the level-0 failures seen + 1) and at least this many simulations (or every
#: segment without a level-0 result). A GP that has seen no level-0 failure put its rate at
#: 1e-6 in a study with a true 0.0057 (15,000 segments, three batches), and K = 5 gave
#: "0, 90% interval [0, 0.49]"; with no failure among 100 uniform samples the 90% interval
#: (two-sided) reaches about 3%.
PLAN_MIN_SAMPLES = 100

#: A new staged estimate (``estimate --plan``, the default design) samples the open
#: cheap-level leads with certainty (``pipeline.estimation.open_leads``): segments whose
#: cheap run failed and that have no level-0 result. They take at most this share of K,
#: the highest p_n first.
LEAD_SHARE = 0.5
#: ... where the study's own pairs show that a cheap-level failure fails at level 0 at
#: least this often (``core.design.lead_share``: the posterior mean under a uniform prior,
#: (k + 1)/(n + 2), over the n segments with a cheap run at or below gamma and a level-0
#: result, k of them failing there). Not tuned: a lead sampled with certainty lowers the
#: design's variance only where its chance of failing exceeds F/K, the failures of U per
#: run of K (it takes a run from the other segments, whose pi all shrink), and the default
#: K = 5 p N puts F/K at 1/5. On the fresh classif problem leads failed at level 0 7% of
#: the time at K = 1.2 F, and half of K in leads raised the variance to 1.32x uniform's.
LEAD_HIT_MIN = 0.2
#: ... and elsewhere at most this share of K: leads that never fail then raise the
#: variance by at most 1 / (1 - 0.1) = 1.11 of the design's.
LEAD_SHARE_UNPROVEN = 0.1
#: ... counting the runs of a cheap level only where the model's scale for it
#: (``Hyperparameters.scales``) is within this factor of 1: a level in other units (a
#: scale of 2.5, 20) has another threshold than gamma.
LEAD_SCALE_LIMIT = 1.5

#: The rate estimate runs in stages (``estimate --plan`` once per stage): stage 1 spends
#: STAGE1_SHARE of the budget K, and its level-0 outcomes check the model before the later
#: stages spend the rest in equal parts (``core.design``), each planned from the model
#: refitted on every stage before it. Three, not two: a refit on a stage's level-0 runs
#: ranks the segments left better wherever the stage saw failures, and the third stage
#: spends its part on that ranking. Measured as the tool runs (the MAP refit between the
#: stages, docs/suite/estimate_refit.md, 10 seeds): on weak_cheap 0.73 [0.91] of uniform's
#: variance and recall 2.1x plain MC's, against 0.82 [0.99] and 1.7x in two halves;
#: rare_regions 0.99 [1.03] and 2.1x against 0.99 [1.05] and 1.6x; digits, whose stages
#: see a failure or none, 0.99 [1.06] and 1.8x against 1.00 [1.06] and 1.9x.
STAGES = 3
#: Where the fitted model's discrepancy-plus-cheap-noise sd is under this share of its
#: level-0 signal sd the cheap level tracks level 0: the screen's pi2 trusts the refitted
#: p_n (RISK_MIX_PRIOR_CONFIRM), and an unscreened plan (--screen off) notes that a screen
#: would pay. At or above it the priors on lam trust p_n less (RISK_MIX_PRIOR_WEAK_CHEAP).
#: A screen confirmed by the refitted p_n alone had at most 1.06x the unscreened design's
#: variance below it on the suite, and up to 1.68x above it (docs/suite/screen_design.md,
#: fourth table); the screen's own leads (SCREEN_LEAD_SHARE) removed that cost.
SCREEN_HINT_DISCREPANCY = 0.3
#: The share of K a screen spends under --screen auto, and the suggested one (the share
#: measured there; 0.4 was worse on braking, ties and blind, README).
SCREEN_HINT_SHARE = 0.3
#: A screen's confirmation runs at level 0, with certainty, the screened segments whose
#: cheap result is among the lowest SCREEN_LEAD_SHARE x K2 of the screen's (K2 the level-0
#: runs left once the screen is paid; ``core.screen.screen_leads``), the open leads
#: counted among them; the rest of K2 goes by the refitted model. Model-free: drawn from
#: the truth with the rest spread uniformly, a screen of 0.3 of K confirming its lowest
#: 0.5 K2 this way held at most 0.92x a uniform design's variance on every one of the 15
#: suite and fresh problems, at 1.5x-3.0x its recall (0.3 K2: 0.90x, 0.7 K2: 1.08x;
#: docs/suite/screen_frontier.md).
SCREEN_LEAD_SHARE = 0.5
#: ``estimate --plan --screen``'s default: "auto" screens SCREEN_HINT_SHARE of a new
#: estimate's K wherever the study has a cheap level and a refit can condition on the
#: screen (``pipeline.screening.auto_share``), and plans the staged design elsewhere; "off"
#: never screens. Measured through the benchmark on the suite (README, "Defaults, and
#: why"; docs/reproduction/suite: weak_cheap, digits and rare_regions, staged until
#: 2026-11-30, went from 1.3x, 1.8x and 1.7x plain MC's recall to 2.1x, 3.5x and 2.3x, at
#: 0.86, 0.56 and 0.50 of uniform's variance). Its cost: where the cheap level is
#: unrelated to level 0 the screen's leads are a random share of S1, and the design had
#: 1.59-2.62 times a uniform one's variance (staged: 0.68-1.05), with nothing before the
#: screen to tell it from a weak level that pays (docs/suite/unrelated_cheap.md).
SCREEN = "auto"
#: Stage 1's share of K: an equal part (each stage spends K / STAGES).
STAGE1_SHARE = 1.0 / 3.0
#: ``estimate --plan`` says so when its default K (5 p N) is at least this share of the
#: segments without a level-0 result: a common failure, or a model that overstates it,
#: asks for nearly a census.
PLAN_LARGE_SHARE = 0.5

#: Beta prior on lam, the share of the failure mass the model does not explain
#: (``core.design.risk_posterior``); its mean (1/3 here) is the trust the first stage places
#: in p_n. Beta(0.5, 1) leans to trust but keeps a heavy tail towards 1 (its 0.9 quantile,
#: where the interval's allowance for unseen failures sits, is 0.81). Chosen on the suite
#: against Beta(1, 1), Beta(1, 2) and Beta(1, 3) (docs/suite/risk_prior.md): with Beta(1, 2),
#: within a few thousandths of it everywhere, it keeps every problem and model within 1.2x
#: of uniform's variance while bringing av_like to about 1/5 of it; Beta(1, 3) took
#: rare_regions and digits past 1.2x at worst.
RISK_MIX_PRIOR = (0.5, 1.0)

#: The prior on lam where the fitted cheap level does not track level 0 (its discrepancy sd
#: at least SCREEN_HINT_DISCREPANCY of the level-0 signal's; ``core.design.risk_prior``):
#: Beta(1, 0.5), mean 2/3, trusting p_n half as much. Such a model's p_n rests on its few
#: level-0 runs, and there the prior decides: stage 1 rarely samples a failure (0.2 expected
#: on rare_regions), so stage 2 is drawn at the prior too. An estimate keeps the prior of
#: its first step (a stage, a screen) to its last. Measured on every run at or above that
#: threshold (docs/suite/weak_cheap_prior.md; held out: every run of weak_cheap, digits and
#: rare_regions, which auto did not screen until 2026-11-30): the worst seed's
#: variance over uniform's fell from 1.16 to 1.07 on the suite, from 1.22 to 1.08 on
#: held-out instances and from 1.19 to 1.09 on a real-data problem written after the
#: defaults (cancer), at the same coverage; a model that ranked well there (one run of a
#: problem whose cheap level is blind to one failure mode) went from 0.26 to 0.36. Since
#: auto screens them, it plans their screen's pi1 and pi2 (suite: 0.86, 0.56 and 0.50 of
#: uniform's variance; coverage 0.956-1.000, docs/suite/screen_design.md).
RISK_MIX_PRIOR_WEAK_CHEAP = (1.0, 0.5)

#: The prior on lam of a screen's level-0 confirmation (pi2 over S1,
#: ``core.design.confirm_prior``) where the fitted cheap level tracks level 0 (its
#: discrepancy sd under SCREEN_HINT_DISCREPANCY of the level-0 signal's): Beta(0.1, 10), mean 0.01, trusting the refitted p_n almost
#: wholly. After the screen every segment of S1 has its own cheap run, so p_n there is
#: close to a measurement, not a prediction from distant level-0 runs; a failure the
#: refit misses is one its cheap level misses too. The screen's pi1 and the interval's
#: allowance keep the study's prior (RISK_MIX_PRIOR). Where the cheap level does not track
#: level 0, the confirmation keeps RISK_MIX_PRIOR_WEAK_CHEAP.
#: Chosen against Beta(0.5, 1) and Beta(0.25, 4) (docs/suite/screen_confirm_prior.md):
#: against Beta(0.5, 1) the mean variance over uniform's fell on every problem measured
#: (toy2d 0.035 -> 0.021, gap_sim 0.40 -> 0.34, av_like's held-out data seed 2 0.31 -> 0.19;
#: three problems written after the defaults: 0.15 -> 0.10, 0.19 -> 0.18, 0.28 -> 0.23),
#: the worst run rose where the cheap level misses failures (0.24 -> 0.29, 0.46 -> 0.49),
#: and the interval's misses below the rate fell (braking 4.2% -> 1.8% of draws).
RISK_MIX_PRIOR_CONFIRM = (0.1, 10.0)

#: Posterior quantile of lam at which the interval's allowance for an unseen failure is
#: computed: the least trust in p_n that the earlier stages cannot rule out.
RISK_MIX_UPPER = 0.9

#: How far (log-sd) the failure rate of what the model explains may stray from its own
#: mean p_n before the count of failures an estimate stage finds says "the model misses
#: failures" (``core.design.risk_posterior``).
RISK_ANCHOR_SD = 1.0

#: ``fit`` finds the hyperparameters (MAP, every restart) on at most this many observations,
#: a random subset stratified by level, and then conditions the model on all of them: each
#: MAP step costs O(n^3), so a study past its estimate stages (hundreds to thousands of
#: level-0 runs) would otherwise spend minutes in the search (measured: 1,000 observations,
#: d = 12, 203 s under load). The suite's fits stay below it (bench/bench_fit.py).
FIT_SUBSET = 300

#: ``fit`` conditions exactly on every observation while the training covariance (factorised
#: in place) fits this many bytes (``core.conditioning_budget.max_conditioned``: 14,654 observations);
#: above, exactly on a subset of that many, level-0 observations first
#: (``core.gp.fit.conditioning_subset``; its sds are never below the exact posterior's,
#: its accuracy measured by ``bench/bench_fit.py --accuracy``). The size also sets the
#: time of scoring (pool size x n^2 flops, 9.7e12 for 45,000 points at 14,654): with
#: 2.5 GiB (16,384) 50,000 observations took 313 s on 2 lightly loaded cores, over the
#: 5-minute target (README, Performance). A study never needs more than this for the
#: model; under ``--max-memory`` at most half the ceiling is used.
FIT_CONDITION_MEMORY = 2 * 2**30

#: ``fit`` scores the pool exactly (mean and sd at every segment against every conditioned
#: observation) while pool size x n^2, the flops of the sds' triangular solves, stays under
#: this (about 5 minutes of solves on 2 cores). Above it (a million segments after an
#: estimate stage's 12,000 level-0 runs: 1.5e14, over an hour) the mean stays exact and an
#: eighth of this buys an upper bound on every sd (a model on fewer observations); the rest
#: buys exact sds where a threshold is within ``SCORE_DECIDED_Z`` bound-sds of the mean,
#: nearest first. Elsewhere p_n is 0 or 1 to within 1e-17 (``core.gp.MFGP.score``). That
#: study's fit: 7 min 14 s at 2e13, every sd within 8.5 sds of the threshold exact (64,368);
#: 6 min 28 s at 5e12, 16,893 of them exact. ``select`` bounds the pool's sds the same
#: way past it (``core.select._predict``), for its first gamma.
SCORE_MAX_WORK = 2e13

#: Where |gamma - mu| exceeds this many (upper-bound) sds, p_n = Phi(-z) is below 1e-17
#: from 0 or 1 whatever the exact sd (never larger than the bound) is.
SCORE_DECIDED_Z = 8.5

#: ``select`` runs the exact greedy (every row, every candidate; picks identical to the
#: brute-force greedy) on pools up to this many segments, ``select --greedy`` overriding.
#: Larger pools get an approximate plan (``core.select.plan_selection``) whose batch keeps
#: >= 99% of the exact greedy's J decrease where both can be run (``bench/bench_select.py
#: --sweep``, tests/core/test_select.py). The exact greedy's work grows as N^2 / S:
#: ``bench/bench_select.py --sizes 10000 25000 45000 --no-reference`` (av_like, 2 idle
#: cores, 2026-11-23) took 1.0 s at 10,000 segments, 4.6 s at 25,000 and 13.4 s at 45,000
#: exactly, the approximate plan 1.5 s, 2.7 s and 3.7 s, with J ratios 1.0000, 1.0026 and
#: 1.0000. The two cost the same somewhere between 10,000 and 25,000; 20,000 keeps the
#: benchmark's toy2d and av_like pools (20,000) on the exact greedy.
SELECT_EXACT_MAX_POOL = 20_000

#: Approximate plan of ``select``: the pool is cut into clusters of about this many
#: segments (never fewer clusters than asked) ...
SELECT_CLUSTER_ROWS = 25_000
#: ... each cluster's J is summed over at most this many of its rows (those where the
#: model is least sure, largest p_n (1 - p_n)); 1,024 is faster, but at 200,000 segments
#: the rows it leaves out could hold 71% of a cluster's sum of p_n (1 - p_n) (32% here) ...
SELECT_MAX_ROWS = 4_096
#: ... and the greedy chooses among at most this many candidates: the best first picks
#: (``core.select.screen_candidates``), plus a uniform random share of the rest. On av_like
#: pools the candidate limit costs more of the J decrease than the row limit does.
SELECT_MAX_CANDIDATES = 1_024
SELECT_RANDOM_SHARE = 0.1
#: ... screened anew, given the picks so far, this many times as each cluster's greedy
#: spends its budget (after each 1/R of it): one screen from the first-step score keeps
#: candidates near the first picks only.
SELECT_SCREEN_ROUNDS = 3
#: ... and K-means with the merge loop runs on a sample of this many segments.
SELECT_CLUSTER_FIT_MAX = 50_000
#: ... and past this many observations, where the candidates' factors (n^2 flops each)
#: exceed ``SCORE_MAX_WORK``, each cluster's greedy conditions on the nearest this many to
#: its segments (``core.gp.MFGP.nearest``): at a million segments after an estimate stage
#: (14,654 observations) the screen's two million candidates took hours. On a sample of
#: that study it kept 78% of the whole model's J decrease (4,000: 79%).
SELECT_LOCAL_OBS = 2_000

#: ``--max-memory`` of ``select``, ``fit``, ``embed-reduce`` and ``report`` when not given:
#: this share of the machine's RAM (``bams_cli.memory``), leaving the rest to the
#: simulators and the operating system that share the machine.
MAX_MEMORY_FRACTION = 0.5
