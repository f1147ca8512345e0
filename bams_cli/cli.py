"""The ``bams-cli`` command line: parse flags, call one pipeline function, print.

The only module that imports typer. Every command runs inside one boundary (``command``):
errors the user can fix (``BamsError``) print as one line with exit code 1 (2 for an
option's value out of range, ``OptionValueError``, a usage error like click's own; 3 when
the command refuses because picks await results: ``PendingResultsError``); anything else
(a damaged state file, a full disk, a bug) prints as one line too, with exit code 1, unless
BAMS_DEBUG is set; warnings print as one line each. Under --json both are one JSON object
per stderr line instead (``{"error": ..., "exit_code": ...}``). Transactions roll back on
the way out, so a failed command leaves the workspace as it was.

Choices are ``defaults`` enums (an unknown value is a usage error, exit code 2, naming the
valid ones) and every default comes from ``defaults``. Precedence: a flag, then its
BAMS_* environment variable (shown in --help), then settings.toml where the option says
so, then ``defaults``.
"""

from __future__ import annotations

import enum
import functools
import inspect
import os
import re
import shlex
import signal
import sys
import typing
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, Literal

import typer
import typer.core
import typer.rich_utils

try:  # typer >= 0.2x ships its own copy of click
    from typer._click import Context
    from typer._click.exceptions import ClickException, UsageError
except ImportError:  # pragma: no cover - older typer on the real click
    from click import Context  # type: ignore[assignment]
    from click.exceptions import ClickException, UsageError  # type: ignore[assignment]

from bams_cli import __version__, console, defaults, memory, pipeline, schemas_json, stopping
from bams_cli import abandon as abandon_runs
from bams_cli import loop as study_loop
from bams_cli.defaults import (
    Design,
    FailedAs,
    Greedy,
    Interval,
    Method,
    Pooling,
    Protocol,
    Strategy,
    Transform,
    Weighting,
)
from bams_cli.errors import EXIT_USAGE, BamsError, OptionValueError
from bams_cli.status import status as study_status

_display_type_rich = getattr(typer.core.TyperOption, "display_type_rich", None)


def _no_bool_metavar(self: typer.core.TyperOption, ctx: Context) -> str | None:
    # typer 0.29 prints "<bool>" beside every flag (--json, --help, --no-standardize);
    # a flag takes no value, so its type column stays empty.
    return None if self.is_flag else _display_type_rich(self, ctx)  # type: ignore[misc]


if _display_type_rich is not None:
    typer.core.TyperOption.display_type_rich = _no_bool_metavar  # type: ignore[method-assign]

_rich_format_error = getattr(typer.rich_utils, "rich_format_error", None)


def _plain(exc: ClickException) -> ClickException:
    """``exc`` without pydantic's "Value error, " prefix: typer checks a value through
    pydantic, which prefixes the ValueError of its choice check ("Invalid value for
    '--strategy': Value error, 'bmas' is not one of ..."); the user needs only the rest."""
    exc.message = exc.message.removeprefix("Value error, ")
    return exc


def _usage_error(exc: ClickException) -> None:
    # A usage error in a log (not a terminal) is click's plain lines, "Usage: ...",
    # "Try ...", "Error: ...": typer's box would wrap the message at 80 columns.
    _plain(exc)
    if console.err.is_terminal and _rich_format_error is not None:
        _rich_format_error(exc)
    elif type(exc).__name__ != "NoArgsIsHelpError":
        exc.show()


if _rich_format_error is not None:
    typer.rich_utils.rich_format_error = _usage_error  # type: ignore[assignment]

app = typer.Typer(
    name="bams-cli",
    help=(
        "Find rare failures of an autonomous system and estimate how often they happen, "
        "with Bayesian adaptive multifidelity sampling (BAMS).\n\n"
        "Every step reads and writes Parquet state in a workspace folder:\n\n"
        "init -> embed-reduce -> select (random) -> \\[simulate] -> ingest-results -> fit -> "
        "select -> ... -> estimate -> report\n\n"
        "bams-cli status shows where a study stands and the command to run next."
    ),
    rich_markup_mode="rich",
    context_settings={"help_option_names": ["-h", "--help"]},
    no_args_is_help=True,
    add_completion=True,
    pretty_exceptions_enable=False,
)

Workspace = Annotated[
    Path,
    typer.Option(
        "--workspace",
        "-w",
        envvar="BAMS_WORKSPACE",
        help="Study folder holding settings.toml and the Parquet state.",
        show_default=True,
    ),
]
Json = Annotated[
    bool,
    typer.Option(
        "--json",
        help="Print the full summary as JSON (bams-cli schema) instead of the short human one; "
        "errors and warnings become one JSON object per stderr line.",
    ),
]
Quiet = Annotated[
    bool,
    typer.Option(
        "--quiet",
        "-q",
        envvar="BAMS_QUIET",
        help="Print nothing but errors (and the --json output, when asked for).",
    ),
]
Wait = Annotated[
    bool,
    typer.Option(
        "--wait",
        envvar="BAMS_WAIT",
        help="Wait for another command's workspace lock instead of failing.",
    ),
]
Workers = Annotated[
    int | None,
    typer.Option(
        "--workers",
        envvar="BAMS_WORKERS",
        help="Local worker processes for clusters \\[default: all cores].",
    ),
]
MaxMemory = Annotated[
    str | None,
    typer.Option(
        "--max-memory",
        metavar="SIZE",
        envvar="BAMS_MAX_MEMORY",
        help="Memory ceiling for this command and its workers: 12G, 800M, or 40% of RAM; the "
        "command plans its work to fit and is stopped in one line if it goes over "
        f"\\[default: {defaults.MAX_MEMORY_FRACTION:.0%} of RAM].",
    ),
]
HandoffInternal = Annotated[
    bool,
    typer.Option(
        "--handoff-internal",
        help="Also put the internal columns (kept in the Parquet state file) in the CSV hand-off.",
    ),
]


def _one_line_warning(message: Warning | str, category: type[Warning], *_: Any, **__: Any) -> None:
    console.warning(" ".join(str(message).split()))


def _unexpected(exc: Exception) -> str:
    """One line for an error the commands did not anticipate; BAMS_DEBUG=1 shows it whole."""
    if isinstance(exc, OSError) and exc.filename is not None:
        text = f"{exc.filename}: {exc.strerror or exc}"
    else:
        text = f"{type(exc).__name__}: {exc}"
    text = " ".join(text.split())
    if len(text) > 300:
        text = text[:297] + "..."
    return f"{text} (unexpected: a damaged or hand-edited state file? rerun with BAMS_DEBUG=1 for the traceback)"


