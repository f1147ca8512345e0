"""The paper-reproduction harness: the paper's protocols run through the real pipeline.

``run_benchmark("toy2d", ...)`` is the synthetic protocol of the paper's appendix
"Synthetic Experiments"; ``run_benchmark("av_like", ...)`` the AV protocol of section 4 on
the AV-like sample data. For every (strategy, seed) a fresh workspace is created in a
temporary folder and driven through exactly the functions behind the subcommands:

    init -> embed-reduce -> select (batch 1: random, budget m1) -> simulate -> ingest-results
         -> fit -> select (strategy, budget m_b) -> simulate -> ingest-results -> fit -> ...

three batches in all. After batch 3 the harness plans the rate estimate with
``estimate --plan`` (K = k p N segments, p the true rate), simulates it, ingests it,
refits the model on it as ``loop`` does (a plain ``fit``), plans and runs each later stage
the same way, and computes it (one realised estimate per run, the tool's whole path), and
then evaluates the *design* exactly from the inclusion probabilities:

* recall = expected fraction of all true failures that end up in hand: the known stratum
  (level-0 observations from discovery, counted exactly) plus sum over the failures of U of
  their inclusion probability (``evaluate.expected_is_recall``);
* RV = Var(p_hat) / p^2, Var the design's exact variance (``evaluate.exact_variance``),
  never the spread of a few hundred trials (DESIGN.md).

Both are reported for the default estimator design (the ``estimate_plan`` defaults:
Poisson sampling over U with the known stratum), for the paper's sampler (K draws with
replacement from q proportional to p_n^2.5 over the whole pool, no known stratum, no
defensive share; paper section 4.1; also as the spread of 200 repeated estimates, the way
the paper measured it) and for that sampler at the default alpha and defensive share.
Plain MC: uniform sampling (the default design with alpha = 0), and under "paper"
importance sampling by uniform random scores raised to 2.5, which is what the paper's MC
row (710) matches (``mc_explanation``, docs/reproduction/README.md).

Three uniform strategies, easy to confuse (``select --strategy random`` and
``--strategy mc-gp`` pick the same segments from the same seed; what differs is what
happens after):

* ``random`` is not a strategy of the harness but the pick rule of every first batch
  (level 0 only, or mixed fidelity for BAMS and MCM-GP).
* ``mc``: uniform level-0 picks in every batch, no GP at all, and a uniform estimate (the
  default design with alpha = 0: every unknown segment has the same inclusion
  probability; the discovered level-0 values are still counted exactly). Its RV is plain
  Monte Carlo's, (1 - pi)/(p K) up to the known stratum.
* ``mc-gp``: the same uniform level-0 picks, but a GP is fitted after every batch and
  the estimate is importance-weighted by its p_n, exactly as for BAMS. The gap between
  ``mc-gp`` and ``bams`` is what the greedy's picks are worth; the gap between ``mc`` and
  ``mc-gp`` is what the GP's scoring is worth.

The suite (``run_suite``, ``--protocol suite``) runs the problems of ``core.suite``
(weak_cheap, digits, rare_regions, gap_sim; generated, truth at both levels) beside toy2d
and av_like, each into its own folder, and writes ``suite.md``: per problem and
strategy, recall, RV, the fitted level-1 discrepancy sd against the true sd(f1 - f0),
level-0 picks per batch and the GP's own estimate mean(p_n) against the true rate. The
paper has no numbers for the new problems (their ``paper`` dicts are empty).

Everything the harness adds is orchestration and arithmetic over the workspaces' own
state files; it selects, fits and estimates nothing by itself.
"""

from __future__ import annotations

import importlib.metadata
import json
import math
import os
import platform
import shutil
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from bams_cli import defaults, pipeline
from bams_cli.core import suite, synthetic
from bams_cli.core.estimate import plan_sample
from bams_cli.core.evaluate import exact_variance, expected_is_recall, retention_recall
from bams_cli.errors import OptionError, OptionValueError
from bams_cli.pipeline._common import ids_in
from bams_cli.settings import Settings, levels_from_costs

Progress = Callable[[str, int, int], None]

SAMPLE_DATA = Path(__file__).resolve().parent.parent / "sample_data"

#: Strategies whose picks feed a GP (all but plain MC, DS and CE).
GP_STRATEGIES = ("bams", "bas", "mcm-gp", "mc-gp", "ds-gp")
#: Strategies whose first batch mixes fidelities.
MULTIFIDELITY = ("bams", "mcm-gp")
#: Grid of retention levels (units of p N) for the retention-recall curves.
RETENTION_GRID = np.round(np.linspace(0.0, 10.0, 101), 10)
#: The paper's sampler: K draws with replacement from p_n^alpha, alpha = 2.5, no defensive
#: share, over the whole pool (paper section 4.1 and appendix "IS parameter alpha").
PAPER_ALPHA = 2.5
#: Repeated trials the paper measured its RV over (section 4.1).
PAPER_TRIALS = 200


@dataclass(frozen=True)
class Protocol:
    """One of the paper's experimental protocols.

    Attributes
    ----------
    name : str
        Problem: ``sample_data/<name>`` when committed there, else generated by
        ``GENERATORS[name]`` (``prepare_data``).
    m1, mb : float
        Budget of batch 1 (random) and of batches 2 and 3 (strategy), in level-0 runs.
    n_batches : int
    k_factor : float
        Rate-estimation budget K = k_factor p N (p the true rate).
    strategies : tuple of str
        In table order.
    reduce : dict
        Keyword arguments for ``pipeline.embed_reduce``.
    default_n : int
        Pool size of the committed sample data (or of the generated pool).
    paper : dict
        The paper's table: strategy -> (recall, recall SE, 100 RV, 100 RV SE); empty for
        problems the paper did not run.
    paper_table1 : dict
        The paper's Table 1 (AV only): strategy -> [(mean f, SE) per batch].
    """

    name: str
    m1: float
    mb: float
    n_batches: int
    k_factor: float
    strategies: tuple[str, ...]
    reduce: dict[str, Any]
    default_n: int
    paper: dict[str, tuple[float, float, float, float]]
    paper_table1: dict[str, list[tuple[float, float]]] = field(default_factory=dict)


PROTOCOLS: dict[str, Protocol] = {
    # Appendix "Synthetic Experiments", Table 3.
    "toy2d": Protocol(
        name="toy2d",
        m1=10,
        mb=5,
        n_batches=3,
        k_factor=2.0,
        strategies=("bams", "bas", "mcm-gp", "mc-gp", "mc"),
        reduce={"columns": "x*", "method": "identity", "standardize": False},
        default_n=20_000,
        paper={
            "bams": (1.00, 0.000, 2.00, 0.003),
            "bas": (0.917, 0.003, 3.85, 0.366),
            "mc": (0.010, 0.001, 710.0, 214.0),
            "mc-gp": (0.394, 0.004, 39.4, 3.88),
            "mcm-gp": (0.537, 0.005, 29.76, 5.08),
        },
    ),
    # Section 4, Tables 1 and 2.
    "av_like": Protocol(
        name="av_like",
        m1=20,
        mb=15,
        n_batches=3,
        k_factor=5.0,
        strategies=("bams", "bas", "mcm-gp", "mc-gp", "ds-gp", "ce", "ds", "mc"),
        reduce={"method": "pca", "dim": 12},
        default_n=2_000,
        paper={
            "bams": (0.511, 0.0013, 0.851, 0.121),
            "bas": (0.388, 0.0013, 0.969, 0.037),
            "mc": (0.048, 0.0006, 13.5, 2.86),
            "mc-gp": (0.368, 0.0012, 5.70, 2.39),
            "mcm-gp": (0.460, 0.0019, 1.43, 0.288),
            "ds": (0.051, 0.0007, 5.40, 0.096),
            "ds-gp": (0.315, 0.0012, 3.67, 0.599),
            "ce": (0.096, 0.0007, 4.43, 0.063),
        },
        paper_table1={
            "bams": [(4.99, 0.51), (1.75, 0.16), (1.49, 0.21)],
            "bas": [(6.55, 0.78), (2.27, 0.58), (3.19, 0.89)],
            "mc-gp": [(6.55, 0.78), (6.34, 0.83), (4.53, 0.6)],
            "mcm-gp": [(4.99, 0.51), (6.09, 0.51), (5.86, 0.55)],
            "ds-gp": [(6.55, 0.78), (6.47, 0.81), (7.37, 0.77)],
            "ce": [(6.55, 0.78), (2.91, 0.26), (2.20, 0.12)],
        },
    ),
}


def _suite_protocol(name: str) -> Protocol:
    """A suite problem's protocol: m1 = 10 random mixed, 2 x 5 by the strategy, K = 2 p N;
    the embedding reduced as a new study does, by ``embed-reduce``'s defaults."""
    return Protocol(
        name=name,
        m1=10,
        mb=5,
        n_batches=3,
        k_factor=2.0,
        strategies=SUITE_STRATEGIES,
        reduce={"method": "pca"},
        default_n=suite.DEFAULT_N[name],
        paper={},
    )


#: Strategies the suite runs by default, on every problem.
SUITE_STRATEGIES = ("bams", "mcm-gp", "mc")
# The dimension is embed-reduce's default, --dim auto (core.reduce.choose_dim): 12 for
# weak_cheap, digits and gap_sim, 24 for rare_regions. Until 2026-11-25 the protocols
# passed 8, 10, 12 and 8, "about what a user would keep"; docs/suite/dimension.md.
PROTOCOLS["weak_cheap"] = _suite_protocol("weak_cheap")
PROTOCOLS["digits"] = _suite_protocol("digits")
PROTOCOLS["rare_regions"] = _suite_protocol("rare_regions")
PROTOCOLS["gap_sim"] = _suite_protocol("gap_sim")
#: ``--protocol suite``: every problem, in table order.
SUITE = ("toy2d", "av_like", "weak_cheap", "digits", "rare_regions", "gap_sim")
#: Pool generators (n, seed) -> SyntheticPool, for the problems prepare_data can make.
GENERATORS: dict[str, Callable[[int, int], synthetic.SyntheticPool]] = {
    "toy2d": synthetic.toy2d,
    "av_like": synthetic.av_like,
    "weak_cheap": suite.weak_cheap,
    "digits": suite.digits,
    "rare_regions": suite.rare_regions,
    "gap_sim": suite.gap_sim,
}

