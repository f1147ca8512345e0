"""``bams-cli select``: the next batch of segments and levels to simulate."""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
import polars as pl
import pyarrow as pa
from numpy.typing import NDArray

from bams_cli import defaults, memory
from bams_cli.errors import (
    InputError,
    OptionError,
    OptionValueError,
    PendingResultsError,
    WorkspaceError,
)
from bams_cli.pipeline import screening
from bams_cli.pipeline._common import (
    SID,
    Progress,
    check_budget,
    check_buys_a_run,
    check_clusters,
    check_workers,
    ids_in,
    locked,
    read_scores,
)
from bams_cli.pipeline._handoff import (
    BATCH_INTERNAL,
    cheap_failures,
    passthrough_columns,
    write_handoff,
)
from bams_cli.pipeline.fitting import load_posterior, scoring_fell_short
from bams_cli.state import handoff as contract
from bams_cli.state import schemas
from bams_cli.state.io import (
    read_metadata_json,
    remove_strays,
    transaction,
)
from bams_cli.state.workspace import Workspace
from bams_cli.status import pending_handoffs

# ---------------------------------------------------------------------------------------
# select
# ---------------------------------------------------------------------------------------
MODEL_STRATEGIES = ("bams", "bas")
STRATEGIES = ("bams", "bas", "random", "mc-gp", "mcm-gp", "ds", "ds-gp", "ce")
#: ``--greedy`` to ``core.select.select_batch``'s ``approximate``.
GREEDY_PLANS: dict[str, Literal["auto", "never", "always"]] = {
    "auto": "auto",
    "exact": "never",
    "approximate": "always",
}


def cluster_bytes(workers: int | None, scheduler: str | None) -> int:
    """Bytes one cluster's rows x candidates covariance may take under ``--max-memory``.

    What the command holds already stays; the rest is shared by the worker processes,
    each of which holds one cluster's covariance, about as much again in the greedy's
    temporaries and its own start-up (``bench/bench_memory.py``), and up to a quarter of
    it in the posterior's remembered factors (``core.select`` gives ``MFGP.localised``
    ``limit // 4``): 9/4 of the covariance in all. With ``--scheduler`` the workers run
    elsewhere and only the local limit of ``core.select`` applies.
    """
    from bams_cli.core.select import MAX_CLUSTER_BYTES

    if scheduler:
        return MAX_CLUSTER_BYTES
    n = workers or os.cpu_count() or 1
    held = memory.tree_rss()
    per_worker = (memory.budget() - held) / n - memory.WORKER_BASE_BYTES
    if per_worker <= 0:
        raise OptionError(
            f"select: --max-memory {memory.format_size(memory.budget())} leaves no room for "
            f"{n} worker process{'es' if n > 1 else ''}: this command holds "
            f"{memory.format_size(held)} already and a worker needs about "
            f"{memory.format_size(memory.WORKER_BASE_BYTES)} to start; raise --max-memory"
            + (" or pass --workers 1" if n > 1 else "")
        )
    return int(min(per_worker * 4 / 9, MAX_CLUSTER_BYTES))


def workers_within_memory(workers: int | None, scheduler: str | None) -> tuple[int | None, str]:
    """``--workers`` left out: one worker process per core, or as many as ``--max-memory``
    leaves room for at the full approximate plan, down to 1 (the greedies run in the
    command); where not even one fits, 1, whose plan ``cluster_bytes`` shrinks to fit.

    A worker needs ``memory.WORKER_BASE_BYTES`` to start and, by ``cluster_bytes``' rule,
    twice its cluster's rows x candidates covariance; below the default plan's
    (``defaults.SELECT_MAX_ROWS`` x ``SELECT_MAX_CANDIDATES`` floats) ``cluster_bytes``
    would shrink the rows J is summed over. Fewer workers take longer; fewer rows lose J
    decrease without a word (at 1,000,000 segments under 1G two workers kept 202 rows of J
    per cluster, one worker the full 4,096).

    Returns the workers to use (``workers`` itself when given, None with ``--scheduler``)
    and, when fewer than the cores, why in one sentence (else "").
    """
    if workers is not None or scheduler:
        return workers, ""
    cores = os.cpu_count() or 1
    room = memory.budget() - memory.tree_rss()
    need = (
        memory.WORKER_BASE_BYTES + 2 * 8 * defaults.SELECT_MAX_ROWS * defaults.SELECT_MAX_CANDIDATES
    )
    fits = [n for n in range(cores, 0, -1) if room / n >= need]
    if fits and fits[0] == cores:
        return None, ""
    if not fits:
        # Not even one worker at the full plan: the greedies run in the command, whose plan
        # cluster_bytes shrinks to fit (or refuses in one line before any work). One per
        # core had been kept here, and refused where --workers 1 ran (a trial at 700MB).
        return 1, (
            f"--max-memory {memory.format_size(memory.budget())} leaves no room for a worker "
            f"process at the full plan (one needs about {memory.format_size(need)} beside "
            "what the command holds): the greedies run in the command, on fewer rows of J"
        )
    n = fits[0]
    return n, (
        f"--max-memory {memory.format_size(memory.budget())} leaves room for {n} of "
        f"{cores} worker processes at the full plan (a worker needs about "
        f"{memory.format_size(need)} beside what the command holds); pass --workers to "
        "run more with fewer rows of J each"
    )