def _reflow(doc: str) -> str:
    """Join a docstring's wrapped lines: rich help keeps single newlines, so wrapping at the
    source's width would break lines again at the terminal's."""
    paragraphs = inspect.cleandoc(doc).split("\n\n")
    return "\n\n".join(" ".join(line.strip() for line in p.splitlines()) for p in paragraphs)


#: What stops a command where it stands (``bams_cli.stopping``): Ctrl-C, ``kill``, a closed
#: terminal. A handler someone else installed is left alone; ``loop`` installs its own
#: inside the command's for its time, and restores the command's after.
COMMAND_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def command(
    name: str | None = None, *, max_memory: bool = False
) -> Callable[[Callable[..., None]], Callable[..., None]]:
    """Register a subcommand whose BamsErrors become one stderr line and their exit code
    (1; 2 for ``OptionValueError``; 3 for ``PendingResultsError``, waiting on results).
    ``max_memory``: the command takes ``--max-memory`` and runs under that ceiling
    (``bams_cli.memory``)."""

    def register(fn: Callable[..., None]) -> Callable[..., None]:
        label = f"bams-cli {name or fn.__name__.replace('_', '-')}"

        @functools.wraps(fn)
        def boundary(
            *args: Any, quiet: bool = False, max_memory: str | None = None, **kwargs: Any
        ) -> None:
            console.set_mode(quiet=quiet or _QUIET, json_out=bool(kwargs.get("json_out")))
            try:
                limit = None if max_memory is None else memory.parse_size(max_memory)
                with (
                    stopping.raising(COMMAND_STOP_SIGNALS),
                    warnings.catch_warnings(),
                    memory.ceiling(limit, label),
                ):
                    warnings.showwarning = _one_line_warning
                    fn(*args, **kwargs)
            except BamsError as exc:
                console.error(str(exc), exc.exit_code)
                raise typer.Exit(exc.exit_code) from None
            except UsageError as exc:
                if console.mode.json:
                    console.error(_plain(exc).format_message(), EXIT_USAGE)
                    raise typer.Exit(EXIT_USAGE) from None
                raise
            except (typer.Exit, typer.Abort, ClickException):
                raise
            except KeyboardInterrupt as exc:
                # ``stopping.Stopped`` (a loop's says what it stopped) carries its exit code.
                code = getattr(exc, "exit_code", 130)
                console.error(str(exc) or "interrupted; files being written were discarded", code)
                raise typer.Exit(code) from None
            except Exception as exc:  # a damaged state file, a full disk, or a bug
                if os.environ.get("BAMS_DEBUG"):
                    raise
                console.error(_unexpected(exc))
                raise typer.Exit(1) from None
            finally:
                console.set_mode(quiet=False, json_out=False)

        # Every command takes --quiet: typer reads the parameters from this signature.
        sig = inspect.signature(fn, eval_str=True)
        keyword = inspect.Parameter.KEYWORD_ONLY
        params = [*sig.parameters.values()]
        extra: dict[str, Any] = {"quiet": Quiet}
        if max_memory:
            params.append(inspect.Parameter("max_memory", keyword, default=None))
            extra["max_memory"] = MaxMemory
        params.append(inspect.Parameter("quiet", keyword, default=False))
        params = [p.replace(annotation=extra.get(p.name, p.annotation)) for p in params]
        boundary.__signature__ = sig.replace(parameters=params)  # type: ignore[attr-defined]
        boundary.__annotations__ = {**typing.get_type_hints(fn, include_extras=True), **extra}
        boundary.__doc__ = _reflow(fn.__doc__ or "")
        app.command(name)(boundary)
        return fn

    return register


def _floats(text: str | None, flag: str) -> list[float] | None:
    if text is None:
        return None
    parts = text.split(",")
    try:
        # An empty part ("1," or "1,,0.1") is a number left out, not nothing: refused,
        # since "--costs 1," had silently made a one-level study.
        values = [float(part) for part in parts] if all(p.strip() for p in parts) else []
    except ValueError:
        values = []
    if not values:
        raise OptionValueError(
            f"{flag} {text!r}: expected comma-separated numbers, e.g. {flag} 1,0.1"
        )
    return values


def _dim_option(text: str | None) -> int | Literal["auto"] | None:
    """--dim: a whole number or 'auto'."""
    if text is None:
        return None
    if text.strip() == "auto":
        return "auto"
    if re.fullmatch(r"\s*-?[0-9]+\s*", text) is None:  # not int()'s "1_2" nor other digits
        raise OptionValueError(f"--dim {text!r}: expected a whole number or 'auto', e.g. --dim 12")
    return int(text)


def _json(name: str, summary: dict[str, Any]) -> None:
    """Print a command's --json output, led by the version of its schema (``bams-cli schema``).

    The summary's ``warnings`` also go to stderr, one JSON object per line, as every other
    warning does under --json (a script watching stderr sees them without parsing stdout);
    not for a no-op re-run, which only repeats what was warned when the work was done, save
    its ``settings_warnings`` (about the settings as they are now)."""
    said = summary.get("settings_warnings" if summary.get("up_to_date") else "warnings")
    for text in said or []:
        console.warning(str(text))
    console.print_json({"schema_version": schemas_json.version(name), **summary})


def _show(
    summary: dict[str, Any], json_out: bool, human: Callable[[dict[str, Any]], None], name: str
) -> None:
    """The full summary as JSON under --json, else ``human``'s few lines of key facts."""
    if json_out:
        _json(name, summary)
    else:
        human(summary)


def _screen_share(value: str | None) -> float | str | None:
    """``--screen``: a share of K, "auto" or "off" (None: not given, the default)."""
    if value is None or value in ("auto", "off"):
        return value
    try:
        return float(value)
    except ValueError:
        raise OptionValueError(
            f"--screen {value}: a share of K in (0, 1) such as 0.3, auto, or off"
        ) from None


def _version(value: bool) -> None:
    if value:
        console.out.print(f"bams-cli {__version__}")
        raise typer.Exit()


#: ``bams-cli schema NAME``: the outputs that have a JSON Schema.
SchemaName = enum.StrEnum("SchemaName", [(name, name) for name in schemas_json.NAMES])  # type: ignore[misc]

#: ``bams-cli --quiet COMMAND``: the global form of every command's --quiet.
_QUIET = False


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version", "-V", callback=_version, is_eager=True, help="Show the version and exit."
        ),
    ] = False,
    quiet: Quiet = False,
) -> None:
    """bams-cli: rate-informed discovery of rare failures."""
    global _QUIET
    _QUIET = quiet