QUICK_SEEDS = 3


# ---------------------------------------------------------------------------------------
# data
# ---------------------------------------------------------------------------------------
def prepare_data(protocol: Protocol, n: int | None, scratch: Path) -> Path:
    """The committed sample data, or a pool of ``n`` segments generated into ``scratch``.

    Generated pools come from ``GENERATORS`` (``core.synthetic``, ``core.suite``) with data
    seed 0, like ``sample_data/generate.py``; the committed files are those pools at the
    default n. toy2d's two coordinates are written as columns x0, x1, every other
    problem's features as one ``embedding`` list column; pass-through columns
    (``difficulty`` for av_like and gap_sim, ``label`` for digits) follow them.
    """
    if n is None or n == protocol.default_n:
        folder = SAMPLE_DATA / protocol.name
        if (folder / "segments.parquet").exists():
            return folder
        n = protocol.default_n  # installed without sample_data/: make the same pool
    folder = scratch / f"{protocol.name}-{n}"
    try:
        pool = GENERATORS[protocol.name](n, 0)
    except ValueError as exc:  # e.g. digits has only 1,797 images
        raise OptionValueError(f"--n {n}: {exc}") from None
    folder.mkdir(parents=True, exist_ok=True)
    ids = pa.array(pool.ids, pa.string())
    cols: dict[str, Any] = {"segment_id": ids}
    if protocol.name == "toy2d":
        for j in range(pool.features.shape[1]):
            cols[f"x{j}"] = pool.features[:, j]
        dim = pool.features.shape[1]
    else:
        flat = pa.array(pool.features.astype(np.float32).ravel(), pa.float32())
        cols["embedding"] = pa.FixedSizeListArray.from_arrays(flat, pool.features.shape[1])
        dim = protocol.reduce.get("dim", "auto")
    for key, values in pool.extra.items():
        values = np.asarray(values)
        cols[key] = pa.array(values if values.dtype.kind in "iu" else np.round(values, 4))
    pq.write_table(pa.table(cols), folder / "segments.parquet", row_group_size=5_000)
    truth: dict[str, Any] = {"segment_id": ids}
    for lv in range(pool.truth.shape[1]):
        truth[f"value_{lv}"] = pa.array(pool.truth[:, lv])
    pq.write_table(pa.table(truth), folder / "truth.parquet")
    settings = Settings(
        gammas=(pool.gamma,), levels=levels_from_costs(pool.costs), seed=0, embedding_dim=dim
    )
    (folder / "settings.toml").write_text(settings.to_toml())
    return folder


def _column(path: Path, name: str) -> np.ndarray:
    return pq.read_table(path, columns=[name]).column(name).to_numpy(zero_copy_only=False)


# ---------------------------------------------------------------------------------------
# one run: a workspace driven through the pipeline
# ---------------------------------------------------------------------------------------
@dataclass
class RunSpec:
    """Everything a worker needs to run one (strategy, seed)."""

    protocol: str
    strategy: str
    seed: int
    data: str
    scratch: str
    level0_share: float
    clusters: int
    K: float
    keep_workspace: bool = False
    greedy: str = defaults.GREEDY.value


@dataclass
class RunResult:
    """What one run hands back; arrays over the pool are in the truth file's row order.

    Attributes
    ----------
    picks : list of (pool index, level) int arrays, one pair per batch
    p_after : list of ndarray of shape (N,) or None
        p_n after each batch (None for strategies without a GP).
    scores : ndarray of shape (N,) or None
        Importance scores of strategies without a GP (DS: difficulty weights, CE: the
        final cross-entropy density); None for MC and GP strategies.
    known : bool ndarray of shape (N,)
        Level-0 value observed during discovery (the known stratum).
    hyperparameters : list of dict or None, one per batch
    realised : dict or None
        The one estimate computed through ``estimate --plan`` ... ``estimate``.
    seconds : dict of phase -> wall seconds
    screen : dict or None
        Where the default estimate screens (``estimate --plan --screen auto``), the
        screened design measured from the truth (``screen_default``); None where it plans
        the staged design, or for strategies without a GP.
    """

    strategy: str
    seed: int
    picks: list[tuple[np.ndarray, np.ndarray]]
    p_after: list[np.ndarray | None]
    scores: np.ndarray | None
    known: np.ndarray
    hyperparameters: list[dict[str, Any] | None]
    realised: dict[str, Any] | None
    seconds: dict[str, float]
    workspace: str | None = None
    screen: dict[str, Any] | None = None


# The options a user leaves at their defaults, passed from ``bams_cli.defaults`` (not
# left to the pipeline functions' signatures), so the benchmark measures what a user runs.
SELECT_DEFAULTS: dict[str, Any] = {
    "overbudget": defaults.OVERBUDGET,
    "pooling": defaults.POOLING.value,
    "confirm_share": defaults.CONFIRM_SHARE,
    "difficulty_column": defaults.DIFFICULTY_COLUMN,
}
FIT_DEFAULTS: dict[str, Any] = {
    "restarts": defaults.RESTARTS,
    "chunk_size": defaults.CHUNK_SIZE,
    "transform": defaults.TRANSFORM.value,
}
PLAN_DEFAULTS: dict[str, Any] = {
    "alpha": defaults.ALPHA,
    "defensive": defaults.DEFENSIVE,
    "design": defaults.DESIGN.value,
    "weighting": defaults.WEIGHTING.value,
    "stages": defaults.STAGES,
    "stage1_share": defaults.STAGE1_SHARE,
    "screen": defaults.SCREEN,
}
ESTIMATE_DEFAULTS: dict[str, Any] = {
    "confidence": defaults.CONFIDENCE,
    "interval": defaults.INTERVAL.value,
}


def open_leads(r: RunResult, f1: np.ndarray, gamma: float) -> np.ndarray:
    """The run's open leads after discovery: segments run at level 1 whose value there is
    at or below gamma, with no level-0 result (truth-file order, bool). The simulator of a
    benchmark returns the truth, so the level-1 value is ``f1``'s. None where the run's
    last fit put level 1 in other units (``pipeline._handoff.reports_level0_units``), as the
    pipeline's ``cheap_failures`` counts none there."""
    from bams_cli.pipeline._handoff import reports_level0_units

    leads = np.zeros(f1.size, bool)
    hp = r.hyperparameters[-1] if r.hyperparameters else None
    if not reports_level0_units((hp.get("scales") or [1.0])[0] if hp else 1.0):
        return leads
    for idx, lv in r.picks:
        cheap = idx[lv == 1]
        leads[cheap[f1[cheap] <= gamma]] = True
    return leads & ~np.asarray(r.known, bool)


def run_leads(
    r: RunResult, f1: np.ndarray, is_failure: np.ndarray, gamma: float
) -> tuple[np.ndarray, float]:
    """The run's open leads and their share of K (``open_leads``, ``run_lead_share``)."""
    return open_leads(r, f1, gamma), run_lead_share(r, f1, is_failure, gamma)


def run_lead_evidence(
    r: RunResult, f1: np.ndarray, is_failure: np.ndarray, gamma: float
) -> tuple[int, int]:
    """The run's evidence on its leads, as ``pipeline._handoff.lead_evidence`` reads it from
    a workspace: segments run at level 1 at or below gamma that have a level-0 result, and
    how many of them fail there; (0, 0) where the run's last fit put level 1 in other
    units (no leads, ``open_leads``)."""
    from bams_cli.pipeline._handoff import reports_level0_units

    hp = r.hyperparameters[-1] if r.hyperparameters else None
    if not reports_level0_units((hp.get("scales") or [1.0])[0] if hp else 1.0):
        return 0, 0
    cheap = np.zeros(f1.size, bool)
    for idx, lv in r.picks:
        run1 = idx[lv == 1]
        cheap[run1[f1[run1] <= gamma]] = True
    pairs = cheap & np.asarray(r.known, bool)
    return int(pairs.sum()), int((pairs & is_failure).sum())


def run_lead_share(r: RunResult, f1: np.ndarray, is_failure: np.ndarray, gamma: float) -> float:
    """The share of K the run's open leads may take (``core.design.lead_share`` of
    ``run_lead_evidence``)."""
    from bams_cli.core.design import lead_share

    return lead_share(*run_lead_evidence(r, f1, is_failure, gamma))


def _select_kwargs(strategy: str, batch: int) -> dict[str, Any]:
    if batch == 1:  # random; mixed fidelity for the multifidelity strategies
        return {"strategy": "random", "mixed_fidelity": strategy in MULTIFIDELITY}
    return {"strategy": "random" if strategy == "mc" else strategy}


def _ce_scores(X: np.ndarray, obs_idx: np.ndarray, obs_f: np.ndarray) -> np.ndarray:
    """Density (up to a constant) of the final cross-entropy Gaussian at every segment.

    Paper appendix "Setup for the cross-entropy method": after batch 3 the CE sampling
    distribution, a diagonal Gaussian fitted to the elite (the ``n_elite`` lowest level-0
    values, as ``baselines.pick_cross_entropy`` fits it), scores every segment for the rate
    estimate.
    """
    from bams_cli.core.baselines import CE_N_ELITE as n_elite
    from bams_cli.core.baselines import CE_VAR_FLOOR as var_floor

    elite = obs_idx[np.argsort(obs_f, kind="stable")[: max(n_elite, 2)]]
    mean = X[elite].mean(axis=0)
    var = X[elite].var(axis=0) + var_floor * X.var(axis=0)
    logd = -0.5 * (((X - mean) ** 2) / var).sum(axis=1)
    return np.exp(logd - logd.max())


