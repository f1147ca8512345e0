"""``bams-cli simulate``: sample-data tooling. It answers a hand-off from a table of known
values (the sample data's truth), standing in for the simulation team in the demo, the tests
and the benchmarks. A real study never calls it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import polars as pl

from bams_cli.errors import (
    InputError,
)
from bams_cli.pipeline._common import SID
from bams_cli.state import handoff as contract
from bams_cli.state.io import (
    read_table,
    require_columns,
    transaction,
)
from bams_cli.state.workspace import Workspace


# ---------------------------------------------------------------------------------------
# simulate (sample data only)
# ---------------------------------------------------------------------------------------
def simulate(handoff: Path, truth: Path, output: Path) -> dict[str, Any]:
    """Answer a hand-off list from a ground-truth table, as a simulation team would.

    For sample data and demos only: real results come from real simulators. Takes no
    workspace and no lock.

    Parameters
    ----------
    handoff : Path
        A hand-off list (Parquet or CSV): ``segment_id``, ``fidelity`` (and ``request_id``).
    truth : Path
        Ground truth: ``segment_id``, ``value_0``, ``value_1``, ... (``--truth``).
    output : Path
        The results file to write, ``.parquet`` or ``.csv`` (``--output``/``-o``).

    Returns
    -------
    dict
        The summary ``--json`` prints: ``results`` (the file written), ``rows``, ``note``.

    Raises
    ------
    InputError
        The hand-off list or truth is missing, malformed or names a segment the truth
        lacks, or ``output`` would overwrite an input or a workspace's state.
    """
    dest = Path(output).resolve()
    in_state = any(Workspace(d).holds_state(dest) for d in (dest.parent, dest.parent.parent))
    if dest in (Path(handoff).resolve(), Path(truth).resolve()) or in_state:
        raise InputError(
            output, "would overwrite an input or a workspace's state; choose another -o"
        )
    picks = read_table(handoff, what="hand-off")
    require_columns(picks, [SID, "fidelity"], handoff)
    truth_t = read_table(truth, what="truth")
    require_columns(truth_t, [SID], truth)
    p = pl.from_arrow(picks)
    t = pl.from_arrow(truth_t)
    assert isinstance(p, pl.DataFrame) and isinstance(t, pl.DataFrame)
    p = p.with_row_index("_row", offset=1).with_columns(
        pl.col(SID).cast(pl.String), pl.col("fidelity").cast(pl.Int64)
    )
    t = t.with_columns(pl.col(SID).cast(pl.String))
    levels = sorted(
        int(c.split("_")[1]) for c in t.columns if c.startswith("value_") and c[6:].isdigit()
    )
    bad = p.filter(~pl.col("fidelity").is_in(levels))
    if bad.height:
        raise InputError(
            handoff,
            f"fidelity {bad['fidelity'][0]} has no value_{bad['fidelity'][0]} column in {truth}",
            column="fidelity",
            row=int(bad["_row"][0]),
        )
    long = t.unpivot(
        index=SID, on=[f"value_{lv}" for lv in levels], variable_name="fidelity", value_name="value"
    ).with_columns(pl.col("fidelity").str.slice(6).cast(pl.Int64))
    out = p.join(long, on=[SID, "fidelity"], how="left")
    missing = out.filter(pl.col("value").is_null())
    if missing.height:
        raise InputError(
            handoff,
            f"segment id {missing[SID][0]!r} is not in {truth}",
            column=SID,
            row=int(missing["_row"][0]),
        )
    # A hand-off list with request ids (state.handoff) is answered by request id too.
    keys = [contract.REQUEST_ID] if contract.REQUEST_ID in out.columns else []
    result = out.sort("_row").select(*keys, SID, "fidelity", "value")
    with transaction() as tx:
        if output.suffix.lower() == ".csv":
            tx.write_with(output, lambda path: result.write_csv(path))
        else:
            tx.write_parquet(output, result.to_arrow())
    return {
        "results": str(output),
        "rows": result.height,
        "note": "simulated from ground truth (sample data only)",
    }