@command()
def init(
    workspace: Workspace = Path(defaults.WORKSPACE),
    gamma: Annotated[
        str | None,
        typer.Option("--gamma", help="Failure threshold(s) on the metric f, comma-separated."),
    ] = None,
    costs: Annotated[
        str | None,
        typer.Option(
            "--costs",
            help="Cost per fidelity level, level 0 first (must be 1) \\[default: 1, one level].",
        ),
    ] = None,
    level_names: Annotated[
        str | None,
        typer.Option(
            "--level-names",
            help="Names for the levels, comma-separated \\[default: high, low1, low2, ...].",
        ),
    ] = None,
    seed: Annotated[
        int | None,
        typer.Option("--seed", help="Seed recorded and used by every step \\[default: 0]."),
    ] = None,
    dim: Annotated[
        str | None,
        typer.Option(
            "--dim",
            help="Reduced embedding dimension, or 'auto': from the embedding's spectrum "
            "\\[default: auto].",
        ),
    ] = None,
    settings_from: Annotated[
        Path | None,
        typer.Option("--settings-from", help="Start from this settings.toml (flags override it)."),
    ] = None,
    force: Annotated[
        bool, typer.Option("--force", help="Overwrite an existing settings.toml.")
    ] = False,
    exist_ok: Annotated[
        bool,
        typer.Option(
            "--exist-ok",
            help="Succeed without writing when settings.toml already holds these settings.",
        ),
    ] = False,
    wait: Wait = False,
    json_out: Json = False,
) -> None:
    """Create a study workspace and its settings file.

    --gamma (or --settings-from) is required. Re-running the same init with --exist-ok
    changes nothing; with other settings it is an error naming them.

    [bold]Example[/]: bams-cli init -w study --gamma 0.56 --costs 1,0.1 --seed 0
    """
    summary = pipeline.init(
        workspace,
        gammas=_floats(gamma, "--gamma"),
        costs=_floats(costs, "--costs"),
        level_names=level_names.split(",") if level_names else None,
        seed=seed,
        dim=_dim_option(dim),
        settings_from=settings_from,
        force=force,
        exist_ok=exist_ok,
        wait=wait,
    )
    if summary.get("unchanged") and not json_out:
        console.out.print(
            f"{summary['settings']} already holds these settings; nothing changed",
            markup=False,
            highlight=False,
        )
        return
    _show(summary, json_out, console.init_summary, "init")


@command("embed-reduce", max_memory=True)
def embed_reduce(
    segments: Annotated[
        Path,
        typer.Argument(
            metavar="SEGMENTS", help="Parquet file of segments: segment_id + embedding."
        ),
    ],
    workspace: Workspace = Path(defaults.WORKSPACE),
    method: Annotated[
        Method,
        typer.Option(
            "--method",
            help="pca (exact, streaming), autoencoder, identity, or ipca (the older "
            "IncrementalPCA, for comparison).",
        ),
    ] = defaults.METHOD,
    dim: Annotated[
        str | None,
        typer.Option(
            "--dim",
            help="Reduced dimension, or 'auto': 12, or more where the embedding's spectrum "
            "drops to its noise floor past 12 \\[default: settings, auto].",
        ),
    ] = None,
    standardize: Annotated[
        bool,
        typer.Option(
            "--standardize/--no-standardize", help="Scale each input column to unit variance."
        ),
    ] = True,
    columns: Annotated[
        str | None,
        typer.Option(
            "--columns",
            help="Glob of numeric embedding columns, e.g. 'emb_*' \\[default: none, a list column holds it].",
        ),
    ] = None,
    embedding_column: Annotated[
        str | None,
        typer.Option(
            "--embedding-column",
            help="The list column holding the embedding \\[default: the file's only list column].",
        ),
    ] = None,
    id_column: Annotated[
        str | None,
        typer.Option("--id-column", help="Segment id column \\[default: settings, segment_id]."),
    ] = None,
    apply: Annotated[
        bool,
        typer.Option(
            "--apply", help="Map new segments with the saved reducer and add them to the pool."
        ),
    ] = False,
    batch_size: Annotated[
        int, typer.Option("--batch-size", help="Rows read per batch.")
    ] = defaults.BATCH_SIZE,
    sample_size: Annotated[
        int,
        typer.Option(
            "--sample-size", help="Rows sampled to train the autoencoder and measure error."
        ),
    ] = defaults.SAMPLE_SIZE,
    force: Annotated[
        bool, typer.Option("--force", help="Refit the reducer over an existing pool.")
    ] = False,
    wait: Wait = False,
    json_out: Json = False,
) -> None:
    """Reduce segment embeddings to a few dimensions and store the pool.

    --dim auto (the default) keeps 12 components, or more where the embedding's spectrum
    drops to its noise floor past component 12 (a drop of 3x or more, up to 32 components);
    the summary says which and why.

    [bold]Example[/]: bams-cli embed-reduce -w study sample_data/av_like/segments.parquet --dim auto
    """
    with console.progress(not json_out, "embed-reduce") as bar:
        summary = pipeline.embed_reduce(
            workspace,
            segments,
            apply=apply,
            method=method.value,
            dim=_dim_option(dim),
            standardize=standardize,
            columns=columns,
            embedding_column=embedding_column,
            id_column=id_column,
            batch_size=batch_size,
            sample_size=sample_size,
            force=force,
            wait=wait,
            progress=bar,
        )
    _show(summary, json_out, console.embed_reduce_summary, "embed-reduce")


