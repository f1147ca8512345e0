"""What every command shares: the workspace lock decorator, the progress callback type, and
small readers of state that several commands use."""

from __future__ import annotations

import functools
import inspect
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl

from bams_cli import stages as stages_mod
from bams_cli.errors import OptionError, OptionValueError
from bams_cli.settings import SETTINGS_FILE
from bams_cli.state import schemas
from bams_cli.state.io import (
    journal_in,
    read_state,
    recover,
    recovered_note,
)
from bams_cli.state.lock import workspace_lock
from bams_cli.state.workspace import Workspace

Progress = Callable[[str, int, int], None]
SID = schemas.SEGMENT_ID


def locked(fn: Callable[..., dict[str, Any]]) -> Callable[..., dict[str, Any]]:
    """Hold the workspace lock for the whole command: from the first read to the commit.

    A command that read the log, then waited for the lock only to write, could overwrite
    what another command appended in between; holding it throughout makes the second
    command fail at once (or wait, with ``wait=True``) before it reads anything.

    The wrapper adds the keyword-only ``wait: bool = False`` to ``fn``'s parameters and to
    its ``__signature__``, so ``inspect.signature`` and ``help()`` show it (the decorated
    function's docstring documents it).

    Parameters
    ----------
    fn : callable
        A command taking the workspace root first and returning its summary.

    Returns
    -------
    callable
        ``fn`` run holding the workspace lock, after recovering an interrupted commit.
    """

    @functools.wraps(fn)
    def run(root: Path, *args: Any, wait: bool = False, **kwargs: Any) -> dict[str, Any]:
        if not (Path(root) / SETTINGS_FILE).exists():
            return fn(root, *args, **kwargs)  # raises "no such workspace" without creating it
        with workspace_lock(Path(root), wait=wait), journal_in(Path(root)):
            moved = recover(Path(root))
            if moved:
                sys.stderr.write(recovered_note(root, moved))
            return fn(root, *args, **kwargs)

    sig = inspect.signature(fn)
    params = list(sig.parameters.values())
    wait = inspect.Parameter(
        "wait", inspect.Parameter.KEYWORD_ONLY, default=False, annotation="bool"
    )
    # before a **kwargs catch-all, if any: a parameter may not follow it
    at = next((i for i, p in enumerate(params) if p.kind is p.VAR_KEYWORD), len(params))
    run.__signature__ = sig.replace(parameters=[*params[:at], wait, *params[at:]])  # type: ignore[attr-defined]
    return run


def ids_in(ids: np.ndarray, among: Any) -> np.ndarray:
    """Which of the segment ids ``ids`` are in ``among``, as a boolean array: a hash lookup.

    ``np.isin`` on text ids (object arrays) compares every pair: a stage-2 ``estimate
    --plan`` at a million segments spent 245 s in it against stage 1's 11,700 results.
    """
    if len(ids) == 0:
        return np.zeros(0, dtype=bool)
    return (
        pl.Series(np.asarray(ids), dtype=pl.String)
        .is_in(pl.Series(np.asarray(among), dtype=pl.String).implode())
        .to_numpy()
    )


def savez(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)  # type: ignore[arg-type]


def not_run_summary(not_run: pl.DataFrame, limit: int = 20) -> dict[str, Any]:
    """Rows a results file marked as not run (a status other than ok): they stay pending."""
    return {
        "count": not_run.height,
        "first": not_run.head(limit).drop("_row").to_dicts(),
    }


def pending_summary(ws: Workspace, limit: int = 20) -> dict[str, Any]:
    pend = ws.pending()

    def per(key: str) -> dict[int, int]:  # a plan's picks have no batch, and vice versa
        rows = pend.filter(pl.col(key).is_not_null()).group_by(key).len().sort(key)
        return {int(k): int(v) for k, v in rows.iter_rows()}

    return {
        "count": pend.height,
        "by_batch": per("batch"),
        "by_plan": per("plan"),
        "first": pend.head(limit).select(SID, "fidelity", "batch", "plan").to_dicts(),
    }


# ---------------------------------------------------------------------------------------
# estimate (plan -> simulate -> compute)
# ---------------------------------------------------------------------------------------
plan_numbers = stages_mod.plan_numbers


def read_scores(
    ws: Workspace, n_gammas: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    t = schemas.SCORES.check(read_state(ws.scores_path), ws.scores_path)
    p = np.column_stack([t.column(f"p_{g}").to_numpy() for g in range(n_gammas)])
    ids = t.column(SID).to_numpy(zero_copy_only=False)
    return ids, t.column("mu").to_numpy(), t.column("sd").to_numpy(), p


def finite_or_none(x: float) -> float | None:
    """x as a JSON number, or None (JSON null) when it is NaN or infinite."""
    x = float(x)
    return x if math.isfinite(x) else None


# Options select, estimate --plan and loop share, checked before anything is read: a value
# out of range is a usage error (exit code 2) naming the option, whichever command got it.
def check_budget(budget: float, flag: str = "--budget") -> None:
    """A batch budget: a finite number of cost units > 0."""
    if not (budget > 0 and math.isfinite(budget)):
        raise OptionValueError(
            f"{flag} {budget:g}: must be a finite number > 0 (cost units; one level-0 run costs 1)"
        )


def check_buys_a_run(
    budget: float, costs: Sequence[float], flag: str = "--budget", level0_only: str | None = None
) -> None:
    """A batch budget that buys at least one run of the levels a batch may pick (``costs``,
    the study's): refused before any work, naming the cheapest cost. ``level0_only``: the
    strategy, when it runs level 0 alone. The costs are the study's, so exit code 1."""
    if budget >= min(costs):
        return
    why = (
        f"--strategy {level0_only} runs level 0 only, at cost {costs[0]:g}"
        if level0_only
        else f"the cheapest level costs {min(costs):g}"
    )
    raise OptionError(f"{flag} {budget:g}: buys no run; {why}")


def check_clusters(clusters: int) -> None:
    if clusters < 1:
        raise OptionValueError(f"--clusters {clusters}: must be >= 1 (1: no clustering)")


def check_workers(workers: int | None) -> None:
    if workers is not None and workers < 1:
        raise OptionValueError(f"--workers {workers}: must be >= 1 (leave it out for one per core)")


def check_samples(samples: float | None) -> None:
    """An estimate's budget K, when given: a finite number of simulations >= 1."""
    if samples is not None and not 1 <= samples < math.inf:
        raise OptionValueError(
            f"--samples {samples:g}: must be a finite number >= 1 (simulations to plan)"
        )