def run_one(spec: RunSpec) -> RunResult:
    """Run the protocol for one (strategy, seed) in a fresh workspace (worker entry point)."""
    from threadpoolctl import threadpool_limits

    from bams_cli.core.baselines import difficulty_weights
    from bams_cli.core.kernels import kernel_threads

    protocol = PROTOCOLS[spec.protocol]
    data = Path(spec.data)
    truth_path = data / "truth.parquet"
    root = Path(tempfile.mkdtemp(prefix=f"{spec.strategy}-{spec.seed}-", dir=spec.scratch))
    gp = spec.strategy in GP_STRATEGIES
    seconds: dict[str, float] = {}

    def clock(key: str, t0: float) -> None:
        seconds[key] = seconds.get(key, 0.0) + time.perf_counter() - t0

    with threadpool_limits(limits=1), kernel_threads(1):
        t0 = time.perf_counter()
        pipeline.init(root, settings_from=data / "settings.toml", seed=spec.seed)
        pipeline.embed_reduce(root, data / "segments.parquet", **protocol.reduce)
        clock("setup", t0)
        picks: list[tuple[np.ndarray, np.ndarray]] = []
        p_after: list[np.ndarray | None] = []
        hps: list[dict[str, Any] | None] = []
        for b in range(1, protocol.n_batches + 1):
            t0 = time.perf_counter()
            pipeline.select(
                root,
                budget=protocol.m1 if b == 1 else protocol.mb,
                clusters=spec.clusters,
                level0_share=spec.level0_share,
                workers=1,
                greedy=spec.greedy,
                **SELECT_DEFAULTS,
                **_select_kwargs(spec.strategy, b),
            )
            clock("select", t0)
            t0 = time.perf_counter()
            handoff = root / "batches" / f"batch-{b:04d}.parquet"
            results = root / f"results-{b:04d}.parquet"
            pipeline.simulate(handoff, truth_path, results)
            pipeline.ingest_results(root, results)
            clock("simulate+ingest", t0)
            picks.append((_column(handoff, "segment_id").astype(str), _column(handoff, "fidelity")))
            if gp:
                t0 = time.perf_counter()
                summary = pipeline.fit(root, **FIT_DEFAULTS)
                clock("fit", t0)
                p_after.append(_column(root / "scores.parquet", "p_0").astype(np.float64))
                hps.append({**summary["hyperparameters"], "transform": summary["transform"]})
            else:
                p_after.append(None)
                hps.append(None)

        # Everything is returned in the truth file's row order.
        truth_ids = _column(truth_path, "segment_id").astype(str)
        pos = {s: i for i, s in enumerate(truth_ids)}
        pool_ids = _column(root / "segments.parquet", "segment_id").astype(str)
        to_truth = np.array([pos[s] for s in pool_ids], np.int64)
        picks_idx = [
            (np.array([pos[s] for s in sid], np.int64), lv.astype(np.int64)) for sid, lv in picks
        ]
        known = np.zeros(len(truth_ids), bool)
        for idx, lv in picks_idx:
            known[idx[lv == 0]] = True
        for i, p in enumerate(p_after):
            if p is not None:
                q = np.empty_like(p)
                q[to_truth] = p
                p_after[i] = q

        scores = None
        if spec.strategy in ("ds", "ce"):
            if spec.strategy == "ds":
                pool_scores = difficulty_weights(
                    _column(root / "segments.parquet", "difficulty").astype(np.float64)
                )
            else:
                from bams_cli.state.workspace import Workspace

                _, X = Workspace(root).read_pool()
                known_pool = known[to_truth]
                f0 = _column(truth_path, "value_0")[to_truth]
                obs = np.flatnonzero(known_pool)
                pool_scores = _ce_scores(X, obs, f0[obs])
            scores = np.empty(len(truth_ids))
            scores[to_truth] = pool_scores

        realised = screen = None
        if gp:
            t0 = time.perf_counter()
            screen = screen_default(root, truth_path, K=spec.K, seed=spec.seed)
            clock("screen", t0)
            # One realised estimate through the real estimate path with the default design
            # (plan -> simulate -> ingest -> compute; a screen first where the default
            # draws one). The tables use the design's exact recall and variance instead
            # (module docstring).
            t0 = time.perf_counter()
            plan = pipeline.estimate_plan(root, samples=spec.K, **PLAN_DEFAULTS)
            while True:
                name = f"screen-{plan['plan']}" if "screen_file" in plan else plan["plan"]
                if plan["handoff"] is not None:  # a screen of cheap runs all in the log has none
                    est_results = root / f"estimate-results-{name}.parquet"
                    pipeline.simulate(Path(plan["handoff"]), truth_path, est_results)
                    pipeline.ingest_results(root, est_results)
                # Each later stage wants, and estimate_compute's GP estimate too, a model
                # fitted on the log that now holds the stage's results: a plain fit, as
                # `loop` and a study's Makefile refit between the stages (the MAP search
                # again; the suite's "recall, as run" is the tool's own path).
                pipeline.fit(root, **FIT_DEFAULTS)
                if "screen_file" not in plan and plan["stage"] >= plan["stages"]:
                    break
                plan = pipeline.estimate_plan(root, **PLAN_DEFAULTS)
            e = pipeline.estimate_compute(root, **ESTIMATE_DEFAULTS)["estimates"][0]
            realised = {
                k: e[k]
                for k in (
                    "p_hat",
                    "se",
                    "ci_low",
                    "ci_high",
                    "n_sampled",
                    "failures_sampled",
                    "distinct_failures_found",
                )
            }
            clock("estimate", t0)
    workspace = str(root) if spec.keep_workspace else None
    if not spec.keep_workspace:
        shutil.rmtree(root, ignore_errors=True)
    return RunResult(
        strategy=spec.strategy,
        seed=spec.seed,
        picks=picks_idx,
        p_after=p_after,
        scores=scores,
        known=known,
        hyperparameters=hps,
        realised=realised,
        seconds=seconds,
        workspace=workspace,
        screen=screen,
    )


#: Screens drawn per run to measure the screened default (each one a refit).
SCREEN_TRIALS = 4


def append_cheap_results(root: Path, ids: np.ndarray, values: np.ndarray, batch: int) -> None:
    """Cheap-level results written straight into a workspace's observation log, as
    ingesting a screen's results would (evaluation only: no batch, no hand-off)."""
    import polars as pl

    from bams_cli.state import schemas
    from bams_cli.state.workspace import Workspace

    ws = Workspace(root)
    full = ws.read_observations(active_only=False)
    n = ids.size
    add = pl.DataFrame(
        {
            "segment_id": ids, "fidelity": np.ones(n, np.int64), "value": values,
            "batch": np.full(n, batch, np.int64), "source_file": ["screen"] * n,
            "source_sha256": ["-"] * n, "ingested_at": ["-"] * n, "active": [True] * n,
            "extra": [None] * n,
        },
        schema=full.schema,
    )  # fmt: skip
    table = pl.concat([full, add]).to_arrow().cast(schemas.OBSERVATIONS.schema)
    pq.write_table(table, ws.observations_path)


def screen_default(root: Path, truth_path: Path, *, K: float, seed: int) -> dict[str, Any] | None:
    """The default estimate's screen, where ``estimate --plan`` draws one, from the truth.

    Asks the fitted workspace what ``--screen`` at its default (``PLAN_DEFAULTS``) would
    do; where it screens, draws the screen ``SCREEN_TRIALS`` times
    (``core.evaluate.screen_trials``), each refit on a copy of the workspace holding S1's
    true cheap-level values, at the discovery model's hyperparameters (as the realised
    estimate refits).

    Returns
    -------
    dict or None
        share, recall (mean over the trials), var_ratio (the design's variance over a
        uniform Poisson design's of K level-0 runs), screened (mean |S1|), leads (the open
        leads taken with certainty), trials; None where the default does not screen.
    """
    from bams_cli.core.evaluate import screen_trials
    from bams_cli.core.screen import lead_budget
    from bams_cli.pipeline import screening
    from bams_cli.pipeline.estimation import open_leads as open_leads_of
    from bams_cli.state.workspace import Workspace

    ws = Workspace(root)
    settings = ws.require_initialised()
    option = PLAN_DEFAULTS["screen"]
    if option in (None, "off") or settings.n_levels == 1:
        return None
    ids = _column(root / "scores.parquet", "segment_id").astype(str)
    obs = ws.read_observations()
    seen = [
        ids_in(ids, obs.filter(obs["fidelity"] == lv)["segment_id"].to_numpy()) for lv in (0, 1)
    ]
    share = option
    if option == "auto":  # the decision estimate --plan makes, at the run's K
        n_unknown = int((~seen[0]).sum())
        share, _ = screening.auto_share(
            ws.read_model(), settings, K=min(K, n_unknown), n_unknown=n_unknown,
            n_observations=obs.height,
        )  # fmt: skip
    if share is None:
        return None
    g = int(np.argmax(settings.gammas))
    p = _column(root / "scores.parquet", f"p_{g}").astype(np.float64)
    truth_ids = _column(truth_path, "segment_id").astype(str)
    pos = {s_: i for i, s_ in enumerate(truth_ids)}
    rows = np.array([pos[s_] for s_ in ids], np.int64)
    fail = _column(truth_path, "value_0").astype(np.float64)[rows] <= settings.gammas[g]
    cheap = _column(truth_path, "value_1").astype(np.float64)[rows]
    next_batch = int(obs["batch"].to_numpy().max(initial=0)) + 1

    def refit(s1: np.ndarray) -> np.ndarray:
        scratch = Path(tempfile.mkdtemp(prefix="screen-", dir=root.parent))
        copy = scratch / "workspace"
        try:
            shutil.copytree(root, copy)
            run = s1[~seen[1][s1]]
            append_cheap_results(copy, ids[run], cheap[run], next_batch)
            pipeline.fit(copy, fixed_hyperparameters=copy / "model.json", **FIT_DEFAULTS)
            return _column(copy / "scores.parquet", f"p_{g}").astype(np.float64)[s1]
        finally:
            shutil.rmtree(scratch, ignore_errors=True)

    model = ws.read_model()
    # The open leads the screen takes with certainty, as ``estimate --plan`` chooses them.
    leads, _ = open_leads_of(
        ws, ids, p, seen[0], settings.gammas[g], ws.pending(),
        K=lead_budget(K, float(share)), scales=model["hyperparameters"].get("scales") or (),
    )  # fmt: skip
    t = screen_trials(
        p, fail, K=K, cost=settings.costs[screening.SCREEN_LEVEL], share=float(share),
        refit=refit, known=seen[0], cheap_known=seen[1], n_trials=SCREEN_TRIALS,
        prior=screening.risk_prior(model, settings),
        confirm_prior=screening.confirm_prior(model, settings), leads=leads, cheap=cheap,
        rng=np.random.default_rng([seed, 2027]),
    )  # fmt: skip
    return {
        "share": float(share),
        "recall": float(t.recall.mean()),
        "var_ratio": float(t.var / t.var_uniform),
        "screened": float(t.screened.mean()),
        "leads": int(leads.sum()),
        "trials": SCREEN_TRIALS,
    }


