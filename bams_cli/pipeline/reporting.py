"""``bams-cli report``: the summary, tables and plots of a study, assembled from its state."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import pyarrow as pa

from bams_cli import schemas_json
from bams_cli.errors import (
    InputError,
    StaleStateError,
    WorkspaceError,
)
from bams_cli.pipeline._common import SID, locked, plan_numbers, read_scores
from bams_cli.pipeline.estimation import design_note
from bams_cli.pipeline.initialise import settings_summary
from bams_cli.state import schemas
from bams_cli.state.io import (
    read_metadata_json,
    read_state,
    read_table,
    require_columns,
    transaction,
)
from bams_cli.state.workspace import Workspace


# ---------------------------------------------------------------------------------------
# report
# ---------------------------------------------------------------------------------------
@locked
def report(
    root: Path,
    *,
    truth: Path | None = None,
    n_diverse: int = 5,
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
    n_diverse : int, default 5
        How many diverse likely failures to list (``--diverse``).
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
        No workspace, ``n_diverse`` below 0 or ``max_points`` below 1.
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
        per_level[str(lv)] = {"count": count, "cost": count * costs[lv]}
    spent = {
        "per_level": per_level,
        "count": int(log.height),
        "cost": float(sum(v["cost"] for v in per_level.values())),
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
            waiting.append(f"batch {b} ({pending} of {df.height} picks, batches/batch-{b:04d}.csv)")
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
                "cost": float(df["cost"].sum()),
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
                "text": f"Results pending for {'; '.join(waiting)}: simulate the hand-off "
                f"list and run `bams-cli ingest-results -w {root}`. A batch's mean level-0 f "
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
        made_of = (doc.get("staging") or {}).get("plans") or [shown_plan]
        estimates = [{**e, "plan": shown_plan, "plans": made_of} for e in doc["estimates"]]
        gp_rows = doc["gp"]
    elif scores is not None:
        from bams_cli.core.estimate import gp_estimate

        for g, gamma in enumerate(gammas):
            m, bound = gp_estimate(scores[2][:, g])
            gp_rows.append({"gamma": gamma, "gp_p_hat": m, "gp_var_bound": bound})

    figures: dict[str, str] = {}
    rng = np.random.default_rng(settings.seed)
    diverse = []
    if n_diverse < 0 or max_points < 1:
        raise WorkspaceError(f"--diverse {n_diverse}: must be >= 0")
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
        diverse = _uniform_rows(diverse)

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
    confirmed = _uniform_rows(confirmed)
    failures = _failures_found(ws, active, gammas, pos)
    head = rep.headline(estimates, gp_rows, failures, spent, gammas[0])
    trends = _trends(ws, frames, log, gammas[0])
    history = _estimate_history(ws, plans, gammas[0])
    stopping = _stopping(trends, history, scores, known0)

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
                p_snap = read_state(snap, columns=["p_0"]).column("p_0").to_numpy()
                if len(p_snap) == n:
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
        figures["rate"] = rep.rate_plot(estimates, truth_rates)

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
        "failures_found": {"csv": str(out / "failures.csv"), "count": len(failures)},
        "diverse_failures": diverse,
        "truth": truth_doc,
        "figures": sorted(figures),
    }
    table = pl.DataFrame(
        [{k: (";".join(f"{g:g}" for g in v) if k == "fails_at" else v) for k, v in r.items()}
         for r in failures] if failures else None,
        schema=None if failures else {SID: pl.String, "status": pl.String, "found_by": pl.String},
        infer_schema_length=None,
    )  # fmt: skip
    first = [SID, "status", "found_by", "fails_at"]
    values = sorted((c for c in table.columns if c.startswith("value_")), key=lambda c: int(c[6:]))
    order = [c for c in first if c in table.columns] + values
    table = table.select(order + [c for c in table.columns if c not in order])
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
            "text": f"Stale model: the observation log changed after the last fit (fitted on "
            f"{fitted} results, the log now holds {active.height}). Failure probabilities, "
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
                f"sampled segments (estimates/plan-{k:04d}-handoff.csv); {shown_text}."
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


def _uniform_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Rows with one key set (segment_id first, then sorted), blanks where a row lacks one."""
    keys = sorted({k for r in rows for k in r}, key=lambda k: (k != SID, k))
    return [{k: r.get(k, "") for k in keys} for r in rows]


def _failures_found(
    ws: Workspace, active: pl.DataFrame, gammas: list[float], pos: dict[str, int]
) -> list[dict[str, Any]]:
    """Every failure the study has seen, one row per segment: ``confirmed`` (its level-0
    value is at or below a gamma) or ``lead`` (a cheaper level failed at the first gamma and
    level 0 has not run). With its value at each level run, the batch or plan whose
    request found it, and the segment's pass-through columns (``report/failures.csv``)."""
    if not active.height:
        return []
    plan_of: dict[str, int] = {}
    picks = ws.read_plan_picks()
    if picks.height:
        for sid, k in picks.select(SID, "plan").iter_rows():
            plan_of.setdefault(sid, int(k))
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
    return _uniform_rows(rows)


def _trends(
    ws: Workspace, frames: dict[int, pl.DataFrame], log: pl.DataFrame, gamma: float
) -> list[dict[str, Any]]:
    """One row per batch: its cost per level, the level-0 failures it confirmed (and all so
    far), the model's rate after it (mean p_n of the snapshot fitted on its results, with
    the Proposition-1 bound on its sd), and the pool's J before and after it (batches
    written before bams-cli stored J leave those null)."""
    from bams_cli.core.gp_rate import gp_estimate

    active0 = log.filter(pl.col("active") & (pl.col("fidelity") == 0) & (pl.col("value") <= gamma))
    rows, seen = [], set()
    for b, df in frames.items():
        meta = read_metadata_json(schemas.batch_path(ws.root, b))
        per_level = {
            str(int(k)): float(v)
            for k, v in df.group_by("fidelity")
            .agg(pl.col("cost").sum())
            .sort("fidelity")
            .iter_rows()
        }
        new = set(active0.filter(pl.col("batch") == b)[SID].to_list())
        seen |= new
        jb, ja = meta.get("j_before"), meta.get("j_after")
        cost = float(df["cost"].sum())
        row: dict[str, Any] = {
            "batch": b,
            "cost": cost,
            "cost_per_level": per_level,
            "confirmed": len(new),
            "confirmed_so_far": len(seen),
            "j_before": jb,
            "j_after": ja,
            "j_decrease_per_cost": (jb - ja) / cost
            if jb is not None and ja is not None and cost > 0
            else None,
            "gp_rate": None,
            "gp_sd_bound": None,
        }
        snap = ws.history_dir / f"scores-after-batch-{b:04d}.parquet"
        if snap.exists():
            m, bound = gp_estimate(read_state(snap, columns=["p_0"]).column("p_0").to_numpy())
            row["gp_rate"], row["gp_sd_bound"] = m, float(np.sqrt(bound))
        rows.append(row)
    return rows


def _estimate_history(ws: Workspace, plans: list[int], gamma: float) -> list[dict[str, Any]]:
    """Every estimate computed, oldest first, at the first gamma."""
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
                "design": doc.get("design"),
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
    from bams_cli import defaults

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
