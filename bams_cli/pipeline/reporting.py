"""``bams-cli report``: the summary, tables and plots of a study, assembled from its state."""

from __future__ import annotations

import datetime as dt
import json
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import pyarrow as pa

from bams_cli import defaults, schemas_json
from bams_cli.errors import (
    InputError,
    OptionError,
    OptionValueError,
    StaleStateError,
)
from bams_cli.pipeline._common import SID, locked, plan_numbers, read_scores
from bams_cli.pipeline.estimation import design_note
from bams_cli.pipeline.initialise import settings_summary
from bams_cli.stages import estimate_again
from bams_cli.state import schemas
from bams_cli.state.io import (
    read_metadata,
    read_metadata_json,
    read_state,
    read_state_schema,
    read_table,
    require_columns,
    transaction,
)
from bams_cli.state.pending import to_simulate
from bams_cli.state.workspace import Workspace, stale_log


# ---------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------
@locked
def report(
    root: Path,
    *,
    truth: Path | None = None,
    n_diverse: int = defaults.DIVERSE,
    by: str | None = None,
    max_points: int = 50_000,
) -> dict[str, Any]:
    """Write report/report.html, summary.json and summary.md for the study.

    Runs at any point of a study. A model older than the observation log, batches or
    estimate plans awaiting results open the report as banners.

    Parameters
    ----------
    root : Path
        The workspace folder (``--workspace``/``-w``).
    truth : Path, optional
        Ground truth (``segment_id``, ``value_0``), e.g. for sample data: adds recall.
    n_diverse : int, default ``defaults.DIVERSE``
        How many diverse likely failures to list (``--diverse``).
    by : str, optional
        A pass-through column of the pool (a scenario tag ...) to break the failures down
        by (``--by``); default: the pool's clusters, as ``select`` forms them.
    max_points : int, default 50000
        At most this many pool points drawn in the report's scatter plots.
    wait : bool, default False
        Wait for another command's workspace lock instead of failing at once
        (``WorkspaceLockedError``).

    Returns
    -------
    dict
        The summary ``--json`` prints: ``report``, ``summary_json``, ``summary_md``,
        ``figures`` (the files written), ``notices`` (the banners), ``estimates``.

    Raises
    ------
    InputError
        ``truth`` lacks a pool segment or has a bad value.
    WorkspaceError
        No workspace.
    OptionValueError
        ``n_diverse`` below 0 or ``max_points`` below 1; exit code 2.
    OptionError
        ``by`` is not a pass-through column of the pool.
    WorkspaceLockedError
        Another command holds the lock and ``wait`` is False.
    """
    from sklearn.decomposition import PCA

    from bams_cli import __version__
    from bams_cli import report as rep
    from bams_cli.core.evaluate import batch_mean_f, dpp_diverse, retention_recall

    ws = Workspace(root)
    settings = ws.require_initialised()
    ids, X = ws.read_pool()
    n = len(ids)
    gammas = list(settings.gammas)
    log = ws.read_observations(active_only=False)
    active = log.filter(pl.col("active"))
    costs = settings.costs

    truth_f0 = None
    if truth is not None:
        tt = read_table(truth, what="truth")
        require_columns(tt, [SID, "value_0"], truth)
        tdf = pl.from_arrow(tt.select([SID, "value_0"]))
        assert isinstance(tdf, pl.DataFrame)
        tdf = tdf.with_columns(pl.col(SID).cast(pl.String))
        aligned = pl.DataFrame({SID: ids}).join(tdf, on=SID, how="left", maintain_order="left")
        if aligned["value_0"].null_count():
            first = aligned.filter(pl.col("value_0").is_null())[SID][0]
            raise InputError(truth, f"no ground truth for pool segment {first!r}", column=SID)
        truth_f0 = aligned["value_0"].to_numpy()

    per_level = {}
    for lv in range(settings.n_levels):
        count = int((log["fidelity"] == lv).sum())
        per_level[str(lv)] = {"count": count, "cost": _cost(count * costs[lv])}
    spent = {
        "per_level": per_level,
        "count": int(log.height),
        "cost": _cost(sum(v["cost"] for v in per_level.values())),
        # Every result delivered counts, a corrected one too (it may have been run again);
        # the headline says how many of them a later --replace superseded.
        "superseded": int(log.height - active.height),
    }

    model_doc = None
    unusable = None
    if ws.model_path.exists():
        # A model fitted before the latest results still describes the pool; the report
        # shows it marked stale rather than refusing (the estimate needs no refit either).
        # One fitted for other gammas does not: its p columns answer other thresholds.
        try:
            model_doc = ws.require_model(allow_newer_observations=True)
        except StaleStateError as exc:
            unusable = str(exc)
    notices = _report_model_notices(ws, model_doc, active)
    if unusable is not None:
        notices = [{"kind": "stale_model", "severity": "warning", "text": unusable}]

    pos = {sid: i for i, sid in enumerate(ids)}
    obs0 = dict(active.filter(pl.col("fidelity") == 0).select(SID, "value").iter_rows())
    known0 = np.zeros(n, bool)  # the pool's segments whose level-0 value is known
    known0[[pos[s] for s in obs0 if s in pos]] = True
    observed_pairs = active.select(SID, "fidelity").unique()
    batch_rows, batch_picks, per_batch_f = [], [], []
    waiting = []
    frames: dict[int, pl.DataFrame] = {}
    for b in ws.batch_numbers():
        df = frames[b] = ws.read_batch(b)
        gone = ws.abandoned_open("batch", b)  # requests that will never come back
        open_ = df.join(observed_pairs, on=[SID, "fidelity"], how="anti")
        pending = open_.join(gone, on=[SID, "fidelity"], how="anti").height
        if pending:
            todo = to_simulate(ws, "batch", b).relative_to(ws.root)
            waiting.append(f"batch {b} ({pending} of {df.height} picks, {todo})")
        idx = np.array([pos[s] for s in df[SID].to_list() if s in pos], dtype=np.int64)
        if truth_f0 is not None:
            f0 = truth_f0[idx]
        else:
            f0 = np.array([obs0[s] for s in df[SID].to_list() if s in obs0])
        per_batch_f.append(f0)
        batch_picks.append((b, idx))
        batch_rows.append(
            {
                "batch": b,
                "strategy": df["strategy"][0] if df.height else "",
                "picks": df.height,
                "picks_per_level": {
                    str(k): int(v)
                    for k, v in df.group_by("fidelity").len().sort("fidelity").iter_rows()
                },
                "picks_per_cluster": {
                    str(k): int(v)
                    for k, v in df.group_by("cluster").len().sort("cluster").iter_rows()
                },
                "cost": _cost(df["cost"].sum()),
                "n_f0": int(len(f0)),
                "pending": pending,
                "abandoned": gone.height,
            }
        )
    if waiting:
        notices.append(
            {
                "kind": "pending_batches",
                "severity": "info",
                "text": f"Results pending for {'; '.join(waiting)}: simulate the list named "
                f"and run `bams-cli ingest-results -w {root}`. A batch's mean level-0 f "
                "counts only the picks whose level-0 value is known.",
            }
        )
    if per_batch_f:
        means, ses = batch_mean_f(per_batch_f)
        for row, m, se in zip(batch_rows, means, ses, strict=True):
            row["mean_f0"] = None if not np.isfinite(m) else float(m)
            row["mean_f0_se"] = None if not np.isfinite(se) else float(se)

    scores = None
    if ws.scores_path.exists() and unusable is None:
        _, mu, sd, p_all = read_scores(ws, len(gammas))
        scores = (mu, sd, p_all)

    estimates, gp_rows = [], []
    plans = plan_numbers(ws)
    shown_plan = next((k for k in reversed(plans) if ws.estimate_path(k).exists()), None)
    notices += _report_plan_notices(ws, plans, shown_plan, set(obs0))
    if shown_plan is not None:
        doc = ws.read_estimate(shown_plan)  # a damaged file is named, with its fix
        # A staged estimate rests on every stage's sample so far, not the last plan alone.
        staging = doc.get("staging") or {}
        made_of = staging.get("plans") or [shown_plan]
        kind = doc.get("interval", "gamma")
        # How many of the estimate's planned stages it rests on (the headline says when
        # one remains).
        stages = {"stages_done": staging.get("stages_done", 1), "stages": staging.get("stages", 1)}
        estimates = [
            {**e, "plan": shown_plan, "plans": made_of, "interval": kind, **stages}
            for e in doc["estimates"]
        ]
        gp_rows = doc["gp"]
        # Next to the headline: discovery that went on after the estimate's sample was drawn.
        notices[:0] = _report_estimate_age(ws, max(made_of), list(frames), active)
        if ws.estimate_out_of_date(shown_plan, doc):
            plans_word = "plans" if len(made_of) > 1 else "plan"
            notices[:0] = [
                {
                    "kind": "outdated_estimate",
                    "severity": "warning",
                    "text": f"The estimate shown is out of date: results of {plans_word} "
                    f"{', '.join(map(str, made_of))} it rests on changed after it was "
                    "computed (a result corrected across a gamma, or an abandoned run "
                    f"simulated after all); `{estimate_again(ws, shown_plan, doc)}` computes "
                    "it from the results the log holds now.",
                }
            ]
    elif scores is not None:
        from bams_cli.core.estimate import gp_estimate

        for g, gamma in enumerate(gammas):
            m, bound = gp_estimate(scores[2][:, g])
            gp_rows.append({"gamma": gamma, "gp_p_hat": m, "gp_var_bound": bound})

    figures: dict[str, str] = {}
    rng = np.random.default_rng(settings.seed)
    diverse = []
    if n_diverse < 0:
        raise OptionValueError(f"--diverse {n_diverse}: must be >= 0")
    if max_points < 1:
        raise OptionValueError(f"max_points {max_points}: must be >= 1")
    if by is not None:
        _passthrough_names(ws, by)  # an unknown column fails before anything is computed
    if scores is not None:
        p0 = scores[2][:, 0]
        if X.shape[1] == 2:
            XY, projected = X, False
        else:
            fit_rows = rng.choice(n, size=min(n, max_points), replace=False)
            XY, projected = PCA(2).fit(X[fit_rows]).transform(X), True
        show = np.sort(rng.choice(n, size=min(n, max_points), replace=False))
        shown = np.zeros(n, bool)
        shown[show] = True
        for _, idx in batch_picks:
            shown[idx] = True
        keep = np.flatnonzero(shown)
        remap = np.full(n, -1)
        remap[keep] = np.arange(len(keep))
        figures["pool_map"] = rep.pool_map(
            XY[keep],
            p0[keep],
            [(b, remap[idx]) for b, idx in batch_picks],
            projected=projected,
            gamma=gammas[0],
        )
        # A likely failure is a guess about a segment's level-0 value, so a segment whose
        # level-0 value is known is never one: observed failing it is a confirmed failure
        # (listed apart), observed above every gamma it passed, whatever a model fitted
        # before that result still says.
        unknown = np.flatnonzero(~known0)
        top = unknown[np.argsort(-p0[unknown], kind="stable")[:500]]
        chosen = (
            top[dpp_diverse(X[top], p0[top], min(n_diverse, len(top)))] if n_diverse else top[:0]
        )
        cheap = active.filter(pl.col("fidelity") > 0).sort("fidelity")
        leads: dict[str, dict[str, float]] = {}
        for sid, lv, value in cheap.select(SID, "fidelity", "value").iter_rows():
            leads.setdefault(sid, {})[f"observed_f{lv}"] = float(value)
        for i, more in zip(chosen, _passthrough_rows(ws, chosen), strict=True):
            row = {SID: str(ids[i]), "p_n": float(p0[i]), "mu": float(scores[0][i])}
            row.update(leads.get(str(ids[i]), {}))
            row.update(more)
            diverse.append(row)
        diverse = _uniform_rows(diverse, blank=None)  # JSON null where a row has no such value

    # Failures seen at level 0: findings, not guesses. Those the estimate plan sampled are
    # here too; the list holds every one (it is bounded by the level-0 runs).
    confirmed = []
    fails_at = {sid: [g for g in gammas if value <= g] for sid, value in obs0.items() if sid in pos}
    failed = sorted((s for s in fails_at if fails_at[s]), key=lambda s: (obs0[s], s))
    rows_failed = np.array([pos[s] for s in failed], dtype=np.int64)
    for sid, more in zip(failed, _passthrough_rows(ws, rows_failed), strict=True):
        row = {SID: sid, "observed_f0": float(obs0[sid]), "fails_at_gamma": fails_at[sid]}
        if scores is not None:
            row["p_n"] = float(scores[2][pos[sid], 0])
        row.update(more)
        confirmed.append(row)
    confirmed = _uniform_rows(confirmed, blank=None)  # JSON null where a row has no such value
    failures = _failures_found(ws, active, gammas, pos)
    table = _failures_table(failures)  # failures.csv, and the page's table from its head
    head = rep.headline(estimates, gp_rows, failures, spent, gammas[0])
    # The model each batch and plan was chosen with (stored snapshots, by the observation
    # log they were fitted on): what it predicted before the results came in.
    models = _Models(ws, n, gammas[0])
    after = _plans_after_batch(ws, plans, frames)
    prior = _prior_p(ws, ids, models, frames, plans, gammas[0])
    trends = _trends(ws, frames, log, gammas[0], prior, pos)
    history = _estimate_history(ws, plans, gammas[0], after)
    stopping = _stopping(trends, history, scores, known0)
    spend = _spend(ws, log, costs, gammas[0], after)
    predicted = _predicted_vs_found(trends)
    p_dist = None
    if scores is not None:
        p_dist = _p_distribution(
            scores[2][:, 0], known0, active, prior, pos, _plan_of(ws), gammas[0]
        )
    groups = _groups(
        ws,
        X,
        model_doc,
        frames,
        settings.seed,
        by,
        scores,
        known0,
        log,
        failures,
        pos,
        gammas[0],
        settings.n_levels,
    )
    _model_against_estimate(groups, estimates, gammas[0], len(known0))
    if any(t["gp_rate"] is not None for t in trends) or history:
        figures["rate_band"] = rep.rate_band_plot(trends, history)
    if predicted is not None:
        figures["predicted"] = rep.predicted_plot(trends)
    if p_dist is not None:
        figures["p_distribution"] = rep.p_distribution_plot(p_dist)
    if groups is not None and groups["rows"]:
        figures["groups"] = rep.groups_plot(groups)

    truth_doc = None
    if truth_f0 is not None:
        fails = truth_f0[:, None] <= np.asarray(gammas)[None, :]
        counts = fails.sum(axis=0)
        est_recall: list[float | None] = [None] * len(gammas)
        for e in estimates:  # by gamma: the estimate may answer gammas edited since
            if e["gamma"] in gammas and counts[gammas.index(e["gamma"])]:
                g = gammas.index(e["gamma"])
                est_recall[g] = e["distinct_failures_found"] / float(counts[g])
        grid = np.linspace(0, 10, 101)
        curves = {}
        if counts[0]:
            for snap in sorted(ws.history_dir.glob("scores-after-batch-*.parquet")):
                batch = int(snap.stem.rsplit("-", 1)[1])
                p_snap = _snapshot_p(snap, gammas[0])
                if p_snap is not None and len(p_snap) == n:
                    curves[batch] = retention_recall(p_snap, fails[:, 0], grid)
        if curves:
            figures["recall"] = rep.recall_plot(curves, grid)
        truth_doc = {
            "rate": [float(c) / n for c in counts],
            "failures": [int(c) for c in counts],
            "estimate_recall": est_recall,
            "retention_recall": {
                str(b): {f"{r:g}": float(v) for r, v in zip(grid[::10], c[::10], strict=True)}
                for b, c in curves.items()
            },
        }
    if estimates:
        truth_rates = None
        if truth_doc is not None:  # by gamma, as the recall above
            rate = dict(zip(gammas, truth_doc["rate"], strict=True))  # type: ignore[call-overload]
            truth_rates = [rate.get(e["gamma"], float("nan")) for e in estimates]
        if len(estimates) > 1:  # one gamma's estimate is in the trend's plot already
            figures["rate"] = rep.rate_plot(estimates, None)
        if truth_rates is not None:  # ground truth only in its own, marked section
            figures["rate_truth"] = rep.rate_plot(estimates, truth_rates)

    out = ws.report_dir
    summary: dict[str, Any] = {
        "schema_version": schemas_json.version("summary.json"),
        "tool_version": __version__,
        "generated_at": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "workspace": str(root),
        "headline": head,
        "notices": notices,
        "study": {**settings_summary(settings), "pool_size": n, "dim": int(X.shape[1])},
        "simulation_spent": spent,
        "model": model_doc,
        "batches": batch_rows,
        "estimates": estimates,
        "estimate_history": history,
        "trends": trends,
        "stopping": stopping,
        "gp_estimate": gp_rows,
        "confirmed_failures": confirmed,
        "failures_found": {
            "csv": str(out / "failures.csv"),
            "count": len(failures),
            "confirmed": sum(1 for f in failures if f["status"] == "confirmed"),
            "leads": sum(1 for f in failures if f["status"] == "lead"),
            "columns": table.columns,
            "shown": table.head(rep.FAILURES_SHOWN).to_dicts(),
        },
        "spend": spend,
        "predicted_vs_found": predicted,
        "p_distribution": p_dist,
        "groups": groups,
        "diverse_failures": diverse,
        "truth": truth_doc,
        "figures": sorted(figures),
    }
    with transaction() as tx:
        tx.write_text(out / "report.html", rep.render_html(summary, figures))
        tx.write_with(out / "failures.csv", lambda p: table.write_csv(p))
        tx.write_text(
            out / "summary.json",
            json.dumps(summary, indent=2, default=str, allow_nan=False) + "\n",
        )
        tx.write_text(out / "summary.md", rep.render_markdown(summary))
    return {
        "report": str(out / "report.html"),
        "summary_json": str(out / "summary.json"),
        "summary_md": str(out / "summary.md"),
        "failures_csv": str(out / "failures.csv"),
        "headline": head["text"],
        "figures": sorted(figures),
        "notices": [n["text"] for n in notices],
        "estimates": [
            {k: e[k] for k in ("gamma", "p_hat", "ci_low", "ci_high")} for e in estimates
        ],
    }