@contextlib.contextmanager
def _memory_limit_is_an_option(greedy: str = "auto") -> Iterator[None]:
    """select_batch's refusal of a cluster too large for memory, as a one-line error."""
    try:
        yield
    except ValueError as exc:
        if "GiB" not in str(exc):
            raise
        text = str(exc).replace("n_clusters", "--clusters")
        ceiling = memory.format_size(memory.budget())
        exact = ", or leave out --greedy exact" if greedy == "exact" else ""
        raise OptionError(
            f"select: {text} (what --max-memory {ceiling} leaves each worker; raise it or "
            f"pass --workers 1{exact})"
        ) from None


def _existing_batch(
    ws: Workspace, batch: int, asked: dict[str, Any], n_levels: int, allow_pending: bool = False
) -> dict[str, Any] | None:
    """``select --batch N``: N's summary if it exists with these options, None if N is next."""
    from bams_cli.state.handoff import template_path

    numbers = ws.batch_numbers()
    following = (numbers or [0])[-1] + 1
    if batch not in numbers:
        if batch != following:
            raise OptionError(
                f"--batch {batch}: the next batch is {following}"
                + (f" (batches {numbers[0]}..{numbers[-1]} exist)" if numbers else "")
            )
        return None
    path = schemas.batch_path(ws.root, batch)
    made = read_metadata_json(path).get("options") or {}
    differ = [
        f"{k} {made[k]!r} there, {v!r} asked"
        for k, v in asked.items()
        if k in made and made[k] != v
    ]
    if differ:
        # A new batch beside one that awaits results needs --allow-pending (``select``).
        waiting = not allow_pending and ws.pending().height > 0
        flag, beside = (
            (" --allow-pending", " beside the picks awaiting results") if waiting else ("", "")
        )
        raise OptionError(
            f"{path}: batch {batch} exists with other options ({'; '.join(differ)}); "
            f"pass the same options, or --batch {following}{flag} for a new batch{beside}"
        )
    df = ws.read_batch(batch)
    level = df["fidelity"].to_numpy()
    purpose = df["purpose"].to_list() if "purpose" in df.columns else ["discover"] * df.height
    csv = path.with_suffix(".csv")
    return {
        "batch": batch,
        "handoff": str(path),
        "handoff_csv": str(csv),
        "results_template": str(template_path(csv)),
        "strategy": str(made.get("strategy", asked["strategy"])),
        "picks": df.height,
        "total_cost": math.fsum(df["cost"].to_list()),
        "budget": float(made.get("budget", asked["budget"])),
        "picks_per_level": {lv: int((level == lv).sum()) for lv in range(n_levels)},
        "picks_per_cluster": {
            int(c): int((df["cluster"] == c).sum()) for c in df["cluster"].unique().sort()
        },
        "confirm_picks": sum(p != "discover" for p in purpose),
        "confirm_leads": sum(p == "confirm lead" for p in purpose),
        "j_before": None,
        "j_after": None,
        "timings_s": {},
        "unchanged": True,
    }