@command("ingest-results")
def ingest_results(
    results: Annotated[
        Path,
        typer.Argument(
            metavar="RESULTS",
            help="Parquet or CSV: request_id or segment_id + fidelity (number or level name), "
            "value, optional status (+ extra columns).",
        ),
    ],
    workspace: Workspace = Path(defaults.WORKSPACE),
    replace: Annotated[
        bool,
        typer.Option("--replace", help="Supersede logged values that disagree with this file."),
    ] = False,
    allow_unselected: Annotated[
        bool, typer.Option("--allow-unselected", help="Accept results for pairs no batch selected.")
    ] = False,
    abandon_failed: Annotated[
        bool,
        typer.Option(
            "--abandon-failed",
            help="Record the rows whose status is neither empty nor ok (crashed, timeout) as "
            "abandoned, in the same commit: they stop being pending (see bams-cli abandon).",
        ),
    ] = False,
    wait: Wait = False,
    json_out: Json = False,
) -> None:
    """Append simulation results to the observation log.

    Each row is keyed by request_id (from the hand-off list), or by segment_id and fidelity
    (the level's number or its name in settings). The results template beside each
    hand-off list has the columns to fill.

    A row whose status is neither empty nor ok (e.g. crashed) is not ingested: its request
    stays pending, or, with --abandon-failed, is recorded as never coming back. Such a row
    leaves value empty: a failure is a value at or below gamma, not a status.

    [bold]Example[/]: bams-cli ingest-results -w study results-0001.parquet
    """
    if abandon_failed:
        summary = abandon_runs.ingest_results_abandoning_failed(
            workspace, results, replace=replace, allow_unselected=allow_unselected, wait=wait
        )
    else:
        summary = pipeline.ingest_results(
            workspace, results, replace=replace, allow_unselected=allow_unselected, wait=wait
        )
    if json_out:
        _json("ingest-results", summary)
        return
    if "message" in summary:
        console.note(summary["message"])
    else:
        console.ingest_summary(summary)
    not_run = summary["not_run"]
    gone = summary.get("abandoned")
    if gone is not None:
        console.note(
            f"{gone['abandoned']} failed requests recorded as abandoned"
            + (f" ({gone['already_abandoned']} were already)" if gone["already_abandoned"] else "")
        )
    elif not_run["count"]:
        first = not_run["first"][0]
        console.note(
            f"{console.plural(not_run['count'], 'row')} not run (status {first['status']!r} ...): "
            "not ingested, their requests stay pending"
        )
    pend = summary["pending"]
    if pend["count"]:
        rows = [
            [
                r["segment_id"],
                r["fidelity"],
                f"batch {r['batch']}" if r["batch"] else f"plan {r.get('plan')}",
            ]
            for r in pend["first"]
        ]
        console.rows_table(
            f"still pending: {pend['count']}",
            ["segment_id", "fidelity", "asked by"],
            rows,
            total=pend["count"],
        )
        console.pending_lists(summary.get("pending_lists") or [])
    # What is still pending is part of the summary (stdout), whether a table or none.
    elif gone is not None and gone["abandoned"] + gone["already_abandoned"]:
        console.out.print(
            "nothing pending: every selected segment has a result or is abandoned", markup=False
        )
    else:
        console.out.print("nothing pending: every selected segment has a result", markup=False)


@command()
def simulate(
    handoff: Annotated[
        Path,
        typer.Argument(
            metavar="HANDOFF", help="A hand-off list (Parquet or CSV): segment_id, fidelity."
        ),
    ],
    truth: Annotated[
        Path, typer.Option("--truth", help="Ground truth: segment_id, value_0, value_1, ...")
    ],
    output: Annotated[
        Path, typer.Option("--output", "-o", help="Results file to write (.parquet or .csv).")
    ],
    json_out: Json = False,
) -> None:
    """[yellow]Sample data and demos only:[/] answer a hand-off list from ground truth.

    Stands in for the simulation team so the loop can run end to end on sample data.

    [bold]Example[/]: bams-cli simulate study/batches/batch-0001.parquet
    --truth sample_data/toy2d/truth.parquet -o results-0001.parquet
    """
    summary = pipeline.simulate(handoff, truth, output)
    _show(summary, json_out, console.simulate_summary, "simulate")


@command(max_memory=True)
def fit(
    workspace: Workspace = Path(defaults.WORKSPACE),
    fixed_hyperparameters: Annotated[
        Path | None,
        typer.Option(
            "--fixed-hyperparameters",
            help="JSON of hyperparameters (e.g. a saved model.json): skip training, only condition.",
        ),
    ] = None,
    restarts: Annotated[
        int, typer.Option("--restarts", help="Seeded L-BFGS-B restarts of the MAP fit.")
    ] = defaults.RESTARTS,
    chunk_size: Annotated[
        int, typer.Option("--chunk-size", help="Pool rows scored per chunk.")
    ] = defaults.CHUNK_SIZE,
    transform: Annotated[
        Transform,
        typer.Option(
            "--transform",
            help="auto: model the metric or an asinh compression of it far from gamma, "
            "whichever the data support best; none: the metric itself.",
        ),
    ] = defaults.TRANSFORM,
    force: Annotated[
        bool,
        typer.Option("--force", help="Fit again although the model is up to date."),
    ] = False,
    wait: Wait = False,
    json_out: Json = False,
) -> None:
    """Fit the multifidelity GP and score every segment's failure probability.

    When the model was already fitted the same way on the current observation log, fit
    says so and changes nothing (--force fits again).

    [bold]Example[/]: bams-cli fit -w study
    """
    with console.progress(not json_out, "fit") as bar:
        summary = pipeline.fit(
            workspace,
            fixed_hyperparameters=fixed_hyperparameters,
            restarts=restarts,
            chunk_size=chunk_size,
            transform=transform.value,
            force=force,
            wait=wait,
            progress=bar,
        )
    if json_out:
        _json("fit", summary)
        return
    if summary.get("up_to_date"):
        console.out.print(summary["message"], markup=False, highlight=False)
        for text in summary.get("settings_warnings") or []:
            console.warning(str(text))
        return
    console.fit_summary(summary)