def _report_model_notices(
    ws: Workspace, model: dict[str, Any] | None, active: pl.DataFrame
) -> list[dict[str, str]]:
    """What the report must say first about the model: missing, or older than the log."""
    fit = f"`bams-cli fit -w {ws.root}`"
    if model is None:
        return [
            {
                "kind": "no_model",
                "severity": "info",
                "text": f"No model yet: once results are ingested, run {fit} for failure "
                "probabilities, the pool map and the likely failures.",
            }
        ]
    if model["fresh"]:
        return []
    fitted = int(sum(model.get("n_observations_per_level", [])))
    return [
        {
            "kind": "stale_model",
            "severity": "warning",
            "text": f"Stale model: {stale_log(fitted, active.height)}. Failure probabilities, "
            "the pool map, the likely failures' ranking and the GP's estimate are that "
            f"fit's and miss the newer results; run {fit} to bring them up to date.",
        }
    ]


def _report_plan_notices(
    ws: Workspace, plans: list[int], shown: int | None, known0: set[str]
) -> list[dict[str, str]]:
    """One notice per estimate plan newer than the estimate shown: results or compute due."""
    out = []
    picks = ws.read_plan_picks()
    for k in plans:
        if shown is not None and k <= shown:
            continue
        sampled = picks.filter(pl.col("plan") == k)[SID].to_list()
        gone = set(ws.abandoned_open("plan", k)[SID].to_list())
        missing = sum(s not in known0 and s not in gone for s in sampled)
        shown_text = (
            "no estimate is shown yet" if shown is None else f"the estimate shown is plan {shown}'s"
        )
        if missing:
            text = (
                f"Estimate plan {k} awaits level-0 results for {missing} of its {len(sampled)} "
                f"sampled segments ({to_simulate(ws, 'plan', k).relative_to(ws.root)}); "
                f"{shown_text}."
            )
        elif gone:
            text = (
                f"Estimate plan {k} has its results but {len(gone)} of its sampled segments "
                f"were abandoned: run `bams-cli estimate -w {ws.root} --failed-as bounds` for "
                f"the worst-case interval over them; {shown_text}."
            )
        else:
            text = (
                f"Estimate plan {k} has all its results: run `bams-cli estimate -w {ws.root}` "
                f"to compute it; {shown_text}."
            )
        out.append({"kind": "pending_plan", "severity": "info", "text": text})
    for k in plans[-1:]:
        note = design_note(read_metadata_json(ws.estimates_dir / f"plan-{k:04d}.parquet"))
        if note:
            out.append({"kind": "design_like_uniform", "severity": "info", "text": note + "."})
    return out


