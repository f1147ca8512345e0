"""``bams-cli fit``: the multifidelity GP's hyperparameters and the pool's scores."""

from __future__ import annotations

import datetime as dt
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import pyarrow as pa

from bams_cli import defaults, memory
from bams_cli.errors import (
    InputError,
    OptionValueError,
    PendingResultsError,
    SchemaError,
    StaleStateError,
    WorkspaceError,
)
from bams_cli.pipeline._common import SID, Progress, locked, read_scores
from bams_cli.settings import Settings
from bams_cli.state import schemas
from bams_cli.state.io import (
    read_metadata_json,
    stamp,
    transaction,
)
from bams_cli.state.workspace import Workspace
from bams_cli.status import pending_handoffs


# ---------------------------------------------------------------------------------------
# fit
# ---------------------------------------------------------------------------------------
def _training_data(
    ws: Workspace, ids: np.ndarray, X: np.ndarray, n_levels: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Active observations as (pool index, level, value) arrays; an observation at a level
    beyond the study's ``n_levels`` (one deleted from settings.toml) is refused."""
    obs = ws.read_observations()
    pend = ws.pending() if obs.height == 0 else None
    if pend is not None and pend.height:
        raise PendingResultsError(
            f"{ws.observations_path}: no observations yet, {pend.height} picks await results; "
            f"simulate {' and '.join(pending_handoffs(ws, pend))} and run "
            f"`bams-cli ingest-results -w {ws.root} RESULTS.parquet`, then fit"
        )
    if obs.height == 0:
        raise WorkspaceError(
            f"{ws.observations_path}: no observations yet; select a first batch "
            f"(`{ws.first_batch_command()}`), simulate it and ingest the results"
        )
    beyond = obs.filter(pl.col("fidelity") >= n_levels)
    if beyond.height:
        # A level removed from settings.toml by hand: its results stay in the log.
        raise WorkspaceError(
            f"{ws.observations_path}: {beyond.height} observation(s) at level "
            f"{int(beyond['fidelity'].max())} (segment {beyond[SID][0]!r}), but "  # type: ignore[arg-type]
            f"{ws.settings_path} declares {n_levels} level(s); restore the levels in "
            "settings.toml (the log keeps every result)"
        )
    index = pl.DataFrame({SID: ids, "_idx": np.arange(len(ids))})
    joined = obs.join(index, on=SID, how="left")
    missing = joined.filter(pl.col("_idx").is_null())
    if missing.height:
        raise WorkspaceError(
            f"{ws.observations_path}: segment {missing[SID][0]!r} is no longer in the pool "
            f"({missing.height} observations in all); re-add it with `embed-reduce --apply`"
        )
    return (
        joined["_idx"].to_numpy().astype(np.int64),
        joined["fidelity"].to_numpy().astype(np.int64),
        joined["value"].to_numpy().astype(np.float64),
    )


def load_posterior(ws: Workspace, settings: Settings, ids: np.ndarray, X: np.ndarray):  # noqa: ANN201
    """The fitted model, conditioned again on the log it was fitted on (cheap: one Cholesky).

    The posterior is of the transformed metric g(y) (model.json's ``transform``); g maps
    the first gamma to itself, so ``select`` compares against it unchanged.
    """
    from bams_cli.core.gp import Hyperparameters, fit_mfgp

    model = ws.require_fresh_model()
    idx, lv, y = _training_data(ws, ids, X, settings.n_levels)
    hp = Hyperparameters.from_dict(model["hyperparameters"])  # checked by read_model
    g = model_transform(ws, model)
    # Condition as fit did: its memory budget decides exact or the same subset (older
    # models, without the record, conditioned exactly on all). A subset is rebuilt from
    # its recorded size, which stays right when a release changes the bytes per entry.
    record = model.get("conditioning") or {}
    budget = record.get("memory_budget_bytes")
    if record.get("method") == "exact_subset" and record.get("conditioned_on"):
        from bams_cli.core.conditioning_budget import BYTES_PER_ENTRY

        budget = BYTES_PER_ENTRY * int(record["conditioned_on"]) ** 2
    return fit_mfgp(
        X[idx], lv, g.forward(y), settings.n_levels, rng=np.random.default_rng(settings.seed),
        fixed=hp, max_memory=None if budget is None else int(budget),
    ), model  # fmt: skip


def model_transform(ws: Workspace, model: dict[str, Any]):  # noqa: ANN202
    """The output transform a model.json records (the identity for older models)."""
    from bams_cli.core.gp import OutputTransform

    try:
        return OutputTransform.from_dict(model.get("transform"))
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(
            ws.model_path, f"transform: {exc}; rewrite it with `bams-cli fit -w {ws.root}`"
        ) from None


@locked
def fit(
    root: Path,
    *,
    fixed_hyperparameters: Path | None = None,
    restarts: int = 8,
    chunk_size: int = 50_000,
    transform: str = defaults.TRANSFORM,
    force: bool = False,
    max_memory: int | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Train the multifidelity GP on the observation log and score every pool segment.

    ``transform`` is "auto" (model g(y) = c + s asinh((y - c)/s), c the first gamma, with
    s chosen by evidence among the identity and a few scales: ``core.gp.transform``) or
    "none". With ``fixed_hyperparameters`` the file's own transform is used.

    A model already fitted the same way on the same log is kept, and nothing is written
    (``up_to_date`` in the summary; ``_fit_up_to_date``), unless ``force``.

    Parameters
    ----------
    root : Path
        The workspace folder (``--workspace``/``-w``).
    fixed_hyperparameters : Path, optional
        JSON of hyperparameters (e.g. a saved model.json): skip training, only condition.
    restarts : int, default 8
        Seeded L-BFGS-B restarts of the MAP fit.
    chunk_size : int, default 50000
        Pool rows scored per chunk.
    transform : {"auto", "none"}, default ``defaults.TRANSFORM``
        The output transform (above).
    force : bool, default False
        Fit again although the model is up to date.
    max_memory : int, optional
        Byte budget of conditioning (default ``defaults.FIT_CONDITION_MEMORY``): exact on
        every observation while it fits, else exact on a subset (``core.gp.fit.condition``);
        the summary's ``conditioning`` says which.
    progress : callable ``(phase, done, total) -> None``, optional
        Called as the work advances (the CLI draws its progress bar with it).
    wait : bool, default False
        Wait for another command's workspace lock instead of failing at once
        (``WorkspaceLockedError``).

    Returns
    -------
    dict
        The summary ``--json`` prints: ``model`` and ``scores`` (the files written),
        ``observations``, ``n_observations_per_level``, ``log_marginal_likelihood``,
        ``hyperparameters``, ``checks``, ``transform``, ``gp_rate_estimate``,
        ``warnings``; or ``up_to_date`` and ``message`` when nothing was written.

    Raises
    ------
    PendingResultsError
        No observations yet while picks await results (exit code 3).
    OptionValueError
        An option out of range (``restarts``, ``chunk_size``, ``transform``); exit code 2.
    WorkspaceError
        No workspace or no observations, or an observed segment missing from the pool.
    InputError
        ``fixed_hyperparameters`` (or the saved model) is missing or does not fit the study.
    WorkspaceLockedError
        Another command holds the lock and ``wait`` is False.
    """
    if restarts < 1:
        raise OptionValueError(f"--restarts {restarts}: must be >= 1")
    if chunk_size < 1:
        raise OptionValueError(f"--chunk-size {chunk_size}: must be >= 1")
    if transform not in TRANSFORMS:
        raise OptionValueError(f"--transform {transform!r}: choose one of {', '.join(TRANSFORMS)}")
    ws = Workspace(root)
    settings = ws.require_initialised()
    # Said on every fit, kept or not: it is about the settings as they are now.
    stale_dim = _dimension_not_applied(ws, settings)
    if not force and fixed_hyperparameters is None:
        kept = _fit_up_to_date(
            ws, settings, restarts=restarts, transform=transform, max_memory=max_memory
        )
        if kept is not None:
            return {
                **kept,
                "warnings": [*stale_dim, *kept["warnings"]],
                "settings_warnings": stale_dim,
            }
    # The numerical stack (scipy.stats alone takes seconds to import) only for a real fit:
    # a Makefile's `fit` with nothing to do returned after 3-7 s.
    from bams_cli.core.gp import GPFitError, Hyperparameters, OutputTransform, fit_transformed
    from bams_cli.core.gp.checks import check_model

    chosen = None if transform == "auto" else OutputTransform()
    ids, X = ws.read_pool()
    idx, lv, y = _training_data(ws, ids, X, settings.n_levels)
    fixed = None
    if fixed_hyperparameters is not None:
        try:
            doc = json.loads(Path(fixed_hyperparameters).read_text())
            fixed = Hyperparameters.from_dict(doc.get("hyperparameters", doc))
            chosen = OutputTransform.from_dict(doc.get("transform"))
        except FileNotFoundError:
            raise InputError(fixed_hyperparameters, "hyperparameter file not found") from None
        except (ValueError, KeyError, TypeError, AttributeError) as exc:
            raise InputError(fixed_hyperparameters, f"not a hyperparameter file ({exc})") from None
        if fixed.lengthscales0.shape[0] != X.shape[1] or fixed.noise.shape[0] != settings.n_levels:
            raise InputError(
                fixed_hyperparameters,
                f"hyperparameters are for d = {fixed.lengthscales0.shape[0]}, {fixed.noise.shape[0]} "
                f"levels; the study has d = {X.shape[1]}, {settings.n_levels} levels",
            )
    rng = np.random.default_rng(settings.seed)
    if progress:
        progress("fit", 0, 1)
    try:
        model, g, evidence = fit_transformed(
            X[idx], lv, y, settings.n_levels, centre=float(settings.gammas[0]), rng=rng,
            restarts=restarts, transform=chosen, fixed=fixed,
            max_memory=condition_budget(max_memory),
        )  # fmt: skip
    except GPFitError as exc:
        raise WorkspaceError(f"fit: {exc}") from None
    model_gammas = g.forward(np.asarray(settings.gammas, dtype=np.float64))
    if progress:
        progress("fit", 1, 1)

    mu, sd, p = model.score(
        X, model_gammas, chunk_size, max_work=defaults.SCORE_MAX_WORK, progress=progress
    )
    sd_exact = np.ones(len(ids), dtype=bool) if model.sd_exact is None else model.sd_exact

    rows = model.conditioned_rows
    checks = check_model(model, idx if rows is None else idx[rows], names=ids)
    warnings = [
        *_no_level0(lv, settings.n_levels),
        *model.notes,
        *scoring_fell_short(model.scoring),
        *checks.warnings,
        *_contradicted_outcomes(ids, idx, lv, y, p, settings.gammas),
    ]
    obs_hash = ws.observations_hash()
    hp = model.hyperparameters
    doc = {
        "hyperparameters": hp.to_dict(),
        "log_marginal_likelihood": float(model.log_marginal_likelihood),
        "log_posterior": float(model.log_posterior),
        "n_observations_per_level": [int(c) for c in np.bincount(lv, minlength=settings.n_levels)],
        "observations_hash": obs_hash,
        "pool": ws.pool_fingerprint(),
        "units": (
            "outputscale0, outputscales and noise are variances; lengthscales and mean in the "
            "metric's units; a cheap level l's discrepancy and noise in level 0's, its offset "
            "in its own (y_l = scales[l] (theta0 + discrepancy + noise) + offsets[l])"
        ),
        "trained": fixed is None,
        "restarts": restarts,
        # The MAP search runs on at most defaults.FIT_SUBSET observations (core.gp.fit_subset);
        # the model conditions on all of them.
        "hyperparameters_fitted_on": int(model.fitted_on),
        # Exact on all observations, or exact on a subset when they exceed the memory
        # budget (core.gp.fit.condition); load_posterior conditions the same way.
        "conditioning": {**model.conditioning, "note": conditioning_note(model.conditioning)},
        # Exact sds everywhere, or exact where a threshold is near (core.gp.MFGP.score).
        "scoring": {**model.scoring, "note": scoring_note(model.scoring)},
        "seed": settings.seed,
        "gammas": list(settings.gammas),
        "fitted_at": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "jitter": float(model.jitter),
        "transform": g.to_dict(),
        "transform_option": transform,
        "transform_evidence": [
            {
                "scale": None if math.isinf(e["scale"]) else e["scale"],
                "log_evidence": e["log_evidence"],
            }
            for e in evidence
        ],
        "checks": checks.to_dict(),
        "warnings": warnings,
    }
    cols: dict[str, Any] = {SID: pa.array(ids, pa.string()), "mu": mu, "sd": sd}
    cols["sd_exact"] = sd_exact
    for j in range(p.shape[1]):
        cols[f"p_{j}"] = p[:, j]
    meta = {"observations_hash": obs_hash, "gammas": list(settings.gammas), "seed": settings.seed}
    # A snapshot of p_n after every batch feeds the report's per-batch retention-recall.
    # It is taken only when the newest results belong to a batch: a refit after ingesting
    # an estimate plan's results must not pass for the model "after batch b".
    log = ws.read_observations(active_only=False)  # append-only: the last rows are the newest
    newest = log.filter(pl.col("source_sha256") == log["source_sha256"][-1])["batch"]
    snapshot_batch = None
    if newest.len() and newest.null_count() == 0:
        snapshot_batch = int(newest.max())  # type: ignore[arg-type]
    history = pa.table({f"p_{g}": p[:, g] for g in range(p.shape[1])})
    with transaction() as tx:
        tx.write_text(ws.model_path, json.dumps(doc, indent=2) + "\n")
        tx.write_parquet(ws.scores_path, schemas.SCORES.conform(pa.table(cols), meta))
        if snapshot_batch is not None:
            snapshot = ws.history_dir / f"scores-after-batch-{snapshot_batch:04d}.parquet"
            tx.write_parquet(snapshot, stamp(history, schemas.SCORES.version, meta))
    return {
        "model": str(ws.model_path),
        "scores": str(ws.scores_path),
        "observations": int(len(y)),
        "n_observations_per_level": doc["n_observations_per_level"],
        "log_marginal_likelihood": doc["log_marginal_likelihood"],
        "log_posterior": doc["log_posterior"],
        "hyperparameters": doc["hyperparameters"],
        "checks": doc["checks"],
        "jitter": doc["jitter"],
        "hyperparameters_fitted_on": doc["hyperparameters_fitted_on"],
        "conditioning": doc["conditioning"],
        "scoring": doc["scoring"],
        "transform": doc["transform"],
        "gp_rate_estimate": {str(g): float(p[:, i].mean()) for i, g in enumerate(settings.gammas)},
        # Segments seen failing at level 0, per gamma: without one, nothing outside the
        # model has checked its rate (the printed summary says so).
        "level0_failures": {
            str(g): int(np.unique(idx[(lv == 0) & (y <= g)]).size) for g in settings.gammas
        },
        "warnings": [*stale_dim, *warnings],
    }


def condition_budget(max_memory: int | None = None) -> int:
    """Bytes ``fit`` may spend on exact conditioning: ``max_memory`` when given, else
    ``defaults.FIT_CONDITION_MEMORY`` or half the command's ``--max-memory`` ceiling,
    whichever is less (the other half holds the pool, its scores and the search)."""
    if max_memory is not None:
        return max_memory
    return min(defaults.FIT_CONDITION_MEMORY, memory.share(0.5))


def _fit_up_to_date(
    ws: Workspace,
    settings: Settings,
    *,
    restarts: int,
    transform: str,
    max_memory: int | None = None,
) -> dict[str, Any] | None:
    """The summary of the model in ``model.json`` if fitting now would redo it, else None.

    Redoing it means: trained (not ``--fixed-hyperparameters``) on the current observation
    log and pool, with scores from that fit (``Workspace.require_model``), for the same
    gammas, seed and number of levels, with the same ``--restarts`` and ``--transform``.
    ``--chunk-size`` only bounds memory, so it does not count; the conditioning budget
    counts only if it would condition on another number of observations.
    """
    from bams_cli.core.conditioning_budget import max_conditioned

    if not ws.model_path.exists() or not ws.segments_path.exists():
        return None
    try:
        model = ws.require_model(allow_newer_observations=True)
    except (StaleStateError, SchemaError):  # damaged, another pool, scores from another fit
        return None
    n_obs = model.get("n_observations_per_level")
    same = (
        model["fresh"]
        and model.get("trained") is True
        and model.get("restarts") == restarts
        and model.get("transform_option") == transform
        and model.get("gammas") == list(settings.gammas)
        and model.get("seed") == settings.seed
        and isinstance(n_obs, list)
        and len(n_obs) == settings.n_levels
    )
    if not same:
        return None
    n = int(np.sum(n_obs or []))
    cap = max_conditioned(condition_budget(max_memory))
    recorded = (model.get("conditioning") or {}).get("conditioned_on", n)  # older: all
    if recorded != (n if cap is None else min(n, cap)):
        return None
    _, _, _, p = read_scores(ws, len(settings.gammas))
    return {
        "up_to_date": True,
        "message": f"model is up to date (fitted on {n} observations); nothing to do "
        f"(pass --force to fit again)",
        "model": str(ws.model_path),
        "scores": str(ws.scores_path),
        "observations": n,
        **{
            k: model.get(k)
            for k in (
                "n_observations_per_level",
                "log_marginal_likelihood",
                "log_posterior",
                "hyperparameters",
                "checks",
                "jitter",
                "conditioning",
                "scoring",
                "transform",
            )
            if k in model  # scoring: models written before it was recorded
        },
        "gp_rate_estimate": {str(g): float(p[:, i].mean()) for i, g in enumerate(settings.gammas)},
        "warnings": model.get("warnings", []),
    }


def conditioning_note(c: dict[str, Any]) -> str:
    """One line saying what the posterior conditions on (``MFGP.conditioning``)."""
    n = int(c["observations"])
    if c["method"] == "exact":
        return f"exact posterior: conditioned on all {n:,} observations"
    budget = float(c.get("memory_budget_bytes") or 0)
    return (
        f"conditioned exactly on {int(c['conditioned_on']):,} of {n:,} observations (level 0 "
        f"first), the most a {budget / 2**30:.1f} GiB budget holds; sds are never below the "
        "exact posterior's"
    )


#: Output transforms ``fit --transform`` accepts.
TRANSFORMS = ("auto", "none")


#: p_n below this at an observed level-0 failure (or 1 - p_n below it at an observed
#: non-failure) means the model contradicts what was measured.
CONTRADICTION = 0.01


def scoring_note(s: dict[str, Any]) -> str:
    """One line on how ``fit`` scored the pool (``model.json``'s ``scoring``)."""
    if s.get("method") != "bounded":
        return "every segment's mean and sd exact"
    rest = s["near_thresholds"] - s["exact_sd_rows"]
    short = (
        f"; {rest:,} more near them kept the bound, their p_n leaning toward 1/2 (it can "
        f"move the pool's sum of p_n by up to {kept_bound_share(s):.2%})"
        if rest
        else ""
    )
    return (
        f"means exact; sds exact on the {s['exact_sd_rows']:,} segments nearest a threshold "
        f"(within {s['decided_z']:g} sds), elsewhere an upper bound from "
        f"{s['bound_observations']:,} observations, where p_n is 0 or 1 within 1e-17{short}: "
        f"exact sds on all {s['rows']:,} would cost over {s['max_work']:.0e} flops"
    )


def kept_bound_share(s: dict[str, Any]) -> float:
    """The most, over gammas, that rows which kept the bound sd can move the pool's sum of
    p_n, as a share of it (``MFGP._score_bounded``: min(p, 1 - p) per row)."""
    shares = [e / t for e, t in zip(s["kept_bound_error"], s["p_sum"], strict=True) if t > 0]
    return max(shares, default=0.0)


def scoring_fell_short(s: dict[str, Any], prefix: str = "scoring") -> list[str]:
    """``scoring_note`` as a warning (after ``prefix``) when rows that kept the bound sd can
    move the pool's sum of p_n (the model's expected failures) by over
    ``SCORING_SHORT_SHARE`` of it; ``fit`` and ``select`` both warn by it."""
    short = s.get("method") == "bounded" and kept_bound_share(s) > SCORING_SHORT_SHARE
    return [f"{prefix}: {scoring_note(s)}"] if short else []


#: ``fit`` warns when the rows that kept a bound sd can move sum p_n by more than this share.
SCORING_SHORT_SHARE = 0.01


def _no_level0(levels: np.ndarray, n_levels: int) -> list[str]:
    """A warning when no observation is at level 0: the cheap levels' offsets from it (their
    bias) and level 0's own noise are then the priors', not measured, and p_n is level 0's
    only as far as the cheap levels are unbiased."""
    if n_levels < 2 or np.any(levels == 0):
        return []
    return [
        f"no level-0 result yet ({levels.size} cheap-level results): the cheap levels' bias "
        "against level 0 and level 0's noise are not measured (taken as 0 and the prior's), "
        "so p_n is level 0's only if the cheap levels are unbiased; ingest level-0 results "
        "before trusting it"
    ]


def _dimension_not_applied(ws: Workspace, settings: Settings) -> list[str]:
    """A warning when settings.toml's embedding_dim is not the count the pool was reduced
    to from it: the pool keeps its coordinates until ``embed-reduce --force``, so an edit of
    the setting after ``embed-reduce`` changes nothing by itself. Silent for a pool reduced
    with an explicit ``--dim`` (the flag rules there) and for pools from before the
    metadata recorded where the count came from."""
    if not ws.segments_path.exists():
        return []
    made = read_metadata_json(ws.segments_path)
    reduced = (made.get("reduce_options") or {}).get("dim")
    if made.get("dim_from_settings") is not True or reduced == settings.embedding_dim:
        return []
    return [
        f"{ws.settings_path}: embedding_dim is {settings.embedding_dim!r}, but the pool was "
        f"reduced with {reduced!r} ({made.get('dim')} components); the setting applies only "
        f"after `bams-cli embed-reduce --force` (then fit again)"
    ]


def _beside(value: float, gamma: float) -> str:
    """``value`` with the digits that tell it from ``gamma`` (1.9002 is not "1.9" beside a
    gamma of 1.9)."""
    for digits in range(4, 17):
        text = f"{value:.{digits}g}"
        shown = float(text)
        # On gamma's side that the value is on, and not gamma itself unless the value is.
        if (shown <= gamma) == (value <= gamma) and (shown != gamma or value == gamma):
            return text
    return repr(value)


def _contradicted_outcomes(
    ids: np.ndarray,
    idx: np.ndarray,
    lv: np.ndarray,
    y: np.ndarray,
    p: np.ndarray,
    gammas: Sequence[float],
) -> list[str]:
    """Observed level-0 outcomes the fitted model is nearly sure did not happen, and a
    model rate below the failures already seen.

    A fit that explains level-0 results as noise (large level-0 noise, or the data handed to
    the discrepancy) gives p_n ~ 0 at segments seen failing. The rate estimate then samples
    the failures like them with tiny probability and its variance explodes, so say so. Its
    own rate, sum p_n / N, can then fall below the count already confirmed at level 0 (a
    trial study: 2.5 failures expected in the pool, 6 confirmed), which no pool can hold.
    """
    out = []
    level0 = lv == 0
    for g, gamma in enumerate(gammas):
        pn = p[idx[level0], g]
        val = y[level0]
        for failed, doubt, what in (
            (val <= gamma, pn, "failing"),
            (val > gamma, 1.0 - pn, "not failing"),
        ):
            bad = np.flatnonzero(failed & (doubt < CONTRADICTION))
            if bad.size == 0:
                continue
            worst = bad[np.argmin(doubt[bad])]
            out.append(
                f"gamma {gamma:g}: {bad.size} of {int(failed.sum())} segments observed "
                f"{what} at level 0 get probability < {CONTRADICTION:g} of that outcome "
                f"(worst {str(ids[idx[level0][worst]])!r}: value {_beside(val[worst], gamma)}, "
                f"probability {doubt[worst]:.2g}); the model explains them as noise, so the "
                "estimate's "
                "variance may be large. Check the level-0 noise in the hyperparameter table; "
                "more level-0 runs near them help"
            )
        # The model's own rate, mean p_n over the pool, below the failures already seen at
        # level 0: it cannot be right, whatever the rest of the pool holds.
        seen = np.unique(idx[level0][val <= gamma]).size
        expected = float(p[:, g].sum())
        if seen and expected < seen:
            out.append(
                f"gamma {gamma:g}: the model's own failure rate {expected / p.shape[0]:.3g} "
                f"({expected:.3g} failures expected in the pool) is below the {seen} "
                f"failure{'s' if seen != 1 else ''} already confirmed at level 0 "
                f"({seen / p.shape[0]:.3g} of the pool); trust `estimate`, not the model's "
                "rate, and check the level-0 noise in the hyperparameter table"
            )
    return out
