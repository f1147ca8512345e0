"""Everything the user sees: rich tables, progress bars, one-line errors."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table
from rich.text import Text

out = Console()
err = Console(stderr=True, highlight=False, soft_wrap=True)


def error(message: str) -> None:
    """One line on stderr: what failed, expected vs got, and the fix."""
    # The message is data (it quotes file contents), never markup: "[[levels]]" or a
    # segment id like "[/a]" must print as written.
    err.print(Text.assemble(("error:", "bold red"), " ", message))


def note(message: str) -> None:
    err.print(message, markup=False)


def print_json(summary: Mapping[str, Any]) -> None:
    # allow_nan=False: a bare NaN/Infinity is not JSON; an undefined number must be null.
    sys.stdout.write(json.dumps(summary, indent=2, default=str, allow_nan=False) + "\n")


def kv_table(title: str, rows: Mapping[str, Any]) -> None:
    table = Table(title=title, show_header=False, title_justify="left")
    table.add_column("key", style="bold")
    table.add_column("value")
    for key, value in rows.items():
        if isinstance(value, float):
            value = f"{value:.6g}"
        elif isinstance(value, list | dict):
            value = json.dumps(value, default=str)
        table.add_row(Text(key), Text(str(value)))
    out.print(table)


def rows_table(title: str, columns: list[str], rows: list[list[Any]]) -> None:
    table = Table(title=title, title_justify="left")
    for col in columns:
        table.add_column(
            col, justify="right" if col not in {"segment_id", "name", "level"} else "left"
        )
    for row in rows:
        table.add_row(*[Text(f"{v:.6g}" if isinstance(v, float) else str(v)) for v in row])
    out.print(table)


def hyperparameter_table(hp: Mapping[str, Any], n_obs: list[int]) -> None:
    """Hyperparameters per level in natural units: what the model believes about f."""
    table = Table(title="model hyperparameters", title_justify="left")
    for col in ("level", "observations", "output scale", "lengthscales", "noise sd"):
        table.add_column(col, justify="left" if col in {"level", "lengthscales"} else "right")
    fmt = lambda xs: ", ".join(f"{x:.3g}" for x in xs)  # noqa: E731
    noise = hp["noise"]
    table.add_row(
        "0 (theta0)",
        str(n_obs[0]),
        f"{hp['outputscale0'] ** 0.5:.4g}",
        fmt(hp["lengthscales0"]),
        f"{noise[0] ** 0.5:.3g}",
    )
    offsets = hp.get("offsets") or [0.0] * len(hp["outputscales"])
    for lv, (scale, ells) in enumerate(zip(hp["outputscales"], hp["lengthscales"], strict=True), 1):
        table.add_row(
            f"{lv} (discrepancy, offset {offsets[lv - 1]:+.3g})",
            str(n_obs[lv]),
            f"{scale**0.5:.4g}",
            fmt(ells),
            f"{noise[lv] ** 0.5:.3g}",
        )
    table.caption = f"constant mean {hp['mean']:.4g}; scales and noise as standard deviations"
    out.print(table)


def model_checks(checks: Mapping[str, Any], transform: Mapping[str, Any] | None = None) -> None:
    """One line per self-check of a fitted model (``core.gp.checks``), and its transform."""
    if transform and transform.get("kind") == "asinh":
        out.print(
            f"model: g(y) = {transform['centre']:.4g} + s asinh((y - {transform['centre']:.4g})"
            f" / s), s = {transform['scale']:.4g} (the metric compressed far from gamma; "
            "scales above are in g's units)"
        )
    loo = checks["loo_level0"]
    if loo["n"]:
        out.print(
            f"check: leave-one-out at {loo['n']} level-0 runs, mean z^2 {loo['mean_z2']:.2f} "
            "(1 if calibrated)"
        )
    for pair in checks["pairs"]:
        if pair["n_pairs"] >= 2:
            out.print(
                f"check: {pair['n_pairs']} segments run at levels 0 and {pair['level']}: "
                f"sd(y{pair['level']} - y0) {pair['sd_observed']:.3g}, model "
                f"{pair['sd_fitted']:.3g}"
            )


def study_status(s: Mapping[str, Any]) -> None:
    """``bams-cli status``: batches, plans, model, latest estimate, then the next command."""
    pool = "no pool yet" if s["pool_size"] is None else f"{s['pool_size']} segments"
    out.print(
        f"study {s['workspace']}: {pool}, levels {', '.join(s['levels'])}, "
        f"gammas {', '.join(f'{g:g}' for g in s['gammas'])}, {s['observations']} results",
        markup=False,
        highlight=False,
        soft_wrap=True,
    )
    if s["batches"]:
        rows_table(
            "batches",
            ["batch", "strategy", "picks", "cost", "pending", "abandoned", "hand-off"],
            [
                [
                    b["batch"],
                    b["strategy"],
                    b["picks"],
                    b["cost"],
                    b["pending"],
                    b.get("abandoned", 0),
                    b["handoff"],
                ]
                for b in s["batches"]
            ],
        )
    if s["plans"]:
        rows_table(
            "estimate plans",
            ["plan", "sampled", "pending", "abandoned", "hand-off", "estimate"],
            [
                [
                    p["plan"],
                    p["sampled"],
                    p["pending"],
                    p.get("abandoned", 0),
                    p["handoff"],
                    p["estimate"] or "-",
                ]
                for p in s["plans"]
            ],
        )
    m = s["model"]
    if m is None:
        text = "none yet"
    elif m["fresh"]:
        text = f"up to date (fitted on {m['fitted_on']} results at {m['fitted_at']})"
    else:
        text = f"stale: {m['reason']}"
    out.print(f"model: {text}", markup=False, highlight=False, soft_wrap=True)
    e = s["latest_estimate"]
    if e is not None:
        for row in e["estimates"]:
            out.print(
                f"estimate (plan {e['plan']}): gamma {row['gamma']:g}: p_hat {row['p_hat']:.4g}, "
                f"{round(100 * row['confidence'])}% interval [{row['ci_low']:.4g}, "
                f"{row['ci_high']:.4g}]",
                markup=False,
                highlight=False,
                soft_wrap=True,
            )
    if s["commit_in_progress"]:
        note(
            "note: a command's commit is in progress or was interrupted; the next command completes it"
        )
    out.print(Text.assemble(("next: ", "bold"), s["next"]["text"]), soft_wrap=True)


@contextmanager
def progress(enabled: bool = True) -> Iterator[Callable[[str, int, int], None] | None]:
    """A ``progress(phase, done, total)`` callback drawing one rich bar per phase."""
    if not enabled or not err.is_terminal:
        yield None
        return
    bars = Progress(
        TextColumn("{task.description:<14}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=err,
        transient=True,
    )
    tasks: dict[str, Any] = {}

    def update(phase: str, done: int, total: int) -> None:
        if phase not in tasks:
            tasks[phase] = bars.add_task(phase, total=total)
        bars.update(tasks[phase], completed=done, total=total)

    with bars:
        yield update


@contextmanager
def loop_progress(enabled: bool = True) -> Iterator[Callable[[str, int, int], None]]:
    """``bams-cli loop``: one line per step on stderr, and a bar of lists done on a terminal."""
    if not enabled:
        yield lambda *_: None
        return
    bars = None
    if err.is_terminal:
        bars = Progress(
            TextColumn("{task.description:<30}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=err,
            transient=True,
        )
    task = bars.add_task("loop", total=1) if bars is not None else None

    def update(step: str, done: int, total: int) -> None:
        if bars is not None and task is not None:
            bars.update(task, description=step, completed=done, total=total)
        if step != "done":
            err.print(f"loop [{done}/{total}]: {step}", markup=False, highlight=False)

    if bars is None:
        yield update
        return
    with bars:
        yield update