def _report_estimate_age(
    ws: Workspace, plan: int, batches: list[int], active: pl.DataFrame
) -> list[dict[str, str]]:
    """A notice when discovery went on after ``plan``, the last the estimate shown rests
    on, was drawn (by the times the state files record): batches selected since, or
    discovery results ingested since. The estimate's rate does not count them, however
    recently it was computed: its known stratum is fixed when its plan is drawn."""
    drawn = read_metadata(ws.estimates_dir / f"plan-{plan:04d}.parquet").get("written_at")
    if not drawn:
        return []  # a plan of an older version: when it was drawn is not known
    later = [
        b
        for b in batches
        if read_metadata(schemas.batch_path(ws.root, b)).get("written_at", "") > drawn
    ]
    results = active.filter(pl.col("batch").is_not_null() & (pl.col("ingested_at") > drawn))
    parts = []
    if later:
        parts.append(
            f"batch {later[0]} was selected"
            if len(later) == 1
            else f"batches {later[0]} {'and' if len(later) == 2 else 'to'} {later[-1]} were selected"
        )
    if results.height:
        n = results.height
        parts.append(f"{n} discovery result{'s were' if n != 1 else ' was'} ingested")
    if not parts:
        return []
    return [
        {
            "kind": "stale_estimate",
            "severity": "warning",
            "text": f"The estimate shown predates the latest discovery: {' and '.join(parts)} "
            f"after plan {plan}, on which it rests, was drawn, and its rate does not count "
            f"them; `bams-cli estimate -w {shlex.quote(str(ws.root))} --plan` draws a new sample "
            "that does.",
        }
    ]