# ---------------------------------------------------------------------------------------
# exact design quantities
# ---------------------------------------------------------------------------------------
def estimate_defaults() -> dict[str, Any]:
    """alpha, defensive and design as a user's ``estimate --plan`` gets them (``defaults``)."""
    return {k: PLAN_DEFAULTS[k] for k in ("alpha", "defensive", "design")}


def design_stats(
    p: np.ndarray,
    is_failure: np.ndarray,
    *,
    K: float,
    known: np.ndarray | None,
    alpha: float,
    defensive: float,
    design: str,
) -> tuple[float, float]:
    """Expected IS recall and exact relative variance Var(p_hat) / p^2 of one design.

    The inclusion probabilities (poisson, fixed) or draw distribution (with-replacement)
    are built exactly as ``estimate --plan`` builds them (``estimate.plan_sample``); recall
    and variance then follow from them and the true failures without drawing anything.

    Parameters
    ----------
    p : ndarray of shape (n_pool,)
        Scores the design is built from (p_n; importance scores for DS and CE).
    is_failure : bool ndarray of shape (n_pool,)
        True level-0 failures.
    K : float
        Expected sample size (poisson, fixed) or number of draws (with-replacement).
    known : bool ndarray of shape (n_pool,), optional
        The known stratum (counted exactly, never sampled); None samples the whole pool.
    alpha, defensive, design
        As ``estimate.plan_sample``.

    Returns
    -------
    recall : float
        E[fraction of the failures known or sampled] (``evaluate.expected_is_recall``).
    rel_var : float
        Var(p_hat) / p^2, p the pool's true rate (``evaluate.exact_variance``: exact for
        poisson and with-replacement, Hajek's approximation for fixed; +inf if a failure
        can never be sampled).
    """
    import warnings

    from bams_cli.core.estimate import ZeroInclusionWarning

    # Scores that underflow (p_n ~ 1e-300) are expected here, not errors: their failures
    # show up as an unbounded variance below.
    with warnings.catch_warnings(), np.errstate(over="ignore", divide="ignore"):
        warnings.simplefilter("ignore", ZeroInclusionWarning)
        plan = plan_sample(
            np.asarray(p, dtype=np.float64),
            K=K,
            rng=np.random.default_rng(0),  # the draw itself is not used
            known=known,
            alpha=alpha,
            defensive=defensive,
            design=design,  # type: ignore[arg-type]
        )
    recall = float(expected_is_recall(plan, is_failure)[0])
    # Poisson and with-replacement variances are sums over the failures of U only
    # (``evaluate.exact_variance``), so pass just those rows: a non-failure whose q
    # underflows to ~1e-320 would otherwise turn 0 x (1/q = inf) into NaN.
    fail_u = np.asarray(is_failure, bool)[plan.unknown]
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        if design == "fixed":  # Hajek's approximation involves every unit of U
            var = exact_variance(plan, fail_u)[0]
        else:
            prob = plan.q if design == "with-replacement" else plan.pi
            var = exact_variance(
                prob[fail_u], np.ones(int(fail_u.sum()), bool), design=design,  # type: ignore[arg-type]
                n_pool=plan.n_pool, budget=plan.budget,
            )[0]  # fmt: skip
    rv = var / np.mean(is_failure) ** 2
    # A failure with q = 0 (p_n^alpha underflows without a defensive share) can never be
    # sampled, and one with q ~ 1e-300 has an astronomically large variance: unbounded.
    return recall, float(rv) if np.isfinite(rv) else math.inf


#: The three estimator configurations the tables report (see ``_run_designs``).
ESTIMATORS = ("default", "paper", "with_replacement")


def _run_designs(
    r: RunResult, is_failure: np.ndarray, K: float, est: dict[str, Any]
) -> dict[str, tuple[float, float]]:
    """(recall, RV) of one run under the default design, the paper's sampler and WR.

    * default: ``estimate --plan`` defaults (design, alpha, defensive) with the known
      stratum; MC samples uniformly (alpha = 0), DS and CE use their scores with alpha 1.
    * paper: K draws with replacement over the whole pool from p_n^2.5, no defensive
      share; MC by uniform random scores^2.5 (what the paper's MC row matches), DS and CE
      from their scores.
    * with_replacement: the paper's sampler at the default alpha and defensive share,
      to separate what the design does from what alpha and eps do.
    """
    N = is_failure.size
    Kw = float(round(K))
    if r.p_after[-1] is not None:
        p, a_def, a_pap = r.p_after[-1], est["alpha"], PAPER_ALPHA
    elif r.scores is not None:
        p, a_def, a_pap = r.scores, 1.0, 1.0
    else:
        p, a_def, a_pap = np.ones(N), 0.0, 0.0
    out = {
        "default": design_stats(
            p, is_failure, K=K, known=r.known, alpha=a_def, defensive=est["defensive"],
            design=est["design"],
        ),
        "with_replacement": design_stats(
            p, is_failure, K=Kw, known=None, alpha=a_def, defensive=est["defensive"],
            design="with-replacement",
        ),
    }  # fmt: skip
    if r.p_after[-1] is None and r.scores is None:
        p, a_pap = np.random.default_rng([r.seed, 2024]).random(N), PAPER_ALPHA
    out["paper"] = design_stats(
        p, is_failure, K=Kw, known=None, alpha=a_pap, defensive=0.0,
        design="with-replacement",
    )  # fmt: skip
    rng = np.random.default_rng([r.seed, 2025])
    out["paper_trials"] = (out["paper"][0], trial_spread(p, is_failure, int(Kw), a_pap, rng))
    return out


#: Draws of the staged design per run for its recall (``_staged_recall``).
STAGED_TRIALS = 100


def fit_prior(hyperparameters: dict[str, Any] | None) -> tuple[float, float]:
    """The prior on lam ``estimate --plan`` takes for a fit with these hyperparameters
    (``core.design.risk_prior``; None, or a one-level fit: the default prior)."""
    from bams_cli.core.design import risk_prior
    from bams_cli.pipeline.screening import cheap_level_discrepancy

    hp = hyperparameters or {}
    return risk_prior(cheap_level_discrepancy({"hyperparameters": hp}) if hp else None)


def saved_run_trials(
    problem_dir: Path,
    strategy: str,
    seed: int,
    *,
    n_trials: int,
    uniform: bool = False,
    rng: np.random.Generator | None = None,
    reference: bool = False,
) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, tuple[float, float]]:
    """The default staged estimate design drawn ``n_trials`` times from the truth, for one
    run that ``run_benchmark(save_arrays=True)`` saved in ``problem_dir``: its final p_n
    (constant for a run without a model, or with ``uniform``: a uniform estimate after
    that run's discovery), its known stratum, its open leads at the share of K their
    evidence allows, and the prior on lam ``estimate --plan`` takes for its last fit.

    Returns (``core.evaluate.StagedTrials``, is_failure, known, p, prior), the design's
    inputs for callers that measure more of it (docs/suite/estimate_design.py).
    ``reference``: draw through the tool's own functions (``staged_trials``' reference).
    """
    from bams_cli.core.evaluate import staged_trials

    z = np.load(problem_dir / "runs.npz")
    fail = z["f0"] <= float(z["gamma"])
    known = z[f"{strategy}-{seed}-known"]
    modelled = not uniform and f"{strategy}-{seed}-p" in z.files
    p = z[f"{strategy}-{seed}-p"] if modelled else np.ones(fail.size)
    entry = json.loads((problem_dir / "results.json").read_text())[strategy]
    finals = dict(zip(entry["seed_values"], entry.get("hyperparameters_final") or [], strict=False))
    prior = fit_prior(finals.get(seed))
    share = z.get(f"{strategy}-{seed}-lead_share")
    t = staged_trials(
        p, fail, K=float(z["K"]), known=known, n_trials=n_trials, prior=prior,
        rng=np.random.default_rng(seed) if rng is None else rng,
        leads=z.get(f"{strategy}-{seed}-leads") if modelled else None,
        lead_share=defaults.LEAD_SHARE if share is None else float(share), reference=reference,
    )  # fmt: skip
    return t, fail, known, p, prior


def _staged_design(
    r: RunResult,
    is_failure: np.ndarray,
    K: float,
    leads: np.ndarray | None = None,
    lead_share: float = defaults.LEAD_SHARE,
) -> tuple[float, float] | None:
    """Expected recall of the staged estimate design (``estimate --plan`` once per stage,
    ``defaults.STAGES``) and its variance over a uniform Poisson design's of the same size,
    over ``STAGED_TRIALS`` draws from the truth (``staged_trials``).

    GP strategies plan it from their p_n, under the prior on lam ``estimate --plan`` takes
    for their last fit (``core.design.risk_prior``); a strategy without a model (MC) from a
    constant p_n, which makes every stage uniform. DS and CE have scores, not
    probabilities: None.
    """
    from bams_cli.core.evaluate import staged_trials

    if r.p_after[-1] is not None:
        p = r.p_after[-1]
    elif r.scores is None:
        p = np.ones(is_failure.size)
    else:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hp = r.hyperparameters[-1] if r.hyperparameters else None
        t = staged_trials(
            p, is_failure, K=K, known=r.known, n_trials=STAGED_TRIALS, prior=fit_prior(hp),
            rng=np.random.default_rng([r.seed, 2026]),
            leads=leads if r.p_after[-1] is not None else None, lead_share=lead_share,
        )  # fmt: skip
    return float(t.recall.mean()), float(t.var / t.var_uniform)