@command(max_memory=True)
def select(
    workspace: Workspace = Path(defaults.WORKSPACE),
    strategy: Annotated[
        Strategy,
        typer.Option(
            "--strategy",
            help="bams; bas (level 0 only); random (the first batch); the paper's baselines "
            "mc-gp, mcm-gp, ds, ds-gp, ce.",
        ),
    ] = defaults.STRATEGY,
    budget: Annotated[
        float,
        typer.Option(
            "--budget",
            "-m",
            envvar="BAMS_BUDGET",
            help="Batch budget m in cost units (a level-0 run costs 1).",
        ),
    ] = defaults.BUDGET,
    clusters: Annotated[
        int,
        typer.Option(
            "--clusters", "-S", envvar="BAMS_CLUSTERS", help="Clusters S (1: no clustering)."
        ),
    ] = defaults.CLUSTERS,
    overbudget: Annotated[
        float,
        typer.Option("--overbudget", help="eta >= 1: each cluster plans ceil(eta m N_s / N)."),
    ] = defaults.OVERBUDGET,
    pooling: Annotated[
        Pooling,
        typer.Option(
            "--pooling", help="global: compare (N_s/N) dJ/c across clusters; raw: the paper's dJ."
        ),
    ] = defaults.POOLING,
    greedy: Annotated[
        Greedy,
        typer.Option(
            "--greedy",
            envvar="BAMS_GREEDY",
            help="bams/bas: exact (every segment and candidate), approximate (bounded "
            "clusters, screened candidates) or auto: exact up to "
            f"{defaults.SELECT_EXACT_MAX_POOL:,} segments.",
        ),
    ] = defaults.GREEDY,
    mixed_fidelity: Annotated[
        bool, typer.Option("--mixed-fidelity", help="random: spread the picks over every level.")
    ] = False,
    level0_share: Annotated[
        float,
        typer.Option("--level0-share", help="random/mcm-gp: share of the budget spent at level 0."),
    ] = defaults.LEVEL0_SHARE,
    confirm_share: Annotated[
        float,
        typer.Option(
            "--confirm-share",
            help="bams: share of the budget for level-0 runs confirming cheap-level failures "
            "(then the likeliest unconfirmed ones); 0 turns it off.",
        ),
    ] = defaults.CONFIRM_SHARE,
    difficulty_column: Annotated[
        str,
        typer.Option(
            "--difficulty-column",
            help="ds/ds-gp: per-segment difficulty (higher = likelier to fail).",
        ),
    ] = defaults.DIFFICULTY_COLUMN,
    allow_pending: Annotated[
        bool,
        typer.Option("--allow-pending", help="Select although an earlier batch awaits results."),
    ] = False,
    include_observed: Annotated[
        bool,
        typer.Option(
            "--include-observed",
            help="Let segments already observed at level 0 (and, for bams and bas, at a cheap "
            "level) be picked again.",
        ),
    ] = False,
    workers: Workers = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            "--scheduler",
            envvar="BAMS_SCHEDULER",
            help="dask.distributed scheduler address to run clusters on.",
        ),
    ] = None,
    retry_abandoned: Annotated[
        bool,
        typer.Option(
            "--retry-abandoned",
            help="Let pairs recorded as abandoned (bams-cli abandon) be picked again.",
        ),
    ] = False,
    handoff_internal: HandoffInternal = False,
    batch: Annotated[
        int | None,
        typer.Option(
            "--batch",
            help="The batch number this call makes, a stable Make target: a no-op when it "
            "exists with the same options, an error when it is not the next one.",
        ),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            "--out",
            help="Also write the batch's CSV hand-off here, a stable Make target; "
            "a --batch re-run rewrites it when missing.",
        ),
    ] = None,
    wait: Wait = False,
    json_out: Json = False,
) -> None:
    """Pick the next batch of segments to simulate, at which fidelity, and write the hand-off list.

    The first batch of a study needs no model: use --strategy random --mixed-fidelity
    (random runs at every level, level-0 and cheap runs of the same segments among them).

    [bold]Example[/]: bams-cli select -w study --budget 5 --clusters 6
    """
    with console.progress(not json_out, "select") as bar:
        summary = pipeline.select(
            workspace,
            strategy=strategy.value,
            budget=budget,
            clusters=clusters,
            overbudget=overbudget,
            pooling=pooling.value,
            greedy=greedy.value,
            mixed_fidelity=mixed_fidelity,
            level0_share=level0_share,
            confirm_share=confirm_share,
            difficulty_column=difficulty_column,
            allow_pending=allow_pending,
            include_observed=include_observed,
            workers=workers,
            scheduler=scheduler,
            handoff_internal=handoff_internal,
            batch=batch,
            retry_abandoned=retry_abandoned,
            out=out,
            wait=wait,
            progress=bar,
        )
    fewer = (summary.get("selection_plan") or {}).get("workers_reason")
    if fewer:
        console.warning(fewer)
    _show(summary, json_out, console.select_summary, "select")


#: ``estimate``'s human summary names the interval's kind as ``--interval`` does, and what
#: it allows for.
INTERVAL_NAMES = {
    "gamma": (
        "gamma interval",
        "allowing for one failure the sample may have missed, of the weight the checked "
        "model predicts",
    ),
    "fay-feuer": (
        "fay-feuer interval",
        "Fay and Feuer's, allowing for one missed failure of the largest weight any segment "
        "could carry: it keeps its coverage however wrong the model (wider)",
    ),
}