def _check_out(out: Path) -> Path:
    """``select --out PATH``: a file path outside the workspace's own state files. What an
    earlier, killed ``select --out PATH`` staged beside it goes."""
    out = Path(out)
    if out.is_dir():
        raise OptionError(f"--out {out}: is a folder; give a file name such as {out / 'batch.csv'}")
    remove_strays(out)
    return out


def _pending_mask(ws: Workspace, ids: np.ndarray, n_levels: int, pend: pl.DataFrame) -> np.ndarray:
    """bool (N, n_levels): True at the pool's (segment, level) pairs awaiting results."""
    out = np.zeros((len(ids), n_levels), bool)
    if pend.height:
        pos = pl.DataFrame({SID: ids, "_i": np.arange(len(ids))})
        rows = pend.join(pos, on=SID).filter(pl.col("fidelity") < n_levels)
        out[rows["_i"].to_numpy(), rows["fidelity"].to_numpy()] = True
    return out


def _copy_handoff_if_needed(csv: Path, out: Path) -> bool:
    """``select --batch N --out PATH`` re-run: (re)write PATH as a copy of batch N's hand-off
    when it is missing or differs; an identical PATH is left alone (Make sees it up to
    date). Returns whether PATH was written."""
    data = csv.read_bytes()
    if out.exists() and out.read_bytes() == data:
        return False
    with transaction() as tx:
        tx.write_bytes(out, data)
    return True


def _nothing_fits(
    budget: float,
    costs: NDArray[np.float64],
    n_usable: int,
    done: NDArray[np.bool_],
) -> str:
    """Why a batch came out empty: the budget, or no segment left at the levels it buys.

    Parameters
    ----------
    budget : float
    costs : ndarray of shape (L + 1,)
        Every level's cost.
    n_usable : int
        How many levels the strategy picks from (1: level 0 only).
    done : bool ndarray of shape (n_pool, L + 1)
        The (segment, level) pairs select may not pick: with a result (unless
        --include-observed), awaiting one, or abandoned (unless --retry-abandoned).

    A level the budget buys with no segment left cannot be picked; the message names the
    level and what would help, not the cost of a level that has nothing left.
    """
    left = (~done).sum(axis=0)
    levels = range(n_usable)
    affordable = [lev for lev in levels if costs[lev] <= budget]
    open_levels = [lev for lev in levels if left[lev] > 0]
    if any(lev in open_levels for lev in affordable) or not affordable:
        return (
            f"select: nothing fits budget {budget:g} (cheapest level costs "
            f"{costs[:n_usable].min():g}); raise --budget"
        )
    # Every segment at the levels the budget buys has a result, awaits one or was abandoned.
    remedy = (
        "ingest the pending results, pass --include-observed to run segments again, "
        "--retry-abandoned to offer abandoned runs, or add segments (embed-reduce --apply)"
    )
    spent = " and ".join(f"level {lev} (cost {costs[lev]:g})" for lev in affordable)
    if not open_levels:
        where = "level 0" if n_usable == 1 else "every level the strategy picks"
        return f"select: no segment is left to run at {where}; {remedy}"
    cheapest = min(open_levels, key=lambda lev: costs[lev])
    n = int(left[cheapest])
    return (
        f"select: budget {budget:g} buys only {spent}, where no segment is left to run; "
        f"level {cheapest} has {n} segment{'' if n == 1 else 's'} left at cost "
        f"{costs[cheapest]:g}: raise --budget to at least {costs[cheapest]:g}"
    )


def _scored_moments(
    scores: Any, model: dict[str, Any], ids: np.ndarray
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]] | None:
    """The pool's means and variances from the scores ``fit`` wrote for this posterior
    (``read_scores``), for use where computing them again would be bounded
    (``core.select._predict``): a million segments after an estimate stage, 6 to 8
    minutes of it. Below that scale select computes them itself in seconds. None when
    the scores are not this pool's."""
    scored, mu, sd, _ = scores
    if not np.array_equal(scored, ids):
        return None
    how = {k: v for k, v in (model.get("scoring") or {}).items() if k != "note"}
    return mu, sd * sd, how or {"method": "exact", "rows": len(ids)}