def trial_spread(
    scores: np.ndarray,
    is_failure: np.ndarray,
    K: int,
    alpha: float,
    rng: np.random.Generator,
    trials: int = PAPER_TRIALS,
) -> float:
    """RV as the paper measured it: the spread of ``trials`` repeated estimates / p^2.

    The paper's sampler (K draws with replacement from q proportional to scores^alpha over
    the pool, p_hat = mean of 1{fail}/(N q)) repeated ``trials`` times (paper section 4.1:
    200). Heavy-tailed weights make this a noisy and usually low estimate of the true
    variance, and failures with q = 0 never show up in it at all.
    """
    from bams_cli.core.estimate import selection_distribution

    N = is_failure.size
    with np.errstate(over="ignore", divide="ignore", under="ignore"):
        q = selection_distribution(np.asarray(scores, np.float64), alpha=alpha, defensive=0.0)
    draws = rng.choice(N, size=(trials, K), p=q / q.sum())
    est = (is_failure[draws] / (N * q[draws])).mean(axis=1)
    return float(est.var(ddof=1) / is_failure.mean() ** 2)


# ---------------------------------------------------------------------------------------
# aggregation over seeds
# ---------------------------------------------------------------------------------------
def _se(x: Sequence[float] | np.ndarray) -> float | None:
    a = np.asarray(x, dtype=np.float64)
    if a.size < 2:
        return None
    if not np.all(np.isfinite(a)):
        return math.inf
    return float(a.std(ddof=1) / math.sqrt(a.size))


def _summary(recalls: Sequence[float], rvs: Sequence[float]) -> dict[str, Any]:
    rv100 = 100.0 * np.asarray(rvs, dtype=np.float64)
    return {
        "recall": float(np.mean(recalls)),
        "recall_se": _se(recalls),
        "rv": float(rv100.mean()),
        "rv_se": _se(rv100),
        "rv_median": float(np.median(rv100)),
        "seeds": len(recalls),
        "per_seed_recall": [float(v) for v in recalls],
        "per_seed_rv": [float(v) for v in rv100],
    }


def _curve(r: RunResult, b: int, is_failure: np.ndarray) -> np.ndarray:
    s = r.p_after[b]
    if s is None and r.scores is not None and b == len(r.p_after) - 1:
        s = r.scores
    if s is None:  # MC, and DS / CE before their final scores: random order (section 4.1)
        s = np.random.default_rng([r.seed, 99, b]).random(is_failure.size)
    return retention_recall(s, is_failure, RETENTION_GRID)


def mc_explanation(
    is_failure: np.ndarray, K: float, seeds: Sequence[int], trials: int = 200
) -> dict[str, Any]:
    """Where the paper's MC row (100 RV = 710) comes from: IS by random scores^alpha.

    Plain MC (uniform draws) has RV = (1 - p)/(p K). The paper's "sampling based on random
    scores" with its importance sampler q proportional to score^alpha gives weights
    1/(N q) proportional to u^-alpha for u ~ U(0, 1), whose variance is heavy-tailed
    (E[u^-alpha] is infinite for alpha >= 1): the exact RV per seed is set by the failure
    that happened to draw the smallest score, and the spread of ``trials`` repeated
    estimates (what the paper reports, 200 trials) is a noisy, usually far smaller, number.

    Returns 100 x RV, mean and median over ``seeds``, for uniform draws (exact),
    random scores^1 and ^2.5 (exact), and random scores^2.5 as the spread of ``trials``
    repeated estimates.
    """
    N = is_failure.size
    p = is_failure.mean()
    Kw = int(round(K))
    rows: dict[str, list[float]] = {"uniform": [], "scores^1": [], "scores^2.5": []}
    spread: list[float] = []
    for seed in seeds:
        u = np.random.default_rng([seed, 2024]).random(N)
        rows["uniform"].append(
            design_stats(np.ones(N), is_failure, K=Kw, known=None, alpha=0.0, defensive=0.0,
                         design="with-replacement")[1]
        )  # fmt: skip
        for a, key in ((1.0, "scores^1"), (PAPER_ALPHA, "scores^2.5")):
            rows[key].append(
                design_stats(u, is_failure, K=Kw, known=None, alpha=a, defensive=0.0,
                             design="with-replacement")[1]
            )  # fmt: skip
        q = u**PAPER_ALPHA / np.sum(u**PAPER_ALPHA)
        draws = np.random.default_rng([seed, 2025]).choice(N, size=(trials, Kw), p=q)
        est = (is_failure[draws] / (N * q[draws])).mean(axis=1)
        spread.append(float(est.var(ddof=1) / p**2))
    out: dict[str, Any] = {
        key: {"mean": float(100 * np.mean(v)), "median": float(100 * np.median(v))}
        for key, v in rows.items()
    }
    out[f"scores^2.5 spread of {trials} trials"] = {
        "mean": float(100 * np.mean(spread)),
        "median": float(100 * np.median(spread)),
        "se": _se(100 * np.asarray(spread)),
    }
    out["formula_uniform"] = float(100 * (1 - p) / (p * Kw))
    return out


def true_discrepancy_sd(
    f0: np.ndarray, f1: np.ndarray, transform: dict[str, Any] | None = None, scale: float = 1.0
) -> float:
    """sd(g(f1) - rho g(f0)) over the pool, g the model's output transform (identity if
    None) and rho the model's scale of the cheap level (``Hyperparameters.scales``).

    The discrepancy a model of g(y) should find; with the identity and rho = 1, sd(f1 - f0).
    """
    from bams_cli.core.gp import OutputTransform

    g = OutputTransform.from_dict(transform)
    return float(np.std(g.forward(f1) - scale * g.forward(f0)))


def level_scale(hyperparameters: dict[str, Any]) -> float:
    """The model's scale rho_1 of the cheap level (1 in a model written before scales)."""
    return float((hyperparameters.get("scales") or [1.0])[0])


def discrepancy_sd(hyperparameters: dict[str, Any]) -> float:
    """The model's sd of y1 - rho y0 at one segment (``checks.fitted_discrepancy_sd``), in
    the model's units. Set beside the true sd(f1 - rho f0) over the pool, it shows whether
    the fit trusts the cheap level more than it deserves."""
    from bams_cli.core.gp import Hyperparameters
    from bams_cli.core.gp.checks import fitted_discrepancy_sd

    return fitted_discrepancy_sd(Hyperparameters.from_dict(hyperparameters))


def evaluate_runs(
    protocol: Protocol,
    runs: Sequence[RunResult],
    f0: np.ndarray,
    gamma: float,
    *,
    K: float,
    estimator: dict[str, Any],
    f1: np.ndarray | None = None,
) -> dict[str, Any]:
    """Per strategy: the IS tables, Table 1 and retention-recall curves over seeds.

    ``f1`` (the cheap level's truth) adds each run's fitted discrepancy sd over the true
    one, both in the model's units (``true_discrepancy_sd``).
    """
    is_failure = f0 <= gamma
    out: dict[str, Any] = {}
    for strategy in protocol.strategies:
        mine = sorted((r for r in runs if r.strategy == strategy), key=lambda r: r.seed)
        if not mine:
            continue
        stats = [_run_designs(r, is_failure, K, estimator) for r in mine]
        entry = _summary([s["default"][0] for s in stats], [s["default"][1] for s in stats])
        # The open leads a GP strategy's estimate samples with certainty (``open_leads``).
        maybe = [
            _staged_design(r, is_failure, K)
            if f1 is None
            else _staged_design(r, is_failure, K, *run_leads(r, f1, is_failure, gamma))
            for r in mine
        ]
        staged = [v for v in maybe if v is not None]
        if len(staged) == len(maybe):
            entry["recall_staged"] = float(np.mean([v[0] for v in staged]))
            entry["recall_staged_se"] = _se([v[0] for v in staged])
            entry["per_seed_recall_staged"] = [v[0] for v in staged]
            # The default estimate: the screen where ``--screen auto`` draws one, else the
            # staged design.
            default = [
                (r.screen["recall"], r.screen["var_ratio"]) if r.screen else v
                for r, v in zip(mine, staged, strict=True)
            ]
            entry["recall_default"] = float(np.mean([v[0] for v in default]))
            entry["recall_default_se"] = _se([v[0] for v in default])
            entry["per_seed_recall_default"] = [v[0] for v in default]
            entry["per_seed_var_default"] = [v[1] for v in default]
            entry["screened_seeds"] = int(sum(r.screen is not None for r in mine))
            entry["screens"] = [r.screen for r in mine]
        entry["seed_values"] = [r.seed for r in mine]
        for name in ("paper", "with_replacement"):
            entry[name] = _summary([s[name][0] for s in stats], [s[name][1] for s in stats])
        trials = 100.0 * np.array([s["paper_trials"][1] for s in stats])
        entry["paper"]["rv_trials"] = float(trials.mean())
        entry["paper"]["rv_trials_se"] = _se(trials)
        entry["paper"]["rv_trials_median"] = float(np.median(trials))
        entry["paper"]["seeds_unbounded"] = int(np.sum(~np.isfinite(entry["paper"]["per_seed_rv"])))
        entry["failures_known"] = [int(is_failure[r.known].sum()) for r in mine]
        entry["table1"] = []
        for b in range(protocol.n_batches):
            per_seed = [float(f0[r.picks[b][0]].mean()) for r in mine]
            entry["table1"].append({"mean_f": float(np.mean(per_seed)), "se": _se(per_seed)})
        entry["picks_per_level"] = [
            [[int((lv == k).sum()) for k in range(2)] for _, lv in r.picks] for r in mine
        ]
        entry["retention_recall"] = {}
        for b in range(protocol.n_batches):
            c = np.array([_curve(r, b, is_failure) for r in mine])
            entry["retention_recall"][str(b + 1)] = {
                "mean": c.mean(axis=0).tolist(),
                "se": (c.std(axis=0, ddof=1) / math.sqrt(len(c))).tolist() if len(c) > 1 else None,
            }
        if strategy == "mc":
            entry["explanation"] = mc_explanation(is_failure, K, [r.seed for r in mine])
        entry["level0_per_batch"] = [
            float(np.mean([int((r.picks[b][1] == 0).sum()) for r in mine]))
            for b in range(protocol.n_batches)
        ]
        entry["discrepancy_sd_fitted"] = [
            discrepancy_sd(r.hyperparameters[-1]) for r in mine if r.hyperparameters[-1]
        ]
        if f1 is not None:
            entry["discrepancy_sd_ratio"] = [
                discrepancy_sd(r.hyperparameters[-1])
                / true_discrepancy_sd(
                    f0,
                    f1,
                    r.hyperparameters[-1].get("transform"),
                    level_scale(r.hyperparameters[-1]),
                )
                for r in mine
                if r.hyperparameters[-1]
            ]
        entry["gp_rate_ratio"] = [
            float(np.mean(r.p_after[-1]) / is_failure.mean())
            for r in mine
            if r.p_after[-1] is not None
        ]
        entry["hyperparameters_final"] = [r.hyperparameters[-1] for r in mine]
        entry["realised_estimates"] = [r.realised for r in mine]
        entry["seconds_per_run"] = {
            k: round(float(np.mean([r.seconds.get(k, 0.0) for r in mine])), 2)
            for k in sorted({k for r in mine for k in r.seconds})
        }
        out[strategy] = entry
    return out