def _passthrough_rows(ws: Workspace, rows: np.ndarray) -> list[dict[str, Any]]:
    """The pool's pass-through columns (scenario tags, difficulty ...) of some pool rows."""
    segs = ws.read_segments()
    cols = [c for c in segs.column_names if c != SID and c not in ws.coordinate_columns(segs)]
    if not cols:
        return [{} for _ in rows]
    return [
        {k: (round(v, 6) if isinstance(v, float) else v) for k, v in r.items()}
        for r in segs.select(cols).take(pa.array(rows, type=pa.int64())).to_pylist()
    ]


def _passthrough_names(ws: Workspace, by: str | None = None) -> list[str]:
    """The pool's pass-through columns; with ``by``, insist it is one of them."""
    segs_schema = ws.read_segments().schema
    coords = set(ws.coordinate_columns())
    names = [c for c in segs_schema.names if c != SID and c not in coords]
    if by is not None and by not in names:
        have = ", ".join(names) if names else "none (embed-reduce passes them through)"
        raise OptionError(f"--by {by!r}: not a pass-through column of the pool; it has {have}")
    return names


#: A pass-through column with more distinct values than this is grouped: numbers into
#: quantile bins (``GROUP_BINS``), other values into the largest groups and "other".
GROUP_MAX = 12
GROUP_BINS = 5


def _column_groups(ws: Workspace, by: str) -> tuple[np.ndarray, list[dict[str, Any]], str]:
    """Each pool segment's group by the pass-through column ``by``: the group index per
    row, the groups (``group`` label, and ``low``/``high`` for a numeric column's quantile
    bins: low <= value < high, the last bin closed), and how they were formed."""
    col = ws.read_segments([SID, by]).column(by)
    values = col.to_pylist()
    numeric = pa.types.is_integer(col.type) or pa.types.is_floating(col.type)
    distinct = {v for v in values if v is not None}
    if numeric and len(distinct) > GROUP_MAX:
        v = np.array([np.nan if x is None else float(x) for x in values])
        finite = v[np.isfinite(v)]
        edges = np.unique(np.quantile(finite, np.linspace(0, 1, GROUP_BINS + 1)))
        inner = edges[1:-1]
        label = np.where(np.isfinite(v), np.searchsorted(inner, v, side="right"), len(edges) - 1)
        groups = [
            {"group": f"{lo:.3g} to {hi:.3g}", "low": float(lo), "high": float(hi)}
            for lo, hi in zip(edges[:-1], edges[1:], strict=True)
        ]
        if not np.isfinite(v).all():
            groups.append({"group": "(none)", "low": None, "high": None})
        how = f"{len(edges) - 1} quantile bins of {by} (low <= {by} < high; the last closed)"
        return label.astype(np.int64), groups, how
    names = ["(none)" if x is None else str(x) for x in values]
    counts: dict[str, int] = {}
    for name in names:
        counts[name] = counts.get(name, 0) + 1
    ranked = sorted(counts, key=lambda k: (-counts[k], k))
    keep = ranked if len(ranked) <= GROUP_MAX else ranked[: GROUP_MAX - 1]
    labels = sorted(keep) + ([] if len(keep) == len(ranked) else ["other"])
    index = {name: i for i, name in enumerate(labels)}
    other = index.get("other", -1)
    label = np.array([index.get(name, other) for name in names], dtype=np.int64)
    how = (
        f"each value of {by}"
        if len(keep) == len(ranked)
        else f"the {len(keep)} largest groups of {by}, and the rest as other"
    )
    return label, [{"group": g} for g in labels], how


