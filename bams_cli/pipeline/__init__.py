"""One function per subcommand: load state -> call core -> write state.

Every function validates everything it reads before it writes anything, stages its
outputs in one ``transaction`` and returns a JSON-serialisable summary (what the CLI prints
as a table, or as-is under ``--json``). Progress is reported through an optional
``progress(phase, done, total)`` callable, so this layer never imports rich.

One module per command (``initialise``, ``embedding``, ``ingest``, ``fitting``,
``selection``, ``estimation``, ``reporting``, and ``simulation``, the sample data's stand-in
for a simulation team); ``_common`` and ``_handoff`` hold what several commands share.
Input tables are parsed in the state layer (``bams_cli.state.inputs``). Layers point one
way: cli -> pipeline -> state and core.
"""

from bams_cli.pipeline._common import Progress, locked, pending_summary, plan_numbers
from bams_cli.pipeline.embedding import embed_reduce
from bams_cli.pipeline.estimation import (
    UNIFORM_NOTE_RATIO,
    WEIGHTINGS,
    design_note,
    estimate_compute,
    estimate_plan,
    plan_estimate,
)
from bams_cli.pipeline.fitting import TRANSFORMS, fit, load_posterior
from bams_cli.pipeline.ingest import ingest_results
from bams_cli.pipeline.initialise import init
from bams_cli.pipeline.reporting import report
from bams_cli.pipeline.selection import MODEL_STRATEGIES, STRATEGIES, select
from bams_cli.pipeline.simulation import simulate
from bams_cli.state.inputs import MAX_EMBEDDING, MAX_VALUE
from bams_cli.state.workspace import Workspace

__all__ = [
    "MAX_EMBEDDING",
    "MAX_VALUE",
    "MODEL_STRATEGIES",
    "STRATEGIES",
    "TRANSFORMS",
    "UNIFORM_NOTE_RATIO",
    "WEIGHTINGS",
    "Progress",
    "Workspace",
    "design_note",
    "embed_reduce",
    "estimate_compute",
    "estimate_plan",
    "fit",
    "ingest_results",
    "init",
    "load_posterior",
    "locked",
    "pending_summary",
    "plan_estimate",
    "plan_numbers",
    "report",
    "select",
    "simulate",
]