def _observed_pairs(ws: Workspace, ids: np.ndarray, n_levels: int) -> np.ndarray:
    """[i, l] True where segment i already has a result at level l (one read of the log).

    Column 0 excludes the segment from selection; the greedy (bams, bas) never offers the
    cheap ones again either: a deterministic cheap simulator would return the logged value,
    and a noisy one a second value that ``ingest-results`` refuses as a conflict; a trial's
    fourth BAMS batch had repeated 11 cheap picks of batches 2-3.
    """
    seen = np.zeros((len(ids), n_levels), bool)
    obs = ws.read_observations()
    for lv in range(n_levels):
        seen[:, lv] = ids_in(ids, obs.filter(pl.col("fidelity") == lv)[SID].to_numpy())
    return seen


@locked
def select(
    root: Path,
    *,
    strategy: str = "bams",
    budget: float = 5.0,
    clusters: int = 6,
    overbudget: float = 2.0,
    pooling: str = "global",
    greedy: str = "auto",
    mixed_fidelity: bool = False,
    level0_share: float = 0.5,
    confirm_share: float = defaults.CONFIRM_SHARE,
    difficulty_column: str = "difficulty",
    allow_pending: bool = False,
    include_observed: bool = False,
    workers: int | None = None,
    scheduler: str | None = None,
    handoff_internal: bool = False,
    batch: int | None = None,
    retry_abandoned: bool = False,
    out: Path | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Pick the next batch of (segment, fidelity) simulations and write the hand-off list.

    ``batch`` names the batch this call makes, a stable target for Make: when it exists
    already with the same options the call is a no-op (``unchanged``); when it exists with
    other options, or is not the next number, it is an error naming the next one.

    ``out`` is a second, stable path for the batch's CSV hand-off (byte for byte the one in
    ``batches/``), written in the same transaction; a no-op ``batch`` re-run rewrites it
    when it is missing or differs.

    The Parquet state file holds every column; the CSV hand-off and its results template
    follow the contract in ``state.handoff`` (internal columns only with
    ``handoff_internal``).

    For ``strategy="bams"`` in a study with cheap levels, ``confirm_share`` of the budget
    first buys level-0 runs of unconfirmed cheap-level failures (leads), then of the
    likeliest failures whose level 0 is unknown (``core.confirm``); the greedy spends the
    rest.

    The first batch of a study needs no model: ``strategy="random"``.

    Parameters
    ----------
    root : Path
        The workspace folder (``--workspace``/``-w``).
    strategy : str, default "bams"
        "bams", "bas" (level 0 only), "random", "mc-gp", "mcm-gp", "ds", "ds-gp" or "ce".
    budget : float, default 5.0
        Batch budget m in cost units (a level-0 run costs 1).
    clusters : int, default 6
        Clusters S (1: no clustering).
    overbudget : float, default 2.0
        eta >= 1: each cluster plans ceil(eta m N_s / N).
    pooling : {"global", "raw"}, default "global"
        global: compare (N_s/N) dJ/c across clusters; raw: the paper's dJ.
    greedy : {"auto", "exact", "approximate"}, default "auto"
        bams / bas: the exact greedy (every segment and candidate), the approximate plan
        (bounded clusters, rows and screened candidates; ``core.select.plan_selection``),
        or "auto": exact up to ``defaults.SELECT_EXACT_MAX_POOL`` segments.
    mixed_fidelity : bool, default False
        ``strategy="random"``: spread the picks over every level.
    level0_share : float, default 0.5
        random / mcm-gp: share of the budget spent at level 0.
    confirm_share : float, default ``defaults.CONFIRM_SHARE``
        bams: share of the budget for confirming level-0 runs (above); 0 turns it off.
    difficulty_column : str, default "difficulty"
        ds / ds-gp: the pool column of per-segment difficulty (higher = likelier to fail).
    allow_pending : bool, default False
        Select although an earlier batch awaits results.
    include_observed : bool, default False
        Let segments already observed at level 0, and (bams, bas) pairs already observed at a
        cheap level, be picked again.
    workers : int, optional
        Local worker processes for clusters (default: all cores).
    scheduler : str, optional
        A dask.distributed scheduler address to run clusters on.
    handoff_internal : bool, default False
        Also put the internal columns in the CSV hand-off.
    batch : int, optional
        The batch number this call makes (above).
    retry_abandoned : bool, default False
        Let pairs recorded as abandoned (``abandon``) be picked again.
    out : Path, optional
        Also write the batch's CSV hand-off here (above).
    progress : callable ``(phase, done, total) -> None``, optional
        Called as the work advances (the CLI draws its progress bar with it).
    wait : bool, default False
        Wait for another command's workspace lock instead of failing at once
        (``WorkspaceLockedError``).

    Returns
    -------
    dict
        The summary ``--json`` prints: ``batch``, ``handoff`` (the Parquet state file),
        ``handoff_csv``, ``results_template``, ``strategy``, ``picks`` (how many),
        ``total_cost``, ``budget``, ``picks_per_level``,
        ``picks_per_cluster``; for bams ``confirm_picks`` and ``confirm_leads``;
        ``unchanged`` for a no-op ``batch`` re-run.

    Raises
    ------
    PendingResultsError
        An earlier batch awaits results (exit code 3; ``allow_pending`` selects anyway).
    OptionValueError
        An option out of range or unknown (strategy, pooling, greedy, budget, clusters,
        overbudget, shares, workers); exit code 2.
    WorkspaceError
        No workspace or pool, no model (or one older than the log) for a model-based
        strategy, nothing that fits the budget, or a budget that buys more than the pool.
    OptionError
        A ``batch`` that is not the next one or exists with other options, or an ``out``
        that is a folder.
    InputError
        The pool's difficulty column holds a value that is not finite (ds, ds-gp).
    WorkspaceLockedError
        Another command holds the lock and ``wait`` is False.
    """
    from bams_cli.core import baselines
    from bams_cli.core.confirm import confirmation_picks, n_confirmations
    from bams_cli.core.select import select_batch
    from bams_cli.parallel import executor

    if strategy not in STRATEGIES:
        raise OptionValueError(f"--strategy {strategy!r}: choose one of {', '.join(STRATEGIES)}")
    if pooling not in ("global", "raw"):
        raise OptionValueError(f"--pooling {pooling!r}: choose global or raw")
    if greedy not in GREEDY_PLANS:
        raise OptionValueError(f"--greedy {greedy!r}: choose one of {', '.join(GREEDY_PLANS)}")
    check_budget(budget)
    check_clusters(clusters)
    if not 1 <= overbudget < math.inf:
        raise OptionValueError(
            f"--overbudget {overbudget:g}: must be a finite number >= 1 (each cluster plans "
            "ceil(eta m N_s / N))"
        )
    if not 0 <= level0_share <= 1:
        raise OptionValueError(f"--level0-share {level0_share:g}: must lie in [0, 1]")
    if not 0 <= confirm_share <= 1:
        raise OptionValueError(f"--confirm-share {confirm_share:g}: must lie in [0, 1]")
    check_workers(workers)
    ws = Workspace(root)
    settings = ws.require_initialised()
    ids, X = ws.read_pool()
    # Every segment at every level costs len(ids) * sum(costs): a budget beyond it cannot be
    # spent. (The bound was budget / the cheapest cost, which refused a level-0 batch of 100
    # on 400 segments with a cheap level of cost 0.1.)
    if budget > len(ids) * sum(settings.costs) * (1 + 1e-9):  # 3 x (1 + 0.2) is 3.5999...
        raise WorkspaceError(
            f"--budget {budget}: buys more simulations than the pool has "
            f"({len(ids)} segments x {settings.n_levels} levels cost "
            f"{len(ids) * sum(settings.costs):g})"
        )
    # A budget below one run of every level the strategy may pick: refused before the work
    # (it was after a full selection, citing the cheap level's cost to a level-0 strategy).
    multi = strategy in ("bams", "mcm-gp") or (strategy == "random" and mixed_fidelity)
    usable = settings.costs if multi and settings.n_levels > 1 else settings.costs[:1]
    check_buys_a_run(budget, usable, level0_only=None if len(usable) > 1 else strategy)
    # The options that decide the picks: recorded in the batch, compared by --batch.
    asked = {
        "strategy": strategy,
        "budget": budget,
        "clusters": clusters,
        "overbudget": overbudget,
        "pooling": pooling,
        "greedy": greedy,
        "mixed_fidelity": mixed_fidelity,
        "level0_share": level0_share,
        "confirm_share": confirm_share,
    }
    if out is not None:
        out = _check_out(out)
    if batch is not None:
        done = _existing_batch(ws, batch, asked, settings.n_levels, allow_pending)
        if done is not None:
            if out is not None:
                _copy_handoff_if_needed(Path(done["handoff_csv"]), out)
                done["out"] = str(out)
            return done
    pend = ws.pending()
    if pend.height and not allow_pending:
        where = [f"batch {b}" for b in sorted(set(pend["batch"].drop_nulls().to_list()))]
        where += [f"estimate plan {p}" for p in sorted(set(pend["plan"].drop_nulls().to_list()))]
        lists = pending_handoffs(ws, pend)
        raise PendingResultsError(
            f"{ws.root}: {pend.height} {'pick' if pend.height == 1 else 'picks'} of "
            f"{', '.join(where)} {'has' if pend.height == 1 else 'have'} no results yet; "
            f"simulate {' and '.join(lists)}, ingest the results with `bams-cli "
            "ingest-results`, or pass --allow-pending"
        )
    number = (ws.batch_numbers() or [0])[-1] + 1
    rng = np.random.default_rng([settings.seed, number])
    costs = np.asarray(settings.costs)
    seen = _observed_pairs(ws, ids, settings.n_levels)
    observed0 = seen[:, 0]
    exclude = np.zeros(len(ids), bool) if include_observed else observed0
    # Abandoned runs (bams_cli.abandon) are done: never offered again unless asked.
    gone = np.zeros((len(ids), settings.n_levels), bool)
    if not retry_abandoned:
        from bams_cli.abandon import abandoned_mask

        gone = abandoned_mask(ws, ids, settings.n_levels)
    # Pending picks (--allow-pending) are in the batch already: never picked again, and the
    # BAMS greedy is conditioned on them. Their results land under the batch that asked.
    waiting = _pending_mask(ws, ids, settings.n_levels, pend)
    exclude = exclude | gone[:, 0] | waiting[:, 0]
    # The (segment, level) pairs a baseline may not pick, and an empty batch's explanation.
    done = (gone | waiting) if include_observed else (gone | waiting | seen)
    model_hash = None
    j_before = j_after = None
    timings: dict[str, float] = {}
    selection_plan: dict[str, Any] | None = None  # core.select.plan_selection, as taken

    purpose: np.ndarray | None = None
    if strategy in MODEL_STRATEGIES:
        posterior, model = load_posterior(ws, settings, ids, X)
        model_hash = model["observations_hash"]
        confirm, is_lead = np.zeros(0, np.int64), np.zeros(0, bool)
        k = (
            n_confirmations(budget, float(costs[0]), confirm_share)
            if strategy == "bams" and settings.n_levels > 1
            else 0
        )
        # fit's scores: the confirmations' p_n, and the pool's moments at a scale where
        # computing them again would be bounded; read once for both.
        bounded = posterior.bounded_scoring(len(ids), defaults.SCORE_MAX_WORK)
        scores = read_scores(ws, len(settings.gammas)) if k or bounded else None
        if k:
            assert scores is not None
            confirm, is_lead = confirmation_picks(
                scores[3][:, 0],
                cheap_failures(
                    ws, ids, settings.gammas[0], model["hyperparameters"].get("scales") or ()
                ),
                exclude,
                k,
            )
        rest = budget - float(costs[0]) * len(confirm)
        moments = _scored_moments(scores, model, ids) if bounded else None
        taken0 = observed0.copy()
        taken0[confirm] = True
        result = None
        if rest >= costs.min() - 1e-12:
            workers, fewer_workers = workers_within_memory(workers, scheduler)
            with executor(workers, scheduler) as pool, _memory_limit_is_an_option(greedy):
                result = select_batch(
                    posterior,
                    X,
                    gamma=settings.gammas[0],
                    costs=list(settings.costs),
                    budget=rest,
                    n_clusters=clusters,
                    overbudget=overbudget,
                    observed_level0_mask=taken0,
                    pooling=pooling,  # type: ignore[arg-type]
                    executor=pool,
                    rng=rng,
                    progress=progress,
                    levels=[0] if strategy == "bas" else None,
                    reobserve_level0=include_observed,
                    # Cheap pairs already logged (level 0's go with the segment).
                    excluded_pairs=gone if include_observed else gone | seen,
                    pending_pairs=waiting if waiting.any() else None,
                    approximate=GREEDY_PLANS[greedy],
                    plan_options={"max_cluster_bytes": cluster_bytes(workers, scheduler)},
                    max_work=defaults.SCORE_MAX_WORK,
                    local_obs=defaults.SELECT_LOCAL_OBS,
                    moments=moments,
                )
        n_greedy = 0 if result is None else len(result.index)
        picks = {
            "index": np.concatenate([confirm, result.index if result else []]).astype(np.int64),
            "level": np.concatenate(
                [np.zeros(len(confirm)), result.level if result else []]
            ).astype(np.int64),
            "delta_j": np.concatenate(
                [np.full(len(confirm), np.nan), result.delta_j if result else []]
            ),
            "cluster": np.concatenate(
                [np.full(len(confirm), -1), result.cluster if result else []]
            ).astype(np.int64),
        }
        purpose = np.array(
            [("confirm lead" if lead else "confirm likely") for lead in is_lead]
            + ["discover"] * n_greedy,
            dtype=object,
        )
        if result is not None:
            j_before, j_after = float(result.j_before), float(result.j_after)
            timings = {k: round(float(v), 3) for k, v in result.timings.items()}
            selection_plan = dict(result.plan)
            selection_plan["workers"] = None if scheduler else (workers or os.cpu_count() or 1)
            if scheduler:
                # Where the greedies ran: --json said workers null and nothing else.
                selection_plan["scheduler"] = scheduler
                selection_plan["workers_reason"] = "the greedies ran on the dask cluster"
            if fewer_workers:
                selection_plan["workers_reason"] = fewer_workers
    else:
        multi = strategy == "mcm-gp" or (strategy == "random" and mixed_fidelity)
        n_rest = settings.n_levels - 1
        shares = [level0_share] + [(1 - level0_share) / n_rest] * n_rest if n_rest else None
        difficulty = observed_index = observed_value = None
        if strategy in ("ds", "ds-gp"):
            table = ws.read_segments()
            if difficulty_column not in table.column_names:
                raise WorkspaceError(
                    f"{ws.segments_path}: --strategy {strategy} needs a difficulty column "
                    f"{difficulty_column!r} (pass it through embed-reduce, or name it with --difficulty-column)"
                )
            difficulty = (
                table.column(difficulty_column).to_numpy(zero_copy_only=False).astype(np.float64)
            )
            if not np.isfinite(difficulty).all():
                row = int(np.flatnonzero(~np.isfinite(difficulty))[0]) + 1
                raise InputError(
                    ws.segments_path, "difficulty must be finite", column=difficulty_column, row=row
                )
        elif strategy == "ce":
            obs = ws.read_observations().filter(pl.col("fidelity") == 0)
            pos = pl.DataFrame({SID: ids, "_i": np.arange(len(ids))})
            o = obs.join(pos, on=SID).select("_i", "value")
            observed_index, observed_value = o["_i"].to_numpy(), o["value"].to_numpy()
        index, level = baselines.pick_baseline(
            strategy,  # type: ignore[arg-type]  # checked against STRATEGIES above
            n_pool=len(ids),
            costs=list(settings.costs),
            budget=budget,
            rng=rng,
            observed_level0_mask=exclude,
            difficulty=difficulty,
            X=X,
            observed_index=observed_index,
            observed_value=observed_value,
            mixed=multi and n_rest > 0,
            level_shares=shares,
            # A cheap level's picks only where that level can still be run: the picks the
            # filter below would drop are never drawn, so the batch spends its budget.
            excluded_pairs=done,
        )
        keep = ~(gone | waiting)[np.asarray(index, np.int64), np.asarray(level, np.int64)]
        index, level = np.asarray(index)[keep], np.asarray(level)[keep]
        picks = {
            "index": np.asarray(index, np.int64),
            "level": np.asarray(level, np.int64),
            "delta_j": np.full(len(index), np.nan),
            "cluster": np.zeros(len(index), np.int64),
        }

    k = len(picks["index"])
    if k == 0:
        raise WorkspaceError(_nothing_fits(budget, costs, len(usable), done))
    cols: dict[str, Any] = contract.contract_columns(
        "batch",
        number,
        ids[picks["index"]],
        picks["level"],
        settings,
        list(purpose) if purpose is not None else ["discover"] * k,
    )
    cols |= {
        "delta_j": picks["delta_j"],
        "cluster": picks["cluster"],
        "rank": np.arange(k, dtype=np.int64),
        "strategy": [strategy] * k,
    }
    cols |= passthrough_columns(ws, picks["index"], taken=cols)
    options = {
        **asked,
        "include_observed": include_observed,
        "allow_pending": allow_pending,
        "retry_abandoned": retry_abandoned,
        "difficulty_column": difficulty_column,
        "workers": workers,
        "scheduler": scheduler,
        "gamma": settings.gammas[0],
    }
    meta = {
        "batch": number,
        "seed": settings.seed,
        "model_hash": model_hash or "",
        "options": options,
        # The pool's J before and after the batch (the report's trend and stopping signal).
        "j_before": j_before,
        "j_after": j_after,
    }
    if selection_plan is not None:
        # The plan as taken (clusters, rows, candidates): the report clusters as select did.
        meta["selection_plan"] = selection_plan
    table = schemas.BATCH.conform(pa.table(cols), meta)
    path = schemas.batch_path(ws.root, number)
    with transaction() as tx:
        tx.write_parquet(path, table)
        csv, template = write_handoff(
            tx, table, path.with_suffix(".csv"), BATCH_INTERNAL, handoff_internal
        )
        if out is not None:
            frame = contract.handoff_frame(table, BATCH_INTERNAL, with_internal=handoff_internal)
            tx.write_with(out, lambda p: frame.write_csv(p))
    per_level = {int(lv): int((picks["level"] == lv).sum()) for lv in range(settings.n_levels)}
    per_cluster = {int(c): int((picks["cluster"] == c).sum()) for c in np.unique(picks["cluster"])}
    # A cost edited by hand in settings.toml: init warned of it when the study began.
    warnings = settings.dear_levels(str(ws.settings_path))
    if j_before is not None and j_before * len(ids) < defaults.SELECT_NEGLIGIBLE_FAILURES:
        # J = mean p_n (1 - p_n) ~ mean p_n here: the model expects (nearly) no failure in
        # the pool, and the greedy's decreases are rounding (a trial's first fit after a
        # random batch without a failure put J at 2.5e-30).
        warnings.append(
            f"the model expects {j_before * len(ids):.2g} failures in the whole pool (J "
            f"{j_before:.2g}): it rules failure out everywhere, so this batch's picks rest "
            "on rounding, not on where failures may be; a random batch (--strategy random "
            "--mixed-fidelity) or more level-0 runs test that belief"
        )
    # Rows near gamma whose sd stayed a bound: the greedy saw a less certain model there.
    sds = (selection_plan or {}).get("pool_sds") or {}
    warnings += scoring_fell_short(sds, "the pool's posterior")
    if per_level.get(0, 0) and (screen := screening.open_screen(ws)) is not None:
        warnings.append(
            f"{screen.name} awaits its level-0 confirmation: this batch's {per_level[0]} "
            "level-0 picks, once their results are in, fall among the segments it counted "
            "as unknown, and its confirmation will refuse it (`bams-cli estimate --plan "
            "--new-series` plans afresh); confirm it first to keep its cheap runs"
        )
    return {
        "batch": number,
        "handoff": str(path),
        "handoff_csv": str(csv),
        "results_template": str(template),
        "strategy": strategy,
        "picks": k,
        "total_cost": math.fsum(costs[picks["level"]].tolist()),
        "budget": budget,
        "picks_per_level": per_level,
        "picks_per_cluster": per_cluster,
        "confirm_picks": int(np.sum(purpose != "discover")) if purpose is not None else 0,
        "confirm_leads": int(np.sum(purpose == "confirm lead")) if purpose is not None else 0,
        "j_before": j_before,
        "j_after": j_after,
        "timings_s": timings,
        **({"selection_plan": selection_plan} if selection_plan is not None else {}),
        **({"out": str(out)} if out is not None else {}),
        "warnings": warnings,
    }