def _select_clustering(
    ws: Workspace, frames: dict[int, Any], n: int, n_levels: int
) -> tuple[int, int | None]:
    """How many clusters the latest BAMS/BAS batch's greedy ran on, and the K-means sample
    size it clustered on (None: every point).

    The batch's recorded plan when it has one; else (batches from before plans were
    recorded) ``plan_selection`` from its options, as ``select`` would have planned: the
    approximate plan runs on more clusters than --clusters once the pool is large.
    """
    from bams_cli.core.select import plan_selection
    from bams_cli.pipeline.selection import GREEDY_PLANS

    clusters, greedy = defaults.CLUSTERS, defaults.GREEDY.value
    for b in sorted(frames, reverse=True):
        meta = read_metadata_json(schemas.batch_path(ws.root, b))
        options = meta.get("options") or {}
        if options.get("strategy") not in ("bams", "bas"):
            continue
        taken = meta.get("selection_plan") or {}
        if isinstance(taken.get("clusters"), int) and taken["clusters"] >= 1:
            sample = taken.get("cluster_fit_sample")
            return taken["clusters"], sample if isinstance(sample, int) and sample > 0 else None
        clusters = int(options.get("clusters", clusters))
        greedy = str(options.get("greedy", greedy))
        break
    plan = plan_selection(n, n_levels, clusters, approximate=GREEDY_PLANS.get(greedy, "auto"))
    return plan.n_clusters, plan.cluster_fit_max


def _groups(
    ws: Workspace,
    X: np.ndarray,
    model: dict[str, Any] | None,
    frames: dict[int, pl.DataFrame],
    seed: int,
    by: str | None,
    scores: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    known0: np.ndarray,
    log: pl.DataFrame,
    failures: list[dict[str, Any]],
    pos: dict[str, int],
    gamma: float,
    n_levels: int,
) -> dict[str, Any] | None:
    """The study per part of the pool: by the pass-through column ``by``, else by the
    pool's clusters as ``select`` forms them (K-means on the pool scaled by the model's
    level-0 lengthscales, merged down to the latest BAMS batch's --clusters, else the
    default). Per group: its size, the failures the model expects in it (sum of p_n) and
    among the segments not yet run at level 0, the runs spent per level, the level-0
    failures confirmed at the first gamma and the leads. None without a model and ``by``."""
    from bams_cli.core.cluster import cluster_pool

    n = len(X)
    if by is not None:
        label, groups, how = _column_groups(ws, by)
        kind = "column"
    elif model is not None:
        lengthscales = np.asarray(model["hyperparameters"]["lengthscales0"], dtype=np.float64)
        clusters, fit_max = _select_clustering(ws, frames, n, n_levels)
        label = cluster_pool(
            X,
            lengthscales,
            clusters,
            rng=np.random.default_rng([seed, 0x5E1EC7]),
            fit_max=fit_max,
        )
        groups = [{"group": f"cluster {c}"} for c in range(int(label.max()) + 1)]
        how = (
            f"{len(groups)} clusters of the pool, formed as select forms them (K-means on the "
            "pool scaled by the model's level-0 lengthscales, merged down)"
        )
        kind = "clusters"
    else:
        return None
    g = len(groups)
    size = np.bincount(label, minlength=g)
    expected = unconfirmed = None
    if scores is not None:
        p0 = scores[2][:, 0]
        expected = np.bincount(label, weights=p0, minlength=g)
        unconfirmed = np.bincount(label[~known0], weights=p0[~known0], minlength=g)
    runs = np.zeros((g, n_levels), dtype=np.int64)
    for sid, lv in log.select(SID, "fidelity").iter_rows():
        if sid in pos:
            runs[label[pos[sid]], lv] += 1
    confirmed = np.zeros(g, dtype=np.int64)
    leads = np.zeros(g, dtype=np.int64)
    for f in failures:
        if f[SID] not in pos:
            continue
        if f["status"] == "confirmed" and gamma in f["fails_at"]:
            confirmed[label[pos[f[SID]]]] += 1
        elif f["status"] == "lead":
            leads[label[pos[f[SID]]]] += 1
    rows = []
    for i, group in enumerate(groups):
        rows.append(
            {
                **group,
                "size": int(size[i]),
                "expected_failures": None if expected is None else float(expected[i]),
                "expected_unconfirmed": None if unconfirmed is None else float(unconfirmed[i]),
                "runs_per_level": {str(lv): int(c) for lv, c in enumerate(runs[i])},
                "confirmed": int(confirmed[i]),
                "leads": int(leads[i]),
            }
        )
    return {"by": by if by is not None else "cluster", "kind": kind, "how": how, "rows": rows}


def _model_against_estimate(
    groups: dict[str, Any] | None, estimates: list[dict[str, Any]], gamma: float, n: int
) -> None:
    """Set ``groups["caveat"]`` when the model's expected failures, summed over the pool,
    lie outside the estimate's interval: the breakdown's numbers are the model's alone, and
    a trial's breakdown put 0.6 unconfirmed failures in a group that held 54 while the
    estimate beside it was right."""
    if groups is None or not groups["rows"]:
        return
    if any(r["expected_failures"] is None for r in groups["rows"]):
        return
    e = next((e for e in estimates if e.get("gamma") == gamma), None)
    if e is None or e.get("ci_low") is None or e.get("ci_high") is None or e.get("p_hat") is None:
        return
    model = sum(r["expected_failures"] for r in groups["rows"])
    lo, hi, est = e["ci_low"] * n, e["ci_high"] * n, e["p_hat"] * n
    if lo <= model <= hi:
        return
    side = "below" if model < lo else "above"
    groups["caveat"] = (
        f"The model expects {model:.3g} failures in the pool, {side} the estimate's "
        f"{est:.3g} ({lo:.3g} to {hi:.3g}): its expected failures per group are the model's "
        "alone and miss that difference; read them as where the model looks, not as counts"
    )