@command()
def estimate(
    workspace: Workspace = Path(defaults.WORKSPACE),
    plan: Annotated[
        bool,
        typer.Option(
            "--plan", help="Phase 1: draw the importance sample and write its hand-off list."
        ),
    ] = False,
    samples: Annotated[
        float | None,
        typer.Option(
            "--samples",
            "-K",
            help="Simulation budget K \\[default: 5 x the GP's p x N, at least 100].",
        ),
    ] = None,
    weighting: Annotated[
        Weighting,
        typer.Option(
            "--weighting",
            help="With --plan: auto (the design with the smallest variance the checked model "
            "predicts: uniform, calibrated or p^alpha), uniform, or p-alpha (--alpha, --defensive).",
        ),
    ] = defaults.WEIGHTING,
    stages: Annotated[
        int,
        typer.Option(
            "--stages",
            help="With --plan, for a new estimate: how many stages K is spent in; each stage's "
            "results check the model before the next is drawn.",
        ),
    ] = defaults.STAGES,
    stage1_share: Annotated[
        float,
        typer.Option("--stage1-share", help="With --plan: share of K that stage 1 spends."),
    ] = defaults.STAGE1_SHARE,
    new_series: Annotated[
        bool,
        typer.Option(
            "--new-series",
            help="With --plan: start a new estimate although the last one has stages to go.",
        ),
    ] = False,
    alpha: Annotated[
        float, typer.Option("--alpha", help="The p^alpha design's exponent.")
    ] = defaults.ALPHA,
    defensive: Annotated[
        float,
        typer.Option("--defensive", help="Uniform share eps mixed into the sampling distribution."),
    ] = defaults.DEFENSIVE,
    design: Annotated[
        Design,
        typer.Option(
            "--design",
            help="With --plan: poisson (Horvitz-Thompson), fixed (systematic), or "
            "with-replacement (the paper's).",
        ),
    ] = defaults.DESIGN,
    seed: Annotated[
        int | None,
        typer.Option(
            "--seed",
            help="With --plan: draw a fresh plan from this seed (recorded in the plan) "
            "\\[default: the study seed and the plan number, so re-runs reproduce].",
        ),
    ] = None,
    screen: Annotated[
        str | None,
        typer.Option(
            "--screen",
            metavar="SHARE|auto|off",
            help="With --plan: spend SHARE of K on cheap-level runs of a sample first; "
            "after their results and a refit, the next --plan confirms within it at level "
            "0, its lowest cheap results for certain. auto: 0.3 wherever the study has a "
            "cheap level, else the staged plan; off: never \\[default: auto].",
        ),
    ] = None,
    plan_number: Annotated[
        int | None,
        typer.Option(
            "--plan-number", help="Phase 2: which plan to compute \\[default: the latest]."
        ),
    ] = None,
    confidence: Annotated[
        float,
        typer.Option(
            "--confidence",
            envvar="BAMS_CONFIDENCE",
            help="Two-sided confidence level of the interval.",
        ),
    ] = defaults.CONFIDENCE,
    interval: Annotated[
        Interval,
        typer.Option(
            "--interval",
            help="gamma: allows for one unseen failure of the weight the checked model "
            "predicts; fay-feuer: of the largest weight any segment could carry, Fay and "
            "Feuer's interval, which keeps its coverage however wrong the model (wider).",
        ),
    ] = defaults.INTERVAL,
    exact_variance: Annotated[
        bool,
        typer.Option(
            "--exact-variance",
            help="Also compute the GP estimate's exact variance (pools <= 50,000).",
        ),
    ] = False,
    handoff_internal: HandoffInternal = False,
    allow_pending: Annotated[
        bool,
        typer.Option(
            "--allow-pending",
            help="With --plan: draw a plan although an earlier plan or batch awaits results.",
        ),
    ] = False,
    failed_as: Annotated[
        FailedAs | None,
        typer.Option(
            "--failed-as",
            help="bounds: when planned segments were abandoned (bams-cli abandon), report the "
            "worst-case interval, them all passing to them all failing \\[default: refuse].",
        ),
    ] = None,
    wait: Wait = False,
    json_out: Json = False,
) -> None:
    """Estimate the failure rate with an unbiased importance sample, in stages.

    --plan draws a stage's sample and writes its hand-off list; once its results are
    ingested, estimate (no --plan) computes the estimate for every configured gamma.

    Unscreened (--screen off, or a study with one level), K is spent in stages
    (--stages, default 3): after each stage's results,
    refit and run --plan again for the next, whose design rests on the model as checked
    against the outcomes so far. The stages' weights are fixed at stage 1, so the combined
    estimate stays unbiased.

    Screened (--screen SHARE, or the default auto wherever the study has a cheap level),
    the first --plan writes cheap-level runs of a sample as a batch
    (batches/batch-NNNN.csv); after their results and a refit, --plan confirms within it
    at level 0 (estimates/plan-NNNN-handoff.csv), the screen's lowest cheap results with
    certainty. Each --plan says which it drew.

    [bold]Example[/]: bams-cli estimate -w study --plan --samples 200

    then simulate the hand-off list, ingest the results, `bams-cli fit -w study`,
    `bams-cli estimate -w study --plan` (the next stage), and so on until `bams-cli status -w
    study` names the estimate itself: bams-cli estimate -w study
    """
    if seed is not None and not plan:
        raise OptionValueError(
            f"--seed {seed} seeds the sample's draw: pass it with --plan (computing the "
            "estimate from a drawn plan involves no randomness)"
        )
    if screen is not None and not plan:
        raise OptionValueError(f"--screen {screen} draws a screen: pass it with --plan")
    if plan:
        summary = pipeline.estimate_plan(
            workspace,
            samples=samples,
            alpha=alpha,
            defensive=defensive,
            design=design.value,
            weighting=weighting.value,
            stages=stages,
            stage1_share=stage1_share,
            new_series=new_series,
            seed=seed,
            screen=defaults.SCREEN if screen is None else _screen_share(screen),
            handoff_internal=handoff_internal,
            allow_pending=allow_pending,
            wait=wait,
        )
        if "screen_file" in summary:
            _show(summary, json_out, console.screen_summary, "estimate-screen")
        else:
            _show(summary, json_out, console.plan_summary, "estimate-plan")
        return
    with console.progress(not json_out, "estimate") as bar:
        summary = pipeline.estimate_compute(
            workspace,
            plan_number=plan_number,
            confidence=confidence,
            interval=interval.value,
            exact_variance=exact_variance,
            failed_as=None if failed_as is None else failed_as.value,
            wait=wait,
            progress=bar,
        )
    if json_out:
        _json("estimate", summary)
        return
    rows = [
        [
            e["gamma"],
            e["p_hat"]
            if "p_hat_low" not in e
            else f"{e['p_hat_low']:.4g} .. {e['p_hat_high']:.4g}",
            "n/a" if e["se"] is None else e["se"],
            f"[{e['ci_low']:.4g}, {e['ci_high']:.4g}]",
            "n/a" if e["rel_var"] is None else e["rel_var"],
            e["distinct_failures_found"],
        ]
        for e in summary["estimates"]
    ]
    # The interval's kind by name: "gamma" beside a gamma column would read as the threshold.
    kind = summary.get("interval", interval.value)
    level = f"{100 * summary['estimates'][0]['confidence']:g}%" if summary["estimates"] else ""
    named = INTERVAL_NAMES.get(kind, (f"{kind} interval", ""))
    console.rows_table(
        f"failure rate (plan {summary['plan']}, {summary['design']} design; {level} {named[0]})",
        ["gamma", "p_hat", "se", "interval", "rel. variance", "failures found"],
        rows,
    )
    console.out.print(
        f"interval: {level} {named[0]}, {named[1]}", markup=False, highlight=False, soft_wrap=True
    )
    for note in [summary["staging"]["note"], *summary["notes"]]:
        if note:
            console.note(note)
    for e in summary["estimates"]:  # what se rests on, why a number is n/a (as the report)
        for key, what in (("variance_note", "se"), ("rel_var_note", "relative variance")):
            if e.get(key):
                console.note(f"gamma {e['gamma']:g}, {what}: {e[key]}")
    gp = [
        [g["gamma"], g["gp_p_hat"], g["gp_var_bound"], g.get("gp_var_exact", "")]
        for g in summary["gp"]
    ]
    console.rows_table("the GP's own estimate", ["gamma", "mean p_n", "Var bound", "Var exact"], gp)
    if summary["gp_model"] != "current":
        console.note(
            "the GP's estimate is the model's as of the plan; `bams-cli fit` adds its results"
        )
    # Where it went, and where the estimate it replaced went: nothing is overwritten.
    written = f"estimate written to {summary['estimate_file']}"
    earlier = summary.get("earlier_estimate")
    if earlier:
        was = ""
        if earlier["confidence"] is not None:  # None: a damaged file, kept as it was
            was_kind = INTERVAL_NAMES.get(earlier["interval"], (f"{earlier['interval']} interval",))
            was = f" ({100 * earlier['confidence']:g}% {was_kind[0]})"
        written += f"; plan {summary['plan']}'s earlier estimate{was} is kept as {earlier['file']}"
    console.out.print(written, markup=False, highlight=False, soft_wrap=True)


