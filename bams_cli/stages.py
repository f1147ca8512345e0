"""Staged rate estimates: which stage the next plan is, and what earlier stages showed.

A *series* is the set of estimate plans that make one estimate: stage 1 fixes the total
budget K, the number of stages, each stage's share of K and the stages' weights in the
estimate (``core.design.stage_weights``) before anything is drawn; each later ``estimate
--plan`` draws the next stage once the previous one's results are in (``core.design``). The
plans' metadata carries the series: ``series`` (the plan number of its stage 1), ``stage``,
``stages``, ``series_K``, ``stage_shares`` and ``stage_weights``. Plans written before
stages existed are single-stage series of their own; plans written before the weights were
set apart from the shares (2026-11-29) have no ``stage_shares``: their weights were the
shares (w_s = K_s / K), and their series keeps them.

Every finished plan is also evidence on how far the model's p_n can be trusted: its sampled
segments are a random sample with their planning-time p_n stored beside them
(``mix_evidence``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import polars as pl

from bams_cli.state import schemas
from bams_cli.state.io import read_metadata_json, read_state
from bams_cli.state.workspace import Workspace

if TYPE_CHECKING:
    from bams_cli.core.design import StageEvidence

SID = schemas.SEGMENT_ID


@dataclass(frozen=True)
class PlanInfo:
    """One estimate plan's place in its series (from its metadata)."""

    number: int
    series: int
    stage: int
    stages: int
    series_K: float
    weights: list[float]
    shares: list[float]
    meta: dict[str, Any]


def plan_numbers(ws: Workspace) -> list[int]:
    """Numbers of the estimate plans in the workspace, ascending."""
    if not ws.estimates_dir.is_dir():
        return []
    out = []
    for p in ws.estimates_dir.glob("plan-*.parquet"):
        stem = p.stem[len("plan-") :]
        if stem.isdigit():
            out.append(int(stem))
    return sorted(out)


def estimate_again(ws: Workspace, k: int, doc: dict[str, Any] | None = None) -> str:
    """The command that computes plan ``k``'s estimate (``doc``, read when not given) again
    as it was computed: its ``--failed-as bounds``, ``--confidence`` and ``--interval``
    kept, and ``--plan-number`` where ``k`` is not the latest plan."""
    import shlex

    doc = ws.read_estimate(k) if doc is None else doc
    parts = [f"bams-cli estimate -w {shlex.quote(str(ws.root))}"]
    if k != (plan_numbers(ws) or [k])[-1]:
        parts.append(f"--plan-number {k}")
    if (doc.get("abandoned") or {}).get("failed_as") == "bounds":
        parts.append("--failed-as bounds")
    confidence = doc["estimates"][0].get("confidence")
    if isinstance(confidence, (int, float)) and confidence != 0.9:
        parts.append(f"--confidence {confidence:g}")
    if doc.get("interval", "gamma") != "gamma":
        parts.append(f"--interval {doc['interval']}")
    return " ".join(parts)


def plan_info(ws: Workspace, number: int) -> PlanInfo:
    """Series, stage and weights of plan ``number``; a plan without them is its own series."""
    meta = read_metadata_json(ws.estimates_dir / f"plan-{number:04d}.parquet")
    stages = int(meta.get("stages") or 1)
    weights = [float(w) for w in meta.get("stage_weights") or [1.0]]
    return PlanInfo(
        number=number,
        series=int(meta.get("series") or number),
        stage=int(meta.get("stage") or 1),
        stages=stages,
        series_K=float(meta.get("series_K") or meta["samples"]),
        weights=weights,
        shares=[float(w) for w in meta.get("stage_shares") or weights],
        meta=meta,
    )


def series_plans(ws: Workspace, last: int) -> list[PlanInfo]:
    """The plans of the series that plan ``last`` belongs to, up to it, in stage order."""
    info = plan_info(ws, last)
    plans = [plan_info(ws, k) for k in plan_numbers(ws) if info.series <= k <= last]
    return [p for p in plans if p.series == info.series]


def plan_complete(ws: Workspace, number: int) -> bool:
    """Whether every sampled segment of plan ``number`` has a level-0 result."""
    pend = ws.pending()
    if not pend.height:
        return True
    return not bool((pend["plan"] == number).any())


#: The calibration shapes a plan's ``risk_norms`` follow when it does not record them.
_OLD_TAUS = (0.5, 1.0, 1.5, 2.0)


def mix_evidence(ws: Workspace, gamma: float) -> tuple[list[StageEvidence], list[int]]:
    """What finished estimate plans say about how far p_n can be trusted at ``gamma``.

    For each plan whose results are all in and that recorded its U's mean p_n and risk
    norms (``p_mean_unknown``, ``risk_norms``): its sampled segments' relative risk
    u = p_n / mean_U(p_n) at planning, and whether their level-0 value is <= gamma
    (``core.design.risk_posterior`` reads them). Plans made for another gamma, or by an
    older version whose shapes cannot be told, are skipped. Returns the evidence and the plan
    numbers it came from.
    """
    from bams_cli.core.design import TAUS, StageEvidence

    obs = ws.read_observations().filter(pl.col("fidelity") == 0).select(SID, "value")
    pend = ws.pending()  # read once: which plans still await results
    waiting = set(pend["plan"].drop_nulls().to_list()) if pend.height else set()
    evidence: list[StageEvidence] = []
    used: list[int] = []
    for k in plan_numbers(ws):
        path = ws.estimates_dir / f"plan-{k:04d}.parquet"
        meta = read_metadata_json(path)
        mean, norms = meta.get("p_mean_unknown"), meta.get("risk_norms")
        if not mean or not norms or meta.get("plan_gamma") != gamma or k in waiting:
            continue
        # Each norm belongs to a shape tau: the plan records which (``risk_taus``); plans
        # from before that record weighed tau 0.5, 1, 1.5 and 2, in that order.
        taus = meta.get("risk_taus") or (_OLD_TAUS if len(norms) == len(_OLD_TAUS) else None)
        if taus is None or len(taus) != len(norms):
            continue
        by_tau = dict(zip((float(t) for t in taus), norms, strict=True))
        if any(float(t) not in by_tau for t in TAUS):
            continue
        norms = [by_tau[float(t)] for t in TAUS]
        t = pl.from_arrow(read_state(path, columns=[SID, "stratum", "p_n"]))
        assert isinstance(t, pl.DataFrame)
        t = t.filter(pl.col("stratum") == "sampled").join(obs, on=SID, how="inner")
        # Leads sampled with certainty were chosen by their cheap runs, not by p_n: where
        # failures fall among them says nothing of p_n's calibration (``open_leads``).
        if leads := meta.get("lead_ids"):
            t = t.filter(~pl.col(SID).is_in(leads))
        if not t.height:
            continue
        evidence.append(
            StageEvidence(
                t["p_n"].to_numpy() / float(mean),
                t["value"].to_numpy() <= gamma,
                np.asarray(norms, dtype=np.float64),
                p_mean=float(mean),
            )
        )
        used.append(k)
    return evidence, used