def _uniform_rows(rows: list[dict[str, Any]], blank: Any = "") -> list[dict[str, Any]]:
    """Rows with one key set (segment_id first, then sorted), ``blank`` where a row lacks
    one (None for a table whose columns must keep their type: a number column with "" in
    it would be read back as text)."""
    keys = sorted({k for r in rows for k in r}, key=lambda k: (k != SID, k))
    return [{k: r.get(k, blank) for k in keys} for r in rows]


def _failures_found(
    ws: Workspace, active: pl.DataFrame, gammas: list[float], pos: dict[str, int]
) -> list[dict[str, Any]]:
    """Every failure the study has seen, one row per segment: ``confirmed`` (its level-0
    value is at or below a gamma) or ``lead`` (a cheaper level failed at the first gamma and
    level 0 has not run). With its value at each level run, the batch or plan whose
    request found it, and the segment's pass-through columns (``report/failures.csv``)."""
    if not active.height:
        return []
    plan_of = _plan_of(ws)
    values: dict[str, dict[int, tuple[float, int | None]]] = {}
    for sid, lv, value, batch in active.select(SID, "fidelity", "value", "batch").iter_rows():
        values.setdefault(sid, {})[int(lv)] = (float(value), batch)
    top = max(gammas)
    rows = []
    for sid, by_level in values.items():
        if sid not in pos:
            continue
        if 0 in by_level:
            if by_level[0][0] > top:
                continue
            status, level = "confirmed", 0
        else:
            cheap = [lv for lv, (v, _) in by_level.items() if v <= gammas[0]]
            if not cheap:
                continue
            status, level = "lead", min(cheap)
        batch = by_level[level][1]
        found_by = (
            f"batch {batch}"
            if batch is not None
            else (f"plan {plan_of[sid]}" if sid in plan_of else "results not asked for")
        )
        row: dict[str, Any] = {
            SID: sid,
            "status": status,
            "found_by": found_by,
            "fails_at": [g for g in gammas if by_level[level][0] <= g],
        }
        for lv in sorted(by_level):
            row[f"value_{lv}"] = by_level[lv][0]
        rows.append(row)
    rows.sort(
        key=lambda r: (
            r["status"] != "confirmed",
            min(r[k] for k in r if k.startswith("value_")),
            r[SID],
        )
    )
    index = np.array([pos[r[SID]] for r in rows], dtype=np.int64)
    for row, more in zip(rows, _passthrough_rows(ws, index), strict=True):
        row.update(more)
    return _uniform_rows(rows, blank=None)


def _failures_table(failures: list[dict[str, Any]]) -> pl.DataFrame:
    """The failures found as one frame: report/failures.csv, and the page's table its head.
    segment_id, status, found_by, fails_at (the gammas, ";"-joined), value_0, value_1 ...,
    then the pass-through columns."""
    table = pl.DataFrame(
        [{k: (";".join(f"{g:g}" for g in v) if k == "fails_at" else v) for k, v in r.items()}
         for r in failures] if failures else None,
        schema=None if failures else {SID: pl.String, "status": pl.String, "found_by": pl.String},
        infer_schema_length=None,
    )  # fmt: skip
    first = [SID, "status", "found_by", "fails_at"]
    values = sorted((c for c in table.columns if c.startswith("value_")), key=lambda c: int(c[6:]))
    order = [c for c in first if c in table.columns] + values
    return table.select(order + [c for c in table.columns if c not in order])


def _cost(total: Any) -> float:
    """A sum of run costs to 12 significant digits: 0.1 added 200 times is 20, not
    19.999999999999993, in summary.json as on the page."""
    return float(f"{float(total):.12g}")


def _snapshot_p(path: Path, gamma: float) -> np.ndarray | None:
    """A stored model's failure probabilities at ``gamma``, from the column its metadata
    gives that gamma (the p_<k> columns follow the gammas of its fit, which an edit of
    settings.toml may have reordered since); None when it was fitted without it."""
    gammas = read_metadata_json(path).get("gammas")
    if not isinstance(gammas, list):  # written before snapshots recorded their gammas
        col = "p_0"
    elif float(gamma) in (known := [float(g) for g in gammas]):
        col = f"p_{known.index(float(gamma))}"
    else:
        return None
    return read_state(path, columns=[col]).column(col).to_numpy()


class _Models:
    """The level-0 failure probabilities p_0 of every stored model (the snapshots in
    ``history/`` and the current scores), by the hash of the observation log each was
    fitted on; a column is read when first asked for. Models fitted for another first
    gamma, or on another pool size, are left out."""

    def __init__(self, ws: Workspace, n: int, gamma: float):
        self.n = n
        self.path: dict[str, Path] = {}
        self.after_batch: dict[int, str] = {}  # batch -> hash of the snapshot after it
        self._p: dict[str, np.ndarray | None] = {}
        snaps = sorted(ws.history_dir.glob("scores-after-batch-*.parquet"))
        for path in [*snaps, ws.scores_path]:
            if not path.exists():
                continue
            meta = read_metadata_json(path)
            h, gammas = meta.get("observations_hash"), meta.get("gammas")
            if not h or not isinstance(gammas, list) or not gammas or gammas[0] != gamma:
                continue
            self.path.setdefault(str(h), path)
            if path != ws.scores_path:
                tail = path.stem.rsplit("-", 1)[1]
                if tail.isdigit():
                    self.after_batch[int(tail)] = str(h)

    def p0(self, h: str | None) -> np.ndarray | None:
        if not h or h not in self.path:
            return None
        if h not in self._p:
            p = read_state(self.path[h], columns=["p_0"]).column("p_0").to_numpy()
            self._p[h] = p if len(p) == self.n else None
        return self._p[h]