@command()
def abandon(
    workspace: Workspace = Path(defaults.WORKSPACE),
    batch: Annotated[
        int | None, typer.Option("--batch", help="Abandon batch N's pending requests.")
    ] = None,
    plan: Annotated[
        int | None, typer.Option("--plan", help="Abandon estimate plan N's pending requests.")
    ] = None,
    segments: Annotated[
        Path | None,
        typer.Option(
            "--segments",
            help="CSV or Parquet naming the requests: request_id, or segment_id (+ fidelity); "
            "e.g. the hand-off list filtered to the lost runs.",
        ),
    ] = None,
    fidelity: Annotated[
        list[str] | None,
        typer.Option(
            "--fidelity", help="Only these levels (number or name; repeat or comma-separate)."
        ),
    ] = None,
    reason: Annotated[
        str | None,
        typer.Option("--reason", help="Why they will never come back (kept in the log)."),
    ] = None,
    wait: Wait = False,
    json_out: Json = False,
) -> None:
    """Record requests that will never come back (a simulation that fails for good).

    Appends them to abandoned.parquet (append-only; a result that arrives later is still
    ingested and counts). They stop being pending, so select, status and Make go on;
    select never picks them again (unless --retry-abandoned); estimate refuses a plan with
    abandoned segments unless --failed-as bounds. A repeat changes nothing.

    [bold]Example[/]: bams-cli abandon -w study --batch 3 --fidelity 0 --reason "simulator crash"
    """
    summary = abandon_runs.abandon(
        workspace,
        batch=batch,
        plan=plan,
        segments=segments,
        fidelity=fidelity,
        reason=reason,
        wait=wait,
    )
    if json_out:
        _json("abandon", summary)
        return
    if summary["unchanged"]:
        console.note(summary["message"])
    else:
        rows = [
            [r["request_id"], r["segment_id"], r["fidelity"], r["batch"] or "", r["plan"] or ""]
            for r in summary["first"]
        ]
        console.rows_table(
            f"abandoned: {console.plural(summary['abandoned'], 'request')} (log: {summary['log']})",
            ["request_id", "segment_id", "fidelity", "batch", "plan"],
            rows,
            total=summary["abandoned"],
        )
    pend = summary["pending"]["count"]
    console.note(f"still pending: {pend}" if pend else "nothing pending")
    console.pending_lists(summary.get("pending_lists") or [])


@command(max_memory=True)
def loop(
    simulator: Annotated[
        str,
        typer.Option(
            "--simulator",
            help="Shell command answering a hand-off list: {handoff} is the list (CSV) to read, "
            "{results} the results file (CSV) to write.",
        ),
    ],
    batches: Annotated[
        int,
        typer.Option(
            "--batches",
            help="Discovery batches the study should have (the first random; an estimate's "
            "screen batch does not count).",
        ),
    ],
    workspace: Workspace = Path(defaults.WORKSPACE),
    budget: Annotated[
        float,
        typer.Option(
            "--budget", "-m", envvar="BAMS_BUDGET", help="Budget of each BAMS batch (cost units)."
        ),
    ] = defaults.BUDGET,
    first_budget: Annotated[
        float | None,
        typer.Option(
            "--first-budget", help="Budget of the random first batch \\[default: --budget]."
        ),
    ] = None,
    then_estimate: Annotated[
        bool,
        typer.Option(
            "--then-estimate", help="Then plan the rate estimate, simulate it and compute it."
        ),
    ] = False,
    samples: Annotated[
        float | None,
        typer.Option(
            "--samples",
            "-K",
            help="With --then-estimate: the estimate's budget K \\[default: 5 x the GP's p x N].",
        ),
    ] = None,
    screen: Annotated[
        str | None,
        typer.Option(
            "--screen",
            metavar="SHARE|auto|off",
            help="With --then-estimate: a screened estimate, this share of K (e.g. 0.3) on "
            "cheap-level runs first, auto or off (see estimate --screen) \\[default: auto].",
        ),
    ] = None,
    results_dir: Annotated[
        Path | None,
        typer.Option(
            "--results-dir",
            help="Where the simulator's results files go, a folder of their own (not the "
            "workspace's) \\[default: WS/loop-results].",
        ),
    ] = None,
    abandon_failed: Annotated[
        bool,
        typer.Option(
            "--abandon-failed",
            help="Record results rows with a failed status as abandoned and go on (and "
            "estimate with --failed-as bounds).",
        ),
    ] = False,
    retries: Annotated[
        int,
        typer.Option(
            "--retries",
            help="Simulate again, up to N times, a list whose simulator run exited non-zero, "
            "whose results file ingest-results refused, or whose requests are still without "
            "a result (failed or missing rows); then stop (with --abandon-failed: abandon "
            "them). N counts tries over every loop run (the retried-* files kept).",
        ),
    ] = defaults.RETRIES,
    clusters: Annotated[
        int, typer.Option("--clusters", "-S", envvar="BAMS_CLUSTERS", help="select: clusters S.")
    ] = defaults.CLUSTERS,
    workers: Workers = None,
    wait: Wait = False,
    json_out: Json = False,
) -> None:
    """Run the discovery loop against your own simulator: fit, select, simulate, ingest.

    Reads the workspace before every step and takes the one it needs next, so a loop that
    was killed resumes where it stopped and a finished one does nothing. Each step is the
    command you would run by hand; the simulator's results land in --results-dir only when
    it exits 0.

    [bold]Example[/]: bams-cli loop -w study --batches 3 --budget 5 --then-estimate
    --simulator 'bams-cli simulate {handoff} --truth sample_data/toy2d/truth.parquet -o {results}'
    """
    with console.loop_progress(not json_out) as bar:
        summary = study_loop.loop(
            workspace,
            simulator=simulator,
            batches=batches,
            budget=budget,
            first_budget=first_budget,
            then_estimate=then_estimate,
            samples=samples,
            screen=_screen_share(screen),
            results_dir=results_dir,
            abandon_failed=abandon_failed,
            retries=retries,
            clusters=clusters,
            workers=workers,
            wait=wait,
            on_step=bar,
            on_warning=console.warning,
        )
    if json_out:
        _json("loop", summary)
        return
    if summary["unchanged"]:
        console.note(
            f"loop: nothing to do; {console.plural(summary['batches'], 'batch', 'batches')} "
            f"{'is' if summary['batches'] == 1 else 'are'} in"
        )
        if summary["estimate"]:
            console.estimate_lines(summary["estimate"])
        return
    console.loop_summary(summary)


@command(max_memory=True)
def report(
    workspace: Workspace = Path(defaults.WORKSPACE),
    truth: Annotated[
        Path | None,
        typer.Option(
            "--truth", help="Ground truth (segment_id, value_0), e.g. for sample data: adds recall."
        ),
    ] = None,
    diverse: Annotated[
        int, typer.Option("--diverse", help="How many diverse likely failures to list.")
    ] = defaults.DIVERSE,
    by: Annotated[
        str | None,
        typer.Option(
            "--by",
            metavar="COLUMN",
            help="Break the failures and runs down by this pass-through column of the pool "
            "(a scenario tag ...) \\[default: the pool's clusters, as select forms them].",
        ),
    ] = None,
    wait: Wait = False,
    json_out: Json = False,
) -> None:
    """Write the study report: report/report.html, summary.json and summary.md.

    Runs at any point of a study. A model older than the observation log, batches or
    estimate plans awaiting results open the report as banners.

    [bold]Example[/]: bams-cli report -w study   (sample data: add --truth sample_data/toy2d/truth.parquet)
    """
    summary = pipeline.report(workspace, truth=truth, n_diverse=diverse, by=by, wait=wait)
    _show(summary, json_out, console.report_summary, "report")


