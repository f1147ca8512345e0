"""Every workspace state file's schema, declared once.

Each ``StateFile`` names its path inside the workspace, its required columns with their
Arrow types, and a schema version stamped into the file's metadata. Files may carry more
columns than these (pass-through columns a simulation team needs); they may not carry
fewer, and a required column must have its declared type. Optional columns are those a
newer version writes and an older file may lack (readers derive them then); when present
they must have their declared type too.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa

from bams_cli.errors import SchemaError
from bams_cli.state.io import require_columns, stamp


@dataclass(frozen=True)
class StateFile:
    """A Parquet state file: where it lives and what it must hold."""

    name: str
    relpath: str
    schema: pa.Schema
    version: int = 1
    optional: pa.Schema = pa.schema([])

    def path(self, workspace: Path) -> Path:
        return workspace / self.relpath

    def conform(self, table: pa.Table, extra_meta: dict | None = None) -> pa.Table:
        """Cast required columns to their declared types, put them first, stamp metadata."""
        require_columns(table, self.schema.names, self.name)
        arrays, names = [], []
        for fld in [*self.schema, *(f for f in self.optional if f.name in table.column_names)]:
            col = table.column(fld.name)
            if col.type != fld.type:
                try:
                    col = col.cast(fld.type)
                except pa.ArrowException as exc:  # invalid value or unsupported cast
                    raise SchemaError(
                        self.name, f"cannot cast to {fld.type} ({exc})", column=fld.name
                    ) from None
            arrays.append(col)
            names.append(fld.name)
        for name in table.column_names:
            if name not in names:
                arrays.append(table.column(name))
                names.append(name)
        return stamp(pa.table(arrays, names=names), self.version, extra_meta)

    def check(self, table: pa.Table, source: object) -> pa.Table:
        """Validate a table read from disk against the declared schema."""
        require_columns(table, self.schema.names, source)
        for fld in [*self.schema, *(f for f in self.optional if f.name in table.column_names)]:
            got = table.schema.field(fld.name).type
            if got != fld.type:
                raise SchemaError(source, f"expected type {fld.type}, got {got}", column=fld.name)
        return table


SEGMENT_ID = "segment_id"

# Reduced pool: segment id, reduced coordinates z0..z{d-1} (float64) and pass-through columns.
# The coordinate columns depend on d, so only the id is declared; state.workspace checks zK.
SEGMENTS = StateFile("segments.parquet", "segments.parquet", pa.schema([(SEGMENT_ID, pa.string())]))

# Append-only observation log. A replaced value stays in the log with active = false.
OBSERVATIONS = StateFile(
    "observations.parquet",
    "observations.parquet",
    pa.schema(
        [
            (SEGMENT_ID, pa.string()),
            ("fidelity", pa.int64()),
            ("value", pa.float64()),
            ("batch", pa.int64()),
            ("source_file", pa.string()),
            ("source_sha256", pa.string()),
            ("ingested_at", pa.string()),
            ("active", pa.bool_()),
            ("extra", pa.string()),
        ]
    ),
)

# Per-segment scores written by `fit`: p_<gamma index> columns follow mu and sd.
SCORES = StateFile(
    "scores.parquet",
    "scores.parquet",
    pa.schema([(SEGMENT_ID, pa.string()), ("mu", pa.float64()), ("sd", pa.float64())]),
    # False where sd is an upper bound of the exact sd (a bounded fit, MFGP.score); files
    # written before it have every sd exact.
    optional=pa.schema([("sd_exact", pa.bool_())]),
)

# The hand-off contract's columns (state.handoff), optional in state files written before it.
_REQUEST_COLUMNS = [
    ("request_id", pa.string()),
    ("source", pa.string()),
    ("fidelity_name", pa.string()),
    ("purpose", pa.string()),
]

# One hand-off list per selected batch.
BATCH = StateFile(
    "batch",
    "batches/batch-{n:04d}.parquet",
    pa.schema(
        [
            (SEGMENT_ID, pa.string()),
            ("fidelity", pa.int64()),
            ("cost", pa.float64()),
            ("delta_j", pa.float64()),
            ("cluster", pa.int64()),
            ("rank", pa.int64()),
            ("strategy", pa.string()),
        ]
    ),
    optional=pa.schema(_REQUEST_COLUMNS),
)

# Estimate plan: every planned segment with its inclusion probability (or draw count).
PLAN = StateFile(
    "plan",
    "estimates/plan-{n:04d}.parquet",
    pa.schema(
        [
            (SEGMENT_ID, pa.string()),
            ("stratum", pa.string()),  # "known" or "sampled"
            ("pi", pa.float64()),
            ("draws", pa.int64()),
        ]
    ),
    # request_id and the rest are null on the known stratum's rows (nothing to simulate).
    optional=pa.schema(_REQUEST_COLUMNS),
)

# A cheap-level screen drawn by `estimate --plan --screen` (bams_cli.pipeline.screening):
# every segment of the pool as it stood, the screen's pi1 over U and which were drawn.
# Named by the number of the plan that confirms it.
SCREEN = StateFile(
    "screen",
    "estimates/screen-{n:04d}.parquet",
    pa.schema(
        [
            (SEGMENT_ID, pa.string()),
            ("stratum", pa.string()),  # "known" (a level-0 result in hand) or "unknown"
            ("pi1", pa.float64()),  # 1 on the known stratum
            ("screened", pa.bool_()),
            ("p_n", pa.float64()),
        ]
    ),
)

# Append-only log of requests that will never come back (`bams-cli abandon`, `ingest-results
# --abandon-failed`): the (segment, level) a batch or a plan asked for, with why. Exactly one
# of batch and plan is set on each row. Nothing is ever removed; a result that arrives
# later is ingested as usual and outranks the abandonment.
ABANDONED = StateFile(
    "abandoned.parquet",
    "abandoned.parquet",
    pa.schema(
        [
            (SEGMENT_ID, pa.string()),
            ("fidelity", pa.int64()),
            ("batch", pa.int64()),
            ("plan", pa.int64()),
            ("request_id", pa.string()),
            ("reason", pa.string()),
            ("source", pa.string()),
            ("abandoned_at", pa.string()),
        ]
    ),
)

ALL = (SEGMENTS, OBSERVATIONS, SCORES, BATCH, PLAN, SCREEN, ABANDONED)


def batch_path(workspace: Path, n: int) -> Path:
    return workspace / BATCH.relpath.format(n=n)