# ---------------------------------------------------------------------------------------
# the harness
# ---------------------------------------------------------------------------------------
def versions() -> dict[str, str]:
    """Python, platform and the versions of the packages the numbers depend on."""
    out = {"python": platform.python_version(), "platform": platform.platform()}
    for pkg in (
        "bams-cli",
        "numpy",
        "scipy",
        "scikit-learn",
        "numba",
        "polars",
        "pyarrow",
        "matplotlib",
    ):
        try:
            out[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def run_benchmark(
    protocol: str,
    *,
    seeds: int,
    quick: bool,
    out_dir: Path,
    strategies: list[str] | None,
    level0_share: float,
    workers: int,
    progress: Progress | None,
    n: int | None = None,
    clusters: int = defaults.CLUSTERS,
    first_seed: int = 0,
    command: str | None = None,
    save_arrays: bool = False,
    greedy: str = defaults.GREEDY.value,
) -> dict[str, Any]:
    """Run a paper protocol over seeds and write its tables, plots and results.json.

    Parameters
    ----------
    protocol : {"toy2d", "av_like", "weak_cheap", "digits", "rare_regions", "gap_sim"}
        The synthetic protocol (paper appendix "Synthetic Experiments"), the AV one
        (paper section 4) on the AV-like sample data, or a suite problem (``core.suite``;
        ``run_suite`` runs them all).
    seeds : int
        Independent repetitions (study seeds ``first_seed`` ..); ``quick`` caps it at 3.
    quick : bool
        CI mode: at most 3 seeds.
    out_dir : Path
        Where results.json, tables.md and the plots go (created if missing).
    strategies : list of str, optional
        Subset of the protocol's strategies (default: all, in table order).
    level0_share : float
        Share of the budget spent at level 0 by the mixed-fidelity random first batch
        (BAMS, MCM-GP) and by every MCM-GP batch; the rest buys level-1 runs.
    workers : int
        Runs in parallel worker processes (1: in this process).
    progress : callable (phase, done, total), optional
        Called as runs finish: one phase per strategy and "all runs".
    n : int, optional
        Pool size; default the committed sample data (toy2d 20,000, av_like 2,000) or the
        suite problem's own (``core.suite.DEFAULT_N``).
    clusters : int
        BAMS / BAS clusters S (paper: 6).
    first_seed : int
    command : str, optional
        The command line to record (default: this process's argv).
    save_arrays : bool
        Also write ``runs.npz``: the true level-0 values and gamma, and per run
        (``<strategy>-<seed>-p``, ``-known``, ``-leads``, ``-lead_share``) the final p_n (or
        importance scores), the known stratum, the open leads (``open_leads``) and their
        share of K (``run_lead_share``), in truth-file
        order. Estimate designs can then be studied on the runs without repeating them
        (``core.design``, ``docs/suite/estimate_design.py``).
    greedy : {"auto", "exact", "approximate"}
        BAMS / BAS: the plan ``select --greedy`` runs; forcing each in turn compares the
        approximate plan with the exact greedy on the same protocol and seeds.

    Returns
    -------
    dict
        The content of results.json.
    """
    if protocol not in PROTOCOLS:
        raise OptionValueError(
            f"--protocol {protocol!r}: choose one of {', '.join(PROTOCOLS)}, or suite"
        )
    proto = PROTOCOLS[protocol]
    chosen = list(proto.strategies) if not strategies else list(strategies)
    unknown = [s for s in chosen if s not in proto.strategies]
    if unknown:
        raise OptionValueError(
            f"--strategies {','.join(unknown)}: not part of the {protocol} protocol "
            f"({', '.join(proto.strategies)})"
        )
    if not 0.0 < level0_share < 1.0:
        raise OptionValueError(f"--level0-share {level0_share}: must lie in (0, 1)")
    if quick:
        seeds = min(seeds, QUICK_SEEDS)
    if seeds < 1:
        raise OptionValueError(f"--seeds {seeds}: need at least 1")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OptionError(f"--out {out_dir}: is a file; give a folder for the results")
    out_dir.mkdir(parents=True, exist_ok=True)
    estimator = estimate_defaults()
    t_start = time.perf_counter()

    with tempfile.TemporaryDirectory(prefix=f"bams-benchmark-{protocol}-") as tmp:
        scratch = Path(tmp)
        data = prepare_data(proto, n, scratch)
        f0 = _column(data / "truth.parquet", "value_0").astype(np.float64)
        f1 = _column(data / "truth.parquet", "value_1").astype(np.float64)
        gamma = Settings.from_toml((data / "settings.toml").read_text()).gammas[0]
        F = int((f0 <= gamma).sum())
        N = f0.size
        K = float(round(proto.k_factor * F))
        # Slow strategies first, so the pool's last workers are not left with a long run.
        order = sorted(chosen, key=lambda s: (s not in ("bams", "bas"), chosen.index(s)))
        specs = [
            RunSpec(
                protocol,
                s,
                first_seed + i,
                str(data),
                str(scratch),
                level0_share,
                clusters,
                K,
                greedy=greedy,
            )
            for s in order
            for i in range(seeds)
        ]
        done_per = dict.fromkeys(chosen, 0)
        runs: list[RunResult] = []

        def finished(r: RunResult) -> None:
            runs.append(r)
            done_per[r.strategy] += 1
            if progress:
                progress(f"{protocol} {r.strategy}", done_per[r.strategy], seeds)
                progress(f"{protocol} all runs", len(runs), len(specs))

        if progress:
            for s in chosen:
                progress(f"{protocol} {s}", 0, seeds)
            progress(f"{protocol} all runs", 0, len(specs))
        if workers <= 1:
            for spec in specs:
                finished(run_one(spec))
        else:
            import multiprocessing as mp

            with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
                pending: set[Future] = {pool.submit(run_one, spec) for spec in specs}
                while pending:
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in done:
                        finished(fut.result())
        table = evaluate_runs(proto, runs, f0, gamma, K=K, estimator=estimator, f1=f1)
        if save_arrays:
            arrays: dict[str, np.ndarray] = {"f0": f0, "gamma": np.array(gamma), "K": np.array(K)}
            for r in runs:
                score = r.p_after[-1] if r.p_after[-1] is not None else r.scores
                if score is not None:
                    arrays[f"{r.strategy}-{r.seed}-p"] = np.asarray(score, np.float64)
                arrays[f"{r.strategy}-{r.seed}-known"] = np.asarray(r.known, bool)
                arrays[f"{r.strategy}-{r.seed}-leads"] = open_leads(r, f1, gamma)
                arrays[f"{r.strategy}-{r.seed}-lead_share"] = np.array(
                    run_lead_share(r, f1, f0 <= gamma, gamma)
                )
            np.savez_compressed(out_dir / "runs.npz", **arrays)  # type: ignore[arg-type]
    wall = time.perf_counter() - t_start

    p = F / N
    result: dict[str, Any] = {
        **table,
        "protocol": protocol,
        "units": {
            "recall": "expected fraction of all true failures known or sampled (exact)",
            "rv": "100 x Var(p_hat) / p^2, the design's exact variance",
            "mean_f": "mean true level-0 metric of a batch's picks, mean over seeds",
        },
        "setup": {
            "data": (
                f"sample_data/{protocol}"
                if data == SAMPLE_DATA / protocol
                else f"generated ({protocol}, data seed 0)"
            ),
            "pool_size": N,
            "gamma": gamma,
            "failures": F,
            "rate": p,
            "K": K,
            "K_rule": f"K = {proto.k_factor:g} p N with p the true rate",
            "m1": proto.m1,
            "mb": proto.mb,
            "batches": proto.n_batches,
            "level0_share": level0_share,
            "clusters": clusters,
            "greedy": greedy,
            "seeds": seeds,
            "first_seed": first_seed,
            "quick": quick,
            "estimator_default": estimator,
            "estimator_paper": {
                "design": "with-replacement",
                "alpha": PAPER_ALPHA,
                "defensive": 0.0,
                "known_stratum": False,
            },
            "mc_rv_uniform_formula": (1 - p) / (p * K),
            "true_discrepancy_sd": float(np.std(f1 - f0)),
            "corr_levels": float(np.corrcoef(f0, f1)[0, 1]),
            "failures_unseen_by_level1": float(np.mean(f1[f0 <= gamma] > gamma)) if F else 0.0,
            "strategies": chosen,
        },
        "paper": {
            s: dict(zip(("recall", "recall_se", "rv", "rv_se"), v, strict=True))
            for s, v in proto.paper.items()
        },
        "paper_table1": {s: v for s, v in proto.paper_table1.items()},
        "command": command or " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "versions": versions(),
        "wall_seconds": round(wall, 1),
        "workers": workers,
        "cpu_count": os.cpu_count(),
    }
    (out_dir / "results.json").write_text(_strict_json(result))
    (out_dir / "tables.md").write_text(render_tables(result))
    plot_retention_recall(result, out_dir / "retention-recall.png")
    return result


def run_suite(
    *,
    seeds: int,
    quick: bool,
    out_dir: Path,
    strategies: list[str] | None,
    level0_share: float,
    workers: int,
    progress: Progress | None,
    n: int | None = None,
    clusters: int = defaults.CLUSTERS,
    first_seed: int = 0,
    problems: Sequence[str] = SUITE,
    command: str | None = None,
    save_arrays: bool = False,
    greedy: str = defaults.GREEDY.value,
) -> dict[str, Any]:
    """Run every suite problem (``run_benchmark`` each) and write ``suite.md`` over them.

    Parameters
    ----------
    problems : sequence of str
        Problems, in table order (default ``SUITE``); each goes to ``out_dir/<problem>/``.
    strategies : list of str, optional
        Run on every problem (default ``SUITE_STRATEGIES``); each must belong to every
        problem's protocol.
    n : int, optional
        Pool size of every problem (capped at digits' 1,797 images); default each
        problem's own.
    seeds, quick, out_dir, level0_share, workers, progress, clusters, first_seed, command,
    save_arrays, greedy
        As ``run_benchmark``.

    Returns
    -------
    dict
        problem -> its results.json content; also written, condensed, to suite.json.
    """
    chosen = list(strategies) if strategies else list(SUITE_STRATEGIES)
    for problem in problems:
        if problem not in PROTOCOLS:
            raise OptionValueError(f"suite problem {problem!r}: choose from {', '.join(PROTOCOLS)}")
        unknown = [st for st in chosen if st not in PROTOCOLS[problem].strategies]
        if unknown:
            raise OptionValueError(
                f"--strategies {','.join(unknown)}: not part of the {problem} protocol "
                f"({', '.join(PROTOCOLS[problem].strategies)}), which the suite runs"
            )
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OptionError(f"--out {out_dir}: is a file; give a folder for the results")
    results: dict[str, Any] = {}
    for problem in problems:
        size = n if n is None or problem != "digits" else min(n, suite.DIGITS_N)
        results[problem] = run_benchmark(
            problem,
            seeds=seeds,
            quick=quick,
            out_dir=out_dir / problem,
            strategies=chosen,
            level0_share=level0_share,
            workers=workers,
            progress=progress,
            n=size,
            clusters=clusters,
            first_seed=first_seed,
            command=command,
            save_arrays=save_arrays,
            greedy=greedy,
        )
    condensed = {p: suite_rows(r) for p, r in results.items()}
    (out_dir / "suite.json").write_text(_strict_json(condensed))
    (out_dir / "suite.md").write_text(render_suite(results))
    return results


def _defined(values: Sequence[float | None] | None) -> list[float]:
    """The finite values of a per-seed list (None or NaN where a seed's is undefined)."""
    return [float(v) for v in values or () if v is not None and math.isfinite(v)]


def suite_rows(result: dict[str, Any]) -> dict[str, Any]:
    """The suite table's numbers for one problem: its setup and one row per strategy."""
    st = result["setup"]
    rows: dict[str, Any] = {}
    for s in strategy_rows(result):
        e = result[s]
        # Per-seed lists as results.json holds them: an undefined value is null there.
        fitted, ratio = _defined(e.get("discrepancy_sd_fitted")), _defined(e.get("gp_rate_ratio"))
        disc, vd = _defined(e.get("discrepancy_sd_ratio")), _defined(e.get("per_seed_var_default"))
        # The failures in hand after each run's one realised estimate (the refit between
        # its stages included), over all of the pool's.
        found = [
            r["distinct_failures_found"] / st["failures"]
            for r in e.get("realised_estimates") or []
            if r and st.get("failures")
        ]
        rows[s] = {
            "recall": e["recall"],
            "recall_se": e["recall_se"],
            "recall_staged": e.get("recall_staged"),
            "recall_staged_se": e.get("recall_staged_se"),
            "recall_default": e.get("recall_default"),
            "recall_default_se": e.get("recall_default_se"),
            "recall_realised": float(np.mean(found)) if found else None,
            "recall_realised_se": (
                float(np.std(found, ddof=1) / math.sqrt(len(found))) if len(found) > 1 else None
            ),
            "var_default": float(np.mean(vd)) if vd else None,
            "var_default_max": float(np.max(vd)) if vd else None,
            "screened_seeds": e.get("screened_seeds"),
            "rv": e["rv"],
            "rv_se": e["rv_se"],
            "discrepancy_sd_fitted": float(np.mean(fitted)) if fitted else None,
            "discrepancy_sd_fitted_range": [min(fitted), max(fitted)] if fitted else None,
            "discrepancy_sd_ratio": float(np.mean(disc)) if disc else None,
            "discrepancy_sd_ratio_range": [min(disc), max(disc)] if disc else None,
            "discrepancy_within_2x": int(sum(0.5 <= v <= 2.0 for v in disc)) if disc else None,
            "level0_per_batch": e.get("level0_per_batch"),
            "gp_rate_ratio": float(np.mean(ratio)) if ratio else None,
            "gp_rate_ratio_range": [min(ratio), max(ratio)] if ratio else None,
        }
    keys: tuple[str, ...] = ("pool_size", "failures", "rate", "K", "seeds")
    keys += (
        "true_discrepancy_sd",
        "corr_levels",
        "failures_unseen_by_level1",
        "m1",
        "mb",
        "batches",
    )
    return {"setup": {k: st.get(k) for k in keys}, "strategies": rows}


def render_suite(results: dict[str, dict[str, Any]]) -> str:
    """Markdown table over the suite: one row per (problem, strategy)."""

    def rng_(v: list[float] | None, digits: int) -> str:
        return f" [{v[0]:.{digits}f}, {v[1]:.{digits}f}]" if v and v[0] != v[1] else ""

    lines = [
        "# Suite: problems unlike the ones the defaults were tuned on",
        "",
        "Per problem: batch 1 random (mixed fidelity for BAMS and MCM-GP), then the "
        "strategy's batches, then `estimate --plan` with K = k p N (p the true rate). "
        "recall, default: the expected share of the true failures in hand after the tool's "
        "default estimate, mean ± SE over seeds: where `estimate --plan --screen auto` "
        f"screens (screened: seeds), the screened design ({SCREEN_TRIALS} screens per run, "
        "each refitted on its cheap results; docs/suite/screen_design.md), elsewhere the "
        f"staged design (`estimate --plan` once per stage; {STAGED_TRIALS} draws per run "
        "from the truth, each later stage keeping stage 1's p_n; "
        "docs/suite/estimate_design.md). recall, as run: the failures in hand after each "
        "run's one realised estimate through the tool's path (`estimate --plan`, the "
        "results ingested, a plain `fit` before each later stage, so each stage is planned "
        "from a model refitted on the ones before), mean ± SE over seeds, and over plain "
        "MC's recall at the same cost. var / uniform, default: the same design's "
        "exact variance over a uniform Poisson design's of K level-0 runs, mean [max] over "
        "seeds. Recall and RV, p^alpha: the single-stage p^alpha design's "
        "(`--weighting p-alpha`, the paper's form), exact (see each problem's tables.md). "
        "disc. sd: the fitted model's sd of y1 - rho y0 at a segment, "
        "rho sqrt(outputscale_1 + noise_1 + noise_0) from the final hyperparameters (rho "
        "the level's scale, 1 unless its pairs show one), mean [range] over seeds, beside "
        "the true sd(f1 - f0) over the pool, both in the metric's units. fitted / true: "
        "the fitted sd over the true sd(f1 - rho f0), per seed in the model's units "
        "(after its output transform, if fit chose one), mean [range] and the seeds within "
        "a factor 2. level-0 picks: per batch, mean over seeds. GP / p: the GP's own "
        "estimate mean(p_n) after the last batch over the true rate, mean [range].",
        "",
        "| problem | N | p | corr(f0, f1) | failures unseen at level 1 | strategy | seeds "
        "| recall, default | recall, as run (x MC) | var / uniform, default | screened "
        "| recall, p^alpha | 100 RV, p^alpha | disc. sd fitted | true sd(f1 - f0) "
        "| fitted / true (within 2x) | level-0 picks per batch | GP / p |",
        "|" + " --- |" * 18,
    ]
    for problem, result in results.items():
        table = suite_rows(result)
        st = table["setup"]
        mc = (table["strategies"].get("mc") or {}).get("recall_default")
        for i, (s, row) in enumerate(table["strategies"].items()):
            head = (
                f"| {problem} | {st['pool_size']:,} | {st['rate']:.4f} | "
                f"{st['corr_levels']:.2f} | {st['failures_unseen_by_level1']:.0%} |"
                if i == 0
                else "| | | | | |"
            )
            fitted = (
                f"{row['discrepancy_sd_fitted']:.3g}{rng_(row['discrepancy_sd_fitted_range'], 2)}"
                if row["discrepancy_sd_fitted"] is not None
                else "-"
            )
            ratio = (
                f"{row['gp_rate_ratio']:.2f}{rng_(row['gp_rate_ratio_range'], 2)}"
                if row["gp_rate_ratio"] is not None
                else "-"
            )
            disc = (
                f"{row['discrepancy_sd_ratio']:.2f}{rng_(row['discrepancy_sd_ratio_range'], 2)} "
                f"({row['discrepancy_within_2x']}/{st['seeds']})"
                if row.get("discrepancy_sd_ratio") is not None
                else "-"
            )
            level0 = " / ".join(f"{v:g}" for v in row["level0_per_batch"] or [])
            var = (
                f"{row['var_default']:.2f} [{row['var_default_max']:.2f}]"
                if row.get("var_default") is not None
                else "-"
            )
            screened = "-" if row.get("screened_seeds") is None else f"{row['screened_seeds']}"
            as_run = _pm(row.get("recall_realised"), row.get("recall_realised_se"))
            if row.get("recall_realised") is not None and mc:
                as_run += f" ({row['recall_realised'] / mc:.1f}x)"
            lines.append(
                f"{head} {NAMES[s]} | {st['seeds']} | "
                f"{_pm(row.get('recall_default'), row.get('recall_default_se'))} | "
                f"{as_run} | {var} | {screened} | "
                f"{_pm(row['recall'], row['recall_se'])} | "
                f"{_pm(row['rv'], row['rv_se'], 2)} | {fitted} | "
                f"{st['true_discrepancy_sd']:.3g} | {disc} | {level0} | {ratio} |"
            )
    first = next(iter(results.values()), None)
    if first is not None:
        lines += [
            "",
            f"Command: `{first['command']}`. Versions: "
            + ", ".join(f"{k} {v}" for k, v in first["versions"].items())
            + ".",
        ]
    return "\n".join(lines) + "\n"


def _json(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def _strict_json(doc: Any) -> str:
    """``doc`` as strict JSON: an undefined number (NaN, inf) is null, never a bare NaN,
    which is not JSON (a table of seeds with an undefined ratio wrote one)."""

    def clean(o: Any) -> Any:
        if isinstance(o, dict):
            return {k: clean(v) for k, v in o.items()}
        if isinstance(o, list | tuple):
            return [clean(v) for v in o]
        if isinstance(o, np.ndarray):
            return clean(o.tolist())
        if isinstance(o, np.generic):
            o = o.item()
        if isinstance(o, float) and not math.isfinite(o):
            return None
        return o

    return json.dumps(clean(doc), indent=1, default=_json, allow_nan=False) + "\n"


# ---------------------------------------------------------------------------------------
# output
# ---------------------------------------------------------------------------------------
NAMES = {
    "bams": "BAMS",
    "bas": "BAS",
    "mc": "MC",
    "mc-gp": "MC-GP",
    "mcm-gp": "MCM-GP",
    "ds": "DS",
    "ds-gp": "DS-GP",
    "ce": "CE",
}


def _pm(v: float | None, se: float | None, digits: int = 3) -> str:
    if v is None or not math.isfinite(v):
        return "inf" if v is not None and v > 0 else "-"
    s = f"{v:.{digits}f}" if abs(v) < 1000 else f"{v:.4g}"
    if se is None:
        return s
    if not math.isfinite(se):
        return f"{s} ± inf"
    return f"{s} ± {se:.{digits}f}" if abs(se) < 1000 else f"{s} ± {se:.3g}"


def strategy_rows(result: dict[str, Any]) -> list[str]:
    return [s for s in result["setup"]["strategies"] if s in result]


def render_tables(result: dict[str, Any]) -> str:
    """Markdown tables of a results.json: IS tables, Table 1, setup."""
    st = result["setup"]
    lines = [
        f"# {result['protocol']}: {st['seeds']} seeds, N = {st['pool_size']:,}, "
        f"{st['failures']} failures (p = {st['rate']:.5f}), K = {st['K']:g}",
        "",
        f"Batches: m1 = {st['m1']:g} random (level-0 share {st['level0_share']:g} for the "
        f"multifidelity strategies), then {st['batches'] - 1} x {st['mb']:g} by the strategy; "
        f"{st['clusters']} clusters. p^alpha estimator: {st['estimator_default']}.",
        "",
    ]
    titles = {
        "default": "Single-stage p^alpha design (Poisson over U, known stratum, "
        f"alpha {st['estimator_default']['alpha']:g}, "
        f"defensive {st['estimator_default']['defensive']:g}: `estimate --plan --stages 1 "
        "--weighting p-alpha`; the staged default's variance and coverage are in "
        "docs/suite/estimate_design.md)",
        "paper": f"Paper's sampler (K draws with replacement over the pool from "
        f"p_n^{PAPER_ALPHA:g}, no defensive share; MC: random scores^{PAPER_ALPHA:g})",
        "with_replacement": "With replacement at the default alpha and defensive share",
    }
    has_paper = bool(result["paper"])  # the suite's own problems have no paper numbers
    for name in ESTIMATORS:
        paper_cols = name == "paper"
        head = "| strategy | recall ± SE | 100 RV mean ± SE | 100 RV median |"
        if paper_cols:
            head += (
                f" seeds with RV = inf | 100 RV from {PAPER_TRIALS} trials, mean ± SE | (median) |"
            )
        if has_paper:
            head += " paper recall | paper 100 RV |"
        lines += [f"## {titles[name]}", "", head, "|" + " --- |" * (head.count("|") - 1)]
        for s in strategy_rows(result):
            e = result[s] if name == "default" else result[s][name]
            pap = result["paper"].get(s)
            row = (
                f"| {NAMES[s]} | {_pm(e['recall'], e['recall_se'])} | "
                f"{_pm(e['rv'], e['rv_se'], 2)} | {_pm(e['rv_median'], None, 2)} |"
            )
            if paper_cols:
                row += (
                    f" {e['seeds_unbounded']}/{e['seeds']} | "
                    f"{_pm(e['rv_trials'], e['rv_trials_se'], 2)} | "
                    f"{_pm(e['rv_trials_median'], None, 2)} |"
                )
            if has_paper:
                row += (
                    f" {_pm(pap['recall'], pap['recall_se'])} | {_pm(pap['rv'], pap['rv_se'], 2)} |"
                    if pap
                    else " - | - |"
                )
            lines.append(row)
        lines.append("")
    lines += [
        "## Mean true f of each batch's picks (the paper's Table 1), ± SE over seeds",
        "",
        "| strategy | " + " | ".join(f"batch {b + 1}" for b in range(st["batches"])) + " |",
        "| --- |" + " --- |" * st["batches"],
    ]
    for s in strategy_rows(result):
        cells = [_pm(t["mean_f"], t["se"], 2) for t in result[s]["table1"]]
        lines.append(f"| {NAMES[s]} | " + " | ".join(cells) + " |")
    if result.get("paper_table1"):
        lines += ["", "Paper (AV, Table 1):", ""]
        lines += [
            "| strategy | " + " | ".join(f"batch {b + 1}" for b in range(st["batches"])) + " |",
            "| --- |" + " --- |" * st["batches"],
        ]
        for s, rows in result["paper_table1"].items():
            lines.append(
                f"| {NAMES[s]} | " + " | ".join(f"{m:.2f} ± {e:.2f}" for m, e in rows) + " |"
            )
    realised = {
        s: [e for e in result[s].get("realised_estimates", []) if e] for s in strategy_rows(result)
    }
    if any(realised.values()):
        lines += [
            "",
            "One realised estimate per run through the real path (`estimate --plan`, "
            "`simulate`, `ingest-results`, `fit`, `estimate`; default design): how often its "
            "interval covers the true rate, and the mean estimate.",
            "",
            "| strategy | interval covers p | mean p_hat ± SE | distinct failures found (mean) |",
            "| --- | --- | --- | --- |",
        ]
        for s, rows in realised.items():
            if not rows:
                continue
            cover = sum(r["ci_low"] <= st["rate"] <= r["ci_high"] for r in rows)
            conf = 0.9  # estimate_compute's default
            ph = [r["p_hat"] for r in rows]
            lines.append(
                f"| {NAMES[s]} | {cover}/{len(rows)} ({conf:.0%} intervals) | "
                f"{_pm(float(np.mean(ph)), _se(ph), 5)} | "
                f"{np.mean([r['distinct_failures_found'] for r in rows]):.1f} of {st['failures']} |"
            )
    lines += [
        "",
        f"Plain MC, uniform sampling of K = {st['K']:g}: RV = (1 - p)/(p K) = "
        f"{st['mc_rv_uniform_formula']:.3f} (100 RV = {100 * st['mc_rv_uniform_formula']:.1f}).",
        "",
    ]
    if "mc" in result and "explanation" in result["mc"]:
        lines += [
            "MC as importance sampling by uniform random scores u^alpha (K draws with "
            "replacement over the pool), 100 RV over seeds:",
            "",
            "| sampler | mean | median |",
            "| --- | --- | --- |",
        ]
        for key, v in result["mc"]["explanation"].items():
            if isinstance(v, dict):
                lines.append(f"| {key} | {_pm(v['mean'], v.get('se'), 1)} | {v['median']:.4g} |")
        lines.append("")
    lines += [
        f"Command: `{result['command']}`; wall time {result['wall_seconds']:.0f} s with "
        f"{result['workers']} worker(s) on {result['cpu_count']} CPUs.",
        "",
        "Versions: " + ", ".join(f"{k} {v}" for k, v in result["versions"].items()) + ".",
        "",
    ]
    return "\n".join(lines)


def plot_retention_recall(result: dict[str, Any], path: Path) -> None:
    """Retention-recall after each batch, mean over seeds with a ±1 SE band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    st = result["setup"]
    nb = st["batches"]
    fig, axes = plt.subplots(1, nb, figsize=(4.2 * nb, 3.6), sharey=True)
    for b, ax in enumerate(np.atleast_1d(axes)):
        for s in strategy_rows(result):
            c = result[s]["retention_recall"][str(b + 1)]
            m = np.asarray(c["mean"])
            (line,) = ax.plot(RETENTION_GRID, m, label=NAMES[s], lw=1.6)
            if c["se"] is not None:
                se = np.asarray(c["se"])
                ax.fill_between(RETENTION_GRID, m - se, m + se, color=line.get_color(), alpha=0.15)
        ax.set_title(f"batch {b + 1}")
        ax.set_xlabel("retention / (p N)")
        ax.set_xlim(0, RETENTION_GRID[-1])
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[0].set_ylabel("recall")
    np.atleast_1d(axes)[-1].legend(loc="lower right", fontsize=8)
    fig.suptitle(
        f"{result['protocol']}: retention-recall, mean ± SE over {st['seeds']} seeds "
        f"(N = {st['pool_size']:,})",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
