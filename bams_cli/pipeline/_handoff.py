"""The hand-off lists ``select`` and ``estimate --plan`` write for the simulation team: one
column layout, internal columns kept in the Parquet state."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import pyarrow as pa

from bams_cli import defaults
from bams_cli.pipeline._common import SID, ids_in
from bams_cli.state import handoff as contract
from bams_cli.state.io import (
    read_state_schema,
)
from bams_cli.state.workspace import Workspace


def observed_level0(ws: Workspace, ids: np.ndarray) -> np.ndarray:
    obs = ws.read_observations().filter(pl.col("fidelity") == 0)
    return ids_in(ids, obs[SID].to_numpy())


def reports_level0_units(scale: float) -> bool:
    """Whether a cheap level fitted at this scale (``Hyperparameters.scales``) counts as
    reporting level 0's units, where gamma is its failure threshold too: within
    ``defaults.LEAD_SCALE_LIMIT`` of 1."""
    return 1.0 / defaults.LEAD_SCALE_LIMIT <= float(scale) <= defaults.LEAD_SCALE_LIMIT


def cheap_failures(
    ws: Workspace, ids: np.ndarray, gamma: float, scales: Sequence[float] = ()
) -> np.ndarray:
    """Segments seen at or below ``gamma`` at some cheap level in level 0's units: a lead
    until level 0 confirms it (``select``'s confirmation runs, ``estimate --plan``'s
    certain leads). A level the model fits with a scale more than
    ``defaults.LEAD_SCALE_LIMIT`` from 1 (``scales``, one per cheap level;
    ``Hyperparameters.scales``) reports other units, where gamma is not its threshold:
    its runs do not count (bool over the pool)."""
    same_units = [lv for lv in range(1, ws.require_initialised().n_levels)
                  if lv > len(scales) or reports_level0_units(scales[lv - 1])]  # fmt: skip
    obs = ws.read_observations().filter(
        pl.col("fidelity").is_in(same_units) & (pl.col("value") <= gamma)
    )
    return ids_in(ids, obs[SID].to_numpy())


def lead_evidence(
    ws: Workspace, ids: np.ndarray, cheap: np.ndarray, gamma: float
) -> tuple[int, int]:
    """(segments of ``cheap`` (``cheap_failures``, bool over the pool) that have a level-0
    result, how many of them fail at level 0 at ``gamma``): how often the study's leads
    have been confirmed (``core.design.lead_share``)."""
    seen = ids[np.flatnonzero(cheap)]
    obs0 = ws.read_observations().filter(pl.col("fidelity") == 0)
    ran = ids_in(seen, obs0[SID].to_numpy())
    failed = ids_in(seen, obs0.filter(pl.col("value") <= gamma)[SID].to_numpy())
    return int(ran.sum()), int(failed.sum())


def describe_leads(
    n_lead: int, facts: dict[str, Any] | None, gamma: float, of: str = "K"
) -> str | None:
    """What a plan or screen says of its certain leads, and of a cap the evidence set
    (``estimation.open_leads``' facts); ``of``: the budget they come out of."""
    if not n_lead:
        return None
    text = (
        f"{n_lead} open lead{'s' if n_lead > 1 else ''} (a cheap run at or below gamma "
        f"{gamma:g}, no level-0 result) {'are' if n_lead > 1 else 'is'} sampled with "
        f"certainty out of {of}: each is confirmed at level 0, and none adds variance"
    )
    if facts and facts["open"] > n_lead:
        text += (
            f"; {facts['open'] - n_lead} more are left to the design (at most "
            f"{facts['share']:g} of {of} in leads: {facts['failed']} of the {facts['pairs']} "
            "run at level 0 so far failed there)"
        )
    return text


# Columns of the state files that only bams-cli reads: the CSV hand-off leaves them out.
BATCH_INTERNAL = ("delta_j", "cluster", "rank", "strategy")
PLAN_INTERNAL = ("stratum", "pi", "draws", "q", "p_n")


def passthrough_columns(ws: Workspace, index: np.ndarray, taken: dict[str, Any]) -> dict[str, Any]:
    """The pool's pass-through columns (scenario tags ...) for the picked rows. A column
    named like one of the hand-off's own, or the results' (value, status), is left out:
    the contract's meaning wins."""
    reserved = {SID, *taken, *BATCH_INTERNAL, *PLAN_INTERNAL, *contract.TEMPLATE_COLUMNS}
    coords = set(ws.coordinate_columns())
    names = [
        c
        for c in read_state_schema(ws.segments_path).names
        if c not in coords and c not in reserved
    ]
    if not names:
        return {}
    rows = ws.read_segments([SID, *names]).take(pa.array(np.asarray(index, np.int64)))
    return {name: rows.column(name) for name in names}


def write_handoff(
    tx: Any, table: pa.Table, csv: Path, internal: tuple[str, ...], with_internal: bool
) -> tuple[Path, Path]:
    """Stage a hand-off CSV and its results template (``state.handoff``) in ``tx``."""
    frame = contract.handoff_frame(table, internal, with_internal=with_internal)
    template = contract.template_path(csv)
    tx.write_with(csv, lambda p: frame.write_csv(p))
    tx.write_with(template, lambda p: contract.template_frame(frame).write_csv(p))
    return csv, template