@command()
def status(
    workspace: Workspace = Path(defaults.WORKSPACE),
    json_out: Json = False,
) -> None:
    """Show where the study stands and the exact command to run next.

    Batches and estimate plans with the picks still awaiting results, whether the model
    was fitted on the current observation log, the latest estimate. Reads only: it takes
    no lock. Exit code 0, or 3 while picks await results (simulate the hand-off list and
    ingest it).

    [bold]Example[/]: bams-cli status -w study
    """
    summary = study_status(workspace)
    if json_out:
        _json("status", summary)
    else:
        console.study_status(summary)
    if summary["exit_code"]:
        raise typer.Exit(summary["exit_code"])


@command()
def schema(
    name: Annotated[
        SchemaName | None,
        typer.Argument(help="Which output \\[default: all, by name]."),
    ] = None,
    json_out: Annotated[
        bool,
        typer.Option("--json", help="Accepted as by every command; the output is JSON anyway."),
    ] = False,
) -> None:
    """Print the JSON Schema of a command's --json output, or of report/summary.json.

    Each output carries schema_version; it rises when a key changes meaning or goes away
    (new keys may appear without it).

    [bold]Example[/]: bams-cli schema select
    """
    if name is None:
        console.print_json(schemas_json.all_schemas())
        return
    console.print_json(schemas_json.schema(name.value))


@command()
def benchmark(
    protocol: Annotated[
        Protocol,
        typer.Option(
            "--protocol",
            help="toy2d: the paper's synthetic protocol; av_like: its AV protocol; weak_cheap, "
            "digits, rare_regions, gap_sim: the suite's problems; suite: all six, with a "
            "suite.md table over them.",
        ),
    ] = defaults.PROTOCOL,
    seeds: Annotated[
        int, typer.Option("--seeds", help="Independent repetitions (the paper: 10).")
    ] = defaults.SEEDS,
    quick: Annotated[
        bool, typer.Option("--quick", help="At most 3 seeds: the CI smoke run.")
    ] = False,
    out: Annotated[
        Path, typer.Option("--out", "-o", help="Folder for results.json, tables and plots.")
    ] = Path(defaults.BENCHMARK_OUT),
    strategies: Annotated[
        str | None,
        typer.Option(
            "--strategies",
            help="Comma-separated subset, e.g. bams,bas,mc \\[default: all] (suite: bams,mcm-gp,mc).",
        ),
    ] = None,
    level0_share: Annotated[
        float,
        typer.Option(
            "--level0-share",
            help="Share of a mixed-fidelity random batch's budget spent at level 0.",
        ),
    ] = defaults.LEVEL0_SHARE,
    n: Annotated[
        int | None, typer.Option("--n", help="Pool size \\[default: the committed sample data].")
    ] = None,
    clusters: Annotated[
        int, typer.Option("--clusters", envvar="BAMS_CLUSTERS", help="BAMS/BAS clusters S.")
    ] = defaults.CLUSTERS,
    greedy: Annotated[
        Greedy,
        typer.Option(
            "--greedy",
            envvar="BAMS_GREEDY",
            help="BAMS/BAS: the plan select runs (select --greedy).",
        ),
    ] = defaults.GREEDY,
    workers: Annotated[
        int, typer.Option("--workers", envvar="BAMS_WORKERS", help="Runs in parallel processes.")
    ] = defaults.BENCHMARK_WORKERS,
    save_arrays: Annotated[
        bool,
        typer.Option(
            "--save-arrays",
            help="Also write runs.npz: per run the final p_n and known stratum, and the truth.",
        ),
    ] = False,
    json_out: Json = False,
) -> None:
    """Reproduce the paper's experiments through the same code a user runs.

    For every strategy and seed: a random first batch, then two batches chosen by the
    strategy, each going through select, simulate, ingest-results and fit in a scratch
    workspace; then the rate estimate's recall and exact relative variance, for the default
    design and the paper's with-replacement sampler. Writes results.json, tables and
    retention-recall plots to --out.

    The suite (--protocol suite) runs every problem into its own subfolder of --out and
    writes suite.md over them: recall, RV, the fitted against the true discrepancy sd,
    level-0 picks per batch and the GP's own rate estimate.

    [bold]Example[/]: bams-cli benchmark --protocol toy2d --quick --out /tmp/repro

    [bold]Example[/]: bams-cli benchmark --protocol suite --seeds 10 --out docs/reproduction/suite
    """
    from bams_cli.benchmark import PROTOCOLS, run_benchmark, run_suite, suite_rows

    if workers < 1:
        raise OptionValueError(f"--workers {workers}: must be >= 1")
    if protocol != Protocol.SUITE and protocol.value not in PROTOCOLS:  # kept in step by a test
        raise OptionValueError(f"--protocol {protocol.value}: not a protocol of this version")
    options: dict[str, Any] = {
        "seeds": seeds,
        "quick": quick,
        "out_dir": out,
        "strategies": strategies.split(",") if strategies else None,
        "level0_share": level0_share,
        "workers": workers,
        "n": n,
        "clusters": clusters,
        "greedy": greedy.value,
        "command": shlex.join(["bams-cli", *sys.argv[1:]]),
        "save_arrays": save_arrays,
    }
    if protocol == "suite":
        with console.progress(not json_out, "benchmark") as bar:
            results = run_suite(progress=bar, **options)
        if json_out:
            console.print_json({p: suite_rows(r) for p, r in results.items()})
            return
        console.out.print((out / "suite.md").read_text())
        console.note(f"results: {out / 'suite.json'} and one folder per problem")
        return
    with console.progress(not json_out, "benchmark") as bar:
        result = run_benchmark(protocol.value, progress=bar, **options)
    if json_out:
        console.print_json(result)
        return
    tables = out / "tables.md"
    if tables.exists():
        console.out.print(tables.read_text())
    console.note(f"results: {out / 'results.json'}")


def main() -> None:
    """Console-script entry point.

    Under --json a usage error (an unknown option, an invalid choice: exit code 2) is a
    JSON line on stderr like every other error; click reports it before any command runs.
    """
    if "--json" not in sys.argv[1:]:
        app()
        return
    try:
        code = app(standalone_mode=False)
    except UsageError as exc:
        console.set_mode(quiet=False, json_out=True)
        console.error(_plain(exc).format_message(), exc.exit_code)
        code = exc.exit_code
    except typer.Abort:
        console.set_mode(quiet=False, json_out=True)
        console.error("aborted", 1)
        code = 1
    sys.exit(code if isinstance(code, int) else 0)