def _prior_p(
    ws: Workspace,
    ids: np.ndarray,
    models: _Models,
    frames: dict[int, pl.DataFrame],
    plans: list[int],
    gamma: float,
) -> dict[tuple[str, int], tuple[str, np.ndarray]]:
    """For each batch and estimate plan (``("batch", b)``, ``("plan", k)``), the p_0 over
    the pool that a model fitted before its results gave, and which model that was: the
    one that chose it (by the hash the batch or plan records), else for a batch the
    snapshot after the latest earlier batch, else for a plan the p_n it stored when drawn
    (at the first gamma only). Batches and plans without one are left out."""
    out: dict[tuple[str, int], tuple[str, np.ndarray]] = {}
    for b in frames:
        meta = read_metadata_json(schemas.batch_path(ws.root, b))
        p = models.p0(meta.get("model_hash"))
        if p is not None:
            out[("batch", b)] = ("the model that chose it", p)
            continue
        earlier = [k for k in models.after_batch if k < b]
        if earlier:
            k = max(earlier)
            p = models.p0(models.after_batch[k])
            if p is not None:
                out[("batch", b)] = (f"the model fitted after batch {k}", p)
    pos = {sid: i for i, sid in enumerate(ids)}
    for k in plans:
        path = ws.estimates_dir / f"plan-{k:04d}.parquet"
        meta = read_metadata_json(path)
        p = models.p0(meta.get("model_hash"))
        if p is not None:
            out[("plan", k)] = ("the model that drew it", p)
        elif meta.get("plan_gamma") == gamma and "p_n" in read_state_schema(path).names:
            # That model is gone (refitted since); the plan kept its p_n at its own rows.
            rows = read_state(path, columns=[SID, "p_n"])
            p = np.full(models.n, np.nan)
            for sid, value in zip(rows.column(SID).to_pylist(), rows.column("p_n").to_pylist(),
                                  strict=True):  # fmt: skip
                if sid in pos:
                    p[pos[sid]] = value
            out[("plan", k)] = ("the p_n the plan stored when drawn", p)
    return out


def _plans_after_batch(
    ws: Workspace, plans: list[int], frames: dict[int, pl.DataFrame]
) -> dict[int, int]:
    """Each estimate plan's place among the batches: the last batch written before it (0:
    none), by the times the state files record."""
    written = {
        b: read_metadata(schemas.batch_path(ws.root, b)).get("written_at", "") for b in frames
    }
    out = {}
    for k in plans:
        at = read_metadata(ws.estimates_dir / f"plan-{k:04d}.parquet").get("written_at", "")
        out[k] = max((b for b, w in written.items() if w and at and w <= at), default=0)
    return out


def _result_source(ws: Workspace, log: pl.DataFrame) -> pl.Series:
    """For each row of the log: "batch", "plan" (a level-0 result an estimate plan asked
    for) or "other" (results nobody asked for, ingested with --allow-unselected)."""
    picks = ws.read_plan_picks()
    planned = set(picks[SID].to_list()) if picks.height else set()
    return pl.Series(
        "source",
        [
            "batch" if b is not None else ("plan" if lv == 0 and sid in planned else "other")
            for sid, lv, b in log.select(SID, "fidelity", "batch").iter_rows()
        ],
        dtype=pl.String,
    )


def _plan_of(ws: Workspace) -> dict[str, int]:
    """The estimate plan that asked for each segment's level-0 run (the first, if several)."""
    plan_of: dict[str, int] = {}
    picks = ws.read_plan_picks()
    if picks.height:
        for sid, k in picks.select(SID, "plan").iter_rows():
            plan_of.setdefault(sid, int(k))
    return plan_of


def _trends(
    ws: Workspace,
    frames: dict[int, pl.DataFrame],
    log: pl.DataFrame,
    gamma: float,
    prior: dict[tuple[str, int], tuple[str, np.ndarray]],
    pos: dict[str, int],
) -> list[dict[str, Any]]:
    """One row per batch: its cost per level (requested, and spent: results in), the
    level-0 failures it confirmed (and all so far), the failures the model expected among
    those level-0 results before they came in (the sum of its p_0 there, with the sd of
    that count), the model's rate after it (mean p_n of the snapshot fitted on its
    results, with the Proposition-1 bound on its sd), and the pool's J before and after it
    (batches written before bams-cli stored J leave those null)."""
    from bams_cli.core.gp_rate import gp_estimate

    active = log.filter(pl.col("active"))
    level0 = active.filter(pl.col("fidelity") == 0)
    active0 = level0.filter(pl.col("value") <= gamma)
    rows, seen = [], set()
    for b, df in frames.items():
        meta = read_metadata_json(schemas.batch_path(ws.root, b))
        per_level = {
            str(int(k)): _cost(v)
            for k, v in df.group_by("fidelity")
            .agg(pl.col("cost").sum())
            .sort("fidelity")
            .iter_rows()
        }
        spent_per_level = {
            str(int(k)): int(v)
            for k, v in log.filter(pl.col("batch") == b)
            .group_by("fidelity")
            .len()
            .sort("fidelity")
            .iter_rows()
        }
        new = set(active0.filter(pl.col("batch") == b)[SID].to_list())
        seen |= new
        jb, ja = meta.get("j_before"), meta.get("j_after")
        cost = _cost(df["cost"].sum())
        results0 = [pos[s] for s in level0.filter(pl.col("batch") == b)[SID].unique().to_list()
                    if s in pos]  # fmt: skip
        row: dict[str, Any] = {
            "batch": b,
            "cost": cost,
            "cost_per_level": per_level,
            "runs_per_level": spent_per_level,
            "level0_results": len(results0),
            "confirmed": len(new),
            "confirmed_so_far": len(seen),
            "predicted_failures": None,
            "predicted_sd": None,
            "predicted_by": None,
            "j_before": jb,
            "j_after": ja,
            "j_decrease_per_cost": (jb - ja) / cost
            if jb is not None and ja is not None and cost > 0
            else None,
            "gp_rate": None,
            "gp_sd_bound": None,
        }
        if ("batch", b) in prior and results0:  # a prediction needs level-0 results
            by, p = prior[("batch", b)]
            q = p[np.asarray(results0, dtype=np.int64)]
            row["predicted_failures"] = float(q.sum())
            row["predicted_sd"] = float(np.sqrt(np.sum(q * (1 - q))))
            row["predicted_by"] = by
        snap = ws.history_dir / f"scores-after-batch-{b:04d}.parquet"
        p_snap = _snapshot_p(snap, gamma) if snap.exists() else None
        if p_snap is not None:
            m, bound = gp_estimate(p_snap)
            row["gp_rate"], row["gp_sd_bound"] = m, float(np.sqrt(bound))
        rows.append(row)
    return rows


def _predicted_vs_found(trends: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Over the batches with a model before their results: the level-0 failures that model
    expected among their level-0 results, with its sd (a sum of independent Bernoullis),
    and the failures found there."""
    rows = [t for t in trends if t["predicted_failures"] is not None]
    if not rows:
        return None
    return {
        "batches": [t["batch"] for t in rows],
        "level0_results": sum(t["level0_results"] for t in rows),
        "predicted": float(sum(t["predicted_failures"] for t in rows)),
        "predicted_sd": float(np.sqrt(sum(t["predicted_sd"] ** 2 for t in rows))),
        "found": sum(t["confirmed"] for t in rows),
    }


def _spend(
    ws: Workspace,
    log: pl.DataFrame,
    costs: Sequence[float],
    gamma: float,
    after: dict[int, int],
) -> dict[str, Any]:
    """The runs spent (every result in the log, as the headline counts them), apart by
    what asked for them: discovery batches, estimate plans (each plan on its own, with the
    level-0 failures among its results), and results nobody asked for."""
    source = _result_source(ws, log)
    tagged = log.with_columns(source)

    def per_level(rows: pl.DataFrame) -> dict[str, Any]:
        counts = dict(rows.group_by("fidelity").len().iter_rows())
        levels = {
            str(lv): {"count": int(counts.get(lv, 0)), "cost": _cost(counts.get(lv, 0) * costs[lv])}
            for lv in range(len(costs))
        }
        return {
            "per_level": levels,
            "count": rows.height,
            "cost": _cost(sum(v["cost"] for v in levels.values())),
        }

    plan_of = _plan_of(ws)
    estimate = tagged.filter(pl.col("source") == "plan")
    by_plan = estimate.with_columns(
        pl.Series("plan", [plan_of[s] for s in estimate[SID].to_list()], dtype=pl.Int64)
    )
    plans = []
    for k in sorted(after):
        rows = by_plan.filter(pl.col("plan") == k)
        failed = rows.filter(pl.col("active") & (pl.col("value") <= gamma))[SID].n_unique()
        plans.append({"plan": k, "after_batch": after[k], **per_level(rows), "confirmed": failed})
    return {
        "discovery": per_level(tagged.filter(pl.col("source") == "batch")),
        "estimate": per_level(estimate),
        "other": per_level(tagged.filter(pl.col("source") == "other")),
        "plans": plans,
    }


#: Bins of the p_n distribution: [0, 1e-6), then four a decade up to 1 (1 itself included).
P_EDGES = np.concatenate([[0.0], np.logspace(-6, 0, 25)])


def _p_distribution(
    p0: np.ndarray,
    known0: np.ndarray,
    active: pl.DataFrame,
    prior: dict[tuple[str, int], tuple[str, np.ndarray]],
    pos: dict[str, int],
    plan_of: dict[str, int],
    gamma: float,
) -> dict[str, Any]:
    """The model's p_n over the pool, binned on a log scale (``P_EDGES``): every segment,
    those whose level-0 value is unknown and the failures the model expects among them
    (sum of p_n per bin); and the level-0 results of batches and plans at the p_n a model
    gave them before they came in, with the failures among them."""
    edges = P_EDGES

    def binned(p: np.ndarray, weights: np.ndarray | None = None) -> list[float]:
        h, _ = np.histogram(np.clip(p, 0.0, 1.0), bins=edges, weights=weights)
        return h.tolist()

    unknown = p0[~known0]
    level0 = active.filter(pl.col("fidelity") == 0)
    run_p, run_failed, without = [], [], 0
    for sid, value, batch in level0.select(SID, "value", "batch").iter_rows():
        if sid not in pos:
            continue
        key = ("batch", int(batch)) if batch is not None else ("plan", plan_of.get(sid, -1))
        if key not in prior:
            without += 1
            continue
        run_p.append(prior[key][1][pos[sid]])
        run_failed.append(value <= gamma)
    rp, rf = np.asarray(run_p, float), np.asarray(run_failed, bool)
    return {
        "gamma": gamma,
        "edges": edges.tolist(),
        "pool": [int(c) for c in binned(p0)],
        "unknown": [int(c) for c in binned(unknown)],
        "expected_failures": binned(unknown, unknown),
        "runs": [int(c) for c in binned(rp)],
        "runs_failed": [int(c) for c in binned(rp[rf])],
        "runs_without_prior": without,
    }


def _estimate_history(
    ws: Workspace, plans: list[int], gamma: float, after: dict[int, int]
) -> list[dict[str, Any]]:
    """Every estimate computed, oldest first, at the first gamma: with its interval's kind,
    the plans its sample rests on, and the last batch written before its plan."""
    out = []
    for k in plans:
        if not ws.estimate_path(k).exists():
            continue
        doc = ws.read_estimate(k)
        e = next((r for r in doc["estimates"] if r["gamma"] == gamma), None)
        if e is None:
            continue
        out.append(
            {
                "plan": k,
                "plans": (doc.get("staging") or {}).get("plans") or [k],
                "after_batch": after.get(k, 0),
                "design": doc.get("design"),
                "interval": doc.get("interval", "gamma"),
                "samples_K": doc.get("samples_K"),
                **{
                    key: e.get(key)
                    for key in (
                        "p_hat",
                        "ci_low",
                        "ci_high",
                        "confidence",
                        "n_sampled",
                        "failures_sampled",
                    )
                },
            }
        )
    return out


def _stopping(
    trends: list[dict[str, Any]],
    history: list[dict[str, Any]],
    scores: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    known0: np.ndarray,
) -> dict[str, Any]:
    """When to stop: what the last batches bought, what the next could find, and what a
    tighter estimate would cost."""
    last = [r["j_decrease_per_cost"] for r in trends[-3:] if r["j_decrease_per_cost"] is not None]
    expected = None
    if scores is not None:
        p0 = scores[2][:, 0][~known0]
        top = np.sort(p0)[::-1][: int(defaults.BUDGET)]
        expected = float(top.sum())
    k_needed = None
    if history:
        h = history[-1]
        width, rate, K = h["ci_high"] - h["ci_low"], h["p_hat"], h.get("samples_K")
        if K and rate and rate > 0 and width > 0:
            # The interval narrows as 1/sqrt(K): the K for a width equal to the rate itself.
            k_needed = float(np.ceil(K * (width / rate) ** 2))
    return {
        "j_decrease_per_cost_last_batches": last,
        "expected_failures_next_batch": expected,
        "next_batch_level0_runs": int(defaults.BUDGET),
        "samples_for_width_equal_to_rate": k_needed,
    }
